"""The exported material proven in Mitsuba 3: `wavelight export --light light.exr --material m.json`
writes bsdf.xml next to emitter.xml; Mitsuba (scalar_rgb, `direct`, two seeds) renders a unit sphere
with the BSDF loaded from that file (`mi.load_file`) under the emitter loaded from its file, and
wavelight renders the same pixel footprints with the same material under the light it exported
(`render.transport`, V = 1, the light on a cube map of R = 32: tool_scenes.wavelight_render).

The scene, the light (a 64-row sky with a 2.5 deg sun) and the comparison (relative RMSE over the
sphere's pixels of the mean of the two renders against wavelight's, next to that mean's noise) are
tests/test_exports_tools.py's. Lambert and plastic (GGX alpha 0.2, Beckmann alpha 0.2) are the same
model on both sides: error at the noise level. Blinn-Phong has no Mitsuba equivalent: the export's
closest roughplastic is reported, its error asserted only to stay what it was measured to be.

The Blender side (tests/blender_render.py, only with the Blender venv: `make venv-blender`):
setup_material.py builds the Principled BSDF from material.json on the sphere, under the World
setup_world.py makes; Lambert (Specular IOR Level 0) is exact, plastic is Principled's own layering
(approximate: reported, loosely bounded).
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

import tool_scenes as ts
from cli_helpers import invoke, ok
from pipelines.io import images
from pipelines.model.materials import Material

SPP = 256  # per Mitsuba render; two renders -> the compared mean has ~0.5-0.8 % noise
FOOTPRINT = 3
MARGIN = 1.25  # allowed error / noise (as tests/test_exports_tools.py)
BLENDER_SPP = 160

MATERIALS = {
    "lambert": Material(kd=(0.6, 0.5, 0.4)),
    "plastic-ggx": Material(kd=(0.5, 0.4, 0.3), ks=(1.0, 1.0, 1.0), model="plastic", roughness=0.2,
                            distribution="ggx", ior=1.49),
    "plastic-beckmann": Material(kd=(0.3, 0.45, 0.6), ks=(0.8, 0.8, 0.8), model="plastic", roughness=0.2,
                                 distribution="beckmann", ior=1.6),
    "blinn-phong": Material(kd=(0.5, 0.4, 0.3), ks=(0.15, 0.15, 0.15), shininess=50.0, model="blinn-phong"),
}
EXACT = ("lambert", "plastic-ggx", "plastic-beckmann")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    work = tmp_path_factory.mktemp("material_export")
    folder = work / "scene"
    folder.mkdir()
    images.write_exr(folder / "light.exr", ts.scene_light())
    light = images.read_latlong(folder / "light.exr")  # as wavelight reads it
    camera, centres = ts.pair_camera()
    n, v, inside = ts.sphere_view(camera, 128, 64, center=centres[0], k=FOOTPRINT)
    return {"work": work, "folder": folder, "light": light, "camera": camera, "center": centres[0],
            "normals": n[inside], "views": v[inside], "inside": inside, "exports": {}, "ours": {}}


def exported(setup, name):
    """out/export/ of `wavelight export --light light.exr --material NAME.json` (Mitsuba and Blender)."""
    if name not in setup["exports"]:
        folder = setup["work"] / name
        folder.mkdir()
        (folder / "light.exr").write_bytes((setup["folder"] / "light.exr").read_bytes())
        (folder / "material.json").write_text(json.dumps(MATERIALS[name].to_json()))
        ok(invoke(folder, "export", "--light", folder / "light.exr", "--material", folder / "material.json",
                  "--format", "mitsuba", "--format", "blender"))
        setup["exports"][name] = folder / "out" / "export"
    return setup["exports"][name]


def ours(setup, name):
    if name not in setup["ours"]:
        setup["ours"][name] = ts.footprint_mean(ts.wavelight_render, setup["normals"], setup["views"], setup["light"],
                                                MATERIALS[name], resolution=32)
    return setup["ours"][name]


def mitsuba_render(setup, name):
    out = exported(setup, name)
    sphere = {"kind": "sphere", "center": list(setup["center"]), "radius": 1.0,
              "material": {"type": "file", "path": out / "mitsuba" / "bsdf.xml"}}
    r = ts.render_mitsuba(out / "mitsuba" / "emitter.xml", setup["camera"], 128, 64, [sphere], SPP)
    return r["seed1"][setup["inside"]], r["seed2"][setup["inside"]]


@pytest.mark.parametrize("name", EXACT)
def test_exported_bsdf_renders_in_mitsuba_as_wavelight(setup, name):
    """Lambert and plastic: Mitsuba's render of bsdf.xml under emitter.xml is wavelight's render of
    the fitted material under the exported light, at Mitsuba's noise level."""
    pytest.importorskip("mitsuba")
    t = time.perf_counter()
    first, second = mitsuba_render(setup, name)
    a = ts.agreement(first, second, ours(setup, name))
    print(f"Mitsuba {name}: error {100 * a['error']:.3f} %, noise {100 * a['noise']:.3f} %, "
          f"bias {100 * a['bias']:.3f} %, mean ratio {a['ratio']:.5f} ({time.perf_counter() - t:.1f} s)")
    assert a["noise"] < 0.012, a
    assert a["error"] <= MARGIN * a["noise"], a


