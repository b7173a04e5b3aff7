"""The results of tension-space motions on the Cosserat model: a followed path
(``tension_follow``, ``tasks.mechanics.follow``) and a planned trajectory
(``tension_trajectory``), with their file forms. Both hold the tensions per waypoint (N,
the robot file's tendon order), the verdict's fresh statics solve at every waypoint (tip
pose, backbone) and the loads they were solved under. SI units throughout."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ...model import Robot
from ...model.cosserat import motor_commands
from .._result import (
    SCHEMA_VERSION,
    OneStage,
    ResultFileError,
    ResultIO,
    Stage,
    array,
    check_header,
    num,
    nums,
    result_robot,
    row_lists,
    typed_stage,
    write_series_csv,
)
from .._timing import StageTiming
from ._motion import EXACT_MODE, MOTION_FAMILIES, TensionMotionVerification


@dataclass(kw_only=True)
class TensionTrajectoryResult(OneStage, ResultIO):
    """One tension motion: waypoints ``dt`` apart, judged as a whole."""

    kind: ClassVar[str] = "tension_trajectory"

    robot: Robot
    tensions: np.ndarray          # (T, n_tendons) N
    dt: float                     # s between waypoints
    position: np.ndarray          # (T, 3) tip of the verdict's forward solve, m
    wxyz: np.ndarray              # (T, 4) its orientation
    backbone: np.ndarray          # (T, P, 3) the solved backbone, m
    clearance: np.ndarray         # (T,) python-fcl obstacle distance, m (inf: no scene)
    min_clearance: float          # m, along the motion (waypoints and samples between)
    max_violation: float
    success: bool
    reason: str
    tip_force: np.ndarray         # (3,) N, world frame (the load case of the whole motion)
    tip_moment: np.ndarray        # (3,) N·m
    gravity: np.ndarray           # (3,) m/s²
    distributed_force: np.ndarray  # (3,) N/m
    point_loads: list[dict]       # [{"s": m, "force": [N], "moment": [N·m]}]
    tension_rate_max: float       # N/s, the limit the motion was judged against
    tendon_displacements: np.ndarray | None = None   # (T, n_tendons) m, pulled > 0
    violations: dict[str, float] = field(default_factory=dict)
    """Per family (``MOTION_FAMILIES``), the largest violation along the motion."""
    stage: Stage = Stage.REFINE
    """``Stage.POLISH`` (exact mode: Ipopt's motion, accepted by the verdict),
    ``Stage.REFINE`` (the banded LM over the whole motion answered), ``Stage.EXPLORE``
    (a plan: the straight-leg search's motion, kept where the refined one did not verify
    or was not better; following: the per-waypoint answers, kept the same way; ``notes``
    say why) or ``Stage.REJECTED`` for a problem refused before solving."""
    notes: list[str] = field(default_factory=list)
    timing: StageTiming = field(default_factory=StageTiming)
    exact_mode: str = EXACT_MODE
    """The exact stage's formulation where exact mode ran (``stages.polish``'s
    ``MOTION_EXACT_MODE``), else ``EXACT_MODE``'s words: none ran."""

    def __post_init__(self) -> None:
        if self.tendon_displacements is None:
            self.tendon_displacements = np.full(self.tensions.shape, np.nan)
        self.stage, self.notes = typed_stage(self.stage, self.notes)
        self.violations = {k: float(self.violations.get(k, np.nan)) for k in MOTION_FAMILIES}

    def __len__(self) -> int:
        return len(self.tensions)

    def judged(self, report: TensionMotionVerification) -> None:
        """Take the verdict's numbers from ``report`` (the same motion's check)."""
        self.position, self.wxyz = report.tip_position, report.tip_wxyz
        self.backbone, self.clearance = report.backbone, report.clearance
        self.min_clearance, self.max_violation = report.min_clearance, report.max_violation
        self.violations = dict(report.violations)
        self.tendon_displacements = report.tendon_displacements
        self.success, self.reason = report.success, report.reason

    def loads(self) -> dict[str, Any]:
        """The load case as keyword arguments of ``model.loads.static_loads``."""
        return {"tip_force": self.tip_force, "tip_moment": self.tip_moment,
                "gravity": self.gravity, "distributed_force": self.distributed_force,
                "point_loads": self.point_loads or None}

    def summary(self) -> dict[str, Any]:
        """The verdict for people (clearance in mm)."""
        return {"waypoints": len(self), "success": bool(self.success),
                "min_clearance_mm": num(self.min_clearance * 1e3),
                "max_violation": num(self.max_violation), "time_s": self.timing.total}

    def _fields_dict(self) -> dict[str, Any]:
        return _trajectories_fields([self], self.timing)

    @classmethod
    def _from_fields(cls, data: dict[str, Any], robot: Robot) -> TensionTrajectoryResult:
        entries = data["results"]
        if len(entries) != 1:
            raise ResultFileError(f"holds {len(entries)} trajectories, not one: read it with "
                                  "load_results")
        return cls.from_entry(entries[0], robot)

    @classmethod
    def list_from_dict(cls, data: Any, robot: Robot | str | None = None,
                       source: str = "") -> list[Any]:
        """Every trajectory of a RESULT.json's content (``tension_trajectories_to_dict``)."""
        where = source or "the result"
        check_header(data, where, kind=cls.kind)
        robot = result_robot(data, robot, where)
        try:
            return [cls.from_entry(e, robot) for e in data["results"]]
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ResultFileError(f"{where}: not a valid {cls.kind} result ({exc!r})") from None

    def entry(self) -> dict[str, Any]:
        """This motion's JSON fields (one entry of a trajectories file)."""
        return {
            "tensions": row_lists(self.tensions), "dt": self.dt,
            "position": row_lists(self.position), "wxyz": row_lists(self.wxyz),
            "backbone": [row_lists(b) for b in self.backbone],
            "clearance": nums(self.clearance), "min_clearance": num(self.min_clearance),
            "max_violation": num(self.max_violation), "success": bool(self.success),
            "reason": self.reason, "tip_force": self.tip_force.tolist(),
            "tip_moment": self.tip_moment.tolist(), "gravity": self.gravity.tolist(),
            "distributed_force": self.distributed_force.tolist(),
            "point_loads": self.point_loads, "tension_rate_max": self.tension_rate_max,
            "tendon_displacements": row_lists(self.tendon_displacements),
            "violations": {k: num(v) for k, v in self.violations.items()},
            "stage": self.stage.value, "notes": self.notes, "status": self.status.value,
            "exact_mode": self.exact_mode, "timing": self.timing.as_dict(),
            "summary": self.summary(),
        }

    @classmethod
    def _common(cls, data: dict[str, Any], robot: Robot) -> dict[str, Any]:
        """The constructor's arguments of the fields every tension motion has."""
        n = robot.n_tendons
        stage, notes = typed_stage(data["stage"], data.get("notes"))
        clearance = array(data["clearance"], name="clearance")
        return {
            "robot": robot, "tensions": array(data["tensions"], n, "tensions"),
            "dt": float(data["dt"]), "position": array(data["position"], 3, "position"),
            "wxyz": array(data["wxyz"], 4, "wxyz"),
            "backbone": np.array([array(b, 3, f"backbone[{i}]")
                                  for i, b in enumerate(data["backbone"])]).reshape(
                len(data["backbone"]), -1, 3) if data["backbone"]
            else np.zeros((0, 0, 3)),   # a motion that never ran (a failed batch chunk)
            "clearance": np.where(np.isnan(clearance), np.inf, clearance),
            "min_clearance": np.inf if data["min_clearance"] is None
            else float(data["min_clearance"]),
            "max_violation": float(array([data["max_violation"]])[0]),
            "success": bool(data["success"]), "reason": str(data["reason"]),
            **{k: array(data[k], name=k) for k in ("tip_force", "tip_moment", "gravity",
                                                   "distributed_force")},
            "point_loads": list(data["point_loads"]),
            "tension_rate_max": float(data["tension_rate_max"]),
            "tendon_displacements": array(data["tendon_displacements"], n,
                                          "tendon_displacements"),
            "violations": {k: float(array([v])[0]) for k, v in data["violations"].items()},
            "stage": stage, "notes": notes, "timing": StageTiming.from_dict(data.get("timing")),
            "exact_mode": str(data.get("exact_mode", EXACT_MODE)),
        }

    @classmethod
    def from_entry(cls, data: dict[str, Any], robot: Robot) -> TensionTrajectoryResult:
        """The result of one ``entry()``."""
        return cls(**cls._common(data, robot))

    def _series(self) -> tuple[list[str], np.ndarray]:
        n = self.robot.n_tendons
        names = [*(f"tension_{i + 1}_N" for i in range(n)), "tip_x", "tip_y", "tip_z",
                 *(f"displacement_{i + 1}_m" for i in range(n))]
        values = [self.tensions, self.position, self.tendon_displacements]
        mech = self.robot.mechanics
        if mech is not None and mech.tendon_stiffness:
            # a robot driven by displacements (calibrate --model cosserat): its commands
            names += [f"command_{i + 1}_m" for i in range(n)]
            values.append(motor_commands(self.robot, self.tensions,
                                         self.tendon_displacements))
        return names, np.concatenate(values, axis=1)

    def save_csv(self, path: str | Path) -> Path:
        """The time series for a controller: ``time_s``, the tensions (N), the solved tip
        x, y, z (m) and the tendon displacements (m), one row per waypoint; for a robot
        whose mechanics block has ``tendon_stiffness`` also the motor commands
        ``command_<j>_m`` (m, the actuation block's zeros and gains: the displacements
        that make the displacement-driven rod hold these tensions)."""
        names, values = self._series()
        return write_series_csv(path, np.arange(len(self)) * self.dt, names, values)


