"""Batches of load cases for the statics' compiled programs: padded to a few sizes,
typed, taken by rows, and a one-case function as a function of a batch of one."""

from __future__ import annotations

import math
from typing import Any

import jax
import numpy as np

from ..._cached_jit import CachedProgram


def _one(fn: Any) -> Any:
    """``fn`` of one case as a function of a batch of one (no vmap)."""
    def call(*args: Any) -> Any:
        out = fn(*jax.tree_util.tree_map(lambda a: a[0], args))
        return jax.tree_util.tree_map(lambda a: a[None], out)

    return call


def _split(fn: Any, arguments: int) -> Any:
    """``fn`` jitted, its batch split over the JAX devices (one per CPU core when the
    process asked for host devices) when the batch divides evenly, else on one: one
    program per argument shapes (``CachedProgram``)."""
    return CachedProgram(fn, name="the Cosserat shooting", batched=(True,) * arguments)


def _padded(rows: Any, edge: bool = False) -> Any:
    """Rows (an array or a pytree of arrays with the same first axis) padded to 16, 64 or
    256 rows, then 512 or 1024, then a multiple of 512 (one row stays one: a live update
    or a viewer's rest shape solves one case, 11 → 6–7 ms), so that a few compiled programs
    serve every batch size: with zero rows (no load: done at once) or copies of the first
    row. (Padding rows still iterate in the vmapped loop: 3333 loaded rows of 10 000 mixed
    cases cost 10–15 % less padded to 3584 than to 4096. Below 256 rows a solve is cheap
    and each program size costs ~2–5 s of compiling: skipping 32 and 128 cut the compiling
    of notebook 07's tension plan from 34 to 21 s, its steady state unchanged.)"""
    leaves, tree = jax.tree_util.tree_flatten(rows)
    count = len(leaves[0])
    size = 1 if count == 1 else max(16, 1 << (count - 1).bit_length())
    if 1 < size < 256:
        size = 1 << (2 * math.ceil(math.log2(size) / 2))
    if size > 1024:
        size = -(-count // 512) * 512

    def pad(a: np.ndarray) -> np.ndarray:
        a = np.asarray(a)
        fill = (np.repeat(a[:1], size - count, axis=0) if edge
                else np.zeros((size - count, *a.shape[1:]), a.dtype))
        return np.concatenate([a, fill])

    return jax.tree_util.tree_unflatten(tree, [pad(a) for a in leaves])


def _typed(rows: Any, dtype: Any) -> Any:
    """The rows as ``dtype`` numpy arrays for a compiled program, which moves them to its
    devices itself (30 µs for ten small arrays, against 180 µs for ``jax.device_put`` of
    the tree first: a one-case solve makes five such calls)."""
    return jax.tree_util.tree_map(lambda a: np.asarray(a, dtype), rows)


def _rows(value: Any, index: np.ndarray) -> Any:
    """The rows ``index`` of every leaf of ``value`` (numpy)."""
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[index], value)
