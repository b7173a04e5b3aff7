"""Path following in tension space on the Cosserat rod model: tendon tensions that put
the tip at each waypoint of a reference path (positions, or poses) under gravity and
loads, one quasi-static motion judged as a whole, through the stages.

- explore: each waypoint is a tension-space IK problem (``tasks.mechanics.ik``), solved in
  blocks of ``block`` consecutive waypoints in one batch, every waypoint of a block
  warm-started from the answer before the block: its tensions and its moment at the base
  M(0), so the LM starts at an equilibrium and stays on that answer's branch (the first
  waypoint from the nearest clear pool seeds); a waypoint whose answer fails its own check
  is solved again from its predecessor's answer, then from the pool's nearer seeds.
- refine: the whole motion at once by the banded LM (``stages.refine``'s
  ``solve_motion``): every waypoint's tip, equilibrium and clearance rows, and between
  neighbours a smoothness term and a hinge on the tension rate (aiming at ``rate_margin``
  of the limit). Solved together, the waypoints stay on one branch of the redundant
  tension sets and keep the rate limit, where waypoints solved one by one jump between
  branches.
- where the refined motion does not verify (the branch the answers followed ran into an
  obstacle, the tension bound or a tip it cannot reach), the branch search
  (``_follow_branches``) carries several branches along the path at once and the chain
  refines its cheapest motion; where that fails too, the per-waypoint answers are
  repaired (the waypoint after a too-fast change solved again from the one before it).
  The better verified motion is kept; ``stage`` and ``notes`` say which.

The verdict (``tasks.mechanics._motion.verify_tension_motion``) is independent of the LM: a
fresh forward statics solve at every waypoint and at ``samples_between`` interpolated
tension sets between each pair, converged; the tensions within [0, τ_max]; their rates
within ``tension_rate_max``; python-fcl clearance of every solved backbone; and every
waypoint's tip within ``tolerance``. A path that needs a faster change or passes through
an obstacle fails the verdict, naming where; it is not retimed.

Exact mode (``exact=True``): a motion the verdict rejects is polished by Ipopt on the
rod's own discrete equations (``stages.polish``'s ``polish_tension_motion``: every
waypoint's and checked sample's equilibrium, every tip at its target, the tension bounds,
the rate and the clearance as constraints, the smoothest motion as the objective), and a
polish the verdict accepts is kept (``_motion_polish``).

Units: metres, radians, seconds, newtons, N·m, m/s².
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ...model import Robot
from ...model.cosserat import solve_statics
from ...model.loads import StaticLoads, static_loads
from ...stages.polish import check_time_limit
from ...stages.refine import (
    MotionTerms,
    base_frame,
    solve_motion,
    tensions_of_unknowns,
    unknowns_of,
)
from ...world.scene import Scene
from .._result import Stage
from .._timing import StageTiming
from ..paths import ReferencePath
from ..readers import checked_path
from ._follow_branches import LM_BATCH, BranchSearch, branch_search, first_answers
from ._motion import TensionMotionVerification, verify_tension_motion
from ._motion_polish import polish_motion
from ._motion_result import TensionFollowResult as TensionFollowResult
from .ik import TensionIKConfig, TensionIKSolver

SWEEP_SEEDS = 8
"""Pool seeds (nearest tips first) of the first waypoint's LM runs, one batch."""


