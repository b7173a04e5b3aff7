"""Path following in exact mode: Ipopt enforces a tendon-speed bound that the penalty
answer breaks, and the independent verdict agrees."""

from __future__ import annotations

from dataclasses import replace

import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp.model import load_robot, q_to_z, tip_pose_z
from cr_nlp.model.rotations import wxyz_from_matrix
from cr_nlp.tasks.geometry.follow import FollowConfig, PathFollower
from cr_nlp.tasks.geometry.ik import IKConfig
from cr_nlp.tasks.geometry.trajectory import tendon_series, verify_trajectory
from cr_nlp.tasks.paths import ReferencePath

WAYPOINTS = 12
Q_A = np.array([0.6, 0.3, 1.0, 0.5, 1.2, 1.0, 0.4, -0.6, 1.0])
Q_B = np.array([0.9, 0.5, 1.0, 0.3, 1.0, 1.0, 0.7, -0.3, 1.0])
LINE = Q_A + np.linspace(0.0, 1.0, WAYPOINTS)[:, None] * (Q_B - Q_A)


@pytest.fixture(scope="module")
def slow_robot_runs():
    # tdcr3 itself (its compiled IK programs are shared with the other follow tests),
    # with Δt chosen so that tracking LINE needs 1/0.7 of the tendon speed limit.
    robot = load_robot("tdcr3")
    step = float(np.max(np.abs(np.diff(tendon_series(robot, LINE), axis=0))))   # m
    dt = step / (robot.tendon_speed_max / 0.7)
    pos, rot = tip_pose_z(robot, q_to_z(robot, jnp.asarray(LINE)))
    path = ReferencePath("line", np.asarray(pos), wxyz_from_matrix(np.asarray(rot)), dt,
                         np.ones(WAYPOINTS, bool))
    # A weak tendon penalty aimed at the real limit, no stiff repair: the penalty answer
    # trades the limit for tracking, which is what a penalty may do.
    config = FollowConfig(tendon_weight=1e-4, tendon_limit_fraction=1.0,
                          tendon_repair_weight=None,
                          ik=IKConfig(pool_size=1024, seeds_per_target=4, refine_iterations=20))
    follower = PathFollower(robot, None, config)
    return robot, path, follower.follow(path), follower.follow(path, exact=True)


def test_penalty_answer_breaks_the_tendon_speed_bound(slow_robot_runs) -> None:
    robot, _, penalty, _ = slow_robot_runs
    assert penalty.tendon_speed > robot.tendon_speed_max + 1e-3, (penalty.tendon_speed,
                                                                  robot.tendon_speed_max)
    assert penalty.violations["tendon_speed"] > 1e-3
    assert not penalty.success


def test_exact_mode_keeps_the_bound_and_the_checker_agrees(slow_robot_runs) -> None:
    robot, path, penalty, exact = slow_robot_runs
    assert exact.stage == "polish", exact.stage
    assert exact.max_violation <= 1e-6, exact.violations
    assert exact.tendon_speed <= robot.tendon_speed_max + 1e-6
    verdict = verify_trajectory(robot, None, exact.q, path.dt)
    assert verdict.max_violation <= 1e-6 and verdict.collision_free, verdict.reason
    # Keeping the bound costs tracking accuracy somewhere: the path needs a faster motion.
    assert np.max(exact.position_error) > np.max(penalty.position_error)


def test_stiff_repair_returns_the_stiff_answer_where_a_soft_penalty_broke_the_bound(
        slow_robot_runs) -> None:
    # A path that needs 1/0.7 of the speed limit, a penalty too soft to hold it: with no
    # repair the answer breaks the limit; with it, the answer is the stiff penalty's
    # own (the same refine from the same stage-1 sequence).
    robot, path, _, _ = slow_robot_runs
    ik = IKConfig(pool_size=1024, seeds_per_target=4, refine_iterations=20)
    soft = FollowConfig(tendon_weight=1e-4, tendon_repair_weight=None, ik=ik)
    broken = PathFollower(robot, None, soft).follow(path)
    repaired = PathFollower(robot, None, replace(soft, tendon_repair_weight=10.0)).follow(path)
    stiff = PathFollower(robot, None, replace(soft, tendon_weight=10.0)).follow(path)
    assert broken.tendon_speed > robot.tendon_speed_max + 1e-3
    np.testing.assert_allclose(repaired.q, stiff.q, atol=1e-6)
    assert repaired.tendon_speed < broken.tendon_speed
