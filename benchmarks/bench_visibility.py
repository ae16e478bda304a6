"""One visibility measurement in a fresh process (so peak memory is this measurement's own).

    python benchmarks/bench_visibility.py --scene tests/data/scenes/spot_overcast --scale 1 \
        --resolution 32 --mode {kernel,bare,stage}

kernel: pipelines.visibility.visibility_rows over all pixels (ray preparation + Embree + packing).
bare:   the same rays, prepared beforehand (untimed), cast by plain embreex `run(..., 'OCCLUDED')`
        calls split over the same number of threads: the ceiling the kernel is measured against.
stage:  the whole cached `wavelight visibility` stage on a copy of the scene (pixel rays, chunk
        files, HDF5 assembly, manifest), forced to run.
Prints one JSON line: seconds, rays, Mrays/s, peak RSS.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipelines.geometry import camera as cam  # noqa: E402
from pipelines.geometry import raycast
from pipelines.geometry import visibility  # noqa: E402
from pipelines.light.cubemap import CubeMap  # noqa: E402
from pipelines.geometry.camera import Camera
from pipelines.io.scene_files import find_mesh, load_mesh, read_camera, read_pose  # noqa: E402

CHUNK = 1024


def scaled_camera(c: Camera, scale: int) -> Camera:
    # pixel centres at integer coordinates: a pixel of the scaled image covers scale x scale
    return Camera(c.width * scale, c.height * scale, c.fx * scale, c.fy * scale,
                  (c.cx + 0.5) * scale - 0.5, (c.cy + 0.5) * scale - 0.5, c.dist)


def bare_rays(backend, samples, rows, cube):
    """Exactly the rays the kernel traces for `rows` (castable pixel-texel pairs), compacted."""
    pos = backend.to_local(samples.position[rows])
    geo = samples.geometric_normal[rows].astype(np.float32)
    pj, ti = np.nonzero(visibility.castable(samples.normal[rows], geo, cube.directions))
    o = (pos + np.float32(backend.offset) * geo)[pj]
    return np.ascontiguousarray(o), np.ascontiguousarray(cube.directions.astype(np.float32)[ti])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--scale", type=int, default=1)
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--mode", choices=["kernel", "bare", "stage"], required=True)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    camera = scaled_camera(read_camera(args.scene / "camera.json"), args.scale)
    pose = read_pose(args.scene / "pose.json")
    mesh = load_mesh(find_mesh(args.scene))
    backend = raycast.make_backend(mesh, "embree", threads=args.threads)
    samples, _ = cam.pixel_samples(camera, pose, mesh, backend, None, edge_margin=1)
    cube = CubeMap(args.resolution)
    n = len(samples)
    chunks = [slice(a, min(n, a + CHUNK)) for a in range(0, n, CHUNK)]
    rays = sum(int(np.count_nonzero(visibility.castable(samples.normal[sl], samples.geometric_normal[sl],
                                                        cube.directions))) for sl in chunks)
    result = {"mode": args.mode, "width": camera.width, "height": camera.height, "pixels": n,
              "texels": cube.n_texels, "rays": rays, "threads": args.threads}

    if args.mode == "kernel":
        t0 = time.perf_counter()
        for sl in chunks:
            visibility.visibility_rows(backend, samples, sl, cube)
        seconds = time.perf_counter() - t0
    elif args.mode == "bare":
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene, backend.triangles)
        prepared = [bare_rays(backend, samples, sl, cube) for sl in chunks]
        seconds = 0.0
        with ThreadPoolExecutor(args.threads) as pool:
            for o, d in prepared:
                bounds = np.linspace(0, len(o), args.threads + 1).astype(int)
                t0 = time.perf_counter()
                list(pool.map(lambda i: scene.run(o[bounds[i]:bounds[i + 1]], d[bounds[i]:bounds[i + 1]],
                                                  query="OCCLUDED"), range(args.threads)))
                seconds += time.perf_counter() - t0
    else:
        from wavelight_cli.scene import SceneFiles
        from wavelight_cli.console import Console
        from pipelines.controllers.visibility import VisibilityOptions
        from wavelight_cli.stages.visibility import visibility_stage

        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp) / "scene"
            shutil.copytree(args.scene, work, ignore=shutil.ignore_patterns("truth", "image*", ".wavelight", "out",
                                                                            "mask*.png"))
            (work / "camera.json").write_text(json.dumps(camera.to_json()))
            t0 = time.perf_counter()
            visibility_stage(SceneFiles(work), VisibilityOptions(args.resolution), Console(quiet=True), force=True)
            seconds = time.perf_counter() - t0
            result["file_mb"] = (work / ".wavelight" / "visibility.h5").stat().st_size / 1e6
    result["seconds"] = seconds
    result["mrays_per_s"] = rays / seconds / 1e6
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps(result))


if __name__ == "__main__":
    main()
