"""Tension-space planning over many problems at once (``tasks.mechanics.trajectory``):
every batched step gives each problem what it gets alone (the refine's LM over several
motions, the verdict of several motions, the via search in rounds), and the LM's
Jacobian of a plan's tip unknowns is their derivative."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from cr_nlp import TensionTrajectoryPlanner
from cr_nlp.model import load_robot
from cr_nlp.model.loads import static_loads

RAO = load_robot("tdcr2_rao2021")
GRAVITY = [0.0, 0.0, -9.81]
PAYLOAD = [0.0, 0.0, -0.005 * 9.81]        # 5 g at the tip, N
# Problems of the clutter benchmark (seed 0) whose direct legs are not clear: each needs a
# via set (the pool's sets 208, 167, 137 and 97, the first clear one 0, 0, 3 and 1 places
# down its candidates, as screening all 16 at once found before the rounds).
STARTS = np.array([[0.224, 3.363, 0.0, 0.897, 0.0, 0.54], [0.0, 0.0, 4.225, 3.95, 0.0, 0.0],
                   [0.0, 3.676, 0.0, 2.319, 0.0, 3.456], [3.789, 2.752, 0.0, 0.898, 5.689, 0.0]])
GOALS = np.array([[5.883, 2.699, 0.0, 4.95, 0.0, 5.484], [4.15, 3.695, 0.0, 0.0, 0.936, 2.885],
                  [0.0, 0.0, 4.14, 5.244, 0.0, 1.541], [5.04, 0.0, 0.0, 3.877, 2.343, 0.0]])


@pytest.fixture(scope="module")
def planner() -> TensionTrajectoryPlanner:
    from cr_nlp.bench.tension_clutter import clutter_scene

    return TensionTrajectoryPlanner(RAO, clutter_scene(RAO, 0))


@pytest.fixture(scope="module")
def loads(planner: TensionTrajectoryPlanner):
    return static_loads(1, planner.length, PAYLOAD, None, GRAVITY)


def test_the_via_search_in_rounds_picks_the_cheapest_clear_via(planner, loads,
                                                               monkeypatch) -> None:
    """Screening every problem's candidates in rounds (the 2 cheapest, then 3 more, then
    the rest) picks, for each problem, the via that screening all 16 at once picks."""
    import cr_nlp.tasks.mechanics.trajectory as trajectory

    monkeypatch.setattr(trajectory, "VIA_ROUNDS", (0,))
    whole = planner._via_plans(STARTS, GOALS, loads)
    monkeypatch.setattr(trajectory, "VIA_ROUNDS", (0, 2, 5))
    rounds = planner._via_plans(STARTS, GOALS, loads)
    assert [n for _, n in rounds] == [n for _, n in whole]
    assert [n[0].split()[3] for _, n in whole] == ["208", "167", "137", "97"]
    for (a, _), (b, _) in zip(rounds, whole, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_batch_of_direct_legs_builds_no_via_pool() -> None:
    """Where every problem's direct leg is clear (no scene), the planner neither solves nor
    loads its pool of via sets."""
    free = TensionTrajectoryPlanner(RAO)
    results = free.plan(STARTS[:2], GOALS[:2], gravity=GRAVITY, tip_force=PAYLOAD)
    assert [r.notes[0] for r in results] == ["direct leg", "direct leg"]
    assert all(r.success for r in results) and free._vias == {}


def test_several_motions_are_verified_as_each_alone(planner, loads) -> None:
    """The verdict of three motions in one batch of fresh solves is, field by field, the
    verdict each gets alone (one passes, one fails by its rate, one by the scene)."""
    from cr_nlp.tasks.mechanics._motion import verify_tension_motion

    motions = [planner._legs([STARTS[0], GOALS[0]]), np.stack([STARTS[1], GOALS[1]]),
               planner._legs([STARTS[2], GOALS[2]])]
    together = planner.verify_motions(motions, loads)
    cfg = planner.config
    for motion, report in zip(motions, together, strict=True):
        alone = verify_tension_motion(RAO, planner.scene, motion, cfg.dt, loads,
                                      margin=cfg.safety_margin, rate_max=cfg.tension_rate_max)
        for field in dataclasses.fields(alone):
            a, b = getattr(report, field.name), getattr(alone, field.name)
            if isinstance(b, np.ndarray):
                np.testing.assert_array_equal(a, b, err_msg=field.name)
            else:
                assert a == b, field.name
    assert not together[1].success and "rate" in together[1].reason
    assert [r.success for r in together].count(False) >= 2


def test_motions_refined_together_get_the_answers_each_gets_alone(planner, loads) -> None:
    """The refine's LM over several motions (one vmapped program per padded length, the
    batch padded by copies) gives every motion its own answer: those of 5, 6 and 11
    waypoints (padded to 8, 8 and 16) refined together and one by one. (The LM's starts
    come from one statics solve of all waypoints, whose rounding differs from the solves
    of each motion's alone: the answers agree to 1e-5 N, not bit for bit.)"""
    from cr_nlp.tasks.mechanics._motion_refine import refine_chain, refine_chains, resampled

    cfg = planner.config
    motions = [resampled(planner._legs([a, b]), count)
               for a, b, count in zip(STARTS[:3], GOALS[:3], (5, 6, 11), strict=True)]
    together = refine_chains(RAO, planner.scene, cfg, motions, 8, loads=loads)
    for motion, answer in zip(motions, together, strict=True):
        alone = refine_chain(RAO, planner.scene, cfg, motion, 8, loads=loads)
        assert answer.shape == motion.shape
        np.testing.assert_allclose(answer, alone, rtol=0, atol=1e-5)
        np.testing.assert_array_equal(answer[[0, -1]], motion[[0, -1]])
        assert np.abs(answer - motion).max() > 1e-3           # the LM moved it


def test_the_tip_unknowns_jacobian_is_their_derivative(planner, loads) -> None:
    """A plan's tip unknowns enter its waypoint rows linearly: the constant Jacobian the
    LM uses instead of differences (``motion_unary_tail``) is the rows' change per unit
    step of each tip unknown (exact for a linear dependence, any step)."""
    from functools import partial

    from cr_nlp.model.cosserat import solve_statics
    from cr_nlp.stages.refine import (
        MotionTerms,
        TensionTerms,
        base_frame,
        unknowns_of,
        waypoint_params,
    )
    from cr_nlp.stages.refine._tension_lm import motion_unary, motion_unary_tail
    from cr_nlp.world.clearance import SceneArrays, scene_arrays

    tensions = np.stack([STARTS[0], GOALS[0]])
    every = loads.rows(np.zeros(2, int))
    solved = solve_statics(RAO, tensions, PAYLOAD, None, GRAVITY)
    shoot, params, _ = waypoint_params(RAO, solved.tip_position, np.full((2, 4), np.nan),
                                       every, tip_weight=0.0)
    waypoint = TensionTerms(RAO, planner.config.statics, shoot, clearance_weight=100.0,
                            clearance_band=0.004, direct=True)
    terms = MotionTerms(waypoint, rate_step=2.0, tip_path_weight=1.0)
    z = np.concatenate([unknowns_of(waypoint, tensions, base_frame(RAO, solved.base_moment)),
                        params.target + 0.01], axis=1)
    with jax.enable_x64(True):
        shared = SceneArrays(*(jax.numpy.asarray(a) for a in scene_arrays(planner.scene,
                                                                          as_numpy=True)))
        rows = jax.jit(partial(motion_unary, terms))
        for k in range(2):
            p = jax.tree_util.tree_map(lambda a, k=k: jax.numpy.asarray(np.asarray(a)[k]),
                                       params)
            tail = np.asarray(motion_unary_tail(terms, z[k], p, shared))
            base = np.asarray(rows(z[k], p, shared))
            assert tail.shape == (len(base), 3)
            for j in range(3):
                moved = z[k].copy()
                moved[waypoint.size + j] += 0.05
                change = (np.asarray(rows(moved, p, shared)) - base) / 0.05
                np.testing.assert_allclose(tail[:, j], change, rtol=0, atol=1e-9)
            assert np.abs(tail[-3:]).max() == terms.tie_weight
