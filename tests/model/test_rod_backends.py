"""One rod, two backends: the Cosserat rod's RK4 steps evaluated by JAX (the statics) and by
CasADi (``model.cosserat.CasadiRod``) give the same backbone, tip moment and tendon lengths
on random tensions and loads (gravity, tip force and moment, a force per metre, point
loads between and on grid points)."""

from __future__ import annotations

import json
from pathlib import Path

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import CasadiRod, RodLoads, StaticsConfig, solve_statics
from cr_nlp.model.cosserat._rod import CaseLoads, _integrate, _layout
from cr_nlp.model.loads import static_loads
from cr_nlp.model.rotations import matrix_from_wxyz

RAO = load_robot("tdcr2_rao2021")
ROBOT_FILE = Path(__file__).resolve().parents[2] / "models" / "robots" / "tdcr2_rao2021.json"


def _shared_tilted():
    """The same rod with shared routing (every tendon to the tip) on a tilted, moved base."""
    data = json.loads(ROBOT_FILE.read_text())
    data["name"] = "tdcr2_shared_tilted"
    data["tendons"]["routing"] = "shared"
    data["base"] = {"position": [0.1, -0.05, 0.2],
                    "wxyz": [np.cos(0.3), np.sin(0.3) / np.sqrt(2), np.sin(0.3) / np.sqrt(2), 0.0]}
    return load_robot(data)


def _random_case(rng: np.random.Generator, tendons: int, points: int) -> dict:
    tension = np.zeros(tendons)
    pulled = rng.choice(tendons, size=min(tendons, 4), replace=False)
    tension[pulled] = rng.uniform(0.0, 4.0, pulled.size)
    return {
        "tension": tension,
        "tip_force": rng.normal(size=3) * 0.04,
        "tip_moment": rng.normal(size=3) * 0.004,
        "gravity": np.array([0.0, 0.0, -9.81]) + rng.normal(size=3),
        "distributed": rng.normal(size=3) * 0.05,
        # one point load between grid points, one on a grid point (0.2 m: the junction)
        "point_s": np.array([0.137, 0.2])[:points],
        "point_force": rng.normal(size=(points, 3)) * 0.03,
        "point_moment": rng.normal(size=(points, 3)) * 0.003,
    }


@pytest.mark.parametrize("points", [0, 2])
def test_casadi_rod_integrates_as_the_jax_rod(points: int) -> None:
    """From the same M(0) (any, not only an equilibrium) the two passes agree at every
    robot grid point: positions, rotations and moments, and the tendon lengths."""
    config = StaticsConfig()
    lay = _layout(RAO, config)
    rod = CasadiRod(RAO, config, np.array([0.137, 0.2])[:points])
    rng = np.random.default_rng(points)
    jax_pass = jax.jit(lambda m, t, loads: _integrate(lay, config, m, t, loads, True))
    for _ in range(3):
        case = _random_case(rng, RAO.n_tendons, points)
        base_moment = rng.normal(size=3) * 0.02
        with jax.enable_x64(True):
            loads = CaseLoads(*(jnp.asarray(case[k], jnp.float64) for k in (
                "tip_force", "tip_moment", "gravity", "distributed", "point_s",
                "point_force", "point_moment")))
            tip_moment, lengths, positions, rotations, moments = (np.asarray(a) for a in (
                jax_pass(jnp.asarray(base_moment), jnp.asarray(case["tension"]), loads)))
        out = rod.integrate(case["tension"], base_moment, RodLoads.numeric(
            case["tip_force"], case["tip_moment"], case["gravity"], case["distributed"],
            case["point_force"], case["point_moment"]))
        states = np.asarray(out["states"])[:, rod.grid.robot_points].T       # (S+1, 15)
        np.testing.assert_allclose(np.asarray(out["positions"]).T, positions, rtol=0, atol=1e-12)
        np.testing.assert_allclose(states[:, 3:12].reshape(-1, 3, 3), rotations, rtol=0,
                                   atol=1e-12)
        np.testing.assert_allclose(states[:, 12:], moments, rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(out["tip_moment"]).ravel(), tip_moment, rtol=0,
                                   atol=1e-14)
        np.testing.assert_allclose(np.asarray(out["tendon_lengths"]).ravel(), lengths, rtol=0,
                                   atol=1e-12)


