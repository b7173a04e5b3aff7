"""Multiple shooting over the Cosserat rod's RK4 steps: the step rows of the tension-space
exact stage and their exact first and second derivatives.

The unknowns are the scaled tensions τ̃ = τ/τ_s, the scaled moment at the base
m̃₀ = M(0)/(E·I/L) and every step's scaled end state x̃_k (position / L, rotation, moment
/ (E·I/L)); row block k is ``x̃_{k+1} − Ψ_k(x̃_k, τ̃)`` with Ψ_k the rod's step
(``model.cosserat.CasadiRod``) in scaled variables, x̃₀ the base (p = 0, R = I, m̃₀).

Derivatives. CasADi's own derivative of the whole NLP (the steps expanded into one SX
graph) was measured at 1.95 million instructions for the Hessian of the Lagrangian on
``tdcr2_rao2021`` (20 steps), 37 ms per evaluation in the virtual machine. Here each
distinct step (one per set of tendons running through it) is one small SX function with
its Jacobian (15 × (15 + n)) and the Hessian of λᵀΨ ((15 + n) square), compiled to machine
code (``stages.polish._compiled_functions``) and called once per step; the NLP's Jacobian
and Hessian are assembled from the blocks. ``-O0``: gcc -O1 took 5 minutes for one step's
Hessian (124 000 instructions) on this 2-core machine, -O0 16 s, and the -O0 code still
runs 2× faster than the virtual machine (1.0 ms against 1.9 ms per step; the Jacobian
0.2 ms against 1.6 ms). Large NLPs (``fast``) also ask for the same functions at ``-Og``,
built once per robot by a detached compiler (``FAST_FLAGS``).
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from ...model.cosserat import CasadiRod, RodLoads
from ._compiled_functions import compiled, faster_pending, pending

STATE = 15
"""Entries of a step's state: position (3), rotation (9, row-major), moment (3)."""
STEP_INPUTS = 19
"""Numbers of one step's loads and grid: h, mass (3), length (3), force (3), gravity (3),
force per metre (3), point-moment jump (3)."""
FLAGS = ("-O0",)
FAST_FLAGS = ("-Og",)
"""For large NLPs: on a 60-waypoint motion's 178 rods the Hessian blocks took 96 ms per
evaluation against 228 ms at -O0 and the Jacobian 64 against 145 ms, for about 75 s of gcc
(-O0: 8.5 s) on a 2-core machine; built by a detached process, not waited for."""


