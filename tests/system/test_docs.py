"""The user documentation stays true: the README's two commands are the ones CI and users
run, its Python blocks parse, every link in README.md, CHANGELOG.md, models/README.md and
docs/*.md points at a file (and heading) inside the repository, and docs/benchmarks.md's
sections are well formed for ``cr-nlp bench --markdown``."""

import ast
import re
from pathlib import Path

import pytest

from cr_nlp.bench._common import section_markers

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "models" / "README.md",
        *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to -."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = path.read_text()
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    return {_slug(line.lstrip("#")) for line in text.splitlines() if line.startswith("#")}


def test_the_readme_is_short_and_keeps_its_two_commands() -> None:
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 300
    assert "pip install . && cr-nlp demo" in readme
    ci = (ROOT / ".ci" / "run").read_text()
    test_command = "pip install -e '.[test]' && pytest"
    assert test_command in readme and test_command in ci


def test_the_readme_python_blocks_parse() -> None:
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert len(blocks) >= 3  # IK, trajectory planning, path following
    for block in blocks:
        ast.parse(block)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_link_points_inside_the_repository(doc: Path) -> None:
    for target in LINK.findall(doc.read_text()):
        assert "://" not in target, f"{doc.name}: {target} points outside the repository"
        file, _, anchor = target.partition("#")
        path = (doc.parent / file).resolve() if file else doc
        assert path.is_file() and ROOT in path.parents, f"{doc.name}: no file {target}"
        if anchor:
            assert anchor in _anchors(path), f"{doc.name}: no heading #{anchor} in {file}"
    assert "DESIGN.md" not in doc.read_text()


def test_the_benchmarks_file_has_well_formed_sections() -> None:
    text = (ROOT / "docs" / "benchmarks.md").read_text()
    names = re.findall(r"^<!-- cr-nlp bench: (\S+) -->$", text, re.M)
    assert {"ik-free", "ik-lattice", "ik-throughput", "plan", "follow"} <= set(names)
    assert len(names) == len(set(names))
    for name in names:
        begin, end = section_markers(name)
        assert text.count(begin) == 1 and text.count(end) == 1
        section = text[text.index(begin):text.index(end)]
        assert "\n| " in section and re.search(r"20\d\d-\d\d-\d\d", section), name


def test_the_readme_imports_exist() -> None:
    """Every name a README Python block imports from cr_nlp is exported at the top level."""
    import cr_nlp

    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    imported = [alias.name for block in blocks for node in ast.walk(ast.parse(block))
                if isinstance(node, ast.ImportFrom) and node.module == "cr_nlp"
                for alias in node.names]
    assert imported and [name for name in imported if not hasattr(cr_nlp, name)] == []
