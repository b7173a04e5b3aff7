"""The package's import structure: no import circle, and no lower layer importing a higher one.

Every module under ``cr_nlp`` is parsed with ``ast`` (nothing is imported), and every import
statement — at module level, inside functions, under ``TYPE_CHECKING`` — becomes an edge
of the intra-package import graph (relative imports resolved; ``from pkg import name``
points at ``pkg.name`` when that is a module, else at ``pkg``). The layers (docs/design.md §5)
are model → world → stages → tasks → interfaces; ``_resources``, ``runtime``,
``_programs`` (with ``_fingerprint`` and ``_program_clock``) and ``_files`` sit below them
all, the package's ``__init__`` (the public surface) above.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import cr_nlp

ROOT = Path(cr_nlp.__file__).resolve().parent
PACKAGE = "cr_nlp"

# Lowest first. A top-level module or package not named here (cli, bench, demo, viz,
# batch, view, …) is an interface; the package __init__ re-exports the public API.
LAYERS = {"_resources": 0, "runtime": 0, "_programs": 0, "_program_clock": 0,
          "_fingerprint": 0, "_files": 0, "_moved": 0, "_by_shape": 0, "_cached_jit": 0,
          "_compile_effort": 0,
          "model": 1, "world": 2, "stages": 3, "tasks": 4}
INTERFACE = 5
FACADE = 6
LAYER_NAMES = {0: "base (_resources, runtime, _programs, _fingerprint, _files)", 1: "model",
               2: "world",
               3: "stages", 4: "tasks", 5: "interfaces (cli, bench, demo, viz, …)",
               6: "cr_nlp/__init__"}


def module_files(root: Path = ROOT, package: str = PACKAGE) -> dict[str, Path]:
    """Dotted module name → file, for every .py file under ``root``."""
    modules = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join([package, *parts])] = path
    return modules


def _is_package(name: str, modules: dict[str, Path]) -> bool:
    return modules[name].name == "__init__.py"


def imports_of(name: str, modules: dict[str, Path], package: str = PACKAGE) -> set[str]:
    """The modules of the package that module ``name`` imports (anywhere in its body)."""
    tree = ast.parse(modules[name].read_text(), filename=str(modules[name]))
    here = name if _is_package(name, modules) else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = here.split(".")
                base_parts = base_parts[:len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            targets = []
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                targets.append(sub if sub in modules else base)
        else:
            continue
        for target in targets:
            # "import cr_nlp.model.kinematics" names that module; keep the longest known prefix.
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target.split(".")[0] == package and target != name:
                found.add(target)
    return found


def import_graph(root: Path = ROOT, package: str = PACKAGE) -> dict[str, set[str]]:
    modules = module_files(root, package)
    return {name: imports_of(name, modules, package) for name in modules}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = 0

    def visit(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return components


def layer(name: str) -> int:
    parts = name.split(".")
    if len(parts) == 1:
        return FACADE
    return LAYERS.get(parts[1], INTERFACE)


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """'a (layer) imports b (higher layer)' for every import against the layering."""
    return [f"{a} ({LAYER_NAMES[layer(a)]}) imports {b} ({LAYER_NAMES[layer(b)]})"
            for a in sorted(graph) for b in sorted(graph[a]) if layer(b) > layer(a)]


def _write_package(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = root / "pkg" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / "pkg"


# ---------------------------------------------------------------- the checker itself


def test_the_checker_finds_a_circle_through_a_function_level_relative_import(
        tmp_path: Path) -> None:
    pkg = _write_package(tmp_path, {
        "__init__.py": "",
        "a.py": "from .b import f\n",
        "sub/__init__.py": "",
        "sub/b.py": "",
        "b.py": "def f():\n    from . import a\n    from .sub import b\n",
        "c.py": "import pkg.sub.b\nfrom pkg.sub import b\n",
    })
    graph = import_graph(pkg, "pkg")
    assert graph["pkg.b"] == {"pkg.a", "pkg.sub.b"}
    assert graph["pkg.c"] == {"pkg.sub.b"}
    assert cycles(graph) == [["pkg.a", "pkg.b"]]


def test_the_checker_finds_an_upward_import(tmp_path: Path) -> None:
    pkg = _write_package(tmp_path, {
        "__init__.py": "",
        "model/__init__.py": "",
        "model/kin.py": "from ..tasks.ik import solve\n",
        "tasks/__init__.py": "",
        "tasks/ik.py": "from ..model import kin\n",
    })
    graph = import_graph(pkg, "pkg")
    found = upward_imports(graph)
    assert found == ["pkg.model.kin (model) imports pkg.tasks.ik (tasks)"]
    assert cycles(graph) == [["pkg.model.kin", "pkg.tasks.ik"]]


# ---------------------------------------------------------------- cr_nlp


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph()


def test_cr_nlp_has_no_import_circle(graph: dict[str, set[str]]) -> None:
    assert "cr_nlp.model.kinematics" in graph and graph["cr_nlp.tasks.geometry.ik"]
    found = cycles(graph)
    assert not found, "import circles in cr_nlp:\n" + "\n".join(" ↔ ".join(c) for c in found)


def test_no_lower_layer_imports_a_higher_one(graph: dict[str, set[str]]) -> None:
    found = upward_imports(graph)
    assert not found, "imports against the layers:\n" + "\n".join(found)


STAGE_PACKAGES = {"explore": 0, "refine": 1, "polish": 2}
"""The stage packages, lowest first: refine starts from explore's seeds, polish from
anything; a module at ``stages/`` itself (``_chunks``) sits below all three."""


def stage_package(name: str) -> int | None:
    """The rank of ``name``'s stage package (-1: a module of ``stages/`` itself; None:
    not a stage module)."""
    parts = name.split(".")
    if len(parts) < 3 or parts[1] != "stages":
        return None
    return STAGE_PACKAGES.get(parts[2], -1) if len(parts) > 3 else (
        None if parts[2] in STAGE_PACKAGES else -1)


def stage_imports_against_the_order(graph: dict[str, set[str]]) -> list[str]:
    """'a imports b' for each stage module importing one of a higher stage package."""
    found = []
    for a in sorted(graph):
        rank = stage_package(a)
        if rank is None:
            continue
        for b in sorted(graph[a]):
            other = stage_package(b)
            if other is not None and other > rank:
                found.append(f"{a} imports {b}")
    return found


def test_the_checker_finds_a_stage_importing_a_later_stage(tmp_path: Path) -> None:
    graph = {"cr_nlp.stages.explore._roadmap": {"cr_nlp.stages.refine._lm",
                                                  "cr_nlp.stages._chunks"},
             "cr_nlp.stages.refine._lm": {"cr_nlp.stages.explore._seed_pool"},
             "cr_nlp.stages._chunks": {"cr_nlp.stages.polish._ipopt"}}
    assert stage_imports_against_the_order(graph) == [
        "cr_nlp.stages._chunks imports cr_nlp.stages.polish._ipopt",
        "cr_nlp.stages.explore._roadmap imports cr_nlp.stages.refine._lm"]


def test_stages_are_three_packages_that_import_only_downward(
        graph: dict[str, set[str]]) -> None:
    stages = ROOT / "stages"
    loose = sorted(p.name for p in stages.glob("*.py") if p.name not in (
        "__init__.py", "_chunks.py", "_faces.py"))
    assert not loose, f"modules of stages/ outside explore/, refine/, polish/: {loose}"
    assert sorted(p.name for p in stages.iterdir() if p.is_dir()
                  and p.name != "__pycache__") == sorted(STAGE_PACKAGES)
    found = stage_imports_against_the_order(graph)
    assert not found, ("stage packages importing a later one (order: explore → refine → "
                       "polish):\n" + "\n".join(found))


def test_every_cli_module_is_a_registered_subcommand(graph: dict[str, set[str]]) -> None:
    from cr_nlp.cli.main import SUBCOMMANDS

    helpers = {"cr_nlp.cli", "cr_nlp.cli._io", "cr_nlp.cli.main", "cr_nlp.cli.__main__"}
    # Private modules (cli/_name.py) are one subcommand's helpers, not subcommands.
    modules = {name for name in graph if name.startswith("cr_nlp.cli.")
               and not name.rsplit(".", 1)[1].startswith("_")} - helpers
    assert modules == {m.__name__ for m in SUBCOMMANDS}
    assert all(callable(m.add_parser) for m in SUBCOMMANDS)
    # The shared helpers import no subcommand, and no subcommand imports another one
    # (what two subcommands share lives in _io).
    assert not {m for m in graph["cr_nlp.cli._io"] if m.startswith("cr_nlp.cli")}
    crossing = [f"{a} imports {b}" for a in sorted(modules) for b in sorted(graph[a])
                if b in modules]
    assert not crossing, "subcommands importing each other:\n" + "\n".join(crossing)


def test_internal_modules_are_private_by_name() -> None:
    """The stages layer is internal machinery: every module there is private by name
    (``_name.py``); users import the tasks (or the top-level ``cr_nlp``), never a stage."""
    stages = Path(cr_nlp.__file__).parent / "stages"
    public = sorted(p.name for p in stages.glob("*.py")
                    if not p.name.startswith("_"))
    assert not public, f"public modules in cr_nlp/stages: {public}"


def family_private_imports(graph: dict[str, set[str]]) -> list[str]:
    """'a imports b' where b is a private module of a task family that a is not in. The
    families are the packages under ``tasks`` (``geometry``, ``mechanics``,
    ``calibration``); they share only the modules directly in ``tasks`` (``_result``,
    ``_timing``, ``paths``, ``readers``)."""

    def family(name: str) -> str | None:
        parts = name.split(".")
        return parts[2] if len(parts) >= 4 and parts[1] == "tasks" else None

    found = []
    for a in sorted(graph):
        for b in sorted(graph[a]):
            private = b.rpartition(".")[2].startswith("_")
            if private and family(b) and family(a) != family(b) and a.startswith("cr_nlp.tasks"):
                found.append(f"{a} ({family(a)}) imports {b} ({family(b)})")
    return found


def stage_private_imports(graph: dict[str, set[str]]) -> list[str]:
    """'a imports b' where a is in ``tasks`` and b is a private module of ``stages``: the
    tasks reach the stages through the packages' public faces only."""
    return [f"{a} imports {b}" for a in sorted(graph) if a.startswith("cr_nlp.tasks.")
            for b in sorted(graph[a]) if b.startswith("cr_nlp.stages.")
            and any(part.startswith("_") for part in b.split(".")[2:])]


