"""Trajectory planning in tension space on the Cosserat rod model: from start tensions
to goal tensions (N) under gravity and loads, collision-free along the quasi-static
motion, within the tension bounds and the tension rate limit.

Between waypoints the tensions move linearly and the robot passes through the equilibria
of the interpolated tensions. A plan is a chain of straight legs in tension space: the
direct leg start → goal, or, where that leg's motion is not clear, start → via → goal
through the cheapest via tension set (fewest seconds at the rate limit) whose legs are
clear, else the quickest route through a roadmap in tension space (``stages.explore``'s
``tension_roadmap``: the via candidates joined to their nearest neighbours by clear legs,
cached on disk per robot, scene and load case; any number of vias). Via candidates come
from a pool of random tension sets solved once per planner and load case, kept where the
robot is clear of the scene.
Each leg is cut into the fewest waypoints ``dt`` apart that keep every tendon's rate
within ``tension_rate_max``, so the rate limit holds by construction, and a candidate is
screened on exactly the samples the verdict checks: every waypoint and
``samples_between`` interpolated tension sets between each pair, each a forward statics
solve and python-fcl on the solved backbone.

That search is the explore stage. The refine stage then optimises the searched motion as
a whole (``refine_motion``): resampled to ``time_slack`` times as many waypoints (the
search's legs run at the rate limit), it is solved by the banded LM over every waypoint's
tension set, M(0) and tip, with the start and goal fixed: the equilibrium and the backbone
clearance at every waypoint, and between neighbours the tip's step (a shorter tip path),
a smoothness term and a hinge on the tension rate (``stages.refine``'s ``MotionTerms``).
The LM has rows at the waypoints only, and a shortened motion can cut through an obstacle
between two clear waypoints; where the verdict rejects the refined motion, the tension sets
it checked on the failing steps become waypoints and the LM runs again (``repair_rounds``),
and where that is still rejected, motions part of the way from the searched motion to the
refined one are tried (``blends``; ``_motion_refine``). The refined motion is kept where it
verifies and its tip path (fresh statics along the motion) is no longer, else the search's
(``Stage.EXPLORE``; the notes say why).

Exact mode (``exact=True``) polishes the motions the verdict rejects with Ipopt on the
rod's own discrete equations (``stages.polish``'s ``polish_tension_motion``: every
waypoint's and checked sample's equilibrium, the tension bounds, the rate between
waypoints and the clearance as constraints, start and goal fixed, the smoothest motion as
the objective) and keeps a polish the verdict accepts (``_motion_polish``). A refined
motion the verdict rejected (the search's kept instead) is polished too, and kept where
the verdict accepts it and its tip path is no longer than the search's.

The verdict is the one of every tension motion (``tasks.mechanics._motion``): a fresh
solve at every checked sample, independent of the screening's, the LM's and Ipopt's.

Units: newtons, N/s, seconds, metres.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from functools import partial
from typing import Any

import numpy as np

from ...model import Robot, load_robot
from ...model.cosserat import StaticsConfig, solve_statics
from ...model.loads import StaticLoads, static_loads
from ...model.mechanics import require_mechanics
from ...model.tendon_groups import tensions_of_configuration
from ...stages.explore import leg_change
from ...stages.polish import check_time_limit
from ...world.clearance import scene_arrays
from ...world.scene import Scene, load_scene
from .._result import Stage
from .._timing import StageTiming
from ._motion import (
    TensionMotionVerification,
    interpolated,
    solve_and_check,
    verify_tension_motion,
    verify_tension_motions,
)
from ._motion_polish import polish_motion
from ._motion_refine import refine_chains, refined_plans, resampled
from ._motion_result import TensionTrajectoryResult as TensionTrajectoryResult

PROBLEM_KEYS = ("start", "goal")
"""The keys of one problem of a tension problems file."""
VIA_ROUNDS = (0, 4)
"""Where each via screening round starts among a problem's candidates (cheapest first)."""


