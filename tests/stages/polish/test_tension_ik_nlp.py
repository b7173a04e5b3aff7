"""The exact stage of tension-space IK (``stages.polish._tension_ik_nlp``): answers polished
by Ipopt on the CasADi rod, replayed by a fresh JAX statics solve and python-fcl, never by
the polish's own numbers. Robot ``tdcr2_rao2021`` under gravity and a 5 g tip payload."""

from __future__ import annotations

import numpy as np
import pytest

from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
from cr_nlp.model.loads import static_loads
from cr_nlp.stages.polish._ipopt import SUCCESS_STATUSES, TIME_LIMIT_STATUS
from cr_nlp.stages.polish._tension_ik_nlp import (
    EXACT_MODE,
    TensionPolishConfig,
    polish_tension_ik,
)
from cr_nlp.world.check import check_chains
from cr_nlp.world.scene import load_scene

RAO = load_robot("tdcr2_rao2021")
GRAVITY = np.array([0.0, 0.0, -9.81])
PAYLOAD = 0.005 * GRAVITY                      # 5 g at the tip, N
MARGIN = 0.002
CONFIG = TensionPolishConfig(compile=False)    # the same numbers; no background gcc here


def _loaded(tensions: np.ndarray):
    return solve_statics(RAO, tensions, PAYLOAD, None, GRAVITY)


def _replay_error(tensions: np.ndarray, targets: np.ndarray) -> np.ndarray:
    replay = _loaded(tensions)
    assert replay.converged.all()
    return np.linalg.norm(replay.tip_position - targets, axis=1)


def test_polish_reaches_the_target_with_least_tension() -> None:
    """From perturbed tensions (the tip ~cm off) to the targets, exactly: a fresh statics
    solve of the answer is within 1e-6 m, the tensions within [0, τ_max] and no larger in
    norm than the tensions that made the targets."""
    rng = np.random.default_rng(3)
    truth_tensions = np.zeros((3, RAO.n_tendons))
    for row in truth_tensions:
        for segment in range(2):
            pulled = rng.choice(3, 2, replace=False)
            row[3 * segment + pulled] = rng.uniform(0.5, 4.0, 2)
    targets = _loaded(truth_tensions).tip_position
    start = np.clip(truth_tensions + rng.normal(scale=0.3, size=truth_tensions.shape), 0, None)
    assert np.all(_replay_error(start, targets) > 1e-3)
    result = polish_tension_ik(RAO, None, start, targets,
                               loads=static_loads(3, 0.4, PAYLOAD, None, GRAVITY),
                               margin=MARGIN, config=CONFIG)
    assert all(s in SUCCESS_STATUSES for s in result.status), result.status
    assert np.all(_replay_error(result.tensions, targets) <= 1e-6)
    assert np.all(result.tensions >= 0) and np.all(result.tensions <= RAO.mechanics.tension_max)
    assert np.all(np.linalg.norm(result.tensions, axis=1)
                  <= np.linalg.norm(truth_tensions, axis=1) + 1e-9)
    assert np.all(result.seconds > 0) and np.all(result.iterations > 0)
    assert "shooting" in EXACT_MODE


