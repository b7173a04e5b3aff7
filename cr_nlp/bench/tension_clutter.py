"""Benchmark: the mechanics tasks in clutter under load (issues 51 and 52).

``cr-nlp bench tension --suite clutter`` on ``tdcr2_rao2021`` under gravity and a 5 g tip
payload, in a scene of 14 spheres and 2 boxes placed through the loaded workspace
(``clutter_scene``: centres on the solved backbones of random tension sets, so every
obstacle is somewhere the robot goes). Rows:

One row per mode (penalty; with ``exact`` in the modes, exact: the answers the verdict
rejects polished by Ipopt on the rod's equations):

- IK: ``targets`` tip positions of random tension sets whose backbones are clear, solved
  by ``TensionIKSolver``;
- following: ``paths`` tip paths of ``waypoints`` waypoints, each traced by a smooth
  tension motion that is clear of the scene (verified) and keeps ``rate_fraction`` of the
  tension-rate limit, followed by ``TensionPathFollower``;
- planning: ``problems`` start/goal pairs of clear random tension sets, planned by
  ``TensionTrajectoryPlanner`` and by its search alone (``chain_iterations=0``), with the median
  ratio of the tip paths (fresh statics along each motion) and beside it the median ratio
  of the chord (the straight line between the start's and the goal's tips, which no tip
  path can undercut) to the search's tip path: the ratio's lower bound; and, over the
  plans whose search needed via points, the median share of the search's detour (its tip
  path beyond the chord) the plan removed, (search − plan) / (search − chord).

Success is every task's own verdict (fresh statics, python-fcl); times are the first
call (compiles, pools) and the median of ``repeats`` later calls.
"""

from __future__ import annotations

import dataclasses
import statistics
from pathlib import Path
from typing import Any

import numpy as np

from ..model import load_robot
from ..model.cosserat import solve_statics
from ..model.loads import static_loads
from ._common import Column, environment, environment_markdown, fixed, markdown_table, write_report
from .tension_motion import GRAVITY, PAYLOAD, timed

RATE_MAX = 50.0
"""The tension-rate limit of the following rows, N/s."""
DT = 0.05
"""Seconds between waypoints."""


class CrowdedScene(ValueError):
    """The clutter scene leaves the robot too few clear equilibria to draw the benchmark's
    tension sets from (``cr-nlp bench`` prints it as one line)."""


def clutter_scene(robot: Any, seed: int = 0, spheres: int = 14, boxes: int = 2) -> dict:
    """A scene dict of ``spheres`` spheres (radius 10–16 mm) and ``boxes`` boxes (20–40 mm)
    centred on points of the loaded robot's workspace (backbones of random tension sets
    under gravity and the payload, m). An obstacle that would leave less than
    ``CLEAR_SHARE`` of the loaded backbones the benchmark draws from clear of the scene
    (δ = ``MARGIN``) moves to another point, drawn from a second generator: on a short
    robot whose segments bend from the base, obstacles near the base touched every
    backbone. Where none moves (``tdcr2_rao2021``'s scenes), the scene is the first
    generator's draws alone.

    Raises:
        CrowdedScene: no point of the workspace leaves ``CLEAR_SHARE`` of the backbones
            clear (naming the robot and the obstacle)."""
    from ..stages.explore import random_tensions

    rng = np.random.default_rng(seed)
    solved = solve_statics(robot, random_tensions(robot, 256, seed), PAYLOAD, None, GRAVITY)
    points = np.asarray(solved.positions)[solved.converged][:, 4:].reshape(-1, 3)
    centres = points[rng.choice(len(points), spheres + boxes, replace=False)]
    obstacles = [{"name": f"ball_{i}", "type": "sphere", "center": c.tolist(),
                  "radius": float(rng.uniform(0.010, 0.016))}
                 for i, c in enumerate(centres[:spheres])]
    obstacles += [{"name": f"box_{i}", "type": "box", "center": c.tolist(),
                   "size": rng.uniform(0.02, 0.04, 3).tolist()}
                  for i, c in enumerate(centres[spheres:])]
    # The backbones ``clear_tensions`` draws from (its scale), other tension sets.
    drawn = solve_statics(robot, 0.6 * random_tensions(robot, 256, seed + 1), PAYLOAD, None,
                          GRAVITY)
    backbones = np.asarray(drawn.positions)[drawn.converged]
    moves = np.random.default_rng([seed, 1])
    clear = np.ones(len(backbones), dtype=bool)
    for obstacle in obstacles:
        for _ in range(100):
            kept = clear & ~_touching(robot, backbones, obstacle)
            if kept.mean() >= CLEAR_SHARE:
                break
            obstacle["center"] = points[moves.integers(len(points))].tolist()
        else:
            raise CrowdedScene(f"clutter scene: no point of {robot.name}'s loaded workspace "
                             f"for {obstacle['name']} leaves {CLEAR_SHARE:.0%} of its "
                             "backbones clear")
        clear = kept
    return {"obstacles": obstacles}


