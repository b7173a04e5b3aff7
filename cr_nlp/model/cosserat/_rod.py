"""The Cosserat rod of a tendon-driven robot: its integration grid and equations (JAX).

Rucker & Webster's model (IEEE T-RO 2011): an elastic backbone with strains v (shear,
extension) and u (bending, torsion), ``n = R Kse (v − e3)``, ``m = R Kbt u``, and each
tendon a frictionless string routed parallel to the backbone at ``r_i`` in the disks'
frame. Cut the robot at arc length s and keep everything distal, tendons included: the
force N and moment M that cross the cut obey ``N' = −f_ext`` and ``M' = −p' × N`` with the
external loads only, so N(s) is known in closed form from the loads (``_grid``) and one
pass from a moment at the base M(0) gives the shape (``_integrate``). The shooting on
M(0) lives in ``model.cosserat``. Units: metres, radians, newtons, N·m, kg, m/s².

External loads (``CaseLoads``, base frame): a tip force and moment, gravity on the
backbone and disks, a force per unit length along the whole backbone, and point wrenches
at given arc lengths. A point load needs a grid point where it acts (N and M jump there):
the case's grid is the robot's grid with a point added at each load's arc length, and
the shape is reported at the robot's grid points only, so every case has the same points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...runtime import cached
from .._ops import JAX, Ops
from ..mechanics import require_mechanics
from ..robot import Robot
from ..routing import routing_of


@dataclass(frozen=True)
class StaticsConfig:
    """Discretisation and solver settings of the Cosserat statics."""

    min_steps_per_segment: int = 10
    """RK4 steps per segment at least; rounded up to a multiple of the segment's disks
    (disk masses act at step ends)."""
    constitutive_iterations: int = 2
    """Sweeps of the strain inversion at every integration point after the first (tendons
    parallel to the backbone); each refreshes the tendons' stretch factors."""
    max_iterations: int = 24
    """Most Newton iterations of the shooting (each: one pass with its Jacobian). 40 let 5 %
    more loading paths converge past a buckling load but cost the 10 000-case batch twice
    the time (its unfinished cases loop together); those go to the branch check instead."""
    tolerance: float | None = None
    """Converged when |M(L) − M_tip| · L / (E I) ≤ tolerance, i.e. the boundary residual as
    the bending angle (radians) it would cause over the robot. None: 1e-10 in float64,
    1e-5 in float32."""
    dtype: str = "float64"
    """"float64" (default) or "float32" (a speed setting for large batches)."""

    @property
    def numpy_dtype(self) -> type:
        """``dtype`` as the numpy type of the programs' arguments."""
        return np.float64 if self.dtype == "float64" else np.float32

    def resolved_tolerance(self) -> float:
        """The tolerance in radians of bending with the dtype's default filled in."""
        if self.tolerance is not None:
            return float(self.tolerance)
        return 1e-10 if self.dtype == "float64" else 1e-5


class _Layout(NamedTuple):
    """Static (numpy) description of the integration grid and the tendons."""

    step_length: np.ndarray   # (S,) m
    mass_distal: np.ndarray   # (S, 3) kg distal of the step's start, middle and end (−)
    active: np.ndarray        # (S, T) 1 where tendon T runs through the step's segment
    routing: np.ndarray       # (T, 3) tendon positions in the disk frame, m
    arc_length: np.ndarray    # (S + 1,) m
    total_mass_moment: np.ndarray  # (S + 1,) kg distal of each grid point (straight guess)
    kse: tuple[float, float, float]
    kbt: tuple[float, float, float]
    moment_scale: float       # E I / L, N·m per radian of bending over the robot
    disk_s: np.ndarray        # (D,) arc length of every disk, m
    linear_density: float     # kg/m
    disk_mass: float          # kg
    tendon_end: np.ndarray    # (T,) arc length where each tendon ends, m
    segment_end: np.ndarray   # (n,) arc length where each segment ends, m
    stiffness: np.ndarray     # (n,) the segments' stiffness factors (mechanics block)