def test_polish_clears_an_obstacle_the_start_goes_through() -> None:
    """A ball on the start's backbone (python-fcl: 16 mm deep): the polished answer reaches
    the same tip and keeps the margin from the ball on the freshly solved backbone."""
    start = np.array([[3.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    truth = _loaded(start)
    middle = truth.positions[0, len(truth.arc_length) // 2]
    scene = load_scene({"obstacles": [{"name": "ball", "type": "sphere",
                                       "center": middle.tolist(), "radius": 0.004}]})
    pieces = (truth.positions.shape[1] - 1) // len(RAO.segments)
    assert check_chains(RAO, scene, truth.positions, pieces).obstacle_distance[0] < 0
    result = polish_tension_ik(RAO, scene, start, truth.tip_position,
                               loads=static_loads(1, 0.4, PAYLOAD, None, GRAVITY),
                               margin=MARGIN, config=CONFIG)
    assert result.status[0] in SUCCESS_STATUSES
    replay = _loaded(result.tensions)
    assert np.linalg.norm(replay.tip_position - truth.tip_position, axis=1)[0] <= 1e-6
    clear = check_chains(RAO, scene, replay.positions, pieces).obstacle_distance[0]
    assert clear >= MARGIN - 1e-9


def test_polish_with_orientation_and_point_load() -> None:
    """Position and orientation as constraints, with a point load mid-body (the rod's grid
    gets its point): the replayed tip frame matches the target's to 1e-6 rad, measured by
    the skew part of R*ᵀR (the RK4 frames of both backends drift from orthonormal by ~1e-7,
    which puts a floor of ~1e-4 rad under arccos((tr R*ᵀR − 1)/2))."""
    truth_tensions = np.array([[0.0, 2.0, 1.0, 1.5, 0.0, 0.5]])
    point = [{"s": 0.15, "force": [0.0, 0.02, 0.0], "moment": [0.0, 0.0, 0.001]}]
    truth = solve_statics(RAO, truth_tensions, PAYLOAD, None, GRAVITY, point_loads=point)
    start = truth_tensions + np.array([[0.2, -0.3, 0.1, 0.0, 0.3, 0.2]])
    result = polish_tension_ik(RAO, None, np.clip(start, 0, None), truth.tip_position,
                               truth.tip_wxyz,
                               loads=static_loads(1, 0.4, PAYLOAD, None, GRAVITY,
                                                  point_loads=point),
                               margin=MARGIN, config=CONFIG)
    assert result.status[0] in SUCCESS_STATUSES
    replay = solve_statics(RAO, result.tensions, PAYLOAD, None, GRAVITY, point_loads=point)
    assert np.linalg.norm(replay.tip_position - truth.tip_position) <= 1e-6
    relative = truth.tip_rotation[0].T @ replay.tip_rotation[0]
    skew = 0.5 * (relative - relative.T)
    assert np.linalg.norm([skew[2, 1], skew[0, 2], skew[1, 0]]) <= 1e-6


def test_time_limit_and_bad_inputs() -> None:
    """No time: rows keep their start tensions, marked; a non-finite row is kept and named;
    wrong shapes are refused."""
    start = np.array([[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]] * 2)
    targets = np.array([[0.0, 0.0, 0.39]] * 2)
    result = polish_tension_ik(RAO, None, start, targets, margin=MARGIN, time_limit=0.0,
                               config=CONFIG)
    assert result.status == [TIME_LIMIT_STATUS] * 2
    np.testing.assert_array_equal(result.tensions, start)
    unknown = polish_tension_ik(RAO, None, start[:1], [[np.nan, 0.0, 0.3]], margin=MARGIN,
                                config=CONFIG)
    assert unknown.status == ["non-finite input"]
    np.testing.assert_array_equal(unknown.tensions, start[:1])
    with pytest.raises(ValueError, match="tensions0"):
        polish_tension_ik(RAO, None, start[:, :4], targets, margin=MARGIN)
    with pytest.raises(ValueError, match="objective"):
        TensionPolishConfig(objective="smallest")


def test_self_pairs_are_spheres_two_segments_apart() -> None:
    """Three segments: the self rows pair spheres (grid points and chord midpoints) of
    segments 1 and 3, a junction sphere counted on both of its segments (the PCC body's
    rule); none with self-collision off."""
    import json
    from pathlib import Path

    from cr_nlp.stages.polish._rod_clearance import _bodies, _self_table

    data = json.loads((Path(__file__).resolve().parents[3] / "models" / "robots"
                       / "tdcr2_rao2021.json").read_text())
    data["name"] = "tdcr3_rao_like"
    data["segments"].append({"length": 0.2, "theta_max": 3.0})
    data["tendons"]["offsets"].append(1.5707963267948966)
    data["mechanics"]["disks_per_segment"] = [4, 4, 4]
    three = load_robot(data)
    arc = np.linspace(0.0, 0.6, 13)                      # 4 steps per segment
    matrix, spheres, spacing = _bodies(arc)
    assert matrix.shape == (25, 13) and spacing == pytest.approx(0.025)
    np.testing.assert_allclose(matrix @ arc, spheres)
    pairs = _self_table(three, spheres)
    first = spheres <= 0.2 + 1e-12
    last = spheres >= 0.4 - 1e-12
    expected = {(i, j) for i in range(25) for j in range(i + 1, 25)
                if (first[i] and last[j]) or (first[j] and last[i])}
    assert {tuple(p) for p in pairs} == expected
    data["self_collision"] = False
    assert len(_self_table(load_robot(data), spheres)) == 0
