"""The vectorised verdict: closed forms against python-fcl, and ``check_many`` against a
plain per-configuration reference (every pair measured, no pruning)."""

import importlib

import fcl
import numpy as np
import pytest

from cr_nlp.model import Robot
from cr_nlp.world import Scene, SpherePart, load_scene
from cr_nlp.world.check import (
    body_chain,
    capsule_capsule_distance,
    capsule_object,
    capsule_sphere_distance,
    check,
    check_many,
    fcl_distance,
    fcl_object,
    point_segment_distance,
    segment_distance,
)

from ..conftest import random_q

check_module = importlib.import_module("cr_nlp.world.check")
fcl_objects = importlib.import_module("cr_nlp.world._fcl_objects")


# ---------------------------------------------------------------- closed forms

def random_segment_pairs(rng: np.random.Generator) -> list[tuple]:
    """(p0, p1, q0, q1) of general, parallel, anti-parallel, collinear end-to-end,
    crossing-direction, and zero-length segments."""
    pairs = []
    for _ in range(150):
        p0, p1, q0, q1 = rng.normal(size=(4, 3))
        pairs.append((p0, p1, q0, q1))
    for _ in range(60):                                   # parallel and anti-parallel
        p0, direction, offset = rng.normal(size=(3, 3))
        length, shift = rng.uniform(0.05, 1.5), rng.uniform(-2.0, 2.0)
        p1 = p0 + length * direction
        q0 = p0 + offset + shift * direction
        q1 = q0 + rng.choice([-1.0, 1.0]) * rng.uniform(0.05, 1.5) * direction
        pairs.append((p0, p1, q0, q1))
    for _ in range(40):                                   # collinear, end to end
        p0, direction = rng.normal(size=(2, 3))
        direction /= np.linalg.norm(direction)
        p1 = p0 + rng.uniform(0.1, 1.0) * direction
        q0 = p1 + rng.uniform(0.2, 0.6) * direction
        pairs.append((p0, p1, q0, q0 + rng.uniform(0.1, 1.0) * direction))
    for _ in range(40):                                   # end near the other's middle
        p0, p1, side = rng.normal(size=(3, 3))
        side -= (side @ (p1 - p0)) / ((p1 - p0) @ (p1 - p0)) * (p1 - p0)
        q0 = 0.5 * (p0 + p1) + 0.4 * side / np.linalg.norm(side)
        pairs.append((p0, p1, q0, q0 + rng.uniform(0.1, 1.0) * side))
    for _ in range(40):                                   # zero-length ends
        p0, q0, q1 = rng.normal(size=(3, 3))
        pairs.append((p0, p0.copy(), q0, q1) if rng.random() < 0.5 else (p0, p0.copy(), q0,
                                                                          q0.copy()))
    return pairs


def test_segment_distance_against_fcl_capsules() -> None:
    rng = np.random.default_rng(11)
    pairs = random_segment_pairs(rng)
    p0, p1, q0, q1 = (np.array(x) for x in zip(*pairs, strict=True))
    r0, r1 = rng.uniform(0.01, 0.1, (2, len(pairs)))
    ours = capsule_capsule_distance(p0, p1, r0[:, None][:, 0], q0, q1, r1)
    assert ours.shape == (len(pairs),)
    compared = 0
    for k in range(len(pairs)):
        if ours[k] < 1e-4:      # fcl's separated-pair query is the accurate one
            continue
        truth = fcl_distance(capsule_object(p0[k], p1[k], r0[k]),
                             capsule_object(q0[k], q1[k], r1[k]))
        assert abs(ours[k] - truth) < 1e-9, (k, ours[k], truth)
        compared += 1
    assert compared > 300
    # Symmetric, and a lower envelope of sampled point pairs that the samples approach.
    assert np.allclose(segment_distance(q0, q1, p0, p1), segment_distance(p0, p1, q0, q1),
                       atol=1e-13, rtol=0)
    s = np.linspace(0.0, 1.0, 401)
    for k in range(0, len(pairs), 7):
        a = p0[k] + s[:, None] * (p1[k] - p0[k])
        b = q0[k] + s[:, None] * (q1[k] - q0[k])
        brute = np.linalg.norm(a[:, None] - b[None], axis=-1).min()
        d = segment_distance(p0[k], p1[k], q0[k], q1[k])
        assert d <= brute + 1e-12 and brute - d < 1e-2


