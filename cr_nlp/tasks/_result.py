"""The one result protocol of the tasks (``RESULT_KINDS``: PCC IK, trajectory and follow,
and their tension-space twins of the mechanics family).

Every result class mixes in ``ResultIO``: ``to_dict()`` / ``from_dict(data)`` (the
RESULT.json form), ``save(path)`` (JSON), ``load(path)``, ``save_csv(path)``. Its JSON
carries ``"kind"`` (the registry key below) and ``"schema_version"``, and the same field
names for the same quantities in every kind: ``q`` (rad, rad, m), ``success``,
``reason``, ``stage`` (a ``Stage``) with ``notes`` (the free text that qualifies it),
``status`` (a ``Status``, written for readers; derived from ``success`` and ``stage``),
``violations`` (largest violation per family, ``world.verdict.UNITS``), ``pose_error`` (the
‖log(T⁻¹·T_target)‖ metric), ``position_error`` (m), ``rotation_error`` (rad),
``min_clearance`` (m, python-fcl), ``max_violation``, ``timing`` (seconds per stage,
``StageTiming``). Arrays are SI; millimetre / degree figures appear only in summaries.

``load_result(path)`` / ``result_from_dict(data)`` read any kind by its ``"kind"``, of
this schema version or the one before (``READS``). A new kind registers with one line in
``RESULT_KINDS``.

Schema 2 (this version) writes ``stage`` as a ``Stage`` value and its free text apart, in
``notes``; schema 1 wrote both in one string, "refine (polish failed: …)", which
``split_stage`` takes apart on reading. ``stage_text`` joins them again for people (the
CLI, summaries): the same text as schema 1 held.
"""

from __future__ import annotations

import contextlib
import csv
import enum
import gc
import importlib
import json
import math
from collections.abc import Callable, Iterator, Sequence
from operator import itemgetter
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from .._files import InputFileError, atomic_open, read_json_or
from ..model.actuation import planned_displacements

if TYPE_CHECKING:
    from ..model import Robot

SCHEMA_VERSION = 2
"""Version of the RESULT.json layout; bumped when a field changes meaning or name."""

READS = (1, SCHEMA_VERSION)
"""The schema versions ``load_result`` reads: this one and the one before (version 1 held
``stage`` and its notes in one string; it had no ``notes``, ``status``, nor IK
``violations``)."""

RESULT_KINDS: dict[str, str] = {
    "ik": "cr_nlp.tasks.geometry.ik:IKResult",
    "trajectory": "cr_nlp.tasks.geometry.trajectory:TrajectoryResult",
    "follow": "cr_nlp.tasks.geometry.follow:FollowResult",
    "tension_ik": "cr_nlp.tasks.mechanics.ik:TensionIKResult",
    "tension_follow": "cr_nlp.tasks.mechanics.follow:TensionFollowResult",
    "tension_trajectory": "cr_nlp.tasks.mechanics.trajectory:TensionTrajectoryResult",
}
"""kind → "module:class" of its result class (imported on first use)."""


class ResultFileError(InputFileError):
    """A RESULT.json (or its dict) that is not a result this version reads; the message
    names the file and the field."""


# ================================================================ stage and status


class Stage(enum.StrEnum):
    """What produced an answer (docs/design.md §2). A ``str``: ``stage == "polish"``
    holds, and it is written to JSON as its value. Why it is that stage (a polish that
    failed, the guess a trajectory started from) is free text in the result's ``notes``."""

    SEARCH = "search"
    """Live IK: the batched IK search (explore, then refine) answered."""
    EXPLORE = "explore"
    """Stage 1's answer as it was, no LM after it (a tension plan's straight-leg search
    where the refined motion did not verify)."""
    REFINE = "refine"
    """The batched penalty LM (stage 2)."""
    POLISH = "polish"
    """Ipopt with the constraints as constraints (stage 3), accepted by the verdict."""
    REJECTED = "rejected"
    """Every task: the input (a target, a problem) was refused before solving (``reason``
    says why)."""
    ERROR = "error"
    """A batch job's chunk failed before solving (``cr_nlp.batch``)."""
    NONE = "rejected"
    """Deprecated alias of ``REJECTED`` (IK's refused targets were ``"none"`` until
    2026-12-02; files that say so still read as ``REJECTED``)."""

    @classmethod
    def _missing_(cls, value: object) -> Stage | None:
        return cls.REJECTED if value == "none" else None


