"""The shooting of one load case on the Cosserat rod (``_rod``): the Newton iteration on
the base moment M(0) continued in a load factor, its implicit derivative
(``jax.lax.custom_root``), the equilibrium's shape and the result types. The batched
driver over many cases is ``_statics``. Units: metres, radians, newtons, N·m."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..robot import Robot
from ..rotations import wxyz_from_matrix
from ._rod import CaseLoads, StaticsConfig, _integrate, _Layout, _layout, _solve3


@dataclass(frozen=True)
class Equilibrium:
    """One equilibrium shape of a load case (world frame, float64 numpy)."""

    positions: np.ndarray
    """(P, 3) backbone points, m."""
    rotations: np.ndarray
    """(P, 3, 3) backbone frames."""
    base_moment: np.ndarray
    """(3,) moment at the base, N·m."""
    stable: bool
    """A strict local minimum of the energy (no conjugate point along the rod)."""
    reached: bool
    """The one ``StaticsResult`` reports (the equilibrium reached by loading from rest)."""

    @property
    def tip_position(self) -> np.ndarray:
        """(3,) tip position, m."""
        return self.positions[-1]


@dataclass(frozen=True)
class StaticsResult:
    """Equilibrium shapes of a batch of load cases (world frame, float64 numpy)."""

    positions: np.ndarray
    """(B, P, 3) backbone points from the base to the tip at every integration step, m."""
    rotations: np.ndarray
    """(B, P, 3, 3) backbone frames at the same points (columns: the disk's x, y, z axes)."""
    arc_length: np.ndarray
    """(P,) arc length of each point from the base, m."""
    tendon_displacements: np.ndarray
    """(B, n_tendons) how far each tendon is pulled (its straight length minus its length
    along the bent robot; positive = pulled), m."""
    converged: np.ndarray
    """(B,) True where the shooting met its tolerance."""
    residual: np.ndarray
    """(B,) boundary residual |M(L) − M_tip|, N·m."""
    iterations: np.ndarray
    """(B,) shooting iterations used."""
    base_moment: np.ndarray
    """(B, 3) moment at the base (rod and tendons together), N·m, world frame."""
    base_force: np.ndarray
    """(B, 3) force at the base (rod and tendons together), N, world frame."""

    stable: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    """(B,) True where the equilibrium is a strict local minimum of the energy (no
    conjugate point along the rod, ``model._equilibria``)."""
    equilibria: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    """(B,) distinct equilibria found for the case's loads (1 where the loads are below a
    buckling load and no other start was tried; ``solve_statics``)."""
    snap_load: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(B,) load factor in (0, 1) at which the loading path left its branch (a
    snap-through: the branch folded, or its end was unstable and a stable equilibrium
    was taken instead, then 1.0); NaN where the path reached the answer smoothly."""
    all_equilibria: list | None = None
    """With ``all_equilibria=True``: per case the list of ``Equilibrium`` found (the one
    reported first); else None."""
    tip_moment_jacobian: np.ndarray | None = None
    """(1, 3, 3) ∂M(L)/∂M(0) at the equilibrium, world frame (its stability test's Jacobi
    field at the tip) from a one-case solve that continued from ``start_moment``: the next
    step's ``start_jacobian``; else None."""

    @property
    def tip_position(self) -> np.ndarray:
        """(B, 3) tip position, m."""
        return self.positions[:, -1]

    @property
    def tip_rotation(self) -> np.ndarray:
        """(B, 3, 3) tip orientation."""
        return self.rotations[:, -1]

    @property
    def tip_wxyz(self) -> np.ndarray:
        """(B, 4) tip orientation as a unit quaternion (w, x, y, z)."""
        return wxyz_from_matrix(self.tip_rotation).reshape(-1, 4)



class _Newton(NamedTuple):
    """The shooting iteration's state for one case (see ``_shooting``)."""

    x: jax.Array        # (3,) M(0), N·m
    lam: jax.Array      # load factor reached
    target: jax.Array   # load factor being tried
    r: jax.Array        # (3,) residual at (x, lam)
    j: jax.Array        # (3, 3) ∂r/∂M(0)
    g: jax.Array        # (3,) ∂r/∂λ
    step: jax.Array     # Newton step length
    it: jax.Array       # iterations used
    stall: jax.Array    # load factor where the continuation stalled (a fold), −1: none


_NEWTON_RANGE = 1e-3
"""A residual below this (radians of bending over the robot, times E·I/L) is one Newton
corrects: a continuation step that leaves less is kept."""
SMALLEST_INCREMENT = 1e-3
"""A load increment the continuation may shrink to before it declares a fold (the branch
ends: a snap-through) and stops; the branch check then looks for where it snaps to."""


def _shooting(lay: _Layout, coarse: _Layout, config: StaticsConfig, tension: jax.Array,
              loads: CaseLoads, mode: jax.Array, secant: bool = False
              ) -> tuple[Any, Any, Any]:
    """(start, iterate, done) of the shooting on M(0) for one case.

    Newton with continuation in a load factor λ: the external loads, and with ``mode[0]``
    = 1 the tensions too, are scaled by λ (with 0 the tensions stay whole: the older,
    direct start); ``mode[1]`` is the largest increment of λ (1: none; small increments
    follow a branch past a bifurcation instead of jumping onto another one). At λ = 0 the
    answer is M(0) = 0 exactly. Each iteration tries the next λ with a predictor step from
    the current Jacobian, keeps it when Newton at least halved the residual it set out to
    remove (the old one plus the load increment), doubles the increment then and quarters
    it otherwise; an increment below ``SMALLEST_INCREMENT`` is a fold (its λ recorded in
    ``stall``), where the iteration stops. A start at λ = 1 is plain damped Newton.

    The Jacobian (∂r/∂M(0), ∂r/∂λ) is taken by forward differences: five passes in one
    vectorised evaluation, on the ``coarse`` grid with one strain sweep (a third of a
    full pass each). XLA's forward-mode derivative of the strain sweeps costs about twenty
    primal passes per direction on the CPU. Newton only needs an approximate Jacobian
    (the residual itself is the full pass), and derivatives of the converged answer are
    implicit and exact (``_shoot``).

    ``secant`` (a program of one case, not vmapped: ``lax.cond`` skips the coarse passes):
    after an accepted step at a fixed load factor, the step's secant (exact: both
    residuals are full passes) updates the Jacobian instead (Broyden's rule). From a
    neighbouring equilibrium under gravity and a payload (tdcr2) Newton then converges in
    4 iterations instead of 6. Not from rest: on 2000 cases under tip forces and moments
    it took more iterations (+0.43 on average; 266 cases instead of 40 needed more than
    10, which sends a case to the branch check) and ended on another equilibrium in 4
    cases, and a rank-one correction of each fresh coarse Jacobian was no better (+0.14).
    ``start``'s ``jacobian`` (3, 3), where given and free of NaN, replaces the first
    differences: the neighbouring equilibrium's own ∂M(L)/∂M(0) (its stability test's, on
    the full grid), with which a live drag step takes 3 iterations instead of 4.

    Long: the iteration's closures (residual, slopes, start, iterate, done) share one
    case's layout, loads and tolerances; apart they would pass them all around.
    """
    dtype = tension.dtype
    tol = config.resolved_tolerance() * lay.moment_scale
    root_eps = float(np.sqrt(np.finfo(np.dtype(dtype)).eps))

    rough = dataclasses.replace(config, constitutive_iterations=1)

    def scaled_residual(base_moment: jax.Array, lam: jax.Array, grid: _Layout = lay,
                        settings: StaticsConfig = config) -> jax.Array:
        pull = tension * (1.0 + mode[0] * (lam - 1.0))
        mom, _, _, _ = _integrate(grid, settings, base_moment, pull, loads.scaled(lam),
                                  False)
        return mom - lam * loads.moment

    def slopes(x: jax.Array, lam: jax.Array) -> tuple[jax.Array, jax.Array]:
        hx = root_eps * jnp.maximum(jnp.max(jnp.abs(x)), lay.moment_scale)
        xs = jnp.concatenate([x[None], x[None] + hx * jnp.eye(3, dtype=dtype), x[None]])
        lams = jnp.concatenate([jnp.broadcast_to(lam, (4,)), (lam + root_eps)[None]])
        rs = jax.vmap(lambda a, b: scaled_residual(a, b, coarse, rough))(xs, lams)
        return (rs[1:4] - rs[0]).T / hx, (rs[4] - rs[0]) / root_eps

    def linearized(x: jax.Array, lam: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        return scaled_residual(x, lam), *slopes(x, lam)

    def start(x0: jax.Array, lam0: jax.Array, jacobian: Any = None) -> _Newton:
        # No external force (the padding rows): nothing to ramp.
        unloaded = ~(jnp.any(loads.force != 0) | jnp.any(loads.gravity != 0)
                     | jnp.any(loads.distributed != 0) | jnp.any(loads.point_force != 0))
        lam0 = jnp.where(unloaded, 1.0, lam0)
        if jacobian is None:
            r0, j0, g0 = linearized(x0, lam0)
        else:  # a given ∂r/∂M(0) unless it holds a NaN; ∂r/∂λ is unused at λ = 1
            r0 = scaled_residual(x0, lam0)
            j0, g0 = jax.lax.cond(jnp.any(jnp.isnan(jacobian)), slopes,
                                  lambda *_: (jacobian, jnp.zeros(3, dtype)), x0, lam0)
        one = 1 + 0 * x0[0]  # varies like x0 (see _integrate)
        return _Newton(x0, lam0, jnp.minimum(1.0, lam0 + mode[1]) * one, r0, j0, g0, one,
                       jnp.asarray(0), -one)

    def done(state: _Newton) -> jax.Array:
        return ((state.lam >= 1.0) & (jnp.linalg.norm(state.r) <= tol)) | (state.stall >= 0)

    def iterate(state: _Newton) -> _Newton:
        x, lam, target, r, j, g, step, it, stall = state
        x_new = x - step * _solve3(j, r + (target - lam) * g)
        r_new = scaled_residual(x_new, target)
        size, size_new = jnp.linalg.norm(r), jnp.linalg.norm(r_new)
        continuing = target > lam
        # The residual the step set out to remove: the old one plus the load increment.
        predicted = jnp.linalg.norm(r + (target - lam) * g)
        # A step that lands within the tolerance is always taken, and so is one that
        # leaves less than ``_NEWTON_RANGE`` (from the unloaded straight rod the first
        # increment's residual is of second order: the predictor has nothing to remove).
        ok = jnp.isfinite(size_new) & (
            (size_new <= tol) | (size_new < jnp.maximum(size, 0.5 * predicted))
            | (size_new < _NEWTON_RANGE * lay.moment_scale))
        reached = jnp.where(ok, target, lam)
        if secant:  # a fresh Jacobian where the point kept is new to it (see above)
            j, g = jax.lax.cond(
                continuing | ~ok, slopes,
                lambda *_: (secant_update(j, x_new - x, r_new - r), g),
                jnp.where(ok, x_new, x), reached)
        else:
            j_new, g_new = slopes(x_new, target)
            j, g = jnp.where(ok, j_new, j), jnp.where(ok, g_new, g)
        x, r = jnp.where(ok, x_new, x), jnp.where(ok, r_new, r)
        # After a success try twice the increment; after a failure a quarter of it.
        increment = jnp.minimum(mode[1], jnp.where(ok, 2.0 * (target - lam),
                                                   0.25 * (target - lam)))
        folded = continuing & ~ok & (increment < SMALLEST_INCREMENT)
        step = jnp.where(ok | continuing, 1.0, 0.25 * step)
        return _Newton(x, reached, jnp.minimum(1.0, reached + increment), r, j, g, step,
                       it + 1, jnp.where(folded, reached, stall))

    return start, iterate, done


def secant_update(j: jax.Array, dx: jax.Array, dr: jax.Array) -> jax.Array:
    """Broyden's rank-one update of the Jacobian ``j`` along a step ``dx`` whose residual
    changed by ``dr``: j + (dr − j dx) dxᵀ / dxᵀdx (``j`` where dx = 0)."""
    dd = jnp.dot(dx, dx)
    return jnp.where(dd > 0.0, j + jnp.outer(dr - j @ dx, dx) / jnp.where(dd > 0.0, dd, 1.0),
                     j)


def _run(iterate: Any, done: Any, state: _Newton, iterations: int) -> _Newton:
    """At most ``iterations`` more Newton iterations from ``state`` (fewer once done)."""
    limit = state.it + iterations
    return jax.lax.while_loop(lambda s: ~done(s) & (s.it < limit), iterate, state)


def _shoot(lay: _Layout, coarse: _Layout, config: StaticsConfig, tension: jax.Array,
           loads: CaseLoads) -> tuple[jax.Array, tuple]:
    """M(0) with M(L) = M_tip by the direct continuation (``solve_statics``' first try),
    differentiable implicitly; and (iterations, λ reached)."""
    mode = jnp.asarray([0.0, 1.0], tension.dtype)
    start, iterate, done = _shooting(lay, coarse, config, tension, loads, mode)

    def residual(base_moment: jax.Array) -> jax.Array:
        mom, _, _, _ = _integrate(lay, config, base_moment, tension, loads, False)
        return mom - loads.moment

    def solve(f: Any, x0: jax.Array) -> tuple[jax.Array, tuple]:
        del f  # the same residual, reached through its load-scaled family
        state = _run(iterate, done, start(x0, 0 * x0[0]), config.max_iterations)
        # aux as floats: custom_root's JVP rule gives aux tangents of the solution's dtype
        return state.x, (state.it.astype(x0.dtype), state.lam)

    def tangent_solve(g: Any, y: jax.Array) -> jax.Array:
        return _solve3(jax.jacfwd(g)(y), y)

    guess = jnp.zeros(3, tension.dtype)
    return jax.lax.custom_root(residual, guess, solve, tangent_solve, has_aux=True)


def case_loads(tip_force: jax.Array, tip_moment: jax.Array, gravity: jax.Array,
               distributed: Any = None, point_s: Any = None, point_force: Any = None,
               point_moment: Any = None) -> CaseLoads:
    """One case's loads in the base frame for the per-case JAX functions (N, N·m, m/s²,
    N/m; point loads: (K,) arc lengths in m, (K, 3) forces and moments); None is none."""
    if point_s is None:
        point_s = jnp.zeros((0,), tip_force.dtype)
        point_force = point_moment = jnp.zeros((0, 3), tip_force.dtype)
    return CaseLoads(tip_force, tip_moment, gravity,
                     jnp.zeros((0,), tip_force.dtype) if distributed is None else distributed,
                     point_s,
                     point_force, point_moment)


def tip_equilibrium(robot: Robot, config: StaticsConfig = StaticsConfig()) -> Any:
    """The per-case JAX function ``f(tension, base_moment, loads) -> (tip position (3,),
    tip rotation (3, 3), equilibrium residual (3,))`` of one integration pass from a given
    moment at the base M(0) (N·m), base frame; ``loads`` from ``case_loads``.

    The residual ``M(L) − M_tip`` (N·m) is zero at an equilibrium: a solver may take M(0)
    as an unknown beside the tensions (tension-space IK does) instead of shooting for it
    at every step.
    """
    lay = _layout(robot, config)

    def tip(tension: jax.Array, base_moment: jax.Array,
            loads: CaseLoads) -> tuple[jax.Array, ...]:
        mom, _, position, rotation = _integrate(lay, config, base_moment, tension, loads,
                                                False)
        return position, rotation, mom - loads.moment

    return tip


def backbone_equilibrium(robot: Robot, config: StaticsConfig = StaticsConfig()) -> Any:
    """As ``tip_equilibrium``, with the whole backbone: ``f(tension, base_moment, loads)
    -> (positions (P, 3) at the robot's points, base to tip, m; tip rotation (3, 3);
    equilibrium residual M(L) − M_tip (3,), N·m)``, base frame, one integration pass."""
    lay = _layout(robot, config)

    def backbone(tension: jax.Array, base_moment: jax.Array,
                 loads: CaseLoads) -> tuple[jax.Array, ...]:
        mom, _, positions, rotations, _ = _integrate(lay, config, base_moment, tension, loads,
                                                     True)
        return positions, rotations[-1], mom - loads.moment

    return backbone


def moment_scale(robot: Robot) -> float:
    """E·I / L (N·m per radian of bending over the robot): the size of a moment."""
    return _layout(robot, StaticsConfig()).moment_scale


def _finish(lay: _Layout, config: StaticsConfig, base_moment: jax.Array,
            tension: jax.Array, loads: CaseLoads) -> dict[str, jax.Array]:
    """The shape and its checks for one case from its M(0): one integration pass."""
    return _finished(lay, config, base_moment, loads,
                     _integrate(lay, config, base_moment, tension, loads, True))


def _finished(lay: _Layout, config: StaticsConfig, base_moment: jax.Array, loads: CaseLoads,
              integrated: tuple) -> dict[str, jax.Array]:
    """``_finish`` of the pass ``integrated`` (``_integrate``'s outputs with the path)."""
    mom, ell, positions, rotations, _ = integrated
    straight = jnp.asarray(lay.active.T @ lay.step_length, ell.dtype)
    residual = jnp.linalg.norm(mom - loads.moment)
    tol = config.resolved_tolerance() * lay.moment_scale
    return {
        "positions": positions, "rotations": rotations,
        "tendon_displacements": straight - ell, "residual": residual,
        # A last check on the final pass itself (the loop's own flag is a twin).
        "converged": jnp.isfinite(residual) & (residual <= 10.0 * tol),
        "base_moment": base_moment,
        "base_force": loads.external_force(lay),
    }


def statics_single(robot: Robot, config: StaticsConfig = StaticsConfig()) -> Any:
    """The per-case JAX function ``f(tension, tip_force, tip_moment, gravity) -> dict``.

    Inputs in the base frame (N, N, N·m, m/s²); the dict holds ``positions`` (P, 3),
    ``rotations`` (P, 3, 3) in the base frame, ``tendon_displacements`` (T,), ``residual``
    (N·m), ``iterations``, ``converged`` and ``base_moment``: the equilibrium of the
    direct continuation (where it is unique, the loading path's). Differentiable (forward
    and reverse) with respect to all four inputs through the implicit solution.
    """
    lay, coarse = _layout(robot, config), _layout(robot, config, coarse=True)

    def solve_case(tension: jax.Array, tip_force: jax.Array, tip_moment: jax.Array,
                   gravity: jax.Array) -> dict[str, jax.Array]:
        loads = case_loads(tip_force, tip_moment, gravity)
        base_moment, (iterations, load_reached) = _shoot(lay, coarse, config, tension, loads)
        out = _finish(lay, config, base_moment, tension, loads)
        out["iterations"] = jax.lax.stop_gradient(iterations).astype(jnp.int32)
        out["load_reached"] = load_reached
        return out

    return solve_case
