"""Pair slots: the clearance constraints of the exact stage and their first derivatives.

A clearance constraint of the exact stage is one row ``d ≥ δ`` per (body sphere, nearby
obstacle part) pair and per nearby self pair (docs/design.md §2). Every NLP is built once per
robot and scene and re-solved with new parameters, so the rows cannot be chosen when the
NLP is built. Instead each part kind of the scene (and the robot itself) owns a group of
``capacity`` rows, "slots", per configuration: a slot's body sphere is a parameter (its
index) and so is its part (one parameter row per part), and each solve assigns the
pairs nearer than a margin at the warm start to the slots, nearest first
(``select_slots``); unused slots are switched off with ``lbg = −∞``.

Rows and derivatives (``SlotRows``). One SX function gives the body-sphere centres
``c(z)`` (N × 3, metres) and their Jacobian ∂c/∂z (3N × 3n) of a configuration; a slot
gathers its sphere's centre and 3 × 3n Jacobian block by its index parameter (an MX
parametric gather), and a small SX function per part kind gives the distance d(c, part)
(``world._distances``, the formulas of the clearance) and its row of the constraint
Jacobian by the chain rule, ∇_c d · ∂c/∂z. The kinematics are differentiated once per
configuration, not once per slot.

The constraints' curvature (the Hessian of Σ λ·d) is not given to Ipopt: the polishers'
Hessians hold the objective's and the bending disks' exact terms only. Measured on eight
shelf trajectories (tdcr3, 24 waypoints): the same optima to six digits, 13–63 Ipopt
iterations against 13–39 with the exact Hessian, and 3 ms instead of 60 ms per Hessian
evaluation. The KKT conditions Ipopt stops on use the exact rows and Jacobians, so a
converged answer is a KKT point of the exact problem; and every answer is re-evaluated
independently before it is called a success.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np

from ...model import CasadiModel, Robot
from ...model._ops import CASADI
from ...world import _distances as dist
from ...world.clearance import SceneArrays, _body_centres, scene_arrays, self_pairs
from ...world.scene import Scene

KINDS = ("sphere", "box", "capsule", "cylinder", "convex")
"""The part kinds in ``SceneArrays`` order (the order of ``scene.parts``)."""


@dataclass(frozen=True)
class SlotGroup:
    """Constraint slots for one part kind, or for self pairs (``kind == "self"``).

    ``table`` holds one parameter row per part of the kind (``part_table``); ``first`` is
    the kind's first index in ``scene.parts``; ``faces`` the face count of convex parts.
    """

    kind: str
    capacity: int
    first: int
    table: np.ndarray
    faces: int = 0

    @property
    def width(self) -> int:
        """Parameters per slot: the body-sphere index (self: two), then the part's row."""
        return 2 if self.kind == "self" else 1 + self.table.shape[1]


def part_table(kind: str, a: SceneArrays) -> np.ndarray:
    """One row of parameters per part of ``kind`` (metres; rotations row-major)."""
    if kind == "sphere":
        return np.c_[a.sphere_center, a.sphere_radius]
    if kind == "box":
        return np.c_[a.box_center, a.box_rotation.reshape(-1, 9), a.box_half_size]
    if kind == "capsule":
        return np.c_[a.capsule_a, a.capsule_b, a.capsule_radius]
    if kind == "cylinder":
        return np.c_[a.cylinder_center, a.cylinder_rotation.reshape(-1, 9), a.cylinder_radius,
                     a.cylinder_half_length]
    planes = a.convex_planes                       # (C, F, 4) → nx(F), ny(F), nz(F), b(F)
    return planes.transpose(0, 2, 1).reshape(planes.shape[0], -1)


