"""Stage 3, polish for trajectories: all waypoints in one NLP, the constraints as real
constraints, solved by Ipopt from stage 2's answer.

The variable is the (W, 3n) matrix of bending vectors ``z_k = [ux1, uy1, L1, …]`` (rad,
rad, m), one row per waypoint. Two objectives share the constraints:

- ``"path"`` (trajectory planning): start and goal fixed (``lbx = ubx``),
  ``f = w_path·Σ‖p(z_{k+1}) − p(z_k)‖² + w_smooth·Σ‖z_{k+1} − z_k‖²``, the LM stage's
  objective (``tasks.geometry.trajectory.trajectory_residual``);
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

Where the pieces are: the settings and the result in ``_trajectory_config``, the NLP's
construction in ``_trajectory_build``, its constant sparsity and assembly matrices in
``_trajectory_assembly``; here the solve (rounds, re-selection, re-evaluation) and one
polish as a unit of work for the tasks and their process pools (``trajectory_polisher``,
``polish_one``, ``describe_polish``).
"""

from __future__ import annotations

import math
import time
from typing import Any

import casadi as ca
import numpy as np

from ...model import Robot, q_to_z_numpy, z_to_q_numpy
from ...model._ops import NUMPY
from ...model.kinematics import model_tendon_lengths
from ...model.limits import project_bending
from ...world.scene import Scene
from ...world.verdict import describe_violations
from ._clearance_rows import select_slots_batch
from ._ipopt import TIME_LIMIT_STATUS, run_solver
from ._trajectory_assembly import interpolated as interpolated
from ._trajectory_build import TrajectoryNLPBuilder
from ._trajectory_config import OBJECTIVES as OBJECTIVES
from ._trajectory_config import TrajectoryPolishConfig as TrajectoryPolishConfig
from ._trajectory_config import TrajectoryPolishResult as TrajectoryPolishResult


def _all_finite(q0: np.ndarray, positions: np.ndarray | None,
                rotations: np.ndarray | None) -> bool:
    """Whether the warm start and the targets (if any) are finite."""
    return bool(np.all(np.isfinite(q0)) and (
        positions is None or (np.all(np.isfinite(positions))
                              and np.all(np.isfinite(rotations)))))


def _tendon_lengths(robot: Robot, z: np.ndarray) -> np.ndarray:
    """(W, n_tendons) tendon lengths (m) of (W, 3n) bending vectors, float64 numpy."""
    values = model_tendon_lengths(NUMPY, robot, [z[:, i] for i in range(robot.dof)])
    return np.stack(np.broadcast_arrays(*values), axis=-1).reshape(len(z), -1)


# ================================================================ the polisher


class TrajectoryPolisher(TrajectoryNLPBuilder):
    """Ipopt polish of whole trajectories for one robot, scene and number of waypoints.

    The NLP is built on first use, once per set of clearance-row capacities (a power of
    two per group, fitted to the pairs that are near), and re-solved by ``solve`` with new
    parameters (the building: ``stages.polish._trajectory_build``); ``builds`` counts
    ``nlpsol`` constructions.

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
        if not _all_finite(q0, positions, rotations):
            return TrajectoryPolishResult(q0, False, "non-finite input", math.inf,
                                          seconds=time.perf_counter() - start)
        cfg, w, dof = self.config, self.waypoints, self.robot.dof
        z0 = q_to_z_numpy(q0)
        lbx, ubx, fixed, lower, upper = self._fixed_inputs(z0, dt, positions, rotations)
        free = not self._groups

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
            solver, parameters, clearance_lower, rows, chosen = self._round_problem(near, fixed)
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
            unseen = self._unseen(distances, rows, chosen)
            limited = np.any((answer <= low + 1e-7) & (low > lbx)) or np.any(
                (answer >= high - 1e-7) & (high < ubx))
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
        errors = None if positions is None else self._pose_error_norms(z, positions, rotations)
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

    def _pose_error_norms(self, z: np.ndarray, positions: np.ndarray,
                          rotations: np.ndarray) -> np.ndarray:
        """(W,) ‖log(T_tip⁻¹·T_target)‖ (mixed m/rad) of the (W, 3n) waypoints z against the
        (W, 3) target positions and (W, 3, 3) rotations."""
        return np.linalg.norm(np.asarray(self._pose_errors(
            z.T, positions.T, np.hstack(list(rotations)))), axis=0)

    def _fixed_inputs(self, z0: np.ndarray, dt: float, positions: np.ndarray | None,
                      rotations: np.ndarray | None
                      ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray],
                                 list[np.ndarray]]:
        """What stays the same over a solve's rounds: the (W, 3n) box bounds (a ``"path"``
        problem's start and goal fixed at ``z0``'s), the parameters before the slots
        (1/Δt, the targets) and the bounds of the rows other than clearance."""
        w, n_t = self.waypoints, self._tendon_matrix.shape[0]
        lbx, ubx = np.tile(self._lbx, (w, 1)), np.tile(self._ubx, (w, 1))
        if self.objective == "path":
            lbx[0] = ubx[0] = z0[0]
            lbx[-1] = ubx[-1] = z0[-1]
        fixed = [np.array([1.0 / dt])]
        if positions is not None:
            fixed += [positions.T.ravel(order="F"),
                      np.hstack(list(rotations)).ravel(order="F")]
        lower = [np.full(self.robot.n_segments * w, -np.inf)]
        upper = [np.tile(self._theta_max ** 2, w)]
        if self._speed:
            lower.append(np.full(n_t * (w - 1), -self.robot.tendon_speed_max))
            upper.append(-lower[-1])
        if self._accel:
            lower.append(np.full(n_t * (w - 2), -self.robot.tendon_accel_max))
            upper.append(-lower[-1])
        return lbx, ubx, fixed, lower, upper

    def _round_problem(self, near: np.ndarray, fixed: list[np.ndarray]
                       ) -> tuple[ca.Function, np.ndarray, np.ndarray, np.ndarray,
                                  list[np.ndarray]]:
        """One round's NLP from the pair distances ``near`` (G, pairs): the solver, its
        parameters, the kept clearance rows' lbg, and (``_place``, ``_select``) the grid
        rows of the NLP's configurations and the pairs switched on at each."""
        fractions, rows = self._place(near)
        slots, clearance_lower, chosen = self._select(near[rows])
        capacities = self._capacities(clearance_lower)
        solver, keep = self._solver(capacities)
        clearance_lower = clearance_lower.reshape(self._n_configs, -1)[:, keep].ravel()
        slots = [s for s, c in zip(slots, capacities, strict=True) if c]
        parameters = np.concatenate([*fixed, *[s.ravel(order="F") for s in slots],
                                     fractions.ravel(order="F")])
        return solver, parameters, clearance_lower, rows, chosen

    def _unseen(self, distances: np.ndarray, rows: np.ndarray,
                chosen: list[np.ndarray]) -> bool:
        """Whether a pair closer than δ at a ``_grid`` configuration (``distances``) had no
        row in the round: no slot, or a sample without a check point."""
        switched_on = np.zeros(distances.shape, dtype=bool)
        for row, flat in zip(rows, chosen, strict=True):
            switched_on[row, flat] = True
        violated = distances < self.safety_margin - self.config.violation_tolerance
        return bool(np.any(violated & ~switched_on))

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
