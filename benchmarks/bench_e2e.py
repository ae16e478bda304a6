"""One whole `wavelight solve` with its defaults, from an empty cache, on a copy of a scene: its wall
time, peak memory and accuracy against the scene's truth. One configuration per call:

    python benchmarks/bench_e2e.py SCENE_DIR WORK_DIR [--scale 2] [--resolution 64] [--exact]

`--scale k` makes the same scene k times finer (camera scaled, the photo and mask repeated k x k:
the same problem sampled more densely, as the scaling section does). `--exact` runs the reference
route (every shadow ray, dense normal equations over every pixel: today's route before the
sampled one). The time is the whole command's (process start, visibility, solve, outputs) and the
peak memory the process' maximum resident set (getrusage of the child).

Accuracy (every number from the stage's own outputs, compared with truth/):
- held-out and relit error (solve_report.json);
- probe spheres: a matte (kd 0.8) and a glossy (Blinn-Phong kd 0.2, ks 0.8, n 100) unit sphere seen
  from the photo's camera, relit by the recovered light and by the true light, scale-invariant
  relative RMSE (light x albedo is one product);
- the brightest light direction (solve_report.json's energy centroid of the brightest region) and,
  for a sun, its angle to the truth's dominant direction (README.txt);
- the reflectance: model, ks/kd, n.
Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from pipelines.metrics import probe_errors as probe_errors_of  # noqa: E402
from bench_visibility import scaled_camera  # noqa: E402
from pipelines.io import images, light_file  # noqa: E402
from pipelines.io.scene_files import read_camera, read_pose  # noqa: E402
from pipelines.light import cubemap  # noqa: E402


def prepare(src: Path, dst: Path, scale: int) -> Path:
    """A copy of the scene without its truth (and k x k finer when scale > 1)."""
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("truth", ".wavelight", "out", "image.png", "calib"))
    for name in ("camera.json", "pose.json"):  # the sample scene keeps them in truth/ (calibrate and register write them)
        if not (dst / name).exists():
            shutil.copy(src / "truth" / name, dst / name)
    if scale > 1:
        cam = scaled_camera(read_camera(dst / "camera.json"), scale)
        data = json.loads((dst / "camera.json").read_text())
        data.update(width=cam.width, height=cam.height, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy)
        (dst / "camera.json").write_text(json.dumps(data))
        photo = images.read_image(src / "image.exr").pixels
        images.write_exr(dst / "image.exr", np.repeat(np.repeat(photo, scale, 0), scale, 1))
        for m in ("mask.png", "mask_object.png"):
            if (src / m).exists():
                mask = images.read_mask(src / m).astype(np.float32)
                images.write_png(dst / m, np.repeat(np.repeat(mask, scale, 0), scale, 1), already_display=True)
    return dst


def dominant_direction(scene: Path) -> np.ndarray | None:
    """The true light's sun: the power-weighted direction of its brightest 1 % of lat-long pixels,
    when they hold at least 30 % of the power (else None: no sun)."""
    env = images.read_latlong(scene / "truth" / "env_latlong.exr")
    power = env.mean(axis=2) * cubemap.latlong_solid_angles(env.shape[0])
    d = cubemap.latlong_directions(env.shape[0]).reshape(-1, 3)
    p = power.ravel()
    top = np.argsort(-p)[: max(1, len(p) // 100)]
    if p[top].sum() < 0.3 * p.sum():
        return None
    v = (p[top, None] * d[top]).sum(axis=0)
    return v / np.linalg.norm(v)


def probe_errors(coefficients: Path, scene: Path) -> dict:
    light, cube, _ = light_file.read_solution_light(coefficients)
    env = images.read_latlong(scene / "truth" / "env_latlong.exr")
    view = read_pose(scene / "pose.json" if (scene / "pose.json").exists() else scene / "truth" / "pose.json").camera_centre
    fine = cubemap.CubeMap(64)
    return probe_errors_of(light, cube, cubemap.latlong_to_cube(env, fine), fine, view)


def timed_solve(scene: Path, args: list[str]) -> tuple[float, dict]:
    """`wavelight -q -s SCENE solve ARGS` in a subprocess: (wall seconds, its solve_report.json)."""
    cmd = [str(Path(sys.executable).parent / "wavelight"), "-q", "-s", str(scene), "solve", *args]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return seconds, json.loads((scene / "out" / "solve_report.json").read_text())


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("scene", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--scale", type=int, default=1)
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--exact", action="store_true")
    args = ap.parse_args()
    name = f"{args.scene.name}-x{args.scale}-R{args.resolution}{'-exact' if args.exact else ''}"
    scene = prepare(args.scene, args.work / name, args.scale)
    exe = Path(sys.executable).parent / "wavelight"
    cmd = [str(exe), "-q", "-s", str(scene), "solve"]
    if args.resolution != 32:
        cmd += ["-R", str(args.resolution)]
    if args.exact:
        cmd += ["--exact"]
    t0 = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if run.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{run.stderr[-3000:]}")
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    report = json.loads((scene / "out" / "solve_report.json").read_text())
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    centroid = report["brightest_direction"]["centroid"]["direction"]
    truth_dir = dominant_direction(args.scene)
    sun_error = None if truth_dir is None else float(np.degrees(np.arccos(np.clip(np.dot(centroid, truth_dir), -1, 1))))
    print(json.dumps({
        "scene": args.scene.name, "scale": args.scale, "resolution": args.resolution, "exact": args.exact,
        "seconds": seconds, "peak_rss_mb": peak, "pixels": report["pixels"]["used"],
        "held_out": report["solution"]["held_out_rmse"], "relit": report["relit"]["relative_rmse_vs_photo"],
        "probes": probe_errors(scene / "out" / "coefficients.h5", args.scene) if args.scale == 1 else None,
        "brightest": centroid, "sun_error_deg": sun_error, "coefficients": report["solution"]["coefficients"],
        "model": refl["model"], "ks_over_kd": refl.get("ks_over_kd"), "n": refl.get("n"),
        "sample": report.get("sample")}))


if __name__ == "__main__":
    main()
