"""The exact stage of tension motions (``stages.polish._tension_motion_nlp``, through
``TensionPathFollower.follow`` and ``TensionTrajectoryPlanner.plan`` with ``exact=True``): answers
replayed by fresh JAX statics and python-fcl, never judged by the polish's own numbers.
Robot ``tdcr2_rao2021`` under gravity and a 5 g tip payload; one 8-waypoint path and one
planning problem shared by the tests (each motion's NLP is built once per process)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from cr_nlp import (
    TensionPathFollower,
    TensionTrajectoryConfig,
    TensionTrajectoryPlanner,
    load_result,
)
from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
from cr_nlp.model.loads import static_loads
from cr_nlp.world.check import check_chains
from cr_nlp.world.scene import load_scene

RAO = load_robot("tdcr2_rao2021")
GRAVITY = [0.0, 0.0, -9.81]
PAYLOAD = [0.0, 0.0, -0.005 * 9.81]        # 5 g at the tip, N
DT = 0.05
MARGIN = 0.002


def _traced_motion(count: int = 8) -> np.ndarray:
    """A loop of tensions (N) on both segments, two tendons pulled per segment."""
    t = np.linspace(0.0, 1.0, count)[:, None]
    return np.concatenate([2 + 2 * np.sin(2 * np.pi * t), 1 + np.cos(2 * np.pi * t), 0 * t,
                           1 + t, 0 * t, 2 * t], axis=1)


def _replay(scene, tensions: np.ndarray, rate_max: float, samples_between: int = 2) -> dict:
    """Every constraint of a motion, re-evaluated here: fresh statics at every waypoint and
    ``samples_between`` interpolated tension sets between each pair, python-fcl on each
    solved backbone; the largest violation per family (N, N/s, m) and the waypoints' tips."""
    fractions = np.arange(samples_between + 1) / (samples_between + 1)
    samples = np.concatenate([a + fractions[:, None] * (b - a)
                              for a, b in zip(tensions[:-1], tensions[1:], strict=True)]
                             + [tensions[-1:]])
    solved = solve_statics(RAO, samples, PAYLOAD, None, GRAVITY)
    assert solved.converged.all()
    checked = check_chains(RAO, scene, solved.positions, 10)
    tension_max = RAO.mechanics.tension_max
    return {"bounds": max(float(-tensions.min()), float(tensions.max() - tension_max), 0.0),
            "rate": max(float(np.abs(np.diff(tensions, axis=0)).max() / DT - rate_max), 0.0),
            "clearance": max(MARGIN - float(checked.obstacle_distance.min()), 0.0),
            "self": max(MARGIN - float(checked.self_distance.min(initial=np.inf)), 0.0),
            "tips": solved.tip_position[::samples_between + 1]}


# ---------------------------------------------------------------- following

@pytest.fixture(scope="module")
def case() -> dict:
    """The tip path of the traced motion, its rate limit the motion's own largest rate,
    and a ball 5 mm from the backbone's surface at the middle waypoint."""
    motion = _traced_motion()
    truth = solve_statics(RAO, motion, PAYLOAD, None, GRAVITY)
    m, k = len(motion) // 2, truth.positions.shape[1] // 2
    across = np.cross(truth.positions[m + 1, k] - truth.positions[m - 1, k],
                      truth.positions[m, k + 1] - truth.positions[m, k - 1])
    across /= np.linalg.norm(across)
    centre = truth.positions[m, k] + (RAO.backbone_radius + 0.01 + 0.005) * across
    scene = {"obstacles": [{"name": "ball", "type": "sphere", "radius": 0.01,
                            "center": centre.tolist()}]}
    rate = float(np.abs(np.diff(motion, axis=0)).max() / DT)
    from cr_nlp.tasks.mechanics.follow import TensionFollowConfig

    # The per-waypoint answers alone (no chain refine, branch search or repair), by the LM
    # with the seed IK's full first steps (starting damping 1e-6, not the follower's 1e-2)
    # and its band 2 mm beyond δ: they jump between branches here (118 N/s over the
    # limit), a rate jump for the exact stage to rescue (the default follower keeps this
    # path's rate: tests/tasks/mechanics/test_motion.py).
    config = TensionFollowConfig(tension_rate_max=rate, waypoint_damping=1e-6,
                                 chain_iterations=0, branch_width=0, smooth_passes=0)
    config = dataclasses.replace(config, ik=dataclasses.replace(config.ik,
                                                                clearance_buffer=0.002))
    # The same ball 2.4 mm from the backbone: clear of δ = 2 mm, but inside the LM's band
    # (δ plus 0.5 mm), where the default follower's answer leaves the rate limit.
    near = truth.positions[m, k] + (RAO.backbone_radius + 0.01 + 0.0024) * across
    return {"path": truth.tip_position, "rate": rate, "scene": load_scene(scene),
            "follower": TensionPathFollower(RAO, scene, config), "near": near}


