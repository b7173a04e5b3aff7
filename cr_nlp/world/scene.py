"""Scene files: obstacles, mesh loading and the cached convex decomposition.

A scene file is JSON (schema in ``models/README.md``, "Scene files"): a list of
obstacles, each a sphere, box, capsule, cylinder or triangle mesh. Loading
validates every field and raises one ``ModelFileError`` naming the file, the
obstacle (index and name) and what is wrong.

Every obstacle becomes a tuple of convex *parts*, the only thing the distance
code sees: ``SpherePart``, ``BoxPart``, ``CapsulePart``, ``CylinderPart`` and
``ConvexPart`` (a convex polytope with its vertices and face planes n·x ≤ b).
A mesh is decomposed by CoACD into convex parts; the decomposition is cached
on disk, keyed by the SHA-256 of the mesh file's bytes and the settings, so a
scene loads in milliseconds after the first time. All lengths are metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._resources import bundled_file, resolve_file
from ..model.robot import ModelFileError, _Checker, read_model_file
from ..model.rotations import matrix_from_wxyz
from ._mesh_cache import MeshData, MeshReadError, decomposed
from ._mesh_cache import coacd_cache_dir as coacd_cache_dir
from ._mesh_cache import coacd_cache_stats as coacd_cache_stats

# ================================================================ parts


@dataclass(frozen=True, eq=False)
class SpherePart:
    """A ball: ``center`` (3,) m, ``radius`` m."""

    center: np.ndarray
    radius: float


@dataclass(frozen=True, eq=False)
class BoxPart:
    """A solid box: ``center`` (3,) m, ``rotation`` (3, 3) world-from-box, ``half_size`` (3,) m."""

    center: np.ndarray
    rotation: np.ndarray
    half_size: np.ndarray


@dataclass(frozen=True, eq=False)
class CapsulePart:
    """All points within ``radius`` m of the segment from ``a`` to ``b`` (3,) m."""

    a: np.ndarray
    b: np.ndarray
    radius: float


@dataclass(frozen=True, eq=False)
class CylinderPart:
    """A solid circular cylinder of ``radius`` m whose axis runs from ``a`` to ``b`` (3,) m."""

    a: np.ndarray
    b: np.ndarray
    radius: float

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (self.a + self.b)

    @property
    def half_length(self) -> float:
        return 0.5 * float(np.linalg.norm(self.b - self.a))

    @property
    def rotation(self) -> np.ndarray:
        """World-from-cylinder rotation whose third column is the axis direction."""
        return rotation_z_to(self.b - self.a)


@dataclass(frozen=True, eq=False)
class ConvexPart:
    """A convex polytope: ``vertices`` (V, 3) m, outward ``triangles`` (T, 3) of its hull,
    and its face planes ``normals`` (F, 3) (unit) and ``offsets`` (F,) m: the part is
    {x : normals·x ≤ offsets}."""

    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray

    @classmethod
    def from_points(cls, points: np.ndarray) -> ConvexPart:
        """The convex hull of ``points`` (K, 3) m, with coplanar hull triangles merged
        into one face plane each."""
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

    def placed(self, scale: float, rotation: np.ndarray, position: np.ndarray) -> ConvexPart:
        """This part scaled by ``scale`` (> 0), turned by ``rotation`` (3, 3) and moved by
        ``position`` (3,) m: vertices s·R·v + t, face planes (R n)·x ≤ s·b + (R n)·t (the
        hull of the placed points)."""
        normals = self.normals @ rotation.T
        return ConvexPart((scale * self.vertices) @ rotation.T + position, self.triangles,
                          normals, scale * self.offsets + normals @ position)


Part = SpherePart | BoxPart | CapsulePart | CylinderPart | ConvexPart

PART_KINDS: tuple[type, ...] = (SpherePart, BoxPart, CapsulePart, CylinderPart, ConvexPart)
"""The order of part kinds in every flat list of parts (and in the clearance's pair axis)."""


def bounding_sphere(part: Part) -> tuple[np.ndarray, float]:
    """A ball (centre (3,) m, radius m) that contains the part; used to prune distance queries."""
    if isinstance(part, SpherePart):
        return part.center, part.radius
    if isinstance(part, BoxPart):
        return part.center, float(np.linalg.norm(part.half_size))
    if isinstance(part, CapsulePart):
        return 0.5 * (part.a + part.b), 0.5 * float(np.linalg.norm(part.b - part.a)) + part.radius
    if isinstance(part, CylinderPart):
        return part.center, math.hypot(part.half_length, part.radius)
    center = 0.5 * (part.vertices.min(axis=0) + part.vertices.max(axis=0))
    return center, float(np.linalg.norm(part.vertices - center, axis=1).max())


def rotation_z_to(direction: np.ndarray) -> np.ndarray:
    """A rotation matrix whose third column is ``direction`` normalised (for a direction
    in the upper half space the shortest turn from +z; in the lower one a half turn about
    x after the shortest turn from +z to the mirrored direction)."""
    x, y, z = (float(v) for v in np.asarray(direction, dtype=float).reshape(3))
    norm = math.sqrt(x * x + y * y + z * z)
    x, y, c = x / norm, y / norm, z / norm
    # Rodrigues for the rotation taking e_z to d: R = I + K + K²/(1 + c), K = [e_z × d]×,
    # written out in Python floats: the verdict builds one per capsule it measures, and
    # 3 × 3 numpy products cost more than the whole formula.
    if c >= 0.0:
        xx, xy, yy = x * x / (1.0 + c), x * y / (1.0 + c), y * y / (1.0 + c)
        return np.array([[1.0 - xx, -xy, x], [-xy, 1.0 - yy, y], [-x, -y, 1.0 - xx - yy]])
    # Near −z, 1/(1 + c) would lose the digits (5.9e-12 m in a sphere–cylinder distance):
    # diag(1, −1, −1) times the turn from +z to (x, −y, −c), whose 1 − c is ≥ 1.
    xx, xy, yy = x * x / (1.0 - c), x * y / (1.0 - c), y * y / (1.0 - c)
    return np.array([[1.0 - xx, xy, x], [-xy, yy - 1.0, y], [x, -y, xx + yy - 1.0]])


# ================================================================ scene


@dataclass(frozen=True, eq=False)
class Obstacle:
    """One obstacle of a scene: its ``name``, ``kind`` (the file's ``type``), its convex
    ``parts``, the placed triangle ``mesh`` for drawing (meshes only) and its ``spec``
    (the JSON entry it came from)."""

    name: str
    kind: str
    parts: tuple[Part, ...]
    spec: dict[str, Any]
    mesh: Any = None


@dataclass(frozen=True, eq=False)
class Scene:
    """A set of obstacles (compared by identity, so caches can key on it)."""

    name: str
    obstacles: tuple[Obstacle, ...]
    description: str = ""
    source: str = ""

    @property
    def parts(self) -> tuple[Part, ...]:
        """All parts, grouped by kind in ``PART_KINDS`` order (the clearance's part axis)."""
        return tuple(p for p, _ in self._parts_with_owner())

    @property
    def part_obstacle(self) -> np.ndarray:
        """(P,) index of the obstacle each part of ``parts`` belongs to."""
        return np.array([i for _, i in self._parts_with_owner()], dtype=np.int64)

    def _parts_with_owner(self) -> list[tuple[Part, int]]:
        out = []
        for kind in PART_KINDS:
            for i, obstacle in enumerate(self.obstacles):
                out += [(p, i) for p in obstacle.parts if isinstance(p, kind)]
        return out

    @classmethod
    def from_file(cls, path: str | Path, settings: DecompositionSettings | None = None) -> Scene:
        """Load and validate a scene JSON file (mesh paths relative to the file)."""
        path = Path(path)
        return cls.from_dict(read_model_file(path), source=str(path), base_dir=path.parent,
                             settings=settings)

    @classmethod
    def from_dict(cls, data: Any, source: str = "", base_dir: str | Path | None = None,
                  settings: DecompositionSettings | None = None) -> Scene:
        """Validate a scene description (the JSON file's content). Relative mesh paths
        are resolved against ``base_dir`` (default: the current directory)."""
        return _parse_scene(data, source, Path(base_dir) if base_dir is not None else Path.cwd(),
                            settings or DecompositionSettings())

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (mesh paths as given in the file)."""
        out: dict[str, Any] = {"name": self.name}
        if self.description:
            out["description"] = self.description
        out["obstacles"] = [dict(o.spec) for o in self.obstacles]
        return out


def bundled_scene_path(name: str) -> Path:
    """Path of a scene bundled in ``models/scenes`` (``name`` without ``.json``)."""
    return bundled_file("scenes", name)


def load_scene(scene: str | Path | Scene | dict) -> Scene:
    """A ``Scene`` from a file path, a bundled scene name (``"shelf"``), a dict, or a
    ``Scene`` (returned as is)."""
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, dict):
        return Scene.from_dict(scene)
    try:
        path = resolve_file(scene, "scenes")
    except FileNotFoundError as exc:
        raise ModelFileError(str(scene), "<file>",
                             str(exc).removeprefix(f"{scene}: ")) from None
    return Scene.from_file(path)


# ================================================================ convex decomposition


@dataclass(frozen=True)
class DecompositionSettings:
    """CoACD settings for mesh obstacles; the defaults decompose a thin shelf in about 2 s.

    Part of the cache key: changing any field recomputes the decomposition.
    """

    threshold: float = 0.05
    """Concavity threshold (relative to the mesh size): smaller gives more, tighter parts."""
    preprocess_mode: str = "off"
    """"off" skips CoACD's remeshing, which took minutes on thin boards; meshes must be
    closed (watertight) for "off" to be correct."""
    resolution: int = 1000
    """Surface samples per cut evaluation."""
    mcts_iterations: int = 30
    """Tree-search iterations per cut (CoACD's default is 150)."""
    mcts_nodes: int = 10
    """Child nodes per tree-search node."""
    mcts_max_depth: int = 2
    """Tree-search depth."""
    merge: bool = False
    """CoACD's merge step; off because merging thin boards made hulls bulge into the
    compartments between them (measured: 60 % more volume than the shelf)."""
    seed: int = 0
    """Random seed, for reproducible parts."""


# ================================================================ validation

_TOP_KEYS = {"name", "description", "obstacles"}
_KEYS = {
    "sphere": ({"type", "name", "center", "radius"}, {"center", "radius"}),
    "box": ({"type", "name", "center", "size", "wxyz"}, {"center", "size"}),
    "capsule": ({"type", "name", "a", "b", "radius"}, {"a", "b", "radius"}),
    "cylinder": ({"type", "name", "a", "b", "radius"}, {"a", "b", "radius"}),
    "mesh": ({"type", "name", "path", "scale", "position", "wxyz"}, {"path"}),
}


def _parse_scene(data: Any, source: str, base_dir: Path,
                 settings: DecompositionSettings) -> Scene:
    c = _Checker(source)
    d = c.obj(data, "", _TOP_KEYS, {"obstacles"})
    name = d.get("name", Path(source).stem if source else "scene")
    if not isinstance(name, str) or not name:
        raise c.fail("name", f"expected a non-empty string, got {name!r}")
    description = d.get("description", "")
    if not isinstance(description, str):
        raise c.fail("description", f"expected a string, got {type(description).__name__}")
    raw = d["obstacles"]
    if not isinstance(raw, list):
        raise c.fail("obstacles", f"expected a list of obstacles, got {type(raw).__name__}")
    obstacles = tuple(_parse_obstacle(c, o, i, base_dir, settings) for i, o in enumerate(raw))
    seen: dict[str, int] = {}
    for i, o in enumerate(obstacles):
        if o.name in seen:
            raise c.fail(f"obstacles[{i}].name",
                         f"name {o.name!r} is already used by obstacles[{seen[o.name]}]")
        seen[o.name] = i
    return Scene(name=name, obstacles=obstacles, description=description, source=source)


def _parse_obstacle(c: _Checker, raw: Any, index: int, base_dir: Path,
                    settings: DecompositionSettings) -> Obstacle:
    path = f"obstacles[{index}]"
    if not isinstance(raw, dict):
        raise c.fail(path, f"expected an object, got {type(raw).__name__}")
    name = raw.get("name")
    if name is not None:
        if not isinstance(name, str) or not name:
            raise c.fail(f"{path}.name", f"expected a non-empty string, got {name!r}")
        path = f"{path} ({name})"
    if "type" not in raw:
        raise c.fail(f"{path}.type", "missing required field "
                                     f"(one of: {', '.join(sorted(_KEYS))})")
    kind = raw["type"]
    if not isinstance(kind, str) or kind not in _KEYS:
        raise c.fail(f"{path}.type", f"unknown obstacle type {kind!r} "
                                     f"(allowed: {', '.join(sorted(_KEYS))})")
    allowed, required = _KEYS[kind]
    c.obj(raw, path, allowed, required)
    name = name or f"{kind}_{index}"

    def vec(key: str) -> np.ndarray:
        return np.array(c.vector(raw[key], f"{path}.{key}", 3))

    def rotation(key: str) -> np.ndarray:
        if key not in raw:
            return np.eye(3)
        q = np.array(c.vector(raw[key], f"{path}.{key}", 4))
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-3:
            raise c.fail(f"{path}.{key}", f"must be a unit quaternion (w, x, y, z), "
                                          f"its norm is {norm:.6g}")
        return matrix_from_wxyz(q / norm)

    parts: tuple[Part, ...]
    mesh = None
    if kind == "sphere":
        parts = (SpherePart(vec("center"),
                            c.number(raw["radius"], f"{path}.radius", positive=True)),)
    elif kind == "box":
        size = vec("size")
        if np.any(size <= 0):
            raise c.fail(f"{path}.size", f"every side must be positive, got {size.tolist()}")
        parts = (BoxPart(vec("center"), rotation("wxyz"), 0.5 * size),)
    elif kind in ("capsule", "cylinder"):
        a, b = vec("a"), vec("b")
        radius = c.number(raw["radius"], f"{path}.radius", positive=True)
        if np.linalg.norm(b - a) <= 1e-9:
            hint = " (use a sphere)" if kind == "capsule" else ""
            raise c.fail(f"{path}.b", f"the axis end points a and b coincide{hint}")
        parts = ((CapsulePart if kind == "capsule" else CylinderPart)(a, b, radius),)
    else:
        parts, mesh = _parse_mesh(c, raw, path, base_dir, settings, vec, rotation)
    return Obstacle(name=name, kind=kind, parts=parts, spec=dict(raw), mesh=mesh)


def _parse_mesh(c: _Checker, raw: dict, path: str, base_dir: Path,
                settings: DecompositionSettings, vec: Any, rotation: Any) -> tuple[tuple, Any]:
    mesh_path = raw["path"]
    if not isinstance(mesh_path, str) or not mesh_path:
        raise c.fail(f"{path}.path", f"expected a file path string, got {mesh_path!r}")
    file = Path(mesh_path) if Path(mesh_path).is_absolute() else base_dir / mesh_path
    try:
        content = file.read_bytes()
    except FileNotFoundError:
        raise c.fail(f"{path}.path", f"mesh file not found: {file}") from None
    except OSError as exc:
        raise c.fail(f"{path}.path", f"cannot read mesh file {file}: {exc}") from None
    scale = c.number(raw.get("scale", 1.0), f"{path}.scale", positive=True)
    position = vec("position") if "position" in raw else np.zeros(3)
    rot = rotation("wxyz")

    def check(loaded: Any) -> None:
        vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=float)
        faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
        if len(faces) == 0 or len(vertices) < 4:
            raise c.fail(f"{path}.path", f"degenerate mesh {file}: it has no faces")
        if not _has_volume(vertices):
            raise c.fail(f"{path}.path", f"degenerate mesh {file}: zero volume "
                                         "(all vertices lie on one plane)")
        if not loaded.is_watertight:
            raise c.fail(f"{path}.path", f"mesh {file} is not closed (watertight); the "
                                         "convex decomposition needs a solid")

    try:
        found = decomposed(content, file.suffix.lstrip(".").lower(), settings, check,
                           ConvexPart.from_points)
    except MeshReadError as exc:
        raise c.fail(f"{path}.path", f"cannot read {file} as a mesh: {exc}") from None
    parts = tuple(ConvexPart(*fields).placed(scale, rot, position) for fields in found.parts)
    placed = MeshData((scale * found.mesh.vertices) @ rot.T + position, found.mesh.faces)
    return parts, placed


def _has_volume(vertices: np.ndarray) -> bool:
    centred = vertices - vertices.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    return bool(singular[-1] > 1e-9 * max(singular[0], 1e-300))

