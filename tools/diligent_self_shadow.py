"""False self-shadowing with a long lens: measure it, and try a fix by monkeypatching (pipelines/ unchanged).

Usage:
    .venv/bin/python tools/diligent_self_shadow.py study [--resolution 8] [--out build/analysis/self_shadow.json]
    .venv/bin/python tools/diligent_self_shadow.py scene SCENE        # all-shadowed pixels of a solved scene
    .venv/bin/python tools/diligent_self_shadow.py patched-cli -s SCENE solve ...   # wavelight with the fix

What goes wrong today (pipelines/geometry/camera.py, pipelines/geometry/raycast.py):
  `pixel_samples` takes Embree's float32 hit distance t (float32 ray: origin rounded in the recentred
  frame, direction rounded) and computes position = o + t d with the float64 ray. From a camera D away,
  Embree's float32 intersection gives t with an error ~eps32 x D (eps32 = 2^-23 ~ 1.2e-7), which moves
  the point off its facet by that x cos(view, normal); the float32/float64 ray mismatch adds little
  (the float32 ray at Embree's t is off its facet by the same RMS, see `study`). The shadow
  rays start RAY_OFFSET = 1e-5 x scene size above it. For a ball of radius r (scene size 2 sqrt 3 r)
  the error beats the offset once D is more than a few hundred r: a point under its own facet sees the
  facet's back from inside toward every direction in front of it, so all its texels are shadowed.

The fix tried here:
  1. hit points in float64 from the hit triangle: intersect the float64 pixel ray with the plane of
     the face Embree reports (float64 vertices, recentred frame), then take the float64 barycentrics of
     that point, clamp them into the triangle and rebuild the point from them: the point lies on its
     triangle to float64 rounding, whatever the camera distance; Embree's t only chose the face.
  2. a shadow-ray offset from float32's precision where the ray starts: the origin is rounded to
     float32 in the recentred frame and Embree intersects in float32 relative to it, so both errors are
     ~eps32 x the coordinates' magnitude there (the point's and its triangle's):
        offset = K x eps32 x (max|p_local| + longest edge of the hit triangle), K = 32,
     computed and added in float64 before the rounding. It scales with the scene (any scale) and is
     independent of the camera distance. (Today's 1e-5 x scene size is ~290 x eps32 x max|p_local| on
     a ball: it was too small for the camera-distance error, not for float32 itself.)
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))

EPS32 = float(np.finfo(np.float32).eps)  # 2^-23
OFFSET_ULPS = 32.0


# --- the fix ---------------------------------------------------------------------------------------

def refine_hits(mesh, backend, origins, directions, faces):
    """(n, 3) float64 world points on the hit triangles: the float64 ray meets the face's plane, and the
    point's barycentrics are clamped into the triangle. Works in the backend's recentred frame."""
    c = backend.centre
    tri = mesh.vertices[mesh.faces[faces]] - c  # (n, 3, 3) float64, recentred
    o = np.asarray(origins, np.float64) - c
    d = np.asarray(directions, np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    denom = np.einsum("ij,ij->i", n, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.einsum("ij,ij->i", n, tri[:, 0] - o) / denom
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    # barycentrics of p in its triangle (least squares in the plane), clamped into it
    q = p - tri[:, 0]
    d00, d01, d11 = (np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e1, e2), np.einsum("ij,ij->i", e2, e2))
    d20, d21 = np.einsum("ij,ij->i", q, e1), np.einsum("ij,ij->i", q, e2)
    det = d00 * d11 - d01 * d01
    w1 = (d11 * d20 - d01 * d21) / det
    w2 = (d00 * d21 - d01 * d20) / det
    w = np.column_stack([1.0 - w1 - w2, w1, w2])
    outside = (w < 0).any(axis=1) | ~np.isfinite(t)
    if outside.any():  # grazing rays or the float64 ray just past the edge: nearest point of the triangle
        wc = np.clip(w[outside], 0.0, None)
        wc /= wc.sum(axis=1, keepdims=True)
        w[outside] = wc
    p = np.einsum("ik,ikj->ij", w, tri)
    return p + c


def robust_offsets(mesh, backend, positions, faces, ulps: float = OFFSET_ULPS):
    """(n,) float64 shadow-ray offsets: ulps x eps32 x (max|p_local| + the hit triangle's longest edge)."""
    local = np.asarray(positions, np.float64) - backend.centre
    tri = mesh.vertices[mesh.faces[faces]]
    edge = np.max(np.stack([np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1), np.linalg.norm(tri[:, 2] - tri[:, 1], axis=1),
                            np.linalg.norm(tri[:, 0] - tri[:, 2], axis=1)]), axis=0)
    return ulps * EPS32 * (np.abs(local).max(axis=1) + edge)