@cached(maxsize=64)
def _layout(robot: Robot, config: StaticsConfig, coarse: bool = False) -> _Layout:
    """The integration grid. ``coarse``: half the steps, placed regardless of the disks
    (whose masses then fall inside steps): the grid of the shooting's Jacobian passes."""
    mech = require_mechanics(robot, "the Cosserat statics")
    if any(s.extendable for s in robot.segments):
        raise ValueError(f"{robot.name}: the Cosserat statics need fixed segment lengths")
    tendons = routing_of(robot)
    angles = tendons.angles(robot.tendons.offsets)            # (T, n)
    alpha = angles[np.arange(len(angles)), tendons.first]     # (T,) where each starts
    if not np.allclose(np.where(tendons.through, angles, alpha[:, None]), alpha[:, None]):
        raise ValueError(f"{robot.name}: a tendon whose angle changes between segments "
                         "(shared routing with different offsets per segment) is not a "
                         "straight routing")
    routing = robot.tendons.radius * np.stack(
        [np.cos(alpha), np.sin(alpha), np.zeros_like(alpha)], axis=-1)

    lengths, active, disk_s = [], [], []
    start_s = 0.0
    for i, seg in enumerate(robot.segments):
        disks = mech.disks_per_segment[i]
        per_disk = max(1, math.ceil(config.min_steps_per_segment / disks))
        steps = (max(2, math.ceil(config.min_steps_per_segment / 2)) if coarse
                 else disks * per_disk)
        disk_s += [start_s + seg.length_min * (k + 1) / disks for k in range(disks)]
        start_s += seg.length_min
        for _ in range(steps):
            lengths.append(seg.length_min / steps)
            active.append(tendons.through[:, i].astype(float))
    h = np.asarray(lengths)
    arc = np.concatenate([[0.0], np.cumsum(h)])
    total = arc[-1]
    disk_s = np.asarray(disk_s)
    ends = np.cumsum([seg.length_min for seg in robot.segments])
    tendon_end = ends[tendons.anchor]

    def distal(s: np.ndarray, include_at: bool) -> np.ndarray:
        rod = mech.linear_density * (total - s)
        gap = disk_s[None, :] - s[:, None]
        at = gap >= -1e-12 if include_at else gap > 1e-12
        return rod + mech.disk_mass * at.sum(axis=1)

    start, end = arc[:-1], arc[1:]
    mass = np.stack([distal(start, False), distal(0.5 * (start + end), False),
                     distal(end, True)], axis=-1)
    kse, kbt = mech.stiffness_diagonals()
    return _Layout(h, mass, np.asarray(active), routing, arc, distal(arc, False), kse, kbt,
                   mech.bending_stiffness / total, disk_s, float(mech.linear_density),
                   float(mech.disk_mass), np.asarray(tendon_end, dtype=float),
                   np.asarray(ends, dtype=float),
                   np.asarray(mech.stiffness_factors(robot.n_segments), dtype=float))


def step_stiffness(lay: _Layout, step_length: Any, factors: Any, xp: Any = np) -> Any:
    """(S',) the stiffness factor of each step of a grid with steps ``step_length`` (S',)
    m: the factor (n,) of the segment that holds the step's middle."""
    ends = xp.cumsum(step_length)
    middle = ends - 0.5 * step_length
    segment = xp.searchsorted(xp.asarray(lay.segment_end[:-1]), middle)
    return xp.asarray(factors)[segment]


class CaseLoads(NamedTuple):
    """One case's external loads in the base frame (a pytree: batched under ``vmap``)."""

    force: jax.Array         # (3,) tip force, N
    moment: jax.Array        # (3,) tip moment, N·m
    gravity: jax.Array       # (3,) gravitational acceleration, m/s²
    distributed: jax.Array   # (3,) force per unit length along the whole backbone, N/m;
    #                          (0,): none (a smaller program, as without point loads)
    point_s: jax.Array       # (K,) arc length of each point load from the base, m
    point_force: jax.Array   # (K, 3) N
    point_moment: jax.Array  # (K, 3) N·m

    def scaled(self, factor: Any) -> CaseLoads:
        """The same loads times ``factor`` (where they act unchanged)."""
        return CaseLoads(factor * self.force, factor * self.moment, factor * self.gravity,
                         factor * self.distributed, self.point_s,
                         factor * self.point_force, factor * self.point_moment)

    def external_force(self, lay: _Layout) -> jax.Array:
        """(3,) the sum of every external force on the robot, N (what the base carries)."""
        total = float(lay.arc_length[-1])
        return (self.force + self.gravity * float(lay.total_mass_moment[0])
                + (self.distributed * total if self.distributed.shape[0] else 0.0)
                + self.point_force.sum(axis=0))


