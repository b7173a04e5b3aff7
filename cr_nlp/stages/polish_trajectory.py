"""Stage 3, polish for trajectories: all waypoints in one NLP, the constraints as real
constraints, solved by Ipopt from stage 2's answer.

The variable is the (W, 3n) matrix of bending vectors ``z_k = [ux1, uy1, L1, …]`` (rad,
rad, m), one row per waypoint. Two objectives share the constraints:

- ``"path"`` (trajectory planning): start and goal fixed (``lbx = ubx``),
  ``f = w_path·Σ‖p(z_{k+1}) − p(z_k)‖² + w_smooth·Σ‖z_{k+1} − z_k‖²``, the LM stage's
  objective (``tasks.trajectory.trajectory_residual``);
- ``"tracking"`` (path following): every waypoint free,
  ``f = ½Σ_k (w_v‖v_k‖² + w_ω‖ω_k‖²) + w_smooth·Σ‖z_{k+1} − z_k‖²`` with
  ``(v_k, ω_k) = log(T_tip(z_k)⁻¹·T_target_k)`` (m, rad).

Constraints (DESIGN.md §2):

- box bounds ``|uxᵢ|, |uyᵢ| ≤ θmaxᵢ``, ``Lᵢ`` in its range; bending disk
  ``uxᵢ² + uyᵢ² ≤ θmaxᵢ²`` per segment and waypoint;
- tendon speed ``|ℓ(z_{k+1}) − ℓ(z_k)|/Δt ≤ v_max`` and acceleration
  ``|ℓ_{k+1} − 2ℓ_k + ℓ_{k−1}|/Δt² ≤ a_max`` per tendon. Tendon lengths are linear in z
  (``ℓ = A·z + b``), so these are linear rows ``A·Δz·(1/Δt)`` with 1/Δt an NLP parameter:
  the rows are in m/s and m/s² whatever Δt is (Ipopt's ``constr_viol_tol`` then means the
  same thing for every Δt), and a new Δt needs no rebuild. A family whose limit is
  infinite has no rows;
- clearance ``d ≥ δ`` at every waypoint and at ``interpolation_checks`` evenly spaced
  points inside every interval (linear in z, the motion the planner verifies), with the
  pair slots of ``stages.polish``: per configuration and part kind (and for self pairs) a
  pool of ``max_pairs`` rows whose body sphere and part are parameters, assigned per
  solve to the pairs nearer than ``near_margin`` at the warm start, the rest switched off
  with ``lbg = −∞``. One configuration's rows are one ``ca.Function``, mapped over all
  configurations, so the graph does not grow with the number of waypoints.

The NLP is built once per polisher (robot, scene, waypoints, objective) and re-solved
with new parameters (1/Δt, targets, slots) and bounds. Every answer is re-evaluated in
float64 independently of Ipopt (JAX kinematics and the world's distances over ALL pairs,
numpy limits and tendon finite differences) before it is called a success.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np

from ..model import (
    CasadiModel,
    Robot,
    load_robot,
    pose_error,
    q_to_z_numpy,
    tip_pose_z,
    z_to_q_numpy,
)
from ..model._ops import CASADI, NUMPY
from ..model.kinematics import model_tendon_lengths
from ..model.limits import limit_violation_q
from ..world import distances as dist
from ..world.clearance import (
    SceneArrays,
    body_gap_tolerance,
    pair_distances_z,
    self_distances_z,
    self_pairs,
)
from ..world.scene import Scene, load_scene
from .polish import (
    _Pool,
    _Selection,
    _slot_distances,
    make_pools,
    select_slots,
)

OBJECTIVES = ("path", "tracking")


@dataclass(frozen=True)
class TrajectoryPolishConfig:
    """Settings of the trajectory polish."""

    tol: float = 1e-8
    """Ipopt's ``tol``: the scaled optimality error at which it stops."""
    constr_viol_tol: float = 1e-8
    """Ipopt's ``constr_viol_tol``: the largest unscaled constraint violation it accepts
    (rad² for the bending disk, m/s and m/s² for the tendon rows, m for clearance)."""
    max_iter: int = 200
    """Ipopt iterations per attempt."""
    near_margin: float = 0.3
    """Metres: pairs farther apart than this at the warm start get no slot in that solve
    (a pair that comes closer during the solve triggers a re-selection)."""
    max_pairs: int = 8
    """Constraint slots per pool and per configuration (one pool per part kind of the
    scene, one for self pairs); when more pairs are near, the nearest get the slots."""
    reselections: int = 2
    """How many times a solve may re-assign the slots and go on when a pair without a
    slot came closer than δ."""
    interpolation_checks: int = 1
    """Clearance check points inside each interval (1: the midpoint; 3: the quarter
    points, the samples ``verify_trajectory`` checks with its default 4)."""
    face_smoothing: float = 0.002
    """Metres: smoothing μ of the max over a convex part's face planes, a conservative
    lower bound at most ⌈log₂ F⌉·μ/2 below the unsmoothed distance."""
    path_weight: float = 1.0
    """``"path"``: weight of the squared tip displacements Σ‖p(z_{k+1}) − p(z_k)‖² (m²)."""
    smoothness_weight: float = 0.01
    """``"path"``: weight of the squared joint-space steps Σ‖z_{k+1} − z_k‖² (rad², m²)."""
    translation_weight: float = 1.0
    """``"tracking"``: weight of the translation part v of the pose error (m²)."""
    rotation_weight: float = 1.0
    """``"tracking"``: weight of the rotation part ω of the pose error (rad²)."""
    tracking_smoothness_weight: float = 1e-8
    """``"tracking"``: weight of Σ‖z_{k+1} − z_k‖² (rad², m²); tiny, it only picks one of
    equally good bodies. It biases reachable poses by about weight·‖Δz‖/‖J‖: 1e-4 was
    measured to leave 1e-3 pose errors on an 8-waypoint tdcr3 path, 1e-8 below 1e-6."""
    hessian: str = "exact"
    """Ipopt's ``hessian_approximation``: ``"exact"`` or ``"limited-memory"``."""
    violation_tolerance: float = 1e-6
    """Largest re-evaluated ``max_violation`` of a successful polish (rad, m, m/s, m/s²)."""
    print_level: int = 0
    """Ipopt's ``print_level`` (0: silent)."""

    def __post_init__(self) -> None:
        if self.max_pairs < 1:
            raise ValueError(f"max_pairs must be at least 1, got {self.max_pairs}")
        if self.interpolation_checks < 0 or self.reselections < 0:
            raise ValueError("interpolation_checks and reselections must be ≥ 0")
        if self.hessian not in ("exact", "limited-memory"):
            raise ValueError(f"hessian must be 'exact' or 'limited-memory', got {self.hessian!r}")


