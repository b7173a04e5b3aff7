"""Stage 3, polish: the IK problem with its constraints as real constraints, solved by Ipopt.

The variable is the bending vector ``z = [ux1, uy1, L1, …]`` (rad, rad, m), warm-started
from stage 2's answer. Constraints (docs/design.md §2):

- simple bounds: ``|uxᵢ|, |uyᵢ| ≤ θmaxᵢ``, ``Lᵢ`` in its range (``lbx = ubx`` when fixed);
- ``‖uᵢ‖² ≤ θmaxᵢ²`` (smooth form of θᵢ ≤ θmaxᵢ);
- clearance: one row ``d ≥ δ`` per (body sphere, obstacle part) pair and per self pair
  (body spheres on segments at least two apart) near the warm start, in the pair slots of
  ``stages.polish._clearance_rows``;
- pose, mode ``"equality"``: ``log(T_tip⁻¹·T_target) = 0`` (6 rows), objective
  ``‖z − z_start‖²``; mode ``"minimize"``: objective ``½‖log(T_tip⁻¹·T_target)‖²``. A
  robot with fewer than six free variables skips ``"equality"`` (six equations would
  over-determine it).

Derivatives: exact first derivatives everywhere; the Hessian holds the exact second
derivatives of the objective, the pose rows and the bending disks, not the clearance
rows' curvature (``stages.polish._clearance_rows`` says why and what was measured).

Azimuth ranges (``phi_range``, rare) are not constraints of the polish; the re-evaluation
still measures them, so a polish that leaves such a range fails.

A solve may be given a time limit (``solve(..., time_limit=)``): every Ipopt run of it stops
at the deadline (``stages.polish._ipopt.Deadline``), the modes not yet run are skipped, and the
result is the best attempt so far with ``out_of_time`` set.

Every answer is projected onto the simple limits (θ ≤ θmax and L in range, which Ipopt's
bound relaxation leaves up to ~1e-8 outside) and re-evaluated in float64 independently of
Ipopt, before it is called a success: the pose error by the model's CasADi function, the
limits by numpy, and every (body sphere, part) and self pair of the scene
(``world.clearance.PairDistances``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
from tqdm.auto import tqdm

from ...model import Robot, q_to_z_numpy, z_to_q_numpy
from ...model.limits import project_bending
from ...world.scene import Scene
from ...world.verdict import VIOLATION_TOLERANCE, describe_violations
from ._clearance_rows import Selection, select_slots
from ._compiled_functions import compiled, pending
from ._ipopt import (
    SUCCESS_STATUSES,
    TIME_LIMIT_STATUS,
    NLPSettings,
    WarmStart,
    build_solver,
    ipopt_options,
    run_solver,
)
from ._polisher import ClearancePolisher

MODES = ("equality", "minimize")


@dataclass(frozen=True)
class PolishConfig(NLPSettings):
    """Settings of the IK polish (the shared ones: ``NLPSettings``)."""

    modes: tuple[str, ...] = ("equality", "minimize")
    """Attempts in order; the next one runs only if the previous failed. ``"equality"``:
    pose as 6 equality constraints, objective ‖z − z_start‖²; ``"minimize"``: objective
    ½‖log(T_tip⁻¹·T_target)‖²."""
    pose_tolerance: float = 1e-6
    """Largest pose error ‖log(T_tip⁻¹·T_target)‖ (mixed m/rad) of a successful polish."""
    clearance_curvature: str = "none"
    """As ``NLPSettings``; "none" measured on the lattice (tdcr6_ext, 50 targets,
    compiled): 28 ms per target, "parts" 34 ms, "full" 39 ms, with 14–15 iterations
    each: IK answers start next to the optimum, where the curvature of the few active
    rows barely matters."""
    warm_start: bool = True
    """Start Ipopt's barrier parameter at 1e-6 with the warm start moved only 1e-9 inside
    its bounds, instead of 0.1 and 1e-2: stage 2's answer is next to the optimum
    (measured on the lattice, tdcr6_ext, 50 targets: 14 → 3–4 iterations, the same
    answers to 1e-9)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.modes or any(m not in MODES for m in self.modes):
            raise ValueError(f"modes must be a non-empty sequence of {MODES}, got {self.modes!r}")


