"""The independent collision verdict: closed forms in float64 numpy, and python-fcl.

The robot's body is a chain of capsules of radius ``backbone_radius`` between
consecutive points of base, backbone point 1, …, backbone point n·k (float64
kinematics); piece i joins chain points i and i + 1 and belongs to segment i // k.
Each piece is measured against every obstacle part and against the pieces of
segments at least two apart (self-collision), as signed distances (metres; negative =
penetration depth). This verdict, not the optimizer's clearance, decides whether a
configuration is collision-free.

What is computed how, for a whole batch of configurations at once:

- Sphere parts: closed form (distance from the centre to the piece's segment minus
  both radii), vectorised over (configuration, piece, sphere). Exact, and it avoids
  fcl's penetration query (EPA), which was seen to never return for a sphere centre
  on a capsule's axis.
- Self-collision: closed form (segment–segment distance minus 2r; negative when the
  capsules overlap), vectorised over (configuration, far pair), one broadcast block per
  pair of segments; the segment distance only for the pairs whose bound can hold the
  minimum. A batch runs in chunks of ``_BATCH_ELEMENTS`` entries of its largest array
  (configuration × piece × part, or configuration × far pair), so its Python is per
  chunk, not per configuration.
- Box, capsule, cylinder and mesh (convex) parts: python-fcl (``fcl_distance``), per
  configuration. Lower bounds are computed vectorised for the batch: the part's
  bounding sphere against the piece's segment, tightened by the part's face planes
  (boxes, convex parts) or by the segment–segment distance to its axis (capsules,
  cylinders). Each configuration's search starts from its best sphere-part distance
  and visits pairs in order of their bound, stopping once no pair can beat the best,
  so the minimum is exact while most pairs are never handed to fcl. A piece's fcl
  capsule is built (by ``capsule_object``) only when a pair needs it.

Motions (the configurations of trajectories and paths) are judged by
``world._motion_check``, which finds their minima and collisions with fewer fcl queries.

fcl stays for those parts because their closed forms (segment–box, segment–cylinder,
segment–polytope) are not written here; the closed forms above agree with fcl's
separated-pair distances to ~1e-15 m. fcl's capsule–capsule penetration depth (EPA),
used for self-collision before, was measured off by up to 7e-7 m against the closed
form and a brute-force check. fcl's GJK answers capsule–convex distances only to ~1e-5 m
and reacts to 1e-16 changes of its inputs, so the capsules handed to it are built
exactly as before: those answers are bit for bit the ones the per-configuration
version got.

The scene's fcl objects and arrays are built once per ``Scene`` and reused. The
previous version (per configuration: fcl capsules, pair loops in Python) spent ~97 %
of its time in Python; on 600 random tdcr3 configurations (median of 5, a shared
2-core machine, so ±40 %) the time went from 0.17–0.29 s to 0.010 s in
``follow_sine`` (two spheres), 0.2–0.35 s to 0.02–0.03 s in ``lattice`` (27 spheres)
and 0.6–1.0 s to 0.10–0.17 s in ``shelf`` (57 convex parts; 2,400 fcl queries instead
of 33,000).

The fcl objects (parts, capsules, a scene's arrays, ``fcl_distance``) are built in
``world._fcl_objects``, the point, segment and capsule closed forms are
``world._segment_distances``; this module is the verdict over them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import fcl
import numpy as np

from ..model._ops import NUMPY
from ..model.kinematics import model_backbone, model_q_to_z
from ..model.robot import Robot
from ..runtime import cached
from ._fcl_objects import Capsules, FclScene, fcl_scene
from ._fcl_objects import capsule_object as capsule_object
from ._fcl_objects import fcl_distance as fcl_distance
from ._fcl_objects import fcl_object as fcl_object
from ._segment_distances import Xyz, dot, point_segment, segment_segment, sub, xyz
from ._segment_distances import capsule_capsule_distance as capsule_capsule_distance
from ._segment_distances import capsule_sphere_distance as capsule_sphere_distance
from ._segment_distances import point_segment_distance as point_segment_distance
from ._segment_distances import segment_distance as segment_distance
from .scene import Scene


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


# ================================================================ the verdict

_BATCH_ELEMENTS = 1 << 17   # (configuration, piece, part) entries per vectorised chunk


@cached(maxsize=32)
def _far_pairs(pieces: int, per_segment: int) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs i < j of pieces whose segments are at least two apart."""
    segment = np.arange(pieces) // per_segment    # piece i joins chain points i and i + 1
    i, j = np.nonzero(np.triu(np.abs(segment[:, None] - segment[None, :]) >= 2, 1))
    return i, j


