"""The polish-and-accept stage (``stages.polish._accept``): toy problems with known answers, then
through IK's exact mode; and the one Ipopt set-up (``stages.polish._ipopt``) on a closed form."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from cr_nlp.stages.polish._accept import Polished, accept_first, polish_and_accept
from cr_nlp.stages.polish._ipopt import WarmStart, build_solver, ipopt_options, run_solver
from cr_nlp.world.verdict import Verdict, judge

# Toy problem: an answer is a number x, "success" means |x − goal| < 0.1 and x ≥ 0 (a
# limit); the "polish" moves its start halfway to the goal.
GOALS = np.array([1.0, 2.0, -3.0, 5.0])


def toy_judge(answers: list[float], rows: np.ndarray) -> list[Verdict]:
    return [judge(margin=0.0, limits=max(-x, 0.0), pose_error=abs(x - GOALS[i]),
                  pose_tolerance=0.1) for x, i in zip(answers, rows.tolist(), strict=True)]


def halfway(starts: list[float], rows: np.ndarray, attempt: int,
            budgets: np.ndarray) -> list[Polished[float]]:
    return [Polished(0.5 * (x + GOALS[i])) for x, i in zip(starts, rows.tolist(), strict=True)]


def test_first_accepted_candidate_wins_and_failures_keep_the_penalty_answer() -> None:
    # Problem 0: its first candidate polishes to the goal. Problem 1: the first lands
    # 0.5 away (rejected), the second on the goal. Problem 2: the goal breaks the limit,
    # every polish is rejected. Problem 3: a single candidate, too far.
    candidates = {0: [1.0], 1: [1.0, 2.1], 2: [-3.0, -2.0, -1.0], 3: [0.0]}
    fallback = [0.9, 1.5, 0.0, 4.0]
    verdicts = toy_judge(fallback, np.arange(4))
    calls: list[list[int]] = []

    def candidate(attempt: int, rows: np.ndarray) -> list[float | None]:
        calls.append(rows.tolist())
        return [candidates[i][attempt] if attempt < len(candidates[i]) else None
                for i in rows.tolist()]

    out = polish_and_accept(fallback, verdicts, candidate, halfway, toy_judge,
                            max_attempts=5)
    first, second, limited, far = out.outcomes
    assert first.accepted and first.candidate == 0 and first.answer == 1.0
    assert first.attempts == 1 and first.failures == ()
    assert second.candidate == 1 and second.answer == pytest.approx(2.05)
    assert second.attempts == 2 and "rejected by the verdict: pose error" in second.failures[0]
    # Rejected by the limit every time: the penalty answer stays with its own verdict.
    assert not limited.accepted and limited.answer == 0.0 and limited.verdict is verdicts[2]
    assert limited.attempts == 3 and all("configuration limit" in f for f in limited.failures)
    assert not far.accepted and far.answer == 4.0 and far.verdict.success is False
    # Only the problems still open are asked for candidates; the stage stops when every
    # open problem ran out.
    assert calls == [[0, 1, 2, 3], [1, 2, 3], [2], [2]]
    assert out.polish_seconds >= 0.0 and out.judge_seconds >= 0.0


def test_a_polish_that_gives_up_is_not_judged_and_its_words_are_kept() -> None:
    judged: list[int] = []

    def judge_rows(answers: list[float], rows: np.ndarray) -> list[Verdict]:
        judged.extend(rows.tolist())
        return toy_judge(answers, rows)

    def polish(starts: list[float], rows: np.ndarray, attempt: int,
               budgets: np.ndarray) -> list[Polished[float]]:
        assert np.all(budgets == np.inf)  # no time limit
        return [Polished(None, "Ipopt: Infeasible_Problem_Detected") if i == 0
                else Polished(GOALS[i]) for i in rows.tolist()]

    fallback = [0.0, 0.0]
    out = polish_and_accept(fallback, toy_judge(fallback, np.arange(2)),
                            lambda attempt, rows: [0.0] * len(rows), polish, judge_rows,
                            max_attempts=2)
    assert out.outcomes[0].failures == ("Ipopt: Infeasible_Problem_Detected",) * 2
    assert not out.outcomes[0].accepted and out.outcomes[1].candidate == 0
    assert judged == [1]


def test_accept_first_on_one_problem_and_bad_input() -> None:
    verdict = toy_judge([0.0], np.array([3]))[0]
    outcome = accept_first([0.0, 4.8], 0.0, verdict,
                           lambda x: Polished(0.5 * (x + 5.0)),
                           lambda x: toy_judge([x], np.array([3]))[0])
    assert outcome.candidate == 1 and outcome.answer == pytest.approx(4.9)
    none = accept_first([], 0.0, verdict, lambda x: Polished(x), lambda x: verdict)
    assert not none.accepted and none.attempts == 0 and none.answer == 0.0
    with pytest.raises(ValueError, match="a verdict per fallback answer"):
        polish_and_accept([0.0], [], lambda a, r: [0.0], halfway, toy_judge, 1)
    with pytest.raises(ValueError, match="max_attempts"):
        polish_and_accept([0.0], [verdict], lambda a, r: [0.0], halfway, toy_judge, 0)
    with pytest.raises(ValueError, match="polish returned 0 entries for 1"):
        polish_and_accept([0.0], [verdict], lambda a, r: [0.0], lambda s, r, a, b: [],
                          toy_judge, 1)


def test_shared_ipopt_setup_solves_a_closed_form_and_reports_failure_as_a_value() -> None:
    # min (x − 2)² s.t. x ≤ 1 (as a row): x = 1, objective 1; warm-started at the answer.
    x, p = ca.MX.sym("x"), ca.MX.sym("p")
    options = ipopt_options(tol=1e-10, constr_viol_tol=1e-10, max_iter=50,
                            warm_start=WarmStart(push=1e-9, mu_init=1e-6),
                            mu_strategy="adaptive")
    assert options["ipopt.linear_solver"] == "mumps" and options["ipopt.mu_init"] == 1e-6
    solver = build_solver("closed_form", {"x": x, "p": p, "f": (x - p) ** 2, "g": x},
                          options)
    run = run_solver(solver, np.array([1.0]), p=2.0, lbg=-np.inf, ubg=1.0)
    assert run.success and run.status == "Solve_Succeeded" and not run.raised
    assert run.x == pytest.approx([1.0], abs=1e-7) and run.objective == pytest.approx(1.0)
    # Infeasible bounds: not an exception, a failed run with Ipopt's words.
    bad = run_solver(solver, np.array([0.0]), p=2.0, lbg=3.0, ubg=1.0)
    assert not bad.success and bad.status != "Solve_Succeeded"


def test_ik_polish_retries_from_the_search_beam_without_searching_again(monkeypatch) -> None:
    """Through IK: every first polish is made to fail; the second attempt starts from
    another member of the search's own beam (not the answer, no new search), and what
    it accepts passes an independent float64 check."""
    import dataclasses

    from cr_nlp.bench.ik import forward_kinematics
    from cr_nlp.model import load_robot
    from cr_nlp.tasks.geometry import _ik_polish as ik_polish
    from cr_nlp.tasks.geometry.ik import IKSolver
    from cr_nlp.world import check_many

    robot = load_robot("tdcr3")
    rng = np.random.default_rng(3)
    lo, hi = robot.q_bounds()
    q_true = rng.uniform(lo, hi, (6, robot.dof))
    q_true = q_true[check_many(robot, None, q_true).self_distance >= 0.01][:4]
    positions, wxyz = forward_kinematics(robot, q_true)
    solver = IKSolver(robot)
    first = solver.solve(positions, wxyz)

    real = ik_polish.polish_many
    starts: list[np.ndarray] = []

    def first_polish_fails(polisher, q0s, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003
        outs = real(polisher, q0s, *args, **kwargs)
        starts.append(np.array(q0s))
        if len(starts) == 1:
            outs = [dataclasses.replace(o, success=False, status="Maximum_Iterations_Exceeded",
                                        pose_error=1.0) for o in outs]
        return outs

    def no_search(*args, **kwargs):  # noqa: ANN002, ANN003
        raise AssertionError("the exact stage must not search again")

    monkeypatch.setattr(ik_polish, "polish_many", first_polish_fails)
    monkeypatch.setattr(IKSolver, "candidates", no_search)
    exact = solver.solve(positions, wxyz, exact=True)
    assert len(starts) >= 2 and 0 < len(starts[1]) <= len(q_true)
    np.testing.assert_allclose(starts[0], first.q)
    # The second warm starts are other beam candidates, not the answers again; the
    # targets whose beam refined to one answer have no second start and stay refined.
    assert np.all(np.abs(starts[1][:, None] - first.q[None]).max(axis=2) > 1e-4)
    polished = np.array([s == "polish" for s in exact.stage])
    assert 1 <= polished.sum() <= len(starts[1]), exact.stage
    assert exact.success.all(), exact.reason
    assert all("polish failed: Ipopt: Maximum_Iterations_Exceeded" in s
               for s in np.array(exact.stage_text)[~polished])
    assert all(exact.notes[i][0].startswith("polish failed: Ipopt: Maximum_Iterations_Exceeded")
               for i in np.flatnonzero(~polished))
    reached_p, reached_w = forward_kinematics(robot, exact.q[polished])
    assert np.abs(reached_p - positions[polished]).max() < 1e-6
    assert np.abs(np.abs(np.sum(reached_w * wxyz[polished], axis=1)) - 1).max() < 1e-9
    assert check_many(robot, None, exact.q).self_distance.min() >= solver.config.safety_margin
