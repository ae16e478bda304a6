"""Tests for image I/O, linearisation, saturation and tone mapping in pipelines.images."""

import numpy as np
import pytest

from pipelines.errors import InputError
from pipelines.io.images import (linear_to_srgb, read_grey8, read_image, read_latlong, srgb_to_linear, tonemap, write_exr,
                                 write_png)


def write_raw(path, array, fmt_name):
    """Write `array` (H, W, C) with OpenImageIO in the given pixel format (test fixture)."""
    import OpenImageIO as oiio

    fmt = {"uint8": oiio.UINT8, "uint16": oiio.UINT16, "float": oiio.FLOAT, "half": oiio.HALF}[fmt_name]
    arr = np.ascontiguousarray(array)
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], fmt)
    spec.attribute("oiio:UnassociatedAlpha", 1)  # store colour as given (no un-premultiplying on write)
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(str(path), spec)
    assert out.write_image(arr)
    out.close()
    return path


def read_raw(path):
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    return buf.spec(), np.asarray(buf.get_pixels(buf.spec().format))


def srgb_reference(code, maxval):
    c = code / maxval
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


# -- EXR -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(5, 7, 3), (16, 32, 3), (3, 4)])
@pytest.mark.parametrize("seed", [0, 1])
def test_exr_round_trip_is_float32_exact(tmp_path, shape, seed):
    rng = np.random.default_rng(seed)
    img = (rng.random(shape) * 10.0 ** rng.uniform(-6, 4, size=shape)).astype(np.float32)
    img.flat[0] = 0.0
    img.flat[-1] = 65504.0 * 100  # beyond half range: must stay float32
    path = write_exr(tmp_path / "sub" / "light.exr", img)
    assert path.is_file() and path.parent.name == "sub"
    loaded = read_image(path)
    assert loaded.pixels.dtype == np.float32
    assert loaded.bit_depth == "float" and loaded.linear_source
    expected = img if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2)
    np.testing.assert_array_equal(loaded.pixels, expected)
    assert not loaded.saturated.any()
    assert (loaded.height, loaded.width) == shape[:2]
    # no temp files left behind by the atomic write
    assert sorted(p.name for p in path.parent.iterdir()) == ["light.exr"]


def test_exr_linear_flag_is_ignored(tmp_path):
    img = np.full((2, 2, 3), 0.5, np.float32)
    path = write_exr(tmp_path / "a.exr", img)
    np.testing.assert_array_equal(read_image(path, linear=False).pixels, img)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_exr_pixels_raise_naming_the_file(tmp_path, bad):
    img = np.ones((4, 6, 3), np.float32)
    img[1, 2, 0] = bad
    img[3, 5, 2] = bad
    path = write_raw(tmp_path / "photo_bad.exr", img, "float")
    with pytest.raises(InputError) as info:
        read_image(path)
    assert "photo_bad.exr" in str(info.value)
    assert info.value.path == path
    assert "2 pixels" in str(info.value)


def _mask_png(path, keep):
    write_raw(path, np.repeat(keep[..., None], 3, axis=2).astype(np.uint8) * 255, "uint8")
    return path


def test_nonfinite_pixels_the_mask_leaves_out_read_as_zero(tmp_path):
    img = np.full((4, 6, 3), 0.5, np.float32)
    img[1, 2, 0], img[3, 5] = np.nan, np.inf
    keep = np.ones((4, 6), bool)
    keep[1, 2] = keep[3, 5] = False
    loaded = read_image(write_raw(tmp_path / "photo.exr", img, "float"), mask=_mask_png(tmp_path / "mask.png", keep))
    assert np.all(loaded.pixels[~keep] == 0.0)
    np.testing.assert_array_equal(loaded.pixels[keep], img[keep])


def test_nonfinite_pixels_inside_the_mask_raise_naming_the_photo_and_the_mask(tmp_path):
    img = np.full((4, 6, 3), 0.5, np.float32)
    img[1, 2, 0], img[3, 5] = np.nan, np.inf
    keep = np.ones((4, 6), bool)
    keep[1, 2] = False  # the NaN is left out, the Inf is not
    path = write_raw(tmp_path / "photo.exr", img, "float")
    with pytest.raises(InputError) as info:
        read_image(path, mask=_mask_png(tmp_path / "mask.png", keep))
    assert info.value.path == path
    assert "1 pixels inside mask.png are NaN or infinite (the first at row 3, column 5)" in str(info.value)
    assert "paint them black in mask.png" in str(info.value)


