"""The block-banded LM for chains of waypoints against the dense LM and dense algebra."""

from __future__ import annotations

from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp.stages.refine._banded_lm import (
    BandedMatrix,
    ChainResidual,
    banded_lm_solve,
    banded_matvec,
    banded_to_dense,
    chain_jacobians,
    chain_residuals,
    normal_equations,
    solve_banded,
    solve_block_tridiagonal,
)
from cr_nlp.stages.refine._lm import LMConfig, lm_solve

# Dense and banded algebra agree to 1e-9 or tighter: float64 JAX arrays, x64 on per test.
pytestmark = pytest.mark.usefixtures("float64")


def unary(z, p, shared):
    return jnp.concatenate([jnp.sin(z) - p, z[:1] * z[1:2]])


def pair(a, b, p, shared):
    return jnp.concatenate([b - a, (a * b)[:2]])


def triple(a, b, c, p, shared):
    return 0.3 * (a - 2.0 * b + c) ** 2


TERMS = ChainResidual(unary, pair, triple)


def problem(t: int, d: int = 3, seed: int = 0) -> tuple[jax.Array, jax.Array]:
    rng = np.random.default_rng(seed)
    return (jnp.asarray(rng.normal(size=(t, d)), jnp.float64),
            jnp.asarray(0.5 * rng.normal(size=(t, d)), jnp.float64))


def dense_residual(z_flat, p, shape):
    return jnp.concatenate([r.reshape(-1) for r in
                            chain_residuals(TERMS, z_flat.reshape(shape), p, None)])


@pytest.mark.parametrize("t", [2, 7])
def test_normal_equations_match_the_dense_jacobian(t: int) -> None:
    z, p = problem(t)
    h, g = jax.jit(lambda z, p: normal_equations(chain_jacobians(TERMS, z, p, None), t))(z, p)
    jac = jax.jacfwd(dense_residual)(z.reshape(-1), p, z.shape)
    r = dense_residual(z.reshape(-1), p, z.shape)
    np.testing.assert_allclose(banded_to_dense(h), jac.T @ jac, atol=1e-12)
    np.testing.assert_allclose(g.reshape(-1), jac.T @ r, atol=1e-12)
    x = jnp.asarray(np.random.default_rng(1).normal(size=z.shape))
    np.testing.assert_allclose(banded_matvec(h, x).reshape(-1), jac.T @ jac @ x.reshape(-1),
                               atol=1e-12)


@pytest.mark.parametrize("t", [1, 2, 5, 8])
def test_block_cholesky_solves_like_numpy(t: int) -> None:
    d = 4
    rng = np.random.default_rng(t)

    factor = np.zeros((t * d, t * d))
    for i in range(t):
        for j in range(max(0, i - 2), i + 1):
            factor[i * d:(i + 1) * d, j * d:(j + 1) * d] = rng.normal(size=(d, d))
        factor[i * d:(i + 1) * d, i * d:(i + 1) * d] += 3.0 * np.eye(d)
    dense = factor @ factor.T                # bandwidth 2 blocks: block pentadiagonal
    blocks = [[dense[i * d:(i + 1) * d, j * d:(j + 1) * d] for j in range(t)] for i in range(t)]
    h = BandedMatrix(jnp.asarray(np.array([blocks[i][i] for i in range(t)])),
                     jnp.asarray(np.array([blocks[i][i + 1] for i in range(t - 1)])
                                 .reshape(-1, d, d)),
                     jnp.asarray(np.array([blocks[i][i + 2] for i in range(t - 2)])
                                 .reshape(-1, d, d)))
    np.testing.assert_allclose(banded_to_dense(h), dense, atol=1e-12)
    rhs = rng.normal(size=(t, d))
    x = solve_banded(h, jnp.asarray(rhs))
    np.testing.assert_allclose(np.asarray(x).reshape(-1), np.linalg.solve(dense, rhs.reshape(-1)),
                               rtol=1e-9, atol=1e-9)


