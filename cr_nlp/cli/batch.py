"""``cr-nlp batch ik|plan``: many IK targets or planning problems on Dask distributed,
written chunk by chunk to ``--out DIR`` and resumable (``cr_nlp.batch``; thin front end).

The input files are those of ``cr-nlp ik`` (``--targets``) and ``cr-nlp plan``
(``--problems``); ``DIR/results.json`` has the schema of their ``--out`` files. With
``--model cosserat`` the tension tasks run instead, with the load options of ``cr-nlp ik
--model cosserat`` (``_tension_ik``).
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

from . import _loads, _tension_ik
from ._io import (
    Stopped,
    UsageError,
    add_time_limit_option,
    fmt,
    load_robot_arg,
    load_scene_arg,
    read_problems_arg,
    resolve,
    stop_on_signals,
    time_limit_arg,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp batch`` and its two kinds on the command's subparsers."""
    p = sub.add_parser(
        "batch",
        help="many IK targets or planning problems on a Dask cluster, resumable",
        description="Splits the input into chunks, solves each chunk as one Dask task (a "
        "LocalCluster with --workers, an existing cluster with --scheduler), "
        "writes every finished chunk to DIR at once and DIR/results.json at "
        "the end. Rerun with --resume to solve only the missing chunks.",
    )
    kinds = p.add_subparsers(dest="kind", required=True)

    ik = kinds.add_parser("ik", help="IK for many target poses (the input of cr-nlp ik)")
    ik.add_argument("--robot", required=True, help="robot JSON file or bundled name (tdcr3)")
    ik.add_argument(
        "--targets",
        required=True,
        help='JSON file {"poses": [{"position": [x,y,z], "wxyz": [w,x,y,z]}, '
        "...]} or bundled name (tdcr3_lattice)",
    )
    ik.add_argument("--scene", help="scene JSON file or bundled name (obstacles)")
    _model_option(ik, "tendon tensions on the Cosserat-rod model (results kind tension_ik)")
    _tension_ik.add_options(ik, pool=True)
    _common(ik)

    plan = kinds.add_parser(
        "plan", help="trajectory planning for many start/goal pairs (the input of cr-nlp plan)"
    )
    plan.add_argument("--robot", required=True, help="robot JSON file or bundled name (tdcr3)")
    plan.add_argument("--scene", help="scene JSON file or bundled scene name (obstacles)")
    plan.add_argument(
        "--problems",
        required=True,
        help='JSON file {"problems": [{"start": [q], "goal": [q]}, ...], '
        '"horizon": H (optional), "dt": seconds (optional)}, or bundled '
        "name (tdcr3_shelf)",
    )
    plan.add_argument(
        "--init",
        choices=("roadmap", "straight"),
        default="roadmap",
        help="initial trajectories (as cr-nlp plan; default roadmap)",
    )
    _model_option(plan, "tension trajectories on the Cosserat-rod model, --problems "
                        '{"problems": [{"start": [N…], "goal": [N…]}]} (results kind '
                        "tension_trajectory; no --exact)")
    _loads.add_load_options(plan)
    _common(plan)