class ShootingRows:
    """The step rows of one rod in scaled variables, their Jacobian and Hessian blocks.

    Args:
        rod: the CasADi rod (its grid and step functions).
        state_scale: (15,) the units of the scaled state (m, 1, N·m).
        tension_scale: N per unit of scaled tension.
        compile: compile the step functions (in the background; ``interpreted`` says
            whether they still run in CasADi's virtual machine).
        fast: with ``compile``, also build them at ``FAST_FLAGS`` (detached) and use that
            library once it is there (``upgrading`` while it is being built).
    """

    def __init__(self, rod: CasadiRod, state_scale: np.ndarray, tension_scale: float,
                 compile: bool, fast: bool = False) -> None:
        self.rod, self.n = rod, rod.n_tendons
        self.scale = np.asarray(state_scale, dtype=float)
        self.tension_scale = float(tension_scale)
        functions, self._names = [], {}
        # One function per distinct step: its tendons and its segment's stiffness factor
        # (the rod's key of a step); the tag names the tendons and the key's place.
        for place, (key, step) in enumerate(sorted(rod._functions.items())):
            tendons, _ = key
            tag = "".join("1" if a else "0" for a in tendons) + f"_{place}"
            functions += self._derivatives(step, tag)
            self._names[key] = tag
        done, self.interpreted = compiled(functions, compile, flags=FLAGS,
                                          faster=FAST_FLAGS if fast else None)
        self.fast = fast
        self.upgrading = compile and fast and faster_pending()
        self._functions = {f.name(): f for f in done}

    def outdated(self) -> bool:
        """Whether better compiled functions than these are now there (the library being
        built when these were made is done)."""
        return ((self.interpreted and not pending())
                or (self.upgrading and not faster_pending()))

    def _derivatives(self, step: ca.Function, tag: str) -> list[ca.Function]:
        """SX (value, Jacobian, Hessian) functions of one step in scaled variables."""
        x, tension = ca.SX.sym("x", STATE), ca.SX.sym("tension", self.n)
        q, lam = ca.SX.sym("step_inputs", STEP_INPUTS), ca.SX.sym("lam", STATE)
        parts = [q[0], q[1:4], q[4:7], q[7:10], q[10:13], q[13:16], q[16:19]]
        end, _ = step(x * ca.DM(self.scale), tension * self.tension_scale, *parts)
        value = end / ca.DM(self.scale)
        both = ca.vertcat(x, tension)
        hessian, _ = ca.hessian(ca.dot(lam, value), both)
        return [ca.Function(f"rod_step_{tag}", [x, tension, q], [value]),
                ca.Function(f"rod_step_{tag}_jacobian", [x, tension, q],
                            [value, ca.jacobian(value, x), ca.jacobian(value, tension)]),
                ca.Function(f"rod_step_{tag}_hessian", [x, tension, q, lam],
                            [hessian])]

    def _call(self, k: int, kind: str, *args: Any) -> Any:
        tag = self._names[self.rod._key(k)]
        return self._functions[f"rod_step_{tag}{kind}"](*args)

    def step_inputs(self, loads: RodLoads) -> list[Any]:
        """Per step the (19,) inputs Ψ_k takes (MX, from the symbolic ``loads``)."""
        g = self.rod.grid
        out = []
        for k in range(self.rod.steps):
            force = loads.tip_force + ca.mtimes(loads.point_force.T, ca.DM(g.distal[k]))
            jump = ca.mtimes(loads.point_moment.T, ca.DM(g.ends_here[k]))
            out.append(ca.vertcat(g.step_length[k], ca.DM(g.mass[k]), ca.DM(g.length[k]),
                                  force, loads.gravity, loads.distributed, jump))
        return out

    def base_state(self, base_moment: Any) -> Any:
        """x̃₀ (15): the base, p = 0 and R = I, with the scaled moment ``base_moment``."""
        return ca.vertcat(ca.DM.zeros(3), ca.DM(np.eye(3).reshape(-1)), base_moment)

    def defects(self, tension: Any, base_moment: Any, states: list[Any],
                inputs: list[Any]) -> list[Any]:
        """The row blocks x̃_{k+1} − Ψ_k(x̃_k, τ̃) (15 each); ``states`` are x̃_1 … x̃_S'."""
        starts = [self.base_state(base_moment), *states[:-1]]
        return [states[k] - self._call(k, "", starts[k], tension, inputs[k])
                for k in range(self.rod.steps)]

    def jacobian(self, tension: Any, base_moment: Any, states: list[Any],
                 inputs: list[Any]) -> tuple[Any, Any]:
        """(the rows, their Jacobian over (τ̃, m̃₀, x̃_1 … x̃_S')) as MX."""
        steps = self.rod.steps
        starts = [self.base_state(base_moment), *states[:-1]]
        values, blocks = [], []
        identity = ca.MX(ca.DM.eye(STATE))
        for k in range(steps):
            value, d_state, d_tension = self._call(k, "_jacobian", starts[k], tension,
                                                   inputs[k])
            values.append(states[k] - value)
            # column blocks: τ̃, m̃₀, then x̃_j at 1 + j
            row = [-d_tension, ca.MX(STATE, 3)] + [ca.MX(STATE, STATE)] * steps
            if k == 0:
                row[1] = -d_state[:, 12:15]
            else:
                row[1 + k] = -d_state
            row[2 + k] = identity
            blocks.append(row)
        return ca.vertcat(*values), ca.blockcat(blocks)

    def hessian(self, tension: Any, base_moment: Any, states: list[Any], inputs: list[Any],
                lam: Any) -> Any:
        """Σ_k λ_kᵀ ∇²(x̃_{k+1} − Ψ_k) over (τ̃, m̃₀, x̃_1 … x̃_S') as MX; ``lam`` the rows'
        multipliers (15 S'). The steps' blocks are summed by one constant sparse product
        over their nonzeros (``_hessian_sum``), not block by block."""
        starts = [self.base_state(base_moment), *states[:-1]]
        blocks = [self._call(k, "_hessian", starts[k], tension, inputs[k],
                             lam[STATE * k: STATE * (k + 1)]) for k in range(self.rod.steps)]
        sparsity, picks, summed = self._hessian_sum([b.sparsity() for b in blocks])
        pieces = ca.vertcat(*[b.nz[pick] for b, pick in zip(blocks, picks, strict=True)])
        return ca.MX(sparsity, ca.mtimes(summed, pieces))

    def _hessian_sum(self, blocks: list[ca.Sparsity]) -> tuple[ca.Sparsity, list[list[int]],
                                                               ca.DM]:
        """For the steps' Hessian blocks of sparsity ``blocks`` (over (x̃_k, τ̃)): the
        sparsity of their sum over the unknowns, each block's nonzeros that fall on an
        unknown (step 0: only m̃₀ of x̃₀ is one), and the matrix (−1 entries) that sums
        those nonzeros into the sum's."""
        n, steps = self.n, self.rod.steps
        size = n + 3 + STATE * steps
        rows, cols, picks = [], [], []
        for k, sparsity in enumerate(blocks):
            place = np.full(STATE + n, -1)
            place[STATE:] = np.arange(n)
            if k == 0:
                place[12:15] = n + np.arange(3)
            else:
                place[:STATE] = n + 3 + STATE * (k - 1) + np.arange(STATE)
            row, col = (np.asarray(v) for v in sparsity.get_triplet())
            kept = np.flatnonzero((place[row] >= 0) & (place[col] >= 0))
            picks.append(kept.tolist())
            rows.append(place[row[kept]]), cols.append(place[col[kept]])
        row, col = np.concatenate(rows), np.concatenate(cols)
        cells, at = np.unique(col * size + row, return_inverse=True)   # column-major order
        sparsity = ca.Sparsity.triplet(size, size, (cells % size).tolist(),
                                       (cells // size).tolist())
        summed = ca.DM.triplet(at.tolist(), list(range(len(at))), ca.DM(-np.ones(len(at))),
                               len(cells), len(at))
        return sparsity, picks, summed


def states_function(rod: CasadiRod) -> ca.Function:
    """(τ (T) N, M(0) (3) N·m, loads (``flat_loads``)) → every grid point's state
    (15 × (S'+1)) of one integration pass: the start of a polish's unknowns."""
    n, load_column = rod.n_tendons, RodLoads.symbols("load", rod.n_points)
    tension, base_moment = ca.MX.sym("tension", n), ca.MX.sym("base_moment", 3)
    path = rod.integrate(tension, base_moment, load_column[0])["states"]
    return ca.Function("rod_states", [tension, base_moment, load_column[1]], [path]).expand()


class ShootingSolvers:
    """What the rod's polishers share: their Ipopt solvers, one per warm-start setting
    (and layout, where a polisher's NLP has several), built on first use from the shooting
    rows (``self._build(warm, *layout)``), and built again on the compiled step functions
    once those are there. A subclass sets ``rod``, ``_state_scale``, ``tension_scale``,
    ``config`` (``compile``), ``_shooting`` and ``_solvers`` ({} at first)."""

    kept_layouts = 4
    """Solvers kept per warm-start setting, the most recently used (a layout's solver
    holds its NLP's graph)."""

    def _solver(self, warm: bool, *layout: Any) -> ca.Function:
        """The Ipopt solver with the warm-start settings or Ipopt's own (of ``layout``)."""
        if self._shooting.outdated():
            self._shooting = ShootingRows(self.rod, self._state_scale, self.tension_scale,
                                          self.config.compile, self._shooting.fast)
            self._solvers.clear()
        key = (warm, *layout)
        solver = self._solvers.pop(key, None)
        if solver is None:
            solver = self._build(warm, *layout)
        self._solvers[key] = solver                  # the most recent last
        same = [k for k in self._solvers if k[0] == warm]
        for old in same[:-self.kept_layouts]:
            del self._solvers[old]
        return solver
