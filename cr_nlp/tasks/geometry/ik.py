"""Inverse kinematics: the problem, the batched solver's wiring and its result.

Problem (docs/design.md §2): z = bending-vector configuration; f = ½‖log(T_tip⁻¹·T_target)‖²
as LM residuals (``ik_residual``); limits by projection; clearance ≥ δ (penalty in JAX, a
real constraint in the exact stage), and the same for the self-clearance between
segments at least two apart, with or without a scene; success is judged independently
of the optimiser by ``world.verdict`` (``IKSolver.verify``): pose error <
``IKConfig.success_tolerance`` re-evaluated in float64, every limit held, clearance ≥ δ
to obstacles (python-fcl) and between segments at least two apart.

Stages: explore, refine and the retries are ``stages.refine._ik_driver`` (a Sobol seed pool
held on the device, the pool entries nearest each target, the fused search program of
``stages.refine._ik_program`` per chunk of targets, one retry program for the targets still
failing, and without a scene the self-clearance repair of the few answers whose segments
come closer than δ); polish (optional) is ``stages.polish._ik_nlp`` under the one acceptance
policy of ``stages.polish._accept``. Large batches stream through in parts of
``IKConfig.stream_size``.
"""

from __future__ import annotations

import operator
import time
from dataclasses import dataclass
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..._compile_effort import LARGE_IK, full_effort
from ...model import Robot, load_robot
from ...model.derivatives import pose_residual
from ...model.limits import project_z
from ...model.rotations import matrix_from_wxyz
from ...runtime import configure
from ...stages import SMALLEST_CHUNK as SMALLEST_CHUNK
from ...stages import chunk_plan as chunk_plan
from ...stages.polish import check_time_limit, polish_note
from ...stages.refine import IKSearch, LMConfig, RetryPlan, SearchPlan, SearchSettings
from ...world import Scene, check_many, load_scene, scene_arrays
from ...world._penalty import sphere_clearances_z
from ...world._verdict_program import answer_geometry
from ...world.clearance import body_gap_tolerance
from ...world.verdict import judge_many
from .._result import Stage
from .._targets import validate_targets as validate_targets
from .._timing import StageTiming
from ._ik_result import COLUMNS as COLUMNS
from ._ik_result import PER_TARGET
from ._ik_result import IKResult as IKResult
from ._ik_result import IKVerification as IKVerification


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
    the problems still improving go on (the others are masked out of the program)."""
    retry_rounds: int = 2
    """Extra rounds, with fresh random seeds, for the targets whose penalised residual is
    still above ``success_tolerance`` (all rounds in one program)."""
    retry_seeds: int = 32
    """Seeds per failing target in a retry round."""
    polish_attempts: int = 3
    """Exact mode: polishes per target at most, from the refined answer, then from the
    other candidates of the search's own beam, until the verdict accepts one."""
    polish_workers: int = 1
    """Exact mode: processes that polish targets in parallel (``stages.polish._process_pool``); 1
    polishes in this process. The answers are the same either way."""
    polish_time_limit: float | None = None
    """Exact mode: seconds of polishing per target, all its attempts together (None: no
    limit). A target out of time keeps the best answer the verdict accepted so far (its
    refined answer when no polish was accepted), with ``stage`` "refine (polish out of
    time: …)". The search before it and the verdict are not limited."""
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
    """Most targets per search program (each with its seeds); larger batches are split
    into chunks (``stages._chunks.chunk_plan``)."""
    large_chunk_size: int | None = None
    """Targets per search program of a batch (a stream part) of at least this many: whole
    chunks of it first, the rest as ``chunk_size`` chunks; one more compiled shape that
    only such batches use (a value not above ``chunk_size``: never). None: 4096 on a CPU,
    16 384 on an accelerator (see ``stream_size``). Host seconds outside the compiled
    programs per 100 000 tdcr3 targets on the CPU, alternated: 0.26 against 0.31–0.36 in
    1024-target chunks on a quiet machine; medians 0.35 against 0.38 (4 runs each) on a
    busy one."""
    stream_size: int | None = None
    """Most targets solved at once: a larger batch is streamed through the stages in
    parts of this many targets, so the memory a solve holds stays bounded whatever the
    batch (measured with tracemalloc, tdcr3: 2000 targets in one part peaked at 7.8 MB
    of host arrays, in parts of 500 at 2.3 MB). None: 16 384 on a CPU, 131 072 on an
    accelerator. Each part costs the host its own bookkeeping and verdict calls: 100 000
    tdcr3 targets in one process on the CPU, parts of 8192, 16 384 and 32 768 alternated
    (3 solves each, 2026-12-03): host seconds outside the compiled programs 0.39, 0.32,
    0.31 (medians), walls the same within noise, the solve's traced peak 101 MB in parts
    of 8192 and of 16 384. On one H200 (2026-12-04, three processes) 100 000 targets took
    1.07–1.25 s as one part of 16 384-target programs against 1.33–1.54 s in parts of
    16 384 with 4096-target programs (a GPU waits on each program's loops, so fewer,
    larger programs pay there)."""
    search_block: int | None = None
    """LM rows per block and device of the search programs; a round runs its active rows in as
    many blocks as they fill, so finished rows cost nothing. None: on a CPU 128 without
    a scene and 64 with one, on an accelerator the whole chunk (a masked row runs in
    parallel there). Measured (CPU s per solve, blocks 64 / 128): 1000 free tdcr3 targets
    0.33 / 0.26, lattice tdcr3 0.89 / 0.97, tdcr4_ext 1.64 / 2.07."""
    dtype: str = "float32"
    """JAX dtype of the batched stages ("float64" needs jax_enable_x64)."""
    seed: int = 0
    """Seed of the pool and of the retry samples."""

    def __post_init__(self) -> None:
        for name in ("chunk_size", "stream_size"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"IKConfig.{name} must be at least 1, got {getattr(self, name)}")
        if self.large_chunk_size is not None and self.large_chunk_size < 1:
            raise ValueError(f"IKConfig.large_chunk_size must be at least 1 or None, got "
                             f"{self.large_chunk_size}")
        check_time_limit(self.polish_time_limit, "IKConfig.polish_time_limit")


