"""Live tension IK (``tasks.mechanics.live_ik``): one target at a time under gravity and a
payload, warm-started from the current tensions; every answer replayed by a fresh statics
solve."""

from __future__ import annotations

import numpy as np
import pytest

from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
from cr_nlp.tasks._result import Stage
from cr_nlp.tasks.mechanics.ik import TensionIKConfig
from cr_nlp.tasks.mechanics.live_ik import TensionLiveIKSolver

RAO = load_robot("tdcr2_rao2021")
GRAVITY = [0.0, 0.0, -9.81]
PAYLOAD = [0.0, 0.0, -0.005 * 9.81]


@pytest.fixture(scope="module")
def live() -> TensionLiveIKSolver:
    return TensionLiveIKSolver(RAO, None, TensionIKConfig(pool_size=1024), gravity=GRAVITY,
                         tip_force=PAYLOAD)


def test_a_dragged_target_is_followed_from_the_current_tensions(live: TensionLiveIKSolver) -> None:
    t = np.linspace(0.0, 1.0, 6)[:, None]
    motion = np.concatenate([1 + 2 * t, 0 * t, 0.5 * t, 1 - t, t, 0 * t], axis=1)
    tips = solve_statics(RAO, motion, PAYLOAD, None, GRAVITY).tip_position
    current = motion[0]
    for target in tips[1:]:
        answer = live.solve(current, target)
        assert answer.success, answer.reason
        assert answer.stage == Stage.REFINE        # the warm start reached it
        again = solve_statics(RAO, answer.tensions[None], PAYLOAD, None, GRAVITY)
        assert np.linalg.norm(again.tip_position[0] - target) < 1e-4
        assert np.allclose(again.tip_position[0], answer.position, atol=1e-9)
        np.testing.assert_allclose(answer.backbone, again.positions[0], atol=1e-9)
        np.testing.assert_allclose(answer.backbone_rotations, again.rotations[0], atol=1e-9)
        current = answer.tensions


def test_bad_inputs_are_named(live: TensionLiveIKSolver) -> None:
    with pytest.raises(ValueError, match="tensions: expected 6"):
        live.solve(np.zeros(5), [0.0, 0.0, 0.4])
    with pytest.raises(ValueError, match="position"):
        live.solve(np.zeros(6), [np.nan, 0.0, 0.4])
    with pytest.raises(ValueError, match="tensions: expected 6"):
        live.equilibrium([1.0, np.inf, 0.0, 0.0, 0.0, 0.0])


def test_the_verdict_continues_from_the_equilibrium_on_screen(live: TensionLiveIKSolver,
                                                              monkeypatch) -> None:
    """The first update's verdict loads the rod from rest; the next one settles from the
    equilibrium that verdict found, in the LM's own program (no ``solve_statics`` call):
    the shape ``solve_statics(start_moment=…)`` gives from there, and a fresh solve from
    rest."""
    import cr_nlp.tasks.mechanics.ik as ik_module

    starts = []

    def spy(*args, **kwargs):
        starts.append(kwargs.get("start_moment"))
        return solve_statics(*args, **kwargs)

    monkeypatch.setattr(ik_module, "solve_statics", spy)
    motion = np.array([[1.0, 0, 0.2, 0.6, 0.3, 0], [1.2, 0, 0.2, 0.6, 0.4, 0]])
    tips = solve_statics(RAO, motion, PAYLOAD, None, GRAVITY).tip_position
    first = live.solve(motion[0], tips[0])
    second = live.solve(first.tensions, tips[1])
    assert first.success and second.success
    assert starts == [None]
    near = solve_statics(RAO, second.tensions[None], PAYLOAD, None, GRAVITY,
                         start_moment=first.base_moment)
    rest = solve_statics(RAO, second.tensions[None], PAYLOAD, None, GRAVITY)
    for fresh in (near, rest):
        np.testing.assert_allclose(second.backbone, fresh.positions[0], atol=1e-9)
        np.testing.assert_allclose(second.backbone_rotations, fresh.rotations[0], atol=1e-9)
        np.testing.assert_allclose(second.base_moment, fresh.base_moment[0], atol=1e-9)


