"""The trajectory NLP's construction (the NLP itself: ``stages.polish._trajectory_nlp``'s
docstring): its variables and parameters, the rows other than clearance, the clearance
rows of the groups in use, the structured Hessian of the Lagrangian and the Ipopt solver,
built once per set of clearance-row capacities and reused. ``TrajectoryPolisher`` adds
the solve on top.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from ...model import Robot
from ...world.scene import Scene
from ._clearance_rows import SlotRows
from ._compiled_functions import pending
from ._ipopt import WarmStart, build_solver, ipopt_options
from ._polisher import ClearancePolisher
from ._trajectory_assembly import band_assembly, chained_jacobian, interpolated, interval_curvature
from ._trajectory_config import OBJECTIVES, TrajectoryPolishConfig


class TrajectoryNLPBuilder(ClearancePolisher):
    """The building half of ``TrajectoryPolisher`` (its arguments are documented there):
    the checked settings, and ``_solver(capacities)``, the Ipopt solver with that many
    clearance rows per group and configuration, built on first use."""

    def __init__(self, robot: Robot | str | Path, scene: Scene | str | Path | dict | None,
                 waypoints: int, safety_margin: float | None = None, objective: str = "path",
                 config: TrajectoryPolishConfig = TrajectoryPolishConfig(),  # noqa: B008 — frozen
                 ) -> None:
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
        self._speed = robot.speed_limited
        self._accel = robot.accel_limited and w >= 3
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
        slot_rows, groups, keep, keep_all = self._kept_rows(capacities)
        x, p, way, inv_dt, targets, slots, fractions = self._symbols(groups)
        objective = self._objective(way, targets)
        smooth_rows = self._smooth_rows(way, inv_dt)
        g, jacobian = smooth_rows, ca.jacobian(smooth_rows, x)
        clearance = None
        if len(keep):
            values, with_jacobian, curvature = slot_rows.functions(
                cfg.clearance_curvature == "full", cfg.compile)
            configs = interpolated(way, fractions)
            rows, blocks = with_jacobian.map(self._n_configs)(configs, *slots)
            rows, blocks = rows[list(keep), :], blocks[list(keep), :]
            jac_g = ca.Function("jac_g", [x, p], [
                ca.vertcat(g, ca.vec(rows)),
                ca.vertcat(jacobian, chained_jacobian(blocks, fractions, len(keep), robot.dof,
                                                      w, cfg.interpolation_checks))],
                ["x", "p"], ["g", "jac_g_x"])
            # configuration after configuration
            g = ca.vertcat(g, ca.vec(values.map(self._n_configs)(configs, *slots)[list(keep), :]))
            if cfg.clearance_curvature != "none":
                clearance = (curvature, configs, slots, fractions, keep, slot_rows.count)
        else:
            jac_g = ca.Function("jac_g", [x, p], [g, jacobian], ["x", "p"], ["g", "jac_g_x"])
        hess_lag = self._hessian(x, p, way, targets, g.size1(), clearance)

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

    def _kept_rows(self, capacities: tuple[int, ...]
                   ) -> tuple[SlotRows, list[Any], np.ndarray, np.ndarray]:
        """The clearance rows of the groups with rows (``capacities[i]`` > 0), the groups
        themselves, and the indices of the kept rows (the first ``capacities[i]`` of each
        group) among those groups' rows and among the rows of all groups."""
        # A group without rows is left out of the functions too (its slots cost as much
        # to evaluate as the rows in use); within a group, the first rows are kept.
        on = tuple(c > 0 for c in capacities)
        groups = [group for group, used in zip(self._groups, on, strict=True) if used]
        if on not in self._slot_rows:
            self._slot_rows[on] = SlotRows(self._model, groups, self.config.face_smoothing)
        full_starts = np.cumsum([0] + [group.capacity for group in self._groups])
        keep_all = np.concatenate([np.arange(c) + start for c, start in
                                   zip(capacities, full_starts, strict=False)] + [[]])
        starts = np.cumsum([0] + [group.capacity for group in groups])
        keep = np.concatenate([np.arange(c) + start for c, start in
                               zip([c for c in capacities if c], starts, strict=False)] + [[]])
        return self._slot_rows[on], groups, keep.astype(np.int64), keep_all.astype(np.int64)

    def _symbols(self, groups: list[Any]) -> tuple[ca.MX, ca.MX, ca.MX, ca.MX, list[ca.MX],
                                                   list[ca.MX], ca.MX]:
        """The NLP's variable x (3n·W) and parameter vector p (``_build``), and the views
        of them the rows use: the (3n × W) waypoints, 1/Δt, the targets (``"tracking"``),
        each group's slots and the check points' (checks × (W − 1)) fractions."""
        dof, w, checks = self.robot.dof, self.waypoints, self.config.interpolation_checks
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
        return x, p, way, inv_dt, targets, slots, fractions

    def _smooth_rows(self, way: ca.MX, inv_dt: ca.MX) -> ca.MX:
        """The rows other than clearance: the bending disks (n × W, waypoint-major), then
        tendon speed (m/s) and acceleration (m/s²) where their limits are finite."""
        n = self.robot.n_segments
        bending = ca.vertcat(*[way[3 * i, :] ** 2 + way[3 * i + 1, :] ** 2 for i in range(n)])
        rows = [ca.vec(bending)]                                # n × W, waypoint-major
        lengths = ca.mtimes(ca.DM(self._tendon_matrix), way)                   # n_t × W
        if self._speed:
            rows.append(ca.vec((lengths[:, 1:] - lengths[:, :-1]) * inv_dt))
        if self._accel:
            rows.append(ca.vec((lengths[:, 2:] - 2 * lengths[:, 1:-1] + lengths[:, :-2])
                               * inv_dt ** 2))
        return ca.vertcat(*rows)

    def _hessian(self, x: ca.MX, p: ca.MX, way: ca.MX, targets: list[ca.MX], n_g: int,
                 clearance: tuple[ca.Function, ca.MX, list[ca.MX], ca.MX, np.ndarray, int]
                 | None) -> ca.Function:
        """``hess_lag(x, p, lam_f, lam_g)``: the Hessian of the Lagrangian (upper triangle)
        assembled from the element Hessians into its band. ``clearance``: the clearance
        rows' curvature function, the configurations, slots and fractions it is mapped
        over, the kept rows and the rows of all groups; None leaves their curvature out."""
        dof, n, w = self.robot.dof, self.robot.n_segments, self.waypoints
        waypoint, interval = self._elements()
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", n_g)
        lam_bend = ca.reshape(lam_g[:n * w], n, w)
        h_w = waypoint.map(w)(way, ca.repmat(lam_f, 1, w), lam_bend, *targets)
        h_i = interval.map(w - 1)(way[:, :-1], way[:, 1:], ca.repmat(lam_f, 1, w - 1))
        if clearance is not None:
            curvature, configs, slots, fractions, keep, count = clearance
            rows_per_config = len(keep)
            lam_kept = ca.reshape(lam_g[n_g - rows_per_config * self._n_configs:],
                                  rows_per_config, self._n_configs)
            # The rows left out have zero multipliers.
            scatter = np.zeros((count, rows_per_config))
            scatter[keep, np.arange(rows_per_config)] = 1.0
            lam_clear = ca.mtimes(ca.DM(scatter), lam_kept)
            h_c = curvature.map(self._n_configs)(configs, *slots, lam_clear)  # 3n × 3n·C
            h_w = h_w + h_c[:, :dof * w]
            if checks := self.config.interpolation_checks:
                h_i = h_i + interval_curvature(dof, checks).map(w - 1)(h_c[:, dof * w:],
                                                                       fractions)
        pattern, assembly = band_assembly(dof, w)
        hessian = ca.MX(pattern, ca.mtimes(assembly, ca.vertcat(ca.vec(h_w), ca.vec(h_i))))
        return ca.Function("hess_lag", [x, p, lam_f, lam_g], [hessian],
                           ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])