@dataclass(kw_only=True)
class TensionFollowResult(TensionTrajectoryResult):
    """A path followed in tension space: the motion, and per waypoint its target and how
    close the fresh statics solve's tip came to it."""

    kind: ClassVar[str] = "tension_follow"

    target_position: np.ndarray   # (T, 3) m
    target_wxyz: np.ndarray       # (T, 4); NaN rows: position-only waypoints
    position_error: np.ndarray    # (T,) m
    rotation_error: np.ndarray    # (T,) rad, NaN for position-only waypoints
    reached: np.ndarray           # (T,) bool: within ``tolerance``
    tolerance: float              # m (with orientations: the pose error, see the config)

    def summary(self) -> dict[str, Any]:
        """The verdict and the tracking errors for people (mm, degrees)."""
        errors = self.position_error * 1e3
        return {**super().summary(), "reached": int(np.sum(self.reached)),
                "unreached": np.flatnonzero(~self.reached).tolist(),
                "mean_position_error_mm": num(np.nanmean(errors)) if len(self) else None,
                "max_position_error_mm": num(np.nanmax(errors)) if len(self) else None,
                "max_rotation_error_deg": num(np.degrees(np.nanmax(self.rotation_error)))
                if np.any(np.isfinite(self.rotation_error)) else None}

    def _fields_dict(self) -> dict[str, Any]:
        return self.entry()

    @classmethod
    def _from_fields(cls, data: dict[str, Any], robot: Robot) -> TensionFollowResult:
        return cls.from_entry(data, robot)

    @classmethod
    def list_from_dict(cls, data: Any, robot: Robot | str | None = None,
                       source: str = "") -> list[Any]:
        """The one followed path of a RESULT.json's content."""
        return [cls.from_dict(data, robot, source)]

    def entry(self) -> dict[str, Any]:
        """This path's JSON fields."""
        return {**super().entry(),
                "target_position": row_lists(self.target_position),
                "target_wxyz": row_lists(self.target_wxyz),
                "position_error": nums(self.position_error),
                "rotation_error": nums(self.rotation_error),
                "reached": [bool(r) for r in self.reached], "tolerance": self.tolerance}

    @classmethod
    def from_entry(cls, data: dict[str, Any], robot: Robot) -> TensionFollowResult:
        """The result of ``entry()``'s form."""
        return cls(**cls._common(data, robot),
                   target_position=array(data["target_position"], 3, "target_position"),
                   target_wxyz=array(data["target_wxyz"], 4, "target_wxyz"),
                   position_error=array(data["position_error"], name="position_error"),
                   rotation_error=array(data["rotation_error"], name="rotation_error"),
                   reached=np.array(data["reached"], dtype=bool),
                   tolerance=float(data["tolerance"]))

    def _series(self) -> tuple[list[str], np.ndarray]:
        names, values = super()._series()
        return ([*names, "target_x", "target_y", "target_z", "position_error_m"],
                np.concatenate([values, self.target_position, self.position_error[:, None]],
                               axis=1))


def _trajectories_fields(results: list[TensionTrajectoryResult],
                         timing: StageTiming | None) -> dict[str, Any]:
    ok = [r.success for r in results]
    return {"results": [r.entry() for r in results],
            "summary": {"problems": len(results),
                        "success_rate": float(np.mean(ok)) if results else 0.0},
            "timing": (timing or StageTiming()).as_dict()}


def tension_trajectories_to_dict(results: list[TensionTrajectoryResult],
                                 timing: StageTiming | None, robot: Robot) -> dict[str, Any]:
    """The RESULT.json form of many tension trajectories (``cr-nlp plan --model
    cosserat``): the header (kind "tension_trajectory"), one entry per problem, a summary
    and the batch's ``timing`` (s); ``load_results`` reads every one back."""
    return {"kind": TensionTrajectoryResult.kind, "schema_version": SCHEMA_VERSION,
            "robot": robot.name, **_trajectories_fields(results, timing)}
