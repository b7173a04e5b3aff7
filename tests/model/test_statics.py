"""Loads anywhere and the equilibrium a robot reaches: point wrenches, distributed forces
and buckling against closed forms (Euler–Bernoulli, the elastica), and bad loads named."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import ellipe, ellipk

from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import StaticsConfig, solve_statics
from cr_nlp.model.cosserat import _statics as statics
from cr_nlp.model.cosserat._statics import small_step
from cr_nlp.model.loads import static_loads
from cr_nlp.model.rotations import matrix_from_wxyz

RAO = load_robot("tdcr2_rao2021")
EI = RAO.mechanics.bending_stiffness
LENGTH = 0.4
NO_TENSION = np.zeros(6)


def test_a_point_load_at_the_tip_is_the_tip_load() -> None:
    tensions = np.array([2.0, 0.3, 1.0, 0.2, 1.5, 0.4])
    force, moment = np.array([0.05, -0.1, 0.02]), np.array([0.0, 0.002, 0.001])
    tip = solve_statics(RAO, tensions, force, moment)
    point = solve_statics(RAO, tensions, point_loads=[
        {"s": LENGTH, "force": force.tolist(), "moment": moment.tolist()}])
    assert tip.converged.all() and point.converged.all()
    np.testing.assert_allclose(point.positions, tip.positions, atol=1e-9)
    np.testing.assert_allclose(point.base_force, tip.base_force, atol=1e-12)


@pytest.mark.parametrize("at", [0.13, 0.2, 0.31])
def test_a_point_force_bends_a_straight_rod_as_euler_bernoulli(at: float) -> None:
    """Tip deflection F a² (3L − a) / (6EI) for a load at a from the clamp (at 0.13 and
    0.31 m the load falls between grid points: the case gets its own)."""
    force = 0.01 * EI / LENGTH ** 2  # F L² / EI = 0.01: small deflection
    result = solve_statics(RAO, NO_TENSION, point_loads=[{"s": at, "force": [force, 0, 0]}])
    expected = force * at ** 2 * (3 * LENGTH - at) / (6 * EI)
    assert result.converged.all() and result.stable.all()
    assert result.tip_position[0, 0] == pytest.approx(expected, rel=2e-3)
    assert len(result.arc_length) == result.positions.shape[1]  # the robot's grid points


def test_a_point_moment_turns_the_rod_distal_of_it_only() -> None:
    """A pure moment M at a: the part proximal of a bends as an arc of curvature M/EI, the
    distal part stays straight (tangent at the tip = tangent at a)."""
    at, moment = 0.1, 0.5 * EI / 0.1  # half a radian of bending over 0.1 m
    result = solve_statics(RAO, NO_TENSION, point_loads=[{"s": at, "moment": [0, moment, 0]}])
    angle = moment * at / EI
    # 1 µm and 1 µrad: the RK4 steps' error at this curvature (test_cosserat's arcs)
    np.testing.assert_allclose(result.tip_rotation[0][:, 2],
                               [np.sin(angle), 0, np.cos(angle)], atol=1e-6)
    arc = np.array([(1 - np.cos(angle)) * at / angle, 0, np.sin(angle) * at / angle])
    tip = arc + (LENGTH - at) * np.array([np.sin(angle), 0, np.cos(angle)])
    np.testing.assert_allclose(result.tip_position[0], tip, atol=1e-6)


def test_a_distributed_force_bends_a_straight_rod_as_the_uniform_cantilever() -> None:
    w = 0.01 * EI / LENGTH ** 3  # w L³ / EI = 0.01
    result = solve_statics(RAO, NO_TENSION, distributed_force=[0, w, 0])
    assert result.converged.all()
    assert result.tip_position[0, 1] == pytest.approx(w * LENGTH ** 4 / (8 * EI), rel=2e-3)
    np.testing.assert_allclose(result.base_force[0], [0, w * LENGTH, 0], rtol=1e-12)


def test_gravity_per_case() -> None:
    gravity = np.array([[0, 0, 0], [-9.81, 0, 0], [9.81, 0, 0]])
    result = solve_statics(RAO, NO_TENSION, gravity=gravity)
    x = result.tip_position[:, 0]
    assert x[0] == 0 and x[1] < -1e-4 and x[2] == pytest.approx(-x[1], rel=1e-9)


def _elastica_tip(load: float) -> tuple[float, float]:
    """(lateral, axial) tip position of the buckled clamped–free elastica under an axial
    load P (Timoshenko & Gere §2.7): L √(P/EI) = K(k), k = sin(α/2)."""
    lam = np.sqrt(load / EI)
    m = brentq(lambda m: ellipk(m) - lam * LENGTH, 1e-12, 1 - 1e-12)  # m = k²
    k = np.sqrt(m)
    return 2 * k / lam, (2 * ellipe(m) - ellipk(m)) / lam


def test_a_column_past_its_buckling_load_has_two_equilibria_and_buckles() -> None:
    """Euler: P_cr = π² EI / (4 L²). Below it the straight column is the only equilibrium;
    at 2 P_cr a column loaded from rest with a sideways nudge of 1e-4 P buckles towards
    it, to the elastica's shape, and its mirror image is an equilibrium too."""
    critical = np.pi ** 2 * EI / (4 * LENGTH ** 2)
    below = solve_statics(RAO, NO_TENSION, [1e-4 * 0.8 * critical, 0, -0.8 * critical],
                          all_equilibria=True)
    assert below.equilibria[0] == 1 and below.stable[0]
    assert abs(below.tip_position[0, 0]) < 1e-3 * LENGTH
    load = 2.0 * critical
    above = solve_statics(RAO, NO_TENSION, [1e-4 * load, 0, -load])
    assert above.converged[0] and above.stable[0]
    assert above.equilibria[0] >= 2
    lateral, axial = _elastica_tip(load)
    assert above.tip_position[0, 0] == pytest.approx(lateral, rel=2e-3)  # towards +x
    assert above.tip_position[0, 2] == pytest.approx(axial, abs=2e-3 * LENGTH)
    every = solve_statics(RAO, NO_TENSION, [1e-4 * load, 0, -load], all_equilibria=True)
    shapes = every.all_equilibria[0]
    assert shapes[0].reached and shapes[0].stable
    np.testing.assert_allclose(shapes[0].tip_position, above.tip_position[0], atol=1e-9)
    # The mirror image, buckled the other way, is an equilibrium too; in 3-D an unstable
    # one (it can turn about the load's line towards the nudge).
    mirror = [e for e in shapes if e.tip_position[0] < -0.5 * lateral]
    assert mirror and not any(e.stable for e in mirror)


