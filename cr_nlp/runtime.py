"""Process-wide settings, in one place: where the caches live, the in-memory caches and
their ``clear_caches()``, the environment variables cr_nlp reads, JAX's persistent
compilation cache, matrix-product precision and host devices.

``import cr_nlp`` changes none of them; ``configure()`` does, once, when a solver is
built or a command runs (every task solver, ``solve_statics``, ``calibrate``, the CLI
and the batch workers call it). A user who set a precision or a compilation cache of
their own keeps it.
"""

from __future__ import annotations

import os
import sys
import weakref
from collections.abc import Callable, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar

# JAX is imported inside the functions that use it: ``import cr_nlp`` stays light.

ENVIRONMENT = {
    "CR_NLP_CACHE_DIR": "where cr_nlp keeps its caches (default ~/.cache/cr_nlp): traced "
                        "programs, XLA's code, compiled CasADi functions, convex parts, "
                        "roadmaps, Sobol pools",
    "CR_NLP_JAX_CACHE": "XLA's compilation cache alone (default $CR_NLP_CACHE_DIR/jax)",
    "CR_NLP_COMPILE": "how hard XLA optimises a program that no cache holds optimised: "
                      "auto (default; quickly on a CPU, optimised by a background process "
                      "for later runs), quick or full (see cr_nlp._compile_effort)",
    "CR_NLP_BATCH_DEVICES": "host devices of each Dask worker of a batch job (set by "
                            "cr_nlp for the workers it starts)",
    "CR_NLP_STARTUP_T": "process start time given to the start-up probe by "
                        "`cr-nlp bench startup` (set by the benchmark)",
}
"""Every environment variable cr_nlp reads, and what it means
(``tests/test_runtime.py`` checks that the package reads no other)."""

_CACHES: list[Any] = []
"""Every in-memory cache of the package (``cached`` functions, ``register``ed dicts)."""
_HELD: weakref.WeakSet = weakref.WeakSet()
"""Objects that keep caches of their own (``register(…, weakly=True)``), while they live."""

F = TypeVar("F", bound=Callable[..., Any])


def cached(maxsize: int | None = 128) -> Callable[[F], F]:
    """``functools.lru_cache(maxsize)``, registered for ``clear_caches``."""
    def wrap(fn: F) -> F:
        wrapped = lru_cache(maxsize=maxsize)(fn)
        _CACHES.append(wrapped)
        return wrapped  # type: ignore[return-value]
    return wrap


def register(cache: Any, weakly: bool = False) -> Any:
    """Register an in-memory cache (anything with ``clear()``) for ``clear_caches``;
    returns it. ``weakly``: only while something else keeps it (an object made per robot,
    e.g. ``_cached_jit.CachedProgram``)."""
    (_HELD.add if weakly else _CACHES.append)(cache)
    return cache


def clear_caches() -> int:
    """Empty every in-memory cache of cr_nlp (compiled programs, scenes, roadmaps, seed
    tables, …; the files on disk stay): the next solver builds and loads afresh. Returns
    how many caches were cleared."""
    held = list(_HELD)
    for cache in [*_CACHES, *held]:
        (cache.cache_clear if hasattr(cache, "cache_clear") else cache.clear)()
    return len(_CACHES) + len(held)


@lru_cache(maxsize=1)
def configure() -> None:
    """The process-wide settings a solve wants, applied once (later calls cost nothing):
    JAX's persistent compilation cache (``enable_compilation_cache``) and full float32
    matrix products (``full_precision_matmuls``), each unless the user set their own."""
    full_precision_matmuls()
    enable_compilation_cache()


