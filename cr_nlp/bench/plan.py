"""``cr-nlp bench plan``: the trajectory-planning benchmark of docs/design.md §4 on this machine.

Problems: tdcr3 in the shelf, cabinet and random (``models/scenes/random_27.json``)
scenes; per scene, start/goal pairs of configurations that are collision-free by
python-fcl (distance ≥ 2 mm) and by the planner's sphere model (clearance ≥ the
planner's margin), whose tip positions are at least 0.1 × the robot's total length
apart (fixed seed; 100 pairs per scene by default, 3 with ``--quick``).

Rows: ``TrajectoryPlanner`` with the roadmap initial guess ("roadmap+opt"), with the
straight line and its perturbations only ("straight-line+opt"), with the exact Ipopt
polish ("roadmap+opt+exact"), and the RRT-Connect baseline (``bench._baselines_plan``,
no shortcutting, resampled to the same waypoints and Δt). Every answer is judged by the
same float64 verdict, ``tasks.geometry.trajectory.verify_trajectory`` (python-fcl along the
interpolated motion, limits, tendon speed and acceleration over Δt).

Times: the planner rows first run a warm-up on the first ``WARMUP_PAIRS`` problems
(compilation of the LM slot program, roadmap load, the exact row's Ipopt build), then
the whole batch is timed; "time/problem" is the batch wall time over its size (the
planner is batched) and "median time" the median of the per-problem stage timings. RRT
times are per problem (it plans one at a time), after one warm-up problem. The roadmap
build time is reported apart. The iteration sweep (success and path length against the
LM budget) runs on the first ``sweep_pairs`` problems of each scene. Results are written
after every scene, so an interrupted run keeps the scenes it finished.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from .._program_clock import timed_programs
from ..model import Robot, load_robot, q_to_z, tip_pose
from ..tasks.geometry.trajectory import TrajectoryConfig, TrajectoryPlanner, verify_trajectory
from ..world import Scene, check_many, clearance_z, load_scene, scene_arrays
from ._baselines_plan import RRTConnect, RRTConnectConfig
from ._common import (
    Column,
    environment,
    environment_markdown,
    fixed,
    markdown_table,
    write_report,
)
from .suites import (
    EXACT,
    PLAN_FULL,
    PLAN_METHODS,
    PLAN_QUICK,
    PLAN_SCENES,
    ROADMAP_OPT,
    RRT,
    STRAIGHT_OPT,
)
from .suites import (
    PlanBenchSizes as PlanBenchSizes,
)

SCENES = PLAN_SCENES
METHODS = PLAN_METHODS
DEFAULT_METHODS = METHODS

RRT_CONFIG = RRTConnectConfig(time_limit=10.0)
"""The RRT-Connect baseline's settings in the benchmark (10 s per problem)."""
MIN_TIP_DISTANCE_FRACTION = 0.1
"""Start and goal tips are at least this fraction of the robot's total length apart."""
FCL_CLEARANCE = 0.002
"""python-fcl distance (m) every start and goal keeps."""


WARMUP_PAIRS = 8
"""Problems of a planner row's warm-up: 16 LM guesses, at least the slots of the default
``TrajectoryConfig.chunk_size``, so the timed run compiles nothing."""


FULL, QUICK = PLAN_FULL, PLAN_QUICK


# ================================================================ problems


