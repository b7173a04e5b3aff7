"""Forward kinematics from motor commands: tendon displacements → shape → tip (PCC with slack).

Conventions (docs/design.md §1b): commanded displacement d (m) per tendon in the robot file's
order, positive = pulled, from the calibrated zero. A tendon pulls, never pushes.

The model. Tendon j's effective pull is ``p_j = g_j·(d_j − d0_j)`` (gain g, zero offset
d0: the command at which the tendon is just taut on the straight backbone). In bending
vectors u_i = θ_i(cos φ_i, sin φ_i), the path shortening of tendon j is ``r·(B u)_j`` with
``B[j, segment i] = (cos α_ij, sin α_ij)`` for each segment the tendon runs through
(docs/design.md §1: ``ℓ = L − r·θ·cos(α − φ)``). The tendon is stretched by ``s_j = p_j − r(B u)_j``
when that is positive and slack otherwise. The backbone takes the shape of least energy

    E(u) = ½ Σ_i c_i ‖u_i‖² + ½ Σ_j κ_j max(0, s_j / r)²,

with c_i = (EI_i / EI_1)·(L_total / L_i) the segments' bending stiffness and
κ_j = k_j r² L_total / EI_1 the tendon stiffness ratio (both dimensionless; κ is given
per group of tendons anchored at the same segment, since their lengths differ).

With axial compliance (the ``actuation`` block's ``axial_stiffness_ratio`` a_i), the taut
tendons also shorten the segments they run through: segment i is compressed by r·δ_i,
every tendon through it is shortened by as much, ``s_j = p_j − r(B u)_j − r Σ_i δ_ij``
(δ_ij = δ_i where tendon j runs through segment i), and E gains ½ Σ_i a_i δ_i². In
equilibrium a_i δ_i is the sum of the tensions through segment i, so a segment shortens in
proportion to the tendon load it carries (pretension included); the shape is the same
constant-curvature arc on the shorter length. Without the field, δ = 0 (today's model).
With ``axial_shortens_segments`` false the arcs keep their lengths and only the take-up
stays (the tendons still lose r·δ_i together): on the FTDCR v6 recording that fits as well
(docs/design.md §1b), and a plan's commands then reproduce its shape exactly.

E is convex and strictly so, so the shape is unique; the tension of tendon j is
∝ κ·max(0, s_j) ≥ 0: a slack tendon carries nothing, and releasing it further changes
nothing. The minimiser is found by Newton steps with a line search on E (a few
active-set changes), and differentiated at the solution (implicit function theorem,
``jax.lax.custom_root``).

The robot file's optional ``actuation`` block holds the calibrated parameters
(models/README.md); without it the nominal values below are used.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._cached_jit import cached_jit
from ._actuation_block import NOMINAL_AXIAL_STIFFNESS_RATIO as NOMINAL_AXIAL_STIFFNESS_RATIO
from ._actuation_block import NOMINAL_TENDON_STIFFNESS_RATIO as NOMINAL_TENDON_STIFFNESS_RATIO
from ._actuation_block import Actuation as Actuation
from ._actuation_block import parse_actuation as parse_actuation
from .kinematics import tip_pose_z
from .robot import Robot
from .routing import routing_of


def actuation_of(robot: Robot) -> Actuation:
    """The robot's calibrated actuation, or the nominal one when its file has none."""
    act = getattr(robot, "actuation", None)
    return act if act is not None else Actuation.nominal(robot.n_tendons, robot.n_segments)


# ================================================================ parameters as a pytree

def tendon_segments(robot: Robot) -> np.ndarray:
    """(n_tendons, n_segments) 0/1: which segments each tendon runs through."""
    return routing_of(robot).through.astype(float)


def _nominal_angles(robot: Robot) -> np.ndarray:
    """(n_tendons, n_segments) nominal angle α of each tendon in each segment, without
    the per-segment offsets (those are parameters), rad."""
    return routing_of(robot).angles(np.zeros(robot.n_segments))


def _offset_owner(robot: Robot) -> np.ndarray:
    """(n_tendons, n_segments) index of the segment whose offset applies to tendon j in
    segment i (``model.routing``)."""
    return routing_of(robot).owner


def _groups(robot: Robot) -> np.ndarray:
    """(n_tendons,) the segment each tendon is anchored at (its stiffness group)."""
    return routing_of(robot).anchor


