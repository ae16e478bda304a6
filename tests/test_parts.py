"""Several materials and known albedo textures (issue 19, items 1, 2, 4): the parts the mesh carries,
the per-pixel albedo through the one forward model and both light routes, the per-part fit, the
errors, and the acceptance numbers on the Mitsuba scenes spot_textured_sun / spot_textured_overcast.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import invoke

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "tests" / "data" / "scenes"
SUN = SCENES / "spot_textured_sun"
OVERCAST = SCENES / "spot_textured_overcast"


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("truth", "views", ".wavelight", "out", "image.png"))
    return dst


# -- the parts of a mesh --------------------------------------------------------------------------
def test_obj_parts_by_name_texture_and_mean():
    from pipelines.io.scene_files import load_mesh
    from pipelines.model import parts as pm

    mesh = load_mesh(SUN / "mesh.obj")
    sp = pm.scene_parts(mesh, SUN / "mesh.obj", SUN)
    by_name = {p.name: p for p in sp.parts}
    assert set(by_name) == {"spot", "ground"}
    assert by_name["spot"].faces == 5856 and by_name["ground"].faces == 20000
    assert by_name["spot"].texture is not None and by_name["ground"].texture is None
    assert by_name["ground"].kd == pytest.approx((0.35, 0.45, 0.6))
    # the texture's area-weighted mean over Spot's surface: README.txt's (0.7894, 0.6414, 0.5785)
    mean = pm.part_mean_base(sp, mesh, sp.names.index("spot"))
    assert mean == pytest.approx([0.7894, 0.6414, 0.5785], rel=0.01)


def test_texture_mip_levels_filter_the_footprint():
    from pipelines.model.parts import Texture

    checker = np.indices((64, 64)).sum(axis=0) % 2  # one-texel checkerboard
    tex = Texture.from_pixels(np.repeat(checker[..., None], 3, axis=2).astype(np.float32), "checker")
    uv = np.random.default_rng(0).uniform(0.1, 0.9, (200, 2))
    fine = tex.sample(uv, np.full(200, 1.0))  # one texel per pixel: the texels themselves (bilinear)
    coarse = tex.sample(uv, np.full(200, 16.0 ** 2))  # 16 x 16 texels per pixel: their mean
    assert fine.std() > 0.1
    assert np.abs(coarse - 0.5).max() < 1e-6


def test_per_row_kd_rows_equal_the_dense_system():
    """RowsPart with kd per row (n, C) builds the same normal equations as the explicit
    T_c = diag(kd_c) D, and the uniform kd still shares one Gram matrix."""
    from pipelines.light.rows import RowsPart

    rng = np.random.default_rng(1)
    n, N = 50, 12
    D = rng.uniform(0, 1, (n, N)).astype(np.float32)
    kd = rng.uniform(0.2, 1.0, (n, 3))
    b = rng.uniform(0, 1, (n, 3))
    w = rng.uniform(0.5, 2.0, n)
    part = RowsPart(_flat(D), None, kd, np.zeros(3), b, w, n)
    sys_ = part.project(np.eye(N))
    for c in range(3):
        T = kd[:, c:c + 1] * D.astype(np.float64)
        assert np.allclose(sys_.gram(c), T.T @ (w[:, None] * T), rtol=1e-5)
        assert np.allclose(sys_.h[:, c], T.T @ (w * b[:, c]), rtol=1e-5)
    L = rng.uniform(0, 1, (N, 3))
    pred = np.column_stack([(kd[:, c:c + 1] * D) @ L[:, c] for c in range(3)])
    assert np.allclose(part.predict(L), pred, rtol=1e-5)
    g = np.column_stack([(kd[:, c:c + 1] * D).T @ (w * (b[:, c] - pred[:, c])) for c in range(3)])
    assert np.allclose(part.gradient(L), g, rtol=1e-4, atol=1e-6)
    uniform = RowsPart(_flat(D), None, np.array([0.5, 0.5, 0.5]), np.zeros(3), b, w, n)
    assert uniform.channel_scale is not None and part.channel_scale is None


def _flat(D):
    """D's rows as a Pyramid without tiles (project / predict / gradient read only the rows)."""
    from pipelines.light.rows import Pyramid

    p = Pyramid.__new__(Pyramid)
    p.rows, p.tile_sizes, p.levels, p.offsets = D, (), [], []
    return p


def test_fit_scales_recovers_part_ratio():
    """Given the light, the closed-form per-part fit recovers the non-reference part's colour,
    also when the light is off by a per-channel factor (taken from the reference part's pixels)."""
    from pipelines.model.parts import Part, PixelAlbedo, SceneParts, fit_scales

    rng = np.random.default_rng(2)
    n = 400
    part = (np.arange(n) % 3 == 0).astype(np.int64)  # part 1 = reference
    base = rng.uniform(0.3, 1.0, (n, 3))
    diffuse = rng.uniform(0.1, 1.0, (n, 3))
    true = np.array([[0.4, 0.6, 1.1], [1.0, 1.0, 1.0]])
    light_factor = np.array([1.3, 0.8, 1.0])  # the photo is brighter / darker per channel than the light says
    photo = base * true[part] * diffuse * light_factor
    sp = SceneParts([Part("ground", (1, 1, 1), ""), Part("spot", (1, 1, 1), "", fit="reference")], part, None, None,
                    1, [])
    a = PixelAlbedo(base, part, np.ones((2, 3)), sp)
    new = fit_scales(a, np.arange(n), np.ones(n), diffuse, None, photo)
    assert new[1] == pytest.approx([1, 1, 1])
    assert new[0] == pytest.approx(true[0], rel=1e-9)


