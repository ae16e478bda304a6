"""Hard cases: scenes and photos that are legal but tell little about the light. Each is solved
(exit 0) with a report that says what the photo could not tell; none raises.

Each builds its photo with wavelight's own renderer (`wavelight render`) on a copy of the sample
scene, so the truth is exactly known, then runs `solve` and checks the report's numbers.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import (RES, copy_sample, decision_line, h5_arrays, invoke, ok, VIS_STAGE, vis_file)
from pipelines.light import cubemap
from pipelines.io import images
from pipelines.light import solution as lt
from pipelines.light import bases
from pipelines.io import light_file
from pipelines.light.system import LightSystem, SystemPart

H, W = 144, 192  # the sample camera


def rendered_photo(scene: Path, light: Path, material: dict, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Replace the scene's photo by wavelight's render of `light` and `material` (plus Gaussian
    noise of `noise` x the render's RMS); returns the noise-free render."""
    (scene / "m.json").write_text(json.dumps(material))
    ok(invoke(scene, "render", "--resolution", RES, "--light", str(light), "--material", str(scene / "m.json")))
    img = images.read_image(scene / "out" / "render.exr").pixels.astype(np.float32)
    photo = img.copy()
    if noise:
        rms = float(np.sqrt(np.mean(img**2))) or 1.0
        photo += np.random.default_rng(seed).normal(0.0, noise * rms, img.shape).astype(np.float32)
    images.write_exr(scene / "image.exr", photo)
    return img


def report(scene: Path) -> dict:
    return json.loads((scene / "out" / "solve_report.json").read_text())


def solved_light(scene: Path) -> tuple[np.ndarray, cubemap.CubeMap]:
    texels, cube, _ = light_file.read_solution_light(scene / "out" / "coefficients.h5")
    return texels, cube


def test_single_plane_says_only_low_frequencies_are_observable(tmp_path):
    """A mesh that is one plane: every pixel has the same normal and nothing casts a shadow, so
    every pixel sees the same blurred light. The solve fits the photo and says that it determines
    only 1 of the 9 lowest-frequency components."""
    scene = copy_sample(tmp_path / "plane")
    (scene / "mesh.obj").write_text("v -40 -40 0\nv 40 -40 0\nv 40 40 0\nv -40 40 0\nf 1 2 3\nf 1 3 4\n")
    rendered_photo(scene, scene / "truth" / "env_latlong.exr", {"model": "lambert", "kd": [0.8, 0.8, 0.8]})
    err = ok(invoke(scene, "solve", "--resolution", RES, "--reflectance", "lambert"))
    r = report(scene)
    assert r["relit"]["relative_rmse_vs_photo"] < 0.01  # any light with the right irradiance fits
    assert any("determine only 1 of the 9 lowest-frequency components" in w for w in r["warnings"]), r["warnings"]
    assert "solve: warning: the pixels determine only 1 of the 9" in err


def test_sample_scene_has_no_warnings(lambert_solved):
    """The control: Spot on its plane, with shadows, fits well and gets no warning."""
    r = report(lambert_solved)
    assert r["warnings"] == []
    assert r["relit"]["relative_rmse_vs_photo"] < 0.1


def test_few_observed_pixels_are_solved_and_called_underdetermined(tmp_path):
    """A mask that keeps 6 pixels: far fewer pixels than light coefficients and too few for a
    specular fit (the default `--reflectance auto` used to crash in the LM there)."""
    scene = copy_sample(tmp_path / "few")
    mask = np.zeros((H, W, 3))
    mask[100:102, 60:63] = 1.0  # ground in front of the cow
    images.write_png(scene / "mask.png", mask, already_display=True)
    err = ok(invoke(scene, "solve", "--resolution", RES))
    r = report(scene)
    assert r["pixels"]["used"] <= 6
    assert r["reflectance"]["model"] == "lambert"
    assert "needs at least 30" in r["reflectance"]["decision"], r["reflectance"]["decision"]
    assert any("underdetermined" in w for w in r["warnings"]), r["warnings"]
    texels, _ = solved_light(scene)
    assert np.all(np.isfinite(texels)) and texels.min() >= 0
    assert "Traceback" not in err


