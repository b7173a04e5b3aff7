"""Stage 1 of tension-space planning: a roadmap over clear tension sets, cached on disk.

The nodes are tension sets whose equilibria keep δ (the planner's via candidates). Each
node is joined to its ``neighbours`` nearest in the legs' own metric, the largest change
of any tendon (N; the leg's duration at the rate limit, up to a constant), and an edge is
kept where the whole straight leg is clear: the caller's ``screen`` solves every sample
the motion verdict will check along it (all edges in one batch). A query joins the start
and the goal to their ``connect`` nearest nodes the same way and takes the quickest route
(Dijkstra over leg durations, ``scipy.sparse.csgraph``): any number of via sets, where the
search before it tried at most two.

A roadmap depends on the robot, the scene, the load case, the nodes and how legs are
screened (rate, waypoint spacing, samples, δ, the rod's discretisation): the caller puts
all of them in ``key``, which names the cache file, so a new process under the same loads
loads the edges instead of screening them again and any change builds a new roadmap. The
nodes themselves (which random tension sets are clear: ``clear_nodes``) are cached the
same way, so a new process's first plan that needs a via solves none of the pool again.
Units: newtons.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...runtime import cache_dir, cached_arrays

FORMAT_VERSION = 1
"""Bumped when the cached file's content or the build procedure changes."""

Screen = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(starts (L, n) N, ends (L, n) N) → (L,) True where the straight leg is clear."""

_CACHE_STATS = {"hits": 0, "builds": 0}


def tension_roadmap_cache_stats() -> dict[str, int]:
    """How many tension roadmaps this process loaded from the disk cache and built."""
    return dict(_CACHE_STATS)


def leg_change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The largest change of any tendon from ``a`` to ``b`` (…, n) N: a leg's duration at
    the rate limit, up to the constant factor."""
    return np.max(np.abs(np.asarray(b) - np.asarray(a)), axis=-1)


def _nearest(points: np.ndarray, nodes: np.ndarray, count: int) -> np.ndarray:
    """(P, k) indices of the ``count`` nodes nearest each point (largest-change metric,
    nearest first; a node never its own neighbour when ``points`` are the nodes)."""
    change = leg_change(points[:, None, :], nodes[None, :, :])
    if points is nodes:
        np.fill_diagonal(change, np.inf)
    count = min(count, nodes.shape[0] - (points is nodes))
    return np.argsort(change, axis=1, kind="stable")[:, :max(count, 0)]


