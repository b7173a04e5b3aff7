"""The forward model from motor commands (PCC with slack), checked against closed forms, an
independent minimiser of the same energy, finite differences and the kinematics."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

from cr_nlp.model import ModelFileError, Robot, load_robot, tip_pose
from cr_nlp.model.actuation import (
    Actuation,
    commands_for_configuration,
    configuration_from_commands,
    equilibrium,
    measured_point,
    params_of,
    predict_tip,
    zero_sensitivity,
)


def _calibrated_like(robot: Robot, seed: int = 0, axial: bool = False,
                     shortens: bool = True) -> Robot:
    """A robot with non-trivial actuation parameters (offsets, gains, stiffness), with
    compressible segments where ``axial`` (the compression only taking up the tendons'
    length where not ``shortens``)."""
    rng = np.random.default_rng(seed)
    t, n = robot.n_tendons, robot.n_segments
    act = Actuation(
        zero_offsets=tuple(rng.uniform(-0.1, 0.1, t) * robot.tendons.radius),
        gains=tuple(rng.uniform(0.85, 1.15, t)),
        tendon_angle_deltas=tuple(rng.uniform(-0.05, 0.05, t)),
        segment_stiffness=tuple(np.r_[1.0, rng.uniform(0.5, 2.0, n - 1)]),
        tendon_stiffness_ratio=tuple(rng.uniform(2.0, 10.0, n)),
        axial_stiffness_ratio=tuple(rng.uniform(10.0, 60.0, n)) if axial else (),
        axial_shortens_segments=shortens,
        tip_marker=(0.001, -0.002, 0.008),
    )
    return dataclasses.replace(robot, actuation=act)


def _commands(robot: Robot, rows: int, seed: int = 1) -> np.ndarray:
    """Antagonistic commands as a controller sends them: pulled and released tendons."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, (rows, robot.n_tendons)) * 0.6 * robot.tendons.radius


def test_one_tendon_bends_towards_itself_by_the_closed_form() -> None:
    # One segment, one tendon pulled by p, the others slack: minimise ½θ² + ½κ(p/r − θ)²,
    # θ = κ/(1+κ)·p/r, in the tendon's direction α.
    robot = Robot.from_dict({"segments": [{"length": 0.1, "theta_max": 3.14}],
                             "backbone_radius": 0.005, "points_per_segment": 4,
                             "tendons": {"per_segment": 3, "radius": 0.004,
                                         "offsets": [0.3]},
                             "actuation": {"tendon_stiffness_ratio": 4.0}})
    pull = 0.002
    q = configuration_from_commands(robot, [[-0.005, pull, -0.005]])[0]
    theta_expected = 4.0 / 5.0 * pull / 0.004
    assert q[0] == pytest.approx(theta_expected, rel=1e-12)
    assert q[1] == pytest.approx(0.3 + 2 * np.pi / 3, abs=1e-12)


def test_axial_compression_by_the_closed_forms() -> None:
    # One segment (c = 1), tendon stiffness κ, axial stiffness a. One tendon pulled by w
    # (rad-equivalent), the others slack: cθ = aδ = κs with s = w − θ − δ, so
    # s = w / (1 + κ + κ/a), θ = κs, δ = κs/a; all three pulled alike: no bending and
    # aδ = 3κ(w − δ), δ = 3κw / (a + 3κ). The segment is r·δ shorter.
    r, length, kappa, a = 0.004, 0.1, 4.0, 25.0
    robot = Robot.from_dict({"segments": [{"length": length, "theta_max": 3.14}],
                             "backbone_radius": 0.005, "points_per_segment": 4,
                             "tendons": {"per_segment": 3, "radius": r, "offsets": [0.3]},
                             "actuation": {"tendon_stiffness_ratio": kappa,
                                           "axial_stiffness_ratio": a}})
    pull = 0.002
    w = pull / r
    q = configuration_from_commands(robot, [[-0.005, pull, -0.005], [pull] * 3])
    s = w / (1.0 + kappa + kappa / a)
    assert q[0, 0] == pytest.approx(kappa * s, rel=1e-12)
    assert q[0, 1] == pytest.approx(0.3 + 2 * np.pi / 3, abs=1e-12)
    assert q[0, 2] == pytest.approx(length - r * kappa * s / a, rel=1e-12)
    assert q[1, 0] == pytest.approx(0.0, abs=1e-12)
    assert q[1, 2] == pytest.approx(length - r * 3 * kappa * w / (a + 3 * kappa), rel=1e-12)
    tip = predict_tip(robot, [[pull] * 3])[0]        # straight, shorter, no marker
    np.testing.assert_allclose(tip, [0.0, 0.0, q[1, 2]], atol=1e-12)
    # Take-up only: the same bending (the same energy), the segment keeps its length.
    data = robot.to_dict()
    data["actuation"]["axial_shortens_segments"] = False
    take_up = Robot.from_dict(data)
    q2 = configuration_from_commands(take_up, [[-0.005, pull, -0.005], [pull] * 3])
    np.testing.assert_allclose(q2[:, :2], q[:, :2], atol=1e-12)
    np.testing.assert_allclose(q2[:, 2], [length, length], rtol=1e-15)
    np.testing.assert_allclose(predict_tip(take_up, [[pull] * 3])[0], [0.0, 0.0, length],
                               atol=1e-12)


