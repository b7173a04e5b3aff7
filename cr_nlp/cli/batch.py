"""``cr-nlp batch ik|plan``: many IK targets or planning problems on Dask distributed,
written chunk by chunk to ``--out DIR`` and resumable (``cr_nlp.batch``; thin front end).

The input files are those of ``cr-nlp ik`` (``--targets``) and ``cr-nlp plan``
(``--problems``); ``DIR/results.json`` has the schema of their ``--out`` files.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

from ._io import (
    Stopped,
    UsageError,
    add_time_limit_option,
    fmt,
    load_robot_arg,
    load_scene_arg,
    read_problems,
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
    _common(plan)


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

    time_limit = time_limit_arg(args)
    robot = load_robot_arg(args.robot)
    scene = load_scene_arg(args.scene)
    options = dict(
        out_dir=args.out,
        scene=scene,
        exact=args.exact,
        workers=args.workers,
        scheduler=args.scheduler,
        host=args.host,
        chunk=args.chunk,
        resume=args.resume,
        progress=not args.no_progress,
    )
    try:
        if args.kind == "ik":
            from ..tasks.ik import IKConfig, read_targets

            try:
                positions, wxyz, problems = read_targets(
                    resolve(args.targets, "targets", "--targets")
                )
            except ValueError as exc:
                raise UsageError(f"--targets: {exc}") from None
            result = run_batch(
                "ik",
                robot,
                (positions, wxyz),
                config=IKConfig(seed=args.seed, polish_time_limit=time_limit),
                problems=problems,
                **options,
            )
            summary = result.summary()
            print(
                f"{robot.name}: {summary['targets']} targets, "
                f"{100 * summary['success_rate']:.1f} % success, mean pose error "
                f"{fmt(summary['mean_pose_error_success'])} (successes), max violation "
                f"{fmt(summary['max_violation'])}; wrote {args.out}/results.json",
                file=sys.stderr,
            )
            return 0
        from ..tasks.trajectory import TrajectoryConfig, with_horizon

        starts, goals, horizon, dt = read_problems(resolve(args.problems, "problems", "--problems"))
        config = with_horizon(
            TrajectoryConfig(seed=args.seed, polish_time_limit=time_limit),
            None if horizon is None else horizon + 1,
            dt,
        )
        # None entries (a problem without "start"/"goal") fail validation with a reason.
        starts = [s if s is not None else [] for s in starts]
        goals = [g if g is not None else [] for g in goals]
        results = run_batch(
            "plan", robot, (starts, goals), config=config, init=args.init, **options
        )
        ok = sum(r.success for r in results)
        print(
            f"{robot.name}: {len(results)} problems, "
            f"{100 * ok / max(len(results), 1):.1f} % success; wrote "
            f"{args.out}/results.json",
            file=sys.stderr,
        )
        return 0
    except BatchError as exc:
        raise UsageError(str(exc)) from None
