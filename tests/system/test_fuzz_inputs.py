"""Bad input files, generated (issue 41: every bad input named).

Each input format's bundled example is mutated once: a key deleted or added, a value
replaced by a wrong type, NaN, ±inf, a huge or negative number or an empty list, the
bytes cut short or given a non-UTF-8 byte, a CSV row given a cell too many or too few.
Its loader must either read it (and then hold finite numbers only) or raise the format's
documented error naming the file and the field or row; never a raw KeyError, TypeError,
UnicodeDecodeError, JSONDecodeError or OverflowError. The CLI layer feeds the files the
loaders reject to the commands: exit status 2, one line on stderr naming the file, no
traceback, no ``--out`` file.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, currently_in_test_context, event, example, given, settings
from hypothesis import strategies as st

from cr_nlp._files import InputFileError
from cr_nlp.cli import main as cli_main
from cr_nlp.cli._io import UsageError
from cr_nlp.cli.statics import _cases_from_file
from cr_nlp.model import ModelFileError, Robot, load_robot
from cr_nlp.tasks._result import ResultFileError, read_json
from cr_nlp.tasks.calibration.measurements import DataFileError
from cr_nlp.tasks.paths import ReferencePath
from cr_nlp.tasks.readers import read_measurements, read_problems, read_targets
from cr_nlp.world.scene import Scene

from ..conftest import MODELS, ROOT

DATA = ROOT / "tests" / "data"

LOADER = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                  suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
"""The loaders are called directly: fast, so most examples go here."""
CLI = settings(LOADER, max_examples=25)
"""A CLI run costs more; only the files the loader rejects reach the command."""

UNKNOWN = "unexpected_key"
WRONG_VALUES: list[Any] = [None, True, "text", "", {}, [], [[]], [1.0], math.nan, math.inf,
                           -math.inf, 1e308, -1e308, 10 ** 400, -1, 0, -0.5, 1e-300]
"""What a field's value is replaced with: wrong types, NaN, ±inf, huge, negative, empty."""
NON_UTF8 = [b"\xff", b"\xc3\x28", b"\x80", b"\xfe\xff"]
LEAKED = (KeyError, TypeError, AttributeError, IndexError, UnicodeDecodeError,
          json.JSONDecodeError, OverflowError)
"""Exceptions that must never reach the user raw."""


def _doc(path: Path) -> Any:
    return json.loads(path.read_text())


def _with(doc: Any, path: list[Any], value: Any) -> tuple[bytes, str, list[Any]]:
    """An explicit mutation: ``doc`` with the value at ``path`` replaced (a regression
    example, in the form the strategies draw)."""
    doc = copy.deepcopy(doc)
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return json.dumps(doc).encode(), f"replaced by {value!r:.20}", path


# ---------------------------------------------------------------- mutations


@st.composite
def mutated_json(draw: st.DrawFn, doc: Any) -> tuple[bytes, str, list[Any]]:
    """One mutation of ``doc``: (the file's bytes, what was done, the mutated JSON path)."""
    kind = draw(st.sampled_from(["delete", "unknown key", "replace", "replace", "truncate",
                                 "non-UTF-8"]))
    if kind in ("truncate", "non-UTF-8"):
        text = json.dumps(doc, indent=1).encode()
        at = draw(st.integers(0, len(text) - 1))
        if kind == "truncate":
            return text[:at], f"truncated at byte {at}", []
        bad = draw(st.sampled_from(NON_UTF8))
        return text[:at] + bad + text[at:], f"{bad!r} at byte {at}", []
    doc = copy.deepcopy(doc)
    parent: Any = None
    key: Any = None
    node, path = doc, []
    # Descend a random branch, stopping at each level with probability 1/4 (the leaves,
    # where most fields are, lie 2 to 4 levels down).
    while isinstance(node, (dict, list)) and node and draw(st.integers(0, 3)) > 0:
        key = draw(st.sampled_from(sorted(node) if isinstance(node, dict) else range(len(node))))
        parent, node = node, node[key]
        path.append(key)
    if kind == "unknown key":
        target = node if isinstance(node, dict) else parent if isinstance(parent, dict) else doc
        if not isinstance(target, dict):
            return json.dumps(doc).encode(), "unchanged", path
        target[UNKNOWN] = 1
        return json.dumps(doc).encode(), kind, path
    if kind == "delete":
        if parent is None:
            if not isinstance(doc, dict) or not doc:
                return json.dumps(doc).encode(), "unchanged", path
            key = draw(st.sampled_from(sorted(doc)))
            parent, path = doc, [key]
        del parent[key]
        return json.dumps(doc).encode(), kind, path
    value = draw(st.sampled_from(WRONG_VALUES))
    if parent is None:
        return json.dumps(value).encode(), f"replaced by {value!r}", path
    parent[key] = value
    return json.dumps(doc).encode(), f"replaced by {value!r}", path


