"""Cosserat statics against closed forms, the equilibrium of its own shapes, finite
differences and the PCC model; the robot file's ``mechanics`` block."""

from __future__ import annotations

import copy

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cr_nlp.model import ModelFileError, Robot, load_robot, tendon_lengths, tip_pose
from cr_nlp.model.cosserat import StaticsConfig, solve_statics, statics_single

RAO = load_robot("tdcr2_rao2021")


def _one_segment() -> Robot:
    data = RAO.to_dict()
    data["segments"] = data["segments"][:1]
    data["tendons"]["offsets"] = data["tendons"]["offsets"][:1]
    data["mechanics"]["disks_per_segment"] = [10]
    return Robot.from_dict(data)


# ---------------------------------------------------------------- one segment, closed forms

@pytest.fixture(scope="module")
def single() -> tuple:
    robot = _one_segment()
    mech = robot.mechanics
    assert mech is not None
    ei, gj = mech.bending_stiffness, mech.stiffness_diagonals()[1][2]
    length = 0.2
    kappa = 1.0 / length  # one radian of bending over the segment
    force = 0.01 * ei / length ** 2  # F L² / (E I) = 0.01: small deflection
    moments = np.array([[kappa * ei, 0, 0], [0, kappa * ei, 0], [0, 0, 0.5 * gj / length],
                        [0, 0, 0], [0, 0, 0]])
    forces = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [force, 0, 0], [0, 0, 0]])
    tensions = np.zeros((5, 3))
    tensions[4, 0] = 3.0
    result = solve_statics(robot, tensions, forces, moments)
    return robot, result, kappa, force, ei, gj, length


def test_pure_tip_moment_bends_a_circular_arc_of_curvature_m_over_ei(single: tuple) -> None:
    _, result, kappa, _, _, _, _ = single
    assert result.converged[:2].all()
    s = result.arc_length
    about_x = np.stack([0 * s, -(1 - np.cos(kappa * s)) / kappa, np.sin(kappa * s) / kappa], -1)
    about_y = np.stack([(1 - np.cos(kappa * s)) / kappa, 0 * s, np.sin(kappa * s) / kappa], -1)
    # 1 µm: ten RK4 steps per segment leave 0.13 µm at this curvature (20 leave 8 nm).
    np.testing.assert_allclose(result.positions[0], about_x, atol=1e-6)
    np.testing.assert_allclose(result.positions[1], about_y, atol=1e-6)
    tip = Rotation.from_matrix(result.tip_rotation[0]).as_rotvec()
    np.testing.assert_allclose(tip, [kappa * s[-1], 0, 0], atol=1e-6)


def test_pure_torsion_twists_a_straight_rod_by_m_over_gj(single: tuple) -> None:
    _, result, _, _, _, gj, length = single
    np.testing.assert_allclose(result.positions[2, :, :2], 0.0, atol=1e-12)
    twist = Rotation.from_matrix(result.tip_rotation[2]).as_rotvec()
    np.testing.assert_allclose(twist, [0, 0, 0.5], atol=1e-9)
    assert abs(0.5 * gj / length * length / gj - 0.5) < 1e-15


def test_small_tip_force_matches_the_euler_bernoulli_cantilever(single: tuple) -> None:
    _, result, _, force, ei, _, length = single
    deflection = force * length ** 3 / (3 * ei)
    tip = result.tip_position[3]
    # F L² / EI = 0.01: the large-deflection correction is of relative order 1e-4.
    assert tip[0] == pytest.approx(deflection, rel=1e-3)
    assert abs(tip[1]) < 1e-12


def test_one_tendon_gives_the_pcc_arc_scaled_by_the_axial_strain(single: tuple) -> None:
    robot, result, _, _, ei, _, length = single
    mech = robot.mechanics
    tension, radius = 3.0, robot.tendons.radius
    theta = tension * radius * length / ei        # bending moment τ r, curvature τ r / EI
    strain = 1.0 - tension / mech.stiffness_diagonals()[0][2]   # v_z = 1 − τ / EA
    alpha = robot.tendons.offsets[0]              # the tendon's side: the bend points there
    q = np.array([theta, alpha, length])
    position, rotation = tip_pose(robot, q)
    # 0.1 µm: the RK4 steps' error at this curvature is 10 nm.
    np.testing.assert_allclose(result.tip_position[4], strain * position, atol=1e-7)
    np.testing.assert_allclose(result.tip_rotation[4], rotation, atol=1e-7)
    # Tendon length ∫ |v + u × r| ds = v_z L − r θ cos(α − φ): PCC's bending term plus
    # the backbone's axial shortening.
    expected = length - (strain * length + tendon_lengths(robot, q) - length)
    np.testing.assert_allclose(result.tendon_displacements[4], expected, atol=1e-10)