def test_pure_noise_photo_is_solved_and_flagged(tmp_path):
    scene = copy_sample(tmp_path / "noise")
    rng = np.random.default_rng(3)
    images.write_exr(scene / "image.exr", np.abs(rng.normal(0, 0.5, (H, W, 3))).astype(np.float32))
    ok(invoke(scene, "solve", "--resolution", RES, "--reflectance", "lambert"))
    r = report(scene)
    assert r["relit"]["relative_rmse_vs_photo"] > 0.3
    assert any("explains little of the photo" in w for w in r["warnings"]), r["warnings"]


def test_light_only_from_directions_no_pixel_sees(tmp_path):
    """All the light comes from below the horizon (the ground hides it from every pixel): the photo
    is noise around black. The solve recovers (almost) no light instead of inventing some, and
    says the fit explains little; a photo that is exactly black is refused (test_solve_cli)."""
    scene = copy_sample(tmp_path / "unseen")
    env = np.zeros((32, 64, 3), np.float32)
    env[20:26, 10:20] = 50.0  # below the horizon (rows 16..31)
    images.write_exr(scene / "below.exr", env)
    clean = rendered_photo(scene, scene / "below.exr", {"model": "lambert", "kd": [0.8, 0.8, 0.8]})
    assert np.all(clean == 0)
    rng = np.random.default_rng(5)
    images.write_exr(scene / "image.exr", rng.normal(0, 0.01, (H, W, 3)).astype(np.float32))
    ok(invoke(scene, "solve", "--resolution", RES, "--reflectance", "lambert"))
    r = report(scene)
    texels, cube = solved_light(scene)
    power = float(np.sum(texels.mean(axis=1) * cube.solid_angles))
    truth_power = float(np.sum(env.mean(axis=2) * cubemap.latlong_solid_angles(32)))
    # no more than the noise can explain: a uniform sky of radiance sigma (power 2 pi sigma) lights
    # an upward white surface to sigma; that is 0.3 % of the hidden light's power
    assert power < 2 * np.pi * 0.01 < 0.003 * truth_power
    assert r["warnings"], "a photo of nothing must come with a warning"


@pytest.mark.parametrize("shininess", [1.0, 5000.0])
def test_extreme_shininess_given(tmp_path, shininess):
    """Blinn-Phong with n = 1 (nearly diffuse) and n = 5000 (a lobe far narrower than a texel at
    R = 8, values spanning hundreds of decades): with the material given and one unknown per texel,
    the solve reproduces wavelight's own render of the true light; the default wavelet solve
    finishes too."""
    scene = copy_sample(tmp_path / f"n{shininess:g}")
    material = {"model": "blinn-phong", "kd": [0.5, 0.5, 0.5], "ks": [0.5, 0.5, 0.5], "n": shininess}
    rendered_photo(scene, scene / "truth" / "env_latlong.exr", material)
    given = ["--resolution", RES, "--reflectance", "given", "--material", str(scene / "m.json")]
    ok(invoke(scene, "solve", *given, "--basis", "discrete"))
    r = report(scene)
    assert r["relit"]["relative_rmse_vs_photo"] < 0.02, r["relit"]
    assert r["solution"]["solver"]["kkt_residual"] < 1e-6 and not r["solution"]["solver"]["fallback"]
    texels, _ = solved_light(scene)
    assert np.all(np.isfinite(texels)) and texels.min() >= 0
    ok(invoke(scene, "solve", *given))
    assert np.isfinite(report(scene)["relit"]["relative_rmse_vs_photo"])


