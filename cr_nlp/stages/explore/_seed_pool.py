"""Stage 1, explore: quasi-random seed pools, nearest-seed lookup, diverse beam selection.

The lookup and the beam selection run as jitted JAX on the default device (a GPU when
there is one): the pool's pose features live there once per solver, a target batch is
answered by blocked brute-force distances and ``jax.lax.top_k``, and the beam is chosen
by masks over the whole batch. ``select_beam`` (numpy) is the reference the device
version is tested against.
"""

from __future__ import annotations

import io
import time
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..._files import write_atomic
from ..._programs import compile_program
from ...model import Robot, q_to_z, q_to_z_numpy
from ...model._ops import NUMPY
from ...model.kinematics import model_q_to_z, model_segment_frames
from ...runtime import cache_dir, cached
from .._chunks import chunk_plan

# Orientation features are unit axes scaled by this length (metres per radian, roughly):
# the pose error weighs one radian like one metre, so do the features.
ORIENTATION_SCALE = 1.0

NEAREST_BLOCK = 4096
"""Pool entries per distance block of the nearest-pose lookup: a batch of B targets
holds B × ``NEAREST_BLOCK`` distances at a time, whatever the pool's size."""
POOL_ROUND = 512
"""A pool smaller than a block is padded to a multiple of this many entries."""


def sobol_configurations(robot: Robot, count: int, seed: int = 0) -> np.ndarray:
    """(count, 3n) configurations (θ, φ, L) spread quasi-uniformly inside the limits.

    Sobol points mapped by ``configurations_from_unit`` (θ = θmax·√s, φ and L uniform).
    """
    # The first ``count`` points of a power-of-two draw: the same points as
    # ``random(count)``, without scipy's warning about unbalanced sample sizes.
    power = int(np.ceil(np.log2(max(count, 1))))
    return configurations_from_unit(robot, sobol_unit(robot.dof, power, seed)[:count])


def sobol_unit(dimension: int, power: int, seed: int) -> np.ndarray:
    """(2**power, dimension) scrambled Sobol points in the unit cube (scipy's), kept in
    ``cache_dir()/sobol``: importing ``scipy.stats`` costs a new process 0.7–1.5 s, more
    than the draw."""
    import scipy

    path = cache_dir() / "sobol" / f"{dimension}-{power}-{seed}-scipy{scipy.__version__}.npy"
    try:
        return np.load(path)
    except (OSError, ValueError):
        pass
    from scipy.stats import qmc

    sample = qmc.Sobol(d=dimension, scramble=True, seed=seed).random_base2(power)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        buffer = io.BytesIO()
        np.save(buffer, sample)
        write_atomic(path, buffer.getvalue())
    except OSError:
        pass  # a read-only cache: draw again next time
    return sample


def configurations_from_unit(robot: Robot, sample: Any, xp: Any = np) -> Any:
    """(…, 3n) configurations (θ, φ, L) from points ``sample`` of the unit cube (…, 3n):
    θ = θmax·√s (uniform over the bending-vector disk, so straight-ish shapes are not
    oversampled), φ and L uniform over their ranges. ``xp``: numpy, or jax.numpy inside
    a traced program (the result in the sample's dtype)."""
    lo, hi = robot.q_bounds(xp)
    theta = np.arange(robot.dof) % 3 == 0
    dtype = sample.dtype
    return xp.where(theta, xp.asarray(hi, dtype) * xp.sqrt(sample),
                    xp.asarray(lo, dtype) + xp.asarray(hi - lo, dtype) * sample)


def random_configurations_z(robot: Robot, key: jax.Array, count: int,
                            dtype: Any = jnp.float32) -> jax.Array:
    """(count, 3n) bending vectors (rad, rad, m) of configurations drawn at random inside
    the limits by ``jax.random`` (traceable: the fused search draws its retry seeds on
    the device), with the distribution of ``sobol_configurations`` (θ = θmax·√s)."""
    sample = jax.random.uniform(key, (count, robot.dof), dtype)
    return q_to_z(robot, configurations_from_unit(robot, sample, jnp))


