"""Trajectory planning: roadmap initialisation through a narrow passage, the independent
verification (tunnelling between waypoints), result files, CLI bad input."""

from __future__ import annotations

import argparse
import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from cr_nlp import SCHEMA_VERSION, load_results
from cr_nlp.cli import plan as plan_command
from cr_nlp.model import load_robot
from cr_nlp.tasks.geometry.trajectory import (
    TrajectoryConfig,
    TrajectoryPlanner,
    TrajectoryResult,
    interpolate_trajectory,
    tendon_series,
    tip_positions,
    trajectories_from_dict,
    trajectories_to_dict,
    verify_trajectory,
)
from cr_nlp.world import load_scene

from ...conftest import MODELS
from ..test_result import assert_same_result

ROBOT = MODELS / "robots" / "tdcr3.json"

# A shelf problem (benchmark protocol: collision-free ends, tips > 0.3 m apart) where the
# straight line in z, optimised, stays stuck in the shelf's boards; the roadmap's path
# leads around them.
SHELF_START = [3.1395115543450083, -0.03016860676928035, 1.0, 0.9348382398164116,
               0.9850967216439708, 1.0, 1.175206334757721, 1.5005017964598384, 1.0]
SHELF_GOAL = [2.553407897782403, 2.979784007141612, 1.0, 1.7290908110047025,
              -0.43082641924965825, 1.0, 2.7551460635192107, 0.8984417405961853, 1.0]


@pytest.fixture(scope="module")
def robot():
    return load_robot(ROBOT)


@pytest.fixture(scope="module")
def shelf_planner(robot):
    return TrajectoryPlanner(robot, load_scene("shelf"), TrajectoryConfig(guesses=1))


def test_roadmap_init_finds_the_passage_the_straight_line_misses(shelf_planner):
    straight = shelf_planner.plan([SHELF_START], [SHELF_GOAL], init="straight")[0]
    assert not straight.success and "collision" in straight.reason
    found = shelf_planner.plan([SHELF_START], [SHELF_GOAL], init="roadmap")[0]
    assert found.success, found.reason
    assert found.stage == "refine" and found.notes == ["roadmap"]
    assert found.stage_text == "refine (roadmap)"
    assert found.max_violation <= 1e-6
    assert found.min_clearance >= 0.0
    np.testing.assert_allclose(found.q[0], SHELF_START)
    assert found.q.dtype == np.float64 and found.tendon_lengths.dtype == np.float64
    np.testing.assert_allclose(found.q[-1], SHELF_GOAL)


# Segment 3 bends from straight to 90° (segments 1 and 2 slightly bent: python-fcl was
# seen to hang on the exactly collinear capsules of a fully straight robot).
TUNNEL_Q = np.array([[0.1, math.pi / 2, 1, 0.1, -math.pi / 2, 1, 0.0, 0.0, 1],
                     [0.1, math.pi / 2, 1, 0.1, -math.pi / 2, 1, math.pi / 2, 0.0, 1]])


def test_verify_catches_tunnelling_between_waypoints(robot):
    # A 2 cm sphere where the tip passes halfway between the two waypoints.
    halfway = interpolate_trajectory(TUNNEL_Q, 2)[1]
    centre = tip_positions(robot, halfway[None])[0]
    scene = load_scene({"name": "thin", "obstacles": [
        {"type": "sphere", "name": "thin", "center": centre.tolist(), "radius": 0.02}]})
    waypoints_only = verify_trajectory(robot, scene, TUNNEL_Q, dt=10.0, samples=1)
    assert waypoints_only.collision_free
    dense = verify_trajectory(robot, scene, TUNNEL_Q, dt=10.0, samples=4)
    assert not dense.success and not dense.collision_free
    assert dense.violations["clearance"] > 0.002
    assert "collision" in dense.reason


def test_verify_measures_tendon_speed_and_acceleration(robot):
    q = np.repeat(TUNNEL_Q[:1], 3, axis=0)
    q[1, 6] = 0.5                      # segment 3 bends 0.5 rad and back
    verdict = verify_trajectory(robot, None, q, dt=0.1)
    lengths = tendon_series(robot, q)
    speed = np.max(np.abs(np.diff(lengths, axis=0))) / 0.1
    assert verdict.tendon_speed == pytest.approx(speed)
    assert verdict.violations["tendon_speed"] == pytest.approx(speed - 0.2)
    assert verdict.violations["tendon_accel"] > 0.0
    assert not verdict.success and "tendon speed" in verdict.reason


