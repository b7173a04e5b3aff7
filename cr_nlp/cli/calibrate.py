"""``cr-nlp calibrate``: fit a robot file to measured commands and tip positions."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .._files import atomic_open
from ._io import add_data_options, load_robot_arg, read_data_arg


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp calibrate`` on the command's subparsers."""
    p = sub.add_parser("calibrate",
                       help="fit a robot file to measured tendon commands and tip positions")
    p.add_argument("--robot", required=True, help="robot JSON file or bundled name (nominal)")
    p.add_argument("--data", required=True,
                   help="TRAIN.csv (or a bundled recording, e.g. ftdcr_v6_train)")
    p.add_argument("--validate", help="VAL.csv: rows the fit never sees, for the errors")
    p.add_argument("--out", required=True, help="CALIBRATED.json: the fitted robot file")
    p.add_argument("--report", help="folder for report.json and the figures")
    p.add_argument("--axial-compression", nargs="?", const="segments",
                   choices=("segments", "tendons"),
                   help="also fit the segments' axial compliance under the taut tendons: "
                        "'segments' (the default when given without a value) shortens the "
                        "segments, so plans' commands reproduce the tip only to ~1 mm; "
                        "'tendons' keeps their lengths and fits the tendons' take-up alone")
    add_data_options(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Fit, write the calibrated robot file (and the report), print the errors."""
    from ..tasks.calibrate import CalibrationConfig, calibrate

    robot = load_robot_arg(args.robot)
    train = read_data_arg(robot, args.data, args)
    val = read_data_arg(robot, args.validate, args) if args.validate else None
    result = calibrate(robot, train, val,
                       CalibrationConfig(
                           axial_compression=args.axial_compression is not None,
                           axial_shortens_segments=args.axial_compression != "tendons"))
    calibrated = result.robot.to_dict()
    calibrated["description"] = (f"{robot.name} calibrated by cr-nlp calibrate on "
                                 f"{Path(train.source).name} ({len(train)} rows; "
                                 f"validation error in actuation.model_error_*)")
    with atomic_open(args.out) as handle:
        handle.write(json.dumps(calibrated, indent=2) + "\n")
    report = result.report()
    report["train_file"], report["validation_file"] = train.source, val.source if val else None
    print(f"calibrated {robot.name} on {len(train)} rows in {result.seconds:.1f} s "
          f"({result.evaluations} evaluations) → {args.out}")
    print(f"{'rows':<16}{'n':>6}{'mean':>9}{'median':>9}{'p95':>9}{'max':>9}{'rmse':>9}"
          f"{'aligned':>9}   (mm; % of length)")
    for label, stats in (("nominal (train)", result.nominal_train), ("train", result.train),
                         ("validation", result.validation)):
        if stats is None:
            continue
        d = stats.to_dict()
        mm = "".join(f"{d['mm'][k]:9.2f}"
                     for k in ("mean", "median", "p95", "max", "rmse", "rmse_aligned"))
        pct = " ".join(f"{d['percent_of_length'][k]:.1f}%" for k in ("mean", "p95"))
        print(f"{label:<16}{stats.rows:>6}{mm}   ({pct})")
    print("aligned: the RMSE after removing the rows' mean error vector (OpenCR-MuJoCo's "
          "metric)")
    sensitivity = report["zero_sensitivity_mm_per_mm"]["median"]
    print(f"zero sensitivity: the tip moves {sensitivity:.1f} mm per mm of tendon zero error "
          f"(median over the training rows)")
    repeat = report["repeatability"]
    if repeat["tip_gap_mm"]:
        gap, tol = repeat["tip_gap_mm"], repeat["tolerance_mm"]
        print(f"repeatability: {repeat['pairs']} pairs of rows whose commands agree within "
              f"{tol:g} mm (≤ {tol * sensitivity:.1f} mm of tip) reach tips {gap['mean']:.1f} mm "
              f"apart (mean; p95 {gap['p95']:.1f} mm): on one row of each pair any model of "
              f"the commands alone errs by about half that")
    if args.report:
        from ..viz._calibration import write_report_figures

        folder = Path(args.report)
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_open(folder / "report.json") as handle:
            handle.write(json.dumps(report, indent=2) + "\n")
        written = write_report_figures(result.robot, train, val, folder)
        print(f"report → {folder / 'report.json'}, " + ", ".join(p.name for p in written))
    return 0
