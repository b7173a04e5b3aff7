"""``cr-nlp bench ik|plan|follow|clearance|batch|statics|tension|startup|calibration|profile``:
benchmarks that print tables.

Every benchmark gets the same options from ``add_common_options`` (``--out`` folder,
``--repeats``, ``--robot``, ``--seed``, ``--devices``, ``--no-progress``, ``--markdown``) and
writes its report through ``cr_nlp.bench._common.write_report`` (Markdown printed and saved,
CSV per table, ``environment.json``); ``--markdown FILE`` also puts it, with the command,
versions, device and date, into its own section of FILE (docs/benchmarks.md).
Adding a benchmark: one ``_add_<name>`` function here that calls ``add_common_options`` and
points ``run`` at the library's ``run_<name>_benchmark``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ._io import UsageError


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp bench`` and its benchmarks on the command's subparsers."""
    p = sub.add_parser("bench", help="benchmarks that print tables (not tests)")
    group = p.add_subparsers(dest="benchmark", required=True)
    for add in BENCHMARKS:
        add(group)


def add_common_options(p: argparse.ArgumentParser, name: str, *,
                       repeats: int | None | bool = False, repeats_help: str = "",
                       robot: bool = True, seed: bool = False) -> None:
    """The options every benchmark shares: ``--out`` (default ``bench_results/<name>``),
    ``--repeats`` (timed runs after a warm-up; its default, or no option when
    ``repeats`` is False), ``--robot`` (file or bundled name), ``--seed``, ``--devices``
    (host devices, default one per core), ``--no-progress`` and ``--markdown``."""
    p.add_argument("--out", default=f"bench_results/{name}",
                   help=f"output folder (default bench_results/{name})")
    if repeats is not False:
        p.add_argument("--repeats", type=int, default=repeats,
                       help=repeats_help or f"timed runs per row after the warm-up "
                                            f"(default {repeats})")
    if robot:
        p.add_argument("--robot", default="tdcr3", help="robot name or file (default tdcr3)")
    if seed:
        p.add_argument("--seed", type=int, default=0, help=f"seed of the {name} problems "
                                                           "(default 0)")
    p.add_argument("--devices", type=int, default=None,
                   help="JAX host devices to shard batches over (default: one per core)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--markdown", metavar="FILE", default=None,
                   help="also write the report into FILE (e.g. docs/benchmarks.md) as this "
                        "benchmark's section (replaced if present), with the command, "
                        "versions, device and date")


def _check_repeats(args: argparse.Namespace) -> None:
    if getattr(args, "repeats", None) is not None and args.repeats < 1:
        raise UsageError("--repeats must be at least 1")


def _wrote(args: argparse.Namespace, name: str) -> None:
    print(f"wrote {Path(args.out) / (name + '.md')}, its CSV files and environment.json",
          file=sys.stderr)
    if args.markdown:
        _publish(args, name)


def _publish(args: argparse.Namespace, name: str) -> None:
    """``--markdown FILE``: the report just written to ``--out`` becomes the section
    ``<name>`` (``<name>-<suite>`` for one suite) of FILE."""
    from ..bench._common import publish_markdown

    out = Path(args.out)
    env = json.loads((out / "environment.json").read_text())["environment"]
    suite = getattr(args, "suite", "all")
    section = name if suite == "all" else f"{name}-{suite}"
    command = getattr(args, "command_line", None) or "cr-nlp bench " + name
    path = publish_markdown(args.markdown, section, (out / f"{name}.md").read_text(),
                            command, env)
    print(f"wrote the section {section!r} of {path}", file=sys.stderr)


# ---------------------------------------------------------------- ik


def _add_ik(group: argparse._SubParsersAction) -> None:
    from ..bench.suites import IK_FULL as FULL
    from ..bench.suites import IK_QUICK as QUICK
    from ..bench.suites import IK_SUITES as SUITES

    p = group.add_parser(
        "ik", help="IK benchmark: cr_nlp vs damped Newton–Raphson and scipy (docs/design.md §4)",
        description="Runs the IK suites, prints Markdown tables and writes ik.md, ik.csv and "
                    "environment.json to --out.")
    p.add_argument("--suite", choices=("all", *SUITES), default="all",
                   help="which suite (default all)")
    p.add_argument("--quick", action="store_true",
                   help="small sizes for CI and notebooks (50/20/20 targets, 1 repeat)")
    p.add_argument("--max-targets", type=int, default=None,
                   help=f"--suite throughput: largest batch (default "
                        f"{max(FULL.throughput_targets)}; sizes "
                        f"{', '.join(map(str, FULL.throughput_targets))} up to it)")
    p.add_argument("--ik-config", nargs="+", default=[], metavar="KEY=VALUE",
                   help="--suite throughput: IKConfig fields to override, e.g. "
                        "chunk_size=8192 refine_round=40")
    add_common_options(p, "ik", repeats=None, robot=False, seed=True,
                       repeats_help=f"timed runs per row after the warm-up (default "
                                    f"{FULL.repeats}, {QUICK.repeats} with --quick)")
    p.set_defaults(run=_run_ik)


