"""``_program_clock``: the seconds inside compiled programs, which the benchmarks' host
share subtracts from the wall time."""

from __future__ import annotations

import time

import jax.numpy as jnp
import numpy as np

from cr_nlp._program_clock import timed_programs
from cr_nlp._programs import compile_program


def _work(x):
    for _ in range(20):
        x = jnp.sin(x @ x.T) @ x
    return x


def test_only_calls_inside_the_block_are_counted_and_waited_for() -> None:
    x = np.random.default_rng(0).normal(size=(300, 300)) / 300
    program = compile_program(_work, (x,), name="a test program")
    program(x).block_until_ready()
    with timed_programs() as clock:
        t0 = time.perf_counter()
        for _ in range(3):
            program(x)               # waited for inside the block: no result is pending
        wall = time.perf_counter() - t0
        time.sleep(0.05)             # host work: not counted
    assert clock.calls == 3
    assert 0.0 < clock.seconds <= wall
    program(x).block_until_ready()
    assert clock.calls == 3 and not clock.active
