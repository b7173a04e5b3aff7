"""The verdict's float64 program (``world._verdict_program``) against the numpy verdict:
the same tip poses, pose errors and self-distances on random configurations, in program
blocks, padded blocks and numpy remainders alike."""

import importlib
from typing import Any

import numpy as np
import pytest

from cr_nlp.model import Robot, pose_error
from cr_nlp.model.kinematics import tip_pose
from cr_nlp.model.limits import limit_violation_q
from cr_nlp.model.rotations import wxyz_from_matrix
from cr_nlp.world import check_many, load_scene
from cr_nlp.world.check import body_chain

from ..conftest import MODELS, random_q

program = importlib.import_module("cr_nlp.world._verdict_program")
motion_check = importlib.import_module("cr_nlp.world._motion_check")


class _Counters:
    device_calls = 0
    device_launch = 0.0
    device_wait = 0.0


def _targets(robot: Robot, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Reachable targets: the tips of other random configurations."""
    pos, rot = tip_pose(robot, random_q(robot, count, seed + 1000))
    return pos, rot


@pytest.mark.parametrize("name", ["tdcr3", "tdcr4_ext"])
def test_program_matches_the_numpy_verdict(name, monkeypatch) -> None:
    robot = Robot.from_file(MODELS / "robots" / f"{name}.json")
    monkeypatch.setattr(program, "ROWS", 256)
    # Two full blocks and one padded block (200 of 256); then a remainder under a quarter
    # of a block (numpy).
    for count, programs in ((712, 3), (530, 2)):
        q = random_q(robot, count, seed=count)
        q[::7, 0] = robot.segments[0].theta_max + 0.3       # some beyond θ max
        target_p, target_r = _targets(robot, count, count)
        counters = _Counters()
        got = program.answer_geometry(robot, q, target_p, target_r, counters)
        pos, rot = tip_pose(robot, q)
        want = {"position": pos, "wxyz": wxyz_from_matrix(rot),
                "pose_error": pose_error(pos, rot, target_p, target_r),
                "position_error": np.linalg.norm(pos - target_p, axis=1),
                "rotation_error": np.arccos(np.clip(
                    (np.trace(np.einsum("bji,bjk->bik", rot, target_r), axis1=1, axis2=2)
                     - 1) / 2, -1, 1)),
                "self_distance": check_many(robot, None, q).self_distance,
                "limits": limit_violation_q(robot, q)}
        for field, value in want.items():
            assert getattr(got, field).dtype == np.float64
            np.testing.assert_allclose(getattr(got, field), value, rtol=0, atol=1e-12,
                                       err_msg=field)
        assert (got.self_distance < 0).any() and (got.self_distance > 0).any()
        assert np.allclose(got.limits[::7], 0.3) and (got.limits[1::7] == 0).all()
        assert counters.device_calls == programs and counters.device_wait >= 0.0


def test_no_self_pairs_give_infinity(monkeypatch) -> None:
    data = Robot.from_file(MODELS / "robots" / "tdcr3.json").to_dict()
    robot = Robot.from_dict({**data, "self_collision": False})
    monkeypatch.setattr(program, "ROWS", 256)
    q = random_q(robot, 300, seed=1)
    target_p, target_r = _targets(robot, 300, 1)
    got = program.answer_geometry(robot, q, target_p, target_r)
    assert np.all(got.self_distance == np.inf)
    np.testing.assert_allclose(got.position, tip_pose(robot, q)[0], rtol=0, atol=1e-12)
    empty = program.answer_geometry(robot, np.zeros((0, robot.dof)), np.zeros((0, 3)),
                                    np.zeros((0, 3, 3)))
    assert empty.self_distance.shape == (0,) and empty.wxyz.shape == (0, 4)


def _numpy_pieces(robot: Robot, chains: np.ndarray) -> Any:
    """The motion search's own ``Pieces`` of body chains (B, points, 3), numpy."""
    ends = (tuple(np.ascontiguousarray(c[..., k]) for k in range(3))
            for c in (chains[:, :-1], chains[:, 1:]))
    return motion_check.piece_geometry(robot.backbone_radius, *ends,
                                       motion_check._run_length(robot.points_per_segment))


def _leaves(pieces: Any) -> list[np.ndarray]:
    return [a for f in pieces for a in (f if isinstance(f, tuple) else (f,))]


@pytest.mark.parametrize("name,self_collision", [("tdcr3", True), ("tdcr4_ext", True),
                                                 ("tdcr3", False)])
def test_motion_program_matches_the_numpy_chains_and_self_distances(name,
                                                                    self_collision) -> None:
    """``motion_chains`` (the motion verdict's program, blocks of ``MOTION_ROWS``, the last
    padded) gives numpy's body chains and ``check_many``'s self distances (+inf where the
    robot's self-collision is off) and the motion search's ``Pieces``, also beyond θ max;
    under half a block, numpy's chains and neither of the others."""
    robot = Robot.from_file(MODELS / "robots" / f"{name}.json")
    if not self_collision:
        robot = Robot.from_dict({**robot.to_dict(), "self_collision": False})
    for count in (program.MOTION_ROWS + 93, program.MOTION_ROWS // 2):
        q = random_q(robot, count, seed=count)
        q[::7, 0] = robot.segments[0].theta_max + 0.3
        chains, own, pieces = program.motion_chains(robot, q)
        assert chains.dtype == own.dtype == np.float64
        np.testing.assert_allclose(chains, body_chain(robot, q), rtol=0, atol=1e-12)
        want = _numpy_pieces(robot, body_chain(robot, q))
        for got, expected in zip(_leaves(pieces), _leaves(want), strict=True):
            assert got.dtype == np.float64 and got.flags.c_contiguous
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
        want = check_many(robot, None, q).self_distance
        np.testing.assert_allclose(own, want, rtol=0, atol=1e-12)
        if not self_collision:
            assert np.all(own == np.inf)
        elif count > program.MOTION_ROWS:
            assert (own < 0).any() and (own > 0).any()
    q = random_q(robot, program.MOTION_ROWS // 2 - 1, seed=5)      # one motion's: numpy
    chains, own, pieces = program.motion_chains(robot, q)
    assert own is None and pieces is None and np.array_equal(chains, body_chain(robot, q))


def test_the_motion_search_on_the_program_pieces_reports_what_it_does_on_its_own() -> None:
    """``check_motions`` given ``motion_chains``' self distances and ``Pieces`` reports for
    every motion what it reports computing them itself (numpy): the same smallest
    obstacle and self distances, closest parts and collisions, in one round and in
    several."""
    robot = Robot.from_file(MODELS / "robots" / "tdcr3.json")
    scene = load_scene("shelf")
    q = random_q(robot, program.MOTION_ROWS + 60, seed=11)
    chains, own, pieces = program.motion_chains(robot, q)
    spans = [(0, 100), (100, 230), (230, len(q))]
    motions = [chains[a:b] for a, b in spans]
    for elements in (motion_check._ROUND_ELEMENTS, 4096):
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(motion_check, "_ROUND_ELEMENTS", elements)
            given = motion_check.check_motions(robot, scene, motions, own, pieces)
            alone = motion_check.check_motions(robot, scene, motions)
        for a, b in zip(given, alone, strict=True):
            assert a.obstacle_distance == b.obstacle_distance and a.closest == b.closest
            assert a.self_distance == pytest.approx(b.self_distance, abs=1e-12)
            assert np.array_equal(a.collision, b.collision)
        assert any(m.collision.any() for m in alone) and not all(m.collision.all()
                                                                 for m in alone)
