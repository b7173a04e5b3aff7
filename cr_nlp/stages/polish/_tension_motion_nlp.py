"""Stage 3, polish, in tension space: a whole tension motion (a plan, a followed path) on
the Cosserat rod, solved by Ipopt with its constraints as constraints.

A motion is T waypoints of tensions ``dt`` apart; between two waypoints the tensions move
linearly and the robot passes through the equilibria of the interpolated tensions. The
verdict (``tasks.mechanics._motion``) checks every waypoint and ``samples_between``
evenly spaced tension sets between each pair, R = T + (T − 1)·k tension sets. Each
waypoint, and each sample whose backbone comes within δ' + ``sample_margin`` of an
obstacle or of itself, is one rod in the NLP (``EXACT_MODE``), in multiple shooting over
the JAX statics' RK4 steps (``_rod_shooting``, as the IK polish): its tensions, its base
moment M(0) and every step's end state are unknowns, each step an equality. The samples
left out are solved afresh (JAX statics) after Ipopt; where one came nearer than δ', the
samples then near join and Ipopt starts again (``sample_rounds``). So every tension set
the verdict checks is either constrained or measured clear. Constraints:

- every rod's steps and its tip's moment balance ``M(L) = M_tip`` (an equilibrium of the
  discrete equations the verdict's fresh statics solves);
- a sample rod's tensions are the interpolation of its two waypoints' (linear rows);
- tension bounds ``0 ≤ τ ≤ τ_max`` at the waypoints (the samples lie between them);
- the tension rate between neighbouring waypoints, ``|τₖ₊₁ − τₖ| ≤ τ̇_max·dt`` (linear);
- clearance ≥ δ' of every rod's backbone: the slot rows of ``_rod_clearance`` (spheres
  at the grid points and along the chords, obstacle and self pairs), at the waypoints
  and at the samples in the NLP;
- planning: the first and last waypoints' tensions fixed (simple bounds);
- following: every waypoint's tip at its target (3 rows, metres; each within
  ``target_tolerance`` or equal) and, when asked, its orientation (the skew part of R*ᵀR).

Objective, in tensions scaled by τ_max: "smooth" Σ‖τ̃ₖ₊₁ − τ̃ₖ‖² + ρ·Σ‖τ̃ₖ‖² (the smoothest
motion; ρ small, the least-tension tie-break among the redundant tension sets) or
"nearest" Σ‖τ̃ₖ − τ̃ₖ,start‖² (nearest to the refine stage's motion).

Derivatives: each rod is one CasADi function (its rows, their Jacobian from the steps'
compiled blocks and CasADi's own for the tip and clearance rows, its Lagrangian's
Hessian); the rods of one kind are evaluated by one CasADi map in threads over the
process's cores; the NLP's Jacobian and Hessian are block-diagonal over the rods (their
nonzeros picked from the maps' outputs by one gather, ``_block_diagonal``) plus the
constant linear rows and the objective's constant Hessian. The clearance rows' curvature
is left out of the Hessian by default (``clearance_curvature``): on the clutter suite's
first 60-waypoint path the same 27 iterations and answer, the Hessian 0.73 → 0.45 s per
evaluation. The rods' functions are built once per robot, scene, statics settings,
point-load arc lengths, waypoint count, samples and target kind
(``tension_motion_polisher``, cached), the NLP once per set of rods (the last few kept),
and re-solved with parameters (loads, targets, reference, slots) and bounds (rate step,
ends, tolerance). Units: metres, radians, newtons, N·m, seconds.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from typing import Any

import casadi as ca
import numpy as np

from ...model import Robot
from ...model.cosserat import CasadiRod, RodLoads, StaticsConfig, flat_loads, moment_scale
from ...model.loads import StaticLoads
from ...model.rotations import matrix_from_wxyz
from ...runtime import cached
from ...world.scene import Scene
from ._block_diagonal import Stacked, block_diagonal, columns_in_order
from ._ipopt import (
    SUCCESS_STATUSES,
    TIME_LIMIT_STATUS,
    Deadline,
    WarmStart,
    build_solver,
    ipopt_options,
    run_solver,
)
from ._rod_clearance import RodClearance
from ._rod_shooting import STATE, ShootingRows, ShootingSolvers, states_function
from ._tension_ik_nlp import _start_moments
from ._tension_motion_config import (
    TARGETS,
    TensionMotionPolish,
    TensionMotionPolishConfig,
    sample_weights,
)


def _triplets(shape: tuple[int, int], rows: list[int], cols: list[int],
              values: list[float]) -> ca.DM:
    return ca.DM.triplet(rows, cols, ca.DM(values), shape[0], shape[1])


class TensionMotionPolisher(ShootingSolvers):
    """The Ipopt polish of tension motions of ``count`` waypoints for one robot, scene,
    load layout and target kind.

    Args:
        robot: a robot with a ``mechanics`` block and fixed segment lengths.
        scene: a ``Scene`` or None (self pairs still constrained).
        statics: the rod's discretisation, the JAX statics' own.
        point_s: arc lengths (K,) of the point loads, m (their wrenches are parameters).
        count: T, waypoints.
        samples_between: the verdict's interpolated tension sets between waypoints.
        targets: "none" (a plan), "position" or "pose" (a followed path).
        margin: δ, metres.
        config: ``TensionMotionPolishConfig``.
    """

    def __init__(self, robot: Robot, scene: Scene | None, statics: StaticsConfig,
                 point_s: tuple[float, ...], count: int, samples_between: int, targets: str,
                 margin: float,
                 config: TensionMotionPolishConfig = TensionMotionPolishConfig()) -> None:
        if targets not in TARGETS:
            raise ValueError(f"targets must be one of {TARGETS}, got {targets!r}")
        self.robot, self.config, self.targets = robot, config, targets
        self.rod = rod = CasadiRod(robot, statics, point_s)
        self.n = rod.n_tendons
        self.length = float(rod.layout.arc_length[-1])
        self.moment_scale = moment_scale(robot)
        self.tension_max = float(robot.mechanics.tension_max)
        self.tension_scale = self.tension_max if math.isfinite(self.tension_max) else 1.0
        self._state_scale = np.r_[[self.length] * 3, [1.0] * 9, [self.moment_scale] * 3]
        self.weights = sample_weights(count, samples_between)
        self.count, self.rods = count, len(self.weights)
        self.waypoint_rods = np.arange(count) * (samples_between + 1)
        self._waypoints = set(self.waypoint_rods.tolist())
        self.block = self.n + 3 + STATE * rod.steps
        self._clear = RodClearance(robot, scene, rod.layout.arc_length, margin,
                                   config.max_pairs, config.near_margin, config.face_smoothing,
                                   config.spheres_per_step)
        self._deadline = Deadline()
        self._shooting = ShootingRows(rod, self._state_scale, self.tension_scale,
                                      config.compile, fast=self.rods >= config.fast_from)
        self._states = states_function(rod)
        self._solvers: dict[tuple, ca.Function] = {}
        self._functions_of: ShootingRows | None = None    # the rods' functions: of these
        self._functions: dict[bool, tuple[tuple[ca.Function, ...], int]] = {}

    # ------------------------------------------------------------ building

    def _aims(self, r: int) -> bool:
        """Whether tension set ``r`` (of the verdict's R) has a tip target: a waypoint of a
        followed path."""
        return self.targets != "none" and r in self._waypoints

    def _rod_function(self, aim: bool) -> tuple[tuple[ca.Function, ...], int]:
        """One rod's functions of (unknowns, loads, target (3), target rotation (3 × 3),
        slots... [, λ]): (its rows and their Jacobian over its unknowns, the Hessian of
        λᵀrows, its rows alone), and its count of equality rows (the steps, the moment
        balance, the target's)."""
        rod, shooting, steps = self.rod, self._shooting, self.rod.steps
        tension, base_moment = ca.MX.sym("tension", self.n), ca.MX.sym("base_moment", 3)
        states = [ca.MX.sym(f"state_{k + 1}", STATE) for k in range(steps)]
        z = ca.vertcat(tension, base_moment, *states)
        loads, load_column = RodLoads.symbols("load", rod.n_points)
        target, target_rot = ca.MX.sym("target", 3), ca.MX.sym("target_rotation", 3, 3)
        inputs = shooting.step_inputs(loads)
        everywhere = [ca.DM.zeros(3)] + [x[:3] * self.length for x in states]
        points = ca.horzcat(*[everywhere[int(i)] for i in rod.grid.robot_points])
        clearance, slots = self._clear.rows(points)
        tip = states[-1]
        others = [tip[12:15] - loads.tip_moment / self.moment_scale]
        if aim:
            others.append(tip[:3] - target / self.length)
            if self.targets == "pose":
                rel = ca.mtimes(target_rot.T, ca.reshape(tip[3:12], 3, 3).T)  # R row-major
                others.append(0.5 * ca.vertcat(rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0],
                                               rel[1, 0] - rel[0, 1]))
        other = ca.vertcat(*others, clearance)
        values, jacobian = shooting.jacobian(tension, base_moment, states, inputs)
        lam = ca.MX.sym("lam", values.size1() + other.size1())
        # The clearance rows' curvature only where asked (``clearance_curvature``): the
        # centres are linear in the unknowns, so "parts" is "full" here.
        curved = other if self.config.clearance_curvature != "none" else ca.vertcat(*others)
        hessian = (shooting.hessian(tension, base_moment, states, inputs,
                                    lam[:STATE * steps])
                   + ca.hessian(ca.dot(lam[STATE * steps:STATE * steps + curved.size1()],
                                       curved), z)[0])
        arguments = [z, load_column, target, target_rot, *slots]
        rows = ca.Function(f"motion_rod_{int(aim)}", arguments,
                           [ca.vertcat(values, other), ca.vertcat(jacobian,
                                                                  ca.jacobian(other, z))])
        curvature = ca.Function(f"motion_rod_{int(aim)}_hessian", [*arguments, lam], [hessian])
        # The rows alone (Ipopt's line search asks for them without the Jacobian).
        alone = ca.Function(f"motion_rod_{int(aim)}_rows", arguments, [ca.vertcat(
            *shooting.defects(tension, base_moment, states, inputs), other)])
        return (rows, curvature, alone), values.size1() + other.size1() - clearance.size1()

    def _linear_rows(self, members: tuple[int, ...]) -> tuple[ca.DM, ca.DM]:
        """(A, D): the constant rows over the unknowns of the rods ``members``: A the
        samples' interpolation rows (= 0) then the waypoints' tension steps (the rate rows);
        D the objective's rows (the steps, then √ρ·τ̃ or the waypoints' τ̃ for "nearest")."""
        n, size = self.n, len(members) * self.block
        column = {r: i * self.block for i, r in enumerate(members)}
        rows, cols, values = [], [], []
        count = 0
        for r in members:
            if r in self._waypoints:
                continue
            for j in range(n):
                rows.append(count), cols.append(column[r] + j), values.append(1.0)
                for i in np.flatnonzero(self.weights[r]):
                    rows.append(count), cols.append(column[int(self.waypoint_rods[i])] + j)
                    values.append(-float(self.weights[r, i]))
                count += 1
        steps_rows, steps_cols, steps_values = [], [], []
        for k in range(self.count - 1):
            a, b = self.waypoint_rods[k], self.waypoint_rods[k + 1]
            for j in range(n):
                steps_rows += [k * n + j] * 2
                steps_cols += [column[int(b)] + j, column[int(a)] + j]
                steps_values += [1.0, -1.0]
        steps = (self.count - 1) * n
        a_matrix = _triplets((count + steps, size), rows + [count + i for i in steps_rows],
                             cols + steps_cols, values + steps_values)
        weight = (1.0 if self.config.objective == "nearest"
                  else math.sqrt(self.config.regularization))
        own = [column[int(w)] + j for w in self.waypoint_rods for j in range(n)]
        smooth = self.config.objective == "smooth"
        d_rows = (steps_rows if smooth else []) + [(steps if smooth else 0) + i
                                                    for i in range(len(own))]
        d_matrix = _triplets(((steps if smooth else 0) + len(own), size), d_rows,
                             (steps_cols if smooth else []) + own,
                             (steps_values if smooth else []) + [weight] * len(own))
        return a_matrix, d_matrix

    def _build(self, warm: bool, members: tuple[int, ...]) -> ca.Function:
        """The Ipopt solver of the rods ``members`` (``warm``: with the warm-start
        settings). Parameters: the loads (``flat_loads``), with targets the waypoints'
        targets (T × 3, base frame) and rotations (T × 3 × 3), the reference tensions
        (T·n, scaled), then every rod's slots."""
        if self._functions_of is not self._shooting:     # the step functions changed
            self._functions_of = self._shooting
            self._functions = {aim: self._rod_function(aim)
                               for aim in {False, self.targets != "none"}}
        functions = self._functions
        self._equalities = {aim: f[1] for aim, f in functions.items()}
        load_column = ca.MX.sym("loads", 12 + 6 * self.rod.n_points)
        zs = [ca.MX.sym(f"rod_{r}", self.block) for r in members]
        unknowns = ca.vertcat(*zs)
        reference = ca.MX.sym("reference", self.count * self.n)
        slot_parameters, calls, target_symbols = [], [], []
        for r, z in zip(members, zs, strict=True):
            aim = self._aims(r)
            function = functions[aim][0][0]
            slots = [ca.MX.sym(f"slot_{r}_{i}", function.size_in(4 + i))
                     for i in range(function.n_in() - 4)]
            slot_parameters += [ca.vec(s) for s in slots]
            if aim:
                target = ca.MX.sym(f"target_{r}", 3)
                rotation = ca.MX.sym(f"rotation_{r}", 3, 3)
                target_symbols += [target, ca.vec(rotation)]
            else:
                target, rotation = ca.DM.zeros(3), ca.DM.eye(3)
            calls.append((functions[aim][0], [z, load_column, target, rotation, *slots]))
        parameters = ca.vertcat(load_column, *target_symbols, reference, *slot_parameters)
        a_matrix, d_matrix = self._linear_rows(members)
        self._linear = a_matrix.size1()
        offset = ca.mtimes(ca.DM(d_matrix), unknowns)
        if self.config.objective == "nearest":
            offset = offset - reference
        objective = ca.sumsqr(offset)
        hessian_f = 2.0 * ca.mtimes(d_matrix.T, d_matrix)
        sizes = [functions[self._aims(r)][0][0].size_out(0)[0] for r in members]
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", sum(sizes) + self._linear)
        starts = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        values, alone, jacobians, hessians = _mapped(
            calls, [lam_g[starts[i]:starts[i + 1]] for i in range(len(members))])
        linear = ca.mtimes(ca.DM(a_matrix), unknowns)
        g = ca.vertcat(columns_in_order(alone), linear)
        callbacks = {
            "grad_f": ca.Function("grad_f", [unknowns, parameters],
                                  [objective, ca.gradient(objective, unknowns)],
                                  ["x", "p"], ["f", "grad_f_x"]),
            "jac_g": ca.Function("jac_g", [unknowns, parameters],
                                 [ca.vertcat(columns_in_order(values), linear),
                                  block_diagonal(jacobians, self.block,
                                                 below=ca.DM(a_matrix))],
                                 ["x", "p"], ["g", "jac_g_x"]),
            "hess_lag": ca.Function("hess_lag", [unknowns, parameters, lam_f, lam_g],
                                    [block_diagonal(hessians, self.block, upper=True)
                                     + lam_f * ca.triu(hessian_f)],
                                    ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])}
        cfg = self.config
        options = ipopt_options(
            tol=cfg.tol, constr_viol_tol=cfg.constr_viol_tol, max_iter=cfg.max_iter,
            print_level=cfg.print_level,
            warm_start=WarmStart(push=1e-9, mu_init=cfg.warm_mu_init) if warm else None,
            callbacks=callbacks, mumps_pivot_order=cfg.mumps_pivot_order)
        return build_solver(f"tension_motion_polish_{self.robot.name}", {
            "x": unknowns, "p": parameters, "f": objective, "g": g}, options, self._deadline)

    # ------------------------------------------------------------ per solve

    def _positions(self, states: np.ndarray) -> np.ndarray:
        """The robot's grid points (S+1, 3, base frame, m) of one rod's states (15 × (S'+1))."""
        return states[:3, self.rod.grid.robot_points].T

    def _fresh(self, tensions: np.ndarray, rods: list[int],
               equilibria: Callable[[np.ndarray], np.ndarray], loads: np.ndarray
               ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """For the tension sets ``rods`` of the waypoints' ``tensions`` (T, n) N: their
        scaled unknowns (the equilibrium ``equilibria`` finds, integrated) and their pair
        distances (m), by rod."""
        samples = self.weights[rods] @ tensions
        moments = equilibria(samples) if rods else np.zeros((0, 3))
        unknowns, near = {}, {}
        for r, tension, moment in zip(rods, samples, moments, strict=True):
            states = np.asarray(self._states(tension, moment, loads))
            unknowns[r] = np.concatenate([tension / self.tension_scale,
                                          moment / self.moment_scale,
                                          (states[:, 1:] / self._state_scale[:, None]).T.ravel()])
            near[r] = self._clear.distances(self._positions(states))
        return unknowns, near

    def _near_samples(self, near: dict[int, np.ndarray]) -> set[int]:
        """The samples between waypoints whose backbone comes within δ' +
        ``sample_margin``."""
        reach = self._clear.row_margin + self.config.sample_margin
        return {r for r, d in near.items() if r not in self._waypoints and d.size
                and float(np.min(d)) < reach}

    def solve(self, tensions0: np.ndarray, equilibria: Callable[[np.ndarray], np.ndarray],
              loads: np.ndarray, targets: np.ndarray | None, rotations: np.ndarray | None,
              reference: np.ndarray, fixed_ends: bool, rate_step: float,
              target_tolerance: float) -> tuple[np.ndarray, str, int]:
        """Polish one motion (base frame): waypoint tensions (T, n) N, ``equilibria`` (the
        base moments M(0) (B, 3) N·m of tension sets (B, n) N, base frame), ``loads``
        (``flat_loads``), targets (T, 3) m and rotations (T, 3, 3) or None, reference
        tensions (T, n) N, the ends fixed or not, the largest tension step between
        waypoints (N) and the targets' tolerance (m). Returns (tensions (T, n) N, Ipopt's
        status, iterations).

        The NLP holds every waypoint and the samples between them that come within
        δ' + ``sample_margin`` at the start; after Ipopt the others are solved afresh, and where
        one came nearer than δ' the samples near then join and Ipopt starts again from the
        start (at most ``sample_rounds`` runs)."""
        scale, n = self.tension_scale, self.n
        start, near = self._fresh(tensions0, list(range(self.rods)), equilibria, loads)
        fixed = [loads]
        if self.targets != "none":
            assert targets is not None
            rotations = np.tile(np.eye(3), (self.count, 1, 1)) if rotations is None else rotations
            fixed += [np.concatenate([t, rot.ravel(order="F")])
                      for t, rot in zip(targets, rotations, strict=True)]
        fixed.append(reference.ravel() / scale)
        members = tuple(sorted(self._waypoints | self._near_samples(near)))
        upper = 1.0 if math.isfinite(self.tension_max) else np.inf
        ends = {int(self.waypoint_rods[0]), int(self.waypoint_rods[-1])}
        # Fixed ends are fixed equilibria: their clearance rows would only ask δ' of shapes
        # the verdict accepted at δ (the planner refuses ends that are not clear).
        loose = ends if fixed_ends else set()
        clear = all(not near[r].size or float(np.min(near[r])) >= self._clear.row_margin
                    for r in members if r not in loose)
        order = [True, False] if self.config.warm_start and clear else [False, True]
        iterations, status = 0, "not run"
        answer = tensions0
        for again in range(self.config.sample_rounds):
            size = len(members) * self.block
            lbx, ubx = np.full(size, -np.inf), np.full(size, np.inf)
            for i, r in enumerate(members):
                at = slice(i * self.block, i * self.block + n)      # a waypoint's tensions
                if r in self._waypoints:
                    lbx[at], ubx[at] = 0.0, upper
                    if fixed_ends and r in ends:
                        lbx[at] = ubx[at] = start[r][:n]
            bounds = (lbx, ubx, rate_step / scale, target_tolerance / self.length, loose)
            x0 = np.concatenate([start[r] for r in members])
            for warm in order[:2 if self.config.warm_start else 1]:
                x, status, used = self._attempt(warm, members, x0, np.concatenate(fixed),
                                                bounds, near)
                iterations += used
                if status in SUCCESS_STATUSES or status == TIME_LIMIT_STATUS:
                    break
            place = {r: i * self.block for i, r in enumerate(members)}
            answer = np.stack([x[place[int(r)]: place[int(r)] + n]
                               for r in self.waypoint_rods]) * scale
            outside = [r for r in range(self.rods) if r not in place]
            if (status not in SUCCESS_STATUSES or not outside
                    or again == self.config.sample_rounds - 1):
                break
            _, after = self._fresh(answer, outside, equilibria, loads)
            if not any(d.size and float(np.min(d)) < self._clear.row_margin
                       - self.config.violation_tolerance for d in after.values()):
                break
            # Again from the start: the answer's motion passes through what it missed.
            near.update({r: np.minimum(near[r], d) for r, d in after.items()})
            members = tuple(sorted(set(members) | self._near_samples(after)))
        return np.clip(answer, 0.0, self.tension_max), status, iterations

    def _row_bounds(self, members: tuple[int, ...], lower: list[np.ndarray], step: float,
                    tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        """(lbg, ubg): per rod of ``members`` its equalities (the targets' within
        ``tolerance``, scaled) and its slots' lower bounds ``lower``; then the
        interpolation rows (= 0) and the rate rows (within ±``step``, scaled)."""
        low, high = [], []
        equal_steps = STATE * self.rod.steps + 3
        for i, r in enumerate(members):
            count = self._equalities[self._aims(r)]
            a, b = np.zeros(count), np.zeros(count)
            a[equal_steps:equal_steps + 3] = -tolerance
            b[equal_steps:equal_steps + 3] = tolerance
            low += [a, lower[i]]
            high += [b, np.full(lower[i].size, np.inf)]
        rates = (self.count - 1) * self.n
        interpolation = self._linear - rates
        low += [np.zeros(interpolation), np.full(rates, -step)]
        high += [np.zeros(interpolation), np.full(rates, step)]
        return np.concatenate(low), np.concatenate(high)

    def _attempt(self, warm: bool, members: tuple[int, ...], x0: np.ndarray,
                 fixed: np.ndarray, bounds: tuple[np.ndarray, np.ndarray, float, float, set[int]],
                 near: dict[int, np.ndarray]) -> tuple[np.ndarray, str, int]:
        """Ipopt on the rods ``members`` (``warm``: with the warm-start settings) from
        ``x0`` with each rod's slots on its pairs ``near`` (m, by rod); where a pair without
        a slot came too close, again from its answer with the pairs near any shape so far
        in the slots (at most ``slot_rounds`` runs; those after the first warm-started
        where ``warm_start``). Returns (the unknowns, Ipopt's status, iterations)."""
        lbx, ubx, step, tolerance, loose = bounds
        iterations, status, x = 0, "not run", x0
        rounds = self.config.slot_rounds
        for again in range(rounds):
            chosen = {r: self._clear.slot_parameters(near[r]) for r in members}
            slots = [p.ravel(order="F") for r in members for p in chosen[r][0]]
            lower = [np.full(chosen[r][1].shape, -np.inf) if r in loose else chosen[r][1]
                     for r in members]
            solver = self._solver(warm or (again > 0 and self.config.warm_start), members)
            lbg, ubg = self._row_bounds(members, lower, step, tolerance)
            run = run_solver(solver, x, self._deadline, p=np.concatenate([fixed, *slots]),
                             lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
            iterations, status = iterations + run.iterations, run.status
            if not np.all(np.isfinite(run.x)):
                return x0, status, iterations
            x = run.x
            if again == rounds - 1 or run.out_of_time or not self._clear.groups:
                break
            closer = False
            for i, r in enumerate(members):
                if r in loose:
                    continue
                z = x[i * self.block: (i + 1) * self.block]
                solved = z[self.n + 3:].reshape(-1, STATE)[:, :3] * self.length
                after = self._clear.distances(np.vstack([np.zeros((1, 3)), solved])[
                    self.rod.grid.robot_points])
                unslotted = np.ones(after.shape, bool)
                unslotted[chosen[r][2]] = False
                closer |= bool(np.any(unslotted & (after < self._clear.row_margin
                                                   - self.config.violation_tolerance)))
                near[r] = np.minimum(near[r], after)
            if not closer:
                break
        return x, status, iterations


def _mapped(calls: list[tuple[tuple[ca.Function, ...], list[Any]]], lams: list[Any]
            ) -> list[list[Stacked]]:
    """The rods (in ``calls``' order: (its functions, its arguments); λ its rows'
    multipliers ``lams``) evaluated kind by kind, each kind by one map over the process's
    cores (CasADi's threads); the loads, the second argument, are every rod's. Per output
    (rows, rows alone, Jacobian, Hessian) the maps' outputs with their rods' places."""
    out: list[list[Stacked]] = [[], [], [], []]
    kinds = list(dict.fromkeys(id(f) for f, _ in calls))
    for kind in kinds:
        group = [i for i, (f, _) in enumerate(calls) if id(f) == kind]
        (rows, curvature, only), first = calls[group[0]]
        stacked = [ca.horzcat(*[calls[i][1][j] for i in group]) for j in range(len(first))]
        stacked[1] = first[1]
        value, jacobian = _each_rod(rows, len(group), *stacked)
        (alone,) = _each_rod(only, len(group), *stacked)
        (hessian,) = _each_rod(curvature, len(group), *stacked,
                               ca.horzcat(*[lams[i] for i in group]))
        for k, m in enumerate((value, alone, jacobian, hessian)):
            out[k].append((m, group))
    return out


def _each_rod(f: ca.Function, count: int, *args: Any) -> list[Any]:
    """``f`` on ``count`` rods' horizontally stacked ``args`` in CasADi's threads: its
    outputs, the rods' side by side."""
    threads = min(count, len(os.sched_getaffinity(0)))
    mapped = f.map(count, "thread", max(1, threads))(*args)
    return list(mapped) if isinstance(mapped, (list, tuple)) else [mapped]


def _checked(robot: Robot, tensions0: Any, dt: float, rate_max: float, samples_between: int,
             targets: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """(tensions (T, n) N, targets (T, 3) m or None), their shapes checked."""
    tensions0 = np.atleast_2d(np.asarray(tensions0, dtype=float))
    count = len(tensions0)
    if tensions0.shape[1:] != (robot.n_tendons,) or count < 2:
        raise ValueError(f"polish_tension_motion needs tensions0 (T ≥ 2, {robot.n_tendons}) "
                         f"N, got {tensions0.shape}")
    if not (dt > 0 and rate_max > 0) or samples_between < 0:
        raise ValueError(f"polish_tension_motion needs dt > 0 s, rate_max > 0 N/s and "
                         f"samples_between ≥ 0, got {dt}, {rate_max}, {samples_between}")
    aims = None if targets is None else np.asarray(targets, dtype=float).reshape(-1, 3)
    if aims is not None and len(aims) != count:
        raise ValueError(f"polish_tension_motion: {len(aims)} targets for {count} waypoints")
    return tensions0, aims


@cached(maxsize=8)
def tension_motion_polisher(robot: Robot, scene: Scene | None, statics: StaticsConfig,
                            point_s: tuple[float, ...], count: int, samples_between: int,
                            targets: str, margin: float,
                            config: TensionMotionPolishConfig = TensionMotionPolishConfig()
                            ) -> TensionMotionPolisher:
    """The ``TensionMotionPolisher`` of these settings, built once per process (building
    the NLP costs seconds)."""
    return TensionMotionPolisher(robot, scene, statics, point_s, count, samples_between,
                                 targets, margin, config)


def polish_tension_motion(robot: Robot, scene: Scene | None, tensions0: Any,
                          loads: StaticLoads, *, dt: float, rate_max: float, margin: float,
                          samples_between: int = 2, fixed_ends: bool = False,
                          targets: Any = None, wxyz: Any = None,
                          statics_config: StaticsConfig | None = None,
                          time_limit: float | None = None,
                          config: TensionMotionPolishConfig = TensionMotionPolishConfig()
                          ) -> TensionMotionPolish:
    """Polish one tension motion with Ipopt (``EXACT_MODE``).

    Args:
        robot: a robot with a ``mechanics`` block.
        scene: the obstacles, or None.
        tensions0: (T, n) start tensions at the waypoints, N (the refine stage's motion).
        loads: the motion's one load case (``model.loads.static_loads(1, …)``, world frame).
        dt: seconds between waypoints.
        rate_max: the largest |dτ/dt| of any tendon, N/s.
        margin: δ, m: the clearance the capsule chain of every solved backbone (waypoints
            and samples) must keep from obstacles and between segments two apart.
        samples_between: the verdict's interpolated tension sets between waypoints, each
            one more rod in the NLP.
        fixed_ends: keep the first and last waypoints' tensions (a plan's start and goal).
        targets: None (a plan) or (T, 3) tip positions to reach, m, world frame.
        wxyz: None, or (T, 4) tip orientations (w, x, y, z) with ``targets``.
        statics_config: the rod's discretisation (the verdict's); None: ``StaticsConfig()``.
        time_limit: seconds for the polish (None: no limit; ≤ 0: none run, the start
            comes back with ``TIME_LIMIT_STATUS``).
        config: ``TensionMotionPolishConfig``.

    Returns:
        ``TensionMotionPolish`` (tensions (T, n) N, Ipopt's status, seconds, iterations);
        "non-finite input" where a tension or target is not finite (the start kept).

    Raises:
        ValueError: shapes that do not match the robot, a bad dt, rate or sample count.
    """
    tensions0, aims = _checked(robot, tensions0, dt, rate_max, samples_between, targets)
    count = len(tensions0)
    began = time.perf_counter()
    if time_limit is not None and time_limit <= 0:
        return TensionMotionPolish(tensions0.copy(), TIME_LIMIT_STATUS, 0.0, 0)
    if not np.all(np.isfinite(tensions0)) or (aims is not None and not np.all(np.isfinite(aims))):
        return TensionMotionPolish(tensions0.copy(), "non-finite input", 0.0, 0)
    statics_config = StaticsConfig() if statics_config is None else statics_config
    base_rot = robot.base_rotation
    frame = loads.in_base_frame(base_rot)
    real = np.any(frame.point_force[0] != 0, axis=1) | np.any(frame.point_moment[0] != 0, axis=1)
    kind = "none" if aims is None else ("position" if wxyz is None else "pose")
    polisher = tension_motion_polisher(robot, scene, statics_config,
                                       tuple(float(s) for s in frame.point_s[0][real]), count,
                                       int(samples_between), kind, float(margin), config)
    starts = np.clip(tensions0, 0.0, polisher.tension_max)

    def equilibria(tensions: np.ndarray) -> np.ndarray:
        return _start_moments(robot, tensions, loads.rows(np.zeros(len(tensions), int)),
                              statics_config) @ base_rot
    column = flat_loads(frame.tip_force[0], frame.tip_moment[0], frame.gravity[0],
                        frame.distributed_force[0], frame.point_force[0][real],
                        frame.point_moment[0][real])
    base_targets = rotations = None
    if aims is not None:
        base_targets = (aims - np.asarray(robot.base_position, dtype=float)) @ base_rot
        if wxyz is not None:
            quats = np.asarray(wxyz, dtype=float).reshape(count, 4)
            rotations = np.stack([base_rot.T @ matrix_from_wxyz(q) for q in quats])
    polisher._deadline.start(None if time_limit is None
                             else time_limit - (time.perf_counter() - began))
    try:
        out, status, iterations = polisher.solve(
            starts, equilibria, column, base_targets, rotations, starts, fixed_ends,
            rate_max * dt, config.target_tolerance)
    finally:
        polisher._deadline.start(None)
    return TensionMotionPolish(out, status, time.perf_counter() - began, iterations)