def test_banded_lm_takes_the_dense_lm_steps() -> None:
    t, d = 7, 3
    z, p = problem(t)

    def flat(z_flat, params, shared):
        return dense_residual(z_flat, params, (t, d))

    free = jnp.ones(d).at[2].set(0.0)        # one fixed variable per waypoint
    for budget in (1, 30):
        zb, cb, ib = banded_lm_solve(TERMS, lambda x: x, z, p, None, free, jnp.int32(budget))
        zd, cd, idd, _ = lm_solve(flat, lambda x: x, z.reshape(1, -1), p[None], None,
                                  jnp.tile(free, t), jnp.int32(budget))
        np.testing.assert_allclose(np.asarray(zb).reshape(-1), np.asarray(zd[0]), atol=1e-10)
        assert float(cb) == pytest.approx(float(cd[0]), rel=1e-10)
        assert int(ib) == int(idd)
    np.testing.assert_array_equal(np.asarray(zb)[:, 2], np.asarray(z)[:, 2])
    assert float(cb) < 0.5 * float(jnp.sum(dense_residual(z.reshape(-1), p, (t, d)) ** 2))


def test_lm_give_up_ends_the_loop_but_not_the_other_problems_steps() -> None:
    # Two problems x² = 2: one from 1.5 (converges in a few steps), one from 300 (far:
    # LM crawls down from it). Giving up after 2 steps above cost 1 ends the loop once the
    # near one converged; the near one takes exactly the steps it takes alone.
    def square_root(z, p, shared):
        return z * z - 2.0

    z0 = jnp.asarray([[1.5], [300.0]])
    free = jnp.ones(1)

    def solve(z, config):
        return lm_solve(square_root, lambda x: x, z, None, None, free, jnp.int32(100),
                        config=config)

    base = LMConfig(stall_tolerance=0.0)
    _, _, it_off, _ = solve(z0, base)
    z_near, _, it_near, _ = solve(z0[:1], base)
    z, cost, it, _ = solve(z0, replace(base, give_up=((2, 1.0),)))
    assert int(it) == max(int(it_near), 2) < int(it_off)
    np.testing.assert_array_equal(np.asarray(z[0]), np.asarray(z_near[0]))
    assert float(cost[1]) > 1.0
    # A give-up cost above the far problem's start: the rule never fires.
    _, _, it_high, _ = solve(z0, replace(base, give_up=((2, 1e12),)))
    assert int(it_high) == int(it_off)


def test_projection_is_applied_every_step() -> None:
    z, p = problem(6)
    box = lambda x: jnp.clip(x, -0.2, 0.2)  # noqa: E731
    zb, _, _ = banded_lm_solve(TERMS, box, z, p, None, jnp.ones(3), jnp.int32(20))
    assert float(jnp.max(jnp.abs(zb))) <= 0.2 + 1e-15


def random_block_tridiagonal(s: int, k: int, rng: np.random.Generator) -> np.ndarray:
    """A random symmetric positive-definite block-tridiagonal (s·k)² matrix: L·Lᵀ for a
    block lower-bidiagonal L with a dominant diagonal."""
    factor = np.zeros((s * k, s * k))
    for i in range(s):
        diagonal = rng.normal(size=(k, k)) / np.sqrt(k) + 2.0 * np.eye(k)
        factor[i * k:(i + 1) * k, i * k:(i + 1) * k] = diagonal
        if i:
            factor[i * k:(i + 1) * k, (i - 1) * k:i * k] = rng.normal(size=(k, k)) / np.sqrt(k)
    return factor @ factor.T


@pytest.mark.parametrize(("s", "k"), [(1, 3), (2, 5), (12, 18), (7, 1)])
def test_block_tridiagonal_solve_equals_the_dense_solve(s: int, k: int) -> None:
    """``solve_block_tridiagonal`` (the trajectory LM's solve: 12 blocks of 2 × 9 for 24
    waypoints of tdcr3) against numpy's dense solve, float64, on random systems; also
    vmapped over a batch, as the planner runs it."""
    rng = np.random.default_rng(100 * s + k)
    batch = [random_block_tridiagonal(s, k, rng) for _ in range(3)]
    a = np.array([[m[i * k:(i + 1) * k, i * k:(i + 1) * k] for i in range(s)] for m in batch])
    c = np.zeros_like(a)
    for b, m in enumerate(batch):
        for i in range(1, s):
            c[b, i] = m[i * k:(i + 1) * k, (i - 1) * k:i * k]
    rhs = rng.normal(size=(3, s, k))
    x = jax.vmap(solve_block_tridiagonal)(jnp.asarray(a), jnp.asarray(c), jnp.asarray(rhs))
    for b, m in enumerate(batch):
        np.testing.assert_allclose(np.asarray(x[b]).reshape(-1),
                                   np.linalg.solve(m, rhs[b].reshape(-1)), rtol=1e-9, atol=1e-10)


