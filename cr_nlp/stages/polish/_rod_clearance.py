"""The clearance rows of a solved Cosserat backbone in a tension-space exact stage (IK and
motions): body spheres of ``backbone_radius`` at the rod's grid points and along its
chords (the capsule chain the verdict checks: IK the midpoints, a motion more), one row
``d ≥ δ'`` per (sphere, nearby obstacle part) pair and per nearby self pair (spheres on
segments at least two apart), in the pair slots of ``stages.polish._clearance_rows``. δ' is
the margin plus the most the capsule chain can come nearer than its spheres. Units: metres.

One ``RodClearance`` serves one rod; a motion's NLP calls ``rows`` once per rod (each call
makes its own slot parameters) and selects each rod's slots from its own distances.
"""

from __future__ import annotations

import math
from typing import Any

import casadi as ca
import numpy as np

from ...model import Robot
from ...model._ops import NUMPY
from ...world.clearance import kind_distances, scene_arrays
from ...world.scene import Scene
from ._clearance_rows import SlotGroup, make_slot_groups, select_slots, slot_distance


def _bodies(s: np.ndarray, per_step: int = 2) -> tuple[np.ndarray, np.ndarray, float]:
    """For grid points at arc lengths ``s`` (S+1,) m: (the body matrix A (N × (S+1)) giving
    the sphere centres from the points: the points, then ``per_step − 1`` evenly spaced
    points inside each chord, chord after chord (2: the chords' midpoints); each sphere's
    arc length (N,) m; the largest spacing of neighbouring spheres, m)."""
    count = len(s)
    inner = np.arange(1, per_step) / per_step
    a = np.zeros((count + (count - 1) * len(inner), count))
    a[np.arange(count), np.arange(count)] = 1.0
    rows = count + np.arange((count - 1) * len(inner))
    chord = np.repeat(np.arange(count - 1), len(inner))
    fraction = np.tile(inner, count - 1)
    a[rows, chord], a[rows, chord + 1] = 1.0 - fraction, fraction
    arc = a @ s
    return a, arc, float(np.max(np.diff(s))) / per_step


def _self_table(robot: Robot, arc: np.ndarray) -> np.ndarray:
    """(M, 2) sphere pairs on segments at least two apart, a sphere at a junction counted
    on both of its segments (as ``world.clearance.self_pairs`` counts the PCC body: the
    verdict's pieces of segments two apart end there); none when the robot file turns
    self-collision off."""
    if not robot.has_self_pairs:
        return np.zeros((0, 2), dtype=np.int64)
    ends = np.cumsum([0.0] + [seg.length_min for seg in robot.segments])
    lo = np.searchsorted(ends, arc - 1e-12, side="right") - 1   # first segment holding it
    hi = np.searchsorted(ends, arc + 1e-12, side="left") - 1    # last one
    lo, hi = np.clip(lo, 0, len(robot.segments) - 1), np.clip(hi, 0, len(robot.segments) - 1)
    i, j = np.triu_indices(len(arc), 1)
    far = (hi[j] - lo[i] >= 2) | (hi[i] - lo[j] >= 2)
    return np.stack([i[far], j[far]], axis=1).astype(np.int64)


