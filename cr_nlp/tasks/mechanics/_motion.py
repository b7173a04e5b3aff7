"""The verdict of a tension-space motion (``tasks.mechanics.follow``, and any tension
trajectory): the one rule of ``world.verdict`` on numbers re-evaluated independently of
the optimiser.

A motion is tendon tensions τ₀ … τ_{T−1} (N) at waypoints ``dt`` seconds apart; between
two waypoints the tensions move linearly and the robot passes through the quasi-static
equilibria of the interpolated tensions. The check: a fresh forward statics solve
(``model.statics.solve_statics``, its own shooting) at every waypoint and at
``samples_between`` interpolated tensions between each pair, converged everywhere; the
tensions within [0, τ_max]; the tension rates |τₖ₊₁ − τₖ|/dt within ``rate_max``; and,
with a scene, python-fcl clearance of every solved backbone (``world.check.check_chains``)
and its self-clearance at least the safety margin. Units: N, N/s, m, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...model import Robot
from ...model.cosserat import StaticsConfig, StaticsResult, solve_statics
from ...model.loads import StaticLoads
from ...world.check import CheckManyResult, check_chains
from ...world.scene import Scene
from ...world.verdict import VIOLATION_TOLERANCE, failure_reason, judge_many

EXACT_MODE = ("none: no Ipopt stage ran (exact=False; with exact=True the Cosserat tasks "
              "polish on the rod's multiple shooting); every answer is judged by a fresh "
              "forward statics solve and python-fcl")
"""What a tension-space result without exact mode says of it (its ``exact_mode`` field);
a result of exact mode names the formulation instead."""

MOTION_FAMILIES = ("limits", "clearance", "self_clearance", "tension_rate")
"""The violation families of a tension motion: tensions outside [0, τ_max] (N), clearance
and self-clearance below δ (m), tension rate above its limit (N/s)."""


@dataclass(frozen=True)
class TensionMotionVerification:
    """The independent check of a tension motion (``verify_tension_motion``)."""

    success: bool
    """Every sample converged and every violation ≤ ``VIOLATION_TOLERANCE``."""
    reason: str
    """Empty on success, else what failed first (which family, where)."""
    violations: dict[str, float]
    """Per family (``MOTION_FAMILIES``) the largest violation along the motion."""
    max_violation: float
    """The largest of ``violations``."""
    converged: bool
    """Every forward solve (waypoints and samples) converged."""
    min_clearance: float
    """Smallest python-fcl obstacle distance along the motion (inf: no scene), m."""
    clearance: np.ndarray
    """(T,) obstacle distance at each waypoint, m."""
    tip_position: np.ndarray
    """(T, 3) tip of the fresh solve at each waypoint, m."""
    tip_wxyz: np.ndarray
    """(T, 4) its orientation."""
    backbone: np.ndarray
    """(T, P, 3) the solved backbone at each waypoint, base to tip, m."""
    tendon_displacements: np.ndarray
    """(T, n) tendon displacements of the solved shapes, m (pulled > 0)."""
    tension_rate: np.ndarray
    """(T − 1, n) (τₖ₊₁ − τₖ)/dt, N/s."""
    failed_steps: np.ndarray
    """Indices k of the steps (waypoint k → k + 1) that fail: a sample on them (its ends
    included) did not converge or broke a bound, the clearance or the self-clearance, or
    a tendon's rate broke its limit; ascending."""


def interpolated(tensions: np.ndarray, samples_between: int) -> tuple[np.ndarray, np.ndarray]:
    """(samples (T + (T−1)·k, n) N, index of each waypoint among them): the waypoints and
    ``k`` evenly spaced tension sets strictly between each consecutive pair."""
    count = len(tensions)
    fractions = np.arange(samples_between + 1) / (samples_between + 1)
    if count < 2:
        return tensions.copy(), np.arange(count)
    steps = (tensions[:-1, None] + fractions[None, :, None] * np.diff(tensions, axis=0)[:, None])
    samples = np.concatenate([steps.reshape(-1, tensions.shape[1]), tensions[-1:]])
    return samples, np.arange(count) * (samples_between + 1)


def solve_and_check(robot: Robot, scene: Scene | None, samples: np.ndarray,
                    loads: StaticLoads, statics: StaticsConfig | None = None
                    ) -> tuple[StaticsResult, CheckManyResult]:
    """A fresh forward statics solve of every tension set of ``samples`` (k, n) N under
    the one load case ``loads``, and python-fcl on each solved backbone."""
    case = loads.rows(np.zeros(len(samples), int))
    solved = solve_statics(robot, samples, case.tip_force, case.tip_moment, case.gravity,
                           statics or StaticsConfig(),
                           distributed_force=case.distributed_force,
                           point_loads=case.point_load_lists())
    per_segment = (solved.positions.shape[1] - 1) // len(robot.segments)
    return solved, check_chains(robot, scene, solved.positions, per_segment)


