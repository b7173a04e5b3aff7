"""Stage 3, polish: the IK problem with its constraints as real constraints, solved by Ipopt.

The variable is the bending vector ``z = [ux1, uy1, L1, …]`` (rad, rad, m), warm-started
from stage 2's answer. Constraints (DESIGN.md §2):

- simple bounds: ``|uxᵢ|, |uyᵢ| ≤ θmaxᵢ``, ``Lᵢ`` in its range (``lbx = ubx`` when fixed);
- ``‖uᵢ‖² ≤ θmaxᵢ²`` (smooth form of θᵢ ≤ θmaxᵢ);
- clearance: one inequality ``d ≥ δ`` per (body sphere, obstacle part) pair and per
  self pair (body spheres on segments at least two apart) near the warm start;
- pose, mode ``"equality"``: ``log(T_tip⁻¹·T_target) = 0`` (6 rows), objective
  ``‖z − z_start‖²``; mode ``"minimize"``: objective ``½‖log(T_tip⁻¹·T_target)‖²``.

Azimuth ranges (``phi_range``, rare) are not constraints of the polish; the re-evaluated
``max_violation`` still measures them, so a polish that leaves such a range fails.

Pair slots. Every NLP is built once per (robot, scene) and re-solved with new parameters.
Giving every (body sphere, part) pair of the scene its own row and switching far pairs off
with ``lbg = −∞`` was measured to cost 4× the solve time of the near pairs alone on the
lattice (free rows still enter Ipopt's KKT system, and the Hessian of every pair is
evaluated), and it grows with the scene (shelf: 1,767 pairs of 16-plane parts, 15 ms per
Hessian evaluation). Instead, each part kind of the scene (and the robot itself) owns a
pool of ``max_pairs`` constraint rows ("slots"). A slot's body sphere is a parametric
index into the body-sphere centres and its part is given by parameters, so each solve
assigns the pairs nearer than ``near_margin`` at the warm start (nearest first) to slots;
unused slots are switched off with ``lbg = −∞``. The distance formulas are those of
``cr_nlp.world.distances``, evaluated by CasADi on all slots at once.

Every answer is re-evaluated in float64 independently of Ipopt (JAX kinematics, the
world's ``pair_distances``/``self_distances`` over all pairs, numpy limits) before it is
called a success.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ..model import (
    CasadiModel,
    Robot,
    load_robot,
    pose_error,
    q_to_z_numpy,
    tip_pose_z,
    z_to_q_numpy,
)
from ..model._ops import CASADI
from ..model.limits import limit_violation_q
from ..world import distances as dist
from ..world.clearance import (
    SceneArrays,
    body_gap_tolerance,
    pair_distances_z,
    scene_arrays,
    self_distances_z,
    self_pairs,
)
from ..world.scene import Scene, load_scene

MODES = ("equality", "minimize")

# The part kinds in ``SceneArrays`` order (the order of ``scene.parts``).
_KINDS = ("sphere", "box", "capsule", "cylinder", "convex")

# CasADi on a (slots × faces) matrix: entry i of a "vector" is column i, so the
# face-plane max of ``distances.sphere_to_convex`` reduces over columns, one row per slot.
_COLUMNS = dataclasses.replace(CASADI, name="casadi_columns", entry=lambda x, i: x[:, i])


@dataclass(frozen=True)
class PolishConfig:
    """Settings of the Ipopt polish."""

    tol: float = 1e-8
    """Ipopt's ``tol``: the scaled optimality error at which it stops."""
    constr_viol_tol: float = 1e-8
    """Ipopt's ``constr_viol_tol``: the largest unscaled constraint violation it accepts
    (radians² for the bending disk, metres for clearance, mixed m/rad for the pose)."""
    max_iter: int = 100
    """Ipopt iterations per attempt."""
    near_margin: float = 0.5
    """Metres: obstacle and self pairs farther apart than this at the warm start are
    switched off for that solve."""
    face_smoothing: float = 0.002
    """Metres: smoothing μ of the max over a convex part's face planes, a conservative
    lower bound at most ⌈log₂ F⌉·μ/2 below the unsmoothed one (``world/distances.py``)."""
    max_pairs: int = 64
    """Constraint slots per pool (one pool per part kind in the scene, one for self
    pairs). When more pairs are near, the nearest ones get the slots."""
    modes: tuple[str, ...] = ("equality", "minimize")
    """Attempts in order; the next one runs only if the previous failed. ``"equality"``:
    pose as 6 equality constraints, objective ‖z − z_start‖²; ``"minimize"``: objective
    ½‖log(T_tip⁻¹·T_target)‖²."""
    pose_tolerance: float = 1e-6
    """Largest pose error ‖log(T_tip⁻¹·T_target)‖ (mixed m/rad) of a successful polish."""
    violation_tolerance: float = 1e-6
    """Largest re-evaluated ``max_violation`` (rad or m) of a successful polish."""
    print_level: int = 0
    """Ipopt's ``print_level`` (0: silent)."""

    def __post_init__(self) -> None:
        if not self.modes or any(m not in MODES for m in self.modes):
            raise ValueError(f"modes must be a non-empty sequence of {MODES}, got {self.modes!r}")
        if self.max_pairs < 1:
            raise ValueError(f"max_pairs must be at least 1, got {self.max_pairs}")


