"""The trajectory-planning baseline: RRT-Connect in configuration space.

Two trees, one from the start and one from the goal, grow towards random configurations
in the bending-vector form z (the roadmap's metric, ``stages.explore._roadmap``). An extension
moves at most ``step`` towards its target; "connect" repeats extensions towards the
other tree's newest node. Every extension is checked as one batch: all of its
configurations at ``check_step`` spacing go through the same float32 sphere-model
clearance as the roadmap, against the same margin. No shortcutting or smoothing: the
raw path is returned (an honest baseline), resampled to the benchmark's waypoint count
by the roadmap's ``resample_polyline``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..model import Robot, q_to_z, z_to_q
from ..stages.explore._roadmap import ClearanceChecker, interpolate_z, resample_polyline
from ..world import Scene, body_gap_tolerance


@dataclass(frozen=True)
class RRTConnectConfig:
    """Settings of the RRT-Connect baseline."""

    step: float = 0.3
    """Longest extension (rad and m in z)."""
    check_step: float = 0.02
    """Spacing of the clearance samples along an extension (rad and m in z)."""
    max_iterations: int = 2000
    """Sampling rounds before giving up (each extends one tree and connects the other)."""
    time_limit: float = 30.0
    """Seconds before giving up."""
    margin: float | None = None
    """Clearance (m, sphere model) every checked sample keeps; None: the roadmap's
    default, ``body_gap_tolerance(robot) + 0.002``."""
    seed: int = 0
    """Seed of the random samples."""


@dataclass(frozen=True)
class RRTResult:
    """An RRT-Connect answer: ``path_z`` (K, 3n) corner points from start to goal (None
    when it failed), ``seconds`` (wall time), ``iterations`` and tree ``nodes``."""

    path_z: np.ndarray | None
    seconds: float
    iterations: int
    nodes: int

    @property
    def success(self) -> bool:
        return self.path_z is not None


class _Tree:
    def __init__(self, root: np.ndarray, capacity: int) -> None:
        self.z = np.empty((capacity, root.size))
        self.parent = np.full(capacity, -1, dtype=np.int64)
        self.z[0] = root
        self.size = 1

    def nearest(self, z: np.ndarray) -> int:
        return int(np.argmin(np.sum((self.z[:self.size] - z) ** 2, axis=1)))

    def add(self, z: np.ndarray, parent: int) -> int:
        if self.size == len(self.z):
            self.z = np.concatenate([self.z, np.empty_like(self.z)])
            self.parent = np.concatenate([self.parent, np.full(len(self.parent), -1)])
        self.z[self.size], self.parent[self.size] = z, parent
        self.size += 1
        return self.size - 1

    def branch(self, index: int) -> list[np.ndarray]:
        """Configurations from the root to ``index``."""
        out = []
        while index >= 0:
            out.append(self.z[index].copy())
            index = int(self.parent[index])
        return out[::-1]


class RRTConnect:
    """RRT-Connect for one robot and scene; ``solve`` answers one start/goal pair."""

    def __init__(self, robot: Robot, scene: Scene, config: RRTConnectConfig = RRTConnectConfig(),
                 checker: ClearanceChecker | None = None) -> None:
        self.robot = robot
        self.scene = scene
        self.config = config
        self.margin = float(config.margin if config.margin is not None
                            else body_gap_tolerance(robot) + 0.002)
        if checker is None or checker.cutoff < self.margin:   # it must decide ≥ margin
            checker = ClearanceChecker(robot, scene, self.margin)
        self.checker = checker
        self.theta_max = np.array([s.theta_max for s in robot.segments])
        self.length_lo = np.array([s.length_min for s in robot.segments])
        self.length_hi = np.array([s.length_max for s in robot.segments])

    def _sample(self, rng: np.random.Generator) -> np.ndarray:
        """A configuration uniform over the bending-vector disks and length ranges."""
        n = self.robot.n_segments
        radius = self.theta_max * np.sqrt(rng.random(n))
        angle = rng.uniform(-np.pi, np.pi, n)
        length = rng.uniform(self.length_lo, self.length_hi)
        return np.stack([radius * np.cos(angle), radius * np.sin(angle), length], 1).ravel()

    def _extend(self, tree: _Tree, target: np.ndarray, connect: bool) -> tuple[int, bool]:
        """Grow ``tree`` from its node nearest ``target`` towards it: one step, or with
        ``connect`` as many steps as stay collision-free. Returns the last node added (or
        the nearest, if none) and whether ``target`` was reached."""
        near = tree.nearest(target)
        start = tree.z[near]
        gap = float(np.linalg.norm(target - start))
        if gap < 1e-12:
            return near, True
        reach = gap if connect else min(gap, self.config.step)
        count = max(1, int(np.ceil(reach / self.config.check_step)))
        # One batch for the whole extension: its first failing sample ends it.
        samples = interpolate_z(start, start + (target - start) * (reach / gap), count + 1)[1:]
        ok = self.checker(samples) >= self.margin
        free = count if ok.all() else int(np.argmin(ok))
        if free == 0:
            return near, False
        stride = max(1, int(round(self.config.step / self.config.check_step)))
        last = near
        for k in [*range(stride - 1, free - 1, stride), free - 1]:
            last = tree.add(samples[k], last)
        return last, free == count and reach == gap

    def solve(self, z_start: np.ndarray, z_goal: np.ndarray) -> RRTResult:
        """Plan from ``z_start`` to ``z_goal`` (3n each, bending-vector form)."""
        begin = time.perf_counter()
        rng = np.random.default_rng(self.config.seed)
        z_start = np.asarray(z_start, dtype=float).ravel()
        z_goal = np.asarray(z_goal, dtype=float).ravel()
        trees = [_Tree(z_start, 1024), _Tree(z_goal, 1024)]
        iteration = 0
        for iteration in range(1, self.config.max_iterations + 1):
            if time.perf_counter() - begin > self.config.time_limit:
                break
            grow, other = trees[0], trees[1]
            target = self._sample(rng) if iteration > 1 else other.z[0]
            new, _ = self._extend(grow, target, connect=False)
            if new != 0 or iteration == 1:
                meet, reached = self._extend(other, grow.z[new], connect=True)
                if reached:
                    first, second = grow.branch(new), other.branch(meet)[::-1]
                    path = first + second[1:] if np.allclose(first[-1], second[0]) \
                        else first + second
                    if trees[0] is not self._start_tree(trees, z_start):
                        path = path[::-1]
                    return RRTResult(np.array(path), time.perf_counter() - begin, iteration,
                                     trees[0].size + trees[1].size)
            trees.reverse()
        return RRTResult(None, time.perf_counter() - begin, iteration,
                         trees[0].size + trees[1].size)

    @staticmethod
    def _start_tree(trees: list[_Tree], z_start: np.ndarray) -> _Tree:
        return trees[0] if np.array_equal(trees[0].z[0], z_start) else trees[1]

    def plan(self, q_start: np.ndarray, q_goal: np.ndarray,
             waypoints: int) -> tuple[np.ndarray | None, RRTResult]:
        """``solve`` for configurations (θ, φ, L) (3n each), the path resampled to
        (waypoints, 3n) configurations (θ, φ, L) uniformly by arc length in z (None on
        failure), and the raw result."""
        q_start = np.asarray(q_start, dtype=float)
        q_goal = np.asarray(q_goal, dtype=float)
        result = self.solve(np.asarray(q_to_z(self.robot, q_start)),
                            np.asarray(q_to_z(self.robot, q_goal)))
        if result.path_z is None:
            return None, result
        q = np.array(z_to_q(self.robot, resample_polyline(result.path_z, waypoints)))
        q[0], q[-1] = q_start, q_goal
        return q, result