def test_a_slow_motion_continued_from_its_last_equilibrium_keeps_the_shapes() -> None:
    """``start_moment``: Newton from the previous step's equilibrium lands on the shape
    the loading path from rest finds (one equilibrium here) in fewer iterations."""
    gravity, payload = [0.0, 0.0, -9.81], [0.0, 0.0, -0.005 * 9.81]
    phase = np.linspace(0.0, 1.0, 25)[:, None] * 2 * np.pi - [0.0, 2.1, 4.2]
    tensions = np.concatenate([1.2 + 0.15 * np.cos(phase), 0.4 + 0.1 * np.cos(2 * phase)], 1)
    rest = solve_statics(RAO, tensions, payload, None, gravity)
    assert rest.converged.all() and (rest.equilibria == 1).all()
    continued = solve_statics(RAO, tensions[1:], payload, None, gravity,
                              start_moment=rest.base_moment[:-1])
    np.testing.assert_allclose(continued.positions, rest.positions[1:], atol=1e-9)
    assert continued.stable.all()
    assert continued.iterations.mean() < 0.7 * rest.iterations[1:].mean()


def test_a_batch_with_one_loaded_case_continued_keeps_every_case() -> None:
    """``start_moment`` on a batch whose only loaded case is continued alone: every case
    keeps its row and its loading-path shape (the one-case shortcut once returned that
    case's shape for the whole batch)."""
    tensions = np.array([[2.0, 0.0, 0.5, 0.5, 1.0, 0.0], [2.1, 0.0, 0.5, 0.5, 1.0, 0.0]])
    force = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.05]])
    rest = solve_statics(RAO, tensions, force)
    continued = solve_statics(RAO, tensions, force, start_moment=rest.base_moment)
    assert continued.positions.shape == rest.positions.shape
    np.testing.assert_allclose(continued.positions, rest.positions, atol=1e-9)
    assert continued.tip_moment_jacobian is None  # a batch's solve: none kept


