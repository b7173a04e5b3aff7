"""The installed package carries every subpackage and every bundled model file.

A regular ``pip install .`` installs exactly what ``pyproject.toml`` lists, so a
subpackage missing from ``packages`` or a model file missed by ``package-data`` would
only break on a user's machine (the tests run from an editable install).
"""

import fnmatch
import tomllib
from pathlib import Path

from cr_nlp._resources import bundled_file, models_root

ROOT = Path(__file__).resolve().parents[2]


def _setuptools() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_subpackage_is_listed():
    listed = set(_setuptools()["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts)
             for p in (ROOT / "cr_nlp").rglob("__init__.py")}
    assert found <= listed, f"add to [tool.setuptools] packages: {sorted(found - listed)}"


def test_every_model_file_is_package_data():
    setup = _setuptools()
    assert setup["package-dir"]["cr_nlp.models"] == "models"
    patterns = setup["package-data"]["cr_nlp.models"]
    files = [p.relative_to(ROOT / "models").as_posix()
             for p in (ROOT / "models").rglob("*") if p.is_file()]
    missed = [f for f in files if not any(fnmatch.fnmatch(f, pat) and
                                          f.count("/") == pat.count("/") for pat in patterns)]
    assert files and not missed, f"model files a wheel would not carry: {missed}"


def test_bundled_files_resolve():
    assert models_root() == ROOT / "models"
    for kind, name in (("robots", "tdcr3"), ("scenes", "shelf"), ("paths", "icra"),
                       ("problems", "tdcr3_shelf"), ("targets", "tdcr3_lattice")):
        assert bundled_file(kind, name).is_file(), (kind, name)
