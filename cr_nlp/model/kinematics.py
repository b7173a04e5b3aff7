"""PCC kinematics, tendon lengths and pose error: written once, evaluated by JAX and CasADi.

Conventions (docs/design.md §1): segment i has bending angle θᵢ ∈ [0, θmaxᵢ]
(radians), azimuth φᵢ (radians) and arc length Lᵢ (metres);
``q = [θ1, φ1, L1, …, θn, φn, Ln]``. The segment transform is
``R = Rz(φ)·Ry(θ)·Rz(−φ)``, ``d = (L/θ)·[cos φ (1 − cos θ), sin φ (1 − cos θ), sin θ]``.

Internally the model is written on the singularity-free bending vector
``u = θ·(cos φ, sin φ)``: with t = ‖u‖² = θ²,

    R = I + A(t)·K + B(t)·K²,  K = [[0, 0, ux], [0, 0, uy], [−ux, −uy, 0]],
    d = L·[B(t)·ux, B(t)·uy, A(t)],

where A = sin θ/θ and B = (1 − cos θ)/θ² are analytic in t. Values and
derivatives are finite at θ = 0 in both parameterisations. The optimiser's
variable vector is ``z = [ux1, uy1, L1, …]`` (radians, radians, metres).

The functions prefixed ``model_`` take an ``Ops`` backend and work on entries;
the public functions at the bottom are the JAX (batched, numpy-friendly) and
CasADi front ends of the same code.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np

from ._ops import CASADI, JAX, NUMPY, Ops
from .lie import (
    Transform,
    Vec,
    bend_coefficients,
    rot_from_quat,
    se3_log,
    transform_apply,
    transform_between,
    transform_compose,
)
from .robot import Robot, robot_jit
from .routing import routing_of

# ================================================================ the model, once

def model_q_to_z(ops: Ops, robot: Robot, q: Any) -> list[Any]:
    """(θ, φ, L) per segment → bending vector entries (ux, uy, L) per segment."""
    z = []
    for i in range(robot.n_segments):
        theta, phi, length = (ops.entry(q, 3 * i + k) for k in range(3))
        z += [theta * ops.cos(phi), theta * ops.sin(phi), length]
    return z


def model_segment_transform(ops: Ops, ux: Any, uy: Any, length: Any) -> Transform:
    """Frame i−1 → frame i of one segment with bending vector (ux, uy) rad and length m."""
    t = ux * ux + uy * uy
    a, b, _, _, _ = bend_coefficients(ops, t)
    rot = (
        1.0 - b * ux * ux, -b * ux * uy, a * ux,
        -b * ux * uy, 1.0 - b * uy * uy, a * uy,
        -a * ux, -a * uy, 1.0 - b * t,
    )
    return rot, (length * b * ux, length * b * uy, length * a)


def _segment_point(ops: Ops, ux: Any, uy: Any, length: Any) -> Vec:
    """The translation of ``model_segment_transform`` alone (the same numbers, m)."""
    t = ux * ux + uy * uy
    a, b, _, _, _ = bend_coefficients(ops, t)
    return length * b * ux, length * b * uy, length * a


def model_base(robot: Robot) -> Transform:
    return rot_from_quat(robot.base_wxyz), robot.base_position


def _segment_axis(ops: Ops, z: list[Any]) -> tuple[Any, Any, Any]:
    """(ux, uy, L) of every segment, each one entry with a trailing segment axis: the
    segment formulas run once for all segments (a compiled program that does not grow
    with the number of segments)."""
    return ops.stack(z[0::3]), ops.stack(z[1::3]), ops.stack(z[2::3])


def model_segment_frames(ops: Ops, robot: Robot, z: list[Any]) -> list[Transform]:
    """World frames at the base (index 0) and at the end of every segment."""
    rot, pos = ops.materialize(model_segment_transform(ops, *_segment_axis(ops, z)))
    frames = [model_base(robot)]
    for i in range(robot.n_segments):
        local = (tuple(ops.entry(e, i) for e in rot), tuple(ops.entry(e, i) for e in pos))
        frames.append(ops.materialize(transform_compose(frames[-1], local)))
    return frames


def model_backbone(ops: Ops, robot: Robot, z: list[Any],
                   frames: list[Transform] | None = None) -> Any:
    """Backbone points, ``points_per_segment`` per segment at arc fractions j/k, j = 1…k.

    A point at fraction s of a segment is the segment formula with θ → sθ, L → sL.
    Returns an (…, n·k, 3) array (JAX) or an (n·k × 3) matrix (CasADi), metres.
    """
    frames = model_segment_frames(ops, robot, z) if frames is None else frames
    k = robot.points_per_segment
    s = ops.fractions(np.arange(1, k + 1) / k)
    per_point = tuple(ops.per_point(v, s) for v in _segment_axis(ops, z))
    # numpy computes what it is asked for (JAX drops the unused rotation): positions only.
    local = (_segment_point(ops, *per_point) if ops.name == "numpy"
             else model_segment_transform(ops, *per_point)[1])
    per_segment = []
    for i in range(robot.n_segments):
        rot, pos = frames[i]
        base = (tuple(ops.along(v) for v in rot), tuple(ops.along(v) for v in pos))
        per_segment.append(transform_apply(base, tuple(ops.points_of(e, i) for e in local)))
    return ops.stack_points(per_segment)


def _offsets_xp(robot: Robot) -> Any:
    """numpy where the tendon offsets are numbers (constants of a program), ``jax.numpy``
    where a compiled program takes them as data (``Robot.program_data``: traced)."""
    return jnp if any(isinstance(o, jax.core.Tracer) for o in robot.tendons.offsets) else np


def tendon_length_matrix(robot: Robot, xp: Any = np) -> tuple[Any, np.ndarray]:
    """∂ℓ/∂z, (3n, T): tendon lengths are linear in the bending vector, ℓ = z·M
    (``ℓₜ = Σᵢ Lᵢ − r·(uxᵢ cos αₜᵢ + uyᵢ sin αₜᵢ)`` over the segments i tendon t runs
    through), m per rad for the ux, uy rows and m per m for the L rows; with the (3n, T)
    mask of its entries that are not structurally zero. ``xp``: numpy (float64), or
    ``jax.numpy`` for offsets a compiled program takes as data (``Robot.program_data``).

    ``shared``: m tendons, each summed over all segments (segment i's offset applies
    inside segment i). ``per_segment``: segment k's m tendons end at segment k and sum
    over segments 1…k; order ``[seg1 tendons, seg2 tendons, …]``.
    """
    n, r = robot.n_segments, robot.tendons.radius
    routing = routing_of(robot)
    alpha = routing.angles(robot.tendons.offsets, xp).T            # (n, T)
    through = routing.through.T.astype(float)                      # (n, T)
    rows = xp.stack([-r * xp.cos(alpha) * through, -r * xp.sin(alpha) * through,
                     xp.asarray(through)], axis=1)                 # (n, 3, T)
    return rows.reshape(3 * n, -1), np.repeat(routing.through.T, 3, axis=0)


def model_tendon_lengths(ops: Ops, robot: Robot, z: list[Any]) -> list[Any]:
    """Tendon lengths (metres), ``ℓ = z·M`` with M = ``tendon_length_matrix``, as one sum
    of the entries of ``z`` (a list of 3n entries) per tendon."""
    matrix, used = tendon_length_matrix(robot, _offsets_xp(robot))
    return [sum(matrix[j, t] * z[j] for j in range(len(z)) if used[j, t])
            for t in range(matrix.shape[1])]


def model_pose_error(ops: Ops, tip: Transform, target: Transform) -> tuple[Any, ...]:
    """The 6-vector log(T_tip⁻¹ · T_target): translation part (m), rotation part (rad)."""
    return se3_log(ops, transform_between(tip, target))


# ================================================================ JAX front end

def _rot_array(rot: Any) -> jax.Array:
    flat = jnp.stack(jnp.broadcast_arrays(*rot), axis=-1)
    return flat.reshape(flat.shape[:-1] + (3, 3))


def _vec_array(v: Any) -> jax.Array:
    return jnp.stack(jnp.broadcast_arrays(*v), axis=-1)


def _entries_of_rot(r: Any) -> tuple:
    return tuple(r[..., i, j] for i in range(3) for j in range(3))


def _check_q(robot: Robot, q: jax.Array) -> jax.Array:
    q = jnp.asarray(q)
    if not jnp.issubdtype(q.dtype, jnp.floating):
        q = q.astype(jnp.result_type(float))
    if q.shape[-1:] != (robot.dof,):
        raise ValueError(
            f"q must have {robot.dof} entries on its last axis ([θ, φ, L] × {robot.n_segments} "
            f"segments of {robot.name!r}), got shape {q.shape}"
        )
    return q


def q_to_z(robot: Robot, q: jax.Array) -> jax.Array:
    """(…, 3n) configurations (θ, φ, L) → (…, 3n) bending-vector form (ux, uy, L)."""
    q = _check_q(robot, q)
    return JAX.stack(model_q_to_z(JAX, robot, q))


def z_to_q(robot: Robot, z: jax.Array) -> jax.Array:
    """(…, 3n) bending-vector form → (θ, φ, L); φ is 0 where θ = 0 (undefined there)."""
    z = jnp.asarray(z)
    ux, uy, length = z[..., 0::3], z[..., 1::3], z[..., 2::3]
    theta = jnp.sqrt(ux * ux + uy * uy)
    phi = jnp.where(theta > 0, jnp.arctan2(uy, ux), 0.0)
    return jnp.stack([theta, phi, length], axis=-1).reshape(z.shape)


def q_to_z_numpy(q: Any) -> np.ndarray:
    """``q_to_z`` in float64 numpy (no JAX), for the float64 checks and the CasADi stages:
    (…, 3n) configurations (θ, φ, L) → bending vectors (ux, uy, L) (rad, rad, m)."""
    z = np.array(q, dtype=np.float64)
    theta, phi = z[..., 0::3].copy(), z[..., 1::3]
    z[..., 0::3], z[..., 1::3] = theta * np.cos(phi), theta * np.sin(phi)
    return z


def z_to_q_numpy(z: Any) -> np.ndarray:
    """``z_to_q`` in float64 numpy: (…, 3n) bending vectors → (θ, φ, L); φ is 0 where
    θ = 0."""
    q = np.array(z, dtype=np.float64)
    ux, uy = q[..., 0::3].copy(), q[..., 1::3].copy()
    theta = np.hypot(ux, uy)
    q[..., 0::3], q[..., 1::3] = theta, np.where(theta > 0.0, np.arctan2(uy, ux), 0.0)
    return q


def _is_jax(*values: Any) -> bool:
    """Whether any argument is a JAX array or tracer (then the JAX path runs)."""
    return any(isinstance(v, jax.Array) for v in values)


def _numpy_q(robot: Robot, q: Any) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (robot.dof,):
        raise ValueError(
            f"q must have {robot.dof} entries on its last axis ([θ, φ, L] × {robot.n_segments} "
            f"segments of {robot.name!r}), got shape {q.shape}"
        )
    return q


def _numpy_entries(robot: Robot, q: Any) -> list[np.ndarray]:
    """The float64 bending-vector entries of numpy configurations q (…, 3n)."""
    z = q_to_z_numpy(_numpy_q(robot, q))
    return [z[..., i] for i in range(robot.dof)]


def _numpy_vec(entries: Any) -> np.ndarray:
    return np.stack(np.broadcast_arrays(*entries), axis=-1).astype(np.float64)


def _numpy_rot(entries: Any) -> np.ndarray:
    flat = _numpy_vec(entries)
    return flat.reshape(flat.shape[:-1] + (3, 3))


@robot_jit
def tip_pose_z(robot: Robot, z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Tip position (…, 3) metres and rotation matrix (…, 3, 3) from bending-vector z."""
    entries = [z[..., i] for i in range(robot.dof)]
    rot, pos = model_segment_frames(JAX, robot, entries)[-1]
    return _vec_array(pos), _rot_array(rot)


