"""The export proven in the tools themselves: `wavelight export` writes a light, Blender (Cycles,
CPU) and Mitsuba 3 render spheres under the files it wrote, and wavelight renders the same pixels
under the light it exported. The scenes and both sides' renderers: tests/tool_scenes.py.

The light (tool_scenes.sky_with_sun): a 64-row lat-long, a sky whose colour changes with azimuth and
elevation (a mirrored, turned or flipped map renders differently) and a 2.5 deg sun at theta 50,
phi 65 holding ~2/3 of a horizontal patch's irradiance; nothing below the horizon.

Agreement is the relative RMSE over the spheres' pixels (those whose whole footprint sees the
sphere) between the mean of two renders with different seeds and the reference, next to the noise
of that mean (from the two renders' difference: E[(A - B)^2] = 2 sigma^2). An unbiased tool gives
error = noise (to a few %: ~5000 values, heavier tails for glossy); the tests allow
error <= 1.25 x noise, i.e. a bias of up to 0.75 x the noise (~0.75 % for Blender, ~0.4-0.5 % for
Mitsuba), and check that the noise is what the sample counts were chosen for. What is left besides
noise, measured at 6-8x the samples (Blender 1024, Mitsuba 2048 per render): Blender diffuse
0.00 %, Mitsuba diffuse 0.02 %, and glossy 0.30 % (Blender) and 0.27 % (Mitsuba): both tools alike,
so it is the reference's (the numerical GGX over the light's 2.8 deg pixels, which both tools read
bilinearly; 0.22 % with 2 x 2 directions per light pixel). A convention error is far outside: a
mirrored or turned map is tens of %, and Mitsuba's rows read as if they were ours (the export
before stage version 3) fails all three Mitsuba checks: diffuse 1.46 x its noise (bias 0.56 %),
glossy 3.2 x (2.0 %), the sun 0.57 deg off.

Blender: bpy (Blender as a module) pins numpy < 2 and wavelight needs numpy >= 2, so it lives in its
own venv (`make venv-blender` -> .venv-blender, ~375 MB download, ~1 GB on disk) and renders in a
subprocess; without it the Blender tests skip, saying so. One Blender process renders every image
(importing bpy is ~5 s of it).
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

import tool_scenes as ts
from cli_helpers import invoke, ok
from pipelines.io import exports as ex
from pipelines.io import images
from pipelines.light import cubemap
from pipelines.model.materials import Material

ROUGHNESS = 0.5  # Blender's Glossy roughness; GGX alpha = roughness^2 (Cycles: alpha = r^2)
ALPHA = ROUGHNESS**2
FOOTPRINT = 3  # k x k sub-pixel samples per pixel for the references (both tools integrate the pixel's area)
BLENDER_SPP = 160  # per render; two renders -> the compared mean has ~1.0 % (diffuse) / 1.2 % (glossy) noise
MITSUBA_SPP = 256  # per render (low-discrepancy sampler); mean ~0.5 % / 0.8 %
SHADOW_SPP = 64  # Mitsuba's low-discrepancy sampler wants a square power of two
MARGIN = 1.25  # allowed error / noise


def agreement(first: np.ndarray, second: np.ndarray, reference: np.ndarray) -> dict:
    """Error of the two renders' mean against the reference, the mean's noise, and the bias left
    when the noise is taken out (sqrt(error^2 - noise^2), 0 if negative)."""
    mean = 0.5 * (first + second)
    err = ts.relative_rmse(mean, reference)
    noise = ts.noise_level(first, second, reference) / np.sqrt(2)
    return {"error": err, "noise": noise, "bias": float(np.sqrt(max(0.0, err**2 - noise**2))),
            "single_error": ts.relative_rmse(first, reference), "ratio": float(mean.mean() / reference.mean())}


def check(name: str, a: dict, max_noise: float):
    print(f"{name}: error {100 * a['error']:.3f} %, noise {100 * a['noise']:.3f} %, bias {100 * a['bias']:.3f} %, "
          f"one render {100 * a['single_error']:.3f} %, mean ratio {a['ratio']:.5f}")
    assert a["noise"] < max_noise, f"{name}: the renders are noisier than planned ({a})"
    assert a["error"] <= MARGIN * a["noise"], f"{name}: not at the noise level ({a})"


# -- the exported light and wavelight's side -------------------------------------------------------------

def _export(folder, light):
    folder.mkdir()
    images.write_exr(folder / "light.exr", light)
    ok(invoke(folder, "export", "--light", folder / "light.exr", "--format", "mitsuba", "--format", "blender"))
    return folder / "out" / "export", images.read_latlong(folder / "light.exr")  # as wavelight reads it


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """`wavelight export --light light.exr` on empty scene folders, for the sky-and-sun light and
    for the sun alone (Mitsuba and Blender only: the OpenGL faces' cube map at its default 64 x 64
    faces takes ~40 s to resample a lat-long)."""
    work = tmp_path_factory.mktemp("tools")
    out, light = _export(work / "scene", ts.scene_light())
    sun_out, sun = _export(work / "sun", ts.sun_light())
    return {"light": light, "out": out, "sun": sun, "sun_out": sun_out, "work": work}


@pytest.fixture(scope="module")
def pair(exported):
    """The two-sphere view: per sphere its pixels ("inside"), the footprints' normals and view
    directions, and wavelight's render of the diffuse one (`transport`, V = 1, R = 32)."""
    camera, centres = ts.pair_camera()
    spheres = []
    for c in centres:
        n, v, inside = ts.sphere_view(camera, 128, 64, center=c, k=FOOTPRINT)
        spheres.append({"center": c, "normals": n, "views": v, "inside": inside})
    d = spheres[0]
    t = time.perf_counter()
    diffuse = ts.footprint_mean(ts.wavelight_render, d["normals"][d["inside"]], d["views"][d["inside"]],
                                exported["light"], Material(), resolution=32)
    print(f"wavelight's render of the diffuse sphere: {time.perf_counter() - t:.1f} s")
    return {"camera": camera, "spheres": spheres, "diffuse": diffuse, "glossy": {}}


