"""Refine-and-verify selection of the trajectory LM's guesses, in two rounds.

Round 1 refines the first ``first_round`` guesses of every problem (``stages.refine._chain_stream``)
and verifies them in cost order until one passes; round 2 refines the remaining guesses
only for the problems that round 1 left unsolved. A problem's best answer is the first
verified success in cost order, else the verified answer with the smallest violation.
Both rounds are one LM stream (``ChainBatchLM.solve``'s ``more``): a problem's round 2
starts as soon as its round 1 is verified (a few problems at a time), in the slots other
trajectories free.

A guess equal to an earlier guess of its problem is refined once: where the roadmap's path
is the direct start–goal edge, its guess is the straight line itself (measured on the
first 20 problems of each bundled scene: 16, 10 and 3 problems, whose second chains took
32 %, 18 % and 4 % of the LM trips on shelf, cabinet and random_27).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...model import z_to_q_numpy
from ...world._motion import MotionVerification
from ._chain_stream import ChainBatchLM

VERIFY_BATCH = 32
"""Problems whose round has finished, verified in one call (``verify`` of their motions
together): the verdict of shelf plans took 3.6 ms per problem one at a time, 3.0 two at a
time, 2.6 from four on (``world._motion.verify_trajectories``, 60 answers, 2-core Xeon);
in the planner, 32 instead of 8 (with ``world._motion_check._ROUND_ELEMENTS`` 1 << 19)
took 0.85× the host time of 300 shelf problems and 0.87× of 300 cabinet ones, the wall
time unchanged. The problems of a smaller batch wait for others to finish, unless no
chain runs."""


@dataclass
class Selection:
    """What ``select_guesses`` found for P problems."""

    best: list[tuple[MotionVerification, int, np.ndarray, float]]
    """Per problem: (verdict, guess index, q (waypoints, 3n) rad/m, LM cost ½‖r‖²)."""
    candidates: list[list[tuple[np.ndarray, int]]]
    """Per problem, every refined guess (q, guess index): verified successes first, then
    by smallest violation, then by cost; unverified guesses last."""
    verify_seconds: np.ndarray
    """(P,) seconds spent verifying each problem's guesses."""
    compile: float
    """Seconds spent compiling LM programs."""
    refine: float
    """Seconds spent in the LM, compilation excluded."""
    programs: int
    """LM device programs launched."""


