"""The float64 verdict on a motion through waypoints, independent of any optimiser.

Between waypoints the robot moves linearly in the bending vector z (hence linearly in the
tendon lengths: the motion of a controller that interpolates the tendon-length series).
``verify_trajectory`` judges that whole motion: python-fcl along the densely interpolated
configurations (``world.check``), limits, tendon speed and acceleration by finite
differences, all through the one success rule of ``world.verdict``. Trajectory planning
and path following both answer to it. Units: rad, m, s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..model import Robot, q_to_z_numpy, z_to_q_numpy
from ..model._ops import NUMPY
from ..model.kinematics import model_segment_frames, model_tendon_lengths
from ..model.limits import limit_violation_q
from ._motion_check import MotionCheck, check_motions
from .check import check_many
from .scene import Scene
from .verdict import VIOLATION_TOLERANCE, Verdict, judge


@dataclass(frozen=True)
class MotionVerification:
    """``verify_trajectory``'s report on a motion: the verdict and what it measured.
    Units: rad, m, s."""

    verdict: Verdict
    """The verdict (``world.verdict.judge``) on the whole motion."""
    min_clearance: float
    """The smaller of the python-fcl obstacle distance and the self-clearance along the
    motion, m; +inf with neither."""
    self_clearance: float
    """Smallest distance between segments at least two apart, m; +inf when not checked."""
    collision_free: bool
    """No python-fcl collision along the dense motion."""
    path_length: float
    """The tip path along the dense motion, m."""
    tendon_lengths: np.ndarray
    """(H+1, n_tendons) tendon lengths at the waypoints, m."""
    tendon_speed: float
    """Largest |tendon speed| by finite differences, m/s."""
    tendon_accel: float
    """Largest |tendon acceleration| by finite differences, m/s²."""
    first_collision: int
    """Index into the dense motion of its first collision, −1 if none."""

    @property
    def success(self) -> bool:
        """The verdict accepts the motion."""
        return self.verdict.success

    @property
    def reason(self) -> str:
        """"" on success, else each failed check and by how much."""
        return self.verdict.reason

    @property
    def violations(self) -> dict[str, float]:
        """Largest violation per family: ``clearance`` and ``self_clearance`` m below δ,
        ``limits`` rad or m, ``tendon_speed`` m/s, ``tendon_accel`` m/s²."""
        return dict(self.verdict.violations)

    @property
    def max_violation(self) -> float:
        """The largest of ``violations``."""
        return self.verdict.max_violation


def interpolate_trajectory(q: np.ndarray, samples: int) -> np.ndarray:
    """The motion between waypoints, linear in the bending vector z (hence linear in the
    tendon lengths): (H·samples + 1, 3n) configurations (rad, rad, m), each interval split
    into ``samples`` pieces, waypoints included."""
    return z_to_q_numpy(_interpolate_z(q_to_z_numpy(q), np.array([len(q)]), samples))


def tip_positions(robot: Robot, q: np.ndarray) -> np.ndarray:
    """(B, 3) tip positions (m) of (B, 3n) configurations, float64 numpy."""
    z = q_to_z_numpy(q)
    _, pos = model_segment_frames(NUMPY, robot, [z[:, i] for i in range(robot.dof)])[-1]
    return np.stack(np.broadcast_arrays(*pos), axis=-1).reshape(-1, 3)


def tendon_series(robot: Robot, q: np.ndarray) -> np.ndarray:
    """(B, n_tendons) tendon lengths (m) of (B, 3n) configurations, float64 numpy."""
    z = q_to_z_numpy(q)
    values = model_tendon_lengths(NUMPY, robot, [z[:, i] for i in range(robot.dof)])
    return np.stack(np.broadcast_arrays(*values), axis=-1).reshape(len(z), -1)


def verify_trajectory(robot: Robot, scene: Scene | None, q: Any, dt: float,
                      margin: float = 0.002, samples: int = 4,
                      tolerance: float = VIOLATION_TOLERANCE) -> MotionVerification:
    """Float64 verdict on a trajectory, independent of any optimiser (``world.verdict``).

    Args:
        robot: the robot.
        scene: obstacles, or None.
        q: (H+1, 3n) waypoints θ, φ, L (rad, rad, m).
        dt: seconds between waypoints.
        margin: δ, metres; a python-fcl distance below it counts as a clearance violation.
        samples: each interval is split into this many pieces (linear in z) and python-fcl
            checks every piece's end, so the whole motion, not only the waypoints, is judged.
        tolerance: the largest violation of any family a success may have.

    Returns a ``MotionVerification``: the ``verdict`` (``world.verdict.judge``: every
    violation ≤ ``tolerance``: clearance to obstacles and between segments at least two
    apart ≥ δ − tolerance along the whole motion, limits and tendon limits; its
    ``success``, ``reason``, ``violations`` per family and ``max_violation``) and the
    measured clearances, path length, tendon lengths, speed and acceleration.
    """
    return verify_trajectories(robot, scene, [q], dt, margin, samples, tolerance)[0]


def verify_trajectories(robot: Robot, scene: Scene | None, qs: Sequence[Any], dt: float,
                        margin: float = 0.002, samples: int = 4,
                        tolerance: float = VIOLATION_TOLERANCE) -> list[MotionVerification]:
    """``verify_trajectory`` of several trajectories at once (e.g. a planner's candidates
    of many problems): the same report for each, ``qs`` a sequence of (H_m+1, 3n)
    waypoints (rad, rad, m; H_m ≥ 1, lengths may differ), ``dt`` s, ``margin`` m. The
    interpolation, kinematics, tendon lengths, limits and the collision search
    (``world._motion_check.check_motions``) run once over every motion's configurations,
    not once per motion.

    Long: one pass over the motions' concatenated waypoints, then a report per motion.
    """
    qs = [np.asarray(q, dtype=np.float64) for q in qs]
    for q in qs:
        if q.ndim != 2 or q.shape[1] != robot.dof or len(q) < 2:
            raise ValueError(f"q must be (H+1, {robot.dof}) with H ≥ 1, got {q.shape}")
    if not qs:
        return []
    waypoints = np.concatenate(qs)
    sizes = np.array([len(q) for q in qs])
    ends = np.cumsum(sizes)                           # each motion's rows end here
    dense = z_to_q_numpy(_interpolate_z(q_to_z_numpy(waypoints), ends, samples))
    dense_ends = np.cumsum((sizes - 1) * samples + 1)
    # The body chain's last point is the tip: one forward kinematics pass, not two.
    chains = own = pieces = None
    if scene is not None or robot.has_self_pairs:
        from ._verdict_program import motion_chains

        chains, own, pieces = motion_chains(robot, dense)
    tips = chains[:, -1] if chains is not None else tip_positions(robot, dense)
    lengths = tendon_series(robot, waypoints)
    limits = limit_violation_q(robot, waypoints)
    dense_spans = list(zip(np.r_[0, dense_ends[:-1]].tolist(), dense_ends.tolist(), strict=True))
    motions = (check_motions(robot, scene, [chains[a:b] for a, b in dense_spans], own, pieces)
               if chains is not None else [None] * len(qs))
    out = []
    for m, (start, stop) in enumerate(zip(np.r_[0, ends[:-1]].tolist(), ends.tolist(),
                                          strict=True)):
        a, b = dense_spans[m]
        out.append(_report(robot, margin, tolerance, samples, dt, lengths[start:stop],
                           float(np.max(limits[start:stop])),
                           float(np.sum(np.linalg.norm(np.diff(tips[a:b], axis=0), axis=1))),
                           motions[m]))
    return out


def _interpolate_z(z: np.ndarray, ends: np.ndarray, samples: int) -> np.ndarray:
    """``interpolate_trajectory``'s motion in z for the motions whose waypoints z
    (rows ending at ``ends``) are concatenated: each motion's dense rows in turn."""
    s = np.arange(samples)[:, None] / samples
    first = np.delete(np.arange(len(z)), ends - 1)    # every interval's first waypoint
    inner = (z[first, None, :] + s[None, :, :] * (z[first + 1] - z[first])[:, None, :]
             ).reshape(-1, z.shape[1])
    intervals = np.cumsum(ends - np.r_[0, ends[:-1]] - 1)
    return np.insert(inner, intervals * samples, z[ends - 1], axis=0)