@dataclass
class TrajectoryPolishResult:
    """The outcome of one trajectory polish (never raised: a failure is ``success=False``)."""

    q: np.ndarray
    """(W, 3n) waypoints θ, φ, L (rad, rad, m): Ipopt's answer, or the warm start if Ipopt
    produced nothing finite."""
    success: bool
    """Ipopt reported success and the re-evaluated ``max_violation`` ≤
    ``violation_tolerance``."""
    status: str
    """Ipopt's return status, or why no solve ran."""
    max_violation: float
    """The largest of ``violations``, re-evaluated at ``q`` in float64."""
    violations: dict[str, float] = field(default_factory=dict)
    """Per family: ``clearance`` (m below δ, over all pairs at the waypoints and check
    points), ``limits`` (rad or m), ``tendon_speed`` (m/s over the limit),
    ``tendon_accel`` (m/s² over the limit)."""
    objective: float = math.nan
    """Ipopt's final objective value (m², rad² mixed)."""
    iterations: int = 0
    """Ipopt iterations, summed over the re-selections of this solve."""
    seconds: float = 0.0
    """Wall time of the whole ``solve``, seconds."""
    pose_errors: np.ndarray | None = None
    """``"tracking"`` only: (W,) ‖log(T_tip⁻¹·T_target)‖ per waypoint (mixed m/rad),
    float64."""


# ================================================================ float64 re-evaluation


@partial(jax.jit, static_argnums=(0, 2))
def _distances(robot: Robot, arrays: SceneArrays | None, with_self: bool,
               z: jax.Array) -> jax.Array:
    """(C, N·P + M) distances (m) of C configurations: obstacle pairs body-major, then the
    self pairs (the order ``select_slots`` expects)."""
    rows = []
    if arrays is not None:
        rows.append(pair_distances_z(robot, arrays, z).reshape(z.shape[0], -1))
    if with_self:
        rows.append(self_distances_z(robot, z))
    return jnp.concatenate(rows, axis=1) if rows else jnp.zeros((z.shape[0], 0), z.dtype)


@partial(jax.jit, static_argnums=0)
def _pose_errors(robot: Robot, z: jax.Array, positions: jax.Array,
                 rotations: jax.Array) -> jax.Array:
    """(W,) pose errors of (W, 3n) waypoints against (W, 3) and (W, 3, 3) targets."""
    position, rotation = jax.vmap(partial(tip_pose_z, robot))(z)
    return pose_error(position, rotation, positions, rotations)


def _tendon_lengths(robot: Robot, z: np.ndarray) -> np.ndarray:
    """(W, n_tendons) tendon lengths (m) of (W, 3n) bending vectors, float64 numpy."""
    values = model_tendon_lengths(NUMPY, robot, [z[:, i] for i in range(robot.dof)])
    return np.stack(np.broadcast_arrays(*values), axis=-1).reshape(len(z), -1)


# ================================================================ clearance rows


def _one_hot_width(pool: _Pool, n_bodies: int) -> int:
    """Parameters per slot in the one-hot form: one (self: two) N-wide body-sphere
    selectors, then the part's row."""
    return 2 * n_bodies if pool.kind == "self" else n_bodies + pool.table.shape[1]


def _one_hot(pool: _Pool, n_bodies: int, slots: np.ndarray) -> np.ndarray:
    """``select_slots``' (capacity × width) slot parameters, body-sphere indices replaced
    by one-hot selector rows."""
    eye = np.eye(n_bodies)
    if pool.kind == "self":
        return np.hstack([eye[slots[:, 0].astype(int)], eye[slots[:, 1].astype(int)]])
    return np.hstack([eye[slots[:, 0].astype(int)], slots[:, 1:]])


