"""Refine-and-verify selection of the trajectory LM's guesses, in two rounds.

Round 1 refines the first ``first_round`` guesses of every problem (``stages._chain_batch``)
and verifies them in cost order until one passes; round 2 refines the remaining guesses
only for the problems that round 1 left unsolved. A problem's best answer is the first
verified success in cost order, else the verified answer with the smallest violation.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..model import z_to_q_numpy
from ._chain_batch import ChainBatchLM


@dataclass
class Selection:
    """What ``select_guesses`` found for P problems."""

    best: list[tuple[dict[str, Any], int, np.ndarray, float]]
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
                   verify: Callable[[np.ndarray], dict[str, Any]]) -> Selection:
    """Refine the (P, G, waypoints, 3n) ``guesses`` (bending vectors z) in two rounds and
    pick each problem's best by ``verify``.

    Args:
        lm: the batched chain LM.
        guesses: initial trajectories in z (rad, rad, m).
        ends: per problem the (3n,) start and goal q (rad, rad, m), written over each
            refined trajectory's first and last waypoint.
        dt: seconds between waypoints.
        arrays: the scene arrays the LM's clearance terms use (or None).
        iterations: LM iterations per guess.
        first_round: guesses refined for every problem in round 1 (at least 1).
        verify: q (waypoints, 3n) → a verdict dict with ``success`` and ``max_violation``.
    """
    p_count, g_count, n, dof = guesses.shape
    first = min(max(first_round, 1), g_count)
    best: list[tuple[dict[str, Any], int, np.ndarray, float] | None] = [None] * p_count
    # Every refined guess: (not verified valid, max violation, cost, q, guess index).
    tried: list[list[tuple[bool, float, float, np.ndarray, int]]] = [[] for _ in range(p_count)]
    verify_seconds = np.zeros(p_count)
    compile_total = refine_total = 0.0
    programs = lm.programs
    for rows, group in ((np.arange(p_count), np.arange(first)),
                        (None, np.arange(first, g_count))):
        if rows is None:
            rows = np.array([r for r, b in enumerate(best)
                             if b is None or not b[0]["success"]], dtype=int)
        if len(rows) == 0 or len(group) == 0:
            continue
        z0 = guesses[rows][:, group].reshape(-1, n * dof)
        t1 = time.perf_counter()
        z, cost, compiled = lm.solve(z0, np.full(len(z0), dt), arrays, iterations)
        compile_total += compiled
        refine_total += time.perf_counter() - t1 - compiled
        z = z.reshape(len(rows), len(group), n, dof)
        cost = cost.reshape(len(rows), len(group))
        for k, row in enumerate(rows):
            q_start, q_goal = ends[row]
            t2 = time.perf_counter()
            # Best by the independent verdict, then by cost: the first success in cost order.
            verified = set()
            for g in np.argsort(cost[k], kind="stable"):
                q = z_to_q_numpy(z[k, g])
                q[0], q[-1] = q_start, q_goal
                verdict = verify(q)
                verified.add(int(g))
                tried[row].append((not verdict["success"], verdict["max_violation"],
                                   float(cost[k, g]), q, int(group[g])))
                b = best[row]
                if b is None or (verdict["success"], -verdict["max_violation"]) > (
                        b[0]["success"], -b[0]["max_violation"]):
                    best[row] = (verdict, int(group[g]), q, float(cost[k, g]))
                if verdict["success"]:
                    break
            for g in range(len(group)):
                if g not in verified:      # not verified: ranked after the verified
                    q = z_to_q_numpy(z[k, g])
                    q[0], q[-1] = q_start, q_goal
                    tried[row].append((True, math.inf, float(cost[k, g]), q, int(group[g])))
            verify_seconds[row] += time.perf_counter() - t2
    found = [b for b in best if b is not None]
    assert len(found) == p_count
    candidates = [[(q, g) for *_, q, g in sorted(t, key=lambda t: t[:3])] for t in tried]
    return Selection(found, candidates, verify_seconds, compile_total, refine_total,
                     lm.programs - programs)
