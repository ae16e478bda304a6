"""`wavelight report`: out/report.md, out/report.html and their figures, every number taken from the
stages' JSON. (The figures themselves: test_report_figures.py; the page in a browser:
test_report_browser.py.)"""

from __future__ import annotations

import base64
import json
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import RES, assert_one_error_line, copy_sample, copy_scene, invoke, ok

_REPORTED: dict[str, Path] = {}


def reported_scene(tmp_path_factory, lambert_solved) -> Path:
    """The sample scene after solve, compare, two relights (one turned, one of the photo's own view
    and light, which has a residual), an insert, export and report (made once per session; read-only)."""
    if "scene" not in _REPORTED:
        scene = copy_scene(lambert_solved, tmp_path_factory.mktemp("report") / "scene")
        ok(invoke(scene, "compare", "--resolution", RES))
        ok(invoke(scene, "relight", "--name", "turned", "--rotate", "90"))
        ok(invoke(scene, "relight", "--name", "same"))
        ok(invoke(scene, "insert", "--at", "0.9", "-0.5", "0.3", "--radius", "0.25"))
        ok(invoke(scene, "export"))
        ok(invoke(scene, "report"))
        _REPORTED["scene"] = scene
    return _REPORTED["scene"]


@pytest.fixture
def reported(tmp_path_factory, lambert_solved):
    return reported_scene(tmp_path_factory, lambert_solved)


class _Tags(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags: list[tuple[str, dict]] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))


def _tags(html: str) -> list[tuple[str, dict]]:
    p = _Tags()
    p.feed(html)
    return p.tags


def _md_images(md: str) -> list[tuple[str, str]]:
    return re.findall(r"!\[([^\]]*)\]\(([^)]+)\)", md)


def test_report_has_its_figures_and_sections(reported):
    out = reported / "out"
    md = (out / "report.md").read_text()
    for fig in ("overview.png", "light.png", "levels.png"):
        assert (out / "report" / fig).stat().st_size > 5000
        assert f"(report/{fig})" in md
    for section in ("## Result", "## Recovered light", "## Refinement, level by level", "## Reflectance",
                    "## The bases side by side", "## Relighting and insertion", "## Exports"):
        assert section in md
    assert "`turned.png`" in md and "`insert.png`" in md
    assert "(compare_lights.png)" in md and (out / "compare_lights.png").stat().st_size > 5000
    assert "(compare.png)" in md
    for _, rel in _md_images(md):  # every image the report shows is on disk
        assert (out / rel).is_file(), rel


def test_relight_and_insert_outputs_are_shown_as_images(reported):
    """They were listed as `name.png` text: now each is an image, with its heat map and numbers."""
    out = reported / "out"
    md = (out / "report.md").read_text()
    shown = {rel for _, rel in _md_images(md)}
    assert {"turned.png", "same.png", "insert.png", "report/output-same-residual.png",
            "report/output-insert-shadow.png"} <= shown
    assert "report/output-turned-residual.png" not in shown  # a turned light has no reference
    same = json.loads((out / "same.json").read_text())
    assert f"| error vs reference | {100 * same['relative_rmse_vs_photo']:.2f} % (" in md
    from wavelight_cli.outputs import read_png_text

    scale = float(read_png_text(out / "same_residual.png")["wavelight:heat_scale"])
    assert f"white = {scale:.4g}" in md
    insert = json.loads((out / "insert.json").read_text())
    assert f"{insert['object_pixels']} px, shadow on {insert['shadowed_pixels_5pct']} px" in md
    assert "white = 50 % darker" in md


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
    export = json.loads((out / "export" / "export.json").read_text())
    assert " ".join(f"{e:.4g}" for e in export["energy_rgb"]) in md


def test_the_levels_caption_says_where_plus_z_is(reported):
    md = (reported / "out" / "report.md").read_text()
    assert "middle of the top row" not in md
    assert "+Z at the top left, above +X; the side faces +X, +Y, -X, -Y left to right" in md


def test_the_light_section_states_its_scale(reported):
    from pipelines.io.light_file import read_solution_light

    out = reported / "out"
    md = (out / "report.md").read_text()
    texels, _, _ = read_solution_light(out / "coefficients.h5")
    section = md.split("## Recovered light")[1].split("## ")[0]
    assert f"to {texels.max():.4g} (white)" in section
    assert "the colour bar's ticks are radiance values (" in section
    assert "+Z in the centre square" in section