@st.composite
def mutated_csv(draw: st.DrawFn, text: str) -> tuple[bytes, str, int | None]:
    """One mutation of a CSV: (bytes, what was done, the data row (1-based) touched)."""
    rows = [line.split(",") for line in text.splitlines()]
    kind = draw(st.sampled_from(["drop cell", "add cell", "replace cell", "replace cell",
                                 "truncate", "non-UTF-8", "header only", "empty"]))
    raw = text.encode()
    if kind == "truncate":
        at = draw(st.integers(0, len(raw) - 1))
        return raw[:at], f"truncated at byte {at}", None
    if kind == "non-UTF-8":
        at = draw(st.integers(0, len(raw) - 1))
        return raw[:at] + draw(st.sampled_from(NON_UTF8)) + raw[at:], kind, None
    if kind == "header only":
        return (",".join(rows[0]) + "\n").encode(), kind, None
    if kind == "empty":
        return b"", kind, None
    r = draw(st.integers(0, len(rows) - 1))
    c = draw(st.integers(0, len(rows[r]) - 1))
    if kind == "drop cell":
        del rows[r][c]
    elif kind == "add cell":
        rows[r].insert(c, "0.5")
    else:
        rows[r][c] = draw(st.sampled_from(["nan", "inf", "-inf", "1e400", "abc", "", " ",
                                           "1,5", "0x10", "-1e308", "tendon_1"]))
    return ("\n".join(",".join(row) for row in rows) + "\n").encode(), kind, r or None


# ---------------------------------------------------------------- shared checks


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def _load(load: Callable[[Path], Any], data: bytes, file: Path,
          errors: tuple[type[Exception], ...]) -> tuple[Any, Exception | None]:
    """``load(file)`` of ``data``: (the value, None), or (None, the error) after checking
    that the error is one of ``errors``, leaks no raw exception and names the file."""
    file.write_bytes(data)
    try:
        value = load(file)
        _event("read")
        return value, None
    except errors as exc:
        _event("rejected")
        assert not isinstance(exc, LEAKED), f"raw {type(exc).__name__} leaked: {exc}"
        message = str(exc)
        assert str(file) in message, f"the error does not name the file: {message}"
        assert "\n" not in message.strip(), f"not one line: {message!r}"
        return None, exc


def _event(name: str) -> None:
    """Count what the loaders did (``pytest --hypothesis-show-statistics``)."""
    if currently_in_test_context():
        event(name)


def _assert_finite_json(value: Any) -> None:
    """JSON without NaN or infinity (``json.dumps`` refuses them with allow_nan=False)."""
    json.dumps(value, allow_nan=False)


def _check_field(exc: Exception | None, what: str, path: list[Any]) -> None:
    """A schema error names a field: the unknown key when one was added."""
    if not isinstance(exc, ModelFileError):
        return
    if what in ("delete", "unknown key") or what.startswith("replaced"):
        assert exc.field_path != "<file>", str(exc)
    if what == "unknown key":
        assert exc.field_path.endswith(UNKNOWN), str(exc)


# ---------------------------------------------------------------- robots


