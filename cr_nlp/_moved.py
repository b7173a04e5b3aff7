"""Old module addresses kept for one release: importing one warns and hands over the new
module (the same object, so ``from old import name`` and ``import old`` both work)."""

from __future__ import annotations

import importlib
import sys
import warnings
from typing import Any


def moved_module(old: str, new: str, until: str = "0.2") -> None:
    """Replace module ``old`` (being imported) by ``new`` in ``sys.modules``, with a
    DeprecationWarning naming both and the release that drops ``old``."""
    warnings.warn(f"{old} moved to {new}; the old name goes in cr_nlp {until}",
                  DeprecationWarning, stacklevel=3)
    sys.modules[old] = importlib.import_module(new)


def moved_names(module: str, names: dict[str, str], until: str = "0.2") -> Any:
    """A module ``__getattr__`` for names that moved out of ``module`` or were renamed:
    ``names[name]`` is the new module, ``"module:new_name"``, or ``":new_name"`` (renamed
    in ``module`` itself); using the old address
    warns (DeprecationWarning) and returns the object from its new one."""

    def attribute(name: str) -> Any:
        if name not in names:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        where, _, new = names[name].partition(":")
        where = where or module
        warnings.warn(f"{module}.{name} is now {where}.{new or name}; the old name goes in "
                      f"cr_nlp {until}", DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module(where), new or name)

    return attribute
