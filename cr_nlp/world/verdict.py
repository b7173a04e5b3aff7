"""The one success rule of every task and both modes (docs/design.md §1).

An answer is a success if and only if

- its pose error, re-evaluated in float64, is below the task's tolerance (IK, path
  following), and
- every independently re-evaluated violation is at most ``VIOLATION_TOLERANCE``:
  configuration ``limits`` (rad or m), ``clearance`` (m below the safety margin δ, the
  distance to the nearest obstacle by python-fcl), ``self_clearance`` (m below δ, the
  distance between segments at least two apart, ``world.check``), ``tendon_speed``
  (m/s), ``tendon_accel`` (m/s²).

Self-clearance is part of the rule in every task, with or without a scene, unless the
robot file says ``"self_collision": false``. A python-fcl collision is a shortfall of at
least δ, so it fails the same rule; the reason names it as a collision (with an
obstacle, or of the robot with itself). ``judge`` decides one answer, ``judge_many`` a
batch (the same rule, vectorised; failing rows get ``judge``'s words). The penalty
stages, the exact polish and every benchmark row are judged by these functions alike,
so "exact" can only add successes, never redefine them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

VIOLATION_TOLERANCE = 1e-6
"""Largest violation (rad, m, m/s or m/s², per family) a success may have."""

UNITS = {
    "limits": "rad or m",
    "clearance": "m below the safety margin",
    "self_clearance": "m below the safety margin",
    "tendon_speed": "m/s",
    "tendon_accel": "m/s²",
    "tension_rate": "N/s",
}
"""The violation families and the unit each is measured in."""

_NAMES = {
    "limits": "a configuration limit",
    "clearance": "the clearance",
    "self_clearance": "the self-clearance",
    "tendon_speed": "the tendon speed limit",
    "tendon_accel": "the tendon acceleration limit",
    "tension_rate": "the tension rate limit",
}


@dataclass(frozen=True)
class Verdict:
    """The verdict on one answer (configuration, trajectory or path), from numbers
    re-evaluated independently of the optimiser that produced it. Picklable (it travels
    with results from worker processes)."""

    success: bool
    """Pose error below the tolerance (where there is a target) and every violation at
    most ``VIOLATION_TOLERANCE``."""
    reason: str
    """"" on success, else every failed check and by how much."""
    pose_error: float | None
    """‖log(T_tip⁻¹·T_target)‖ (mixed m/rad), None when the task has no target pose."""
    violations: Mapping[str, float]
    """Largest violation per family (``UNITS``): always ``limits``, ``clearance`` and
    ``self_clearance``; ``tendon_speed``/``tendon_accel`` where the task has them."""
    max_violation: float
    """The largest of ``violations`` (their mixed units)."""
    min_clearance: float
    """Smallest signed distance to any obstacle (m, python-fcl); +inf without obstacles."""
    self_clearance: float
    """Smallest signed distance between segments at least two apart (m, closed-form
    capsule distance of ``world.check``); +inf when not checked (fewer than three
    segments, or ``"self_collision": false``)."""


def describe_violations(violations: Mapping[str, float],
                        tolerance: float = VIOLATION_TOLERANCE) -> str:
    """The families over ``tolerance``, each with its amount and unit ("" if none), e.g.
    "breaks a configuration limit by 3.2e-05 rad or m"."""
    return "; ".join(f"breaks {_NAMES.get(name, name)} by {value:.3g} {UNITS.get(name, '')}"
                     .rstrip()
                     for name, value in violations.items() if value > tolerance)


def failure_reason(violations: Mapping[str, float], *, pose_error: float | None = None,
                   pose_tolerance: float | None = None, min_clearance: float | None = None,
                   collision_where: str = "", self_clearance: float | None = None,
                   tolerance: float = VIOLATION_TOLERANCE) -> str:
    """Why an answer is not a success, "" when it is (the rule of this module).

    Args:
        violations: the largest violation per family (see ``UNITS``), independently
            re-evaluated.
        pose_error: float64 pose error ‖log(T_tip⁻¹·T_target)‖ (mixed m/rad), or None
            when the task has no target pose.
        pose_tolerance: the success tolerance on ``pose_error``.
        min_clearance: the smallest python-fcl distance to an obstacle (m); negative (or
            0) means a collision, reported as such.
        collision_where: words placing the collision ("at t = 0.4 s"), optional.
        self_clearance: the smallest distance (m) between segments at least two apart;
            negative means the robot passes through itself, reported as such.
        tolerance: ``VIOLATION_TOLERANCE`` unless a caller deliberately differs.
    """
    reasons = []
    if pose_error is not None and pose_tolerance is not None and not pose_error < pose_tolerance:
        reasons.append(f"pose error {pose_error:.3g} ≥ {pose_tolerance:g} (target possibly "
                       "unreachable with this robot's limits)")
    rest = dict(violations)
    where = f" {collision_where}" if collision_where else ""
    if min_clearance is not None and min_clearance <= 0.0:
        reasons.append(f"in collision by python-fcl{where} (distance {min_clearance:.4g} m)")
        rest.pop("clearance", None)
    if self_clearance is not None and self_clearance < 0.0:
        reasons.append(f"in self-collision{where}: segments at least two apart overlap by "
                       f"{-self_clearance:.4g} m")
        rest.pop("self_clearance", None)
    text = describe_violations(rest, tolerance)
    if text:
        reasons.append(text)
    return "; ".join(reasons)


def _pose_passes(pose_error: Any, pose_tolerance: float | None) -> Any:
    """pose error < tolerance (NaN fails), True where there is no tolerance."""
    if pose_tolerance is None:
        return True
    with np.errstate(invalid="ignore"):
        return np.asarray(pose_error, dtype=float) < pose_tolerance


def judge(*, margin: float, limits: float = 0.0, min_clearance: float = math.inf,
          self_clearance: float = math.inf, pose_error: float | None = None,
          pose_tolerance: float | None = None, tendon_speed: float | None = None,
          tendon_accel: float | None = None, collision_where: str = "",
          tolerance: float = VIOLATION_TOLERANCE) -> Verdict:
    """The verdict on one answer from independently re-evaluated numbers.

    Args:
        margin: δ, metres: the clearance every answer keeps from obstacles and between
            segments at least two apart.
        limits: largest configuration-limit violation (rad or m), ≥ 0.
        min_clearance: smallest python-fcl distance to an obstacle (m); +inf: none.
        self_clearance: smallest distance between segments at least two apart (m);
            +inf: not checked.
        pose_error: float64 pose error (mixed m/rad), None without a target pose.
        pose_tolerance: success tolerance on ``pose_error``.
        tendon_speed, tendon_accel: how far the largest tendon speed (m/s) and
            acceleration (m/s²) exceed the robot's limits (≥ 0), None when the task has
            no motion.
        collision_where: words placing a collision in a motion ("at t = 0.4 s").
        tolerance: ``VIOLATION_TOLERANCE`` unless a caller deliberately differs.
    """
    violations = {"limits": max(float(limits), 0.0),
                  "clearance": max(margin - float(min_clearance), 0.0),
                  "self_clearance": max(margin - float(self_clearance), 0.0)}
    if tendon_speed is not None:
        violations["tendon_speed"] = max(float(tendon_speed), 0.0)
    if tendon_accel is not None:
        violations["tendon_accel"] = max(float(tendon_accel), 0.0)
    reason = failure_reason(violations, pose_error=pose_error, pose_tolerance=pose_tolerance,
                            min_clearance=float(min_clearance),
                            self_clearance=float(self_clearance),
                            collision_where=collision_where, tolerance=tolerance)
    passes = (bool(_pose_passes(pose_error, pose_tolerance))
              and all(v <= tolerance for v in violations.values()))   # NaN fails
    if not passes and not reason:
        reason = f"not a number among the pose error {pose_error} and {violations}"
    return Verdict(success=not reason, reason=reason,
                   pose_error=None if pose_error is None else float(pose_error),
                   violations=dict(violations),
                   max_violation=max(violations.values()),
                   min_clearance=float(min_clearance), self_clearance=float(self_clearance))


@dataclass(frozen=True)
class Verdicts:
    """``judge`` over a batch of B answers: arrays of shape (B,)."""

    success: np.ndarray
    """bool."""
    reason: tuple[str, ...]
    """"" on success, else ``judge``'s words."""
    violations: Mapping[str, np.ndarray]
    """Per family (``limits``, ``clearance``, ``self_clearance``), as in ``Verdict``."""
    max_violation: np.ndarray
    """The largest of ``violations`` per answer."""


