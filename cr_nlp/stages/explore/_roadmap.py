"""Stage 1 for trajectories: a probabilistic roadmap (PRM) per (robot, scene), searched
for shortest paths.

Build (once per robot, scene and ``RoadmapConfig``; cached on disk):

1. Sobol configurations are drawn in batches and kept when their clearance (the JAX
   sphere-model clearance, float32, with the broad-phase cell table of
   ``world._broad_phase``, exact below the margin) is at least the margin.
2. Each node is joined to its ``neighbours`` nearest nodes (``cKDTree``) in the
   roadmap metric below.
3. An edge is kept when ``edge_checks`` interpolated configurations along it keep the
   margin (checked in fixed-size batches, split over every JAX device).

Query (any number of start/goal pairs at once, ``query_many_z``): starts and goals are
attached to their nearest nodes by edges that pass the ``edge_checks`` samples
(``neighbours`` nearest, widened 4× at a time while none passes), the shortest paths of
all pairs are found in one batched search (``roadmap_search``: scipy's Dijkstra, or a
min-plus relaxation in JAX on the device), and the edges of those paths, attach edges
included, are checked densely (every ``query_step`` in the metric); an edge that fails
is dropped and the pairs that used it search again (lazy PRM). Every check is one
batched clearance call for all pairs. The path is resampled uniformly by arc length.

Metric: the Euclidean distance in the bending-vector form z = [ux, uy, L]·n
(radians for u = θ(cos φ, sin φ), metres for L). It has no azimuth wrap-around and no
singularity at θ = 0 (every φ at θ = 0 is one point), straight-line interpolation in z
stays inside the limits ‖u‖ ≤ θmax (a disk is convex), and one radian of bending weighs
like one metre of length, which moves a 1 m segment's tip by about as much.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import time
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..._cached_jit import cached_jit
from ..._files import write_atomic
from ...model import Robot, q_to_z, q_to_z_numpy, z_to_q_numpy
from ...runtime import cache_dir, cached
from ...world import Scene, body_gap_tolerance, scene_arrays, scene_digest
from ...world._broad_phase import PartCells, part_cells, reach_box
from ...world._clearance_groups import near_clearance_z
from ._roadmap_search import neighbour_table, shortest_paths
from ._seed_pool import sobol_configurations

CHECK_CHUNK = 1024
"""Configurations per clearance call (fixed, so the check compiles once per scene).
Measured with the broad-phase table on the 2-core CPU (jax 0.10, tdcr3, 16 384 Sobol
configurations in shelf and cabinet): 4.2–4.5 µs per configuration in chunks of 512 or
1024, 10–11 µs in chunks of 2048 or 4096 (the gathered face planes no longer fit the
caches)."""
CHUNKS = (64, 256, CHECK_CHUNK)
"""Compiled batch sizes: a request uses the smallest that holds it (RRT steps and
query-time checks are small), else chunks of ``CHECK_CHUNK``."""
SAMPLE_BLOCK = 16 * CHECK_CHUNK
"""Most interpolated configurations an edge check holds at once."""
FORMAT_VERSION = 2
"""Bumped when the cached file's content or the build procedure changes."""

_CACHE_STATS = {"hits": 0, "builds": 0}


def roadmap_cache_stats() -> dict[str, int]:
    """How often ``Roadmap.build`` loaded a roadmap from disk (``hits``) or built one
    (``builds``) in this process."""
    return dict(_CACHE_STATS)


def roadmap_cache_dir() -> Path:
    """Where roadmaps are cached: ``cache_dir()/roadmaps``."""
    return cache_dir() / "roadmaps"