ROBOT_DOCS = [_doc(MODELS / "robots" / f"{name}.json")
              for name in ("tdcr3", "tdcr4_ext", "ftdcr_v6_calibrated", "tdcr2_rao2021")]
"""Fixed and extendable segments, speed limits, an ``actuation`` and a ``mechanics`` block."""


def _robot_mutation() -> st.SearchStrategy:
    return st.sampled_from(ROBOT_DOCS).flatmap(mutated_json)


def _check_robot(data: bytes, what: str, path: list[Any], file: Path,
                 load: Callable[[Path], Any] = Robot.from_file) -> Exception | None:
    robot, exc = _load(load, data, file, (ModelFileError,))
    _check_field(exc, what, path)
    if robot is not None:
        _assert_finite_json(robot.to_dict())
        assert all(s.length_max >= s.length_min > 0 for s in robot.segments)
    return exc


@LOADER
@given(_robot_mutation())
@example(mutation=_with(ROBOT_DOCS[0], ["backbone_radius"], 10 ** 400))
@example(mutation=_with(ROBOT_DOCS[0], ["points_per_segment"], 10 ** 400))
@example(mutation=_with(ROBOT_DOCS[0], ["points_per_segment"], 10 ** 9))
@example(mutation=_with(ROBOT_DOCS[3], ["mechanics", "disks_per_segment", 0], 10 ** 9))
@example(mutation=(b'{"segments": [\xff]}', "non-UTF-8", []))
def test_robot_files(workdir: Path, mutation: tuple[bytes, str, list[Any]]) -> None:
    _check_robot(*mutation, workdir / "robot.json")


@settings(LOADER, max_examples=20)
@given(_robot_mutation())
def test_load_robot_names_the_file(workdir: Path, mutation: tuple[bytes, str, list[Any]]) -> None:
    _check_robot(*mutation, workdir / "robot_by_path.json", load=lambda f: load_robot(str(f)))


# ---------------------------------------------------------------- scenes


PRIMITIVES = {"name": "primitives", "description": "one obstacle of each primitive type",
              "obstacles": [
                  {"type": "sphere", "name": "ball", "center": [1.0, 0.0, 1.0], "radius": 0.2},
                  {"type": "box", "name": "crate", "center": [0.0, 1.0, 1.0],
                   "size": [0.2, 0.3, 0.4], "wxyz": [1.0, 0.0, 0.0, 0.0]},
                  {"type": "capsule", "name": "pole", "a": [-1.0, 0.0, 0.0],
                   "b": [-1.0, 0.0, 1.0], "radius": 0.1},
                  {"type": "cylinder", "a": [0.0, -1.0, 0.0], "b": [0.0, -1.0, 2.0],
                   "radius": 0.05}]}
SHELF = _doc(MODELS / "scenes" / "shelf.json")
SHELF["obstacles"][0]["path"] = str(MODELS / "meshes" / "shelf.obj")
SCENE_DOCS = [PRIMITIVES, _doc(MODELS / "scenes" / "follow_square.json"), SHELF]


def _check_scene(data: bytes, what: str, path: list[Any], file: Path) -> Exception | None:
    scene, exc = _load(Scene.from_file, data, file, (ModelFileError,))
    _check_field(exc, what, path)
    if scene is not None:
        _assert_finite_json(scene.to_dict())
        for part in scene.parts:
            for value in vars(part).values():
                assert np.all(np.isfinite(value)), (part, what)
    return exc


@LOADER
@given(st.sampled_from(SCENE_DOCS).flatmap(mutated_json))
def test_scene_files(workdir: Path, mutation: tuple[bytes, str, list[Any]]) -> None:
    _check_scene(*mutation, workdir / "scene.json")


# ---------------------------------------------------------------- reference paths


PATH_DOC = _doc(MODELS / "paths" / "icra.json")
PATH_DOC = {**PATH_DOC, "poses": PATH_DOC["poses"][:6], "pen_down": PATH_DOC["pen_down"][:6],
            "description": "the first waypoints of icra"}


