"""Displacement-driven Cosserat statics: the tensions it finds meet the commands on the
tension statics' own shapes, slack tendons carry nothing, bad inputs are named; the
per-segment stiffness and take-up of the mechanics block."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cr_nlp.model import ModelFileError, Robot, load_robot
from cr_nlp.model.cosserat import motor_commands, solve_displacement_statics, solve_statics

RAO = load_robot("tdcr2_rao2021")
K = 4000.0  # N/m
ROBOT = replace(RAO, mechanics=replace(RAO.mechanics, tendon_stiffness=(K, 2 * K)))
GRAVITY = [0.0, 0.0, -9.81]
COMMANDS = np.array([
    [0.002, 0.0, 0.0, 0.0, 0.0, 0.0],            # one tendon pulled: its antagonists engage
    [0.003, -0.002, -0.002, 0.0, 0.0015, 0.0],   # two tendons released by 2 mm
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],              # at the zeros: gravity alone, all slack
    [0.001, 0.001, 0.001, 0.002, 0.0, 0.0],      # a common pull on segment 1
])


@pytest.fixture(scope="module")
def solved() -> tuple:
    return solve_displacement_statics(ROBOT, COMMANDS, gravity=GRAVITY), \
        np.array([K, K, K, 2 * K, 2 * K, 2 * K])


def test_tensions_meet_the_commands_on_the_tension_statics_shape(solved: tuple) -> None:
    result, k = solved
    assert result.converged.all() and result.stable.all()
    check = solve_statics(ROBOT, result.tensions, gravity=GRAVITY)
    assert np.abs(check.positions - result.positions).max() <= 1e-6
    # the tension statics' own tendon shortening: τ = k · max(0, pull − shortening)
    stretch = COMMANDS - check.tendon_displacements
    np.testing.assert_allclose(result.tensions, k * np.maximum(0.0, stretch), atol=1e-9 * K)
    assert (result.tensions[[0, 1, 3]].max(axis=1) > 0.1).all()


def test_motor_commands_invert_the_solve(solved: tuple) -> None:
    result, _ = solved
    commands = motor_commands(ROBOT, result.tensions, result.tendon_displacements)
    taut = ~result.slack
    np.testing.assert_allclose(commands[taut], COMMANDS[taut], atol=1e-9)
    # a slack tendon's command leaves it just taut: at least what was commanded
    assert (commands[~taut] >= COMMANDS[~taut]).all()


def test_a_slack_tendon_carries_no_tension(solved: tuple) -> None:
    result, _ = solved
    assert result.slack[1, 1] and result.slack[1, 2]
    assert result.tensions[1, 1] == 0.0 and result.tensions[1, 2] == 0.0
    assert (result.tensions[2] == 0.0).all() and result.slack[2].all()
    # gravity alone sags the robot along the base axis; nothing bends it sideways
    assert np.abs(result.tip_position[2, :2]).max() < 1e-9
    assert (result.tensions >= 0.0).all()


def test_pulling_a_tendon_bends_the_tip_towards_it(solved: tuple) -> None:
    result, _ = solved
    # tendon 1 sits at 90° (the offset): +y
    assert result.tip_position[0, 1] > 0.02 and abs(result.tip_position[0, 0]) < 1e-9


def test_bad_inputs_are_named() -> None:
    with pytest.raises(ValueError, match="6 tendons"):
        solve_displacement_statics(ROBOT, np.zeros((2, 5)))
    with pytest.raises(ValueError, match="case 1: displacements: tendon 3"):
        solve_displacement_statics(ROBOT, np.array([[0.0] * 6, [0, 0, np.nan, 0, 0, 0]]))
    with pytest.raises(ValueError, match="mechanics"):
        solve_displacement_statics(load_robot("tdcr3"), np.zeros(9))
    with pytest.raises(ValueError, match="mechanics.tendon_stiffness"):
        solve_displacement_statics(RAO, np.zeros(6))
    with pytest.raises(ValueError, match="tendon_stiffness"):
        solve_displacement_statics(ROBOT, np.zeros(6), tendon_stiffness=[1.0, -1.0])


def test_segment_stiffness_scales_the_bending_of_its_segment() -> None:
    data = RAO.to_dict()
    data["segments"] = data["segments"][:1]
    data["tendons"]["offsets"] = data["tendons"]["offsets"][:1]
    data["mechanics"]["disks_per_segment"] = [10]
    data["mechanics"]["segment_stiffness"] = [2.0]
    robot = Robot.from_dict(data)
    ei = robot.mechanics.bending_stiffness
    result = solve_statics(robot, np.zeros(3), tip_moment=[0.2 * ei, 0.0, 0.0])
    # a pure moment M bends an arc of curvature M / (2 E I): 0.02 rad over 0.2 m
    kappa = 0.1
    s = result.arc_length
    arc = np.stack([0 * s, -(1 - np.cos(kappa * s)) / kappa, np.sin(kappa * s) / kappa], -1)
    np.testing.assert_allclose(result.positions[0], arc, atol=1e-9)


@pytest.mark.parametrize("field, value", [("segment_stiffness", [1.0, 0.0]),
                                          ("tendon_stiffness", [1.0]),
                                          ("tendon_take_up", [1e-4, -1e-4])])
def test_mechanics_stiffness_fields_are_checked_and_round_trip(field: str,
                                                               value: object) -> None:
    data = RAO.to_dict()
    data["mechanics"][field] = value
    with pytest.raises(ModelFileError, match=f"mechanics.{field}"):
        Robot.from_dict(data)
    data["mechanics"][field] = 3.0  # one number stands for every segment
    robot = Robot.from_dict(data)
    assert getattr(robot.mechanics, field) == (3.0, 3.0)
    assert Robot.from_dict(robot.to_dict()) == robot


TAKE_UP = (2e-4, 1e-4)  # m/N per segment
TAKEN = replace(ROBOT, mechanics=replace(ROBOT.mechanics, tendon_take_up=TAKE_UP))


@pytest.fixture(scope="module")
def taken() -> object:
    return solve_displacement_statics(TAKEN, COMMANDS, gravity=GRAVITY)


def test_the_take_up_shortens_every_tendon_through_a_segment_by_its_load(
        taken: object, solved: tuple) -> None:
    result, k = taken, solved[1]
    assert result.converged.all() and result.stable.all()
    check = solve_statics(TAKEN, result.tensions, gravity=GRAVITY)  # tensions alone
    assert np.abs(check.positions - result.positions).max() <= 1e-6
    # segment 1 carries every tension, segment 2 its own tendons' (4-6); tendons 1-3 run
    # through segment 1 only, tendons 4-6 through both
    t = result.tensions
    carried = np.stack([t.sum(axis=1), t[:, 3:].sum(axis=1)], axis=1)
    lost = np.where(np.arange(6) < 3, TAKE_UP[0] * carried[:, :1],
                    TAKE_UP[0] * carried[:, :1] + TAKE_UP[1] * carried[:, 1:])
    stretch = COMMANDS - check.tendon_displacements - lost
    np.testing.assert_allclose(t, k * np.maximum(0.0, stretch), atol=1e-9 * K)
    np.testing.assert_allclose(result.stretch, stretch, atol=1e-9)
    # it matters: the same commands pull with less tension than without the take-up
    assert (t[[0, 1, 3]].sum(axis=1) < 0.9 * solved[0].tensions[[0, 1, 3]].sum(axis=1)).all()


def test_motor_commands_invert_the_solve_with_the_take_up(taken: object) -> None:
    result = taken
    commands = motor_commands(TAKEN, result.tensions, result.tendon_displacements)
    taut = ~result.slack
    np.testing.assert_allclose(commands[taut], COMMANDS[taut], atol=1e-9)


def test_one_taut_tendon_takes_up_like_a_softer_tendon_in_series() -> None:
    # tendon 1 alone taut runs through segment 1 only: its take-up c₁τ is a compliance in
    # series with the tendon, k' = 1 / (1/k + c₁)
    command = [0.003, -0.01, -0.01, -0.01, -0.01, -0.01]  # the others well slack
    a = solve_displacement_statics(TAKEN, command)
    softer = [1.0 / (1.0 / K + TAKE_UP[0]), K, K, 2 * K, 2 * K, 2 * K]
    b = solve_displacement_statics(ROBOT, command, tendon_stiffness=softer)
    assert a.converged.all() and a.slack[0, 1:].all() and a.tensions[0, 0] > 1.0
    np.testing.assert_allclose(a.tensions, b.tensions, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(a.positions, b.positions, atol=1e-9)


def test_a_tension_motion_of_a_displacement_driven_robot_writes_its_commands(
        solved: tuple, tmp_path) -> None:
    from cr_nlp.tasks.mechanics.trajectory import TensionTrajectoryResult

    result, _ = solved
    rows = len(COMMANDS)
    motion = TensionTrajectoryResult(
        robot=ROBOT, tensions=result.tensions, dt=0.1, position=result.tip_position,
        wxyz=np.tile([1.0, 0, 0, 0], (rows, 1)), backbone=result.positions,
        clearance=np.full(rows, np.inf), min_clearance=np.inf, max_violation=0.0,
        success=True, reason="", tip_force=np.zeros(3), tip_moment=np.zeros(3),
        gravity=np.array(GRAVITY), distributed_force=np.zeros(3), point_loads=[],
        tension_rate_max=10.0, tendon_displacements=result.tendon_displacements)
    table = np.genfromtxt(motion.save_csv(tmp_path / "motion.csv"), delimiter=",",
                          names=True)
    written = np.stack([table[f"command_{j + 1}_m"] for j in range(6)], axis=1)
    taut = ~result.slack
    np.testing.assert_allclose(written[taut], COMMANDS[taut], atol=2e-9)


def test_cases_left_after_the_first_round_continue_where_they_were(
        solved: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    from cr_nlp.model.cosserat import _displacement as displacement_statics

    monkeypatch.setattr(displacement_statics, "_FIRST_ROUND", 1)
    again = solve_displacement_statics(ROBOT, COMMANDS[[0, 3]], gravity=GRAVITY)
    assert again.converged.all() and (again.iterations > 1).all()
    np.testing.assert_allclose(again.tensions, solved[0].tensions[[0, 3]], atol=1e-9)


def test_the_newton_steps_linear_solve_pivots_like_lapack(float64) -> None:
    import jax
    import jax.numpy as jnp

    from cr_nlp.model.cosserat._displacement import pivoted_solve

    rng = np.random.default_rng(3)
    a = rng.normal(size=(64, 12, 12))
    a[:, 0, 0] = 0.0           # no elimination without a row swap
    a[:8] *= np.logspace(0, 6, 12)  # badly scaled columns
    b = rng.normal(size=(64, 12))
    x = np.asarray(jax.jit(jax.vmap(pivoted_solve))(jnp.asarray(a), jnp.asarray(b)))
    want = np.linalg.solve(a, b[..., None])[..., 0]
    np.testing.assert_allclose(x, want, rtol=1e-9, atol=1e-12)
