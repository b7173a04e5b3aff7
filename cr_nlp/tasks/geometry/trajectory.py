"""Trajectory planning: the problem (config, residuals), its solver wiring and result.

Problem (docs/design.md §2): z = (z₀, …, z_H), one bending-vector configuration per waypoint
(``waypoints = H + 1``), the time step Δt between waypoints fixed; start z₀ and goal z_H
fixed; f = end-effector path; c = clearance ≥ δ at every waypoint and along the motion
between them, tendon speed |Δℓ/Δt| ≤ v_max and acceleration |Δ²ℓ/Δt²| ≤ a_max (finite
differences of the tendon lengths over the waypoints); limits by projection.

Between waypoints the robot moves linearly in z. Tendon lengths are linear in z
(``ℓ = L − r·(ux cos α + uy sin α)``), so this is exactly the motion of a controller that
interpolates the tendon-length series linearly (``TrajectoryResult.save_csv``).

Objective. The LM stage minimises Σₖ ‖p(zₖ₊₁) − p(zₖ)‖² (tip displacements squared), not
the length Σₖ ‖p(zₖ₊₁) − p(zₖ)‖: the squared form is a smooth least-squares residual (the
length's gradient is undefined where two waypoints coincide) and, by Cauchy–Schwarz,
(length)² ≤ H·Σₖ‖Δp‖² with equality for evenly spaced waypoints, so it shortens the path
and spreads the waypoints evenly at once. A small joint-space term Σ‖zₖ₊₁ − zₖ‖² fixes
the body's shape where the tip alone leaves it free (three of six bending DOF for tdcr3).

Stages: explore (the roadmap query, ``stages.explore._roadmap``; initial guesses,
``stages.explore._trajectory_guesses``), refine (``stages.refine._chain_stream``: the LM on all
guesses of
all problems at once, penalties for clearance (``world._clearance_groups``) and tendon
limits; ``stages.refine._trajectory_select``: two rounds of guesses, the best by the verdict),
verify (``world._motion.verify_trajectory``: python-fcl along the densely interpolated
motion, float64 tendon finite differences, limits), optional polish
(``stages.polish._trajectory_nlp``: Ipopt with the constraints as constraints;
``tasks.geometry._trajectory_polish``). The result and its file forms are in
``tasks.geometry._trajectory_result``; the start/goal checks are ``world._motion.check_ends``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..._compile_effort import LARGE_PLAN, full_effort
from ...model import Robot, load_robot, q_to_z_numpy
from ...model.derivatives import tip_position_z
from ...model.kinematics import tendon_lengths_z
from ...model.limits import project_z
from ...runtime import configure
from ...stages.explore import initial_guesses
from ...stages.polish import check_time_limit, trajectory_polisher
from ...stages.polish import describe_polish as describe_polish
from ...stages.refine import (
    ChainBatchLM,
    ChainResidual,
    LMConfig,
    select_guesses,
    tendon_accel_excess,
    tendon_speed_excess,
)
from ...world import Scene, load_scene, scene_arrays
from ...world._broad_phase import part_cells, reach_box
from ...world._clearance_groups import clearance_groups, has_clearance, near_clearance_groups
from ...world._motion import MotionVerification as MotionVerification
from ...world._motion import check_ends, verify_trajectories
from ...world._motion import interpolate_trajectory as interpolate_trajectory
from ...world._motion import tendon_series as tendon_series
from ...world._motion import tip_positions as tip_positions
from ...world._motion import verify_trajectory as verify_trajectory
from ...world.clearance import SceneArrays, body_gap_tolerance
from .._result import Stage
from .._timing import StageTiming
from ._trajectory_polish import polish_results
from ._trajectory_result import TrajectoryResult as TrajectoryResult
from ._trajectory_result import controller_columns as controller_columns
from ._trajectory_result import result_from_verdict
from ._trajectory_result import save_results as save_results
from ._trajectory_result import trajectories_from_dict as trajectories_from_dict
from ._trajectory_result import trajectories_to_dict as trajectories_to_dict


@dataclass(frozen=True)
class TrajectoryConfig:
    """Settings of the trajectory planner. Defaults measured on tdcr3 in the bundled scenes."""

    waypoints: int = 24
    """H + 1 configurations per trajectory, start and goal included."""
    dt: float = 0.35
    """Δt, seconds between waypoints (default duration 23 × 0.35 = 8.05 s). Measured on
    400 start/goal pairs per bundled scene (tips ≥ 0.3 m apart): the straight line in z
    needs a tendon travel of 0.37 m (median), 0.85 m (99th percentile) and 0.98 m (max);
    at tdcr3's 0.2 m/s the default duration allows 1.6 m, room for detours."""
    guesses: int = 4
    """Initial trajectories per problem: the roadmap's (with ``init="roadmap"``), the
    straight line in z, then straight lines bent by random bumps."""
    first_round: int = 2
    """Guesses optimised first for every problem (the roadmap's and the straight line);
    the remaining ones only for the problems where none of these passes the
    verification."""
    perturbation: float = 0.6
    """Radians: amplitude of the half-sine bump added to the bending vectors of a
    perturbed guess (largest at the middle waypoint, zero at start and goal)."""
    iterations: int = 60
    """LM iterations on every guess."""
    give_up: tuple[tuple[int, float], ...] = ((12, 8.0), (20, 5.0))
    """Checkpoints (LM iterations, cost ½‖r‖²): a guess whose cost is still above a
    checkpoint's cost after its iterations stops there (``LMConfig.give_up``; (): off,
    every guess runs until it stalls or uses ``iterations``). 5.0 is ½·w_clear·(0.1 m)² at
    the default clearance weight, a clearance shortfall of 10 cm (root of the sum of
    squares). Measured on all 4 guesses of the first 20 problems of each bundled scene
    (seed 0, float32): of the 36 guesses still running at iteration 20 with a cost above 5
    (shelf 3, cabinet 23, random_27 10), none passed the verification after 60
    iterations, and no guess that passed was above 1.34 there; their remaining trips were
    3 %, 27 % and 9 % of all the LM trips. The earlier checkpoint: on the 4 guesses of
    problems 0–19 and of seed 1's 0–19 in shelf, cabinet, random_27 and 14 random boxes
    (562 guesses), no guess that passed was above 5.44 at iteration 12; (12, 8) stops
    another 1.7–9.7 % of the trips, on guesses that all failed."""
    path_weight: float = 1.0
    """Weight of the squared tip displacements (m²)."""
    smoothness_weight: float = 0.01
    """Weight of the squared joint-space steps ‖zₖ₊₁ − zₖ‖² (rad², m²)."""
    clearance_weight: float = 1000.0
    """Penalty weight of a clearance shortfall (per m²) at waypoints and check points."""
    tendon_weight: float = 10.0
    """Penalty weight of a relative tendon speed/acceleration overshoot (dimensionless)."""
    tendon_limit_fraction: float = 0.95
    """The LM stage aims for this fraction of the tendon limits, so that a penalty
    answer's small overshoot still lies inside the real limits."""
    safety_margin: float = 0.002
    """δ, metres: the clearance every answer must keep, as python-fcl measures it on the
    capsule body. The optimisers work on the sphere body with δ plus its discretisation
    bound (``world.clearance.body_gap_tolerance``), which implies it."""
    interpolation_checks: int = 1
    """Clearance check points inside each interval for the optimisers (1: the midpoint),
    so that thin obstacles are not tunnelled between waypoints."""
    verify_samples: int = 4
    """The verification splits every interval into this many pieces (fcl at each); the
    exact stage constrains the clearance at the same samples."""
    polish_attempts: int = 3
    """Exact mode: LM candidates (best first) the polish starts from in turn until one
    polish passes the verification."""
    polish_accepted: bool = False
    """Exact mode: also polish the problems whose LM answer the verification already
    accepts (Ipopt may then shorten their paths). False: such answers are kept as they
    are and only the rejected ones are polished."""
    polish_workers: int = 1
    """Exact mode: processes that polish problems in parallel
    (``stages.polish._process_pool``); 1 polishes in this process. The answers are the
    same either way."""
    polish_time_limit: float | None = None
    """Exact mode: seconds of polishing per problem, all its candidates and re-selection
    rounds together (None: no limit). A problem out of time keeps the best answer the
    verification accepted so far (its LM answer when no polish was accepted), its
    ``stage`` ending "(polish out of time: …)". Planning and verification are not
    limited."""
    chunk_size: int = 8
    """Most trajectories per compiled LM call: the slots of the continuous batching
    (``stages.refine._chain_stream``; split between its lanes, one per JAX device, at most
    chunk_size // 2 lanes), or the chunk size of the dense structure's fixed chunks. Measured
    on the 40 round-1 shelf trajectories (2-core CPU under a load of ~6, float32,
    interleaved, best of 5): 2, 4 and 8 slots took 6.0, 6.1 and 6.2 s in 38, 35 and 22
    device calls, 16 slots 14.3 s (more slots idle while the stream drains)."""
    dtype: str = "float32"
    """JAX dtype of the LM stage ("float64" needs jax_enable_x64)."""
    near_parts: int = 16
    """Banded LM: a body sphere's clearance terms measure only the parts listed for its
    cell in a table built once per scene (``world._broad_phase``: the parts that can be
    nearest below the margin), at most this many per part kind and cell (the bundled
    scenes need 9); 0 measures every part. The verification always checks every
    part."""
    cell_size: float | None = None
    """Edge (m) of that table's cells; None: chosen from the body radius and the robot's
    reach, within 16 MB (``world._broad_phase.part_cells``; 0.05 m for tdcr3)."""
    lm_structure: str = "banded"
    """How the LM stage solves its normal equations: "banded" (``stages.refine._banded_lm``: the
    residual as per-waypoint, pair and triple terms, a block-tridiagonal Cholesky; each
    trajectory stops on its own once converged) or "dense" (``stages.refine._lm``: one Jacobian
    of the whole trajectory, a dense (waypoints·3n)² Cholesky; kept as the reference the
    banded form is checked against)."""

    seed: int = 0
    """Seed of the perturbed guesses."""
    roadmap_cache: bool = True
    """Let ``Roadmap.build`` reuse a roadmap cached on disk."""
    roadmap_search: str = "auto"
    """Shortest-path backend of the roadmap queries (``stages.explore._roadmap_search``): "device"
    (batched min-plus relaxation in JAX), "scipy" (Dijkstra), or "auto" (scipy on a CPU
    backend, where it was measured faster at 1 to 1000 pairs, the device otherwise)."""
    problem_chunk: int = 256
    """Most problems planned together (roadmap queries, guesses, LM, verification); a
    larger batch is streamed in blocks of this many, so memory stays bounded."""

    def __post_init__(self) -> None:
        if self.waypoints < 3:
            raise ValueError(f"waypoints must be at least 3, got {self.waypoints}")
        if not self.dt > 0:
            raise ValueError(f"dt must be positive, got {self.dt}")
        if self.guesses < 1 or self.verify_samples < 1 or self.interpolation_checks < 0:
            raise ValueError("guesses and verify_samples must be ≥ 1, interpolation_checks ≥ 0")
        if self.roadmap_search not in ("auto", "device", "scipy"):
            raise ValueError(f"roadmap_search must be 'auto', 'device' or 'scipy', "
                             f"got {self.roadmap_search!r}")
        if self.lm_structure not in ("banded", "dense"):
            raise ValueError(f"lm_structure must be 'banded' or 'dense', "
                             f"got {self.lm_structure!r}")
        if self.chunk_size < 1:
            raise ValueError(f"chunk_size must be ≥ 1, got {self.chunk_size}")
        if self.problem_chunk < 1:
            raise ValueError(f"problem_chunk must be ≥ 1, got {self.problem_chunk}")
        check_time_limit(self.polish_time_limit, "polish_time_limit")


