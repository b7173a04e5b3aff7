"""CasADi functions compiled to machine code with the system C compiler, cached on disk.

The exact stage evaluates a few small per-configuration functions (the clearance rows,
their Jacobian, their curvature: ``stages._slots``) hundreds of times per Ipopt
iteration. CasADi's virtual machine runs them; its generated C code, compiled with
``gcc -O1``, was measured 2.7× (rows and Jacobian) to 3.9× (curvature) faster on tdcr3
among 27 spheres, and costs 4–12 s of compilation once. The shared library is kept in
``cache_dir()/casadi`` under the hash of its source, so later processes, and the pool's
workers, load it in milliseconds (as JAX's persistent cache does for the JAX stages).

Without a C compiler (``$CC``, ``cc`` or ``gcc``), or if compiling fails, the functions
run in the virtual machine: the same numbers, slower; a warning says so once.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path

import casadi as ca

from .._jax_setup import cache_dir

FLAGS = ("-O1",)
"""Optimisation flags: -O2 measured 2× faster on the curvature function than -O1 but
3–4× longer to compile (40 s)."""

_warned = False


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def compiled(functions: Sequence[ca.Function], enabled: bool = True) -> list[ca.Function]:
    """``functions`` as compiled ``ca.external`` functions from one cached shared library
    (same names, inputs and outputs), or unchanged when ``enabled`` is False or no
    compiler works."""
    global _warned
    functions = list(functions)
    compiler = _compiler() if enabled else None
    if compiler is None:
        if enabled and not _warned:
            warnings.warn("no C compiler found (set $CC): cr_nlp's exact stage runs its "
                          "CasADi functions in the virtual machine, about 3× slower",
                          RuntimeWarning, stacklevel=2)
            _warned = True
        return functions
    generator = ca.CodeGenerator("cr_nlp_functions.c", {"with_header": False})
    for function in functions:
        generator.add(function)
    source = generator.dump()
    key = hashlib.sha256("\n".join([ca.__version__, *FLAGS, source]).encode()).hexdigest()[:24]
    folder = cache_dir() / "casadi"
    library = folder / f"{key}.so"
    if not library.exists():
        try:
            _build(compiler, source, library)
        except (OSError, subprocess.CalledProcessError) as exc:
            if not _warned:
                warnings.warn(f"compiling the exact stage's CasADi functions failed ({exc}); "
                              "they run in the virtual machine, about 3× slower",
                              RuntimeWarning, stacklevel=2)
                _warned = True
            return functions
    return [ca.external(f.name(), str(library)) for f in functions]


def _build(compiler: str, source: str, library: Path) -> None:
    """Compile ``source`` into ``library`` atomically (a library is complete or absent,
    also when several processes compile it at once)."""
    library.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=library.parent) as work:
        c_file, out = Path(work) / "functions.c", Path(work) / "functions.so"
        c_file.write_text(source)
        subprocess.run([compiler, *FLAGS, "-shared", "-fPIC", "-o", str(out), str(c_file),
                        "-lm"], check=True, capture_output=True)
        os.replace(out, library)
