"""The register stage: 2D-3D correspondences (+ the camera, the mesh and the photo) -> the mesh's pose.

Policy: refuse clicks outside the image or mostly off the mesh, find outliers by RANSAC when a
residual exceeds the outlier threshold, refuse an inlier RMS above `max_rms`, then refine the
pose against the photo's edges and keep it only if the outline fits the edges better and the
clicks stay within `max_rms`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError, OptionError


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
                raise OptionError(f"--{name.replace('_', '-')} must be a positive number of pixels, got {v}", None,
                                 "fix the option")
        if not 0 < self.max_mesh_distance <= 1:
            raise OptionError(f"--max-mesh-distance must be in (0, 1], got {self.max_mesh_distance}", None,
                             "use e.g. 0.01 (1 % of the mesh's size)")


def _lines(indices) -> str:
    idx = list(indices)
    text = ", ".join(str(i + 2) for i in idx[:6])  # line 1 is the header
    return text + (f" (+{len(idx) - 6} more)" if len(idx) > 6 else "")


@dataclass
class RegisterResult:
    pose: object  # geometry.camera.Pose with its `registration` diagnostics
    residuals: np.ndarray  # (n, 2) projected - clicked, pixels
    inliers: np.ndarray
    warnings: list = field(default_factory=list)
    lines: list = field(default_factory=list)  # the result lines to print


def register_scene(camera, uv: np.ndarray, xyz: np.ndarray, mesh, photo: np.ndarray | None, options: RegisterOptions,
                   csv_path=None) -> RegisterResult:
    """The pose of `mesh` from clicked points (uv pixels, xyz world) and, if given, the photo's edges."""
    from ..geometry import raycast
    from ..geometry import registration as reg
    from ..geometry.camera import Pose

    options.check()
    outside = np.flatnonzero((uv[:, 0] < -0.5) | (uv[:, 1] < -0.5) | (uv[:, 0] > camera.width - 0.5)
                             | (uv[:, 1] > camera.height - 0.5))
    if len(outside):
        raise InputError(f"pixels outside the {camera.width}x{camera.height} image on lines {_lines(outside)}",
                         csv_path, "u is the column and v the row, in pixels of the photo camera.json describes")
    distance = reg.distance_to_mesh(xyz, mesh.vertices, mesh.faces)
    tol = options.max_mesh_distance * mesh.scale
    far = np.flatnonzero(distance > tol)
    if len(far) > len(xyz) // 2:
        raise InputError(f"most 3D points are not on the mesh (median distance {np.median(distance):.3g}, "
                         f"mesh size {mesh.scale:.3g})", csv_path,
                         "x,y,z must be in the mesh's world frame and units (z up)")
    warnings = []
    if len(far):
        warnings.append(f"3D points off the mesh surface (> {tol:.3g}) on lines {_lines(far)}")
    threshold = options.outlier_threshold or reg.default_threshold(camera.width, camera.height)
    max_rms = options.max_rms or 0.5 * threshold
    ransac = {"auto": None, "on": True, "off": False}[options.ransac]
    try:
        r = reg.register(uv, xyz, camera.K, camera.dist_coeffs, options.method, ransac, threshold)
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
    backend = raycast.make_backend(mesh, "embree")
    R, t, res = r.R, r.t, r.residuals
    edge = None
    if options.edge_refine and photo is not None:
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
    lines = [f"register: {r.method}, {int(r.inliers.sum())} of {len(uv)} points, RMS {r.rms:.3f} px "
             f"(max {r.errors[r.inliers].max():.2f} px); from the clicks alone rotation +- "
             f"{r.sigma_rotation_deg:.3f} deg, camera centre +- {r.sigma_translation:.3g}"]
    if edge and edge["accepted"]:
        lines.append(f"register: refined against the photo's edges: outline on edges "
                     f"{100 * edge['outline_on_edges_before']:.0f} -> {100 * edge['outline_on_edges_after']:.0f} %"
                     f" of {edge['outline_samples']} samples, clicks RMS {rms:.3f} px, pose moved "
                     f"{edge['rotation_change_deg']:.3f} deg / {100 * edge['translation_change']:.2f} % of |t|")
    return RegisterResult(pose, res, r.inliers, warnings, lines)
