"""The verdict's float64 re-evaluation of many IK answers as one compiled program.

The verdict re-evaluates every answer in float64, apart from the optimiser's float32
numbers (``world.verdict``). For IK batches that re-evaluation (the tip pose, the pose
error, the limits and the distance between segments at least two apart) was numpy on the
host: about 0.5 s per 100 000 targets, most of the host's share of a batch, and all of it
on a GPU. Here the same formulas (``model.kinematics``'s model, ``model.limits``,
``_segment_distances``' closed forms) run as one XLA program traced with float64 enabled
for it alone (``jax.enable_x64``), in blocks of ``ROWS`` configurations split over the
devices. The float32 solver programs are untouched; the program never sees their
intermediate numbers, only the answers.

Blocks under a quarter of ``ROWS`` (a batch's remainder, small batches) go through the
numpy verdict instead: compiling a program for them would cost more than it saves. Both
give the same numbers to rounding (tests pin 1e-12).
"""

from __future__ import annotations

import time
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._programs import compile_program
from ..model._ops import JAX
from ..model.kinematics import model_q_to_z, model_segment_frames, pose_error, tip_pose
from ..model.lie import quat_from_rot
from ..model.limits import limit_violation_q
from ..model.robot import Robot
from ..model.rotations import wxyz_from_matrix
from ..runtime import cached
from ._motion_check import Pieces, _run_length, piece_geometry
from ._segment_distances import segment_segment
from .clearance import _body_centres

ROWS = 4096
"""Configurations per run of the program (a batch is cut into blocks of this size);
blocks under a quarter of it use the numpy verdict (``tip_pose``, ``world.check``)."""
MOTION_ROWS = 256
"""Configurations per run of the motion verdict's program (``motion_chains``): a
planner's verdict judges a few hundred at a time."""


class AnswerGeometry(NamedTuple):
    """The verdict's float64 re-evaluation of B configurations against their targets."""

    position: np.ndarray
    """(B, 3) tip positions, m."""
    wxyz: np.ndarray
    """(B, 4) tip orientations, unit quaternions (w ≥ 0)."""
    pose_error: np.ndarray
    """(B,) ‖log(T_tip⁻¹·T_target)‖ (mixed m/rad)."""
    position_error: np.ndarray
    """(B,) m."""
    rotation_error: np.ndarray
    """(B,) rad."""
    self_distance: np.ndarray
    """(B,) smallest signed distance between pieces of segments at least two apart, m
    (+inf where not checked: fewer than three segments or ``"self_collision": false``)."""
    limits: np.ndarray
    """(B,) largest violation of the configuration limits, rad or m (≥ 0)."""


def _self_distance(robot: Robot, q: jax.Array, z: list[Any]) -> jax.Array:
    """(B,) every pair of pieces of segments at least two apart (capsules of the backbone
    radius), as ``world.check`` measures it, in q's precision."""
    chain = _body_centres(JAX, robot, z)   # the base point, then the backbone's
    k = robot.points_per_segment
    a, b = chain[:, :-1], chain[:, 1:]     # piece i joins chain points i and i + 1

    def pieces(x: jax.Array, segment: int, axis: int) -> tuple[jax.Array, ...]:
        part = x[:, segment * k:(segment + 1) * k]
        return tuple(jnp.expand_dims(part[..., c], axis) for c in range(3))

    own = jnp.full(q.shape[:-1], jnp.inf, q.dtype)
    n = robot.n_segments
    for s in range(n):
        for t in range(s + 2, n):
            d = segment_segment(pieces(a, s, 2), pieces(b, s, 2), pieces(a, t, 1),
                                pieces(b, t, 1), jnp)
            own = jnp.minimum(own, jnp.min(d, axis=(1, 2)))
    return own - 2.0 * robot.backbone_radius


def _checked_self_distance(robot: Robot, q: jax.Array, z: list[Any]) -> jax.Array:
    """``_self_distance`` where the robot checks it, else +inf (B,)."""
    return (_self_distance(robot, q, z) if robot.has_self_pairs
            else jnp.full(q.shape[:-1], jnp.inf, q.dtype))


