"""The result of trajectory planning: ``TrajectoryResult`` and its file forms (RESULT.json
for one or many trajectories, .npz, the controller's tendon-length CSV). Units: rad, m, s."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..._files import atomic_open
from ...model import Robot
from ...model.routing import tendon_names
from ...world._motion import MotionVerification
from .._result import (
    SCHEMA_VERSION,
    OneStage,
    ResultFileError,
    ResultIO,
    Stage,
    as_float,
    check_header,
    num,
    read_stage,
    result_robot,
    write_json,
    write_series_csv,
)
from .._timing import StageTiming


@dataclass
class TrajectoryResult(OneStage, ResultIO):
    """One planned trajectory (or the reason there is none). Units: rad, m, s.

    Its RESULT.json (``to_dict``) is a list of one: the form ``cr-nlp plan --out`` writes
    for many (``trajectories_to_dict``), so one file layout serves both."""

    kind: ClassVar[str] = "trajectory"

    robot: Robot
    q: np.ndarray | None
    """(H+1, 3n) waypoints θ, φ, L; None when the problem was rejected before planning."""
    dt: float
    """Seconds between waypoints."""
    success: bool
    """Verified (``world.verdict``, both modes): every violation ≤ 1e-6 along the whole
    motion by python-fcl and float64 re-evaluation: clearance ≥ δ, limits, tendon speed
    and acceleration limits."""
    reason: str
    """"" on success, else why it failed."""
    stage: Stage
    """What produced ``q``: ``Stage.REFINE`` (notes: the guess it started from,
    "roadmap", "straight" or "perturbed", then the polish's failure where the polish was
    tried: "polish failed: …", or "polish out of time: …" under ``polish_time_limit``),
    ``Stage.POLISH``; ``Stage.REJECTED`` for bad input, ``Stage.ERROR`` for a batch chunk
    that failed. A string "refine (roadmap)" is split into stage and notes."""
    path_length: float = math.nan
    """Tip path length along the interpolated motion, m."""
    min_clearance: float = math.nan
    """Smallest python-fcl distance along the motion, m (+inf without obstacles)."""
    max_violation: float = math.nan
    """Largest of ``violations``."""
    violations: dict[str, float] = field(default_factory=dict)
    """Largest violation per family: clearance (m below δ), limits (rad or m),
    tendon_speed (m/s), tendon_accel (m/s²)."""
    tendon_lengths: np.ndarray | None = None
    """(H+1, n_tendons) tendon lengths at the waypoints, m."""
    tendon_speed: float = math.nan
    """Largest |tendon speed| by finite differences, m/s."""
    tendon_accel: float = math.nan
    """Largest |tendon acceleration| by finite differences, m/s²."""
    cost: float = math.nan
    """The LM stage's final penalised cost ½‖r‖² of the chosen guess."""
    timing: StageTiming = field(default_factory=StageTiming)
    """Seconds per stage for this problem (shared batch work split evenly)."""
    tendon_displacements: np.ndarray | None = None
    """(H+1, n_tendons) motor commands at the waypoints, m (positive = pulled), when the
    robot file has an ``actuation`` block (``model.actuation``); else None."""
    notes: list[str] = field(default_factory=list)
    """Free text qualifying ``stage``, in order: the guess, then why no polish was
    accepted."""

    @property
    def times(self) -> np.ndarray:
        """(H+1,) time of each waypoint, seconds."""
        n = 0 if self.q is None else len(self.q)
        return np.arange(n) * self.dt

    def entry(self) -> dict[str, Any]:
        """This trajectory's entry of a RESULT.json ``results`` list."""
        ok = self.q is not None
        return {
            "success": bool(self.success),
            "q": self.q.tolist() if ok else None,
            "dt": float(self.dt),
            "times": self.times.tolist() if ok else None,
            "tendon_lengths": self.tendon_lengths.tolist() if self.tendon_lengths is not None
            else None,
            **({"tendon_displacements": self.tendon_displacements.tolist()}
               if self.tendon_displacements is not None else {}),
            "path_length": num(self.path_length),
            "min_clearance": num(self.min_clearance),
            "max_violation": num(self.max_violation),
            "violations": {k: num(v) for k, v in self.violations.items()},
            "tendon_speed": num(self.tendon_speed),
            "tendon_accel": num(self.tendon_accel),
            "cost": num(self.cost),
            "stage": Stage(self.stage).value,
            "notes": list(self.notes),
            "status": self.status.value,
            "reason": self.reason or None,
            "timing": self.timing.as_dict(),
        }

    @classmethod
    def from_entry(cls, robot: Robot, entry: dict[str, Any],
                   version: int = SCHEMA_VERSION) -> TrajectoryResult:
        """The result of one ``entry()`` (a row of a RESULT.json ``results`` list of schema
        ``version``)."""
        q, tendons = entry["q"], entry["tendon_lengths"]
        stage, notes = read_stage(entry, version)
        return cls(
            robot, None if q is None else np.asarray(q, dtype=float).reshape(-1, robot.dof),
            float(entry["dt"]), bool(entry["success"]), entry["reason"] or "", stage,
            notes=notes,
            path_length=as_float(entry["path_length"], "path_length"),
            min_clearance=as_float(entry["min_clearance"], "min_clearance"),
            max_violation=as_float(entry["max_violation"], "max_violation"),
            violations={k: as_float(v, f"violations.{k}") for k, v in entry["violations"].items()},
            tendon_lengths=None if tendons is None else np.asarray(tendons, dtype=float),
            tendon_speed=as_float(entry["tendon_speed"], "tendon_speed"),
            tendon_accel=as_float(entry["tendon_accel"], "tendon_accel"),
            cost=as_float(entry.get("cost"), "cost"),
            timing=StageTiming.from_dict(entry["timing"]))

    def _fields_dict(self) -> dict[str, Any]:
        return _trajectories_fields([self], self.timing)

    @classmethod
    def _from_fields(cls, data: dict[str, Any], robot: Robot) -> TrajectoryResult:
        entries = data["results"]
        if len(entries) != 1:
            raise ResultFileError(f"holds {len(entries)} trajectories, not one: read it with "
                                  f"load_results / trajectories_from_dict")
        return cls.from_entry(robot, entries[0], data["schema_version"])

    @classmethod
    def list_from_dict(cls, data: Any, robot: Robot | str | None = None,
                       source: str = "") -> list[TrajectoryResult]:
        """Every trajectory of a RESULT.json's content (``trajectories_to_dict``)."""
        return trajectories_from_dict(data, robot, source)

    def save_csv(self, path: str | Path) -> Path:
        """The tendon-length series for a controller: a ``time_s`` column, then one column
        per tendon (``tendon_<segment>_<j>`` for per-segment routing, ``tendon_<j>`` for
        shared), lengths in metres, one row per waypoint."""
        if self.tendon_lengths is None:
            raise ValueError(f"no trajectory to save ({self.reason})")
        return write_series_csv(path, self.times, *controller_columns(
            self.robot, self.tendon_lengths, self.tendon_displacements))

    def save_npz(self, path: str | Path) -> None:
        """q, times, dt, tendon lengths and the scalar verdicts as a numpy .npz file."""
        n_t = self.robot.n_tendons
        path = Path(path)
        if not path.name.endswith(".npz"):  # as np.savez names a file
            path = path.with_name(path.name + ".npz")
        with atomic_open(path, "wb") as handle:
            np.savez(handle, q=self.q if self.q is not None else np.zeros((0, self.robot.dof)),
                     times=self.times, dt=self.dt, success=self.success,
                     tendon_lengths=(self.tendon_lengths if self.tendon_lengths is not None
                                     else np.zeros((0, n_t))),
                     path_length=self.path_length, min_clearance=self.min_clearance,
                     max_violation=self.max_violation, reason=self.reason,
                     stage=self.stage_text)


