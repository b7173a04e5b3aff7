"""The one Ipopt set-up of the exact stage: options, solver construction, one solve.

Both polishers (``stages.polish._ik_nlp`` for IK answers, ``stages.polish._trajectory_nlp`` for
trajectories and paths) build their NLPs here and read Ipopt's outcome here, so the
linear solver, the tolerances, the warm start and the reading of Ipopt's status are the
same in every task:

- the linear solver is MUMPS: the HSL solvers are absent from CasADi's wheels, and asking
  for one leaves the process unable to run any later Ipopt solve (docs/design.md);
- ``tol`` and ``constr_viol_tol`` are always set: they decide what a converged solve's
  "max violation" means;
- a warm start (the penalty stage's answer is next to the optimum) keeps the start point
  where it is (``warm_start_init_point``, a bound push of ``push`` instead of 1e-2) and
  may start the barrier parameter small (``mu_init``);
- a solve never raises: a numerical failure is an ``IpoptRun`` with ``success`` False;
- a solver built with a ``Deadline`` stops when it passes (status ``TIME_LIMIT_STATUS``):
  Ipopt's own ``max_wall_time`` is fixed when a solver is built, a deadline is set before
  each solve, so one built solver serves every remaining budget (exact mode's time limit).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from ...world.verdict import VIOLATION_TOLERANCE

CURVATURES = ("full", "parts", "none")


@dataclass(frozen=True)
class NLPSettings:
    """The settings every Ipopt polish shares (IK: ``PolishConfig``, trajectories and
    paths: ``TrajectoryPolishConfig``, which set their own defaults where they differ)."""

    tol: float = 1e-8
    """Ipopt's ``tol``: the scaled optimality error at which it stops."""
    constr_viol_tol: float = 1e-8
    """Ipopt's ``constr_viol_tol``: the largest unscaled constraint violation it accepts
    (rad² for the bending disks, m for clearance, m/s and m/s² for tendon rows, mixed
    m/rad for IK's pose rows)."""
    max_iter: int = 100
    """Ipopt iterations per attempt."""
    near_margin: float = 0.2
    """Metres: obstacle and self pairs farther apart than this at the warm start get no
    slot in that solve (one that comes closer than δ during the solve makes the polish
    re-assign the slots and go on)."""
    max_pairs: int = 16
    """Constraint slots per group (one group per part kind in the scene, one for self
    pairs; for trajectories, per configuration). When more pairs are near, the nearest
    ones get the slots."""
    face_smoothing: float = 0.002
    """Metres: smoothing μ of the max over a convex part's face planes, a conservative
    lower bound at most ⌈log₂ F⌉·μ/2 below the unsmoothed one (``world/_distances.py``)."""
    clearance_curvature: str = "none"
    """The clearance rows' second derivatives in the Hessian: ``"full"`` (through the
    parts' shape and the kinematics), ``"parts"`` (the parts' shape only) or ``"none"``."""
    compile: bool = True
    """Compile the clearance rows' functions to machine code, cached on disk
    (``stages.polish._compiled_functions``: about 3× faster evaluations; gcc runs in the
    background, 5–20 s once per robot and scene structure). False, or no C compiler:
    CasADi's virtual machine, the same numbers."""
    violation_tolerance: float = VIOLATION_TOLERANCE
    """Largest re-evaluated violation (rad, m, m/s, m/s²) of a successful polish."""
    print_level: int = 0
    """Ipopt's ``print_level`` (0: silent)."""

    def __post_init__(self) -> None:
        if self.max_pairs < 1:
            raise ValueError(f"max_pairs must be at least 1, got {self.max_pairs}")
        if self.clearance_curvature not in CURVATURES:
            raise ValueError("clearance_curvature must be 'full', 'parts' or 'none', got "
                             f"{self.clearance_curvature!r}")

SUCCESS_STATUSES = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
"""Ipopt return statuses of a converged solve."""