def _tighten(r: float, fscene: FclScene, sa: np.ndarray, sb: np.ndarray, qi: np.ndarray,
             low: np.ndarray, below: float | np.ndarray = np.inf) -> np.ndarray:
    """Tighter lower bounds than ``low`` (N,) on the signed distance between pieces sa–sb
    (N, 3) and fcl parts qi (N,) (indices into the scene's non-sphere parts). A pair whose
    bound reaches ``below`` (scalar or (N,)) by the cheap axis-aligned box keeps that
    bound, not tightened further: the callers drop it."""
    # The part's axis-aligned box: the piece's coordinate ranges miss it by at least the
    # largest gap along an axis.
    gaps = np.maximum(fscene.box_lower.take(qi, axis=0) - np.maximum(sa, sb),
                      np.minimum(sa, sb) - fscene.box_upper.take(qi, axis=0))
    low = np.maximum(low, gaps.max(axis=1) - r)
    open_ = np.flatnonzero(low < below)
    if len(open_) < len(low):
        low[open_] = _tighten_more(r, fscene, sa[open_], sb[open_], qi[open_], low[open_],
                                   gaps[open_])
        return low
    return _tighten_more(r, fscene, sa, sb, qi, low, gaps)


def _tighten_more(r: float, fscene: FclScene, sa: np.ndarray, sb: np.ndarray,
                  qi: np.ndarray, low: np.ndarray, gaps: np.ndarray) -> np.ndarray:
    """``_tighten``'s bounds past the axis-aligned box (``gaps`` (N, 3): the box's gaps
    along each axis, from ``_tighten``): the part's bounding sphere against the piece's
    segment, face planes, the axis of capsules and cylinders."""
    sa_, sb_ = xyz(sa), xyz(sb)
    u = sub(sb_, sa_)
    # Separated axis-aligned boxes (the piece's, the part's) are apart by their gaps along
    # all three axes together (where they overlap, ``_tighten``'s largest gap stays).
    gap = np.maximum(gaps, 0.0)
    apart = np.sqrt(np.einsum("ij,ij->i", gap, gap))
    low = np.where(apart > 0.0, np.maximum(low, apart - r), low)
    # The part's bounding sphere against the piece's segment.
    centre = fscene.other_centres.take(qi, axis=0)
    low = np.maximum(low, point_segment(xyz(centre), sa_, u, dot(u, u))
                     - r - fscene.other_radii[qi])
    # Face planes n·x ≤ o: the capsule lies beyond one by min(n·a, n·b) − o − r.
    n = tuple(c.take(qi, axis=0) for c in fscene.normals)
    beyond = np.minimum(dot(n, tuple(c[:, None] for c in sa_)),
                        dot(n, tuple(c[:, None] for c in sb_))) - fscene.offsets.take(qi, axis=0)
    low = np.maximum(low, beyond.max(axis=1) - r)
    # Capsules and cylinders lie in the capsule around their axis.
    axis = fscene.has_axis[qi]
    if axis.any():
        q = qi[axis]
        low[axis] = np.maximum(low[axis], capsule_capsule_distance(
            sa[axis], sb[axis], r, fscene.axis_a[q], fscene.axis_b[q], fscene.axis_radius[q]))
    return low


_SEED_CANDIDATES = 8   # pairs per configuration whose tight bound picks the first fcl query
_FEW_CONFIGURATIONS = 2  # batches up to this size skip the seed and the tight bounds


