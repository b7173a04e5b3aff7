"""The two-round guess selection of the trajectory planner (``stages.refine._trajectory_select``):
each distinct guess is refined once, round 2 only where round 1 found no valid answer."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from cr_nlp.stages.refine._chain_stream import ChainSolution
from cr_nlp.stages.refine._trajectory_select import distinct_guesses, select_guesses


class RecordingLM:
    """A stand-in for ``ChainBatchLM``: every chain's answer is its start and its cost the
    start's first entry; records the chains it was given, streamed as the real one."""

    def __init__(self) -> None:
        self.programs = 0
        self.chains: list[np.ndarray] = []

    def solve(self, z0, step, arrays, iterations, more=None) -> ChainSolution:
        waiting, done = list(z0), []
        while waiting:
            batch, waiting = waiting, []
            self.programs += 1
            start = len(done)
            done += batch
            self.chains += batch
            z = np.array(batch)
            added = more(start + np.arange(len(batch)), z, z[:, 0].copy()) if more else None
            if added is not None:
                waiting = list(added[0])
        z = np.array(done)
        return ChainSolution(z, z[:, 0].copy(), np.zeros(len(z), int), 0.0, 0.0)


def _guesses(problems: int, count: int, waypoints: int = 3, dof: int = 2) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform(1.0, 2.0, size=(problems, count, waypoints, dof))


def test_distinct_guesses_leaves_out_repeats_within_and_across_rounds():
    g = _guesses(1, 4)[0]
    g[1] = g[0]                  # the roadmap's direct edge: the straight line again
    g[3] = g[0] + 1e-12          # equal within the tolerance
    assert distinct_guesses(g, 2) == ([0], [2])
    g[1] += 1e-6
    assert distinct_guesses(g, 2) == ([0, 1], [2])


def test_a_repeated_guess_is_refined_once_and_round_two_runs_only_where_needed():
    guesses = _guesses(3, 4)
    guesses[0, 1] = guesses[0, 0]            # problem 0: roadmap guess = straight line
    ends = [(g[0, 0], g[0, -1]) for g in guesses]
    # Problem 2 (known by its start, written over each answer's first waypoint) fails
    # every verdict; the others pass with their first verified guess.

    def verify(qs: list[np.ndarray]) -> list[SimpleNamespace]:   # the two fields read
        ok = [not np.array_equal(q[0], ends[2][0]) for q in qs]
        return [SimpleNamespace(success=o, max_violation=0.0 if o else 1.0) for o in ok]

    lm = RecordingLM()
    sel = select_guesses(lm, guesses, ends, 0.35, None, 10, 2, verify)
    solved = [c.reshape(guesses.shape[2:]) for c in lm.chains]
    # Round 1: one chain for problem 0, two for 1 and 2; round 2: problem 2's two others.
    assert len(solved) == 1 + 2 + 2 + 2
    for expected in (guesses[0, 0], guesses[1, 0], guesses[1, 1], guesses[2, 2]):
        assert sum(np.array_equal(c, expected) for c in solved) == 1
    assert not any(np.array_equal(c, guesses[0, 2]) for c in solved)
    assert [b[0].success for b in sel.best] == [True, True, False]
    assert [len(c) for c in sel.candidates] == [1, 2, 4]


class OneAtATimeLM(RecordingLM):
    """``RecordingLM`` finishing one chain per call, as a stream's slots often do."""

    def solve(self, z0, step, arrays, iterations, more=None) -> ChainSolution:
        waiting, done = list(z0), []
        while waiting:
            chain = waiting.pop(0)
            self.programs += 1
            done.append(chain)
            self.chains.append(chain)
            z = np.array([chain])
            added = more(np.array([len(done) - 1]), z, z[:, 0].copy()) if more else None
            if added is not None:
                waiting += list(added[0])
        z = np.array(done)
        return ChainSolution(z, z[:, 0].copy(), np.zeros(len(z), int), 0.0, 0.0)


def test_problems_are_verified_a_batch_at_a_time_and_every_one_is_judged():
    """2·VERIFY_BATCH + 4 problems finishing one by one: verified ``VERIFY_BATCH`` at a
    time (the last few once no chain runs), not one call each; a failing problem still
    gets its round 2."""
    from cr_nlp.stages.refine._trajectory_select import VERIFY_BATCH

    count = 2 * VERIFY_BATCH + 4
    guesses = _guesses(count, 3)
    ends = [(g[0, 0], g[0, -1]) for g in guesses]
    calls = []

    def verify(qs: list[np.ndarray]) -> list[SimpleNamespace]:
        calls.append(len(qs))
        ok = [not np.array_equal(q[0], ends[5][0]) for q in qs]     # problem 5 fails
        return [SimpleNamespace(success=o, max_violation=0.0 if o else 1.0) for o in ok]

    lm = OneAtATimeLM()
    sel = select_guesses(lm, guesses, ends, 0.35, None, 10, 1, verify)
    assert [b[0].success for b in sel.best] == [p != 5 for p in range(count)]
    assert len(sel.candidates[5]) == 3                  # round 2: its two other guesses
    assert len(lm.chains) == count + 2
    assert sum(calls) == count + 2                       # each refined guess verified once
    assert len(calls) <= -(-count // VERIFY_BATCH) + 2   # not one call per problem
    assert max(calls) == VERIFY_BATCH
