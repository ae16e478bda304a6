"""The calibrate stage: photos of a calibration target -> the camera's intrinsics and distortion,
the per-photo diagnostics, and what a careful user should know (`calibration_warnings`)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError, OptionError

UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "in": 0.0254}
MIN_VIEWS = 3


def _length(text: str, option: str) -> float:
    """'20mm', '2.5cm', '0.02m', '1in' or a bare number of millimetres -> metres."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][-+]?\d+)?)\s*(mm|cm|m|in)?\s*", str(text))
    if not m or float(m[1]) <= 0:
        raise OptionError(f"{option} must be a positive length like 20mm, 2.5cm, 0.02m or 1in, got {text!r}", None,
                         f"fix {option}")
    return float(m[1]) * UNITS[m[2] or "mm"]


@dataclass(frozen=True)
class CalibrateOptions:
    images: str | None  # glob (relative to the scene folder); None = the scene's calib/ folder
    pattern: str
    pattern_size: str  # "COLSxROWS" as OpenCV counts them
    spacing: str | None  # "20mm"; None = 1 (the intrinsics do not depend on it)
    marker_size: str | None = None  # charuco: the marker's side, "15mm"
    dictionary: str = "DICT_5X5_100"  # charuco
    fix_k3: bool = False
    zero_tangent: bool = False
    fix_aspect: bool = False
    outlier_factor: float = 5.0

    def target(self):
        from ..geometry.calibration import Target

        m = re.fullmatch(r"\s*(\d+)\s*[xX*,]\s*(\d+)\s*", self.pattern_size)
        if not m:
            raise OptionError(f"--pattern-size must be COLSxROWS (e.g. 4x11), got {self.pattern_size!r}", None,
                             "give the number of dots / inner corners per row and the number of rows")
        marker = None
        if self.pattern == "charuco":
            if self.spacing is None or self.marker_size is None:
                raise OptionError("a ChArUco board needs --spacing (the square's side) and --marker-size", None,
                                 "give both with units, e.g. --spacing 30mm --marker-size 22mm")
            marker = _length(self.marker_size, "--marker-size")
        try:
            return Target(self.pattern, int(m[1]), int(m[2]), self.spacing_m or 1.0, marker, self.dictionary)
        except ValueError as exc:
            raise OptionError(str(exc), None, "fix --pattern / --pattern-size / --spacing / --marker-size / "
                             "--dictionary") from None

    @property
    def spacing_m(self) -> float | None:
        return None if self.spacing is None else _length(self.spacing, "--spacing")

    def check(self) -> None:
        self.target()
        if not self.outlier_factor > 1:
            raise OptionError(f"--outlier-factor must be > 1, got {self.outlier_factor}", None, "use e.g. 5")


