"""Batched roadmap search (stages/explore/_roadmap_search.py, Roadmap.query_many_z) against scipy's
Dijkstra run one pair at a time, the lazy re-check of many pairs against one-by-one
queries, and many planning problems in one call (streamed in blocks)."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from cr_nlp.bench.plan import plan_problems
from cr_nlp.model import load_robot, q_to_z_numpy
from cr_nlp.stages.explore._roadmap import Roadmap, RoadmapConfig, polyline_length, resolved_margin
from cr_nlp.stages.explore._roadmap_search import neighbour_table, shortest_paths
from cr_nlp.tasks.geometry.trajectory import TrajectoryConfig, TrajectoryPlanner
from cr_nlp.world import load_scene

from ...conftest import MODELS


@pytest.fixture(autouse=True)
def private_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "cache"))


@pytest.fixture(scope="module")
def robot():
    return load_robot(MODELS / "robots" / "tdcr3.json")


def random_graph(rng, n, edges):
    """A symmetric CSR graph of random points, in two components (nodes < n/2 and the
    rest), edge lengths the points' distances."""
    points = rng.random((n, 3))
    half = n // 2
    i = rng.integers(0, half, edges)
    j = rng.integers(0, half, edges)
    i = np.r_[i, half + rng.integers(0, n - half, edges)]
    j = np.r_[j, half + rng.integers(0, n - half, edges)]
    keep = i != j
    i, j = i[keep], j[keep]
    length = np.linalg.norm(points[i] - points[j], axis=1)
    graph = sp.coo_matrix((np.r_[length, length], (np.r_[i, j], np.r_[j, i])), shape=(n, n))
    graph = graph.tocsr()                               # repeated pairs add up: re-measure
    rows = np.repeat(np.arange(n), np.diff(graph.indptr))
    graph.data[:] = np.linalg.norm(points[rows] - points[graph.indices], axis=1)
    return graph


def one_pair_dijkstra(graph, start_nodes, start_lengths, goal_nodes, goal_lengths):
    """The reference: scipy Dijkstra on the graph plus one start and one goal node, as
    the roadmap's one-pair query built it before batching."""
    n = graph.shape[0]
    ok_s, ok_g = np.isfinite(start_lengths), np.isfinite(goal_lengths)
    s_nodes, s_len = start_nodes[ok_s], start_lengths[ok_s]
    g_nodes, g_len = goal_nodes[ok_g], goal_lengths[ok_g]
    extra = sp.coo_matrix(
        (np.r_[s_len, s_len, g_len, g_len],
         (np.r_[np.full(len(s_nodes), n), s_nodes, np.full(len(g_nodes), n + 1), g_nodes],
          np.r_[s_nodes, np.full(len(s_nodes), n), g_nodes, np.full(len(g_nodes), n + 1)])),
        shape=(n + 2, n + 2))
    full = (sp.block_diag([graph, sp.csr_matrix((2, 2))]) + extra).tocsr()
    dist, pred = dijkstra(full, directed=False, indices=n, return_predecessors=True)
    if not np.isfinite(dist[n + 1]):
        return np.inf, None
    path = [int(pred[n + 1])]
    while pred[path[-1]] != n:
        path.append(int(pred[path[-1]]))
    return dist[n + 1], np.array(path[::-1])


def path_length(graph, start_nodes, start_lengths, goal_nodes, goal_lengths, path):
    """Float64 length of a returned path: start edge, roadmap edges, goal edge."""
    first = np.min(start_lengths[start_nodes == path[0]])
    last = np.min(goal_lengths[goal_nodes == path[-1]])
    return first + last + sum(graph[a, b] for a, b in zip(path[:-1], path[1:], strict=True))