_ORIGINAL = {}


def install(ulps: float = OFFSET_ULPS):
    """Monkeypatch pipelines.camera.pixel_samples (refined hit points) and
    pipelines.visibility.visibility_rows (float64 origins, robust offsets)."""
    from pipelines.geometry import camera as cam
    from pipelines.geometry import visibility as vis

    if _ORIGINAL:
        return
    _ORIGINAL["pixel_samples"] = cam.pixel_samples
    _ORIGINAL["visibility_rows"] = vis.visibility_rows

    def pixel_samples(camera, pose, mesh, backend, mask=None, edge_margin=1, mask_path=None):
        samples, diag = _ORIGINAL["pixel_samples"](camera, pose, mesh, backend, mask, edge_margin, mask_path)
        o, d = cam.pixel_rays(camera, pose, samples.pixel[:, 0], samples.pixel[:, 1])
        position = refine_hits(mesh, backend, o, d, samples.face)
        return cam.PixelSamples(samples.pixel, position, samples.normal, samples.geometric_normal,
                                samples.view, samples.face), diag

    def visibility_rows(backend, samples, rows, cube, supersample=1):
        # same as today's, with the origins built in float64 from a per-pixel offset
        pos = samples.position[rows]
        geo = samples.geometric_normal[rows]
        offset = robust_offsets(backend.mesh, backend, pos, samples.face[rows], ulps)
        origins64 = pos - backend.centre + offset[:, None] * geo
        shim = _OffsetShim(backend, origins64)
        return _ORIGINAL["visibility_rows"](shim, samples, rows, cube, supersample)

    cam.pixel_samples = pixel_samples
    vis.visibility_rows = visibility_rows


class _OffsetShim:
    """A backend view whose `to_local` returns the prepared float32 origins and whose offset is 0, so
    that the unchanged visibility_rows adds nothing to them."""

    def __init__(self, backend, origins64):
        self._b = backend
        self._origins = origins64.astype(np.float32)
        self.offset = 0.0
        self.threads = backend.threads

    def to_local(self, points):
        return self._origins

    def occluded_local(self, *a, **k):
        return self._b.occluded_local(*a, **k)


def uninstall():
    from pipelines.geometry import camera as cam
    from pipelines.geometry import visibility as vis

    if _ORIGINAL:
        cam.pixel_samples = _ORIGINAL.pop("pixel_samples")
        vis.visibility_rows = _ORIGINAL.pop("visibility_rows")


# --- measuring ---------------------------------------------------------------------------------------

def plane_distance(mesh, positions, faces):
    """Signed distance of points from their hit facet's plane (float64; > 0 = outside)."""
    v0 = mesh.vertices[mesh.faces[faces, 0]]
    return np.einsum("ij,ij->i", positions - v0, mesh.face_normals[faces])


def shadow_counts(samples, backend, cube):
    """(pixels with V = 0 toward every texel, pixels with any castable texel shadowed, falsely
    occluded castable rays / castable rays). The ball is convex: no castable ray may be occluded."""
    from pipelines.geometry import visibility as vis

    data = vis.compute_visibility(backend, samples, cube)
    V = data.dense() > 0
    cast = vis.castable(samples.normal, samples.geometric_normal, cube.directions)
    blocked = cast & ~V
    return int(np.count_nonzero(V.sum(axis=1) == 0)), int(np.count_nonzero(blocked.any(axis=1))), \
        float(blocked.sum() / cast.sum())