class _Grid(NamedTuple):
    """A case's integration grid (the robot's grid plus a point at each point load)."""

    step_length: Any         # (S',) m
    mass: Any                # (S', 3) kg distal of each step's start, middle and end
    length: Any              # (S', 3) m of backbone distal of the same points
    active: Any              # (S', T)
    point_force: Any         # (S', 3) point forces distal of each step, N; None: none
    moment_jump: Any         # (S', 3) point moments at each step's end, N·m; None: none
    robot_points: Any        # (S + 1,) which of the S' + 1 points are the robot's; None: all


def _grid(lay: _Layout, loads: CaseLoads, dtype: Any) -> _Grid:
    """The grid of one case: without point loads the robot's own (constants, shared by a
    batch), else with a point added where each load acts (the cut's force N jumps there
    by the load's force, the moment M by its moment)."""
    total = float(lay.arc_length[-1])
    if loads.point_s.shape[0] == 0:
        start, end = lay.arc_length[:-1], lay.arc_length[1:]
        length = total - np.stack([start, 0.5 * (start + end), end], -1)
        return _Grid(lay.step_length, lay.mass_distal, length, lay.active, None, None, None)
    step_length, mass, length, active, distal, ends_here, robot_points = _grid_with_points(
        lay, loads.point_s, jnp, dtype)
    return _Grid(step_length, mass, length, active, distal @ loads.point_force,
                 ends_here @ loads.point_moment, robot_points)


def _grid_with_points(lay: _Layout, point_s: Any, xp: Any, dtype: Any) -> tuple:
    """The grid with a point at each arc length ``point_s`` (K,) m, by array module ``xp``
    (jnp inside the JAX programs, np for a CasADi rod built for fixed load points):
    (step lengths (S',), masses and lengths distal of each step's three points (S', 3),
    tendons through each step (S', T), which point loads lie distal of each step (S', K),
    which act at its end (S', K), and which of the S' + 1 points are the robot's (S + 1,))."""
    total = float(lay.arc_length[-1])
    robot_points = len(lay.arc_length)
    s_all = xp.concatenate([xp.asarray(lay.arc_length, dtype), xp.asarray(point_s, dtype)])
    order = xp.argsort(s_all, stable=True)  # a load at a grid point comes after it
    s = s_all[order]
    place = xp.argsort(order)               # where each entry landed in s
    start, end = s[:-1], s[1:]
    stage_s = xp.stack([start, 0.5 * (start + end), end], -1)  # (S', 3)
    gap = xp.asarray(lay.disk_s, dtype) - stage_s[..., None]
    include = xp.asarray([False, False, True])[None, :, None]
    at = xp.where(include, gap >= -1e-12, gap > 1e-12)
    mass = lay.linear_density * (total - stage_s) + lay.disk_mass * at.sum(-1)
    step = xp.arange(s.shape[0] - 1)
    load_at = place[robot_points:]             # (K,) the point where each load acts
    distal = (load_at[None, :] >= step[:, None] + 1).astype(dtype)   # (S', K)
    ends_here = (load_at[None, :] == step[:, None] + 1).astype(dtype)
    active = (stage_s[:, 1:2] < xp.asarray(lay.tendon_end, dtype)[None, :] - 1e-12)
    return (end - start, mass, total - stage_s, active.astype(dtype), distal, ends_here,
            place[:robot_points])


# ---------------------------------------------------------------- small vector helpers
# The rod equations are written once, on tuples of scalars (x, y, z; a rotation's nine
# entries), for both backends (``model._ops``): under JAX's vmap every entry is one (B,)
# array and XLA fuses the whole right-hand side into a few loops over the batch, instead of
# many small (B, 3, 3) products; under CasADi every entry is an SX or MX scalar
# (``model.rod_casadi``). Only ``ops.sqrt`` and the loop over the RK4 stages differ.

Vec = tuple[Any, Any, Any]
Rot = tuple[Any, Any, Any, Any, Any, Any, Any, Any, Any]
State = tuple[Vec, Rot, Vec, tuple]
"""The integrated state at a grid point: position p (m), rotation R (row-major), the cut's
moment M (N·m) and the tendons' lengths so far (m)."""

