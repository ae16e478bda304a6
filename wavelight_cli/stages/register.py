"""`wavelight register`: correspondences.csv + camera.json (+ the photo) -> pose.json and
out/register_overlay.png (the mesh's outline on the photo, the clicked points and their residuals).
The policy is in `pipelines.controllers.register`."""

from __future__ import annotations

import numpy as np

from pipelines.controllers.register import RegisterOptions

from ..cache import Ran, SceneCache, Stage, run_stage, RECORD_FIELD
from ..outputs import write_json
from ..scene import SceneFiles, load_photo, require

VERSION = 2
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


def register_stage(scene: SceneFiles, opts: RegisterOptions, console, force: bool = False, lock_wait: float = 600.0):
    from pipelines.controllers.register import register_scene
    from pipelines.geometry import camera as cam
    from pipelines.geometry import raycast
    from pipelines.geometry import registration as reg
    from pipelines.io import images
    from pipelines.io.scene_files import load_mesh, read_camera, read_correspondences

    opts.check()
    require(scene.camera, "run wavelight calibrate, or write camera.json by hand (see README)")
    require(scene.correspondences, "write correspondences.csv (header u,v,x,y,z: pixel column, row and the world point)")
    mesh_path = scene.mesh
    cache = SceneCache(scene.root)
    from dataclasses import asdict

    stage = Stage("register", VERSION, asdict(opts), {"camera.json": scene.camera,
                                                    "correspondences.csv": scene.correspondences,
                                                    mesh_path.name: mesh_path, "photo": scene.image})
    with cache.lock(lock_wait, console.say):

        def work(d) -> Ran:
            cache.guard_user_file("register", scene.pose, force)
            camera = read_camera(scene.camera)
            uv, xyz = read_correspondences(scene.correspondences, min_points=reg.MIN_PLANAR)
            mesh = load_mesh(mesh_path)
            photo = load_photo(scene, camera)[1].pixels if scene.image is not None else None
            r = register_scene(camera, uv, xyz, mesh, photo, opts, scene.correspondences)
            outline = cam.mesh_outline(camera, r.pose, mesh, raycast.make_backend(mesh, "embree"))
            overlay = images.write_png(scene.out / "register_overlay.png",
                                       _overlay(photo, outline, uv, r.residuals, r.inliers), already_display=True)
            reg_info = r.pose.extra["registration"]
            summary = {"rms_px": reg_info["rms_px"], "inliers": reg_info["inliers"], "points": reg_info["points"],
                       "method": reg_info["method"], "lines": r.lines + [f"register: -> {cache.relative(scene.pose)}"],
                       "warnings": r.warnings}
            data = r.pose.to_json()
            data[RECORD_FIELD] = cache.embedded_record(d, summary, data)
            write_json(scene.pose, data)
            return Ran([scene.pose, overlay], summary)

        d = run_stage(cache, stage, console, force, work)
        rec = cache.record_of("register") or {}
    summary = rec.get("summary", {})
    if d.run:
        for w in summary.get("warnings", []):
            console.say(f"register: warning: {w}")
    for line in summary.get("lines", []):
        console.result(line)
    if d.run:
        console.say(f"register: overlay {cache.relative(scene.out / 'register_overlay.png')}")
    return d