def params_of(robot: Robot) -> dict[str, np.ndarray]:
    """The robot's model parameters as a dict of float64 arrays (the calibration's
    unknowns and the forward model's inputs): lengths (n) m, radius m, segment_offsets
    (n) rad, angle_deltas, zero_offsets (m), gains, log_stiffness (n), log_kappa,
    marker (3) m, base_position (3) m, base_rotation (3×3); and log_axial (n), the log of
    the axial stiffness ratio, only where the robot's segments are compressible."""

    act = actuation_of(robot)
    axial = (
        {"log_axial": np.log(np.array(act.axial_stiffness_ratio, float))}
        if act.axial_stiffness_ratio else {})
    return axial | {
        "lengths": np.array([s.length_min for s in robot.segments], float),
        "radius": np.array(robot.tendons.radius, float),
        "segment_offsets": np.array(robot.tendons.offsets, float),
        "angle_deltas": np.array(act.tendon_angle_deltas, float),
        "zero_offsets": np.array(act.zero_offsets, float),
        "gains": np.array(act.gains, float),
        "log_stiffness": np.log(np.array(act.segment_stiffness, float)),
        "log_kappa": np.log(np.array(act.tendon_stiffness_ratio or
                                     (NOMINAL_TENDON_STIFFNESS_RATIO,) * robot.n_segments,
                                     float)),
        "marker": np.array(act.tip_marker, float),
        "base_position": np.array(robot.base_position, float),
        "base_rotation": np.array(robot.base_rotation),
    }


def robot_with_params(robot: Robot, params: dict[str, Any],
                      model_error: tuple[float | None, float | None] = (None, None)) -> Robot:
    """A copy of ``robot`` carrying ``params`` (as from ``params_of``) in its geometry, base
    and ``actuation`` block; ``model_error`` = (mean, p95) in m to record with it."""
    from .robot import Tendons
    from .rotations import wxyz_from_matrix

    p = {k: np.asarray(v, float) for k, v in params.items()}
    segments = tuple(replace(s, length_min=float(L), length_max=float(L))
                     if not s.extendable else s
                     for s, L in zip(robot.segments, p["lengths"], strict=True))
    tendons = Tendons(robot.tendons.per_segment, float(p["radius"]),
                      tuple(float(v) for v in p["segment_offsets"]), robot.tendons.routing)
    stiffness = np.exp(p["log_stiffness"] - p["log_stiffness"][0])
    act = Actuation(
        zero_offsets=tuple(float(v) for v in p["zero_offsets"]),
        gains=tuple(float(v) for v in p["gains"]),
        tendon_angle_deltas=tuple(float(v) for v in p["angle_deltas"]),
        segment_stiffness=tuple(float(v) for v in stiffness),
        tendon_stiffness_ratio=tuple(float(v) for v in
                                     np.exp(p["log_kappa"] - p["log_stiffness"][0])),
        axial_stiffness_ratio=(
            tuple(float(v) for v in np.exp(p["log_axial"] - p["log_stiffness"][0]))
            if "log_axial" in p else ()),
        axial_shortens_segments=("log_axial" not in p
                                 or actuation_of(robot).axial_shortens_segments),
        tip_marker=tuple(float(v) for v in p["marker"]),  # type: ignore[arg-type]
        model_error_mean=model_error[0],
        model_error_p95=model_error[1],
    )
    wxyz = wxyz_from_matrix(p["base_rotation"])
    return replace(robot, segments=segments, tendons=tendons, actuation=act,
                   base_position=tuple(float(v) for v in p["base_position"]),
                   base_wxyz=tuple(float(v) for v in wxyz / np.linalg.norm(wxyz)))


# ================================================================ the equilibrium solve

@dataclass(frozen=True)
class _Topology:
    """The static part of the model: routing masks and nominal angles (hashable)."""

    runs_through: tuple[tuple[float, ...], ...]
    nominal_angles: tuple[tuple[float, ...], ...]
    offset_owner: tuple[tuple[int, ...], ...]
    group: tuple[int, ...]
    n_segments: int

    @classmethod
    def of(cls, robot: Robot) -> _Topology:
        as_tuple = lambda a: tuple(tuple(row) for row in a.tolist())  # noqa: E731
        return cls(as_tuple(tendon_segments(robot)), as_tuple(_nominal_angles(robot)),
                   as_tuple(_offset_owner(robot)), tuple(_groups(robot).tolist()),
                   robot.n_segments)