def test_duplicate_pixels_change_nothing():
    """Every pixel twice (G, h and the pixel counts doubled): the same light, for every basis."""
    rng = np.random.default_rng(11)
    cube = cubemap.CubeMap(4)
    n = cube.n_texels
    T = np.abs(rng.normal(size=(400, n))) * (rng.random((400, n)) < 0.6)
    truth = np.maximum(rng.normal(size=(n, 3)), 0)
    b = T @ truth + 0.01 * rng.normal(size=(400, 3))
    fit, held = slice(0, 360), slice(360, 400)

    def part(rows, k):
        Tk, bk = np.vstack([T[rows]] * k), np.vstack([b[rows]] * k)
        return SystemPart(Tk.T @ Tk, Tk.T @ bk, np.sum(bk**2, axis=0), len(bk))

    for basis in ("wavelet", "quadtree", "discrete", "points", "sh"):
        once = bases.solve(LightSystem(part(fit, 1), part(held, 1), 0.0), cube, basis)
        twice = bases.solve(LightSystem(part(fit, 2), part(held, 2), 0.0), cube, basis)
        np.testing.assert_allclose(twice.light, once.light, rtol=1e-6, atol=1e-9 * np.abs(once.light).max(),
                                   err_msg=basis)


def _offset_scene(src: Path, dst: Path, offset) -> Path:
    """The same scene moved by `offset` (mesh and camera together)."""
    shutil.copytree(src, dst)
    text = []
    for line in (src / "mesh.obj").read_text().splitlines():
        if line.startswith("v "):
            x, y, z = (float(c) for c in line.split()[1:4])
            line = f"v {x + offset[0]:.9f} {y + offset[1]:.9f} {z + offset[2]:.9f}"
        text.append(line)
    (dst / "mesh.obj").write_text("\n".join(text) + "\n")
    pose = json.loads((src / "pose.json").read_text())
    R, t = np.asarray(pose["R"]), np.asarray(pose["t"])
    pose["t"] = (t - R @ np.asarray(offset, float)).tolist()  # x_cam = R (X - offset) + t
    (dst / "pose.json").write_text(json.dumps(pose))
    return dst


def test_scene_far_from_origin_gives_the_same_shadows(tmp_path):
    """Mesh and camera 1e6 from the origin (float32 has 0.06 precision there): the mesh is
    recentred before Embree, so the visibility bits are those of the scene at the origin."""
    near = copy_sample(tmp_path / "near")
    far = _offset_scene(near, tmp_path / "far", (1e6, -1e6, 1e6))
    for s in (near, far):
        ok(invoke(s, "visibility", "--resolution", RES))
    a, b = (h5_arrays(vis_file(s)) for s in (near, far))
    assert a["visibility"] == b["visibility"]
    assert a["pixels/pixel"] == b["pixels/pixel"]


@pytest.mark.parametrize("damage, note", [
    ("zero-area", "removed 1 zero-area faces"),
    ("duplicate", "removed 5 duplicate faces"),
    ("quads", "split 2 polygons of more than 3 corners into triangles"),
])
def test_mesh_repairs_are_noted_and_change_nothing(tmp_path, damage, note):
    """Zero-area and duplicate triangles are dropped and quads split, each with a note; the
    visibility is the clean mesh's, bit for bit."""
    clean = copy_sample(tmp_path / "clean")
    ok(invoke(clean, "visibility", "--resolution", RES))
    scene = copy_sample(tmp_path / damage)
    lines = (scene / "mesh.obj").read_text().splitlines()
    faces = [i for i, ln in enumerate(lines) if ln.startswith("f ")]
    if damage == "zero-area":
        lines.append("f 1//1 1//1 2//2")
    elif damage == "duplicate":
        lines += [lines[i] for i in faces[:5]]
    else:  # two pairs of triangles a b c, a c d written as the quads a b c d they are (fan order)
        by_edge = {tuple(lines[i].split()[1:4:2]): i for i in faces}  # (a, c) of each a b c
        pairs = []
        for j in faces:
            a, c, d = lines[j].split()[1:]
            i = by_edge.get((a, c))
            if i is not None and i != j and len(pairs) < 2 and not {i, j} & {k for p in pairs for k in p}:
                pairs.append((i, j))
        assert len(pairs) == 2
        quads = [f"f {' '.join(lines[i].split()[1:])} {lines[j].split()[3]}" for i, j in pairs]
        drop = {k for p in pairs for k in p}
        lines = [ln for k, ln in enumerate(lines) if k not in drop] + quads
    (scene / "mesh.obj").write_text("\n".join(lines) + "\n")
    err = ok(invoke(scene, "visibility", "--resolution", RES))
    assert note in err, err
    assert decision_line(err, VIS_STAGE) == f"{VIS_STAGE}: running (no previous run)"
    a, b = (h5_arrays(vis_file(s)) for s in (clean, scene))
    assert a["visibility"] == b["visibility"]


