"""`wavelight report`: out/report.md and its figures, every number taken from the stages' JSON."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from cli_helpers import RES, assert_one_error_line, copy_sample, copy_scene, invoke, ok


@pytest.fixture(scope="module")
def reported(tmp_path_factory, lambert_solved):
    scene = copy_scene(lambert_solved, tmp_path_factory.mktemp("report") / "scene")
    ok(invoke(scene, "compare", "--resolution", RES))
    ok(invoke(scene, "relight", "--name", "turned", "--rotate", "90"))
    ok(invoke(scene, "insert", "--at", "0.9", "-0.5", "0.3", "--radius", "0.25"))
    ok(invoke(scene, "report"))
    return scene


def test_report_has_its_figures_and_sections(reported):
    out = reported / "out"
    md = (out / "report.md").read_text()
    for fig in ("overview.png", "levels.png"):
        assert (out / "report" / fig).stat().st_size > 5000
        assert f"report/{fig}" in md
    for section in ("## Result", "## Refinement, level by level", "## Reflectance", "## The bases side by side",
                    "## Relighting and insertion"):
        assert section in md
    assert "`turned.png`" in md and "`insert.png`" in md
    assert "compare_lights.png" in md and (out / "compare_lights.png").stat().st_size > 5000


def test_every_number_comes_from_the_json(reported):
    out = reported / "out"
    md = (out / "report.md").read_text()
    solve = json.loads((out / "solve_report.json").read_text())
    compare = json.loads((out / "compare.json").read_text())
    assert f"| relit error (all used pixels) | {100 * solve['relit']['relative_rmse_vs_photo']:.2f} % |" in md
    assert f"| held-out error | {100 * solve['solution']['held_out_rmse']:.2f} % |" in md
    for lv in solve["solution"]["levels"]:
        assert re.search(rf"\| {lv['level']} \| {lv['coefficients']} \| .* \| {100 * lv['fit_rmse']:.2f} % \|", md)
    for row in compare["rows"]:
        assert f"| {row['basis']} | {row['coefficients']} | {100 * row['fit_rmse']:.2f} % |" in md
    insert = json.loads((out / "insert.json").read_text())
    assert f"{insert['object_pixels']} px, shadow on {insert['shadowed_pixels_5pct']} px" in md


def test_report_without_a_solve_is_one_error_line(tmp_path):
    scene = copy_sample(tmp_path / "s")
    assert_one_error_line(invoke(scene, "report"), "solve_report.json", quiet=False)


def test_report_with_a_corrupt_json_names_it(reported, tmp_path):
    scene = shutil.copytree(reported, tmp_path / "s")
    (scene / "out" / "reflectance.json").write_text("{not json")
    assert_one_error_line(invoke(scene, "report"), "reflectance.json", quiet=False)
