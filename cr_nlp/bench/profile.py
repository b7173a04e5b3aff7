"""Benchmark: where one warm IK solve's time goes, op by op (``cr-nlp bench profile``).

One ``IKSolver`` (default ``IKConfig``, no obstacles) solves ``targets`` free targets of
the robot once (compiling or loading its programs), three times more (the warm wall, their
median), then once under ``jax.profiler.trace``. The trace
(an XSpace file, read back with ``jax.profiler.ProfileData``) is summed per timeline: on a
GPU the device's streams, one row per kernel; on a CPU the XLA worker threads, one row
per compiled operation; and the host's Python (inclusive times of nested calls). A
timeline's busy time is the union of its events' intervals.

What it answers: whether a solve is bound by arithmetic (a few long kernels), by the
number of kernels (many short ones: launch latency, the host busy launching them) or by
the host's Python. The raw trace stays under ``<out>/trace`` for Perfetto or
TensorBoard. Seconds and milliseconds of wall time throughout.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..model import load_robot
from ._common import Column, environment, environment_markdown, fixed, markdown_table, write_report

TIMELINE_COLUMNS = [Column("timeline", "timeline", str), Column("events", "events"),
                    Column("busy_ms", "busy (ms)", fixed(1)),
                    Column("span_ms", "span (ms)", fixed(1)),
                    Column("busy_pct", "busy / traced wall (%)", fixed(1))]
"""The columns of the timelines table."""

OP_COLUMNS = [Column("timeline", "timeline", str), Column("name", "kernel or op", str),
              Column("count", "count"), Column("total_ms", "total (ms)", fixed(2)),
              Column("mean_us", "mean (µs)", fixed(1))]
"""The columns of the ops table."""


def kept_timeline(plane: str, line: str, names: Iterable[str]) -> bool:
    """The timelines summed: a device's streams, the CPU's XLA worker threads and the
    host's Python thread (the one whose events are Python frames, ``$file:line name``);
    the trace's other host threads are the profiler's and the runtime's own."""
    if plane.startswith("/device:"):
        return True
    return line.startswith("tf_XLAEigen") or any(n.startswith("$") for n in names)


def _solve_window(events: list[Any]) -> tuple[int, int] | None:
    """(start, end) ns of the longest Python frame named ``… solve`` among ``events`` (the
    host's Python timeline), None on other timelines: the rest of that timeline is the
    trace's own start and stop (stopping writes the trace: seconds)."""
    solves = [e for e in events if e.name.startswith("$") and e.name.endswith(" solve")]
    if not solves:
        return None
    longest = max(solves, key=lambda e: e.duration_ns)
    return longest.start_ns, longest.start_ns + longest.duration_ns


def busy_ms(starts: np.ndarray, ends: np.ndarray) -> float:
    """Length of the union of intervals [start, end) (ns), in ms: nested or overlapping
    events count once."""
    if not len(starts):
        return 0.0
    order = np.argsort(starts, kind="stable")
    starts, ends = starts[order], np.maximum.accumulate(ends[order])
    # A new run begins where an interval starts after every earlier one ended.
    new = np.concatenate([[True], starts[1:] > ends[:-1]])
    first = np.flatnonzero(new)
    last = np.concatenate([first[1:] - 1, [len(starts) - 1]])
    return float(np.sum(ends[last] - starts[first])) / 1e6


