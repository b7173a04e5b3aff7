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
from functools import partial
from typing import Any

import jax
import numpy as np

from ...model import Robot
from ...model.cosserat import solve_statics
from ...model.loads import StaticLoads
from ...stages.refine import (
    LMConfig,
    MotionTerms,
    TensionTerms,
    base_frame,
    solve_motions,
    tensions_of_unknowns,
    unknowns_of,
    waypoint_params,
)
from ...world.clearance import scene_arrays
from ...world.scene import Scene
from .._timing import StageTiming
from ._motion import TensionMotionVerification, interpolated


def refine_chain(robot: Robot, scene: Scene | None, config: Any, tensions: np.ndarray,
                 iterations: int, *, loads: StaticLoads) -> np.ndarray:
    """``iterations`` of the banded LM on the motion (T, n) N as it is (its waypoints
    kept, the first and last fixed) under the planner's ``config``
    (``TensionTrajectoryConfig``: weights, δ, rate): each waypoint's equilibrium and
    backbone clearance, between neighbours the tip's step, a smoothness term and the
    tension-rate hinge (``stages.refine``'s ``solve_motion``); returns (T, n) N."""
    return refine_chains(robot, scene, config, [tensions], iterations, loads=loads)[0]


def refine_chains(robot: Robot, scene: Scene | None, config: Any, motions: list[np.ndarray],
                  iterations: int, *, loads: StaticLoads) -> list[np.ndarray]:
    """``refine_chain`` of several motions (each (T_i, n) N), in order, each refined as
    it is alone: one statics solve for every waypoint's start, one vmapped LM per padded
    length (``stages.refine``'s ``solve_motions``)."""
    if not motions:
        return []
    cfg = config
    tensions = np.concatenate(motions)
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
    bounds = np.cumsum([0, *(len(m) for m in motions)])
    pieces = list(zip(bounds[:-1], bounds[1:], strict=True))
    frees = []
    for a, b in pieces:
        free = np.ones_like(z0[a:b])
        free[[0, -1], :waypoint.size] = 0.0      # the start and goal stay as they are
        frees.append(free)
    answers = solve_motions(
        terms, [z0[a:b] for a, b in pieces],
        [jax.tree_util.tree_map(lambda x, a=a, b=b: np.asarray(x)[a:b], params)
         for a, b in pieces], arrays, frees, iterations,
        LMConfig(jacobian="differences", stall_tolerance=1e-6))
    out = []
    for motion, (z, _, _) in zip(motions, answers, strict=True):
        refined = np.array(tensions_of_unknowns(waypoint, z))
        refined[0], refined[-1] = motion[0], motion[-1]
        out.append(refined)
    return out


Mended = tuple[np.ndarray, TensionMotionVerification, list[str]]
"""A mended motion (T, n) N, its verdict, and notes saying what ran."""


