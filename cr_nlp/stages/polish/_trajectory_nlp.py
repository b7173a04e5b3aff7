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

Constraints (docs/design.md §2):

- box bounds ``|uxᵢ|, |uyᵢ| ≤ θmaxᵢ``, ``Lᵢ`` in its range; bending disk
  ``uxᵢ² + uyᵢ² ≤ θmaxᵢ²`` per segment and waypoint;
- tendon speed ``|ℓ(z_{k+1}) − ℓ(z_k)|/Δt ≤ v_max`` and acceleration
  ``|ℓ_{k+1} − 2ℓ_k + ℓ_{k−1}|/Δt² ≤ a_max`` per tendon. Tendon lengths are linear in z
  (``ℓ = A·z + b``), so these are linear rows ``A·Δz·(1/Δt)`` with 1/Δt an NLP parameter:
  the rows are in m/s and m/s² whatever Δt is, and a new Δt needs no rebuild. A family
  whose limit is infinite has no rows;
- clearance ``d ≥ δ`` at every waypoint and at ``interpolation_checks`` evenly spaced
  points inside every interval (linear in z, the motion the planner verifies). The
  planner sets ``interpolation_checks = verify_samples − 1``, so the polish constrains
  every configuration the python-fcl verification checks: a motion that cuts an
  obstacle between two waypoints is a violated row of the NLP, not only a rejection
  afterwards. The rows are the pair slots of ``stages.polish._clearance_rows``, one configuration's
  rows
  one CasADi function mapped over all configurations.

Derivatives (``stages.polish._clearance_rows``): exact first derivatives; the Hessian of the
Lagrangian
holds the objective's and the bending disks' exact second derivatives, assembled from
per-waypoint and per-interval element Hessians into its block-tridiagonal band, and not
the clearance rows' curvature (measured on the shelf: the same optima, the Hessian 20×
cheaper; the stage-wise structure is then cheap enough that the general sparse MUMPS
factorisation of the band is not the bottleneck).

