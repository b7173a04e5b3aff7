"""The roadmap in tension space (``stages.explore._tension_roadmap``): routes checked
against an obstacle written in closed form (a square of forbidden tension pairs, every leg
re-checked here at fine samples), the disk cache, and a plan through it on the Cosserat
rod replayed by fresh statics and python-fcl."""

from __future__ import annotations

import numpy as np
import pytest

from cr_nlp.stages.explore import (
    clear_nodes,
    leg_change,
    tension_roadmap,
    tension_roadmap_cache_stats,
)

LOW, HIGH = 3.0, 7.0
"""A square of tension pairs (N) no leg may cross."""


def _blocked(points: np.ndarray) -> np.ndarray:
    return np.all((points > LOW) & (points < HIGH), axis=-1)


def _leg_clear(a: np.ndarray, b: np.ndarray, samples: int = 201) -> np.ndarray:
    """(L,) True where no point of the leg a → b lies in the square (fine samples)."""
    t = np.linspace(0.0, 1.0, samples)[None, :, None]
    return ~_blocked(a[:, None] + t * (b - a)[:, None]).any(axis=1)


class _Counting:
    """The closed-form screen, counting the legs it was asked about."""

    def __init__(self) -> None:
        self.legs = 0

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        self.legs += len(a)
        return _leg_clear(a, b)


def _nodes() -> np.ndarray:
    """A 11 × 11 grid of tension pairs over [0, 10] N, without the blocked ones."""
    grid = np.stack(np.meshgrid(np.linspace(0, 10, 11), np.linspace(0, 10, 11)), -1)
    grid = grid.reshape(-1, 2)
    return grid[~_blocked(grid)]


@pytest.fixture()
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path / "cache"))


def test_a_route_goes_around_the_blocked_square_on_clear_legs() -> None:
    nodes = _nodes()
    roadmap = tension_roadmap(nodes, _Counting(), neighbours=8)
    assert _leg_clear(nodes[roadmap.edges[:, 0]], nodes[roadmap.edges[:, 1]]).all()
    start, goal = np.array([5.0, 1.5]), np.array([5.0, 8.5])
    assert not _leg_clear(start[None], goal[None])[0]       # the direct leg is blocked
    route = roadmap.route(start, goal, _Counting(), connect=4)
    assert route is not None and len(route) >= 2
    points = np.concatenate([start[None], nodes[route], goal[None]])
    assert _leg_clear(points[:-1], points[1:]).all()
    # The quickest way around: out to a side of the square (x = 3 or 7) while climbing,
    # 2 N for 1.5 N of climb at each end, and 4 N along the side: 8 N. The route is no
    # quicker than that, and no slower than the side's column of grid nodes (2 + 6 + 2).
    cost = float(leg_change(points[:-1], points[1:]).sum())
    assert 8.0 - 1e-9 <= cost <= 10.0 + 1e-9, cost


def test_no_route_where_the_goal_is_walled_off() -> None:
    roadmap = tension_roadmap(_nodes(), _Counting(), neighbours=8)

    def walled(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        goal = np.array([5.0, 8.5])
        return _leg_clear(a, b) & ~np.all(b == goal, axis=-1) & ~np.all(a == goal, axis=-1)

    assert roadmap.route(np.array([5.0, 1.5]), np.array([5.0, 8.5]), walled, 4) is None
    assert tension_roadmap(np.zeros((0, 2)), _Counting(), 8).route(
        np.zeros(2), np.ones(2), _Counting(), 4) is None


def test_the_disk_cache_is_reused_and_keyed_on_what_changes_it(private_cache) -> None:
    nodes, key = _nodes(), {"robot": "toy", "margin": 0.002}
    screen = _Counting()
    built = tension_roadmap(nodes, screen, 8, key)
    asked, before = screen.legs, tension_roadmap_cache_stats()
    again = tension_roadmap(nodes, screen, 8, key)
    assert again.loaded_from_cache and not built.loaded_from_cache
    assert screen.legs == asked                               # nothing screened again
    np.testing.assert_array_equal(again.edges, built.edges)
    assert tension_roadmap_cache_stats()["hits"] == before["hits"] + 1
    for changed in ({**key, "margin": 0.003}, key):
        other = tension_roadmap(nodes if changed is not key else nodes + 0.5, screen, 8,
                                changed)
        assert not other.loaded_from_cache
    assert not tension_roadmap(nodes, screen, 6, key).loaded_from_cache


def test_the_clear_nodes_are_cached_too(private_cache) -> None:
    grid = np.stack(np.meshgrid(np.linspace(0, 10, 11), np.linspace(0, 10, 11)), -1)
    candidates, key, asked = grid.reshape(-1, 2), {"robot": "toy"}, []

    def clear(sets: np.ndarray) -> np.ndarray:
        asked.append(len(sets))
        return ~_blocked(sets)

    first = clear_nodes(candidates, clear, key)
    np.testing.assert_array_equal(first, _nodes())           # the square's 9 left out
    again = clear_nodes(candidates, clear, key)
    np.testing.assert_array_equal(again, first)
    assert asked == [121]                                     # solved once
    clear_nodes(candidates, clear, {"robot": "toy", "margin": 0.003})
    clear_nodes(candidates[:-1], clear, key)
    assert asked == [121, 121, 120]


def test_a_plan_through_the_roadmap_replayed_by_fresh_statics_and_fcl(private_cache) -> None:
    """A problem of ``bench tension --suite clutter`` whose direct leg is blocked, with
    one via candidate screened (not clear) of a pool of 128: the roadmap routes it through
    two via sets or more; every waypoint and the verdict's samples between them, solved
    again here, keep δ by python-fcl and the rate limit holds."""
    from cr_nlp import TensionTrajectoryConfig, TensionTrajectoryPlanner
    from cr_nlp.bench.tension_clutter import clutter_scene
    from cr_nlp.model import load_robot
    from cr_nlp.model.cosserat import solve_statics
    from cr_nlp.tasks.mechanics._motion import interpolated
    from cr_nlp.world.check import check_chains

    rao = load_robot("tdcr2_rao2021")
    gravity, payload = [0.0, 0.0, -9.81], [0.0, 0.0, -0.005 * 9.81]
    planner = TensionTrajectoryPlanner(rao, clutter_scene(rao, 0), TensionTrajectoryConfig(
        via_pool=128, via_candidates=1, chain_iterations=0))
    start = np.array([3.789121, 2.751595, 0.0, 0.89808, 5.689187, 0.0])
    goal = np.array([5.039994, 0.0, 0.0, 3.876874, 2.343225, 0.0])
    result = planner.plan(start, goal, gravity=gravity, tip_force=payload)[0]
    assert result.success, (result.reason, result.notes)
    assert result.notes[0].endswith("of the pool (the roadmap)"), result.notes
    assert result.notes[0].count(",") >= 1                     # two vias or more
    np.testing.assert_array_equal(result.tensions[[0, -1]], np.stack([start, goal]))
    cfg = planner.config
    assert np.abs(np.diff(result.tensions, axis=0)).max() / cfg.dt <= cfg.tension_rate_max
    samples = interpolated(result.tensions, cfg.samples_between)[0]
    solved = solve_statics(rao, samples, payload, None, gravity)
    assert solved.converged.all()
    checked = check_chains(rao, planner.scene, solved.positions, 10)
    assert checked.obstacle_distance.min() >= cfg.safety_margin
