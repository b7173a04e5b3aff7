"""`cr-nlp fk` as a user runs it."""

import json
from pathlib import Path

import numpy as np
import pytest

from cr_nlp.cli import main

from ..conftest import MODELS

TDCR3 = str(MODELS / "robots" / "tdcr3.json")
TDCR4 = str(MODELS / "robots" / "tdcr4_ext.json")


def test_fk_json_single(capsys: pytest.CaptureFixture) -> None:
    assert main(["fk", "--robot", TDCR3, "--q", "0,0,1,0,0,1,0,0,1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"position", "wxyz", "tendon_lengths", "backbone"}
    np.testing.assert_allclose(out["position"], [0, 0, 3], atol=1e-9)
    np.testing.assert_allclose(out["wxyz"], [1, 0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(out["tendon_lengths"], [1, 1, 1, 2, 2, 2, 3, 3, 3], atol=1e-9)
    assert len(out["backbone"]) == 30


def test_fk_fixed_lengths_may_be_omitted(capsys: pytest.CaptureFixture) -> None:
    main(["fk", "--robot", TDCR3, "--q", "1.5707963267948966,0,0,0,0,0", "--json"])
    out = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(out["position"], [2 + 2 / np.pi, 0, 2 / np.pi], atol=1e-9)


def test_fk_text_output(capsys: pytest.CaptureFixture) -> None:
    assert main(["fk", "--robot", TDCR3, "--q", "0.3,0.1,0.2,0.4,0.5,0.6"]) == 0
    text = capsys.readouterr().out
    assert "tip position" in text and "tendons seg 3" in text


def test_fk_q_file_gives_a_list(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    qfile = tmp_path / "q.json"
    qfile.write_text(json.dumps({"q": [[0, 0, 1.0] * 4, [0.5, 1.0, 0.7] * 4]}))
    assert main(["fk", "--robot", TDCR4, "--q-file", str(qfile), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert isinstance(out, list) and len(out) == 2
    np.testing.assert_allclose(out[0]["position"], [0, 0, 4], atol=1e-9)


@pytest.mark.parametrize(("q", "message"), [
    ("0,0,1,0,0,1,0,0", "needs 9 or 6"),
    ("4,0,1,0,0,1,0,0,1", "θ1 = 4.0 rad is outside"),
    ("0,0,1.2,0,0,1,0,0,1", "must equal the fixed length"),
    ("0,a,1", "comma-separated numbers"),
    ("nan,0,0,0,0,0", "non-finite"),
])
def test_fk_bad_configurations(q: str, message: str, capsys: pytest.CaptureFixture) -> None:
    assert main(["fk", "--robot", TDCR3, "--q", q]) == 2
    assert message in capsys.readouterr().err


def test_fk_bad_robot_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad = tmp_path / "robot.json"
    data = json.loads(Path(TDCR3).read_text())
    data["segments"] = []
    bad.write_text(json.dumps(data))
    assert main(["fk", "--robot", str(bad), "--q", "0,0,1"]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "segments" in err


# ---------------------------------------------------------------- bundled names (one resolver)


def test_fk_takes_a_bundled_robot_name_from_any_directory(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture) -> None:
    q = "0.3,0.1,0.2,0.4,0.5,0.6"
    assert main(["fk", "--robot", TDCR3, "--q", q, "--json"]) == 0
    from_file = json.loads(capsys.readouterr().out)
    monkeypatch.chdir(tmp_path)  # no models/ folder here
    assert main(["fk", "--robot", "tdcr3", "--q", q, "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == from_file


def test_a_file_beats_a_bundled_name_and_an_unknown_name_lists_the_choices(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture) -> None:
    data = json.loads(Path(TDCR3).read_text())
    data["name"] = "local_tdcr3"
    monkeypatch.chdir(tmp_path)
    Path("tdcr3").write_text(json.dumps(data))  # a local file called like the bundled robot
    assert main(["fk", "--robot", "tdcr3", "--q", "0,0,0,0,0,0"]) == 0
    assert "local_tdcr3" in capsys.readouterr().out
    assert main(["fk", "--robot", "tdcr9", "--q", "0,0,0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cr-nlp fk: error: --robot: tdcr9: file not found")
    assert "tdcr3, tdcr4_ext" in err and len(err.splitlines()) == 1


@pytest.mark.parametrize(("kind", "name"), [
    ("robots", "tdcr6_ext"), ("scenes", "cabinet"), ("paths", "sine"),
    ("targets", "tdcr3_lattice"), ("problems", "tdcr3_shelf")])
def test_the_resolver_finds_every_kind_of_bundled_file(
        kind: str, name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from cr_nlp._resources import resolve_file

    monkeypatch.chdir(tmp_path)
    assert resolve_file(name, kind) == MODELS / kind / f"{name}.json"
    with pytest.raises(FileNotFoundError, match=f"not a bundled {kind[:-1]} name"):
        resolve_file(f"{name}_missing", kind)
    with pytest.raises(FileNotFoundError):  # a path is never looked up among the bundled
        resolve_file(f"somewhere/{name}", kind)


def test_plan_and_ik_inputs_take_bundled_names(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    from cr_nlp.cli._io import resolve
    from cr_nlp.tasks.readers import read_problems, read_targets

    monkeypatch.chdir(tmp_path)
    starts, goals, _, _ = read_problems(resolve("tdcr3_shelf", "problems", "--problems"))
    assert len(starts) == len(goals) > 0
    positions, wxyz, problems = read_targets(resolve("tdcr3_lattice", "targets", "--targets"))
    assert positions.shape == (20, 3) and wxyz.shape == (20, 4) and not any(problems)


def test_fk_prints_float64_numbers_that_match_an_independent_evaluation(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture) -> None:
    from cr_nlp.model import load_robot

    from ..model.test_public_float64 import reference_backbone, reference_tendons, reference_tip

    robot = load_robot("tdcr3")
    q = np.array([0.3, 0.1, 1.0, 2.9, -2.5, 1.0, 1e-7, 0.6, 1.0])
    monkeypatch.chdir(tmp_path)
    text = ",".join(repr(float(v)) for v in q)
    assert main(["fk", "--robot", "tdcr3", "--q", text, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    tip = reference_tip(robot, q)
    np.testing.assert_allclose(out["position"], tip[:3, 3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(out["backbone"], reference_backbone(robot, q), rtol=0, atol=1e-12)
    np.testing.assert_allclose(out["tendon_lengths"], reference_tendons(robot, q), rtol=0,
                               atol=1e-12)
    from scipy.spatial.transform import Rotation

    wxyz = np.roll(Rotation.from_matrix(tip[:3, :3]).as_quat(), 1)
    np.testing.assert_allclose(out["wxyz"], wxyz * np.sign(wxyz[0]), rtol=0, atol=1e-12)
    # The text output carries the same numbers to 12 decimals.
    assert main(["fk", "--robot", "tdcr3", "--q", text]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("tip position"))
    printed = [float(v) for v in line.split("[")[1].split("]")[0].split(",")]
    np.testing.assert_allclose(printed, tip[:3, 3], rtol=0, atol=1e-12)


def test_a_bad_compile_setting_is_named(monkeypatch: pytest.MonkeyPatch,
                                        capsys: pytest.CaptureFixture) -> None:
    monkeypatch.setenv("CR_NLP_COMPILE", "fastest")
    assert main(["fk", "--robot", TDCR3, "--q", "0,0,1,0,0,1,0,0,1", "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "CR_NLP_COMPILE must be one of auto, quick, full, got 'fastest'" in captured.err
