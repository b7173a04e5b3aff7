"""Compiled programs that a new process loads from disk instead of tracing them again.

JAX's persistent compilation cache keeps XLA's compiled code only: a new process still
traces and lowers every program before it can look that code up (measured on a 2-core
CPU: 2–3 s per IK search program, 7–10 s of a warm 13 s one-shot IK). ``compile_program``
traces a program once, serialises it with ``jax.export`` (StableHLO) into
``cache_dir()/programs``, and compiles the deserialised program, so every later process
(and every later solver of the same process) skips tracing and lowering; XLA's cache then
skips the compilation too.

An entry's key is everything that changes the program:

- the function and everything it closes over (``fingerprint``: robots and scenes by
  their numbers, frozen settings dataclasses field by field, functions by module,
  qualified name, code and closure);
- the arguments' pytree structure, shapes, dtypes and weak types;
- how the batch is split over devices, and the device kind and count;
- the cr_nlp source (a hash of the package's ``.py`` files), JAX's and jaxlib's versions,
  and the JAX settings that change a trace (x64, matmul precision, PRNG).

A function holding something ``fingerprint`` cannot key (an object it does not know) is
traced and compiled as before, never stored under a key that might be wrong. An entry
that cannot be read (truncated, corrupt, written by another JAX, or holding another
program's key) is ignored with a warning and traced again; its checksum makes a damaged
file fail before it is used.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import io
import os
import pickle
import sys
import threading
import time
import warnings
from collections import OrderedDict
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import numpy as np

from . import _compile_effort as _effort
from ._by_shape import ByShape, WithData, lift
from ._files import write_atomic
from ._fingerprint import Unkeyable, fingerprint
from ._program_clock import Flat as _Flat
from .runtime import cache_dir, programs_dir, register

FORMAT = b"cr_nlp-program-3\n"
"""First bytes of an entry: the file format (a change of format is a change of key too)."""
_MEMORY_SIZE = 16
"""Compiled programs kept in memory for later solvers of the same process. Few: XLA's CPU
code of one big program holds ~1 000 memory mappings (the IK search: 4 programs, 4 000),
and a process may hold 65 530 (Linux's vm.max_map_count); 128 programs exhausted them
in the test suite ("LLVM ERROR: Unable to allocate section memory")."""
SECONDS_PER_OP = 0.004
"""Rough XLA CPU compile seconds per StableHLO operation of a program, for the first-run
message before any compile time was measured on this machine (measured on a 2-core CPU:
the IK search program, ~4 000 operations, 15–20 s)."""

_memory: OrderedDict[str, Any] = register(OrderedDict())
_pending: dict[str, Future] = {}
"""Programs being compiled (``compile_ahead``), by the same key as ``_memory``."""
_queued: dict[str, tuple[Future, Callable[[], None]]] = {}
"""Programs asked for ahead whose build has not started: the background pool's future and
the build, which a thread that needs the program now takes over (``_requested``)."""
_lock = threading.Lock()
_tracing: dict[str, threading.Lock] = {}
"""Per disk key: held while a thread loads or traces that program."""


@dataclasses.dataclass
class ProgramStats:
    """What ``compile_program`` did in this process (for the start-up benchmark and tests)."""

    traced: int = 0
    """Programs traced and lowered (no usable entry on disk), then stored."""
    loaded: int = 0
    """Programs read from disk (no tracing)."""
    reused: int = 0
    """Programs reused from memory (an earlier solver of this process compiled them)."""
    moved: int = 0
    """Programs compiled for one device and moved to another (``_moved``), not compiled
    again."""
    unkeyed: int = 0
    """Programs traced without the disk cache (their function holds something unkeyable)."""
    unkeyable: list[str] = dataclasses.field(default_factory=list)
    """Why, for each of them: the program's name and the object that could not be keyed."""
    rejected: int = 0
    """Entries on disk that could not be read (ignored, traced again)."""
    trace_seconds: float = 0.0
    """Seconds spent tracing, lowering and serialising."""
    load_seconds: float = 0.0
    """Seconds spent reading and deserialising entries."""
    compile_seconds: float = 0.0
    """Seconds spent in XLA (compiling, or loading compiled code from its cache)."""


stats = ProgramStats()
"""This process's counts (reset with ``stats.__init__()``)."""

announce = True
"""Print a line on stderr before tracing and compiling a program that no cache holds."""


# ================================================================ keys

@functools.cache
def source_hash() -> str:
    """A hash of the installed cr_nlp package's source files (every ``.py`` under it): a
    program traced by other code is never loaded."""
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def environment_key() -> tuple:
    """What besides the program itself changes its compiled form: versions, device,
    JAX settings that change a trace."""
    import jaxlib

    device = jax.devices()[0]
    return (FORMAT, source_hash(), jax.__version__, jaxlib.__version__, device.platform,
            device.device_kind, jax.device_count(), jax.config.jax_enable_x64,
            str(jax.config.jax_default_matmul_precision), jax.config.jax_default_prng_impl)


def _avals(args: Sequence[Any]) -> tuple:
    """The arguments' pytree structure and each leaf's shape, dtype and weak type."""
    leaves, tree = jax.tree.flatten(tuple(args))
    out = []
    for leaf in leaves:
        aval = jax.typeof(leaf)
        out.append((aval.shape, str(aval.dtype), bool(getattr(aval, "weak_type", False))))
    return str(tree), tuple(out)


def program_key(fn: Callable, args: Sequence[Any], split: tuple | None = None) -> str:
    """The disk key of ``fn`` traced on ``args`` (raises ``Unkeyable``)."""
    digest = hashlib.sha256()
    for part in (fingerprint(fn), _avals(args), split, environment_key()):
        digest.update(repr(part).encode())
        digest.update(b"\x1e")
    return digest.hexdigest()[:40]


# ================================================================ compiling

def _batch_size(batched: Sequence[bool] | None, args: Sequence[Any]) -> int | None:
    """The batch size of a program split over the devices (``runtime.split_over_devices``'s
    rule: more than one device and a batch that divides evenly), or None: one device."""
    if batched is None or jax.device_count() == 1:
        return None
    size = next(np.shape(jax.tree.leaves(a)[0])[0] for a, b in zip(args, batched, strict=True)
                if b)
    return size if size % jax.device_count() == 0 else None


def compile_program(fn: Callable, args: Sequence[Any], *, name: str = "",
                    batched: Sequence[bool] | None = None, outputs: int = 1,
                    by_shape: bool = False) -> Any:
    """``fn`` compiled for ``args`` (their shapes and dtypes): a callable that takes
    arguments like ``args`` and returns ``fn``'s outputs.

    ``batched``: as ``runtime.split_over_devices`` (which arguments are split along
    axis 0 over the devices; ``outputs`` results, all split), or None: one device (the one
    the committed arguments live on). ``name``: what the first-run message calls it.

    Loads the traced program from ``cache_dir()/programs`` when an entry with its key is
    there, else traces, stores and compiles it; a program compiled earlier in this
    process with the same key is reused, and one that ``compile_ahead`` is compiling is
    waited for. Turns on JAX's persistent compilation cache
    (``runtime.configure``) unless the user configured one.

    ``by_shape``: the robots among ``fn``'s partial arguments are the program's data,
    not constants, so a robot of the same shape runs the same program (``_by_shape``)."""
    return _request(fn, args, name, batched, outputs, ahead=False, by_shape=by_shape)


def compile_ahead(fn: Callable, args: Sequence[Any], *, name: str = "",
                  batched: Sequence[bool] | None = None, outputs: int = 1,
                  by_shape: bool = False) -> None:
    """Start ``compile_program(fn, args, …)`` on a background thread and return at once;
    the ``compile_program`` call that later asks for the same program waits for it.

    XLA compiles a program on one core, so a process that will need several programs
    (one per device of a schedule's lanes, a repair program beside its search) gets them
    side by side on a multi-core CPU. Nothing happens for a program already compiled or
    under way in this process, or for an unkeyable function. The thread keeps running
    until the program is compiled (a process exits after it), so ask only for programs
    the process is likely to run; one that is not run is still stored for later ones."""
    _request(fn, args, name, batched, outputs, ahead=True, by_shape=by_shape)


def _request(fn: Callable, args: Sequence[Any], name: str, batched: Sequence[bool] | None,
             outputs: int, ahead: bool, by_shape: bool = False) -> Any:
    fn, data = lift(fn) if by_shape else (fn, ())
    if not len(data):
        return _requested(fn, args, name, batched, outputs, ahead)
    program = _requested(ByShape(fn), (data, *args), name or _name(fn),
                         batched and (False, *batched), outputs, ahead)
    return program and WithData(program, data)


def _requested(fn: Callable, args: Sequence[Any], name: str,
               batched: Sequence[bool] | None, outputs: int, ahead: bool) -> Any:
    from .runtime import configure, split_over_devices

    configure()  # XLA's half of the cache (a no-op once on, or user-set)
    size = _batch_size(batched, args)
    split = size is not None
    placement = (tuple(batched), outputs) if split else None
    try:
        key = program_key(fn, args, placement)
    except Unkeyable as exc:
        if ahead:
            return None
        stats.unkeyed += 1
        stats.unkeyable.append(f"{name or _name(fn)}: {exc}")
        jitted = split_over_devices(fn, batched, size, outputs) if split else jax.jit(fn)
        t0 = time.perf_counter()
        compiled = jitted.lower(*args).compile()
        stats.compile_seconds += time.perf_counter() - t0
        return compiled
    leaves = jax.tree.leaves(tuple(args))
    devices = tuple(sorted({d.id for leaf in leaves if isinstance(leaf, jax.Array)
                            for d in leaf.devices()}))
    effort = _effort.effort(key, _effort.forced_full(), leaves, split)
    tier = key if effort == "full" else f"{key}+{effort}"  # one program per effort in memory
    memory_key = f"{tier}:{devices}"
    with _lock:
        if memory_key in _memory:
            if not ahead:
                _memory.move_to_end(memory_key)
                stats.reused += 1
            return _memory[memory_key]
        future = _pending.get(memory_key)
        owner = future is None
        queued = None if owner or ahead else _queued.pop(memory_key, None)
        # Asked for ahead but still waiting for a background thread (behind longer
        # builds): built here and now instead of waited for.
        take_over = queued[1] if queued is not None and queued[0].cancel() else None
        if owner:
            # The same program for another single device, done or under way: moved, not
            # compiled again (requested earlier, so never queued behind this one). Not
            # where it is on disk already: then XLA's cache likely has its code, which
            # each device loads at once (side by side) and which cannot be moved.
            siblings = [] if split or len(devices) != 1 or _stored(key) else [
                k for k in (*_memory, *_pending) if k.startswith(f"{tier}:(")]
            future = _pending[memory_key] = Future()
    if take_over is not None:
        take_over()
    if owner:
        build = functools.partial(_build, future, fn, args, key, memory_key, name,
                                  batched if split else None, outputs, siblings, effort)
        if ahead:
            with _lock:
                _queued[memory_key] = (_background().submit(build), build)
        else:
            build()
    return None if ahead else future.result()


def _build(future: Future, fn: Callable, args: Sequence[Any], key: str, memory_key: str,
           name: str, batched: Sequence[bool] | None, outputs: int,
           siblings: Sequence[str] = (), effort: str = "full") -> None:
    """Load or trace, then compile, the program under ``key`` (or move a sibling's copy
    of it to this device); its result (or error) goes to ``future``, the program into
    the memory."""
    with _lock:
        _queued.pop(memory_key, None)
    try:
        compiled = _from_sibling(siblings, args) if siblings else None
        if compiled is None:
            compiled = _compiled(fn, args, key, name, batched, outputs, effort)
    except BaseException as exc:
        with _lock:
            del _pending[memory_key]
        future.set_exception(exc)
        if not isinstance(exc, Exception):
            raise
        return
    with _lock:
        _memory[memory_key] = compiled
        while len(_memory) > _MEMORY_SIZE:
            _memory.popitem(last=False)
        del _pending[memory_key]
    future.set_result(compiled)


def _compiled(fn: Callable, args: Sequence[Any], key: str, name: str,
              batched: Sequence[bool] | None, outputs: int, effort: str = "full") -> Any:
    """The program under ``key``: loaded from disk, else traced and stored; compiled
    with ``effort`` ("quick" in auto mode: noted for the background upgrade)."""
    leaves, in_tree = jax.tree.flatten(tuple(args))
    # The program is exported over the arguments' leaves (its pytrees, NamedTuples of
    # cr_nlp's among them, need no serialisation of their own); the output structure is
    # stored beside it.
    leaf_batched = None if batched is None else [
        b for arg, b in zip(args, batched, strict=True) for _ in jax.tree.leaves(arg)]
    in_shardings, out_shardings = split_shardings(leaf_batched)
    with _lock:
        tracing = _tracing.setdefault(key, threading.Lock())
    with tracing:  # one thread traces a program; one compiling it for another device waits
        entry = _load(key)
        ops = 0
        if entry is None:
            t0 = time.perf_counter()
            exported, out_tree = _export(fn, in_tree, leaves, batched)
            _store(key, exported, out_tree)
            stats.traced += 1
            stats.trace_seconds += time.perf_counter() - t0
            ops = _operations(exported)
            if announce:
                print(f"cr_nlp: compiling {name or _name(fn)} ({ops} operations; about "
                      f"{max(1, round(ops * _seconds_per_op(effort)))} s"
                      f"{', quickly' if effort == 'quick' else ''}, once: later processes "
                      f"load it from {cache_dir()})", file=sys.stderr, flush=True)
        else:
            exported, out_tree = entry
    runner = jax.jit(exported.call, in_shardings=in_shardings, out_shardings=out_shardings)
    _watch_xla_cache()
    hits = getattr(_xla_cache, "hits", 0)
    t0 = time.perf_counter()
    executable = runner.lower(*leaves).compile(compiler_options=_effort.compile_options(effort))
    seconds = time.perf_counter() - t0
    stats.compile_seconds += seconds
    if ops:
        _record_rate(seconds / ops, effort)
    if effort == "quick" and _effort.setting() == "auto":
        _effort.note_quick(key, leaves, leaf_batched, environment_key())
    return _Flat(executable, out_tree, movable=getattr(_xla_cache, "hits", 0) == hits)


_xla_cache = threading.local()
"""Per thread: ``hits``, how many programs XLA loaded from its disk cache."""


@functools.cache
def _watch_xla_cache() -> None:
    """Count XLA's disk-cache hits per thread (JAX reports them in the compiling thread):
    a program loaded from the cache cannot be moved to another device (``_moved``)."""

    def heard(event: str, **_: Any) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            _xla_cache.hits = getattr(_xla_cache, "hits", 0) + 1

    jax.monitoring.register_event_listener(heard)


def _from_sibling(siblings: Sequence[str], args: Sequence[Any]) -> _Flat | None:
    """The first movable program in memory (or under way) under one of ``siblings``,
    moved to the one device of ``args``; None where there is none or moving failed (then
    the caller compiles, or loads from XLA's cache)."""
    program = None
    for sibling in siblings:
        with _lock:
            program, future = _memory.get(sibling), _pending.get(sibling)
        if program is None and future is not None:
            try:
                program = future.result()
            except Exception:
                program = None
        if program is not None and program.movable:
            break
    else:
        return None
    device = next(iter(next(leaf for leaf in jax.tree.leaves(tuple(args))
                            if isinstance(leaf, jax.Array)).devices()))
    try:
        moved = _moved(program, device)
    except Exception as exc:  # a JAX whose executables no longer move: compile instead
        warnings.warn(f"cr_nlp: could not move a compiled program to {device} ({exc}); "
                      "compiling it for that device", RuntimeWarning, stacklevel=2)
        return None
    stats.moved += 1
    return moved


def _moved(program: _Flat, device: Any) -> _Flat:
    """``program`` (compiled for one device) bound to ``device`` of the same client.

    XLA's CPU executables carry their device, so each lane of a schedule compiled its own
    copy (the trajectory LM: 13 s alone, 20–28 s two side by side on 2 cores). The code is
    the same: serialised and loaded with the other device's assignment (~2 ms), as JAX's
    cache does for GPUs. Only a program XLA compiled in this process moves (one loaded
    from XLA's disk cache serialises without its code: "Function … not found"); warm,
    each lane loads the one cache entry (``runtime._one_cache_entry_per_program``)."""
    from jax._src.lib import xla_client as xc
    from jax.experimental import serialize_executable as se

    blob, in_tree, out_tree = se.serialize(program.executable)

    class _OnDevice(se._JaxPjrtUnpickler):
        def persistent_load(self, pid: Any) -> Any:
            if pid[0] == "device":
                return device
            if pid[0] == "exec":
                options = xc.CompileOptions()
                options.device_assignment = xc.DeviceAssignment.create(
                    np.array([[device.id]]))
                return self.backend.deserialize_executable(pid[1], self.execution_devices,
                                                           options)
            return super().persistent_load(pid)

    unloaded, args_info, no_kwargs = _OnDevice(io.BytesIO(blob), device.client,
                                               [device]).load()
    executable = jax.stages.Compiled(unloaded.load(), [], in_tree.unflatten(args_info),
                                     out_tree, no_kwargs=no_kwargs)
    return _Flat(executable, program.out_tree, movable=False)


@functools.cache
def _background() -> ThreadPoolExecutor:
    """The threads of ``compile_ahead``: one per core this process may use, less the one
    that goes on solving, at least two (XLA loads a cached program's copies for two lanes
    side by side: 0.72 s for the trajectory LM's two against 1.05–1.24 s one after the
    other; the caller's host work goes on meanwhile)."""
    return ThreadPoolExecutor(max(2, len(os.sched_getaffinity(0)) - 1),
                              thread_name_prefix="cr_nlp-compile")


def _mesh() -> Any:
    from jax.sharding import Mesh

    return Mesh(np.array(jax.devices()), ("batch",))


def split_shardings(leaf_batched: Sequence[bool] | None) -> tuple[Any, Any]:
    """The input shardings (one per leaf: split along axis 0 over the devices, or
    replicated) and the output sharding (split) of a program split over the devices;
    (None, None) for ``leaf_batched`` None (one device)."""
    if leaf_batched is None:
        return None, None
    mesh = _mesh()
    return tuple(_sharding(mesh, b) for b in leaf_batched), _sharding(mesh, True)


def _sharding(mesh: Any, batched: bool) -> Any:
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    return NamedSharding(mesh, P("batch") if batched else P())


def _export(fn: Callable, in_tree: Any, leaves: list, batched: Sequence[bool] | None
            ) -> tuple[Any, Any]:
    """Trace and lower ``fn`` over the leaves of its arguments (split over the devices by
    ``batched``, as ``split_over_devices``): the exported program and its output
    structure."""
    inner = fn
    if batched is not None:
        from jax.sharding import PartitionSpec as P

        specs = tuple(P("batch") if b else P() for b in batched)
        inner = jax.shard_map(fn, mesh=_mesh(), in_specs=specs, out_specs=P("batch"),
                              check_vma=False)  # as split_over_devices (why: there)
    out_trees = []

    def flat(*leaves: Any) -> tuple:
        out, out_tree = jax.tree.flatten(inner(*jax.tree.unflatten(in_tree, leaves)))
        out_trees.append(out_tree)
        return tuple(out)

    exported = jax.export.export(jax.jit(flat))(*leaves)
    return exported, out_trees[-1]


def _name(fn: Callable) -> str:
    while isinstance(fn, functools.partial):
        fn = fn.func
    return getattr(fn, "__name__", type(fn).__name__)


def _operations(exported: Any) -> int:
    """StableHLO operations in an exported program (lines of its text that assign)."""
    text = exported.mlir_module()
    return sum(1 for line in text.splitlines() if " = " in line)


# ================================================================ the disk

def _entry(key: str) -> Path:
    """The file of the program stored under ``key``."""
    return programs_dir() / f"{key}.jaxexport"


def _stored(key: str) -> bool:
    """Whether a program is stored under ``key`` (readable or not)."""
    return _entry(key).exists()


def _load(key: str) -> tuple[Any, Any] | None:
    """The exported program stored under ``key`` and its output structure, or None
    (absent, or unreadable: warned and counted in ``stats.rejected``)."""
    path = _entry(key)
    t0 = time.perf_counter()
    try:
        data = path.read_bytes()
    except OSError:
        return None
    try:
        head = len(FORMAT)
        checksum, body = data[head:head + 32], data[head + 32:]
        if data[:head] != FORMAT or hashlib.sha256(body).digest() != checksum:
            raise ValueError("damaged: its checksum does not match")
        if body[:len(key)] != key.encode():
            raise ValueError("stale: it holds another program")
        body = body[len(key):]
        tree_size = int.from_bytes(body[:8], "little")
        # The output structure (cr_nlp's own pytree types), pickled by this module into
        # this user's cache, as trusted as the compiled code that JAX's cache loads.
        out_tree = pickle.loads(body[8:8 + tree_size])
        exported = jax.export.deserialize(bytearray(body[8 + tree_size:]))
    except Exception as exc:  # any unreadable entry: trace again, never a wrong answer
        warnings.warn(f"cr_nlp: ignoring the cached program {path} ({exc}); tracing it "
                      "again", RuntimeWarning, stacklevel=3)
        stats.rejected += 1
        return None
    stats.loaded += 1
    stats.load_seconds += time.perf_counter() - t0
    return exported, out_tree


def _store(key: str, exported: Any, out_tree: Any) -> None:
    """Write ``exported`` and its output structure under ``key`` atomically (a reader sees
    a whole entry or none); a full or read-only disk only costs the next process a trace."""
    tree = pickle.dumps(out_tree)
    body = (key.encode() + len(tree).to_bytes(8, "little") + tree
            + bytes(exported.serialize()))
    folder = programs_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_atomic(_entry(key), FORMAT + hashlib.sha256(body).digest() + body)
    except OSError as exc:
        warnings.warn(f"cr_nlp: could not store a compiled program in {folder} ({exc})",
                      RuntimeWarning, stacklevel=3)


def _seconds_per_op(effort: str = "full") -> float:
    """Compile seconds per operation at ``effort`` measured on this machine last time (or
    the default: ``SECONDS_PER_OP``, a fifth of it quickly)."""
    try:
        return float((programs_dir() / f"seconds_per_op.{effort}.txt").read_text())
    except (OSError, ValueError):
        return SECONDS_PER_OP / (5 if effort == "quick" else 1)


def _record_rate(rate: float, effort: str = "full") -> None:
    with contextlib.suppress(OSError):
        write_atomic(programs_dir() / f"seconds_per_op.{effort}.txt", f"{rate:.6g}".encode())


def clear_memory() -> None:
    """Forget the programs compiled in this process (the disk entries stay)."""
    with _lock:
        _memory.clear()
