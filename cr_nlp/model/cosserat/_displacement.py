"""Cosserat statics driven by tendon displacements (motor commands), batched in JAX.

A real robot's motors set how far each tendon is pulled, not its tension. Tendon j's
commanded pull is ``p_j = g_j (d_j − d0_j)`` (the command d in m, positive = pulled, with
the gain g and zero offset d0 of the robot file's ``actuation`` block, as ``calibrate``
reads them; nominal 1 and 0 without one). Along the solved rod the tendon's path is
shorter than its straight length by s_j: the geometric shortening (bending, and the
backbone's compression) plus the take-up ``Σ_i c_i N_i`` over the segments i it runs
through (c_i: ``mechanics.tendon_take_up``, m/N; N_i the sum of the tensions through
segment i). The tendon is stretched by ``p_j − s_j`` when that is positive and slack
otherwise, and pulls with

    τ_j = k_j · max(0, p_j − s_j)        (k_j: ``mechanics.tendon_stiffness``, N/m)

so a slack tendon carries nothing and a tendon never pushes. The take-up couples the
tendons (one tendon's tension shortens the others through the same segments) but not the
shape: the rod's shape depends on the tensions alone. The unknowns of one case are
the moment at the base M(0) (as in the tension statics, ``_shooting``) and the
tensions τ: one integration pass gives both the moment balance at the tip and every s_j,
so Newton solves the 3 + T equations together, with continuation in a factor λ that
scales the commands and the external loads from rest (λ = 0: straight, no tension, exact)
to 1, following the branch the robot takes when loaded from rest. The Jacobian is taken
by forward differences on the coarse grid (as the shooting's).

The answer's tensions are then solved again by the tension statics
(``solve_statics``): its shape, stability label and equilibrium count are
the result's, and the displacement residual is measured on that shape, so the two models
agree by construction where the result says ``converged``. Units: metres, radians,
newtons, N·m, kg, m/s².
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..._cached_jit import CachedProgram
from ...runtime import cached, configure
from .._actuation_block import Actuation
from ..actuation import tendon_segments
from ..loads import static_loads
from ..mechanics import require_mechanics
from ..robot import Robot
from ..routing import routing_of
from ._batch_rows import _padded, _typed
from ._rod import CaseLoads, StaticsConfig, _integrate, _Layout, _layout
from ._shooting import StaticsResult, secant_update
from ._statics import _case_loads, _load_batch, _stable, solve_statics
from ._statics import _programs as _statics_programs

__all__ = ["DisplacementStaticsResult", "commanded_pull", "displacement_pass",
           "displacement_solver", "motor_commands", "predict_marker", "solve_displacement_statics",
           "take_up_lengths", "tension_scale", "tendon_stiffness_of"]

DISPLACEMENT_TOLERANCE = 1e-9
"""A case is converged when every tendon's tension matches its stretch within this, m
(|τ/k − max(0, p − s)|), besides the tension statics' own test."""


