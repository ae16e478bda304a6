"""`wavelight calibrate`: photos of a calibration target -> camera.json (with diagnostics) and one
detection overlay per photo in out/calibrate/. The policy is in `pipelines.controllers.calibrate`."""

from __future__ import annotations

import glob
from dataclasses import asdict
from pathlib import Path

import numpy as np

from pipelines.controllers.calibrate import CalibrateOptions
from pipelines.errors import InputError

from ..cache import RECORD_FIELD, Ran, SceneCache, Stage, run_stage
from ..outputs import write_json
from ..scene import SceneFiles

VERSION = 2
PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr", ".hdr", ".pfm")


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


def calibrate_stage(scene: SceneFiles, opts: CalibrateOptions, console, force: bool = False, lock_wait: float = 600.0):
    from pipelines.controllers.calibrate import calibrate_target
    from pipelines.io import images
    from pipelines.io.files import output_set

    opts.check()
    photos = find_photos(scene, opts.images)
    cache = SceneCache(scene.root)
    params = {**asdict(opts), "images": None, "spacing_m": opts.spacing_m}  # the photos are the inputs
    stage = Stage("calibrate", VERSION, params, {cache.relative(p): p for p in photos})
    overlay_dir = scene.out / "calibrate"
    with cache.lock(lock_wait, console.say):

        def work(d) -> Ran:
            cache.guard_user_file("calibrate", scene.camera, force)
            greys = [images.read_grey8(p) for p in photos]
            task = console.task("calibrate", "finding the target", len(photos), "photos")
            c = calibrate_target([p.name for p in photos], greys, opts, photos[0].parent, task.update)
            task.close()
            for name, why in c.failed.items():
                console.say(f"calibrate: {name}: not found ({why})")
            overlays = []
            for name, g, found, text, good, projected, _ in c.views:
                overlays.append(images.write_png(overlay_dir / f"{Path(name).stem}_overlay.png",
                                                 _overlay(g, found, projected, good, text), already_display=True))
            with output_set() as files:  # overlays of photos that are gone go with the old set
                for old in overlay_dir.glob("*_overlay.png") if overlay_dir.is_dir() else []:
                    files.discard(old)
            K, std, dist = c.result.K, c.result.std, c.result.dist
            summary = {"rms_px": c.result.rms, "used": len(c.used), "photos": len(photos),
                       "rejected": len(c.rejected), "not_found": len(c.failed), "warnings": c.warnings,
                       "rejected_why": c.rejected,
                       "lines": [f"calibrate: {len(c.used)} of {len(photos)} photos used ({len(c.rejected)} rejected, "
                                 f"{len(c.failed)} without the pattern), RMS {c.result.rms:.3f} px",
                                 f"calibrate: fx {K[0, 0]:.2f} +- {std[0]:.2f}, fy {K[1, 1]:.2f} +- {std[1]:.2f}, "
                                 f"cx {K[0, 2]:.2f} +- {std[2]:.2f}, cy {K[1, 2]:.2f} +- {std[3]:.2f} px; "
                                 f"dist {' '.join(f'{x:.4g}' for x in dist)} -> {cache.relative(scene.camera)}"]}
            camera = dict(c.camera)
            camera[RECORD_FIELD] = cache.embedded_record(d, summary, camera)
            write_json(scene.camera, camera)
            return Ran([scene.camera] + overlays, summary)

        d = run_stage(cache, stage, console, force, work)
        rec = cache.record_of("calibrate") or {}
    summary = rec.get("summary", {})
    if d.run:
        for name, why in summary.get("rejected_why", {}).items():
            console.say(f"calibrate: {name}: rejected, {why}")
        for w in summary.get("warnings", []):
            console.say(f"calibrate: warning: {w}")
    for line in summary.get("lines", []):
        console.result(line)
    if d.run:
        console.say(f"calibrate: overlays in {cache.relative(overlay_dir)}/")
    return d
