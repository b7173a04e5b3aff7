"""``cr-nlp bench ik``: the IK benchmarks of docs/design.md §4 on this machine.

Suites:

- ``free``: tdcr3 without obstacles, 1000 targets, each the forward kinematics of a
  configuration drawn uniformly inside the limits (θ, φ, L independently, fixed seed)
  whose segments keep the safety margin from each other (the verdict checks self-collision).
- ``lattice``: the 3×3×3 sphere lattice (``models/scenes/lattice.json``), 100 targets
  from configurations whose python-fcl clearance is at least the solver's safety margin
  δ (``IKSolver.margin``), for tdcr3 and tdcr4_ext.
- ``scaling``: no obstacles, 200 targets for each of tdcr3, tdcr4_ext, tdcr5_ext and
  tdcr6_ext (3 to 6 segments).
- ``throughput``: tdcr3 without obstacles at growing batch sizes (10³, 10⁴, 10⁵ targets;
  ``max_targets`` caps them): targets per second and where the time goes, the stages of
  ``IKTiming`` and the device's share (``IKSolver.device_wait``: the time the host waited
  for device results). Not part of ``all`` (10⁵ targets take minutes on a CPU).
- ``polish``: the exact stage on its own terms: the lattice targets for tdcr3 and
  tdcr6_ext, exact mode with the polishes in one process and in a pool of 2 worker
  processes (``IKConfig.polish_workers``); its column "polish ms / target" is the
  polish stage's median time divided by the targets.

Rows: cr_nlp with its default ``IKConfig`` ("beam search"), with one seed and no beam
or retries ("single seed"), with the exact Ipopt polish, and two baselines from
``bench._baselines`` (damped Newton–Raphson; a scipy derivative-free method on a subset).

Every answer, whoever produced it, is judged the same way: ``IKSolver.verify`` (float64
pose error, limits, python-fcl) and the library's success rule (pose error < 0.01, limits
held, collision-free in scenes). Times: a warm-up call on the same targets first (its
wall time is the "first call" column, its JAX compile time the "compile" column), then
the median wall time of ``repeats`` further calls; reported quality is from the last call.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..model import Robot, load_robot
from ..model._ops import NUMPY
from ..model.kinematics import model_q_to_z, model_segment_frames
from ..model.rotations import wxyz_from_matrix
from ..runtime import use_host_devices
from ..tasks.geometry.ik import IKConfig, IKSolver, IKVerification
from ..world import Scene, check_many, load_scene
from ._baselines import DampedNewtonConfig, ScipyConfig, damped_newton_ik, scipy_ik
from ._common import Column, environment, environment_markdown, fixed, markdown_table, write_report
from .suites import IK_FULL, IK_QUICK, IK_SUITES, IKBenchSizes

NEWTON_CONFIG = DampedNewtonConfig()
"""The damped Newton–Raphson baseline's settings in the benchmark (its defaults)."""
SCIPY_CONFIG = ScipyConfig()
"""The scipy baseline's settings in the benchmark (its defaults)."""

CR_BEAM = "cr_nlp beam search"
CR_SINGLE = "cr_nlp single seed"
CR_EXACT = "cr_nlp + exact polish"
CR_EXACT_POOL = "cr_nlp + exact polish, 2 workers"
NEWTON = "damped Newton–Raphson"
SCIPY = f"scipy {SCIPY_CONFIG.method}"
METHODS = (CR_BEAM, CR_SINGLE, CR_EXACT, NEWTON, SCIPY)
"""The rows of every table, in order."""

SUITES = IK_SUITES
ALL_SUITES = ("free", "lattice", "scaling", "polish")
"""The suites that ``suite="all"`` runs (the paper's tables)."""
LATTICE_ROBOTS = ("tdcr3", "tdcr4_ext")
SCALING_ROBOTS = ("tdcr3", "tdcr4_ext", "tdcr5_ext", "tdcr6_ext")
POLISH_ROBOTS = ("tdcr3", "tdcr6_ext")
POLISH_METHODS = (CR_EXACT, CR_EXACT_POOL)
"""The rows of the ``polish`` suite (it runs these instead of ``methods``)."""

SINGLE_SEED = IKConfig(seeds_per_target=1, beam_width=1, retry_rounds=0)
"""The "cr_nlp single seed" configuration: the nearest pool seed, LM, nothing else."""

