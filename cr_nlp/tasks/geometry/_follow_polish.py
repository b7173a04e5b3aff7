"""The path follower's exact stage: when to polish the LM answer with Ipopt and which
answer to keep (the polish itself is ``stages.polish._trajectory_nlp``)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ...model import Robot
from ...model.limits import clip_to_limits
from ...model.rotations import matrix_from_wxyz
from ...stages.polish import Polished, accept_first, describe_polish, polish_note
from ...world.verdict import VIOLATION_TOLERANCE, Verdict
from .._result import Stage
from .._timing import StageTiming
from ..paths import ReferencePath
from ._follow_result import FollowResult, PathVerification, tracking_cost


def polish_follow(robot: Robot, polisher: Callable[[int], Any], lm: FollowResult,
                  path: ReferencePath, trackable: np.ndarray,
                  verify: Callable[[np.ndarray], PathVerification],
                  make_result: Callable[[np.ndarray, PathVerification], FollowResult],
                  timing: StageTiming, progress: bool,
                  time_limit: float | None = None) -> FollowResult:
    """Stage 3: Ipopt from the LM answer ``lm``; keep the polish only if the independent
    verdict agrees (collision-free, every violation ≤ 1e-6) and, where the LM answer is
    feasible too, only if it tracks the path better. Otherwise ``lm`` is returned with its
    ``notes`` saying why.

    Args:
        robot: the robot.
        polisher: waypoint count → a ``TrajectoryPolisher`` (objective "tracking").
        lm: the stage-2 result.
        path: the reference (positions m, wxyz, ``dt`` s).
        trackable: (T,) bool, the waypoints within reach.
        verify: q (T, 3n) → the follower's report (``PathFollower.verify``).
        make_result: (q, verdict) → the polished ``FollowResult``.
        timing: its ``polish`` and ``verify`` seconds are increased.
        progress: print a line to stderr before the polish.
        time_limit: seconds the polish may take (None: no limit); out of time, ``lm``
            stays with the note "polish out of time: …".
    """
    try:
        from ...stages.polish import polish_one  # noqa: F401 — only whether it is available
    except ImportError:
        lm.stage, lm.notes = Stage.REFINE, [
            "polish failed: the Ipopt trajectory stage (stages.polish.polish_one) is not "
            "available"]
        return lm
    if lm.max_violation <= VIOLATION_TOLERANCE and lm.collision_free and \
            bool(np.all(lm.reached)):
        # Every constraint already holds (verified independently) and every waypoint is
        # tracked: Ipopt has nothing to enforce. Measured on the bundled shapes, its
        # interior-point iterates left such an answer for another branch (square: mean
        # error 0.0 → 4.3 mm) at 50–150 s per path, so the answer is kept as it is.
        lm.stage, lm.notes = Stage.REFINE, ["feasible: polish not needed"]
        return lm
    t = len(lm.q)
    solver = polisher(t)
    if progress:
        print(f"polish (Ipopt): {t} waypoints …", file=sys.stderr)
    # Untrackable waypoints keep the LM's reference: its own tip pose (zero error).
    positions = np.where(trackable[:, None], path.positions, lm.position)
    rotations = matrix_from_wxyz(np.where(trackable[:, None], path.wxyz, lm.wxyz))
    reports: list[PathVerification] = []

    def polish(q0: np.ndarray) -> Polished[np.ndarray]:
        t0 = time.perf_counter()
        try:
            out = solver.solve(q0, path.dt, positions, rotations, time_limit=time_limit)
        except Exception as exc:  # noqa: BLE001 — a crashed polish must not lose the answer
            return Polished(None, f"{type(exc).__name__}: {exc}")
        finally:
            timing.polish += time.perf_counter() - t0
        if not out.success:
            return Polished(None, describe_polish(out), out.seconds, out.out_of_time)
        return Polished(clip_to_limits(robot, np.asarray(out.q, dtype=np.float64)),
                        seconds=out.seconds, out_of_time=out.out_of_time)

    def judge(q: np.ndarray) -> Verdict:
        t1 = time.perf_counter()
        reports.append(verify(q))
        timing.verify += time.perf_counter() - t1
        return reports[-1].motion.verdict

    outcome = accept_first([lm.q], lm.q, lm, polish, judge)
    if not outcome.accepted:
        lm.stage, lm.notes = Stage.REFINE, [polish_note(outcome)]
        return lm
    polished = make_result(outcome.answer, reports[-1])
    if lm.max_violation <= VIOLATION_TOLERANCE and lm.collision_free and \
            tracking_cost(polished) > tracking_cost(lm):
        # Both feasible: keep the one that tracks the path better.
        lm.stage, lm.notes = Stage.REFINE, ["feasible; the polished answer tracked worse"]
        return lm
    return polished
