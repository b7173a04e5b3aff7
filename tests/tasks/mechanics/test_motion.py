"""Path following (and its verdict) in tension space on the Cosserat model
(``tasks.mechanics.follow``): a followed path under gravity and a payload re-solved by a
fresh statics solve, bad input, the result file and the command. Small batches: one
follower and one 24-waypoint path shared by the tests."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cr_nlp import TensionFollowResult, TensionPathFollower, load_result
from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
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
def follower() -> TensionPathFollower:
    return TensionPathFollower(RAO)


@pytest.fixture(scope="module")
def followed(follower: TensionPathFollower, path: np.ndarray) -> TensionFollowResult:
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


def test_the_branch_search_reaches_every_waypoint_within_the_rate(
        follower: TensionPathFollower, path: np.ndarray) -> None:
    """The follower's branch search (``_follow_branches``) on the loop: every waypoint's
    tensions put the tip of a fresh statics solve on it, within the tension bounds, and no
    tendon changes by more than the step between waypoints; with a step no branch keeps it
    carries on with the branches that break it least; with a waypoint no answer reaches
    (1 m away) it names the waypoint where every branch was lost."""
    from cr_nlp.model.loads import static_loads
    from cr_nlp.tasks.mechanics._follow_branches import BranchSearch, branch_search

    loads = static_loads(1, follower.ik.length, PAYLOAD, None, GRAVITY)
    quats = np.full((len(path), 4), np.nan)
    settings = BranchSearch(width=4, tries=2, spread=1.0, distinct=1.0)
    step = 50.0 * 0.05
    motion, reached = branch_search(follower.ik, follower.ik, path, quats, loads, step,
                                    settings)
    assert reached == len(path) and motion.shape == (len(path), RAO.n_tendons)
    assert np.abs(np.diff(motion, axis=0)).max() <= step
    assert motion.min() >= 0.0 and motion.max() <= float(RAO.mechanics.tension_max)
    again = solve_statics(RAO, motion, PAYLOAD, None, GRAVITY)
    assert again.converged.all()
    assert np.linalg.norm(again.tip_position - path, axis=1).max() < 1e-4 + 1e-9
    tight, reached = branch_search(follower.ik, follower.ik, path, quats, loads, 1e-6,
                                   settings)
    assert reached == len(path) and np.abs(np.diff(tight, axis=0)).max() > 1e-6
    tips = solve_statics(RAO, tight, PAYLOAD, None, GRAVITY).tip_position
    assert np.linalg.norm(tips - path, axis=1).max() < 1e-4 + 1e-9
    away = path.copy()
    away[5, 2] += 1.0
    assert branch_search(follower.ik, follower.ik, away, quats, loads, step,
                         settings) == (None, 5)


def test_an_obstacle_on_the_motion_fails_the_verdict(follower: TensionPathFollower,
                                                     followed: TensionFollowResult) -> None:
    middle = followed.backbone[12, 15]      # a point of the body at waypoint 12
    scene = {"obstacles": [{"name": "ball", "type": "sphere", "center": middle.tolist(),
                            "radius": 0.01}]}
    blocked = TensionPathFollower(RAO, scene, follower.config)
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
def test_bad_loads_name_the_key(follower: TensionPathFollower, path: np.ndarray,
                                options: dict, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        follower.follow(path[:3], **options)


def test_bad_path_names_the_waypoint(follower: TensionPathFollower, path: np.ndarray) -> None:
    bad = path[:4].copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="waypoint 2"):
        follower.follow(bad)
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        follower.follow(path[:4, :2])


def test_verdict_rejects_a_negative_tension_and_a_fast_change(
        follower: TensionPathFollower, followed: TensionFollowResult) -> None:
    from cr_nlp.model.loads import static_loads

    loads = static_loads(1, follower.ik.length, PAYLOAD, None, GRAVITY)
    tensions = followed.tensions[:3].copy()
    tensions[1, 0] = -0.5
    with pytest.raises(ValueError, match="waypoint 1: tendon 1: a tension must be"):
        follower.verify_tensions(tensions, 0.05, loads)
    jump = followed.tensions[[0, 12]]
    report = follower.verify_tensions(jump, 0.01, loads)
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
    out, table, loads = tmp_path / "R.json", tmp_path / "t.csv", tmp_path / "loads.json"
    loads.write_text(json.dumps({"tip_force": [0, 0, -0.04905]}))
    run = subprocess.run([sys.executable, "-m", "cr_nlp.cli", "follow", "--model", "cosserat",
                          "--robot", "tdcr2_rao2021", "--path", str(file), "--gravity",
                          "0,0,-9.81", "--loads", str(loads), "--out", str(out),
                          "--csv", str(table)], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr
    result = load_result(out)
    assert result.kind == "tension_follow" and result.success, result.reason
    np.testing.assert_array_equal(result.tip_force, [0, 0, -0.04905])
    np.testing.assert_array_equal(result.gravity, [0, 0, -9.81])
    assert len(table.read_text().splitlines()) == 9



@pytest.mark.slow  # a 3-segment, 9-tendon rod of its own (about a minute of compiling);
# the default run covers its parts: the follow command's --csv (above), motor commands
# from tensions (test_ik's result file) and their inverse (test_displacement_statics).
def test_the_fitted_robot_follows_a_path_under_its_gravity_and_its_commands_replay_it(
        tmp_path) -> None:
    """``ftdcr_v6_cosserat`` (``calibrate --model cosserat`` on the bundled recording):
    ``follow --model cosserat`` runs under the recording's gravity without a --gravity,
    and the motor commands it writes, replayed through the displacement-driven statics
    (not the tension statics the follower solved), put the tip on the path."""
    from cr_nlp.model.cosserat import solve_displacement_statics

    robot = load_robot("ftdcr_v6_cosserat")
    gravity = list(robot.mechanics.calibration_gravity)
    s = np.linspace(0.0, 1.0, 12)[:, None]
    tensions = (s * [1.0, 0, 0, 0.5, 0, 0, 0.3, 0, 0]
                + (1 - s) * [0, 0.8, 0, 0, 0.4, 0, 0, 0, 0.2])           # N
    truth = solve_statics(robot, tensions, gravity=gravity)
    file = tmp_path / "path.json"
    file.write_text(json.dumps({"dt": 0.1, "poses": [
        {"position": p.tolist(), "wxyz": w.tolist()}
        for p, w in zip(truth.tip_position, truth.tip_wxyz, strict=True)]}))
    out, table = tmp_path / "R.json", tmp_path / "t.csv"
    run = subprocess.run([sys.executable, "-m", "cr_nlp.cli", "follow", "--model", "cosserat",
                          "--robot", "ftdcr_v6_cosserat", "--path", str(file), "--out",
                          str(out), "--csv", str(table)],
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr
    assert "calibration_gravity" in run.stderr
    result = load_result(out)
    assert result.success, result.reason
    np.testing.assert_array_equal(result.gravity, gravity)
    columns = np.genfromtxt(table, delimiter=",", names=True)
    commands = np.stack([columns[f"command_{j}_m"] for j in range(1, 10)], axis=1)
    replay = solve_displacement_statics(robot, commands, gravity=gravity)
    assert replay.converged.all()
    error = np.linalg.norm(replay.tip_position - truth.tip_position, axis=1)
    assert error.max() <= result.tolerance + 1e-6, error.max()


@pytest.mark.slow  # the fitted rod's programs (about a minute of compiling)
def test_the_fitted_robot_follows_every_path_clear_motions_trace_in_its_clutter() -> None:
    """On the fitted FTDCR rod (3 segments of 3 tendons) in its clutter scene of seed 2,
    three 60-waypoint paths that clear motions trace at 35 N/s: each is followed, by the
    verdict (fresh statics and python-fcl at every checked sample) and again here, within
    the rate limit, every tip on the path. Two of them need the branch search: the branch
    the first waypoint's answer sets out on runs into a dead end (before the follower
    carried M(0) from waypoint to waypoint and kept the backbone off itself, 9 of the 12
    paths of seeds 0–3 were followed)."""
    from cr_nlp.bench.tension_clutter import DT, RATE_MAX, clear_motions, clutter_scene
    from cr_nlp.tasks.mechanics.follow import TensionFollowConfig

    robot = load_robot("ftdcr_v6_cosserat")
    follower = TensionPathFollower(robot, clutter_scene(robot, 2),
                                   TensionFollowConfig(tension_rate_max=RATE_MAX))
    searched = 0
    for motion in clear_motions(follower, 3, 60, 0.7, np.random.default_rng(2)):
        truth = solve_statics(robot, motion, PAYLOAD, None, GRAVITY)
        result = follower.follow(truth.tip_position, dt=DT, gravity=GRAVITY,
                                 tip_force=PAYLOAD)
        assert result.success, (result.reason, result.notes)
        searched += result.notes[0].startswith("branch search")
        assert np.abs(np.diff(result.tensions, axis=0)).max() / DT <= RATE_MAX
        again = solve_statics(robot, result.tensions, PAYLOAD, None, GRAVITY)
        assert again.converged.all()
        assert np.linalg.norm(again.tip_position - truth.tip_position, axis=1).max() <= 1e-3
        checked = check_chains(robot, follower.scene, again.positions, 10)
        assert checked.obstacle_distance.min() >= 0.002
        assert checked.self_distance.min() >= 0.002
    assert searched == 2


# ---------------------------------------------------------------- planning

SCENE = {"obstacles": [
    {"name": "ball", "type": "sphere", "center": [0.12, 0.0, 0.30], "radius": 0.03},
    {"name": "crate", "type": "box", "center": [0.0, -0.2, 0.2], "size": [0.1, 0.04, 0.1]}]}


@pytest.fixture(scope="module")
def planner():
    from cr_nlp import TensionTrajectoryConfig, TensionTrajectoryPlanner

    return TensionTrajectoryPlanner(RAO, SCENE, TensionTrajectoryConfig(via_pool=128))


def test_a_plan_replayed_through_fresh_statics_keeps_its_clearance(planner) -> None:
    # The straight legs between these pairs pass through the scene: a via is needed.
    starts = np.array([[0, 0, 0, 0, 0, 3.0], [0, 0, 0, 0, 0, 6.0]])
    goals = np.array([[0, 6.0, 0, 0, 0, 3.0], [0, 6.0, 0, 0, 0, 0]])
    straight = starts[:, None] + np.linspace(0, 1, 9)[None, :, None] * (goals - starts)[:, None]
    direct = solve_statics(RAO, straight.reshape(-1, 6), PAYLOAD, None, GRAVITY)
    assert check_chains(RAO, planner.scene, direct.positions, 10).obstacle_distance.min() < 0
    results = planner.plan(starts, goals, gravity=GRAVITY, tip_force=PAYLOAD)
    assert all(r.success and "via" in r.notes[0] for r in results), [
        (r.reason, r.notes) for r in results]
    for result, start, goal in zip(results, starts, goals, strict=True):
        np.testing.assert_array_equal(result.tensions[[0, -1]], np.stack([start, goal]))
        assert np.abs(np.diff(result.tensions, axis=0)).max() / result.dt <= 50.0
        # Independent replay: statics at waypoints and midpoints, python-fcl on each.
        mids = 0.5 * (result.tensions[1:] + result.tensions[:-1])
        replay = solve_statics(RAO, np.concatenate([result.tensions, mids]), PAYLOAD, None,
                               GRAVITY)
        assert replay.converged.all()
        checked = check_chains(RAO, planner.scene, replay.positions, 10)
        assert checked.obstacle_distance.min() >= planner.config.safety_margin


def test_the_verdict_names_the_steps_that_fail(planner) -> None:
    """A motion whose waypoints are clear but whose straight step between two of them
    passes through the ball (samples between them collide), and a step too fast: the
    verdict names exactly those steps (k: waypoint k → k + 1)."""
    from cr_nlp.model.loads import static_loads
    from cr_nlp.tasks.mechanics._motion import interpolated, verify_tension_motion

    loads = static_loads(1, planner.length, PAYLOAD, None, GRAVITY)
    start, goal = np.array([0, 0, 0, 0, 0, 3.0]), np.array([0, 6.0, 0, 0, 0, 3.0])
    motion = np.stack([start, start, goal, goal])
    samples, at = interpolated(motion, 2)
    replay = solve_statics(RAO, samples, PAYLOAD, None, GRAVITY)
    distance = check_chains(RAO, planner.scene, replay.positions, 10).obstacle_distance
    assert distance[at].min() >= 0.002 and distance[at[1]:at[2]].min() < 0.0
    report = verify_tension_motion(RAO, planner.scene, motion, 10.0, loads, margin=0.002,
                                   rate_max=50.0)
    assert not report.success and report.failed_steps.tolist() == [1]
    fast = verify_tension_motion(RAO, None, motion, 0.01, loads, margin=0.002,
                                 rate_max=50.0)
    assert "tension rate" in fast.reason and fast.failed_steps.tolist() == [1]
    assert verify_tension_motion(RAO, None, motion, 10.0, loads, margin=0.002,
                                 rate_max=50.0).failed_steps.tolist() == []


def test_the_samples_of_a_step_made_waypoints_are_the_ones_the_verdict_checks() -> None:
    from cr_nlp.tasks.mechanics._motion import interpolated
    from cr_nlp.tasks.mechanics._motion_refine import with_samples

    motion = np.random.default_rng(3).uniform(0.0, 6.0, (5, 6))
    samples, _ = interpolated(motion, 2)
    denser = with_samples(motion, np.array([1, 3]), 2)
    np.testing.assert_allclose(denser, np.concatenate(
        [motion[:2], samples[4:6], motion[2:4], samples[10:12], motion[4:]]), atol=1e-12)


def test_a_refined_motion_that_cuts_an_obstacle_between_waypoints_is_mended() -> None:
    """In the benchmark's clutter, a via plan whose refined motion (shorter) passes
    through an obstacle between two waypoints: without the repair the search's motion is
    kept; with it, the checked samples of that step become waypoints, the LM runs again,
    and the answer keeps δ at every sample the verdict checks (replayed here by fresh
    statics and python-fcl) with a shorter tip path than the search's."""
    from cr_nlp import TensionTrajectoryConfig, TensionTrajectoryPlanner
    from cr_nlp.bench.tension_clutter import clutter_scene
    from cr_nlp.model.loads import static_loads
    from cr_nlp.tasks.mechanics._motion import interpolated

    scene = clutter_scene(RAO, 0)
    start, goal = [3.9, 2.727, 0.0, 0.181, 0.0, 0.0], [4.629, 4.793, 0.0, 0.0, 0.0, 0.733]
    plain = TensionTrajectoryPlanner(RAO, scene, TensionTrajectoryConfig(repair_rounds=0,
                                                                         blends=()))
    kept = plain.plan(start, goal, gravity=GRAVITY, tip_force=PAYLOAD)[0]
    assert kept.success and kept.stage.value == "explore", kept.notes
    assert kept.notes[-1].startswith("the refined motion was not kept"), kept.notes
    planner = TensionTrajectoryPlanner(RAO, scene)
    result = planner.plan(start, goal, gravity=GRAVITY, tip_force=PAYLOAD)[0]
    assert result.success and result.stage.value == "refine", (result.reason, result.notes)
    assert any(note.startswith("repair 1") for note in result.notes), result.notes
    samples, _ = interpolated(result.tensions, planner.config.samples_between)
    replay = solve_statics(RAO, samples, PAYLOAD, None, GRAVITY)
    checked = check_chains(RAO, planner.scene, replay.positions, 10)
    assert replay.converged.all() and checked.obstacle_distance.min() >= 0.002
    assert np.abs(np.diff(result.tensions, axis=0)).max() / result.dt <= 50.0 + 1e-9
    loads = static_loads(1, planner.length, PAYLOAD, None, GRAVITY)
    assert planner.tip_path(result.tensions, loads) < 0.8 * planner.tip_path(kept.tensions,
                                                                             loads)


