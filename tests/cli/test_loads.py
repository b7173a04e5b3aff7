"""The Cosserat rod's CLI options in one module (``cli._loads``), for ``statics`` and
``ik``, ``plan``, ``follow`` with ``--model cosserat``: a bad loads file names the file and
the key; the option set is the same for every command."""

from __future__ import annotations

import argparse
import json

import pytest

from cr_nlp.cli._io import UsageError
from cr_nlp.cli._loads import add_load_options, fitted_gravity, loads_from_args


@pytest.mark.parametrize(("content", "words"), [
    ({"tip_force": [0, 0, -0.1], "payload": 1}, r"payload: unknown key"),
    ({"gravity": [0, 0, -9.81]}, r"gravity is also given as --gravity"),
    ({"point_loads": [{"s": 0.5, "force": [0, 0, -1]}]},
     r"point_loads\[0\]\.s: 0\.5 m lies outside"),
    ({"distributed_force": [0, "x", 0]}, r"distributed_force: expected 3 numbers"),
    ([1, 2], r"expected an object"),
])
def test_a_bad_loads_file_names_the_file_and_key(tmp_path, content, words: str) -> None:
    parser = argparse.ArgumentParser()
    add_load_options(parser)
    file = tmp_path / "loads.json"
    file.write_text(json.dumps(content))
    args = parser.parse_args(["--gravity", "0,0,-9.81", "--loads", str(file)])
    with pytest.raises(UsageError, match=words) as caught:
        loads_from_args(args, 0.4)
    assert str(file) in str(caught.value)
    good = parser.parse_args(["--loads", str(file)]) if content == {
        "gravity": [0, 0, -9.81]} else None
    if good is not None:
        assert loads_from_args(good, 0.4)["gravity"] == [0, 0, -9.81]


def test_every_command_on_the_rod_takes_the_same_load_options() -> None:
    from cr_nlp.cli.main import build_parser

    parser = build_parser()
    wanted = {"--tip-force", "--tip-moment", "--gravity", "--distributed-force",
              "--point-load", "--loads"}
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for command in ("statics", "ik", "plan", "follow"):
        options = {o for a in sub.choices[command]._actions for o in a.option_strings}
        assert wanted <= options, (command, wanted - options)


def test_a_fitted_robot_gets_its_recordings_gravity_unless_one_is_given(capsys) -> None:
    """``ftdcr_v6_cosserat`` (``calibrate --model cosserat``): without ``--gravity`` the
    tension tasks run under the gravity of the recording it was fitted to, as ``predict``
    predicts; ``--gravity`` or a loads file's gravity wins; a robot without a fitted
    gravity gets none."""
    from cr_nlp.model import load_robot

    fitted = load_robot("ftdcr_v6_cosserat")
    parser = argparse.ArgumentParser()
    add_load_options(parser)
    loads = loads_from_args(parser.parse_args([]), 0.222, fitted)
    assert loads["gravity"] == list(fitted.mechanics.calibration_gravity)
    assert "calibration_gravity" in capsys.readouterr().err
    given = loads_from_args(parser.parse_args(["--gravity", "0,0,-9.81"]), 0.222, fitted)
    assert given["gravity"] == [0.0, 0.0, -9.81]
    assert loads_from_args(parser.parse_args([]), 0.4, load_robot("tdcr2_rao2021"))[
        "gravity"] is None
    # the one default, also for the cases of a statics --cases file
    assert fitted_gravity(fitted) == list(fitted.mechanics.calibration_gravity)
    assert fitted_gravity(load_robot("tdcr2_rao2021")) is None
