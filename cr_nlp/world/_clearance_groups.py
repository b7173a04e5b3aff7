"""Grouped clearance shortfalls: the clearance residual of the chain LMs (trajectory
planning and path following), with Jacobians from the primal alone.

For one configuration, the body spheres' distances to their nearest obstacle part
(``world.clearance``'s sphere body) and the self pairs' distances are turned into
shortfalls max(0, δ − d) and grouped: one group per segment's spheres, one for all self
pairs, each group's value the norm of its shortfalls. Grouping keeps the LM's residual
count (hence the cost of JᵀJ) small; ½‖group‖² equals the per-sphere penalty, so the
gradient is unchanged.

Derivatives: the body-sphere centres' closed-form Jacobian (``model.derivatives``) times
each sphere's distance gradient (the gradient of a min is that of its argmin, so only
the nearest part of each kind is differentiated), wrapped in ``jax.custom_jvp`` so that a
forward-mode pass over every tangent direction costs one matrix product. With a broad
phase (``world._broad_phase``) only the parts whose bounding balls are nearest to a
sphere are measured. Distances in metres; configurations are bending vectors z
(rad, rad, m).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..model.derivatives import backbone_jacobian_z
from ..model.kinematics import backbone_points_z
from ..model.robot import Robot
from ._broad_phase import PartBalls
from ._penalty import body_clearances_z
from .clearance import SceneArrays, _kind_blocks, body_segments, self_pairs


def has_clearance(robot: Robot, arrays: SceneArrays | None) -> bool:
    """Whether there is any clearance to keep: obstacle parts, or self pairs."""
    return (arrays is not None and arrays.n_parts > 0) or robot.has_self_pairs


def body_centres_from(robot: Robot, points: jax.Array,
                      d_points: jax.Array | None = None) -> tuple[jax.Array, jax.Array | None]:
    """Body-sphere centres (N, 3) m in ``world.clearance._centres`` order (the base, then
    the backbone points (n·k, 3)) and, given the points' Jacobian (n·k, 3, d), theirs
    (N, 3, d) (the base does not move), else None."""
    centres = jnp.concatenate([jnp.asarray(robot.base_position, points.dtype)[None], points])
    if d_points is None:
        return centres, None
    base = jnp.zeros((1,) + d_points.shape[1:], d_points.dtype)
    return centres, jnp.concatenate([base, d_points])


def body_centres_z(robot: Robot, z: jax.Array) -> jax.Array:
    """Body-sphere centres (N, 3) m of one z (3n,), ``world.clearance._centres`` order:
    the base, then the backbone points."""
    return body_centres_from(robot, backbone_points_z(robot, z).astype(z.dtype))[0]


def body_centres_jacobian_z(robot: Robot, z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``body_centres_z`` (N, 3) m and its closed-form Jacobian (N, 3, 3n)."""
    centres, jac = body_centres_from(robot, *backbone_jacobian_z(robot, z))
    assert jac is not None
    return centres, jac


def _safe_norm(x: jax.Array) -> jax.Array:
    eps = jnp.asarray(1e-9, x.dtype)
    return jnp.sqrt(jnp.sum(x * x, axis=-1) + eps * eps) - eps


def group_indices(robot: Robot, arrays: SceneArrays | None) -> list[np.ndarray]:
    """Index sets into ``body_clearances_z``'s output, one per residual group: each
    segment's body spheres (nearest-obstacle rows), then all self pairs."""
    out, offset = [], 0
    if arrays is not None and arrays.n_parts > 0:
        out += list(body_segments(robot))
        offset = robot.n_points + 1
    if robot.has_self_pairs:
        out.append(offset + np.arange(len(self_pairs(robot))))
    return out


def clearance_group_values(robot: Robot, margin: float, arrays: SceneArrays | None,
                           z: jax.Array) -> jax.Array:
    """Grouped clearance shortfalls (m) of one configuration z (3n,): for each segment, the
    norm of max(0, δ − d) over its body spheres' nearest-obstacle distances
    (``body_clearances_z``), then the norm over the self pairs. Grouping keeps the LM's
    residual count (hence the cost of JᵀJ) small; ½‖group‖² equals the per-sphere
    penalty, so the gradient is unchanged."""
    shortfall = jnp.maximum(margin - body_clearances_z(robot, arrays, z), 0.0)
    return jnp.stack([_safe_norm(shortfall[idx]) for idx in group_indices(robot, arrays)])