def test_banded_lm_finds_the_known_answer_of_a_linear_chain() -> None:
    """A chain with fixed ends z₀ = 0, z₅ = 5 (d = 2) and pair residuals z_{t+1} − z_t − 1
    plus a triple term (z_t − 2z_{t+1} + z_{t+2}): the unique minimiser is z_t = t (every
    residual zero); LM reaches it, float64, and leaves the fixed ends alone."""
    def step_pair(a, b, p, shared):
        return b - a - 1.0

    def bend(a, b, c, p, shared):
        return a - 2.0 * b + c

    terms = ChainResidual(None, step_pair, bend)
    t, d = 6, 2
    z0 = jnp.asarray(np.random.default_rng(3).normal(size=(t, d)), jnp.float64)
    z0 = z0.at[0].set(0.0).at[-1].set(5.0)
    free = jnp.ones((t, d), jnp.float64).at[0].set(0.0).at[-1].set(0.0)
    z, cost, _ = banded_lm_solve(terms, lambda x: x, z0, None, None, free, jnp.int32(50))
    expected = np.repeat(np.arange(t, dtype=float)[:, None], d, axis=1)
    np.testing.assert_allclose(np.asarray(z), expected, atol=1e-8)
    assert float(cost) < 1e-16


def step_unary(z, p, shared):
    # shared = (scene arrays, extra, the chain's own scalar): the scalar shifts the target.
    return jnp.sin(z) - 0.1 * shared[2]


def unprojected(z):
    return z


def test_chain_batch_solves_every_chain_as_its_own_banded_solve() -> None:
    """Three chains in chunks of two (the last padded): each answer equals the single
    banded solve with that chain's scalar; one program per chunk, compiled once."""
    from cr_nlp.stages.refine._chain_stream import ChainBatchLM

    t, d = 5, 3
    terms = ChainResidual(step_unary, pair, None)
    rng = np.random.default_rng(3)
    z0 = rng.normal(size=(3, t * d))
    steps = np.array([0.5, -1.0, 2.0])
    free = jnp.ones(t * d, jnp.float64).at[:d].set(0.0)       # the first waypoint is fixed
    batch = ChainBatchLM(terms, unprojected, t, free, jnp.float64, chunk_size=2,
                         schedule="chunks")
    solution = batch.solve(z0, steps, None, 25)
    z, cost = solution.z, solution.cost
    assert batch.programs == 2 and solution.compile > 0.0
    for k in range(3):
        zk, ck, _ = banded_lm_solve(terms, unprojected, jnp.asarray(z0[k].reshape(t, d)), None,
                                    (None, None, jnp.float64(steps[k])), free.reshape(t, d),
                                    jnp.int32(25))
        np.testing.assert_allclose(z[k], np.asarray(zk).reshape(-1), atol=1e-12)
        assert cost[k] == pytest.approx(float(ck), rel=1e-12)
    np.testing.assert_array_equal(z[:, :d], z0[:, :d])
    again = batch.solve(z0[:1], steps[:1], None, 25)
    assert again.compile == 0.0 and batch.programs == 3
    np.testing.assert_allclose(again.z[0], z[0], atol=1e-12)


def test_lanes_split_the_chains_between_devices_with_the_one_shot_iterates() -> None:
    """One lane per device, at most ``chunk_size // 2`` (the tests run on the CPU's host
    devices): every lane's device gets a program and chains, and every chain still takes
    its one-shot ``banded_lm_solve`` iterates; ``lanes=1`` keeps them all on the first
    device."""
    from cr_nlp.stages.refine._chain_stream import ChainBatchLM

    t, d, budget, count = 5, 3, 7, 10
    terms = ChainResidual(step_unary, pair, triple)
    rng = np.random.default_rng(21)
    z0 = rng.normal(size=(count, t * d))
    steps = rng.normal(size=count)
    free = jnp.ones(t * d, jnp.float64).at[:d].set(0.0)
    one_shot = [banded_lm_solve(terms, unprojected, jnp.asarray(z0[k].reshape(t, d)), None,
                                (None, None, jnp.float64(steps[k])), free.reshape(t, d),
                                jnp.int32(budget))[0] for k in range(count)]
    devices = jax.devices()
    for lanes in (None, 1):
        batch = ChainBatchLM(terms, unprojected, t, free, jnp.float64, chunk_size=4,
                             lanes=lanes)
        solution = batch.solve(z0, steps, None, budget)
        used = sorted({device for device, _ in batch._slot_programs})
        assert used == [x.id for x in devices[:2 if lanes is None else 1]]
        for k in range(count):
            np.testing.assert_allclose(solution.z[k], np.asarray(one_shot[k]).reshape(-1),
                                       atol=1e-12)


