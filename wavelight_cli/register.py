"""The register stage: correspondences.csv + camera.json -> pose.json (with diagnostics) and
out/register_overlay.png (the mesh's outline on the photo, the clicked points and their residuals)."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from pipelines.errors import InputError

from .cache import SceneCache, output_set, write_json_atomic
from .scenefiles import SceneFiles

REGISTER_VERSION = 1
RESIDUAL_SCALE = 10  # residual vectors are drawn this many times longer


@dataclass(frozen=True)
class RegisterOptions:
    method: str = "sqpnp"
    ransac: str = "auto"  # auto / on / off
    outlier_threshold: float | None = None  # px; None = 0.5 % of the image diagonal, >= 3 px
    max_rms: float | None = None  # px; None = half the outlier threshold
    max_mesh_distance: float = 0.01  # fraction of the mesh's size
    edge_refine: bool = True  # refine so the mesh's outline meets the photo's edges (when there is a photo)

    def check(self) -> None:
        for name in ("outlier_threshold", "max_rms"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise InputError(f"--{name.replace('_', '-')} must be a positive number of pixels, got {v}", None,
                                 "fix the option")
        if not 0 < self.max_mesh_distance <= 1:
            raise InputError(f"--max-mesh-distance must be in (0, 1], got {self.max_mesh_distance}", None,
                             "use e.g. 0.01 (1 % of the mesh's size)")


def _lines(indices) -> str:
    idx = list(indices)
    text = ", ".join(str(i + 2) for i in idx[:6])  # line 1 is the header
    return text + (f" (+{len(idx) - 6} more)" if len(idx) > 6 else "")


def _overlay(photo, outline, uv, residuals, inliers):
    """Display image: the photo, the mesh's outline (cyan), each clicked point (green inlier, red
    outlier) and its residual vector (projected - clicked) magnified RESIDUAL_SCALE times."""
    import cv2

    from pipelines import images

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


def register_stage(scene: SceneFiles, opts: RegisterOptions, console, force: bool = False,
                   lock_wait: float = 600.0):
    from pipelines import camera as cam
    from pipelines import images, raycast
    from pipelines import registration as reg
    from pipelines.scene import Pose, load_mesh, read_camera, read_correspondences

    from .stages import _require, load_photo

    opts.check()
    _require(scene.camera, "camera", "run wavelight calibrate, or write camera.json by hand (see README)")
    _require(scene.correspondences, "correspondences",
             "write correspondences.csv (header u,v,x,y,z: pixel column, row and the world point)")
    mesh_path = scene.mesh
    cache = SceneCache(scene.root)
    with cache.lock(lock_wait, console.say):
        inputs = {"camera.json": scene.camera, "correspondences.csv": scene.correspondences, mesh_path.name: mesh_path,
                  "photo": scene.image}
        d = cache.plan("register", REGISTER_VERSION, asdict(opts), inputs, {}, force)
        console.decision(d)
        if not d.run:
            return d
        cache.guard_user_file("register", scene.pose, force)
        t0 = time.monotonic()
        camera = read_camera(scene.camera)
        uv, xyz = read_correspondences(scene.correspondences, min_points=reg.MIN_PLANAR)
        csv_path = scene.correspondences
        outside = np.flatnonzero((uv[:, 0] < -0.5) | (uv[:, 1] < -0.5) | (uv[:, 0] > camera.width - 0.5)
                                 | (uv[:, 1] > camera.height - 0.5))
        if len(outside):
            raise InputError(f"pixels outside the {camera.width}x{camera.height} image on lines {_lines(outside)}",
                             csv_path, "u is the column and v the row, in pixels of the photo camera.json describes")
        mesh = load_mesh(mesh_path)
        distance = reg.distance_to_mesh(xyz, mesh.vertices, mesh.faces)
        tol = opts.max_mesh_distance * mesh.scale
        far = np.flatnonzero(distance > tol)
        if len(far) > len(xyz) // 2:
            raise InputError(f"most 3D points are not on the mesh (median distance {np.median(distance):.3g}, "
                             f"mesh size {mesh.scale:.3g})", csv_path,
                             "x,y,z must be in the mesh's world frame and units (z up)")
        warnings = []
        if len(far):
            warnings.append(f"3D points off the mesh surface (> {tol:.3g}) on lines {_lines(far)}")
        threshold = opts.outlier_threshold or reg.default_threshold(camera.width, camera.height)
        max_rms = opts.max_rms or 0.5 * threshold
        ransac = {"auto": None, "on": True, "off": False}[opts.ransac]
        try:
            r = reg.register(uv, xyz, camera.K, camera.dist_coeffs, opts.method, ransac, threshold)
        except InputError as exc:
            raise InputError(exc.problem, csv_path, exc.fix) from None
        errors = r.errors
        if r.rms > max_rms:
            worst = np.argsort(-errors)[:3]
            detail = ", ".join(f"line {i + 2}: {errors[i]:.1f} px" for i in worst)
            raise InputError(f"reprojection RMS {r.rms:.2f} px > {max_rms:.2f} px (worst {detail})", csv_path,
                             "check those rows (u = column, v = row), or use --ransac on / --max-rms")
        outliers = np.flatnonzero(~r.inliers)
        if len(outliers):
            warnings.append(f"{len(outliers)} outliers left out by RANSAC on lines {_lines(outliers)}")
        photo = None
        if scene.image is not None:
            photo = load_photo(scene, camera)[1].pixels
        backend = raycast.make_backend(mesh, "embree")
        R, t, res = r.R, r.t, r.residuals
        edge = None
        if opts.edge_refine and photo is not None:
            e = reg.refine_with_edges(r, uv, xyz, camera.K, camera.dist_coeffs, mesh.vertices, mesh.faces, backend,
                                      reg.photo_edges(photo), max_click_rms=max_rms)
            edge = {"accepted": e.accepted, "reason": e.reason, "outline_samples": e.outline_points,
                    "outline_on_edges_before": e.aligned_before, "outline_on_edges_after": e.aligned_after,
                    "clicks_rms_before_px": e.rms_clicks_before, "clicks_rms_after_px": e.rms_clicks_after,
                    "rotation_change_deg": e.rotation_change_deg, "translation_change": e.translation_change,
                    "clicks_only_pose": {"R": r.R.tolist(), "t": r.t.tolist()}}
            if e.accepted:
                R, t = e.R, e.t
                res = reg.reprojection(R, t, uv, xyz, camera.K, camera.dist_coeffs)
            else:
                warnings.append(f"pose not refined against the photo's edges: {e.reason}")
        errors = np.linalg.norm(res, axis=1)
        rms = float(np.sqrt(np.mean(errors[r.inliers] ** 2)))
        residuals = [{"line": i + 2, "u": float(uv[i, 0]), "v": float(uv[i, 1]), "du": float(res[i, 0]),
                      "dv": float(res[i, 1]), "error_px": float(errors[i]), "inlier": bool(r.inliers[i]),
                      "distance_to_mesh": float(distance[i])} for i in range(len(uv))]
        pose = Pose(R, t, extra={"registration": {
            "rms_px": rms, "rms_all_px": float(np.sqrt(np.mean(errors**2))), "method": r.method
            + ("+edges" if edge and edge["accepted"] else ""), "points": len(uv),
            "inliers": int(r.inliers.sum()), "planar": r.planar, "outlier_threshold_px": threshold,
            "max_rms_px": max_rms, "sigma_rotation_deg_clicks": r.sigma_rotation_deg,
            "sigma_camera_centre_clicks": r.sigma_translation, "camera_centre": (-R.T @ t).tolist(),
            "edge_refinement": edge, "warnings": warnings, "residuals": residuals,
            "note": "x_cam = R X + t (world -> camera); residual = projected - clicked, pixels; sigma_*_clicks: "
                    "1-sigma from the clicks alone (the edge refinement, when accepted, is tighter)",
        }})
        outline = cam.mesh_outline(camera, pose, mesh, backend)
        with output_set():  # the stage's files replace the old ones together, or not at all
            overlay = scene.out / "register_overlay.png"
            images.write_png(overlay, _overlay(photo, outline, uv, res, r.inliers), already_display=True)
            write_json_atomic(scene.pose, pose.to_json())
        seconds = time.monotonic() - t0
        cache.record(d, [scene.pose, overlay], seconds,
                     {"rms_px": rms, "inliers": int(r.inliers.sum()), "points": len(uv),
                      "method": pose.extra["registration"]["method"]})
        for w in warnings:
            console.say(f"register: warning: {w}")
        console.result(f"register: {r.method}, {int(r.inliers.sum())} of {len(uv)} points, RMS {r.rms:.3f} px "
                       f"(max {r.errors[r.inliers].max():.2f} px); from the clicks alone rotation +- "
                       f"{r.sigma_rotation_deg:.3f} deg, camera centre +- {r.sigma_translation:.3g}")
        if edge and edge["accepted"]:
            console.result(f"register: refined against the photo's edges: outline on edges "
                           f"{100 * edge['outline_on_edges_before']:.0f} -> {100 * edge['outline_on_edges_after']:.0f} %"
                           f" of {edge['outline_samples']} samples, clicks RMS {rms:.3f} px, pose moved "
                           f"{edge['rotation_change_deg']:.3f} deg / {100 * edge['translation_change']:.2f} % of |t|")
        console.result(f"register: -> {cache.relative(scene.pose)}")
        console.say(f"register: overlay {cache.relative(overlay)}")
    return d
