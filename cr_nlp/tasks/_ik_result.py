"""The IK result: one row per target, its summary, and its JSON, CSV and column forms."""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from .._files import atomic_open
from ..model import Robot
from ._result import ResultIO, array, nums, row_lists
from ._timing import StageTiming

PER_TARGET = ("pose_error", "position_error", "rotation_error", "max_violation",
               "min_clearance")
"""The float columns of an ``IKResult`` that ``IKSolver.verify`` fills per target."""
VERIFIED = {"min_clearance": "clearance"}
"""``IKResult`` column → the key of ``IKSolver.verify``'s output where they differ."""
COLUMNS = ("q", "position", "wxyz", *PER_TARGET, "collision_free", "success", "stage",
           "reason")
"""The per-target fields of an ``IKResult`` (``IKResult.columns``)."""


@dataclass
class IKResult(ResultIO):
    """One row per target. Units: rad, m; errors in the pose-error metric, m and rad."""

    kind: ClassVar[str] = "ik"

    robot: Robot
    q: np.ndarray                  # (T, 3n) θ, φ, L
    position: np.ndarray           # (T, 3) tip position reached, m
    wxyz: np.ndarray               # (T, 4) tip orientation reached
    pose_error: np.ndarray         # (T,) ‖log(T⁻¹ T_target)‖
    position_error: np.ndarray     # (T,) m
    rotation_error: np.ndarray     # (T,) rad
    max_violation: np.ndarray      # (T,) largest limit violation (rad, m) or clearance
    #                                shortfall below the safety margin (m; obstacles by
    #                                python-fcl, and segments at least two apart)
    min_clearance: np.ndarray      # (T,) signed distance, m: the smaller of the python-fcl
    #                                obstacle distance and the self-clearance (nan when
    #                                neither is checked)
    collision_free: np.ndarray     # (T,) bool: no obstacle or self penetration
    success: np.ndarray            # (T,) bool
    stage: list[str]               # which stage produced each answer
    reason: list[str]              # empty on success, else why it failed
    timing: StageTiming = field(default_factory=StageTiming)
    has_scene: bool = False
    tendon_displacements: np.ndarray | None = None
    """(T, n_tendons) motor commands reproducing each answer, m (positive = pulled), when
    the robot file has an ``actuation`` block (``model.actuation``); else None."""

    def __len__(self) -> int:
        return len(self.q)

    @property
    def theta(self) -> np.ndarray:
        return self.q[:, 0::3]

    @property
    def phi(self) -> np.ndarray:
        return self.q[:, 1::3]

    @property
    def length(self) -> np.ndarray:
        return self.q[:, 2::3]

    def summary(self) -> dict[str, Any]:
        """Success rate, mean pose error (all finite, successes), largest violation, and
        with a scene the collision-free rate."""
        ok = self.success
        finite = np.isfinite(self.pose_error)
        return {
            "targets": len(self),
            "success_rate": float(ok.mean()) if len(self) else 0.0,
            "mean_pose_error": float(self.pose_error[finite].mean()) if finite.any() else None,
            "mean_pose_error_success": float(self.pose_error[ok].mean()) if ok.any() else None,
            "max_violation": float(np.nanmax(self.max_violation)) if len(self) else None,
            "collision_free_rate": (float(self.collision_free.mean())
                                    if self.has_scene and len(self) else None),
        }

    def _fields_dict(self) -> dict[str, Any]:
        # Whole columns to Python lists at once: per-row indexing and tolist() cost
        # ~15 ms per 1000 rows, paid by every `cr-nlp ik --out` and batch job.
        finite = np.all(np.isfinite(self.q), axis=1).tolist()
        q, theta, phi, length, position, wxyz = (
            row_lists(a, finite) for a in (self.q, self.theta, self.phi, self.length,
                                      self.position, self.wxyz))
        pose_error, position_error, rotation_error, max_violation = (
            nums(a) for a in (self.pose_error, self.position_error, self.rotation_error,
                              self.max_violation))
        none = [None] * len(self)
        collision_free = (np.asarray(self.collision_free, bool).tolist() if self.has_scene
                          else none)
        min_clearance = nums(self.min_clearance) if self.has_scene else none
        success = np.asarray(self.success, bool).tolist()
        entries = [{"q": q[i], "theta": theta[i], "phi": phi[i], "length": length[i],
                    "position": position[i], "wxyz": wxyz[i], "pose_error": pose_error[i],
                    "position_error": position_error[i],
                    "rotation_error": rotation_error[i], "success": success[i],
                    "collision_free": collision_free[i], "min_clearance": min_clearance[i],
                    "max_violation": max_violation[i], "stage": self.stage[i],
                    "reason": self.reason[i] or None}
                   for i in range(len(self))]
        if self.tendon_displacements is not None:
            for entry, d in zip(entries, row_lists(self.tendon_displacements, finite),
                                strict=True):
                entry["tendon_displacements"] = d
        return {"has_scene": bool(self.has_scene), "results": entries,
                "summary": self.summary(), "timing": self.timing.as_dict()}

    @classmethod
    def _from_fields(cls, data: dict[str, Any], robot: Robot) -> IKResult:
        entries = data["results"]
        has_scene = bool(data["has_scene"])

        def column(name: str, width: int | None = None) -> np.ndarray:
            return array([e[name] for e in entries], width, name)

        return cls(
            robot, column("q", robot.dof), column("position", 3), column("wxyz", 4),
            **{k: column(k) for k in PER_TARGET},
            collision_free=np.array([bool(e["collision_free"]) if has_scene else True
                                     for e in entries], dtype=bool),
            success=np.array([bool(e["success"]) for e in entries], dtype=bool),
            stage=[str(e["stage"]) for e in entries],
            reason=[e["reason"] or "" for e in entries],
            timing=StageTiming.from_dict(data.get("timing")), has_scene=has_scene)

    def columns(self) -> dict[str, np.ndarray]:
        """The per-target fields as arrays (``COLUMNS``; stage and reason as strings): the
        compact form a batch job's chunk files hold."""
        return {k: np.asarray(getattr(self, k), dtype=str if k in ("stage", "reason") else None)
                for k in COLUMNS}

    @classmethod
    def from_columns(cls, robot: Robot, columns: dict[str, np.ndarray],
                     timing: StageTiming | dict[str, float] | None = None,
                     has_scene: bool = False) -> IKResult:
        """The result of ``columns()`` (of one result, or concatenated over many)."""
        if not isinstance(timing, StageTiming):
            timing = StageTiming.from_dict(timing)
        return cls(
            robot, *(np.asarray(columns[k], dtype=float) for k in COLUMNS[:3]),
            **{k: np.asarray(columns[k], dtype=float) for k in PER_TARGET},
            collision_free=np.asarray(columns["collision_free"], dtype=bool),
            success=np.asarray(columns["success"], dtype=bool),
            stage=[str(x) for x in columns["stage"]],
            reason=[str(x) for x in columns["reason"]],
            timing=timing, has_scene=has_scene)

    def save_csv(self, path: str | Path) -> Path:
        """One row per target: ``target``, ``success``, ``pose_error``,
        ``position_error_m``, ``rotation_error_rad``, ``min_clearance_m``,
        ``max_violation``, then q (``theta_<i>``, ``phi_<i>`` rad, ``length_<i>`` m per
        segment i), ``stage`` and ``reason``; empty cells where not finite."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        names = [f"{p}_{i + 1}" for i in range(self.robot.n_segments)
                 for p in ("theta", "phi", "length")]
        columns = [nums(a) for a in (self.pose_error, self.position_error,
                                     self.rotation_error, self.min_clearance,
                                     self.max_violation)]
        q = row_lists(self.q, [True] * len(self))
        with atomic_open(path, newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["target", "success", "pose_error", "position_error_m",
                             "rotation_error_rad", "min_clearance_m", "max_violation",
                             *names, "stage", "reason"])
            for i in range(len(self)):
                cells = [c[i] for c in columns] + [None if not np.isfinite(v) else v
                                                   for v in q[i]]
                writer.writerow([i, int(bool(self.success[i])),
                                 *("" if v is None else f"{v:.9g}" for v in cells),
                                 self.stage[i], self.reason[i]])
        return path