def controller_columns(robot: Robot, lengths: np.ndarray,
                       displacements: np.ndarray | None) -> tuple[list[str], np.ndarray]:
    """A controller's time-series columns: the tendon lengths (m, ``tendon_names``), then
    the motor commands (``<tendon name>_displacement``, m) when there are any; the names and
    the (T, columns) values."""
    if displacements is None:
        return tendon_names(robot), lengths
    return ([*tendon_names(robot), *(f"{name}_displacement" for name in tendon_names(robot))],
            np.hstack([lengths, displacements]))


def _trajectories_fields(results: list[TrajectoryResult],
                         timing: StageTiming | dict[str, float] | None) -> dict[str, Any]:
    ok = [r.success for r in results]
    lengths = [r.path_length for r in results if r.success]
    if not isinstance(timing, StageTiming):
        timing = StageTiming.from_dict(timing)
    return {
        "results": [r.entry() for r in results],
        "summary": {"problems": len(results),
                    "success_rate": float(np.mean(ok)) if results else 0.0,
                    "median_path_length": float(np.median(lengths)) if lengths else None},
        "timing": timing.as_dict(),
    }


def trajectories_to_dict(results: list[TrajectoryResult],
                         timing: StageTiming | dict[str, float] | None = None,
                         robot: Robot | None = None) -> dict[str, Any]:
    """The RESULT.json form of many trajectories (``cr-nlp plan``): the header (kind
    "trajectory"), one entry per result, a summary and the batch's ``timing`` (s).
    ``robot`` names the robot of an empty list."""
    name = results[0].robot.name if results else (robot.name if robot is not None else None)
    return {"kind": TrajectoryResult.kind, "schema_version": SCHEMA_VERSION,
            "robot": name, **_trajectories_fields(results, timing)}


