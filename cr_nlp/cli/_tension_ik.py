"""``cr-nlp ik --model cosserat``: tendon tensions for target tip positions on the
Cosserat-rod model (tension-space IK, ``tasks.mechanics.ik``)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

import numpy as np

from ._io import (
    UsageError,
    fmt,
    load_scene_arg,
    model_margin,
    parse_vector3,
    point_loads_arg,
    read_json,
    resolve,
    time_limit_arg,
    write_result,
)


def add_options(p: argparse.ArgumentParser) -> None:
    """The options ``cr-nlp ik`` and ``follow`` take for ``--model cosserat``."""
    p.add_argument("--orientation", action="store_true",
                   help="--model cosserat: also reach the targets' wxyz (robots with the "
                        "freedom for it); default: positions only")
    add_load_options(p)


def add_load_options(p: argparse.ArgumentParser) -> None:
    """The load options of ``--model cosserat`` (those of ``cr-nlp statics``)."""
    p.add_argument("--tip-force", help="--model cosserat: fx,fy,fz force on the tip, N, "
                                       "world frame")
    p.add_argument("--tip-moment", help="--model cosserat: mx,my,mz moment on the tip, N·m")
    p.add_argument("--gravity", help="--model cosserat: gx,gy,gz gravity, m/s², world frame")
    p.add_argument("--distributed-force", help="--model cosserat: wx,wy,wz force per metre "
                                               "along the backbone, N/m, world frame")
    p.add_argument("--point-load", action="append", metavar="S,FX,FY,FZ[,MX,MY,MZ]",
                   help="--model cosserat: a wrench at arc length S (m from the base), N and "
                        "N·m, world frame; repeat for more")
    p.add_argument("--loads", metavar="LOADS.json",
                   help="--model cosserat: the loads as a file, {\"gravity\": [m/s²], "
                        "\"tip_force\": [N], \"tip_moment\": [N·m], \"distributed_force\": "
                        "[N/m], \"point_loads\": [{\"s\": m, \"force\": [N], \"moment\": "
                        "[N·m]}]} (any of them; not also given as an option)")


def loads_from_args(args: argparse.Namespace, length: float) -> dict:
    """The load options and the ``--loads`` file as keyword arguments of the tension
    solvers (N, N·m, m/s², N/m), checked against the robot's ``length`` (m).

    Raises:
        UsageError: naming the option, or the file and the key.
    """
    from ..model.loads import LOAD_KEYS, static_loads

    loads = {"tip_force": parse_vector3(args.tip_force, "--tip-force"),
             "tip_moment": parse_vector3(args.tip_moment, "--tip-moment"),
             "gravity": parse_vector3(args.gravity, "--gravity"),
             "distributed_force": parse_vector3(args.distributed_force, "--distributed-force"),
             "point_loads": point_loads_arg(args.point_load)}
    where = "the load options"
    if getattr(args, "loads", None):
        where = f"--loads: {args.loads}"
        data = read_json(args.loads, "--loads")
        if not isinstance(data, dict):
            raise UsageError(f"{where}: expected an object with any of {', '.join(LOAD_KEYS)}")
        for key, value in data.items():
            if key not in LOAD_KEYS:
                raise UsageError(f"{where}: {key}: unknown key (a loads file has "
                                 f"{', '.join(LOAD_KEYS)})")
            if loads[key]:
                raise UsageError(f"{where}: {key} is also given as --{key.replace('_', '-')}")
            loads[key] = value
    try:
        static_loads(1, length, **loads)
    except ValueError as exc:
        raise UsageError(f"{where}: {str(exc).removeprefix('case 0: ')}") from None
    return loads


def needs_mechanics(robot: object) -> None:
    """Refuse ``--model cosserat`` for a robot without mechanics (every tension task, ik,
    plan and follow, has its exact stage on the rod: ``--exact`` is not refused)."""
    if getattr(robot, "mechanics", None) is None:
        raise UsageError(f"--model cosserat: {robot.name} has no 'mechanics' block (the rod's "
                         f"stiffness and tension limit); see models/README.md")


def run(args: argparse.Namespace, robot: object) -> int:
    """Solve in tension space, write RESULT.json (kind ``tension_ik``) and, with ``--csv``,
    the tensions; print a one-line summary on stderr."""
    from ..tasks.mechanics.ik import TensionIKConfig, TensionIKSolver
    from ..tasks.readers import read_targets

    needs_mechanics(robot)
    time_limit = time_limit_arg(args)
    try:
        positions, wxyz, problems = read_targets(resolve(args.targets, "targets", "--targets"))
    except ValueError as exc:
        raise UsageError(f"--targets: {exc}") from None
    config = TensionIKConfig(seed=args.seed)
    config = replace(config, safety_margin=config.safety_margin
                     + model_margin(robot, args.model_margin))
    solver = TensionIKSolver(robot, load_scene_arg(args.scene), config)
    loads = loads_from_args(args, solver.length)
    try:
        result = solver.solve(positions, wxyz if args.orientation else None, **loads,
                              exact=args.exact, time_limit=time_limit)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    for i, problem in enumerate(problems):
        if problem:
            result.reason[i] = problem
    write_result(result, args.out)
    if args.csv:
        result.save_csv(args.csv)
    summary = result.summary()
    errors = result.position_error[result.success]
    print(f"{robot.name} (Cosserat): {summary['targets']} targets, "
          f"{100 * summary['success_rate']:.1f} % success, median position error "
          f"{fmt(float(np.median(errors)) if errors.size else None)} m (successes); "
          f"{result.timing.total:.2f} s", file=sys.stderr)
    return 0
