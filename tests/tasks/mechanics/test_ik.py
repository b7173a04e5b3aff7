"""Tension-space IK on the Cosserat model: round trips tensions → statics → IK → statics
(checked by a fresh forward solve, not by the result's own numbers), the least-tension
map against its definition, a scene's clearance, the result file and the command."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from cr_nlp import load_result
from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
from cr_nlp.model.loads import static_loads
from cr_nlp.model.tendon_groups import moments_from_tensions, tendon_groups, tensions_from_moments
from cr_nlp.tasks._result import Stage
from cr_nlp.tasks.mechanics.ik import TensionIKConfig, TensionIKResult, TensionIKSolver
from cr_nlp.world.check import check_chains
from cr_nlp.world.scene import load_scene

RAO = load_robot("tdcr2_rao2021")
TENSION_MAX = RAO.mechanics.tension_max


def _random_tensions(count: int, seed: int) -> np.ndarray:
    """1–3 pulled tendons per segment, U[0, 0.8 τ_max] N (some sets co-contract)."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0.0, 0.8 * TENSION_MAX, (count, RAO.n_tendons))
    t[rng.random(t.shape) < 0.4] = 0.0
    return t


@pytest.fixture(scope="module")
def solver() -> TensionIKSolver:
    return TensionIKSolver(RAO, config=TensionIKConfig(pool_size=4096))


def test_least_tensions_give_the_moment_with_two_tendons_per_segment() -> None:
    import jax

    groups = tendon_groups(RAO)
    assert groups is not None
    rng = np.random.default_rng(1)
    d = rng.normal(scale=0.01, size=(200, 2, 2))            # N·m, well below τ_max·r
    with jax.enable_x64(True):
        t = np.asarray(jax.vmap(lambda x: tensions_from_moments(groups, 6, 1e3, x))(d))
    assert (t >= 0).all()
    assert ((t > 0).reshape(200, 2, 3).sum(axis=2) <= 2).all()
    np.testing.assert_allclose(moments_from_tensions(groups, t), d, atol=1e-12)
    # Least: no other non-negative set with that moment has a smaller sum (a third
    # tendon only adds pull that the other two must cancel).
    common = t + 0.5                                         # all three pulled
    np.testing.assert_allclose(moments_from_tensions(groups, common), d, atol=1e-12)
    assert (common.sum(axis=1) > t.sum(axis=1)).all()


def test_round_trip_tensions_statics_ik_statics(solver: TensionIKSolver) -> None:
    truth = solve_statics(RAO, _random_tensions(40, seed=2))
    assert truth.converged.all()
    result = solver.solve(truth.tip_position)
    assert result.success.mean() >= 0.975, [r for r in result.reason if r]
    # Independent of the result's own numbers: solve the answer's tensions afresh.
    again = solve_statics(RAO, result.tensions)
    error = np.linalg.norm(again.tip_position - truth.tip_position, axis=1)
    assert np.all(error[result.success] < 1e-4)
    assert np.median(error) < 1e-8
    assert (result.tensions >= 0).all() and (result.tensions <= TENSION_MAX).all()
    np.testing.assert_allclose(result.tendon_displacements, again.tendon_displacements,
                               atol=1e-12)