def trajectories_from_dict(data: Any, robot: Robot | str | None = None,
                           source: str = "") -> list[TrajectoryResult]:
    """Every ``TrajectoryResult`` of ``trajectories_to_dict``'s form."""
    where = source or "the result"
    check_header(data, where, kind=TrajectoryResult.kind)
    robot = result_robot(data, robot, where)
    try:
        return [TrajectoryResult.from_entry(robot, e, data["schema_version"])
                for e in data["results"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise ResultFileError(f"{where}: not a valid trajectory result ({exc!r})") from None


def save_results(results: list[TrajectoryResult], path: str | Path,
                 timing: StageTiming | dict[str, float] | None = None,
                 robot: Robot | None = None) -> Path:
    """Write ``trajectories_to_dict`` to ``path`` (.json) or every result to one .npz
    (``q_<i>``, ``tendon_lengths_<i>``, ``success``, ``dt``) by the file's suffix."""
    path = Path(path)
    if path.suffix != ".npz":
        return write_json(trajectories_to_dict(results, timing, robot), path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, Any] = {
        "success": np.array([r.success for r in results]),
        "dt": np.array([r.dt for r in results]),
        "path_length": np.array([r.path_length for r in results]),
        "max_violation": np.array([r.max_violation for r in results]),
    }
    for i, r in enumerate(results):
        if r.q is not None:
            arrays[f"q_{i}"] = r.q
            arrays[f"tendon_lengths_{i}"] = r.tendon_lengths
    with atomic_open(path, "wb") as handle:
        np.savez(handle, **arrays)
    return path



def result_from_verdict(robot: Robot, q: np.ndarray, dt: float, verdict: MotionVerification,
                        stage: Stage | str, cost: float, timing: StageTiming) -> TrajectoryResult:
    """The result of trajectory ``q`` (rad, rad, m; ``dt`` s) judged by ``verdict``
    (``world._motion.verify_trajectory``'s report); ``stage`` may carry its notes in
    parentheses ("refine (roadmap)")."""
    return TrajectoryResult(
        robot, q, dt, bool(verdict.success), verdict.reason, stage,
        path_length=verdict.path_length, min_clearance=verdict.min_clearance,
        max_violation=verdict.max_violation, violations=verdict.violations,
        tendon_lengths=verdict.tendon_lengths, tendon_speed=verdict.tendon_speed,
        tendon_accel=verdict.tendon_accel, cost=cost, timing=timing)
