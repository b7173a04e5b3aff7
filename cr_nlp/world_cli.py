"""The ``cr-nlp show`` and ``cr-nlp bench clearance`` subcommands (registered by ``cli.py``)."""

from __future__ import annotations

import argparse

from .model.robot import load_robot

# ---------------------------------------------------------------- show

def add_show_parser(sub: argparse._SubParsersAction) -> None:
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
    p.set_defaults(run=_run_show)


def _run_show(args: argparse.Namespace) -> int:
    import numpy as np

    from .cli import UsageError, parse_numbers
    from .viz import save_figure
    from .world.check import check
    from .world.scene import load_scene

    robot = load_robot(args.robot)
    if args.q is None:
        q = np.array([v for s in robot.segments for v in (0.0, 0.0, s.length_min)])
    else:
        try:
            q = robot.full_q(parse_numbers(args.q, "--q"))
        except ValueError as exc:
            raise UsageError(f"--q: {exc}") from None
    scene = load_scene(args.scene) if args.scene else None
    path = save_figure(robot, q, scene, path=args.out, tendons=args.tendons,
                       show_parts=args.parts, title=args.title, elev=args.elev, azim=args.azim)
    print(f"wrote {path}")
    if scene is not None:
        verdict = check(robot, scene, q)
        state = "COLLISION" if verdict.collision else "collision-free"
        print(f"{state}: min distance {verdict.min_distance:.4f} m to {verdict.closest or '-'} "
              f"(python-fcl)")
    return 0


# ---------------------------------------------------------------- bench clearance

def add_bench_clearance(sub: argparse._SubParsersAction) -> None:
    """``cr-nlp bench clearance [--robot R] [--scene S …] [--configs N] [--dtype D …]``."""
    p = sub.add_parser("clearance",
                       help="benchmark batched clearance (configurations per second)")
    p.add_argument("--robot", default="tdcr3", help="robot JSON file or bundled name")
    p.add_argument("--scene", nargs="+", default=["lattice"],
                   help="scene files or bundled names (default: lattice)")
    p.add_argument("--configs", type=int, default=100_000, help="batch size")
    p.add_argument("--dtype", nargs="+", default=["float32"], choices=["float32", "float64"])
    p.add_argument("--repeats", type=int, default=7, help="timed runs (median reported)")
    p.add_argument("--devices", type=int, default=None,
                   help="host devices to shard the batch over (default: one per core)")
    p.set_defaults(run=_run_bench_clearance)


def _run_bench_clearance(args: argparse.Namespace) -> int:
    from ._jax_setup import use_host_devices
    from .bench.clearance import main

    if not use_host_devices(args.devices):
        print("# note: JAX had already started; running on its existing devices")
    return main(robot=args.robot, scenes=tuple(args.scene), configs=args.configs,
                dtypes=tuple(args.dtype), repeats=args.repeats)
