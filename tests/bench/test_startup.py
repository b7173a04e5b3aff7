"""``cr-nlp bench startup``'s inputs: the ``-new`` entries run on a robot file that is not
bundled, with targets that robot reaches."""

from __future__ import annotations

import json

import numpy as np

from cr_nlp.bench.startup import entry_argv, write_inputs
from cr_nlp.model import load_robot


def test_the_new_robot_entry_runs_on_a_file_that_is_not_bundled(tmp_path) -> None:
    write_inputs(tmp_path, ("ik-new",))
    argv = entry_argv("ik-new", tmp_path, tmp_path / "out")
    robot_file = argv[argv.index("--robot") + 1]
    robot = load_robot(robot_file)
    bundled = load_robot("tdcr3")
    assert robot.name != bundled.name
    assert robot.n_tendons == bundled.n_tendons  # the same shapes, other numbers
    poses = json.loads((tmp_path / "targets_new.json").read_text())["poses"]
    assert len(poses) == 1000
    # the targets are the new robot's own reachable tips, not tdcr3's
    tips = np.array([p["position"] for p in poses])
    reach = sum(s.length_max for s in robot.segments)
    assert np.linalg.norm(tips, axis=1).max() <= reach + 1e-9
    assert np.linalg.norm(tips, axis=1).max() > 0.5 * reach
