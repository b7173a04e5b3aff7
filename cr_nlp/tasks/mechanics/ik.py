"""Inverse kinematics in tension space: tendon tensions that put the tip of the Cosserat
rod model (``model.cosserat``) at target positions (and orientations), batched.

The problem of one target: tensions τ ∈ [0, τ_max]ⁿ and the moment at the base M(0)
(the shooting unknown of the statics, here an unknown of the IK itself) minimise

    ‖p(τ, M(0)) − p*‖² + ‖L·rot(R*ᵀR)‖² (with an orientation) + w_eq‖L·(M(L) − M_tip)/(EI/L)‖²
    + ρ²‖τ/τ_max‖²,

one integration pass of the rod per residual evaluation. The equilibrium term is zero at
a solution, so the answer is an equilibrium of the rod, not a penalty compromise (it and
M(0) are left out when no external force acts: then M(0) = M_tip plus the point moments
exactly). The loads are those of the forward statics (``model.loads``): tip wrench,
gravity, a force per metre and point wrenches at given arc lengths.

The unknowns. Three or more tendons per segment (evenly around it) bend it in two
directions, so many tension sets give one shape. The LM therefore works on each tendon
group's net pull moment d = Σ τ_i (r_i × e3) (2 numbers per segment; one group for shared
routing), and the tensions are the least ones giving it: the two tendons whose directions
enclose d (a 2×2 solve), the others slack, capped at τ_max (``model.tendon_groups``).
That map is continuous and piecewise linear, needs no bounds in the LM, and never asks
antagonistic tendons to fight. Robots with fewer than three tendons per group solve
in the tensions themselves, kept in [0, τ_max] by the LM's active-set projection, with
ρ (a length, default 10 µm) picking the least-tension answer. The LM's Jacobian is taken
by forward differences (``LMConfig.jacobian``), and every target starts from the pool
tension set whose tip is nearest (a batch of forward statics solves).

Success is the one verdict (``world.verdict``) on numbers re-evaluated independently of
the LM: the tip of a fresh forward statics solve (``solve_statics``, its own shooting) of
the answer's tensions within ``tolerance`` of the target, that solve converged, the
tensions within their bounds, and with a scene the clearance of the solved backbone
(python-fcl capsules, ``world.check.check_chains``) and its self-clearance at least the
safety margin. Units: metres, radians, newtons, N·m, m/s².
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from ...model import Robot, load_robot
from ...model.cosserat import CaseLoads, StaticsConfig, StaticsResult, moment_scale
from ...model.cosserat import tip_equilibrium as _tip_equilibrium
from ...model.loads import StaticLoads, static_loads
from ...model.mechanics import require_mechanics
from ...model.rotations import matrix_from_wxyz
from ...model.statics import solve_statics
from ...model.tendon_groups import (
    moments_from_tensions,
    tendon_groups,
    tensions_from_moments,
)
from ...runtime import configure
from ...stages.refine._lm import LMConfig, lm_solve
from ...world.check import check_chains
from ...world.scene import Scene, load_scene
from ...world.verdict import judge_many
from .._result import Stage
from .._timing import StageTiming
from ._ik_result import TensionIKResult as TensionIKResult

EQUILIBRIUM_WEIGHT = 10.0
"""Weight of the equilibrium residual against the tip residual (both in metres)."""


@dataclass(frozen=True)
class TensionIKConfig:
    """Settings of the tension-space IK."""

    tolerance: float = 1e-4
    """Success: the re-evaluated tip is within this of the target (m; with orientations
    the pose error √(‖Δp‖² + (L·Δθ)²), Δθ in rad, L the robot's length)."""
    tension_weight: float = 1e-5
    """ρ, metres: the least-tension preference (see the module's docstring)."""
    pool_size: int = 16384
    """Random tension sets whose tips seed the search (one forward statics batch, once per
    solver and load case)."""
    iterations: int = 20
    """LM iterations at most."""
    retry_seeds: int = 6
    """Targets that fail the verdict are solved again from their next-nearest pool
    entries, this many (0: no retry)."""
    safety_margin: float = 0.002
    """δ, metres: the clearance every answer keeps from obstacles and between segments at
    least two apart."""
    seed: int = 0
    """Seed of the pool."""
    statics: StaticsConfig = field(default_factory=StaticsConfig)
    """The rod discretisation (shared by the LM and the verdict's solve) and its dtype."""


# ---------------------------------------------------------------- the LM problem

def _residual(robot: Robot, statics: StaticsConfig, weights: tuple[float, float, float, float],
              shoot: bool, z: jax.Array, p: tuple, shared: Any) -> jax.Array:
    """One target's residual (metres) at z = (the unknowns of the tensions, then with
    ``shoot`` M(0)/(EI/L)); ``weights`` are (τ_max N, EI/L N·m, robot length m, ρ m)."""
    del shared
    tension_max, scale, length, rho = weights
    target, target_rot, rot_weight, loads = p
    n = robot.n_tendons
    groups = tendon_groups(robot)
    if groups is None:
        tension = z[:n] * tension_max
        width = n
        unknowns = rho * z[:n]
    else:
        width = 2 * len(groups.index)
        reference = tension_max * robot.tendons.radius
        tension = tensions_from_moments(groups, n, tension_max,
                                         z[:width].reshape(-1, 2) * reference)
        unknowns = jnp.zeros(0, z.dtype)
    base_moment = (z[width:] * scale if shoot
                   else loads.moment + loads.point_moment.sum(axis=0))
    tip, rot, eq = _tip_equilibrium(robot, statics)(tension, base_moment, loads)
    # rot(R*ᵀR): the vector of its skew part, sin of the angle about its axis.
    rel = target_rot.T @ rot
    twist = 0.5 * jnp.stack([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0],
                             rel[1, 0] - rel[0, 1]])
    rows = [tip - target, rot_weight * length * twist, unknowns]
    if shoot:
        rows.append(EQUILIBRIUM_WEIGHT * length * eq / scale)
    return jnp.concatenate(rows)


