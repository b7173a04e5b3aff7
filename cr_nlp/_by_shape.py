"""Robots as data of compiled programs (``_programs.compile_program``'s ``by_shape``).

A program traced from a function that closes over a robot holds the robot's numbers as
constants: every robot, even one that differs from another only in a length, compiles
its own programs (a calibrated robot, a robot file a lab writes, each test's variant).
``lift`` takes the robots out of a function's ``functools.partial`` arguments and puts a
``_Slot`` in their place; the program (``ByShape``) takes their numbers as its first
argument and rebuilds each robot from them while it is traced (``Robot.filled``). The
program is then keyed by the robots' shape (``Robot.program_data``'s template: segment
count, points, tendon layout, which limits are finite, the mechanics block) and serves
every robot of that shape. Floats among the partial arguments (a margin, a weight) are
taken out the same way, so a new margin does not compile a new program either.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class _Slot:
    """Where ``lift`` took a number or a robot out of a function: its entries of the
    program's data vector and, for a robot, its template (``program_data``), which keys
    the program (None: a number, entry ``start``)."""

    start: int
    stop: int
    template: Any = None


def lift(fn: Callable) -> tuple[Callable, np.ndarray]:
    """``fn`` with every float and every object with ``program_data`` (a robot) among its
    partial arguments (nested partials, tuples, lists and dataclasses of functions
    included) replaced by a ``_Slot``, and their numbers as one float64 vector, in slot
    order (an object met twice is one slot)."""
    slots: dict[int, _Slot] = {}
    data: list[np.ndarray] = []
    size = 0

    def slot(x: Any, template: Any, numbers: np.ndarray) -> _Slot:
        nonlocal size
        if id(x) not in slots:
            slots[id(x)] = _Slot(size, size + len(numbers), template)
            data.append(numbers)
            size += len(numbers)
        return slots[id(x)]

    def walk(x: Any) -> Any:
        if isinstance(x, float):
            return slot(x, None, np.array([x]))
        if hasattr(x, "program_data") and not isinstance(x, type):
            return slot(x, *x.program_data())
        if isinstance(x, functools.partial):
            return functools.partial(walk(x.func), *map(walk, x.args),
                                     **{k: walk(v) for k, v in x.keywords.items()})
        if type(x) in (tuple, list):
            return type(x)(map(walk, x))
        if _holds_functions(x):
            return dataclasses.replace(x, **{f: walk(getattr(x, f)) for f in _fields(x)})
        return x

    lifted = walk(fn)
    return lifted, np.concatenate(data) if data else np.zeros(0)


def _filled(x: Any, data: Any) -> Any:
    """``lift``'s function with each slot's number or robot rebuilt from the (traced)
    data vector."""
    if isinstance(x, _Slot):
        return data[x.start] if x.template is None else x.template.filled(
            data[x.start:x.stop])
    if isinstance(x, functools.partial):
        return functools.partial(_filled(x.func, data), *(_filled(a, data) for a in x.args),
                                 **{k: _filled(v, data) for k, v in x.keywords.items()})
    if type(x) in (tuple, list):
        return type(x)(_filled(v, data) for v in x)
    if _holds_functions(x):
        return dataclasses.replace(x, **{f: _filled(getattr(x, f), data) for f in _fields(x)})
    return x


def _fields(x: Any) -> list[str]:
    return [f.name for f in dataclasses.fields(x) if f.init]


def _holds_functions(x: Any) -> bool:
    """A dataclass of functions (a residual's terms, each a partial or None): walked into;
    a dataclass with numbers (a settings class) stays a constant of the program."""
    return (dataclasses.is_dataclass(x) and not isinstance(x, type)
            and all(callable(getattr(x, f)) or getattr(x, f) is None for f in _fields(x)))


@dataclasses.dataclass(frozen=True)
class ByShape:
    """The program of a lifted function: its data vector first."""

    fn: Callable

    def __call__(self, data: Any, *args: Any) -> Any:
        return _filled(self.fn, data)(*args)


class WithData:
    """A compiled ``ByShape`` program bound to one request's data vector: called like the
    function it was compiled from."""

    def __init__(self, program: Any, data: np.ndarray) -> None:
        self.program, self.data = program, data

    def __call__(self, *args: Any) -> Any:
        return self.program(self.data, *args)
