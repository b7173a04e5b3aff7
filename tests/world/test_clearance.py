"""The differentiable clearance: against the python-fcl verdict, and JAX against CasADi."""


import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp.model import Robot
from cr_nlp.world import (
    Scene,
    body_chain,
    body_gap_tolerance,
    casadi_clearance,
    check,
    check_many,
    clearance,
    clearance_z,
    load_scene,
    pair_distances,
    scene_arrays,
    self_distances,
    self_pairs,
    soft_clearance,
)

from ..conftest import MODELS, random_q, write_mixed_scene


@pytest.fixture(scope="module")
def tdcr3() -> Robot:
    return Robot.from_file(MODELS / "robots" / "tdcr3.json")


@pytest.fixture(scope="module")
def mixed_scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    """One obstacle of every kind, all within reach of tdcr3."""
    root = tmp_path_factory.mktemp("mixed")
    return write_mixed_scene(root)


# ---------------------------------------------------------------- against the verdict

@pytest.mark.parametrize("scene_name", ["lattice", "shelf"])
def test_clearance_is_conservative_against_fcl(tdcr3: Robot, scene_name: str) -> None:
    """clearance ≤ max(d_fcl, 0) + body_gap_tolerance on thousands of configurations, so
    clearance ≥ tolerance proves the capsule body collision-free."""
    scene = load_scene(scene_name)
    qs = random_q(tdcr3, 2000, seed=1)
    ours = np.asarray(clearance(tdcr3, scene_arrays(scene), qs))
    truth = check_many(tdcr3, scene, qs)
    eps = body_gap_tolerance(tdcr3)
    excess = ours - (np.maximum(truth.min_distance, 0.0) + eps)
    assert excess.max() <= 1e-5, f"worst excess {excess.max():.3g} m"
    assert not np.any((ours >= eps) & truth.collision)
    # Where both say free and something is near, the estimate is close to the truth:
    # an error budget, not a blanket under-estimate (measured: ~1e-3 m median).
    near = (truth.min_distance > 0) & (truth.min_distance < 0.2)
    assert near.sum() > 50
    assert np.median(np.abs(truth.min_distance[near] - ours[near])) < 0.01


def test_tolerance_of_tdcr3(tdcr3: Robot) -> None:
    # r = 0.1 m, h = 0.1 m: max(√(0.01 + 0.0025) − 0.1, √(0.04 + 0.005) − 0.2)
    assert body_gap_tolerance(tdcr3) == pytest.approx(np.sqrt(0.045) - 0.2)


def test_mixed_scene_conservative_and_self_pairs(tdcr3: Robot, mixed_scene: Scene) -> None:
    qs = random_q(tdcr3, 600, seed=2)
    ours = np.asarray(clearance(tdcr3, scene_arrays(mixed_scene), qs))
    truth = check_many(tdcr3, mixed_scene, qs)
    eps = body_gap_tolerance(tdcr3)
    assert np.max(ours - (np.maximum(truth.min_distance, 0.0) + eps)) <= 1e-5
    # Self-clearance alone against fcl's capsule self-distance.
    own = np.asarray(self_distances(tdcr3, qs)).min(axis=-1)
    assert np.max(own - (np.maximum(truth.self_distance, 0.0) + eps)) <= 1e-5
    assert truth.self_collision.any()          # curled configurations exist in the sample


def test_self_pairs_only_between_segments_two_apart(tdcr3: Robot) -> None:
    pairs = self_pairs(tdcr3)
    k = tdcr3.points_per_segment
    assert len(pairs) == (k + 1) ** 2                 # segment 1's chain × segment 3's
    assert np.all(pairs[:, 0] <= k) and np.all(pairs[:, 1] >= 2 * k)
    two = Robot.from_dict({**tdcr3.to_dict(), "segments": tdcr3.to_dict()["segments"][:2],
                           "tendons": {**tdcr3.to_dict()["tendons"], "offsets": [0, 0]}})
    assert len(self_pairs(two)) == 0
    assert float(clearance(two, scene_arrays(Scene("empty", ())), np.array([0, 0, 1.0] * 2))) \
        == np.inf


@pytest.mark.usefixtures("float64")  # closed-form clearances at 1e-12
def test_straight_robot_values(tdcr3: Robot) -> None:
    straight = np.array([0.0, 0.0, 1.0] * 3)
    lattice = scene_arrays(load_scene("lattice"))
    # Nearest lattice sphere (0, 0.4, 0.2) r 0.2: 0.4 − 0.2 − 0.1 = 0.1 m.
    assert float(clearance(tdcr3, lattice, straight)) == pytest.approx(0.1, abs=1e-12)
    # Segments 1 and 3 of a straight robot: 1 m apart along the axis, minus 2r.
    assert float(np.min(self_distances(tdcr3, straight))) == pytest.approx(0.8, abs=1e-12)
    assert check(tdcr3, load_scene("lattice"), straight).min_distance == pytest.approx(0.1,
                                                                                       abs=1e-5)
    # The bending-vector form of the straight robot is the same configuration.
    from cr_nlp.model import q_to_z

    assert float(clearance_z(tdcr3, lattice, q_to_z(tdcr3, straight))) == pytest.approx(0.1)