@dataclass(frozen=True)
class TensionTrajectoryConfig:
    """Settings of tension-space trajectory planning."""

    dt: float = 0.05
    """Seconds between waypoints."""
    tension_rate_max: float = 50.0
    """The largest |dτ/dt| of any tendon, N/s."""
    safety_margin: float = 0.002
    """δ, metres: the clearance kept from obstacles and between segments two apart."""
    samples_between: int = 2
    """Interpolated tension sets checked between consecutive waypoints."""
    via_pool: int = 512
    """Random tension sets solved once per load case; the clear ones are via candidates."""
    via_candidates: int = 16
    """Via points screened per problem whose direct leg is not clear (cheapest first); on
    the roadmap, the nodes the start and the goal are joined to (nearest first)."""
    roadmap_neighbours: int = 10
    """Each via candidate's nearest candidates it is joined to on the roadmap (by clear
    legs), the roadmap built where a problem has no clear single via."""
    seed: int = 0
    """Seed of the via pool."""
    statics: StaticsConfig = StaticsConfig()
    """The rod discretisation of every forward solve."""
    chain_iterations: int = 30
    """Iterations of the banded LM that refines each searched motion (0: the search's
    motion as it is)."""
    tip_path_weight: float = 1.0
    """Weight of the refine's tip path length rows (each waypoint's step of the tip, m)."""
    rate_weight: float = 10.0
    """h of the refine's rate hinge rows h·max(0, |Δτ| − κ·τ̇_max·dt)/τ_max, m."""
    smooth_weight: float = 1e-2
    """s of the refine's smoothness rows s·Δτ/τ_max, m."""
    rate_margin: float = 0.9
    """κ: the refine aims at this fraction of ``tension_rate_max``."""
    time_slack: float = 1.5
    """The refined motion may take this many times the searched one's duration (the
    search's legs run at the rate limit, which leaves the refine no room): the searched
    motion is resampled to that many more waypoints before it is refined."""
    clearance_weight: float = 100.0
    """Weight of the refine's clearance rows of the solved backbones (against the tip
    path's 1: 10 let the shortened motions cut through obstacles)."""
    clearance_buffer: float = 0.002
    """The refine keeps the backbone's spheres this far beyond δ, m."""
    repair_rounds: int = 2
    """Rounds that mend a refined motion the verdict rejects: the checked samples of each
    failing step (``samples_between`` tension sets between two waypoints, where the LM has
    no rows) become waypoints, and the LM runs again on the whole motion."""
    repair_iterations: int = 10
    """LM iterations of each repair round."""
    blends: tuple[float, ...] = (0.75, 0.5, 0.25)
    """A refined motion still rejected after the repairs: motions this fraction of the way
    from the searched motion (resampled to as many waypoints) to the refined one, verified
    in turn; the first the verdict accepts is the refine's answer."""
    polish_accepted: bool = False
    """Exact mode: also polish a motion the verdict accepts (kept where the polish verifies)."""
    polish: Any = None
    """Exact mode's ``stages.polish.TensionMotionPolishConfig`` (None: its defaults)."""

    def __post_init__(self) -> None:
        if self.repair_rounds < 0:
            raise ValueError(f"repair_rounds must be ≥ 0, got {self.repair_rounds}")
        if self.repair_rounds and self.repair_iterations < 1:
            raise ValueError(f"repair_iterations must be ≥ 1, got {self.repair_iterations}")
        bad = [f for f in self.blends if not 0.0 < f < 1.0]
        if bad:
            raise ValueError(f"blends must be fractions between 0 and 1 (exclusive) of the "
                             f"way from the searched motion to the refined one, got {bad[0]!r}")