# Fields of ``SceneArrays`` per part kind, in ``_kind_blocks`` order.
_KIND_FIELDS = (("sphere_center", "sphere_radius"),
                ("box_center", "box_rotation", "box_half_size"),
                ("capsule_a", "capsule_b", "capsule_radius"),
                ("cylinder_center", "cylinder_rotation", "cylinder_radius",
                 "cylinder_half_length"),
                ("convex_planes",))


def _candidates(arrays: SceneArrays, balls: PartBalls, near: int, present: list[int],
                centres: jax.Array) -> list[jax.Array]:
    """Broad phase: per present part kind, the indices (N, k) of the parts each body
    sphere (centres (N, 3) m) may be nearest to: the ``near`` parts whose bounding balls
    (``world._broad_phase``) are nearest to it, or every part of a kind with at most
    ``near`` parts."""
    out = []
    for kind in present:
        count = getattr(arrays, _KIND_FIELDS[kind][0]).shape[0]
        if count <= near:
            out.append(jnp.broadcast_to(jnp.arange(count), (centres.shape[0], count)))
            continue
        ball_centres, radii = balls[kind]
        gap = jnp.sqrt(jnp.sum((centres[:, None] - ball_centres[None]) ** 2, axis=-1)) - radii
        out.append(jax.lax.top_k(-gap, near)[1])
    return out


def _nearest_and_gradient(robot: Robot, arrays: SceneArrays, centres: jax.Array,
                          balls: PartBalls | None = None,
                          near: int = 0) -> tuple[jax.Array, jax.Array]:
    """Each body sphere's nearest-obstacle distance (N,) m and its gradient (N, 3) with
    respect to the sphere's centre. The gradient of a min is that of its argmin, so only
    the nearest part of each kind is differentiated (measured 10–20× cheaper than the
    reverse pass over every (sphere, part) pair). With ``balls`` and ``near`` > 0 only the
    ``near`` parts per kind whose bounding balls are nearest to a sphere are measured
    (``_candidates``); a part outside them is taken to be farther."""
    present = [k for k, f in enumerate(_KIND_FIELDS) if getattr(arrays, f[0]).shape[0]]
    if balls is not None and near > 0:
        candidates = _candidates(arrays, balls, near, present, centres)
        gathered = dict(arrays._asdict())
        axes = dict.fromkeys(gathered)
        for kind, idx in zip(present, candidates, strict=True):
            for name in _KIND_FIELDS[kind]:
                gathered[name] = getattr(arrays, name)[idx]           # (N, k, …)
                axes[name] = 0
        blocks = jax.vmap(lambda one, c: [b[0] for b in _kind_blocks(robot, one, c[None], 0.0)],
                          in_axes=(SceneArrays(**axes), 0))(SceneArrays(**gathered), centres)
        chosen = [jnp.take_along_axis(idx, jnp.argmin(b, axis=-1)[:, None], axis=1)
                  for idx, b in zip(candidates, blocks, strict=True)]
    else:
        blocks = _kind_blocks(robot, arrays, centres, 0.0)
        chosen = [jnp.argmin(b, axis=-1)[:, None] for b in blocks]
    picked = dict(arrays._asdict())
    axes = dict.fromkeys(picked)
    for kind, nearest in zip(present, chosen, strict=True):   # (N, 1): one part per sphere
        for name in _KIND_FIELDS[kind]:
            picked[name] = getattr(arrays, name)[nearest]
            axes[name] = 0
    per_sphere = SceneArrays(**picked)

    def distance(one: SceneArrays, centre: jax.Array) -> jax.Array:
        rows = _kind_blocks(robot, one, centre[None], 0.0)
        return jnp.min(jnp.concatenate([b.reshape(-1) for b in rows]))

    return jax.vmap(jax.value_and_grad(distance, argnums=1),
                    in_axes=(SceneArrays(**axes), 0))(per_sphere, centres)


