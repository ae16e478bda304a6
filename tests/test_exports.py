"""Exports of the light in other tools' conventions (pipelines/io/exports.py, `wavelight export`), each
read back the way that tool reads it: every direction gets the same radiance, the energy is kept."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cli_helpers import check_bad_input, invoke, ok
from pipelines.light import cubemap
from pipelines.io import exports as ex
from pipelines.io import images


def _light(H=64, seed=0, hemisphere=True):
    img = np.random.default_rng(seed).uniform(0.1, 2.0, size=(H, 2 * H, 3))
    if hemisphere:
        img[H // 2:] = 0.0
    return img


def _energy(img):
    return (img * cubemap.latlong_solid_angles(img.shape[0])[..., None]).sum(axis=(0, 1))


def test_blender_export_round_trips_every_direction():
    """Read back through Blender's own mapping at the centre of every one of our pixels (and at
    random directions): exactly our radiance; its pixels have our rows' solid angles, so the
    energy is exact too."""
    img = _light(seed=1, hemisphere=False)
    out = ex.to_blender(img)
    assert out.shape == img.shape
    d = cubemap.latlong_directions(64).reshape(-1, 3)
    np.testing.assert_array_equal(ex.blender_lookup(out, d), img.reshape(-1, 3))
    rnd = np.random.default_rng(2).normal(size=(5000, 3))
    rnd /= np.linalg.norm(rnd, axis=1, keepdims=True)
    np.testing.assert_array_equal(ex.blender_lookup(out, rnd), ex.latlong_lookup(img, rnd))
    np.testing.assert_allclose(_energy(out), _energy(img), rtol=1e-12)


def test_mitsuba_export_reads_our_radiance_at_every_pixel_centre():
    """Mitsuba's envmap puts its first and last rows on the poles (row r at v = r / (H - 1)) and
    interpolates bilinearly: the export holds 2H + 1 rows, our rows at the odd ones and the means
    of neighbouring rows at the even ones (our pixels' edges). Read back through Mitsuba's lookup:
    our radiance at the centre of every one of our pixels, in between a blend of the pixels around
    (never outside their range), and our energy (a fine quadrature of Mitsuba's reading) to 1e-4."""
    img = _light(seed=1, hemisphere=False)
    out = ex.to_mitsuba(img)
    assert out.shape == (2 * 64 + 1, 128, 3)
    d = cubemap.latlong_directions(64).reshape(-1, 3)
    np.testing.assert_allclose(ex.mitsuba_lookup(out, d), img.reshape(-1, 3), rtol=1e-12)
    rnd = np.random.default_rng(2).normal(size=(5000, 3))
    rnd /= np.linalg.norm(rnd, axis=1, keepdims=True)
    got = ex.mitsuba_lookup(out, rnd)
    theta = np.arccos(np.clip(rnd[:, 2], -1, 1))
    phi = np.arctan2(rnd[:, 1], rnd[:, 0]) % (2 * np.pi)
    r = np.clip(np.floor(theta / np.pi * 64 - 0.5).astype(int), 0, 63)
    c = np.floor(phi / (2 * np.pi) * 128 - 0.5).astype(int)
    around = np.stack([img[np.clip(r + dr, 0, 63), (c + dc) % 128] for dr in (0, 1) for dc in (0, 1)])
    assert np.all(got >= around.min(axis=0) - 1e-12) and np.all(got <= around.max(axis=0) + 1e-12)
    fine = cubemap.latlong_directions(512).reshape(-1, 3)
    w = cubemap.latlong_solid_angles(512).reshape(-1, 1)
    np.testing.assert_allclose((ex.mitsuba_lookup(out, fine) * w).sum(axis=0), _energy(img), rtol=1e-4)
    # the image as it is (export stage versions 1-2) is read up to half a row towards the poles
    off = ex.mitsuba_lookup(np.ascontiguousarray(img[:, ::-1]), d)
    assert np.median(np.abs(off / img.reshape(-1, 3) - 1)) > 0.1


def test_mitsuba_anchor_directions():
    """Hand-worked anchors of Mitsuba's mapping with our to_world: world +Z (up) is Mitsuba's local
    +Y (v = 0, the top row); the centre of our pixel (H/2, 0) (theta 92.8 deg, azimuth 2.8 deg from
    +X towards +Y) is local u = -2.8/360 wrapped, the centre of Mitsuba's column W - 1 (the mirror
    of ours), and v = (H/2 + 1/2) / H = row H + 1 of Mitsuba's 2H + 1 (v = r / 2H)."""
    H, W = 32, 64
    img = np.zeros((H, W))
    img[0, :] = 1.0
    img[H // 2, 0] = 2.0
    out = ex.to_mitsuba(img)
    assert ex.mitsuba_lookup(out, np.array([[0.0, 0.0, 1.0]]))[0] == 1.0
    theta, phi = np.pi * (H // 2 + 0.5) / H, 2 * np.pi * 0.5 / W
    d = np.array([[np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)]])
    assert out[H + 1, W - 1] == 2.0 and out[H, W - 1] == out[H + 2, W - 1] == 1.0
    np.testing.assert_allclose(ex.mitsuba_lookup(out, d)[0], 2.0, rtol=1e-12)


def test_opengl_faces_keep_every_texel():
    """Face pixels of size R are our texels: every texel's direction reads its radiance back through
    the OpenGL cube-map rule, the energy (exact face-pixel solid angles) is the light's, and the
    faces below the horizon of a hemisphere light are black."""
    cube = cubemap.CubeMap(16)
    tex = np.random.default_rng(3).uniform(0.1, 2.0, size=(cube.n_texels, 3))
    faces = ex.to_gl_faces(tex, cube)
    assert set(faces) == set(ex.GL_FACES) and all(f.shape == (16, 16, 3) for f in faces.values())
    np.testing.assert_array_equal(ex.gl_lookup(faces, cube.directions), tex)
    w = ex.gl_face_solid_angles(16)[..., None]
    energy = sum((f * w).sum(axis=(0, 1)) for f in faces.values())
    np.testing.assert_allclose(energy, (tex * cube.solid_angles[:, None]).sum(axis=0), rtol=1e-12)
    assert np.all(faces["ny"] == 0)  # GL -Y is world -Z: below the horizon
    assert np.all(faces["py"] > 0)  # GL +Y is world up
    # the side faces: lower half (larger t = lower rows in GL's -y direction) is empty
    assert np.all(faces["px"][8:] == 0) and np.all(faces["px"][:8] > 0)


def test_opengl_face_directions_follow_the_gl_table():
    """Independent anchors: the centre of face +X is GL +X = world +X; GL +Y (face py) is world +Z;
    GL +Z (face pz) is world -Y; on +X, s grows towards GL -Z (world +Y) and t towards GL -Y."""
    c = 8
    for face, world in (("px", [1, 0, 0]), ("py", [0, 0, 1]), ("pz", [0, -1, 0]), ("nx", [-1, 0, 0])):
        d = ex.gl_face_directions(face, 16)[c - 1:c + 1, c - 1:c + 1].mean(axis=(0, 1))
        np.testing.assert_allclose(d / np.linalg.norm(d), world, atol=1e-12)
    d = ex.gl_face_directions("px", 16)
    assert d[8, 15, 1] > 0.9 * d[8, 15, 0] and d[15, 8, 2] < 0  # right edge -> +Y world; bottom -> down


def test_real_mitsuba_reads_our_export_when_installed():
    """With Mitsuba 3 installed (the test extra; scalar_rgb needs no LLVM) its envmap emitter
    evaluated at random directions is our model of its lookup (`mitsuba_lookup`, to float32), and
    gives our smooth light. Measured with Mitsuba 3.9.1: the model to 5e-7; the light median
    0.009 %, max 0.07 % (bilinear interpolation on a 64-row map); with the image as it is (rows off
    Mitsuba's grid, export stage versions 1-2) median 0.10 %, max 1.3 %, and without the column
    mirror 300 %."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    d = cubemap.latlong_directions(64)

    def f(v):
        return np.stack([1 + 0.5 * v[..., 0] + 0.3 * v[..., 1], 1 + 0.2 * v[..., 2] + 0.4 * v[..., 0] * v[..., 1],
                         1 + 0.6 * v[..., 1]], -1)

    image = ex.to_mitsuba(f(d)).astype(np.float32)
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(image),
                            "to_world": mi.ScalarTransform4f(ex.MITSUBA_TO_WORLD.tolist())})
    q = np.random.default_rng(0).normal(size=(300, 3))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    vals = []
    for v in q:
        si = mi.SurfaceInteraction3f()
        si.wi = mi.ScalarVector3f(*(-v))
        vals.append(np.array(emitter.eval(si)))
    vals = np.array(vals)
    np.testing.assert_allclose(vals, ex.mitsuba_lookup(image, q), rtol=5e-6)
    rel = np.abs(vals / f(q) - 1)
    assert np.median(rel) < 0.0005 and rel.max() < 0.003


@pytest.fixture
def solved(lambert_solved):
    return lambert_solved  # the shared sample after a Lambertian solve at R = 8 (conftest.py)


def test_export_command_writes_every_format_and_they_read_back(solved, tmp_path):
    scene = shutil.copytree(solved, tmp_path / "s")
    ok(invoke(scene, "export"))
    out = scene / "out" / "export"
    from pipelines.io import light_file as lt

    tex, cube, _ = lt.read_solution_light(scene / "out" / "coefficients.h5")
    faces = {f: images.read_image(out / "opengl" / f"{f}.exr").pixels for f in ex.GL_FACES}
    np.testing.assert_allclose(ex.gl_lookup(faces, cube.directions), tex, rtol=1e-6)  # float32 files
    mitsuba = images.read_image(out / "mitsuba" / "light.exr").pixels
    blender = images.read_image(out / "blender" / "light_equirect.exr").pixels
    assert blender.shape == (64, 128, 3)  # 4 R rows, at least 64
    assert mitsuba.shape == (129, 128, 3)  # on Mitsuba's row grid: 2 H + 1
    d = cubemap.latlong_directions(64).reshape(-1, 3)
    np.testing.assert_allclose(ex.mitsuba_lookup(mitsuba, d), ex.blender_lookup(blender, d), rtol=1e-6, atol=1e-9)
    info = json.loads((out / "export.json").read_text())
    np.testing.assert_allclose(_energy(blender), info["energy_rgb"], rtol=1e-5)
    np.testing.assert_allclose(info["energy_rgb"], (tex * cube.solid_angles[:, None]).sum(axis=0), rtol=0.005)
    assert 'to_world"><matrix value="0 0 -1 0 -1 0 0 0 0 1 0 0 0 0 0 1"' in (out / "mitsuba" / "emitter.xml").read_text()
    # the fitted material (out/reflectance.json) next to the light
    from wavelight_cli.scene import material_from_options

    fitted = material_from_options(scene / "out" / "reflectance.json", None, None, None, None)
    for f in ("mitsuba/bsdf.xml", "blender/material.json", "blender/setup_material.py"):
        assert f"out/export/{f}" in info["files"]
    assert (out / "mitsuba" / "bsdf.xml").read_text() == ex.mitsuba_bsdf_xml(fitted)
    assert json.loads((out / "blender" / "material.json").read_text()) == ex.blender_material_description(fitted)
    assert info["material"]["source"] == "out/reflectance.json" and info["material"]["model"] == fitted.model
    assert info["material"]["mitsuba"]["file"] == "mitsuba/bsdf.xml"
    assert "export: skipped" in ok(invoke(scene, "export"))


def test_export_material_option_and_approximation_note(solved, tmp_path):
    """--material exports a given material; a Blinn-Phong one says it is approximate; a material
    with colours above 1 scales the exported light by the same factor."""
    scene = shutil.copytree(solved, tmp_path / "s")
    (scene / "bp.json").write_text(json.dumps({"model": "blinn-phong", "kd": [0.5, 0.4, 0.3], "ks": [0.2] * 3, "n": 40}))
    ok(invoke(scene, "export", "--format", "mitsuba", "--material", scene / "bp.json"))
    out = scene / "out" / "export"
    info = json.loads((out / "export.json").read_text())
    assert info["material"]["approximate"] and info["material"]["model"] == "blinn-phong"
    assert any(n.startswith("approximate") for n in info["material"]["notes"])
    assert "APPROXIMATION" in (out / "mitsuba" / "bsdf.xml").read_text()
    assert not (out / "blender" / "material.json").exists()
    (scene / "bright.json").write_text(json.dumps({"model": "lambert", "kd": [2.0, 1.0, 0.5]}))
    ok(invoke(scene, "export", "--format", "mitsuba", "--format", "blender", "--material", scene / "bright.json"))
    info = json.loads((out / "export.json").read_text())
    assert info["material"]["light_scale"] == 2.0
    assert 'name="scale" value="2"' in (out / "mitsuba" / "emitter.xml").read_text()
    assert "STRENGTH = 2.0" in (out / "blender" / "setup_world.py").read_text()
    assert json.loads((out / "blender" / "material.json").read_text())["inputs"]["Base Color"] == [1.0, 0.5, 0.25]


BAD = [
    ("no-solve", lambda s: (s / "out" / "coefficients.h5").unlink(), ["export"], "coefficients.h5"),
    ("light-missing", None, ["export", "--light", "nope.exr"], "nope.exr"),
    ("face-size", None, ["export", "--face-size", "12"], "--face-size"),
    ("height", None, ["export", "--height", "2"], "--height"),
    ("material-missing", None, ["export", "--material", "nope.json"], "nope.json"),
    ("material-bad", lambda s: (s / "m.json").write_text('{"model": "velvet"}'), ["export", "--material", "m.json"],
     "m.json"),
    ("corrupt-solution", lambda s: (s / "out" / "coefficients.h5").write_bytes(b"x" * 64), ["export"],
     "coefficients.h5"),
]


@pytest.mark.parametrize("mutate, args, culprit", [pytest.param(*c[1:], id=c[0]) for c in BAD])
def test_export_bad_input(solved, tmp_path, mutate, args, culprit):
    check_bad_input(solved, tmp_path, mutate, args, culprit)


# -- the fitted material ----------------------------------------------------------------------------------

from pipelines.model import microfacet as mf  # noqa: E402
from pipelines.model.materials import Material  # noqa: E402

PLASTIC_GGX = Material(kd=(0.5, 0.4, 0.3), ks=(1.0, 1.0, 1.0), model="plastic", roughness=0.2, distribution="ggx",
                       ior=1.49)


def test_material_mapping_lambert_and_plastic_are_exact():
    """lambert -> `diffuse` (reflectance kd); plastic -> `roughplastic` with our alpha, distribution,
    int_ior = ior and ext_ior = 1 (ours is relative; Mitsuba's default outside is air), kd, ks,
    nonlinear false, or `plastic` for alpha = 0; Blender: Metallic 0, Roughness = sqrt(alpha)."""
    m = ex.material_mapping(Material(kd=(0.6, 0.5, 0.4)))
    assert m["mitsuba"] == {"type": "diffuse", "reflectance": [0.6, 0.5, 0.4]} and m["exact"] and m["blender_exact"]
    assert m["blender"]["Specular IOR Level"] == 0.0 and m["blender"]["Base Color"] == [0.6, 0.5, 0.4]
    assert m["light_scale"] == 1.0
    # blinn-phong with ks = 0 is Lambert too
    assert ex.material_mapping(Material(kd=(0.6, 0.5, 0.4), model="blinn-phong", shininess=30))["mitsuba"]["type"] == "diffuse"
    m = ex.material_mapping(PLASTIC_GGX)
    assert m["mitsuba"] == {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2, "sample_visible": True,
                            "int_ior": 1.49, "ext_ior": 1.0, "diffuse_reflectance": [0.5, 0.4, 0.3],
                            "specular_reflectance": [1.0, 1.0, 1.0], "nonlinear": False}
    assert m["exact"] and not m["blender_exact"]
    b = m["blender"]
    assert b["Metallic"] == 0.0 and b["Roughness"] == pytest.approx(np.sqrt(0.2)) and b["IOR"] == 1.49
    assert b["Specular IOR Level"] == 0.5 and b["distribution"] == "GGX"
    smooth = ex.material_mapping(Material(kd=(0.5, 0.4, 0.3), ks=(0.8, 0.8, 0.8), model="plastic", roughness=0.0))
    assert smooth["mitsuba"]["type"] == "plastic" and "alpha" not in smooth["mitsuba"]
    assert smooth["mitsuba"]["specular_reflectance"] == [0.8, 0.8, 0.8]
    assert smooth["blender"]["Roughness"] == 0.0 and smooth["blender"]["Specular IOR Level"] == pytest.approx(0.4)
    beck = ex.material_mapping(Material(kd=(0.5, 0.4, 0.3), ks=(1, 1, 1), model="plastic", roughness=0.3,
                                        distribution="beckmann"))
    assert beck["mitsuba"]["distribution"] == "beckmann" and any("no Beckmann" in n for n in beck["notes"])


def _mitsuba_eval(xml_text, tmp_path, wi, wo):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    (tmp_path / "bsdf.xml").write_text(xml_text)
    bsdf = mi.load_file(str(tmp_path / "bsdf.xml"))
    out = []
    for a, b in zip(wi, wo):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*a)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        out.append(np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*b))))
    return np.array(out)


def _pairs(seed, n=200):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(2, n, 3))
    v[..., 2] = np.abs(v[..., 2]) + 0.05
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return v[0], v[1]


@pytest.mark.parametrize("material", [Material(kd=(0.6, 0.5, 0.4)), PLASTIC_GGX,
                                      Material(kd=(0.2, 0.5, 0.7), ks=(0.9, 0.7, 1.0), model="plastic", roughness=0.05,
                                               distribution="beckmann", ior=1.6),
                                      Material(kd=(0.5, 0.4, 0.3), ks=(1, 1, 1), model="plastic", roughness=0.0)],
                         ids=["lambert", "ggx", "beckmann", "smooth"])
def test_exported_bsdf_xml_evaluates_as_our_model(material, tmp_path):
    """bsdf.xml loaded by Mitsuba (mi.load_file) and evaluated at random direction pairs: f cos of
    our model per channel (the smooth coating: its non-delta part, the diffuse base), to 1e-4."""
    wi, wo = _pairs(1)
    got = _mitsuba_eval(ex.mitsuba_bsdf_xml(material), tmp_path, wi, wo)
    for c in range(3):
        if material.model == "lambert":
            want = material.kd[c] * wo[:, 2] / np.pi
        else:
            d, s = mf.eval_cos(material.kd[c], material.ks[c], material.roughness, material.ior,
                               material.distribution, wi[:, 2], wo[:, 2], np.sum(wi * wo, axis=1))
            want = d + s
        np.testing.assert_allclose(got[:, c], want, rtol=1e-4)


@pytest.mark.parametrize("model, n, alpha", [("blinn-phong", 50.0, np.sqrt(2 / 52)), ("phong", 20.0, np.sqrt(2 / 82)),
                                             ("phong-classic", 20.0, np.sqrt(2 / 82))])
def test_phong_family_maps_to_the_closest_roughplastic(model, n, alpha, tmp_path):
    """No tool has a Phong lobe: Beckmann alpha = sqrt(2 / (n' + 2)) (n' = n for Blinn-Phong, 4n for
    Phong's R.d lobe), the lobe's peak at normal incidence kept (Mitsuba's eval there = ours), the
    diffuse albedo head on kd; export.json / the XML say it is approximate."""
    m = Material(kd=(0.5, 0.4, 0.3), ks=(0.1, 0.15, 0.2), shininess=n, model=model)
    mapping = ex.material_mapping(m)
    assert not mapping["exact"] and any(n_.startswith("approximate") for n_ in mapping["notes"])
    assert mapping["mitsuba"]["distribution"] == "beckmann"
    assert mapping["mitsuba"]["alpha"] == pytest.approx(alpha)
    xml = ex.mitsuba_bsdf_xml(m)
    assert "APPROXIMATION" in xml
    # the specular peak: kd = 0, view and light along the normal
    spec_only = Material(kd=(0.0, 0.0, 0.0), ks=m.ks, shininess=n, model=model)
    z = np.array([[0.0, 0.0, 1.0]])
    got = _mitsuba_eval(ex.mitsuba_bsdf_xml(spec_only), tmp_path, z, z)[0]
    peak = {"blinn-phong": (n + 8) / (8 * np.pi), "phong": (n + 2) / (2 * np.pi), "phong-classic": 1.0}[model]
    np.testing.assert_allclose(got, np.asarray(m.ks) * peak, rtol=2e-3)
    # the diffuse albedo head on: kd (Mitsuba's diffuse part, integrated over the hemisphere)
    diffuse_only = Material(kd=m.kd, ks=(1e-9,) * 3, shininess=n, model=model)
    p = ex.material_mapping(diffuse_only)["mitsuba"]
    albedo = (np.asarray(p["diffuse_reflectance"])
              * ex.diffuse_albedo_factor(p["alpha"], p["int_ior"], "beckmann"))
    np.testing.assert_allclose(albedo, m.kd, rtol=1e-9)


def test_colours_above_one_move_into_the_light():
    """Mitsuba refuses RGB reflectances > 1: the material's colours are divided by the largest, s,
    and the light multiplied by s (emitter.xml's scale, the World's Strength): the same render."""
    m = ex.material_mapping(Material(kd=(1.6, 0.8, 0.4)))
    assert m["light_scale"] == pytest.approx(1.6)
    np.testing.assert_allclose(m["mitsuba"]["reflectance"], [1.0, 0.5, 0.25])
    np.testing.assert_allclose(m["blender"]["Base Color"], [1.0, 0.5, 0.25])
    assert 'name="scale" value="1.6"' in ex.mitsuba_xml("light.exr", m["light_scale"])
    assert "STRENGTH = 1.6" in ex.blender_world_script("light_equirect.exr", 1.6)


def test_blender_material_description_says_what_to_type():
    desc = ex.blender_material_description(PLASTIC_GGX)
    assert desc["node"] == "ShaderNodeBsdfPrincipled" and desc["distribution"] == "GGX"
    assert desc["inputs"]["Roughness"] == pytest.approx(np.sqrt(0.2)) and desc["inputs"]["Metallic"] == 0.0
    text = "\n".join(desc["settings"])
    assert "Roughness: 0.4472" in text and "Metallic: 0" in text and "IOR: 1.49" in text
    assert Material.from_json(desc["wavelight_material"]) == PLASTIC_GGX
    compile(ex.blender_material_script(), "setup_material.py", "exec")
    json.dumps(desc)


def _fake_bpy(active):
    """The few parts of Blender's bpy that setup_material.py touches (Blender 4/5 Principled BSDF
    input names), recording what it sets: the script's logic checked without Blender (the render
    in Blender itself: tests/test_exports_material.py, with the Blender venv)."""
    import types

    class Socket:
        def __init__(self, value):
            self.default_value = value

    class Node:
        def __init__(self, kind):
            self.bl_idname, self.location, self.distribution = kind, (0, 0), "MULTI_GGX"
            if kind == "ShaderNodeBsdfPrincipled":
                self.inputs = {"Base Color": Socket([0.8, 0.8, 0.8, 1.0]), "Metallic": Socket(0.0),
                               "Roughness": Socket(0.5), "IOR": Socket(1.5), "Specular IOR Level": Socket(0.5),
                               "Specular Tint": Socket([1.0, 1.0, 1.0, 1.0]), "Coat Weight": Socket(0.0)}
                self.outputs = {"BSDF": "bsdf-out"}
            elif kind == "ShaderNodeTexImage":
                self.inputs, self.outputs, self.image = {}, {"Color": "image-colour-out"}, None
                self.interpolation, self.extension = "Closest", "CLIP"
            else:
                self.inputs, self.outputs = {"Surface": "surface-in"}, {}

    class Tree:
        def __init__(self):
            self.nodes = types.SimpleNamespace(list=[], clear=lambda: self.nodes.list.clear(),
                                               new=lambda kind: self.nodes.list.append(Node(kind)) or self.nodes.list[-1])
            self.links = types.SimpleNamespace(made=[], new=lambda a, b: self.links.made.append((a, b)))

    materials = {}

    def new_material(name):
        materials[name] = types.SimpleNamespace(name=name, node_tree=Tree(), use_nodes=True)
        return materials[name]

    def load_image(path, check_existing=False):
        return types.SimpleNamespace(filepath=path, colorspace_settings=types.SimpleNamespace(name="sRGB"))

    bpy = types.ModuleType("bpy")
    bpy.data = types.SimpleNamespace(materials=types.SimpleNamespace(get=materials.get, new=new_material), texts=[],
                                     images=types.SimpleNamespace(load=load_image))
    bpy.made_materials = materials
    bpy.path = types.SimpleNamespace(abspath=lambda p: p)
    bpy.context = types.SimpleNamespace(view_layer=types.SimpleNamespace(objects=types.SimpleNamespace(active=active)))
    return bpy


@pytest.mark.parametrize("material", [Material(kd=(0.6, 0.5, 0.4)), PLASTIC_GGX], ids=["lambert", "plastic"])
def test_setup_material_script_sets_what_material_json_says(material, tmp_path, monkeypatch):
    import runpy
    import sys
    import types

    (tmp_path / "material.json").write_text(json.dumps(ex.blender_material_description(material)))
    (tmp_path / "setup_material.py").write_text(ex.blender_material_script())
    obj = types.SimpleNamespace(name="ball", data=types.SimpleNamespace(materials=[]))
    monkeypatch.setitem(sys.modules, "bpy", _fake_bpy(obj))
    runpy.run_path(str(tmp_path / "setup_material.py"), run_name="__main__")
    assert len(obj.data.materials) == 1 and obj.data.materials[0].name == "wavelight"
    tree = obj.data.materials[0].node_tree
    bsdf = next(n for n in tree.nodes.list if n.bl_idname == "ShaderNodeBsdfPrincipled")
    want = ex.blender_material_description(material)
    assert bsdf.distribution == want["distribution"] == "GGX"
    for name, value in want["inputs"].items():
        got = bsdf.inputs[name].default_value
        assert (list(got[:3]) if isinstance(value, list) else got) == value, name
        if isinstance(value, list):
            assert got[3] == 1.0
    assert tree.links.made == [("bsdf-out", "surface-in")]


# -- several parts: one light scale, a textured part as a linear bitmap ------------------------------
def _two_parts(model_material):
    """A plain part and a textured one (reflectance.json's `parts`, and the scene's parts with the
    texture's linear pixels: their largest red texel 0.9, times the part's red scale 1.5)."""
    import types

    tex = np.full((4, 8, 3), 0.5, np.float32)
    tex[1, 2] = (0.9, 0.2, 0.1)
    listed = [{"name": "ground", "kd": [0.2, 0.3, 0.4], "textured": False, "texture": None, "scale": [1, 1, 1]},
              {"name": "cow body", "kd": [0.8, 0.5, 0.5], "textured": True, "texture": "cow.png",
               "scale": [1.5, 1.0, 1.0]}]
    sp = types.SimpleNamespace(parts=[types.SimpleNamespace(name="cow body", texture=types.SimpleNamespace(levels=[tex])),
                                      types.SimpleNamespace(name="ground", texture=None)])
    return ex.part_exports(model_material, listed, sp), tex


def test_parts_share_one_light_scale_and_a_texture_becomes_a_bitmap():
    parts, tex = _two_parts(Material(kd=(1.0, 1.0, 1.0)))
    assert [p.file_stem for p in parts] == ["ground", "cow_body"]
    assert parts[0].texture is None and parts[1].texture is tex and parts[1].exact
    scale = ex.parts_light_scale(Material(kd=(1.0, 1.0, 1.0)), parts)
    assert scale == pytest.approx(1.5 * 0.9)  # the textured part's largest colour
    bitmap, base = ex.textured_images(parts[1].material, tex, scale)
    assert bitmap == pytest.approx(tex * np.array([1.5, 1.0, 1.0]) / scale)
    assert bitmap.max() == pytest.approx(1.0) and base == pytest.approx(bitmap)  # Lambert: the same in both tools
    xml = ex.mitsuba_bsdf_xml(parts[1].material, "p", scale, "kd_cow_body.exr")
    assert '<texture type="bitmap" name="reflectance"><string name="filename" value="kd_cow_body.exr"/>' in xml
    assert '<boolean name="raw" value="true"/>' in xml
    plain = ex.material_mapping(parts[0].material, scale)
    assert plain["mitsuba"]["reflectance"] == pytest.approx(np.array([0.2, 0.3, 0.4]) / scale)
    assert plain["light_scale"] == scale


def test_plastic_parts_texture_the_diffuse_reflectance():
    """Plastic: the bitmap replaces diffuse_reflectance; the coating's colours share the light scale."""
    base = Material(kd=(1.0, 1.0, 1.0), ks=(2.0, 2.0, 2.0), model="plastic", roughness=0.2, distribution="ggx", ior=1.5)
    parts, tex = _two_parts(base)
    scale = ex.parts_light_scale(base, parts)
    assert scale >= 2.0  # ks = 2 is a colour too
    m = ex.material_mapping(parts[1].material, scale)
    assert m["mitsuba"]["specular_reflectance"] == pytest.approx([2.0 / scale] * 3)
    bitmap, blender = ex.textured_images(parts[1].material, tex, scale)
    assert bitmap == pytest.approx(tex * np.asarray(m["mitsuba"]["diffuse_reflectance"], np.float32))
    assert blender == pytest.approx(tex * np.asarray(m["blender"]["Base Color"], np.float32))
    xml = ex.mitsuba_bsdf_xml(parts[1].material, "p", scale, "kd_cow_body.exr")
    assert '<texture type="bitmap" name="diffuse_reflectance">' in xml and "specular_reflectance" in xml


def test_setup_material_script_makes_the_parts_materials(tmp_path, monkeypatch):
    """material.json with parts: one material per part, named as the part; the textured one's Base
    Color an Image Texture (linear) of its base_<part>.exr; an existing material of that name (the
    OBJ import's) rebuilt in place; the object keeps its slots."""
    import runpy
    import sys
    import types

    parts, _ = _two_parts(Material(kd=(1.0, 1.0, 1.0)))
    desc = ex.blender_material_description(Material(kd=(1.0, 1.0, 1.0)), 1.35,
                                           [(parts[0], None), (parts[1], "base_cow_body.exr")])
    assert [p["name"] for p in desc["parts"]] == ["ground", "cow body"]
    assert desc["parts"][1]["base_color_image"] == "base_cow_body.exr"
    assert any("Image Texture" in line for line in desc["parts"][1]["settings"])
    (tmp_path / "material.json").write_text(json.dumps(desc))
    (tmp_path / "setup_material.py").write_text(ex.blender_material_script())
    bpy = _fake_bpy(None)
    imported = bpy.data.materials.new("ground")  # as Blender's OBJ import names the usemtl group's material
    obj = types.SimpleNamespace(name="cow", data=types.SimpleNamespace(materials=[imported]))
    bpy.context.view_layer.objects.active = obj
    monkeypatch.setitem(sys.modules, "bpy", bpy)
    runpy.run_path(str(tmp_path / "setup_material.py"), run_name="__main__")
    made = bpy.made_materials
    assert set(made) == {"ground", "cow body"} and obj.data.materials == [imported] and made["ground"] is imported
    ground = next(n for n in imported.node_tree.nodes.list if n.bl_idname == "ShaderNodeBsdfPrincipled")
    assert list(ground.inputs["Base Color"].default_value[:3]) == pytest.approx(np.array([0.2, 0.3, 0.4]) / 1.35)
    cow = made["cow body"].node_tree
    image = next(n for n in cow.nodes.list if n.bl_idname == "ShaderNodeTexImage")
    assert image.image.filepath == str(tmp_path / "base_cow_body.exr")
    assert image.image.colorspace_settings.name == "Linear Rec.709" and image.extension == "REPEAT"
    bsdf = next(n for n in cow.nodes.list if n.bl_idname == "ShaderNodeBsdfPrincipled")
    assert ("image-colour-out", bsdf.inputs["Base Color"]) in cow.links.made