class Status(enum.StrEnum):
    """The outcome of one answer, from ``success`` and ``stage`` (``status_of``)."""

    SUCCESS = "success"
    """The verdict (``world.verdict``) accepts the answer."""
    FAILED = "failed"
    """Solved, and the verdict rejects the answer (``reason`` says why)."""
    REJECTED = "rejected"
    """Never solved: the input was refused or its chunk failed (``reason`` says why)."""


_UNSOLVED = (Stage.REJECTED, Stage.ERROR)


def status_of(success: bool, stage: Stage | str) -> Status:
    """The ``Status`` of an answer that ``success`` judges and ``stage`` produced."""
    if success:
        return Status.SUCCESS
    return Status.REJECTED if Stage(stage) in _UNSOLVED else Status.FAILED


def split_stage(text: Stage | str) -> tuple[Stage, list[str]]:
    """A stage with its notes in parentheses, as schema 1 wrote it ("refine (roadmap)
    (polish failed: …)"), → (``Stage.REFINE``, ["roadmap", "polish failed: …"]). A note
    may hold parentheses of its own ("… the time limit (7 iterations, 2 s)").

    Raises:
        ValueError: not a known stage, or unbalanced parentheses.
    """
    if isinstance(text, Stage):
        return text, []
    head, _, rest = str(text).partition(" (")
    notes: list[str] = []
    rest = f"({rest}" if rest else ""
    while rest:
        depth, end = 0, -1
        for k, char in enumerate(rest):
            depth += {"(": 1, ")": -1}.get(char, 0)
            if depth == 0:
                end = k
                break
        if not rest.startswith("(") or end < 0:
            raise ValueError(f"stage {text!r:.60}: unbalanced parentheses")
        notes.append(rest[1:end])
        rest = rest[end + 1:].lstrip(" ")
    try:
        return Stage(head), notes
    except ValueError:
        raise ValueError(f"unknown stage {head!r:.40}; known: "
                         f"{', '.join(s.value for s in Stage)}") from None


def stage_text(stage: Stage | str, notes: list[str] | tuple[str, ...] = ()) -> str:
    """The stage and its notes for people, each note in parentheses: "refine (polish
    failed: …)" (the inverse of ``split_stage``; what schema 1 wrote)."""
    return "".join([Stage(stage).value, *(f" ({note})" for note in notes)])


def read_stage(entry: dict[str, Any], version: int) -> tuple[Stage, list[str]]:
    """``stage`` and ``notes`` of a RESULT.json entry of schema ``version``."""
    if version < 2:
        return split_stage(entry["stage"])
    return Stage(entry["stage"]), [str(note) for note in entry.get("notes") or []]


def typed_stage(stage: Stage | str, notes: list[str] | None) -> tuple[Stage, list[str]]:
    """``stage`` as a ``Stage`` and its notes: those in parentheses in a ``stage`` string
    ("refine (roadmap)", the form schema 1 and older callers used), then ``notes``."""
    stage, more = split_stage(stage)
    return stage, [*more, *(notes or [])]


def _per_object(values: Sequence[Any], fn: Callable[[Any], Any]) -> list[Any]:
    """``fn`` of every entry of ``values``, called once per distinct object (by identity:
    hashing a ``Stage`` runs ``Enum.__hash__``, a Python call per entry)."""
    keys = list(map(id, values))
    done = {key: fn(value) for key, value in dict(zip(keys, values, strict=True)).items()}
    return list(map(done.__getitem__, keys))


def _with_notes(notes: Sequence[Any]) -> list[int]:
    """Indices of the entries of ``notes`` that are not empty."""
    return np.flatnonzero(np.fromiter(map(bool, notes), bool, len(notes))).tolist()