# Baseline random starts must not be the configurations the targets came from.
_START_SEED_OFFSET = 7919


FULL, QUICK = IK_FULL, IK_QUICK


# ================================================================ targets


@dataclass
class Case:
    """One robot, one scene (or none) and its targets."""

    suite: str
    robot: Robot
    scene: Scene | None
    q: np.ndarray
    """(T, 3n) configurations the targets are the forward kinematics of (rad, rad, m)."""
    positions: np.ndarray
    """(T, 3) target positions, metres."""
    wxyz: np.ndarray
    """(T, 4) target orientations, unit quaternions (w, x, y, z)."""

    @property
    def scene_name(self) -> str:
        return self.scene.name if self.scene is not None else "none"


@dataclass(frozen=True)
class RowAnswers:
    """The answers a row's quality columns come from (its last timed call), kept with
    the row (key "answers", not written to the files) so that a test can judge them
    again with the library's verdict."""

    q: np.ndarray
    """(T, 3n) answers (rad, rad, m)."""
    positions: np.ndarray
    """(T, 3) their target positions, metres."""
    wxyz: np.ndarray
    """(T, 4) their target orientations."""
    success: np.ndarray
    """(T,) the success flags the row's success % counts."""


def forward_kinematics(robot: Robot, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tip positions (T, 3) m and orientations (T, 4) wxyz of configurations q (T, 3n),
    float64 numpy (independent of JAX's precision setting)."""
    q = np.asarray(q, dtype=float).reshape(-1, robot.dof)
    with np.errstate(invalid="ignore", divide="ignore"):  # the unused branch of safe_where
        rot, pos = model_segment_frames(NUMPY, robot, model_q_to_z(NUMPY, robot, q))[-1]
    rotation = np.stack(np.broadcast_arrays(*rot), -1).reshape(-1, 3, 3)
    return np.stack(np.broadcast_arrays(*pos), -1).reshape(-1, 3), wxyz_from_matrix(rotation)


def free_case(robot: Robot, count: int, seed: int, suite: str = "free",
              margin: float = IKConfig.safety_margin) -> Case:
    """``count`` targets from configurations drawn uniformly inside the limits, kept in
    the order drawn where segments at least two apart keep ``margin`` (m) from each
    other (the library's verdict would reject the others: 1.5 % of tdcr3's draws, 9 % of
    tdcr6_ext's)."""
    rng = np.random.default_rng(seed)
    lo, hi = robot.q_bounds()
    kept: list[np.ndarray] = []
    while sum(len(k) for k in kept) < count:
        q = rng.uniform(lo, hi, (max(count, 64), robot.dof))
        if robot.has_self_pairs:
            q = q[check_many(robot, None, q).self_distance >= margin]
        kept.append(q)
    q = np.concatenate(kept)[:count]
    positions, wxyz = forward_kinematics(robot, q)
    return Case(suite, robot, None, q, positions, wxyz)


def lattice_case(robot: Robot, scene: Scene, count: int, margin: float, seed: int,
                 batch: int = 2000, max_draws: int = 200_000, suite: str = "lattice") -> Case:
    """``count`` targets from uniform configurations whose python-fcl clearance in
    ``scene`` is at least ``margin`` (m), kept in the order drawn."""
    rng = np.random.default_rng(seed)
    lo, hi = robot.q_bounds()
    kept: list[np.ndarray] = []
    drawn = 0
    while sum(len(k) for k in kept) < count:
        if drawn >= max_draws:
            raise RuntimeError(f"only {sum(len(k) for k in kept)} of {max_draws} random "
                               f"configurations of {robot.name} keep {margin} m clearance")
        q = rng.uniform(lo, hi, (batch, robot.dof))
        drawn += batch
        kept.append(q[check_many(robot, scene, q).min_distance >= margin])
    q = np.concatenate(kept)[:count]
    positions, wxyz = forward_kinematics(robot, q)
    return Case(suite, robot, scene, q, positions, wxyz)


# ================================================================ judging


def judge(solver: IKSolver, q: np.ndarray, positions: np.ndarray,
          wxyz: np.ndarray) -> IKVerification:
    """The library's verdict on answers q (T, 3n), whoever produced them:
    ``solver.verify`` (float64 pose error, limits, python-fcl clearance, self-clearance;
    ``world.verdict.judge_many``), exactly what ``IKSolver.solve`` reports for its own."""
    return solver.verify(np.asarray(q, dtype=float), positions, wxyz)


def _quality(pose_error: np.ndarray, success: np.ndarray, max_violation: np.ndarray,
             collision_free: np.ndarray, has_scene: bool) -> dict[str, Any]:
    finite = np.isfinite(pose_error)
    return {
        "targets": int(len(success)),
        "success_pct": 100.0 * float(np.mean(success)),
        "collision_free_pct": 100.0 * float(np.mean(collision_free)) if has_scene else None,
        "mean_pose_error": float(np.mean(pose_error[finite])) if finite.any() else None,
        "median_pose_error": float(np.median(pose_error[finite])) if finite.any() else None,
        "max_violation": float(np.nanmax(max_violation)) if len(max_violation) else None,
    }


def _times(first: float, runs: Sequence[float], compile_s: float | None) -> dict[str, Any]:
    median = statistics.median(runs)
    return {"total_s": median, "min_s": min(runs), "max_s": max(runs), "runs": len(runs),
            "first_call_s": first, "compile_s": compile_s}


# ================================================================ measuring


def measure_cr_nlp(case: Case, method: str, repeats: int, seed: int = 0) -> dict[str, Any]:
    """One cr_nlp row: a fresh ``IKSolver``, a warm-up call, ``repeats`` timed calls."""
    config = {CR_BEAM: IKConfig(), CR_SINGLE: SINGLE_SEED, CR_EXACT: IKConfig(),
              CR_EXACT_POOL: IKConfig(polish_workers=2)}[method]
    solver = IKSolver(case.robot, case.scene, replace(config, seed=seed))
    exact = method in (CR_EXACT, CR_EXACT_POOL)
    start = time.perf_counter()
    result = solver.solve(case.positions, case.wxyz, exact=exact)
    first = time.perf_counter() - start
    compile_s = result.timing.compile
    walls, stages = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        result = solver.solve(case.positions, case.wxyz, exact=exact)
        walls.append(time.perf_counter() - start)
        stages.append(result.timing.as_dict())
    row = _quality(result.pose_error, result.success, result.max_violation,
                   result.collision_free, case.scene is not None)
    row["answers"] = RowAnswers(result.q, case.positions, case.wxyz, result.success)
    row.update(_times(first, walls, compile_s))
    for stage in ("explore", "refine", "polish", "verify"):
        row[f"{stage}_s"] = statistics.median(s[stage] for s in stages)
    if exact:
        row["polished_pct"] = 100.0 * float(np.mean([s == "polish" for s in result.stage]))
        row["polish_ms"] = 1e3 * row["polish_s"] / max(len(result.success), 1)
    solver.close()
    return row


def ik_config_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``IKConfig`` field values from ``KEY=VALUE`` strings (e.g. ``chunk_size=8192``,
    ``search_block=none``), each converted to the field's type.

    Raises:
        ValueError: an item without "=", an unknown field or a value of the wrong type.
    """
    from dataclasses import fields

    types = {f.name: f.type for f in fields(IKConfig)}
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"expected KEY=VALUE, got {item!r}")
        if key not in types:
            raise ValueError(f"IKConfig has no field {key!r}; fields: {', '.join(types)}")
        kind = str(types[key])
        optional = kind.endswith(" | None")
        kind = kind.removesuffix(" | None")
        try:
            if optional and value.lower() == "none":
                out[key] = None
            else:
                out[key] = {"int": int, "float": float}.get(kind, str)(value)
        except (KeyError, ValueError):
            raise ValueError(f"{key} needs a {types[key]}, got {value!r}") from None
    IKConfig(**out)  # its own checks (e.g. sizes of at least 1) now, not mid-benchmark
    return out


def measure_throughput(robot: Robot, sizes: Sequence[int], repeats: int, seed: int = 0,
                       progress: Any = None,
                       overrides: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """The throughput rows: one ``IKSolver`` (default ``IKConfig`` with ``overrides``)
    over batches of growing size; per size a warm-up call and ``repeats`` timed calls.
    Columns: targets per second and the median seconds of each ``IKTiming`` stage, of the
    device wait (``IKSolver.device_wait``) and of the host's work outside the compiled
    programs (wall time less the device wait, the program calls and any compile), as the
    planning benchmark counts it."""
    solver = IKSolver(robot, None, IKConfig(**{"seed": seed, **(overrides or {})}))
    rows = []
    for size in sizes:
        case = free_case(robot, size, seed, "throughput")
        start = time.perf_counter()
        result = solver.solve(case.positions, case.wxyz)
        first = time.perf_counter() - start
        compile_s = result.timing.compile
        walls, stages, waits, outside = [], [], [], []
        for _ in range(repeats):
            start = time.perf_counter()
            result = solver.solve(case.positions, case.wxyz)
            walls.append(time.perf_counter() - start)
            stages.append(result.timing.as_dict())
            waits.append(solver.device_wait)
            outside.append(walls[-1] - solver.device_wait - solver.device_launch
                           - result.timing.compile)
        row = _quality(result.pose_error, result.success, result.max_violation,
                       result.collision_free, False)
        row["answers"] = RowAnswers(result.q, case.positions, case.wxyz, result.success)
        row.update(_times(first, walls, compile_s))
        for stage in ("explore", "refine", "verify"):
            row[f"{stage}_s"] = statistics.median(s[stage] for s in stages)
        row["device_wait_s"] = statistics.median(waits)
        row["host_s"] = statistics.median(outside)
        row["host_pct"] = 100.0 * row["host_s"] / max(row["total_s"], 1e-12)
        row["host_per_1e5_s"] = row["host_s"] * 1e5 / max(size, 1)
        row["targets_per_s"] = size / max(row["total_s"], 1e-12)
        row["stream_parts"] = len(solver.stream_parts)
        rows.append({"suite": "throughput", "robot": robot.name, "scene": "none",
                     "method": CR_BEAM, **row})
        if progress is not None:
            progress.update()
    solver.close()
    return rows


def measure_newton(case: Case, judge_solver: IKSolver, repeats: int, seed: int,
                   config: DampedNewtonConfig = NEWTON_CONFIG) -> dict[str, Any]:
    """The damped Newton–Raphson row: a first call (compiles), ``repeats`` timed calls with
    the same random starts; compile time is estimated as first call − median."""
    start_seed = seed + _START_SEED_OFFSET
    first = damped_newton_ik(case.robot, case.positions, case.wxyz, config,
                             start_seed).seconds
    walls = []
    for _ in range(repeats):
        solved = damped_newton_ik(case.robot, case.positions, case.wxyz, config, start_seed)
        walls.append(solved.seconds)
    return _baseline_row(case, judge_solver, solved.q, case.positions, case.wxyz,
                         _times(first, walls, max(first - statistics.median(walls), 0.0)))


def measure_scipy(case: Case, judge_solver: IKSolver, count: int, seed: int,
                  config: ScipyConfig = SCIPY_CONFIG) -> dict[str, Any]:
    """The scipy row on the first ``count`` targets: one run (nothing to compile or warm
    up), reported as both the first call and the steady-state time."""
    positions, wxyz = case.positions[:count], case.wxyz[:count]
    solved = scipy_ik(case.robot, positions, wxyz, config, seed + _START_SEED_OFFSET)
    return _baseline_row(case, judge_solver, solved.q, positions, wxyz,
                         _times(solved.seconds, [solved.seconds], None))


def _baseline_row(case: Case, judge_solver: IKSolver, q: np.ndarray, positions: np.ndarray,
                  wxyz: np.ndarray, times: dict[str, Any]) -> dict[str, Any]:
    start = time.perf_counter()
    checked = judge(judge_solver, q, positions, wxyz)
    row = _quality(checked.pose_error, checked.success, checked.max_violation,
                   checked.collision_free, case.scene is not None)
    row["answers"] = RowAnswers(np.asarray(q, dtype=float), positions, wxyz, checked.success)
    row.update(times)
    row["verify_s"] = time.perf_counter() - start  # not part of total_s for baselines
    return row


# ================================================================ the benchmark


def _cases(suite: str, sizes: IKBenchSizes, seed: int, lattice_robots: Sequence[str],
           scaling_robots: Sequence[str]) -> Iterable[tuple[Case, IKSolver]]:
    """Each case with the solver that judges the baselines (built lazily, suite by suite,
    so target generation shows up in the progress)."""
    if suite in ("all", "free"):
        robot = load_robot("tdcr3")
        yield free_case(robot, sizes.free_targets, seed), IKSolver(robot)
    if suite in ("all", "lattice"):
        scene = load_scene("lattice")
        for name in lattice_robots:
            robot = load_robot(name)
            solver = IKSolver(robot, scene)
            yield lattice_case(robot, scene, sizes.lattice_targets, solver.margin, seed), solver
    if suite in ("all", "scaling"):
        for name in scaling_robots:
            robot = load_robot(name)
            yield free_case(robot, sizes.scaling_targets, seed, "scaling"), IKSolver(robot)
    if suite in ("all", "polish"):
        scene = load_scene("lattice")
        for name in POLISH_ROBOTS:
            robot = load_robot(name)
            solver = IKSolver(robot, scene)
            yield lattice_case(robot, scene, sizes.lattice_targets, solver.margin, seed,
                               suite="polish"), solver


def run_ik_benchmark(suite: str = "all", quick: bool = False, repeats: int | None = None,
                     out: str | Path | None = "bench_results/ik", seed: int = 0,
                     sizes: IKBenchSizes | None = None, methods: Sequence[str] = METHODS,
                     lattice_robots: Sequence[str] = LATTICE_ROBOTS,
                     scaling_robots: Sequence[str] = SCALING_ROBOTS,
                     progress: bool = True, echo: bool = True,
                     max_targets: int | None = None,
                     ik_config: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Run the IK benchmark and return one dict per (suite, robot, method) row.

    Long: the suites run in order over shared sizes, targets and report rows.

    Args:
        suite: "all" (free, lattice, scaling, polish), one of those, or "throughput".
        quick: small sizes (``QUICK``: 50/20/20 targets, 10 for scipy, 1 repeat).
        repeats: timed calls per row after the warm-up (default from the sizes).
        out: folder for ``ik.md``, ``ik.csv`` and ``environment.json``; None writes nothing.
        seed: seed of the targets (the baselines' random starts use ``seed + 7919``, the
            cr_nlp solvers ``IKConfig.seed = seed``).
        sizes: explicit sizes (overrides ``quick``).
        methods: which rows to run (a subset of ``METHODS``).
        lattice_robots, scaling_robots: bundled robot names (or files) per suite.
        progress: tqdm progress bar on stderr.
        echo: print the Markdown tables to stdout.
        max_targets: the throughput suite's largest batch (sizes above it are dropped;
            with none left, this one size is run).
        ik_config: ``IKConfig`` fields that the throughput suite's solver overrides (e.g.
            ``{"chunk_size": 8192}``; see ``ik_config_overrides``).

    Asks for one JAX CPU device per core (``use_host_devices``) when JAX has not started
    yet; the devices used are recorded in the environment.

    Row keys: suite, robot, scene, method, targets, success_pct, collision_free_pct
    (None without a scene), mean_pose_error and median_pose_error (‖log(T⁻¹T_target)‖,
    mixed m/rad), max_violation (rad or m: limits, clearance below δ to obstacles and
    between segments at least two apart),
    total_s (median steady-state wall time), per_target_ms, min_s, max_s, runs,
    first_call_s, compile_s (None where nothing compiles), explore_s, refine_s,
    polish_s, verify_s (stage medians, cr_nlp rows), polished_pct and polish_ms (the
    polish stage per target, exact rows), notes, answers (``RowAnswers``: the answers
    and success flags the quality columns come from; not written to the files).
    """
    use_host_devices()  # both cores, as the CLI does (no effect once JAX has started)
    if suite not in ("all", *SUITES):
        raise ValueError(f"suite must be 'all' or one of {SUITES}, got {suite!r}")
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown methods {unknown}; choose from {METHODS}")
    sizes = sizes or (QUICK if quick else FULL)
    if repeats is not None:
        sizes = replace(sizes, repeats=repeats)
    if sizes.repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {sizes.repeats}")
    throughput_sizes = list(sizes.throughput_targets)
    if max_targets is not None:
        if max_targets < 1:
            raise ValueError(f"max_targets must be at least 1, got {max_targets}")
        throughput_sizes = [n for n in throughput_sizes if n <= max_targets] or [max_targets]
    robots = {"free": 1, "lattice": len(lattice_robots), "scaling": len(scaling_robots)}
    jobs = sum(n for s, n in robots.items() if suite in ("all", s)) * len(methods)
    if suite in ("all", "polish"):
        jobs += len(POLISH_ROBOTS) * len(POLISH_METHODS)
    if suite == "throughput":
        jobs = len(throughput_sizes)

    from tqdm import tqdm

    bar = tqdm(total=jobs, desc="bench ik", unit="row", disable=not progress, file=sys.stderr)
    started = time.perf_counter()
    rows: list[dict[str, Any]] = []
    for case, judge_solver in _cases(suite, sizes, seed, lattice_robots, scaling_robots):
        for method in (POLISH_METHODS if case.suite == "polish" else methods):
            bar.set_postfix_str(f"{case.suite} {case.robot.name} {method}")
            if method == NEWTON:
                row = measure_newton(case, judge_solver, sizes.repeats, seed)
            elif method == SCIPY:
                row = measure_scipy(case, judge_solver, sizes.scipy_targets, seed)
            else:
                row = measure_cr_nlp(case, method, sizes.repeats, seed)
            row = {"suite": case.suite, "robot": case.robot.name, "scene": case.scene_name,
                   "method": method, **row}
            row["per_target_ms"] = 1e3 * row["total_s"] / max(row["targets"], 1)
            row["notes"] = _row_note(method, case)
            rows.append(row)
            bar.update()
    if suite == "throughput":
        bar.set_postfix_str("throughput tdcr3")
        rows += measure_throughput(load_robot("tdcr3"), throughput_sizes, sizes.repeats, seed,
                                   bar, ik_config)
    bar.close()
    wall = time.perf_counter() - started
    env = environment()
    env["benchmark wall time"] = f"{wall:.0f} s"
    env["settings"] = (f"suite={suite}, seed={seed}, repeats={sizes.repeats}, sizes: "
                       f"free {sizes.free_targets}, lattice {sizes.lattice_targets}, "
                       f"scaling {sizes.scaling_targets}, scipy subset {sizes.scipy_targets}"
                       + (f", throughput {throughput_sizes}, IKConfig overrides "
                          f"{ik_config or {}}" if suite == "throughput" else ""))
    write_report("ik", format_report(rows, env, sizes), out, {"ik": rows}, env,
                 {"sizes": asdict(sizes)}, {"ik": CSV_KEYS}, echo=echo)
    return rows


CSV_KEYS = ("suite", "robot", "scene", "method", "targets", "success_pct",
            "collision_free_pct", "mean_pose_error", "median_pose_error", "max_violation",
            "total_s", "per_target_ms", "min_s", "max_s", "runs", "first_call_s", "compile_s",
            "explore_s", "refine_s", "polish_s", "verify_s", "polished_pct", "polish_ms",
            "targets_per_s", "device_wait_s", "host_s", "host_pct", "host_per_1e5_s",
            "stream_parts", "notes")
"""The columns of ``ik.csv``, in order."""

TABLE_COLUMNS = (
    Column("robot", "robot"),
    Column("method", "method"),
    Column("targets", "targets"),
    Column("success_pct", "success %", fixed(1)),
    Column("collision_free_pct", "collision-free %", fixed(1)),
    Column("mean_pose_error", "mean pose error"),
    Column("max_violation", "max violation"),
    Column("total_s", "time s (median)"),
    Column("per_target_ms", "ms / target"),
    Column("first_call_s", "first call s"),
    Column("compile_s", "compile s"),
    Column("polish_ms", "polish ms / target"),
    Column("notes", "notes"),
)
"""The columns of the Markdown tables."""

THROUGHPUT_COLUMNS = (
    Column("targets", "targets"),
    Column("success_pct", "success %", fixed(1)),
    Column("total_s", "time s (median)"),
    Column("targets_per_s", "targets / s", fixed(0)),
    Column("explore_s", "explore s"),
    Column("refine_s", "refine s"),
    Column("verify_s", "verify s"),
    Column("device_wait_s", "device wait s"),
    Column("host_s", "host s"),
    Column("host_pct", "host %", fixed(1)),
    Column("host_per_1e5_s", "host s / 10⁵ targets"),
    Column("first_call_s", "first call s"),
    Column("compile_s", "compile s"),
    Column("stream_parts", "parts"),
)
"""The columns of the throughput table."""

_TITLES = {
    "free": "IK without obstacles (tdcr3, targets from uniform configurations free of "
            "self-collision)",
    "lattice": "IK among obstacles (3×3×3 sphere lattice, targets from configurations whose "
               "python-fcl clearance ≥ the solver's sphere margin `IKSolver.margin`)",
    "scaling": "IK scaling with the number of segments (no obstacles)",
    "polish": "The exact stage: IK polish among the lattice's spheres, one process and a "
              "pool of 2",
    "throughput": "IK throughput and where the time goes (tdcr3, no obstacles, default "
                  "`IKConfig`)",
}


def _row_note(method: str, case: Case) -> str:
    notes = []
    if method == SCIPY:
        notes.append("subset: first targets only (see targets), one start, one run")
    if method in (NEWTON, SCIPY) and case.scene is not None:
        notes.append("ignores obstacles")
    return "; ".join(notes)


def format_report(rows: Sequence[dict[str, Any]], env: dict[str, str],
                  sizes: IKBenchSizes) -> str:
    """The Markdown report: one table per suite, the notes, and the environment."""
    parts = ["# cr-nlp bench ik"]
    for suite in SUITES:
        chosen = [r for r in rows if r["suite"] == suite]
        if not chosen:
            continue
        columns = THROUGHPUT_COLUMNS if suite == "throughput" else TABLE_COLUMNS
        parts += [f"## {_TITLES[suite]}", markdown_table(chosen, columns)]
    d, s = NEWTON_CONFIG, SCIPY_CONFIG
    parts += ["## Notes", "\n".join([
        "- success %: pose error ‖log(T⁻¹·T_target)‖ < 0.01 re-evaluated in float64, every "
        "limit held, segments at least two apart at least δ = 2 mm apart and, in the "
        "lattice, at least δ from every obstacle by python-fcl; one rule (`IKSolver.verify`"
        ", i.e. `world.verdict.judge_many`) for every row.",
        "- mean pose error over all targets (mixed m/rad); max violation: largest limit "
        "violation or clearance shortfall below the safety margin δ (m; obstacles and "
        "self), over all targets.",
        f"- time s: median wall time of {sizes.repeats} call(s) after a warm-up call on the "
        "same targets; cr_nlp times include its own float64 verification, baseline times "
        "do not. first call s: the warm-up call's wall time (seed pool, compilation or "
        "loading from JAX's persistent cache, and the exact polisher's CasADi build). "
        "compile s: JAX compile time inside the first call (cr_nlp: `IKResult.timing."
        "compile`; damped Newton: first call − median).",
        "- cr_nlp beam search: default `IKConfig`; single seed: `IKConfig(seeds_per_target=1,"
        " beam_width=1, retry_rounds=0)`; exact polish: `solve(exact=True)` (Ipopt per "
        "target, one process); 2 workers: `IKConfig(polish_workers=2)` (a process pool). "
        "polish ms / target: the polish stage's median time over the targets.",
        f"- damped Newton–Raphson: Δz = −Jᵀ(JJᵀ + λ²I)⁻¹r with λ = {d.damping}, "
        f"{d.iterations} iterations from {d.starts} uniform random starts per target (best "
        "kept), batched in JAX (jacfwd, float32), on the bending vector with projection onto "
        "the limits.",
        f"- scipy {s.method}: one uniform random start per target, bounded θ and L, at most "
        f"{s.max_evaluations} evaluations, CasADi-evaluated pose error; run once on the first "
        f"{sizes.scipy_targets} targets of each case (it is slow).",
        "- The baselines ignore obstacles and self-collision; their answers are judged "
        "by the same verdict (python-fcl, self-clearance) as every other row.",
        "- throughput: explore (the seed pool), refine (per chunk one search program: "
        "nearest-pose lookup, coarse LM, beam, LM; retries) and verify (the float64 "
        "verdict: a compiled float64 program for blocks of 4096 answers, numpy for "
        "smaller ones, python-fcl for obstacles) are `IKResult.timing`; device wait "
        "is the time the host blocked on device results (`IKSolver.device_wait`: device "
        "work nothing on the host overlapped); host s: the wall time outside compiled "
        "programs (less the device wait, the program calls, `IKSolver.device_launch`, and "
        "any compile), the float64 verdict included, as `bench plan` counts it; host %: "
        "its share of the wall; host s / 10⁵ targets: scaled (a GPU's host waits inside "
        "a call for its loops; a CPU may run the program there); parts: the stream's "
        "parts (`IKConfig.stream_size`: 16 384 on a CPU, 131 072 on an accelerator).",
    ])]
    parts += ["## Environment", environment_markdown(env)]
    return "\n\n".join(parts)
