"""Inverse kinematics: the problem, the batched solver and its result.

Problem (DESIGN.md §2): z = bending-vector configuration; f = ½‖log(T_tip⁻¹·T_target)‖²
as LM residuals; limits by projection; clearance ≥ δ (penalty in JAX, a real
constraint in the exact stage); success is judged independently of the optimiser:
pose error < ``IKConfig.success_tolerance`` re-evaluated in float64, every limit held,
and, with a scene, collision-free by python-fcl.

Stages: explore (a Sobol seed pool, the K pool entries nearest each target in pose,
a few coarse LM steps on all of them, a diverse beam of the best), refine (LM on the
beam, best per target, retries with fresh seeds for the targets still failing),
polish (optional: Ipopt with the constraints as constraints).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._jax_setup import enable_compilation_cache, split_over_devices
from ..model import Robot, load_robot, q_to_z, z_to_q
from ..model._ops import NUMPY
from ..model.derivatives import pose_residual
from ..model.kinematics import model_pose_error, model_q_to_z, model_segment_frames
from ..model.limits import clip_to_limits, limit_violation_q, project_z
from ..model.rotations import matrix_from_wxyz, wxyz_from_matrix
from ..stages.explore import SeedPool, select_beam, sobol_configurations
from ..stages.lm import LMConfig, lm_solve
from ..world import Scene, check_many, load_scene, scene_arrays
from ..world.clearance import body_gap_tolerance
from ..world.penalty import sphere_clearances_z
from ..world.verdict import failure_reason
from ._timing import StageTiming


@dataclass(frozen=True)
class IKConfig:
    """Settings of the batched IK solver. Defaults measured on tdcr3 (README table)."""

    pool_size: int = 4096
    """Sobol configurations whose tip poses seed the search."""
    seeds_per_target: int = 12
    """Pool entries nearest each target (in pose) that start the coarse LM steps."""
    coarse_iterations: int = 6
    """LM iterations on every seed before the beam is chosen."""
    beam_width: int = 3
    """Candidates per target kept for refinement."""
    beam_min_distance: float = 0.1
    """Beam candidates closer than this in bending-vector space (rad, m) count as one."""
    refine_iterations: int = 40
    """LM iterations on the beam."""
    refine_round: int = 10
    """The refinement runs in rounds of this many LM iterations; after each round only
    the problems still improving go on, packed into smaller chunks (see ``_refine``)."""
    retry_rounds: int = 2
    """Extra rounds, with fresh random seeds, for the targets whose penalised residual is
    still above ``success_tolerance``."""
    retry_seeds: int = 32
    """Seeds per failing target in a retry round."""
    polish_attempts: int = 3
    """Exact mode: polishes per target at most, from the refined answer, then from the
    target's other beam candidates, until one passes the verification."""
    polish_workers: int = 1
    """Exact mode: processes that polish targets in parallel (``stages.pool``); 1
    polishes in this process. The answers are the same either way."""
    success_tolerance: float = 1e-2
    """A target is reached when the pose error ‖log(T⁻¹T_target)‖ is below this."""
    converged_error: float = 1e-6
    """LM stops early once every problem's pose error is below this."""
    safety_margin: float = 0.002
    """δ, metres: the clearance every answer must keep, as python-fcl measures it on the
    capsule body. The optimisers work on the sphere body with δ plus its discretisation
    bound (``world.clearance.body_gap_tolerance``), which implies it."""
    clearance_weight: float = 30.0
    """Penalty weight of a clearance shortfall (per metre) in the JAX stages."""
    chunk_size: int = 1024
    """Most problems per compiled LM call; larger batches are split into chunks."""
    dtype: str = "float32"
    """JAX dtype of the batched stages ("float64" needs jax_enable_x64)."""
    seed: int = 0
    """Seed of the pool and of the retry samples."""


@dataclass
class IKTiming(StageTiming):
    """Wall-clock seconds per stage (compile apart from steady-state work)."""

    compile: float = 0.0
    explore: float = 0.0
    refine: float = 0.0
    polish: float = 0.0
    verify: float = 0.0


