"""Which equilibrium, how many, and is it stable: the branch checks of the Cosserat statics.

Stability. The shape is a clamped–free rod under dead loads (tip and point wrenches,
gravity, distributed forces) and constant tendon tensions. With N(s) fixed by the loads, a
perturbation of the equilibrium is a Jacobi field started by a change δM(0) of the base
moment; at arc length s its moment is δM(s) = Y(s)δM(0). The test is Till & Rucker's
(IEEE T-RO 2017) for Cosserat rods: the equilibrium is stable when det Y(s) does not
change sign on (0, L] (a conjugate point is an s where a Jacobi field meets the free end's
condition δM = 0). Y comes from four passes (forward differences in M(0)) that keep the
path, read at every grid point. Two conjugate points at one s (a straight rod under an
axial load buckles in x and y at once: det Y = cos²(ks) only touches zero), or two
between neighbouring grid points, keep the sign: they leave Y with two negative real
eigenvalues, which the test also counts as unstable.

How many equilibria. More than one equilibrium needs loads of the order of a buckling
load; ``load_parameter`` compares the loads with the clamped–free column's: Euler's
P_cr = π²EI/(4s²) for each point force at arc length s (the tip force at L, the disks'
weights) and Greenhill's heavy column, q_cr = 7.837·EI/L³, for the loads per metre. Below
1 a case counts as unique (its check is skipped); at 1 or more it is doubtful and more
starts are solved. Units: metres, radians, newtons, N·m.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._rod import CaseLoads, StaticsConfig, _integrate, _Layout

EULER_CLAMPED_FREE = np.pi ** 2 / 4
"""P_cr L² / (E I) of a clamped–free column under an axial end load (Euler)."""
GREENHILL_CLAMPED_FREE = 7.837
"""q_cr L³ / (E I) of a clamped–free column under its own uniform weight (Greenhill)."""
DOUBTFUL = 1.0
"""Load parameter from which a case's answer is checked against other equilibria."""


def load_parameter(lay: _Layout, loads: Any, ei: float) -> np.ndarray:
    """(B,) the loads as a fraction of a clamped–free column's buckling loads: every point
    force F at arc length s counts |F| s² / (π²EI/4), a force per metre q counts
    q L³ / (7.837 EI). ``loads`` is a ``model.loads.StaticLoads``; EI in N·m²."""
    length = float(lay.arc_length[-1])
    g = np.linalg.norm(loads.gravity, axis=1)
    point = (np.linalg.norm(loads.tip_force, axis=1) * length ** 2
             + np.sum(np.linalg.norm(loads.point_force, axis=2) * loads.point_s ** 2, axis=1)
             + g * lay.disk_mass * float(np.sum(lay.disk_s ** 2)))
    per_metre = np.linalg.norm(loads.distributed_force, axis=1) + g * lay.linear_density
    return (point / (EULER_CLAMPED_FREE * ei)
            + per_metre * length ** 3 / (GREENHILL_CLAMPED_FREE * ei))


def _det3(a: jax.Array) -> jax.Array:
    """Determinants of (..., 3, 3) matrices by cofactors (no LAPACK: fine on sharded
    paths)."""
    return (a[..., 0, 0] * (a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1])
            - a[..., 0, 1] * (a[..., 1, 0] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 0])
            + a[..., 0, 2] * (a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0]))


def jacobi_margin(lay: _Layout, config: StaticsConfig, base_moment: jax.Array,
                  tension: jax.Array, loads: CaseLoads, with_tip: bool = False) -> Any:
    """Positive for a stable equilibrium at M(0) = ``base_moment`` (one case): the smallest
    det Y(s) over the rod's grid points (Y = ∂M(s)/∂M(0), the identity at the base), and
    −1 where Y(s) has two negative real eigenvalues (two conjugate points passed at once,
    which keeps the determinant's sign; see the module). ``with_tip``: (that margin,
    Y(L)), the shooting residual's Jacobian at the equilibrium (a next Newton's start)."""
    rough = dataclasses.replace(config, constitutive_iterations=1)
    margin, y, _ = _jacobi_field(lay, rough, base_moment, tension, loads)
    return (margin, y[-1]) if with_tip else margin


def shape_and_margin(lay: _Layout, config: StaticsConfig, base_moment: jax.Array,
                     tension: jax.Array, loads: CaseLoads) -> tuple:
    """``jacobi_margin(..., with_tip=True)`` and the shape's pass at ``base_moment`` in one
    vmapped integration (its unperturbed lane is the shape: one sequential pass fewer than
    the two apart, for a one-case solve; every lane with ``config``'s own constitutive
    iterations). Returns (margin, Y(L), ``_integrate``'s outputs with the path)."""
    margin, y, shape = _jacobi_field(lay, config, base_moment, tension, loads)
    return margin, y[-1], shape


def _jacobi_field(lay: _Layout, config: StaticsConfig, base_moment: jax.Array,
                  tension: jax.Array, loads: CaseLoads) -> tuple:
    """(the margin of ``jacobi_margin``, Y at every grid point (P, 3, 3), the unperturbed
    pass's ``_integrate`` outputs with the path) from four passes with ``config``."""
    dtype = base_moment.dtype
    h = float(np.sqrt(np.finfo(np.dtype(dtype)).eps)) * jnp.maximum(
        jnp.max(jnp.abs(base_moment)), lay.moment_scale)
    starts = base_moment[None] + jnp.concatenate(
        [jnp.zeros((1, 3), dtype), h * jnp.eye(3, dtype=dtype)])
    passes = jax.vmap(lambda m0: _integrate(lay, config, m0, tension, loads, True))(starts)
    mom = passes[-1]
    y = jnp.moveaxis((mom[1:] - mom[0]) / h, 0, -1)                     # (P, 3, 3)
    # det(μI − Y) = μ³ − aμ² + bμ − d; with d > 0 it has two negative roots iff its local
    # maximum lies at μ < 0 and is not below zero (a touch: the symmetric case).
    a = jnp.trace(y, axis1=-2, axis2=-1)
    b = (y[:, 0, 0] * y[:, 1, 1] - y[:, 0, 1] * y[:, 1, 0]
         + y[:, 0, 0] * y[:, 2, 2] - y[:, 0, 2] * y[:, 2, 0]
         + y[:, 1, 1] * y[:, 2, 2] - y[:, 1, 2] * y[:, 2, 1])
    d = _det3(y)
    spread = a * a - 3 * b
    mu = (a - jnp.sqrt(jnp.maximum(spread, 0.0))) / 3
    peak = mu ** 3 - a * mu ** 2 + b * mu - d
    two_negative = (spread >= 0) & (mu < 0) & (peak >= -1e-6)
    return (jnp.min(jnp.where(two_negative, -1.0, d)), y,
            tuple(out[0] for out in passes))


def distinct(base_moments: np.ndarray, valid: np.ndarray, scale: float) -> np.ndarray:
    """(B, C) True for the first of each group of equal answers among ``valid`` ones:
    two M(0) (N·m) closer than 1e-6·``scale`` (E·I/L) are one equilibrium."""
    count = base_moments.shape[1]
    first = valid.copy()
    for c in range(1, count):
        gaps = np.linalg.norm(base_moments[:, :c] - base_moments[:, c:c + 1], axis=2)
        seen = np.any(valid[:, :c] & (gaps <= 1e-6 * scale), axis=1)
        first[:, c] &= ~seen
    return first