def study_case(ratio: float, scale: float, resolution: int, workdir: Path, scan=()) -> dict:
    """Ball of radius ~scale seen from ratio x radius, image as the photos (rho ~ 70.9 px)."""
    import photometric as ph
    from pipelines.light import cubemap
    from pipelines.geometry import raycast
    from pipelines.io import scene_files as sc

    mask = ph.read_mask()
    rho = ph.fit_circle(ph.outline_points(mask)).radius
    focal = rho * np.sqrt(ratio**2 - 1.0)
    view = ph.ball_view(mask, focal_px=focal, distance=ratio * scale)
    scene, _, _ = ph.build_ball_scene(workdir / f"k{ratio:g}_s{scale:g}", 0, focal_px=focal, distance=ratio * scale,
                                      view=view)
    camera, pose = sc.read_camera(scene / "camera.json"), sc.read_pose(scene / "pose.json")
    mesh = sc.load_mesh(scene / "mesh.ply")
    backend = raycast.make_backend(mesh)
    cube = cubemap.CubeMap(resolution)
    from pipelines.geometry import camera as cam
    from pipelines.io import images

    m = images.read_mask(scene / "mask.png")
    row = {"distance_over_radius": ratio, "scale": scale, "radius": view.radius, "focal_px": focal,
           "scene_size": mesh.scale, "offset_today": backend.offset}
    samples, diag = cam.pixel_samples(camera, pose, mesh, backend, m, 1)
    row["used_pixels"] = len(samples)
    err = plane_distance(mesh, samples.position, samples.face)
    sph = np.linalg.norm(samples.position - view.centre, axis=1) - view.radius
    row.update({"plane_err_rms": float(np.sqrt(np.mean(err**2))), "plane_err_max": float(np.abs(err).max()),
                "sphere_err_rms": float(np.sqrt(np.mean(sph**2))),
                "below_offset_today": int(np.count_nonzero(err < -backend.offset)),
                "err_over_offset_p99": float(np.percentile(np.abs(err), 99) / backend.offset)})
    # Embree's own share: the float32 ray it traced, evaluated at its t in float64
    o, d = cam.pixel_rays(camera, pose, samples.pixel[:, 0], samples.pixel[:, 1])
    o32, d32 = backend.to_local(o).astype(np.float64), d.astype(np.float32).astype(np.float64)
    t, face, _, _ = backend.intersect(o, d)
    p32 = backend.centre + o32 + t[:, None] * d32
    same = face == samples.face
    e32 = plane_distance(mesh, p32[same], face[same])
    row.update({"embree_ray_err_rms": float(np.sqrt(np.mean(e32**2))), "embree_ray_err_max": float(np.abs(e32).max()),
                "t_ulp": float(np.spacing(np.float32(np.median(t))))})
    t0 = time.monotonic()
    row["all_shadowed_today"], row["any_shadowed_today"], row["false_ray_share_today"] = \
        shadow_counts(samples, backend, cube)
    row["vis_seconds_today"] = time.monotonic() - t0
    install()
    try:
        from pipelines.geometry import camera as cam2

        fixed, _ = cam2.pixel_samples(camera, pose, mesh, backend, m, 1)
        ferr = plane_distance(mesh, fixed.position, fixed.face)
        offs = robust_offsets(mesh, backend, fixed.position, fixed.face)
        row.update({"plane_err_max_fixed": float(np.abs(ferr).max()), "offset_fixed_median": float(np.median(offs)),
                    "moved_vs_today_max": float(np.linalg.norm(fixed.position - samples.position, axis=1).max())})
        row["all_shadowed_fixed"], row["any_shadowed_fixed"], row["false_ray_share_fixed"] = \
            shadow_counts(fixed, backend, cube)
    finally:
        uninstall()
    for k in scan:  # the fix's hit points with smaller offsets: how much margin K = 32 leaves
        install(k)
        try:
            row[f"any_shadowed_fixed_K{k:g}"] = shadow_counts(fixed, backend, cube)[1]
        finally:
            uninstall()
    return row