@pytest.mark.parametrize("search", ["device", "scipy"])
def test_batched_search_matches_dijkstra_one_pair_at_a_time(search):
    rng = np.random.default_rng(7)
    n, pairs, width = 120, 40, 4
    graph = random_graph(rng, n, 150)
    start_nodes = np.stack([rng.choice(n, width, replace=False) for _ in range(pairs)])
    goal_nodes = np.stack([rng.choice(n, width, replace=False) for _ in range(pairs)])
    start_lengths = rng.uniform(0.05, 0.5, (pairs, width))
    goal_lengths = rng.uniform(0.05, 0.5, (pairs, width))
    start_lengths[rng.random((pairs, width)) < 0.3] = np.inf      # pads
    start_lengths[0] = np.inf                                     # a start attached nowhere
    # Ends only in different components: no path.
    start_nodes[1], goal_nodes[1] = np.arange(width), n - 1 - np.arange(width)
    start_lengths[1] = goal_lengths[1] = 0.1

    neighbours, weights = neighbour_table(graph)
    lengths, paths = shortest_paths(neighbours, weights, start_nodes, start_lengths,
                                    goal_nodes, goal_lengths, search)
    unreachable = 0
    for p in range(pairs):
        args = (start_nodes[p], start_lengths[p], goal_nodes[p], goal_lengths[p])
        expected, expected_path = one_pair_dijkstra(graph, *args)
        if expected_path is None:
            unreachable += 1
            assert lengths[p] == np.inf and paths[p] is None
            continue
        assert lengths[p] == pytest.approx(expected, rel=1e-5)
        assert path_length(graph, *args, paths[p]) == pytest.approx(expected, rel=1e-5)
        if not np.array_equal(paths[p], expected_path):     # only a tie may differ
            assert path_length(graph, *args, paths[p]) == pytest.approx(
                path_length(graph, *args, expected_path), rel=1e-5)
    assert 2 <= unreachable < pairs // 2


def test_device_and_scipy_searches_pick_the_same_paths():
    rng = np.random.default_rng(3)
    graph = random_graph(rng, 300, 900)
    neighbours, weights = neighbour_table(graph)
    weights[5, :] = np.inf                               # an edge dropped in one direction
    pairs = 20
    start_nodes, goal_nodes = rng.integers(0, 300, (pairs, 3)), rng.integers(0, 300, (pairs, 3))
    start_lengths, goal_lengths = rng.random((pairs, 3)), rng.random((pairs, 3))
    out = [shortest_paths(neighbours, weights, start_nodes, start_lengths, goal_nodes,
                          goal_lengths, search) for search in ("device", "scipy")]
    np.testing.assert_allclose(out[0][0], out[1][0], rtol=1e-5)
    same = [a is None and b is None or (a is not None and b is not None and np.array_equal(a, b))
            for a, b in zip(out[0][1], out[1][1], strict=True)]
    assert sum(same) >= pairs - 1                         # float32 against float64 ties


def test_neighbour_table_holds_every_edge_once():
    graph = random_graph(np.random.default_rng(1), 50, 80)
    neighbours, weights = neighbour_table(graph)
    rows = np.repeat(np.arange(50), neighbours.shape[1])
    kept = np.isfinite(weights.ravel())
    rebuilt = sp.csr_matrix((weights.ravel()[kept], (rows[kept], neighbours.ravel()[kept])),
                            shape=(50, 50))
    assert (rebuilt != graph).nnz == 0


@pytest.mark.parametrize("search", ["device", "scipy"])
def test_an_end_attached_twice_to_a_node_counts_its_shorter_edge(search):
    """A path 0 — 1 — 2 (lengths 1, 2); the start attached to node 0 at 0.5 and again at
    0.25, the goal to node 2 at 0.75 and again at 0.125, and a pad (+inf) naming a node
    out of range: 0.25 + 3 + 0.125, not a sum of the repeats."""
    graph = sp.csr_matrix(([1.0, 1.0, 2.0, 2.0], ([0, 1, 1, 2], [1, 0, 2, 1])), shape=(3, 3))
    neighbours, weights = neighbour_table(graph)
    lengths, paths = shortest_paths(neighbours, weights, np.array([[0, 0, 99]]),
                                    np.array([[0.5, 0.25, np.inf]]), np.array([[2, 2, 99]]),
                                    np.array([[0.75, 0.125, np.inf]]), search)
    assert lengths[0] == pytest.approx(3.375) and paths[0].tolist() == [0, 1, 2]


@pytest.fixture(scope="module")
def coarse_roadmap_problems(robot):
    """A small roadmap with one interior check per edge (so the dense query-time checks
    drop edges) in the random scene, and start/goal pairs."""
    scene = load_scene(MODELS / "scenes" / "random_27.json")
    config = RoadmapConfig(nodes=384, neighbours=6, edge_checks=1, seed=5, max_query_rounds=100)
    starts, goals = plan_problems(robot, scene, 16, resolved_margin(robot, config), seed=4)
    return scene, config, q_to_z_numpy(starts), q_to_z_numpy(goals)


