"""``cr-nlp plan``: trajectory planning from a PROBLEMS.json file (thin front end).

PROBLEMS.json (a file, or the bundled name ``tdcr3_shelf``)::

    {"problems": [{"start": [q...], "goal": [q...]}, ...],
     "horizon": 23,      # optional: intervals H (waypoints = H + 1)
     "dt": 0.35}         # optional: seconds between waypoints

q is ``[θ1, φ1, L1, …]`` (rad, rad, m); fixed lengths may be omitted (``Robot.full_q``).
A malformed problem (wrong length, outside the limits, start or goal in collision by
python-fcl) becomes a failed result with its reason, never a crash of the batch.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from . import _loads, _tension_follow, _tension_plan
from ._io import (
    add_model_margin_option,
    add_time_limit_option,
    load_robot_arg,
    load_scene_arg,
    model_margin,
    read_problems_arg,
    time_limit_arg,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp plan`` on the command's subparsers."""
    p = sub.add_parser("plan", help="trajectory planning between start/goal configurations")
    p.add_argument("--robot", required=True, help="robot JSON file or bundled name (tdcr3)")
    p.add_argument("--scene", help="scene JSON file or bundled scene name (obstacles)")
    p.add_argument("--problems", required=True,
                   help='JSON file {"problems": [{"start": [q], "goal": [q]}, ...], '
                        '"horizon": H (optional), "dt": seconds (optional)}, or bundled '
                        "name (tdcr3_shelf)")
    p.add_argument("--exact", action="store_true",
                   help="polish every trajectory with Ipopt, tendon limits and clearance "
                        "as hard constraints (stage 'polish'; the LM answer is kept, "
                        "marked, where the polish fails; --model cosserat: the motions "
                        "the verdict rejects, on the rod's equations)")
    add_time_limit_option(p)
    p.add_argument("--init", choices=("roadmap", "straight"), default="roadmap",
                   help="initial trajectories: roadmap path + straight + perturbed (default), "
                        "or straight + perturbed")
    p.add_argument("--seed", type=int, default=0, help="seed of the perturbed guesses")
    p.add_argument("--out", required=True, help="RESULT.json to write ('-' for stdout)")
    p.add_argument("--csv", help="directory for one tendon-length CSV per result "
                                 "(problem_<i>.csv: time_s, then one column per tendon, m; "
                                 "with a calibrated robot also <tendon>_displacement, m)")
    p.add_argument("--model", choices=("pcc", "cosserat"), default="pcc",
                   help="pcc (default): configurations of the constant-curvature model; "
                        "cosserat: tension trajectories on the Cosserat-rod model under "
                        'loads, problems {"problems": [{"start": [N…], "goal": [N…]}]} '
                        "(robot files with a mechanics block), result kind "
                        "tension_trajectory")
    _loads.add_load_options(p)
    _tension_follow.add_options(p)
    _tension_plan.add_options(p)
    add_model_margin_option(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Plan, write RESULT.json (and the CSVs) and print a one-line summary on stderr."""
    from ..tasks.geometry.trajectory import (
        TrajectoryConfig,
        TrajectoryPlanner,
        save_results,
        trajectories_to_dict,
    )

    time_limit = time_limit_arg(args)
    robot = load_robot_arg(args.robot)
    if args.model == "cosserat":
        return _tension_plan.run(args, robot)
    scene = load_scene_arg(args.scene)
    starts, goals, horizon, dt = read_problems_arg(args.problems)
    config = TrajectoryConfig(seed=args.seed)
    if horizon is not None:
        config = TrajectoryConfig(waypoints=horizon + 1, seed=args.seed)
    if dt is not None:
        config = TrajectoryConfig(waypoints=config.waypoints, dt=dt, seed=args.seed)
    from dataclasses import replace

    config = replace(config, safety_margin=config.safety_margin
                     + model_margin(robot, args.model_margin), polish_time_limit=time_limit)
    planner = TrajectoryPlanner(robot, scene, config)
    # None entries (a problem without "start"/"goal") fail validation with a reason.
    starts = [s if s is not None else [] for s in starts]
    goals = [g if g is not None else [] for g in goals]
    results = planner.plan(starts, goals, exact=args.exact, init=args.init,
                           progress=sys.stderr.isatty())
    timing = planner.last_timing
    if args.out == "-":  # several results: the one-file form of them all
        print(json.dumps(trajectories_to_dict(results, timing, robot), indent=2))
    else:
        save_results(results, args.out, timing, robot)
    if args.csv:
        folder = Path(args.csv)
        for i, result in enumerate(results):
            if result.q is not None:
                result.save_csv(folder / f"problem_{i}.csv")
    rate = sum(r.success for r in results) / max(len(results), 1)
    print(f"{robot.name}: {len(results)} problems, "
          f"{100 * rate:.1f} % success; {timing['total']:.2f} s "
          f"(compile {timing['compile']:.2f} s)", file=sys.stderr)
    return 0