@dataclass(frozen=True)
class RoadmapConfig:
    """Settings of the roadmap build and query."""

    nodes: int = 2048
    """Collision-free configurations to keep (Sobol draws continue until this many keep
    the margin, at most ``max_draws_factor`` × nodes draws)."""
    neighbours: int = 10
    """k of the k-nearest-neighbour edges (per node, and per attached start/goal)."""
    edge_checks: int = 8
    """Interpolated configurations checked inside each edge at build time."""
    margin: float | None = None
    """Clearance (m, sphere model) every node and checked sample must keep; None means
    ``body_gap_tolerance(robot) + 0.002``, which makes the capsule body (python-fcl)
    at least 2 mm clear at the checked samples."""
    seed: int = 0
    """Seed of the Sobol draws."""
    query_step: float = 0.02
    """Spacing (rad or m in z) of the dense re-check of a path's edges at query time."""
    max_query_rounds: int = 2000
    """Most searches per query (each drops the path's edges that fail the dense check);
    queries that run out return None."""
    max_draws_factor: int = 16
    """Give up drawing nodes after this many × ``nodes`` draws (very cluttered scenes)."""


def resolved_margin(robot: Robot, config: RoadmapConfig) -> float:
    """The margin (m) a roadmap built with ``config`` keeps."""
    return float(config.margin if config.margin is not None
                 else body_gap_tolerance(robot) + 0.002)


# ================================================================ helpers


def interpolate_z(za: np.ndarray, zb: np.ndarray, count: int) -> np.ndarray:
    """(…, count, 3n) configurations evenly spaced on the straight line from ``za`` to
    ``zb`` (…, 3n) in the bending-vector form, both ends included (count ≥ 2)."""
    za, zb = np.asarray(za, dtype=float), np.asarray(zb, dtype=float)
    t = np.linspace(0.0, 1.0, count)[:, None]
    return za[..., None, :] + t * (zb - za)[..., None, :]


def resample_polyline(points_z: np.ndarray, count: int) -> np.ndarray:
    """(count, 3n) configurations spaced uniformly by arc length (roadmap metric) along
    the polyline through ``points_z`` (K, 3n), first and last points kept."""
    points_z = np.asarray(points_z, dtype=float)
    if len(points_z) == 1:
        return np.repeat(points_z, count, axis=0)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points_z, axis=0), axis=1))])
    if arc[-1] <= 0.0:
        return np.repeat(points_z[:1], count, axis=0)
    s = np.linspace(0.0, arc[-1], count)
    return np.stack([np.interp(s, arc, points_z[:, d]) for d in range(points_z.shape[1])],
                    axis=1)


def polyline_length(points_z: np.ndarray) -> float:
    """Length of a polyline (K, 3n) in the roadmap metric (rad and m mixed, see module)."""
    return float(np.sum(np.linalg.norm(np.diff(np.asarray(points_z), axis=0), axis=1)))


@cached(maxsize=16)
def _chunk_program(robot: Robot, chunk: int) -> Any:
    """``near_clearance_z`` over a (chunk, 3n) float32 batch; chunks of 512 and more are
    split over the JAX devices (splitting tiny ones costs more than it saves)."""
    return cached_jit(partial(near_clearance_z, robot), name="the roadmap clearance",
                      batched=None if chunk < 512 else (False, False, True), by_shape=True)


