"""Rotations and rigid transforms (SO(3), SE(3)): the one home of these helpers.

On entries (see ``_ops``), for every backend: a rotation is a row-major tuple of nine
entries, a vector a tuple of three, a transform a ``(rotation, translation)`` pair.
Quaternions are ``(w, x, y, z)``. At the bottom, the few JAX array forms the solvers
use. Angles are in radians, translations in metres.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._ops import JAX, Ops, polynomial, safe_where

Vec = tuple[Any, Any, Any]
Rot = tuple[Any, Any, Any, Any, Any, Any, Any, Any, Any]
Transform = tuple[Rot, Vec]

# Below this squared angle (rad²) se3_log's coefficient c(θ) uses its Taylor series.
SERIES_BELOW = 1e-2


# ---------------------------------------------------------------- smooth scalars

_SINC = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(8))
_VERSINE = tuple((-1.0) ** k / math.factorial(2 * k + 2) for k in range(8))
_DEFICIT = tuple((-1.0) ** k / math.factorial(2 * k + 3) for k in range(8))
_SINC_SLOPE = tuple(k * (-1.0) ** k / math.factorial(2 * k + 1) for k in range(1, 9))
_VERSINE_SLOPE = tuple(k * (-1.0) ** k / math.factorial(2 * k + 2) for k in range(1, 9))

BEND_SERIES_BELOW = 0.1
"""Below this t = θ² (rad²) ``bend_coefficients`` uses its Taylor series (eight terms:
truncation error < 1e-17 there); above it the closed forms lose at most ~3e-14 relative
to cancellation in float64."""


class Bend(NamedTuple):
    """The smooth functions of t = θ² (rad²) behind a constant-curvature arc."""

    a: Any
    """A = sin θ/θ."""
    b: Any
    """B = (1 − cos θ)/θ²."""
    c: Any
    """C = (θ − sin θ)/θ³ = (1 − A)/t."""
    da: Any = None
    """A′(t) = (cos θ − A)/(2t) (with ``slopes``)."""
    db: Any = None
    """B′(t) = (A − 2B)/(2t) (with ``slopes``)."""


def bend_coefficients(ops: Ops, t: Any, slopes: bool = False) -> Bend:
    """A, B, C (and with ``slopes`` A′, B′) of t = θ² from one sine and cosine of θ/2 and
    one series/closed-form switch, finite with finite derivatives at t = 0. One call per
    arc instead of one per coefficient keeps the compiled programs small."""
    series_below = t < BEND_SERIES_BELOW
    safe = ops.where(series_below, 1.0, t)
    half = 0.5 * ops.sqrt(safe)
    sin_h, cos_h = ops.sin(half), ops.cos(half)
    sinc_h = sin_h / half
    a = sinc_h * cos_h  # sin θ/θ = sin(θ/2)·cos(θ/2)/(θ/2)
    b = 0.5 * sinc_h * sinc_h  # (1 − cos θ)/θ² = ½·sinc²(θ/2): no cancellation
    exact = [a, b, (1.0 - a) / safe]
    tables = [_SINC, _VERSINE, _DEFICIT]
    if slopes:
        cos_theta = 1.0 - 2.0 * sin_h * sin_h
        exact += [(cos_theta - a) / (2.0 * safe), (a - 2.0 * b) / (2.0 * safe)]
        tables += [_SINC_SLOPE, _VERSINE_SLOPE]
    # numpy evaluates every entry it is given (no dead-code elimination, no fusion): it
    # evaluates the series only where they are used (``_numpy_series_where``).
    lazy = ops.name == "numpy" and np.ndim(series_below) > 0
    series = [] if lazy else ops.polynomials(t, tables)
    if lazy:
        return Bend(*_numpy_series_where(series_below, t, tables, exact))
    # Computed once (JAX: an optimisation barrier), not again inside every consumer.
    return ops.materialize(Bend(*(ops.where(series_below, s, e)
                                  for s, e in zip(series, exact, strict=True))))


def _numpy_series_where(series_below: np.ndarray, t: Any, tables: list[tuple[float, ...]],
                        exact: list[Any]) -> list[np.ndarray]:
    """``np.where(series_below, polynomial(t, table), exact)`` per table, each series
    evaluated only on the entries below the switch: the same numbers (elementwise
    arithmetic), a fraction of the work where most arcs bend past the series range."""
    below = np.nonzero(series_below)
    t_below = np.broadcast_to(t, series_below.shape)[below]
    out = []
    for table, value in zip(tables, exact, strict=True):
        value = np.array(np.broadcast_to(value, series_below.shape), dtype=float)
        value[below] = polynomial(t_below, table)
        out.append(value)
    return out


# ---------------------------------------------------------------- rotation algebra

def rot_identity() -> Rot:
    return (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def rot_mul(a: Rot, b: Rot) -> Rot:
    return tuple(
        a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j]
        for i in range(3)
        for j in range(3)
    )  # type: ignore[return-value]


def rot_transpose(a: Rot) -> Rot:
    return (a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8])


def rot_hat(w: Vec) -> Rot:
    """[w]×, the cross-product matrix of w: [w]×·v = w × v."""
    return (0.0, -w[2], w[1], w[2], 0.0, -w[0], -w[1], w[0], 0.0)


def vec_cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def vec_add(a: Vec, b: Vec) -> Vec:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def vec_sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def rot_apply(r: Rot, v: Vec) -> Vec:
    return (
        r[0] * v[0] + r[1] * v[1] + r[2] * v[2],
        r[3] * v[0] + r[4] * v[1] + r[5] * v[2],
        r[6] * v[0] + r[7] * v[1] + r[8] * v[2],
    )


def transform_compose(a: Transform, b: Transform) -> Transform:
    """a · b."""
    ra, pa = a
    rb, pb = b
    moved = rot_apply(ra, pb)
    return rot_mul(ra, rb), (pa[0] + moved[0], pa[1] + moved[1], pa[2] + moved[2])


def transform_apply(a: Transform, v: Vec) -> Vec:
    r, p = a
    moved = rot_apply(r, v)
    return (p[0] + moved[0], p[1] + moved[1], p[2] + moved[2])


def transform_between(a: Transform, b: Transform) -> Transform:
    """a⁻¹ · b: the pose of b seen from a."""
    ra, pa = a
    rb, pb = b
    rat = rot_transpose(ra)
    return rot_mul(rat, rb), rot_apply(rat, (pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2]))


# ---------------------------------------------------------------- quaternions

def rot_from_quat(q: tuple[Any, Any, Any, Any]) -> Rot:
    """Rotation of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return (
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


def quat_from_rot(ops: Ops, r: Rot) -> tuple[Any, Any, Any, Any]:
    """Unit quaternion (w, x, y, z) with w ≥ 0 (Shepperd's method, branch-free form)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = ops.materialize(r)
    trace = r00 + r11 + r22
    # Four candidate formulas; the one with the largest 4·q_i² ≥ 1 is well conditioned.
    cand_w = 1.0 + trace
    cand_x = 1.0 + r00 - r11 - r22
    cand_y = 1.0 - r00 + r11 - r22
    cand_z = 1.0 - r00 - r11 + r22

    def from_w(c: Any) -> tuple[Any, Any, Any, Any]:
        s = 0.5 / ops.sqrt(ops.fmax(c, 1e-12))
        return 0.25 / s, (r21 - r12) * s, (r02 - r20) * s, (r10 - r01) * s

    def from_x(c: Any) -> tuple[Any, Any, Any, Any]:
        s = 0.5 / ops.sqrt(ops.fmax(c, 1e-12))
        return (r21 - r12) * s, 0.25 / s, (r01 + r10) * s, (r02 + r20) * s

    def from_y(c: Any) -> tuple[Any, Any, Any, Any]:
        s = 0.5 / ops.sqrt(ops.fmax(c, 1e-12))
        return (r02 - r20) * s, (r01 + r10) * s, 0.25 / s, (r12 + r21) * s

    def from_z(c: Any) -> tuple[Any, Any, Any, Any]:
        s = 0.5 / ops.sqrt(ops.fmax(c, 1e-12))
        return (r10 - r01) * s, (r02 + r20) * s, (r12 + r21) * s, 0.25 / s

    qw, qx, qy, qz = from_w(cand_w), from_x(cand_x), from_y(cand_y), from_z(cand_z)
    use_w = (cand_w >= cand_x) * (cand_w >= cand_y) * (cand_w >= cand_z)
    use_x = (cand_x >= cand_y) * (cand_x >= cand_z)
    use_y = cand_y >= cand_z

    def pick(i: int) -> Any:
        return ops.where(use_w, qw[i], ops.where(use_x, qx[i], ops.where(use_y, qy[i], qz[i])))

    w, x, y, z = ops.materialize((pick(0), pick(1), pick(2), pick(3)))
    sign = ops.where(w < 0.0, -1.0, 1.0)
    return w * sign, x * sign, y * sign, z * sign


# ---------------------------------------------------------------- logarithms

def so3_log(ops: Ops, r: Rot) -> Vec:
    """Rotation vector ω (radians) with exp([ω]×) = r and ‖ω‖ ≤ π."""
    w, x, y, z = quat_from_rot(ops, r)
    n2 = x * x + y * y + z * z

    def series(n2: Any) -> Any:  # 2·atan2(n, w)/n for small n, w ≈ 1
        w2 = w * w
        return 2.0 / w * (1.0 - n2 / (3.0 * w2) + n2 * n2 / (5.0 * w2 * w2))

    def exact(n2: Any) -> Any:
        n = ops.sqrt(n2)
        return 2.0 * ops.atan2(n, w) / n

    scale = safe_where(ops, n2 < 1e-6, series, exact, n2, 1.0)
    return x * scale, y * scale, z * scale


def se3_log(ops: Ops, t: Transform) -> tuple[Any, Any, Any, Any, Any, Any]:
    """The 6-vector (v, ω) = log(T): v in metres, ω in radians.

    v = V(ω)⁻¹ p with V⁻¹ = I − ½[ω]× + c(θ)[ω]×², c = (1 − θ sin θ / (2(1 − cos θ)))/θ².
    """
    r, p = ops.materialize(t)
    wx, wy, wz = ops.materialize(so3_log(ops, r))
    th2 = wx * wx + wy * wy + wz * wz

    def series(th2: Any) -> Any:
        return 1.0 / 12.0 + th2 / 720.0 + th2 * th2 / 30240.0

    bend = bend_coefficients(ops, th2)

    def exact(th2_safe: Any) -> Any:  # A, B are smooth at 0: only the division needs a safe t
        return (1.0 - bend.a / (2.0 * bend.b)) / th2_safe

    c = safe_where(ops, th2 < SERIES_BELOW, series, exact, th2, 1.0)
    # [ω]× p and [ω]×² p = ω (ω·p) − θ² p
    cross = (wy * p[2] - wz * p[1], wz * p[0] - wx * p[2], wx * p[1] - wy * p[0])
    dot = wx * p[0] + wy * p[1] + wz * p[2]
    v = tuple(
        p[i] - 0.5 * cross[i] + c * ((wx, wy, wz)[i] * dot - th2 * p[i]) for i in range(3)
    )
    return v[0], v[1], v[2], wx, wy, wz


def so3_exp(ops: Ops, w: Vec) -> Rot:
    """Rotation exp([ω]×) of a rotation vector ω (radians), by Rodrigues' formula."""
    wx, wy, wz = w
    a, b, _, _, _ = bend_coefficients(ops, wx * wx + wy * wy + wz * wz)
    k = rot_hat(w)
    k2 = rot_mul(k, k)
    eye = rot_identity()
    return tuple(eye[i] + a * k[i] + b * k2[i] for i in range(9))  # type: ignore[return-value]


def se3_exp(ops: Ops, xi: tuple[Any, Any, Any, Any, Any, Any]) -> Transform:
    """Transform exp(ξ) of a twist ξ = (v, ω) (metres, radians); inverse of ``se3_log``."""
    v = xi[:3]
    w = xi[3:]
    a, b, c, _, _ = bend_coefficients(ops, w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    k = rot_hat(w)
    k2 = rot_mul(k, k)
    eye = rot_identity()
    rot = tuple(eye[i] + a * k[i] + b * k2[i] for i in range(9))
    v_mat = tuple(eye[i] + b * k[i] + c * k2[i] for i in range(9))
    return rot, rot_apply(v_mat, v)  # type: ignore[return-value, arg-type]


# ---------------------------------------------------------------- JAX array forms


def hat(w: jax.Array) -> jax.Array:
    """(…, 3) vectors → (…, 3, 3) cross-product matrices [w]×."""
    zero = jnp.zeros_like(w[..., 0])
    return jnp.stack([jnp.stack([zero, -w[..., 2], w[..., 1]], -1),
                      jnp.stack([w[..., 2], zero, -w[..., 0]], -1),
                      jnp.stack([-w[..., 1], w[..., 0], zero], -1)], -2)


def rotation_log(rotation: jax.Array) -> jax.Array:
    """Rotation vector (3,) rad of one rotation matrix (3, 3) (``so3_log``), its dtype."""
    entries = tuple(rotation[i, j] for i in range(3) for j in range(3))
    return jnp.stack(so3_log(JAX, entries)).astype(rotation.dtype)


def so3_right_jacobian_inverse(e: jax.Array) -> jax.Array:
    """J_r⁻¹(e) = I + ½[e]× + c(θ)[e]×², c = 1/θ² − (1 + cos θ)/(2θ sin θ): the
    derivative of log(R·exp([ω]×)) with respect to ω at ω = 0, R = exp([e]×), e (3,) rad.

    Close to θ = π the exact coefficient diverges; θ is capped at 3 rad there, which
    keeps a descent direction for a least-squares solver (not the exact derivative)."""
    th2 = jnp.sum(e * e)
    theta = jnp.sqrt(jnp.maximum(th2, 1e-12))
    theta_c = jnp.minimum(theta, 3.0)
    exact = 1.0 / (theta_c * theta_c) - (1.0 + jnp.cos(theta_c)) / (
        2.0 * theta_c * jnp.sin(theta_c))
    c = jnp.where(th2 < 1e-4, 1.0 / 12.0 + th2 / 720.0, exact)
    k = hat(e)
    return jnp.eye(3, dtype=e.dtype) + 0.5 * k + c * k @ k


def _series(t: jax.Array, coefficients: tuple[float, ...]) -> jax.Array:
    out = jnp.zeros_like(t) + coefficients[-1]
    for c in coefficients[-2::-1]:
        out = c + t * out
    return out


def se3_left_jacobian_inverse(xi: jax.Array) -> jax.Array:
    """J_l⁻¹(ξ) (6, 6) of a twist ξ = (v, ω) (3,) m and (3,) rad (``se3_log``'s order):
    log(exp(δ)·exp(ξ)) = ξ + J_l⁻¹(ξ)·δ + O(δ²). Closed form (Barfoot's Q(v, ω)), with
    Taylor branches near θ = ‖ω‖ = 0; finite up to θ = π.

    J_l = [[J, Q], [0, J]] with J the SO(3) left Jacobian, so
    J_l⁻¹ = [[J⁻¹, −J⁻¹·Q·J⁻¹], [0, J⁻¹]], J⁻¹ = I − ½[ω]× + c₀[ω]×²."""
    v, w = xi[:3], xi[3:]
    t = jnp.sum(w * w)
    small = t < 1.0
    safe = jnp.where(small, 1.0, t)
    theta = jnp.sqrt(safe)
    a = jnp.sin(theta) / theta                                  # sin θ/θ
    b = (1.0 - jnp.cos(theta)) / safe                           # (1 − cos θ)/θ²
    # (−t)ᵏ/(2k+3)!, (−t)ᵏ/(2k+4)!, (−1)ᵏ⁺¹ k tᵏ⁻¹/(2k+3)!, k from 0 (from 1 for the last)
    c1 = jnp.where(small, _series(t, tuple((-1.0) ** k / math.factorial(2 * k + 3)
                                          for k in range(9))), (1.0 - a) / safe)
    c2 = jnp.where(small, _series(t, tuple((-1.0) ** k / math.factorial(2 * k + 4)
                                          for k in range(9))), (1.0 - 2.0 * b) / (2.0 * safe))
    c3 = jnp.where(small, _series(t, tuple((-1.0) ** (k + 1) * k / math.factorial(2 * k + 3)
                                          for k in range(1, 10))),
                   (3.0 * c1 - b) / (2.0 * safe))
    # c₀ = 1/θ² − (1 + cos θ)/(2θ sin θ) = (1 − A/(2B))/θ², 1/12 at θ = 0.
    # Its series converges slowly (ratio ≈ t/π²): used only below t = 0.1 (error < 1e-14).
    tiny = t < 0.1
    safe_tiny = jnp.where(tiny, 1.0, t)
    theta_tiny = jnp.sqrt(safe_tiny)
    ratio = jnp.sin(theta_tiny) * theta_tiny / (2.0 * (1.0 - jnp.cos(theta_tiny)))  # A/(2B)
    c0 = jnp.where(tiny, _series(t, (1.0 / 12.0, 1.0 / 720.0, 1.0 / 30240.0,
                                     1.0 / 1209600.0, 1.0 / 47900160.0)),
                   (1.0 - ratio) / safe_tiny)
    wh, vh = hat(w), hat(v)
    wv, vw, wvw = wh @ vh, vh @ wh, wh @ vh @ wh
    q = (0.5 * vh + c1 * (wv + vw + wvw) + c2 * (wh @ wv + vw @ wh - 3.0 * wvw)
         + c3 * (wvw @ wh + wh @ wvw))
    eye = jnp.eye(3, dtype=xi.dtype)
    j_inv = eye - 0.5 * wh + c0 * wh @ wh
    top = jnp.concatenate([j_inv, -j_inv @ q @ j_inv], axis=1)
    bottom = jnp.concatenate([jnp.zeros((3, 3), xi.dtype), j_inv], axis=1)
    return jnp.concatenate([top, bottom], axis=0)