def test_a_warm_start_with_its_moment_at_the_base_stays_at_its_equilibrium(
        solver: TensionIKSolver) -> None:
    """Under gravity and a payload M(0) is one of the LM's unknowns. Started from exact
    answers with their equilibria's M(0) (``_lm_carried``: what the follower carries from
    one waypoint to the next), the LM keeps each shape (fresh statics of its answer) and
    returns that M(0); started from the tip moment instead, closing the equilibrium gap
    moves the tensions as well, and the shapes leave by centimetres."""
    from cr_nlp.stages.refine import base_frame

    gravity, payload = [0.0, 0.0, -9.81], [0.0, 0.0, -0.005 * 9.81]
    tensions = _random_tensions(8, seed=3)
    truth = solve_statics(RAO, tensions, payload, None, gravity)
    loads = static_loads(8, solver.length, payload, None, gravity)
    free = np.full((8, 4), np.nan)
    moments = base_frame(RAO, truth.base_moment)
    answer, carried = solver._lm_carried(tensions, truth.tip_position, free, loads, moments)
    again = solve_statics(RAO, answer, payload, None, gravity)
    # (antagonistic sets come back as the least tensions of the same moments: same shape)
    assert np.abs(again.positions - truth.positions).max() < 1e-4
    assert np.linalg.norm(again.tip_position - truth.tip_position, axis=1).max() < 1e-8
    np.testing.assert_allclose(carried, moments, atol=1e-4)
    cold = solve_statics(RAO, solver._lm(tensions, truth.tip_position, free, loads), payload,
                         None, gravity)
    assert np.abs(cold.positions - truth.positions).max() > 0.01


def test_a_solver_with_another_first_damping_runs_the_same_compiled_lm(
        solver: TensionIKSolver) -> None:
    """``with_lm`` (the follower's waypoint and seed LMs) shares the residuals and passes
    the first damping as data: no new program, and its own damping still acts (from the
    same starts its answers differ from the parent's)."""
    from cr_nlp.stages.refine._tension_lm import _lm_waypoints

    truth = solve_statics(RAO, _random_tensions(4, seed=4))
    loads = static_loads(4, solver.length)
    free = np.full((4, 4), np.nan)
    start = np.full((4, RAO.n_tendons), 1.0)
    before = solver._lm(start, truth.tip_position, free, loads)
    programs = len(_lm_waypoints._compiled)
    other = solver.with_lm(initial_damping=10.0)
    after = other._lm(start, truth.tip_position, free, loads)
    assert len(_lm_waypoints._compiled) == programs
    assert not np.allclose(after, before)
    assert other.config.initial_damping == 10.0 != solver.config.initial_damping
    with pytest.raises(ValueError, match="pool_size"):
        solver.with_lm(pool_size=16)


def test_round_trip_under_a_payload_held_mid_body(solver: TensionIKSolver, tmp_path) -> None:
    """A 20 g payload held at 0.25 m from the base, a sideways force on the tip and gravity
    on the backbone; the result file keeps the loads it was solved under."""
    loads = {"gravity": [0.0, 0.0, -9.81], "tip_force": [0.03, -0.02, 0.0],
             "point_loads": [{"s": 0.25, "force": [0.0, 0.0, -0.196]}]}
    truth = solve_statics(RAO, _random_tensions(12, seed=4), **loads)
    result = solver.solve(truth.tip_position, **loads)
    assert result.success.mean() >= 11 / 12, [r for r in result.reason if r]
    again = solve_statics(RAO, result.tensions, **loads)
    error = np.linalg.norm(again.tip_position - truth.tip_position, axis=1)
    assert np.all(error[result.success] < 1e-4)
    # Without the payload, or without the tip force, in the model the same tensions miss:
    # each load was solved for.
    for dropped in ("point_loads", "tip_force"):
        fewer = solve_statics(RAO, result.tensions, **{k: v for k, v in loads.items()
                                                       if k != dropped})
        assert np.median(np.linalg.norm(fewer.tip_position - truth.tip_position, axis=1)) > 1e-3
    back = load_result(result.save(tmp_path / "R.json"))
    assert back.point_loads == [[{**loads["point_loads"][0], "moment": [0.0, 0.0, 0.0]}]] * 12
    np.testing.assert_array_equal(back.gravity, np.tile(loads["gravity"], (12, 1)))
    np.testing.assert_array_equal(back.distributed_force, np.zeros((12, 3)))
    np.testing.assert_array_equal(back.tip_force, np.tile(loads["tip_force"], (12, 1)))
    replayed = solve_statics(RAO, back.tensions, back.tip_force, gravity=back.gravity,
                             point_loads=back.point_loads)
    np.testing.assert_allclose(replayed.tip_position, again.tip_position, atol=1e-12)


