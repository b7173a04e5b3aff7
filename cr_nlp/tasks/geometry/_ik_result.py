"""The IK result: one row per target, its summary, and its JSON, CSV and column forms."""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..._files import atomic_open
from ...model import Robot
from ...world.verdict import Verdicts
from .._result import (
    ResultIO,
    Stage,
    Status,
    array,
    nums,
    read_stage,
    row_lists,
    stage_texts,
    statuses,
    typed_stages,
)
from .._timing import StageTiming


@dataclass(frozen=True)
class IKVerification:
    """``IKSolver.verify``'s report on B answers: their float64 re-evaluation, independent
    of the optimiser, and the verdict on each (``world.verdict.judge_many``). Arrays (B, …);
    units m, rad."""

    position: np.ndarray
    """(B, 3) tip positions reached, m."""
    wxyz: np.ndarray
    """(B, 4) tip orientations reached, unit quaternions."""
    pose_error: np.ndarray
    """(B,) ‖log(T_tip⁻¹·T_target)‖ (mixed m/rad)."""
    position_error: np.ndarray
    """(B,) m."""
    rotation_error: np.ndarray
    """(B,) rad."""
    obstacle_clearance: np.ndarray
    """(B,) python-fcl distance to the nearest obstacle, m; +inf without a scene."""
    self_clearance: np.ndarray
    """(B,) distance between segments at least two apart, m; +inf where not checked."""
    clearance: np.ndarray
    """(B,) the smaller of the two, m; NaN when neither is checked."""
    collision_free: np.ndarray
    """(B,) bool: no obstacle or self penetration."""
    verdicts: Verdicts
    """The verdict on each answer."""

    @property
    def success(self) -> np.ndarray:
        """(B,) bool: the verdict accepts the answer."""
        return self.verdicts.success

    @property
    def reason(self) -> np.ndarray:
        """(B,) str (object array): "" on success, else why not."""
        return np.array(self.verdicts.reason, dtype=object)

    @property
    def violations(self) -> dict[str, np.ndarray]:
        """Per family (limits, clearance, self_clearance), (B,) the largest violation."""
        return dict(self.verdicts.violations)

    @property
    def max_violation(self) -> np.ndarray:
        """(B,) the largest of ``violations`` (rad or m)."""
        return self.verdicts.max_violation

    def take(self, rows: Any) -> IKVerification:
        """The report on answers ``rows`` (an index array, or a slice)."""
        def part(values: np.ndarray) -> np.ndarray:
            return np.asarray(values)[rows]

        verdicts = self.verdicts
        return IKVerification(
            part(self.position), part(self.wxyz), part(self.pose_error),
            part(self.position_error), part(self.rotation_error),
            part(self.obstacle_clearance), part(self.self_clearance), part(self.clearance),
            part(self.collision_free),
            Verdicts(success=part(verdicts.success), reason=tuple(part(self.reason).tolist()),
                     violations={k: part(v) for k, v in verdicts.violations.items()},
                     max_violation=part(verdicts.max_violation)))


PER_TARGET = ("pose_error", "position_error", "rotation_error", "max_violation",
               "min_clearance")
"""The float columns of an ``IKResult`` that ``IKSolver.verify`` fills per target."""
VERIFIED = {"min_clearance": "clearance"}
"""``IKResult`` column → the field of ``IKVerification`` where they differ."""
FAMILIES = ("limits", "clearance", "self_clearance")
"""The violation families of IK (``world.verdict.UNITS``), each an ``IKResult.violations``
column."""
COLUMNS = ("q", "position", "wxyz", *PER_TARGET, "collision_free", "success", "stage",
           "reason", *(f"violation_{k}" for k in FAMILIES))
