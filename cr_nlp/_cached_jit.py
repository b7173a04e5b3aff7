"""``cached_jit``: ``jax.jit`` whose programs come from ``_programs.compile_program``, so a
new process loads them from disk instead of tracing them."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

from ._programs import compile_ahead, compile_program
from .runtime import register


class CachedProgram:
    """``jax.jit(fn)`` whose programs come from ``compile_program``: one per argument
    shapes (and devices), loaded from disk in a new process instead of traced.

    ``batched``, ``outputs`` and ``by_shape``: as ``compile_program`` (split over the
    devices when the batch divides evenly). ``static_argnums``: arguments that are Python
    values fixed at trace time (as ``jax.jit``'s), one program per value."""

    def __init__(self, fn: Callable, *, name: str = "", batched: Sequence[bool] | None = None,
                 outputs: int = 1, static_argnums: tuple[int, ...] = (),
                 by_shape: bool = False) -> None:
        self.fn, self.name, self.batched, self.outputs = fn, name, batched, outputs
        self.static_argnums, self.by_shape = tuple(static_argnums), by_shape
        self._compiled: dict[Any, Any] = {}
        register(self, weakly=True)                  # ``clear_caches`` empties it

    def clear(self) -> None:
        """Forget this function's programs (``runtime.clear_caches``)."""
        self._compiled.clear()

    def __call__(self, *args: Any) -> Any:
        fn, args, signature = self._split(args)
        program = self._compiled.get(signature)
        if program is None:
            program = compile_program(fn, args, name=self.name, batched=self.batched,
                                      outputs=self.outputs, by_shape=self.by_shape)
            self._compiled[signature] = program
        return program(*args)

    def ahead(self, *args: Any) -> None:
        """Start compiling (or loading) the program for these arguments' shapes in the
        background (``compile_ahead``); a later call with such arguments takes it over."""
        fn, args, signature = self._split(args)
        if signature not in self._compiled:
            compile_ahead(fn, args, name=self.name, batched=self.batched,
                          outputs=self.outputs, by_shape=self.by_shape)

    def _split(self, args: tuple) -> tuple[Callable, tuple, tuple]:
        """The function of the dynamic arguments (the static ones bound), those
        arguments, and their signature (pytree, shapes, dtypes, devices, static values)."""
        fn, static = self.fn, ()
        if self.static_argnums:
            static = tuple(args[i] for i in self.static_argnums)
            fn = functools.partial(_with_static, self.fn, self.static_argnums, static)
            args = tuple(a for i, a in enumerate(args) if i not in self.static_argnums)
        leaves, tree = jax.tree.flatten(args)
        # A jax.Array by its sharding (its devices; half the time of listing their ids).
        return fn, args, (tree, tuple(
            (x.shape, x.dtype.str, x.sharding) if isinstance(x, jax.Array) else
            (np.shape(x), (x.dtype if hasattr(x, "dtype") else np.result_type(x)).str,
             isinstance(x, float | int))
            for x in leaves), static)


def _with_static(fn: Callable, positions: tuple[int, ...], values: tuple,
                 *dynamic: Any) -> Any:
    """``fn`` called with the static ``values`` put back at ``positions`` among ``dynamic``."""
    args, rest = [], iter(dynamic)
    for i in range(len(positions) + len(dynamic)):
        args.append(values[positions.index(i)] if i in positions else next(rest))
    return fn(*args)


def cached_jit(fn: Callable | None = None, *, name: str = "",
               batched: Sequence[bool] | None = None, outputs: int = 1,
               static_argnums: tuple[int, ...] = (), by_shape: bool = False) -> Any:
    """``CachedProgram(fn)``; also a decorator (``@cached_jit`` or ``@cached_jit(name=…)``)."""
    if fn is None:
        return functools.partial(cached_jit, name=name, batched=batched, outputs=outputs,
                                 static_argnums=static_argnums, by_shape=by_shape)
    return CachedProgram(fn, name=name, batched=batched, outputs=outputs,
                         static_argnums=static_argnums, by_shape=by_shape)