def tip_pose(robot: Robot, q: Any) -> tuple[Any, Any]:
    """Tip position (…, 3) in metres and rotation (…, 3, 3) in the world frame.

    ``q`` is (…, 3n) as ``[θ1, φ1, L1, …]`` (radians, radians, metres), any leading
    batch shape. Numpy (or list) in: evaluated in float64 numpy, float64 numpy out.
    JAX array in: JAX out with q's dtype, traceable (jit, vmap, jacfwd).
    """
    if _is_jax(q):
        return tip_pose_z(robot, q_to_z(robot, q))
    rot, pos = model_segment_frames(NUMPY, robot, _numpy_entries(robot, q))[-1]
    return _numpy_vec(pos), _numpy_rot(rot)


@robot_jit
def backbone_points_z(robot: Robot, z: jax.Array) -> jax.Array:
    """Backbone points (…, n·k, 3) in metres from bending-vector z (z's dtype)."""
    return model_backbone(JAX, robot, [z[..., i] for i in range(robot.dof)]).astype(z.dtype)


def backbone_points(robot: Robot, q: Any) -> Any:
    """Backbone points (…, n·k, 3), metres: k = ``points_per_segment`` per segment at arc
    fractions j/k (j = 1…k), segment by segment; the base point is not included.

    ``q`` (…, 3n) in radians and metres; numpy in → float64 numpy out, JAX in → JAX out.
    """
    if _is_jax(q):
        return backbone_points_z(robot, q_to_z(robot, q))
    return np.asarray(model_backbone(NUMPY, robot, _numpy_entries(robot, q)), dtype=np.float64)