def calibration_warnings(result, points: list[np.ndarray], opts: CalibrateOptions) -> list[str]:
    """What a careful user should know about a calibration: parameters the photos do not
    determine, too few photos, image regions the target never reached."""
    import cv2

    w, h = result.image_size
    std, dist = result.std, result.dist
    out = []
    if len(points) < 8:
        out.append(f"only {len(points)} photos used: 10-20 at varied tilts give stable intrinsics")
    if std[2] > 0.01 * w or std[3] > 0.01 * h:
        out.append(f"the principal point is poorly determined (cx +- {std[2]:.1f}, cy +- {std[3]:.1f} px): "
                   "add photos with the target tilted 30-50 degrees in different directions")
    names = ("k1", "k2", "p1", "p2", "k3")
    loose = [n for n, v, s in zip(names, dist, std[4:9]) if s > 0 and s > abs(v)]
    if loose:
        hint = []
        if "k3" in loose and not opts.fix_k3:
            hint.append("--fix-k3")
        if ("p1" in loose or "p2" in loose) and not opts.zero_tangent:
            hint.append("--zero-tangent")
        out.append(f"{', '.join(loose)} not determined by these photos (uncertainty larger than the value)"
                   + (f": consider {' '.join(hint)}" if hint else ""))
    cover = np.zeros((h, w), np.uint8)
    for p in points:
        cv2.fillConvexPoly(cover, cv2.convexHull(np.round(p).astype(np.int32)), 1)
    corners = [cover[:h // 4, :w // 4], cover[:h // 4, -(w // 4):], cover[-(h // 4):, :w // 4],
               cover[-(h // 4):, -(w // 4):]]
    empty = sum(int(not c.any()) for c in corners)
    if empty:
        out.append(f"the target never reached {empty} of the image's 4 corner regions: the lens distortion there "
                   "is extrapolated; add photos with the target near the corners")
    return out


@dataclass
class CalibrationOutcome:
    camera: dict  # camera.json's content (intrinsics, distortion, `calibration` diagnostics)
    views: list  # per photo: (name, grey image, found points or None, status text, ok, projected points or None, ids)
    warnings: list = field(default_factory=list)
    rejected: dict = field(default_factory=dict)
    failed: dict = field(default_factory=dict)
    used: list = field(default_factory=list)
    result: object = None


def calibrate_target(names: list[str], greys: list[np.ndarray], opts: CalibrateOptions, folder=None,
                     progress=None) -> CalibrationOutcome:
    """Find the target in each photo (8-bit grey images of one size) and calibrate the camera."""
    from ..geometry import calibration as cal

    target = opts.target()
    sizes: dict = {}
    for name, g in zip(names, greys):
        sizes.setdefault((g.shape[1], g.shape[0]), []).append(name)
    if len(sizes) > 1:
        listing = "; ".join(f"{w}x{h}: {', '.join(n[:3])}{' ...' if len(n) > 3 else ''}" for (w, h), n in sizes.items())
        raise InputError(f"the photos have different sizes ({listing})", folder,
                         "use photos from one camera at one resolution (no crops or resizes)")
    (width, height), = sizes
    points, areas, ids, failed = [], [], [], {}
    for k, (name, g) in enumerate(zip(names, greys)):
        pts, area, why, view_ids = cal.find_target(g, target)
        points.append(pts)
        areas.append(area)
        ids.append(view_ids)
        if pts is None:
            failed[name] = why
        if progress:
            progress(k + 1, len(names))
    ok = [i for i, pts in enumerate(points) if pts is not None]
    what = f"{target.cols}x{target.rows} {target.pattern}"
    if not ok:
        first = next(iter(failed.values()))
        raise InputError(f"the {what} pattern was found in none of the {len(names)} photos (first: {first})", folder,
                         "check --pattern and --pattern-size (dots or inner corners per row x rows, as OpenCV counts "
                         "them)")
    if len(ok) < MIN_VIEWS:
        listing = "; ".join(f"{n}: {w}" for n, w in failed.items())
        raise InputError(f"the pattern was found in only {len(ok)} of {len(names)} photos, calibration needs "
                         f"{MIN_VIEWS} ({listing})", folder,
                         "add photos that show the whole target sharply, at different angles")
    result = cal.calibrate([points[i] for i in ok], target, (width, height), opts.fix_k3, opts.zero_tangent,
                           opts.fix_aspect, outlier_factor=opts.outlier_factor, min_views=MIN_VIEWS,
                           dot_areas=[areas[i] for i in ok] if target.pattern in ("circles", "acircles") else None,
                           ids=[ids[i] for i in ok] if target.pattern == "charuco" else None)
    used = [ok[i] for i in result.used]
    rejected = {names[ok[i]]: why for i, why in result.rejected.items()}
    per_view = {names[i]: round(float(r), 4) for i, r in zip(used, result.per_view_rms)}
    K, dist, std = result.K, result.dist, result.std
    warnings = calibration_warnings(result, [points[i] for i in used], opts)
    camera = {
        "width": width, "height": height, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
        "cx": float(K[0, 2]), "cy": float(K[1, 2]), "dist": [float(x) for x in dist],
        "calibration": {
            "rms_px": round(result.rms, 5), "per_view_rms_px": per_view,
            "used": [names[i] for i in used], "rejected": rejected, "not_found": failed,
            "image_size": [width, height],
            "std": {name: float(v) for name, v in zip(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"), std)},
            "pattern": target.pattern, "pattern_size": [target.cols, target.rows],
            **({"marker_size_m": target.marker, "dictionary": target.dictionary} if target.pattern == "charuco" else {}),
            "spacing_m": opts.spacing_m, "fix_k3": opts.fix_k3, "zero_tangent": opts.zero_tangent,
            "fix_aspect": opts.fix_aspect, "outlier_factor": opts.outlier_factor,
            "dot_radius_m": (result.dot_radius if opts.spacing_m else None),
            "dot_centroid_correction_rms_px": result.dot_bias_px, "warnings": warnings,
            "note": "pixel (0,0)'s centre is at (u, v) = (0, 0); dist = k1 k2 p1 p2 k3 (OpenCV)",
        },
    }
    projected = dict(zip(used, result.projected))
    views = []
    for i, (name, g) in enumerate(zip(names, greys)):
        if points[i] is None:
            views.append((name, g, None, f"{name}: not found ({failed[name]})", False, None, None))
        elif name in rejected:
            views.append((name, g, (points[i], target.size, ids[i]), f"{name}: rejected ({rejected[name]})", False,
                          None, None))
        else:
            views.append((name, g, (points[i], target.size, ids[i]), f"{name}: RMS {per_view[name]:.3f} px (red +: model)",
                          True, projected.get(i), None))
    return CalibrationOutcome(camera, views, warnings, rejected, failed, [names[i] for i in used], result)
