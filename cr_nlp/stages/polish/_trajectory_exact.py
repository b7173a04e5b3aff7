"""The trajectory exact stage: each problem's LM candidates, best first, polished by Ipopt
(``stages.polish._trajectory_nlp``) and accepted by the verdict (``stages.polish._accept``).

Attempt k polishes the k-th candidate of every problem not yet accepted, in this process
or spread over a ``stages.polish._process_pool.PolishPool``; a polish that Ipopt reports as failed
is not
judged. Trajectories are (waypoints, 3n) configurations θ, φ, L (rad, rad, m). A time
limit covers each problem's polishes together (``stages.polish._accept``): each polish gets what
its problem has left.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ...model.robot import Robot
from ...world.scene import Scene
from ...world.verdict import describe_violations
from ._accept import Acceptance, Judged, Polished, polish_and_accept


def trajectory_polisher(robot: Robot, scene: Scene | None, waypoints: int, margin: float,
                        samples: int) -> Any:
    """A path-length ``TrajectoryPolisher`` with clearance rows at every waypoint and at
    the ``samples`` − 1 points inside every interval that the verification checks (δ =
    ``margin`` m on the sphere body); module level, so pool workers can build it."""
    from ._trajectory_nlp import TrajectoryPolishConfig, TrajectoryPolisher

    return TrajectoryPolisher(robot, scene, waypoints, safety_margin=margin,
                              config=TrajectoryPolishConfig(interpolation_checks=samples - 1,
                                                            verify_samples=samples))


def describe_polish(out: Any) -> str:
    """Why a trajectory polish failed: Ipopt's status (or that the time limit stopped it)
    and the violations it left."""
    broken = describe_violations(out.violations)
    head = (f"Ipopt stopped at the time limit ({out.iterations} iterations, "
            f"{out.seconds:.3g} s)" if _out_of_time(out) else f"Ipopt {out.status}")
    return head + (f", {broken}" if broken else "")


def polish_one(polisher: Any, q0: np.ndarray, dt: float,
               time_limit: float | None = None) -> tuple[np.ndarray | None, str, float, bool]:
    """One Ipopt polish of the trajectory ``q0`` (``dt`` s between waypoints) in at most
    ``time_limit`` seconds (None: no limit): its answer, or None with why Ipopt failed,
    the seconds it took, and whether the time limit stopped it."""
    t0 = time.perf_counter()
    out = polisher.solve(q0, dt, time_limit=time_limit)
    if not out.success:
        return None, describe_polish(out), time.perf_counter() - t0, _out_of_time(out)
    return out.q, "", time.perf_counter() - t0, _out_of_time(out)


def _out_of_time(out: Any) -> bool:
    """A polish result's ``out_of_time``; a result without one (a stand-in polisher's)
    did not run out of time."""
    return bool(getattr(out, "out_of_time", False))


def polish_trajectories(options: Sequence[Sequence[tuple[np.ndarray, str]]],
                        fallback: Sequence[Any], dt: float,
                        judge: Callable[[np.ndarray, int], Judged],
                        polisher: Callable[[], Any], pool: Callable[[], Any] | None = None,
                        bar: Any = None,
                        time_limit: float | None = None) -> tuple[Acceptance, np.ndarray]:
    """Polish P problems' candidates in order and keep, per problem, the first polish the
    verdict accepts, else its penalty answer.

    Args:
        options: per problem, its candidates (q (waypoints, 3n), what produced it), best
            first; as many attempts as the longest list.
        fallback: per problem, the penalty result (its ``q``, ``success`` and ``reason``
            stand when no polish is accepted).
        dt: seconds between waypoints.
        judge: ``(q, problem index) → verdict`` (``success``, ``reason``).
        polisher: returns this process's polisher (built on first use).
        pool: returns a ``PolishPool`` of ``trajectory_polisher`` workers, or None:
            polish in this process.
        bar: a tqdm bar advanced per problem of the first attempt, or None.
        time_limit: seconds of polishing per problem, all its candidates together (None:
            no limit).

    Returns:
        The ``Acceptance`` (an outcome per problem; its k-th failure note is that of
        candidate k) and the seconds spent per problem (P,), polishing and judging.
    """
    seconds = np.zeros(len(options))

    def candidate(attempt: int, rows: np.ndarray) -> list[np.ndarray | None]:
        return [options[r][attempt][0] if attempt < len(options[r]) else None for r in rows]

    def polish(starts: list[np.ndarray], rows: np.ndarray, attempt: int,
               budgets: np.ndarray) -> list[Polished[np.ndarray]]:
        items = [(q0, dt, None if time_limit is None else float(budget))
                 for q0, budget in zip(starts, budgets, strict=True)]
        progress = bar if attempt == 0 else None
        if pool is not None and len(items) > 1:
            outs = pool().map(polish_one, items, progress)
        else:
            outs = []
            for item in items:
                outs.append(polish_one(polisher(), *item))
                if progress is not None:
                    progress.update(1)
        seconds[rows] += [elapsed for _, _, elapsed, _ in outs]
        return [Polished(q, why, elapsed, late) for q, why, elapsed, late in outs]

    def judged(answers: list[np.ndarray], rows: np.ndarray) -> list[Judged]:
        out = []
        for q, r in zip(answers, rows, strict=True):
            t0 = time.perf_counter()
            out.append(judge(q, int(r)))
            seconds[r] += time.perf_counter() - t0
        return out

    attempts = max((len(o) for o in options), default=1)
    acceptance = polish_and_accept([r.q for r in fallback], list(fallback), candidate,
                                   polish, judged, max(attempts, 1), time_limit)
    return acceptance, seconds
