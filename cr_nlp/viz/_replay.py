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
        return (*self.tube(pos, rot), pos)

    def tube(self, pos: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tube vertices (V, 3) and tendon line segments (S, 2, 3), metres, around the
        backbone frames ``pos`` (1 + n·SAMPLES, 3) m and ``rot`` (…, 3, 3)."""
        x, y, z = tube_grid(pos, rot, self.robot.backbone_radius, around=AROUND)
        vertices = np.stack([x, y, z], -1).reshape(-1, 3)
        lines = [np.stack([p[:-1], p[1:]], 1) for p in tendon_paths(self.robot, pos, rot, SAMPLES)]
        return vertices, np.concatenate(lines)


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


def read_result(
    robot: Robot, data: Any, targets: Any = None, path: Any = None, source: str = ""
) -> list[Motion] | Answers:
    """The motions (trajectory, follow) or answers (ik) of a RESULT.json's content, read
    through the result protocol (``tasks._result``: the file's ``kind`` picks the class).

    Args:
        robot: the robot the result is for (its name must match the file's).
        data: the loaded JSON of ``cr-nlp ik``, ``plan`` or ``follow`` ``--out``.
        targets: for an ik result, the target poses ((positions (T, 3) m, wxyz (T, 4)));
            the ik result file holds the reached poses only.
        path: for a follow result, another reference path to draw (a file, a bundled name
            or a ``ReferencePath``) than the one the result holds.
        source: the file's name, for error messages.

    Raises:
        ResultFileError: (a ``ValueError``) naming ``source``: not a result (no or an
            unknown ``kind``), for another robot, or without what the viewer shows.
    """
    from ..tasks._result import ResultFileError, check_header, results_from_dict

    where = source or "the result"
    kind = check_header(data, where)
    if kind not in _READERS:
        raise ResultFileError(f"{where}: the viewer cannot show a {kind!r} result")
    results = results_from_dict(data, robot, source=source)
    try:
        return _READERS[kind](robot, results, targets=targets, path=path)
    except ValueError as exc:  # what the viewer needs of the result: name the file too
        raise ResultFileError(f"{where}: {exc}") from None


def _ik_answers(robot: Robot, results: list[Any], targets: Any = None, **_: Any) -> Answers:
    (result,) = results
    positions = wxyz = None
    if targets is not None:
        positions = np.asarray(targets[0], dtype=float).reshape(-1, 3)
        wxyz = np.asarray(targets[1], dtype=float).reshape(-1, 4)
        if len(positions) != len(result):
            raise ValueError(f"{len(positions)} targets for {len(result)} ik answers")
    straight = np.ravel([[0.0, 0.0, s.length_min] for s in robot.segments])
    solved = np.all(np.isfinite(result.q), axis=1)
    qs = np.where(solved[:, None], result.q, straight)
    reached = [
        (result.position[i], result.wxyz[i]) if np.all(np.isfinite(result.position[i])) else None
        for i in range(len(result))
    ]
    goal = [
        (positions[i], wxyz[i])
        if positions is not None and np.all(np.isfinite(positions[i]))
        else None
        for i in range(len(result))
    ]
    text = []
    for i in range(len(result)):
        clearance = _finite(result.min_clearance[i]) if result.has_scene else None
        text.append(
            f"answer {i}: "
            + _verdict_line(
                bool(result.success[i]),
                result.reason[i],
                result.stage_text[i],
                _finite(result.max_violation[i]),
            )
            + f"  \npose error: {_fmt(_finite(result.pose_error[i]))} (m/rad)"
            + f"  \nposition error: {_fmt(_mm(_finite(result.position_error[i])), ' mm')}"
            + f"  \nrotation error: {_fmt(_deg(_finite(result.rotation_error[i])), '°')}"
            + (
                f"  \nclearance: {_fmt(clearance, ' m')} (python-fcl)"
                if clearance is not None
                else ""
            )
        )
    ok = int(np.count_nonzero(result.success))
    return Answers(qs, reached, goal, text, f"ik: {ok}/{len(result)} answers succeed")


def _finite(x: Any) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def _mm(x: Any) -> Any:
    return None if x is None else 1e3 * x


def _deg(x: Any) -> Any:
    return None if x is None else float(np.degrees(x))


def _trajectory_motions(robot: Robot, results: list[Any], **_: Any) -> list[Motion]:

    motions = []
    for i, result in enumerate(results):
        if result.q is None:
            continue
        motions.append(
            _motion(
                robot,
                result,
                f"problem {i}",
                f"tip path: {_fmt(_finite(result.path_length), ' m')}",
            )
        )
    if not motions:
        raise ValueError(
            "the plan result has no trajectory to show (every problem failed "
            "before a trajectory existed)"
        )
    return motions


def _follow_motion(robot: Robot, results: list[Any], path: Any = None, **_: Any) -> list[Motion]:
    from ..tasks.readers import load_path

    (result,) = results
    reference = np.asarray(result.path.positions, dtype=float)
    if path is not None:
        reference = np.asarray(load_path(path).positions, dtype=float)
        if len(reference) != len(result.q):
            raise ValueError(
                f"the reference path has {len(reference)} waypoints, "
                f"the follow result {len(result.q)}"
            )
    err = 1e3 * result.position_error
    detail = f"position error: mean {np.nanmean(err):.3g} mm, max {np.nanmax(err):.3g} mm"
    return [_motion(robot, result, f"follow '{result.path.name}'", detail, reference)]


def _motion(
    robot: Robot, result: Any, label: str, detail: str, reference: Any = None
) -> Motion:
    """The motion of a trajectory or follow result, its verdict, ``detail`` and the
    minimum clearance as the summary."""
    from ..model.routing import tendon_names

    return Motion(
        label=label,
        q=result.q,
        times=result.times,
        tendon_lengths=np.asarray(result.tendon_lengths, dtype=float),
        tendon_names=tendon_names(robot),
        summary=f"{label}: "
        + _verdict_line(
            result.success, result.reason, result.stage_text, _finite(result.max_violation)
        )
        + f"  \n{detail}"
        + f"  \nmin clearance: {_fmt(_finite(result.min_clearance), ' m')}",
        reference=reference,
    )


_READERS = {"ik": _ik_answers, "trajectory": _trajectory_motions, "follow": _follow_motion}
"""Result kind → what the viewer shows of it."""


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
    from ..tasks.readers import read_targets

    positions, wxyz, _ = read_targets(path)
    return positions, wxyz
