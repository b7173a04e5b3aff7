"""Seconds inside compiled programs, for the benchmarks' host share, and the callable a
compiled program is (``Flat``, made by ``_programs``).

The host share of a job is the wall time outside compiled programs: the Python and numpy
around them, python-fcl, file output. On a GPU that is what a user waits for while the
device idles. Inside ``timed_programs()`` every program call waits for its results and
adds its seconds to the clock. Waiting serialises what host and device would overlap, so
this is a benchmark's measure, not a mode for production runs. Programs that do not come
from ``_programs`` (a plain ``jax.jit``) count as outside; a benchmark names them.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import jax


@dataclass
class ProgramClock:
    """What ``timed_programs`` counted."""

    active: bool = False
    seconds: float = 0.0
    """Wall seconds from each program call until its results were ready."""
    calls: int = 0
    """Program calls counted."""


clock = ProgramClock()


@contextlib.contextmanager
def timed_programs() -> Iterator[ProgramClock]:
    """Count the seconds inside compiled programs while the block runs (not re-entrant);
    yields the clock, which keeps its counts after the block."""
    clock.seconds, clock.calls, clock.active = 0.0, 0, True
    try:
        yield clock
    finally:
        clock.active = False


class Flat:
    """A compiled program over its arguments' leaves, called with the arguments.
    ``movable``: XLA compiled it in this process (``_programs._moved`` can move it)."""

    def __init__(self, executable: Any, out_tree: Any, movable: bool = False) -> None:
        self.executable, self.out_tree, self.movable = executable, out_tree, movable

    def __call__(self, *args: Any) -> Any:
        if not clock.active:
            return jax.tree.unflatten(self.out_tree, self.executable(*jax.tree.leaves(args)))
        t0 = time.perf_counter()
        out = jax.block_until_ready(jax.tree.unflatten(
            self.out_tree, self.executable(*jax.tree.leaves(args))))
        clock.seconds += time.perf_counter() - t0
        clock.calls += 1
        return out