def pose_features(position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(…, 9) features whose Euclidean distance approximates the pose error:
    position (m) and two tip axes scaled by ``ORIENTATION_SCALE``."""
    position = np.asarray(position, dtype=float)
    rotation = np.asarray(rotation, dtype=float)
    return np.concatenate([position, ORIENTATION_SCALE * rotation[..., :, 0],
                           ORIENTATION_SCALE * rotation[..., :, 2]], axis=-1)


@partial(jax.jit, static_argnames=("k",))
def nearest_features(pool: jax.Array, pool_valid: jax.Array, targets: jax.Array,
                     k: int) -> jax.Array:
    """(B, k) indices of the ``k`` pool rows nearest each target row, nearest first.

    Args:
        pool: (blocks, block, d) pool features, padded to whole blocks.
        pool_valid: (blocks, block) False on padding rows (never picked).
        targets: (B, d) target features (same units and centring as the pool).
        k: neighbours per target, at most the number of valid pool rows.

    Squared distances ‖t‖² + ‖p‖² − 2 t·p block by block (``lax.scan``), each block's
    ``top_k`` merged into the running best, so memory is B × block whatever the pool.
    """
    blocks, block, _ = pool.shape
    kb = min(k, block)
    t2 = jnp.sum(targets * targets, axis=-1)

    def merge(best: tuple, inputs: tuple) -> tuple:
        best_neg, best_idx = best
        features, valid, offset = inputs
        d2 = (t2[:, None] + jnp.sum(features * features, axis=-1)[None, :]
              - 2.0 * jnp.matmul(targets, features.T, precision="highest"))
        neg = jnp.where(valid[None, :], -d2, -jnp.inf)
        block_neg, block_idx = jax.lax.top_k(neg, kb)
        both_neg = jnp.concatenate([best_neg, block_neg], axis=1)
        both_idx = jnp.concatenate([best_idx, block_idx + offset], axis=1)
        keep_neg, where = jax.lax.top_k(both_neg, k)
        return (keep_neg, jnp.take_along_axis(both_idx, where, axis=1)), None

    # Derived from the targets so that, split over devices, the carry varies per shard.
    origin = (0.0 * t2)[:, None]
    start = (jnp.full((targets.shape[0], k), -jnp.inf, targets.dtype) + origin,
             jnp.zeros((targets.shape[0], k), jnp.int32) + origin.astype(jnp.int32))
    offsets = jnp.arange(blocks, dtype=jnp.int32) * block
    (_, idx), _ = jax.lax.scan(merge, start, (pool, pool_valid, offsets))
    return idx


class SeedPool:
    """Pre-computed configurations and their tip poses, searchable by target pose.

    The pose features are held as one device array (built once); ``nearest`` answers a
    batch in fixed-size chunks (``chunk_plan``) so one compiled program serves every
    batch size, split over every JAX device (``split_over_devices``: both cores of a
    2-core CPU with ``use_host_devices``).
    """

    def __init__(self, robot: Robot, q: np.ndarray, dtype: str = "float32",
                 block: int = NEAREST_BLOCK, chunk_size: int = 1024) -> None:
        self.robot = robot
        self.q = np.asarray(q, dtype=float).reshape(-1, robot.dof)
        self.z = q_to_z_numpy(self.q)
        # Float64 numpy kinematics: no JAX program to trace or compile for a new pool
        # (measured: 4096 tdcr3 poses in 0.01 s, against 2.8-3.3 s op by op in JAX in a
        # fresh process, most of a one-shot ``cr-nlp ik`` call's explore time).
        with np.errstate(invalid="ignore", divide="ignore"):  # safe_where's unused branch
            rot, pos = model_segment_frames(NUMPY, robot, model_q_to_z(NUMPY, robot, self.q))[-1]
        rotation = np.stack(np.broadcast_arrays(*rot), -1).reshape(-1, 3, 3)
        position = np.stack(np.broadcast_arrays(*pos), -1).reshape(-1, 3)
        self.features = pose_features(position, rotation)
        """(P, 9) float64 pose features of the pool entries (m, and m per rad)."""
        # Centred: the distance expansion ‖t‖² + ‖p‖² − 2t·p loses less in float32.
        self._centre = self.features.mean(axis=0) if len(self.q) else np.zeros(9)
        self.dtype = jnp.dtype(dtype)
        self.chunk_size = chunk_size
        count = len(self.q)
        # Padded to a multiple of POOL_ROUND: pools of a few entries more or less (robots
        # of one shape keep different numbers of entries clear) share one lookup program.
        block = max(1, min(block, -(-count // POOL_ROUND) * POOL_ROUND))
        blocks = max(1, -(-count // block))
        padded = np.zeros((blocks * block, self.features.shape[1]))
        padded[:count] = self.features - self._centre
        valid = np.arange(blocks * block) < count
        self._device_features = jnp.asarray(padded.reshape(blocks, block, -1), self.dtype)
        self._device_valid = jnp.asarray(valid.reshape(blocks, block))
        self._device_z: jax.Array | None = None
        self._device_z_padded: jax.Array | None = None
        self._programs: dict[tuple[int, int], object] = {}
        self.compile_seconds = 0.0
        """Seconds spent compiling lookup programs so far (one per chunk shape and k)."""
        self.calls = 0
        """Lookup programs launched so far (one per chunk of a batch)."""
        self.wait_seconds = 0.0
        """Seconds the host has waited for lookup results so far (device busy time that
        no host work overlapped)."""
        self.launch_seconds = 0.0
        """Seconds inside the calls that launched lookup programs so far."""

    def __len__(self) -> int:
        return len(self.q)

    def target_features(self, target_position: np.ndarray,
                        target_rotation: np.ndarray) -> np.ndarray:
        """(T, 9) pose features of targets (positions (T, 3) m, rotations (T, 3, 3)),
        centred as the pool's: the ``targets`` argument of ``nearest_features``."""
        return pose_features(target_position, target_rotation).reshape(-1, 9) - self._centre

    def device_arrays(self, padded: bool = False) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The pool on the device, for programs that look up seeds themselves (the fused
        search and its retries): features and valid mask as ``nearest_features`` takes
        them, and the entries' bending vectors (P, 3n) (rad, rad, m); ``padded``: with
        zero rows to the features' padded length, so that pools of one padded size (robots
        of one shape) give programs arrays of one shape."""
        if not padded:
            if self._device_z is None:
                self._device_z = jnp.asarray(self.z, self.dtype)
            return self._device_features, self._device_valid, self._device_z
        if self._device_z_padded is None:
            z = np.zeros((self._device_valid.size, self.z.shape[1]), self.dtype)
            z[:len(self.z)] = self.z
            self._device_z_padded = jnp.asarray(z)
        return self._device_features, self._device_valid, self._device_z_padded

    def nearest(self, target_position: np.ndarray, target_rotation: np.ndarray,
                k: int) -> np.ndarray:
        """(T, k) indices of the pool entries whose tip poses are nearest each target,
        nearest first (T targets: positions (T, 3) m, rotations (T, 3, 3))."""
        k = min(k, len(self))
        features = self.target_features(target_position, target_rotation)
        count = len(features)
        if count == 0 or k == 0:
            return np.zeros((count, k), dtype=np.int64)
        parts = []
        start = 0
        for chunk in chunk_plan(count, self.chunk_size):
            stop = min(start + chunk, count)
            # Cast on the host, then one transfer (``jnp.asarray`` of float64 converts on
            # the device, behind the chunks already launched).
            rows = np.zeros((chunk, features.shape[1]), self.dtype)
            rows[: stop - start] = features[start:stop]
            args = (self._device_features, self._device_valid, jax.device_put(rows))
            if (chunk, k) not in self._programs:
                t0 = time.perf_counter()
                self._programs[chunk, k] = compile_program(
                    partial(nearest_features, k=k), args, name="the seed lookup",
                    batched=(False, False, True))
                self.compile_seconds += time.perf_counter() - t0
            t0 = time.perf_counter()
            parts.append((stop - start, self._programs[chunk, k](*args)))
            self.launch_seconds += time.perf_counter() - t0
            self.calls += 1
            start = stop
        # Every chunk is dispatched before the first result is waited for.
        t0 = time.perf_counter()
        jax.block_until_ready([idx for _, idx in parts])
        self.wait_seconds += time.perf_counter() - t0
        return np.concatenate([np.asarray(idx)[:used] for used, idx in parts]).astype(np.int64)


@cached(maxsize=8)
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


@partial(jax.jit, static_argnames=("width",))
def select_beam_device(z: jax.Array, cost: jax.Array, width: int,
                       min_distance: float | jax.Array) -> jax.Array:
    """``select_beam`` as one jitted program over the whole batch: the same greedy rule
    (lowest cost first, skipping candidates within ``min_distance`` of one already
    picked), one ``lax.fori_loop`` step per rank with masks instead of shrinking batches.

    Args:
        z: (T, K, n) candidates (bending-vector units, rad or m). cost: (T, K).
        width: candidates to pick per problem (static).
        min_distance: diversity radius, same units as z.
    Returns:
        (T, width) int32 indices into K (repeats the best when too few are diverse).
    """
    order = jnp.argsort(cost, axis=1)
    ranked = jnp.take_along_axis(z, order[:, :, None], axis=1)
    slots = jnp.arange(width)
    chosen = jnp.repeat(ranked[:, :1], width, axis=1)
    # Derived from the input, so that split over devices the carry varies per shard.
    origin = (0 * cost[:, :1]).astype(jnp.int32)
    picked = jnp.zeros((z.shape[0], width), jnp.int32) + origin
    count = jnp.ones(z.shape[0], jnp.int32) + origin[:, 0]

    def step(rank: jax.Array, state: tuple) -> tuple:
        chosen, picked, count = state
        candidate = jax.lax.dynamic_index_in_dim(ranked, rank, axis=1, keepdims=False)
        dist = jnp.linalg.norm(chosen - candidate[:, None, :], axis=-1)
        valid = slots[None, :] < count[:, None]
        far = jnp.all(jnp.where(valid, dist > min_distance, True), axis=1)
        take = (count < width) & far
        slot = take[:, None] & (slots[None, :] == count[:, None])
        chosen = jnp.where(slot[:, :, None], candidate[:, None, :], chosen)
        picked = jnp.where(slot, rank, picked)
        return chosen, picked, count + take

    _, picked, _ = jax.lax.fori_loop(1, z.shape[1], step, (chosen, picked, count))
    return jnp.take_along_axis(order, picked, axis=1).astype(jnp.int32)
