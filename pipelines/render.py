"""The one forward model (DESIGN §2): every solver and every render goes through `transport`.

    I_j = sum_i L_i w_i V_ij max(0, N_j . d_i) f_j(d_i, v_j)

with L_i the radiance of light texel i, w_i its exact solid angle, V_ij its visibility, N_j the
shading normal, v_j the direction to the camera and f the BRDF:
    lambert       f = kd / pi
    blinn-phong   f = kd / pi + ks (n + 8) / (8 pi) max(0, N . H)^n,  H = normalize(d + v)
    phong         f = kd / pi + ks (n + 2) / (2 pi) max(0, R . d)^n,  R = reflect(v, N)
    phong-classic f = kd / pi + ks max(0, R . d)^n / max(N . d, eps)  (the paper's unnormalised
                  term: its radiance contribution is ks (R.d)^n L w, without the cosine)
kd and ks are RGB; the transport splits into a diffuse part D (kd = 1) and a specular part S
(ks = 1) so that channel c renders kd_c D L_c + ks_c S L_c.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .cubemap import CubeMap
from .visibility import VisibilityData, facing

SPECULAR_MODELS = ("blinn-phong", "phong", "phong-classic")
MODELS = ("lambert",) + SPECULAR_MODELS


@dataclass(frozen=True)
class Material:
    """Uniform reflectance: RGB albedo kd, RGB specular ks, shininess n, model name."""

    kd: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ks: tuple[float, float, float] = (0.0, 0.0, 0.0)
    shininess: float = 1.0
    model: str = "lambert"
    extra: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"unknown reflectance model {self.model!r}; choose one of {MODELS}")
        for name in ("kd", "ks"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"{name} must be 3 non-negative numbers, got {getattr(self, name)!r}")
        if not (np.isfinite(self.shininess) and self.shininess >= 0):
            raise ValueError(f"shininess must be a non-negative number, got {self.shininess!r}")

    @property
    def specular(self) -> bool:
        return self.model != "lambert" and any(k > 0 for k in self.ks)

    @classmethod
    def from_json(cls, data: dict) -> "Material":
        """Accepts our own reflectance.json and the scenes' truth/material.json
        ({"type": "diffuse"|"blinnphong", "kd": .., "ks": .., "n": ..})."""
        kind = str(data.get("model", data.get("type", "lambert"))).lower()
        model = {"diffuse": "lambert", "lambertian": "lambert", "blinnphong": "blinn-phong",
                 "blinn_phong": "blinn-phong"}.get(kind, kind)

        if not isinstance(data, dict):
            raise ValueError(f"a material must be a JSON object, got {type(data).__name__}")

        def rgb(name, default):
            v = data.get(name)
            v = default if v is None else v
            try:
                return tuple(float(x) for x in (np.broadcast_to(np.asarray(v, float), (3,))))
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a number or 3 numbers, got {v!r}") from None

        n = data.get("n", data.get("shininess", 1.0))
        if isinstance(n, bool) or not isinstance(n, (int, float)):
            raise ValueError(f"n (shininess) must be a number, got {n!r}")
        return cls(kd=rgb("kd", 1.0), ks=rgb("ks", 0.0), shininess=float(n), model=model)

    def to_json(self) -> dict:
        return {"model": self.model, "kd": list(self.kd), "ks": list(self.ks), "n": self.shininess,
                **self.extra}


def specular_lobe(normals: np.ndarray, views: np.ndarray, directions: np.ndarray, cosines: np.ndarray,
                  shininess: float, model: str) -> np.ndarray:
    """(P, N) specular BRDF values (ks = 1) times nothing else; zero where cosines == 0."""
    n = np.float32(shininess)
    if model == "blinn-phong":
        # N.H without forming H: |v + d|^2 = 2 + 2 v.d
        vd = views.astype(np.float32) @ directions.astype(np.float32).T
        nv = np.einsum("pk,pk->p", normals, views).astype(np.float32)[:, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            c = (nv + normals.astype(np.float32) @ directions.astype(np.float32).T) / np.sqrt(
                np.maximum(2.0 + 2.0 * vd, 1e-12))
        norm = (n + 8) / (8 * np.pi)
    else:
        r = 2.0 * np.einsum("pk,pk->p", normals, views)[:, None] * normals - views  # mirror of v
        c = r.astype(np.float32) @ directions.astype(np.float32).T
        norm = (n + 2) / (2 * np.pi) if model == "phong" else 1.0
    lobe = np.power(np.maximum(c, 0.0), n) * np.float32(norm)
    if model == "phong-classic":
        lobe = lobe / np.maximum(cosines, 1e-6)
    return np.where(cosines > 0, lobe, 0.0).astype(np.float32)


def transport(V: np.ndarray, normals: np.ndarray, views: np.ndarray, cube: CubeMap,
              material: Material) -> tuple[np.ndarray, np.ndarray | None]:
    """Transport blocks for a set of pixels: the light texels' contributions per unit radiance.

    The radiance of a texel is constant over it (that is what a texel value means), so its
    diffuse contribution is V x the integral over the texel of max(0, N.d) / pi. That integral is
    N . m_i with m_i the texel's vector solid angle (`CubeMap.vector_solid_angles`), exact for
    texels wholly above the shading horizon and clamped at 0 for the few that straddle it: as
    cheap as a texel-centre rule and exact where the centre rule is off by O(1/R^2). The specular
    lobe is evaluated at the texel centre (w_i max(0, N.d_i) f(d_i)). Visibility is per texel (V
    may be a supersampled fraction).

    Parameters
    ----------
    V : (P, N) float32 visibility in [0, 1].
    normals, views : (P, 3) shading normals and unit directions to the camera.
    cube : the texel layout.

    Returns
    -------
    D : (P, N) float32 diffuse transport for kd = 1;
    S : (P, N) float32 specular transport for ks = 1, or None for a Lambertian material.
    """
    D = facing(normals, cube.vector_solid_angles)
    D *= V * np.float32(1.0 / np.pi)
    if not material.specular:
        return D, None
    cos = facing(normals, cube.directions)
    S = V * cos * cube.solid_angles.astype(np.float32)[None, :]
    S *= specular_lobe(normals, views, cube.directions, cos, material.shininess, material.model)
    return D, S


def render(vis: VisibilityData, light: np.ndarray, material: Material, rows: int = 2048) -> np.ndarray:
    """Radiance of every used pixel under `light` ((N,) or (N, 3) texel radiances) -> (P, 3)."""
    L = np.asarray(light, dtype=np.float64)
    if L.ndim == 1:
        L = np.repeat(L[:, None], 3, axis=1)
    if L.shape != (vis.cube.n_texels, 3):
        raise ValueError(f"light must have shape ({vis.cube.n_texels}, 3), got {np.shape(light)}")
    kd = np.asarray(material.kd)
    ks = np.asarray(material.ks)
    out = np.zeros((vis.n_pixels, 3))
    Lf = L.astype(np.float32)
    s = vis.samples
    for sl, V in vis.blocks(rows):
        D, S = transport(V, s.normal[sl], s.view[sl], vis.cube, material)
        out[sl] = kd * (D @ Lf)
        if S is not None:
            out[sl] += ks * (S @ Lf)
    return out


def pixels_to_image(values: np.ndarray, pixels: np.ndarray, height: int, width: int,
                    background: float | np.ndarray = 0.0) -> np.ndarray:
    """Scatter per-pixel values ((P,) or (P, C)) into an (H, W[, C]) image."""
    values = np.asarray(values)
    img = np.empty((height, width) + values.shape[1:], dtype=np.float32)
    img[...] = background
    img[pixels[:, 0], pixels[:, 1]] = values
    return img
