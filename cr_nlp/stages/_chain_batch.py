"""Batched LM over many chains of waypoints (trajectories), in fixed-size compiled chunks.

A batch of B chains, each (waypoints, d) flattened to (waypoints·d,), is cut into chunks
of one size (one compiled program per size; the last chunk is padded with copies of its
first row), and every chunk is solved by one device program:

- "banded" (``stages._banded_lm``): one banded solve per chain, vmapped, so a chain that
  has converged keeps its iterate while the others go on (the loop's batched predicate
  masks it);
- "dense" (``stages._lm``): one Jacobian of the whole chain and a dense Cholesky of its
  (waypoints·d)² normal matrix; kept as the reference the banded form is checked
  against.

The residuals are the caller's (``ChainResidual`` window terms for "banded", one
function of the flat chain for "dense"); this module only batches, pads, compiles and
counts.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._banded_lm import ChainResidual, banded_lm_solve
from ._lm import LMConfig, lm_solve


class ChainBatchLM:
    """LM on batches of chains (waypoints, d) with a per-chain scalar (a time step, s).

    Args:
        terms: the window residual terms of one chain (banded structure).
        project: feasibility projection of one chain (waypoints, d) (hashable).
        waypoints: chain length.
        free: (waypoints·d,) 1.0 for the variables the solver may move, 0.0 for fixed.
        dtype: the device dtype.
        chunk_size: most chains per compiled call.
        structure: "banded" or "dense".
        dense_residual: ``(z (waypoints·d,), step, arrays) → r``, the whole chain's
            residual (needed for "dense").
        dense_project: projection of a (B, waypoints·d) batch (needed for "dense").
        extra: unbatched data passed to every term besides the scene arrays and the
            per-chain scalar (e.g. a broad phase), as the banded terms' ``shared`` =
            (arrays, extra, step).
    """

    def __init__(self, terms: ChainResidual, project: Callable[[jax.Array], jax.Array],
                 waypoints: int, free: jax.Array, dtype: Any, chunk_size: int,
                 structure: str = "banded", dense_residual: Callable | None = None,
                 dense_project: Callable | None = None, extra: Any = None) -> None:
        if structure not in ("banded", "dense"):
            raise ValueError(f"structure must be 'banded' or 'dense', got {structure!r}")
        if structure == "dense" and (dense_residual is None or dense_project is None):
            raise ValueError("the dense structure needs dense_residual and dense_project")
        self.terms, self.project = terms, project
        self.waypoints, self.free, self.dtype = waypoints, free, dtype
        self.chunk_size, self.structure = chunk_size, structure
        self.dense_residual, self.dense_project, self.extra = (dense_residual, dense_project,
                                                               extra)
        self._compiled: dict[int, Any] = {}
        self.programs = 0
        """Device programs launched so far (one per chunk)."""

    def solve(self, z0: np.ndarray, step: np.ndarray, arrays: Any,
              iterations: int) -> tuple[np.ndarray, np.ndarray, float]:
        """LM on (B, waypoints·d) chains z0 with per-chain scalars ``step`` (B,); returns
        z (B, waypoints·d) and final costs ½‖r‖² (B,) as float64, and the seconds spent
        compiling programs for new chunk sizes."""
        # One chunk size per solver (one compiled program); a batch smaller than a chunk
        # gets the smallest power of two (≥ the device count) that holds it.
        chunk = max(2, len(jax.devices()))
        while chunk < min(len(z0), self.chunk_size):
            chunk *= 2
        chunk = max(chunk, min(self._compiled, default=0))
        z_out, cost_out, compile_seconds = [], [], 0.0
        for start in range(0, len(z0), chunk):
            stop = min(start + chunk, len(z0))
            pad = chunk - (stop - start)

            def padded(x: np.ndarray, start: int = start, stop: int = stop,
                       pad: int = pad) -> np.ndarray:
                part = x[start:stop]
                return np.concatenate([part, np.repeat(part[:1], pad, 0)]) if pad else part

            args = (jnp.asarray(padded(z0), self.dtype), jnp.asarray(padded(step), self.dtype),
                    arrays, self.free, jnp.int32(iterations))
            if chunk not in self._compiled:
                t0 = time.perf_counter()
                self._compiled[chunk] = self.lower(args).compile()
                compile_seconds += time.perf_counter() - t0
            z, cost = self._compiled[chunk](*args)[:2]
            self.programs += 1
            z_out.append(np.array(z[: stop - start], dtype=np.float64))
            cost_out.append(np.array(cost[: stop - start], dtype=np.float64))
        return np.concatenate(z_out), np.concatenate(cost_out), compile_seconds

    def lower(self, args: tuple) -> Any:
        """The LM program for one chunk, on one device. Unlike IK it is not split with
        ``shard_map`` over host devices: measured with jax 0.10 on 2 CPU host devices,
        the sharded program of a 16-trajectory chunk never returned (every thread waiting
        on a futex), while the same program unsharded, where XLA's own thread pool
        parallelises the large JᵀJ products, runs normally."""
        if self.structure == "dense":
            config = LMConfig(cost_tolerance=0.0, linear_solver="cholesky")
            solve = partial(lm_solve, self.dense_residual, self.dense_project, config=config)
            return jax.jit(lambda *a: solve(*a)[:2]).lower(*args)
        n = self.waypoints
        one = partial(banded_lm_solve, self.terms, self.project,
                      config=LMConfig(cost_tolerance=0.0))
        extra = self.extra

        def solve_chunk(z0: jax.Array, step: jax.Array, arrays: Any, free: jax.Array,
                        iterations: jax.Array) -> tuple[jax.Array, jax.Array]:
            def single(z: jax.Array, h: jax.Array) -> tuple[jax.Array, jax.Array]:
                out, cost, _ = one(z.reshape(n, -1), None, (arrays, extra, h),
                                   free.reshape(n, -1), iterations)
                return out.reshape(-1), cost

            return jax.vmap(single)(z0, step)

        return jax.jit(solve_chunk).lower(*args)