def glossy_reference(pair, exported, shadowing: str, sphere: int) -> np.ndarray:
    key = (shadowing, sphere)
    if key not in pair["glossy"]:
        g = pair["spheres"][sphere]
        t = time.perf_counter()
        pair["glossy"][key] = ts.footprint_mean(ts.GLOSSY_REFERENCE, g["normals"][g["inside"]], g["views"][g["inside"]],
                                                exported["light"], ALPHA, shadowing)
        print(f"glossy reference ({shadowing}): {time.perf_counter() - t:.1f} s")
    return pair["glossy"][key]


def test_export_writes_the_blender_script_and_lists_it(exported):
    out = exported["out"]
    info = json.loads((out / "export.json").read_text())
    assert "out/export/blender/setup_world.py" in info["files"]
    text = (out / "blender" / "setup_world.py").read_text()
    assert text == ex.blender_world_script("light_equirect.exr")
    compile(text, "setup_world.py", "exec")
    with pytest.raises(ValueError):
        ex.blender_world_script("../x.exr")


# -- Blender ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def blender(exported, pair):
    """Every Blender image, in one bpy process: the two spheres (left diffuse, right glossy GGX; each
    seen by camera rays only, so they neither shadow nor reflect each other) under a World built by
    hand, twice (seeds 1, 2); the same with the World that setup_world.py makes (seed 1); the
    world that script makes when run from Blender's Text Editor (described, not rendered); and the
    ball over the ground plane in the sun."""
    python, why = ts.blender_python()
    if python is None:
        pytest.skip(why)
    image = str(exported["out"] / "blender" / "light_equirect.exr")
    script = str(exported["out"] / "blender" / "setup_world.py")
    spheres = [{"kind": "sphere", "center": list(s["center"]), "radius": 1.0, "camera_only": True, "material": m}
               for s, m in zip(pair["spheres"], ({"type": "diffuse", "color": [1, 1, 1]},
                                                 {"type": "glossy", "roughness": ROUGHNESS, "distribution": "GGX"}))]
    base = {"camera": pair["camera"], "width": 128, "height": 64, "samples": BLENDER_SPP, "threads": 2,
            "objects": spheres}
    hand = {"mode": "nodes", "image": image}
    jobs = {"pair_seed1": dict(base, world=hand, seed=1),
            "pair_seed2": dict(base, world=hand, seed=2),
            "pair_script": dict(base, world={"mode": "script", "script": script}, seed=1),
            "text_world": dict(base, world={"mode": "text", "script": script}, seed=1, render=False),
            "shadow": {"camera": ts.shadow_camera(), "width": 96, "height": 96, "samples": SHADOW_SPP, "seed": 1,
                       "threads": 2, "objects": ts.SHADOW_OBJECTS,
                       "world": {"mode": "nodes", "image": str(exported["sun_out"] / "blender" / "light_equirect.exr")}}}
    t = time.perf_counter()
    out = ts.render_blender(jobs, exported["work"] / "blender")
    print(f"Blender: {len(jobs)} jobs in {time.perf_counter() - t:.1f} s")
    return out


def _sphere_pixels(blender, pair, job, sphere):
    s = pair["spheres"][sphere]
    return blender[job]["passes"]["Combined"][s["inside"]]