@dataclass
class PolishResult:
    """The outcome of one polish (never raised: a failure is ``success=False``)."""

    q: np.ndarray
    """(3n,) θ, φ, L (rad, rad, m), converted back from z and projected onto the simple
    limits: the attempt that came out best (the warm start itself if Ipopt produced
    nothing finite)."""
    success: bool
    """Ipopt reported success, every re-evaluated violation ≤ ``violation_tolerance`` and
    ``pose_error`` ≤ ``pose_tolerance``."""
    status: str
    """Ipopt's return status of the attempt that produced ``q``."""
    max_violation: float
    """The largest of ``violations``."""
    pose_error: float
    """‖log(T_tip⁻¹·T_target)‖ at ``q`` (mixed m/rad), float64."""
    iterations: int
    """Ipopt iterations, summed over every attempt of this solve."""
    seconds: float
    """Wall time of the whole ``solve`` (selection, attempts, re-evaluation), seconds."""
    mode: str
    """The pose formulation that produced ``q``: ``"equality"`` or ``"minimize"``."""
    violations: dict[str, float] = field(default_factory=dict)
    """Re-evaluated at ``q`` in float64: ``limits`` (rad or m) and ``clearance`` (m below
    the safety margin δ, over every pair of the scene)."""
    out_of_time: bool = False
    """The solve's time limit stopped it: an Ipopt run stopped at the deadline, or a mode
    was not run (``status`` is then ``TIME_LIMIT_STATUS`` when no run finished)."""

    def failure(self, pose_tolerance: float = 1e-6,
                violation_tolerance: float = VIOLATION_TOLERANCE) -> str:
        """Why the polish did not succeed, in words ("" if it did): Ipopt's status when
        Ipopt failed; otherwise which independent re-evaluation rejected its answer, by
        how much."""
        if self.success:
            return ""
        if self.status == TIME_LIMIT_STATUS:
            return (f"Ipopt stopped at the time limit ({self.iterations} iterations, "
                    f"{self.seconds:.3g} s)")
        if self.status not in SUCCESS_STATUSES:
            return f"Ipopt: {self.status}"
        if self.max_violation > violation_tolerance:
            broken = describe_violations(self.violations or {"constraint": self.max_violation},
                                         violation_tolerance)
            return f"Ipopt converged, but the float64 re-evaluation finds {broken}"
        return (f"Ipopt converged to a point {self.pose_error:.2g} (m/rad) from the target: "
                f"the pose is not reachable while keeping every constraint")


@dataclass
class _Attempt:
    mode: str
    z: np.ndarray
    status: str
    ipopt_success: bool
    iterations: int
    pose_error: float
    violations: dict[str, float]
    distances: np.ndarray              # (N·P + M,) at z (m): exact near δ, lower bounds far

    @property
    def max_violation(self) -> float:
        return max(self.violations.values())


