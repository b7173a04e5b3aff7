"""Cosserat-rod statics of a tendon-driven robot, batched in JAX.

The model is Rucker & Webster's (IEEE T-RO 2011): an elastic backbone with strains
v (shear, extension) and u (bending, torsion), ``n = R Kse (v − e3)``,
``m = R Kbt u``, and each tendon a frictionless string routed parallel to the backbone
at ``r_i`` in the disks' frame, pulling with tension τ_i ≥ 0 and ending at the end of its
segment (per-segment routing) or at the tip (shared routing).

How it is solved. Cut the robot at arc length s and take everything distal of the cut,
tendons included: the force and moment that cross the cut are
``N = n + Σ τ_i t_i`` and ``M = m + Σ (R r_i) × τ_i t_i`` (t_i the tendon's unit tangent).
The tendons' distributed loads and their end loads are internal to that free body, so
N and M obey the plain rod equations with the external loads only:
``N' = −f_ext`` and ``M' = −p' × N``. With a tip force F, a tip moment M_tip and gravity g
(backbone mass per metre, disk masses) this gives N(s) = F + g·m_distal(s) in closed
form; the only unknown is M(0) (3 numbers), found by shooting on ``M(L) = M_tip`` with
Newton's method and continuation in the loads (``_shooting``). Without a tip force and
gravity N ≡ 0, so M is constant and M(0) = M_tip: the batched solve integrates those cases
once, with no iteration. At each integration point the strains come from N and M by
inverting the constitutive law with the tendons (``_strains``): a small fixed-point
iteration on the tendons' stretch factors |v + u × r_i|, each step a closed-form 2×2 +
1×1 + diagonal solve.

The solution M(0) is differentiated implicitly (``jax.lax.custom_root``): derivatives of
the shape with respect to tensions and loads cost one 3×3 solve, not the unrolled
iterations. Units: metres, radians, newtons, N·m, kg, m/s².
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._programs import CachedProgram
from ..runtime import cached, configure
from .kinematics import tendon_angles
from .robot import Robot
from .rotations import matrix_from_wxyz, wxyz_from_matrix


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
    """Most Newton iterations of the shooting (each: one pass with its Jacobian)."""
    tolerance: float | None = None
    """Converged when |M(L) − M_tip| · L / (E I) ≤ tolerance, i.e. the boundary residual as
    the bending angle (radians) it would cause over the robot. None: 1e-10 in float64,
    1e-5 in float32."""
    dtype: str = "float64"
    """"float64" (default) or "float32" (a speed setting for large batches)."""

    def resolved_tolerance(self) -> float:
        """The tolerance in radians of bending with the dtype's default filled in."""
        if self.tolerance is not None:
            return float(self.tolerance)
        return 1e-10 if self.dtype == "float64" else 1e-5


@dataclass(frozen=True)
class StaticsResult:
    """Equilibrium shapes of a batch of load cases (world frame, float64 numpy)."""

    positions: np.ndarray
    """(B, P, 3) backbone points from the base to the tip at every integration step, m."""
    rotations: np.ndarray
    """(B, P, 3, 3) backbone frames at the same points (columns: the disk's x, y, z axes)."""
    arc_length: np.ndarray
    """(P,) arc length of each point from the base, m."""
    tendon_displacements: np.ndarray
    """(B, n_tendons) how far each tendon is pulled (its straight length minus its length
    along the bent robot; positive = pulled), m."""
    converged: np.ndarray
    """(B,) True where the shooting met its tolerance."""
    residual: np.ndarray
    """(B,) boundary residual |M(L) − M_tip|, N·m."""
    iterations: np.ndarray
    """(B,) shooting iterations used."""
    base_moment: np.ndarray
    """(B, 3) moment at the base (rod and tendons together), N·m, world frame."""
    base_force: np.ndarray
    """(B, 3) force at the base (rod and tendons together), N, world frame."""

    @property
    def tip_position(self) -> np.ndarray:
        """(B, 3) tip position, m."""
        return self.positions[:, -1]

    @property
    def tip_rotation(self) -> np.ndarray:
        """(B, 3, 3) tip orientation."""
        return self.rotations[:, -1]

    @property
    def tip_wxyz(self) -> np.ndarray:
        """(B, 4) tip orientation as a unit quaternion (w, x, y, z)."""
        return np.array([wxyz_from_matrix(r) for r in self.tip_rotation]).reshape(-1, 4)


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