@pytest.mark.parametrize("search", ["device", "scipy"])
def test_many_pairs_at_once_answer_as_one_by_one(robot, coarse_roadmap_problems, search):
    scene, config, z_starts, z_goals = coarse_roadmap_problems
    roadmap = Roadmap.build(robot, scene, config)
    alone = [roadmap.query_z(a, b, search) for a, b in zip(z_starts, z_goals, strict=True)]
    fresh = Roadmap.build(robot, scene, config)
    together = fresh.query_many_z(z_starts, z_goals, search)
    assert fresh.last_query_rounds > 1                   # the lazy re-search ran
    assert sum(path is not None for path in together) >= len(z_starts) // 2
    assert any(path is not None and len(path) > 2 for path in together)
    expected = shortest_dense_free_paths(Roadmap.build(robot, scene, config), z_starts, z_goals)
    for one, many, length in zip(alone, together, expected, strict=True):
        assert (one is None) == (many is None) == (length == np.inf)
        if many is not None:
            assert polyline_length(many) == pytest.approx(polyline_length(one), rel=1e-5)
            assert polyline_length(many) == pytest.approx(length, rel=1e-5)
            assert fresh.dense_free(many[:-1], many[1:]).all()


def shortest_dense_free_paths(roadmap, z_starts, z_goals):
    """The reference of the lazy search: every roadmap edge and every attach edge checked
    densely up front, the failing ones removed, then scipy Dijkstra pair by pair."""
    graph = roadmap.edges.tocoo()
    upper = graph.row < graph.col
    a, b = graph.row[upper], graph.col[upper]
    ok = roadmap.dense_free(roadmap.nodes_z[a], roadmap.nodes_z[b])
    length = graph.data[upper][ok]
    n = len(roadmap.nodes_z)
    free = sp.coo_matrix((np.r_[length, length], (np.r_[a[ok], b[ok]], np.r_[b[ok], a[ok]])),
                         shape=(n, n)).tocsr()
    out = []
    for z_start, z_goal in zip(z_starts, z_goals, strict=True):
        if roadmap.dense_free(z_start, z_goal)[0]:
            out.append(float(np.linalg.norm(z_goal - z_start)))
            continue
        ends = []
        for z in (z_start, z_goal):
            nodes, lengths = roadmap._attach(z[None])
            nodes, lengths = nodes[0], lengths[0].copy()
            used = nodes >= 0
            lengths[used] = np.where(roadmap.dense_free(np.repeat(z[None], used.sum(), 0),
                                                        roadmap.nodes_z[nodes[used]]),
                                     lengths[used], np.inf)
            ends += [nodes, lengths]
        out.append(one_pair_dijkstra(free, *ends)[0])
    return out


def plan_many_problems(robot, count, seed):
    scene = load_scene("shelf")
    # The device search here (the other planner tests run "auto", scipy on a CPU).
    planner = TrajectoryPlanner(robot, scene, TrajectoryConfig(
        guesses=1, iterations=5, problem_chunk=2, roadmap_search="device"))
    starts, goals = plan_problems(robot, scene, count, planner.margin, seed=seed)
    return planner, starts, goals


def test_planning_many_problems_in_one_call_matches_one_by_one_and_streams(robot,
                                                                           monkeypatch):
    planner, starts, goals = plan_many_problems(robot, 5, seed=2)
    blocks = []
    plan_valid = planner._plan_valid

    def spy(valid, *args):
        blocks.append(len(valid))
        return plan_valid(valid, *args)

    monkeypatch.setattr(planner, "_plan_valid", spy)
    together = planner.plan(starts, goals)
    assert blocks == [2, 2, 1]
    alone = [planner.plan(starts[i:i + 1], goals[i:i + 1])[0] for i in range(len(starts))]
    assert [r.success for r in together] == [r.success for r in alone]
    assert [r.stage_text for r in together] == [r.stage_text for r in alone]
    for a, b in zip(together, alone, strict=True):
        np.testing.assert_allclose(a.q, b.q, atol=1e-4)


@pytest.mark.slow  # 1000 planning problems: minutes on 2 cores
def test_a_thousand_problems_stream_through_one_call(robot):
    planner, starts, goals = plan_many_problems(robot, 1000, seed=5)
    planner = TrajectoryPlanner(robot, planner.scene, TrajectoryConfig(
        guesses=1, iterations=5, problem_chunk=256, roadmap_search="device"))
    results = planner.plan(starts, goals)
    assert len(results) == 1000 and all(r.q is not None for r in results)
    sample = np.arange(0, 1000, 97)
    again = planner.plan(starts[sample], goals[sample])
    assert [results[i].success for i in sample] == [r.success for r in again]