class RodClearance:
    """The clearance rows of one rod's backbone (robot's grid points, base frame).

    Args:
        robot: the robot (its base pose, backbone radius, segments).
        scene: the obstacles, or None (self pairs only).
        arc_length: (S+1,) arc lengths of the rod's grid points, m.
        margin: δ, m: what the verdict's capsule chain must keep.
        max_pairs: slots per group (per part kind, and for self pairs).
        near_margin: pairs farther than this (m) at the start get no slot.
        face_smoothing: μ of the max over a convex part's faces, m.
        per_step: spheres per chord of the grid (its start point and ``per_step − 1``
            inside it): the more, the nearer δ' is to δ.
    """

    def __init__(self, robot: Robot, scene: Scene | None, arc_length: np.ndarray,
                 margin: float, max_pairs: int, near_margin: float,
                 face_smoothing: float, per_step: int = 2) -> None:

        self.robot, self.near_margin, self.smoothing = robot, near_margin, face_smoothing
        self.body_matrix, arc, spacing = _bodies(np.asarray(arc_length, dtype=float),
                                                 per_step)
        r = robot.backbone_radius
        # How much nearer the capsule chain can come than its spheres (world.clearance).
        gap = max(math.sqrt(r * r + spacing ** 2 / 4) - r,
                  math.sqrt(4 * r * r + spacing ** 2 / 2) - 2 * r)
        self.row_margin = float(margin) + gap
        self.n_bodies = len(arc)
        self.self_table = _self_table(robot, arc)
        groups, _ = make_slot_groups(robot, scene, max_pairs, include_self=False)
        self.groups = [SlotGroup(g.kind, min(max_pairs, len(g.table) * self.n_bodies),
                                 g.first, g.table, g.faces) for g in groups]
        if len(self.self_table):
            self.groups.append(SlotGroup("self", min(max_pairs, len(self.self_table)), 0,
                                         np.zeros((0, 0))))
        self.arrays = scene_arrays(scene, as_numpy=True) if scene is not None else None
        self.base_rot = robot.base_rotation
        self.base_pos = np.asarray(robot.base_position, dtype=float)

    @property
    def rows_count(self) -> int:
        """Clearance rows of one rod (the slots of every group)."""
        return sum(g.capacity for g in self.groups)

    def centres(self, positions: Any) -> Any:
        """Sphere centres (N × 3, world frame, m) of the robot's grid points (3 × (S+1),
        base frame, m), symbolic or numeric."""
        world = ca.mtimes(ca.DM(self.base_rot), ca.mtimes(positions,
                                                            ca.DM(self.body_matrix.T)))
        return (world + ca.repmat(ca.DM(self.base_pos), 1, self.n_bodies)).T

    def rows(self, positions: Any, tag: str = "") -> tuple[Any, list[Any]]:
        """The slot rows (m) of the robot's grid points ``positions`` (3 × (S+1), base
        frame, m, symbolic) and new slot parameters (named with ``tag``): per group the
        one-hot rows choosing each slot's sphere(s) (capacity × N) and its part rows. A
        slot's centre is taken from the grid points through its row of the body matrix
        (capacity × (S+1)), not from all N centres: the rows' derivatives pass through
        3 × (S+1) numbers, not N × 3."""
        world = ca.mtimes(ca.DM(self.base_rot), positions).T           # (S+1) × 3, rotated
        rows, parameters = [], []
        for group in self.groups:
            spheres = 2 if group.kind == "self" else 1
            pick = [ca.MX.sym(f"pick_{group.kind}_{k}{tag}", group.capacity, self.n_bodies)
                    for k in range(spheres)]
            part = ca.MX.sym(f"part_{group.kind}{tag}", group.capacity, group.width - spheres)
            centre = [ca.SX.sym(f"centre_{k}", 3) for k in range(spheres)]
            part_sx = ca.SX.sym("part", group.width - spheres)
            distance = ca.Function(f"slot_{group.kind}", [*centre, part_sx], [slot_distance(
                group, centre, part_sx, self.robot.backbone_radius, self.smoothing)])
            offset = ca.repmat(ca.DM(self.base_pos).T, group.capacity, 1)
            chosen = [(ca.mtimes(ca.mtimes(p, ca.DM(self.body_matrix)), world) + offset).T
                      for p in pick]
            rows.append(distance.map(group.capacity)(*chosen, part.T).T)
            parameters += [*pick, part]
        return (ca.vertcat(*rows) if rows else ca.MX(0, 1)), parameters

    def distances(self, positions: np.ndarray) -> np.ndarray:
        """(N·P + M,) pair distances (m) of the robot's grid points (S+1, 3, base frame):
        every sphere to every part (body-major), then the self pairs."""
        centres = np.asarray(self.centres(ca.DM(positions.T)))
        blocks = ([] if self.arrays is None else
                  kind_distances(self.robot.backbone_radius, self.arrays, centres,
                                 self.smoothing, NUMPY))
        obstacle = (np.concatenate(blocks, axis=1).reshape(-1) if blocks else np.zeros(0))
        i, j = self.self_table.T
        own = (np.linalg.norm(centres[i] - centres[j], axis=1) - 2 * self.robot.backbone_radius
               if len(self.self_table) else np.zeros(0))
        return np.concatenate([obstacle, own])

    def slot_parameters(self, distances: np.ndarray) -> tuple[list[np.ndarray], np.ndarray,
                                                               np.ndarray]:
        """(the slot parameters in ``rows``' order, lbg of the slot rows, the chosen pairs'
        indices) for the pairs nearer than ``near_margin``."""
        selection = select_slots(self.groups, self.n_bodies, self.self_table,
                                 self.near_margin, self.row_margin, distances)
        out = []
        for group, rows in zip(self.groups, selection.parameters, strict=True):
            spheres = 2 if group.kind == "self" else 1
            for k in range(spheres):
                pick = np.zeros((group.capacity, self.n_bodies))
                pick[np.arange(group.capacity), rows[:, k].astype(int)] = 1.0
                out.append(pick)
            out.append(rows[:, spheres:])
        return out, selection.lower, selection.chosen
