"""The one success rule of every task and both modes (DESIGN.md §1).

An answer is a success if and only if

- its pose error, re-evaluated in float64, is below the task's tolerance (IK, path
  following), and
- every independently re-evaluated violation is at most ``VIOLATION_TOLERANCE``:
  configuration ``limits`` (rad or m), ``clearance`` (m below the safety margin δ, from
  python-fcl), ``tendon_speed`` (m/s), ``tendon_accel`` (m/s²).

A python-fcl collision is a clearance shortfall of at least δ, so it fails the same rule;
the reason names it as a collision. The penalty stages and the exact polish are judged by
these functions alike, so "exact" can only add successes, never redefine them.
"""

from __future__ import annotations

from collections.abc import Mapping

VIOLATION_TOLERANCE = 1e-6
"""Largest violation (rad, m, m/s or m/s², per family) a success may have."""

UNITS = {
    "limits": "rad or m",
    "clearance": "m below the safety margin",
    "tendon_speed": "m/s",
    "tendon_accel": "m/s²",
}
"""The violation families and the unit each is measured in."""

_NAMES = {
    "limits": "a configuration limit",
    "clearance": "the clearance",
    "tendon_speed": "the tendon speed limit",
    "tendon_accel": "the tendon acceleration limit",
}


def describe_violations(violations: Mapping[str, float],
                        tolerance: float = VIOLATION_TOLERANCE) -> str:
    """The families over ``tolerance``, each with its amount and unit ("" if none), e.g.
    "breaks a configuration limit by 3.2e-05 rad or m"."""
    return "; ".join(f"breaks {_NAMES.get(name, name)} by {value:.3g} {UNITS.get(name, '')}"
                     .rstrip()
                     for name, value in violations.items() if value > tolerance)


def failure_reason(violations: Mapping[str, float], *, pose_error: float | None = None,
                   pose_tolerance: float | None = None, min_clearance: float | None = None,
                   collision_where: str = "",
                   tolerance: float = VIOLATION_TOLERANCE) -> str:
    """Why an answer is not a success, "" when it is (the rule of this module).

    Args:
        violations: the largest violation per family (see ``UNITS``), independently
            re-evaluated.
        pose_error: float64 pose error ‖log(T_tip⁻¹·T_target)‖ (mixed m/rad), or None
            when the task has no target pose.
        pose_tolerance: the success tolerance on ``pose_error``.
        min_clearance: the smallest python-fcl distance (m); negative (or 0) means a
            collision, reported as such.
        collision_where: words placing the collision ("at t = 0.4 s"), optional.
        tolerance: ``VIOLATION_TOLERANCE`` unless a caller deliberately differs.
    """
    reasons = []
    if pose_error is not None and pose_tolerance is not None and not pose_error < pose_tolerance:
        reasons.append(f"pose error {pose_error:.3g} ≥ {pose_tolerance:g} (target possibly "
                       "unreachable with this robot's limits)")
    rest = dict(violations)
    if min_clearance is not None and min_clearance <= 0.0:
        where = f" {collision_where}" if collision_where else ""
        reasons.append(f"in collision by python-fcl{where} (distance {min_clearance:.4g} m)")
        rest.pop("clearance", None)
    text = describe_violations(rest, tolerance)
    if text:
        reasons.append(text)
    return "; ".join(reasons)
