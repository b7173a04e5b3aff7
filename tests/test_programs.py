"""Traced programs kept on disk (``cr_nlp._programs``): the key changes with everything that
changes a program and with nothing else; a later process (here: a cleared memory) loads
instead of tracing; a damaged or stale entry is ignored with a warning and traced again,
with the same answers; ``import cr_nlp`` and ``cr-nlp --help`` import no heavy package."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp import _programs
from cr_nlp._cached_jit import cached_jit
from cr_nlp._programs import (
    Unkeyable,
    compile_ahead,
    compile_program,
    fingerprint,
    program_key,
    programs_dir,
)
from cr_nlp.model import load_robot
from cr_nlp.stages.refine._ik_program import SearchPlan
from cr_nlp.stages.refine._lm import LMConfig

HEAVY = ("casadi", "trimesh", "coacd", "fcl", "dask", "distributed", "matplotlib", "viser",
         "scipy.stats", "scipy.optimize", "scipy.spatial")


def _residual(robot, scale: float, z: jax.Array) -> jax.Array:
    lengths = jnp.asarray([s.length_max for s in robot.segments], z.dtype)
    return scale * jnp.sin(z) * jnp.sum(lengths)


def _plan(**changes) -> SearchPlan:
    base = SearchPlan(width=4, coarse_iterations=8, refine_iterations=20, refine_round=5,
                      per_target=True, min_distance=0.1, block=64)
    return dataclasses.replace(base, **changes)


# ---------------------------------------------------------------- the key

def test_the_key_changes_with_what_changes_a_program_and_nothing_else() -> None:
    robot = load_robot("tdcr3")
    args = (np.zeros((8, 9), np.float32),)

    default = partial(_residual, robot, 1.0)

    def key(fn=default, arguments=args, split=None):
        return program_key(fn, arguments, split)

    same = key()
    # Equal inputs built anew, and a label that is not part of the robot: the same key.
    again = dataclasses.replace(load_robot("tdcr3"), source="elsewhere/tdcr3.json")
    assert key(partial(_residual, again, 1.0)) == same
    # The robot's structure or numbers.
    longer = dataclasses.replace(robot, segments=(dataclasses.replace(
        robot.segments[0], length_min=1.1, length_max=1.1), *robot.segments[1:]))
    assert key(partial(_residual, longer, 1.0)) != same
    assert key(partial(_residual, load_robot("tdcr4_ext"), 1.0)) != same
    # A static setting (a closed-over number, a field of a settings dataclass).
    assert key(partial(_residual, robot, 2.0)) != same
    assert fingerprint(_plan()) != fingerprint(_plan(block=32))
    assert fingerprint(_plan()) != fingerprint(_plan(lm=LMConfig(cost_tolerance=1e-9)))
    assert fingerprint(_plan()) == fingerprint(_plan())
    # Shapes (a scene with more parts, a bigger batch) and dtypes.
    assert key(arguments=(np.zeros((16, 9), np.float32),)) != same
    assert key(arguments=(np.zeros((8, 9), np.float16),)) != same
    # How the batch is split over the devices.
    assert key(split=((True,), 1)) != same


def test_the_key_changes_with_float64(float64: None) -> None:
    """The batched stages' dtype: float64 arrays (with JAX's x64 on) key other programs."""
    fn = partial(_residual, load_robot("tdcr3"), 1.0)
    assert program_key(fn, (np.zeros((8, 9), np.float64),)) != program_key(
        fn, (np.zeros((8, 9), np.float32),))


def test_the_key_changes_with_the_versions_and_the_source(monkeypatch) -> None:
    fn, args = partial(_residual, load_robot("tdcr3"), 1.0), (np.zeros((4, 9), np.float32),)
    same = program_key(fn, args)
    monkeypatch.setattr(jax, "__version__", "0.0.1")
    assert program_key(fn, args) != same
    monkeypatch.undo()
    monkeypatch.setattr(_programs, "source_hash", lambda: "another cr_nlp")
    assert program_key(fn, args) != same


def test_an_object_the_key_cannot_describe_is_refused() -> None:
    class Opaque:
        pass

    with pytest.raises(Unkeyable):
        fingerprint(partial(_residual, Opaque(), 1.0))


def test_a_function_is_keyed_by_its_code_and_closure() -> None:
    def make(c):
        return lambda z: z * c

    assert fingerprint(make(1.0)) == fingerprint(make(1.0))
    assert fingerprint(make(1.0)) != fingerprint(make(2.0))
    assert fingerprint(lambda z: z + 1) != fingerprint(lambda z: z - 1)


# ---------------------------------------------------------------- the disk

def _square_sum(offset: float, z: jax.Array, w: dict) -> tuple[jax.Array, dict]:
    return jnp.sum((z - offset) ** 2, axis=1), {"scaled": z * w["scale"]}


def _run(offset: float = 0.5):
    z = np.arange(12, dtype=np.float32).reshape(4, 3)
    args = (z, {"scale": np.float32(3.0)})
    program = compile_program(partial(_square_sum, offset), args, name="a test program")
    total, extra = program(*args)
    return np.asarray(total), np.asarray(extra["scaled"])


def _expected(offset: float = 0.5):
    z = np.arange(12, dtype=np.float32).reshape(4, 3)
    return np.sum((z - offset) ** 2, axis=1), z * 3.0


def _same(answer: tuple, expected: tuple) -> None:
    for a, b in zip(answer, expected, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6)


def test_a_new_process_loads_the_program_instead_of_tracing_it(program_cache: Path) -> None:
    _same(_run(), _expected())
    assert (_programs.stats.traced, _programs.stats.loaded) == (1, 0)
    assert len(list(programs_dir().glob("*.jaxexport"))) == 1
    _run()  # the same process: from memory
    assert _programs.stats.reused == 1
    _programs.clear_memory()  # as a new process finds it
    _same(_run(), _expected())
    assert (_programs.stats.traced, _programs.stats.loaded) == (1, 1)
    # A changed key (another closed-over number) traces a program of its own.
    _same(_run(1.5), _expected(1.5))
    assert _programs.stats.traced == 2


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage", "empty"])
def test_a_damaged_entry_is_ignored_with_a_warning(program_cache: Path, damage: str) -> None:
    _run()
    (entry,) = programs_dir().glob("*.jaxexport")
    data = entry.read_bytes()
    entry.write_bytes({"truncate": data[: len(data) // 2],
                       "flip": data[:-100] + bytes([data[-100] ^ 0xFF]) + data[-99:],
                       "garbage": os.urandom(len(data)),
                       "empty": b""}[damage])
    _programs.clear_memory()
    with pytest.warns(RuntimeWarning, match="ignoring the cached program"):
        answer = _run()
    _same(answer, _expected())
    assert _programs.stats.rejected == 1 and _programs.stats.traced == 2
    _programs.clear_memory()  # the entry was written again, whole
    _same(_run(), _expected())
    assert _programs.stats.loaded == 1


def test_a_stale_entry_of_another_program_is_not_used(program_cache: Path) -> None:
    """A file under this key that holds another program (copied or left over) is
    rejected by the key it carries and traced again."""
    _run(0.5)
    (first,) = programs_dir().glob("*.jaxexport")
    _programs.clear_memory()
    z = np.arange(12, dtype=np.float32).reshape(4, 3)
    args = (z, {"scale": np.float32(3.0)})
    key = program_key(partial(_square_sum, 1.5), args)
    (programs_dir() / f"{key}.jaxexport").write_bytes(first.read_bytes())
    with pytest.warns(RuntimeWarning, match="stale"):
        answer = _run(1.5)
    _same(answer, _expected(1.5))
    assert _programs.stats.rejected == 1


def test_cached_jit_keeps_one_program_per_shape_and_static_value(program_cache: Path) -> None:
    @partial(cached_jit, static_argnums=(0,))
    def power(n: int, z: jax.Array) -> jax.Array:
        return z ** n

    z = np.arange(4, dtype=np.float32)
    np.testing.assert_allclose(power(2, z), z ** 2)
    np.testing.assert_allclose(power(3, z), z ** 3)
    np.testing.assert_allclose(power(2, np.arange(6, dtype=np.float32)),
                               np.arange(6) ** 2)
    assert _programs.stats.traced == 3


@pytest.mark.skipif(jax.device_count() < 2, reason="needs two JAX devices")
def test_a_program_split_over_the_devices_round_trips(program_cache: Path) -> None:
    def fn(z, w):
        return jnp.sin(z) * w, jnp.sum(z, axis=1)

    z, w = np.arange(16, dtype=np.float32).reshape(8, 2), np.float32(2.0)
    first = compile_program(fn, (z, w), batched=(True, False), outputs=2)(z, w)
    _programs.clear_memory()
    second = compile_program(fn, (z, w), batched=(True, False), outputs=2)(z, w)
    assert _programs.stats.loaded == 1
    assert len(second[0].sharding.device_set) == jax.device_count()
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(second[0], np.sin(z) * 2.0, rtol=1e-6)


# ---------------------------------------------------------------- compiling ahead

def test_a_program_compiled_ahead_is_waited_for_not_compiled_again(program_cache: Path) -> None:
    z = np.arange(12, dtype=np.float32).reshape(4, 3)
    args = (z, {"scale": np.float32(3.0)})
    fn = partial(_square_sum, 0.5)
    assert compile_ahead(fn, args, name="the test program") is None  # returns at once
    total, extra = compile_program(fn, args)(*args)
    _same((total, extra["scaled"]), _expected())
    assert (_programs.stats.traced, _programs.stats.reused) == (1, 0)
    # Asking again, ahead or not, for a program compiled already starts nothing.
    compile_ahead(fn, args)
    compile_program(fn, args)
    assert (_programs.stats.traced, _programs.stats.reused) == (1, 1)
    assert not _programs._pending


def test_an_error_compiling_ahead_is_raised_where_the_program_is_asked_for(
        program_cache: Path) -> None:
    def broken(z: jax.Array) -> jax.Array:
        return z @ jnp.ones((5, 2), z.dtype)  # (4, 3) @ (5, 2): shapes that do not fit

    args = (np.zeros((4, 3), np.float32),)
    compile_ahead(broken, args)  # no error here: nobody asked for the program yet
    with pytest.raises(TypeError, match="dot_general"):
        compile_program(broken, args)
    assert not _programs._pending


def test_a_program_asked_for_ahead_but_not_started_is_built_by_who_needs_it(
        program_cache: Path, monkeypatch) -> None:
    """A program queued behind a longer build (the background pool busy) is built by the
    thread that asks for it, not waited for; asked ahead again, it starts nothing."""
    from concurrent.futures import ThreadPoolExecutor
    from threading import Event

    busy, pool = Event(), ThreadPoolExecutor(1)
    pool.submit(busy.wait, 60)                    # the pool's one thread: taken
    monkeypatch.setattr(_programs, "_background", lambda: pool)
    z = np.arange(12, dtype=np.float32).reshape(4, 3)
    args = (z, {"scale": np.float32(3.0)})
    fn = partial(_square_sum, 0.5)
    compile_ahead(fn, args)
    assert _programs._pending and _programs._queued
    try:
        total, extra = compile_program(fn, args)(*args)   # would wait 60 s for the pool
        assert not busy.is_set()
    finally:
        busy.set()
        pool.shutdown()
    _same((total, extra["scaled"]), _expected())
    assert _programs.stats.traced == 1
    assert not _programs._pending and not _programs._queued
    compile_ahead(fn, args)
    assert not _programs._pending


def _on_devices(devices: list) -> list[tuple]:
    copies = []
    for device in devices:
        z = jax.device_put(np.arange(12, dtype=np.float32).reshape(4, 3), device)
        copies.append((z, {"scale": jax.device_put(np.float32(3.0), device)}))
    return copies


@pytest.mark.skipif(jax.device_count() < 2, reason="needs two JAX devices")
@pytest.mark.parametrize("ahead", [False, True])
def test_a_second_device_gets_the_first_ones_program_not_a_compile_of_its_own(
        program_cache: Path, ahead: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """As the trajectory LM's lanes: one program per device, traced and compiled once.
    Asked for side by side (ahead), the second copy is moved from the first; asked for
    after the first is stored, it is loaded from the same two cache entries."""
    fn = partial(_square_sum, 0.5)
    devices = jax.devices()[:2]
    copies = _on_devices(devices)
    if ahead:
        # Not stored yet when the second asks (a first trace can be quicker than the ask).
        monkeypatch.setattr(_programs, "_stored", lambda key: False)
        for args in copies:
            compile_ahead(fn, args)
    for device, args in zip(devices, copies, strict=True):
        total, extra = compile_program(fn, args)(*args)
        assert total.devices() == {device} and extra["scaled"].devices() == {device}
        _same((total, extra["scaled"]), _expected())
    stats = _programs.stats
    assert (stats.traced, stats.loaded, stats.moved) == ((1, 0, 1) if ahead else (1, 1, 0))
    assert not _programs._pending


_TWO_LANES = """
from cr_nlp.runtime import use_host_devices
use_host_devices(2)
import json, os
from functools import partial
import jax, jax.numpy as jnp, numpy as np
from cr_nlp import _programs

