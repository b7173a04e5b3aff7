"""The interactive 3-D viewer in the browser (viser): a scene, a robot, and a result of
``cr-nlp ik``, ``plan`` or ``follow`` to orbit and replay, and live IK by dragging a target.

Everything a replay shows is computed once when the viewer starts (the robot's tube and
tendons at every waypoint, the closest obstacle point, tendon speeds); scrubbing only
sends precomputed geometry. Live IK re-solves with ``tasks.live_ik.LiveIKSolver``,
warm-started from the answer on screen. Lengths in metres, angles in radians, times in
seconds.
"""

from __future__ import annotations

import contextlib
import io
import json
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

try:
    import viser
except ImportError as exc:  # the optional extra
    raise ImportError("the viewer needs viser: pip install 'cr_nlp[viewer]'") from exc

from ..model import Robot, load_robot
from ..model._ops import NUMPY
from ..model.kinematics import model_q_to_z, model_segment_frames
from ..model.rotations import wxyz_from_matrix
from ..world import Scene, load_scene
from ..world.check import capsule_object, check_many, fcl_object, point_segment_distance
from ..world.scene import (
    BoxPart,
    CapsulePart,
    ConvexPart,
    CylinderPart,
    SpherePart,
    bounding_sphere,
)
from ._geometry import backbone_frames, tendon_paths, tube_grid

ROBOT_RGB = (217, 95, 2)
TENDON_RGB = (31, 120, 180)
OBSTACLE_RGB = (127, 143, 166)
MESH_RGB = (200, 167, 126)
REFERENCE_RGB = (227, 26, 28)
TRACE_RGB = (255, 127, 0)
CLOSEST_RGB = (200, 0, 120)
PALETTE = [
    "#1b9e77",
    "#d95f02",
    "#7570b3",
    "#e7298a",
    "#66a61e",
    "#e6ab02",
    "#a6761d",
    "#666666",
    "#1f78b4",
    "#b2df8a",
    "#fb9a99",
    "#cab2d6",
]
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
    """Tip position (3,) m and orientation (4,) wxyz of q (3n), float64."""
    rot, pos = model_segment_frames(NUMPY, robot, model_q_to_z(NUMPY, robot, np.asarray(q, float)))[
        -1
    ]
    matrix = np.array([float(v) for v in rot]).reshape(3, 3)
    return np.array([float(v) for v in pos]), wxyz_from_matrix(matrix[None])[0]


