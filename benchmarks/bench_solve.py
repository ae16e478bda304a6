"""Light-solve measurements in a fresh process: the normal-equations pass and every basis at one R,
or our NNLS against scipy.optimize.nnls on the same problem.

    python benchmarks/bench_solve.py --scene tests/data/scenes/spot_overcast --resolution 32 --mode bases
    python benchmarks/bench_solve.py --scene tests/data/scenes/spot_overcast --resolution 16 --mode nnls

bases: visibility (untimed), then the G pass (build_normal_equations, 10 % held out) and each basis'
       solve (pipelines.light.solve: every level, the held-out choice and the final re-solve), with
       its error. Prints one JSON line.
nnls:  one colour channel of the discrete problem at R (one unknown per texel): scipy's NNLS on
       the tall transport matrix T versus ours on G = T'T (with and without building G), interleaved.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipelines.geometry import camera as cam  # noqa: E402
from pipelines.io import images
from pipelines.geometry import raycast  # noqa: E402
from pipelines.light import bases as lt  # noqa: E402
from pipelines.geometry import visibility as vis  # noqa: E402
from pipelines.light.cubemap import CubeMap  # noqa: E402
from pipelines.light.system import build_normal_equations, holdout_mask  # noqa: E402
from pipelines.model.materials import Material
from pipelines.model.render import transport  # noqa: E402
from pipelines.io.scene_files import find_mesh, load_mesh, read_camera, read_pose  # noqa: E402

RUNS = [("wavelet", {}), ("quadtree", {}), ("discrete", {}), ("sh", {}), ("sh", {"sh_nonnegative": True}),
        ("points", {})]


def load(scene: Path, R: int, step: int = 1):
    camera, pose = read_camera(scene / "camera.json"), read_pose(scene / "pose.json")
    mesh = load_mesh(find_mesh(scene))
    backend = raycast.make_backend(mesh)
    mask = images.read_mask(scene / "mask.png") if (scene / "mask.png").exists() else None
    samples, _ = cam.pixel_samples(camera, pose, mesh, backend, mask, 1)
    if step > 1:
        samples = type(samples)(**{k: v[::step] for k, v in vars(samples).items()})
    data = vis.compute_visibility(backend, samples, CubeMap(R))
    photo = images.read_image(scene / "image.exr").pixels
    values = photo[samples.pixel[:, 0], samples.pixel[:, 1]].astype(np.float64)
    return camera, data, values


def bases(scene: Path, R: int) -> dict:
    camera, data, values = load(scene, R)
    t0 = time.perf_counter()
    ne = build_normal_equations(data, values, Material(), held_out=holdout_mask(data.samples.pixel, 0.1))
    g_pass = time.perf_counter() - t0
    out = {"width": camera.width, "height": camera.height, "pixels": data.n_pixels, "texels": data.cube.n_texels,
           "g_pass_seconds": g_pass, "runs": []}
    for basis, kw in RUNS:
        t0 = time.perf_counter()
        sol = lt.solve(ne, data.cube, basis, **kw)
        seconds = time.perf_counter() - t0
        out["runs"].append({"basis": sol.basis, "seconds": seconds, "coefficients": sol.n_coefficients,
                            "levels": len(sol.levels), "held_out_rmse": sol.held_out_rmse,
                            "all_pixels_rmse": sol.fit_rmse, "kkt": sol.solver.get("kkt_residual"),
                            "level_seconds": [lv.seconds for lv in sol.levels]})
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def nnls(scene: Path, R: int, repeats: int, step: int) -> dict:
    from scipy.optimize import nnls as scipy_nnls

    from pipelines.light.nnls import nnls_gram

    camera, data, values = load(scene, R, step)
    V = data.dense()
    D, _ = transport(V, data.samples.normal, data.samples.view, data.cube, Material())
    T = D.astype(np.float64)
    b = values[:, 1]
    times = {"scipy": [], "ours_G": [], "ours_with_G": []}
    objective = {}
    for _ in range(repeats):
        t0 = time.perf_counter()
        x_ref, _ = scipy_nnls(T, b, maxiter=50 * T.shape[1])
        times["scipy"].append(time.perf_counter() - t0)
        objective["scipy"] = float(np.sum((T @ x_ref - b) ** 2))
        t0 = time.perf_counter()
        ne = build_normal_equations(data, values, Material())
        G, h = ne.fit.G, ne.fit.h[:, 1]
        t1 = time.perf_counter()
        res = nnls_gram(G, h)
        t2 = time.perf_counter()
        times["ours_G"].append(t2 - t1)
        times["ours_with_G"].append(t2 - t0)
        objective["ours"] = float(np.sum((T @ res.x - b) ** 2))
        objective["ours_kkt"] = res.kkt_residual
    return {"width": camera.width, "height": camera.height, "pixels": data.n_pixels, "texels": data.cube.n_texels,
            "times": times, "objective": objective}


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--mode", choices=["bases", "nnls"], required=True)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--step", type=int, default=4, help="nnls: every step-th used pixel (scipy is slow)")
    args = ap.parse_args()
    result = bases(args.scene, args.resolution) if args.mode == "bases" else nnls(args.scene, args.resolution,
                                                                                 args.repeats, args.step)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
