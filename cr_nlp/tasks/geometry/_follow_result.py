"""The result of path following: ``FollowResult``, its file forms (RESULT.json, .npz, the
controller's tendon-length CSV) and the float64 tracking measures it reports. Units: rad,
m, s (millimetre / degree figures in ``FollowResult.summary``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..._files import atomic_open
from ...model import Robot
from ...model.kinematics import pose_error, tip_pose
from ...model.rotations import matrix_from_wxyz, wxyz_from_matrix
from ...model.routing import tendon_names
from ...world._motion import MotionVerification
from .._result import (
    OneStage,
    ResultFileError,
    ResultIO,
    Stage,
    array,
    as_float,
    num,
    nums,
    read_stage,
    write_series_csv,
)
from .._timing import StageTiming
from ..paths import ReferencePath
from ._trajectory_result import controller_columns


def tracking_errors(robot: Robot, q: np.ndarray, positions: np.ndarray,
                    wxyz: np.ndarray) -> dict[str, np.ndarray]:
    """Per-waypoint tip pose and its distance to the reference, float64: ``position``
    (T, 3) m, ``wxyz`` (T, 4), ``pose_error`` (T,) (‖log(T_tip⁻¹·T_ref)‖, docs/design.md §1),
    ``position_error`` (T,) m and ``rotation_error`` (T,) rad (the angle of
    R_tipᵀ·R_ref)."""
    position, rotation = tip_pose(robot, np.asarray(q, np.float64))
    reference = matrix_from_wxyz(wxyz)
    relative = np.einsum("tji,tjk->tik", rotation, reference)
    cos_angle = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return {"position": position, "wxyz": wxyz_from_matrix(rotation),
            "pose_error": pose_error(position, rotation, positions, reference),
            "position_error": np.linalg.norm(position - positions, axis=1),
            "rotation_error": np.arccos(cos_angle)}


@dataclass(frozen=True)
class PathVerification:
    """``PathFollower.verify``'s report on a followed path: the motion's report
    (``verify_trajectory``) and the float64 tracking of the reference. Units: rad, m."""

    motion: MotionVerification
    """The verdict on the motion and what it measured (clearance, tendon limits)."""
    position: np.ndarray
    """(T, 3) tip positions reached, m."""
    wxyz: np.ndarray
    """(T, 4) tip orientations reached."""
    pose_error: np.ndarray
    """(T,) ‖log(T_tip⁻¹·T_ref)‖ (mixed m/rad)."""
    position_error: np.ndarray
    """(T,) m."""
    rotation_error: np.ndarray
    """(T,) rad."""
    reached: np.ndarray
    """(T,) bool: within the follower's position and rotation tolerances."""

    @classmethod
    def of(cls, robot: Robot, motion: MotionVerification, q: np.ndarray, path: ReferencePath,
           position_tolerance_mm: float, rotation_tolerance_deg: float) -> PathVerification:
        """The report on (T, 3n) q following ``path``, its motion judged by ``motion``."""
        errors = tracking_errors(robot, q, path.positions, path.wxyz)
        reached = ((1e3 * errors["position_error"] <= position_tolerance_mm)
                   & (np.degrees(errors["rotation_error"]) <= rotation_tolerance_deg))
        return cls(motion, **errors, reached=reached)

    @property
    def success(self) -> bool:
        """The verdict accepts the motion (``reached`` is judged apart)."""
        return self.motion.success

    @property
    def reason(self) -> str:
        """The motion verdict's words ("" on success)."""
        return self.motion.reason

    @property
    def violations(self) -> dict[str, float]:
        """Largest violation per family (``MotionVerification.violations``)."""
        return self.motion.violations

    @property
    def max_violation(self) -> float:
        """The largest of ``violations``."""
        return self.motion.max_violation


def unreached_stretches(reached: np.ndarray) -> list[tuple[int, int]]:
    """Runs of consecutive unreached waypoints as (first, last) indices, inclusive."""
    out, start = [], None
    for i, ok in enumerate(np.asarray(reached, bool)):
        if not ok and start is None:
            start = i
        elif ok and start is not None:
            out.append((start, i - 1))
            start = None
    if start is not None:
        out.append((start, len(reached) - 1))
    return out


