"""The settings and answer of the tension-motion exact stage
(``stages.polish._tension_motion_nlp``), and the verdict's tension sets along a motion.
Units: metres, newtons, seconds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ._ipopt import NLPSettings

EXACT_MODE = ("cosserat multiple shooting over the motion (every waypoint and the "
              "verdict's samples between them that come near; the others measured)")
"""The formulation of the tension-motion exact stage (a result's ``exact_mode``)."""

OBJECTIVES = ("smooth", "nearest")
TARGETS = ("none", "position", "pose")


@dataclass(frozen=True)
class TensionMotionPolishConfig(NLPSettings):
    """Settings of the tension-motion polish (the shared ones: ``NLPSettings``; the
    clearance centres are linear in the unknowns, so ``clearance_curvature`` "parts" is
    "full" here)."""

    tol: float = 1e-6
    """Ipopt's ``tol`` (scaled optimality error; the objective is O(1) in scaled tensions;
    the rows are held by ``constr_viol_tol``). On the clutter suite's first 60-waypoint
    path 1e-8 took 25 iterations and 1e-6 22, objectives 0.0592975 and 0.0593008."""
    constr_viol_tol: float = 1e-10
    """Scaled rows: 1e-10 of the robot's length on positions, of E·I/L on moments, of
    τ_max on the tension rows, metres on the clearance rows."""
    max_iter: int = 150
    """Ipopt iterations per attempt."""
    objective: str = "smooth"
    """"smooth": Σ‖Δτ/τ_max‖² + ρ·Σ‖τ/τ_max‖²; "nearest": Σ‖(τ − τ_start)/τ_max‖²."""
    regularization: float = 1e-3
    """ρ of the "smooth" objective (a least-tension tie-break)."""
    warm_start: bool = True
    """Start Ipopt's barrier parameter at 1e-6 with the start kept in place where every
    rod of the start keeps its clearance, else Ipopt's own settings first; a failed solve
    is tried once more with the other (False: Ipopt's own only)."""
    target_tolerance: float = 0.0
    """Following: each tip coordinate within this of its target, m (0: equality)."""
    spheres_per_step: int = 4
    """Body spheres per chord of the rod's grid (``_rod_clearance``): the rows ask
    δ' = δ + the most the capsule chain can come nearer than its spheres (with
    tdcr2_rao2021's 12 mm envelope and 20 mm steps: 1.0 mm at 2 per step, 0.26 mm at 4)."""

    slot_rounds: int = 4
    """Ipopt runs per attempt: after each, where a pair without a clearance slot came
    nearer than δ', the pairs near any of the shapes so far get the slots and Ipopt goes on
    from its answer. A plan's refined motion shortened far through the clutter of
    ``bench tension`` needed 3 (with 2 its last run's answer was 11.8 mm inside a box
    that had no slot)."""

    sample_margin: float = 0.008
    """Metres beyond δ': a tension set the verdict checks between two waypoints is a rod
    of the NLP where its backbone comes within δ' + this of an obstacle or of itself (pair
    distance) at the start; the others are solved afresh after Ipopt (``sample_rounds``).
    inf: every sample a rod. On the clutter suite's first 60-waypoint path 32 of 118
    samples come within 10 mm (δ' = 2.26 mm on tdcr2_rao2021)."""
    mumps_pivot_order: int = 0
    """MUMPS's fill-reducing ordering of the KKT systems (Ipopt's ``mumps_pivot_order``):
    0 AMD; 7 MUMPS's own choice. On the clutter suite's first 60-waypoint path (94 rods,
    25 iterations) AMD's factorizations and solves took 3.6–3.8 s against 4.6–4.9 s,
    alternated, the same answer."""
    sample_rounds: int = 3
    """Ipopt runs over the rods (each with its ``slot_rounds``): after each, where a sample
    outside the NLP came nearer than δ', the samples then within δ' + ``sample_margin``
    join and Ipopt starts again from the start."""
    warm_mu_init: float = 1e-5
    """Ipopt's first barrier parameter where the solve is warm-started (``warm_start``).
    On the clutter suite's six 60-waypoint paths (polished from their verified motions,
    one process, alternated) 1e-5 took 85 iterations in all against 92 at 1e-6 and 103 at
    1e-4 (the densest path 14 against 18), the same answers; on 8 plans 134 against 135."""
    fast_from: int = 120
    """Tension sets (waypoints and the samples between them; 120: 40 waypoints with 2
    samples between) from which a motion's step functions are also compiled at -Og
    (``stages.polish._rod_shooting.FAST_FLAGS``: its derivatives about 2.3× faster, for
    75 s of gcc once per robot in a detached process; until it is there, the -O0 ones)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("slot_rounds", "sample_rounds", "fast_from"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be ≥ 1, got {getattr(self, name)}")
        if not self.warm_mu_init > 0:
            raise ValueError(f"warm_mu_init must be > 0, got {self.warm_mu_init}")
        if not self.sample_margin > 0:
            raise ValueError(f"sample_margin must be > 0 m, got {self.sample_margin}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {self.objective!r}")
        if not (self.regularization >= 0 and self.target_tolerance >= 0):
            raise ValueError("regularization and target_tolerance must be ≥ 0")
        if self.spheres_per_step < 1:
            raise ValueError(f"spheres_per_step must be ≥ 1, got {self.spheres_per_step}")


class TensionMotionPolish(NamedTuple):
    """One polished motion (a failure is a status, never an exception; nothing here is
    judged: the caller's verdict replays the tensions through fresh statics)."""

    tensions: np.ndarray
    """(T, n) N within [0, τ_max]: Ipopt's last iterate (clipped), or the start where no
    run finished (no time, non-finite input, a numerical failure)."""
    status: str
    """Ipopt's return status (``TIME_LIMIT_STATUS`` where the time ran out)."""
    seconds: float
    """Wall time (start solves, Ipopt, refreshed slots), s."""
    iterations: int
    """Ipopt iterations."""


def sample_weights(count: int, samples_between: int) -> np.ndarray:
    """(R, T) weights giving the R tension sets the verdict checks from the T waypoints'
    (its order: each waypoint, then ``samples_between`` evenly spaced sets strictly
    between it and the next; R = T + (T − 1)·k)."""
    if count < 2:
        return np.eye(count)
    rows = []
    for i in range(count - 1):
        for j in range(samples_between + 1):
            row = np.zeros(count)
            f = j / (samples_between + 1)
            row[i], row[i + 1] = 1.0 - f, f
            rows.append(row)
    rows.append(np.eye(count)[-1])
    return np.array(rows)