def configuration_clearance(model: CasadiModel, pools: list[_Pool],
                            face_smoothing: float) -> ca.Function:
    """One configuration's slot rows as an SX ``ca.Function(z, *slots) -> rows``: z (3n,)
    bending vector, one (capacity × ``_one_hot_width``) parameter matrix per pool; rows:
    for each pool, the (capacity,) signed distances (m) of its slots' pairs.

    A slot picks its body sphere by a one-hot row (a product with the N × 3 centres)
    instead of a parametric index, so the whole function is SX: its exact Hessian, mapped
    over all configurations, was measured far cheaper than the MX graph with indices."""
    robot = model.robot
    n_bodies, r = robot.n_points + 1, robot.backbone_radius
    z = ca.SX.sym("z", robot.dof)
    slots = [ca.SX.sym(f"slots_{p.kind}", p.capacity, _one_hot_width(p, n_bodies))
             for p in pools]
    base = ca.DM(np.asarray(robot.base_position, dtype=float)).T
    centres = ca.vertcat(base, model.functions_z["backbone"](z))           # N × 3

    def centre(selector: ca.SX) -> tuple[Any, Any, Any]:
        picked = ca.mtimes(selector, centres)                              # capacity × 3
        return picked[:, 0], picked[:, 1], picked[:, 2]

    rows = []
    for pool, slot in zip(pools, slots, strict=True):
        if pool.kind == "self":
            rows.append(dist.sphere_to_sphere(CASADI, centre(slot[:, :n_bodies]), r,
                                              centre(slot[:, n_bodies:]), r))
        else:
            rows.append(_slot_distances(pool, centre(slot[:, :n_bodies]), r,
                                        slot[:, n_bodies:], face_smoothing))
    return ca.Function("clearance_rows", [z, *slots], [ca.vertcat(*rows)])


# ================================================================ the polisher


