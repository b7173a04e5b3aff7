"""Every input file a task reads, one reader each (units: metres, radians, seconds,
newtons): IK targets (``read_targets``), planning problems of the geometry family
(``read_problems``) and of the mechanics family (``read_tension_problems``), reference
paths (``load_path``, and ``checked_path`` with the checks a follower needs), a robot's
recording of commands and tips (``read_measurements``, ``read_labels``). Robot and scene
files are read by ``model.load_robot`` and ``world.load_scene``, result files by
``load_result``.

Every reader names the file and the field in its error, and every error about a file is
an ``InputFileError`` (a ``ValueError``; the recording's ``DataFileError`` and the robot
files' ``ModelFileError`` are kinds of it); a malformed entry of a batch (one target, one
problem) is reported with that entry, not by sinking the batch where the format allows.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from .._files import InputFileError, read_json_or
from .._resources import resolve_file
from ..model import Robot
from ..model.robot import ModelFileError
from .calibration.measurements import (
    DEFAULT_TIP_COLUMNS,
    UNITS,
    DataFileError,
    Measurements,
    default_tendon_columns,
)
from .paths import ReferencePath

MAX_HORIZON = 10_000
"""Most trajectory steps a problems file may ask for (the default plan has 23)."""
_PROBLEMS_KEYS = {"problems", "horizon", "dt", "description", "robot", "scene", "name"}
TENSION_PROBLEM_KEYS = ("start", "goal")
"""The keys of one problem of a tension problems file."""
_TOP_KEYS = {"poses", "description", "name"}
_POSE_KEYS = {"position", "wxyz"}


def _read_top(path: str | Path, key: str, allowed: set[str], shape: str) -> dict[str, Any]:
    """A JSON file's object holding the list ``key`` and no keys outside ``allowed``
    (``shape``: the form the error shows).

    Raises:
        InputFileError: naming the file (and the unknown field).
    """
    data = read_json_or(path, lambda reason: InputFileError(f"{path}: {reason}"))
    if not isinstance(data, dict) or not isinstance(data.get(key), list):
        raise InputFileError(f"{path} must hold {shape}")
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise InputFileError(f"{path}: field {unknown[0]!r}: unknown key "
                             f"(allowed: {', '.join(sorted(allowed))})")
    return data


def read_targets(path: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Target poses from a file ``{"poses": [{"position": [x, y, z], "wxyz": [w, x, y, z]},
    ...]}`` (positions in metres, unit quaternions; ``wxyz`` defaults to the identity).

    Returns (positions (k, 3), wxyz (k, 4), problems): a malformed entry becomes a NaN row
    with its reason in ``problems`` (empty strings elsewhere), so one bad target never
    sinks the batch.

    Raises:
        InputFileError: the file is missing, not JSON, or not of that shape.
    """
    data = _read_top(path, "poses", _TOP_KEYS,
                     '{"poses": [{"position": [x, y, z], "wxyz": [w, x, y, z]}, ...]}')
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


def read_problems(path: str | Path) -> tuple[list[Any], list[Any], int | None, float | None]:
    """A planning problems file of the geometry family, ``{"problems": [{"start": q,
    "goal": q}, …], "horizon": steps, "dt": s}``: starts, goals (raw rows, validated later
    per problem by the planner), horizon and dt (seconds).

    Raises:
        InputFileError: naming the file and the field: not of the problems file's shape, an
            unknown key, or a horizon (an integer 2…``MAX_HORIZON``) or dt (seconds,
            positive and finite) out of range.
    """
    data = _read_top(path, "problems", _PROBLEMS_KEYS,
                     '{"problems": [{"start": [...], "goal": [...]}, ...]}')
    horizon, dt = data.get("horizon"), data.get("dt")
    if horizon is not None and (isinstance(horizon, bool) or not isinstance(horizon, int)
                                or not 2 <= horizon <= MAX_HORIZON):
        raise InputFileError(f"{path}: field 'horizon': must be an integer from 2 "
                         f"to {MAX_HORIZON}, got {_short(horizon)}")
    seconds = (_as_float(dt) if isinstance(dt, (int, float)) and not isinstance(dt, bool)
               else math.nan)
    if dt is not None and not 0 < seconds < math.inf:
        raise InputFileError(f"{path}: field 'dt': must be a positive, finite number "
                         f"of seconds, got {_short(dt)}")
    starts, goals = [], []
    for i, entry in enumerate(data["problems"]):
        ok = isinstance(entry, dict)
        unknown = sorted(set(entry) - {"start", "goal"}) if ok else []
        if unknown:
            raise InputFileError(f"{path}: field 'problems[{i}].{unknown[0]}': "
                             f"unknown key (allowed: goal, start)")
        starts.append(entry.get("start") if ok else None)
        goals.append(entry.get("goal") if ok else None)
    return starts, goals, horizon, (seconds if dt is not None else None)


