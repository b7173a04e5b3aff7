"""The independent collision verdict, by python-fcl.

The robot's body is a chain of capsules of radius ``backbone_radius`` between
consecutive points of base, backbone point 1, …, backbone point n·k (float64
kinematics). Each is measured against every obstacle part (``fcl.Sphere``, ``Box``,
``Capsule``, ``Cylinder`` and ``Convex`` for the mesh parts) with fcl's signed
distance (GJK/EPA: negative = penetration depth, metres), and against the capsules
of segments at least two apart (self-collision). This verdict, not the optimizer's
clearance, decides whether a configuration is collision-free.

The scene's fcl objects are built once per ``Scene`` and reused; per query only the
robot's capsules are made. Pairs are visited in order of a bounding-sphere lower bound
and the search stops when no remaining pair can beat the best distance, so the minimum
is exact while most pairs are never handed to fcl.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any

import fcl
import numpy as np

from ..model._ops import NUMPY
from ..model.kinematics import model_backbone, model_q_to_z
from ..model.robot import Robot
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


@dataclass(frozen=True)
class CheckResult:
    """The verdict for one configuration (distances signed, metres)."""

    collision: bool
    """True if the body penetrates an obstacle or itself (min_distance < 0)."""
    min_distance: float
    """min(obstacle_distance, self_distance)."""
    closest: str
    """Name of the obstacle at ``min_distance``, "self" for the robot itself, "" if none."""
    self_collision: bool
    """True if capsules of segments at least two apart penetrate."""
    obstacle_distance: float
    """Smallest signed distance between the body and any obstacle (+inf: no obstacles)."""
    self_distance: float
    """Smallest signed distance between non-neighbouring segments (+inf: fewer than 3)."""


@dataclass(frozen=True)
class CheckManyResult:
    """Verdicts for a batch: arrays of shape (B,), ``closest`` a tuple of B names."""

    collision: np.ndarray
    min_distance: np.ndarray
    self_collision: np.ndarray
    obstacle_distance: np.ndarray
    self_distance: np.ndarray
    closest: tuple[str, ...]


# ================================================================ kinematics (float64)


def body_chain(robot: Robot, q: Any) -> np.ndarray:
    """(…, 1 + n·k, 3) base point followed by the backbone points (m), float64 numpy, for
    q (…, 3n) (rad, rad, m)."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (robot.dof,):
        raise ValueError(f"q must have {robot.dof} entries on its last axis, got shape {q.shape}")
    with np.errstate(invalid="ignore", divide="ignore"):  # the unused branch of safe_where
        z = model_q_to_z(NUMPY, robot, q)
        points = model_backbone(NUMPY, robot, z)
    base = np.broadcast_to(np.asarray(robot.base_position, dtype=float), q.shape[:-1] + (1, 3))
    return np.concatenate([base, points], axis=-2)