@dataclass
class IKResult:
    """One row per target. Units: rad, m; errors in the pose-error metric, m and rad."""

    robot: Robot
    q: np.ndarray                  # (T, 3n) θ, φ, L
    position: np.ndarray           # (T, 3) tip position reached, m
    wxyz: np.ndarray               # (T, 4) tip orientation reached
    pose_error: np.ndarray         # (T,) ‖log(T⁻¹ T_target)‖
    position_error: np.ndarray     # (T,) m
    rotation_error: np.ndarray     # (T,) rad
    max_violation: np.ndarray      # (T,) largest limit violation (rad, m) or python-fcl
    #                                clearance shortfall below the safety margin (m)
    clearance: np.ndarray          # (T,) python-fcl signed distance, m (nan without scene)
    collision_free: np.ndarray     # (T,) bool, python-fcl verdict (True without scene)
    success: np.ndarray            # (T,) bool
    stage: list[str]               # which stage produced each answer
    reason: list[str]              # empty on success, else why it failed
    timing: IKTiming = field(default_factory=IKTiming)
    has_scene: bool = False

    def __len__(self) -> int:
        return len(self.q)

    @property
    def theta(self) -> np.ndarray:
        return self.q[:, 0::3]

    @property
    def phi(self) -> np.ndarray:
        return self.q[:, 1::3]

    @property
    def length(self) -> np.ndarray:
        return self.q[:, 2::3]

    def summary(self) -> dict[str, Any]:
        ok = self.success
        finite = np.isfinite(self.pose_error)
        return {
            "targets": len(self),
            "success_rate": float(ok.mean()) if len(self) else 0.0,
            "mean_pose_error": float(self.pose_error[finite].mean()) if finite.any() else None,
            "mean_pose_error_success": float(self.pose_error[ok].mean()) if ok.any() else None,
            "max_violation": float(np.nanmax(self.max_violation)) if len(self) else None,
            "collision_free_rate": (float(self.collision_free.mean())
                                    if self.has_scene and len(self) else None),
        }

    def to_json(self) -> dict[str, Any]:
        """The RESULT.json form (README: ``cr-nlp ik``)."""
        rows = []
        for i in range(len(self)):
            finite = bool(np.all(np.isfinite(self.q[i])))
            rows.append({
                "q": self.q[i].tolist() if finite else None,
                "theta": self.theta[i].tolist() if finite else None,
                "phi": self.phi[i].tolist() if finite else None,
                "length": self.length[i].tolist() if finite else None,
                "position": self.position[i].tolist() if finite else None,
                "wxyz": self.wxyz[i].tolist() if finite else None,
                "pose_error": _num(self.pose_error[i]),
                "position_error": _num(self.position_error[i]),
                "rotation_error": _num(self.rotation_error[i]),
                "success": bool(self.success[i]),
                "collision_free": bool(self.collision_free[i]) if self.has_scene else None,
                "clearance": _num(self.clearance[i]) if self.has_scene else None,
                "max_violation": _num(self.max_violation[i]),
                "stage": self.stage[i],
                "reason": self.reason[i] or None,
            })
        return {"robot": self.robot.name, "results": rows, "summary": self.summary(),
                "timing": self.timing.as_dict()}


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


# ---------------------------------------------------------------- the problem

def ik_residual(robot: Robot, margin: float, weight: float, z: jax.Array, target: Any,
                scene: Any) -> jax.Array:
    """Residuals of one IK problem: the 6-vector pose error (m, rad) and, with a scene,
    √weight·max(0, δ − d) for each body sphere's nearest obstacle part and each body
    sphere's nearest self-clearance partner (``world.penalty.sphere_clearances_z``).
    The pose part differentiates by the model's closed-form Jacobian
    (``model.derivatives.pose_residual``)."""
    pose = pose_residual(robot, z, target)
    if scene is None:
        return pose
    shortfall = jnp.maximum(margin - sphere_clearances_z(robot, scene, z), 0.0)
    return jnp.concatenate([pose, jnp.sqrt(weight) * shortfall])


# ---------------------------------------------------------------- targets