def test_exports_say_what_each_file_is_for(reported):
    md = (reported / "out" / "report.md").read_text()
    section = md.split("## Exports")[1]
    for tool, files in (("Mitsuba 3", ("`mitsuba/light.exr`", "`mitsuba/emitter.xml`", "`mitsuba/bsdf.xml`")),
                        ("Blender", ("`blender/light_equirect.exr`", "`blender/material.json`",
                                     "`blender/setup_material.py`")),
                        ("OpenGL / three.js", tuple(f"`opengl/{f}.exr`" for f in ("px", "nx", "py", "ny", "pz", "nz")))):
        row = next(ln for ln in section.splitlines() if ln.startswith(f"| {tool} |"))
        assert all(f in row for f in files), row
        assert len(row.split(" | ")[-1]) > 40  # a how-to
    assert "The material (" in section and "is exported too" in section


def test_the_html_page_is_self_contained(reported):
    out = reported / "out"
    html = (out / "report.html").read_text()
    tags = _tags(html)
    imgs = [a for t, a in tags if t == "img"]
    assert len(imgs) >= 12
    import cv2

    for a in imgs:
        assert a["src"].startswith("data:image/png;base64,"), a["src"][:60]
        png = base64.b64decode(a["src"].split(",", 1)[1])
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.shape[1] > 0
        assert a.get("alt")
    assert not [t for t, a in tags if t in ("link", "iframe", "object", "embed")]
    assert not [a for t, a in tags if t == "script" and "src" in a]
    assert not [a for t, a in tags if "href" in a and not a["href"].startswith("#")]
    assert not re.search(r"https?://|url\(|@import", html)
    csp = next(a["content"] for t, a in tags if t == "meta" and a.get("http-equiv") == "Content-Security-Policy")
    assert "default-src 'none'" in csp and "img-src data:" in csp
    # the markdown's images are all in the page (plus the slider's photo and relit)
    md = (out / "report.md").read_text()
    alts = [a["alt"] for a in imgs]
    for alt, _ in _md_images(md):
        assert alt in alts
    assert sum(1 for t, a in tags if t == "input" and a.get("type") == "range") == 1


def test_the_html_page_has_the_reports_numbers(reported):
    out = reported / "out"
    html = (out / "report.html").read_text()
    solve = json.loads((out / "solve_report.json").read_text())
    compare = json.loads((out / "compare.json").read_text())
    assert f"<td>relit error (all used pixels)</td><td>{100 * solve['relit']['relative_rmse_vs_photo']:.2f} %" in html
    for row in compare["rows"]:
        assert f"<td>{row['basis']}</td><td class=\"r\">{row['coefficients']}</td>" in html
    for section in ("result", "light", "levels", "reflectance", "bases", "outputs", "exports"):
        assert f'<section id="{section}">' in html and f'href="#{section}"' in html
    assert "<code>mitsuba/emitter.xml</code>" in html and "&lt;emitter&gt;" in html


PROBE_REFLECTANCE = {  # the shape `solve --reflectance auto` writes when the probe is rejected (solve version 5)
    "format": "wavelight-reflectance-1", "model": "lambert", "kd": [1.0, 1.0, 1.0], "ks": [0.0, 0.0, 0.0], "n": 1.0,
    "ks_over_kd": 0.0, "mode": "auto", "chosen_round": 0,
    "decision": "lambert: a blinn-phong term fitted with the Lambertian light fixed is not significant",
    "candidates": {"lambert": {"held_out_rmse": 0.0306, "fit_rmse": 0.0327},
                   "probe": {"pixels": 5580, "fit_rmse": 0.0278, "held_out_rmse": 0.0297, "gain": 0.0033,
                             "compared_on": "held-out rows of the probe", "lambert_rmse_same_rows": 0.0298,
                             "ks_significant": False}},
    "rounds": [{"round": 0, "kind": "round", "material": {"model": "lambert", "kd": [1, 1, 1], "ks": [0, 0, 0], "n": 1.0},
                "fit_rmse": 0.0327, "held_out_rmse": 0.0306, "light_seconds": 8.0},
               {"round": 1, "kind": "probe",
                "material": {"model": "blinn-phong", "kd": [1, 1, 1], "ks": [1e-5] * 3, "n": 8192.0},
                "fit_rmse": 0.0278, "held_out_rmse": 0.0297, "light_seconds": 0.0, "lambert_rmse_same_rows": 0.0298,
                "lm": {"pixels": 5580}}]}


