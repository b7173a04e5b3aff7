"""Stages 1–2 as one device program: coarse LM on every seed, beam selection, and the
refinement rounds, for one chunk of targets.

Instead of launching the coarse LM, the beam selection and each refinement round as
separate programs and repacking the unfinished problems on the host between rounds (the
form this search replaced: 25 device calls per 1000-target solve instead of 2), the
whole search is one jitted program (driven by ``stages.refine._ik_driver``): every row (target
× seed) stays in one array, a boolean mask says which rows iterate, and
``lax.while_loop`` runs the rounds. So that finished rows cost
nothing on a CPU either, each round gathers its active rows to the front (a stable
sort of the mask) and runs LM on them in blocks of ``SearchPlan.block`` rows, as many
blocks as there are active rows; on a GPU one block holds the whole chunk.
``retry_targets`` runs every retry round for the targets still failing as one more
program: fresh seeds (pool lookup and random draws on the device), the same masked
search, rounds until every target succeeded.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

from ..explore._seed_pool import nearest_features, select_beam_device
from ._lm import LMConfig, Projection, Residual, lm_solve

Sampler = Callable[[jax.Array], jax.Array]
"""(key) → (count, n) random starting points (bending-vector units)."""


@dataclass(frozen=True)
class SearchPlan:
    """Static settings of ``search_targets`` (one compiled program per plan and shape)."""

    width: int
    """Beam candidates kept per target for refinement."""
    coarse_iterations: int
    """LM iterations on every seed before the beam is chosen."""
    refine_iterations: int
    """LM iterations on the beam in all."""
    refine_round: int
    """Iterations per refinement round; after each round a candidate stops when its cost
    is below ``lm.cost_tolerance``, when the round lowered it by less than 1 %, or (with
    ``per_target``) when another candidate of its target got below that tolerance."""
    per_target: bool
    """Only the best candidate per target is wanted (see ``refine_round``)."""
    min_distance: float
    """Beam diversity radius in bending-vector units (rad, m)."""
    block: int
    """Rows per LM block (per device): the compute granularity of a masked round."""
    lm: LMConfig = LMConfig()
    """LM tolerances and damping (damping restarts each round)."""

    @property
    def rounds(self) -> int:
        """Rounds in all: the coarse one, then the refinement rounds."""
        return 1 + -(-self.refine_iterations // max(self.refine_round, 1))

    @property
    def budgets(self) -> tuple[int, ...]:
        """LM iterations of each round: the coarse one, then ``refine_round`` at a time
        (the last one what is left of ``refine_iterations``)."""
        step = max(self.refine_round, 1)
        return (self.coarse_iterations, *(min(step, self.refine_iterations - r * step)
                                          for r in range(self.rounds - 1)))


def _lm_on_active(residual: Residual, project: Projection, plan: SearchPlan, z: jax.Array,
                  cost: jax.Array, active: jax.Array, target_of: jax.Array, params: Any,
                  shared: Any, free: jax.Array, iterations: jax.Array) -> tuple:
    """LM on the rows where ``active`` holds, in blocks of ``plan.block``: (z, cost, most
    iterations any block ran). Inactive rows are left untouched and cost no compute."""
    rows = z.shape[0]
    block = min(plan.block, rows)
    blocks = -(-rows // block)
    order = jnp.argsort(~active, stable=True).astype(jnp.int32)  # active rows first
    order = jnp.concatenate([order, jnp.zeros(blocks * block - rows, jnp.int32)])
    count = jnp.sum(active, dtype=jnp.int32)
    slots = jnp.arange(block, dtype=jnp.int32)

    def body(state: tuple) -> tuple:
        b, z, cost, used = state
        slot = b * block + slots
        live = slot < count
        first = jax.lax.dynamic_index_in_dim(order, b * block, keepdims=False)
        # A slot past the active rows repeats the block's first row (which is active):
        # it iterates exactly as that row, so it never holds the block's loop back.
        idx = jnp.where(live, jax.lax.dynamic_slice_in_dim(order, b * block, block), first)
        block_params = jax.tree.map(lambda p: p[target_of[idx]], params)
        z_b, c_b, it, _ = lm_solve(residual, project, z[idx], block_params, shared, free,
                                iterations, config=plan.lm)
        write = jnp.where(live, idx, rows)  # out of range: dropped
        z = z.at[write].set(z_b, mode="drop")
        cost = cost.at[write].set(c_b, mode="drop")
        return b + 1, z, cost, jnp.maximum(used, it)

    def more(state: tuple) -> jax.Array:
        return state[0] * block < count

    _, z, cost, used = jax.lax.while_loop(more, body, (jnp.int32(0), z, cost, jnp.int32(0)))
    return z, cost, used


def search_targets(residual: Residual, project: Projection, plan: SearchPlan,
                   z_seeds: jax.Array, params: Any, valid: jax.Array, shared: Any,
                   free: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Coarse LM on (T, K) seeds, a diverse beam of ``plan.width``, refinement rounds.

    Args:
        residual, project: the problem, as for ``stages.refine._lm.lm_solve``.
        plan: static settings.
        z_seeds: (T, K, n) starting points (bending-vector units, rad and m).
        params: pytree of per-target leaves with leading dimension T.
        valid: (T,) False for padding targets (never iterated).
        shared: pytree given whole to every residual (scene arrays).
        free: (n,) 1.0 for the variables LM may move.

    Returns:
        z (T, width, n) and cost ½‖r‖² (T, width) of the refined beam, best first (NaN
        last), and per round (coarse first) the rows iterated (1, rounds) and the most LM
        iterations any of its blocks ran (1, rounds), for profiling (the leading 1 is one
        row per device).
    """
    z, cost, counted, iterated = _search_rows(residual, project, plan, z_seeds, params,
                                              valid, shared, free)
    # Sorted here, not on the host: 10⁵ targets' beams took ~0.04 s of host time.
    order = jnp.argsort(cost, axis=1)
    return (jnp.take_along_axis(z, order[..., None], axis=1),
            jnp.take_along_axis(cost, order, axis=1), counted[None], iterated[None])


