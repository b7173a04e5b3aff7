"""The public surface: one function per task at the top level of ``cr_nlp``, every public
name resolves, and every name the README and the notebooks import from ``cr_nlp`` is one."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cr_nlp

ROOT = Path(__file__).resolve().parents[2]
TASK_FUNCTIONS = ("solve_ik", "plan_trajectories", "follow_path", "solve_tension_ik",
                  "solve_statics", "calibrate", "follow_tension_path", "plan_tension_trajectories")


def test_every_public_name_resolves_and_each_task_has_its_function() -> None:
    for name in cr_nlp.__all__:
        assert getattr(cr_nlp, name) is not None, name
    for name in TASK_FUNCTIONS:
        assert name in cr_nlp.__all__ and callable(getattr(cr_nlp, name)), name
        doc = getattr(cr_nlp, name).__doc__
        assert re.search(r"metres|newtons|\bin m\b|\bm\)|\bm\.|rad", doc), (
            f"{name}: no units in {doc!r}")


def _imported_from_cr_nlp(text: str) -> set[str]:
    names = set()
    for match in re.finditer(r"from cr_nlp import (?:\(([^)]*)\)|([^\n]+))", text):
        listed = match.group(1) or match.group(2)
        names |= {n.strip().split(" as ")[0] for n in listed.split(",") if n.strip()}
    return names


def test_every_name_the_readme_and_notebooks_import_is_public() -> None:
    texts = [(ROOT / "README.md").read_text()]
    for notebook in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = json.loads(notebook.read_text())["cells"]
        texts += ["".join(c["source"]) for c in cells if c["cell_type"] == "code"]
    names = set().union(*(_imported_from_cr_nlp(t) for t in texts))
    modules = {"viz", "runtime"}
    assert names and not (names - set(cr_nlp.__all__) - modules), sorted(
        names - set(cr_nlp.__all__) - modules)


def test_renamed_and_moved_names_warn_and_return_the_new_object() -> None:
    """The mechanics names mirror the geometry ones (TensionTrajectoryPlanner beside
    TrajectoryPlanner, …) and old module addresses moved into packages; the old names
    work for one release, each with a DeprecationWarning naming the new one."""
    import importlib
    import sys
    import warnings

    old_new = {"TensionPlanner": "TensionTrajectoryPlanner",
               "TensionPlanConfig": "TensionTrajectoryConfig",
               "plan_tensions": "plan_tension_trajectories",
               "TensionFollower": "TensionPathFollower", "follow_tensions": "follow_tension_path",
               "TensionLiveIK": "TensionLiveIKSolver"}
    for old, new in old_new.items():
        module = importlib.import_module(cr_nlp._PUBLIC[old], "cr_nlp")
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            assert getattr(module, old) is getattr(cr_nlp, new)
        assert any(issubclass(w.category, DeprecationWarning) and new in str(w.message)
                   for w in seen), old
    sys.modules.pop("cr_nlp.tasks.calibrate", None)   # as a process that never imported it
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        old_module = importlib.import_module("cr_nlp.tasks.calibrate")
    assert old_module is importlib.import_module("cr_nlp.tasks.calibration.calibrate")
    assert any("cr_nlp.tasks.calibration.calibrate" in str(w.message) for w in seen)