def part_sizes(config: IKConfig, backend: str) -> tuple[int, int]:
    """(targets per stream part, targets per program of a large part) of ``config`` on a
    JAX backend ("cpu", "gpu", …): its ``stream_size`` and ``large_chunk_size``, or where
    None the backend's (16 384 and 4096 on a CPU, 131 072 and 16 384 elsewhere)."""
    cpu = backend == "cpu"
    return (config.stream_size or (16384 if cpu else 131072),
            config.large_chunk_size or (4096 if cpu else 16384))


IKTiming = StageTiming
"""Seconds per stage of one ``IKSolver.solve`` call (the tasks' one ``StageTiming``)."""

# ---------------------------------------------------------------- the problem

def ik_residual(robot: Robot, margin: float, weight: float, z: jax.Array, target: Any,
                scene: Any, *, self_clearance: bool = True) -> jax.Array:
    """Residuals of one IK problem: the 6-vector pose error (m, rad) and
    √weight·max(0, δ − d) for each body sphere's nearest obstacle part (with a scene) and
    each body sphere's nearest self-clearance partner (with or without a scene, unless
    the robot has no self pairs; ``world._penalty.sphere_clearances_z``). The pose part
    differentiates by the model's closed-form Jacobian (``model.derivatives.pose_residual``).
    ``self_clearance`` False drops the self-clearance rows where there is no scene (the
    pose residual alone: the IK solver's fast first pass, ``IKSolver._solve_part``)."""
    pose = pose_residual(robot, z, target)
    if scene is None and not (self_clearance and robot.has_self_pairs):
        return pose
    shortfall = jnp.maximum(margin - sphere_clearances_z(robot, scene, z), 0.0)
    return jnp.concatenate([pose, jnp.sqrt(weight) * shortfall])


# ---------------------------------------------------------------- the solver

@dataclass(frozen=True)
class _Checked:
    """``IKSolver.verify``'s verdict on one answer, as ``stages.polish._accept`` reads it."""

    success: bool
    reason: str
    row: IKVerification | None
    """``verify``'s report on the answer alone (None: the result holds it)."""


_STAGES = np.array([Stage.REJECTED, Stage.REFINE], dtype=object)
"""A target's stage after the search by its validity (0: refused, 1: searched)."""


def _valid(reasons: list[str]) -> np.ndarray:
    """(T,) bool: the targets ``validate_targets`` gave no reason to refuse."""
    return np.fromiter(map(operator.not_, reasons), bool, len(reasons))


def _counter(name: str, doc: str) -> property:
    """A read-only ``IKSolver`` attribute: one of its search's ``SearchCounters``."""
    return property(lambda solver: getattr(solver._search.counters, name), doc=doc)


