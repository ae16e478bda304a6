"""Pixels the model cannot explain, and clipped pixels as lower bounds (README: Robust fit).

After the light and the reflectance are solved, every used pixel's residual under them is compared
with what the model can be expected to miss there:

- the noise: the pixels sorted by their predicted brightness y (mean over channels) into bins of
  equal count; per bin the median of the pixels' residual (RMS over the channels) / 0.888 (the
  median of a 3-channel Gaussian's RMS in units of its sigma), made non-decreasing in y (the
  brighter, the noisier: shot noise) and interpolated at each pixel's y: sigma(y);
- the edges: the model places a shadow or a silhouette to within a pixel or two (the light's
  texels, the registration), so near an edge of the prediction a pixel may take any value the
  prediction takes within EDGE_PIXELS of it: per channel the window's range [lo, hi], widened by
  EDGE_SLACK (hi - lo) each way (a predicted edge blurrier than the photo's, from the light's
  texels, does not reach the plateaus' values within EDGE_PIXELS). A pixel whose prediction is at
  the top of that range (within EDGE_SLACK of it: a peak, or the lit side of a step) may exceed it
  by PEAK_WIDTHS widths more, and one at the bottom go below it as far (a highlight's core, or a
  shadow's, that the light's texels blur). The pixel's edge residual is its distance to that range
  (0 inside it; away from edges lo = hi = the prediction, and it is the plain residual). A
  misplaced shadow is inside the range; a dark speck on the lit side of an edge, darker than the
  shadow beside it, is not: the lit side is the top of its range and may only exceed it. (The
  range's width added to the noise in quadrature, the first rule, let such specks through: a fifth
  of the spoiled pixels of bunny_sun.)
- a pixel's standardised residual z = e_edge / sigma(y) (e_edge: the RMS over the channels of the
  edge residual) and its weight
  w = 1 for z <= t, (1 - ((z - t) / t)^2)^2 for t < z < 2t, 0 beyond (a redescending taper),
  t = max(INLIER_Z, the (1 - MAX_DOWN_SHARE) quantile of z): a photo the model explains to its
  noise loses no pixel (z > 4 has a probability ~1e-10 for Gaussian noise), and one it explains
  poorly everywhere keeps at least 95 % of its pixels at full weight (a poor fit is the model's,
  not a few outliers'; the controller's check below is the second guard);
- a clipped channel (at the format's maximum) is a lower bound: its residual is the hinge
  max(0, bound - prediction). The pixels whose prediction is below a bound are fitted to it (their
  other channels to their values), the others are left out (an active set: pinning them to their
  prediction would hold the light to values the photo does not know), and the light is solved
  again until the set settles. A bound says how bright, not where: its hinge is judged by the
  noise alone (no edge term), so a clipped highlight the model cannot reach is down-weighted like
  any pixel it cannot explain.

The controller (`controllers/solve.py`) solves the light again under these weights while they
move at least 1 % of the squared error (`--reflectance auto` chooses its model again once: after a
Lambertian first choice, once the weights settle), and keeps that solve only if its plain error
over every usable pixel rises by at most 2 % (else the down-weighted pixels were carrying the
light).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

INLIER_Z = 4.0  # rows within this many noise scales keep their full weight
MAX_DOWN_SHARE = 0.05  # at most this share of the rows is down-weighted
EDGE_PIXELS = 2  # a prediction's edges are trusted to within this many pixels
EDGE_SLACK = 0.25  # ... and the range the prediction takes there widened by this share of it each way
PEAK_WIDTHS = 1.0  # ... and by this many of its widths beyond a peak (or below a trough) of the prediction
ROWS_PER_BIN = 512  # brightness bins of the noise scale: this many rows each (at most MAX_BINS)
MAX_BINS = 16
CHI3_MEDIAN = 0.888  # median of sqrt(chi2_3 / 3): a 3-channel Gaussian's RMS over its sigma


@dataclass(frozen=True)
class NoiseModel:
    """sigma(y): the residual noise at predicted brightness y (piecewise linear, non-decreasing), and t."""

    brightness: np.ndarray  # (K,) the bins' median predicted brightness
    sigma: np.ndarray  # (K,)
    threshold: float  # t: weight 1 up to z = t, 0 from 2t

    def summary(self) -> dict:
        return {"threshold_sigmas": float(self.threshold), "edge_pixels": EDGE_PIXELS, "edge_slack": EDGE_SLACK,
                "peak_widths": PEAK_WIDTHS,
                "sigma_by_brightness": [[float(b), float(s)] for b, s in zip(self.brightness, self.sigma)]}


def brightness(prediction: np.ndarray) -> np.ndarray:
    return np.maximum(np.asarray(prediction, np.float64), 0.0).mean(axis=1)


def lower_bound_targets(values: np.ndarray, clipped: np.ndarray, prediction: np.ndarray) -> np.ndarray:
    """(n, C) what each channel is fitted to: its value, or for a clipped channel max(bound, prediction)."""
    return np.where(clipped, np.maximum(values, prediction), values)


def below_bound(values: np.ndarray, clipped: np.ndarray, prediction: np.ndarray) -> np.ndarray:
    """(n,) the pixels with a clipped channel predicted below its bound (the active lower bounds)."""
    return (np.asarray(clipped, bool) & (prediction < values)).any(axis=1)


def residual_rms(values: np.ndarray, clipped: np.ndarray, prediction: np.ndarray) -> np.ndarray:
    """(n,) each pixel's RMS residual over the channels (a clipped channel's: the hinge)."""
    r = lower_bound_targets(values, clipped, prediction) - prediction
    return np.sqrt((r * r).mean(axis=1))


def taper(z: np.ndarray, t: float) -> np.ndarray:
    """The weight of standardised residuals z: 1 up to t, a smooth taper to 0 at 2t."""
    u = np.clip((np.asarray(z, np.float64) - t) / t, 0.0, 1.0)
    return (1.0 - u * u) ** 2


def edge_span(pixels: np.ndarray, prediction: np.ndarray, radius: int = EDGE_PIXELS,
              exempt: np.ndarray | None = None) -> np.ndarray:
    """(n, C, 2) per pixel and channel the range [lo, hi] the prediction takes within `radius`
    pixels of it (the (2 radius + 1)^2 window's used pixels), widened by EDGE_SLACK (hi - lo) each
    way, and by PEAK_WIDTHS (hi - lo) more above a pixel predicted at its top (below one at its
    bottom); `pixels` (n, 2). `exempt` (n,) bool: pixels judged without an edge term (lo = hi = their
    prediction)."""
    from scipy import ndimage

    pixels = np.asarray(pixels, np.int64)
    prediction = np.asarray(prediction, np.float64)
    lo_r, lo_c = pixels.min(axis=0) - radius
    r, c = pixels[:, 0] - lo_r, pixels[:, 1] - lo_c
    shape = (int(r.max()) + radius + 1, int(c.max()) + radius + 1)
    size = 2 * radius + 1
    out = np.empty(prediction.shape + (2,), np.float64)
    hi, lo = np.full(shape, -np.inf), np.full(shape, np.inf)
    for ch in range(prediction.shape[1]):
        hi[r, c] = lo[r, c] = prediction[:, ch]
        out[:, ch, 0] = ndimage.minimum_filter(lo, size)[r, c]
        out[:, ch, 1] = ndimage.maximum_filter(hi, size)[r, c]
    width = out[..., 1] - out[..., 0]
    # a pixel at the top of its window's range may be a peak the prediction blurs (a highlight's core, a
    # sharper lobe than the light's texels give): the photo may exceed the range there by its width;
    # likewise below it at the bottom (a trough). A pixel beside a step is at one end and may not go
    # past the other: a dark speck on a shadow edge's lit side is out of range
    top = prediction >= out[..., 1] - EDGE_SLACK * width
    bottom = prediction <= out[..., 0] + EDGE_SLACK * width
    out[..., 0] -= EDGE_SLACK * width + np.where(bottom, PEAK_WIDTHS * width, 0.0)
    out[..., 1] += EDGE_SLACK * width + np.where(top, PEAK_WIDTHS * width, 0.0)
    if exempt is not None:
        out[exempt] = prediction[exempt][..., None]
    return out


def edge_residual_rms(values: np.ndarray, clipped: np.ndarray, prediction: np.ndarray,
                      span: np.ndarray) -> np.ndarray:
    """(n,) each pixel's RMS over the channels of its distance to the prediction's range near it
    (`edge_span`); a clipped channel's: the hinge below its bound (judged by the noise alone)."""
    v = np.asarray(values, np.float64)
    r = v - np.clip(v, span[..., 0], span[..., 1])
    r = np.where(clipped, np.maximum(v - np.asarray(prediction, np.float64), 0.0), r)
    return np.sqrt((r * r).mean(axis=1))


def noise_model(values: np.ndarray, clipped: np.ndarray, prediction: np.ndarray, span: np.ndarray) -> NoiseModel:
    """sigma(y) and the threshold t from pixels ((n, C) values, clipped, prediction; (n, C, 2) the
    prediction's range near each, `edge_span`)."""
    e = residual_rms(values, clipped, prediction)
    y = brightness(prediction)
    n = len(e)
    k = int(np.clip(n // ROWS_PER_BIN, 1, MAX_BINS))
    groups = np.array_split(np.argsort(y, kind="stable"), k)
    centre = np.array([np.median(y[g]) if len(g) else 0.0 for g in groups])
    sigma = np.maximum.accumulate([np.median(e[g]) / CHI3_MEDIAN if len(g) else 0.0 for g in groups])
    # a noise-free render explained exactly would have sigma 0: a floor far below any photo's noise
    sigma = np.maximum(sigma, 1e-6 * max(float(np.max(y)) if n else 0.0, 1e-30))
    model = NoiseModel(centre, sigma, INLIER_Z)
    if n:
        z = standardised(model, values, clipped, prediction, span)
        model = NoiseModel(centre, sigma, max(INLIER_Z, float(np.quantile(z, 1.0 - MAX_DOWN_SHARE))))
    return model


def standardised(model: NoiseModel, values, clipped, prediction, span) -> np.ndarray:
    """(n,) z = e_edge / sigma(y)."""
    sigma = np.interp(brightness(prediction), model.brightness, model.sigma)
    return edge_residual_rms(values, clipped, prediction, span) / sigma


def weights(model: NoiseModel, values, clipped, prediction, span) -> np.ndarray:
    """(n,) the pixels' robust weights under a noise model."""
    return taper(standardised(model, values, clipped, prediction, span), model.threshold)