@contextlib.contextmanager
def _young_objects_only() -> Iterator[None]:
    """While a block makes many small containers (a note list per answer), Python's
    collections it triggers look at young objects only: everything older is frozen
    (``gc.freeze``) for the block and thawed after. Otherwise a collection on the way
    walks every object the process holds (JAX's among them): 0.08–0.18 s for 10⁵ empty
    lists, measured, against 0.015 s. Nothing is done where the process froze objects of
    its own (thawing would undo that)."""
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def typed_stages(stages: Sequence[Stage | str], notes: Sequence[list[str] | None] | None = None
                 ) -> tuple[list[Stage], list[list[str]]]:
    """``typed_stage`` over a batch of answers, called once per distinct stage object
    rather than per answer (a solve of 10⁵ targets holds two or three): the stages as
    ``Stage``s and each answer's notes (a new list each), those in parentheses in its
    stage text first, then its entry of ``notes`` (None: none)."""
    if notes is not None and len(notes) != len(stages):
        raise ValueError(f"{len(notes)} notes for {len(stages)} stages")
    pairs = _per_object(stages, lambda stage: typed_stage(stage, None))
    with _young_objects_only():
        out_notes = list(map(list, map(itemgetter(1), pairs)))
    for i in _with_notes(notes or ()):
        out_notes[i] += notes[i]        # type: ignore[index]
    return list(map(itemgetter(0), pairs)), out_notes


_STATUS_CHOICES = np.array([Status.FAILED, Status.REJECTED, Status.SUCCESS], dtype=object)


def statuses(success: Any, stages: Sequence[Stage | str]) -> list[Status]:
    """``status_of`` over a batch: (B,) ``success`` and B stages → B ``Status``es, in
    numpy and one stage lookup per distinct stage object rather than a call per answer."""
    success = np.asarray(success, dtype=bool).reshape(-1)
    if len(stages) != len(success):
        raise ValueError(f"{len(success)} success flags for {len(stages)} stages")
    unsolved = np.array(_per_object(stages, lambda stage: Stage(stage) in _UNSOLVED), bool)
    return _STATUS_CHOICES[np.where(success, 2, unsolved.reshape(-1).astype(np.int64))].tolist()


def stage_texts(stages: Sequence[Stage | str], notes: Sequence[Sequence[str]]) -> list[str]:
    """``stage_text`` over a batch: one call per distinct stage object and one per answer
    that carries notes."""
    texts = _per_object(stages, lambda stage: Stage(stage).value)
    for i in _with_notes(notes):
        texts[i] = stage_text(stages[i], notes[i])
    return texts


# ================================================================ JSON values


def num(x: Any) -> float | None:
    """A float for JSON: None where absent or not finite (JSON has no NaN/inf)."""
    return float(x) if x is not None and np.isfinite(x) else None


def nums(values: Any) -> list[float | None]:
    """A 1-D array as floats, None where not finite. Whole columns at once: per-element
    indexing cost ~15 ms per 1000 rows."""
    values = np.asarray(values, dtype=float)
    return [v if f else None
            for v, f in zip(values.tolist(), np.isfinite(values).tolist(), strict=True)]


def row_lists(values: Any, keep: list[bool] | None = None) -> list[list[float] | None]:
    """Rows of a 2-D array as lists; None where ``keep`` is False (default: where a row
    has a non-finite entry)."""
    values = np.asarray(values, dtype=float)
    if keep is None:
        keep = np.all(np.isfinite(values), axis=1).tolist() if values.size else [True] * len(
            values)
    return [row if k else None for row, k in zip(values.tolist(), keep, strict=True)]


def as_float(value: Any, name: str = "value") -> float:
    """A JSON number back to a float: None → NaN. Raises ``ResultFileError`` naming
    ``name`` for anything else."""
    if value is None:
        return math.nan
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ResultFileError(f"{name}: expected a number or null, got {value!r:.40}") from None
    except OverflowError:  # an integer past float's range
        raise ResultFileError(f"{name}: {value!r:.40} is too large for a float") from None


