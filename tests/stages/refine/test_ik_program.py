"""The fused search (``stages.refine._ik_program``: coarse LM, beam and refinement rounds as one
device program per chunk, driven by ``stages.refine._ik_driver``) against closed forms and an
independent forward kinematics."""


import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp.model.limits import limit_violation_q
from cr_nlp.stages.refine._ik_program import SearchPlan, search_targets
from cr_nlp.stages.refine._lm import LMConfig
from cr_nlp.tasks.geometry.ik import IKConfig, IKSolver

from ...tasks.geometry.test_ik import LATTICE, TDCR3, TDCR4, free_configurations, targets_from


def _square_residual(z: jnp.ndarray, p: jnp.ndarray, shared: None) -> jnp.ndarray:
    """r = z² − p: two roots ±√p per coordinate."""
    return z * z - p


def _toy_plan(block: int, per_target: bool = False) -> SearchPlan:
    return SearchPlan(width=2, coarse_iterations=3, refine_iterations=30, refine_round=5,
                      per_target=per_target, min_distance=0.5, block=block,
                      lm=LMConfig(cost_tolerance=1e-20))


def _toy_search(block: int, per_target: bool = False) -> tuple:
    rng = np.random.default_rng(3)
    targets = rng.uniform(0.5, 2.0, (6, 1))
    seeds = np.linspace(-2.5, 2.5, 8)[None, :, None] + rng.uniform(-0.1, 0.1, (6, 8, 1))
    valid = np.array([True] * 5 + [False])  # the last target is padding
    out = search_targets(_square_residual, lambda z: z, _toy_plan(block, per_target),
                         jnp.asarray(seeds), jnp.asarray(targets), jnp.asarray(valid), None,
                         jnp.ones(1))
    return targets, seeds, valid, [np.asarray(x) for x in out]


@pytest.mark.usefixtures("float64")  # the toy roots to 1e-8, costs below 1e-16
def test_fused_search_finds_both_roots_and_leaves_padding_alone() -> None:
    targets, seeds, valid, (z, cost, counted, iterated) = _toy_search(block=4)
    # The diverse beam of two holds both roots ±√p of every valid target.
    roots = np.sort(z[valid, :, 0], axis=1)
    np.testing.assert_allclose(roots, np.sqrt(targets[valid]) * [[-1.0, 1.0]], atol=1e-8)
    assert np.all(cost[valid] < 1e-16)
    # A padding target is never iterated: its beam is two of its own seeds, cost inf.
    assert np.all(np.isin(z[~valid].ravel(), seeds[~valid].ravel()))
    assert np.all(np.isinf(cost[~valid]))
    # The coarse round iterates every valid seed; the first refinement round the beam;
    # the rounds stop once every candidate converged.
    assert counted[0, 0] == 8 * valid.sum() and counted[0, 1] == 2 * valid.sum()
    assert counted[0, -1] == 0 and 0 < iterated[0, 0] <= 3


def test_fused_search_answer_does_not_depend_on_the_block_size() -> None:
    """Compaction into blocks is bookkeeping: one row per block, a few, or one block for
    the whole batch give the same refined beam (as a set: the two roots of a target cost
    the same, so their order in the beam is a tie that rounding may break either way)."""

    def beams(block: int) -> tuple[np.ndarray, np.ndarray]:
        _, _, valid, (z, cost, _, _) = _toy_search(block=block)
        order = np.argsort(z[valid, :, 0], axis=1)
        return (np.take_along_axis(z[valid], order[..., None], axis=1),
                np.take_along_axis(cost[valid], order, axis=1))

    z_ref, c_ref = beams(1 << 20)
    for block in (1, 3, 16):
        z, cost = beams(block)
        np.testing.assert_allclose(z, z_ref, atol=1e-9)
        # converged costs are float32 round-off of squared residuals below 1e-7: ≤ 1e-13
        np.testing.assert_allclose(cost, c_ref, atol=1e-13)


@pytest.mark.usefixtures("float64")  # the toy roots to 1e-8, costs below 1e-16
def test_per_target_search_stops_the_other_candidates() -> None:
    """With ``per_target`` a target's candidates stop once one converged: after the round
    in which every target has a converged candidate nothing iterates."""
    _, _, valid, (z, cost, counted, _) = _toy_search(block=4, per_target=True)
    assert np.all(cost[valid].min(axis=1) < 1e-16)
    _, _, _, (_, _, counted_all, _) = _toy_search(block=4, per_target=False)
    assert counted[0].sum() <= counted_all[0].sum()


# The lattice case compiles the programs with a scene (~20 s on 2 cores); the default run
# keeps the free case, and test_ik's lattice tests run the search with a scene too.
@pytest.mark.parametrize(("robot", "scene"), [
    (TDCR3, None), pytest.param(TDCR4, LATTICE, marks=pytest.mark.slow)],
                         ids=["tdcr3-free", "tdcr4_ext-lattice"])
