"""The broad-phase table (``world._broad_phase``): a body sphere's cell row holds its
nearest part whenever that part is within the cutoff, checked against brute force over
every part, on the bundled scenes and on a scene of every part kind; and the grouped
clearance terms built on it against autodiff of the penalty distances."""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cr_nlp.model import load_robot, q_to_z_numpy
from cr_nlp.model._ops import NUMPY
from cr_nlp.tasks.geometry.trajectory import TrajectoryConfig
from cr_nlp.world import ConvexPart, Obstacle, Scene, load_scene, scene_arrays
from cr_nlp.world._broad_phase import (
    CELL_BASE,
    GRID_ROUND,
    TABLE_BYTES,
    WIDTH_ROUND,
    _cells_per_axis,
    _least_table_bytes,
    _part_box,
    _reach,
    cell_candidates,
    part_cells,
    part_cells_cache_stats,
    reach_box,
)
from cr_nlp.world._clearance_groups import (
    body_centres_jacobian_z,
    body_centres_z,
    clearance_group_values,
    grouped_shortfalls,
)
from cr_nlp.world.clearance import body_gap_tolerance, kind_distances, self_pairs

from ..conftest import MODELS

ROBOT = load_robot(MODELS / "robots" / "tdcr3.json")
CUTOFF = 0.1


def mixed_scene() -> Scene:
    """Spheres, a rotated box, a capsule, a cylinder and two convex blobs, near each other
    and within tdcr3's reach."""
    primitives = load_scene({"name": "primitives", "obstacles": [
        {"type": "sphere", "center": [0.5, 0.2, 1.0], "radius": 0.2},
        {"type": "sphere", "center": [0.7, 0.3, 1.3], "radius": 0.1},
        {"type": "box", "center": [-0.5, 0.3, 1.2], "size": [0.3, 0.4, 0.5],
         "wxyz": [0.9, 0.1, 0.3, 0.3]},
        {"type": "capsule", "a": [0.0, -0.6, 0.5], "b": [0.4, -0.5, 1.5], "radius": 0.1},
        {"type": "cylinder", "a": [-0.4, -0.4, 0.8], "b": [-0.2, -0.7, 1.6], "radius": 0.15},
    ]})
    rng = np.random.default_rng(3)
    blobs = tuple(Obstacle(f"blob{i}", "mesh", (ConvexPart.from_points(
        rng.normal(size=(30, 3)) * 0.2 + centre),), {})
        for i, centre in enumerate([(0.3, 0.5, 2.0), (0.1, 0.2, 1.6)]))
    return Scene("mixed", primitives.obstacles + blobs)


def scene_named(name: str) -> Scene:
    return mixed_scene() if name == "mixed" else load_scene(name)


def sample_points(scene: Scene, count: int, seed: int) -> np.ndarray:
    """(2·count, 3) points, m: uniform in tdcr3's reach box, and uniform in the box of the
    points within the body radius plus the cutoff of a random part (many within it)."""
    rng = np.random.default_rng(seed)
    lo, hi = reach_box(ROBOT)
    boxes = [_part_box(p, ROBOT.backbone_radius + CUTOFF) for p in scene.parts]
    pick = rng.integers(len(boxes), size=count)
    near_lo = np.array([boxes[i][0] for i in pick])
    near_hi = np.array([boxes[i][1] for i in pick])
    return np.concatenate([rng.uniform(lo, hi, (count, 3)), rng.uniform(near_lo, near_hi)])


def row_and_true_minimum(scene: Scene, cells, points: np.ndarray) -> tuple[np.ndarray, ...]:
    """Float64 distances (M,) m of body spheres at ``points``: the minimum over their cell
    rows (looked up in float32, as the optimisers do) and over every part."""
    arrays = scene_arrays(scene, as_numpy=True)
    blocks = kind_distances(ROBOT.backbone_radius, arrays, points, 0.0, NUMPY)
    rows = cell_candidates(cells, jnp.asarray(points, jnp.float32))
    assert len(rows) == len(blocks)
    row_min = np.min([np.take_along_axis(b, np.asarray(r), axis=1).min(axis=1)
                      for b, r in zip(blocks, rows, strict=True)], axis=0)
    true_min = np.min([b.min(axis=1) for b in blocks], axis=0)
    return row_min, true_min


