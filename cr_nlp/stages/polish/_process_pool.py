"""Independent polishes in parallel over the cores: a process pool whose workers build
their polisher once.

The exact stage is CPU work (Ipopt, MUMPS, CasADi) of milliseconds to seconds per
problem and the problems are independent, so ``PolishPool`` spreads them over worker
processes (``spawn``: no JAX or CasADi state is forked). Each worker builds the polisher
it is given the recipe for once, on its first task, and keeps it (the compiled CasADi
functions come from the disk cache of ``stages.polish._compiled_functions``). Work goes out in
contiguous
chunks and comes back in input order, so a parallel run returns exactly what a serial
run returns: the same polisher settings on the same inputs.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from ...runtime import register

_WORKER: dict[str, Any] = register({})


def _initialise(build: Callable[..., Any], args: tuple[Any, ...]) -> None:
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    _WORKER["build"], _WORKER["args"] = build, args


def _run(task: Callable[..., Any], items: Sequence[Any]) -> list[Any]:
    if "polisher" not in _WORKER:
        _WORKER["polisher"] = _WORKER["build"](*_WORKER["args"])
    return [task(_WORKER["polisher"], *item) for item in items]


class PolishPool:
    """``workers`` processes, each with its own ``build(*args)`` polisher.

    Args:
        build: a module-level function returning the polisher (it must pickle).
        args: its arguments (robot, scene, settings: they must pickle).
        workers: processes; default the usable cores.
    """

    def __init__(self, build: Callable[..., Any], args: tuple[Any, ...],
                 workers: int | None = None) -> None:
        self.workers = int(workers or len(os.sched_getaffinity(0)))
        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        self._executor = ProcessPoolExecutor(
            self.workers, mp_context=multiprocessing.get_context("spawn"),
            initializer=_initialise, initargs=(build, args))

    def map(self, task: Callable[..., Any], items: Sequence[tuple[Any, ...]],
            progress: Any = None) -> list[Any]:
        """``[task(polisher, *item) for item in items]``, in order, over the workers in
        about 4 chunks per worker. ``progress``: a tqdm bar to advance per item."""
        items = list(items)
        if not items:
            return []
        size = max(1, -(-len(items) // (4 * self.workers)))
        chunks = [items[i:i + size] for i in range(0, len(items), size)]
        futures = [self._executor.submit(_run, task, chunk) for chunk in chunks]
        out: list[Any] = []
        for future, chunk in zip(futures, chunks, strict=True):
            out.extend(future.result())
            if progress is not None:
                progress.update(len(chunk))
        return out

    def close(self) -> None:
        """Stop the workers."""
        self._executor.shutdown(cancel_futures=True)

    def __enter__(self) -> PolishPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