def _check_path(data: bytes, what: str, path: list[Any], file: Path) -> Exception | None:
    reference, exc = _load(ReferencePath.from_file, data, file, (ModelFileError,))
    _check_field(exc, what, path)
    if reference is not None:
        _assert_finite_json(reference.to_dict())
        assert len(reference) >= 2 and reference.dt > 0
    return exc


@LOADER
@given(mutated_json(PATH_DOC))
def test_reference_paths(workdir: Path, mutation: tuple[bytes, str, list[Any]]) -> None:
    _check_path(*mutation, workdir / "path.json")


# ---------------------------------------------------------------- IK targets


TARGETS_DOC = _doc(MODELS / "targets" / "tdcr3_lattice.json")
TARGETS_DOC = {**TARGETS_DOC, "poses": TARGETS_DOC["poses"][:4]}


def _check_targets(data: bytes, what: str, path: list[Any], file: Path) -> Exception | None:
    read, exc = _load(read_targets, data, file, (ValueError,))
    if read is None:
        return exc
    positions, wxyz, problems = read
    assert positions.shape == (len(problems), 3) and wxyz.shape == (len(problems), 4)
    for i, problem in enumerate(problems):
        finite = bool(np.all(np.isfinite(positions[i])) and np.all(np.isfinite(wxyz[i])))
        # A bad entry fails alone: a NaN row with its reason, never a silent NaN row.
        assert finite == (not problem), (i, problem, positions[i], wxyz[i])
        if problem:
            assert np.all(np.isnan(positions[i])) and np.all(np.isnan(wxyz[i]))
    if what == "unknown key" and len(path) >= 2:
        assert any(UNKNOWN in p for p in problems), problems
    return None


@LOADER
@given(mutated_json(TARGETS_DOC))
@example(mutation=(b'{"poses": []}\xff', "non-UTF-8", []))
@example(mutation=_with(TARGETS_DOC, ["poses", 0, UNKNOWN], 1))
@example(mutation=_with(TARGETS_DOC, ["poses", 1, "position", 0], 10 ** 400))
@example(mutation=_with(TARGETS_DOC, ["poses", 1, "wxyz", 2], math.nan))
@example(mutation=_with(TARGETS_DOC, [UNKNOWN], 1))
def test_target_files(workdir: Path, mutation: tuple[bytes, str, list[Any]]) -> None:
    _check_targets(*mutation, workdir / "targets.json")


# ---------------------------------------------------------------- planning problems


PROBLEMS_DOC = {**_doc(MODELS / "problems" / "tdcr3_shelf.json"), "horizon": 11, "dt": 0.5}
PROBLEMS_DOC["problems"] = PROBLEMS_DOC["problems"][:2]
TDCR3 = load_robot("tdcr3")


def _check_problems(data: bytes, what: str, path: list[Any], file: Path) -> Exception | None:
    from cr_nlp.world._motion import check_ends

    read, exc = _load(read_problems, data, file, (InputFileError,))
    if read is None:
        return exc
    starts, goals, horizon, dt = read
    assert horizon is None or 2 <= horizon <= 10_000
    assert dt is None or (math.isfinite(dt) and dt > 0)
    # The rows are checked per problem (a bad one fails alone, with a reason).
    rows = check_ends(TDCR3, None, [s if s is not None else [] for s in starts],
                      [g if g is not None else [] for g in goals])
    for start, goal, reason in rows:
        assert (start is None) == bool(reason)
        if start is not None:
            assert np.all(np.isfinite(start)) and np.all(np.isfinite(goal))
    return None


@LOADER
@given(mutated_json(PROBLEMS_DOC))
@example(mutation=(b'\xff{"problems": []}', "non-UTF-8", []))
@example(mutation=_with(PROBLEMS_DOC, ["horizon"], True))
@example(mutation=_with(PROBLEMS_DOC, ["horizon"], 10 ** 9))
@example(mutation=_with(PROBLEMS_DOC, ["dt"], "text"))
@example(mutation=_with(PROBLEMS_DOC, ["dt"], math.inf))
@example(mutation=_with(PROBLEMS_DOC, ["dt"], 10 ** 400))
@example(mutation=_with(PROBLEMS_DOC, ["problems", 0, "start", 3], 10 ** 400))
@example(mutation=_with(PROBLEMS_DOC, ["problems", 1, UNKNOWN], 1))
def test_problem_files(workdir: Path, mutation: tuple[bytes, str, list[Any]]) -> None:
    _check_problems(*mutation, workdir / "problems.json")


