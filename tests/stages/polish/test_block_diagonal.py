"""The block-diagonal gather against numpy's dense block diagonal."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from scipy.linalg import block_diag

from cr_nlp.stages.polish._block_diagonal import block_diagonal


def _kind(rng: np.random.Generator, height: int, width: int, places: list[int]):
    """A map-like output: ``len(places)`` blocks of one random sparsity side by side, its
    nonzeros a symbol."""
    pattern = ca.DM((rng.random((height, width)) < 0.5).astype(float)).sparsity()
    x = ca.MX.sym("x", pattern.nnz() * len(places))
    nnz = pattern.nnz()
    stacked = ca.horzcat(*[ca.MX(pattern, x[j * nnz:(j + 1) * nnz]) for j in range(len(places))])
    return (stacked, places), x


@pytest.mark.parametrize("upper", [False, True])
def test_blocks_land_in_the_rods_order_with_the_rows_below(upper: bool) -> None:
    rng = np.random.default_rng(3)
    width, order = 6, rng.permutation(7).tolist()
    (a, xa), (b, xb) = _kind(rng, 4, width, order[:3]), _kind(rng, 9, width, order[3:])
    below = None if upper else ca.DM(rng.random((3, 7 * width)) * (rng.random((3, 42)) < 0.2))
    f = ca.Function("f", [xa, xb], [block_diagonal([a, b], width, below, upper)])
    ga, gb = ca.Function("a", [xa], [a[0]]), ca.Function("b", [xb], [b[0]])
    va, vb = rng.random(xa.numel()), rng.random(xb.numel())
    blocks = {}
    for (_, places), fun, v in ((a, ga, va), (b, gb, vb)):
        dense = np.array(fun(v))
        for j, place in enumerate(places):
            blocks[place] = dense[:, j * width:(j + 1) * width]
    expected = block_diag(*[blocks[p] for p in range(7)])
    if below is not None:
        expected = np.vstack([expected, np.array(below)])
    if upper:
        expected = np.triu(expected)
    assert np.array_equal(np.array(ca.densify(f(va, vb))), expected)
