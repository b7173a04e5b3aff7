"""Robots as data of compiled programs (``cr_nlp._by_shape``): robots of one shape share a
template and a program, robots of other shapes do not; the program computes with each
robot's own numbers (checked against the numpy model); a second robot of the same shape
solves IK and plans among spheres without tracing a program, and its answers pass the
verdict (python-fcl and its own model)."""

from __future__ import annotations

import copy
import dataclasses
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp import _programs
from cr_nlp._programs import compile_program, fingerprint
from cr_nlp.model import load_robot
from cr_nlp.model.kinematics import backbone_points, tendon_lengths, tip_pose
from cr_nlp.model.limits import limit_violation_q
from cr_nlp.model.robot import Robot
from cr_nlp.model.rotations import wxyz_from_matrix
from cr_nlp.tasks.geometry.ik import IKSolver


def _variant(robot: Robot, name: str = "variant") -> Robot:
    """``robot``'s shape with other numbers: lengths, bending limits, radii, tendon
    offsets, base pose."""
    data = copy.deepcopy(robot.to_dict())
    data["name"] = name
    for i, seg in enumerate(data["segments"]):
        seg["length"] = ([v * (0.8 + 0.1 * i) for v in seg["length"]]
                         if isinstance(seg["length"], list) else seg["length"] * (0.8 + 0.1 * i))
        seg["theta_max"] = seg["theta_max"] * 0.7
    data["backbone_radius"] *= 1.3
    data["tendons"]["radius"] *= 0.9
    data["tendons"]["offsets"] = [o + 0.2 for o in data["tendons"]["offsets"]]
    c, s = np.cos(0.3), np.sin(0.3)
    data["base"] = {"position": [0.02, -0.01, 0.05], "wxyz": [c, s, 0.0, 0.0]}
    return Robot.from_dict(data)


def test_robots_of_one_shape_share_a_template_and_others_do_not() -> None:
    tdcr3 = load_robot("tdcr3")
    other = _variant(tdcr3)
    (template, numbers), (template_2, numbers_2) = tdcr3.program_data(), other.program_data()
    assert fingerprint(template) == fingerprint(template_2)
    assert not np.allclose(numbers, numbers_2)
    filled = template.filled(numbers_2)
    for field in ("backbone_radius", "base_position", "base_wxyz"):
        assert getattr(filled, field) == pytest.approx(getattr(other, field))
    for a, b in zip(filled.segments, other.segments, strict=True):
        assert (a.length_min, a.length_max, a.theta_max, a.extendable, a.phi_limited) == (
            b.length_min, b.length_max, b.theta_max, b.extendable, b.phi_limited)
    assert filled.tendons.offsets == pytest.approx(other.tendons.offsets)
    # A limited azimuth, a length that can change or a segment more is another shape.
    assert not tdcr3.segments[0].extendable and not tdcr3.segments[0].phi_limited
    limited = dataclasses.replace(tdcr3, segments=(dataclasses.replace(
        tdcr3.segments[0], phi_min=-1.0, phi_max=1.0), *tdcr3.segments[1:]))
    extendable = dataclasses.replace(tdcr3, segments=(dataclasses.replace(
        tdcr3.segments[0], length_min=0.5 * tdcr3.segments[0].length_max),
        *tdcr3.segments[1:]))
    longer = load_robot("tdcr4_ext")
    keys = {fingerprint(r.program_data()[0]) for r in (tdcr3, limited, extendable, longer)}
    assert len(keys) == 4


def _chain(robot: Robot, scale: float, q: jax.Array) -> jax.Array:
    """The backbone (as ``backbone_points``) scaled, the limits' violation and the tendon
    lengths (the tendon offsets as data)."""
    from cr_nlp.model._ops import JAX
    from cr_nlp.model.kinematics import model_backbone, model_q_to_z, tendon_lengths_z

    z = model_q_to_z(JAX, robot, q)
    points = model_backbone(JAX, robot, z)   # (B, points, 3)
    return (scale * points, limit_violation_q(robot, q, jnp),
            tendon_lengths_z(robot, JAX.stack(z)))


