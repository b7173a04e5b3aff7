"""Signed distances between a body sphere and one obstacle part, written once on entries.

Each function takes an ``Ops`` backend (see ``cr_nlp.model._ops``), the body sphere's
centre as three entries and its radius, and the part's parameters as entries, and
returns the signed distance in metres (negative: penetration depth). With JAX the
entries broadcast, so one call evaluates every (configuration, body sphere, part)
triple; with CasADi they are ``SX`` scalars and plain floats.

Exactness (the clearance's error budget, see ``clearance.py``):

- sphere, capsule, box, cylinder: exact signed distances.
- convex polytope: ``max_f (n_f·c − b_f) − r``, a lower bound of the true distance,
  exact wherever the closest point lies on a face (and inside the part), smaller near
  edges and corners. With ``smoothing`` μ > 0 the max becomes a smooth max shifted
  down by its largest overshoot, so it stays a lower bound and is below the max by at
  most ``smooth_max_shift(F, μ)``.
"""

from __future__ import annotations

import math
from typing import Any

from ..model._ops import Ops

Vec = tuple[Any, Any, Any]
Rot = tuple[Any, Any, Any, Any, Any, Any, Any, Any, Any]


def safe_norm(ops: Ops, x: Any, y: Any, z: Any = 0.0) -> Any:
    """‖(x, y, z)‖ with a zero (not NaN) derivative at the origin."""
    s = x * x + y * y + z * z
    positive = s > 0.0
    return ops.where(positive, ops.sqrt(ops.where(positive, s, 1.0)), 0.0)


def _abs(ops: Ops, x: Any) -> Any:
    return ops.fmax(x, -x)


def _to_local(rot: Rot, origin: Vec, c: Vec) -> Vec:
    """Rᵀ(c − origin): a world point in the frame of a part (R row-major, world-from-part)."""
    dx, dy, dz = c[0] - origin[0], c[1] - origin[1], c[2] - origin[2]
    return (rot[0] * dx + rot[3] * dy + rot[6] * dz,
            rot[1] * dx + rot[4] * dy + rot[7] * dz,
            rot[2] * dx + rot[5] * dy + rot[8] * dz)


# ---------------------------------------------------------------- primitives

def sphere_to_sphere(ops: Ops, c: Vec, r: Any, center: Vec, radius: Any) -> Any:
    """Exact: ‖c − center‖ − radius − r."""
    return safe_norm(ops, c[0] - center[0], c[1] - center[1], c[2] - center[2]) - radius - r


def sphere_to_capsule(ops: Ops, c: Vec, r: Any, a: Vec, b: Vec, radius: Any) -> Any:
    """Exact: distance from c to the segment ab, minus both radii."""
    ab = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
    ac = (c[0] - a[0], c[1] - a[1], c[2] - a[2])
    t = (ac[0] * ab[0] + ac[1] * ab[1] + ac[2] * ab[2]) / (
        ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2])
    t = ops.fmin(ops.fmax(t, 0.0), 1.0)
    return safe_norm(ops, ac[0] - t * ab[0], ac[1] - t * ab[1], ac[2] - t * ab[2]) - radius - r


def sphere_to_box(ops: Ops, c: Vec, r: Any, center: Vec, rot: Rot, half: Vec) -> Any:
    """Exact signed distance to a box (rotation world-from-box, half sizes in metres)."""
    p = _to_local(rot, center, c)
    q = tuple(_abs(ops, p[i]) - half[i] for i in range(3))
    outside = safe_norm(ops, ops.fmax(q[0], 0.0), ops.fmax(q[1], 0.0), ops.fmax(q[2], 0.0))
    inside = ops.fmin(ops.fmax(q[0], ops.fmax(q[1], q[2])), 0.0)
    return outside + inside - r


def sphere_to_cylinder(ops: Ops, c: Vec, r: Any, center: Vec, rot: Rot, radius: Any,
                       half_length: Any) -> Any:
    """Exact signed distance to a solid cylinder (axis = third column of ``rot``)."""
    p = _to_local(rot, center, c)
    radial = safe_norm(ops, p[0], p[1]) - radius
    axial = _abs(ops, p[2]) - half_length
    outside = safe_norm(ops, ops.fmax(radial, 0.0), ops.fmax(axial, 0.0))
    inside = ops.fmin(ops.fmax(radial, axial), 0.0)
    return outside + inside - r


def smooth_max(ops: Ops, a: Any, b: Any, smoothing: float) -> Any:
    """½(a + b + √((a − b)² + μ²)): smooth, and max(a, b) ≤ it ≤ max(a, b) + μ/2."""
    return 0.5 * (a + b + ops.sqrt((a - b) * (a - b) + smoothing * smoothing))


def smooth_max_shift(count: int, smoothing: float) -> float:
    """The largest overshoot of ``tree_max`` over the true max of ``count`` values:
    μ/2 per level of the pairwise tree, log₂(count) levels (metres)."""
    return 0.0 if smoothing <= 0.0 or count <= 1 else math.log2(count) * smoothing / 2


def tree_max(ops: Ops, values: Any, count: int, smoothing: float = 0.0) -> Any:
    """The max of ``count`` (a power of two) values on the last axis (JAX) or in a column
    (CasADi), by halving: entries i and i + count/2 are combined at each level. Smooth
    if μ = ``smoothing`` > 0, then between the max and ``smooth_max_shift(count, μ)`` above."""
    if count & (count - 1):
        raise ValueError(f"tree_max needs a power-of-two count, got {count}")
    while count > 1:
        half = count // 2
        a, b = ops.entry(values, slice(0, half)), ops.entry(values, slice(half, count))
        values = smooth_max(ops, a, b, smoothing) if smoothing > 0 else ops.fmax(a, b)
        count = half
    return ops.entry(values, 0)


def sphere_to_convex(ops: Ops, c: Vec, r: Any, planes: tuple[Any, Any, Any, Any], count: int,
                     smoothing: float = 0.0) -> Any:
    """Lower bound of the signed distance to the convex part ∩_f {n_f·x ≤ b_f}.

    ``planes`` = (nx, ny, nz, b), each holding the part's ``count`` face planes (unit
    outward normals) on its last axis (JAX) or as a column (CasADi); ``count`` is a power
    of two (pad by repeating a plane). The result is max_f(n_f·c − b_f) − r, or with
    μ = ``smoothing`` > 0 its smooth tree max minus ``smooth_max_shift(count, μ)``: in
    both cases never above the true distance.
    """
    nx, ny, nz, b = planes
    values = nx * c[0] + ny * c[1] + nz * c[2] - b
    return tree_max(ops, values, count, smoothing) - smooth_max_shift(count, smoothing) - r