def _model_option(p: argparse.ArgumentParser, cosserat: str) -> None:
    p.add_argument("--model", choices=("pcc", "cosserat"), default="pcc",
                   help="pcc (default): configurations of the constant-curvature model; "
                        f"cosserat: {cosserat}, robots with a 'mechanics' block")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--exact",
        action="store_true",
        help="polish every answer with Ipopt, constraints as hard constraints",
    )
    add_time_limit_option(p)
    p.add_argument("--seed", type=int, default=0, help="seed of the search (default 0)")
    p.add_argument(
        "--out", required=True, help="DIR for manifest.json, chunk_<id>.npz files and results.json"
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=int,
        help="start a LocalCluster of N worker processes (default: one per core)",
    )
    where.add_argument("--scheduler", help="address of a running Dask scheduler (tcp://host:8786)")
    p.add_argument(
        "--host",
        help="address the LocalCluster listens on (default 127.0.0.1: this machine only; "
        "another address makes it reachable from the network, with a warning)",
    )
    p.add_argument(
        "--chunk",
        type=int,
        help="problems per chunk, one Dask task each (default: about four "
        "chunks per worker, at most 256 targets or 8 problems; penalty-mode IK: one "
        "per worker, at most 4096 targets)",
    )
    p.add_argument(
        "--resume", action="store_true", help="finish the job in DIR: solve only its missing chunks"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the job, write DIR/results.json and print a one-line summary on stderr.

    SIGINT and SIGTERM (also when the shell started this with SIGINT ignored) close the
    cluster, keep the chunks written so far and exit with 128 + the signal's number,
    saying how to resume."""
    from ..batch import ExposedClusterWarning, exposure_warning

    time_limit_arg(args)  # a bad value fails here, before a cluster starts
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be at least 1, got {args.workers}")
    if args.chunk is not None and args.chunk < 1:
        raise UsageError(f"--chunk must be at least 1, got {args.chunk}")
    if args.host is not None and args.scheduler is not None:
        raise UsageError("--host is where a cluster started here listens: not with --scheduler")
    exposed = exposure_warning(args.host) if args.host is not None else None
    if exposed is not None:
        print(f"cr-nlp batch: warning: {exposed}", file=sys.stderr)
    with stop_on_signals(), warnings.catch_warnings():
        # Printed above as one line, not again by start_local_cluster.
        warnings.simplefilter("ignore", ExposedClusterWarning)
        try:
            return _solve(args)
        except Stopped as stopped:
            print(f"cr-nlp batch: stopped by {stopped.name}; {_left(Path(args.out))}",
                  file=sys.stderr)
            return 128 + stopped.signum


def _left(out: Path) -> str:
    """What a stopped job left in ``out`` and how to finish it."""
    from ..batch import MANIFEST

    written = len(list(out.glob("chunk_*.npz")))
    try:
        total = f" of {json.loads((out / MANIFEST).read_text())['chunks']}"
    except (OSError, ValueError, KeyError, TypeError):
        total = ""
    return (f"{written}{total} chunks are written in {out}; rerun the same command with "
            f"--resume to solve the rest")


def _solve(args: argparse.Namespace) -> int:
    """The job of ``run``: its exit status."""
    from ..batch import BatchError, run_batch

    robot = load_robot_arg(args.robot)
    if args.model == "cosserat":
        _loads.needs_mechanics(robot)
        inputs, options = _tension_job(args, robot)
    elif args.kind == "ik":
        inputs, options = _ik_job(args)
    else:
        inputs, options = _plan_job(args)
    try:
        result = run_batch(
            args.kind,
            robot,
            inputs,
            out_dir=args.out,
            scene=load_scene_arg(args.scene),
            exact=args.exact,
            workers=args.workers,
            scheduler=args.scheduler,
            host=args.host,
            chunk=args.chunk,
            resume=args.resume,
            progress=not args.no_progress,
            **options,
        )
    except BatchError as exc:
        raise UsageError(str(exc)) from None
    print(f"{_summary(args, result, robot.name)}; wrote {args.out}/results.json",
          file=sys.stderr)
    return 0


def _targets(args: argparse.Namespace) -> tuple:
    """``--targets``: positions (T, 3) m, wxyz (T, 4) and a reason per bad target."""
    from ..tasks.readers import read_targets

    try:
        return read_targets(resolve(args.targets, "targets", "--targets"))
    except ValueError as exc:
        raise UsageError(f"--targets: {exc}") from None


def _ik_job(args: argparse.Namespace) -> tuple[tuple, dict]:
    """PCC IK: ``run_batch``'s inputs and its options of this kind."""
    from ..tasks.geometry.ik import IKConfig

    positions, wxyz, problems = _targets(args)
    config = IKConfig(seed=args.seed, polish_time_limit=time_limit_arg(args))
    return (positions, wxyz), {"config": config, "problems": problems}


def _plan_job(args: argparse.Namespace) -> tuple[tuple, dict]:
    """PCC planning: ``run_batch``'s inputs and its options of this kind."""
    from ..tasks.geometry.trajectory import TrajectoryConfig, with_horizon

    starts, goals, horizon, dt = read_problems_arg(args.problems)
    config = with_horizon(
        TrajectoryConfig(seed=args.seed, polish_time_limit=time_limit_arg(args)),
        None if horizon is None else horizon + 1,
        dt,
    )
    # None entries (a problem without "start"/"goal") fail validation with a reason.
    starts = [s if s is not None else [] for s in starts]
    goals = [g if g is not None else [] for g in goals]
    return (starts, goals), {"config": config, "init": args.init}


def _tension_job(args: argparse.Namespace, robot: object) -> tuple[tuple, dict]:
    """``--model cosserat``: ``run_batch``'s inputs and options, the loads from the
    options of ``cr-nlp ik --model cosserat`` (``_loads.loads_from_args``)."""
    length = float(sum(s.length_min for s in robot.segments))
    loads = _loads.loads_from_args(args, length, robot)
    options = {"model": "cosserat", "loads": loads}
    if args.kind == "ik":
        from ..tasks.mechanics.ik import TensionIKConfig

        positions, wxyz, problems = _targets(args)
        return (positions, wxyz if args.orientation else None), {
            **options, "config": TensionIKConfig(seed=args.seed, **_tension_ik.pool_options(args)),
            "problems": problems,
            "time_limit": time_limit_arg(args)}
    from ..tasks.mechanics.trajectory import TensionTrajectoryConfig
    from ..tasks.readers import read_tension_problems

    try:
        starts, goals = read_tension_problems(robot, resolve(args.problems, "problems",
                                                             "--problems"))
    except ValueError as exc:
        raise UsageError(f"--problems: {exc}") from None
    return (starts, goals), {**options, "config": TensionTrajectoryConfig(seed=args.seed)}


def _summary(args: argparse.Namespace, result: object, name: str) -> str:
    """One line on the job's answers."""
    if args.kind == "plan":
        ok = sum(r.success for r in result)
        model = " (Cosserat)" if args.model == "cosserat" else ""
        return (f"{name}{model}: {len(result)} problems, "
                f"{100 * ok / max(len(result), 1):.1f} % success")
    summary = result.summary()
    if args.model == "cosserat":
        return (f"{name} (Cosserat): {summary['targets']} targets, "
                f"{100 * summary['success_rate']:.1f} % success, median position error "
                f"{fmt(summary['median_position_error_mm'])} mm")
    return (f"{name}: {summary['targets']} targets, "
            f"{100 * summary['success_rate']:.1f} % success, mean pose error "
            f"{fmt(summary['mean_pose_error_success'])} (successes), max violation "
            f"{fmt(summary['max_violation'])}")