@dataclass(frozen=True)
class TensionFollowConfig:
    """Settings of tension-space path following."""

    tolerance: float = 1e-3
    """A waypoint is reached when the fresh solve's tip is within this of it (m; with
    orientations the pose error √(‖Δp‖² + (L·Δθ)²))."""
    tension_rate_max: float = 50.0
    """The largest |dτ/dt| of any tendon, N/s."""
    safety_margin: float = 0.002
    """δ, metres: the clearance kept from obstacles and between segments two apart."""
    samples_between: int = 2
    """Interpolated tension sets checked between consecutive waypoints."""
    block: int = 8
    """Waypoints solved together, each warm-started from the waypoint before the block."""
    smooth_passes: int = 16
    """Passes that re-solve the waypoint after a too-fast tension change from the one
    before it (``TensionPathFollower._smooth``), where the branch search found no motion
    the verdict accepts."""
    retry_seeds: int = 2
    """Waypoints that fail are solved again from their predecessor, then from this many
    further pool seeds."""
    chain_iterations: int = 40
    """Iterations of the banded LM over the whole motion (0: no chain refine)."""
    smooth_weight: float = 1e-2
    """s of the chain's smoothness rows s·Δτ/τ_max (m): keeps the motion on one branch of
    the redundant tension sets."""
    rate_weight: float = 1.0
    """h of the chain's rate hinge rows h·max(0, |Δτ| − κ·τ̇_max·dt)/τ_max (m)."""
    rate_margin: float = 0.9
    """κ: the chain aims at this fraction of ``tension_rate_max``."""
    branch_width: int = 8
    """Where the verdict rejects the chain over the per-waypoint answers: tension sets
    kept per waypoint by the branch search (``_follow_branches``; 0: no search), whose
    motion is then refined by the chain; kept where it verifies (on the fitted FTDCR rod's
    clutter scenes it followed the 7 of 12 paths the per-waypoint answers could not,
    2.5–5 s of search each; width 6 lost one, 4 lost three)."""
    branch_tries: int = 1
    """LM runs from each kept set to the next waypoint (itself and ``tries − 1`` moved
    copies). Before the LM carried M(0) from one waypoint to the next, 4 were needed; now
    1 follows the same paths in 2.5–5 s instead of 7–12."""
    branch_spread: float = 1.0
    """The Gaussian move of those copies, N."""
    branch_distinct: float = 1.0
    """Kept sets differ by more than this on some tendon, N (0.2 N: copies of one branch,
    every one lost by waypoint 39 with width 8)."""
    polish_accepted: bool = False
    """Exact mode: also polish a motion the verdict accepts (kept where the polish verifies)."""
    polish: Any = None
    """Exact mode's ``stages.polish.TensionMotionPolishConfig`` (None: its defaults)."""
    waypoint_damping: float = 1e-2
    """The per-waypoint LM's starting damping (``TensionIKConfig.initial_damping``, which
    this replaces for the follower). Each waypoint starts from the one before, where short
    first steps keep the answer on that branch of the redundant tension sets; from pool
    seeds the IK starts at 1e-6 (on the 24-waypoint test path the rate peaked at 42 N/s
    with 1e-6, 12 N/s with 1e-2)."""
    ik: TensionIKConfig = field(default_factory=lambda: TensionIKConfig(
        tolerance=1e-4, pool_size=4096, retry_seeds=0, clearance_buffer=0.001))
    """The per-waypoint tension IK (its pool seeds the first waypoint; its clearance rows
    and LM rules serve the chain too). The follower runs its LM in one round from
    ``waypoint_damping``. Its band is 1 mm beyond δ, where the IK's is 0.5 mm: the verdict
    also checks tension sets between the waypoints, which the rows do not see (on six
    60-waypoint paths in clutter, 0.5 mm left one 0.16 mm inside δ between two waypoints,
    2 mm kept one from reaching its waypoints; 1 mm followed all six)."""


def _reference(path: Any, dt: float | None) -> ReferencePath:
    """A ``ReferencePath`` from a path, a file or bundled name, or (T, 3) positions (m)."""
    if isinstance(path, (np.ndarray, list, tuple)):
        positions = np.asarray(path, dtype=float)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"path: expected (T, 3) positions in metres, got shape "
                             f"{positions.shape}")
        wxyz = np.tile([1.0, 0.0, 0.0, 0.0], (len(positions), 1))
        path = ReferencePath("positions", positions, wxyz, 0.1 if dt is None else dt,
                             np.ones(len(positions), bool))
    return checked_path(path, dt)


