"""Issue 41, time budgets: exact mode's ``polish_time_limit`` covers a problem's whole exact
stage; out of time, a problem keeps its best verified answer and says so. From the Ipopt
deadline up through the acceptance, IK, a trajectory polish and the command line."""

from __future__ import annotations

import math
import time
from dataclasses import replace
from types import SimpleNamespace

import casadi as ca
import numpy as np
import pytest

from cr_nlp.cli import main
from cr_nlp.stages.polish._accept import Polished, check_time_limit, polish_and_accept, polish_note
from cr_nlp.stages.polish._ipopt import (
    TIME_LIMIT_STATUS,
    Deadline,
    build_solver,
    ipopt_options,
    run_solver,
)
from cr_nlp.world.verdict import Verdict, judge

from ...conftest import MODELS


@pytest.mark.parametrize("bad", [0, 0.0, -1.0, math.nan, math.inf, True, "1"])
def test_a_time_limit_is_positive_and_finite_or_none(bad: object) -> None:
    with pytest.raises(ValueError, match="positive number of seconds"):
        check_time_limit(bad, "time_limit")  # type: ignore[arg-type]
    for good in (None, 1e-9, 2, 13.5):
        check_time_limit(good, "time_limit")


def test_a_deadline_stops_an_ipopt_solve_and_no_deadline_changes_nothing() -> None:
    # The extended Rosenbrock function from its standard start: hundreds of iterations.
    n = 400
    x = ca.MX.sym("x", n)
    nlp = {"x": x, "f": ca.sum1(100 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2),
           "g": ca.MX(0, 1)}
    x0 = np.tile([-1.2, 1.0], n // 2)
    options = ipopt_options(tol=1e-12, constr_viol_tol=1e-10, max_iter=3000)
    deadline = Deadline()
    plain, timed = build_solver("plain", nlp, options), build_solver("timed", nlp, options,
                                                                      deadline)
    free = run_solver(plain, x0)
    unlimited = run_solver(timed, x0, deadline)
    assert free.success and unlimited.success and not unlimited.out_of_time
    assert unlimited.iterations == free.iterations
    np.testing.assert_array_equal(unlimited.x, free.x)
    # Stopped mid-solve: Ipopt's last iterate, the time-limit status, in bounded time.
    deadline.start(0.01)
    t0 = time.perf_counter()
    stopped = run_solver(timed, x0, deadline)
    elapsed = time.perf_counter() - t0
    assert stopped.status == TIME_LIMIT_STATUS and stopped.out_of_time and not stopped.success
    assert 0 < stopped.iterations < free.iterations and elapsed < 1.0
    # A deadline already passed stops before the first step.
    deadline.at = 0.0
    assert run_solver(timed, x0, deadline).iterations == 0
    deadline.start(None)
    assert run_solver(timed, x0, deadline).iterations == free.iterations


GOALS = np.array([1.0, 2.0, 3.0])


def toy_judge(answers: list[float], rows: np.ndarray) -> list[Verdict]:
    return [judge(margin=0.0, limits=0.0, pose_error=abs(x - GOALS[i]), pose_tolerance=0.1)
            for x, i in zip(answers, rows.tolist(), strict=True)]


def test_the_limit_covers_every_attempt_of_a_problem() -> None:
    # Problem 0: every polish lands 1 away (rejected) and takes 0.4 s: the third uses the
    # last of its 1 s, no fourth starts. Problem 1: its first polish runs out of time,
    # nothing more is tried. Problem 2: accepted at once.
    budgets_seen: dict[int, list[float]] = {0: [], 1: [], 2: []}

    def polish(starts: list[float], rows: np.ndarray, attempt: int,
               budgets: np.ndarray) -> list[Polished[float]]:
        out = []
        for i, budget in zip(rows.tolist(), budgets.tolist(), strict=True):
            budgets_seen[i].append(budget)
            if i == 0:
                out.append(Polished(GOALS[0] + 1.0, seconds=0.4))
            elif i == 1:
                out.append(Polished(None, "Ipopt stopped at the time limit", seconds=1.0,
                                    out_of_time=True))
            else:
                out.append(Polished(GOALS[2], seconds=0.1))
        return out

    fallback = [0.5, 0.5, 0.5]
    verdicts = toy_judge(fallback, np.arange(3))
    out = polish_and_accept(fallback, verdicts, lambda attempt, rows: [0.0] * len(rows),
                            polish, toy_judge, max_attempts=5, time_limit=1.0)
    slow, stopped, quick = out.outcomes
    assert budgets_seen[0] == pytest.approx([1.0, 0.6, 0.2])
    assert budgets_seen[1] == [1.0] and budgets_seen[2] == [1.0]
    # Out of time: the penalty answer with its own verdict, and the stage's words.
    assert slow.out_of_time and not slow.accepted and slow.attempts == 3
    assert slow.answer == 0.5 and slow.verdict is verdicts[0]
    assert polish_note(slow).startswith("polish out of time: rejected by the verdict")
    assert stopped.out_of_time and stopped.attempts == 1 and stopped.verdict is verdicts[1]
    assert polish_note(stopped) == "polish out of time: Ipopt stopped at the time limit"
    assert quick.accepted and not quick.out_of_time and quick.answer == GOALS[2]
    # Without a limit the same polishes run to max_attempts.
    unlimited = polish_and_accept(fallback, verdicts, lambda attempt, rows: [0.0] * len(rows),
                                  polish, toy_judge, max_attempts=5)
    assert unlimited.outcomes[0].attempts == 5 and not unlimited.outcomes[0].out_of_time
    assert polish_note(unlimited.outcomes[0]).startswith("polish failed: ")


@pytest.fixture(scope="module")
def ik_case():
    from cr_nlp.bench.ik import forward_kinematics
    from cr_nlp.model import load_robot
    from cr_nlp.world import check_many

    robot = load_robot("tdcr3")
    rng = np.random.default_rng(3)
    lo, hi = robot.q_bounds()
    q_true = rng.uniform(lo, hi, (8, robot.dof))
    q_true = q_true[check_many(robot, None, q_true).self_distance >= 0.01][:4]
    return robot, *forward_kinematics(robot, q_true)


def test_exact_ik_out_of_time_keeps_the_verified_penalty_answer(ik_case) -> None:
    from cr_nlp.tasks.geometry.ik import IKConfig, IKSolver

    robot, positions, wxyz = ik_case
    # A limit too short for any Ipopt iteration: every target runs out of time at once.
    solver = IKSolver(robot, config=IKConfig(polish_time_limit=1e-9))
    penalty = solver.solve(positions, wxyz)
    late = solver.solve(positions, wxyz, exact=True)
    for i in range(len(positions)):
        assert late.stage[i] == "refine" and late.notes[i][0].startswith(
            "polish out of time: Ipopt stopped at the time limit (0 iterations"), late.notes[i]
        assert late.stage_text[i].startswith("refine (polish out of time: Ipopt stopped at "
                                             "the time limit (0 iterations"), late.stage_text[i]
    # The penalty answer, judged by the same verdict.
    np.testing.assert_array_equal(late.q, penalty.q)
    np.testing.assert_array_equal(late.success, penalty.success)
    assert late.reason == penalty.reason
    np.testing.assert_array_equal(late.max_violation, penalty.max_violation)
    # A generous limit gives the answers of no limit.
    solver.config = replace(solver.config, polish_time_limit=None)
    free = solver.solve(positions, wxyz, exact=True)
    solver.config = replace(solver.config, polish_time_limit=600.0)
    generous = solver.solve(positions, wxyz, exact=True)
    assert generous.stage_text == free.stage_text
    assert "out of time" not in " ".join(free.stage_text)
    np.testing.assert_array_equal(generous.q, free.q)
    np.testing.assert_array_equal(generous.success, free.success)


def test_a_trajectory_polish_out_of_time_keeps_the_lm_answer_marked() -> None:
    from cr_nlp.model import load_robot
    from cr_nlp.stages.polish._trajectory_nlp import TrajectoryPolisher
    from cr_nlp.tasks.geometry._trajectory_polish import polish_trajectories
    from cr_nlp.tasks.geometry.trajectory import verify_trajectory

    from .test_polish_verdict import cut_between_waypoints

    robot = load_robot(MODELS / "robots" / "tdcr3.json")
    q0, scene = cut_between_waypoints(robot)   # the motion cuts a sphere: polish needed
    dt = 1.0
    polisher = TrajectoryPolisher(robot, scene, 6)
    assert polisher.solve(q0, dt).success      # built, and repaired without a limit
    t0 = time.perf_counter()
    out = polisher.solve(q0, dt, time_limit=1e-3)
    assert time.perf_counter() - t0 < 2.0
    assert out.out_of_time and not out.success
    before = verify_trajectory(robot, scene, q0, dt)
    lm = SimpleNamespace(q=q0, success=bool(before.success), reason=before.reason)
    acceptance, seconds = polish_trajectories(
        [[(q0, "refine (straight)"), (q0, "refine (perturbed)")]], [lm], dt,
        lambda q, r: verify_trajectory(robot, scene, q, dt).verdict, lambda: polisher,
        time_limit=1e-3)
    outcome = acceptance.outcomes[0]
    assert outcome.out_of_time and not outcome.accepted and outcome.attempts == 1
    assert outcome.answer is q0 and outcome.verdict is lm
    assert polish_note(outcome).startswith("polish out of time: Ipopt stopped at the time "
                                           "limit")
    assert seconds[0] < 2.0


def test_a_path_polish_out_of_time_keeps_the_lm_answer_marked() -> None:
    from cr_nlp.stages.polish._trajectory_nlp import TrajectoryPolishResult
    from cr_nlp.tasks._timing import StageTiming
    from cr_nlp.tasks.geometry._follow_polish import polish_follow

    identity = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    lm = SimpleNamespace(q=np.zeros((3, 9)), max_violation=0.5, collision_free=False,
                         reached=np.ones(3, bool), position=np.zeros((3, 3)), wxyz=identity,
                         stage="refine", success=False, reason="in collision")
    limits: list[float | None] = []

    class Slow:
        def solve(self, q0, dt, positions, rotations, time_limit=None):  # noqa: ANN001, ANN202
            limits.append(time_limit)
            return TrajectoryPolishResult(q0, False, TIME_LIMIT_STATUS, 0.5, {"clearance": 0.5},
                                          iterations=7, seconds=2.0, out_of_time=True)

    def never(*args: object) -> None:
        raise AssertionError("a polish without an answer is not judged")

    path = SimpleNamespace(positions=np.zeros((3, 3)), wxyz=identity, dt=0.1)
    out = polish_follow(None, lambda waypoints: Slow(), lm, path, np.ones(3, bool), never,
                        never, StageTiming(), False, time_limit=2.0)
    assert out is lm and limits == [2.0]
    assert lm.stage == "refine" and lm.notes[0].startswith(
        "polish out of time: Ipopt stopped at the time limit (7 iterations, 2 s)"), lm.notes


@pytest.mark.parametrize("command", [
    ["ik", "--robot", "tdcr3", "--targets", "tdcr3_lattice", "--out", "r.json", "--exact"],
    ["plan", "--robot", "tdcr3", "--problems", "tdcr3_shelf", "--out", "r.json", "--exact"],
    ["follow", "--robot", "tdcr3", "--path", "square", "--out", "r.json", "--exact"],
    ["batch", "ik", "--robot", "tdcr3", "--targets", "tdcr3_lattice", "--out", "d",
     "--exact"],
])
@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "soon"])
def test_the_cli_refuses_a_time_limit_that_is_not_positive(
        command: list[str], value: str, capsys: pytest.CaptureFixture) -> None:
    assert main([*command, "--time-limit", value]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--time-limit" in err[0], err


@pytest.mark.parametrize("kind", ["ik", "batch"])
def test_the_cli_time_limit_needs_exact(kind: str, capsys: pytest.CaptureFixture) -> None:
    command = ["ik", "--robot", "tdcr3", "--targets", "tdcr3_lattice", "--out", "r.json"]
    if kind == "batch":
        command = ["batch", *command[:-1], "d"]
    assert main([*command, "--time-limit", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "give it with --exact" in err[0], err
