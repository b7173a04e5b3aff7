"""``cr-nlp calibrate``: fit a robot file to measured commands and tip positions."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import TYPE_CHECKING

from .._files import atomic_open
from ._io import UsageError, add_data_options, load_robot_arg, read_data_arg

if TYPE_CHECKING:
    from ..model import Robot
    from ..tasks.calibration.calibrate import ErrorStats
    from ..tasks.calibration.history import HistoryCalibration
    from ..tasks.calibration.measurements import Measurements

HISTORY_NAMES = ("play1", "play2", "play3")
"""The named history models (``tasks.calibration.history.VARIANTS``; here without importing JAX)."""


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
    p.add_argument("--model", choices=("pcc", "cosserat"), default="pcc",
                   help="pcc (default): the geometric actuation model; cosserat: fit a "
                        "mechanics block (segment stiffness ratios, tendon stiffness, zero "
                        "offsets, gains, gravity, base pose, marker) to the Cosserat rod "
                        "driven by the commands (slow: minutes)")
    p.add_argument("--start", choices=("pcc", "pcc-geometry", "nominal"), default="pcc",
                   help="with --model cosserat: start the base pose, marker, zeros and "
                        "gains from a geometric calibration of the same rows (default; "
                        "pcc-geometry also keeps its segment lengths, tendon radius and "
                        "segment angle offsets) or from the robot file")
    p.add_argument("--axial-compression", nargs="?", const="segments",
                   choices=("segments", "tendons"),
                   help="also fit the segments' axial compliance under the taut tendons: "
                        "'segments' (the default when given without a value) shortens the "
                        "segments, so plans' commands reproduce the tip only to ~1 mm; "
                        "'tendons' keeps their lengths and fits the tendons' take-up alone")
    p.add_argument("--history", default="none", choices=("none", "auto", *HISTORY_NAMES),
                   help="also fit a history-aware model (play operators on each tendon's "
                        "command, rows in time order): 'auto' picks none, play1, play2 or "
                        "play3 by leave-one-family-out folds of the training rows; default "
                        "none (the static model alone)")
    p.add_argument("--fold-column", default="pattern_label",
                   help="with --history auto: the column whose text names each row's "
                        "pattern family (default pattern_label; without it, 5 blocks of "
                        "rows in time order)")
    p.add_argument("--fold-pattern",
                   help="a regular expression whose first group, found in --fold-column, "
                        "is the family (e.g. '_(tendon|seg|pair\\d\\d)' for ftdcr_v6)")
    add_data_options(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Fit, write the calibrated robot file (and the report), print the errors."""
    from ..tasks.calibration.calibrate import CalibrationConfig, calibrate

    robot = load_robot_arg(args.robot)
    train = read_data_arg(robot, args.data, args)
    val = read_data_arg(robot, args.validate, args) if args.validate else None
    if args.model == "cosserat":
        return _run_mechanics(args, robot, train, val)
    result = calibrate(robot, train, val,
                       CalibrationConfig(
                           axial_compression=args.axial_compression is not None,
                           axial_shortens_segments=args.axial_compression != "tendons"))
    history = _fit_history(args, result.robot, train, val) if args.history != "none" else None
    calibrated = (history.robot if history else result.robot).to_dict()
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
        _print_row(label, stats)
    if history is not None:
        _print_history(history)
        report["history"] = history.report()
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
        written = write_report_figures(result.robot, train, val, folder)  # the static model
        print(f"report → {folder / 'report.json'}, " + ", ".join(p.name for p in written))
    return 0


def _print_row(label: str, stats: ErrorStats) -> None:
    d = stats.to_dict()
    mm = "".join(f"{d['mm'][k]:9.2f}"
                 for k in ("mean", "median", "p95", "max", "rmse", "rmse_aligned"))
    pct = " ".join(f"{d['percent_of_length'][k]:.1f}%" for k in ("mean", "p95"))
    print(f"{label:<16}{stats.rows:>6}{mm}   ({pct})")


