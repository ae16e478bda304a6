"""What the render images look like (README: Outputs, "Render images"): solve's relit.exr/png,
relight's NAME.exr/png and render's render.exr/png.

- No black ring: the edge margin (pixels of the mesh next to silhouettes and depth jumps, left out
  of the solve) used to be written as 0, a black outline around the object wherever the photo is
  not black. It now takes the nearest rendered pixel's value; off the mesh the PNG shows the photo
  (the photo's view) or is transparent (another view), and the EXR's alpha says what was rendered.
- One exposure: a PNG used to be auto-exposed on its own 99.5th percentile, so a light one stop
  darker looked the same (or brighter, turned). Every render PNG now takes the photo's exposure.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cli_helpers import RES, invoke, ok
from pipelines.io import images
from wavelight_cli import outputs
from wavelight_cli.outputs import read_png_text, read_rgba


@pytest.fixture(scope="module")
def relit(lambert_solved, tmp_path_factory):
    """A copy of the solved sample with relights: the photo's light, one stop darker, -1 stop with
    --exposure 0, and from another view (the same camera, moved)."""
    scene = shutil.copytree(lambert_solved, tmp_path_factory.mktemp("render_images") / "s")
    ok(invoke(scene, "relight", "--name", "same"))
    ok(invoke(scene, "relight", "--name", "dark", "--light-exposure", "-1"))
    ok(invoke(scene, "relight", "--name", "dark_fixed", "--light-exposure", "-1", "--exposure", "0"))
    ok(invoke(scene, "relight", "--name", "same_fixed", "--exposure", "0"))
    pose = json.loads((scene / "pose.json").read_text())
    pose = {"R": pose["R"], "t": [pose["t"][0] + 0.15, pose["t"][1], pose["t"][2] * 1.1]}  # a step aside, back
    (scene / "other_pose.json").write_text(json.dumps(pose))
    ok(invoke(scene, "relight", "--name", "aside", "--view", scene / "other_pose.json", "-R", RES))
    return scene


def _coverage(scene, pose_name="pose.json"):
    """(mesh coverage of the view, the used pixels) as (H, W) bool images."""
    from pipelines.geometry import camera as cam, raycast
    from pipelines.io import scene_files as sc

    camera = sc.read_camera(scene / "camera.json")
    pose = sc.read_pose(scene / pose_name)
    mesh = sc.load_mesh(scene / "mesh.obj")
    backend = raycast.make_backend(mesh)
    hit, _ = cam.pixel_samples(camera, pose, mesh, backend, None, edge_margin=-1)
    used, _ = cam.pixel_samples(camera, pose, mesh, backend, None, edge_margin=1)
    masks = []
    for s in (hit, used):
        m = np.zeros((camera.height, camera.width), bool)
        m[s.pixel[:, 0], s.pixel[:, 1]] = True
        masks.append(m)
    return masks


def _png(path):
    """(H, W, C) 8-bit codes of a PNG as stored (RGBA keeps its alpha)."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    return np.asarray(buf.get_pixels(oiio.UINT8))


@pytest.mark.parametrize("name", ["relit", "same", "dark"])
def test_no_black_ring_at_the_edge_margin(relit, name):
    cover, used = _coverage(relit)
    ring = cover & ~used  # on the mesh but left out: the edge margin
    assert ring.sum() > 500  # the sample has ~950 such pixels at --edge-margin 1
    photo = images.read_image(relit / "image.exr").pixels
    lit = photo.max(axis=-1) > 1e-3
    png = _png(relit / "out" / f"{name}.png")
    assert png.shape[2] == 3  # the photo's view: an opaque image
    black = png.max(axis=-1) == 0
    assert not np.any(black & ring & lit), f"{np.sum(black & ring & lit)} black ring pixels where the photo is not"
    assert not np.any(black & lit), "a pixel black in the PNG where the photo is not"
    rgba = read_rgba(relit / "out" / f"{name}.exr")
    np.testing.assert_array_equal(rgba[..., 3] > 0.5, cover)  # alpha: the mesh's image, margin included
    assert np.all(rgba[ring, :3].max(axis=-1) > 0)
    assert np.all(rgba[~cover] == 0)  # off the mesh: transparent, not a colour