def _project(n: int, z: jax.Array) -> jax.Array:
    """Tensions onto [0, τ_max] (z's first n entries onto [0, 1]); M(0) is free."""
    return z.at[:, :n].set(jnp.clip(z[:, :n], 0.0, 1.0))


def _identity(z: jax.Array) -> jax.Array:
    return z


class TensionIKSolver:
    """Tension-space IK of a robot with a ``mechanics`` block (batched, numpy in/out)."""

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | None = None,
                 config: TensionIKConfig = TensionIKConfig()) -> None:
        configure()
        self.robot = load_robot(robot)
        require_mechanics(self.robot, "tension-space IK")
        self.scene = None if scene is None else load_scene(scene)
        self.config = config
        self.tension_max = float(self.robot.mechanics.tension_max)
        self.length = float(sum(s.length_min for s in self.robot.segments))
        self._pool: dict[bytes, tuple[np.ndarray, cKDTree]] = {}
        self._groups = tendon_groups(self.robot)
        # One residual and projection object per solver and case (with or without M(0)
        # as an unknown): lm_solve compiles per object.
        weights = (self.tension_max, moment_scale(self.robot), self.length,
                   config.tension_weight)
        self._residuals = {shoot: partial(_residual, self.robot, config.statics, weights, shoot)
                           for shoot in (False, True)}
        self._project = (_identity if self._groups is not None
                         else partial(_project, self.robot.n_tendons))

    # ------------------------------------------------------------ the seeds

    def pool(self, loads: StaticLoads) -> tuple[np.ndarray, cKDTree]:
        """(tensions (P, n) N, a k-d tree of their tips (m, world frame)): the seed pool
        under one load case, random tensions on one or two tendons of each segment (most
        robots bend with at most two of three), solved once and kept."""
        key = b"".join(np.ascontiguousarray(a).tobytes() for a in loads.arrays())
        if key not in self._pool:
            rng = np.random.default_rng(self.config.seed)
            per = self.robot.tendons.per_segment
            n = self.robot.n_tendons
            size = self.config.pool_size
            tensions = rng.uniform(0.0, self.tension_max, (size, n))
            # Slacken one tendon (or, for a third of the sets, two) of every segment.
            for s in range(n // per):
                drop = rng.integers(0, per, size)
                tensions[np.arange(size), s * per + drop] = 0.0
                second = rng.random(size) < 1 / 3
                tensions[np.flatnonzero(second), s * per + (drop[second] + 1) % per] = 0.0
            one = loads.rows(np.zeros(size, int))
            result = solve_statics(self.robot, tensions, one.tip_force, one.tip_moment,
                                   one.gravity, self.config.statics,
                                   distributed_force=one.distributed_force,
                                   point_loads=one.point_load_lists())
            keep = result.converged
            self._pool[key] = (tensions[keep], cKDTree(result.tip_position[keep]))
        return self._pool[key]

    # ------------------------------------------------------------ solve

    def solve(self, positions: Any, wxyz: Any = None, tip_force: Any = None,
              tip_moment: Any = None, gravity: Any = None, *,
              distributed_force: Any = None, point_loads: Any = None) -> TensionIKResult:
        """Tensions for each target.

        Args:
            positions: (B, 3) or (3,) target tip positions, m, world frame.
            wxyz: None (position only) or (B, 4) / (4,) target orientations (unit
                quaternions w, x, y, z); a row of NaN leaves that target's orientation free.
            tip_force, tip_moment, gravity: (3,) or (B, 3) loads in the world frame (N,
                N·m, m/s²); default none.
            distributed_force: (3,) or (B, 3) force per metre along the backbone, N/m.
            point_loads: ``[{"s": m, "force": [N], "moment": [N·m]}]`` for every target,
                or one such list per target (world frame; ``model.loads``).

        Returns:
            ``TensionIKResult`` with every target's tensions and the independent verdict.
        """
        positions = np.atleast_2d(np.asarray(positions, dtype=float))
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"positions: expected (B, 3) metres, got shape "
                             f"{np.shape(positions)}")
        count = len(positions)
        finite = np.all(np.isfinite(positions), axis=1)
        if not finite.all():  # such rows are reported, not solved
            return self._solve_finite(finite, positions, wxyz, tip_force, tip_moment, gravity,
                                      distributed_force, point_loads)
        if wxyz is None:
            quats = np.full((count, 4), np.nan)
        else:
            quats = np.array(np.broadcast_to(np.asarray(wxyz, dtype=float), (count, 4)))
            rows = ~np.any(np.isnan(quats), axis=1)
            norms = np.linalg.norm(quats[rows], axis=1)
            if np.any(np.abs(norms - 1.0) > 1e-6):
                bad = np.flatnonzero(rows)[np.argmax(np.abs(norms - 1.0))]
                raise ValueError(f"wxyz: target {bad} is not a unit quaternion")
        loads = static_loads(count, self.length, tip_force, tip_moment, gravity,
                             distributed_force, point_loads)
        timing = StageTiming()
        if count == 0:
            nothing = np.zeros((0, self.robot.n_tendons))
            empty = np.zeros(0)
            return TensionIKResult(
                robot=self.robot, tensions=nothing, target_position=positions,
                target_wxyz=quats, position=positions, wxyz=quats, pose_error=empty,
                position_error=empty, rotation_error=empty, min_clearance=empty,
                max_violation=empty, success=np.zeros(0, bool), reason=[],
                tip_force=loads.tip_force, tip_moment=loads.tip_moment,
                gravity=loads.gravity, distributed_force=loads.distributed_force,
                point_loads=[], tendon_displacements=nothing, timing=timing)
        start = time.perf_counter()
        tensions = self._seeds(positions, loads, 0)
        timing.explore = time.perf_counter() - start
        start = time.perf_counter()
        tensions = self._lm(tensions, positions, quats, loads)
        timing.refine = time.perf_counter() - start
        start = time.perf_counter()
        result = self._verdict(tensions, positions, quats, loads, timing)
        timing.verify = time.perf_counter() - start
        for k in range(1, self.config.retry_seeds + 1):
            failed = np.flatnonzero(~result.success)
            if not failed.size:
                break
            start = time.perf_counter()
            part = loads.rows(failed)
            retry = self._lm(self._seeds(positions[failed], part, k), positions[failed],
                             quats[failed], part)
            timing.refine += time.perf_counter() - start
            start = time.perf_counter()
            again = self._verdict(retry, positions[failed], quats[failed], part, timing)
            better = again.success | (again.pose_error < result.pose_error[failed])
            _replace_rows(result, again, failed[better], np.flatnonzero(better))
            timing.verify += time.perf_counter() - start
        result.timing = timing
        return result

    def _solve_finite(self, finite: np.ndarray, positions: np.ndarray, wxyz: Any,
                      *loads: Any) -> TensionIKResult:
        """``solve`` on the rows with finite positions; the others failed, with a reason."""
        count = len(positions)

        def rows(value: Any, width: int) -> Any:
            if value is None:
                return None
            arr = np.asarray(value, dtype=float)
            return arr[finite] if arr.ndim == 2 and len(arr) == count else arr

        points = loads[4]
        if points is not None and len(points) == count and not isinstance(points[0], dict):
            points = [p for p, keep in zip(points, finite, strict=True) if keep]
        part = self.solve(positions[finite], rows(wxyz, 4), *(rows(v, 3) for v in loads[:3]),
                          distributed_force=rows(loads[3], 3), point_loads=points)
        full = self.solve(np.zeros((0, 3)))
        for name in ("tensions", "target_position", "target_wxyz", "position", "wxyz",
                     "pose_error", "position_error", "rotation_error", "min_clearance",
                     "max_violation", "success", "tip_force", "tip_moment", "gravity",
                     "distributed_force", "tendon_displacements"):
            values = getattr(part, name)
            out = (np.zeros(count, bool) if values.dtype == bool
                   else np.full((count, *values.shape[1:]), np.nan))
            out[finite] = values
            setattr(full, name, out)
        full.target_position = positions
        full.reason = ["the target has non-finite coordinates"] * count
        full.stage = [Stage.REFINE if ok else Stage.NONE for ok in finite.tolist()]
        full.notes = [[] for _ in range(count)]
        full.point_loads = [[] for _ in range(count)]   # a refused target: none solved for
        for i, j in zip(np.flatnonzero(finite).tolist(), range(len(part)), strict=True):
            full.point_loads[i] = part.point_loads[j]
        full.violations = {k: np.full(count, np.nan) for k in part.violations}
        for k, values in part.violations.items():
            full.violations[k][finite] = values
        for i, j in zip(np.flatnonzero(finite).tolist(), range(len(part)), strict=True):
            full.reason[i] = part.reason[j]
        full.timing = part.timing
        return full

    def _seeds(self, positions: np.ndarray, loads: StaticLoads, rank: int) -> np.ndarray:
        """The pool tensions whose tip is the ``rank``-th nearest to each target, under the
        target's loads when all targets share one load case, else without loads."""
        shared = all(np.all(v == v[:1]) for v in loads.arrays())
        case = (loads.rows(np.zeros(1, int)) if shared
                else static_loads(1, self.length))
        pool_t, tree = self.pool(case)
        _, order = tree.query(positions, k=[rank + 1])
        return pool_t[order[:, 0]]

    def _lm(self, tensions: np.ndarray, positions: np.ndarray, quats: np.ndarray,
            loads: StaticLoads) -> np.ndarray:
        """LM from the given tensions; returns the answer's tensions (B, n), N."""
        robot, cfg = self.robot, self.config
        dtype = np.float64 if cfg.statics.dtype == "float64" else np.float32
        base_rot = matrix_from_wxyz(np.asarray(robot.base_wxyz))
        base_pos = np.asarray(robot.base_position)
        # Targets and loads into the base frame (the rod is solved there).
        target = (positions - base_pos) @ base_rot
        oriented = ~np.any(np.isnan(quats), axis=1)
        target_rot = np.tile(np.eye(3), (len(positions), 1, 1))
        if oriented.any():
            target_rot[oriented] = base_rot.T @ np.stack(
                [matrix_from_wxyz(q) for q in quats[oriented]])
        frame = loads.in_base_frame(base_rot)
        moment = frame.tip_moment + frame.point_moment.sum(axis=1)
        scale = moment_scale(robot)
        n = robot.n_tendons
        shoot = bool(np.any(frame.has_force()))
        if self._groups is None:
            z0 = tensions / self.tension_max
        else:
            reference = self.tension_max * robot.tendons.radius
            z0 = moments_from_tensions(self._groups, tensions).reshape(len(tensions), -1)
            z0 = z0 / reference
        width = z0.shape[1]
        if shoot:  # M(0) starts at the tip and point moments (exact without forces)
            z0 = np.concatenate([z0, moment / scale], axis=1)
        size = max(16, 1 << (len(z0) - 1).bit_length())
        pad = size - len(z0)

        def padded(a: np.ndarray) -> jax.Array:
            return jnp.asarray(np.concatenate([a, np.repeat(a[:1], pad, axis=0)]), dtype)

        with jax.enable_x64(dtype == np.float64):
            params = tuple(padded(a) for a in (target, target_rot,
                                               oriented.astype(float))) + (
                CaseLoads(*(padded(a) for a in frame.arrays())),)
            bounds = None
            if self._groups is None:
                extra = z0.shape[1] - n
                bounds = (jnp.asarray(np.r_[np.zeros(n), np.full(extra, -np.inf)], dtype),
                          jnp.asarray(np.r_[np.ones(n), np.full(extra, np.inf)], dtype))
            z, _, _ = lm_solve(self._residuals[shoot], self._project, padded(z0), params,
                               None, jnp.ones(z0.shape[1], dtype), jnp.asarray(cfg.iterations),
                               LMConfig(jacobian="differences", linear_solver="unrolled",
                                        cost_tolerance=0.5 * (1e-3 * cfg.tolerance) ** 2,
                                        stall_tolerance=1e-6), bounds=bounds)
            z = np.asarray(z, dtype=float)[:len(z0), :width]
        if self._groups is None:
            return np.clip(z, 0.0, 1.0) * self.tension_max
        reference = self.tension_max * robot.tendons.radius
        with jax.enable_x64(True):
            tension = jax.vmap(partial(tensions_from_moments, self._groups, n,
                                       self.tension_max))(
                jnp.asarray(z.reshape(len(z), -1, 2) * reference))
        return np.asarray(tension, dtype=float)

    def _verdict(self, tensions: np.ndarray, positions: np.ndarray, quats: np.ndarray,
                 loads: StaticLoads, timing: StageTiming) -> TensionIKResult:
        """The independent check: a fresh forward statics solve of the answer's tensions,
        the bounds, and with a scene python-fcl clearance of the solved backbone."""
        cfg = self.config
        statics: StaticsResult = solve_statics(
            self.robot, tensions, loads.tip_force, loads.tip_moment, loads.gravity,
            cfg.statics, distributed_force=loads.distributed_force,
            point_loads=loads.point_load_lists())
        position_error = np.linalg.norm(statics.tip_position - positions, axis=1)
        oriented = ~np.any(np.isnan(quats), axis=1)
        rotation_error = np.full(len(positions), np.nan)
        for i in np.flatnonzero(oriented):
            rel = matrix_from_wxyz(quats[i]).T @ statics.tip_rotation[i]
            rotation_error[i] = np.arccos(np.clip(0.5 * (np.trace(rel) - 1.0), -1.0, 1.0))
        pose_error = np.sqrt(position_error ** 2
                             + np.where(oriented, self.length * np.nan_to_num(rotation_error),
                                        0.0) ** 2)
        pose_error = np.where(statics.converged, pose_error, np.nan)
        limits = np.maximum(np.max(-tensions, axis=1),
                            np.max(tensions - self.tension_max, axis=1)).clip(0.0)
        per_segment = (statics.positions.shape[1] - 1) // len(self.robot.segments)
        checked = check_chains(self.robot, self.scene, statics.positions, per_segment)
        verdicts = judge_many(
            margin=cfg.safety_margin, limits=limits,
            min_clearance=None if self.scene is None else checked.obstacle_distance,
            self_clearance=checked.self_distance, pose_error=pose_error,
            pose_tolerance=cfg.tolerance)
        reason = [r if c else f"the forward statics did not converge (residual {res:.1e} N·m)"
                  for r, c, res in zip(verdicts.reason, statics.converged, statics.residual,
                                       strict=True)]
        return TensionIKResult(
            robot=self.robot, tensions=tensions, target_position=positions, target_wxyz=quats,
            position=np.array(statics.tip_position), wxyz=np.array(statics.tip_wxyz),
            pose_error=pose_error,
            position_error=position_error, rotation_error=rotation_error,
            min_clearance=np.array(checked.obstacle_distance),
            max_violation=np.array(verdicts.max_violation),
            success=np.array(verdicts.success & statics.converged), reason=reason,
            tip_force=loads.tip_force, tip_moment=loads.tip_moment, gravity=loads.gravity,
            distributed_force=loads.distributed_force,
            point_loads=loads.point_load_lists(),
            tendon_displacements=np.array(statics.tendon_displacements), timing=timing,
            violations=dict(verdicts.violations))


def _replace_rows(result: TensionIKResult, other: TensionIKResult, rows: np.ndarray,
                  from_rows: np.ndarray) -> None:
    """Rows ``rows`` of ``result`` from rows ``from_rows`` of ``other`` (same targets)."""
    for name in ("tensions", "position", "wxyz", "pose_error", "position_error",
                 "rotation_error", "min_clearance", "max_violation", "success",
                 "tendon_displacements"):
        values = np.array(getattr(result, name))
        values[rows] = getattr(other, name)[from_rows]
        setattr(result, name, values)
    for k, values in other.violations.items():
        result.violations[k][rows] = values[from_rows]
    for i, j in zip(rows.tolist(), from_rows.tolist(), strict=True):
        result.reason[i] = other.reason[j]


def solve_tension_ik(robot: Robot | str | dict, positions: Any, wxyz: Any = None,
                     **loads: Any) -> TensionIKResult:
    """One-call tension-space IK with the default config (see ``TensionIKSolver.solve``):
    positions in metres, wxyz unit quaternions, loads in N and N·m; tensions in N."""
    return TensionIKSolver(robot).solve(positions, wxyz, **loads)