def _routing(topo: _Topology, params: dict[str, Any]) -> jax.Array:
    """(n_tendons, 2n) matrix B: tendon j's shortening per unit bending vector, / r."""
    mask = jnp.asarray(topo.runs_through)
    owner = np.asarray(topo.offset_owner, dtype=np.int32)   # as ``TendonRouting.owner``
    alpha = (jnp.asarray(topo.nominal_angles) + params["segment_offsets"][owner]
             + params["angle_deltas"][:, None])
    b = jnp.stack([jnp.cos(alpha) * mask, jnp.sin(alpha) * mask], axis=-1)
    return b.reshape(b.shape[0], 2 * topo.n_segments)


def _stiffness(params: dict[str, Any]) -> jax.Array:
    """(2n,) c_i = exp(log_stiffness_i)·L_total/L_i, each repeated for ux, uy."""
    lengths = params["lengths"]
    c = jnp.exp(params["log_stiffness"]) * jnp.sum(lengths) / lengths
    return jnp.repeat(c, 2)


def _energy(u: jax.Array, w: jax.Array, c: jax.Array, b: jax.Array,
            kappa: jax.Array) -> jax.Array:
    stretch = jnp.maximum(w - b @ u, 0.0)
    return 0.5 * jnp.sum(c * u * u) + 0.5 * jnp.sum(kappa * stretch * stretch)


def _gradient(u: jax.Array, w: jax.Array, c: jax.Array, b: jax.Array,
              kappa: jax.Array) -> jax.Array:
    return c * u - b.T @ (kappa * jnp.maximum(w - b @ u, 0.0))


_STEPS = (1.0, 0.5, 0.25, 0.1, 0.03)


def _newton(w: jax.Array, c: jax.Array, b: jax.Array, kappa: jax.Array,
            iterations: int) -> jax.Array:
    """Minimise E over u by Newton steps (the active set = the taut tendons) with the
    best of a few step lengths; E is a strictly convex piecewise quadratic."""
    steps = jnp.asarray(_STEPS, w.dtype)

    def step(_: int, u: jax.Array) -> jax.Array:
        taut = (w - b @ u > 0.0).astype(w.dtype)
        hessian = jnp.diag(c) + (b.T * (kappa * taut)) @ b
        direction = -jnp.linalg.solve(hessian, _gradient(u, w, c, b, kappa))
        trials = u + steps[:, None] * direction
        energies = jax.vmap(lambda v: _energy(v, w, c, b, kappa))(trials)
        best = jnp.argmin(energies)
        better = energies[best] < _energy(u, w, c, b, kappa)
        return jnp.where(better, trials[best], u)

    return jax.lax.fori_loop(0, iterations, step, jnp.zeros_like(c))


def bending_from_pull(pull: jax.Array, c: jax.Array, b: jax.Array, kappa: jax.Array,
                      iterations: int = 12) -> jax.Array:
    """Equilibrium bending vectors u (2n,) rad for one row of tendon pulls ``pull / r``
    (n_tendons,) rad; differentiable in every argument at the solution."""

    def solve(grad_fn: Any, u0: jax.Array) -> jax.Array:
        del grad_fn, u0
        return _newton(pull, c, b, kappa, iterations)

    def tangent_solve(g: Any, y: jax.Array) -> jax.Array:
        return jnp.linalg.solve(jax.jacobian(g)(y), y)

    return jax.lax.custom_root(lambda u: _gradient(u, pull, c, b, kappa), jnp.zeros_like(c),
                               solve, tangent_solve)


def base_rotation(params: dict[str, Any]) -> jax.Array:
    """Base rotation (3×3): the stored matrix times exp(hat(base_rotvec)) where a fit adds the
    rotation vector ``base_rotvec`` (rad); the matrix alone otherwise."""
    r = params["base_rotation"]
    if "base_rotvec" not in params:
        return r
    w = params["base_rotvec"]
    angle2 = jnp.sum(w * w)
    small = angle2 < 1e-12
    safe = jnp.where(small, 1.0, angle2)
    angle = jnp.sqrt(safe)
    a = jnp.where(small, 1.0 - angle2 / 6.0, jnp.sin(angle) / angle)
    bb = jnp.where(small, 0.5 - angle2 / 24.0, (1.0 - jnp.cos(angle)) / safe)
    k = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]], w.dtype)
    return r @ (jnp.eye(3, dtype=w.dtype) + a * k + bb * (k @ k))


