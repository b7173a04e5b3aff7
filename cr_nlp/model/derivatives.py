"""Closed-form derivatives of the PCC kinematics with respect to the bending-vector
configuration ``z = [ux1, uy1, L1, …]`` (radians, radians, metres): the segment transform,
the tip pose, the backbone points and the pose error. Written once on entries (see
``_ops``), so JAX, NumPy and CasADi evaluate the same formulas; the IK, trajectory and
path-following solvers take their Jacobians from here.

The segment transform (``kinematics.model_segment_transform``) is
``R = I + A(t)·K + B(t)·K²``, ``d = L·(B·ux, B·uy, A)`` with t = ux² + uy² = θ²,
A = sin θ/θ, B = (1 − cos θ)/θ². Its derivatives need A′(t) and B′(t), written here with
Taylor branches below ``SLOPE_SERIES_BELOW`` so that values and derivatives are finite
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

from ._ops import JAX, Ops, safe_where
from .kinematics import model_base, model_pose_error, model_segment_frames
from .lie import (
    Rot,
    Transform,
    Vec,
    rot_apply,
    rot_transpose,
    se3_left_jacobian_inverse,
    sinc_of_square,
    transform_compose,
    vec_add,
    vec_cross,
    vec_sub,
    versine_of_square,
)
from .robot import Robot

SLOPE_SERIES_BELOW = 0.1
"""Below this t = θ² (rad²) the slopes A′, B′ and the coefficient C use their Taylor
series (truncation error < 1e-17 there); above it the closed forms lose at most
~3e-14 relative to cancellation in float64."""


# ---------------------------------------------------------------- smooth scalars of t = θ²


def sinc_of_square_slope(ops: Ops, t: Any) -> Any:
    """A′(t) = d/dt (sin θ/θ) = (cos θ − A)/(2t), t = θ² (rad²); −1/6 at t = 0."""

    def series(t: Any) -> Any:  # Σₖ k(−1)ᵏ tᵏ⁻¹/(2k+1)!, k = 1…6
        return -1.0 / 6.0 + t * (
            2.0 / 120.0
            + t
            * (
                -3.0 / 5040.0
                + t * (4.0 / 362880.0 + t * (-5.0 / 39916800.0 + t * (6.0 / 6227020800.0)))
            )
        )

    def exact(t: Any) -> Any:
        theta = ops.sqrt(t)
        return (ops.cos(theta) - ops.sin(theta) / theta) / (2.0 * t)

    return safe_where(ops, t < SLOPE_SERIES_BELOW, series, exact, t, 1.0)


def versine_of_square_slope(ops: Ops, t: Any) -> Any:
    """B′(t) = d/dt ((1 − cos θ)/θ²) = (A − 2B)/(2t), t = θ² (rad²); −1/24 at t = 0."""

    def series(t: Any) -> Any:  # Σₖ k(−1)ᵏ tᵏ⁻¹/(2k+2)!, k = 1…6
        return -1.0 / 24.0 + t * (
            2.0 / 720.0
            + t
            * (
                -3.0 / 40320.0
                + t * (4.0 / 3628800.0 + t * (-5.0 / 479001600.0 + t * (6.0 / 87178291200.0)))
            )
        )

    def exact(t: Any) -> Any:
        return (sinc_of_square(ops, t) - 2.0 * versine_of_square(ops, t)) / (2.0 * t)

    return safe_where(ops, t < SLOPE_SERIES_BELOW, series, exact, t, 1.0)


def sine_deficit_of_square(ops: Ops, t: Any) -> Any:
    """C(t) = (θ − sin θ)/θ³ = (1 − A)/t, t = θ² (rad²); 1/6 at t = 0."""

    def series(t: Any) -> Any:  # Σₖ (−t)ᵏ/(2k+3)!, k = 0…5
        return 1.0 / 6.0 + t * (
            -1.0 / 120.0
            + t
            * (
                1.0 / 5040.0
                + t * (-1.0 / 362880.0 + t * (1.0 / 39916800.0 + t * (-1.0 / 6227020800.0)))
            )
        )

    def exact(t: Any) -> Any:
        return (1.0 - sinc_of_square(ops, t)) / t

    return safe_where(ops, t < SLOPE_SERIES_BELOW, series, exact, t, 1.0)


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
    a, b = sinc_of_square(ops, t), versine_of_square(ops, t)
    da, db = sinc_of_square_slope(ops, t), versine_of_square_slope(ops, t)
    c = sine_deficit_of_square(ops, t)
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


def _scale(s: Any, a: Vec) -> Vec:
    return (s * a[0], s * a[1], s * a[2])


# ---------------------------------------------------------------- the chain


class KinematicsDerivatives(NamedTuple):
    """The kinematics of one configuration with derivatives by every entry of z."""

    frames: list[Transform]
    """World frames at the base (index 0) and at the end of every segment."""
    d_position: list[Vec]
    """Per variable k of z: ∂p_tip/∂z_k, world frame (m per rad, or per m for a length)."""
    rates: list[Vec | None]
    """Per variable k: the world rate ω_k with ∂R_tip/∂z_k = [ω_k]×·R_tip (None for a
    length, whose rate is zero)."""
    points: list[Vec] | None
    """Per segment: its backbone points (entries along the trailing point axis)."""
    d_points: list[list[Vec | None]] | None
    """[segment][k]: ∂point/∂z_k, world frame; None for the variables of later segments."""


def model_kinematics_derivatives(
    ops: Ops, robot: Robot, z: list[Any], points: bool = True
) -> KinematicsDerivatives:
    """Tip pose, backbone points (with ``points``) and their closed-form derivatives with
    respect to every entry of z (``[ux1, uy1, L1, …]``), on the backend ``ops``."""
    n = robot.n_segments
    frames = [model_base(robot)]
    rates: list[Vec | None] = []
    moves: list[Vec] = []  # R_{m−1}·∂d/∂z_k, world
    ends: list[Vec] = []  # p_m of the segment owning variable k
    for m in range(n):
        ux, uy, length = z[3 * m], z[3 * m + 1], z[3 * m + 2]
        seg = segment_transform_derivatives(ops, ux, uy, length)
        base_rot = frames[-1][0]
        frame = ops.materialize(transform_compose(frames[-1], (seg.rotation, seg.position)))
        frames.append(frame)
        rates += [ops.materialize(rot_apply(base_rot, w)) for w in seg.rates] + [None]
        moves += [ops.materialize(rot_apply(base_rot, d)) for d in seg.d_position]
        ends += [frame[1]] * 3
    tip = frames[-1][1]
    d_position = [
        moves[k] if w is None else vec_add(vec_cross(w, vec_sub(tip, ends[k])), moves[k])
        for k, w in enumerate(rates)
    ]
    if not points:
        return KinematicsDerivatives(frames, d_position, rates, None, None)

    count = robot.points_per_segment
    s = ops.fractions(np.arange(1, count + 1) / count)
    seg_points, seg_d_points = [], []
    for m in range(n):
        ux, uy, length = (ops.along(v) for v in z[3 * m : 3 * m + 3])
        local = segment_transform_derivatives(ops, ux * s, uy * s, length * s)
        # Computed once per point: without the barrier XLA recomputed the slopes A′, B′
        # inside each of the 9 entries of every point's Jacobian (3.0 → 0.9 ms for 376
        # tdcr3 configurations, float32, CPU).
        local_position, local_d_position = ops.materialize((local.position, local.d_position))
        rot, pos = frames[m]
        rot_a = tuple(ops.along(v) for v in rot)
        pos_a = tuple(ops.along(v) for v in pos)
        x = vec_add(pos_a, rot_apply(rot_a, local_position))
        seg_points.append(x)
        d_x: list[Vec | None] = []
        for k in range(robot.dof):
            owner = k // 3
            if owner < m:  # an earlier segment's variable turns this segment rigidly
                moved = tuple(ops.along(v) for v in moves[k])
                if rates[k] is None:
                    d_x.append(moved)
                else:
                    w = tuple(ops.along(v) for v in rates[k])
                    end = tuple(ops.along(v) for v in ends[k])
                    d_x.append(vec_add(vec_cross(w, vec_sub(x, end)), moved))
            elif owner == m:  # the point's own arc: chain factor s of (s·ux, s·uy, s·L)
                d_x.append(_scale(s, rot_apply(rot_a, local_d_position[k - 3 * m])))
            else:
                d_x.append(None)
        seg_d_points.append(d_x)
    return KinematicsDerivatives(frames, d_position, rates, seg_points, seg_d_points)


# ---------------------------------------------------------------- JAX front end (arrays)


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


def kinematics_jacobians_z(robot: Robot, z: jax.Array, points: bool = True) -> KinematicsJacobians:
    """Tip pose, backbone points (with ``points``) and their closed-form Jacobians with
    respect to bending-vector configurations z (…, 3n) (rad, rad, m), in z's dtype."""
    z = jnp.asarray(z)
    shape, dtype = z.shape[:-1], z.dtype
    d = model_kinematics_derivatives(
        JAX, robot, [z[..., i] for i in range(robot.dof)], points=points
    )
    rot, pos = d.frames[-1]
    zero = (0.0, 0.0, 0.0)
    columns = [
        _stack(tuple(dp) + tuple(zero if w is None else w), dtype, shape)
        for dp, w in zip(d.d_position, d.rates, strict=True)
    ]
    rotation = _stack(rot, dtype, shape).reshape(shape + (3, 3))
    out = KinematicsJacobians(
        _stack(pos, dtype, shape), rotation, jnp.stack(columns, -1), None, None
    )
    if not points:
        return out
    k = robot.points_per_segment
    values, jac = [], []
    for m in range(robot.n_segments):
        values.append(_stack(d.points[m], dtype, shape + (k,)))
        cols = [
            jnp.zeros(shape + (k, 3), dtype) if dx is None else _stack(dx, dtype, shape + (k,))
            for dx in d.d_points[m]
        ]
        jac.append(jnp.stack(cols, axis=-1))
    return out._replace(
        points=jnp.concatenate(values, axis=-2), d_points=jnp.concatenate(jac, axis=-3)
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
    d = model_kinematics_derivatives(JAX, robot, [z[i] for i in range(robot.dof)], points=False)
    rot, pos = d.frames[-1]
    goal = (
        tuple(target_rotation[i] for i in range(9)),
        tuple(target_position[i] for i in range(3)),
    )
    value = jnp.stack(jnp.broadcast_arrays(*model_pose_error(JAX, (rot, pos), goal)))
    value = value.astype(dtype)
    rot_t = rot_transpose(rot)
    zero = (0.0, 0.0, 0.0)
    body = [
        tuple(rot_apply(rot_t, dp)) + tuple(rot_apply(rot_t, zero if w is None else w))
        for dp, w in zip(d.d_position, d.rates, strict=True)
    ]
    twists = jnp.stack([jnp.stack(jnp.broadcast_arrays(*col)) for col in body], axis=-1)
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