class TrajectoryPolisher:
    """Ipopt polish of whole trajectories for one robot, scene and number of waypoints.

    The NLP is built once here and re-solved by ``solve`` with new parameters; ``builds``
    counts ``nlpsol`` constructions (1).

    Args:
        robot: a ``Robot`` or a robot file / bundled name.
        scene: a ``Scene``, a scene file or bundled name, or None. Self pairs (segments at
            least two apart) are constrained with or without a scene.
        waypoints: W ≥ 2 configurations per trajectory, start and goal included.
        safety_margin: δ (m) every pair must keep on the sphere body; default
            ``body_gap_tolerance(robot) + 0.002`` (then python-fcl sees ≥ 2 mm on the
            capsule body).
        objective: ``"path"`` (planning, start and goal fixed) or ``"tracking"`` (path
            following, every waypoint free, targets per waypoint).
        config: ``TrajectoryPolishConfig``.
    """

    def __init__(self, robot: Robot | str | Path, scene: Scene | str | Path | dict | None,
                 waypoints: int, safety_margin: float | None = None, objective: str = "path",
                 config: TrajectoryPolishConfig = TrajectoryPolishConfig()) -> None:
        if objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
        if int(waypoints) != waypoints or waypoints < 2:
            raise ValueError(f"waypoints must be an integer ≥ 2, got {waypoints!r}")
        self.robot = robot = load_robot(robot)
        self.scene = (load_scene(scene) if isinstance(scene, (str, Path, dict)) else scene)
        self.waypoints = int(waypoints)
        self.objective = objective
        self.config = config
        self.safety_margin = float(body_gap_tolerance(robot) + 0.002 if safety_margin is None
                                   else safety_margin)
        self.builds = 0
        """How many ``nlpsol`` solvers this polisher constructed."""

        w, checks = self.waypoints, config.interpolation_checks
        self._n_configs = w + checks * (w - 1)
        self._n_bodies = robot.n_points + 1
        self._self_pairs = (self_pairs(robot) if robot.n_segments >= 3
                            else np.zeros((0, 2), dtype=np.int64))
        self._pools, self._arrays = make_pools(robot, self.scene, config.max_pairs,
                                               include_self=True)
        self._theta_max = np.array([s.theta_max for s in robot.segments])
        self._lbx = np.ravel([[-s.theta_max, -s.theta_max, s.length_min] for s in robot.segments])
        self._ubx = np.ravel([[s.theta_max, s.theta_max, s.length_max] for s in robot.segments])
        self._model = CasadiModel(robot)
        # ℓ = A·z + b exactly (linear), A from the model's own CasADi tendon function.
        self._tendon_matrix = np.asarray(ca.Function(
            "tendon_jacobian", [self._model.z],
            [ca.jacobian(self._model.functions_z["tendons"](self._model.z), self._model.z)],
        )(np.zeros(robot.dof)))
        self._speed = math.isfinite(robot.tendon_speed_max)
        self._accel = math.isfinite(robot.tendon_accel_max) and w >= 3
        self._solver = self._build()
        # Compile the float64 re-evaluation now, so that no solve pays for it.
        rest = np.tile(np.ravel([[0.0, 0.0, s.length_min] for s in robot.segments]),
                       (w, 1))
        self._all_distances(rest)
        if objective == "tracking":
            with jax.enable_x64(True):
                _pose_errors(robot, rest, np.zeros((w, 3)), np.tile(np.eye(3), (w, 1, 1)))

    # ------------------------------------------------------------ building

    def _interpolated(self, way: Any) -> Any:
        """The (3n × C) configurations of a (3n × W) trajectory: the W waypoints, then
        interval after interval its ``checks`` points at fractions c/(checks + 1)."""
        checks = self.config.interpolation_checks
        if checks == 0:
            return way
        step = way[:, 1:] - way[:, :-1]
        inner = [way[:, :-1] + (c / (checks + 1)) * step for c in range(1, checks + 1)]
        if isinstance(way, (ca.MX, ca.SX)):
            # Column k of the stack holds interval k's points one above the other.
            return ca.horzcat(way, ca.reshape(ca.vertcat(*inner), way.shape[0], -1))
        stacked = np.stack(inner, axis=2)                       # 3n × (W − 1) × checks
        return np.hstack([way, stacked.reshape(way.shape[0], -1)])

    def _elements(self) -> tuple[ca.Function, ca.Function, list[ca.SX], list[ca.SX]]:
        """The Lagrangian split into elements (SX functions): one per waypoint k
        (objective part, bending rows, clearance rows of z_k) and one per interval
        (objective part, clearance rows of its check points). Tendon rows are linear and
        add nothing to the Hessian.

        Returns (waypoint element, interval element, their symbolic inputs): each element
        is ``Function(z…, lam_f, multipliers…, slots…, targets…) -> value``."""
        robot, cfg, checks = self.robot, self.config, self.config.interpolation_checks
        fz, dof, n = self._model.functions_z, robot.dof, robot.n_segments
        one = (configuration_clearance(self._model, self._pools, cfg.face_smoothing)
               if self._pools else None)
        rows_per_config = sum(p.capacity for p in self._pools)
        widths = [_one_hot_width(p, self._n_bodies) for p in self._pools]
        z_k, z_next = ca.SX.sym("z_k", dof), ca.SX.sym("z_next", dof)
        lam_f = ca.SX.sym("lam_f")

        # Waypoint element.
        lam_bend = ca.SX.sym("lam_bending", n)
        lam_way = ca.SX.sym("lam_clearance", rows_per_config)
        slots_way = [ca.SX.sym(f"slots_{p.kind}", p.capacity, wd)
                     for p, wd in zip(self._pools, widths, strict=True)]
        targets: list[ca.SX] = []
        bending = ca.vertcat(*[z_k[3 * i] ** 2 + z_k[3 * i + 1] ** 2 for i in range(n)])
        value = ca.dot(lam_bend, bending)
        if self.objective == "tracking":
            targets = [ca.SX.sym("target_position", 3), ca.SX.sym("target_rotation", 3, 3)]
            error = fz["pose_error"](z_k, *targets)
            value += lam_f * (0.5 * cfg.translation_weight * ca.sumsqr(error[:3])
                              + 0.5 * cfg.rotation_weight * ca.sumsqr(error[3:]))
        if one is not None:
            value += ca.dot(lam_way, one(z_k, *slots_way))
        way_inputs = [z_k, lam_f, lam_bend, lam_way, *slots_way, *targets]
        waypoint = ca.Function("waypoint_element", way_inputs, [value])

        # Interval element.
        lam_int = ca.SX.sym("lam_clearance", rows_per_config, checks)
        slots_int = [ca.SX.sym(f"slots_{p.kind}", p.capacity, wd * checks)
                     for p, wd in zip(self._pools, widths, strict=True)]
        step = z_next - z_k
        if self.objective == "path":
            tip_k, tip_next = fz["tip"](z_k)[0], fz["tip"](z_next)[0]
            value = lam_f * (cfg.path_weight * ca.sumsqr(tip_next - tip_k)
                             + cfg.smoothness_weight * ca.sumsqr(step))
        else:
            value = lam_f * cfg.tracking_smoothness_weight * ca.sumsqr(step)
        if one is not None:
            for c in range(checks):
                z_c = z_k + ((c + 1) / (checks + 1)) * step
                value += ca.dot(lam_int[:, c], one(z_c, *[
                    slot[:, c * wd:(c + 1) * wd] for slot, wd in zip(slots_int, widths,
                                                                      strict=True)]))
        int_inputs = [z_k, z_next, lam_f, lam_int, *slots_int]
        interval = ca.Function("interval_element", int_inputs, [value])
        return waypoint, interval, way_inputs, int_inputs

    def _objective(self, way: ca.MX, targets: list[ca.MX]) -> ca.MX:
        """f of a (3n × W) trajectory: the path or tracking objective (module docstring)."""
        cfg, w = self.config, self.waypoints
        fz = self._model.functions_z
        step = way[:, 1:] - way[:, :-1]
        if self.objective == "path":
            tips = fz["tip"].map(w)(way)[0]                                    # 3 × W
            return (cfg.path_weight * ca.sumsqr(tips[:, 1:] - tips[:, :-1])
                    + cfg.smoothness_weight * ca.sumsqr(step))
        error = fz["pose_error"].map(w)(way, *targets)                         # 6 × W
        return (0.5 * cfg.translation_weight * ca.sumsqr(error[:3, :])
                + 0.5 * cfg.rotation_weight * ca.sumsqr(error[3:, :])
                + cfg.tracking_smoothness_weight * ca.sumsqr(step))

    def _build(self) -> ca.Function:
        """The Ipopt solver. Parameters: 1/Δt (1/s), then for ``"tracking"`` the target
        positions (3 × W) and rotations (3 × 3W), then each pool's one-hot slots
        (capacity × width·C), configuration after configuration (``_interpolated``).

        The exact Hessian of the Lagrangian is assembled from per-element Hessians (SX,
        mapped over the waypoints and intervals) into its block-tridiagonal pattern:
        CasADi's own Hessian of the mapped graph colours the whole band and re-evaluates
        every configuration per colour (measured 5 s per solve for 150 waypoints, and
        2 minutes to build when expanded to SX)."""
        robot, cfg, w = self.robot, self.config, self.waypoints
        dof, n, checks = robot.dof, robot.n_segments, cfg.interpolation_checks
        waypoint, interval, way_inputs, int_inputs = self._elements()
        widths = [_one_hot_width(p, self._n_bodies) for p in self._pools]
        rows_per_config = sum(p.capacity for p in self._pools)
        n_t = self._tendon_matrix.shape[0]

        x = ca.MX.sym("x", dof * w)
        n_p = 1 + (12 * w if self.objective == "tracking" else 0) + sum(
            p.capacity * wd * self._n_configs for p, wd in zip(self._pools, widths, strict=True))
        p = ca.MX.sym("p", n_p)
        way = ca.reshape(x, dof, w)                             # column k: waypoint k
        inv_dt = p[0]
        offset = 1
        targets: list[ca.MX] = []
        if self.objective == "tracking":
            targets = [ca.reshape(p[offset:offset + 3 * w], 3, w),
                       ca.reshape(p[offset + 3 * w:offset + 12 * w], 3, 3 * w)]
            offset += 12 * w
        slots = []
        for pool, wd in zip(self._pools, widths, strict=True):
            size = pool.capacity * wd * self._n_configs
            slots.append(ca.reshape(p[offset:offset + size], pool.capacity,
                                    wd * self._n_configs))
            offset += size
        slots_way = [s[:, :wd * w] for s, wd in zip(slots, widths, strict=True)]
        slots_int = [s[:, wd * w:] for s, wd in zip(slots, widths, strict=True)]

        def elements(lam_f: Any, lam_bend: Any, lam_clear: Any, fn: str) -> tuple[Any, Any]:
            """Mapped waypoint and interval elements (or their Hessians with fn)."""
            fw = waypoint if fn == "value" else ca.Function(
                "waypoint_hessian", way_inputs,
                [ca.hessian(waypoint(*way_inputs), way_inputs[0])[0]])
            pair = ca.vertcat(int_inputs[0], int_inputs[1])
            fi = interval if fn == "value" else ca.Function(
                "interval_hessian", int_inputs,
                [ca.hessian(interval(*int_inputs), pair)[0]])
            lam_way = lam_clear[:, :w]
            lam_int = lam_clear[:, w:]
            out_w = fw.map(w)(way, ca.repmat(lam_f, 1, w), lam_bend, lam_way, *slots_way,
                              *targets)
            out_i = fi.map(w - 1)(way[:, :-1], way[:, 1:], ca.repmat(lam_f, 1, w - 1),
                                  lam_int, *slots_int)
            return out_w, out_i

        objective = self._objective(way, targets)

        bending = ca.vertcat(*[way[3 * i, :] ** 2 + way[3 * i + 1, :] ** 2 for i in range(n)])
        rows = [ca.vec(bending)]                                # n × W, waypoint-major
        lengths = ca.mtimes(ca.DM(self._tendon_matrix), way)                   # n_t × W
        if self._speed:
            rows.append(ca.vec((lengths[:, 1:] - lengths[:, :-1]) * inv_dt))
        if self._accel:
            rows.append(ca.vec((lengths[:, 2:] - 2 * lengths[:, 1:-1] + lengths[:, :-2])
                               * inv_dt ** 2))
        linear_rows = ca.vertcat(*rows)
        g, jacobian = linear_rows, ca.jacobian(linear_rows, x)
        if self._pools:
            # Rows and their Jacobian per configuration (SX, mapped), chained through the
            # interpolation by a constant assembly matrix (as for the Hessian below).
            one = configuration_clearance(self._model, self._pools, cfg.face_smoothing)
            z_one = ca.SX.sym("z", dof)
            slots_one = [ca.SX.sym(f"slots_{q.kind}", q.capacity, wd)
                         for q, wd in zip(self._pools, widths, strict=True)]
            values = one(z_one, *slots_one)
            with_jacobian = ca.Function("clearance_jacobian", [z_one, *slots_one],
                                        [values, ca.jacobian(values, z_one)])
            configs = self._interpolated(way)
            clearance, blocks = with_jacobian.map(self._n_configs)(configs, *slots)
            pattern, assembly = _rows_assembly(rows_per_config, dof, w, checks)
            jac_g = ca.Function("jac_g", [x, p], [
                ca.vertcat(g, ca.vec(clearance)),
                ca.vertcat(jacobian, ca.MX(pattern, ca.mtimes(assembly, ca.vec(blocks))))],
                ["x", "p"], ["g", "jac_g_x"])
            # configuration after configuration
            g = ca.vertcat(g, ca.vec(one.map(self._n_configs)(configs, *slots)))
        else:
            jac_g = ca.Function("jac_g", [x, p], [g, jacobian], ["x", "p"], ["g", "jac_g_x"])

        # The Hessian of the Lagrangian, assembled from the element Hessians.
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", g.size1())
        lam_bend = ca.reshape(lam_g[:n * w], n, w)
        start = n * w + (n_t * (w - 1) if self._speed else 0) + (
            n_t * (w - 2) if self._accel else 0)
        lam_clear = ca.reshape(lam_g[start:], rows_per_config, self._n_configs)
        h_w, h_i = elements(lam_f, lam_bend, lam_clear, "hessian")
        pattern, assembly = _band_assembly(dof, w)
        hessian = ca.MX(pattern, ca.mtimes(assembly, ca.vertcat(ca.vec(h_w), ca.vec(h_i))))
        hess_lag = ca.Function("hess_lag", [x, p, lam_f, lam_g], [hessian],
                               ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])

        options: dict[str, Any] = {
            "ipopt.tol": cfg.tol,
            "ipopt.constr_viol_tol": cfg.constr_viol_tol,
            "ipopt.max_iter": cfg.max_iter,
            "ipopt.linear_solver": "mumps",      # HSL solvers are absent: never select them
            "ipopt.hessian_approximation": cfg.hessian,
            "ipopt.mu_strategy": "adaptive",
            "ipopt.print_level": cfg.print_level,
            "ipopt.sb": "yes",
            "print_time": cfg.print_level > 0,
            "error_on_fail": False,
        }
        options["jac_g"] = jac_g
        if cfg.hessian == "exact":
            options["hess_lag"] = hess_lag
        self.builds += 1
        return ca.nlpsol(f"polish_trajectory_{robot.name}_{self.objective}_{w}", "ipopt",
                         {"x": x, "p": p, "f": objective, "g": g}, options)

    # ------------------------------------------------------------ per solve

    def _all_distances(self, z: np.ndarray) -> np.ndarray:
        """(C, N·P + M) float64 distances (m, convex parts unsmoothed) at the waypoints and
        check points of a (W, 3n) trajectory in z."""
        configs = np.ascontiguousarray(self._interpolated(z.T).T)
        with jax.enable_x64(True):
            out = _distances(self.robot, self._arrays, len(self._self_pairs) > 0, configs)
        return np.asarray(out, dtype=np.float64)

    def _select(self, distances: np.ndarray, fixed_ends: bool = True
                ) -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray]]:
        """Slot parameters per pool (capacity × width·C), the clearance lbg (config-major)
        and, per configuration, the switched-on pair indices in row order. With
        ``fixed_ends`` the rows of a ``"path"`` problem's fixed start and goal are off."""
        selections: list[_Selection] = [
            select_slots(self._pools, self._n_bodies, self._self_pairs,
                         self.config.near_margin, self.safety_margin, row) for row in distances]
        parameters = [np.hstack([_one_hot(pool, self._n_bodies, s.parameters[p])
                                 for s in selections])
                      for p, pool in enumerate(self._pools)]
        lower = np.concatenate([s.lower for s in selections]) if selections else np.zeros(0)
        if fixed_ends and self.objective == "path" and len(lower):
            # Start and goal are fixed: their rows are constants Ipopt cannot change (and a
            # start closer than δ must not make the whole NLP infeasible); the
            # re-evaluation still measures them.
            width = len(lower) // self._n_configs
            lower[:width] = -np.inf
            lower[(self.waypoints - 1) * width: self.waypoints * width] = -np.inf
        return parameters, lower, [s.chosen for s in selections]

    def _evaluate(self, z: np.ndarray, dt: float) -> tuple[dict[str, float], np.ndarray]:
        """Float64, independent of Ipopt: the violation per family and all distances."""
        robot = self.robot
        distances = self._all_distances(z)
        lengths = _tendon_lengths(robot, z)
        speed = np.abs(np.diff(lengths, axis=0)) / dt
        accel = (np.abs(np.diff(lengths, 2, axis=0)) / (dt * dt) if len(z) > 2
                 else np.zeros((0, lengths.shape[1])))
        violations = {
            "clearance": (max(0.0, self.safety_margin - float(np.min(distances)))
                          if distances.size else 0.0),
            "limits": float(np.max(limit_violation_q(robot, z_to_q_numpy(z)))),
            "tendon_speed": max(0.0, float(np.max(speed, initial=0.0)) - robot.tendon_speed_max),
            "tendon_accel": max(0.0, float(np.max(accel, initial=0.0)) - robot.tendon_accel_max),
        }
        return violations, distances

    def _check_inputs(self, q0: Any, dt: Any, target_positions: Any,
                      target_rotations: Any) -> tuple[np.ndarray, float, Any, Any]:
        w, dof = self.waypoints, self.robot.dof
        q0 = np.asarray(q0, dtype=np.float64)
        if q0.shape != (w, dof):
            raise ValueError(f"q0 must be ({w}, {dof}) waypoints θ, φ, L, got {q0.shape}")
        if not (np.isscalar(dt) or np.ndim(dt) == 0) or not float(dt) > 0:
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
        if self.objective == "path":
            if target_positions is not None or target_rotations is not None:
                raise ValueError("targets are for the 'tracking' objective; this polisher "
                                 "was built for 'path'")
            return q0, float(dt), None, None
        if target_positions is None or target_rotations is None:
            raise ValueError("the 'tracking' objective needs target_positions (W, 3) and "
                             "target_rotations (W, 3, 3)")
        positions = np.asarray(target_positions, dtype=np.float64)
        rotations = np.asarray(target_rotations, dtype=np.float64)
        if positions.shape != (w, 3) or rotations.shape != (w, 3, 3):
            raise ValueError(f"targets must be ({w}, 3) positions and ({w}, 3, 3) rotations, "
                             f"got {positions.shape} and {rotations.shape}")
        return q0, float(dt), positions, rotations

    def solve(self, q0: Any, dt: float, target_positions: Any = None,
              target_rotations: Any = None) -> TrajectoryPolishResult:
        """Polish one trajectory.

        Args:
            q0: (W, 3n) warm start θ, φ, L (rad, rad, m), typically stage 2's answer; it
                may violate any constraint. For ``"path"`` its first and last rows are the
                fixed start and goal.
            dt: seconds between waypoints (> 0).
            target_positions: ``"tracking"`` only: (W, 3) tip positions, metres.
            target_rotations: ``"tracking"`` only: (W, 3, 3) tip rotation matrices.

        Returns a ``TrajectoryPolishResult``; a numerical failure is ``success=False`` with
        Ipopt's last iterate (or ``q0``), never an exception. Bad shapes raise ValueError.
        """
        start = time.perf_counter()
        q0, dt, positions, rotations = self._check_inputs(q0, dt, target_positions,
                                                          target_rotations)
        finite = np.all(np.isfinite(q0)) and (
            positions is None or (np.all(np.isfinite(positions))
                                  and np.all(np.isfinite(rotations))))
        if not finite:
            return TrajectoryPolishResult(q0, False, "non-finite input", math.inf,
                                          seconds=time.perf_counter() - start)
        cfg, w, dof = self.config, self.waypoints, self.robot.dof
        z0 = q_to_z_numpy(q0)
        lbx, ubx = np.tile(self._lbx, (w, 1)), np.tile(self._ubx, (w, 1))
        if self.objective == "path":
            lbx[0] = ubx[0] = z0[0]
            lbx[-1] = ubx[-1] = z0[-1]
        fixed = [1.0 / dt]
        if positions is not None:
            fixed += [positions.T.ravel(order="F"),
                      np.hstack(list(rotations)).ravel(order="F")]
        n_t = self._tendon_matrix.shape[0]
        lower = [np.full(self.robot.n_segments * w, -np.inf)]
        upper = [np.tile(self._theta_max ** 2, w)]
        if self._speed:
            lower.append(np.full(n_t * (w - 1), -self.robot.tendon_speed_max))
            upper.append(-lower[-1])
        if self._accel:
            lower.append(np.full(n_t * (w - 2), -self.robot.tendon_accel_max))
            upper.append(-lower[-1])

        near = self._all_distances(z0)
        z, status, ipopt_success, iterations, objective = z0, "not run", False, 0, math.nan
        violations, distances = self._evaluate(z0, dt)
        for _ in range(cfg.reselections + 1):
            slots, clearance_lower, chosen = self._select(near)
            parameters = np.concatenate([np.ravel(fixed[0]), *fixed[1:],
                                         *[s.ravel(order="F") for s in slots]])
            try:
                solution = self._solver(
                    x0=z.reshape(-1), p=parameters, lbx=lbx.reshape(-1), ubx=ubx.reshape(-1),
                    lbg=np.concatenate([*lower, clearance_lower]),
                    ubg=np.concatenate([*upper, np.full(clearance_lower.size, np.inf)]))
                stats = self._solver.stats()
                answer = np.asarray(solution["x"], dtype=np.float64).reshape(w, dof)
                status = str(stats.get("return_status", "unknown"))
                ipopt_success = bool(stats.get("success", False))
                iterations += int(stats.get("iter_count", 0))
                objective = float(solution["f"])
            except RuntimeError as exc:                # a numerical failure is a result
                answer, status, ipopt_success = z, f"error: {exc}", False
            if not np.all(np.isfinite(answer)):
                status, ipopt_success = f"{status} (non-finite iterate)", False
                break
            z = answer
            violations, distances = self._evaluate(z, dt)
            if not self._pools:
                break
            switched_on = np.zeros(distances.shape, dtype=bool)
            for c, flat in enumerate(chosen):
                switched_on[c, flat] = True
            violated = distances < self.safety_margin - cfg.violation_tolerance
            if not np.any(violated & ~switched_on):
                break
            # A pair without a slot came too close: give the pairs near either point the
            # slots and go on from here.
            near = np.minimum(near, distances)
        max_violation = max(violations.values())
        errors = None
        if positions is not None:
            with jax.enable_x64(True):
                errors = np.asarray(_pose_errors(self.robot, z, positions, rotations),
                                    dtype=np.float64)
        return TrajectoryPolishResult(
            q=z_to_q_numpy(z),
            success=ipopt_success and max_violation <= cfg.violation_tolerance,
            status=status,
            max_violation=max_violation,
            violations=violations,
            objective=objective,
            iterations=iterations,
            seconds=time.perf_counter() - start,
            pose_errors=errors,
        )

    # ------------------------------------------------------------ checks

    def _slot_values(self, q_near: Any, q: Any) -> tuple[np.ndarray, np.ndarray]:
        """The clearance rows switched on for the warm start ``q_near`` (W, 3n), evaluated
        at ``q`` (W, 3n) by the NLP's own mapped CasADi function, and the world's float64
        distances of the same pairs (m, convex parts with ``face_smoothing``): the two
        must agree."""
        z_near, z = (q_to_z_numpy(x) for x in (q_near, q))
        slots, lower, chosen = self._select(self._all_distances(z_near), fixed_ends=False)
        one = configuration_clearance(self._model, self._pools, self.config.face_smoothing)
        configs = self._interpolated(z.T)
        values = np.asarray(one.map(self._n_configs)(configs, *slots)).reshape(-1, order="F")
        with jax.enable_x64(True):
            pairs = pair_distances_z(self.robot, self._arrays, configs.T,
                                     self.config.face_smoothing).reshape(self._n_configs, -1) \
                if self._arrays is not None else np.zeros((self._n_configs, 0))
            own = (self_distances_z(self.robot, configs.T) if len(self._self_pairs)
                   else np.zeros((self._n_configs, 0)))
        world = np.concatenate([np.asarray(pairs), np.asarray(own)], axis=1)
        expected = np.concatenate([world[c, flat] for c, flat in enumerate(chosen)])
        return values[np.isfinite(lower)], expected