def test_a_via_pool_smaller_than_the_candidates_gives_a_failed_plan_not_an_error() -> None:
    """One via candidate (not clear): no via, no route through the roadmap of that one
    node (a search asking for 16 candidates of the 1 raised before), so the direct legs,
    judged in collision."""
    from cr_nlp import TensionTrajectoryConfig, TensionTrajectoryPlanner

    planner = TensionTrajectoryPlanner(RAO, SCENE,
                                       TensionTrajectoryConfig(via_pool=1, chain_iterations=0))
    result = planner.plan([0, 0, 0, 0, 0, 3.0], [0, 6.0, 0, 0, 0, 3.0], gravity=GRAVITY,
                          tip_force=PAYLOAD)[0]
    assert not result.success and "collision" in result.reason, result.reason
    assert result.notes[0] == ("no clear via among the 1 cheapest of 1 candidates, nor a "
                               "route through the roadmap"), result.notes


@pytest.mark.parametrize(("problem", "words"), [
    ({"start": [1, 0, 0, 0, 0, -1], "goal": [0] * 6}, r"problem 0: start\[5\].*≥ 0 N"),
    ({"start": [1, 0, 0], "goal": [0] * 6}, "problem 0: start: expected 6 tensions"),
    ({"start": [0] * 6, "goal": [0] * 6, "via": [0] * 6}, "problem 0: unknown key 'via'"),
])
def test_bad_problems_name_the_problem_and_key(problem: dict, words: str) -> None:
    from cr_nlp.tasks.readers import read_tension_problems

    with pytest.raises(ValueError, match=words):
        read_tension_problems(RAO, {"problems": [problem]})