@cached(maxsize=64)
def _layout(robot: Robot, config: StaticsConfig, coarse: bool = False) -> _Layout:
    """The integration grid. ``coarse``: half the steps, placed regardless of the disks
    (whose masses then fall inside steps): the grid of the shooting's Jacobian passes."""
    mech = robot.mechanics
    if mech is None:
        raise ValueError(f"{robot.name}: the robot file has no 'mechanics' block; the "
                         "Cosserat statics need one (see models/README.md)")
    if any(s.extendable for s in robot.segments):
        raise ValueError(f"{robot.name}: the Cosserat statics need fixed segment lengths")
    angles = tendon_angles(robot)
    if robot.tendons.routing == "shared":
        if not np.allclose(angles, angles[0]):
            raise ValueError(f"{robot.name}: shared routing with different offsets per "
                             "segment is not a straight routing")
        angles = angles[:1]
    alpha = angles.reshape(-1)
    routing = robot.tendons.radius * np.stack(
        [np.cos(alpha), np.sin(alpha), np.zeros_like(alpha)], axis=-1)

    m = robot.tendons.per_segment
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
            if robot.tendons.routing == "shared":
                active.append(np.ones(m))
            else:
                active.append((np.arange(robot.n_tendons) // m >= i).astype(float))
    h = np.asarray(lengths)
    arc = np.concatenate([[0.0], np.cumsum(h)])
    total = arc[-1]
    disk_s = np.asarray(disk_s)

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
                   mech.bending_stiffness / total)


# ---------------------------------------------------------------- small vector helpers
# The rod equations are written on tuples of scalars (x, y, z; a rotation's nine entries):
# under vmap every entry is one (B,) array and XLA fuses the whole right-hand side into a
# few loops over the batch, instead of many small (B, 3, 3) products.

Vec = tuple[Any, Any, Any]
Rot = tuple[Any, Any, Any, Any, Any, Any, Any, Any, Any]


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

def _strains(lay: _Layout, n_body: Vec, m_body: Vec, tension: list[Any],
             iterations: int) -> tuple[Vec, Vec, list[Any]]:
    """Strains (u, v) from the cut's force and moment in the disk frame, and the tendons'
    stretch factors |v + u × r_i|.

    Solves ``Kse (v − e3) + Σ c_i w_i = n``, ``Kbt u + Σ c_i r_i × w_i = m`` with
    ``w_i = v + u × r_i`` and ``c_i = τ_i / |w_i|`` (τ_i zero for tendons not in this
    segment). The first pass takes every tendon parallel to the backbone (t_i = e3, exact
    for a bend without torsion or shear). Each further sweep fixes c_i at the current
    strains and solves the then linear equations: u from a 2×2 + 1×1 system (r_i lies in
    the disk plane), v from a diagonal one.
    """
    (gax, gay, eaz), (ei, _, gj) = lay.kse, lay.kbt
    rs = [(float(x), float(y)) for x, y, _ in lay.routing]
    # r_i × (τ_i e3) = τ_i (r_y, −r_x, 0)
    u = ((m_body[0] - sum(t * ry for t, (_, ry) in zip(tension, rs, strict=True))) / ei,
         (m_body[1] + sum(t * rx for t, (rx, _) in zip(tension, rs, strict=True))) / ei,
         m_body[2] / gj)
    total = sum(tension)
    v = (n_body[0] / gax, n_body[1] / gay, 1.0 + (n_body[2] - total) / eaz)

    def stretches(u: Vec, v: Vec) -> list[Any]:
        # w_i = v + u × r_i with r_i = (rx, ry, 0)
        return [jnp.sqrt((v[0] - u[2] * ry) ** 2 + (v[1] + u[2] * rx) ** 2
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


def _derivative(lay: _Layout, config: StaticsConfig, rotation: Rot, moment: Vec,
                force: Vec, tension: list[Any]) -> tuple:
    """d/ds of (p, R, M, tendon lengths) at one point; N (``force``) is given."""
    u, v, stretch = _strains(lay, _rmatvec(rotation, force), _rmatvec(rotation, moment),
                             tension, config.constitutive_iterations)
    dp = _matvec(rotation, v)
    dm = _cross(dp, force)
    return dp, _rot_times_hat(rotation, u), (-dm[0], -dm[1], -dm[2]), tuple(stretch)


def _integrate(lay: _Layout, config: StaticsConfig, base_moment: jax.Array,
               tension: jax.Array, tip_force: jax.Array, gravity: jax.Array,
               keep_path: bool) -> tuple:
    """RK4 from the base (disk frame = base frame) with M(0) = ``base_moment``.

    Returns (M at the tip (3,), tendon lengths (T,), then with ``keep_path`` the positions
    (S+1, 3) and rotations (S+1, 3, 3) along the arc, else the tip's position (3,) and
    rotation (3, 3)).
    """
    dtype = base_moment.dtype
    n_tendons = lay.active.shape[1]
    xs = (jnp.asarray(lay.step_length, dtype), jnp.asarray(lay.mass_distal, dtype),
          jnp.asarray(lay.active, dtype))
    # Start values made from the inputs (not fresh constants): when the batch is split over
    # devices (shard_map) a loop carry must vary over the devices like the values it takes.
    zero = 0 * (base_moment[0] + tension.sum() + tip_force[0] + gravity[0])
    one = zero + 1
    p0 = (zero, zero, zero)
    r0 = (one, zero, zero, zero, one, zero, zero, zero, one)
    l0 = tuple(zero for _ in range(n_tendons))
    tension_list = [tension[i] for i in range(n_tendons)]
    fvec, gvec = _vec(tip_force), _vec(gravity)

    def axpy(y: Any, h: Any, k: Any) -> Any:
        return jax.tree_util.tree_map(lambda a, b: a + h * b, y, k)

    stage_shift = jnp.asarray([0.0, 0.5, 0.5, 1.0], dtype)
    stage_weight = jnp.asarray([1.0, 2.0, 2.0, 1.0], dtype) / 6.0
    stage_point = jnp.asarray([0, 1, 1, 2])

    def step(carry: tuple, x: tuple) -> tuple:
        h, mass, act = x
        active = [t * act[i] for i, t in enumerate(tension_list)]

        def stage(inner: tuple, c: tuple) -> tuple:
            previous, total = inner
            shift, weight, point = c
            _, rot, mom, _ = axpy(carry, shift * h, previous)
            force = tuple(f + g * mass[point] for f, g in zip(fvec, gvec, strict=True))
            dp, drot, dmom, dl = _derivative(lay, config, rot, mom, force, active)
            k = (dp, drot, dmom, tuple(s * act[i] for i, s in enumerate(dl)))
            return (k, axpy(total, weight, k)), None

        zeros = jax.tree_util.tree_map(lambda a: 0 * a, carry)  # varying, as above
        (_, slope), _ = jax.lax.scan(stage, (zeros, zeros),
                                     (stage_shift, stage_weight, stage_point))
        new = axpy(carry, h, slope)
        return new, ((_array(new[0]), _array(new[1]).reshape(3, 3)) if keep_path else None)

    (tip, frame, mom, ell), path = jax.lax.scan(step, (p0, r0, _vec(base_moment), l0), xs)
    mom, ell = _array(mom), _array(ell) if n_tendons else jnp.zeros(0, dtype)
    if not keep_path:
        return mom, ell, _array(tip), _array(frame).reshape(3, 3)
    positions = jnp.concatenate([jnp.zeros((1, 3), dtype), path[0]], axis=0)
    rotations = jnp.concatenate([jnp.eye(3, dtype=dtype)[None], path[1]], axis=0)
    return mom, ell, positions, rotations


class _Newton(NamedTuple):
    """The shooting iteration's state for one case (see ``_shoot``)."""

    x: jax.Array        # (3,) M(0), N·m
    lam: jax.Array      # load factor reached
    target: jax.Array   # load factor being tried
    r: jax.Array        # (3,) residual at (x, lam)
    j: jax.Array        # (3, 3) ∂r/∂M(0)
    g: jax.Array        # (3,) ∂r/∂λ
    step: jax.Array     # Newton step length
    it: jax.Array       # iterations used


def _shooting(lay: _Layout, coarse: _Layout, config: StaticsConfig, tension: jax.Array,
              tip_force: jax.Array, tip_moment: jax.Array,
              gravity: jax.Array) -> tuple[Any, Any, Any]:
    """(start, iterate, done) of the shooting on M(0) for one case.

    Newton with continuation in the external loads: with the loads scaled by λ = 0 the
    answer is M(0) = 0 exactly (tendons alone); each iteration tries the next λ with a
    predictor step from the current Jacobian, keeps it when Newton at least halved the
    residual it set out to remove (the old one plus the load increment), doubles the
    increment then and quarters it otherwise. A case without loads starts at λ = 1.

    The Jacobian (∂r/∂M(0), ∂r/∂λ) is taken by forward differences: five passes in one
    vectorised evaluation, on the ``coarse`` grid with one strain sweep (a third of a
    full pass each). XLA's forward-mode derivative of the strain sweeps costs about twenty
    primal passes per direction on the CPU. Newton only needs an approximate Jacobian
    (the residual itself is the full pass), and derivatives of the converged answer are
    implicit and exact (``_shoot``).
    """
    dtype = tension.dtype
    tol = config.resolved_tolerance() * lay.moment_scale
    root_eps = float(np.sqrt(np.finfo(np.dtype(dtype)).eps))

    rough = dataclasses.replace(config, constitutive_iterations=1)

    def scaled_residual(base_moment: jax.Array, lam: jax.Array, grid: _Layout = lay,
                        settings: StaticsConfig = config) -> jax.Array:
        mom, _, _, _ = _integrate(grid, settings, base_moment, tension, lam * tip_force,
                                  lam * gravity, False)
        return mom - lam * tip_moment

    def linearized(x: jax.Array, lam: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        hx = root_eps * jnp.maximum(jnp.max(jnp.abs(x)), lay.moment_scale)
        xs = jnp.concatenate([x[None], x[None] + hx * jnp.eye(3, dtype=dtype), x[None]])
        lams = jnp.concatenate([jnp.broadcast_to(lam, (4,)), (lam + root_eps)[None]])
        rs = jax.vmap(lambda a, b: scaled_residual(a, b, coarse, rough))(xs, lams)
        return scaled_residual(x, lam), (rs[1:4] - rs[0]).T / hx, (rs[4] - rs[0]) / root_eps

    def start(x0: jax.Array) -> _Newton:
        unloaded = (jnp.all(tip_force == 0) & jnp.all(tip_moment == 0)
                    & jnp.all(gravity == 0))
        lam0 = jnp.where(unloaded, 1.0, 0.0).astype(dtype) + 0 * x0[0]
        r0, j0, g0 = linearized(x0, lam0)
        one = 1 + 0 * x0[0]  # varies like x0 (see _integrate)
        return _Newton(x0, lam0, one, r0, j0, g0, one, jnp.asarray(0))

    def done(state: _Newton) -> jax.Array:
        return (state.lam >= 1.0) & (jnp.linalg.norm(state.r) <= tol)

    def iterate(state: _Newton) -> _Newton:
        x, lam, target, r, j, g, step, it = state
        x_new = x - step * _solve3(j, r + (target - lam) * g)
        r_new, j_new, g_new = linearized(x_new, target)
        size, size_new = jnp.linalg.norm(r), jnp.linalg.norm(r_new)
        continuing = target > lam
        # The residual the step set out to remove: the old one plus the load increment.
        predicted = jnp.linalg.norm(r + (target - lam) * g)
        # A step that lands within the tolerance is always taken.
        ok = jnp.isfinite(size_new) & ((size_new <= tol)
                                       | (size_new < jnp.maximum(size, 0.5 * predicted)))
        x, r, j, g = (jnp.where(ok, a, b) for a, b in
                      ((x_new, x), (r_new, r), (j_new, j), (g_new, g)))
        reached = jnp.where(ok, target, lam)
        # After a success try twice the increment; after a failure a quarter of it.
        increment = jnp.where(ok, 2.0 * (target - lam), 0.25 * (target - lam))
        step = jnp.where(ok | continuing, 1.0, 0.25 * step)
        return _Newton(x, reached, jnp.minimum(1.0, reached + increment), r, j, g, step,
                       it + 1)

    return start, iterate, done


def _run(iterate: Any, done: Any, state: _Newton, iterations: int) -> _Newton:
    """At most ``iterations`` more Newton iterations from ``state`` (fewer once done)."""
    limit = state.it + iterations
    return jax.lax.while_loop(lambda s: ~done(s) & (s.it < limit), iterate, state)


def _shoot(lay: _Layout, coarse: _Layout, config: StaticsConfig, tension: jax.Array,
           tip_force: jax.Array, tip_moment: jax.Array,
           gravity: jax.Array) -> tuple[jax.Array, tuple]:
    """M(0) with M(L) = M_tip, differentiable implicitly; and (iterations, λ reached)."""
    start, iterate, done = _shooting(lay, coarse, config, tension, tip_force, tip_moment,
                                     gravity)

    def residual(base_moment: jax.Array) -> jax.Array:
        mom, _, _, _ = _integrate(lay, config, base_moment, tension, tip_force, gravity,
                                  False)
        return mom - tip_moment

    def solve(f: Any, x0: jax.Array) -> tuple[jax.Array, tuple]:
        del f  # the same residual, reached through its load-scaled family
        state = _run(iterate, done, start(x0), config.max_iterations)
        # aux as floats: custom_root's JVP rule gives aux tangents of the solution's dtype
        return state.x, (state.it.astype(x0.dtype), state.lam)

    def tangent_solve(g: Any, y: jax.Array) -> jax.Array:
        return _solve3(jax.jacfwd(g)(y), y)

    guess = jnp.zeros(3, tension.dtype)
    return jax.lax.custom_root(residual, guess, solve, tangent_solve, has_aux=True)


def tip_equilibrium(robot: Robot, config: StaticsConfig = StaticsConfig()) -> Any:
    """The per-case JAX function ``f(tension, base_moment, tip_force, tip_moment, gravity)
    -> (tip position (3,), tip rotation (3, 3), equilibrium residual (3,))`` of one
    integration pass from a given moment at the base M(0) (N·m), base frame.

    The residual ``M(L) − M_tip`` (N·m) is zero at an equilibrium: a solver may take M(0)
    as an unknown beside the tensions (tension-space IK does) instead of shooting for it
    at every step.
    """
    lay = _layout(robot, config)

    def tip(tension: jax.Array, base_moment: jax.Array, tip_force: jax.Array,
            tip_moment: jax.Array, gravity: jax.Array) -> tuple[jax.Array, ...]:
        mom, _, position, rotation = _integrate(lay, config, base_moment, tension,
                                                tip_force, gravity, False)
        return position, rotation, mom - tip_moment

    return tip


def moment_scale(robot: Robot) -> float:
    """E·I / L (N·m per radian of bending over the robot): the size of a moment."""
    return _layout(robot, StaticsConfig()).moment_scale


def _finish(lay: _Layout, config: StaticsConfig, base_moment: jax.Array,
            tension: jax.Array, tip_force: jax.Array, tip_moment: jax.Array,
            gravity: jax.Array) -> dict[str, jax.Array]:
    """The shape and its checks for one case from its M(0): one integration pass."""
    mom, ell, positions, rotations = _integrate(lay, config, base_moment, tension,
                                                tip_force, gravity, True)
    straight = jnp.asarray(lay.active.T @ lay.step_length, ell.dtype)
    residual = jnp.linalg.norm(mom - tip_moment)
    tol = config.resolved_tolerance() * lay.moment_scale
    return {
        "positions": positions, "rotations": rotations,
        "tendon_displacements": straight - ell, "residual": residual,
        # A last check on the final pass itself (the loop's own flag is a twin).
        "converged": jnp.isfinite(residual) & (residual <= 10.0 * tol),
        "base_moment": base_moment,
        "base_force": tip_force + gravity * float(lay.total_mass_moment[0]),
    }


def statics_single(robot: Robot, config: StaticsConfig = StaticsConfig()) -> Any:
    """The per-case JAX function ``f(tension, tip_force, tip_moment, gravity) -> dict``.

    Inputs in the base frame (N, N, N·m, m/s²); the dict holds ``positions`` (P, 3),
    ``rotations`` (P, 3, 3) in the base frame, ``tendon_displacements`` (T,), ``residual``
    (N·m), ``iterations``, ``converged`` and ``base_moment``. Differentiable (forward and
    reverse) with respect to all four inputs through the implicit solution.
    """
    lay, coarse = _layout(robot, config), _layout(robot, config, coarse=True)

    def solve_case(tension: jax.Array, tip_force: jax.Array, tip_moment: jax.Array,
                   gravity: jax.Array) -> dict[str, jax.Array]:
        base_moment, (iterations, load_reached) = _shoot(lay, coarse, config, tension,
                                                         tip_force,
                                                         tip_moment, gravity)
        out = _finish(lay, config, base_moment, tension, tip_force, tip_moment, gravity)
        out["iterations"] = jax.lax.stop_gradient(iterations).astype(jnp.int32)
        out["load_reached"] = load_reached
        return out

    return solve_case


# Newton iterations every case of a batch gets; the few cases that need more continue in
# a smaller batch, so that they do not hold the whole batch in the loop.
_FIRST_ROUND = 10


@cached(maxsize=64)
def _programs(robot: Robot, config: StaticsConfig) -> tuple[Any, Any, Any]:
    """(first round, further rounds, finish): jitted and vmapped over cases; jit keeps one
    compiled program per padded batch size."""
    lay, coarse = _layout(robot, config), _layout(robot, config, coarse=True)

    def first(tension: jax.Array, force: jax.Array, moment: jax.Array,
              gravity: jax.Array) -> _Newton:
        start, iterate, done = _shooting(lay, coarse, config, tension, force, moment, gravity)
        zero = 0 * tension[:1]  # varies over the devices like the state (see _integrate)
        return _run(iterate, done, start(jnp.broadcast_to(zero, (3,))),
                    min(_FIRST_ROUND, config.max_iterations))

    def further(tension: jax.Array, force: jax.Array, moment: jax.Array,
                gravity: jax.Array, state: _Newton) -> _Newton:
        _, iterate, done = _shooting(lay, coarse, config, tension, force, moment, gravity)
        return _run(iterate, done, state, max(0, config.max_iterations - _FIRST_ROUND))

    def finish(base_moment: jax.Array, tension: jax.Array, force: jax.Array,
               moment: jax.Array, gravity: jax.Array) -> dict[str, jax.Array]:
        return _finish(lay, config, base_moment, tension, force, moment, gravity)

    return (_split(jax.vmap(first), 4), _split(jax.vmap(further), 5),
            _split(jax.vmap(finish), 5))


def _split(fn: Any, arguments: int) -> Any:
    """``fn`` jitted, its batch split over the JAX devices (one per CPU core when the
    process asked for host devices) when the batch divides evenly, else on one."""
    programs: dict[int, Any] = {}

    def call(*args: Any) -> Any:
        size = args[0].shape[0]
        if size not in programs:
            programs[size] = CachedProgram(fn, name="the Cosserat shooting",
                                           batched=(True,) * arguments)
        return programs[size](*args)

    return call


def _padded(rows: np.ndarray, edge: bool = False) -> np.ndarray:
    """Rows padded to a power of two (at least 16; above 1024 a multiple of 1024) so that a
    few compiled programs serve every batch size: with zero rows (no load: done at once) or
    copies of the first row."""
    size = max(16, 1 << (len(rows) - 1).bit_length())
    if size > 1024:
        size = -(-len(rows) // 1024) * 1024
    fill = (np.repeat(rows[:1], size - len(rows), axis=0) if edge
            else np.zeros((size - len(rows), *rows.shape[1:]), rows.dtype))
    return np.concatenate([rows, fill])


def _base_moments(robot: Robot, config: StaticsConfig, cases: list[np.ndarray],
                  dtype: Any) -> tuple[np.ndarray, np.ndarray]:
    """M(0) (B, 3) and the Newton iterations (B,) of every case.

    Without a tip force and gravity the cut's force N is zero, so M is constant along the
    robot and M(0) = M_tip exactly (no iteration). The other cases are shot: every case
    gets ``_FIRST_ROUND`` iterations, then the unfinished ones continue in a smaller batch.
    """
    tension, force, moment, gravity = cases
    base = moment.copy()
    iterations = np.zeros(len(tension), dtype=int)
    shot = np.flatnonzero(np.any(force != 0, axis=1) | np.any(gravity != 0, axis=1))
    if shot.size == 0:
        return base, iterations
    first, further, _ = _programs(robot, config)
    rows = [v[shot] for v in cases]
    state = first(*(jnp.asarray(_padded(v), dtype) for v in rows))
    x, its = np.array(state.x)[:shot.size], np.array(state.it)[:shot.size]
    limit = min(_FIRST_ROUND, config.max_iterations)
    # Unfinished: the loop's own test (``done`` in ``_shooting``), read on the host.
    tol = config.resolved_tolerance() * _layout(robot, config).moment_scale
    finished = ((np.asarray(state.lam)[:shot.size] >= 1.0)
                & (np.linalg.norm(np.asarray(state.r)[:shot.size], axis=1) <= tol))
    left = np.flatnonzero(~finished & (its >= limit))
    if left.size and config.max_iterations > limit:
        # Padded with copies of the first unfinished case (zero rows would have no state).
        def pick(a: Any) -> jax.Array:
            return jnp.asarray(_padded(np.asarray(a)[left], edge=True))

        more = further(*(pick(v) for v in rows), jax.tree_util.tree_map(pick, state))
        x[left], its[left] = np.asarray(more.x)[:left.size], np.asarray(more.it)[:left.size]
    base[shot], iterations[shot] = x, its
    return base, iterations


def load_cases(value: Any, batch: int, size: int, name: str) -> np.ndarray:
    """A load input as (batch, size) float64: None → zeros, one row → broadcast to every
    case; a wrong shape or a non-finite entry is a ValueError naming ``name``."""
    if value is None:
        return np.zeros((batch, size))
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 1:
        arr = np.broadcast_to(arr, (batch, arr.shape[0]))
    if arr.shape != (batch, size):
        raise ValueError(f"{name}: expected {size} numbers or ({batch}, {size}), got shape "
                         f"{np.shape(value)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: non-finite entries")
    return np.array(arr)


def solve_statics(robot: Robot, tensions: Any, tip_force: Any = None, tip_moment: Any = None,
                  gravity: Any = None, config: StaticsConfig = StaticsConfig()) -> StaticsResult:
    """Equilibrium shapes for a batch of tendon tensions and loads (numpy in, numpy out).

    Args:
        robot: a robot with a ``mechanics`` block and fixed segment lengths.
        tensions: (n_tendons,) or (B, n_tendons) tendon tensions, newtons, ≥ 0, in the
            robot file's tendon order.
        tip_force: (3,) or (B, 3) force on the tip, N, world frame (default none).
        tip_moment: (3,) or (B, 3) moment on the tip, N·m, world frame (default none).
        gravity: (3,) or (B, 3) gravitational acceleration, m/s², world frame (default none).
        config: discretisation, tolerance and dtype.

    Returns:
        ``StaticsResult`` in the world frame; a case that did not converge is marked in
        ``converged`` (a value, not an exception).

    Raises:
        ValueError: wrong shapes, negative or non-finite tensions, a robot without mechanics.
    """
    configure()
    t = np.atleast_2d(np.asarray(tensions, dtype=float))
    if t.ndim != 2 or t.shape[1] != robot.n_tendons:
        raise ValueError(f"tensions: {robot.name} has {robot.n_tendons} tendons, got shape "
                         f"{np.shape(tensions)}")
    if not np.all(np.isfinite(t)) or np.any(t < 0):
        bad = np.argwhere(~np.isfinite(t) | (t < 0))[0]
        raise ValueError(f"tensions: case {bad[0]}, tendon {bad[1] + 1}: a tension must be a "
                         f"finite number ≥ 0 N, got {t[tuple(bad)]}")
    batch = t.shape[0]
    base_rot = matrix_from_wxyz(np.asarray(robot.base_wxyz))
    base_pos = np.asarray(robot.base_position)
    loads = [load_cases(v, batch, 3, n) @ base_rot for v, n in
             ((tip_force, "tip_force"), (tip_moment, "tip_moment"), (gravity, "gravity"))]
    if config.dtype not in ("float64", "float32"):
        raise ValueError(f"dtype: 'float64' or 'float32', got {config.dtype!r}")
    dtype = np.float64 if config.dtype == "float64" else np.float32
    # float64 without touching the process-wide flag (the batched stages keep theirs).
    with jax.enable_x64(config.dtype == "float64"):
        cases = [t, *loads]
        base, iterations = _base_moments(robot, config, cases, dtype)
        finish = _programs(robot, config)[2]
        out = finish(*(jnp.asarray(_padded(v), dtype) for v in (base, *cases)))
        out = {k: np.asarray(v)[:batch] for k, v in out.items()}
    positions = out["positions"].astype(float) @ base_rot.T + base_pos
    rotations = np.einsum("ij,bpjk->bpik", base_rot, out["rotations"].astype(float))
    return StaticsResult(
        positions=positions, rotations=rotations,
        arc_length=_layout(robot, config).arc_length,
        tendon_displacements=out["tendon_displacements"].astype(float),
        converged=out["converged"].astype(bool), residual=out["residual"].astype(float),
        iterations=iterations,
        base_moment=out["base_moment"].astype(float) @ base_rot.T,
        base_force=out["base_force"].astype(float) @ base_rot.T)