RK4_STAGES = ((0.0, 1.0 / 6.0, 0), (0.5, 2.0 / 6.0, 1), (0.5, 2.0 / 6.0, 1), (1.0, 1.0 / 6.0, 2))
"""The classical RK4 tableau as (shift of the stage along the step, weight, which of the
step's three points (start, middle, end) its loads are taken at)."""


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _matvec(r: Rot, v: Vec) -> Vec:
    return tuple(r[3 * i] * v[0] + r[3 * i + 1] * v[1] + r[3 * i + 2] * v[2]
                 for i in range(3))  # type: ignore[return-value]


def _rmatvec(r: Rot, v: Vec) -> Vec:
    """Rᵀ v."""
    return tuple(r[i] * v[0] + r[3 + i] * v[1] + r[6 + i] * v[2]
                 for i in range(3))  # type: ignore[return-value]


def _rot_times_hat(r: Rot, u: Vec) -> Rot:
    """R · û (the rotation's derivative along the arc)."""
    out = []
    for i in range(3):
        a, b, c = r[3 * i], r[3 * i + 1], r[3 * i + 2]
        out += [b * u[2] - c * u[1], c * u[0] - a * u[2], a * u[1] - b * u[0]]
    return tuple(out)  # type: ignore[return-value]


def _axpy(y: tuple, h: Any, k: tuple) -> tuple:
    """y + h k on nested tuples of entries (a state and its slope)."""
    return tuple(_axpy(a, h, b) if isinstance(a, tuple) else a + h * b
                 for a, b in zip(y, k, strict=True))


def _zeros(y: tuple) -> tuple:
    """0 · y on nested tuples of entries (zeros that vary like y)."""
    return tuple(_zeros(a) if isinstance(a, tuple) else 0 * a for a in y)


def _vec(x: jax.Array) -> Vec:
    return (x[0], x[1], x[2])


def _array(v: tuple) -> jax.Array:
    return jnp.stack(v)


def _solve3(a: jax.Array, b: jax.Array) -> jax.Array:
    """a⁻¹ b for one 3×3 matrix by cofactors (Cramer), no LAPACK call."""
    c0 = jnp.cross(a[1], a[2])
    c1 = jnp.cross(a[2], a[0])
    c2 = jnp.cross(a[0], a[1])
    det = jnp.dot(a[0], c0)
    det = jnp.where(jnp.abs(det) > 0, det, jnp.finfo(a.dtype).tiny)
    return (c0 * b[0] + c1 * b[1] + c2 * b[2]) / det


# ---------------------------------------------------------------- the rod equations

