"""Compile effort (``cr_nlp._compile_effort``, ``cr_nlp._upgrade``): a first process
compiles quickly and notes what it compiled; the background process it leaves compiles
those programs fully into XLA's cache, so that a later process finds every one of them
there (none compiled again), with the same answers up to float32 rounding."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cr_nlp import _compile_effort
from cr_nlp.tasks.geometry.ik import IKSolver
from cr_nlp.tasks.geometry.trajectory import TrajectoryPlanner

CHILD = r'''
import json, sys
from functools import partial
from cr_nlp.runtime import configure, use_host_devices
use_host_devices(2)
configure()                          # as compile_program does: the persistent cache on
import jax, jax.numpy as jnp, numpy as np
from cr_nlp import _compile_effort, _programs

seen = {"hits": 0, "misses": 0}
def heard(event, **_):
    for name in seen:
        if event == f"/jax/compilation_cache/cache_{name}":
            seen[name] += 1
jax.monitoring.register_event_listener(heard)

def bend(scale, x, y):
    return jnp.tanh(scale * x @ y.T) + jnp.cumsum(jnp.sin(x), axis=0).sum()

def spread(x):
    return jnp.cos(x) * x[:, :1]

x = np.linspace(-1.0, 1.0, 24, dtype=np.float32).reshape(8, 3)
y = jax.device_put(np.linspace(0.0, 2.0, 12, dtype=np.float32).reshape(4, 3),
                   jax.devices()[1])                       # committed to the second device
programs, counts, efforts = [], [], []
for fn, args, batched, x64 in ((partial(bend, 0.5), (x, y), None, False),
                               (spread, (x,), (True,), False),
                               (spread, (x.astype(np.float64),), None, True)):
    with jax.enable_x64(x64):                      # the third traced in float64
        before = dict(seen)
        key = _programs.program_key(fn, args, ((True,), 1) if batched else None)
        efforts.append(_compile_effort.effort(key, False, jax.tree.leaves(args),
                                              bool(batched)))
        program = _programs.compile_program(fn, args, batched=batched)
        programs.append(np.asarray(program(*args)))
        counts.append({k: seen[k] - before[k] for k in seen})
print(json.dumps({"counts": counts, "efforts": efforts, "pending": _compile_effort.pending(),
                  "values": [p.tolist() for p in programs]}))
'''


def _child(tmp_path: Path) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("CR_NLP_COMPILE", "CR_NLP_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR")}
    env.update(CR_NLP_CACHE_DIR=str(tmp_path / "cache"), XLA_FLAGS="")
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    done = subprocess.run([sys.executable, str(script)], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_later_process_loads_every_quick_program_fully_optimised(tmp_path: Path) -> None:
    first = _child(tmp_path)
    assert first["efforts"] == ["quick"] * 3
    assert [c["misses"] for c in first["counts"]] == [1, 1, 1]    # compiled here
    assert len(first["pending"]) == 3                              # noted for the upgrade
    folder = tmp_path / "cache" / "programs"
    log = folder / "upgrade.log"
    assert _compile_effort.wait_for_upgrade(folder, timeout=240), (
        log.read_text() if log.exists() else "no upgrade log")
    assert "compiled" in log.read_text()
    later = _child(tmp_path)
    assert later["efforts"] == ["full"] * 3
    # Every program, one with an argument committed to a device, one split over the
    # devices, one traced in float64, comes from XLA's cache: the background process
    # compiled what this one asks for.
    assert later["counts"] == [{"hits": 1, "misses": 0}] * 3
    assert later["pending"] == []
    for quick, full in zip(first["values"], later["values"], strict=True):
        np.testing.assert_allclose(quick, full, rtol=1e-5, atol=1e-6)


def test_the_setting_and_large_jobs_choose_the_effort(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    import jax

    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    monkeypatch.delenv("CR_NLP_COMPILE", raising=False)
    one = [np.zeros(3)]
    expected = "quick" if jax.devices()[0].platform == "cpu" else "full"
    assert _compile_effort.effort("k" * 40, False, one, False) == expected
    assert _compile_effort.effort("k" * 40, True, one, False) == "full"     # a large job
    spread = [jax.device_put(np.zeros(4), jax.sharding.NamedSharding(
        jax.sharding.Mesh(np.array(jax.devices()), ("b",)), jax.sharding.PartitionSpec("b")))]
    if len(jax.devices()) > 1:            # an argument another program spread out: full
        assert _compile_effort.effort("k" * 40, False, spread, False) == "full"
    (tmp_path / "programs").mkdir()
    (tmp_path / "programs" / f"{'k' * 40}.full").touch()             # optimised already
    assert _compile_effort.effort("k" * 40, False, one, False) == "full"
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")  # the user's own
    assert _compile_effort.effort("j" * 40, False, one, False) == "full"
    monkeypatch.setenv("CR_NLP_COMPILE", "quick")
    assert _compile_effort.effort("j" * 40, True, one, False) == "quick"
    monkeypatch.setenv("CR_NLP_COMPILE", "fastest")
    with pytest.raises(ValueError, match="CR_NLP_COMPILE must be one of auto, quick, full"):
        _compile_effort.setting()


@pytest.mark.parametrize(("count", "large"), [(2, False), (3, True)])
def test_large_ik_and_planning_calls_compile_fully(count: int, large: bool,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    import cr_nlp.tasks.geometry.ik as ik
    import cr_nlp.tasks.geometry.trajectory as trajectory

    monkeypatch.setattr(ik, "LARGE_IK", 3)
    monkeypatch.setattr(trajectory, "LARGE_PLAN", 3)
    seen = []
    solver = SimpleNamespace(_solve=lambda *a: seen.append(_compile_effort.forced_full()))
    planner = SimpleNamespace(_plan=lambda *a: seen.append(_compile_effort.forced_full()))
    IKSolver.solve(solver, np.zeros((count, 3)), np.zeros((count, 4)))
    TrajectoryPlanner.plan(planner, [None] * count, [None] * count)
    assert seen == [large, large]
    assert not _compile_effort.forced_full()


def test_one_background_process_per_cache(tmp_path: Path) -> None:
    import fcntl

    folder = tmp_path / "programs"
    folder.mkdir()
    env = dict(os.environ, CR_NLP_CACHE_DIR=str(tmp_path))
    with open(folder / "upgrade.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)        # one is running
        done = subprocess.run([sys.executable, "-m", "cr_nlp._upgrade", "--devices", "1"],
                              env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr
    done = subprocess.run([sys.executable, "-m", "cr_nlp._upgrade", "--devices", "1"],
                          env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr                      # nothing noted: done


def test_waiting_ends_when_no_background_process_will_compile_what_is_left(
        tmp_path: Path) -> None:
    import time

    (tmp_path / f"{'k' * 40}.quick.json").write_text("{}")       # noted, never compiled
    t0 = time.monotonic()
    assert not _compile_effort.wait_for_upgrade(tmp_path, timeout=60, poll=0.05, idle=0.5)
    assert time.monotonic() - t0 < 10
    (tmp_path / f"{'k' * 40}.full").touch()
    assert _compile_effort.wait_for_upgrade(tmp_path, timeout=1)