@dataclass(frozen=True)
class TensionRoadmap:
    """Clear tension sets and the clear straight legs between neighbours."""

    nodes: np.ndarray
    """(V, n) tension sets whose equilibria are clear, N."""
    edges: np.ndarray
    """(E, 2) node indices of the clear legs (each pair once, smaller index first)."""
    build_seconds: float
    """Seconds the build took (loaded from the cache: the original build's)."""
    loaded_from_cache: bool = False

    def route(self, start: np.ndarray, goal: np.ndarray, screen: Screen,
              connect: int) -> list[int] | None:
        """Node indices of the quickest route start → nodes → goal over clear legs (the
        start's and goal's legs to their ``connect`` nearest nodes screened here), or None
        where the roadmap joins no clear leg of the start to one of the goal."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        v = len(self.nodes)
        if v == 0:
            return None
        start, goal = np.asarray(start, float), np.asarray(goal, float)
        ends = np.stack([start, goal])
        near = _nearest(ends, self.nodes, connect)
        tails = np.repeat(ends, near.shape[1], axis=0)
        heads = self.nodes[near.ravel()]
        # legs are screened from the start towards a node and from a node to the goal
        first = np.arange(near.size) < near.shape[1]
        clear = screen(np.where(first[:, None], tails, heads),
                       np.where(first[:, None], heads, tails))
        rows = [self.edges[:, 0], self.edges[:, 1]]
        cols = [self.edges[:, 1], self.edges[:, 0]]
        at = near.ravel()[clear]
        end = np.where(first[clear], v, v + 1)
        rows += [at, end]
        cols += [end, at]
        a, b = np.concatenate(rows), np.concatenate(cols)
        every = np.concatenate([self.nodes, ends])
        weight = leg_change(every[a], every[b]) + 1e-12    # 0 would read as no edge
        graph = coo_matrix((weight, (a, b)), shape=(v + 2, v + 2)).tocsr()
        distance, previous = dijkstra(graph, indices=v, return_predecessors=True)
        if not np.isfinite(distance[v + 1]):
            return None
        path, at_node = [], int(previous[v + 1])
        while at_node != v:
            path.append(at_node)
            at_node = int(previous[at_node])
        return path[::-1]


def _cached(kind: str, key: dict[str, Any] | None, arrays: tuple[np.ndarray, ...],
            build: Callable[[], dict[str, np.ndarray]]) -> tuple[dict[str, np.ndarray], bool]:
    """``build()``'s arrays, from ``cache_dir()/tension_roadmaps`` where a file of this
    ``kind``, ``key`` (JSON-able) and ``arrays`` is there, else built and written there
    (``key`` None: built, not cached); and whether they came from the cache."""
    path = None
    if key is not None:
        h = hashlib.sha256(json.dumps({"version": FORMAT_VERSION, "kind": kind, **key},
                                      sort_keys=True, default=str).encode())
        for array in arrays:
            h.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
        path = cache_dir() / "tension_roadmaps" / f"{kind}-{h.hexdigest()}.npz"
    return cached_arrays(path, build, _CACHE_STATS)


def clear_nodes(candidates: np.ndarray, clear: Callable[[np.ndarray], np.ndarray],
                key: dict[str, Any] | None = None,
                arrays: tuple[np.ndarray, ...] = ()) -> np.ndarray:
    """The ``candidates`` (V, n) N whose equilibria ``clear`` accepts (one batch), cached
    like the roadmap under ``key`` and ``arrays`` with the candidates themselves: a new
    process under the same loads solves none of them again."""
    candidates = np.asarray(candidates, dtype=float)
    out, _ = _cached("nodes", key, (candidates, *arrays),
                     lambda: {"nodes": candidates[np.asarray(clear(candidates), bool)]})
    return np.asarray(out["nodes"], dtype=float)


def tension_roadmap(nodes: np.ndarray, screen: Screen, neighbours: int,
                    key: dict[str, Any] | None = None,
                    arrays: tuple[np.ndarray, ...] = ()) -> TensionRoadmap:
    """The roadmap over ``nodes`` (V, n) N: each joined to its ``neighbours`` nearest
    where ``screen`` finds the leg clear.

    ``key`` (JSON-able: robot, scene, screening settings) and ``arrays`` (the load case,
    the scene's geometry) name the cache file in ``cache_dir()/tension_roadmaps`` with the
    nodes and ``neighbours``; None: not cached. A damaged cache file is rebuilt."""
    nodes = np.asarray(nodes, dtype=float)

    def build() -> dict[str, np.ndarray]:
        began = time.perf_counter()
        near = _nearest(nodes, nodes, neighbours)
        pairs = np.stack([np.repeat(np.arange(len(nodes)), near.shape[1]), near.ravel()], 1)
        pairs = np.unique(np.sort(pairs, axis=1), axis=0).reshape(-1, 2)
        clear = (screen(nodes[pairs[:, 0]], nodes[pairs[:, 1]]) if len(pairs)
                 else np.zeros(0, bool))
        return {"edges": pairs[clear], "build_seconds": np.array(time.perf_counter() - began)}

    out, hit = _cached("edges", None if key is None else {"neighbours": neighbours, **key},
                       (nodes, *arrays), build)
    return TensionRoadmap(nodes, np.asarray(out["edges"], dtype=np.int64).reshape(-1, 2),
                          float(out["build_seconds"]), hit)
