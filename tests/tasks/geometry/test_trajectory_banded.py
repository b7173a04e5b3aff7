"""The banded trajectory LM: its window terms define the dense problem, its broad phase
measures the nearest parts, and planning answers agree with the dense LM's."""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp.model import load_robot
from cr_nlp.stages.refine._banded_lm import (
    banded_to_dense,
    chain_cost,
    chain_jacobians,
    normal_equations,
)
from cr_nlp.tasks.geometry.trajectory import (
    TrajectoryConfig,
    TrajectoryPlanner,
    trajectory_residual,
    trajectory_terms,
)
from cr_nlp.world import load_scene, scene_arrays
from cr_nlp.world._broad_phase import part_cells, reach_box
from cr_nlp.world._clearance_groups import clearance_group_values, near_clearance_groups

from ...conftest import MODELS

ROBOT = load_robot(MODELS / "robots" / "tdcr3.json")


def random_trajectory(waypoints: int, seed: int) -> np.ndarray:
    """(waypoints, 9) bending vectors near the shelf's boards, float64."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(-1.2, 1.2, (waypoints, ROBOT.dof))
    z[:, 2::3] = 1.0
    return z


@pytest.mark.parametrize("scene_name", [pytest.param("shelf", marks=pytest.mark.slow),
                                        "random_27"])
@pytest.mark.usefixtures("float64")
def test_window_terms_give_the_dense_residuals_cost_and_normal_equations(scene_name):
    """``trajectory_terms`` (the banded LM's problem) against ``trajectory_residual`` (the
    dense LM's), float64, at a trajectory in contact with the scene: the same ½‖r‖², and
    JᵀJ and Jᵀr of the dense residual's forward-mode Jacobian equal the banded blocks."""
    config = TrajectoryConfig(waypoints=6, near_parts=0)
    arrays = scene_arrays(load_scene(scene_name), dtype=jnp.float64)
    margin, dt = 0.05, 0.35
    weights = (config.path_weight, config.smoothness_weight, config.clearance_weight,
               config.tendon_weight)
    dense = partial(trajectory_residual, ROBOT, config.waypoints, config.interpolation_checks,
                    margin, weights, config.tendon_limit_fraction)
    terms = trajectory_terms(ROBOT, margin, config, arrays)
    z = jnp.asarray(random_trajectory(config.waypoints, 7))
    shared = (arrays, None, jnp.float64(dt))
    r = jax.jit(dense)(z.reshape(-1), jnp.float64(dt), arrays)
    assert float(jnp.sum(r[r > 0])) > 0.0                     # penalties are active
    assert float(jax.jit(lambda z: chain_cost(terms, z, None, shared))(z)) == pytest.approx(
        0.5 * float(r @ r), rel=1e-12)
    jac = jax.jit(jax.jacfwd(dense))(z.reshape(-1), jnp.float64(dt), arrays)
    h, g = jax.jit(lambda z: normal_equations(chain_jacobians(terms, z, None, shared),
                                              config.waypoints))(z)
    np.testing.assert_allclose(banded_to_dense(h), jac.T @ jac, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(g).reshape(-1), jac.T @ r, rtol=1e-9, atol=1e-9)


@pytest.mark.usefixtures("float64")
def test_broad_phase_measures_the_nearest_parts():
    """``near_clearance_groups`` with every part equals ``clearance_group_values``
    (world._penalty's distances), float64, on 120 random configurations of tdcr3; with the
    broad-phase table (``world._broad_phase``, cutoff = the margin) it gives the same
    values and Jacobians in the shelf (57 convex parts) and random_27 (27 spheres)."""
    z = jnp.asarray(random_trajectory(120, 3))
    margin = 0.05
    for name in ("shelf", "random_27"):
        scene = load_scene(name)
        arrays = scene_arrays(scene, dtype=jnp.float64)
        cells = part_cells(scene, ROBOT.backbone_radius, reach_box(ROBOT), margin,
                           dtype=jnp.float64)
        assert cells.truncated == 0
        reference = jax.jit(jax.vmap(partial(clearance_group_values, ROBOT, margin, arrays)))(z)
        assert int(jnp.sum(reference > 0)) > 50                # many groups in contact
        all_parts = partial(near_clearance_groups, ROBOT, margin, arrays, None)
        ref_jac = jax.jit(jax.vmap(jax.jacfwd(all_parts)))(z)
        for table in (None, cells):
            fn = partial(near_clearance_groups, ROBOT, margin, arrays, table)
            values = np.asarray(jax.jit(jax.vmap(fn))(z))
            jac = np.asarray(jax.jit(jax.vmap(jax.jacfwd(fn)))(z))
            np.testing.assert_allclose(values, reference, rtol=0, atol=1e-12)
            np.testing.assert_allclose(jac, np.asarray(ref_jac), rtol=0, atol=1e-10)
        with pytest.raises(ValueError, match="margin"):
            near_clearance_groups(ROBOT, 2 * margin, arrays, cells, z[0])


def _plan_alike(scene_name: str, count: int, other: TrajectoryConfig, least_successes: int,
                rel: float) -> tuple[TrajectoryPlanner, TrajectoryPlanner]:
    """Plan ``count`` problems of the benchmark protocol with the default config and with
    ``other``; assert the same successes and path lengths within ``rel``."""
    from cr_nlp.bench.plan import plan_problems

    scene = load_scene(scene_name)
    default = TrajectoryPlanner(ROBOT, scene, TrajectoryConfig())
    changed = TrajectoryPlanner(ROBOT, scene, other)
    starts, goals = plan_problems(ROBOT, scene, count, default.margin, seed=0)
    a, b = default.plan(starts, goals), changed.plan(starts, goals)
    assert [r.success for r in a] == [r.success for r in b]
    assert sum(r.success for r in a) >= least_successes
    for ra, rb in zip(a, b, strict=True):
        if ra.success:
            assert ra.path_length == pytest.approx(rb.path_length, rel=rel)
    return default, changed


@pytest.mark.slow  # two planners' compilations: `pytest -m slow`
def test_banded_and_dense_lm_plan_alike_on_the_shelf():
    """Before/after: the banded LM (default) and the dense LM plan 6 shelf problems of the
    benchmark protocol with the same successes and path lengths within 2 %."""
    _plan_alike("shelf", 6, replace(TrajectoryConfig(), lm_structure="dense"), 5, 0.02)


@pytest.mark.slow  # two planners' compilations: `pytest -m slow`
def test_give_up_stop_plans_the_cabinet_alike_in_fewer_trips():
    """Before/after: stopping guesses still deep in an obstacle after 12 and 20 iterations
    (default) and running every guess to its stall or cap plan 12 cabinet problems of the
    benchmark protocol with the same successes and path lengths (the same guess chosen;
    float32 programs of other slot counts round differently, which moved one problem's
    path by 0.3 % after 60 iterations), in fewer LM trips."""
    new, old = _plan_alike("cabinet", 12, replace(TrajectoryConfig(), give_up=()), 10, 5e-3)
    assert new.lm.slot_trips < old.lm.slot_trips


@pytest.mark.slow  # two planners' compilations: `pytest -m slow`
def test_early_give_up_checkpoint_plans_random_27_alike_in_fewer_trips():
    """Before/after: the give-up checkpoint at 12 iterations (cost 8) added to the one at 20
    (cost 5) plans 12 random_27 problems of the benchmark protocol with the same successes
    and path lengths, in fewer LM trips."""
    new, old = _plan_alike("random_27", 12, replace(TrajectoryConfig(), give_up=((20, 5.0),)),
                           10, 5e-3)
    assert new.lm.slot_trips < old.lm.slot_trips


def test_the_first_slot_program_compiles_while_the_roadmap_is_built(monkeypatch):
    """The planner asks for the LM's first slot program, for every lane's device, before
    it builds the roadmap (a warm process loads the copies side by side), and it is the
    program the stream then runs (not a second compile of another size)."""
    from cr_nlp.bench.plan import plan_problems
    from cr_nlp.stages.refine import _chain_stream

    asked: list[tuple[str, int, int]] = []
    real = _chain_stream.compile_ahead

    def recording(fn, args, **kwargs):
        device = next(iter(args[1].devices())).id
        asked.append((kwargs.get("name", ""), int(args[1].shape[0]), device))
        return real(fn, args, **kwargs)

    monkeypatch.setattr(_chain_stream, "compile_ahead", recording)
    scene = load_scene("shelf")
    planner = TrajectoryPlanner(ROBOT, scene, TrajectoryConfig())
    built = []
    real_roadmap = planner.roadmap
    monkeypatch.setattr(planner, "roadmap", lambda: (built.append(len(asked)), real_roadmap())[1])
    starts, goals = plan_problems(ROBOT, scene, 3, planner.margin, seed=0)
    results = planner.plan(starts, goals)
    assert all(r.q is not None for r in results)
    name, slots, _ = asked[0]
    lanes = [d.id for d in planner.lm.devices]
    assert name == "the trajectory LM" and built
    assert sorted(d for _, _, d in asked[:built[0]]) == lanes  # asked before the roadmap
    assert all(a[:2] == (name, slots) for a in asked[:built[0]])
    first_device = lanes[0]
    assert (first_device, slots) in planner.lm._slot_programs
    assert min(s for d, s in planner.lm._slot_programs if d == first_device) == slots