def test_nonfinite_pixels_and_a_mask_of_another_size_raise_naming_the_mask(tmp_path):
    img = np.full((4, 6, 3), 0.5, np.float32)
    img[0, 0] = np.nan
    mask = _mask_png(tmp_path / "mask.png", np.ones((4, 5), bool))
    with pytest.raises(InputError) as info:
        read_image(write_raw(tmp_path / "photo.exr", img, "float"), mask=mask)
    assert info.value.path == mask and "mask is 5x4, the photo photo.exr is 6x4" in str(info.value)


@pytest.mark.parametrize("written, named, says", [
    ("jpg", "photo.exr", "holds JPEG data, not EXR as its name (.exr) says. Rename it to photo.jpg, or convert it to EXR"),
    ("png", "photo.exr", "holds PNG data, not EXR as its name (.exr) says. Rename it to photo.png, or convert it to EXR"),
    ("png", "photo.hdr", "holds PNG data, not HDR as its name (.hdr) says. Rename it to photo.png"),
    ("exr", "photo.png", "holds EXR data, not PNG as its name (.png) says. Rename it to photo.exr"),
    ("png", "photo.jpg", "holds PNG data, not JPEG as its name (.jpg) says. Rename it to photo.png"),
])
def test_content_of_another_format_than_the_name_is_refused(tmp_path, written, named, says):
    """A JPEG renamed .exr would be read as 8-bit sRGB where the name promises linear radiance:
    OpenImageIO says which format it read, and a disagreement with the name is one clear error."""
    import shutil

    fmt = "float" if written == "exr" else "uint8"
    src = write_raw(tmp_path / f"src.{written}", np.full((4, 6, 3), 0.5 if fmt == "float" else 128,
                                                       np.float32 if fmt == "float" else np.uint8), fmt)
    path = tmp_path / named
    shutil.copy(src, path)
    for read in (read_image, read_grey8):
        with pytest.raises(InputError) as info:
            read(path)
        assert info.value.path == path and says in str(info.value), str(info.value)


@pytest.mark.parametrize("name", ["a.jpeg", "a.jpg", "a.JPG", "a.tif", "a.tiff", "a.pfm", "a.hdr", "a.bmp"])
def test_content_that_matches_its_name_is_read(tmp_path, name):
    fmt = "float" if name.endswith(("pfm", "hdr")) else "uint8"
    img = np.full((4, 6, 3), 0.5 if fmt == "float" else 128, np.float32 if fmt == "float" else np.uint8)
    assert read_image(write_raw(tmp_path / name, img, fmt)).pixels.shape == (4, 6, 3)


def test_small_negative_exr_values_are_clipped_to_zero(tmp_path):
    img = np.full((2, 3, 3), 0.25, np.float32)
    img[0, 0] = -1e-3
    loaded = read_image(write_exr(tmp_path / "n.exr", img))
    assert loaded.pixels.min() == 0.0
    assert loaded.pixels[1, 1, 1] == np.float32(0.25)


# -- integer formats -----------------------------------------------------------------------------
@pytest.mark.parametrize("code,expected", [(128, 0.2158605), (0, 0.0), (255, 1.0), (10, 0.0030353)])
def test_png8_is_srgb_decoded(tmp_path, code, expected):
    img = np.full((3, 4, 3), code, np.uint8)
    loaded = read_image(write_raw(tmp_path / "p.png", img, "uint8"))
    assert loaded.bit_depth == "8" and not loaded.linear_source
    assert loaded.pixels.dtype == np.float32 and loaded.pixels.shape == (3, 4, 3)
    np.testing.assert_allclose(loaded.pixels, expected, atol=2e-6)
    np.testing.assert_allclose(loaded.pixels, srgb_reference(code, 255), atol=1e-6)


@pytest.mark.parametrize("code", [0, 1, 128, 200, 254])
def test_png8_linear_flag_keeps_values_linear(tmp_path, code):
    img = np.full((2, 2, 3), code, np.uint8)
    loaded = read_image(write_raw(tmp_path / "p.png", img, "uint8"), linear=True)
    assert loaded.linear_source
    np.testing.assert_allclose(loaded.pixels, code / 255.0, atol=1e-7)


def test_png16_is_srgb_decoded(tmp_path):
    img = np.array([[[32768, 0, 65535], [1000, 20000, 40000]]], np.uint16)
    loaded = read_image(write_raw(tmp_path / "p16.png", img, "uint16"))
    assert loaded.bit_depth == "16"
    expected = np.vectorize(lambda c: srgb_reference(c, 65535))(img.astype(float))
    np.testing.assert_allclose(loaded.pixels, expected, atol=1e-6)


