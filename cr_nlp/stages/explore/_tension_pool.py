"""Stage 1 of the mechanics tasks: the tension seed pool of a robot under one load case,
built once and cached on disk (like the roadmaps of ``_roadmap``).

A pool is ``size`` random tension sets (N) with one tendon (a third of the time two) of
every segment slack (most shapes need at most two of three), each solved by the forward
statics (``model.statics.solve_statics``) under the load case; the converged ones are
kept with their tip positions (world frame, m) and their backbones. Tension IK seeds each
target from the pool sets whose tips are nearest; the planner takes its via candidates
from the sets whose backbones are clear of the scene.

A pool depends on the robot (its whole file form, mechanics included), the load case, the
pool's size and seed and the rod discretisation: all of them key the cache file, so a new
process under the same loads loads it (no statics solve) and any change builds a new one.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..._files import write_atomic
from ...model import Robot
from ...model.cosserat import StaticsConfig, solve_statics
from ...model.loads import StaticLoads
from ...runtime import cache_dir
from ...world.clearance import SceneArrays, backbone_clearance_numpy, chain_self_clearance_numpy

FORMAT_VERSION = 2
"""Bumped when the cached file's content or the build procedure changes."""

_CACHE_STATS = {"hits": 0, "builds": 0}


def tension_pool_cache_stats() -> dict[str, int]:
    """How many pools this process loaded from the disk cache (``hits``) and built."""
    return dict(_CACHE_STATS)


@dataclass(frozen=True)
class TensionPool:
    """Converged random tension sets of one robot under one load case."""

    tensions: np.ndarray
    """(P, n) tensions, N, the robot file's tendon order."""
    tips: np.ndarray
    """(P, 3) tip positions of their equilibria, m, world frame."""
    backbones: np.ndarray
    """(P, S, 3) the solved backbones at the robot's points, base to tip, m."""
    base_moments: np.ndarray
    """(P, 3) moment at the base of each equilibrium, N·m, world frame (an LM started
    from a pool set starts at its equilibrium)."""
    build_seconds: float
    """Seconds the build took (loaded from the cache: the original build's)."""
    loaded_from_cache: bool = False
    """True when this pool came from the disk cache."""
    tree: cKDTree = field(init=False, repr=False, compare=False)
    """A k-d tree of ``tips``."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "tree", cKDTree(self.tips))

    def nearest(self, positions: np.ndarray, rank: int = 0) -> np.ndarray:
        """(B,) index of the pool set whose tip is the ``rank``-th nearest (0: nearest) to
        each of ``positions`` (B, 3) m."""
        _, order = self.tree.query(positions, k=[rank + 1])
        return order[:, 0]

    def nearest_clear(self, positions: np.ndarray, rank: int, clear: np.ndarray,
                      neighbours: int) -> np.ndarray:
        """``nearest``, where among the ``neighbours + rank`` nearest sets the clear ones
        (``clear`` (P,) True: ``clear_sets``) come first, in order of distance."""
        k = min(len(self.tensions), neighbours + rank)
        _, index = self.tree.query(positions, k=k)
        order = np.argsort(~clear[index], axis=1, kind="stable")
        return np.take_along_axis(index, order[:, rank:rank + 1], axis=1)[:, 0]

    def clear_sets(self, robot: Robot, arrays: SceneArrays | None, band: float) -> np.ndarray:
        """(P,) True where a set's backbone keeps ``band`` m from the scene's parts
        (``arrays``, numpy; None: no scene) and from itself (segments at least two apart): a
        quick sphere screen (the verdict's capsules are python-fcl's)."""
        clear = backbone_clearance_numpy(robot.backbone_radius, arrays, self.backbones) >= band
        if robot.has_self_pairs:
            clear &= chain_self_clearance_numpy(robot, self.backbones) >= band
        return clear


def _pool_key(robot: Robot, loads: StaticLoads, size: int, seed: int,
              statics: StaticsConfig) -> str:
    """sha256 of everything a pool depends on (see the module's docstring)."""
    h = hashlib.sha256()
    h.update(json.dumps({"version": FORMAT_VERSION, "robot": robot.to_dict(), "size": size,
                         "seed": seed, "statics": asdict(statics)},
                        sort_keys=True, default=str).encode())
    for array in loads.arrays():
        h.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return h.hexdigest()


def random_tensions(robot: Robot, size: int, seed: int) -> np.ndarray:
    """(size, n) random tensions in [0, τ_max] N with one tendon of every segment slack
    and, for a third of the sets, a second one."""
    rng = np.random.default_rng(seed)
    per = robot.tendons.per_segment
    n = robot.n_tendons
    tensions = rng.uniform(0.0, float(robot.mechanics.tension_max), (size, n))
    for s in range(n // per):
        drop = rng.integers(0, per, size)
        tensions[np.arange(size), s * per + drop] = 0.0
        second = rng.random(size) < 1 / 3
        tensions[np.flatnonzero(second), s * per + (drop[second] + 1) % per] = 0.0
    return tensions


def _build(robot: Robot, loads: StaticLoads, size: int, seed: int,
           statics: StaticsConfig) -> TensionPool:
    start = time.perf_counter()
    tensions = random_tensions(robot, size, seed)
    one = loads.rows(np.zeros(size, int))
    solved = solve_statics(robot, tensions, one.tip_force, one.tip_moment, one.gravity, statics,
                           distributed_force=one.distributed_force,
                           point_loads=one.point_load_lists())
    keep = np.asarray(solved.converged)
    return TensionPool(tensions[keep], np.asarray(solved.tip_position)[keep],
                       np.asarray(solved.positions)[keep], np.asarray(solved.base_moment)[keep],
                       time.perf_counter() - start)


def tension_pool_path(robot: Robot, loads: StaticLoads, size: int, seed: int = 0,
                      statics: StaticsConfig = StaticsConfig()) -> Path:
    """The cache file of a pool (``tension_pool``'s arguments; ``loads``' first row)."""
    case = loads.rows(np.zeros(1, int))
    return cache_dir() / "tension_pools" / f"{_pool_key(robot, case, size, seed, statics)}.npz"


def tension_pool(robot: Robot, loads: StaticLoads, size: int, seed: int = 0,
                 statics: StaticsConfig = StaticsConfig(), cache: bool = True) -> TensionPool:
    """The seed pool of ``robot`` under the one load case ``loads`` (its first row).

    Loaded from ``cache_dir()/tension_pools`` when one with the same robot, loads, size,
    seed and rod settings is there (``cache``), else built (a batch of ``size`` forward
    statics solves) and written there. A damaged cache file is rebuilt."""
    case = loads.rows(np.zeros(1, int))
    path = tension_pool_path(robot, case, size, seed, statics)
    if cache and path.exists():
        try:
            with np.load(path) as data:
                pool = TensionPool(data["tensions"], data["tips"], data["backbones"],
                                   data["base_moments"], float(data["build_seconds"]),
                                   loaded_from_cache=True)
            _CACHE_STATS["hits"] += 1
            return pool
        except (OSError, KeyError, ValueError):
            pass
    pool = _build(robot, case, size, seed, statics)
    _CACHE_STATS["builds"] += 1
    if cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        buffer = io.BytesIO()
        np.savez(buffer, tensions=pool.tensions, tips=pool.tips, backbones=pool.backbones,
                 base_moments=pool.base_moments, build_seconds=pool.build_seconds)
        write_atomic(path, buffer.getvalue())   # a concurrent reader never sees half a file
    return pool