@pytest.mark.parametrize(("settings", "words"), [
    ({"repair_rounds": -1}, "repair_rounds must be ≥ 0, got -1"),
    ({"repair_iterations": 0}, "repair_iterations must be ≥ 1, got 0"),
    ({"blends": (0.5, 1.5)}, "blends must be fractions between 0 and 1.*got 1.5"),
])
def test_bad_repair_settings_are_named(settings: dict, words: str) -> None:
    from cr_nlp import TensionTrajectoryConfig

    with pytest.raises(ValueError, match=words):
        TensionTrajectoryConfig(**settings)
    TensionTrajectoryConfig(repair_rounds=0, repair_iterations=0, blends=())   # no repair


def test_trajectories_file_round_trip(planner, tmp_path) -> None:
    from cr_nlp import TensionTrajectoryResult, load_results
    from cr_nlp.tasks._result import write_json
    from cr_nlp.tasks.mechanics._motion_result import tension_trajectories_to_dict

    results = planner.plan(np.zeros(6), [0, 1.0, 0, 0, 0, 0.5], gravity=GRAVITY)
    path = tmp_path / "R.json"
    write_json(tension_trajectories_to_dict(results, None, RAO), path)
    mode = json.loads(path.read_text())["results"][0]["exact_mode"]
    assert mode.startswith("none: no Ipopt stage ran")
    back = load_results(path)
    assert len(back) == 1 and isinstance(back[0], TensionTrajectoryResult)
    assert back[0].kind == "tension_trajectory" and back[0].success == results[0].success
    np.testing.assert_array_equal(back[0].tensions, results[0].tensions)
    np.testing.assert_array_equal(back[0].backbone, results[0].backbone)


