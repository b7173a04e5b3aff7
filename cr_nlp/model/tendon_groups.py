"""Tendon groups and the least tensions that pull with a given net moment.

A group is the tendons that end at one segment (per-segment routing) or all of them
(shared routing). Tendon i at radius r and angle α pulls the backbone with a moment
τ_i (r_i × e3) = τ_i r (sin α, −cos α) about the disk's x and y axes; a group's net pull
moment d is their sum. With three or more tendons evenly around the backbone every d is
reached by non-negative tensions, and the least of them (smallest total pull) use only
the two tendons whose directions enclose d: ``tensions_from_moments`` (continuous,
piecewise linear, a 2×2 solve per group). Units: newtons, metres, N·m.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..runtime import cached
from .mechanics import require_mechanics
from .robot import Robot
from .routing import routing_of


class TendonGroups(NamedTuple):
    """Static description of the tendon groups (numpy): tendons of group g are
    ``index[g]``, their pull directions r_i × e3 (in the xy plane) ``pull[g]`` (m), and
    ``pairs[g]`` the neighbouring pairs (i, j) around the circle (positions in the group)."""

    index: np.ndarray   # (G, m) tendon indices
    pull: np.ndarray    # (G, m, 2) m
    pairs: np.ndarray   # (m, 2)


@cached(maxsize=64)
def tendon_groups(robot: Robot) -> TendonGroups | None:
    """The tendon groups of ``robot``, None if a group has fewer than three tendons (their
    moments then do not cover the plane)."""
    m = robot.tendons.per_segment
    if m < 3:
        return None
    routing = routing_of(robot)
    # a group: the tendons that end at one segment, at their angles where they start
    index = np.stack([np.flatnonzero(routing.anchor == g) for g in np.unique(routing.anchor)])
    first = routing.angles(robot.tendons.offsets)[np.arange(len(routing.anchor)),
                                                  routing.first]
    angles = first[index]
    r = robot.tendons.radius
    # r_i × e3 for r_i = r (cos α, sin α, 0): r (sin α, −cos α, 0)
    pull = r * np.stack([np.sin(angles), -np.cos(angles)], axis=-1)
    order = np.argsort(np.mod(angles[0] - angles[0, 0], 2 * np.pi))
    pairs = np.stack([order, np.roll(order, -1)], axis=-1)
    return TendonGroups(index, pull, pairs)


def tensions_from_moments(groups: TendonGroups, n_tendons: int, tension_max: float,
                          d: jax.Array) -> jax.Array:
    """The least tensions (n_tendons,), N, whose groups pull with net moments d (G, 2),
    N·m: per group the two neighbouring tendons enclosing d, capped at τ_max."""
    tension = jnp.zeros(n_tendons, d.dtype)
    for g in range(len(groups.index)):
        v = groups.pull[g]
        found = jnp.zeros((), bool)
        for i, j in groups.pairs:
            det = v[i, 0] * v[j, 1] - v[i, 1] * v[j, 0]
            a = (d[g, 0] * v[j, 1] - d[g, 1] * v[j, 0]) / det
            b = (v[i, 0] * d[g, 1] - v[i, 1] * d[g, 0]) / det
            use = (a >= 0) & (b >= 0) & ~found
            found = found | use
            tension = tension.at[groups.index[g, i]].add(jnp.where(use, a, 0.0))
            tension = tension.at[groups.index[g, j]].add(jnp.where(use, b, 0.0))
    return jnp.minimum(tension, tension_max)


def moments_from_tensions(groups: TendonGroups, tensions: np.ndarray) -> np.ndarray:
    """(B, G, 2) net pull moments of tension sets (B, n), N·m (the map's inverse on its
    least-tension sets, and a seed for any set)."""
    return np.einsum("bgm,gmk->bgk", tensions[:, groups.index], groups.pull)


# ------------------------------------------------ PCC configurations and tensions, unloaded
def bending_per_tension(robot: Robot) -> np.ndarray:
    """(2S, n) rad/N: the bending vectors u = (ux₁, uy₁, …) of the unloaded rod per unit
    tension, u = B τ.

    Closed form (parallel routing, no loads): tension τ_j pulls its tendon by d = A u
    (A = ∂d/∂u, m/rad, exact from the PCC tendon lengths), so by virtual work it loads the
    bending vectors with the moments Aᵀτ (N·m), and segment i resists with EI_i / L_i (E I
    times its stiffness factor); the Cosserat rod agrees to its axial compression
    (micrometres, notebook 04)."""
    mech = require_mechanics(robot, "the tensions of a configuration")
    from .kinematics import tendon_lengths, z_to_q_numpy

    lengths = np.array([s.length_min for s in robot.segments])
    count = len(lengths)
    # E I of each segment (its stiffness factor), once per bending component
    stiffness = np.repeat(mech.bending_stiffness
                          * np.asarray(mech.stiffness_factors(count), float), 2)[:, None]

    def configuration(u: np.ndarray) -> np.ndarray:
        return z_to_q_numpy(np.insert(u.reshape(count, 2), 2, lengths, axis=1).reshape(-1))

    straight = np.asarray(tendon_lengths(robot, configuration(np.zeros(2 * count))))
    pull = np.stack([straight - np.asarray(tendon_lengths(robot, configuration(e)))
                     for e in np.eye(2 * count)], axis=1)            # (n, 2S) m/rad
    return np.repeat(lengths, 2)[:, None] / stiffness * pull.T


def configuration_of_tensions(robot: Robot, tensions: Any) -> np.ndarray:
    """The PCC configuration (…, 3S) (θ rad, φ rad, L m) the unloaded rod takes under
    tendon tensions (…, n) N, the robot file's tendon order (``bending_per_tension``)."""
    from .kinematics import z_to_q_numpy

    u = np.asarray(tensions, dtype=float) @ bending_per_tension(robot).T
    lengths = np.array([s.length_min for s in robot.segments])
    z = np.concatenate([u.reshape(*u.shape[:-1], -1, 2),
                        np.broadcast_to(lengths[:, None], (*u.shape[:-1], len(lengths), 1))],
                       axis=-1)
    return z_to_q_numpy(z.reshape(*u.shape[:-1], -1))


