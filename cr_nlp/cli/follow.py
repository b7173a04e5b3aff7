"""``cr-nlp follow``: path following from a path file (thin front end).

PATH.json is the ``tasks.paths`` format (``{"poses": [{"position": [x, y, z], "wxyz":
[w, x, y, z]}, ...], "dt": seconds}``) or a bundled path name ("square", "sine",
"icra"). RESULT.json (``FollowResult.to_dict``, kind "follow") holds one row per
waypoint: ``q``, ``position``, ``pose_error``, ``position_error`` (m),
``rotation_error`` (rad), ``reached``, ``tendon_lengths``, and the verdict
``collision_free``, ``min_clearance`` (m), ``max_violation``, ``timing`` (s).
Waypoints the robot cannot reach are reported per waypoint (``reached`` false), never a
crash; a malformed file is a usage error (exit status 2).
"""

from __future__ import annotations

import argparse
import sys

from . import _tension_follow, _tension_ik
from ._io import (
    UsageError,
    add_model_margin_option,
    add_time_limit_option,
    load_robot_arg,
    load_scene_arg,
    model_margin,
    resolve,
    time_limit_arg,
    write_path_result,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp follow`` on the command's subparsers."""
    p = sub.add_parser("follow", help="path following: the tip traces a reference path")
    p.add_argument("--robot", required=True, help="robot JSON file or bundled robot name")
    p.add_argument("--path", required=True,
                   help='path JSON file {"poses": [{"position": [x,y,z], "wxyz": [w,x,y,z]}, '
                        '...], "dt": seconds}, or a bundled shape: square, sine, icra')
    p.add_argument("--scene", help="scene JSON file or bundled scene name (obstacles)")
    p.add_argument("--exact", action="store_true",
                   help="polish with Ipopt, the constraints as constraints (falls back to "
                        "the LM answer, marked in 'stage', if the polish fails; --model "
                        "cosserat: a motion the verdict rejects, on the rod's equations)")
    add_time_limit_option(p)
    p.add_argument("--dt", type=float, help="seconds between waypoints (default: the file's)")
    p.add_argument("--seed", type=int, default=0, help="seed of the IK stage (default 0)")
    p.add_argument("--out", required=True,
                   help="RESULT.json to write ('-' for stdout); a .npz suffix writes numpy "
                        "arrays, a .csv suffix the tendon-length series")
    p.add_argument("--csv", help="also write the tendon-length series (time_s, one column per "
                                 "tendon, m; with a calibrated robot also "
                                 "<tendon>_displacement, m) to this CSV file")
    p.add_argument("--model", choices=("pcc", "cosserat"), default="pcc",
                   help="pcc (default): configurations of the constant-curvature model; "
                        "cosserat: tendon tensions on the Cosserat-rod model under loads "
                        "(robot files with a mechanics block), result kind tension_follow")
    _tension_ik.add_options(p)
    _tension_follow.add_options(p)
    add_model_margin_option(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Follow the path, write RESULT and print a one-line summary on stderr."""
    import math

    from ..tasks.geometry.follow import FollowConfig, PathFollower
    from ..tasks.readers import load_path

    time_limit = time_limit_arg(args)
    robot = load_robot_arg(args.robot)
    if args.model == "cosserat":
        return _tension_follow.run(args, robot)
    scene = load_scene_arg(args.scene)
    path = load_path(resolve(args.path, "paths", "--path"))
    if args.dt is not None and not (math.isfinite(args.dt) and args.dt > 0):
        raise UsageError(f"--dt must be a positive number of seconds, got {args.dt}")
    follower = PathFollower(robot, scene, FollowConfig(
        seed=args.seed, safety_margin=FollowConfig.safety_margin
        + model_margin(robot, args.model_margin), polish_time_limit=time_limit))
    try:
        result = follower.follow(path, exact=args.exact, progress=sys.stderr.isatty(),
                                 dt=args.dt)
    except ValueError as exc:
        raise UsageError(f"--path: {exc}") from None
    write_path_result(result, args.out, args.csv)
    s, timing = result.summary(), result.timing
    print(f"{robot.name} on {path.name}: {s['reached']}/{s['waypoints']} waypoints reached, "
          f"position error mean {s['mean_position_error_mm']:.3g} mm (max "
          f"{s['max_position_error_mm']:.3g}), rotation error mean "
          f"{s['mean_rotation_error_deg']:.3g}° (max {s['max_rotation_error_deg']:.3g}), "
          f"collision-free {result.collision_free}, max violation "
          f"{result.max_violation:.3g}, stage {result.stage_text}; {timing['total']:.2f} s "
          f"(compile {timing['compile']:.2f} s)", file=sys.stderr)
    return 0