def _run_ik(args: argparse.Namespace) -> int:
    from ..bench.ik import run_ik_benchmark

    _check_repeats(args)
    if args.max_targets is not None and args.max_targets < 1:
        raise UsageError("--max-targets must be at least 1")
    from ..bench.ik import ik_config_overrides

    try:
        overrides = ik_config_overrides(args.ik_config)
    except ValueError as exc:
        raise UsageError(f"--ik-config: {exc}") from None
    run_ik_benchmark(suite=args.suite, quick=args.quick, repeats=args.repeats, out=args.out,
                     seed=args.seed, progress=not args.no_progress,
                     max_targets=args.max_targets, ik_config=overrides)
    _wrote(args, "ik")
    return 0


# ---------------------------------------------------------------- plan


def _add_plan(group: argparse._SubParsersAction) -> None:
    from ..bench.suites import PLAN_FULL as FULL
    from ..bench.suites import PLAN_METHODS as METHODS
    from ..bench.suites import PLAN_QUICK as QUICK
    from ..bench.suites import PLAN_SCENES as SCENES

    DEFAULT_METHODS = METHODS

    p = group.add_parser(
        "plan", help="trajectory benchmark: roadmap/straight-line + LM, exact, RRT-Connect",
        description="Runs the trajectory-planning benchmark (docs/design.md §4), prints Markdown "
                    "tables and writes plan.md, plan.csv, roadmap_build.csv, iterations.csv "
                    "and iterations.png to --out.")
    p.add_argument("--quick", action="store_true",
                   help=f"small sizes ({QUICK.pairs_per_scene} pairs per scene)")
    p.add_argument("--pairs", type=int, default=None,
                   help=f"start/goal pairs per scene (default {FULL.pairs_per_scene})")
    p.add_argument("--scenes", nargs="+", default=list(SCENES),
                   help="scene names or files (default: shelf cabinet random_27)")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(DEFAULT_METHODS),
                   help="rows to run (default all)")
    p.add_argument("--iterations", type=int, nargs="*", default=None,
                   help="LM iteration budgets of the sweep figure (none: no sweep)")
    p.add_argument("--sweep-pairs", type=int, default=None,
                   help=f"pairs per scene of the sweep (default {FULL.sweep_pairs})")
    p.add_argument("--search-pairs", type=int, nargs="+", default=None,
                   help="instead of the benchmark: time the roadmap search alone, scipy vs "
                        "device, for these pair counts (e.g. 1 20 1000)")
    add_common_options(p, "plan", seed=True)
    p.set_defaults(run=_run_plan)


def _run_plan(args: argparse.Namespace) -> int:
    from ..bench.plan import run_plan_benchmark, search_scaling

    if args.search_pairs:
        search_scaling(args.scenes, args.search_pairs, robot=args.robot, out=args.out,
                       seed=args.seed)
        _wrote(args, "search")
        return 0
    run_plan_benchmark(quick=args.quick, pairs_per_scene=args.pairs, scenes=args.scenes,
                       robot=args.robot, out=args.out, seed=args.seed, methods=args.methods,
                       iteration_budgets=args.iterations, sweep_pairs=args.sweep_pairs,
                       progress=not args.no_progress)
    _wrote(args, "plan")
    return 0


# ---------------------------------------------------------------- follow


