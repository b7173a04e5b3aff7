"""Choosing one IK answer per waypoint so that the sequence moves as little as possible.

Dynamic programming (Viterbi) over the candidate sets: the cost of a sequence is the sum
of squared configuration jumps between consecutive waypoints, measured in the
bending-vector form (no azimuth wrap-around, no singularity at θ = 0); candidates that do
not reach their waypoint are excluded unless a waypoint has none, in which case its best
candidate is kept (and the caller reports that waypoint as unreached).

``smoothest_choice`` is the traceable JAX form (a forward min-plus ``lax.scan`` with
argmin back-pointers, then a reverse scan that reads the choice back), so a caller can
run it inside its own device program; ``smoothest_sequence`` is the numpy-in,
numpy-out front end.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..._cached_jit import cached_jit
from ...model import Robot, q_to_z_numpy


def smoothest_choice(z: jax.Array, errors: jax.Array, tolerance: jax.Array | float) -> jax.Array:
    """Indices (T,) int32 of the candidate to use at each waypoint (traceable JAX).

    Args:
        z: (T, K, 3n) candidates in bending-vector form (rad, rad, m).
        errors: (T, K) residual norms of the candidates (pose error, m/rad); inf or NaN
            marks an empty slot.
        tolerance: candidates with an error at or above this are not used where a
            waypoint has a better one.

    Ties go to the lowest index, as ``numpy.argmin``.
    """
    _, k, _ = z.shape
    usable = errors < tolerance
    # A waypoint with no usable candidate keeps its best one rather than breaking the chain.
    best = jnp.argmin(jnp.where(jnp.isnan(errors), jnp.inf, errors), axis=1)
    usable = usable | (~usable.any(axis=1, keepdims=True)
                       & (jnp.arange(k) == best[:, None]))
    # Unused slots may hold anything (NaN from a diverged chain): keep them out of the sums.
    z = jnp.where(usable[..., None], z, 0.0)
    inf = jnp.asarray(jnp.inf, z.dtype)
    node = jnp.where(usable, jnp.zeros((), z.dtype), inf)

    def forward(total: jax.Array, step: tuple) -> tuple[jax.Array, jax.Array]:
        z_prev, z_here, node_here = step
        jump = jnp.sum((z_here[None, :, :] - z_prev[:, None, :]) ** 2, axis=-1)  # (K_prev, K)
        options = total[:, None] + jump
        back = jnp.argmin(options, axis=0)
        return jnp.min(options, axis=0) + node_here, back

    total, back = jax.lax.scan(forward, node[0], (z[:-1], z[1:], node[1:]))

    def backward(later: jax.Array, back_here: jax.Array) -> tuple[jax.Array, jax.Array]:
        earlier = back_here[later]
        return earlier, earlier

    last = jnp.argmin(total).astype(jnp.int32)
    _, earlier = jax.lax.scan(backward, last, back.astype(jnp.int32), reverse=True)
    return jnp.concatenate([earlier, last[None]])


_smoothest_choice = cached_jit(smoothest_choice, name="the waypoint sequence")


def smoothest_sequence(robot: Robot, candidates: np.ndarray, errors: np.ndarray,
                       tolerance: float) -> np.ndarray:
    """Indices (T,) of the candidate to use at each waypoint (``smoothest_choice`` on
    the device, in float64 where JAX has x64 enabled, else float32).

    Args:
        candidates: (T, K, 3n) configurations (θ, φ, L) per waypoint (rad, rad, m).
        errors: (T, K) residual norms of the candidates (pose error, m/rad).
        tolerance: candidates with an error at or above this are not used where a
            waypoint has a better one.
    """
    candidates = np.asarray(candidates, dtype=np.float64)
    if candidates.ndim != 3 or candidates.shape[2] != robot.dof:
        raise ValueError(f"candidates must be (T, K, {robot.dof}), got {candidates.shape}")
    errors = np.asarray(errors, dtype=np.float64)
    if errors.shape != candidates.shape[:2]:
        raise ValueError(f"errors must be {candidates.shape[:2]}, got {errors.shape}")
    choice = _smoothest_choice(q_to_z_numpy(candidates), errors, tolerance)
    return np.asarray(choice, dtype=int)
