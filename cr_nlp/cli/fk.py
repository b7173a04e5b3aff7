"""``cr-nlp fk``: tip pose, tendon lengths and backbone of one or more configurations."""

from __future__ import annotations

import argparse

from ._io import configurations_from_args, load_robot_arg, write_json


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp fk`` on the command's subparsers."""
    p = sub.add_parser("fk", help="forward kinematics: tip pose, tendon lengths, backbone")
    p.add_argument("--robot", required=True, help="robot JSON file or bundled name (tdcr3)")
    p.add_argument("--q", help="θ1,φ1,L1,... (rad, rad, m); fixed lengths may be omitted")
    p.add_argument("--q-file", help='JSON file {"q": [[...], ...]}')
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Print the forward kinematics as text, or as JSON with ``--json``."""
    import numpy as np

    from ..model import backbone_points, tendon_lengths, tip_pose
    from ..model.rotations import wxyz_from_matrix
    from ..model.routing import routing_of

    robot = load_robot_arg(args.robot)
    routing = routing_of(robot)
    qs = configurations_from_args(robot, args.q, args.q_file)
    # numpy in: the model evaluates in float64 numpy (no float32 JAX noise in the output).
    pos, rot = tip_pose(robot, qs)
    lengths = tendon_lengths(robot, qs)
    points = backbone_points(robot, qs)
    records = [
        {"position": pos[i].tolist(), "wxyz": wxyz_from_matrix(rot[i]).tolist(),
         "tendon_lengths": lengths[i].tolist(), "backbone": points[i].tolist()}
        for i in range(len(qs))
    ]
    if args.json:
        write_json(records[0] if args.q is not None else records, None)
        return 0
    for i, rec in enumerate(records):
        if len(records) > 1:
            print(f"# configuration {i}: q = {np.round(qs[i], 6).tolist()}")
        print(f"robot          {robot.name} ({robot.n_segments} segments, "
              f"{robot.tendons.routing} routing)")
        # 12 decimals: the float64 evaluation is good to ~1e-15 m (JSON has every digit).
        print("tip position   [{:.12f}, {:.12f}, {:.12f}] m".format(*rec["position"]))
        print("tip wxyz       [{:.12f}, {:.12f}, {:.12f}, {:.12f}]".format(*rec["wxyz"]))
        for segment in np.unique(routing.anchor):   # one row per segment tendons end at
            label = "tendons" if routing.shared else f"tendons seg {segment + 1}"
            lengths = np.asarray(rec["tendon_lengths"])[routing.anchor == segment]
            vals = ", ".join(f"{v:.12f}" for v in lengths)
            print(f"{label:<15}[{vals}] m")
    return 0
