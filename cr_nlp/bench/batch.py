"""``cr-nlp bench batch``: throughput of batch jobs on Dask (``cr_nlp.batch``) against
the single-process solver, on this machine.

Targets: tdcr3 (or ``--robot``) without obstacles, ``targets`` poses, each the forward
kinematics of a configuration drawn uniformly inside the limits (``bench.ik.free_case``).
For each mode (penalty: the JAX stages; exact: plus the Ipopt polish) the rows are

- "in-process": ``IKSolver.solve`` on all targets in this process (its JAX shards the
  batch over one host device per core, as ``cr-nlp ik`` does);
- "batch, N workers": ``run_batch`` on a ``LocalCluster`` of N worker processes (one
  thread each; each worker's JAX gets the cores divided among the workers), with
  ``--chunk`` or else the chunk size ``cr-nlp batch ik`` picks for that mode and count.

Every row is timed after a warm-up run on the same cluster (the solvers built and their
programs compiled on every worker; compile excluded), as the median of ``repeats`` runs,
each into a fresh output folder (the chunk files and ``results.json`` are part of the
cost). Columns: seconds, targets per second, success, the largest pose error of the
successes, whether a batch row succeeded on exactly the targets the in-process solve did,
the speedup over one worker and the cost relative to the in-process solve.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._jax_setup import use_host_devices
from ..batch import close_cluster, default_chunk, run_batch, solver_key, start_local_cluster
from ..model import load_robot
from ..tasks.ik import IKConfig, IKSolver
from .common import Column, environment, environment_markdown, markdown_table, write_report
from .ik import free_case

MODES = ("penalty", "exact")
"""Penalty: the JAX stages only; exact: with the Ipopt polish of every answer."""

COLUMNS = [
    Column("mode", "mode"),
    Column("runner", "runner"),
    Column("workers", "workers"),
    Column("chunk", "chunk"),
    Column("targets", "targets"),
    Column("first_s", "first run s"),
    Column("total_s", "s (median)"),
    Column("per_second", "targets / s"),
    Column("success_pct", "success %"),
    Column("max_pose_error", "max pose error"),
    Column("same_success", "same successes as in-process"),
    Column("speedup", "speedup vs 1 worker"),
    Column("vs_in_process", "time / in-process"),
]


def _timed(call: Any, repeats: int, warm_up: Any = None) -> tuple[float, list[float], Any]:
    """Run ``warm_up`` (default: ``call``) once, then ``call`` ``repeats`` times;
    (first s, times, last out)."""
    t0 = time.perf_counter()
    out = (warm_up or call)()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = call()
        times.append(time.perf_counter() - t0)
    return first, times, out


def _row(
    mode: str,
    runner: str,
    workers: int | None,
    chunk: int | None,
    first: float,
    times: Sequence[float],
    result: Any,
) -> dict[str, Any]:
    total = statistics.median(times)
    return {
        "mode": mode,
        "runner": runner,
        "workers": workers,
        "chunk": chunk,
        "targets": len(result),
        "first_s": first,
        "total_s": total,
        "per_second": len(result) / total,
        "runs": len(times),
        "success_pct": 100.0 * float(result.success.mean()),
        "max_pose_error": float(result.pose_error[result.success].max(initial=0.0)),
        "min_s": min(times),
        "max_s": max(times),
    }


def _warm_workers(client: Any, key: str, call: Any, tries: int = 3) -> None:
    """Run ``call`` (a batch job) until every worker holds the solver ``key``: the timed
    runs then pay no solver build or compile on any worker."""
    for _ in range(tries):
        call()
        built = client.run(lambda: key in __import__("cr_nlp.batch").batch._SOLVERS)
        if all(built.values()):
            return


def run_batch_benchmark(
    robot: str = "tdcr3",
    targets: int = 1000,
    workers: Sequence[int] = (1, 2),
    modes: Sequence[str] = MODES,
    chunk: int | None = None,
    repeats: int = 1,
    seed: int = 0,
    out: str | Path | None = None,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Measure batch throughput; print the report, write ``batch.md``, ``batch.csv`` and
    ``environment.json`` to ``out``. Returns the rows (seconds, targets per second)."""
    use_host_devices()  # the in-process rows use every core, as the CLI does
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        raise ValueError(f"unknown modes {unknown}; choose from {MODES}")
    if repeats < 1 or targets < 1 or not workers or min(workers) < 1:
        raise ValueError("repeats, targets and every worker count must be at least 1")
    robot_model = load_robot(robot)
    case = free_case(robot_model, targets, seed)
    inputs = (case.positions, case.wxyz)
    config = IKConfig()
    # --chunk for every row, else what `cr-nlp batch ik` picks for that mode and worker count.
    chunks = {(m, n): int(chunk or default_chunk("ik", targets, n, m == "exact"))
              for m in modes for n in workers}
    rows: list[dict[str, Any]] = []
    started = time.perf_counter()
    scratch = Path(tempfile.mkdtemp(prefix="cr_nlp_bench_batch_"))
    runs = iter(range(10**9))

    solver = IKSolver(robot_model, None, config)
    reference: dict[str, np.ndarray] = {}  # in-process success flags per mode
    for mode in modes:
        exact = mode == "exact"
        if progress:
            print(f"bench batch: {mode}, in-process", file=sys.stderr)
        first, times, result = _timed(
            lambda exact=exact: solver.solve(*inputs, exact=exact), repeats
        )
        rows.append(_row(mode, "in-process", None, None, first, times, result))
        reference[mode] = result.success
    solver.close()

    key = solver_key("ik", robot_model, None, config)
    for count in workers:
        client = start_local_cluster(count, quiet=not progress)
        try:
            for mode in modes:
                if progress:
                    print(f"bench batch: {mode}, {count} workers", file=sys.stderr)

                size = chunks[mode, count]

                def job(mode: str = mode, client: Any = client, size: int = size) -> Any:
                    return run_batch(
                        "ik",
                        robot_model,
                        inputs,
                        out_dir=scratch / str(next(runs)),
                        exact=mode == "exact",
                        config=config,
                        client=client,
                        chunk=size,
                        progress=progress,
                    )

                first, times, result = _timed(
                    job, repeats, lambda job=job, client=client: _warm_workers(client, key, job)
                )
                row = _row(mode, f"batch, {count} workers", count, size, first, times, result)
                row["same_success"] = bool(np.array_equal(result.success, reference[mode]))
                rows.append(row)
        finally:
            close_cluster(client)
    for row in rows:
        base = next((r for r in rows if r["mode"] == row["mode"] and r["workers"] == 1), None)
        own = next(r for r in rows if r["mode"] == row["mode"] and r["workers"] is None)
        row["speedup"] = (
            base["total_s"] / row["total_s"] if base is not None and row["workers"] else None
        )
        row["vs_in_process"] = row["total_s"] / own["total_s"]
    env = environment()
    env["benchmark wall time"] = f"{time.perf_counter() - started:.0f} s"
    env["settings"] = (
        f"robot={robot}, targets={targets}, workers={list(workers)}, "
        f"chunk={', '.join(f'{c} ({m}, {n} workers)' for (m, n), c in chunks.items())}, "
        f"repeats={repeats}, seed={seed}, modes={list(modes)}"
    )
    write_report("batch", format_report(rows, env), out, {"batch": rows}, env)
    return rows


def format_report(rows: Sequence[dict[str, Any]], env: dict[str, str]) -> str:
    """The Markdown report: the table and the environment it was measured in."""
    return "\n\n".join(
        [
            "# Batch jobs on Dask: throughput (cr-nlp bench batch)",
            "Free targets (no obstacles), steady state after a warm-up on every worker "
            '(compile excluded); "first run s" is the warm-up (solver builds, compiles or '
            "cache loads on the workers). Batch rows include writing the chunk files and "
            "results.json.",
            markdown_table(rows, COLUMNS),
            "## Environment",
            environment_markdown(env),
        ]
    )
