"""Reflectance models and the material a solve fits or a user gives (DESIGN §2).

`MODELS` is the one registry of reflectance models that the CLI, the fits, compare, the report and
the tests read: a new model is its lobe in `pipelines.model.render` plus one entry here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class ModelInfo:
    name: str  # what users type: --model / --reflectance NAME
    description: str
    specular: bool  # has a specular lobe (ks, n)


MODELS: dict[str, ModelInfo] = {m.name: m for m in (
    ModelInfo("lambert", "kd / pi", False),
    ModelInfo("blinn-phong", "kd / pi + ks (n + 8) / (8 pi) max(0, N.H)^n (energy-normalised)", True),
    ModelInfo("phong", "kd / pi + ks (n + 2) / (2 pi) max(0, R.d)^n (energy-normalised)", True),
    ModelInfo("phong-classic", "the paper's unnormalised Phong: ks max(0, R.d)^n without the cosine", True),
)}
SPECULAR_MODELS = tuple(name for name, m in MODELS.items() if m.specular)


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
            raise ValueError(f"unknown reflectance model {self.model!r}; choose one of {tuple(MODELS)}")
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