@pytest.fixture(scope="module")
def penalty(case: dict):
    return case["follower"].follow(case["path"], dt=DT, gravity=GRAVITY, tip_force=PAYLOAD)


@pytest.fixture(scope="module")
def exact(case: dict):
    return case["follower"].follow(case["path"], dt=DT, gravity=GRAVITY, tip_force=PAYLOAD,
                                   exact=True)


def test_exact_following_rescues_the_rate_jump_the_penalty_stages_leave(penalty,
                                                                       exact) -> None:
    """The traced motion keeps the rate limit, but the penalty stages' answer jumps between
    branches of the redundant tension sets; Ipopt, with the rate as a constraint, finds a
    motion through the same tips that keeps it."""
    from cr_nlp.stages.polish import MOTION_EXACT_MODE

    assert not penalty.success and "tension rate" in penalty.reason, penalty.reason
    assert exact.success, (exact.reason, exact.notes)
    assert exact.stage == "polish" and exact.exact_mode == MOTION_EXACT_MODE
    assert exact.notes[-1].startswith("polished by Ipopt")
    assert penalty.exact_mode.startswith("none: no Ipopt stage ran")


def test_an_exact_path_replayed_by_fresh_statics_and_fcl_keeps_its_constraints(
        case: dict, exact) -> None:
    replay = _replay(case["scene"], exact.tensions, case["rate"])
    worst = max(v for k, v in replay.items() if k != "tips")
    assert worst <= 1e-6, replay
    assert np.linalg.norm(replay["tips"] - case["path"], axis=1).max() <= 1e-6
    # the ball is where the motion goes: the answer uses the room the margin leaves
    assert exact.min_clearance < 0.005


def test_a_time_limit_keeps_the_penalty_answer(case: dict, penalty) -> None:
    late = case["follower"].follow(case["path"], dt=DT, gravity=GRAVITY, tip_force=PAYLOAD,
                                   exact=True, time_limit=1e-3)
    assert not late.success and late.stage == penalty.stage
    np.testing.assert_array_equal(late.tensions, penalty.tensions)
    assert late.notes[-1].startswith("polish out of time"), late.notes


def test_the_result_file_keeps_the_exact_stage(exact, tmp_path) -> None:
    path = exact.save(tmp_path / "R.json")
    data = json.loads(path.read_text())
    assert data["stage"] == "polish" and "multiple shooting" in data["exact_mode"]
    back = load_result(path)
    assert back.exact_mode == exact.exact_mode and back.stage == exact.stage
    np.testing.assert_array_equal(back.tensions, exact.tensions)


def test_cli_follow_exact_writes_the_polished_motion(case: dict, tmp_path) -> None:
    """``cr-nlp follow --model cosserat --exact`` (no longer refused) on the same path,
    the ball moved closer (``case["near"]``): the default penalty stages break the rate
    there and the exact stage rescues the motion."""
    from cr_nlp.cli.main import main

    path, scene, out = tmp_path / "path.json", tmp_path / "scene.json", tmp_path / "R.json"
    path.write_text(json.dumps({"dt": DT, "poses": [
        {"position": p.tolist(), "wxyz": [1, 0, 0, 0]} for p in case["path"]]}))
    scene.write_text(json.dumps({"obstacles": [
        {"name": "ball", "type": "sphere", "radius": 0.01,
         "center": case["near"].tolist()}]}))
    code = main(["follow", "--model", "cosserat", "--robot", "tdcr2_rao2021", "--path",
                 str(path), "--scene", str(scene), "--gravity", "0,0,-9.81", "--tip-force",
                 f"0,0,{PAYLOAD[2]}", "--tension-rate-max", repr(case["rate"]), "--exact",
                 "--time-limit", "300", "--out", str(out)])
    assert code == 0
    result = load_result(out)
    assert result.success and result.stage == "polish", (result.reason, result.notes)
    assert "multiple shooting" in result.exact_mode


