"""The roadmap (stages/explore/_roadmap.py): a path across the shelf's divider that python-fcl
accepts, the disk cache, and the interpolation helpers."""

import numpy as np
import pytest

from cr_nlp.model import load_robot, q_to_z, tip_pose, z_to_q
from cr_nlp.stages.explore._roadmap import (
    Roadmap,
    RoadmapConfig,
    interpolate_z,
    polyline_length,
    resample_polyline,
    roadmap_cache_stats,
)
from cr_nlp.stages.explore._seed_pool import sobol_configurations
from cr_nlp.world import check_many, clearance, load_scene, scene_arrays

from ...conftest import MODELS


@pytest.fixture(scope="module")
def robot():
    return load_robot(MODELS / "robots" / "tdcr3.json")


@pytest.fixture(scope="module")
def shelf():
    return load_scene("shelf")


@pytest.fixture(autouse=True)
def private_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "cache"))


def dense_motion(robot, q: np.ndarray, pieces: int) -> np.ndarray:
    """The waypoints and ``pieces − 1`` configurations inside every interval, linear in z."""
    z = np.asarray(q_to_z(robot, q))
    parts = [interpolate_z(z[i], z[i + 1], pieces + 1)[:-1] for i in range(len(z) - 1)]
    return np.asarray(z_to_q(robot, np.concatenate(parts + [z[-1:]])))


@pytest.mark.slow  # a benchmark run or a repeat of covered work: `pytest -m slow`
def test_query_crosses_the_shelf_divider_collision_free(robot, shelf):
    roadmap = Roadmap.build(robot, shelf)
    # Tips in the middle compartments, one on each side of the vertical divider (y = 0).
    q = sobol_configurations(robot, 1 << 14, seed=3)
    tips = np.asarray(tip_pose(robot, q)[0])
    inside = ((tips[:, 0] > 1.0) & (tips[:, 2] > 0.9) & (tips[:, 2] < 1.5)
              & (np.abs(tips[:, 1]) > 0.2) & (np.abs(tips[:, 1]) < 0.85))
    q, tips = q[inside], tips[inside]
    q = q[np.asarray(clearance(robot, scene_arrays(shelf), q)) >= roadmap.margin + 0.01]
    tips = np.asarray(tip_pose(robot, q)[0])
    start, goal = q[np.flatnonzero(tips[:, 1] > 0)[0]], q[np.flatnonzero(tips[:, 1] < 0)[0]]
    straight = dense_motion(robot, np.stack([start, goal]), 30)
    assert check_many(robot, shelf, straight).collision.any()  # the divider is in the way

    path = roadmap.query(start, goal, 24)
    assert path is not None and path.shape == (24, robot.dof)
    np.testing.assert_array_equal(path[0], start)
    np.testing.assert_array_equal(path[-1], goal)
    verdict = check_many(robot, shelf, dense_motion(robot, path, 4))
    assert not verdict.collision.any()
    assert verdict.min_distance.min() > 0.0


def test_second_build_loads_from_the_disk_cache(robot):
    scene = load_scene(MODELS / "scenes" / "random_27.json")
    config = RoadmapConfig(nodes=128, neighbours=5, seed=11)
    before = roadmap_cache_stats()
    first = Roadmap.build(robot, scene, config)
    middle = roadmap_cache_stats()
    second = Roadmap.build(robot, scene, config)
    after = roadmap_cache_stats()
    assert middle["builds"] == before["builds"] + 1 and middle["hits"] == before["hits"]
    assert after["hits"] == middle["hits"] + 1 and after["builds"] == middle["builds"]
    assert second.loaded_from_cache and not first.loaded_from_cache
    np.testing.assert_array_equal(first.nodes_z, second.nodes_z)
    assert (first.edges != second.edges).nnz == 0
    # Other settings are another roadmap.
    Roadmap.build(robot, scene, RoadmapConfig(nodes=128, neighbours=5, seed=12))
    assert roadmap_cache_stats()["builds"] == after["builds"] + 1


def test_interpolation_and_resampling():
    za, zb = np.zeros(3), np.array([3.0, 0.0, 4.0])
    line = interpolate_z(za, zb, 6)
    np.testing.assert_allclose(line[:, 0], [0.0, 0.6, 1.2, 1.8, 2.4, 3.0])
    corners = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 2.0, 1.0]])
    assert polyline_length(corners) == pytest.approx(3.0)
    even = resample_polyline(corners, 4)
    np.testing.assert_allclose(even, [[0, 0, 1], [1, 0, 1], [1, 1, 1], [1, 2, 1]], atol=1e-12)