The NLP is built once per polisher (robot, scene, waypoints, objective, checks) and set of
clearance-row capacities (the rows of a group that no near pair needs are left out of
Ipopt's KKT system), and re-solved with new parameters (1/Δt, targets, slots) and
bounds. Every answer is projected onto the simple limits and re-evaluated in float64
independently of Ipopt (the world's distances over all pairs at every waypoint and check
point, numpy limits and tendon finite differences) before it is called a success.

A solve may be given a time limit (``solve(..., time_limit=)``): its Ipopt runs stop at the
deadline (``stages.polish._ipopt.Deadline``), no re-selection round starts after it, and the
result is the best round so far with ``out_of_time`` set.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from ...model import Robot, q_to_z_numpy, z_to_q_numpy
from ...model._ops import NUMPY
from ...model.kinematics import model_tendon_lengths
from ...model.limits import project_bending
from ...world.scene import Scene
from ...world.verdict import describe_violations
from ._clearance_rows import SlotRows, select_slots_batch
from ._compiled_functions import pending
from ._ipopt import (
    TIME_LIMIT_STATUS,
    NLPSettings,
    WarmStart,
    build_solver,
    ipopt_options,
    run_solver,
)
from ._polisher import ClearancePolisher

OBJECTIVES = ("path", "tracking")


@dataclass(frozen=True)
class TrajectoryPolishConfig(NLPSettings):
    """Settings of the trajectory and path polish (the shared ones: ``NLPSettings``)."""

    max_iter: int = 200
    """Ipopt iterations per attempt (a whole trajectory: more than an IK target's)."""
    near_margin: float = 0.3
    """As ``NLPSettings``; pairs coming closer during the solve trigger a re-selection."""
    max_pairs: int = 8
    """As ``NLPSettings``, per configuration."""
    reselections: int = 4
    """How many times a solve may go on from its answer with re-placed check points and
    re-assigned slots: when a pair without a slot (or a sample without a check point)
    came closer than δ, or the answer stopped at the step limit."""
    step_limit: float = 0.5
    """Per round, every body sphere may move at most about ``step_limit·room`` metres,
    where a waypoint's room is ``near_margin`` or, if larger, the smallest pair distance at
    it and in its two intervals (at most twice ``near_margin``): each of its variables
    stays within that distance divided by its largest lever Σⱼ‖∂c/∂zⱼ‖ (m per rad or m)
    at the round's start; a round stopped by the limit goes on in the next. Pairs farther
    than ``near_margin`` have no rows; without the limit a solve pulled paths straight
    through such obstacles (measured on random_27: 0.2–0.4 m deep). The last round is
    free of it when only the limit stopped the one before."""
    interpolation_checks: int = 3
    """Clearance check points inside each interval, at the ``verify_samples`` samples
    where the motion comes closest to an obstacle (all of them with the default 3 and 4,
    so the polish constrains every configuration the verification checks). Fewer points
    are placed per solve and moved when the answer comes closer elsewhere; measured on
    random_27, one point per interval left 9/10 answers failing at the other samples
    (the motion slides along a sphere: the chord between two checked points cuts it)."""
    verify_samples: int = 4
    """Every interval is re-evaluated at fractions j/``verify_samples`` (the samples
    ``verify_trajectory`` checks with python-fcl); a polish succeeds only if all keep δ."""
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
    clearance_curvature: str = "full"
    """As ``NLPSettings`` (exact second derivatives by default)."""
    hessian: str = "exact"
    """Ipopt's ``hessian_approximation``: ``"exact"`` (the structured Hessian of the
    module docstring: exact objective and bending terms, no clearance curvature) or
    ``"limited-memory"`` (L-BFGS)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.interpolation_checks < 0 or self.reselections < 0:
            raise ValueError("interpolation_checks and reselections must be ≥ 0")
        if self.verify_samples < 1 or self.interpolation_checks > self.verify_samples - 1:
            raise ValueError("verify_samples must be ≥ 1 and interpolation_checks ≤ "
                             f"verify_samples − 1, got {self.verify_samples} and "
                             f"{self.interpolation_checks}")
        if self.hessian not in ("exact", "limited-memory"):
            raise ValueError(f"hessian must be 'exact' or 'limited-memory', got {self.hessian!r}")


@dataclass
class TrajectoryPolishResult:
    """The outcome of one trajectory polish (never raised: a failure is ``success=False``)."""

    q: np.ndarray
    """(W, 3n) waypoints θ, φ, L (rad, rad, m): Ipopt's answer projected onto the simple
    limits, or the warm start if Ipopt produced nothing finite."""
    success: bool
    """The re-evaluated ``max_violation`` ≤ ``violation_tolerance``: every constraint
    holds at every waypoint and sample, whatever Ipopt reported (``status``; an answer
    that is valid is not thrown away because Ipopt stopped early)."""
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
    warm_start_violations: dict[str, float] = field(default_factory=dict)
    """``violations`` of the warm start, as the NLP's constraints see it (the same
    families, the same configurations)."""
    out_of_time: bool = False
    """The solve's time limit stopped it (an Ipopt run stopped at the deadline, or no
    time was left for the next round); the answer is the best round so far."""


def _tendon_lengths(robot: Robot, z: np.ndarray) -> np.ndarray:
    """(W, n_tendons) tendon lengths (m) of (W, 3n) bending vectors, float64 numpy."""
    values = model_tendon_lengths(NUMPY, robot, [z[:, i] for i in range(robot.dof)])
    return np.stack(np.broadcast_arrays(*values), axis=-1).reshape(len(z), -1)


def interpolated(way: Any, fractions: Any) -> Any:
    """The (3n × C) configurations of a (3n × W) trajectory (numpy or CasADi): the W
    waypoints, then interval after interval its check points, (1 − s)·z_k + s·z_{k+1} for
    the (checks × (W − 1)) ``fractions`` s, C = W + checks·(W − 1)."""
    checks = fractions.shape[0]
    if checks == 0:
        return way
    step = way[:, 1:] - way[:, :-1]
    if isinstance(way, (ca.MX, ca.SX)):
        inner = [way[:, :-1] + step * ca.repmat(fractions[c, :], way.shape[0], 1)
                 for c in range(checks)]
        # Column k of the stack holds interval k's points one above the other.
        return ca.horzcat(way, ca.reshape(ca.vertcat(*inner), way.shape[0], -1))
    inner = way[:, :-1, None] + step[:, :, None] * np.asarray(fractions).T[None]
    return np.hstack([way, inner.reshape(way.shape[0], -1)])


# ================================================================ the polisher


class TrajectoryPolisher(ClearancePolisher):
    """Ipopt polish of whole trajectories for one robot, scene and number of waypoints.

    The NLP is built on first use, once per set of clearance-row capacities (a power of
    two per group, fitted to the pairs that are near), and re-solved by ``solve`` with new
    parameters; ``builds`` counts ``nlpsol`` constructions.

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
        super().__init__(robot, scene, safety_margin, config)
        robot = self.robot
        self.waypoints = w = int(waypoints)
        self.objective = objective
        self._n_configs = w + config.interpolation_checks * (w - 1)
        self._samples = np.arange(1, config.verify_samples) / config.verify_samples
        self._slot_rows = {(True,) * len(self._groups): self._rows}
        # ℓ = A·z + b exactly (linear), A from the model's own CasADi tendon function.
        self._tendon_matrix = np.asarray(ca.Function(
            "tendon_jacobian", [self._model.z],
            [ca.jacobian(self._model.functions_z["tendons"](self._model.z), self._model.z)],
        )(np.zeros(robot.dof)))
        self._speed = math.isfinite(robot.tendon_speed_max)
        self._accel = math.isfinite(robot.tendon_accel_max) and w >= 3
        self._pose_errors = self._model.functions_z["pose_error"].map(w)
        self._solvers: dict[tuple[int, ...], tuple[ca.Function, np.ndarray]] = {}

    # ------------------------------------------------------------ building

    def _elements(self) -> tuple[ca.Function, ca.Function]:
        """The Hessians of the Lagrangian's smooth elements (SX functions): one per
        waypoint k (bending rows and, for ``"tracking"``, its pose-error term) and one per
        interval (the ``"path"`` terms, or the tracking smoothness term). Tendon rows are
        linear; clearance curvature is left out (module docstring).

        Returns ``waypoint(z_k, lam_f, lam_bending, *targets) -> H (3n × 3n)`` and
        ``interval(z_k, z_next, lam_f) -> H (6n × 6n)``."""
        cfg, dof, n = self.config, self.robot.dof, self.robot.n_segments
        fz = self._model.functions_z
        z_k, z_next = ca.SX.sym("z_k", dof), ca.SX.sym("z_next", dof)
        lam_f, lam_bend = ca.SX.sym("lam_f"), ca.SX.sym("lam_bending", n)
        targets: list[ca.SX] = []
        value = ca.dot(lam_bend, ca.vertcat(*[z_k[3 * i] ** 2 + z_k[3 * i + 1] ** 2
                                               for i in range(n)]))
        if self.objective == "tracking":
            targets = [ca.SX.sym("target_position", 3), ca.SX.sym("target_rotation", 3, 3)]
            error = fz["pose_error"](z_k, *targets)
            value += lam_f * (0.5 * cfg.translation_weight * ca.sumsqr(error[:3])
                              + 0.5 * cfg.rotation_weight * ca.sumsqr(error[3:]))
        waypoint = ca.Function("waypoint_hessian", [z_k, lam_f, lam_bend, *targets],
                               [ca.hessian(value, z_k)[0]])
        step = z_next - z_k
        if self.objective == "path":
            tip_k, tip_next = fz["tip"](z_k)[0], fz["tip"](z_next)[0]
            value = lam_f * (cfg.path_weight * ca.sumsqr(tip_next - tip_k)
                             + cfg.smoothness_weight * ca.sumsqr(step))
        else:
            value = lam_f * cfg.tracking_smoothness_weight * ca.sumsqr(step)
        pair = ca.vertcat(z_k, z_next)
        interval = ca.Function("interval_hessian", [z_k, z_next, lam_f],
                               [ca.hessian(value, pair)[0]])
        return waypoint, interval

    def _objective(self, way: ca.MX, targets: list[ca.MX]) -> ca.MX:
        """f of a (3n × W) trajectory: the path or tracking objective (module docstring)."""
        cfg, w = self.config, self.waypoints
        fz = self._model.functions_z
        step = way[:, 1:] - way[:, :-1]
        if self.objective == "path":
            tips = fz["tip"].map(w)(way)[0]                                    # 3 × W
            return (cfg.path_weight * ca.sumsqr(tips[:, 1:] - tips[:, :-1])
                    + cfg.smoothness_weight * ca.sumsqr(step))
        error = self._pose_errors(way, *targets)                               # 6 × W
        return (0.5 * cfg.translation_weight * ca.sumsqr(error[:3, :])
                + 0.5 * cfg.rotation_weight * ca.sumsqr(error[3:, :])
                + cfg.tracking_smoothness_weight * ca.sumsqr(step))

    def _solver(self, capacities: tuple[int, ...]) -> tuple[ca.Function, np.ndarray]:
        """The Ipopt solver with ``capacities[i]`` clearance rows per configuration for
        group i (built on first use, then reused), and the indices of those rows among one
        configuration's rows of all groups (``_select``'s layout)."""
        if self._interpreted and not pending():
            self._interpreted = False
            self._solvers.clear()
        if capacities not in self._solvers:
            self._solvers[capacities] = self._build(capacities)
            self._interpreted |= any(rows.interpreted for rows in self._slot_rows.values())
        return self._solvers[capacities]

    def _capacities(self, lower: np.ndarray) -> tuple[int, ...]:
        """Rows per configuration and group that hold every switched-on slot of the
        config-major ``lower`` (``_select``): the largest count over the configurations,
        rounded up to a power of two (a few solver variants, not one per solve). Slots
        are filled from the first, so the first rows of each group suffice. Every row,
        switched on or not, is a row of Ipopt's KKT system: measured on a 150-waypoint
        path, the unused self-pair group's rows doubled the time per iteration."""
        switched = np.isfinite(lower.reshape(self._n_configs, self._rows.count))
        out, start = [], 0
        for group in self._groups:
            needed = int(np.max(np.sum(switched[:, start:start + group.capacity], axis=1),
                                initial=0))
            start += group.capacity
            out.append(0 if needed == 0 else min(group.capacity, 1 << (needed - 1).bit_length()))
        return tuple(out)

    def _build(self, capacities: tuple[int, ...]) -> tuple[ca.Function, np.ndarray]:
        """The Ipopt solver and its kept rows (``_solver``). Parameters: 1/Δt (1/s), then
        for ``"tracking"`` the target positions (3 × W) and rotations (3 × 3W), then each
        group's slots (capacity × width·C), configuration after configuration
        (``interpolated``), then the check points' fractions (checks × (W − 1)).

        The constraint Jacobian is given as a function: the linear rows' constant
        Jacobian, and the clearance rows' per-configuration Jacobians (``SlotRows``,
        mapped) chained through the interpolation by a constant assembly matrix. The
        Hessian is assembled from the element Hessians into its band: CasADi's own
        Hessian of the mapped graph colours the whole band and re-evaluates every
        configuration per colour (measured 5 s per solve for 150 waypoints)."""
        robot, cfg, w = self.robot, self.config, self.waypoints
        dof, n, checks = robot.dof, robot.n_segments, cfg.interpolation_checks
        # A group without rows is left out of the functions too (its slots cost as much
        # to evaluate as the rows in use); within a group, the first rows are kept.
        on = tuple(c > 0 for c in capacities)
        groups = [group for group, used in zip(self._groups, on, strict=True) if used]
        if on not in self._slot_rows:
            self._slot_rows[on] = SlotRows(self._model, groups, cfg.face_smoothing)
        slot_rows = self._slot_rows[on]
        full_starts = np.cumsum([0] + [group.capacity for group in self._groups])
        keep_all = np.concatenate([np.arange(c) + start for c, start in
                                   zip(capacities, full_starts, strict=False)] + [[]])
        starts = np.cumsum([0] + [group.capacity for group in groups])
        keep = np.concatenate([np.arange(c) + start for c, start in
                               zip([c for c in capacities if c], starts, strict=False)] + [[]])
        keep, keep_all = keep.astype(np.int64), keep_all.astype(np.int64)
        rows_per_config = len(keep)

        x = ca.MX.sym("x", dof * w)
        n_p = 1 + (12 * w if self.objective == "tracking" else 0) + sum(
            p.capacity * p.width * self._n_configs for p in groups) + checks * (w - 1)
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
        for group in groups:
            size = group.capacity * group.width * self._n_configs
            slots.append(ca.reshape(p[offset:offset + size], group.capacity,
                                    group.width * self._n_configs))
            offset += size
        fractions = ca.reshape(p[offset:offset + checks * (w - 1)], checks, w - 1)

        objective = self._objective(way, targets)
        bending = ca.vertcat(*[way[3 * i, :] ** 2 + way[3 * i + 1, :] ** 2 for i in range(n)])
        rows = [ca.vec(bending)]                                # n × W, waypoint-major
        lengths = ca.mtimes(ca.DM(self._tendon_matrix), way)                   # n_t × W
        if self._speed:
            rows.append(ca.vec((lengths[:, 1:] - lengths[:, :-1]) * inv_dt))
        if self._accel:
            rows.append(ca.vec((lengths[:, 2:] - 2 * lengths[:, 1:-1] + lengths[:, :-2])
                               * inv_dt ** 2))
        smooth_rows = ca.vertcat(*rows)
        g, jacobian = smooth_rows, ca.jacobian(smooth_rows, x)
        if rows_per_config:
            values, with_jacobian, curvature = slot_rows.functions(
                cfg.clearance_curvature == "full", cfg.compile)
            configs = interpolated(way, fractions)
            clearance, blocks = with_jacobian.map(self._n_configs)(configs, *slots)
            clearance, blocks = clearance[list(keep), :], blocks[list(keep), :]
            # A check point's Jacobian block enters waypoint k with weight 1 − s and
            # waypoint k + 1 with weight s.
            inner = blocks[:, dof * w:]
            right = inner * ca.repmat(ca.kron(ca.vec(fractions).T, ca.DM.ones(1, dof)),
                                      rows_per_config, 1)
            sources = ca.vertcat(ca.vec(blocks[:, :dof * w]), ca.vec(inner - right),
                                 ca.vec(right))
            pattern, assembly = _rows_assembly(rows_per_config, dof, w, checks)
            jac_g = ca.Function("jac_g", [x, p], [
                ca.vertcat(g, ca.vec(clearance)),
                ca.vertcat(jacobian, ca.MX(pattern, ca.mtimes(assembly, sources)))],
                ["x", "p"], ["g", "jac_g_x"])
            # configuration after configuration
            g = ca.vertcat(g, ca.vec(values.map(self._n_configs)(configs, *slots)[list(keep), :]))
        else:
            jac_g = ca.Function("jac_g", [x, p], [g, jacobian], ["x", "p"], ["g", "jac_g_x"])

        # The Hessian of the Lagrangian, assembled from the element Hessians.
        waypoint, interval = self._elements()
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", g.size1())
        lam_bend = ca.reshape(lam_g[:n * w], n, w)
        h_w = waypoint.map(w)(way, ca.repmat(lam_f, 1, w), lam_bend, *targets)
        h_i = interval.map(w - 1)(way[:, :-1], way[:, 1:], ca.repmat(lam_f, 1, w - 1))
        if rows_per_config and cfg.clearance_curvature != "none":
            lam_kept = ca.reshape(lam_g[g.size1() - rows_per_config * self._n_configs:],
                                  rows_per_config, self._n_configs)
            # The rows left out have zero multipliers.
            scatter = np.zeros((slot_rows.count, rows_per_config))
            scatter[keep, np.arange(rows_per_config)] = 1.0
            lam_clear = ca.mtimes(ca.DM(scatter), lam_kept)
            h_c = curvature.map(self._n_configs)(configs, *slots, lam_clear)  # 3n × 3n·C
            h_w = h_w + h_c[:, :dof * w]
            if checks:
                h_i = h_i + _interval_curvature(dof, checks).map(w - 1)(h_c[:, dof * w:],
                                                                        fractions)
        pattern, assembly = _band_assembly(dof, w)
        hessian = ca.MX(pattern, ca.mtimes(assembly, ca.vertcat(ca.vec(h_w), ca.vec(h_i))))
        hess_lag = ca.Function("hess_lag", [x, p, lam_f, lam_g], [hessian],
                               ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])

        # The warm start is stage 2's answer, usually feasible or nearly: start there
        # instead of pushing it 1e-2 into the interior (measured on the shelf: median
        # 0.31 → 0.12 s, the same optima; neutral on cabinet and random_27).
        options = ipopt_options(
            tol=cfg.tol, constr_viol_tol=cfg.constr_viol_tol, max_iter=cfg.max_iter,
            print_level=cfg.print_level, warm_start=WarmStart(push=1e-6),
            mu_strategy="adaptive", hessian_approximation=cfg.hessian,
            callbacks={"jac_g": jac_g, **({"hess_lag": hess_lag} if cfg.hessian == "exact"
                                          else {})})
        self.builds += 1
        name = "_".join(["polish_trajectory", robot.name, self.objective, str(w),
                         *map(str, capacities)])
        return (build_solver(name, {"x": x, "p": p, "f": objective, "g": g}, options,
                             self._deadline), keep_all)

    # ------------------------------------------------------------ per solve

    def _grid(self, z: np.ndarray) -> np.ndarray:
        """(G, 3n) configurations the re-evaluation checks, of a (W, 3n) trajectory in z:
        the waypoints, then interval after interval its samples at fractions
        j/``verify_samples``; G = W + (S − 1)(W − 1)."""
        fractions = np.repeat(self._samples[:, None], self.waypoints - 1, axis=1)
        return np.ascontiguousarray(interpolated(z.T, fractions).T)

    def _all_distances(self, z: np.ndarray) -> np.ndarray:
        """(G, N·P + M) float64 pair distances (m) at the ``_grid`` configurations of a
        (W, 3n) trajectory in z: exact below ``near_margin`` (and δ), lower bounds above
        (``PairDistances.near``)."""
        return self._pairs.near(self._grid(z), self._margin)

    def _levers(self, z: np.ndarray) -> np.ndarray:
        """(W,) the largest Σⱼ‖∂c_b/∂zⱼ‖ over the body spheres b at each of the (W, 3n)
        waypoints z: metres a sphere moves at most when every variable moves by one (rad
        or m)."""
        levers = []
        for row in z:
            jacobian = np.asarray(self._rows._centres_jacobian(row)[1])        # 3N × 3n
            blocks = jacobian.reshape(3, self._n_bodies, -1)
            levers.append(np.max(np.sum(np.linalg.norm(blocks, axis=0), axis=1)))
        return np.maximum(np.array(levers), 1e-9)

    def _step(self, z: np.ndarray, near: np.ndarray) -> np.ndarray:
        """(W, 1) how far each waypoint's variables may move in one round (rad or m):
        ``step_limit`` times the room its spheres have, over its lever. The room is
        ``near_margin``, or more where every pair at the waypoint and in its two intervals
        is farther (``near`` holds lower bounds there): a waypoint far from everything
        need not crawl (measured on the 150-waypoint ICRA path at Δt = 0.2 s: 3 rounds and
        29 iterations instead of 5 and 46, 4.8 s instead of 7.1 s, a valid answer both
        ways)."""
        cfg, w, per = self.config, self.waypoints, len(self._samples)
        closest = (np.min(near, axis=1) if near.shape[1] else np.full(len(near), np.inf))
        room = closest[:w].copy()
        if per:
            interval = np.min(closest[w:].reshape(w - 1, per), axis=1)
            room[:-1] = np.minimum(room[:-1], interval)
            room[1:] = np.minimum(room[1:], interval)
        # At most twice the old room: larger steps led a reachable 8-waypoint tracking
        # problem into another basin (one pose 2.5 mm off instead of reached).
        room = np.clip(room, cfg.near_margin, 2.0 * cfg.near_margin)
        return (cfg.step_limit * room / self._levers(z))[:, None]

    def _place(self, near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the check points go: per interval, at the ``interpolation_checks``
        samples with the smallest pair distance in ``near`` (G, pairs). Returns their
        (checks × (W − 1)) fractions and the NLP configurations' (C,) rows of the grid."""
        w, checks, per = self.waypoints, self.config.interpolation_checks, len(self._samples)
        closest = (np.min(near, axis=1) if near.shape[1] else np.zeros(len(near)))
        picked = np.sort(np.argsort(closest[w:].reshape(w - 1, per), axis=1,
                                    kind="stable")[:, :checks], axis=1)      # (W − 1, checks)
        grid_rows = w + np.arange(w - 1)[:, None] * per + picked
        return self._samples[picked].T, np.concatenate([np.arange(w), grid_rows.reshape(-1)])

    def _select(self, distances: np.ndarray, fixed_ends: bool = True
                ) -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray]]:
        """Slot parameters per group (capacity × width·C), the clearance lbg (config-major)
        and, per configuration, the switched-on pair indices in row order. With
        ``fixed_ends`` the rows of a ``"path"`` problem's fixed start and goal are off."""
        batch, lower, chosen = select_slots_batch(
            self._groups, self._n_bodies, self._self_pairs, self.config.near_margin,
            self.safety_margin, distances)
        # (C, capacity, width) → (capacity, width·C), configuration after configuration.
        parameters = [np.transpose(b, (1, 0, 2)).reshape(b.shape[1], -1) for b in batch]
        lower = lower.reshape(-1)
        if fixed_ends and self.objective == "path" and len(lower):
            # Start and goal are fixed: their rows are constants Ipopt cannot change (and a
            # start closer than δ must not make the whole NLP infeasible); the
            # re-evaluation still measures them.
            width = len(lower) // self._n_configs
            lower[:width] = -np.inf
            lower[(self.waypoints - 1) * width: self.waypoints * width] = -np.inf
        return parameters, lower, chosen

    def _evaluate(self, z: np.ndarray, dt: float) -> tuple[dict[str, float], np.ndarray]:
        """Float64, independent of Ipopt: the violation per family and all distances."""
        robot = self.robot
        distances = self._all_distances(z)
        lengths = _tendon_lengths(robot, z)
        speed = np.abs(np.diff(lengths, axis=0)) / dt
        accel = (np.abs(np.diff(lengths, 2, axis=0)) / (dt * dt) if len(z) > 2
                 else np.zeros((0, lengths.shape[1])))
        violations = {
            **self._shared_violations(z, distances),
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
              target_rotations: Any = None,
              time_limit: float | None = None) -> TrajectoryPolishResult:
        """Polish one trajectory.

        Args:
            q0: (W, 3n) warm start θ, φ, L (rad, rad, m), typically stage 2's answer; it
                may violate any constraint. For ``"path"`` its first and last rows are the
                fixed start and goal.
            dt: seconds between waypoints (> 0).
            target_positions: ``"tracking"`` only: (W, 3) tip positions, metres.
            target_rotations: ``"tracking"`` only: (W, 3, 3) tip rotation matrices.
            time_limit: seconds this solve may take (None: no limit); past it Ipopt stops,
                no further round starts, and the best round so far is returned with
                ``out_of_time``.

        Returns a ``TrajectoryPolishResult``; a numerical failure is ``success=False`` with
        Ipopt's last iterate (or ``q0``), never an exception. Bad shapes raise ValueError.
        """
        start = time.perf_counter()
        q0, dt, positions, rotations = self._check_inputs(q0, dt, target_positions,
                                                          target_rotations)
        self._deadline.at = math.inf if time_limit is None else start + float(time_limit)
        try:
            return self._solve(q0, dt, positions, rotations, start)
        finally:
            self._deadline.start(None)

    def _solve(self, q0: np.ndarray, dt: float, positions: np.ndarray | None,
               rotations: np.ndarray | None, start: float) -> TrajectoryPolishResult:
        """``solve`` with checked inputs and its deadline set."""
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
        free = not self._groups
        fixed = [np.array([1.0 / dt])]
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

        z, status, iterations, objective = z0, "not run", 0, math.nan
        warm_violations, near = self._evaluate(z0, dt)
        violations = warm_violations
        best: tuple[float, np.ndarray, dict[str, float], str, float] | None = None
        out_of_time = False
        for round_ in range(cfg.reselections + 1):
            if self._deadline.passed():
                out_of_time, status = True, TIME_LIMIT_STATUS
                break
            step = np.inf if free else self._step(z, near)
            low, high = np.maximum(lbx, z - step), np.minimum(ubx, z + step)
            fractions, rows = self._place(near)
            slots, clearance_lower, chosen = self._select(near[rows])
            capacities = self._capacities(clearance_lower)
            solver, keep = self._solver(capacities)
            clearance_lower = clearance_lower.reshape(self._n_configs, -1)[:, keep].ravel()
            slots = [s for s, c in zip(slots, capacities, strict=True) if c]
            parameters = np.concatenate([*fixed, *[s.ravel(order="F") for s in slots],
                                         fractions.ravel(order="F")])
            run = run_solver(
                solver, z, self._deadline, p=parameters, lbx=low.reshape(-1), ubx=high.reshape(-1),
                lbg=np.concatenate([*lower, clearance_lower]),
                ubg=np.concatenate([*upper, np.full(clearance_lower.size, np.inf)]))
            answer, status = run.x.reshape(w, dof), run.status
            iterations += run.iterations
            if not run.raised:
                objective = run.objective
            if not np.all(np.isfinite(answer)):
                status = f"{status} (non-finite iterate)"
                break
            # Ipopt's bound relaxation leaves the box bounds up to ~1e-8 outside: project.
            z = q_to_z_numpy(project_bending(self.robot, z_to_q_numpy(answer)))
            violations, distances = self._evaluate(z, dt)
            worst = max(violations.values())
            if best is None or worst < best[0] or worst <= cfg.violation_tolerance:
                best = (worst, z, violations, status, objective)
            if run.out_of_time:
                out_of_time = True
                break
            if not self._groups:
                break
            switched_on = np.zeros(distances.shape, dtype=bool)
            for row, flat in zip(rows, chosen, strict=True):
                switched_on[row, flat] = True
            violated = distances < self.safety_margin - cfg.violation_tolerance
            limited = np.any((answer <= low + 1e-7) & (low > lbx)) or np.any(
                (answer >= high - 1e-7) & (high < ubx))
            unseen = np.any(violated & ~switched_on)
            if not (unseen or limited) or (worst <= cfg.violation_tolerance
                                           and self.objective == "path"):
                # A valid path stopped by the step limit is kept as it is (measured on
                # random_27: going on to the unlimited optimum took 4–5× the time, every
                # round ~15 more iterations); tracking goes on, its objective is the
                # pose error.
                break
            # A pair without a slot, or a sample without a check point, came too close, or
            # the step limit stopped the answer: place the checks and slots where either
            # point is near, and go on from here. The last round is free of the step limit
            # if only the limit stopped the one before (the best round is kept anyway).
            near = np.minimum(near, distances)
            if round_ == cfg.reselections - 1 and not unseen:
                free = True
        if best is not None:
            # The round that came out best: valid (the last valid one) or least violated.
            _, z, violations, status, objective = best
        max_violation = max(violations.values())
        errors = None
        if positions is not None:
            errors = np.linalg.norm(np.asarray(self._pose_errors(
                z.T, positions.T, np.hstack(list(rotations)))), axis=0)
        return TrajectoryPolishResult(
            q=z_to_q_numpy(z),
            success=max_violation <= cfg.violation_tolerance,
            status=status,
            max_violation=max_violation,
            violations=violations,
            objective=objective,
            iterations=iterations,
            seconds=time.perf_counter() - start,
            pose_errors=errors,
            warm_start_violations=warm_violations,
            out_of_time=out_of_time and max_violation > cfg.violation_tolerance,
        )

    # ------------------------------------------------------------ checks

    def _slot_values(self, q_near: Any, q: Any) -> tuple[np.ndarray, np.ndarray]:
        """The clearance rows switched on for the warm start ``q_near`` (W, 3n), evaluated
        at ``q`` (W, 3n) by the NLP's own mapped CasADi function at the same check points,
        and the world's float64 distances of the same pairs (m, convex parts with
        ``face_smoothing``): the two must agree."""
        from ...world.clearance import all_pair_distances_numpy

        z_near, z = (q_to_z_numpy(x) for x in (q_near, q))
        near = self._all_distances(z_near)
        fractions, rows = self._place(near)
        slots, lower, chosen = self._select(near[rows], fixed_ends=False)
        configs = interpolated(z.T, fractions)                               # 3n × C
        values = np.asarray(self._rows.functions()[0].map(self._n_configs)(
            configs, *slots)).reshape(-1, order="F")
        world = all_pair_distances_numpy(self.robot, self._pairs.arrays,
                                         np.ascontiguousarray(configs.T),
                                         self.config.face_smoothing)
        expected = np.concatenate([world[c, flat] for c, flat in enumerate(chosen)])
        return values[np.isfinite(lower)], expected