def _geometry(robot: Robot, q: jax.Array, target_p: jax.Array,
              target_r: jax.Array) -> tuple[jax.Array, ...]:
    """``AnswerGeometry``'s fields for configurations q (B, 3n) and targets (positions
    (B, 3) m, rotations (B, 9) row-major), in q's precision."""
    z = model_q_to_z(JAX, robot, q)
    frames = model_segment_frames(JAX, robot, z)
    rot, pos = frames[-1]
    tip_p = jnp.stack(jnp.broadcast_arrays(*pos), axis=-1)
    tip_r = jnp.stack(jnp.broadcast_arrays(*rot), axis=-1)
    wxyz = jnp.stack(jnp.broadcast_arrays(*quat_from_rot(JAX, rot)), axis=-1)
    shape = q.shape[:-1] + (3, 3)
    error = pose_error(tip_p, tip_r.reshape(shape), target_p, target_r.reshape(shape))
    # trace(Rᵀ·R_target) = Σᵢⱼ Rᵢⱼ·R_targetᵢⱼ
    cos_angle = jnp.clip((jnp.sum(tip_r * target_r, axis=-1) - 1.0) / 2.0, -1.0, 1.0)
    return (tip_p, wxyz, error, jnp.linalg.norm(tip_p - target_p, axis=-1),
            jnp.arccos(cos_angle), _checked_self_distance(robot, q, z),
            limit_violation_q(robot, q, jnp))


@cached(maxsize=16)
def _program(robot: Robot, rows: int) -> Any:
    """The compiled ``_geometry`` of ``robot`` for ``rows`` float64 configurations (one
    program per robot shape: the robot is its data)."""
    with jax.enable_x64(True):
        return compile_program(partial(_geometry, robot),
                               (np.zeros((rows, robot.dof)), np.zeros((rows, 3)),
                                np.zeros((rows, 9))),
                               name="the float64 verdict", batched=(True, True, True),
                               outputs=len(AnswerGeometry._fields), by_shape=True)


def _numpy_geometry(robot: Robot, q: np.ndarray, target_p: np.ndarray,
                    target_r: np.ndarray, self_distance: bool,
                    pose: bool) -> tuple[np.ndarray, ...]:
    """``_geometry`` in numpy (``tip_pose``, ``pose_error``, ``world.check``); the
    self-distance +inf unless asked for, the pose fields and limits NaN unless asked
    for."""
    from .check import check_many

    count = len(q)
    own = (check_many(robot, None, q).self_distance if self_distance and robot.has_self_pairs
           else np.full(count, np.inf))
    if not pose:
        nan = np.full(count, np.nan)
        return (np.full((count, 3), np.nan), np.full((count, 4), np.nan), nan, nan, nan,
                own, nan)
    pos, rot = tip_pose(robot, q)
    target_m = target_r.reshape(-1, 3, 3)
    cos_angle = np.clip((np.sum(rot.reshape(-1, 9) * target_r, axis=-1) - 1.0) / 2.0, -1, 1)
    return (pos, wxyz_from_matrix(rot), pose_error(pos, rot, target_p, target_m),
            np.linalg.norm(pos - target_p, axis=1), np.arccos(cos_angle), own,
            limit_violation_q(robot, q))