misses = []
jax.monitoring.register_event_listener(
    lambda event, **_: misses.append(event) if event.endswith("cache_misses") else None)

def square_sum(offset, z, w):
    return jnp.sum((z - offset) ** 2, axis=1), {"scaled": z * w["scale"]}

if os.environ.get("CR_NLP_TEST_FIRST"):  # not stored yet when the second lane asks
    _programs._stored = lambda key: False
out, lanes = [], []
for device in jax.devices()[:2]:  # as the trajectory LM's lanes: asked for side by side
    z = jax.device_put(np.arange(12, dtype=np.float32).reshape(4, 3), device)
    lanes.append((z, {"scale": jax.device_put(np.float32(3.0), device)}))
    _programs.compile_ahead(partial(square_sum, 0.25), lanes[-1])
for z, w in lanes:
    total, _ = _programs.compile_program(partial(square_sum, 0.25), (z, w))(z, w)
    out.append([next(iter(total.devices())).id, np.asarray(total).tolist()])
print(json.dumps({"out": out, "moved": _programs.stats.moved, "misses": len(misses)}))
"""


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="two host devices: a CPU test")
def test_one_xla_cache_entry_serves_both_devices_and_is_not_moved(tmp_path: Path) -> None:
    """The first process compiles for one device and moves the program to the other; the
    second loads both from XLA's one cache entry: code loaded from it serialises without
    its functions (moved, it failed when run: "Function … not found"), so it is not
    moved."""
    runs = []
    for first in ("1", ""):
        done = subprocess.run([sys.executable, "-c", _TWO_LANES], capture_output=True,
                              text=True, timeout=300,
                              env={**os.environ, "CR_NLP_CACHE_DIR": str(tmp_path),
                                   "CR_NLP_TEST_FIRST": first})
        assert done.returncode == 0, done.stderr[-2000:]
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    assert [run["moved"] for run in runs] == [1, 0]
    # One cache entry serves both devices: the second process compiles nothing.
    assert runs[0]["misses"] > 0 and runs[1]["misses"] == 0
    expected = _expected(0.25)[0]
    for run in runs:
        assert [device for device, _ in run["out"]] == [0, 1]
        for _, total in run["out"]:
            np.testing.assert_allclose(total, expected, rtol=1e-6)


@pytest.mark.skipif(jax.device_count() < 2, reason="needs two JAX devices")
def test_a_program_that_cannot_move_is_compiled_for_its_device(program_cache: Path,
                                                                monkeypatch) -> None:
    def refuse(program: object, device: object) -> None:
        raise RuntimeError("this JAX cannot move executables")

    monkeypatch.setattr(_programs, "_moved", refuse)
    monkeypatch.setattr(_programs, "_stored", lambda key: False)
    fn = partial(_square_sum, 0.5)
    devices = jax.devices()[:2]
    copies = _on_devices(devices)
    compile_ahead(fn, copies[0])  # under way when the second device asks
    with pytest.warns(RuntimeWarning, match="could not move a compiled program"):
        total, extra = compile_program(fn, copies[1])(*copies[1])
    assert total.devices() == {devices[1]}
    _same((total, extra["scaled"]), _expected())
    assert (_programs.stats.traced, _programs.stats.moved) == (1, 0)


# ---------------------------------------------------------------- imports

def _imported(code: str, env: dict | None = None) -> list[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport json, sys\n"
                          "print(json.dumps(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True, timeout=300,
                         env={**os.environ, **(env or {})})
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_cr_nlp_imports_no_heavy_package() -> None:
    modules = _imported("import cr_nlp")
    assert not [m for m in modules if m in HEAVY or m == "jax"]


def test_the_command_help_imports_no_heavy_package() -> None:
    modules = _imported("from cr_nlp.cli.main import build_parser\n"
                        "build_parser().format_help()")
    assert not [m for m in modules if m in HEAVY or m == "jax"]


def test_an_ik_solve_imports_no_plotting_meshing_or_cluster_package(tmp_path: Path) -> None:
    """Nor, once its seed pool's Sobol points are cached, scipy.stats."""
    code = ("import numpy as np\n"
            "from cr_nlp import IKConfig, IKSolver, tip_pose, wxyz_from_matrix\n"
            "solver = IKSolver('tdcr3', config=IKConfig(pool_size=256, retry_rounds=0))\n"
            "p, r = tip_pose(solver.robot, np.array([[0.5, 0.1, 1.0] * 3]))\n"
            "solver.solve(p, wxyz_from_matrix(r))")
    _imported(code, {"CR_NLP_CACHE_DIR": str(tmp_path)})
    modules = _imported(code, {"CR_NLP_CACHE_DIR": str(tmp_path)})
    assert not [m for m in modules if m in ("trimesh", "coacd", "dask", "distributed",
                                            "matplotlib", "viser", "scipy.stats")]


