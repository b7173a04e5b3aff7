"""The trajectory NLP's CasADi assembly (``stages.polish._trajectory_nlp``): the check
points between waypoints, and the constant sparsity patterns and 0/1 matrices that sum
per-waypoint, per-interval and per-configuration element blocks into the constraint
Jacobian and the banded Hessian of the Lagrangian.

The NLP's variable is the (3n × W) matrix of waypoints in z, column k waypoint k; its
configurations are the W waypoints, then interval after interval its check points
(``interpolated``). Building the patterns once from index lists, not letting CasADi
differentiate the mapped graph, keeps the Hessian cheap (``TrajectoryPolisher._build``).
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np


def interpolated(way: Any, fractions: Any) -> Any:
    """The (3n × C) configurations of a (3n × W) trajectory (numpy or CasADi): the W
    waypoints, then interval after interval its check points, (1 − s)·z_k + s·z_{k+1} for
    the (checks × (W − 1)) ``fractions`` s, C = W + checks·(W − 1)."""
    checks = fractions.shape[0]
    if checks == 0:
        return way
    step = way[:, 1:] - way[:, :-1]
    if isinstance(way, (ca.MX, ca.SX)):
        inner = [way[:, :-1] + step * ca.repmat(fractions[c, :], way.shape[0], 1)
                 for c in range(checks)]
        # Column k of the stack holds interval k's points one above the other.
        return ca.horzcat(way, ca.reshape(ca.vertcat(*inner), way.shape[0], -1))
    inner = way[:, :-1, None] + step[:, :, None] * np.asarray(fractions).T[None]
    return np.hstack([way, inner.reshape(way.shape[0], -1)])


def interval_curvature(dof: int, checks: int) -> ca.Function:
    """(3n × 3n·checks) Hessians of one interval's check points and their (checks,)
    fractions s → their (6n × 6n) Hessian with respect to the interval's two waypoints: a
    point (1 − s)·z_k + s·z_{k+1} with Hessian H enters as
    [[(1−s)², (1−s)s], [(1−s)s, s²]] ⊗ H."""
    h, fractions = ca.SX.sym("h", dof, dof * checks), ca.SX.sym("fractions", checks)
    total = ca.SX(2 * dof, 2 * dof)
    for c in range(checks):
        s = fractions[c]
        block = h[:, c * dof:(c + 1) * dof]
        total += ca.vertcat(ca.horzcat((1 - s) ** 2 * block, (1 - s) * s * block),
                            ca.horzcat((1 - s) * s * block, s ** 2 * block))
    return ca.Function("interval_curvature", [h, fractions], [total])


def band_assembly(dof: int, waypoints: int) -> tuple[ca.Sparsity, ca.DM]:
    """The upper-triangular block-tridiagonal Hessian pattern of ``waypoints`` blocks of
    ``dof`` variables, and the constant 0/1 matrix that sums the waypoint element
    Hessians (dof × dof·W, column-major) and the interval element Hessians
    (2dof × 2dof·(W − 1)) into its nonzeros."""
    entries: list[tuple[int, int, int]] = []          # (global row, global column, source)
    for k in range(waypoints):
        for j in range(dof):
            for i in range(j + 1):
                entries.append((k * dof + i, k * dof + j, (k * dof + j) * dof + i))
    base = dof * dof * waypoints
    two = 2 * dof
    for k in range(waypoints - 1):
        for j in range(two):
            for i in range(j + 1):
                entries.append((k * dof + i, k * dof + j, base + (k * two + j) * two + i))
    size = dof * waypoints
    keys = sorted({(r, c) for r, c, _ in entries}, key=lambda rc: (rc[1], rc[0]))
    index = {rc: i for i, rc in enumerate(keys)}
    pattern = ca.Sparsity.triplet(size, size, [r for r, _ in keys], [c for _, c in keys])
    sources = base + two * two * (waypoints - 1)
    assembly = ca.DM(ca.Sparsity.triplet(len(keys), sources,
                                         [index[(r, c)] for r, c, _ in entries],
                                         [src for _, _, src in entries]),
                     np.ones(len(entries)))
    return pattern, assembly


def chained_jacobian(blocks: ca.MX, fractions: ca.MX, rows: int, dof: int, waypoints: int,
                     checks: int) -> ca.MX:
    """The clearance rows' Jacobian with respect to the (dof·W) waypoint variables, from
    their per-configuration Jacobian ``blocks`` (rows × dof·C, the configurations of
    ``interpolated``) and the check points' (checks × (W − 1)) ``fractions``: a check
    point's block enters waypoint k with weight 1 − s and waypoint k + 1 with weight s."""
    inner = blocks[:, dof * waypoints:]
    right = inner * ca.repmat(ca.kron(ca.vec(fractions).T, ca.DM.ones(1, dof)), rows, 1)
    sources = ca.vertcat(ca.vec(blocks[:, :dof * waypoints]), ca.vec(inner - right),
                         ca.vec(right))
    pattern, assembly = rows_assembly(rows, dof, waypoints, checks)
    return ca.MX(pattern, ca.mtimes(assembly, sources))


def rows_assembly(rows: int, dof: int, waypoints: int, checks: int) -> tuple[ca.Sparsity,
                                                                              ca.DM]:
    """The sparsity of the clearance rows' Jacobian (``rows`` per configuration, the
    configurations of ``interpolated``) with respect to the (dof·W) waypoint variables,
    and the constant 0/1 matrix that maps its sources to its nonzeros. The sources,
    stacked column-major: the waypoints' Jacobians (rows × dof·W), then the check points'
    Jacobians weighted by 1 − s (rows × dof·checks·(W − 1), for waypoint k), then the
    same weighted by s (for waypoint k + 1)."""
    entries: list[tuple[int, int, int]] = []            # (row, column, source)
    inner = rows * dof * checks * (waypoints - 1)

    def block(config: int, waypoint: int, source: int) -> None:
        for j in range(dof):
            for i in range(rows):
                entries.append((config * rows + i, waypoint * dof + j, source + j * rows + i))

    for k in range(waypoints):
        block(k, k, k * dof * rows)
    base = rows * dof * waypoints
    for k in range(waypoints - 1):
        for c in range(checks):
            index = k * checks + c
            block(waypoints + index, k, base + index * dof * rows)
            block(waypoints + index, k + 1, base + inner + index * dof * rows)
    configs = waypoints + checks * (waypoints - 1)
    keys = sorted({(r, c) for r, c, _ in entries}, key=lambda rc: (rc[1], rc[0]))
    index_of = {rc: i for i, rc in enumerate(keys)}
    pattern = ca.Sparsity.triplet(rows * configs, dof * waypoints,
                                  [r for r, _ in keys], [c for _, c in keys])
    assembly = ca.DM(ca.Sparsity.triplet(len(keys), base + 2 * inner,
                                         [index_of[(r, c)] for r, c, _ in entries],
                                         [src for _, _, src in entries]),
                     np.ones(len(entries)))
    return pattern, assembly