@pytest.mark.parametrize("fmt,maxval", [("uint8", 255), ("uint16", 65535)])
def test_saturated_pixels_at_format_maximum(tmp_path, fmt, maxval):
    dtype = np.uint8 if fmt == "uint8" else np.uint16
    img = np.full((3, 4, 3), maxval // 2, dtype)
    img[0, 0] = maxval  # all channels clipped
    img[1, 2, 1] = maxval  # one channel clipped
    img[2, 3] = maxval - 1  # just below: not clipped
    loaded = read_image(write_raw(tmp_path / "s.png", img, fmt))
    expected = np.zeros((3, 4), bool)
    expected[0, 0] = expected[1, 2] = True
    np.testing.assert_array_equal(loaded.saturated, expected)
    assert loaded.pixels[0, 0, 0] == 1.0


def test_grey_png_becomes_three_equal_channels(tmp_path):
    img = np.array([[[0], [128]], [[255], [64]]], np.uint8)
    loaded = read_image(write_raw(tmp_path / "g.png", img, "uint8"))
    assert loaded.pixels.shape == (2, 2, 3)
    np.testing.assert_array_equal(loaded.pixels[..., 0], loaded.pixels[..., 2])
    np.testing.assert_allclose(loaded.pixels[0, 1], 0.2158605, atol=2e-6)
    np.testing.assert_array_equal(loaded.saturated, [[False, False], [True, False]])


def test_rgba_png_drops_alpha_and_keeps_colour(tmp_path):
    """Alpha is dropped: the colour is what the file stores, whatever the alpha."""
    img = np.array([[[128, 64, 255, 255], [128, 64, 255, 0]],
                    [[128, 64, 255, 100], [255, 255, 255, 254]]], np.uint8)
    loaded = read_image(write_raw(tmp_path / "rgba.png", img, "uint8"))
    assert loaded.pixels.shape == (2, 2, 3)
    expected = np.vectorize(lambda c: srgb_reference(c, 255))(img[..., :3].astype(float))
    np.testing.assert_allclose(loaded.pixels, expected, atol=2e-6)
    np.testing.assert_array_equal(loaded.saturated, [[True, True], [True, True]])


def test_grey_alpha_png_drops_alpha_and_keeps_grey(tmp_path):
    img = np.array([[[128, 0], [255, 10]]], np.uint8)
    loaded = read_image(write_raw(tmp_path / "ga.png", img, "uint8"))
    assert loaded.pixels.shape == (1, 2, 3)
    np.testing.assert_allclose(loaded.pixels[0, :, 0], [0.2158605, 1.0], atol=2e-6)


def test_rgb_exr_with_alpha_drops_alpha(tmp_path):
    img = np.array([[[0.5, 2.0, 8.0, 1.0], [0.25, 0.125, 4.0, 1.0]]], np.float32)
    loaded = read_image(write_raw(tmp_path / "a.exr", img, "float"))
    np.testing.assert_array_equal(loaded.pixels, img[..., :3])


# -- bad files -----------------------------------------------------------------------------------
def test_missing_file_raises_naming_it(tmp_path):
    path = tmp_path / "nowhere.exr"
    with pytest.raises(InputError) as info:
        read_image(path)
    assert "nowhere.exr" in str(info.value) and "not found" in str(info.value)


@pytest.mark.parametrize("suffix", ["png", "exr", "jpg", "tif"])
def test_garbage_file_raises_naming_it(tmp_path, suffix):
    path = tmp_path / f"garbage.{suffix}"
    path.write_bytes(np.random.default_rng(7).bytes(4000))
    with pytest.raises(InputError) as info:
        read_image(path)
    assert f"garbage.{suffix}" in str(info.value)


@pytest.mark.parametrize("suffix,fmt", [("png", "uint8"), ("exr", "float"), ("tif", "uint8"),
                                        ("jpg", "uint8")])
@pytest.mark.parametrize("fraction", [0.3, 0.9])
def test_truncated_file_raises_naming_it(tmp_path, suffix, fmt, fraction):
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (96, 128, 3)).astype(np.uint8 if fmt == "uint8" else np.float32)
    full = write_raw(tmp_path / f"full.{suffix}", img, fmt)
    data = full.read_bytes()
    path = tmp_path / f"cut.{suffix}"
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(InputError) as info:
        read_image(path)
    assert f"cut.{suffix}" in str(info.value)


def test_empty_file_raises(tmp_path):
    path = tmp_path / "empty.png"
    path.write_bytes(b"")
    with pytest.raises(InputError, match="empty.png"):
        read_image(path)