def _report(robot: Robot, margin: float, tolerance: float, samples: int, dt: float,
            lengths: np.ndarray, limits: float, path_length: float,
            motion: MotionCheck | None) -> MotionVerification:
    """One motion's ``MotionVerification`` from what ``verify_trajectories`` measured:
    its waypoints' tendon lengths (H+1, n_tendons; m), largest limit violation, tip path
    (m) and collision verdict (None: nothing to collide with)."""
    speed = np.diff(lengths, axis=0) / dt
    accel = (np.diff(lengths, 2, axis=0) / (dt * dt) if len(lengths) > 2
             else np.zeros((0, lengths.shape[1])))
    speed_max = float(np.max(np.abs(speed))) if speed.size else 0.0
    accel_max = float(np.max(np.abs(accel))) if accel.size else 0.0
    min_clearance, self_clearance, first_collision = math.inf, math.inf, -1
    if motion is not None:
        min_clearance = motion.obstacle_distance
        self_clearance = motion.self_distance
        hits = np.flatnonzero(motion.collision)
        first_collision = int(hits[0]) if len(hits) else -1
    where = ""
    if first_collision >= 0:
        at = first_collision / samples
        where = f"at t = {at * dt:.3f} s (interval {int(at)})"
    verdict = judge(margin=margin, limits=limits,
                    min_clearance=min_clearance, self_clearance=self_clearance,
                    tendon_speed=speed_max - robot.tendon_speed_max,
                    tendon_accel=accel_max - robot.tendon_accel_max,
                    collision_where=where, tolerance=tolerance)
    return MotionVerification(
        verdict=verdict, min_clearance=min(min_clearance, self_clearance),
        self_clearance=self_clearance, collision_free=first_collision < 0,
        path_length=path_length, tendon_lengths=lengths, tendon_speed=speed_max,
        tendon_accel=accel_max, first_collision=first_collision)


