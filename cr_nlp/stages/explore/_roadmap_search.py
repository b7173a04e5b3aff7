"""Shortest roadmap paths for many start/goal pairs at once.

The roadmap is a padded neighbour table: ``neighbours`` (N, D) node indices and
``weights`` (N, D) edge lengths, +inf where a row has fewer than D edges or an edge was
dropped (lazy PRM). Every pair p attaches its start to the nodes ``start_nodes[p]``
(A,) at lengths ``start_lengths[p]`` and its goal to ``goal_nodes[p]`` at
``goal_lengths[p]`` (+inf pads). Two backends give the same answer up to ties:

- ``"device"``: min-plus (Bellman–Ford) relaxation of all pairs at once in JAX, in a
  ``lax.while_loop`` that stops, per pair, once no node whose distance changed is closer
  than the best goal distance (no later change can shorten the goal's path: weights are
  positive). One compiled program per padded pair count (``chunk_plan`` sizes).
- ``"scipy"``: one ``scipy.sparse.csgraph.dijkstra`` call over the roadmap plus one
  directed start node per pair (it has only outgoing edges, so no path runs through
  another pair's start); a goal is reached through the best of its attachments.

``"auto"`` picks scipy on a CPU backend and the device search elsewhere (measured on a
2-core CPU, see ``SEARCH_CHOICE``).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from ..._cached_jit import cached_jit
from ...runtime import cached
from .._chunks import chunk_plan

SEARCH_BACKENDS = ("auto", "device", "scipy")
SEARCH_CHOICE = "scipy on a CPU backend, device otherwise"
"""What ``"auto"`` picks. Measured with ``cr-nlp bench plan --search-pairs 1 20 1000``
(tdcr3, shelf roadmap of 2048 nodes, 2-core CPU, 2026-12-05, the graph made without
sorting): scipy took 0.9 ms for 1 pair, 5.3 ms for 20 and 0.25 s for 1000; the relaxation
on the CPU 9.5 ms, 8.2 ms and 0.29 s."""
SEARCH_CHUNK = 256
"""Most pairs per compiled search (the relaxation holds (N, D, pairs) sums: 50 MB in
float32 for a 2048-node roadmap of degree 24)."""
SEARCH_SMALLEST = 32
"""Fewest pairs per compiled search (a single query pads to this; with ``SEARCH_CHUNK``
the two compiled shapes of ``chunk_plan``)."""


def neighbour_table(edges: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """(N, D) neighbour indices (int32; a node's own index as padding) and (N, D) edge
    lengths (float64; +inf as padding) of a symmetric CSR graph, D its largest degree."""
    edges = edges.tocsr()
    edges.sort_indices()
    n = edges.shape[0]
    degree = np.diff(edges.indptr)
    width = max(int(degree.max(initial=0)), 1)
    neighbours = np.repeat(np.arange(n, dtype=np.int32)[:, None], width, axis=1)
    weights = np.full((n, width), np.inf)
    row = np.repeat(np.arange(n), degree)
    column = np.arange(edges.nnz) - np.repeat(edges.indptr[:-1], degree)
    neighbours[row, column] = edges.indices
    weights[row, column] = edges.data
    return neighbours, weights


def resolve_backend(search: str) -> str:
    """"device" or "scipy" for a ``search`` setting ("auto" per ``SEARCH_CHOICE``)."""
    if search not in SEARCH_BACKENDS:
        raise ValueError(f"search must be one of {SEARCH_BACKENDS}, got {search!r}")
    if search != "auto":
        return search
    return "scipy" if jax.default_backend() == "cpu" else "device"


def shortest_paths(neighbours: np.ndarray, weights: np.ndarray, start_nodes: np.ndarray,
                   start_lengths: np.ndarray, goal_nodes: np.ndarray, goal_lengths: np.ndarray,
                   search: str = "auto") -> tuple[np.ndarray, list[np.ndarray | None]]:
    """Shortest start → goal paths of P pairs through the roadmap.

    Args:
        neighbours, weights: the roadmap (``neighbour_table``), lengths in the roadmap
            metric (+inf: no edge).
        start_nodes, start_lengths: (P, A) nodes each start attaches to and the lengths of
            those edges (+inf pads; the node index of a pad is ignored).
        goal_nodes, goal_lengths: (P, B) the same for the goals.
        search: "auto", "device" or "scipy" (module docstring).

    Returns (P,) path lengths (float64, +inf where no path exists) and per pair the
    roadmap nodes of its path from the start's side to the goal's (int64), None where
    there is none.
    """
    backend = resolve_backend(search)
    count = len(start_nodes)
    lengths = np.full(count, np.inf)
    paths: list[np.ndarray | None] = [None] * count
    done = 0
    sizes = chunk_plan(count, SEARCH_CHUNK, SEARCH_SMALLEST) if backend == "device" else [
        SEARCH_CHUNK] * -(-count // SEARCH_CHUNK)
    for size in sizes:
        rows = slice(done, min(done + size, count))
        parts = (start_nodes[rows], start_lengths[rows], goal_nodes[rows], goal_lengths[rows])
        if backend == "device":
            dist, last, pred = _device_search(neighbours, weights, *parts, size)
        else:
            dist, last, pred = _scipy_search(neighbours, weights, *parts)
        lengths[rows] = dist
        paths[rows] = _follow(pred, last)
        done += size
    return lengths, paths


def _follow(pred: np.ndarray, last: np.ndarray) -> list[np.ndarray | None]:
    """Paths (start side first) from predecessor rows (P, N) (−1: reached from the start)
    ending at ``last`` (P,) (−1: no path), every pair stepped at once."""
    cursor = last.astype(np.int64)
    steps = [cursor]
    alive = cursor >= 0
    rows = np.arange(len(last))
    for _ in range(pred.shape[1]):
        if not alive.any():
            break
        cursor = np.where(alive, pred[rows, np.maximum(cursor, 0)], -1)
        alive = cursor >= 0
        steps.append(cursor)
    table = np.stack(steps, axis=1)
    return [table[p, :int(np.sum(table[p] >= 0))][::-1] if last[p] >= 0 else None
            for p in range(len(last))]


# ================================================================ the device search


def _padded(array: np.ndarray, rows: int, fill: float) -> np.ndarray:
    out = np.full((rows,) + array.shape[1:], fill, dtype=array.dtype)
    out[:len(array)] = array
    return out


def _device_search(neighbours: np.ndarray, weights: np.ndarray, start_nodes: np.ndarray,
                   start_lengths: np.ndarray, goal_nodes: np.ndarray,
                   goal_lengths: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray,
                                                                 np.ndarray]:
    count = len(start_nodes)
    dist, last, pred = _relaxation()(
        jnp.asarray(neighbours, jnp.int32), jnp.asarray(weights, jnp.float32),
        jnp.asarray(_padded(np.maximum(start_nodes, 0), size, 0), jnp.int32),
        jnp.asarray(_padded(start_lengths, size, np.inf), jnp.float32),
        jnp.asarray(_padded(np.maximum(goal_nodes, 0), size, 0), jnp.int32),
        jnp.asarray(_padded(goal_lengths, size, np.inf), jnp.float32))
    dist = np.asarray(dist, dtype=np.float64)[:count]
    return dist, np.asarray(last)[:count], np.asarray(pred)[:count]


@cached(maxsize=1)
def _relaxation() -> Any:
    return cached_jit(_relax, name="the roadmap search")


def _relax(neighbours: jax.Array, weights: jax.Array, start_nodes: jax.Array,
           start_lengths: jax.Array, goal_nodes: jax.Array,
           goal_lengths: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Min-plus relaxation of P pairs on one graph: (P,) goal distances, (P,) last roadmap
    node of each path (−1: none) and (P, N) predecessors (−1: attached to the start).
    Distances are held node-major, (N, P), so that the gather over neighbours reads whole
    rows (contiguous on a CPU, coalesced on a GPU)."""
    pairs, n = start_nodes.shape[0], neighbours.shape[0]
    inf = jnp.asarray(jnp.inf, weights.dtype)
    columns = jnp.broadcast_to(jnp.arange(pairs)[:, None], start_nodes.shape)
    dist = jnp.full((n, pairs), inf).at[start_nodes, columns].min(start_lengths)
    goal_columns = jnp.broadcast_to(jnp.arange(pairs)[:, None], goal_nodes.shape)

    def relaxed(dist: jax.Array) -> jax.Array:
        return dist[neighbours] + weights[:, :, None]             # (N, D, P)

    def goal_best(dist: jax.Array) -> jax.Array:
        return jnp.min(dist[goal_nodes, goal_columns] + goal_lengths, axis=1)

    def active(changed: jax.Array, dist: jax.Array) -> jax.Array:
        # A pair goes on while a node that just changed is closer than its goal.
        frontier = jnp.min(jnp.where(changed, dist, inf), axis=0)
        return frontier < goal_best(dist)

    def step(state: tuple) -> tuple:
        dist, changed, _ = state
        go = active(changed, dist)
        best = jnp.min(relaxed(dist), axis=1)
        better = (best < dist) & go[None, :]
        return jnp.where(better, best, dist), better, go.any()

    changed = jnp.isfinite(dist)
    dist, _, _ = jax.lax.while_loop(lambda s: s[2], step,
                                    (dist, changed, jnp.any(active(changed, dist))))
    # Predecessors from the final distances: the neighbour that gives a node its
    # distance (a strictly shorter one, as weights are positive, so no cycles); −1 where
    # the start's own edge is shorter. Nodes on a goal's path are settled (the loop ends
    # only when no change can reach them), so their rows are exact.
    through = relaxed(dist)
    pick = jnp.argmin(through, axis=1)                            # (N, P)
    via = jnp.take_along_axis(through, pick[:, None], axis=1)[:, 0]
    pred = jnp.where(via <= dist, jnp.take_along_axis(neighbours, pick, axis=1), -1)
    through_goal = dist[goal_nodes, goal_columns] + goal_lengths  # (P, B)
    length = jnp.min(through_goal, axis=1)
    last = goal_nodes[jnp.arange(pairs), jnp.argmin(through_goal, axis=1)]
    return length, jnp.where(jnp.isfinite(length), last, -1), pred.T


# ================================================================ scipy


def _scipy_search(neighbours: np.ndarray, weights: np.ndarray, start_nodes: np.ndarray,
                  start_lengths: np.ndarray, goal_nodes: np.ndarray,
                  goal_lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scipy backend: the roadmap's rows as they are (a neighbour table holds each
    edge once) and one row per pair's start, made into a CSR graph without sorting, one
    Dijkstra from every start, and each goal reached through the best of its attachments
    (the device search's rule)."""
    n, pairs = len(neighbours), len(start_nodes)
    keep = np.isfinite(weights)
    rows, nodes, lengths = _shortest_attachments(start_nodes, start_lengths)
    counts = np.r_[keep.sum(axis=1), np.bincount(rows, minlength=pairs)]
    # Positive lengths only: csgraph reads an explicit zero as no edge.
    graph = sp.csr_matrix((np.maximum(np.r_[weights[keep], lengths], 1e-12),
                           np.r_[neighbours[keep], nodes], np.r_[0, np.cumsum(counts)]),
                          shape=(n + pairs, n + pairs))
    dist, pred = dijkstra(graph, directed=True, indices=n + np.arange(pairs),
                          return_predecessors=True)
    attached = np.isfinite(goal_lengths)
    at = np.where(attached, goal_nodes, 0)
    through = np.where(attached, np.take_along_axis(dist, at, axis=1) + goal_lengths, np.inf)
    best = np.argmin(through, axis=1)[:, None]
    length_out = np.take_along_axis(through, best, axis=1)[:, 0]
    last = np.where(np.isfinite(length_out), np.take_along_axis(at, best, axis=1)[:, 0], -1)
    pred = pred[:, :n].astype(np.int64)
    pred[pred >= n] = -1
    return length_out, last, pred


def _shortest_attachments(nodes: np.ndarray, lengths: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pair, node, length) of the finite attachments (P, A), the shortest of a node
    attached twice to one pair (a sparse matrix would add them up), by pair then node."""
    pair, column = np.nonzero(np.isfinite(lengths))
    node, length = nodes[pair, column], lengths[pair, column]
    order = np.lexsort((length, node, pair))
    first = np.ones(len(order), dtype=bool)
    first[1:] = (np.diff(pair[order]) != 0) | (np.diff(node[order]) != 0)
    order = order[first]
    return pair[order], node[order], length[order]