def array(values: Any, width: int | None = None, name: str = "array") -> np.ndarray:
    """A JSON list (1-D, or rows of ``width`` with None for a missing row or entry) back
    to a float64 array with NaN for None. Raises ``ResultFileError`` naming ``name``, the
    row and the entry."""
    if isinstance(values, (str, bytes, dict)) or not hasattr(values, "__len__"):
        raise ResultFileError(f"{name}: expected a list, got {type(values).__name__}")
    if width is None:
        return np.array([as_float(v, f"{name}[{i}]") for i, v in enumerate(values)],
                        dtype=float)
    out = np.full((len(values), width), np.nan)
    for i, row in enumerate(values):
        if row is not None:
            if isinstance(row, (str, bytes, dict)) or not hasattr(row, "__len__"):
                raise ResultFileError(f"{name}[{i}]: expected a list of {width} numbers, "
                                      f"got {type(row).__name__}")
            if len(row) != width:
                raise ResultFileError(f"{name}[{i}] has {len(row)} entries, expected {width}")
            out[i] = [as_float(v, f"{name}[{i}][{j}]") for j, v in enumerate(row)]
    return out


def write_json(data: dict[str, Any], path: str | Path, indent: int | None = 2) -> Path:
    """Write ``data`` as JSON to ``path`` (its folder made; atomically: a reader sees the
    old file or the whole new one); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as handle:
        handle.write(json.dumps(data, indent=indent) + "\n")
    return path


def write_series_csv(path: str | Path, times: np.ndarray, names: list[str],
                     values: np.ndarray) -> Path:
    """A time series for a controller: a ``time_s`` column, then one column per name
    (``values`` (T, len(names)), e.g. tendon lengths in m); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["time_s", *names])
        for t, row in zip(times, values, strict=True):
            writer.writerow([f"{t:.6f}", *(f"{v:.9f}" for v in row)])
    return path


# ================================================================ the protocol


class OneStage:
    """The stage of a result of one problem (trajectory, follow): ``stage`` typed as a
    ``Stage`` with its free text in ``notes`` on construction (an old one-line text is
    split), ``stage_text`` and ``status`` derived from them. Mixed in before
    ``ResultIO``."""

    stage: Stage
    notes: list[str]
    success: bool

    def __post_init__(self) -> None:
        super().__post_init__()  # type: ignore[misc]
        self.stage, self.notes = typed_stage(self.stage, self.notes)

    @property
    def stage_text(self) -> str:
        """The stage and its notes for people: "refine (roadmap) (polish failed: …)"."""
        return stage_text(self.stage, self.notes)

    @property
    def status(self) -> Status:
        """``Status``: success, failed (rejected by the verdict) or rejected (refused
        before solving)."""
        return status_of(self.success, self.stage)


class ResultIO:
    """What every task result provides. A class sets ``kind`` and implements
    ``_fields_dict`` (its fields, JSON-ready, without the header) and
    ``_from_fields(data, robot)``, and ``save_csv``."""

    kind: ClassVar[str]
    robot: Robot
    q: np.ndarray
    tendon_displacements: np.ndarray | None

    def __post_init__(self) -> None:
        # Plans in motor commands: a robot with a calibrated zero (an ``actuation`` block)
        # gets the displacements that reproduce its configurations (model.actuation).
        if self.tendon_displacements is None:
            self.tendon_displacements = planned_displacements(self.robot, self.q)

    def _fields_dict(self) -> dict[str, Any]:
        raise NotImplementedError

    @classmethod
    def _from_fields(cls, data: dict[str, Any], robot: Robot) -> Any:
        raise NotImplementedError

    def save_csv(self, path: str | Path) -> Path:
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        """The RESULT.json form: ``kind``, ``schema_version``, ``robot`` (its name), then
        the fields."""
        return {"kind": self.kind, "schema_version": SCHEMA_VERSION,
                "robot": self.robot.name, **self._fields_dict()}

    @classmethod
    def from_dict(cls, data: Any, robot: Robot | str | None = None, source: str = "") -> Any:
        """The result of ``to_dict``'s form. ``robot``: the ``Robot`` it is for (default:
        the bundled robot the file names); ``source`` names the file in errors.

        Raises:
            ResultFileError: not a result of this kind, another schema version, or for
                another robot.
        """
        where = source or "the result"
        check_header(data, where, kind=cls.kind)
        robot = result_robot(data, robot, where)
        try:
            return cls._from_fields(data, robot)
        except (KeyError, TypeError, ValueError, OverflowError, IndexError,
                AttributeError) as exc:  # a field of the wrong shape or type
            if isinstance(exc, ResultFileError):
                raise ResultFileError(f"{where}: {exc}") from None
            field = f"field {exc}" if isinstance(exc, KeyError) else str(exc)
            raise ResultFileError(f"{where}: not a valid {cls.kind} result ({field})") from None

    @classmethod
    def list_from_dict(cls, data: Any, robot: Robot | str | None = None,
                       source: str = "") -> list[Any]:
        """Every result a file of this kind holds (one, except trajectory files)."""
        return [cls.from_dict(data, robot, source)]

    def save(self, path: str | Path, indent: int | None = 2) -> Path:
        """Write ``to_dict`` as JSON to ``path``; returns the path."""
        return write_json(self.to_dict(), path, indent)

    @classmethod
    def load(cls, path: str | Path, robot: Robot | str | None = None) -> Any:
        """The result saved in ``path`` (``save``)."""
        return cls.from_dict(read_json(path), robot, source=str(path))