# ---------------------------------------------------------------- statics cases


STATICS_ROBOT = load_robot("tdcr2_rao2021")
CASES_DOC = {"cases": [
    {"tensions": [0.5, 0.0, 0.0, 0.0, 0.2, 0.0], "tip_force": [0.0, 0.0, -0.01],
     "tip_moment": [0.0, 0.0, 0.0], "gravity": [0.0, -9.81, 0.0],
     "distributed_force": [0.01, 0.0, 0.0],
     "point_loads": [{"s": 0.1, "force": [0.0, 0.02, 0.0], "moment": [0.0, 0.0, 0.001]}]},
    {"tensions": [0.0] * 6}]}
STATICS_LENGTH = sum(seg.length_min for seg in STATICS_ROBOT.segments)


def _check_cases(data: bytes, what: str, path: list[Any], file: Path) -> Exception | None:
    read, exc = _load(lambda f: _cases_from_file(str(f), STATICS_ROBOT.n_tendons,
                                                 STATICS_LENGTH), data, file, (UsageError,))
    if read is None:
        return exc
    tensions = read.tensions
    assert np.asarray(tensions, dtype=float).shape == (len(tensions), STATICS_ROBOT.n_tendons)
    assert np.all(np.isfinite(np.asarray(tensions, dtype=float)))
    assert np.all(np.asarray(tensions, dtype=float) >= 0)
    gravity = [g for g in read.gravity if g is not None]
    for vectors in (read.tip_force, read.tip_moment, gravity, read.distributed_force):
        assert np.all(np.isfinite(np.asarray(vectors, dtype=float).reshape(-1, 3)))
    for loads in read.point_loads:
        for load in loads:
            assert 0.0 <= load["s"] <= STATICS_LENGTH
            assert np.all(np.isfinite(load["force"])) and np.all(np.isfinite(load["moment"]))
    return None


@LOADER
@given(mutated_json(CASES_DOC))
@example(mutation=(b'{"cases": [\xc3\x28]}', "non-UTF-8", []))
@example(mutation=_with(CASES_DOC, ["cases", 0, "tensions", 1], "text"))
@example(mutation=_with(CASES_DOC, ["cases", 0, "tensions", 1], -1))
@example(mutation=_with(CASES_DOC, ["cases", 1, "tensions", 0], 10 ** 400))
@example(mutation=_with(CASES_DOC, ["cases", 0, "tip_force", 2], math.nan))
@example(mutation=_with(CASES_DOC, ["cases", 0, "tip_moment", 0], {}))
@example(mutation=_with(CASES_DOC, ["cases", 0, "point_loads", 0, "s"], 0.5))
@example(mutation=_with(CASES_DOC, ["cases", 0, "point_loads", 0, "force", 1], math.inf))
@example(mutation=_with(CASES_DOC, ["cases", 0, "gravity"], [0.0, 1.0]))
def test_statics_cases(workdir: Path, mutation: tuple[bytes, str, list[Any]]) -> None:
    _check_cases(*mutation, workdir / "cases.json")


# ---------------------------------------------------------------- calibration CSVs


CSV_TEXT = "\n".join((MODELS / "data" / "ftdcr_v6" / "ftdcr_v6_val.csv")
                     .read_text().splitlines()[:8]) + "\n"
CALIBRATED = load_robot("ftdcr_v6_calibrated")


def _check_csv(data: bytes, what: str, row: int | None, file: Path) -> Exception | None:
    read, exc = _load(lambda f: read_measurements(f, CALIBRATED.n_tendons, units="mm"),
                      data, file, (DataFileError,))
    if read is None:
        if row is not None and what != "drop cell" and "row " in str(exc):
            assert f"row {row}" in str(exc), (row, str(exc))
        return exc
    assert len(read) >= 1 and read.commands.shape == (len(read), CALIBRATED.n_tendons)
    assert read.tip is not None and np.all(np.isfinite(read.tip))
    assert np.all(np.isfinite(read.commands))
    return None


