"""Rendering a view under a light with the one forward model (`model.render`), for the stages that
render (render, relight): where the visibility was inferred (adaptive), the directions that carry
much of this light are cast exactly for every pixel first (`controllers.solve.bright_texels`)."""

from __future__ import annotations

import numpy as np


def render_view(vis, light: np.ndarray, material, backend=None, albedo=None) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) radiance of every used pixel under a texel light, and the texels cast again; `albedo`:
    a function (samples -> (P, 3) relative albedo: parts, textures, `model.parts.view_albedo`) or None."""
    from ..geometry.visibility import VisibilityData, recast_columns
    from ..model.render import render
    from .solve import bright_texels

    recast = np.zeros(0, np.int64)
    if vis.method == "adaptive" and backend is not None:
        recast = bright_texels(light, vis.cube)
        if len(recast):
            stored = recast_columns(backend, vis.samples, vis.cube, np.asarray(vis.stored), recast, vis.supersample)
            vis = VisibilityData(vis.samples, vis.cube, vis.supersample, stored, vis.method, vis.castable_only)
    return render(vis, light, material, albedo=None if albedo is None else albedo(vis.samples),
                  specular=_specular(albedo, vis.samples)), recast


def _specular(shading, samples):
    """The parts' specular weights of some pixel samples (`parts.ViewShading`), None: all glossy."""
    spec = getattr(shading, "specular", None)
    return None if spec is None else spec(samples)
