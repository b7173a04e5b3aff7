"""``cr-nlp warmup``: compile a robot's programs ahead, into the cache (``cr_nlp.warmup``)."""

from __future__ import annotations

import argparse
import sys

from ..warmup import TASKS
from ._io import load_robot_arg, load_scene_arg


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp warmup`` on the command's subparsers."""
    p = sub.add_parser(
        "warmup", help="compile a robot's programs ahead into the cache (workers, CI, demos)",
        description="Solves small representative problems so that the programs later "
                    "processes need are traced and compiled into the cache "
                    "($CR_NLP_CACHE_DIR, default ~/.cache/cr_nlp). The IK programs serve "
                    "every robot of the same shape (segments, points per segment, tendon "
                    "layout, actuation and mechanics blocks; other lengths, limits, radii "
                    "and base pose); the planning and following programs, which take the "
                    "scene's broad-phase grid, those of a similar size too.")
    p.add_argument("--robot", required=True, help="robot JSON file or bundled name (tdcr3)")
    p.add_argument("--scene", help="scene JSON file or bundled name (planning needs one)")
    p.add_argument("--tasks", nargs="+", choices=TASKS, default=["ik", "plan", "follow"],
                   help="tasks to compile (default: ik plan follow)")
    p.add_argument("--exact", action="store_true",
                   help="also compile the exact stage's CasADi functions")
    p.add_argument("--waypoints", type=int, default=150,
                   help="waypoints of the paths you will follow (default 150)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Compile and print a table of what each task traced and loaded."""
    from ..warmup import format_rows, warm_up

    robot = load_robot_arg(args.robot)
    scene = load_scene_arg(args.scene)
    rows = warm_up(robot, scene, tuple(args.tasks), exact=args.exact,
                   waypoints=args.waypoints, progress=sys.stderr.isatty())
    print(format_rows(rows))
    return 0
