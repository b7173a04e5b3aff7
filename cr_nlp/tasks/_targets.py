"""IK targets: checking target poses, and reading them from a file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .._files import read_json_or
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



def read_targets(path: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Target poses from a file ``{"poses": [{"position": [x, y, z], "wxyz": [w, x, y, z]},
    ...]}`` (positions in metres, unit quaternions; ``wxyz`` defaults to the identity).

    Returns (positions (k, 3), wxyz (k, 4), problems): a malformed entry becomes a NaN row
    with its reason in ``problems`` (empty strings elsewhere), so one bad target never
    sinks the batch.

    Raises:
        ValueError: the file is missing, not JSON, or not of that shape.
    """
    data = read_json_or(path, lambda reason: ValueError(f"{path}: {reason}"))
    if not isinstance(data, dict) or not isinstance(data.get("poses"), list):
        raise ValueError(f"{path} must hold {{\"poses\": [{{\"position\": [x, y, z], "
                         f"\"wxyz\": [w, x, y, z]}}, ...]}}")
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ValueError(f"{path}: field {unknown[0]!r}: unknown key "
                         f"(allowed: {', '.join(sorted(_TOP_KEYS))})")
    poses = data["poses"]
    positions = np.full((len(poses), 3), np.nan)
    wxyz = np.full((len(poses), 4), np.nan)
    problems = [""] * len(poses)
    for i, pose in enumerate(poses):
        try:
            if not isinstance(pose, dict):
                raise ValueError("entry is not an object")
            unknown = sorted(set(pose) - _POSE_KEYS)
            if unknown:
                raise ValueError(f"unknown key {unknown[0]!r} (allowed: position, wxyz)")
            p = np.asarray(pose["position"], dtype=float)
            w = np.asarray(pose.get("wxyz", [1.0, 0.0, 0.0, 0.0]), dtype=float)
            if p.shape != (3,) or w.shape != (4,):
                raise ValueError(f"position needs 3 numbers and wxyz 4, got {p.size} and {w.size}")
            if not (np.all(np.isfinite(p)) and np.all(np.isfinite(w))):
                raise ValueError(f"numbers must be finite, got position {p.tolist()} and "
                                 f"wxyz {w.tolist()}")
            positions[i], wxyz[i] = p, w
        except KeyError as exc:
            problems[i] = f"malformed pose entry: missing field {exc}"
        except (TypeError, ValueError, OverflowError) as exc:
            problems[i] = f"malformed pose entry: {exc}"
    return positions, wxyz, problems


_TOP_KEYS = {"poses", "description", "name"}
_POSE_KEYS = {"position", "wxyz"}
