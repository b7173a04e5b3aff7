"""Atomic writes (``cr_nlp._files``): a reader sees a file's old content or its whole new
content, never part of one; a writer that raises leaves the old file and no temporary one;
a writer killed at any moment leaves a complete file."""

from __future__ import annotations

import json
import os
import random
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cr_nlp._files import atomic_open, write_atomic
from cr_nlp.tasks._result import write_json, write_series_csv


def _names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# ================================================================ the helper


def test_a_successful_write_replaces_the_file(tmp_path: Path) -> None:
    path = tmp_path / "result.json"
    path.write_text("old\n")
    with atomic_open(path) as handle:
        handle.write("new\n")
        assert path.read_text() == "old\n"  # nothing visible before the block ends
    assert path.read_text() == "new\n"
    assert _names(tmp_path) == ["result.json"]


def test_an_exception_leaves_the_old_file_and_no_temporary_file(tmp_path: Path) -> None:
    path = tmp_path / "result.json"
    path.write_text("old\n")
    with pytest.raises(RuntimeError, match="half way"), atomic_open(path) as handle:
        handle.write("new, half")
        raise RuntimeError("half way")
    assert path.read_text() == "old\n"
    assert _names(tmp_path) == ["result.json"]
    with pytest.raises(RuntimeError), atomic_open(tmp_path / "absent.json") as handle:
        raise RuntimeError
    assert _names(tmp_path) == ["result.json"]  # a new file is not created either


def test_text_and_binary_modes(tmp_path: Path) -> None:
    text, binary = tmp_path / "rows.csv", tmp_path / "arrays.npz"
    with atomic_open(text, newline="", encoding="utf-8") as handle:
        handle.write("θ,φ\r\n1,2\n")
    assert text.read_bytes() == "θ,φ\r\n1,2\n".encode()  # newline="" translates nothing
    with atomic_open(binary, "wb") as handle:
        np.savez(handle, q=np.arange(3.0))
    with np.load(binary) as data:
        np.testing.assert_array_equal(data["q"], np.arange(3.0))
    write_atomic(tmp_path / "raw.bin", b"\x00\x01", sync=False)
    assert (tmp_path / "raw.bin").read_bytes() == b"\x00\x01"
    with pytest.raises(ValueError, match="mode"), atomic_open(tmp_path / "log.txt", "a"):
        pass