def grouped_shortfalls(robot: Robot, margin: float, arrays: SceneArrays | None,
                       centres: jax.Array, jac_centres: jax.Array | None,
                       balls: PartBalls | None = None,
                       near: int = 0) -> tuple[jax.Array, jax.Array | None]:
    """Grouped clearance shortfalls (G,) m of the body spheres' centres (N, 3) m
    (``clearance_group_values``: per segment the norm of max(0, δ − d) over its spheres'
    nearest-obstacle distances, then the norm over the self pairs) and, given the centres'
    Jacobian (N, 3, d), theirs (G, d) (else None). Shared by the trajectory LM and path
    following, which build the centre Jacobian differently. ``balls``, ``near``:
    the broad phase of ``_nearest_and_gradient`` (None, 0: every part)."""
    values, rows = [], []
    if arrays is not None and arrays.n_parts > 0:
        d, grad = _nearest_and_gradient(robot, arrays, centres, balls, near)
        values.append(d)
        if jac_centres is not None:
            rows.append(jnp.einsum("nk,nkj->nj", grad, jac_centres))
    if robot.has_self_pairs:
        pairs = self_pairs(robot)
        diff = centres[pairs[:, 0]] - centres[pairs[:, 1]]
        norm = jnp.sqrt(jnp.maximum(jnp.sum(diff * diff, axis=-1), 1e-30))
        values.append(norm - 2.0 * robot.backbone_radius)
        if jac_centres is not None:
            unit = diff / norm[:, None]
            rows.append(jnp.einsum("nk,nkj->nj", unit,
                                   jac_centres[pairs[:, 0]] - jac_centres[pairs[:, 1]]))
    d = jnp.concatenate(values)
    shortfall = jnp.maximum(margin - d, 0.0)
    jac_d = jnp.concatenate(rows) if jac_centres is not None else None
    out, jac = [], []
    eps = jnp.asarray(1e-9, centres.dtype)
    for idx in group_indices(robot, arrays):
        s = shortfall[idx]
        root = jnp.sqrt(jnp.sum(s * s) + eps * eps)
        out.append(root - eps)
        if jac_d is not None:
            jac.append(-(s / root) @ jac_d[idx])
    return jnp.stack(out), (jnp.stack(jac) if jac_d is not None else None)


def clearance_group_jacobian(robot: Robot, margin: float, arrays: SceneArrays | None,
                             z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``clearance_group_values`` (G,) m and its Jacobian (G, 3n), from the body spheres'
    closed-form centre Jacobian (``model.derivatives``) and per-sphere distance gradients
    (no pass over every tangent direction)."""
    centres, jac_centres = body_centres_jacobian_z(robot, z)
    return grouped_shortfalls(robot, margin, arrays, centres, jac_centres)


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def clearance_groups(robot: Robot, margin: float, arrays: SceneArrays | None,
                     z: jax.Array) -> jax.Array:
    """``clearance_group_values`` (G,) m of one configuration z (3n,), every part measured;
    its Jacobian is ``clearance_group_jacobian``, computed from the primal alone."""
    return clearance_group_values(robot, margin, arrays, z)


@clearance_groups.defjvp
def _clearance_groups_jvp(robot: Robot, margin: float, primals: tuple,
                          tangents: tuple) -> tuple:
    # The configuration's own Jacobian from the primal, then one product.
    arrays, z = primals
    z_dot = tangents[1]
    values, jac = clearance_group_jacobian(robot, margin, arrays, z)
    return values, jac @ z_dot


@partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def near_clearance_groups(robot: Robot, margin: float, near: int, arrays: SceneArrays | None,
                          balls: PartBalls | None, z: jax.Array) -> jax.Array:
    """``clearance_group_values`` (G,) m of one configuration z (3n,) with the broad phase
    of ``_nearest_and_gradient``: only the ``near`` parts per kind whose bounding balls
    (``balls``, ``world._broad_phase``) are nearest to a body sphere are measured (``near``
    0 or ``balls`` None: every part). Its Jacobian comes from the primal alone."""
    return grouped_shortfalls(robot, margin, arrays, body_centres_z(robot, z), None, balls,
                              near)[0]


@near_clearance_groups.defjvp
def _near_clearance_groups_jvp(robot: Robot, margin: float, near: int, primals: tuple,
                               tangents: tuple) -> tuple:
    arrays, balls, z = primals
    z_dot = tangents[2]
    centres, jac_centres = body_centres_jacobian_z(robot, z)
    values, jac = grouped_shortfalls(robot, margin, arrays, centres, jac_centres, balls, near)
    return values, jac @ z_dot
