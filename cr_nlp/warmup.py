"""``cr-nlp warmup``: compile a robot's programs ahead, into the cache every later process
reads (a cluster's workers, a CI image, before a demo).

Each task solves small representative problems of the shapes the solvers use: the
programs they trace are stored in ``cache_dir()/programs`` (``cr_nlp._programs``) and
compiled into JAX's cache, roadmaps and seed pools into theirs; a later process of the
same cr_nlp, JAX and device loads them instead of tracing and compiling.

- ``ik``: a one-target batch and a 1000-target batch (both compiled chunk shapes, the
  retry and self-repair programs when some targets need them).
- ``plan`` (needs a scene): a few problems between free configurations (roadmap, LM).
- ``follow``: a path of ``waypoints`` poses from the robot's own forward kinematics (the
  path LM is compiled per waypoint count: give the count your paths have).
- ``statics`` (a robot file with a ``mechanics`` block): the smallest case batch.
With ``exact``, the IK and planning problems are also polished (CasADi's compiled
functions are cached too).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

TASKS = ("ik", "plan", "follow", "statics")
"""Tasks ``warmup`` can compile (the command's choices; this module imports nothing heavy)."""


@dataclass
class WarmupRow:
    """What one task's warm-up did."""

    task: str
    seconds: float
    """Wall seconds the task took."""
    traced: int
    """Programs traced and stored (0: every one was in the cache already)."""
    loaded: int
    """Programs loaded from the cache."""
    note: str = ""


def warm_up(robot: Any, scene: Any = None, tasks: Sequence[str] = ("ik", "plan", "follow"),
            exact: bool = False, waypoints: int = 150, progress: bool = True
            ) -> list[WarmupRow]:
    """Compile ``robot``'s programs (with ``scene``, a ``Scene`` or name, or None) for
    ``tasks``; returns one row per task. A task that does not apply (``plan`` without a
    scene, ``statics`` without a mechanics block) is skipped with a note."""
    from tqdm.auto import tqdm

    from ._programs import stats
    from .model import load_robot
    from .world import load_scene

    robot = load_robot(robot)
    scene = load_scene(scene) if scene is not None else None
    rows = []
    bar = tqdm(list(tasks), desc="cr-nlp warmup", unit="task", disable=not progress)
    for task in bar:
        bar.set_postfix_str(task)
        traced, loaded, t0 = stats.traced, stats.loaded, time.perf_counter()
        note = _WARMERS[task](robot, scene, exact, waypoints)
        rows.append(WarmupRow(task, time.perf_counter() - t0, stats.traced - traced,
                              stats.loaded - loaded, note))
    return rows


def _ik(robot: Any, scene: Any, exact: bool, waypoints: int) -> str:
    from .bench.ik import free_case
    from .tasks.geometry.ik import IKSolver

    solver = IKSolver(robot, scene)
    case = free_case(robot, 1000, seed=0)
    solver.solve(case.positions[:1], case.wxyz[:1], exact=exact)
    solver.solve(case.positions, case.wxyz)
    solver.close()
    return "1 and 1000 targets"


def _plan(robot: Any, scene: Any, exact: bool, waypoints: int) -> str:
    if scene is None:
        return "skipped: planning needs a scene (--scene)"
    from .bench.plan import plan_problems
    from .tasks.geometry.trajectory import TrajectoryConfig, TrajectoryPlanner

    starts, goals = plan_problems(robot, scene, 4, TrajectoryConfig.safety_margin, seed=0)
    planner = TrajectoryPlanner(robot, scene)
    planner.plan(starts, goals, exact=exact)
    return f"{len(starts)} problems"


def _follow(robot: Any, scene: Any, exact: bool, waypoints: int) -> str:
    import numpy as np

    from .model import tip_pose
    from .model.rotations import wxyz_from_matrix
    from .tasks.geometry.follow import PathFollower
    from .tasks.paths import ReferencePath

    lo, hi = robot.q_bounds()
    s = np.linspace(0.0, 1.0, waypoints)[:, None]
    q = lo + (hi - lo) * (0.3 + 0.2 * s)  # a smooth sweep inside the limits
    positions, rotations = tip_pose(robot, q)
    path = ReferencePath("warmup", positions, wxyz_from_matrix(rotations), 0.1,
                         np.ones(waypoints, dtype=bool))
    PathFollower(robot, scene).follow(path)
    return f"{waypoints} waypoints"


def _statics(robot: Any, scene: Any, exact: bool, waypoints: int) -> str:
    if robot.mechanics is None:
        return "skipped: the robot file has no mechanics block"
    import numpy as np

    from .model.cosserat import solve_statics

    solve_statics(robot, np.zeros((1, robot.n_tendons)))
    return "1 case"


_WARMERS = {"ik": _ik, "plan": _plan, "follow": _follow, "statics": _statics}


def format_rows(rows: Sequence[WarmupRow]) -> str:
    """A short table of the rows."""
    lines = [f"{'task':<9}{'seconds':>9}{'traced':>8}{'loaded':>8}  note"]
    lines += [f"{r.task:<9}{r.seconds:>9.1f}{r.traced:>8}{r.loaded:>8}  {r.note}" for r in rows]
    return "\n".join(lines)

