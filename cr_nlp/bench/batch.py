"""``cr-nlp bench batch``: throughput of batch jobs on Dask (``cr_nlp.batch``) against
the single-process solver, on this machine.

Targets: tdcr3 (or ``--robot``) without obstacles, ``targets`` poses, each the forward
kinematics of a configuration drawn uniformly inside the limits (``bench.ik.free_case``).
For each mode (penalty: the JAX stages; exact: plus the Ipopt polish) the rows are

- "in-process": ``IKSolver.solve`` on all targets in this process (its JAX shards the
  batch over one host device per core, as ``cr-nlp ik`` does);
- "cr-nlp ik --out": what ``cr-nlp ik`` does with them in steady state: the same solve,
  then RESULT.json written as that command writes it (``IKResult.save``), since a
  batch row's time includes writing its ``results.json`` of the same schema;
- "batch, N workers": ``run_batch`` on a ``LocalCluster`` of N worker processes (one
  thread each; each worker's JAX gets the cores divided among the workers), with
  ``--chunk`` or else the chunk size ``cr-nlp batch ik`` picks for that mode and count;
- "N processes, no Dask": the machine's own ceiling for the same split, N plain
  processes (each with the worker's JAX device count) each solving 1/N of the targets
  with ``IKSolver.solve`` at the same time, no files. Its speedup over one such process
  is what any scheduler could reach here: on a shared virtual machine two busy
  processes can each run slower than one alone.

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

import multiprocessing
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..batch import (
    close_cluster,
    default_chunk,
    prepare_worker_process,
    run_batch,
    solver_key,
    start_local_cluster,
    worker_env,
)
from ..model import load_robot
from ..runtime import use_host_devices
from ..tasks.geometry.ik import IKConfig, IKSolver
from ._common import Column, environment, environment_markdown, markdown_table, write_report
from .ik import free_case
from .suites import BATCH_MODES

MODES = BATCH_MODES

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
    Column("speedup", "speedup vs 1 of its kind"),
    Column("vs_in_process", "time / in-process"),
    Column("vs_cli", "time / cr-nlp ik --out"),
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


@dataclass
class _Answers:
    """The parts of an ``IKResult`` a row reads, gathered from plain processes."""

    success: np.ndarray
    pose_error: np.ndarray

    def __len__(self) -> int:
        return len(self.success)


def _serve(robot: str, config: IKConfig, inputs: tuple[np.ndarray, np.ndarray],
           requests: Any, replies: Any) -> None:
    """A plain process of ``_PlainProcesses``, set up as a batch worker: solves the
    (start, stop, exact) slices it is sent until it gets None; replies (success, pose
    error)."""
    prepare_worker_process()
    solver = IKSolver(load_robot(robot), None, config)
    for start, stop, exact in iter(requests.get, None):
        result = solver.solve(inputs[0][start:stop], inputs[1][start:stop], exact=exact)
        replies.put((start, result.success, result.pose_error))
    solver.close()


class _PlainProcesses:
    """``count`` processes, started like local Dask workers (spawned, the cores divided
    among them), each solving its share of the targets when called: the two-process
    ceiling of the machine for the batch rows."""

    def __init__(self, count: int, robot: str, config: IKConfig,
                 inputs: tuple[np.ndarray, np.ndarray]) -> None:
        context = multiprocessing.get_context("spawn")
        self.count, self.targets = count, len(inputs[0])
        self.replies = context.Queue()
        self.requests = [context.Queue() for _ in range(count)]
        saved = dict(os.environ)
        os.environ.update(worker_env(count))
        try:
            self.processes = [context.Process(target=_serve, daemon=True, args=(
                robot, config, inputs, queue, self.replies)) for queue in self.requests]
            for process in self.processes:
                process.start()
        finally:
            os.environ.clear()
            os.environ.update(saved)

    def __call__(self, exact: bool) -> _Answers:
        bounds = np.linspace(0, self.targets, self.count + 1).astype(int)
        for queue, start, stop in zip(self.requests, bounds[:-1], bounds[1:], strict=True):
            queue.put((int(start), int(stop), exact))
        parts = sorted((self.replies.get() for _ in self.requests), key=lambda p: p[0])
        return _Answers(np.concatenate([p[1] for p in parts]),
                        np.concatenate([p[2] for p in parts]))

    def close(self) -> None:
        for queue in self.requests:
            queue.put(None)
        for process in self.processes:
            process.join(timeout=30)


CLI = "cr-nlp ik --out"
"""The runner label of ``cr-nlp ik``'s own work: solve, then write RESULT.json."""


