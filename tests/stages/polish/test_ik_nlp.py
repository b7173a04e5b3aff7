"""Stage 3 (polish): Ipopt from a warm start, constraints as constraints, verdicts re-checked."""

import casadi as ca
import numpy as np
import pytest

from cr_nlp.model import load_robot, tip_pose
from cr_nlp.model.limits import limit_violation_q
from cr_nlp.stages.polish import _ik_nlp as polish_module
from cr_nlp.stages.polish._ik_nlp import (
    IKPolisher,
    PolishConfig,
    PolishResult,
    polish_many,
)
from cr_nlp.world import (
    ConvexPart,
    Obstacle,
    Scene,
    check,
    clearance,
    load_scene,
    scene_arrays,
)

from ...conftest import MODELS


@pytest.fixture(scope="module")
def tdcr3():
    return load_robot(MODELS / "robots" / "tdcr3.json")


@pytest.fixture(scope="module")
def tdcr4_ext():
    return load_robot(MODELS / "robots" / "tdcr4_ext.json")


@pytest.fixture(scope="module")
def lattice():
    return load_scene(MODELS / "scenes" / "lattice.json")


@pytest.fixture(scope="module")
def free_polisher(tdcr3):
    return IKPolisher(tdcr3)


@pytest.fixture(scope="module")
def lattice_polisher(tdcr3, lattice):
    return IKPolisher(tdcr3, lattice)


def target_of(robot, q):
    position, rotation = tip_pose(robot, np.asarray(q, dtype=np.float64))
    return np.asarray(position), np.asarray(rotation)


def random_q(robot, rng):
    lo, hi = robot.q_bounds()
    return lo + (hi - lo) * rng.random(robot.dof)


def perturbed(robot, q, rng, sigma):
    """q + noise, lengths kept in range (a perturbed stage-2 answer)."""
    lo, hi = robot.q_bounds()
    q0 = q + rng.normal(0.0, sigma, robot.dof)
    q0[2::3] = np.clip(q0[2::3], lo[2::3], hi[2::3])
    return q0


def assert_exact(result: PolishResult):
    assert result.success, result
    assert result.pose_error < 1e-6
    assert 0.0 <= result.max_violation <= 1e-6


# ---------------------------------------------------------------- without obstacles


@pytest.mark.parametrize("modes", [("equality", "minimize"), ("minimize",)])
def test_tdcr3_reaches_the_target_from_a_perturbed_start(tdcr3, free_polisher, modes):
    polisher = free_polisher if modes == free_polisher.config.modes else IKPolisher(
        tdcr3, config=PolishConfig(modes=modes))
    rng = np.random.default_rng(0)
    for _ in range(3):
        q_true = random_q(tdcr3, rng)
        result = polisher.solve(perturbed(tdcr3, q_true, rng, 0.05), *target_of(tdcr3, q_true))
        assert_exact(result)
        assert result.mode == modes[0]
        assert result.q.shape == (tdcr3.dof,)
        # The answer is checked again here, from q (θ, φ, L) through the JAX kinematics.
        position, rotation = target_of(tdcr3, result.q)
        target_position, target_rotation = target_of(tdcr3, q_true)
        assert np.linalg.norm(position - target_position) < 1e-6
        assert np.abs(rotation - target_rotation).max() < 1e-6


def test_tdcr4_ext_reaches_the_target_with_lengths_in_range(tdcr4_ext):
    polisher = IKPolisher(tdcr4_ext)
    rng = np.random.default_rng(1)
    for _ in range(3):
        q_true = random_q(tdcr4_ext, rng)
        result = polisher.solve(perturbed(tdcr4_ext, q_true, rng, 0.1),
                                *target_of(tdcr4_ext, q_true))
        assert_exact(result)
        lengths = result.q[2::3]
        assert np.all(lengths >= 0.5 - 1e-6) and np.all(lengths <= 1.5 + 1e-6)


