"""The exact stage's CasADi functions are compiled in the background
(``stages.polish._compiled_functions``):
a polisher solves in CasADi's virtual machine until the library is built, then switches to
it with the same answers; a build another process holds is not started twice; a process
waits for its builds at exit, so the next one finds the library."""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys
import time
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from cr_nlp.model import load_robot, tip_pose
from cr_nlp.stages.polish import _compiled_functions as compiled_functions
from cr_nlp.stages.polish._ik_nlp import IKPolisher, PolishConfig

from ...conftest import MODELS

pytestmark = pytest.mark.skipif(compiled_functions._compiler() is None, reason="needs a C compiler")


def _square() -> list[ca.Function]:
    x = ca.SX.sym("x")
    return [ca.Function("square_plus_one", [x], [x * x + 1.0])]


def test_a_polisher_switches_to_the_compiled_library_once_it_is_built(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path))
    robot = load_robot(MODELS / "robots" / "tdcr3.json")
    lo, hi = robot.q_bounds()
    q_true = lo + (hi - lo) * np.random.default_rng(4).random(robot.dof)
    position, rotation = (np.asarray(x) for x in tip_pose(robot, q_true))
    q0 = np.clip(q_true + 0.03, lo, hi)

    polisher = IKPolisher(robot)
    assert polisher._interpreted                 # no library yet: the virtual machine
    assert compiled_functions.wait_for_builds(timeout=300)
    assert list((tmp_path / "casadi").glob("*.so"))
    builds = polisher.builds
    switched = polisher.solve(q0, position, rotation)
    assert polisher.builds == builds + len(polisher.modes) and not polisher._interpreted
    # The same numbers as the virtual machine's.
    reference = IKPolisher(robot, config=PolishConfig(compile=False)).solve(q0, position,
                                                                           rotation)
    assert switched.success and reference.success
    np.testing.assert_allclose(switched.q, reference.q, atol=1e-9)
    # A polisher built now loads the library at once.
    assert not IKPolisher(robot)._interpreted


def test_a_build_that_another_process_holds_is_not_started_again(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path))
    functions = _square()
    (tmp_path / "casadi").mkdir()
    # Find the library's lock by a first call that waits for its build, then remove it.
    done, waiting = compiled_functions.compiled(functions, wait=True)
    assert not waiting and done[0](3.0) == 10.0
    (library,) = (tmp_path / "casadi").glob("*.so")
    library.unlink()
    with open(library.with_suffix(".lock"), "a+") as held:
        fcntl.flock(held, fcntl.LOCK_EX)          # "another process" is building it
        out, waiting = compiled_functions.compiled(functions)
        assert waiting and compiled_functions.pending() and out[0](3.0) == 10.0
        assert compiled_functions._pending[library] is None   # no thread of ours
        fcntl.flock(held, fcntl.LOCK_UN)
    # That process went away without the library: nothing is pending any more, and the
    # next call builds it here.
    assert not compiled_functions.pending()
    out, waiting = compiled_functions.compiled(functions)
    assert waiting and compiled_functions.wait_for_builds(timeout=120) and library.exists()
    out, waiting = compiled_functions.compiled(functions)
    assert not waiting and out[0](3.0) == 10.0


def test_a_process_waits_for_its_builds_at_exit(tmp_path: Path) -> None:
    script = ("import casadi as ca\n"
              "from cr_nlp.stages.polish._compiled_functions import compiled\n"
              "x = ca.SX.sym('x')\n"
              "out, waiting = compiled([ca.Function('cube', [x], [x ** 3])])\n"
              "assert waiting and float(out[0](2.0)) == 8.0\n")
    env = {**os.environ, "CR_NLP_CACHE_DIR": str(tmp_path)}
    run = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "compiling the exact stage's CasADi functions in the background" in run.stderr
    assert len(list((tmp_path / "casadi").glob("*.so"))) == 1


def _cube() -> list[ca.Function]:
    x = ca.SX.sym("x")
    return [ca.Function("cube", [x], [x ** 3])]


def test_a_faster_library_is_built_by_a_process_nobody_waits_for(tmp_path: Path) -> None:
    """``faster``: a detached compiler (here slowed down by 8 s) builds it; the process
    that asked exits at once with the quicker library's functions, the faster library
    appears later, and a new process takes it without building anything."""
    slow = tmp_path / "slow-cc"
    slow.write_text(f'#!/bin/sh\nsleep 8\nexec {compiled_functions._compiler()} "$@"\n')
    slow.chmod(0o755)
    script = ("import os, sys\n"
              "from cr_nlp.stages.polish import _compiled_functions as c\n"
              "import casadi as ca\n"
              "x = ca.SX.sym('x')\n"
              "f = [ca.Function('cube', [x], [x ** 3])]\n"
              "out, waiting = c.compiled(f, wait=True)          # the quick one, here\n"
              "assert not waiting\n"
              "os.environ['CC'] = sys.argv[1]\n"
              "out, waiting = c.compiled(f, wait=True, faster=('-O2',))\n"
              "assert not waiting and c.faster_pending() and float(out[0](2.0)) == 8.0\n")
    env = {**os.environ, "CR_NLP_CACHE_DIR": str(tmp_path)}
    env.pop("CC", None)
    start = time.monotonic()
    run = subprocess.run([sys.executable, "-c", script, str(slow)], env=env,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "compiling faster functions for large problems" in run.stderr
    libraries = tmp_path / "casadi"
    assert len(list(libraries.glob("*.so"))) == 1           # the faster one is not there yet
    while len(list(libraries.glob("*.so"))) < 2:
        assert time.monotonic() - start < 120, "the detached build never finished"
        time.sleep(0.5)
    quick = set(libraries.glob("*.so"))
    monkey_env = {**env, "CC": "/nonexistent-compiler"}
    check = ("from cr_nlp.stages.polish import _compiled_functions as c\n"
             "import casadi as ca\n"
             "x = ca.SX.sym('x')\n"
             "out, waiting = c.compiled([ca.Function('cube', [x], [x ** 3])], faster=('-O2',))\n"
             "assert not waiting and not c.faster_pending() and not c.pending()\n"
             "assert float(out[0](3.0)) == 27.0 and 'external' in str(out[0]).lower()\n")
    run = subprocess.run([sys.executable, "-c", check], env=monkey_env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert set(libraries.glob("*.so")) == quick and not list(libraries.glob("tmp*"))


def test_a_failed_faster_build_is_not_started_again(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The faster build starts once the quick library is there; where it fails, the
    process keeps the quick library and does not start it again."""
    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path))
    functions = _cube()
    out, waiting = compiled_functions.compiled(functions, faster=("-O2",))
    assert waiting and not compiled_functions.faster_pending()    # the quick one first
    assert compiled_functions.wait_for_builds(timeout=120)
    broken = tmp_path / "broken-cc"
    broken.write_text("#!/bin/sh\nexit 1\n")
    broken.chmod(0o755)
    monkeypatch.setattr(compiled_functions, "_compiler", lambda: str(broken))
    out, waiting = compiled_functions.compiled(functions, faster=("-O2",))
    assert not waiting and float(out[0](2.0)) == 8.0                # the quick library
    (started,) = compiled_functions._detached.values()
    started.wait(timeout=60)
    assert not compiled_functions.faster_pending()                  # ended, no library
    out, waiting = compiled_functions.compiled(functions, faster=("-O2",))
    assert not waiting and float(out[0](3.0)) == 27.0
    assert list(compiled_functions._detached.values()) == [started]     # not started again
    assert len(list((tmp_path / "casadi").glob("*.so"))) == 1
