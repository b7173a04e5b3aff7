"""The Cosserat rod of ``model._rod`` evaluated by CasADi: the same discrete equations.

``model._rod.rk4_step`` is the one RK4 step of the rod (strains with their constitutive
sweeps, the tendons' terms, gravity on the grid's masses, the tip and point forces, the
force per metre, the point moments' jumps), written on entries (``model._ops``). JAX scans
it over the grid (``_integrate``); here each step is an SX function of its start state,
the tensions and the step's loads, called once per step of the same grid: the grid of
``_grid_with_points`` for point loads at fixed arc lengths. A solver may chain the calls
(single shooting: ``CasadiRod.integrate``) or take every step's end state as a variable
and the step as an equality (multiple shooting: ``CasadiRod.step``); both give exactly the
discrete equations the JAX statics solves. Units: metres, radians, newtons, N·m, kg, m/s².
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from .._ops import CASADI
from ..robot import Robot
from ._rod import (
    RK4_STAGES,
    StaticsConfig,
    _grid_with_points,
    _Layout,
    _layout,
    rk4_step,
    step_stiffness,
)

STATE_SIZE = 15
"""Entries of a step's state: position p (3, m), rotation R (9, row-major), moment M (3, N·m)."""


@dataclass(frozen=True)
class RodGrid:
    """The integration grid of one set of point-load arc lengths (float64 numpy)."""

    step_length: np.ndarray   # (S',) m
    mass: np.ndarray          # (S', 3) kg distal of each step's start, middle and end
    length: np.ndarray        # (S', 3) m of backbone distal of the same points
    active: np.ndarray        # (S', T) 1 where the tendon runs through the step
    distal: np.ndarray        # (S', K) 1 where point load k lies distal of the step
    ends_here: np.ndarray     # (S', K) 1 where point load k acts at the step's end
    robot_points: np.ndarray  # (S + 1,) which of the S' + 1 points are the robot's grid


def rod_grid(lay: _Layout, point_s: Any) -> RodGrid:
    """The grid of ``lay`` with a point at each arc length ``point_s`` (K,) m (K = 0: the
    robot's own grid, as the JAX statics takes it without point loads)."""
    point_s = np.asarray(point_s, dtype=np.float64).reshape(-1)
    if point_s.size == 0:
        start, end = lay.arc_length[:-1], lay.arc_length[1:]
        length = lay.arc_length[-1] - np.stack([start, 0.5 * (start + end), end], -1)
        steps = len(lay.step_length)
        return RodGrid(lay.step_length, lay.mass_distal, length, lay.active,
                       np.zeros((steps, 0)), np.zeros((steps, 0)), np.arange(steps + 1))
    arrays = _grid_with_points(lay, point_s, np, np.float64)
    return RodGrid(*(np.asarray(a, dtype=np.int64 if k == 6 else np.float64)
                     for k, a in enumerate(arrays)))


def _stages(body: Any, init: tuple) -> tuple:
    """The RK4 stages as a Python loop (``rk4_step``'s ``stages`` on CasADi)."""
    inner = init
    for stage in RK4_STAGES:
        inner = body(inner, stage)
    return inner