def select_guesses(lm: ChainBatchLM, guesses: np.ndarray, ends: list[tuple[np.ndarray,
                                                                            np.ndarray]],
                   dt: float, arrays: Any, iterations: int, first_round: int,
                   verify: Callable[[list[np.ndarray]], list[MotionVerification]]
                   ) -> Selection:
    """Refine the (P, G, waypoints, 3n) ``guesses`` (bending vectors z) in two rounds and
    pick each problem's best by ``verify``.

    Both rounds run in one LM stream (``ChainBatchLM.solve`` with ``more``): a problem's
    round-1 guesses are verified once the last of them and those of ``VERIFY_BATCH`` − 1
    other problems have finished (or no chain runs), and if none passes, its round-2
    guesses join the stream at once, so round 2 does not wait for every round-1
    trajectory (nor round 1's slowest for round 2).

    Long: the stream's callbacks close over the rounds' shared per-problem state.

    Args:
        lm: the batched chain LM.
        guesses: initial trajectories in z (rad, rad, m).
        ends: per problem the (3n,) start and goal q (rad, rad, m), written over each
            refined trajectory's first and last waypoint.
        dt: seconds between waypoints.
        arrays: the scene arrays the LM's clearance terms use (or None).
        iterations: LM iterations per guess.
        first_round: guesses refined for every problem in round 1 (at least 1).
        verify: a list of q (waypoints, 3n) → their ``MotionVerification`` s
            (``success``, ``max_violation``), e.g. ``world._motion.verify_trajectories``.
    """
    p_count, g_count, n, dof = guesses.shape
    first = min(max(first_round, 1), g_count)
    rounds = [distinct_guesses(guesses[p], first) for p in range(p_count)]
    best: list[tuple[dict[str, Any], int, np.ndarray, float] | None] = [None] * p_count
    # Every refined guess: (not verified valid, max violation, cost, q, guess index).
    tried: list[list[tuple[bool, float, float, np.ndarray, int]]] = [[] for _ in range(p_count)]
    verify_seconds = np.zeros(p_count)
    # The stream's chains: chain k is guess owner[k][1] of problem owner[k][0].
    owner = [(p, g) for p in range(p_count) for g in rounds[p][0]]
    outstanding = np.array([len(r[0]) for r in rounds])  # chains of the current round
    second = np.zeros(p_count, dtype=bool)         # the problem is in round 2
    finished: list[dict[int, tuple[np.ndarray, float]]] = [{} for _ in range(p_count)]

    def judge(rows: list[int]) -> None:
        """Verify each problem's finished round in cost order until one passes: the
        problems' first-ranked guesses in one ``verify`` call, then the second-ranked of
        those still unsolved, and so on."""
        t2 = time.perf_counter()
        done = {row: finished[row] for row in rows}
        order = {row: sorted(done[row], key=lambda g, d=done[row]: (d[g][1], g)) for row in rows}
        for row in rows:
            finished[row] = {}
        verified: dict[int, set[int]] = {row: set() for row in rows}
        pending, rank = list(rows), 0
        while pending:
            batch = [(row, order[row][rank]) for row in pending if rank < len(order[row])]
            qs = []
            for row, g in batch:
                q = z_to_q_numpy(done[row][g][0].reshape(n, dof))
                q[0], q[-1] = ends[row]
                qs.append(q)
            pending = []
            for (row, g), q, verdict in zip(batch, qs, verify(qs) if qs else [], strict=True):
                verified[row].add(g)
                tried[row].append((not verdict.success, verdict.max_violation,
                                   done[row][g][1], q, g))
                b = best[row]
                if b is None or (verdict.success, -verdict.max_violation) > (
                        b[0].success, -b[0].max_violation):
                    best[row] = (verdict, g, q, done[row][g][1])
                if not verdict.success:
                    pending.append(row)
            rank += 1
        for row in rows:
            for g in sorted(done[row]):
                if g not in verified[row]:     # not verified: ranked after the verified
                    q = z_to_q_numpy(done[row][g][0].reshape(n, dof))
                    q[0], q[-1] = ends[row]
                    tried[row].append((True, math.inf, done[row][g][1], q, g))
        verify_seconds[rows] += (time.perf_counter() - t2) / len(rows)

    ready: list[int] = []           # problems whose round has finished, not yet verified
    running = [len(owner)]          # chains in the stream, not finished

    def more(chains: np.ndarray, z: np.ndarray,
             cost: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        added = []
        running[0] -= len(chains)
        for k, chain in enumerate(chains):
            row, g = owner[chain]
            finished[row][g] = (z[k], float(cost[k]))
            outstanding[row] -= 1
            if not outstanding[row]:
                ready.append(row)
        # Verified VERIFY_BATCH problems at a time, or whatever is ready once no chain runs
        # (the stream would end): one problem per call cost 1.4× the time per problem.
        if len(ready) < VERIFY_BATCH and (running[0] or not ready):
            return None
        complete = ready[:]
        ready.clear()
        judge(complete)
        for row in complete:
            b = best[row]
            later = rounds[row][1]
            if not second[row] and not (b is not None and b[0].success) and later:
                # Round 2 for this problem: its remaining guesses.
                owner.extend((row, h) for h in later)
                outstanding[row], second[row] = len(later), True
                running[0] += len(later)
                added.extend(guesses[row, later].reshape(len(later), n * dof))
        if not added:
            return None
        return np.stack(added), np.full(len(added), dt)

    programs = lm.programs
    z0 = np.stack([guesses[p, g] for p, g in owner]).reshape(-1, n * dof)
    t1 = time.perf_counter()
    solution = lm.solve(z0, np.full(len(z0), dt), arrays, iterations, more)
    refine = time.perf_counter() - t1 - solution.compile - solution.callback
    found = [b for b in best if b is not None]
    assert len(found) == p_count
    candidates = [[(q, g) for *_, q, g in sorted(t, key=lambda t: t[:3])] for t in tried]
    return Selection(found, candidates, verify_seconds, solution.compile, refine,
                     lm.programs - programs)


def distinct_guesses(guesses: np.ndarray, first: int,
                     tolerance: float = 1e-9) -> tuple[list[int], list[int]]:
    """The indices of one problem's (G, waypoints, 3n) guesses to refine in round 1 (among
    the first ``first``) and in round 2 (the rest), each guess that equals an earlier one
    (every entry within ``tolerance``, rad or m) left out: its chain would take the same
    iterates."""
    kept: list[int] = []
    for g in range(len(guesses)):
        if all(np.max(np.abs(guesses[g] - guesses[k])) > tolerance for k in kept):
            kept.append(g)
    return [g for g in kept if g < first], [g for g in kept if g >= first]