def test_an_obstacle_on_the_backbone_fails_the_verdict() -> None:
    truth = solve_statics(RAO, [[3.0, 0, 0, 0, 0, 0]])
    middle = truth.positions[0, len(truth.arc_length) // 3]
    scene = {"obstacles": [{"name": "ball", "type": "sphere", "center": middle.tolist(),
                            "radius": 0.004}]}
    blocked = TensionIKSolver(RAO, scene, TensionIKConfig(pool_size=1024, retry_seeds=0,
                                                          clearance_weight=0.0))
    result = blocked.solve(truth.tip_position)
    # Without its clearance rows the LM does not see obstacles: it reaches the target
    # through the ball, and the verdict (python-fcl on the solved backbone) refuses it.
    assert result.position_error[0] < 1e-4
    assert not result.success[0]
    assert "collision" in result.reason[0], result.reason[0]
    assert result.min_clearance[0] < 0


GRAVITY = [0, 0, -9.81]


@pytest.fixture(scope="module")
def ball_beside() -> tuple:
    """(the target's statics, a scene) where the first answer's backbone touches a ball
    (1 mm deep) and another tension set for the same tip clears it by a few millimetres."""
    truth = solve_statics(RAO, [[3.0, 0, 0, 0, 0, 0]], gravity=GRAVITY)
    plain = TensionIKSolver(RAO, None, TensionIKConfig(pool_size=1024, retry_seeds=0,
                                                       clearance_weight=0.0))
    # Another tension set for the same tip (the redundancy of 2 × 2 bending moments for 3
    # coordinates): its backbone leaves the first one by a few millimetres mid-body.
    loads = static_loads(1, plain.length, None, None, GRAVITY)
    other = plain._lm(np.array([[2.0, 0, 0, 0, 0, 2.0]]), truth.tip_position,
                      np.full((1, 4), np.nan), loads)
    second = solve_statics(RAO, other, gravity=GRAVITY)
    apart = np.linalg.norm(second.positions[0] - truth.positions[0], axis=1)
    k = int(np.argmax(apart))
    assert apart[k] > 0.005
    away = (truth.positions[0, k] - second.positions[0, k]) / apart[k]
    centre = truth.positions[0, k] + away * (RAO.backbone_radius + 0.004 - 0.001)
    return truth, {"obstacles": [{"name": "ball", "type": "sphere", "center": centre.tolist(),
                                  "radius": 0.004}]}


def test_the_clearance_rows_steer_the_backbone_around_an_obstacle(ball_beside) -> None:
    truth, scene = ball_beside
    config = TensionIKConfig(pool_size=1024, retry_seeds=0, clearance_weight=0.0)
    blind = TensionIKSolver(RAO, scene, config).solve(truth.tip_position, gravity=GRAVITY)
    steered_solver = TensionIKSolver(RAO, scene, TensionIKConfig(pool_size=1024))
    steered = steered_solver.solve(truth.tip_position, gravity=GRAVITY)
    assert not blind.success[0], blind.reason[0]
    assert blind.min_clearance[0] < steered_solver.config.safety_margin
    # The same target, by a tension set whose backbone keeps δ from the ball, checked by
    # python-fcl on a fresh statics solve of the answer.
    assert steered.success[0], steered.reason[0]
    assert steered.min_clearance[0] >= steered_solver.config.safety_margin
    again = solve_statics(RAO, steered.tensions, gravity=GRAVITY)
    assert np.linalg.norm(again.tip_position[0] - truth.tip_position[0]) < 1e-4


def test_exact_mode_rescues_an_answer_the_penalty_stage_leaves_in_collision(
        ball_beside, tmp_path) -> None:
    truth, scene = ball_beside
    solver = TensionIKSolver(RAO, scene, TensionIKConfig(pool_size=1024, retry_seeds=0,
                                                         clearance_weight=0.0))
    penalty = solver.solve(truth.tip_position, gravity=GRAVITY)
    exact = solver.solve(truth.tip_position, gravity=GRAVITY, exact=True)
    assert not penalty.success[0] and penalty.stage[0] == Stage.REFINE
    assert exact.success[0], (exact.reason[0], exact.notes[0])
    assert exact.stage[0] == Stage.POLISH and exact.max_violation[0] <= 1e-6
    # Replayed independently: a fresh JAX statics solve of the polished tensions reaches the
    # target, and python-fcl keeps its backbone δ from the ball.
    again = solve_statics(RAO, exact.tensions, gravity=GRAVITY)
    assert np.linalg.norm(again.tip_position[0] - truth.tip_position[0]) < 1e-4
    checked = check_chains(RAO, load_scene(scene), again.positions,
                           (again.positions.shape[1] - 1) // 2)
    assert checked.obstacle_distance[0] >= solver.config.safety_margin - 1e-6
    exact.save(tmp_path / "exact.json")
    written = json.loads((tmp_path / "exact.json").read_text())
    assert written["exact_mode"] == "cosserat multiple shooting"
    assert load_result(tmp_path / "exact.json").stage[0] == Stage.POLISH


def test_result_file_round_trip(solver: TensionIKSolver, tmp_path) -> None:
    truth = solve_statics(RAO, _random_tensions(3, seed=4))
    targets = np.vstack([truth.tip_position, [np.nan, 0, 0]])
    result = solver.solve(targets)
    assert not result.success[3] and "non-finite" in result.reason[3]
    path = result.save(tmp_path / "R.json")
    written = json.loads(path.read_text())
    assert written["kind"] == "tension_ik"
    assert written["exact_mode"].startswith("none: no Ipopt stage ran")
    back = load_result(path)
    assert isinstance(back, TensionIKResult)
    np.testing.assert_array_equal(back.tensions[:3], result.tensions[:3])
    np.testing.assert_array_equal(back.success, result.success)
    assert back.reason == result.reason
    again = TensionIKResult.from_dict(result.to_dict())
    np.testing.assert_array_equal(again.position[:3], result.position[:3])
    header = result.save_csv(tmp_path / "t.csv").read_text().splitlines()[0]
    assert header.split(",")[3:9] == [f"tension_{i}_N" for i in range(1, 7)]
    # a displacement-driven robot's answers also carry its motor commands
    driven = replace(RAO, mechanics=replace(RAO.mechanics, tendon_stiffness=(4000.0,) * 2))
    table = np.genfromtxt(replace(result, robot=driven).save_csv(tmp_path / "c.csv"),
                          delimiter=",", names=True)
    written = np.stack([table[f"command_{i}_m"] for i in range(1, 7)], axis=1)[:3]
    np.testing.assert_allclose(written, result.tendon_displacements[:3]
                               + result.tensions[:3] / 4000.0, atol=2e-9)


def test_cli_ik_model_cosserat(tmp_path) -> None:
    truth = solve_statics(RAO, _random_tensions(4, seed=5))
    targets = tmp_path / "targets.json"
    targets.write_text(json.dumps({"poses": [{"position": p.tolist()}
                                             for p in truth.tip_position]}))
    out, table = tmp_path / "R.json", tmp_path / "t.csv"
    run = subprocess.run([sys.executable, "-m", "cr_nlp.cli", "ik", "--model", "cosserat",
                          "--robot", "tdcr2_rao2021", "--targets", str(targets),
                          "--out", str(out), "--csv", str(table),
                          "--pool-size", "4096"],  # the solver fixture's pool, on disk
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr
    assert "Cosserat" in run.stderr
    result = load_result(out)
    assert result.kind == "tension_ik" and len(result) == 4
    again = solve_statics(RAO, result.tensions)
    ok = result.success
    assert ok.sum() >= 3
    assert np.all(np.linalg.norm(again.tip_position - truth.tip_position, axis=1)[ok] < 1e-4)
    assert len(table.read_text().splitlines()) == 5
    bad = subprocess.run([sys.executable, "-m", "cr_nlp.cli", "ik", "--model", "cosserat",
                          "--robot", "tdcr3", "--targets", str(targets), "--out", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "mechanics" in bad.stderr
