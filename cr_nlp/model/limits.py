"""Configuration limits in the bending-vector form: exact projection and violation measures."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .robot import Robot


def _limit_arrays(robot: Robot, dtype: jnp.dtype) -> tuple[jax.Array, ...]:
    theta_max = jnp.asarray([s.theta_max for s in robot.segments], dtype)
    length_lo = jnp.asarray([s.length_min for s in robot.segments], dtype)
    length_hi = jnp.asarray([s.length_max for s in robot.segments], dtype)
    return theta_max, length_lo, length_hi


def project_z(robot: Robot, z: jax.Array) -> jax.Array:
    """Nearest point of the limits for (…, 3n) bending-vector configurations.

    ‖uᵢ‖ ≤ θmaxᵢ (radians) by radial scaling, Lᵢ clipped to its range (metres) and,
    where a segment has an azimuth range, φᵢ clipped to it.
    """
    theta_max, length_lo, length_hi = _limit_arrays(robot, z.dtype)
    seg = z.reshape(z.shape[:-1] + (robot.n_segments, 3))
    u = seg[..., :2]
    theta = jnp.sqrt(jnp.sum(u * u, axis=-1))
    scale = jnp.where(theta > theta_max, theta_max / jnp.maximum(theta, 1e-30), 1.0)
    u = u * scale[..., None]
    if any(s.phi_limited for s in robot.segments):
        lo = jnp.asarray([s.phi_min for s in robot.segments], z.dtype)  # −inf: no limit
        hi = jnp.asarray([s.phi_max for s in robot.segments], z.dtype)
        th = jnp.minimum(theta, theta_max)
        phi = jnp.clip(jnp.arctan2(u[..., 1], u[..., 0]), lo, hi)
        u = jnp.stack([th * jnp.cos(phi), th * jnp.sin(phi)], axis=-1)
    length = jnp.clip(seg[..., 2], length_lo, length_hi)
    return jnp.concatenate([u, length[..., None]], axis=-1).reshape(z.shape)


def limit_violation_q(robot: Robot, q: np.ndarray, xp: Any = np) -> np.ndarray:
    """Largest violation of the limits by (…, 3n) configurations (θ, φ, L), in rad or m (≥ 0).
    ``xp``: numpy (float64), or ``jax.numpy`` inside a traced program (the verdict's)."""
    q = xp.asarray(q, dtype=float) if xp is np else q
    seg = q.reshape(q.shape[:-1] + (robot.n_segments, 3))
    theta, phi, length = seg[..., 0], seg[..., 1], seg[..., 2]
    # xp's arrays: inside a program whose robot is data (``Robot.program_data``) the
    # limits are traced.
    theta_max, lo_l, hi_l, lo_p, hi_p = (
        xp.asarray([getattr(s, f) for s in robot.segments])
        for f in ("theta_max", "length_min", "length_max", "phi_min", "phi_max"))
    parts = [
        xp.maximum(theta - theta_max, 0.0), xp.maximum(-theta, 0.0),
        xp.maximum(length - hi_l, 0.0), xp.maximum(lo_l - length, 0.0),
    ]
    limited = np.array([s.phi_limited for s in robot.segments])
    # φ is undefined for a straight segment: its range cannot be broken there.
    bent = theta > 1e-12
    parts += [xp.where(limited & bent, xp.maximum(phi - hi_p, 0.0), 0.0),
              xp.where(limited & bent, xp.maximum(lo_p - phi, 0.0), 0.0)]
    return xp.max(xp.stack(parts, axis=-1), axis=(-1, -2))


def project_bending(robot: Robot, q: np.ndarray) -> np.ndarray:
    """(…, 3n) configurations (θ, φ, L) with θ clipped into [0, θmax] (the bending disk)
    and L into its range, float64; φ unchanged (an azimuth range is not a simple set in
    the optimisers' variables). Removes the ~1e-8 that Ipopt's bound relaxation leaves
    outside an active bound, before the answer is judged."""
    lo, hi = robot.q_bounds()
    simple = np.array([[True, False, True] for _ in robot.segments]).ravel()
    q = np.asarray(q, dtype=np.float64)
    return np.where(simple, np.clip(q, lo, hi), q)


def clip_to_limits(robot: Robot, q: np.ndarray) -> np.ndarray:
    """(…, 3n) configurations (θ, φ, L) with θ, L (and limited φ) clipped into their ranges,
    in float64: removes the round-off a float32 solver leaves at an active limit."""
    lo, hi = robot.q_bounds()
    periodic = np.array([[False, not s.phi_limited, False] for s in robot.segments]).ravel()
    return np.where(periodic, q, np.clip(q, lo, hi))