# ---------------------------------------------------------------- a PCC plan under load

def test_tensions_of_a_configuration_round_trip() -> None:
    from cr_nlp.model.tendon_groups import configuration_of_tensions, tensions_of_configuration

    rng = np.random.default_rng(3)
    tensions = rng.uniform(0.0, 5.0, (20, 6))
    q = configuration_of_tensions(RAO, tensions)
    least, missed = tensions_of_configuration(RAO, q)
    assert least.dtype == np.float64 and missed.max() < 1e-12
    np.testing.assert_allclose(configuration_of_tensions(RAO, least), q, atol=1e-12)
    # the least tensions: never more total pull than the set that made the shape
    assert (least.sum(axis=1) <= tensions.sum(axis=1) + 1e-9).all()
    # the unloaded rod (independent: the Cosserat shooting) takes the PCC shape
    from cr_nlp.model import tip_pose

    solved = solve_statics(RAO, least)
    pcc_tips = np.array([tip_pose(RAO, x)[0] for x in q])
    assert np.linalg.norm(solved.tip_position - pcc_tips, axis=1).max() < 1e-4
    # a bend the tension limit cannot hold is reported, not clipped silently
    _, missed = tensions_of_configuration(RAO, [3.0, 0.0, 0.2, 0.0, 0.0, 0.2])
    assert missed > 0.1