def test_a_missing_folder_is_a_clear_error(tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such"
    with pytest.raises(FileNotFoundError, match="no such folder") as info, \
            atomic_open(missing / "result.json"):
        pass
    assert info.value.filename == str(missing)
    assert not (tmp_path / "no").exists()


def test_permissions_as_open_gives_them_and_a_replaced_file_keeps_its_own(
        tmp_path: Path) -> None:
    plain, atomic = tmp_path / "plain.txt", tmp_path / "atomic.txt"
    plain.write_text("x")
    write_atomic(atomic, b"x")
    assert stat.S_IMODE(atomic.stat().st_mode) == stat.S_IMODE(plain.stat().st_mode)
    atomic.chmod(0o640)
    write_atomic(atomic, b"y")
    assert stat.S_IMODE(atomic.stat().st_mode) == 0o640


def test_a_symbolic_link_is_followed(tmp_path: Path) -> None:
    target, link = tmp_path / "target.json", tmp_path / "link.json"
    target.write_text("old")
    link.symlink_to(target)
    write_atomic(link, b"new")
    assert link.is_symlink() and target.read_text() == "new"


def test_a_writer_that_fails_half_way_leaves_the_old_file(tmp_path: Path) -> None:
    """The result writers write through the helper: a CSV whose rows run out half way
    (``zip(strict=True)`` raises after the first rows) leaves the previous CSV."""
    path = write_series_csv(tmp_path / "tendons.csv", np.arange(3.0), ["a"], np.ones((3, 1)))
    before = path.read_bytes()
    with pytest.raises(ValueError):
        write_series_csv(path, np.arange(5.0), ["a"], np.ones((3, 1)))
    assert path.read_bytes() == before
    assert _names(tmp_path) == ["tendons.csv"]


def test_figures_and_npz_files_keep_the_names_their_libraries_give(tmp_path: Path) -> None:
    """``write_figure`` names a file as ``savefig`` does (no suffix: the default format's
    suffix added) and ``save_npz`` as ``np.savez`` does (".npz" added)."""
    from matplotlib.figure import Figure

    from cr_nlp.model import load_robot
    from cr_nlp.tasks.geometry.trajectory import TrajectoryResult
    from cr_nlp.viz._figures import write_figure

    figure = Figure()
    figure.add_subplot().plot([0, 1], [1, 0])
    assert write_figure(figure, tmp_path / "plot.PNG").read_bytes()[:4] == b"\x89PNG"
    assert write_figure(figure, tmp_path / "plot").name == "plot.png"
    assert write_figure(figure, tmp_path / "plot.svg").read_text().lstrip().startswith("<?xml")
    rejected = TrajectoryResult(load_robot("tdcr3"), None, 0.5, False, "bad start", "rejected")
    rejected.save_npz(tmp_path / "plan")
    with np.load(tmp_path / "plan.npz") as data:
        assert str(data["reason"]) == "bad start"
    assert _names(tmp_path) == ["plan.npz", "plot.PNG", "plot.png", "plot.svg"]


# ================================================================ killed writers

PAYLOAD = '''
def payload(generation):
    """A RESULT.json-like content of ~8 MB; every entry names its generation."""
    return {"kind": "ik", "schema_version": 1, "generation": generation,
            "reason": [f"{generation}:{i:03d}:" + "x" * 40000 for i in range(200)]}
'''

WRITER = PAYLOAD + '''
import os, sys
from cr_nlp.tasks._result import write_json

path = sys.argv[1]
for line in sys.stdin:  # one line per round: the first generation to write
    generation = int(line)
    pid = os.fork()
    if pid == 0:  # the writer: the CLI's --out writer in a loop until it is killed
        try:
            while True:
                write_json(payload(generation), path)
                generation += 1
        finally:
            os._exit(1)
    print(pid, flush=True)
    os.waitpid(pid, 0)
    print("reaped", flush=True)
'''


def test_a_killed_writer_leaves_the_old_or_the_new_complete_file(tmp_path: Path) -> None:
    """SIGKILL a process that rewrites a large result file (``write_json``, what ``--out``
    uses) in a loop, 20 times at random moments: each time, and whenever the test reads it
    while the writer runs, the file is exactly one generation's complete content, never
    older than the last one seen."""
    namespace: dict = {}
    exec(PAYLOAD, namespace)
    payload = namespace["payload"]
    path = tmp_path / "RESULT.json"
    expected: dict[int, bytes] = {}
    seen = [0]

    def check() -> None:
        content = path.read_bytes()
        found = re.search(rb'"generation": (\d+)', content[:200])
        assert found, f"not a whole result file: {content[:80]!r}…"
        generation = int(found[1])
        if generation not in expected:
            expected[generation] = (json.dumps(payload(generation), indent=2) + "\n").encode()
        assert content == expected[generation], (
            f"generation {generation}: {len(content)} of {len(expected[generation])} bytes")
        assert generation >= seen[-1]
        seen.append(generation)

    started = time.perf_counter()
    write_json(payload(0), path)
    # Kill windows up to 2.5 whole writes long (at least 0.25 s), so that on a loaded
    # machine some writes finish and others are cut, as on a quiet one.
    window = max(0.25, 2.5 * (time.perf_counter() - started))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")])}
    driver = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True, env=env)
    rng = random.Random(41)
    try:
        for _ in range(20):
            driver.stdin.write(f"{seen[-1] + 1}\n")
            driver.stdin.flush()
            pid = int(driver.stdout.readline())
            try:
                # Until a write has finished (a loaded machine can cut all 20 short), let
                # this round's first one finish before its random kill.
                give_up = time.perf_counter() + 60.0
                while seen[-1] == 0 and time.perf_counter() < give_up:
                    check()
                deadline = time.perf_counter() + rng.uniform(0.0, window)
                while time.perf_counter() < deadline:
                    check()  # a reader beside the writer
            finally:
                os.kill(pid, signal.SIGKILL)
            assert driver.stdout.readline().strip() == "reaped"
            check()
            json.loads(path.read_text())  # and it parses
            # A kill mid-write may leave its hidden temporary file, nothing else.
            assert all(name == path.name or name.startswith(f".{path.name}.")
                       for name in _names(tmp_path))
    finally:
        driver.stdin.close()
        driver.wait(timeout=30)
    assert seen[-1] > 0, "the writer never finished a file: the test proved nothing"