@dataclass(frozen=True)
class DisplacementStaticsResult(StaticsResult):
    """``StaticsResult`` of the tensions found, and how the commands were met."""

    tensions: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    """(B, n_tendons) the tensions found, N (≥ 0; 0 where a tendon is slack)."""
    pull: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    """(B, n_tendons) commanded pull g (d − d0), m."""
    stretch: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    """(B, n_tendons) pull minus the tendon's shortening along the solved rod and its
    take-up, m: > 0 taut (τ = k · stretch), ≤ 0 slack."""
    displacement_residual: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(B,) largest |τ/k − max(0, stretch)| over the tendons, m."""

    @property
    def slack(self) -> np.ndarray:
        """(B, n_tendons) True where a tendon is slack (carries no tension)."""
        return self.stretch <= 0.0


def tendon_stiffness_of(robot: Robot, tendon_stiffness: Any = None) -> np.ndarray:
    """(n_tendons,) each tendon's stiffness k, N/m: ``tendon_stiffness`` (one number, one
    per segment (tendons anchored there) or one per tendon), else the mechanics block's.

    Raises:
        ValueError: none given and the robot's mechanics block has no ``tendon_stiffness``,
            or a value that is not finite and positive.
    """
    mech = require_mechanics(robot, "the displacement-driven statics")
    anchor = routing_of(robot).anchor
    if tendon_stiffness is None:
        if not mech.tendon_stiffness:
            raise ValueError(f"{robot.name}: the displacement-driven statics needs "
                             "mechanics.tendon_stiffness (N/m per segment's tendons) in the "
                             "robot file, or tendon_stiffness=")
        tendon_stiffness = mech.tendon_stiffness
    k = np.atleast_1d(np.asarray(tendon_stiffness, dtype=float))
    if k.size == 1:
        k = np.full(robot.n_tendons, k[0])
    elif k.size == robot.n_segments and k.size != robot.n_tendons:
        k = k[anchor]
    if k.shape != (robot.n_tendons,) or not np.all(np.isfinite(k) & (k > 0)):
        raise ValueError(f"tendon_stiffness: one positive number, {robot.n_segments} (per "
                         f"segment) or {robot.n_tendons} (per tendon), N/m; got "
                         f"{np.asarray(tendon_stiffness).tolist()}")
    return k


def take_up_of(robot: Robot) -> np.ndarray:
    """(n_segments,) the segments' take-up compliances c, m/N (``mechanics.tendon_take_up``;
    zeros without)."""
    mech = require_mechanics(robot, "the displacement-driven statics")
    return np.asarray(mech.take_up(robot.n_segments), dtype=float)


def take_up_coupling(through: Any, take_up: Any) -> Any:
    """(T, T) the take-up's lengths per tension: tendon j loses ``(C τ)_j`` m of its path
    under tensions τ (N), ``C = B diag(c) Bᵀ`` with B = ``routing.through`` (T, n) and c
    (n,) m/N (numpy, or JAX with traced c)."""
    return (through * take_up[None, :]) @ through.T


def take_up_lengths(robot: Robot, tensions: Any) -> np.ndarray:
    """(B, n_tendons) how much of each tendon's path the take-up takes under tensions (B,
    n_tendons) N, m (zeros for a robot without ``mechanics.tendon_take_up``)."""
    through = tendon_segments(robot)
    return np.asarray(tensions, float) @ take_up_coupling(through, take_up_of(robot)).T


def commanded_pull(robot: Robot, displacements: Any) -> np.ndarray:
    """(B, n_tendons) pull g (d − d0), m, of commanded displacements (B or 1, n_tendons) m
    with the robot's ``actuation`` gains and zero offsets (1 and 0 without the block).

    Raises:
        ValueError: a wrong shape or a value that is not finite (naming the row).
    """
    d = np.asarray(displacements, dtype=float)
    d = d[None] if d.ndim == 1 else d
    if d.ndim != 2 or d.shape[1] != robot.n_tendons:
        raise ValueError(f"displacements: {robot.name} has {robot.n_tendons} tendons, got "
                         f"shape {np.shape(displacements)}")
    if not np.all(np.isfinite(d)):
        bad = np.argwhere(~np.isfinite(d))[0]
        raise ValueError(f"case {bad[0]}: displacements: tendon {bad[1] + 1}: a "
                         f"displacement must be a finite number of metres, got {d[tuple(bad)]}")
    act = robot.actuation or Actuation.nominal(robot.n_tendons, robot.n_segments)
    return np.asarray(act.gains) * (d - np.asarray(act.zero_offsets))


class _Newton(NamedTuple):
    """The iteration's state for one case: scaled unknowns y = (M(0)/(EI/L), τ/τ_s) and
    the smooth parts F = (moment balance / (EI/L) (3), tendon shortenings s (T) m) with
    their derivatives; the rows are assembled from F (``_rows``)."""

    y: jax.Array       # (3 + T,)
    lam: jax.Array     # load factor reached
    target: jax.Array  # load factor being tried
    f: jax.Array       # (3 + T,) F at (y, lam)
    jf: jax.Array      # (3 + T, 3 + T) ∂F/∂y
    gf: jax.Array      # (3 + T,) ∂F/∂λ
    step: jax.Array
    it: jax.Array


def _scales(lay: _Layout) -> tuple[float, float, float]:
    """(moment scale E I / L in N·m, tension scale τ_s = (E I / L) / r in N, tendon radius
    r in m): the unknowns and rows are measured in them."""
    radius = float(np.max(np.linalg.norm(lay.routing, axis=1)))
    return lay.moment_scale, lay.moment_scale / radius, radius


def _smooth(lay: _Layout, config: StaticsConfig, y: jax.Array, lam: jax.Array,
            stiffness: Any, coupling: jax.Array, loads: CaseLoads,
            scales: tuple[float, float, float]) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(F (3 + T,), tip position (3,), tip rotation (3, 3)) of one pass at load factor
    ``lam``: F = (the tip's moment balance / (EI/L), each tendon's shortening s in m, the
    take-up ``coupling`` (T, T) m/N times the tensions included)."""
    ms, ts, _ = scales
    mom, ell, tip, frame = _integrate(lay, config, y[:3] * ms, y[3:] * ts, loads.scaled(lam),
                                      False, stiffness)
    shortening = jnp.asarray(lay.tendon_end, y.dtype) - ell + coupling @ (y[3:] * ts)
    return jnp.concatenate([(mom - lam * loads.moment) / ms, shortening]), tip, frame


