"""Per-waypoint tip kinematics of the path follower with closed-form Jacobians.

The LM needs, per waypoint, a 6 × 3n tracking Jacobian and a G × 3n clearance Jacobian.
Pushing 3n tangents through the model's entry-by-entry code costs thousands of small XLA
operations per call; the functions here take their values from the model
(``model.kinematics``), their derivatives from the model's closed forms
(``model.derivatives``), and get their Jacobians from the primal alone
(``jax.custom_jvp``), so the banded LM's forward-mode pass over a window costs one matrix
product. Units: m, rad.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp

from ...model import Robot
from ...model._ops import JAX
from ...model.derivatives import kinematics_jacobians_z
from ...model.kinematics import model_backbone, model_segment_frames
from ...model.lie import rotation_log, so3_right_jacobian_inverse
from ...world._clearance_groups import body_centres_from


def waypoint_kinematics(robot: Robot, z: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Tip rotation (3, 3), tip position (3,) m and body-sphere centres (N, 3) m of one
    bending-vector configuration z (3n,), from one evaluation of the model's frames
    (``model_segment_frames``, ``model_backbone``), in z's dtype."""
    entries = [z[i] for i in range(robot.dof)]
    frames = model_segment_frames(JAX, robot, entries)
    rot, pos = frames[-1]
    points = model_backbone(JAX, robot, entries, frames).astype(z.dtype)
    return (jnp.stack(jnp.broadcast_arrays(*rot)).reshape(3, 3).astype(z.dtype),
            jnp.stack(jnp.broadcast_arrays(*pos)).astype(z.dtype),
            body_centres_from(robot, points)[0])


def waypoint_jacobians(robot: Robot, z: jax.Array) -> dict[str, jax.Array]:
    """``waypoint_kinematics`` and its closed-form derivatives (``model.derivatives``) for
    one z (3n,). Returns ``rotation`` (3, 3), ``position`` (3,), ``centres`` (N, 3),
    ``d_position`` (3, 3n), ``body_rates`` (3, 3n) (Rᵀ∂R/∂z_k as vectors) and
    ``d_centres`` (N, 3, 3n)."""
    kin = kinematics_jacobians_z(robot, z)
    centres, d_centres = body_centres_from(robot, kin.points, kin.d_points)
    return {"rotation": kin.rotation, "position": kin.position, "centres": centres,
            "d_position": kin.jacobian[:3], "body_rates": kin.rotation.T @ kin.jacobian[3:],
            "d_centres": d_centres}


def tracking_from(rot: jax.Array, pos: jax.Array, target: Any) -> jax.Array:
    """``tracking_error`` from the tip rotation (3, 3) and position (3,) m: position
    error (3,) m, then log(R_refᵀ·R_tip) (3,) rad."""
    target_position, target_rotation, _ = target
    error = target_rotation.reshape(3, 3).T @ rot
    return jnp.concatenate([pos - target_position, rotation_log(error)])


def tracking_jacobian(kin: dict[str, jax.Array], error: jax.Array) -> jax.Array:
    """(6, d) Jacobian of ``tracking_error`` from ``waypoint_jacobians`` and the error."""
    return jnp.concatenate([kin["d_position"],
                            so3_right_jacobian_inverse(error[3:]) @ kin["body_rates"]])


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def tracking_error(robot: Robot, z: jax.Array, target: Any) -> jax.Array:
    """The tracking error of one waypoint z (3n,): the tip position minus the reference
    position (3,) m, then log(R_refᵀ·R_tip) (3,) rad. Their norms are the reported
    position and rotation errors. ``target`` = (position (3,), rotation (9,) row major,
    tracking switch); only z is differentiated."""
    rot, pos, _ = waypoint_kinematics(robot, z)
    return tracking_from(rot, pos, target)


@tracking_error.defjvp
def _tracking_error_jvp(robot: Robot, primals: tuple, tangents: tuple) -> tuple:
    z, target = primals
    z_dot = tangents[0]
    kin = waypoint_jacobians(robot, z)
    value = tracking_from(kin["rotation"], kin["position"], target)
    return value, tracking_jacobian(kin, value) @ z_dot