def test_bending_beyond_theta_max_is_brought_back(tdcr3, free_polisher):
    q_true = np.array([3.0, 0.4, 1.0, 1.2, -2.0, 1.0, 0.7, 2.5, 1.0])
    q0 = q_true + np.array([np.pi + 0.4 - 3.0, 0.05, 0.0, 0.05, 0.0, 0.0, -0.05, 0.05, 0.0])
    assert limit_violation_q(tdcr3, q0) > 0.3           # θ1 = π + 0.4 rad
    result = free_polisher.solve(q0, *target_of(tdcr3, q_true))
    assert_exact(result)
    assert np.all(result.q[0::3] <= np.pi + 1e-6)
    assert limit_violation_q(tdcr3, result.q) <= 1e-6


def test_the_nlp_is_built_once_and_reused(tdcr3, monkeypatch):
    constructions = []
    real_nlpsol = ca.nlpsol

    def counting_nlpsol(*args, **kwargs):
        constructions.append(args[0])
        return real_nlpsol(*args, **kwargs)

    monkeypatch.setattr(polish_module.ca, "nlpsol", counting_nlpsol)
    # CasADi's virtual machine: no switch to compiled functions mid-test (that switch is
    # tested in test_compiled_functions.py).
    polisher = IKPolisher(tdcr3, config=PolishConfig(compile=False))
    assert polisher.builds == len(polisher.config.modes) == len(constructions)
    rng = np.random.default_rng(2)
    q_true = [random_q(tdcr3, rng) for _ in range(4)]
    targets = [target_of(tdcr3, q) for q in q_true]
    results = polish_many(polisher, [perturbed(tdcr3, q, rng, 0.05) for q in q_true],
                          [p for p, _ in targets], [r for _, r in targets], progress=True)
    results.append(polisher.solve(q_true[0], *targets[1]))   # a far warm start: more work
    assert len(results) == 5 and all(r.success for r in results)
    assert polisher.builds == len(constructions) == 2


def test_an_unreachable_target_fails_without_raising(tdcr3, free_polisher):
    q0 = np.array([0.5, 0.0, 1.0, 0.5, 1.0, 1.0, 0.5, 2.0, 1.0])
    result = free_polisher.solve(q0, np.array([10.0, 0.0, 0.0]), np.eye(3))
    assert not result.success
    assert isinstance(result.status, str) and result.status
    assert result.pose_error > 1.0
    assert np.all(np.isfinite(result.q)) and result.q.shape == (tdcr3.dof,)
    assert result.iterations > 0 and result.seconds > 0.0


def test_azimuth_ranges_are_not_enforced_but_measured(tdcr3):
    data = tdcr3.to_dict()
    data["segments"][1]["phi_range"] = [0.0, 1.0]
    robot = load_robot(data)
    polisher = IKPolisher(robot)
    q_true = np.array([1.0, 0.3, 1.0, 0.8, 0.5, 1.0, 0.6, -1.0, 1.0])
    inside = polisher.solve(q_true + 0.05, *target_of(robot, q_true))
    assert_exact(inside)
    # The only answer near this start has φ2 = −1.7 rad: reached, and reported as violating.
    q_out = q_true.copy()
    q_out[4] = -1.7
    outside = polisher.solve(q_out + 0.05, *target_of(robot, q_out))
    assert outside.pose_error < 1e-6
    assert not outside.success
    assert outside.max_violation == pytest.approx(1.7, abs=1e-6)


# ---------------------------------------------------------------- with obstacles


def penetrating_case(robot, scene, polisher, seed):
    """A target whose configuration keeps clearance > δ + 2 cm, and a warm start near it
    whose sphere body penetrates an obstacle by more than 2 cm (fcl agrees)."""
    arrays = scene_arrays(scene)
    delta = polisher.safety_margin
    lo, hi = robot.q_bounds()
    rng = np.random.default_rng(seed)
    q_true = random_q(robot, rng)
    while float(clearance(robot, arrays, q_true)) <= delta + 0.02:
        q_true = random_q(robot, rng)
    for _ in range(500):
        q0 = perturbed(robot, q_true, rng, 0.3)
        q0[0::3] = np.clip(q0[0::3], 0.0, hi[0::3])
        if float(clearance(robot, arrays, q0)) < -0.02:
            break
    assert check(robot, scene, q0).collision
    return q_true, q0


