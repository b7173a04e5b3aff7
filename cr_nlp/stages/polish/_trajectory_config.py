"""What a trajectory polish is asked and what it answers: ``TrajectoryPolishConfig`` (its
settings beyond the shared ``NLPSettings``) and ``TrajectoryPolishResult`` (never raised:
a failure is ``success=False``). The polisher is ``stages.polish._trajectory_nlp``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ._ipopt import NLPSettings

OBJECTIVES = ("path", "tracking")


@dataclass(frozen=True)
class TrajectoryPolishConfig(NLPSettings):
    """Settings of the trajectory and path polish (the shared ones: ``NLPSettings``)."""

    max_iter: int = 200
    """Ipopt iterations per attempt (a whole trajectory: more than an IK target's)."""
    near_margin: float = 0.3
    """As ``NLPSettings``; pairs coming closer during the solve trigger a re-selection."""
    max_pairs: int = 8
    """As ``NLPSettings``, per configuration."""
    reselections: int = 4
    """How many times a solve may go on from its answer with re-placed check points and
    re-assigned slots: when a pair without a slot (or a sample without a check point)
    came closer than δ, or the answer stopped at the step limit."""
    step_limit: float = 0.5
    """Per round, every body sphere may move at most about ``step_limit·room`` metres,
    where a waypoint's room is ``near_margin`` or, if larger, the smallest pair distance at
    it and in its two intervals (at most twice ``near_margin``): each of its variables
    stays within that distance divided by its largest lever Σⱼ‖∂c/∂zⱼ‖ (m per rad or m)
    at the round's start; a round stopped by the limit goes on in the next. Pairs farther
    than ``near_margin`` have no rows; without the limit a solve pulled paths straight
    through such obstacles (measured on random_27: 0.2–0.4 m deep). The last round is
    free of it when only the limit stopped the one before."""
    interpolation_checks: int = 3
    """Clearance check points inside each interval, at the ``verify_samples`` samples
    where the motion comes closest to an obstacle (all of them with the default 3 and 4,
    so the polish constrains every configuration the verification checks). Fewer points
    are placed per solve and moved when the answer comes closer elsewhere; measured on
    random_27, one point per interval left 9/10 answers failing at the other samples
    (the motion slides along a sphere: the chord between two checked points cuts it)."""
    verify_samples: int = 4
    """Every interval is re-evaluated at fractions j/``verify_samples`` (the samples
    ``verify_trajectory`` checks with python-fcl); a polish succeeds only if all keep δ."""
    path_weight: float = 1.0
    """``"path"``: weight of the squared tip displacements Σ‖p(z_{k+1}) − p(z_k)‖² (m²)."""
    smoothness_weight: float = 0.01
    """``"path"``: weight of the squared joint-space steps Σ‖z_{k+1} − z_k‖² (rad², m²)."""
    translation_weight: float = 1.0
    """``"tracking"``: weight of the translation part v of the pose error (m²)."""
    rotation_weight: float = 1.0
    """``"tracking"``: weight of the rotation part ω of the pose error (rad²)."""
    tracking_smoothness_weight: float = 1e-8
    """``"tracking"``: weight of Σ‖z_{k+1} − z_k‖² (rad², m²); tiny, it only picks one of
    equally good bodies. It biases reachable poses by about weight·‖Δz‖/‖J‖: 1e-4 was
    measured to leave 1e-3 pose errors on an 8-waypoint tdcr3 path, 1e-8 below 1e-6."""
    clearance_curvature: str = "full"
    """As ``NLPSettings`` (exact second derivatives by default)."""
    hessian: str = "exact"
    """Ipopt's ``hessian_approximation``: ``"exact"`` (the structured Hessian of the
    module docstring: exact objective and bending terms, no clearance curvature) or
    ``"limited-memory"`` (L-BFGS)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.interpolation_checks < 0 or self.reselections < 0:
            raise ValueError("interpolation_checks and reselections must be ≥ 0")
        if self.verify_samples < 1 or self.interpolation_checks > self.verify_samples - 1:
            raise ValueError("verify_samples must be ≥ 1 and interpolation_checks ≤ "
                             f"verify_samples − 1, got {self.verify_samples} and "
                             f"{self.interpolation_checks}")
        if self.hessian not in ("exact", "limited-memory"):
            raise ValueError(f"hessian must be 'exact' or 'limited-memory', got {self.hessian!r}")


@dataclass
class TrajectoryPolishResult:
    """The outcome of one trajectory polish (never raised: a failure is ``success=False``)."""

    q: np.ndarray
    """(W, 3n) waypoints θ, φ, L (rad, rad, m): Ipopt's answer projected onto the simple
    limits, or the warm start if Ipopt produced nothing finite."""
    success: bool
    """The re-evaluated ``max_violation`` ≤ ``violation_tolerance``: every constraint
    holds at every waypoint and sample, whatever Ipopt reported (``status``; an answer
    that is valid is not thrown away because Ipopt stopped early)."""
    status: str
    """Ipopt's return status, or why no solve ran."""
    max_violation: float
    """The largest of ``violations``, re-evaluated at ``q`` in float64."""
    violations: dict[str, float] = field(default_factory=dict)
    """Per family: ``clearance`` (m below δ, over all pairs at the waypoints and check
    points), ``limits`` (rad or m), ``tendon_speed`` (m/s over the limit),
    ``tendon_accel`` (m/s² over the limit)."""
    objective: float = math.nan
    """Ipopt's final objective value (m², rad² mixed)."""
    iterations: int = 0
    """Ipopt iterations, summed over the re-selections of this solve."""
    seconds: float = 0.0
    """Wall time of the whole ``solve``, seconds."""
    pose_errors: np.ndarray | None = None
    """``"tracking"`` only: (W,) ‖log(T_tip⁻¹·T_target)‖ per waypoint (mixed m/rad),
    float64."""
    warm_start_violations: dict[str, float] = field(default_factory=dict)
    """``violations`` of the warm start, as the NLP's constraints see it (the same
    families, the same configurations)."""
    out_of_time: bool = False
    """The solve's time limit stopped it (an Ipopt run stopped at the deadline, or no
    time was left for the next round); the answer is the best round so far."""