def study(resolution: int, out: Path, ratios, scales, scan=()):
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for ratio in ratios:
            for scale in scales:
                r = study_case(ratio, scale, resolution, Path(tmp), scan)
                rows.append(r)
                print(f"D/r {ratio:>6g}  scale {scale:>6g}: radius {r['radius']:.3g}, offset {r['offset_today']:.2g}; "
                      f"hit error to facet plane rms {r['plane_err_rms']:.2g} max {r['plane_err_max']:.2g} "
                      f"(p99/offset {r['err_over_offset_p99']:.2f}), below -offset {r['below_offset_today']}; "
                      f"all-shadowed {r['all_shadowed_today']} / {r['used_pixels']}, false rays "
                      f"{100 * r['false_ray_share_today']:.2f} % | fixed: err max {r['plane_err_max_fixed']:.2g}, "
                      f"offset {r['offset_fixed_median']:.2g}, all-shadowed {r['all_shadowed_fixed']}, any "
                      f"{r['any_shadowed_fixed']}, false rays {100 * r['false_ray_share_fixed']:.3f} %; Embree's own "
                      f"ray error rms {r['embree_ray_err_rms']:.2g}"
                      + "".join(f", K={k:g}: {r[f'any_shadowed_fixed_K{k:g}']}" for k in scan), flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=2) + "\n")
    return rows


def scene_report(scene: Path):
    """All-shadowed pixels of a scene's cached visibility, and where they are (radius from the ball's
    centre in px)."""
    import photometric as ph
    from pipelines.geometry import visibility as vis
    from pipelines.io import visibility_file

    data = visibility_file.read_visibility(scene / ".wavelight" / "visibility.h5")
    s = data.samples
    V = data.dense() > 0
    cast = vis.castable(s.normal, s.geometric_normal, data.cube.directions)
    zero = V.sum(axis=1) == 0
    c = ph.ball_view().circle
    rad = np.hypot(s.pixel[:, 1] - c.u, s.pixel[:, 0] - c.v)
    print(f"{scene}: {int(zero.sum())} of {len(s)} used pixels shadowed toward every texel "
          f"(castable texels per pixel: min {cast.sum(1).min()}, median {np.median(cast.sum(1)):.0f}); "
          f"falsely occluded castable rays {100 * (cast & ~V).sum() / cast.sum():.2f} %")
    edges = np.arange(0, 80, 10)
    hz, _ = np.histogram(rad[zero], edges)
    ha, _ = np.histogram(rad, edges)
    for a, z, n in zip(edges[:-1], hz, ha):
        print(f"  {a:2.0f}-{a + 10:2.0f} px from the centre: {z:5d} / {n:5d} ({100 * z / max(n, 1):.0f} %)")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "patched-cli":
        install()
        from wavelight_cli.main import cli

        sys.argv = ["wavelight", *argv[1:]]
        cli(prog_name="wavelight")
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("study")
    s.add_argument("--resolution", type=int, default=8)
    s.add_argument("--out", type=Path, default=REPO / "build" / "analysis" / "self_shadow.json")
    s.add_argument("--ratios", type=float, nargs="*", default=[10, 100, 1000, 10000])
    s.add_argument("--scales", type=float, nargs="*", default=[1e-3, 1e-2, 1e-1, 1, 1e1, 1e2, 1e3])
    s.add_argument("--scan", type=float, nargs="*", default=[],
                   help="also count shadowed pixels of the fixed hit points with these offset multipliers K")
    c = sub.add_parser("scene")
    c.add_argument("scene", type=Path)
    a = ap.parse_args(argv)
    if a.cmd == "study":
        study(a.resolution, a.out, a.ratios, a.scales, a.scan)
    else:
        scene_report(a.scene)


if __name__ == "__main__":
    main()