def test_an_update_that_does_not_settle_from_the_last_equilibrium_loads_from_rest(
        live: TensionLiveIKSolver, monkeypatch) -> None:
    """Where Newton from the last equilibrium does not settle within its round (or settles
    on an unstable equilibrium), the verdict solves the answer's tensions from rest."""
    import cr_nlp.tasks.mechanics.ik as ik_module
    import cr_nlp.tasks.mechanics.live_ik as live_module

    starts = []

    def spy(*args, **kwargs):
        starts.append(kwargs.get("start_moment"))
        return solve_statics(*args, **kwargs)

    motion = np.array([[1.0, 0, 0.2, 0.6, 0.3, 0], [1.2, 0, 0.2, 0.6, 0.4, 0]])
    tips = solve_statics(RAO, motion, PAYLOAD, None, GRAVITY).tip_position
    first = live.solve(motion[0], tips[0])
    monkeypatch.setattr(ik_module, "solve_statics", spy)
    monkeypatch.setattr(live_module, "settled_statics", lambda *args: None)
    second = live.solve(first.tensions, tips[1])
    assert second.success, second.reason
    assert starts == [None]                        # one solve, from rest
    rest = solve_statics(RAO, second.tensions[None], PAYLOAD, None, GRAVITY)
    np.testing.assert_allclose(second.backbone, rest.positions[0], atol=1e-9)


def test_a_missed_update_tries_the_next_pool_seeds(live: TensionLiveIKSolver,
                                                   monkeypatch) -> None:
    """Where the warm start and the nearest pool set both miss, the update goes on to the
    next pool sets (as the batch's retries do) and answers from the first that verifies."""
    motion = np.array([[1.0, 0, 0.2, 0.6, 0.3, 0], [2.0, 0.5, 0, 0.2, 0.8, 0.1]])
    tips = solve_statics(RAO, motion, PAYLOAD, None, GRAVITY).tip_position
    stuck = motion[:1]
    real_lm, real_start = live.ik._lm, live.ik._start
    ranks = []

    def lm(tensions, *args, **kwargs):      # an LM that cannot leave ``stuck``
        return tensions if np.array_equal(tensions, stuck) else real_lm(tensions, *args,
                                                                        **kwargs)

    def start(positions, loads, rank):      # the nearest pool set is ``stuck``
        ranks.append(rank)
        return (stuck, None) if rank == 0 else real_start(positions, loads, rank)

    monkeypatch.setattr(live.ik, "_lm", lm)
    monkeypatch.setattr(live.ik, "_start", start)
    answer = live.solve(motion[0], tips[1])
    assert answer.success, answer.reason
    assert answer.stage == Stage.SEARCH and ranks == [0, 1]
    assert answer.timing.explore > 0.0 and answer.timing.refine > 0.0
    again = solve_statics(RAO, answer.tensions[None], PAYLOAD, None, GRAVITY)
    assert np.linalg.norm(again.tip_position[0] - tips[1]) < 1e-4
    missed = live.solve(motion[0], tips[1], search=False)
    assert not missed.success and missed.stage == Stage.REFINE


def test_newton_starts_from_the_lms_moment_only_a_drags_step_from_the_last_equilibrium(
        ) -> None:
    """The verdict's Newton starts from the LM's own M(0) where the LM moved it less than
    ``LIVE_NEWTON_START`` rad of bending from the last equilibrium, else from that one."""
    import jax

    from cr_nlp.tasks.mechanics.live_ik import LIVE_NEWTON_START, newton_start

    scale = 2.0                                           # N·m per radian of bending
    last = np.array([[0.3, -0.2, 0.05]])
    with jax.enable_x64(True):
        for move, lm_start in ((0.5 * LIVE_NEWTON_START, True),
                               (2.0 * LIVE_NEWTON_START, False)):
            lm_moment = last + move * scale * np.array([[0.6, 0.8, 0.0]])
            z = np.concatenate([np.full((1, 6), 0.4), lm_moment / scale], axis=1)
            start = np.asarray(newton_start(z, last, scale))
            np.testing.assert_allclose(start, lm_moment if lm_start else last, atol=1e-15)