def equilibrium(robot: Robot, params: dict[str, Any], commands: jax.Array,
                iterations: int = 12) -> tuple[jax.Array, jax.Array]:
    """Equilibrium bending vectors (…, n, 2) rad and segment lengths (…, n) m for
    (…, n_tendons) commands (m), with the model parameters ``params`` (``params_of``;
    traced values allowed). The lengths are ``params["lengths"]`` less the axial
    compression where ``params`` has ``log_axial`` and the robot's compression shortens
    its segments (``axial_shortens_segments``), and those lengths otherwise."""
    topo = _Topology.of(robot)
    n = topo.n_segments
    b = _routing(topo, params)
    c = _stiffness(params)
    if "log_axial" in params:
        # δ_i (compression / r) as n more unknowns: tendons through segment i shorten by δ_i
        b = jnp.concatenate([b, jnp.asarray(topo.runs_through, b.dtype)], axis=1)
        c = jnp.concatenate([c, jnp.exp(params["log_axial"])])
    kappa = jnp.exp(params["log_kappa"])[np.asarray(topo.group)]
    pull = params["gains"] * (commands - params["zero_offsets"]) / params["radius"]
    flat = pull.reshape(-1, pull.shape[-1])
    x = jax.vmap(lambda row: bending_from_pull(row, c, b, kappa, iterations))(flat)
    u = x[:, :2 * n].reshape(pull.shape[:-1] + (n, 2))
    lengths = jnp.broadcast_to(params["lengths"], pull.shape[:-1] + (n,))
    if "log_axial" in params and actuation_of(robot).axial_shortens_segments:
        lengths = lengths - params["radius"] * x[:, 2 * n:].reshape(pull.shape[:-1] + (n,))
    return u, lengths


def bending_vectors(robot: Robot, params: dict[str, Any], commands: jax.Array,
                    iterations: int = 12) -> jax.Array:
    """(…, n, 2) equilibrium bending vectors (rad) for (…, n_tendons) commands (m), with
    the model parameters ``params`` (``params_of``; traced values allowed)."""
    return equilibrium(robot, params, commands, iterations)[0]


def _z_of(u: jax.Array, lengths: jax.Array) -> jax.Array:
    return jnp.concatenate([u, lengths[..., None]], axis=-1).reshape(u.shape[:-2] + (-1,))


def measured_point(robot: Robot, params: dict[str, Any], commands: jax.Array,
                   iterations: int = 12) -> jax.Array:
    """(…, 3) predicted measured point (tip marker) in the measurement frame, m."""
    return _marker_at(robot, params, *equilibrium(robot, params, commands, iterations))


def _marker_at(robot: Robot, params: dict[str, Any], u: jax.Array,
               lengths: jax.Array) -> jax.Array:
    """(…, 3) the measured point, m, of the shape with bending vectors u (…, n, 2) rad and
    segment lengths (…, n) m."""
    z = _z_of(u, lengths)
    local = replace(robot, base_position=(0.0, 0.0, 0.0), base_wxyz=(1.0, 0.0, 0.0, 0.0),
                    actuation=None)
    pos, rot = tip_pose_z(local, z)
    marker = pos + jnp.einsum("...ij,j->...i", rot, params["marker"])
    return marker @ base_rotation(params).T + params["base_position"]