def test_segment_distance_special_cases() -> None:
    z = np.zeros(3)
    ex, ey, ez = np.eye(3)
    # Parallel, overlapping: the gap between the lines.
    assert segment_distance(z, ex, ey, ey + 2 * ex) == pytest.approx(1.0, abs=1e-15)
    # Collinear, end to end with a gap of 0.5.
    assert segment_distance(z, ex, 1.5 * ex, 3 * ex) == pytest.approx(0.5, abs=1e-15)
    # Touching ends, and crossing: zero.
    assert segment_distance(z, ex, ex, ex + ey) == 0.0
    assert segment_distance(-ex, ex, -ey, ey) == 0.0
    # Skew lines whose closest points are inside both segments.
    assert segment_distance(-ex, ex, ez - ey, ez + ey) == pytest.approx(1.0, abs=1e-15)
    # Zero-length: point to segment, and point to point.
    assert segment_distance(ez, ez, -ex, ex) == pytest.approx(1.0, abs=1e-15)
    assert segment_distance(ez, ez, ey, ey) == pytest.approx(np.sqrt(2.0), abs=1e-15)
    # Capsules: penetration depth is 2r minus the segment distance.
    assert capsule_capsule_distance(-ex, ex, 0.3, ez - ey, ez + ey, 0.2) == pytest.approx(0.5)
    assert capsule_capsule_distance(-ex, ex, 0.3, 0.1 * ez - ey, 0.1 * ez + ey, 0.2) \
        == pytest.approx(-0.4)


def test_point_segment_distance_matches_the_scalar_closed_form() -> None:
    rng = np.random.default_rng(4)
    a, b, c = rng.normal(size=(3, 200, 3))
    b[:20] = a[:20]                                           # zero-length pieces
    ours = point_segment_distance(c, a, b) - 0.1 - 0.2
    scalar = [capsule_sphere_distance(a[k], b[k], 0.1, c[k], 0.2) for k in range(200)]
    assert np.max(np.abs(ours - scalar)) < 1e-14


# ---------------------------------------------------------------- check_many vs reference

def reference(robot: Robot, scene: Scene, q: np.ndarray) -> dict:
    """Every pair measured: spheres by the closed form, other parts and self pairs by fcl."""
    chain = body_chain(robot, q)
    a, b = chain[:-1], chain[1:]
    r = robot.backbone_radius
    capsules = [capsule_object(a[i], b[i], r) for i in range(len(a))]
    names = [scene.obstacles[i].name for i in scene.part_obstacle]
    obstacle, closest = np.inf, ""
    for j, part in enumerate(scene.parts):
        obj = None if isinstance(part, SpherePart) else fcl_object(part)
        for i in range(len(a)):
            d = (capsule_sphere_distance(a[i], b[i], r, part.center, part.radius) if obj is None
                 else fcl_distance(capsules[i], obj))
            if d < obstacle:
                obstacle, closest = d, names[j]
    own = np.inf
    segment = np.arange(len(a)) // robot.points_per_segment
    for i in range(len(a)):
        for j in range(i + 1, len(a)):
            if segment[j] - segment[i] >= 2:
                own = min(own, fcl_distance(capsules[i], capsules[j]))
    if own < obstacle:
        closest = "self"
    return {"obstacle_distance": obstacle, "self_distance": own,
            "min_distance": min(obstacle, own), "closest": closest}


@pytest.mark.parametrize("robot_name,scene_name,count", [
    ("tdcr3", "follow_square", 40), ("tdcr3", "lattice", 30), ("tdcr3", "shelf", 12),
    ("tdcr3", "mixed", 40), ("tdcr4_ext", "lattice", 20), ("tdcr4_ext", "shelf", 8),
    ("tdcr4_ext", "mixed", 30),
])
def test_check_many_matches_the_reference(robots, mixed_scene, robot_name, scene_name,
                                          count) -> None:
    robot = robots[robot_name]
    scene = mixed_scene if scene_name == "mixed" else load_scene(scene_name)
    qs = random_q(robot, count, seed=len(scene_name) + count)
    got = check_many(robot, scene, qs)
    for k, q in enumerate(qs):
        want = reference(robot, scene, q)
        # Obstacles: the same closed form and the same fcl calls (on the same capsule
        # objects), only fewer of them.
        assert got.obstacle_distance[k] == pytest.approx(want["obstacle_distance"], abs=1e-12)
        # Self: closed form against fcl's capsule pair; fcl's penetration depth (EPA) was
        # measured off by up to 7e-7 m, its separated distance agrees to ~1e-15.
        tol = 1e-10 if want["self_distance"] > 0 else 1e-5
        assert got.self_distance[k] == pytest.approx(want["self_distance"], abs=tol)
        assert got.min_distance[k] == min(got.obstacle_distance[k], got.self_distance[k])
        assert got.collision[k] == (want["min_distance"] < 0)
        assert got.self_collision[k] == (want["self_distance"] < 0)
        assert got.closest[k] == want["closest"]
        one = check(robot, scene, q)
        assert one.min_distance == got.min_distance[k] and one.closest == got.closest[k]
        assert one.self_distance == got.self_distance[k]
    assert got.collision.dtype == bool and got.min_distance.shape == (count,)


