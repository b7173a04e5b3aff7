"""Distances between points, segments and capsules, closed forms in float64 numpy (the
verdict's, ``world.check``).

Internally points are triples of coordinate arrays (x, y, z), broadcast together: numpy
is several times faster on separate contiguous coordinates than on (…, 3) arrays
(``Xyz``; ``xyz``, ``dot``, ``sub`` and the ``point_segment`` / ``segment_segment``
kernels work on them). The public functions take (…, 3) arrays. The kernels take the
array module ``xp`` (numpy, or ``jax.numpy`` inside the verdict's float64 program,
``world._verdict_program``): the same formulas in both.
"""

from __future__ import annotations

from typing import Any

import numpy as np

Xyz = tuple[np.ndarray, np.ndarray, np.ndarray]


def xyz(points: Any) -> Xyz:
    p = np.asarray(points, dtype=float)
    return p[..., 0], p[..., 1], p[..., 2]


def dot(u: Xyz, v: Xyz) -> np.ndarray:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def sub(u: Xyz, v: Xyz) -> Xyz:
    return u[0] - v[0], u[1] - v[1], u[2] - v[2]


def point_segment_square(p: Xyz, a: Xyz, u: Xyz, uu: np.ndarray, xp: Any = np) -> np.ndarray:
    """Squared distance from points p to segments a + t·u, t ∈ [0, 1], with uu = |u|²."""
    w = sub(p, a)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = xp.where(uu > 0.0, xp.clip(dot(w, u) / uu, 0.0, 1.0), 0.0)
    dx, dy, dz = w[0] - t * u[0], w[1] - t * u[1], w[2] - t * u[2]
    return dx * dx + dy * dy + dz * dz


def point_segment(p: Xyz, a: Xyz, u: Xyz, uu: np.ndarray) -> np.ndarray:
    """Distance from points p to segments a + t·u, t ∈ [0, 1], with uu = |u|²."""
    return np.sqrt(point_segment_square(p, a, u, uu))


def segment_segment(p0: Xyz, p1: Xyz, q0: Xyz, q1: Xyz, xp: Any = np) -> np.ndarray:
    """Distance between segments p0–p1 and q0–q1 (see ``segment_distance``)."""
    d1, d2 = sub(p1, p0), sub(q1, q0)
    a, e = dot(d1, d1), dot(d2, d2)
    best = xp.minimum(xp.minimum(point_segment_square(p0, q0, d2, e, xp),
                                 point_segment_square(p1, q0, d2, e, xp)),
                      xp.minimum(point_segment_square(q0, p0, d1, a, xp),
                                 point_segment_square(q1, p0, d1, a, xp)))
    w = sub(p0, q0)
    b, c, f = dot(d1, d2), dot(d1, w), dot(d2, w)
    denominator = a * e - b * b
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        s = (b * f - c * e) / denominator
        t = (a * f - b * c) / denominator
    inside = (denominator > 0.0) & (s >= 0.0) & (s <= 1.0) & (t >= 0.0) & (t <= 1.0)
    if xp is not np or np.any(inside):      # numpy skips the work where no pair needs it
        s, t = xp.where(inside, s, 0.0), xp.where(inside, t, 0.0)
        gx = w[0] + s * d1[0] - t * d2[0]
        gy = w[1] + s * d1[1] - t * d2[1]
        gz = w[2] + s * d1[2] - t * d2[2]
        best = xp.where(inside, xp.minimum(best, gx * gx + gy * gy + gz * gz), best)
    return xp.sqrt(best)


def point_segment_distance(p: Any, a: Any, b: Any) -> np.ndarray:
    """Distance (m) from points p to segments a–b, all (…, 3) broadcast together; a
    zero-length segment is its point a."""
    a_ = xyz(a)
    u = sub(xyz(b), a_)
    return point_segment(xyz(p), a_, u, dot(u, u))


def segment_distance(p0: Any, p1: Any, q0: Any, q1: Any) -> np.ndarray:
    """Distance (m) between segments p0–p1 and q0–q1, all (…, 3) broadcast together.

    |p0 + s·(p1 − p0) − q0 − t·(q1 − q0)| is convex in (s, t) ∈ [0, 1]², so its minimum
    lies either on the square's boundary (an end point against the other segment: four
    point–segment distances) or at the stationary point of the two lines. The latter is
    taken only where it falls inside the square; parallel and zero-length segments (no
    unique stationary point) are covered by the boundary. Every candidate is the length
    of a real pair of points, so rounding in a nearly parallel, ill-conditioned
    stationary point can only raise that candidate, never undercut the boundary."""
    return segment_segment(xyz(p0), xyz(p1), xyz(q0), xyz(q1))


def capsule_capsule_distance(a0: Any, b0: Any, r0: Any, a1: Any, b1: Any,
                             r1: Any) -> np.ndarray:
    """Signed distance (m) between capsules of radius r0 around a0–b0 and r1 around a1–b1
    (broadcast, (…, 3) points): the segment distance minus both radii, exact when they
    are apart. A negative value says they overlap (exactly where the sign changes), and
    moving them apart along their closest-point direction by its magnitude separates
    them; a shorter separating move may exist (e.g. off a segment's end)."""
    return segment_distance(a0, b0, a1, b1) - r0 - r1


def capsule_sphere_distance(a: np.ndarray, b: np.ndarray, radius: float, centre: np.ndarray,
                            sphere_radius: float) -> float:
    """Exact signed distance (m) between the capsule of ``radius`` around segment a–b and a
    sphere: the distance from the centre to the segment minus both radii.

    Used instead of fcl for spheres: fcl's penetration query (EPA) was seen to never
    return when a sphere's centre lies on the capsule's axis."""
    ab = b - a
    denominator = float(ab @ ab)
    t = 0.0 if denominator <= 0.0 else min(max(float((centre - a) @ ab) / denominator, 0.0), 1.0)
    return float(np.linalg.norm(centre - (a + t * ab))) - radius - sphere_radius