def _add_follow(group: argparse._SubParsersAction) -> None:
    from ..bench.suites import FOLLOW_MODES as MODES
    from ..bench.suites import FOLLOW_SHAPES as SHAPES

    p = group.add_parser(
        "follow", help="path-following benchmark: square, sine, ICRA; penalty and exact",
        description="Runs the path-following benchmark (docs/design.md §4), prints a Markdown "
                    "table and writes follow.md, follow.csv and figures to --out.")
    p.add_argument("--shapes", nargs="+", default=list(SHAPES),
                   help="bundled shapes (square sine icra) or path files (no obstacles)")
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES),
                   help="rows to run (default penalty and exact)")
    p.add_argument("--dt", type=float, default=None,
                   help="seconds between waypoints instead of the path files' (smaller: "
                        "faster tendons, the speed limit binds and exact mode polishes)")
    add_common_options(p, "follow", repeats=3)
    p.set_defaults(run=_run_follow)


def _run_follow(args: argparse.Namespace) -> int:
    from ..bench.follow import run_follow_benchmark

    _check_repeats(args)
    if args.dt is not None and not args.dt > 0:
        raise UsageError(f"--dt must be a positive number of seconds, got {args.dt}")
    run_follow_benchmark(args.shapes, args.modes, args.repeats, args.robot, args.out,
                         progress=not args.no_progress, dt=args.dt)
    _wrote(args, "follow")
    return 0


# ---------------------------------------------------------------- clearance


def _add_clearance(group: argparse._SubParsersAction) -> None:
    p = group.add_parser("clearance",
                         help="benchmark batched clearance (configurations per second)")
    p.add_argument("--scene", nargs="+", default=["lattice"],
                   help="scene files or bundled names (default: lattice)")
    p.add_argument("--configs", type=int, default=100_000, help="batch size")
    p.add_argument("--dtype", nargs="+", default=["float32"], choices=["float32", "float64"])
    add_common_options(p, "clearance", repeats=7,
                       repeats_help="timed runs (median reported; default 7)")
    p.set_defaults(run=_run_clearance)


def _run_clearance(args: argparse.Namespace) -> int:
    from ..bench.clearance import run_clearance_benchmark

    _check_repeats(args)
    run_clearance_benchmark(robot=args.robot, scenes=tuple(args.scene), configs=args.configs,
                            dtypes=tuple(args.dtype), repeats=args.repeats, out=args.out)
    _wrote(args, "clearance")
    return 0


# ---------------------------------------------------------------- statics


def _add_statics(group: argparse._SubParsersAction) -> None:
    from ..bench.suites import STATICS_SETS as SETS

    p = group.add_parser("statics", help="Cosserat statics: solves per second and "
                                         "convergence for 10^2-10^5 cases")
    p.add_argument("--cases", type=int, nargs="+", default=[100, 1000, 10_000],
                   help="batch sizes (default 100 1000 10000)")
    p.add_argument("--loads", nargs="+", choices=SETS, default=list(SETS),
                   help="load sets (default: tensions mixed)")
    p.add_argument("--dtype", nargs="+", default=["float64", "float32"],
                   choices=["float32", "float64"])
    add_common_options(p, "statics", repeats=5,
                       repeats_help="timed runs (median reported; default 5)", robot=False,
                       seed=True)
    p.add_argument("--robot", default="tdcr2_rao2021",
                   help="robot with a mechanics block (default tdcr2_rao2021)")
    p.add_argument("--ik-targets", type=int, nargs="*", default=[1000],
                   help="tension-space IK rows: targets per batch (default 1000; none: "
                        "no IK rows)")
    p.set_defaults(run=_run_statics)


def _run_statics(args: argparse.Namespace) -> int:
    from ..bench.statics import run_statics_benchmark

    _check_repeats(args)
    run_statics_benchmark(robot=args.robot, sizes=tuple(args.cases),
                          load_sets=tuple(args.loads), dtypes=tuple(args.dtype),
                          repeats=args.repeats, seed=args.seed, out=args.out,
                          ik_targets=tuple(args.ik_targets))
    _wrote(args, "statics")
    return 0


