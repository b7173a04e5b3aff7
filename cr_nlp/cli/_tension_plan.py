"""``cr-nlp plan --model cosserat``: tension trajectories from start to goal tensions on
the Cosserat-rod model under loads (``tasks.mechanics.trajectory``)."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from ._io import UsageError, load_scene_arg, model_margin, resolve, time_limit_arg
from ._loads import loads_from_args, needs_mechanics


def add_options(p: argparse.ArgumentParser) -> None:
    """The options ``cr-nlp plan`` takes for ``--model cosserat``."""
    p.add_argument("--dt", type=float,
                   help="--model cosserat: seconds between waypoints (default 0.05)")


def run(args: argparse.Namespace, robot: object) -> int:
    """Plan in tension space (with ``--exact``, Ipopt polishes the motions the verdict
    rejects, ``--time-limit`` seconds per problem), write RESULT.json (kind
    ``tension_trajectory``, one entry per problem) and, with ``--csv``, one time series per
    problem; print a summary."""
    from ..tasks.mechanics._motion_result import tension_trajectories_to_dict
    from ..tasks.mechanics.trajectory import TensionTrajectoryConfig, TensionTrajectoryPlanner
    from ..tasks.readers import read_tension_problems

    needs_mechanics(robot)
    time_limit = time_limit_arg(args)
    config = TensionTrajectoryConfig(seed=args.seed)
    config = replace(config, safety_margin=config.safety_margin
                     + model_margin(robot, args.model_margin))
    for name, value in (("dt", args.dt), ("tension_rate_max", args.tension_rate_max)):
        if value is not None:
            if not value > 0:
                raise UsageError(f"--{name.replace('_', '-')} must be positive, got {value}")
            config = replace(config, **{name: value})
    try:
        starts, goals = read_tension_problems(robot, resolve(args.problems, "problems",
                                                             "--problems"))
    except ValueError as exc:
        raise UsageError(f"--problems: {exc}") from None
    planner = TensionTrajectoryPlanner(robot, load_scene_arg(args.scene), config)
    loads = loads_from_args(args, planner.length, robot)
    results = planner.plan(starts, goals, **loads, exact=args.exact, time_limit=time_limit)
    data = tension_trajectories_to_dict(results, None, robot)
    if args.out == "-":
        print(json.dumps(data, indent=2))
    else:
        from ..tasks._result import write_json

        write_json(data, args.out)
    if args.csv:
        for i, result in enumerate(results):
            result.save_csv(Path(args.csv) / f"problem_{i}.csv")
    rate = sum(r.success for r in results) / max(len(results), 1)
    print(f"{robot.name} (Cosserat): {len(results)} problems, {100 * rate:.1f} % success; "
          f"{sum(r.timing.total for r in results):.2f} s", file=sys.stderr)
    return 0