"""The per-target fields of an ``IKResult`` (``IKResult.columns``; ``stage`` as
``stage_text``, its notes included)."""


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
    stage: list[Stage]             # which stage produced each answer (a string such as
    #                                "refine (polish failed: …)" is split into stage and notes)
    reason: list[str]              # empty on success, else why it failed
    timing: StageTiming = field(default_factory=StageTiming)
    has_scene: bool = False
    tendon_displacements: np.ndarray | None = None
    """(T, n_tendons) motor commands reproducing each answer, m (positive = pulled), when
    the robot file has an ``actuation`` block (``model.actuation``); else None."""
    notes: list[list[str]] = field(default_factory=list)
    """Per answer, the free text that qualifies its stage ("polish failed: …"); empty
    lists by default."""
    violations: dict[str, np.ndarray] = field(default_factory=dict)
    """Per family (``FAMILIES``: limits rad or m, clearance and self_clearance m below δ),
    (T,) the largest violation of each answer (``world.verdict``); NaN where not judged."""

    def __post_init__(self) -> None:
        super().__post_init__()
        self.stage, self.notes = typed_stages(self.stage, self.notes or None)
        self.violations = {k: np.asarray(self.violations[k], dtype=float)
                           if k in self.violations else np.full(len(self.q), np.nan)
                           for k in FAMILIES}

    def store(self, rows: Any, checked: IKVerification) -> None:
        """The report ``checked`` on answers ``rows`` (``IKSolver.verify``) into their
        columns: reached pose, errors, clearance, violations and the verdict."""
        for k in ("position", "wxyz", "collision_free", "success", *PER_TARGET):
            getattr(self, k)[rows] = getattr(checked, VERIFIED.get(k, k))
        for k in FAMILIES:
            self.violations[k][rows] = checked.violations[k]
        at = np.arange(len(self))[rows].reshape(-1).tolist()
        why = list(map(str, checked.verdicts.reason))
        if len(at) != len(why):
            raise ValueError(f"{len(why)} verdicts for {len(at)} rows")
        list(map(self.reason.__setitem__, at, why))     # no Python call per row

    def set_stage(self, i: int, stage: Stage, *notes: str) -> None:
        """Answer i was produced by ``stage``; ``notes`` say why (they replace any)."""
        self.stage[i], self.notes[i] = Stage(stage), list(notes)

    @property
    def stage_text(self) -> list[str]:
        """Per answer, the stage and its notes for people: "refine (polish failed: …)"."""
        return stage_texts(self.stage, self.notes)

    @property
    def status(self) -> list[Status]:
        """Per answer, ``Status``: success, failed (solved, rejected by the verdict) or
        rejected (never solved)."""
        return statuses(self.success, self.stage)

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
        status = self.status
        violations = {k: nums(v) for k, v in self.violations.items()}
        entries = [{"q": q[i], "theta": theta[i], "phi": phi[i], "length": length[i],
                    "position": position[i], "wxyz": wxyz[i], "pose_error": pose_error[i],
                    "position_error": position_error[i],
                    "rotation_error": rotation_error[i], "success": success[i],
                    "collision_free": collision_free[i], "min_clearance": min_clearance[i],
                    "max_violation": max_violation[i],
                    "violations": {k: v[i] for k, v in violations.items()},
                    "stage": Stage(self.stage[i]).value, "notes": self.notes[i],
                    "status": status[i].value, "reason": self.reason[i] or None}
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
        version = data["schema_version"]
        judged = version >= 2 and entries   # schema 1 kept no violations per family

        def column(name: str, width: int | None = None) -> np.ndarray:
            return array([e[name] for e in entries], width, name)

        pose = (column("q", robot.dof), column("position", 3), column("wxyz", 4))
        stages = [read_stage(e, version) for e in entries]
        return cls(
            robot, *pose, **{k: column(k) for k in PER_TARGET},
            collision_free=np.array([bool(e["collision_free"]) if has_scene else True
                                     for e in entries], dtype=bool),
            success=np.array([bool(e["success"]) for e in entries], dtype=bool),
            stage=[stage for stage, _ in stages], notes=[notes for _, notes in stages],
            reason=[e["reason"] or "" for e in entries],
            violations={k: array([e["violations"].get(k) for e in entries], name=k)
                        for k in FAMILIES} if judged else {},
            timing=StageTiming.from_dict(data.get("timing")), has_scene=has_scene)

    def columns(self) -> dict[str, np.ndarray]:
        """The per-target fields as arrays (``COLUMNS``; stage and reason as strings): the
        compact form a batch job's chunk files hold."""
        out = {k: np.asarray(getattr(self, k), dtype=str if k == "reason" else None)
               for k in COLUMNS[:-len(FAMILIES)] if k != "stage"}
        return {**out, "stage": np.asarray(self.stage_text, dtype=str),
                **{f"violation_{k}": self.violations[k] for k in FAMILIES}}

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
            violations={k: np.asarray(columns[f"violation_{k}"], dtype=float)
                        for k in FAMILIES if f"violation_{k}" in columns},
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
        stages = self.stage_text
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
                                 stages[i], self.reason[i]])
        return path