def _as_float(value: int | float) -> float:
    try:
        return float(value)
    except OverflowError:  # an integer past float's range
        return math.inf


def _short(value: Any) -> str:
    """``repr`` of a file's value, cut to 40 characters."""
    text = repr(value)
    return text if len(text) <= 40 else f"{text[:37]}..."


def read_tension_problems(robot: Robot, source: str | Path | dict) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """A planning problems file of the mechanics family, ``{"problems": [{"start": [N…],
    "goal": [N…]}]}`` (a file or its content), every entry checked: (starts (B, n),
    goals (B, n)) N.

    Raises:
        InputFileError: one error naming the problem and the key (a ``ValueError``), or
            the file that cannot be read.
    """
    from .mechanics.trajectory import check_tensions

    where = "" if isinstance(source, dict) else f"{source}: "
    data = source if isinstance(source, dict) else read_json_or(
        source, lambda reason: InputFileError(f"{where}{reason}"))
    if not isinstance(data, dict) or set(data) != {"problems"} or not isinstance(
            data["problems"], list):
        raise InputFileError(f'{where}expected {{"problems": [{{"start": [N…], "goal": '
                             f'[N…]}}, …]}}')
    starts, goals = [], []
    for i, problem in enumerate(data["problems"]):
        if not isinstance(problem, dict):
            raise InputFileError(f"{where}problem {i}: expected an object with 'start' and "
                                 f"'goal'")
        unknown = sorted(set(problem) - set(TENSION_PROBLEM_KEYS))
        if unknown:
            raise InputFileError(f"{where}problem {i}: unknown key {unknown[0]!r} (a problem "
                                 f"has 'start' and 'goal', tensions in N)")
        for key in TENSION_PROBLEM_KEYS:
            if key not in problem:
                raise InputFileError(f"{where}problem {i}: missing {key!r}")
        try:
            starts.append(check_tensions(robot, problem["start"], f"problem {i}: start"))
            goals.append(check_tensions(robot, problem["goal"], f"problem {i}: goal"))
        except ValueError as exc:
            raise InputFileError(f"{where}{exc}") from None
    n = robot.n_tendons
    return np.reshape(starts, (-1, n)), np.reshape(goals, (-1, n))


def load_path(path: str | Path | ReferencePath) -> ReferencePath:
    """A ``ReferencePath`` from a file, or a bundled path name ("square", "sine", "icra")."""
    if isinstance(path, ReferencePath):
        return path
    try:
        candidate = resolve_file(path, "paths")
    except FileNotFoundError as exc:
        raise ModelFileError(str(path), "<file>",
                             str(exc).removeprefix(f"{path}: ")) from None
    return ReferencePath.from_file(candidate)


def checked_path(path: str | Path | ReferencePath, dt: float | None = None) -> ReferencePath:
    """``load_path``, then the checks a follower needs: at least 2 waypoints, finite
    reference poses, unit quaternions (|‖wxyz‖ − 1| ≤ 1e-6) and a positive, finite time
    step. ``dt``: seconds between waypoints replacing the path's own (None: keep it).

    Raises:
        ValueError: naming the first bad waypoint, or the bad ``dt``.
    """
    path = load_path(path)
    dt = float(path.dt if dt is None else dt)
    if not dt > 0 or not math.isfinite(dt):
        raise ValueError(f"dt must be a positive number of seconds, got {dt}")
    positions = np.asarray(path.positions, dtype=np.float64)
    wxyz = np.asarray(path.wxyz, dtype=np.float64)
    if len(positions) < 2:
        raise ValueError(f"a path needs at least 2 waypoints, got {len(positions)}")
    bad = np.flatnonzero(~np.isfinite(positions).all(1) | ~np.isfinite(wxyz).all(1))
    if len(bad):
        raise ValueError(f"waypoint {bad[0]}: the reference pose is not finite")
    norms = np.linalg.norm(wxyz, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-6)
    if len(bad):
        raise ValueError(f"waypoint {bad[0]}: wxyz is not a unit quaternion "
                         f"(norm {norms[bad[0]]:.6g})")
    if dt != path.dt:
        path = ReferencePath(path.name, positions, wxyz, dt, path.pen_down)
    return path

# ---------------------------------------------------------------- the benchmark shapes


