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

    def slot(x: Any) -> Any:
        nonlocal size
        if isinstance(x, float):
            template, numbers = None, np.array([x])
        elif hasattr(x, "program_data") and not isinstance(x, type):
            template, numbers = x.program_data()
        else:
            return x
        if id(x) not in slots:
            slots[id(x)] = _Slot(size, size + len(numbers), template)
            data.append(numbers)
            size += len(numbers)
        return slots[id(x)]

    lifted = _rebuilt(fn, slot)
    return lifted, np.concatenate(data) if data else np.zeros(0)


def _filled(x: Any, data: Any) -> Any:
    """``lift``'s function with each slot's number or robot rebuilt from the (traced)
    data vector."""
    def fill(y: Any) -> Any:
        if not isinstance(y, _Slot):
            return y
        return data[y.start] if y.template is None else y.template.filled(
            data[y.start:y.stop])

    return _rebuilt(x, fill)


def _rebuilt(x: Any, leaf: Callable[[Any], Any]) -> Any:
    """``x`` with ``leaf(y)`` in place of everything ``y`` inside it that is not a
    ``functools.partial``, a tuple or list, or a dataclass of functions (those are built
    again around their new contents)."""
    if isinstance(x, functools.partial):
        return functools.partial(_rebuilt(x.func, leaf), *(_rebuilt(a, leaf) for a in x.args),
                                 **{k: _rebuilt(v, leaf) for k, v in x.keywords.items()})
    if type(x) in (tuple, list):
        return type(x)(_rebuilt(v, leaf) for v in x)
    if _holds_functions(x):
        return dataclasses.replace(x, **{f: _rebuilt(getattr(x, f), leaf) for f in _fields(x)})
    return leaf(x)


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