def test_slots_take_the_one_shot_iterates_whatever_the_schedule() -> None:
    """Continuous batching (two slots, refilled as chains finish, the LM state carried
    between device calls) gives every chain exactly its one-shot ``banded_lm_solve``:
    the same z, cost and iteration count, for chains that stop after very different
    numbers of iterations (some stall early, some use the whole budget), whether a call
    runs one trip, three or until a slot frees up; chains added by ``more`` too."""
    from cr_nlp.stages.refine._chain_stream import ChainBatchLM

    t, d, budget = 5, 3, 6
    terms = ChainResidual(step_unary, pair, triple)
    rng = np.random.default_rng(3)
    scales = np.array([0.01, 0.1, 0.3, 1.0, 2.0, 3.0, 0.05, 1.5, 4.0])
    z0 = rng.normal(size=(9, t * d)) * scales[:, None]
    steps = rng.normal(size=9)
    free = jnp.ones(t * d, jnp.float64).at[:d].set(0.0)
    one_shot = [banded_lm_solve(terms, unprojected, jnp.asarray(z0[k].reshape(t, d)), None,
                                (None, None, jnp.float64(steps[k])), free.reshape(t, d),
                                jnp.int32(budget)) for k in range(9)]
    expected_its = np.array([int(o[2]) for o in one_shot])
    assert expected_its.min() == 3 and (expected_its == budget).sum() >= 3     # different
    first = 6                                       # the rest are added while solving

    reported: list[int] = []

    def more(chains, z, cost):
        reported.extend(chains)
        if 0 in chains:                             # once chain 0 is done: the others
            return z0[first:], steps[first:]
        return None

    batch = ChainBatchLM(terms, unprojected, t, free, jnp.float64, chunk_size=2)
    for trips, refill in ((1, 1), (3, 2), (1 << 30, 1)):
        reported.clear()
        batch.trips, batch.refill, batch.slot_trips = trips, refill, 0   # run-time settings
        solution = batch.solve(z0[:first], steps[:first], None, budget, more)
        np.testing.assert_array_equal(solution.iterations, expected_its)
        assert sorted(reported) == list(range(9))       # each chain reported once
        for k in range(9):
            np.testing.assert_allclose(solution.z[k], np.asarray(one_shot[k][0]).reshape(-1),
                                       atol=1e-12)
            assert solution.cost[k] == pytest.approx(float(one_shot[k][1]), rel=1e-12)
        # Work: never more slot-trips than two slots running every call to its end, and
        # at least the trips the chains needed (one more than their iterations).
        assert batch.slot_trips >= (expected_its + 1).sum()
    # One program size for every schedule, one program per lane (device).
    assert sorted(batch._slot_programs) == [(device.id, 2) for device in batch.devices]


def test_prediction_stop_ends_the_same_iterates_early() -> None:
    z, p = problem(7)
    free = jnp.ones(3)
    plain = LMConfig(cost_tolerance=0.0, stall_tolerance=0.0)
    stopping = LMConfig(cost_tolerance=0.0, stall_tolerance=0.0, prediction_tolerance=1e-8)
    solve = jax.jit(banded_lm_solve, static_argnames=("terms", "project", "config"))
    z_full, cost_full, used_full = solve(TERMS, unprojected, z, p, None, free, jnp.int32(60),
                                         config=plain)
    z_stop, cost_stop, used = solve(TERMS, unprojected, z, p, None, free, jnp.int32(60),
                                    config=stopping)
    assert int(used) < int(used_full)
    # The rule only ends the loop: the plain solve with that budget has the same iterate.
    z_same, cost_same, _ = solve(TERMS, unprojected, z, p, None, free, used, config=plain)
    np.testing.assert_array_equal(np.asarray(z_stop), np.asarray(z_same))
    assert float(cost_stop) == float(cost_same)
    # ...and what the plain solve gains afterwards is within the tolerance's reach.
    assert float(cost_full) <= float(cost_stop) <= float(cost_full) * (1.0 + 1e-6)