def judge_many(*, margin: float, limits: Any, min_clearance: Any = None,
               self_clearance: Any = None, pose_error: Any = None,
               pose_tolerance: float | None = None,
               tolerance: float = VIOLATION_TOLERANCE) -> Verdicts:
    """``judge`` for B answers at once (IK batches): the passing case vectorised, every
    failing row worded by ``judge`` (so both always agree).

    Args:
        margin: δ, metres.
        limits: (B,) largest limit violations (rad or m).
        min_clearance: (B,) python-fcl obstacle distances (m), None: no obstacles.
        self_clearance: (B,) distances between segments at least two apart (m), None:
            not checked.
        pose_error: (B,) float64 pose errors, None without target poses.
        pose_tolerance: success tolerance on ``pose_error``.
        tolerance: ``VIOLATION_TOLERANCE`` unless a caller deliberately differs.
    """
    limits = np.maximum(np.asarray(limits, dtype=float).reshape(-1), 0.0)
    count = len(limits)
    inf = np.full(count, np.inf)
    obstacle = inf if min_clearance is None else np.asarray(min_clearance, float).reshape(-1)
    own = inf if self_clearance is None else np.asarray(self_clearance, float).reshape(-1)
    with np.errstate(invalid="ignore"):
        violations = {"limits": limits, "clearance": np.maximum(margin - obstacle, 0.0),
                      "self_clearance": np.maximum(margin - own, 0.0)}
        worst = np.max(np.stack(list(violations.values())), axis=0)
        passing = worst <= tolerance                     # NaN fails
        if pose_error is not None:
            passing &= _pose_passes(pose_error, pose_tolerance)
    reasons = [""] * count
    errors = None if pose_error is None else np.asarray(pose_error, float).reshape(-1)
    for i in np.flatnonzero(~passing).tolist():
        reasons[i] = judge(margin=margin, limits=limits[i], min_clearance=obstacle[i],
                           self_clearance=own[i],
                           pose_error=None if errors is None else errors[i],
                           pose_tolerance=pose_tolerance, tolerance=tolerance).reason
    return Verdicts(success=passing, reason=tuple(reasons),
                    violations=dict(violations), max_violation=worst)
