"""Closed-form derivatives of the PCC kinematics with respect to the bending-vector
configuration ``z = [ux1, uy1, L1, …]`` (radians, radians, metres): the segment transform,
the tip pose, the backbone points and the pose error. Written once on entries (see
``_ops``), so JAX, NumPy and CasADi evaluate the same formulas; the IK, trajectory and
path-following solvers take their Jacobians from here.

The segment transform (``kinematics.model_segment_transform``) is
``R = I + A(t)·K + B(t)·K²``, ``d = L·(B·ux, B·uy, A)`` with t = ux² + uy² = θ²,
A = sin θ/θ, B = (1 − cos θ)/θ². Its derivatives need A′(t) and B′(t), written here with
Taylor branches (``lie.bend_coefficients``) so that values and derivatives are finite
and exact at θ = 0. R is the rotation exp([w]×) about w = (−uy, ux, 0), so its spatial
rate ∂R·Rᵀ = [J_l(w)·∂w]× with the SO(3) left Jacobian J_l = I + B·K + C·K²,
C = (θ − sin θ)/θ³ = (1 − A)/t.

Along the chain every variable of segment m turns everything beyond segment m rigidly:
a point x beyond it moves by ``∂x = ω × (x − p_m) + R_{m−1}·∂d`` (ω the world rate of the
variable, p_m the end of segment m), and the tip rotation by ``∂R_tip = [ω]×·R_tip``.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._ops import JAX, Ops
from .kinematics import model_base, model_pose_error, model_segment_frames
from .lie import (
    Rot,
    Transform,
    Vec,
    bend_coefficients,
    rot_apply,
    rot_transpose,
    se3_left_jacobian_inverse,
    transform_compose,
    vec_add,
    vec_cross,
    vec_sub,
)
from .robot import Robot

# ---------------------------------------------------------------- one segment


class SegmentDerivatives(NamedTuple):
    """A segment transform and its partial derivatives by (ux, uy, L)."""

    rotation: Rot
    position: Vec
    d_rotation: tuple[Rot, Rot]
    """∂R/∂ux, ∂R/∂uy (∂R/∂L = 0), row-major entries, per radian."""
    d_position: tuple[Vec, Vec, Vec]
    """∂d/∂ux, ∂d/∂uy (metres per radian), ∂d/∂L (dimensionless)."""
    rates: tuple[Vec, Vec]
    """Spatial rotation rates vee(∂R·Rᵀ) of ux and uy in the segment's base frame (the
    rate of L is zero), dimensionless (radians per radian)."""


def segment_transform_derivatives(ops: Ops, ux: Any, uy: Any, length: Any) -> SegmentDerivatives:
    """The segment transform (frame i−1 → i) of bending vector (ux, uy) rad and length m,
    with its closed-form derivatives; finite and exact at θ = 0."""
    t = ux * ux + uy * uy
    a, b, c, da, db = bend_coefficients(ops, t, slopes=True)
    rotation = (
        1.0 - b * ux * ux,
        -b * ux * uy,
        a * ux,
        -b * ux * uy,
        1.0 - b * uy * uy,
        a * uy,
        -a * ux,
        -a * uy,
        1.0 - b * t,
    )
    position = (length * b * ux, length * b * uy, length * a)
    # ∂A/∂ux = 2ux·A′ etc.
    a_x, a_y, b_x, b_y = 2.0 * ux * da, 2.0 * uy * da, 2.0 * ux * db, 2.0 * uy * db
    d_rot_x = (
        -b_x * ux * ux - 2.0 * b * ux,
        -b_x * ux * uy - b * uy,
        a_x * ux + a,
        -b_x * ux * uy - b * uy,
        -b_x * uy * uy,
        a_x * uy,
        -a_x * ux - a,
        -a_x * uy,
        -b_x * t - 2.0 * b * ux,
    )
    d_rot_y = (
        -b_y * ux * ux,
        -b_y * ux * uy - b * ux,
        a_y * ux,
        -b_y * ux * uy - b * ux,
        -b_y * uy * uy - 2.0 * b * uy,
        a_y * uy + a,
        -a_y * ux,
        -a_y * uy - a,
        -b_y * t - 2.0 * b * uy,
    )
    d_pos_x = (length * (b_x * ux + b), length * b_x * uy, length * a_x)
    d_pos_y = (length * b_y * ux, length * (b_y * uy + b), length * a_y)
    d_pos_l = (b * ux, b * uy, a)
    # Columns of J_l(w) for ∂w/∂ux = (0, 1, 0) and ∂w/∂uy = (−1, 0, 0).
    rate_x = (-c * ux * uy, 1.0 - c * uy * uy, -b * uy)
    rate_y = (c * ux * ux - 1.0, c * ux * uy, b * ux)
    return SegmentDerivatives(
        rotation, position, (d_rot_x, d_rot_y), (d_pos_x, d_pos_y, d_pos_l), (rate_x, rate_y)
    )


# ---------------------------------------------------------------- the chain (JAX arrays)


def _stack(entries: Any, dtype: Any, shape: tuple[int, ...]) -> jax.Array:
    return jnp.stack([jnp.broadcast_to(jnp.asarray(e, dtype), shape) for e in entries], -1)


class KinematicsJacobians(NamedTuple):
    """Arrays of ``kinematics_jacobians_z`` (leading batch shape …)."""

    position: jax.Array
    """(…, 3) tip position, m."""
    rotation: jax.Array
    """(…, 3, 3) tip rotation."""
    jacobian: jax.Array
    """(…, 6, 3n) world-frame geometric Jacobian: rows 0–2 ∂p_tip/∂z, rows 3–5 the rates
    ω with ∂R_tip/∂z_k = [ω_k]×·R_tip."""
    points: jax.Array | None
    """(…, n·k, 3) backbone points, m (``backbone_points_z`` order), or None."""
    d_points: jax.Array | None
    """(…, n·k, 3, 3n) their Jacobian, or None."""


def _by_variable(per_segment: list[Any], n: int) -> jax.Array:
    """Entries (…, n) of each segment's 3 variables (None: zero) → one entry (…, 3n) in
    z's order."""
    like = next(e for e in per_segment if e is not None)
    zero = jnp.zeros_like(like)
    stacked = jnp.stack([zero if e is None else e for e in per_segment], axis=-1)
    return stacked.reshape(stacked.shape[:-2] + (3 * n,))


