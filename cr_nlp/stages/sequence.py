"""Choosing one IK answer per waypoint so that the sequence moves as little as possible.

Dynamic programming (Viterbi) over the candidate sets: the cost of a sequence is the sum
of squared configuration jumps between consecutive waypoints, measured in the
bending-vector form (no azimuth wrap-around, no singularity at θ = 0); candidates that do
not reach their waypoint are excluded unless a waypoint has none, in which case its best
candidate is kept (and the caller reports that waypoint as unreached).
"""

from __future__ import annotations

import numpy as np

from ..model import Robot, q_to_z


def smoothest_sequence(robot: Robot, candidates: np.ndarray, errors: np.ndarray,
                       tolerance: float) -> np.ndarray:
    """Indices (T,) of the candidate to use at each waypoint.

    Args:
        candidates: (T, K, 3n) configurations (θ, φ, L) per waypoint.
        errors: (T, K) residual norms of the candidates (pose error, m/rad).
        tolerance: candidates with an error at or above this are not used where a
            waypoint has a better one.
    """
    t, k, _ = candidates.shape
    z = np.asarray(q_to_z(robot, candidates), dtype=float)
    usable = errors < tolerance
    # A waypoint with no usable candidate keeps its best one rather than breaking the chain.
    none = ~usable.any(axis=1)
    usable[none, np.argmin(errors[none], axis=1)] = True
    node = np.where(usable, 0.0, np.inf)
    total = node[0].copy()
    back = np.zeros((t, k), dtype=int)
    for i in range(1, t):
        jump = np.sum((z[i][None, :, :] - z[i - 1][:, None, :]) ** 2, axis=-1)  # (K_prev, K)
        options = total[:, None] + jump
        back[i] = np.argmin(options, axis=0)
        total = options[back[i], np.arange(k)] + node[i]
    choice = np.empty(t, dtype=int)
    choice[-1] = int(np.argmin(total))
    for i in range(t - 1, 0, -1):
        choice[i - 1] = back[i, choice[i]]
    return choice