def test_fit_scales_recovers_each_glossy_parts_specular_weight():
    """Under a specular material the closed-form step also fits each glossy part's specular weight
    (the factor on the material's ks) with its colour: exact on noise-free rows, the part whose lobe
    carries the most signal keeping its weight (the material's ks is its own), and a part whose
    highlight is out of view keeping the weight it had (its rows cannot tell it)."""
    from pipelines.model.parts import Part, PixelAlbedo, SceneParts, fit_scales

    rng = np.random.default_rng(3)
    n = 900
    part = np.arange(n) % 3  # 0 reference (the strongest lobe), 1 a weaker coating, 2 no highlight in view
    base = rng.uniform(0.3, 1.0, (n, 3))
    diffuse = rng.uniform(0.1, 1.0, (n, 3))
    lobe = rng.uniform(0.0, 2.0, (n, 1)) * np.array([1.0, 0.9, 0.8])
    lobe[part == 2] = 0.0
    true = np.array([[1.0, 1.0, 1.0], [0.5, 0.7, 0.9], [1.2, 0.8, 0.6]])
    ks_true = np.array([1.0, 0.3, 5.0])
    photo = base * true[part] * diffuse + ks_true[part][:, None] * lobe
    sp = SceneParts([Part("spot", (1, 1, 1), "", fit="reference"), Part("ground", (1, 1, 1), ""),
                     Part("table", (1, 1, 1), "")], part, None, None, 0, [])
    a = PixelAlbedo(base, part, np.ones((3, 3)), sp)
    scales, ks = fit_scales(a, np.arange(n), np.ones(n), diffuse, lobe, photo, ks=True)
    assert scales == pytest.approx(true, rel=1e-9)
    assert ks == pytest.approx([1.0, 0.3, 1.0], rel=1e-9)
    # the step is bounded (the light moves with it): from a weight far off, a factor 4 at most
    a.ks_scales = np.array([1.0, 0.01, 1.0])
    _, ks = fit_scales(a, np.arange(n), np.ones(n), diffuse, lobe * a.ks_scales[part][:, None], photo, ks=True)
    assert ks[1] == pytest.approx(0.04)
    # rows that show no highlight where the lobe would put one: the weight goes down (a matte part
    # under a given model), a step at a time; rows whose noise drowns the lobe keep their weight
    a.ks_scales = None
    matte = photo + (0.0 - ks_true[part][:, None]) * lobe * (part == 1)[:, None]
    _, ks = fit_scales(a, np.arange(n), np.ones(n), diffuse, lobe, matte + rng.normal(0, 0.3, photo.shape), ks=True)
    assert ks[1] == 0.25
    drowned = photo + rng.normal(0, 10.0, photo.shape) * (part == 1)[:, None]  # (h's standard error ~0.3)
    _, ks = fit_scales(a, np.arange(n), np.ones(n), diffuse, lobe, drowned, ks=True)
    assert ks[1] == 1.0
    a.glossy = np.array([True, False, True])
    assert a.specular_weight()[part == 1].max() == 0 and a.specular_weight()[part == 0].min() == 1


# -- errors ---------------------------------------------------------------------------------------
def _error_line(result) -> str:
    lines = [ln for ln in result.output.splitlines() if ln.startswith("Error:")]
    assert result.exit_code == 1, result.output
    assert len(lines) == 1 and "Traceback" not in result.output, result.output
    return lines[0]


def _untouched(scene: Path):
    assert not (scene / "out" / "reflectance.json").exists()
    manifest = scene / ".wavelight" / "manifest.json"
    assert not manifest.exists() or "solve" not in json.loads(manifest.read_text()).get("stages", {})


@pytest.fixture
def textured(tmp_path):
    return _copy(SUN, tmp_path / "scene")


def test_missing_texture_is_one_line(textured):
    """...before any stage runs: no visibility cast and cached first (it was; bad-input sweep), and
    `check` refuses it as solve does (it said ok)."""
    (textured / "spot_texture.png").rename(textured / "elsewhere.png")
    line = _error_line(invoke(textured, "solve", "-R", "8", "--reflectance", "lambert"))
    assert "mesh.mtl" in line and "spot_texture.png" in line and "does not exist" in line and "--no-texture" in line
    _untouched(textured)
    assert not (textured / ".wavelight" / "visibility").exists()
    checked = _error_line(invoke(textured, "check"))
    assert "spot_texture.png" in checked and "does not exist" in checked and "[solve] no-texture = true" in checked
    (textured / "scene.toml").write_text("[solve]\nno-texture = true\n")  # (check reads the parts as solve would)
    assert invoke(textured, "check").exit_code == 0
    (textured / "scene.toml").unlink()
    # --no-texture solves it (the part keeps its .mtl Kd)
    assert invoke(textured, "solve", "-R", "8", "--reflectance", "lambert", "--no-texture").exit_code == 0


def test_missing_material_library_is_one_line_before_any_stage(textured):
    """An OBJ whose mtllib names a missing .mtl: one line naming the mesh, before visibility is cast
    and cached; `check` refuses it as solve does (bad-input sweep)."""
    (textured / "mesh.mtl").rename(textured / "elsewhere.mtl")
    line = _error_line(invoke(textured, "solve", "-R", "8", "--reflectance", "lambert"))
    assert "mesh.obj" in line and "mesh.mtl" in line and "does not exist" in line
    _untouched(textured)
    assert not (textured / ".wavelight" / "visibility").exists()
    assert "mesh.mtl" in _error_line(invoke(textured, "check"))


