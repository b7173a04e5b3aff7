"""The local Dask cluster of a batch job (``cr_nlp.batch``): its worker processes' share
of the cores as JAX host devices, the lighter diagnostics they run with, where it listens
and the warning when other machines can reach it.
"""

from __future__ import annotations

import copy
import os
import sys
import warnings
from typing import Any

from ._batch_files import BatchError

PRE_SPAWN = "distributed.nanny.pre-spawn-environ"
"""Dask's config of the environment its nannies set before spawning a worker process."""
QUIET_WORKERS = {
    "distributed.worker.profile.enabled": False,
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.tick.interval": "500ms",
    "distributed.admin.system-monitor.interval": "5s",
}
"""Dask settings of the scheduler and workers that ``start_local_cluster`` starts. A
chunk is seconds of CPU-bound work in one worker thread, and Dask's defaults spend CPU
beside it: the statistical profiler takes the GIL to sample every thread's stack 100
times a second, the event loop ticks every 20 ms and the system and memory monitors poll
every 0.5 and 0.1 s (idle, measured: 4 % of a core per worker and 6 % for the scheduler
with the defaults, 0.4 % and 1 % with these)."""
DEVICES_ENV = "CR_NLP_BATCH_DEVICES"
"""Environment variable of a worker process: JAX host devices for its solver (set by
``start_local_cluster``: the cores divided among the workers)."""


LOCAL_HOST = "127.0.0.1"
"""Where ``start_local_cluster`` listens by default: this machine only."""



class ExposedClusterWarning(UserWarning):
    """A local cluster asked to listen on an address other machines can reach."""



def worker_env(workers: int) -> dict[str, str]:
    """Environment of one of ``workers`` local worker processes: its share of the usable
    cores as JAX host devices (at least one), also in ``XLA_FLAGS`` (which it would
    otherwise inherit from this process, set for all the cores); programs optimised fully
    at once (a batch is a large job: ``cr_nlp._compile_effort``) unless
    ``$CR_NLP_COMPILE`` says otherwise."""
    devices = max(1, len(os.sched_getaffinity(0)) // workers)
    flags = [
        f
        for f in os.environ.get("XLA_FLAGS", "").split()
        if not f.startswith("--xla_force_host_platform_device_count")
    ]
    flags.append(f"--xla_force_host_platform_device_count={devices}")
    return {DEVICES_ENV: str(devices), "XLA_FLAGS": " ".join(flags),
            "CR_NLP_COMPILE": os.environ.get("CR_NLP_COMPILE", "full")}


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name) is reachable from this machine only: a
    loopback address, or a name that resolves to loopback addresses only ("localhost")."""
    import ipaddress
    import socket

    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        pass
    if not host:  # "" is every interface
        return False
    try:
        found = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except OSError:
        return False
    return bool(found) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in found)


def exposure_warning(host: str) -> str | None:
    """The warning for a local cluster listening on ``host``, None for a loopback host."""
    if is_loopback(host):
        return None
    where = host or "every interface"
    return (
        f"the Dask cluster listens on {where}: its scheduler, workers and dashboard are "
        f"reachable from the network, and a Dask scheduler runs whatever code a client "
        f"sends it (use --host 127.0.0.1 unless other machines must connect)"
    )


def start_local_cluster(
    workers: int | None = None, quiet: bool = False, host: str = LOCAL_HOST
) -> Any:
    """A ``distributed.Client`` on a new ``LocalCluster`` of ``workers`` worker processes
    (default one per usable core), one thread each; each worker's JAX gets the cores
    divided among the workers as host devices. Prints the dashboard address on stderr
    unless ``quiet``. Close both with ``close_cluster(client)``.

    The scheduler, its dashboard, the nannies and the workers listen on ``host`` (default
    127.0.0.1: this machine only; Dask's own default puts the dashboard on every
    interface). Another host issues an ``ExposedClusterWarning`` (``exposure_warning``).

    The workers start without Dask's default ``MALLOC_TRIM_THRESHOLD_=65536``: setting it
    turns off glibc's adaptive mmap threshold, so every array over 128 KiB is mapped
    afresh and page-faulted in (measured: 17 000 page faults per 1000-target penalty
    solve against ~0, 7–40 % more CPU time; 12 700 per 100 exact targets). Its
    scheduler and workers also run with ``QUIET_WORKERS``' lighter diagnostics (no
    statistical profiler; the dashboard's other pages remain)."""
    import dask
    import distributed
    from distributed import Client

    cores = len(os.sched_getaffinity(0))
    workers = int(workers or cores)
    if workers < 1:
        raise BatchError(f"workers must be at least 1, got {workers}")
    message = exposure_warning(host)
    if message is not None:
        warnings.warn(message, ExposedClusterWarning, stacklevel=2)
    # Dask wants an IPv6 host in brackets, and splits a dashboard "HOST:PORT" at every
    # colon (an IPv6 dashboard address as a pair, without them).
    address = host.strip("[]")
    ipv6 = ":" in address
    # Read when the scheduler and the nannies are made (here).
    with dask.config.set({f"{PRE_SPAWN}.MALLOC_TRIM_THRESHOLD_": None, **QUIET_WORKERS}):
        cluster = distributed.LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host=f"[{address}]" if ipv6 else address,
            dashboard_address=(address, 0) if ipv6 else f"{address}:0",
            env=worker_env(workers),
            # The nanny sets this config in every worker process it starts, also when it
            # restarts a dead one after this block has restored the defaults (without it,
            # measured: the replacement ran with the profiler). A copy of all of
            # "distributed": the live dict is restored in place, and a partial one would
            # replace the whole section in the worker.
            config={"distributed": copy.deepcopy(dask.config.get("distributed"))},
        )
    client = Client(cluster)
    if not quiet:
        import importlib.util

        note = "" if importlib.util.find_spec("bokeh") else " (install bokeh to view it)"
        print(
            f"Dask LocalCluster: {workers} workers; dashboard {client.dashboard_link}{note}",
            file=sys.stderr,
        )
    return client


def close_cluster(client: Any) -> None:
    """Close ``client`` and the ``LocalCluster`` it was started with
    (``start_local_cluster``), without the workers' shutdown chatter on stderr."""
    import logging

    cluster = getattr(client, "cluster", None)
    logger = logging.getLogger("distributed")
    level = logger.level
    logger.setLevel(logging.CRITICAL)  # heartbeats that meet a closed scheduler
    try:
        client.close()
        if cluster is not None:
            cluster.close()
    finally:
        logger.setLevel(level)
