"""Test-wide settings: the persistent JAX compilation cache (cr_nlp's own) and the
``float64`` fixture; helpers shared by the world tests.

The tests run in a user's numeric configuration: ``import cr_nlp`` leaves JAX's x64 off,
so JAX arrays default to float32 and the batched stages run their float32 paths. A test
that needs float64 JAX arrays (agreement at 1e-9 with an independent float64 evaluation,
derivatives against autodiff or CasADi) asks for it with the ``float64`` fixture, which
turns x64 on for that test only."""

from __future__ import annotations

import contextlib
import json
import os
import signal
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import numpy as np
import pytest

from cr_nlp.runtime import enable_compilation_cache, use_host_devices

if TYPE_CHECKING:  # the world and model modules are imported lazily, after the settings
    from cr_nlp.model import Robot
    from cr_nlp.world import Scene

ROOT = Path(__file__).resolve().parent.parent
MODELS = ROOT / "models"

use_host_devices()  # the solvers' sharded path runs in the tests as it does in the CLI
# Every program with one effort, the run's XLA flags (below), and no background process
# optimising them afterwards (``cr_nlp._compile_effort``; tests/test_compile_effort.py
# runs its default in processes of its own). The commands and kernels the tests start
# inherit it.
os.environ.setdefault("CR_NLP_COMPILE", "full")
# The cache the CLI and every cr_nlp process use ($CR_NLP_JAX_CACHE, else the cr_nlp cache
# folder's jax/): the commands the tests start, the notebooks' kernels and the other
# worker load what one process compiled. The test processes store only programs that
# took 0.5 s or more: test_programs' tiny programs must compile in each test, not load
# (a loaded program cannot be moved to another device).
enable_compilation_cache()
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
SESSION_X64 = bool(jax.config.jax_enable_x64)  # off, unless $JAX_ENABLE_X64 asks for it


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto`` (the default run): one worker per core this process may use, at most 4.

    Each worker holds its own compiled solvers (a few GB with the larger tests); past 4
    workers the shared disk caches and the longest test files set the run's length."""
    return max(1, min(4, len(os.sched_getaffinity(0))))


QUICK_XLA_FLAGS = ("--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false")
"""XLA settings of the default run: LLVM's optimisations off, and XLA's older loop-fusion
emitters, which compile a Cosserat shooting program in 3.8 s of XLA time instead of 7.3 s
and tests/tasks/geometry/test_follow.py in 124 s instead of 190 s (2 cores, empty caches,
2026-12-02). Same XLA programs; results equal up to float32 rounding."""


def pytest_configure(config: pytest.Config) -> None:
    """The default run (slow tests deselected, as in CI) compiles with XLA's LLVM
    optimisations off.

    Most of that run's time was XLA compiling programs that then solve small problems in
    milliseconds. Level 0 gives the same XLA programs (XLA's own HLO passes still run, no
    fast-math either way): results equal up to rounding, slower machine code. Measured
    on 2 shared cores with empty caches (old → level 0): test_follow_exact +
    test_exact_verdict's parallel polish + test_ik's exact test + test_compile_cache
    194 s → 151 s, notebook 03 113 s → 65 s; but test_roadmap_search 45 s → 50 s and the
    slow 1000-problem test 103 s → 270 s, so a run with the slow tests keeps XLA's
    default. Runs before JAX starts (collection imports the solvers); a level already in
    $XLA_FLAGS is kept. Processes the tests start (the CLI, pool workers, the notebooks'
    kernels in the same run) inherit it."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "not slow" in (config.getoption("markexpr") or "") and \
            "xla_backend_optimization_level" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {' '.join(QUICK_XLA_FLAGS)}".strip()


@pytest.fixture(autouse=True)
def _x64_stays_off() -> Iterator[None]:
    """Fail the test that changed JAX's x64 setting for the rest of the session."""
    yield
    if bool(jax.config.jax_enable_x64) != SESSION_X64:
        jax.config.update("jax_enable_x64", SESSION_X64)
        pytest.fail("the test changed jax_enable_x64 for the session; use the float64 fixture")


@pytest.fixture
def float64() -> Iterator[None]:
    """JAX's x64 on for one test (JAX arrays default to float64), off again after it.

    ``jax.enable_x64`` is a context-local setting that jit caches key on, so code compiled
    inside the test is not reused by the float32 tests after it. Arrays a test builds at
    import or in a wider-scoped fixture are built without it."""
    with jax.enable_x64(True):
        yield


def write_mixed_scene(root: Path, extra: Sequence[dict] = ()) -> Scene:
    """One obstacle of every kind (sphere, box, capsule, cylinder, mesh), all within reach
    of tdcr3, plus ``extra`` obstacles, written to ``root/mixed.json`` and loaded."""
    from cr_nlp.world import Scene, union_of_boxes

    union_of_boxes([((0, 0, 0), (0.6, 0.1, 0.5)), ((0, 0, 0), (0.1, 0.5, 0.5))]).export(
        root / "corner.obj")
    data = {"obstacles": [
        {"type": "sphere", "name": "ball", "center": [0.9, 0.3, 1.5], "radius": 0.25},
        {"type": "box", "name": "crate", "center": [-0.8, 0.2, 1.2], "size": [0.4, 0.6, 0.3],
         "wxyz": [0.9238795, 0.0, 0.3826834, 0.0]},
        *extra,
        {"type": "capsule", "name": "pipe", "a": [-0.5, -1.0, 2.2], "b": [0.6, -0.6, 2.0],
         "radius": 0.12},
        {"type": "cylinder", "name": "post", "a": [0.4, -0.9, 0.0], "b": [0.5, -0.8, 1.4],
         "radius": 0.15},
        {"type": "mesh", "name": "corner", "path": "corner.obj", "position": [0.5, 0.6, 0.6]},
    ]}
    (root / "mixed.json").write_text(json.dumps(data))
    return Scene.from_file(root / "mixed.json")


def random_q(robot: Robot, count: int, seed: int) -> np.ndarray:
    """``count`` configurations drawn uniformly inside the robot's limits (rad, rad, m)."""
    lo, hi = robot.q_bounds()
    return np.random.default_rng(seed).uniform(lo, hi, (count, robot.dof))


@contextlib.contextmanager
def sigint_ignored() -> Iterator[None]:
    """SIGINT ignored in this process while the block starts a subprocess, which inherits
    it, as a shell's background job does. (Not ``preexec_fn``: forking a multithreaded
    process to run Python in the child can deadlock.)"""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.fixture
def program_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty cr_nlp program cache and no programs in memory (``clear_caches``: also
    those kept by the functions that make them, e.g. the verdict's program per robot, and
    by ``cached_jit`` functions); counts reset."""
    from cr_nlp import _programs, clear_caches

    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path))
    clear_caches()
    _programs.stats.__init__()
    yield tmp_path
    clear_caches()