def assert_clear(robot, scene, polisher, result):
    assert_exact(result)
    arrays = scene_arrays(scene)
    assert float(clearance(robot, arrays, result.q)) >= polisher.safety_margin - 1e-6
    verdict = check(robot, scene, result.q)
    assert not verdict.collision and verdict.min_distance > 0.0


def test_a_penetrating_start_is_pushed_out_of_the_lattice(tdcr3, lattice, lattice_polisher):
    q_true, q0 = penetrating_case(tdcr3, lattice, lattice_polisher, seed=1)
    result = lattice_polisher.solve(q0, *target_of(tdcr3, q_true))
    assert_clear(tdcr3, lattice, lattice_polisher, result)


def test_an_active_clearance_constraint_holds_exactly(tdcr4_ext, lattice):
    # tdcr4_ext is redundant: the pose alone would let it stay close to the penetrating
    # start, so the answer lies on the clearance boundary d = δ.
    polisher = IKPolisher(tdcr4_ext, lattice)
    q_true, q0 = penetrating_case(tdcr4_ext, lattice, polisher, seed=4)
    result = polisher.solve(q0, *target_of(tdcr4_ext, q_true))
    assert_clear(tdcr4_ext, lattice, polisher, result)
    slack = float(clearance(tdcr4_ext, scene_arrays(lattice), result.q)) - polisher.safety_margin
    assert slack < 1e-4


def test_slot_rows_equal_the_world_pair_distances(tdcr3, lattice):
    """The NLP's clearance rows (pairs assigned to slots by parameters) are the world's
    pair distances, for every part kind, convex parts with the configured smoothing."""
    primitives = load_scene({"name": "primitives", "obstacles": [
        {"type": "sphere", "center": [0.5, 0.2, 1.0], "radius": 0.2},
        {"type": "box", "center": [-0.5, 0.3, 1.2], "size": [0.3, 0.4, 0.5],
         "wxyz": [0.9, 0.1, 0.3, 0.3]},
        {"type": "capsule", "a": [0.0, -0.6, 0.5], "b": [0.4, -0.5, 1.5], "radius": 0.1},
        {"type": "cylinder", "a": [-0.4, -0.4, 0.8], "b": [-0.2, -0.7, 1.6], "radius": 0.15},
    ]})
    rng = np.random.default_rng(3)
    blob = ConvexPart.from_points(rng.normal(size=(30, 3)) * 0.25 + [0.3, 0.5, 2.0])
    scene = Scene("mixed", primitives.obstacles + (Obstacle("blob", "mesh", (blob,), {}),))
    polisher = IKPolisher(tdcr3, scene, config=PolishConfig(max_pairs=16))
    kinds = [group.kind for group in polisher._groups]
    assert kinds == ["sphere", "box", "capsule", "cylinder", "convex", "self"]
    compared = 0
    for _ in range(4):
        q_near = random_q(tdcr3, rng)
        values, expected = polisher._slot_values(q_near, perturbed(tdcr3, q_near, rng, 0.05))
        np.testing.assert_allclose(values, expected, rtol=0, atol=1e-12)
        compared += len(values)
    assert compared > 20


def test_failure_reason_names_what_rejected_the_answer() -> None:
    def result(success: bool, status: str, violation: float, error: float) -> PolishResult:
        return PolishResult(np.zeros(9), success, status, violation, error, 3, 0.01, "equality",
                            {"limits": 0.0, "clearance": violation})

    assert result(True, "Solve_Succeeded", 0.0, 1e-9).failure() == ""
    assert result(False, "Infeasible_Problem_Detected", 0.1, 0.2).failure() == \
        "Ipopt: Infeasible_Problem_Detected"
    rejected = result(False, "Solve_Succeeded", 3e-3, 1e-9).failure()
    assert "breaks the clearance by 0.003 m" in rejected and "limit" not in rejected
    unreachable = result(False, "Solve_Succeeded", 0.0, 0.05).failure()
    assert "0.05" in unreachable and "not reachable" in unreachable
