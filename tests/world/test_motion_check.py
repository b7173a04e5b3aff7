"""The verdict on motions (``world._motion_check``): the smallest distances and the
collisions of ``check_many`` and of a plain every-pair reference, with fewer fcl queries,
for one motion and for several at once."""

import importlib

import numpy as np
import pytest

from cr_nlp.world import Scene, load_scene
from cr_nlp.world._motion_check import check_motion, check_motions
from cr_nlp.world.check import body_chain, capsule_object, check, check_many, fcl_distance

from ..conftest import random_q

check_module = importlib.import_module("cr_nlp.world.check")
motion_module = importlib.import_module("cr_nlp.world._motion_check")
fcl_objects = importlib.import_module("cr_nlp.world._fcl_objects")


@pytest.mark.parametrize("robot_name,scene_name,chunk", [
    ("tdcr3", "shelf", None), ("tdcr3", "cabinet", None), ("tdcr3", "mixed", None),
    ("tdcr3", "lattice", None), ("tdcr4_ext", "mixed", 1 << 12), ("tdcr3", "shelf", 1),
    ("tdcr3", "random_27", None), ("tdcr3", "random_27", 1 << 12), ("tdcr3", "lattice", 1),
])
def test_check_motion_gives_the_minima_and_collisions_of_check_many(
        robots, mixed_scene, monkeypatch, robot_name, scene_name, chunk) -> None:
    """The motion verdict measures fewer pairs but decides the same: the smallest obstacle
    and self distances (the same fcl calls on the same capsules; where two pairs tie for
    the minimum either may be measured, so to rounding) and every configuration's
    collision, on motions that hit and miss the obstacles. Small chunks (``chunk``) split
    a motion into several, each starting from the minimum of those before."""
    robot = robots[robot_name]
    scene = mixed_scene if scene_name == "mixed" else load_scene(scene_name)
    if chunk is not None:
        monkeypatch.setattr(motion_module, "_CHUNK_ELEMENTS", chunk >> 2)
    ends = random_q(robot, 12, seed=len(scene_name))
    for start, goal in zip(ends[::2], ends[1::2], strict=True):
        qs = start + np.linspace(0.0, 1.0, 25)[:, None] * (goal - start)
        want = check_many(robot, scene, qs)
        got = check_motion(robot, scene, qs)
        assert got.obstacle_distance == pytest.approx(want.obstacle_distance.min(), abs=1e-12)
        assert got.self_distance == want.self_distance.min()
        assert np.array_equal(got.collision, want.collision)
        nearest = int(np.argmin(want.obstacle_distance))
        if np.isfinite(got.obstacle_distance):
            assert got.closest == check(robot, scene, qs[nearest]).closest or \
                got.obstacle_distance < want.self_distance[nearest]
    empty = check_motion(robot, Scene("empty", ()), ends)
    assert empty.obstacle_distance == np.inf and empty.closest == ""
    none = check_motion(robot, scene, np.zeros((0, robot.dof)))
    assert none.collision.shape == (0,) and none.obstacle_distance == np.inf


