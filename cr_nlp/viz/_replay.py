"""What the viewer replays, computed once, without viser: the robot's tube and tendon
lines at a configuration, the closest obstacle point of a motion, and the contents of the
result files of ``cr-nlp ik``, ``plan`` and ``follow``. Lengths in metres, angles in
radians, times in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import fcl
import numpy as np

from ..model import Robot
from ..model.kinematics import tip_pose as model_tip_pose
from ..model.rotations import wxyz_from_matrix
from ..world import Scene
from ..world.check import (
    body_chain,
    capsule_object,
    check_many,
    fcl_object,
    point_segment_distance,
)
from ..world.scene import bounding_sphere
from ._geometry import backbone_frames, tendon_paths, tube_grid

SAMPLES = 12
"""Backbone frames per segment of the drawn tube."""
AROUND = 16
"""Points around each ring of the drawn tube."""


# ================================================================ robot geometry


class RobotMesh:
    """The robot drawn as a tube (radius ``backbone_radius``) and its tendons' routing
    lines; the triangle list is fixed, the vertices follow q."""

    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        rings = 1 + robot.n_segments * SAMPLES
        i, j = np.meshgrid(np.arange(rings - 1), np.arange(AROUND - 1), indexing="ij")
        a, b = i * AROUND + j, (i + 1) * AROUND + j
        self.faces = np.concatenate(
            [
                np.stack([a, b, b + 1], -1).reshape(-1, 3),
                np.stack([a, b + 1, a + 1], -1).reshape(-1, 3),
            ]
        )

    def geometry(self, q: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tube vertices (V, 3), tendon line segments (S, 2, 3) and the backbone points
        (1 + n·SAMPLES, 3), metres, for q (3n; rad, rad, m)."""
        pos, rot = backbone_frames(self.robot, q, samples=SAMPLES)
        x, y, z = tube_grid(pos, rot, self.robot.backbone_radius, around=AROUND)
        vertices = np.stack([x, y, z], -1).reshape(-1, 3)
        lines = [np.stack([p[:-1], p[1:]], 1) for p in tendon_paths(self.robot, pos, rot, SAMPLES)]
        return vertices, np.concatenate(lines), pos


def tip_pose(robot: Robot, q: Any) -> tuple[np.ndarray, np.ndarray]:
    """Tip position (3,) m and orientation (4,) wxyz of q (3n), float64 (the model's
    public ``tip_pose``, with the rotation as a quaternion)."""
    position, rotation = model_tip_pose(robot, np.asarray(q, dtype=float))
    return position, wxyz_from_matrix(rotation[None])[0]


