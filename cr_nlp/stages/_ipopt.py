"""The one Ipopt set-up of the exact stage: options, solver construction, one solve.

Both polishers (``stages._polish`` for IK answers, ``stages._polish_trajectory`` for
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
- a solve never raises: a numerical failure is an ``IpoptRun`` with ``success`` False.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

SUCCESS_STATUSES = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
"""Ipopt return statuses of a converged solve."""


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
                  callbacks: dict[str, ca.Function] | None = None) -> dict[str, Any]:
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
    if warm_start is not None:
        options.update({"ipopt.warm_start_init_point": "yes",
                        "ipopt.warm_start_bound_push": warm_start.push,
                        "ipopt.warm_start_mult_bound_push": warm_start.push})
        if warm_start.mu_init is not None:
            options["ipopt.mu_init"] = warm_start.mu_init
    options.update(callbacks or {})
    return options


def build_solver(name: str, nlp: dict[str, Any], options: dict[str, Any]) -> ca.Function:
    """An Ipopt ``nlpsol`` for ``nlp`` (``x``, ``p``, ``f``, ``g``) with ``options``
    (``ipopt_options``); built once, re-solved with new parameters and bounds."""
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


def run_solver(solver: ca.Function, x0: np.ndarray, **arguments: Any) -> IpoptRun:
    """Solve once from ``x0`` with ``arguments`` (``p``, ``lbx``, ``ubx``, ``lbg``,
    ``ubg``) and read Ipopt's statistics; a numerical failure is a result, not an
    exception."""
    x0 = np.asarray(x0, dtype=np.float64)
    try:
        solution = solver(x0=x0.reshape(-1), **arguments)
        stats = solver.stats()
    except RuntimeError as exc:
        return IpoptRun(x0.reshape(-1).copy(), math.nan, f"error: {exc}", False, 0, True)
    return IpoptRun(np.asarray(solution["x"], dtype=np.float64).reshape(-1),
                    float(solution["f"]), str(stats.get("return_status", "unknown")),
                    bool(stats.get("success", False)), int(stats.get("iter_count", 0)))