def validate_targets(robot: Robot, positions: Any, wxyz: Any) -> tuple[np.ndarray, np.ndarray,
                                                                       list[str]]:
    """Check targets; returns positions (T, 3), unit quaternions (T, 4) and a reason per
    target ("" when valid). Invalid targets get NaN rows instead of raising."""
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    wxyz = np.asarray(wxyz, dtype=float).reshape(-1, 4)
    if len(positions) != len(wxyz):
        raise ValueError(f"{len(positions)} positions but {len(wxyz)} orientations")
    reasons = [""] * len(positions)
    base = np.asarray(robot.base_position)
    reach = robot.total_length_max
    norms = np.linalg.norm(wxyz, axis=1)
    for i in range(len(positions)):
        if not np.all(np.isfinite(positions[i])):
            reasons[i] = "target position is not finite"
        elif not np.all(np.isfinite(wxyz[i])):
            reasons[i] = "target orientation is not finite"
        elif abs(norms[i] - 1.0) > 1e-3:
            reasons[i] = f"target wxyz is not a unit quaternion (norm {norms[i]:.6g})"
        elif np.linalg.norm(positions[i] - base) > reach * (1 + 1e-9):
            reasons[i] = (f"target is out of reach: {np.linalg.norm(positions[i] - base):.4g} m "
                          f"from the base, the robot is at most {reach:.4g} m long")
    bad = np.array([bool(r) for r in reasons], dtype=bool)
    wxyz = np.where(bad[:, None], np.nan, wxyz / np.where(norms > 0, norms, 1.0)[:, None])
    positions = np.where(bad[:, None], np.nan, positions)
    return positions, wxyz, reasons


# ---------------------------------------------------------------- the solver

def _with_count(out: tuple) -> tuple:
    """``lm_solve``'s (z, cost, iterations) with the iteration count as a (1,) array, so
    that each shard of a sharded call returns its own."""
    z, cost, used = out
    return z, cost, used[None]


SMALLEST_CHUNK = 128
"""Fewest problems per compiled LM call (64 per core on 2 cores)."""