def test_sixteen_bit_png_photo(lambert_solved, tmp_path):
    """The photo as a 16-bit sRGB PNG (scaled into range): solved like the EXR, to within the
    PNG's quantisation."""
    import cv2

    scene = copy_sample(tmp_path / "png16")
    img = images.read_image(scene / "image.exr").pixels
    scale = 0.9 / float(img.max())
    x = np.clip(img * scale, 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    (scene / "image.exr").unlink()
    cv2.imwrite(str(scene / "image.png"), np.round(srgb * 65535).astype(np.uint16)[..., ::-1])
    ok(invoke(scene, "solve", "--resolution", RES, "--reflectance", "lambert"))
    ours, ref = report(scene), report(lambert_solved)
    assert abs(ours["relit"]["relative_rmse_vs_photo"] - ref["relit"]["relative_rmse_vs_photo"]) < 0.002
    a, _ = solved_light(scene)
    b, _ = solved_light(lambert_solved)
    np.testing.assert_allclose(a / scale, b, rtol=0.02, atol=0.01 * b.max())


def test_every_texel_unobservable_but_three():
    """Pixels that see only 3 of the 192 light directions (every other column of the transport is
    zero): every basis solves, puts no light where nothing is seen (SH cannot: it is smooth, and
    says so by its negative lobes), and the diagnosis says only 3 of 9 low-frequency components
    are determined."""
    rng = np.random.default_rng(13)
    cube = cubemap.CubeMap(8)
    n = cube.n_texels
    seen = np.array([5, 77, 150])
    T = np.zeros((500, n))
    T[:, seen] = np.abs(rng.normal(size=(500, 3)))
    b = T @ np.full((n, 3), 2.0) + 0.01 * rng.normal(size=(500, 3))
    fit, held = slice(0, 450), slice(450, 500)

    def part(rows):
        return SystemPart(T[rows].T @ T[rows], T[rows].T @ b[rows], np.sum(b[rows] ** 2, axis=0), len(b[rows]))

    ne = LightSystem(part(fit), part(held), 0.0)
    for basis in ("wavelet", "quadtree", "discrete", "points", "sh"):
        sol = bases.solve(ne, cube, basis)
        assert np.all(np.isfinite(sol.light)), basis
        if basis != "sh":
            assert sol.light.min() >= 0, basis
            unseen = np.setdiff1d(np.arange(n), seen)
            assert np.all(sol.light[unseen] == 0), basis
            assert sol.fit_rmse < 0.02, (basis, sol.fit_rmse)
    notes = lt.diagnose(ne, bases.solve(ne, cube, "discrete"), cube, relit_error=0.01)
    assert any("determine only 3 of the 9" in w for w in notes), notes


def test_convex_object_without_shadows_sees_only_a_blurred_light(tmp_path):
    """A lone sphere (no ground, nothing casts a shadow): all 9 low-frequency components are
    determined, but ~99 % of what its pixels see lies in them (a clamped cosine); the solve says
    so. The sample (Spot casting shadows on its ground) stays below the threshold (test above)."""
    from pipelines.geometry.mesh import sphere

    scene = copy_sample(tmp_path / "sphere")
    m = sphere(0.5, 4)
    v = m.vertices + np.array([0.0, 0.0, 0.5])
    lines = [f"v {a:.7f} {b:.7f} {c:.7f}" for a, b, c in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces]
    (scene / "mesh.obj").write_text("\n".join(lines) + "\n")
    rendered_photo(scene, scene / "truth" / "env_latlong.exr", {"model": "lambert", "kd": [0.8, 0.8, 0.8]})
    ok(invoke(scene, "solve", "--resolution", RES, "--reflectance", "lambert"))
    warnings = report(scene)["warnings"]
    assert any("lowest-frequency components (few cast shadows)" in w for w in warnings), warnings
    assert not any("determine only" in w for w in warnings), warnings
    ok(invoke(scene, "report"))
    text = (scene / "out" / "report.md").read_text()
    assert "What the photo cannot tell" in text and warnings[0] in text
