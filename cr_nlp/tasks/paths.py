"""Reference paths for path following: the file format and the benchmark shapes.

A path file is JSON: ``{"poses": [{"position": [x, y, z], "wxyz": [w, x, y, z]}, ...],
"dt": seconds}`` with optional ``"pen_down": [bool, ...]`` (False on the pen-up moves
between strokes, which the tip still follows) and ``"name"``/``"description"``.

The benchmark shapes (docs/design.md §4) lie in the plane x = 1.5 m in front of the robot,
inside the regions the bundled ``follow_*`` scenes were built around
(``world._builders.PATH_REGIONS``), with the tip pointing along +x, towards the plane:
a 1.0 m square with sharp corners, a sinusoid, and the letters "ICRA".
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._files import atomic_open
from .._resources import models_root
from ..model.robot import _Checker, read_model_file

PLANE_X = 1.5
"""The drawing plane of the benchmark shapes, metres."""
TIP_TOWARDS_PLANE = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)
"""wxyz of the tip frame whose z axis points along +x (90° about y)."""


@dataclass(frozen=True)
class ReferencePath:
    """Waypoint poses to follow: positions (N, 3) in metres, unit quaternions (N, 4),
    the time step ``dt`` in seconds between waypoints, and which waypoints draw."""

    name: str
    positions: np.ndarray
    wxyz: np.ndarray
    dt: float
    pen_down: np.ndarray

    def __len__(self) -> int:
        return len(self.positions)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "dt": self.dt,
                "poses": [{"position": p.tolist(), "wxyz": w.tolist()}
                          for p, w in zip(self.positions, self.wxyz, strict=True)],
                "pen_down": self.pen_down.tolist()}

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        with atomic_open(path) as handle:
            handle.write(json.dumps(self.to_dict(), indent=1) + "\n")
        return path

    @classmethod
    def from_file(cls, path: str | Path) -> ReferencePath:
        """Load and validate a path file (errors name the file, the field and the problem)."""
        return cls.from_dict(read_model_file(path), source=str(path))

    @classmethod
    def from_dict(cls, data: Any, source: str = "") -> ReferencePath:
        c = _Checker(source)
        d = c.obj(data, "", {"name", "description", "poses", "dt", "pen_down"}, {"poses", "dt"})
        dt = c.number(d["dt"], "dt", positive=True)
        poses = d["poses"]
        if not isinstance(poses, list) or len(poses) < 2:
            raise c.fail("poses", "expected a list of at least 2 poses")
        positions, quats = [], []
        for i, pose in enumerate(poses):
            p = c.obj(pose, f"poses[{i}]", {"position", "wxyz"}, {"position", "wxyz"})
            positions.append(c.vector(p["position"], f"poses[{i}].position", 3))
            w = np.array(c.vector(p["wxyz"], f"poses[{i}].wxyz", 4))
            if abs(np.linalg.norm(w) - 1.0) > 1e-6:
                raise c.fail(f"poses[{i}].wxyz",
                             f"must be a unit quaternion, its norm is {np.linalg.norm(w):.6g}")
            quats.append(w)
        pen = d.get("pen_down", [True] * len(poses))
        if (not isinstance(pen, list) or len(pen) != len(poses)
                or not all(isinstance(v, bool) for v in pen)):
            raise c.fail("pen_down", f"expected {len(poses)} booleans, one per pose")
        name = d.get("name", Path(source).stem if source else "path")
        return cls(str(name), np.array(positions), np.array(quats), dt, np.array(pen, bool))


def resample_polyline(points: np.ndarray, count: int,
                      pen_down: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points evenly spaced by arc length along a polyline (N, 3), keeping its
    corners where they fall; ``pen_down`` per input segment is carried to the samples."""
    points = np.asarray(points, dtype=float)
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    s = np.linspace(0.0, arc[-1], count)
    segment = np.clip(np.searchsorted(arc, s, side="right") - 1, 0, len(steps) - 1)
    t = (s - arc[segment]) / np.where(steps[segment] > 0, steps[segment], 1.0)
    out = points[segment] + t[:, None] * (points[segment + 1] - points[segment])
    down = np.ones(len(steps), bool) if pen_down is None else np.asarray(pen_down, bool)
    return out, down[segment]