@dataclass
class FollowResult(OneStage, ResultIO):
    """A followed path. Units: rad, m, s (millimetre / degree figures in ``summary``)."""

    kind: ClassVar[str] = "follow"

    robot: Robot
    path: ReferencePath
    """The reference (positions m, unit quaternions, Δt s)."""
    q: np.ndarray
    """(T, 3n) configurations θ, φ, L, one per waypoint."""
    position: np.ndarray
    """(T, 3) tip positions reached, m."""
    wxyz: np.ndarray
    """(T, 4) tip orientations reached, unit quaternions (w, x, y, z)."""
    pose_error: np.ndarray
    """(T,) ‖log(T_tip⁻¹·T_ref)‖ (the IK success metric, m and rad mixed)."""
    position_error: np.ndarray
    """(T,) ‖p_tip − p_ref‖, m."""
    rotation_error: np.ndarray
    """(T,) rotation angle between the tip and reference frames, rad."""
    reached: np.ndarray
    """(T,) bool: position error ≤ ``FollowConfig.position_tolerance_mm`` (default 5 mm)
    and rotation error ≤ ``FollowConfig.rotation_tolerance_deg`` (default 1°)."""
    tendon_lengths: np.ndarray
    """(T, n_tendons) tendon lengths at the waypoints, m."""
    tendon_speed: float
    """Largest |tendon speed| by finite differences, m/s."""
    tendon_accel: float
    """Largest |tendon acceleration| by finite differences, m/s²."""
    collision_free: bool
    """python-fcl: no contact anywhere along the interpolated motion."""
    min_clearance: float
    """Smallest python-fcl distance along the motion, m (+inf with nothing to hit)."""
    max_violation: float
    """Largest of ``violations``."""
    violations: dict[str, float]
    """Largest violation per family (``verify_trajectory``): clearance (m below δ),
    limits (rad or m), tendon_speed (m/s), tendon_accel (m/s²)."""
    success: bool
    """Every waypoint reached and every violation ≤ 1e-6 (``verify_trajectory``, the one
    verdict of ``world.verdict``): clearance ≥ δ along the motion, limits, tendon
    limits."""
    reason: str
    """"" on success, else why not (unreached waypoints, collision, limits)."""
    stage: Stage
    """What produced ``q``: ``Stage.REFINE`` or ``Stage.POLISH``; why a refine answer
    stands in exact mode is in ``notes``."""
    timing: StageTiming = field(default_factory=StageTiming)
    """Seconds per stage: compile, explore, refine, polish, verify (and ``total``)."""
    scene_name: str | None = None
    """The scene's name, or None without obstacles."""
    safety_margin: float = 0.002
    """δ, metres, used by the verdict."""
    tendon_displacements: np.ndarray | None = None
    """(T, n_tendons) motor commands at the waypoints, m (positive = pulled), when the
    robot file has an ``actuation`` block (``model.actuation``); else None."""
    notes: list[str] = field(default_factory=list)
    """Free text qualifying ``stage`` in exact mode: "polish failed: <why>", "polish out
    of time: <why>" (``FollowConfig.polish_time_limit``), "feasible: polish not needed" or
    "feasible; the polished answer tracked worse" (the LM answer already keeps every
    constraint: max violation ≤ 1e-6 by the independent checks)."""

    @property
    def dt(self) -> float:
        """Seconds between waypoints."""
        return float(self.path.dt)

    @property
    def times(self) -> np.ndarray:
        """(T,) time of each waypoint, seconds."""
        return np.arange(len(self.q)) * self.dt

    def summary(self) -> dict[str, Any]:
        """Tracking statistics: mean/std/max position error (mm), mean/max rotation error
        (degrees), reached count, unreached waypoint indices and stretches."""
        pos, rot = 1e3 * self.position_error, np.degrees(self.rotation_error)
        return {
            "waypoints": len(self.q),
            "mean_position_error_mm": float(np.mean(pos)),
            "std_position_error_mm": float(np.std(pos)),
            "max_position_error_mm": float(np.max(pos)),
            "mean_rotation_error_deg": float(np.mean(rot)),
            "max_rotation_error_deg": float(np.max(rot)),
            "reached": int(np.count_nonzero(self.reached)),
            "unreached": np.flatnonzero(~self.reached).tolist(),
            "unreached_stretches": [list(s) for s in unreached_stretches(self.reached)],
        }

    def _fields_dict(self) -> dict[str, Any]:
        return {
            "path": self.path.to_dict(),
            "scene": self.scene_name,
            "success": bool(self.success),
            "reason": self.reason or None,
            "stage": Stage(self.stage).value,
            "notes": list(self.notes),
            "status": self.status.value,
            "dt": self.dt,
            "times": self.times.tolist(),
            "q": self.q.tolist(),
            "position": self.position.tolist(),
            "wxyz": self.wxyz.tolist(),
            "pose_error": nums(self.pose_error),
            "position_error": nums(self.position_error),
            "rotation_error": nums(self.rotation_error),
            "reached": self.reached.tolist(),
            "tendon_names": tendon_names(self.robot),
            "tendon_lengths": self.tendon_lengths.tolist(),
            **({"tendon_displacements": self.tendon_displacements.tolist()}
               if self.tendon_displacements is not None else {}),
            "tendon_speed": num(self.tendon_speed),
            "tendon_accel": num(self.tendon_accel),
            "collision_free": bool(self.collision_free),
            "min_clearance": num(self.min_clearance),
            "safety_margin": self.safety_margin,
            "max_violation": num(self.max_violation),
            "violations": {k: num(v) for k, v in self.violations.items()},
            "summary": self.summary(),
            "timing": self.timing.as_dict(),
        }

    @classmethod
    def _from_fields(cls, data: dict[str, Any], robot: Robot) -> FollowResult:
        path = ReferencePath.from_dict(data["path"], source="path")
        count = len(path)
        stage, notes = read_stage(data, data["schema_version"])
        return cls(
            robot, path, array(data["q"], robot.dof, "q"), array(data["position"], 3, "position"),
            array(data["wxyz"], 4, "wxyz"), *(array(data[k], name=k) for k in (
                "pose_error", "position_error", "rotation_error")),
            np.array(data["reached"], dtype=bool),
            array(data["tendon_lengths"], robot.n_tendons, "tendon_lengths"),
            as_float(data["tendon_speed"], "tendon_speed"),
            as_float(data["tendon_accel"], "tendon_accel"),
            bool(data["collision_free"]), as_float(data["min_clearance"], "min_clearance"),
            as_float(data["max_violation"], "max_violation"),
            {k: as_float(v, f"violations.{k}") for k, v in data["violations"].items()},
            success=bool(data["success"]), reason=data["reason"] or "", stage=stage,
            notes=notes,
            timing=StageTiming.from_dict(data["timing"]), scene_name=data["scene"],
            safety_margin=float(data["safety_margin"]),
        )._checked(count)

    def _checked(self, count: int) -> FollowResult:
        """This result, after checking that every per-waypoint field has ``count`` rows."""
        for name in ("q", "position", "wxyz", "pose_error", "position_error",
                     "rotation_error", "reached", "tendon_lengths"):
            if len(getattr(self, name)) != count:
                raise ResultFileError(f"{name} has {len(getattr(self, name))} rows, the path "
                                      f"{count} waypoints")
        return self

    def save(self, path: str | Path, indent: int | None = 2) -> Path:
        """Write ``to_dict`` as JSON (.json, or any suffix but .npz), or the arrays as a
        numpy .npz by the file's suffix; returns the path."""
        path = Path(path)
        if path.suffix != ".npz":
            return super().save(path, indent)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_open(path, "wb") as handle:
            np.savez(handle, q=self.q, times=self.times, dt=self.dt,
                     position=self.position, wxyz=self.wxyz,
                     target_positions=self.path.positions, target_wxyz=self.path.wxyz,
                     pose_error=self.pose_error, position_error=self.position_error,
                     rotation_error=self.rotation_error, reached=self.reached,
                     tendon_lengths=self.tendon_lengths, collision_free=self.collision_free,
                     min_clearance=self.min_clearance, max_violation=self.max_violation,
                     success=self.success, stage=self.stage_text, reason=self.reason)
        return path

    def save_csv(self, path: str | Path) -> Path:
        """The tendon-length series for a controller: ``time_s``, then one column per
        tendon (``model.routing.tendon_names``), lengths in metres, one row per waypoint."""
        return write_series_csv(path, self.times, *controller_columns(
            self.robot, self.tendon_lengths, self.tendon_displacements))


