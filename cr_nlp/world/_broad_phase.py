"""Bounding balls of a scene's parts: the broad phase of the batched clearance terms.

A body sphere's nearest obstacle is one of the few parts whose bounding ball is nearest
to it; the optimisers' clearance terms (``world._clearance_groups``) evaluate the exact
sphere-to-part distance only for those ``near`` parts instead of for every part
(57 convex parts of 16 face planes in the bundled shelf). The balls: a sphere is its
own, a box's is centred with radius ‖half size‖, a capsule's and a cylinder's at the
axis midpoint, a convex part's at its vertices' bounding-box centre with radius the
largest vertex distance from it.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from .scene import BoxPart, CapsulePart, ConvexPart, CylinderPart, Scene, SpherePart


class PartBalls(NamedTuple):
    """Bounding balls per part kind, in ``SceneArrays`` kind order (sphere, box, capsule,
    cylinder, convex); each entry is (centres (P, 3) m, radii (P,) m)."""

    sphere: tuple[Any, Any]
    box: tuple[Any, Any]
    capsule: tuple[Any, Any]
    cylinder: tuple[Any, Any]
    convex: tuple[Any, Any]


def _ball(part: Any) -> tuple[np.ndarray, float]:
    if isinstance(part, SpherePart):
        return np.asarray(part.center, float), float(part.radius)
    if isinstance(part, BoxPart):
        return np.asarray(part.center, float), float(np.linalg.norm(part.half_size))
    if isinstance(part, (CapsulePart, CylinderPart)):
        a, b = np.asarray(part.a, float), np.asarray(part.b, float)
        half, r = 0.5 * float(np.linalg.norm(b - a)), float(part.radius)
        return 0.5 * (a + b), (half + r if isinstance(part, CapsulePart) else math.hypot(half, r))
    if isinstance(part, ConvexPart):
        v = np.asarray(part.vertices, float)
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        return centre, float(np.max(np.linalg.norm(v - centre, axis=1)))
    raise TypeError(f"unknown part type {type(part).__name__}")


def part_balls(scene: Scene, dtype: Any = None) -> PartBalls:
    """The bounding ball (centre m, radius m) of every part of ``scene``, grouped by kind
    in ``SceneArrays`` order, as JAX arrays of ``dtype`` (default JAX's default float)."""
    kinds = (SpherePart, BoxPart, CapsulePart, CylinderPart, ConvexPart)
    dtype = dtype or jnp.result_type(float)
    out = []
    for kind in kinds:
        balls = [_ball(p) for p in scene.parts if isinstance(p, kind)]
        centres = np.array([c for c, _ in balls], float).reshape(-1, 3)
        radii = np.array([r for _, r in balls], float)
        out.append((jnp.asarray(centres, dtype), jnp.asarray(radii, dtype)))
    return PartBalls(*out)