def tensions_of_configuration(robot: Robot, q: Any) -> tuple[np.ndarray, np.ndarray]:
    """The least tensions (…, n) N whose unloaded rod takes PCC configuration q (…, 3S)
    (θ rad, φ rad, L m), and (…,) the bending each misses, rad (0 where q is reachable:
    every tension within [0, τ_max] and one independent group per segment).

    Per tendon group the two neighbouring tendons enclosing the needed net moment carry
    it (``tensions_from_moments``), so the answer is continuous along a path of q.

    Raises:
        ValueError: no ``mechanics`` block, or fewer than three tendons per group.
    """
    from .kinematics import q_to_z_numpy

    groups = tendon_groups(robot)
    if groups is None:
        raise ValueError(f"{robot.name}: the tensions of a configuration need at least "
                         "three tendons per group")
    per_tension = bending_per_tension(robot)                          # (2S, n)
    q = np.asarray(q, dtype=float)
    u = q_to_z_numpy(q).reshape(*q.shape[:-1], -1, 3)[..., :2].reshape(*q.shape[:-1], -1)
    # u depends on the tensions only through the groups' net moments D: u = C D
    moments = np.zeros((2 * len(groups.index), robot.n_tendons))
    for g, index in enumerate(groups.index):
        moments[2 * g:2 * g + 2, index] = groups.pull[g].T
    per_moment = per_tension @ np.linalg.pinv(moments)               # (2S, 2G)
    needed = np.linalg.lstsq(per_moment, u.reshape(-1, u.shape[-1]).T, rcond=None)[0].T
    least = partial(tensions_from_moments, groups, robot.n_tendons,
                    float(robot.mechanics.tension_max))
    with jax.enable_x64(True):
        tensions = np.asarray(jax.vmap(least)(jnp.asarray(needed.reshape(len(needed), -1, 2))),
                              dtype=np.float64)
    tensions = tensions.reshape(*q.shape[:-1], robot.n_tendons)
    missed = np.linalg.norm(tensions @ per_tension.T - u, axis=-1)
    return tensions, missed
