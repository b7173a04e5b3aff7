"""The trajectory planner's exact mode: which LM answers to polish and how a polish's
outcome replaces or annotates them (the polish itself is ``stages.polish._trajectory_exact``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from ..model import Robot
from ..stages.polish._accept import polish_note
from ..stages.polish._trajectory_exact import polish_trajectories
from ..world.verdict import Verdict
from ._trajectory_result import TrajectoryResult, result_from_verdict


def polish_results(robot: Robot, rows: list[int], candidates: list[list[tuple[np.ndarray, str]]],
                   results: list[TrajectoryResult | None], dt: float,
                   verify: Callable[[np.ndarray], dict[str, Any]], polisher: Callable[[], Any],
                   pool: Callable[[], Any] | None, attempts: int, polish_accepted: bool,
                   bar: Any, time_limit: float | None = None) -> None:
    """Polish each problem's LM candidates in order (best first, at most ``attempts``) and
    keep the first polished answer the verification accepts; if none is, the LM answer
    stays with its own verdict, its ``stage`` noting why each polish failed (exact mode
    never succeeds less often than the LM stage), or that its time limit ran out.

    Args:
        robot: the robot.
        rows: per problem, its index into ``results`` (whose entries are replaced or
            annotated in place; each gets its polish seconds in ``timing.polish``).
        candidates: per problem, (q (waypoints, 3n) rad/m, stage name), best first.
        results: the LM results.
        dt: seconds between waypoints.
        verify: q → ``world._motion.verify_trajectory``'s dict.
        polisher, pool: as for ``stages.polish._trajectory_exact.polish_trajectories``.
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
    reports: dict[int, dict[str, Any]] = {}

    def judge(q: np.ndarray, r: int) -> Verdict:
        reports[r] = verify(q)
        return reports[r]["verdict"]

    acceptance, seconds = polish_trajectories(
        options, [results[rows[row]] for row in todo], dt, judge, polisher, pool, bar,
        time_limit)
    for r, (row, outcome) in enumerate(zip(todo, acceptance.outcomes, strict=True)):
        i = rows[row]
        previous = results[i]
        assert previous is not None
        if outcome.accepted:
            results[i] = result_from_verdict(robot, outcome.answer, dt, reports[r], "polish",
                                             previous.cost, previous.timing)
        else:
            failures = [f"from {options[r][k][1]}: {why}"
                        for k, why in enumerate(outcome.failures)]
            previous.stage = f"{previous.stage} ({polish_note(outcome, failures)})"
        result = results[i]
        assert result is not None
        result.timing = replace(previous.timing, polish=float(seconds[r]))
