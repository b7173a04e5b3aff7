"""What the subcommands share: the usage error, number and JSON input/output, the resolver
of file-or-bundled-name arguments, the stop on SIGINT and SIGTERM. Imports no subcommand
(and nothing heavy: JAX starts only when a subcommand runs)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .._files import InputFileError, atomic_open, read_json_or
from .._resources import resolve_file
from .._signals import Stopped as Stopped
from .._signals import stop_on_signals as stop_on_signals

if TYPE_CHECKING:
    import numpy as np

    from ..model import Robot
    from ..tasks.calibration.measurements import Measurements
    from ..world import Scene


class UsageError(Exception):
    """Bad command-line input: printed as one line, exit status 2."""


def resolve(value: str, kind: str, option: str) -> Path:
    """The file behind a ``--robot``/``--scene``/``--path``/``--targets``/``--problems``
    value: a file path, or a bundled name of ``kind`` (``"robots"``, ``"scenes"``,
    ``"paths"``, ``"targets"``, ``"problems"``), from any directory."""
    try:
        return resolve_file(value, kind)
    except FileNotFoundError as exc:
        raise UsageError(f"{option}: {exc}") from None


def load_robot_arg(value: str, option: str = "--robot") -> Robot:
    """The robot of a ``--robot`` value (file or bundled name)."""
    from ..model import Robot

    return Robot.from_file(resolve(value, "robots", option))


def load_scene_arg(value: str | None, option: str = "--scene") -> Scene | None:
    """The scene of a ``--scene`` value (file or bundled name), None without one."""
    if value is None:
        return None
    from ..world import load_scene

    return load_scene(resolve(value, "scenes", option))


def parse_numbers(text: str, what: str) -> list[float]:
    """'0.1,0.2,1' → [0.1, 0.2, 1.0], with an error that names ``what``."""
    try:
        return [float(v) for v in text.replace(" ", "").split(",") if v != ""]
    except ValueError:
        raise UsageError(f"{what}: expected comma-separated numbers, got {text!r}") from None


def parse_vector3(text: str | None, what: str) -> list[float] | None:
    """'fx,fy,fz' → three floats (None when the option was not given), with an error that
    names ``what``."""
    if text is None:
        return None
    values = parse_numbers(text, what)
    if len(values) != 3:
        raise UsageError(f"{what}: expected 3 numbers, got {len(values)}")
    return values


def point_loads_arg(values: list[str] | None) -> list[dict]:
    """``--point-load S,FX,FY,FZ[,MX,MY,MZ]`` options (arc length m, force N, moment N·m)
    as point-load objects ``{"s", "force", "moment"}``."""
    out = []
    for k, text in enumerate(values or []):
        numbers = parse_numbers(text, f"--point-load[{k}]")
        if len(numbers) not in (4, 7):
            raise UsageError(f"--point-load[{k}]: expected S,FX,FY,FZ or S,FX,FY,FZ,MX,MY,MZ, "
                             f"got {len(numbers)} numbers")
        moment = numbers[4:] if len(numbers) == 7 else [0.0, 0.0, 0.0]
        out.append({"s": numbers[0], "force": numbers[1:4], "moment": moment})
    return out


def read_json(path: str | Path, what: str) -> Any:
    """The JSON content of ``path``; a missing or invalid file is a usage error."""
    return read_json_or(path, lambda reason: UsageError(f"{what}: {path}: {reason}"))


def read_problems_arg(value: str) -> tuple[list[Any], list[Any], int | None, float | None]:
    """``tasks.readers.read_problems`` of ``--problems`` (a file or a bundled name); a
    file that is not a problems file is a usage error naming the option, the file and the
    field."""
    from ..tasks.readers import read_problems

    try:
        return read_problems(resolve(value, "problems", "--problems"))
    except InputFileError as exc:
        raise UsageError(f"--problems: {exc}") from None


def write_json(data: Any, path: str | None) -> None:
    """Write JSON to ``path``, or to stdout when ``path`` is None or '-'."""
    text = json.dumps(data, indent=2)
    if path in (None, "-"):
        print(text)
    else:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        with atomic_open(path) as handle:
            handle.write(text + "\n")


def write_result(result: Any, path: str) -> None:
    """A result to ``--out``: ``result.save(path)``, or ``result.to_dict()`` as JSON on
    stdout for '-' (``tasks._result``: the RESULT.json with its kind)."""
    if path == "-":
        print(json.dumps(result.to_dict(), indent=2))
    else:
        result.save(path)


def write_path_result(result: Any, out: str, csv: str | None) -> None:
    """A path-following result to ``--out`` (its CSV time series where the name ends in
    .csv, else ``write_result``) and, with ``--csv``, its time series there too."""
    if Path(out).suffix == ".csv":
        result.save_csv(out)
    else:
        write_result(result, out)
    if csv:
        result.save_csv(csv)


def configurations_from_args(robot: Robot, q: str | None, q_file: str | None) -> np.ndarray:
    """(k, 3n) configurations from ``--q`` or ``--q-file`` ({"q": [[...], ...]})."""
    import numpy as np

    if (q is None) == (q_file is None):
        raise UsageError("give exactly one of --q or --q-file")
    rows = [parse_numbers(q, "--q")] if q is not None else read_json(q_file, "--q-file")
    if q_file is not None:
        if not isinstance(rows, dict) or not isinstance(rows.get("q"), list):
            raise UsageError(f"--q-file: {q_file} must hold {{\"q\": [[...], ...]}}")
        rows = rows["q"]
    out = []
    for i, row in enumerate(rows):
        try:
            out.append(robot.full_q(row))
        except (ValueError, TypeError) as exc:
            raise UsageError(f"configuration {i}: {exc}") from None
    return np.array(out)


def fmt(x: float | None) -> str:
    """A summary number: 3 significant digits, "n/a" for None."""
    return "n/a" if x is None else f"{x:.3g}"


def add_model_margin_option(p: Any) -> None:
    """``--model-margin``: metres added to the clearance margin, or ``auto``."""
    p.add_argument("--model-margin", default=None,
                   help="add to the clearance margin (m), or 'auto': the robot file's "
                        "calibrated 95th-percentile tip error (actuation.model_error_p95), "
                        "so that the clearance holds for the real robot")


def model_margin(robot: Robot, value: str | None) -> float:
    """The extra clearance margin of a ``--model-margin`` value, metres (0 without one)."""
    if value is None:
        return 0.0
    if value == "auto":
        act = getattr(robot, "actuation", None)
        if act is None or act.model_error_p95 is None:
            raise UsageError(f"--model-margin auto: {robot.name} has no calibrated error "
                             f"(actuation.model_error_p95); run cr-nlp calibrate first")
        return float(act.model_error_p95)
    try:
        margin = float(value)
    except ValueError:
        raise UsageError(f"--model-margin: expected metres or 'auto', got {value!r}") from None
    if not margin >= 0.0:
        raise UsageError(f"--model-margin must be ≥ 0 m, got {value}")
    return margin


def add_time_limit_option(p: Any) -> None:
    """``--time-limit SECONDS``: exact mode's time budget per problem."""
    p.add_argument("--time-limit", metavar="SECONDS",
                   help="with --exact: seconds of Ipopt polishing per problem (an IK target, "
                        "a trajectory, a path), all its attempts together; out of time, a "
                        "problem keeps its best verified answer so far and its stage says "
                        "'polish out of time'")


