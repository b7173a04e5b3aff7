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
phase (``world._broad_phase``) only the parts listed for a sphere's cell are measured.
Distances in metres; configurations are bending vectors z (rad, rad, m).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..model.derivatives import backbone_jacobian_z
from ..model.kinematics import backbone_points_z
from ..model.robot import Robot
from ._broad_phase import KIND_FIELDS, PartCells, cell_candidates
from ._penalty import body_clearances_z, self_pair_blocks
from .clearance import (
    SceneArrays,
    _kind_blocks,
    _self_block,
    body_segments,
    clearance_z,
    self_pairs,
)


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


def _kind_only(arrays: SceneArrays, kind: int, fields: dict) -> SceneArrays:
    """``arrays`` with the fields of ``kind`` replaced by ``fields`` and every other kind
    empty."""
    out = {name: value[:0] for name, value in arrays._asdict().items()}
    out.update(fields)
    return SceneArrays(**out)


def _kind_nearest(robot: Robot, arrays: SceneArrays, kind: int, centres: jax.Array,
                  candidates: jax.Array | None) -> tuple[jax.Array, jax.Array]:
    """Each body sphere's distance (N,) m to its nearest part of one kind, among its
    ``candidates`` (N, W) (None: every part of the kind), and its gradient (N, 3) with
    respect to the sphere's centre (the nearest part's; ties pick one).

    Convex parts: the distance is max_f(n_f·c − b_f) − r and its gradient the normal of
    the largest plane, both read at the chosen (part, face) of the plane values. Measured
    on CPU (XLA, jax 0.10, 767 configurations × 31 spheres × 8 candidates), a reverse pass
    through the plane max was 3–5× slower, and a value taken as the min of the per-part
    maxima (the plane values then never materialised) 10–30× slower. Other kinds: one
    reverse pass over the nearest part only."""
    fields = {name: getattr(arrays, name) for name in KIND_FIELDS[kind]}
    if candidates is not None:
        gathered = {name: value[candidates] for name, value in fields.items()}  # (N, W, …)
    r = robot.backbone_radius
    if KIND_FIELDS[kind] == ("convex_planes",):
        planes = fields["convex_planes"]                                     # (P, F, 4)
        # (N or 1, W or P, F) per plane coefficient, gathered one coefficient at a time.
        coeffs = [planes[None, ..., k] if candidates is None else planes[..., k][candidates]
                  for k in range(4)]
        x = centres[:, None, None, :]
        values = (coeffs[0] * x[..., 0] + coeffs[1] * x[..., 1] + coeffs[2] * x[..., 2]
                  - coeffs[3])                                               # (N, ·, F)
        best = jnp.argmin(jnp.max(values, axis=-1), axis=-1)
        row = jnp.take_along_axis(values, best[:, None, None], axis=1)[:, 0]    # (N, F)
        face = jnp.argmax(row, axis=-1)
        part = best if candidates is None else jnp.take_along_axis(
            candidates, best[:, None], axis=1)[:, 0]
        return (jnp.take_along_axis(row, face[:, None], axis=1)[:, 0] - r,
                planes[part, face, :3])
    per_sphere = SceneArrays(**{name: 0 if name in fields else None for name in arrays._fields})

    def distances(one: SceneArrays, centre: jax.Array) -> jax.Array:    # (count,)
        return _kind_blocks(robot, one, centre[None], 0.0)[0][0]

    if candidates is None:
        block = _kind_blocks(robot, _kind_only(arrays, kind, fields), centres, 0.0)[0]
        part = jnp.argmin(block, axis=-1)
    else:
        block = jax.vmap(distances, in_axes=(per_sphere, 0))(
            _kind_only(arrays, kind, gathered), centres)
        part = jnp.take_along_axis(candidates, jnp.argmin(block, axis=-1)[:, None], 1)[:, 0]
    nearest = {name: value[part][:, None] for name, value in fields.items()}   # (N, 1, …)
    return jax.vmap(jax.value_and_grad(lambda one, c: distances(one, c)[0], argnums=1),
                    in_axes=(per_sphere, 0))(_kind_only(arrays, kind, nearest), centres)