CLEAR_SHARE = 0.25
"""The share of loaded backbones (tension sets as ``clear_tensions`` draws them) a clutter
scene leaves clear at least (``tdcr2_rao2021``'s scenes of seeds 0–3: 0.37–0.79)."""
MARGIN = 0.002
"""δ of the clutter scene's share of clear backbones, m (the planners' default)."""


def _touching(robot: Any, backbones: np.ndarray, obstacle: dict) -> np.ndarray:
    """(B,) True where a backbone (points (B, k, 3), m; the robot's backbone radius around
    them) comes within ``MARGIN`` of the obstacle (a scene dict's sphere or box)."""
    gap = backbones - np.asarray(obstacle["center"])
    if obstacle["type"] == "sphere":
        apart = np.linalg.norm(gap, axis=-1) - obstacle["radius"]
    else:
        outside = np.maximum(np.abs(gap) - 0.5 * np.asarray(obstacle["size"]), 0.0)
        apart = np.linalg.norm(outside, axis=-1)
    return apart.min(axis=1) < robot.backbone_radius + MARGIN


def clear_tensions(follower: Any, count: int, rng: np.random.Generator,
                   rounds: int = 20) -> np.ndarray:
    """(count, n) random tension sets whose equilibria keep δ from the scene, N.

    Raises:
        CrowdedScene: ``rounds`` batches of 4·count candidates found fewer (the scene
            leaves the robot almost no clear equilibrium; naming how many were found)."""
    from ..stages.explore import random_tensions
    from ..tasks.mechanics.trajectory import TensionTrajectoryPlanner

    loads = static_loads(1, follower.ik.length, PAYLOAD, None, GRAVITY)
    screen = TensionTrajectoryPlanner(follower.robot, follower.scene)
    found: list[np.ndarray] = []
    for _ in range(rounds):
        candidates = 0.6 * random_tensions(follower.robot, 4 * count,
                                           int(rng.integers(1 << 30)))
        found.append(candidates[screen.clear(candidates, loads)])
        if sum(len(f) for f in found) >= count:
            return np.concatenate(found)[:count]
    have = sum(len(f) for f in found)
    raise CrowdedScene(f"clutter benchmark: {have} of {rounds * 4 * count} random tension sets "
                     f"of {follower.robot.name} keep δ from the scene under the load, "
                     f"{count} wanted")


def clear_motions(follower: Any, count: int, waypoints: int, rate_fraction: float,
                  rng: np.random.Generator, tries: int = 40) -> list[np.ndarray]:
    """Up to ``count`` smooth tension motions (waypoints, n) N that the verdict accepts
    (clear, rate within ``rate_fraction`` of ``RATE_MAX``): each a loop through two clear
    tension sets, scaled in time to the rate."""
    loads = static_loads(1, follower.ik.length, PAYLOAD, None, GRAVITY)
    ends = clear_tensions(follower, 2 * tries, rng)
    t = np.linspace(0.0, 1.0, waypoints)[:, None]
    motions = []
    for k in range(tries):
        a, b = ends[2 * k], ends[2 * k + 1]
        motion = a + (b - a) * 0.5 * (1 - np.cos(2 * np.pi * t))     # out and back
        step = np.max(np.abs(np.diff(motion, axis=0)))
        if step / DT > rate_fraction * RATE_MAX:
            motion = a + (motion - a) * rate_fraction * RATE_MAX * DT / step
        if follower.verify_tensions(motion, DT, loads).success:
            motions.append(motion)
        if len(motions) == count:
            break
    return motions


def bench_ik(robot: Any, scene: dict, targets: int, modes: list[str], repeats: int,
             follower: Any, rng: np.random.Generator) -> list[dict[str, Any]]:
    """IK rows, one per mode."""
    from ..tasks.mechanics.ik import TensionIKSolver

    tips = solve_statics(robot, clear_tensions(follower, targets, rng), PAYLOAD, None,
                         GRAVITY).tip_position
    solver = TensionIKSolver(robot, scene)
    rows = []
    for mode in modes:
        result, first, median = timed(
            lambda mode=mode: solver.solve(tips, None, PAYLOAD, None, GRAVITY,
                                           exact=mode == "exact"), repeats)
        ok = result.success
        rows.append({"mode": mode, "targets": len(tips), "success_pct": 100.0 * ok.mean(),
                     "polished": int(sum(s == "polish" for s in result.stage)),
                     "max_violation": float(np.nanmax(result.max_violation)),
                     "min_clearance_mm": 1e3 * float(np.min(result.min_clearance)),
                     "first_s": first, "median_s": median,
                     "per_1000_s": 1000.0 * median / max(len(tips), 1)})
    return rows