# ================================================================ residuals


def trajectory_residual(robot: Robot, waypoints: int, checks: int, margin: float,
                        weights: tuple[float, float, float, float], limit_fraction: float,
                        z: jax.Array, dt: jax.Array, scene: SceneArrays | None) -> jax.Array:
    """Residuals of one trajectory z (waypoints·3n,) with time step dt (s):

    - √w_path · (p(zₖ₊₁) − p(zₖ)) (m), the tip displacements;
    - √w_smooth · (zₖ₊₁ − zₖ) (rad, m);
    - √w_clear · grouped clearance shortfalls (m) at every waypoint and at ``checks``
      evenly spaced points inside every interval;
    - √w_tendon · max(0, |v|/(f·v_max) − 1) per tendon and interval, and the same for the
      acceleration (dimensionless), f = ``limit_fraction``.

    ``weights`` = (path, smoothness, clearance, tendon).
    """
    w_path, w_smooth, w_clear, w_tendon = weights
    way = z.reshape(waypoints, robot.dof)
    tips = jax.vmap(partial(tip_position_z, robot))(way)
    out = [math.sqrt(w_path) * (tips[1:] - tips[:-1]).reshape(-1),
           math.sqrt(w_smooth) * (way[1:] - way[:-1]).reshape(-1)]
    if has_clearance(robot, scene):
        step = way[1:] - way[:-1]
        configs = [way] + [way[:-1] + (c / (checks + 1)) * step for c in range(1, checks + 1)]
        groups = jax.vmap(partial(clearance_groups, robot, margin, scene))(
            jnp.concatenate(configs))
        out.append(math.sqrt(w_clear) * groups.reshape(-1))
    lengths = tendon_lengths_z(robot, way).astype(z.dtype)
    if robot.speed_limited:
        speed = (lengths[1:] - lengths[:-1]) / dt
        over = jnp.abs(speed) / (limit_fraction * robot.tendon_speed_max) - 1.0
        out.append(math.sqrt(w_tendon) * jnp.maximum(over, 0.0).reshape(-1))
    if robot.accel_limited:
        accel = (lengths[2:] - 2.0 * lengths[1:-1] + lengths[:-2]) / (dt * dt)
        over = jnp.abs(accel) / (limit_fraction * robot.tendon_accel_max) - 1.0
        out.append(math.sqrt(w_tendon) * jnp.maximum(over, 0.0).reshape(-1))
    return jnp.concatenate(out)


