"""Stage 1, explore: quasi-random seed pools, nearest-seed lookup, diverse beam selection."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import qmc

from ..model import Robot, q_to_z, tip_pose

# Orientation features are unit axes scaled by this length (metres per radian, roughly):
# the pose error weighs one radian like one metre, so do the features.
ORIENTATION_SCALE = 1.0


def sobol_configurations(robot: Robot, count: int, seed: int = 0) -> np.ndarray:
    """(count, 3n) configurations (θ, φ, L) spread quasi-uniformly inside the limits.

    θ is drawn as θmax·√s (uniform over the bending-vector disk, so straight-ish shapes
    are not oversampled), φ uniform over its range, L uniform over its range.
    """
    lo, hi = robot.q_bounds()
    sample = qmc.Sobol(d=robot.dof, scramble=True, seed=seed).random(count)
    q = lo + (hi - lo) * sample
    q[:, 0::3] = hi[0::3] * np.sqrt(sample[:, 0::3])
    return q


def pose_features(position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(…, 9) features whose Euclidean distance approximates the pose error:
    position (m) and two tip axes scaled by ``ORIENTATION_SCALE``."""
    position = np.asarray(position, dtype=float)
    rotation = np.asarray(rotation, dtype=float)
    return np.concatenate([position, ORIENTATION_SCALE * rotation[..., :, 0],
                           ORIENTATION_SCALE * rotation[..., :, 2]], axis=-1)


class SeedPool:
    """Pre-computed configurations and their tip poses, searchable by target pose."""

    def __init__(self, robot: Robot, q: np.ndarray) -> None:
        self.robot = robot
        self.q = np.asarray(q, dtype=float)
        self.z = np.asarray(q_to_z(robot, self.q))
        position, rotation = (np.asarray(x) for x in tip_pose(robot, self.q))
        self.tree = cKDTree(pose_features(position, rotation))

    def __len__(self) -> int:
        return len(self.q)

    def nearest(self, target_position: np.ndarray, target_rotation: np.ndarray,
                k: int) -> np.ndarray:
        """(T, k) indices of the pool entries whose tip poses are nearest each target."""
        k = min(k, len(self))
        _, idx = self.tree.query(pose_features(target_position, target_rotation), k=k)
        return np.asarray(idx).reshape(len(target_position), k)


@lru_cache(maxsize=8)
def default_pool(robot: Robot, size: int, seed: int) -> SeedPool:
    """A Sobol seed pool for a robot, built once per process."""
    return SeedPool(robot, sobol_configurations(robot, size, seed))


def select_beam(z: np.ndarray, cost: np.ndarray, width: int, min_distance: float) -> np.ndarray:
    """Pick ``width`` candidates per problem: lowest cost first, skipping candidates within
    ``min_distance`` (bending-vector units, rad or m) of one already picked.

    Args:
        z: (T, K, n) candidates. cost: (T, K).
    Returns:
        (T, width) indices into K (repeats the best when too few are diverse).
    """
    order = np.argsort(cost, axis=1)
    picked = np.repeat(order[:, :1], width, axis=1)
    count = np.ones(len(z), dtype=int)
    for rank in range(1, z.shape[1]):
        need = count < width
        if not need.any():
            break
        cand = order[:, rank]
        zc = z[np.arange(len(z)), cand]
        chosen = z[np.arange(len(z))[:, None], picked]
        dist = np.linalg.norm(chosen - zc[:, None, :], axis=-1)
        valid = np.arange(width)[None, :] < count[:, None]
        far = np.all(np.where(valid, dist > min_distance, True), axis=1)
        take = need & far
        picked[take, count[take]] = cand[take]
        count += take
    return picked
