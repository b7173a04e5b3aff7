"""The closed-form kinematic derivatives (model/derivatives.py) against JAX's forward-mode
autodiff of the model and against CasADi's symbolic derivatives, in float64, including
θ = 0 exactly and θ = θmax."""

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp.model import (
    CasadiModel,
    Robot,
    backbone_points_z,
    pose_error_vector,
    q_to_z_numpy,
    tip_pose_z,
)
from cr_nlp.model._ops import CASADI, JAX, NUMPY
from cr_nlp.model.derivatives import (
    backbone_jacobian_z,
    pose_error_jacobian,
    pose_residual,
    segment_transform_derivatives,
    tip_jacobian_z,
)
from cr_nlp.model.kinematics import model_segment_transform
from cr_nlp.model.lie import BEND_SERIES_BELOW, bend_coefficients

from ..conftest import MODELS

TDCR3 = Robot.from_file(MODELS / "robots" / "tdcr3.json")
TDCR4 = Robot.from_file(MODELS / "robots" / "tdcr4_ext.json")
ROBOTS = [TDCR3, TDCR4]
# The 4-segment jacfwd references take a minute to compile on 2 cores: slow-marked.
ROBOTS_SLOW4 = [TDCR3, pytest.param(TDCR4, marks=pytest.mark.slow)]
# Every check here compares float64 derivatives at 1e-9 or tighter: JAX's x64 on for each.
pytestmark = pytest.mark.usefixtures("float64")


def configurations(robot: Robot, count: int, seed: int) -> np.ndarray:
    """Bending-vector configurations z, the first rows at the singular and limit bends."""
    lo, hi = robot.q_bounds()
    q = np.random.default_rng(seed).uniform(lo, hi, (count, robot.dof))
    q[0, 0::3] = 0.0  # every segment straight: θ = 0 exactly
    q[1, 0::3] = hi[0::3]  # every segment at θmax
    q[2, 0::3] = [0.0, hi[3], 1e-9, 0.0][: robot.n_segments]  # mixed
    q[3, 0::3] = np.sqrt(BEND_SERIES_BELOW)  # on the series/closed-form switch
    return q_to_z_numpy(q)


def vee_of_rate(d_rot: jax.Array, rot: jax.Array) -> jax.Array:
    """vee(∂R·Rᵀ) for ∂R (…, 3, 3, n) and R (…, 3, 3): (…, 3, n)."""
    spin = jnp.einsum("...ijn,...kj->...ikn", d_rot, rot)
    return jnp.stack([spin[..., 2, 1, :], spin[..., 0, 2, :], spin[..., 1, 0, :]], axis=-2)


# ------------------------------------------------------------------ scalar slopes


def test_bend_coefficients_match_closed_forms_autodiff_and_their_series_at_zero() -> None:
    t = jnp.asarray(
        np.concatenate(
            [
                [0.0, 1e-12, 1e-6],
                np.linspace(0.01, np.pi**2, 400),
                [BEND_SERIES_BELOW * (1 - 1e-12), BEND_SERIES_BELOW * (1 + 1e-12)],
            ]
        )
    )
    bend = bend_coefficients(JAX, t, slopes=True)
    # The slopes against autodiff of the values (through the series/closed-form switch).
    da = jax.vmap(jax.grad(lambda x: bend_coefficients(JAX, x).a))(t)
    db = jax.vmap(jax.grad(lambda x: bend_coefficients(JAX, x).b))(t)
    np.testing.assert_allclose(bend.da, da, rtol=0, atol=1e-12)
    np.testing.assert_allclose(bend.db, db, rtol=0, atol=1e-12)
    # Everything against the textbook forms in θ, away from their cancellation at 0.
    theta = np.sqrt(np.asarray(t)[3:])
    a = np.sin(theta) / theta
    b = (1.0 - np.cos(theta)) / theta**2
    for ours, exact in [(bend.a, a), (bend.b, b), (bend.c, (theta - np.sin(theta)) / theta**3),
                        (bend.da, (np.cos(theta) - a) / (2.0 * theta**2)),
                        (bend.db, (a - 2.0 * b) / (2.0 * theta**2))]:
        np.testing.assert_allclose(np.asarray(ours)[3:], exact, rtol=1e-9)
    at_zero = bend_coefficients(NUMPY, np.float64(0.0), slopes=True)
    assert tuple(float(v) for v in at_zero) == (1.0, 0.5, 1.0 / 6.0, -1.0 / 6.0, -1.0 / 24.0)


