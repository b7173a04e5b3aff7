"""The follower's branch search: tension sets for every waypoint of a path, carried along
several branches of the redundant tension sets at once, for robots where the
per-waypoint answers run into a dead end.

A robot with more tendons than its tip has coordinates reaches most tips with many
tension sets. Answers warm-started waypoint by waypoint (tensions and M(0) carried) follow
one branch of them, and the branch the first answer sets out on can end: on the fitted
FTDCR rod (3 segments of 3 tendons) in clutter, 7 of 12 paths that clear, slow motions
trace ran into an obstacle or a tip the branch could not reach, and the banded LM over
the whole motion, started from those answers, did not recover.

The search keeps up to ``width`` tension sets per waypoint. Each is the warm start (with
its M(0)) of ``tries`` LM runs to the next waypoint, itself and ``tries − 1`` copies moved
by Gaussian noise of ``spread`` N (clipped to the bounds), all in one batch; an answer
joins where it passes the waypoint's own check (tip, bounds, clearance of the scene and of
itself, on a statics solve started at the LM's own M(0): 3.5 ms for 8 sets against
9.5–12 ms from rest; the motion's verdict, from rest, judges what the search returns),
linked to its cheapest kept predecessor. The cost: the sum over steps of the
largest tendon change, N, plus ``EXCESS_WEIGHT`` times its excess over the rate limit's
step, so branches that keep the limit always come first and, where none does, the search
carries on with those that break it least (the chain's rate rows and Ipopt start from
there). The cheapest are kept, none within ``distinct`` N of another (distinct branches,
not copies of one). The first waypoint's sets are the LM's answers from the pool's
nearest clear seeds. Units: newtons, metres, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ...model.loads import StaticLoads
from ...stages.refine import world_frame
from .._timing import StageTiming

FIRST_SEEDS = 24
"""Pool seeds (nearest tips first) of each round of the first waypoint's LM runs (16 lost
every branch of an FTDCR path by waypoint 30)."""
FIRST_ROUNDS = 4
"""Rounds of further pool seeds for the first waypoint while fewer than ``width`` distinct
sets pass its check."""

LM_BATCH = 8
"""The smallest batch of the follower's LM programs (the IK's is 16): its blocks of 8
waypoints and the search's steps of 8 sets (``branch_width``); such a step 15–16 → 11 ms
on tdcr2 in clutter."""

EXCESS_WEIGHT = 100.0
"""Cost of a step's excess over the rate limit's step, per newton of steps: a branch that
keeps the limit is always cheaper, and where none does the search carries on with those
that break it least (a start for the chain's rate rows and for Ipopt)."""


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
    tendon where a kept branch allows (else by as little beyond it as the search found),
    each passing its waypoint's own check by ``ik`` (a ``TensionIKSolver`` whose LM takes
    short first steps from a warm start); the first waypoint's from pool seeds by
    ``seeding`` (one whose LM starts undamped, as from a pool seed); ``loads`` one load
    case. Returns (the cheapest motion, T), or (None, k) where no answer from a kept
    branch passes waypoint k's check."""
    rng = np.random.default_rng(settings.seed)
    tension_max = float(ik.robot.mechanics.tension_max)
    found, found_moments = [], []
    for first in range(0, FIRST_ROUNDS * FIRST_SEEDS, FIRST_SEEDS):
        answers, moments, passed = first_answers(seeding, positions, quats, loads,
                                                 range(first, first + FIRST_SEEDS))
        found.append(answers[passed])
        found_moments.append(moments[passed])
        every = np.concatenate(found)
        kept = _distinct(every, np.arange(len(every)), settings)
        if len(kept) == settings.width:
            break
    sets, moments, cost = every[kept], np.concatenate(found_moments)[kept], np.zeros(len(kept))
    if not len(sets):
        return None, 0
    history = [(sets, np.full(len(sets), -1))]
    for k in range(1, len(positions)):
        moved = [np.clip(sets + rng.normal(0.0, settings.spread, sets.shape), 0.0,
                         tension_max) for _ in range(settings.tries - 1)]
        answers, moments, passed = _solved(ik, np.concatenate([sets, *moved]),
                                           np.tile(moments, (settings.tries, 1)), positions,
                                           quats, loads, k)
        answers, moments = answers[passed], moments[passed]
        if not len(answers):
            return None, k
        step = np.abs(answers[:, None, :] - sets[None, :, :]).max(axis=2)  # (new, kept)
        total = cost[None, :] + step + EXCESS_WEIGHT * np.maximum(step - step_max, 0.0)
        parent, total = total.argmin(axis=1), total.min(axis=1)
        order = np.argsort(total, kind="stable")
        kept = _distinct(answers, order, settings)
        sets, moments, cost = answers[kept], moments[kept], total[kept]
        history.append((sets, parent[kept]))
    index = int(np.argmin(cost))
    motion = []
    for sets, parent in reversed(history):
        motion.append(sets[index])
        index = int(parent[index])
    return np.array(motion[::-1]), len(positions)


def first_answers(seeding: Any, positions: np.ndarray, quats: np.ndarray, loads: StaticLoads,
                  ranks: range) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The LM's answers (R, n) N to the first waypoint from the pool seeds of ``ranks``
    (nearest tips first, clear ones first) by ``seeding``, their M(0) (R, 3) N·m, base
    frame, and (R,) True where one passes the waypoint's own check."""
    starts = [seeding._start(positions[:1], loads, rank) for rank in ranks]
    return _solved(seeding, np.concatenate([t for t, _ in starts]),
                   np.concatenate([m for _, m in starts]), positions, quats, loads, 0)


def _solved(ik: Any, starts: np.ndarray, moments: np.ndarray | None, positions: np.ndarray,
            quats: np.ndarray, loads: StaticLoads, k: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The LM's answers (B, n) N to waypoint k from ``starts`` (B, n) N with M(0)
    ``moments`` (B, 3) N·m, base frame (None: from the tip moment), the answers' own M(0),
    and (B,) True where one passes the waypoint's own check (its statics started at the
    answer's M(0))."""
    count = len(starts)
    where = np.repeat(positions[k:k + 1], count, axis=0)
    turn = np.repeat(quats[k:k + 1], count, axis=0)
    case = loads.rows(np.zeros(count, int))
    answers, moments = ik._lm_carried(starts, where, turn, case, moments, smallest=LM_BATCH)
    statics = ik._forward(answers, case, world_frame(ik.robot, moments))
    return answers, moments, ik._judge(statics, answers, where, turn, case,
                                       StageTiming()).success


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