def _nearest_and_gradient(robot: Robot, arrays: SceneArrays, centres: jax.Array,
                          cells: PartCells | None = None) -> tuple[jax.Array, jax.Array]:
    """Each body sphere's nearest-obstacle distance (N,) m and its gradient (N, 3) with
    respect to the sphere's centre. The gradient of a min is that of its argmin, so only
    the nearest part of each kind is differentiated (measured 10–20× cheaper than the
    reverse pass over every (sphere, part) pair; ``_kind_nearest``). With ``cells``
    (``world._broad_phase``) only the parts of the sphere's cell are measured: exact below
    ``cells.cutoff``, never nearer than the true distance above it."""
    present = [k for k, f in enumerate(KIND_FIELDS) if getattr(arrays, f[0]).shape[0]]
    if cells is None:
        candidates: list = [None] * len(present)
    else:
        if [k for k, w in enumerate(cells.widths) if w] != present:
            raise ValueError(f"the broad-phase table's part kinds (widths {cells.widths}) "
                             "do not match the scene arrays")
        candidates = cell_candidates(cells, centres)
    nearest = [_kind_nearest(robot, arrays, kind, centres, idx)
               for kind, idx in zip(present, candidates, strict=True)]
    if len(nearest) == 1:
        return nearest[0]
    values = jnp.stack([d for d, _ in nearest])                               # (K, N)
    kind = jnp.argmin(values, axis=0)
    grads = jnp.stack([g for _, g in nearest])                                # (K, N, 3)
    return jnp.min(values, axis=0), jnp.take_along_axis(grads, kind[None, :, None], 0)[0]


def near_clearance_z(robot: Robot, arrays: SceneArrays, cells: PartCells | None,
                     z: jax.Array) -> jax.Array:
    """(…,) sphere-body clearance (m) of configurations z (…, 3n): the smallest signed
    distance of a body sphere to an obstacle part or, for non-neighbouring segments, to
    another body sphere. With ``cells`` (``world._broad_phase``) only the parts of each
    sphere's cell are measured: equal to ``world.clearance.clearance_z`` wherever that is
    below ``cells.cutoff``, at least ``cells.cutoff`` elsewhere, so ``≥ margin`` is decided
    exactly for any margin ≤ the cutoff. None: every part (``clearance_z`` itself)."""
    if cells is None:
        return clearance_z(robot, arrays, z)

    def one(zi: jax.Array) -> jax.Array:
        centres = body_centres_z(robot, zi)
        out = jnp.asarray(jnp.inf, centres.dtype)
        if arrays.n_parts > 0:
            out = jnp.min(_nearest_and_gradient(robot, arrays, centres, cells)[0])
        if robot.has_self_pairs:
            out = jnp.minimum(out, jnp.min(_self_block(robot, centres)))
        return out

    flat = z.reshape(-1, z.shape[-1])
    return jax.vmap(one)(flat).reshape(z.shape[:-1])