# ------------------------------------------------------------------ one segment


def test_segment_derivatives_match_autodiff_at_zero_and_full_bend() -> None:
    rng = np.random.default_rng(1)
    phi = rng.uniform(-np.pi, np.pi, 40)
    theta = np.concatenate([[0.0, 0.0, 1e-9, np.pi, np.pi], rng.uniform(0, np.pi, 35)])
    u = jnp.asarray(
        np.stack([theta * np.cos(phi), theta * np.sin(phi), rng.uniform(0.5, 1.5, 40)], -1)
    )

    def transform(x: jax.Array) -> tuple[jax.Array, jax.Array]:
        rot, pos = model_segment_transform(JAX, x[0], x[1], x[2])
        return jnp.stack(rot).reshape(3, 3), jnp.stack(pos)

    d_rot, d_pos = jax.vmap(jax.jacfwd(transform))(u)
    ours = jax.vmap(lambda x: segment_transform_derivatives(JAX, x[0], x[1], x[2]))(u)
    rot = jnp.stack(ours.rotation, -1).reshape(-1, 3, 3)
    got_rot = jnp.stack([jnp.stack(r, -1) for r in ours.d_rotation], -1).reshape(-1, 3, 3, 2)
    got_pos = jnp.stack([jnp.stack(p, -1) for p in ours.d_position], -1)
    np.testing.assert_allclose(got_rot, d_rot[..., :2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(d_rot[..., 2], 0.0, atol=0)  # ∂R/∂L = 0
    np.testing.assert_allclose(got_pos, d_pos, rtol=0, atol=1e-12)
    rates = jnp.stack([jnp.stack(w, -1) for w in ours.rates], -1)
    np.testing.assert_allclose(rates, vee_of_rate(d_rot[..., :2], rot), rtol=0, atol=1e-12)
    # θ = 0: ∂d/∂ux = L/2·(1, 0, 0) and the rates are the plain axes.
    np.testing.assert_allclose(got_pos[0, :, 0], [u[0, 2] / 2, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(rates[0], [[0.0, -1.0], [1.0, 0.0], [0.0, 0.0]], atol=1e-15)


# ------------------------------------------------------------------ the chain vs jacfwd


@pytest.mark.parametrize("robot", ROBOTS_SLOW4, ids=["tdcr3", "tdcr4_ext"])
def test_tip_and_backbone_jacobians_match_jacfwd(robot: Robot) -> None:
    z = jnp.asarray(configurations(robot, 30, 2))
    position, rotation, jac = jax.jit(jax.vmap(lambda x: tip_jacobian_z(robot, x)))(z)
    p_ref, r_ref = tip_pose_z(robot, z)
    np.testing.assert_allclose(position, p_ref, rtol=0, atol=1e-13)
    np.testing.assert_allclose(rotation, r_ref, rtol=0, atol=1e-13)
    d_p = jax.vmap(jax.jacfwd(lambda x: tip_pose_z(robot, x)[0]))(z)
    d_r = jax.vmap(jax.jacfwd(lambda x: tip_pose_z(robot, x)[1]))(z)
    assert np.all(np.isfinite(jac))
    np.testing.assert_allclose(jac[:, :3], d_p, rtol=0, atol=1e-9)
    np.testing.assert_allclose(jac[:, 3:], vee_of_rate(d_r, r_ref), rtol=0, atol=1e-9)
    # The world rate reproduces ∂R_tip = [ω]×·R_tip entry by entry.
    w = jac[:, 3:]
    zero = jnp.zeros_like(w[:, 0])
    hat = jnp.stack(
        [
            jnp.stack([zero, -w[:, 2], w[:, 1]], 1),
            jnp.stack([w[:, 2], zero, -w[:, 0]], 1),
            jnp.stack([-w[:, 1], w[:, 0], zero], 1),
        ],
        1,
    )  # (B, 3, 3, n)
    np.testing.assert_allclose(jnp.einsum("bijn,bjk->bikn", hat, r_ref), d_r, atol=1e-9)

    points, d_points = jax.jit(jax.vmap(lambda x: backbone_jacobian_z(robot, x)))(z)
    np.testing.assert_allclose(points, backbone_points_z(robot, z), rtol=0, atol=1e-13)
    expected = jax.vmap(jax.jacfwd(lambda x: backbone_points_z(robot, x)))(z)
    assert d_points.shape == (len(z), robot.n_points, 3, robot.dof)
    assert np.all(np.isfinite(d_points))
    np.testing.assert_allclose(d_points, expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("robot", ROBOTS_SLOW4, ids=["tdcr3", "tdcr4_ext"])
def test_pose_error_jacobian_and_residual_match_jacfwd(robot: Robot) -> None:
    z = jnp.asarray(configurations(robot, 30, 3))
    goal_p, goal_r = tip_pose_z(robot, jnp.asarray(configurations(robot, 30, 4)[::-1]))
    goal_r9 = goal_r.reshape(-1, 9)
    # Also targets reached exactly (error 0, the log's series branch).
    goal_p = goal_p.at[5].set(tip_pose_z(robot, z[5])[0])
    goal_r9 = goal_r9.at[5].set(tip_pose_z(robot, z[5])[1].reshape(9))

    def reference(x: jax.Array, p: jax.Array, r: jax.Array) -> jax.Array:
        return pose_error_vector(*tip_pose_z(robot, x), p, r.reshape(3, 3))

    value, jac = jax.vmap(lambda x, p, r: pose_error_jacobian(robot, x, p, r))(z, goal_p, goal_r9)
    np.testing.assert_allclose(value, jax.vmap(reference)(z, goal_p, goal_r9), atol=1e-13)
    expected = jax.vmap(jax.jacfwd(reference))(z, goal_p, goal_r9)
    keep = np.linalg.norm(np.asarray(value)[:, 3:], axis=1) < np.pi - 1e-3  # log at π: branch
    assert keep.sum() >= 25
    np.testing.assert_allclose(jac[keep], expected[keep], rtol=0, atol=1e-9)
    # pose_residual differentiates through the same Jacobian (custom JVP), under jit.
    through = jax.jit(jax.vmap(jax.jacfwd(lambda x, p, r: pose_residual(robot, x, (p, r)))))
    np.testing.assert_allclose(through(z, goal_p, goal_r9), jac, rtol=0, atol=1e-13)


# ------------------------------------------------------------------ against CasADi


@pytest.mark.parametrize("robot", ROBOTS, ids=lambda r: r.name)
def test_jacobians_match_casadi_symbolic_derivatives(robot: Robot) -> None:
    z = configurations(robot, 12, 5)
    model = CasadiModel(robot)
    zs = model.z
    tip_p, tip_r = model.functions_z["tip"](zs)
    points = model.functions_z["backbone"](zs)
    fn = ca.Function(
        "d",
        [zs],
        [
            ca.jacobian(tip_p, zs),
            ca.jacobian(ca.vec(tip_r.T), zs),
            ca.jacobian(ca.vec(points.T), zs),
        ],
    )
    _, rotation, jac = jax.vmap(lambda x: tip_jacobian_z(robot, x))(jnp.asarray(z))
    _, d_points = jax.vmap(lambda x: backbone_jacobian_z(robot, x))(jnp.asarray(z))
    for i in range(len(z)):
        d_p, d_r, d_b = (np.asarray(x) for x in fn(z[i]))
        np.testing.assert_allclose(jac[i, :3], d_p, rtol=0, atol=1e-9)
        rates = vee_of_rate(jnp.asarray(d_r.reshape(3, 3, -1)), rotation[i])
        np.testing.assert_allclose(jac[i, 3:], rates, rtol=0, atol=1e-9)
        np.testing.assert_allclose(
            d_points[i], d_b.reshape(robot.n_points, 3, -1), rtol=0, atol=1e-9
        )


def test_the_same_formulas_run_on_numpy_and_casadi() -> None:
    """One source: the segment derivatives evaluated by NumPy and by CasADi agree."""
    u = np.array([0.7, -0.4, 1.1])
    sym = ca.SX.sym("u", 3)
    ours = segment_transform_derivatives(NUMPY, *u)
    on_casadi = segment_transform_derivatives(CASADI, sym[0], sym[1], sym[2])
    fn = ca.Function("seg", [sym], [ca.vertcat(*on_casadi.d_rotation[0], *on_casadi.rates[1])])
    np.testing.assert_allclose(
        np.asarray(fn(u)).ravel(),
        np.array([*ours.d_rotation[0], *ours.rates[1]], dtype=float),
        rtol=0,
        atol=1e-15,
    )


def test_penalty_clearances_differentiate_through_the_closed_form_centres() -> None:
    """world._penalty's custom JVPs (centre rates from ``backbone_jacobian_z``) against
    plain autodiff of the same values through the model's centres."""
    from cr_nlp.world import load_scene, scene_arrays
    from cr_nlp.world._penalty import (
        _sphere_values,
        _values,
        body_clearances_z,
        sphere_clearances_z,
    )
    from cr_nlp.world.clearance import _centres

    arrays = scene_arrays(load_scene(MODELS / "scenes" / "lattice.json"))
    z = jnp.asarray(configurations(TDCR3, 6, 7))

    def plain_body(x: jax.Array) -> jax.Array:
        return _values(TDCR3, arrays, _centres(TDCR3, x, False))

    def plain_sphere(x: jax.Array) -> jax.Array:
        return _sphere_values(TDCR3, arrays, _centres(TDCR3, x, False))[0]

    for ours, plain in ((body_clearances_z, plain_body), (sphere_clearances_z, plain_sphere)):
        got = jax.jit(jax.vmap(jax.jacfwd(lambda x, f=ours: f(TDCR3, arrays, x))))(z)
        expected = jax.jit(jax.vmap(jax.jacfwd(plain)))(z)
        assert np.all(np.isfinite(got))
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)


def test_trajectory_residual_jacobians_use_the_closed_forms_correctly() -> None:
    """The chain LMs' custom JVPs (``model.derivatives.tip_position_z``,
    ``world._clearance_groups.clearance_groups``) against plain autodiff of the same values."""
    from cr_nlp.model.derivatives import tip_position_z
    from cr_nlp.model.kinematics import tip_pose_z
    from cr_nlp.world import load_scene, scene_arrays
    from cr_nlp.world._clearance_groups import clearance_group_values, clearance_groups

    arrays = scene_arrays(load_scene(MODELS / "scenes" / "lattice.json"))
    z = jnp.asarray(configurations(TDCR3, 10, 8))
    margin = 1.5  # every group feels it: no zero rows
    pairs = (
        (lambda x: tip_position_z(TDCR3, x), lambda x: tip_pose_z(TDCR3, x)[0]),
        (
            lambda x: clearance_groups(TDCR3, margin, arrays, x),
            lambda x: clearance_group_values(TDCR3, margin, arrays, x),
        ),
    )
    # Clearances: random rows only. A straight robot sits on the lattice's symmetry plane,
    # where two obstacle spheres tie for nearest and the two ways pick different ones.
    for (ours, plain), rows in zip(pairs, (z, z[4:]), strict=True):
        got = jax.jit(jax.vmap(jax.jacfwd(ours)))(rows)
        expected = jax.jit(jax.vmap(jax.jacfwd(plain)))(rows)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)


def test_se3_left_jacobian_inverse_matches_autodiff_of_the_log() -> None:
    """∂/∂δ log(exp(δ)·exp(ξ)) at δ = 0, by jacfwd through the model's exp and log, for
    rotation angles across the series switches (θ² = 0.1, 1) up to near π."""
    from cr_nlp.model.lie import se3_exp, se3_left_jacobian_inverse, se3_log, transform_compose

    def moved_log(delta: jax.Array, xi: jax.Array) -> jax.Array:
        twist = se3_exp(JAX, tuple(xi[i] for i in range(6)))
        nudge = se3_exp(JAX, tuple(delta[i] for i in range(6)))
        return jnp.stack(se3_log(JAX, transform_compose(nudge, twist)))

    rng = np.random.default_rng(9)
    angles = [0.0, 1e-7, 0.2, 0.316, 0.317, 0.9, 0.999, 1.001, 2.0, 3.0, 3.13]
    axes = rng.normal(size=(len(angles), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    xi = jnp.asarray(
        np.concatenate(
            [rng.normal(size=(len(angles), 3)), axes * np.array(angles)[:, None]], axis=1
        )
    )
    expected = jax.vmap(jax.jacfwd(moved_log), in_axes=(None, 0))(jnp.zeros(6), xi)
    got = jax.vmap(se3_left_jacobian_inverse)(xi)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-10)