def closest_obstacle_points(
    robot: Robot, scene: Scene, qs: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each configuration of qs (T, 3n): the python-fcl distance (m) from the capsule
    body to the nearest obstacle part and the witness points on the robot and on the
    obstacle ((T, 3) each, m). Pairs are pruned by bounding-sphere lower bounds, so only
    the few pairs that can be nearest go to fcl."""
    import fcl

    from ..world.check import body_chain

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


def _precompute(motion: Motion, mesh: RobotMesh, scene: Scene | None) -> None:
    """Every frame's geometry and clearance, once."""
    for q in motion.q:
        vertices, lines, points = mesh.geometry(q)
        motion.vertices.append(vertices.astype(np.float32))
        motion.tendon_lines.append(lines.astype(np.float32))
    motion.tips = np.array([tip_pose(mesh.robot, q)[0] for q in motion.q])
    if scene is not None and scene.parts:
        verdict = check_many(mesh.robot, scene, motion.q)
        motion.clearance = np.asarray(verdict.obstacle_distance, dtype=float)
        motion.closest_name = list(verdict.closest)
        _, on_robot, on_obstacle = closest_obstacle_points(mesh.robot, scene, motion.q)
        motion.closest = np.stack([on_robot, on_obstacle], axis=1)


# ================================================================ the viewer


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nobody listens on now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class Viewer:
    """A viser server showing a robot, a scene and a result; ``url`` is its address.

    Args:
        robot: a ``Robot``, a robot file or a bundled name ("tdcr3").
        scene: a ``Scene``, a scene file or bundled name, or None.
        result: a RESULT.json path of ``cr-nlp ik``, ``plan`` or ``follow``, its loaded
            content, or None (the robot straight, with live IK).
        port: TCP port; None picks a free one.
        host: the address to listen on (default localhost only).
        targets: for an ik result, the target poses (positions (T, 3) m, wxyz (T, 4)),
            drawn beside the reached ones.
        path: for a follow result, its reference path (file, bundled name or
            ``ReferencePath``) when the result's path name does not resolve.
        live_ik: offer live IK (a target gizmo; re-solves on every move).
        q: the configuration to show without a result (default straight).
    """

    def __init__(
        self,
        robot: Robot | str | Path,
        scene: Scene | str | Path | None = None,
        result: Any = None,
        port: int | None = None,
        *,
        host: str = "127.0.0.1",
        targets: Any = None,
        path: Any = None,
        live_ik: bool = True,
        q: Any = None,
    ) -> None:
        self.robot = load_robot(robot if not isinstance(robot, Path) else str(robot))
        self.scene = (
            load_scene(scene if not isinstance(scene, Path) else str(scene))
            if scene is not None and not isinstance(scene, Scene)
            else scene
        )
        if isinstance(result, str | Path):
            result = json.loads(Path(result).read_text())
        content = read_result(self.robot, result, targets, path) if result is not None else None
        self.motions: list[Motion] = content if isinstance(content, list) else []
        self.answers: Answers | None = content if isinstance(content, Answers) else None
        self._mesh = RobotMesh(self.robot)
        for motion in self.motions:
            _precompute(motion, self._mesh, self.scene)
        straight = np.ravel([[0.0, 0.0, s.length_min] for s in self.robot.segments])
        self.q = (
            self.robot.full_q(np.ravel(q))
            if q is not None
            else self.motions[0].q[0]
            if self.motions
            else self.answers.q[0]
            if self.answers is not None
            else straight
        )
        """The configuration on screen (3n; rad, rad, m)."""
        self.last_live: Any = None
        """The last live-IK answer (``tasks.live_ik.LiveIKResult``), None before."""

        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: we print the url
            self.server = viser.ViserServer(
                host=host, port=free_port(host) if port is None else int(port), verbose=False
            )
        self.port = self.server.get_port()
        """The TCP port served (viser takes the next free one if ``port`` is taken)."""
        self.url = f"http://{host}:{self.port}"
        """The page's address."""
        self._motion = self.motions[0] if self.motions else None
        self._frame = 0
        self._stop = threading.Event()
        self._solve_lock = threading.Lock()
        self._solver_lock = threading.Lock()
        self._pending: tuple[np.ndarray, np.ndarray, bool] | None = None
        self._live_solver: Any = None
        self._live_on = live_ik and not self.motions and self.answers is None

        try:
            self._build_page(live_ik)
        except BaseException:
            self.server.stop()
            raise
        self._player = threading.Thread(target=self._play_loop, daemon=True)
        self._player.start()
        self._wake = threading.Event()
        self._solving = threading.Thread(target=self._live_loop, daemon=True)
        if live_ik:
            self._solving.start()
        # Not a daemon: a compile cut off at interpreter exit aborts the process.
        self._warming = threading.Thread(target=self._warm_up) if live_ik else None
        if self._warming is not None:
            self._warming.start()

    def _build_page(self, live_ik: bool) -> None:
        """The scene, the robot, the controls and the camera."""
        self.server.scene.set_up_direction("+z")
        self._add_scene()
        self._add_robot()
        self._add_gui(live_ik)
        self._aim_camera()
        if self._motion is not None:
            self.show_frame(0)
        elif self.answers is not None:
            self.show_answer(0)

    # ------------------------------------------------------------ scene
    def _add_scene(self) -> None:
        scene_api = self.server.scene
        lowest = float(self.robot.base_position[2])
        if self.scene is not None:
            for k, obstacle in enumerate(self.scene.obstacles):
                name = f"/scene/{k}_{obstacle.name}".replace(" ", "_")
                if obstacle.mesh is not None:
                    vertices = np.asarray(obstacle.mesh.vertices, dtype=float)
                    scene_api.add_mesh_simple(
                        name,
                        vertices,
                        np.asarray(obstacle.mesh.faces),
                        color=MESH_RGB,
                        side="double",
                    )
                    lowest = min(lowest, float(vertices[:, 2].min()))
                    continue
                for j, part in enumerate(obstacle.parts):
                    lowest = min(lowest, self._add_part(f"{name}/{j}", part))
        self.server.scene.add_grid(
            "/floor",
            width=6.0,
            height=6.0,
            cell_size=0.25,
            section_size=1.0,
            position=(0.0, 0.0, lowest),
        )
        self.server.scene.add_frame(
            "/base", axes_length=0.2, axes_radius=0.01, position=tuple(self.robot.base_position)
        )

    def _add_part(self, name: str, part: Any) -> float:
        """Draw one convex part; returns its lowest z (m)."""
        scene_api = self.server.scene
        if isinstance(part, SpherePart):
            scene_api.add_icosphere(
                name, radius=float(part.radius), color=OBSTACLE_RGB, position=tuple(part.center)
            )
            return float(part.center[2] - part.radius)
        if isinstance(part, BoxPart):
            wxyz = wxyz_from_matrix(np.asarray(part.rotation, float)[None])[0]
            scene_api.add_box(
                name,
                color=OBSTACLE_RGB,
                dimensions=tuple(2.0 * np.asarray(part.half_size)),
                wxyz=tuple(wxyz),
                position=tuple(part.center),
            )
            corners = np.abs(np.asarray(part.rotation)) @ np.asarray(part.half_size)
            return float(part.center[2] - corners[2])
        if isinstance(part, CapsulePart | CylinderPart):
            a, b = np.asarray(part.a, float), np.asarray(part.b, float)
            from ..world.scene import rotation_z_to

            wxyz = wxyz_from_matrix(rotation_z_to(b - a)[None])[0]
            scene_api.add_cylinder(
                name,
                radius=float(part.radius),
                height=float(np.linalg.norm(b - a)),
                color=OBSTACLE_RGB,
                wxyz=tuple(wxyz),
                position=tuple(0.5 * (a + b)),
            )
            if isinstance(part, CapsulePart):
                for end, p in (("a", a), ("b", b)):
                    scene_api.add_icosphere(
                        f"{name}_{end}",
                        radius=float(part.radius),
                        color=OBSTACLE_RGB,
                        position=tuple(p),
                    )
            return float(min(a[2], b[2]) - part.radius)
        if isinstance(part, ConvexPart):
            scene_api.add_mesh_simple(
                name,
                np.asarray(part.vertices, float),
                np.asarray(part.triangles),
                color=OBSTACLE_RGB,
                flat_shading=True,
            )
            return float(np.min(part.vertices[:, 2]))
        raise TypeError(f"not a scene part: {type(part).__name__}")

    def _add_robot(self) -> None:
        vertices, lines, _ = self._mesh.geometry(self.q)
        scene_api = self.server.scene
        self._body = scene_api.add_mesh_simple(
            "/robot/body", vertices, self._mesh.faces, color=ROBOT_RGB, opacity=0.55, side="double"
        )
        self._tendons = scene_api.add_line_segments(
            "/robot/tendons", lines, TENDON_RGB, thickness=0.006
        )
        motion = self._motion
        self._trace = self._reference = self._closest = self._closest_dot = None
        if motion is not None:
            self._add_motion_lines(motion)
        self._target_frame = self._reached_frame = None
        if self.answers is not None:
            self._target_frame = scene_api.add_frame(
                "/ik/target", axes_length=0.2, axes_radius=0.012, visible=False
            )
            self._reached_frame = scene_api.add_frame(
                "/ik/reached", axes_length=0.12, axes_radius=0.02, visible=False
            )

    def _add_motion_lines(self, motion: Motion) -> None:
        scene_api = self.server.scene
        tips = motion.tips if motion.tips is not None else np.zeros((1, 3))
        if len(tips) > 1:
            self._trace = scene_api.add_line_segments(
                "/motion/tip_trace", np.stack([tips[:-1], tips[1:]], 1), TRACE_RGB, thickness=0.012
            )
        if motion.reference is not None and len(motion.reference) > 1:
            ref = motion.reference
            self._reference = scene_api.add_line_segments(
                "/motion/reference",
                np.stack([ref[:-1], ref[1:]], 1),
                REFERENCE_RGB,
                thickness=0.008,
            )
        if motion.closest is not None:
            self._closest = scene_api.add_line_segments(
                "/motion/closest",
                motion.closest[:1].astype(np.float32),
                CLOSEST_RGB,
                thickness=0.015,
            )
            self._closest_dot = scene_api.add_icosphere(
                "/motion/closest_point",
                radius=0.03,
                color=CLOSEST_RGB,
                position=tuple(motion.closest[0, 1]),
            )

    def _aim_camera(self) -> None:
        reach = self.robot.total_length_max
        base = np.asarray(self.robot.base_position, float)
        centre = base + np.array([0.4 * reach / 3.0, 0.0, 0.35 * reach])
        if self.scene is not None and self.scene.parts:
            centre = 0.5 * (
                centre + np.mean([bounding_sphere(p)[0] for p in self.scene.parts], axis=0)
            )
        camera = self.server.initial_camera
        camera.look_at = tuple(centre)
        camera.position = tuple(centre + np.array([-1.5, -2.0, 1.0]) * reach * 0.6)

    # ------------------------------------------------------------ GUI
    def _add_gui(self, live_ik: bool) -> None:
        gui = self.server.gui
        scene_name = self.scene.name if self.scene is not None else "no scene"
        gui.add_markdown(f"**cr_nlp** · robot `{self.robot.name}` · scene `{scene_name}`")
        self._summary = gui.add_markdown("")
        self._status = gui.add_markdown("")
        if self.motions:
            if len(self.motions) > 1:
                choice = gui.add_dropdown(
                    "motion", [m.label for m in self.motions], initial_value=self.motions[0].label
                )

                @choice.on_update
                def _(_: Any) -> None:
                    self.select_motion([m.label for m in self.motions].index(choice.value))

            count = len(self.motions[0].q)
            self._time = gui.add_slider(
                "waypoint", min=0, max=max(count - 1, 1), step=1, initial_value=0
            )

            @self._time.on_update
            def _(_: Any) -> None:
                if int(self._time.value) != self._frame:
                    self.show_frame(int(self._time.value))

            controls = gui.add_button_group("replay", ["play", "pause"])

            @controls.on_click
            def _(_: Any) -> None:
                self.playing = controls.value == "play"

            self._speed = gui.add_slider("speed ×", min=0.25, max=4.0, step=0.25, initial_value=1.0)
            self.playing = False
            self._length_plot = self._speed_plot = None
            self._add_plots(self.motions[0])
        if self.answers is not None:
            count = len(self.answers.q)
            self._answer = gui.add_slider(
                "answer", min=0, max=max(count - 1, 1), step=1, initial_value=0, disabled=count < 2
            )

            @self._answer.on_update
            def _(_: Any) -> None:
                self.show_answer(int(self._answer.value))

        self._live_gizmo = None
        if live_ik:
            with gui.add_folder("live IK"):
                self._live_box = gui.add_checkbox(
                    "drag the target",
                    self._live_on,
                    hint="a gizmo at the tip; moving it re-solves from the answer shown",
                )
                self._exact_box = gui.add_checkbox("exact (Ipopt polish)", False)
                self._live_text = gui.add_markdown("")

            @self._live_box.on_update
            def _(_: Any) -> None:
                self.set_live(bool(self._live_box.value))

            self.set_live(self._live_on)

    def _add_plots(self, motion: Motion) -> None:
        gui = self.server.gui
        series: tuple[Any, ...] = ({"label": "t (s)"},) + tuple(
            {"label": name, "stroke": PALETTE[j % len(PALETTE)], "width": 1.5}
            for j, name in enumerate(motion.tendon_names)
        )
        scales = {"x": {"time": False}}
        data = (motion.times, *motion.tendon_lengths.T)
        self._length_plot = gui.add_uplot(
            data, series, title="tendon lengths (m)", scales=scales, aspect=1.6
        )
        speeds = (motion.times, *motion.tendon_speeds.T)
        self._speed_plot = gui.add_uplot(
            speeds, series, title="tendon speeds (m/s)", scales=scales, aspect=1.6
        )

    # ------------------------------------------------------------ replay
    def select_motion(self, index: int) -> None:
        """Show motion ``index`` (a plan result's problem) from its first waypoint."""
        motion = self.motions[index]
        self._motion = motion
        for handle in (self._trace, self._reference, self._closest, self._closest_dot):
            if handle is not None:
                handle.remove()
        self._trace = self._reference = self._closest = self._closest_dot = None
        self._add_motion_lines(motion)
        self._time.max = max(len(motion.q) - 1, 1)
        if self._length_plot is not None:
            self._length_plot.data = (motion.times, *motion.tendon_lengths.T)
            self._speed_plot.data = (motion.times, *motion.tendon_speeds.T)
        self.show_frame(0)

    def show_frame(self, k: int) -> None:
        """Show waypoint k of the current motion (precomputed: nothing is solved)."""
        motion = self._motion
        if motion is None:
            raise ValueError("no motion to show: the viewer has no plan or follow result")
        k = int(np.clip(k, 0, len(motion.q) - 1))
        self._frame = k
        self.q = motion.q[k]
        with self.server.atomic():
            self._body.vertices = motion.vertices[k]
            self._tendons.points = motion.tendon_lines[k]
            if motion.closest is not None and self._closest is not None:
                if np.all(np.isfinite(motion.closest[k])):
                    self._closest.points = motion.closest[k : k + 1].astype(np.float32)
                    self._closest_dot.position = tuple(motion.closest[k, 1])
            if int(self._time.value) != k:
                self._time.value = k
        self._summary.content = motion.summary
        speeds = motion.tendon_speeds[k]
        lines = [f"t = {motion.times[k]:.2f} s (waypoint {k} of {len(motion.q) - 1})"]
        if motion.clearance is not None:
            lines.append(
                f"clearance {motion.clearance[k]:.4f} m to "
                f"`{motion.closest_name[k] or '-'}` (python-fcl)"
            )
        lines.append(f"fastest tendon {np.max(np.abs(speeds)):.3f} m/s")
        self._status.content = "  \n".join(lines)
        if self._live_gizmo is not None:
            self._place_gizmo()

    @property
    def playing(self) -> bool:
        """Whether the replay advances by itself."""
        return self._playing

    @playing.setter
    def playing(self, value: bool) -> None:
        self._playing = bool(value)

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            motion = self._motion
            if motion is None or not getattr(self, "_playing", False) or self._live_on:
                self._stop.wait(0.1)
                continue
            dt = float(np.median(np.diff(motion.times))) if len(motion.times) > 1 else 0.1
            self._stop.wait(max(dt / float(self._speed.value), 0.02))
            self.show_frame((self._frame + 1) % len(motion.q))

    # ------------------------------------------------------------ ik answers
    def show_answer(self, i: int) -> None:
        """Show IK answer i with its target and reached frames and its verdict."""
        answers = self.answers
        if answers is None:
            raise ValueError("no ik answers to show: the viewer has no ik result")
        i = int(np.clip(i, 0, len(answers.q) - 1))
        self._show_q(answers.q[i])
        for handle, pose in (
            (self._target_frame, answers.targets[i]),
            (self._reached_frame, answers.reached[i]),
        ):
            handle.visible = pose is not None
            if pose is not None:
                handle.position, handle.wxyz = tuple(pose[0]), tuple(pose[1])
        self._summary.content = answers.summary
        self._status.content = answers.text[i]
        if int(self._answer.value) != i:
            self._answer.value = i
        if self._live_gizmo is not None:
            self._place_gizmo()

    def _show_q(self, q: np.ndarray) -> None:
        self.q = np.asarray(q, dtype=float)
        vertices, lines, _ = self._mesh.geometry(self.q)
        with self.server.atomic():
            self._body.vertices = vertices.astype(np.float32)
            self._tendons.points = lines.astype(np.float32)

    # ------------------------------------------------------------ live IK
    def set_live(self, on: bool) -> None:
        """Turn live IK on (a target gizmo at the tip of the robot shown) or off.

        Raises:
            ValueError: the viewer was made with ``live_ik=False``.
        """
        if not hasattr(self, "_live_box"):
            raise ValueError("this viewer has no live IK (made with live_ik=False)")
        self._live_on = bool(on)
        if bool(self._live_box.value) != self._live_on:
            self._live_box.value = self._live_on
        if on and self._live_gizmo is None:
            self._live_gizmo = self.server.scene.add_transform_controls(
                "/live/target", scale=0.35, depth_test=False
            )
            self._place_gizmo()

            @self._live_gizmo.on_update
            async def _(event: Any) -> None:
                # On viser's event loop, so poses arrive in the drag's order; the solving
                # thread takes the newest. The slow fallback search only where a drag ends.
                self.target_moved(
                    event.target.position,
                    event.target.wxyz,
                    getattr(event, "phase", "end") == "end",
                )
        elif not on and self._live_gizmo is not None:
            self._live_gizmo.remove()
            self._live_gizmo = None
            if self._motion is not None:
                self.show_frame(self._frame)
            elif self.answers is not None:
                self.show_answer(int(self._answer.value))

    def _place_gizmo(self) -> None:
        position, wxyz = tip_pose(self.robot, self.q)
        self._live_gizmo.position, self._live_gizmo.wxyz = tuple(position), tuple(wxyz)

    def target_moved(self, position: Any, wxyz: Any, final: bool) -> None:
        """The gizmo's callback: queue the target pose (position (3,) m, wxyz (4,)) for
        the solving thread and return at once. A drag sends poses faster than they can
        be solved: only the newest waiting one is solved. ``final``: the drag ended, so
        a miss may run the slow fallback search."""
        self._pending = (np.array(position, float), np.array(wxyz, float), bool(final))
        self._wake.set()

    def _live_loop(self) -> None:
        """The solving thread: the newest queued target, one at a time."""
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            pose, self._pending = self._pending, None
            if pose is not None:
                with self._solve_lock:
                    self._live_update(*pose)

    def solver(self) -> Any:
        """The live-IK solver (``tasks.live_ik.LiveIKSolver``), built on first use."""
        with self._solver_lock:
            if self._live_solver is None:
                from ..tasks.live_ik import LiveIKSolver

                self._live_solver = LiveIKSolver(self.robot, self.scene)
            return self._live_solver

    def _warm_up(self) -> None:
        """Compile the live-IK program in the background, so the first drag is fast."""
        with self._solve_lock:
            self._live_text.content = "compiling the live-IK solver (once, cached on disk)…"
            try:
                position, wxyz = tip_pose(self.robot, self.q)
                seconds = self.solver().solve(self.q, position, wxyz, search=False).seconds
            except Exception as exc:  # shown, never fatal: the replay works without it
                if not self._stop.is_set():
                    self._live_text.content = f"live IK unavailable: {exc}"
                return
            if self.last_live is None and not self._stop.is_set():
                self._live_text.content = f"ready (first solve {seconds:.1f} s)"

    def move_target(
        self, position: Any, wxyz: Any, exact: bool | None = None, search: bool = True
    ) -> Any:
        """What moving the gizmo does: re-solve IK for the target pose from the answer
        on screen, show the new answer and its verdict; returns the ``LiveIKResult``
        (None for an invalid target, reported on the page).

        Args:
            position: (3,) target tip position, m.
            wxyz: (4,) target orientation, unit quaternion.
            exact: polish with Ipopt; None: the page's checkbox.
            search: fall back to the batched search when the warm start misses (the
                gizmo does so where a drag ends, not during it).
        """
        with self._solve_lock:
            return self._live_update(
                np.asarray(position, float), np.asarray(wxyz, float), search, exact
            )

    def _live_update(
        self, position: np.ndarray, wxyz: np.ndarray, search: bool, exact: bool | None = None
    ) -> Any:
        if exact is None:
            exact = bool(getattr(self, "_exact_box", None) and self._exact_box.value)
        try:
            answer = self.solver().solve(self.q, position, wxyz, exact=exact, search=search)
        except ValueError as exc:  # an unreachable or invalid target: say so, keep the robot
            if hasattr(self, "_live_text"):
                self._live_text.content = f"target rejected: {exc}"
            return None
        self.last_live = answer
        self._show_q(answer.q)
        verdict = "**reached**" if answer.success else f"**not reached**: {answer.reason}"
        clearance = (
            ""
            if not np.isfinite(answer.clearance)
            else f"  \nclearance {answer.clearance:.4f} m (python-fcl)"
        )
        if hasattr(self, "_live_text"):
            self._live_text.content = (
                f"{verdict}  \nsolve {1e3 * answer.seconds:.1f} ms ({answer.stage})  \n"
                f"pose error {answer.pose_error:.2e} (m/rad){clearance}"
            )
        return answer

    # ------------------------------------------------------------ lifetime
    def wait(self) -> None:
        """Block until Ctrl-C, then stop the server."""
        try:
            while not self._stop.is_set():
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()
            if self._warming is not None and self._warming.is_alive():
                print("waiting for the live-IK compile to finish…", file=sys.stderr)
                self._warming.join()

    def stop(self) -> None:
        """Stop the replay and solving threads and the server (the port is free
        afterwards)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._wake.set()
        if self._solving.is_alive() and self._solving is not threading.current_thread():
            self._solving.join(timeout=60)  # a solve in progress ends in milliseconds
        self.server.stop()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *_: Any) -> None:
        self.stop()


def targets_of(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Target poses of a targets file (``cr-nlp ik --targets``): positions (T, 3) m and
    wxyz (T, 4)."""
    from ..tasks.ik import read_targets

    positions, wxyz, _ = read_targets(path)
    return positions, wxyz