# ---------------------------------------------------------------- two segments, loads

BASE_TENSION = np.array([2.0, 0.3, 1.0, 0.2, 1.5, 0.4])
BASE_FORCE = np.array([0.05, -0.1, 0.0])
BASE_MOMENT = np.array([0.0, 0.002, 0.0])
GRAVITY = np.array([-9.81, 0.0, 0.0])
STEP = 1e-4


@pytest.fixture(scope="module")
def rao() -> tuple:
    """The base case and central differences in each tension and in the tip force's x."""
    tensions = [BASE_TENSION]
    forces = [BASE_FORCE]
    for k in range(6):
        for sign in (1, -1):
            t = BASE_TENSION.copy()
            t[k] += sign * STEP
            tensions.append(t)
            forces.append(BASE_FORCE)
    for sign in (1, -1):
        tensions.append(BASE_TENSION)
        forces.append(BASE_FORCE + sign * STEP * np.array([1.0, 0, 0]))
    return solve_statics(RAO, np.array(tensions), np.array(forces), BASE_MOMENT, GRAVITY)


def test_loaded_cases_converge(rao: tuple) -> None:
    assert rao.converged.all()
    assert rao.residual.max() < 1e-10


def test_the_shape_is_in_moment_equilibrium(rao: tuple) -> None:
    """Rebuild the moment at every step's middle from the shape alone: the rod's bending
    moment from the frames' rotation between neighbours, the tendons' pull along their own
    paths, against the tip load and the weight distal of the cut."""
    mech = RAO.mechanics
    kbt = np.array(mech.stiffness_diagonals()[1])
    p, rot, s = rao.positions[0], rao.rotations[0], rao.arc_length
    h = np.diff(s)
    alpha = np.pi / 2 + np.arange(3) * 2 * np.pi / 3
    routing = 0.01 * np.stack([np.cos(alpha), np.sin(alpha), 0 * alpha], -1)
    seg_end = 0.2
    disk_s = np.concatenate([np.arange(1, 11) * 0.02, 0.2 + np.arange(1, 11) * 0.02])
    # positions of the disks: grid points (every second one)
    disk_p = np.array([p[np.argmin(abs(s - d))] for d in disk_s])
    worst, scale = 0.0, 0.0
    for k in range(len(h)):
        rel = Rotation.from_matrix(rot[k].T @ rot[k + 1]).as_rotvec()
        half = rot[k] @ Rotation.from_rotvec(0.5 * rel).as_matrix()
        rod = half @ (kbt * rel / h[k])
        mid = 0.5 * (p[k] + p[k + 1])
        s_mid = 0.5 * (s[k] + s[k + 1])
        tendons = np.zeros(3)
        active = range(6) if s_mid < seg_end else range(3, 6)
        for i in active:
            r = routing[i % 3]
            a, b = p[k] + rot[k] @ r, p[k + 1] + rot[k + 1] @ r
            t = (b - a) / np.linalg.norm(b - a)
            tendons += np.cross(0.5 * (a + b) - mid, BASE_TENSION[i] * t)
        external = BASE_MOMENT + np.cross(p[-1] - mid, BASE_FORCE)
        rod_mass = [(0.5 * (p[j] + p[j + 1]), mech.linear_density * h[j])
                    for j in range(k + 1, len(h))]
        rod_mass.append((0.5 * (mid + p[k + 1]), mech.linear_density * 0.5 * h[k]))
        for c, m in rod_mass + [(dp, mech.disk_mass) for dp, ds in zip(disk_p, disk_s, strict=True)
                                if ds > s_mid]:
            external = external + np.cross(c - mid, m * GRAVITY)
        worst = max(worst, np.abs(rod + tendons - external).max())
        scale = max(scale, np.abs(external).max(), np.abs(rod).max())
    # second-order differences over 1 cm steps: 0.1 % of the largest moment
    assert worst < 1e-3 * scale, (worst, scale)