def _rows(y: jax.Array, f: jax.Array, lam: jax.Array, pull: jax.Array, k: jax.Array,
          scales: tuple[float, float, float], taut: Any = None) -> jax.Array:
    """(3 + T,) the equations: the moment balance and (τ/k − max(0, λp − s)) / r; with
    ``taut`` given, that active set in place of the max (the Newton model's)."""
    _, ts, radius = scales
    stretch = lam * pull - f[3:]
    pulled = jnp.maximum(0.0, stretch) if taut is None else taut * stretch
    return jnp.concatenate([f[:3], (y[3:] * ts / k - pulled) / radius])


_ACTIVE_SET_ROUNDS = 4
"""Active-set rounds of each Newton step's linear model (tendons taut or slack)."""


def _continuation(lay: _Layout, coarse: _Layout, config: StaticsConfig, pull: jax.Array,
                  k: jax.Array, stiffness: Any, coupling: jax.Array, loads: CaseLoads,
                  axis: str | None = None) -> tuple[Any, Any, Any]:
    """(start, iterate, done) of semismooth Newton on (M(0), τ) with continuation in λ,
    as the shooting's (``model.cosserat._shooting``): the smooth parts F are linearised by
    forward differences on the coarse grid; the tendons taut in the Newton model are those
    stretched at the predicted F for the λ being tried (so from rest the pulled tendons
    are taut at once); a step is kept where it at least halved the residual it set out to
    remove, the increment then doubles, else it is quartered. At a fixed λ the step's
    secant corrects the Jacobian instead (``secant_update``: on the FTDCR validation
    rows 1.95 iterations on average instead of 3.88, the same answers to 1e-11 m, every
    row converged; tension statics under tip loads did worse with it, see
    ``_shooting``); vmapped under the name
    ``axis``, a batch skips the coarse passes on the iterations where none of its cases
    needs them (``lax.psum`` over the batch makes the test one ``lax.cond``).

    Long: as ``_shooting``, the iteration's closures share one case's layout, pulls,
    stiffness and loads."""
    dtype = pull.dtype
    tol = config.resolved_tolerance()
    eps = float(np.sqrt(np.finfo(np.dtype(dtype)).eps))
    rough = dataclasses.replace(config, constitutive_iterations=1)
    scales = _scales(lay)
    size = 3 + pull.shape[0]
    tension_columns = jnp.concatenate([jnp.zeros(3, dtype), scales[1] / k])

    def smooth(y: jax.Array, lam: jax.Array) -> jax.Array:
        return _smooth(lay, config, y, lam, stiffness, coupling, loads, scales)[0]

    def slopes(y: jax.Array, lam: jax.Array) -> tuple[jax.Array, jax.Array]:
        h = eps * jnp.maximum(jnp.max(jnp.abs(y)), 1.0)
        ys = jnp.concatenate([y[None], y[None] + h * jnp.eye(size, dtype=dtype), y[None]])
        lams = jnp.concatenate([jnp.broadcast_to(lam, (size + 1,)), (lam + eps)[None]])
        fs = jax.vmap(lambda a, b: _smooth(coarse, rough, a, b, stiffness, coupling, loads,
                                           scales)[0])(ys, lams)
        return (fs[1:size + 1] - fs[0]).T / h, (fs[size + 1] - fs[0]) / eps

    def linearized(y: jax.Array, lam: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        return smooth(y, lam), *slopes(y, lam)

    def start(y0: jax.Array, lam0: jax.Array) -> _Newton:
        f0, j0, g0 = linearized(y0, lam0)
        one = 1 + 0 * y0[0]
        return _Newton(y0, lam0, jnp.minimum(1.0, lam0 + 1.0) * one, f0, j0, g0, one,
                       jnp.asarray(0))

    def done(state: _Newton) -> jax.Array:
        rows = _rows(state.y, state.f, state.lam, pull, k, scales)
        return (state.lam >= 1.0) & (jnp.max(jnp.abs(rows)) <= tol)

    def iterate(state: _Newton) -> _Newton:
        y, lam, target, f, jf, gf, step, it = state
        predicted_f = f + (target - lam) * gf
        stretch = target * pull - predicted_f[3:]

        def newton_step(taut: jax.Array, _: Any) -> tuple[jax.Array, jax.Array]:
            # tendon rows: ∂(τ/k − taut (λp − s))/∂y = (diag(τ_s/k) + taut ∂s/∂y) / r
            jac = jnp.concatenate([jf[:3], (jnp.diag(tension_columns)[3:]
                                            + taut[:, None] * jf[3:]) / scales[2]])
            rows = _rows(y, predicted_f, target, pull, k, scales, taut)
            dy = -pivoted_solve(jac, rows)
            # the tendons the linear model stretches after the step: the next active set
            return (stretch - jf[3:] @ dy > 0.0).astype(dtype), (dy, rows)

        # a few rounds of the active set in the linear model (no rod passes): from rest,
        # pulling one tendon stretches its antagonists at once
        taut0 = (stretch > 0.0).astype(dtype)
        _, (dys, models) = jax.lax.scan(newton_step, taut0, None, length=_ACTIVE_SET_ROUNDS)
        dy, rows = dys[-1], models[-1]
        y_new = y + step * dy
        f_new = smooth(y_new, target)
        size_old = jnp.linalg.norm(_rows(y, f, lam, pull, k, scales))
        size_new = jnp.linalg.norm(_rows(y_new, f_new, target, pull, k, scales))
        continuing = target > lam
        # At a fixed load factor the step's secant (both F full passes) corrects the
        # Jacobian along the step, as in the shooting (``secant_update``).
        keep = ~continuing & jnp.all(jnp.isfinite(f_new))
        secant = secant_update(jf, y_new - y, f_new - f)

        def fresh(*_: Any) -> tuple[jax.Array, jax.Array]:
            jf_c, gf_c = slopes(y_new, target)
            return jnp.where(keep, secant, jf_c), jnp.where(keep, gf, gf_c)

        if axis is None:
            jf_new, gf_new = fresh()
        else:
            needed = jax.lax.psum((~keep & ~done(state)).astype(jnp.int32), axis) > 0
            jf_new, gf_new = jax.lax.cond(needed, fresh, lambda *_: (secant, gf))
        ok = jnp.isfinite(size_new) & (
            (size_new <= tol) | (size_new < jnp.maximum(size_old, 0.5 * jnp.linalg.norm(rows))))
        y, f, jf, gf = (jnp.where(ok, a, b) for a, b in
                        ((y_new, y), (f_new, f), (jf_new, jf), (gf_new, gf)))
        reached = jnp.where(ok, target, lam)
        increment = jnp.where(ok, 2.0 * (target - lam), 0.25 * (target - lam))
        step = jnp.where(ok | continuing, 1.0, 0.5 * step)
        return _Newton(y, reached, jnp.minimum(1.0, reached + jnp.maximum(increment, 1e-3)),
                       f, jf, gf, step, it + 1)

    return start, iterate, done


def displacement_solver(robot: Robot, config: StaticsConfig = StaticsConfig(),
                        iterations: int = 40, axis: str | None = None) -> Any:
    """The per-case JAX function ``f(pull (T,) m, k (T,) N/m, stiffness (n,), take_up (n,)
    m/N, loads, y0, lam0) -> (y, converged, iterations, stretch (T,) m, λ reached)``:
    Newton with
    continuation (at most ``iterations``) from the scaled unknowns ``y0`` = (M(0)/(EI/L),
    τ/τ_s) at load factor ``lam0`` (0 and zeros: from rest; 1 and a neighbour's answer: a
    warm start); ``displacement_pass`` reads y. A tendon
    whose stretch (pull − shortening) is not positive is slack: its tension is set to 0.
    ``axis``: the name of the vmap this function will be mapped by (``jax.vmap(…,
    axis_name=axis)``), where the batch shares one test for the coarse Jacobian
    (``_continuation``)."""
    lay, coarse = _layout(robot, config), _layout(robot, config, coarse=True)
    through = tendon_segments(robot)

    def solve(pull: jax.Array, k: jax.Array, stiffness: jax.Array, take_up: jax.Array,
              loads: CaseLoads, y0: jax.Array, lam0: jax.Array) -> tuple[jax.Array, ...]:
        coupling = take_up_coupling(jnp.asarray(through, pull.dtype), take_up)
        start, iterate, done = _continuation(lay, coarse, config, pull, k, stiffness,
                                             coupling, loads, axis)
        state = jax.lax.while_loop(lambda s: ~done(s) & (s.it < iterations), iterate,
                                   start(y0, lam0))
        stretch = state.lam * pull - state.f[3:]
        y = state.y.at[3:].set(jnp.where(stretch > 0.0, state.y[3:], 0.0))
        return y, done(state), state.it, stretch, state.lam

    return solve


def displacement_pass(robot: Robot, config: StaticsConfig = StaticsConfig()) -> Any:
    """The per-case JAX function ``f(y, pull, k, stiffness, take_up, loads) -> (rows (3 +
    T,), tip position (3,) m, tip rotation (3, 3))`` of one pass at the full loads, base
    frame:
    ``rows`` vanish at a displacement-driven equilibrium (see ``displacement_solver``);
    tensions are ``y[3:] * tension_scale``."""
    lay = _layout(robot, config)
    scales = _scales(lay)
    through = tendon_segments(robot)

    def one_pass(y: jax.Array, pull: jax.Array, k: jax.Array, stiffness: jax.Array,
                 take_up: jax.Array, loads: CaseLoads) -> tuple[jax.Array, jax.Array, jax.Array]:
        one = jnp.asarray(1.0, y.dtype)
        coupling = take_up_coupling(jnp.asarray(through, y.dtype), take_up)
        f, tip, frame = _smooth(lay, config, y, one, stiffness, coupling, loads, scales)
        return _rows(y, f, one, pull, k, scales), tip, frame

    return one_pass


def tension_scale(robot: Robot, config: StaticsConfig = StaticsConfig()) -> float:
    """τ_s = (E I / L) / r, N: the tensions in ``displacement_solver``'s y are y[3:] · τ_s."""
    return _scales(_layout(robot, config))[1]


_FIRST_ROUND = 10
"""Newton iterations every case of a batch gets; the few that need more continue in a
smaller batch (a vmapped loop runs until its slowest case is done). From rest with the
secant updates most cases take 7–10 (the FTDCR validation rows: 34 of 512 done after 6,
510 after 10); at 6 nearly every case went on into the second program, which then ran the
whole batch again: 512 rows 0.70 → 0.63 s, 2048 rows 3.1–3.3 → 2.8–3.0 s, the same
answers to 5e-12 m; ``bench_displacement_statics`` (10 000 tdcr2 cases) 1.45–1.55 against
1.56–1.58 s, alternated."""


def pivoted_solve(a: jax.Array, b: jax.Array) -> jax.Array:
    """Solve A x = b for one small square A (n, n), b (n,): Gaussian elimination with
    partial pivoting in plain array operations (a loop over the columns, then over the
    rows back). No LAPACK call, so a vmapped batch of them can be split over the CPU
    devices (a sharded batched ``jnp.linalg.solve`` never returned with jax 0.10 on 2
    host devices, ``runtime.split_over_devices``)."""
    n = a.shape[0]
    rows = jnp.arange(n)

    def eliminate(k: jax.Array, ab: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, ...]:
        a, b = ab
        column = jnp.take(a, k, axis=1)
        pivot = jnp.argmax(jnp.where(rows >= k, jnp.abs(column), -1.0))
        order = jnp.where(rows == k, pivot, jnp.where(rows == pivot, k, rows))
        a, b = a[order], b[order]
        top, column = a[k], jnp.take(a, k, axis=1)
        factor = jnp.where(rows > k, column / top[k], 0.0)
        return a - factor[:, None] * top[None, :], b - factor * b[k]

    a, b = jax.lax.fori_loop(0, n, eliminate, (a, b))

    def substitute(i: jax.Array, x: jax.Array) -> jax.Array:
        k = n - 1 - i
        return x.at[k].set((b[k] - a[k] @ x) / a[k, k])

    return jax.lax.fori_loop(0, n, substitute, jnp.zeros_like(b))


CASES = "cases"
"""The name of the vmap over a batch's cases (``displacement_solver``'s ``axis``)."""


@cached(maxsize=16)
def _program(robot: Robot, config: StaticsConfig, iterations: int) -> Any:
    """The Newton loop of ``iterations`` over a batch of cases, split over the devices
    (one per CPU core in the CLI) where the batch divides evenly."""
    return CachedProgram(jax.vmap(displacement_solver(robot, config, iterations, CASES),
                                  axis_name=CASES),
                         name="the displacement-driven statics", batched=(True,) * 7,
                         outputs=5)


def _solve_rows(robot: Robot, config: StaticsConfig, rows: tuple) -> tuple[np.ndarray, ...]:
    """(y, solved, iterations) of the cases ``rows`` = (pull, k, stiffness, take-up, loads):
    a first
    round of ``_FIRST_ROUND`` iterations for all, then the unfinished ones from where they
    were."""
    batch = len(rows[0])
    size = 3 + rows[0].shape[1]
    start = (np.zeros((batch, size)), np.zeros(batch))
    y, solved, its, _, lam = (np.array(a)[:batch] for a in _program(robot, config, _FIRST_ROUND)(
        *_typed(_padded((*rows, *start), edge=True), np.float64)))
    left = np.flatnonzero(~solved)
    if left.size:
        def pick(a: Any) -> Any:
            return jax.tree_util.tree_map(lambda v: np.asarray(v)[left], a)

        more = _program(robot, config, config.max_iterations + 16)(*_typed(
            _padded((*pick(rows), y[left], lam[left]), edge=True), np.float64))
        y[left], solved[left], its[left] = (np.asarray(a)[:left.size] for a in more[:3])
    return y, solved, its


def solve_displacement_statics(robot: Robot, displacements: Any, tip_force: Any = None,
                               tip_moment: Any = None, gravity: Any = None,
                               config: StaticsConfig = StaticsConfig(), *,
                               distributed_force: Any = None, point_loads: Any = None,
                               tendon_stiffness: Any = None) -> DisplacementStaticsResult:
    """Equilibrium shapes for a batch of commanded tendon displacements and loads (numpy in,
    float64 numpy out).

    Args:
        robot: a robot with a ``mechanics`` block (with ``tendon_stiffness``, or pass it)
            and fixed segment lengths; its ``actuation`` block's gains and zero offsets map
            commands to pulls (nominal without one).
        displacements: (n_tendons,) or (B, n_tendons) commanded displacements, m, positive
            = pulled, in the robot file's tendon order.
        tip_force, tip_moment, gravity, distributed_force, point_loads: the loads, world
            frame, as ``model.statics.solve_statics`` takes them (N, N·m, m/s², N/m).
        config: discretisation, tolerance (float64 only).
        tendon_stiffness: k, N/m (one, per segment or per tendon); None: the mechanics
            block's.

    Returns:
        ``DisplacementStaticsResult``: the tension statics' result at the tensions found
        (shape, stability, equilibria) with the tensions (N), pulls and stretches (m);
        ``converged`` also needs every tension to match its stretch within
        ``DISPLACEMENT_TOLERANCE``.

    Raises:
        ValueError: a robot without mechanics or tendon stiffness, wrong shapes, values
            that are not finite, bad loads (named as ``solve_statics`` names them).
    """
    configure()
    require_mechanics(robot, "the displacement-driven statics")
    k = tendon_stiffness_of(robot, tendon_stiffness)
    pull = commanded_pull(robot, displacements)
    if config.dtype != "float64":
        raise ValueError(f"dtype: the displacement-driven statics runs in float64, got "
                         f"{config.dtype!r}")
    lay = _layout(robot, config)
    if len(pull) == 1:
        pull = np.repeat(pull, _load_batch(tip_force, tip_moment, gravity,
                                           distributed_force, point_loads), axis=0)
    batch = len(pull)
    world = static_loads(batch, float(lay.arc_length[-1]), tip_force, tip_moment, gravity,
                         distributed_force, point_loads)
    loads = _case_loads(world.in_base_frame(robot.base_rotation))
    scales = _scales(lay)
    with jax.enable_x64(True):
        # padded with copies of a row: a zero k has no solution
        y, solved, iterations = _solve_rows(robot, config, (pull, np.broadcast_to(k, pull.shape),
                                                np.broadcast_to(lay.stiffness,
                                                                (batch, robot.n_segments)),
                                                np.broadcast_to(take_up_of(robot),
                                                                (batch, robot.n_segments)),
                                                loads))
        tensions = np.maximum(0.0, y[:, 3:] * scales[1])
        result = _verdict(robot, config, y[:, :3] * scales[0], tensions, loads, iterations)
    doubtful = np.flatnonzero(~(solved & result.stable & result.converged))
    if doubtful.size:  # the tension statics' own branch check and stability test
        part = world.rows(doubtful)
        checked = solve_statics(robot, tensions[doubtful], part.tip_force, part.tip_moment,
                                part.gravity, config, distributed_force=part.distributed_force,
                                point_loads=part.point_load_lists())
        result = _replace_rows(result, doubtful, checked)
    stretch = pull - result.tendon_displacements - take_up_lengths(robot, tensions)
    residual = np.max(np.abs(tensions / k - np.maximum(0.0, stretch)), axis=1)
    fields = {f.name: getattr(result, f.name) for f in dataclasses.fields(StaticsResult)}
    fields["converged"] = result.converged & (residual <= DISPLACEMENT_TOLERANCE)
    return DisplacementStaticsResult(**fields, tensions=tensions, pull=pull, stretch=stretch,
                                     displacement_residual=residual)


def _verdict(robot: Robot, config: StaticsConfig, base_moment: np.ndarray,
             tensions: np.ndarray, loads: CaseLoads, iterations: np.ndarray) -> StaticsResult:
    """The tension statics' result fields of the equilibria with M(0) = ``base_moment``
    (base frame, N·m): one finishing pass and the stability test (the tension statics'
    programs), in the world frame; ``iterations``: the Newton iterations that found them."""
    _, _, finish, _ = _statics_programs(robot, config)
    batch = len(tensions)
    out = finish(*_typed(_padded((base_moment, tensions, loads)), np.float64))
    out = {key: np.asarray(v)[:batch] for key, v in out.items()}
    stable = _stable(robot, config, base_moment, tensions, loads, np.float64)
    base_rot = robot.base_rotation
    positions = out["positions"].astype(float) @ base_rot.T + np.asarray(robot.base_position)
    return StaticsResult(
        positions=positions,
        rotations=np.einsum("ij,bpjk->bpik", base_rot, out["rotations"].astype(float)),
        arc_length=_layout(robot, config).arc_length,
        tendon_displacements=out["tendon_displacements"].astype(float),
        converged=out["converged"].astype(bool), residual=out["residual"].astype(float),
        iterations=np.asarray(iterations, int),
        base_moment=out["base_moment"].astype(float) @ base_rot.T,
        base_force=out["base_force"].astype(float) @ base_rot.T,
        stable=stable, equilibria=np.ones(batch, int), snap_load=np.full(batch, np.nan))


def _replace_rows(result: StaticsResult, rows: np.ndarray,
                  checked: StaticsResult) -> StaticsResult:
    """``result`` with the cases ``rows`` taken from ``checked`` (their own solve)."""
    fields = {}
    for f in dataclasses.fields(StaticsResult):
        value = getattr(result, f.name)
        if f.name in ("arc_length", "all_equilibria"):
            fields[f.name] = value
            continue
        value = np.array(value)
        value[rows] = getattr(checked, f.name)
        fields[f.name] = value
    return StaticsResult(**fields)


def predict_marker(robot: Robot, displacements: Any, gravity: Any = None,
                   config: StaticsConfig = StaticsConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(predicted measured points (B, 3) m in the robot file's world frame, converged (B,))
    of commanded displacements (B, n_tendons) m on the Cosserat rod: the tip plus the
    ``actuation`` block's ``tip_marker`` in the tip frame, under ``gravity`` (3,) m/s² in
    the world frame (None: the mechanics block's ``calibration_gravity``, else none)."""
    mech = require_mechanics(robot, "the Cosserat prediction")
    if gravity is None and mech.calibration_gravity:
        gravity = mech.calibration_gravity
    result = solve_displacement_statics(robot, displacements, gravity=gravity, config=config)
    act = robot.actuation or Actuation.nominal(robot.n_tendons, robot.n_segments)
    marker = result.tip_position + result.tip_rotation @ np.asarray(act.tip_marker, float)
    return marker, result.converged


def motor_commands(robot: Robot, tensions: Any, shortening: Any) -> np.ndarray:
    """(B, n_tendons) the commanded displacements d, m, that hold tensions (B, n_tendons) N
    on a solved rod whose tendon paths are shorter than straight by ``shortening`` (B,
    n_tendons) m (``StaticsResult.tendon_displacements``): the pull p = s + Cτ + τ/k (Cτ:
    the take-up, ``take_up_lengths``), d = d0 + p/g (the inverse of
    ``solve_displacement_statics``; a tendon without tension gets the command that leaves
    it just taut, and any smaller one gives the same shape)."""
    k = tendon_stiffness_of(robot)
    act = robot.actuation or Actuation.nominal(robot.n_tendons, robot.n_segments)
    tensions = np.asarray(tensions, float)
    pull = np.asarray(shortening, float) + take_up_lengths(robot, tensions) + tensions / k
    return np.asarray(act.zero_offsets) + pull / np.asarray(act.gains)