def check_header(data: Any, where: str, kind: str | None = None) -> str:
    """The ``kind`` of a RESULT.json's content, after checking its header."""
    if not isinstance(data, dict):
        raise ResultFileError(f"{where}: a result must be a JSON object "
                              f"(cr-nlp ik, plan or follow --out)")
    if "kind" not in data:
        raise ResultFileError(
            f"{where}: no 'kind' field: not a result of cr-nlp ik, plan or follow --out, or "
            f"written before schema_version {SCHEMA_VERSION} (solve again to rewrite it)")
    found = data["kind"]
    if found not in RESULT_KINDS:
        raise ResultFileError(f"{where}: unknown kind {found!r}; known kinds: "
                              f"{', '.join(RESULT_KINDS)}")
    if kind is not None and found != kind:
        raise ResultFileError(f"{where}: holds a {found!r} result, not {kind!r}")
    version = data.get("schema_version")
    if version not in READS or isinstance(version, bool):
        raise ResultFileError(f"{where}: schema_version {version!r}; this version of cr_nlp "
                              f"reads {' and '.join(map(str, READS))}")
    return found


def result_robot(data: dict[str, Any], robot: Robot | str | None, where: str) -> Robot:
    """The robot a result is for: ``robot`` (checked against the file's name), or the
    bundled robot of that name."""
    from ..model import load_robot

    name = data.get("robot")
    if robot is None:
        if not isinstance(name, str):
            raise ResultFileError(f"{where}: no 'robot' name; pass the robot")
        return load_robot(name)
    robot = load_robot(robot)
    if name is not None and name != robot.name:
        raise ResultFileError(f"{where}: the result is for robot {name!r}, not {robot.name!r}")
    return robot


def read_json(path: str | Path) -> Any:
    """The JSON content of a result file."""
    return read_json_or(path, lambda reason: ResultFileError(f"{path}: {reason}"))


def result_class(kind: str) -> type:
    """The result class registered for ``kind``."""
    if kind not in RESULT_KINDS:
        raise ResultFileError(f"unknown result kind {kind!r}; known: {', '.join(RESULT_KINDS)}")
    module, name = RESULT_KINDS[kind].split(":")
    return getattr(importlib.import_module(module), name)


def results_from_dict(data: Any, robot: Robot | str | None = None,
                      source: str = "") -> list[Any]:
    """Every result of a RESULT.json's content, of whichever kind it names."""
    kind = check_header(data, source or "the result")
    return result_class(kind).list_from_dict(data, robot, source)


def result_from_dict(data: Any, robot: Robot | str | None = None, source: str = "") -> Any:
    """The result of a RESULT.json's content (``IKResult``, ``TrajectoryResult``,
    ``FollowResult``, …, by its ``kind``)."""
    kind = check_header(data, source or "the result")
    return result_class(kind).from_dict(data, robot, source)


def load_results(path: str | Path, robot: Robot | str | None = None) -> list[Any]:
    """Every result in a RESULT.json (``cr-nlp plan`` writes several trajectories)."""
    return results_from_dict(read_json(path), robot, source=str(path))


def load_result(path: str | Path, robot: Robot | str | None = None) -> Any:
    """The result in a RESULT.json file, of the class its ``kind`` names."""
    return result_from_dict(read_json(path), robot, source=str(path))
