"""``cr-nlp statics``: one case as text and JSON, many cases from a file, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cr_nlp.cli.main import main
from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics


def test_statics_json_matches_the_library(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["statics", "--robot", "tdcr2_rao2021", "--tensions", "4,0,0,0,2,0",
                 "--tip-moment", "0,0.002,0", "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    expected = solve_statics(load_robot("tdcr2_rao2021"), [4, 0, 0, 0, 2, 0],
                             tip_moment=[0, 0.002, 0])
    assert record["converged"] is True
    np.testing.assert_allclose(record["position"], expected.tip_position[0], atol=1e-12)
    assert len(record["backbone"]) == expected.positions.shape[1]
    assert np.linalg.norm(record["wxyz"]) == pytest.approx(1.0)


def test_statics_text_output(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["statics", "--robot", "tdcr2_rao2021", "--tensions", "0,0,0,0,0,0"]) == 0
    out = capsys.readouterr().out
    # no load: the straight robot, 0.4 m tall
    assert "tip position   [0.000000000, 0.000000000, 0.400000000] m" in out
    assert "converged      True" in out


def test_statics_cases_file_keeps_the_input_order(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    cases = [{"tensions": [float(k), 0, 0, 0, 0, 0]} for k in range(9)]
    cases[3]["tip_force"] = [0.0, 0.05, 0.0]
    path = tmp_path / "cases.json"
    path.write_text(json.dumps({"cases": cases}))
    assert main(["statics", "--robot", "tdcr2_rao2021", "--cases", str(path)]) == 0
    records = json.loads(capsys.readouterr().out)
    assert len(records) == 9 and all(r["converged"] for r in records)
    # More tension on the 90° tendon bends the tip further towards +y.
    ys = [records[k]["position"][1] for k in (0, 1, 2, 4, 5)]
    assert ys == sorted(ys) and ys[0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize(("args", "message"), [
    (["--tensions", "1,2"], "6 tendons"),
    (["--tensions", "1,0,0,0,0,0", "--tip-force", "1,2"], "--tip-force: expected 3"),
    (["--tensions=-1,0,0,0,0,0"], "≥ 0 N"),
    ([], "give one of --tensions, --displacements or --cases"),
    (["--tensions", "0,0,0,0,0,0", "--displacements", "0,0,0,0,0,0"],
     "not --tensions and --displacements"),
    (["--displacements", "0.001,0,0,0,0,0"], "tendon_stiffness"),  # the robot has none
    (["--displacements", "0.001,0"], "--displacements: tdcr2_rao2021 has 6 tendons"),
])
def test_statics_bad_input_is_a_usage_error(args: list[str], message: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["statics", "--robot", "tdcr2_rao2021", *args]) == 2
    assert message in capsys.readouterr().err


def test_statics_needs_a_mechanics_block(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["statics", "--robot", "tdcr3", "--tensions", "0,0,0,0,0,0,0,0,0"]) == 2
    assert "mechanics" in capsys.readouterr().err


def test_statics_cases_with_loads_anywhere(tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """Per-case gravity, a force per metre and point loads reach the library unchanged, and
    every record says whether it is stable and how many equilibria were found."""
    point = [{"s": 0.15, "force": [0.0, 0.02, 0.0], "moment": [0.0, 0.0, 0.001]}]
    cases = [{"tensions": [1.0, 0, 0, 0, 0.5, 0], "gravity": [0.0, 0.0, -9.81]},
             {"tensions": [0.0] * 6, "point_loads": point},
             {"tensions": [0.0] * 6, "distributed_force": [0.05, 0.0, 0.0]}]
    path = tmp_path / "cases.json"
    path.write_text(json.dumps({"cases": cases}))
    assert main(["statics", "--robot", "tdcr2_rao2021", "--cases", str(path)]) == 0
    records = json.loads(capsys.readouterr().out)
    robot = load_robot("tdcr2_rao2021")
    # The library on the same cases, given as its own arguments (one batch, as the command
    # solves them; a batch equals its cases one by one: tests/model/test_cosserat.py).
    expected = solve_statics(robot, [c["tensions"] for c in cases],
                             gravity=[[0, 0, -9.81], [0, 0, 0], [0, 0, 0]],
                             point_loads=[[], point, []],
                             distributed_force=[[0, 0, 0], [0, 0, 0], [0.05, 0, 0]])
    for record, tip in zip(records, expected.tip_position, strict=True):
        np.testing.assert_allclose(record["position"], tip, atol=1e-12)
        assert record["stable"] is True and record["equilibria"] == 1
        assert record["snap_load"] is None
    assert records[2]["position"][0] > 1e-3  # the force per metre bends it towards +x


def test_statics_all_equilibria_of_a_buckled_column(capsys: pytest.CaptureFixture[str]) -> None:
    """Twice Euler's load π²EI/(4L²) down a straight column, nudged towards +x."""
    ei = load_robot("tdcr2_rao2021").mechanics.bending_stiffness
    load = 2 * np.pi ** 2 * ei / (4 * 0.4 ** 2)
    assert main(["statics", "--robot", "tdcr2_rao2021", "--tensions", "0,0,0,0,0,0",
                 "--tip-force", f"{1e-4 * load},0,{-load}", "--all-equilibria", "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["stable"] is True and record["equilibria"] >= 2
    assert record["position"][0] > 0.1
    found = record["all_equilibria"]
    assert len(found) == record["equilibria"] and found[0]["reached"]
    # Its mirror image is an equilibrium too, but in 3-D an unstable one: it can turn
    # about the load's line towards the nudge.
    assert any(e["position"][0] < -0.1 and not e["stable"] for e in found)


@pytest.mark.parametrize(("case", "message"), [
    ({"point_loads": [{"s": 0.45, "force": [0, 0, 1]}]},
     "cases[1].point_loads[0].s: 0.45 m lies outside the robot"),
    ({"point_loads": [{"s": 0.1, "force": [0, 1e999, 0]}]},
     "cases[1].point_loads[0].force[1]: must be finite"),
    ({"point_loads": [{"s": 0.1, "torque": [0, 0, 1]}]},
     "cases[1].point_loads[0].torque: unknown key"),
    ({"gravity": [0, 9.81]}, "cases[1].gravity: expected 3 numbers"),
    ({"distributed_forces": [0, 0, 1]}, "cases[1].distributed_forces: unknown key"),
    ({"tensions": [0, 0, -1, 0, 0, 0]}, "cases[1].tensions[2]: a tension must not be negative"),
])
def test_statics_bad_case_names_the_case_and_key(tmp_path: Path, case: dict, message: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    cases = [{"tensions": [0.0] * 6}, {"tensions": [0.0] * 6, **case}]
    path = tmp_path / "cases.json"
    path.write_text(json.dumps({"cases": cases}))
    assert main(["statics", "--robot", "tdcr2_rao2021", "--cases", str(path)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def test_statics_point_load_option_is_the_tip_force(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    base = ["statics", "--robot", "tdcr2_rao2021", "--tensions", "1,0,0,0,0.5,0", "--json"]
    assert main([*base, "--tip-force", "0.02,0,0"]) == 0
    tip = json.loads(capsys.readouterr().out)
    assert main([*base, "--point-load", "0.4,0.02,0,0"]) == 0
    point = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(point["position"], tip["position"], atol=1e-9)
    # The same wrench from a loads file (the option set every command on the rod shares).
    loads = tmp_path / "loads.json"
    loads.write_text(json.dumps({"tip_force": [0.02, 0, 0]}))
    assert main([*base, "--loads", str(loads)]) == 0
    assert json.loads(capsys.readouterr().out)["position"] == tip["position"]


def test_statics_displacements_finds_the_tensions_tension_statics_agrees_with(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--displacements`` on a robot file whose mechanics block has tendon stiffnesses:
    the tensions printed, fed to the tension statics, give the same backbone; the
    released tendons are slack and carry nothing."""
    data = load_robot("tdcr2_rao2021").to_dict()
    data["mechanics"]["tendon_stiffness"] = [4000.0, 8000.0]          # N/m per segment
    path = tmp_path / "robot.json"
    path.write_text(json.dumps(data))
    command = [0.003, -0.002, -0.002, 0.0, 0.0015, 0.0]                # m
    assert main(["statics", "--robot", str(path), "--displacements",
                 ",".join(map(str, command)), "--gravity", "0,0,-9.81", "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["converged"] and record["slack"][1] and record["slack"][2]
    assert record["tensions"][1] == 0.0 == record["tensions"][2]
    assert record["tensions"][0] > 0.1
    check = solve_statics(load_robot(str(path)), record["tensions"], gravity=[0, 0, -9.81])
    assert np.abs(check.positions[0] - np.array(record["backbone"])).max() <= 1e-6
    assert main(["statics", "--robot", str(path), "--displacements",
                 ",".join(map(str, command)), "--gravity", "0,0,-9.81"]) == 0
    assert "(slack: tendon 2, 3)" in capsys.readouterr().out