def time_limit_arg(args: Any) -> float | None:
    """The seconds of a ``--time-limit`` value (None without one): a positive finite
    number, and only with ``--exact`` (nothing else is limited), else a usage error."""
    value = args.time_limit
    if value is None:
        return None
    try:
        seconds = float(value)
    except ValueError:
        raise UsageError(f"--time-limit: expected seconds, got {value!r}") from None
    if not (math.isfinite(seconds) and seconds > 0):
        raise UsageError(f"--time-limit must be a positive number of seconds, got {value}")
    if not args.exact:
        raise UsageError("--time-limit bounds the exact stage (Ipopt): give it with --exact")
    return seconds


def add_data_options(p: Any) -> None:
    """``--tendon-columns``, ``--tip-columns`` and ``--units``."""
    p.add_argument("--tendon-columns",
                   help="command columns in the robot file's tendon order "
                        "(default tendon_1,…,tendon_N)")
    p.add_argument("--tip-columns", default="tip_x,tip_y,tip_z",
                   help="measured tip columns x,y,z (default tip_x,tip_y,tip_z)")
    p.add_argument("--units", choices=["m", "mm"], default="m",
                   help="length unit of commands and tip in the file (default m)")
    p.add_argument("--time-column", default="timestamp",
                   help="with --history: the column of times (s) that orders the rows "
                        "(default timestamp; a file without it is read in its own order)")


def read_data_arg(robot: Robot, value: str, args: Any, *,
                  require_tip: bool = True) -> Measurements:
    """The measurements of a ``--data``/``--validate`` value (a CSV file, or a bundled
    recording's name such as ``ftdcr_v6_train``); ``require_tip=False``: a file without
    the tip columns gives commands only."""
    from .._resources import resolve_data_file
    from ..tasks.calibration.measurements import DataFileError
    from ..tasks.readers import read_measurements

    try:
        path = resolve_data_file(value)
    except FileNotFoundError as exc:
        raise UsageError(str(exc)) from None
    columns = (args.tendon_columns.split(",") if args.tendon_columns else None)
    tips = args.tip_columns.split(",")
    # Rows are a time series only for the history-aware model: --history none reads as before.
    clock = args.time_column if getattr(args, "history", "none") != "none" else None
    try:
        return read_measurements(path, robot.n_tendons, tendon_columns=columns,
                                 tip_columns=tips, units=args.units,
                                 require_tip=require_tip, time_column=clock)
    except DataFileError as exc:
        raise UsageError(str(exc)) from None
