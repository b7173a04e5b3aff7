"""Fingerprints: a digest of everything in a Python object that can change a program JAX
traces from it (``cr_nlp._programs`` keys its disk entries with them).

Numbers and arrays by content, settings dataclasses field by field, functions by module,
qualified name, code and closure; anything else is ``Unkeyable``, so that a program is
never stored under a key that might be wrong.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import math
import types
from collections.abc import Callable
from typing import Any

import jax
import numpy as np


class Unkeyable(TypeError):
    """``fingerprint`` met an object it cannot turn into a key."""


def fingerprint(obj: Any) -> str:
    """A hex digest of everything in ``obj`` that can change a traced program.

    Numbers, strings, numpy and JAX arrays (by content), tuples, lists, dicts, sets,
    dataclasses (by type and every field that takes part in comparisons), enums, dtypes,
    types, ``functools.partial`` and functions (module, qualified name, code, defaults,
    closure) and bound methods. Raises ``Unkeyable`` for anything else."""
    digest = hashlib.sha256()
    _feed(obj, digest, set())
    return digest.hexdigest()


def _feed(obj: Any, digest: Any, active: set[int]) -> None:
    def put(*parts: Any) -> None:
        for part in parts:
            digest.update(part if isinstance(part, bytes) else repr(part).encode())
            digest.update(b"\x1f")

    if obj is None or obj is Ellipsis or isinstance(obj, bool | int | str | bytes | complex):
        put(type(obj).__name__, obj)
        return
    if type(obj) is object:  # a sentinel (jax.vmap's wrapper holds one): no value
        put("sentinel")
        return
    if isinstance(obj, float):
        put("float", obj.hex() if math.isfinite(obj) else repr(obj))
        return
    if isinstance(obj, np.dtype):
        put("dtype", obj.str)
        return
    if isinstance(obj, np.ndarray | np.generic):
        array = np.ascontiguousarray(obj)
        put("ndarray", array.dtype.str, array.shape, array.tobytes())
        return
    if isinstance(obj, jax.core.Tracer):
        raise Unkeyable("a traced value")
    if isinstance(obj, jax.Array):
        _feed(np.asarray(obj), digest, active)
        put("weak", getattr(obj, "weak_type", False))
        return
    if isinstance(obj, type):
        put("type", obj.__module__, obj.__qualname__)
        return
    if isinstance(obj, enum.Enum):
        put("enum", type(obj).__qualname__, obj.name)
        return
    if id(obj) in active:
        put("cycle")
        return
    active.add(id(obj))
    try:
        _feed_container(obj, digest, active, put)
    finally:
        active.discard(id(obj))


def _feed_container(obj: Any, digest: Any, active: set[int], put: Callable) -> None:
    if isinstance(obj, tuple | list):
        put(type(obj).__name__, len(obj))
        for item in obj:
            _feed(item, digest, active)
    elif isinstance(obj, dict):
        put("dict", len(obj))
        for key in sorted(obj, key=repr):
            _feed(key, digest, active)
            _feed(obj[key], digest, active)
    elif isinstance(obj, set | frozenset):
        put("set", sorted(fingerprint(item) for item in obj))
    elif dataclasses.is_dataclass(obj):
        put("dataclass", type(obj).__module__, type(obj).__qualname__)
        for f in dataclasses.fields(obj):
            if f.compare:  # compare=False: a label (a file name), not part of the value
                put(f.name)
                _feed(getattr(obj, f.name), digest, active)
    elif isinstance(obj, functools.partial):
        put("partial")
        _feed(obj.func, digest, active)
        _feed(obj.args, digest, active)
        _feed(obj.keywords, digest, active)
    elif isinstance(obj, types.MethodType):
        put("method")
        _feed(obj.__self__, digest, active)
        _feed(obj.__func__, digest, active)
    elif isinstance(obj, types.FunctionType):
        code = obj.__code__
        put("function", obj.__module__, obj.__qualname__, code.co_code, code.co_names)
        _feed(tuple(c for c in code.co_consts if not isinstance(c, types.CodeType)),
              digest, active)
        _feed(obj.__defaults__, digest, active)
        _feed(obj.__kwdefaults__, digest, active)
        _feed(tuple(cell.cell_contents for cell in obj.__closure__ or ()), digest, active)
    elif isinstance(obj, types.BuiltinFunctionType) or (
            callable(obj) and getattr(obj, "__module__", "").split(".")[0] in ("jax", "numpy")
            and hasattr(obj, "__qualname__")):
        # jax.numpy, lax and numpy functions (jitted ones included): by name; the versions
        # are part of every key.
        put("library", obj.__module__, obj.__qualname__)
    elif hasattr(obj, "__wrapped__"):  # functools.wraps, jax.jit of a cr_nlp function
        put("wrapped", type(obj).__qualname__)
        _feed(obj.__wrapped__, digest, active)
    else:
        raise Unkeyable(f"{type(obj).__module__}.{type(obj).__qualname__}")