def _run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    plan_command.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.run(args)


def test_cli_plans_and_reports_bad_input(tmp_path, robot):
    scene = load_scene("shelf")
    planner = TrajectoryPlanner(robot, scene)
    in_collision = [1.5, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0]
    assert "collision" in planner.validate(in_collision, SHELF_GOAL)[2]
    problems = {"problems": [
        # The short form: fixed lengths omitted.
        {"start": np.delete(SHELF_START, [2, 5, 8]).tolist(),
         "goal": np.delete(SHELF_GOAL, [2, 5, 8]).tolist()},
        {"start": in_collision, "goal": SHELF_GOAL},
        {"start": SHELF_START, "goal": [4.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0]},
        {"start": [0.1, 0.2], "goal": SHELF_GOAL},
    ], "horizon": 11, "dt": 0.5}
    path = tmp_path / "problems.json"
    path.write_text(json.dumps(problems))
    out = tmp_path / "result.json"
    assert _run_cli(["plan", "--robot", str(ROBOT), "--scene", "shelf", "--problems", str(path),
                     "--init", "straight", "--out", str(out), "--csv", str(tmp_path / "csv")]) == 0
    data = json.loads(out.read_text())
    rows = data["results"]
    assert len(rows) == 4 and "total" in data["timing"]
    assert data["kind"] == "trajectory" and data["schema_version"] == SCHEMA_VERSION
    first = rows[0]
    assert len(first["q"]) == 12 and first["dt"] == 0.5
    assert len(first["tendon_lengths"]) == 12 and len(first["tendon_lengths"][0]) == 9
    for key in ("success", "path_length", "min_clearance", "max_violation", "reason"):
        assert key in first
    assert not rows[1]["success"] and "start is in collision" in rows[1]["reason"]
    assert not rows[2]["success"] and "bad goal" in rows[2]["reason"]
    assert not rows[3]["success"] and "bad start" in rows[3]["reason"]
    with (tmp_path / "csv" / "problem_0.csv").open() as handle:
        table = list(csv.reader(handle))
    assert table[0][0] == "time_s" and len(table[0]) == 10 and len(table) == 13
    times = [float(r[0]) for r in table[1:]]
    np.testing.assert_allclose(times, np.arange(12) * 0.5)
    np.testing.assert_allclose(np.array(table[1:], dtype=float)[:, 1:],
                               np.array(first["tendon_lengths"]), atol=1e-8)
    assert not (tmp_path / "csv" / "problem_1.csv").exists()


def test_cli_rejects_a_malformed_file(tmp_path):
    from cr_nlp.cli import UsageError

    path = tmp_path / "problems.json"
    path.write_text(json.dumps({"start": [0.0]}))
    with pytest.raises(UsageError, match="problems"):
        _run_cli(["plan", "--robot", str(ROBOT), "--problems", str(path), "--out", "-"])


def test_results_json_and_npz_round_trip(tmp_path, shelf_planner):
    from cr_nlp.tasks.geometry.trajectory import save_results

    results = shelf_planner.plan([SHELF_START], [SHELF_GOAL], init="roadmap")
    save_results(results, tmp_path / "r.json", shelf_planner.last_timing.as_dict())
    save_results(results, tmp_path / "r.npz")
    loaded = json.loads((tmp_path / "r.json").read_text())
    assert loaded == json.loads(json.dumps(trajectories_to_dict(
        results, shelf_planner.last_timing.as_dict())))
    assert loaded["kind"] == "trajectory" and loaded["schema_version"] == SCHEMA_VERSION
    # The result protocol: the same TrajectoryResults back from the file (the LM cost too).
    (back,) = load_results(tmp_path / "r.json")
    assert_same_result(back, results[0])
    assert_same_result(TrajectoryResult.from_dict(results[0].to_dict()), results[0])
    arrays = np.load(tmp_path / "r.npz")
    np.testing.assert_allclose(arrays["q_0"], results[0].q)
    assert arrays["success"][0] == results[0].success


