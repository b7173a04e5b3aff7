"""The python-fcl side of the verdict (``world.check``): a scene part's fcl object, the
capsule around a piece of the body, a scene's fcl objects with the arrays the vectorised
bounds need (built once per ``Scene``), and fcl's signed distance.
"""

from __future__ import annotations

import math
import weakref

import fcl
import numpy as np

from .scene import (
    BoxPart,
    CapsulePart,
    ConvexPart,
    CylinderPart,
    Part,
    Scene,
    SpherePart,
    bounding_sphere,
    rotation_z_to,
)


def fcl_object(part: Part) -> fcl.CollisionObject:
    """The fcl collision object of a scene part, placed in the world."""
    if isinstance(part, SpherePart):
        return fcl.CollisionObject(fcl.Sphere(float(part.radius)),
                                   fcl.Transform(np.asarray(part.center, dtype=float)))
    if isinstance(part, BoxPart):
        return fcl.CollisionObject(fcl.Box(*(2.0 * part.half_size)),
                                   fcl.Transform(part.rotation, part.center))
    if isinstance(part, CapsulePart):
        return capsule_object(part.a, part.b, part.radius)
    if isinstance(part, CylinderPart):
        return fcl.CollisionObject(fcl.Cylinder(float(part.radius), 2.0 * part.half_length),
                                   fcl.Transform(part.rotation, part.center))
    if isinstance(part, ConvexPart):
        tris = np.asarray(part.triangles, dtype=np.int64)
        faces = np.c_[np.full(len(tris), 3), tris].ravel()
        return fcl.CollisionObject(fcl.Convex(part.vertices, len(tris), faces), fcl.Transform())
    raise TypeError(f"not a scene part: {type(part).__name__}")


def capsule_object(a: np.ndarray, b: np.ndarray, radius: float) -> fcl.CollisionObject:
    """An fcl capsule of ``radius`` (m) around the segment a–b (fcl's capsule lies along z).
    Computed in Python floats: the verdict builds one for each piece it measures."""
    ax, ay, az = np.asarray(a, dtype=float).tolist()
    bx, by, bz = np.asarray(b, dtype=float).tolist()
    dx, dy, dz = bx - ax, by - ay, bz - az
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    if length < 1e-12:
        return fcl.CollisionObject(fcl.Sphere(float(radius)),
                                   fcl.Transform(np.array([ax, ay, az])))
    centre = np.array([0.5 * (ax + bx), 0.5 * (ay + by), 0.5 * (az + bz)])
    return fcl.CollisionObject(fcl.Capsule(float(radius), length),
                               fcl.Transform(rotation_z_to((dx, dy, dz)), centre))


class FclScene:
    """A scene's fcl objects and the arrays the vectorised verdict needs."""

    def __init__(self, scene: Scene) -> None:
        parts = scene.parts
        owner = scene.part_obstacle
        self.objects = [fcl_object(p) for p in parts]
        self.names = [scene.obstacles[i].name for i in owner]
        sphere = [i for i, p in enumerate(parts) if isinstance(p, SpherePart)]
        other = [i for i, p in enumerate(parts) if not isinstance(p, SpherePart)]
        # Sphere parts: exact closed form (see capsule_sphere_distance).
        self.sphere_index = np.array(sphere, dtype=np.int64)
        self.sphere_centres = np.array([parts[i].center for i in sphere],
                                       dtype=float).reshape(-1, 3)
        self.sphere_radii = np.array([parts[i].radius for i in sphere], dtype=float)
        # Other parts: fcl, pruned by lower bounds.
        self.other_index = np.array(other, dtype=np.int64)
        bounds = [bounding_sphere(parts[i]) for i in other]
        self.other_centres = np.array([c for c, _ in bounds], dtype=float).reshape(-1, 3)
        self.other_radii = np.array([r for _, r in bounds], dtype=float)
        # Face planes n·x ≤ o of boxes and convex parts, padded by repeating a row (the
        # max over planes is unchanged); parts without planes get a −inf row.
        planes = [_face_planes(parts[i]) for i in other]
        width = max([len(o) for _, o in planes] + [1])
        normals = np.zeros((len(other), width, 3))
        self.offsets = np.full((len(other), width), np.inf)
        for q, (n, o) in enumerate(planes):
            if len(o):
                normals[q] = np.concatenate([n, np.repeat(n[:1], width - len(o), 0)])
                self.offsets[q] = np.concatenate([o, np.repeat(o[:1], width - len(o))])
        self.normals = tuple(np.ascontiguousarray(normals[..., k]) for k in range(3))
        self.other_centre_norm2 = np.einsum("ij,ij->i", self.other_centres, self.other_centres)
        # Axis-aligned boxes around the parts, 1e-12 m wider than rounding could need.
        boxes = [_axis_aligned_box(parts[i]) for i in other]
        self.box_lower = np.array([lo for lo, _ in boxes], dtype=float).reshape(-1, 3) - 1e-12
        self.box_upper = np.array([hi for _, hi in boxes], dtype=float).reshape(-1, 3) + 1e-12
        # The same, a coordinate at a time (gathering from a 1-D array is the fast kind).
        self.other_centres_xyz, self.box_lower_xyz, self.box_upper_xyz = (
            tuple(np.ascontiguousarray(a[:, k]) for k in range(3))
            for a in (self.other_centres, self.box_lower, self.box_upper))
        # float32 copies for the motion search's first, dense bounds (``_motion_check.
        # _tile_bounds``), and the largest coordinate or radius they hold, m.
        self.other_centres32, self.other_radii32, self.box_lower32, self.box_upper32 = (
            a.astype(np.float32) for a in (self.other_centres, self.other_radii,
                                           self.box_lower, self.box_upper))
        finite = [np.abs(a[np.isfinite(a)]) for a in (self.other_centres, self.other_radii,
                                                      self.box_lower, self.box_upper)]
        self.extent = float(max((a.max() for a in finite if a.size), default=0.0))
        # Capsules and cylinders: the capsule around the axis contains the part.
        axis = [_axis(parts[i]) for i in other]
        self.axis_a = np.array([a for a, _, _ in axis], dtype=float).reshape(-1, 3)
        self.axis_b = np.array([b for _, b, _ in axis], dtype=float).reshape(-1, 3)
        self.axis_radius = np.array([r for _, _, r in axis], dtype=float)
        self.has_axis = np.array([np.isfinite(r) for _, _, r in axis], dtype=bool)