class IKSolver:
    """Batched IK for one robot (and optionally one scene); reuse it across calls.

    ``solve(positions, wxyz, exact=False)`` takes target positions (T, 3) in metres and
    orientations (T, 4) as unit quaternions (w, x, y, z) and returns an ``IKResult``.
    """

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | None = None,
                 config: IKConfig = IKConfig()) -> None:
        configure()
        self.robot = robot = load_robot(robot)
        self.scene = load_scene(scene) if isinstance(scene, str) else scene
        self.config = cfg = config
        self.dtype = jnp.dtype(cfg.dtype)
        # The sphere-body margin the optimisers enforce: implies config.safety_margin for
        # the capsule body that python-fcl checks.
        self.margin = cfg.safety_margin + body_gap_tolerance(robot)
        arrays = scene_arrays(self.scene, dtype=self.dtype) if self.scene is not None else None
        residuals = {own: partial(ik_residual, robot, float(self.margin),
                                  float(cfg.clearance_weight), self_clearance=own)
                     for own in (False, True)}
        # Without a scene the search solves the pose alone (the self-clearance rows made
        # a free tdcr3 solve ~8× slower) and repairs the few answers whose segments come
        # too close (``stages.refine._ik_driver``).
        self_repair = self.scene is None and robot.has_self_pairs
        free = np.ones(robot.dof)
        free[2::3] = ~robot.lengths_fixed()  # a fixed length is not a variable
        backend = jax.default_backend()
        cpu = backend == "cpu"
        # Targets per part of a solve's stream and per program of a large part, resolved.
        self.stream_size, self.large_chunk_size = part_sizes(cfg, backend)
        block = cfg.search_block
        if block is None:
            # A scene's clearance rows make each LM row several times heavier.
            block = (128 if self.scene is None else 64) if cpu else 1 << 30
        plan = SearchPlan(
            width=cfg.beam_width, coarse_iterations=cfg.coarse_iterations,
            refine_iterations=cfg.refine_iterations, refine_round=cfg.refine_round,
            per_target=True, min_distance=float(cfg.beam_min_distance), block=block,
            lm=LMConfig(cost_tolerance=0.5 * cfg.converged_error ** 2))
        retry = RetryPlan(rounds=cfg.retry_rounds, seeds=cfg.retry_seeds,
                          nearest=cfg.retry_seeds // 2, first_rank=cfg.seeds_per_target,
                          success_cost=0.5 * cfg.success_tolerance ** 2, seed=cfg.seed)
        self._search = IKSearch(
            robot, self.scene, arrays, (residuals[not self_repair], residuals[True]),
            partial(project_z, robot), jnp.asarray(free, self.dtype),
            SearchSettings(plan=plan, retry=retry, seeds_per_target=cfg.seeds_per_target,
                           pool_size=cfg.pool_size, seed=cfg.seed, chunk_size=cfg.chunk_size,
                           large_chunk_size=self.large_chunk_size, margin=float(self.margin),
                           safety_margin=cfg.safety_margin, dtype=cfg.dtype),
            self_repair)
        self._polisher: Any = None
        self._polish_pool: Any = None
        self.stream_parts: list[int] = []
        """Targets per part of the last ``solve``'s stream (``IKConfig.stream_size``)."""

    # The search's counters of the last ``solve``/``candidates`` (``stages.refine._ik_driver``).
    lm_calls = _counter("lm_calls", "Per round of a search program that iterated any row: "
                        "(rows iterated, rows of the chunk, budget, most iterations run).")
    retried = _counter("retried", "Targets retried in each retry round (0: did not run).")
    self_repaired = _counter("self_repaired", "Targets searched again with the "
                             "self-clearance rows (no scene: their answer came closer than δ).")
    device_calls = _counter("device_calls", "Compiled programs launched: device round trips.")
    device_launch = _counter("device_launch", "Seconds inside the calls that launch compiled "
                             "programs (on a CPU, XLA may run a program there).")
    device_wait = _counter("device_wait", "Seconds waiting for device results with no host "
                           "work to overlap (the device's share of the wall time).")

    def candidates(self, positions: Any, wxyz: Any) -> tuple[np.ndarray, np.ndarray]:
        """Several distinct IK answers per target (the refined beam), for callers that
        choose among them (path following picks the smoothest sequence).

        Args:
            positions: (T, 3) metres; wxyz: (T, 4) unit quaternions (valid targets only).
        Returns:
            q (T, B, 3n) configurations (θ, φ, L), best first, and their penalised
            residual norms (T, B) (pose error in m/rad plus the clearance penalty),
            B = ``beam_width``.
        """
        positions, wxyz, reasons = validate_targets(self.robot, positions, wxyz)
        if any(reasons):
            bad = next(i for i, r in enumerate(reasons) if r)
            raise ValueError(f"target {bad}: {reasons[bad]}")
        self._search.reset()
        return self._search.candidates(positions, matrix_from_wxyz(wxyz), IKTiming())

    # ------------------------------------------------------------ verification
    def verify(self, q: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
               self_clearance: np.ndarray | None = None) -> IKVerification:
        """Float64 re-evaluation of answers q (B, 3n; rad, rad, m) against targets
        (positions (B, 3) m, wxyz (B, 4)), independent of the optimiser's numbers, and
        the library's verdict on them (``world.verdict.judge_many``).

        The tip pose, the pose error and the distance between segments at least two apart
        in float64 (``world._verdict_program``: a compiled float64 program for large
        batches, numpy for small ones), the limits, and with a scene the python-fcl
        distance to the obstacles (``world.check``). Returns an ``IKVerification``: arrays
        (B, …) position, wxyz, pose_error, position_error (m), rotation_error (rad),
        obstacle_clearance and self_clearance (m, +inf where not checked), clearance (m,
        the smaller of the two, NaN when neither is checked), collision_free, and the
        verdicts: success, reason, violations per family and max_violation (rad or m: the
        largest limit violation or clearance shortfall below δ).
        ``self_clearance``: (B,) the answers' self-clearance by ``world.check`` when the
        caller has it already (no scene only; the search's self-repair measured it)."""
        robot = self.robot
        q = np.asarray(q, dtype=float).reshape(-1, robot.dof)
        found = answer_geometry(robot, q, positions, matrix_from_wxyz(wxyz),
                                self._search.counters,
                                self.scene is None and self_clearance is None)
        obstacle, own = np.full(len(q), np.inf), found.self_distance
        if self.scene is None and self_clearance is not None:
            own = np.asarray(self_clearance, dtype=float).reshape(len(q))
        elif self.scene is not None:
            # In parts of the stream's size: the check's temporaries grow with its rows.
            step = self.stream_size
            parts = [check_many(robot, self.scene, q[i:i + step])
                     for i in (range(0, len(q), step) if len(q) else [0])]
            obstacle = np.concatenate([c.obstacle_distance for c in parts])
            own = np.concatenate([c.self_distance for c in parts])
        nearest = np.minimum(obstacle, own)
        verdicts = judge_many(margin=self.config.safety_margin,
                              limits=found.limits, min_clearance=obstacle,
                              self_clearance=own, pose_error=found.pose_error,
                              pose_tolerance=self.config.success_tolerance)
        return IKVerification(
            position=found.position, wxyz=found.wxyz, pose_error=found.pose_error,
            position_error=found.position_error, rotation_error=found.rotation_error,
            obstacle_clearance=obstacle,
            self_clearance=own, clearance=np.where(np.isfinite(nearest), nearest, np.nan),
            collision_free=~(nearest < 0.0), verdicts=verdicts)

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
            exact: polish every answer with Ipopt, constraints as constraints (each
                target within ``config.polish_time_limit``, if set).
            progress: show a progress bar for the exact stage.

        From ``LARGE_IK`` targets on, programs this solve compiles are optimised fully
        at once (``cr_nlp._compile_effort``).
        """
        with full_effort(len(positions) >= LARGE_IK):
            return self._solve(positions, wxyz, exact, progress)

    def _solve(self, positions: Any, wxyz: Any, exact: bool, progress: bool) -> IKResult:
        timing = IKTiming()
        self._search.reset()
        self.stream_parts = []
        positions, wxyz, reasons = validate_targets(self.robot, positions, wxyz)
        valid = _valid(reasons)
        q_out = np.full((len(positions), self.robot.dof), np.nan)
        own = np.full(len(positions), np.inf)
        # The search's beams as bending vectors: made configurations only for a polish.
        beam = np.full((len(positions), self.config.beam_width, self.robot.dof), np.nan)
        idx = np.flatnonzero(valid)
        step = self.stream_size
        for start in range(0, len(idx), step):
            part = idx[start:start + step]
            self.stream_parts.append(len(part))

            def accepts(q: np.ndarray, rows: np.ndarray, part: np.ndarray = part) -> np.ndarray:
                return self.verify(q, positions[part[rows]], wxyz[part[rows]]).success

            q_out[part], found, own[part] = self._search.solve_part(
                positions[part], matrix_from_wxyz(wxyz[part]), timing, accepts)
            beam[part, :found.shape[1]] = found
        stage = _STAGES[valid.astype(np.int64)].tolist()
        self_checked = own if self._search.self_repair else None
        result = self._finish(q_out, positions, wxyz, reasons, stage, timing, self_checked)
        if exact and len(idx):
            self._polish(result, positions, wxyz, idx, beam, timing, progress)
        return result

    def _finish(self, q: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
                reasons: list[str], stage: list[Stage], timing: IKTiming,
                self_clearance: np.ndarray | None = None) -> IKResult:
        t0 = time.perf_counter()
        valid = _valid(reasons)
        n = len(q)
        fields = {k: np.full(n, np.nan) for k in PER_TARGET}
        result = IKResult(self.robot, q, np.full((n, 3), np.nan), np.full((n, 4), np.nan),
                          collision_free=np.zeros(n, bool), success=np.zeros(n, bool),
                          stage=list(stage), reason=list(reasons), timing=timing,
                          has_scene=self.scene is not None, **fields)
        rows = np.flatnonzero(valid)
        if len(rows):
            result.store(rows, self.verify(
                q[rows], positions[rows], wxyz[rows],
                None if self_clearance is None else self_clearance[rows]))
        timing.verify += time.perf_counter() - t0
        return result

    def _polish(self, result: IKResult, positions: np.ndarray, wxyz: np.ndarray,
                idx: np.ndarray, beam: np.ndarray, timing: IKTiming, progress: bool) -> None:
        """Exact stage (``tasks.geometry._ik_polish``): polish every answer; where the polish fails
        or the verdict rejects it, polish the other candidates of the search's own beam
        (``beam``: (T, width, 3n) bending vectors, best first) in turn, up to
        ``config.polish_attempts`` polishes in all. An accepted polish replaces the answer;
        otherwise the refined answer stays with its own verdict (exact mode never succeeds
        less often than the penalty stages). ``config.polish_time_limit`` bounds each
        target's polishes."""
        from ...stages.polish import IKPolisher, build_polisher
        from ._ik_polish import polish_answers

        t0 = time.perf_counter()
        if self._polisher is None:
            self._polisher = IKPolisher(self.robot, self.scene, safety_margin=self.margin)
        if self.config.polish_workers > 1 and self._polish_pool is None:
            from ...stages.polish import PolishPool
            self._polish_pool = PolishPool(build_polisher, (self.robot, self.scene, self.margin),
                                           self.config.polish_workers)
        todo = np.asarray(idx)

        def judge(q: np.ndarray, rows: np.ndarray) -> list[_Checked]:
            checked = self.verify(q, positions[todo[rows]], wxyz[todo[rows]])
            return [_Checked(bool(checked.success[j]), str(checked.reason[j]),
                             checked.take(np.array([j]))) for j in range(len(q))]

        accepted = polish_answers(
            self._polisher, result.q[todo], self._search.beam_q(beam[todo]),
            result.pose_error[todo],
            positions[todo], matrix_from_wxyz(wxyz[todo]),
            [_Checked(bool(result.success[i]), result.reason[i], None) for i in todo], judge,
            self.config.polish_attempts, progress, self._polish_pool,
            self.config.polish_time_limit)
        for i, outcome in zip(todo.tolist(), accepted.outcomes, strict=True):
            if outcome.accepted:
                result.q[i] = outcome.answer
                result.store(np.array([i]), outcome.verdict.row)
                result.set_stage(i, Stage.POLISH)
            else:
                result.set_stage(i, Stage.REFINE, polish_note(outcome))
        timing.verify += accepted.judge_seconds
        timing.polish += time.perf_counter() - t0 - accepted.judge_seconds


def solve_ik(robot: Robot | str | dict, positions: Any, wxyz: Any,
             scene: Scene | str | None = None, config: IKConfig = IKConfig(),
             exact: bool = False) -> IKResult:
    """One-call IK: see ``IKSolver.solve`` (positions in metres, wxyz unit quaternions)."""
    return IKSolver(robot, scene, config).solve(positions, wxyz, exact=exact)

from ..._moved import moved_names  # noqa: E402 — the old addresses, for one release (CHANGELOG 2026-12-02)

__getattr__ = moved_names(__name__, {"read_targets": "cr_nlp.tasks.readers"})
