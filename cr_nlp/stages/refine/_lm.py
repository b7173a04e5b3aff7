"""Batched projected Levenberg–Marquardt in JAX (stage 2, "refine", and stage 1's coarse steps).

Every problem in the batch minimises ½‖r(z; p)‖² over its own z, with box-like
limits enforced *exactly* by a projection after each step (the bending-vector
disk ‖u‖ ≤ θmax, the length range), and everything else (clearance) as penalty
residuals inside r. Damping follows Nielsen's trust-region rule; the damped
normal equations are solved by a Cholesky factorisation unrolled over matrix
entries, which XLA fuses across the batch (faster than batched LAPACK calls at
these sizes).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg

from ...runtime import cached

Residual = Callable[[jax.Array, Any, Any], jax.Array]
"""r(z, params, shared) for ONE problem: z (n,), params this problem's pytree, shared the
batch's common data (e.g. scene arrays); returns (m,)."""
Projection = Callable[[jax.Array], jax.Array]
"""Maps a batch of iterates (B, n) onto the feasible box-like set."""


@dataclass(frozen=True)
class LMConfig:
    """Levenberg–Marquardt settings (the iteration budget is a run-time argument)."""

    initial_damping: float = 1e-2
    """Starting λ relative to the diagonal of JᵀJ (Marquardt scaling)."""
    cost_tolerance: float = 1e-12
    """A problem counts as converged once ½‖r‖² is below this (units of r squared)."""
    stall_tolerance: float = 1e-4
    """...or once an accepted step lowers the cost by less than this fraction."""
    prediction_tolerance: float = 0.0
    """(``stages.refine._banded_lm`` only) ...or once the next proposed step is predicted by the
    Gauss–Newton model to lower the cost by less than this fraction: a run of rejected
    steps at that size would end in the stall rule or the λ cap anyway. 0: off."""
    give_up: tuple[tuple[int, float], ...] = ()
    """...or once, at any checkpoint (steps judged, cost ½‖r‖² in units of r squared) of
    this tuple, that many steps were judged while the cost is still above that cost: a
    problem stuck far from an answer (e.g. a trajectory through an obstacle) stops instead
    of creeping on to the iteration budget, and no longer keeps the batch's loop running.
    (): off."""
    stop_when_converged: bool = True
    """End the loop early once every problem in the batch converged or stalled."""
    linear_solver: str = "unrolled"
    """How the damped normal equations are solved: ``"unrolled"`` (``solve_spd``, fastest
    for n ≲ 24 but its program grows as n³) or ``"cholesky"`` (batched LAPACK
    ``cho_factor``/``cho_solve``, for large n such as a whole trajectory)."""

    jacobian: str = "forward"
    """How the Jacobian is taken: ``"forward"`` (forward-mode derivatives, exact) or
    ``"differences"`` (forward differences: n + 1 residual evaluations in one vectorised
    call, steps √ε·max(|z|, 1), so z should be scaled to order one). Differences serve
    residuals whose forward-mode derivative XLA compiles poorly, such as an ODE
    integration with inner fixed-point sweeps (the Cosserat rod). ``"broyden"``: forward
    differences every ``refresh`` trips and Broyden's rank-one secant update in between,
    one residual evaluation per trip instead of n + 1 (for expensive residuals started
    near their answer; the loop keeps J (B, m, n), so not for very large batches)."""
    refresh: int = 4
    """(``jacobian="broyden"``) trips between two difference Jacobians."""

    def __post_init__(self) -> None:
        if self.refresh < 1:
            raise ValueError(f"refresh must be at least 1, got {self.refresh}")
        if self.linear_solver not in ("unrolled", "cholesky"):
            raise ValueError(f"linear_solver must be 'unrolled' or 'cholesky', "
                             f"got {self.linear_solver!r}")
        if self.jacobian not in ("forward", "differences", "broyden"):
            raise ValueError(f"jacobian must be 'forward', 'differences' or 'broyden', "
                             f"got {self.jacobian!r}")


def solve_spd(a: jax.Array, b: jax.Array) -> jax.Array:
    """Solve A x = b for a batch of small symmetric positive-definite A (…, n, n), b (…, n).

    Cholesky unrolled over entries: O(n³/6) fused elementwise operations over the batch.
    """
    n = a.shape[-1]
    ent = [[a[..., i, j] for j in range(n)] for i in range(n)]
    chol: list[list[Any]] = [[None] * n for _ in range(n)]
    for j in range(n):
        s = ent[j][j] - sum(chol[j][k] * chol[j][k] for k in range(j))
        chol[j][j] = jnp.sqrt(jnp.maximum(s, 1e-30))
        inv = 1.0 / chol[j][j]
        for i in range(j + 1, n):
            chol[i][j] = (ent[i][j] - sum(chol[i][k] * chol[j][k] for k in range(j))) * inv
    y: list[Any] = [None] * n
    for i in range(n):
        y[i] = (b[..., i] - sum(chol[i][k] * y[k] for k in range(i))) / chol[i][i]
    x: list[Any] = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(chol[k][i] * x[k] for k in range(i + 1, n))) / chol[i][i]
    return jnp.stack(x, axis=-1)


