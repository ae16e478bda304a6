"""The calibrate stage: photos of a calibration target -> camera.json (with diagnostics) and one
detection overlay per photo in out/calibrate/."""

from __future__ import annotations

import glob
import re
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipelines.errors import InputError

from .cache import SceneCache, write_json_atomic
from .scenefiles import SceneFiles

CALIBRATE_VERSION = 1
PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr", ".hdr", ".pfm")
UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "in": 0.0254}
MIN_VIEWS = 3


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
        from pipelines.calibration import Target

        m = re.fullmatch(r"\s*(\d+)\s*[xX*,]\s*(\d+)\s*", self.pattern_size)
        if not m:
            raise InputError(f"--pattern-size must be COLSxROWS (e.g. 4x11), got {self.pattern_size!r}", None,
                             "give the number of dots / inner corners per row and the number of rows")
        marker = None
        if self.pattern == "charuco":
            if self.spacing is None or self.marker_size is None:
                raise InputError("a ChArUco board needs --spacing (the square's side) and --marker-size", None,
                                 "give both with units, e.g. --spacing 30mm --marker-size 22mm")
            marker = _length(self.marker_size, "--marker-size")
        try:
            return Target(self.pattern, int(m[1]), int(m[2]), self.spacing_m or 1.0, marker, self.dictionary)
        except ValueError as exc:
            raise InputError(str(exc), None, "fix --pattern / --pattern-size / --spacing / --marker-size / "
                             "--dictionary") from None

    @property
    def spacing_m(self) -> float | None:
        return None if self.spacing is None else _length(self.spacing, "--spacing")

    def check(self) -> None:
        self.target()
        if not self.outlier_factor > 1:
            raise InputError(f"--outlier-factor must be > 1, got {self.outlier_factor}", None, "use e.g. 5")