class IKPolisher(ClearancePolisher):
    """Ipopt polish of IK answers for one robot in one scene.

    The NLPs (one per mode in ``config.modes``) are built once here and re-solved by
    ``solve`` with new parameters; ``builds`` counts ``nlpsol`` constructions.

    Args:
        robot: a ``Robot`` or a robot file.
        scene: a ``Scene``, a scene file or bundled scene name, or None (no obstacles;
            self pairs are still constrained).
        safety_margin: δ (m), the clearance every pair must keep; default
            ``body_gap_tolerance(robot) + 0.002``, so that clearance ≥ δ proves the capsule
            body collision-free for ``world.check``.
        config: ``PolishConfig``.
    """

    def __init__(self, robot: Robot | str | Path, scene: Scene | str | Path | dict | None = None,
                 safety_margin: float | None = None, config: PolishConfig = PolishConfig()) -> None:
        super().__init__(robot, scene, safety_margin, config)
        free = int(np.count_nonzero(self._ubx > self._lbx))
        # Six pose equations over-determine a robot with fewer free variables.
        self.modes = tuple(m for m in config.modes if m != "equality" or free >= 6) or ("minimize",)
        """The modes this robot uses, in order."""
        self._solvers = self._build_all()

    # ------------------------------------------------------------ building

    def _build_all(self) -> dict[str, ca.Function]:
        """The solver of every mode (``_interpreted`` set while built uncompiled)."""
        self._interpreted = False
        solvers = {mode: self._build(mode) for mode in self.modes}
        self._interpreted |= self._rows.interpreted
        return solvers

    def _build(self, mode: str) -> ca.Function:
        """The Ipopt solver of one mode. Parameters: target position (3), target rotation
        (3×3, column-major), z_start (3n), then each group's (capacity × width) slots.
        The constraint Jacobian and the Hessian are given as functions: the clearance rows'
        Jacobian by the chain rule (``SlotRows.with_jacobian``), the Hessian without the
        clearance rows' curvature."""
        robot, cfg, dof, n = self.robot, self.config, self.robot.dof, self.robot.n_segments
        z = ca.MX.sym("z", dof)
        target_position = ca.MX.sym("target_position", 3)
        target_rotation = ca.MX.sym("target_rotation", 3, 3)
        z_start = ca.MX.sym("z_start", dof)
        slots = [ca.MX.sym(f"slots_{group.kind}", group.capacity, group.width)
                 for group in self._groups]
        p = ca.vertcat(target_position, ca.vec(target_rotation), z_start,
                       *[ca.vec(s) for s in slots])

        # The smooth part (objective, pose rows, bending disks) as one SX function with its
        # exact derivatives; the clearance rows come from the slots.
        zs = ca.SX.sym("z", dof)
        tp, tr, zs0 = ca.SX.sym("tp", 3), ca.SX.sym("tr", 3, 3), ca.SX.sym("z0", dof)
        error = self._model.functions_z["pose_error"](zs, tp, tr)
        bending = ca.vertcat(*[zs[3 * i] ** 2 + zs[3 * i + 1] ** 2 for i in range(n)])
        if mode == "equality":
            objective, smooth = ca.sumsqr(zs - zs0), ca.vertcat(error, bending)
        else:
            objective, smooth = 0.5 * ca.sumsqr(error), bending
        lam_f, lam_s = ca.SX.sym("lam_f"), ca.SX.sym("lam_smooth", smooth.size1())
        lagrangian = lam_f * objective + ca.dot(lam_s, smooth)
        inputs = [zs, tp, tr, zs0]
        # Separate functions for each callback, so that evaluating the objective or the
        # rows does not evaluate derivatives (CasADi's generated gradient of an objective
        # taken from a function with more outputs was measured at ~0.8 ms per solve).
        objective_fn = ca.Function("objective", inputs, [objective, ca.gradient(objective, zs)])
        smooth_fn = ca.Function("smooth", inputs, [smooth])
        smooth_jacobian_fn = ca.Function("smooth_jacobian", inputs,
                                         [smooth, ca.jacobian(smooth, zs)])
        hessian_fn = ca.Function("smooth_hessian", [*inputs, lam_f, lam_s],
                                 [ca.triu(ca.hessian(lagrangian, zs)[0])])
        (objective_fn, smooth_fn, smooth_jacobian_fn, hessian_fn), waiting = compiled(
            [objective_fn, smooth_fn, smooth_jacobian_fn, hessian_fn], cfg.compile)
        self._interpreted |= waiting

        data = (z, target_position, target_rotation, z_start)
        f, gradient = objective_fn(*data)
        g_smooth = smooth_fn(*data)
        g_smooth_again, j_smooth = smooth_jacobian_fn(*data)
        values, with_jacobian, curvature = self._rows.functions(
            cfg.clearance_curvature == "full", cfg.compile)
        if self._groups:
            rows, rows_jacobian = with_jacobian(z, *slots)
            g = ca.vertcat(g_smooth, values(z, *slots))
        else:
            rows, rows_jacobian = ca.MX(0, 1), ca.MX(0, dof)
            g = g_smooth
        jac_g = ca.Function("jac_g", [z, p], [ca.vertcat(g_smooth_again, rows),
                                              ca.vertcat(j_smooth, rows_jacobian)],
                            ["x", "p"], ["g", "jac_g_x"])
        grad_f = ca.Function("grad_f", [z, p], [f, gradient], ["x", "p"], ["f", "grad_f_x"])
        lam_obj, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", g.size1())
        hessian = hessian_fn(z, target_position, target_rotation, z_start, lam_obj,
                             lam_g[:g_smooth.size1()])
        if self._groups and cfg.clearance_curvature != "none":
            hessian += ca.triu(curvature(z, *slots, lam_g[g_smooth.size1():]))
        hess_lag = ca.Function("hess_lag", [z, p, lam_obj, lam_g], [hessian],
                               ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])
        # Least squares from a nearby start: the monotone barrier update stalls
        # (docs/design.md); the equality mode measured as fast or faster with the default.
        options = ipopt_options(
            tol=cfg.tol, constr_viol_tol=cfg.constr_viol_tol, max_iter=cfg.max_iter,
            print_level=cfg.print_level,
            warm_start=WarmStart(push=1e-9, mu_init=1e-6) if cfg.warm_start else None,
            mu_strategy="adaptive" if mode == "minimize" else None,
            callbacks={"grad_f": grad_f, "jac_g": jac_g, "hess_lag": hess_lag})
        self.builds += 1
        return build_solver(f"polish_{robot.name}_{mode}", {"x": z, "p": p, "f": f, "g": g},
                            options, self._deadline)

    # ------------------------------------------------------------ per solve

    def _select(self, distances: np.ndarray) -> Selection:
        """Assign the pairs nearer than ``near_margin`` (nearest first) to the slots.

        ``distances``: (N·P + M,) obstacle pair distances (body-major) then self distances.
        """
        return select_slots(self._groups, self._n_bodies, self._self_pairs,
                            self.config.near_margin, self.safety_margin, distances)

    def _distances(self, z: np.ndarray) -> np.ndarray:
        """(…, N·P + M) pair distances (m) of z (…, 3n): exact below ``near_margin`` (and
        δ), lower bounds above."""
        if np.ndim(z) == 1:
            return self._pairs.near(z, self._margin, centres=self._rows.centres(z))
        return self._pairs.near(z, self._margin)

    def _slot_values(self, q_near: Any, q: Any) -> tuple[np.ndarray, np.ndarray]:
        """The clearance rows switched on for the warm start ``q_near``, evaluated at ``q``
        (3n, rad/m) as the NLP sees them, and the world's float64 distances of the same
        pairs (m, convex parts with ``face_smoothing``): the two must agree."""
        from ...world.clearance import all_pair_distances_numpy

        z_near, z = (q_to_z_numpy(np.reshape(x, -1)) for x in (q_near, q))
        selection = self._select(self._distances(z_near))
        values = np.asarray(self._rows.functions()[0](z, *selection.parameters)).reshape(-1)
        world = all_pair_distances_numpy(self.robot, self._pairs.arrays, z,
                                         self.config.face_smoothing)
        return values[np.isfinite(selection.lower)], world[selection.chosen]

    def _evaluate(self, z: np.ndarray, target_position: np.ndarray,
                  target_rotation: np.ndarray) -> tuple[np.ndarray, float, dict[str, float],
                                                        np.ndarray]:
        """Float64, independent of Ipopt, at z projected onto the simple limits: (that z,
        pose error, violations per family, all pair distances)."""
        q = project_bending(self.robot, z_to_q_numpy(z))
        z = q_to_z_numpy(q)
        error = np.asarray(self._model.functions_z["pose_error"](z, target_position,
                                                                 target_rotation))
        distances = self._distances(z)
        return (z, float(np.linalg.norm(error)), self._shared_violations(z, distances),
                distances)

    def _run(self, mode: str, x0: np.ndarray, z_start: np.ndarray, selection: Selection,
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
        run = run_solver(self._solvers[mode], x0, self._deadline, p=parameters, lbx=self._lbx,
                         ubx=self._ubx, lbg=np.concatenate(lower), ubg=np.concatenate(upper))
        z, status, ipopt_success, iterations = run.x, run.status, run.success, run.iterations
        if not np.all(np.isfinite(z)):
            z, ipopt_success = x0.copy(), False
        z, error, violations, distances = self._evaluate(z, target_position, target_rotation)
        return _Attempt(mode, z, status, ipopt_success, iterations, error, violations,
                        distances)

    def _succeeded(self, attempt: _Attempt) -> bool:
        cfg = self.config
        return (attempt.ipopt_success and attempt.max_violation <= cfg.violation_tolerance
                and attempt.pose_error <= cfg.pose_tolerance)

    def solve(self, q0: Any, target_position: Any, target_rotation: Any,
              time_limit: float | None = None) -> PolishResult:
        """Polish one IK answer.

        Args:
            q0: (3n,) warm start θ, φ, L (rad, rad, m), typically stage 2's answer; it may
                violate the limits or the clearance.
            target_position: (3,) metres, world frame.
            target_rotation: (3, 3) rotation matrix, world frame.
            time_limit: seconds this solve may take (None: no limit); past it Ipopt stops
                and the best attempt so far is returned with ``out_of_time``.

        Returns a ``PolishResult``; a numerical failure is ``success=False`` with the best
        configuration Ipopt reached (or ``q0``), never an exception.
        """
        q0 = np.asarray(q0, dtype=np.float64).reshape(-1)
        near = (self._distances(q_to_z_numpy(q0)) if np.all(np.isfinite(q0))
                and q0.shape == (self.robot.dof,) else None)
        return self._solve(q0, target_position, target_rotation, near, time_limit)

    def _solve(self, q0: np.ndarray, target_position: Any, target_rotation: Any,
               near: np.ndarray | None, time_limit: float | None = None) -> PolishResult:
        """``solve`` with the warm start's pair distances ``near`` already computed."""
        start = time.perf_counter()
        if self._interpreted and not pending():
            self._solvers = self._build_all()
        self._deadline.start(time_limit)
        try:
            return self._solve_until(q0, target_position, target_rotation, near, start)
        finally:
            self._deadline.start(None)

    def _solve_until(self, q0: np.ndarray, target_position: Any, target_rotation: Any,
                     near: np.ndarray | None, start: float) -> PolishResult:
        """``_solve`` with its deadline set."""
        robot = self.robot
        target_position = np.asarray(target_position, dtype=np.float64).reshape(-1)
        target_rotation = np.asarray(target_rotation, dtype=np.float64)
        if q0.shape != (robot.dof,) or target_position.shape != (3,) \
                or target_rotation.shape != (3, 3):
            raise ValueError(f"solve needs q0 ({robot.dof},), target_position (3,) and "
                             f"target_rotation (3, 3); got {q0.shape}, {target_position.shape}, "
                             f"{target_rotation.shape}")
        if near is None or not (np.all(np.isfinite(target_position))
                                and np.all(np.isfinite(target_rotation))):
            return PolishResult(q0, False, "non-finite input", math.inf, math.inf, 0,
                                time.perf_counter() - start, self.modes[0])

        z_start = q_to_z_numpy(q0)
        selection = self._select(near)
        switched_on = np.zeros(near.shape, dtype=bool)
        switched_on[selection.chosen] = True
        attempts: list[_Attempt] = []
        out_of_time = False
        for mode in self.modes:
            if self._deadline.passed():
                out_of_time = True
                break
            attempt = self._run(mode, z_start, z_start, selection, target_position,
                                target_rotation)
            out_of_time = attempt.status == TIME_LIMIT_STATUS
            violated = attempt.distances < (self.safety_margin
                                            - self.config.violation_tolerance)
            if self._groups and np.any(violated & ~switched_on) and not out_of_time:
                # A pair without a slot (far at the warm start, or beyond the capacity) came
                # too close: give the pairs near either point the slots and go on from there.
                refreshed = self._select(np.minimum(near, attempt.distances))
                again = self._run(mode, attempt.z, z_start, refreshed, target_position,
                                  target_rotation)
                again.iterations += attempt.iterations
                attempt = again
                out_of_time = attempt.status == TIME_LIMIT_STATUS
            attempts.append(attempt)
            if self._succeeded(attempt) or out_of_time:
                break
        if not attempts:
            return PolishResult(q0, False, TIME_LIMIT_STATUS, math.inf, math.inf, 0,
                                time.perf_counter() - start, self.modes[0], out_of_time=True)

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
            violations=dict(best.violations),
            out_of_time=out_of_time and not self._succeeded(best),
        )


