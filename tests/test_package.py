"""Packaging facts other code relies on."""

import ast
from pathlib import Path

import pipelines
import wavelight_cli

ROOT = Path(__file__).resolve().parents[1]


def test_imported_pipelines_is_ours():
    # An unrelated `pipelines` distribution exists on PyPI: ours must win on the import path.
    assert Path(pipelines.__file__).resolve().parent == ROOT / "pipelines"
    assert Path(wavelight_cli.__file__).resolve().parent == ROOT / "wavelight_cli"
    from pipelines.light import haar  # noqa: F401  (modules only we have)


def test_pipelines_never_imports_the_cli_layer():
    offenders = []
    for path in sorted((ROOT / "pipelines").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            offenders += [f"{path.name}: {n}" for n in names if n.split(".")[0] in ("click", "wavelight_cli")]
    assert offenders == []