def _fit_history(args: argparse.Namespace, static: Robot, train: Measurements,
                 val: Measurements | None) -> HistoryCalibration:
    """The history model of ``--history`` on the calibrated static robot
    (``tasks.calibration.history.calibrate_history``), folds by ``--fold-column`` /
    ``--fold-pattern``."""
    from ..tasks.calibration.history import calibrate_history, families_of, time_blocks
    from ..tasks.readers import read_labels

    labels = read_labels(train.source, args.fold_column) if args.history == "auto" else None
    try:
        families = (families_of(labels, args.fold_pattern) if labels is not None
                    else time_blocks(len(train)))
    except (ValueError, re.error) as exc:
        raise UsageError(f"--fold-pattern: {exc}") from None
    return calibrate_history(static, train, val, args.history, families)


def _print_history(history: HistoryCalibration) -> None:
    model = history.history
    if history.folds is not None:
        folds = history.folds
        scores = "  ".join(f"{name} {1e3 * folds.score(name):.2f}" for name in folds.errors)
        print(f"history folds (leave one of {', '.join(folds.families)} out; held-out mean "
              f"mm): {scores} → {folds.chosen} ({folds.seconds:.0f} s)")
    if model is None:
        print("history: none (the static model alone is saved)")
        return
    widths = ", ".join(f"{1e3 * w:.3g}" for w in model.widths)
    print(f"history: {len(model.widths)} play operators per tendon, widths {widths} mm "
          f"({history.seconds:.0f} s)")
    _print_row("history (train)", history.train)
    if history.validation is not None:
        _print_row("history (valid.)", history.validation)


def _run_mechanics(args: argparse.Namespace, robot: Robot, train: Measurements,
                   val: Measurements | None) -> int:
    """``--model cosserat``: fit the mechanics model, write the robot file and the report."""
    from ..tasks.calibration.mechanics import MechanicsCalibrationConfig, calibrate_mechanics

    if args.axial_compression is not None or args.history != "none":
        raise UsageError("--model cosserat: --axial-compression and --history belong to the "
                         "geometric model")
    try:
        result = calibrate_mechanics(robot, train, val,
                                     MechanicsCalibrationConfig(
                                         start=args.start.split("-")[0], progress=True,
                                         pcc_geometry=args.start == "pcc-geometry"))
    except ValueError as exc:
        raise UsageError(f"--model cosserat: {exc}") from None
    calibrated = result.robot.to_dict()
    calibrated["description"] = (f"{robot.name} calibrated by cr-nlp calibrate --model "
                                 f"cosserat on {Path(train.source).name} ({len(train)} rows; "
                                 "validation error in actuation.model_error_*; gravity of "
                                 "the recording in mechanics.calibration_gravity)")
    with atomic_open(args.out) as handle:
        handle.write(json.dumps(calibrated, indent=2) + "\n")
    report = result.report()
    report["train_file"], report["validation_file"] = train.source, val.source if val else None
    print(f"calibrated the Cosserat model of {robot.name} on {len(train)} rows in "
          f"{result.seconds:.1f} s ({result.evaluations} evaluations, {result.status}) → "
          f"{args.out}")
    print(f"{'rows':<16}{'n':>6}{'mean':>9}{'median':>9}{'p95':>9}{'max':>9}{'rmse':>9}"
          f"{'aligned':>9}   (mm; % of length)")
    for label, stats in (("start (train)", result.nominal_train), ("train", result.train),
                         ("validation", result.validation)):
        if stats is not None:
            _print_row(label, stats)
    if result.unconverged:
        print(f"{result.unconverged} rows did not converge (left out of the errors' fit)")
    mech = result.robot.mechanics
    gravity = ",".join(f"{v:.4g}" for v in mech.calibration_gravity)
    take_up = ", ".join(f"{1e6 * v:.3g}" for v in mech.take_up(result.robot.n_segments))
    print(f"segment stiffness {', '.join(f'{v:.3g}' for v in mech.segment_stiffness)}; "
          f"tendon stiffness {', '.join(f'{v:.4g}' for v in mech.tendon_stiffness)} N/m; "
          f"take-up {take_up} µm/N; "
          f"gravity of the recording {gravity} m/s² (pass --gravity {gravity} to statics, "
          f"ik, plan and follow --model cosserat)")
    if args.report:
        from ..model.cosserat import predict_marker
        from ..viz._calibration import write_report_figures

        folder = Path(args.report)
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_open(folder / "report.json") as handle:
            handle.write(json.dumps(report, indent=2) + "\n")
        written = write_report_figures(result.robot, train, val, folder,
                                       lambda c: predict_marker(result.robot, c)[0])
        print(f"report → {folder / 'report.json'}, " + ", ".join(p.name for p in written))
    return 0