def test_search_reaches_every_target_in_one_device_call(robot, scene) -> None:  # noqa: ANN001
    q = free_configurations(robot, 24, seed=21, clearance=0.05)
    positions, wxyz = targets_from(robot, q)
    solver = IKSolver(robot, scene)
    result = solver.solve(positions, wxyz)
    assert result.success.all()
    # To LM's convergence level, not just below the 1 cm verdict, by an independent FK.
    reached, _ = targets_from(robot, result.q)
    assert np.median(np.linalg.norm(reached - positions, axis=1)) < 1e-5
    assert np.all(result.max_violation <= 1e-6) and result.collision_free.all()
    # One search program, the seed lookup inside it: no retry, no repair was needed.
    assert solver.device_calls == 1 and solver.retried == [0, 0]


def test_candidates_are_a_diverse_refined_beam() -> None:
    """``candidates`` (every beam member refined, not only the best): best first, the
    best at LM's convergence level by an independent FK, not one answer repeated."""
    q = free_configurations(TDCR3, 10, seed=4, clearance=0.05)
    positions, wxyz = targets_from(TDCR3, q)
    q_beam, errors = IKSolver(TDCR3).candidates(positions, wxyz)
    assert q_beam.shape == (10, IKConfig().beam_width, TDCR3.dof)
    assert np.all(np.diff(errors, axis=1) >= 0)
    assert np.all(errors[:, 0] < 1e-4)
    reached, _ = targets_from(TDCR3, q_beam[:, 0])
    assert np.linalg.norm(reached - positions, axis=1).max() < 1e-4
    spread = np.linalg.norm(q_beam[:, :, None] - q_beam[:, None, :], axis=-1)
    assert np.any(spread > 1e-3)  # not one answer repeated


def _solve_with(config: IKConfig, positions: np.ndarray, wxyz: np.ndarray) -> tuple:
    solver = IKSolver(TDCR3, config=config)
    return solver.solve(positions, wxyz), solver


def _assert_verified(result, positions: np.ndarray) -> None:  # noqa: ANN001
    """Every success holds by an independent forward kinematics and the limits."""
    reached, _ = targets_from(TDCR3, result.q[result.success])
    assert np.all(np.linalg.norm(reached - positions[result.success], axis=1) < 1e-2)
    assert np.all(limit_violation_q(TDCR3, result.q[result.success]) <= 1e-6)


def test_fused_retries_run_inside_the_search_program() -> None:
    """Targets the search cannot reach (98 % of the robot's length from its base but off
    its axis: only a nearly straight robot reaches that far) are retried: one search
    program (its seed lookup inside) and one retry program for both rounds, and a solve
    is reproducible. Same 24 targets as the tdcr3 case above, so the search program
    comes from the compilation cache."""
    q = free_configurations(TDCR3, 20, seed=21, clearance=0.05)
    positions, wxyz = targets_from(TDCR3, q)
    sideways = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, -1], [-0.6, 0.8, 0]])
    positions = np.concatenate([positions, np.asarray(TDCR3.base_position)
                                + 0.98 * TDCR3.total_length_max * sideways])
    wxyz = np.concatenate([wxyz, np.tile([1.0, 0, 0, 0], (4, 1))])
    new, new_solver = _solve_with(IKConfig(), positions, wxyz)
    reachable = np.arange(24) < 20
    np.testing.assert_array_equal(new.success, reachable)
    _assert_verified(new, positions)
    # The unreachable four fail every round.
    assert new_solver.retried == [4, 4]
    assert new_solver.device_calls == 2
    # Both retry rounds ran in the retry program: each one's coarse round iterated the
    # four targets' 32 seeds.
    assert [c[0] for c in new_solver.lm_calls].count(4 * 32) == 2
    # Random retry seeds come from IKConfig.seed: another solver, the same answers.
    again, _ = _solve_with(IKConfig(), positions, wxyz)
    np.testing.assert_array_equal(again.q, new.q)
    np.testing.assert_array_equal(new_solver.solve(positions, wxyz).q, new.q)


@pytest.mark.slow
def test_fused_retries_rescue_targets() -> None:
    """With one seed per target and tiny LM budgets most targets fail the main search;
    the retry rounds (one program) rescue many of them, verified independently."""
    q = free_configurations(TDCR3, 60, seed=1, clearance=0.05)
    positions, wxyz = targets_from(TDCR3, q)
    tiny = dict(seeds_per_target=1, coarse_iterations=1, refine_iterations=2, refine_round=1)
    (new, new_solver), (none, _) = (
        _solve_with(IKConfig(retry_rounds=rounds, **tiny), positions, wxyz)
        for rounds in (2, 0))
    assert new_solver.retried[0] > 20
    assert new.success.sum() > none.success.sum() + 10
    _assert_verified(new, positions)
    assert new_solver.device_calls == 2