def trajectory_unary(robot: Robot, margin: float, sqrt_clear: float, z: jax.Array,
                     params: Any, shared: Any) -> jax.Array:
    """√w_clear · grouped clearance shortfalls (m) of one waypoint z (3n,)
    (``near_clearance_groups``); ``shared`` = (scene arrays or None, broad-phase table
    or None, Δt s)."""
    arrays, cells, _ = shared
    return sqrt_clear * near_clearance_groups(robot, margin, arrays, cells, z)


def trajectory_pair(robot: Robot, margin: float, checks: int,
                    weights: tuple[float, float, float, float], limit_fraction: float,
                    z_a: jax.Array, z_b: jax.Array, params: Any, shared: Any) -> jax.Array:
    """Residuals of one interval z_a → z_b (each (3n,)): √w_path·(p(z_b) − p(z_a)) (m),
    √w_smooth·(z_b − z_a) (rad, m), √w_clear·grouped clearance shortfalls (m) at
    ``checks`` evenly spaced points inside the interval, and √w_tendon·max(0,
    |Δℓ/Δt|/(f·v_max) − 1) per tendon. ``weights`` = (√w_path, √w_smooth, √w_clear,
    √w_tendon); f = ``limit_fraction``; ``shared`` as for ``trajectory_unary``."""
    sqrt_path, sqrt_smooth, sqrt_clear, sqrt_tendon = weights
    arrays, cells, dt = shared
    step = z_b - z_a
    out = [sqrt_path * (tip_position_z(robot, z_b) - tip_position_z(robot, z_a)),
           sqrt_smooth * step]
    if checks and has_clearance(robot, arrays):
        for c in range(1, checks + 1):
            out.append(sqrt_clear * near_clearance_groups(
                robot, margin, arrays, cells, z_a + (c / (checks + 1)) * step))
    if robot.speed_limited:
        out.append(sqrt_tendon * tendon_speed_excess(robot, limit_fraction, z_a, z_b, dt))
    return jnp.concatenate(out)