# ================================================================ one polish as a unit of work


def trajectory_polisher(robot: Robot, scene: Scene | None, waypoints: int, margin: float,
                        samples: int) -> TrajectoryPolisher:
    """A path-length ``TrajectoryPolisher`` with clearance rows at every waypoint and at
    the ``samples`` − 1 points inside every interval that the verification checks (δ =
    ``margin`` m on the sphere body); module level, so pool workers can build it."""
    return TrajectoryPolisher(robot, scene, waypoints, safety_margin=margin,
                              config=TrajectoryPolishConfig(interpolation_checks=samples - 1,
                                                            verify_samples=samples))


def describe_polish(out: Any) -> str:
    """Why a trajectory polish failed: Ipopt's status (or that the time limit stopped it)
    and the violations it left."""
    broken = describe_violations(out.violations)
    head = (f"Ipopt stopped at the time limit ({out.iterations} iterations, "
            f"{out.seconds:.3g} s)" if _out_of_time(out) else f"Ipopt {out.status}")
    return head + (f", {broken}" if broken else "")


def polish_one(polisher: Any, q0: np.ndarray, dt: float,
               time_limit: float | None = None) -> tuple[np.ndarray | None, str, float, bool]:
    """One Ipopt polish of the trajectory ``q0`` (``dt`` s between waypoints) in at most
    ``time_limit`` seconds (None: no limit): its answer, or None with why Ipopt failed,
    the seconds it took, and whether the time limit stopped it; module level, so a
    ``PolishPool`` can send it to its workers."""
    t0 = time.perf_counter()
    out = polisher.solve(q0, dt, time_limit=time_limit)
    if not out.success:
        return None, describe_polish(out), time.perf_counter() - t0, _out_of_time(out)
    return out.q, "", time.perf_counter() - t0, _out_of_time(out)


