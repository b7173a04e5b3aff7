"""Path following (and its verdict) in tension space on the Cosserat model
(``tasks.tension_follow``): a followed path under gravity and a payload re-solved by a
fresh statics solve, bad input, the result file and the command. Small batches: one
follower and one 24-waypoint path shared by the tests."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cr_nlp import TensionFollower, TensionFollowResult, load_result
from cr_nlp.model import load_robot
from cr_nlp.model.statics import solve_statics
from cr_nlp.world.check import check_chains

RAO = load_robot("tdcr2_rao2021")
GRAVITY = [0.0, 0.0, -9.81]
PAYLOAD = [0.0, 0.0, -0.005 * 9.81]        # 5 g at the tip, N


def _tension_path(count: int) -> np.ndarray:
    """A smooth loop of tensions (N) on both segments."""
    t = np.linspace(0.0, 1.0, count)[:, None]
    return np.concatenate([2 + 2 * np.sin(2 * np.pi * t), 1 + np.cos(2 * np.pi * t), 0 * t,
                           1 + t, 0 * t, 2 * t], axis=1)


@pytest.fixture(scope="module")
def path() -> np.ndarray:
    truth = solve_statics(RAO, _tension_path(24), PAYLOAD, None, GRAVITY)
    assert truth.converged.all()
    return truth.tip_position


@pytest.fixture(scope="module")
def follower() -> TensionFollower:
    return TensionFollower(RAO)


@pytest.fixture(scope="module")
def followed(follower: TensionFollower, path: np.ndarray) -> TensionFollowResult:
    return follower.follow(path, dt=0.05, gravity=GRAVITY, tip_force=PAYLOAD)


def test_followed_tips_by_fresh_statics_are_on_the_path(followed: TensionFollowResult,
                                                       path: np.ndarray) -> None:
    assert followed.success, followed.reason
    again = solve_statics(RAO, followed.tensions, PAYLOAD, None, GRAVITY)
    assert again.converged.all()
    assert np.max(np.linalg.norm(again.tip_position - path, axis=1)) < 1e-3
    assert np.all(followed.tensions >= 0) and np.all(followed.tensions <= 10.0)
    rate = np.abs(np.diff(followed.tensions, axis=0)) / 0.05
    assert rate.max() <= followed.tension_rate_max


def test_an_obstacle_on_the_motion_fails_the_verdict(follower: TensionFollower,
                                                     followed: TensionFollowResult) -> None:
    middle = followed.backbone[12, 15]      # a point of the body at waypoint 12
    scene = {"obstacles": [{"name": "ball", "type": "sphere", "center": middle.tolist(),
                            "radius": 0.01}]}
    blocked = TensionFollower(RAO, scene, follower.config)
    report = blocked.verify(followed)
    assert not report.success and "collision" in report.reason
    # python-fcl on an independent solve of the same tensions agrees.
    again = solve_statics(RAO, followed.tensions[12], PAYLOAD, None, GRAVITY)
    assert check_chains(RAO, blocked.scene, again.positions, 10).collision[0]


@pytest.mark.parametrize(("options", "words"), [
    ({"tip_force": [0.0, -1.0]}, "tip_force"),
    ({"point_loads": [{"s": 0.1, "force": [0, 0, -1], "mass": 1}]}, "mass"),
    ({"point_loads": [{"s": 0.9, "force": [0, 0, -1]}]}, "outside the robot"),
])
def test_bad_loads_name_the_key(follower: TensionFollower, path: np.ndarray,
                                options: dict, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        follower.follow(path[:3], **options)


def test_bad_path_names_the_waypoint(follower: TensionFollower, path: np.ndarray) -> None:
    bad = path[:4].copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="waypoint 2"):
        follower.follow(bad)
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        follower.follow(path[:4, :2])


def test_verdict_rejects_a_negative_tension_and_a_fast_change(
        follower: TensionFollower, followed: TensionFollowResult) -> None:
    from cr_nlp.model.loads import static_loads

    loads = static_loads(1, follower.ik.length, PAYLOAD, None, GRAVITY)
    tensions = followed.tensions[:3].copy()
    tensions[1, 0] = -0.5
    with pytest.raises(ValueError, match="waypoint 1: tendon 1: a tension must be"):
        follower.verify_tensions(tensions, 0.05, loads)
    jump = followed.tensions[[0, 12]]
    report = follower.verify_tensions(jump, 0.05, loads)
    assert not report.success and "tension rate" in report.reason


def test_result_file_round_trip(followed: TensionFollowResult, tmp_path) -> None:
    path = followed.save(tmp_path / "R.json")
    assert json.loads(path.read_text())["kind"] == "tension_follow"
    back = load_result(path)
    assert isinstance(back, TensionFollowResult)
    np.testing.assert_array_equal(back.tensions, followed.tensions)
    np.testing.assert_array_equal(back.backbone, followed.backbone)
    assert back.success == followed.success and back.stage == followed.stage
    assert back.loads()["gravity"].tolist() == GRAVITY
    rows = followed.save_csv(tmp_path / "t.csv").read_text().splitlines()
    assert rows[0].startswith("time_s,tension_1_N") and len(rows) == len(followed) + 1


@pytest.mark.slow
def test_cli_follow_model_cosserat(path: np.ndarray, tmp_path) -> None:
    file = tmp_path / "path.json"
    file.write_text(json.dumps({"dt": 0.05, "poses": [
        {"position": p.tolist(), "wxyz": [1, 0, 0, 0]} for p in path[:8]]}))
    out, table = tmp_path / "R.json", tmp_path / "t.csv"
    run = subprocess.run([sys.executable, "-m", "cr_nlp.cli", "follow", "--model", "cosserat",
                          "--robot", "tdcr2_rao2021", "--path", str(file), "--gravity",
                          "0,0,-9.81", "--tip-force", "0,0,-0.04905", "--out", str(out),
                          "--csv", str(table)], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr
    result = load_result(out)
    assert result.kind == "tension_follow" and result.success, result.reason
    assert len(table.read_text().splitlines()) == 9