def tracking_cost(result: FollowResult) -> float:
    """Σ over waypoints of (position error in mm)² + (rotation error in degrees)²."""
    return float(np.sum((1e3 * result.position_error) ** 2
                        + np.degrees(result.rotation_error) ** 2))


def result_from_verdict(robot: Robot, path: ReferencePath, q: np.ndarray,
                        verdict: PathVerification, stage: Stage | str,
                        why_untrackable: dict[int, str], scene_name: str | None,
                        safety_margin: float) -> FollowResult:
    """The result of the followed path ``q`` (T, 3n) (rad, rad, m) judged by ``verdict``
    (``PathFollower.verify``'s report); ``why_untrackable``: waypoint index → why it
    cannot be tracked; ``safety_margin`` δ, m."""
    reached = np.asarray(verdict.reached, bool)
    motion = verdict.motion
    reasons = []
    unreached = np.flatnonzero(~reached)
    if len(unreached):
        stretches = ", ".join(f"{a}" if a == b else f"{a}–{b}"
                              for a, b in unreached_stretches(reached))
        reasons.append(f"{len(unreached)} of {len(q)} waypoints not reached (waypoints "
                       f"{stretches})")
        for i, why in sorted(why_untrackable.items())[:3]:
            reasons.append(f"waypoint {i}: {why}")
    if motion.reason:
        reasons.append(motion.reason)
    return FollowResult(
        robot, path, q, verdict.position, verdict.wxyz, verdict.pose_error,
        verdict.position_error, verdict.rotation_error, reached,
        motion.tendon_lengths, motion.tendon_speed, motion.tendon_accel,
        bool(motion.collision_free), float(motion.min_clearance),
        float(motion.max_violation), motion.violations,
        success=bool(motion.success) and bool(reached.all()),
        reason="; ".join(reasons), stage=stage, scene_name=scene_name,
        safety_margin=safety_margin)
