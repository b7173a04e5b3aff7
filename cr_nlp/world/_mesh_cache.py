"""A mesh obstacle's file read once: its triangles and its convex decomposition (CoACD),
with every part's hull, cached on disk under the SHA-256 of the file's bytes and the
decomposition settings.

A later load reads one ``.npz`` and places the parts, without trimesh or CoACD: importing
trimesh alone took 0.3–0.5 s of a 4.5 s warm ``cr-nlp plan`` in the shelf. The hulls are
kept in the mesh's own frame; placing (uniform scale s, rotation R, translation t) moves
vertices to s·R·v + t and face planes n·x ≤ b to (R n)·x ≤ s·b + (R n)·t, the same
hull as that of the placed points. Units: the mesh file's (metres after ``scale``).
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from .._files import write_atomic
from ..runtime import cache_dir

FORMAT = 2
"""Bumped when the cached file's content changes (1: the parts' points only)."""

_CACHE_STATS = {"hits": 0, "misses": 0}


def coacd_cache_stats() -> dict[str, int]:
    """How often a mesh decomposition came from the disk cache (``hits``) or was computed
    (``misses``) in this process."""
    return dict(_CACHE_STATS)


def coacd_cache_dir() -> Any:
    """Where decompositions are cached: ``$CR_NLP_CACHE_DIR/coacd``, else
    ``~/.cache/cr_nlp/coacd``."""
    return cache_dir() / "coacd"


@dataclass(frozen=True)
class Hull:
    """A convex hull: ``vertices`` (V, 3), outward ``triangles`` (T, 3), and its face
    planes ``normals`` (F, 3) (unit) and ``offsets`` (F,): {x : normals·x ≤ offsets}."""

    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray

    @classmethod
    def of_points(cls, points: np.ndarray) -> Hull:
        """The convex hull of ``points`` (K, 3), coplanar triangles merged into one face
        plane each."""
        import trimesh

        hull = trimesh.Trimesh(np.asarray(points, dtype=float)).convex_hull
        normals = np.asarray(hull.face_normals, dtype=float)
        offsets = np.einsum("ij,ij->i", normals, hull.triangles[:, 0])
        # Triangles of one hull face share their plane; one plane per face keeps F small.
        key = np.round(np.c_[normals, offsets], 6)
        _, first = np.unique(key, axis=0, return_index=True)
        first = np.sort(first)
        return cls(np.asarray(hull.vertices, dtype=float), np.asarray(hull.faces, dtype=np.int64),
                   normals[first], offsets[first])

    def placed(self, scale: float, rotation: np.ndarray, position: np.ndarray) -> Hull:
        """This hull scaled by ``scale`` (> 0), turned by ``rotation`` (3, 3) and moved
        by ``position`` (3,)."""
        normals = self.normals @ rotation.T
        return Hull((scale * self.vertices) @ rotation.T + position, self.triangles,
                    normals, scale * self.offsets + normals @ position)


@dataclass(frozen=True)
class MeshData:
    """A triangle mesh for drawing: ``vertices`` (V, 3) and ``faces`` (F, 3) indices."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) the corners of every face."""
        return self.vertices[self.faces]


@dataclass(frozen=True)
class Decomposed:
    """A mesh file read and decomposed, in its own frame."""

    mesh: MeshData
    hulls: tuple[Hull, ...]


def decomposed(content: bytes, file_type: str, settings: Any,
               check: Callable[[Any], None]) -> Decomposed:
    """The mesh in ``content`` (a ``file_type`` file: "obj", "stl", …) and its convex
    parts under the CoACD ``settings`` (a dataclass), from the disk cache or computed.
    ``check(loaded)`` judges a freshly read ``trimesh.Trimesh`` (raising for a broken
    one) before anything is computed or stored."""
    key = hashlib.sha256(content + json.dumps({"format": FORMAT, **asdict(settings)},
                                              sort_keys=True).encode()).hexdigest()
    path = coacd_cache_dir() / f"{key}.npz"
    if path.exists():
        try:
            with np.load(path) as data:
                out = _unpacked(data)
            _CACHE_STATS["hits"] += 1
            return out
        except (OSError, KeyError, ValueError):
            pass  # a damaged cache file is recomputed and overwritten below
    import coacd
    import trimesh

    loaded = trimesh.load(io.BytesIO(content), file_type=file_type, force="mesh", process=True)
    check(loaded)
    vertices = np.asarray(loaded.vertices, dtype=float)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    coacd.set_log_level("error")
    result = coacd.run_coacd(coacd.Mesh(vertices, faces.astype(np.int32)), **asdict(settings))
    out = Decomposed(MeshData(vertices, faces),
                     tuple(Hull.of_points(np.asarray(v, dtype=float)) for v, _ in result))
    _CACHE_STATS["misses"] += 1
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    np.savez(buffer, **_packed(out))
    write_atomic(path, buffer.getvalue())   # a concurrent reader never sees half a file
    return out


_HULL_FIELDS = ("vertices", "triangles", "normals", "offsets")


def _packed(out: Decomposed) -> dict[str, np.ndarray]:
    arrays = {"mesh_vertices": out.mesh.vertices, "mesh_faces": out.mesh.faces}
    for name in _HULL_FIELDS:
        parts = [getattr(h, name) for h in out.hulls]
        arrays[name] = np.concatenate(parts)
        arrays[f"{name}_counts"] = np.array([len(p) for p in parts])
    return arrays


def _unpacked(data: Any) -> Decomposed:
    columns = []
    for name in _HULL_FIELDS:
        counts = np.asarray(data[f"{name}_counts"])
        columns.append(np.split(np.asarray(data[name]), np.cumsum(counts)[:-1]))
    hulls = tuple(Hull(v, t.astype(np.int64), n, o) for v, t, n, o in zip(*columns,
                                                                        strict=True))
    return Decomposed(MeshData(np.asarray(data["mesh_vertices"], dtype=float),
                               np.asarray(data["mesh_faces"], dtype=np.int64)), hulls)
