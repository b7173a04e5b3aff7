"""Benchmark: the train-only fold score of a calibration (docs/design.md §1b).

``cr-nlp bench calibration`` holds out each family of patterns of a robot's bundled
training recording in turn (FTDCR v6: pair12, pair13, pair23, single tendons, single
segments), calibrates on the other families and measures the mean tip error on the family
left out; the score is the mean over the families. Model changes are chosen by this score;
the validation file is never read. With ``history``, the same folds score the
history-aware models (none, play1, play2, play3), each fold's static model calibrated on
its own rows. With ``model="cosserat"`` each fold is a ``cr-nlp calibrate --model cosserat``
fit of the Cosserat rod driven by the commands (~10 min on 2 cores; the geometric fit of
the same rows is its start). Each geometric fold is one ``cr-nlp calibrate`` fit (~35 s on
2 cores). Errors in mm.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path
from typing import Any

import numpy as np

from .._resources import models_root
from ..model import Robot, load_robot
from ..tasks.calibration.calibrate import CalibrationConfig, calibrate, tip_errors
from ..tasks.calibration.measurements import Measurements
from ..tasks.readers import read_measurements
from ._common import Column, environment, environment_markdown, fixed, markdown_table, write_report
from .suites import CALIBRATION_FAMILIES

FAMILIES = CALIBRATION_FAMILIES


def family_of(label: str, families: tuple[str, ...] = FAMILIES) -> str:
    """The family of a pattern label such as ``rep1_pair12_opp_dir0`` (→ ``pair12``).

    Raises:
        ValueError: the label names none of ``families``.
    """
    for name in families:
        if f"_{name}" in label:
            return name
    raise ValueError(f"pattern {label!r} belongs to no family of {families}")


def training_file(robot_name: str) -> Path:
    """The bundled training recording of ``robot_name``."""
    return models_root() / "data" / robot_name / f"{robot_name}_train.csv"


def family_labels(robot_name: str = "ftdcr_v6") -> np.ndarray:
    """(rows,) the family of each data row of the bundled training recording."""
    with open(training_file(robot_name), newline="") as handle:
        return np.array([family_of(row["pattern_label"]) for row in csv.DictReader(handle)])


def _static_folds(robot: Robot, data: Measurements, family: np.ndarray,
                  families: tuple[str, ...], config: CalibrationConfig,
                  progress: bool, model: str = "pcc") -> list[dict[str, Any]]:
    rows = []
    for name in families:
        keep, left_out = family != name, family == name
        start = time.perf_counter()
        train = Measurements(data.commands[keep], data.tip[keep], data.source)
        held_out = Measurements(data.commands[left_out], data.tip[left_out], data.source)
        if model == "cosserat":
            from ..tasks.calibration.mechanics import calibrate_mechanics

            fit = calibrate_mechanics(robot, train, held_out)  # the fit never reads held_out
            held_out_mm = 1e3 * fit.validation.mean
        else:
            fit = calibrate(robot, train, None, config)
            held_out_mm = 1e3 * float(tip_errors(fit.robot, held_out).mean())
        rows.append({"model": "cosserat" if model == "cosserat" else "static",
                     "held_out": name, "fitted_rows": int(keep.sum()),
                     "held_out_rows": int(left_out.sum()),
                     "train_mm": 1e3 * fit.train.mean, "held_out_mm": held_out_mm,
                     "fit_s": time.perf_counter() - start})
        if progress:
            print(f"{name}: {rows[-1]['held_out_mm']:.2f} mm held out", flush=True)
    return rows


def _history_folds(robot: Robot, robot_name: str,
                   config: CalibrationConfig) -> list[dict[str, Any]]:
    from ..tasks.calibration.history import fold_errors

    path = training_file(robot_name)
    data = read_measurements(path, robot.n_tendons, units="mm", time_column="timestamp")

    def static(rows: np.ndarray) -> Robot:
        return calibrate(robot, Measurements(data.commands[rows], data.tip[rows], str(path)),
                         None, config).robot

    report = fold_errors(static, data, family_labels(robot_name))
    return [{"model": model, "held_out": family, "held_out_mm": 1e3 * error}
            for model, errors in report.errors.items()
            for family, error in zip(report.families, errors, strict=True)]


def run_calibration_benchmark(robot: str = "ftdcr_v6", families: tuple[str, ...] = FAMILIES,
                              axial_compression: str | None = None, history: bool = False,
                              out: str | Path | None = None, progress: bool = True,
                              model: str = "pcc") -> list[dict[str, Any]]:
    """The fold table (one row per model and held-out family, mm) and its score; writes
    ``calibration.md``, ``folds.csv`` and ``environment.json`` to ``out``.

    Args:
        robot: a bundled robot with a training recording whose rows carry a
            ``pattern_label`` (``models/data/<robot>/<robot>_train.csv``).
        families: the families to hold out, each in turn.
        axial_compression: fit the axial compliance, shortening "segments" or "tendons"
            (``cr-nlp calibrate --axial-compression``); None: not fitted.
        history: score the history-aware models instead of the static one (every family:
            the play operators run over all rows in time order).
        model: "pcc" (the geometric calibration) or "cosserat" (the rod driven by the
            commands, ``calibrate_mechanics`` with its defaults).

    Raises:
        ValueError: an unknown family, a subset of families with ``history``, or history
            or axial compression with ``model="cosserat"``.
    """
    unknown = sorted(set(families) - set(FAMILIES))
    if unknown:
        raise ValueError(f"unknown family {unknown[0]!r} (the families: {', '.join(FAMILIES)})")
    if history and set(families) != set(FAMILIES):
        raise ValueError("history folds hold out every family in turn; no subset")
    if model not in ("pcc", "cosserat"):
        raise ValueError(f"model: expected 'pcc' or 'cosserat', got {model!r}")
    if model == "cosserat" and (history or axial_compression):
        raise ValueError("model 'cosserat': no history or axial compression folds")
    config = CalibrationConfig(axial_compression=axial_compression is not None,
                               axial_shortens_segments=axial_compression != "tendons")
    model_kind, model = model, load_robot(robot)
    if history:
        rows = _history_folds(model, robot, config)
    else:
        data = read_measurements(training_file(robot), model.n_tendons, units="mm")
        rows = _static_folds(model, data, family_labels(robot), families, config, progress,
                             model_kind)
    scores = {name: float(np.mean([r["held_out_mm"] for r in rows if r["model"] == name]))
              for name in dict.fromkeys(r["model"] for r in rows)}
    columns = [Column("model", "model"), Column("held_out", "held out"),
               Column("held_out_mm", "held-out mean (mm)", fixed(2))]
    if not history:
        columns += [Column("fitted_rows", "fitted rows"), Column("train_mm", "train (mm)",
                                                                 fixed(2)),
                    Column("fit_s", "fit (s)", fixed(0))]
    score_lines = "\n".join(f"- {name}: score {score:.2f} mm (mean of the held-out families)"
                            for name, score in scores.items())
    env = environment()
    report = (f"# Calibration folds: {robot}\n\nEach family of the training recording held "
              f"out in turn; the validation file is not read. Model: {model_kind}; axial "
              f"compliance: {axial_compression or 'not fitted'}.\n\n"
              f"{markdown_table(rows, columns)}\n\n"
              f"{score_lines}\n\n{environment_markdown(env)}\n")
    write_report("calibration", report, out, {"folds": rows}, env,
                 {"robot": robot, "model": model_kind, "families": list(families),
                  "history": history,
                  "axial_compression": axial_compression, "scores": scores})
    return rows
