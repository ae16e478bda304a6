"""Speed against error across wavelight's own bases and refinement levels on one Mitsuba scene.

`solve` (wavelet, every level it tries) and `compare` (every basis at its chosen size), both with
the TRUE material at one R, from an empty cache. For each level and basis: coefficients, solve time
(after the normal equations), fit and held-out error (from the stages' JSON), and the light error
against the true light (relative RMSE of the irradiance over upward normals, as in
bench_mitsuba.py), and the relighting error of two probe spheres seen from the scene's camera
(`probe_error`). Prints one JSON line. Usage:
    python benchmarks/bench_bases.py SCENE_DIR WORK_DIR [--resolution 32]
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
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_mitsuba import irradiance, irradiance_normals, light_error  # noqa: E402
from pipelines.light import cubemap
from pipelines.light import haar
from pipelines.io import images  # noqa: E402
from pipelines.io import light_file as lt  # noqa: E402
from pipelines.io.scene_files import read_pose  # noqa: E402

from pipelines.metrics import PROBES, probe_geometry, probe_image  # noqa: E402  (shared with the tests)


def probe_error(texels: np.ndarray, cube: cubemap.CubeMap, truth: dict, geometry) -> dict:
    """Relative RMSE of each probe relit by `texels` against the same probe under the true light."""
    out = {}
    for name, material in PROBES.items():
        img = probe_image(texels, cube, *geometry, material)
        ref = truth[name]
        out[name] = float(np.sqrt(np.mean((img - ref) ** 2)) / np.sqrt(np.mean(ref**2)))
    return out


def latlong(texels, cube, height=128):
    return cubemap.cube_to_latlong(np.asarray(texels, np.float64), cube, height)


def timed(exe: Path, scene: Path, command: str, resolution: str, material: Path) -> float:
    """Run one `wavelight` stage on the scene (quiet, true material); its wall time in seconds."""
    t0 = time.perf_counter()
    subprocess.run([str(exe), "-q", "-s", str(scene), command, "-R", resolution, "--material", str(material)],
                   check=True, capture_output=True)
    return time.perf_counter() - t0


def main():
    import h5py

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("scene", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--resolution", type=int, default=32)
    args = ap.parse_args()
    scene = args.work / args.scene.name
    shutil.rmtree(scene, ignore_errors=True)
    shutil.copytree(args.scene, scene, ignore=shutil.ignore_patterns("truth"))
    material = args.scene / "truth" / "material.json"
    exe = Path(sys.executable).parent / "wavelight"
    normals = irradiance_normals()
    truth_E = irradiance(images.read_latlong(args.scene / "truth" / "env_latlong.exr"), normals)
    R = str(args.resolution)
    # the true light, on a finer hemisphere cube than the solves' (its sun stays sharp)
    pose = read_pose(args.scene / "pose.json")
    view = pose.camera_centre  # the probe at the world origin, seen from the photo's camera
    geometry = probe_geometry(view / np.linalg.norm(view))
    fine = cubemap.CubeMap(max(64, 2 * args.resolution))
    truth_texels = cubemap.latlong_to_cube(images.read_latlong(args.scene / "truth" / "env_latlong.exr"), fine)
    truth_probes = {name: probe_image(truth_texels, fine, *geometry, m) for name, m in PROBES.items()}
    solve_seconds = timed(exe, scene, "solve", R, material)
    report = json.loads((scene / "out" / "solve_report.json").read_text())
    levels = []
    with h5py.File(scene / "out" / "coefficients.h5", "r") as f:
        cube = cubemap.CubeMap(int(f.attrs["resolution"]), bool(f.attrs["hemisphere"]))
        for lv in report["solution"]["levels"]:
            g = f["levels"][f"{lv['level']:02d}"]
            texels = haar.synthesise(g["coefficients"][:], lt.read_tree(g["tree"]))
            levels.append({"level": lv["level"], "coefficients": lv["coefficients"], "seconds": lv["seconds"],
                           "fit_rmse": lv["fit_rmse"], "held_out_rmse": lv["held_out_rmse"],
                           "light_err": light_error(latlong(texels, cube), truth_E, normals),
                           "probe_err": probe_error(texels, cube, truth_probes, geometry)})
    compare_seconds = timed(exe, scene, "compare", R, material)
    table = json.loads((scene / "out" / "compare.json").read_text())
    bases = []
    with h5py.File(scene / "out" / "compare_lights.h5", "r") as f:
        names = sorted(f)
        for row, name in zip(table["rows"], names):
            texels = np.clip(f[name][:].astype(np.float64), 0, None)  # what a renderer would use
            bases.append({**{k: row[k] for k in ("basis", "coefficients", "seconds", "fit_rmse", "held_out_rmse",
                                                 "min_radiance_relative")},
                          "light_err": light_error(latlong(texels, cube), truth_E, normals),
                          "probe_err": probe_error(texels, cube, truth_probes, geometry)})
    print(json.dumps({"scene": args.scene.name, "resolution": args.resolution, "solve_stage_seconds": solve_seconds,
                      "normal_equations_seconds": report["normal_equations_seconds"],
                      "compare_stage_seconds": compare_seconds, "levels": levels, "bases": bases,
                      "pixels": report["pixels"]}))


if __name__ == "__main__":
    main()
