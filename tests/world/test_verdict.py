"""The one verdict (``world.verdict``) with self-collision in every task, with or without
a scene: its rule, the robot-file switch, IK's verification and IK's search on a robot
that is not bundled (5 segments that can pass through each other)."""

from __future__ import annotations

import dataclasses
import math

import fcl
import numpy as np
import pytest

from cr_nlp import ModelFileError
from cr_nlp.bench.ik import forward_kinematics
from cr_nlp.model import Robot
from cr_nlp.tasks.geometry.ik import IKConfig, IKSolver
from cr_nlp.tasks.geometry.trajectory import verify_trajectory
from cr_nlp.world import body_chain, check_many
from cr_nlp.world.scene import rotation_z_to
from cr_nlp.world.verdict import VIOLATION_TOLERANCE, judge, judge_many

SEGMENT = {"length": 0.4, "theta_max": 3.14159}
SNAKE = {"name": "snake5", "segments": [SEGMENT] * 5, "backbone_radius": 0.04,
         "points_per_segment": 6, "tendons": {"per_segment": 3, "radius": 0.03}}
"""Not bundled: five 0.4 m segments of radius 4 cm bending up to π, which can pass
through each other (11 of 300 first answers of the pose-only search did, by 1.4–7.4 cm)."""

# Configurations whose targets (their forward kinematics) the pose-only search answered
# with a configuration that self-collides; they themselves keep clear of it.
SNAKE_TARGET_Q = np.array([
    [2.833, -2.43, 0.4, 1.777, 0.41, 0.4, 3.071, 0.548, 0.4, 2.191, -2.306, 0.4,
     0.961, -0.886, 0.4],
    [2.152, 0.278, 0.4, 0.62, 0.393, 0.4, 1.525, 1.126, 0.4, 2.524, 1.388, 0.4,
     2.417, -1.352, 0.4],
    [0.447, 0.605, 0.4, 2.397, -1.345, 0.4, 2.035, 0.472, 0.4, 2.621, -0.912, 0.4,
     1.492, -0.326, 0.4],
    [2.855, -0.981, 0.4, 0.449, 0.349, 0.4, 2.381, -0.179, 0.4, 0.404, -1.739, 0.4,
     2.851, -0.58, 0.4],
])


def fcl_self_clearance(robot: Robot, q: np.ndarray) -> np.ndarray:
    """(B,) smallest signed distance (m) between the capsules of segments at least two
    apart, by python-fcl itself (capsules built here, not by ``world.check``)."""
    chains = body_chain(robot, np.atleast_2d(q))
    k = robot.points_per_segment
    request = fcl.DistanceRequest(enable_signed_distance=True)
    out = []
    for chain in chains:
        capsules = []
        for i in range(len(chain) - 1):
            a, b = chain[i], chain[i + 1]
            capsules.append(fcl.CollisionObject(
                fcl.Capsule(robot.backbone_radius, float(np.linalg.norm(b - a))),
                fcl.Transform(rotation_z_to(b - a), 0.5 * (a + b))))
        best = math.inf
        for i in range(len(capsules)):
            for j in range(i + 1, len(capsules)):
                if j // k - i // k >= 2:
                    best = min(best, fcl.distance(capsules[i], capsules[j], request,
                                                  fcl.DistanceResult()))
        out.append(best)
    return np.array(out)


def test_judge_many_is_judge_row_by_row() -> None:
    rng = np.random.default_rng(4)
    count = 400
    limits = np.where(rng.random(count) < 0.2, rng.uniform(0, 3e-6, count), 0.0)
    obstacle = rng.choice([np.inf, 0.05, 0.002, 0.002 - 2e-6, -0.01], count)
    own = rng.choice([np.inf, 0.3, 0.002 - 5e-7, 0.0019, -0.02], count)
    pose = rng.choice([1e-7, 0.0099, 0.01, 0.5, np.nan], count)
    many = judge_many(margin=0.002, limits=limits, min_clearance=obstacle,
                      self_clearance=own, pose_error=pose, pose_tolerance=0.01)
    for i in range(count):
        one = judge(margin=0.002, limits=limits[i], min_clearance=obstacle[i],
                    self_clearance=own[i], pose_error=pose[i], pose_tolerance=0.01)
        assert one.success == many.success[i] and one.reason == many.reason[i]
        assert one.max_violation == many.max_violation[i]
        # The rule itself, written out.
        expected = (pose[i] < 0.01 and limits[i] <= VIOLATION_TOLERANCE
                    and obstacle[i] >= 0.002 - VIOLATION_TOLERANCE
                    and own[i] >= 0.002 - VIOLATION_TOLERANCE)
        assert one.success == expected, one
        assert one.success == (one.reason == "")
    assert 0 < many.success.sum() < count


def test_self_collision_is_its_own_family_with_its_own_words() -> None:
    v = judge(margin=0.002, self_clearance=-0.015, pose_error=1e-8, pose_tolerance=0.01)
    assert not v.success and v.self_clearance == -0.015
    assert v.violations["self_clearance"] == pytest.approx(0.017)
    assert v.violations["clearance"] == 0.0 and v.max_violation == pytest.approx(0.017)
    assert "self-collision" in v.reason and "0.015 m" in v.reason
    near = judge(margin=0.002, self_clearance=0.001)
    assert not near.success and "self-clearance by 0.001 m" in near.reason
    with pytest.raises(dataclasses.FrozenInstanceError):
        v.success = True  # type: ignore[misc]


