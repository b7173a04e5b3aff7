"""The stage packages' public faces load on first use (PEP 562): importing a package for
one name does not import every module behind the face (CasADi, the IK driver's programs)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from importlib import import_module
from typing import Any


def lazy_face(package: str, table: dict[str, tuple[str, str]]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for ``package``: ``table[name] = (module, attribute)``,
    the module relative to the package; the value is kept in the package once loaded."""

    def attribute(name: str) -> Any:
        if name not in table:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module, attr = table[name]
        value = getattr(import_module(module, package), attr)
        setattr(sys.modules[package], name, value)
        return value

    return attribute