def bench_follow(follower: Any, motions: list[np.ndarray], repeats: int,
                 mode: str = "penalty") -> dict[str, Any]:
    """The following row of one mode: every path traced by a clear, rate-feasible motion
    (``exact``: the motions the verdict rejects polished by Ipopt)."""
    paths = [solve_statics(follower.robot, m, PAYLOAD, None, GRAVITY).tip_position
             for m in motions]
    results, firsts, medians = [], [], []
    for path in paths:
        result, first, median = timed(
            lambda path=path: follower.follow(path, dt=DT, gravity=GRAVITY, tip_force=PAYLOAD,
                                              exact=mode == "exact"), repeats)
        results.append(result)
        firsts.append(first)
        medians.append(median)
    rate = max(float(np.max(np.abs(np.diff(r.tensions, axis=0)))) / DT for r in results)
    return {"mode": mode, "paths": len(paths), "waypoints": len(paths[0]) if paths else 0,
            "verified": sum(bool(r.success) for r in results),
            "polished": sum(r.stage.value == "polish" for r in results),
            "max_error_mm": 1e3 * max(float(np.max(r.position_error)) for r in results),
            "max_rate_n_s": rate,
            "min_clearance_mm": 1e3 * min(r.min_clearance for r in results),
            "median_s": statistics.median(medians) if medians else 0.0,
            "polish_median_s": statistics.median(r.timing.polish for r in results),
            "polish_s": max(r.timing.polish for r in results),
            "first_s": max(firsts) if firsts else 0.0,
            "stages": ", ".join(sorted({r.stage.value for r in results}))}


def bench_plan(robot: Any, scene: dict, problems: int, repeats: int, follower: Any,
               rng: np.random.Generator, modes: tuple[str, ...] = ("penalty",),
               polish_accepted: bool = False) -> list[dict[str, Any]]:
    """The planning rows, one per mode: plans against the search's on the same problems
    (``exact``: the motions the verdict rejects polished by Ipopt; with
    ``polish_accepted`` every motion)."""
    from ..tasks.mechanics.trajectory import TensionTrajectoryPlanner

    ends = clear_tensions(follower, 2 * problems, rng)
    starts, goals = ends[:problems], ends[problems:]
    planner = TensionTrajectoryPlanner(robot, scene)
    exact = TensionTrajectoryPlanner(robot, scene, dataclasses.replace(
        planner.config, polish_accepted=polish_accepted))
    search = TensionTrajectoryPlanner(robot, scene, dataclasses.replace(planner.config,
                                                              chain_iterations=0))
    loads = static_loads(1, planner.length, PAYLOAD, None, GRAVITY)
    searched = search.plan(starts, goals, gravity=GRAVITY, tip_force=PAYLOAD)
    rows = []
    for mode in modes:
        runner = exact if mode == "exact" else planner
        results, first, median = timed(
            lambda mode=mode, runner=runner: runner.plan(
                starts, goals, gravity=GRAVITY, tip_force=PAYLOAD, exact=mode == "exact"),
            repeats)
        pairs = [(r, s) for r, s in zip(results, searched, strict=True)
                 if r.success and s.success]
        search_path = [planner.tip_path(s.tensions, loads) for _, s in pairs]
        ratio = [planner.tip_path(r.tensions, loads) / length
                 for (r, _), length in zip(pairs, search_path, strict=True)]
        # no tip path is shorter than the straight line between its two ends
        chord = [planner.tip_path(s.tensions[[0, -1]], loads, samples=2) / length
                 for (_, s), length in zip(pairs, search_path, strict=True)]
        # where the search needed via points: the share of its detour (its tip path
        # beyond the chord) that the plan removed
        detour = [(1.0 - a) / (1.0 - c) for a, c, (_, s) in zip(ratio, chord, pairs,
                                                                strict=True)
                  if s.notes[0] != "direct leg" and c < 1.0]
        rows.append({
            "mode": mode, "problems": problems,
            "success_pct": 100.0 * np.mean([r.success for r in results]),
            "search_success_pct": 100.0 * np.mean([s.success for s in searched]),
            "refined_pct": 100.0 * np.mean([r.stage.value == "refine" for r in results]),
            "polished": sum(r.stage.value == "polish" for r in results),
            "tip_path_ratio": statistics.median(ratio) if ratio else float("nan"),
            "chord_ratio": statistics.median(chord) if chord else float("nan"),
            "detour_removed": statistics.median(detour) if detour else float("nan"),
            "min_clearance_mm": 1e3 * min(r.min_clearance for r in results),
            "polish_s": max(r.timing.polish for r in results),
            "per_problem_s": median / max(problems, 1), "first_s": first})
    return rows