def test_incompressible_is_the_limit_of_axial_compression() -> None:
    robot = _calibrated_like(load_robot("ftdcr_v6"), seed=2)
    stiff = dataclasses.replace(robot, actuation=dataclasses.replace(
        robot.actuation, axial_stiffness_ratio=(1e12,) * 3))
    cmd = _commands(robot, 20)
    np.testing.assert_allclose(predict_tip(stiff, cmd), predict_tip(robot, cmd), atol=1e-9)
    soft = dataclasses.replace(stiff, actuation=dataclasses.replace(
        robot.actuation, axial_stiffness_ratio=(20.0,) * 3))
    assert np.max(np.linalg.norm(predict_tip(soft, cmd) - predict_tip(robot, cmd),
                                 axis=1)) > 1e-4


@pytest.mark.parametrize("axial", [False, True])
def test_equilibrium_minimises_the_energy_found_by_an_independent_solver(axial: bool) -> None:
    robot = _calibrated_like(load_robot("ftdcr_v6"), axial=axial)
    cmd = _commands(robot, 6)
    p = params_of(robot)
    act = robot.actuation
    u = configuration_from_commands(robot, cmd)
    r = robot.tendons.radius
    alpha = np.array([[2 * np.pi * (j % 3) / 3 + robot.tendons.offsets[j // 3]
                       + act.tendon_angle_deltas[j]] * 3 for j in range(9)])
    runs = np.array([[1.0 if i <= j // 3 else 0.0 for i in range(3)] for j in range(9)])
    lengths = p["lengths"]
    c = np.array(act.segment_stiffness) * lengths.sum() / lengths
    a = np.array(act.axial_stiffness_ratio) if axial else np.zeros(3)
    for row, q in zip(cmd, u, strict=True):
        w = np.array(act.gains) * (row - np.array(act.zero_offsets)) / r

        def energy(v: np.ndarray, w: np.ndarray = w) -> float:
            bend = v[:6].reshape(3, 2)
            squeeze = np.r_[v[6:], np.zeros(9 - len(v))]    # compression / r
            short = (np.cos(alpha) * runs * bend[None, :, 0]
                     + np.sin(alpha) * runs * bend[None, :, 1]).sum(axis=1)
            stretch = np.maximum(w - short - runs @ squeeze, 0.0)
            kappa = np.repeat(act.tendon_stiffness_ratio, 3)
            return 0.5 * float(np.sum(c[:, None] * bend * bend) + np.sum(kappa * stretch ** 2)
                               + np.sum(a * squeeze ** 2))

        size = 9 if axial else 6
        best = minimize(energy, np.zeros(size), method="Powell",
                        options={"xtol": 1e-12, "ftol": 1e-15, "maxfev": 80000}).x
        ours = np.r_[np.stack([q[0::3] * np.cos(q[1::3]), q[0::3] * np.sin(q[1::3])],
                              -1).ravel(), (lengths - q[2::3]) / r][:size]
        assert energy(ours) <= energy(best) + 1e-12
        np.testing.assert_allclose(ours, best, atol=1e-5)


@pytest.mark.parametrize("axial", [False, True])
def test_a_released_tendon_never_pushes(axial: bool) -> None:
    robot = _calibrated_like(load_robot("ftdcr_v6"), axial=axial)
    cmd = _commands(robot, 40)
    base = predict_tip(robot, cmd)
    with jax.enable_x64(True):
        jp = {k: jnp.asarray(v) for k, v in params_of(robot).items()}
        pull = jp["gains"] * (cmd - jp["zero_offsets"]) / jp["radius"]
        u, lengths = equilibrium(robot, jp, jnp.asarray(cmd))
        from cr_nlp.model.actuation import _routing, _Topology, tendon_segments

        shortening = np.asarray(u.reshape(len(cmd), -1) @ _routing(_Topology.of(robot), jp).T)
        squeeze = (np.asarray(jp["lengths"]) - np.asarray(lengths)) / robot.tendons.radius
        shortening = shortening + squeeze @ tendon_segments(robot).T
    assert (squeeze > 1e-6).any() == axial
    slack = np.asarray(pull) < shortening - 1e-9
    assert slack.any() and (~slack).any()
    released = cmd - np.where(slack, 0.003, 0.0)       # slack tendons released by 3 mm
    np.testing.assert_allclose(predict_tip(robot, released), base, atol=1e-12)
    pulled = cmd + np.where(~slack, 0.0005, 0.0)        # taut tendons pulled: the tip moves
    assert np.min(np.linalg.norm(predict_tip(robot, pulled) - base, axis=1)) > 1e-6


def test_implicit_derivatives_match_finite_differences() -> None:
    robot = _calibrated_like(load_robot("ftdcr_v6"), axial=True)
    cmd = jnp.asarray(_commands(robot, 5))
    with jax.enable_x64(True):
        p0 = {k: jnp.asarray(v) for k, v in params_of(robot).items()}

        @jax.jit
        def f(x: jax.Array) -> jax.Array:
            p = dict(p0, gains=p0["gains"] * (1 + x[0]), log_kappa=p0["log_kappa"] + x[1],
                     lengths=p0["lengths"] * (1 + x[2]), radius=p0["radius"] * (1 + x[3]),
                     log_axial=p0["log_axial"] + x[4])
            return measured_point(robot, p, cmd)

        x = jnp.zeros(5)
        jac = jax.jit(jax.jacfwd(f))(x)
        jac_rev = jax.jit(jax.jacrev(f))(x)
        h = 1e-6
        fd = jnp.stack([(f(x.at[k].set(h)) - f(x.at[k].set(-h))) / (2 * h) for k in range(5)],
                       axis=-1)
    assert float(jnp.max(jnp.abs(jac[..., 4]))) > 1e-6   # the compression moves the tip
    np.testing.assert_allclose(jac, fd, atol=1e-7)
    np.testing.assert_allclose(jac_rev, jac, atol=1e-10)


def test_zero_sensitivity_is_the_tip_motion_per_zero_error_of_robot_files() -> None:
    """Against central differences of ``predict_tip`` on robot files whose zero offsets are
    shifted one tendon at a time: the largest singular value of that 3 × n Jacobian."""
    robot = _calibrated_like(load_robot("ftdcr_v6"), axial=True, shortens=False)
    cmd = _commands(robot, 4, seed=3)
    h = 1e-7
    zeros = np.array(robot.actuation.zero_offsets)
    columns = []
    for j in range(robot.n_tendons):
        tips = [predict_tip(dataclasses.replace(robot, actuation=dataclasses.replace(
                    robot.actuation, zero_offsets=tuple(zeros + sign * h * np.eye(9)[j]))), cmd)
                for sign in (1, -1)]
        columns.append((tips[0] - tips[1]) / (2 * h))
    expected = np.linalg.norm(np.stack(columns, axis=-1), ord=2, axis=(1, 2))
    got = zero_sensitivity(robot, cmd)
    assert got.dtype == np.float64 and got.shape == (4,)
    assert np.all(expected > 1.0)            # a zero error moves the tip more than itself
    np.testing.assert_allclose(got, expected, rtol=1e-5)


def test_commands_for_a_configuration_reproduce_its_bending_on_compressed_segments() -> None:
    robot = _calibrated_like(load_robot("ftdcr_v6"), seed=3, axial=True)
    rng = np.random.default_rng(5)
    q = np.zeros((50, 9))
    q[:, 0::3] = rng.uniform(0.0, 1.0, (50, 3))
    q[:, 1::3] = rng.uniform(-np.pi, np.pi, (50, 3))
    q[:, 2::3] = [s.length_min for s in robot.segments]
    cmd = commands_for_configuration(robot, q)
    back = configuration_from_commands(robot, cmd)
    bend = lambda v: np.stack([v[:, 0::3] * np.cos(v[:, 1::3]),  # noqa: E731
                               v[:, 0::3] * np.sin(v[:, 1::3])], -1)
    np.testing.assert_allclose(bend(back), bend(q), atol=1e-10)
    shorter = q[:, 2::3] - back[:, 2::3]
    assert (shorter > 0).all()
    # Arcs of the same angles, shorter: the tip moves by at most the total compression.
    gap = np.linalg.norm(tip_pose(robot, back)[0] - tip_pose(robot, q)[0], axis=1)
    assert (gap <= shorter.sum(axis=1) + 1e-12).all()


@pytest.mark.parametrize("axial", [False, True])
def test_commands_for_a_configuration_reproduce_it(axial: bool) -> None:
    # Incompressible, or compression that only takes up the tendons' length.
    robot = _calibrated_like(load_robot("ftdcr_v6"), seed=3, axial=axial, shortens=False)
    rng = np.random.default_rng(4)
    q = np.zeros((50, 9))
    q[:, 0::3] = rng.uniform(0.0, 1.0, (50, 3))
    q[:, 1::3] = rng.uniform(-np.pi, np.pi, (50, 3))
    q[:, 2::3] = [s.length_min for s in robot.segments]
    for slack in (0.0, 0.002):
        cmd = commands_for_configuration(robot, q, slack=slack)
        back = configuration_from_commands(robot, cmd)
        pos, _ = tip_pose(robot, q)
        pos_back, _ = tip_pose(robot, back)
        np.testing.assert_allclose(pos_back, pos, atol=1e-10)
        np.testing.assert_allclose(back[:, 2::3], q[:, 2::3], rtol=1e-15)


def test_nominal_straight_and_predict_in_the_measurement_frame() -> None:
    robot = dataclasses.replace(load_robot("tdcr3"), base_position=(0.1, 0.2, 0.3))
    tip = predict_tip(robot, np.zeros((2, 9)))
    np.testing.assert_allclose(tip, [[0.1, 0.2, 3.3]] * 2, atol=1e-12)
    with pytest.raises(ValueError, match=r"\(N, 9\)"):
        predict_tip(robot, np.zeros((2, 8)))


def test_actuation_block_round_trips_and_is_validated(tmp_path) -> None:
    for axial, shortens in ((False, True), (True, True), (True, False)):
        robot = _calibrated_like(load_robot("ftdcr_v6"), axial=axial, shortens=shortens)
        again = Robot.from_dict(json.loads(json.dumps(robot.to_dict())))
        assert again == robot
        assert ("axial_stiffness_ratio" in robot.to_dict()["actuation"]) == axial
        assert ("axial_shortens_segments" in robot.to_dict()["actuation"]) != shortens
    bad = robot.to_dict()
    bad["actuation"]["axial_shortens_segments"] = "no"
    with pytest.raises(ModelFileError, match="axial_shortens_segments.*true or false"):
        Robot.from_dict(bad)
    bad = _calibrated_like(load_robot("ftdcr_v6")).to_dict()
    bad["actuation"]["axial_shortens_segments"] = False
    with pytest.raises(ModelFileError, match="axial_shortens_segments.*axial_stiffness"):
        Robot.from_dict(bad)
    bad = robot.to_dict()
    bad["actuation"]["axial_stiffness_ratio"] = [10.0, 0.0, 2.0]
    with pytest.raises(ModelFileError, match="axial_stiffness_ratio.*positive"):
        Robot.from_dict(bad)
    bad = robot.to_dict()
    bad["actuation"]["gains"] = [1.0] * 8
    with pytest.raises(ModelFileError, match=r"actuation\.gains"):
        Robot.from_dict(bad)
    bad = robot.to_dict()
    bad["actuation"]["tendon_stiffness_ratio"] = [1.0, -1.0, 2.0]
    with pytest.raises(ModelFileError, match="tendon_stiffness_ratio.*positive"):
        Robot.from_dict(bad)
    bad = robot.to_dict()
    bad["actuation"]["gain"] = 1.0
    with pytest.raises(ModelFileError, match=r"actuation\.gain.*unknown"):
        Robot.from_dict(bad)


@pytest.mark.slow  # two IK compilations (API float64, CLI float32): ~50 s on a loaded CPU
def test_ik_answers_carry_motor_commands_that_reproduce_them(tmp_path) -> None:
    from cr_nlp.cli import main
    from cr_nlp.tasks.geometry.ik import IKConfig, IKSolver

    robot = dataclasses.replace(_calibrated_like(load_robot("ftdcr_v6"), seed=5),
                                base_position=(0.01, -0.02, 0.0))
    robot = dataclasses.replace(robot, actuation=dataclasses.replace(
        robot.actuation, tip_marker=(0.0, 0.0, 0.0), model_error_p95=0.004))
    q = np.array([[0.5, 0.3, 0.1, 0.4, 2.0, 0.1, 0.9, -1.0, 0.022],
                  [0.2, -2.0, 0.1, 0.7, 0.5, 0.1, 0.3, 3.0, 0.022]])
    pos, rot = tip_pose(robot, q)
    from cr_nlp.model.rotations import wxyz_from_matrix

    wxyz = np.array([wxyz_from_matrix(r) for r in rot])
    result = IKSolver(robot, None, IKConfig(pool_size=512)).solve(pos, wxyz)
    assert result.success.all()
    d = result.tendon_displacements
    assert d.shape == (2, 9)
    np.testing.assert_allclose(predict_tip(robot, d), result.position, atol=1e-9)
    assert np.max(np.linalg.norm(predict_tip(robot, d) - pos, axis=1)) < 1e-3
    rows = result.to_dict()["results"]
    np.testing.assert_allclose(rows[1]["tendon_displacements"], d[1])
    # The command line: --csv writes them, --model-margin auto reads the calibrated p95.
    robot_file, targets = tmp_path / "robot.json", tmp_path / "targets.json"
    robot_file.write_text(json.dumps(robot.to_dict()))
    targets.write_text(json.dumps({"poses": [{"position": p.tolist(), "wxyz": w.tolist()}
                                             for p, w in zip(pos, wxyz, strict=True)]}))
    assert main(["ik", "--robot", str(robot_file), "--targets", str(targets), "--out",
                 str(tmp_path / "r.json"), "--csv", str(tmp_path / "d.csv"),
                 "--model-margin", "auto"]) == 0
    written = np.loadtxt(tmp_path / "d.csv", delimiter=",", skiprows=1)[:, 1:]
    q_cli = np.array([r["q"] for r in json.loads((tmp_path / "r.json").read_text())["results"]])
    np.testing.assert_allclose(predict_tip(robot, written), tip_pose(robot, q_cli)[0],
                               atol=1e-8)


def test_results_of_a_calibrated_robot_carry_motor_commands(tmp_path) -> None:
    from cr_nlp.tasks.geometry.ik import IKResult
    from cr_nlp.tasks.geometry.trajectory import TrajectoryResult

    robot = _calibrated_like(load_robot("ftdcr_v6"), seed=6)
    q = np.array([[0.5, 0.3, 0.1, 0.4, 2.0, 0.1, 0.9, -1.0, 0.022],
                  [np.nan] * 9])
    pos, _ = tip_pose(robot, q[:1])
    ik = IKResult(robot, q, *(np.zeros((2, k)) for k in (3, 4)), *(np.zeros(2),) * 5,
                  np.ones(2, bool), np.ones(2, bool), ["refine"] * 2, ["", "failed"])
    rows = ik.to_dict()["results"]
    assert rows[1]["tendon_displacements"] is None
    marker = dataclasses.replace(robot, actuation=dataclasses.replace(
        robot.actuation, tip_marker=(0.0, 0.0, 0.0)))
    np.testing.assert_allclose(predict_tip(marker, [rows[0]["tendon_displacements"]]), pos,
                               atol=1e-10)
    plan = TrajectoryResult(robot, np.repeat(q[:1], 3, axis=0), 0.1, True, "", "refine",
                            tendon_lengths=np.zeros((3, 9)))
    plan.save_csv(tmp_path / "plan.csv")
    header = (tmp_path / "plan.csv").read_text().splitlines()[0].split(",")
    assert header[10:] == [f"{name}_displacement" for name in header[1:10]]
    assert "tendon_displacements" in plan.to_dict()["results"][0]
    plain = IKResult(load_robot("ftdcr_v6"), q, *(np.zeros((2, k)) for k in (3, 4)),
                     *(np.zeros(2),) * 5, np.ones(2, bool), np.ones(2, bool), ["refine"] * 2,
                     ["", ""])
    assert plain.tendon_displacements is not None   # the bundled file has an actuation block
