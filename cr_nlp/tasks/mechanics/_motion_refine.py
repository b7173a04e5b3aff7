"""The refine stage of tension-space planning (``trajectory.TensionTrajectoryPlanner``): the
banded LM on a whole motion, and the mending of a refined motion the verdict rejects.

The LM has rows at the waypoints only (each one's equilibrium and backbone clearance),
while the verdict also checks ``samples_between`` interpolated tension sets between each
pair: a refined motion that shortens the tip's path can cut through an obstacle between
two clear waypoints. ``mended`` then makes the checked samples of the failing steps
waypoints (the same tension path, more waypoints, so the LM has rows where the verdict
found the collision), runs the LM again, and, where that is still rejected, tries motions
part of the way from the searched motion to the refined one.

Units: newtons, metres, seconds.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ...model import Robot
from ...model.cosserat import solve_statics
from ...model.loads import StaticLoads
from ...stages.refine import (
    LMConfig,
    MotionTerms,
    TensionTerms,
    base_frame,
    solve_motion,
    tensions_of_unknowns,
    unknowns_of,
    waypoint_params,
)
from ...world.clearance import scene_arrays
from ...world.scene import Scene
from ._motion import TensionMotionVerification, interpolated


def refine_chain(robot: Robot, scene: Scene | None, config: Any, tensions: np.ndarray,
                 iterations: int, *, loads: StaticLoads) -> np.ndarray:
    """``iterations`` of the banded LM on the motion (T, n) N as it is (its waypoints
    kept, the first and last fixed) under the planner's ``config``
    (``TensionTrajectoryConfig``: weights, δ, rate): each waypoint's equilibrium and
    backbone clearance, between neighbours the tip's step, a smoothness term and the
    tension-rate hinge (``stages.refine``'s ``solve_motion``); returns (T, n) N."""
    cfg = config
    count = len(tensions)
    every = loads.rows(np.zeros(count, int))
    solved = solve_statics(robot, tensions, every.tip_force, every.tip_moment, every.gravity,
                           cfg.statics, distributed_force=every.distributed_force,
                           point_loads=every.point_load_lists())
    tips = np.asarray(solved.tip_position)
    shoot, params, _ = waypoint_params(robot, tips, np.full((count, 4), np.nan), every,
                                       tip_weight=0.0)
    arrays = (None if scene is None or not scene.parts
              else scene_arrays(scene, as_numpy=True))
    waypoint = TensionTerms(robot, cfg.statics, shoot,
                            clearance_weight=0.0 if arrays is None else cfg.clearance_weight,
                            clearance_band=cfg.safety_margin + cfg.clearance_buffer,
                            self_weight=cfg.clearance_weight if robot.has_self_pairs else 0.0,
                            direct=True)
    terms = MotionTerms(waypoint, rate_step=cfg.rate_margin * cfg.tension_rate_max * cfg.dt,
                        smooth_weight=cfg.smooth_weight, rate_weight=cfg.rate_weight,
                        tip_path_weight=cfg.tip_path_weight)
    z0 = np.concatenate([unknowns_of(waypoint, tensions, base_frame(robot, solved.base_moment)),
                         params.target], axis=1)
    free = np.ones_like(z0)
    free[[0, -1], :waypoint.size] = 0.0      # the start and goal stay as they are
    z, _, _ = solve_motion(terms, z0, params, arrays, free, iterations,
                           LMConfig(jacobian="differences", stall_tolerance=1e-6))
    out = np.array(tensions_of_unknowns(waypoint, z))
    out[0], out[-1] = tensions[0], tensions[-1]
    return out


def mended(config: Any, searched: np.ndarray, tensions: np.ndarray,
           verify: Callable[[np.ndarray], TensionMotionVerification],
           refine: Callable[[np.ndarray, int], np.ndarray]
           ) -> tuple[np.ndarray, TensionMotionVerification, list[str], float]:
    """A refined motion ``tensions`` (T, n) N, mended where ``verify`` rejects it: up to
    ``config.repair_rounds`` times the checked samples of its failing steps become
    waypoints (``with_samples``) and ``refine`` runs ``config.repair_iterations`` LM
    iterations on the whole motion; still rejected, the first of ``config.blends``
    (fractions of the way from ``searched``, resampled, to the refined motion) that
    ``verify`` accepts. Returns (the motion, its verdict, notes saying what ran, seconds
    spent in ``verify``)."""
    seconds, notes = 0.0, []

    def judged(motion: np.ndarray) -> TensionMotionVerification:
        nonlocal seconds
        begin = time.perf_counter()
        report = verify(motion)
        seconds += time.perf_counter() - begin
        return report

    report = judged(tensions)
    for round_ in range(config.repair_rounds):
        if report.success or not len(report.failed_steps):
            break
        tensions = refine(with_samples(tensions, report.failed_steps,
                                       config.samples_between), config.repair_iterations)
        report = judged(tensions)
        notes.append(f"repair {round_ + 1}: the samples the verdict checks on the steps it "
                     "rejected made waypoints, refined again")
    if report.success:
        return tensions, report, notes, seconds
    base = resampled(searched, len(tensions))
    for fraction in config.blends:
        blend = base + fraction * (tensions - base)
        blended = judged(blend)
        if blended.success:
            notes.append(f"{fraction:g} of the way from the searched motion to the refined "
                         f"one (the refined one: {report.reason})")
            return blend, blended, notes, seconds
    return tensions, report, notes, seconds


def with_samples(tensions: np.ndarray, steps: np.ndarray, between: int) -> np.ndarray:
    """The motion (T, n) N with the ``between`` tension sets the verdict checks on each of
    the ``steps`` (k: waypoint k → k + 1; ``_motion.interpolated``) made waypoints: the
    tension path unchanged."""
    samples, at = interpolated(tensions, between)
    keep = np.zeros(len(samples), dtype=bool)
    keep[at] = True
    keep[(at[np.asarray(steps, int)][:, None] + np.arange(1, between + 1)).ravel()] = True
    return samples[keep]


def resampled(tensions: np.ndarray, count: int) -> np.ndarray:
    """The piecewise-linear motion through ``tensions`` (T, n) N at ``count`` waypoints
    evenly spaced in the waypoint index (the same path in tension space, slower)."""
    old = np.linspace(0.0, 1.0, len(tensions))
    new = np.linspace(0.0, 1.0, count)
    return np.stack([np.interp(new, old, column) for column in tensions.T], axis=1)
