"""Reflectance measurements in a fresh process: one LM round and a full `auto` alternation.

    python benchmarks/bench_reflectance.py --scene tests/data/scenes/teapot_sun_phong --resolution 32

Visibility is computed first (untimed). Then, interleaved `repeats` times so that machine noise
hits both alike: the Lambertian normal-equations pass (the baseline every ratio is taken against)
and one LM round (`specular_data` for the light + `fit_specular` from the CLI's default start).
Finally one full `reflectance.select` (what `wavelight solve` runs by default) with its rounds.
Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_solve import load  # noqa: E402

from pipelines.light import bases as lt  # noqa: E402
from pipelines.model import reflectance as rf  # noqa: E402
from pipelines.light.system import build_normal_equations, holdout_mask  # noqa: E402
from pipelines.model.materials import Material  # noqa: E402

START = Material(kd=(1.0, 1.0, 1.0), ks=(0.25, 0.25, 0.25), shininess=20.0, model="blinn-phong")  # CLI default


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--step", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    camera, data, values = load(args.scene, args.resolution, args.step)
    held = holdout_mask(data.samples.pixel, 0.1)
    lambert = Material()
    g_times, lm_times, data_times, lm_evals = [], [], [], []
    light = None
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        ne = build_normal_equations(data, values, lambert, held_out=held)
        g_times.append(time.perf_counter() - t0)
        if light is None:
            light = lt.solve(ne, data.cube, "wavelet").light
        t0 = time.perf_counter()
        sd = rf.specular_data(data, values, light, "blinn-phong", held_out=held)
        data_times.append(time.perf_counter() - t0)
        fit = rf.fit_specular(sd, START)
        lm_times.append(time.perf_counter() - t0)
        lm_evals.append(fit.evaluations)

    timings = []

    def solve_light(material):
        t0 = time.perf_counter()
        ne = build_normal_equations(data, values, material, held_out=held)
        t1 = time.perf_counter()
        sol = lt.solve(ne, data.cube, "wavelet")
        timings.append({"model": material.model, "g_pass": t1 - t0, "light": time.perf_counter() - t1,
                        "grams": 1 if ne.fit.G.ndim == 2 else 3})
        return sol, ne

    t0 = time.perf_counter()
    result = rf.select(data, values, START, solve_light, held_out=held, kd_reference=START.kd)
    total = time.perf_counter() - t0
    lm = [r.fit.seconds for r in result.rounds if r.fit is not None]
    m = result.material
    print(json.dumps({
        "width": camera.width, "height": camera.height, "pixels": data.n_pixels, "texels": data.cube.n_texels,
        "lambert_g_pass_seconds": g_times, "lm_round_seconds": lm_times, "specular_data_seconds": data_times,
        "lm_evaluations": lm_evals, "lit_texels": sd.lit_texels, "lm_pixels": len(sd.photo),
        "ratio_lm_round_to_g_pass": statistics.median(lm_times) / statistics.median(g_times),
        "alternation_seconds": total, "alternation_rounds": len(result.rounds) - 1,
        "alternation_light_solves": timings, "alternation_lm_seconds": lm,
        "ratio_alternation_to_g_pass": total / statistics.median(g_times),
        "model": m.model, "kd": list(m.kd), "ks": float(m.ks[0]), "n": m.shininess, "decision": result.decision,
        "fit_rmse": [r.fit_rmse for r in result.rounds], "held_out_rmse": [r.held_out_rmse for r in result.rounds],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }))


if __name__ == "__main__":
    main()
