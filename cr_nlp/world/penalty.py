"""Clearance residuals for the LM stages, with a Jacobian that costs one gradient.

The LM penalty needs, per body sphere, the distance to its nearest obstacle part, and
the self-clearance pairs. Forward-mode differentiation would push every tangent
direction (3n of them) through every (sphere, part) distance; but sphere i's nearest
distance depends on its own centre cᵢ only, so

    d dᵢ/dz = ∇_c dᵢ(cᵢ) · ∂cᵢ/∂z,

one reverse pass over the pair distances (independent of the tangent) and the cheap
forward Jacobian of the centres. Self pairs use the closed-form unit vector.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from ..model.robot import Robot
from .clearance import SceneArrays, _centres, _kind_blocks, _self_block, self_pairs


def _nearest_obstacle(robot: Robot, arrays: SceneArrays, centres: jax.Array) -> jax.Array:
    blocks = _kind_blocks(robot, arrays, centres, 0.0)
    return jnp.min(jnp.concatenate(blocks, axis=-1), axis=-1)


def _has_obstacles(arrays: SceneArrays | None) -> bool:
    return arrays is not None and arrays.n_parts > 0


def body_clearances_z(robot: Robot, arrays: SceneArrays | None, z: jax.Array) -> jax.Array:
    """Signed distances (m) of ONE configuration z (3n, bending vector): each body sphere
    to its nearest obstacle part (N values, when the scene has parts), then every
    self-clearance pair (M values, robots of ≥ 3 segments). Differentiable, with the
    cheap Jacobian described in the module docstring."""
    return _body_clearances(robot, arrays, z)


def _values(robot: Robot, arrays: SceneArrays | None, centres: jax.Array) -> jax.Array:
    parts = []
    if _has_obstacles(arrays):
        parts.append(_nearest_obstacle(robot, arrays, centres))
    if robot.n_segments >= 3:
        parts.append(_self_block(robot, centres))
    if not parts:
        return jnp.zeros((0,), centres.dtype)
    return jnp.concatenate(parts)


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _clearance_core(robot: Robot, arrays: SceneArrays | None, z: jax.Array) -> jax.Array:
    return _values(robot, arrays, _centres(robot, z, False))


def _body_clearances(robot: Robot, arrays: SceneArrays | None, z: jax.Array) -> jax.Array:
    return _clearance_core(robot, arrays, z)


@_clearance_core.defjvp
def _clearance_jvp(robot: Robot, primals: tuple,
                   tangents: tuple) -> tuple[jax.Array, jax.Array]:
    arrays, z = primals
    z_dot = tangents[1]
    centres, centres_dot = jax.jvp(lambda x: _centres(robot, x, False), (z,), (z_dot,))
    value = _values(robot, arrays, centres)
    out = []
    if _has_obstacles(arrays):
        grad = jax.grad(lambda c: jnp.sum(_nearest_obstacle(robot, arrays, c)))(centres)
        out.append(jnp.sum(grad * centres_dot, axis=-1))
    if robot.n_segments >= 3:
        pairs = self_pairs(robot)
        diff = centres[pairs[:, 0]] - centres[pairs[:, 1]]
        norm = jnp.sqrt(jnp.maximum(jnp.sum(diff * diff, axis=-1, keepdims=True), 1e-30))
        rate = centres_dot[pairs[:, 0]] - centres_dot[pairs[:, 1]]
        out.append(jnp.sum(diff / norm * rate, axis=-1))
    tangent = jnp.concatenate(out) if out else jnp.zeros((0,), centres.dtype)
    return value, tangent
