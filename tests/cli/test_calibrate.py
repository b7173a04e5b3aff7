"""`cr-nlp calibrate` and `cr-nlp predict` as a user runs them, and the errors of bad data
files (naming file, column and row)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from cr_nlp.cli import main
from cr_nlp.model import load_robot
from cr_nlp.model.actuation import predict_tip
from cr_nlp.tasks.calibration.measurements import DataFileError
from cr_nlp.tasks.readers import read_measurements

HEADER = ["t"] + [f"tendon_{i}" for i in range(1, 10)] + ["tip_x", "tip_y", "tip_z"]


def _write(path: Path, rows: list[list], header: list[str] = HEADER) -> Path:
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)
    return path


def _rows(n: int, seed: int = 0) -> list[list]:
    rng = np.random.default_rng(seed)
    cmd = rng.uniform(-3.0, 3.0, (n, 9))                         # mm
    tip = 1e3 * predict_tip(load_robot("ftdcr_v6"), cmd * 1e-3)  # mm
    return [[k, *c, *p] for k, (c, p) in enumerate(zip(cmd, tip, strict=True))]


@pytest.mark.parametrize("edit, message", [
    (lambda rows, header: (rows, header[:5] + header[6:]),
     r"bad\.csv: tendon column 'tendon_5' not found"),
    (lambda rows, header: ([r if k != 2 else r[:10] + ["nan"] + r[11:]
                            for k, r in enumerate(rows)], header),
     r"bad\.csv: column 'tip_x', row 3: 'nan' is not a finite number"),
    (lambda rows, header: ([r if k != 1 else r[:3] + [1, 5] + r[4:]
                            for k, r in enumerate(rows)], header),
     r"bad\.csv: row 2 has 14 cells, the header has 13"),
    (lambda rows, header: ([r if k != 0 else r[:4] + ["x"] + r[5:]
                            for k, r in enumerate(rows)], header),
     r"bad\.csv: column 'tendon_4', row 1: not a number: 'x'"),
])
def test_bad_data_files_name_file_column_and_row(tmp_path, edit, message) -> None:
    rows, header = edit(_rows(4), list(HEADER))
    path = _write(tmp_path / "bad.csv", rows, header)
    with pytest.raises(DataFileError, match=message):
        read_measurements(path, 9, units="mm")


def test_wrong_tendon_count_and_cli_errors(tmp_path, capsys) -> None:
    path = _write(tmp_path / "d.csv", _rows(3))
    with pytest.raises(DataFileError, match=r"d\.csv: 8 tendon columns given .* 9 tendons"):
        read_measurements(path, 9, tendon_columns=[f"tendon_{i}" for i in range(1, 9)])
    status = main(["predict", "--robot", "ftdcr_v6", "--data", str(path), "--out",
                   str(tmp_path / "p.csv"), "--tendon-columns", "tendon_1,tendon_2"])
    assert status == 2
    assert "d.csv: 2 tendon columns given" in capsys.readouterr().err
    status = main(["calibrate", "--robot", "ftdcr_v6", "--data", str(tmp_path / "none.csv"),
                   "--out", str(tmp_path / "c.json")])
    assert status == 2
    assert "none.csv: file not found, and not a bundled recording" in capsys.readouterr().err


def test_predict_writes_the_model_tip_in_the_data_units(tmp_path, capsys) -> None:
    rows = _rows(20, seed=3)
    commands_only = [r[:10] for r in rows]
    path = _write(tmp_path / "cmd.csv", commands_only, HEADER[:10])
    out = tmp_path / "pred.csv"
    assert main(["predict", "--robot", "ftdcr_v6", "--data", str(path), "--out", str(out),
                 "--units", "mm"]) == 0
    pred = np.loadtxt(out, delimiter=",", skiprows=1)
    np.testing.assert_allclose(pred[:, 1:], np.array([r[10:] for r in rows]), atol=1e-9)
    # With the measured tips present, predict also prints the tip error (here zero).
    assert main(["predict", "--robot", "ftdcr_v6", "--data", str(_write(tmp_path / "d.csv",
                 rows)), "--out", str(out), "--units", "mm"]) == 0
    assert "tip error mm: mean 0.00" in capsys.readouterr().out


@pytest.mark.slow  # a second full fit (~15 s on a quiet 2-core CPU); test_calibrate has one
def test_calibrate_writes_a_robot_file_every_command_accepts(tmp_path, capsys) -> None:
    train = _write(tmp_path / "train.csv", _rows(60, seed=5))
    val = _write(tmp_path / "val.csv", _rows(20, seed=6))
    out, report = tmp_path / "cal.json", tmp_path / "report"
    assert main(["calibrate", "--robot", "ftdcr_v6", "--data", str(train), "--validate",
                 str(val), "--units", "mm", "--out", str(out), "--report", str(report)]) == 0
    text = capsys.readouterr().out
    assert "validation" in text
    calibrated = json.loads(out.read_text())
    assert "actuation" in calibrated and calibrated["actuation"]["model_error_p95"] < 1e-4
    summary = json.loads((report / "report.json").read_text())
    assert summary["validation"]["mm"]["mean"] < 0.1       # the data came from this model
    assert summary["validation"]["mm"]["rmse_aligned"] <= summary["validation"]["mm"]["rmse"]
    assert summary["repeatability"]["tolerance_mm"] == pytest.approx(0.05)
    assert summary["zero_sensitivity_mm_per_mm"]["median"] > 1.0
    assert "zero sensitivity: the tip moves" in text
    assert (report / "errors.png").stat().st_size > 0
    assert (report / "tip_paths.png").stat().st_size > 0
    assert main(["fk", "--robot", str(out), "--q", "0.1,0,0.1,0,0,0", "--json"]) == 0


@pytest.mark.parametrize("option, fitted, shortens", [
    ([], False, True),
    (["--axial-compression"], True, True),
    (["--axial-compression", "segments"], True, True),
    (["--axial-compression", "tendons"], True, False),
])
def test_axial_compression_option_reaches_the_fit(tmp_path, monkeypatch, option, fitted,
                                                  shortens) -> None:
    import cr_nlp.tasks.calibration.calibrate as calibrate_module

    class Stop(Exception):
        pass

    def fake_calibrate(robot, train, val, config):
        raise Stop(config)

    monkeypatch.setattr(calibrate_module, "calibrate", fake_calibrate)
    train = _write(tmp_path / "train.csv", _rows(5))
    with pytest.raises(Stop) as stop:
        main(["calibrate", "--robot", "ftdcr_v6", "--data", str(train), "--units", "mm",
              "--out", str(tmp_path / "cal.json"), *option])
    config = stop.value.args[0]
    assert (config.axial_compression, config.axial_shortens_segments) == (fitted, shortens)
    with pytest.raises(SystemExit):
        main(["calibrate", "--robot", "ftdcr_v6", "--data", str(train), "--units", "mm",
              "--out", str(tmp_path / "cal.json"), "--axial-compression", "squash"])
