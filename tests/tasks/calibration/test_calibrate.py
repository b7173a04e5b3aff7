"""Calibration recovers a synthetic robot with known offsets, slack, axial compliance and base
pose from noisy samples of its own model, and its held-out error falls to the noise level."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cr_nlp.model import load_robot
from cr_nlp.model.actuation import Actuation, predict_tip
from cr_nlp.model.rotations import wxyz_from_matrix
from cr_nlp.tasks.calibration.calibrate import (
    CalibrationConfig,
    ErrorStats,
    Repeatability,
    calibrate,
    tip_errors,
)
from cr_nlp.tasks.calibration.measurements import Measurements

NOISE = 2e-4  # m per coordinate


def _truth(axial: str):
    nominal = load_robot("ftdcr_v6")
    rng = np.random.default_rng(7)
    yaw, tilt = 2.0, 0.03  # the measurement frame is turned by ~115° and tilted
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ np.array(
        [[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    act = Actuation(
        zero_offsets=tuple(rng.uniform(-0.8e-3, 0.2e-3, 9)),   # mostly slack at zero
        gains=tuple(rng.uniform(0.9, 1.1, 9)),
        tendon_angle_deltas=tuple(rng.uniform(-0.04, 0.04, 9)),
        segment_stiffness=(1.0, 0.8, 0.5),
        tendon_stiffness_ratio=(8.0, 5.0, 4.0),
        axial_stiffness_ratio=(40.0, 15.0, 80.0) if axial else (),
        axial_shortens_segments=axial != "tendons",
        tip_marker=(0.0, 0.0, 0.008),
    )
    truth = dataclasses.replace(
        nominal, actuation=act, base_position=(0.012, -0.02, 0.005),
        base_wxyz=tuple(wxyz_from_matrix(rot)),
        tendons=dataclasses.replace(nominal.tendons, offsets=(0.05, 0.55, 1.0)))
    return nominal, truth


def _sample(robot, rows: int, seed: int) -> Measurements:
    rng = np.random.default_rng(seed)
    # Antagonistic bends per segment (pull one side, release the other) plus single pulls.
    cmd = rng.uniform(-4e-3, 4e-3, (rows, 9))
    cmd[rows // 2:] = np.where(rng.random((rows - rows // 2, 9)) < 0.3, cmd[rows // 2:], -6e-3)
    tip = predict_tip(robot, cmd) + rng.normal(0.0, NOISE, (rows, 3))
    return Measurements(cmd, tip, f"synthetic-{seed}")


@pytest.mark.parametrize("axial", [
    "",                                             # incompressible
    pytest.param("segments", marks=pytest.mark.slow),  # a second full fit (~40 s)
    pytest.param("tendons", marks=pytest.mark.slow),   # take-up only, arcs keep lengths
])
def test_calibration_recovers_a_synthetic_robot(axial: str) -> None:
    nominal, truth = _truth(axial)
    train, held_out = _sample(truth, 240, 1), _sample(truth, 80, 2)
    result = calibrate(nominal, train, held_out,
                       CalibrationConfig(noise=NOISE, axial_compression=bool(axial),
                                         axial_shortens_segments=axial != "tendons"))
    noise_mean = NOISE * np.sqrt(8 / np.pi)            # mean length of a 3-D normal vector
    assert result.nominal_train.mean > 20 * noise_mean  # the nominal robot is far off
    assert result.validation.mean < 1.3 * noise_mean, result.report()
    # Noise-free predictions on the held-out commands agree to a fraction of the noise.
    exact = dataclasses.replace(held_out, tip=predict_tip(truth, held_out.commands))
    assert tip_errors(result.robot, exact).mean() < 0.5 * noise_mean
    fit, act, true_act = result.robot, result.robot.actuation, truth.actuation
    np.testing.assert_allclose(fit.base_position, truth.base_position, atol=1e-3)
    # ~1.6° or better; ~2.3° with axial compliance (1.7° here: it trades a little with the
    # base tilt)
    assert abs(abs(np.dot(fit.base_wxyz, truth.base_wxyz)) - 1.0) < (2e-4 if axial else 1e-4)
    # Gains and radius enter as gain / radius: compare that, and the zero offsets of the
    # tendons the data pulled taut.
    np.testing.assert_allclose(np.array(act.gains) / fit.tendons.radius,
                               np.array(true_act.gains) / truth.tendons.radius, rtol=0.05)
    np.testing.assert_allclose(act.zero_offsets, true_act.zero_offsets, atol=2e-4)
    np.testing.assert_allclose(act.tip_marker, true_act.tip_marker, atol=2e-3)
    if axial == "segments":  # the axial stiffness ratios, from a start of 30 for each
        np.testing.assert_allclose(act.axial_stiffness_ratio, true_act.axial_stiffness_ratio,
                                   rtol=0.2)
    if axial == "tendons":
        # Without shorter arcs only the take-up shows, ∝ 1/a: the stiff short segment 3
        # (a = 80) comes out at ~61, 0.004 in 1/a against 0.067 for segment 2.
        np.testing.assert_allclose(1.0 / np.array(act.axial_stiffness_ratio),
                                   1.0 / np.array(true_act.axial_stiffness_ratio),
                                   atol=0.1 / min(true_act.axial_stiffness_ratio))
    if axial:
        assert act.axial_shortens_segments == (axial == "segments")
    else:
        assert not act.axial_stiffness_ratio
    assert fit.actuation.model_error_p95 == result.validation.p95


def test_repeatability_pairs_rows_with_the_same_commands_by_hand() -> None:
    """Rows within the tolerance on every tendon pair up; their tip gaps are the
    distances between the measured tips (computed here by hand)."""
    base = np.linspace(-2e-3, 2e-3, 9)
    step = np.eye(9)[4]
    commands = np.array([base, base + 3e-5 * step, base + 9e-5 * step, base + 1e-3])
    tips = np.array([[0.0, 0.0, 0.2], [0.004, 0.0, 0.2], [0.0, 0.010, 0.2], [0.1, 0.1, 0.1]])
    data = Measurements(commands, tips, "hand")
    one = Repeatability.of(data, 5e-5)            # rows 0-1 only (row 2 is 9e-5 away)
    np.testing.assert_allclose(one.gaps, [0.004])
    assert one.rows == 2
    three = Repeatability.of(data, 1e-4)          # rows 0-1, 0-2, 1-2
    np.testing.assert_allclose(np.sort(three.gaps),
                               np.sort([0.004, 0.010, np.hypot(0.004, 0.010)]))
    assert three.rows == 3
    summary = three.to_dict()
    assert summary["pairs"] == 3 and summary["tolerance_mm"] == pytest.approx(0.1)
    assert summary["tip_gap_mm"]["max"] == pytest.approx(1e3 * np.hypot(0.004, 0.010))
    assert Repeatability.of(data, 1e-6).to_dict()["tip_gap_mm"] is None


def test_error_stats_by_hand() -> None:
    """Mean, RMSE and the offset-aligned RMSE of hand-made residuals (closed forms)."""
    residuals = np.array([[0.003, 0.004, 0.0], [0.0, 0.0, 0.0], [0.003, 0.0, 0.0],
                          [0.003, -0.004, 0.0]])                       # norms 5, 0, 3, 5 mm
    stats = ErrorStats.of(residuals, 0.2)
    assert stats.rows == 4 and stats.mean == pytest.approx(0.00325)
    assert stats.rmse == pytest.approx(np.sqrt((25 + 0 + 9 + 25) / 4) * 1e-3)
    # the mean vector (2.25, 0, 0) mm removed: x residuals 0.75, -2.25, 0.75, 0.75 mm
    aligned = np.sqrt((3 * 0.75 ** 2 + 2.25 ** 2 + 16 + 16) / 4) * 1e-3
    assert stats.rmse_aligned == pytest.approx(aligned)
    d = stats.to_dict()
    assert d["mm"]["rmse_aligned"] == pytest.approx(1e3 * aligned)
    assert d["percent_of_length"]["max"] == pytest.approx(100 * 0.005 / 0.2)