# A PCC motion sweeping segment 1 from 0.6 to 0.9 rad and segment 2 to 0.3 rad towards +x;
# the ball sits clear of it (by the PCC model) and where the sagging tip goes under gravity.
PCC_MOTION = (np.array([0.6, 0.0, 0.2, 0.0, 0.0, 0.2])
              + np.linspace(0.0, 1.0, 8)[:, None] * np.array([0.3, 0.0, 0.0, 0.3, 0.0, 0.0]))
SAG_SCENE = {"obstacles": [{"name": "ball", "type": "sphere", "center": [0.30, 0.0, 0.17],
                            "radius": 0.03}]}


def test_a_pcc_plan_replayed_under_gravity_shows_the_error() -> None:
    from cr_nlp import check_many, load_scene, replay_pcc_motion, tip_pose

    scene = load_scene(SAG_SCENE)
    pcc_clearance = check_many(RAO, scene, PCC_MOTION).obstacle_distance
    pcc_tips = np.array([tip_pose(RAO, x)[0] for x in PCC_MOTION])
    assert pcc_clearance.min() > 0.05                      # python-fcl on the PCC shapes
    free = replay_pcc_motion(RAO, PCC_MOTION, scene, dt=0.1)
    assert free.success, free.reason
    assert np.linalg.norm(free.position - pcc_tips, axis=1).max() < 1e-4
    np.testing.assert_allclose(free.clearance, pcc_clearance, atol=1e-4)
    loaded = replay_pcc_motion(RAO, PCC_MOTION, scene, dt=0.1, gravity=GRAVITY)
    assert not loaded.success and "collision" in loaded.reason, loaded.reason
    assert loaded.min_clearance < 0.0 and loaded.violations["clearance"] > 0.0
    sag = np.linalg.norm(loaded.position - pcc_tips, axis=1)
    assert sag.min() > 0.05                                # m: the robot sags by > 5 cm
    # the reported tips are the statics of the replayed tensions (a fresh solve)
    again = solve_statics(RAO, loaded.tensions, gravity=GRAVITY)
    np.testing.assert_allclose(loaded.position, again.tip_position, atol=1e-9)


