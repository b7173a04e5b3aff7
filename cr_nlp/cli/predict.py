"""``cr-nlp predict``: predicted tip positions for rows of commanded tendon displacements."""

from __future__ import annotations

import argparse

from ._io import add_data_options, load_robot_arg, read_data_arg


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp predict`` on the command's subparsers."""
    p = sub.add_parser("predict", help="tip positions predicted from tendon commands (CSV)")
    p.add_argument("--robot", required=True,
                   help="robot JSON file (calibrated: its actuation block) or bundled name")
    p.add_argument("--data", required=True, help="CSV with the commands (tip columns optional)")
    p.add_argument("--out", required=True, help="PRED.csv: pred_x, pred_y, pred_z per row")
    add_data_options(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Write the predicted tip of every row (measurement frame, the data's units); print the
    tip error summary when the file has measured tips."""
    import numpy as np

    from ..model.actuation import predict_tip
    from ..tasks.measurements import write_tip_csv

    robot = load_robot_arg(args.robot)
    data = read_data_arg(robot, args.data, args, require_tip=False)
    tip = predict_tip(robot, data.commands)
    write_tip_csv(args.out, tip, args.units, ("pred_x", "pred_y", "pred_z"),
                  {"row": np.arange(1, len(tip) + 1)})
    print(f"{len(tip)} rows predicted → {args.out} ({args.units})")
    if data.tip is not None:
        err = np.linalg.norm(tip - data.tip, axis=1) * 1e3
        print(f"tip error mm: mean {err.mean():.2f}  median {np.median(err):.2f}  "
              f"p95 {np.percentile(err, 95):.2f}  max {err.max():.2f}")
    return 0
