"""Differentiable clearance: signed distances between the robot's body and a scene.

The body is a chain of spheres of radius ``robot.backbone_radius`` centred at the base
point and at the backbone points (``N = 1 + n·k`` spheres, index 0 is the base). The
clearance is the minimum over

- every (body sphere, obstacle part) pair (``distances.py``, one formula per part kind);
- every pair of spheres on non-neighbouring segments (self-clearance), where the
  spheres of segment s are the end points of its chain of k backbone pieces, the
  junction with segment s − 1 (or the base) included; robots with fewer than three
  segments have no self pairs.

JAX front end (batched over configurations, jit-compiled once per robot and array
shapes, float32 or float64): ``pair_distances`` (…, N, P), ``self_distances`` (…, M),
``clearance`` (…,) and the smooth lower bound ``soft_clearance``. A scene enters as
``SceneArrays``, a pytree of arrays: another scene with the same part counts reuses the
compiled code. CasADi front end for Ipopt: ``casadi_clearance``, one output per pair
near a given configuration.

Error budget against the independent verdict (``check.py``: capsules between
consecutive points of the same chain, the base included). With h the longest piece
of the chain (≤ max Lᵢ/k) and r the body radius, for every configuration

    clearance(q) ≤ max(d_true(q), 0) + body_gap_tolerance(robot),

    body_gap_tolerance = max(√(r² + h²/4) − r, √(4r² + h²/2) − 2r),

so ``clearance(q) ≥ body_gap_tolerance(robot)`` proves the capsule body collision-free
(tdcr3: r = h = 0.1 m gives 0.0121 m). Why: the point of a piece closest to a convex
part is within h/2 of a sphere centre, along the piece and orthogonal to the direction
towards the part (√(m² + h²/4) − m ≤ √(r² + h²/4) − r for a gap m ≥ r); for two pieces
the two offsets add to at most h/√2. The convex-part formula and its smoothing only
make the clearance smaller (``distances.py``).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from functools import cache, partial
from typing import Any, NamedTuple

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np

from ..model._ops import CASADI, JAX, NUMPY, Ops
from ..model.kinematics import model_backbone, model_q_to_z, q_to_z
from ..model.robot import Robot
from . import _distances as dist
from .scene import (
    BoxPart,
    CapsulePart,
    ConvexPart,
    CylinderPart,
    Scene,
    SpherePart,
)

# ================================================================ scene as arrays


class SceneArrays(NamedTuple):
    """The parts of a scene as arrays (metres), grouped by kind in ``PART_KINDS`` order.

    Rotations are world-from-part. ``convex_planes`` is (C, F, 4) rows (nx, ny, nz, b)
    of the planes n·x ≤ b, F a power of two; parts with fewer planes repeat their first.
    """

    sphere_center: Any      # (S, 3)
    sphere_radius: Any      # (S,)
    box_center: Any         # (B, 3)
    box_rotation: Any       # (B, 3, 3)
    box_half_size: Any      # (B, 3)
    capsule_a: Any          # (A, 3)
    capsule_b: Any          # (A, 3)
    capsule_radius: Any     # (A,)
    cylinder_center: Any    # (Y, 3)
    cylinder_rotation: Any  # (Y, 3, 3)
    cylinder_radius: Any    # (Y,)
    cylinder_half_length: Any  # (Y,)
    convex_planes: Any      # (C, F, 4)

    @property
    def n_parts(self) -> int:
        return int(sum(x.shape[0] for x in (self.sphere_radius, self.box_center,
                                             self.capsule_radius, self.cylinder_radius,
                                             self.convex_planes)))


def scene_arrays(scene: Scene, dtype: Any = None, as_numpy: bool = False) -> SceneArrays:
    """The ``SceneArrays`` of a scene, as JAX arrays of ``dtype`` (default: JAX's default
    float, float64 when x64 is enabled) or as float64 numpy arrays with ``as_numpy``."""
    parts = scene.parts

    def stack(values: list, shape: tuple[int, ...]) -> np.ndarray:
        return np.array(values, dtype=float).reshape((len(values),) + shape)

    spheres = [p for p in parts if isinstance(p, SpherePart)]
    boxes = [p for p in parts if isinstance(p, BoxPart)]
    capsules = [p for p in parts if isinstance(p, CapsulePart)]
    cylinders = [p for p in parts if isinstance(p, CylinderPart)]
    convex = [p for p in parts if isinstance(p, ConvexPart)]
    # A power of two, for the halving tree max (distances.tree_max).
    faces = 1 << max(0, math.ceil(math.log2(max((len(p.offsets) for p in convex), default=1))))
    planes = np.zeros((len(convex), faces, 4))
    for i, p in enumerate(convex):
        rows = np.c_[p.normals, p.offsets]
        planes[i] = np.concatenate([rows, np.repeat(rows[:1], faces - len(rows), axis=0)])
    arrays = SceneArrays(
        stack([p.center for p in spheres], (3,)), stack([p.radius for p in spheres], ()),
        stack([p.center for p in boxes], (3,)), stack([p.rotation for p in boxes], (3, 3)),
        stack([p.half_size for p in boxes], (3,)),
        stack([p.a for p in capsules], (3,)), stack([p.b for p in capsules], (3,)),
        stack([p.radius for p in capsules], ()),
        stack([p.center for p in cylinders], (3,)),
        stack([p.rotation for p in cylinders], (3, 3)),
        stack([p.radius for p in cylinders], ()), stack([p.half_length for p in cylinders], ()),
        planes,
    )
    if as_numpy:
        return arrays
    dtype = dtype or jnp.result_type(float)
    return SceneArrays(*(jnp.asarray(a, dtype=dtype) for a in arrays))


def scene_digest(scene: Scene) -> str:
    """sha256 (hex) of a scene's content, the key of what is built from it and cached: its
    file form and its parts' arrays (``scene_arrays``: they cover mesh contents and their
    decomposition)."""
    digest = hashlib.sha256(json.dumps(scene.to_dict(), sort_keys=True, default=str).encode())
    for array in scene_arrays(scene, as_numpy=True):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()


# ================================================================ the body


def body_segments(robot: Robot) -> list[np.ndarray]:
    """Indices of the body spheres on each segment's chain (end points of its k pieces,
    the junction with the previous segment, or the base, included)."""
    k = robot.points_per_segment
    return [np.arange(s * k, s * k + k + 1) for s in range(robot.n_segments)]


def self_pairs(robot: Robot) -> np.ndarray:
    """(M, 2) body-sphere index pairs on segments at least two apart (M = 0 for n < 3 or
    when the robot file turns self-collision off)."""
    if not robot.has_self_pairs:
        return np.zeros((0, 2), dtype=np.int64)
    chains = body_segments(robot)
    pairs = {(int(i), int(j)) if i < j else (int(j), int(i))
             for s in range(robot.n_segments) for t in range(s + 2, robot.n_segments)
             for i in chains[s] for j in chains[t]}
    return np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)


def body_gap_tolerance(robot: Robot) -> float:
    """How much the sphere-chain clearance can exceed the capsule-chain distance near
    contact (metres): see the module docstring."""
    r = robot.backbone_radius
    h = max(s.length_max for s in robot.segments) / robot.points_per_segment
    return max(math.sqrt(r * r + h * h / 4) - r, math.sqrt(4 * r * r + h * h / 2) - 2 * r)


def _body_centres(ops: Ops, robot: Robot, z: list[Any]) -> Any:
    """(…, N, 3) JAX or NumPy array, or an N × 3 CasADi matrix, of body-sphere centres."""
    points = model_backbone(ops, robot, z)
    if ops is CASADI:
        return ca.vertcat(ca.DM(np.array(robot.base_position, dtype=float)).T, points)
    xp = np if ops is NUMPY else jnp
    base = xp.broadcast_to(xp.asarray(robot.base_position, dtype=points.dtype),
                           points.shape[:-2] + (1, 3))
    return xp.concatenate([base, points], axis=-2)


# ================================================================ pair distances, JAX

def _cols(x: Any) -> tuple[Any, ...]:
    return tuple(x[..., i] for i in range(x.shape[-1]))


def _rot_entries(r: Any) -> tuple[Any, ...]:
    return tuple(r[..., i, j] for i in range(3) for j in range(3))


def _kind_blocks(robot: Robot, arrays: SceneArrays, centres: Any,
                 smoothing: float, ops: Ops = JAX) -> list[Any]:
    """Per part kind, the (…, N, count) distances of every body sphere to every part
    (``ops``: JAX, or NUMPY for float64 numpy arrays)."""
    return kind_distances(robot.backbone_radius, arrays, centres, smoothing, ops)


def kind_distances(radius: float, arrays: SceneArrays, centres: Any,
                   smoothing: float = 0.0, ops: Ops = JAX) -> list[Any]:
    """Per present part kind (``PART_KINDS`` order), the (…, N, count) signed distances (m)
    of spheres of ``radius`` m centred at ``centres`` (…, N, 3) m to every part of that
    kind (``ops``: JAX, or NUMPY for float64 numpy arrays); radius 0 gives the points'
    signed distances to the parts."""
    c = tuple(centres[..., :, None, i] for i in range(3))
    r = radius
    a = arrays
    blocks = []
    if a.sphere_radius.shape[0]:
        blocks.append(dist.sphere_to_sphere(ops, c, r, _cols(a.sphere_center), a.sphere_radius))
    if a.box_center.shape[0]:
        blocks.append(dist.sphere_to_box(ops, c, r, _cols(a.box_center),
                                         _rot_entries(a.box_rotation), _cols(a.box_half_size)))
    if a.capsule_radius.shape[0]:
        blocks.append(dist.sphere_to_capsule(ops, c, r, _cols(a.capsule_a), _cols(a.capsule_b),
                                             a.capsule_radius))
    if a.cylinder_radius.shape[0]:
        blocks.append(dist.sphere_to_cylinder(
            ops, c, r, _cols(a.cylinder_center), _rot_entries(a.cylinder_rotation),
            a.cylinder_radius, a.cylinder_half_length))
    if a.convex_planes.shape[0]:
        # Faces on a trailing axis: (…, N, C, F) plane values, reduced over F.
        c_faces = tuple(x[..., None] for x in c)
        blocks.append(dist.sphere_to_convex(ops, c_faces, r, _cols(a.convex_planes),
                                            a.convex_planes.shape[1], smoothing))
    return blocks


def _self_block(robot: Robot, centres: Any, ops: Ops = JAX,
                pairs: np.ndarray | None = None) -> Any:
    pairs = self_pairs(robot) if pairs is None else pairs
    r = robot.backbone_radius
    ci, cj = centres[..., pairs[:, 0], :], centres[..., pairs[:, 1], :]
    return dist.sphere_to_sphere(ops, _cols(ci), r, _cols(cj), r)


def _centres(robot: Robot, x: jax.Array, is_q: bool) -> jax.Array:
    """Body-sphere centres (…, N, 3) from q (θ, φ, L) or from the bending vector z."""
    x = q_to_z(robot, x) if is_q else jnp.asarray(x)
    # Keep the caller's precision (the model's float64 constants would promote float32).
    return _body_centres(JAX, robot, [x[..., i] for i in range(robot.dof)]).astype(x.dtype)


def _pairs(robot: Robot, arrays: SceneArrays, x: jax.Array, is_q: bool,
           face_smoothing: float) -> jax.Array:
    centres = _centres(robot, x, is_q)
    blocks = _kind_blocks(robot, arrays, centres, face_smoothing)
    if not blocks:
        return jnp.zeros(centres.shape[:-1] + (0,), centres.dtype)
    return jnp.concatenate(blocks, axis=-1)


def _clearance(robot: Robot, arrays: SceneArrays, x: jax.Array, is_q: bool,
               face_smoothing: float, include_self: bool) -> jax.Array:
    centres = _centres(robot, x, is_q)
    out = jnp.full(centres.shape[:-2], jnp.inf, centres.dtype)
    # One reduction per kind: no concatenated (…, N, P) array is built just to be reduced.
    for block in _kind_blocks(robot, arrays, centres, face_smoothing):
        out = jnp.minimum(out, jnp.min(block, axis=(-2, -1)))
    if include_self and robot.has_self_pairs:
        out = jnp.minimum(out, jnp.min(_self_block(robot, centres), axis=-1))
    return out


def _soft_clearance(robot: Robot, arrays: SceneArrays, x: jax.Array, is_q: bool,
                    temperature: float, face_smoothing: float) -> jax.Array:
    centres = _centres(robot, x, is_q)
    flat = [b.reshape(b.shape[:-2] + (-1,))
            for b in _kind_blocks(robot, arrays, centres, face_smoothing)]
    if robot.has_self_pairs:
        flat.append(_self_block(robot, centres))
    if not flat:
        return jnp.full(centres.shape[:-2], jnp.inf, centres.dtype)
    d = jnp.concatenate(flat, axis=-1)
    return -temperature * jax.nn.logsumexp(-d / temperature, axis=-1)


@partial(jax.jit, static_argnums=(0, 3))
def pair_distances(robot: Robot, arrays: SceneArrays, q: jax.Array,
                   face_smoothing: float = 0.0) -> jax.Array:
    """(…, N, P) signed distances (m) between the N = 1 + n·k body spheres (base first)
    and the P parts of the scene (``scene.parts`` order), for q (…, 3n) (rad, rad, m).

    ``face_smoothing`` μ (m) smooths the max over the face planes of convex parts
    (a lower bound, at most ⌈log₂ F⌉·μ/2 below the unsmoothed value)."""
    return _pairs(robot, arrays, q, True, face_smoothing)


@partial(jax.jit, static_argnums=(0, 3))
def pair_distances_z(robot: Robot, arrays: SceneArrays, z: jax.Array,
                     face_smoothing: float = 0.0) -> jax.Array:
    """``pair_distances`` of the bending-vector form z (…, 3n) (rad, rad, m)."""
    return _pairs(robot, arrays, z, False, face_smoothing)


@partial(jax.jit, static_argnums=0)
def self_distances(robot: Robot, q: jax.Array) -> jax.Array:
    """(…, M) signed distances (m) between body spheres of non-neighbouring segments,
    one per row of ``self_pairs(robot)``, for q (…, 3n)."""
    return _self_block(robot, _centres(robot, q, True))


@partial(jax.jit, static_argnums=0)
def self_distances_z(robot: Robot, z: jax.Array) -> jax.Array:
    """``self_distances`` of the bending-vector form z (…, 3n)."""
    return _self_block(robot, _centres(robot, z, False))


@partial(jax.jit, static_argnums=(0, 3, 4))
def clearance(robot: Robot, arrays: SceneArrays, q: jax.Array, face_smoothing: float = 0.0,
              include_self: bool = True) -> jax.Array:
    """(…,) clearance (m) of q (…, 3n; rad, rad, m): the minimum signed distance between
    the body and every obstacle part and, with ``include_self``, between non-neighbouring
    segments; +inf when there is no pair.

    Never above the capsule-body distance by more than ``body_gap_tolerance(robot)``
    near contact (module docstring)."""
    return _clearance(robot, arrays, q, True, face_smoothing, include_self)


@partial(jax.jit, static_argnums=(0, 3, 4))
def clearance_z(robot: Robot, arrays: SceneArrays, z: jax.Array, face_smoothing: float = 0.0,
                include_self: bool = True) -> jax.Array:
    """``clearance`` of the bending-vector form z (…, 3n)."""
    return _clearance(robot, arrays, z, False, face_smoothing, include_self)


@partial(jax.jit, static_argnums=(0, 4))
def soft_clearance(robot: Robot, arrays: SceneArrays, q: jax.Array, temperature: float,
                   face_smoothing: float = 0.0) -> jax.Array:
    """(…,) smooth lower bound −τ·log Σₖ exp(−dₖ/τ) of ``clearance`` over all K pairs
    (obstacle and self), for q (…, 3n): between clearance − τ·log K and clearance
    (τ = ``temperature``, metres)."""
    return _soft_clearance(robot, arrays, q, True, temperature, face_smoothing)


@partial(jax.jit, static_argnums=(0, 4))
def soft_clearance_z(robot: Robot, arrays: SceneArrays, z: jax.Array, temperature: float,
                     face_smoothing: float = 0.0) -> jax.Array:
    """``soft_clearance`` of the bending-vector form z (…, 3n)."""
    return _soft_clearance(robot, arrays, z, False, temperature, face_smoothing)


def backbone_clearance_numpy(radius: float, arrays: SceneArrays | None,
                             points: Any) -> np.ndarray:
    """Float64 numpy: (…,) the smallest signed distance (m) from spheres of ``radius`` m at
    the backbone ``points`` (…, P, 3) m and at the midpoints between neighbours to any part
    of the scene (``arrays``: numpy ``SceneArrays``; inf with none). A quick screen (e.g.
    of seed pools); the verdict uses python-fcl capsules."""
    points = np.asarray(points, dtype=np.float64)
    if arrays is None or arrays.n_parts == 0:
        return np.full(points.shape[:-2], np.inf)
    centres = np.concatenate([points, 0.5 * (points[..., 1:, :] + points[..., :-1, :])],
                             axis=-2)
    blocks = kind_distances(radius, arrays, centres, 0.0, NUMPY)
    return np.min(np.concatenate(blocks, axis=-1), axis=(-2, -1))


@cache
def chain_self_pairs(segments: int, per_segment: int) -> np.ndarray:
    """(M, 2) index pairs of the spheres of a backbone chain of ``segments`` ×
    ``per_segment`` pieces (its 1 + n·k points, then its n·k piece midpoints) whose pieces
    lie on segments at least two apart (the verdict's self pairs)."""
    pieces = segments * per_segment
    point = np.arange(pieces + 1)
    low = np.r_[np.maximum(point - 1, 0) // per_segment, np.arange(pieces) // per_segment]
    high = np.r_[np.minimum(point, pieces - 1) // per_segment, np.arange(pieces) // per_segment]
    # A point joins the pieces on each side: a pair counts where any piece of one lies
    # two segments from any piece of the other (the verdict's capsules hold both ends).
    apart = (high[:, None] - low[None, :] >= 2) | (high[None, :] - low[:, None] >= 2)
    return np.stack(np.nonzero(np.triu(apart, 1)), axis=1)


def chain_self_distances(robot: Robot, chains: Any, ops: Ops = JAX) -> Any:
    """(…, M) signed distances (m) between spheres of the backbone radius at the points and
    piece midpoints of backbone chains (…, 1 + n·k, 3) m on segments at least two apart
    (``chain_self_pairs``; M = 0 for fewer than three segments; ``ops``: JAX or NUMPY)."""
    xp = np if ops is NUMPY else jnp
    centres = xp.concatenate([chains, 0.5 * (chains[..., 1:, :] + chains[..., :-1, :])], axis=-2)
    segments = len(robot.segments)
    pairs = chain_self_pairs(segments, (chains.shape[-2] - 1) // segments)
    return _self_block(robot, centres, ops, pairs)


def chain_self_clearance_numpy(robot: Robot, chains: Any) -> np.ndarray:
    """Float64 numpy: (B,) the smallest of ``chain_self_distances`` of each chain (inf for
    fewer than three segments)."""
    distances = chain_self_distances(robot, np.asarray(chains, dtype=np.float64), NUMPY)
    return distances.min(axis=-1, initial=np.inf)


def all_pair_distances_numpy(robot: Robot, arrays: SceneArrays | None, z: Any,
                             face_smoothing: float = 0.0,
                             include_self: bool = True) -> np.ndarray:
    """Float64 numpy, every pair of the exact stage: (…, N·P + M) signed distances (m) of
    the bending-vector configurations z (…, 3n), the N·P obstacle pairs body-major
    (``pair_distances_z`` flattened), then, with ``include_self`` and n ≥ 3 segments, the
    M self pairs (``self_distances_z``). ``arrays``: numpy ``SceneArrays`` or None."""
    z = np.asarray(z, dtype=np.float64)
    centres = _body_centres(NUMPY, robot, [z[..., i] for i in range(robot.dof)])
    rows = []
    if arrays is not None:
        blocks = _kind_blocks(robot, arrays, centres, face_smoothing, NUMPY)
        if blocks:
            pairs = np.concatenate(blocks, axis=-1)
            rows.append(pairs.reshape(pairs.shape[:-2] + (-1,)))
    if include_self and robot.has_self_pairs:
        rows.append(_self_block(robot, centres, NUMPY))
    if not rows:
        return np.zeros(z.shape[:-1] + (0,))
    return np.concatenate(rows, axis=-1)


class PairDistances:
    """Float64 numpy distances of every pair of the exact stage, with a broad phase.

    ``near(z)`` returns (…, N·P + M) signed distances (m) for bending-vector
    configurations z (…, 3n): the N·P obstacle pairs body-major (the order of
    ``pair_distances_z`` flattened), then, with n ≥ 3 segments, the M self pairs
    (``self_pairs``). A pair whose lower bound from the part's bounding ball is at least
    ``margin`` gets that lower bound (≥ margin) instead of its distance: the values are
    exact below ``margin`` and never above the exact ones, which is all that choosing the
    pairs near a configuration and measuring a shortfall below δ ≤ margin need.

    Args:
        robot: the robot.
        scene: the obstacles, or None (self pairs only).
        face_smoothing: metres, μ of the convex parts' face-plane max (a lower bound).
    """

    def __init__(self, robot: Robot, scene: Scene | None, face_smoothing: float = 0.0) -> None:
        from .scene import bounding_sphere

        self.robot = robot
        self.face_smoothing = float(face_smoothing)
        self.arrays = scene_arrays(scene, as_numpy=True) if scene is not None else None
        parts = scene.parts if scene is not None else ()
        balls = [bounding_sphere(p) for p in parts]
        self._ball_centres = np.array([c for c, _ in balls], dtype=float).reshape(-1, 3)
        self._ball_radii = np.array([r for _, r in balls], dtype=float)
        a = self.arrays
        counts = ([a.sphere_radius.shape[0], a.box_center.shape[0], a.capsule_radius.shape[0],
                   a.cylinder_radius.shape[0], a.convex_planes.shape[0]] if a is not None
                  else [0] * 5)
        self._kind_starts = np.cumsum([0] + counts)
        self._self_pairs = self_pairs(robot) if robot.has_self_pairs else np.zeros((0, 2), int)

    @property
    def size(self) -> int:
        """N·P + M: pairs per configuration."""
        return (self.robot.n_points + 1) * len(self._ball_radii) + len(self._self_pairs)

    def centres(self, z: Any) -> np.ndarray:
        """(…, N, 3) body-sphere centres (m) of z (…, 3n), float64."""
        z = np.asarray(z, dtype=np.float64)
        return _body_centres(NUMPY, self.robot, [z[..., i] for i in range(self.robot.dof)])

    def near(self, z: Any, margin: float, centres: np.ndarray | None = None) -> np.ndarray:
        """The (…, N·P + M) distances of z (…, 3n), exact where below ``margin`` (m);
        ``centres`` may pass ``self.centres(z)`` when the caller has them."""
        centres = self.centres(z) if centres is None else np.asarray(centres, dtype=np.float64)
        batch = centres.shape[:-2]
        flat = centres.reshape(-1, centres.shape[-2], 3)
        r = self.robot.backbone_radius
        rows = []
        if len(self._ball_radii):
            gap = flat[:, :, None, :] - self._ball_centres[None, None]
            bound = np.sqrt(np.einsum("bnpk,bnpk->bnp", gap, gap)) - self._ball_radii - r
            exact = np.argwhere(bound < margin)
            bound[tuple(exact.T)] = self._exact(flat[exact[:, 0], exact[:, 1]], exact[:, 2])
            rows.append(bound.reshape(len(flat), -1))
        if len(self._self_pairs):
            rows.append(_self_block(self.robot, flat, NUMPY, self._self_pairs))
        out = (np.concatenate(rows, axis=-1) if rows else np.zeros((len(flat), 0)))
        return out.reshape(batch + (out.shape[-1],))

    def _exact(self, centres: np.ndarray, parts: np.ndarray) -> np.ndarray:
        """Signed distances (m) of K body spheres (K, 3) to K parts (flat indices)."""
        a, r, out = self.arrays, self.robot.backbone_radius, np.empty(len(parts))
        starts = self._kind_starts
        for kind in range(5):
            mine = np.flatnonzero((parts >= starts[kind]) & (parts < starts[kind + 1]))
            if not len(mine):
                continue
            j = parts[mine] - starts[kind]
            c = _cols(centres[mine])
            if kind == 0:
                d = dist.sphere_to_sphere(NUMPY, c, r, _cols(a.sphere_center[j]),
                                          a.sphere_radius[j])
            elif kind == 1:
                d = dist.sphere_to_box(NUMPY, c, r, _cols(a.box_center[j]),
                                       _rot_entries(a.box_rotation[j]), _cols(a.box_half_size[j]))
            elif kind == 2:
                d = dist.sphere_to_capsule(NUMPY, c, r, _cols(a.capsule_a[j]),
                                           _cols(a.capsule_b[j]), a.capsule_radius[j])
            elif kind == 3:
                d = dist.sphere_to_cylinder(NUMPY, c, r, _cols(a.cylinder_center[j]),
                                            _rot_entries(a.cylinder_rotation[j]),
                                            a.cylinder_radius[j], a.cylinder_half_length[j])
            else:
                planes = a.convex_planes[j]
                d = dist.sphere_to_convex(NUMPY, tuple(x[:, None] for x in c), r, _cols(planes),
                                          planes.shape[1], self.face_smoothing)
            out[mine] = d
        return out


# ================================================================ CasADi

@dataclass(frozen=True)
class CasadiClearance:
    """Per-pair clearance constraints for an NLP, restricted to pairs near a configuration.

    ``function`` maps q (3n) and ``function_z`` maps z (3n) to the (K,) signed distances
    (m) of ``obstacle_pairs`` (body sphere, part index) followed by ``self_pairs`` (body
    sphere, body sphere). ``names`` gives the obstacle name (or "self") of each output.
    """

    function: ca.Function
    function_z: ca.Function
    obstacle_pairs: np.ndarray
    self_pairs: np.ndarray
    names: tuple[str, ...]
    face_smoothing: float

    @property
    def size(self) -> int:
        return len(self.names)


def casadi_clearance(robot: Robot, scene: Scene, near_q: Any, margin: float = 0.5,
                     face_smoothing: float = 0.0, include_self: bool = True,
                     arrays: SceneArrays | None = None) -> CasadiClearance:
    """CasADi functions of the pair distances that are below ``margin`` (m) at ``near_q``
    (3n; rad, rad, m), so an Ipopt problem around ``near_q`` gets one small constraint per
    relevant pair. Built from the same formulas as the JAX side (same values)."""
    arrays_np = arrays if arrays is not None else scene_arrays(scene, as_numpy=True)
    arrays_np = SceneArrays(*(np.asarray(a, dtype=float) for a in arrays_np))
    q0 = np.asarray(near_q, dtype=np.float64)
    # The selection only compares with a margin, so JAX's default precision is enough.
    near = np.asarray(pair_distances(robot, SceneArrays(*map(jnp.asarray, arrays_np)),
                                     jnp.asarray(q0), face_smoothing))
    near_self = (np.asarray(self_distances(robot, jnp.asarray(q0)))
                 if include_self and robot.has_self_pairs else np.zeros(0))
    obstacle_pairs = np.argwhere(near < margin).reshape(-1, 2)
    all_self = self_pairs(robot)
    chosen_self = all_self[near_self < margin] if len(near_self) else all_self[:0]
    part_owner = scene.part_obstacle
    names = tuple([scene.obstacles[part_owner[j]].name for _, j in obstacle_pairs]
                  + ["self"] * len(chosen_self))

    q = ca.SX.sym("q", robot.dof)
    z = ca.SX.sym("z", robot.dof)

    def outputs(z_entries: list[Any]) -> ca.SX:
        centres = _body_centres(CASADI, robot, z_entries)
        values = [_casadi_pair(robot, arrays_np, centres, int(i), int(j), face_smoothing)
                  for i, j in obstacle_pairs]
        r = robot.backbone_radius
        for i, j in chosen_self:
            ci = tuple(centres[int(i), k] for k in range(3))
            cj = tuple(centres[int(j), k] for k in range(3))
            values.append(dist.sphere_to_sphere(CASADI, ci, r, cj, r))
        return ca.vertcat(*values) if values else ca.SX(0, 1)

    fq = ca.Function("clearance_pairs_q", [q], [outputs(model_q_to_z(CASADI, robot, q))],
                     ["q"], ["distances"])
    fz = ca.Function("clearance_pairs_z", [z], [outputs([z[i] for i in range(robot.dof)])],
                     ["z"], ["distances"])
    return CasadiClearance(fq, fz, obstacle_pairs, chosen_self, names, face_smoothing)


def _casadi_pair(robot: Robot, a: SceneArrays, centres: ca.SX, body: int, part: int,
                 smoothing: float) -> ca.SX:
    """The distance of body sphere ``body`` to part ``part`` (flat ``scene.parts`` index)."""
    c = tuple(centres[body, k] for k in range(3))
    r = robot.backbone_radius
    counts = [a.sphere_radius.shape[0], a.box_center.shape[0], a.capsule_radius.shape[0],
              a.cylinder_radius.shape[0], a.convex_planes.shape[0]]
    kind, j = 0, part
    while j >= counts[kind]:
        j -= counts[kind]
        kind += 1

    def f(x: np.ndarray) -> tuple[float, ...]:
        return tuple(float(v) for v in np.ravel(x))

    if kind == 0:
        return dist.sphere_to_sphere(CASADI, c, r, f(a.sphere_center[j]), float(a.sphere_radius[j]))
    if kind == 1:
        return dist.sphere_to_box(CASADI, c, r, f(a.box_center[j]), f(a.box_rotation[j]),
                                  f(a.box_half_size[j]))
    if kind == 2:
        return dist.sphere_to_capsule(CASADI, c, r, f(a.capsule_a[j]), f(a.capsule_b[j]),
                                      float(a.capsule_radius[j]))
    if kind == 3:
        return dist.sphere_to_cylinder(CASADI, c, r, f(a.cylinder_center[j]),
                                       f(a.cylinder_rotation[j]), float(a.cylinder_radius[j]),
                                       float(a.cylinder_half_length[j]))
    planes = tuple(ca.DM(a.convex_planes[j][:, k]) for k in range(4))
    return dist.sphere_to_convex(CASADI, c, r, planes, a.convex_planes.shape[1], smoothing)