@pytest.mark.parametrize("name", ["shelf", "cabinet", "random_27", "mixed"])
def test_cell_rows_hold_the_nearest_part_within_the_cutoff(name):
    """With no row cut short, a sphere's row minimum is the brute-force nearest distance
    (float64, to the bit) wherever that is below the cutoff, and above the cutoff
    elsewhere: 4000 points in the reach box and 4000 around the parts."""
    scene = scene_named(name)
    cells = part_cells(scene, ROBOT.backbone_radius, reach_box(ROBOT), CUTOFF, near=64)
    assert cells.truncated == 0 and cells.cell_size == pytest.approx(0.05)
    assert cells.table.nbytes < 16e6
    row_min, true_min = row_and_true_minimum(scene, cells, sample_points(scene, 4000, 1))
    within = true_min < CUTOFF
    assert within.sum() > 1000 and (~within).sum() > 1000
    np.testing.assert_array_equal(row_min[within], true_min[within])
    assert np.all(row_min[~within] >= CUTOFF)


def test_a_sharp_convex_part_is_kept_as_far_as_its_face_planes_reach():
    """A convex part's distance is its largest face-plane value, which stays below the
    cutoff far beyond a sharp tip (much farther than the body radius plus the cutoff from
    the part): on the line through a needle's tip the rows still hold it there."""
    tip = np.array([0.3, -0.2, 1.2])
    needle = ConvexPart.from_points(np.array(
        [[0.0, 0.0, 0.0], [0.03, 0.0, 0.0], [0.0, 0.03, 0.0], [0.0, 0.0, 0.8]]) + tip - [0, 0, 0.8])
    scene = Scene("needle", (Obstacle("needle", "mesh", (needle,), {}),))
    cells = part_cells(scene, ROBOT.backbone_radius, reach_box(ROBOT), CUTOFF)
    points = tip + np.linspace(0.0, 1.5, 600)[:, None] * [0.001, 0.001, 1.0]
    row_min, true_min = row_and_true_minimum(scene, cells, points)
    within = true_min < CUTOFF
    beyond = np.linalg.norm(points - tip, axis=1) > ROBOT.backbone_radius + CUTOFF + 0.1
    assert np.any(within & beyond)
    np.testing.assert_array_equal(row_min[within], true_min[within])


def test_the_planners_tables_are_exact_on_the_bundled_scenes():
    """With the trajectory planner's settings (cutoff = its sphere-body margin, at most 16
    parts per kind, automatic 0.05 m cells) no row of the bundled scenes is cut, and the
    widest row (the work per body sphere) is at most 12 convex parts, or 4 spheres."""
    planner_margin = TrajectoryConfig().safety_margin + body_gap_tolerance(ROBOT)
    widths = {}
    for name in ("shelf", "cabinet", "random_27"):
        cells = part_cells(load_scene(name), ROBOT.backbone_radius, reach_box(ROBOT),
                           planner_margin, near=TrajectoryConfig().near_parts)
        assert cells.truncated == 0
        widths[name] = max(cells.widths)
    assert widths["random_27"] == 4 and max(widths["shelf"], widths["cabinet"]) <= 12


def test_a_cut_row_is_never_nearer_than_the_truth():
    """Truncation (one part per row, the row padded with part 0 to ``WIDTH_ROUND``
    columns) may miss the nearest part of a cell; what it measures is then farther than
    the truth, never nearer (every entry is a real part)."""
    scene = load_scene("shelf")
    cells = part_cells(scene, ROBOT.backbone_radius, reach_box(ROBOT), CUTOFF, near=1)
    assert cells.truncated > 0 and cells.widths == (0, 0, 0, 0, WIDTH_ROUND)
    row_min, true_min = row_and_true_minimum(scene, cells, sample_points(scene, 2000, 2))
    assert np.all(row_min >= true_min)
    assert np.any(row_min[true_min < CUTOFF] > true_min[true_min < CUTOFF])


def test_a_scene_out_of_reach_gets_one_cell():
    """Parts beyond the reach box plus the cutoff: one cell, and every sphere measured
    beyond the cutoff."""
    far = load_scene({"name": "far", "obstacles": [
        {"type": "sphere", "center": [9.0, 0.0, 0.0], "radius": 0.5},
        {"type": "box", "center": [0.0, -9.0, 0.0], "size": [1.0, 1.0, 1.0]}]})
    cells = part_cells(far, ROBOT.backbone_radius, reach_box(ROBOT), CUTOFF)
    assert cells.table.shape[:3] == (1, 1, 1)
    assert cells.widths == (WIDTH_ROUND, WIDTH_ROUND, 0, 0, 0)
    row_min, true_min = row_and_true_minimum(far, cells, sample_points(far, 500, 3)[:500])
    assert np.all(true_min > CUTOFF) and np.all(row_min >= true_min)


