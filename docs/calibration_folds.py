"""The train-only fold score of a calibration (docs/design.md §1b, docs/benchmarks.md).

Five folds on the FTDCR v6 training file, each leaving out one family of patterns (pair12,
pair13, pair23, single tendons, single segments): calibrate on the other four families,
then the mean tip error (mm) on the family left out. The score is the mean of the five.
Model changes are chosen by this score; the validation file is not read.

    python docs/calibration_folds.py [--axial-compression [segments|tendons]]
                                     [--families pair12,tendon] [--history]

Each fold is one ``cr-nlp calibrate`` fit (~35 s on 2 cores). ``--history``: the same folds
score the history-aware models (``tasks.calibration.history``: none, play1, play2, play3), each fold's
static model calibrated on its own training rows (``cr-nlp calibrate --history auto`` keeps
the static model fitted on all training rows instead, to stay within its time budget).
"""

from __future__ import annotations

import argparse
import csv

import numpy as np

from cr_nlp._resources import models_root
from cr_nlp.model import load_robot
from cr_nlp.tasks.calibration.calibrate import CalibrationConfig, calibrate, tip_errors
from cr_nlp.tasks.calibration.measurements import Measurements
from cr_nlp.tasks.readers import read_measurements

FAMILIES = ("pair12", "pair13", "pair23", "tendon", "seg")
"""The training file's pattern families, as named in its ``pattern_label`` column."""


def family_of(label: str) -> str:
    """The family of a pattern label such as ``rep1_pair12_opp_dir0`` (→ ``pair12``)."""
    for name in FAMILIES:
        if f"_{name}" in label:
            return name
    raise ValueError(f"pattern {label!r} belongs to no family of {FAMILIES}")


def family_labels(robot_name: str = "ftdcr_v6") -> np.ndarray:
    """(rows,) the family of each row of the bundled training file."""
    path = models_root() / "data" / robot_name / f"{robot_name}_train.csv"
    with open(path) as f:
        return np.array([family_of(row["pattern_label"]) for row in csv.DictReader(f)])


def history_fold_errors(config: CalibrationConfig, robot_name: str = "ftdcr_v6") -> dict:
    """The held-out errors (m) per model and family, each fold's static model refitted."""
    from cr_nlp.tasks.calibration.history import fold_errors as history_folds

    robot = load_robot(robot_name)
    path = models_root() / "data" / robot_name / f"{robot_name}_train.csv"
    data = read_measurements(path, robot.n_tendons, units="mm", time_column="timestamp")

    def static(rows: np.ndarray):
        kept = Measurements(data.commands[rows], data.tip[rows], str(path))
        return calibrate(robot, kept, None, config).robot

    report = history_folds(static, data, family_labels(robot_name))
    for name, errors in report.errors.items():
        print(f"{name}: " + "  ".join(f"{f} {1e3 * e:.2f}" for f, e in
                                      zip(report.families, errors, strict=True))
              + f"  score {1e3 * report.score(name):.2f} mm", flush=True)
    return report.to_dict()


def fold_errors(config: CalibrationConfig, families: tuple[str, ...] = FAMILIES,
                robot_name: str = "ftdcr_v6") -> dict[str, float]:
    """Mean tip error (mm) on each held-out family of the bundled training file."""
    robot = load_robot(robot_name)
    path = models_root() / "data" / robot_name / f"{robot_name}_train.csv"
    data = read_measurements(path, robot.n_tendons, units="mm")
    with open(path) as f:
        family = np.array([family_of(row["pattern_label"]) for row in csv.DictReader(f)])
    out = {}
    for name in families:
        keep, left_out = family != name, family == name
        fit = calibrate(robot, Measurements(data.commands[keep], data.tip[keep], str(path)),
                        None, config)
        held_out = Measurements(data.commands[left_out], data.tip[left_out], str(path))
        out[name] = 1e3 * float(tip_errors(fit.robot, held_out).mean())
        print(f"{name}: {out[name]:.2f} mm held out ({1e3 * fit.train.mean:.2f} mm on the "
              f"{keep.sum()} fitted rows, {fit.seconds:.0f} s)", flush=True)
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--axial-compression", nargs="?", const="segments",
                        choices=("segments", "tendons"),
                        help="fit the axial compliance (as cr-nlp calibrate's option)")
    parser.add_argument("--families", default=",".join(FAMILIES),
                        help="comma-separated families to hold out (default: all five)")
    parser.add_argument("--history", action="store_true",
                        help="score the history-aware models (each fold refits the static)")
    args = parser.parse_args()
    config = CalibrationConfig(axial_compression=args.axial_compression is not None,
                               axial_shortens_segments=args.axial_compression != "tendons")
    if args.history:
        history_fold_errors(config)
        raise SystemExit(0)
    errors = fold_errors(config, tuple(args.families.split(",")))
    print(f"score (mean of the held-out families): {np.mean(list(errors.values())):.2f} mm")