# ---------------------------------------------------------------- planning

SCENE = {"obstacles": [
    {"name": "ball", "type": "sphere", "center": [0.12, 0.0, 0.30], "radius": 0.03},
    {"name": "crate", "type": "box", "center": [0.0, -0.2, 0.2], "size": [0.1, 0.04, 0.1]}]}
START, GOAL = np.array([0, 0, 0, 0, 0, 3.0]), np.array([0, 6.0, 0, 0, 0, 3.0])


@pytest.fixture(scope="module")
def planner() -> TensionTrajectoryPlanner:
    """Exact mode on every motion, also the ones the verdict accepts (its straight leg
    passes through the ball: the plan goes through a via)."""
    return TensionTrajectoryPlanner(RAO, SCENE, TensionTrajectoryConfig(via_pool=128,
                                                                         polish_accepted=True))


def test_an_exact_plan_replayed_by_fresh_statics_and_fcl_keeps_its_constraints(
        planner: TensionTrajectoryPlanner) -> None:
    result = planner.plan(START, GOAL, gravity=GRAVITY, tip_force=PAYLOAD, exact=True)[0]
    assert result.success and result.stage == "polish", (result.reason, result.notes)
    np.testing.assert_array_equal(result.tensions[[0, -1]], np.stack([START, GOAL]))
    replay = _replay(planner.scene, result.tensions, planner.config.tension_rate_max)
    assert max(v for k, v in replay.items() if k != "tips") <= 1e-6, replay
    # a time limit keeps the best verified answer: here the penalty stages' plan
    late = planner.plan(START, GOAL, gravity=GRAVITY, tip_force=PAYLOAD, exact=True,
                        time_limit=1e-3)[0]
    assert late.success
    # kept: the penalty plan ("polish out of time: …"), or Ipopt's last iterate where the
    # verdict accepts it (its note names the status)
    assert ("polish out of time" in late.notes[-1]
            or "Maximum_WallTime_Exceeded" in late.notes[-1]), late.notes


CLUTTER_START = np.array([3.789121, 2.751595, 0.0, 0.89808, 5.689187, 0.0])
CLUTTER_GOAL = np.array([5.039994, 0.0, 0.0, 3.876874, 2.343225, 0.0])


UNMENDED = TensionTrajectoryConfig(repair_rounds=0, blends=())
"""The refine without its repair: the refined motion the verdict rejects stays rejected."""


@pytest.fixture(scope="module")
def clutter() -> dict:
    from cr_nlp.bench.tension_clutter import clutter_scene

    return clutter_scene(RAO, 0)


def test_exact_planning_rescues_the_refined_motion_the_verdict_rejected(clutter) -> None:
    """A problem of ``cr-nlp bench tension --suite clutter`` (16 spheres and boxes, seed 0):
    the banded LM shortens the search's motion, but the verdict finds the shortened motion
    0.7 mm inside δ between its waypoints, so the penalty stages (without their repair
    rounds and blends, which mend this one) keep the search's. Exact mode polishes the
    rejected refined motion (every waypoint and the samples the verdict checks between
    them that come near, each a rod in the NLP; the clearance slots re-assigned as it
    moves through the clutter) and keeps it: verified by fresh statics and python-fcl, a
    shorter tip path."""
    start, goal = CLUTTER_START, CLUTTER_GOAL
    planner = TensionTrajectoryPlanner(RAO, clutter, UNMENDED)
    penalty = planner.plan(start, goal, gravity=GRAVITY, tip_force=PAYLOAD)[0]
    assert penalty.success and penalty.stage == "explore", penalty.notes
    assert "the refined motion was not kept: breaks the clearance" in penalty.notes[-1]
    exact = planner.plan(start, goal, gravity=GRAVITY, tip_force=PAYLOAD, exact=True)[0]
    assert exact.success and exact.stage == "polish", (exact.reason, exact.notes)
    assert "polished by Ipopt from the refined motion" in " ".join(exact.notes)
    np.testing.assert_array_equal(exact.tensions[[0, -1]], np.stack([start, goal]))
    replay = _replay(planner.scene, exact.tensions, planner.config.tension_rate_max)
    assert max(v for k, v in replay.items() if k != "tips") <= 1e-6, replay
    loads = static_loads(1, planner.length, PAYLOAD, None, GRAVITY)
    assert (planner.tip_path(exact.tensions, loads)
            < planner.tip_path(penalty.tensions, loads) - 0.01)


