"""CasADi functions compiled to machine code with the system C compiler, cached on disk.

The exact stage evaluates a few small per-configuration functions (the clearance rows,
their Jacobian, their curvature: ``stages.polish._clearance_rows``) hundreds of times per Ipopt
iteration. CasADi's virtual machine runs them; its generated C code, compiled with
``gcc -O1``, was measured 2.7× (rows and Jacobian) to 3.9× (curvature) faster on tdcr3
among 27 spheres, and costs 4–12 s of compilation once. The shared library is kept in
``cache_dir()/casadi`` under the hash of its source, so later processes, and the pool's
workers, load it in milliseconds (as JAX's persistent cache does for the JAX stages).

The compiler runs in the background: until the library is built, ``compiled`` hands back
the functions as they are (CasADi's virtual machine, the same numbers) and ``pending``
says so; a polisher asks ``pending`` before each solve and rebuilds its solvers on the
compiled library once it is there. A small job (the demo's 20 IK targets polish in
0.1 s) no longer waits 10 s for gcc, and a long one switches within seconds. A build
another process started (a lock file says so) is not started again. The interpreter
waits at exit for the builds it started, so that the next process finds the library.

A library that takes long to build and pays off only on large problems (``faster``: the
tension motions' step functions at -Og, about 75 s of gcc) is built after the quick one, by
a detached compiler process: no process waits for it, at exit or before switching, and a
later call (or process) that finds it uses it instead of the quicker-built one.

Without a C compiler (``$CC``, ``cc`` or ``gcc``), or if compiling fails, the functions
run in the virtual machine: the same numbers, slower; a warning says so once.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path

import casadi as ca

from ...runtime import cache_dir

FLAGS = ("-O1",)
"""Optimisation flags: -O2 measured 2× faster on the curvature function than -O1 but
3–4× longer to compile (40 s)."""

_warned = False

_lock = threading.Lock()
_pending: dict[Path, threading.Thread | None] = {}
"""Libraries asked for and not built yet: this process's build thread, or None where
another process holds the build's lock."""
_detached: dict[Path, subprocess.Popen | None] = {}
"""Faster libraries asked for: the detached compiler this process started, or None where
another process holds the build's lock."""
_failed: set[Path] = set()
"""Faster libraries whose detached build could not start or ended without the library:
not started again by this process."""


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def compiled(functions: Sequence[ca.Function], enabled: bool = True,
             wait: bool = False, flags: Sequence[str] = FLAGS,
             faster: Sequence[str] | None = None) -> tuple[list[ca.Function], bool]:
    """``functions`` as compiled ``ca.external`` functions from one cached shared library
    (same names, inputs and outputs), or unchanged when ``enabled`` is False or no
    compiler works; and whether they came back unchanged because the library is being
    built (in the background; ``wait``: here, before returning): ask again once
    ``pending()`` is False. ``flags``: the compiler's optimisation flags (``FLAGS``).
    ``faster``: flags of a library worth a long build; where it is built its functions
    come back, else, once the ``flags`` library is there, its build starts in a detached
    process (``faster_pending()`` says while it runs) and the ``flags`` library serves
    meanwhile: ask again once ``pending()`` is False, then once ``faster_pending()`` is."""
    functions = list(functions)
    compiler = _compiler() if enabled else None
    if compiler is None:
        if enabled:
            _warn_once("no C compiler found (set $CC): cr_nlp's exact stage runs its "
                       "CasADi functions in the virtual machine, about 3× slower")
        return functions, False
    generator = ca.CodeGenerator("cr_nlp_functions.c", {"with_header": False})
    for function in functions:
        generator.add(function)
    source = generator.dump()
    library = _library(source, flags)
    fast = None if faster is None else _library(source, faster)
    if fast is not None and fast.exists():
        return [ca.external(f.name(), str(fast)) for f in functions], False
    if not library.exists():
        if wait:
            if not _build(compiler, source, library, tuple(flags)):
                return functions, False
        else:
            _start(compiler, source, library, tuple(flags))
            return functions, True
    if fast is not None:        # after the quick one: the two builds do not share the cores
        _start_detached(compiler, source, fast, tuple(faster))
    return [ca.external(f.name(), str(library)) for f in functions], False


def _library(source: str, flags: Sequence[str]) -> Path:
    """Where the library of ``source`` compiled with ``flags`` is kept."""
    key = hashlib.sha256("\n".join([ca.__version__, *flags, source]).encode()).hexdigest()[:24]
    return cache_dir() / "casadi" / f"{key}.so"


def pending() -> bool:
    """Whether a library ``compiled`` was asked for is still being built (by this
    process or by another); a failed build is not pending."""
    with _lock:
        for library, thread in list(_pending.items()):
            if library.exists() or (thread is not None and not thread.is_alive()) or (
                    thread is None and not _locked(library)):
                del _pending[library]
        return bool(_pending)


