"""Projected Levenberg–Marquardt for chains of waypoints (block-banded normal equations).

Problems over a chain of T waypoints z₀ … z_{T−1} (each z_t of size d) whose residuals
each depend on at most three consecutive waypoints — path following, trajectory
optimisation — have a block-banded Gauss–Newton matrix: JᵀJ is block pentadiagonal with
d × d blocks. Treating it as dense (``stages.refine._lm``) costs O((T·d)³) per iteration; here

- the residuals are given as window terms (``ChainResidual``): a unary term r(z_t), a
  pair term r(z_t, z_{t+1}) and a triple term r(z_t, z_{t+1}, z_{t+2}), each vmapped
  over the chain, so the Jacobian is computed per window (forward mode over k·d
  directions, not T·d);
- the normal matrix is assembled as its blocks: ``diag`` (T, d, d) = H[t, t],
  ``upper1`` (T−1, d, d) = H[t, t+1], ``upper2`` (T−2, d, d) = H[t, t+2];
- the damped system is solved by grouping waypoints in pairs, which makes the matrix
  block *tridiagonal* with 2d × 2d blocks, and running a block Cholesky (block Thomas)
  forward and back in two ``jax.lax.scan`` passes: O(T·d³).

The step rule is that of ``stages.refine._lm``: Marquardt-scaled damping updated by Nielsen's
trust-region rule, a projection onto the limits after every step (``project`` maps a
(T, d) chain onto its feasible set, e.g. ``model.limits.project_z`` per waypoint), and
``free`` masks that keep fixed variables where they are.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np

from ._lm import LMConfig, difference_jacobian, lm_step_rule

UnaryResidual = Callable[[jax.Array, Any, Any], jax.Array]
"""r(z_t, params_t, shared) → (m₁,): depends on one waypoint z_t (d,)."""
PairResidual = Callable[[jax.Array, jax.Array, Any, Any], jax.Array]
"""r(z_t, z_{t+1}, params_t, shared) → (m₂,): depends on two consecutive waypoints."""
TripleResidual = Callable[[jax.Array, jax.Array, jax.Array, Any, Any], jax.Array]
"""r(z_t, z_{t+1}, z_{t+2}, params_t, shared) → (m₃,): three consecutive waypoints."""


@dataclass(frozen=True)
class ChainResidual:
    """The residual of a chain problem as window terms (any may be None).

    ``params`` given to the solver is a pytree whose leaves have leading dimension T (one
    entry per waypoint); a pair or triple term receives the entry of its window's FIRST
    waypoint. ``shared`` is passed unbatched to every term. The functions must be
    hashable (module-level functions or ``functools.partial`` of them with hashable
    arguments): they are static arguments of the compiled solver.
    """

    unary: UnaryResidual | None = None
    pair: PairResidual | None = None
    triple: TripleResidual | None = None
    unary_far: UnaryResidual | None = None
    """A cheaper form of ``unary``: the same rows with the same derivatives wherever
    ``near`` is False (e.g. the tracking rows alone and zeros for clearance penalties that
    vanish with their derivatives far from every obstacle). None: always ``unary``."""
    unary_tail: Callable[[jax.Array, Any, Any], jax.Array] | None = None
    """(z_t, params_t, shared) → (m₁, k): ``unary``'s constant Jacobian with respect to
    a waypoint's last k unknowns, which enter it linearly (a plan's tip unknowns, tied to
    the rod's tip): with difference Jacobians only the others are perturbed (each
    perturbation is a pass of the rod). (Only functions here: ``_by_shape`` walks a
    dataclass of functions.)"""
    near: Callable[[jax.Array, Any, Any], jax.Array] | None = None
    """(z (T, d), params, shared) → bool: whether ``unary`` may differ from ``unary_far``
    anywhere on the chain z. Where False, the Jacobians come from ``unary_far`` (a
    ``lax.cond`` over the whole chain: both run when the solve is vmapped over chains)."""


class BandedMatrix(NamedTuple):
    """A symmetric block-pentadiagonal matrix by its upper blocks (d × d each)."""

    diag: jax.Array
    """(T, d, d): H[t, t]."""
    upper1: jax.Array
    """(T−1, d, d): H[t, t+1]."""
    upper2: jax.Array
    """(T−2, d, d): H[t, t+2]."""


# ================================================================ residuals and Jacobians


def _slice(params: Any, start: int, stop: int) -> Any:
    return jax.tree_util.tree_map(lambda x: x[start:stop], params)


def chain_residuals(terms: ChainResidual, z: jax.Array, params: Any,
                    shared: Any) -> list[jax.Array]:
    """The residual values of a chain z (T, d): one (windows, m_k) array per term present,
    in the order unary, pair, triple."""
    t = z.shape[0]
    out = []
    if terms.unary is not None:
        out.append(jax.vmap(terms.unary, in_axes=(0, 0, None))(z, params, shared))
    if terms.pair is not None:
        out.append(jax.vmap(terms.pair, in_axes=(0, 0, 0, None))(
            z[:-1], z[1:], _slice(params, 0, t - 1), shared))
    if terms.triple is not None:
        out.append(jax.vmap(terms.triple, in_axes=(0, 0, 0, 0, None))(
            z[:-2], z[1:-1], z[2:], _slice(params, 0, t - 2), shared))
    return out


def chain_cost(terms: ChainResidual, z: jax.Array, params: Any, shared: Any) -> jax.Array:
    """½‖r(z)‖² of a chain z (T, d)."""
    return 0.5 * sum(jnp.sum(r * r) for r in chain_residuals(terms, z, params, shared))


def chain_jacobians(terms: ChainResidual, z: jax.Array, params: Any,
                    shared: Any, differences: bool = False
                    ) -> list[tuple[int, jax.Array, jax.Array]]:
    """Per-window residuals and Jacobians: a list of (k, r (W, m), J (W, m, k, d)) for
    each term present, k its window size and W = T − k + 1 its window count; J[w, :, a]
    is the derivative with respect to waypoint w + a. With ``differences`` the unary
    term's Jacobian is taken by forward differences (``LMConfig.jacobian`` other than
    ``"forward"``), the others by forward mode. The chain has no Broyden updates: tried
    per waypoint block (a fresh Jacobian every 2–8 trips and after each rejected step),
    they cut a plan's refine 0.16 → 0.05–0.11 s but left one of 8 refined plans in
    collision and one of 6 followed paths 3 µm inside δ, where differences kept both."""
    t, d = z.shape

    def window_jacobians(fn: Callable, k: int) -> tuple[jax.Array, jax.Array]:
        def window_fn(zw: jax.Array, p: Any, sh: Any) -> tuple[jax.Array, jax.Array]:
            r = fn(*[zw[a] for a in range(k)], p, sh)
            return r, r

        jac = jax.vmap(jax.jacfwd(window_fn, has_aux=True), in_axes=(0, 0, None))
        windows = jnp.stack([z[a: t - k + 1 + a] for a in range(k)], axis=1)   # (W, k, d)
        j, r = jac(windows, _slice(params, 0, t - k + 1), shared)
        return r, j

    out = []
    for k, fn in ((1, terms.unary), (2, terms.pair), (3, terms.triple)):
        if fn is None:
            continue
        if k == 1 and differences:
            if terms.unary_tail is None:
                j, r = difference_jacobian(fn, z, params, shared)
            else:
                tail = jax.vmap(terms.unary_tail, in_axes=(0, 0, None))(z, params, shared)
                j, r = difference_jacobian(fn, z, params, shared, d - tail.shape[-1])
                j = jnp.concatenate([j, tail.astype(j.dtype)], axis=2)
            out.append((1, r, j[:, :, None, :]))
            continue
        if k == 1 and terms.unary_far is not None and terms.near is not None:
            far = terms.unary_far
            r, j = jax.lax.cond(terms.near(z, params, shared),
                                lambda fn=fn: window_jacobians(fn, 1),
                                lambda far=far: window_jacobians(far, 1))
        else:
            r, j = window_jacobians(fn, k)
        out.append((k, r, j))
    return out


def normal_equations(blocks: list[tuple[int, jax.Array, jax.Array]],
                     t: int) -> tuple[BandedMatrix, jax.Array]:
    """Gauss–Newton matrix JᵀJ (as ``BandedMatrix``) and gradient Jᵀr (T, d) from
    ``chain_jacobians``'s blocks, for a chain of ``t`` waypoints. Each term's window
    Jacobian (W, m, k·d) makes one product (W, k·d, k·d), whose d × d blocks are added
    where they belong: one batched product per term instead of one per pair of window
    waypoints (measured on a planning LM trip, 8 slots, 2-core CPU: 0.81–0.86× the
    trip's CPU time)."""
    d = blocks[0][2].shape[-1]
    dtype = blocks[0][2].dtype
    diag = jnp.zeros((t, d, d), dtype)
    upper1 = jnp.zeros((max(t - 1, 0), d, d), dtype)
    upper2 = jnp.zeros((max(t - 2, 0), d, d), dtype)
    grad = jnp.zeros((t, d), dtype)
    for k, r, j in blocks:
        w = t - k + 1
        flat = j.reshape(j.shape[:2] + (k * d,))                       # (W, m, k·d)
        product = jnp.einsum("wmi,wmj->wij", flat, flat)                # (W, k·d, k·d)
        window_grad = jnp.einsum("wmi,wm->wi", flat, r)                 # (W, k·d)
        for a in range(k):
            rows = slice(a * d, (a + 1) * d)
            grad = grad.at[a: a + w].add(window_grad[:, rows])
            for b in range(a, k):
                block = product[:, rows, b * d:(b + 1) * d]
                if b == a:
                    diag = diag.at[a: a + w].add(block)
                elif b == a + 1:
                    upper1 = upper1.at[a: a + w].add(block)
                else:
                    upper2 = upper2.at[a: a + w].add(block)
    return BandedMatrix(diag, upper1, upper2), grad


# ================================================================ linear algebra


def banded_matvec(h: BandedMatrix, x: jax.Array) -> jax.Array:
    """H·x for a symmetric block-pentadiagonal H and x (T, d)."""
    y = jnp.einsum("tij,tj->ti", h.diag, x)
    if h.upper1.shape[0]:
        y = y.at[:-1].add(jnp.einsum("tij,tj->ti", h.upper1, x[1:]))
        y = y.at[1:].add(jnp.einsum("tji,tj->ti", h.upper1, x[:-1]))
    if h.upper2.shape[0]:
        y = y.at[:-2].add(jnp.einsum("tij,tj->ti", h.upper2, x[2:]))
        y = y.at[2:].add(jnp.einsum("tji,tj->ti", h.upper2, x[:-2]))
    return y


def banded_to_dense(h: BandedMatrix) -> np.ndarray:
    """The (T·d, T·d) dense form of a block-pentadiagonal H as numpy (tests, small T)."""
    diag, upper1, upper2 = (np.asarray(x) for x in h)
    t, d, _ = diag.shape
    dense = np.zeros((t * d, t * d), diag.dtype)
    for i in range(t):
        dense[i * d:(i + 1) * d, i * d:(i + 1) * d] = diag[i]
        for off, ups in ((1, upper1), (2, upper2)):
            if i + off < t:
                rows, cols = slice(i * d, (i + 1) * d), slice((i + off) * d, (i + off + 1) * d)
                dense[rows, cols] = ups[i]
                dense[cols, rows] = ups[i].T
    return dense


def _paired(h: BandedMatrix, rhs: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Group waypoints (2s, 2s+1) into one block: the block-tridiagonal form
    (diagonal A (S, 2d, 2d), sub-diagonal C (S, 2d, 2d) with C[s] = H[pair s, pair s−1],
    C[0] = 0) and the paired right-hand side (S, 2d). An odd T gets an identity padding
    waypoint."""
    t, d, _ = h.diag.shape
    dtype = h.diag.dtype
    pad = t % 2
    eye = jnp.eye(d, dtype=dtype)
    zeros = jnp.zeros((1, d, d), dtype)
    diag = jnp.concatenate([h.diag, eye[None]]) if pad else h.diag
    # upper1 of length T' − 1 and upper2 of length T' − 2 for the padded length T'.
    upper1 = jnp.concatenate([h.upper1, zeros] if pad else [h.upper1])
    upper2 = jnp.concatenate([h.upper2, zeros] if pad else [h.upper2])
    rhs = jnp.concatenate([rhs, jnp.zeros((1, d), dtype)]) if pad else rhs
    tp = t + pad
    s = tp // 2
    even, odd = diag[0::2], diag[1::2]
    inner = upper1[0::2]                                   # H[2s, 2s+1]
    a = jnp.concatenate([jnp.concatenate([even, inner], axis=2),
                         jnp.concatenate([jnp.swapaxes(inner, 1, 2), odd], axis=2)], axis=1)
    # Rows (2s, 2s+1) × columns (2s−2, 2s−1), for s ≥ 1:
    # [[H[2s, 2s−2], H[2s, 2s−1]], [0, H[2s+1, 2s−1]]].
    h_20 = jnp.swapaxes(upper2[0::2], 1, 2)                # H[2s+2, 2s], (S−1, d, d)
    h_21 = jnp.swapaxes(upper1[1::2], 1, 2)                # H[2s+2, 2s+1]
    h_31 = jnp.swapaxes(upper2[1::2], 1, 2)                # H[2s+3, 2s+1]
    if h_31.shape[0] < s - 1:                              # T' = 2: no such blocks
        h_31 = jnp.concatenate([h_31, jnp.zeros((s - 1 - h_31.shape[0], d, d), dtype)])
    zero_block = jnp.zeros_like(h_20)
    c_rest = jnp.concatenate([jnp.concatenate([h_20, h_21], axis=2),
                              jnp.concatenate([zero_block, h_31], axis=2)], axis=1)
    c = jnp.concatenate([jnp.zeros((1, 2 * d, 2 * d), dtype), c_rest])
    return a, c, rhs.reshape(s, 2 * d)


def solve_block_tridiagonal(a: jax.Array, c: jax.Array, b: jax.Array) -> jax.Array:
    """Solve a symmetric positive-definite block-tridiagonal system by block Cholesky.

    Args:
        a: (S, k, k) diagonal blocks; c: (S, k, k) sub-diagonal blocks M[s, s−1] (c[0]
            ignored); b: (S, k) right-hand side.
    Returns:
        x (S, k). Two sequential scans of S steps, each a k × k Cholesky, two triangular
        solves and a few products.
    """
    k = a.shape[-1]
    eye = jnp.eye(k, dtype=a.dtype)

    def forward(carry: tuple, inputs: tuple) -> tuple:
        chol_prev, y_prev = carry
        a_s, c_s, b_s = inputs
        # B = C·L_prev⁻ᵀ, L = chol(A − B·Bᵀ), y = L⁻¹(b − B·y_prev).
        coupling = jax.scipy.linalg.solve_triangular(chol_prev, c_s.T, lower=True).T
        chol = jnp.linalg.cholesky(a_s - coupling @ coupling.T)
        y = jax.scipy.linalg.solve_triangular(chol, b_s - coupling @ y_prev, lower=True)
        return (chol, y), (chol, coupling, y)

    c = c.at[0].set(0.0)
    init = (eye, jnp.zeros((k,), a.dtype))
    _, (chol, coupling, y) = jax.lax.scan(forward, init, (a, c, b))

    def backward(x_next: jax.Array, inputs: tuple) -> tuple:
        chol_s, coupling_next, y_s = inputs
        x = jax.scipy.linalg.solve_triangular(chol_s, y_s - coupling_next.T @ x_next,
                                              lower=True, trans="T")
        return x, x

    coupling_next = jnp.concatenate([coupling[1:], jnp.zeros((1, k, k), a.dtype)])
    _, x = jax.lax.scan(backward, jnp.zeros((k,), a.dtype), (chol, coupling_next, y),
                        reverse=True)
    return x


def solve_banded(h: BandedMatrix, rhs: jax.Array) -> jax.Array:
    """Solve H x = rhs for a symmetric positive-definite block-pentadiagonal H, rhs (T, d);
    returns x (T, d)."""
    t, d = rhs.shape
    if t == 1:
        return jnp.linalg.solve(h.diag[0], rhs[0])[None]
    a, c, b = _paired(h, rhs)
    return solve_block_tridiagonal(a, c, b).reshape(-1, d)[:t]


# ================================================================ the solver

DEFAULT_CONFIG = LMConfig()
"""``banded_lm_solve``'s default settings (those of ``stages.refine._lm``)."""


def _damped(h: BandedMatrix, lam: jax.Array, scale: jax.Array) -> BandedMatrix:
    d = h.diag.shape[-1]
    return h._replace(diag=h.diag + lam * scale[:, :, None] * jnp.eye(d, dtype=h.diag.dtype))


class BandedLMState(NamedTuple):
    """The banded LM's loop state between two trips, for one chain (a batch of chains
    adds a leading axis to every field). Carrying it whole lets a solve stop after any
    trip and go on later with exactly the same iterates (``stages.refine._chain_stream``'s
    slots)."""

    z: jax.Array
    """(T, d): the accepted iterate."""
    cost: jax.Array
    """½‖r(z)‖² (inf before the first evaluation)."""
    hessian: BandedMatrix
    """JᵀJ at z, fixed variables masked out."""
    gradient: jax.Array
    """(T, d): Jᵀr at z, zero for fixed variables."""
    damping: jax.Array
    """λ, relative to the diagonal of JᵀJ (Marquardt scaling)."""
    nu: jax.Array
    """ν, the factor λ grows by after a rejected step (Nielsen's rule)."""
    done: jax.Array
    """Converged or stalled."""
    iteration: jax.Array
    """Steps judged so far (int32); −1 before the first evaluation."""
    trial: jax.Array
    """(T, d): the pending trial point, evaluated on the next trip (z0 on the first)."""
    predicted: jax.Array
    """The cost reduction the Gauss–Newton model predicts for ``trial``."""


def banded_lm_start(project: Callable[[jax.Array], jax.Array], z0: jax.Array,
                    config: LMConfig = DEFAULT_CONFIG) -> BandedLMState:
    """The state of a chain solve before its first trip: z0 (T, d) projected, nothing
    evaluated yet (``iteration`` −1)."""
    dtype = z0.dtype
    t, d = z0.shape
    z0 = project(z0)
    eye = jnp.eye(d, dtype=dtype)
    h_init = BandedMatrix(jnp.broadcast_to(eye, (t, d, d)),
                          jnp.zeros((max(t - 1, 0), d, d), dtype),
                          jnp.zeros((max(t - 2, 0), d, d), dtype))
    return BandedLMState(z0, jnp.asarray(jnp.inf, dtype), h_init, jnp.zeros((t, d), dtype),
                         jnp.asarray(config.initial_damping, dtype), jnp.asarray(2.0, dtype),
                         jnp.asarray(False), jnp.int32(-1), z0, jnp.asarray(1.0, dtype))


def banded_lm_running(state: BandedLMState, iterations: jax.Array,
                      config: LMConfig = DEFAULT_CONFIG) -> jax.Array:
    """Whether a chain solve takes another trip: fewer than ``iterations`` steps judged
    and (with ``config.stop_when_converged``) neither converged nor stalled."""
    more = (~state.done | (state.iteration < 0)) if config.stop_when_converged else True
    return (state.iteration < iterations) & more


def banded_lm_trip(terms: ChainResidual, project: Callable[[jax.Array], jax.Array],
                   state: BandedLMState, params: Any, shared: Any, free: jax.Array,
                   config: LMConfig = DEFAULT_CONFIG) -> BandedLMState:
    """One trip of the LM loop: evaluate the normal equations at the pending trial point
    (z0 on the first trip, which is always accepted), judge the step, update λ and ν,
    and propose the next step. Arguments as for ``banded_lm_solve``.

    One evaluation per trip, at the trial point: ``step_system`` is traced once, not once
    before the loop and again inside it (its Jacobians dominate the compilation)."""
    z, cost, h, g, lam, nu, done, it, z_trial, predicted = state
    dtype = z.dtype
    t, d = z.shape
    free = jnp.broadcast_to(free.astype(dtype), (t, d))
    fixed_diag = (1.0 - free)[:, :, None] * jnp.eye(d, dtype=dtype)

    def step_system(z: jax.Array) -> tuple[BandedMatrix, jax.Array, jax.Array]:
        blocks = chain_jacobians(terms, z, params, shared,
                                 differences=config.jacobian != "forward")
        h, g = normal_equations(blocks, t)
        g = g * free
        # Fixed variables: zero coupling, unit diagonal, zero gradient (a zero step).
        h = BandedMatrix(h.diag * free[:, :, None] * free[:, None, :] + fixed_diag,
                         h.upper1 * free[:-1, :, None] * free[1:, None, :],
                         h.upper2 * free[:-2, :, None] * free[2:, None, :])
        cost = 0.5 * sum(jnp.sum(r * r) for _, r, _ in blocks)
        return h, g, cost

    def trial(z: jax.Array, h: BandedMatrix, g: jax.Array,
              lam: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The damped step's trial point and the reduction the model predicts for it."""
        diag = jnp.diagonal(h.diag, axis1=-2, axis2=-1)            # (T, d)
        scale = jnp.maximum(diag, 1e-9 * jnp.max(diag) + 1e-12)
        z_new = project(z + solve_banded(_damped(h, lam, scale), -g))
        actual = z_new - z
        predicted = -(jnp.sum(g * actual) + 0.5 * jnp.sum(actual * banded_matvec(h, actual)))
        return z_new, predicted

    first = it < 0
    h_new, g_new, cost_new = step_system(z_trial)
    verdict = lm_step_rule(config, cost, cost_new, predicted, lam, nu, done, it + 1, first)
    keep = partial(jnp.where, verdict.accept)
    z, h, g = keep(z_trial, z), jax.tree_util.tree_map(keep, h_new, h), keep(g_new, g)
    cost, done, lam, nu = verdict.cost, verdict.done, verdict.damping, verdict.growth
    z_trial, predicted = trial(z, h, g, lam)
    if config.prediction_tolerance > 0.0:  # off: float32 can predict a tiny negative gain
        # Nothing left for the model to gain: later trips could only reject or stall.
        done = done | (~first & (predicted < config.prediction_tolerance * cost))
    return BandedLMState(z, cost, h, g, lam, nu, done, it + 1, z_trial, predicted)


@partial(jax.jit, static_argnames=("terms", "project", "config"))
def banded_lm_solve(terms: ChainResidual, project: Callable[[jax.Array], jax.Array],
                    z0: jax.Array, params: Any, shared: Any, free: jax.Array,
                    iterations: jax.Array,
                    config: LMConfig = DEFAULT_CONFIG) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Run projected LM on one chain.

    Args:
        terms: the window residual terms (``ChainResidual``).
        project: feasibility projection of a (T, d) chain (hashable).
        z0: (T, d) starting chain (projected first).
        params: pytree of per-waypoint data, leaves with leading dimension T.
        shared: pytree passed unbatched to every term.
        free: (d,) or (T, d): 1.0 for variables the solver may move, 0.0 for fixed ones.
        iterations: maximum iterations (a traced integer: no recompilation per budget).
        config: damping and stopping rules (``stages.refine._lm.LMConfig``; ``linear_solver`` is
            not used: the banded solve is always the block Cholesky).

    Returns:
        z (T, d), final cost ½‖r‖² (scalar), iterations used (scalar).
    """
    state = jax.lax.while_loop(
        partial(banded_lm_running, iterations=iterations, config=config),
        partial(banded_lm_trip, terms, project, params=params, shared=shared, free=free,
                config=config),
        banded_lm_start(project, z0, config))
    return state.z, state.cost, state.iteration
