"""Issue 11: one verdict for every task and mode, a polish that constrains what the
checker checks, and parallel polishes equal to serial ones."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cr_nlp import IKConfig, IKSolver, TrajectoryConfig, TrajectoryPlanner, load_robot
from cr_nlp.bench.ik import free_case
from cr_nlp.model import CasadiModel
from cr_nlp.model.limits import limit_violation_q
from cr_nlp.stages.polish._trajectory_nlp import TrajectoryPolishConfig, TrajectoryPolisher
from cr_nlp.tasks.geometry.trajectory import interpolate_trajectory, verify_trajectory
from cr_nlp.world import check_many
from cr_nlp.world.scene import load_scene
from cr_nlp.world.verdict import failure_reason

from ...conftest import MODELS

# A 2-segment robot with fixed lengths, per-segment routing and a rotated, offset base:
# the robot of the issue's false failures.
TDCR2_ROT = {
    "name": "tdcr2_rot",
    "segments": [{"length": 0.12, "theta_max": 2.0}, {"length": 0.10, "theta_max": 1.6}],
    "backbone_radius": 0.006,
    "points_per_segment": 8,
    "tendons": {"per_segment": 4, "radius": 0.005, "offsets": [0.0, 0.785],
                "routing": "per_segment"},
    "base": {"position": [0.3, -0.2, 0.5], "wxyz": [0.7071067811865476, 0.7071067811865476,
                                                   0.0, 0.0]},
    "tendon_speed_max": 0.05,
    "tendon_accel_max": 0.5,
}


def test_the_rule_accepts_1e_8_and_names_what_fails_by_how_much() -> None:
    assert failure_reason({"limits": 1e-8, "clearance": 0.0}, pose_error=1e-9,
                          pose_tolerance=1e-2) == ""
    why = failure_reason({"limits": 2e-6, "tendon_speed": 0.0}, pose_error=1e-9,
                         pose_tolerance=1e-2)
    assert "configuration limit by 2e-06" in why and "speed" not in why
    assert "pose error 0.5" in failure_reason({}, pose_error=0.5, pose_tolerance=1e-2)
    assert "in collision" in failure_reason({"clearance": 0.01}, min_clearance=-0.008)


def test_a_valid_answer_breaking_a_limit_by_1e_8_is_a_success() -> None:
    robot = load_robot(TDCR2_ROT)
    q = np.array([2.0 + 1e-8, 0.4, 0.12, 1.2, -0.7, 0.10])   # θ1 beyond θmax by 1e-8
    assert limit_violation_q(robot, q[None])[0] == pytest.approx(1e-8, rel=1e-3)
    position, rotation = CasadiModel(robot).tip(q)
    from cr_nlp.model.rotations import wxyz_from_matrix

    solver = IKSolver(robot)
    wxyz = wxyz_from_matrix(rotation[None])
    checked = solver.verify(q[None], position[None], wxyz)
    assert checked.success[0], checked.reason[0]
    assert checked.max_violation[0] == pytest.approx(1e-8, rel=1e-3)
    # A trajectory with that waypoint is judged by the same rule.
    traj = np.stack([q, q, q])
    traj[:, 2], traj[:, 5] = 0.12, 0.10
    assert verify_trajectory(robot, None, traj, 1.0).success
    traj[1, 0] = 2.0 + 2e-6
    verdict = verify_trajectory(robot, None, traj, 1.0)
    assert not verdict.success and "configuration limit by 2e-06" in verdict.reason


def test_exact_ik_on_the_issue_robot_calls_every_valid_answer_a_success() -> None:
    robot = load_robot(TDCR2_ROT)
    case = free_case(robot, 12, seed=3)
    result = IKSolver(robot).solve(case.positions, case.wxyz, exact=True)
    assert result.success.all(), [r for r in result.reason if r]
    assert np.all(result.pose_error < 1e-2)
    assert np.all(limit_violation_q(robot, result.q) <= 1e-6)


def test_parallel_ik_polishes_return_the_serial_answers() -> None:
    robot = load_robot(MODELS / "robots" / "tdcr3.json")
    case = free_case(robot, 8, seed=5)
    serial = IKSolver(robot, "lattice").solve(case.positions, case.wxyz, exact=True)
    parallel_solver = IKSolver(robot, "lattice", IKConfig(polish_workers=2))
    parallel = parallel_solver.solve(case.positions, case.wxyz, exact=True)
    parallel_solver._polish_pool.close()
    assert serial.stage_text == parallel.stage_text
    np.testing.assert_array_equal(serial.success, parallel.success)
    np.testing.assert_allclose(parallel.q, serial.q, atol=1e-9)


def cut_between_waypoints(robot):
    """A 6-waypoint motion, and a small sphere that every waypoint clears by more than
    δ + 2 cm while the motion between waypoints 2 and 3 passes through it."""
    q_a = np.array([0.5, 0.3, 1.0, 0.6, 1.0, 1.0, 0.4, 2.0, 1.0])
    q_b = np.array([1.2, -0.5, 1.0, 0.9, 2.0, 1.0, 1.0, -1.0, 1.0])
    q0 = q_a + np.linspace(0.0, 1.0, 6)[:, None] * (q_b - q_a)
    dense = interpolate_trajectory(q0, 4)
    middle = dense[2 * 4 + 2]                       # halfway between waypoints 2 and 3
    tip = CasadiModel(robot).tip(middle)[0]
    scene = load_scene({"name": "cut", "obstacles": [
        {"type": "sphere", "name": "thin", "center": [float(x) for x in tip], "radius": 0.01}]})
    return q0, scene


def test_a_motion_cutting_an_obstacle_between_clear_waypoints_is_caught_and_repaired() -> None:
    robot = load_robot(MODELS / "robots" / "tdcr3.json")
    q0, scene = cut_between_waypoints(robot)
    dt = 1.0
    waypoints = check_many(robot, scene, q0)
    assert not waypoints.collision.any() and waypoints.min_distance.min() > 0.022
    before = verify_trajectory(robot, scene, q0, dt)
    assert not before.collision_free             # only the motion cuts it
    polisher = TrajectoryPolisher(robot, scene, 6)
    out = polisher.solve(q0, dt)
    # The polish's own constraints see the cut (at the samples inside the interval) ...
    assert out.warm_start_violations["clearance"] > 0.01
    # ... and repair it: the checker accepts the polished motion.
    assert out.success, out.status
    after = verify_trajectory(robot, scene, out.q, dt)
    assert after.success, after.reason
    np.testing.assert_allclose(out.q[[0, -1]], q0[[0, -1]], atol=1e-12)
    # Rows at the waypoints alone do not see it: that polish leaves the cut.
    blind = TrajectoryPolisher(robot, scene, 6, config=TrajectoryPolishConfig(
        interpolation_checks=0, verify_samples=1))
    assert blind.solve(q0, dt).warm_start_violations["clearance"] == 0.0


def test_parallel_trajectory_polishes_return_the_serial_answers() -> None:
    # Two problems whose LM answers break the tendon speed limit (a nearly free tendon
    # penalty), so both are polished: once in this process, once by a 2-process pool.
    robot = load_robot(MODELS / "robots" / "tdcr3.json")
    starts = [[0.5, 0.3, 1.0, 0.6, 1.0, 1.0, 0.4, 2.0, 1.0],
              [1.2, -0.5, 1.0, 0.9, 2.0, 1.0, 1.0, -1.0, 1.0]]
    goals = [starts[1], [0.4, 0.8, 1.0, 0.3, -2.0, 1.0, 0.9, 1.0, 1.0]]
    config = TrajectoryConfig(waypoints=10, dt=0.12, guesses=1, tendon_weight=1e-9,
                              tendon_limit_fraction=1.0)
    serial = TrajectoryPlanner(robot, None, config).plan(starts, goals, init="straight",
                                                          exact=True)
    pooled_planner = TrajectoryPlanner(robot, None, replace(config, polish_workers=2))
    try:
        pooled = pooled_planner.plan(starts, goals, init="straight", exact=True)
    finally:
        pooled_planner.close()
    assert [r.stage for r in serial] == [r.stage for r in pooled] == ["polish", "polish"]
    for a, b in zip(serial, pooled, strict=True):
        assert a.success and b.success
        np.testing.assert_allclose(b.q, a.q, atol=1e-9)
