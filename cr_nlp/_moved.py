"""Old module addresses kept for one release: importing one warns and hands over the new
module (the same object, so ``from old import name`` and ``import old`` both work)."""

from __future__ import annotations

import importlib
import sys
import warnings


def moved_module(old: str, new: str, until: str = "0.2") -> None:
    """Replace module ``old`` (being imported) by ``new`` in ``sys.modules``, with a
    DeprecationWarning naming both and the release that drops ``old``."""
    warnings.warn(f"{old} moved to {new}; the old name goes in cr_nlp {until}",
                  DeprecationWarning, stacklevel=3)
    sys.modules[old] = importlib.import_module(new)
