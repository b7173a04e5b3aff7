"""Path following: the tip traces a reference path while the body avoids obstacles and
the tendons move smoothly.

Problem (docs/design.md §2): z = (z₀, …, z_{T−1}), one bending-vector configuration per
waypoint of the path (time step Δt between waypoints); f = Σₜ pose error to the
reference pose (the 6-vector log(T_tip⁻¹·T_ref), docs/design.md §1) plus a small smoothness
term; c = clearance ≥ δ at every waypoint and along the motion between waypoints,
tendon speed |Δℓ/Δt| ≤ v_max and acceleration |Δ²ℓ/Δt²| ≤ a_max; limits by projection.
Between waypoints the robot moves linearly in z (as ``tasks.geometry.trajectory``:
linear in the tendon lengths).

Stages:

1. explore (``stages.refine.BranchContinuation``): IK on every ``ik_stride``-th waypoint
   in one batch (``IKSolver.candidates``: a refined beam of distinct answers per
   waypoint), each answer carried halfway to the neighbouring IK waypoints by
   continuation (a few LM steps per waypoint on this module's ``follow_unary``), then the
   sequence with the smallest configuration jumps (``stages.explore._sequence``), its
   jumps bridged by continuation. For a robot with no more free variables than the 6 a
   pose fixes (tdcr3), the IK and the chains solve the pose alone (``follow_tracking``: no
   body points, ~30× cheaper per LM row) and ``follow_unary`` with its clearance rows
   scores every candidate.
2. refine: all waypoints jointly by the block-banded LM (``stages.refine.banded_lm_solve``):
   every residual depends on at most three consecutive waypoints (tracking and clearance:
   one; smoothness, tendon speed, clearance between waypoints: two; tendon acceleration:
   three), so each iteration costs O(T), not O(T³). Constraints are penalties here. While
   no body sphere of the chain comes near the margin (``follow_near``), the clearance
   rows are zero with zero derivatives and the Jacobians skip the body points.
3. polish (``exact=True``): Ipopt with the constraints as constraints, minimising the
   tracking error, warm-started from stage 2 (``stages.polish.polish_one``); a polish
   that fails, or that the independent check rejects, returns the stage-2 answer,
   marked in ``FollowResult.stage`` (``tasks.geometry._follow_polish``).

The tracking error with its closed-form Jacobians is ``tasks.geometry._follow_kinematics``;
the reference-path checks are ``tasks.readers.checked_path``.

Every answer is judged in float64 independently of the optimisers:
``world._motion.verify_trajectory`` (python-fcl along the interpolated motion, limits,
tendon finite differences) and the tip poses by the numpy backend of the model.

Waypoints outside the robot's reach (farther from the base than its longest length)
cannot be tracked: their tracking residual is switched off, the motion there is set by
its neighbours, and the result reports them (``reached`` False), never an exception.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import jax
import jax.monitoring
import jax.numpy as jnp
import numpy as np

from ..._programs import compile_ahead, compile_program
from ...model import Robot, load_robot, q_to_z_numpy, z_to_q_numpy
from ...model.limits import clip_to_limits, project_z
from ...model.rotations import matrix_from_wxyz
from ...runtime import configure
from ...stages.polish import check_time_limit
from ...stages.refine import (
    BranchContinuation,
    ChainResidual,
    ContinuationSettings,
    LMConfig,
    banded_lm_solve,
    tendon_accel_excess,
    tendon_speed_excess,
)
from ...world import Scene, load_scene, scene_arrays
from ...world._clearance_groups import (
    clearance_groups,
    group_indices,
    grouped_shortfalls,
    has_clearance,
)
from ...world._motion import verify_trajectory
from ...world.clearance import SceneArrays, body_gap_tolerance
from .._result import Stage
from .._timing import StageTiming, compile_seconds
from ..paths import ReferencePath
from ..readers import checked_path
from ._follow_kinematics import tracking_error as tracking_error
from ._follow_kinematics import tracking_from, tracking_jacobian, waypoint_jacobians
from ._follow_kinematics import waypoint_kinematics as waypoint_kinematics
from ._follow_polish import polish_follow
from ._follow_result import FollowResult as FollowResult
from ._follow_result import PathVerification, result_from_verdict
from .ik import IKConfig, IKSolver, validate_targets

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
    tendon_weight: float = 0.1
    """Penalty weight of a relative tendon speed/acceleration overshoot (dimensionless).
    A stiff penalty makes the LM creep along the limit's kink (a step the model thinks
    free crosses it and is rejected). Measured on icra (dt 0.3, 0.2, 0.15), square and
    sine (dt 0.04), 150 waypoints: 10 → 0.1 took icra 30 → 9 refine iterations at the
    same errors (2.62 mm, 0.172° max) and never tracked worse; the largest tendon speed
    rose to at most 0.961 v_max (the LM aims at ``tendon_limit_fraction`` 0.95)."""
    tendon_repair_weight: float | None = 10.0
    """Where the refine's answer still breaks a real tendon limit (a path the LM did not
    finish, e.g. square at Δt 0.04 s: once 2 % over v_max after 40 iterations), the refine
    runs again from stage 1's sequence with this stiffer tendon weight and its answer is
    returned (None: never). Paths within the limits never run it."""
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
    continuation_damping: float = 1e-4
    """Stage 1: starting LM damping of the continuation chains (relative to the diagonal of
    JᵀJ). Measured on square (tdcr3, 150 waypoints): from the secant prediction (~3e-3 m/rad
    off) 1e-4 converged in 2 iterations where 1e-2 (a plain LM solve's) took 4–5, to the
    same answers (float32 noise)."""
    continuation_give_up: int = 2
    """Stage 1: a chain still at or above the IK's ``success_tolerance`` after this many LM
    iterations at a waypoint stops iterating there (0: never), so that chains from
    candidates that solve nothing (~15 % of them on square) no longer keep every chain's
    loop running to ``continuation_iterations``."""
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
    last); the waypoints between are reached by continuation from the nearer neighbouring
    anchor (both in the middle; ``PathFollower.waypoint_candidates``). 1: IK on every
    waypoint."""
    dtype: str = "float32"
    """JAX dtype of the batched stages ("float64" needs jax_enable_x64)."""
    seed: int = 0
    """Seed of the IK seed pool."""
    polish_time_limit: float | None = None
    """Exact mode: seconds the polish of a path may take, its re-selection rounds
    together (None: no limit). Out of time, the LM answer stays (unless the polish's
    last round already passes the verification), with ``stage`` "refine (polish out of
    time: …)". Stages 1 and 2 and the verification are not limited."""

    def __post_init__(self) -> None:
        if self.iterations < 0 or self.verify_samples < 1 or self.interpolation_checks < 0:
            raise ValueError("iterations ≥ 0, verify_samples ≥ 1 and interpolation_checks ≥ 0")
        if not 0.0 < self.tendon_limit_fraction <= 1.0:
            raise ValueError(f"tendon_limit_fraction must be in (0, 1], got "
                             f"{self.tendon_limit_fraction}")
        weights = (self.tracking_weight, self.position_weight, self.rotation_weight,
                   self.smoothness_weight, self.clearance_weight, self.tendon_weight)
        if min(weights) < 0 or (self.tendon_repair_weight or 0.0) < 0:
            raise ValueError("weights must not be negative")
        check_time_limit(self.polish_time_limit, "polish_time_limit")

    def ik_config(self) -> IKConfig:
        """The stage-1 ``IKConfig``: ``ik`` with this config's margin, dtype and seed."""
        return replace(self.ik, safety_margin=self.safety_margin, dtype=self.dtype,
                       seed=self.seed)


# ================================================================ residuals


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def waypoint_residual(robot: Robot, margin: float, z: jax.Array, target: Any,
                      arrays: SceneArrays | None) -> jax.Array:
    """``tracking_error`` (6,) then the grouped clearance shortfalls (G,) m of one waypoint
    z (3n,) (``world._clearance_groups.grouped_shortfalls``), sharing one kinematics
    Jacobian (the LM's per-waypoint term)."""
    rot, pos, centres = waypoint_kinematics(robot, z)
    out = [tracking_from(rot, pos, target)]
    if has_clearance(robot, arrays):
        out.append(grouped_shortfalls(robot, margin, arrays, centres, None)[0])
    return jnp.concatenate(out)


@waypoint_residual.defjvp
def _waypoint_residual_jvp(robot: Robot, margin: float, primals: tuple,
                           tangents: tuple) -> tuple:
    z, target, arrays = primals
    z_dot = tangents[0]
    kin = waypoint_jacobians(robot, z)
    error = tracking_from(kin["rotation"], kin["position"], target)
    values, jac = [error], [tracking_jacobian(kin, error)]
    if has_clearance(robot, arrays):
        groups, groups_jac = grouped_shortfalls(robot, margin, arrays, kin["centres"],
                                          kin["d_centres"])
        values.append(groups)
        jac.append(groups_jac)
    return jnp.concatenate(values), jnp.concatenate(jac) @ z_dot


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


def follow_tracking(robot: Robot, weights: tuple[float, float], z: jax.Array, target: Any,
                    shared: Any) -> jax.Array:
    """The tracking part of ``follow_unary`` alone: √w_p·(p_tip − p_ref) (m) and
    √w_r·log(R_refᵀR_tip) (rad) of one waypoint z (3n,), times its tracking switch.
    ``weights`` = (√w_p, √w_r). No body points: its forward-mode Jacobian costs a small
    fraction of the clearance rows' (measured on tdcr3: ~30× less)."""
    sqrt_pos, sqrt_rot = weights
    scale = jnp.concatenate([jnp.full(3, sqrt_pos), jnp.full(3, sqrt_rot)]).astype(z.dtype)
    return target[2] * scale * tracking_error(robot, z, target)


NEAR_SLACK = 1e-3
"""Metres added to the margin by ``follow_near``: far more than the float32 difference
between the clearance values of the forward kinematics and of its derivatives (~1e-7 m),
so that where ``follow_near`` is False every clearance row is zero."""


def follow_unary_far(robot: Robot, weights: tuple[float, float, float], z: jax.Array,
                     target: Any, shared: Any) -> jax.Array:
    """``follow_unary`` where no body sphere comes within the margin (``follow_near``
    False): its tracking rows, then zeros for the clearance rows (a shortfall of zero has
    a zero derivative). No body points: the banded LM's Jacobian of a far chain costs a
    fraction of the whole residual's (measured on icra, 150 waypoints: 0.33 against
    2.1 ms)."""
    arrays, _ = shared
    groups = len(group_indices(robot, arrays)) if has_clearance(robot, arrays) else 0
    tracking = follow_tracking(robot, weights[:2], z, target, shared)
    return jnp.concatenate([tracking, jnp.zeros(groups, tracking.dtype)])


def follow_near(robot: Robot, margin: float, z: jax.Array, params: Any,
                shared: Any) -> jax.Array:
    """Whether any waypoint of a chain z (T, 3n) has a body sphere within the margin plus
    ``NEAR_SLACK`` (m) of an obstacle part or, for self pairs, of another sphere: where
    not, ``follow_unary`` equals ``follow_unary_far``."""
    arrays, _ = shared
    if not has_clearance(robot, arrays):
        return jnp.asarray(False)

    def shortfalls(zt: jax.Array) -> jax.Array:
        centres = waypoint_kinematics(robot, zt)[2]
        return grouped_shortfalls(robot, margin + NEAR_SLACK, arrays, centres, None)[0]

    return jnp.any(jax.vmap(shortfalls)(z) > 0.0)


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
    if checks and has_clearance(robot, arrays):
        for c in range(1, checks + 1):
            out.append(sqrt_clear * clearance_groups(robot, margin, arrays,
                                                      z_a + (c / (checks + 1)) * step))
    if robot.speed_limited:
        out.append(sqrt_tendon * tendon_speed_excess(robot, limit_fraction, z_a, z_b, dt))
    return jnp.concatenate(out)


def follow_triple(robot: Robot, sqrt_tendon: float, limit_fraction: float, z_a: jax.Array,
                  z_b: jax.Array, z_c: jax.Array, target: Any, shared: Any) -> jax.Array:
    """√w_t·max(0, |Δ²ℓ/Δt²|/(f·a_max) − 1) per tendon at the middle waypoint z_b."""
    _, dt = shared
    return sqrt_tendon * tendon_accel_excess(robot, limit_fraction, z_a, z_b, z_c, dt)


def follow_terms(robot: Robot, margin: float, config: FollowConfig) -> ChainResidual:
    """The path-following residual as window terms for ``stages.refine._banded_lm``; a chain with
    no body sphere near the margin (``follow_near``) takes its Jacobians from the tracking
    rows alone (``follow_unary_far``)."""
    sqrt = math.sqrt
    track = config.tracking_weight
    unary_weights = (sqrt(track * config.position_weight), sqrt(track * config.rotation_weight),
                     sqrt(config.clearance_weight))
    unary = partial(follow_unary, robot, float(margin), unary_weights)
    pair = partial(follow_pair, robot, float(margin), config.interpolation_checks,
                   (sqrt(config.smoothness_weight), sqrt(config.clearance_weight),
                    sqrt(config.tendon_weight)), config.tendon_limit_fraction)
    triple = (partial(follow_triple, robot, sqrt(config.tendon_weight),
                      config.tendon_limit_fraction)
              if robot.accel_limited else None)
    return ChainResidual(unary, pair, triple,
                         unary_far=partial(follow_unary_far, robot, unary_weights),
                         near=partial(follow_near, robot, float(margin)))


FollowTiming = StageTiming
"""Seconds per stage of one ``PathFollower.follow`` call."""


# ================================================================ the follower


class PathFollower:
    """Path following for one robot in one scene; reuse it across paths (the LM program
    is compiled once per path length, the IK seed pool built once).

    ``follow(path)`` takes a ``ReferencePath``, a bundled path name ("square", "sine",
    "icra") or a path file, and returns a ``FollowResult``.
    """

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | Path | dict | None = None,
                 config: FollowConfig = FollowConfig()) -> None:
        configure()
        self.robot = load_robot(robot)
        self.scene = load_scene(scene) if scene is not None else None
        self.config = config
        self.dtype = jnp.dtype(config.dtype)
        self.margin = config.safety_margin + body_gap_tolerance(self.robot)
        """The sphere-body clearance (m) the optimisers enforce."""
        self._arrays: SceneArrays | None = (scene_arrays(self.scene, dtype=self.dtype)
                                            if self.scene is not None else None)
        self._terms = follow_terms(self.robot, self.margin, config)
        self._repair_terms = (None if config.tendon_repair_weight is None else follow_terms(
            self.robot, self.margin, replace(config, tendon_weight=config.tendon_repair_weight)))
        self._project = partial(project_z, self.robot)
        free = np.ones(self.robot.dof)
        free[2::3] = ~self.robot.lengths_fixed()   # a fixed length is not a variable
        self._free = jnp.asarray(free, self.dtype)
        self._compiled: dict[Any, Any] = {}
        chain_weights = (1.0, 1.0, math.sqrt(config.ik.clearance_weight))
        # With no more free variables than a pose fixes, the IK answers of a waypoint are
        # isolated points: clearance rows cannot move a chain along its branch, only trade
        # tracking error for clearance. The chains then track the pose alone (no body
        # points, far cheaper) and the clearance enters through their answers' scores.
        isolated = int(free.sum()) <= 6
        self._anchor_scene = None if isolated else self.scene
        """The scene of stage 1's IK: none where the chains track the pose alone (the
        table scores its answers with the clearance rows)."""
        self.continuation = BranchContinuation(
            self.robot, partial(follow_unary, self.robot, float(self.margin), chain_weights),
            lambda positions, wxyz: self.ik_solver.candidates(positions, wxyz), free,
            self.dtype, ContinuationSettings(
                config.continuation_iterations, config.continuation_rounds, config.max_jumps,
                config.bridge_window, config.ik_stride, config.ik.success_tolerance,
                config.continuation_damping, config.continuation_give_up),
            chain_residual=(partial(follow_tracking, self.robot, (1.0, 1.0))
                            if isolated else None))
        """Stage 1 (``stages.refine._path_continuation``): IK candidates, continuation, bridging."""
        self._ik: IKSolver | None = None
        self._polishers: dict[int, Any] = {}
        self.last_timing = FollowTiming()

    @property
    def ik_solver(self) -> IKSolver:
        """Stage 1's batched IK solver (built on first use; on the pose alone, without the
        scene, where the chains track the pose alone: ``_anchor_scene``)."""
        if self._ik is None:
            self._ik = IKSolver(self.robot, self._anchor_scene, self.config.ik_config())
        return self._ik

    # ------------------------------------------------------------ stage 1
    def initial_sequence(self, positions: np.ndarray, wxyz: np.ndarray,
                         trackable: np.ndarray, dt: float) -> np.ndarray:
        """Stage 1: (T, 3n) configurations (θ, φ, L), one IK answer per trackable waypoint
        chosen for the smallest jumps; untrackable waypoints are interpolated in z between
        their trackable neighbours (the nearest one's at the ends; straight if none).

        The candidates and the sequence come from ``stages.refine._path_continuation``: full IK on
        every ``ik_stride``-th waypoint, continuation in between, the smoothest sequence, and
        each jump (a tendon would have to move faster than ``tendon_speed_max``) bridged by
        continuation from both sides (``continuation_rounds`` times)."""
        t = len(positions)
        z = np.zeros((t, self.robot.dof))
        z[:, 2::3] = [0.5 * (s.length_min + s.length_max) for s in self.robot.segments]
        rows = np.flatnonzero(trackable)
        if len(rows):
            chosen = self.continuation.sequence(positions[rows], wxyz[rows], dt * np.diff(rows),
                                                self._shared(dt))
            for k in range(self.robot.dof):
                z[:, k] = np.interp(np.arange(t), rows, np.asarray(chosen[:, k], np.float64))
        return z_to_q_numpy(z)

    def waypoint_candidates(self, positions: np.ndarray, wxyz: np.ndarray,
                            dt: float) -> tuple[np.ndarray, np.ndarray]:
        """IK candidates for R trackable waypoints (positions (R, 3) m, wxyz (R, 4)):
        z (R, K, 3n) and penalised residual norms (R, K) (m/rad; inf: no candidate), as
        ``stages.refine._path_continuation.BranchContinuation.table`` builds them."""
        return self.continuation.table(positions, wxyz, self._shared(dt))

    def _shared(self, dt: float) -> tuple:
        """The residuals' shared data: (scene arrays or None, Δt s) in the device dtype."""
        return (self._arrays, np.asarray(dt, self.dtype))

    # ------------------------------------------------------------ stage 2
    def _refined_and_judged(self, q0: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
                            trackable: np.ndarray, path: ReferencePath, dt: float,
                            timing: StageTiming,
                            repair: bool = False) -> tuple[np.ndarray, PathVerification]:
        """``refine`` then ``verify`` (Δt ``dt``, s), their seconds added to ``timing``."""
        t1 = time.perf_counter()
        with compile_seconds() as compiled:
            q, _, _ = self.refine(q0, positions, wxyz, trackable, dt, repair=repair)
        timing.compile += compiled[0]
        timing.refine += time.perf_counter() - t1 - compiled[0]
        t2 = time.perf_counter()
        verdict = self.verify(q, path, dt)
        timing.verify += time.perf_counter() - t2
        return q, verdict

    def refine(self, q0: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
               trackable: np.ndarray, dt: float,
               repair: bool = False) -> tuple[np.ndarray, float, int]:
        """Stage 2: the banded LM over all waypoints from (T, 3n) q0. Returns q (T, 3n),
        the final penalised cost ½‖r‖² and the iterations used. ``repair``: with the
        stiffer ``tendon_repair_weight`` (for an answer that breaks a tendon limit)."""
        args = self._lm_args(q0, positions, wxyz, trackable, dt)
        key = (len(q0), repair)
        if key not in self._compiled:
            self._compiled[key] = compile_program(self._path_lm(repair), args,
                                                  name="the path LM", by_shape=True)
        z, cost, iterations = jax.device_get(self._compiled[key](*args))
        q = z_to_q_numpy(z)
        return clip_to_limits(self.robot, q), float(cost), int(iterations)

    def _path_lm(self, repair: bool) -> Callable:
        """Stage 2's LM (``banded_lm_solve`` on the path's terms; ``repair``: the stiff
        tendon terms), as ``compile_program`` takes it."""
        config = LMConfig(cost_tolerance=0.0,
                          stall_tolerance=self.config.refine_stall_tolerance,
                          prediction_tolerance=self.config.refine_stall_tolerance)
        terms = self._repair_terms if repair else self._terms
        return partial(banded_lm_solve, terms, self._project, config=config)

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
        return z0, params, self._shared(dt), self._free, np.int32(self.config.iterations)

    # ------------------------------------------------------------ verification
    def verify(self, q: np.ndarray, path: ReferencePath, dt: float) -> PathVerification:
        """Float64 verdict on (T, 3n) q against the reference: ``verify_trajectory``'s
        report with ``tracking_errors`` and ``reached`` (``PathVerification``)."""
        motion = verify_trajectory(self.robot, self.scene, q, dt, self.config.safety_margin,
                                   self.config.verify_samples)
        return PathVerification.of(self.robot, motion, q, path, self.config.position_tolerance_mm,
                                   self.config.rotation_tolerance_deg)

    def _result(self, q: np.ndarray, path: ReferencePath, verdict: PathVerification,
                stage: Stage,
                why_untrackable: dict[int, str]) -> FollowResult:
        return result_from_verdict(self.robot, path, q, verdict, stage, why_untrackable,
                                   self.scene.name if self.scene is not None else None,
                                   self.config.safety_margin)

    # ------------------------------------------------------------ the solve
    def follow(self, path: ReferencePath | str | Path, exact: bool = False,
               progress: bool = False, dt: float | None = None) -> FollowResult:
        """Follow a reference path.

        Args:
            path: a ``ReferencePath``, a bundled name ("square", "sine", "icra") or a
                path file (``tasks.paths`` format).
            exact: polish with Ipopt, the constraints as constraints, minimising the
                tracking error (``stages.polish._trajectory_nlp``); a failed or rejected
                polish returns the LM answer with ``stage`` "refine (polish failed: …)"
                (or "refine (polish out of time: …)", ``config.polish_time_limit``).
            progress: print the polish stage's progress to stderr.
            dt: seconds between waypoints (default: the path's own ``dt``).

        Raises:
            ValueError: a reference pose that is not finite or not a unit quaternion,
                a non-positive ``dt``, or fewer than 2 waypoints (``tasks.readers.checked_path``).
        """
        path = checked_path(path, dt)
        dt = float(path.dt)
        positions = np.asarray(path.positions, dtype=np.float64)
        wxyz = np.asarray(path.wxyz, dtype=np.float64)
        _, _, reasons = validate_targets(self.robot, positions, wxyz)
        trackable = np.array([not r for r in reasons], bool)
        why = {i: r for i, r in enumerate(reasons) if r}

        timing = FollowTiming()
        self.last_timing = timing
        if (len(positions), False) not in self._compiled:
            # Stage 2's program (the largest) compiles or loads on another core while
            # stage 1 runs; ``refine`` then waits for it.
            compile_ahead(self._path_lm(False), self._lm_args(
                np.zeros((len(positions), self.robot.dof)), positions, wxyz, trackable, dt),
                name="the path LM", by_shape=True)
        t0 = time.perf_counter()
        with compile_seconds() as compiled:
            q0 = self.initial_sequence(positions, wxyz, trackable, dt)
        timing.compile += compiled[0]
        timing.explore = time.perf_counter() - t0 - compiled[0]
        refine_args = (q0, positions, wxyz, trackable, path, dt, timing)
        q, verdict = self._refined_and_judged(*refine_args)
        if self._repair_terms is not None and (
                verdict.motion.tendon_speed > self.robot.tendon_speed_max
                or verdict.motion.tendon_accel > self.robot.tendon_accel_max):
            # The soft tendon penalty left a limit broken: the stiff one from stage 1's
            # sequence (from the soft answer, measured, it may creep for 40 iterations).
            q, verdict = self._refined_and_judged(*refine_args, repair=True)
        result = self._result(q, path, verdict, Stage.REFINE, why)
        if exact:   # stage 3 (``tasks.geometry._follow_polish``)
            result = polish_follow(
                self.robot, self.polisher, result, path, trackable,
                lambda q: self.verify(q, path, path.dt),
                lambda q, verdict: self._result(q, path, verdict, Stage.POLISH, why), timing,
                progress, self.config.polish_time_limit)
        result.timing = timing
        return result

    def polisher(self, waypoints: int) -> Any:
        """Stage 3's Ipopt polisher for paths of this many waypoints (built on first use;
        ``stages.polish._trajectory_nlp``, objective "tracking", clearance rows at the
        verification's samples)."""
        if waypoints not in self._polishers:
            from ...stages.polish import TrajectoryPolishConfig, TrajectoryPolisher
            samples = self.config.verify_samples
            self._polishers[waypoints] = TrajectoryPolisher(
                self.robot, self.scene, waypoints, safety_margin=self.margin,
                objective="tracking", config=TrajectoryPolishConfig(
                    interpolation_checks=samples - 1, verify_samples=samples))
        return self._polishers[waypoints]

def follow_path(robot: Robot | str | dict, path: ReferencePath | str | Path,
                scene: Scene | str | None = None, config: FollowConfig = FollowConfig(),
                exact: bool = False) -> FollowResult:
    """One-call path following: see ``PathFollower.follow`` (waypoint poses in metres
    and unit quaternions; answers θ, φ, L in rad, rad, m)."""
    return PathFollower(robot, scene, config).follow(path, exact=exact)