def test_a_replay_names_the_waypoint_no_tension_reaches() -> None:
    from cr_nlp import replay_pcc_motion

    motion = PCC_MOTION.copy()
    motion[5, 0] = 3.0                                     # rad: beyond τ_max
    result = replay_pcc_motion(RAO, motion, dt=0.1)
    assert not result.success and result.reason.startswith("waypoint 5:"), result.reason
    with pytest.raises(ValueError, match="dt"):
        replay_pcc_motion(RAO, motion)
    # a follow result's dt is its path's
    from types import SimpleNamespace

    followed = SimpleNamespace(q=PCC_MOTION, path=SimpleNamespace(dt=0.2))
    assert replay_pcc_motion(RAO, followed).dt == 0.2
    with pytest.raises(ValueError, match="configurations"):
        replay_pcc_motion(RAO, motion[:, :3], dt=0.1)


DENSE_SCENE = {"obstacles": SCENE["obstacles"] + [
    {"name": "ball_b", "type": "sphere", "center": [-0.10, 0.12, 0.28], "radius": 0.03},
    {"name": "post", "type": "box", "center": [-0.2, -0.05, 0.15], "size": [0.04, 0.1, 0.1]},
    {"name": "ball_c", "type": "sphere", "center": [0.0, 0.15, 0.20], "radius": 0.035},
    {"name": "ball_d", "type": "sphere", "center": [0.18, -0.10, 0.22], "radius": 0.035},
    {"name": "slab", "type": "box", "center": [0.15, 0.15, 0.12], "size": [0.08, 0.08, 0.06]}]}


