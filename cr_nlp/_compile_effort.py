"""How hard XLA optimises a program: quickly on a first run, fully for every later one.

On a 2-core CPU most of a first run is XLA compiling (the demo: 154 s of XLA in a 96 s
run). With LLVM's optimisations off and XLA's older loop emitters (``QUICK_OPTIONS``) the
same programs compile about 5× faster and run 1.2–5× slower: the cold demo 96 → 50 s, a
warm one 9–11 → 11–13 s, a steady 10 000-target IK 2.1 → 7.5 s, 20 plans 0.34 → 1.6 s.

So, on a CPU, a program that XLA's cache does not hold fully optimised is compiled quickly
(``effort``: "quick") and noted (``note_quick``: its arguments' shapes beside its stored
program); when the process ends, one detached background process (``cr_nlp._upgrade``,
at the lowest CPU priority) compiles the noted programs fully into XLA's cache and marks
each one done. Every later process loads the optimised code. Steps aside for:

- ``CR_NLP_COMPILE=full`` (optimise at once, as JAX does) or ``quick`` (quick code, no
  background process); the default is ``auto``;
- a large job (``full_effort()``: the tasks use it above ``LARGE_IK``/``LARGE_PLAN``,
  batch workers and benchmarks always): its run time outweighs the compile saved; and
  the live solvers' updates (``compiles_fully``), whose latency is what they are for;
- a GPU (only CPU compiles were measured), an optimisation level in ``$XLA_FLAGS`` (the
  user's own), no persistent compilation cache (nothing to upgrade), a system without
  POSIX file locks, or arguments spread over several devices by an earlier program (the
  background process compiles single-device programs over uncommitted or device-0
  arguments, and split ones as ``_programs`` splits them).

A process's answers do not depend on when the upgrade finishes: a program is compiled
once per process with one effort. The quick and the full code run the same XLA program;
their float32 results agree up to rounding (as the test suite's quick flags, there).
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import hashlib
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

QUICK_OPTIONS = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
"""XLA's compile options of a quick compile (debug options, by name)."""
SETTINGS = ("auto", "quick", "full")
"""The values of ``$CR_NLP_COMPILE``."""
LARGE_IK = 50_000
"""IK targets from which a solve compiles fully: on a 2-core CPU quick code costs
~0.54 ms more per target and saves ~34 s of compiling once (measured 2026-12-03)."""
LARGE_PLAN = 200
"""Planning problems from which a call compiles fully (~63 ms more per problem, ~12 s
of compiling saved once)."""

F = TypeVar("F", bound=Callable[..., Any])
_large_jobs = 0
"""``full_effort()`` blocks running in this process."""
_queued: set[str] = set()
_lock = threading.Lock()


def setting() -> str:
    """``$CR_NLP_COMPILE`` (default "auto"); an unknown value is named."""
    value = os.environ.get("CR_NLP_COMPILE", "auto").strip().lower() or "auto"
    if value not in SETTINGS:
        raise ValueError(f"CR_NLP_COMPILE must be one of {', '.join(SETTINGS)}, got "
                         f"{os.environ['CR_NLP_COMPILE']!r}")
    return value


def forced_full() -> bool:
    """Whether a ``full_effort()`` block is running in this process."""
    return _large_jobs > 0


@contextlib.contextmanager
def full_effort(active: bool = True) -> Iterator[None]:
    """While the block runs, programs this process compiles (on any thread) are
    optimised fully (``active`` False: no change): for jobs whose run time outweighs the
    compile a quick one saves."""
    global _large_jobs
    with _lock:
        _large_jobs += int(active)
    try:
        yield
    finally:
        with _lock:
            _large_jobs -= int(active)


def compiles_fully(method: F) -> F:
    """``method`` run inside ``full_effort()``: for latency-bound calls (live IK), whose
    every later call runs the code its first one compiles."""
    @functools.wraps(method)
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        with full_effort():
            return method(*args, **kwargs)

    return wrapped  # type: ignore[return-value]


def effort(key: str, forced: bool, leaves: Sequence[Any], split: bool) -> str:
    """"quick" or "full" for the program stored under ``key`` with arguments ``leaves``
    (``forced``: asked for inside ``full_effort()``; ``split``: split over the devices)."""
    import jax

    chosen = setting()
    if chosen != "auto":
        return chosen
    if (forced or jax.devices()[0].platform != "cpu" or os.name != "posix"
            or "xla_backend_optimization_level" in os.environ.get("XLA_FLAGS", "")
            or not jax.config.jax_compilation_cache_dir or _marker(key).exists()
            or not (split or _on_one_device(leaves))):
        return "full"
    return "quick"


