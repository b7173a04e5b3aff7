"""A cluster that cr_nlp starts listens on this machine only (``start_local_cluster``'s
``host``, default 127.0.0.1), and says so when asked to listen elsewhere.

The listening sockets are read from ``/proc`` (``/proc/<pid>/fd`` socket inodes,
``/proc/<pid>/net/tcp`` and ``tcp6``) for this process and its descendants, so the test
needs Linux but no extra package."""

from __future__ import annotations

import ipaddress
import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

from cr_nlp.batch import (
    ExposedClusterWarning,
    close_cluster,
    exposure_warning,
    start_local_cluster,
)

LISTEN = "0A"
"""The TCP state LISTEN in ``/proc/net/tcp``."""

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="reads the listening sockets from /proc"
)


def _descendants(pid: int) -> list[int]:
    """``pid`` and every process below it (from each process's parent id in /proc)."""
    parents: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:  # the process ended meanwhile
            continue
        parent = int(stat.rsplit(")", 1)[1].split()[1])  # after "pid (comm) state"
        parents.setdefault(parent, []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        current = todo.pop()
        found.append(current)
        todo.extend(parents.get(current, []))
    return found


def _socket_inodes(pid: int) -> set[str]:
    inodes = set()
    try:
        fds = list(Path(f"/proc/{pid}/fd").iterdir())
    except OSError:
        return inodes
    for fd in fds:
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:["):-1])
    return inodes


def _address(hex_address: str) -> str:
    """The address of a ``/proc/net/tcp[6]`` "HEX:PORT" field: 32-bit words in host
    (little-endian) byte order."""
    raw = bytes.fromhex(hex_address.split(":")[0])
    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
    return str(ipaddress.ip_address(words))


def listening_addresses(pid: int) -> list[tuple[int, str, int]]:
    """(pid, address, port) of every listening TCP socket of ``pid`` and its descendants."""
    found = []
    for process in _descendants(pid):
        inodes = _socket_inodes(process)
        for table in ("tcp", "tcp6"):
            try:
                lines = Path(f"/proc/{process}/net/{table}").read_text().splitlines()[1:]
            except OSError:
                continue
            for line in lines:
                fields = line.split()
                if fields[3] == LISTEN and fields[9] in inodes:
                    found.append((process, _address(fields[1]), int(fields[1].split(":")[1], 16)))
    return found


def test_proc_parsing_reads_a_socket_it_opened() -> None:
    """The helper finds a listening socket of this process, with its address."""
    import socket

    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        assert (os.getpid(), "127.0.0.1", port) in listening_addresses(os.getpid())


def test_a_local_cluster_listens_on_loopback_only() -> None:
    """Scheduler, dashboard, nannies and workers of ``start_local_cluster``: every listening
    socket of this process and its children is on 127.0.0.1 or ::1."""
    client = start_local_cluster(1, quiet=True)
    try:
        client.wait_for_workers(1, timeout=120)
        sockets = listening_addresses(os.getpid())
    finally:
        close_cluster(client)
    assert len({pid for pid, _, _ in sockets}) >= 2, sockets  # the scheduler and a worker
    exposed = [s for s in sockets if not ipaddress.ip_address(s[1]).is_loopback]
    assert not exposed, f"listening beyond this machine: {exposed}"


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "::1", "localhost"])
def test_loopback_hosts_need_no_warning(host: str) -> None:
    assert exposure_warning(host) is None


@pytest.mark.parametrize("host", ["0.0.0.0", "", "::", "192.168.1.7"])
def test_other_hosts_are_reachable_from_the_network(host: str) -> None:
    message = exposure_warning(host)
    assert message is not None and "reachable from the network" in message


def test_starting_on_a_public_host_warns(monkeypatch) -> None:
    """``start_local_cluster`` warns before it starts anything (the start itself is
    replaced here: no cluster on a public interface in a test)."""
    import distributed

    class Started(Exception):
        pass

    def refuse(*args, **kwargs):
        raise Started(kwargs.get("host"))

    monkeypatch.setattr(distributed, "LocalCluster", refuse)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(Started, match="0.0.0.0"):
            start_local_cluster(1, quiet=True, host="0.0.0.0")
    assert any(issubclass(w.category, ExposedClusterWarning) for w in caught)


# ================================================================ stopping cr-nlp batch

STOP_TARGETS = 60


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_stopped_batch_closes_its_cluster_and_resumes(tmp_path) -> None:
    """SIGTERM to ``cr-nlp batch`` (started with SIGINT ignored, one local worker): it
    exits with 143 and one line on how to resume, its worker processes are gone, the
    chunks written stay; ``--resume`` then solves only the others."""
    from cr_nlp.bench.ik import forward_kinematics
    from cr_nlp.model import load_robot

    from ..conftest import ROOT, random_q, sigint_ignored

    robot = load_robot("tdcr3")
    positions, wxyz = forward_kinematics(robot, random_q(robot, STOP_TARGETS, seed=5))
    targets = tmp_path / "targets.json"
    targets.write_text(json.dumps({"poses": [
        {"position": p.tolist(), "wxyz": w.tolist()} for p, w in zip(positions, wxyz, strict=True)
    ]}))
    out = tmp_path / "job"
    command = [sys.executable, "-m", "cr_nlp.cli", "batch", "ik", "--robot", "tdcr3",
               "--targets", str(targets), "--out", str(out), "--chunk", "1",
               "--workers", "1", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    with sigint_ignored():  # as a shell starts a background job
        proc = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while (not list(out.glob("chunk_*.npz")) and proc.poll() is None
               and time.monotonic() < deadline):
            time.sleep(0.005)
        workers = [pid for pid in _descendants(proc.pid) if pid != proc.pid]
        proc.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        _, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    seconds = time.monotonic() - t0
    assert proc.returncode == 128 + signal.SIGTERM, stderr[-3000:]
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("cr-nlp batch: stopped by SIGTERM;") and "--resume" in last, last
    assert f"of {STOP_TARGETS} chunks are written in {out}" in last, last
    assert workers, "no worker process was seen"
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in workers), "a worker outlived the stopped batch"
    written = {p.name: p.stat().st_mtime_ns for p in out.glob("chunk_*.npz")}
    assert 1 <= len(written) < STOP_TARGETS
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["runs"][-1].get("stopped") is True
    assert not (out / "results.json").exists()
    print(f"stopped {seconds:.1f} s after SIGTERM with {len(written)} chunks written")

    done = subprocess.run([*command, "--resume"], env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())["results"]
    assert len(results) == STOP_TARGETS
    after = {p.name: p.stat().st_mtime_ns for p in out.glob("chunk_*.npz")}
    assert {name: after[name] for name in written} == written  # not solved again
    runs = json.loads((out / "manifest.json").read_text())["runs"]
    assert len(runs[-1]["solved"]) == STOP_TARGETS - len(written)
