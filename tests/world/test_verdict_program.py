"""The verdict's float64 program (``world._verdict_program``) against the numpy verdict:
the same tip poses and self-distances on random configurations, program blocks, padded
blocks and numpy remainders alike."""

import importlib

import numpy as np
import pytest

from cr_nlp.model import Robot
from cr_nlp.model.kinematics import tip_pose
from cr_nlp.world import check_many

from ..conftest import MODELS, random_q

program = importlib.import_module("cr_nlp.world._verdict_program")


class _Counters:
    device_calls = 0
    device_launch = 0.0
    device_wait = 0.0


@pytest.mark.parametrize("name", ["tdcr3", "tdcr4_ext"])
def test_program_matches_the_numpy_verdict(name, monkeypatch) -> None:
    robot = Robot.from_file(MODELS / "robots" / f"{name}.json")
    monkeypatch.setattr(program, "ROWS", 256)
    # Two full blocks, one padded block (200 of 256) and, in the second call, a remainder
    # under a quarter of a block (numpy).
    for count, programs in ((712, 3), (530, 2)):
        q = random_q(robot, count, seed=count)
        counters = _Counters()
        pos, rot, own = program.configuration_geometry(robot, q, counters)
        want_pos, want_rot = tip_pose(robot, q)
        want_own = check_many(robot, None, q).self_distance
        assert pos.dtype == rot.dtype == own.dtype == np.float64
        np.testing.assert_allclose(pos, want_pos, rtol=0, atol=1e-12)
        np.testing.assert_allclose(rot, want_rot, rtol=0, atol=1e-12)
        np.testing.assert_allclose(own, want_own, rtol=0, atol=1e-12)
        assert (own < 0).any() and (own > 0).any()     # both sides of contact compared
        assert counters.device_calls == programs and counters.device_wait >= 0.0


def test_no_self_pairs_give_infinity(monkeypatch) -> None:
    data = Robot.from_file(MODELS / "robots" / "tdcr3.json").to_dict()
    robot = Robot.from_dict({**data, "self_collision": False})
    monkeypatch.setattr(program, "ROWS", 256)
    q = random_q(robot, 300, seed=1)
    pos, _, own = program.configuration_geometry(robot, q)
    assert np.all(own == np.inf)
    np.testing.assert_allclose(pos, tip_pose(robot, q)[0], rtol=0, atol=1e-12)
    assert program.configuration_geometry(robot, np.zeros((0, robot.dof)))[2].shape == (0,)
