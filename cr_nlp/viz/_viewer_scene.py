"""What the viewer (``viz.viewer``) draws of the world: its colours, and a scene's
obstacles (meshes, spheres, boxes, capsules, cylinders, convex parts) with the floor
grid and the robot's base frame, through viser's scene API (no import of viser here).
Lengths in metres.
"""

from __future__ import annotations

import socket
from typing import Any

import numpy as np

from ..model import Robot
from ..model.rotations import wxyz_from_matrix
from ..world import Scene
from ..world.scene import (
    BoxPart,
    CapsulePart,
    ConvexPart,
    CylinderPart,
    SpherePart,
    bounding_sphere,
    rotation_z_to,
)

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
"""Tendon colours in the plots."""


def add_scene(server: Any, robot: Robot, scene: Scene | None) -> None:
    """Draw ``scene``'s obstacles (meshes as they are, other obstacles part by part), a
    floor grid under the lowest of them and the robot's base, and the base frame."""
    scene_api = server.scene
    lowest = float(robot.base_position[2])
    if scene is not None:
        for k, obstacle in enumerate(scene.obstacles):
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
                lowest = min(lowest, add_part(scene_api, f"{name}/{j}", part))
    server.scene.add_grid(
        "/floor",
        width=6.0,
        height=6.0,
        cell_size=0.25,
        section_size=1.0,
        position=(0.0, 0.0, lowest),
    )
    server.scene.add_frame(
        "/base", axes_length=0.2, axes_radius=0.01, position=tuple(robot.base_position)
    )


def add_part(scene_api: Any, name: str, part: Any) -> float:
    """Draw one convex part; returns its lowest z (m)."""
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


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nobody listens on now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def camera_aim(robot: Robot, scene: Scene | None) -> tuple[tuple, tuple]:
    """The first camera's look-at point and position (m): the robot's reach, and the
    scene's parts where there are some."""
    reach = robot.total_length_max
    centre = np.asarray(robot.base_position, float) + np.array([0.4 * reach / 3.0, 0.0,
                                                                0.35 * reach])
    if scene is not None and scene.parts:
        centre = 0.5 * (centre + np.mean([bounding_sphere(p)[0] for p in scene.parts], axis=0))
    return tuple(centre), tuple(centre + np.array([-1.5, -2.0, 1.0]) * reach * 0.6)


def live_text(answer: Any) -> str:
    """The page's lines on a live-IK answer (``LiveIKResult``): verdict, time, pose error
    and clearance."""
    verdict = "**reached**" if answer.success else f"**not reached**: {answer.reason}"
    clearance = ("" if not np.isfinite(answer.min_clearance)
                 else f"  \nclearance {answer.min_clearance:.4f} m (python-fcl)")
    return (f"{verdict}  \nsolve {1e3 * answer.seconds:.1f} ms ({answer.stage})  \n"
            f"pose error {answer.pose_error:.2e} (m/rad){clearance}")