def test_blinn_phong_export_is_the_closest_roughplastic(setup):
    """Blinn-Phong has no Mitsuba BSDF: the exported roughplastic (Beckmann alpha = sqrt(2 / (n + 2)),
    the peak and the head-on albedo kept) rendered against wavelight's Blinn-Phong: reported; the
    bound only keeps it where it was measured (see the README's Exports)."""
    pytest.importorskip("mitsuba")
    info = json.loads((exported(setup, "blinn-phong") / "export.json").read_text())
    assert info["material"]["approximate"]
    first, second = mitsuba_render(setup, "blinn-phong")
    ref = ours(setup, "blinn-phong")
    a = ts.agreement(first, second, ref)
    lum = np.array([0.2126, 0.7152, 0.0722])
    mean = 0.5 * (first + second)
    worst = float(np.percentile(np.abs(mean @ lum - ref @ lum) / np.maximum(ref @ lum, 1e-6), 95))
    print(f"Mitsuba blinn-phong approximation: error {100 * a['error']:.2f} % (noise {100 * a['noise']:.2f} %), "
          f"mean ratio {a['ratio']:.4f}, 95th percentile per-pixel {100 * worst:.1f} %")
    assert a["error"] < 0.15, a


# -- Blender ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def blender(setup):
    """The sphere with setup_material.py's material (from material.json) under setup_world.py's World,
    twice (seeds 1, 2), for Lambert and the GGX plastic, in one bpy process."""
    python, why = ts.blender_python()
    if python is None:
        pytest.skip(why)
    jobs = {}
    for name in ("lambert", "plastic-ggx"):
        out = exported(setup, name)
        sphere = {"kind": "sphere", "center": list(setup["center"]), "radius": 1.0, "camera_only": True,
                  "material": {"type": "script", "script": str(out / "blender" / "setup_material.py")}}
        for seed in (1, 2):
            jobs[f"{name}_seed{seed}"] = {"camera": setup["camera"], "width": 128, "height": 64, "samples": BLENDER_SPP,
                                          "seed": seed, "threads": 2, "objects": [sphere],
                                          "world": {"mode": "script", "script": str(out / "blender" / "setup_world.py")}}
    t = time.perf_counter()
    result = ts.render_blender(jobs, setup["work"] / "blender")
    print(f"Blender: {len(jobs)} jobs in {time.perf_counter() - t:.1f} s")
    return result


def _blender_pixels(blender, setup, job):
    return blender[job]["passes"]["Combined"][setup["inside"]]


@pytest.mark.slow
def test_blender_lambert_material_renders_as_wavelight(blender, setup):
    """Principled BSDF with Specular IOR Level 0 is Lambert: at Cycles' noise level."""
    a = ts.agreement(_blender_pixels(blender, setup, "lambert_seed1"), _blender_pixels(blender, setup, "lambert_seed2"),
                  ours(setup, "lambert"))
    print(f"Blender lambert: error {100 * a['error']:.3f} %, noise {100 * a['noise']:.3f} %, ratio {a['ratio']:.5f}")
    assert a["noise"] < 0.015, a
    assert a["error"] <= MARGIN * a["noise"], a


@pytest.mark.slow
def test_blender_plastic_material_is_close_to_wavelight(blender, setup):
    """Principled BSDF (GGX, Roughness sqrt(alpha), IOR, Base Color for the head-on albedo) is not
    Mitsuba's roughplastic layering: reported, loosely bounded (not measured locally: bpy is not
    installed here; see the report)."""
    a = ts.agreement(_blender_pixels(blender, setup, "plastic-ggx_seed1"),
                  _blender_pixels(blender, setup, "plastic-ggx_seed2"), ours(setup, "plastic-ggx"))
    print(f"Blender plastic (GGX 0.2): error {100 * a['error']:.2f} %, noise {100 * a['noise']:.2f} %, "
          f"ratio {a['ratio']:.4f}")
    assert a["error"] < 0.10, a