def _loose_bounds(r: float, fscene: FclScene, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(B, m·parts) lower bounds on the distance between pieces a–b (B, m, 3) and the
    fcl parts: each part's bounding sphere against the piece's. |m − c|² comes from a
    matrix product, lowered by far more than its rounding error so that it stays a true
    lower bound."""
    count, pieces = a.shape[:2]
    mid = 0.5 * (a + b).reshape(-1, 3)
    half = 0.5 * (b - a).reshape(-1, 3)
    reach = np.sqrt(np.einsum("ij,ij->i", half, half)) + r
    mm, cc = np.einsum("ij,ij->i", mid, mid), fscene.other_centre_norm2
    square = mm[:, None] + cc[None] - 2.0 * (mid @ fscene.other_centres.T)
    square -= 1e-12 * (mm[:, None] + cc[None] + 1.0)
    return (np.sqrt(np.maximum(square, 0.0)) - reach[:, None]
            - fscene.other_radii).reshape(count, pieces * len(fscene.other_index))


def _measure_seeds(r: float, fscene: FclScene, a: np.ndarray, b: np.ndarray,
                   lower: np.ndarray, obstacle: np.ndarray,
                   part: np.ndarray) -> dict[int, fcl.CollisionObject]:
    """``_fcl_search``'s seeds: where the best sphere-part distance (or none) leaves pairs
    open, measure first the pair of smallest tight bound among the few of smallest loose
    bound, so that the candidates after it are only those that can beat it. Lowers
    ``obstacle``, ``part`` in place and marks the measured pairs' ``lower`` inf; returns
    their capsules by configuration · pieces + piece."""
    pieces, parts = a.shape[1], len(fscene.other_index)
    width = min(_SEED_CANDIDATES, pieces * parts)
    near = np.argpartition(lower, width - 1, axis=1)[:, :width]
    seed = np.flatnonzero(np.take_along_axis(lower, near, axis=1).min(axis=1) < obstacle)
    seeded: dict[int, fcl.CollisionObject] = {}
    if len(seed):
        rep, flat = np.repeat(seed, width), near[seed].ravel()
        pi, qi = np.divmod(flat, parts)
        tight = _tighten(r, fscene, a[rep, pi], b[rep, pi], qi, lower[rep, flat])
        tight = tight.reshape(-1, width)
        first = near[seed, np.argmin(tight, axis=1)]
        piece, which = np.divmod(first, parts)
        built = Capsules(r, a[seed, piece], b[seed, piece])
        for row, (k, i, q) in enumerate(zip(seed.tolist(), piece.tolist(),
                                            fscene.other_index[which].tolist(), strict=True)):
            seeded[k * pieces + i] = built[row]
            d = fcl_distance(built[row], fscene.objects[q])
            if d < obstacle[k]:
                obstacle[k], part[k] = d, q
        lower[seed, first] = np.inf            # measured
    return seeded


def _fcl_search(r: float, fscene: FclScene, a: np.ndarray, b: np.ndarray,
                obstacle: np.ndarray, part: np.ndarray) -> None:
    """Lower ``obstacle`` (B,) and set ``part`` (B,) in place by the fcl parts, for pieces
    a–b (B, m, 3): per configuration from its best distance so far, pairs in order of a
    lower bound, until no pair can beat the best."""
    count, pieces = a.shape[:2]
    parts = len(fscene.other_index)
    objects, part_of = fscene.objects, fscene.other_index
    lower = _loose_bounds(r, fscene, a, b)
    # A few configurations (one live update's backbone) go by the loose bounds alone: the
    # seed and the tighter bounds cost more than the fcl queries they save there (4
    # queries either way against the clutter's boxes; check_chains 0.50 → 0.28 ms).
    few = count <= _FEW_CONFIGURATIONS
    seeded = {} if few else _measure_seeds(r, fscene, a, b, lower, obstacle, part)
    bi, flat = np.nonzero(lower < obstacle[:, None])
    if not len(bi):
        return
    pi, qi = np.divmod(flat, parts)
    low = (lower[bi, flat] if few else
           _tighten(r, fscene, a[bi, pi], b[bi, pi], qi, lower[bi, flat], obstacle[bi]))
    order = np.flatnonzero(low < obstacle[bi])
    if not len(order):
        return
    order = order[np.lexsort((low[order], bi[order]))]   # by configuration, then bound
    bi, pi, low = bi[order], pi[order], low[order]
    # Capsules of the pieces still needed, at most one per (configuration, piece).
    unique, slot = np.unique(bi * pieces + pi, return_inverse=True)
    capsules = Capsules(r, a.reshape(-1, 3)[unique], b.reshape(-1, 3)[unique])
    for i, x in enumerate(unique.tolist()):
        if x in seeded:
            capsules.built[i] = seeded[x]
    rows = np.r_[0, np.flatnonzero(np.diff(bi)) + 1, len(bi)].tolist()
    bi_list, slot_list, low_list = bi.tolist(), slot.tolist(), low.tolist()
    q_list = part_of[qi[order]].tolist()
    for start, stop in zip(rows[:-1], rows[1:], strict=True):
        k = bi_list[start]
        best, best_part = float(obstacle[k]), int(part[k])
        for row in range(start, stop):
            if low_list[row] >= best:
                break
            d = fcl_distance(capsules[slot_list[row]], objects[q_list[row]])
            if d < best:
                best, best_part = d, q_list[row]
        obstacle[k], part[k] = best, best_part


def _self_distance(r: float, a: Xyz, b: Xyz, per_segment: int,
                   motion: np.ndarray | None = None) -> np.ndarray:
    """Smallest signed distance (B,) between the capsules of pieces of segments at least
    two apart (``_far_pairs``), for pieces running a–b (coordinates (B, m) each), k =
    ``per_segment`` pieces per segment. Exact: a pair whose bound (mid-point gap minus
    both half lengths) exceeds the smallest mid-point gap (the distance of a real pair of
    points) cannot hold the minimum; only the others get the segment distance. Each pair
    of segments is one (B, k, k) block, by broadcasting rather than gathering pairs.

    ``motion`` (B,): the configurations' motions, of which only the smallest distance and
    the collisions count. A pair is then measured only if it can also hold its motion's
    minimum (bound below the motion's smallest mid-point gap) or collide; a configuration
    none of whose pairs is measured gets +inf, its distance being above both (on the
    planner's shelf motions, 2.8 pairs per configuration instead of 9.6)."""
    mid = tuple(0.5 * (p + q) for p, q in zip(a, b, strict=True))
    u = sub(b, a)
    half = 0.5 * np.sqrt(dot(u, u))
    count, pieces = half.shape
    segments = pieces // per_segment
    blocks = [(s, t) for s in range(segments) for t in range(s + 2, segments)]

    def of(x: np.ndarray, segment: int) -> np.ndarray:
        return x[:, segment * per_segment:(segment + 1) * per_segment]

    gaps = []
    for s, t in blocks:
        between = sub(tuple(of(c, s)[:, :, None] for c in mid),
                      tuple(of(c, t)[:, None, :] for c in mid))
        gaps.append(np.sqrt(dot(between, between)))
    upper = np.minimum.reduce([gap.min(axis=(1, 2)) for gap in gaps])
    if motion is not None:
        least = np.full(int(motion.max(initial=0)) + 1, np.inf)
        np.minimum.at(least, motion, upper)
        upper = np.minimum(upper, np.maximum(least[motion], 2.0 * r))
    upper = upper[:, None, None]
    found = [np.nonzero(gap - of(half, s)[:, :, None] - of(half, t)[:, None, :]
                        <= upper + 1e-9) for (s, t), gap in zip(blocks, gaps, strict=True)]
    rows = np.concatenate([row for row, _, _ in found])
    pi = np.concatenate([i + s * per_segment for (s, _), (_, i, _) in zip(blocks, found,
                                                                           strict=True)])
    pj = np.concatenate([j + t * per_segment for (_, t), (_, _, j) in zip(blocks, found,
                                                                           strict=True)])
    d = segment_segment(tuple(c[rows, pi] for c in a), tuple(c[rows, pi] for c in b),
                        tuple(c[rows, pj] for c in a), tuple(c[rows, pj] for c in b))
    own = np.full(count, np.inf)
    np.minimum.at(own, rows, d)
    return own - 2.0 * r


def _sphere_distances(r: float, fscene: FclScene, a: Xyz,
                      b: Xyz) -> tuple[np.ndarray, np.ndarray]:
    """Distance (B,) from the pieces a–b (coordinates (B, m) each) to the nearest sphere
    part of the scene, closed form, and that part's index (B,)."""
    count = len(a[0])
    u = sub(b, a)
    centre = tuple(fscene.sphere_centres[:, k] for k in range(3))
    d = (point_segment(centre, tuple(c[:, :, None] for c in a),
                       tuple(c[:, :, None] for c in u), dot(u, u)[:, :, None])
         - r - fscene.sphere_radii).reshape(count, -1)
    nearest = np.argmin(d, axis=1)
    return (d[np.arange(count), nearest],
            fscene.sphere_index[nearest % len(fscene.sphere_index)])


def _own_distances(robot: Robot, chains: np.ndarray, per_segment: int,
                   motion: np.ndarray | None = None) -> np.ndarray:
    """The self distance (B,) of body chains (B, 1 + n·k, 3) of k = ``per_segment``
    pieces per segment (``_self_distance``, of motions ``motion`` (B,) if given; +inf
    where not checked), in chunks of ``_BATCH_ELEMENTS`` far pairs."""
    pairs = len(_far_pairs(chains.shape[1] - 1, per_segment)[0])
    if not pairs or not robot.self_collision:
        return np.full(len(chains), np.inf)
    step = max(1, _BATCH_ELEMENTS // pairs)
    out = [_self_distance(robot.backbone_radius,
                          *(tuple(np.ascontiguousarray(c[..., k]) for k in range(3))
                            for c in (chains[s:s + step, :-1], chains[s:s + step, 1:])),
                          per_segment, None if motion is None else motion[s:s + step])
           for s in range(0, len(chains), step)]
    return np.concatenate(out) if out else np.zeros(0)


def _verdicts(robot: Robot, fscene: FclScene, chains: np.ndarray,
              per_segment: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Obstacle distance (B,), its part index (B,; −1: none) and self distance (B,) for
    body chains (B, 1 + n·k, 3) of k pieces per segment, every entry exact."""
    r = robot.backbone_radius
    count = len(chains)
    obstacle = np.full(count, np.inf)
    part = np.full(count, -1, dtype=np.int64)
    if not count:
        return obstacle, part, np.full(count, np.inf)
    x = tuple(np.ascontiguousarray(chains[..., k]) for k in range(3))
    a, b = tuple(c[:, :-1] for c in x), tuple(c[:, 1:] for c in x)
    if len(fscene.sphere_index):
        obstacle, part = _sphere_distances(r, fscene, a, b)
    if len(fscene.other_index):
        _fcl_search(r, fscene, chains[:, :-1], chains[:, 1:], obstacle, part)
    return obstacle, part, _own_distances(robot, chains, per_segment)


def check(robot: Robot, scene: Scene | None, q: Any) -> CheckResult:
    """The verdict for one configuration q (3n; rad, rad, m); ``scene`` None: the robot's
    self-collision only."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (robot.dof,):
        raise ValueError(f"check takes one configuration of {robot.dof} entries, got {q.shape}")
    many = check_many(robot, scene, q[None])
    return CheckResult(collision=bool(many.collision[0]),
                       min_distance=float(many.min_distance[0]), closest=many.closest[0],
                       self_collision=bool(many.self_collision[0]),
                       obstacle_distance=float(many.obstacle_distance[0]),
                       self_distance=float(many.self_distance[0]))


def check_many(robot: Robot, scene: Scene | None, qs: Any) -> CheckManyResult:
    """The verdicts for a batch of configurations qs (B, 3n); ``scene`` None: the robot's
    self-collision only (``robot.self_collision`` false: none)."""
    qs = np.asarray(qs, dtype=np.float64).reshape(-1, robot.dof)
    return check_chains(robot, scene, body_chain(robot, qs), robot.points_per_segment)


def check_chains(robot: Robot, scene: Scene | None, chains: Any,
                 pieces_per_segment: int) -> CheckManyResult:
    """The verdicts for backbone polylines of any shape model (e.g. Cosserat statics):
    ``chains`` (B, 1 + n·k, 3) from the base to the tip in metres, the robot's body a
    capsule of ``robot.backbone_radius`` around every piece, k pieces per segment (so
    that pieces of segments at least two apart are checked against each other)."""
    chains = np.asarray(chains, dtype=np.float64)
    if chains.ndim != 3 or chains.shape[2] != 3 or (chains.shape[1] - 1) % pieces_per_segment:
        raise ValueError(f"chains must be (B, 1 + n·{pieces_per_segment}, 3), got "
                         f"{chains.shape}")
    fscene = fcl_scene(scene)
    pieces = chains.shape[1] - 1
    # (configuration, piece, part) entries of the obstacles, (configuration, far pair) of
    # the self-distance: sized by the piece count of both, chunks were 30× too small
    # without a scene (43 tdcr3 configurations, the Python of each chunk most of the time).
    width = max(pieces * len(fscene.objects), len(_far_pairs(pieces, pieces_per_segment)[0]), 1)
    step = max(1, _BATCH_ELEMENTS // width)
    parts = [_verdicts(robot, fscene, chains[s:s + step], pieces_per_segment)
             for s in range(0, len(chains), step)]
    obstacle, part, own = (np.concatenate([p[k] for p in parts]) if parts else
                           np.zeros(0, dtype=np.int64 if k == 1 else float) for k in range(3))
    min_distance = np.minimum(obstacle, own)
    names = np.array([*fscene.names, ""], dtype=object)      # part −1 (none): ""
    closest = names[part]
    closest[own < obstacle] = "self"
    return CheckManyResult(collision=min_distance < 0.0, min_distance=min_distance,
                           self_collision=own < 0.0, obstacle_distance=obstacle,
                           self_distance=own, closest=tuple(closest.tolist()))