@pytest.mark.parametrize("robot", [RAO, _shared_tilted()], ids=["per_segment", "shared"])
def test_casadi_rod_replays_the_statics_equilibria(robot) -> None:
    """The statics' M(0) put through the CasADi rod: the same backbone to 1e-9 m, the tip
    moment met (the statics' tolerance) and the same tendon displacements."""
    rng = np.random.default_rng(7)
    cases = [_random_case(rng, robot.n_tendons, 2) for _ in range(4)]
    point_loads = [[{"s": float(s), "force": f.tolist(), "moment": m.tolist()}
                    for s, f, m in zip(c["point_s"], c["point_force"], c["point_moment"],
                                       strict=True)] for c in cases]

    def stack(key: str) -> np.ndarray:
        return np.stack([c[key] for c in cases])

    result = solve_statics(robot, stack("tension"), stack("tip_force"), stack("tip_moment"),
                           stack("gravity"), distributed_force=stack("distributed"),
                           point_loads=point_loads)
    assert result.converged.all()
    world = static_loads(len(cases), 0.4, stack("tip_force"), stack("tip_moment"),
                         stack("gravity"), stack("distributed"), point_loads)
    base_rot = matrix_from_wxyz(np.asarray(robot.base_wxyz))
    frame = world.in_base_frame(base_rot)
    rod = CasadiRod(robot, StaticsConfig(), cases[0]["point_s"])
    lay = rod.layout
    straight = lay.active.T @ lay.step_length
    for i in range(len(cases)):
        out = rod.integrate(cases[i]["tension"], result.base_moment[i] @ base_rot,
                            RodLoads.numeric(*(a[i] for a in (
                                frame.tip_force, frame.tip_moment, frame.gravity,
                                frame.distributed_force, frame.point_force,
                                frame.point_moment))))
        positions = (np.asarray(out["positions"]).T @ base_rot.T
                     + np.asarray(robot.base_position))
        assert np.max(np.abs(positions - result.positions[i])) <= 1e-9
        residual = np.asarray(out["tip_moment"]).ravel() - frame.tip_moment[i]
        assert np.linalg.norm(residual) <= 10 * 1e-10 * lay.moment_scale
        displacement = straight - np.asarray(out["tendon_lengths"]).ravel()
        np.testing.assert_allclose(displacement, result.tendon_displacements[i], rtol=0,
                                   atol=1e-12)


def test_casadi_rod_is_differentiable_symbolically() -> None:
    """The step is an SX function: its Jacobian with respect to the tensions matches central
    differences of the numeric pass (what the exact stage's Ipopt relies on)."""
    rod = CasadiRod(RAO)
    tension = ca.MX.sym("tension", RAO.n_tendons)
    loads = RodLoads.numeric(gravity=[0.0, 0.0, -9.81], tip_force=[0.0, 0.01, -0.05])
    tip = rod.integrate(tension, ca.DM([0.01, -0.02, 0.0]), loads)["positions"][:, -1]
    jacobian = ca.Function("j", [tension], [ca.jacobian(tip, tension)])
    at = np.array([1.0, 0.0, 2.0, 0.5, 1.5, 0.0])
    step = 1e-6
    columns = []
    for k in range(RAO.n_tendons):
        e = np.zeros(RAO.n_tendons)
        e[k] = step
        ahead, back = (np.asarray(rod.integrate(at + s * e, ca.DM([0.01, -0.02, 0.0]),
                                                loads)["positions"])[:, -1] for s in (1, -1))
        columns.append((ahead - back) / (2 * step))
    np.testing.assert_allclose(np.asarray(jacobian(at)), np.stack(columns, 1), rtol=1e-5,
                               atol=1e-10)