def faster_pending() -> bool:
    """Whether a faster library (``compiled``'s ``faster``) is still being built, by this
    process's detached compiler or by another process."""
    with _lock:
        running = False
        for library, process in list(_detached.items()):
            if library.exists() or library in _failed:
                continue
            if process is None:
                running |= _locked(library)
            elif process.poll() is None:
                running = True
            else:
                _failed.add(library)
        return running


def wait_for_builds(timeout: float | None = None) -> bool:
    """Wait for the builds this process started; True when none is left pending."""
    with _lock:
        threads = [t for t in _pending.values() if t is not None]
    for thread in threads:
        thread.join(timeout)
    return not pending()


def _start(compiler: str, source: str, library: Path, flags: tuple[str, ...] = FLAGS) -> None:
    """Build ``library`` in a background thread, unless this process or another is
    building it already."""
    with _lock:
        if library in _pending:
            return
        if _locked(library):
            _pending[library] = None
            return
        print(f"cr_nlp: compiling the exact stage's CasADi functions in the background "
              f"(5–20 s, once: later processes load them from {cache_dir()}); until then "
              "they run in CasADi's virtual machine", file=sys.stderr, flush=True)
        # Not a daemon: the interpreter waits for it at exit, so the library is kept.
        thread = threading.Thread(target=_build, args=(compiler, source, library, flags),
                                  name=f"cr_nlp gcc {library.stem}")
        _pending[library] = thread
        thread.start()


def _start_detached(compiler: str, source: str, library: Path, flags: tuple[str, ...]) -> None:
    """Build ``library`` in a compiler process of its own session, which outlives this
    one and holds the build's lock (the lock file's descriptor passed on); not where
    this process started it already, or failed to, or another process holds the lock."""
    try:
        import fcntl
    except ImportError:          # no advisory locks: no detached builds either
        return
    with _lock:
        if library in _failed or isinstance(_detached.get(library), subprocess.Popen):
            return
        try:
            library.parent.mkdir(parents=True, exist_ok=True)
            with open(_lock_path(library), "a+") as lock:
                try:
                    fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    _detached[library] = None                  # another process builds it
                    return
                work = Path(tempfile.mkdtemp(dir=library.parent))
                try:
                    (work / "functions.c").write_text(source)
                    # Compile, put the library in place by one rename, clean up; the lock
                    # is released when the shell exits.
                    out = work / "functions.so"
                    command = _command(compiler, flags, work / "functions.c", out)
                    _detached[library] = subprocess.Popen(
                        ["sh", "-c", '"$@" && mv "$OUT" "$L"; rm -rf "$W"', "sh", *command],
                        env={**os.environ, "W": str(work), "OUT": str(out), "L": str(library)},
                        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                        stderr=subprocess.DEVNULL, pass_fds=(lock.fileno(),),
                        start_new_session=True)
                except OSError:
                    shutil.rmtree(work, ignore_errors=True)
                    raise
        except OSError:
            _failed.add(library)
            return
    print(f"cr_nlp: compiling faster functions for large problems in a background process "
          f"(1–2 min, once: later solves and processes load them from {cache_dir()})",
          file=sys.stderr, flush=True)


def _command(compiler: str, flags: Sequence[str], c_file: Path, out: Path) -> list[str]:
    """The compiler's command line that builds the shared library ``out`` from ``c_file``."""
    return [compiler, *flags, "-shared", "-fPIC", "-o", str(out), str(c_file), "-lm"]


def _lock_path(library: Path) -> Path:
    return library.with_suffix(".lock")


def _locked(library: Path) -> bool:
    """Whether another process holds ``library``'s build lock."""
    try:
        import fcntl
    except ImportError:  # no advisory locks here: every process builds its own
        return False
    try:
        with open(_lock_path(library), "a+") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            fcntl.flock(handle, fcntl.LOCK_UN)
    except BlockingIOError:
        return True
    except OSError:
        return False
    return False


def _build(compiler: str, source: str, library: Path, flags: tuple[str, ...] = FLAGS) -> bool:
    """Compile ``source`` into ``library`` atomically (a library is complete or absent,
    also when several processes compile it at once), holding its lock file; False (and
    a warning, once) when compiling failed."""
    try:
        library.parent.mkdir(parents=True, exist_ok=True)
        with open(_lock_path(library), "a+") as lock:
            try:
                import fcntl
                fcntl.flock(lock, fcntl.LOCK_EX)
            except ImportError:
                pass
            if library.exists():  # another process built it while this one waited
                return True
            with tempfile.TemporaryDirectory(dir=library.parent) as work:
                c_file, out = Path(work) / "functions.c", Path(work) / "functions.so"
                c_file.write_text(source)
                subprocess.run(_command(compiler, flags, c_file, out), check=True,
                               capture_output=True)
                os.replace(out, library)
        return True
    except (OSError, subprocess.CalledProcessError) as exc:
        _warn_once(f"compiling the exact stage's CasADi functions failed ({exc}); they run "
                   "in the virtual machine, about 3× slower")
        return False


def _warn_once(message: str) -> None:
    global _warned
    if not _warned:
        _warned = True
        warnings.warn(message, RuntimeWarning, stacklevel=3)