def make_slot_groups(robot: Robot, scene: Scene | None, capacity: int,
                     include_self: bool) -> tuple[list[SlotGroup], SceneArrays | None]:
    """The slot groups of ``robot`` in ``scene``: one per part kind present (in ``KINDS``
    order), then, with ``include_self`` and n ≥ 3 segments, one for self pairs; each holds
    at most ``capacity`` rows. Also the scene's float64 JAX arrays (None without a scene)."""
    n_bodies = robot.n_points + 1
    groups: list[SlotGroup] = []
    arrays: SceneArrays | None = None
    if scene is not None:
        numeric = scene_arrays(scene, as_numpy=True)
        counts = [numeric.sphere_radius.shape[0], numeric.box_center.shape[0],
                  numeric.capsule_radius.shape[0], numeric.cylinder_radius.shape[0],
                  numeric.convex_planes.shape[0]]
        first = 0
        for kind, count in zip(KINDS, counts, strict=True):
            if count:
                groups.append(SlotGroup(kind, min(capacity, count * n_bodies), first,
                                        part_table(kind, numeric),
                                        numeric.convex_planes.shape[1]))
            first += count
        with jax.enable_x64(True):
            arrays = scene_arrays(scene, dtype=jnp.float64)
    n_self = len(self_pairs(robot)) if robot.has_self_pairs else 0
    if include_self and n_self:
        groups.append(SlotGroup("self", min(capacity, n_self), 0, np.zeros((0, 0))))
    return groups, arrays


@dataclass
class Selection:
    """The slot parameters and clearance bounds of one configuration in one solve."""

    parameters: list[np.ndarray]
    """Per group, the (capacity, width) slot parameters."""
    lower: np.ndarray
    """lbg of all slot rows: the margin where a pair is switched on, −∞ elsewhere."""
    chosen: np.ndarray
    """The switched-on pairs, in row order, as indices into the all-pairs vector
    (obstacle pairs body-major, N·P of them, then the self pairs)."""


def select_slots(groups: list[SlotGroup], n_bodies: int, self_pair_table: np.ndarray,
                 near_margin: float, margin: float, distances: np.ndarray) -> Selection:
    """Assign the pairs nearer than ``near_margin`` (m) at one configuration to the slots:
    first each part's locally nearest body spheres (local minima of the distance along the
    backbone), nearest first, then the other pairs, nearest first. Switched-on rows get
    the lower bound ``margin`` (m).

    ``distances``: (N·P + M,) obstacle pair distances (body-major) then the M self
    distances (``self_pair_table`` rows), metres.
    """
    parameters, lower, chosen = select_slots_batch(groups, n_bodies, self_pair_table,
                                                   near_margin, margin, distances[None])
    return Selection([p[0] for p in parameters], lower[0], chosen[0])


