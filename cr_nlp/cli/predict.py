"""``cr-nlp predict``: predicted tip positions for rows of commanded tendon displacements, or
(``--compensate``) the motor commands that make the history-aware model follow a plan."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from ._io import UsageError, add_data_options, load_robot_arg, read_data_arg

if TYPE_CHECKING:
    import numpy as np

    from ..model import Robot


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp predict`` on the command's subparsers."""
    p = sub.add_parser("predict", help="tip positions predicted from tendon commands (CSV)")
    p.add_argument("--robot", required=True,
                   help="robot JSON file (calibrated: its actuation block) or bundled name")
    p.add_argument("--data", help="CSV with the commands (tip columns optional)")
    p.add_argument("--out", required=True,
                   help="PRED.csv: pred_x, pred_y, pred_z per row (with --compensate: the "
                        "command series)")
    p.add_argument("--history", choices=("auto", "none"), default="auto",
                   help="auto (default): the robot file's actuation.history model where it "
                        "has one, rows taken as a time series (--time-column); none: the "
                        "static model, each row on its own")
    p.add_argument("--model", choices=("pcc", "cosserat"), default="pcc",
                   help="pcc (default): the geometric actuation model; cosserat: the "
                        "Cosserat rod driven by the commands (a robot file with a mechanics "
                        "block, e.g. from calibrate --model cosserat; under its "
                        "calibration_gravity)")
    p.add_argument("--compensate", metavar="RESULT.json",
                   help="instead of --data: a plan, follow or IK result (its configurations "
                        "in order); writes the compensated and uncompensated motor commands "
                        "with the predicted tip error of both (needs actuation.history)")
    add_data_options(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Write the predicted tip of every row (measurement frame, the data's units); print the
    tip error summary when the file has measured tips."""
    import numpy as np

    from ..model.history import history_of, predict_tip_series
    from ..tasks.calibration.measurements import write_tip_csv

    if (args.data is None) == (args.compensate is None):
        raise UsageError("give exactly one of --data (commands to predict) or --compensate "
                         "(a result to make commands for)")
    robot = load_robot_arg(args.robot)
    if args.compensate is not None:
        return _compensate(robot, args)
    if history_of(robot) is None or args.model == "cosserat":
        args.history = "none"      # a static robot file reads and predicts as before
    data = read_data_arg(robot, args.data, args, require_tip=False)
    if args.model == "cosserat":
        tip = _predict_mechanics(robot, data.commands)
    else:
        tip = predict_tip_series(robot, data.commands, history=args.history != "none")
    write_tip_csv(args.out, tip, args.units, ("pred_x", "pred_y", "pred_z"),
                  {"row": np.arange(1, len(tip) + 1)})
    print(f"{len(tip)} rows predicted → {args.out} ({args.units})")
    if data.tip is not None:
        err = np.linalg.norm(tip - data.tip, axis=1) * 1e3
        print(f"tip error mm: mean {err.mean():.2f}  median {np.median(err):.2f}  "
              f"p95 {np.percentile(err, 95):.2f}  max {err.max():.2f}")
    return 0


def _compensate(robot: Robot, args: argparse.Namespace) -> int:
    """``--compensate``: the command series of a result's configurations, compensated and
    not, to ``--out`` (CSV, the data's units) with each one's predicted tip error (mm)."""
    import csv

    import numpy as np

    from .._files import atomic_open
    from ..tasks._result import ResultFileError, load_results
    from ..tasks.calibration.history import compensate_plan
    from ..tasks.calibration.measurements import UNITS

    if args.history == "none":
        raise UsageError("--compensate needs the history-aware model (not --history none)")
    try:
        results = load_results(args.compensate, robot)
        plan = compensate_plan(robot, np.vstack([r.q for r in results]))
    except (ResultFileError, ValueError) as exc:
        raise UsageError(f"--compensate: {exc}") from None
    scale = 1.0 / UNITS[args.units]
    n = robot.n_tendons
    header = (["step"] + [f"tendon_{j + 1}" for j in range(n)]
              + [f"uncompensated_{j + 1}" for j in range(n)]
              + ["tip_error_compensated_mm", "tip_error_uncompensated_mm"])
    with atomic_open(args.out, newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        for t in range(len(plan.compensated)):
            writer.writerow([t + 1, *(repr(float(v)) for v in plan.compensated[t] * scale),
                             *(repr(float(v)) for v in plan.uncompensated[t] * scale),
                             repr(1e3 * float(plan.error_compensated[t])),
                             repr(1e3 * float(plan.error_uncompensated[t]))])
    for label, err in (("uncompensated", plan.error_uncompensated),
                       ("compensated", plan.error_compensated)):
        mm = 1e3 * err
        print(f"{label:<14} commands: predicted tip error mean {mm.mean():.3f} mm, "
              f"max {mm.max():.3f} mm")
    print(f"{len(plan.compensated)} steps → {args.out} (tendon_* compensated, "
          f"uncompensated_* static; {args.units})")
    return 0


def _predict_mechanics(robot: Robot, commands: np.ndarray) -> np.ndarray:
    """The Cosserat rod's predicted points of the commands; unconverged rows are named."""
    import numpy as np

    from ..model.cosserat import predict_marker

    try:
        tip, converged = predict_marker(robot, commands)
    except ValueError as exc:
        raise UsageError(f"--model cosserat: {exc}") from None
    if not converged.all():
        rows = ", ".join(str(i + 1) for i in np.flatnonzero(~converged)[:10])
        print(f"{int((~converged).sum())} rows did not converge (rows {rows}…)")
    return tip