def trajectory_triple(robot: Robot, sqrt_tendon: float, limit_fraction: float,
                      z_a: jax.Array, z_b: jax.Array, z_c: jax.Array, params: Any,
                      shared: Any) -> jax.Array:
    """√w_tendon·max(0, |Δ²ℓ/Δt²|/(f·a_max) − 1) per tendon at the middle waypoint z_b
    (dimensionless); ``shared`` as for ``trajectory_unary``."""
    return sqrt_tendon * tendon_accel_excess(robot, limit_fraction, z_a, z_b, z_c, shared[2])


def trajectory_terms(robot: Robot, margin: float, config: TrajectoryConfig,
                     scene: SceneArrays | None) -> ChainResidual:
    """``trajectory_residual`` as window terms for the banded LM (``stages.refine._banded_lm``):
    the same residuals (hence the same cost ½‖r‖²) grouped by the waypoints they touch.
    ``scene`` only decides whether clearance terms exist."""
    sqrt = math.sqrt
    clear = has_clearance(robot, scene)
    unary = (partial(trajectory_unary, robot, float(margin),
                     sqrt(config.clearance_weight)) if clear else None)
    pair = partial(trajectory_pair, robot, float(margin),
                   config.interpolation_checks if clear else 0,
                   (sqrt(config.path_weight), sqrt(config.smoothness_weight),
                    sqrt(config.clearance_weight), sqrt(config.tendon_weight)),
                   config.tendon_limit_fraction)
    triple = (partial(trajectory_triple, robot, sqrt(config.tendon_weight),
                      config.tendon_limit_fraction)
              if robot.accel_limited else None)
    return ChainResidual(unary, pair, triple)


