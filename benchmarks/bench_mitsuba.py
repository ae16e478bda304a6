"""The peer: a Mitsuba 3 inverse-rendering loop against wavelight, on the same scene and image.

Mitsuba side (its documentation's recipe, given its best case): the scene's mesh with the TRUE
material, a 64 x 32 lat-long envmap as the only light, `prb` with max_depth 2 (direct light only,
as the reference renders), spp 4, Adam on the envmap's texels with lr = 1.0 x the mean starting
radiance, clamped at zero after each step, L2 loss over the scene's mask. The envmap starts
constant, at the level that makes the first render's mean match the photo's.

wavelight side: `solve` with the same true material at R = 8, 16, 32 (whole stage: visibility,
normal equations, solve).

Errors, both sides the same way:
- image: relative RMSE of the render against the photo over the mask (wavelight: its relit view
  over its used pixels);
- light: relative RMSE of the irradiance (the light after a cosine blur, what a diffuse scene can
  determine) over upward normals, against the true light.

Prints one JSON line: {"scene", "mitsuba": {"curve": [[seconds, image_err, light_err], ...], ...},
"wavelight": [{"R", "seconds", "image_err", "light_err"}], ...}. Usage:
    python benchmarks/bench_mitsuba.py SCENE_DIR WORK_DIR [--iterations 300]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipelines.light import cubemap
from pipelines.io import exports
from pipelines.io import images  # noqa: E402
from pipelines.io.scene_files import load_mesh, read_camera, read_pose  # noqa: E402

ENV_H = 32  # the peer's map: 64 x 32


def irradiance_normals(n_theta: int = 12, n_phi: int = 24) -> np.ndarray:
    """Upward normals (theta < 90 deg) on a grid."""
    t = (np.arange(n_theta) + 0.5) / n_theta * (np.pi / 2)
    p = (np.arange(n_phi) + 0.5) / n_phi * 2 * np.pi
    tt, pp = np.meshgrid(t, p, indexing="ij")
    return cubemap.spherical_to_direction(tt, pp).reshape(-1, 3)


def irradiance(latlong: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """E(n) = integral of L(d) max(0, n.d) d omega, from a lat-long light, per normal (n, 3)."""
    H = latlong.shape[0]
    d = cubemap.latlong_directions(H).reshape(-1, 3)
    w = cubemap.latlong_solid_angles(H).reshape(-1)
    L = latlong.reshape(-1, latlong.shape[-1])
    cos = np.clip(normals @ d.T, 0, None)
    return (cos * w) @ L


def light_error(estimate: np.ndarray, truth_E: np.ndarray, normals: np.ndarray) -> float:
    E = irradiance(estimate, normals)
    return float(np.sqrt(np.mean((E - truth_E) ** 2)) / np.sqrt(np.mean(truth_E**2)))


def write_obj(path: Path, mesh) -> None:
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in mesh.vertices]
    lines += [f"vn {x:.7g} {y:.7g} {z:.7g}" for x, y, z in mesh.vertex_normals]
    lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in mesh.faces + 1]
    path.write_text("\n".join(lines) + "\n")


def envmap_image(data: np.ndarray) -> np.ndarray:
    """Mitsuba's envmap tensor -> the (ENV_H, 2 ENV_H, 3) image it was loaded from: Mitsuba pads the
    image with a copy of its last column on the left and of its first on the right (measured with
    3.9.1), for interpolation across the seam."""
    cols = data.shape[1]
    return data[:, 1:1 + 2 * ENV_H, :3] if cols == 2 * ENV_H + 2 else data[:, :2 * ENV_H, :3]


def peer_latlong(image: np.ndarray, rows: int = 2 * ENV_H) -> np.ndarray:
    """The peer's light in our lat-long convention, `rows` x 2 `rows`: what Mitsuba's envmap reads
    from `image` (its own layout, `exports.to_mitsuba`: 2 ENV_H + 1 rows on its pole-to-pole grid,
    columns mirrored) at our pixel centres, by its bilinear lookup (`exports.mitsuba_lookup`)."""
    d = cubemap.latlong_directions(rows).reshape(-1, 3)
    return exports.mitsuba_lookup(image, d).reshape(rows, 2 * rows, -1)


def mitsuba_scene(mi, scene_dir: Path, work: Path, kd, env0: np.ndarray, spp: int):
    camera = read_camera(scene_dir / "camera.json")
    pose = read_pose(scene_dir / "pose.json")
    mesh = load_mesh(next(scene_dir.glob("mesh.*")))
    obj = work / "mesh.obj"
    if not obj.is_file():
        write_obj(obj, mesh)
    c = pose.camera_centre
    forward = pose.R[2]
    up = -pose.R[1]  # OpenCV's y points down the image
    fov = float(np.degrees(2 * np.arctan(camera.width / (2 * camera.fx))))
    W, H = camera.width, camera.height
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2, "hide_emitters": True},
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "x",
                   # principal point: ours is at (cx, cy) with pixel (0, 0)'s centre at 0; Mitsuba's offset is
                   # a fraction of the film from its centre (pixel centres at +0.5), counted the other way round
                   # (measured: these signs render bunny_sun within 2.8 % of its reference, the others 22-36 %)
                   "principal_point_offset_x": -(camera.cx + 0.5 - W / 2) / W,
                   "principal_point_offset_y": -(camera.cy + 0.5 - H / 2) / H,
                   "to_world": mi.ScalarTransform4f().look_at(origin=c.tolist(), target=(c + forward).tolist(),
                                                            up=up.tolist()),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"}},
        "shape": {"type": "obj", "filename": str(obj), "face_normals": False,
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(map(float, kd))}}},
        "emitter": {"type": "envmap", "bitmap": mi.Bitmap(exports.to_mitsuba(env0).astype(np.float32)),
                    "to_world": mi.ScalarTransform4f(exports.MITSUBA_TO_WORLD.tolist())},
    })


def run_mitsuba(scene_dir: Path, work: Path, iterations: int, spp: int, truth_E, normals, log,
                lr_factor: float = 1.0) -> dict:
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    kd = json.loads((scene_dir / "truth" / "material.json").read_text())["kd"]
    photo = images.read_image(scene_dir / "image.exr").pixels.astype(np.float32)
    mask = images.read_mask(scene_dir / "mask.png")
    env0 = np.ones((ENV_H, 2 * ENV_H, 3), np.float32)
    scene = mitsuba_scene(mi, scene_dir, work, kd, env0, spp)
    first = np.array(mi.render(scene, spp=16))
    level = float(photo[mask].mean() / max(first[mask].mean(), 1e-12))
    params = mi.traverse(scene)
    key = "emitter.data"
    start = np.array(params[key])
    params[key] = mi.TensorXf(start * level)
    params.update()
    opt = mi.ad.Adam(lr=lr_factor * level)
    opt[key] = params[key]
    params.update(opt)
    target = mi.TensorXf(photo)
    m = mi.TensorXf(np.repeat(mask[..., None], 3, axis=2).astype(np.float32))
    n_mask = float(mask.sum() * 3)
    ref_norm = float(np.sqrt(np.mean(photo[mask] ** 2)))
    curve = []
    t0 = time.perf_counter()
    for it in range(iterations):
        img = mi.render(scene, params, spp=spp, seed=it)
        loss = dr.sum(dr.square((img - target) * m)) / n_mask
        dr.backward(loss)
        opt.step()
        opt[key] = dr.clip(opt[key], 0.0, 1e30)
        params.update(opt)
        if it % 10 == 9 or it == iterations - 1:
            elapsed = time.perf_counter() - t0
            data = np.array(params[key])
            if it == iterations - 1 or len(curve) == 0:
                log(f"mitsuba: envmap tensor {data.shape}")
            ours = peer_latlong(envmap_image(data))
            image_err = float(np.sqrt(float(np.array(loss).ravel()[0])) / ref_norm)
            curve.append([elapsed, image_err, light_error(ours.astype(np.float64), truth_E, normals)])
            log(f"mitsuba: iteration {it + 1}: {elapsed:.1f} s, image {100 * image_err:.2f} %, "
                f"light {100 * curve[-1][2]:.2f} %")
    # the final light, rendered once with many samples: the image error without Monte Carlo noise
    final = np.array(mi.render(scene, params, spp=256, seed=10_000))
    final_err = float(np.sqrt(np.mean((final[mask] - photo[mask]) ** 2)) / ref_norm)
    return {"curve": curve, "final_image_err_256spp": final_err, "iterations": iterations, "spp": spp,
            "lr": lr_factor * level, "lr_factor": lr_factor, "seconds_per_iteration": curve[-1][0] / iterations, "mitsuba": mi.__version__}


def run_wavelight(scene_dir: Path, work: Path, truth_E, normals, log) -> list[dict]:
    out = []
    for R in (8, 16, 32):
        s = work / f"wl_{R}"
        shutil.rmtree(s, ignore_errors=True)
        shutil.copytree(scene_dir, s, ignore=shutil.ignore_patterns("truth"))
        material = scene_dir / "truth" / "material.json"
        exe = Path(sys.executable).parent / "wavelight"
        t0 = time.perf_counter()
        subprocess.run([str(exe), "-q", "-s", str(s), "solve", "-R", str(R), "--material", str(material)], check=True,
                       capture_output=True)
        seconds = time.perf_counter() - t0
        report = json.loads((s / "out" / "solve_report.json").read_text())
        light = images.read_latlong(s / "out" / "light_latlong.exr")
        row = {"R": R, "seconds": seconds, "image_err": report["relit"]["relative_rmse_vs_photo"],
               "light_err": light_error(light, truth_E, normals)}
        log(f"wavelight: R = {R}: {seconds:.1f} s, image {100 * row['image_err']:.2f} %, "
            f"light {100 * row['light_err']:.2f} %")
        out.append(row)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("scene", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--lr-factor", type=float, default=1.0, help="Adam's lr in units of the starting radiance")
    ap.add_argument("--skip-wavelight", action="store_true")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    normals = irradiance_normals()
    truth = images.read_latlong(args.scene / "truth" / "env_latlong.exr")
    truth_E = irradiance(truth, normals)
    result = {"scene": args.scene.name}
    if not args.skip_wavelight:
        result["wavelight"] = run_wavelight(args.scene, args.work, truth_E, normals, log)
    result["mitsuba"] = run_mitsuba(args.scene, args.work, args.iterations, args.spp, truth_E, normals, log,
                                    args.lr_factor)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