def _bounds(r, fscene, chains, group, tile, motion_length=7):
    """The motion search's bounds for body chains, each piece's entries (B, pieces,
    parts): its tile's run (``_tile_bounds``, tiles of ``tile`` configurations of one
    motion of ``motion_length``), its run (``_run_bounds``); and each piece's own ball
    (float64: the part's bounding sphere and its box: the distance outside, the largest
    gap inside) against every part."""
    a, b = chains[:, :-1], chains[:, 1:]
    count, pieces = a.shape[:2]
    mid, half = 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=-1)
    balls = motion_module._run_balls(r, tuple(mid[..., k] for k in range(3)), half, group)
    starts = motion_module._tiles(np.arange(count) // motion_length, tile)
    tiles = motion_module._tile_bounds(fscene, *balls, starts)
    parts = len(fscene.other_index)
    assert tiles.shape == (len(starts), pieces // group, parts)
    of_tile = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, count]))
    k, g, q = (x.ravel() for x in np.meshgrid(np.arange(count), np.arange(pieces // group),
                                              np.arange(parts), indexing="ij"))
    runs = motion_module._run_bounds(fscene, *balls, k, g, q).reshape(tiles[of_tile].shape)
    mid = mid[:, :, None]
    beyond = np.maximum(fscene.box_lower - mid, mid - fscene.box_upper)
    box = np.where(beyond.max(axis=-1) > 0.0,
                   np.linalg.norm(np.maximum(beyond, 0.0), axis=-1), beyond.max(axis=-1))
    piece_ball = (np.maximum(np.linalg.norm(mid - fscene.other_centres, axis=-1)
                             - fscene.other_radii, box) - half[:, :, None] - r)
    return (np.repeat(tiles[of_tile], group, axis=1), np.repeat(runs, group, axis=1),
            piece_ball)


@pytest.mark.parametrize("group,tile", [(1, 1), (2, 3), (5, 1), (5, 4), (10, 7)])
def test_tile_and_run_balls_bound_every_piece_of_them(robots, mixed_scene, group,
                                                     tile) -> None:
    """The motion search's first cuts are true lower bounds: a tile's run (a ball around
    a run's pieces in several configurations of a motion) below every run of it, a run
    below every piece's own ball in it (against the part's bounding sphere and
    axis-aligned box) and below fcl's distance of each piece; also where the pieces lie
    deep inside a part (a box around the whole robot, distances below −r)."""
    robot = robots["tdcr3"]
    r = robot.backbone_radius
    chains = body_chain(robot, random_q(robot, 14, seed=group))
    around = {"name": "around", "obstacles": [
        {"type": "box", "name": "around", "center": [0.0, 0.0, 1.5], "size": [5.0, 5.0, 5.0]}]}
    deep = 0
    for scene in (mixed_scene, load_scene("cabinet"), load_scene(around)):
        fscene = fcl_objects.fcl_scene(scene)
        tiles, runs, piece_ball = _bounds(r, fscene, chains, group, tile)
        assert np.all(tiles <= runs + 1e-6)              # float32 entries: their slack
        assert np.all(runs <= piece_ball + 1e-12)
        count, pieces = chains.shape[0], chains.shape[1] - 1
        for k in range(count):
            for i in range(0, pieces, 3):
                capsule = capsule_object(chains[k, i], chains[k, i + 1], r)
                for q, whole in enumerate(fscene.other_index):
                    d = fcl_distance(capsule, fscene.objects[whole])
                    assert runs[k, i, q] <= d + 1e-5     # fcl's GJK: ~1e-5 m
                    deep += d < -r
    assert deep > 0


@pytest.mark.parametrize("offset", [0.0, 300.0])
@pytest.mark.parametrize("group,tile", [(1, 1), (5, 1), (5, 8)])
def test_tile_bounds_in_float32_stay_below_far_from_the_origin(robots, offset, group,
                                                              tile) -> None:
    """The tile bounds are float32 lowered by a bound on their rounding: still below every
    piece's own ball (float64) in a scene of boxes, tilted and not, around the robot's
    motions (five of eight configurations), also where both are moved ``offset`` m from
    the origin (larger coordinates, larger rounding). Tiles of one configuration's runs of
    one piece are that piece's ball: there the float32 rounding alone would lift many
    bounds above it."""
    robot = robots["tdcr3"]
    ends = random_q(robot, 10, seed=3)
    motions = [start + np.linspace(0.0, 1.0, 8)[:, None] * (goal - start)
               for start, goal in zip(ends[::2], ends[1::2], strict=True)]
    chains = body_chain(robot, np.concatenate(motions)) + [offset, 0.0, 0.0]
    tilt = {"wxyz": [0.9621, 0.20255, 0.15191, 0.10127]}
    boxes = [{"type": "box", "name": f"box{i}", "size": [0.05, 0.4, 0.3],
              "center": [offset + x, y, z], **(tilt if i % 2 else {})}
             for i, (x, y, z) in enumerate(np.random.default_rng(4).uniform(
                 [-0.3, -0.3, 0.0], [0.3, 0.3, 0.4], (12, 3)))]
    fscene = fcl_objects.fcl_scene(load_scene({"name": "far", "obstacles": boxes}))
    tiles, runs, piece_ball = _bounds(robot.backbone_radius, fscene, chains, group, tile, 8)
    assert np.all(tiles <= piece_ball)
    assert np.all(runs <= piece_ball + 1e-12)
    assert np.mean(np.abs(tiles) < 0.02) > 0.01          # some tiles near the boxes


def test_pruned_motion_search_gives_the_minima_of_the_plain_one(robots) -> None:
    """On random box scenes, the motion search (runs pruned by their balls) gives the
    smallest distance and the collisions of every pair measured."""
    robot = robots["tdcr3"]
    rng = np.random.default_rng(7)
    hits = 0
    for trial in range(6):
        centres = rng.uniform([-1.2, -1.2, 0.8], [1.2, 1.2, 2.4], (12, 3))
        boxes = [{"type": "box", "name": f"box{j}", "center": centre.tolist(),
                  "size": rng.uniform(0.1, 0.6, 3).tolist()} for j, centre in enumerate(centres)]
        scene = Scene.from_dict({"obstacles": boxes})
        start, goal = random_q(robot, 2, seed=trial)
        qs = start + np.linspace(0.0, 1.0, 9)[:, None] * (goal - start)
        got = check_motion(robot, scene, qs)
        chains = body_chain(robot, qs)
        capsules = [[capsule_object(c[i], c[i + 1], robot.backbone_radius)
                     for i in range(len(c) - 1)] for c in chains]
        every = np.array([[min(fcl_distance(p, obj) for obj in
                               fcl_objects.fcl_scene(scene).objects) for p in row]
                          for row in capsules]).min(axis=1)
        assert got.obstacle_distance == pytest.approx(every.min(), abs=1e-12)
        hits += int(np.any(every < 0.0))
        assert np.array_equal(got.collision, np.minimum(every, check_many(
            robot, scene, qs).self_distance) < 0.0)
    assert 0 < hits < 6                  # motions that hit boxes and motions that miss




@pytest.mark.parametrize("scene_name,chunk,batch", [
    ("shelf", None, None), ("mixed", None, 1 << 12), ("lattice", 1 << 12, None),
    ("cabinet", 1 << 11, 1),
])
def test_motions_checked_together_get_what_each_gets_alone(
        robots, mixed_scene, monkeypatch, scene_name, chunk, batch) -> None:
    """``check_motions`` on motions of different lengths (one empty, one a single
    configuration) gives each motion's report from ``check_motion`` alone: the same
    minimum (the same fcl calls on the same capsules), self distance, collisions and
    nearest obstacle, with motions sharing a batch (``batch``: one motion per batch)
    and split into chunks (``chunk``)."""
    robot = robots["tdcr3"]
    scene = mixed_scene if scene_name == "mixed" else load_scene(scene_name)
    ends = random_q(robot, 16, seed=3)
    motions = [start + np.linspace(0.0, 1.0, n)[:, None] * (goal - start)
               for start, goal, n in zip(ends[::2], ends[1::2], (25, 1, 40, 9, 0, 60, 17, 3),
                                         strict=True)]
    alone = [check_motion(robot, scene, qs) for qs in motions]
    if chunk is not None:
        monkeypatch.setattr(motion_module, "_CHUNK_ELEMENTS", chunk >> 2)
    if batch is not None:
        monkeypatch.setattr(motion_module, "_ROUND_ELEMENTS", batch)
    together = check_motions(robot, scene, [body_chain(robot, qs) for qs in motions])
    hits = 0
    for qs, one, got in zip(motions, alone, together, strict=True):
        want = check_many(robot, scene, qs)
        assert got.obstacle_distance == pytest.approx(
            want.obstacle_distance.min(initial=np.inf), abs=1e-12)
        if chunk is None:      # the same chunks: the same queries, bit for bit
            assert got.obstacle_distance == one.obstacle_distance
            assert got.closest == one.closest
        assert got.self_distance == one.self_distance
        assert np.array_equal(got.collision, want.collision)
        hits += int(got.collision.any())
    assert hits > 0                                 # motions that hit obstacles
    assert check_motions(robot, scene, []) == []
