"""Where the bundled models (robots, scenes, meshes, targets, problems, paths) live.

In a source checkout or an editable install they are the repository's ``models/``
folder; a regular ``pip install .`` installs the same folder as ``cr_nlp/models``
(``pyproject.toml``), so bundled names work either way.
"""

from __future__ import annotations

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def models_root() -> Path:
    """The folder holding ``robots/``, ``scenes/``, ``meshes/``, ``targets/``,
    ``problems/`` and ``paths/``."""
    for candidate in (_PACKAGE.parent / "models", _PACKAGE / "models"):
        if (candidate / "robots").is_dir():
            return candidate
    raise FileNotFoundError(f"the bundled models folder is missing (looked in "
                            f"{_PACKAGE.parent / 'models'} and {_PACKAGE / 'models'}); "
                            f"reinstall cr_nlp")


def bundled_file(kind: str, name: str, suffix: str = ".json") -> Path:
    """``models/<kind>/<name><suffix>``, e.g. ``bundled_file("scenes", "shelf")``."""
    return models_root() / kind / f"{name}{suffix}"
