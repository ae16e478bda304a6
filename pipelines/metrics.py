"""How well one image explains another: the relative errors every stage and the benchmarks report,
and the probe spheres that measure a recovered light against a true one."""

from __future__ import annotations

import numpy as np


def relative_rmse(values: np.ndarray, reference: np.ndarray, weights: np.ndarray | None = None) -> float:
    """sqrt(sum w (values - reference)^2 / sum w reference^2) over all entries (0 = perfect)."""
    v, r = np.asarray(values, np.float64), np.asarray(reference, np.float64)
    w = 1.0 if weights is None else np.asarray(weights, np.float64).reshape(-1, *([1] * (v.ndim - 1)))
    den = float((w * r**2).sum())
    return float(np.sqrt(float((w * (v - r) ** 2).sum()) / den)) if den > 0 else float("nan")


def scale_invariant_rmse(values: np.ndarray, reference: np.ndarray) -> float:
    """`relative_rmse` after the best single scale of `values` (light x albedo is only known as a
    product, so a recovered light is compared up to its overall scale)."""
    v, r = np.asarray(values, np.float64), np.asarray(reference, np.float64)
    vv = float((v * v).sum())
    s = float((v * r).sum()) / vv if vv > 0 else 0.0
    return relative_rmse(s * v, r)


def versus_photo(values: np.ndarray, photo: np.ndarray, usable: np.ndarray) -> dict:
    """Relative RMSE and bias of rendered pixel values (P, 3) against the photo's (P, 3) over the
    usable pixels (saturated ones left out)."""
    ok = np.asarray(usable, bool)
    if not ok.any():
        return {"relative_rmse_vs_photo": float("nan"), "bias_vs_photo": float("nan"), "compared_pixels": 0}
    v, r = np.asarray(values, np.float64)[ok], np.asarray(photo, np.float64)[ok]
    return {"relative_rmse_vs_photo": relative_rmse(v, r), "bias_vs_photo": float(v.mean() / max(r.mean(), 1e-30) - 1),
            "compared_pixels": int(ok.sum())}


def _probe_materials():
    from .model.materials import Material

    # a matte sphere (what a diffuse object inserted into the photo would show) and a glossy one
    # (what a specular object would reflect: the light's sharper detail)
    return {"diffuse": Material(kd=(0.8, 0.8, 0.8)),
            "glossy": Material(kd=(0.2, 0.2, 0.2), ks=(0.8, 0.8, 0.8), shininess=100.0, model="blinn-phong")}


PROBES = _probe_materials()
PROBE_PIXELS = 48  # the probe's image is PROBE_PIXELS across


def probe_geometry(view: np.ndarray, pixels: int = PROBE_PIXELS) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a unit sphere seen orthographically from unit direction `view` (toward the
    camera), one per pixel of its disc, and the view direction repeated: (P, 3) each."""
    view = np.asarray(view, np.float64) / np.linalg.norm(view)
    up = np.array([0.0, 0.0, 1.0]) if abs(view[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(up, view)
    right /= np.linalg.norm(right)
    up = np.cross(view, right)
    u = (np.arange(pixels) + 0.5) / pixels * 2 - 1
    x, y = np.meshgrid(u, -u)
    inside = x**2 + y**2 < 1
    z = np.sqrt(1 - x[inside] ** 2 - y[inside] ** 2)
    normals = x[inside, None] * right + y[inside, None] * up + z[:, None] * view
    return normals, np.broadcast_to(view, normals.shape).copy()


def probe_image(texels: np.ndarray, cube, normals: np.ndarray, views: np.ndarray, material) -> np.ndarray:
    """The probe's radiance (P, 3) under a hemisphere light: the same transport as every solver,
    with nothing in the way (a sphere does not shadow itself; the ground hides the lower half)."""
    from .model.render import transport

    V = np.ones((len(normals), cube.n_texels), np.float32)
    D, S = transport(V, normals, views, cube, material)
    L = np.asarray(texels, np.float64).reshape(cube.n_texels, -1)
    out = (D.astype(np.float64) @ L) * np.asarray(material.kd)
    if S is not None:
        out += (S.astype(np.float64) @ L) * np.asarray(material.ks)
    return out


def probe_errors(light: np.ndarray, cube, true_light: np.ndarray, true_cube, view: np.ndarray) -> dict:
    """Scale-invariant relative RMSE of each probe (`PROBES`) seen from `view`, relit by `light`
    on `cube` against the same probe under `true_light` on `true_cube` (light x albedo is only
    known as a product, so the comparison is up to one overall scale)."""
    geometry = probe_geometry(view)
    return {name: scale_invariant_rmse(probe_image(light, cube, *geometry, m),
                                       probe_image(true_light, true_cube, *geometry, m))
            for name, m in PROBES.items()}