def mended(config: Any, searched: list[np.ndarray], motions: list[np.ndarray],
           verify: Callable[[list[np.ndarray]], list[TensionMotionVerification]],
           refine: Callable[[list[np.ndarray], int], list[np.ndarray]]
           ) -> tuple[list[Mended], float]:
    """Refined motions (each (T, n) N), each mended where ``verify`` rejects it: up to
    ``config.repair_rounds`` times the checked samples of its failing steps become
    waypoints (``with_samples``) and ``refine`` runs ``config.repair_iterations`` LM
    iterations on the whole motion; still rejected, the first of ``config.blends``
    (fractions of the way from its ``searched`` motion, resampled, to the refined one)
    that ``verify`` accepts. ``verify`` and ``refine`` take lists: each round is one
    batch over the motions that need it. Returns (per motion (the motion, its verdict,
    notes saying what ran), seconds spent in ``verify``)."""
    seconds = 0.0
    motions = list(motions)
    notes: list[list[str]] = [[] for _ in motions]

    def judged(batch: list[np.ndarray]) -> list[TensionMotionVerification]:
        nonlocal seconds
        begin = time.perf_counter()
        reports = verify(batch)
        seconds += time.perf_counter() - begin
        return reports

    reports = judged(motions)
    for round_ in range(config.repair_rounds):
        todo = [i for i, r in enumerate(reports) if not r.success and len(r.failed_steps)]
        if not todo:
            break
        again = refine([with_samples(motions[i], reports[i].failed_steps,
                                     config.samples_between) for i in todo],
                       config.repair_iterations)
        for i, motion, report in zip(todo, again, judged(again), strict=True):
            motions[i], reports[i] = motion, report
            notes[i].append(f"repair {round_ + 1}: the samples the verdict checks on the "
                            "steps it rejected made waypoints, refined again")
    failing = [i for i, r in enumerate(reports) if not r.success]
    blends = []
    for i in failing:
        base = resampled(searched[i], len(motions[i]))
        blends += [(i, fraction, base + fraction * (motions[i] - base))
                   for fraction in config.blends]
    chosen: set[int] = set()
    for (i, fraction, blend), report in zip(blends, judged([b for _, _, b in blends]),
                                            strict=True):
        if report.success and i not in chosen:
            chosen.add(i)
            notes[i].append(f"{fraction:g} of the way from the searched motion to the "
                            f"refined one (the refined one: {reports[i].reason})")
            motions[i], reports[i] = blend, report
    return list(zip(motions, reports, notes, strict=True)), seconds


def refined_plans(planner: Any, planned: list[int], searched: list[Any], loads: StaticLoads,
                  timings: list[StageTiming], judged: Callable[..., Any]
                  ) -> dict[int, tuple[Any, np.ndarray]]:
    """The refine stage of a ``TensionTrajectoryPlanner`` (``planner``): the searched
    motions (``searched``, results) of the problems ``planned`` refined by the banded LM
    (its ``refine_motions``), mended where the verdict rejects them
    (``mended``), each kept where it verifies and is no worse (verified,
    then the shorter tip path), else the search's (``Stage.EXPLORE``, the note says
    why); all problems in one batch per step, their seconds shared evenly in
    ``timings``. ``judged``: the planner's maker of a judged result (problem index,
    start, goal, ends clear, tensions, notes, loads, report=). Per problem: (the result,
    the refined tensions); none without a refine."""
    if planner.config.chain_iterations <= 0 or not planned:
        return {}
    start = time.perf_counter()
    before = [searched[i] for i in planned]
    motions = planner.refine_motions([r.tensions for r in before], loads)
    answers, verify = mended(
        planner.config, [r.tensions for r in before], motions,
        partial(planner.verify_motions, loads=loads),
        partial(refine_chains, planner.robot, planner.scene, planner.config, loads=loads))
    refine = time.perf_counter() - start - verify
    start = time.perf_counter()
    refined = [judged(i, tensions[0], tensions[-1], np.ones(2, bool), tensions,
                      [*searched[i].notes, "refined by the banded LM", *notes], loads,
                      report=report)
               for i, (tensions, report, notes) in zip(planned, answers, strict=True)]
    passed = [k for k, r in enumerate(refined) if r.success]   # the tip paths decide these
    lengths = planner.tip_paths([refined[k].tensions for k in passed]
                                + [before[k].tensions for k in passed], loads)
    paths = {k: (lengths[n], lengths[len(passed) + n]) for n, k in enumerate(passed)}
    verify += time.perf_counter() - start
    out = {}
    for k, i in enumerate(planned):
        timings[i].refine = refine / len(planned)
        timings[i].verify += verify / len(planned)
        result, kept = refined[k], before[k]
        length, shorter = paths.get(k, (np.nan, np.nan))   # measured where it passed
        if result.success and (not kept.success or length <= shorter):
            result.notes.append(f"tip path {1e3 * length:.1f} mm (searched "
                                f"{1e3 * shorter:.1f})")
        else:
            why = (result.reason if not result.success else f"its tip path "
                   f"{1e3 * length:.1f} mm is not shorter than {1e3 * shorter:.1f}")
            kept.notes.append(f"the refined motion was not kept: {why}")
            result = kept
        out[i] = (result, answers[k][0])
    return out


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