@pytest.mark.usefixtures("float64")  # float32 against the float64 default
def test_batch_shapes_and_dtypes(tdcr3: Robot) -> None:
    scene = load_scene("lattice")
    qs = random_q(tdcr3, 12, seed=3).reshape(3, 4, 9)
    arrays = scene_arrays(scene)
    pairs = pair_distances(tdcr3, arrays, qs)
    assert pairs.shape == (3, 4, 1 + 3 * 10, 27)
    full = clearance(tdcr3, arrays, qs)
    assert full.shape == (3, 4)
    expected = np.minimum(np.asarray(pairs).min(axis=(-2, -1)),
                          np.asarray(self_distances(tdcr3, qs)).min(axis=-1))
    np.testing.assert_allclose(np.asarray(full), expected, atol=1e-12)
    single = clearance(tdcr3, scene_arrays(scene, jnp.float32), jnp.asarray(qs, jnp.float32))
    assert single.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(single), np.asarray(full), atol=2e-5)


@pytest.mark.usefixtures("float64")  # the bounds at 1e-12
def test_soft_clearance_bounds(tdcr3: Robot, mixed_scene: Scene) -> None:
    qs = random_q(tdcr3, 600, seed=2)   # the batch of the test above: compiled already
    arrays = scene_arrays(mixed_scene)
    hard = np.asarray(clearance(tdcr3, arrays, qs))
    count = (1 + tdcr3.n_points) * arrays.n_parts + len(self_pairs(tdcr3))
    for tau in (1e-3, 1e-2):
        soft = np.asarray(soft_clearance(tdcr3, arrays, qs, tau))
        assert np.all(soft <= hard + 1e-12)
        assert np.all(soft >= hard - tau * np.log(count) - 1e-12)


def test_gradients_are_finite_at_the_straight_configuration(tdcr3: Robot,
                                                           mixed_scene: Scene) -> None:
    arrays = scene_arrays(mixed_scene)
    straight = jnp.array([0.0, 0.0, 1.0] * 3)
    jac = jax.jacfwd(pair_distances, argnums=2)(tdcr3, arrays, straight, 0.01)
    assert np.all(np.isfinite(np.asarray(jac)))


def test_body_chain_starts_at_the_base(tdcr3: Robot) -> None:
    from cr_nlp.model import backbone_points

    q = random_q(tdcr3, 5, seed=5)
    chain = body_chain(tdcr3, q)
    np.testing.assert_allclose(chain[:, 0], 0.0)
    np.testing.assert_allclose(chain[:, 1:], np.asarray(backbone_points(tdcr3, q)), atol=1e-12)


# ---------------------------------------------------------------- JAX against CasADi

# Smoothing changes only the convex-part formula: the mixed scene (every kind) runs with
# it, the shelf (convex parts only) without; each JAX derivative compiles in seconds.
@pytest.mark.usefixtures("float64")  # JAX against CasADi at 1e-10
@pytest.mark.parametrize(("scene_name", "smoothing"), [("mixed", 0.01), ("shelf", 0.0)])
def test_jax_and_casadi_agree_on_values_and_jacobians(tdcr3: Robot, mixed_scene: Scene,
                                                      scene_name: str, smoothing: float) -> None:
    scene = mixed_scene if scene_name == "mixed" else load_scene("shelf")
    arrays = scene_arrays(scene)
    # jacfwd of the jitted functions: their derivative is compiled once and cached.
    jac_pairs = jax.jacfwd(pair_distances, argnums=2)
    jac_self = jax.jacfwd(self_distances, argnums=1)
    all_self = {tuple(p): i for i, p in enumerate(self_pairs(tdcr3))}
    checked = 0
    for q in random_q(tdcr3, 4, seed=6):
        built = casadi_clearance(tdcr3, scene, q, margin=0.6, face_smoothing=smoothing)
        if built.size == 0:
            continue
        values = np.asarray(built.function(q)).ravel()
        jac = np.asarray(_casadi_jacobian(built.function)(q))
        obstacle, own = built.obstacle_pairs, built.self_pairs
        own_rows = [all_self[tuple(p)] for p in own]
        expected = np.concatenate([
            np.asarray(pair_distances(tdcr3, arrays, q, smoothing))[obstacle[:, 0], obstacle[:, 1]],
            np.asarray(self_distances(tdcr3, q))[own_rows]])
        np.testing.assert_allclose(values, expected, atol=1e-10)
        jax_jac = np.concatenate([
            np.asarray(jac_pairs(tdcr3, arrays, q, smoothing))[obstacle[:, 0], obstacle[:, 1]],
            np.asarray(jac_self(tdcr3, q))[own_rows].reshape(-1, 9)])
        np.testing.assert_allclose(jac, jax_jac, atol=1e-8)
        assert np.all(np.isfinite(jax_jac))
        assert np.all(values < 0.6 + 1e-9)
        checked += built.size
    assert checked > 20


def _casadi_jacobian(f: ca.Function) -> ca.Function:
    q = ca.SX.sym("q", f.size1_in(0))
    return ca.Function("jacobian_q", [q], [ca.jacobian(f(q), q)])


@pytest.mark.usefixtures("float64")  # the JAX q_to_z feeds a 1e-12 comparison
def test_casadi_keeps_only_near_pairs(tdcr3: Robot) -> None:
    scene = load_scene("lattice")
    straight = np.array([0.0, 0.0, 1.0] * 3)
    near = casadi_clearance(tdcr3, scene, straight, margin=0.15)
    everything = casadi_clearance(tdcr3, scene, straight, margin=10.0, include_self=False)
    assert 0 < near.size < 100 and everything.size == 31 * 27
    assert set(near.names) <= {o.name for o in scene.obstacles} | {"self"}
    # The z form is the same function of the bending vector.
    from cr_nlp.model import q_to_z

    q = random_q(tdcr3, 1, seed=7)[0]
    np.testing.assert_allclose(np.asarray(near.function(q)),
                               np.asarray(near.function_z(np.asarray(q_to_z(tdcr3, q)))),
                               atol=1e-12)
