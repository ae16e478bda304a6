"""`plastic` through the CLI on the sample scene (R = 8): `render --model plastic --alpha ...`, a
material JSON file (ours and Mitsuba's names), `solve --reflectance plastic` writing the fitted
plastic to reflectance.json, and `relight` reading it back."""

from __future__ import annotations

import json

import numpy as np

from cli_helpers import RES, invoke, ok
from pipelines.io import images


def _render(scene, name, *material):
    ok(invoke(scene, "render", "--resolution", RES, "--light", str(scene / "truth" / "env_latlong.exr"), *material))
    return np.array(images.read_image(scene / "out" / "render.exr").pixels)


def test_render_with_plastic_options_and_files(scene):
    glossy = _render(scene, "glossy", "--model", "plastic", "--kd", "0.5", "0.5", "0.5", "--alpha", "0.1")
    rough = _render(scene, "rough", "--model", "plastic", "--kd", "0.5", "0.5", "0.5", "--alpha", "0.5",
                    "--distribution", "beckmann", "--ior", "1.6")
    assert np.isfinite(glossy).all() and glossy.max() > 0
    assert np.abs(glossy - rough).max() > 1e-3  # alpha, distribution and IOR reach the render
    (scene / "mine.json").write_text(json.dumps({"model": "plastic", "kd": 0.5, "alpha": 0.1}))
    (scene / "mitsuba.json").write_text(json.dumps({"type": "roughplastic", "diffuse_reflectance": 0.5,
                                                    "alpha": 0.1, "distribution": "ggx", "int_ior": 1.49,
                                                    "ext_ior": 1.0}))
    mine = _render(scene, "mine", "--material", str(scene / "mine.json"))
    mitsuba = _render(scene, "mitsuba", "--material", str(scene / "mitsuba.json"))
    np.testing.assert_allclose(mine, glossy, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(mitsuba, glossy, rtol=1e-6, atol=1e-7)


def test_solve_fits_plastic_and_relight_uses_it(scene):
    ok(invoke(scene, "solve", "--resolution", RES, "--reflectance", "plastic", "--max-rounds", "2"))
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    assert refl["model"] == "plastic" and refl["mode"] == "plastic"
    assert 0.005 <= refl["alpha"] <= 1.0 and refl["distribution"] == "ggx" and refl["ior"] == 1.49
    assert "alpha" in refl["uncertainty"]
    ok(invoke(scene, "relight", "--name", "again"))
    assert (scene / "out" / "again.exr").is_file()
