"""The normal equations give the same residuals as rendering, for fit and held-out pixels."""

import numpy as np
import pytest

from pipelines.light.cubemap import CubeMap
from pipelines.light.system import build_normal_equations, holdout_mask
from pipelines.model.materials import Material
from pipelines.model.render import render
from test_render import make_samples, make_vis, unit


@pytest.mark.parametrize("material", [
    Material(),
    Material(kd=(0.9, 0.6, 0.3)),
    Material(kd=(0.5, 0.5, 0.5), ks=(0.4, 0.2, 0.4), shininess=20.0, model="blinn-phong"),  # per-channel G
])
def test_residual_from_gram_equals_rendered_residual(material):
    rng = np.random.default_rng(0)
    cube = CubeMap(8)
    normals = unit(rng.normal(size=(300, 3)) + [0, 0, 1.0])
    vis = make_vis(make_samples(normals), cube, rng.random((300, cube.n_texels)) < 0.7)
    light = rng.random((cube.n_texels, 3))
    photo = render(vis, rng.random((cube.n_texels, 3)), material) + 0.01 * rng.normal(size=(300, 3))
    held = holdout_mask(vis.samples.pixel, 0.2)
    ne = build_normal_equations(vis, photo, material, held_out=held, rows=64)
    assert ne.fit.n_pixels + ne.held_out.n_pixels == 300 and 20 < ne.held_out.n_pixels < 100
    I = render(vis, light, material)
    for part, sel in ((ne.fit, ~held), (ne.held_out, held)):
        direct = np.sum((I[sel] - photo[sel]) ** 2, axis=0)
        np.testing.assert_allclose(part.residual(light), direct, rtol=1e-4)


def test_holdout_is_deterministic_and_scattered():
    rows, cols = np.meshgrid(np.arange(100), np.arange(120), indexing="ij")
    pix = np.column_stack([rows.ravel(), cols.ravel()])
    a, b = holdout_mask(pix, 0.1), holdout_mask(pix, 0.1)
    assert np.array_equal(a, b) and 0.08 < a.mean() < 0.12
    # every 10x10 block gets some held-out pixels (no large holes in the fit)
    assert a.reshape(10, 10, 12, 10).any(axis=(1, 3)).all()