TIME_LIMIT_STATUS = "Maximum_WallTime_Exceeded"
"""The status of a solve stopped by its ``Deadline`` (Ipopt's own name for a stop at
``max_wall_time``)."""


class Deadline:
    """When the solves of the solvers built with it (``build_solver(..., deadline=)``)
    stop: Ipopt asks at every iteration (an ``iteration_callback``) and stops once
    ``time.perf_counter()`` has passed ``at``. One deadline may serve several solvers
    (a polisher's modes and slot capacities)."""

    def __init__(self) -> None:
        self.at = math.inf
        """``time.perf_counter()`` seconds at which solves stop; +inf: never."""
        self._callbacks: list[ca.Callback] = []   # CasADi keeps no Python reference

    def start(self, seconds: float | None) -> None:
        """Solves from now on stop ``seconds`` from now (None: never)."""
        self.at = math.inf if seconds is None else time.perf_counter() + float(seconds)

    def left(self) -> float:
        """Seconds until the deadline (negative once passed, +inf without one)."""
        return self.at - time.perf_counter()

    def passed(self) -> bool:
        """The deadline has passed."""
        return time.perf_counter() >= self.at


class _StopAtDeadline(ca.Callback):
    """Ipopt's ``iteration_callback``: returns 1 (stop) once the deadline has passed. Its
    inputs are the NLP's outputs (x, f, g, lam_x, lam_g, lam_p), unread."""

    def __init__(self, name: str, sizes: dict[str, int], deadline: Deadline) -> None:
        ca.Callback.__init__(self)
        self._sizes, self._deadline = sizes, deadline
        self.construct(name, {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "stop"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self._sizes[ca.nlpsol_out(i)], 1)

    def eval(self, arg: list[Any]) -> list[Any]:
        return [1 if time.perf_counter() >= self._deadline.at else 0]


@dataclass(frozen=True)
class WarmStart:
    """How a solve from a good start point is started."""

    push: float
    """Ipopt's ``warm_start_bound_push`` and ``warm_start_mult_bound_push``: how far the
    start point and its multipliers are moved inside their bounds (Ipopt's default
    1e-3, here small: the start is already where it should be)."""
    mu_init: float | None = None
    """Ipopt's ``mu_init`` (the first barrier parameter), None for Ipopt's 0.1."""


def ipopt_options(*, tol: float, constr_viol_tol: float, max_iter: int, print_level: int = 0,
                  warm_start: WarmStart | None = None, mu_strategy: str | None = None,
                  hessian_approximation: str | None = None,
                  callbacks: dict[str, ca.Function] | None = None,
                  mumps_pivot_order: int | None = None) -> dict[str, Any]:
    """The ``nlpsol`` options of one polish NLP.

    Args:
        tol: Ipopt's ``tol``, the scaled optimality error at which it stops.
        constr_viol_tol: Ipopt's ``constr_viol_tol``, the largest unscaled constraint
            violation (the rows' own units: m, rad, m/s, ...) it accepts.
        max_iter: Ipopt iterations at most.
        print_level: Ipopt's ``print_level`` (0: silent; above 0 also CasADi's timings).
        warm_start: start from the given point (``WarmStart``), None for a cold start.
        mu_strategy: Ipopt's ``mu_strategy`` ("monotone", "adaptive"), None: Ipopt's.
        hessian_approximation: "exact" or "limited-memory", None: Ipopt's ("exact").
        callbacks: CasADi derivative functions by option name (``grad_f``, ``jac_g``,
            ``hess_lag``) that replace the ones CasADi would generate.
        mumps_pivot_order: MUMPS's fill-reducing ordering (Ipopt's ``mumps_pivot_order``:
            0 AMD, 5 METIS, 7 MUMPS's choice), None: Ipopt's (7).
    """
    options: dict[str, Any] = {
        "ipopt.tol": tol,
        "ipopt.constr_viol_tol": constr_viol_tol,
        "ipopt.max_iter": max_iter,
        "ipopt.linear_solver": "mumps",      # HSL solvers are absent: never select them
        "ipopt.print_level": print_level,
        "ipopt.sb": "yes",
        "print_time": print_level > 0,
        "error_on_fail": False,
        # The multipliers of the parameters are not used; their derivative graph is not
        # built.
        "no_nlp_grad": True,
        "calc_lam_p": False,
    }
    if hessian_approximation is not None:
        options["ipopt.hessian_approximation"] = hessian_approximation
    if mu_strategy is not None:
        options["ipopt.mu_strategy"] = mu_strategy
    if mumps_pivot_order is not None:
        options["ipopt.mumps_pivot_order"] = mumps_pivot_order
    if warm_start is not None:
        options.update({"ipopt.warm_start_init_point": "yes",
                        "ipopt.warm_start_bound_push": warm_start.push,
                        "ipopt.warm_start_mult_bound_push": warm_start.push})
        if warm_start.mu_init is not None:
            options["ipopt.mu_init"] = warm_start.mu_init
    options.update(callbacks or {})
    return options


def build_solver(name: str, nlp: dict[str, Any], options: dict[str, Any],
                 deadline: Deadline | None = None) -> ca.Function:
    """An Ipopt ``nlpsol`` for ``nlp`` (``x``, ``p``, ``f``, ``g``) with ``options``
    (``ipopt_options``); built once, re-solved with new parameters and bounds. With a
    ``deadline``, each solve stops once it has passed (``run_solver``)."""
    if deadline is not None:
        nx, ng = nlp["x"].numel(), nlp["g"].numel()
        np_ = nlp["p"].numel() if "p" in nlp else 0
        sizes = {"x": nx, "f": 1, "g": ng, "lam_x": nx, "lam_g": ng, "lam_p": np_}
        stop = _StopAtDeadline(f"{name}_deadline", sizes, deadline)
        deadline._callbacks.append(stop)
        options = {**options, "iteration_callback": stop}
    return ca.nlpsol(name, "ipopt", nlp, options)


@dataclass(frozen=True)
class IpoptRun:
    """The outcome of one Ipopt solve (never raised)."""

    x: np.ndarray
    """The solution vector, flat, float64: Ipopt's last iterate, or the start point when
    the solve raised (numbers as Ipopt returned them: not necessarily finite)."""
    objective: float
    """The objective at ``x`` (the NLP's own units); NaN when the solve raised."""
    status: str
    """Ipopt's return status, or "error: ..." when the solve raised."""
    success: bool
    """Ipopt reported a converged solve."""
    iterations: int
    """Ipopt iterations of this solve."""
    raised: bool = False
    """The solve raised (a numerical failure inside CasADi or Ipopt)."""

    @property
    def out_of_time(self) -> bool:
        """The solve stopped at its deadline (status ``TIME_LIMIT_STATUS``)."""
        return self.status == TIME_LIMIT_STATUS


def run_solver(solver: ca.Function, x0: np.ndarray, deadline: Deadline | None = None,
               **arguments: Any) -> IpoptRun:
    """Solve once from ``x0`` with ``arguments`` (``p``, ``lbx``, ``ubx``, ``lbg``,
    ``ubg``) and read Ipopt's statistics; a numerical failure is a result, not an
    exception. ``deadline``: the one the solver was built with; a solve it stopped has
    status ``TIME_LIMIT_STATUS`` (Ipopt reports the callback's stop as a user's)."""
    x0 = np.asarray(x0, dtype=np.float64)
    try:
        solution = solver(x0=x0.reshape(-1), **arguments)
        stats = solver.stats()
    except RuntimeError as exc:
        return IpoptRun(x0.reshape(-1).copy(), math.nan, f"error: {exc}", False, 0, True)
    status = str(stats.get("return_status", "unknown"))
    if status == "User_Requested_Stop" and deadline is not None and deadline.passed():
        status = TIME_LIMIT_STATUS
    return IpoptRun(np.asarray(solution["x"], dtype=np.float64).reshape(-1),
                    float(solution["f"]), status,
                    bool(stats.get("success", False)), int(stats.get("iter_count", 0)))
