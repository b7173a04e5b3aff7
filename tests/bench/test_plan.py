"""The trajectory benchmark's baseline (RRT-Connect) and a tiny benchmark run."""

import numpy as np
import pytest

from cr_nlp.bench._baselines_plan import RRTConnect, RRTConnectConfig
from cr_nlp.model import load_robot, q_to_z, z_to_q
from cr_nlp.stages.explore._roadmap import interpolate_z
from cr_nlp.world import body_gap_tolerance, check_many, clearance_z, load_scene, scene_arrays

from ..conftest import MODELS


@pytest.fixture(scope="module")
def robot():
    return load_robot(MODELS / "robots" / "tdcr3.json")


def test_rrt_connect_solves_an_easy_problem_collision_free(robot):
    scene = load_scene(MODELS / "scenes" / "random_27.json")
    # Two free, moderately bent configurations among the 27 spheres.
    rng = np.random.default_rng(4)
    margin = body_gap_tolerance(robot) + 0.002
    z = np.array(q_to_z(robot, rng.uniform(*robot.q_bounds(), size=(400, robot.dof))))
    z[:, 0::3] *= 0.5
    z[:, 1::3] *= 0.5
    z = z[np.asarray(clearance_z(robot, scene_arrays(scene), z)) >= margin + 0.01]
    za, zb = z[0], z[1]
    q_start, q_goal = np.asarray(z_to_q(robot, np.stack([za, zb])))

    planner = RRTConnect(robot, scene, RRTConnectConfig(seed=0, time_limit=30.0))
    q, result = planner.plan(q_start, q_goal, 20)
    assert result.success and q is not None and q.shape == (20, robot.dof)
    np.testing.assert_array_equal(q[0], q_start)
    np.testing.assert_array_equal(q[-1], q_goal)
    corners = result.path_z
    np.testing.assert_allclose(corners[0], za)
    np.testing.assert_allclose(corners[-1], zb)
    steps = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    assert steps.max() <= planner.config.step + 1e-9
    dense = np.concatenate([interpolate_z(corners[i], corners[i + 1], 8)
                            for i in range(len(corners) - 1)])
    verdict = check_many(robot, scene, np.asarray(z_to_q(robot, dense)))
    assert not verdict.collision.any()


@pytest.mark.slow  # a benchmark run or a repeat of covered work: `pytest -m slow`
def test_plan_benchmark_runs_on_a_tiny_size(tmp_path, monkeypatch):
    from cr_nlp.bench.plan import ROADMAP_OPT, RRT, STRAIGHT_OPT, run_plan_benchmark
    from cr_nlp.tasks.geometry.trajectory import TrajectoryConfig

    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path / "cache"))
    methods = (ROADMAP_OPT, STRAIGHT_OPT, RRT)
    small = TrajectoryConfig(waypoints=8, dt=1.0, guesses=2, iterations=10)
    rows = run_plan_benchmark(pairs_per_scene=1, scenes=("random_27",), out=tmp_path / "out",
                              methods=methods, iteration_budgets=(0, 10), config=small,
                              rrt_config=RRTConnectConfig(time_limit=2.0), progress=False)
    assert [r["method"] for r in rows] == [*methods, *methods]
    assert {r["scene"] for r in rows} == {"random_27", "all"}
    for row in rows:
        assert row["problems"] == 1
        assert 0.0 <= row["success_pct"] <= 100.0
        assert row["success_pct"] <= row["collision_free_pct"] or row["success_pct"] == 0.0
    for row in rows[:2]:       # the planner's rows carry its per-stage seconds per problem
        assert row["query_time"] >= 0.0 and row["lm_time"] > 0.0 and row["programs"] >= 1
        assert 0.0 < row["host_pct"] < 100.0 and row["host_per_1000"] > 0.0
    for name in ("plan.md", "plan.csv", "roadmap_build.csv", "iterations.csv",
                 "iterations.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0
    assert "RRT-Connect" in (tmp_path / "out" / "plan.md").read_text()


def test_search_scaling_times_both_backends_on_the_same_paths(tmp_path, monkeypatch):
    from cr_nlp.bench.plan import search_scaling

    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path / "cache"))
    rows = search_scaling(("random_27",), (1, 6), out=tmp_path / "out", repeats=1)
    assert [r["pairs"] for r in rows] == [1, 6]
    for row in rows:
        assert row["same_lengths"] is True
        assert row["scipy_ms"] > 0.0 and row["device_ms"] > 0.0
    assert "device (ms)" in (tmp_path / "out" / "search.md").read_text()