@pytest.mark.parametrize("name", ["shelf", "cabinet", "random_27"])
def test_the_broad_phase_checker_decides_the_margin_like_every_part(robot, name):
    """The roadmap's checker measures each body sphere only against its cell's parts:
    below the margin its clearance equals the every-part clearance (``clearance``), and a
    configuration it passes has every-part clearance ≥ the margin; Sobol samples over the
    whole configuration space, half of them in collision."""
    from cr_nlp.stages.explore._roadmap import ClearanceChecker, resolved_margin

    scene = load_scene(name)
    margin = resolved_margin(robot, RoadmapConfig())
    fast = ClearanceChecker(robot, scene, margin)
    assert fast.cells is not None and fast.cutoff == pytest.approx(margin)
    q = sobol_configurations(robot, 4096, seed=3)
    z = np.asarray(q_to_z(robot, q))
    got = fast(z)
    every = np.asarray(clearance(robot, scene_arrays(scene, dtype=np.float32),
                                 np.asarray(q, np.float32)), dtype=float)
    below = every < margin
    assert 0.2 < below.mean() < 0.95                      # both verdicts occur
    np.testing.assert_allclose(got[below], every[below], atol=2e-6)
    assert np.all(got[~below] >= margin - 2e-6)
    assert np.array_equal(got >= margin, every >= margin) or \
        np.abs(every[(got >= margin) != (every >= margin)] - margin).max() < 2e-6


class ThinWall:
    """A stand-in clearance checker in z: −1 m on a wall 1 cm thick across the first
    coordinate (0.29 ≤ z₀ ≤ 0.30, |z₁| < 0.05), 1 m elsewhere. An edge from z₀ = 0 to
    z₀ = 1 passes its 8 coarse samples (z₀ = 0.22, 0.33, …) and fails the dense ones."""

    def __call__(self, z: np.ndarray) -> np.ndarray:
        z = np.atleast_2d(z)
        wall = (z[:, 0] >= 0.29) & (z[:, 0] <= 0.30) & (np.abs(z[:, 1]) < 0.05)
        return np.where(wall, -1.0, 1.0)

    def compile_all(self) -> None:
        pass


def _point(robot, x: float, y: float) -> np.ndarray:
    """A configuration z with z₀ = x, z₁ = y (the plane of ``ThinWall``), lengths 1 m."""
    z = np.zeros(robot.dof)
    z[0], z[1], z[2::3] = x, y, 1.0
    return z


def _thin_wall_roadmap(robot, shelf, n2_y: float, neighbours: int) -> tuple:
    """Nodes N1 = (1, 0), N2 = (0, ``n2_y``), N3 = (2, 1), edges N1–N3 and N2–N3, checked
    by ``ThinWall``; returns the roadmap and its nodes."""
    import scipy.sparse as sp

    nodes = np.stack([_point(robot, 1, 0), _point(robot, 0, n2_y), _point(robot, 2, 1)])
    hops = [(0, 2), (1, 2)]
    rows, cols = zip(*(hops + [(b, a) for a, b in hops]), strict=True)
    lengths = [float(np.linalg.norm(nodes[a] - nodes[b])) for a, b in zip(rows, cols,
                                                                             strict=True)]
    edges = sp.csr_matrix((lengths, (rows, cols)), shape=(3, 3))
    roadmap = Roadmap(robot, shelf, RoadmapConfig(neighbours=neighbours, edge_checks=8),
                      nodes, edges, 0.0)
    roadmap._checker = ThinWall()
    return roadmap, nodes


def test_an_attach_edge_only_the_dense_check_rejects_is_not_used(robot, shelf):
    """Start S = (0, 0) attaches to N1 = (1, 0) (coarse samples pass, the wall is between
    them) and N2 = (0, 1); the shortest path S–N1–G crosses the wall, so the query must
    find the longer S–N2–N3–G, every edge of which keeps the margin densely."""
    roadmap, nodes = _thin_wall_roadmap(robot, shelf, 1.0, neighbours=2)
    start, goal = _point(robot, 0, 0), _point(robot, 2, 0)
    path = roadmap.query_z(start, goal)
    np.testing.assert_array_equal(path, np.stack([start, nodes[1], nodes[2], goal]))
    assert roadmap.dense_free(path[:-1], path[1:]).all()
    assert not roadmap.dense_free(start, nodes[0]).any()


def test_an_end_whose_every_coarse_attach_edge_fails_is_attached_again_densely(robot, shelf):
    """With one neighbour, S = (0, 0) attaches to N1 = (1, 0) only (N2 = (0, 1.1) is
    farther), through the thin wall: the query must attach S again with the dense check
    (to N2) and still find a path, every edge of which keeps the margin densely."""
    roadmap, nodes = _thin_wall_roadmap(robot, shelf, 1.1, neighbours=1)
    start, goal = _point(robot, 0, 0), _point(robot, 2, 0)
    path = roadmap.query_z(start, goal)
    assert path is not None
    np.testing.assert_array_equal(path[:2], np.stack([start, nodes[1]]))
    np.testing.assert_array_equal(path[-1], goal)
    assert roadmap.dense_free(path[:-1], path[1:]).all()
