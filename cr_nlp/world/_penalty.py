"""Clearance residuals for the LM stages, with a Jacobian that costs one gradient.

Two forms: ``body_clearances_z`` (nearest obstacle part per body sphere, then every self
pair; the trajectory LM groups them) and ``sphere_clearances_z`` (nearest obstacle part
and nearest self partner per body sphere; the IK LM, fewer residuals).

The LM penalty needs, per body sphere, the distance to its nearest obstacle part, and
the self-clearance pairs. Forward-mode differentiation would push every tangent
direction (3n of them) through every (sphere, part) distance; but sphere i's nearest
distance depends on its own centre cᵢ only, so

    d dᵢ/dz = ∇_c dᵢ(cᵢ) · ∂cᵢ/∂z,

one reverse pass over the pair distances (independent of the tangent) and the cheap
forward Jacobian of the centres. Self pairs use the closed-form unit vector.

The self pairs are evaluated block by block (``self_pair_blocks``: every sphere of one
segment's chain against every sphere of a chain two or more segments on), with static
slices and broadcasting, never a gather: measured on 2 busy CPU cores (tdcr4_ext, 341
pairs, 1024 problems, float32), the self-pair tangent over the 12 tangent directions
took 127–230 ms with the gathered form ``c[pairs[:, 0]] − c[pairs[:, 1]]`` and 90–117 ms
in blocks; the per-sphere form below avoids most of that cost.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..model._ops import JAX
from ..model.derivatives import backbone_jacobian_z
from ..model.robot import Robot
from ..runtime import cached
from . import _distances as dist
from .clearance import SceneArrays, _centres, _kind_blocks, body_segments


def _nearest_obstacle(robot: Robot, arrays: SceneArrays, centres: jax.Array) -> jax.Array:
    blocks = _kind_blocks(robot, arrays, centres, 0.0)
    return jnp.min(jnp.concatenate(blocks, axis=-1), axis=-1)


def _has_obstacles(arrays: SceneArrays | None) -> bool:
    return arrays is not None and arrays.n_parts > 0


def self_pair_blocks(robot: Robot) -> tuple[tuple[int, int, int, int], ...]:
    """The self pairs (``clearance.self_pairs``) as blocks of consecutive body spheres:
    ``(row_start, row_stop, col_start, col_stop)``, one block per chain pair (s, t ≥ s + 2),
    each pair exactly once. Chains share their junction sphere, so a block drops its first
    row when s ≥ 1 (that pair is in block (s − 1, t)) and its last column when t < n − 1
    (that pair is in block (s, t + 1)). From the robot's shape alone (a robot whose
    numbers are traced has them too); not cached by robot, as a traced one cannot be a
    key (a few segments: cheap, and asked for while a program is traced)."""
    chains = body_segments(robot)
    n = robot.n_segments if robot.self_collision else 0
    blocks = []
    for s in range(n):
        for t in range(s + 2, n):
            rows, cols = chains[s], chains[t]
            r0 = int(rows[0]) + (1 if s >= 1 else 0)
            c1 = int(cols[-1]) + (0 if t < n - 1 else 1)
            blocks.append((r0, int(rows[-1]) + 1, int(cols[0]), c1))
    return tuple(blocks)


def penalty_self_pairs(robot: Robot) -> np.ndarray:
    """(M, 2) body-sphere index pairs in the order ``body_clearances_z`` returns the self
    distances (the same set as ``clearance.self_pairs``, block by block)."""
    out = [np.stack(np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij"), -1)
           .reshape(-1, 2) for r0, r1, c0, c1 in self_pair_blocks(robot)]
    return np.concatenate(out) if out else np.zeros((0, 2), dtype=np.int64)


def body_clearances_z(robot: Robot, arrays: SceneArrays | None, z: jax.Array) -> jax.Array:
    """Signed distances (m) of ONE configuration z (3n, bending vector): each body sphere
    to its nearest obstacle part (N values, when the scene has parts), then every
    self-clearance pair (M values, robots of ≥ 3 segments, in ``penalty_self_pairs``
    order). Differentiable, with the cheap Jacobian described in the module docstring."""
    return _body_clearances(robot, arrays, z)


def _self_values(robot: Robot, centres: jax.Array) -> jax.Array:
    """(M,) self-pair distances (m), block by block (``self_pair_blocks``)."""
    r = robot.backbone_radius
    out = []
    for r0, r1, c0, c1 in self_pair_blocks(robot):
        ci = centres[r0:r1, None, :]
        cj = centres[None, c0:c1, :]
        d = dist.sphere_to_sphere(JAX, tuple(ci[..., k] for k in range(3)), r,
                                  tuple(cj[..., k] for k in range(3)), r)
        out.append(d.reshape(-1))
    return jnp.concatenate(out)


def _self_tangent(robot: Robot, centres: jax.Array, centres_dot: jax.Array) -> jax.Array:
    """(M,) directional derivatives of ``_self_values``: unit(cᵢ − cⱼ)·(ċᵢ − ċⱼ)."""
    out = []
    for r0, r1, c0, c1 in self_pair_blocks(robot):
        diff = centres[r0:r1, None, :] - centres[None, c0:c1, :]
        norm = jnp.sqrt(jnp.maximum(jnp.sum(diff * diff, axis=-1, keepdims=True), 1e-30))
        rate = centres_dot[r0:r1, None, :] - centres_dot[None, c0:c1, :]
        out.append(jnp.sum(diff / norm * rate, axis=-1).reshape(-1))
    return jnp.concatenate(out)


def _values(robot: Robot, arrays: SceneArrays | None, centres: jax.Array) -> jax.Array:
    parts = []
    if _has_obstacles(arrays):
        parts.append(_nearest_obstacle(robot, arrays, centres))
    if robot.has_self_pairs:
        parts.append(_self_values(robot, centres))
    if not parts:
        return jnp.zeros((0,), centres.dtype)
    return jnp.concatenate(parts)


def _centres_and_rates(robot: Robot, z: jax.Array,
                       z_dot: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Body-sphere centres (N, 3) m of one z (3n,) (``clearance._centres``: the base, then
    the backbone points) and their rates (N, 3) along z_dot, by the model's closed-form
    centre Jacobian: under the LM's jacfwd it is built once per configuration and only
    the contraction is batched over the tangents."""
    points, d_points = backbone_jacobian_z(robot, z)
    centres = jnp.concatenate([jnp.asarray(robot.base_position, z.dtype)[None], points])
    rates = jnp.concatenate([jnp.zeros((1, 3), z.dtype), d_points @ z_dot])
    return centres, rates


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
    centres, centres_dot = _centres_and_rates(robot, z, z_dot)
    value = _values(robot, arrays, centres)
    out = []
    if _has_obstacles(arrays):
        grad = jax.grad(lambda c: jnp.sum(_nearest_obstacle(robot, arrays, c)))(centres)
        out.append(jnp.sum(grad * centres_dot, axis=-1))
    if robot.has_self_pairs:
        out.append(_self_tangent(robot, centres, centres_dot))
    tangent = jnp.concatenate(out) if out else jnp.zeros((0,), centres.dtype)
    return value, tangent