def select_slots_batch(groups: list[SlotGroup], n_bodies: int, self_pair_table: np.ndarray,
                       near_margin: float, margin: float, distances: np.ndarray
                       ) -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray]]:
    """``select_slots`` for K configurations at once: ``distances`` (K, N·P + M).

    Returns per group the (K, capacity, width) slot parameters, the (K, Σ capacity) lower
    bounds (group after group) and per configuration the switched-on pair indices in row
    order."""
    k_configs = len(distances)
    n_self = len(self_pair_table)
    n_parts = (distances.shape[1] - n_self) // n_bodies
    parameters, lower, picked = [], [], []
    for group in groups:
        if group.kind == "self":
            flat = n_bodies * n_parts + np.arange(n_self)
            later = np.zeros((k_configs, n_self), dtype=bool)
        else:
            body = np.arange(n_bodies)[:, None]
            part = np.arange(group.first, group.first + len(group.table))[None, :]
            flat = (body * n_parts + part).reshape(-1)
            # A part's nearest spheres along the backbone (local minima of the distance)
            # first, then the others: every near part gets a slot before a second sphere
            # of one part does.
            d = distances[:, flat].reshape(k_configs, n_bodies, -1)
            padded = np.pad(d, ((0, 0), (1, 1), (0, 0)), constant_values=np.inf)
            later = ~((d <= padded[:, :-2]) & (d <= padded[:, 2:])).reshape(k_configs, -1)
        d = distances[:, flat]
        # Near pairs ordered by (later, distance), ties in pair order; the rest last.
        key = np.where(d < near_margin, d + 1e6 * later, np.inf)
        order = np.argsort(key, axis=1, kind="stable")[:, : group.capacity]
        used = np.isfinite(np.take_along_axis(key, order, axis=1))
        pairs = np.where(used, flat[order], -1)
        rows = np.zeros((k_configs, group.capacity, group.width))
        if group.kind == "self":
            table = self_pair_table[np.where(used, pairs - n_bodies * n_parts, 0)]
            rows[:] = np.where(used[..., None], table, self_pair_table[0])   # filler: harmless
        else:
            rows[:, :, 0] = np.where(used, pairs // n_parts, 0)
            rows[:, :, 1:] = group.table[np.where(used, pairs % n_parts - group.first, 0)]
        parameters.append(rows)
        lower.append(np.where(used, margin, -np.inf))
        picked.append(pairs)
    if not groups:
        return [], np.zeros((k_configs, 0)), [np.zeros(0, dtype=np.int64)] * k_configs
    all_pairs = np.concatenate(picked, axis=1)
    chosen = [row[row >= 0] for row in all_pairs]
    return parameters, np.concatenate(lower, axis=1), chosen


class SlotRows:
    """The slot rows of one configuration, and their Jacobian, as CasADi expressions.

    Args:
        model: the robot's ``CasadiModel``.
        groups: the slot groups (``make_slot_groups``).
        face_smoothing: metres, smoothing μ of a convex part's face-plane max
            (``world._distances.sphere_to_convex``: a lower bound of the distance).
    """

    def __init__(self, model: CasadiModel, groups: list[SlotGroup], face_smoothing: float) -> None:
        robot = model.robot
        self.robot, self.groups = robot, groups
        self.n_bodies = robot.n_points + 1
        self.count = sum(group.capacity for group in groups)
        """Rows per configuration."""
        z = ca.SX.sym("z", robot.dof)
        centres = _body_centres(CASADI, robot, [z[i] for i in range(robot.dof)])   # N × 3
        self._centres = ca.Function("body_centres", [z], [centres])
        self._centres_jacobian = ca.Function(
            "body_centres_jacobian", [z],
            [centres, ca.densify(ca.jacobian(ca.vec(centres), z))])         # 3N × 3n
        self._slot = [self._slot_functions(group, face_smoothing) for group in groups]
        # Second-order part through the kinematics: ∇²_z Σ_b W_b · c_b(z) for weights W.
        weights = ca.SX.sym("weights", self.n_bodies, 3)
        self._centres_curvature = ca.Function(
            "body_centres_curvature", [z, weights],
            [ca.hessian(ca.sum1(ca.sum2(weights * centres)), z)[0]])
        self._slot_curvature = [self._curvature_function(group, face_smoothing)
                                for group in groups]
        self._functions: dict[tuple[bool, bool], tuple[ca.Function, ...]] = {}
        self._interpreted: set[tuple[bool, bool]] = set()

    def centres(self, z: Any) -> np.ndarray:
        """(N, 3) body-sphere centres (m) of one configuration z (3n), float64, by the SX
        function the rows use (microseconds, where numpy's per-configuration kinematics
        costs about a millisecond of Python)."""
        return np.asarray(self._centres(z), dtype=np.float64)

    def _slot_functions(self, group: SlotGroup,
                        smoothing: float) -> tuple[ca.Function, ca.Function]:
        """SX functions of one slot: (centres…, part) → d (m), and (centres…, centre
        Jacobians…, part) → (d, its row ∇_c d · ∂c/∂z)."""
        r, dof = self.robot.backbone_radius, self.robot.dof
        spheres = 2 if group.kind == "self" else 1
        centre = [ca.SX.sym(f"centre_{k}", 3) for k in range(spheres)]
        jacobian = [ca.SX.sym(f"centre_jacobian_{k}", 3, dof) for k in range(spheres)]
        part = ca.SX.sym("part", group.width - spheres)
        d = slot_distance(group, centre, part, r, smoothing)
        row = sum(ca.mtimes(ca.gradient(d, x).T, j) for x, j in zip(centre, jacobian,
                                                                       strict=True))
        value = ca.Function(f"slot_{group.kind}", [*centre, part], [d])
        derivative = ca.Function(f"slot_{group.kind}_row", [*centre, *jacobian, part], [d, row])
        return value, derivative

    def _curvature_function(self, group: SlotGroup, smoothing: float) -> ca.Function:
        """SX function of one slot: (centres…, centre Jacobians…, part, λ) → (λ·Jᵀ∇²_c d·J
        flattened (3n·3n), λ·∇_c d per sphere): the slot's curvature through its sphere
        centres, and the weights its centres' own curvature gets."""
        value, _ = self._slot[self.groups.index(group)]
        dof = self.robot.dof
        spheres = 2 if group.kind == "self" else 1
        centre = [ca.SX.sym(f"centre_{k}", 3) for k in range(spheres)]
        jacobian = [ca.SX.sym(f"centre_jacobian_{k}", 3, dof) for k in range(spheres)]
        part = ca.SX.sym("part", group.width - spheres)
        lam = ca.SX.sym("lam")
        c, j = ca.vertcat(*centre), ca.vertcat(*jacobian)
        d = value(*centre, part)
        hessian, gradient = ca.hessian(d, c)
        outer = lam * ca.mtimes([j.T, hessian, j])
        weights = [lam * gradient[3 * k: 3 * k + 3] for k in range(spheres)]
        return ca.Function(f"slot_{group.kind}_curvature", [*centre, *jacobian, part, lam],
                           [ca.vec(outer), *weights])

    def _gather_centres(self, centres: Any, index: Any) -> Any:
        """(3 × K) centres of the K body spheres with (K,) indices ``index`` (MX)."""
        offsets = ca.DM([0.0, self.n_bodies, 2.0 * self.n_bodies])
        return ca.vec(centres)[ca.repmat(index.T, 3, 1) + ca.repmat(offsets, 1, index.size1())]

    def _gather_jacobians(self, jacobian: Any, index: Any) -> Any:
        """(3 × 3n·K) Jacobian blocks of the K body spheres with indices ``index`` (MX)."""
        n, dof, k = self.n_bodies, self.robot.dof, index.size1()
        block = np.array([[row * n + col * 3 * n for col in range(dof)] for row in range(3)])
        offsets = ca.DM(np.tile(block, (1, k)))
        spread = ca.repmat(ca.kron(index.T, ca.DM.ones(1, dof)), 3, 1)
        return ca.vec(jacobian)[spread + offsets]

    def values(self, z: Any, slots: list[Any]) -> Any:
        """The (count,) rows at configuration z (3n, MX): signed distances (m), group after
        group, slot after slot. ``slots``: per group the (capacity × width) parameters."""
        if not self.groups:
            return ca.MX(0, 1)
        centres = self._centres(z)
        rows = []
        for group, slot, (value, _) in zip(self.groups, slots, self._slot, strict=True):
            spheres = 2 if group.kind == "self" else 1
            gathered = [self._gather_centres(centres, slot[:, k]) for k in range(spheres)]
            rows.append(value.map(group.capacity)(*gathered, slot[:, spheres:].T).T)
        return ca.vertcat(*rows)

    def with_jacobian(self, z: Any, slots: list[Any]) -> tuple[Any, Any]:
        """``values`` and their (count × 3n) Jacobian with respect to z (MX)."""
        dof = self.robot.dof
        if not self.groups:
            return ca.MX(0, 1), ca.MX(0, dof)
        centres, jacobian = self._centres_jacobian(z)
        rows, rows_jacobian = [], []
        for group, slot, (_, derivative) in zip(self.groups, slots, self._slot, strict=True):
            spheres = 2 if group.kind == "self" else 1
            gathered = [self._gather_centres(centres, slot[:, k]) for k in range(spheres)]
            blocks = [self._gather_jacobians(jacobian, slot[:, k]) for k in range(spheres)]
            d, row = derivative.map(group.capacity)(*gathered, *blocks, slot[:, spheres:].T)
            rows.append(d.T)
            rows_jacobian.append(ca.reshape(row, dof, group.capacity).T)
        return ca.vertcat(*rows), ca.vertcat(*rows_jacobian)

    def hessian(self, z: Any, slots: list[Any], lam: Any, kinematic: bool = True) -> Any:
        """The (3n × 3n) Hessian Σ_s λ_s ∇²_z d_s of one configuration's rows (MX), exact:
        each slot's curvature through its sphere centres, Jᵀ∇²_c d J, plus the centres'
        own curvature weighted by λ_s ∇_c d_s, summed per body sphere first (so that the
        kinematics are differentiated twice once per configuration, not once per slot).
        ``lam``: the (count,) multipliers of ``values``' rows. Without ``kinematic`` only
        the first part (the parts' own curvature)."""
        dof = self.robot.dof
        if not self.groups:
            return ca.MX(dof, dof)
        centres, jacobian = self._centres_jacobian(z)
        total = ca.MX(dof * dof, 1)
        weights = ca.MX(self.n_bodies, 3)
        bodies = ca.DM(np.arange(self.n_bodies)).T
        start = 0
        for group, slot, curvature in zip(self.groups, slots, self._slot_curvature, strict=True):
            spheres = 2 if group.kind == "self" else 1
            lam_pool = lam[start: start + group.capacity]
            start += group.capacity
            gathered = [self._gather_centres(centres, slot[:, k]) for k in range(spheres)]
            blocks = [self._gather_jacobians(jacobian, slot[:, k]) for k in range(spheres)]
            outer, *grads = curvature.map(group.capacity)(*gathered, *blocks,
                                                         slot[:, spheres:].T, lam_pool.T)
            total += ca.sum2(outer)
            for k, grad in enumerate(grads if kinematic else []):
                # One-hot rows of the slots' spheres scatter λ·∇_c d onto the bodies.
                one_hot = ca.repmat(slot[:, k], 1, self.n_bodies) == ca.repmat(
                    bodies, group.capacity, 1)
                weights += ca.mtimes(one_hot.T, grad.T)
        total = ca.reshape(total, dof, dof)
        return total + self._centres_curvature(z, weights) if kinematic else total

    def functions(self, kinematic: bool = True,
                  compile: bool = False) -> tuple[ca.Function, ca.Function, ca.Function]:
        """The rows of one configuration as functions ``(z, *slots) -> rows``,
        ``(z, *slots) -> (rows, jacobian)`` and ``(z, *slots, λ) -> Σ λ ∇²rows``, to map
        over many configurations (``kinematic``: see ``hessian``); with ``compile``,
        compiled to machine code and cached on disk (``stages.polish._compiled_functions``; while
        that is
        being built, the functions as they are, asked for again once it is there)."""
        from ._compiled_functions import compiled, pending

        key = (kinematic, compile)
        if key not in self._functions or (key in self._interpreted and not pending()):
            z = ca.MX.sym("z", self.robot.dof)
            slots = [ca.MX.sym(f"slots_{p.kind}", p.capacity, p.width) for p in self.groups]
            lam = ca.MX.sym("lam", self.count)
            functions = [
                ca.Function("slot_rows", [z, *slots], [self.values(z, slots)]),
                ca.Function("slot_rows_jacobian", [z, *slots],
                            [*self.with_jacobian(z, slots)]),
                ca.Function("slot_rows_hessian", [z, *slots, lam],
                            [self.hessian(z, slots, lam, kinematic)])]
            done, waiting = compiled(functions, compile)
            self._functions[key] = tuple(done)
            self._interpreted.discard(key)
            if waiting:
                self._interpreted.add(key)
        return self._functions[key]

    @property
    def interpreted(self) -> bool:
        """Some functions were handed out uncompiled while their library is being built."""
        return bool(self._interpreted)


def slot_distance(group: SlotGroup, centre: list[Any], part: Any, radius: float,
                  smoothing: float) -> Any:
    """The signed distance (m, SX) of one slot: a body sphere of ``radius`` m at
    ``centre[0]`` (3) to the part whose parameter row is ``part`` (a ``part_table`` row of
    the group's kind), or for self pairs between the spheres at ``centre[0]`` and
    ``centre[1]``; convex parts' face-plane max smoothed by ``smoothing`` m."""
    c = tuple(centre[0][i] for i in range(3))
    r = radius
    if group.kind == "self":
        return dist.sphere_to_sphere(CASADI, c, r, tuple(centre[1][i] for i in range(3)), r)
    if group.kind == "sphere":
        return dist.sphere_to_sphere(CASADI, c, r, _entries(part, 0, 3), part[3])
    if group.kind == "box":
        return dist.sphere_to_box(CASADI, c, r, _entries(part, 0, 3), _entries(part, 3, 12),
                                  _entries(part, 12, 15))
    if group.kind == "capsule":
        return dist.sphere_to_capsule(CASADI, c, r, _entries(part, 0, 3), _entries(part, 3, 6),
                                      part[6])
    if group.kind == "cylinder":
        return dist.sphere_to_cylinder(CASADI, c, r, _entries(part, 0, 3),
                                       _entries(part, 3, 12), part[12], part[13])
    f = group.faces
    planes = tuple(part[k * f:(k + 1) * f] for k in range(4))
    return dist.sphere_to_convex(CASADI, c, r, planes, f, smoothing)


def _entries(x: Any, start: int, stop: int) -> tuple[Any, ...]:
    return tuple(x[i] for i in range(start, stop))
