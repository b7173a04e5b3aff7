"""Inverse kinematics in tension space: tendon tensions that put the tip of the Cosserat
rod model (``model.cosserat``) at target positions (and orientations), batched, through
the stages of every task.

The problem of one target: tensions τ ∈ [0, τ_max]ⁿ and the moment at the base M(0)
(the shooting unknown of the statics, here an unknown of the IK itself) minimise

    ‖p(τ, M(0)) − p*‖² + ‖L·rot(R*ᵀR)‖² (with an orientation) + w_eq‖L·(M(L) − M_tip)/(EI/L)‖²
    + w_c²‖max(0, δ + b − d(backbone))‖² (with a scene) (+ ρ²‖τ/τ_max‖²),

one integration pass of the rod per residual evaluation (the rows and the unknowns, the
tendon groups' net pull moments, are ``stages.refine``'s ``waypoint_residual``). The
equilibrium term is zero at a solution, so the answer is an equilibrium of the rod, not a
penalty compromise; the clearance rows steer the solved backbone away from obstacles.

The stages:
- explore: the seed pool of the robot under the load case (``stages.explore``'s
  ``tension_pool``: random tension sets solved once, cached on disk, so a new process
  under the same loads does not rebuild it); each target starts from the pool set whose
  tip is nearest;
- refine: the batched LM (``stages.refine.lm_solve``; its Jacobians: ``TensionIKConfig.jacobian``);
- verify, then again from the next-nearest pool sets for the targets that failed.
- polish (``exact=True``): the answers the verdict rejects, polished by Ipopt on the rod's
  own discrete equations with the target, the tension bounds and the clearance as
  constraints (``stages.polish``'s ``polish_tension_ik``, multiple shooting), accepted
  through the one acceptance policy: a polish is kept only where the verdict accepts it.

Success is the one verdict (``world.verdict``) on numbers re-evaluated independently of
the LM: the tip of a fresh forward statics solve (``solve_statics``, its own shooting) of
the answer's tensions within ``tolerance`` of the target, that solve converged, the
tensions within their bounds, and with a scene the clearance of the solved backbone
(python-fcl capsules, ``world.check.check_chains``) and its self-clearance at least the
safety margin. Units: metres, radians, newtons, N·m, m/s².
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ...model import Robot, load_robot
from ...model.cosserat import StaticsConfig, StaticsResult, solve_statics
from ...model.loads import StaticLoads, static_loads
from ...model.mechanics import require_mechanics
from ...model.rotations import matrix_from_wxyz
from ...runtime import configure
from ...stages import polish as exact_stage
from ...stages.explore import TensionPool, tension_pool
from ...stages.polish import (
    Polished,
    RowVerdict,
    check_time_limit,
    polish_and_accept,
    polish_note,
)
from ...stages.refine import (
    LMConfig,
    TensionTerms,
    WaypointParams,
    base_frame,
    box_bounds,
    iteration_budget,
    moments_of_unknowns,
    project_box,
    solve_waypoints,
    tensions_of_unknowns,
    unknowns_of,
    waypoint_params,
    waypoint_residual,
)
from ...world.check import check_chains
from ...world.clearance import SceneArrays, scene_arrays
from ...world.scene import Scene, load_scene
from ...world.verdict import judge_many
from .._result import Stage
from .._timing import StageTiming
from ._ik_result import TensionIKResult as TensionIKResult


@dataclass(frozen=True)
class TensionIKConfig:
    """Settings of the tension-space IK."""

    tolerance: float = 1e-4
    """Success: the re-evaluated tip is within this of the target (m; with orientations
    the pose error √(‖Δp‖² + (L·Δθ)²), Δθ in rad, L the robot's length)."""
    tension_weight: float = 1e-5
    """ρ, metres: the least-tension preference (see the module's docstring)."""
    pool_size: int = 16384
    """Random tension sets whose tips seed the search (one forward statics batch, once per
    solver and load case)."""
    iterations: int = 24
    """LM iterations at most."""
    round_iterations: int = 6
    """The LM runs in rounds of this many iterations; after each round only the targets
    still running go on (0: one round)."""
    initial_damping: float = 1e-6
    """The LM's starting λ relative to the diagonal of JᵀJ. From a pool seed the
    Gauss–Newton step is good: at 1e-2 the first steps were cut short and the median
    target needed 10 iterations to 1e-7 m instead of 5 (docs/benchmarks.md)."""
    retry_seeds: int = 6
    """Targets that fail the verdict are solved again from their next-nearest pool
    entries, this many (0: no retry)."""
    safety_margin: float = 0.002
    """δ, metres: the clearance every answer keeps from obstacles and between segments at
    least two apart."""
    seed: int = 0
    """Seed of the pool."""
    clearance_weight: float = 10.0
    """Weight of the clearance rows of the solved backbone in the LM (with a scene): a
    sphere 1 mm inside the band costs as much as 1 cm of tip error."""
    clearance_buffer: float = 0.0005
    """The LM keeps the backbone's spheres this far beyond δ (m): the verdict checks
    capsules between the points, which can come closer than the spheres. A target whose
    only clear answers keep less than δ plus this is pulled off by the rows: at 2 mm,
    1.9 % of clear targets in clutter failed, at 0.5 mm 0–0.1 % (docs/benchmarks.md)."""
    lm_precision: float | None = None
    """The LM stops once its residual is below this fraction of ``tolerance`` (its rows in
    metres). None: 1e-3 for a batch (answers about a thousand times inside the verdict's
    tolerance), ``live_ik.LIVE_PRECISION`` for ``TensionLiveIKSolver``'s single updates,
    where each trip of the LM is a visible share of the update."""
    jacobian: str = "broyden"
    """How the LM differentiates the rod (``LMConfig.jacobian``): ``"broyden"`` (forward
    differences at the start of each round and every 8 iterations within one, Broyden's
    secant updates in between: one pass of the rod per iteration instead of one per
    unknown and one), ``"differences"``
    (forward differences every iteration) or ``"forward"`` (forward mode)."""
    statics: StaticsConfig = field(default_factory=StaticsConfig)
    """The rod discretisation (shared by the LM and the verdict's solve) and its dtype."""


SEED_NEIGHBOURS = 16
"""Pool sets nearest to a target among which a clear one is preferred as its seed."""


class TensionIKSolver:
    """Tension-space IK of a robot with a ``mechanics`` block (batched, numpy in/out)."""

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | None = None,
                 config: TensionIKConfig = TensionIKConfig()) -> None:
        configure()
        self.robot = load_robot(robot)
        require_mechanics(self.robot, "tension-space IK")
        self.scene = None if scene is None else load_scene(scene)
        self.config = config
        self.tension_max = float(self.robot.mechanics.tension_max)
        self.length = float(sum(s.length_min for s in self.robot.segments))
        self._pools: dict[bytes, TensionPool] = {}
        self._pool_clear: dict[int, np.ndarray] = {}
        self._on_device: dict[str, SceneArrays] = {}
        self._arrays = (None if self.scene is None or not self.scene.parts
                        else scene_arrays(self.scene, as_numpy=True))
        weight = config.clearance_weight if self._arrays is not None else 0.0
        own = config.clearance_weight if self.robot.has_self_pairs else 0.0
        # One residual and projection object per case (M(0) an unknown or not): one program.
        self._terms = {shoot: TensionTerms(self.robot, config.statics, shoot,
                                           config.tension_weight, weight,
                                           config.safety_margin + config.clearance_buffer,
                                           self_weight=own)
                       for shoot in (False, True)}
        self._residuals = {shoot: partial(waypoint_residual, terms)
                           for shoot, terms in self._terms.items()}
        self._project = partial(project_box, self._terms[False])

    # ------------------------------------------------------------ the seeds

    def pool(self, loads: StaticLoads) -> TensionPool:
        """The seed pool under one load case (``stages.explore``'s ``tension_pool``:
        random tension sets solved once, cached on disk per robot and loads, and kept
        here), with a k-d tree of its tips (m, world frame)."""
        key = b"".join(np.ascontiguousarray(a).tobytes() for a in loads.arrays())
        if key not in self._pools:
            cfg = self.config
            self._pools[key] = tension_pool(self.robot, loads, cfg.pool_size, cfg.seed,
                                            cfg.statics)
        return self._pools[key]

    def with_lm(self, **changes: Any) -> TensionIKSolver:
        """A solver of the same robot and scene with other LM ``iterations``, ``round_iterations``
        or ``initial_damping``, sharing all else with this one (seed pools, their screens,
        residuals: its compiled programs), none of which depends on the three."""
        unknown = set(changes) - {"iterations", "round_iterations", "initial_damping"}
        if unknown:
            raise ValueError(f"with_lm changes the LM's settings only, not {sorted(unknown)}")
        other = copy.copy(self)
        other.config = replace(self.config, **changes)
        return other

    # ------------------------------------------------------------ solve

    def solve(self, positions: Any, wxyz: Any = None, tip_force: Any = None,
              tip_moment: Any = None, gravity: Any = None, *,
              distributed_force: Any = None, point_loads: Any = None, exact: bool = False,
              time_limit: float | None = None) -> TensionIKResult:
        """Tensions for each target.

        Args:
            positions: (B, 3) or (3,) target tip positions, m, world frame.
            wxyz: None (position only) or (B, 4) / (4,) target orientations (unit
                quaternions w, x, y, z); a row of NaN leaves that target's orientation free.
            tip_force, tip_moment, gravity: (3,) or (B, 3) loads in the world frame (N,
                N·m, m/s²); default none.
            distributed_force: (3,) or (B, 3) force per metre along the backbone, N/m.
            point_loads: ``[{"s": m, "force": [N], "moment": [N·m]}]`` for every target,
                or one such list per target (world frame; ``model.loads``).
            exact: polish the answers the verdict rejects with Ipopt (the rod's equations,
                the target, the tension bounds and the clearance as constraints,
                ``stages.polish``'s tension-IK stage) and keep a polish the verdict
                accepts (``Stage.POLISH``); the others keep their answer.
            time_limit: with ``exact``, seconds of polishing per target (None: no limit).

        Returns:
            ``TensionIKResult`` with every target's tensions and the independent verdict.
        """
        check_time_limit(time_limit, "time_limit")
        positions = np.atleast_2d(np.asarray(positions, dtype=float))
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"positions: expected (B, 3) metres, got shape "
                             f"{np.shape(positions)}")
        count = len(positions)
        finite = np.all(np.isfinite(positions), axis=1)
        if not finite.all():  # such rows are reported, not solved
            return self._solve_finite(finite, positions, wxyz, tip_force, tip_moment, gravity,
                                      distributed_force, point_loads, exact=exact,
                                      time_limit=time_limit)
        if wxyz is None:
            quats = np.full((count, 4), np.nan)
        else:
            quats = np.array(np.broadcast_to(np.asarray(wxyz, dtype=float), (count, 4)))
            rows = ~np.any(np.isnan(quats), axis=1)
            norms = np.linalg.norm(quats[rows], axis=1)
            if np.any(np.abs(norms - 1.0) > 1e-6):
                bad = np.flatnonzero(rows)[np.argmax(np.abs(norms - 1.0))]
                raise ValueError(f"wxyz: target {bad} is not a unit quaternion")
        loads = static_loads(count, self.length, tip_force, tip_moment, gravity,
                             distributed_force, point_loads)
        timing = StageTiming()
        if count == 0:
            return self._empty(positions, quats, loads)
        start = time.perf_counter()
        tensions, moments = self._start(positions, loads, 0)
        timing.explore = time.perf_counter() - start
        start = time.perf_counter()
        tensions, stopped = self._lm_stopped(tensions, positions, quats, loads, moments)
        timing.refine = time.perf_counter() - start
        start = time.perf_counter()
        result = self._verdict(tensions, positions, quats, loads, timing)
        timing.verify = time.perf_counter() - start
        for k in range(1, self.config.retry_seeds + 1):
            failed = np.flatnonzero(~result.success)
            if not failed.size:
                break
            start = time.perf_counter()
            part = loads.rows(failed)
            seeds, moments = self._start(positions[failed], part, k)
            retry, why = self._lm_stopped(seeds, positions[failed], quats[failed], part,
                                          moments)
            timing.refine += time.perf_counter() - start
            start = time.perf_counter()
            again = self._verdict(retry, positions[failed], quats[failed], part, timing)
            better = again.success | (again.pose_error < result.pose_error[failed])
            result.replace_rows(again, failed[better], np.flatnonzero(better))
            stopped[failed[better]] = why[better]
            timing.verify += time.perf_counter() - start
        for i in np.flatnonzero(~result.success):   # why the LM left a rejected answer
            result.notes[i].append(f"refine: the LM {stopped[i]}")
        if exact:
            self._polish(result, positions, quats, loads, time_limit, timing)
        result.timing = timing
        return result

    def _polish(self, result: TensionIKResult, positions: np.ndarray, quats: np.ndarray,
                loads: StaticLoads, time_limit: float | None, timing: StageTiming) -> None:
        """Exact mode: the rejected answers polished by Ipopt and judged by the verdict,
        through the one acceptance policy (``polish_and_accept``); ``result`` is updated in
        place (accepted rows: ``Stage.POLISH``; the others: a note why)."""
        result.exact_mode = exact_stage.POLISH_EXACT_MODE   # imports CasADi (first use)
        done = (*exact_stage.SUCCESS_STATUSES, exact_stage.TIME_LIMIT_STATUS)
        rows = np.flatnonzero(~result.success)
        if not rows.size:
            return
        oriented = bool(np.any(~np.isnan(quats[rows])))
        found: dict[int, TensionIKResult] = {}

        def polish(starts: list, index: np.ndarray, attempt: int,
                   budgets: np.ndarray) -> list[Polished]:
            del attempt
            limit = None if not np.all(np.isfinite(budgets)) else float(np.sum(budgets))
            out = exact_stage.polish_tension_ik(
                self.robot, self.scene, np.stack(starts), positions[index],
                quats[index] if oriented else None, loads.rows(index),
                margin=self.config.safety_margin, statics_config=self.config.statics,
                time_limit=limit)
            # Ipopt's answer is judged where it succeeded or ran out of time (its last
            # iterate may still pass the verdict); otherwise the status is the reason.
            return [Polished(t if status in done else None,
                             "" if status in done[:-1] else f"Ipopt: {status}",
                             float(sec), status == done[-1])
                    for t, status, sec in zip(out.tensions, out.status, out.seconds,
                                              strict=True)]

        def judge(answers: list, index: np.ndarray) -> list[RowVerdict]:
            judged = self._verdict(np.stack(answers), positions[index], quats[index],
                                   loads.rows(index), timing)
            for k, i in enumerate(index.tolist()):
                found[i] = (judged, k)
            return [RowVerdict(bool(ok), why) for ok, why in zip(judged.success, judged.reason,
                                                                  strict=True)]

        fallback = [RowVerdict(False, result.reason[i]) for i in rows.tolist()]
        start = time.perf_counter()
        accepted = polish_and_accept(
            list(result.tensions[rows]), fallback,
            lambda attempt, index: [result.tensions[rows[i]] for i in index.tolist()],
            lambda starts, index, attempt, budgets: polish(starts, rows[index], attempt,
                                                           budgets),
            lambda answers, index: judge(answers, rows[index]), 1, time_limit)
        timing.polish += time.perf_counter() - start - accepted.judge_seconds
        for i, outcome in zip(rows.tolist(), accepted.outcomes, strict=True):
            if outcome.accepted:
                judged, k = found[i]
                result.replace_rows(judged, np.array([i]), np.array([k]))
                result.stage[i] = Stage.POLISH
            else:
                result.notes[i].append(polish_note(outcome))

    def _empty(self, positions: np.ndarray, quats: np.ndarray,
               loads: StaticLoads) -> TensionIKResult:
        """The result of no targets."""
        nothing = np.zeros((0, self.robot.n_tendons))
        empty = np.zeros(0)
        return TensionIKResult(
            robot=self.robot, tensions=nothing, target_position=positions,
            target_wxyz=quats, position=positions, wxyz=quats, pose_error=empty,
            position_error=empty, rotation_error=empty, min_clearance=empty,
            max_violation=empty, success=np.zeros(0, bool), reason=[],
            tip_force=loads.tip_force, tip_moment=loads.tip_moment,
            gravity=loads.gravity, distributed_force=loads.distributed_force,
            point_loads=[], tendon_displacements=nothing)

    def _solve_finite(self, finite: np.ndarray, positions: np.ndarray, wxyz: Any,
                      *loads: Any, exact: bool = False,
                      time_limit: float | None = None) -> TensionIKResult:
        """``solve`` on the rows with finite positions; the others failed, with a reason."""
        count = len(positions)

        def rows(value: Any, width: int) -> Any:
            if value is None:
                return None
            arr = np.asarray(value, dtype=float)
            return arr[finite] if arr.ndim == 2 and len(arr) == count else arr

        points = loads[4]
        if points is not None and len(points) == count and not isinstance(points[0], dict):
            points = [p for p, keep in zip(points, finite, strict=True) if keep]
        part = self.solve(positions[finite], rows(wxyz, 4), *(rows(v, 3) for v in loads[:3]),
                          distributed_force=rows(loads[3], 3), point_loads=points,
                          exact=exact, time_limit=time_limit)
        full = self.solve(np.zeros((0, 3)))
        for name in ("tensions", "target_position", "target_wxyz", "position", "wxyz",
                     "pose_error", "position_error", "rotation_error", "min_clearance",
                     "max_violation", "success", "tip_force", "tip_moment", "gravity",
                     "distributed_force", "tendon_displacements", "base_moment"):
            values = getattr(part, name)
            out = (np.zeros(count, bool) if values.dtype == bool
                   else np.full((count, *values.shape[1:]), np.nan))
            out[finite] = values
            setattr(full, name, out)
        full.target_position = positions
        full.reason = ["the target has non-finite coordinates"] * count
        full.stage = [Stage.REJECTED] * count
        full.notes = [[] for _ in range(count)]
        for i, j in zip(np.flatnonzero(finite).tolist(), range(len(part)), strict=True):
            full.stage[i], full.notes[i] = part.stage[j], part.notes[j]
        full.exact_mode = part.exact_mode
        full.point_loads = [[] for _ in range(count)]   # a refused target: none solved for
        for i, j in zip(np.flatnonzero(finite).tolist(), range(len(part)), strict=True):
            full.point_loads[i] = part.point_loads[j]
        full.violations = {k: np.full(count, np.nan) for k in part.violations}
        for k, values in part.violations.items():
            full.violations[k][finite] = values
        for i, j in zip(np.flatnonzero(finite).tolist(), range(len(part)), strict=True):
            full.reason[i] = part.reason[j]
        full.timing = part.timing
        return full

    def _start(self, positions: np.ndarray, loads: StaticLoads,
               rank: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(tensions (B, n) N, their equilibria's M(0) (B, 3) N·m, base frame, or None): the
        pool sets whose tips are the ``rank``-th nearest to each target, clear ones first
        with a scene, under the targets' loads when all share one load case (then the LM
        starts at an equilibrium), else from the unloaded pool (M(0) unknown: None)."""
        shared = all(np.all(v == v[:1]) for v in loads.arrays())
        case = (loads.rows(np.zeros(1, int)) if shared
                else static_loads(1, self.length))
        pool = self.pool(case)
        if self._arrays is None and not self.robot.has_self_pairs:
            pick = pool.nearest(positions, rank)
        else:
            pick = pool.nearest_clear(positions, rank, self._clear_pool(pool), SEED_NEIGHBOURS)
        moments = base_frame(self.robot, pool.base_moments[pick]) if shared else None
        return pool.tensions[pick], moments

    def _clear_pool(self, pool: TensionPool) -> np.ndarray:
        """(P,) True where a pool set's backbone keeps δ + buffer from the scene and from
        itself (segments at least two apart): a quick sphere screen, once per pool."""
        key = id(pool)
        if key not in self._pool_clear:
            self._pool_clear[key] = pool.clear_sets(
                self.robot, self._arrays, self.config.safety_margin + self.config.clearance_buffer)
        return self._pool_clear[key]

    def terms(self, shoot: bool) -> TensionTerms:
        """The rows of one waypoint for this solver (with M(0) as an unknown: ``shoot``)."""
        return self._terms[shoot]

    @property
    def scene_arrays(self) -> Any:
        """The scene's parts as numpy arrays for the clearance rows, or None."""
        return self._arrays

    def waypoint_params(self, positions: np.ndarray, quats: np.ndarray, loads: StaticLoads,
                        tip_weight: float = 1.0) -> tuple[bool, WaypointParams, np.ndarray]:
        """``stages.refine``'s ``waypoint_params`` for this solver's robot."""
        return waypoint_params(self.robot, positions, quats, loads, tip_weight)

    def _device_scene(self, dtype: Any) -> SceneArrays | None:
        """The scene's arrays on the device in ``dtype`` (made once per dtype)."""
        if self._arrays is None:
            return None
        key = np.dtype(dtype).name
        if key not in self._on_device:
            self._on_device[key] = SceneArrays(*(jnp.asarray(a, dtype) for a in self._arrays))
        return self._on_device[key]

    def lm_config(self) -> LMConfig:
        """The refine stage's LM rules for this solver's tolerance."""
        precision = 1e-3 if self.config.lm_precision is None else self.config.lm_precision
        return LMConfig(jacobian=self.config.jacobian, refresh=8, linear_solver="unrolled",
                        cost_tolerance=0.5 * (precision * self.config.tolerance) ** 2,
                        stall_tolerance=1e-6)

    def waypoint_lm_config(self) -> LMConfig:
        """``lm_config`` with the IK's first damping: one waypoint's LM (batch or live)."""
        return replace(self.lm_config(), initial_damping=self.config.initial_damping)

    def lm_arguments(self, z0: np.ndarray, params: WaypointParams, iterations: int,
                     pad: int = 0) -> tuple:
        """``lm_solve``'s arguments from the start to the budget for unknowns ``z0`` (B, size)
        and their ``WaypointParams``: numpy in the statics' dtype (the compiled call moves
        them: cheaper), each batch padded with ``pad`` copies of its first row."""
        dtype = self.config.statics.numpy_dtype

        def padded(a: np.ndarray) -> np.ndarray:
            a = np.asarray(a, dtype)
            return np.concatenate([a, np.repeat(a[:1], pad, axis=0)]) if pad else a

        return (padded(z0), jax.tree_util.tree_map(padded, params), self._device_scene(dtype),
                np.ones(z0.shape[1], dtype), iteration_budget(iterations))

    def _lm(self, tensions: np.ndarray, positions: np.ndarray, quats: np.ndarray,
            loads: StaticLoads, base_moment: np.ndarray | None = None,
            smallest: int = 16) -> np.ndarray:
        """LM from the given tensions (and M(0) (B, 3) N·m, base frame, where known: a warm
        start); returns the answer's tensions (B, n), N. The batch is padded to a power of
        two, at least ``smallest`` (a few compiled programs for every batch size)."""
        terms, z, _, _ = self._lm_unknowns(tensions, positions, quats, loads, base_moment,
                                           smallest)
        return tensions_of_unknowns(terms, z)

    def _lm_carried(self, tensions: np.ndarray, positions: np.ndarray, quats: np.ndarray,
                    loads: StaticLoads, base_moment: np.ndarray | None = None,
                    smallest: int = 16) -> tuple[np.ndarray, np.ndarray]:
        """``_lm`` and the answers' own M(0) (B, 3) N·m, base frame: the warm start of the
        next waypoint's LM. Without it the LM starts M(0) from the tip moment, which under
        gravity is far from the equilibrium, and closing that gap moves the tensions too
        (on the fitted FTDCR rod 6–8 N from an exact answer, onto another branch)."""
        terms, z, _, moment = self._lm_unknowns(tensions, positions, quats, loads,
                                                base_moment, smallest)
        return tensions_of_unknowns(terms, z), moments_of_unknowns(terms, z, moment)

    def _lm_stopped(self, tensions: np.ndarray, positions: np.ndarray, quats: np.ndarray,
                    loads: StaticLoads, base_moment: np.ndarray | None = None,
                    smallest: int = 16) -> tuple[np.ndarray, np.ndarray]:
        """``_lm`` and why the LM stopped on each target ((B,) words of
        ``stages.refine.STOP_REASONS``)."""
        terms, z, why, _ = self._lm_unknowns(tensions, positions, quats, loads, base_moment,
                                             smallest)
        return tensions_of_unknowns(terms, z), why

    def _lm_unknowns(self, tensions: np.ndarray, positions: np.ndarray, quats: np.ndarray,
                     loads: StaticLoads, base_moment: np.ndarray | None, smallest: int
                     ) -> tuple[TensionTerms, np.ndarray, np.ndarray, np.ndarray]:
        """The LM's (terms, answers' unknowns (B, size), why each stopped, the M(0) that
        holds without forces), in rounds of ``TensionIKConfig.round_iterations``: after each
        only the targets still running go on, in a batch padded to their own count (a
        batch's loop runs until its last problem stops: stragglers kept it iterating)."""
        cfg = self.config
        shoot, params, moment = self.waypoint_params(positions, quats, loads)
        terms = self._terms[shoot]
        z = unknowns_of(terms, tensions, moment if base_moment is None else base_moment)
        why = np.full(len(z), "out of iterations", dtype=object)
        going = np.arange(len(z))
        left = cfg.iterations
        while left > 0 and going.size:
            trips = min(left, cfg.round_iterations) if cfg.round_iterations > 0 else left
            part = jax.tree_util.tree_map(lambda a, rows=going: np.asarray(a)[rows], params)
            z[going], why[going] = self._lm_round(terms, z[going], part, trips, smallest)
            going = going[why[going] == "out of iterations"]
            left -= trips
        return terms, z, why, moment

    def _lm_round(self, terms: TensionTerms, z0: np.ndarray, params: WaypointParams,
                  iterations: int, smallest: int) -> tuple[np.ndarray, np.ndarray]:
        """One round of the LM from unknowns ``z0`` (B, size): (z, why each stopped). The
        batch is padded to a power of two, at least ``smallest``."""
        dtype = self.config.statics.numpy_dtype
        size = max(smallest, 1 << (len(z0) - 1).bit_length())
        config = self.waypoint_lm_config()   # its first damping as data: one program
        with jax.enable_x64(dtype == np.float64):     # for the solvers of ``with_lm``
            solution = solve_waypoints(
                self._residuals[terms.shoot], self._project,
                *self.lm_arguments(z0, params, iterations, size - len(z0)),
                replace(config, initial_damping=0.0), box_bounds(terms, dtype),
                np.full(size, config.initial_damping, dtype))
            z = np.asarray(solution.z, dtype=float)[:len(z0)]
        return z, np.array(solution.reasons()[:len(z0)], dtype=object)

    def _verdict(self, tensions: np.ndarray, positions: np.ndarray, quats: np.ndarray,
                 loads: StaticLoads, timing: StageTiming) -> TensionIKResult:
        """The independent check: a fresh forward statics solve of the answer's tensions,
        the bounds, and with a scene python-fcl clearance of the solved backbone."""
        return self._judge(self._forward(tensions, loads), tensions, positions, quats, loads,
                           timing)

    def _forward(self, tensions: np.ndarray, loads: StaticLoads,
                 start_moment: np.ndarray | None = None,
                 start_jacobian: np.ndarray | None = None) -> StaticsResult:
        """The verdict's fresh forward statics of ``tensions`` under ``loads`` (from
        ``start_moment`` and ``start_jacobian``, world frame, where given:
        ``solve_statics``)."""
        return solve_statics(self.robot, tensions, loads.tip_force, loads.tip_moment,
                             loads.gravity, self.config.statics,
                             distributed_force=loads.distributed_force,
                             point_loads=loads.point_load_lists(), start_moment=start_moment,
                             start_jacobian=start_jacobian)

    def _judge(self, statics: StaticsResult, tensions: np.ndarray, positions: np.ndarray,
               quats: np.ndarray, loads: StaticLoads, timing: StageTiming) -> TensionIKResult:
        """The verdict on the forward statics ``statics`` of ``tensions``."""
        cfg = self.config
        position_error = np.linalg.norm(statics.tip_position - positions, axis=1)
        oriented = ~np.any(np.isnan(quats), axis=1)
        rotation_error = np.full(len(positions), np.nan)
        for i in np.flatnonzero(oriented):
            rel = matrix_from_wxyz(quats[i]).T @ statics.tip_rotation[i]
            rotation_error[i] = np.arccos(np.clip(0.5 * (np.trace(rel) - 1.0), -1.0, 1.0))
        pose_error = np.sqrt(position_error ** 2
                             + np.where(oriented, self.length * np.nan_to_num(rotation_error),
                                        0.0) ** 2)
        pose_error = np.where(statics.converged, pose_error, np.nan)
        limits = np.maximum(np.max(-tensions, axis=1),
                            np.max(tensions - self.tension_max, axis=1)).clip(0.0)
        per_segment = (statics.positions.shape[1] - 1) // len(self.robot.segments)
        checked = check_chains(self.robot, self.scene, statics.positions, per_segment)
        verdicts = judge_many(
            margin=cfg.safety_margin, limits=limits,
            min_clearance=None if self.scene is None else checked.obstacle_distance,
            self_clearance=checked.self_distance, pose_error=pose_error,
            pose_tolerance=cfg.tolerance)
        reason = [r if c else f"the forward statics did not converge (residual {res:.1e} N·m)"
                  for r, c, res in zip(verdicts.reason, statics.converged, statics.residual,
                                       strict=True)]
        return TensionIKResult(
            robot=self.robot, tensions=tensions, target_position=positions, target_wxyz=quats,
            position=np.array(statics.tip_position), wxyz=np.array(statics.tip_wxyz),
            pose_error=pose_error,
            position_error=position_error, rotation_error=rotation_error,
            min_clearance=np.array(checked.obstacle_distance),
            max_violation=np.array(verdicts.max_violation),
            success=np.array(verdicts.success & statics.converged), reason=reason,
            tip_force=loads.tip_force, tip_moment=loads.tip_moment, gravity=loads.gravity,
            distributed_force=loads.distributed_force,
            point_loads=loads.point_load_lists(),
            tendon_displacements=np.array(statics.tendon_displacements), timing=timing,
            violations=dict(verdicts.violations), base_moment=np.array(statics.base_moment))


def solve_tension_ik(robot: Robot | str | dict, positions: Any, wxyz: Any = None,
                     **loads: Any) -> TensionIKResult:
    """One-call tension-space IK with the default config (see ``TensionIKSolver.solve``):
    positions in metres, wxyz unit quaternions, loads in N and N·m; tensions in N."""
    return TensionIKSolver(robot).solve(positions, wxyz, **loads)
