"""The IK solver's exact mode: which answers to polish (each target's answer, then the
other candidates of the search's own beam) and which polish counts; the polish itself is
``stages.polish._ik_nlp``, the acceptance ``stages.polish._accept``.

A polish counts as worth judging when Ipopt succeeded, or when it keeps every
constraint and comes nearer the target than the answer it started from (it may miss the
polish's own 1e-6 pose tolerance and still pass the task's): so is the last iterate of a
polish that ran out of time. Candidates of one beam that refined to the same answer are
polished once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ...stages.polish import (
    Acceptance,
    IKPolisher,
    Judged,
    Polished,
    polish_and_accept,
    polish_many,
)


def other_candidates(beam: np.ndarray, answer: np.ndarray,
                     apart: float = 1e-4) -> list[np.ndarray]:
    """A target's beam candidates (width, 3n), best first, that differ from its answer
    and from each other by more than ``apart`` (rad or m) in some variable, finite ones
    only: the exact stage's next warm starts (``candidate_order`` for one target)."""
    order = candidate_order(beam[None], np.asarray(answer)[None], apart)[0]
    return [beam[j] for j in order[order >= 0].tolist()]


def candidate_order(beams: np.ndarray, answers: np.ndarray, apart: float = 1e-4) -> np.ndarray:
    """For T targets' beams (T, width, 3n), best first, and answers (T, 3n): (T, width)
    indices into each beam of its candidates that differ from the answer and from each
    other by more than ``apart`` (rad or m) in some variable, finite ones only, in beam
    order, then −1. In numpy over the targets, one step per beam member."""
    count, width = beams.shape[:2]
    finite = np.all(np.isfinite(beams), axis=2)
    with np.errstate(invalid="ignore"):
        # NaN differences (an answer with no value) never count as apart.
        from_answer = np.max(np.abs(beams - answers[:, None]), axis=2) > apart
        between = np.max(np.abs(beams[:, :, None] - beams[:, None]), axis=3) > apart
    kept = np.zeros((count, width), dtype=bool)
    for j in range(width):   # apart from every candidate kept before it
        kept[:, j] = (finite[:, j] & from_answer[:, j]
                      & np.all(between[:, j, :j] | ~kept[:, :j], axis=1))
    rank = np.where(kept, np.arange(width), width)
    order = np.sort(rank, axis=1)
    return np.where(order < width, order, -1)


def polish_answers(polisher: IKPolisher, answers: np.ndarray, beams: np.ndarray,
                   pose_errors: np.ndarray, positions: np.ndarray, rotations: np.ndarray,
                   verdicts: Sequence[Judged],
                   judge: Callable[[np.ndarray, np.ndarray], Sequence[Judged]],
                   attempts: int, progress: bool = False, pool: Any = None,
                   time_limit: float | None = None) -> Acceptance:
    """Polish T answers and accept the first polish of each that the verdict accepts.

    Args:
        polisher: the ``IKPolisher`` of the robot and scene.
        answers: (T, 3n) the penalty stage's answers θ, φ, L (rad, rad, m).
        beams: (T, width, 3n) the search's refined beam per target, best first (NaN rows
            where there is none).
        pose_errors: (T,) the answers' verified pose errors (mixed m/rad).
        positions: (T, 3) target positions, m; rotations: (T, 3, 3).
        verdicts: (T,) the verdicts on ``answers`` (kept where no polish is accepted).
        judge: ``(q (B, 3n), rows (B,)) → verdicts``, rows indexing the T targets.
        attempts: polishes per target at most.
        progress: a progress bar for the first attempt.
        pool: a ``stages.polish._process_pool.PolishPool`` spreading the polishes over processes,
        or None.
        time_limit: seconds of polishing per target, all its attempts together (None: no
            limit); a target out of time keeps its best accepted answer so far.

    Returns:
        ``stages.polish._accept.Acceptance`` with one outcome per target (answer q (3n,)).
    """
    cfg = polisher.config
    order = candidate_order(beams, answers)

    def candidate(attempt: int, rows: np.ndarray) -> list[np.ndarray | None]:
        if attempt == 0:
            return list(answers[rows])
        if attempt > order.shape[1]:
            return [None] * len(rows)
        which = order[rows, attempt - 1]
        return [beams[i, j] if j >= 0 else None
                for i, j in zip(rows.tolist(), which.tolist(), strict=True)]

    def polish(starts: list[np.ndarray], rows: np.ndarray, attempt: int,
               budgets: np.ndarray) -> list[Polished[np.ndarray]]:
        outs = polish_many(polisher, np.stack(starts), positions[rows], rotations[rows],
                           progress=progress and attempt == 0,
                           pool=pool if len(rows) > 1 else None,
                           time_limits=None if time_limit is None else budgets)
        out = []
        for i, o in zip(rows.tolist(), outs, strict=True):
            worth = o.success or (o.max_violation <= cfg.violation_tolerance
                                  and np.isfinite(o.pose_error) and o.pose_error < pose_errors[i])
            out.append(Polished(o.q if worth else None,
                                "" if worth else o.failure(cfg.pose_tolerance,
                                                           cfg.violation_tolerance),
                                o.seconds, o.out_of_time))
        return out

    return polish_and_accept(list(answers), list(verdicts), candidate, polish,
                             lambda q, rows: judge(np.stack(q), rows), max(attempts, 1),
                             time_limit)