def test_give_up_stops_only_chains_left_above_the_cost() -> None:
    """A chain whose cost after a checkpoint's steps is still above its cost
    (``LMConfig.give_up``) stops there with the plain solve's iterate at that budget; one
    below it (or the rule off) runs as before."""
    z, p = problem(7)
    free = jnp.ones(3)
    plain = LMConfig(cost_tolerance=0.0, stall_tolerance=0.0)
    solve = jax.jit(banded_lm_solve, static_argnames=("terms", "project", "config"))
    z_full, cost_full, used_full = solve(TERMS, unprojected, z, p, None, free, jnp.int32(60),
                                         config=plain)
    _, cost_3, _ = solve(TERMS, unprojected, z, p, None, free, jnp.int32(3), config=plain)
    assert int(used_full) > 3 and float(cost_3) > float(cost_full)
    # Above the cost after 3 steps: stops at 3, the plain solve's iterate at that budget.
    high = LMConfig(cost_tolerance=0.0, stall_tolerance=0.0,
                    give_up=((3, 0.5 * float(cost_3)),))
    z_stop, cost_stop, used = solve(TERMS, unprojected, z, p, None, free, jnp.int32(60),
                                    config=high)
    assert int(used) == 3 and float(cost_stop) == float(cost_3)
    # Below it: never triggers, the same iterates as the plain solve.
    low = replace(high, give_up=((3, 2.0 * float(cost_3)),))
    z_low, cost_low, used_low = solve(TERMS, unprojected, z, p, None, free, jnp.int32(60),
                                      config=low)
    np.testing.assert_array_equal(np.asarray(z_low), np.asarray(z_full))
    assert int(used_low) == int(used_full)


def test_give_up_checkpoints_each_stop_at_their_own_step() -> None:
    """Two checkpoints (``LMConfig.give_up``): the earlier one stops a chain still above its
    (higher) cost at its step, with the plain solve's iterate there; a chain below it there
    goes on to the later checkpoint and stops at its step."""
    z, p = problem(7)
    free = jnp.ones(3)
    plain = LMConfig(cost_tolerance=0.0, stall_tolerance=0.0)
    solve = jax.jit(banded_lm_solve, static_argnames=("terms", "project", "config"))
    costs = {k: solve(TERMS, unprojected, z, p, None, free, jnp.int32(k), config=plain)[1]
             for k in (2, 5)}
    assert float(costs[5]) < float(costs[2])
    # Above the earlier checkpoint's cost after 2 steps: stops at 2.
    early = replace(plain, give_up=((2, 0.5 * float(costs[2])), (5, 0.5 * float(costs[5]))))
    _, cost, used = solve(TERMS, unprojected, z, p, None, free, jnp.int32(60), config=early)
    assert int(used) == 2 and float(cost) == float(costs[2])
    # Below it (a cost above the chain's there), still above the later one's: stops at 5.
    later = replace(plain, give_up=((2, 2.0 * float(costs[2])), (5, 0.5 * float(costs[5]))))
    _, cost, used = solve(TERMS, unprojected, z, p, None, free, jnp.int32(60), config=later)
    assert int(used) == 5 and float(cost) == float(costs[5])


def test_chains_added_after_the_last_one_finished_are_solved_alike() -> None:
    """``more`` runs while the next device call computes; chains it adds only once every
    given chain has finished (no call left to overlap with) still get their one-shot
    ``banded_lm_solve`` iterates, and every chain is reported exactly once."""
    from cr_nlp.stages.refine._chain_stream import ChainBatchLM

    t, d, budget = 5, 3, 6
    terms = ChainResidual(step_unary, pair, triple)
    rng = np.random.default_rng(5)
    z0 = rng.normal(size=(7, t * d)) * np.array([0.02, 0.5, 2.0, 0.1, 1.0, 3.0, 0.3])[:, None]
    steps = rng.normal(size=7)
    free = jnp.ones(t * d, jnp.float64).at[:d].set(0.0)
    first = 4
    reported: list[int] = []

    def more(chains, z, cost):
        reported.extend(chains)
        if len(reported) == first:                  # the last given chain just finished
            return z0[first:], steps[first:]
        return None

    batch = ChainBatchLM(terms, unprojected, t, free, jnp.float64, chunk_size=2)
    solution = batch.solve(z0[:first], steps[:first], None, budget, more)
    assert sorted(reported) == list(range(7))
    for k in range(7):
        zk, ck, its = banded_lm_solve(terms, unprojected, jnp.asarray(z0[k].reshape(t, d)),
                                      None, (None, None, jnp.float64(steps[k])),
                                      free.reshape(t, d), jnp.int32(budget))
        np.testing.assert_allclose(solution.z[k], np.asarray(zk).reshape(-1), atol=1e-12)
        assert solution.cost[k] == pytest.approx(float(ck), rel=1e-12)
        assert solution.iterations[k] == int(its)


