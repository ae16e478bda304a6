"""Reflectance models and the material a solve fits or a user gives (DESIGN §2).

`MODELS` is the one registry of reflectance models that the CLI, the fits, compare, the report and
the tests read: a new model is its lobe in `pipelines.model.render` plus one entry here.

`plastic` is the microfacet dielectric (`pipelines.model.microfacet`): a Fresnel-weighted GGX or
Beckmann lobe of roughness alpha over a diffuse base seen through the coating, exactly Mitsuba 3's
`roughplastic` (alpha > 0) and `plastic` (alpha = 0) with nonlinear = false. Its ks is the coating's
specular weight (1 = physical: Mitsuba's specular_reflectance), `ior` its index of refraction
relative to the outside.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class ModelInfo:
    name: str  # what users type: --model / --reflectance NAME
    description: str
    specular: bool  # has a specular lobe
    lobe: str = ""  # the lobe's width parameter the fit adjusts: "n" (shininess) or "alpha" (roughness)


MODELS: dict[str, ModelInfo] = {m.name: m for m in (
    ModelInfo("lambert", "kd / pi", False),
    ModelInfo("blinn-phong", "kd / pi + ks (n + 8) / (8 pi) max(0, N.H)^n (energy-normalised)", True, "n"),
    ModelInfo("phong", "kd / pi + ks (n + 2) / (2 pi) max(0, R.d)^n (energy-normalised)", True, "n"),
    ModelInfo("phong-classic", "the paper's unnormalised Phong: ks max(0, R.d)^n without the cosine", True, "n"),
    ModelInfo("plastic", "glossy dielectric (Mitsuba roughplastic / plastic): ks F(v.h) D(h) G / (4 N.v N.d) + "
              "kd t(N.v) t(N.d) / (pi eta^2 (1 - Fdr)); GGX or Beckmann of roughness alpha, Fresnel of the IOR",
              True, "alpha"),
)}
SPECULAR_MODELS = tuple(name for name, m in MODELS.items() if m.specular)
PLASTIC = "plastic"
DEFAULT_ROUGHNESS = 0.1  # a plastic material's alpha when none is given (Mitsuba's roughplastic default)
DEFAULT_IOR = 1.49  # a plastic material's IOR when none is given (Mitsuba's polypropylene; glaze, varnish ~1.5)


@dataclass(frozen=True)
class Material:
    """Uniform reflectance: RGB albedo kd, RGB specular ks, shininess n, model name; for `plastic` the
    roughness alpha (0: smooth), the microfacet distribution and the coating's IOR."""

    kd: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ks: tuple[float, float, float] = (0.0, 0.0, 0.0)
    shininess: float = 1.0
    model: str = "lambert"
    extra: dict = field(default_factory=dict, compare=False)
    roughness: float = DEFAULT_ROUGHNESS
    distribution: str = "ggx"
    ior: float = DEFAULT_IOR

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"unknown reflectance model {self.model!r}; choose one of {tuple(MODELS)}")
        for name in ("kd", "ks"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"{name} must be 3 non-negative numbers, got {getattr(self, name)!r}")
        if not (np.isfinite(self.shininess) and self.shininess >= 0):
            raise ValueError(f"shininess must be a non-negative number, got {self.shininess!r}")
        from .microfacet import DISTRIBUTIONS, IOR_RANGE

        if not (isinstance(self.roughness, (int, float)) and np.isfinite(self.roughness) and 0 <= self.roughness <= 4):
            raise ValueError(f"roughness (alpha) must be a number from 0 (smooth) to 4, got {self.roughness!r}")
        if self.distribution not in DISTRIBUTIONS:
            raise ValueError(f"unknown microfacet distribution {self.distribution!r}; choose one of {DISTRIBUTIONS}")
        if not (isinstance(self.ior, (int, float)) and IOR_RANGE[0] <= self.ior <= IOR_RANGE[1]):
            raise ValueError(f"ior must be a dielectric's index of refraction from {IOR_RANGE[0]} to {IOR_RANGE[1]}, "
                             f"got {self.ior!r}")
        # the fields a model does not use take their defaults, so that materials that render alike
        # compare equal (and a JSON round trip, which writes only the model's own fields, is exact)
        if self.model == PLASTIC:
            object.__setattr__(self, "shininess", 1.0)
        else:
            object.__setattr__(self, "roughness", DEFAULT_ROUGHNESS)
            object.__setattr__(self, "distribution", "ggx")
            object.__setattr__(self, "ior", DEFAULT_IOR)
        object.__setattr__(self, "roughness", float(self.roughness))
        object.__setattr__(self, "ior", float(self.ior))

    @property
    def specular(self) -> bool:
        return self.model != "lambert" and any(k > 0 for k in self.ks)

    @property
    def lobe(self) -> str:
        """The name of the lobe's width parameter ("n" or "alpha"; "" for lambert)."""
        return MODELS[self.model].lobe

    @property
    def lobe_value(self) -> float:
        """n for the Phong family, alpha for plastic."""
        return self.roughness if self.model == PLASTIC else self.shininess

    @property
    def lobe_alpha(self) -> float | None:
        """The lobe's width as a microfacet alpha (its half vectors spread ~alpha / sqrt 2 radians
        about the normal): plastic's roughness, or for the Phong family sqrt(2 / (n' + 2)) with n'
        its half-vector exponent (Blinn-Phong's n; a Phong lobe about the mirror direction ~4n);
        None without a lobe."""
        if not self.specular:
            return None
        if self.model == PLASTIC:
            return self.roughness
        n_half = self.shininess if self.model == "blinn-phong" else 4.0 * self.shininess
        return float(np.sqrt(2.0 / (n_half + 2.0)))

    def with_lobe(self, value: float) -> "Material":
        from dataclasses import replace

        return replace(self, roughness=float(value)) if self.model == PLASTIC else replace(self, shininess=float(value))

    @classmethod
    def from_json(cls, data: dict) -> "Material":
        """Accepts our own reflectance.json and the scenes' truth/material.json
        ({"type": "diffuse"|"blinnphong", "kd": .., "ks": .., "n": ..}, and Mitsuba's own
        "roughplastic" / "plastic" parameters: diffuse_reflectance, specular_reflectance, alpha,
        distribution, int_ior, ext_ior, with Mitsuba's defaults)."""
        if not isinstance(data, dict):
            raise ValueError(f"a material must be a JSON object, got {type(data).__name__}")
        kind = str(data.get("model", data.get("type", "lambert"))).lower()
        mitsuba = "model" not in data and kind in ("roughplastic", "plastic")
        model = {"diffuse": "lambert", "lambertian": "lambert", "blinnphong": "blinn-phong",
                 "blinn_phong": "blinn-phong", "roughplastic": PLASTIC, "microfacet": PLASTIC}.get(kind, kind)
        if mitsuba:
            if data.get("nonlinear"):
                raise ValueError("Mitsuba's nonlinear (rough)plastic is not modelled; use nonlinear = false")
            if "alpha_u" in data or "alpha_v" in data:
                raise ValueError("anisotropic roughness (alpha_u, alpha_v) is not modelled; give one alpha")
            data = {**data, "kd": data.get("diffuse_reflectance", data.get("kd", 0.5)),
                    "ks": data.get("specular_reflectance", data.get("ks", 1.0))}

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
        if model != PLASTIC:
            return cls(kd=rgb("kd", 1.0), ks=rgb("ks", 0.0), shininess=n, model=model)

        def number(names, default):
            for name in names:
                v = data.get(name)
                if v is not None:
                    if isinstance(v, bool) or not isinstance(v, (int, float)):
                        raise ValueError(f"{name} must be a number, got {v!r}")
                    try:
                        return float(v)
                    except OverflowError:
                        raise ValueError(f"{name} must be a finite number, got a huge integer") from None
            return default

        if mitsuba:  # Mitsuba's defaults: roughplastic alpha 0.1 beckmann; polypropylene in air
            alpha = 0.0 if kind == "plastic" else number(("alpha",), 0.1)
            distribution = str(data.get("distribution", "beckmann")).lower()
            ior = number(("int_ior",), 1.49) / number(("ext_ior",), 1.000277)
        else:
            alpha = number(("alpha", "roughness"), DEFAULT_ROUGHNESS)
            distribution = str(data.get("distribution", "ggx")).lower()
            ior = number(("ior",), DEFAULT_IOR)
        return cls(kd=rgb("kd", 1.0), ks=rgb("ks", 1.0), shininess=n, model=model, roughness=alpha,
                   distribution=distribution, ior=ior)

    def to_json(self) -> dict:
        if self.model == PLASTIC:
            return {"model": self.model, "kd": list(self.kd), "ks": list(self.ks), "alpha": self.roughness,
                    "distribution": self.distribution, "ior": self.ior, **self.extra}
        return {"model": self.model, "kd": list(self.kd), "ks": list(self.ks), "n": self.shininess,
                **self.extra}