IK_COLUMNS = [
    Column("mode", "mode"), Column("targets", "targets"),
    Column("success_pct", "verified (%)", fixed(1)), Column("polished", "polished"),
    Column("max_violation", "max violation", lambda v: f"{v:.1e}"),
    Column("min_clearance_mm", "min clearance (mm)", fixed(1)),
    Column("per_1000_s", "s per 1000 targets", fixed(2)),
    Column("first_s", "first call (s)", fixed(1)),
]
FOLLOW_COLUMNS = [
    Column("mode", "mode"), Column("paths", "paths"), Column("waypoints", "waypoints"),
    Column("verified", "verified"), Column("polished", "polished"),
    Column("max_error_mm", "max error (mm)", fixed(4)),
    Column("max_rate_n_s", f"max rate (N/s, limit {RATE_MAX:g})", fixed(1)),
    Column("min_clearance_mm", "min clearance (mm)", fixed(1)),
    Column("median_s", "median s per path", fixed(2)),
    Column("polish_median_s", "median polish (s)", fixed(1)),
    Column("polish_s", "largest polish (s)", fixed(1)),
    Column("first_s", "first call (s)", fixed(1)), Column("stages", "stage"),
]
PLAN_COLUMNS = [
    Column("mode", "mode"), Column("problems", "problems"),
    Column("success_pct", "verified (%)", fixed(1)),
    Column("search_success_pct", "search alone (%)", fixed(1)),
    Column("refined_pct", "refined kept (%)", fixed(1)), Column("polished", "polished"),
    Column("tip_path_ratio", "median tip path / search's", fixed(2)),
    Column("chord_ratio", "its bound: median chord / search's", fixed(2)),
    Column("detour_removed", "via plans: median share of the detour removed", fixed(2)),
    Column("min_clearance_mm", "min clearance (mm)", fixed(1)),
    Column("polish_s", "largest polish (s)", fixed(1)),
    Column("per_problem_s", "s per problem", fixed(3)),
    Column("first_s", "first call (s)", fixed(1)),
]


def run_tension_clutter_benchmark(robot: str = "tdcr2_rao2021", targets: int = 200,
                                  paths: int = 6, waypoints: int = 60, problems: int = 20,
                                  modes: tuple[str, ...] = ("penalty",), repeats: int = 2,
                                  seed: int = 0, rate_fraction: float = 0.7,
                                  polish_accepted: bool = False,
                                  out: str | Path | None = None) -> dict[str, Any]:
    """All three rows in the clutter scene, printed and written to ``out``
    (``polish_accepted``: exact mode polishes every motion, the ones the verdict accepts
    too, timing the exact stage on each path and plan)."""
    from ..tasks.mechanics.follow import TensionFollowConfig, TensionPathFollower

    rob = load_robot(robot)
    scene = clutter_scene(rob, seed)
    rng = np.random.default_rng(seed)
    follower = TensionPathFollower(rob, scene, TensionFollowConfig(tension_rate_max=RATE_MAX))
    motions = clear_motions(follower, paths, waypoints, rate_fraction, rng)
    ik = bench_ik(rob, scene, targets, list(modes), repeats, follower, rng)
    exact = TensionPathFollower(rob, scene, dataclasses.replace(
        follower.config, polish_accepted=polish_accepted))
    follow = [bench_follow(exact if mode == "exact" else follower, motions, repeats, mode)
              for mode in modes]
    plan = bench_plan(rob, scene, problems, repeats, follower, rng, tuple(modes),
                      polish_accepted)
    env = environment()
    report = (f"## Mechanics tasks in clutter under load, {robot}\n\n"
              f"Gravity and a 5 g tip payload, {len(scene['obstacles'])} spheres and boxes "
              "through the loaded workspace (seed "
              f"{seed}); success by each task's verdict (fresh statics, python-fcl); steady "
              f"state is the median of {repeats} runs after the first call.\n\n"
              + markdown_table(ik, IK_COLUMNS) + "\n\n"
              + markdown_table(follow, FOLLOW_COLUMNS) + "\n\n"
              + markdown_table(plan, PLAN_COLUMNS) + "\n\n" + environment_markdown(env))
    write_report("tension_clutter", report, out,
                 tables={"ik": ik, "follow": follow, "plan": plan}, env=env,
                 settings={"robot": robot, "repeats": repeats, "seed": seed,
                           "rate_fraction": rate_fraction,
                           "polish_accepted": polish_accepted})
    return {"ik": ik, "follow": follow, "plan": plan}