def summarise_trace(trace_dir: str | Path, top: int = 25
                    ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(timeline rows, op rows) of every XSpace file under ``trace_dir``: per kept
    timeline its event count, busy and span (ms); per timeline its ``top`` costliest
    event names (count, total ms, mean µs)."""
    from jax.profiler import ProfileData

    files = sorted(Path(trace_dir).rglob("*.xplane.pb"))
    if not files:
        raise FileNotFoundError(f"no *.xplane.pb under {trace_dir}: the trace was not written")
    timelines, ops = [], []
    for path in files:
        for plane in ProfileData.from_file(str(path)).planes:
            for line in plane.lines:
                per_name: dict[str, list[float]] = defaultdict(lambda: [0, 0.0])
                starts, ends = [], []
                events = list(line.events)
                window = _solve_window(events)
                for event in events:
                    if window and not window[0] <= event.start_ns <= window[1]:
                        continue   # the trace's own start and stop, not the solve
                    entry = per_name[event.name]
                    entry[0] += 1
                    entry[1] += event.duration_ns / 1e6
                    starts.append(event.start_ns)
                    ends.append(event.start_ns + event.duration_ns)
                if not starts or not kept_timeline(plane.name, line.name, per_name):
                    continue
                name = f"{plane.name} {line.name}"
                begin, end = np.array(starts, np.float64), np.array(ends, np.float64)
                timelines.append({"timeline": name, "events": len(starts),
                                  "busy_ms": busy_ms(begin, end),
                                  "span_ms": float(end.max() - begin.min()) / 1e6})
                costly = sorted(per_name.items(), key=lambda item: -item[1][1])[:top]
                ops += [{"timeline": name, "name": op[:100], "count": int(count),
                         "total_ms": total, "mean_us": 1e3 * total / count}
                        for op, (count, total) in costly]
    return timelines, ops


def profile_ik(robot: str, targets: int, seed: int, trace_dir: str | Path,
               top: int = 25) -> dict[str, Any]:
    """Trace one warm IK solve of ``targets`` free targets (see the module): the untraced
    warm wall (s, median of 3), the traced one, the success rate, and the summed trace."""
    import jax

    from ..tasks.geometry.ik import IKConfig, IKSolver
    from .ik import free_case

    model = load_robot(robot)
    solver = IKSolver(model, None, IKConfig(seed=seed))
    case = free_case(model, targets, seed, "throughput")
    solver.solve(case.positions, case.wxyz)
    walls = []
    for _ in range(3):
        begin = time.perf_counter()
        solver.solve(case.positions, case.wxyz)
        walls.append(time.perf_counter() - begin)
    with jax.profiler.trace(str(trace_dir)):
        begin = time.perf_counter()
        result = solver.solve(case.positions, case.wxyz)
        traced = time.perf_counter() - begin
    solver.close()
    timelines, ops = summarise_trace(trace_dir, top)
    for row in timelines:
        row["busy_pct"] = 100.0 * row["busy_ms"] / (1e3 * traced)
    return {"robot": model.name, "targets": targets, "wall_s": float(np.median(walls)),
            "traced_s": traced, "success": float(np.mean(result.success)),
            "timelines": timelines, "ops": ops}


def run_profile_benchmark(robot: str = "tdcr3", targets: int = 10_000, seed: int = 0,
                          top: int = 25, out: str | Path | None = None) -> dict[str, Any]:
    """``profile_ik`` into a report: prints it and writes profile.md, timelines.csv,
    ops.csv, environment.json and the raw trace (``trace/``) to ``out`` (a temporary
    folder without one)."""
    import shutil
    import tempfile

    if targets < 1 or top < 1:
        raise ValueError(f"targets and top must be at least 1, got {targets} and {top}")
    with tempfile.TemporaryDirectory() as scratch:
        trace_dir = Path(out) / "trace" if out is not None else Path(scratch)
        shutil.rmtree(trace_dir, ignore_errors=True)   # an earlier run's trace
        found = profile_ik(robot, targets, seed, trace_dir, top)
    env = environment()
    report = (f"## Where a warm IK solve's time goes ({found['robot']}, {targets} free "
              f"targets)\n\n"
              f"Warm solve {found['wall_s']:.3f} s (median of 3), traced "
              f"{found['traced_s']:.3f} s, {100 * found['success']:.1f} % verified; "
              f"backend {env.get('backend', '?')}.\n\n"
              "### Timelines\n\n" + markdown_table(found["timelines"], TIMELINE_COLUMNS)
              + f"\n\n### The costliest kernels and ops per timeline (top {top})\n\n"
              + markdown_table(found["ops"], OP_COLUMNS)
              + "\n\n## Notes\n\n- busy: the union of a timeline's events (nested events "
                "once); the python timeline's rows are inclusive times of nested calls.\n"
                "- Many short kernels with the device busy well under the traced wall: "
                "the solve is bound by launches, not arithmetic.\n\n"
              + "## Environment\n\n" + environment_markdown(env))
    write_report("profile", report, out, {"timelines": found["timelines"],
                                          "ops": found["ops"]}, env,
                 {"settings": {"robot": robot, "targets": targets, "seed": seed,
                               "top": top}})
    return found