def test_one_program_computes_with_each_robots_own_numbers(program_cache: Path) -> None:
    tdcr3 = load_robot("tdcr3")
    robots = [tdcr3, _variant(tdcr3), _variant(tdcr3, "other")]
    rng = np.random.default_rng(3)
    lo, hi = tdcr3.q_bounds()
    q = rng.uniform(lo, hi, (5, tdcr3.dof))
    with jax.enable_x64(True):
        for i, robot in enumerate(robots):
            program = compile_program(partial(_chain, robot, 2.0 + i), (q,), by_shape=True)
            points, limits, lengths = program(q)
            np.testing.assert_allclose(points, (2.0 + i) * backbone_points(robot, q),
                                       atol=1e-12)
            np.testing.assert_allclose(limits, limit_violation_q(robot, q), atol=1e-12)
            np.testing.assert_allclose(lengths, tendon_lengths(robot, q), atol=1e-12)
    # Three robots and three scales, one program.
    assert (_programs.stats.traced, _programs.stats.reused) == (1, 2)
    # Without by_shape each robot keeps its own program.
    with jax.enable_x64(True):
        compile_program(partial(_chain, robots[1], 2.0), (q,))
    assert _programs.stats.traced == 2


def test_a_second_robot_of_the_same_shape_solves_ik_on_the_first_ones_programs(
        program_cache: Path) -> None:
    tdcr3 = load_robot("tdcr3")
    other = _variant(tdcr3)
    rng = np.random.default_rng(5)
    answers = {}
    for robot in (tdcr3, other):
        lo, hi = robot.q_bounds()
        q = rng.uniform(lo, hi, (40, robot.dof))
        position, rotation = tip_pose(robot, q)
        _programs.stats.__init__()
        result = IKSolver(robot).solve(position, wxyz_from_matrix(rotation))
        answers[robot.name] = (result, position)
    assert _programs.stats.traced == 0 and _programs.stats.unkeyed == 0
    assert _programs.stats.reused >= 1   # the search with its seed lookup, at least
    result, position = answers["variant"]
    assert np.mean(result.success) >= 0.95
    ok = result.success
    # The answers reach the variant's targets by the variant's own model, not tdcr3's.
    np.testing.assert_allclose(tip_pose(other, result.q[ok])[0], position[ok], atol=1e-3)
    assert np.all(np.linalg.norm(tip_pose(tdcr3, result.q[ok])[0] - position[ok], axis=1)
                  > 1e-3)


def test_a_second_robot_of_the_same_shape_plans_on_the_first_ones_programs(
        program_cache: Path) -> None:
    # The broad-phase grid's cells come from one series of sizes (robots of similar
    # size and reach share a grid, hence the programs that take it).
    from cr_nlp.bench.plan import plan_problems
    from cr_nlp.model import q_to_z_numpy
    from cr_nlp.stages.explore._roadmap import ClearanceChecker
    from cr_nlp.tasks.geometry.trajectory import (
        TrajectoryConfig,
        TrajectoryPlanner,
        verify_trajectory,
    )
    from cr_nlp.world import load_scene
    from cr_nlp.world._motion import verify_trajectories

    scene = load_scene("lattice")
    tdcr3 = load_robot("tdcr3")
    data = tdcr3.to_dict()
    data["name"] = "thinner"
    data["backbone_radius"] *= 0.9
    data["tendons"]["radius"] *= 0.9
    data["segments"][1]["theta_max"] *= 0.95
    thinner = Robot.from_dict(data)
    clearances = []
    for robot in (tdcr3, thinner):
        planner = TrajectoryPlanner(robot, scene, TrajectoryConfig(guesses=2))
        starts, goals = plan_problems(robot, scene, 2, planner.margin, seed=1)
        _programs.stats.__init__()
        # Straight and perturbed guesses (a roadmap is built per robot, seconds each);
        # the roadmap's clearance program on its own below.
        results = planner.plan(starts, goals, init="straight")
        # The motion verdict's program, which the planner's verdicts use only when enough
        # motions finish together (timing): here on a motion of 401 configurations.
        verify_trajectories(robot, scene, [np.linspace(starts[0], goals[0], 101)],
                            planner.config.dt)
        checker = ClearanceChecker(robot, scene, planner.margin)
        clearances.append(checker(q_to_z_numpy(np.concatenate([starts, goals]))))
    assert _programs.stats.traced == 0 and _programs.stats.unkeyed == 0
    assert _programs.stats.reused >= 3   # the roadmap clearance, trajectory LM, verdict
    assert any(r.success for r in results)   # the straight guesses of a problem may collide
    for result in results:
        assert verify_trajectory(thinner, scene, result.q, planner.config.dt).success == (
            result.success)
    # The checker measured the thinner body (its ends keep the margin by python-fcl).
    assert np.all(clearances[1] >= planner.margin - 1e-4)