def polish_many(polisher: IKPolisher, q0s: Any, positions: Any, rotations: Any,
                progress: bool = False, pool: Any = None,
                time_limits: Any = None) -> list[PolishResult]:
    """``polisher.solve`` for each row: q0s (B, 3n) rad/m, positions (B, 3) m, rotations
    (B, 3, 3), ``time_limits`` (B,) seconds per solve (None: no limit); a tqdm progress
    bar with ``progress``. The warm starts' pair distances come from one batched
    evaluation by ``polisher``; with a ``stages.polish._process_pool.PolishPool`` (whose workers
    build
    the same polisher) the solves are spread over its processes and come back in order,
    the same answers (each solve's limit counts from its own start)."""
    q0s = np.asarray(q0s, dtype=np.float64)
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    if not len(q0s) == len(positions) == len(rotations):
        raise ValueError(f"polish_many needs as many warm starts as targets, got {len(q0s)}, "
                         f"{len(positions)} positions and {len(rotations)} rotations")
    bar = tqdm(total=len(q0s), desc="polish (Ipopt)", unit="target") if progress else None
    near = _near_distances(polisher, q0s)
    limits = ([None] * len(q0s) if time_limits is None
              else [float(t) if np.isfinite(t) else None for t in np.ravel(time_limits)])
    if pool is not None:
        out = pool.map(_solve_near, list(zip(q0s, positions, rotations, near, limits,
                                             strict=True)), bar)
    else:
        out = []
        for i in range(len(q0s)):
            out.append(polisher._solve(q0s[i], positions[i], rotations[i], near[i],
                                       limits[i]))
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    return out