def closest_obstacle_points(
    robot: Robot, scene: Scene, qs: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each configuration of qs (T, 3n): the python-fcl distance (m) from the capsule
    body to the nearest obstacle part and the witness points on the robot and on the
    obstacle ((T, 3) each, m). Pairs are pruned by bounding-sphere lower bounds, so only
    the few pairs that can be nearest go to fcl."""
    qs = np.asarray(qs, dtype=float).reshape(-1, robot.dof)
    parts = scene.parts
    distance = np.full(len(qs), np.inf)
    on_robot = np.full((len(qs), 3), np.nan)
    on_obstacle = np.full((len(qs), 3), np.nan)
    if not parts:
        return distance, on_robot, on_obstacle
    objects = [fcl_object(p) for p in parts]
    spheres = [bounding_sphere(p) for p in parts]
    centres = np.array([c for c, _ in spheres], dtype=float)
    radii = np.array([r for _, r in spheres], dtype=float)
    r = robot.backbone_radius
    chains = body_chain(robot, qs)  # (T, K + 1, 3)
    a, b = chains[:, :-1], chains[:, 1:]
    lower = (
        point_segment_distance(centres[None, None], a[:, :, None], b[:, :, None]) - radii - r
    )  # (T, K, P)
    request = fcl.DistanceRequest(enable_nearest_points=True, enable_signed_distance=True)
    for t in range(len(qs)):
        flat = lower[t].ravel()
        for k in np.argsort(flat):
            if flat[k] > distance[t]:
                break
            piece, part = divmod(int(k), len(parts))
            result = fcl.DistanceResult()
            d = fcl.distance(
                capsule_object(a[t, piece], b[t, piece], r), objects[part], request, result
            )
            if d < distance[t]:
                distance[t] = d
                on_robot[t], on_obstacle[t] = result.nearest_points
    return distance, on_robot, on_obstacle


# ================================================================ results


@dataclass
class Motion:
    """A trajectory or followed path to replay, precomputed frame by frame."""

    label: str
    q: np.ndarray  # (T, 3n) rad, rad, m
    times: np.ndarray  # (T,) s
    tendon_lengths: np.ndarray  # (T, m) m
    tendon_names: list[str]
    summary: str  # the verdict, Markdown
    reference: np.ndarray | None = None  # (N, 3) m, the path to follow
    vertices: list[np.ndarray] = field(default_factory=list)
    tendon_lines: list[np.ndarray] = field(default_factory=list)
    tips: np.ndarray | None = None  # (T, 3) m
    clearance: np.ndarray | None = None  # (T,) m, python-fcl verdict distance
    closest: np.ndarray | None = None  # (T, 2, 3) m, robot and obstacle witness
    closest_name: list[str] = field(default_factory=list)

    @property
    def tendon_speeds(self) -> np.ndarray:
        """(T, m) m/s by central differences in time (one-sided at the ends)."""
        if len(self.times) < 2:
            return np.zeros_like(self.tendon_lengths)
        return np.gradient(self.tendon_lengths, self.times, axis=0)


@dataclass
class Answers:
    """IK answers to page through."""

    q: np.ndarray  # (K, 3n)
    reached: list[tuple[np.ndarray, np.ndarray] | None]
    targets: list[tuple[np.ndarray, np.ndarray] | None]
    text: list[str]
    summary: str


def _verdict_line(success: bool, reason: Any, stage: Any, max_violation: Any) -> str:
    state = "**success**" if success else f"**failed**: {reason or 'unknown reason'}"
    mv = "n/a" if max_violation is None else f"{max_violation:.2e}"
    return f"{state}  \nstage: {stage}  \nmax violation: {mv}"


def _fmt(x: Any, unit: str = "", digits: int = 4) -> str:
    return "n/a" if x is None else f"{x:.{digits}g}{unit}"


def _tendon_names(robot: Robot) -> list[str]:
    from ..tasks.trajectory import tendon_names

    return list(tendon_names(robot))


def read_result(
    robot: Robot, data: Any, targets: Any = None, path: Any = None
) -> list[Motion] | Answers:
    """The motions (plan, follow) or answers (ik) of a RESULT.json's content.

    Args:
        robot: the robot the result is for (its name must match the file's).
        data: the loaded JSON of ``cr-nlp ik``, ``plan`` or ``follow`` ``--out``.
        targets: for an ik result, the target poses ((positions (T, 3) m, wxyz (T, 4)));
            the ik result file holds the reached poses only.
        path: for a follow result, the reference path (a file, a bundled name or a
            ``ReferencePath``); default the result's ``path`` name where it resolves.

    Raises:
        ValueError: not such a result, or for another robot.
    """
    if not isinstance(data, dict):
        raise ValueError("a result must be a JSON object (cr-nlp ik, plan or follow --out)")
    name = data.get("robot")
    if name is not None and name != robot.name:
        raise ValueError(f"the result is for robot {name!r}, the viewer shows {robot.name!r}")
    rows = data.get("results")
    if isinstance(rows, list) and rows and isinstance(rows[0], dict) and "pose_error" in rows[0]:
        return _ik_answers(robot, rows, targets)
    if isinstance(rows, list) and (not rows or "times" in rows[0]):
        return _plan_motions(robot, rows)
    if "tip_positions" in data and "q" in data:
        return [_follow_motion(robot, data, path)]
    raise ValueError(
        "not a result of cr-nlp ik, plan or follow: expected 'results' rows "
        "with 'pose_error' (ik) or 'times' (plan), or 'q' and 'tip_positions' "
        "(follow)"
    )


def _ik_answers(robot: Robot, rows: list[dict], targets: Any) -> Answers:
    positions = wxyz = None
    if targets is not None:
        positions = np.asarray(targets[0], dtype=float).reshape(-1, 3)
        wxyz = np.asarray(targets[1], dtype=float).reshape(-1, 4)
        if len(positions) != len(rows):
            raise ValueError(f"{len(positions)} targets for {len(rows)} ik answers")
    qs, reached, goal, text = [], [], [], []
    straight = np.ravel([[0.0, 0.0, s.length_min] for s in robot.segments])
    for i, row in enumerate(rows):
        q = row.get("q")
        qs.append(np.asarray(q, dtype=float) if q is not None else straight)
        reached.append(
            (np.asarray(row["position"], float), np.asarray(row["wxyz"], float))
            if row.get("position") is not None
            else None
        )
        goal.append(
            (positions[i], wxyz[i])
            if positions is not None and np.all(np.isfinite(positions[i]))
            else None
        )
        clearance = row.get("clearance")
        text.append(
            f"answer {i}: "
            + _verdict_line(
                row.get("success", False),
                row.get("reason"),
                row.get("stage"),
                row.get("max_violation"),
            )
            + f"  \npose error: {_fmt(row.get('pose_error'))} (m/rad)"
            + f"  \nposition error: {_fmt(_mm(row.get('position_error')), ' mm')}"
            + f"  \nrotation error: {_fmt(_deg(row.get('rotation_error')), '°')}"
            + (
                f"  \nclearance: {_fmt(clearance, ' m')} (python-fcl)"
                if clearance is not None
                else ""
            )
        )
    ok = sum(bool(r.get("success")) for r in rows)
    return Answers(np.array(qs), reached, goal, text, f"ik: {ok}/{len(rows)} answers succeed")


def _mm(x: Any) -> Any:
    return None if x is None else 1e3 * x


def _deg(x: Any) -> Any:
    return None if x is None else float(np.degrees(x))


def _plan_motions(robot: Robot, rows: list[dict]) -> list[Motion]:
    motions = []
    names = _tendon_names(robot)
    for i, row in enumerate(rows):
        if row.get("q") is None:
            continue
        q = np.asarray(row["q"], dtype=float)
        motions.append(
            Motion(
                label=f"problem {i}",
                q=q,
                times=np.asarray(row["times"], dtype=float),
                tendon_lengths=np.asarray(row["tendon_lengths"], dtype=float).reshape(len(q), -1),
                tendon_names=names,
                summary=f"plan, problem {i}: "
                + _verdict_line(
                    row.get("success", False),
                    row.get("reason"),
                    row.get("stage"),
                    row.get("max_violation"),
                )
                + f"  \ntip path: {_fmt(row.get('path_length'), ' m')}"
                + f"  \nmin clearance: {_fmt(row.get('min_clearance'), ' m')}",
            )
        )
    if not motions:
        raise ValueError(
            "the plan result has no trajectory to show (every problem failed "
            "before a trajectory existed)"
        )
    return motions


def _follow_motion(robot: Robot, data: dict, path: Any = None) -> Motion:
    from ..model import ModelFileError
    from ..tasks.paths import load_path

    q = np.asarray(data["q"], dtype=float)
    reference = None
    if path is not None:
        reference = np.asarray(load_path(path).positions, dtype=float)
        if len(reference) != len(q):
            raise ValueError(
                f"the reference path has {len(reference)} waypoints, the follow result {len(q)}"
            )
    else:
        try:  # the result's path by name; a file not at hand: the tip trace still shows
            found = load_path(str(data.get("path")))
            if len(found.positions) == len(q):
                reference = np.asarray(found.positions, dtype=float)
        except (ModelFileError, OSError, ValueError):
            reference = None
    err = np.asarray(data.get("position_error_mm") or [np.nan], dtype=float)
    return Motion(
        label=f"follow '{data.get('path')}'",
        q=q,
        times=np.asarray(data.get("times") or np.arange(len(q)) * data["dt"], dtype=float),
        tendon_lengths=np.asarray(data["tendon_lengths"], dtype=float).reshape(len(q), -1),
        tendon_names=list(data.get("tendon_names") or _tendon_names(robot)),
        summary=f"follow '{data.get('path')}': "
        + _verdict_line(
            data.get("success", False),
            data.get("reason"),
            data.get("stage"),
            data.get("max_violation"),
        )
        + f"  \nposition error: mean {np.nanmean(err):.3g} mm, max {np.nanmax(err):.3g} mm"
        + f"  \nmin clearance: {_fmt(data.get('min_clearance'), ' m')}",
        reference=reference,
    )


def precompute(motion: Motion, mesh: RobotMesh, scene: Scene | None) -> None:
    """Every frame's geometry and clearance, once."""
    for q in motion.q:
        vertices, lines, points = mesh.geometry(q)
        motion.vertices.append(vertices.astype(np.float32))
        motion.tendon_lines.append(lines.astype(np.float32))
    motion.tips = model_tip_pose(mesh.robot, np.asarray(motion.q, dtype=float))[0]
    if scene is not None and scene.parts:
        verdict = check_many(mesh.robot, scene, motion.q)
        motion.clearance = np.asarray(verdict.obstacle_distance, dtype=float)
        motion.closest_name = list(verdict.closest)
        _, on_robot, on_obstacle = closest_obstacle_points(mesh.robot, scene, motion.q)
        motion.closest = np.stack([on_robot, on_obstacle], axis=1)


def targets_of(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Target poses of a targets file (``cr-nlp ik --targets``): positions (T, 3) m and
    wxyz (T, 4)."""
    from ..tasks.ik import read_targets

    positions, wxyz, _ = read_targets(path)
    return positions, wxyz
