"""Reference paths: the file format, the benchmark shapes, and that they are reachable."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from cr_nlp.model import ModelFileError, Robot
from cr_nlp.model.rotations import matrix_from_wxyz
from cr_nlp.tasks.geometry.ik import IKSolver
from cr_nlp.tasks.paths import SHAPES, ReferencePath, resample_polyline
from cr_nlp.tasks.readers import load_path
from cr_nlp.world import load_scene

from ..conftest import MODELS

TDCR3 = Robot.from_file(MODELS / "robots" / "tdcr3.json")


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_bundled_paths_match_their_generators(name: str) -> None:
    path = load_path(MODELS / "paths" / f"{name}.json")
    fresh = SHAPES[name]()
    assert len(path) == 150 and path.dt > 0
    np.testing.assert_allclose(path.positions, fresh.positions, atol=1e-12)
    np.testing.assert_array_equal(path.pen_down, fresh.pen_down)
    np.testing.assert_allclose(path.positions[:, 0], 1.5)  # the drawing plane
    # The tip points along +x, towards the plane.
    np.testing.assert_allclose(matrix_from_wxyz(path.wxyz)[:, :, 2], [[1, 0, 0]] * 150,
                               atol=1e-12)


def test_square_has_sharp_corners_and_even_spacing() -> None:
    path = SHAPES["square"]()
    yz = path.positions[:, 1:]
    for corner in ([-0.5, 1.0], [0.5, 1.0], [0.5, 2.0], [-0.5, 2.0]):
        assert np.min(np.linalg.norm(yz - corner, axis=1)) < 4.0 / 149 / 2 + 1e-9
    steps = np.linalg.norm(np.diff(path.positions, axis=0), axis=1)
    assert steps.max() <= 4.0 / 149 + 1e-9  # perimeter / intervals; corners cut shorter


def test_icra_has_pen_up_moves_between_its_strokes() -> None:
    path = SHAPES["icra"]()
    changes = np.count_nonzero(np.diff(path.pen_down.astype(int)))
    assert not path.pen_down.all() and changes >= 6  # four moves between five strokes
    assert path.positions[:, 1].min() >= -0.8 - 1e-9 and path.positions[:, 1].max() <= 0.8


def test_resample_polyline_keeps_length_and_ends() -> None:
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 2, 0]], dtype=float)
    out, _ = resample_polyline(pts, 31)
    np.testing.assert_allclose(out[[0, -1]], pts[[0, -1]])
    np.testing.assert_allclose(np.linalg.norm(np.diff(out, axis=0), axis=1), 0.1, atol=1e-12)


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n == "icra" else n
                                  for n in sorted(SHAPES)])
def test_every_waypoint_is_reachable_collision_free(name: str) -> None:
    path = load_path(MODELS / "paths" / f"{name}.json")
    scene = load_scene(MODELS / "scenes" / f"follow_{name}.json")
    result = IKSolver(TDCR3, scene).solve(path.positions[::3], path.wxyz[::3])
    assert result.success.all(), [result.reason[i] for i in np.flatnonzero(~result.success)]


def write(tmp_path: Path, data: object) -> Path:
    p = tmp_path / "path.json"
    p.write_text(json.dumps(data))
    return p


GOOD = {"dt": 0.1, "poses": [{"position": [1.5, 0, 1.5], "wxyz": [1, 0, 0, 0]}] * 3}


@pytest.mark.parametrize(("data", "message"), [
    ({**GOOD, "dt": 0}, "'dt': must be positive"),
    ({"poses": GOOD["poses"]}, "'dt': missing required field"),
    ({**GOOD, "poses": GOOD["poses"][:1]}, "at least 2 poses"),
    ({**GOOD, "poses": [{"position": [1, 2], "wxyz": [1, 0, 0, 0]}] * 2},
     "'poses[0].position'"),
    ({**GOOD, "poses": [{"position": [1, 2, 3], "wxyz": [1, 1, 0, 0]}] * 2}, "unit quaternion"),
    ({**GOOD, "pen_down": [True]}, "'pen_down'"),
    ({**GOOD, "speed": 3}, "unknown key"),
])
def test_bad_path_files(tmp_path: Path, data: dict, message: str) -> None:
    with pytest.raises(ModelFileError, match=re.escape(message)):
        ReferencePath.from_file(write(tmp_path, data))


def test_round_trip_through_a_file(tmp_path: Path) -> None:
    path = SHAPES["sine"](count=20, dt=0.05)
    back = ReferencePath.from_file(path.save(tmp_path / "sine.json"))
    np.testing.assert_allclose(back.positions, path.positions)
    assert back.dt == 0.05 and back.name == "sine"