def _out_of_time(out: Any) -> bool:
    """A polish result's ``out_of_time``; a result without one (a stand-in polisher's)
    did not run out of time."""
    return bool(getattr(out, "out_of_time", False))


def _interval_curvature(dof: int, checks: int) -> ca.Function:
    """(3n × 3n·checks) Hessians of one interval's check points and their (checks,)
    fractions s → their (6n × 6n) Hessian with respect to the interval's two waypoints: a
    point (1 − s)·z_k + s·z_{k+1} with Hessian H enters as
    [[(1−s)², (1−s)s], [(1−s)s, s²]] ⊗ H."""
    h, fractions = ca.SX.sym("h", dof, dof * checks), ca.SX.sym("fractions", checks)
    total = ca.SX(2 * dof, 2 * dof)
    for c in range(checks):
        s = fractions[c]
        block = h[:, c * dof:(c + 1) * dof]
        total += ca.vertcat(ca.horzcat((1 - s) ** 2 * block, (1 - s) * s * block),
                            ca.horzcat((1 - s) * s * block, s ** 2 * block))
    return ca.Function("interval_curvature", [h, fractions], [total])


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
    configurations of ``interpolated``) with respect to the (dof·W) waypoint variables,
    and the constant 0/1 matrix that maps its sources to its nonzeros. The sources,
    stacked column-major: the waypoints' Jacobians (rows × dof·W), then the check points'
    Jacobians weighted by 1 − s (rows × dof·checks·(W − 1), for waypoint k), then the
    same weighted by s (for waypoint k + 1)."""
    entries: list[tuple[int, int, int]] = []            # (row, column, source)
    inner = rows * dof * checks * (waypoints - 1)

    def block(config: int, waypoint: int, source: int) -> None:
        for j in range(dof):
            for i in range(rows):
                entries.append((config * rows + i, waypoint * dof + j, source + j * rows + i))

    for k in range(waypoints):
        block(k, k, k * dof * rows)
    base = rows * dof * waypoints
    for k in range(waypoints - 1):
        for c in range(checks):
            index = k * checks + c
            block(waypoints + index, k, base + index * dof * rows)
            block(waypoints + index, k + 1, base + inner + index * dof * rows)
    configs = waypoints + checks * (waypoints - 1)
    keys = sorted({(r, c) for r, c, _ in entries}, key=lambda rc: (rc[1], rc[0]))
    index_of = {rc: i for i, rc in enumerate(keys)}
    pattern = ca.Sparsity.triplet(rows * configs, dof * waypoints,
                                  [r for r, _ in keys], [c for _, c in keys])
    assembly = ca.DM(ca.Sparsity.triplet(len(keys), base + 2 * inner,
                                         [index_of[(r, c)] for r, c, _ in entries],
                                         [src for _, _, src in entries]),
                     np.ones(len(entries)))
    return pattern, assembly