def grouped_shortfalls(robot: Robot, margin: float, arrays: SceneArrays | None,
                       centres: jax.Array, jac_centres: jax.Array | None,
                       cells: PartCells | None = None) -> tuple[jax.Array, jax.Array | None]:
    """Grouped clearance shortfalls (G,) m of the body spheres' centres (N, 3) m
    (``clearance_group_values``: per segment the norm of max(0, δ − d) over its spheres'
    nearest-obstacle distances, then the norm over the self pairs) and, given the centres'
    Jacobian (N, 3, d), theirs (G, d) (else None). Shared by the trajectory LM and path
    following, which build the centre Jacobian differently. ``cells``: the broad phase of
    ``_nearest_and_gradient`` (``world._broad_phase``; None: every part), whose cutoff
    must be at least ``margin`` (checked here where the margin is a number, not data of
    the program)."""
    if cells is not None and isinstance(margin, float) and isinstance(
            cells.cutoff, float) and cells.cutoff < margin:
        raise ValueError(f"the broad-phase table is exact below {cells.cutoff} m, less than "
                         f"the margin {margin} m")
    obstacles = arrays is not None and arrays.n_parts > 0
    values = []
    if obstacles:
        d, grad = _nearest_and_gradient(robot, arrays, centres, cells)
        values.append(d)
    blocks = self_pair_blocks(robot) if robot.has_self_pairs else ()
    # Self pairs block by block, static slices and broadcasting (no gather; see
    # ``world._penalty``): each block's centre differences (R, C, 3) and distances (R, C).
    diffs = [centres[r0:r1, None, :] - centres[None, c0:c1, :] for r0, r1, c0, c1 in blocks]
    norms = [jnp.sqrt(jnp.maximum(jnp.sum(diff * diff, axis=-1), 1e-30)) for diff in diffs]
    values += [(norm - 2.0 * robot.backbone_radius).reshape(-1) for norm in norms]
    shortfall = jnp.maximum(margin - jnp.concatenate(values), 0.0)
    eps = jnp.asarray(1e-9, centres.dtype)
    roots = jnp.stack([jnp.sqrt(jnp.sum(shortfall[idx] ** 2) + eps * eps)
                       for idx in group_indices(robot, arrays)])
    if jac_centres is None:
        return roots - eps, None
    # Group g's Jacobian is −Σ_rows (s_r/root_g)·∂d_r/∂z; every row is a direction at one
    # or two body spheres times their centre Jacobians, so the sum is first collected per
    # sphere, (G, N, 3), then contracted once with the centre Jacobians (N, 3, d): no
    # per-row (or per-pair) copy of a centre Jacobian is made.
    count, weights = centres.shape[0], []
    if obstacles:
        member = jnp.asarray(_segment_membership(robot), centres.dtype)      # (S, N)
        pull = shortfall[:count, None] * grad                                # (N, 3)
        scale = member / roots[:member.shape[0], None]
        weights.append(-scale[:, :, None] * pull[None])
    if blocks:
        # Pair (i, j) pulls sphere i along +unit(cᵢ − cⱼ) and sphere j along −unit.
        pull, start = jnp.zeros_like(centres), count if obstacles else 0
        for (r0, r1, c0, c1), diff, norm in zip(blocks, diffs, norms, strict=True):
            stop = start + norm.size
            block = shortfall[start:stop].reshape(norm.shape)[..., None] * diff / norm[..., None]
            pull = pull.at[r0:r1].add(jnp.sum(block, axis=1)).at[c0:c1].add(-jnp.sum(block, 0))
            start = stop
        weights.append(-pull[None] / roots[-1])
    return roots - eps, jnp.einsum("gnk,nkj->gj", jnp.concatenate(weights), jac_centres)


def _segment_membership(robot: Robot) -> np.ndarray:
    """(n, N) 1 where body sphere j lies on segment i's chain (``body_segments``)."""
    out = np.zeros((robot.n_segments, robot.n_points + 1))
    for i, idx in enumerate(body_segments(robot)):
        out[i, idx] = 1.0
    return out


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


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def near_clearance_groups(robot: Robot, margin: float, arrays: SceneArrays | None,
                          cells: PartCells | None, z: jax.Array) -> jax.Array:
    """``clearance_group_values`` (G,) m of one configuration z (3n,) with the broad phase
    of ``_nearest_and_gradient``: only the parts in a body sphere's cell of ``cells``
    (``world._broad_phase``, built with a cutoff ≥ ``margin``) are measured, which gives
    the same shortfalls (None: every part). Its Jacobian comes from the primal alone."""
    return grouped_shortfalls(robot, margin, arrays, body_centres_z(robot, z), None, cells)[0]


@near_clearance_groups.defjvp
def _near_clearance_groups_jvp(robot: Robot, margin: float, primals: tuple,
                               tangents: tuple) -> tuple:
    arrays, cells, z = primals
    z_dot = tangents[2]
    centres, jac_centres = body_centres_jacobian_z(robot, z)
    values, jac = grouped_shortfalls(robot, margin, arrays, centres, jac_centres, cells)
    return values, jac @ z_dot