def chunk_plan(count: int, largest: int, smallest: int = SMALLEST_CHUNK) -> list[int]:
    """Chunk sizes that cover ``count`` problems with fewer than ``smallest`` padded rows,
    using only two compiled shapes: the largest power of two ≤ ``largest`` ("big") for
    whole big chunks, and ``smallest`` chunks for the rest (one more big chunk instead
    when the rest is within ``smallest`` of it). Measured (tdcr4_ext, lattice, 100
    targets): one chunk size per batch ran the 1200 coarse problems as 2 × 1024 and the
    300 refined ones as 512 (41 % padding); a plan over every power of two between the
    two sizes padded little but compiled up to four shapes per solver, about 26 s each
    from a cold cache; this one pads as little with two."""
    if count <= 0:
        return []
    big = smallest
    while big * 2 <= max(largest, smallest):
        big *= 2
    n_big, rest = divmod(count, big)
    if rest > big - smallest:
        n_big, rest = n_big + 1, 0
    return [big] * n_big + [smallest] * -(-rest // smallest)


class IKSolver:
    """Batched IK for one robot (and optionally one scene); reuse it across calls.

    ``solve(positions, wxyz, exact=False)`` takes target positions (T, 3) in metres and
    orientations (T, 4) as unit quaternions (w, x, y, z) and returns an ``IKResult``.
    """

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | None = None,
                 config: IKConfig = IKConfig()) -> None:
        enable_compilation_cache()
        self.robot = load_robot(robot)
        self.scene = load_scene(scene) if isinstance(scene, str) else scene
        self.config = config
        self.dtype = jnp.dtype(config.dtype)
        # The sphere-body margin the optimisers enforce: implies config.safety_margin for
        # the capsule body that python-fcl checks.
        self.margin = config.safety_margin + body_gap_tolerance(self.robot)
        self._arrays = (scene_arrays(self.scene, dtype=self.dtype)
                        if self.scene is not None else None)
        self._residual = partial(ik_residual, self.robot, float(self.margin),
                                 float(config.clearance_weight))
        self._project = partial(project_z, self.robot)
        free = np.ones(self.robot.dof)
        free[2::3] = ~self.robot.lengths_fixed()  # a fixed length is not a variable
        self._free = jnp.asarray(free, self.dtype)
        self._compiled: dict[int, Any] = {}
        self._pool: SeedPool | None = None
        self._polisher: Any = None
        self._polish_pool: Any = None
        self._rng = np.random.default_rng(config.seed)
        self.lm_calls: list[tuple[int, int, int, int]] = []
        """Per compiled LM call of the last ``solve``/``candidates``: (problems, chunk
        size, iteration budget, iterations run), for profiling."""

    # ------------------------------------------------------------ pieces
    def _seed_pool(self, timing: IKTiming) -> SeedPool:
        if self._pool is None:
            t0 = time.perf_counter()
            q = sobol_configurations(self.robot, self.config.pool_size, self.config.seed)
            if self.scene is not None:
                q = q[self._collision_free(q)]
            self._pool = SeedPool(self.robot, q)
            timing.explore += time.perf_counter() - t0
        return self._pool

    def _collision_free(self, q: np.ndarray) -> np.ndarray:
        """Which configurations keep clearance ≥ δ by the differentiable clearance (fast)."""
        from ..world import clearance as clearance_fn

        d = np.asarray(clearance_fn(self.robot, self._arrays, jnp.asarray(q, self.dtype)))
        return d >= self.margin

    def _lm(self, z0: np.ndarray, positions: np.ndarray, rotations: np.ndarray,
            iterations: int, timing: IKTiming) -> tuple[np.ndarray, np.ndarray]:
        """LM over a batch in power-of-two chunks (``chunk_plan``), so a few compiled
        programs serve every batch size and budget; returns z (B, n) and cost ½‖r‖² (B,).
        Appends one entry per chunk to ``lm_calls``."""
        config = LMConfig(cost_tolerance=0.5 * self.config.converged_error ** 2)
        z_out, cost_out = [], []
        start = 0
        for chunk in chunk_plan(len(z0), self.config.chunk_size):
            stop = min(start + chunk, len(z0))
            pad = chunk - (stop - start)

            def padded(x: np.ndarray, start: int = start, stop: int = stop,
                       pad: int = pad) -> np.ndarray:
                part = x[start:stop]
                return np.concatenate([part, np.repeat(part[:1], pad, 0)]) if pad else part

            args = (jnp.asarray(padded(z0), self.dtype),
                    (jnp.asarray(padded(positions), self.dtype),
                     jnp.asarray(padded(rotations).reshape(-1, 9), self.dtype)),
                    self._arrays, self._free, jnp.int32(iterations))
            if chunk not in self._compiled:
                t0 = time.perf_counter()
                self._compiled[chunk] = self._lower(args, config).compile()
                timing.compile += time.perf_counter() - t0
            z, cost, used = self._compiled[chunk](*args)
            self.lm_calls.append((stop - start, chunk, iterations, int(np.max(used))))
            z_out.append(np.array(z[: stop - start]))
            cost_out.append(np.array(cost[: stop - start]))
            start = stop
        return np.concatenate(z_out), np.concatenate(cost_out)

    def _lower(self, args: tuple, config: LMConfig) -> Any:
        """The LM program for one chunk, split over every JAX device (one shard per CPU
        core with ``use_host_devices``): each device runs its own loop on its share."""
        solve = partial(lm_solve, self._residual, self._project, config=config)
        program = split_over_devices(lambda *a: _with_count(solve(*a)),
                                     (True, True, False, False, False), len(args[0]), outputs=3)
        return program.lower(*args)

    def _refine(self, z0: np.ndarray, positions: np.ndarray, rotations: np.ndarray,
                width: int, per_target: bool, timing: IKTiming) -> tuple[np.ndarray,
                                                                          np.ndarray]:
        """LM on a beam of ``width`` candidates per target (rows grouped by target), in
        rounds of ``refine_round`` iterations up to ``refine_iterations``. After a round a
        candidate stops when its pose error is below ``converged_error``, when the round
        lowered its cost by less than 1 %, or (``per_target``) when another candidate of
        its target converged; the rest go on, repacked into smaller chunks. Damping
        restarts each round. Returns z (B, n) and cost ½‖r‖² (B,).

        Measured (tdcr4_ext, lattice, 100 targets, 300 candidates): ``_lm`` stops a chunk
        only when all its problems are done, and every chunk ran the full 40 iterations
        while after 10 only a minority of the targets were not yet at 1e-6."""
        cfg = self.config
        z, cost = z0.copy(), np.full(len(z0), np.inf)
        tolerance = 0.5 * cfg.converged_error ** 2
        target = np.arange(len(z0)) // width
        active = np.arange(len(z0))
        budget = cfg.refine_iterations
        while budget > 0 and len(active):
            rounds = min(max(cfg.refine_round, 1), budget)
            z_a, c_a = self._lm(z[active], positions[active], rotations[active], rounds,
                                timing)
            improving = c_a < 0.99 * cost[active]
            z[active], cost[active] = z_a, c_a
            budget -= rounds
            keep = improving & (c_a > tolerance)
            if per_target:
                best = np.full(target[-1] + 1, np.inf)
                np.minimum.at(best, target, cost)
                keep &= best[target[active]] > tolerance
            active = active[keep]
        return z, cost

    def _search(self, z_seeds: np.ndarray, positions: np.ndarray, rotations: np.ndarray,
                timing: IKTiming) -> tuple[np.ndarray, np.ndarray]:
        """Coarse LM on (T, K) seeds, diverse beam, refinement; best z (T, n), cost (T,)."""
        z, cost = self._search_beam(z_seeds, positions, rotations, timing, per_target=True)
        best = np.argmin(cost, axis=1)
        return z[np.arange(len(z)), best], cost[np.arange(len(z)), best]

    def _search_beam(self, z_seeds: np.ndarray, positions: np.ndarray, rotations: np.ndarray,
                     timing: IKTiming, per_target: bool = False) -> tuple[np.ndarray,
                                                                          np.ndarray]:
        """Coarse LM on (T, K) seeds, diverse beam, refinement: z (T, B, n), cost (T, B).
        With ``per_target`` (only the best candidate is wanted) a target's other
        candidates stop refining once one has converged."""
        t, k, n = z_seeds.shape
        cfg = self.config
        t0 = time.perf_counter()
        c0 = timing.compile
        z, cost = self._lm(z_seeds.reshape(-1, n), np.repeat(positions, k, 0),
                           np.repeat(rotations, k, 0), cfg.coarse_iterations, timing)
        z, cost = z.reshape(t, k, n), cost.reshape(t, k)
        width = min(cfg.beam_width, k)
        beam = select_beam(z, cost, width, cfg.beam_min_distance)
        z_beam = z[np.arange(t)[:, None], beam]
        timing.explore += time.perf_counter() - t0 - (timing.compile - c0)
        t1 = time.perf_counter()
        c1 = timing.compile
        z, cost = self._refine(z_beam.reshape(-1, n), np.repeat(positions, width, 0),
                               np.repeat(rotations, width, 0), width, per_target, timing)
        timing.refine += time.perf_counter() - t1 - (timing.compile - c1)
        return z.reshape(t, width, n), cost.reshape(t, width)

    def candidates(self, positions: Any, wxyz: Any) -> tuple[np.ndarray, np.ndarray]:
        """Several distinct IK answers per target (the refined beam), for callers that
        choose among them (path following picks the smoothest sequence).

        Args:
            positions: (T, 3) metres; wxyz: (T, 4) unit quaternions (valid targets only).
        Returns:
            q (T, B, 3n) configurations (θ, φ, L) and their penalised residual norms (T, B)
            (pose error in m/rad plus the clearance penalty), B = ``beam_width``.
        """
        positions, wxyz, reasons = validate_targets(self.robot, positions, wxyz)
        if any(reasons):
            bad = next(i for i, r in enumerate(reasons) if r)
            raise ValueError(f"target {bad}: {reasons[bad]}")
        timing = IKTiming()
        self.lm_calls = []
        rotations = matrix_from_wxyz(wxyz)
        pool = self._seed_pool(timing)
        nearest = pool.nearest(positions, rotations, self.config.seeds_per_target)
        z, cost = self._search_beam(pool.z[nearest], positions, rotations, timing)
        q = clip_to_limits(self.robot, np.asarray(z_to_q(self.robot, z), dtype=float))
        return q, np.sqrt(2.0 * cost)

    def _random_seeds(self, count: int, per_target: int) -> np.ndarray:
        q = sobol_configurations(self.robot, count * per_target,
                                 int(self._rng.integers(1 << 30)))
        self._rng.shuffle(q)
        return np.array(q_to_z(self.robot, q)).reshape(count, per_target, -1)

    # ------------------------------------------------------------ verification
    def verify(self, q: np.ndarray, positions: np.ndarray,
               wxyz: np.ndarray) -> dict[str, np.ndarray]:
        """Float64 re-evaluation of answers, independent of the optimiser's numbers:
        pose error by the numpy backend of the model, limits, python-fcl clearance."""
        robot = self.robot
        rot, pos = model_segment_frames(NUMPY, robot, model_q_to_z(NUMPY, robot, q))[-1]
        rot_m = np.stack(np.broadcast_arrays(*rot), -1).reshape(-1, 3, 3)
        pos_v = np.stack(np.broadcast_arrays(*pos), -1).reshape(-1, 3)
        target_r = matrix_from_wxyz(wxyz)
        goal = (tuple(target_r[:, i, j] for i in range(3) for j in range(3)),
                tuple(positions[:, i] for i in range(3)))
        tip = (tuple(rot_m[:, i, j] for i in range(3) for j in range(3)),
               tuple(pos_v[:, i] for i in range(3)))
        err = np.stack(np.broadcast_arrays(*model_pose_error(NUMPY, tip, goal)), -1)
        rel_rot = np.einsum("bji,bjk->bik", rot_m, target_r)
        cos_angle = np.clip((np.trace(rel_rot, axis1=1, axis2=2) - 1) / 2, -1, 1)
        violation = limit_violation_q(robot, q)
        out = {
            "position": pos_v, "wxyz": wxyz_from_matrix(rot_m),
            "pose_error": np.linalg.norm(err, axis=1),
            "position_error": np.linalg.norm(pos_v - positions, axis=1),
            "rotation_error": np.arccos(cos_angle),
            "clearance": np.full(len(q), np.nan), "collision_free": np.ones(len(q), bool),
        }
        if self.scene is not None:
            verdict = check_many(robot, self.scene, q)
            out["clearance"] = verdict.min_distance
            out["collision_free"] = ~verdict.collision
            shortfall = np.maximum(self.config.safety_margin - verdict.min_distance, 0.0)
            violation = np.maximum(violation, shortfall)
        out["max_violation"] = violation
        return out

    def close(self) -> None:
        """Stop the polish pool's worker processes (``polish_workers`` > 1), if any; the
        next exact solve starts a new pool. Also done at interpreter exit."""
        if self._polish_pool is not None:
            self._polish_pool.close()
            self._polish_pool = None

    # ------------------------------------------------------------ the solve
    def solve(self, positions: Any, wxyz: Any, exact: bool = False,
              progress: bool = False) -> IKResult:
        """Solve a batch of IK targets.

        Args:
            positions: (T, 3) target tip positions, metres.
            wxyz: (T, 4) target tip orientations, unit quaternions (w, x, y, z).
            exact: polish every answer with Ipopt, constraints as constraints.
            progress: show a progress bar for the exact stage.
        """
        timing = IKTiming()
        self.lm_calls = []
        cfg = self.config
        robot = self.robot
        positions, wxyz, reasons = validate_targets(robot, positions, wxyz)
        t_all = len(positions)
        valid = np.array([not r for r in reasons], dtype=bool)
        q_out = np.full((t_all, robot.dof), np.nan)
        stage = ["none"] * t_all
        idx = np.flatnonzero(valid)
        if len(idx):
            pos_v, rot_v = positions[idx], matrix_from_wxyz(wxyz[idx])
            pool = self._seed_pool(timing)
            t0 = time.perf_counter()
            nearest = pool.nearest(pos_v, rot_v, cfg.seeds_per_target)
            timing.explore += time.perf_counter() - t0
            z_best, cost = self._search(pool.z[nearest], pos_v, rot_v, timing)
            ok = np.sqrt(2 * cost) < cfg.success_tolerance
            used = cfg.seeds_per_target
            for _ in range(cfg.retry_rounds):
                todo = np.flatnonzero(~ok)
                if not len(todo):
                    break
                t0 = time.perf_counter()
                # Half the retry seeds are the next-nearest pool entries (collision-free,
                # close in pose), half are fresh random configurations (other branches).
                near = cfg.retry_seeds // 2
                nearest = pool.nearest(pos_v[todo], rot_v[todo], used + near)[:, used:]
                used += near
                seeds = self._random_seeds(len(todo), cfg.retry_seeds)
                seeds[:, 1: 1 + nearest.shape[1]] = pool.z[nearest]
                seeds[:, 0] = z_best[todo]  # keep the best so far in the race
                timing.explore += time.perf_counter() - t0
                z_new, c_new = self._search(seeds, pos_v[todo], rot_v[todo], timing)
                better = c_new < cost[todo]
                z_best[todo[better]] = z_new[better]
                cost[todo[better]] = c_new[better]
                ok = np.sqrt(2 * cost) < cfg.success_tolerance
            q_out[idx] = clip_to_limits(robot, np.asarray(z_to_q(robot, z_best), dtype=float))
            for i in idx:
                stage[i] = "refine"
        result = self._finish(q_out, positions, wxyz, reasons, stage, timing)
        if exact and len(idx):
            self._polish(result, positions, wxyz, idx, timing, progress)
        return result

    def _finish(self, q: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
                reasons: list[str], stage: list[str], timing: IKTiming) -> IKResult:
        t0 = time.perf_counter()
        valid = np.array([not r for r in reasons])
        n = len(q)
        fields = {k: np.full(n, np.nan) for k in ("pose_error", "position_error",
                                                  "rotation_error", "max_violation", "clearance")}
        position = np.full((n, 3), np.nan)
        quat = np.full((n, 4), np.nan)
        collision_free = np.zeros(n, bool)
        if valid.any():
            checked = self.verify(q[valid], positions[valid], wxyz[valid])
            for k in fields:
                fields[k][valid] = checked[k]
            position[valid] = checked["position"]
            quat[valid] = checked["wxyz"]
            collision_free[valid] = checked["collision_free"]
        result = IKResult(self.robot, q, position, quat, collision_free=collision_free,
                          success=np.zeros(n, bool), stage=list(stage), reason=list(reasons),
                          timing=timing, has_scene=self.scene is not None, **fields)
        self._judge(result, valid)
        timing.verify += time.perf_counter() - t0
        return result

    def _judge(self, result: IKResult, rows: np.ndarray) -> None:
        """Success flags and failure reasons from the verified numbers: the one verdict
        of ``world.verdict`` (pose error below ``success_tolerance``, every violation ≤
        1e-6: limits, clearance shortfall below δ)."""
        tol = self.config.success_tolerance
        for i in np.flatnonzero(rows):
            violations = {"limits": float(limit_violation_q(self.robot, result.q[i]))}
            if result.has_scene:
                violations["clearance"] = max(0.0, self.config.safety_margin
                                              - float(result.clearance[i]))
            result.reason[i] = failure_reason(
                violations, pose_error=float(result.pose_error[i]), pose_tolerance=tol,
                min_clearance=None if result.collision_free[i] else float(result.clearance[i]))
            result.success[i] = not result.reason[i]

    def _polish(self, result: IKResult, positions: np.ndarray, wxyz: np.ndarray,
                idx: np.ndarray, timing: IKTiming, progress: bool) -> None:
        """Exact stage: polish every answer; where the polish fails or the verification
        rejects it, polish the target's other beam candidates (``candidates``) in turn,
        up to ``config.polish_attempts`` polishes in all. A verified polish replaces the
        answer; otherwise the refined answer stays with its own verdict (exact mode never
        succeeds less often than the penalty stages)."""
        from ..stages.polish import IKPolisher, build_polisher, polish_many

        t0 = time.perf_counter()
        if self._polisher is None:
            self._polisher = IKPolisher(self.robot, self.scene, safety_margin=self.margin)
        if self.config.polish_workers > 1 and self._polish_pool is None:
            from ..stages.pool import PolishPool
            self._polish_pool = PolishPool(build_polisher, (self.robot, self.scene, self.margin),
                                    self.config.polish_workers)
        rotations = matrix_from_wxyz(wxyz)
        todo = np.asarray(idx)
        starts = result.q[todo]
        why: dict[int, list[str]] = {int(i): [] for i in todo}
        for attempt in range(max(self.config.polish_attempts, 1)):
            if not len(todo):
                break
            if attempt == 1:
                # The other beam candidates of the targets still failing, best first.
                q_beam, _ = self.candidates(positions[todo], wxyz[todo])
                beam = {int(i): q_beam[k] for k, i in enumerate(todo)}
            if attempt >= 1:
                if attempt > q_beam.shape[1]:
                    break
                starts = np.stack([beam[int(i)][attempt - 1] for i in todo])
            o_tol = self._polisher.config.violation_tolerance
            outs = polish_many(self._polisher, starts, positions[todo], rotations[todo],
                               progress=progress and attempt == 0,
                               pool=self._polish_pool if len(todo) > 1 else None)
            # Valid polishes; one that misses the polish's own 1e-6 pose tolerance still
            # counts where it is nearer the target than the answer it started from.
            good = np.array([o.success or (o.max_violation <= o_tol and np.isfinite(
                o.pose_error) and o.pose_error < result.pose_error[i])
                for i, o in zip(todo, outs, strict=True)], bool)
            for i, o in zip(todo, outs, strict=True):
                if not o.success and not good[list(todo).index(i)]:
                    cfg = self._polisher.config
                    why[int(i)].append(o.failure(cfg.pose_tolerance, cfg.violation_tolerance))
            kept = np.zeros(len(todo), bool)
            if good.any():
                t1 = time.perf_counter()
                rows = todo[good]
                polished = np.stack([o.q for o, g in zip(outs, good, strict=True) if g])
                checked = self.verify(polished, positions[rows], wxyz[rows])
                for j, i in enumerate(rows):
                    before = (result.q[i].copy(), result.stage[i])
                    result.q[i] = polished[j]
                    self._store(result, i, checked, j)
                    self._judge(result, np.isin(np.arange(len(result)), [i]))
                    if result.success[i]:
                        result.stage[i] = "polish"
                        kept[np.flatnonzero(todo == i)] = True
                    else:
                        why[int(i)].append(f"rejected by the checker: {result.reason[i]}")
                        result.q[i] = before[0]
                        self._store(result, i, self.verify(before[0][None], positions[i][None],
                                                           wxyz[i][None]), 0)
                        self._judge(result, np.isin(np.arange(len(result)), [i]))
                timing.verify += time.perf_counter() - t1
            todo = todo[~kept]
        for i in todo:
            result.stage[i] = f"refine (polish failed: {'; '.join(why[int(i)])})"
        timing.polish += time.perf_counter() - t0

    @staticmethod
    def _store(result: IKResult, i: int, checked: dict[str, np.ndarray], j: int) -> None:
        """Row j of ``verify``'s output into answer i of ``result``."""
        result.position[i] = checked["position"][j]
        result.wxyz[i] = checked["wxyz"][j]
        for k in ("pose_error", "position_error", "rotation_error", "max_violation",
                  "clearance"):
            getattr(result, k)[i] = checked[k][j]
        result.collision_free[i] = checked["collision_free"][j]


