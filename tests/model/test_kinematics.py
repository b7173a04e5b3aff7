"""Kinematics against closed forms, and JAX against CasADi (values and Jacobians)."""

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cr_nlp.model import (
    CasadiModel,
    Robot,
    backbone_points,
    pose_error,
    q_to_z,
    tendon_lengths,
    tip_pose,
    z_to_q,
)
from cr_nlp.model._ops import JAX
from cr_nlp.model.lie import se3_exp, se3_log

from ..conftest import MODELS

TDCR3 = Robot.from_file(MODELS / "robots" / "tdcr3.json")
TDCR4 = Robot.from_file(MODELS / "robots" / "tdcr4_ext.json")


def one_segment(length: float = 1.0) -> Robot:
    return Robot.from_dict({
        "segments": [{"length": length, "theta_max": np.pi}],
        "backbone_radius": 0.1, "points_per_segment": 10,
        "tendons": {"per_segment": 3, "radius": 0.08, "routing": "shared"},
    })


def random_q(robot: Robot, rng: np.random.Generator, size: int) -> np.ndarray:
    lo, hi = robot.q_bounds()
    q = rng.uniform(lo, hi, size=(size, robot.dof))
    # Near-singular bending angles on purpose: exactly straight and 1e-8 rad.
    q[0, 0::3] = 0.0
    q[1, 0::3] = 1e-8
    q[2, 0] = 0.0
    q[3, 3] = 1e-8
    q[4, 0::3] = np.pi
    return q


# ------------------------------------------------------------------ closed forms

def test_straight_robot_tip_is_sum_of_lengths() -> None:
    q = np.array([0.0, 0.3, 0.7, 0.0, -1.0, 1.2, 0.0, 2.0, 0.9, 0.0, 0.0, 1.5])
    p, r = tip_pose(TDCR4, q)
    np.testing.assert_allclose(p, [0.0, 0.0, 4.3], atol=1e-12)
    np.testing.assert_allclose(r, np.eye(3), atol=1e-12)


def test_quarter_circle_tip() -> None:
    length = 1.3
    p, r = tip_pose(one_segment(length), np.array([np.pi / 2, 0.0, length]))
    np.testing.assert_allclose(p, [2 * length / np.pi, 0.0, 2 * length / np.pi], atol=1e-12)
    ry90 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    np.testing.assert_allclose(r, ry90, atol=1e-12)


def test_azimuth_rotates_the_bend_about_z() -> None:
    robot = one_segment()
    phi = 0.7
    p0, _ = tip_pose(robot, np.array([1.1, 0.0, 1.0]))
    p1, _ = tip_pose(robot, np.array([1.1, phi, 1.0]))
    rz = np.array([[np.cos(phi), -np.sin(phi), 0], [np.sin(phi), np.cos(phi), 0], [0, 0, 1]])
    np.testing.assert_allclose(p1, rz @ np.asarray(p0), atol=1e-12)


def test_backbone_points_lie_on_the_arc() -> None:
    robot = one_segment(2.0)
    theta = 1.2
    pts = np.asarray(backbone_points(robot, np.array([theta, 0.0, 2.0])))
    radius = 2.0 / theta  # circle of radius L/θ centred at (L/θ, 0, 0) in the x-z plane
    np.testing.assert_allclose(np.hypot(pts[:, 0] - radius, pts[:, 2]), radius, atol=1e-12)
    np.testing.assert_allclose(pts[-1], tip_pose(robot, np.array([theta, 0.0, 2.0]))[0], atol=1e-12)
    arc = np.linalg.norm(np.diff(np.vstack([[0, 0, 0], pts]), axis=0), axis=1)
    np.testing.assert_allclose(arc, arc[0], atol=1e-12)  # evenly spaced along the arc


def test_base_pose_is_applied() -> None:
    d = TDCR3.to_dict()
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    d["base"] = {"position": [1.0, 2.0, 3.0], "wxyz": [c, s, 0.0, 0.0]}  # 90° about x
    moved = Robot.from_dict(d)
    p, _ = tip_pose(moved, np.array([0.0, 0.0, 1.0] * 3))
    np.testing.assert_allclose(p, [1.0, -1.0, 3.0], atol=1e-12)