def _face_planes(part: Part) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals (F, 3) and offsets (F,) of a box's or convex part's faces
    (the part is {x : n·x ≤ o}); none for other parts."""
    if isinstance(part, BoxPart):
        rotation = np.asarray(part.rotation, dtype=float)
        normals = np.concatenate([rotation.T, -rotation.T])
        half = np.asarray(part.half_size, dtype=float)
        centre = np.asarray(part.center, dtype=float)
        return normals, normals @ centre + np.concatenate([half, half])
    if isinstance(part, ConvexPart):
        return np.asarray(part.normals, dtype=float), np.asarray(part.offsets, dtype=float)
    return np.zeros((0, 3)), np.zeros(0)


def _axis_aligned_box(part: Part) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners (3,) m of an axis-aligned box that contains the part."""
    if isinstance(part, BoxPart):
        extent = np.abs(np.asarray(part.rotation, dtype=float)) @ np.asarray(part.half_size,
                                                                              dtype=float)
        centre = np.asarray(part.center, dtype=float)
        return centre - extent, centre + extent
    if isinstance(part, (CapsulePart, CylinderPart)):    # in the capsule around the axis
        a, b = np.asarray(part.a, dtype=float), np.asarray(part.b, dtype=float)
        return np.minimum(a, b) - part.radius, np.maximum(a, b) + part.radius
    if isinstance(part, ConvexPart):
        vertices = np.asarray(part.vertices, dtype=float)
        return vertices.min(axis=0), vertices.max(axis=0)
    centre, radius = bounding_sphere(part)
    return np.asarray(centre, dtype=float) - radius, np.asarray(centre, dtype=float) + radius


def _axis(part: Part) -> tuple[np.ndarray, np.ndarray, float]:
    """The axis end points and radius of a capsule or cylinder part (+inf radius: none)."""
    if isinstance(part, (CapsulePart, CylinderPart)):
        return (np.asarray(part.a, dtype=float), np.asarray(part.b, dtype=float),
                float(part.radius))
    return np.zeros(3), np.zeros(3), np.inf


_SCENES: weakref.WeakKeyDictionary[Scene, FclScene] = weakref.WeakKeyDictionary()
_NO_OBSTACLES = Scene("no obstacles", ())


def fcl_scene(scene: Scene | None) -> FclScene:
    """The fcl objects and arrays of ``scene`` (None: no obstacles), built on first use."""
    scene = _NO_OBSTACLES if scene is None else scene
    built = _SCENES.get(scene)
    if built is None:
        built = _SCENES[scene] = FclScene(scene)
    return built


_UNSIGNED = fcl.DistanceRequest(enable_nearest_points=True, enable_signed_distance=False)
_SIGNED = fcl.DistanceRequest(enable_nearest_points=True, enable_signed_distance=True)


def fcl_distance(a: fcl.CollisionObject, b: fcl.CollisionObject) -> float:
    """fcl's signed distance between two objects (m; negative = penetration depth).

    Separated pairs use fcl's unsigned query: its signed one was measured off by up to
    1.2 mm for separated sphere–box pairs (depending on the argument order), while
    the unsigned one matched the closed form to 1e-9. Only colliding pairs (reported
    as −1) go to the signed query (EPA) for their depth."""
    d = float(fcl.distance(a, b, _UNSIGNED, fcl.DistanceResult()))
    if d > 0.0:
        return d
    return min(float(fcl.distance(a, b, _SIGNED, fcl.DistanceResult())), 0.0)


class Capsules:
    """``capsule_object(a[i], b[i], r)`` for pieces a, b (N, 3), each built on first use.

    Built by ``capsule_object`` itself, not from rotations vectorised here: fcl's GJK
    answers capsule–convex distances only to ~1e-5 m, and a 1e-16 change of the capsule's
    rotation was seen to move its answer by 1.6e-5 m; the same inputs keep the verdict
    identical to the per-configuration one."""

    def __init__(self, r: float, a: np.ndarray, b: np.ndarray) -> None:
        self.r, self.a, self.b = r, a, b
        self.built: list[fcl.CollisionObject | None] = [None] * len(a)

    def __getitem__(self, i: int) -> fcl.CollisionObject:
        capsule = self.built[i]
        if capsule is None:
            capsule = self.built[i] = capsule_object(self.a[i], self.b[i], self.r)
        return capsule