def test_slots_shrink_and_grow_without_changing_the_iterates() -> None:
    """With up to 8 slots, the draining stream moves to programs of 4 and 2 slots and
    back to more when ``more`` adds chains late; every chain still takes its one-shot
    ``banded_lm_solve`` iterates, and a program without resizing does the same with more
    slot-trips. The first stream moves down only to programs compiled already (none: a
    one-shot process does not compile them for its tail); the second compiles them."""
    from cr_nlp.stages.refine._chain_stream import ChainBatchLM

    t, d, budget = 5, 3, 8
    terms = ChainResidual(step_unary, pair, triple)
    rng = np.random.default_rng(11)
    count, first = 14, 9
    z0 = rng.normal(size=(count, t * d)) * rng.uniform(0.01, 3.0, size=(count, 1))
    steps = rng.normal(size=count)
    free = jnp.ones(t * d, jnp.float64).at[:d].set(0.0)
    one_shot = [banded_lm_solve(terms, unprojected, jnp.asarray(z0[k].reshape(t, d)), None,
                                (None, None, jnp.float64(steps[k])), free.reshape(t, d),
                                jnp.int32(budget)) for k in range(count)]
    finished: list[int] = []

    def more(chains, z, cost):
        finished.extend(chains)
        if len(finished) == first - 1:              # one chain of the first lot left
            return z0[first:], steps[first:]
        return None

    work = {}
    for resize in (True, False):
        batch = ChainBatchLM(terms, unprojected, t, free, jnp.float64, chunk_size=8,
                             resize=resize)
        for stream in (1, 2):
            finished.clear()
            batch.slot_trips = 0
            solution = batch.solve(z0[:first], steps[:first], None, budget, more)
            assert sorted(finished) == list(range(count))
            for k in range(count):
                np.testing.assert_allclose(solution.z[k],
                                           np.asarray(one_shot[k][0]).reshape(-1), atol=1e-12)
                assert solution.cost[k] == pytest.approx(float(one_shot[k][1]), rel=1e-12)
                assert solution.iterations[k] == int(one_shot[k][2])
            work[resize, stream] = (batch.slot_trips,
                                    sorted({s for _, s in batch._slot_programs}))
    lane = batch.lane_slots                         # 8 slots, split between the lanes
    assert work[False, 2][1] == [lane]
    assert work[True, 1] == work[False, 1]
    assert work[True, 2][1] == [2 ** k for k in range(1, lane.bit_length())]
    assert work[True, 2][0] < work[False, 2][0]


def test_slots_and_chunks_never_exceed_a_chunk_size_that_is_not_a_power_of_two() -> None:
    """chunk_size 6 (or 3): programs of at most 6 slots (3 rows), every chain still its
    one-shot ``banded_lm_solve``."""
    from cr_nlp.stages.refine._chain_stream import ChainBatchLM

    t, d, budget = 5, 3, 8
    terms = ChainResidual(step_unary, pair, triple)
    rng = np.random.default_rng(12)
    count = 11
    z0 = rng.normal(size=(count, t * d))
    steps = rng.normal(size=count)
    free = jnp.ones(t * d, jnp.float64).at[:d].set(0.0)
    for chunk_size, schedule in ((6, "slots"), (3, "chunks")):
        batch = ChainBatchLM(terms, unprojected, t, free, jnp.float64, chunk_size=chunk_size,
                             schedule=schedule)
        solution = batch.solve(z0, steps, None, budget)
        sizes = ({s for _, s in batch._slot_programs} if schedule == "slots" else
                 batch._compiled)
        assert sizes and max(sizes) <= chunk_size
        for k in range(count):
            zk, _, _ = banded_lm_solve(terms, unprojected, jnp.asarray(z0[k].reshape(t, d)),
                                       None, (None, None, jnp.float64(steps[k])),
                                       free.reshape(t, d), jnp.int32(budget))
            np.testing.assert_allclose(solution.z[k], np.asarray(zk).reshape(-1), atol=1e-12)