def test_bad_table_settings_are_refused():
    scene = load_scene("random_27")
    with pytest.raises(ValueError, match="near"):
        part_cells(scene, 0.1, reach_box(ROBOT), CUTOFF, near=0)
    with pytest.raises(ValueError, match="cell_size"):
        part_cells(scene, 0.1, reach_box(ROBOT), CUTOFF, cell_size=0.0)
    with pytest.raises(ValueError, match="cutoff finite"):   # the automatic size too
        part_cells(scene, 0.1, reach_box(ROBOT), math.inf)


@pytest.mark.usefixtures("float64")
@pytest.mark.parametrize(("name", "margin"), [
    ("mixed", 1.5), pytest.param("mixed", 0.05, marks=pytest.mark.slow),
    pytest.param("shelf", 0.05, marks=pytest.mark.slow),
    pytest.param("shelf", 1.5, marks=pytest.mark.slow)])
def test_group_jacobians_equal_autodiff_of_the_penalty_distances(name, margin):
    """``grouped_shortfalls`` with the closed-form centre Jacobians (per-sphere distance
    gradients collected per group, one contraction) against forward-mode autodiff of
    ``clearance_group_values`` (``world._penalty``'s distances), float64, at 40 random
    tdcr3 configurations, with the broad-phase table and without: a 1.5 m margin (every
    sphere and the self pairs active) and a 0.05 m one (some spheres in contact)."""
    scene = scene_named(name)
    arrays = scene_arrays(scene, dtype=jnp.float64)
    rng = np.random.default_rng(5)
    z = rng.uniform(-1.2, 1.2, (40, ROBOT.dof))
    z[:, 2::3] = 1.0
    z = jnp.asarray(z)
    values, auto = jax.jit(jax.vmap(lambda x: (
        clearance_group_values(ROBOT, margin, arrays, x),
        jax.jacfwd(partial(clearance_group_values, ROBOT, margin, arrays))(x))))(z)
    active = np.asarray(values) > 0
    assert active.sum() >= 10 and (margin < 1 or active[:, -1].all())
    cells = part_cells(scene, ROBOT.backbone_radius, reach_box(ROBOT), margin, near=64,
                       dtype=jnp.float64)
    for table in (None, cells):
        got = jax.jit(jax.vmap(lambda x, t=table: grouped_shortfalls(
            ROBOT, margin, arrays, *body_centres_jacobian_z(ROBOT, x), t)))(z)
        np.testing.assert_allclose(got[0], values, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[1], auto, rtol=0, atol=1e-9)