def test_samples_left_out_of_the_nlp_join_where_the_answer_passes_through_them(
        clutter) -> None:
    """The same problem with no sample between waypoints in the NLP at first
    (``sample_margin`` 1 µm): Ipopt's motion then passes through an obstacle between two
    waypoints. With one run the verdict rejects it; with the default rounds the samples the
    fresh statics finds near join the NLP, Ipopt starts again, and the answer keeps every
    constraint at every sample (replayed)."""
    from cr_nlp.stages.polish import TensionMotionPolishConfig

    def planned(rounds: int):
        polish = TensionMotionPolishConfig(sample_margin=1e-6, sample_rounds=rounds)
        planner = TensionTrajectoryPlanner(RAO, clutter, dataclasses.replace(UNMENDED,
                                                                             polish=polish))
        return planner, planner.plan(CLUTTER_START, CLUTTER_GOAL, gravity=GRAVITY,
                                     tip_force=PAYLOAD, exact=True)[0]

    _, once = planned(1)
    assert once.stage != "polish" and "rejected by the verdict" in once.notes[-1], once.notes
    planner, rounds = planned(3)
    assert rounds.success and rounds.stage == "polish", (rounds.reason, rounds.notes)
    replay = _replay(planner.scene, rounds.tensions, planner.config.tension_rate_max)
    assert max(v for k, v in replay.items() if k != "tips") <= 1e-6, replay


# ---------------------------------------------------------------- bad input

def test_bad_inputs_are_named(case: dict, tmp_path, capsys) -> None:
    from cr_nlp.cli.main import main
    from cr_nlp.stages.polish import TensionMotionPolishConfig, polish_tension_motion

    loads = static_loads(1, 0.4, PAYLOAD, None, GRAVITY)
    with pytest.raises(ValueError, match=r"tensions0 \(T ≥ 2, 6\)"):
        polish_tension_motion(RAO, None, np.zeros((3, 4)), loads, dt=DT, rate_max=50.0,
                              margin=MARGIN)
    with pytest.raises(ValueError, match="2 targets for 3 waypoints"):
        polish_tension_motion(RAO, None, np.ones((3, 6)), loads, dt=DT, rate_max=50.0,
                              margin=MARGIN, targets=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="dt > 0"):
        polish_tension_motion(RAO, None, np.ones((3, 6)), loads, dt=0.0, rate_max=50.0,
                              margin=MARGIN)
    unknown = polish_tension_motion(RAO, None, np.full((3, 6), np.nan), loads, dt=DT,
                                    rate_max=50.0, margin=MARGIN)
    assert unknown.status == "non-finite input"
    with pytest.raises(ValueError, match="objective"):
        TensionMotionPolishConfig(objective="shortest")
    with pytest.raises(ValueError, match="slot_rounds must be ≥ 1, got 0"):
        TensionMotionPolishConfig(slot_rounds=0)
    with pytest.raises(ValueError, match="sample_rounds must be ≥ 1, got 0"):
        TensionMotionPolishConfig(sample_rounds=0)
    with pytest.raises(ValueError, match="sample_margin must be > 0 m, got -0.01"):
        TensionMotionPolishConfig(sample_margin=-0.01)
    with pytest.raises(ValueError, match="warm_mu_init must be > 0, got 0.0"):
        TensionMotionPolishConfig(warm_mu_init=0.0)
    with pytest.raises(ValueError, match="fast_from must be ≥ 1, got 0"):
        TensionMotionPolishConfig(fast_from=0)
    with pytest.raises(ValueError, match="time_limit"):
        case["follower"].follow(case["path"], dt=DT, exact=True, time_limit=-1.0)
    with pytest.raises(ValueError, match="time_limit"):
        TensionTrajectoryPlanner(RAO).plan(START, GOAL, exact=True, time_limit=0.0)
    code = main(["plan", "--model", "cosserat", "--robot", "tdcr2_rao2021", "--problems",
                 str(tmp_path / "none.json"), "--time-limit", "5", "--out",
                 str(tmp_path / "R.json")])
    assert code == 2 and "give it with --exact" in capsys.readouterr().err