# ---------------------------------------------------------------- commands

def test_bench_startup_times_whole_processes_cold_and_warm(tmp_path: Path) -> None:
    from cr_nlp.bench.startup import run_startup_benchmark

    rows = run_startup_benchmark(entries=("import", "predict"), out=tmp_path / "out",
                                 progress=False)
    by = {(r["entry"], r["cache"]): r for r in rows}
    assert set(by) == {(e, c) for e in ("import", "predict") for c in ("cold", "warm")}
    # The cold process traced the prediction program; the warm one loaded it.
    assert by["predict", "cold"]["programs_traced"] >= 1
    assert by["predict", "warm"]["programs_traced"] == 0
    assert by["predict", "warm"]["programs_loaded"] >= 1
    for row in rows:
        assert 0 < row["first_answer"] <= row["wall"]
    report = (tmp_path / "out" / "startup.md").read_text()
    assert "| predict |" in report and "jax:" in report


def test_warmup_fills_the_cache_a_later_process_loads(tmp_path: Path) -> None:
    env = {**os.environ, "CR_NLP_CACHE_DIR": str(tmp_path)}
    command = [sys.executable, "-m", "cr_nlp.cli", "warmup", "--robot", "tdcr2_rao2021",
               "--tasks", "statics", "plan"]
    first = subprocess.run(command, env=env, capture_output=True, text=True, check=True,
                           timeout=600)
    assert "skipped: planning needs a scene" in first.stdout
    assert "compiling the Cosserat shooting" in first.stderr
    assert list((tmp_path / "programs").glob("*.jaxexport"))
    second = subprocess.run(command, env=env, capture_output=True, text=True, check=True,
                            timeout=600)
    statics = next(line for line in second.stdout.splitlines() if line.startswith("statics"))
    assert statics.split()[2:4] == ["0", "1"], statics  # traced 0, loaded 1
    assert "compiling" not in second.stderr
