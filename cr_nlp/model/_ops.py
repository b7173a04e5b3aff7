"""The two numeric backends behind the one kinematic model.

The model (kinematics, tendons, pose error, clearance) is written once, as
scalar-level code on *entries*: a 3×3 rotation is a tuple of nine entries, a
point a tuple of three. An entry is whatever the backend calls a number:

- JAX: an array of any batch shape; elementwise arithmetic broadcasts, so the
  same code is batched over configurations (and over points along a segment,
  which live on one extra trailing axis). XLA fuses the elementwise graph into
  a few tight loops.
- CasADi: an ``SX`` scalar (or a column vector of points along a segment).

Only the handful of functions below differ between the backends; everything
else is ordinary Python arithmetic.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np


@dataclass(frozen=True)
class Ops:
    """The functions the model needs beyond ``+ - * /``."""

    name: str
    sin: Callable[[Any], Any]
    cos: Callable[[Any], Any]
    sqrt: Callable[[Any], Any]
    atan2: Callable[[Any, Any], Any]
    where: Callable[[Any, Any, Any], Any]
    fmax: Callable[[Any, Any], Any]
    fmin: Callable[[Any, Any], Any]
    entry: Callable[[Any, int], Any]
    """Entry i of the last axis of a vector (JAX: ``x[..., i]``; CasADi: ``x[i]``)."""
    stack: Callable[[list[Any]], Any]
    """Entries back into a vector on the last axis (JAX) or a column (CasADi)."""
    along: Callable[[Any], Any]
    """Give an entry one trailing axis so it broadcasts against per-point entries."""
    fractions: Callable[[np.ndarray], Any]
    """A constant vector of arc fractions, laid out for per-point entries."""
    per_point: Callable[[Any, Any], Any]
    """An entry with a segment axis (``stack``) times the arc fractions: one entry per
    (segment, point) (JAX: ``x[..., None] * s``; CasADi: the n × k outer product)."""
    points_of: Callable[[Any, int], Any]
    """Segment m's points of a ``per_point`` entry, laid out as ``along`` entries."""
    stack_points: Callable[[list[tuple[Any, Any, Any]]], Any]
    """Stack per-point (x, y, z) entries of each segment into an (N, 3) array."""
    materialize: Callable[[Any], Any]
    """Compute a tuple of entries here. On JAX an optimisation barrier: without it XLA's
    fusion recomputes shared subexpressions inside every consumer, which made the
    derivative of the pose error ~100× slower. Identity on CasADi."""
    polynomials: Callable[[Any, list[tuple[float, ...]]], list[Any]]
    """Σₖ cₖ·tᵏ of one entry t for each table of coefficients c₀, c₁, … (Horner form).
    JAX: the tables side by side on one trailing axis (one Horner loop, not one per
    table: the compiled programs that evaluate many arcs stay smaller)."""


def polynomial(t: Any, coefficients: tuple[float, ...]) -> Any:
    """Σₖ cₖ·tᵏ in Horner form (plain arithmetic: every backend)."""
    out = coefficients[-1]
    for c in coefficients[-2::-1]:
        out = c + t * out
    return out


def _polynomials(t: Any, tables: list[tuple[float, ...]]) -> list[Any]:
    return [polynomial(t, c) for c in tables]


def _jax_polynomials(t: Any, tables: list[tuple[float, ...]]) -> list[Any]:
    t = jnp.asarray(t)[..., None]
    rows = np.array(tables, dtype=float).T           # (degree + 1, tables)
    out = jnp.asarray(rows[-1], t.dtype)
    for row in rows[-2::-1]:
        out = jnp.asarray(row, t.dtype) + t * out
    return [out[..., i] for i in range(len(tables))]


def _jax_stack_points(per_segment: list[tuple[Any, Any, Any]]) -> Any:
    return jnp.concatenate([jnp.stack(xyz, axis=-1) for xyz in per_segment], axis=-2)


def _jax_materialize(entries: Any) -> Any:
    leaves, tree = jax.tree_util.tree_flatten(entries)
    packed = jax.lax.optimization_barrier(jnp.stack(jnp.broadcast_arrays(*leaves), axis=-1))
    return jax.tree_util.tree_unflatten(tree, [packed[..., i] for i in range(len(leaves))])


def _casadi_stack_points(per_segment: list[tuple[Any, Any, Any]]) -> Any:
    return ca.vertcat(*[ca.horzcat(*xyz) for xyz in per_segment])


JAX = Ops(
    name="jax",
    sin=jnp.sin,
    cos=jnp.cos,
    sqrt=jnp.sqrt,
    atan2=jnp.arctan2,
    where=jnp.where,
    fmax=jnp.maximum,
    fmin=jnp.minimum,
    entry=lambda x, i: x[..., i],
    stack=lambda xs: jnp.stack(jnp.broadcast_arrays(*xs), axis=-1),
    along=lambda x: jnp.asarray(x)[..., None],
    fractions=lambda s: jnp.asarray(s),
    per_point=lambda x, s: x[..., None] * s,
    points_of=lambda x, m: x[..., m, :],
    stack_points=_jax_stack_points,
    materialize=_jax_materialize,
    polynomials=_jax_polynomials,
)

CASADI = Ops(
    name="casadi",
    sin=ca.sin,
    cos=ca.cos,
    sqrt=ca.sqrt,
    atan2=ca.atan2,
    where=ca.if_else,
    fmax=ca.fmax,
    fmin=ca.fmin,
    entry=lambda x, i: x[i],
    stack=lambda xs: ca.vertcat(*xs),
    along=lambda x: x,
    fractions=lambda s: ca.DM(np.asarray(s, dtype=float)),
    per_point=lambda x, s: ca.mtimes(x, s.T),
    points_of=lambda x, m: x[m, :].T,
    stack_points=_casadi_stack_points,
    materialize=lambda x: x,
    polynomials=_polynomials,
)


def safe_where(ops: Ops, condition: Any, series: Callable[[Any], Any],
               exact: Callable[[Any], Any], x: Any, safe_value: float) -> Any:
    """``series(x)`` where ``condition`` holds, else ``exact(x)``, with finite derivatives.

    Both backends evaluate both branches (and differentiate both), so the exact
    branch is fed a harmless ``safe_value`` wherever the series is used: the
    classic double-``where`` that keeps NaN out of gradients at the singular point.
    """
    x_exact = ops.where(condition, safe_value, x)
    return ops.where(condition, series(x), exact(x_exact))


# float64 kinematics for verdicts and figures, independent of JAX's precision setting.
def _numpy_stack_points(per_segment: list[tuple[Any, Any, Any]]) -> np.ndarray:
    return np.concatenate([np.stack(np.broadcast_arrays(*xyz), axis=-1) for xyz in per_segment],
                          axis=-2)


NUMPY = Ops(
    name="numpy",
    sin=np.sin,
    cos=np.cos,
    sqrt=np.sqrt,
    atan2=np.arctan2,
    where=np.where,
    fmax=np.maximum,
    fmin=np.minimum,
    entry=lambda x, i: x[..., i],
    stack=lambda xs: np.stack(np.broadcast_arrays(*xs), axis=-1),
    along=lambda x: np.asarray(x)[..., None],
    fractions=lambda s: np.asarray(s, dtype=float),
    per_point=lambda x, s: np.asarray(x)[..., None] * s,
    points_of=lambda x, m: x[..., m, :],
    stack_points=_numpy_stack_points,
    materialize=lambda x: x,
    polynomials=_polynomials,
)