@pytest.mark.usefixtures("float64")
@pytest.mark.parametrize("margin", [1.0, 0.3])
def test_self_pair_blocks_give_the_group_jacobian_of_every_pair(margin):
    """The self group of ``grouped_shortfalls`` (pairs taken block by block, each block's
    pulls summed back onto its spheres) against forward-mode autodiff of a plain sum over
    ``clearance.self_pairs`` (one gathered pair at a time), float64, on a 4-segment robot
    whose self pairs form three blocks, with a margin of 1 m and of 0.3 m."""
    robot = load_robot(MODELS / "robots" / "tdcr4_ext.json")
    pairs = self_pairs(robot)
    rng = np.random.default_rng(11)
    lo, hi = robot.q_bounds()
    z = jnp.asarray(q_to_z_numpy(rng.uniform(lo, hi, (30, robot.dof))))

    def reference(x):
        centres = body_centres_z(robot, x)
        diff = centres[pairs[:, 0]] - centres[pairs[:, 1]]
        short = jnp.maximum(margin + 2 * robot.backbone_radius
                            - jnp.linalg.norm(diff, axis=-1), 0.0)
        return jnp.sqrt(jnp.sum(short ** 2) + 1e-18)[None] - 1e-9

    expected = jax.jit(jax.vmap(reference))(z)
    expected_jac = jax.jit(jax.vmap(jax.jacfwd(reference)))(z)
    values, jac = jax.jit(jax.vmap(lambda x: grouped_shortfalls(
        robot, margin, None, *body_centres_jacobian_z(robot, x))))(z)
    active = np.asarray(expected[:, 0]) > 0
    assert active.sum() >= 5
    np.testing.assert_allclose(values, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(jac, expected_jac, rtol=0, atol=1e-9)


def test_a_cell_size_is_skipped_only_where_its_table_cannot_fit():
    """The automatic cell size skips, without building it, a size whose smallest possible
    table (``_least_table_bytes``) is over ``TABLE_BYTES``: that bound is never above the
    table built at that size, and the size chosen is the first whose table fits."""
    scenes = {name: load_scene(name) for name in ("shelf", "cabinet", "random_27")}
    scenes["mixed"] = scene_named("mixed")
    region = reach_box(ROBOT)
    def least(scene, cutoff, size):
        kinds, _, lo, hi = _reach(scene, ROBOT.backbone_radius, region, cutoff)
        return _least_table_bytes(kinds, _cells_per_axis(lo, hi, size))

    for name, scene in scenes.items():
        for cutoff, sizes in ((0.014, (0.05, 0.1)), (0.3, (0.1, 0.2))):
            for size in sizes:
                built = part_cells(scene, ROBOT.backbone_radius, region, cutoff, cell_size=size)
                assert 0 < least(scene, cutoff, size) <= built.table.nbytes, (name, cutoff, size)
    # 1.5 m: the sizes below 0.1 m cannot fit (the automatic table skips them unbuilt)
    scene, cutoff = scenes["mixed"], 1.5
    auto = part_cells(scene, ROBOT.backbone_radius, region, cutoff, near=64)
    assert auto.cell_size == pytest.approx(4 * CELL_BASE) and auto.table.nbytes <= TABLE_BYTES
    for size in (CELL_BASE * 2**0.5, 2 * CELL_BASE, CELL_BASE * 2**1.5):
        assert least(scene, cutoff, size) > TABLE_BYTES


def test_robots_of_similar_size_get_one_grid_shape():
    """The automatic cell edge comes from one series (``CELL_BASE``·√2ᵏ) and the grid is
    padded to ``GRID_ROUND`` cells per axis: tdcr3 and a robot of its layout with other
    lengths and radii (reach 2.8 m instead of 3 m) get tables of one shape with the
    trajectory planner's settings (so one program serves both), each exact for its own
    robot. (Near a boundary of the padding two such robots can still differ: with a
    0.1 m cutoff the shelf's grids are 48 and 64 cells deep.)"""
    from cr_nlp.bench.startup import NEW_ROBOT
    from cr_nlp.model.robot import Robot

    other = Robot.from_dict(NEW_ROBOT)
    for name in ("shelf", "cabinet"):
        scene = load_scene(name)
        tables = [part_cells(scene, r.backbone_radius, reach_box(r),
                             TrajectoryConfig().safety_margin + body_gap_tolerance(r),
                             near=TrajectoryConfig().near_parts) for r in (ROBOT, other)]
        assert tables[0].table.shape == tables[1].table.shape
        assert tables[0].widths == tables[1].widths
        assert tables[0].cell_size == tables[1].cell_size == pytest.approx(2 * CELL_BASE)
        assert all(d % GRID_ROUND == 0 for d in tables[1].table.shape[:3])
        assert tables[1].truncated == 0


def test_a_table_is_built_once_and_read_back_from_the_cache(tmp_path, monkeypatch):
    """A second ``part_cells`` with the same scene and settings reads the table the first
    one built (the same arrays and fields, in the asked dtype); another cutoff or a moved
    part builds its own; a damaged file is built again and replaced."""
    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path))
    scene, region = load_scene("shelf"), reach_box(ROBOT)
    before = part_cells_cache_stats()

    def counts() -> tuple[int, int]:
        now = part_cells_cache_stats()
        return now["hits"] - before["hits"], now["builds"] - before["builds"]

    built = part_cells(scene, ROBOT.backbone_radius, region, 0.014)
    again = part_cells(scene, ROBOT.backbone_radius, region, 0.014, dtype=jnp.float32)
    assert counts() == (1, 1)
    assert np.array_equal(np.asarray(again.table), np.asarray(built.table))
    assert again.table.dtype == built.table.dtype
    assert (again.widths, again.cell_size, again.cutoff, again.truncated) == (
        built.widths, built.cell_size, built.cutoff, built.truncated)
    assert again.origin.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(again.origin), np.asarray(built.origin, np.float32))
    part_cells(scene, ROBOT.backbone_radius, region, 0.02)
    moved = Scene("moved", tuple(scene.obstacles[1:]))
    part_cells(moved, ROBOT.backbone_radius, region, 0.014)
    assert counts() == (1, 3)
    files = sorted((tmp_path / "cell_tables").glob("*.npz"))
    assert len(files) == 3
    for path in files:
        path.write_bytes(b"not a table")
    damaged = part_cells(scene, ROBOT.backbone_radius, region, 0.014)
    assert counts() == (1, 4)
    assert np.array_equal(np.asarray(damaged.table), np.asarray(built.table))