def solve_spd_cholesky(a: jax.Array, b: jax.Array) -> jax.Array:
    """Solve A x = b for a batch of symmetric positive-definite A (…, n, n), b (…, n) with
    batched LAPACK Cholesky (``jax.scipy.linalg.cho_factor``/``cho_solve``)."""
    factor = jax.scipy.linalg.cho_factor(a, lower=True)
    return jax.scipy.linalg.cho_solve(factor, b[..., None])[..., 0]


def difference_jacobian(residual: Residual, z: jax.Array, params: Any,
                        shared: Any, columns: int | None = None) -> tuple[jax.Array, jax.Array]:
    """(J (B, m, k), r (B, m)) by forward differences over the first k = ``columns``
    unknowns (None: all n), all k + 1 points in one call."""
    k = z.shape[-1] if columns is None else columns
    h = jnp.sqrt(jnp.finfo(z.dtype).eps) * jnp.maximum(jnp.abs(z[:, :k]), 1.0)   # (B, k)
    steps = jnp.eye(z.shape[-1], dtype=z.dtype)[:k] * h[:, :, None]            # (B, k, n)
    points = jnp.concatenate([z[:, None], z[:, None] + steps], axis=1)     # (B, k + 1, n)
    each = jax.vmap(jax.vmap(residual, in_axes=(0, None, None)), in_axes=(0, 0, None))
    r = each(points, params, shared)                                       # (B, k + 1, m)
    j = (r[:, 1:] - r[:, :1]) / h[:, :, None]                              # (B, k, m)
    return jnp.swapaxes(j, 1, 2), r[:, 0]


def gave_up(config: LMConfig, judged: jax.Array, cost: jax.Array) -> jax.Array | bool:
    """The give-up rule (``LMConfig.give_up``): at some checkpoint, at least its steps
    judged and the cost still above its cost; False when the rule is off."""
    out: jax.Array | bool = False
    for steps, limit in config.give_up:
        out = out | ((judged >= steps) & (cost > limit))
    return out


STOP_REASONS = ("running", "converged", "stalled", "damping cap", "gave up",
                "out of iterations")
"""Why an LM problem stopped, by code (``LMSolution.reason``, ``Judgement.stop``): still
running (a loop's state only), its cost below ``cost_tolerance``, an accepted step that
gained less than ``stall_tolerance``, λ past 1e10, the give-up rule
(``LMConfig.give_up``), or the iteration budget spent first."""


class LMSolution(NamedTuple):
    """``lm_solve``'s answer: per problem, and the loop's trips."""

    z: jax.Array
    """(B, n) the last accepted iterates."""
    cost: jax.Array
    """(B,) their cost ½‖r‖²."""
    iterations: jax.Array
    """The loop's trips (a scalar: the batch iterates together)."""
    reason: jax.Array
    """(B,) int8, why each problem stopped: an index of ``STOP_REASONS`` (1–5)."""

    def reasons(self) -> list[str]:
        """``reason`` in words (host side)."""
        return [STOP_REASONS[int(k)] for k in jax.device_get(self.reason)]


class Judgement(NamedTuple):
    """``lm_step_rule``'s verdict on one trial step (per problem)."""

    accept: jax.Array
    """Whether the trial point replaces the iterate."""
    cost: jax.Array
    """The cost after the verdict (the trial's where accepted)."""
    done: jax.Array
    """Converged, stalled, out of damping or given up."""
    damping: jax.Array
    """λ for the next step."""
    growth: jax.Array
    """ν, the factor λ grows by after the next rejection."""
    stop: jax.Array
    """int8, why this step ended the problem (an index of ``STOP_REASONS``; 0 where it
    did not, or where the problem was done before)."""


