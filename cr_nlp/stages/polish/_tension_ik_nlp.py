"""Stage 3, polish, in tension space: tension-space IK on the Cosserat rod, solved by Ipopt.

The rod is ``model.cosserat.CasadiRod``: the RK4 steps of the JAX statics, evaluated by
CasADi. Multiple shooting over those steps (``EXACT_MODE``): the unknowns are the tensions
τ, the moment at the base M(0) and every step's end state (position, rotation, moment),
and each step is an equality ``x_{k+1} = Φ_k(x_k, τ, loads)``, so a converged answer is
an equilibrium of exactly the discrete equations the JAX statics solves. Constraints
(docs/design.md §2):

- the steps, and the tip's boundary condition ``M(L) = M_tip`` (moment balance; the force
  balance holds by construction: the cut's force is known in closed form from the loads);
- the tip at the target (3 rows, metres) and, when asked, its orientation (3 rows: the
  skew part of R*ᵀR);
- tension bounds ``0 ≤ τ ≤ τ_max`` as simple bounds;
- clearance: body spheres of ``backbone_radius`` at the solved backbone's grid points and
  at the midpoints of its chords (the capsule chain the verdict checks), one row ``d ≥ δ'``
  per (sphere, nearby obstacle part) pair and per nearby self pair (spheres on segments
  at least two apart), in the pair slots of ``stages.polish._clearance_rows``; δ' is the
  margin plus the most the capsule chain can come nearer than its spheres.

Objective: ``‖(τ − τ_ref)/τ_max‖²`` with τ_ref = 0 (least tension, default) or the start's
tensions (nearest). Variables and rows are scaled (positions by the robot's length,
moments by E·I/L, tensions by τ_max). The NLP is built once per robot, statics settings,
scene, point-load arc lengths and orientation flag (``tension_ik_polisher``, cached) and
re-solved with parameters (target, loads, reference tensions, slots) from the start's
states (its JAX statics solve, integrated by the CasADi rod). Units: metres, radians,
newtons, N·m, m/s², seconds.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import casadi as ca
import numpy as np

from ...model import Robot
from ...model.cosserat import (
    CasadiRod,
    RodLoads,
    StaticsConfig,
    flat_loads,
    moment_scale,
    solve_statics,
)
from ...model.loads import StaticLoads, static_loads
from ...model.rotations import matrix_from_wxyz
from ...runtime import cached
from ...world.scene import Scene
from ._ipopt import (
    SUCCESS_STATUSES,
    TIME_LIMIT_STATUS,
    Deadline,
    NLPSettings,
    WarmStart,
    build_solver,
    ipopt_options,
    run_solver,
)
from ._rod_clearance import RodClearance
from ._rod_shooting import STATE, ShootingRows, ShootingSolvers, states_function

EXACT_MODE = "cosserat multiple shooting"
"""The formulation of the tension-space exact stage (a result's ``exact_mode``)."""

OBJECTIVES = ("least", "nearest")


@dataclass(frozen=True)
class TensionPolishConfig(NLPSettings):
    """Settings of the tension-space IK polish (the shared ones: ``NLPSettings``; the
    clearance rows' curvature is always exact here, ``clearance_curvature`` unused)."""

    tol: float = 1e-8
    """Ipopt's ``tol`` (scaled optimality error; the objective is O(1) in scaled tensions)."""
    constr_viol_tol: float = 1e-10
    """Scaled rows: 1e-10 of the robot's length on the steps' and target's positions, of
    E·I/L on the moments, metres on the clearance rows."""
    max_iter: int = 200
    """Ipopt iterations per attempt (a start inside an obstacle took 40–75)."""
    objective: str = "least"
    """"least": ‖τ/τ_max‖²; "nearest": ‖(τ − τ_start)/τ_max‖²."""
    warm_start: bool = True
    """Start Ipopt's barrier parameter at 1e-6 with the start moved 1e-9 inside its bounds
    (the penalty stage's answer is next to the target) where the start keeps its clearance,
    and try Ipopt's own start settings where that fails (``TensionIKPolisher.solve``);
    False: Ipopt's own only."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {self.objective!r}")


class TensionPolish(NamedTuple):
    """The polished rows (a failure is a status, never an exception; nothing here is
    judged: the caller replays the tensions through a fresh statics solve)."""

    tensions: np.ndarray
    """(B, n) tensions, N, within [0, τ_max]: Ipopt's last iterate (clipped), or the start
    where no run finished (time limit, non-finite input, a numerical failure)."""
    status: list[str]
    """Ipopt's return status per row (``TIME_LIMIT_STATUS`` where the time ran out)."""
    seconds: np.ndarray
    """(B,) wall time per row (start solve, Ipopt, refreshed slots), s."""
    iterations: np.ndarray
    """(B,) Ipopt iterations per row."""


class TensionIKPolisher(ShootingSolvers):
    """The Ipopt polish of tension-space IK answers for one robot, scene and load layout.

    Args:
        robot: a robot with a ``mechanics`` block and fixed segment lengths.
        scene: a ``Scene`` or None (no obstacles; self pairs still constrained).
        statics: the rod's discretisation, the JAX statics' own.
        point_s: arc lengths (K,) of the point loads, m (their wrenches are parameters).
        oriented: with the tip orientation rows.
        margin: δ, metres: the clearance the verdict's capsule chain must keep.
        config: ``TensionPolishConfig``.
    """

    def __init__(self, robot: Robot, scene: Scene | None, statics: StaticsConfig,
                 point_s: tuple[float, ...], oriented: bool, margin: float,
                 config: TensionPolishConfig = TensionPolishConfig()) -> None:
        self.robot, self.scene, self.statics, self.config = robot, scene, statics, config
        self.oriented, self.margin = oriented, float(margin)
        self.rod = rod = CasadiRod(robot, statics, point_s)
        self.length = float(rod.layout.arc_length[-1])
        self.moment_scale = moment_scale(robot)
        tension_max = float(robot.mechanics.tension_max)
        self.tension_max = tension_max
        self.tension_scale = tension_max if math.isfinite(tension_max) else 1.0
        self._state_scale = np.r_[[self.length] * 3, [1.0] * 9, [self.moment_scale] * 3]
        self._clear = RodClearance(robot, scene, rod.layout.arc_length, self.margin,
                                   config.max_pairs, config.near_margin, config.face_smoothing)
        self.row_margin = self._clear.row_margin
        self._deadline = Deadline()
        self._shooting = ShootingRows(rod, self._state_scale, self.tension_scale, config.compile)
        self._solvers: dict[tuple, ca.Function] = {}
        self._states = states_function(rod)
        self._solver(config.warm_start)

    # ------------------------------------------------------------ building

    def _tip_rows(self, tip: Any, target: Any, target_rot: Any, loads: RodLoads) -> list[Any]:
        """The boundary rows at the tip's scaled state ``tip`` (15): M(L) = M_tip (scaled
        by E·I/L), the position at the target (by L), with ``oriented`` the orientation
        (the skew part of R*ᵀR)."""
        rows = [tip[12:15] - loads.tip_moment / self.moment_scale,
                tip[:3] - target / self.length]
        if self.oriented:
            rel = ca.mtimes(target_rot.T, ca.reshape(tip[3:12], 3, 3).T)   # R row-major
            rows.append(0.5 * ca.vertcat(rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0],
                                         rel[1, 0] - rel[0, 1]))
        return rows

    def _build(self, warm: bool) -> ca.Function:
        """The Ipopt solver (``warm``: with the warm-start settings). Parameters: target
        (3, base frame), target rotation (3 × 3, column-major), reference tensions (T),
        loads (``flat_loads``), then the slots' picks and part rows. The derivatives are
        given as callbacks: the steps' blocks (``ShootingRows``), CasADi's own for the
        objective and the few other rows."""
        rod, cfg, n, shooting = self.rod, self.config, self.rod.n_tendons, self._shooting
        tension, base_moment = ca.MX.sym("tension", n), ca.MX.sym("base_moment", 3)
        states = [ca.MX.sym(f"state_{k + 1}", STATE) for k in range(rod.steps)]
        unknowns = ca.vertcat(tension, base_moment, *states)
        target, target_rot = ca.MX.sym("target", 3), ca.MX.sym("target_rotation", 3, 3)
        reference = ca.MX.sym("reference", n)
        loads, load_column = RodLoads.symbols("load", rod.n_points)
        inputs = shooting.step_inputs(loads)
        everywhere = [ca.DM.zeros(3)] + [x[:3] * self.length for x in states]
        points = ca.horzcat(*[everywhere[int(i)] for i in rod.grid.robot_points])
        clearance, slots = self._clear.rows(points)
        others = ca.vertcat(*self._tip_rows(states[-1], target, target_rot, loads), clearance)
        defects = shooting.defects(tension, base_moment, states, inputs)
        objective = ca.sumsqr(tension - reference / self.tension_scale)
        parameters = ca.vertcat(target, ca.vec(target_rot), reference, load_column,
                                *[ca.vec(s) for s in slots])
        self._equalities = STATE * rod.steps + others.size1() - clearance.size1()
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", self._equalities
                                                      + clearance.size1())
        values, jacobian = shooting.jacobian(tension, base_moment, states, inputs)
        hessian = (shooting.hessian(tension, base_moment, states, inputs,
                                    lam_g[:STATE * rod.steps])
                   + ca.hessian(lam_f * objective
                                + ca.dot(lam_g[STATE * rod.steps:], others), unknowns)[0])
        callbacks = {
            "grad_f": ca.Function("grad_f", [unknowns, parameters],
                                  [objective, ca.gradient(objective, unknowns)],
                                  ["x", "p"], ["f", "grad_f_x"]),
            "jac_g": ca.Function("jac_g", [unknowns, parameters],
                                 [ca.vertcat(values, others),
                                  ca.vertcat(jacobian, ca.jacobian(others, unknowns))],
                                 ["x", "p"], ["g", "jac_g_x"]),
            "hess_lag": ca.Function("hess_lag", [unknowns, parameters, lam_f, lam_g],
                                    [ca.triu(hessian)], ["x", "p", "lam_f", "lam_g"],
                                    ["triu_hess_gamma_x_x"])}
        options = ipopt_options(
            tol=cfg.tol, constr_viol_tol=cfg.constr_viol_tol, max_iter=cfg.max_iter,
            print_level=cfg.print_level,
            warm_start=WarmStart(push=1e-9, mu_init=1e-6) if warm else None,
            callbacks=callbacks)
        return build_solver(f"tension_polish_{self.robot.name}", {
            "x": unknowns, "p": parameters, "f": objective,
            "g": ca.vertcat(*defects, others)}, options, self._deadline)

    # ------------------------------------------------------------ per solve

    def solve(self, tension0: np.ndarray, base_moment0: np.ndarray, target: np.ndarray,
              target_rotation: np.ndarray | None, loads: np.ndarray,
              reference: np.ndarray) -> tuple[np.ndarray, str, int]:
        """Polish one answer (base frame): tensions (T,) N and M(0) (3,) N·m of the start,
        target (3,) m, target rotation (3, 3) or None, ``loads`` (``flat_loads``),
        reference tensions (T,) N. Returns (tensions (T,) N, Ipopt's status, iterations).

        A start that keeps its clearance is solved with the warm-start settings (a small
        barrier parameter, the start kept where it is), one inside an obstacle with Ipopt's
        own (a warm start there was seen to end in Ipopt's restoration phase, "infeasible");
        a failed solve is tried again with the other settings."""
        states = np.asarray(self._states(tension0, base_moment0, loads))       # 15 × (S'+1)
        near = self._clear.distances(states[:3, self.rod.grid.robot_points].T)
        x0 = np.concatenate([tension0 / self.tension_scale, base_moment0 / self.moment_scale,
                             (states[:, 1:] / self._state_scale[:, None]).T.reshape(-1)])
        rotation = np.eye(3) if target_rotation is None else target_rotation
        fixed = np.concatenate([target, rotation.ravel(order="F"), reference, loads])
        clear = not near.size or float(np.min(near)) >= self.row_margin
        order = [True, False] if self.config.warm_start and clear else [False, True]
        iterations, status, x = 0, "not run", x0
        for warm in order[:2 if self.config.warm_start else 1]:
            x, status, used = self._attempt(self._solver(warm), x0, fixed, near)
            iterations += used
            if status in SUCCESS_STATUSES or status == TIME_LIMIT_STATUS:
                break
        n = self.rod.n_tendons
        return np.clip(x[:n] * self.tension_scale, 0.0, self.tension_max), status, iterations

    def _attempt(self, solver: ca.Function, x0: np.ndarray, fixed: np.ndarray,
                 near: np.ndarray) -> tuple[np.ndarray, str, int]:
        """One Ipopt run from ``x0`` with the slots of the pairs ``near`` (m); where a pair
        without a slot came too close, one more from its answer with the pairs near either
        shape in the slots. Returns (the unknowns, Ipopt's status, iterations)."""
        n = self.rod.n_tendons
        upper = 1.0 if math.isfinite(self.tension_max) else np.inf
        lbx = np.r_[np.zeros(n), np.full(len(x0) - n, -np.inf)]
        ubx = np.r_[np.full(n, upper), np.full(len(x0) - n, np.inf)]
        iterations, status, x = 0, "not run", x0
        for again in range(2):
            slots, lower, chosen = self._clear.slot_parameters(near)
            parameters = np.concatenate([fixed, *[s.ravel(order="F") for s in slots]])
            run = run_solver(solver, x, self._deadline, p=parameters, lbx=lbx, ubx=ubx,
                             lbg=np.r_[np.zeros(self._equalities), lower],
                             ubg=np.r_[np.zeros(self._equalities), np.full(lower.size, np.inf)])
            iterations, status = iterations + run.iterations, run.status
            if not np.all(np.isfinite(run.x)):
                return x0, status, iterations
            x = run.x
            if again or run.out_of_time or not self._clear.groups:
                break
            solved = x[n + 3:].reshape(-1, STATE)[:, :3] * self.length
            after = self._clear.distances(np.vstack([np.zeros((1, 3)), solved])[
                self.rod.grid.robot_points])
            unslotted = np.ones(after.shape, bool)
            unslotted[chosen] = False
            if not np.any(unslotted & (after < self.row_margin - self.config.violation_tolerance)):
                break
            near = np.minimum(near, after)
        return x, status, iterations