def solve_ik(robot: Robot | str | dict, positions: Any, wxyz: Any,
             scene: Scene | str | None = None, config: IKConfig = IKConfig(),
             exact: bool = False) -> IKResult:
    """One-call IK: see ``IKSolver.solve`` (positions in metres, wxyz unit quaternions)."""
    return IKSolver(robot, scene, config).solve(positions, wxyz, exact=exact)


def read_targets(path: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Target poses from a file ``{"poses": [{"position": [x, y, z], "wxyz": [w, x, y, z]},
    ...]}`` (positions in metres, unit quaternions; ``wxyz`` defaults to the identity).

    Returns (positions (k, 3), wxyz (k, 4), problems): a malformed entry becomes a NaN row
    with its reason in ``problems`` (empty strings elsewhere), so one bad target never
    sinks the batch.

    Raises:
        ValueError: the file is missing, not JSON, or not of that shape.
    """
    import json

    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"file not found: {path}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("poses"), list):
        raise ValueError(f"{path} must hold {{\"poses\": [{{\"position\": [x, y, z], "
                         f"\"wxyz\": [w, x, y, z]}}, ...]}}")
    poses = data["poses"]
    positions = np.full((len(poses), 3), np.nan)
    wxyz = np.full((len(poses), 4), np.nan)
    problems = [""] * len(poses)
    for i, pose in enumerate(poses):
        try:
            if not isinstance(pose, dict):
                raise ValueError("entry is not an object")
            p = np.asarray(pose["position"], dtype=float)
            w = np.asarray(pose.get("wxyz", [1.0, 0.0, 0.0, 0.0]), dtype=float)
            if p.shape != (3,) or w.shape != (4,):
                raise ValueError(f"position needs 3 numbers and wxyz 4, got {p.size} and {w.size}")
            positions[i], wxyz[i] = p, w
        except (KeyError, TypeError, ValueError) as exc:
            problems[i] = f"malformed pose entry: {exc}"
    return positions, wxyz, problems