def _add_tension(group: argparse._SubParsersAction) -> None:
    p = group.add_parser("tension", help="tension-space IK, planning and following under "
                                         "gravity and a 5 g payload (Cosserat model)")
    p.add_argument("--suite", choices=("loop", "clutter", "live"), default="loop",
                   help="loop (default): planning among four obstacles and one followed "
                        "loop; clutter: IK, following and planning among 14 spheres and "
                        "2 boxes through the loaded workspace; live: the viewer's dragged "
                        "target, one update at a time (ms per update), without a scene "
                        "and in the clutter")
    p.add_argument("--problems", type=int, default=20, help="planning problems (default 20)")
    p.add_argument("--waypoints", type=int, default=None,
                   help="waypoints of each followed path or drag (default 100 loop, 60 "
                        "clutter and live)")
    p.add_argument("--targets", type=int, default=200,
                   help="clutter: IK targets (default 200)")
    p.add_argument("--paths", type=int, default=6, help="clutter: followed paths (default 6)")
    p.add_argument("--modes", nargs="+", choices=("penalty", "exact"), default=["penalty"],
                   help="clutter: modes of every row, IK, following and planning "
                        "(default penalty)")
    p.add_argument("--polish-accepted", action="store_true",
                   help="clutter: exact mode polishes every path and plan, also those the "
                        "verdict accepts (times the exact stage on each)")
    add_common_options(p, "tension", repeats=3, robot=False, seed=True)
    p.add_argument("--robot", default="tdcr2_rao2021",
                   help="robot with a mechanics block (default tdcr2_rao2021; the loop "
                        "suite: 2×3 tendons)")
    p.set_defaults(run=_run_tension)


def _run_tension(args: argparse.Namespace) -> int:
    _check_repeats(args)
    if args.suite == "clutter":
        from ..bench.tension_clutter import CrowdedScene, run_tension_clutter_benchmark

        try:
            run_tension_clutter_benchmark(robot=args.robot, targets=args.targets,
                                          paths=args.paths, waypoints=args.waypoints or 60,
                                          problems=args.problems, modes=tuple(args.modes),
                                          repeats=args.repeats, seed=args.seed,
                                          polish_accepted=args.polish_accepted, out=args.out)
        except CrowdedScene as exc:
            raise UsageError(f"{exc} (try another --seed)") from exc
        _wrote(args, "tension_clutter")
        return 0
    if args.suite == "live":
        from ..bench.tension_live import run_tension_live_benchmark

        run_tension_live_benchmark(robot=args.robot, waypoints=args.waypoints or 60,
                                   repeats=args.repeats, seed=args.seed, out=args.out)
        _wrote(args, "tension_live")
        return 0
    from ..bench.tension_motion import run_tension_motion_benchmark
    from ..model import load_robot

    robot = load_robot(args.robot)
    if (robot.n_tendons, robot.tendons.per_segment) != (6, 3):
        raise UsageError(f"the loop suite drives both segments of a 2×3-tendon robot; "
                         f"--robot {args.robot} has {robot.n_tendons} tendons, "
                         f"{robot.tendons.per_segment} per segment (--suite clutter runs any "
                         "robot with a mechanics block)")
    run_tension_motion_benchmark(robot=args.robot, problems=args.problems,
                                 waypoints=args.waypoints or 100, repeats=args.repeats,
                                 seed=args.seed, out=args.out)
    _wrote(args, "tension")
    return 0


# ---------------------------------------------------------------- batch


def _add_batch(group: argparse._SubParsersAction) -> None:
    from ..bench.suites import BATCH_MODES as MODES

    p = group.add_parser(
        "batch", help="batch jobs on Dask: throughput per worker count vs in-process",
        description="Times cr_nlp.batch.run_batch on LocalClusters of --workers worker "
                    "processes, IKSolver in this process, and IKSolver in N plain processes "
                    "at once (the machine's ceiling for the split) on the same free targets "
                    "(after warm-up, compile excluded); writes batch.md, batch.csv and "
                    "environment.json to --out.")
    p.add_argument("--targets", type=int, default=1000, help="free targets (default 1000)")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2],
                   help="worker counts, one LocalCluster each (default 1 2)")
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES),
                   help="penalty (JAX stages) and/or exact (with the Ipopt polish)")
    p.add_argument("--chunk", type=int, default=None,
                   help="targets per chunk (default: cr_nlp.batch.default_chunk for the "
                        "largest worker count and the mode, the same for every row of a mode)")
    add_common_options(p, "batch", repeats=1, seed=True)
    p.set_defaults(run=_run_batch)


def _run_batch(args: argparse.Namespace) -> int:
    from ..bench.batch import run_batch_benchmark

    _check_repeats(args)
    if args.targets < 1 or min(args.workers) < 1 or (args.chunk is not None and args.chunk < 1):
        raise UsageError("--targets, --workers and --chunk must be at least 1")
    run_batch_benchmark(robot=args.robot, targets=args.targets, workers=args.workers,
                        modes=args.modes, chunk=args.chunk, repeats=args.repeats,
                        seed=args.seed, out=args.out, progress=not args.no_progress)
    _wrote(args, "batch")
    return 0


