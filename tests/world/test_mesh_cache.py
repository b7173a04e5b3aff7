"""The cached mesh decomposition (``world._mesh_cache``): a placed part
(``ConvexPart.placed``) is the hull of the placed points (checked against a fresh hull of
them), and a scene whose decomposition is cached loads without importing trimesh or
CoACD, with the parts of a fresh decomposition."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cr_nlp.model.rotations import matrix_from_wxyz
from cr_nlp.world._builders import union_of_boxes
from cr_nlp.world.scene import ConvexPart


def _planes(hull: ConvexPart) -> np.ndarray:
    """The face planes (normal, offset) as a sorted set, rounded to 1e-9."""
    planes = np.round(np.c_[hull.normals, hull.offsets], 9)
    return planes[np.lexsort(planes.T[::-1])]


def _points(hull: ConvexPart) -> np.ndarray:
    points = np.round(hull.vertices, 9)
    return points[np.lexsort(points.T[::-1])]


def test_a_placed_hull_is_the_hull_of_the_placed_points() -> None:
    rng = np.random.default_rng(3)
    points = rng.normal(size=(40, 3)) * [0.3, 0.1, 0.2]
    rotation = matrix_from_wxyz(np.array([0.8, 0.1, -0.5, 0.3]) / np.linalg.norm(
        [0.8, 0.1, -0.5, 0.3]))
    scale, position = 1.7, np.array([0.4, -1.2, 0.9])
    placed = ConvexPart.from_points(points).placed(scale, rotation, position)
    fresh = ConvexPart.from_points(scale * points @ rotation.T + position)
    np.testing.assert_allclose(_points(placed), _points(fresh), atol=1e-12)
    np.testing.assert_allclose(_planes(placed), _planes(fresh), atol=1e-9)
    # every vertex on or inside every face plane, each plane touching the hull
    slack = placed.offsets[None] - placed.vertices @ placed.normals.T
    assert slack.min() > -1e-12 and np.abs(slack.min(axis=0)).max() < 1e-12


@pytest.fixture
def corner_scene(tmp_path: Path) -> Path:
    """An L-shaped solid as an OBJ file, placed turned, scaled and moved by a scene file."""
    mesh = tmp_path / "corner.obj"
    union_of_boxes([((0, 0, 0), (0.6, 0.1, 0.4)), ((0, 0, 0), (0.1, 0.5, 0.4))]).export(mesh)
    scene = tmp_path / "corner.json"
    scene.write_text(json.dumps({"obstacles": [
        {"type": "mesh", "name": "corner", "path": "corner.obj", "scale": 0.5,
         "position": [0.2, 0.1, 0.3], "wxyz": [0.9, 0.0, 0.0, 0.4359]}]}))
    return scene


def _load_in_new_process(scene: Path, cache: Path) -> dict:
    code = ("import json, sys; from cr_nlp.world.scene import load_scene; "
            f"s = load_scene({str(scene)!r}); "
            "print(json.dumps({'trimesh': 'trimesh' in sys.modules, "
            "'coacd': 'coacd' in sys.modules, 'parts': [[p.vertices.tolist(), "
            "p.normals.tolist(), p.offsets.tolist()] for p in s.parts], "
            "'mesh': s.obstacles[0].mesh.triangles.tolist()}))")
    env = {**os.environ, "CR_NLP_CACHE_DIR": str(cache)}
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.splitlines()[-1])


def test_a_cached_scene_loads_without_trimesh_and_gives_the_same_parts(
        corner_scene: Path, tmp_path: Path) -> None:
    first = _load_in_new_process(corner_scene, tmp_path / "cache")
    again = _load_in_new_process(corner_scene, tmp_path / "cache")
    assert first["trimesh"] and first["coacd"]          # decomposed: both were needed
    assert not again["trimesh"] and not again["coacd"]  # from the cache: neither
    assert len(first["parts"]) == len(again["parts"]) >= 2
    for one, other in zip(first["parts"], again["parts"], strict=True):
        for a, b in zip(one, other, strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(first["mesh"]), np.asarray(again["mesh"]))
    # the placed mesh: the file's corner (0, 0, 0) moved to the scene's position
    corners = np.asarray(again["mesh"]).reshape(-1, 3)
    assert np.min(np.linalg.norm(corners - [0.2, 0.1, 0.3], axis=1)) < 1e-12