def cache_dir() -> Path:
    """Where cr_nlp keeps its caches ($CR_NLP_CACHE_DIR, else ~/.cache/cr_nlp)."""
    root = os.environ.get("CR_NLP_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "cr_nlp"


def programs_dir() -> Path:
    """Where the traced programs are kept (``cache_dir()/programs``; ``cr_nlp._programs``)."""
    return cache_dir() / "programs"


def cached_arrays(path: Path | None, build: Callable[[], dict[str, Any]],
                  stats: dict[str, int], miss: str = "builds") -> tuple[dict[str, Any], bool]:
    """The named numpy arrays of the ``.npz`` file ``path`` where it is there and
    readable, else ``build()``'s, written there atomically (a concurrent reader never sees
    half a file; ``path`` None: built, not written); and whether they came from the file.
    ``stats`` counts ``"hits"`` and ``miss``. A damaged file is rebuilt and overwritten."""
    import io

    import numpy as np

    from ._files import write_atomic

    if path is not None and path.exists():
        try:
            with np.load(path) as data:
                out = {name: data[name] for name in data.files}
            stats["hits"] += 1
            return out, True
        except (OSError, KeyError, ValueError):
            pass
    out = build()
    stats[miss] += 1
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        buffer = io.BytesIO()
        np.savez(buffer, **out)
        write_atomic(path, buffer.getvalue())
    return out, False


def enable_compilation_cache() -> None:
    """Turn on JAX's persistent compilation cache, unless the user configured one already.

    A second process then loads the solvers' compiled code instead of recompiling it.
    """
    import jax

    _one_cache_entry_per_program()
    if jax.config.jax_compilation_cache_dir:
        return
    path = Path(os.environ.get("CR_NLP_JAX_CACHE", cache_dir() / "jax"))
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Every program, the small ones of eager operations too: a new process compiled ~30 of
    # them (10–40 ms each) before a first IK answer; loading one takes milliseconds.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def _one_cache_entry_per_program() -> None:
    """Key XLA's disk cache without the device assignment on every platform, as JAX does
    on GPUs: a program compiled for one host device is then loaded for another (JAX
    deserialises it with the caller's assignment) instead of compiled again. Each lane of
    the trajectory LM (one per host device) had compiled its own copy: a warm process
    found only the copies a cold one had compiled, and 13 s of XLA per missing copy.

    JAX has no setting for this: its private hash function is wrapped (once); a JAX
    without it keeps its own keys (one compile per device, as before)."""
    try:
        from jax._src import cache_key
    except ImportError:
        return
    original = getattr(cache_key, "_hash_serialized_compile_options", None)
    if original is None or getattr(original, "cr_nlp_strips", False):
        return

    def hashed(hash_obj: Any, options: Any, strip_device_assignment: bool = False) -> Any:
        return original(hash_obj, options, strip_device_assignment=True)

    hashed.cr_nlp_strips = True  # type: ignore[attr-defined]
    cache_key._hash_serialized_compile_options = hashed


def full_precision_matmuls() -> bool:
    """Make float32 matrix products full float32 (JAX's "highest" precision) unless the
    user chose a precision (``JAX_DEFAULT_MATMUL_PRECISION`` or ``jax.config``).

    JAX's default on NVIDIA GPUs computes float32 products in TF32 (a 10-bit mantissa,
    ~1e-3 relative): tip positions of a 1 m robot would be off by millimetres on a GPU
    and exact on a CPU. Returns whether it changed the setting; no effect on CPUs.

    Before JAX is imported this sets ``JAX_DEFAULT_MATMUL_PRECISION`` (which JAX reads
    when it starts, as do the processes this one starts), so it costs no JAX import.
    Called by ``configure``, never on import.
    """
    if "jax" not in sys.modules:
        if os.environ.get("JAX_DEFAULT_MATMUL_PRECISION"):
            return False
        os.environ["JAX_DEFAULT_MATMUL_PRECISION"] = "highest"
        return True
    import jax

    if jax.config.jax_default_matmul_precision is not None:
        return False
    jax.config.update("jax_default_matmul_precision", "highest")
    return True


def use_host_devices(count: int | None = None) -> bool:
    """Ask XLA for ``count`` CPU devices (default: the usable cores) so a sharded batch
    runs on every core. Must run before the first JAX operation; returns False (and
    changes nothing) if JAX has already started. Harmless on a GPU: the solvers shard
    over whatever ``jax.devices()`` returns."""
    import jax

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


def split_over_devices(fn: Callable[..., Any], batched: Sequence[bool], batch_size: int,
                       outputs: int = 1) -> Callable[..., Any]:
    """``jax.jit(fn)`` with the batch split along axis 0 over every JAX device (one shard
    per CPU core with ``use_host_devices``, one per GPU on a multi-GPU machine).

    ``batched[i]`` says whether argument i is split (True) or passed whole to every
    device (False: scene arrays, shared settings); all ``outputs`` results are split.
    With one device, or a ``batch_size`` that is not a multiple of the device count
    (pad the batch to make it one), this is plain ``jax.jit(fn)``.

    Keep LAPACK calls (``jnp.linalg.solve``, ``cho_factor``) out of ``fn``: with jax 0.10
    on 2 CPU host devices a sharded batched solve never returned, nor did two unsharded
    programs with ``cho_factor`` running at once on the two devices (measured: 16 shelf
    trajectories each; one after the other they took 22 s).
    """
    import jax
    import numpy as np

    devices = jax.devices()
    if len(devices) == 1 or batch_size % len(devices):
        return jax.jit(fn)
    from jax.sharding import Mesh
    from jax.sharding import PartitionSpec as P

    mesh = Mesh(np.array(devices), ("batch",))
    split = P("batch")
    in_specs = tuple(split if b else P() for b in batched)
    out_specs = split if outputs == 1 else (split,) * outputs
    # Every output is split, so there is no replication for JAX to check; its check also
    # rejects a lax.cond on a sum over a vmapped batch (jax 0.10: an assertion in pvary),
    # which a shard's batch uses to skip work none of its cases needs.
    return jax.jit(jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs,
                                 check_vma=False))
