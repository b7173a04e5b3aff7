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


BUNDLED_KINDS = ("robots", "scenes", "paths", "targets", "problems")
"""The kinds of bundled file a name can stand for (folders of ``models/``)."""


def bundled_names(kind: str) -> list[str]:
    """The bundled names of one kind, e.g. ``bundled_names("robots")`` → ["tdcr3", …]."""
    folder = models_root() / kind
    return sorted(p.stem for p in folder.glob("*.json")) if folder.is_dir() else []


def resolve_file(value: str | Path, kind: str) -> Path:
    """The one resolver of the file arguments: ``value`` as a path when that file exists,
    else, for a bare name (no folder, no suffix), the bundled ``models/<kind>/<value>.json``.

    Works from any directory, in a checkout and after a plain ``pip install .``.

    Raises:
        FileNotFoundError: neither a file nor a bundled name; the message names the
            bundled choices of ``kind``.
    """
    if kind not in BUNDLED_KINDS:
        raise ValueError(f"kind must be one of {BUNDLED_KINDS}, got {kind!r}")
    path = Path(value)
    if path.is_file():
        return path
    bare = path.suffix == "" and path.name == str(value)
    if bare and bundled_file(kind, str(value)).is_file():
        return bundled_file(kind, str(value))
    names = ", ".join(bundled_names(kind)) or "none"
    singular = kind.removesuffix("s")
    raise FileNotFoundError(f"{value}: file not found, and not a bundled {singular} name "
                            f"(bundled: {names})")


def resolve_data_file(value: str | Path) -> Path:
    """A measurement CSV: ``value`` as a path when that file exists, else a bare name
    ("ftdcr_v6_train") of a bundled recording, ``models/data/<robot>/<name>.csv``.

    Raises:
        FileNotFoundError: neither; the message names the bundled recordings.
    """
    path = Path(value)
    if path.is_file():
        return path
    folder = models_root() / "data"
    bundled = sorted(folder.glob("*/*.csv")) if folder.is_dir() else []
    if path.suffix == "" and path.name == str(value):
        for candidate in bundled:
            if candidate.stem == str(value):
                return candidate
    names = ", ".join(p.stem for p in bundled) or "none"
    raise FileNotFoundError(f"{value}: file not found, and not a bundled recording "
                            f"(bundled: {names})")