class ClearanceChecker:
    """Batched float32 sphere-model clearance of bending-vector configurations, in
    fixed-size chunks (one compilation per robot and scene part counts).

    ``cutoff`` (m): with one, each body sphere is measured only against the parts of its
    cell in a broad-phase table (``world._broad_phase``, built here): the values are exact
    below ``cutoff`` and only known to be at least ``cutoff`` above it, so the checker
    answers ``clearance ≥ margin`` exactly for margins up to ``cutoff``. None (or a scene
    whose table would drop parts): every part is measured."""

    def __init__(self, robot: Robot, scene: Scene, cutoff: float | None = None) -> None:
        self.robot = robot
        self.arrays = scene_arrays(scene, jnp.float32)
        self.cells: PartCells | None = None
        if cutoff is not None and self.arrays.n_parts > 0:
            cells = part_cells(scene, robot.backbone_radius, reach_box(robot), cutoff,
                               dtype=jnp.float32)
            self.cells = cells if cells.truncated == 0 else None
        self.cutoff = math.inf if self.cells is None else self.cells.cutoff
        """Values below this (m) are exact clearances; +inf: all are."""
        self.programs = {chunk: _chunk_program(robot, chunk) for chunk in CHUNKS}
        self.calls = 0
        self._ask_others = False

    def __call__(self, z: np.ndarray) -> np.ndarray:
        """(B,) clearances (m) of z (B, 3n); values at or above ``cutoff`` only say that
        the clearance is at least ``cutoff``."""
        z = np.asarray(z, dtype=np.float32).reshape(-1, self.robot.dof)
        out = np.empty(len(z), dtype=np.float64)
        chunk = next((c for c in CHUNKS if len(z) <= c), CHECK_CHUNK)
        for start in range(0, len(z), chunk):
            block = z[start:start + chunk]
            padded = np.empty((chunk, self.robot.dof), dtype=np.float32)
            padded[:len(block)] = block
            padded[len(block):] = block[:1]
            # numpy, moved by the program's call: ``jnp.asarray`` first was an eager JAX
            # operation on the host (a 256-row call 1.65 → 1.58 ms)
            values = self.programs[chunk](self.arrays, self.cells, padded)
            out[start:start + len(block)] = np.asarray(values)[:len(block)]
            self.calls += 1
        if self._ask_others:
            self._ask_others = False
            for other in CHUNKS:
                if other != chunk:
                    self.programs[other].ahead(self.arrays, self.cells, np.zeros(
                        (other, self.robot.dof), np.float32))
        return out

    def compile_all(self) -> None:
        """Have every chunk size compiled from the next call on, so that later queries,
        whose request sizes vary, do not compile inside a timed call: the next call
        compiles the size it needs and then asks for the others in the background
        (``CachedProgram.ahead``; a call that needs one before it is built builds it
        itself). A warm ``cr-nlp plan`` of 20 problems used only the largest size; loading
        the two others on its main thread took 0.27 s."""
        self._ask_others = True


def _edge_free(checker: ClearanceChecker, za: np.ndarray, zb: np.ndarray, counts: np.ndarray,
               margin: float) -> np.ndarray:
    """(E,) True where every interior sample of the edge za→zb (E, 3n) keeps the margin;
    edge e has ``counts[e]`` interior samples, evenly spaced. The samples are made for
    groups of edges of about ``SAMPLE_BLOCK`` samples at a time (bounded memory for the
    dense checks of many queries)."""
    counts = np.asarray(counts, dtype=np.int64)
    free = np.ones(len(za), dtype=bool)
    ends = np.cumsum(counts)
    first = 0
    while first < len(za):
        before = ends[first - 1] if first else 0
        last = max(first + 1, int(np.searchsorted(ends, before + SAMPLE_BLOCK, side="right")))
        part = counts[first:last]
        edge = np.repeat(np.arange(len(part)), part)
        offsets = np.arange(len(edge)) - np.repeat(np.cumsum(part) - part, part)
        t = (offsets + 1.0) / (part[edge] + 1.0)
        a, b = za[first:last].take(edge, axis=0), zb[first:last].take(edge, axis=0)
        ok = checker(a + t[:, None] * (b - a)) >= margin
        free[first + edge[~ok]] = False
        first = last
    return free


def _scene_key(robot: Robot, scene: Scene, config: RoadmapConfig) -> str:
    """sha256 of the robot, the scene (its file form and its parts' geometry, which
    covers mesh contents and their decomposition) and the settings."""
    return hashlib.sha256(json.dumps(
        {"version": FORMAT_VERSION, "robot": robot.to_dict(), "scene": scene_digest(scene),
         "config": asdict(config), "margin": resolved_margin(robot, config),
         "chunk": CHECK_CHUNK}, sort_keys=True, default=str).encode()).hexdigest()


# ================================================================ the roadmap


