"""The trajectory planner's exact mode: which LM answers to polish, the attempt loop over
each problem's candidates, and how a polish's outcome replaces or annotates them (the
polish itself is ``stages.polish._trajectory_nlp``, the acceptance ``stages.polish._accept``).

Attempt k polishes the k-th candidate of every problem not yet accepted, in this process
or spread over a ``stages.polish._process_pool.PolishPool``; a polish that Ipopt reports
as failed is not judged. Trajectories are (waypoints, 3n) configurations θ, φ, L (rad,
rad, m). A time limit covers each problem's polishes together (``stages.polish._accept``):
each polish gets what its problem has left.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ...model import Robot
from ...stages.polish import (
    Acceptance,
    Judged,
    Polished,
    polish_and_accept,
    polish_note,
    polish_one,
)
from ...world._motion import MotionVerification
from ...world.verdict import Verdict
from .._result import Stage
from ._trajectory_result import TrajectoryResult, result_from_verdict


def polish_results(robot: Robot, rows: list[int], candidates: list[list[tuple[np.ndarray, str]]],
                   results: list[TrajectoryResult | None], dt: float,
                   verify: Callable[[np.ndarray], MotionVerification],
                   polisher: Callable[[], Any],
                   pool: Callable[[], Any] | None, attempts: int, polish_accepted: bool,
                   bar: Any, time_limit: float | None = None) -> None:
    """Polish each problem's LM candidates in order (best first, at most ``attempts``) and
    keep the first polished answer the verification accepts; if none is, the LM answer
    stays with its own verdict, its ``notes`` saying why each polish failed (exact mode
    never succeeds less often than the LM stage), or that its time limit ran out.

    Args:
        robot: the robot.
        rows: per problem, its index into ``results`` (whose entries are replaced or
            annotated in place; each gets its polish seconds in ``timing.polish``).
        candidates: per problem, (q (waypoints, 3n) rad/m, stage name), best first.
        results: the LM results.
        dt: seconds between waypoints.
        verify: q → ``world._motion.verify_trajectory``'s report.
        polisher, pool: as for ``polish_trajectories``.
        attempts: most candidates polished per problem.
        polish_accepted: also polish problems whose LM answer the verification accepts.
        bar: a tqdm bar advanced per problem, or None.
        time_limit: seconds of polishing per problem, all its candidates together (None:
            no limit).
    """
    # A penalty answer the independent verdict accepts needs no polish to be valid.
    todo = []
    for row, i in enumerate(rows):
        result = results[i]
        assert result is not None
        if result.success and not polish_accepted:
            result.timing = replace(result.timing, polish=0.0)
            if bar is not None:
                bar.update(1)
        else:
            todo.append(row)
    options = [candidates[row][:attempts] for row in todo]
    reports: dict[int, MotionVerification] = {}

    def judge(q: np.ndarray, r: int) -> Verdict:
        reports[r] = verify(q)
        return reports[r].verdict

    acceptance, seconds = polish_trajectories(
        options, [results[rows[row]] for row in todo], dt, judge, polisher, pool, bar,
        time_limit)
    for r, (row, outcome) in enumerate(zip(todo, acceptance.outcomes, strict=True)):
        i = rows[row]
        previous = results[i]
        assert previous is not None
        if outcome.accepted:
            results[i] = result_from_verdict(robot, outcome.answer, dt, reports[r], Stage.POLISH,
                                             previous.cost, previous.timing)
        else:
            failures = [f"from {options[r][k][1]}: {why}"
                        for k, why in enumerate(outcome.failures)]
            previous.notes.append(polish_note(outcome, failures))
        result = results[i]
        assert result is not None
        result.timing = replace(previous.timing, polish=float(seconds[r]))


def polish_trajectories(options: Sequence[Sequence[tuple[np.ndarray, str]]],
                        fallback: Sequence[Any], dt: float,
                        judge: Callable[[np.ndarray, int], Judged],
                        polisher: Callable[[], Any], pool: Callable[[], Any] | None = None,
                        bar: Any = None,
                        time_limit: float | None = None) -> tuple[Acceptance, np.ndarray]:
    """Polish P problems' candidates in order and keep, per problem, the first polish the
    verdict accepts, else its penalty answer.

    Args:
        options: per problem, its candidates (q (waypoints, 3n), what produced it), best
            first; as many attempts as the longest list.
        fallback: per problem, the penalty result (its ``q``, ``success`` and ``reason``
            stand when no polish is accepted).
        dt: seconds between waypoints.
        judge: ``(q, problem index) → verdict`` (``success``, ``reason``).
        polisher: returns this process's polisher (built on first use).
        pool: returns a ``PolishPool`` of ``stages.polish._trajectory_nlp.trajectory_polisher``
            workers, or None: polish in this process.
        bar: a tqdm bar advanced per problem of the first attempt, or None.
        time_limit: seconds of polishing per problem, all its candidates together (None:
            no limit).

    Returns:
        The ``Acceptance`` (an outcome per problem; its k-th failure note is that of
        candidate k) and the seconds spent per problem (P,), polishing and judging.
    """
    seconds = np.zeros(len(options))

    def candidate(attempt: int, rows: np.ndarray) -> list[np.ndarray | None]:
        return [options[r][attempt][0] if attempt < len(options[r]) else None for r in rows]

    def polish(starts: list[np.ndarray], rows: np.ndarray, attempt: int,
               budgets: np.ndarray) -> list[Polished[np.ndarray]]:
        items = [(q0, dt, None if time_limit is None else float(budget))
                 for q0, budget in zip(starts, budgets, strict=True)]
        progress = bar if attempt == 0 else None
        if pool is not None and len(items) > 1:
            outs = pool().map(polish_one, items, progress)
        else:
            outs = []
            for item in items:
                outs.append(polish_one(polisher(), *item))
                if progress is not None:
                    progress.update(1)
        seconds[rows] += [elapsed for _, _, elapsed, _ in outs]
        return [Polished(q, why, elapsed, late) for q, why, elapsed, late in outs]

    def judged(answers: list[np.ndarray], rows: np.ndarray) -> list[Judged]:
        out = []
        for q, r in zip(answers, rows, strict=True):
            t0 = time.perf_counter()
            out.append(judge(q, int(r)))
            seconds[r] += time.perf_counter() - t0
        return out

    attempts = max((len(o) for o in options), default=1)
    acceptance = polish_and_accept([r.q for r in fallback], list(fallback), candidate,
                                   polish, judged, max(attempts, 1), time_limit)
    return acceptance, seconds
