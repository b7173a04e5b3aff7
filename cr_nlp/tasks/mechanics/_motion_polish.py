"""Exact mode of the tension motions (planning and following): which refine-stage motion
to polish with Ipopt, and which answer to keep (the polish itself is ``stages.polish``'s
``polish_tension_motion``, the acceptance its ``polish_and_accept``).

A motion the verdict rejects is polished from its candidates in order (the refine stage's
answer first, then the task's other motion where it has one); with ``polish_accepted`` a
verified motion is polished too (its polish replaces it only where the verdict accepts
the polish). The first polish the verdict accepts is kept (``Stage.POLISH``); otherwise
the refine-stage answer stays with its own verdict and a note says why each polish
failed: exact mode never succeeds less often than the penalty stages. A time limit covers
the motion's polishes together."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ...stages import polish as exact_stage
from ...stages.polish import Polished, polish_and_accept, polish_note
from .._result import Stage
from .._timing import StageTiming
from ._motion_result import TensionTrajectoryResult


def polish_motion(result: TensionTrajectoryResult, candidates: Sequence[tuple[np.ndarray, str]],
                  polish: Callable[[np.ndarray, float | None], Any],
                  remake: Callable[[np.ndarray], TensionTrajectoryResult],
                  timing: StageTiming, time_limit: float | None = None,
                  polish_accepted: bool = False) -> TensionTrajectoryResult:
    """Exact mode on one motion (see the module's docstring).

    Args:
        result: the refine stage's judged motion (a plan's or a followed path's).
        candidates: (tensions (T, n) N, what produced them) to polish, best first.
        polish: (start tensions, seconds left or None) → ``TensionMotionPolish``.
        remake: tensions → the task's judged result of that motion (its verdict).
        timing: its ``polish`` and ``verify`` seconds grow; the kept result gets it.
        time_limit: seconds of polishing for this motion, all candidates (None: none).
        polish_accepted: also polish a motion the verdict accepts.

    Returns:
        The accepted polish (``Stage.POLISH``), else ``result`` with a note; either way
        ``exact_mode`` names the formulation.
    """
    result.exact_mode = exact_stage.MOTION_EXACT_MODE    # imports CasADi (first use)
    if result.stage is Stage.REJECTED or (result.success and not polish_accepted):
        return result
    succeeded = tuple(exact_stage.SUCCESS_STATUSES)
    out_of_time = exact_stage.TIME_LIMIT_STATUS
    judged: list[TensionTrajectoryResult] = []
    runs: list[Any] = []

    def candidate(attempt: int, rows: np.ndarray) -> list[np.ndarray | None]:
        return [candidates[attempt][0] if attempt < len(candidates) else None]

    def run(starts: list, rows: np.ndarray, attempt: int,
            budgets: np.ndarray) -> list[Polished]:
        budget = None if not math.isfinite(float(budgets[0])) else float(budgets[0])
        out = polish(starts[0], budget)
        runs.append(out)
        # Ipopt's answer is judged where it converged or ran out of time (its last
        # iterate may still pass the verdict); otherwise its status is the reason.
        keep = out.status in succeeded or out.status == out_of_time
        return [Polished(out.tensions if keep else None,
                         "" if out.status in succeeded else f"Ipopt: {out.status}",
                         float(out.seconds), out.status == out_of_time)]

    def judge(answers: list, rows: np.ndarray) -> list[TensionTrajectoryResult]:
        started = time.perf_counter()
        judged.append(remake(answers[0]))
        timing.verify += time.perf_counter() - started
        return [judged[-1]]

    start = time.perf_counter()
    accepted = polish_and_accept([result.tensions], [result], candidate, run, judge,
                                 len(candidates), time_limit)
    timing.polish += time.perf_counter() - start - accepted.judge_seconds
    outcome = accepted.outcomes[0]
    if not outcome.accepted:
        failures = [f"from {candidates[k][1]}: {why}" for k, why in enumerate(outcome.failures)]
        result.notes.append(polish_note(outcome, failures))
        result.timing = timing
        return result
    polished = judged[-1]
    last = runs[-1]
    polished.stage, polished.exact_mode, polished.timing = (Stage.POLISH,
                                                            result.exact_mode, timing)
    polished.notes = [*result.notes, f"polished by Ipopt from {candidates[outcome.candidate][1]}"
                      f" ({last.status}, {last.iterations} iterations, {last.seconds:.2f} s)"]
    return polished