class CasadiRod:
    """The rod of a robot as CasADi functions on one grid.

    Args:
        robot: a robot with a ``mechanics`` block and fixed segment lengths.
        config: the discretisation (steps, constitutive sweeps) shared with the JAX statics.
        point_s: arc lengths (K,) of the point loads from the base, m (the grid's extra
            points); their forces and moments stay inputs.
    """

    def __init__(self, robot: Robot, config: StaticsConfig = StaticsConfig(),
                 point_s: Any = ()) -> None:
        self.robot, self.config = robot, config
        self.layout = lay = _layout(robot, config)
        self.grid = rod_grid(lay, point_s)
        self.n_tendons = lay.active.shape[1]
        self.n_points = int(np.asarray(point_s).size)
        # a step's constants: its tendons and its segment's stiffness factor
        self._stiffness = step_stiffness(lay, self.grid.step_length, lay.stiffness)
        patterns = {self._key(k) for k in range(self.steps)}
        self._functions = {key: self._step_function(*key) for key in patterns}

    @property
    def steps(self) -> int:
        """S', the number of RK4 steps."""
        return len(self.grid.step_length)

    def _key(self, k: int) -> tuple[tuple[float, ...], float]:
        return tuple(self.grid.active[k].tolist()), float(self._stiffness[k])

    def _step_function(self, act: tuple[float, ...], stiffness: float) -> ca.Function:
        """SX ``(x (15), tension (T), h, mass (3), length (3), force (3), gravity (3),
        distributed (3), jump (3)) -> (x at the step's end (15), tendon length gained
        (T))`` for the tendons ``act`` (constants: a slack tendon's terms vanish)."""
        x = ca.SX.sym("x", STATE_SIZE)
        tension = ca.SX.sym("tension", self.n_tendons)
        h = ca.SX.sym("h")
        mass, length = ca.SX.sym("mass", 3), ca.SX.sym("length", 3)
        force, gravity = ca.SX.sym("force", 3), ca.SX.sym("gravity", 3)
        distributed, jump = ca.SX.sym("distributed", 3), ca.SX.sym("jump", 3)
        entries = [x[i] for i in range(STATE_SIZE)]
        zero = ca.SX(0)
        state = (tuple(entries[:3]), tuple(entries[3:12]), tuple(entries[12:15]),
                 tuple(zero for _ in range(self.n_tendons)))
        new = rk4_step(CASADI, self.layout, self.config, state, h, mass, length, act,
                       [tension[i] for i in range(self.n_tendons)], _entries(force),
                       _entries(gravity), _entries(distributed), _entries(jump), _stages,
                       stiffness)
        return ca.Function("rod_step", [x, tension, h, mass, length, force, gravity,
                                        distributed, jump],
                           [ca.vertcat(*new[0], *new[1], *new[2]), ca.vertcat(*new[3])],
                           ["x", "tension", "h", "mass", "length", "force", "gravity",
                            "distributed", "jump"], ["x_end", "tendon_length"])

    def step(self, k: int, x: Any, tension: Any, loads: RodLoads) -> tuple[Any, Any]:
        """Step ``k`` from state ``x`` (15, SX/MX/DM): (the state at its end (15), the
        tendon lengths gained over it (T), m)."""
        g = self.grid
        force = loads.tip_force + ca.mtimes(loads.point_force.T, ca.DM(g.distal[k]))
        jump = ca.mtimes(loads.point_moment.T, ca.DM(g.ends_here[k]))
        function = self._functions[self._key(k)]
        return function(x, tension, g.step_length[k], g.mass[k], g.length[k], force,
                        loads.gravity, loads.distributed, jump)

    def start_state(self, base_moment: Any) -> Any:
        """The state at the base (15): p = 0, R = I (base frame), M(0) = ``base_moment``."""
        return ca.vertcat(ca.DM.zeros(3), ca.DM(np.eye(3).reshape(-1)), base_moment)

    def integrate(self, tension: Any, base_moment: Any, loads: RodLoads) -> dict[str, Any]:
        """One pass from the base (single shooting), symbolic or numeric: ``states``
        (15 × (S' + 1), every grid point's state), ``positions`` (3 × (S + 1), m, the
        robot's grid points), ``tip_moment`` M(L) (3, N·m; the tip moment not
        subtracted) and ``tendon_lengths`` (T, m) along the bent robot."""
        x = self.start_state(base_moment)
        states, lengths = [x], 0
        for k in range(self.steps):
            x, gained = self.step(k, x, tension, loads)
            states.append(x)
            lengths = lengths + gained
        all_states = ca.horzcat(*states)
        return {"states": all_states,
                "positions": all_states[:3, [int(i) for i in self.grid.robot_points]],
                "tip_moment": x[12:15], "tendon_lengths": lengths}


@dataclass(frozen=True)
class RodLoads:
    """One case's loads in the base frame as CasADi columns (symbols or numbers)."""

    tip_force: Any      # (3,) N
    tip_moment: Any     # (3,) N·m
    gravity: Any        # (3,) m/s²
    distributed: Any    # (3,) N/m
    point_force: Any    # (K, 3) N
    point_moment: Any   # (K, 3) N·m

    @staticmethod
    def numeric(tip_force: Any = None, tip_moment: Any = None, gravity: Any = None,
                distributed: Any = None, point_force: Any = None,
                point_moment: Any = None) -> RodLoads:
        """Loads from numbers (None: zero; point loads (K, 3))."""
        def vec(v: Any) -> ca.DM:
            return ca.DM(np.zeros(3) if v is None else np.asarray(v, dtype=float).reshape(3))

        def rows(v: Any) -> ca.DM:
            return ca.DM(np.zeros((0, 3)) if v is None
                         else np.asarray(v, dtype=float).reshape(-1, 3))

        return RodLoads(vec(tip_force), vec(tip_moment), vec(gravity), vec(distributed),
                        rows(point_force), rows(point_moment))

    @staticmethod
    def symbols(prefix: str, points: int, sym: Any = ca.MX.sym) -> tuple[RodLoads, Any]:
        """Symbolic loads with ``points`` point loads, and all their entries as one column
        (tip force, tip moment, gravity, distributed, then the point forces and moments
        row after row): ``flat_loads`` gives the matching numbers."""
        parts = [sym(f"{prefix}_{name}", 3) for name in ("force", "moment", "gravity",
                                                         "distributed")]
        pf, pm = sym(f"{prefix}_point_force", points, 3), sym(f"{prefix}_point_moment",
                                                              points, 3)
        flat = ca.vertcat(*parts, ca.vec(pf.T), ca.vec(pm.T))
        return RodLoads(*parts, pf, pm), flat


def flat_loads(tip_force: Any, tip_moment: Any, gravity: Any, distributed: Any,
               point_force: Any, point_moment: Any) -> np.ndarray:
    """The numbers of ``RodLoads.symbols``' column: (12 + 6K,) N, N·m, m/s², N/m."""
    return np.concatenate([np.asarray(v, dtype=float).reshape(-1) for v in (
        tip_force, tip_moment, gravity, distributed, point_force, point_moment)])


def _entries(x: Any) -> tuple[Any, Any, Any]:
    return (x[0], x[1], x[2])
