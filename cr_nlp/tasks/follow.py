"""Path following: the tip traces a reference path while the body avoids obstacles and
the tendons move smoothly.

Problem (DESIGN.md §2): z = (z₀, …, z_{T−1}), one bending-vector configuration per
waypoint of the path (time step Δt between waypoints); f = Σₜ pose error to the
reference pose (the 6-vector log(T_tip⁻¹·T_ref), DESIGN.md §1) plus a small smoothness
term; c = clearance ≥ δ at every waypoint and along the motion between waypoints,
tendon speed |Δℓ/Δt| ≤ v_max and acceleration |Δ²ℓ/Δt²| ≤ a_max; limits by projection.
Between waypoints the robot moves linearly in z (as ``tasks.trajectory``: linear in the
tendon lengths).

Stages:

1. explore: IK on every ``ik_stride``-th waypoint in one batch (``IKSolver.candidates``:
   a refined beam of distinct answers per waypoint), each answer carried to the
   neighbouring IK waypoints by continuation (a few LM steps per waypoint), then the
   sequence with the smallest configuration jumps (``stages.sequence.smoothest_choice``,
   dynamic programming on the device, in the same program as the candidate table).
2. refine: all waypoints jointly by the block-banded LM (``stages.banded_lm``): every
   residual depends on at most three consecutive waypoints (tracking and clearance: one;
   smoothness, tendon speed, clearance between waypoints: two; tendon acceleration:
   three), so each iteration costs O(T), not O(T³). Constraints are penalties here.
3. polish (``exact=True``): Ipopt with the constraints as constraints, minimising the
   tracking error, warm-started from stage 2 (``stages.polish_trajectory``); a polish
   that fails, or that the independent check rejects, returns the stage-2 answer,
   marked in ``FollowResult.stage``.

Every answer is judged in float64 independently of the optimisers:
``tasks.trajectory.verify_trajectory`` (python-fcl along the interpolated motion, limits,
tendon finite differences) and the tip poses by the numpy backend of the model.

Waypoints outside the robot's reach (farther from the base than its longest length)
cannot be tracked: their tracking residual is switched off, the motion there is set by
its neighbours, and the result reports them (``reached`` False), never an exception.
"""

from __future__ import annotations

import math
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, ClassVar

import jax
import jax.monitoring
import jax.numpy as jnp
import numpy as np

from .._jax_setup import enable_compilation_cache, split_over_devices
from ..model import Robot, load_robot, q_to_z_numpy, z_to_q_numpy
from ..model._ops import JAX, NUMPY
from ..model.actuation import planned_displacements
from ..model.derivatives import kinematics_jacobians_z
from ..model.kinematics import (
    model_base,
    model_segment_frames,
    model_segment_transform,
    model_tendon_lengths,
    pose_error,
)
from ..model.lie import rotation_log, so3_right_jacobian_inverse
from ..model.limits import clip_to_limits, project_z
from ..model.rotations import matrix_from_wxyz, wxyz_from_matrix
from ..stages.banded_lm import ChainResidual, banded_lm_solve
from ..stages.lm import LMConfig, lm_solve
from ..stages.sequence import smoothest_choice
from ..world import Scene, load_scene, scene_arrays
from ..world.clearance import SceneArrays, body_gap_tolerance
from ..world.verdict import VIOLATION_TOLERANCE
from ._result import ResultFileError, ResultIO, array, as_float, num, nums, write_series_csv
from ._timing import StageTiming
from .ik import IKConfig, IKSolver, validate_targets
from .paths import ReferencePath, load_path
from .trajectory import (
    _groups_from,
    _has_clearance,
    controller_columns,
    describe_polish,
    tendon_names,
    verify_trajectory,
)

FOLLOW_IK = IKConfig(seeds_per_target=8, refine_iterations=10)
"""Stage 1's default IK settings: fewer seeds and refinement iterations than a plain IK
solve, since the continuation chains and stage 2 finish the job. Measured on
square/sine/icra (tdcr3): 10 refinement iterations gave the same final errors as 30 and
saved two LM calls (0.1–0.2 s per path)."""


@dataclass(frozen=True)
class FollowConfig:
    """Settings of the path follower. Defaults measured on tdcr3 with the bundled
    square/sine/icra paths in their ``follow_*`` scenes (README)."""

    iterations: int = 40
    """Most LM iterations of stage 2 (it stops earlier once the cost stalls)."""
    refine_stall_tolerance: float = 1e-5
    """Stage 2 stops once an accepted step lowers the cost by less than this fraction.
    Measured on square/sine/icra (150 waypoints): 1e-7 ran 13/40/40 iterations, 1e-5
    1/12/33 with the same final cost and tracking errors (the rest is float32 noise)."""
    tracking_weight: float = 1.0
    """Overall weight of the tracking residuals (multiplies the next two)."""
    position_weight: float = 1.0
    """Weight of the translation part of the pose error (per m²)."""
    rotation_weight: float = 1.0
    """Weight of the rotation part of the pose error (per rad²)."""
    smoothness_weight: float = 1e-6
    """Weight of the squared joint-space steps ‖zₜ₊₁ − zₜ‖² (per rad², m²): only breaks
    ties where the tip pose leaves the body free; large values cost tracking accuracy."""
    clearance_weight: float = 1e4
    """Penalty weight of a clearance shortfall (per m²) at waypoints and check points."""
    tendon_weight: float = 10.0
    """Penalty weight of a relative tendon speed/acceleration overshoot (dimensionless)."""
    tendon_limit_fraction: float = 0.95
    """The LM stage aims for this fraction of the tendon limits, so that a penalty
    answer's small overshoot still lies inside the real limits."""
    safety_margin: float = 0.002
    """δ, metres: the clearance every answer must keep, as python-fcl measures it on the
    capsule body (the optimisers add ``world.clearance.body_gap_tolerance``)."""
    interpolation_checks: int = 0
    """Clearance check points inside each interval for the optimiser (1: the midpoint).
    0 by default: the waypoints of a path are dense (the bundled paths move the tip
    ~2.7 cm per step), so the waypoints' margin covers the motion between them; the
    verification checks the motion itself either way."""
    verify_samples: int = 4
    """The verification splits every interval into this many pieces (python-fcl at each)."""
    position_tolerance_mm: float = 5.0
    """A waypoint is reached when its tip position error is at most this, millimetres..."""
    rotation_tolerance_deg: float = 1.0
    """...and its tip rotation error at most this, degrees."""
    ik: IKConfig = FOLLOW_IK
    """Stage 1's per-waypoint IK (``IKSolver.candidates``): its ``beam_width`` is the
    number of distinct answers per waypoint among which the sequence is chosen, and
    candidates with a residual norm (pose error, m/rad, plus clearance penalty) at or
    above its ``success_tolerance`` are used only where a waypoint has no better one.
    Its ``safety_margin``, ``dtype`` and ``seed`` are replaced by this config's."""
    continuation_iterations: int = 6
    """Stage 1: LM iterations per waypoint of the continuation chains that carry an IK
    branch across waypoints where the independent per-waypoint IK missed it."""
    continuation_rounds: int = 2
    """Stage 1: rounds of (find the jumps of the chosen sequence, continue the branches on
    both sides of each, choose again)."""
    max_jumps: int = 4
    """Stage 1: most jumps continued per round (the largest first)."""
    bridge_window: int = 40
    """Stage 1: waypoints each jump-bridging continuation chain walks (from the jump
    outward). Measured on icra (150 waypoints): whole-path chains took 1.3 s per round
    and bridged nothing the windowed ones did not."""
    ik_stride: int = 10
    """Stage 1: the full IK runs on every ``ik_stride``-th trackable waypoint (and the
    last); the waypoints between are reached by continuation from both neighbouring
    anchors (``PathFollower.waypoint_candidates``). 1: IK on every waypoint."""
    dtype: str = "float32"
    """JAX dtype of the batched stages ("float64" needs jax_enable_x64)."""
    seed: int = 0
    """Seed of the IK seed pool."""

    def __post_init__(self) -> None:
        if self.iterations < 0 or self.verify_samples < 1 or self.interpolation_checks < 0:
            raise ValueError("iterations ≥ 0, verify_samples ≥ 1 and interpolation_checks ≥ 0")
        if not 0.0 < self.tendon_limit_fraction <= 1.0:
            raise ValueError(f"tendon_limit_fraction must be in (0, 1], got "
                             f"{self.tendon_limit_fraction}")
        weights = (self.tracking_weight, self.position_weight, self.rotation_weight,
                   self.smoothness_weight, self.clearance_weight, self.tendon_weight)
        if min(weights) < 0:
            raise ValueError("weights must not be negative")

    def ik_config(self) -> IKConfig:
        """The stage-1 ``IKConfig``: ``ik`` with this config's margin, dtype and seed."""
        return replace(self.ik, safety_margin=self.safety_margin, dtype=self.dtype,
                       seed=self.seed)


