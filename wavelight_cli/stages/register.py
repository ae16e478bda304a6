"""`wavelight register`: correspondences.csv + camera.json (+ the photo) -> pose.json and
out/register_overlay.png (the mesh's outline on the photo, the clicked points and their residuals).
The policy is in `pipelines.controllers.register`."""

from __future__ import annotations

import numpy as np

from pipelines.controllers.register import RegisterOptions

from ..cache import Ran, SceneCache, Stage, run_stage, RECORD_FIELD
from ..outputs import write_json
from ..scene import MAIN_VIEW, SceneFiles, View, load_view_photo, photo_view, require, scene_views

VERSION = 2  # (views/NAME are registered as their own stages, register/NAME: the main photo's result is unchanged)
RESIDUAL_SCALE = 10  # residual vectors are drawn this many times longer


def _overlay(photo, outline, uv, residuals, inliers):
    """Display image: the photo, the mesh's outline (cyan), each clicked point (green inlier, red
    outlier) and its residual vector (projected - clicked) magnified RESIDUAL_SCALE times."""
    import cv2

    from pipelines.io import images

    H, W = outline.shape
    base = images.tonemap(photo) if photo is not None else np.full((H, W, 3), 0.3)
    base[outline] = (0.0, 0.9, 0.9)
    k = max(1, int(np.ceil(800 / W)))
    img = np.ascontiguousarray((np.repeat(np.repeat(base, k, 0), k, 1)[..., ::-1] * 255).astype(np.uint8))
    for (u, v), r, ok in zip(uv, residuals, inliers):
        c = np.array([u, v]) * k + (k - 1) / 2
        colour = (60, 200, 60) if ok else (40, 40, 230)
        end = c + RESIDUAL_SCALE * k * r
        cv2.circle(img, (int(round(c[0])), int(round(c[1]))), 4, colour, 1, cv2.LINE_AA)
        cv2.line(img, (int(round(c[0])), int(round(c[1]))), (int(round(end[0])), int(round(end[1]))), colour, 1,
                 cv2.LINE_AA)
    cv2.rectangle(img, (0, 0), (img.shape[1], 24), (255, 255, 255), -1)
    cv2.putText(img, f"cyan: mesh outline; circles: clicked points (red: outliers); lines: residual x{RESIDUAL_SCALE}",
                (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (40, 40, 40), 1, cv2.LINE_AA)
    return img[..., ::-1].astype(np.float64) / 255.0


def register_stage(scene: SceneFiles, opts: RegisterOptions, console, force: bool = False, lock_wait: float = 600.0,
                   view: View | None = None):
    """Register one view (default: the scene folder's photo) -> its pose.json and overlay."""
    from pipelines.controllers.register import register_scene
    from pipelines.geometry import camera as cam
    from pipelines.geometry import raycast
    from pipelines.geometry import registration as reg
    from pipelines.io import images
    from pipelines.io.scene_files import load_mesh, read_camera, read_correspondences

    opts.check()
    view = view or photo_view(scene)
    main = view.label == MAIN_VIEW
    require(view.camera, "run wavelight calibrate, or write camera.json by hand (see README)")
    require(view.correspondences, "write correspondences.csv (header u,v,x,y,z: pixel column, row and the world point)")
    mesh_path = scene.mesh
    cache = SceneCache(scene.root)
    from dataclasses import asdict

    name = "register" if main else f"register/{view.label}"
    tag = "register" if main else f"register {view.label}"
    out_dir = scene.out if main else scene.out / "views" / view.label
    stage = Stage(name, VERSION, asdict(opts), {"camera.json": view.camera,
                                               "correspondences.csv": view.correspondences,
                                               mesh_path.name: mesh_path, "photo": view.image})
    with cache.lock(lock_wait, console.say):

        def work(d) -> Ran:
            cache.guard_user_file(name, view.pose, force)
            camera = read_camera(view.camera)
            uv, xyz = read_correspondences(view.correspondences, min_points=reg.MIN_PLANAR)
            mesh = load_mesh(mesh_path)
            photo = load_view_photo(view, camera)[1].pixels if view.image is not None else None
            r = register_scene(camera, uv, xyz, mesh, photo, opts, view.correspondences)
            outline = cam.mesh_outline(camera, r.pose, mesh, raycast.make_backend(mesh, "embree"))
            overlay = images.write_png(out_dir / "register_overlay.png",
                                       _overlay(photo, outline, uv, r.residuals, r.inliers), already_display=True)
            reg_info = r.pose.extra["registration"]
            lines = r.lines if main else [line.replace("register: ", f"{tag}: ", 1) for line in r.lines]
            summary = {"rms_px": reg_info["rms_px"], "inliers": reg_info["inliers"], "points": reg_info["points"],
                       "method": reg_info["method"], "lines": lines + [f"{tag}: -> {cache.relative(view.pose)}"],
                       "warnings": r.warnings}
            data = r.pose.to_json()
            data[RECORD_FIELD] = cache.embedded_record(d, summary, data)
            write_json(view.pose, data)
            return Ran([view.pose, overlay], summary)

        d = run_stage(cache, stage, console, force, work)
        rec = cache.record_of(name) or {}
    summary = rec.get("summary", {})
    if d.run:
        for w in summary.get("warnings", []):
            console.say(f"{tag}: warning: {w}")
    for line in summary.get("lines", []):
        console.result(line)
    if d.run:
        console.say(f"{tag}: overlay {cache.relative(out_dir / 'register_overlay.png')}")
    return d


def register_views(scene: SceneFiles, opts: RegisterOptions, console, force: bool = False, lock_wait: float = 600.0,
                   select: str | None = None):
    """Register every view (of `select`, default all) that has a correspondences.csv; with none, the
    main photo's missing correspondences.csv is the error, as for a single photo."""
    views = scene_views(scene, select, need_main=False)
    todo = [v for v in views if v.correspondences is not None and v.correspondences.is_file()]
    if not todo:
        todo = [views[0]]  # (its require() names the missing file)
    return [register_stage(scene, opts, console, force, lock_wait, v) for v in todo]
