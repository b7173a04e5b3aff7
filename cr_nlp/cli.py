"""The ``cr-nlp`` command: one subcommand per task, each a thin front end to the library."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .model import ModelFileError, Robot


class UsageError(Exception):
    """Bad command-line input: printed as one line, exit status 2."""


def parse_numbers(text: str, what: str) -> list[float]:
    """'0.1,0.2,1' → [0.1, 0.2, 1.0], with an error that names ``what``."""
    try:
        return [float(v) for v in text.replace(" ", "").split(",") if v != ""]
    except ValueError:
        raise UsageError(f"{what}: expected comma-separated numbers, got {text!r}") from None


def read_json(path: str | Path, what: str) -> Any:
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise UsageError(f"{what}: file not found: {path}") from None
    except json.JSONDecodeError as exc:
        raise UsageError(f"{what}: {path} is not valid JSON: {exc}") from None


def write_json(data: Any, path: str | None) -> None:
    """Write JSON to ``path``, or to stdout when ``path`` is None or '-'."""
    text = json.dumps(data, indent=2)
    if path in (None, "-"):
        print(text)
    else:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(text + "\n")


def configurations_from_args(robot: Robot, q: str | None, q_file: str | None) -> np.ndarray:
    """(k, 3n) configurations from ``--q`` or ``--q-file`` ({"q": [[...], ...]})."""
    if (q is None) == (q_file is None):
        raise UsageError("give exactly one of --q or --q-file")
    rows = [parse_numbers(q, "--q")] if q is not None else read_json(q_file, "--q-file")
    if q_file is not None:
        if not isinstance(rows, dict) or not isinstance(rows.get("q"), list):
            raise UsageError(f"--q-file: {q_file} must hold {{\"q\": [[...], ...]}}")
        rows = rows["q"]
    out = []
    for i, row in enumerate(rows):
        try:
            out.append(robot.full_q(row))
        except (ValueError, TypeError) as exc:
            raise UsageError(f"configuration {i}: {exc}") from None
    return np.array(out)


# ---------------------------------------------------------------- fk

def _add_fk(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fk", help="forward kinematics: tip pose, tendon lengths, backbone")
    p.add_argument("--robot", required=True, help="robot JSON file")
    p.add_argument("--q", help="θ1,φ1,L1,... (rad, rad, m); fixed lengths may be omitted")
    p.add_argument("--q-file", help='JSON file {"q": [[...], ...]}')
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(run=_run_fk)


def _run_fk(args: argparse.Namespace) -> int:
    from .model import backbone_points, tendon_lengths, tip_pose
    from .model.rotations import wxyz_from_matrix

    robot = Robot.from_file(args.robot)
    qs = configurations_from_args(robot, args.q, args.q_file)
    pos, rot = (np.asarray(x) for x in tip_pose(robot, qs))
    lengths = np.asarray(tendon_lengths(robot, qs))
    points = np.asarray(backbone_points(robot, qs))
    records = [
        {"position": pos[i].tolist(), "wxyz": wxyz_from_matrix(rot[i]).tolist(),
         "tendon_lengths": lengths[i].tolist(), "backbone": points[i].tolist()}
        for i in range(len(qs))
    ]
    if args.json:
        write_json(records[0] if args.q is not None else records, None)
        return 0
    for i, rec in enumerate(records):
        if len(records) > 1:
            print(f"# configuration {i}: q = {np.round(qs[i], 6).tolist()}")
        print(f"robot          {robot.name} ({robot.n_segments} segments, "
              f"{robot.tendons.routing} routing)")
        print("tip position   [{:.6f}, {:.6f}, {:.6f}] m".format(*rec["position"]))
        print("tip wxyz       [{:.6f}, {:.6f}, {:.6f}, {:.6f}]".format(*rec["wxyz"]))
        m = robot.tendons.per_segment
        for k in range(0, len(rec["tendon_lengths"]), m):
            label = "tendons" if robot.tendons.routing == "shared" else f"tendons seg {k // m + 1}"
            vals = ", ".join(f"{v:.6f}" for v in rec["tendon_lengths"][k: k + m])
            print(f"{label:<15}[{vals}] m")
    return 0


# ---------------------------------------------------------------- ik

def read_pose_file(path: str, what: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Poses from {"poses": [{"position": [x, y, z], "wxyz": [w, x, y, z]}, ...]}.

    A malformed file is a usage error; a malformed entry becomes a NaN row with a reason,
    so one bad target never sinks the batch."""
    data = read_json(path, what)
    if not isinstance(data, dict) or not isinstance(data.get("poses"), list):
        raise UsageError(f"{what}: {path} must hold {{\"poses\": [{{\"position\": [x, y, z], "
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


def _add_ik(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ik", help="inverse kinematics for a batch of target poses")
    p.add_argument("--robot", required=True, help="robot JSON file")
    p.add_argument("--targets", required=True,
                   help='JSON file {"poses": [{"position": [x,y,z], "wxyz": [w,x,y,z]}, ...]}')
    p.add_argument("--scene", help="scene JSON file (obstacles)")
    p.add_argument("--exact", action="store_true",
                   help="polish every answer with Ipopt, constraints as hard constraints")
    p.add_argument("--seed", type=int, default=0, help="seed of the search (default 0)")
    p.add_argument("--out", required=True, help="RESULT.json to write ('-' for stdout)")
    p.set_defaults(run=_run_ik)


def _run_ik(args: argparse.Namespace) -> int:
    from .tasks.ik import IKConfig, IKSolver
    from .world import load_scene

    robot = Robot.from_file(args.robot)
    scene = load_scene(args.scene) if args.scene else None
    positions, wxyz, problems = read_pose_file(args.targets, "--targets")
    solver = IKSolver(robot, scene, IKConfig(seed=args.seed))
    result = solver.solve(positions, wxyz, exact=args.exact, progress=sys.stderr.isatty())
    for i, problem in enumerate(problems):
        if problem:
            result.reason[i] = problem
    data = result.to_json()
    write_json(data, args.out)
    summary, timing = data["summary"], data["timing"]
    print(f"{robot.name}: {summary['targets']} targets, "
          f"{100 * summary['success_rate']:.1f} % success, mean pose error "
          f"{_fmt(summary['mean_pose_error_success'])} (successes), max violation "
          f"{_fmt(summary['max_violation'])}; {timing['total']:.2f} s "
          f"(compile {timing['compile']:.2f} s)", file=sys.stderr)
    return 0


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3g}"


# ---------------------------------------------------------------- entry point

SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [_add_fk, _add_ik]


def _add_show(sub: argparse._SubParsersAction) -> None:
    from .world_cli import add_show_parser

    add_show_parser(sub)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    from .bench.follow import add_bench_follow
    from .bench.ik import add_bench_ik
    from .bench.plan import add_bench_plan
    from .world_cli import add_bench_clearance

    p = sub.add_parser("bench", help="benchmarks that print tables (not tests)")
    group = p.add_subparsers(dest="benchmark", required=True)
    add_bench_ik(group)
    add_bench_plan(group)
    add_bench_clearance(group)
    add_bench_follow(group)


def _add_plan(sub: argparse._SubParsersAction) -> None:
    from .tasks.trajectory_cli import add_plan_parser

    add_plan_parser(sub)


def _add_demo(sub: argparse._SubParsersAction) -> None:
    from .demo import add_demo_parser

    add_demo_parser(sub)


def _add_follow(sub: argparse._SubParsersAction) -> None:
    from .tasks.follow_cli import add_follow_parser

    add_follow_parser(sub)


SUBCOMMANDS += [_add_plan, _add_follow, _add_show, _add_bench, _add_demo]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cr-nlp",
        description="IK, trajectory planning and path following for tendon-driven continuum "
                    "robots (batched JAX search and refinement, exact CasADi/Ipopt polish).")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in SUBCOMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from ._jax_setup import enable_compilation_cache, use_host_devices

    args = build_parser().parse_args(argv)
    use_host_devices()  # both cores for the batched stages (before JAX starts)
    enable_compilation_cache()
    try:
        return args.run(args)
    except (UsageError, ModelFileError) as exc:
        print(f"cr-nlp {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
