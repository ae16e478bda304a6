"""False self-shadowing with a long lens: measure the hit points' error and the shadowed pixels of a
convex ball seen from 10 to 10^4 radii at scene scales 1e-3 ... 1e3, and of a solved scene.

Usage:
    .venv/bin/python tools/diligent_self_shadow.py study [--resolution 8] [--out build/analysis/self_shadow.json]
    .venv/bin/python tools/diligent_self_shadow.py scene SCENE [--resolution 16]   # all-shadowed pixels of a solved scene

What went wrong (issue 17, before the fix now in pipelines/geometry/raycast.py):
  `pixel_samples` took Embree's float32 hit distance t and computed position = o + t d. From a camera
  D away, Embree's float32 intersection gives t with an error ~eps32 x D (eps32 = 2^-23 ~ 1.2e-7), which
  moved the point off its facet by that x cos(view, normal); the shadow rays started 1e-5 x scene size
  above it. For a ball of radius r the error beat the offset once D was more than ~150 r: a point under
  its own facet sees the facet's back toward every direction in front of it (22 % of the pixels
  all-shadowed at 1,000 r, 40 % at 10^4 r, at every scale).

The fix (`_Backend.first_hits`, `_Backend.shadow_origins`), measured here:
  1. hit points in float64 on the hit face: Embree chooses the face (a second query from just short of
     the first hit, so that far cameras choose the face a near float32 ray hits), the float64 ray meets
     the face's plane (float64 vertices, recentred frame), barycentrics clamped into the triangle;
  2. the shadow-ray offset from float32's precision where the ray starts:
        offset = 32 x eps32 x (max|p_local| + longest edge of the hit triangle),
     added in float64 before the rounding to float32: larger than the float32 rounding of the origin and
     of the triangle, at any camera distance and scale. (The old 1e-5 x scene size was ~290 x eps32 x
     max|p_local| on a ball: too small for the camera-distance error, not for float32 itself.)
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))


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


def study_case(ratio: float, scale: float, resolution: int, workdir: Path) -> dict:
    """Ball of radius ~scale seen from ratio x radius, image as the photos (rho ~ 70.9 px)."""
    import photometric as ph
    from pipelines.geometry import camera as cam
    from pipelines.geometry import raycast
    from pipelines.io import images
    from pipelines.io import scene_files as sc
    from pipelines.light import cubemap

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
    samples, _ = cam.pixel_samples(camera, pose, mesh, backend, images.read_mask(scene / "mask.png"), 1)
    err = plane_distance(mesh, samples.position, samples.face)
    # how far above the float32 triangle the float32 shadow-ray origin is
    origins = backend.shadow_origins(samples.position, samples.geometric_normal, samples.face).astype(np.float64)
    tri = backend.triangles[samples.face].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    height = np.abs(np.einsum("ij,ij->i", origins - tri[:, 0], n))
    row = {"distance_over_radius": ratio, "scale": scale, "radius": view.radius, "focal_px": focal,
           "scene_size": mesh.scale, "used_pixels": len(samples),
           "plane_err_max": float(np.abs(err).max()), "offset_min": float(height.min()),
           "offset_median": float(np.median(height))}
    row["all_shadowed"], row["any_shadowed"], row["false_ray_share"] = shadow_counts(samples, backend, cube)
    return row


def study(resolution: int, out: Path, ratios, scales):
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for ratio in ratios:
            for scale in scales:
                r = study_case(ratio, scale, resolution, Path(tmp))
                rows.append(r)
                print(f"D/r {ratio:>6g}  scale {scale:>6g}: radius {r['radius']:.3g}; hit error to facet plane max "
                      f"{r['plane_err_max']:.2g}; origin above the float32 facet min {r['offset_min']:.2g} median "
                      f"{r['offset_median']:.2g}; all-shadowed {r['all_shadowed']} / {r['used_pixels']}, any "
                      f"{r['any_shadowed']}, false rays {100 * r['false_ray_share']:.3f} %", flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=2) + "\n")
    return rows


def scene_report(scene: Path, resolution: int):
    """All-shadowed pixels of a scene's cached visibility, and where they are (radius from the ball's
    centre in px)."""
    import photometric as ph
    from pipelines.geometry import visibility as vis
    from pipelines.io import visibility_file

    data = visibility_file.read_visibility(scene / ".wavelight" / "visibility" / f"photo-R{resolution}.h5")
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
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("study")
    s.add_argument("--resolution", type=int, default=8)
    s.add_argument("--out", type=Path, default=REPO / "build" / "analysis" / "self_shadow.json")
    s.add_argument("--ratios", type=float, nargs="*", default=[10, 100, 1000, 10000])
    s.add_argument("--scales", type=float, nargs="*", default=[1e-3, 1e-2, 1e-1, 1, 1e1, 1e2, 1e3])
    c = sub.add_parser("scene")
    c.add_argument("scene", type=Path)
    c.add_argument("--resolution", type=int, default=32)
    a = ap.parse_args(argv if argv is not None else sys.argv[1:])
    if a.cmd == "study":
        study(a.resolution, a.out, a.ratios, a.scales)
    else:
        scene_report(a.scene, a.resolution)


if __name__ == "__main__":
    main()
