"""``cr-nlp bench follow``: the path-following benchmark of docs/design.md §4 on this machine.

tdcr3 follows the three bundled shapes (``models/paths/{square,sine,icra}.json``, 150
waypoints, Δt = 0.1 s) among the two spheres of their scenes (``follow_square`` …).
Rows: the penalty answer (stages 1–2, JAX) and the exact answer (Ipopt polish). Columns:
per-waypoint position error (mean, std, max; mm) and rotation error (mean, max;
degrees), time per path (median of ``--repeats`` timed runs after a warm-up, compile
apart), collision-free by python-fcl along the whole motion, max violation, and how many
waypoints missed the tolerances.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..tasks.readers import load_path
from ._common import (
    Column,
    environment,
    environment_markdown,
    fixed,
    markdown_table,
    write_report,
)
from .suites import FOLLOW_MODES, FOLLOW_SHAPES

SHAPES, MODES = FOLLOW_SHAPES, FOLLOW_MODES


def measure_follow(follower: Any, shape: str, exact: bool, repeats: int,
                   path: Any = None, dt: float | None = None) -> tuple[dict[str, Any], Any]:
    """One row for a ``PathFollower``: a warm-up run (compilation, Ipopt build; its time
    is "first call"), then ``repeats`` timed runs; the last run's result is judged.
    ``dt``: seconds between waypoints instead of the path file's (a smaller Δt asks the
    tendons to move faster, so that their speed limit binds)."""
    reference = load_path(shape if path is None else path)
    if dt is not None:
        reference = replace(reference, dt=float(dt))
    t0 = time.perf_counter()
    result = follower.follow(reference, exact=exact)
    first = time.perf_counter() - t0
    seconds, polish = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = follower.follow(reference, exact=exact)
        seconds.append(time.perf_counter() - t0)
        polish.append(result.timing.polish)
    pos, rot = 1e3 * result.position_error, np.degrees(result.rotation_error)
    return {
        "shape": reference.name, "mode": "exact" if exact else "penalty",
        "waypoints": len(reference),
        "mean_position_mm": float(np.mean(pos)), "std_position_mm": float(np.std(pos)),
        "max_position_mm": float(np.max(pos)),
        "mean_rotation_deg": float(np.mean(rot)), "max_rotation_deg": float(np.max(rot)),
        "unreached": int(np.sum(~np.asarray(result.reached))),
        "collision_free": bool(result.collision_free),
        "min_clearance_mm": 1e3 * float(result.min_clearance),
        "max_violation": float(result.max_violation),
        "stage": result.stage_text,
        "time_per_path": statistics.median(seconds) if seconds else float("nan"),
        "polish_seconds": statistics.median(polish) if exact and polish else float("nan"),
        "dt": reference.dt,
        "first_call": first,
    }, result


COLUMNS = (
    Column("shape", "shape"), Column("mode", "mode"), Column("dt", "Δt (s)", fixed(2)),
    Column("mean_position_mm", "position mean (mm)", fixed(2)),
    Column("std_position_mm", "position std (mm)", fixed(2)),
    Column("max_position_mm", "position max (mm)", fixed(2)),
    Column("mean_rotation_deg", "rotation mean (°)", fixed(3)),
    Column("max_rotation_deg", "rotation max (°)", fixed(3)),
    Column("unreached", "missed waypoints"),
    Column("collision_free", "collision-free"),
    Column("min_clearance_mm", "min clearance (mm)", fixed(1)),
    Column("max_violation", "max violation"),
    Column("time_per_path", "time/path (s)", fixed(3)),
    Column("polish_seconds", "polish (s)", fixed(3)),
    Column("first_call", "first call (s)", fixed(1)),
    Column("stage", "stage"),
)


def run_follow_benchmark(shapes: Sequence[str] = SHAPES, modes: Sequence[str] = MODES,
                         repeats: int = 3, robot: str = "tdcr3",
                         out: str | Path | None = "bench_results/follow",
                         config: Any = None,
                         progress: bool = True, dt: float | None = None) -> list[dict[str, Any]]:
    """Run the benchmark; returns the rows, prints the Markdown report and, with ``out``,
    writes follow.md, follow.csv and one figure per shape and mode there. A shape is a
    bundled name (its scene is ``follow_<name>``) or a path file (followed without
    obstacles). ``config``: a ``FollowConfig`` (default settings when None). ``dt``:
    seconds between waypoints instead of each path file's."""
    from ..tasks.geometry.follow import FollowConfig, PathFollower

    rows = []
    jobs = [(s, m) for s in shapes for m in modes]
    followers: dict[str, Any] = {}
    for shape, mode in tqdm(jobs, desc="bench follow", unit="row", disable=not progress):
        scene = f"follow_{shape}" if shape in SHAPES else None
        if shape not in followers:
            followers[shape] = PathFollower(robot, scene, config or FollowConfig())
        row, result = measure_follow(followers[shape], shape, mode == "exact", repeats,
                                     dt=dt)
        rows.append(row)
        if out is not None:
            from ..model.routing import tendon_names
            from ..viz import follow_figure
            from ..viz._figures import write_figure

            figure = follow_figure(result, followers[shape].scene,
                                   tendon_names(followers[shape].robot),
                                   title=f"{row['shape']} ({mode}): {result.stage_text}")
            Path(out).mkdir(parents=True, exist_ok=True)
            write_figure(figure, Path(out) / f"{row['shape']}_{mode}.png", dpi=110)
    env = environment()
    write_report("follow", format_report(rows, env, robot, repeats, dt), out, {"follow": rows}, env)
    return rows


def format_report(rows: Sequence[dict[str, Any]], env: dict[str, str], robot: str,
                  repeats: int, dt: float | None = None) -> str:
    """The Markdown report: the table, how it was measured, the environment."""
    return "\n\n".join([
        f"# Path-following benchmark ({robot})",
        markdown_table(rows, COLUMNS),
        "Errors are per waypoint (position: distance of the tip to the reference point; "
        "rotation: angle between the tip frame and the reference frame). collision-free "
        "and min clearance: python-fcl along the interpolated motion; max violation: the "
        "largest of clearance below δ (m), limits, tendon speed (m/s) and acceleration "
        f"(m/s²) over Δt. time/path: median of {repeats} runs after a warm-up; polish: the "
        "exact stage's part of it (0 where the penalty answer already met every "
        "constraint and reached every waypoint: nothing to polish); first call: "
        "the warm-up (compilation or JAX cache load, Ipopt build). Δt: "
        + ("each path file's" if dt is None else f"{dt} s instead of the path files'") + ".",
        "## Environment", environment_markdown(env)])