def test_exact_mode_respects_tendon_limits_where_the_penalty_answer_breaks_them(robot):
    # A nearly free tendon penalty: the LM answer shortens the tip path and overshoots the
    # tendon speed/acceleration limits; Ipopt holds them as constraints. The straight line
    # in z between the ends needs 0.167 m/s at dt = 0.12 s (limit 0.2 m/s): feasible.
    start = [0.5, 0.3, 1.0, 0.6, 1.0, 1.0, 0.4, 2.0, 1.0]
    goal = [1.2, -0.5, 1.0, 0.9, 2.0, 1.0, 1.0, -1.0, 1.0]
    config = TrajectoryConfig(waypoints=10, dt=0.12, guesses=1, tendon_weight=1e-9,
                              tendon_limit_fraction=1.0)
    planner = TrajectoryPlanner(robot, None, config)
    penalty = planner.plan([start], [goal], init="straight")[0]
    verdict = verify_trajectory(robot, None, penalty.q, config.dt)
    assert not verdict.success and "tendon" in verdict.reason
    assert max(verdict.violations["tendon_speed"],
               verdict.violations["tendon_accel"]) > 1e-3
    # Beside it, a short move whose LM answer the verdict accepts: it is not polished,
    # and its result (polish time 0) is written and read back like any other.
    near = np.add(start, [0.02, 0.0, 0.0] * 3)
    exact, short = planner.plan([start, start], [goal, near], init="straight", exact=True)
    assert short.success and short.stage.startswith("refine") and short.timing.polish == 0.0
    again = trajectories_from_dict(json.loads(json.dumps(trajectories_to_dict([short]))))[0]
    assert again.stage_text == short.stage_text and again.timing.polish == 0.0
    np.testing.assert_allclose(again.q, short.q)
    assert exact.stage == "polish", exact.stage
    assert exact.success and exact.max_violation <= 1e-6
    checked = verify_trajectory(robot, None, exact.q, config.dt)
    assert checked.success and checked.max_violation <= 1e-6
    np.testing.assert_allclose(exact.q[0], start, atol=1e-9)
    np.testing.assert_allclose(exact.q[-1], goal, atol=1e-9)


def test_one_verdict_a_margin_violation_is_a_failure_in_both_modes(shelf_planner,
                                                                   monkeypatch):
    # A failed polish returns the LM answer with its own verdict. An answer 1 mm closer
    # to the shelf than δ (still collision-free) fails that verdict in both modes, and
    # the reason says which check failed by how much.
    from cr_nlp.stages.polish._trajectory_nlp import TrajectoryPolisher
    from cr_nlp.tasks.geometry import trajectory as T
    from cr_nlp.world.verdict import failure_reason

    class Failed:
        success, status, q, violations = False, "Infeasible_Problem_Detected", None, {}

    monkeypatch.setattr(TrajectoryPolisher, "solve", lambda self, q, dt, *a, **k: Failed())
    assert shelf_planner.plan([SHELF_START], [SHELF_GOAL])[0].success
    true_verify = T.verify_trajectories

    def short(checked):
        violations = {**checked.violations, "clearance": 1e-3}
        reason = failure_reason(violations)
        return replace(checked, verdict=replace(
            checked.verdict, violations=violations, max_violation=max(violations.values()),
            reason=reason, success=not reason))

    def verify_with_a_short_margin(robot, scene, qs, dt, margin, samples, *a, **k):
        return [short(c) for c in true_verify(robot, scene, qs, dt, margin, samples, *a, **k)]

    monkeypatch.setattr(T, "verify_trajectories", verify_with_a_short_margin)
    penalty = shelf_planner.plan([SHELF_START], [SHELF_GOAL])[0]
    exact = shelf_planner.plan([SHELF_START], [SHELF_GOAL], exact=True)[0]
    assert "polish failed: from refine" in exact.stage_text
    assert "Infeasible_Problem_Detected" in exact.stage_text
    assert exact.stage == "refine" and exact.notes[-1].startswith("polish failed: from refine")
    for result in (penalty, exact):
        assert not result.success and result.max_violation > 1e-6
        assert "breaks the clearance by 0.001 m" in result.reason


def test_planning_without_a_scene_needs_no_roadmap(robot):
    # The default init ("roadmap") without a scene: no roadmap to build (there was a
    # crash here: the roadmap's cache key read the missing scene), straight and perturbed
    # guesses only, and the verdict accepts the answer.
    start = [0.5, 0.3, 1.0, 0.6, 1.0, 1.0, 0.4, 2.0, 1.0]
    goal = np.add(start, [0.3, 0.2, 0.0] * 3)
    config = TrajectoryConfig(waypoints=10, dt=0.12, guesses=1)
    planner = TrajectoryPlanner(robot, None, config)
    result = planner.plan([start], [goal])[0]
    assert planner.roadmap() is None
    assert result.success, result.reason
    assert verify_trajectory(robot, None, result.q, config.dt).success
