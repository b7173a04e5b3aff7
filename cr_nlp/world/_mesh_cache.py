"""A mesh obstacle's file read once: its triangles and its convex decomposition (CoACD),
with every part's hull, cached on disk under the SHA-256 of the file's bytes and the
decomposition settings.

A later load reads one ``.npz`` and places the parts, without trimesh or CoACD: importing
trimesh alone took 0.3–0.5 s of a 4.5 s warm ``cr-nlp plan`` in the shelf. The hulls are
kept in the mesh's own frame as the fields of ``world.scene.ConvexPart``s, placed by
``ConvexPart.placed`` (vertices s·R·v + t, face planes (R n)·x ≤ s·b + (R n)·t: the hull
of the placed points). Units: the mesh file's (metres after ``scale``).
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..runtime import cache_dir, cached_arrays

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


class MeshReadError(ValueError):
    """The mesh file's bytes are not a mesh trimesh can read (its message says why)."""


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
    parts: tuple[tuple[np.ndarray, ...], ...]
    """The hull of each of CoACD's parts as the fields of a ``world.scene.ConvexPart``
    (``PART_FIELDS``)."""


def decomposed(content: bytes, file_type: str, settings: Any,
               check: Callable[[Any], None], hull: Callable[[np.ndarray], Any]) -> Decomposed:
    """The mesh in ``content`` (a ``file_type`` file: "obj", "stl", …) and its convex
    parts under the CoACD ``settings`` (a dataclass), from the disk cache or computed.
    ``check(loaded)`` judges a freshly read ``trimesh.Trimesh`` (raising for a broken
    one) before anything is computed or stored; ``hull(points)`` is the convex hull of a
    part's points (``ConvexPart.from_points``: its ``PART_FIELDS`` are kept).

    Raises:
        MeshReadError: trimesh cannot read ``content``.
    """
    key = hashlib.sha256(content + json.dumps({"format": FORMAT, **asdict(settings)},
                                              sort_keys=True).encode()).hexdigest()

    def build() -> dict[str, np.ndarray]:
        import coacd
        import trimesh

        try:
            loaded = trimesh.load(io.BytesIO(content), file_type=file_type, force="mesh",
                                  process=True)
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise MeshReadError(str(exc)) from exc
        check(loaded)
        vertices = np.asarray(loaded.vertices, dtype=float)
        faces = np.asarray(loaded.faces, dtype=np.int64)
        coacd.set_log_level("error")
        result = coacd.run_coacd(coacd.Mesh(vertices, faces.astype(np.int32)),
                                 **asdict(settings))
        parts = [hull(np.asarray(v, dtype=float)) for v, _ in result]
        return _packed(Decomposed(MeshData(vertices, faces), tuple(
            tuple(getattr(part, name) for name in PART_FIELDS) for part in parts)))

    out, _ = cached_arrays(coacd_cache_dir() / f"{key}.npz", build, _CACHE_STATS, "misses")
    return _unpacked(out)


PART_FIELDS = ("vertices", "triangles", "normals", "offsets")
"""The fields of a ``world.scene.ConvexPart``, in its order."""


def _packed(out: Decomposed) -> dict[str, np.ndarray]:
    arrays = {"mesh_vertices": out.mesh.vertices, "mesh_faces": out.mesh.faces}
    for k, name in enumerate(PART_FIELDS):
        column = [part[k] for part in out.parts]
        arrays[name] = np.concatenate(column)
        arrays[f"{name}_counts"] = np.array([len(c) for c in column])
    return arrays


def _unpacked(data: Any) -> Decomposed:
    columns = []
    for name in PART_FIELDS:
        counts = np.asarray(data[f"{name}_counts"])
        columns.append(np.split(np.asarray(data[name]), np.cumsum(counts)[:-1]))
    parts = tuple((np.asarray(v, dtype=float), t.astype(np.int64), n, o)
                  for v, t, n, o in zip(*columns, strict=True))
    return Decomposed(MeshData(np.asarray(data["mesh_vertices"], dtype=float),
                               np.asarray(data["mesh_faces"], dtype=np.int64)), parts)