class TensionPathFollower:
    """Tension-space path following of a robot with a ``mechanics`` block (numpy in/out)."""

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | None = None,
                 config: TensionFollowConfig = TensionFollowConfig()) -> None:
        self.config = config
        self.ik = TensionIKSolver(robot, scene, replace(
            config.ik, initial_damping=config.waypoint_damping, round_iterations=0))
        self.robot, self.scene = self.ik.robot, self.ik.scene
        self._seeding: TensionIKSolver | None = None

    def follow(self, path: Any, *, dt: float | None = None, orientation: bool = False,
               tip_force: Any = None, tip_moment: Any = None, gravity: Any = None,
               distributed_force: Any = None, point_loads: Any = None,
               exact: bool = False, time_limit: float | None = None) -> TensionFollowResult:
        """Tensions for every waypoint of ``path``, judged as one motion.

        Args:
            path: a ``ReferencePath``, a path file or bundled name ("square", …), or
                (T, 3) tip positions, m, world frame.
            dt: seconds between waypoints (default: the path's own; 0.1 for positions).
            orientation: also reach the path's orientations (default positions only).
            tip_force, tip_moment, gravity, distributed_force: (3,) loads throughout the
                motion, world frame: N, N·m, m/s², N/m (default none).
            point_loads: ``[{"s": m, "force": [N], "moment": [N·m]}]``, world frame.
            exact: polish a motion the verdict rejects with Ipopt (every waypoint's and
                sample's equilibrium, the tips at their targets, the bounds, the rate and
                the clearance as constraints; ``stages.polish``'s ``polish_tension_motion``)
                and keep a polish the verdict accepts (``Stage.POLISH``).
            time_limit: with ``exact``, seconds of polishing (None: no limit).

        Returns:
            ``TensionFollowResult``: tensions (T, n) N, the verdict's tip, backbone and
            errors per waypoint, success and reason for the whole motion.

        Raises:
            ValueError: a malformed path or load (naming the waypoint or key).
        """
        check_time_limit(time_limit, "time_limit")
        start = time.perf_counter()
        reference = _reference(path, dt)
        count = len(reference)
        loads = static_loads(1, self.ik.length, tip_force, tip_moment, gravity,
                             distributed_force, point_loads)
        positions = reference.positions
        quats = (reference.wxyz if orientation else np.full((count, 4), np.nan))
        timing = StageTiming()
        tensions, moments = self._sweep(positions, quats, loads)
        tensions, moments = self._retry(tensions, moments, positions, quats, loads)
        timing.explore = time.perf_counter() - start
        start = time.perf_counter()
        chained = self._chain(tensions, reference.dt, positions, quats, loads)
        timing.refine = time.perf_counter() - start
        start = time.perf_counter()
        report = self.verify_tensions(chained, reference.dt, loads)
        timing.verify = time.perf_counter() - start
        stage, notes = ((Stage.REFINE, ["banded LM over the whole motion"])
                        if self.config.chain_iterations > 0 and count > 1 else
                        (Stage.EXPLORE, ["per-waypoint answers (no chain refine)"]))
        alternative = None
        tolerance = self.config.tolerance
        if not _whole(report, positions, tolerance):    # the branch search; the better motion
            found, note = self._branches(positions, quats, loads, reference.dt, timing)
            if found is not None and _better(found[1], report, positions, tolerance):
                why = report.reason or "waypoints missed"
                alternative, (chained, report, stage, notes) = chained, found
                notes = [*notes, f"(the motion refined from the per-waypoint answers: {why})"]
            else:
                notes = [*notes, note]
        if not _whole(report, positions, tolerance):    # the per-waypoint repair
            start = time.perf_counter()
            smoothed = self._smooth(tensions, moments, reference.dt, positions, quats, loads)
            timing.explore += time.perf_counter() - start
            start = time.perf_counter()
            other = self.verify_tensions(smoothed, reference.dt, loads)
            if _better(other, report, positions, tolerance):
                why = report.reason or "waypoints missed"
                alternative, chained, report = chained, smoothed, other
                stage, notes = Stage.EXPLORE, [
                    f"per-waypoint answers (the motion refined as a whole was worse: {why})",
                    *notes[1:]]
            elif alternative is None:
                alternative = smoothed
            timing.verify += time.perf_counter() - start
        result = self._result(chained, reference, quats, loads, report, stage, notes)
        result.timing = timing
        if exact:
            result = self._polish(result, alternative, reference, quats, loads, timing,
                                  time_limit)
        return result

    def _polish(self, result: TensionFollowResult, alternative: np.ndarray | None,
                reference: ReferencePath, quats: np.ndarray, loads: StaticLoads,
                timing: StageTiming, time_limit: float | None) -> TensionFollowResult:
        """Exact mode (``_motion_polish.polish_motion``): the motion, then the other
        motion the refine stage made (the per-waypoint repair or the chain), polished with
        every waypoint's tip at its target."""
        from ...stages.polish import TensionMotionPolishConfig, polish_tension_motion

        cfg = self.config
        candidates = [(result.tensions, f"the {result.stage.value} stage's motion")]
        if alternative is not None and not np.array_equal(alternative, result.tensions):
            candidates.append((alternative, "the other refine-stage motion"))
        oriented = not np.any(np.isnan(quats))

        def polish(tensions: np.ndarray, budget: float | None) -> Any:
            return polish_tension_motion(
                self.robot, self.scene, tensions, loads, dt=reference.dt,
                rate_max=cfg.tension_rate_max, margin=cfg.safety_margin,
                samples_between=cfg.samples_between, targets=reference.positions,
                wxyz=quats if oriented else None, statics_config=cfg.ik.statics,
                time_limit=budget, config=cfg.polish or TensionMotionPolishConfig())

        def remake(tensions: np.ndarray) -> TensionFollowResult:
            report = self.verify_tensions(tensions, reference.dt, loads)
            return self._result(tensions, reference, quats, loads, report,
                                notes=list(result.notes))

        return polish_motion(result, candidates, polish, remake, timing, time_limit,
                             self.config.polish_accepted)

    def _branches(self, positions: np.ndarray, quats: np.ndarray, loads: StaticLoads,
                  dt: float, timing: StageTiming
                  ) -> tuple[tuple[np.ndarray, TensionMotionVerification, Stage, list[str]]
                             | None, str]:
        """The branch search's motion (``_follow_branches``) and the chain over it, the
        better of the two by the verdict: (tensions, verdict, stage, notes), or None where
        the search is off or no branch reaches the last waypoint; and a note saying why
        not. ``timing`` gets the seconds."""
        cfg = self.config
        if cfg.branch_width <= 0:
            return None, "no branch search (branch_width 0)"
        start = time.perf_counter()
        motion, reached = branch_search(
            self.ik, self._seeding_ik(), positions, quats, loads,
            cfg.tension_rate_max * dt * (1 - 1e-9),
            BranchSearch(cfg.branch_width, cfg.branch_tries, cfg.branch_spread,
                         cfg.branch_distinct))
        timing.explore += time.perf_counter() - start
        if motion is None:
            return None, f"the branch search lost every branch at waypoint {reached}"
        start = time.perf_counter()
        chained = self._chain(motion, dt, positions, quats, loads)
        timing.refine += time.perf_counter() - start
        start = time.perf_counter()
        own, over = (self.verify_tensions(m, dt, loads) for m in (motion, chained))
        timing.verify += time.perf_counter() - start
        worse = "the branch search's motion was not better"
        if _better(own, over, positions, cfg.tolerance):
            return (motion, own, Stage.EXPLORE, [
                f"branch search over the waypoints (the chain over it was worse: "
                f"{over.reason or 'waypoints missed'})"]), worse
        return (chained, over, Stage.REFINE, [
            "branch search over the waypoints, then the banded LM over the whole motion"]), worse

    def _chain(self, tensions: np.ndarray, dt: float, positions: np.ndarray,
               quats: np.ndarray, loads: StaticLoads) -> np.ndarray:
        """The whole motion refined at once by the banded LM (``stages.refine``'s
        ``solve_motion``): every waypoint's tip, equilibrium and clearance rows, and
        between neighbours the smoothness and tension-rate rows, from the per-waypoint
        answers ``tensions`` (T, n) N; M(0) of each starts at a fresh statics solve's."""
        cfg, ik = self.config, self.ik
        count = len(tensions)
        if cfg.chain_iterations <= 0 or count < 2:
            return tensions
        every = loads.rows(np.zeros(count, int))
        shoot, params, _ = ik.waypoint_params(positions, quats, every)
        solved = solve_statics(self.robot, tensions, every.tip_force, every.tip_moment,
                               every.gravity, cfg.ik.statics,
                               distributed_force=every.distributed_force,
                               point_loads=every.point_load_lists())
        terms = MotionTerms(ik.terms(shoot), rate_step=cfg.rate_margin * cfg.tension_rate_max
                            * dt, smooth_weight=cfg.smooth_weight, rate_weight=cfg.rate_weight)
        z0 = unknowns_of(terms.waypoint, tensions, base_frame(self.robot, solved.base_moment))
        z, _, _ = solve_motion(terms, z0, params, ik.scene_arrays, np.ones_like(z0),
                               cfg.chain_iterations, ik.lm_config())
        return tensions_of_unknowns(terms.waypoint, z)

    def _sweep(self, positions: np.ndarray, quats: np.ndarray,
               loads: StaticLoads) -> tuple[np.ndarray, np.ndarray]:
        """Blocks of waypoints, each warm-started from the answer before it (its tensions
        and M(0)): the tensions (T, n) N and their M(0) (T, 3) N·m, base frame."""
        count, block = len(positions), max(1, self.config.block)
        tensions = np.zeros((count, self.robot.n_tendons))
        moments = np.zeros((count, 3))
        previous, moment = self._first(positions, quats, loads)
        for first in range(0, count, block):
            rows = np.arange(first, min(first + block, count))
            tensions[rows], moments[rows] = self.ik._lm_carried(
                np.repeat(previous, len(rows), axis=0), positions[rows], quats[rows],
                loads.rows(np.zeros(len(rows), int)),
                None if moment is None else np.repeat(moment, len(rows), axis=0),
                smallest=LM_BATCH)
            previous, moment = tensions[rows[-1:]], moments[rows[-1:]]
        return tensions, moments

    def _first(self, positions: np.ndarray, quats: np.ndarray,
               loads: StaticLoads) -> tuple[np.ndarray, np.ndarray]:
        """The first waypoint's answer (1, n) N and its M(0) (1, 3) N·m, base frame: the
        IK's LM from the ``SWEEP_SEEDS`` nearest clear pool seeds, the nearest seed's answer
        that passes the waypoint's check (else the closest tip). From the nearest seed by
        the waypoints' short first steps it missed the tip by 8.6 mm on a fitted FTDCR
        path."""
        answers, moments, passed = first_answers(self._seeding_ik(), positions, quats,
                                                 loads, range(SWEEP_SEEDS))
        pick = int(np.argmax(passed)) if passed.any() else 0
        return answers[pick:pick + 1], moments[pick:pick + 1]

    def _seeding_ik(self) -> TensionIKSolver:
        """The IK with its own first damping (long first steps, as from a pool seed); the
        follower's ``ik`` takes short ones (a warm start keeps its branch)."""
        if self._seeding is None:
            self._seeding = self.ik.with_lm(round_iterations=0,
                                            initial_damping=self.config.ik.initial_damping)
        return self._seeding

    def _retry(self, tensions: np.ndarray, moments: np.ndarray, positions: np.ndarray,
               quats: np.ndarray, loads: StaticLoads) -> tuple[np.ndarray, np.ndarray]:
        """Waypoints whose own check fails, again from their predecessor's answer, then
        from further pool seeds; an attempt is kept where it passes its check (tip,
        bounds, clearance of the scene), or fails it closer to the target. Returns the
        tensions and their M(0) (``_sweep``'s)."""
        count = len(positions)
        check = self.ik._verdict(tensions, positions, quats, loads.rows(np.zeros(count, int)),
                                 StageTiming())
        error = np.nan_to_num(check.pose_error, nan=np.inf)
        for attempt in range(self.config.retry_seeds + 1):
            failed = np.flatnonzero(~check.success)
            if not failed.size:
                break
            part = loads.rows(np.zeros(len(failed), int))
            if attempt == 0:
                before = np.maximum(failed - 1, 0)
                seeds, moment = tensions[before], moments[before]
            else:
                seeds, moment = self.ik._start(positions[failed], part, attempt)
            again, again_moments = self.ik._lm_carried(seeds, positions[failed],
                                                       quats[failed], part, moment,
                                                       smallest=LM_BATCH)
            judged = self.ik._verdict(again, positions[failed], quats[failed], part,
                                      StageTiming())
            new_error = np.nan_to_num(judged.pose_error, nan=np.inf)
            # A check passed (e.g. another tension set for the same tip that is clear of
            # the scene) beats any failed one; among failed ones the closer tip wins.
            better = judged.success | (new_error < error[failed])
            tensions[failed[better]] = again[better]
            moments[failed[better]] = again_moments[better]
            error[failed[better]] = new_error[better]
            check.success[failed[better]] = judged.success[better]
        return tensions, moments

    def _smooth(self, tensions: np.ndarray, moments: np.ndarray, dt: float,
                positions: np.ndarray, quats: np.ndarray, loads: StaticLoads) -> np.ndarray:
        """Where the tensions jump faster than ``tension_rate_max`` (a block's far
        waypoints landed on another tension set for the same tip), the waypoint after the
        jump is solved again from the one before it, pass after pass (each pass carries
        the branch one waypoint on); an answer is kept where it passes its check and
        slows the jump."""
        rate_max = self.config.tension_rate_max
        for _ in range(self.config.smooth_passes):
            rate = np.max(np.abs(np.diff(tensions, axis=0)), axis=1) / dt
            steps = np.flatnonzero(rate > rate_max)
            if not steps.size:
                break
            rows = steps + 1
            part = loads.rows(np.zeros(len(rows), int))
            again, again_moments = self.ik._lm_carried(tensions[steps], positions[rows],
                                                       quats[rows], part, moments[steps],
                                                       smallest=LM_BATCH)
            judged = self.ik._verdict(again, positions[rows], quats[rows], part,
                                      StageTiming())
            slower = np.max(np.abs(again - tensions[steps]), axis=1) / dt < rate[steps]
            keep = judged.success & slower
            if not keep.any():
                break
            tensions[rows[keep]] = again[keep]
            moments[rows[keep]] = again_moments[keep]
        return tensions

    def verify_tensions(self, tensions: np.ndarray, dt: float,
                        loads: StaticLoads) -> TensionMotionVerification:
        """The independent check of a motion (``verify_tension_motion``) with this
        follower's scene, margin and limits."""
        cfg = self.config
        return verify_tension_motion(self.robot, self.scene, tensions, dt, loads,
                                     margin=cfg.safety_margin, rate_max=cfg.tension_rate_max,
                                     samples_between=cfg.samples_between,
                                     statics=cfg.ik.statics)

    def verify(self, result: TensionFollowResult) -> TensionMotionVerification:
        """The verdict of a result again, from its tensions and loads alone (a typed
        report; ``result`` is not changed)."""
        loads = static_loads(1, self.ik.length, **result.loads())
        return self.verify_tensions(result.tensions, result.dt, loads)

    def _result(self, tensions: np.ndarray, reference: ReferencePath, quats: np.ndarray,
                loads: StaticLoads, report: TensionMotionVerification,
                stage: Stage = Stage.REFINE,
                notes: list[str] | None = None) -> TensionFollowResult:
        """The result of a judged motion, with its tracking errors."""
        position_error = np.linalg.norm(report.tip_position - reference.positions, axis=1)
        oriented = ~np.any(np.isnan(quats), axis=1)
        rotation_error = np.full(len(tensions), np.nan)
        for i in np.flatnonzero(oriented):
            w = np.abs(np.dot(quats[i], report.tip_wxyz[i]))
            rotation_error[i] = 2.0 * np.arccos(np.clip(w, 0.0, 1.0))
        pose_error = np.sqrt(position_error ** 2 + np.where(
            oriented, self.ik.length * np.nan_to_num(rotation_error), 0.0) ** 2)
        reached = pose_error <= self.config.tolerance
        result = TensionFollowResult(
            robot=self.robot, tensions=tensions, dt=reference.dt,
            position=report.tip_position, wxyz=report.tip_wxyz, backbone=report.backbone,
            clearance=report.clearance, min_clearance=report.min_clearance,
            max_violation=report.max_violation, success=False, reason="",
            tip_force=loads.tip_force[0], tip_moment=loads.tip_moment[0],
            gravity=loads.gravity[0], distributed_force=loads.distributed_force[0],
            point_loads=loads.point_load_lists()[0],
            tension_rate_max=self.config.tension_rate_max, stage=stage, notes=notes or [],
            target_position=reference.positions, target_wxyz=quats,
            position_error=position_error, rotation_error=rotation_error, reached=reached,
            tolerance=self.config.tolerance)
        result.judged(report)
        if not reached.all():
            missed = np.flatnonzero(~reached)
            words = (f"{len(missed)} of {len(reached)} waypoints not reached within "
                     f"{self.config.tolerance:g} m (first: waypoint {missed[0]}, error "
                     f"{pose_error[missed[0]]:.3g} m)")
            result.reason = "; ".join(filter(None, [words, result.reason]))
            result.success = False
        return result