def lm_step_rule(config: LMConfig, cost: jax.Array, cost_new: jax.Array, predicted: jax.Array,
               damping: jax.Array, growth: jax.Array, done: jax.Array, judged: jax.Array,
               first: jax.Array | bool = False) -> Judgement:
    """The one step rule of both LMs (this dense one and ``stages.refine._banded_lm``).

    A trial step is accepted when it lowers the cost ½‖r‖² (and is finite); the problem
    is done once it converged (cost below ``cost_tolerance``), stalled (an accepted step
    gained less than ``stall_tolerance`` of the cost), ran out of damping (λ > 1e10) or
    gave up (``gave_up`` after ``judged`` steps). λ follows Nielsen's rule: on
    acceptance λ·max(⅓, 1 − (2ρ − 1)³) with ρ the actual over the predicted reduction and
    ν = 2; on rejection λ·ν and ν doubles; λ stays in [1e-12, 1e12]. ``first`` marks a
    trip that only evaluates the starting point: accepted, λ and ν kept."""
    first = jnp.asarray(first)
    rho = (cost - cost_new) / jnp.maximum(predicted, 1e-30)
    accept = first | ((cost_new < cost) & jnp.isfinite(cost_new))
    stalled = ~first & accept & (cost - cost_new < config.stall_tolerance * cost)
    converged = cost_new < config.cost_tolerance
    capped = damping > 1e10
    cost = jnp.where(accept, cost_new, cost)
    given_up = gave_up(config, judged, cost)  # still deep in a penalty
    stop = jnp.select([done, converged, stalled, capped, jnp.asarray(given_up) & ~first],
                      [0, 1, 2, 3, 4], 0).astype(jnp.int8)
    done = done | stalled | converged | capped | given_up
    shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * jnp.clip(rho, 0.0, 1.0) - 1.0) ** 3)
    stepped = jnp.clip(jnp.where(accept, damping * shrink, damping * growth), 1e-12, 1e12)
    dtype = damping.dtype
    return Judgement(accept, cost, done, jnp.where(first, damping, stepped).astype(dtype),
                     jnp.where(first, growth, jnp.where(accept, 2.0, growth * 2.0)).astype(dtype),
                     stop)


def iteration_budget(iterations: int) -> jax.Array:
    """``iterations`` as the traced integer ``lm_solve`` and ``banded_lm_solve`` take (a
    weakly typed scalar, int64 under ``jax.enable_x64``), made once per value: an eager
    ``jnp.asarray`` per call cost a live update 0.1–0.4 ms of its host time."""
    return _budget(int(iterations), bool(jax.config.jax_enable_x64))


@cached(maxsize=64)
def _budget(iterations: int, x64: bool) -> jax.Array:
    return jnp.asarray(iterations)