def _band_assembly(dof: int, waypoints: int) -> tuple[ca.Sparsity, ca.DM]:
    """The upper-triangular block-tridiagonal Hessian pattern of ``waypoints`` blocks of
    ``dof`` variables, and the constant 0/1 matrix that sums the waypoint element
    Hessians (dof × dof·W, column-major) and the interval element Hessians
    (2dof × 2dof·(W − 1)) into its nonzeros."""
    entries: list[tuple[int, int, int]] = []          # (global row, global column, source)
    for k in range(waypoints):
        for j in range(dof):
            for i in range(j + 1):
                entries.append((k * dof + i, k * dof + j, (k * dof + j) * dof + i))
    base = dof * dof * waypoints
    two = 2 * dof
    for k in range(waypoints - 1):
        for j in range(two):
            for i in range(j + 1):
                entries.append((k * dof + i, k * dof + j, base + (k * two + j) * two + i))
    size = dof * waypoints
    keys = sorted({(r, c) for r, c, _ in entries}, key=lambda rc: (rc[1], rc[0]))
    index = {rc: i for i, rc in enumerate(keys)}
    pattern = ca.Sparsity.triplet(size, size, [r for r, _ in keys], [c for _, c in keys])
    sources = base + two * two * (waypoints - 1)
    assembly = ca.DM(ca.Sparsity.triplet(len(keys), sources,
                                         [index[(r, c)] for r, c, _ in entries],
                                         [src for _, _, src in entries]),
                     np.ones(len(entries)))
    return pattern, assembly