def test_a_second_robot_of_the_same_shape_follows_on_the_first_ones_programs(
        program_cache: Path) -> None:
    # test_follow's line path, settings and scene, each robot's own tip path.
    from cr_nlp.tasks.geometry.follow import PathFollower
    from cr_nlp.tasks.paths import ReferencePath
    from cr_nlp.world import load_scene

    from .tasks.geometry.test_follow import CONFIG, DT, OBSTACLE, Q_A, Q_B, WAYPOINTS

    tdcr3 = load_robot("tdcr3")
    data = tdcr3.to_dict()
    data["name"] = "thinner"
    data["backbone_radius"] *= 0.9
    data["tendons"]["radius"] *= 0.9
    thinner = Robot.from_dict(data)
    q = Q_A + np.linspace(0.0, 1.0, WAYPOINTS)[:, None] * (Q_B - Q_A)
    for robot in (tdcr3, thinner):
        position, rotation = tip_pose(robot, q)
        path = ReferencePath("line", position, wxyz_from_matrix(rotation), DT,
                             np.ones(WAYPOINTS, bool))
        _programs.stats.__init__()
        result = PathFollower(robot, load_scene(OBSTACLE), CONFIG).follow(path)
    assert _programs.stats.traced == 0 and _programs.stats.unkeyed == 0
    assert _programs.stats.reused >= 4   # stage 1's programs and the path LM
    assert result.success, result.reason
    # The answer tracks the thinner robot's own tip path by its own model.
    np.testing.assert_allclose(tip_pose(thinner, result.q)[0], position, atol=1e-3)


def test_azimuth_ranges_are_data_too(program_cache: Path) -> None:
    # Two robots whose middle segment has an azimuth range (other bounds): one program,
    # and each robot's answers keep its own range (the verdict measures the limits;
    # the ranges do not overlap, so the first robot's could not serve the second).
    tdcr3 = load_robot("tdcr3")
    robots = []
    for name, bounds in (("narrow", [0.0, 1.0]), ("apart", [1.5, 2.5])):
        data = tdcr3.to_dict()
        data["name"] = name
        data["segments"][1]["phi_range"] = bounds
        robots.append(Robot.from_dict(data))
    rng = np.random.default_rng(11)
    for robot in robots:
        lo, hi = robot.q_bounds()
        q = rng.uniform(lo, hi, (30, robot.dof))
        position, rotation = tip_pose(robot, q)
        _programs.stats.__init__()
        result = IKSolver(robot).solve(position, wxyz_from_matrix(rotation))
        assert np.mean(result.success) >= 0.9
        ok = result.success
        assert np.all(limit_violation_q(robot, result.q[ok]) <= 1e-6)
        phi = result.q[ok, 4]
        bent = result.q[ok, 3] > 1e-9
        low, high = robot.segments[1].phi_min, robot.segments[1].phi_max
        assert np.all((phi[bent] >= low - 1e-6) & (phi[bent] <= high + 1e-6))
    assert _programs.stats.traced == 0