def _start_moments(robot: Robot, tensions0: np.ndarray, loads: StaticLoads,
                   statics: StaticsConfig) -> np.ndarray:
    """(B, 3) M(0) of the start tensions (N·m, world frame) by the JAX statics; where it did
    not solve, M(0) as without external forces (the tip and point moments), from which
    Ipopt's unknowns start."""
    start = solve_statics(robot, np.where(np.isfinite(tensions0), tensions0, 0.0).clip(0.0),
                          loads.tip_force, loads.tip_moment, loads.gravity, statics,
                          distributed_force=loads.distributed_force,
                          point_loads=loads.point_load_lists())
    moments = np.array(start.base_moment)
    unsolved = ~start.converged | ~np.all(np.isfinite(moments), axis=1)
    moments[unsolved] = (loads.tip_moment + loads.point_moment.sum(axis=1))[unsolved]
    return moments


@cached(maxsize=16)
def tension_ik_polisher(robot: Robot, scene: Scene | None, statics: StaticsConfig,
                        point_s: tuple[float, ...], oriented: bool, margin: float,
                        config: TensionPolishConfig = TensionPolishConfig()
                        ) -> TensionIKPolisher:
    """The ``TensionIKPolisher`` of these settings, built once per process (the NLP's
    construction and Ipopt's set-up cost seconds; a solve milliseconds)."""
    return TensionIKPolisher(robot, scene, statics, point_s, oriented, margin, config)


