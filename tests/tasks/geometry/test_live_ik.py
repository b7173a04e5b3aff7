"""Live IK (``tasks.geometry.live_ik``): warm-started single-target IK, judged in float64."""

from __future__ import annotations

import numpy as np
import pytest

from cr_nlp.model import load_robot
from cr_nlp.model._ops import NUMPY
from cr_nlp.model.kinematics import model_q_to_z, model_segment_frames
from cr_nlp.model.rotations import wxyz_from_matrix
from cr_nlp.tasks.geometry.live_ik import LiveIKConfig, LiveIKSolver


def _tip(robot, q):
    rot, pos = model_segment_frames(NUMPY, robot, model_q_to_z(NUMPY, robot, np.asarray(q)))[-1]
    return np.array([float(v) for v in pos]), np.array([float(v) for v in rot]).reshape(3, 3)


def test_a_far_target_falls_back_to_the_search_and_a_near_one_does_not() -> None:
    robot = load_robot("tdcr3")
    # Two LM iterations cannot cross the workspace (the next test): the search must run.
    solver = LiveIKSolver(robot, config=LiveIKConfig(iterations=2))
    straight = np.array([0.0, 0.0, 1.0] * 3)
    far = np.array([2.5, 0.3, 1.0, 2.0, 2.8, 1.0, 1.5, -2.0, 1.0])
    position, rotation = _tip(robot, far)
    answer = solver.solve(straight, position, wxyz_from_matrix(rotation[None])[0])
    reached, reached_rotation = _tip(robot, answer.q)
    assert answer.success and answer.stage == "search" and "search" in answer.timing, answer
    assert np.linalg.norm(reached - position) < 1e-2
    assert np.arccos(np.clip((np.trace(reached_rotation.T @ rotation) - 1) / 2, -1, 1)) < 1e-2
    # A small move from there is the warm-started LM alone.
    near = answer.q + np.r_[[0.01, 0.01, 0.0] * 3]
    position, rotation = _tip(robot, near)
    step = solver.solve(answer.q, position, wxyz_from_matrix(rotation[None])[0])
    assert step.success and step.stage == "refine" and "search" not in step.timing, step
    assert step.pose_error < 1e-3  # two LM iterations from a 0.01 rad move


def test_without_the_fallback_a_miss_is_reported_not_hidden() -> None:
    robot = load_robot("tdcr3")
    solver = LiveIKSolver(robot, config=LiveIKConfig(fallback_search=False, iterations=2))
    far = np.array([2.5, 0.3, 1.0, 2.0, 2.8, 1.0, 1.5, -2.0, 1.0])
    position, rotation = _tip(robot, far)
    answer = solver.solve([0.0, 0.0, 1.0] * 3, position, wxyz_from_matrix(rotation[None])[0])
    assert not answer.success and "pose error" in answer.reason
    assert answer.pose_error > 1e-2


def test_invalid_targets_are_errors() -> None:
    solver = LiveIKSolver("tdcr3")
    with pytest.raises(ValueError, match="out of reach"):
        solver.solve([0.0, 0.0, 1.0] * 3, [0.0, 0.0, 9.0], [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="unit quaternion"):
        solver.solve([0.0, 0.0, 1.0] * 3, [0.0, 0.0, 2.0], [2.0, 0.0, 0.0, 0.0])


def test_live_updates_compile_their_programs_fully(monkeypatch: pytest.MonkeyPatch) -> None:
    from cr_nlp import _compile_effort

    robot = load_robot("tdcr3")
    solver = LiveIKSolver(robot, config=LiveIKConfig(fallback_search=False, iterations=2))
    refine, asked = solver._refine, []

    def recorded(*args):
        asked.append(_compile_effort.forced_full())
        return refine(*args)

    monkeypatch.setattr(solver, "_refine", recorded)
    position, rotation = _tip(robot, np.array([0.1, 0.2, 1.0] * 3))
    answer = solver.solve([0.0, 0.0, 1.0] * 3, position, wxyz_from_matrix(rotation[None])[0])
    # The update runs with programs optimised at once: a live solver's later updates run
    # the code its first one compiles (cr_nlp._compile_effort).
    assert asked == [True] and answer.success
    assert not _compile_effort.forced_full()