@LOADER
@given(mutated_csv(CSV_TEXT))
def test_measurement_csvs(workdir: Path, mutation: tuple[bytes, str, int | None]) -> None:
    _check_csv(*mutation, workdir / "data.csv")


# ---------------------------------------------------------------- result files (viewer)


RESULT_DOCS = {"ik": _doc(DATA / "ik_lattice_result.json"),
               "trajectory": _doc(DATA / "plan_shelf_result.json"),
               "follow": _doc(DATA / "follow_icra_result.json")}
RESULT_DOCS["ik"]["results"] = RESULT_DOCS["ik"]["results"][:3]
for _key in ("times", "q", "position", "wxyz", "pose_error", "position_error",
             "rotation_error", "reached", "tendon_lengths"):
    RESULT_DOCS["follow"][_key] = RESULT_DOCS["follow"][_key][:4]
RESULT_DOCS["follow"]["path"]["poses"] = RESULT_DOCS["follow"]["path"]["poses"][:4]
RESULT_DOCS["follow"]["path"]["pen_down"] = RESULT_DOCS["follow"]["path"]["pen_down"][:4]


def _read_for_viewer(file: Path) -> Any:
    from cr_nlp.viz._replay import read_result

    return read_result(TDCR3, read_json(file), source=str(file))


@LOADER
@given(st.sampled_from(sorted(RESULT_DOCS)).flatmap(lambda k: mutated_json(RESULT_DOCS[k])))
@example(mutation=(b'{"kind": "ik"\xff}', "non-UTF-8", []))
@example(mutation=_with(RESULT_DOCS["ik"], ["results", 0, "pose_error"], 10 ** 400))
@example(mutation=_with(RESULT_DOCS["trajectory"], ["results", 0, "q"], None))
@example(mutation=_with(RESULT_DOCS["follow"], ["q"], [[0.1] * 9]))
def test_result_files(workdir: Path, mutation: tuple[bytes, str, list[Any]]) -> None:
    _load(_read_for_viewer, mutation[0], workdir / "result.json", (ResultFileError, ValueError))


@pytest.mark.parametrize(("kind", "path", "value", "field"), [
    ("ik", ["results", 1, "pose_error"], "text", "pose_error[1]"),
    ("ik", ["results", 0, "q", 4], 10 ** 400, "q[0][4]"),
    ("follow", ["position_error", 2], {}, "position_error[2]"),
    ("follow", ["tendon_speed"], [], "tendon_speed"),
    ("trajectory", ["results", 0, "min_clearance"], "far", "min_clearance"),
])
def test_result_errors_name_the_field(workdir: Path, kind: str, path: list[Any], value: Any,
                                      field: str) -> None:
    _, exc = _load(_read_for_viewer, _with(RESULT_DOCS[kind], path, value)[0],
                   workdir / "result_field.json", (ResultFileError,))
    assert exc is not None and field in str(exc), str(exc)


# ---------------------------------------------------------------- the CLI


def _run(argv: list[str]) -> tuple[int, str]:
    """``cr-nlp argv`` in this process: (exit status, stderr)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            status = cli_main(argv)
        except SystemExit as exc:  # argparse
            status = exc.code
    return int(status or 0), err.getvalue()


def _assert_rejected(argv: list[str], file: Path, out: Path | None, error: Exception) -> None:
    """The command stops with status 2 and one stderr line: the loader's message."""
    if out is not None and out.exists():
        out.unlink()
    status, err = _run(argv)
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2, (status, err)
    assert len(lines) == 1, err
    assert "Traceback" not in err and str(file) in lines[0], err
    assert str(error) in lines[0], (str(error), err)
    assert out is None or not out.exists(), "an --out file was left behind"
    assert not [p for p in file.parent.iterdir() if p.name.endswith(".tmp")], "a temporary file"