def test_tasks_import_the_stages_through_their_public_faces(
        graph: dict[str, set[str]]) -> None:
    assert graph["cr_nlp.tasks.geometry.ik"] & {"cr_nlp.stages.refine", "cr_nlp.stages.polish"}
    found = stage_private_imports(graph)
    assert not found, "tasks importing a private stage module:\n" + "\n".join(found)
    assert stage_private_imports({"cr_nlp.tasks.geometry.ik": {"cr_nlp.stages.refine._lm"}}) \
        == ["cr_nlp.tasks.geometry.ik imports cr_nlp.stages.refine._lm"]


def test_task_families_import_no_private_module_of_another(
        graph: dict[str, set[str]]) -> None:
    assert "cr_nlp.tasks.mechanics.ik" in graph
    found = family_private_imports(graph)
    assert not found, "a task family reaching into another's private modules:\n" + \
        "\n".join(found)


def test_the_family_check_finds_a_private_import() -> None:
    graph = {"cr_nlp.tasks.mechanics.follow": {"cr_nlp.tasks.geometry._follow_result",
                                               "cr_nlp.tasks._result"},
             "cr_nlp.tasks.geometry.ik": {"cr_nlp.tasks.mechanics.ik"}}
    assert family_private_imports(graph) == [
        "cr_nlp.tasks.mechanics.follow (mechanics) imports cr_nlp.tasks.geometry._follow_result "
        "(geometry)"]