def test_robot_file_switch_turns_self_collision_off() -> None:
    snake = Robot.from_dict(SNAKE)
    assert snake.self_collision and snake.has_self_pairs
    off = Robot.from_dict({**SNAKE, "self_collision": False})
    assert not off.has_self_pairs
    assert Robot.from_dict(off.to_dict()) == off and "self_collision" not in snake.to_dict()
    with pytest.raises(ModelFileError, match="self_collision"):
        Robot.from_dict({**SNAKE, "self_collision": "no"})
    q = SNAKE_TARGET_Q[:1].copy()
    q[0, 0::3] = [2.9, 2.9, 2.9, 2.9, 2.9]        # curled: segments 1 and 3+ overlap
    assert check_many(snake, None, q).self_distance[0] < -0.01
    assert fcl_self_clearance(snake, q)[0] < -0.01
    assert check_many(off, None, q).self_distance[0] == np.inf


def test_verify_rejects_a_self_colliding_answer_without_a_scene() -> None:
    snake = Robot.from_dict(SNAKE)
    q = SNAKE_TARGET_Q[:1].copy()
    q[0, 0::3] = 2.9
    own = fcl_self_clearance(snake, q)[0]
    positions, wxyz = forward_kinematics(snake, q)
    checked = IKSolver(snake).verify(q, positions, wxyz)       # its own target: exact
    assert checked.pose_error[0] < 1e-9
    assert not checked.success[0] and "self-collision" in checked.reason[0]
    assert checked.self_clearance[0] == pytest.approx(own, abs=1e-6)
    assert checked.max_violation[0] == pytest.approx(0.002 - own, abs=1e-6)
    off = dataclasses.replace(snake, self_collision=False)
    assert IKSolver(off).verify(q, positions, wxyz).success[0]
    # A trajectory holding that configuration fails by the same rule.
    still = verify_trajectory(snake, None, np.repeat(q, 2, 0), dt=1.0)
    assert not still.success and "self-collision" in still.reason
    assert still.violations["self_clearance"] == pytest.approx(0.002 - own, abs=1e-6)


def _snake_solver(robot: Robot) -> IKSolver:
    return IKSolver(robot, None, IKConfig(pool_size=512, chunk_size=8, retry_rounds=1))


@pytest.mark.slow  # 78 s of compiling (empty cache, 2 cores at load 7–9): -m slow
def test_ik_solves_free_targets_whose_first_answer_self_collides() -> None:
    snake = Robot.from_dict(SNAKE)
    assert np.all(fcl_self_clearance(snake, SNAKE_TARGET_Q) > 0.002)   # answers exist
    positions, wxyz = forward_kinematics(snake, SNAKE_TARGET_Q)
    solver = _snake_solver(snake)
    result = solver.solve(positions, wxyz)
    assert solver.self_repaired >= 1            # some first answer came too close
    assert result.success.all(), result.reason
    assert np.all(fcl_self_clearance(snake, result.q) >= 0.002 - 1e-6)
    assert np.all(result.pose_error < 1e-2)


@pytest.mark.slow  # a second solver's compile: `pytest -m slow`
def test_without_the_self_model_the_first_answers_self_collide() -> None:
    snake = Robot.from_dict(SNAKE)
    positions, wxyz = forward_kinematics(snake, SNAKE_TARGET_Q)
    off = dataclasses.replace(snake, self_collision=False)
    blind = _snake_solver(off).solve(positions, wxyz)
    assert blind.success.all()                 # by a rule without self-collision …
    assert np.any(fcl_self_clearance(snake, blind.q) < -1e-3)   # … they pass through


@pytest.mark.parametrize(("scene", "self_collision"),
                         [("lattice", True), (None, True), (None, False)])
def test_a_motions_path_length_is_its_tips_polyline(scene: str | None,
                                                    self_collision: bool) -> None:
    """The verdict's tip path (taken from the body chain it checks when it checks one:
    with a scene or the robot's self-collision; else from the tips alone) is the polyline
    through the tips of the densely interpolated motion by the forward kinematics
    (``bench.ik.forward_kinematics``)."""
    from cr_nlp.model import load_robot
    from cr_nlp.world import load_scene
    from cr_nlp.world._motion import interpolate_trajectory

    robot = dataclasses.replace(load_robot("tdcr3"), self_collision=self_collision)
    lo, hi = robot.q_bounds()
    q = np.random.default_rng(3).uniform(lo, hi, size=(5, robot.dof))
    verdict = verify_trajectory(robot, scene and load_scene(scene), q, dt=1.0, samples=4)
    tips, _ = forward_kinematics(robot, interpolate_trajectory(q, 4))
    expected = np.linalg.norm(np.diff(tips, axis=0), axis=1).sum()
    assert verdict.path_length == pytest.approx(expected, rel=1e-12)