@dataclass
class PolishResult:
    """The outcome of one polish (never raised: a failure is ``success=False``)."""

    q: np.ndarray
    """(3n,) θ, φ, L (rad, rad, m), converted back from z: the attempt that came out best
    (the warm start itself if Ipopt produced nothing finite)."""
    success: bool
    """Ipopt reported success, the re-evaluated ``max_violation`` ≤ ``violation_tolerance``
    and ``pose_error`` ≤ ``pose_tolerance``."""
    status: str
    """Ipopt's return status of the attempt that produced ``q``."""
    max_violation: float
    """Re-evaluated at ``q`` in float64: the largest limit violation (rad or m) or
    clearance shortfall below the safety margin (m), over all pairs of the scene."""
    pose_error: float
    """‖log(T_tip⁻¹·T_target)‖ at ``q`` (mixed m/rad), float64."""
    iterations: int
    """Ipopt iterations, summed over every attempt of this solve."""
    seconds: float
    """Wall time of the whole ``solve`` (selection, attempts, re-evaluation), seconds."""
    mode: str
    """The pose formulation that produced ``q``: ``"equality"`` or ``"minimize"``."""

    def failure(self, pose_tolerance: float = 1e-6, violation_tolerance: float = 1e-6) -> str:
        """Why the polish did not succeed, in words ("" if it did): Ipopt's status when
        Ipopt failed; otherwise which independent re-evaluation rejected its answer."""
        if self.success:
            return ""
        if self.status not in ("Solve_Succeeded", "Solved_To_Acceptable_Level"):
            return f"Ipopt: {self.status}"
        if self.max_violation > violation_tolerance:
            return (f"Ipopt converged, but the float64 re-evaluation finds a constraint "
                    f"violated by {self.max_violation:.2g}")
        return (f"Ipopt converged to a point {self.pose_error:.2g} (m/rad) from the target: "
                f"the pose is not reachable while keeping every constraint")


# ================================================================ float64 re-evaluation