def check_tensions(robot: Robot, values: Any, where: str) -> np.ndarray:
    """One tension set (n,) N, checked: the robot's tendon count, finite, in
    [0, τ_max]. ``where`` names it in the error ("problem 3: start").

    Raises:
        ValueError: naming ``where``, the tendon and the problem.
    """
    n, tension_max = robot.n_tendons, float(robot.mechanics.tension_max)
    if isinstance(values, (str, bytes, dict)) or not hasattr(values, "__len__"):
        raise ValueError(f"{where}: expected a list of {n} tensions in N")
    if len(values) != n:
        raise ValueError(f"{where}: expected {n} tensions (the robot file's tendon order), "
                         f"got {len(values)}")
    out = np.zeros(n)
    for j, value in enumerate(values):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
            raise ValueError(f"{where}[{j}]: expected a number of newtons, got {value!r:.40}")
        x = float(value)
        if not math.isfinite(x) or x < 0.0:
            raise ValueError(f"{where}[{j}]: a tension must be a finite number ≥ 0 N (a "
                             f"tendon pulls), got {value!r:.40}")
        if x > tension_max:
            raise ValueError(f"{where}[{j}]: {x:g} N is above the robot's tension_max "
                             f"{tension_max:g} N")
        out[j] = x
    return out




class TensionTrajectoryPlanner:
    """Tension-space trajectory planning of a robot with a ``mechanics`` block."""

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | None = None,
                 config: TensionTrajectoryConfig = TensionTrajectoryConfig()) -> None:
        self.robot = load_robot(robot)
        require_mechanics(self.robot, "tension-space planning")
        self.scene = None if scene is None else load_scene(scene)
        self.config = config
        self.length = float(sum(s.length_min for s in self.robot.segments))
        self._vias: dict[bytes, np.ndarray] = {}
        self._roadmaps: dict[bytes, Any] = {}

    def clear(self, samples: np.ndarray, loads: StaticLoads) -> np.ndarray:
        """(k,) True where the solved robot of a tension set converged and keeps δ."""
        solved, checked = solve_and_check(self.robot, self.scene, samples, loads,
                                          self.config.statics)
        margin = self.config.safety_margin
        return (solved.converged & (checked.obstacle_distance >= margin)
                & (checked.self_distance >= margin))

    def _legs(self, points: list[np.ndarray]) -> np.ndarray:
        """The waypoints of straight legs through ``points``, each cut so that no tendon
        changes faster than the rate limit."""
        step = self.config.tension_rate_max * self.config.dt * (1 - 1e-9)
        out = [points[0][None]]
        for a, b in zip(points[:-1], points[1:], strict=True):
            count = max(1, math.ceil(float(leg_change(a, b)) / step))
            out.append(a + np.linspace(0.0, 1.0, count + 1)[1:, None] * (b - a))
        return np.concatenate(out)

    def vias(self, loads: StaticLoads) -> np.ndarray:
        """The via candidates under one load case: random tension sets (one or two
        tendons of each segment slack) where the robot is clear, (V, n) N; cached on disk
        with the roadmap (``stages.explore.clear_nodes``), so a new process under the same
        robot, scene and loads solves none of them again."""
        from ...stages.explore import clear_nodes

        key = _case_key(loads)
        if key not in self._vias:
            rng = np.random.default_rng(self.config.seed)
            per, n = self.robot.tendons.per_segment, self.robot.n_tendons
            size = self.config.via_pool
            tensions = rng.uniform(0.0, float(self.robot.mechanics.tension_max), (size, n))
            for s in range(n // per):
                tensions[np.arange(size), s * per + rng.integers(0, per, size)] = 0.0
            settings, arrays = self._cache_key(loads)
            self._vias[key] = clear_nodes(tensions, lambda sets: self.clear(sets, loads),
                                          settings, arrays)
        return self._vias[key]

    def _cache_key(self, loads: StaticLoads) -> tuple[dict[str, Any], tuple[np.ndarray, ...]]:
        """What a clear set and a clear leg depend on besides the tensions: the robot, the
        scene, δ and the rod's discretisation (JSON-able), the load case and the scene's
        geometry (arrays); the disk caches of the via sets and the roadmap key on them."""
        arrays = [*loads.arrays()]
        if self.scene is not None and self.scene.parts:
            arrays += list(scene_arrays(self.scene, as_numpy=True))
        settings = {"robot": self.robot.to_dict(),
                    "scene": None if self.scene is None else self.scene.to_dict(),
                    "margin": self.config.safety_margin, "statics": asdict(self.config.statics)}
        return settings, tuple(arrays)

    def _screen(self, plans: list[np.ndarray], loads: StaticLoads) -> np.ndarray:
        """(len(plans),) True where every sample the verdict will check is clear (one
        batch of forward solves for all plans)."""
        samples = [interpolated(p, self.config.samples_between)[0] for p in plans]
        if not samples:
            return np.zeros(0, bool)
        clear = self.clear(np.concatenate(samples), loads)
        bounds = np.cumsum([0, *(len(s) for s in samples)])
        return np.array([clear[a:b].all() for a, b in zip(bounds[:-1], bounds[1:],
                                                          strict=True)])

    def _verify(self, tensions: np.ndarray, loads: StaticLoads,
                dt: float | None = None) -> TensionMotionVerification:
        """The verdict of a motion (T, n) N under ``loads`` with this planner's settings
        (``_motion.verify_tension_motion``)."""
        cfg = self.config
        return verify_tension_motion(self.robot, self.scene, tensions,
                                     cfg.dt if dt is None else dt, loads,
                                     margin=cfg.safety_margin, rate_max=cfg.tension_rate_max,
                                     samples_between=cfg.samples_between, statics=cfg.statics)

    def verify_motions(self, motions: list[np.ndarray],
                       loads: StaticLoads) -> list[TensionMotionVerification]:
        """The verdicts of several motions (T_i, n) N under ``loads`` with this planner's
        settings, in one batch of fresh solves (``_motion.verify_tension_motions``)."""
        cfg = self.config
        return verify_tension_motions(self.robot, self.scene, motions, cfg.dt, loads,
                                      margin=cfg.safety_margin, rate_max=cfg.tension_rate_max,
                                      samples_between=cfg.samples_between,
                                      statics=cfg.statics)

    def plan(self, starts: Any, goals: Any, *, tip_force: Any = None, tip_moment: Any = None,
             gravity: Any = None, distributed_force: Any = None,
             point_loads: Any = None, exact: bool = False,
             time_limit: float | None = None) -> list[TensionTrajectoryResult]:
        """A tension trajectory for every (start, goal) pair.

        Args:
            starts, goals: (B, n) or (n,) tensions, N, the robot file's tendon order.
            tip_force, tip_moment, gravity, distributed_force: (3,) loads throughout, world
                frame: N, N·m, m/s², N/m (default none).
            point_loads: ``[{"s": m, "force": [N], "moment": [N·m]}]``, world frame.
            exact: polish the motions the verdict rejects with Ipopt (every waypoint's and
                sample's equilibrium, the bounds, the rate and the clearance as constraints,
                start and goal fixed; ``stages.polish``'s ``polish_tension_motion``) and
                keep a polish the verdict accepts (``Stage.POLISH``).
            time_limit: with ``exact``, seconds of polishing per problem (None: no limit).

        Returns:
            One ``TensionTrajectoryResult`` per problem, in order; a start or goal in
            collision is refused (``Stage.REJECTED``) with its reason.

        Raises:
            ValueError: a malformed tension set or load (naming the problem and key).

        Long: the search's three steps (endpoints, direct legs, via points), its verdicts,
        the refine and exact mode, in order, each step over the whole batch.
        """
        check_time_limit(time_limit, "time_limit")
        begin = time.perf_counter()
        starts, goals = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (starts, goals))
        if starts.shape != goals.shape:
            raise ValueError(f"starts {starts.shape} and goals {goals.shape} differ in shape")
        for i in range(len(starts)):
            check_tensions(self.robot, starts[i].tolist(), f"problem {i}: start")
            check_tensions(self.robot, goals[i].tolist(), f"problem {i}: goal")
        loads = static_loads(1, self.length, tip_force, tip_moment, gravity,
                             distributed_force, point_loads)
        count = len(starts)
        ends_clear = (self.clear(np.concatenate([starts, goals]), loads).reshape(2, count)
                      if count else np.zeros((2, 0), bool))
        plans: list[np.ndarray | None] = [None] * count
        notes: list[list[str]] = [[] for _ in range(count)]
        valid = np.flatnonzero(ends_clear.all(axis=0))
        direct = [self._legs([starts[i], goals[i]]) for i in valid]
        for i, plan, ok in zip(valid, direct, self._screen(direct, loads), strict=True):
            if ok:
                plans[i], notes[i] = plan, ["direct leg"]
        todo = [i for i in valid if plans[i] is None]
        for i, (plan, note) in zip(todo, self._via_plans(starts[todo], goals[todo], loads),
                                   strict=True):
            plans[i], notes[i] = plan, note
        explore = (time.perf_counter() - begin) / max(count, 1)
        timings = [StageTiming(explore=explore) for _ in range(count)]
        begin = time.perf_counter()
        planned = [i for i in range(count) if plans[i] is not None]
        reports = dict(zip(planned, self.verify_motions([plans[i] for i in planned], loads),
                           strict=True))
        searched = [self._result(i, starts[i], goals[i], ends_clear[:, i], plans[i],
                                 notes[i], loads, stage=Stage.EXPLORE, report=reports.get(i))
                    for i in range(count)]
        for timing in timings:
            timing.verify = (time.perf_counter() - begin) / max(count, 1)
        refined = refined_plans(self, planned, searched, loads, timings, self._result)
        results = []
        for i in range(count):
            result, motion = refined.get(i, (searched[i], None))
            result.timing = timings[i]
            if exact:
                result = self._polish(result, motion, loads, timings[i], time_limit)
            results.append(result)
        return results

    def _polish(self, result: TensionTrajectoryResult, refined: np.ndarray | None,
                loads: StaticLoads, timing: StageTiming,
                time_limit: float | None) -> TensionTrajectoryResult:
        """Exact mode on one plan (``_motion_polish.polish_motion``), the start and goal
        fixed: a rejected plan's motion, then the refined one where the search's was kept.
        Where the search's motion was kept because the verdict rejected the refined one,
        that refined motion is polished too and its polish kept where the verdict accepts
        it and its tip path is no longer (exact mode rescues what the penalty stage left
        in collision or beyond a limit)."""
        from ...stages.polish import TensionMotionPolishConfig, polish_tension_motion

        cfg = self.config
        rejected = refined is not None and not np.array_equal(refined, result.tensions)
        candidates = [(result.tensions, f"the {result.stage.value} stage's motion")]
        if rejected:
            candidates.append((refined, "the refined motion"))

        def polish(tensions: np.ndarray, budget: float | None) -> Any:
            return polish_tension_motion(
                self.robot, self.scene, tensions, loads, dt=cfg.dt,
                rate_max=cfg.tension_rate_max, margin=cfg.safety_margin,
                samples_between=cfg.samples_between, fixed_ends=True,
                statics_config=cfg.statics, time_limit=budget,
                config=cfg.polish or TensionMotionPolishConfig())

        def remake(tensions: np.ndarray) -> TensionTrajectoryResult:
            return self._result(0, tensions[0], tensions[-1], np.ones(2, bool), tensions,
                                list(result.notes), loads)

        if not (result.success and rejected and not cfg.polish_accepted):
            return polish_motion(result, candidates, polish, remake, timing, time_limit,
                                 cfg.polish_accepted)
        polished = polish_motion(result, candidates[1:], polish, remake, timing, time_limit,
                                 polish_accepted=True)
        if polished is result:        # not accepted: the note says why
            return result
        length, kept = self.tip_paths([polished.tensions, result.tensions], loads)
        if length <= kept:
            polished.notes.append(f"tip path {1e3 * length:.1f} mm (the {result.stage.value}"
                                  f" stage's {1e3 * kept:.1f})")
            return polished
        result.notes.append(f"the polished refined motion was not kept: its tip path "
                            f"{1e3 * length:.1f} mm is not shorter than {1e3 * kept:.1f}")
        return result   # its timing is ``timing`` and polish_motion set its exact_mode

    def tip_path(self, tensions: np.ndarray, loads: StaticLoads, samples: int = 64) -> float:
        """The length of the tip's path (m) along a motion (T, n) N, from fresh statics
        at ``samples`` tension sets evenly spaced along it (so that motions with different
        waypoint counts compare fairly)."""
        return float(self.tip_paths([tensions], loads, samples)[0])

    def tip_paths(self, motions: list[np.ndarray], loads: StaticLoads,
                  samples: int = 64) -> np.ndarray:
        """``tip_path`` of several motions (m each), one statics solve for all."""
        if not motions:
            return np.zeros(0)
        dense = np.concatenate([resampled(np.asarray(m, float), samples) for m in motions])
        every = loads.rows(np.zeros(len(dense), int))
        solved = solve_statics(self.robot, dense, every.tip_force, every.tip_moment,
                               every.gravity, self.config.statics,
                               distributed_force=every.distributed_force,
                               point_loads=every.point_load_lists())
        tips = np.asarray(solved.tip_position).reshape(len(motions), samples, 3)
        return np.sum(np.linalg.norm(np.diff(tips, axis=1), axis=2), axis=1)

    def refine_motion(self, tensions: np.ndarray, loads: StaticLoads) -> np.ndarray:
        """A motion (T, n) N refined as a whole with its first and last tension sets
        fixed: resampled to ``time_slack`` times as many steps, then each waypoint's
        equilibrium and backbone clearance, between neighbours the tip's step, a
        smoothness term and the tension-rate hinge (``stages.refine``'s ``solve_motion``,
        tip path weight ``tip_path_weight``); returns (T', n) N."""
        return self.refine_motions([tensions], loads)[0]

    def refine_motions(self, motions: list[np.ndarray], loads: StaticLoads
                       ) -> list[np.ndarray]:
        """``refine_motion`` of several motions (N), in order: one batched LM
        (``_motion_refine.refine_chains``)."""
        cfg = self.config
        counts = [max(len(t), math.ceil(cfg.time_slack * (len(t) - 1)) + 1) for t in motions]
        return refine_chains(self.robot, self.scene, cfg,
                             [resampled(t, c) for t, c in zip(motions, counts, strict=True)],
                             cfg.chain_iterations, loads=loads)

    def _via_plans(self, starts: np.ndarray, goals: np.ndarray, loads: StaticLoads
                   ) -> list[tuple[np.ndarray, list[str]]]:
        """Per problem (starts, goals (B, n) N): the cheapest clear start → via → goal
        among its best via candidates, else the quickest route through the roadmap
        (``roadmap``), else the direct legs (which the verdict will fail, saying where).
        The candidates are screened cheapest first in rounds (``VIA_ROUNDS``), every
        problem's in one batch: most problems find a clear via among their first few."""
        if not len(starts):
            return []       # every direct leg clear: no via pool to build
        vias = self.vias(loads)
        orders = [np.argsort(leg_change(vias, a) + leg_change(b, vias))[
            :self.config.via_candidates] for a, b in zip(starts, goals, strict=True)]
        found: list[tuple[np.ndarray, list[str]] | None] = [None] * len(starts)
        for first, last in zip(VIA_ROUNDS, (*VIA_ROUNDS[1:], None), strict=True):
            candidates = [(k, int(j), self._legs([starts[k], vias[j], goals[k]]))
                          for k in range(len(starts)) if found[k] is None
                          for j in orders[k][first:last]]
            for (k, j, plan), ok in zip(candidates, self._screen(
                    [plan for _, _, plan in candidates], loads), strict=True):
                if ok and found[k] is None:
                    found[k] = plan, [f"via tension set {j} of the pool"]
        for k in range(len(starts)):
            if found[k] is None:
                found[k] = self._route(starts[k], goals[k], loads, len(orders[k]))
        return found

    def _route(self, start: np.ndarray, goal: np.ndarray, loads: StaticLoads,
               screened: int) -> tuple[np.ndarray, list[str]]:
        """The roadmap's quickest route, else the direct legs (no clear single via)."""
        vias = self.vias(loads)
        route = self.roadmap(loads).route(start, goal, partial(self._screen_legs, loads),
                                          self.config.via_candidates)
        if route is not None:
            return self._legs([start, *vias[route], goal]), [
                f"via tension sets {', '.join(map(str, route))} of the pool (the roadmap)"]
        return self._legs([start, goal]), [
            f"no clear via among the {screened} cheapest of {len(vias)} candidates, nor a "
            "route through the roadmap"]

    def roadmap(self, loads: StaticLoads) -> Any:
        """The roadmap over the via candidates under one load case
        (``stages.explore.TensionRoadmap``), built once per planner, loaded from the disk
        cache where a process built it for the same robot, scene, loads and settings."""
        from ...stages.explore import tension_roadmap

        key = _case_key(loads)
        if key not in self._roadmaps:
            cfg = self.config
            settings, arrays = self._cache_key(loads)
            settings.update(rate=cfg.tension_rate_max, dt=cfg.dt,
                            samples_between=cfg.samples_between)
            self._roadmaps[key] = tension_roadmap(self.vias(loads),
                                                  partial(self._screen_legs, loads),
                                                  cfg.roadmap_neighbours, settings, arrays)
        return self._roadmaps[key]

    def _screen_legs(self, loads: StaticLoads, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(L,) True where the straight leg a[i] → b[i] (N) is clear at every sample the
        verdict checks (one batch)."""
        return self._screen([self._legs([x, y]) for x, y in zip(a, b, strict=True)], loads)

    def replay(self, motion: Any, dt: float | None = None, *, tip_force: Any = None,
               tip_moment: Any = None, gravity: Any = None, distributed_force: Any = None,
               point_loads: Any = None) -> TensionTrajectoryResult:
        """A PCC motion replayed through the mechanics model under loads: what the robot
        does when a geometric plan is executed by tensions.

        At each waypoint the tendons get the least tensions whose unloaded rod takes the
        waypoint's PCC shape (``model.tendon_groups.tensions_of_configuration``, closed
        form); the result is that tension motion judged like every plan of this planner
        (fresh statics under the loads at every waypoint and between them, python-fcl on
        the solved backbone, tension bounds and rates). Without loads its tips are the PCC
        tips to the rod's axial compression (micrometres); with loads, the distance
        between the two is what the PCC plan leaves out.

        Args:
            motion: a ``TrajectoryResult`` or ``FollowResult`` (its ``q``), or PCC
                configurations (T, 3S) (θ rad, φ rad, L m).
            dt: seconds between waypoints (default: the result's ``dt``).
            tip_force, tip_moment, gravity, distributed_force, point_loads: as ``plan``.

        Returns:
            A ``TensionTrajectoryResult``; a waypoint that no tensions within [0, τ_max]
            reach fails it, named in ``reason``.

        Raises:
            ValueError: no configurations, or no ``dt``.
        """
        q = np.atleast_2d(np.asarray(getattr(motion, "q", motion), dtype=float))
        if dt is None:  # a plan's dt, or a followed path's
            dt = getattr(motion, "dt", None) or getattr(getattr(motion, "path", None), "dt", None)
        if dt is None or not math.isfinite(float(dt)) or float(dt) <= 0.0:
            raise ValueError("replay: give dt > 0 (seconds between waypoints)")
        if q.ndim != 2 or len(q) == 0 or q.shape[1] != 3 * self.robot.n_segments:
            raise ValueError(f"replay: expected configurations (T, {3 * self.robot.n_segments}),"
                             f" got {q.shape}")
        tensions, missed = tensions_of_configuration(self.robot, q)
        loads = static_loads(1, self.length, tip_force, tip_moment, gravity,
                             distributed_force, point_loads)
        result = self._result(0, tensions[0], tensions[-1], np.ones(2, bool), tensions,
                              ["replay of a PCC motion"], loads, dt=float(dt))
        far = np.flatnonzero(missed > 1e-6)
        if far.size:
            result.success = False
            result.reason = (f"waypoint {far[0]}: no tensions within [0, τ_max] give its PCC "
                             f"shape (misses it by {missed[far[0]]:.3g} rad)")
        return result

    def _result(self, index: int, start: np.ndarray, goal: np.ndarray, ends_clear: np.ndarray,
                plan: np.ndarray | None, notes: list[str], loads: StaticLoads,
                dt: float | None = None, stage: Stage = Stage.REFINE,
                report: TensionMotionVerification | None = None) -> TensionTrajectoryResult:
        """The judged result of one problem (refused where an end is not clear);
        ``report``: the verdict of ``plan`` where the caller has it already."""
        cfg = self.config
        dt = cfg.dt if dt is None else dt
        tensions = np.stack([start, goal]) if plan is None else plan
        if report is None:
            report = self._verify(tensions, loads, dt)
        result = TensionTrajectoryResult(
            robot=self.robot, tensions=tensions, dt=dt, position=report.tip_position,
            wxyz=report.tip_wxyz, backbone=report.backbone, clearance=report.clearance,
            min_clearance=report.min_clearance, max_violation=report.max_violation,
            success=False, reason="", tip_force=loads.tip_force[0],
            tip_moment=loads.tip_moment[0], gravity=loads.gravity[0],
            distributed_force=loads.distributed_force[0],
            point_loads=loads.point_load_lists()[0], tension_rate_max=cfg.tension_rate_max,
            stage=stage if plan is not None else Stage.REJECTED, notes=list(notes))
        result.judged(report)
        if plan is None:
            which = " and ".join(k for k, ok in zip(("start", "goal"), ends_clear,
                                                    strict=True) if not ok)
            result.success = False
            result.reason = (f"problem {index}: the {which} is not clear of the scene by "
                             f"{cfg.safety_margin:g} m (or its statics did not converge)")
        return result


def _case_key(loads: StaticLoads) -> bytes:
    """The bytes of a load case: what the planner's via sets and roadmap are kept under."""
    return b"".join(np.ascontiguousarray(a).tobytes() for a in loads.arrays())


def plan_tension_trajectories(robot: Robot | str | dict, starts: Any, goals: Any,
                  scene: Scene | str | None = None,
                  **loads: Any) -> list[TensionTrajectoryResult]:
    """One-call tension-space planning with the default config (see
    ``TensionTrajectoryPlanner.plan``): start and goal tensions in newtons, loads in N, N·m, m/s²,
    N/m (clearance in metres);
    returns one trajectory of tensions (N) per problem."""
    return TensionTrajectoryPlanner(robot, scene).plan(starts, goals, **loads)


def replay_pcc_motion(robot: Robot | str | dict, motion: Any, scene: Scene | str | None = None,
                      dt: float | None = None, **loads: Any) -> TensionTrajectoryResult:
    """A PCC plan or path (``TrajectoryResult``, ``FollowResult`` or configurations
    (T, 3S), rad and m) replayed through the mechanics model under loads (N, N·m, m/s²,
    N/m), judged like a tension plan (see ``TensionTrajectoryPlanner.replay``); dt in seconds."""
    return TensionTrajectoryPlanner(robot, scene).replay(motion, dt, **loads)

from ..._moved import moved_names  # noqa: E402 — old names, for one release

__getattr__ = moved_names(__name__, {"TensionPlanConfig": ":TensionTrajectoryConfig",
                                     "TensionPlanner": ":TensionTrajectoryPlanner",
                                     "plan_tensions": ":plan_tension_trajectories",
                                     "read_tension_problems": "cr_nlp.tasks.readers"})