def test_reflectance_rounds_and_stale_figures(reported, tmp_path):
    scene = copy_scene(reported, tmp_path / "s")
    out = scene / "out"
    (out / "reflectance.json").write_text(json.dumps(PROBE_REFLECTANCE))
    (out / "report" / "output-gone-residual.png").write_bytes((out / "report" / "overview.png").read_bytes())
    for name in ("turned.json", "turned.png", "turned.exr"):
        (out / name).unlink()
    ok(invoke(scene, "report"))
    md = (out / "report.md").read_text()
    assert "![reflectance rounds](report/reflectance.png)" in md
    assert "| probe | probe (LM, light of round 0 fixed) |" in md and md.count("| not kept |") == 1
    assert "| 2.97 % (Lambert on these rows: 2.98 %) | not kept |" in md
    assert "| 0 | light solved under this material | lambert kd (1, 1, 1) | 3.27 % | 3.06 % | **kept** |" in md
    assert ("on 5580 pixels; no light is solved for it, so its errors are over its own rows: on the held-out rows "
            "of the probe it has 2.97 % against Lambert's 2.98 % on the same rows (gain 0.33 %); it was not kept.") in md
    assert not (out / "report" / "output-gone-residual.png").exists()  # an earlier run's figure
    assert "turned.png" not in md and "turned.png" not in (out / "report.html").read_text()


def test_the_probe_of_a_real_auto_solve_is_reported_against_lambert_on_its_rows(lambert_solved, tmp_path):
    """`solve` with its default --reflectance auto on the (Lambertian) sample: the probe is
    rejected; the report quotes its error and Lambert's on the same rows from reflectance.json,
    not round 0's error over other pixels."""
    scene = copy_scene(lambert_solved, tmp_path / "s")
    ok(invoke(scene, "solve", "--resolution", RES))
    ok(invoke(scene, "report"))
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    (probe,) = [r for r in refl["rounds"] if r.get("kind") == "probe"]
    md = (scene / "out" / "report.md").read_text()
    section = md.split("## Reflectance")[1].split("\n## ")[0]
    assert (f"it has {100 * probe['held_out_rmse']:.2f} % against Lambert's "
            f"{100 * probe['lambert_rmse_same_rows']:.2f} % on the same rows") in section
    assert f"(Lambert on these rows: {100 * probe['lambert_rmse_same_rows']:.2f} %) | not kept |" in section
    assert "| 1 |" not in section  # the probe is not round 1 of the light
    assert (scene / "out" / "report" / "reflectance.png").is_file()


def test_a_report_of_a_solve_alone(lambert_solved, tmp_path):
    scene = copy_scene(lambert_solved, tmp_path / "s")
    ok(invoke(scene, "report"))
    out = scene / "out"
    md = (out / "report.md").read_text()
    for absent in ("## The bases side by side", "## Relighting and insertion", "## Exports", "report/reflectance.png"):
        assert absent not in md
    html = (out / "report.html").read_text()
    assert html.count("<img ") == len(_md_images(md)) + 2  # + the slider's two images
    assert sorted(p.name for p in (out / "report").iterdir()) == ["levels.png", "light.png", "overview.png",
                                                                   "photo.png", "relit.png"]


def test_report_without_a_solve_is_one_error_line(tmp_path):
    scene = copy_sample(tmp_path / "s")
    assert_one_error_line(invoke(scene, "report"), "solve_report.json", quiet=False)


def test_report_with_a_corrupt_json_names_it(reported, tmp_path):
    scene = shutil.copytree(reported, tmp_path / "s")
    (scene / "out" / "reflectance.json").write_text("{not json")
    assert_one_error_line(invoke(scene, "report"), "reflectance.json", quiet=False)


def test_report_with_a_corrupt_export_json_names_it(reported, tmp_path):
    scene = shutil.copytree(reported, tmp_path / "s")
    (scene / "out" / "export" / "export.json").write_text("[1, 2")
    before = (scene / "out" / "report.md").read_bytes()
    assert_one_error_line(invoke(scene, "report"), "export.json", quiet=False)
    assert (scene / "out" / "report.md").read_bytes() == before


@pytest.mark.parametrize("name", ["coefficients.h5", "light_latlong.exr"])
def test_report_with_a_damaged_solve_output_names_it_and_draws_nothing(reported, tmp_path, name):
    """A truncated coefficients.h5 named the scene folder and blamed the disk, and the figures drawn
    before it were left without their pages (bad-input sweep): now one line naming the file and the
    fix, and the report as it was."""
    scene = shutil.copytree(reported, tmp_path / "s")
    path = scene / "out" / name
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
    before = {p: p.read_bytes() for p in (scene / "out").rglob("*") if p.is_file() and "report" in p.as_posix()}
    line = assert_one_error_line(invoke(scene, "report"), name, quiet=False)
    assert "solve --force" in line
    after = {p: p.read_bytes() for p in (scene / "out").rglob("*") if p.is_file() and "report" in p.as_posix()}
    assert after == before