def search_pooled(residual: Residual, project: Projection, plan: SearchPlan, seeds: int,
                  features: jax.Array, params: Any, valid: jax.Array, shared: Any,
                  free: jax.Array, pool: tuple) -> tuple[jax.Array, jax.Array, jax.Array,
                                                         jax.Array]:
    """``search_targets`` from the ``seeds`` pool entries nearest each target in pose,
    looked up in the same program (``explore.nearest_features``): the targets' pose
    features (T, 9) go in, not their seeds (T, seeds, n), and no indices come back to the
    host between the lookup and the search. ``pool``: ``SeedPool.device_arrays(padded=
    True)``; ``seeds`` at most the pool's valid entries."""
    pool_features, pool_valid, pool_z = pool
    nearest = nearest_features(pool_features, pool_valid, features, seeds)
    return search_targets(residual, project, plan, pool_z[nearest], params, valid, shared,
                          free)


def _search_rows(residual: Residual, project: Projection, plan: SearchPlan,
                 z_seeds: jax.Array, params: Any, valid: jax.Array, shared: Any,
                 free: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """``search_targets`` with the per-round counts as (rounds,) arrays."""
    t, k, n = z_seeds.shape
    rows = t * k
    width = min(plan.width, k)
    dtype = z_seeds.dtype
    target_of = jnp.arange(rows, dtype=jnp.int32) // k
    tolerance = plan.lm.cost_tolerance
    rounds = plan.rounds

    budgets = jnp.asarray(plan.budgets, jnp.int32)

    def beam_of(z: jax.Array, cost: jax.Array) -> jax.Array:
        picked = select_beam_device(z.reshape(t, k, n), cost.reshape(t, k), width,
                                    plan.min_distance)
        return picked + jnp.arange(t, dtype=jnp.int32)[:, None] * k  # (t, width) rows

    def body(state: tuple) -> tuple:
        r, z, cost, active, beam, counted, iterated = state
        before = cost
        z, cost, used = _lm_on_active(residual, project, plan, z, cost, active, target_of,
                                      params, shared, free, budgets[r])
        counted = counted.at[r].set(jnp.sum(active, dtype=jnp.int32))
        iterated = iterated.at[r].set(used)

        def choose_beam(_: None) -> tuple:
            chosen = beam_of(z, cost)
            in_beam = jnp.zeros(rows, bool).at[chosen.reshape(-1)].set(True)
            return chosen, in_beam & jnp.repeat(valid, k)

        def go_on(_: None) -> tuple:
            # The first refinement round always counts as improving (the coarse cost is
            # no baseline: damping restarts).
            baseline = jnp.where(r == 1, jnp.inf, before)
            keep = active & (cost < 0.99 * baseline) & (cost > tolerance)
            if plan.per_target:
                best = jnp.min(cost[beam], axis=1)  # (t,)
                keep &= best[target_of] > tolerance
            return beam, keep

        beam, active = jax.lax.cond(r == 0, choose_beam, go_on, None)
        return r + 1, z, cost, active, beam, counted, iterated

    def more(state: tuple) -> jax.Array:
        r, *_, active, _, _, _ = state
        return (r < rounds) & jnp.any(active)

    active = jnp.repeat(valid, k)
    # Derived from the inputs, so that split over devices every carry varies per shard.
    zero = jnp.sum(z_seeds[:1, :1, :1]) * 0
    cost = jnp.full(rows, jnp.inf, dtype) + zero
    beam = jnp.zeros((t, width), jnp.int32) + zero.astype(jnp.int32)
    stats = jnp.zeros(rounds, jnp.int32) + zero.astype(jnp.int32)
    state = (jnp.int32(0), z_seeds.reshape(rows, n), cost, active, beam, stats, stats)
    _, z, cost, _, beam, counted, iterated = jax.lax.while_loop(more, body, state)
    return z[beam], cost[beam], counted, iterated


@dataclass(frozen=True)
class RetryPlan:
    """Static settings of ``retry_targets``."""

    rounds: int
    """Retry rounds at most; a round runs only if some target is still failing."""
    seeds: int
    """Seeds per failing target in a round: its best answer so far, ``nearest``
    next-nearest pool entries, random configurations for the rest."""
    nearest: int
    """Next-nearest pool entries among a round's seeds (further down the pool's ranking
    each round)."""
    first_rank: int
    """Pool ranks the main search already used (its seeds per target)."""
    success_cost: float
    """A target whose best cost ½‖r‖² is not below this is failing."""
    seed: int
    """Seed of the random configurations (``jax.random``)."""


def retry_targets(residual: Residual, project: Projection, sample: Sampler,
                  plan: SearchPlan, retry: RetryPlan, z_best: jax.Array, c_best: jax.Array,
                  params: Any, features: jax.Array, stream: jax.Array, valid: jax.Array,
                  shared: Any, free: jax.Array, pool: tuple) -> tuple:
    """Up to ``retry.rounds`` retry rounds, as one program, for targets whose best cost
    after ``search_targets`` is still above ``retry.success_cost``.

    A round is the same masked search (``plan``) on ``retry.seeds`` seeds per target,
    only for the targets still failing: the target's best answer so far, its next-nearest
    pool entries (one lookup on the device, in the first round) and random
    configurations within the limits (``sample``, keyed by ``retry.seed``, the target's
    ``stream`` number and the round, so a solve is reproducible). A target keeps a
    round's answer only if it is better; the rounds stop when every target succeeded.

    Args:
        residual, project: the problem, as for ``stages.refine._lm.lm_solve``.
        sample: (key) → (retry.seeds, n) random bending vectors within the limits.
        plan, retry: static settings.
        z_best: (T, n) best answers so far (bending-vector units); c_best: (T,) their
            cost ½‖r‖².
        params, shared, free: as for ``search_targets``.
        features: (T, 9) target pose features for ``explore.nearest_features``.
        stream: (T,) int32 number of each target (keys its random seeds).
        valid: (T,) False for padding targets (never retried).
        pool: the seed pool on the device (``SeedPool.device_arrays``).

    Returns:
        z (T, n) and cost (T,), per round of each retry's search the rows iterated and
        the most LM iterations run (1, plan.rounds · retry.rounds), and the targets each
        retry round retried (1, retry.rounds) (the leading 1: one row per device).
    """
    pool_features, pool_valid, pool_z = pool
    t = z_best.shape[0]
    ranks = min(retry.first_rank + retry.rounds * retry.nearest, pool_z.shape[0])
    near = min(retry.nearest, retry.seeds - 1)
    zero = jnp.sum(stream[:1], dtype=jnp.int32) * 0  # varies per shard, like the carries
    base = jax.random.key(retry.seed)
    # Next-nearest pool entries, ranked once for every round.
    nearest = nearest_features(pool_features, pool_valid, features, ranks) if near else None

    def failing(c_best: jax.Array) -> jax.Array:
        return valid & ~(c_best < retry.success_cost)

    def body(state: tuple) -> tuple:
        r, z_best, c_best, counted, iterated, retried = state
        todo = failing(c_best)
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.fold_in(base, r), i))(stream)
        seeds = jax.vmap(sample)(keys)
        if near:
            rank = retry.first_rank + r * retry.nearest + jnp.arange(near)
            pooled = pool_z[jnp.take(nearest, jnp.minimum(rank, ranks - 1), axis=1)]
            seeds = seeds.at[:, 1:1 + near].set(
                jnp.where((rank < ranks)[None, :, None], pooled, seeds[:, 1:1 + near]))
        seeds = seeds.at[:, 0].set(z_best)  # the best so far stays in the race
        z, cost, c_round, i_round = _search_rows(residual, project, plan, seeds, params,
                                                 todo, shared, free)
        pick = jnp.argmin(cost, axis=1)
        z_new, c_new = z[jnp.arange(t), pick], cost[jnp.arange(t), pick]
        better = todo & (c_new < c_best)
        span = plan.rounds * r
        return (r + 1, jnp.where(better[:, None], z_new, z_best),
                jnp.where(better, c_new, c_best),
                jax.lax.dynamic_update_slice(counted, c_round, (span,)),
                jax.lax.dynamic_update_slice(iterated, i_round, (span,)),
                retried.at[r].set(jnp.sum(todo, dtype=jnp.int32)))

    def more(state: tuple) -> jax.Array:
        r, _, c_best, *_ = state
        return (r < retry.rounds) & jnp.any(failing(c_best))

    stats = jnp.zeros(plan.rounds * retry.rounds, jnp.int32) + zero
    state = (jnp.int32(0), z_best, c_best, stats, stats,
             jnp.zeros(retry.rounds, jnp.int32) + zero)
    _, z_best, c_best, counted, iterated, retried = jax.lax.while_loop(more, body, state)
    return z_best, c_best, counted[None], iterated[None], retried[None]
