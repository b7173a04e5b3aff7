"""``cr-nlp ik``: inverse kinematics for a batch of target poses (thin front end)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from . import _tension_ik as tension_ik
from ._io import (
    UsageError,
    add_model_margin_option,
    add_time_limit_option,
    fmt,
    load_robot_arg,
    load_scene_arg,
    model_margin,
    resolve,
    time_limit_arg,
    write_result,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp ik`` on the command's subparsers."""
    p = sub.add_parser("ik", help="inverse kinematics for a batch of target poses")
    p.add_argument("--robot", required=True, help="robot JSON file or bundled name (tdcr3)")
    p.add_argument("--targets", required=True,
                   help='JSON file {"poses": [{"position": [x,y,z], "wxyz": [w,x,y,z]}, ...]} '
                        "or bundled name (tdcr3_lattice)")
    p.add_argument("--scene", help="scene JSON file or bundled name (obstacles)")
    p.add_argument("--exact", action="store_true",
                   help="polish every answer with Ipopt, constraints as hard constraints")
    add_time_limit_option(p)
    p.add_argument("--seed", type=int, default=0, help="seed of the search (default 0)")
    p.add_argument("--out", required=True, help="RESULT.json to write ('-' for stdout)")
    p.add_argument("--csv", help="also write the motor commands (a robot file with an "
                                 "actuation block): target, then one column per tendon, m")
    p.add_argument("--model", choices=("pcc", "cosserat"), default="pcc",
                   help="pcc (default): configurations of the constant-curvature model; "
                        "cosserat: tendon tensions on the Cosserat-rod model (robot files "
                        "with a mechanics block), written to --out and --csv")
    tension_ik.add_options(p, pool=True)
    add_model_margin_option(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Solve, write RESULT.json and print a one-line summary on stderr."""
    from ..tasks.geometry.ik import IKConfig, IKSolver
    from ..tasks.readers import read_targets

    time_limit = time_limit_arg(args)
    robot = load_robot_arg(args.robot)
    if args.model == "cosserat":
        return tension_ik.run(args, robot)
    scene = load_scene_arg(args.scene)
    try:
        positions, wxyz, problems = read_targets(resolve(args.targets, "targets", "--targets"))
    except ValueError as exc:
        raise UsageError(f"--targets: {exc}") from None
    config = IKConfig(seed=args.seed, polish_time_limit=time_limit)
    config = replace(config, safety_margin=config.safety_margin
                     + model_margin(robot, args.model_margin))
    solver = IKSolver(robot, scene, config)
    result = solver.solve(positions, wxyz, exact=args.exact, progress=sys.stderr.isatty())
    for i, problem in enumerate(problems):
        if problem:
            result.reason[i] = problem
    write_result(result, args.out)
    if args.csv:
        _write_commands(args.csv, robot, result.tendon_displacements)
    summary, timing = result.summary(), result.timing
    print(f"{robot.name}: {summary['targets']} targets, "
          f"{100 * summary['success_rate']:.1f} % success, mean pose error "
          f"{fmt(summary['mean_pose_error_success'])} (successes), max violation "
          f"{fmt(summary['max_violation'])}; {timing['total']:.2f} s "
          f"(compile {timing['compile']:.2f} s)", file=sys.stderr)
    return 0


def _write_commands(path: str, robot: object, displacements: object) -> None:
    """One row per target: ``target`` then the tendon displacements (m) by tendon name."""
    import csv

    from .._files import atomic_open
    from ..model.routing import tendon_names

    if displacements is None:
        raise UsageError(f"--csv: {robot.name} has no actuation block (no calibrated zero); "
                         f"calibrate it with cr-nlp calibrate")
    with atomic_open(path, newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["target", *tendon_names(robot)])
        for i, row in enumerate(displacements):
            writer.writerow([i, *(f"{v:.9f}" for v in row)])