def test_shared_tendons_length_changes_sum_to_zero() -> None:
    robot = Robot.from_dict({**TDCR3.to_dict(), "tendons": {
        "per_segment": 3, "radius": 0.08, "offsets": [0.0, 0.4, 1.0], "routing": "shared"}})
    q = random_q(robot, np.random.default_rng(1), 50)
    lengths = np.asarray(tendon_lengths(robot, q))
    change = lengths - q[:, 2::3].sum(axis=1, keepdims=True)
    np.testing.assert_allclose(change.sum(axis=1), 0.0, atol=1e-12)
    assert lengths.shape == (50, 3)


def test_per_segment_tendons_closed_form() -> None:
    q = np.array([0.5, 0.2, 1.0, 1.0, -1.3, 1.0, 0.3, 2.0, 1.0])
    lengths = np.asarray(tendon_lengths(TDCR3, q))
    alpha = np.arange(3) * 2 * np.pi / 3
    theta, phi = q[0::3], q[1::3]
    expected = [
        sum(1.0 - 0.08 * theta[i] * np.cos(alpha[j] - phi[i]) for i in range(k + 1))
        for k in range(3) for j in range(3)
    ]
    np.testing.assert_allclose(lengths, expected, atol=1e-12)


# ------------------------------------------------------------------ JAX vs CasADi

@pytest.mark.usefixtures("float64")  # JAX Jacobians against CasADi at 1e-9
@pytest.mark.parametrize("robot", [TDCR3, pytest.param(TDCR4, marks=pytest.mark.slow)],
                         ids=["tdcr3", "tdcr4_ext"])
def test_jax_and_casadi_agree_values_and_jacobians(robot: Robot) -> None:
    rng = np.random.default_rng(7)
    qs = random_q(robot, rng, 200)
    model = CasadiModel(robot)
    q = model.q
    tip_p, tip_r = model.functions_q["tip"](q)
    tip_fn = ca.Function("tipjac", [q], [tip_p, ca.jacobian(tip_p, q),
                                          ca.jacobian(ca.vec(tip_r), q)]).map(len(qs))
    backbone = model.functions_q["backbone"](q)
    bb_fn = ca.Function("bbjac", [q], [ca.jacobian(ca.vec(backbone), q)]).map(len(qs))
    tendons = model.functions_q["tendons"](q)
    td_fn = ca.Function("tdjac", [q], [tendons, ca.jacobian(tendons, q)]).map(len(qs))

    p_c, jp_c, jr_c = (np.asarray(x) for x in tip_fn(qs.T))
    p_j, r_j = tip_pose(robot, qs)
    np.testing.assert_allclose(p_c.T, p_j, atol=1e-9)
    jac_p = jax.vmap(jax.jacfwd(lambda x: tip_pose(robot, x)[0]))(qs)
    jac_r = jax.vmap(jax.jacfwd(lambda x: tip_pose(robot, x)[1].T.reshape(-1)))(qs)
    np.testing.assert_allclose(jp_c.reshape(3, len(qs), -1).transpose(1, 0, 2), jac_p, atol=1e-9)
    np.testing.assert_allclose(jr_c.reshape(9, len(qs), -1).transpose(1, 0, 2), jac_r, atol=1e-9)
    assert np.all(np.isfinite(jac_p)) and np.all(np.isfinite(jac_r))

    jb_c = np.asarray(bb_fn(qs.T)).reshape(robot.n_points * 3, len(qs), -1).transpose(1, 0, 2)
    jac_b = jax.vmap(jax.jacfwd(lambda x: backbone_points(robot, x).T.reshape(-1)))(qs)
    np.testing.assert_allclose(jb_c, jac_b, atol=1e-9)

    t_c, jt_c = (np.asarray(x) for x in td_fn(qs.T))
    np.testing.assert_allclose(t_c.T, tendon_lengths(robot, qs), atol=1e-9)
    jac_t = jax.vmap(jax.jacfwd(lambda x: tendon_lengths(robot, x)))(qs)
    np.testing.assert_allclose(jt_c.reshape(robot.n_tendons, len(qs), -1).transpose(1, 0, 2),
                               jac_t, atol=1e-9)