def _solve_and_write(solver: IKSolver, inputs: tuple[np.ndarray, np.ndarray], exact: bool,
                     path: Path) -> Any:
    result = solver.solve(*inputs, exact=exact)
    result.save(path)
    return result


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
    ``environment.json`` to ``out``. Returns the rows (seconds, targets per second).

    Long: one measured session (in-process rows, then each cluster) over shared inputs.
    """
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
    plain = {count: _PlainProcesses(count, robot, config, inputs) for count in workers}
    # (mode, runner label): a timed call; labels name the runner kind and process count.
    runners: dict[tuple[str, str], Any] = {}
    kinds: dict[str, tuple[str, int | None]] = {"in-process": ("in-process", None),
                                                CLI: ("cli", None)}
    for mode in modes:
        exact = mode == "exact"
        runners[mode, "in-process"] = lambda exact=exact: solver.solve(*inputs, exact=exact)
        runners[mode, CLI] = lambda exact=exact: _solve_and_write(
            solver, inputs, exact, scratch / f"{next(runs)}.json")
        for count, client in clients.items():

            def job(exact: bool = exact, client: Any = client, size: int = chunks[mode, count]):
                return run_batch("ik", robot_model, inputs, out_dir=scratch / str(next(runs)),
                                 exact=exact, config=config, client=client, chunk=size,
                                 progress=progress)

            runners[mode, f"batch, {count} workers"] = job
            kinds[f"batch, {count} workers"] = ("batch", count)
        for count, processes in plain.items():
            runners[mode, f"{count} processes, no Dask"] = (
                lambda exact=exact, processes=processes: processes(exact))
            kinds[f"{count} processes, no Dask"] = ("processes", count)
    try:
        # Warm-up (first run s): solver builds and compiles or cache loads on every worker.
        first: dict[tuple[str, str], float] = {}
        for (mode, label), call in runners.items():
            if progress:
                print(f"bench batch: warm-up, {mode}, {label}", file=sys.stderr)
            t0 = time.perf_counter()
            kind, count = kinds[label]
            if kind == "batch":
                _warm_workers(clients[count], key, call)
            else:
                call()
            first[mode, label] = time.perf_counter() - t0
        # Timed runs interleaved (each repeat runs every row once), so that a change of
        # the machine's load during the benchmark shifts every row alike.
        times: dict[tuple[str, str], list[float]] = {k: [] for k in runners}
        results: dict[tuple[str, str], Any] = {}
        for repeat in range(repeats):
            for (mode, label), call in runners.items():
                if progress:
                    print(f"bench batch: run {repeat + 1}/{repeats}, {mode}, {label}",
                          file=sys.stderr)
                t0 = time.perf_counter()
                results[mode, label] = call()
                times[mode, label].append(time.perf_counter() - t0)
    finally:
        solver.close()
        for client in clients.values():
            close_cluster(client)
        for processes in plain.values():
            processes.close()
    rows: list[dict[str, Any]] = []
    for mode, label in runners:
        kind, count = kinds[label]
        result = results[mode, label]
        row = _row(mode, label, count, chunks[mode, count] if kind == "batch" else None,
                   first[mode, label], times[mode, label], result)
        row["kind"] = kind
        if kind != "in-process":
            row["same_success"] = bool(np.array_equal(result.success,
                                                      results[mode, "in-process"].success))
        rows.append(row)
    for row in rows:
        # Speedup over one process of the same kind (one Dask worker, one plain process).
        base = next((r for r in rows if r["mode"] == row["mode"] and r["kind"] == row["kind"]
                     and r["workers"] == 1), None)
        own = next(r for r in rows if r["mode"] == row["mode"] and r["kind"] == "in-process")
        row["speedup"] = (
            base["total_s"] / row["total_s"] if base is not None and row["workers"] else None
        )
        row["vs_in_process"] = row["total_s"] / own["total_s"]
        cli = next(r for r in rows if r["mode"] == row["mode"] and r["kind"] == "cli")
        row["vs_cli"] = row["total_s"] / cli["total_s"]
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
            'results.json; "cr-nlp ik --out" is the same solve plus writing RESULT.json as '
            "that command does.",
            markdown_table(rows, COLUMNS),
            "## Environment",
            environment_markdown(env),
        ]
    )
