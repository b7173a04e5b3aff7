"""Process-wide JAX settings that cr_nlp's entry points apply."""

from __future__ import annotations

import os
from pathlib import Path

import jax


def cache_dir() -> Path:
    """Where cr_nlp keeps its caches ($CR_NLP_CACHE_DIR, else ~/.cache/cr_nlp)."""
    root = os.environ.get("CR_NLP_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "cr_nlp"


def enable_compilation_cache() -> None:
    """Turn on JAX's persistent compilation cache, unless the user configured one already.

    A second process then loads the solvers' compiled code instead of recompiling it.
    """
    if jax.config.jax_compilation_cache_dir:
        return
    path = Path(os.environ.get("CR_NLP_JAX_CACHE", cache_dir() / "jax"))
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


def use_host_devices(count: int | None = None) -> bool:
    """Ask XLA for ``count`` CPU devices (default: the usable cores) so a sharded batch
    runs on every core. Must run before the first JAX operation; returns False (and
    changes nothing) if JAX has already started. Harmless on a GPU: the solvers shard
    over whatever ``jax.devices()`` returns."""
    count = int(count or len(os.sched_getaffinity(0)))
    try:
        jax.config.update("jax_num_cpu_devices", count)
    except RuntimeError:  # JAX's backends are up: the device count is fixed
        return False
    # Measured with jax 0.10: ``jax_num_cpu_devices`` alone made the devices share one
    # thread; the XLA flag gives each its own, which is what uses the second core.
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={count}".strip()
    return True
