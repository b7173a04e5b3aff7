"""The follower's branch search: tension sets for every waypoint of a path, carried along
several branches of the redundant tension sets at once, for robots where the
per-waypoint answers run into a dead end.

A robot with more tendons than its tip has coordinates reaches most tips with many
tension sets. Answers warm-started waypoint by waypoint follow one branch of them; on the
fitted FTDCR rod (3 segments of 3 tendons) that branch reached the 20 N bound halfway
along a path that a clear, slow motion traces, and the path was then reached only by
jumping between branches (400 N/s, in collision between waypoints), and the banded LM over
the whole motion, started from those answers, did not recover (13.8 mm inside an
obstacle; from the traced motion plus 1 N of noise it converged).

The search keeps up to ``width`` tension sets per waypoint. Each is the warm start of
``tries`` LM runs to the next waypoint, itself and ``tries − 1`` copies moved by Gaussian
noise of ``spread`` N (clipped to the bounds), all in one batch; an answer joins where it
passes the waypoint's own check (tip, bounds, clearance of the scene) and is within the
rate limit of a kept predecessor, linked to its cheapest one (the cost: the sum over
steps of the largest tendon change, N). The cheapest are kept, none within ``distinct`` N
of another (distinct branches, not copies of one). The first waypoint's sets are the LM's
answers from the pool's nearest seeds. Units: newtons, metres, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ...model.loads import StaticLoads
from .._timing import StageTiming

FIRST_SEEDS = 24
"""Pool seeds (nearest tips first) of each round of the first waypoint's LM runs (16 lost
every branch of an FTDCR path by waypoint 30)."""
FIRST_ROUNDS = 4
"""Rounds of further pool seeds for the first waypoint while fewer than ``width`` distinct
sets pass its check."""


@dataclass(frozen=True)
class BranchSearch:
    """Settings of the branch search (``TensionFollowConfig``'s ``branch_*``)."""

    width: int
    tries: int
    spread: float
    distinct: float
    seed: int = 0


def branch_search(ik: Any, seeding: Any, positions: np.ndarray, quats: np.ndarray,
                  loads: StaticLoads, step_max: float, settings: BranchSearch
                  ) -> tuple[np.ndarray | None, int]:
    """Tension sets (T, n) N for the waypoints ``positions`` (T, 3) m (``quats`` (T, 4),
    NaN rows: position only) whose consecutive sets differ by at most ``step_max`` N per
    tendon, each passing its waypoint's own check by ``ik`` (a ``TensionIKSolver`` whose LM
    takes short first steps from a warm start); the first waypoint's from pool seeds by
    ``seeding`` (one whose LM starts undamped, as from a pool seed); ``loads`` one load
    case. Returns (the cheapest motion, T), or (None, k) where no kept branch carries on
    to waypoint k."""
    rng = np.random.default_rng(settings.seed)
    tension_max = float(ik.robot.mechanics.tension_max)
    found = []
    for first in range(0, FIRST_ROUNDS * FIRST_SEEDS, FIRST_SEEDS):
        seeds = np.concatenate([seeding._seeds(positions[:1], loads, rank)
                                for rank in range(first, first + FIRST_SEEDS)])
        answers, passed = _solved(seeding, seeds, positions, quats, loads, 0)
        found.append(answers[passed])
        every = np.concatenate(found)
        kept = _distinct(every, np.arange(len(every)), settings)
        if len(kept) == settings.width:
            break
    sets, cost = every[kept], np.zeros(len(kept))
    if not len(sets):
        return None, 0
    history = [(sets, np.full(len(sets), -1))]
    for k in range(1, len(positions)):
        moved = [np.clip(sets + rng.normal(0.0, settings.spread, sets.shape), 0.0,
                         tension_max) for _ in range(settings.tries - 1)]
        answers, passed = _solved(ik, np.concatenate([sets, *moved]), positions, quats,
                                  loads, k)
        answers = answers[passed]
        step = np.abs(answers[:, None, :] - sets[None, :, :]).max(axis=2)  # (new, kept)
        total = np.where(step <= step_max, cost[None, :] + step, np.inf)
        parent, total = total.argmin(axis=1), total.min(axis=1)
        order = np.flatnonzero(np.isfinite(total))
        if not len(order):
            return None, k
        order = order[np.argsort(total[order], kind="stable")]
        kept = _distinct(answers, order, settings)
        sets, cost = answers[kept], total[kept]
        history.append((sets, parent[kept]))
    index = int(np.argmin(cost))
    motion = []
    for sets, parent in reversed(history):
        motion.append(sets[index])
        index = int(parent[index])
    return np.array(motion[::-1]), len(positions)


def _solved(ik: Any, starts: np.ndarray, positions: np.ndarray, quats: np.ndarray,
            loads: StaticLoads, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The LM's answers (B, n) N to waypoint k from ``starts`` (B, n) N, and (B,) True where
    one passes the waypoint's own check."""
    count = len(starts)
    where = np.repeat(positions[k:k + 1], count, axis=0)
    turn = np.repeat(quats[k:k + 1], count, axis=0)
    case = loads.rows(np.zeros(count, int))
    answers = ik._lm(starts, where, turn, case)
    return answers, ik._verdict(answers, where, turn, case, StageTiming()).success


def _distinct(sets: np.ndarray, order: np.ndarray, settings: BranchSearch) -> np.ndarray:
    """Rows of ``sets`` in ``order``, skipping any within ``distinct`` N (every tendon) of
    one taken, ``width`` at most."""
    taken: list[int] = []
    for i in order.tolist():
        if all(np.abs(sets[i] - sets[j]).max() > settings.distinct for j in taken):
            taken.append(i)
            if len(taken) == settings.width:
                break
    return np.array(taken, dtype=int)
