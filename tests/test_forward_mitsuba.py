"""Our forward model against an independent renderer (Mitsuba 3) on the reference scenes.

Each scene is rendered by our model (cube-map light from the true lat-long light, ray-cast
visibility, the true material) at its used pixels (mask.png ∩ `pixel_samples`, edge margin 1) and
compared with Mitsuba's noise-free render truth/image_clean.exr (MC noise 0.3-0.7 % of the mean).
The error that remains is the cube map's quantisation of the light: at the MC noise level for an
overcast sky, larger for a sun (in the truth light one 1.4 deg lat-long pixel holding ~2/3 of the
power; at R = 32 it goes to texels 2.8 deg wide and casts its shadows from their centres), which
moves and hardens shadow edges and shifts the sun's cosine and, on a glossy object, highlights.
"""

import numpy as np
import pytest

from conftest import MITSUBA_SCENES


@pytest.mark.parametrize("name, resolution, limit", [
    ("spot_overcast", 32, 0.02),
    ("bunny_sun", 32, 0.04),
])
def test_relative_rmse(forward_render, name, resolution, limit):
    """Today: spot_overcast 0.35 % (MC noise 0.28 %), bunny_sun 3.1 % (sun quantisation)."""
    result = forward_render(name, resolution)
    assert result.relative_rmse() < limit


@pytest.mark.slow
def test_bunny_sun_converges_with_resolution(forward_render):
    """At R = 64 the sun lands closer to its true direction and the error drops below 2.5 %
    (today 2.0 %; R = 128 on every 8th pixel: 1.3 %).

    To keep the cost near that of R = 32 (4x the texels), this evaluates every 2nd used pixel
    (a deterministic subset: `samples[::2]`, ~24k pixels x ~6k shadow rays).
    """
    assert forward_render("bunny_sun", 64, step=2).relative_rmse() < 0.025


def test_overcast_brightness_is_unbiased(forward_render):
    """Units: solid angles, the 1/pi of the Lambertian BRDF and the light's scale all agree with
    Mitsuba's, so the mean brightness matches to better than 1 % under a diffuse sky."""
    assert forward_render("spot_overcast", 32).brightness_ratio() == pytest.approx(1.0, abs=0.01)


@pytest.mark.slow  # ~30 s: the glossy teapot at R = 32
def test_teapot_sun_phong_error_is_the_known_sun_quantisation(forward_render):
    """Glossy teapot (Blinn-Phong, n = 30) under a sun at 10.5 deg elevation: 9.6 % at R = 32.

    Not a model bug: the error is the sun's discretisation and falls with R (R = 16, 32, 64: 14 %,
    9.6 %, 4.9 %; R = 128 on every 8th pixel: 2.5 %). At R = 32 the sun's lat-long pixel lands in texels whose centres
    are 1.4 deg away (11.9 deg elevation instead of 10.55: +13 % cosine on the plane) and its
    1.4 deg disc becomes a 2.8 deg texel with one shadow ray, which moves and hardens shadow
    edges on the object. With the sun's own directions (and the sky on the cube) the same pixels
    are at 2.5 %. The bound guards this deterministic number with a 10 % margin.
    """
    assert forward_render("teapot_sun_phong", 32).relative_rmse() < 0.105


def test_blinn_phong_matches_mitsuba(forward_render):
    """Mitsuba's object pixels = a x (our diffuse part) + b x (our specular part) with a, b ~ 1:
    the (n + 8) / (8 pi) normalisation, the half vector and kd / pi agree with Mitsuba's
    Blinn-Phong plugin (truth/material.json). Today a = 0.996, b = 0.969 at R = 32 (b -> 0.995
    with the exact sun directions); a wrong lobe or normalisation moves b by tens of percent.
    """
    from pipelines.model import materials as render

    result = forward_render("teapot_sun_phong", 32)
    material = result.scene.material
    diffuse = np.asarray(material.kd) * result.render(render.Material(kd=(1.0, 1.0, 1.0)))
    specular = result.rendered - diffuse
    obj = result.on_object
    design = np.column_stack([diffuse[obj].ravel(), specular[obj].ravel()])
    (a, b), *_ = np.linalg.lstsq(design, result.reference[obj].ravel(), rcond=None)
    assert a == pytest.approx(1.0, abs=0.03)
    assert b == pytest.approx(1.0, abs=0.06)


@pytest.mark.parametrize("name", MITSUBA_SCENES)
def test_used_pixels_cover_the_mask(mitsuba_scene, name):
    """Nearly every mask pixel is used: the camera, pose and mesh put the geometry where Mitsuba
    saw it (only the one-pixel margin at silhouettes and depth jumps is dropped)."""
    diagnostics = mitsuba_scene(name).diagnostics
    assert diagnostics["used"] > 0.9 * diagnostics["mask"]
