"""The geometry the figures and the viewer draw, in numpy (no plotting library): frames
along the backbone, the tube around it, the tendons' routing lines, box faces. Lengths in
metres, angles in radians.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..model._ops import NUMPY
from ..model.kinematics import (
    model_q_to_z,
    model_segment_frames,
    model_segment_transform,
)
from ..model.lie import transform_compose
from ..model.robot import Robot
from ..model.routing import routing_of
from ..world.scene import BoxPart


def backbone_frames(robot: Robot, q: Any, samples: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Frames along the backbone for drawing: positions (M, 3) m and rotations (M, 3, 3),
    the base followed by ``samples`` frames per segment (M = 1 + n·samples)."""
    q = np.asarray(q, dtype=float).reshape(robot.dof)
    z = model_q_to_z(NUMPY, robot, q)
    frames = model_segment_frames(NUMPY, robot, z)
    s = np.arange(1, samples + 1) / samples
    positions = [np.asarray(frames[0][1], dtype=float)[None]]
    rotations = [np.asarray(frames[0][0], dtype=float).reshape(1, 3, 3)]
    for i in range(robot.n_segments):
        ux, uy, length = z[3 * i : 3 * i + 3]
        with np.errstate(invalid="ignore", divide="ignore"):  # unused safe_where branch
            local = model_segment_transform(NUMPY, ux * s, uy * s, length * s)
        rot, pos = transform_compose(frames[i], local)
        positions.append(np.stack(np.broadcast_arrays(*pos), axis=-1))
        rotations.append(np.stack(np.broadcast_arrays(*rot), axis=-1).reshape(-1, 3, 3))
    return np.concatenate(positions), np.concatenate(rotations)


def tube_grid(
    positions: np.ndarray, rotations: np.ndarray, radius: float, around: int = 16
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    angle = np.linspace(0.0, 2.0 * np.pi, around)
    ring = (
        np.cos(angle)[None, :, None] * rotations[:, None, :, 0]
        + np.sin(angle)[None, :, None] * rotations[:, None, :, 1]
    )
    surface = positions[:, None, :] + radius * ring
    return surface[..., 0], surface[..., 1], surface[..., 2]


def tendon_paths(
    robot: Robot, positions: np.ndarray, rotations: np.ndarray, samples: int
) -> list[np.ndarray]:
    """Polylines of every tendon (m), at the routing radius in each cross-section, from
    the base to the end of the segment it ends at (``positions`` (1 + n·samples, 3) and
    ``rotations`` from ``backbone_frames``)."""
    routing = routing_of(robot)
    alpha = routing.angles(robot.tendons.offsets)   # (T, n)
    r = robot.tendons.radius
    paths = []
    for t, anchor in enumerate(routing.anchor):
        index = np.arange(1 + (anchor + 1) * samples)
        segment = np.maximum(index - 1, 0) // samples
        local = np.stack([np.cos(alpha[t, segment]), np.sin(alpha[t, segment])], axis=-1) * r
        rot = rotations[index]
        paths.append(positions[index] + local[:, :1] * rot[:, :, 0] + local[:, 1:] * rot[:, :, 1])
    return paths


def box_faces(part: BoxPart) -> np.ndarray:
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    corners = part.center + (signs * part.half_size) @ part.rotation.T
    quads = [[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]]
    return corners[np.array(quads)]