@robot_jit
def tendon_lengths_z(robot: Robot, z: jax.Array) -> jax.Array:
    """Tendon lengths (…, n_tendons) in metres from bending-vector z: one product with
    ``tendon_length_matrix`` (a program of a few operations, not one per entry)."""
    matrix = tendon_length_matrix(robot, _offsets_xp(robot))[0]
    return jnp.matmul(z, jnp.asarray(matrix, z.dtype), precision=jax.lax.Precision.HIGHEST)


def tendon_lengths(robot: Robot, q: Any) -> Any:
    """Tendon lengths (…, n_tendons) in metres for the robot's routing (see docs/design.md §1).

    ``q`` (…, 3n) in radians and metres; numpy in → float64 numpy out, JAX in → JAX out.
    """
    if _is_jax(q):
        return tendon_lengths_z(robot, q_to_z(robot, q))
    entries = _numpy_entries(robot, q)
    shape = entries[0].shape
    return np.stack([np.broadcast_to(v, shape) for v in model_tendon_lengths(NUMPY, robot,
                                                                           entries)],
                    axis=-1).astype(np.float64)


@jax.jit
def _pose_error_vector_jax(position: jax.Array, rotation: jax.Array,
                           target_position: jax.Array, target_rotation: jax.Array) -> jax.Array:
    tip = (_entries_of_rot(rotation), tuple(position[..., i] for i in range(3)))
    target = (_entries_of_rot(target_rotation), tuple(target_position[..., i] for i in range(3)))
    return _vec_array(model_pose_error(JAX, tip, target))