def verify_tension_motion(robot: Robot, scene: Scene | None, tensions: np.ndarray, dt: float,
                          loads: StaticLoads, *, margin: float, rate_max: float,
                          samples_between: int = 2,
                          statics: StaticsConfig | None = None
                          ) -> TensionMotionVerification:
    """Check a tension motion independently (see the module's docstring).

    Args:
        robot: a robot with a ``mechanics`` block.
        scene: obstacles, or None.
        tensions: (T, n) tensions at the waypoints, N, the robot file's tendon order.
        dt: seconds between waypoints.
        loads: one load case (``model.loads.static_loads(1, …)``), applied throughout.
        margin: δ, m.
        rate_max: the largest |dτ/dt| per tendon, N/s.
        samples_between: interpolated tension sets checked between waypoints.
        statics: the rod discretisation of the fresh solves (default ``StaticsConfig()``).
    """
    return verify_tension_motions(robot, scene, [tensions], dt, loads, margin=margin,
                                  rate_max=rate_max, samples_between=samples_between,
                                  statics=statics)[0]


def verify_tension_motions(robot: Robot, scene: Scene | None, motions: list[np.ndarray],
                           dt: float, loads: StaticLoads, *, margin: float, rate_max: float,
                           samples_between: int = 2,
                           statics: StaticsConfig | None = None
                           ) -> list[TensionMotionVerification]:
    """``verify_tension_motion`` of several motions (each (T_i, n) N), in order: the
    samples of all of them solved and checked in one batch (a plan's searched and refined
    motions of every problem; each report is the one its motion gets alone)."""
    motions = [np.asarray(m, dtype=float) for m in motions]
    for tensions in motions:
        bad = np.argwhere(~(tensions >= 0.0) | ~np.isfinite(tensions))
        if bad.size:
            k, j = bad[0]
            raise ValueError(f"waypoint {k}: tendon {j + 1}: a tension must be a finite "
                             f"number ≥ 0 N (a tendon pulls), got {tensions[k, j]:g}")
    if not motions:
        return []
    each = [interpolated(tensions, samples_between) for tensions in motions]
    solved, checked = solve_and_check(robot, scene, np.concatenate([s for s, _ in each]),
                                      loads, statics)
    bounds = np.cumsum([0, *(len(s) for s, _ in each)])
    return [_judged(robot, scene, tensions, dt, samples, at, solved, checked,
                    slice(a, b), margin, rate_max, samples_between)
            for tensions, (samples, at), a, b in zip(motions, each, bounds[:-1], bounds[1:],
                                                     strict=True)]


def _judged(robot: Robot, scene: Scene | None, tensions: np.ndarray, dt: float,
            samples: np.ndarray, at: np.ndarray, solved: StaticsResult,
            checked: CheckManyResult, rows: slice, margin: float, rate_max: float,
            samples_between: int) -> TensionMotionVerification:
    """The verdict of one motion from its ``rows`` of a batch's fresh solves and checks."""
    converged_rows = solved.converged[rows]
    obstacle = np.asarray(checked.obstacle_distance[rows], dtype=float)
    own = np.asarray(checked.self_distance[rows], dtype=float)
    tension_max = float(robot.mechanics.tension_max)
    limits = np.maximum(np.max(-samples, axis=1), np.max(samples - tension_max, axis=1))
    verdicts = judge_many(margin=margin, limits=limits,
                          min_clearance=None if scene is None else obstacle,
                          self_clearance=own)
    rate = np.diff(tensions, axis=0) / dt
    violations = {k: float(np.max(v, initial=0.0)) for k, v in verdicts.violations.items()}
    violations["tension_rate"] = float(np.max(np.abs(rate) - rate_max, initial=0.0).clip(0.0))
    worst = max(violations.values())
    converged = bool(converged_rows.all())
    reason = ""
    if not converged:
        bad = int(np.flatnonzero(~converged_rows)[0])
        reason = (f"the forward statics did not converge at sample {bad} (waypoint "
                  f"{bad / (samples_between + 1):.2f})")
    else:
        reason = failure_reason(violations, min_clearance=float(np.min(obstacle,
                                                                       initial=np.inf)),
                                self_clearance=float(np.min(own, initial=np.inf)))
    failed = ~converged_rows | ~(verdicts.max_violation <= VIOLATION_TOLERANCE)
    steps = np.flatnonzero(np.add.reduceat(failed, np.arange(0, len(samples) - 1,
                                                              samples_between + 1))
                           | failed[at[1:]] if len(tensions) > 1 else [])
    steps = np.union1d(steps, np.flatnonzero(np.max(np.abs(rate), axis=1, initial=0.0)
                                             - rate_max > VIOLATION_TOLERANCE))
    waypoints = rows.start + at
    return TensionMotionVerification(
        success=converged and worst <= VIOLATION_TOLERANCE, reason=reason,
        violations=violations, max_violation=worst, converged=converged,
        min_clearance=float(np.min(obstacle, initial=np.inf)), clearance=obstacle[at],
        tip_position=np.array(solved.tip_position[waypoints]),
        tip_wxyz=np.array(solved.tip_wxyz[waypoints]),
        backbone=np.array(solved.positions[waypoints]),
        tendon_displacements=np.array(solved.tendon_displacements[waypoints]),
        tension_rate=rate, failed_steps=steps.astype(int))