def test_the_margin_takes_the_nearest_rendered_value_and_the_rest_is_the_photo(relit):
    from scipy import ndimage

    cover, used = _coverage(relit)
    rgba = read_rgba(relit / "out" / "relit.exr")
    _, (r, c) = ndimage.distance_transform_edt(~used, return_indices=True)
    ring = cover & ~used
    np.testing.assert_array_equal(rgba[ring, :3], rgba[r[ring], c[ring], :3])
    # off the mesh the PNG is the photo at the PNG's exposure (the photo's own preview)
    photo = images.read_image(relit / "image.exr").pixels
    stops = float(read_png_text(relit / "out" / "relit.png")["wavelight:exposure_stops"])
    assert stops == pytest.approx(outputs.photo_exposure(photo), abs=1e-5)
    expected = np.round(images.tonemap(photo, stops) * 255)
    png = _png(relit / "out" / "relit.png").astype(float)
    assert np.abs(png[~cover] - expected[~cover]).max() <= 1


def test_another_view_is_transparent_where_nothing_was_rendered(relit):
    cover, used = _coverage(relit, "other_pose.json")
    png = _png(relit / "out" / "aside.png")
    assert png.shape[2] == 4, "another view's PNG has an alpha channel"
    alpha = png[..., 3]
    assert set(np.unique(alpha)) == {0, 255}
    np.testing.assert_array_equal(alpha == 255, cover)
    assert (alpha == 0).mean() > 0.2  # the background of this view: no photo behind it
    text = read_png_text(relit / "out" / "aside.png")
    assert text["wavelight:unrendered"] == "transparent"
    # its exposure is still the photo's (the scene's photo), not the render's own
    photo = images.read_image(relit / "image.exr").pixels
    assert float(text["wavelight:exposure_stops"]) == pytest.approx(outputs.photo_exposure(photo), abs=1e-5)
    rgba = read_rgba(relit / "out" / "aside.exr")
    np.testing.assert_array_equal(rgba[..., 3] > 0.5, cover)


def test_a_darker_light_gives_a_darker_png(relit):
    out = relit / "out"
    same, dark = (images.read_image(out / f"{n}.png").pixels for n in ("same", "dark"))
    assert dark.mean() < 0.75 * same.mean()
    # one stop: half the linear radiance wherever the object is rendered and not clipped
    _, used = _coverage(relit)
    ok_px = used & (same.max(axis=-1) < 0.95) & (same.min(axis=-1) > 0.02)
    ratio = dark[ok_px].sum() / same[ok_px].sum()
    assert ratio == pytest.approx(0.5, abs=0.03)
    # relight of the photo's light draws what solve's relit.png does, with the same mapping (one
    # pixel of the sample, (97, 109), renders differently in solve and relight: see the report)
    assert read_png_text(out / "same.png") == read_png_text(out / "relit.png")
    differ = np.abs(_png(out / "same.png").astype(int) - _png(out / "relit.png")).max(axis=-1) > 1
    assert differ.sum() <= 3
    # --exposure fixes the PNG's exposure instead: the same stops for both lights
    for n in ("same_fixed", "dark_fixed"):
        text = read_png_text(out / f"{n}.png")
        assert text["wavelight:exposure"] == "--exposure" and float(text["wavelight:exposure_stops"]) == 0
    a, b = (images.read_image(out / f"{n}.png").pixels for n in ("same_fixed", "dark_fixed"))
    assert b.mean() < 0.75 * a.mean()


def test_an_exposure_change_redraws_the_png_with_the_same_backdrop(relit, tmp_path):
    scene = shutil.copytree(relit, tmp_path / "s")
    err = ok(invoke(scene, "relight", "--name", "same", "--exposure", "1"))
    assert "relight-same: " in err
    cover, _ = _coverage(scene)
    png = _png(scene / "out" / "same.png")
    photo = images.read_image(scene / "image.exr").pixels
    expected = np.round(images.tonemap(photo, 1.0) * 255)
    assert np.abs(png[~cover].astype(float) - expected[~cover]).max() <= 1
    assert float(read_png_text(scene / "out" / "same.png")["wavelight:exposure_stops"]) == 1.0


def test_render_png_has_no_ring_and_the_photos_exposure(relit, tmp_path):
    scene = shutil.copytree(relit, tmp_path / "s")
    ok(invoke(scene, "render", "-R", RES, "--light", scene / "out" / "light_latlong.exr"))
    cover, used = _coverage(scene)
    png = _png(scene / "out" / "render.png")
    photo = images.read_image(scene / "image.exr").pixels
    assert not np.any((png.max(axis=-1) == 0) & (photo.max(axis=-1) > 1e-3))
    stops = float(read_png_text(scene / "out" / "render.png")["wavelight:exposure_stops"])
    assert stops == pytest.approx(outputs.photo_exposure(photo), abs=1e-5)
    np.testing.assert_array_equal(read_rgba(scene / "out" / "render.exr")[..., 3] > 0.5, cover)