def polish_tension_ik(robot: Robot, scene: Scene | None, tensions0: Any, targets: Any,
                      wxyz: Any = None, loads: StaticLoads | None = None, *, margin: float,
                      statics_config: StaticsConfig | None = None,
                      time_limit: float | None = None,
                      config: TensionPolishConfig = TensionPolishConfig()) -> TensionPolish:
    """Polish tension-space IK answers with Ipopt (``EXACT_MODE``), one row at a time.

    Args:
        robot: a robot with a ``mechanics`` block.
        scene: the obstacles, or None.
        tensions0: (B, n) start tensions, N (the penalty stage's answers).
        targets: (B, 3) tip positions, m, world frame.
        wxyz: None, or (B, 4) tip orientations (unit quaternions w, x, y, z; a row of NaN
            leaves that row's orientation free).
        loads: the B cases' loads (``model.loads.static_loads``, world frame), None: none.
        margin: δ, m: the clearance the capsule chain of the solved backbone must keep
            from obstacles and between segments at least two apart.
        statics_config: the rod's discretisation (the JAX statics' own, so that a fresh
            solve of the answer meets the same equations); None: ``StaticsConfig()``.
        time_limit: seconds for the whole batch (None: no limit); rows not finished by then
            keep Ipopt's last iterate (status ``TIME_LIMIT_STATUS``), rows not started keep
            their start tensions.
        config: ``TensionPolishConfig`` (objective, tolerances, slots).

    Returns:
        ``TensionPolish``: tensions (B, n) N, Ipopt's status per row ("non-finite input"
        for a row with non-finite tensions or target: kept as given), seconds per row (the
        first row of a new robot, scene or load layout includes building its NLP, seconds),
        Ipopt iterations per row. Nothing here judges the answer: the caller's verdict does.
    """
    statics_config = StaticsConfig() if statics_config is None else statics_config
    tensions0 = np.atleast_2d(np.asarray(tensions0, dtype=float))
    targets = np.atleast_2d(np.asarray(targets, dtype=float))
    count = len(targets)
    if tensions0.shape != (count, robot.n_tendons) or targets.shape[1:] != (3,):
        raise ValueError(f"polish_tension_ik needs tensions0 ({count}, {robot.n_tendons}) N "
                         f"and targets ({count}, 3) m, got {tensions0.shape} and "
                         f"{targets.shape}")
    quats = (np.full((count, 4), np.nan) if wxyz is None
             else np.array(np.broadcast_to(np.asarray(wxyz, dtype=float), (count, 4))))
    length = float(sum(seg.length_min for seg in robot.segments))
    if loads is None:
        loads = static_loads(count, length)
    end = math.inf if time_limit is None else time.perf_counter() + float(time_limit)
    base_rot = robot.base_rotation
    frame = loads.in_base_frame(base_rot)
    base_targets = (targets - np.asarray(robot.base_position, dtype=float)) @ base_rot
    base_moments = _start_moments(robot, tensions0, loads, statics_config) @ base_rot
    finite = np.all(np.isfinite(tensions0), axis=1) & np.all(np.isfinite(targets), axis=1)
    out = np.array(tensions0)
    status = [TIME_LIMIT_STATUS] * count
    seconds, iterations = np.zeros(count), np.zeros(count, dtype=int)
    for i in range(count):
        began = time.perf_counter()
        if began >= end:
            break
        if not finite[i]:
            status[i] = "non-finite input"
            continue
        real = np.any(frame.point_force[i] != 0, axis=1) | np.any(frame.point_moment[i] != 0,
                                                                  axis=1)
        oriented = not np.any(np.isnan(quats[i]))
        polisher = tension_ik_polisher(robot, scene, statics_config,
                                       tuple(float(s) for s in frame.point_s[i][real]),
                                       oriented, float(margin), config)
        column = flat_loads(frame.tip_force[i], frame.tip_moment[i], frame.gravity[i],
                            frame.distributed_force[i], frame.point_force[i][real],
                            frame.point_moment[i][real])
        rotation = base_rot.T @ matrix_from_wxyz(quats[i]) if oriented else None
        reference = (tensions0[i] if config.objective == "nearest"
                     else np.zeros(robot.n_tendons))
        polisher._deadline.start(None if time_limit is None else end - began)
        try:
            out[i], status[i], iterations[i] = polisher.solve(
                np.clip(tensions0[i], 0.0, polisher.tension_max), base_moments[i],
                base_targets[i], rotation, column, reference)
        finally:
            polisher._deadline.start(None)
        seconds[i] = time.perf_counter() - began
    return TensionPolish(out, status, seconds, iterations)