@pytest.mark.usefixtures("float64")  # JAX Jacobians against CasADi at 1e-9
def test_pose_error_jax_and_casadi_agree() -> None:
    rng = np.random.default_rng(3)
    qs = random_q(TDCR3, rng, 100)
    targets = random_q(TDCR3, rng, 100)
    tp, tr = (np.asarray(x) for x in tip_pose(TDCR3, targets))
    model = CasadiModel(TDCR3)
    err = model.functions_q["pose_error"](model.q, *[ca.SX.sym(n, *s) for n, s in
                                                     [("p", (3, 1)), ("r", (3, 3))]])
    del err
    fn = model.functions_q["pose_error"]
    jac_fn = ca.Function("pej", [model.q, fn.sx_in(1), fn.sx_in(2)],
                         [ca.jacobian(fn(model.q, fn.sx_in(1), fn.sx_in(2)), model.q)])
    p, r = tip_pose(TDCR3, qs)
    e_j = pose_error(p, r, tp, tr)
    from cr_nlp.model import pose_error_vector
    jac_j = jax.vmap(jax.jacfwd(
        lambda x, a, b: pose_error_vector(*tip_pose(TDCR3, x), a, b)))(qs, tp, tr)
    for i in range(len(qs)):
        e_c = np.asarray(fn(qs[i], tp[i], tr[i])).ravel()
        assert abs(np.linalg.norm(e_c) - e_j[i]) < 1e-9
        np.testing.assert_allclose(np.asarray(jac_fn(qs[i], tp[i], tr[i])), jac_j[i], atol=1e-8)


# ------------------------------------------------------------------ derivatives at θ = 0

def test_derivatives_finite_and_correct_at_zero_bend() -> None:
    robot = one_segment()
    for theta in (0.0, 1e-8, 1e-4, 0.09, 0.11):
        q = np.array([theta, 0.3, 1.0])
        jac = np.asarray(jax.jacfwd(lambda x: tip_pose(robot, x)[0])(q))
        assert np.all(np.isfinite(jac))
        # d(tip)/dθ at θ = 0 is the half-length sideways move (L/2)(cos φ, sin φ, 0).
        eps = 1e-6
        fd = (np.asarray(tip_pose(robot, q + [eps, 0, 0])[0])
              - np.asarray(tip_pose(robot, q - [eps, 0, 0] if theta >= eps else q)[0]))
        fd /= 2 * eps if theta >= eps else eps
        np.testing.assert_allclose(jac[:, 0], fd, atol=1e-6)
    jac0 = np.asarray(jax.jacfwd(lambda x: tip_pose(robot, x)[0])(np.array([0.0, 0.3, 1.0])))
    np.testing.assert_allclose(jac0[:, 0], [0.5 * np.cos(0.3), 0.5 * np.sin(0.3), 0.0], atol=1e-12)


def test_float32_jax_batches_keep_their_dtype_and_shape() -> None:
    q = jnp.asarray(random_q(TDCR3, np.random.default_rng(0), 24).reshape(2, 3, 4, 9),
                    jnp.float32)
    p, r = tip_pose(TDCR3, q)
    assert p.dtype == jnp.float32 and p.shape == (2, 3, 4, 3) and r.shape == (2, 3, 4, 3, 3)
    points = backbone_points(TDCR3, q)
    assert points.dtype == jnp.float32 and points.shape == (2, 3, 4, 30, 3)
    p64, _ = tip_pose(TDCR3, np.asarray(q, dtype=np.float64))  # numpy: float64 numpy
    assert type(p64) is np.ndarray and p64.dtype == np.float64
    np.testing.assert_allclose(p, p64, atol=1e-5)


def test_wrong_q_length_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="9 entries"):
        tip_pose(TDCR3, np.zeros(8))


# ------------------------------------------------------------------ property tests

angles = st.floats(0.0, np.pi, allow_nan=False)
azimuths = st.floats(-np.pi, np.pi, allow_nan=False)


@pytest.mark.usefixtures("float64")  # the JAX q ↔ z round trip at 1e-12
@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(angles, azimuths), min_size=3, max_size=3))
def test_bending_vector_round_trip(segments: list[tuple[float, float]]) -> None:
    q = np.array([v for theta, phi in segments for v in (theta, phi, 1.0)])
    back = np.asarray(z_to_q(TDCR3, q_to_z(TDCR3, q)))
    # Same robot shape (tip pose) even where φ is undefined (θ = 0).
    np.testing.assert_allclose(tip_pose(TDCR3, back)[0], tip_pose(TDCR3, q)[0], atol=1e-12)
    np.testing.assert_allclose(back[0::3], q[0::3], atol=1e-12)


