"""``cr-nlp show``: draw the robot (and a scene) to an image file, with the python-fcl
verdict."""

from __future__ import annotations

import argparse

from ._io import UsageError, load_robot_arg, load_scene_arg, parse_numbers


def add_parser(sub: argparse._SubParsersAction) -> None:
    """``cr-nlp show --robot R [--scene S] [--q θ1,φ1,L1,…] --out fig.png``."""
    p = sub.add_parser("show", help="draw the robot (and a scene) to an image file")
    p.add_argument("--robot", required=True, help="robot JSON file or bundled name (tdcr3)")
    p.add_argument("--scene", help="scene JSON file or bundled name (lattice, shelf, cabinet, …)")
    p.add_argument("--q", help="θ1,φ1,L1,... (rad, rad, m); fixed lengths may be omitted; "
                              "default: straight")
    p.add_argument("--out", required=True, help="image file to write (PNG by suffix)")
    p.add_argument("--tendons", action="store_true", help="draw the tendons")
    p.add_argument("--parts", action="store_true",
                   help="draw the convex parts of mesh obstacles instead of the meshes")
    p.add_argument("--title", help="figure title")
    p.add_argument("--elev", type=float, default=20.0, help="camera elevation, degrees")
    p.add_argument("--azim", type=float, default=-135.0, help="camera azimuth, degrees")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Save the figure and print the python-fcl verdict when a scene is given."""
    import numpy as np

    from ..viz import save_figure
    from ..world.check import check

    robot = load_robot_arg(args.robot)
    if args.q is None:
        q = np.array([v for s in robot.segments for v in (0.0, 0.0, s.length_min)])
    else:
        try:
            q = robot.full_q(parse_numbers(args.q, "--q"))
        except ValueError as exc:
            raise UsageError(f"--q: {exc}") from None
    scene = load_scene_arg(args.scene)
    path = save_figure(robot, q, scene, path=args.out, tendons=args.tendons,
                       show_parts=args.parts, title=args.title, elev=args.elev, azim=args.azim)
    print(f"wrote {path}")
    if scene is not None:
        verdict = check(robot, scene, q)
        state = "COLLISION" if verdict.collision else "collision-free"
        print(f"{state}: min distance {verdict.min_distance:.4f} m to {verdict.closest or '-'} "
              f"(python-fcl)")
    return 0
