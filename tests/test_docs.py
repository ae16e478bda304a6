"""Pointers into the documents lead somewhere: every `DESIGN §N` names a section docs/DESIGN.md has,
every `README: Section` a section README.md has. Checked in the documents themselves, in every
string and comment of the code (the help texts, and what goes into report.md, solve_report.json,
reflectance.json, export.json ...), and in every --help as shown. tests/test_status.py checks the
files a real run writes with `broken_references` too."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest
from click.testing import CliRunner

from wavelight_cli.main import cli

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DESIGN = REPO / "docs" / "DESIGN.md"
DESIGN_REF = re.compile(r"DESIGN(?:\.md)?\s*§\s*(\d+)")
README_REF = re.compile(r"README(?:\.md)?:\s*(\S.*)")


def _sections(path: Path) -> list[str]:
    return [ln.lstrip("#").strip() for ln in path.read_text().splitlines() if re.match(r"#{2,3} ", ln)]


def readme_titles() -> list[str]:
    """README's section titles without a trailing note in parentheses ("Conventions (fixed; ...)")."""
    return [re.sub(r"\s*\(.*\)$", "", t).lower() for t in _sections(README)]


def design_numbers() -> set[str]:
    return {m[1] for t in _sections(DESIGN) if (m := re.match(r"(\d+)\.", t))}


def broken_references(text: str) -> list[str]:
    """The references in `text` that point to no section: `DESIGN §N` without a `## N.` heading in
    docs/DESIGN.md, `README: X` where X does not begin with one of README.md's section titles."""
    text = " ".join(text.split())
    bad = [m[0] for m in DESIGN_REF.finditer(text) if m[1] not in design_numbers()]
    titles = readme_titles()
    for m in README_REF.finditer(text):
        after = m[1].lower()
        if not any(after.startswith(t) for t in titles):
            bad.append(m[0][:60])
    return bad


def python_texts(path: Path) -> list[str]:
    """Every string (adjacent literals joined, as Python joins them) and comment of a module."""
    source = path.read_text()
    texts = [n.value for n in ast.walk(ast.parse(source)) if isinstance(n, ast.Constant) and isinstance(n.value, str)]
    texts += [t.string for t in tokenize.generate_tokens(io.StringIO(source).readline) if t.type == tokenize.COMMENT]
    return texts


SOURCES = sorted([*(REPO / "wavelight_cli").rglob("*.py"), *(REPO / "pipelines").rglob("*.py")])


def test_the_documents_have_sections_to_point_to():
    assert {"1", "2", "3", "4", "5", "6"} <= design_numbers()
    assert {"commands", "scene folder", "outputs", "conventions"} <= set(readme_titles())


def test_the_check_finds_a_broken_reference():
    assert broken_references("see README: Exports") == ["README: Exports"]
    assert broken_references("(DESIGN §99)") == ["DESIGN §99"]
    assert broken_references("README: Relight, insert, export, report (export); DESIGN §2, docs/DESIGN.md §6") == []


@pytest.mark.parametrize("doc", [README, DESIGN], ids=lambda p: p.name)
def test_document_references(doc):
    assert broken_references(doc.read_text()) == []


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(REPO)))
def test_code_references(path):
    bad = [ref for text in python_texts(path) for ref in broken_references(text)]
    assert bad == [], f"{path.relative_to(REPO)}: {bad}"


@pytest.mark.parametrize("name", ["", *sorted(cli.commands)])
def test_help_references(name):
    result = CliRunner().invoke(cli, [*([name] if name else []), "--help"])
    assert result.exit_code == 0
    assert broken_references(result.stdout) == []