def test_unreadable_texture_is_one_line(textured):
    (textured / "spot_texture.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    line = _error_line(invoke(textured, "solve", "-R", "8", "--reflectance", "lambert"))
    assert "spot_texture.png" in line and "cannot read its texture" in line
    _untouched(textured)


def _rewrite_obj(scene: Path, fn):
    obj = scene / "mesh.obj"
    obj.write_text("".join(fn(line) for line in obj.read_text().splitlines(keepends=True)))


def test_uvs_far_outside_the_texture_are_one_line(textured):
    def scale_vt(line):
        if line.startswith("vt "):
            u, v = (float(x) for x in line.split()[1:3])
            return f"vt {10 * u:.6f} {10 * v:.6f}\n"
        return line

    _rewrite_obj(textured, scale_vt)
    line = _error_line(invoke(textured, "solve", "-R", "8", "--reflectance", "lambert"))
    assert "mesh.obj" in line and "part 'spot'" in line and "far outside the texture" in line
    _untouched(textured)


def test_textured_part_without_uvs_is_one_line(textured):
    def drop_vt(line):
        if line.startswith("f "):
            return "f " + " ".join(re.sub(r"^(\d+)/\d*/(\d+)$", r"\1//\2", t) for t in line.split()[1:]) + "\n"
        return "" if line.startswith("vt ") else line

    _rewrite_obj(textured, drop_vt)
    line = _error_line(invoke(textured, "solve", "-R", "8", "--reflectance", "lambert"))
    assert "mesh.obj" in line and "no UV coordinates" in line
    _untouched(textured)


def test_materials_toml_unknown_part_is_one_line(textured):
    (textured / "materials.toml").write_text('[parts.table]\nkd = [0.5, 0.5, 0.5]\n')
    line = _error_line(invoke(textured, "solve", "-R", "8", "--reflectance", "lambert"))
    assert "materials.toml" in line and "table" in line


def test_cache_follows_the_mtl_and_texture(textured):
    assert invoke(textured, "solve", "-R", "8", "--reflectance", "lambert").exit_code == 0
    again = invoke(textured, "solve", "-R", "8", "--reflectance", "lambert")
    assert "solve: skipped" in again.output
    mtl = textured / "mesh.mtl"
    mtl.write_text(mtl.read_text().replace("Kd 0.350000 0.450000 0.600000", "Kd 0.300000 0.450000 0.600000"))
    changed = invoke(textured, "solve", "-R", "8", "--reflectance", "lambert")
    assert "solve: running (input changed: mtl" in changed.output, changed.output
    refl = json.loads((textured / "out" / "reflectance.json").read_text())
    assert {p["name"] for p in refl["parts"]} == {"spot", "ground"}
    assert refl["reference_part"]["name"] == "spot"


# -- the routes agree -----------------------------------------------------------------------------
@pytest.mark.slow
def test_exact_and_sampled_routes_agree_on_parts(tmp_path):
    """The dense reference route (--exact) and the sampled default fit the same part ratio and the
    same relit error (R = 8), from a ground start of kd 1 (materials.toml)."""
    out = {}
    for route in ("sampled", "exact"):
        scene = _copy(SUN, tmp_path / route)
        (scene / "materials.toml").write_text("[parts.ground]\nkd = [1.0, 1.0, 1.0]\n")
        args = ["solve", "-R", "8", "--reflectance", "lambert"] + (["--exact"] if route == "exact" else [])
        r = invoke(scene, *args)
        assert r.exit_code == 0, r.output
        refl = json.loads((scene / "out" / "reflectance.json").read_text())
        rep = json.loads((scene / "out" / "solve_report.json").read_text())
        ground = [p for p in refl["parts"] if p["name"] == "ground"][0]
        out[route] = (np.array(ground["relative_to_reference"]), rep["relit"]["relative_rmse_vs_photo"])
    assert out["sampled"][0] == pytest.approx(out["exact"][0], rel=0.03)
    assert out["sampled"][1] == pytest.approx(out["exact"][1], rel=0.1)


# -- acceptance on the Mitsuba scenes ---------------------------------------------------------------
def _solve_and_measure(src: Path, scene: Path, *options) -> dict:
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_e2e import probe_errors

    base = [sys.executable, "-c", "import sys; from wavelight_cli.main import cli; sys.exit(cli())", "-q", "-s",
            str(scene)]
    subprocess.run(base + ["solve", *options], check=True, capture_output=True, cwd=REPO)
    nv = src / "truth" / "novel_view"
    subprocess.run(base + ["relight", "--view", str(nv / "pose.json"), "--view-camera", str(nv / "camera.json"),
                           "--reference", str(nv / "image.exr"), "--reference-mask", str(nv / "mask.png"),
                           "--name", "novel"], check=True, capture_output=True, cwd=REPO)
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    return {"probe": probe_errors(scene / "out" / "coefficients.h5", src)["diffuse"],
            "novel": json.loads((scene / "out" / "novel.json").read_text())["relative_rmse_vs_photo"],
            "parts": refl.get("parts")}


@pytest.mark.slow
@pytest.mark.parametrize("src", [SUN, OVERCAST], ids=["sun", "overcast"])
def test_parts_and_texture_beat_the_uniform_model(tmp_path, src):
    uniform = _solve_and_measure(src, _copy(src, tmp_path / "uniform"), "--single-material")
    parts = _solve_and_measure(src, _copy(src, tmp_path / "parts"))
    assert parts["probe"] <= 0.03 and parts["novel"] <= 0.04, parts
    assert 2 * parts["probe"] <= uniform["probe"] and 2 * parts["novel"] <= uniform["novel"], (parts, uniform)
    truth = json.loads((src / "truth" / "material.json").read_text())["ground_over_spot_albedo_rgb"]
    ground = [p for p in parts["parts"] if p["name"] == "ground"][0]["relative_to_reference"]
    assert ground == pytest.approx(truth, rel=0.05)


@pytest.mark.slow
def test_part_ratio_does_not_depend_on_the_start(tmp_path):
    """From a ground start of kd = 1 (materials.toml) instead of the .mtl's Kd, the same ratio."""
    ratios = []
    for k, toml in enumerate(("", "[parts.ground]\nkd = [1.0, 1.0, 1.0]\n")):
        scene = _copy(SUN, tmp_path / f"s{k}")
        if toml:
            (scene / "materials.toml").write_text(toml)
        r = invoke(scene, "solve", "--reflectance", "lambert")
        assert r.exit_code == 0, r.output
        parts = json.loads((scene / "out" / "reflectance.json").read_text())["parts"]
        ratios.append(np.array([p for p in parts if p["name"] == "ground"][0]["relative_to_reference"]))
    assert ratios[1] == pytest.approx(ratios[0], rel=0.01)


def test_downstream_stages_use_the_parts(textured):
    """relight renders each part with its colour and texture (the photo view: the solve's own relit
    error), export writes a BSDF per part, the report has the parts' table."""
    assert invoke(textured, "solve", "-R", "8", "--reflectance", "lambert").exit_code == 0
    solved = json.loads((textured / "out" / "solve_report.json").read_text())["relit"]["relative_rmse_vs_photo"]
    assert invoke(textured, "relight").exit_code == 0
    relit = json.loads((textured / "out" / "relight.json").read_text())["relative_rmse_vs_photo"]
    assert relit == pytest.approx(solved, rel=0.02)
    (textured / "uniform.json").write_text('{"model": "lambert", "kd": [1, 1, 1]}')
    assert invoke(textured, "relight", "--material", str(textured / "uniform.json"), "--name", "plain").exit_code == 0
    plain = json.loads((textured / "out" / "plain.json").read_text())["relative_rmse_vs_photo"]
    assert plain > 3 * relit  # without the parts' colours the same light is far off
    assert invoke(textured, "export").exit_code == 0
    export = json.loads((textured / "out" / "export" / "export.json").read_text())
    assert {p["name"] for p in export["material"]["parts"]} == {"spot", "ground"}
    assert (textured / "out" / "export" / "mitsuba" / "bsdf_ground.xml").is_file()
    assert invoke(textured, "report").exit_code == 0
    assert "| part | faces | pixels | texture |" in (textured / "out" / "report.md").read_text()
    _exported_parts_render_in_mitsuba_as_the_photo(textured, solved)


def _exported_parts_render_in_mitsuba_as_the_photo(scene: Path, solved: float):
    """The export's round trip: Mitsuba renders the mesh's parts with their exported BSDFs (Spot's
    texture as the linear bitmap kd_spot.exr x its scale, the ground's colour) under the exported
    light, from the photo's camera. Away from the object's silhouette (pixels part object, part
    ground), that render's error against the photo, beyond Mitsuba's own noise (two seeds), is the
    solve's relit error (the light at R = 8), and far below the render with Spot exported as its
    mean colour (what export wrote before)."""
    pytest.importorskip("mitsuba")
    export = scene / "out" / "export"
    spot = next(p for p in json.loads((export / "export.json").read_text())["material"]["parts"] if p["name"] == "spot")
    assert spot["bitmap"] == "mitsuba/kd_spot.exr" and spot["exact"]

    def bias(bsdf_files=None):
        return _export_bias(scene, bsdf_files)

    textured, noise = bias()
    kd = next(p for p in json.loads((scene / "out" / "reflectance.json").read_text())["parts"] if p["name"] == "spot")["kd"]
    mean = scene / "mean_spot.xml"
    mean.write_text('<bsdf type="diffuse" version="3.0.0"><rgb name="reflectance" value="'
                    + ", ".join(f"{v:.6g}" for v in kd) + '"/></bsdf>\n')
    plain, _ = bias({"spot": mean})
    print(f"Mitsuba render of the export vs the photo: {100 * textured:.2f} % beyond its noise {100 * noise:.2f} % "
          f"(the solve's relit error {100 * solved:.2f} %; Spot as its mean colour: {100 * plain:.2f} %)")
    assert textured < 1.3 * solved + 0.005
    assert plain > 4 * textured


def _export_bias(scene: Path, bsdf_files=None) -> tuple[float, float]:
    """Mitsuba's render of the scene's export (`bsdf_files`: some parts' BSDFs replaced) against the
    photo, away from the object's silhouette: (the relative error beyond Mitsuba's noise, that
    noise), from two renders of 16 spp with different seeds."""
    import tool_scenes as ts
    from scipy.ndimage import binary_dilation, binary_erosion

    from pipelines.io import images

    photo = images.read_image(scene / "image.exr").pixels
    obj = images.read_mask(scene / "mask_object.png").astype(bool)
    keep = images.read_mask(scene / "mask.png").astype(bool) & ~(binary_dilation(obj) & ~binary_erosion(obj))
    norm = float((photo[keep] ** 2).sum())
    a, b = (ts.render_mitsuba_parts(scene, scene / "out" / "export", 16, bsdf_files, seed)[keep] for seed in (1, 2))
    err2 = ((0.5 * (a + b) - photo[keep]) ** 2).sum() / norm
    noise2 = ((a - b) ** 2).sum() / (4 * norm)  # of the two renders' mean
    return float(np.sqrt(max(err2 - noise2, 0.0))), float(np.sqrt(noise2))


# -- a glossy part and a matte one (each part's own specular term) ----------------------------------
GLOSSY = SCENES / "spot_glossy_sun"


def test_matte_rows_lose_the_lobe_and_the_coating():
    """The forward model with per-pixel specular weights: a matte pixel's transport is the Lambertian
    one (no lobe, no coating), a glossy pixel's that of the material, under Blinn-Phong and plastic."""
    from pipelines.light.cubemap import CubeMap
    from pipelines.model.materials import Material
    from pipelines.model.render import transport

    rng = np.random.default_rng(3)
    cube = CubeMap(8)
    n = rng.normal(size=(6, 3)) + [0, 0, 3]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(size=(6, 3)) + [0, 0, 2]
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    V = (rng.random((6, cube.n_texels)) > 0.3).astype(np.float32)
    w = np.array([1, 0, 1, 0, 0, 1], np.float32)
    lambert_D, _ = transport(V, n, v, cube, Material())
    for m in (Material(ks=(0.3,) * 3, shininess=40.0, model="blinn-phong"),
              Material(ks=(1.0,) * 3, model="plastic", roughness=0.15)):
        D0, S0 = transport(V, n, v, cube, m)
        D, S = transport(V, n, v, cube, m, w)
        g, mt = w > 0, w == 0
        assert np.array_equal(D[g], D0[g]) and np.array_equal(S[g], S0[g])
        assert not S[mt].any() and S0[mt].any()
        assert np.allclose(D[mt], lambert_D[mt])
        assert m.model != "plastic" or not np.allclose(D0[mt], lambert_D[mt])  # (the coating changes D)


def test_glossy_parts_tells_a_glossy_part_from_a_matte_one():
    """`glossy_parts`: per part its own kd and ks on its probe rows; a part whose photo has the lobe
    keeps it, one whose photo has none (its ks fits noise) does not; a materials.toml declaration
    wins; a part with too few rows keeps the lobe (undecided)."""
    from pipelines.model import parts as pm

    rng = np.random.default_rng(7)
    m = 600
    diffuse = rng.uniform(0.2, 1.0, (3 * m, 3))
    lobe = np.where(rng.random((3 * m, 1)) < 0.15, rng.uniform(0.5, 3.0, (3 * m, 1)), 0.01) * np.ones(3)
    part = np.repeat([0, 1, 2], m)
    kd = np.array([0.6, 0.5, 0.4])
    photo = kd * diffuse + np.where(part[:, None] == 0, 0.3 * lobe, 0.0)
    photo += rng.normal(0, 0.005, photo.shape)
    sp = pm.SceneParts([pm.Part("glossy", (1, 1, 1), "t"), pm.Part("matte", (1, 1, 1), "t"),
                        pm.Part("declared", (1, 1, 1), "t", specular=True)], np.zeros(1, int), None, None, 0, [])
    glossy, sources, info = pm.glossy_parts(sp, part, diffuse, lobe, photo, 0.05)
    assert glossy.tolist() == [True, False, True]
    assert info[0]["ks"] == pytest.approx(0.3, rel=0.05) and info[0]["gain"] > 0.5
    assert info[1]["gain"] < 0.05 and sources[2] == "materials.toml"
    few = np.r_[part[:m], np.full(10, 1)]
    glossy, sources, _ = pm.glossy_parts(sp, few, diffuse[:m + 10], lobe[:m + 10], photo[:m + 10], 0.05)
    assert glossy.tolist() == [True, True, True] and "too few" in sources[1]


def _relight_as_solved_and_export(scene: Path) -> float:
    """`relight` renders the photo as the solve did (each part's material as fitted: its error equals
    the solve's); then `export`. Returns the solve's relit error."""
    solved = json.loads((scene / "out" / "solve_report.json").read_text())["relit"]["relative_rmse_vs_photo"]
    assert invoke(scene, "relight").exit_code == 0
    relit = json.loads((scene / "out" / "relight.json").read_text())["relative_rmse_vs_photo"]
    assert relit == pytest.approx(solved, rel=2e-3)
    assert invoke(scene, "export").exit_code == 0
    return solved


def _copy_glossy(tmp_path: Path) -> Path:
    return _copy(GLOSSY, tmp_path / "glossy")


def test_a_glossy_part_and_a_matte_one(tmp_path):
    """spot_glossy_sun (Spot under a rough coating on a matte ground; nothing in the folder says which
    is glossy), R = 8: auto gives Spot the lobe and the ground none; reflectance.json says why;
    relight renders both parts as the solve did (its error equals the solve's); export writes the
    ground as a diffuse BSDF and Spot as a roughplastic one, and Mitsuba renders the export as the
    photo; a materials.toml declaration takes precedence, and a bad one is one error line."""
    scene = _copy_glossy(tmp_path)
    r = invoke(scene, "solve", "-R", "8")
    assert r.exit_code == 0, r.output
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    assert refl["model"] == "plastic"
    parts = {p["name"]: p for p in refl["parts"]}
    assert parts["spot"]["specular"] and not parts["ground"]["specular"]
    assert parts["ground"]["specular_decided_by"].startswith("auto: its own ks")
    by = {p["name"]: p for p in refl["candidates"]["parts"]}
    assert by["spot"]["gain"] > 0.3 and by["ground"]["gain"] < 0.05  # measured 60 % and 0.3 %
    solved = _relight_as_solved_and_export(scene)
    mitsuba = scene / "out" / "export" / "mitsuba"
    assert 'bsdf type="diffuse"' in (mitsuba / "bsdf_ground.xml").read_text()
    assert 'bsdf type="roughplastic"' in (mitsuba / "bsdf_spot.xml").read_text()
    _glossy_export_renders_as_the_photo(scene, solved)
    (scene / "materials.toml").write_text("[parts.ground]\nspecular = false\n[parts.spot]\nspecular = false\n")
    r = invoke(scene, "solve", "-R", "8")
    assert r.exit_code == 0, r.output
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    assert refl["model"] == "lambert"  # (no part may have a lobe: nothing to fit it to)
    assert not any(p["specular"] for p in refl["parts"])
    print(refl["decision"])
    (scene / "materials.toml").write_text("[parts.ground]\nspecular = \"no\"\n")
    r = invoke(scene, "solve", "-R", "8")
    assert r.exit_code != 0 and "Traceback" not in r.output
    line = [ln for ln in r.output.splitlines() if ln.startswith("Error:")]
    assert len(line) == 1 and "materials.toml" in line[0] and "specular must be true or false" in line[0]


@pytest.mark.slow
def test_a_matte_ground_under_a_glossy_object(tmp_path):
    """spot_glossy_sun at the defaults (R = 32, the main photo): auto puts the lobe on Spot alone, and
    against the lobe on both parts at one ks (materials.toml `specular = true`, `--shared-ks`: one
    specular model for the whole scene, as before each part had its own) the light and the ground's
    colour are right. Measured: diffuse probe 1.34 % against 2.20 %, new view 5.69 % against
    10.46 %, the ground's albedo relative to Spot's 2.7 / 2.6 / 0.9 % low against 43 / 41 / 35 % high
    (the coated ground's colour makes up for the coating's Fresnel loss), alpha 0.142 (truth 0.15).
    Since the microfacet lobe's texel blur goes through v.h across the plane of incidence and is
    widened by the pixel's footprint (2026-12-06): diffuse probe 2.06 % against 2.36 %, new view
    6.53 % against 10.17 %, alpha 0.141 (with the footprint but the blur through N.v: not measured;
    with neither, at the same commit: 1.45 % / 6.09 % against 2.20 % / 10.44 %; with the blur alone
    2.24 % / 7.74 %). The per-part model's lead on the diffuse probe shrank from 1.5x to 1.15x: not
    understood yet (issue 17's closing note); its lead on the new view holds."""
    per_part = _solve_and_measure(GLOSSY, _copy(GLOSSY, tmp_path / "per_part"))
    scene = _copy(GLOSSY, tmp_path / "one")
    (scene / "materials.toml").write_text("[parts.spot]\nspecular = true\n[parts.ground]\nspecular = true\n")
    one = _solve_and_measure(GLOSSY, scene, "--shared-ks")  # (one ks too: each part's own would lower the ground's)
    print("per part:", per_part["probe"], per_part["novel"], "one model:", one["probe"], one["novel"])
    parts = {p["name"]: p for p in per_part["parts"]}
    assert parts["spot"]["specular"] and not parts["ground"]["specular"]
    assert per_part["probe"] <= 0.025 and per_part["novel"] <= 0.07, per_part
    assert per_part["probe"] < one["probe"] and 1.5 * per_part["novel"] <= one["novel"], (per_part, one)
    truth = json.loads((GLOSSY / "truth" / "material.json").read_text())["ground_over_spot_albedo_rgb"]
    assert parts["ground"]["relative_to_reference"] == pytest.approx(truth, rel=0.05)
    coated = [p for p in one["parts"] if p["name"] == "ground"][0]["relative_to_reference"]
    assert min(np.array(coated) / truth) > 1.2


def test_a_given_model_tests_the_parts(tmp_path):
    """spot_glossy_sun, R = 8, `--reflectance plastic`: the given model's lobe goes on the parts whose
    own lobe is significant, decided as auto decides (a probe of the model with the Lambertian light
    fixed) against the Lambertian shading of a matte part (no coating): Spot glossy, the ground
    matte (measured: the ground's coated base and lobe fit 19 % worse than its plain colour)."""
    scene = _copy_glossy(tmp_path)
    r = invoke(scene, "solve", "-R", "8", "--reflectance", "plastic")
    assert r.exit_code == 0, r.output
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    assert refl["model"] == "plastic" and refl["mode"] == "plastic"
    parts = {p["name"]: p for p in refl["parts"]}
    assert parts["spot"]["specular"] and not parts["ground"]["specular"]
    by = {p["name"]: p for p in refl["candidates"]["parts"]}
    assert by["spot"]["gain"] > 0.3 and by["ground"]["gain"] < 0.0
    truth = json.loads((GLOSSY / "truth" / "material.json").read_text())["ground_over_spot_albedo_rgb"]
    assert parts["ground"]["relative_to_reference"] == pytest.approx(truth, rel=0.12)  # (R = 8; measured 8 % high)


def _glossy_export_renders_as_the_photo(scene: Path, solved: float):
    """Mitsuba renders the export (Spot's roughplastic over its texture, the ground diffuse) from the
    photo's camera: away from the object's silhouette its error against the photo, beyond Mitsuba's
    noise, is about the solve's relit error; the same colours with the ground under Spot's coating
    (one specular model for every part) are far off: the parts' own BSDF types matter."""
    pytest.importorskip("mitsuba")
    export = scene / "out" / "export"

    def bias(bsdf_files=None):
        return _export_bias(scene, bsdf_files)[0]

    exported = bias()
    spot = (export / "mitsuba" / "bsdf_spot.xml").read_text()
    ground = (export / "mitsuba" / "bsdf_ground.xml").read_text()
    value = re.search(r'name="reflectance" value="([^"]+)"', ground).group(1)
    coated = scene / "coated_ground.xml"
    coated.write_text(re.sub(r'<texture type="bitmap".*?</texture>',
                             f'<rgb name="diffuse_reflectance" value="{value}"/>', spot, flags=re.S))
    as_one = bias({"ground": coated})
    print(f"Mitsuba render of the export vs the photo: {100 * exported:.2f} % (solve {100 * solved:.2f} %); "
          f"the ground under Spot's coating: {100 * as_one:.2f} %")
    assert exported < 1.3 * solved + 0.005
    assert as_one > 2 * exported


# -- two glossy parts of different ks (each glossy part's own specular weight) -----------------------
TWO_COATS = SCENES / "spot_two_coats_sun"


def _two_coats(scene: Path) -> tuple[dict, dict]:
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    return refl, {p["name"]: p for p in refl["parts"]}


def test_two_glossy_parts_each_with_its_own_ks(tmp_path):
    """spot_two_coats_sun (Spot in two parts under one coating, specular_reflectance 1 and 0.3, the
    texture their diffuse base; the ground matte), R = 8: both parts keep the lobe, each with its own
    ks (measured 1.10 and 0.329: 0.299 of it); relight renders them as the solve did; the export
    writes each part's specular_reflectance, and Mitsuba renders it as the photo, unlike the same
    export with the weaker part at the other's ks."""
    scene = _copy(TWO_COATS, tmp_path / "two")
    r = invoke(scene, "solve", "-R", "8")
    assert r.exit_code == 0, r.output
    refl, parts = _two_coats(scene)
    assert refl["model"] == "plastic" and not parts["ground"]["specular"]
    assert parts["spot"]["specular"] and parts["spot_flank"]["specular"]
    ratio = parts["spot_flank"]["ks"][0] / parts["spot"]["ks"][0]
    print("ks", parts["spot"]["ks"][0], parts["spot_flank"]["ks"][0], "ratio", ratio)
    assert ratio == pytest.approx(0.3, rel=0.15)
    assert parts["ground"]["specular_weight"] == 0.0
    solved = _relight_as_solved_and_export(scene)
    mitsuba = scene / "out" / "export" / "mitsuba"
    weight = {n: float(re.search(r'name="specular_reflectance" value="([^,"]+)', (mitsuba / f"bsdf_{n}.xml")
                                 .read_text()).group(1)) for n in ("spot", "spot_flank")}
    assert weight["spot_flank"] / weight["spot"] == pytest.approx(ratio, rel=1e-6)
    pytest.importorskip("mitsuba")
    exported = _export_bias(scene)[0]
    shared = mitsuba / "flank_at_spots_ks.xml"  # (beside the texture it names)
    shared.write_text(re.sub(r'(name="specular_reflectance" value=")[^"]+"',
                             lambda m: m.group(1) + ", ".join([repr(weight["spot"])] * 3) + '"',
                             (mitsuba / "bsdf_spot_flank.xml").read_text()))
    as_one = _export_bias(scene, {"spot_flank": shared})[0]
    print(f"Mitsuba render of the export vs the photo: {100 * exported:.2f} % (solve {100 * solved:.2f} %); "
          f"the flank at Spot's ks: {100 * as_one:.2f} %")
    assert exported < 1.3 * solved + 0.005
    assert as_one > 1.5 * exported


@pytest.mark.slow
def test_two_glossy_parts_of_different_ks_beat_one_shared_ks(tmp_path):
    """spot_two_coats_sun at the defaults (R = 32, the main photo): each glossy part's own ks against
    one ks shared by both (`--shared-ks`, the behaviour before). Measured: ks 0.891 and 0.288 (truth
    1 and 0.3: 0.323 of it), diffuse probe 1.11 % against 3.31 %, glossy probe 3.36 % against 5.69 %,
    new view 5.40 % against 5.95 %, the flank's albedo relative to Spot's (truth 1) 0.94-1.00 against
    0.88-0.93, the ground's within 6 % of the truth against 14 %. Since the robust pass's interval
    edge rule (solve VERSION 15) both solve this clean render again (own: 57 pixels down-weighted):
    diffuse probe 1.13 % against 2.68 %, new view 5.69 % against 5.18 % (own with --no-robust:
    1.10 %, 5.38 %). The new view no longer separates them; it stays within 15 %. Since the
    microfacet lobe's texel blur goes through v.h and is widened by the pixel's footprint
    (2026-12-06): diffuse probe 1.28 % against 1.97 %, new view 6.80 % against 4.30 %: the shared
    ks's light improved more than the parts' own, and its new view is now the better one (not
    understood yet: issue 17's closing note)."""
    own = _solve_and_measure(TWO_COATS, _copy(TWO_COATS, tmp_path / "own"))
    shared = _solve_and_measure(TWO_COATS, _copy(TWO_COATS, tmp_path / "shared"), "--shared-ks")
    print("own:", own["probe"], own["novel"], "shared:", shared["probe"], shared["novel"])
    parts = {p["name"]: p for p in own["parts"]}
    ratio = parts["spot_flank"]["ks"][0] / parts["spot"]["ks"][0]
    assert ratio == pytest.approx(0.3, rel=0.15)
    assert parts["spot"]["ks"][0] == pytest.approx(1.0, rel=0.2)  # (the light holds the overall scale)
    same = {p["name"]: p for p in shared["parts"]}
    assert same["spot_flank"]["ks"] == same["spot"]["ks"]
    assert own["probe"] <= 0.02 and 1.4 * own["probe"] <= shared["probe"], (own, shared)
    assert own["novel"] <= 0.08, own
    truth = json.loads((TWO_COATS / "truth" / "material.json").read_text())["ground_over_spot_albedo_rgb"]
    flank = np.array(parts["spot_flank"]["relative_to_reference"])
    assert np.all(np.abs(flank - 1) < 0.07) and np.all(np.abs(flank - 1) < np.abs(
        np.array(same["spot_flank"]["relative_to_reference"]) - 1))
    assert parts["ground"]["relative_to_reference"] == pytest.approx(truth, rel=0.08)


def test_glb_primitives_materials_and_base_colour_texture(tmp_path):
    """The same scene as a GLB (trimesh's export): two primitives with their materials, Spot's
    baseColorTexture embedded, the same texture mean over Spot's surface as the OBJ's map_Kd."""
    import trimesh

    from pipelines.io.scene_files import load_mesh
    from pipelines.model import parts as pm

    trimesh.load(SUN / "mesh.obj", process=False).export(tmp_path / "mesh.glb")
    mesh = load_mesh(tmp_path / "mesh.glb")
    sp = pm.scene_parts(mesh, tmp_path / "mesh.glb", tmp_path)
    by_name = {p.name: p for p in sp.parts}
    assert by_name["spot"].texture is not None and by_name["ground"].texture is None
    assert by_name["ground"].kd == pytest.approx((0.35, 0.45, 0.6), abs=0.003)  # glTF's factor, 8 bits here
    assert pm.part_mean_base(sp, mesh, sp.names.index("spot")) == pytest.approx([0.7894, 0.6414, 0.5785], rel=0.01)


def _ply_with_labels(src_obj: Path, dst: Path, prop: str = "label") -> Path:
    """The OBJ scene as one binary PLY (trimesh's export): the same vertices, normals and UVs, each
    face's part as an integer face property `prop` (0 the ground, 1 Spot: the OBJ's part order)."""
    import trimesh

    parts = trimesh.load(src_obj, process=False).dump()
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    mesh = trimesh.Trimesh(np.concatenate([p.vertices for p in parts]),
                           np.concatenate([p.faces + o for p, o in zip(parts, offsets)]),
                           vertex_normals=np.concatenate([p.vertex_normals for p in parts]), process=False,
                           visual=trimesh.visual.TextureVisuals(uv=np.concatenate([p.visual.uv for p in parts])))
    mesh.face_attributes[prop] = np.concatenate([np.full(len(p.faces), k, np.int32) for k, p in enumerate(parts)])
    dst.write_bytes(trimesh.exchange.ply.export_ply(mesh, vertex_normal=True, include_attributes=True))
    return dst


def test_ply_face_labels_are_parts(tmp_path):
    """A PLY's integer face label is one part per value (`label_0`, `label_1`), with the OBJ's own
    geometry; materials.toml gives each its colour and texture by that name, and the parts are then
    the OBJ's: the same faces, start colour and texture mean over Spot's surface."""
    from pipelines.io.scene_files import load_mesh
    from pipelines.model import parts as pm

    obj = load_mesh(SUN / "mesh.obj")
    ply = load_mesh(_ply_with_labels(SUN / "mesh.obj", tmp_path / "mesh.ply"))
    assert ply.part_names == ("label_0", "label_1")
    assert np.array_equal(ply.faces, obj.faces) and np.allclose(ply.vertices, obj.vertices, atol=1e-6)
    assert np.allclose(ply.vertex_normals, obj.vertex_normals, atol=1e-5)
    assert np.array_equal(ply.face_part, obj.face_part)  # ground 0, spot 1 in both
    assert np.allclose(ply.face_uv, obj.face_uv, atol=1e-6)
    shutil.copy(SUN / "spot_texture.png", tmp_path)
    (tmp_path / "materials.toml").write_text('[parts.label_0]\nkd = [0.35, 0.45, 0.6]\n\n'
                                             '[parts.label_1]\ntexture = "spot_texture.png"\n')
    sp = pm.scene_parts(ply, tmp_path / "mesh.ply", tmp_path)
    by_name = {p.name: p for p in sp.parts}
    assert by_name["label_0"].faces == 20000 and by_name["label_1"].faces == 5856
    assert by_name["label_0"].kd == pytest.approx((0.35, 0.45, 0.6)) and by_name["label_0"].texture is None
    assert pm.part_mean_base(sp, ply, sp.names.index("label_1")) == pytest.approx([0.7894, 0.6414, 0.5785], rel=0.01)
    # a texture the header names is every part's (the parts share the file's one UV map)
    data = (tmp_path / "mesh.ply").read_bytes()
    (tmp_path / "named.ply").write_bytes(data.replace(b"\nelement vertex", b"\ncomment TextureFile spot_texture.png"
                                                                         b"\nelement vertex", 1))
    named = load_mesh(tmp_path / "named.ply")
    assert named.part_names == ("label_0", "label_1") and all(m["image"] is not None for m in named.part_materials)
    assert all(m["image"] is None for m in ply.part_materials)  # none named: trimesh's placeholder is dropped


def test_ply_other_face_properties_are_not_parts(tmp_path):
    """An integer face property that is not a label (MeshLab's `flags`) leaves the PLY one uniform
    material (its UVs name no texture: trimesh's placeholder image is not one); a `material_index`
    is read like `label`."""
    from pipelines.io.scene_files import load_mesh
    from pipelines.model import parts as pm

    flags = load_mesh(_ply_with_labels(SUN / "mesh.obj", tmp_path / "flags.ply", "flags"))
    assert len(flags.part_names) <= 1 and not any(n.startswith("flags") for n in flags.part_names)
    assert pm.scene_parts(flags, tmp_path / "flags.ply", tmp_path) is None
    m = load_mesh(_ply_with_labels(SUN / "mesh.obj", tmp_path / "mi.ply", "material_index"))
    assert m.part_names == ("material_index_0", "material_index_1")
    assert np.bincount(m.face_part).tolist() == [20000, 5856]


def test_ply_labels_solve_like_the_obj(tmp_path):
    """The whole solve (R = 4, lambert) from the labelled PLY and materials.toml recovers the same
    ground-to-Spot albedo ratio as from the OBJ and its .mtl."""
    ratios = {}
    for kind in ("obj", "ply"):
        scene = _copy(SUN, tmp_path / kind)
        if kind == "ply":
            _ply_with_labels(scene / "mesh.obj", scene / "mesh.ply")
            for name in ("mesh.obj", "mesh.mtl"):
                (scene / name).unlink()
            (scene / "materials.toml").write_text('[parts.label_0]\nkd = [0.35, 0.45, 0.6]\n\n'
                                                  '[parts.label_1]\ntexture = "spot_texture.png"\n')
        r = invoke(scene, "solve", "-R", "4", "--reflectance", "lambert")
        assert r.exit_code == 0, r.output
        parts = {p["name"]: p for p in json.loads((scene / "out" / "reflectance.json").read_text())["parts"]}
        ground = parts["ground" if kind == "obj" else "label_0"]
        ratios[kind] = np.array(ground["relative_to_reference"])
    assert ratios["ply"] == pytest.approx(ratios["obj"], rel=0.005)
    assert np.all(ratios["obj"] > 0.2)