def test_a_one_case_step_started_from_its_neighbours_jacobian_keeps_the_shape() -> None:
    """``start_jacobian``: one case continued from the previous step's equilibrium with
    that step's ``tip_moment_jacobian`` (the stability test's ∂M(L)/∂M(0)) lands on the
    same shape in fewer Newton iterations; the Jacobian is CasADi's exact derivative of
    the rod's tip moment (within 4e-7 of its size here: the stability test sweeps the
    strains once), and a turned base turns it (world frame)."""
    import casadi as ca

    from cr_nlp.model.cosserat._casadi import CasadiRod, RodLoads

    gravity, payload = [0.0, 0.0, -9.81], [0.0, 0.0, -0.005 * 9.81]
    step = np.array([[2.0, 0.0, 0.5, 0.5, 1.0, 0.0], [2.1, 0.0, 0.55, 0.45, 1.05, 0.0],
                     [2.2, 0.0, 0.6, 0.4, 1.1, 0.0]])
    rest = solve_statics(RAO, step, payload, None, gravity)
    first = solve_statics(RAO, step[1], payload, None, gravity,
                          start_moment=rest.base_moment[0])
    jacobian = first.tip_moment_jacobian
    assert jacobian.shape == (1, 3, 3) and rest.tip_moment_jacobian is None
    # CasADi's derivative of M(L) in M(0) at that equilibrium (base frame: identity here)
    rod = CasadiRod(RAO, StaticsConfig(), np.zeros(0))
    m0 = ca.MX.sym("m0", 3)
    tip = rod.integrate(step[1], m0, RodLoads.numeric(payload, None, gravity))["tip_moment"]
    exact = np.asarray(ca.Function("j", [m0], [ca.jacobian(tip, m0)])(first.base_moment[0]))
    np.testing.assert_allclose(jacobian[0], exact, rtol=0, atol=1e-5 * np.abs(exact).max())
    cold = solve_statics(RAO, step[2], payload, None, gravity, start_moment=first.base_moment[0])
    warm = solve_statics(RAO, step[2], payload, None, gravity, start_moment=first.base_moment[0],
                         start_jacobian=jacobian[0])
    np.testing.assert_allclose(warm.positions, rest.positions[2:], atol=1e-9)
    np.testing.assert_allclose(cold.positions, rest.positions[2:], atol=1e-9)
    assert warm.stable[0] and warm.iterations[0] < cold.iterations[0]
    # the base turned 90° about x, the loads with it: the same rod, its Jacobian turned
    from dataclasses import replace

    turn = matrix_from_wxyz(np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0]))
    turned = replace(RAO, base_wxyz=tuple(np.array([np.cos(np.pi / 4), np.sin(np.pi / 4),
                                                    0.0, 0.0])))
    again = solve_statics(turned, step[1], turn @ payload, None, turn @ gravity,
                          start_moment=turn @ rest.base_moment[0])
    np.testing.assert_allclose(again.tip_moment_jacobian[0], turn @ jacobian[0] @ turn.T,
                               atol=1e-9 * np.abs(jacobian).max())
    with pytest.raises(ValueError, match=r"start_jacobian: expected a finite \(3, 3\)"):
        solve_statics(RAO, step[2], payload, None, gravity, start_moment=first.base_moment[0],
                      start_jacobian=np.eye(2))


def test_an_unstable_start_moment_falls_back_to_the_loading_path() -> None:
    """Newton from the mirror image of a buckled column converges to that mirror image,
    which is unstable: the answer is the loading path's, buckled towards the nudge."""
    load = 2.0 * np.pi ** 2 * EI / (4 * LENGTH ** 2)
    force = [1e-4 * load, 0, -load]
    every = solve_statics(RAO, NO_TENSION, force, all_equilibria=True)
    mirror = [e for e in every.all_equilibria[0] if e.tip_position[0] < 0]
    assert mirror and not mirror[0].stable
    answer = solve_statics(RAO, NO_TENSION, force, start_moment=mirror[0].base_moment)
    assert answer.stable[0] and answer.tip_position[0, 0] > 0
    np.testing.assert_allclose(answer.positions, every.positions, atol=1e-9)
    with pytest.raises(ValueError, match=r"start_moment: expected \(3,\) or \(1, 3\)"):
        solve_statics(RAO, NO_TENSION, force, start_moment=[0.0, np.nan, 0.0])


def test_the_small_step_loading_path_reaches_the_full_loads(float64) -> None:
    """The branch check's second try, loading from rest in increments of at most
    ``small_step``, ends at the full loads within the iteration budget, at the one
    equilibrium of a moderately loaded case (a fixed 1/32 needed 32 steps of 24)."""
    config = StaticsConfig()
    tensions = np.array([[2.0, 0.3, 1.0, 0.2, 1.5, 0.4]])
    force = [0.05, -0.1, 0.02]
    base = matrix_from_wxyz(np.asarray(RAO.base_wxyz))
    loads = statics._case_loads(static_loads(1, LENGTH, force).in_base_frame(base))
    path = statics._solve_rows(RAO, config, tensions, loads, np.zeros((1, 3)), np.zeros(1),
                               np.array([[1.0, small_step(config)]]), np.float64)
    assert path.converged[0] and path.stall[0] < 0
    assert path.iterations[0] <= config.max_iterations
    answer = solve_statics(RAO, tensions, force)
    assert answer.equilibria[0] == 1
    np.testing.assert_allclose(path.x[0], answer.base_moment[0] @ base, atol=1e-7)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"point_loads": [{"s": 0.5, "force": [0, 0, 1]}]}, "case 0: point_loads[0].s"),
    ({"point_loads": [[], [{"s": 0.1, "force": [0, np.inf, 0]}]]},
     "case 1: point_loads[0].force[1]"),
    ({"point_loads": [{"s": 0.1, "forse": [0, 0, 1]}]}, "point_loads[0].forse: unknown key"),
    ({"distributed_force": [[0, 0, 0], [0, np.nan, 0]]}, "case 1: distributed_force"),
])
def test_bad_loads_name_the_case_and_the_key(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        solve_statics(RAO, np.zeros((2, 6)), **kwargs)
    with pytest.raises(ValueError, match=r"case 1: tensions: tendon 3"):
        solve_statics(RAO, [[0, 0, 0, 0, 0, 0], [0, 0, -1, 0, 0, 0]])