@partial(jax.jit, static_argnames=("residual", "project", "config"))
def lm_solve(residual: Residual, project: Projection, z0: jax.Array, params: Any, shared: Any,
             free: jax.Array, iterations: jax.Array, config: LMConfig = LMConfig(),
             bounds: tuple[jax.Array, jax.Array] | None = None,
             damping: jax.Array | None = None) -> LMSolution:
    """Run projected LM on a batch.

    Long: one traced while_loop whose step helpers close over residual, bounds and config.

    Args:
        residual: r(z, params) of one problem (see ``Residual``); must be hashable (a
            module-level function or a ``functools.partial`` of one with hashable args).
        project: feasibility projection of a (B, n) batch.
        z0: (B, n) starting points (projected first).
        params: pytree whose leaves have leading dimension B.
        shared: pytree passed unbatched to every problem's residual.
        free: (n,) 1.0 for variables the solver may move, 0.0 for fixed ones.
        iterations: maximum iterations (a traced integer: no recompilation per budget).
        config: tolerances and damping.
        bounds: optional (lower (n,), upper (n,)) box that ``project`` enforces (±inf where
            none). A variable on its bound whose gradient points out of the box is held
            there for the step (the projected-Newton active set), so that the step of the
            others is not spoiled by a clipped one.
        damping: optional (B,) starting damping of each problem, replacing
            ``config.initial_damping`` (data: solvers that differ only by it share one
            compiled program).

    Returns:
        ``LMSolution``: z (B, n), final cost ½‖r‖² (B,), iterations used (scalar) and why
        each problem stopped (``STOP_REASONS``).
    """
    if config.jacobian == "broyden":
        return _broyden_solve(residual, project, z0, params, shared, free, iterations,
                              config, bounds, damping)
    dtype = z0.dtype
    free = free.astype(dtype)
    z0 = project(z0)
    solve = solve_spd_cholesky if config.linear_solver == "cholesky" else solve_spd

    def with_value(z: jax.Array, p: Any, sh: Any) -> tuple[jax.Array, jax.Array]:
        r = residual(z, p, sh)
        return r, r

    # One forward-mode pass gives the Jacobian and the residual together.
    jac_and_residual = jax.vmap(jax.jacfwd(with_value, has_aux=True), in_axes=(0, 0, None))
    if config.jacobian == "differences":
        jac_and_residual = partial(difference_jacobian, residual)

    def normal_equations(z: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """JᵀJ (B, n, n), Jᵀr (B, n) over the free variables, and the cost ½‖r‖² (B,)."""
        j, r = jac_and_residual(z, params, shared)
        j = j * free
        return (*normal_products(j, r), 0.5 * jnp.sum(r * r, axis=-1))

    def trial(z: jax.Array, h: jax.Array, g: jax.Array,
              lam: jax.Array) -> tuple[jax.Array, jax.Array]:
        return damped_trial(z, h, g, lam, free, project, solve, bounds)

    def body(state: tuple) -> tuple:
        # One evaluation per trip, at the trial point (z0 on the first trip, which is
        # always accepted): the residual and its Jacobian are traced once, and a
        # rejected step costs no new Jacobian at the point it came from.
        z, h, g, cost, z_trial, predicted, lam, nu, done, why, it = state
        first = it < 0
        h_new, g_new, cost_new = normal_equations(z_trial)
        verdict = lm_step_rule(config, cost, cost_new, predicted, lam, nu, done, it + 1, first)
        accept = verdict.accept
        z = jnp.where(accept[:, None], z_trial, z)
        h = jnp.where(accept[:, None, None], h_new, h)
        g = jnp.where(accept[:, None], g_new, g)
        cost, done, lam, nu = verdict.cost, verdict.done, verdict.damping, verdict.growth
        why = jnp.where(why == 0, verdict.stop, why)
        z_trial, predicted = trial(z, h, g, lam)
        return z, h, g, cost, z_trial, predicted, lam, nu, done, why, it + 1

    running = partial(_running, config, iterations)

    # Derived from z0 (not jnp.full) so that under shard_map they vary per shard too.
    zero = jnp.zeros_like(z0[:, 0])
    lam0 = zero + jnp.asarray(config.initial_damping if damping is None else damping, dtype)
    nu0 = zero + jnp.asarray(2.0, dtype)
    state = (z0, jnp.zeros_like(z0[:, :, None] * z0[:, None, :]), jnp.zeros_like(z0),
             zero + jnp.inf, z0, zero, lam0, nu0, zero > 0, (zero > 0).astype(jnp.int8),
             jnp.int32(-1))
    z, _, _, cost, *_, why, it = jax.lax.while_loop(running, body, state)
    out_of_iterations = jnp.asarray(STOP_REASONS.index("out of iterations"), jnp.int8)
    return LMSolution(z, cost, it, jnp.where(why == 0, out_of_iterations, why))


def _running(config: LMConfig, iterations: jax.Array, state: tuple) -> jax.Array:
    """Whether the LM loop takes another trip (both loops' states end with done, it):
    fewer than ``iterations`` trips and, with ``stop_when_converged``, some problem still
    running (always the first trip)."""
    *_, done, it = state
    more = (~jnp.all(done) | (it < 0)) if config.stop_when_converged else True
    return (it < iterations) & more


def normal_products(j: jax.Array, r: jax.Array) -> tuple[jax.Array, jax.Array]:
    """JᵀJ (B, n, n) and Jᵀr (B, n) of Jacobians j (B, m, n) and residuals r (B, m), as
    products summed over the rows rather than batched matrix products: XLA's CPU backend
    runs a batch of small matrix products as one slow operation (tdcr3's IK search: 18 % of
    its time, 110 µs per LM iteration of 128 rows), where these fuse into the loop
    (10 000 free tdcr3 targets: 2.29–2.35 s against 2.67–3.11 s, alternated)."""
    return jnp.sum(j[:, :, :, None] * j[:, :, None, :], axis=1), jnp.sum(j * r[:, :, None], axis=1)


def damped_trial(z: jax.Array, h: jax.Array, g: jax.Array, lam: jax.Array, free: jax.Array,
                 project: Projection, solve: Callable,
                 bounds: tuple[jax.Array, jax.Array] | None) -> tuple[jax.Array, jax.Array]:
    """The damped step's trial point (B, n) from JᵀJ ``h`` and Jᵀr ``g`` and the reduction
    the Gauss–Newton model predicts for it (B,) (see ``lm_solve``'s ``bounds``)."""
    dtype = z.dtype
    if bounds is None:
        h = h + jnp.diag(1.0 - free)        # JᵀJ is zero off the free variables already
    else:
        tight = 1e-12 * (1.0 + jnp.abs(z))
        held = (((z <= bounds[0] + tight) & (g > 0))
                | ((z >= bounds[1] - tight) & (g < 0)))
        moving = free * (1.0 - held.astype(dtype))                          # (B, n)
        g = g * moving
        h = (h * moving[:, :, None] * moving[:, None, :]
             + jax.vmap(jnp.diag)(1.0 - moving))
    diag = jnp.diagonal(h, axis1=-2, axis2=-1)
    # Marquardt scaling with a floor so a vanishing column still gets damped.
    scale = jnp.maximum(diag, 1e-9 * jnp.max(diag, axis=-1, keepdims=True) + 1e-12)
    z_new = project(z + solve(h + lam[:, None, None] * jax.vmap(jnp.diag)(scale), -g))
    actual = z_new - z
    predicted = -(jnp.sum(g * actual, -1)
                  + 0.5 * jnp.einsum("bi,bij,bj->b", actual, h, actual))
    return z_new, predicted


def _broyden_solve(residual: Residual, project: Projection, z0: jax.Array, params: Any,
                   shared: Any, free: jax.Array, iterations: jax.Array, config: LMConfig,
                   bounds: tuple[jax.Array, jax.Array] | None,
                   damping: jax.Array | None = None) -> LMSolution:
    """``lm_solve`` with ``jacobian="broyden"``: the loop keeps J and r of the current
    iterate; a trip evaluates the trial point's residual only and updates J by Broyden's
    rule J += (r_t − r − J s) sᵀ / sᵀs along the step s (accepted or not: the secant
    holds either way), except every ``config.refresh`` trips, where the whole batch takes
    a difference Jacobian at its trial point. Same step rule, stops and answer."""
    dtype = z0.dtype
    free = free.astype(dtype)
    z0 = project(z0)
    solve = solve_spd_cholesky if config.linear_solver == "cholesky" else solve_spd
    each = jax.vmap(residual, in_axes=(0, 0, None))

    def fresh(z_t: jax.Array, *_: Any) -> tuple[jax.Array, jax.Array]:
        return difference_jacobian(residual, z_t, params, shared)

    def secant(z_t: jax.Array, z: jax.Array, j: jax.Array,
               r: jax.Array) -> tuple[jax.Array, jax.Array]:
        r_t = each(z_t, params, shared)
        s = z_t - z
        ss = jnp.sum(s * s, axis=-1)
        miss = r_t - r - jnp.einsum("bmn,bn->bm", j, s)
        update = miss[:, :, None] * s[:, None, :] / jnp.where(ss > 0, ss, 1.0)[:, None, None]
        return jnp.where((ss > 0)[:, None, None], j + update, j), r_t

    def body(state: tuple) -> tuple:
        z, j, r, cost, z_trial, predicted, lam, nu, done, why, it = state
        first = it < 0
        j_t, r_t = jax.lax.cond(first | ((it + 1) % config.refresh == 0), fresh, secant,
                                z_trial, z, j, r)
        j_t = j_t * free
        cost_new = 0.5 * jnp.sum(r_t * r_t, axis=-1)
        verdict = lm_step_rule(config, cost, cost_new, predicted, lam, nu, done, it + 1, first)
        accept = verdict.accept
        z = jnp.where(accept[:, None], z_trial, z)
        r = jnp.where(accept[:, None], r_t, r)
        j = j_t      # the secant along a rejected step still describes the residual
        cost, done, lam, nu = verdict.cost, verdict.done, verdict.damping, verdict.growth
        why = jnp.where(why == 0, verdict.stop, why)
        z_trial, predicted = damped_trial(z, *normal_products(j, r), lam, free, project,
                                          solve, bounds)
        return z, j, r, cost, z_trial, predicted, lam, nu, done, why, it + 1

    running = partial(_running, config, iterations)

    zero = jnp.zeros_like(z0[:, 0])
    r0 = jax.eval_shape(lambda: each(z0, params, shared))
    j0 = jnp.zeros((*r0.shape, z0.shape[1]), dtype) + zero[:, None, None]
    state = (z0, j0, jnp.zeros(r0.shape, dtype) + zero[:, None], zero + jnp.inf, z0, zero,
             zero + jnp.asarray(config.initial_damping if damping is None else damping, dtype),
             zero + jnp.asarray(2.0, dtype),
             zero > 0, (zero > 0).astype(jnp.int8), jnp.int32(-1))
    z, _, _, cost, *_, why, it = jax.lax.while_loop(running, body, state)
    out_of_iterations = jnp.asarray(STOP_REASONS.index("out of iterations"), jnp.int8)
    return LMSolution(z, cost, it, jnp.where(why == 0, out_of_iterations, why))
