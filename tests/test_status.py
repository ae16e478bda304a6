"""What a user reads after the run (issue 18): `status` shows every stage built on a stale solve
(relight, insert, export) as stale and says why; `-q solve` on an up-to-date scene still prints
its result; the files the stages write point to document sections that exist."""

from __future__ import annotations

import json

import pytest
from cli_helpers import RES, copy_scene, invoke, ok, run_proc
from test_docs import broken_references

DOWNSTREAM = ("relight", "insert", "export")
SOLVE_ARGS = ("solve", "--resolution", RES, "--reflectance", "lambert")  # as conftest's lambert_solved


@pytest.fixture(scope="module")
def downstream(lambert_solved, tmp_path_factory):
    """The solved sample with a relight, an insert, the exports and the report (read-only)."""
    scene = copy_scene(lambert_solved, tmp_path_factory.mktemp("downstream") / "scene")
    ok(invoke(scene, "relight"))
    ok(invoke(scene, "insert", "--at", "0.8", "-0.6", "0.25", "--radius", "0.25"))
    ok(invoke(scene, "export"))
    ok(invoke(scene, "report"))
    return scene


def _status(scene) -> dict:
    result = invoke(scene, "status", "--json")
    ok(result)
    return {r["stage"]: r for r in json.loads(result.stdout)}


def _table(scene) -> dict:
    result = invoke(scene, "status")
    ok(result)
    return {ln.split()[0]: ln.split()[1] for ln in result.stdout.splitlines()[1:]}


def test_everything_is_fresh_after_the_run(downstream):
    rows = _status(downstream)
    for stage in ("solve", *DOWNSTREAM):
        assert rows[stage]["state"] == "fresh", rows[stage]


def test_a_stale_solve_makes_relight_insert_and_export_stale(downstream, tmp_path):
    """Only the solve is touched (one of its outputs is gone): the stages built on it say so."""
    scene = copy_scene(downstream, tmp_path / "scene")
    (scene / "out" / "solve_report.json").unlink()
    rows = _status(scene)
    assert rows["solve"]["state"] == "stale"
    assert rows["solve"]["reason"] == "output missing or damaged: out/solve_report.json"
    for stage in DOWNSTREAM:
        assert rows[stage]["state"] == "stale", rows[stage]
        assert rows[stage]["reason"] == "upstream stale: solve", rows[stage]
    table = _table(scene)
    assert all(table[s] == "stale" for s in ("solve", *DOWNSTREAM)), table


def test_a_new_photo_makes_the_solve_and_everything_after_it_stale(downstream, tmp_path):
    from pipelines.io import images

    scene = copy_scene(downstream, tmp_path / "scene")
    images.write_exr(scene / "image.exr", images.read_image(scene / "image.exr").pixels * 1.01)
    rows = _status(scene)
    assert rows["solve"]["state"] == "stale" and "photo" in rows["solve"]["reason"]
    for stage in DOWNSTREAM:
        assert rows[stage]["state"] == "stale", rows[stage]
    assert rows["export"]["reason"] == "upstream stale: solve"  # export reads no photo: only the solve says it


def test_quiet_solve_on_an_up_to_date_scene_prints_its_result(downstream, tmp_path):
    """A real process: `wavelight -q solve` skips the solve and still prints the result lines."""
    scene = copy_scene(downstream, tmp_path / "scene")
    loud = run_proc(scene, *SOLVE_ARGS)
    assert loud.returncode == 0, loud.stderr
    assert "solve: skipped, up to date" in loud.stderr
    quiet = run_proc(scene, "-q", *SOLVE_ARGS)
    assert quiet.returncode == 0, quiet.stderr
    assert quiet.stderr == ""
    assert quiet.stdout == loud.stdout
    lines = quiet.stdout.splitlines()
    assert len(lines) == 2 and lines[0].startswith("solve: wavelet, ") and lines[1].startswith("solve: reflectance ")


def test_written_files_point_to_sections_that_exist(downstream):
    """report.md, report.html, solve_report.json, reflectance.json, export.json, ... as written."""
    files = [p for p in (downstream / "out").rglob("*") if p.suffix in {".md", ".json", ".html"}]
    names = {p.name for p in files}
    assert {"report.md", "report.html", "solve_report.json", "reflectance.json", "export.json"} <= names
    pointers = 0
    for path in files:
        text = path.read_text()
        assert broken_references(text) == [], path
        pointers += text.count("README:") + text.count("DESIGN")
    assert pointers > 0  # the check has something to check (reflectance.json, export.json point to the README)
