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
        if not isinstance(data, dict):
            raise ValueError(f"a material must be a JSON object, got {type(data).__name__}")
        kind = str(data.get("model", data.get("type", "lambert"))).lower()
        model = {"diffuse": "lambert", "lambertian": "lambert", "blinnphong": "blinn-phong",
                 "blinn_phong": "blinn-phong"}.get(kind, kind)

        def rgb(name, default):
            v = data.get(name)
            v = default if v is None else v
            try:
                return tuple(float(x) for x in (np.broadcast_to(np.asarray(v, float), (3,))))
            except (TypeError, ValueError, OverflowError):
                raise ValueError(f"{name} must be a number or 3 numbers, got {v!r}") from None

        n = data.get("n", data.get("shininess", 1.0))
        if isinstance(n, bool) or not isinstance(n, (int, float)):
            raise ValueError(f"n (shininess) must be a number, got {n!r}")
        try:
            n = float(n)
        except OverflowError:
            raise ValueError("n (shininess) must be a finite number, got a huge integer") from None
        return cls(kd=rgb("kd", 1.0), ks=rgb("ks", 0.0), shininess=n, model=model)

    def to_json(self) -> dict:
        return {"model": self.model, "kd": list(self.kd), "ks": list(self.ks), "n": self.shininess,
                **self.extra}


def lobe_cosines(normals: np.ndarray, views: np.ndarray, directions: np.ndarray, model: str) -> np.ndarray:
    """(P, N) float32 cosine the specular lobe raises to the power n: N.H (blinn-phong) or R.d
    (phong, phong-classic; R the mirror of the view direction). Not clipped: may be negative."""
    if model == "blinn-phong":
        # N.H without forming H: |v + d|^2 = 2 + 2 v.d
        vd = views.astype(np.float32) @ directions.astype(np.float32).T
        nv = np.einsum("pk,pk->p", normals, views).astype(np.float32)[:, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            return (nv + normals.astype(np.float32) @ directions.astype(np.float32).T) / np.sqrt(
                np.maximum(2.0 + 2.0 * vd, 1e-12))
    if model in ("phong", "phong-classic"):
        r = 2.0 * np.einsum("pk,pk->p", normals, views)[:, None] * normals - views  # mirror of v
        return r.astype(np.float32) @ directions.astype(np.float32).T
    raise ValueError(f"no specular lobe for model {model!r}")


def lobe_norm(shininess: float, model: str) -> tuple[float, float]:
    """The lobe's normalisation factor and its derivative with respect to n."""
    if model == "blinn-phong":
        return (shininess + 8) / (8 * np.pi), 1 / (8 * np.pi)
    if model == "phong":
        return (shininess + 2) / (2 * np.pi), 1 / (2 * np.pi)
    return 1.0, 0.0


def specular_factors(V: np.ndarray, normals: np.ndarray, views: np.ndarray, cube: CubeMap, model: str,
                     texels: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
    """The parts of the specular transport that do not depend on n, for some texels.

    S_ij = A_ij * lobe_norm(n) * c_ij^n, with A = V w max(0, N.d) (phong-classic: V w, the
    paper's term has no cosine) and c = max(0, lobe_cosines); A is 0 wherever c or N.d is 0.

    Returns (A, c): two (P, K) float32 arrays, K = the selected texels.
    """
    dirs = cube.directions[texels]
    cos = facing(normals, dirs)
    c = np.maximum(lobe_cosines(normals, views, dirs, model), 0.0)
    c = np.nan_to_num(c, nan=0.0)
    w = cube.solid_angles[texels].astype(np.float32)[None, :]
    A = V * ((cos > 0) * w if model == "phong-classic" else cos * w)
    A[c <= 0] = 0.0
    return A.astype(np.float32, copy=False), c


def transport(V: np.ndarray, normals: np.ndarray, views: np.ndarray, cube: CubeMap,
              material: Material) -> tuple[np.ndarray, np.ndarray | None]:
    """Transport blocks for a set of pixels: the light texels' contributions per unit radiance.

    The radiance of a texel is constant over it (that is what a texel value means), so its
    diffuse contribution is V x the integral over the texel of max(0, N.d) / pi. That integral is
    N . m_i with m_i the texel's vector solid angle (`CubeMap.vector_solid_angles`), exact for
    texels wholly above the shading horizon and clamped at 0 for the few that straddle it: as
    cheap as a texel-centre rule and exact where the centre rule is off by O(1/R^2). The specular
    lobe is evaluated at the texel centre (w_i max(0, N.d_i) f(d_i), `specular_factors`). Visibility is per texel (V
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
    S, c = specular_factors(V, normals, views, cube, material.model)
    norm, _ = lobe_norm(material.shininess, material.model)
    S *= np.power(c, np.float32(material.shininess)) * np.float32(norm)
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