def kinematics_jacobians_z(robot: Robot, z: jax.Array, points: bool = True) -> KinematicsJacobians:
    """Tip pose, backbone points (with ``points``) and their closed-form Jacobians with
    respect to bending-vector configurations z (…, 3n) (rad, rad, m), in z's dtype.

    Every variable of segment m turns everything beyond segment m rigidly: a point x
    beyond it moves by ω × (x − p_m) + R_{m−1}·∂d (module docstring). The segments, the
    points along them and the variables live on trailing array axes of each entry (one
    entry per coordinate): the compiled program barely grows with the number of segments
    and points, and stays elementwise (no tiny matrix products)."""
    z = jnp.asarray(z)
    shape, dtype, n = z.shape[:-1], z.dtype, robot.n_segments
    ux, uy, length = z[..., 0::3], z[..., 1::3], z[..., 2::3]
    seg = JAX.materialize(segment_transform_derivatives(JAX, ux, uy, length))  # (…, n)
    frames = [model_base(robot)]
    for m in range(n):  # the chain: n small products of entries
        local = jax.tree.map(lambda e, m=m: e[..., m], (seg.rotation, seg.position))
        frames.append(JAX.materialize(transform_compose(frames[-1], local)))
    tip_rot, tip = frames[-1]
    # One entry per segment → one entry with a trailing segment axis (…, n).
    base_rot = tuple(JAX.stack([f[0][i] for f in frames[:-1]]) for i in range(9))
    base_pos = tuple(JAX.stack([f[1][i] for f in frames[:-1]]) for i in range(3))
    end_pos = tuple(JAX.stack([f[1][i] for f in frames[1:]]) for i in range(3))
    rates = [rot_apply(base_rot, w) for w in seg.rates]
    moves = [rot_apply(base_rot, d) for d in seg.d_position]
    # Per variable of z (…, 3n): world rate ω (zero for a length), move, segment end.
    omega = tuple(_by_variable([rates[0][c], rates[1][c], None], n) for c in range(3))
    move = tuple(_by_variable([moves[v][c] for v in range(3)], n) for c in range(3))
    end = tuple(jnp.repeat(jnp.broadcast_to(e, shape + (n,)), 3, axis=-1) for e in end_pos)
    tip_v = tuple(e[..., None] for e in tip)
    d_tip = vec_add(vec_cross(omega, vec_sub(tip_v, end)), move)
    jacobian = jnp.stack(jnp.broadcast_arrays(*d_tip, *omega), axis=-2).astype(dtype)
    out = KinematicsJacobians(
        _stack(tip, dtype, shape), _stack(tip_rot, dtype, shape).reshape(shape + (3, 3)),
        jacobian, None, None,
    )
    if not points:
        return out

    k = robot.points_per_segment
    s = jnp.asarray(np.arange(1, k + 1) / k, dtype)
    local = segment_transform_derivatives(
        JAX, ux[..., None] * s, uy[..., None] * s, length[..., None] * s)  # (…, n, k)
    # Computed once per point: without the barrier XLA recomputed the slopes A′, B′
    # inside each entry of every point's Jacobian (3.0 → 0.9 ms for 376 tdcr3
    # configurations, float32, CPU).
    local_position, local_d_position = JAX.materialize((local.position, local.d_position))
    rot_p = tuple(e[..., None] for e in base_rot)  # (…, n, 1)
    x = vec_add(tuple(e[..., None] for e in base_pos), rot_apply(rot_p, local_position))
    # Own arc: the chain factor s of (s·ux, s·uy, s·L), tiled over every segment's
    # variables and kept where the variable is the point's own segment's.
    own_v = [rot_apply(rot_p, d) for d in local_d_position]
    own = tuple(jnp.tile(jnp.stack([s * own_v[v][c] for v in range(3)], -1), n)
                for c in range(3))
    # Earlier segments' variables turn the point rigidly.
    x_v = tuple(e[..., None] for e in x)  # (…, n, k, 1)

    def per_variable(e: jax.Array) -> jax.Array:
        return e[..., None, None, :]  # (…, 1, 1, 3n)

    rigid = vec_add(
        vec_cross(tuple(map(per_variable, omega)), vec_sub(x_v, tuple(map(per_variable, end)))),
        tuple(map(per_variable, move)),
    )
    owner = np.arange(3 * n) // 3
    earlier = (owner[None, :] < np.arange(n)[:, None])[:, None, :]  # (n, 1, 3n)
    mine = (owner[None, :] == np.arange(n)[:, None])[:, None, :]
    d_points = [jnp.where(earlier, r, jnp.where(mine, o, 0.0))
                for r, o in zip(rigid, own, strict=True)]
    return out._replace(
        points=_stack(x, dtype, shape + (n, k)).reshape(shape + (n * k, 3)),
        d_points=jnp.stack(jnp.broadcast_arrays(*d_points), axis=-2)
        .astype(dtype).reshape(shape + (n * k, 3, 3 * n)),
    )