def check_ends(robot: Robot, scene: Scene | None, starts: Any,
               goals: Any) -> list[tuple[np.ndarray | None, np.ndarray | None, str]]:
    """Per (start, goal) pair the full (3n,) start and goal q (rad, rad, m, through
    ``Robot.full_q``), or (None, None, reason) when the pair cannot be planned: a row of
    the wrong form, or an end in collision by python-fcl (one ``check_many`` on all
    ends). ``starts``, ``goals``: sequences of rows, short or full form."""
    out: list[tuple[np.ndarray | None, np.ndarray | None, str]] = []
    for start, goal in zip(starts, goals, strict=True):
        try:
            q_start = robot.full_q(start)
        except (ValueError, TypeError) as exc:
            out.append((None, None, f"bad start: {exc}"))
            continue
        try:
            out.append((q_start, robot.full_q(goal), ""))
        except (ValueError, TypeError) as exc:
            out.append((None, None, f"bad goal: {exc}"))
    rows = [i for i, (_, _, reason) in enumerate(out) if not reason]
    if rows and (scene is not None or robot.has_self_pairs):
        verdict = check_many(robot, scene, np.stack([q for i in rows for q in out[i][:2]]))
        hits = verdict.collision.reshape(-1, 2)
        distances = verdict.min_distance.reshape(-1, 2)
        for i, hit, d in zip(rows, hits, distances, strict=True):
            for name, h, di in zip(("start", "goal"), hit, d, strict=True):
                if h:
                    out[i] = (None, None, f"{name} is in collision by python-fcl "
                                          f"(distance {di:.4g} m)")
                    break
    return out
