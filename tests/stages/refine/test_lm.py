"""The one LM step rule (``stages.refine._lm.lm_step_rule``) that the dense and banded LMs share,
against Nielsen's rule worked by hand."""

import jax
import jax.numpy as jnp
import numpy as np

from cr_nlp.stages.refine import STOP_REASONS, iteration_budget, lm_solve
from cr_nlp.stages.refine._lm import LMConfig, lm_step_rule, normal_products

CONFIG = LMConfig(give_up=((5, 1.0),))


def judge(cost, cost_new, predicted, damping=0.1, growth=2.0, judged=1, first=False):
    out = lm_step_rule(CONFIG, jnp.asarray(cost), jnp.asarray(cost_new), jnp.asarray(predicted),
                     jnp.asarray(damping), jnp.asarray(growth), jnp.asarray(False),
                     jnp.asarray(judged), first)
    return tuple(np.asarray(v).item() for v in out[:5])   # the stop code: tested below


def test_a_step_that_gains_what_the_model_predicted_shrinks_the_damping_threefold() -> None:
    accept, cost, done, damping, growth = judge(0.5, 0.25, 0.25)  # ρ = 1
    assert accept and cost == 0.25 and not done
    np.testing.assert_allclose(damping, 0.1 / 3.0)
    assert growth == 2.0


def test_a_half_gain_keeps_the_damping_and_a_small_gain_grows_it_by_nielsen() -> None:
    _, _, _, damping, _ = judge(0.5, 0.375, 0.25)  # ρ = ½: factor 1 − 0³ = 1
    np.testing.assert_allclose(damping, 0.1)
    _, _, _, damping, _ = judge(0.5, 0.45, 0.25)  # ρ = 0.2: factor 1 − (−0.6)³ = 1.216
    np.testing.assert_allclose(damping, 0.1 * 1.216, rtol=1e-6)  # float32


def test_a_rejected_step_keeps_the_cost_and_multiplies_the_damping_by_nu() -> None:
    accept, cost, done, damping, growth = judge(0.5, 0.6, 0.25, damping=0.1, growth=4.0)
    assert not accept and cost == 0.5 and not done
    np.testing.assert_allclose(damping, 0.4)
    assert growth == 8.0
    assert not judge(0.5, float("nan"), 0.25)[0]


def test_stall_convergence_damping_cap_and_give_up_end_the_problem() -> None:
    assert judge(0.5, 0.5 * (1 - 1e-5), 0.25)[2]  # accepted, gained < 1e-4 of the cost
    assert judge(0.5, 1e-13, 0.5)[2]  # below the cost tolerance
    assert judge(0.5, 0.6, 0.25, damping=2e10)[2]  # out of damping
    assert judge(5.0, 4.0, 2.0, judged=5)[2]  # 5 steps judged, cost still above 1.0
    assert not judge(5.0, 4.0, 2.0, judged=4)[2]


def test_a_first_trip_is_accepted_and_keeps_damping_and_growth() -> None:
    accept, cost, done, damping, growth = judge(np.inf, 3.0, 0.0, damping=0.1, growth=2.0,
                                                first=True)
    assert accept and cost == 3.0 and not done
    np.testing.assert_allclose(damping, 0.1)
    assert growth == 2.0


def _cubic(z, params, shared):
    """r = ((z − a)³, c) for z ∈ R: Gauss–Newton shrinks z − a by ⅓ per step; with c = 0 the
    cost reaches zero (converged), with c = 1 it stays above ½ and its gains fade (stalled)."""
    return jnp.concatenate([(z - params[0]) ** 3, params[1]])


def _line(z, params, shared):
    """r = (z − a, z − b): least squares at (a + b)/2, reached in one step."""
    return jnp.concatenate([z - params[0], z - params[1]])


def test_lm_solve_says_why_each_problem_stopped() -> None:
    # One batch: a zero-cost root (converged) and a cost floor (stalled); with one
    # iteration, both out of iterations.
    params = (jnp.asarray([[1.0], [1.0]]), jnp.asarray([[0.0], [1.0]]))
    z0 = jnp.asarray([[5.0], [5.0]])
    free = jnp.ones(1)
    solved = lm_solve(_cubic, lambda z: z, z0, params, None, free, jnp.int32(200))
    assert solved.reasons() == ["converged", "stalled"]
    np.testing.assert_allclose(np.asarray(solved.z)[:, 0], [1.0, 1.0], atol=0.1)
    assert solved.reason.dtype == jnp.int8 and set(solved.reasons()) <= set(STOP_REASONS)
    short = lm_solve(_cubic, lambda z: z, z0, params, None, free, jnp.int32(1))
    assert short.reasons() == ["out of iterations"] * 2
    # A linear least-squares problem with a cost floor: solved in one step, after which
    # every trial is rejected until the damping passes its cap.
    line = (jnp.asarray([[0.0]]), jnp.asarray([[2.0]]))
    capped = lm_solve(_line, lambda z: z, z0[:1], line, None, free, jnp.int32(200))
    assert capped.reasons() == ["damping cap"]
    params = (jnp.asarray([[1.0], [0.0]]), jnp.asarray([[1.0], [2.0]]))
    # The give-up rule: still above a cost of 1e-9 after 2 judged steps.
    stubborn = LMConfig(give_up=((2, 1e-9),), stall_tolerance=0.0)
    gave = lm_solve(_line, lambda z: z, z0, params, None, free, jnp.int32(50), config=stubborn)
    assert gave.reasons()[1] == "gave up"


