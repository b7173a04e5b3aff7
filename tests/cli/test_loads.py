"""The Cosserat rod's CLI options in one module (``cli._loads``), for ``statics`` and
``ik``, ``plan``, ``follow`` with ``--model cosserat``: a bad loads file names the file and
the key; the option set is the same for every command."""

from __future__ import annotations

import argparse
import json

import pytest

from cr_nlp.cli._io import UsageError
from cr_nlp.cli._loads import add_load_options, loads_from_args


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