def answer_geometry(robot: Robot, q: Any, positions: Any, rotations: Any,
                    counters: Any = None, self_distance: bool = True,
                    pose: bool = True) -> AnswerGeometry:
    """The verdict's float64 re-evaluation of PCC configurations against their targets.

    Args:
        robot: the robot.
        q: (B, 3n) configurations θ, φ, L (rad, rad, m).
        positions: (B, 3) target tip positions, m; rotations: (B, 3, 3) target tip
            orientations.
        counters: where the program's seconds are booked, or None: an object with
            ``device_calls``, ``device_launch`` and ``device_wait`` (the IK search's
            counters), so that a benchmark's host share leaves them out.
        self_distance: False where the caller measures the self-distance itself (a
            scene's check, the search's self-repair): then it is +inf where numpy
            evaluates a block (the program measures it anyway, on the device).
        pose: False where the caller needs the self-distance only (the search's
            self-repair): then the other fields are NaN where numpy evaluates a block.

    Returns:
        an ``AnswerGeometry`` of float64 numpy arrays.
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1, robot.dof)
    count = len(q)
    target_p = np.asarray(positions, dtype=np.float64).reshape(count, 3)
    target_r = np.asarray(rotations, dtype=np.float64).reshape(count, 9)
    out = [np.empty((count, 3)), np.empty((count, 4))] + [np.empty(count) for _ in range(5)]
    launched, small = [], []
    size = ROWS
    t0 = time.perf_counter()
    for start in range(0, count, size):
        rows = slice(start, min(start + size, count))
        used = rows.stop - start
        if used < max(size // 4, 1):
            small.append(rows)
            continue
        args = []
        for x in (q, target_p, target_r):
            padded = np.empty((size, x.shape[1]))
            padded[:used] = x[rows]
            padded[used:] = x[start]
            args.append(padded)
        with jax.enable_x64(True):
            launched.append((rows, _program(robot, size)(*args)))
    t1 = time.perf_counter()
    for rows in small:                # on the host while the device runs the blocks
        for field, value in zip(out, _numpy_geometry(robot, q[rows], target_p[rows],
                                                     target_r[rows], self_distance, pose),
                              strict=True):
            field[rows] = value
    t2 = time.perf_counter()
    jax.block_until_ready([result for _, result in launched])
    t3 = time.perf_counter()
    for rows, result in launched:
        for field, value in zip(out, result, strict=True):
            field[rows] = np.asarray(value)[:rows.stop - rows.start]
    if counters is not None and launched:
        counters.device_calls += len(launched)
        counters.device_launch += t1 - t0
        counters.device_wait += t3 - t2
    return AnswerGeometry(*out)


def _motion_geometry(robot: Robot, q: jax.Array) -> tuple[jax.Array, ...]:
    """``motion_chains``' body chains (B, 1 + n·k, 3), self distances (B,) and the
    chains' ``Pieces`` (mid points (3, B, m), half lengths (B, m), run balls' centres (3,
    B, runs) and radii (B, runs)) of configurations q (B, 3n), in q's precision."""
    z = model_q_to_z(JAX, robot, q)
    chains = _body_centres(JAX, robot, z)
    ends = tuple(tuple(c[..., k] for k in range(3)) for c in (chains[:, :-1], chains[:, 1:]))
    mid, half, centre, reach = piece_geometry(robot.backbone_radius, *ends,
                                              _run_length(robot.points_per_segment), jnp)
    return (chains, _checked_self_distance(robot, q, z), jnp.stack(mid), half,
            jnp.stack(centre), reach)


@cached(maxsize=16)
def _motion_program(robot: Robot, rows: int) -> Any:
    """The compiled ``_motion_geometry`` of ``robot`` for ``rows`` float64 configurations
    (one program per robot shape)."""
    with jax.enable_x64(True):
        return compile_program(partial(_motion_geometry, robot), (np.zeros((rows, robot.dof)),),
                               name="the float64 motion verdict", outputs=6, by_shape=True)


def motion_chains(robot: Robot, q: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray | None, Pieces | None]:
    """The motion verdict's float64 re-evaluation of configurations q (B, 3n; rad, rad,
    m): their body chains (``world.check.body_chain``: the base point, then the backbone
    points; (B, 1 + n·k, 3), m), their self distances (B,; ``check_many``'s
    ``self_distance``, m; +inf where not checked) and the chains' ``Pieces`` (what the
    motion search reads of them), as one program over blocks of ``MOTION_ROWS`` (the last
    one padded). The same formulas as numpy's, to rounding (tests pin 1e-12 m). Under half
    a block (one motion's configurations): numpy's chains and neither of the others
    (None: the motion search computes what it needs).

    On the planner's 300 shelf problems the host's share of planning fell from 3.19–3.23
    to 2.56–2.58 s per 1000 problems, the whole run's wall time unchanged; the
    ``Pieces`` from the program too, 2.02–2.38 → 1.95–2.10 (whole processes alternated
    three times)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, robot.dof)
    count = len(q)
    if count < MOTION_ROWS // 2:
        from .check import body_chain

        return body_chain(robot, q), None, None
    launched = []
    for start in range(0, count, MOTION_ROWS):
        rows = slice(start, min(start + MOTION_ROWS, count))
        block = np.empty((MOTION_ROWS, robot.dof))
        block[:rows.stop - start] = q[rows]
        block[rows.stop - start:] = q[start]
        with jax.enable_x64(True):
            launched.append((rows, _motion_program(robot, MOTION_ROWS)(block)))
    # Each output's blocks joined along the configurations' axis (the first, or the second
    # for the stacked coordinates), the last block's padding left out.
    joined = [np.concatenate([np.asarray(out[k])[(slice(None),) * axis
                                                 + (slice(0, rows.stop - rows.start),)]
                              for rows, out in launched], axis=axis)
              for k, axis in enumerate((0, 0, 1, 0, 1, 0))]
    chains, own, mid, half, centre, reach = joined
    return chains, own, Pieces(tuple(mid), half, tuple(centre), reach)