@CLI
@given(_robot_mutation())
def test_cli_fk_rejects_bad_robots(workdir: Path, mutation: tuple[bytes, str, list[Any]]) -> None:
    file = workdir / "cli_robot.json"
    error = _check_robot(*mutation, file)
    if error is not None:
        _assert_rejected(["fk", "--robot", str(file), "--q", "0,0,0,0,0,0"], file, None, error)


@CLI
@given(mutated_json(CASES_DOC))
def test_cli_statics_rejects_bad_cases(workdir: Path,
                                       mutation: tuple[bytes, str, list[Any]]) -> None:
    file = workdir / "cli_cases.json"
    error = _check_cases(*mutation, file)
    if error is not None:
        _assert_rejected(["statics", "--robot", "tdcr2_rao2021", "--cases", str(file)],
                         file, None, error)


@CLI
@given(st.sampled_from(SCENE_DOCS[:2]).flatmap(mutated_json))
def test_cli_show_rejects_bad_scenes(workdir: Path,
                                     mutation: tuple[bytes, str, list[Any]]) -> None:
    file, out = workdir / "cli_scene.json", workdir / "cli_show.png"
    error = _check_scene(*mutation, file)
    if error is not None:
        _assert_rejected(["show", "--robot", "tdcr3", "--scene", str(file), "--out", str(out)],
                         file, out, error)


@CLI
@given(mutated_json(TARGETS_DOC))
def test_cli_ik_rejects_bad_target_files(workdir: Path,
                                         mutation: tuple[bytes, str, list[Any]]) -> None:
    file, out = workdir / "cli_targets.json", workdir / "cli_ik.json"
    error = _check_targets(*mutation, file)
    if error is not None:
        _assert_rejected(["ik", "--robot", "tdcr3", "--targets", str(file), "--out", str(out)],
                         file, out, error)


@CLI
@given(mutated_json(PROBLEMS_DOC))
def test_cli_plan_rejects_bad_problem_files(workdir: Path,
                                            mutation: tuple[bytes, str, list[Any]]) -> None:
    file, out = workdir / "cli_problems.json", workdir / "cli_plan.json"
    error = _check_problems(*mutation, file)
    if error is not None:
        _assert_rejected(["plan", "--robot", "tdcr3", "--problems", str(file),
                          "--out", str(out)], file, out, error)


@CLI
@given(mutated_json(PATH_DOC))
def test_cli_follow_rejects_bad_paths(workdir: Path,
                                      mutation: tuple[bytes, str, list[Any]]) -> None:
    file, out = workdir / "cli_path.json", workdir / "cli_follow.json"
    error = _check_path(*mutation, file)
    if error is not None:
        _assert_rejected(["follow", "--robot", "tdcr3", "--path", str(file), "--out", str(out)],
                         file, out, error)


@settings(CLI, max_examples=15)
@given(mutated_csv(CSV_TEXT))
def test_cli_calibrate_rejects_bad_data(workdir: Path,
                                        mutation: tuple[bytes, str, int | None]) -> None:
    file, out = workdir / "cli_data.csv", workdir / "cli_calibrated.json"
    error = _check_csv(*mutation, file)
    if error is not None:
        _assert_rejected(["calibrate", "--robot", "ftdcr_v6", "--data", str(file),
                          "--units", "mm", "--out", str(out)], file, out, error)


def test_cli_process_prints_one_line_for_a_non_utf8_robot(tmp_path: Path) -> None:
    """The same as a user sees it: a separate process, its whole stderr."""
    file = tmp_path / "robot.json"
    file.write_bytes((MODELS / "robots" / "tdcr3.json").read_bytes().replace(b'"', b'\xff"', 1))
    done = subprocess.run([sys.executable, "-m", "cr_nlp.cli", "fk", "--robot", str(file),
                           "--q", "0,0,0,0,0,0"], capture_output=True, text=True, cwd=ROOT,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and str(file) in done.stderr
    assert "Traceback" not in done.stderr
