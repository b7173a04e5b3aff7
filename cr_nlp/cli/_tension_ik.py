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
    resolve,
    time_limit_arg,
    write_result,
)
from ._loads import add_load_options, loads_from_args, needs_mechanics


def add_options(p: argparse.ArgumentParser, pool: bool = False) -> None:
    """The options ``cr-nlp ik`` and ``follow`` take for ``--model cosserat`` (``pool``:
    also ``--pool-size``, for the IK commands)."""
    p.add_argument("--orientation", action="store_true",
                   help="--model cosserat: also reach the targets' wxyz (robots with the "
                        "freedom for it); default: positions only")
    if pool:
        p.add_argument("--pool-size", type=int,
                       help="--model cosserat: random tension sets whose tips seed the "
                            "search (default: TensionIKConfig.pool_size): one batch of forward "
                            "statics per robot and load case, kept in the cache folder; a "
                            "smaller pool starts faster under new loads and seeds fewer far "
                            "targets")
    add_load_options(p)


def pool_options(args: argparse.Namespace) -> dict[str, int]:
    """``TensionIKConfig`` keywords of ``--pool-size`` (none: the config's default).

    Raises:
        UsageError: a pool of fewer than 16 tension sets.
    """
    if args.pool_size is None:
        return {}
    if args.pool_size < 16:
        raise UsageError(f"--pool-size: must be at least 16, got {args.pool_size}")
    return {"pool_size": args.pool_size}


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
    config = TensionIKConfig(seed=args.seed, **pool_options(args))
    config = replace(config, safety_margin=config.safety_margin
                     + model_margin(robot, args.model_margin))
    solver = TensionIKSolver(robot, load_scene_arg(args.scene), config)
    loads = loads_from_args(args, solver.length, robot)
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
