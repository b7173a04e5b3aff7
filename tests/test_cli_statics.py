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
    ([], "either --tensions or --cases"),
])
def test_statics_bad_input_is_a_usage_error(args: list[str], message: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["statics", "--robot", "tdcr2_rao2021", *args]) == 2
    assert message in capsys.readouterr().err


def test_statics_needs_a_mechanics_block(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["statics", "--robot", "tdcr3", "--tensions", "0,0,0,0,0,0,0,0,0"]) == 2
    assert "mechanics" in capsys.readouterr().err