def test_a_problem_no_single_via_solves_gets_two() -> None:
    from cr_nlp import TensionTrajectoryPlanner

    planner = TensionTrajectoryPlanner(RAO, DENSE_SCENE)
    start = np.array([0.077, 0.0, 0.0, 4.965, 0.662, 0.345])
    goal = np.array([0.0, 5.596, 2.12, 0.0, 1.314, 5.639])
    result = planner.plan(start, goal, gravity=GRAVITY, tip_force=PAYLOAD)[0]
    assert result.success and result.notes[0].startswith("via tension sets "), (
        result.reason, result.notes)
    # no single via of the screened candidates is clear (what sent it to two)
    from cr_nlp.model.loads import static_loads

    loads = static_loads(1, planner.length, PAYLOAD, None, GRAVITY)
    vias = planner.vias(loads)
    cost = np.abs(vias - start).max(axis=1) + np.abs(goal - vias).max(axis=1)
    singles = [planner._legs([start, vias[k], goal]) for k in np.argsort(cost)[:16]]
    assert not planner._screen(singles, loads).any()
    # independent replay: statics at waypoints and midpoints, python-fcl on each
    mids = 0.5 * (result.tensions[1:] + result.tensions[:-1])
    replay = solve_statics(RAO, np.concatenate([result.tensions, mids]), PAYLOAD, None, GRAVITY)
    assert replay.converged.all()
    clearance = check_chains(RAO, planner.scene, replay.positions, 10).obstacle_distance
    assert clearance.min() >= planner.config.safety_margin
    assert np.abs(np.diff(result.tensions, axis=0)).max() / result.dt <= 50.0 + 1e-9


def test_a_path_through_a_narrow_gap_keeps_the_rate_limit_and_the_margin() -> None:
    """A tip path traced by a clear tension motion (70 % of the rate limit) that passes
    between two balls 6 mm from its backbone: followed, the motion is
    verified (fresh statics at waypoints and between them, python-fcl, rates), refined as
    a whole (stage refine), and its rates stay within the limit."""
    from cr_nlp.model.loads import static_loads
    from cr_nlp.tasks.mechanics._motion import verify_tension_motion
    from cr_nlp.tasks.mechanics.follow import TensionFollowConfig

    count, dt = 24, 0.05
    # A planar sweep: the first tendon of each segment (same angle), gravity in the plane.
    motion = np.zeros((count, 6))
    motion[:, 0] = np.linspace(0.5, 3.5, count)
    motion[:, 3] = np.linspace(1.0, 0.4, count)
    rate_max = np.max(np.abs(np.diff(motion, axis=0))) / dt / 0.7   # the motion: 70 %
    truth = solve_statics(RAO, motion, PAYLOAD, None, GRAVITY)
    # Two balls either side of the sweep's plane at the backbone's mid point at the middle
    # waypoint, 6 mm beyond the body's surface: the robot passes between them.
    m, k = count // 2, truth.positions.shape[1] // 2
    moving = truth.positions[m + 1, k] - truth.positions[m - 1, k]
    tangent = truth.positions[m, k + 1] - truth.positions[m, k - 1]
    across = np.cross(moving, tangent)
    across /= np.linalg.norm(across)
    offset = RAO.backbone_radius + 0.005 + 0.006
    scene = {"obstacles": [
        {"name": f"ball_{i}", "type": "sphere", "radius": 0.005,
         "center": (truth.positions[m, k] + sign * offset * across).tolist()}
        for i, sign in enumerate((1.0, -1.0))]}
    follower = TensionPathFollower(RAO, scene, TensionFollowConfig(tension_rate_max=rate_max))
    loads = static_loads(1, follower.ik.length, PAYLOAD, None, GRAVITY)
    traced = verify_tension_motion(RAO, follower.scene, motion, dt, loads, margin=0.002,
                                   rate_max=rate_max)
    assert traced.success and traced.min_clearance < 0.008, (traced.reason,
                                                             traced.min_clearance)
    result = follower.follow(truth.tip_position, dt=dt, gravity=GRAVITY, tip_force=PAYLOAD)
    assert result.success, (result.reason, result.notes)
    assert result.stage.value == "refine"
    assert np.max(np.abs(np.diff(result.tensions, axis=0))) / dt <= rate_max
    assert result.min_clearance >= 0.002
    again = follower.verify(result)
    assert again.success and again.violations["tension_rate"] == 0.0
