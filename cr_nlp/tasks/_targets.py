"""IK targets: checking target poses, and reading them from a file."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..model import Robot


def validate_targets(robot: Robot, positions: Any, wxyz: Any) -> tuple[np.ndarray, np.ndarray,
                                                                       list[str]]:
    """Check targets; returns positions (T, 3), unit quaternions (T, 4) and a reason per
    target ("" when valid). Invalid targets get NaN rows instead of raising."""
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    wxyz = np.asarray(wxyz, dtype=float).reshape(-1, 4)
    if len(positions) != len(wxyz):
        raise ValueError(f"{len(positions)} positions but {len(wxyz)} orientations")
    base = np.asarray(robot.base_position)
    reach = robot.total_length_max
    norms = np.linalg.norm(wxyz, axis=1)
    with np.errstate(invalid="ignore"):
        distance = np.linalg.norm(positions - base, axis=1)
        suspect = ~(np.all(np.isfinite(positions), axis=1) & np.all(np.isfinite(wxyz), axis=1)
                    & (np.abs(norms - 1.0) <= 1e-3) & (distance <= reach * (1 + 1e-9)))
    reasons = [""] * len(positions)
    for i in np.flatnonzero(suspect):  # only the bad targets get words
        if not np.all(np.isfinite(positions[i])):
            reasons[i] = "target position is not finite"
        elif not np.all(np.isfinite(wxyz[i])):
            reasons[i] = "target orientation is not finite"
        elif abs(norms[i] - 1.0) > 1e-3:
            reasons[i] = f"target wxyz is not a unit quaternion (norm {norms[i]:.6g})"
        elif distance[i] > reach * (1 + 1e-9):
            reasons[i] = (f"target is out of reach: {distance[i]:.4g} m "
                          f"from the base, the robot is at most {reach:.4g} m long")
    bad = suspect
    wxyz = np.where(bad[:, None], np.nan, wxyz / np.where(norms > 0, norms, 1.0)[:, None])
    positions = np.where(bad[:, None], np.nan, positions)
    return positions, wxyz, reasons



