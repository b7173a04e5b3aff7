"""The verdict's float64 geometry of many PCC configurations as one compiled program.

The verdict re-evaluates every answer in float64, apart from the optimiser's float32
numbers (``world.verdict``). For IK batches that re-evaluation (the tip pose and the
distance between segments at least two apart) was numpy on the host: about 0.5 s per
100 000 targets, most of the host's share of a batch, and all of it on a GPU. Here the
same formulas (``model.kinematics``'s model, ``_segment_distances``' closed forms) run
as one XLA program traced with float64 enabled for it alone (``jax.enable_x64``), in
blocks of ``ROWS`` configurations split over the devices. The float32 solver programs
are untouched; the program never sees their intermediate numbers, only the answers.

Blocks under a quarter of ``ROWS`` (a batch's remainder, small batches) go
through the numpy verdict instead: compiling a program for them would cost more than it
saves. Both give the same numbers to rounding (tests pin 1e-12 m).
"""

from __future__ import annotations

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._programs import compile_program
from ..model._ops import JAX
from ..model.kinematics import model_backbone, model_q_to_z, model_segment_frames, tip_pose
from ..model.robot import Robot
from ..runtime import cached
from ._segment_distances import segment_segment

ROWS = 4096
"""Configurations per run of the program (a batch is cut into blocks of this size);
blocks under a quarter of it use the numpy verdict (``tip_pose``, ``world.check``)."""


def _far_blocks(robot: Robot) -> list[tuple[int, int]]:
    """Segment pairs (s, t ≥ s + 2) whose pieces the self-distance compares (none when
    the robot file turns self-collision off)."""
    n = robot.n_segments if robot.self_collision else 0
    return [(s, t) for s in range(n) for t in range(s + 2, n)]


def _geometry(robot: Robot, q: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Tip position (B, 3) m, tip rotation (B, 3, 3) and the self-distance (B,) m of
    configurations q (B, 3n), in q's precision: every pair of pieces of segments at least
    two apart (capsules of the backbone radius), as ``world.check`` measures it."""
    z = model_q_to_z(JAX, robot, q)
    frames = model_segment_frames(JAX, robot, z)
    rot, pos = frames[-1]
    tip_p = jnp.stack(jnp.broadcast_arrays(*pos), axis=-1)
    tip_r = jnp.stack(jnp.broadcast_arrays(*rot), axis=-1).reshape(q.shape[:-1] + (3, 3))
    blocks = _far_blocks(robot)
    if not blocks:
        return tip_p, tip_r, jnp.full(q.shape[:-1], jnp.inf, q.dtype)
    points = model_backbone(JAX, robot, z, frames)
    base = jnp.broadcast_to(jnp.asarray(robot.base_position, q.dtype),
                            points.shape[:-2] + (1, 3))
    chain = jnp.concatenate([base, points], axis=-2)
    k = robot.points_per_segment
    a, b = chain[:, :-1], chain[:, 1:]     # piece i joins chain points i and i + 1

    def pieces(x: jax.Array, segment: int, axis: int) -> tuple[jax.Array, ...]:
        part = x[:, segment * k:(segment + 1) * k]
        return tuple(jnp.expand_dims(part[..., c], axis) for c in range(3))

    own = jnp.full(q.shape[:-1], jnp.inf, q.dtype)
    for s, t in blocks:
        d = segment_segment(pieces(a, s, 2), pieces(b, s, 2), pieces(a, t, 1),
                            pieces(b, t, 1), jnp)
        own = jnp.minimum(own, jnp.min(d, axis=(1, 2)))
    return tip_p, tip_r, own - 2.0 * robot.backbone_radius


@cached(maxsize=16)
def _program(robot: Robot, rows: int) -> Any:
    """The compiled ``_geometry`` of ``robot`` for ``rows`` float64 configurations."""
    def geometry(q: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        return _geometry(robot, q)

    with jax.enable_x64(True):
        return compile_program(geometry, (np.zeros((rows, robot.dof)),),
                               name="the float64 verdict geometry", batched=(True,),
                               outputs=3)


def _numpy_geometry(robot: Robot, q: np.ndarray) -> tuple[np.ndarray, ...]:
    from .check import check_many

    pos, rot = tip_pose(robot, q)
    own = (check_many(robot, None, q).self_distance if _far_blocks(robot)
           else np.full(len(q), np.inf))
    return pos, rot, own


def configuration_geometry(robot: Robot, q: Any, counters: Any = None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The verdict's float64 tip pose and self-distance of PCC configurations.

    Args:
        robot: the robot.
        q: (B, 3n) configurations θ, φ, L (rad, rad, m).
        counters: where the program's seconds are booked, or None: an object with
            ``device_calls``, ``device_launch`` and ``device_wait`` (the IK search's
            counters), so that a benchmark's host share leaves them out.

    Returns:
        tip positions (B, 3) m, tip rotations (B, 3, 3) and the smallest signed distance
        (B,) m between pieces of segments at least two apart (+inf where not checked:
        fewer than three segments or ``"self_collision": false``), all float64 numpy.
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1, robot.dof)
    count = len(q)
    pos, rot, own = np.empty((count, 3)), np.empty((count, 3, 3)), np.empty(count)
    launched, small = [], []
    size = ROWS
    t0 = time.perf_counter()
    for start in range(0, count, size):
        block = q[start:start + size]
        if len(block) < max(size // 4, 1):
            small.append((start, block))
            continue
        padded = np.empty((size, robot.dof))
        padded[:len(block)] = block
        padded[len(block):] = block[0]
        with jax.enable_x64(True):
            launched.append((start, len(block), _program(robot, size)(padded)))
    t1 = time.perf_counter()
    for start, block in small:        # on the host while the device runs the blocks
        rows = slice(start, start + len(block))
        pos[rows], rot[rows], own[rows] = _numpy_geometry(robot, block)
    t2 = time.perf_counter()
    jax.block_until_ready([out for _, _, out in launched])
    t3 = time.perf_counter()
    for start, used, out in launched:
        rows = slice(start, start + used)
        pos[rows], rot[rows], own[rows] = (np.asarray(x)[:used] for x in out)
    if counters is not None and launched:
        counters.device_calls += len(launched)
        counters.device_launch += t1 - t0
        counters.device_wait += t3 - t2
    return pos, rot, own
