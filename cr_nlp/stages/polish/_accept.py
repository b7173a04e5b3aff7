"""Polish and accept: the exact stage's one acceptance policy, for every task.

Each problem (an IK target, a trajectory, a path) comes with candidates in order of
preference (the penalty stage's answer first, then its alternatives) and its penalty
answer already judged. Attempt after attempt, the problems not yet accepted polish their
next candidate, every polished answer is judged by the library's one verdict
(``world.verdict``), and the first accepted one is kept. A problem none of whose
polishes passes keeps its penalty answer with that answer's own verdict: the exact stage
can only add successes, never lose an answer (docs/design.md §2).

The answers are opaque to this module (configurations, trajectories, whole paths): the
caller gives three callables, each over a batch of the open problems, so a task can
polish a batch in parallel (a worker pool) and judge it in one vectorised call:

- ``candidate(attempt, rows)``: the ``attempt``-th candidate of each problem in ``rows``
  (None where a problem has no more);
- ``polish(starts, rows, attempt, budgets)``: a ``Polished`` per start: the polished
  answer worth judging, or None with the reason the polish gave up; ``budgets`` are the
  seconds each problem has left of its time limit (+inf without one);
- ``judge(answers, rows)``: one verdict per answer, any object with ``success`` (bool)
  and ``reason`` (str): ``world.verdict.Verdict`` or a task's row of checked numbers.

A time limit (exact mode's ``polish_time_limit``) covers a problem's whole exact stage:
the seconds its polishes report are summed, each polish gets what is left, and a problem
stops once a polish ran out of time or nothing is left for its next candidate. It keeps
the best answer the verdict accepted so far, else its penalty answer, and its outcome
says it ran out of time (``Outcome.out_of_time``). The verdict itself is never cut short.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

import numpy as np


class Judged(Protocol):
    """What ``polish_and_accept`` reads of a verdict (``world.verdict.Verdict`` is one)."""

    @property
    def success(self) -> bool: ...

    @property
    def reason(self) -> str: ...


@dataclass(frozen=True)
class RowVerdict:
    """A verdict as the acceptance reads it, for a task whose checks come as arrays (one
    row of a judged batch)."""

    success: bool
    """The answer passed the verdict."""
    reason: str
    """Empty on success, else why not."""


A = TypeVar("A")
V = TypeVar("V", bound=Judged)


@dataclass(frozen=True)
class Polished(Generic[A]):
    """One polish's outcome as the acceptance sees it."""

    answer: A | None
    """The polished answer to judge, or None: the polish produced nothing worth judging."""
    note: str = ""
    """Why the polish gave up (``answer`` None), in words; "" otherwise."""
    seconds: float = 0.0
    """Wall time of this polish, counted against its problem's time limit."""
    out_of_time: bool = False
    """The polish stopped at its time budget (``answer`` is then its last iterate, if
    worth judging)."""


@dataclass(frozen=True)
class Outcome(Generic[A, V]):
    """What one problem ends with."""

    answer: A
    """The first polished answer the verdict accepted, else the penalty answer."""
    verdict: V
    """The verdict on ``answer`` (the penalty answer's own when no polish passed)."""
    candidate: int | None
    """0-based index of the candidate whose polish was accepted; None: none was (the
    penalty answer stands)."""
    attempts: int
    """Polishes run for this problem."""
    failures: tuple[str, ...]
    """Why each polish that was not accepted failed, in attempt order."""
    out_of_time: bool = False
    """The time limit stopped this problem's exact stage: a polish ran out of time, or
    none was left for its next candidate."""

    @property
    def accepted(self) -> bool:
        """A polished answer was accepted."""
        return self.candidate is not None


@dataclass(frozen=True)
class Acceptance(Generic[A, V]):
    """The outcomes of ``polish_and_accept`` and where its time went."""

    outcomes: tuple[Outcome[A, V], ...]
    """One per problem, in the order given."""
    polish_seconds: float
    """Wall time in ``candidate`` and ``polish``, seconds."""
    judge_seconds: float
    """Wall time in ``judge``, seconds."""


