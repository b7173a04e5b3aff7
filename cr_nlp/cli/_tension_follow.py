"""``cr-nlp follow --model cosserat``: tendon tensions that make the tip of the
Cosserat-rod model trace a path under loads (``tasks.mechanics.follow``)."""

from __future__ import annotations

import argparse
import sys

from ._io import (
    UsageError,
    load_scene_arg,
    model_margin,
    resolve,
    time_limit_arg,
    write_path_result,
)
from ._loads import loads_from_args, needs_mechanics


def add_options(p: argparse.ArgumentParser) -> None:
    """The options ``cr-nlp follow`` takes for ``--model cosserat``."""
    p.add_argument("--tension-rate-max", type=float,
                   help="--model cosserat: the largest tension rate of any tendon, N/s "
                        "(default 50)")


def run(args: argparse.Namespace, robot: object) -> int:
    """Follow in tension space (with ``--exact``, Ipopt polishes a motion the verdict
    rejects, ``--time-limit`` seconds), write RESULT.json (kind ``tension_follow``) and, with
    ``--csv``, the time series; print a one-line summary on stderr."""
    from dataclasses import replace

    from ..tasks.mechanics.follow import TensionFollowConfig, TensionPathFollower
    from ..tasks.readers import load_path

    needs_mechanics(robot)
    time_limit = time_limit_arg(args)
    config = TensionFollowConfig()
    config = replace(config, safety_margin=config.safety_margin
                     + model_margin(robot, args.model_margin),
                     ik=replace(config.ik, seed=args.seed))
    if args.tension_rate_max is not None:
        if not args.tension_rate_max > 0:
            raise UsageError(f"--tension-rate-max must be positive N/s, got "
                             f"{args.tension_rate_max}")
        config = replace(config, tension_rate_max=args.tension_rate_max)
    path = load_path(resolve(args.path, "paths", "--path"))
    follower = TensionPathFollower(robot, load_scene_arg(args.scene), config)
    loads = loads_from_args(args, follower.ik.length, robot)
    try:
        result = follower.follow(path, dt=args.dt, orientation=args.orientation, **loads,
                                 exact=args.exact, time_limit=time_limit)
    except ValueError as exc:
        raise UsageError(f"--path: {exc}") from None
    write_path_result(result, args.out, args.csv)
    s = result.summary()
    print(f"{robot.name} (Cosserat) on {path.name}: {s['reached']}/{s['waypoints']} waypoints "
          f"reached, position error max {s['max_position_error_mm']:.3g} mm, success "
          f"{result.success}{'' if result.success else ' (' + result.reason + ')'}; "
          f"{result.timing.total:.2f} s", file=sys.stderr)
    return 0
