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
cost). The clusters of every worker count are up together and the runs interleaved
(each repeat runs every row once), so a change of the machine's load during the
benchmark shifts every row alike. Steady state: the cluster is up and each worker holds
its solver; starting a ``LocalCluster``, which ``cr-nlp batch --workers N`` does per
call, is in no row. Columns: seconds, targets per second, success, the largest pose
error of the successes, whether a batch row succeeded on exactly the targets the
in-process solve did, the speedup over one worker and the cost relative to the
in-process solve.
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
    started = time.perf_counter()
    scratch = Path(tempfile.mkdtemp(prefix="cr_nlp_bench_batch_"))
    runs = iter(range(10**9))
    solver = IKSolver(robot_model, None, config)
    key = solver_key("ik", robot_model, None, config)
    clients = {count: start_local_cluster(count, quiet=not progress) for count in workers}
    runners: dict[tuple[str, int | None], Any] = {}  # (mode, workers or None): a timed call
    for mode in modes:
        exact = mode == "exact"
        runners[mode, None] = lambda exact=exact: solver.solve(*inputs, exact=exact)
        for count, client in clients.items():

            def job(exact: bool = exact, client: Any = client, size: int = chunks[mode, count]):
                return run_batch("ik", robot_model, inputs, out_dir=scratch / str(next(runs)),
                                 exact=exact, config=config, client=client, chunk=size,
                                 progress=progress)

            runners[mode, count] = job
    try:
        # Warm-up (first run s): solver builds and compiles or cache loads on every worker.
        first: dict[tuple[str, int | None], float] = {}
        for (mode, count), call in runners.items():
            if progress:
                print(f"bench batch: warm-up, {mode}, {count or 'in-process'}", file=sys.stderr)
            t0 = time.perf_counter()
            if count is None:
                call()
            else:
                _warm_workers(clients[count], key, call)
            first[mode, count] = time.perf_counter() - t0
        # Timed runs interleaved (each repeat runs every row once), so that a change of
        # the machine's load during the benchmark shifts every row alike.
        times: dict[tuple[str, int | None], list[float]] = {k: [] for k in runners}
        results: dict[tuple[str, int | None], Any] = {}
        for repeat in range(repeats):
            for (mode, count), call in runners.items():
                if progress:
                    print(f"bench batch: run {repeat + 1}/{repeats}, {mode}, "
                          f"{count or 'in-process'}", file=sys.stderr)
                t0 = time.perf_counter()
                results[mode, count] = call()
                times[mode, count].append(time.perf_counter() - t0)
    finally:
        solver.close()
        for client in clients.values():
            close_cluster(client)
    rows: list[dict[str, Any]] = []
    for mode, count in runners:
        result = results[mode, count]
        if count is None:
            rows.append(_row(mode, "in-process", None, None, first[mode, count],
                             times[mode, count], result))
            continue
        row = _row(mode, f"batch, {count} workers", count, chunks[mode, count],
                   first[mode, count], times[mode, count], result)
        row["same_success"] = bool(np.array_equal(result.success, results[mode, None].success))
        rows.append(row)
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