@partial(cached_jit, static_argnums=(0, 3), name="the tip prediction")
def _predict_jit(robot: Robot, params: dict[str, Any], commands: jax.Array,
                 iterations: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    u, lengths = equilibrium(robot, params, commands, iterations)   # solved once
    return _marker_at(robot, params, u, lengths), u, lengths


def _jax_params(robot: Robot) -> dict[str, jax.Array]:
    return {k: jnp.asarray(v, jnp.float64) for k, v in params_of(robot).items()}


def predict_tip(robot: Robot, commands: Any, iterations: int = 12) -> np.ndarray:
    """Predicted measured tip positions (N, 3) in the robot file's (measurement) frame, m,
    for commanded tendon displacements (N, n_tendons) in m (positive = pulled).

    Uses the robot's ``actuation`` block (nominal values without one) and its base pose;
    the point is the tip plus ``actuation.tip_marker`` in the tip frame. Float64.
    """
    cmd = _commands(robot, commands)
    with jax.enable_x64(True):
        pos, _, _ = _predict_jit(robot, _jax_params(robot), jnp.asarray(cmd, jnp.float64),
                                 iterations)
        return np.asarray(pos, dtype=np.float64)


def zero_sensitivity(robot: Robot, commands: Any, iterations: int = 12) -> np.ndarray:
    """(N,) how far the predicted tip moves per unit error of the tendon zero offsets, m/m,
    at each row of commanded displacements (N, n_tendons) m: the largest singular value of
    ∂tip/∂zero_offsets (the worst direction of an error shared among the tendons). A tip
    error budget of e m needs the zeros known to about e / sensitivity m. Float64."""
    cmd = _commands(robot, commands)
    with jax.enable_x64(True):
        params = _jax_params(robot)

        def tips(zeros: jax.Array) -> jax.Array:
            return measured_point(robot, params | {"zero_offsets": zeros},
                                  jnp.asarray(cmd, jnp.float64), iterations)

        jac = np.asarray(jax.jacfwd(tips)(params["zero_offsets"]), np.float64)
    return np.linalg.norm(jac, ord=2, axis=(1, 2))


def configuration_from_commands(robot: Robot, commands: Any,
                                iterations: int = 12) -> np.ndarray:
    """The configurations q (N, 3n) = [θ1, φ1, L1, …] (rad, rad, m) that commanded tendon
    displacements (N, n_tendons) m produce: forward kinematics from motor commands. The
    lengths L are the segments' own, less their axial compression where the robot's
    ``actuation`` block gives ``axial_stiffness_ratio`` (and does not set
    ``axial_shortens_segments`` false)."""
    from .kinematics import z_to_q_numpy

    cmd = _commands(robot, commands)
    with jax.enable_x64(True):
        _, u, lengths = _predict_jit(robot, _jax_params(robot),
                                     jnp.asarray(cmd, jnp.float64), iterations)
        u, lengths = np.asarray(u, np.float64), np.asarray(lengths, np.float64)
    z = np.concatenate([u, lengths[..., None]], axis=-1)
    return z_to_q_numpy(z.reshape(len(cmd), -1))


def _commands(robot: Robot, commands: Any) -> np.ndarray:
    cmd = np.atleast_2d(np.asarray(commands, dtype=np.float64))
    if cmd.ndim != 2 or cmd.shape[1] != robot.n_tendons:
        raise ValueError(f"commands must be (N, {robot.n_tendons}) tendon displacements "
                         f"(m) for {robot.name!r}, got shape {np.shape(commands)}")
    if not np.all(np.isfinite(cmd)):
        raise ValueError("commands contain non-finite values")
    return cmd


# ================================================================ commands for a shape

def commands_for_configuration(robot: Robot, q: Any, slack: float = 0.0) -> np.ndarray:
    """Commanded tendon displacements (N, n_tendons) m that make the forward model take the
    configurations q (N, 3n) (rad, rad, m): the inverse of ``configuration_from_commands``.

    The backbone's equilibrium needs tensions λ ≥ 0 with c_i u_i = Σ_j λ_j b_ji; they are
    chosen segment by segment from the tip, each segment's remaining moment carried by
    the two of its tendons that bracket its direction (the least tension; the third
    tendon is left just taut, or ``slack`` m slack, so ``predict`` gives back q exactly).
    Needs at least three tendons per segment spread around the backbone.

    With axial compliance (``axial_stiffness_ratio``) the commands also take up the
    compression those tensions cause. Where the compression shortens the segments (the
    default), the robot takes q's bending on segments shortened by it, which no command
    can undo (``configuration_from_commands`` gives back q's angles and the shorter
    lengths; the tip moves by at most the total compression); with
    ``axial_shortens_segments`` false it gives back q itself.
    """
    from .kinematics import q_to_z_numpy

    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    if q.shape[-1] != robot.dof:
        raise ValueError(f"q must be (N, {robot.dof}), got shape {q.shape}")
    if routing_of(robot).shared:
        raise ValueError("commands_for_configuration needs per_segment routing")
    p = params_of(robot)
    z = q_to_z_numpy(q)
    u = np.stack([z[:, 0::3], z[:, 1::3]], axis=-1).reshape(len(q), -1)   # (N, 2n)
    with jax.enable_x64(True):
        jp = {k: jnp.asarray(v, jnp.float64) for k, v in p.items()}
        b = np.asarray(_routing(_Topology.of(robot), jp))
        c = np.asarray(_stiffness(jp))
    tension = _holding_tensions(robot, b, c, u)
    kappa = np.exp(p["log_kappa"])[_groups(robot)]
    shortening = u @ b.T + _compression(robot, p, tension) @ tendon_segments(robot).T
    pull = shortening + tension / kappa - np.where(tension > 0, 0.0, slack / p["radius"])
    return p["zero_offsets"] + pull * p["radius"] / p["gains"]


def _holding_tensions(robot: Robot, b: np.ndarray, c: np.ndarray,
                      u: np.ndarray) -> np.ndarray:
    """(N, n_tendons) the least tensions λ ≥ 0 (energy units per rad) that hold the
    bending vectors u (N, 2n) rad: c·u = Bᵀλ, from the tip segment down."""
    anchor = _groups(robot)
    moment = c * u                                           # (N, 2n) = Bᵀ λ
    tension = np.zeros((len(u), robot.n_tendons))
    carried = np.zeros_like(moment)
    for k in reversed(range(robot.n_segments)):
        rows = np.flatnonzero(anchor == k)                   # the tendons ending at k
        need = moment[:, 2 * k: 2 * k + 2] - carried[:, 2 * k: 2 * k + 2]
        dirs = b[rows, 2 * k: 2 * k + 2]                     # (m, 2)
        lam = _bracketing_tensions(need, dirs)
        tension[:, rows] = lam
        carried += lam @ b[rows]
    if np.max(np.abs(carried - moment)) > 1e-9 * max(1.0, float(np.max(np.abs(moment)))):
        raise ValueError("the tendon directions cannot hold this shape (a segment's "
                         "tendons do not surround its backbone)")
    return tension


def _compression(robot: Robot, p: dict[str, np.ndarray], tension: np.ndarray) -> np.ndarray:
    """(N, n) each segment's compression / r (rad-equivalent): a_i δ_i = Σ tensions through
    segment i; zero for incompressible segments."""
    if "log_axial" not in p:
        return np.zeros((len(tension), robot.n_segments))
    return (tension @ tendon_segments(robot)) / np.exp(p["log_axial"])


def _bracketing_tensions(need: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N, m) λ ≥ 0 with λ @ dirs = need (N, 2), using two adjacent tendon directions."""
    m = len(dirs)
    out = np.zeros((len(need), m))
    done = np.zeros(len(need), bool)
    order = np.argsort(np.arctan2(dirs[:, 1], dirs[:, 0]))
    for a, bidx in zip(order, np.roll(order, -1), strict=True):
        mat = np.stack([dirs[a], dirs[bidx]], axis=1)        # columns: the two tendons
        if abs(np.linalg.det(mat)) < 1e-12:
            continue
        lam = np.linalg.solve(mat, need.T).T                 # (N, 2)
        ok = ~done & np.all(lam >= -1e-12, axis=1)
        out[ok, a] += np.maximum(lam[ok, 0], 0.0)
        out[ok, bidx] += np.maximum(lam[ok, 1], 0.0)
        done |= ok
    if not done.all():
        raise ValueError("the tendon directions cannot hold this shape")
    return out


def planned_displacements(robot: Robot, q: Any) -> np.ndarray | None:
    """Motor commands for planned configurations: (N, n_tendons) tendon displacements, m
    (``commands_for_configuration``, taut tendons just taut), NaN rows where q is not
    finite; None when the robot file has no ``actuation`` block (no calibrated zero)."""
    if getattr(robot, "actuation", None) is None or q is None:
        return None
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    out = np.full((len(q), robot.n_tendons), np.nan)
    finite = np.all(np.isfinite(q), axis=1)
    if finite.any():
        out[finite] = commands_for_configuration(robot, q[finite])
    return out
