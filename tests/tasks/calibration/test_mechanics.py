"""Calibration of the mechanics model: a known mechanics block is recovered from its own
synthetic recording, and ``cr-nlp calibrate --model cosserat`` → ``predict --model
cosserat`` runs end to end on a small recording."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cr_nlp.cli.main import main
from cr_nlp.model import Robot, load_robot
from cr_nlp.model.actuation import Actuation
from cr_nlp.model.cosserat import predict_marker
from cr_nlp.tasks.calibration.calibrate import Prior
from cr_nlp.tasks.calibration.measurements import Measurements
from cr_nlp.tasks.calibration.mechanics import (
    MechanicsCalibrationConfig,
    _default_priors,
    calibrate_mechanics,
)

RAO = load_robot("tdcr2_rao2021")
MARKER = (0.0, 0.0, 0.01)
GRAVITY = (0.0, 0.0, -9.81)
NOMINAL = replace(RAO, mechanics=replace(RAO.mechanics, tendon_stiffness=(3000.0, 3000.0),
                                         calibration_gravity=GRAVITY),
                  actuation=replace(Actuation.nominal(6, 2), tip_marker=MARKER))
ZEROS = np.array([0.07, 0.27, -0.21, 0.27, -0.11, -0.05]) * 1e-3   # m
TRUTH = replace(NOMINAL, mechanics=replace(NOMINAL.mechanics, segment_stiffness=(1.0, 0.7),
                                           tendon_stiffness=(2000.0, 4000.0),
                                           tendon_take_up=(1.5e-4, 0.6e-4)),
                actuation=replace(NOMINAL.actuation, zero_offsets=tuple(ZEROS)))
NOISE = 2e-6  # m per axis


def _recording(rows: int, seed: int) -> Measurements:
    """Commands pulling 1–2 tendons of each segment by up to 4 mm (a third of the rows
    release tendons by up to 1 mm: only a tendon that goes slack shows the common part of
    its segment's zero offsets) and the true robot's measured points plus noise."""
    rng = np.random.default_rng(seed)
    d = np.zeros((rows, 6))
    for k in range(rows):
        for s in range(2):
            pulled = rng.choice(3, size=rng.integers(1, 3), replace=False)
            d[k, 3 * s + pulled] = rng.uniform(0, 0.004, len(pulled))
    d[: rows // 3] = rng.uniform(-0.001, 0.003, (rows // 3, 6))
    tip, converged = predict_marker(TRUTH, d)
    assert converged.all()
    return Measurements(d, tip + NOISE * rng.normal(size=tip.shape), f"synthetic{seed}")


@pytest.fixture(scope="module")
def recordings() -> tuple[Measurements, Measurements]:
    """A training and a held-out recording of the true robot (24 and 8 rows; both tests
    use them, so they run the same compiled programs)."""
    return _recording(24, 1), _recording(8, 2)


def test_a_known_mechanics_block_is_recovered_from_its_recording(recordings: tuple) -> None:
    train, held_out = recordings
    priors = _default_priors()
    for known in ("base_position", "base_rotvec", "marker", "gains", "gravity"):
        priors[known] = Prior(1.0, fit=False)
    result = calibrate_mechanics(NOMINAL, train, held_out, MechanicsCalibrationConfig(
        priors=priors, start="nominal", noise=NOISE, max_evaluations=40))
    mech = result.robot.mechanics
    assert mech.segment_stiffness[1] == pytest.approx(0.7, rel=0.02)
    np.testing.assert_allclose(mech.tendon_stiffness, [2000.0, 4000.0], rtol=0.02)
    np.testing.assert_allclose(mech.tendon_take_up, [1.5e-4, 0.6e-4], rtol=0.02)
    # zero offsets within 2 % of their spread (0.48 mm): 10 µm
    np.testing.assert_allclose(result.robot.actuation.zero_offsets, ZEROS, atol=1e-5)
    assert result.nominal_train.mean > 100 * NOISE
    # held-out rows at the noise level (the norm of 3 axes of 2 µm: about 3.5 µm); a row
    # whose tendons go slack where no training row's did errs more (the tip moves ~20 µm
    # per µm of zero error there): 17 µm mean, 0.11 mm at most when this was written
    held = result.validation
    assert held is not None and held.median < 2 * NOISE * np.sqrt(3)
    assert held.max < 0.3e-3 < 0.1 * result.nominal_train.mean
    assert result.unconverged == 0


def _write_csv(path: Path, data: Measurements) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow([f"tendon_{j + 1}" for j in range(6)] + ["tip_x", "tip_y", "tip_z"])
        for d, tip in zip(data.commands * 1e3, data.tip * 1e3, strict=True):
            writer.writerow([repr(float(v)) for v in (*d, *tip)])


def test_calibrate_cosserat_then_predict_end_to_end(recordings: tuple, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture) -> None:
    robot_file = tmp_path / "robot.json"
    robot_file.write_text(json.dumps(NOMINAL.to_dict()))
    _write_csv(tmp_path / "train.csv", recordings[0])
    _write_csv(tmp_path / "val.csv", recordings[1])
    out = tmp_path / "calibrated.json"
    assert main(["calibrate", "--robot", str(robot_file), "--data",
                 str(tmp_path / "train.csv"), "--validate", str(tmp_path / "val.csv"),
                 "--units", "mm", "--model", "cosserat", "--start", "nominal",
                 "--out", str(out), "--report", str(tmp_path / "report")]) == 0
    printed = capsys.readouterr().out
    assert "validation" in printed and "gravity of the recording" in printed
    calibrated = Robot.from_file(out)
    assert calibrated.mechanics.tendon_stiffness and calibrated.mechanics.segment_stiffness
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["model"] == "cosserat" and report["validation"]["rows"] == 8
    assert (tmp_path / "report" / "errors.png").exists()
    assert report["validation"]["mm"]["mean"] < report["nominal_train"]["mm"]["mean"]
    pred = tmp_path / "pred.csv"
    assert main(["predict", "--robot", str(out), "--data", str(tmp_path / "val.csv"),
                 "--units", "mm", "--model", "cosserat", "--out", str(pred)]) == 0
    mean = float(capsys.readouterr().out.split("mean ")[1].split()[0])
    assert mean == pytest.approx(report["validation"]["mm"]["mean"], abs=0.006)
    assert main(["calibrate", "--robot", str(robot_file), "--data",
                 str(tmp_path / "train.csv"), "--units", "mm", "--model", "cosserat",
                 "--history", "auto", "--out", str(tmp_path / "x.json")]) == 2
    assert "--history belong to the geometric model" in capsys.readouterr().err


def test_the_bundled_cosserat_fit_predicts_the_held_out_rows_at_its_stated_error() -> None:
    """``ftdcr_v6_cosserat`` (``calibrate --model cosserat`` on the bundled training rows):
    a fresh prediction of the 274 validation rows it never saw gives the error its file
    states, and beats the uncalibrated geometric model on them."""
    from cr_nlp._resources import resolve_data_file
    from cr_nlp.model.actuation import predict_tip
    from cr_nlp.tasks.readers import read_measurements

    robot = load_robot("ftdcr_v6_cosserat")
    val = read_measurements(resolve_data_file("ftdcr_v6_val"), robot.n_tendons, units="mm")
    marker, converged = predict_marker(robot, val.commands)
    assert converged.all()
    error = np.linalg.norm(marker - val.tip, axis=1)
    assert abs(error.mean() - robot.actuation.model_error_mean) < 2e-4   # m
    assert abs(np.percentile(error, 95) - robot.actuation.model_error_p95) < 5e-4
    nominal = np.linalg.norm(predict_tip(load_robot("ftdcr_v6"), val.commands) - val.tip, axis=1)
    assert error.mean() < 0.5 * nominal.mean()