# ---------------------------------------------------------------- startup


def _add_startup(group: argparse._SubParsersAction) -> None:
    from ..bench.suites import STARTUP_ENTRIES

    p = group.add_parser(
        "startup", help="start-up: whole processes from an empty cache and a warm one",
        description="Times each entry point as a new process, cold (empty cache) and warm "
                    "(a second process): interpreter and imports, tracing, XLA, first and "
                    "steady call. Writes startup.md, startup.csv and environment.json.")
    p.add_argument("--entries", nargs="+", choices=STARTUP_ENTRIES,
                   default=list(STARTUP_ENTRIES),
                   help="entry points to time (default all)")
    add_common_options(p, "startup", repeats=1,
                       repeats_help="cold/warm pairs per entry (median reported; default 1)",
                       robot=False)
    p.set_defaults(run=_run_startup)


def _run_startup(args: argparse.Namespace) -> int:
    from ..bench.startup import run_startup_benchmark

    _check_repeats(args)
    run_startup_benchmark(entries=tuple(args.entries), repeats=args.repeats, out=args.out,
                          progress=not args.no_progress)
    _wrote(args, "startup")
    return 0


def _add_calibration(group: argparse._SubParsersAction) -> None:
    from ..bench.suites import CALIBRATION_FAMILIES as FAMILIES

    p = group.add_parser("calibration", help="the train-only fold score of a calibration: "
                                             "each family of patterns held out in turn")
    p.add_argument("--families", default=",".join(FAMILIES),
                   help=f"comma-separated families to hold out (default: all, "
                        f"{','.join(FAMILIES)})")
    p.add_argument("--axial-compression", nargs="?", const="segments",
                   choices=("segments", "tendons"),
                   help="fit the axial compliance (as cr-nlp calibrate's option)")
    p.add_argument("--history", action="store_true",
                   help="score the history-aware models (each fold refits the static one)")
    p.add_argument("--model", choices=("pcc", "cosserat"), default="pcc",
                   help="the geometric calibration (default) or the Cosserat rod driven by "
                        "the commands (calibrate --model cosserat: ~10 min per fold)")
    add_common_options(p, "calibration", robot=False)
    p.add_argument("--robot", default="ftdcr_v6",
                   help="bundled robot with a training recording (default ftdcr_v6)")
    p.set_defaults(run=_run_calibration)


def _run_calibration(args: argparse.Namespace) -> int:
    from ..bench.calibration import run_calibration_benchmark

    try:
        run_calibration_benchmark(robot=args.robot, families=tuple(args.families.split(",")),
                                  axial_compression=args.axial_compression,
                                  history=args.history, out=args.out,
                                  progress=not args.no_progress, model=args.model)
    except ValueError as exc:
        option = "--model" if str(exc).startswith("model") else "--families"
        raise UsageError(f"{option}: {exc}") from None
    _wrote(args, "calibration")
    return 0


# ---------------------------------------------------------------- profile


def _add_profile(group: argparse._SubParsersAction) -> None:
    p = group.add_parser("profile", help="where one warm IK solve's time goes: kernels or "
                                         "ops per timeline (device streams, XLA threads, "
                                         "host Python) from a jax.profiler trace")
    p.add_argument("--targets", type=int, default=10_000,
                   help="free IK targets of the traced solve (default 10000)")
    p.add_argument("--top", type=int, default=25,
                   help="costliest kernels or ops listed per timeline (default 25)")
    add_common_options(p, "profile", seed=True)
    p.set_defaults(run=_run_profile)


def _run_profile(args: argparse.Namespace) -> int:
    from ..bench.profile import run_profile_benchmark

    if args.targets < 1 or args.top < 1:
        raise UsageError(f"--targets and --top must be at least 1, got {args.targets} and "
                         f"{args.top}")
    run_profile_benchmark(robot=args.robot, targets=args.targets, seed=args.seed,
                          top=args.top, out=args.out)
    _wrote(args, "profile")
    return 0


BENCHMARKS = [_add_ik, _add_plan, _add_follow, _add_clearance, _add_batch, _add_statics,
              _add_tension, _add_startup, _add_calibration, _add_profile]
"""The ``cr-nlp bench`` benchmarks, in ``--help`` order."""