twists = st.lists(st.floats(-2.0, 2.0, allow_nan=False), min_size=6, max_size=6)


@pytest.mark.usefixtures("float64")  # the JAX SE(3) log ∘ exp round trip at 1e-9
@settings(max_examples=100, deadline=None)
@given(twists)
def test_se3_log_exp_round_trip(xi: list[float]) -> None:
    xi = np.array(xi)
    if np.linalg.norm(xi[3:]) >= np.pi - 1e-3:  # log returns the principal branch ‖ω‖ ≤ π
        xi[3:] *= (np.pi - 0.1) / np.linalg.norm(xi[3:])
    entries = tuple(jnp.asarray(v) for v in xi)
    back = np.array([float(v) for v in se3_log(JAX, se3_exp(JAX, entries))])
    np.testing.assert_allclose(back, xi, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(angles, azimuths), min_size=3, max_size=3))
def test_pose_error_is_zero_at_target_and_symmetric(segments: list[tuple[float, float]]) -> None:
    q = np.array([v for theta, phi in segments for v in (theta, phi, 1.0)])
    p, r = tip_pose(TDCR3, q)
    assert float(pose_error(p, r, p, r)) < 1e-7
    p2, r2 = tip_pose(TDCR3, q[::-1].copy() % np.pi)
    np.testing.assert_allclose(pose_error(p, r, p2, r2), pose_error(p2, r2, p, r), atol=1e-9)


def test_numpy_q_z_pair_matches_jax_and_round_trips():
    from cr_nlp.model import q_to_z_numpy, z_to_q_numpy

    robot = TDCR4
    rng = np.random.default_rng(3)
    lo, hi = robot.q_bounds()
    q = rng.uniform(lo, hi, size=(5, 7, robot.dof))
    q[0, 0, 0::3] = 0.0                          # straight segments: φ is reported as 0
    q[0, 0, 1::3] = 0.0
    z = q_to_z_numpy(q)
    assert z.shape == q.shape and z.dtype == np.float64
    np.testing.assert_allclose(z, np.asarray(q_to_z(robot, q)), atol=1e-6)
    back = z_to_q_numpy(z)
    np.testing.assert_allclose(np.asarray(z_to_q(robot, z)), back, atol=1e-6)
    # φ is defined modulo 2π: compare the bending vectors of the round trip, and θ, L.
    np.testing.assert_allclose(q_to_z_numpy(back), z, atol=1e-12)
    np.testing.assert_allclose(back[..., 0::3], q[..., 0::3], atol=1e-12)
    np.testing.assert_allclose(back[..., 2::3], q[..., 2::3], atol=1e-12)
    assert np.all(back[0, 0, 1::3] == 0.0)
    one = q[1, 1]
    np.testing.assert_allclose(q_to_z_numpy(one), z[1, 1])    # a single (3n,) row
    assert q_to_z_numpy(one) is not one and np.all(one == q[1, 1])  # input untouched


def test_tendon_lengths_with_the_offsets_as_data_after_a_float64_program() -> None:
    """A program that takes the robot's numbers as data (``Robot.program_data``) traces
    the tendon lengths with traced offsets; one traced under ``jax.enable_x64`` (as the
    float64 stages do) must leave the next float32 trace working and exact."""
    from cr_nlp.model.kinematics import q_to_z_numpy, tendon_lengths_z

    template, numbers = TDCR3.program_data()
    q = random_q(TDCR3, np.random.default_rng(5), 8)
    z = q_to_z_numpy(q)

    def lengths(data: jax.Array, z: jax.Array) -> jax.Array:
        return tendon_lengths_z(template.filled(data), z)

    with jax.enable_x64(True):
        np.testing.assert_allclose(jax.jit(lengths)(numbers, z), tendon_lengths(TDCR3, q),
                                   atol=1e-12)
    single = jax.jit(lengths)(numbers.astype(np.float32), z.astype(np.float32))
    np.testing.assert_allclose(single, tendon_lengths(TDCR3, q), atol=1e-5)