def _rows_assembly(rows: int, dof: int, waypoints: int, checks: int) -> tuple[ca.Sparsity,
                                                                              ca.DM]:
    """The sparsity of the clearance rows' Jacobian (``rows`` per configuration, the
    configurations of ``TrajectoryPolisher._interpolated``) with respect to the (dof·W)
    waypoint variables, and the constant matrix that maps the per-configuration
    Jacobians (rows × dof·C, column-major) to its nonzeros: a check point at fraction s of
    interval k depends on waypoint k with weight 1 − s and on waypoint k + 1 with s."""
    entries: list[tuple[int, int, int, float]] = []     # (row, column, source, weight)

    def block(config: int, waypoint: int, weight: float) -> None:
        for j in range(dof):
            for i in range(rows):
                entries.append((config * rows + i, waypoint * dof + j,
                                (config * dof + j) * rows + i, weight))

    for k in range(waypoints):
        block(k, k, 1.0)
    config = waypoints
    for k in range(waypoints - 1):
        for c in range(1, checks + 1):
            s = c / (checks + 1)
            block(config, k, 1.0 - s)
            block(config, k + 1, s)
            config += 1
    keys = sorted({(r, c) for r, c, _, _ in entries}, key=lambda rc: (rc[1], rc[0]))
    index = {rc: i for i, rc in enumerate(keys)}
    pattern = ca.Sparsity.triplet(rows * config, dof * waypoints,
                                  [r for r, _ in keys], [c for _, c in keys])
    assembly = ca.DM(ca.Sparsity.triplet(len(keys), rows * dof * config,
                                         [index[(r, c)] for r, c, _, _ in entries],
                                         [src for _, _, src, _ in entries]),
                     [weight for _, _, _, weight in entries])
    return pattern, assembly