@pytest.mark.slow
def test_blender_sees_the_spheres_where_we_do(blender, pair):
    """Geometry first: Blender's Normal pass (the mean over each pixel's samples) is the mean of our
    footprints' normals, so the camera, the pixel grid and the spheres are the same on both sides,
    and Cycles integrates the pixel's area (its box filter is one pixel wide whatever its width):
    the normals at the pixels' centres alone are several times further off."""
    normal = blender["pair_seed1"]["passes"]["Normal"]
    for i, s in enumerate(pair["spheres"]):
        footprint = _rms(normal[s["inside"]] - s["normals"].mean(axis=2)[s["inside"]])
        o, d = ts.pixel_rays(pair["camera"], 128, 64)
        t, _ = ts.hit_sphere(o[0], d[0], s["center"], 1.0)
        centre = _rms(normal[s["inside"]] - (o[0] + t[..., None] * d[0] - s["center"])[s["inside"]])
        print(f"sphere {i}: Normal pass vs our footprint mean {footprint:.2g} rms, vs the pixel centres {centre:.2g}")
        assert footprint < 3e-4 and footprint < 0.5 * centre


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


@pytest.mark.slow
def test_blender_diffuse_sphere_renders_as_wavelight(blender, pair):
    """Cycles' Diffuse BSDF (roughness 0: Lambert) under the exported Environment Texture against
    wavelight's transport (kd = 1) of the light it exported, over the diffuse sphere's pixels."""
    a = agreement(_sphere_pixels(blender, pair, "pair_seed1", 0), _sphere_pixels(blender, pair, "pair_seed2", 0),
                  pair["diffuse"])
    check("Blender diffuse", a, max_noise=0.012)


@pytest.mark.slow
def test_blender_glossy_sphere_renders_as_ggx(blender, pair, exported):
    """Cycles' Glossy BSDF, GGX (single scattering, F = 1, alpha = roughness^2) against the GGX lobe
    integrated numerically over the exported light (tool_scenes.GLOSSY_REFERENCE) with Cycles'
    height-correlated Smith term. Why not Mitsuba's roughconductor as the reference: it uses the
    separable Smith term, a different BRDF (0.04 % overall here, more at grazing angles), and brings
    its own noise; the numerical integral is exact up to the light's pixels and is the slot that
    wavelight's own microfacet model will fill."""
    ref = glossy_reference(pair, exported, "height-correlated", 1)
    a = agreement(_sphere_pixels(blender, pair, "pair_seed1", 1), _sphere_pixels(blender, pair, "pair_seed2", 1), ref)
    check("Blender glossy", a, max_noise=0.015)


@pytest.mark.slow
def test_blender_setup_world_script_makes_the_same_world(blender, exported):
    """setup_world.py (run as `blender --python` runs it, and from the Text Editor) makes a World
    that renders exactly as the hand-built one (same seed: the same image, bit for bit or to
    float rounding), from the exported file next to the script, linear, strength 1, no turn."""
    a, b = blender["pair_seed1"]["passes"]["Combined"], blender["pair_script"]["passes"]["Combined"]
    print(f"script world vs hand-built: max |difference| {np.abs(a - b).max():.3g} (image max {a.max():.3g})")
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6)
    for job in ("pair_script", "text_world"):
        w = blender[job]["world"]
        assert w["name"] == "wavelight"
        env = next(n for n in w["nodes"] if n["type"] == "ShaderNodeTexEnvironment")
        assert env["image"] == str(exported["out"] / "blender" / "light_equirect.exr")
        assert env["colorspace"] == "Linear Rec.709" and env["projection"] == "EQUIRECTANGULAR"
        bg = next(n for n in w["nodes"] if n["type"] == "ShaderNodeBackground")
        assert bg["strength"] == 1.0
        mapping = next(n for n in w["nodes"] if n["type"] == "ShaderNodeMapping")
        assert mapping["Rotation"] == [0, 0, 0] and mapping["Scale"] == [1, 1, 1] and mapping["Location"] == [0, 0, 0]
    assert blender["text_world"]["world"] == blender["pair_script"]["world"]


@pytest.mark.slow
def test_blender_puts_the_sun_where_wavelight_has_it(blender, exported):
    """A black ball over a white ground plane under the sun alone: the centre of its shadow, from
    Blender's Position pass, gives the sun's direction as Cycles sees the exported map; against
    the direction of the light's brightest spot wavelight exported (the centroid of its sun pixels;
    the solve's `brightest_direction` texel at R = 32 is printed too: it is quantised to its
    2.8 deg texel)."""
    passes = blender["shadow"]["passes"]
    seen, count = ts.sun_from_shadow(passes["Combined"], passes["Position"])
    _check_sun("Blender", seen, count, exported["sun"])


