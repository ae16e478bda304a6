"""`make bench`: run the benchmarks and write benchmarks/RESULTS.md.

Every comparison is a ratio measured in the same run, with the measurements interleaved
(A, B, A, B, ...) so that machine noise hits both sides alike; absolute times are given as
min / median / max over the repeats. Each measurement runs in a fresh process so that its peak
memory is its own.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "tests" / "data" / "scenes" / "spot_overcast"


def measure(args: list[str], script: str = "bench_visibility.py") -> dict:
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args],
                         check=True, capture_output=True, text=True, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def spread(values: list[float], fmt: str = "{:.2f}") -> str:
    return " / ".join(fmt.format(v) for v in (min(values), statistics.median(values), max(values)))


def versions() -> dict:
    import cv2
    import embreex
    import h5py
    import numpy
    import OpenImageIO
    import scipy
    import trimesh

    return {"python": platform.python_version(), "numpy": numpy.__version__, "scipy": scipy.__version__,
            "embreex": getattr(embreex, "__version__", "?"), "trimesh": trimesh.__version__,
            "h5py": h5py.__version__, "OpenImageIO": OpenImageIO.__version__, "opencv": cv2.__version__}


def visibility_section(repeats: int) -> list[str]:
    lines = ["## Visibility throughput (issue 2)", "",
             f"Scene `tests/data/scenes/spot_overcast` (Spot on a ground plane, {SCENE.name}), R = 32 (3072 "
             "texels), 2 threads. *bare*: the same rays, prepared beforehand, cast by plain embreex "
             "`run(..., 'OCCLUDED')` calls (the ceiling); *kernel*: `pipelines.visibility.visibility_rows` "
             "(ray preparation + Embree + bit packing); *stage*: the whole cached `wavelight visibility` stage "
             "(pixel rays, resumable chunk files, HDF5 assembly, manifest). Ratios are throughput relative to "
             "bare, from medians of interleaved repeats; goal >= 0.9.", "",
             "| image | rays | bare Mrays/s | kernel Mrays/s | stage Mrays/s | kernel/bare | stage/bare | "
             "stage s (min/med/max) | peak RSS MB bare/kernel/stage | file MB |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for scale in (1, 2):
        runs: dict[str, list[dict]] = {"bare": [], "kernel": [], "stage": []}
        for _ in range(repeats):
            for mode in runs:
                runs[mode].append(measure(["--scene", str(SCENE), "--scale", str(scale), "--resolution", "32",
                                           "--mode", mode]))
        med = {m: statistics.median(r["seconds"] for r in runs[m]) for m in runs}
        first = runs["stage"][0]
        rate = {m: first["rays"] / med[m] / 1e6 for m in runs}
        rss = "/".join(f"{max(r['peak_rss_mb'] for r in runs[m]):.0f}" for m in runs)
        lines.append(f"| {first['width']}x{first['height']} | {first['rays'] / 1e6:.1f} M | {rate['bare']:.2f} | "
                     f"{rate['kernel']:.2f} | {rate['stage']:.2f} | {med['bare'] / med['kernel']:.2f} | "
                     f"{med['bare'] / med['stage']:.2f} | {spread([r['seconds'] for r in runs['stage']])} | {rss} | "
                     f"{first.get('file_mb', float('nan')):.1f} |")
        print(lines[-1], flush=True)
    return lines


def solve_section(repeats: int) -> list[str]:
    lines = ["## Light solve (issue 3)", "",
             f"Scene `tests/data/scenes/spot_overcast` (its noisy `image.exr`), white Lambert material, 10 % of "
             "the pixels held out, `--levels auto`. *G pass*: one pass over the pixels building G = T'T and "
             "h = T'b (fit and held-out sets). Each basis' time is everything after it: all levels, the held-out "
             "choice and the final re-solve on all pixels; median of the repeats (each in a fresh process). "
             "Error: relative RMSE of the final light over the held-out pixels (chosen level, before the "
             "re-solve). Goal: the R = 32 wavelet solve (all levels) <= 2 s.", "",
             "| R | texels | pixels | G pass s | wavelet s | quadtree s | discrete s | sh s | sh+ s | points s | "
             "coefficients w/q/d/sh/p | held-out error w/q/d/sh/sh+/p % | peak RSS MB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for R in (8, 16, 32, 64):
        runs = [measure(["--scene", str(SCENE), "--resolution", str(R), "--mode", "bases"], "bench_solve.py")
                for _ in range(repeats if R < 64 else 1)]
        med = {r["basis"]: statistics.median(x["runs"][i]["seconds"] for x in runs)
               for i, r in enumerate(runs[0]["runs"])}
        first = runs[0]
        coef = "/".join(str(r["coefficients"]) for r in first["runs"] if r["basis"] != "sh+")
        err = "/".join(f"{100 * (r['held_out_rmse'] or 0):.2f}" for r in first["runs"])
        g = statistics.median(x["g_pass_seconds"] for x in runs)
        lines.append(f"| {R} | {first['texels']} | {first['pixels']} | {g:.2f} | " +
                     " | ".join(f"{med[b]:.3f}" for b in ("wavelet", "quadtree", "discrete", "sh", "sh+", "points"))
                     + f" | {coef} | {err} | {max(x['peak_rss_mb'] for x in runs):.0f} |")
        print(lines[-1], flush=True)
        if R == 32:
            w = first["runs"][0]
            goal = (f"R = 32 wavelet: {med['wavelet']:.2f} s for all {w['levels']} levels "
                    f"(per level {', '.join(f'{s:.2f}' for s in w['level_seconds'])} s; goal <= 2 s: "
                    f"{'met' if med['wavelet'] <= 2 else 'NOT met'}).")
    lines += ["", goal, ""]
    nn = measure(["--scene", str(SCENE), "--resolution", "16", "--mode", "nnls", "--repeats", str(repeats),
                  "--step", "4"], "bench_solve.py")
    t = {k: statistics.median(v) for k, v in nn["times"].items()}
    lines += [f"NNLS at R = 16 ({nn['texels']} unknowns, every 4th pixel: {nn['pixels']}, one channel, interleaved "
              f"{repeats}x): scipy.optimize.nnls on T {spread(nn['times']['scipy'])} s; ours on G "
              f"{spread(nn['times']['ours_G'], '{:.3f}')} s (**{t['scipy'] / t['ours_G']:.0f}x** faster), "
              f"{spread(nn['times']['ours_with_G'])} s including building G (**{t['scipy'] / t['ours_with_G']:.1f}x**). "
              f"Residual |Tx - b|^2: scipy {nn['objective']['scipy']:.6g}, ours {nn['objective']['ours']:.6g} "
              f"(KKT {nn['objective']['ours_kkt']:.1e})."]
    print(lines[-1], flush=True)
    return lines


def reflectance_section(repeats: int) -> list[str]:
    scene = ROOT / "tests" / "data" / "scenes" / "teapot_sun_phong"
    r = measure(["--scene", str(scene), "--resolution", "32", "--repeats", str(repeats)], "bench_reflectance.py")
    g = r["lambert_g_pass_seconds"]
    lines = ["## Reflectance (issue 4)", "",
             f"Scene `tests/data/scenes/teapot_sun_phong` ({r['width']}x{r['height']}, {r['pixels']} used pixels, "
             f"R = 32: {r['texels']} texels; glossy Blinn-Phong truth ks/kd 0.8, n 30), its noisy `image.exr`, 10 % "
             "held out, the CLI defaults (`--reflectance auto`, start ks 0.25, n 20, kd 1). Baseline: the "
             f"Lambertian normal-equations pass, interleaved with the LM round {repeats}x in the same process.", "",
             "| measurement | min / median / max s | x Lambertian G pass |",
             "|---|---|---|",
             f"| Lambertian G pass (baseline) | {spread(g)} | 1 |",
             f"| one LM round: specular_data ({r['lm_pixels']} pixels x {r['lit_texels']} lit texels) + LM "
             f"({statistics.median(r['lm_evaluations']):.0f} evaluations + n scan) | {spread(r['lm_round_seconds'])} | "
             f"{r['ratio_lm_round_to_g_pass']:.2f} |",
             f"| of which specular_data | {spread(r['specular_data_seconds'])} | |",
             f"| full `auto` alternation ({r['alternation_rounds']} rounds incl. the Lambertian solve and the probe) | "
             f"{r['alternation_seconds']:.1f} | {r['ratio_alternation_to_g_pass']:.1f} |", ""]
    spec = [t for t in r["alternation_light_solves"] if t["model"] != "lambert"]
    if spec:
        lines += [f"Inside the alternation: {len(spec)} specular light solves, each a G pass of "
                  f"{spread([t['g_pass'] for t in spec], '{:.1f}')} s ({spec[-1]['grams']} Gram matrices: a "
                  "coloured kd gives each channel its own) plus the light solve "
                  f"{spread([t['light'] for t in spec])} s; LM rounds {spread(r['alternation_lm_seconds'])} s. "
                  "The G passes are the cost, not the LM.", ""]
    lines += [f"Result: {r['model']}, kd {' '.join(f'{v:.3f}' for v in r['kd'])}, ks {r['ks']:.3f}, n {r['n']:.1f} "
              f"({r['decision']}); relative RMSE by round "
              + ", ".join(f"{100 * e:.2f} %" for e in r["fit_rmse"]) + f". Peak RSS {r['peak_rss_mb']:.0f} MB."]
    print("\n".join(lines), flush=True)
    return lines


SECTIONS = {"visibility": visibility_section, "solve": solve_section, "reflectance": reflectance_section}


def _existing_sections(path: Path) -> dict[str, str]:
    """'## ' sections of an earlier RESULTS.md by their first word after the issue title."""
    if not path.is_file():
        return {}
    parts = path.read_text().split("\n## ")[1:]
    found = {}
    for part in parts:
        title = part.splitlines()[0].lower()
        for name in SECTIONS:
            if name in title:
                found[name] = "## " + part.rstrip() + "\n"
    return found


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", choices=sorted(SECTIONS), action="append",
                    help="Run only this section (repeatable); the others are kept from the existing file.")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "RESULTS.md")
    args = ap.parse_args()
    header = ["# wavelight benchmarks", "",
              f"Generated by `make bench` on {datetime.datetime.now().strftime('%Y-%m-%d %H:%M')} — "
              f"{platform.machine()}, {os.cpu_count()} cores, {platform.platform()}.", "",
              "Versions: " + ", ".join(f"{k} {v}" for k, v in versions().items()) + ".", ""]
    kept = _existing_sections(args.out)
    body = []
    for name, section in SECTIONS.items():
        if args.only and name not in args.only and name in kept:
            body += [kept[name]]
        else:
            body += section(args.repeats) + [""]
    args.out.write_text("\n".join(header + body).rstrip() + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
