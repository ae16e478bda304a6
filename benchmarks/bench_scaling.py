"""How each stage's time and memory grow with the problem: one configuration per fresh process.

    python benchmarks/bench_scaling.py --scene tests/data/scenes/spot_overcast --scale 2 --resolution 16

The scene's camera is scaled by `--scale` (each pixel becomes scale x scale pixels, the photo and
mask repeated to match: the same problem, sampled more densely) and the light is solved at
`--resolution` R. Stages, each timed, with the peak resident memory of the process while it ran
(sampled every 5 ms by a thread; psutil when installed, else the process' lifetime peak):

- visibility: pipelines.visibility.compute_visibility, every used pixel x every texel (2 threads);
- G pass: the normal equations G = T'T, h = T'b (10 % held out), white Lambert material;
- solve: pipelines.light.solve for the wavelet basis (every level, `--levels auto`), for the
  per-texel discrete basis (R <= 32: at R = 64 it takes minutes) and for 9 spherical harmonics.
  These read only G and h: their time should not depend on the pixel count.

Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_visibility import scaled_camera  # noqa: E402
from pipelines.geometry import camera as cam  # noqa: E402
from pipelines.io import images
from pipelines.geometry import raycast  # noqa: E402
from pipelines.light import bases as lt  # noqa: E402
from pipelines.geometry import visibility as vis  # noqa: E402
from pipelines.light.cubemap import CubeMap  # noqa: E402
from pipelines.light.system import build_normal_equations, holdout_mask  # noqa: E402
from pipelines.model.materials import Material  # noqa: E402
from pipelines.io.scene_files import find_mesh, load_mesh, read_camera, read_pose  # noqa: E402


def _rss_mb() -> float:
    try:
        import psutil

        return psutil.Process().memory_info().rss / 2**20
    except ImportError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@contextmanager
def stage(results: dict, name: str):
    """Time the block and sample the process' resident memory while it runs."""
    peak = [_rss_mb()]
    done = threading.Event()

    def sample():
        while not done.wait(0.005):
            peak[0] = max(peak[0], _rss_mb())

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t0 = time.perf_counter()
    try:
        yield
    finally:
        seconds = time.perf_counter() - t0
        done.set()
        sampler.join()
        results[name] = {"seconds": seconds, "peak_rss_mb": max(peak[0], _rss_mb())}


def upscale(img: np.ndarray, scale: int) -> np.ndarray:
    return np.repeat(np.repeat(img, scale, axis=0), scale, axis=1) if scale > 1 else img


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--scale", type=int, default=1)
    ap.add_argument("--resolution", type=int, default=32)
    args = ap.parse_args()

    camera = scaled_camera(read_camera(args.scene / "camera.json"), args.scale)
    pose = read_pose(args.scene / "pose.json")
    mesh = load_mesh(find_mesh(args.scene))
    backend = raycast.make_backend(mesh, "embree", threads=2)
    mask_path = args.scene / "mask.png"
    mask = upscale(images.read_mask(mask_path), args.scale) if mask_path.is_file() else None
    samples, _ = cam.pixel_samples(camera, pose, mesh, backend, mask, edge_margin=args.scale)
    photo = upscale(images.read_image(args.scene / "image.exr").pixels, args.scale)
    values = photo[samples.pixel[:, 0], samples.pixel[:, 1]].astype(np.float64)
    cube = CubeMap(args.resolution)
    stages: dict = {}
    with stage(stages, "visibility"):
        data = vis.compute_visibility(backend, samples, cube)
    with stage(stages, "g_pass"):
        ne = build_normal_equations(data, values, Material(), held_out=holdout_mask(data.samples.pixel, 0.1))
    errors = {}
    for basis in ("wavelet", "discrete", "sh"):
        if basis == "discrete" and args.resolution > 32:
            continue
        with stage(stages, f"solve_{basis}"):
            sol = lt.solve(ne, cube, basis)
        errors[basis] = sol.held_out_rmse
    print(json.dumps({"scale": args.scale, "width": camera.width, "height": camera.height, "pixels": len(samples),
                      "resolution": args.resolution, "texels": cube.n_texels, "stages": stages,
                      "held_out_rmse": errors,
                      "visibility_mb": data.stored.nbytes / 1e6}))


if __name__ == "__main__":
    main()