# ---------------------------------------------------------------- per-sphere form (IK)
#
# The IK residual needs one value per body sphere, not one per self pair: a sphere's
# nearest obstacle part and its nearest sphere on a non-neighbouring segment. Both are
# zero-shortfall exactly when every pair keeps the margin (the same feasible set as the
# per-pair form). Measured on 2 CPU cores (tdcr4_ext in the lattice, 1024 problems,
# float32): the per-pair form gives 388 residuals and 170–250 ms per Jacobian, most of it
# the (12 tangents × 341 pairs × 3) self-pair tangent; this form gives 88 residuals, and
# 6 sharded LM iterations on 1024 problems took 1.35–2.4 s instead of 1.6–3.9 s
# (interleaved runs, load 5–7).


def _self_partners(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """Body spheres with at least one self-clearance partner (R,) and the (R, N) mask of
    their partners (spheres on segments at least two apart, ``clearance.self_pairs``)."""
    return _partners(robot.n_points + 1, self_pair_blocks(robot))


@cached(maxsize=32)
def _partners(n_bodies: int, blocks: tuple[tuple[int, int, int, int], ...]
              ) -> tuple[np.ndarray, np.ndarray]:
    mask = np.zeros((n_bodies, n_bodies), bool)
    for r0, r1, c0, c1 in blocks:
        mask[r0:r1, c0:c1] = True
    mask |= mask.T
    rows = np.flatnonzero(mask.any(axis=1))
    return rows, mask[rows]


def nearest_self_clearances(robot: Robot, centres: jax.Array) -> tuple[jax.Array, jax.Array]:
    """For each sphere of ``_self_partners`` (R,): the signed distance (m) to its nearest
    partner sphere, and the (R, N, 3) derivative of those distances by the centres
    (unit vector on the sphere itself, its negative on the partner)."""
    rows, mask = _self_partners(robot)
    # The rows picked by a 0/1 product, not a gather: a gather's index dtype follows the
    # x64 setting at trace time, which a program traced in one setting and reused in the
    # other got wrong (int32 + int64 in JAX's index normalisation).
    select = jnp.asarray(np.eye(centres.shape[0])[rows], centres.dtype)  # (R, N)
    own = select @ centres                                         # (R, 3)
    diff = own[:, None, :] - centres[None, :, :]                   # (R, N, 3)
    sq = jnp.sum(diff * diff, axis=-1)
    sq = jnp.where(jnp.asarray(mask), sq, jnp.inf)
    # The nearest partner as a 0/1 row (ties share the weight): XLA's CPU argmin is a
    # slow variadic reduction, a min and a compare are not.
    onehot = (sq <= jnp.min(sq, axis=-1, keepdims=True)).astype(centres.dtype)
    onehot = onehot / jnp.sum(onehot, axis=-1, keepdims=True)     # (R, N)
    d_vec = own - onehot @ centres                                 # (R, 3)
    norm = jnp.sqrt(jnp.maximum(jnp.sum(d_vec * d_vec, axis=-1), 1e-30))
    unit = d_vec / norm[:, None]
    grad = (select - onehot)[:, :, None] * unit[:, None, :]
    return norm - 2.0 * robot.backbone_radius, grad


def sphere_clearances_z(robot: Robot, arrays: SceneArrays | None, z: jax.Array) -> jax.Array:
    """Per-sphere signed distances (m) of ONE configuration z (3n, bending vector): each
    body sphere to its nearest obstacle part (N values, when the scene has parts), then
    each body sphere that has self-clearance partners to its nearest partner (R values,
    robots of ≥ 3 segments; ``_self_partners``). Differentiable: the Jacobian costs one
    centre Jacobian plus a contraction per residual, never a pass per (pair, tangent)."""
    return _sphere_core(robot, arrays, z)


def _sphere_values(robot: Robot, arrays: SceneArrays | None,
                   centres: jax.Array) -> tuple[jax.Array, jax.Array | None]:
    """The values of ``sphere_clearances_z`` and the (R, N, 3) self-distance gradient."""
    parts, grads = [], []
    if _has_obstacles(arrays):
        parts.append(_nearest_obstacle(robot, arrays, centres))
    if robot.has_self_pairs:
        d, g = nearest_self_clearances(robot, centres)
        parts.append(d)
        grads.append(g)
    if not parts:
        return jnp.zeros((0,), centres.dtype), None
    return jnp.concatenate(parts), (grads[0] if grads else None)


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _sphere_core(robot: Robot, arrays: SceneArrays | None, z: jax.Array) -> jax.Array:
    return _sphere_values(robot, arrays, _centres(robot, z, False))[0]


@_sphere_core.defjvp
def _sphere_jvp(robot: Robot, primals: tuple, tangents: tuple) -> tuple[jax.Array, jax.Array]:
    arrays, z = primals
    centres, centres_dot = _centres_and_rates(robot, z, tangents[1])
    value, self_grad = _sphere_values(robot, arrays, centres)
    out = []
    if _has_obstacles(arrays):
        grad = jax.grad(lambda c: jnp.sum(_nearest_obstacle(robot, arrays, c)))(centres)
        out.append(jnp.sum(grad * centres_dot, axis=-1))
    if self_grad is not None:
        out.append(jnp.einsum("rnk,nk->r", self_grad, centres_dot))
    tangent = jnp.concatenate(out) if out else jnp.zeros((0,), centres.dtype)
    return value, tangent