def _strains(ops: Ops, lay: _Layout, n_body: Vec, m_body: Vec, tension: list[Any],
             iterations: int, stiffness: Any = 1.0) -> tuple[Vec, Vec, list[Any]]:
    """Strains (u, v) from the cut's force and moment in the disk frame, and the tendons'
    stretch factors |v + u × r_i|.

    Solves ``Kse (v − e3) + Σ c_i w_i = n``, ``Kbt u + Σ c_i r_i × w_i = m`` with
    ``w_i = v + u × r_i`` and ``c_i = τ_i / |w_i|`` (τ_i zero for tendons not in this
    segment). The first pass takes every tendon parallel to the backbone (t_i = e3, exact
    for a bend without torsion or shear). Each further sweep fixes c_i at the current
    strains and solves the then linear equations: u from a 2×2 + 1×1 system (r_i lies in
    the disk plane), v from a diagonal one. ``stiffness`` scales Kse and Kbt (the
    segment's factor; a Python 1.0 leaves the program as it was).
    """
    (gax, gay, eaz), (ei, _, gj) = lay.kse, lay.kbt
    if not (isinstance(stiffness, float) and stiffness == 1.0):
        gax, gay, eaz, ei, gj = (k * stiffness for k in (gax, gay, eaz, ei, gj))
    rs = [(float(x), float(y)) for x, y, _ in lay.routing]
    # r_i × (τ_i e3) = τ_i (r_y, −r_x, 0)
    u = ((m_body[0] - sum(t * ry for t, (_, ry) in zip(tension, rs, strict=True))) / ei,
         (m_body[1] + sum(t * rx for t, (rx, _) in zip(tension, rs, strict=True))) / ei,
         m_body[2] / gj)
    total = sum(tension)
    v = (n_body[0] / gax, n_body[1] / gay, 1.0 + (n_body[2] - total) / eaz)

    def stretches(u: Vec, v: Vec) -> list[Any]:
        # w_i = v + u × r_i with r_i = (rx, ry, 0)
        return [ops.sqrt((v[0] - u[2] * ry) ** 2 + (v[1] + u[2] * rx) ** 2
                         + (v[2] + u[0] * ry - u[1] * rx) ** 2) for rx, ry in rs]

    for _ in range(iterations):
        c = [t / s for t, s in zip(tension, stretches(u, v), strict=True)]
        sxx = sum(ci * ry * ry for ci, (_, ry) in zip(c, rs, strict=True))
        syy = sum(ci * rx * rx for ci, (rx, _) in zip(c, rs, strict=True))
        sxy = sum(ci * rx * ry for ci, (rx, ry) in zip(c, rs, strict=True))
        csum = sum(c)
        crx = sum(ci * rx for ci, (rx, _) in zip(c, rs, strict=True))
        cry = sum(ci * ry for ci, (_, ry) in zip(c, rs, strict=True))
        # b = m − Σ c_i r_i × v,  r × v = (ry vz, −rx vz, rx vy − ry vx)
        b0 = m_body[0] - cry * v[2]
        b1 = m_body[1] + crx * v[2]
        b2 = m_body[2] - (crx * v[1] - cry * v[0])
        axx, ayy = ei + sxx, ei + syy
        det = axx * ayy - sxy * sxy
        u = ((ayy * b0 + sxy * b1) / det, (sxy * b0 + axx * b1) / det, b2 / (gj + sxx + syy))
        # Σ c_i u × r_i = (−uz Σc ry, uz Σc rx, ux Σc ry − uy Σc rx)
        v = ((n_body[0] + u[2] * cry) / (gax + csum),
             (n_body[1] - u[2] * crx) / (gay + csum),
             (eaz + n_body[2] - (u[0] * cry - u[1] * crx)) / (eaz + csum))
    return u, v, stretches(u, v)


def _derivative(ops: Ops, lay: _Layout, config: StaticsConfig, rotation: Rot, moment: Vec,
                force: Vec, tension: list[Any], stiffness: Any = 1.0) -> tuple:
    """d/ds of (p, R, M, tendon lengths) at one point; N (``force``) is given."""
    u, v, stretch = _strains(ops, lay, _rmatvec(rotation, force),
                             _rmatvec(rotation, moment), tension,
                             config.constitutive_iterations, stiffness)
    dp = _matvec(rotation, v)
    dm = _cross(dp, force)
    return dp, _rot_times_hat(rotation, u), (-dm[0], -dm[1], -dm[2]), tuple(stretch)


def rk4_step(ops: Ops, lay: _Layout, config: StaticsConfig, state: State, h: Any,
             mass: Any, length: Any, act: Any, tension: list[Any], force: Vec, gravity: Vec,
             distributed: Vec | None, moment_jump: Vec | None, stages: Any,
             stiffness: Any = 1.0) -> State:
    """One RK4 step of the rod over a step of length ``h`` (m) from ``state``.

    ``mass`` and ``length``: the kg and m of backbone distal of the step's start, middle
    and end (indexable by 0, 1, 2); ``act``: 1 per tendon running through the step;
    ``force``: the cut's force from the tip and point loads distal of the step (N);
    ``gravity`` (m/s²) and ``distributed`` (N/m, None: none) add theirs per stage point;
    ``moment_jump`` (N·m, None: none): a point moment at the step's end. ``stages`` runs
    ``body(inner, (shift, weight, point))`` over ``RK4_STAGES`` and returns the last inner
    value: a ``lax.scan`` on JAX (a small program), a Python loop on CasADi.
    ``stiffness``: the factor on the section's stiffnesses over this step (its segment's).
    """
    active = [t * act[i] for i, t in enumerate(tension)]

    def stage(inner: tuple, c: tuple) -> tuple:
        previous, total = inner
        shift, weight, point = c
        _, rot, mom, _ = _axpy(state, shift * h, previous)
        n = tuple(f + g * mass[point] for f, g in zip(force, gravity, strict=True))
        if distributed is not None:  # the force per metre distal of the stage's point
            n = tuple(a + w * length[point] for a, w in zip(n, distributed, strict=True))
        dp, drot, dmom, dl = _derivative(ops, lay, config, rot, mom, n, active, stiffness)
        k = (dp, drot, dmom, tuple(s * act[i] for i, s in enumerate(dl)))
        return k, _axpy(total, weight, k)

    zeros = _zeros(state)  # varying like the state (see _integrate)
    _, slope = stages(stage, (zeros, zeros))
    new = _axpy(state, h, slope)
    if moment_jump is not None:  # a point moment: M just distal of its point is smaller by it
        new = (new[0], new[1], tuple(m - j for m, j in zip(new[2], moment_jump, strict=True)),
               new[3])
    return new


