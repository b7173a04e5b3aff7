"""Benchmark: batched Cosserat statics (solves per second and convergence).

``cr-nlp bench statics`` times ``solve_statics`` on batches of random load cases of a
robot with a ``mechanics`` block (default ``tdcr2_rao2021``): tensions of 0–6 N on one or
two tendons per segment; in the ``mixed`` set a third of the cases also carry a 0.3 N
tip force and a third a 0.01 N·m tip moment (random directions), the ``tensions`` set has
no external load. Compile time (first call) is reported apart from the steady state
(median of ``repeats`` timed runs after it); every row records the convergence rate.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..model import load_robot
from ..model.cosserat import StaticsConfig, solve_statics
from ._common import Column, environment, environment_markdown, fixed, markdown_table, write_report
from .suites import STATICS_SETS

SETS = STATICS_SETS


@dataclass(frozen=True)
class StaticsBenchRow:
    """One measured line of the table (times in seconds)."""

    cases: int
    load_set: str
    dtype: str
    compile_s: float
    median_s: float
    min_s: float
    converged: float

    @property
    def solves_per_s(self) -> float:
        return self.cases / self.median_s


def statics_cases(robot_tendons: int, per_segment: int, cases: int, load_set: str,
                  seed: int = 0, tension_max: float = 6.0) -> tuple[np.ndarray, ...]:
    """Random (tensions, tip forces, tip moments): 1–2 tendons of each segment pulled with
    U[0, tension_max] N; in the ``mixed`` set cases 1, 4, 7, … get a 0.3 N tip force and
    2, 5, 8, … a 0.01 N·m tip moment in uniformly random directions."""
    rng = np.random.default_rng(seed)
    tensions = np.zeros((cases, robot_tendons))
    segments = robot_tendons // per_segment
    for k in range(cases):
        for s in range(segments):
            pulled = rng.choice(per_segment, size=rng.integers(1, 3), replace=False)
            tensions[k, s * per_segment + pulled] = rng.uniform(0, tension_max, len(pulled))
    forces, moments = np.zeros((cases, 3)), np.zeros((cases, 3))
    if load_set == "mixed":
        kind = np.arange(cases) % 3
        direction = rng.normal(size=(cases, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        forces[kind == 1] = 0.3 * direction[kind == 1]
        moments[kind == 2] = 0.01 * direction[kind == 2]
    return tensions, forces, moments


def bench_statics(robot: str = "tdcr2_rao2021", cases: int = 1000, load_set: str = "mixed",
                  dtype: str = "float64", repeats: int = 5, seed: int = 0) -> StaticsBenchRow:
    """Time ``solve_statics`` on ``cases`` random cases (compile apart, median of repeats)."""
    rob = load_robot(robot)
    t, f, m = statics_cases(rob.n_tendons, rob.tendons.per_segment, cases, load_set, seed)
    config = StaticsConfig(dtype=dtype)
    start = time.perf_counter()
    result = solve_statics(rob, t, f, m, config=config)
    compile_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = solve_statics(rob, t, f, m, config=config)  # numpy out: synchronised
        times.append(time.perf_counter() - start)
    return StaticsBenchRow(cases, load_set, dtype, compile_s, statistics.median(times),
                           min(times), float(result.converged.mean()))



def bench_displacement_statics(robot: str = "tdcr2_rao2021", cases: int = 10_000,
                               tendon_stiffness: float = 5000.0, repeats: int = 3,
                               seed: int = 0) -> StaticsBenchRow:
    """Time ``solve_displacement_statics`` under gravity on ``cases`` random commands: 1–2
    tendons of each segment pulled by U[0, 3] mm, the others at their zeros (taut on the
    straight robot), tendons of ``tendon_stiffness`` N/m (compile apart, median of
    repeats)."""
    from ..model.cosserat import solve_displacement_statics

    rob = load_robot(robot)
    d, _, _ = statics_cases(rob.n_tendons, rob.tendons.per_segment, cases, "tensions", seed,
                            tension_max=0.003)
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        result = solve_displacement_statics(rob, d, gravity=[0.0, 0.0, -9.81],
                                            tendon_stiffness=tendon_stiffness)
        times.append(time.perf_counter() - start)
    return StaticsBenchRow(cases, "commands + gravity", "float64", times[0],
                           statistics.median(times[1:]), min(times[1:]),
                           float(result.converged.mean()))

COLUMNS = [
    Column("cases", "cases"),
    Column("load_set", "loads"),
    Column("dtype", "dtype"),
    Column("compile_s", "first call (s)", fixed(2)),
    Column("median_s", "median (s)", fixed(3)),
    Column("solves_per_s", "solves/s", fixed(0)),
    Column("converged_pct", "converged (%)", fixed(2)),
]


@dataclass(frozen=True)
class TensionIKBenchRow:
    """One measured line of the tension-space IK table (times in seconds)."""

    targets: int
    loads: str
    compile_s: float
    median_s: float
    success: float
    median_error_m: float
    max_error_m: float


def bench_tension_ik(robot: str = "tdcr2_rao2021", targets: int = 1000, loads: str = "none",
                     repeats: int = 3, seed: int = 0) -> TensionIKBenchRow:
    """Time ``TensionIKSolver.solve`` on ``targets`` tip positions made by forward statics
    from random feasible tensions (``statics_cases``' tension sets; ``loads`` "force": all
    under one 0.05 N sideways tip force). Compile and the seed pool are the first call."""
    from ..tasks.mechanics.ik import TensionIKSolver

    rob = load_robot(robot)
    t, _, _ = statics_cases(rob.n_tendons, rob.tendons.per_segment, targets, "tensions",
                            seed + 1)
    force = np.array([0.0, 0.05, 0.0]) if loads == "force" else None
    truth = solve_statics(rob, t, force)
    goal = truth.tip_position[truth.converged]
    solver = TensionIKSolver(rob)
    start = time.perf_counter()
    result = solver.solve(goal, tip_force=force)
    compile_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = solver.solve(goal, tip_force=force)
        times.append(time.perf_counter() - start)
    error = result.position_error
    return TensionIKBenchRow(len(goal), loads, compile_s, statistics.median(times),
                             float(result.success.mean()), float(np.nanmedian(error)),
                             float(np.nanmax(error)))


IK_COLUMNS = [
    Column("targets", "targets"),
    Column("loads", "loads"),
    Column("compile_s", "first call (s)", fixed(2)),
    Column("median_s", "median (s)", fixed(3)),
    Column("success_pct", "success (%)", fixed(1)),
    Column("median_error_mm", "median error (mm)", lambda v: f"{v:.1e}"),
    Column("max_error_mm", "max error (mm)", lambda v: f"{v:.3f}"),
]


def run_statics_benchmark(robot: str = "tdcr2_rao2021",
                          sizes: tuple[int, ...] = (100, 1000, 10_000),
                          load_sets: tuple[str, ...] = SETS,
                          dtypes: tuple[str, ...] = ("float64", "float32"), repeats: int = 5,
                          seed: int = 0, out: str | Path | None = None,
                          ik_targets: tuple[int, ...] = (1000,)) -> list[dict[str, Any]]:
    """Every (size, load set, dtype) row and the tension-space IK rows (``ik_targets``
    targets, without and under a tip force); prints the Markdown tables and writes
    statics.md, statics.csv, tension_ik.csv and environment.json to ``out``."""
    rows = []
    for load_set in load_sets:
        for dtype in dtypes:
            for cases in sizes:
                row = bench_statics(robot, cases, load_set, dtype, repeats, seed)
                rows.append({**asdict(row), "solves_per_s": row.solves_per_s,
                             "converged_pct": 100.0 * row.converged})
    ik_rows = []
    for targets in ik_targets:
        for loads in ("none", "force"):
            ik = bench_tension_ik(robot, targets, loads, min(repeats, 3), seed)
            ik_rows.append({**asdict(ik), "success_pct": 100.0 * ik.success,
                            "median_error_mm": 1e3 * ik.median_error_m,
                            "max_error_mm": 1e3 * ik.max_error_m})
    env = environment()
    report = (f"## Cosserat statics, {robot}\n\n"
              "`solve_statics` on random cases (tensions 0–6 N on 1–2 tendons per segment; "
              "`mixed`: a third with a 0.3 N tip force, a third with a 0.01 N·m tip "
              f"moment); steady state is the median of {repeats} runs after the first "
              "call.\n\n" + markdown_table(rows, COLUMNS))
    if ik_rows:
        report += ("\n\nTension-space IK (`TensionIKSolver`) on tip positions of random "
                   "feasible tensions (the same tension sets; `force`: all under a 0.05 N "
                   "sideways tip force); errors by an independent forward solve.\n\n"
                   + markdown_table(ik_rows, IK_COLUMNS))
    report += "\n\n" + environment_markdown(env)
    write_report("statics", report, out, tables={"statics": rows, "tension_ik": ik_rows},
                 env=env, settings={"robot": robot, "repeats": repeats, "seed": seed})
    return rows
