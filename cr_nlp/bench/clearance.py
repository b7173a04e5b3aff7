"""Benchmark: batched clearance of many configurations against a scene (JAX).

``cr-nlp bench clearance`` prints a table of configurations per second for
``clearance(robot, arrays, q)`` over a batch of random configurations drawn inside the
limits (fixed seed): compile time (first call) apart from steady state, a warm-up call,
``block_until_ready`` before every clock stop, the median (and range) of repeated runs,
and the versions, device and core count. The batch is sharded over all host devices:
call ``use_host_devices`` (or run through the ``cr-nlp bench clearance`` command, which
does) before JAX starts, so XLA's CPU backend gets one device per core.
"""

from __future__ import annotations

import contextlib
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..model import load_robot
from ..runtime import split_over_devices, use_host_devices
from ._common import (
    Column,
    environment,
    environment_markdown,
    fixed,
    markdown_table,
    write_report,
)


@dataclass(frozen=True)
class ClearanceBenchRow:
    """One measured line of the table (times in seconds)."""

    scene: str
    parts: int
    configs: int
    dtype: str
    devices: int
    compile_s: float
    median_s: float
    min_s: float
    max_s: float

    @property
    def configs_per_s(self) -> float:
        return self.configs / self.median_s


def bench_clearance(robot: str = "tdcr3", scene: str = "lattice", configs: int = 100_000,
                    dtype: str = "float32", repeats: int = 7, seed: int = 0) -> ClearanceBenchRow:
    """Time ``clearance`` on ``configs`` random configurations of ``robot`` in ``scene``
    (bundled names or file paths), sharded over all JAX devices."""
    import jax
    import jax.numpy as jnp

    from ..model.robot import Robot
    from ..world.clearance import clearance, scene_arrays
    from ..world.scene import load_scene

    # float64 needs JAX's x64: on for this measurement only, so the process's other JAX
    # arrays keep the user's default dtype afterwards.
    with jax.enable_x64(True) if dtype == "float64" else contextlib.nullcontext():
        rob = load_robot(robot)
        world = load_scene(scene)
        float_type = {"float32": jnp.float32, "float64": jnp.float64}[dtype]
        arrays = scene_arrays(world, float_type)
        lo, hi = Robot.q_bounds(rob)
        devices = jax.devices()
        batch = configs - configs % len(devices)   # equal shards
        qs = np.random.default_rng(seed).uniform(lo, hi, (batch, rob.dof))
        # Each device evaluates its slice of the batch with the scene replicated.
        sharded = split_over_devices(lambda a, q: clearance(rob, a, q), (False, True), batch)
        q_all = jnp.asarray(qs, float_type)

        def run() -> Any:
            return sharded(arrays, q_all).block_until_ready()

        start = time.perf_counter()
        run()
        compile_s = time.perf_counter() - start
        run()  # warm-up: first run after compiling still touches fresh buffers
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
        return ClearanceBenchRow(scene=world.name, parts=arrays.n_parts, configs=batch,
                                 dtype=dtype, devices=len(devices), compile_s=compile_s,
                                 median_s=statistics.median(times), min_s=min(times),
                                 max_s=max(times))


COLUMNS = (
    Column("scene", "scene"), Column("parts", "parts"), Column("configs", "configs"),
    Column("dtype", "dtype"), Column("devices", "devices"),
    Column("compile_s", "compile s", fixed(3)), Column("median_s", "median s", fixed(4)),
    Column("min_s", "min s", fixed(4)), Column("max_s", "max s", fixed(4)),
    Column("configs_per_s", "configs/s"),
)


def _row_dict(row: ClearanceBenchRow) -> dict[str, Any]:
    return {**asdict(row), "configs_per_s": row.configs_per_s}


def format_table(rows: list[ClearanceBenchRow], env: dict[str, str], robot: str = "tdcr3",
                 repeats: int = 7) -> str:
    """The Markdown report: the table, how it was measured, the environment."""
    return "\n\n".join([
        f"# Clearance benchmark ({robot})",
        markdown_table([_row_dict(r) for r in rows], COLUMNS),
        "Random configurations inside the limits (seed 0); compile: the first call; "
        f"median, min and max of {repeats} runs after a warm-up; the batch is sharded over "
        "the JAX devices.",
        "## Environment", environment_markdown(env)])


def run_clearance_benchmark(robot: str = "tdcr3", scenes: tuple[str, ...] = ("lattice",),
                            configs: int = 100_000, dtypes: tuple[str, ...] = ("float32",),
                            repeats: int = 7, out: str | Path | None = "bench_results/clearance",
                            echo: bool = True) -> list[ClearanceBenchRow]:
    """Run the benchmark for every scene × dtype; print the Markdown report and, with
    ``out``, write clearance.md, clearance.csv and environment.json there."""
    rows = [bench_clearance(robot, s, configs, d, repeats) for s in scenes for d in dtypes]
    env = environment()
    write_report("clearance", format_table(rows, env, robot, repeats), out,
                 {"clearance": [_row_dict(r) for r in rows]}, env, echo=echo)
    return rows


if __name__ == "__main__":
    use_host_devices()
    run_clearance_benchmark()