def pose_error_vector(position: Any, rotation: Any, target_position: Any,
                      target_rotation: Any) -> Any:
    """log(T⁻¹·T_target) as (…, 6): translation part (m) then rotation part (rad).

    Positions (…, 3) m, rotations (…, 3, 3). All numpy in → float64 numpy out; any JAX
    array in → JAX out (traceable).
    """
    if _is_jax(position, rotation, target_position, target_rotation):
        return _pose_error_vector_jax(position, rotation, target_position, target_rotation)
    p, r, tp, tr = (np.asarray(x, dtype=np.float64)
                    for x in (position, rotation, target_position, target_rotation))
    tip = (_entries_of_rot(r), tuple(p[..., i] for i in range(3)))
    target = (_entries_of_rot(tr), tuple(tp[..., i] for i in range(3)))
    return _numpy_vec(model_pose_error(NUMPY, tip, target))


def pose_error(position: Any, rotation: Any, target_position: Any, target_rotation: Any) -> Any:
    """The success metric ‖log(T⁻¹·T_target)‖₂ (…,) (mixed metres/radians, docs/design.md §1).

    Positions (…, 3) m, rotations (…, 3, 3). All numpy in → float64 numpy out; any JAX
    array in → JAX out (traceable).
    """
    vector = pose_error_vector(position, rotation, target_position, target_rotation)
    if isinstance(vector, jax.Array):
        return jnp.linalg.norm(vector, axis=-1)
    return np.linalg.norm(vector, axis=-1)


# ================================================================ CasADi front end

class CasadiModel:
    """CasADi functions of one robot, built from the same model code as the JAX side.

    Every function takes ``q`` (3n, θ/φ/L) and has a twin taking ``z`` (bending vector):
    ``tip(q) -> (position 3×1, rotation 3×3)``, ``backbone(q) -> N×3``,
    ``tendons(q) -> n_tendons×1``, ``pose_error(q, target_position, target_rotation) -> 6×1``.
    """

    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        n = robot.dof
        self.q = ca.SX.sym("q", n)
        self.z = ca.SX.sym("z", n)
        target_p = ca.SX.sym("target_position", 3)
        target_r = ca.SX.sym("target_rotation", 3, 3)

        def build(var: ca.SX, name: str, z_entries: list) -> dict[str, ca.Function]:
            frames = model_segment_frames(CASADI, robot, z_entries)
            rot, pos = frames[-1]
            rot_m = ca.reshape(ca.vertcat(*rot), 3, 3).T  # row-major entries → matrix
            target = (tuple(target_r[i, j] for i in range(3) for j in range(3)),
                      tuple(target_p[i] for i in range(3)))
            err = ca.vertcat(*model_pose_error(CASADI, frames[-1], target))
            return {
                "tip": ca.Function(f"tip_{name}", [var], [ca.vertcat(*pos), rot_m]),
                "backbone": ca.Function(f"backbone_{name}", [var],
                                        [model_backbone(CASADI, robot, z_entries, frames)]),
                "tendons": ca.Function(
                    f"tendons_{name}", [var],
                    [ca.vertcat(*model_tendon_lengths(CASADI, robot, z_entries))]),
                "pose_error": ca.Function(f"pose_error_{name}", [var, target_p, target_r], [err]),
            }

        zq = model_q_to_z(CASADI, robot, self.q)
        self.functions_q = build(self.q, "q", zq)
        self.functions_z = build(self.z, "z", [self.z[i] for i in range(n)])

    def tip(self, q: Any) -> tuple[np.ndarray, np.ndarray]:
        p, r = self.functions_q["tip"](q)
        return np.asarray(p).ravel(), np.asarray(r)

    def backbone(self, q: Any) -> np.ndarray:
        return np.asarray(self.functions_q["backbone"](q))

    def tendons(self, q: Any) -> np.ndarray:
        return np.asarray(self.functions_q["tendons"](q)).ravel()