def test_chunking_and_empty_cases(robots, mixed_scene, monkeypatch) -> None:
    robot = robots["tdcr3"]
    qs = random_q(robot, 50, seed=3)
    whole = check_many(robot, mixed_scene, qs)
    monkeypatch.setattr(check_module, "_BATCH_ELEMENTS", 1)     # one configuration a chunk
    pieces = check_many(robot, mixed_scene, qs)
    for field in ("min_distance", "obstacle_distance", "self_distance"):
        assert np.array_equal(getattr(whole, field), getattr(pieces, field))
    assert whole.closest == pieces.closest
    # No configurations, no obstacles.
    none = check_many(robot, mixed_scene, np.zeros((0, robot.dof)))
    assert none.min_distance.shape == (0,) and none.closest == ()
    empty = check_many(robot, Scene("empty", ()), qs)
    assert np.all(np.isinf(empty.obstacle_distance))
    assert all(c in ("", "self") for c in empty.closest)
    assert np.array_equal(empty.self_distance, whole.self_distance)
    two = Robot.from_dict({**robot.to_dict(), "segments": robot.to_dict()["segments"][:2],
                           "tendons": {**robot.to_dict()["tendons"], "offsets": [0, 0]}})
    lone = check(two, Scene("empty", ()), np.array([0.0, 0.0, 1.0] * 2))
    assert lone.min_distance == np.inf and lone.closest == "" and not lone.collision


def test_lazy_capsules_are_capsule_objects() -> None:
    """Zero-length pieces become balls, and a piece along −z gets the half turn."""
    built = fcl_objects.Capsules(0.1, np.zeros((2, 3)), np.array([[0, 0, 0], [0, 0, -1.0]]))
    ball = fcl_object(SpherePart(np.array([0.0, 0.0, 0.5]), 0.1))
    assert built[0].getNodeType() == fcl.CollisionObject(fcl.Sphere(1.0)).getNodeType()
    assert built[1].getNodeType() == fcl.CollisionObject(fcl.Capsule(1.0, 1.0)).getNodeType()
    assert fcl_distance(built[0], ball) == pytest.approx(0.3, abs=1e-9)
    assert fcl_distance(built[1], ball) == pytest.approx(0.3, abs=1e-9)   # the −z turn


def test_tightened_bounds_are_below_fcl_and_a_threshold_only_skips_work(robots,
                                                                         mixed_scene) -> None:
    """``_tighten`` (axis-aligned box, bounding sphere, face planes, axis) stays below fcl's
    distance for every kind of part, and with a threshold the pairs below it get the same
    bounds while the others stay at or above it."""
    robot = robots["tdcr3"]
    r = robot.backbone_radius
    chains = body_chain(robot, random_q(robot, 8, seed=11))
    for scene in (mixed_scene, load_scene("cabinet")):
        fscene = fcl_objects.fcl_scene(scene)
        parts = len(fscene.other_index)
        a, b = chains[:, :-1].reshape(-1, 3), chains[:, 1:].reshape(-1, 3)
        pi, qi = np.repeat(np.arange(len(a)), parts), np.tile(np.arange(parts), len(a))
        loose = np.full(len(pi), -np.inf)
        full = check_module._tighten(r, fscene, a[pi], b[pi], qi, loose.copy())
        threshold = np.median(full)
        cut = check_module._tighten(r, fscene, a[pi], b[pi], qi, loose.copy(), threshold)
        below = full < threshold
        assert np.array_equal(cut[below], full[below]) and np.all(cut[~below] >= threshold)
        capsules = [capsule_object(a[i], b[i], r) for i in range(len(a))]
        d = np.array([fcl_distance(capsules[i], fscene.objects[fscene.other_index[q]])
                      for i, q in zip(pi, qi, strict=True)])
        assert np.all(full <= d + 1e-5)                 # fcl's GJK: ~1e-5 m
        assert np.mean(full > 0.5 * d) > 0.5            # and not a trivial bound
