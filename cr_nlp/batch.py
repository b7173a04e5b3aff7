"""Offline batch jobs on Dask distributed: many IK targets or planning problems over a
cluster, on the PCC or the Cosserat model, written to disk chunk by chunk, resumable.

``run_batch(kind, robot, inputs, out_dir=...)`` splits the inputs into chunks; each chunk
is one Dask task that solves its problems with the single-process solver
(``IKSolver.solve`` or ``TrajectoryPlanner.plan``) on a worker. Scheduling, retries and
worker management are Dask's: a chunk whose worker dies is re-run by the scheduler, a
chunk that raises is retried (``retries``). Per worker process the solver is built once
(``_worker_solver``: a module-level cache keyed by kind, robot, scene and settings) and
its JAX programs come from the persistent compilation cache (``runtime``).

What lands in ``out_dir``:

- ``manifest.json``: what the job is (kind, robot, scene, exact, the solver config, a
  hash of robot, scene and settings, chunk size, problem count, a hash of the inputs)
  and a log of the runs: which chunk ids each run solved. ``resume=True`` refuses a
  directory whose manifest describes another job.
- ``chunk_<id>.npz``: one per finished chunk, written atomically (temporary file,
  fsync, ``os.replace``) as soon as it arrives; a chunk file is complete or absent.
  ``read_chunk`` reads one: ``{"chunk", "start", "stop", "run", "worker", "pid",
  "seconds", "timing"}`` and the answers: for IK the ``IKResult`` columns as arrays
  (``"columns"``, ``IKResult.columns``: q, position, wxyz, errors, flags, stage, reason),
  for planning the entries of ``cr-nlp plan --out`` (``"rows"``,
  ``TrajectoryResult.entry``). Arrays, not JSON rows: converting 1000
  IK answers to rows on the worker, to JSON, back and to rows again cost ~60 ms of CPU
  per job, a third of the penalty-mode solve itself.
- ``results.json``: assembled at the end from the chunk files, in input order: the
  RESULT.json of ``cr-nlp ik --out`` (kind "ik", ``IKResult.to_dict``) or ``cr-nlp plan
  --out`` (kind "trajectory", ``trajectories_to_dict``), readable by
  ``tasks.load_result``; its ``timing`` is the worker seconds summed over the chunks.

What differs between the kinds of job (solver, inputs, a chunk's answers, the results)
is in one adapter per kind and model (``_batch_kinds``). ``model="cosserat"`` runs the
tension tasks on the Cosserat rod (``TensionIKSolver.solve``, ``TensionTrajectoryPlanner.plan``)
under one load case (``loads``): chunks, files and resume as above, the manifest also
records the model and the loads (a resume under other loads is refused), and the results
are the ``cr-nlp ik|plan --model cosserat`` files (kinds "tension_ik",
"tension_trajectory").

This module is an interface (beside ``cli/``): it imports ``tasks/``, nothing imports it
but the CLI and the benchmarks.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._batch_cluster import DEVICES_ENV as DEVICES_ENV
from ._batch_cluster import LOCAL_HOST as LOCAL_HOST
from ._batch_cluster import PRE_SPAWN as PRE_SPAWN
from ._batch_cluster import QUIET_WORKERS as QUIET_WORKERS
from ._batch_cluster import ExposedClusterWarning as ExposedClusterWarning
from ._batch_cluster import close_cluster as close_cluster
from ._batch_cluster import exposure_warning as exposure_warning
from ._batch_cluster import is_loopback as is_loopback
from ._batch_cluster import start_local_cluster as start_local_cluster
from ._batch_cluster import worker_env as worker_env
from ._batch_files import MANIFEST as MANIFEST
from ._batch_files import MANIFEST_VERSION as MANIFEST_VERSION
from ._batch_files import RESULTS as RESULTS
from ._batch_files import BatchError as BatchError
from ._batch_files import chunk_file as chunk_file
from ._batch_files import chunk_ranges as chunk_ranges
from ._batch_files import digest, open_manifest, read_chunks, write_json
from ._batch_files import read_chunk as read_chunk
from ._batch_files import solver_key as solver_key
from ._batch_files import write_chunk as write_chunk
from ._batch_kinds import KINDS as KINDS
from ._batch_kinds import MODELS as MODELS
from ._batch_kinds import JobSpec as JobSpec
from ._batch_kinds import adapter
from ._signals import signals_held
from .runtime import register

# ================================================================ the job


def default_chunk(kind: str, count: int, slots: int, exact: bool = True,
                  model: str = "pcc") -> int:
    """Problems per chunk. Exact-mode IK: about two chunks per worker thread, at most 256
    targets; each chunk pays the solver's fixed costs per call, which outweighed finer
    load balancing (1000 exact tdcr3 targets on 2 workers, medians of 7, interleaved:
    chunks of 125 / 250 / 500 took 2.67 / 2.46 / 2.37 s against 4.22 s on one worker).
    Planning: about four chunks per worker thread (seconds per problem, more uneven), at
    most 8 problems. Penalty-mode IK (milliseconds per target, batched in JAX): one chunk
    per worker thread of at most 4096 targets (a chunk of 125 targets cost ~50 ms more
    than its share of one 1000-target call). The caps bound what a dying worker loses.
    Cosserat (``model``): IK about two chunks per worker thread of at most 256 targets
    (tenths of a second per target), planning as on PCC."""
    per_slot, largest = adapter(kind, model).chunking(exact)
    return int(min(largest, max(1, math.ceil(count / max(per_slot * slots, 1)))))


def _inputs_hash(spec: JobSpec, inputs: tuple[Any, Any],
                 problems: Sequence[str] | None) -> str:
    # No reasons and all-empty reasons are the same job (the API's None, the CLI's list).
    marks = [str(p) for p in problems] if problems and any(problems) else []
    return spec.jobs.inputsdigest(inputs, marks)


# ================================================================ on the worker

_SOLVERS: dict[str, Any] = register({})
_SOLVERS_LOCK = threading.Lock()


def prepare_worker_process() -> None:
    """JAX in a local worker process, before its first solver: the host devices
    ``start_local_cluster`` gave it (``DEVICES_ENV``; a no-op once JAX has started) and
    the persistent compilation cache."""
    from .runtime import configure, use_host_devices

    devices = os.environ.get(DEVICES_ENV)
    if devices:
        use_host_devices(int(devices))
    configure()


def _worker_solver(spec: JobSpec) -> Any:
    """This process's solver for ``spec`` (built on first use, then reused by every chunk
    with the same robot, scene and settings)."""
    with _SOLVERS_LOCK:
        solver = _SOLVERS.get(spec.key)
        if solver is None:
            prepare_worker_process()
            solver = spec.jobs.solver(spec)
            _SOLVERS[spec.key] = solver
    return solver


def solve_chunk(spec: JobSpec, index: int, first: Any, second: Any) -> dict[str, Any]:
    """Solve one chunk on this worker: IK targets (``first`` positions (k, 3) m, ``second``
    wxyz (k, 4)) or planning problems (``first`` starts, ``second`` goals: rad and m on
    PCC, tensions in N on the Cosserat rod).

    Returns the chunk's record: the answers in input order (IK: ``"columns"``, the
    ``IKResult`` / ``TensionIKResult`` fields as arrays, their ``columns``; planning:
    ``"rows"``, RESULT.json entries, ``TrajectoryResult.entry`` /
    ``TensionTrajectoryResult.entry``), the solver's stage seconds, the worker's address
    and pid. A PCC solver's random generator is reseeded from (seed, chunk index) (the
    Cosserat solvers have none: their seed pools come from the config's seed), so a
    chunk re-run after a failure or on resume gives the same answers. A problem that
    raises becomes a failed answer with its reason; the chunk itself raises only where
    Dask should retry it.
    """
    t0 = time.perf_counter()
    solver = _worker_solver(spec)
    if hasattr(solver, "_rng"):
        solver._rng = np.random.default_rng([spec.config.seed, index])
    kind = spec.jobs
    try:
        answers, timing = kind.solve(spec, solver, first, second)
    except Exception:  # one problem's error must not sink its neighbours: solve one by one
        parts, timing = [], {}
        for k in range(len(first)):
            try:
                one, one_timing = kind.solve(spec, solver, first[k : k + 1], second[k : k + 1])
            except Exception as exc:
                one = kind.failed(spec, 1, f"solver raised {type(exc).__name__}: {exc}")
                one_timing = {}
            parts.append(one)
            for key, value in one_timing.items():
                timing[key] = timing.get(key, 0.0) + value
        answers = kind.join(parts)
    try:
        from distributed import get_worker

        worker = get_worker().address
    except (ImportError, ValueError):  # called outside a Dask worker
        worker = ""
    return {
        "chunk": index,
        kind.answers: answers,
        "timing": timing,
        "worker": worker,
        "pid": os.getpid(),
        "seconds": time.perf_counter() - t0,
    }


# ================================================================ the job on the client


def run_batch(kind: str, robot: Any, inputs: tuple[Any, Any], *, out_dir: str | Path,
              scene: Any = None, exact: bool = False, config: Any = None, init: str = "roadmap",
              problems: Sequence[str] | None = None, model: str = "pcc",
              loads: dict[str, Any] | None = None, time_limit: float | None = None,
              client: Any = None, workers: int | None = None, scheduler: str | None = None,
              host: str | None = None, chunk: int | None = None, resume: bool = False,
              progress: bool = True, retries: int = 2) -> Any:
    """Solve many IK targets or planning problems on Dask, chunk by chunk, into ``out_dir``.

    Args:
        kind: "ik" or "plan".
        robot: a ``Robot``, robot file or bundled name.
        inputs: ik: (positions (T, 3) m, wxyz (T, 4) unit quaternions; Cosserat: NaN rows
            or None for position-only targets); plan: (starts, goals), PCC: rows θ, φ, L
            (rad, rad, m; fixed lengths may be omitted; a bad row is a failed result),
            Cosserat: (B, n) tensions in N.
        out_dir: folder of the manifest, the chunk files and ``results.json``.
        scene: a ``Scene``, scene file or bundled name, or None.
        exact: polish every answer with Ipopt (as ``cr-nlp ik/plan --exact``).
        config: ``IKConfig`` / ``TrajectoryConfig``, Cosserat ``TensionIKConfig`` /
            ``TensionTrajectoryConfig`` (default: the solver's defaults).
        init: planning: "roadmap" or "straight".
        problems: ik: a reason per target read badly from its file ("" where fine), as
            ``read_targets`` returns; it replaces the solver's reason in the results.
        model: "pcc" (configurations θ, φ, L) or "cosserat" (tendon tensions on the
            Cosserat rod, ``TensionIKSolver.solve`` / ``TensionTrajectoryPlanner.plan``: a
            robot with a ``mechanics`` block; ``exact`` for ik and plan).
        loads: Cosserat: the one load case of every problem, the solvers' keyword
            arguments (tip_force N, tip_moment N·m, gravity m/s², distributed_force N/m,
            world frame; point_loads ``[{"s": m, "force": [N], "moment": [N·m]}]``).
        time_limit: Cosserat with ``exact``: seconds of polishing per target or problem (PCC:
            the config's ``polish_time_limit``).
        client: a ``distributed.Client`` to run on. Else ``scheduler`` (the address of a
            running Dask scheduler), else a new ``LocalCluster`` of ``workers`` processes
            (default one per core), closed at the end.
        host: where that new ``LocalCluster`` listens (default 127.0.0.1, this machine
            only; another address warns that the cluster is reachable from the network).
        chunk: problems per chunk (one Dask task); default ``default_chunk``, or the
            manifest's on resume.
        resume: solve only the chunks missing from ``out_dir`` (the same job: refused
            with ``BatchError`` if the manifest differs). Without it, ``out_dir`` must not
            hold a job yet.
        progress: a progress bar (chunks, problems per second, time left) on stderr.
        retries: Dask retries of a chunk that raises (a dead worker's chunk is re-run by
            the scheduler regardless).

    Returns:
        ik: an ``IKResult`` (Cosserat: ``TensionIKResult``) over all targets; plan: a list
        of ``TrajectoryResult`` (``TensionTrajectoryResult``); in input order, the same
        objects as the single-process solvers return.

    Raises:
        BatchError: ``out_dir`` holds another job, or chunks failed after their retries
            (those written are kept: rerun with ``resume=True``), or the job cannot run
            (a Cosserat job for a robot without mechanics, ``exact`` for Cosserat plans).
    """
    spec, first, second = _job_spec(kind, robot, inputs, scene, exact, config, init, problems,
                                    (model, loads, time_limit), client, workers, scheduler,
                                    host)
    job = _job_entry(spec, first, second, problems)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if chunk is not None and chunk < 1:
        raise BatchError(f"chunk must be at least 1, got {chunk}")
    manifest = open_manifest(out, job, chunk, resume)

    own_client = None
    try:
        if client is None:
            client = own_client = _new_client(scheduler, workers, progress, host)
        if not manifest:
            slots = max(sum(client.nthreads().values()), 1)
            size = int(chunk or default_chunk(kind, job["count"], slots, exact, model))
            manifest = {**job, "chunk": size, "chunks": len(chunk_ranges(job["count"], size)),
                        "runs": []}
        _run_chunks(client, spec, out, manifest, first, second, progress, retries)
    finally:
        if own_client is not None:
            close_cluster(own_client)
    return _assemble(spec, out, manifest, problems)


def _new_client(scheduler: str | None, workers: int | None, progress: bool,
                host: str | None) -> Any:
    """A client of the Dask scheduler at ``scheduler``, or of a new local cluster
    (``start_local_cluster``): the one ``run_batch`` closes at the end."""
    if scheduler is not None:
        from distributed import Client

        return Client(scheduler)
    return start_local_cluster(workers, quiet=not progress, host=host or LOCAL_HOST)


def _job_spec(kind: str, robot: Any, inputs: tuple[Any, Any], scene: Any, exact: bool,
              config: Any, init: str, problems: Sequence[str] | None,
              mechanics: tuple[str, dict[str, Any] | None, float | None], client: Any,
              workers: int | None, scheduler: str | None,
              host: str | None) -> tuple[JobSpec, Any, Any]:
    """``run_batch``'s arguments checked (``BatchError`` where they cannot run) and
    loaded: the job's ``JobSpec`` and its inputs, normalised by the kind's adapter
    (``mechanics``: the model, the loads and the Cosserat time limit)."""
    from .model import load_robot
    from .world import load_scene

    model, loads, time_limit = mechanics
    jobs = adapter(kind, model)
    if sum(x is not None for x in (client, workers, scheduler)) > 1:
        raise BatchError("give at most one of client, workers and scheduler")
    if host is not None and (client is not None or scheduler is not None):
        raise BatchError("host is where a new local cluster listens: not with client or scheduler")
    robot = load_robot(robot)
    loads = jobs.settings(robot, exact, loads, time_limit)
    scene = load_scene(scene) if isinstance(scene, (str, Path, dict)) else scene
    try:
        first, second = inputs
    except (TypeError, ValueError):
        raise BatchError(
            "inputs must be a pair: (positions, wxyz) for ik, (starts, goals) for plan"
        ) from None
    first, second = jobs.normalise(first, second)
    if problems is not None and len(problems) != len(first):
        raise BatchError(f"{len(problems)} problems for {len(first)} inputs")
    if config is None:
        config = jobs.default_config()
    if init not in ("roadmap", "straight"):
        raise BatchError(f"init must be 'roadmap' or 'straight', got {init!r}")
    key = solver_key(f"{model}:{kind}" if model != "pcc" else kind, robot, scene, config)
    spec = JobSpec(kind, robot, scene, config, bool(exact), init, key, model, loads,
                   None if time_limit is None else float(time_limit))
    return spec, first, second


def _job_entry(spec: JobSpec, first: Any, second: Any,
               problems: Sequence[str] | None) -> dict[str, Any]:
    """What the job is, as its manifest records it (a resume must match it)."""
    return {
        "version": MANIFEST_VERSION,
        "kind": spec.kind,
        "robot": spec.robot.name,
        "scene": getattr(spec.scene, "name", None),
        "exact": spec.exact,
        "init": spec.init if spec.jobs.uses_init else None,
        "config": json.loads(json.dumps(dataclasses.asdict(spec.config))),
        "settings": digest((spec.key, spec.init)),  # robot, scene and config contents
        "count": len(first),
        "inputs": _inputs_hash(spec, (first, second), problems),
        **spec.jobs.manifest_fields(spec),  # Cosserat: the model and the loads
    }


def _run_chunks(
    client: Any,
    spec: JobSpec,
    out: Path,
    manifest: dict[str, Any],
    first: Any,
    second: Any,
    progress: bool,
    retries: int,
) -> None:
    """Submit the missing chunks, write each one as it finishes, log the run."""
    from distributed import as_completed
    from tqdm.auto import tqdm

    ranges = chunk_ranges(manifest["count"], manifest["chunk"])
    missing = [i for i in range(len(ranges)) if read_chunk(chunk_file(out, i)) is None]
    run_id = len(manifest["runs"]) + 1
    run = {
        "run": run_id,
        "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "missing": len(missing),
        "solved": [],
        "failed": [],
    }
    manifest["runs"].append(run)
    write_json(out / MANIFEST, manifest)
    if not missing:
        return
    futures = _submit(client, spec, ranges, missing, first, second, retries,
                      f"{run_id}-{manifest['inputs'][:8]}")
    total = sum(ranges[i][1] - ranges[i][0] for i in missing)
    bar = tqdm(
        total=total,
        unit="problem",
        desc=f"batch {spec.kind}",
        disable=not progress,
        file=sys.stderr,
        smoothing=0.1,
    )
    done = 0
    bar.set_postfix_str(f"chunks 0/{len(missing)}")
    failed: list[str] = []
    t0 = time.perf_counter()
    try:
        for future in as_completed(list(futures)):
            i = futures[future]
            start, stop = ranges[i]
            try:
                record = future.result()
            except Exception as exc:  # after Dask's retries (or a worker killed repeatedly)
                failed.append(f"chunk {i}: {type(exc).__name__}: {exc}")
                run["failed"].append(i)
            else:
                record.update(start=start, stop=stop, run=run_id)
                with signals_held():  # a stop waits for the file (a half-written zip hides it)
                    write_chunk(chunk_file(out, i), record)
                run["solved"].append(i)
                done += 1
            future.release()
            run["seconds"] = time.perf_counter() - t0
            # The run log only (resume reads the chunk files): atomic, not flushed to disk.
            with signals_held():
                write_json(out / MANIFEST, manifest, sync=False)
            bar.update(stop - start)
            bar.set_postfix_str(f"chunks {done}/{len(missing)}")
    except KeyboardInterrupt:  # a stop (Ctrl-C, SIGTERM): the chunk files stay for resume
        run["stopped"] = True
        write_json(out / MANIFEST, manifest, sync=False)
        bar.close()
        raise
    bar.close()
    if failed:
        raise BatchError(
            f"{len(failed)} of {len(missing)} chunks failed (the others are "
            f"written in {out}; rerun with --resume): " + "; ".join(failed[:5])
        )


def _submit(client: Any, spec: JobSpec, ranges: list[tuple[int, int]], missing: list[int],
            first: Any, second: Any, retries: int, tag: str) -> dict[Any, int]:
    """One Dask task per missing chunk (``solve_chunk``), each with a key of its own
    (``tag``: the run and the inputs' hash); future → chunk id."""
    futures = {}
    for i in missing:
        start, stop = ranges[i]
        future = client.submit(
            solve_chunk,
            spec,
            i,
            first[start:stop],
            second[start:stop],
            retries=retries,
            pure=False,
            key=f"cr_nlp-chunk-{i}-{tag}-{os.getpid()}-{time.time_ns()}",
        )
        futures[future] = i
    return futures


# ================================================================ assembling the results


def _assemble(
    spec: JobSpec, out: Path, manifest: dict[str, Any], problems: Sequence[str] | None
) -> Any:
    """Read every chunk file, in input order, into the single-process result objects and
    write ``results.json``."""
    records, timing = read_chunks(out, manifest)
    kind = spec.jobs
    result, data = kind.assemble(spec, [r[kind.answers] for r in records], timing, problems)
    write_json(out / RESULTS, data)
    return result
