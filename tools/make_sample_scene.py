"""Build sample_data/spot_sun: Spot on a ground plane under a sunny park light, seen by a camera
with real lens distortion, rendered by wavelight's own forward model at a finer light resolution
than the demo solves at, with noise.

Run once by a developer (it reads third-party data from outside the project):
    python tools/make_sample_scene.py --spot path/to/spot_triangulated.obj \
        --envmap path/to/rooitou_park_1k.hdr --out sample_data/spot_sun
then tools/make_sample_calibration.py (calibration photos; camera.json and pose.json go to truth/).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pipelines.geometry import camera as cam
from pipelines.light import cubemap
from pipelines.io import images
from pipelines.geometry import raycast
from pipelines.model import render
from pipelines.model import materials
from pipelines.io import scene_files as scene
from pipelines.geometry import visibility

CAMERA = {"width": 192, "height": 144, "fx": 215.0, "fy": 215.0, "cx": 95.3, "cy": 72.6,
          "dist": [-0.09, 0.03, 0.0004, -0.0003, 0.0]}
AZIMUTH_DEG, ELEVATION_DEG, DISTANCE, TARGET = 35.0, 28.0, 3.3, (0.0, 0.0, 0.42)
LIGHT_ROTATION_DEG = 75.0
MATERIAL = {"model": "lambert", "kd": [0.8, 0.8, 0.8]}
NOISE_REL = 0.005
RENDER_R = 64
SEED = 20261123


def look_at(azimuth_deg, elevation_deg, distance, target):
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    target = np.asarray(target, float)
    eye = target + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world (OpenCV: x right, y down, z forward)
    return R, -R @ eye


def spot_on_plane(spot_path: Path, plane_size=3.0, cells=12):
    import trimesh

    m = trimesh.load(str(spot_path), force="mesh", process=False)
    v = np.asarray(m.vertices, float)
    v = np.column_stack([v[:, 0], -v[:, 2], v[:, 1]])  # y-up -> z-up
    v -= [0.5 * (v[:, 0].min() + v[:, 0].max()), 0.5 * (v[:, 1].min() + v[:, 1].max()), v[:, 2].min()]
    v /= v[:, 2].max()
    obj = trimesh.Trimesh(v, m.faces, process=False)
    g = np.linspace(-plane_size / 2, plane_size / 2, cells + 1)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    pv = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    pf = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    plane_normals = np.tile([0.0, 0.0, 1.0], (len(pv), 1))
    vertices = np.vstack([obj.vertices, pv])
    faces = np.vstack([obj.faces, pf + len(obj.vertices)])
    normals = np.vstack([obj.vertex_normals, plane_normals])
    return vertices, faces, normals, len(obj.vertices)


def write_obj(path: Path, vertices, faces, normals, header: str):
    lines = [f"# {line}" for line in header.splitlines()]
    lines += [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in vertices]
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in normals]
    lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in faces + 1]
    path.write_text("\n".join(lines) + "\n")


def light_from_hdr(path: Path, height=64):
    """Downsample an equirectangular HDR to (height, 2*height) preserving power, rotate in azimuth,
    zero the lower hemisphere, scale so a white upward patch sees radiance ~1."""
    src = images.read_image(path).pixels.astype(np.float64)
    H0 = src.shape[0]
    f = H0 // height
    w = cubemap.latlong_solid_angles(H0)[..., None]
    power = (src * w).reshape(height, f, 2 * height, f, 3).sum(axis=(1, 3))
    img = power / cubemap.latlong_solid_angles(height)[..., None]
    shift = int(round(LIGHT_ROTATION_DEG / 360.0 * 2 * height))
    img = np.roll(img, shift, axis=1)
    img[height // 2:] = 0.0
    theta = np.pi * (np.arange(height) + 0.5) / height
    irradiance_up = (img.mean(axis=2) * np.cos(theta)[:, None] * cubemap.latlong_solid_angles(height)).sum()
    return img * (np.pi / irradiance_up)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--spot", type=Path, required=True)
    ap.add_argument("--envmap", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    out = args.out
    (out / "truth").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(SEED)

    vertices, faces, normals, n_obj = spot_on_plane(args.spot)
    write_obj(out / "mesh.obj", vertices, faces, normals,
              "Spot (Keenan Crane, public domain), z-up, height 1, on a 3x3 ground plane at z=0.\n"
              "vn = smooth per-vertex shading normals.")
    R, t = look_at(AZIMUTH_DEG, ELEVATION_DEG, DISTANCE, TARGET)
    (out / "camera.json").write_text(json.dumps(CAMERA, indent=1) + "\n")
    (out / "pose.json").write_text(json.dumps({"R": R.tolist(), "t": t.tolist()}, indent=1) + "\n")

    camera = scene.read_camera(out / "camera.json")
    pose = scene.read_pose(out / "pose.json")
    mesh = scene.load_mesh(out / "mesh.obj")
    backend = raycast.make_backend(mesh)
    # edge_margin=-1: every pixel whose centre ray hits the mesh, silhouettes included (a photo has no
    # black ring around objects; the solver drops mixed pixels itself)
    samples, _ = cam.pixel_samples(camera, pose, mesh, backend, None, edge_margin=-1)
    cube = cubemap.CubeMap(RENDER_R)
    vis = visibility.compute_visibility(backend, samples, cube)
    env = light_from_hdr(args.envmap)
    images.write_exr(out / "truth" / "env_latlong.exr", env)
    images.write_png(out / "truth" / "env_latlong.png", env)
    material = materials.Material.from_json(MATERIAL)
    values = render.render(vis, cubemap.latlong_to_cube(env, cube), material)
    clean = render.pixels_to_image(values, samples.pixel, camera.height, camera.width)
    sigma = NOISE_REL * float(values.mean())
    noisy = clean + rng.normal(0.0, sigma, clean.shape).astype(np.float32)
    noisy[clean == 0] = 0.0  # background: no geometry, no light model
    noisy = np.clip(noisy, 0.0, None)
    images.write_exr(out / "truth" / "image_clean.exr", clean)
    images.write_exr(out / "image.exr", noisy)
    images.write_png(out / "image.png", np.clip(noisy, 0, 1), exposure=0.0)
    (out / "truth" / "material.json").write_text(json.dumps(MATERIAL, indent=1) + "\n")

    # 2D-3D correspondences: object vertices visible from the camera, projected + 0.3 px noise
    centre = pose.camera_centre
    cand = rng.choice(n_obj, 400, replace=False)
    d = mesh.vertices[cand] - centre
    dist = np.linalg.norm(d, axis=1)
    tt, face, _, _ = backend.intersect(np.tile(centre, (len(cand), 1)), d / dist[:, None])
    visible = np.abs(tt - dist) < 1e-3 * mesh.scale
    uv = cam.project(camera, pose, mesh.vertices[cand])
    inside = (uv[:, 0] > 5) & (uv[:, 0] < camera.width - 5) & (uv[:, 1] > 5) & (uv[:, 1] < camera.height - 5)
    keep = cand[visible & inside][:16]
    uvk = cam.project(camera, pose, mesh.vertices[keep]) + rng.normal(0, 0.3, (len(keep), 2))
    rows = ["u,v,x,y,z"] + [f"{u:.4f},{v:.4f},{x:.7f},{y:.7f},{z:.7f}"
                            for (u, v), (x, y, z) in zip(uvk, mesh.vertices[keep])]
    (out / "correspondences.csv").write_text("\n".join(rows) + "\n")
    params = {"camera": CAMERA, "azimuth_deg": AZIMUTH_DEG, "elevation_deg": ELEVATION_DEG, "distance": DISTANCE,
              "target": TARGET, "light_rotation_deg": LIGHT_ROTATION_DEG, "material": MATERIAL,
              "render_resolution": RENDER_R, "noise_sigma": sigma, "noise_rel": NOISE_REL, "seed": SEED,
              "used_pixels": int(len(samples)), "correspondences": int(len(keep))}
    (out / "truth" / "scene_params.json").write_text(json.dumps(params, indent=1) + "\n")
    print(json.dumps(params, indent=1))


if __name__ == "__main__":
    main()
