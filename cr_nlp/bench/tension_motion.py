"""Benchmark: planning and path following in tension space under load (issue 40's
targets).

``cr-nlp bench tension`` on a robot with a ``mechanics`` block (default
``tdcr2_rao2021``) under gravity and a 5 g payload at the tip, among the spheres and boxes
of ``SCENE`` (both rows): ``problems`` planning problems between random collision-free
start and goal tensions (``TensionTrajectoryPlanner``), and a ``waypoints``-waypoint path
(``TensionPathFollower``) traced by the tip of a smooth loop of tensions (so every waypoint is
reachable). Success is the planners' own verdict (fresh statics at every checked sample,
python-fcl); the first call (compiles, seed and via pools) is reported apart from the
steady state (the median of ``repeats`` timed runs after it).
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..model import load_robot
from ..model.cosserat import solve_statics
from ..model.loads import static_loads
from ._common import Column, environment, environment_markdown, fixed, markdown_table, write_report

GRAVITY = [0.0, 0.0, -9.81]
PAYLOAD = [0.0, 0.0, -0.005 * 9.81]
"""5 g at the tip, N."""

SCENE = {"obstacles": [
    {"name": "ball_a", "type": "sphere", "center": [0.12, 0.0, 0.30], "radius": 0.03},
    {"name": "ball_b", "type": "sphere", "center": [-0.10, 0.12, 0.28], "radius": 0.03},
    {"name": "crate", "type": "box", "center": [0.0, -0.2, 0.2], "size": [0.1, 0.04, 0.1]},
    {"name": "post", "type": "box", "center": [-0.2, -0.05, 0.15], "size": [0.04, 0.1, 0.1]},
]}
"""Spheres and boxes around the 0.4 m robot of ``tdcr2_rao2021``, m."""


def loop_tensions(count: int) -> np.ndarray:
    """A smooth loop of tensions on both segments of a 2×3-tendon robot, (count, 6) N."""
    t = np.linspace(0.0, 1.0, count)[:, None]
    return np.concatenate([2 + 2 * np.sin(2 * np.pi * t), 1 + np.cos(2 * np.pi * t), 0 * t,
                           1 + t, 0 * t, 2 * t], axis=1)


def timed(call: Any, repeats: int) -> tuple[Any, float, float]:
    """(result, first call s, median of ``repeats`` later calls s)."""
    start = time.perf_counter()
    result = call()
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = call()
        times.append(time.perf_counter() - start)
    return result, first, statistics.median(times) if times else first


def bench_plan(robot: str, problems: int, repeats: int, seed: int) -> dict[str, Any]:
    """Plan ``problems`` random collision-free problems; success and seconds."""
    from ..tasks.mechanics.trajectory import TensionTrajectoryPlanner

    planner = TensionTrajectoryPlanner(robot, SCENE)
    rob = planner.robot
    loads = static_loads(1, planner.length, PAYLOAD, None, GRAVITY)
    rng = np.random.default_rng(seed)
    candidates = rng.uniform(0.0, 6.0, (8 * problems, rob.n_tendons))
    candidates[rng.random(candidates.shape) < 0.4] = 0.0
    clear = candidates[planner.clear(candidates, loads)][:2 * problems]
    starts, goals = clear[:problems], clear[problems:]
    results, first, median = timed(
        lambda: planner.plan(starts, goals, gravity=GRAVITY, tip_force=PAYLOAD), repeats)
    return {"problems": len(starts), "first_s": first, "median_batch_s": median,
            "per_problem_s": median / max(len(starts), 1),
            "success_pct": 100.0 * np.mean([r.success for r in results]),
            "via_pct": 100.0 * np.mean([r.notes[0].startswith("via") for r in results]),
            "min_clearance_mm": 1e3 * min(r.min_clearance for r in results)}


def bench_follow(robot: str, waypoints: int, repeats: int) -> dict[str, Any]:
    """Follow a ``waypoints``-waypoint loop under load; error (fresh statics) and time."""
    from ..tasks.mechanics.follow import TensionPathFollower

    rob = load_robot(robot)
    path = solve_statics(rob, loop_tensions(waypoints), PAYLOAD, None, GRAVITY).tip_position
    follower = TensionPathFollower(rob, SCENE)
    result, first, median = timed(
        lambda: follower.follow(path, dt=0.05, gravity=GRAVITY, tip_force=PAYLOAD), repeats)
    return {"waypoints": waypoints, "first_s": first, "median_s": median,
            "success": bool(result.success), "reached": int(result.reached.sum()),
            "max_error_mm": 1e3 * float(np.max(result.position_error)),
            "max_rate_n_s": float(np.max(np.abs(np.diff(result.tensions, axis=0)))) / 0.05,
            "min_clearance_mm": 1e3 * result.min_clearance}


PLAN_COLUMNS = [
    Column("problems", "problems"), Column("success_pct", "verified success (%)", fixed(1)),
    Column("via_pct", "via a pool set (%)", fixed(1)),
    Column("per_problem_s", "s per problem (median batch / problems)", fixed(3)),
    Column("first_s", "first call (s)", fixed(2)),
    Column("min_clearance_mm", "min clearance (mm)", fixed(1)),
]
FOLLOW_COLUMNS = [
    Column("waypoints", "waypoints"), Column("reached", "reached"),
    Column("max_error_mm", "max position error (mm)", fixed(4)),
    Column("max_rate_n_s", "max tension rate (N/s)", fixed(1)),
    Column("min_clearance_mm", "min clearance (mm)", fixed(1)),
    Column("median_s", "median (s)", fixed(3)), Column("first_s", "first call (s)", fixed(2)),
]


def run_tension_motion_benchmark(robot: str = "tdcr2_rao2021", problems: int = 20,
                                 waypoints: int = 100, repeats: int = 3, seed: int = 0,
                                 out: str | Path | None = None) -> dict[str, Any]:
    """Both rows (planning and following), printed and written to ``out``."""
    plan = bench_plan(robot, problems, repeats, seed)
    follow = bench_follow(robot, waypoints, repeats)
    env = environment()
    report = (f"## Tension-space planning and following under load, {robot}\n\n"
              "Gravity and a 5 g tip payload, four spheres and boxes; success by the "
              "verdict (fresh statics at every checked sample, python-fcl); steady state is "
              f"the median of {repeats} runs after the first call.\n\n"
              + markdown_table([plan], PLAN_COLUMNS) + "\n\n"
              + markdown_table([follow], FOLLOW_COLUMNS) + "\n\n" + environment_markdown(env))
    write_report("tension", report, out, tables={"plan": [plan], "follow": [follow]},
                 env=env, settings={"robot": robot, "repeats": repeats, "seed": seed})
    return {"plan": plan, "follow": follow}