def test_batched_solve_agrees_with_the_per_case_loop() -> None:
    """``solve_statics`` takes M(0) = M_tip without a tip force or gravity and shoots the
    rest in rounds (the unfinished cases continue in a smaller batch); the per-case
    function runs one loop per case from M(0) = 0 (the loading path, no branch check).
    Where only one equilibrium was found both must land on the same shape."""
    from cr_nlp.bench.statics import statics_cases

    tensions, forces, moments = statics_cases(6, 3, 48, "mixed", seed=3)
    gravity = np.zeros((48, 3))
    gravity[::4] = [0.0, -9.81, 0.0]
    batched = solve_statics(RAO, tensions, forces, moments, gravity)
    assert batched.converged.all()
    assert batched.iterations.max() > 10  # some cases went on to the second round
    with jax.enable_x64(True):
        single = jax.jit(jax.vmap(statics_single(RAO)))(
            *(jax.numpy.asarray(v) for v in (tensions, forces, moments, gravity)))
    unique = (batched.equilibria == 1) & np.asarray(single["converged"])
    assert unique.sum() >= 40
    np.testing.assert_allclose(batched.positions[unique],
                               np.asarray(single["positions"])[unique], atol=1e-9)
    unloaded = ~np.any(forces, axis=1) & ~np.any(gravity, axis=1)
    assert (batched.iterations[unloaded] == 0).all()
    # A case that needed the second round past a buckling load was also solved along the
    # loading path (its iterations are reported); the others are the direct loop's.
    direct = ~unloaded & unique & ((batched.iterations <= 10) | ~np.any(forces, axis=1))
    assert direct.sum() >= 15
    np.testing.assert_array_equal(batched.iterations[direct],
                                  np.asarray(single["iterations"])[direct])


@pytest.mark.slow  # compiles the forward- and reverse-mode programs (minutes under load)
def test_derivatives_match_central_differences(rao: tuple) -> None:
    solve = statics_single(RAO)
    with jax.enable_x64(True):
        def tip(tension: jax.Array, force: jax.Array) -> jax.Array:
            return solve(tension, force, jax.numpy.asarray(BASE_MOMENT),
                         jax.numpy.asarray(GRAVITY))["positions"][-1]

        args = (jax.numpy.asarray(BASE_TENSION), jax.numpy.asarray(BASE_FORCE))
        d_tension, d_force = jax.jit(jax.jacfwd(tip, argnums=(0, 1)))(*args)
        grad_x = jax.jit(jax.grad(lambda t, f: tip(t, f)[0]))(*args)
    tips = rao.tip_position
    fd_tension = np.stack([(tips[1 + 2 * k] - tips[2 + 2 * k]) / (2 * STEP)
                           for k in range(6)], -1)
    fd_force_x = (tips[13] - tips[14]) / (2 * STEP)
    np.testing.assert_allclose(np.asarray(d_tension), fd_tension, atol=1e-6, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(d_force)[:, 0], fd_force_x, atol=1e-6, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(grad_x), np.asarray(d_tension)[0], atol=1e-9)
    assert np.abs(fd_tension).max() > 1e-3  # the tensions do move the tip


# ---------------------------------------------------------------- inputs and the robot file

def test_bad_inputs_are_named() -> None:
    with pytest.raises(ValueError, match="tendon 2"):
        solve_statics(RAO, [1.0, -1.0, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="6 tendons"):
        solve_statics(RAO, [1.0, 1.0])
    with pytest.raises(ValueError, match="mechanics"):
        solve_statics(load_robot("tdcr3"), np.zeros(9))


@pytest.mark.parametrize(("field", "value", "message"), [
    ("youngs_modulus", -1.0, "mechanics.youngs_modulus"),
    ("poisson_ratio", 0.7, "mechanics.poisson_ratio"),
    ("backbone_inner_radius", 0.001, "mechanics.backbone_inner_radius"),
    ("disks_per_segment", [10], "mechanics.disks_per_segment"),
    ("disk_mass", "heavy", "mechanics.disk_mass"),
    ("colour", "blue", "mechanics.colour"),
])
def test_mechanics_block_errors_name_the_field(field: str, value: object,
                                               message: str) -> None:
    data = copy.deepcopy(RAO.to_dict())
    data["mechanics"][field] = value
    with pytest.raises(ModelFileError, match=message):
        Robot.from_dict(data, source="robot.json")


def test_mechanics_block_round_trips_and_gives_the_section() -> None:
    assert Robot.from_dict(RAO.to_dict()) == RAO
    mech = RAO.mechanics
    assert mech.area == pytest.approx(np.pi * 0.0007 ** 2)
    assert mech.bending_stiffness == pytest.approx(54e9 * np.pi * 0.0007 ** 4 / 4)
    assert mech.shear_modulus == pytest.approx(54e9 / 2.6)
    assert load_robot("tdcr3").mechanics is None


@pytest.mark.slow  # one more program to compile
def test_float32_agrees_with_float64(single: tuple) -> None:
    robot = single[0]
    t = np.array([[3.0, 0.0, 1.0]])
    f64 = solve_statics(robot, t, [0.01, 0, 0])
    f32 = solve_statics(robot, t, [0.01, 0, 0], config=StaticsConfig(dtype="float32"))
    assert f32.converged.all() and f32.positions.dtype == np.float64
    np.testing.assert_allclose(f32.tip_position, f64.tip_position, atol=2e-6)