class Roadmap:
    """Collision-free configurations (``nodes_z``, (N, 3n) bending-vector form) joined
    by collision-free straight edges (``edges``, (N, N) symmetric CSR of edge lengths
    in the roadmap metric). Build with ``Roadmap.build``."""

    def __init__(self, robot: Robot, scene: Scene, config: RoadmapConfig,
                 nodes_z: np.ndarray, edges: sp.csr_matrix, build_seconds: float) -> None:
        self.robot = robot
        self.scene = scene
        self.config = config
        self.margin = resolved_margin(robot, config)
        self.nodes_z = np.asarray(nodes_z, dtype=float)
        self.edges = edges.tocsr()
        self.build_seconds = float(build_seconds)
        """Seconds the build took (when loaded from the cache: the original build's)."""
        self.loaded_from_cache = False
        self.tree = cKDTree(self.nodes_z)
        self._checker: ClearanceChecker | None = None
        self._queried = False
        self._dense_ok: dict[tuple[int, int], bool] = {}
        self._neighbours: np.ndarray | None = None
        self._weights: np.ndarray | None = None
        self.last_query_rounds = 0
        """Batched searches the last query needed (lazy edge checks)."""

    @property
    def checker(self) -> ClearanceChecker:
        if self._checker is None:
            self._checker = ClearanceChecker(self.robot, self.scene, self.margin)
        return self._checker

    @property
    def edge_count(self) -> int:
        """Undirected edges."""
        return int(self.edges.nnz // 2)

    # ------------------------------------------------------------ build

    @classmethod
    def build(cls, robot: Robot, scene: Scene, config: RoadmapConfig = RoadmapConfig(),
              cache: bool = True) -> Roadmap:
        """The roadmap of ``robot`` in ``scene``: loaded from ``roadmap_cache_dir()`` when
        one with the same robot, scene and settings is there (``cache``), else built
        (and written there)."""
        path = roadmap_cache_dir() / f"{_scene_key(robot, scene, config)}.npz"
        if cache and path.exists():
            try:
                with np.load(path) as data:
                    nodes_z = data["nodes_z"]
                    edges = sp.csr_matrix((data["data"], data["indices"], data["indptr"]),
                                          shape=(len(nodes_z), len(nodes_z)))
                    seconds = float(data["build_seconds"])
                _CACHE_STATS["hits"] += 1
                roadmap = cls(robot, scene, config, nodes_z, edges, seconds)
                roadmap.loaded_from_cache = True
                return roadmap
            except (OSError, KeyError, ValueError):
                pass  # a damaged cache file is rebuilt and overwritten
        roadmap = cls._build(robot, scene, config)
        _CACHE_STATS["builds"] += 1
        if cache:
            path.parent.mkdir(parents=True, exist_ok=True)
            buffer = io.BytesIO()
            e = roadmap.edges
            np.savez(buffer, nodes_z=roadmap.nodes_z, data=e.data, indices=e.indices,
                     indptr=e.indptr, build_seconds=roadmap.build_seconds)
            # Write then rename, so a concurrent reader never sees half a file.
            write_atomic(path, buffer.getvalue())
        return roadmap

    @classmethod
    def _build(cls, robot: Robot, scene: Scene, config: RoadmapConfig) -> Roadmap:
        start = time.perf_counter()
        margin = resolved_margin(robot, config)
        checker = ClearanceChecker(robot, scene, margin)
        kept: list[np.ndarray] = []
        total, drawn, round_ = 0, 0, 0
        while total < config.nodes and drawn < config.max_draws_factor * config.nodes:
            # A power of two keeps the Sobol points balanced.
            batch = 1 << int(np.ceil(np.log2(max(CHECK_CHUNK, 2 * (config.nodes - total)))))
            q = sobol_configurations(robot, batch, seed=config.seed * 7919 + round_)
            z = np.asarray(q_to_z(robot, q), dtype=float)
            free = z[checker(z) >= margin]
            kept.append(free)
            total += len(free)
            drawn += batch
            round_ += 1
        nodes_z = np.concatenate(kept)[:config.nodes] if kept else np.zeros((0, robot.dof))
        n = len(nodes_z)
        k = min(config.neighbours, n - 1)
        if k < 1:
            return cls(robot, scene, config, nodes_z, sp.csr_matrix((n, n)),
                       time.perf_counter() - start)
        tree = cKDTree(nodes_z)
        _, idx = tree.query(nodes_z, k=k + 1)
        i = np.repeat(np.arange(n), k)
        j = idx[:, 1:].ravel()
        pairs = np.unique(np.sort(np.c_[i, j], axis=1), axis=0)
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        ok = _edge_free(checker, nodes_z[pairs[:, 0]], nodes_z[pairs[:, 1]],
                        np.full(len(pairs), config.edge_checks), margin)
        pairs = pairs[ok]
        length = np.linalg.norm(nodes_z[pairs[:, 0]] - nodes_z[pairs[:, 1]], axis=1)
        # Lengths are > 0 (distinct Sobol points): csgraph reads explicit zeros as no edge.
        edges = sp.coo_matrix((np.r_[length, length], (np.r_[pairs[:, 0], pairs[:, 1]],
                                                        np.r_[pairs[:, 1], pairs[:, 0]])),
                              shape=(n, n)).tocsr()
        roadmap = cls(robot, scene, config, nodes_z, edges, time.perf_counter() - start)
        roadmap._checker = checker
        return roadmap

    # ------------------------------------------------------------ query

    def dense_free(self, za: np.ndarray, zb: np.ndarray) -> np.ndarray:
        """(E,) True where the straight edge za → zb (E, 3n each) keeps the margin at
        every ``query_step`` (one batched clearance call for all edges)."""
        za, zb = np.atleast_2d(za), np.atleast_2d(zb)
        counts = np.maximum(1, np.ceil(np.linalg.norm(zb - za, axis=1)
                                       / self.config.query_step).astype(np.int64))
        return _edge_free(self.checker, za, zb, counts, self.margin)

    def _attach(self, z: np.ndarray, dense: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Nearby nodes that each configuration z (M, 3n) may connect to without collision:
        (M, ``neighbours``) indices (−1 pads) and lengths (+inf pads), the nearest whose
        edge keeps the margin at ``edge_checks`` evenly spaced samples (with ``dense``,
        also at every ``query_step``). The ``neighbours`` nearest are tried first, then
        4×, 16×, … as many for the rows where none passes (configurations deep in a
        narrow space have few free straight lines); every row's candidates are checked
        in one batched clearance call per round.

        Without ``dense`` the dense check is left to the query, which makes it on the
        attach edges of each path it finds and searches again without a failing one
        (lazily, as for roadmap edges); an end whose every attach edge fails it is
        attached again with ``dense``. Measured on 40 cabinet problems (80 ends): 770
        edges passed the coarse check, 760 of them the dense one, which took 61 633 of the
        attach's 68 033 samples."""
        width = self.config.neighbours
        nodes, out = np.full((len(z), width), -1, dtype=np.int64), np.full((len(z), width),
                                                                            np.inf)
        pending, count, done = np.arange(len(z)), width, 0
        while len(pending) and done < len(self.nodes_z):
            k = min(count, len(self.nodes_z))
            dist, idx = self.tree.query(z[pending], k=k)
            dist = dist.reshape(len(pending), k)[:, done:]
            idx = idx.reshape(len(pending), k)[:, done:]
            ok = _edge_free(self.checker, np.repeat(z[pending], idx.shape[1], axis=0),
                            self.nodes_z[idx.ravel()],
                            np.full(idx.size, self.config.edge_checks),
                            self.margin).reshape(idx.shape)
            if dense:             # the dense check on the nearest coarse survivors
                row, column = np.nonzero(ok & (np.cumsum(ok, axis=1) <= width))
                steps = np.ceil(dist[row, column] / self.config.query_step).astype(np.int64)
                ok[row, column] = _edge_free(self.checker, z[pending[row]],
                                             self.nodes_z[idx[row, column]],
                                             np.maximum(self.config.edge_checks, steps),
                                             self.margin)
            rank = np.cumsum(ok, axis=1)
            row, column = np.nonzero(ok & (rank <= width))
            slot = rank[row, column] - 1
            nodes[pending[row], slot] = idx[row, column]
            out[pending[row], slot] = np.maximum(dist[row, column], 1e-12)
            pending = pending[~np.isin(np.arange(len(pending)), row)]
            done, count = k, 4 * count
        return nodes, out

    def _table(self) -> tuple[np.ndarray, np.ndarray]:
        """The roadmap as a neighbour table (``roadmap_search.neighbour_table``) with the
        edges that failed a dense check dropped (+inf)."""
        if self._neighbours is None:
            self._neighbours, self._weights = neighbour_table(self.edges)
            self._drop([h for h, ok in self._dense_ok.items() if not ok])
        assert self._weights is not None
        return self._neighbours, self._weights

    def _drop(self, hops: list[tuple[int, int]]) -> None:
        """Remove roadmap edges (a, b) from the neighbour table (both directions)."""
        if self._neighbours is None or not hops:
            return
        assert self._weights is not None
        for a, b in hops:
            for u, v in ((a, b), (b, a)):
                self._weights[u, self._neighbours[u] == v] = np.inf

    def query_z(self, z_start: np.ndarray, z_goal: np.ndarray,
                search: str = "auto") -> np.ndarray | None:
        """The shortest roadmap path from ``z_start`` to ``z_goal`` (3n, bending-vector
        form) as its corner points (K, 3n), start and goal included, every edge
        re-checked densely; None if either end cannot be attached or no path exists.
        ``query_many_z`` for one pair."""
        z_start = np.asarray(z_start, dtype=float).reshape(1, self.robot.dof)
        z_goal = np.asarray(z_goal, dtype=float).reshape(1, self.robot.dof)
        return self.query_many_z(z_start, z_goal, search)[0]

    def query_many_z(self, z_starts: np.ndarray, z_goals: np.ndarray,
                     search: str = "auto") -> list[np.ndarray | None]:
        """``query_z`` for P pairs at once: (P, 3n) starts and goals in the bending-vector
        form; per pair the corner points (K, 3n) or None. The checks of every pair run
        as batched clearance calls and the searches as one batched shortest-path call per
        lazy round (``roadmap_search.shortest_paths``, backend ``search``: "auto",
        "device" or "scipy"); each pair's answer is the one ``query_z`` gives alone."""
        z_starts = np.asarray(z_starts, dtype=float).reshape(-1, self.robot.dof)
        z_goals = np.asarray(z_goals, dtype=float).reshape(-1, self.robot.dof)
        count, n = len(z_starts), len(self.nodes_z)
        out: list[np.ndarray | None] = [None] * count
        if not self._queried:           # a query's check sizes vary: compile them all once
            self.checker.compile_all()
            self._queried = True
        direct = self.dense_free(z_starts, z_goals) if count else np.zeros(0, dtype=bool)
        for p in np.flatnonzero(direct):
            out[p] = np.stack([z_starts[p], z_goals[p]])
        self.last_query_rounds = 0
        active = np.flatnonzero(~direct)
        if n == 0 or len(active) == 0:
            return out
        ends_nodes, ends_len = self._attach(np.vstack([z_starts[active], z_goals[active]]))
        start_nodes, goal_nodes = np.split(ends_nodes, 2)
        start_len, goal_len = np.split(ends_len, 2)
        attached = np.isfinite(start_len).any(axis=1) & np.isfinite(goal_len).any(axis=1)
        rows = np.flatnonzero(attached)               # rows into the attach arrays
        redone = np.zeros((len(start_len), 2), dtype=bool)   # ends attached again densely
        neighbours, weights = self._table()
        # Lazy PRM: path edges that fail the dense check are removed, then search again.
        for _ in range(self.config.max_query_rounds):
            if len(rows) == 0:
                break
            self.last_query_rounds += 1
            _, paths = shortest_paths(neighbours, weights, start_nodes[rows], start_len[rows],
                                      goal_nodes[rows], goal_len[rows], search)
            found = [k for k, path in enumerate(paths) if path is not None]
            # Roadmap edges keep their verdict for later queries; the attach edges of a
            # path are checked again with the path (their lengths are per pair).
            hops = {(min(a, b), max(a, b)) for k in found
                    for a, b in zip(paths[k][:-1], paths[k][1:], strict=True)}
            unknown = sorted(h for h in hops if h not in self._dense_ok)
            za = [self.nodes_z[[h[0] for h in unknown]]]
            zb = [self.nodes_z[[h[1] for h in unknown]]]
            for k in found:
                p = active[rows[k]]
                za += [z_starts[p][None], self.nodes_z[paths[k][-1]][None]]
                zb += [self.nodes_z[paths[k][0]][None], z_goals[p][None]]
            verdicts = self.dense_free(np.vstack(za), np.vstack(zb))
            failed = [h for h, ok in zip(unknown, verdicts, strict=False) if not ok]
            self._dense_ok.update(zip(unknown, map(bool, verdicts), strict=False))
            self._drop(failed)
            ends_ok = verdicts[len(unknown):].reshape(-1, 2)
            again, lost = [], []
            for k, (start_ok, goal_ok) in zip(found, ends_ok, strict=True):
                row, path = rows[k], paths[k]
                if not start_ok:
                    start_len[row, start_nodes[row] == path[0]] = np.inf
                if not goal_ok:
                    goal_len[row, goal_nodes[row] == path[-1]] = np.inf
                for end, lengths in ((0, start_len), (1, goal_len)):
                    if not np.isfinite(lengths[row]).any() and not redone[row, end]:
                        lost.append((row, end))     # every coarse attach edge failed
                inner = all(self._dense_ok[(min(a, b), max(a, b))]
                            for a, b in zip(path[:-1], path[1:], strict=True))
                if start_ok and goal_ok and inner:
                    p = active[row]
                    out[p] = np.vstack([z_starts[p], self.nodes_z[path], z_goals[p]])
                else:
                    again.append(row)
            if lost:                   # attach those ends again, densely checked
                ends = np.stack([(z_starts if end == 0 else z_goals)[active[row]]
                                 for row, end in lost])
                nodes_new, len_new = self._attach(ends, dense=True)
                for (row, end), n_row, l_row in zip(lost, nodes_new, len_new, strict=True):
                    (start_nodes, goal_nodes)[end][row] = n_row
                    (start_len, goal_len)[end][row] = l_row
                    redone[row, end] = True
            rows = np.array(again, dtype=np.int64)
        return out

    def query_many(self, q_starts: np.ndarray, q_goals: np.ndarray, waypoints: int,
                   search: str = "auto") -> list[np.ndarray | None]:
        """``query`` for P pairs at once ((P, 3n) each; rad, rad, m), through
        ``query_many_z``: per pair (waypoints, 3n) configurations or None."""
        q_starts = np.asarray(q_starts, dtype=float).reshape(-1, self.robot.dof)
        q_goals = np.asarray(q_goals, dtype=float).reshape(-1, self.robot.dof)
        # numpy, not eager JAX: eager ops compile again for every new batch size.
        corners = self.query_many_z(q_to_z_numpy(q_starts), q_to_z_numpy(q_goals), search)
        out: list[np.ndarray | None] = []
        for q_start, q_goal, points in zip(q_starts, q_goals, corners, strict=True):
            if points is None:
                out.append(None)
                continue
            q = z_to_q_numpy(resample_polyline(points, waypoints))
            # Keep the given end points bit for bit (the z round trip moves φ at θ = 0).
            q[0], q[-1] = q_start, q_goal
            out.append(q)
        return out

    def query(self, q_start: np.ndarray, q_goal: np.ndarray, waypoints: int,
              search: str = "auto") -> np.ndarray | None:
        """A collision-free path from ``q_start`` to ``q_goal`` (3n each; rad, rad, m) as
        (waypoints, 3n) configurations (θ, φ, L): the roadmap path (``query_z``) resampled
        uniformly by arc length in z. None if start or goal cannot be attached or no
        path exists. The resampled polyline cuts the path's corners slightly: check the
        result where that matters."""
        return self.query_many(np.reshape(q_start, (1, -1)), np.reshape(q_goal, (1, -1)),
                               waypoints, search)[0]
