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

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .robot import Robot
from .routing import routing_of


class TendonGroups(NamedTuple):
    """Static description of the tendon groups (numpy): tendons of group g are
    ``index[g]``, their pull directions r_i × e3 (in the xy plane) ``pull[g]`` (m), and
    ``pairs[g]`` the neighbouring pairs (i, j) around the circle (positions in the group)."""

    index: np.ndarray   # (G, m) tendon indices
    pull: np.ndarray    # (G, m, 2) m
    pairs: np.ndarray   # (m, 2)


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