# ================================================================ per-waypoint Jacobians
#
# The LM needs, per waypoint, a 6 × 3n tracking Jacobian and a G × 3n clearance Jacobian.
# Pushing 3n tangents through the model's entry-by-entry code costs thousands of small
# XLA operations per call; here the values come from the same model functions
# (``model_segment_transform``, ``model_base``) evaluated on whole arrays (one 3 × 3
# matrix product per segment), the derivatives from the model's closed forms
# (``model.derivatives``), and the residuals get their Jacobians from the primal alone
# (``jax.custom_jvp``), so the banded LM's forward-mode pass over a window costs one
# matrix product.


def _stack_transform(transform: Any, dtype: Any) -> tuple[jax.Array, jax.Array]:
    # The barrier stops XLA's fusion from recomputing the entries in every consumer
    # (as ``Ops.materialize`` in the model; measured 5–10× here).
    rot, pos = jax.lax.optimization_barrier(transform)
    rot = jnp.stack(jnp.broadcast_arrays(*rot), axis=-1).astype(dtype)
    pos = jnp.stack(jnp.broadcast_arrays(*pos), axis=-1).astype(dtype)
    return rot.reshape(rot.shape[:-1] + (3, 3)), pos


def waypoint_kinematics(robot: Robot, z: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Tip rotation (3, 3), tip position (3,) m and body-sphere centres (N, 3) m of one
    bending-vector configuration z (3n,): the model's kinematics (``model_segment_frames``,
    ``world.clearance._centres`` order: the base, then ``points_per_segment`` points per
    segment) evaluated in array form."""
    dtype = z.dtype
    k = robot.points_per_segment
    fractions = jnp.arange(1, k + 1, dtype=dtype) / k
    rot, pos = _stack_transform(model_base(robot), dtype)
    centres = [pos[None]]
    for i in range(robot.n_segments):
        ux, uy, length = z[3 * i], z[3 * i + 1], z[3 * i + 2]
        _, points = _stack_transform(model_segment_transform(
            JAX, ux * fractions, uy * fractions, length * fractions), dtype)
        centres.append(pos + points @ rot.T)
        local_rot, local_pos = _stack_transform(model_segment_transform(JAX, ux, uy, length),
                                                dtype)
        rot, pos = rot @ local_rot, pos + rot @ local_pos
    return rot, pos, jnp.concatenate(centres)


def waypoint_jacobians(robot: Robot, z: jax.Array) -> dict[str, jax.Array]:
    """``waypoint_kinematics`` and its closed-form derivatives (``model.derivatives``) for
    one z (3n,). Returns ``rotation`` (3, 3), ``position`` (3,), ``centres`` (N, 3),
    ``d_position`` (3, 3n), ``body_rates`` (3, 3n) (Rᵀ∂R/∂z_k as vectors) and
    ``d_centres`` (N, 3, 3n)."""
    kin = kinematics_jacobians_z(robot, z)
    base = jnp.asarray(robot.base_position, z.dtype)[None]
    return {"rotation": kin.rotation, "position": kin.position,
            "centres": jnp.concatenate([base, kin.points]),
            "d_position": kin.jacobian[:3], "body_rates": kin.rotation.T @ kin.jacobian[3:],
            "d_centres": jnp.concatenate([jnp.zeros((1, 3, robot.dof), z.dtype),
                                          kin.d_points])}


def _tracking_from(rot: jax.Array, pos: jax.Array, target: Any) -> jax.Array:
    target_position, target_rotation, _ = target
    error = target_rotation.reshape(3, 3).T @ rot
    return jnp.concatenate([pos - target_position, rotation_log(error)])


def _tracking_jacobian(kin: dict[str, jax.Array], error: jax.Array) -> jax.Array:
    """(6, d) Jacobian of ``tracking_error`` from ``waypoint_jacobians`` and the error."""
    return jnp.concatenate([kin["d_position"],
                            so3_right_jacobian_inverse(error[3:]) @ kin["body_rates"]])


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def tracking_error(robot: Robot, z: jax.Array, target: Any) -> jax.Array:
    """The tracking error of one waypoint z (3n,): the tip position minus the reference
    position (3,) m, then log(R_refᵀ·R_tip) (3,) rad. Their norms are the reported
    position and rotation errors. ``target`` = (position (3,), rotation (9,) row major,
    tracking switch); only z is differentiated."""
    rot, pos, _ = waypoint_kinematics(robot, z)
    return _tracking_from(rot, pos, target)


@tracking_error.defjvp
def _tracking_error_jvp(robot: Robot, primals: tuple, tangents: tuple) -> tuple:
    z, target = primals
    z_dot = tangents[0]
    kin = waypoint_jacobians(robot, z)
    value = _tracking_from(kin["rotation"], kin["position"], target)
    return value, _tracking_jacobian(kin, value) @ z_dot


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def clearance_groups(robot: Robot, margin: float, arrays: SceneArrays | None,
                     z: jax.Array) -> jax.Array:
    """Grouped clearance shortfalls (G,) m of one configuration z (3n,) below the sphere
    margin (m); differentiable in z with a Jacobian built from the primal."""
    return _groups_from(robot, margin, arrays, waypoint_kinematics(robot, z)[2], None)[0]


@clearance_groups.defjvp
def _clearance_groups_jvp(robot: Robot, margin: float, primals: tuple,
                          tangents: tuple) -> tuple:
    arrays, z = primals
    z_dot = tangents[1]
    kin = waypoint_jacobians(robot, z)
    values, jac = _groups_from(robot, margin, arrays, kin["centres"], kin["d_centres"])
    return values, jac @ z_dot


# ================================================================ residuals


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def waypoint_residual(robot: Robot, margin: float, z: jax.Array, target: Any,
                      arrays: SceneArrays | None) -> jax.Array:
    """``tracking_error`` (6,) then ``clearance_groups`` (G,) of one waypoint z (3n,),
    sharing one kinematics Jacobian (the LM's per-waypoint term)."""
    rot, pos, centres = waypoint_kinematics(robot, z)
    out = [_tracking_from(rot, pos, target)]
    if _has_clearance(robot, arrays):
        out.append(_groups_from(robot, margin, arrays, centres, None)[0])
    return jnp.concatenate(out)


@waypoint_residual.defjvp
def _waypoint_residual_jvp(robot: Robot, margin: float, primals: tuple,
                           tangents: tuple) -> tuple:
    z, target, arrays = primals
    z_dot = tangents[0]
    kin = waypoint_jacobians(robot, z)
    error = _tracking_from(kin["rotation"], kin["position"], target)
    values, jac = [error], [_tracking_jacobian(kin, error)]
    if _has_clearance(robot, arrays):
        groups, groups_jac = _groups_from(robot, margin, arrays, kin["centres"],
                                          kin["d_centres"])
        values.append(groups)
        jac.append(groups_jac)
    return jnp.concatenate(values), jnp.concatenate(jac) @ z_dot


def _lengths(robot: Robot, z: jax.Array) -> jax.Array:
    """Tendon lengths (n_tendons,) m of one configuration z (linear in z)."""
    values = model_tendon_lengths(JAX, robot, [z[i] for i in range(robot.dof)])
    return jnp.stack(jnp.broadcast_arrays(*values)).astype(z.dtype)


def follow_unary(robot: Robot, margin: float, weights: tuple[float, float, float],
                 z: jax.Array, target: Any, shared: Any) -> jax.Array:
    """Residuals of one waypoint z (3n,): √w_p·(p_tip − p_ref) (m) and √w_r·log(R_refᵀR_tip)
    (rad) (``tracking_error``), both times the waypoint's tracking switch (1, or 0 for an
    untrackable waypoint), then √w_c·grouped clearance shortfalls (m).

    ``weights`` = (√w_p, √w_r, √w_c); ``target`` = (position (3,), rotation (9,) row
    major, tracking switch ()); ``shared`` = (scene arrays or None, Δt)."""
    sqrt_pos, sqrt_rot, sqrt_clear = weights
    arrays, _ = shared
    track = target[2]
    values = waypoint_residual(robot, margin, z, target, arrays)
    scale = jnp.concatenate([jnp.full(3, sqrt_pos), jnp.full(3, sqrt_rot)]).astype(z.dtype)
    return jnp.concatenate([track * scale * values[:6], sqrt_clear * values[6:]])


def follow_pair(robot: Robot, margin: float, checks: int, weights: tuple[float, float, float],
                limit_fraction: float, z_a: jax.Array, z_b: jax.Array, target: Any,
                shared: Any) -> jax.Array:
    """Residuals of one interval (z_a → z_b): √w_s·(z_b − z_a) (rad, m); √w_c·grouped
    clearance shortfalls (m) at ``checks`` evenly spaced points inside the interval;
    √w_t·max(0, |Δℓ/Δt|/(f·v_max) − 1) per tendon (dimensionless).

    ``weights`` = (√w_s, √w_c, √w_t); f = ``limit_fraction``."""
    sqrt_smooth, sqrt_clear, sqrt_tendon = weights
    arrays, dt = shared
    step = z_b - z_a
    out = [sqrt_smooth * step]
    if checks and _has_clearance(robot, arrays):
        for c in range(1, checks + 1):
            out.append(sqrt_clear * clearance_groups(robot, margin, arrays,
                                                     z_a + (c / (checks + 1)) * step))
    if math.isfinite(robot.tendon_speed_max):
        speed = (_lengths(robot, z_b) - _lengths(robot, z_a)) / dt
        over = jnp.abs(speed) / (limit_fraction * robot.tendon_speed_max) - 1.0
        out.append(sqrt_tendon * jnp.maximum(over, 0.0))
    return jnp.concatenate(out)


def follow_triple(robot: Robot, sqrt_tendon: float, limit_fraction: float, z_a: jax.Array,
                  z_b: jax.Array, z_c: jax.Array, target: Any, shared: Any) -> jax.Array:
    """√w_t·max(0, |Δ²ℓ/Δt²|/(f·a_max) − 1) per tendon at the middle waypoint z_b."""
    _, dt = shared
    accel = (_lengths(robot, z_c) - 2.0 * _lengths(robot, z_b) + _lengths(robot, z_a)) / (dt * dt)
    over = jnp.abs(accel) / (limit_fraction * robot.tendon_accel_max) - 1.0
    return sqrt_tendon * jnp.maximum(over, 0.0)


def follow_terms(robot: Robot, margin: float, config: FollowConfig) -> ChainResidual:
    """The path-following residual as window terms for ``stages.banded_lm``."""
    sqrt = math.sqrt
    track = config.tracking_weight
    unary = partial(follow_unary, robot, float(margin),
                    (sqrt(track * config.position_weight), sqrt(track * config.rotation_weight),
                     sqrt(config.clearance_weight)))
    pair = partial(follow_pair, robot, float(margin), config.interpolation_checks,
                   (sqrt(config.smoothness_weight), sqrt(config.clearance_weight),
                    sqrt(config.tendon_weight)), config.tendon_limit_fraction)
    triple = (partial(follow_triple, robot, sqrt(config.tendon_weight),
                      config.tendon_limit_fraction)
              if math.isfinite(robot.tendon_accel_max) else None)
    return ChainResidual(unary, pair, triple)


def _project_chain(robot: Robot, z: jax.Array) -> jax.Array:
    """``project_z`` on every waypoint of a (T, 3n) chain."""
    return project_z(robot, z)


def _continue_chains(robot: Robot, margin: float, weights: tuple[float, float, float],
                     iterations: int, z_start: jax.Array, index: jax.Array, active: jax.Array,
                     positions: jax.Array, rotations: jax.Array, track: jax.Array, shared: Any,
                     free: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Numerical continuation of C IK answers along the path (stage 1's branch keeper).

    Chain c starts at ``z_start[c]`` (3n,) and visits the waypoints ``index[c, 0]``,
    ``index[c, 1]``, … (C, L) in turn, ``iterations`` LM steps per waypoint from the
    previous waypoint's answer, so it stays on one branch of the IK solutions; where
    ``active[c, τ]`` (C, L) is False the chain holds still. Returns z (C, L, 3n) and the
    penalised residual norms (C, L) at every visited waypoint (pose error m/rad, plus
    √w_c times the clearance shortfall, m)."""
    residual = partial(follow_unary, robot, margin, weights)
    project = partial(project_z, robot)
    config = LMConfig(cost_tolerance=1e-14)

    def step(z: jax.Array, tau: jax.Array) -> tuple[jax.Array, tuple]:
        at = index[:, tau]
        target = (positions[at], rotations[at], track[at])
        solved, cost, _ = lm_solve(residual, project, z, target, shared, free,
                                   jnp.int32(iterations), config=config)
        z_out = jnp.where(active[:, tau, None], solved, z)
        return z_out, (z_out, jnp.sqrt(2.0 * cost))

    _, (z, err) = jax.lax.scan(step, z_start, jnp.arange(index.shape[1]))
    return jnp.swapaxes(z, 0, 1), jnp.swapaxes(err, 0, 1)


def _pad_chains(starts: np.ndarray, index: np.ndarray, active: np.ndarray,
                column: np.ndarray) -> tuple[np.ndarray, ...]:
    """C chains (starts (C, 3n); index, active (C, L); table column (C,)) padded with
    inactive ones to a multiple of 16, so that few chain programs are compiled (the
    anchors' 90 chains of a 150-waypoint path run as 96, not 128)."""
    extra = 16 * -(-len(starts) // 16) - len(starts)
    return (np.concatenate([starts, np.repeat(starts[:1], extra, 0)]),
            np.concatenate([index, np.zeros((extra, index.shape[1]), int)]),
            np.concatenate([active, np.zeros((extra, index.shape[1]), bool)]),
            np.concatenate([column, np.full(extra, column[-1] if len(column) else 0)]))


def _extend_table(extra: int, table_z: jax.Array, table_err: jax.Array, chain_z: jax.Array,
                  chain_err: jax.Array, index: jax.Array, active: jax.Array,
                  column: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Stage 1's candidate table (R, K, 3n) z and (R, K) residual norms with ``extra``
    empty columns appended and the chains' answers written in: chain c's answer at its
    τ-th waypoint goes to row ``index[c, τ]``, column ``column[c]``, where
    ``active[c, τ]``; a residual that is not finite counts as no answer (inf)."""
    r = table_z.shape[0]
    dtype = chain_z.dtype
    table_z = jnp.concatenate([table_z.astype(dtype),
                               jnp.zeros((r, extra, table_z.shape[2]), dtype)], axis=1)
    table_err = jnp.concatenate([table_err.astype(dtype),
                                 jnp.full((r, extra), jnp.inf, dtype)], axis=1)
    rows = jnp.where(active, index, r)                      # row r: dropped
    columns = jnp.broadcast_to(column[:, None], index.shape)
    chain_err = jnp.where(active & jnp.isfinite(chain_err), chain_err, jnp.inf)
    return (table_z.at[rows, columns].set(chain_z, mode="drop"),
            table_err.at[rows, columns].set(chain_err, mode="drop"))


def _extend_and_choose(robot: Robot, extra: int, table_z: jax.Array, table_err: jax.Array,
                       chain_z: jax.Array, chain_err: jax.Array, index: jax.Array,
                       active: jax.Array, column: jax.Array, tolerance: jax.Array,
                       seconds: jax.Array) -> tuple[jax.Array, ...]:
    """``_extend_table``, then the smoothest sequence through it
    (``stages.sequence.smoothest_choice``) and its tendon speeds, in one device program.

    Returns the table (z, residual norms), the chosen (R, 3n) z and the largest tendon
    speed (R − 1,) m/s of every interval (Δℓ over ``seconds`` (R − 1,) s)."""
    table_z, table_err = _extend_table(extra, table_z, table_err, chain_z, chain_err, index,
                                       active, column)
    choice = smoothest_choice(table_z, table_err, tolerance)
    chosen = table_z[jnp.arange(table_z.shape[0]), choice]
    lengths = jax.vmap(partial(_lengths, robot))(chosen)
    speed = jnp.max(jnp.abs(jnp.diff(lengths, axis=0)), axis=1) / seconds
    return table_z, table_err, chosen, speed


# ================================================================ measures (float64)


def tip_poses(robot: Robot, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tip positions (B, 3) m and rotation matrices (B, 3, 3) of (B, 3n) configurations
    (θ, φ, L), float64 numpy."""
    z = q_to_z_numpy(q)
    rot, pos = model_segment_frames(NUMPY, robot, [z[:, i] for i in range(robot.dof)])[-1]
    position = np.stack(np.broadcast_arrays(*pos), axis=-1).reshape(-1, 3)
    rotation = np.stack(np.broadcast_arrays(*rot), axis=-1).reshape(-1, 3, 3)
    return position, rotation


def tracking_errors(robot: Robot, q: np.ndarray, positions: np.ndarray,
                    wxyz: np.ndarray) -> dict[str, np.ndarray]:
    """Per-waypoint tip pose and its distance to the reference, float64: ``position``
    (T, 3) m, ``wxyz`` (T, 4), ``pose_error`` (T,) (‖log(T_tip⁻¹·T_ref)‖, DESIGN.md §1),
    ``position_error`` (T,) m and ``rotation_error`` (T,) rad (the angle of
    R_tipᵀ·R_ref)."""
    position, rotation = tip_poses(robot, q)
    reference = matrix_from_wxyz(wxyz)
    relative = np.einsum("tji,tjk->tik", rotation, reference)
    cos_angle = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return {"position": position, "wxyz": wxyz_from_matrix(rotation),
            "pose_error": pose_error(position, rotation, positions, reference),
            "position_error": np.linalg.norm(position - positions, axis=1),
            "rotation_error": np.arccos(cos_angle)}


def unreached_stretches(reached: np.ndarray) -> list[tuple[int, int]]:
    """Runs of consecutive unreached waypoints as (first, last) indices, inclusive."""
    out, start = [], None
    for i, ok in enumerate(np.asarray(reached, bool)):
        if not ok and start is None:
            start = i
        elif ok and start is not None:
            out.append((start, i - 1))
            start = None
    if start is not None:
        out.append((start, len(reached) - 1))
    return out


# ================================================================ the result


FollowTiming = StageTiming
"""Seconds per stage of one ``PathFollower.follow`` call."""


@dataclass
class FollowResult(ResultIO):
    """A followed path. Units: rad, m, s (millimetre / degree figures in ``summary``)."""

    kind: ClassVar[str] = "follow"

    robot: Robot
    path: ReferencePath
    """The reference (positions m, unit quaternions, Δt s)."""
    q: np.ndarray
    """(T, 3n) configurations θ, φ, L, one per waypoint."""
    position: np.ndarray
    """(T, 3) tip positions reached, m."""
    wxyz: np.ndarray
    """(T, 4) tip orientations reached, unit quaternions (w, x, y, z)."""
    pose_error: np.ndarray
    """(T,) ‖log(T_tip⁻¹·T_ref)‖ (the IK success metric, m and rad mixed)."""
    position_error: np.ndarray
    """(T,) ‖p_tip − p_ref‖, m."""
    rotation_error: np.ndarray
    """(T,) rotation angle between the tip and reference frames, rad."""
    reached: np.ndarray
    """(T,) bool: position error ≤ ``FollowConfig.position_tolerance_mm`` (default 5 mm)
    and rotation error ≤ ``FollowConfig.rotation_tolerance_deg`` (default 1°)."""
    tendon_lengths: np.ndarray
    """(T, n_tendons) tendon lengths at the waypoints, m."""
    tendon_speed: float
    """Largest |tendon speed| by finite differences, m/s."""
    tendon_accel: float
    """Largest |tendon acceleration| by finite differences, m/s²."""
    collision_free: bool
    """python-fcl: no contact anywhere along the interpolated motion."""
    min_clearance: float
    """Smallest python-fcl distance along the motion, m (+inf with nothing to hit)."""
    max_violation: float
    """Largest of ``violations``."""
    violations: dict[str, float]
    """Largest violation per family (``verify_trajectory``): clearance (m below δ),
    limits (rad or m), tendon_speed (m/s), tendon_accel (m/s²)."""
    success: bool
    """Every waypoint reached and every violation ≤ 1e-6 (``verify_trajectory``, the one
    verdict of ``world.verdict``): clearance ≥ δ along the motion, limits, tendon
    limits."""
    reason: str
    """"" on success, else why not (unreached waypoints, collision, limits)."""
    stage: str
    """What produced ``q``: "refine", "polish", "refine (polish failed: <why>)", or in
    exact mode "refine (feasible: polish not needed)" / "refine (feasible; the polished
    answer tracked worse)" when the LM answer already keeps every constraint (max
    violation ≤ 1e-6 by the independent checks)."""
    timing: StageTiming = field(default_factory=StageTiming)
    """Seconds per stage: compile, explore, refine, polish, verify (and ``total``)."""
    scene_name: str | None = None
    """The scene's name, or None without obstacles."""
    safety_margin: float = 0.002
    """δ, metres, used by the verdict."""
    tendon_displacements: np.ndarray | None = None
    """(T, n_tendons) motor commands at the waypoints, m (positive = pulled), when the
    robot file has an ``actuation`` block (``model.actuation``); else None."""

    def __post_init__(self) -> None:
        if self.tendon_displacements is None:
            self.tendon_displacements = planned_displacements(self.robot, self.q)

    @property
    def dt(self) -> float:
        """Seconds between waypoints."""
        return float(self.path.dt)

    @property
    def times(self) -> np.ndarray:
        """(T,) time of each waypoint, seconds."""
        return np.arange(len(self.q)) * self.dt

    def summary(self) -> dict[str, Any]:
        """Tracking statistics: mean/std/max position error (mm), mean/max rotation error
        (degrees), reached count, unreached waypoint indices and stretches."""
        pos, rot = 1e3 * self.position_error, np.degrees(self.rotation_error)
        return {
            "waypoints": len(self.q),
            "mean_position_error_mm": float(np.mean(pos)),
            "std_position_error_mm": float(np.std(pos)),
            "max_position_error_mm": float(np.max(pos)),
            "mean_rotation_error_deg": float(np.mean(rot)),
            "max_rotation_error_deg": float(np.max(rot)),
            "reached": int(np.count_nonzero(self.reached)),
            "unreached": np.flatnonzero(~self.reached).tolist(),
            "unreached_stretches": [list(s) for s in unreached_stretches(self.reached)],
        }

    def _fields_dict(self) -> dict[str, Any]:
        return {
            "path": self.path.to_dict(),
            "scene": self.scene_name,
            "success": bool(self.success),
            "reason": self.reason or None,
            "stage": self.stage,
            "dt": self.dt,
            "times": self.times.tolist(),
            "q": self.q.tolist(),
            "position": self.position.tolist(),
            "wxyz": self.wxyz.tolist(),
            "pose_error": nums(self.pose_error),
            "position_error": nums(self.position_error),
            "rotation_error": nums(self.rotation_error),
            "reached": self.reached.tolist(),
            "tendon_names": tendon_names(self.robot),
            "tendon_lengths": self.tendon_lengths.tolist(),
            **({"tendon_displacements": self.tendon_displacements.tolist()}
               if self.tendon_displacements is not None else {}),
            "tendon_speed": num(self.tendon_speed),
            "tendon_accel": num(self.tendon_accel),
            "collision_free": bool(self.collision_free),
            "min_clearance": num(self.min_clearance),
            "safety_margin": self.safety_margin,
            "max_violation": num(self.max_violation),
            "violations": {k: num(v) for k, v in self.violations.items()},
            "summary": self.summary(),
            "timing": self.timing.as_dict(),
        }

    @classmethod
    def _from_fields(cls, data: dict[str, Any], robot: Robot) -> FollowResult:
        path = ReferencePath.from_dict(data["path"], source="path")
        count = len(path)
        return cls(
            robot, path, array(data["q"], robot.dof, "q"), array(data["position"], 3, "position"),
            array(data["wxyz"], 4, "wxyz"), *(array(data[k]) for k in (
                "pose_error", "position_error", "rotation_error")),
            np.array(data["reached"], dtype=bool),
            array(data["tendon_lengths"], robot.n_tendons, "tendon_lengths"),
            as_float(data["tendon_speed"]), as_float(data["tendon_accel"]),
            bool(data["collision_free"]), as_float(data["min_clearance"]),
            as_float(data["max_violation"]),
            {k: as_float(v) for k, v in data["violations"].items()},
            success=bool(data["success"]), reason=data["reason"] or "", stage=data["stage"],
            timing=StageTiming.from_dict(data["timing"]), scene_name=data["scene"],
            safety_margin=float(data["safety_margin"]),
        )._checked(count)

    def _checked(self, count: int) -> FollowResult:
        """This result, after checking that every per-waypoint field has ``count`` rows."""
        for name in ("q", "position", "wxyz", "pose_error", "position_error",
                     "rotation_error", "reached", "tendon_lengths"):
            if len(getattr(self, name)) != count:
                raise ResultFileError(f"{name} has {len(getattr(self, name))} rows, the path "
                                      f"{count} waypoints")
        return self

    def save(self, path: str | Path, indent: int | None = 2) -> Path:
        """Write ``to_dict`` as JSON (.json, or any suffix but .npz), or the arrays as a
        numpy .npz by the file's suffix; returns the path."""
        path = Path(path)
        if path.suffix != ".npz":
            return super().save(path, indent)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, q=self.q, times=self.times, dt=self.dt,
                 position=self.position, wxyz=self.wxyz,
                 target_positions=self.path.positions, target_wxyz=self.path.wxyz,
                 pose_error=self.pose_error, position_error=self.position_error,
                 rotation_error=self.rotation_error, reached=self.reached,
                 tendon_lengths=self.tendon_lengths, collision_free=self.collision_free,
                 min_clearance=self.min_clearance, max_violation=self.max_violation,
                 success=self.success, stage=self.stage, reason=self.reason)
        return path

    def save_csv(self, path: str | Path) -> Path:
        """The tendon-length series for a controller: ``time_s``, then one column per
        tendon (``trajectory.tendon_names``), lengths in metres, one row per waypoint."""
        return write_series_csv(path, self.times, *controller_columns(
            self.robot, self.tendon_lengths, self.tendon_displacements))


# ================================================================ compile-time accounting

_COMPILE = threading.local()


def _on_duration(event: str, duration: float, **_: Any) -> None:
    if event.startswith("/jax/core/compile/") and getattr(_COMPILE, "active", False):
        _COMPILE.seconds += duration


jax.monitoring.register_event_duration_secs_listener(_on_duration)


@contextmanager
def _compile_seconds() -> Any:
    """Collects JAX's tracing/lowering/compile durations inside the block (this thread):
    yields a one-element list that holds the total once the block ends."""
    out = [0.0]
    previous = (getattr(_COMPILE, "active", False), getattr(_COMPILE, "seconds", 0.0))
    _COMPILE.active, _COMPILE.seconds = True, 0.0
    try:
        yield out
    finally:
        out[0] = _COMPILE.seconds
        _COMPILE.active, _COMPILE.seconds = previous[0], previous[1] + out[0]


# ================================================================ the follower


class PathFollower:
    """Path following for one robot in one scene; reuse it across paths (the LM program
    is compiled once per path length, the IK seed pool built once).

    ``follow(path)`` takes a ``ReferencePath``, a bundled path name ("square", "sine",
    "icra") or a path file, and returns a ``FollowResult``.
    """

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | Path | dict | None = None,
                 config: FollowConfig = FollowConfig()) -> None:
        enable_compilation_cache()
        self.robot = load_robot(robot)
        self.scene = load_scene(scene) if scene is not None else None
        self.config = config
        self.dtype = jnp.dtype(config.dtype)
        self.margin = config.safety_margin + body_gap_tolerance(self.robot)
        """The sphere-body clearance (m) the optimisers enforce."""
        self._arrays: SceneArrays | None = (scene_arrays(self.scene, dtype=self.dtype)
                                            if self.scene is not None else None)
        self._terms = follow_terms(self.robot, self.margin, config)
        self._project = partial(_project_chain, self.robot)
        free = np.ones(self.robot.dof)
        free[2::3] = ~self.robot.lengths_fixed()   # a fixed length is not a variable
        self._free = jnp.asarray(free, self.dtype)
        self._compiled: dict[Any, Any] = {}
        self._choose_program = jax.jit(partial(_extend_and_choose, self.robot),
                                       static_argnums=0)
        self._extend = jax.jit(_extend_table, static_argnums=0)
        self._ik: IKSolver | None = None
        self._polishers: dict[int, Any] = {}
        self.last_timing = FollowTiming()

    @property
    def ik_solver(self) -> IKSolver:
        """Stage 1's batched IK solver (built on first use)."""
        if self._ik is None:
            self._ik = IKSolver(self.robot, self.scene, self.config.ik_config())
        return self._ik

    # ------------------------------------------------------------ stage 1
    def initial_sequence(self, positions: np.ndarray, wxyz: np.ndarray,
                         trackable: np.ndarray, dt: float) -> np.ndarray:
        """Stage 1: (T, 3n) configurations (θ, φ, L), one IK answer per trackable waypoint
        chosen for the smallest jumps; untrackable waypoints are interpolated in z between
        their trackable neighbours (the nearest one's at the ends; straight if none).

        The candidates come from ``waypoint_candidates`` (full IK on every
        ``ik_stride``-th waypoint, continuation in between). The IK can still miss the
        branch the neighbours use; then the chosen sequence jumps (a tendon would have to
        move faster than ``tendon_speed_max``). Each such jump is bridged by continuation:
        the answers on both sides are carried across, waypoint by waypoint, and added to
        the candidates before choosing again (``continuation_rounds`` times).

        On the device each round is two programs (the continuation chains; the candidate
        table, the sequence and its tendon speeds) and one read back (the chosen
        sequence and its speeds, to find the jumps)."""
        t = len(positions)
        z = np.zeros((t, self.robot.dof))
        z[:, 2::3] = [0.5 * (s.length_min + s.length_max) for s in self.robot.segments]
        rows = np.flatnonzero(trackable)
        if len(rows):
            positions, wxyz = positions[rows], wxyz[rows]
            seconds = dt * np.diff(rows)
            base, ends, chains = self._anchor_chains(positions, wxyz, dt)
            table = self._choose(base, chains, 0, seconds)
            chosen, speed = jax.device_get(table[2:])
            bridged: set[int] = set()
            for _ in range(self.config.continuation_rounds):
                # An interval bridged once is not bridged again: measured on icra, the
                # one jump that no branch crosses (waypoint 70) was bridged a second time
                # from the answers the first round's chains brought, with the same final
                # answer (0.1 s; 1.3 s per round with whole-path chains).
                jumps = [i for i in self._jumps(speed) if i not in bridged]
                if not jumps:
                    break
                bridged |= set(jumps)
                width = table[0].shape[1]
                chains = self._bridge(chosen, np.array(jumps), positions, wxyz, dt, ends,
                                      width)
                ends = None   # the ends' own answers are carried once
                table = self._choose(table[:2], chains, len(chains[2]), seconds)
                chosen, speed = jax.device_get(table[2:])
            for k in range(self.robot.dof):
                z[:, k] = np.interp(np.arange(t), rows, np.asarray(chosen[:, k], np.float64))
        return z_to_q_numpy(z)

    def waypoint_candidates(self, positions: np.ndarray, wxyz: np.ndarray,
                            dt: float) -> tuple[np.ndarray, np.ndarray]:
        """IK candidates for R trackable waypoints (positions (R, 3) m, wxyz (R, 4)):
        z (R, K, 3n) and penalised residual norms (R, K) (m/rad; inf: no candidate).

        ``IKSolver.candidates`` runs only on the anchors, every ``ik_stride``-th waypoint
        and the last; neighbouring waypoints are close, so each anchor's B answers are
        carried to the next anchor (forward) and the previous one (backward) by
        continuation. Slots: [0, B) the anchors' own IK answers, [B, 2B) the forward
        chains, [2B, 3B) the backward chains (K = 3B; B = K with ``ik_stride`` 1)."""
        base, _, chains = self._anchor_chains(positions, wxyz, dt)
        z, errors = self._extend(0, *base, *chains)
        return np.asarray(z, np.float64), np.asarray(errors, np.float64)

    def _anchor_chains(self, positions: np.ndarray, wxyz: np.ndarray,
                       dt: float) -> tuple[tuple, tuple, tuple]:
        """``waypoint_candidates`` before its table is filled in: the anchors' table
        (z (R, K, 3n), residual norms (R, K), numpy, K = 3B), the first and last
        waypoints' own IK answers ((B, 3n) each, numpy) and the continuation chains on
        the device (z (C, L, 3n), residual norms (C, L), then index, active (C, L) and
        the table column (C,) of every chain, numpy)."""
        r = len(positions)
        stride = max(int(self.config.ik_stride), 1)
        anchors = np.unique(np.r_[np.arange(0, r, stride), r - 1])
        q, err = self.ik_solver.candidates(positions[anchors], wxyz[anchors])
        z_anchor = q_to_z_numpy(q)                                   # (A, B, 3n)
        ends = (z_anchor[0], z_anchor[-1])
        width = z_anchor.shape[1]
        slots = width if len(anchors) == r else 3 * width
        z = np.zeros((r, slots, self.robot.dof))
        errors = np.full((r, slots), np.inf)
        z[anchors, :width], errors[anchors, :width] = z_anchor, err
        # Chain order: (interval between anchors, beam, forward/backward).
        lo, hi = anchors[:-1], anchors[1:]
        tau = np.arange(stride)
        visits = tau < (hi - lo)[:, None]                              # (A − 1, S)
        index = np.where(visits[:, None], np.stack([lo[:, None] + 1 + tau,
                                                    hi[:, None] - 1 - tau], axis=1), 0)
        shape = (len(lo), width, 2)
        index = np.broadcast_to(index[:, None], shape + (stride,)).reshape(-1, stride)
        active = np.broadcast_to(visits[:, None, None], shape + (stride,)).reshape(-1, stride)
        starts = np.stack([z_anchor[:-1], z_anchor[1:]], axis=2).reshape(-1, self.robot.dof)
        column = np.broadcast_to(width * np.arange(1, 3) + np.arange(width)[:, None],
                                 shape).reshape(-1)
        if len(anchors) == r:   # every waypoint has its own IK: nothing to continue
            starts, index, active, column = (x[:0] for x in (starts, index, active, column))
        return (z, errors), ends, self._chains(starts, index, active, column, positions,
                                               wxyz, dt)

    def _chains(self, starts: np.ndarray, index: np.ndarray, active: np.ndarray,
                column: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
                dt: float) -> tuple[Any, ...]:
        """``_continue_chains`` for C chains (starts (C, 3n); index, active (C, L); table
        column (C,)) over the R waypoints (positions (R, 3) m, wxyz (R, 4)), padded by
        ``_pad_chains``: z (C', L, 3n) and residual norms (C', L) on the device (not
        waited for), then index, active and column padded alike. R is padded to a power
        of two (at least 32), so few programs are compiled."""
        starts, index, active, column = _pad_chains(starts, index, active, column)
        padded, length = index.shape
        if padded == 0:
            dtype = self.dtype
            return (np.zeros((0, length, self.robot.dof), dtype), np.zeros((0, length), dtype),
                    index, active, column)
        # The waypoint tables are padded too (never visited: ``index`` < R).
        rows = max(32, 1 << (len(positions) - 1).bit_length())
        positions = np.concatenate([positions, np.repeat(positions[:1], rows - len(positions), 0)])
        rotations = matrix_from_wxyz(wxyz).reshape(-1, 9)
        rotations = np.concatenate([rotations, np.repeat(rotations[:1], rows - len(rotations), 0)])
        # numpy in the program's dtypes: jnp.asarray would launch one conversion each.
        dtype = self.dtype
        args = (starts.astype(dtype), index.astype(np.int32), active,
                positions.astype(dtype), rotations.astype(dtype), np.ones(rows, dtype),
                (self._arrays, np.asarray(dt, dtype)), self._free)
        key = ("chains", padded, length, rows)
        if key not in self._compiled:
            weights = (1.0, 1.0, math.sqrt(self.config.ik.clearance_weight))
            fn = partial(_continue_chains, self.robot, float(self.margin), weights,
                         self.config.continuation_iterations)
            # Chains are independent: split over the devices like the IK's LM (measured:
            # unsplit, the anchors' 96 chains ran on one core).
            program = split_over_devices(fn, (True,) * 3 + (False,) * 5, padded, outputs=2)
            self._compiled[key] = program.lower(*args).compile()
        z, err = self._compiled[key](*args)
        return z, err, index, active, column

    def _choose(self, table: tuple, chains: tuple, extra: int,
                seconds: np.ndarray) -> tuple[Any, ...]:
        """``_extend_and_choose`` on the device (not waited for): the table (z, residual
        norms) with ``extra`` columns for the chains, the chosen (R, 3n) z and the
        tendon speed (R − 1,) m/s of every interval."""
        tolerance = np.asarray(self.config.ik.success_tolerance, self.dtype)
        return self._choose_program(extra, *table, *chains, tolerance,
                                    np.asarray(seconds, self.dtype))

    def _jumps(self, speed: np.ndarray) -> np.ndarray:
        """Intervals (indices i: between rows i and i+1) of a sequence whose tendon speed
        (R − 1,) m/s exceeds the limit, the largest first (at most ``max_jumps``)."""
        limit = self.robot.tendon_speed_max if math.isfinite(self.robot.tendon_speed_max) \
            else np.inf
        speed = np.asarray(speed, np.float64)
        bad = np.flatnonzero(speed > limit)
        return bad[np.argsort(-speed[bad], kind="stable")][: self.config.max_jumps]

    def _bridge(self, z: np.ndarray, jumps: np.ndarray, positions: np.ndarray,
                wxyz: np.ndarray, dt: float, ends: tuple[np.ndarray, np.ndarray] | None,
                width: int) -> tuple[Any, ...]:
        """Continuation chains (``_chains``' output) into new table columns from
        ``width`` on: from each jump's left answer (of the (R, 3n) sequence z) forward
        and its right answer backward, and (``ends``: the (B, 3n) candidates of the first
        and last waypoints) from every first candidate forward and every last one
        backward; each chain walks at most ``bridge_window`` waypoints (one compiled
        shape whatever the jump's place)."""
        r = len(z)
        window = max(int(self.config.bridge_window), 1)
        first_row = np.stack([jumps, jumps + 1], axis=1).reshape(-1)
        starts = z[first_row]
        if ends is not None:
            pairs = np.stack([ends[0], ends[1]], axis=1)               # (B, 2, 3n)
            starts = np.concatenate([pairs.reshape(-1, z.shape[1]), starts])
            first_row = np.concatenate([np.tile([0, r - 1], len(ends[0])), first_row])
        forward = np.arange(len(first_row)) % 2 == 0
        tau = np.arange(window)
        index = np.where(forward[:, None], first_row[:, None] + tau, first_row[:, None] - tau)
        active = (index >= 0) & (index < r)
        return self._chains(starts, np.clip(index, 0, r - 1), active,
                            width + np.arange(len(starts)), positions, wxyz, dt)

    # ------------------------------------------------------------ stage 2
    def refine(self, q0: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
               trackable: np.ndarray, dt: float) -> tuple[np.ndarray, float, int]:
        """Stage 2: the banded LM over all waypoints from (T, 3n) q0. Returns q (T, 3n),
        the final penalised cost ½‖r‖² and the iterations used."""
        args = self._lm_args(q0, positions, wxyz, trackable, dt)
        t = len(q0)
        if t not in self._compiled:
            config = LMConfig(cost_tolerance=0.0,
                              stall_tolerance=self.config.refine_stall_tolerance)
            solve = partial(banded_lm_solve, self._terms, self._project, config=config)
            self._compiled[t] = jax.jit(solve).lower(*args).compile()
        z, cost, iterations = jax.device_get(self._compiled[t](*args))
        q = z_to_q_numpy(z)
        return clip_to_limits(self.robot, q), float(cost), int(iterations)

    def _lm_args(self, q0: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
                 trackable: np.ndarray, dt: float) -> tuple:
        dtype = self.dtype
        safe_positions = np.where(trackable[:, None], positions, 0.0)
        safe_rotations = np.where(trackable[:, None, None], matrix_from_wxyz(
            np.where(trackable[:, None], wxyz, [1.0, 0.0, 0.0, 0.0])), np.eye(3))
        # numpy in the program's dtypes: jnp.asarray would launch one conversion each.
        params = (safe_positions.astype(dtype), safe_rotations.reshape(-1, 9).astype(dtype),
                  trackable.astype(dtype))
        z0 = q_to_z_numpy(q0).astype(dtype)
        shared = (self._arrays, np.asarray(dt, dtype))
        return z0, params, shared, self._free, np.int32(self.config.iterations)

    # ------------------------------------------------------------ verification
    def verify(self, q: np.ndarray, path: ReferencePath, dt: float) -> dict[str, Any]:
        """Float64 verdict on (T, 3n) q against the reference: ``verify_trajectory``'s
        dict plus ``tracking_errors``' arrays and ``reached``."""
        verdict = verify_trajectory(self.robot, self.scene, q, dt, self.config.safety_margin,
                                    self.config.verify_samples)
        verdict.update(tracking_errors(self.robot, q, path.positions, path.wxyz))
        verdict["reached"] = ((1e3 * verdict["position_error"]
                               <= self.config.position_tolerance_mm)
                              & (np.degrees(verdict["rotation_error"])
                                 <= self.config.rotation_tolerance_deg))
        return verdict

    def _result(self, q: np.ndarray, path: ReferencePath, verdict: dict[str, Any], stage: str,
                why_untrackable: dict[int, str]) -> FollowResult:
        reached = np.asarray(verdict["reached"], bool)
        reasons = []
        unreached = np.flatnonzero(~reached)
        if len(unreached):
            stretches = ", ".join(f"{a}" if a == b else f"{a}–{b}"
                                  for a, b in unreached_stretches(reached))
            reasons.append(f"{len(unreached)} of {len(q)} waypoints not reached (waypoints "
                           f"{stretches})")
            for i, why in sorted(why_untrackable.items())[:3]:
                reasons.append(f"waypoint {i}: {why}")
        if verdict["reason"]:
            reasons.append(verdict["reason"])
        return FollowResult(
            self.robot, path, q, verdict["position"], verdict["wxyz"], verdict["pose_error"],
            verdict["position_error"], verdict["rotation_error"], reached,
            verdict["tendon_lengths"], verdict["tendon_speed"], verdict["tendon_accel"],
            bool(verdict["collision_free"]), float(verdict["min_clearance"]),
            float(verdict["max_violation"]), dict(verdict["violations"]),
            success=bool(verdict["success"]) and bool(reached.all()),
            reason="; ".join(reasons), stage=stage,
            scene_name=self.scene.name if self.scene is not None else None,
            safety_margin=self.config.safety_margin)

    # ------------------------------------------------------------ the solve
    def follow(self, path: ReferencePath | str | Path, exact: bool = False,
               progress: bool = False, dt: float | None = None) -> FollowResult:
        """Follow a reference path.

        Args:
            path: a ``ReferencePath``, a bundled name ("square", "sine", "icra") or a
                path file (``tasks.paths`` format).
            exact: polish with Ipopt, the constraints as constraints, minimising the
                tracking error (``stages.polish_trajectory``); a failed or rejected
                polish returns the LM answer with ``stage`` "refine (polish failed: …)".
            progress: print the polish stage's progress to stderr.
            dt: seconds between waypoints (default: the path's own ``dt``).

        Raises:
            ValueError: a reference pose that is not finite or not a unit quaternion,
                a non-positive ``dt``, or fewer than 2 waypoints.
        """
        path = load_path(path)
        dt = float(path.dt if dt is None else dt)
        if not dt > 0 or not math.isfinite(dt):
            raise ValueError(f"dt must be a positive number of seconds, got {dt}")
        positions = np.asarray(path.positions, dtype=np.float64)
        wxyz = np.asarray(path.wxyz, dtype=np.float64)
        if len(positions) < 2:
            raise ValueError(f"a path needs at least 2 waypoints, got {len(positions)}")
        bad = np.flatnonzero(~np.isfinite(positions).all(1) | ~np.isfinite(wxyz).all(1))
        if len(bad):
            raise ValueError(f"waypoint {bad[0]}: the reference pose is not finite")
        norms = np.linalg.norm(wxyz, axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-6)
        if len(bad):
            raise ValueError(f"waypoint {bad[0]}: wxyz is not a unit quaternion "
                             f"(norm {norms[bad[0]]:.6g})")
        if dt != path.dt:
            path = ReferencePath(path.name, positions, wxyz, dt, path.pen_down)
        _, _, reasons = validate_targets(self.robot, positions, wxyz)
        trackable = np.array([not r for r in reasons], bool)
        why = {i: r for i, r in enumerate(reasons) if r}

        timing = FollowTiming()
        self.last_timing = timing
        t0 = time.perf_counter()
        with _compile_seconds() as compiled:
            q0 = self.initial_sequence(positions, wxyz, trackable, dt)
        timing.compile += compiled[0]
        timing.explore = time.perf_counter() - t0 - compiled[0]
        t1 = time.perf_counter()
        with _compile_seconds() as compiled:
            q, _, _ = self.refine(q0, positions, wxyz, trackable, dt)
        timing.compile += compiled[0]
        timing.refine = time.perf_counter() - t1 - compiled[0]
        t2 = time.perf_counter()
        verdict = self.verify(q, path, dt)
        result = self._result(q, path, verdict, "refine", why)
        timing.verify = time.perf_counter() - t2
        if exact:
            result = self._polish(result, path, trackable, why, timing, progress)
        result.timing = timing
        return result

    def _polish(self, lm: FollowResult, path: ReferencePath, trackable: np.ndarray,
                why: dict[int, str], timing: FollowTiming, progress: bool) -> FollowResult:
        """Stage 3: Ipopt from the LM answer; keep it only if the independent verdict
        agrees (collision-free, every violation ≤ 1e-6)."""
        try:
            from ..stages.polish_trajectory import TrajectoryPolishConfig, TrajectoryPolisher
        except ImportError:
            lm.stage = ("refine (polish failed: the Ipopt trajectory stage "
                        "cr_nlp.stages.polish_trajectory is not available)")
            return lm
        import sys

        if lm.max_violation <= VIOLATION_TOLERANCE and lm.collision_free and \
                bool(np.all(lm.reached)):
            # Every constraint already holds (verified independently) and every waypoint is
            # tracked: Ipopt has nothing to enforce. Measured on the bundled shapes, its
            # interior-point iterates left such an answer for another branch (square: mean
            # error 0.0 → 4.3 mm) at 50–150 s per path, so the answer is kept as it is.
            lm.stage = "refine (feasible: polish not needed)"
            return lm
        t0 = time.perf_counter()
        t = len(lm.q)
        if t not in self._polishers:
            samples = self.config.verify_samples
            self._polishers[t] = TrajectoryPolisher(
                self.robot, self.scene, t, safety_margin=self.margin, objective="tracking",
                config=TrajectoryPolishConfig(interpolation_checks=samples - 1,
                                              verify_samples=samples))
        if progress:
            print(f"polish (Ipopt): {t} waypoints …", file=sys.stderr)
        # Untrackable waypoints keep the LM's reference: its own tip pose (zero error).
        positions = np.where(trackable[:, None], path.positions, lm.position)
        rotations = matrix_from_wxyz(np.where(trackable[:, None], path.wxyz, lm.wxyz))
        try:
            out = self._polishers[t].solve(lm.q, path.dt, positions, rotations)
        except Exception as exc:  # noqa: BLE001 — a crashed polish must not lose the answer
            lm.stage = f"refine (polish failed: {type(exc).__name__}: {exc})"
            timing.polish += time.perf_counter() - t0
            return lm
        timing.polish += time.perf_counter() - t0
        if not out.success:
            lm.stage = f"refine (polish failed: {describe_polish(out)})"
            return lm
        t1 = time.perf_counter()
        q = clip_to_limits(self.robot, np.asarray(out.q, dtype=np.float64))
        verdict = self.verify(q, path, path.dt)
        timing.verify += time.perf_counter() - t1
        if not verdict["success"]:
            lm.stage = f"refine (polish failed: rejected by the checker: {verdict['reason']})"
            return lm
        polished = self._result(q, path, verdict, "polish", why)
        if lm.max_violation <= VIOLATION_TOLERANCE and lm.collision_free and \
                _tracking_cost(polished) > _tracking_cost(lm):
            # Both feasible: keep the one that tracks the path better.
            lm.stage = "refine (feasible; the polished answer tracked worse)"
            return lm
        return polished


def _tracking_cost(result: FollowResult) -> float:
    """Σ over waypoints of (position error in mm)² + (rotation error in degrees)²."""
    return float(np.sum((1e3 * result.position_error) ** 2
                        + np.degrees(result.rotation_error) ** 2))


def follow_path(robot: Robot | str | dict, path: ReferencePath | str | Path,
                scene: Scene | str | None = None, config: FollowConfig = FollowConfig(),
                exact: bool = False) -> FollowResult:
    """One-call path following: see ``PathFollower.follow``."""
    return PathFollower(robot, scene, config).follow(path, exact=exact)