@partial(jax.jit, static_argnums=0)
def _measures(robot: Robot, arrays: SceneArrays | None, z: jax.Array, target_position: jax.Array,
              target_rotation: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Pose error, (N, P) obstacle pair distances and (M,) self distances at z (m, rad)."""
    position, rotation = tip_pose_z(robot, z)
    error = pose_error(position, rotation, target_position, target_rotation)
    pairs = (pair_distances_z(robot, arrays, z) if arrays is not None
             else jnp.zeros((robot.n_points + 1, 0), z.dtype))
    own = self_distances_z(robot, z) if robot.n_segments >= 3 else jnp.zeros((0,), z.dtype)
    return error, pairs, own


# ================================================================ pair slots


@dataclass(frozen=True)
class _Pool:
    """Constraint slots for one part kind (or for self pairs, ``kind == "self"``).

    ``table`` holds one parameter row per part of the kind (see ``_part_table``);
    ``first`` is the kind's first index in ``scene.parts``.
    """

    kind: str
    capacity: int
    first: int
    table: np.ndarray
    faces: int = 0

    @property
    def width(self) -> int:
        """Parameters per slot: the body-sphere index(es), then the part's row."""
        return 2 if self.kind == "self" else 1 + self.table.shape[1]


def _part_table(kind: str, a: SceneArrays) -> np.ndarray:
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


def _slot_distances(pool: _Pool, centre: tuple[Any, Any, Any], radius: float, part: Any,
                    smoothing: float) -> Any:
    """Signed distances (m) of the slots' body spheres to their parts, one row per slot.

    ``centre``: three (K,) columns; ``part``: the (K, width − 1) part parameters.
    """
    def cols(start: int, stop: int) -> tuple[Any, ...]:
        return tuple(part[:, j] for j in range(start, stop))

    if pool.kind == "sphere":
        return dist.sphere_to_sphere(CASADI, centre, radius, cols(0, 3), part[:, 3])
    if pool.kind == "box":
        return dist.sphere_to_box(CASADI, centre, radius, cols(0, 3), cols(3, 12), cols(12, 15))
    if pool.kind == "capsule":
        return dist.sphere_to_capsule(CASADI, centre, radius, cols(0, 3), cols(3, 6), part[:, 6])
    if pool.kind == "cylinder":
        return dist.sphere_to_cylinder(CASADI, centre, radius, cols(0, 3), cols(3, 12),
                                       part[:, 12], part[:, 13])
    f = pool.faces
    planes = tuple(part[:, k * f:(k + 1) * f] for k in range(4))
    spread = tuple(ca.repmat(c, 1, f) for c in centre)
    return dist.sphere_to_convex(_COLUMNS, spread, radius, planes, f, smoothing)


@dataclass
class _Selection:
    """The slot parameters and clearance bounds of one solve."""

    parameters: list[np.ndarray]
    """Per pool, the (capacity, width) slot parameters."""
    lower: np.ndarray
    """lbg of all slot rows: δ where a pair is switched on, −∞ elsewhere."""
    chosen: np.ndarray
    """The switched-on pairs, in row order, as indices into the all-pairs vector
    (obstacle pairs body-major, N·P of them, then the self pairs)."""


@dataclass
class _Attempt:
    mode: str
    z: np.ndarray
    status: str
    ipopt_success: bool
    iterations: int
    pose_error: float
    max_violation: float
    pair_distances: np.ndarray         # (N·P + M,) at z (m), all pairs


def make_pools(robot: Robot, scene: Scene | None, max_pairs: int,
               include_self: bool) -> tuple[list[_Pool], SceneArrays | None]:
    """The slot pools of ``robot`` in ``scene``: one per part kind present (in
    ``SceneArrays`` order), then, with ``include_self`` and n ≥ 3 segments, one for self
    pairs; each holds at most ``max_pairs`` rows. Also the scene's float64 arrays (None
    without a scene)."""
    n_bodies = robot.n_points + 1
    pools: list[_Pool] = []
    arrays: SceneArrays | None = None
    if scene is not None:
        numeric = scene_arrays(scene, as_numpy=True)
        counts = [numeric.sphere_radius.shape[0], numeric.box_center.shape[0],
                  numeric.capsule_radius.shape[0], numeric.cylinder_radius.shape[0],
                  numeric.convex_planes.shape[0]]
        first = 0
        for kind, count in zip(_KINDS, counts, strict=True):
            if count:
                pools.append(_Pool(kind, min(max_pairs, count * n_bodies), first,
                                   _part_table(kind, numeric), numeric.convex_planes.shape[1]))
            first += count
        with jax.enable_x64(True):
            arrays = scene_arrays(scene, dtype=jnp.float64)
    n_self = len(self_pairs(robot)) if robot.n_segments >= 3 else 0
    if include_self and n_self:
        pools.append(_Pool("self", min(max_pairs, n_self), 0, np.zeros((0, 0))))
    return pools, arrays


def clearance_rows(model: CasadiModel, pools: list[_Pool], z: Any, slots: list[Any],
                   face_smoothing: float) -> Any:
    """The slot rows of one configuration z (3n, bending vector; SX or MX): for each pool,
    the (capacity,) signed distances (m) of its slots' pairs. ``slots``: per pool, the
    (capacity × width) slot parameters (``select_slots``)."""
    if not pools:
        return ca.SX(0, 1)
    robot = model.robot
    n_bodies, r = robot.n_points + 1, robot.backbone_radius
    backbone = model.functions_z["backbone"](z)                        # (N − 1) × 3
    base = ca.DM(np.asarray(robot.base_position, dtype=float)).T
    flat = ca.vec(ca.vertcat(base, backbone))           # x of every sphere, then y, then z

    def centre(index: Any) -> tuple[Any, Any, Any]:
        return tuple(flat[index + k * n_bodies] for k in range(3))

    rows = []
    for pool, slot in zip(pools, slots, strict=True):
        if pool.kind == "self":
            rows.append(dist.sphere_to_sphere(CASADI, centre(slot[:, 0]), r,
                                              centre(slot[:, 1]), r))
        else:
            rows.append(_slot_distances(pool, centre(slot[:, 0]), r, slot[:, 1:],
                                        face_smoothing))
    return ca.vertcat(*rows)


def select_slots(pools: list[_Pool], n_bodies: int, self_pair_table: np.ndarray,
                 near_margin: float, margin: float, distances: np.ndarray) -> _Selection:
    """Assign the pairs nearer than ``near_margin`` (m) at one configuration (nearest
    first) to the slots; switched-on rows get the lower bound ``margin`` (m).

    ``distances``: (N·P + M,) obstacle pair distances (body-major) then the M self
    distances (``self_pair_table`` rows), metres.
    """
    n_self = len(self_pair_table)
    n_parts = (len(distances) - n_self) // n_bodies
    parameters, lower, chosen = [], [], []
    for pool in pools:
        if pool.kind == "self":
            flat = n_bodies * n_parts + np.arange(n_self)
        else:
            body = np.arange(n_bodies)[:, None]
            part = np.arange(pool.first, pool.first + len(pool.table))[None, :]
            flat = (body * n_parts + part).reshape(-1)
        flat = flat[distances[flat] < near_margin]
        flat = flat[np.argsort(distances[flat], kind="stable")][: pool.capacity]
        rows = np.zeros((pool.capacity, pool.width))
        if pool.kind == "self":
            rows[:] = self_pair_table[0]                          # harmless filler
            rows[: len(flat)] = self_pair_table[flat - n_bodies * n_parts]
        else:
            rows[:, 1:] = pool.table[0]                           # base sphere ↔ first part
            rows[: len(flat), 0] = flat // n_parts
            rows[: len(flat), 1:] = pool.table[flat % n_parts - pool.first]
        bound = np.full(pool.capacity, -np.inf)
        bound[: len(flat)] = margin
        parameters.append(rows)
        lower.append(bound)
        chosen.append(flat)
    if not pools:
        return _Selection([], np.zeros(0), np.zeros(0, dtype=np.int64))
    return _Selection(parameters, np.concatenate(lower), np.concatenate(chosen))


# ================================================================ the polisher


class IKPolisher:
    """Ipopt polish of IK answers for one robot in one scene.

    The NLPs (one per mode in ``config.modes``) are built once here and re-solved by
    ``solve`` with new parameters; ``builds`` counts ``nlpsol`` constructions.

    Args:
        robot: a ``Robot`` or a robot file.
        scene: a ``Scene``, a scene file or bundled scene name, or None (no clearance).
        safety_margin: δ (m), the clearance every pair must keep; default
            ``body_gap_tolerance(robot) + 0.002``, so that clearance ≥ δ proves the capsule
            body collision-free for ``world.check``.
        config: ``PolishConfig``.
    """

    def __init__(self, robot: Robot | str | Path, scene: Scene | str | Path | dict | None = None,
                 safety_margin: float | None = None, config: PolishConfig = PolishConfig()) -> None:
        self.robot = robot = load_robot(robot)
        self.scene = load_scene(scene) if scene is not None else None
        self.config = config
        self.safety_margin = float(body_gap_tolerance(robot) + 0.002 if safety_margin is None
                                   else safety_margin)
        self.builds = 0
        """How many ``nlpsol`` solvers this polisher constructed."""

        n = robot.n_segments
        self._theta_max = np.array([s.theta_max for s in robot.segments])
        self._lbx = np.ravel([[-s.theta_max, -s.theta_max, s.length_min] for s in robot.segments])
        self._ubx = np.ravel([[s.theta_max, s.theta_max, s.length_max] for s in robot.segments])
        self._n_bodies = robot.n_points + 1
        self._self_pairs = self_pairs(robot) if n >= 3 else np.zeros((0, 2), dtype=np.int64)

        self._pools, self._arrays = make_pools(robot, self.scene, config.max_pairs,
                                               include_self=self.scene is not None)

        self._model = CasadiModel(robot)
        self._solvers = {mode: self._build(mode) for mode in config.modes}
        # Compile the float64 re-evaluation now, so that no solve pays for it.
        self._evaluate(np.ravel([[0.0, 0.0, s.length_min] for s in robot.segments]),
                       np.zeros(3), np.eye(3))

    # ------------------------------------------------------------ building

    def _build(self, mode: str) -> ca.Function:
        """The Ipopt solver of one mode. Parameters: target position (3), target rotation
        (3×3, column-major), z_start (3n), then each pool's (capacity × width) slots."""
        robot, cfg = self.robot, self.config
        # Slots index the body spheres by parameter, which only MX expresses; without
        # slots the whole problem is one SX graph (25–50 % faster per solve, measured).
        sym = ca.MX if self._pools else ca.SX
        z = sym.sym("z", robot.dof)
        target_position = sym.sym("target_position", 3)
        target_rotation = sym.sym("target_rotation", 3, 3)
        z_start = sym.sym("z_start", robot.dof)
        error = self._model.functions_z["pose_error"](z, target_position, target_rotation)
        bending = ca.vertcat(*[z[3 * i] ** 2 + z[3 * i + 1] ** 2
                               for i in range(robot.n_segments)])
        slots = [sym.sym(f"slots_{pool.kind}", pool.capacity, pool.width) for pool in self._pools]
        clearance = self._clearance_rows(z, slots)
        if mode == "equality":
            objective, rows = ca.sumsqr(z - z_start), [error, bending, clearance]
        else:
            objective, rows = 0.5 * ca.sumsqr(error), [bending, clearance]
        nlp = {"x": z, "f": objective, "g": ca.vertcat(*rows),
               "p": ca.vertcat(target_position, ca.vec(target_rotation), z_start,
                               *[ca.vec(s) for s in slots])}
        options: dict[str, Any] = {
            "ipopt.tol": cfg.tol,
            "ipopt.constr_viol_tol": cfg.constr_viol_tol,
            "ipopt.max_iter": cfg.max_iter,
            "ipopt.linear_solver": "mumps",      # HSL solvers are absent: never select them
            "ipopt.hessian_approximation": "exact",
            "ipopt.print_level": cfg.print_level,
            "ipopt.sb": "yes",
            "print_time": cfg.print_level > 0,
            "error_on_fail": False,
        }
        if mode == "minimize":
            # Least squares from a nearby start: the monotone barrier update stalls (DESIGN
            # §3). The equality mode measured as fast or faster with the default monotone.
            options["ipopt.mu_strategy"] = "adaptive"
        self.builds += 1
        return ca.nlpsol(f"polish_{robot.name}_{mode}", "ipopt", nlp, options)

    def _clearance_rows(self, z: Any, slots: list[Any]) -> Any:
        """All slot rows: for each pool, the (capacity,) signed distances (m)."""
        return clearance_rows(self._model, self._pools, z, slots, self.config.face_smoothing)

    # ------------------------------------------------------------ per solve

    def _select(self, distances: np.ndarray) -> _Selection:
        """Assign the pairs nearer than ``near_margin`` (nearest first) to the slots.

        ``distances``: (N·P + M,) obstacle pair distances (body-major) then self distances.
        """
        return select_slots(self._pools, self._n_bodies, self._self_pairs,
                            self.config.near_margin, self.safety_margin, distances)

    def _slot_values(self, q_near: Any, q: Any) -> tuple[np.ndarray, np.ndarray]:
        """The clearance rows switched on for the warm start ``q_near``, evaluated at ``q``
        (3n, rad/m) as the NLP sees them, and the world's ``pair_distances`` /
        ``self_distances`` of the same pairs (m, convex parts with ``face_smoothing``):
        the two must agree."""
        z_near, z = (q_to_z_numpy(np.reshape(x, -1)) for x in (q_near, q))
        selection = self._select(self._evaluate(z_near, np.zeros(3), np.eye(3))[3])
        symbol = ca.MX.sym("z", self.robot.dof)
        slots = [ca.MX.sym(f"slots_{p.kind}", p.capacity, p.width) for p in self._pools]
        rows = ca.Function("rows", [symbol, *slots], [self._clearance_rows(symbol, slots)])
        values = np.asarray(rows(z, *selection.parameters)).reshape(-1)
        with jax.enable_x64(True):
            pairs = pair_distances_z(self.robot, self._arrays, z, self.config.face_smoothing)
            own = self_distances_z(self.robot, z) if len(self._self_pairs) else np.zeros(0)
        world = np.concatenate([np.asarray(pairs).reshape(-1), np.asarray(own)])
        return values[np.isfinite(selection.lower)], world[selection.chosen]

    def _evaluate(self, z: np.ndarray, target_position: np.ndarray,
                  target_rotation: np.ndarray) -> tuple[float, float, float, np.ndarray]:
        """Float64, independent of Ipopt: (pose error, limit violation, clearance shortfall,
        all pair distances) at z."""
        with jax.enable_x64(True):
            # numpy arguments: jnp.asarray first would cost more than the evaluation.
            error, pairs, own = _measures(self.robot, self._arrays, z, target_position,
                                          target_rotation)
        distances = np.concatenate([np.asarray(pairs).reshape(-1), np.asarray(own)])
        limits = float(limit_violation_q(self.robot, z_to_q_numpy(z)))
        shortfall = 0.0
        if self.scene is not None and distances.size:
            shortfall = max(0.0, self.safety_margin - float(np.min(distances)))
        return float(error), limits, shortfall, distances

    def _run(self, mode: str, x0: np.ndarray, z_start: np.ndarray, selection: _Selection,
             target_position: np.ndarray, target_rotation: np.ndarray) -> _Attempt:
        """One Ipopt run and its independent re-evaluation."""
        n = self.robot.n_segments
        lower = [np.full(n, -np.inf), selection.lower]
        upper = [self._theta_max ** 2, np.full(selection.lower.size, np.inf)]
        if mode == "equality":
            lower.insert(0, np.zeros(6))
            upper.insert(0, np.zeros(6))
        parameters = np.concatenate([target_position, target_rotation.ravel(order="F"), z_start,
                                     *[p.ravel(order="F") for p in selection.parameters]])
        solver = self._solvers[mode]
        try:
            solution = solver(x0=x0, p=parameters, lbx=self._lbx, ubx=self._ubx,
                              lbg=np.concatenate(lower), ubg=np.concatenate(upper))
            stats = solver.stats()
            z = np.asarray(solution["x"], dtype=np.float64).reshape(-1)
            status = str(stats.get("return_status", "unknown"))
            ipopt_success = bool(stats.get("success", False))
            iterations = int(stats.get("iter_count", 0))
        except RuntimeError as exc:                    # a numerical failure is a result
            z, status, ipopt_success, iterations = x0.copy(), f"error: {exc}", False, 0
        if not np.all(np.isfinite(z)):
            z, ipopt_success = x0.copy(), False
        error, limits, shortfall, distances = self._evaluate(z, target_position, target_rotation)
        return _Attempt(mode, z, status, ipopt_success, iterations, error,
                        max(limits, shortfall), distances)

    def _succeeded(self, attempt: _Attempt) -> bool:
        cfg = self.config
        return (attempt.ipopt_success and attempt.max_violation <= cfg.violation_tolerance
                and attempt.pose_error <= cfg.pose_tolerance)

    def solve(self, q0: Any, target_position: Any, target_rotation: Any) -> PolishResult:
        """Polish one IK answer.

        Args:
            q0: (3n,) warm start θ, φ, L (rad, rad, m), typically stage 2's answer; it may
                violate the limits or the clearance.
            target_position: (3,) metres, world frame.
            target_rotation: (3, 3) rotation matrix, world frame.

        Returns a ``PolishResult``; a numerical failure is ``success=False`` with the best
        configuration Ipopt reached (or ``q0``), never an exception.
        """
        start = time.perf_counter()
        robot = self.robot
        q0 = np.asarray(q0, dtype=np.float64).reshape(-1)
        target_position = np.asarray(target_position, dtype=np.float64).reshape(-1)
        target_rotation = np.asarray(target_rotation, dtype=np.float64)
        if q0.shape != (robot.dof,) or target_position.shape != (3,) \
                or target_rotation.shape != (3, 3):
            raise ValueError(f"solve needs q0 ({robot.dof},), target_position (3,) and "
                             f"target_rotation (3, 3); got {q0.shape}, {target_position.shape}, "
                             f"{target_rotation.shape}")
        if not (np.all(np.isfinite(q0)) and np.all(np.isfinite(target_position))
                and np.all(np.isfinite(target_rotation))):
            return PolishResult(q0, False, "non-finite input", math.inf, math.inf, 0,
                                time.perf_counter() - start, self.config.modes[0])

        z_start = q_to_z_numpy(q0)
        _, _, _, near = self._evaluate(z_start, target_position, target_rotation)
        selection = self._select(near)
        switched_on = np.zeros(near.shape, dtype=bool)
        switched_on[selection.chosen] = True
        attempts: list[_Attempt] = []
        for mode in self.config.modes:
            attempt = self._run(mode, z_start, z_start, selection, target_position,
                                target_rotation)
            violated = attempt.pair_distances < (self.safety_margin
                                                 - self.config.violation_tolerance)
            if self._pools and np.any(violated & ~switched_on):
                # A pair without a slot (far at the warm start, or beyond the capacity) came
                # too close: give the pairs near either point the slots and go on from there.
                refreshed = self._select(np.minimum(near, attempt.pair_distances))
                again = self._run(mode, attempt.z, z_start, refreshed, target_position,
                                  target_rotation)
                again.iterations += attempt.iterations
                attempt = again
            attempts.append(attempt)
            if self._succeeded(attempt):
                break

        def rank(a: _Attempt) -> tuple[bool, bool, float, float]:
            feasible = a.max_violation <= self.config.violation_tolerance
            return (not self._succeeded(a), not feasible,
                    0.0 if feasible else a.max_violation, a.pose_error)

        best = min(attempts, key=rank)
        return PolishResult(
            q=z_to_q_numpy(best.z),
            success=self._succeeded(best),
            status=best.status,
            max_violation=best.max_violation,
            pose_error=best.pose_error,
            iterations=sum(a.iterations for a in attempts),
            seconds=time.perf_counter() - start,
            mode=best.mode,
        )


def polish_many(polisher: IKPolisher, q0s: Any, positions: Any, rotations: Any,
                progress: bool = False) -> list[PolishResult]:
    """``polisher.solve`` for each row: q0s (B, 3n) rad/m, positions (B, 3) m, rotations
    (B, 3, 3); a tqdm progress bar with ``progress``."""
    q0s = np.asarray(q0s, dtype=np.float64).reshape(-1, polisher.robot.dof)
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    if not len(q0s) == len(positions) == len(rotations):
        raise ValueError(f"polish_many needs as many warm starts as targets, got {len(q0s)}, "
                         f"{len(positions)} positions and {len(rotations)} rotations")
    rows: Iterable[int] = range(len(q0s))
    if progress:
        rows = tqdm(rows, desc=f"polish {polisher.robot.name}", unit="target")
    return [polisher.solve(q0s[i], positions[i], rotations[i]) for i in rows]