def plan_problems(robot: Robot, scene: Scene, count: int, margin: float,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` start/goal pairs (two (count, 3n) arrays θ, φ, L) for ``scene``: both
    ends with sphere clearance ≥ ``margin`` (m) and python-fcl distance ≥ 2 mm, tips at
    least 0.1 × total length apart."""
    rng = np.random.default_rng(seed)
    lo, hi = robot.q_bounds()
    arrays = scene_arrays(scene)
    free_q: list[np.ndarray] = []
    need = 2 * count
    for _ in range(200):
        if sum(len(f) for f in free_q) >= need:
            break
        q = rng.uniform(lo, hi, size=(max(256, 4 * need), robot.dof))
        # θ uniform over the bending-vector disk, as the roadmap samples it.
        q[:, 0::3] = hi[0::3] * np.sqrt(rng.random((len(q), robot.n_segments)))
        sphere = np.asarray(clearance_z(robot, arrays, q_to_z(robot, q)))
        q = q[sphere >= margin]
        if len(q):
            q = q[check_many(robot, scene, q).min_distance >= FCL_CLEARANCE]
        free_q.append(q)
    pool = np.concatenate(free_q)
    tips = np.asarray(tip_pose(robot, pool)[0])
    starts, goals = [], []
    order = rng.permutation(len(pool))
    used = np.zeros(len(pool), dtype=bool)
    min_gap = MIN_TIP_DISTANCE_FRACTION * robot.total_length_max
    for i in order:
        if len(starts) == count:
            break
        if used[i]:
            continue
        far = np.flatnonzero(~used & (np.linalg.norm(tips - tips[i], axis=1) >= min_gap))
        if len(far) == 0:
            continue
        j = int(rng.choice(far))
        used[i] = used[j] = True
        starts.append(pool[i])
        goals.append(pool[j])
    if len(starts) < count:
        raise RuntimeError(f"{scene.name}: found only {len(starts)} of {count} start/goal pairs")
    return np.array(starts), np.array(goals)


# ================================================================ measuring


def _summary(scene: str, method: str, verdicts: Sequence[dict[str, Any]],
             per_problem: Sequence[float], time_per_problem: float,
             first_call: float) -> dict[str, Any]:
    success = [bool(v["success"]) for v in verdicts]
    lengths = [v["path_length"] for v in verdicts if v["success"]]
    return {
        "scene": scene, "method": method, "problems": len(verdicts),
        "success_pct": 100.0 * float(np.mean(success)) if verdicts else float("nan"),
        "collision_free_pct": 100.0 * float(np.mean([bool(v["collision_free"])
                                                      for v in verdicts])),
        "median_path_length": float(np.median(lengths)) if lengths else float("nan"),
        "time_per_problem": time_per_problem,
        "median_time": float(np.median(per_problem)) if per_problem else float("nan"),
        "max_violation": float(max((v["max_violation"] for v in verdicts
                                    if v["max_violation"] == v["max_violation"]), default=0.0)),
        "max_violation_success": float(max((v["max_violation"] for v in verdicts
                                            if v["success"]), default=0.0)),
        "first_call": first_call,
    }


def _judge(planner: TrajectoryPlanner, q: np.ndarray | None, dt: float) -> dict[str, Any]:
    """The shared verdict's numbers a row sums up (``verify_trajectory``), or a failure
    without a trajectory."""
    if q is None:
        return {"success": False, "collision_free": False, "path_length": float("nan"),
                "max_violation": float("nan")}
    checked = verify_trajectory(planner.robot, planner.scene, q, dt,
                                planner.config.safety_margin, planner.config.verify_samples)
    return {"success": checked.success, "collision_free": checked.collision_free,
            "path_length": checked.path_length, "max_violation": checked.max_violation}


def measure_planner(planner: TrajectoryPlanner, scene: str, method: str, starts: np.ndarray,
                    goals: np.ndarray, progress: bool = True) -> tuple[dict[str, Any], list[Any]]:
    """One planner row: a warm-up on the first ``WARMUP_PAIRS`` problems (compilation,
    roadmap, the exact row's Ipopt build), then the whole batch timed."""
    exact = method == EXACT
    init = "straight" if method == STRAIGHT_OPT else "roadmap"
    t0 = time.perf_counter()
    planner.plan(starts[:WARMUP_PAIRS], goals[:WARMUP_PAIRS], exact=exact, init=init)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    results = planner.plan(starts, goals, exact=exact, init=init, progress=exact and progress)
    wall = time.perf_counter() - t0
    # The planner's own success may be stricter than the shared verdict (exact mode
    # also demands the clearance margin): a row counts a success only if both agree.
    verdicts = []
    for r in results:
        verdict = _judge(planner, r.q, r.dt)
        verdicts.append({**verdict, "success": verdict["success"] and r.success})
    per_problem = [r.timing.total - r.timing.compile for r in results]
    row = _summary(scene, method, verdicts, per_problem, wall / len(starts), first)
    # Per-stage seconds per problem of the timed batch (``PlanTiming``: roadmap query and
    # initial guesses, LM, float64 verdict, Ipopt polish) and the LM's device programs.
    stages = planner.last_timing
    for key, seconds in (("query_time", stages.explore), ("lm_time", stages.refine),
                         ("verdict_time", stages.verify), ("polish_time", stages.polish)):
        row[key] = seconds / len(starts)
    row["programs"] = planner.last_programs
    if not exact:  # the host share: the batch again, timing its compiled programs
        with timed_programs() as inside:
            t0 = time.perf_counter()
            planner.plan(starts, goals, exact=False, init=init)
            timed = time.perf_counter() - t0
        host = max(timed - inside.seconds, 0.0)
        row["host_per_1000"] = 1000.0 * host / len(starts)
        row["host_pct"] = 100.0 * host / max(timed, 1e-12)
    if exact:
        row["median_polish"] = float(np.median([r.timing.polish for r in results]))
        row["polished_pct"] = 100.0 * float(np.mean([r.stage == "polish" for r in results]))
    return row, results


def measure_rrt(planner: TrajectoryPlanner, scene: str, starts: np.ndarray, goals: np.ndarray,
                config: RRTConnectConfig = RRT_CONFIG,
                progress: bool = True) -> tuple[dict[str, Any], list[float]]:
    """The RRT-Connect row and the path lengths (m) of its successes: one problem at a
    time, resampled to the planner's waypoints and judged with its Δt (one warm-up problem
    first, its time the "first call")."""
    roadmap = planner.roadmap()
    rrt = RRTConnect(planner.robot, planner.scene, replace(config, margin=planner.margin),
                     checker=None if roadmap is None else roadmap.checker)
    n, dt = planner.config.waypoints, planner.config.dt
    t0 = time.perf_counter()
    rrt.plan(starts[0], goals[0], n)
    first = time.perf_counter() - t0
    verdicts, seconds = [], []
    for start, goal in tqdm(list(zip(starts, goals, strict=True)), desc=f"{scene} RRT",
                            disable=not progress, leave=False):
        q, result = rrt.plan(start, goal, n)
        seconds.append(result.seconds)
        verdicts.append(_judge(planner, q, dt))
    row = _summary(scene, RRT, verdicts, seconds, float(np.mean(seconds)), first)
    return row, [v["path_length"] for v in verdicts if v["success"]]


def iteration_sweep(planner: TrajectoryPlanner, scene: str, starts: np.ndarray,
                    goals: np.ndarray, budgets: Sequence[int]) -> list[dict[str, Any]]:
    """Success % and median path length of "roadmap+opt" for each LM iteration budget
    (the iteration count is a run-time argument: no recompilation)."""
    base = planner.config
    rows = []
    try:
        for budget in budgets:
            planner.config = replace(base, iterations=int(budget))
            results = planner.plan(starts, goals, init="roadmap")
            verdicts = [_judge(planner, r.q, r.dt) for r in results]
            row = _summary(scene, ROADMAP_OPT, verdicts, [], float("nan"), float("nan"))
            rows.append({"scene": scene, "iterations": int(budget),
                         "success_pct": row["success_pct"],
                         "median_path_length": row["median_path_length"]})
    finally:
        planner.config = base
    return rows


def _pooled(rows: Sequence[dict[str, Any]], verdict_rows: dict[str, list[dict[str, Any]]]
            ) -> list[dict[str, Any]]:
    """One "all scenes" row per method, weighted by the problem counts."""
    out = []
    for method in METHODS:
        mine = [r for r in rows if r["method"] == method]
        if not mine:
            continue
        total = sum(r["problems"] for r in mine)

        def weighted(key: str, rows_: list[dict[str, Any]] = mine, total_: int = total) -> float:
            return float(sum(r[key] * r["problems"] for r in rows_) / total_)

        out.append({
            "scene": "all", "method": method, "problems": total,
            "success_pct": weighted("success_pct"),
            "collision_free_pct": weighted("collision_free_pct"),
            "median_path_length": float(np.median(verdict_rows[method]))
            if verdict_rows[method] else float("nan"),
            "time_per_problem": weighted("time_per_problem"),
            "median_time": statistics.median(r["median_time"] for r in mine),
            "max_violation": max(r["max_violation"] for r in mine),
            "max_violation_success": max(r["max_violation_success"] for r in mine),
            "first_call": max(r["first_call"] for r in mine),
            "median_polish": statistics.median(r.get("median_polish", math.nan)
                                               for r in mine),
            "polished_pct": weighted("polished_pct") if all(
                "polished_pct" in r for r in mine) else math.nan,
            **{key: weighted(key) if all(key in r for r in mine) else math.nan
               for key in ("query_time", "lm_time", "verdict_time", "polish_time")},
            "programs": sum(r["programs"] for r in mine) if all(
                "programs" in r for r in mine) else None,
        })
    return out


def run_plan_benchmark(quick: bool = False, pairs_per_scene: int | None = None,
                       scenes: Sequence[str] = SCENES, robot: str = "tdcr3",
                       out: str | Path | None = "bench_results/plan", seed: int = 0,
                       methods: Sequence[str] = DEFAULT_METHODS,
                       iteration_budgets: Sequence[int] | None = None,
                       sweep_pairs: int | None = None,
                       config: TrajectoryConfig | None = None,
                       rrt_config: RRTConnectConfig = RRT_CONFIG,
                       progress: bool = True) -> list[dict[str, Any]]:
    """Run the benchmark; returns the rows (per scene, then "all"), prints the Markdown
    report and, with ``out``, writes plan.md, plan.csv, iterations.csv and
    iterations.png there (after every scene). ``sweep_pairs``: problems per scene of the
    iteration sweep (default: the size's ``sweep_pairs``, at most ``pairs``). ``config``:
    the planner's settings (default ``TrajectoryConfig()``); ``rrt_config``: the
    baseline's (its margin is replaced by the planner's)."""
    sizes = QUICK if quick else FULL
    pairs = pairs_per_scene or sizes.pairs_per_scene
    budgets = tuple(iteration_budgets if iteration_budgets is not None
                    else sizes.iteration_budgets)
    sweep_count = min(pairs, sweep_pairs or sizes.sweep_pairs)
    robot_model = load_robot(robot)
    rows: list[dict[str, Any]] = []
    all_rows: list[dict[str, Any]] = []       # rows + the pooled "all" rows
    report = ""
    sweep: list[dict[str, Any]] = []
    builds: list[dict[str, Any]] = []
    lengths: dict[str, list[float]] = {m: [] for m in METHODS}
    for name in tqdm(scenes, desc="scenes", disable=not progress):
        scene = load_scene(name)
        planner = TrajectoryPlanner(robot_model, scene, config or TrajectoryConfig())
        t0 = time.perf_counter()
        roadmap = planner.roadmap()
        builds.append({"scene": name, "build_seconds": roadmap.build_seconds,
                       "loaded_seconds": time.perf_counter() - t0,
                       "from_cache": roadmap.loaded_from_cache,
                       "nodes": len(roadmap.nodes_z), "edges": roadmap.edge_count})
        starts, goals = plan_problems(robot_model, scene, pairs, planner.margin, seed)
        for method in tqdm([m for m in METHODS if m in methods], desc=name,
                           disable=not progress, leave=False):
            if method == RRT:
                row, found = measure_rrt(planner, name, starts, goals, rrt_config, progress)
            else:
                row, results = measure_planner(planner, name, method, starts, goals, progress)
                found = [r.path_length for r in results if r.success]
            rows.append(row)
            lengths[method] += found
        if budgets:
            sweep += iteration_sweep(planner, name, starts[:sweep_count],
                                     goals[:sweep_count], budgets)
        # Written after every scene: an interrupted run keeps the scenes it finished.
        all_rows = rows + _pooled(rows, lengths)
        env = environment()
        report = format_report(all_rows, builds, sweep, env, robot, pairs, sweep_count)
        tables = {"plan": all_rows, "roadmap_build": builds}
        if sweep:
            tables["iterations"] = sweep
        write_report("plan", report, out, tables, env, echo=False)
        if out is not None and sweep:
            plot_iterations(sweep, Path(out) / "iterations.png")
    print(report)
    return all_rows


def search_scaling(scenes: Sequence[str] = ("shelf", "cabinet"),
                   counts: Sequence[int] = (1, 20, 1000), robot: str = "tdcr3",
                   out: str | Path | None = "bench_results/plan", seed: int = 0,
                   repeats: int = 5) -> list[dict[str, Any]]:
    """Time the batched roadmap search alone (``stages.explore._roadmap_search.shortest_paths``),
    scipy against the device's min-plus relaxation, for ``counts`` start/goal pairs on
    each scene's roadmap. The ends are the benchmark's problems attached to their
    ``neighbours`` nearest nodes without edge checks (the checks are the same for both
    backends). Medians of ``repeats`` calls, the two backends alternating, after a
    warm-up call each (compilation). Prints and writes search.md / search.csv."""
    from ..stages.explore._roadmap_search import neighbour_table, shortest_paths

    robot_model = load_robot(robot)
    rows: list[dict[str, Any]] = []
    for name in scenes:
        scene = load_scene(name)
        planner = TrajectoryPlanner(robot_model, scene)
        roadmap = planner.roadmap()
        neighbours, weights = neighbour_table(roadmap.edges)
        starts, goals = plan_problems(robot_model, scene, max(counts), planner.margin, seed)
        k = roadmap.config.neighbours
        ends = [roadmap.tree.query(np.asarray(q_to_z(robot_model, q)), k=k)
                for q in (starts, goals)]
        for count in counts:
            args = (neighbours, weights, ends[0][1][:count], ends[0][0][:count],
                    ends[1][1][:count], ends[1][0][:count])
            times: dict[str, list[float]] = {"scipy": [], "device": []}
            found = {}
            for backend in times:
                found[backend] = shortest_paths(*args, search=backend)[0]     # warm-up
            for _ in range(repeats):
                for backend, spent in times.items():
                    t0 = time.perf_counter()
                    shortest_paths(*args, search=backend)
                    spent.append(time.perf_counter() - t0)
            agree = np.allclose(found["scipy"], found["device"], rtol=1e-5)
            rows.append({"scene": name, "pairs": count,
                         "scipy_ms": 1e3 * statistics.median(times["scipy"]),
                         "device_ms": 1e3 * statistics.median(times["device"]),
                         "same_lengths": bool(agree)})
    env = environment()
    report = "\n\n".join([
        f"# Roadmap search: scipy Dijkstra vs device min-plus ({robot}, nodes "
        f"{len(roadmap.nodes_z)}, median of {repeats})",
        markdown_table(rows, (Column("scene", "scene"), Column("pairs", "pairs"),
                              Column("scipy_ms", "scipy (ms)", fixed(2)),
                              Column("device_ms", "device (ms)", fixed(2)),
                              Column("same_lengths", "same lengths"))),
        "## Environment", environment_markdown(env)])
    write_report("search", report, out, {"search": rows}, env)
    return rows


# ================================================================ output


def plot_iterations(sweep: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """Success % and median path length (m) against the LM iteration budget, one line
    per scene; saved to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..viz._figures import write_figure

    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.5))
    for scene in dict.fromkeys(r["scene"] for r in sweep):
        mine = [r for r in sweep if r["scene"] == scene]
        its = [r["iterations"] for r in mine]
        left.plot(its, [r["success_pct"] for r in mine], "o-", label=scene)
        right.plot(its, [r["median_path_length"] for r in mine], "o-", label=scene)
    left.set(xlabel="LM iterations", ylabel="success (%)", ylim=(0, 105))
    right.set(xlabel="LM iterations", ylabel="median tip path length (m)")
    left.legend()
    fig.suptitle("roadmap+opt: success and path length vs optimisation iterations")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_figure(fig, path, dpi=120)
    plt.close(fig)
    return path


COLUMNS = (
    Column("scene", "scene"), Column("method", "method"), Column("problems", "problems"),
    Column("success_pct", "success %", fixed(1)),
    Column("collision_free_pct", "collision-free %", fixed(1)),
    Column("median_path_length", "median path (m)", fixed(3)),
    Column("time_per_problem", "time/problem (s)", fixed(3)),
    Column("median_time", "median time (s)", fixed(3)),
    Column("query_time", "query (s)", fixed(3)),
    Column("lm_time", "LM (s)", fixed(3)),
    Column("verdict_time", "verdict (s)", fixed(3)),
    Column("polish_time", "polish (s)", fixed(3)),
    Column("programs", "LM programs"),
    Column("median_polish", "exact stage median (s)", fixed(3)),
    Column("polished_pct", "polished %", fixed(1)),
    Column("max_violation", "max violation"),
    Column("max_violation_success", "max violation (successes)"),
    Column("first_call", "first call (s)", fixed(2)),
    Column("host_per_1000", "host s / 1000 problems", fixed(2)),
    Column("host_pct", "host %", fixed(1)),
)


def format_report(rows: Sequence[dict[str, Any]], builds: Sequence[dict[str, Any]],
                  sweep: Sequence[dict[str, Any]], env: dict[str, str], robot: str,
                  pairs: int, sweep_pairs: int | None = None) -> str:
    """The Markdown report: results, roadmap builds, iteration sweep, environment."""
    parts = [f"# Trajectory planning benchmark ({robot}, {pairs} start/goal pairs per scene)",
             markdown_table(rows, COLUMNS),
             "Success and collision-free are judged by `verify_trajectory` (python-fcl along "
             "the interpolated motion, limits, tendon speed/acceleration over Δt) for every "
             "row. time/problem: batch wall time / problems (RRT: mean per problem); median "
             "time: median of per-problem times; query / LM / verdict / polish: each stage's "
             "batch seconds / problems (query: roadmap query and initial guesses); LM "
             "programs: compiled LM calls of the timed batch; first call: warm-up "
             "(compilation, roadmap load). host: the batch run once more with every "
             "compiled program waited for and timed (`_program_clock.timed_programs`); "
             "the wall time outside them (roadmap bookkeeping, result assembly, the "
             "python-fcl verdict), per 1000 problems and as % of that run: what a GPU "
             "would leave the host to do (penalty rows only; the exact rows' Ipopt is "
             "all host). RRT-Connect is not shortcut; it uses the planner's waypoints "
             "and Δt.",
             "## Roadmap build",
             markdown_table(builds, (Column("scene", "scene"),
                                     Column("build_seconds", "build (s)", fixed(2)),
                                     Column("from_cache", "loaded from cache"),
                                     Column("loaded_seconds", "load (s)", fixed(2)),
                                     Column("nodes", "nodes"), Column("edges", "edges")))]
    if sweep:
        parts += ["## Success and path length vs LM iterations (roadmap+opt"
                  + (f", first {sweep_pairs} pairs per scene" if sweep_pairs else "") + ")",
                  markdown_table(sweep, (Column("scene", "scene"),
                                         Column("iterations", "iterations"),
                                         Column("success_pct", "success %", fixed(1)),
                                         Column("median_path_length", "median path (m)",
                                                fixed(3))))]
    parts += ["## Environment", environment_markdown(env)]
    return "\n\n".join(parts)