def _near_distances(polisher: IKPolisher, q0s: np.ndarray) -> list[np.ndarray | None]:
    """The warm starts' pair distances (one batched evaluation), None for a warm start
    that is not finite or has the wrong length."""
    q0s = q0s.reshape(len(q0s), -1)
    if q0s.shape[1] != polisher.robot.dof:
        return [None] * len(q0s)
    finite = np.all(np.isfinite(q0s), axis=1)
    distances = polisher._distances(q_to_z_numpy(q0s[finite])) if finite.any() else None
    out: list[np.ndarray | None] = [None] * len(q0s)
    for k, i in enumerate(np.flatnonzero(finite)):
        out[i] = distances[k]
    return out


def _solve_near(polisher: IKPolisher, q0: np.ndarray, position: np.ndarray,
                rotation: np.ndarray, near: np.ndarray | None,
                time_limit: float | None = None) -> PolishResult:
    return polisher._solve(q0, position, rotation, near, time_limit)


def build_polisher(robot: Robot, scene: Scene | None, safety_margin: float,
                   config: PolishConfig = PolishConfig()) -> IKPolisher:
    """An ``IKPolisher`` (a module-level builder, for ``stages.polish._process_pool`` workers)."""
    return IKPolisher(robot, scene, safety_margin=safety_margin, config=config)