def tip_jacobian_z(robot: Robot, z: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Tip position (…, 3) m, rotation (…, 3, 3) and the world-frame geometric Jacobian
    (…, 6, 3n) of bending-vector configurations z (…, 3n): rows 0–2 ∂p_tip/∂z (m per rad
    or per m), rows 3–5 the rates ω with ∂R_tip/∂z_k = [ω_k]×·R_tip. Closed form."""
    out = kinematics_jacobians_z(robot, z, points=False)
    return out.position, out.rotation, out.jacobian


def backbone_jacobian_z(robot: Robot, z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Backbone points (…, n·k, 3) m (``kinematics.backbone_points_z`` order) and their
    Jacobian (…, n·k, 3, 3n) with respect to the bending-vector z (…, 3n). Closed form."""
    out = kinematics_jacobians_z(robot, z)
    return out.points, out.d_points


def pose_error_jacobian(
    robot: Robot, z: jax.Array, target_position: jax.Array, target_rotation: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """The pose error 6-vector e = log(T_tip⁻¹·T_target) (m, rad) of ONE configuration z
    (3n,) and its Jacobian (6, 3n) by z, in closed form; the target (position (3,) m,
    rotation (9,) row major) is a constant. With the tip's body twist δ_k =
    (R_tipᵀ ∂p_tip/∂z_k, R_tipᵀ ω_k), T_tip⁻¹·T_target moves by exp(−δ_k^) on the left,
    so ∂e/∂z_k = −J_l⁻¹(e)·δ_k (``lie.se3_left_jacobian_inverse``)."""
    dtype = z.dtype
    kin = kinematics_jacobians_z(robot, z, points=False)
    rot = tuple(kin.rotation[i, j] for i in range(3) for j in range(3))
    pos = tuple(kin.position[i] for i in range(3))
    goal = (
        tuple(target_rotation[i] for i in range(9)),
        tuple(target_position[i] for i in range(3)),
    )
    value = jnp.stack(jnp.broadcast_arrays(*model_pose_error(JAX, (rot, pos), goal)))
    value = value.astype(dtype)
    rot_t = rot_transpose(rot)
    rows = tuple(kin.jacobian[i] for i in range(6))  # (3n,) each
    twists = jnp.stack(rot_apply(rot_t, rows[:3]) + rot_apply(rot_t, rows[3:]))
    return value, -se3_left_jacobian_inverse(value) @ twists.astype(dtype)


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def pose_residual(robot: Robot, z: jax.Array, target: tuple[jax.Array, jax.Array]) -> jax.Array:
    """The pose error 6-vector (m, rad) of one configuration z (3n,) against ``target`` =
    (position (3,) m, rotation (9,) row major), with the closed-form Jacobian of
    ``pose_error_jacobian`` as its derivative (only z is differentiated)."""
    target_position, target_rotation = target
    tip = _tip_entries(robot, z)
    goal = (
        tuple(target_rotation[i] for i in range(9)),
        tuple(target_position[i] for i in range(3)),
    )
    return jnp.stack(jnp.broadcast_arrays(*model_pose_error(JAX, tip, goal))).astype(z.dtype)


def _tip_entries(robot: Robot, z: jax.Array) -> Transform:
    return model_segment_frames(JAX, robot, [z[i] for i in range(robot.dof)])[-1]


@pose_residual.defjvp
def _pose_residual_jvp(robot: Robot, primals: tuple, tangents: tuple) -> tuple:
    # The Jacobian comes from the primal alone: under the LM's jacfwd over all 3n
    # directions it is evaluated once, and only the product is batched.
    z, (target_position, target_rotation) = primals
    value, jac = pose_error_jacobian(robot, z, target_position, target_rotation)
    return value, jac @ tangents[0]


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def tip_position_z(robot: Robot, z: jax.Array) -> jax.Array:
    """Tip position (3,) m of one configuration z (3n,) (rad, rad, m), with the
    closed-form Jacobian of ``tip_jacobian_z`` as its derivative."""
    return jnp.stack(jnp.broadcast_arrays(*_tip_entries(robot, z)[1])).astype(z.dtype)


@tip_position_z.defjvp
def _tip_position_jvp(robot: Robot, primals: tuple, tangents: tuple) -> tuple:
    # As for ``pose_residual``: the waypoint's own 3 × 3n Jacobian from the primal, so
    # that the LM's jacfwd over all directions evaluates it once.
    (z,), (z_dot,) = primals, tangents
    position, _, jac = tip_jacobian_z(robot, z)
    return position, jac[:3] @ z_dot