# ================================================================ fcl objects


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
    """An fcl capsule of ``radius`` (m) around the segment a–b (fcl's capsule lies along z)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    axis = b - a
    length = float(np.linalg.norm(axis))
    if length < 1e-12:
        return fcl.CollisionObject(fcl.Sphere(float(radius)), fcl.Transform(a))
    return fcl.CollisionObject(fcl.Capsule(float(radius), length),
                               fcl.Transform(rotation_z_to(axis), 0.5 * (a + b)))


class _FclScene:
    def __init__(self, scene: Scene) -> None:
        parts = scene.parts
        owner = scene.part_obstacle
        self.objects = [fcl_object(p) for p in parts]
        # Spheres get the exact closed form instead of fcl (see capsule_sphere_distance).
        self.sphere = [(np.asarray(p.center, dtype=float), float(p.radius))
                       if isinstance(p, SpherePart) else None for p in parts]
        spheres = [bounding_sphere(p) for p in parts]
        self.centres = np.array([c for c, _ in spheres], dtype=float).reshape(-1, 3)
        self.radii = np.array([r for _, r in spheres], dtype=float)
        self.names = [scene.obstacles[i].name for i in owner]


_SCENES: weakref.WeakKeyDictionary[Scene, _FclScene] = weakref.WeakKeyDictionary()


def _fcl_scene(scene: Scene) -> _FclScene:
    built = _SCENES.get(scene)
    if built is None:
        built = _SCENES[scene] = _FclScene(scene)
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


# ================================================================ the verdict


def _min_over_pairs(lower: np.ndarray, distance: Any) -> tuple[float, int]:
    """Smallest ``distance(flat index)`` over a matrix of lower bounds, visiting pairs in
    order of their bound and stopping once no pair can beat the best (exact minimum)."""
    flat = lower.ravel()
    best, best_index = np.inf, -1
    for index in np.argsort(flat, kind="stable"):
        if flat[index] >= best:
            break
        d = distance(int(index))
        if d < best:
            best, best_index = d, int(index)
    return best, best_index


def capsule_sphere_distance(a: np.ndarray, b: np.ndarray, radius: float, centre: np.ndarray,
                            sphere_radius: float) -> float:
    """Exact signed distance (m) between the capsule of ``radius`` around segment a–b and a
    sphere: the distance from the centre to the segment minus both radii.

    Used instead of fcl for spheres: fcl's penetration query (EPA) was seen to never
    return when a sphere's centre lies on the capsule's axis."""
    ab = b - a
    denominator = float(ab @ ab)
    t = 0.0 if denominator <= 0.0 else min(max(float((centre - a) @ ab) / denominator, 0.0), 1.0)
    return float(np.linalg.norm(centre - (a + t * ab))) - radius - sphere_radius


def _check_chain(robot: Robot, fscene: _FclScene, chain: np.ndarray) -> CheckResult:
    r = robot.backbone_radius
    a, b = chain[:-1], chain[1:]
    mid = 0.5 * (a + b)
    reach = 0.5 * np.linalg.norm(b - a, axis=1) + r   # bounding-sphere radius of each capsule
    capsules: dict[int, fcl.CollisionObject] = {}

    def capsule(i: int) -> fcl.CollisionObject:
        if i not in capsules:
            capsules[i] = capsule_object(a[i], b[i], r)
        return capsules[i]

    n_parts = len(fscene.objects)
    obstacle, closest = np.inf, ""
    if n_parts:
        lower = (np.linalg.norm(mid[:, None, :] - fscene.centres[None], axis=-1)
                 - reach[:, None] - fscene.radii[None])
        def pair(k: int) -> float:
            i, j = divmod(k, n_parts)
            sphere = fscene.sphere[j]
            if sphere is not None:
                return capsule_sphere_distance(a[i], b[i], r, *sphere)
            return fcl_distance(capsule(i), fscene.objects[j])

        obstacle, index = _min_over_pairs(lower, pair)
        closest = fscene.names[index % n_parts] if index >= 0 else ""

    own = np.inf
    k = robot.points_per_segment
    segment = np.arange(len(a)) // k          # piece i joins chain points i and i + 1
    far = np.abs(segment[:, None] - segment[None, :]) >= 2
    far &= np.triu(np.ones_like(far), 1).astype(bool)
    if far.any():
        centre_gap = np.linalg.norm(mid[:, None, :] - mid[None], axis=-1)
        lower = np.where(far, centre_gap - reach[:, None] - reach[None], np.inf)
        m = len(a)
        own, _ = _min_over_pairs(lower, lambda q: fcl_distance(capsule(q // m), capsule(q % m)))

    min_distance = min(obstacle, own)
    if own < obstacle:
        closest = "self"
    return CheckResult(collision=bool(min_distance < 0.0), min_distance=float(min_distance),
                       closest=closest, self_collision=bool(own < 0.0),
                       obstacle_distance=float(obstacle), self_distance=float(own))


def check(robot: Robot, scene: Scene, q: Any) -> CheckResult:
    """The python-fcl verdict for one configuration q (3n; rad, rad, m)."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (robot.dof,):
        raise ValueError(f"check takes one configuration of {robot.dof} entries, got {q.shape}")
    return _check_chain(robot, _fcl_scene(scene), body_chain(robot, q))


def check_many(robot: Robot, scene: Scene, qs: Any) -> CheckManyResult:
    """The verdicts for a batch of configurations qs (B, 3n)."""
    qs = np.asarray(qs, dtype=np.float64).reshape(-1, robot.dof)
    chains = body_chain(robot, qs)
    fscene = _fcl_scene(scene)
    results = [_check_chain(robot, fscene, chain) for chain in chains]
    return CheckManyResult(
        collision=np.array([r.collision for r in results], dtype=bool),
        min_distance=np.array([r.min_distance for r in results]),
        self_collision=np.array([r.self_collision for r in results], dtype=bool),
        obstacle_distance=np.array([r.obstacle_distance for r in results]),
        self_distance=np.array([r.self_distance for r in results]),
        closest=tuple(r.closest for r in results),
    )