def polish_and_accept(
    fallback: Sequence[A],
    fallback_verdicts: Sequence[V],
    candidate: Callable[[int, np.ndarray], Sequence[A | None]],
    polish: Callable[[list[A], np.ndarray, int], Sequence[Polished[A]]],
    judge: Callable[[list[A], np.ndarray], Sequence[V]],
    max_attempts: int,
    time_limit: float | None = None,
) -> Acceptance[A, V]:
    """Polish each problem's candidates in order and keep the first one the verdict
    accepts, else the penalty answer with its own verdict.

    Long: one attempt loop over eight per-problem tallies; split, its pieces would pass them all.

    Args:
        fallback: per problem, the penalty stage's answer (kept when no polish passes).
        fallback_verdicts: per problem, the verdict on ``fallback`` (from the same judge).
        candidate: ``(attempt, rows) → starts``: per problem index in ``rows`` (int
            array), its candidate number ``attempt`` (0 first), or None when it has no
            more (that problem stops). Called once per attempt with the open problems.
        polish: ``(starts, rows, attempt, budgets) → Polished`` per start (same order);
            ``budgets`` (len(rows),) seconds left to each problem (+inf: no limit).
        judge: ``(answers, rows) → verdicts`` per answer (same order).
        max_attempts: polishes per problem at most (≥ 1).
        time_limit: seconds of polishing per problem, all its attempts together (the
            ``Polished.seconds`` are summed); None: no limit.

    Returns:
        ``Acceptance``: an ``Outcome`` per problem and the seconds spent polishing and
        judging.

    Raises:
        ValueError: ``fallback`` and ``fallback_verdicts`` differ in length, a callable
            returns a list of the wrong length, ``max_attempts`` < 1, or ``time_limit``
            is not a positive finite number or None.
    """
    count = len(fallback)
    if len(fallback_verdicts) != count:
        raise ValueError(f"polish_and_accept needs a verdict per fallback answer, got "
                         f"{count} answers and {len(fallback_verdicts)} verdicts")
    if max_attempts < 1:
        raise ValueError(f"max_attempts must be at least 1, got {max_attempts}")
    check_time_limit(time_limit, "time_limit")
    limit = math.inf if time_limit is None else float(time_limit)
    spent = np.zeros(count)
    out_of_time = np.zeros(count, dtype=bool)
    answers: list[A] = list(fallback)
    verdicts: list[V] = list(fallback_verdicts)
    won: list[int | None] = [None] * count
    tries = [0] * count
    failures: list[list[str]] = [[] for _ in range(count)]
    polish_seconds = judge_seconds = 0.0
    todo = np.arange(count)
    for attempt in range(max_attempts):
        if not len(todo):
            break
        t0 = time.perf_counter()
        starts = _sized(candidate(attempt, todo), len(todo), "candidate")
        has = np.array([s is not None for s in starts], dtype=bool)
        # A problem with a next candidate but no time left for it stops here.
        late = has & (spent[todo] >= limit)
        out_of_time[todo[late]] = True
        keep = has & ~late
        todo, starts = todo[keep], [s for s, k in zip(starts, keep, strict=True) if k]
        if not len(todo):
            polish_seconds += time.perf_counter() - t0
            break
        polished = _sized(polish(starts, todo, attempt, limit - spent[todo]), len(todo),
                          "polish")
        polish_seconds += time.perf_counter() - t0
        for i, p in zip(todo.tolist(), polished, strict=True):
            tries[i] += 1
            spent[i] += p.seconds
            if p.out_of_time:
                out_of_time[i] = True
        made = np.array([p.answer is not None for p in polished], dtype=bool)
        for i, p in zip(todo[~made].tolist(), (p for p in polished if p.answer is None),
                        strict=True):
            failures[i].append(p.note or "the polish produced no answer")
        accepted = np.zeros(len(todo), dtype=bool)
        if made.any():
            rows = todo[made]
            candidates = [p.answer for p in polished if p.answer is not None]
            t0 = time.perf_counter()
            judged = _sized(judge(candidates, rows), len(rows), "judge")
            judge_seconds += time.perf_counter() - t0
            for k, (i, answer, verdict) in enumerate(zip(rows.tolist(), candidates, judged,
                                                         strict=True)):
                if verdict.success:
                    answers[i], verdicts[i], won[i] = answer, verdict, attempt
                    accepted[np.flatnonzero(made)[k]] = True
                else:
                    failures[i].append(f"rejected by the verdict: {verdict.reason}")
        # A problem whose polish ran out of time has no time for another candidate.
        todo = todo[~accepted & ~out_of_time[todo]]
    outcomes = tuple(Outcome(answers[i], verdicts[i], won[i], tries[i], tuple(failures[i]),
                             bool(out_of_time[i]))
                     for i in range(count))
    return Acceptance(outcomes, polish_seconds, judge_seconds)


def accept_first(candidates: Sequence[A], fallback: A, fallback_verdict: V,
                 polish: Callable[[A], Polished[A]], judge: Callable[[A], V]) -> Outcome[A, V]:
    """``polish_and_accept`` for one problem whose candidates are known up front:
    polish ``candidates`` in order, keep the first the verdict accepts, else ``fallback``
    with ``fallback_verdict``."""
    out = polish_and_accept(
        [fallback], [fallback_verdict],
        lambda attempt, rows: [candidates[attempt] if attempt < len(candidates) else None],
        lambda starts, rows, attempt, budgets: [polish(starts[0])],
        lambda answers, rows: [judge(answers[0])],
        max(len(candidates), 1))
    return out.outcomes[0]


def check_time_limit(value: float | None, name: str) -> None:
    """Raise ValueError unless ``value`` (seconds) is None or a positive finite number."""
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number of seconds or None, got {value!r}")


def polish_note(outcome: Outcome, failures: Sequence[str] | None = None) -> str:
    """How a task's ``stage`` says why no polish was accepted: "polish failed: …" or,
    when the time limit stopped the exact stage, "polish out of time: …", then the
    failures (``outcome.failures`` unless given) joined by "; "."""
    why = "; ".join(outcome.failures if failures is None else failures)
    head = "polish out of time" if outcome.out_of_time else "polish failed"
    return f"{head}: {why}" if why else head


def _sized(values: Sequence, count: int, name: str) -> list:
    values = list(values)
    if len(values) != count:
        raise ValueError(f"polish_and_accept: {name} returned {len(values)} entries for "
                         f"{count} problems")
    return values
