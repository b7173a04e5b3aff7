"""A table of the parts near each cell of a grid: the broad phase of the batched clearance
terms, one floor and one gather per body sphere.

A body sphere's clearance term needs its distance d to the nearest obstacle part only
where d is below the optimiser's margin (the shortfall max(0, δ − d) is zero above it).
On the host, once per scene, the region the robot can reach is cut into cubic cells and
each cell gets the indices of the parts (per kind) that can be the nearest part of a
point of the cell at a distance below ``cutoff``; on the device a sphere's candidates are
the row of its cell (``cell_candidates``), and only they are measured
(``world._clearance_groups``).

Which parts a cell keeps. For every part p near a cell B the builder bounds the part's
distance function m_p (the signed distance the optimisers use, ``world._distances``:
convex and 1-Lipschitz in the sphere's centre) over the cell:

- above: U_p = the largest of m_p at the cell's 8 corners (exact, m_p is convex);
- below: L_p = m_p(cell centre) − half the cell diagonal (1-Lipschitz), raised for a box
  or a convex part by its face planes (m_p ≥ max_f min_B (n_f·x − b_f)), for a sphere to
  its exact distance to the cell, for a capsule or cylinder by its bounding ball's.

The part nearest to a point x of B has m(x) ≤ min_q U_q, so every part that can be the
nearest one below the cutoff has L_p ≤ min(cutoff, min_q U_q); those are kept (with a
``SLACK`` for float32 rounding of the cell index), sorted by L_p, at most ``near`` per
kind. A cell whose list was cut (``PartCells.truncated`` counts them) may miss its
nearest part. Rows are padded with part 0 of the kind: every entry is a real part, so
the minimum over a row is never below the true nearest distance.

Guarantee when no cell was cut: for a point x of the reach box, the minimum of m over
the row of x's cell equals the minimum over every part whenever that is below
``cutoff``, and is at least ``cutoff`` otherwise (outside the grid no part is within the
cutoff). A point outside the reach box is clamped to a border cell and may be measured
too far, never too near.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import HalfspaceIntersection

from .._programs import source_hash
from ..model._ops import NUMPY
from ..model.robot import Robot
from ..runtime import cache_dir, cached_arrays
from .clearance import SceneArrays, kind_distances, scene_arrays, scene_digest
from .scene import (
    PART_KINDS,
    BoxPart,
    CapsulePart,
    ConvexPart,
    CylinderPart,
    Part,
    Scene,
    SpherePart,
    bounding_sphere,
)

KIND_FIELDS: tuple[tuple[str, ...], ...] = (
    ("sphere_center", "sphere_radius"),
    ("box_center", "box_rotation", "box_half_size"),
    ("capsule_a", "capsule_b", "capsule_radius"),
    ("cylinder_center", "cylinder_rotation", "cylinder_radius", "cylinder_half_length"),
    ("convex_planes",))
"""Fields of ``SceneArrays`` per part kind, in ``PART_KINDS`` order."""

TABLE_BYTES = 16 * 2**20
"""The automatic cell size keeps a table within this many bytes."""

_CACHE_STATS = {"hits": 0, "builds": 0}

SLACK = 1e-4
"""Metres added to the keep threshold: a float32 centre this close to a cell's border may
be indexed into the neighbouring cell."""


CELL_BASE = 0.025
"""Automatic cell edges are ``CELL_BASE``·√2ᵏ metres (tdcr3's 0.05 m is one)."""
GRID_ROUND = 16
"""The table's cells per axis (more than one) are padded to a multiple of this (copies of
the border cells, which a point outside the grid takes anyway)."""
WIDTH_ROUND = 4
"""Columns per part kind are padded to a multiple of this (part 0: measuring a part
more never makes a distance wrong)."""


@dataclass(frozen=True)
class PartCells:
    """The broad-phase table of one scene (``part_cells``); a pytree whose arrays are
    ``origin``, ``inverse_size`` and ``table``, the rest static."""

    origin: Any
    """(3,) m: the grid's lower corner."""
    inverse_size: Any
    """() 1/m: one over the cell edge."""
    table: Any
    """(nx, ny, nz, W) integers: per cell, ``widths[k]`` part indices of each kind k in
    ``PART_KINDS`` order (indices into that kind's parts)."""
    widths: tuple[int, ...]
    """Columns per part kind (0 for a kind the scene does not have)."""
    cell_size: float
    """Edge of a cell, m."""
    cutoff: float
    """Distances below this (m) are measured exactly (see the module docstring)."""
    truncated: int
    """Cells that had more than ``near`` parts of a kind to keep (0: the table is exact)."""


jax.tree_util.register_dataclass(
    PartCells, data_fields=["origin", "inverse_size", "table", "cell_size", "cutoff",
                            "truncated"],
    meta_fields=["widths"])
# Only the column widths shape a program: the numbers are data, the grid is padded to
# ``GRID_ROUND`` cells per axis and the widths to ``WIDTH_ROUND``, so robots of one shape
# (whose reach, hence grid and cell size, differ) share the programs that take a table.


def cell_candidates(cells: PartCells, centres: jax.Array) -> list[jax.Array]:
    """Per part kind with a nonzero width, the (…, width) indices of the parts to measure
    for each body sphere centred at ``centres`` (…, 3) m: its cell's row of the table
    (points outside the grid take the nearest border cell)."""
    top = jnp.asarray(cells.table.shape[:3], centres.dtype) - 1
    scaled = (centres - cells.origin.astype(centres.dtype)) * cells.inverse_size.astype(
        centres.dtype)
    ijk = jnp.floor(jnp.clip(scaled, 0, top)).astype(jnp.int32)
    rows = cells.table[ijk[..., 0], ijk[..., 1], ijk[..., 2]].astype(jnp.int32)
    out, start = [], 0
    for width in cells.widths:
        if width:
            out.append(rows[..., start:start + width])
        start += width
    return out


def reach_box(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners (3,) m of a box holding every body-sphere centre of every
    configuration: the base position ± the robot's largest total length."""
    base = np.asarray(robot.base_position, dtype=float)
    return base - robot.total_length_max, base + robot.total_length_max


def _part_box(part: Part, grow: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box (lower, upper corners, m) holding every point whose signed
    distance to the part (as ``world._distances`` measures it) is at most ``grow`` m. For
    a convex part that distance is the largest face-plane value, whose sublevel set is the
    part with every face pushed out by ``grow``: near a sharp vertex it reaches much
    farther than ``grow`` from the part, so its corners are computed."""
    if isinstance(part, ConvexPart):
        if grow <= 0.0:
            return part.vertices.min(axis=0), part.vertices.max(axis=0)
        grown = HalfspaceIntersection(np.c_[part.normals, -(part.offsets + grow)],
                                      part.vertices.mean(axis=0)).intersections
        return grown.min(axis=0), grown.max(axis=0)
    if isinstance(part, BoxPart):
        extent = np.abs(np.asarray(part.rotation, float)) @ np.asarray(part.half_size, float)
        lo, hi = part.center - extent, part.center + extent
    elif isinstance(part, (CapsulePart, CylinderPart)):
        a, b = np.asarray(part.a, float), np.asarray(part.b, float)
        lo, hi = np.minimum(a, b) - part.radius, np.maximum(a, b) + part.radius
    else:
        centre, radius = bounding_sphere(part)
        lo, hi = np.asarray(centre, float) - radius, np.asarray(centre, float) + radius
    return lo - grow, hi + grow


def _box_gap(point: np.ndarray, centres: np.ndarray, half: float) -> np.ndarray:
    """Distance (m) from ``point`` (3,) to each cube of half edge ``half`` centred at
    ``centres`` (…, 3); 0 inside."""
    return np.linalg.norm(np.maximum(np.abs(centres - point) - half, 0.0), axis=-1)


def _lower_bound(part: Part, values: np.ndarray, centres: np.ndarray, half: float) -> np.ndarray:
    """A lower bound (…,) m of the part's signed distance over each cube of half edge
    ``half`` centred at ``centres`` (…, 3), given the distance ``values`` at the centres."""
    bound = values - half * math.sqrt(3.0)                        # 1-Lipschitz
    if isinstance(part, SpherePart):
        return _box_gap(np.asarray(part.center, float), centres, half) - part.radius
    if isinstance(part, (BoxPart, ConvexPart)):
        if isinstance(part, BoxPart):
            axes = np.asarray(part.rotation, float).T                # rows: the box's axes
            along = axes @ np.asarray(part.center, float)
            normals = np.concatenate([axes, -axes])
            offsets = np.concatenate([along, -along]) + np.tile(part.half_size, 2)
        else:
            normals, offsets = part.normals, part.offsets
        # min over the cube of n·x − b: the centre's value less half·Σ|nᵢ|.
        planes = centres @ normals.T - offsets - half * np.abs(normals).sum(axis=1)
        return np.maximum(bound, planes.max(axis=-1))
    centre, radius = bounding_sphere(part)
    return np.maximum(bound, _box_gap(np.asarray(centre, float), centres, half) - radius)


def _reach(scene: Scene, body_radius: float, region: tuple[np.ndarray, np.ndarray],
           cutoff: float) -> tuple[list, list, np.ndarray, np.ndarray]:
    """What ``part_cells``' grid covers, whatever its cell size: the parts per kind, their
    boxes padded by the body radius and the cutoff, and the lower and upper corners (m) of
    the part of ``region`` they reach."""
    region_lo, region_hi = (np.asarray(x, dtype=float) for x in region)
    kinds = [[p for p in scene.parts if isinstance(p, kind)] for kind in PART_KINDS]
    pad = body_radius + cutoff + SLACK
    boxes = [[_part_box(p, pad) for p in parts] for parts in kinds]
    flat = [b for kind in boxes for b in kind     # parts that can come within the cutoff
            if np.all(b[0] <= region_hi) and np.all(b[1] >= region_lo)]
    if flat:
        lo = np.maximum(region_lo, np.min([b[0] for b in flat], axis=0))
        hi = np.minimum(region_hi, np.max([b[1] for b in flat], axis=0))
    else:
        lo, hi = region_lo, region_lo
    return kinds, boxes, lo, hi


def _cells_per_axis(lo: np.ndarray, hi: np.ndarray, cell_size: float) -> np.ndarray:
    """Cells of ``cell_size`` m per axis covering the box ``lo``–``hi`` (at least one)."""
    return np.maximum(np.ceil((hi - lo) / cell_size), 1).astype(int)


def _padded(dims: np.ndarray) -> list[int]:
    """The table's cells per axis: more than one padded to a multiple of ``GRID_ROUND``."""
    return [1 if d == 1 else -(-d // GRID_ROUND) * GRID_ROUND for d in dims]


def _least_table_bytes(kinds: list, dims: np.ndarray) -> int:
    """Bytes of the smallest table ``part_cells`` can build on a grid of ``dims`` cells
    for the parts ``kinds``: its padded cells, ``WIDTH_ROUND`` columns per present kind,
    16-bit indices."""
    return int(np.prod(_padded(dims))) * WIDTH_ROUND * sum(1 for parts in kinds if parts) * 2


def _one_part(arrays: SceneArrays, kind: int, index: int) -> SceneArrays:
    """``arrays`` holding only part ``index`` of kind ``kind``."""
    fields = set(KIND_FIELDS[kind])
    return SceneArrays(**{name: value[index:index + 1] if name in fields else value[:0]
                          for name, value in arrays._asdict().items()})


def part_cells(scene: Scene, body_radius: float, region: tuple[np.ndarray, np.ndarray],
               cutoff: float, near: int = 16, cell_size: float | None = None,
               dtype: Any = None) -> PartCells:
    """The broad-phase table (module docstring) of ``scene`` for body spheres of
    ``body_radius`` m whose centres stay in ``region`` (lower, upper corners, m; e.g.
    ``reach_box``): cubic cells of ``cell_size`` m, distances exact below ``cutoff`` m,
    at most ``near`` ≥ 1 parts per kind and cell. Arrays as JAX arrays of ``dtype``
    (default JAX's default float).

    ``cell_size`` None: the larger of half the body radius and 1/128 of the region's
    longest edge, rounded up to ``CELL_BASE``·√2ᵏ, doubled while the table would take
    more than ``TABLE_BYTES``. Measured
    for tdcr3 (r = 0.1 m, cutoff 0.014 m; cells of 0.025 / 0.05 / 0.1 / 0.2 m): the widest
    row (the device's work per sphere) was 8 / 9 / 9 / 12 convex parts in shelf, 9 / 9 /
    9 / 13 in cabinet (9–13 at 0.05–0.1 m when the grid was shifted by 0.1 m), 4 spheres
    in random_27; the tables took 5.2–21 / 0.73–2.7 / 0.10–0.34 / ≤ 0.04 MB and were
    built in 0.7–1.8 / 0.17–0.27 / 0.04–0.13 / 0.05–0.10 s (2 busy cores).

    A table is built once per scene, settings and cr_nlp source and kept in
    ``cache_dir()/cell_tables``: a later process (a warm ``cr-nlp plan``'s two tables took
    0.10 and 0.17 s) reads it from there (``part_cells_cache_stats``).
    """
    if near < 1:
        raise ValueError(f"near must be at least 1, got {near}")
    if not (cell_size is None or cell_size > 0) or not math.isfinite(cutoff):
        raise ValueError(f"cell_size must be positive and cutoff finite, got {cell_size}, "
                         f"{cutoff}")
    key = _table_key(scene, body_radius, region, cutoff, near, cell_size)
    data, _ = cached_arrays(cache_dir() / "cell_tables" / f"{key}.npz", lambda: _built(
        scene, body_radius, region, cutoff, near, cell_size), _CACHE_STATS)
    dtype = dtype or jnp.result_type(float)
    size = float(data["cell_size"])
    return PartCells(jnp.asarray(data["origin"], dtype), jnp.asarray(1.0 / size, dtype),
                     jnp.asarray(data["table"]), tuple(data["widths"].tolist()), size,
                     float(cutoff), int(data["truncated"]))


def part_cells_cache_stats() -> dict[str, int]:
    """How often ``part_cells`` loaded a table from ``cache_dir()/cell_tables``
    (``hits``) or built one (``builds``) in this process."""
    return dict(_CACHE_STATS)


def _table_key(scene: Scene, body_radius: float, region: tuple[np.ndarray, np.ndarray],
               cutoff: float, near: int, cell_size: float | None) -> str:
    """sha256 of everything a table depends on: the scene (its file form and its parts'
    arrays), the settings, the cr_nlp source and numpy's version."""
    return hashlib.sha256(json.dumps({
        "scene": scene_digest(scene), "body_radius": float(body_radius),
        "region": [np.asarray(x, dtype=float).tolist() for x in region],
        "cutoff": float(cutoff), "near": int(near), "cell_size": cell_size,
        "source": source_hash(), "numpy": np.__version__}, sort_keys=True).encode()).hexdigest()


def _built(scene: Scene, body_radius: float, region: tuple[np.ndarray, np.ndarray],
           cutoff: float, near: int, cell_size: float | None) -> dict[str, np.ndarray]:
    """``part_cells``' table built (its numpy fields), the automatic cell size chosen."""
    kinds, boxes, lo, hi = _reach(scene, body_radius, region, cutoff)
    if cell_size is not None:
        return _table(scene, body_radius, cutoff, near, cell_size, kinds, boxes, lo,
                      _cells_per_axis(lo, hi, cell_size))
    region_lo, region_hi = (np.asarray(x, dtype=float) for x in region)
    size = max(0.5 * body_radius, float(np.max(region_hi - region_lo)) / 128)
    # Up to the next size of one series: robots of similar size get the same grid
    # (and so share the programs that take the table).
    size = CELL_BASE * math.sqrt(2.0) ** math.ceil(2 * math.log2(size / CELL_BASE) - 1e-9)
    while True:
        # A size whose table cannot fit (its fewest columns) is not built.
        dims = _cells_per_axis(lo, hi, size)
        if _least_table_bytes(kinds, dims) <= TABLE_BYTES:
            table = _table(scene, body_radius, cutoff, near, size, kinds, boxes, lo, dims)
            if table["table"].nbytes <= TABLE_BYTES:
                return table
        size *= 2.0


def _table(scene: Scene, body_radius: float, cutoff: float, near: int, cell_size: float,
           kinds: list, boxes: list, lo: np.ndarray, dims: np.ndarray) -> dict[str, np.ndarray]:
    """``part_cells``' numpy fields at ``cell_size`` on the grid ``_reach`` and
    ``_cells_per_axis`` give (``lo``: its lower corner, m; ``dims``: its cells per axis):
    ``origin``, ``table``, ``widths``, ``cell_size`` and ``truncated``.

    Long: one table built in order (grid, per-part cell bounds, per-kind columns) on shared arrays.
    """
    n_cells = int(np.prod(dims))
    arrays = scene_arrays(scene, as_numpy=True)
    threshold = np.full(n_cells, float(cutoff))       # min(cutoff, min_q U_q) per cell
    kept: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = [[] for _ in PART_KINDS]
    half = 0.5 * cell_size
    for kind, parts in enumerate(kinds):
        for index, part in enumerate(parts):
            part_lo, part_hi = boxes[kind][index]
            first = np.floor((part_lo - lo) / cell_size).astype(int)
            last = np.floor((part_hi - lo) / cell_size).astype(int)
            if np.any(last < 0) or np.any(first >= dims):
                continue                                    # never within the cutoff
            first, last = np.clip(first, 0, dims - 1), np.clip(last, 0, dims - 1)
            ticks = [lo[d] + cell_size * np.arange(first[d], last[d] + 2) for d in range(3)]
            nodes = np.stack(np.meshgrid(*ticks, indexing="ij"), axis=-1)
            centres = nodes[:-1, :-1, :-1] + half
            one = _one_part(arrays, kind, index)
            at_nodes = kind_distances(0.0, one, nodes.reshape(-1, 3), 0.0, NUMPY)[0]
            at_nodes = at_nodes.reshape(nodes.shape[:3]) - body_radius
            at_centres = kind_distances(0.0, one, centres.reshape(-1, 3), 0.0, NUMPY)[0]
            at_centres = at_centres.reshape(centres.shape[:3])
            lower = _lower_bound(part, at_centres, centres, half) - body_radius
            a, b, c = centres.shape[:3]
            upper = np.max([at_nodes[i:i + a, j:j + b, k:k + c]
                            for i in (0, 1) for j in (0, 1) for k in (0, 1)], axis=0)
            grid = np.ix_(*(np.arange(first[d], last[d] + 1) for d in range(3)))
            ids = ((grid[0] * dims[1] + grid[1]) * dims[2] + grid[2]).reshape(-1)
            lower, upper = lower.reshape(-1), upper.reshape(-1)
            near_upper = upper < cutoff
            np.minimum.at(threshold, ids[near_upper], upper[near_upper])
            keep = lower <= cutoff + SLACK
            kept[kind].append((ids[keep], np.full(int(keep.sum()), index), lower[keep]))
    columns, widths, truncated = [], [], np.zeros(n_cells, bool)
    for kind, parts in enumerate(kinds):
        if not parts:
            widths.append(0)
            continue
        ids, index, lower = (np.concatenate([k[i] for k in kept[kind]]) if kept[kind]
                             else np.zeros(0, t) for i, t in enumerate((int, int, float)))
        keep = lower <= threshold[ids] + SLACK
        ids, index, lower = ids[keep], index[keep], lower[keep]
        order = np.lexsort((lower, ids))
        ids, index = ids[order], index[order]
        listed, start, count = np.unique(ids, return_index=True, return_counts=True)
        rank = np.arange(ids.size) - np.repeat(start, count)
        width = int(min(near, count.max())) if count.size else 1
        truncated[listed[count > near]] = True
        table = np.zeros((n_cells, -(-width // WIDTH_ROUND) * WIDTH_ROUND), dtype=np.int64)
        use = rank < width
        table[ids[use], rank[use]] = index[use]
        columns.append(table)
        widths.append(table.shape[1])
    biggest = max((len(p) for p in kinds), default=0)
    index_type = np.int16 if biggest <= np.iinfo(np.int16).max else np.int32
    table = (np.concatenate(columns, axis=1) if columns else np.zeros((n_cells, 0), int))
    grid = table.reshape(tuple(dims) + (-1,)).astype(index_type)
    grid = np.pad(grid, [(0, p - d) for p, d in zip(_padded(dims), dims, strict=True)]
                  + [(0, 0)], mode="edge")
    return {"origin": np.asarray(lo, dtype=float), "table": grid,
            "widths": np.array(widths, dtype=np.int64), "cell_size": np.array(float(cell_size)),
            "truncated": np.array(int(truncated.sum()))}