def _same(z):
    return z


def test_every_iteration_budget_runs_on_one_compiled_lm() -> None:
    # A live update calls the LM with the same budget every time and the rounds of a
    # batch with their own: each budget made by ``iteration_budget`` is the same traced
    # integer (made once per value), so no budget compiles a program of its own.
    import jax

    params = (jnp.asarray([[1.0], [1.0]]), jnp.asarray([[0.0], [1.0]]))
    z0, free = jnp.asarray([[5.0], [5.0]]), jnp.ones(1)
    assert iteration_budget(7) is iteration_budget(7)
    before = lm_solve._cache_size()
    for budget in (1, 6, 200):
        solved = lm_solve(_cubic, _same, z0, params, None, free, iteration_budget(budget))
    assert solved.reasons() == ["converged", "stalled"]
    assert lm_solve._cache_size() == before + 1
    with jax.enable_x64(True):  # an int64 budget there, made once too
        assert iteration_budget(7).dtype == jnp.int64
        assert iteration_budget(7) is iteration_budget(7)


def _rosenbrock(z, params, shared):
    """Rosenbrock's residuals (10(y − x²), 1 − x), scaled by a per-problem factor: the
    root is (1, 1) whatever the start."""
    return params[0] * jnp.stack([10.0 * (z[1] - z[0] ** 2), 1.0 - z[0]])


def test_broyden_updates_reach_the_same_root_as_difference_jacobians() -> None:
    starts = jnp.asarray([[-1.2, 1.0], [0.5, -0.5], [2.0, 3.0], [1.1, 1.3]])
    params = (jnp.asarray([1.0, 2.0, 0.5, 1.0]),)
    free = jnp.ones(2)
    for jacobian, refresh in (("differences", 4), ("broyden", 4), ("broyden", 100)):
        config = LMConfig(jacobian=jacobian, refresh=refresh, initial_damping=1e-3)
        solved = lm_solve(_rosenbrock, lambda z: z, starts, params, None, free,
                          jnp.int32(200), config)
        assert solved.reasons() == ["converged"] * 4, (jacobian, refresh)
        np.testing.assert_allclose(np.asarray(solved.z), 1.0, atol=1e-5)


def test_broyden_on_a_linear_residual_converges_in_the_first_steps() -> None:
    # The difference Jacobian of a linear residual is exact and the secant updates keep
    # it so: one Gauss–Newton step reaches the least-squares answer (a + b)/2.
    import jax

    config = LMConfig(jacobian="broyden", initial_damping=1e-12)
    with jax.enable_x64(True):
        params = (jnp.asarray([[1.0], [-3.0]]), jnp.asarray([[3.0], [5.0]]))
        solved = lm_solve(_line, lambda z: z, jnp.asarray([[0.0], [10.0]]), params, None,
                          jnp.ones(1), jnp.int32(2), config)
        np.testing.assert_allclose(np.asarray(solved.z)[:, 0], [2.0, 1.0], atol=1e-9)


def test_bad_jacobian_settings_are_named() -> None:
    import pytest

    with pytest.raises(ValueError, match="refresh"):
        LMConfig(jacobian="broyden", refresh=0)
    with pytest.raises(ValueError, match="broyden"):
        LMConfig(jacobian="secant")


def test_normal_products_are_the_matrix_products() -> None:
    """JᵀJ and Jᵀr as sums over the rows equal the batched matrix products (float64)."""
    rng = np.random.default_rng(7)
    j, r = rng.normal(size=(5, 13, 9)), rng.normal(size=(5, 13))
    with jax.enable_x64(True):
        h, g = normal_products(jnp.asarray(j), jnp.asarray(r))
    np.testing.assert_allclose(np.asarray(h), np.swapaxes(j, 1, 2) @ j, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(g), (np.swapaxes(j, 1, 2) @ r[..., None])[..., 0],
                               rtol=1e-12)
