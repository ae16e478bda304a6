"""How well one image explains another: the relative errors every stage and the benchmarks report."""

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