def _check_sun(tool, seen, count, light):
    """The direction the tool's shadow gives against the one the exported light predicts for the
    same measurement (`shadow_direction`), and for the record the light's mean direction, the true
    sun and the solve's `brightest_direction` (its brightest texel at R = 32: 2.8 deg texels)."""
    predicted = ts.shadow_direction(light)
    cube = cubemap.CubeMap(32)
    texel = cube.directions[np.argmax(cubemap.latlong_to_cube(light, cube) @ np.array([0.2126, 0.7152, 0.0722]))]
    err = ts.angle_deg(seen, predicted)
    print(f"{tool}: sun from the shadow ({count} umbra px) {err:.3f} deg from wavelight's prediction; "
          f"{ts.angle_deg(seen, ts.mean_direction(light)):.3f} deg from the light's mean direction, "
          f"{ts.angle_deg(seen, ts.sun_direction(*ts.SUN)):.3f} deg from the true sun, "
          f"{ts.angle_deg(seen, texel):.2f} deg from the brightest R = 32 texel")
    assert count > 50
    assert err < 0.2


# -- Mitsuba 3 -------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def mitsuba(exported, pair):
    pytest.importorskip("mitsuba")
    emitter = exported["out"] / "mitsuba" / "emitter.xml"
    out = {}
    t = time.perf_counter()
    for i, material in enumerate(({"type": "diffuse"}, {"type": "roughconductor", "alpha": ALPHA})):
        sphere = {"kind": "sphere", "center": list(pair["spheres"][i]["center"]), "radius": 1.0, "material": material}
        out[material["type"]] = ts.render_mitsuba(emitter, pair["camera"], 128, 64, [sphere], MITSUBA_SPP,
                                                  aov_spp=16 if i == 0 else 0)
    out["shadow"] = ts.render_mitsuba(exported["sun_out"] / "mitsuba" / "emitter.xml", ts.shadow_camera(), 96, 96,
                                      ts.SHADOW_OBJECTS, SHADOW_SPP, seeds=(1,), aov_spp=4)
    print(f"Mitsuba: 6 renders in {time.perf_counter() - t:.1f} s")
    return out


def test_mitsuba_loads_the_emitter_file_every_way(exported):
    """emitter.xml by itself (mi.load_file), included from a scene, and pasted into one (less its
    root's version attribute, as its comment says)."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    folder = exported["out"] / "mitsuba"
    assert "EnvironmentMapEmitter" in str(mi.load_file(str(folder / "emitter.xml")))
    (folder / "scene_include.xml").write_text('<scene version="3.0.0"><include filename="emitter.xml"/></scene>')
    assert mi.load_file(str(folder / "scene_include.xml")).environment() is not None
    # pasted, the root's version attribute goes (Mitsuba 3.9 refuses it on an inner element)
    pasted = '<scene version="3.0.0">\n' + (folder / "emitter.xml").read_text().replace(' version="3.0.0"', "") + "</scene>\n"
    (folder / "scene_pasted.xml").write_text(pasted)
    assert mi.load_file(str(folder / "scene_pasted.xml")).environment() is not None


def test_mitsuba_sees_the_sphere_where_we_do(mitsuba, pair):
    """Mitsuba's shading-normal AOV (16 random samples per pixel) is the mean of our footprint's
    normals, up to its own sampling noise (~1e-3 rms)."""
    s = pair["spheres"][0]
    d = mitsuba["diffuse"]["normal"][s["inside"]] - s["normals"].mean(axis=2)[s["inside"]]
    assert np.sqrt(np.mean(d**2)) < 4e-3 and np.abs(d.mean(axis=0)).max() < 3e-4


def test_mitsuba_diffuse_sphere_renders_as_wavelight(mitsuba, pair):
    """Mitsuba's `diffuse` (reflectance 1) under the exported envmap against wavelight's transport."""
    s = pair["spheres"][0]
    a = agreement(mitsuba["diffuse"]["seed1"][s["inside"]], mitsuba["diffuse"]["seed2"][s["inside"]], pair["diffuse"])
    check("Mitsuba diffuse", a, max_noise=0.008)


def test_mitsuba_glossy_sphere_renders_as_ggx(mitsuba, pair, exported):
    """Mitsuba's `roughconductor` (GGX, material "none": F = 1, the same alpha) against the
    numerical GGX integral with Mitsuba's separable Smith term (its BSDF's eval is that formula to
    float precision)."""
    ref = glossy_reference(pair, exported, "separable", 1)
    s = pair["spheres"][1]
    a = agreement(mitsuba["roughconductor"]["seed1"][s["inside"]], mitsuba["roughconductor"]["seed2"][s["inside"]], ref)
    check("Mitsuba glossy", a, max_noise=0.012)


def test_mitsuba_puts_the_sun_where_wavelight_has_it(mitsuba, exported):
    seen, count = ts.sun_from_shadow(mitsuba["shadow"]["seed1"], mitsuba["shadow"]["position"])
    _check_sun("Mitsuba", seen, count, exported["sun"])