def _on_one_device(leaves: Sequence[Any]) -> bool:
    """Whether no leaf is spread over several devices: the background process compiles
    a program that is not split over the devices on one device, so it reproduces only
    those (an argument sharded by an earlier program would change the program)."""
    import jax

    return all(len(leaf.sharding.device_set) == 1 for leaf in leaves
               if isinstance(leaf, jax.Array))


def compile_options(chosen: str) -> dict[str, Any] | None:
    """The ``Lowered.compile`` options of an effort (None: XLA's defaults)."""
    return dict(QUICK_OPTIONS) if chosen == "quick" else None


# ================================================================ the queue on disk

def _folder() -> Path:
    from .runtime import programs_dir

    return programs_dir()


def _marker(key: str) -> Path:
    """Present once XLA's cache holds the program's fully optimised code."""
    return _folder() / f"{key}.full"


def _note(key: str) -> Path:
    """What the background process needs to compile the program again."""
    return _folder() / f"{key}.quick.json"


def environment_hash(environment: tuple) -> str:
    """A short hash of ``_programs.environment_key()``'s ``environment``: a note is
    compiled only by a process whose key would be the same (device count, versions, JAX
    settings)."""
    return hashlib.sha256(repr(environment).encode()).hexdigest()[:16]


def note_quick(key: str, leaves: Sequence[Any], batched: Sequence[bool] | None,
               environment: tuple) -> None:
    """Record that ``key`` was compiled quickly in this process, with its arguments'
    leaves (shapes, dtypes, weak types, whether committed to a device: that changes the
    program's text) and which are split over the devices (``batched`` per leaf, None: one
    device), in the ``environment`` it was compiled in (``_programs.environment_key()``);
    the process's exit starts the upgrade."""
    import jax

    from ._files import write_atomic

    avals = []
    for leaf in leaves:
        aval = jax.typeof(leaf)
        committed = isinstance(leaf, jax.Array) and bool(leaf.committed)
        avals.append([list(aval.shape), str(aval.dtype),
                      bool(getattr(aval, "weak_type", False)), committed])
    note = {"environment": environment_hash(environment), "devices": jax.device_count(),
            "leaves": avals, "batched": None if batched is None else [bool(b) for b in batched]}
    with contextlib.suppress(OSError):
        write_atomic(_note(key), json.dumps(note).encode())
        with _lock:
            first = not _queued
            _queued.add(key)
        if first:
            atexit.register(start_upgrade)


def pending(folder: Path | None = None) -> list[str]:
    """Keys noted as quick whose full code is not marked done (any environment), in
    ``folder`` (default: this process's ``programs_dir()``)."""
    folder = _folder() if folder is None else Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p.name[:-len(".quick.json")] for p in folder.glob("*.quick.json")
                  if not (folder / f"{p.name[:-len('.quick.json')]}.full").exists())


def start_upgrade() -> subprocess.Popen | None:
    """Start the detached background process that compiles the noted programs fully
    (``cr_nlp._upgrade``; its output goes to ``upgrade.log`` beside them). None: nothing
    queued, or it could not start (the next process queues them again)."""
    import jax

    with _lock:
        queued = bool(_queued)
        _queued.clear()
    if not queued:
        return None
    folder = _folder()
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(jax.config.jax_compilation_cache_dir))
    try:
        log = open(folder / "upgrade.log", "ab")  # noqa: SIM115 — handed to the child
    except OSError:
        return None
    with log:
        try:
            return subprocess.Popen(
                [sys.executable, "-m", "cr_nlp._upgrade", "--devices",
                 str(jax.device_count())],
                stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=env,
                start_new_session=True, close_fds=True)
        except OSError:
            return None


def wait_for_upgrade(folder: Path | None = None, timeout: float = 900.0,
                     poll: float = 0.5, idle: float = 5.0) -> bool:
    """Wait until every program noted in ``folder`` (default: ``programs_dir()``) is
    compiled fully: a benchmark's warm process then measures the code every later
    process gets. Gives up after ``timeout`` seconds, or once no background process has
    held the folder's lock for ``idle`` seconds (what is left, none will compile).
    Returns whether none is pending."""
    import fcntl

    folder = _folder() if folder is None else Path(folder)
    stop = time.monotonic() + timeout
    free_since = None
    while pending(folder):
        now = time.monotonic()
        if now > stop:
            return False
        try:
            with open(folder / "upgrade.lock", "a") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)    # released on close
            free_since = now if free_since is None else free_since
        except BlockingIOError:
            free_since = None
        if free_since is not None and now - free_since > idle:
            return False
        time.sleep(poll)
    return True