def _reached(report: TensionMotionVerification, positions: np.ndarray,
             tolerance: float) -> int:
    """Waypoints (T, 3) m whose fresh tip is within ``tolerance`` (position only)."""
    return int(np.sum(np.linalg.norm(report.tip_position - positions, axis=1) <= tolerance))


def _whole(report: TensionMotionVerification, positions: np.ndarray, tolerance: float) -> bool:
    """The motion verifies and reaches every waypoint (T, 3) m within ``tolerance``."""
    return report.success and _reached(report, positions, tolerance) == len(positions)


def _better(a: TensionMotionVerification, b: TensionMotionVerification,
            positions: np.ndarray, tolerance: float) -> bool:
    """Whether motion check ``a`` beats ``b`` on the path ``positions`` (T, 3) m: verified
    and every waypoint within ``tolerance`` first, then more waypoints reached, then the
    smaller largest violation (position only: a check of a fresh solve's tips)."""
    reached = [_reached(r, positions, tolerance) for r in (a, b)]
    whole = [_whole(r, positions, tolerance) for r in (a, b)]
    if whole[0] != whole[1]:
        return whole[0]
    if reached[0] != reached[1]:
        return reached[0] > reached[1]
    return a.max_violation < b.max_violation


def follow_tension_path(robot: Robot | str | dict, path: Any, scene: Scene | str | None = None,
                    **options: Any) -> TensionFollowResult:
    """One-call tension-space path following with the default config (see
    ``TensionPathFollower.follow``): a path of tip positions in metres (or poses), loads in N,
    N·m, m/s², N/m; returns tensions per waypoint in N."""
    return TensionPathFollower(robot, scene).follow(path, **options)

from ..._moved import moved_names  # noqa: E402 — the old names, for one release

__getattr__ = moved_names(__name__, {"TensionFollower": ":TensionPathFollower",
                                     "follow_tensions": ":follow_tension_path"})
