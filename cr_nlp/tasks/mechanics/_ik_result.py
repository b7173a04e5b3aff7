"""The result of tension-space IK (``tasks.mechanics.ik``) and its file forms."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..._files import atomic_open
from ...model import Robot
from ...model.cosserat import motor_commands
from .._result import ResultIO, Stage, Status, array, nums, read_stage, row_lists, status_of
from .._timing import StageTiming
from ._motion import EXACT_MODE

FAMILIES = ("limits", "clearance", "self_clearance")
"""The violation families of tension IK (``world.verdict.judge_many``)."""
ARRAYS = ("tensions", "target_position", "target_wxyz", "position", "wxyz", "pose_error",
          "position_error", "rotation_error", "min_clearance", "max_violation", "tip_force",
          "tip_moment", "gravity", "distributed_force", "tendon_displacements")
"""The float columns of ``TensionIKResult.columns`` (the per-target arrays)."""


@dataclass
class TensionIKResult(ResultIO):
    """One row per target (SI units; the tip as the independent forward solve puts it).

    It has no ``q``, on purpose: the answer is the tensions, and the shape they give is a
    Cosserat rod's (``model.cosserat``), not PCC arcs, so there is no configuration θ, φ, L
    to report without fitting one (which would be a second, inexact answer)."""

    kind: ClassVar[str] = "tension_ik"

    robot: Robot
    tensions: np.ndarray          # (B, n_tendons) N
    target_position: np.ndarray   # (B, 3) m
    target_wxyz: np.ndarray       # (B, 4), NaN rows: position-only targets
    position: np.ndarray          # (B, 3) tip of the verdict's forward solve, m
    wxyz: np.ndarray              # (B, 4) its orientation
    pose_error: np.ndarray        # (B,) m (see TensionIKConfig.tolerance)
    position_error: np.ndarray    # (B,) m
    rotation_error: np.ndarray    # (B,) rad, NaN for position-only targets
    min_clearance: np.ndarray     # (B,) m to the nearest obstacle (inf: no scene)
    max_violation: np.ndarray     # (B,) worst violation of the verdict
    success: np.ndarray           # (B,) bool
    reason: list[str]
    tip_force: np.ndarray         # (B, 3) N, world frame
    tip_moment: np.ndarray        # (B, 3) N·m
    gravity: np.ndarray           # (B, 3) m/s²
    distributed_force: np.ndarray | None = None  # (B, 3) N/m along the backbone; None: 0
    point_loads: list[list[dict]] | None = None
    """Per target, the point wrenches ``[{"s": m, "force": [N], "moment": [N·m]}, …]``,
    world frame (``solve_statics``' form); None: none."""
    tendon_displacements: np.ndarray | None = None   # (B, n_tendons) m, pulled > 0
    timing: StageTiming = field(default_factory=StageTiming)
    violations: dict[str, np.ndarray] = field(default_factory=dict)
    """Per family (``FAMILIES``: limits N outside [0, τ_max], clearance and
    self_clearance m below δ), (B,) the largest violation of each answer; NaN where not
    judged."""
    stage: list[Stage] = field(default_factory=list)
    """Per answer: ``Stage.REFINE`` (the LM in tension space), ``Stage.POLISH`` (exact
    mode: Ipopt's answer, accepted by the verdict), or ``Stage.REJECTED`` for a target refused
    before solving."""
    notes: list[list[str]] = field(default_factory=list)
    """Per answer, free text qualifying its stage (why a polish was not accepted)."""
    exact_mode: str = EXACT_MODE
    """The exact stage's formulation where it ran (``stages.polish``'s tension-IK
    ``EXACT_MODE``), else why there was none."""
    base_moment: np.ndarray | None = None
    """(B, 3) moment at the base of each solved rod, N·m, world frame (the verdict's
    statics; a warm start for the next solve). Not written to RESULT.json."""

    def __post_init__(self) -> None:
        count = len(self.tensions)
        if self.distributed_force is None:
            self.distributed_force = np.zeros((count, 3))
        if self.point_loads is None:
            self.point_loads = [[] for _ in range(count)]
        self.violations = {k: np.asarray(self.violations[k], dtype=float)
                           if k in self.violations else np.full(count, np.nan)
                           for k in FAMILIES}
        self.stage = [Stage(s) for s in self.stage] or [Stage.REFINE] * count
        self.notes = self.notes or [[] for _ in range(count)]

    @property
    def status(self) -> list[Status]:
        """Per answer, ``Status`` (success, failed, or rejected: never solved)."""
        return [status_of(bool(ok), s) for ok, s in zip(self.success, self.stage, strict=True)]

    def __len__(self) -> int:
        return len(self.tensions)

    def replace_rows(self, other: TensionIKResult, rows: np.ndarray,
                     from_rows: np.ndarray) -> None:
        """Rows ``rows`` of this result from rows ``from_rows`` of ``other`` (a solve of
        the same targets, e.g. from other seeds)."""
        for name in ("tensions", "position", "wxyz", "pose_error", "position_error",
                     "rotation_error", "min_clearance", "max_violation", "success",
                     "tendon_displacements", "base_moment"):
            if getattr(self, name) is None or getattr(other, name) is None:
                continue
            values = np.array(getattr(self, name))
            values[rows] = getattr(other, name)[from_rows]
            setattr(self, name, values)
        for k, values in other.violations.items():
            self.violations[k][rows] = values[from_rows]
        for i, j in zip(rows.tolist(), from_rows.tolist(), strict=True):
            self.reason[i] = other.reason[j]

    def summary(self) -> dict[str, Any]:
        """Success rate and position errors in mm, for people."""
        ok = self.success
        return {"targets": len(self), "success_rate": float(np.mean(ok)) if len(self) else 0.0,
                "median_position_error_mm": float(np.nanmedian(self.position_error) * 1e3)
                if len(self) else float("nan"),
                "max_position_error_mm": float(np.nanmax(self.position_error) * 1e3)
                if len(self) else float("nan"),
                "time_s": self.timing.total}

    def _fields_dict(self) -> dict[str, Any]:
        return {
            "tensions": row_lists(self.tensions),
            "target_position": row_lists(self.target_position),
            "target_wxyz": row_lists(self.target_wxyz),
            "position": row_lists(self.position), "wxyz": row_lists(self.wxyz),
            "pose_error": nums(self.pose_error), "position_error": nums(self.position_error),
            "rotation_error": nums(self.rotation_error),
            "min_clearance": nums(self.min_clearance),
            "max_violation": nums(self.max_violation),
            "success": [bool(s) for s in self.success], "reason": list(self.reason),
            "tip_force": row_lists(self.tip_force), "tip_moment": row_lists(self.tip_moment),
            "gravity": row_lists(self.gravity),
            "distributed_force": row_lists(self.distributed_force),
            "point_loads": self.point_loads,
            "tendon_displacements": row_lists(self.tendon_displacements),
            "violations": {k: nums(v) for k, v in self.violations.items()},
            "stage": [Stage(s).value for s in self.stage], "notes": self.notes,
            "status": [s.value for s in self.status], "exact_mode": self.exact_mode,
            "timing": self.timing.as_dict(), "summary": self.summary(),
        }

    @classmethod
    def _from_fields(cls, data: dict[str, Any], robot: Robot) -> TensionIKResult:
        n = robot.n_tendons
        count = len(data["tensions"])
        points = data.get("point_loads")
        if points is not None and (not isinstance(points, list) or len(points) != count
                                   or not all(isinstance(p, list) for p in points)):
            raise ValueError(f"point_loads: one list of point loads per target ({count}) "
                             "expected")
        stages = ([read_stage({"stage": s, "notes": m}, 2)
                   for s, m in zip(data["stage"], data["notes"], strict=True)]
                  if data["schema_version"] >= 2 else [])   # schema 1: every row refined

        def inf(values: list) -> np.ndarray:
            out = array(values)
            return np.where(np.isnan(out), np.inf, out)  # JSON keeps no infinity

        return cls(
            robot=robot, tensions=array(data["tensions"], n, "tensions"),
            target_position=array(data["target_position"], 3, "target_position"),
            target_wxyz=array(data["target_wxyz"], 4, "target_wxyz"),
            position=array(data["position"], 3, "position"),
            wxyz=array(data["wxyz"], 4, "wxyz"),
            pose_error=array(data["pose_error"]), position_error=array(data["position_error"]),
            rotation_error=array(data["rotation_error"]),
            min_clearance=inf(data["min_clearance"]),
            max_violation=array(data["max_violation"]),
            success=np.array(data["success"], dtype=bool), reason=list(data["reason"]),
            tip_force=array(data["tip_force"], 3, "tip_force"),
            tip_moment=array(data["tip_moment"], 3, "tip_moment"),
            gravity=array(data["gravity"], 3, "gravity"),
            distributed_force=array(data["distributed_force"], 3, "distributed_force")
            if "distributed_force" in data else None,   # files before the loads: none
            point_loads=points,
            tendon_displacements=array(data["tendon_displacements"], n,
                                       "tendon_displacements") if count else np.zeros((0, n)),
            timing=StageTiming.from_dict(data.get("timing")),
            violations={k: array(v, name=f"violations.{k}")
                        for k, v in data.get("violations", {}).items()},
            stage=[stage for stage, _ in stages], notes=[notes for _, notes in stages],
            exact_mode=str(data.get("exact_mode", EXACT_MODE)))

    def columns(self) -> dict[str, np.ndarray]:
        """The per-target fields as arrays: ``ARRAYS`` (SI units), success, reason, stage,
        ``violation_<family>``, and per target its point loads, notes and exact mode as
        JSON text or strings: the compact form a batch job's chunk files hold."""
        return {**{k: np.asarray(getattr(self, k), dtype=float) for k in ARRAYS},
                "success": np.asarray(self.success, dtype=bool),
                "reason": np.asarray(self.reason, dtype=str).reshape(-1),
                "stage": np.asarray([Stage(s).value for s in self.stage], dtype=str).reshape(-1),
                "notes": np.asarray([json.dumps(n) for n in self.notes], dtype=str).reshape(-1),
                "point_loads": np.asarray([json.dumps(p) for p in self.point_loads],
                                          dtype=str).reshape(-1),
                "exact_mode": np.asarray([self.exact_mode] * len(self), dtype=str).reshape(-1),
                **{f"violation_{k}": self.violations[k] for k in FAMILIES}}

    @classmethod
    def from_columns(cls, robot: Robot, columns: dict[str, np.ndarray],
                     timing: StageTiming | dict[str, float] | None = None) -> TensionIKResult:
        """The result of ``columns()`` (of one result, or concatenated over many); the
        exact mode is the one a polish ran with where any row has it."""
        if not isinstance(timing, StageTiming):
            timing = StageTiming.from_dict(timing)
        modes = {str(m) for m in columns["exact_mode"]} - {EXACT_MODE}
        return cls(robot=robot, **{k: np.asarray(columns[k], dtype=float) for k in ARRAYS},
                   success=np.asarray(columns["success"], dtype=bool),
                   reason=[str(x) for x in columns["reason"]],
                   stage=[str(x) for x in columns["stage"]],
                   notes=[json.loads(str(x)) for x in columns["notes"]],
                   point_loads=[json.loads(str(x)) for x in columns["point_loads"]],
                   exact_mode=min(modes) if modes else EXACT_MODE, timing=timing,
                   violations={k: np.asarray(columns[f"violation_{k}"], dtype=float)
                               for k in FAMILIES})

    def save_csv(self, path: str | Path) -> Path:
        """One row per target: target x, y, z (m), the tensions t1…tN (N), the reached tip
        x, y, z (m), position error (m), success; for a robot whose mechanics block has
        ``tendon_stiffness`` also the motor commands ``command_<j>_m`` (m, the
        displacements that make the displacement-driven rod hold these tensions)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        n = self.robot.n_tendons
        mech = self.robot.mechanics
        commands = (motor_commands(self.robot, self.tensions, self.tendon_displacements)
                    if mech is not None and mech.tendon_stiffness and len(self)
                    else np.zeros((len(self), 0)))
        with atomic_open(path, newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["target_x", "target_y", "target_z",
                             *(f"tension_{i + 1}_N" for i in range(n)),
                             "tip_x", "tip_y", "tip_z", "position_error", "success",
                             *(f"command_{i + 1}_m" for i in range(commands.shape[1]))])
            for i in range(len(self)):
                writer.writerow([*(f"{v:.9f}" for v in self.target_position[i]),
                                 *(f"{v:.6f}" for v in self.tensions[i]),
                                 *(f"{v:.9f}" for v in self.position[i]),
                                 f"{self.position_error[i]:.3e}", int(self.success[i]),
                                 *(f"{v:.9f}" for v in commands[i])])
        return path
