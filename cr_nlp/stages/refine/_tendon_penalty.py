"""Penalty residuals of the tendon speed and acceleration limits, for the LM stages.

Tendon lengths are linear in the bending vector z (``model.kinematics.tendon_lengths_z``);
speed and acceleration are finite differences over the time step Δt between waypoints
(docs/design.md §1). A penalty LM aims at a fraction f ≤ 1 of each limit, so that the small
overshoot a penalty leaves still lies inside the real limit.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ...model import Robot
from ...model.kinematics import tendon_lengths_z


def _lengths(robot: Robot, z: jax.Array) -> jax.Array:
    return tendon_lengths_z(robot, z).astype(z.dtype)


def tendon_speed_excess(robot: Robot, limit_fraction: float, z_a: jax.Array, z_b: jax.Array,
                        dt: jax.Array) -> jax.Array:
    """max(0, |Δℓ/Δt|/(f·v_max) − 1) per tendon (n_tendons,), dimensionless, of the
    interval z_a → z_b ((3n,) each, rad, rad, m) taking ``dt`` seconds;
    f = ``limit_fraction``, v_max = ``robot.tendon_speed_max`` (m/s, finite)."""
    speed = (_lengths(robot, z_b) - _lengths(robot, z_a)) / dt
    return jnp.maximum(jnp.abs(speed) / (limit_fraction * robot.tendon_speed_max) - 1.0, 0.0)


def tendon_accel_excess(robot: Robot, limit_fraction: float, z_a: jax.Array, z_b: jax.Array,
                        z_c: jax.Array, dt: jax.Array) -> jax.Array:
    """max(0, |Δ²ℓ/Δt²|/(f·a_max) − 1) per tendon (n_tendons,), dimensionless, at the
    middle waypoint z_b of z_a, z_b, z_c ((3n,) each) ``dt`` seconds apart;
    a_max = ``robot.tendon_accel_max`` (m/s², finite)."""
    accel = (_lengths(robot, z_c) - 2.0 * _lengths(robot, z_b) + _lengths(robot, z_a)) / (dt * dt)
    return jnp.maximum(jnp.abs(accel) / (limit_fraction * robot.tendon_accel_max) - 1.0, 0.0)