def _integrate(lay: _Layout, config: StaticsConfig, base_moment: jax.Array,
               tension: jax.Array, loads: CaseLoads, keep_path: bool,
               stiffness: Any = None) -> tuple:
    """RK4 from the base (disk frame = base frame) with M(0) = ``base_moment``;
    ``stiffness`` (n,): the segments' stiffness factors (traced values allowed), None: the
    mechanics block's.

    Returns (M at the tip (3,), tendon lengths (T,), then with ``keep_path`` the positions
    (S+1, 3), rotations (S+1, 3, 3) and moments M (S+1, 3) at the robot's grid points, else
    the tip's position (3,) and rotation (3, 3)). The tip moment is not subtracted.
    """
    dtype = base_moment.dtype
    n_tendons = lay.active.shape[1]
    grid = _grid(lay, loads, dtype)
    points = grid.point_force is not None
    spread = loads.distributed.shape[0] > 0
    xs = tuple(jnp.asarray(a, dtype) for a in (grid.step_length, grid.mass, grid.length,
                                                 grid.active))
    if stiffness is None and np.any(lay.stiffness != 1.0):
        stiffness = lay.stiffness
    if stiffness is not None:
        xs += (step_stiffness(lay, jnp.asarray(grid.step_length, dtype),
                              jnp.asarray(stiffness, dtype), jnp),)
    if points:
        xs += (grid.point_force, grid.moment_jump)
    # Start values made from the inputs (not fresh constants): when the batch is split over
    # devices (shard_map) a loop carry must vary over the devices like the values it takes.
    zero = 0 * (base_moment[0] + tension.sum() + loads.force[0] + loads.gravity[0])
    one = zero + 1
    p0 = (zero, zero, zero)
    r0 = (one, zero, zero, zero, one, zero, zero, zero, one)
    l0 = tuple(zero for _ in range(n_tendons))
    tension_list = [tension[i] for i in range(n_tendons)]

    stage_table = tuple(jnp.asarray([c[k] for c in RK4_STAGES], dtype if k < 2 else None)
                        for k in range(3))

    def stages(body: Any, init: tuple) -> tuple:
        return jax.lax.scan(lambda inner, c: (body(inner, c), None), init, stage_table)[0]

    gravity = _vec(loads.gravity)
    distributed = _vec(loads.distributed) if spread else None

    scaled = stiffness is not None

    def step(carry: tuple, x: tuple) -> tuple:
        h, mass, length, act = x[:4]
        factor = x[4] if scaled else 1.0
        x = x[5:] if scaled else x[4:]
        force = _vec(loads.force + x[0] if points else loads.force)
        new = rk4_step(JAX, lay, config, carry, h, mass, length, act, tension_list, force,
                       gravity, distributed, _vec(x[1]) if points else None, stages,
                       factor)
        return new, ((_array(new[0]), _array(new[1]).reshape(3, 3), _array(new[2]))
                     if keep_path else None)

    (tip, frame, mom, ell), path = jax.lax.scan(step, (p0, r0, _vec(base_moment), l0), xs)
    mom, ell = _array(mom), _array(ell) if n_tendons else jnp.zeros(0, dtype)
    if not keep_path:
        return mom, ell, _array(tip), _array(frame).reshape(3, 3)
    positions = jnp.concatenate([jnp.zeros((1, 3), dtype), path[0]], axis=0)
    rotations = jnp.concatenate([jnp.eye(3, dtype=dtype)[None], path[1]], axis=0)
    moments = jnp.concatenate([base_moment[None], path[2]], axis=0)
    if grid.robot_points is not None:
        positions, rotations, moments = (a[grid.robot_points]
                                         for a in (positions, rotations, moments))
    return mom, ell, positions, rotations, moments