# -- lat-long ------------------------------------------------------------------------------------
def test_read_latlong_accepts_2_to_1(tmp_path):
    img = np.random.default_rng(0).random((8, 16, 3)).astype(np.float32) * 50
    light = read_latlong(write_exr(tmp_path / "l.exr", img))
    assert light.dtype == np.float64 and light.shape == (8, 16, 3)
    np.testing.assert_array_equal(light, img.astype(np.float64))


@pytest.mark.parametrize("h,w", [(8, 8), (8, 15), (8, 17), (16, 8)])
def test_read_latlong_rejects_non_2_to_1(tmp_path, h, w):
    path = write_exr(tmp_path / "bad_light.exr", np.ones((h, w, 3), np.float32))
    with pytest.raises(InputError) as info:
        read_latlong(path)
    assert "bad_light.exr" in str(info.value)
    assert f"{w}x{h}" in str(info.value)


# -- tone mapping and PNG output -----------------------------------------------------------------
def test_srgb_curves_are_inverse():
    v = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(v)), v, atol=1e-12)
    assert abs(srgb_to_linear(0.5) - 0.21404114) < 1e-7
    assert linear_to_srgb(-1.0) == 0.0


def test_write_png_with_fixed_exposure_encodes_srgb_uint8(tmp_path):
    img = np.array([[[0.0, 0.2158605, 1.0], [4.0, 0.0031308, 0.5]]], np.float32)
    path = write_png(tmp_path / "out" / "preview.png", img, exposure=0.0)
    spec, px = read_raw(path)
    assert px.dtype == np.uint8 and str(spec.format) == "uint8"
    assert px.shape == (1, 2, 3)
    np.testing.assert_array_equal(px[0, 0], [0, 128, 255])
    assert px[0, 1, 0] == 255  # above 1 is clipped
    assert px[0, 1, 1] == round(255 * 12.92 * 0.0031308)
    assert px[0, 1, 2] == round(255 * (1.055 * 0.5 ** (1 / 2.4) - 0.055))
    # exposure +1 doubles the linear value
    _, px2 = read_raw(write_png(tmp_path / "p2.png", np.full((1, 1, 3), 0.2158605 / 2), exposure=1.0))
    assert px2[0, 0, 0] == 128


def test_write_png_auto_exposure_maps_percentile_to_white(tmp_path):
    rng = np.random.default_rng(5)
    img = rng.random((40, 50, 3)) * 1000.0
    img[0, 0] = np.nan  # ignored by the tone mapper
    disp = tonemap(img, percentile=50.0)
    assert disp.min() >= 0.0 and disp.max() <= 1.0
    assert abs(np.mean(disp >= 1.0) - 0.5) < 0.01
    _, px = read_raw(write_png(tmp_path / "auto.png", img))
    assert px.dtype == np.uint8 and px.max() == 255 and px[0, 0, 0] == 0


def test_write_png_already_display(tmp_path):
    img = np.array([[[0.0, 0.5, 1.0]]])
    _, px = read_raw(write_png(tmp_path / "d.png", img, already_display=True))
    np.testing.assert_array_equal(px[0, 0], [0, 128, 255])


@pytest.mark.parametrize("layout", ["grey", "rgba-opaque", "alpha-only", "grey-alpha"])
def test_a_mask_with_an_alpha_channel_is_read_by_its_colour_and_its_alpha(tmp_path, layout):
    """An RGBA mask.png (as image editors export them) was read as all used: its opaque alpha counted
    as a channel above half (bad-input sweep). Now the colour says white = used and the alpha, when
    there is one, transparent = not used."""
    import cv2

    from pipelines.io.images import read_mask

    rng = np.random.default_rng(3)
    want = rng.random((12, 20)) < 0.5
    m = np.where(want, 255, 0).astype(np.uint8)
    full = np.full_like(m, 255)
    img = {"grey": m, "rgba-opaque": np.dstack([m, m, m, full]), "alpha-only": np.dstack([full, full, full, m]),
           "grey-alpha": np.dstack([m, full])}[layout]
    if layout == "grey-alpha":  # (cv2 writes no 2-channel PNG: OpenImageIO does)
        import OpenImageIO as oiio

        spec = oiio.ImageSpec(20, 12, 2, oiio.UINT8)
        spec.channelnames, spec.alpha_channel = ("Y", "A"), 1
        out = oiio.ImageOutput.create(str(tmp_path / "mask.png"))
        out.open(str(tmp_path / "mask.png"), spec)
        out.write_image(img)
        out.close()
    else:
        cv2.imwrite(str(tmp_path / "mask.png"), img)
    assert np.array_equal(read_mask(tmp_path / "mask.png"), want)