def read_measurements(path: str | Path, n_tendons: int, *,
                      tendon_columns: list[str] | None = None,
                      tip_columns: list[str] | tuple[str, ...] | None = DEFAULT_TIP_COLUMNS,
                      units: str = "m", require_tip: bool = True,
                      time_column: str | None = None) -> Measurements:
    """Read a measurement CSV (see the module docstring) into metres.

    Args:
        path: the CSV file.
        n_tendons: the robot's tendon count; ``tendon_columns`` must name that many.
        tendon_columns: command columns in the robot file's tendon order (default
            ``tendon_1 … tendon_N``).
        tip_columns: the three measured-tip columns, or None to read commands only.
        units: "m" or "mm", for commands and tips alike.
        time_column: a column of times (s) to read where the file has it; the rows must
            be in time order (the history-aware model runs through them in that order).

    Raises:
        DataFileError: missing file or column, wrong tendon count, an empty file, a cell
            that is not a finite number (naming file, column and data row, 1-based), a
            time earlier than the row before.
    """
    source = str(path)
    if units not in UNITS:
        raise DataFileError(f"{source}: units must be one of {sorted(UNITS)}, got {units!r}")
    columns = list(tendon_columns) if tendon_columns is not None else \
        default_tendon_columns(n_tendons)
    if len(columns) != n_tendons:
        raise DataFileError(f"{source}: {len(columns)} tendon columns given "
                            f"({', '.join(columns)}), the robot has {n_tendons} tendons")
    tips = list(tip_columns) if tip_columns is not None else []
    if tip_columns is not None and len(tips) != 3:
        raise DataFileError(f"{source}: the tip needs 3 columns (x, y, z), got {tips}")
    try:
        with open(path, newline="") as handle:
            rows = list(csv.reader(handle))
    except FileNotFoundError:
        raise DataFileError(f"{source}: file not found") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DataFileError(f"{source}: cannot read: {exc}") from None
    if not rows:
        raise DataFileError(f"{source}: the file is empty (a header row is needed)")
    header = [h.strip() for h in rows[0]]
    index = {name: i for i, name in enumerate(header)}
    if not require_tip and not any(name in index for name in tips):
        tips = []
    for name in columns + tips:
        if name not in index:
            kind = "tip" if name in tips else "tendon"
            raise DataFileError(f"{source}: {kind} column {name!r} not found "
                                f"(columns: {', '.join(header)})")
    body = [(k + 1, r) for k, r in enumerate(rows[1:]) if any(cell.strip() for cell in r)]
    if not body:
        raise DataFileError(f"{source}: no data rows after the header")
    clock = [time_column] if time_column and time_column in index else []
    wanted = columns + tips + clock
    values = np.empty((len(body), len(wanted)))
    for out, (row_number, row) in enumerate(body):
        if len(row) != len(header):
            raise DataFileError(f"{source}: row {row_number} has {len(row)} cells, the "
                                f"header has {len(header)}")
        for k, name in enumerate(wanted):
            cell = row[index[name]].strip()
            try:
                x = float(cell)
            except ValueError:
                raise DataFileError(f"{source}: column {name!r}, row {row_number}: not a "
                                    f"number: {cell!r}") from None
            if not math.isfinite(x):
                raise DataFileError(f"{source}: column {name!r}, row {row_number}: "
                                    f"{cell!r} is not a finite number")
            values[out, k] = x
    times = _in_time_order(values[:, -1], [k for k, _ in body], source, clock[0]) \
        if clock else None
    values = values[:, :len(columns) + len(tips)] * UNITS[units]
    commands = values[:, :n_tendons]
    tip = values[:, n_tendons:] if tips else None
    return Measurements(commands, tip, source, times)


def _in_time_order(times: np.ndarray, row_numbers: list[int], source: str,
                   column: str) -> np.ndarray:
    """``times`` (s), after checking that no row is earlier than the one before."""
    late = np.flatnonzero(np.diff(times) < 0)
    if late.size:
        raise DataFileError(f"{source}: column {column!r}, row {row_numbers[late[0] + 1]}: "
                            f"earlier than the row before (rows must be in time order)")
    return times.copy()


def read_labels(path: str | Path, column: str) -> np.ndarray | None:
    """(N,) the text of ``column`` in each data row of a measurement CSV (rows as
    ``read_measurements`` reads them), None when the file has no such column."""
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    header = [h.strip() for h in rows[0]] if rows else []
    if column not in header:
        return None
    k = header.index(column)
    return np.array([r[k].strip() for r in rows[1:] if any(cell.strip() for cell in r)])
