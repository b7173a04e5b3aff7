"""The demo (``run_demo``, ``cr-nlp demo``): the three tasks on the bundled defaults, with a
summary table and figures.

1. IK: the 20 targets of ``models/targets/tdcr3_lattice.json`` for tdcr3 among the 27
   spheres of the lattice scene.
2. Trajectory planning: ``models/problems/tdcr3_shelf_demo.json`` in the shelf scene: the
   tip moves from the top-left compartment to the top-right one, so the motion backs out
   of the shelf, passes the divider and reaches in again.
3. Path following: the letters "ICRA" (``models/paths/icra.json``, 150 waypoints) in the
   ``follow_icra`` scene.

Every task runs in exact mode (Ipopt polish) unless ``--penalty-only`` is given, and every
answer is judged by the independent checks (python-fcl, float64 limits and tendon
limits). Each task's result is written as JSON (and the tendon series as CSV), and one
figure per task as PNG, into ``--out``. The first run compiles the JAX programs (cached on
disk for the next runs: see ``cr_nlp.runtime``).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._files import atomic_open
from ._resources import bundled_file


@dataclass
class DemoRow:
    """One line of the summary table."""

    task: str
    problem: str
    success: str
    accuracy: str
    max_violation: float
    seconds: float
    files: list[str]


def _ik(out: Path, exact: bool) -> DemoRow:
    from .model import load_robot
    from .tasks.geometry.ik import IKSolver
    from .tasks.readers import read_targets
    from .viz import save_figure
    from .world import load_scene

    robot, scene = load_robot("tdcr3"), load_scene("lattice")
    positions, wxyz, _ = read_targets(bundled_file("targets", "tdcr3_lattice"))
    start = time.perf_counter()
    result = IKSolver(robot, scene).solve(positions, wxyz, exact=exact)
    seconds = time.perf_counter() - start
    result.save(out / "ik_result.json")
    from .model.rotations import matrix_from_wxyz

    targets = list(zip(positions, matrix_from_wxyz(wxyz), strict=True))
    save_figure(robot, result.q[0], scene, trajectory=None, targets=targets[:6],
                path=out / "ik.png", title="IK: tdcr3 in the lattice (first answer)")
    summary = result.summary()
    return DemoRow("IK", f"{len(positions)} targets, lattice",
                   f"{int(result.success.sum())}/{len(result)}",
                   f"mean pose error {np.mean(result.pose_error):.1e}",
                   float(summary["max_violation"]), seconds, ["ik_result.json", "ik.png"])


def _plan(out: Path, exact: bool) -> DemoRow:
    from .model.routing import tendon_names
    from .tasks.geometry.trajectory import TrajectoryPlanner
    from .viz import trajectory_figure
    from .viz._figures import write_figure

    (problem,) = json.loads(bundled_file("problems", "tdcr3_shelf_demo").read_text())["problems"]
    planner = TrajectoryPlanner("tdcr3", "shelf")
    start = time.perf_counter()
    (result,) = planner.plan([problem["start"]], [problem["goal"]], exact=exact)
    seconds = time.perf_counter() - start
    result.save(out / "plan_result.json")
    files = ["plan_result.json"]
    if result.q is not None:
        result.save_csv(out / "plan_tendons.csv")
        figure = trajectory_figure(
            result, planner.scene, tendon_names(planner.robot),
            title=f"shelf: {result.stage_text}, {result.path_length:.2f} m tip path")
        write_figure(figure, out / "plan.png", dpi=120)
        files += ["plan_tendons.csv", "plan.png"]
    return DemoRow("plan", "shelf, compartment to compartment", "yes" if result.success else
                   f"no ({result.reason})", f"tip path {result.path_length:.2f} m",
                   float(result.max_violation), seconds, files)


def _follow(out: Path, exact: bool) -> DemoRow:
    from .model.routing import tendon_names
    from .tasks.geometry.follow import PathFollower
    from .viz import follow_figure
    from .viz._figures import write_figure

    follower = PathFollower("tdcr3", "follow_icra")
    start = time.perf_counter()
    result = follower.follow("icra", exact=exact)
    seconds = time.perf_counter() - start
    result.save(out / "follow_result.json")
    result.save_csv(out / "follow_tendons.csv")
    figure = follow_figure(result, follower.scene, tendon_names(follower.robot),
                           title=f"{result.path.name}: {result.stage_text}")
    write_figure(figure, out / "follow.png", dpi=120)
    err = 1e3 * result.position_error
    return DemoRow("follow", f"'{result.path.name}', {len(err)} waypoints",
                   "yes" if result.success else f"no ({result.reason})",
                   f"position error mean {np.mean(err):.2f} mm, max {np.max(err):.2f} mm",
                   float(result.max_violation), seconds,
                   ["follow_result.json", "follow_tendons.csv", "follow.png"])


TASKS: dict[str, Callable[[Path, bool], DemoRow]] = {"ik": _ik, "plan": _plan,
                                                     "follow": _follow}


def format_table(rows: list[DemoRow]) -> str:
    """The summary as a Markdown table."""
    lines = ["| task | problem | success | accuracy | max violation | time (s, compile included) |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r.task} | {r.problem} | {r.success} | {r.accuracy} | "
              f"{r.max_violation:.1e} | {r.seconds:.1f} |" for r in rows]
    return "\n".join(lines)


def _compile_follow_ahead() -> threading.Thread:
    """Start the follow task's programs compiling on a thread (the ICRA path followed in
    penalty mode, no CasADi), so that they compile beside the IK and planning tasks rather
    than after them; the follow task joins the thread before it runs."""
    from .tasks.geometry.follow import PathFollower

    def run() -> None:
        try:
            PathFollower("tdcr3", "follow_icra").follow("icra")
        except Exception:  # noqa: BLE001, S110 — only a head start: the task itself reports
            pass

    thread = threading.Thread(target=run, name="cr_nlp demo: follow programs", daemon=True)
    thread.start()
    return thread


def run_demo(out: str | Path = "demo_output", exact: bool = True,
             tasks: tuple[str, ...] = tuple(TASKS), progress: bool = True) -> list[DemoRow]:
    """Run the demo tasks, write their files into ``out`` and return the summary rows.

    When following comes after other tasks, its JAX programs compile on a thread beside
    them (a cold first demo on 2 cores: measured in the CHANGELOG)."""
    from tqdm.auto import tqdm

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ahead = (_compile_follow_ahead() if "follow" in tasks and tasks[0] != "follow"
             else None)
    rows = []
    bar = tqdm(tasks, desc="cr-nlp demo", unit="task", disable=not progress)
    for name in bar:
        bar.set_postfix_str(name)
        if name == "follow" and ahead is not None:
            ahead.join()
        rows.append(TASKS[name](out, exact))
    with atomic_open(out / "summary.md") as handle:
        handle.write(format_table(rows) + "\n")
    return rows