def _length(text: str, option: str) -> float:
    """'20mm', '2.5cm', '0.02m', '1in' or a bare number of millimetres -> metres."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][-+]?\d+)?)\s*(mm|cm|m|in)?\s*", str(text))
    if not m or float(m[1]) <= 0:
        raise InputError(f"{option} must be a positive length like 20mm, 2.5cm, 0.02m or 1in, got {text!r}", None,
                         f"fix {option}")
    return float(m[1]) * UNITS[m[2] or "mm"]


def find_photos(scene: SceneFiles, pattern: str | None) -> list[Path]:
    if pattern is None:
        folder = scene.root / "calib"
        if not folder.is_dir():
            raise InputError("no calibration photos: the folder does not exist", folder,
                             "put photos of the target in calib/, or pass --images 'path/*.jpg'")
        files = [p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file()]
        where = folder
    else:
        full = pattern if Path(pattern).is_absolute() else str(scene.root / pattern)
        files = [Path(p) for p in glob.glob(full) if Path(p).is_file()]
        where = Path(full)
    if not files:
        raise InputError("no calibration photos match", where,
                         f"add photos ({', '.join(PHOTO_SUFFIXES)}) or fix --images")
    return sorted(files)


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


def _overlay(grey: np.ndarray, found, projected, colour_ok: bool, text: str) -> np.ndarray:
    """Display image: the photo, detected points in OpenCV's ordered colours, the model's
    reprojection as red crosses, and a caption."""
    import cv2

    k = max(1, int(np.ceil(640 / grey.shape[1])))
    img = cv2.cvtColor(cv2.resize(grey, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST), cv2.COLOR_GRAY2BGR)
    if found is not None:
        pts = (found[0] * k + (k - 1) / 2).reshape(-1, 1, 2).astype(np.float32)
        if found[2] is None:
            cv2.drawChessboardCorners(img, found[1], pts, True)
        else:  # a ChArUco view: the corners it saw, with their ids
            cv2.aruco.drawDetectedCornersCharuco(img, pts, found[2].reshape(-1, 1).astype(np.int32), (0, 200, 0))
    if projected is not None:
        for u, v in projected * k + (k - 1) / 2:
            cv2.drawMarker(img, (int(round(u)), int(round(v))), (0, 0, 255), cv2.MARKER_CROSS, 2 * k + 4, 1)
    colour = (40, 160, 40) if colour_ok else (0, 0, 220)
    cv2.rectangle(img, (0, 0), (img.shape[1], 26), (255, 255, 255), -1)
    cv2.putText(img, text, (6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
    return img[..., ::-1].astype(np.float64) / 255.0


def calibrate_stage(scene: SceneFiles, opts: CalibrateOptions, console, force: bool = False,
                    lock_wait: float = 600.0):
    from pipelines import calibration as cal
    from pipelines import images

    opts.check()
    target = opts.target()
    photos = find_photos(scene, opts.images)
    cache = SceneCache(scene.root)
    with cache.lock(lock_wait, console.say):
        params = {**asdict(opts), "images": None, "spacing_m": opts.spacing_m}  # the photos are the inputs
        d = cache.plan("calibrate", CALIBRATE_VERSION, params, {cache.relative(p): p for p in photos}, {}, force)
        console.decision(d)
        if not d.run:
            return d
        cache.guard_user_file("calibrate", scene.camera, force)
        t0 = time.monotonic()
        greys, sizes = [], {}
        for p in photos:
            g = images.read_grey8(p)
            greys.append(g)
            sizes.setdefault((g.shape[1], g.shape[0]), []).append(p.name)
        if len(sizes) > 1:
            listing = "; ".join(f"{w}x{h}: {', '.join(n[:3])}{' ...' if len(n) > 3 else ''}"
                                for (w, h), n in sizes.items())
            raise InputError(f"the photos have different sizes ({listing})", photos[0].parent,
                             "use photos from one camera at one resolution (no crops or resizes)")
        (width, height), = sizes
        points, areas, ids, failed = [], [], [], {}
        for p, g in zip(photos, greys):
            pts, area, why, view_ids = cal.find_target(g, target)
            points.append(pts)
            areas.append(area)
            ids.append(view_ids)
            if pts is None:
                failed[p.name] = why
                console.say(f"calibrate: {p.name}: not found ({why})")
        ok = [i for i, pts in enumerate(points) if pts is not None]
        what = f"{target.cols}x{target.rows} {target.pattern}"
        if not ok:
            first = next(iter(failed.values()))
            raise InputError(f"the {what} pattern was found in none of the {len(photos)} photos (first: {first})",
                             photos[0].parent, "check --pattern and --pattern-size (dots or inner corners per row "
                             "x rows, as OpenCV counts them)")
        if len(ok) < MIN_VIEWS:
            listing = "; ".join(f"{n}: {w}" for n, w in failed.items())
            raise InputError(f"the pattern was found in only {len(ok)} of {len(photos)} photos, calibration needs "
                             f"{MIN_VIEWS} ({listing})", photos[0].parent,
                             "add photos that show the whole target sharply, at different angles")
        result = cal.calibrate([points[i] for i in ok], target, (width, height), opts.fix_k3, opts.zero_tangent,
                               opts.fix_aspect, outlier_factor=opts.outlier_factor, min_views=MIN_VIEWS,
                               dot_areas=[areas[i] for i in ok] if target.pattern in ("circles", "acircles") else None,
                               ids=[ids[i] for i in ok] if target.pattern == "charuco" else None)
        used = [ok[i] for i in result.used]
        rejected = {photos[ok[i]].name: why for i, why in result.rejected.items()}
        per_view = {photos[i].name: round(float(r), 4) for i, r in zip(used, result.per_view_rms)}
        K, dist, std = result.K, result.dist, result.std
        warnings = calibration_warnings(result, [points[i] for i in used], opts)
        camera = {
            "width": width, "height": height, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
            "cx": float(K[0, 2]), "cy": float(K[1, 2]), "dist": [float(x) for x in dist],
            "calibration": {
                "rms_px": round(result.rms, 5), "per_view_rms_px": per_view,
                "used": [photos[i].name for i in used], "rejected": rejected, "not_found": failed,
                "image_size": [width, height],
                "std": {name: float(v) for name, v in zip(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"),
                                                           std)},
                "pattern": target.pattern, "pattern_size": [target.cols, target.rows],
                **({"marker_size_m": target.marker, "dictionary": target.dictionary}
                   if target.pattern == "charuco" else {}),
                "spacing_m": opts.spacing_m, "fix_k3": opts.fix_k3, "zero_tangent": opts.zero_tangent,
                "fix_aspect": opts.fix_aspect, "outlier_factor": opts.outlier_factor,
                "dot_radius_m": (result.dot_radius if opts.spacing_m else None),
                "dot_centroid_correction_rms_px": result.dot_bias_px, "warnings": warnings,
                "note": "pixel (0,0)'s centre is at (u, v) = (0, 0); dist = k1 k2 p1 p2 k3 (OpenCV)",
            },
        }
        # overlays go to a fresh folder that replaces out/calibrate/ whole (no stale views)
        scene.out.mkdir(parents=True, exist_ok=True)
        tmp_dir = Path(tempfile.mkdtemp(prefix=".calibrate.", dir=scene.out))
        try:
            projected = dict(zip(used, result.projected))
            overlays = []
            for i, (p, g) in enumerate(zip(photos, greys)):
                if points[i] is None:
                    text, good, found = f"{p.name}: not found ({failed[p.name]})", False, None
                elif p.name in rejected:
                    text, good, found = (f"{p.name}: rejected ({rejected[p.name]})", False,
                                         (points[i], target.size, ids[i]))
                else:
                    text, good, found = (f"{p.name}: RMS {per_view[p.name]:.3f} px (red +: model)", True,
                                         (points[i], target.size, ids[i]))
                out = tmp_dir / f"{p.stem}_overlay.png"
                images.write_png(out, _overlay(g, found, projected.get(i), good, text), already_display=True)
                overlays.append(out)
            final_dir = scene.out / "calibrate"
            old = None
            if final_dir.exists():
                old = scene.out / f".calibrate.old.{time.monotonic_ns()}"
                final_dir.rename(old)
            tmp_dir.rename(final_dir)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        finally:
            if tmp_dir.exists():
                shutil.rmtree(tmp_dir, ignore_errors=True)
        write_json_atomic(scene.camera, camera)
        outputs = [scene.camera] + [final_dir / p.name for p in overlays]
        seconds = time.monotonic() - t0
        summary = {"rms_px": result.rms, "used": len(used), "photos": len(photos), "rejected": len(rejected),
                   "not_found": len(failed)}
        cache.record(d, outputs, seconds, summary)
        for name, why in rejected.items():
            console.say(f"calibrate: {name}: rejected, {why}")
        for w in warnings:
            console.say(f"calibrate: warning: {w}")
        console.result(f"calibrate: {len(used)} of {len(photos)} photos used ({len(rejected)} rejected, "
                       f"{len(failed)} without the pattern), RMS {result.rms:.3f} px in {seconds:.1f} s")
        console.result(f"calibrate: fx {K[0, 0]:.2f} +- {std[0]:.2f}, fy {K[1, 1]:.2f} +- {std[1]:.2f}, "
                       f"cx {K[0, 2]:.2f} +- {std[2]:.2f}, cy {K[1, 2]:.2f} +- {std[3]:.2f} px; "
                       f"dist {' '.join(f'{x:.4g}' for x in dist)} -> {cache.relative(scene.camera)}")
        console.say(f"calibrate: overlays in {cache.relative(final_dir)}/")
    return d
