"""Stage 3 for trajectories: one Ipopt NLP over all waypoints, built once, constraints as
constraints (tendon speed/acceleration, bending, clearance at waypoints and check points),
every answer re-evaluated in float64."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from cr_nlp.model import CasadiModel, load_robot
from cr_nlp.stages.polish import _trajectory_nlp as module
from cr_nlp.stages.polish._trajectory_nlp import TrajectoryPolishConfig, TrajectoryPolisher
from cr_nlp.tasks.geometry.trajectory import tendon_series, verify_trajectory
from cr_nlp.world import load_scene

from ...conftest import MODELS

# Two bent tdcr3 configurations (θ, φ, L): the straight line between them in z needs
# 0.167 m/s of tendon speed at dt = 0.12 s over 9 intervals (the limit is 0.2 m/s).
Q_A = np.array([0.5, 0.3, 1.0, 0.6, 1.0, 1.0, 0.4, 2.0, 1.0])
Q_B = np.array([1.2, -0.5, 1.0, 0.9, 2.0, 1.0, 1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def tdcr3():
    return load_robot(MODELS / "robots" / "tdcr3.json")


@pytest.fixture(scope="module")
def path_polisher(tdcr3):
    return TrajectoryPolisher(tdcr3, None, 6)


@pytest.fixture(scope="module")
def tracking_polisher(tdcr3):
    return TrajectoryPolisher(tdcr3, None, 8, objective="tracking")


def straight(a, b, waypoints):
    """Waypoints evenly spaced on the straight line in (θ, φ, L) (not in z)."""
    s = np.linspace(0.0, 1.0, waypoints)[:, None]
    return a + s * (b - a)


def poses(robot, q):
    model = CasadiModel(robot)
    tips = [model.tip(row) for row in q]
    return np.stack([p for p, _ in tips]), np.stack([r for _, r in tips])


def test_path_polish_keeps_the_ends_and_meets_a_tendon_speed_limit(tdcr3, path_polisher):
    # φ interpolated linearly bends the line in z: a detour, too fast at this dt.
    q0 = straight(Q_A, Q_B, 6)
    dt = 0.25
    before = verify_trajectory(tdcr3, None, q0, dt)
    assert before.violations["tendon_speed"] > 0.01
    out = path_polisher.solve(q0, dt)
    assert out.success, out
    assert out.max_violation <= 1e-6
    np.testing.assert_allclose(out.q[0], Q_A, atol=1e-12)
    np.testing.assert_allclose(out.q[-1], Q_B, atol=1e-12)
    speed = np.abs(np.diff(tendon_series(tdcr3, out.q), axis=0)) / dt
    assert speed.max() <= tdcr3.tendon_speed_max + 1e-6
    verdict = verify_trajectory(tdcr3, None, out.q, dt)
    assert verdict.success, verdict.reason
    assert out.objective < 10.0 and out.iterations > 0 and out.seconds > 0.0


def test_the_nlp_is_built_once_over_solves_with_new_dt_and_warm_starts(tdcr3, monkeypatch):
    constructions = []
    real_nlpsol = ca.nlpsol

    def counting_nlpsol(*args, **kwargs):
        constructions.append(args[0])
        return real_nlpsol(*args, **kwargs)

    monkeypatch.setattr(module.ca, "nlpsol", counting_nlpsol)
    # CasADi's virtual machine: no switch to compiled functions mid-test (that switch is
    # tested in test_compiled_functions.py).
    polisher = TrajectoryPolisher(tdcr3, None, 5, config=TrajectoryPolishConfig(compile=False))
    assert polisher.builds == 0 == len(constructions)          # built on first use
    rng = np.random.default_rng(0)
    dts = (1.0, 0.5, 0.25)
    results = []
    for dt in dts:
        q0 = straight(Q_A, Q_B, 5)
        q0[1:-1] += rng.normal(0.0, 0.05, q0[1:-1].shape)
        q0[:, 2::3] = 1.0
        results.append(polisher.solve(q0, dt))
        assert polisher.builds == 1 == len(constructions)      # the same rows: no rebuild
    assert all(r.success for r in results), [r.status for r in results]
    for r, dt in zip(results, dts, strict=True):
        assert verify_trajectory(tdcr3, None, r.q, dt).success


@pytest.mark.parametrize("scene_name", ["lattice", "shelf"])
def test_clearance_rows_agree_with_the_world_distances(tdcr3, scene_name):
    polisher = TrajectoryPolisher(tdcr3, load_scene(scene_name), 3,
                                  config=TrajectoryPolishConfig(max_pairs=12))
    kinds = {group.kind for group in polisher._groups}
    assert "self" in kinds and len(kinds) == 2
    rng = np.random.default_rng(3)
    q_near = straight(np.array([2.0, 0.5, 1.0, 2.5, 2.0, 1.0, 1.5, -1.0, 1.0]),
                      np.array([1.5, 1.5, 1.0, 2.0, 3.0, 1.0, 2.0, 0.0, 1.0]), 3)
    q = q_near + rng.normal(0.0, 0.05, q_near.shape)
    q[:, 2::3] = 1.0
    values, expected = polisher._slot_values(q_near, q)
    assert len(values) > 10                     # obstacle and self pairs were selected
    np.testing.assert_allclose(values, expected, rtol=0.0, atol=1e-9)


def test_tracking_reaches_every_pose_when_the_limits_allow(tdcr3, tracking_polisher):
    q_ref = straight(Q_A, Q_B, 8)
    positions, rotations = poses(tdcr3, q_ref)
    rng = np.random.default_rng(1)
    q0 = q_ref + rng.normal(0.0, 0.05, q_ref.shape)
    q0[:, 2::3] = 1.0
    out = tracking_polisher.solve(q0, 1.0, positions, rotations)
    assert out.success, out
    assert out.pose_errors.shape == (8,)
    assert out.pose_errors.max() <= 1e-6
    assert out.max_violation <= 1e-6


def test_tracking_keeps_a_too_small_tendon_speed_limit_at_the_price_of_error(
        tdcr3, tracking_polisher):
    q_ref = straight(Q_A, Q_B, 8)
    positions, rotations = poses(tdcr3, q_ref)
    dt = 0.02                                    # the reference would need ~3 m/s
    assert verify_trajectory(tdcr3, None, q_ref, dt).violations["tendon_speed"] > 1.0
    out = tracking_polisher.solve(q_ref, dt, positions, rotations)
    assert out.success, out
    assert out.max_violation <= 1e-6
    verdict = verify_trajectory(tdcr3, None, out.q, dt)
    assert verdict.violations["tendon_speed"] <= 1e-6
    assert verdict.violations["tendon_accel"] <= 1e-6
    assert out.pose_errors.max() > 1e-2


def test_bad_shapes_raise_and_bad_numbers_fail(tdcr3, path_polisher, tracking_polisher):
    q0 = straight(Q_A, Q_B, 6)
    with pytest.raises(ValueError, match="q0 must be"):
        path_polisher.solve(q0[:5], 0.5)
    with pytest.raises(ValueError, match="q0 must be"):
        path_polisher.solve(q0[:, :6], 0.5)
    with pytest.raises(ValueError, match="dt"):
        path_polisher.solve(q0, 0.0)
    with pytest.raises(ValueError, match="tracking"):
        path_polisher.solve(q0, 0.5, np.zeros((6, 3)), np.tile(np.eye(3), (6, 1, 1)))
    q8 = straight(Q_A, Q_B, 8)
    with pytest.raises(ValueError, match="needs target"):
        tracking_polisher.solve(q8, 0.5)
    with pytest.raises(ValueError, match="targets must be"):
        tracking_polisher.solve(q8, 0.5, np.zeros((8, 3)), np.tile(np.eye(3), (7, 1, 1)))
    with pytest.raises(ValueError, match="objective"):
        TrajectoryPolisher(tdcr3, None, 6, objective="length")
    with pytest.raises(ValueError, match="waypoints"):
        TrajectoryPolisher(tdcr3, None, 1)
    q0[2, 0] = np.nan
    out = path_polisher.solve(q0, 0.5)
    assert not out.success and out.status == "non-finite input"