def _project_waypoints(robot: Robot, waypoints: int, z: jax.Array) -> jax.Array:
    """``project_z`` on every waypoint of a (B, waypoints·3n) batch."""
    return project_z(robot, z.reshape(z.shape[:-1] + (waypoints, robot.dof))).reshape(z.shape)


# ================================================================ the planner


PlanTiming = StageTiming
"""Seconds per stage of one ``TrajectoryPlanner.plan`` call."""


class TrajectoryPlanner:
    """Batched trajectory planning for one robot in one scene; reuse it across calls.

    ``plan(starts, goals)`` takes (P, 3n) start and goal configurations θ, φ, L (rad,
    rad, m; fixed lengths may be omitted, see ``Robot.full_q``) and returns one
    ``TrajectoryResult`` per problem. The LM program is compiled once per slot count
    (``TrajectoryConfig.chunk_size``).
    """

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | None = None,
                 config: TrajectoryConfig = TrajectoryConfig()) -> None:
        configure()
        self.robot = load_robot(robot)
        self.scene = load_scene(scene) if isinstance(scene, (str, Path, dict)) else scene
        self.config = config
        self.dtype = jnp.dtype(config.dtype)
        self.margin = config.safety_margin + body_gap_tolerance(self.robot)
        """The sphere-body clearance (m) the optimisers enforce."""
        self._arrays = (scene_arrays(self.scene, dtype=self.dtype)
                        if self.scene is not None else None)
        n = config.waypoints
        weights = (config.path_weight, config.smoothness_weight, config.clearance_weight,
                   config.tendon_weight)
        self.cells = (part_cells(self.scene, self.robot.backbone_radius, reach_box(self.robot),
                                 self.margin, config.near_parts, config.cell_size, self.dtype)
                      if self.scene is not None and config.near_parts > 0 else None)
        """The clearance terms' broad phase (``world._broad_phase``), or None."""
        free = np.ones((n, self.robot.dof))
        free[:, 2::3] = ~self.robot.lengths_fixed()
        free[0] = free[-1] = 0.0                       # start and goal are fixed
        self.lm = ChainBatchLM(
            trajectory_terms(self.robot, self.margin, config, self._arrays),
            partial(project_z, self.robot), n, jnp.asarray(free.reshape(-1), self.dtype),
            self.dtype, config.chunk_size, config.lm_structure,
            dense_residual=partial(trajectory_residual, self.robot, n,
                                   config.interpolation_checks, float(self.margin), weights,
                                   config.tendon_limit_fraction),
            dense_project=partial(_project_waypoints, self.robot, n), extra=self.cells,
            config=LMConfig(cost_tolerance=0.0, give_up=config.give_up))
        """Stage 2 (``stages.refine._chain_stream``): the LM over a stream of trajectories."""
        self.last_programs = 0
        """LM device programs launched by the last ``plan`` call (one per slot call or
        chunk)."""
        self._roadmap: Any = None
        self._polisher: Any = None
        self._polish_pool: Any = None
        self._rng = np.random.default_rng(config.seed)

    # ------------------------------------------------------------ pieces
    def roadmap(self) -> Any:
        """The scene's roadmap (built, or loaded from the cache, on first use); None
        without a scene (no obstacles to route around: the straight and perturbed
        guesses) or if ``cr_nlp.stages.explore._roadmap`` is not available."""
        if self._roadmap is None and self.scene is not None:
            try:
                from ...stages.explore import Roadmap, RoadmapConfig
            except ImportError:
                return None
            self._roadmap = Roadmap.build(self.robot, self.scene, RoadmapConfig(),
                                          cache=self.config.roadmap_cache)
        return self._roadmap

    def _roadmap_paths(self, valid: list[tuple[int, np.ndarray, np.ndarray]],
                       init: str) -> list[np.ndarray | None]:
        """The roadmap path (waypoints, 3n) of every problem, None where there is none
        (or ``init`` is not "roadmap"): one batched query for all of them."""
        roadmap = self.roadmap() if init == "roadmap" else None
        if roadmap is None:
            return [None] * len(valid)
        return roadmap.query_many(np.stack([q for _, q, _ in valid]),
                                  np.stack([q for _, _, q in valid]), self.config.waypoints,
                                  self.config.roadmap_search)

    def validate(self, start: Any, goal: Any) -> tuple[np.ndarray | None, np.ndarray | None, str]:
        """Full (3n,) start and goal, or a reason why the problem cannot be planned."""
        return self.validate_many([start], [goal])[0]

    def validate_many(self, starts: Any, goals: Any) -> list[tuple[np.ndarray | None,
                                                                   np.ndarray | None, str]]:
        """``validate`` for every (start, goal) pair, python-fcl run once on all ends."""
        return check_ends(self.robot, self.scene, starts, goals)

    def verify(self, q: np.ndarray, dt: float) -> MotionVerification:
        """``verify_trajectory`` with this planner's scene, δ and sampling: q (H+1, 3n)
        rad, rad, m; dt s."""
        return self.verify_many([q], dt)[0]

    def verify_many(self, qs: Sequence[np.ndarray], dt: float) -> list[MotionVerification]:
        """``verify`` of several trajectories (each (H+1, 3n) rad, rad, m; dt s) in one
        pass (``world._motion.verify_trajectories``)."""
        return verify_trajectories(self.robot, self.scene, qs, dt,
                                   self.config.safety_margin, self.config.verify_samples)

    # ------------------------------------------------------------ the solve
    def plan(self, starts: Any, goals: Any, exact: bool = False, init: str = "roadmap",
             progress: bool = False, dt: float | None = None) -> list[TrajectoryResult]:
        """Plan one trajectory per (start, goal) pair.

        Args:
            starts: (P, 3n) start configurations θ, φ, L (rad, rad, m), or the short form
                without fixed lengths; a list of rows of mixed lengths is allowed (a bad
                row is a failed result, not an exception).
            goals: (P, 3n) goal configurations, same form.
            exact: polish the trajectories with Ipopt (``stages.polish._trajectory_nlp``), the
                constraints as constraints: tendon speed and acceleration limits, bending
                limits, and clearance ≥ ``margin`` at every waypoint and at every sample
                the verification checks. Only the problems whose LM answer the
                verification rejects are polished, unless ``config.polish_accepted``. A
                polished answer replaces the LM answer only when the verification
                accepts it (``stage == "polish"``); a failed polish is retried from the
                next LM candidate (``polish_attempts``), and if none passes, the LM answer
                stays with its own verdict, its ``stage`` noting why each polish failed
                (or that ``config.polish_time_limit`` ran out).
            init: "roadmap" (roadmap path, straight line, perturbed) or "straight"
                (straight line and perturbed ones only).
            progress: show a progress bar for the exact stage.
            dt: seconds between waypoints (default ``config.dt``).

        From ``LARGE_PLAN`` problems on, programs this call compiles are optimised fully
        at once (``cr_nlp._compile_effort``).
        """
        with full_effort(len(starts) >= LARGE_PLAN):
            return self._plan(starts, goals, exact, init, progress, dt)

    def _plan(self, starts: Any, goals: Any, exact: bool, init: str, progress: bool,
              dt: float | None) -> list[TrajectoryResult]:
        if init not in ("roadmap", "straight"):
            raise ValueError(f"init must be 'roadmap' or 'straight', got {init!r}")
        if len(starts) != len(goals):
            raise ValueError(f"{len(starts)} starts but {len(goals)} goals")
        cfg = self.config
        dt = float(cfg.dt if dt is None else dt)
        timing = PlanTiming()
        self.last_timing = timing
        self.last_programs = 0
        results: list[TrajectoryResult | None] = [None] * len(starts)
        valid: list[tuple[int, np.ndarray, np.ndarray]] = []
        t0 = time.perf_counter()
        for i, (q_start, q_goal, reason) in enumerate(self.validate_many(starts, goals)):
            if reason:
                results[i] = TrajectoryResult(self.robot, None, dt, False, reason,
                                              Stage.REJECTED)
            else:
                valid.append((i, q_start, q_goal))
        timing.verify += time.perf_counter() - t0
        # Streamed in blocks: a block's guesses, LM answers and candidates are all that
        # is held at once besides the results. One progress bar spans every block.
        bar = None
        if progress and exact and valid:
            from tqdm.auto import tqdm
            bar = tqdm(total=len(valid), desc="polish (Ipopt)", unit="trajectory")
        try:
            for block in range(0, len(valid), cfg.problem_chunk):
                part = valid[block:block + cfg.problem_chunk]
                candidates = self._plan_valid(part, results, dt, init, timing)
                if exact:   # the exact stage (``tasks.geometry._trajectory_polish``)
                    t0 = time.perf_counter()
                    polish_results(self.robot, [i for i, _, _ in part], candidates, results,
                                   dt, lambda q: self.verify(q, dt), self.polisher,
                                   self._pool if cfg.polish_workers > 1 else None,
                                   cfg.polish_attempts, cfg.polish_accepted, bar,
                                   cfg.polish_time_limit)
                    timing.polish += time.perf_counter() - t0
        finally:
            if bar is not None:
                bar.close()
        return [r for r in results if r is not None]

    def _plan_valid(self, valid: list[tuple[int, np.ndarray, np.ndarray]],
                    results: list[TrajectoryResult | None], dt: float, init: str,
                    timing: PlanTiming) -> list[list[tuple[np.ndarray, str]]]:
        """The LM stage for the valid problems; fills ``results`` and returns, per
        problem, every refined guess (q, stage name), best first: the candidates the
        exact stage polishes in turn."""
        cfg = self.config
        t0 = time.perf_counter()
        # The LM's first program compiles while the roadmap is built and searched.
        self.lm.compile_ahead(len(valid) * min(max(cfg.first_round, 1), cfg.guesses),
                              self._arrays)
        guesses, kinds = [], []
        paths = self._roadmap_paths(valid, init)
        for (_, q_start, q_goal), path in zip(valid, paths, strict=True):
            g, k = initial_guesses(self.robot, q_to_z_numpy(q_start), q_to_z_numpy(q_goal),
                                   path, cfg.waypoints, cfg.guesses, cfg.perturbation,
                                   self._rng)
            guesses.append(g)
            kinds.append(k)
        timing.explore += time.perf_counter() - t0
        sel = select_guesses(self.lm, np.stack(guesses), [(a, b) for _, a, b in valid], dt,
                             self._arrays, cfg.iterations, cfg.first_round,
                             lambda qs: self.verify_many(qs, dt))
        self.last_programs += sel.programs
        timing.compile += sel.compile
        timing.refine += sel.refine
        timing.verify += float(sel.verify_seconds.sum())
        share = {"explore": timing.explore / len(valid), "refine": timing.refine / len(valid),
                 "compile": timing.compile / len(valid)}
        for row, (i, _, _) in enumerate(valid):
            verdict, g, q, cost_g = sel.best[row]
            results[i] = result_from_verdict(
                self.robot, q, dt, verdict, f"refine ({kinds[row][g]})", cost_g,
                StageTiming(**share, verify=float(sel.verify_seconds[row])))
        return [[(q, f"refine ({kinds[row][g]})") for q, g in sel.candidates[row]]
                for row in range(len(valid))]

    def close(self) -> None:
        """Stop the polish pool's worker processes (``polish_workers`` > 1), if any; the
        next exact solve starts a new pool. Also done at interpreter exit."""
        if self._polish_pool is not None:
            self._polish_pool.close()
            self._polish_pool = None

    def polisher(self) -> Any:
        """The trajectory polisher of this planner (built on first use): rows at every
        waypoint and at every sample the verification checks."""
        if self._polisher is None:
            cfg = self.config
            self._polisher = trajectory_polisher(self.robot, self.scene, cfg.waypoints,
                                                 self.margin, cfg.verify_samples)
        return self._polisher

    def _pool(self) -> Any:
        """The exact stage's worker pool (``stages.polish._process_pool``), started on first use."""
        if self._polish_pool is None:
            from ...stages.polish import PolishPool
            cfg = self.config
            self._polish_pool = PolishPool(trajectory_polisher, (
                self.robot, self.scene, cfg.waypoints, self.margin, cfg.verify_samples),
                cfg.polish_workers)
        return self._polish_pool


def plan_trajectories(robot: Robot | str | dict, starts: Any, goals: Any,
                      scene: Scene | str | None = None,
                      config: TrajectoryConfig = TrajectoryConfig(), exact: bool = False,
                      init: str = "roadmap") -> list[TrajectoryResult]:
    """One-call planning: see ``TrajectoryPlanner.plan`` (configurations in rad, m)."""
    return TrajectoryPlanner(robot, scene, config).plan(starts, goals, exact=exact, init=init)


def with_horizon(config: TrajectoryConfig, waypoints: int | None,
                 dt: float | None) -> TrajectoryConfig:
    """``config`` with another number of waypoints and/or time step (None: unchanged)."""
    changes: dict[str, Any] = {}
    if waypoints is not None:
        changes["waypoints"] = int(waypoints)
    if dt is not None:
        changes["dt"] = float(dt)
    return replace(config, **changes)

from ..._moved import moved_names  # noqa: E402 — the old address, for one release

__getattr__ = moved_names(__name__, {"tendon_names": "cr_nlp.model.routing"})
