"""Size limits of the package (issue 39): no module over ``MAX_MODULE_LINES`` lines and
no function over ``MAX_FUNCTION_LINES`` lines in ``cr_nlp/`` unless its docstring says
why in a line starting with "Long: ". A long module hides a stage or a second concern
(docs/design.md, "The house"); a long function, pieces that split naturally.

Every module is parsed with ``ast`` (nothing is imported); a function's length counts
its def line to its last, docstring included.
"""

from __future__ import annotations

import ast
from pathlib import Path

import cr_nlp

ROOT = Path(cr_nlp.__file__).resolve().parent
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80
LONG = "Long: "

EXEMPT: frozenset[str] = frozenset()
"""Modules (relative to cr_nlp/) the limits skip: none."""


def _functions(tree: ast.AST) -> list[ast.FunctionDef | ast.AsyncFunctionDef]:
    return [node for node in ast.walk(tree)
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))]


def _has_reason(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    doc = ast.get_docstring(node) or ""
    return any(line.strip().startswith(LONG) for line in doc.splitlines())


def oversized(root: Path = ROOT, exempt: frozenset[str] = EXEMPT) -> list[str]:
    """'path: N lines' for each module over the limit and 'path:line name: N lines' for
    each function over it without a "Long: " line in its docstring."""
    found = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel in exempt:
            continue
        text = path.read_text()
        lines = len(text.splitlines())
        if lines > MAX_MODULE_LINES:
            found.append(f"cr_nlp/{rel}: {lines} lines (over {MAX_MODULE_LINES})")
        for node in _functions(ast.parse(text, filename=str(path))):
            length = node.end_lineno - node.lineno + 1
            if length > MAX_FUNCTION_LINES and not _has_reason(node):
                found.append(f"cr_nlp/{rel}:{node.lineno} {node.name}: {length} lines (over "
                             f"{MAX_FUNCTION_LINES}, no '{LONG}' reason in its docstring)")
    return found


def test_the_checker_names_long_modules_and_unexplained_long_functions(
        tmp_path: Path) -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    (tmp_path / "short.py").write_text("def f():\n    return 1\n")
    (tmp_path / "long_function.py").write_text(f"def f():\n{body}\n")
    (tmp_path / "explained.py").write_text(
        f'def g():\n    """Why.\n\n    {LONG}one loop over shared state.\n    """\n{body}\n')
    (tmp_path / "long_module.py").write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    (tmp_path / "skipped.py").write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    found = oversized(tmp_path, frozenset({"skipped.py"}))
    assert found == [
        f"cr_nlp/long_function.py:1 f: {MAX_FUNCTION_LINES + 1} lines (over "
        f"{MAX_FUNCTION_LINES}, no '{LONG}' reason in its docstring)",
        f"cr_nlp/long_module.py: {MAX_MODULE_LINES + 1} lines (over {MAX_MODULE_LINES})"]


def test_no_module_or_function_of_cr_nlp_is_over_its_size_limit() -> None:
    found = oversized()
    assert not found, "over the size limits (split it, or say why: 'Long: …'):\n" + \
        "\n".join(found)