def _in_plane(yz: np.ndarray) -> np.ndarray:
    return np.c_[np.full(len(yz), PLANE_X), yz]


def _make(name: str, yz: np.ndarray, count: int, dt: float,
          pen_down: np.ndarray | None = None) -> ReferencePath:
    positions, down = resample_polyline(_in_plane(yz), count, pen_down)
    wxyz = np.tile(TIP_TOWARDS_PLANE, (count, 1))
    return ReferencePath(name, positions, wxyz, dt, down)


def square_path(count: int = 150, dt: float = 0.1) -> ReferencePath:
    """A 1.0 m square (y ∈ [−0.5, 0.5] m, z ∈ [1.0, 2.0] m) with sharp corners, starting
    and ending at its lower-left corner."""
    corners = np.array([[-0.5, 1.0], [0.5, 1.0], [0.5, 2.0], [-0.5, 2.0], [-0.5, 1.0]])
    return _make("square", corners, count, dt)


def sine_path(count: int = 150, dt: float = 0.1) -> ReferencePath:
    """Two periods of z = 1.5 + 0.3·sin(2π·2s) m over y ∈ [−0.75, 0.75] m."""
    s = np.linspace(0.0, 1.0, 2000)
    yz = np.c_[-0.75 + 1.5 * s, 1.5 + 0.3 * np.sin(2 * np.pi * 2 * s)]
    return _make("sine", yz, count, dt)


def _letter_strokes() -> list[np.ndarray]:
    """The strokes of "ICRA" in (y, z), metres: letters 0.6 m tall (z ∈ [1.2, 1.8]),
    across y ∈ [−0.8, 0.8]."""
    bottom, top = 1.2, 1.8
    i_stroke = np.array([[-0.7, top], [-0.7, bottom]])
    angles = np.linspace(np.pi / 3, 2 * np.pi - np.pi / 3, 40)
    c_stroke = np.c_[-0.3 + 0.3 * np.cos(angles), 1.5 + 0.3 * np.sin(angles)]
    bowl = np.linspace(np.pi / 2, -np.pi / 2, 20)
    r_stroke = np.vstack([[[0.05, bottom], [0.05, top]],
                          np.c_[0.2 + 0.15 * np.cos(bowl), 1.65 + 0.15 * np.sin(bowl)],
                          [[0.05, 1.5], [0.35, bottom]]])
    a_stroke = np.array([[0.45, bottom], [0.625, top], [0.8, bottom]])
    a_bar = np.array([[0.5125, 1.5], [0.7375, 1.5]])
    return [i_stroke, c_stroke, r_stroke, a_stroke, a_bar]


def icra_path(count: int = 150, dt: float = 0.3) -> ReferencePath:
    """The letters "ICRA" (z ∈ [1.2, 1.8] m, y ∈ [−0.8, 0.8] m), stroke by stroke, joined
    by straight pen-up moves (``pen_down`` False) that the tip follows too."""
    points, down = [], []
    for k, stroke in enumerate(_letter_strokes()):
        if k:
            down.append(False)  # the move from the previous stroke's end to this start
        points.extend(stroke)
        down.extend([True] * (len(stroke) - 1))
    return _make("icra", np.array(points), count, dt, np.array(down))


SHAPES = {"square": square_path, "sine": sine_path, "icra": icra_path}


def write_bundled_paths(root: str | Path | None = None) -> list[Path]:
    """Write ``models/paths/{square,sine,icra}.json`` (150 waypoints each)."""
    root = Path(root) if root else models_root() / "paths"
    root.mkdir(parents=True, exist_ok=True)
    return [make().save(root / f"{name}.json") for name, make in SHAPES.items()]


if __name__ == "__main__":
    for written in write_bundled_paths():
        print(written)

from .._moved import moved_names  # noqa: E402 — the old addresses, for one release (CHANGELOG 2026-12-02)

__getattr__ = moved_names(__name__, {"load_path": "cr_nlp.tasks.readers",
                                     "checked_path": "cr_nlp.tasks.readers"})
