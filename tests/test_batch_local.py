"""A cluster that cr_nlp starts listens on this machine only (``start_local_cluster``'s
``host``, default 127.0.0.1), and says so when asked to listen elsewhere.

The listening sockets are read from ``/proc`` (``/proc/<pid>/fd`` socket inodes,
``/proc/<pid>/net/tcp`` and ``tcp6``) for this process and its descendants, so the test
needs Linux but no extra package."""

from __future__ import annotations

import ipaddress
import os
import sys
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
