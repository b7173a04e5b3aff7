"""``cr-nlp view``: the interactive 3-D viewer in the browser (viser) for a robot, a scene
and a result of ``cr-nlp ik``, ``plan`` or ``follow``; live IK by dragging a target (with
``--model cosserat``: tendon tensions on the Cosserat rod under the load options)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ._io import Stopped, UsageError, load_robot_arg, load_scene_arg, resolve, stop_on_signals
from ._loads import add_load_options, loads_from_args, needs_mechanics

if TYPE_CHECKING:
    from ..viz.viewer import Viewer


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp view`` on the command's subparsers."""
    p = sub.add_parser(
        "view",
        help="interactive 3-D viewer in the browser (needs viser: pip install 'cr_nlp[viewer]')",
    )
    p.add_argument("--robot", required=True, help="robot JSON file or bundled name (tdcr3)")
    p.add_argument("--scene", help="scene JSON file or bundled name (shelf, lattice, …)")
    p.add_argument("--result", help="RESULT.json of cr-nlp ik, plan or follow to replay")
    p.add_argument(
        "--targets",
        help="the ik result's targets file or bundled name, to draw "
        "the target frames beside the reached ones",
    )
    p.add_argument(
        "--path",
        help="a follow result's reference path (file or bundled name), "
        "when the result's path name is not a bundled one",
    )
    p.add_argument("--port", type=int, help="TCP port (default: a free one)")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1, this machine only)",
    )
    p.add_argument(
        "--no-live-ik",
        action="store_true",
        help="no target gizmo (live IK compiles a solver in the background)",
    )
    p.add_argument(
        "--model",
        choices=("pcc", "cosserat"),
        default="pcc",
        help="live IK on the PCC model (default) or for tendon tensions on the Cosserat rod "
        "(a robot with a mechanics block, no --result): drag the target under the loads",
    )
    add_load_options(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Serve the viewer, print its address and wait for SIGINT (Ctrl-C) or SIGTERM, also
    when the shell started this with SIGINT ignored; then stop the server and exit 0."""
    with stop_on_signals():
        try:
            viewer = _start(args)
        except Stopped as stopped:
            print(f"cr-nlp view: stopped by {stopped.name} while starting", file=sys.stderr)
            return 128 + stopped.signum
        try:
            print(f"cr-nlp view: {viewer.url}  (Ctrl-C stops)", flush=True)
            viewer.wait()  # returns on the signal, the server stopped
        except KeyboardInterrupt:  # before wait() took over, or a second signal in it
            # (a live-IK compile still in progress is then joined at exit)
            viewer.stop()
    return 0


def _start(args: argparse.Namespace) -> Viewer:
    """The ``Viewer`` of ``args``, serving."""
    try:
        from ..viz.viewer import Viewer, targets_of
    except ImportError as exc:
        raise UsageError(str(exc)) from None

    robot = load_robot_arg(args.robot)
    scene = load_scene_arg(args.scene)
    if args.result and not Path(args.result).is_file():
        raise UsageError(f"--result: file not found: {args.result}")
    loads = None
    if args.model == "cosserat":
        needs_mechanics(robot)
        if args.result:
            raise UsageError("--model cosserat: the viewer shows the rod's live IK, not a --result")
        loads = loads_from_args(args, sum(s.length_min for s in robot.segments), robot)
    targets = None
    if args.targets:
        try:
            targets = targets_of(resolve(args.targets, "targets", "--targets"))
        except ValueError as exc:
            raise UsageError(f"--targets: {exc}") from None
    try:
        return Viewer(
            robot,
            scene,
            args.result,
            port=args.port,
            host=args.host,
            targets=targets,
            path=resolve(args.path, "paths", "--path") if args.path else None,
            live_ik=not args.no_live_ik,
            model=args.model,
            loads=loads,
        )
    except ValueError as exc:
        raise UsageError(f"--result: {exc}") from None
    except OSError as exc:
        raise UsageError(f"--port: cannot listen on {args.host}:{args.port}: {exc}") from None
