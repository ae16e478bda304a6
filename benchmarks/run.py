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
import re
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

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
    goals = []
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
        goals.append((f"{first['width']}x{first['height']}: kernel {med['bare'] / med['kernel']:.2f}x, "
                      f"whole stage {med['bare'] / med['stage']:.2f}x the bare loop", med['bare'] / med['stage']))
    met = all(ratio >= 0.9 for _, ratio in goals)
    lines += ["", f"**Goal** (visibility >= 0.9x a bare embreex loop): {'met' if met else 'NOT met'} — "
              + "; ".join(text for text, _ in goals) + ".", ""]
    return lines


def solve_section(repeats: int) -> list[str]:
    lines = ["## Light solve (issue 3)", "",
             "Scene `tests/data/scenes/spot_overcast` (its noisy `image.exr`), white Lambert material, 10 % of "
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
            goal = (f"**Goal** (the R = 32 wavelet solve, all levels, <= 2 s): "
                    f"{'met' if med['wavelet'] <= 2 else 'NOT met'} — {med['wavelet']:.2f} s for all {w['levels']} "
                    f"levels (per level {', '.join(f'{s:.2f}' for s in w['level_seconds'])} s).")
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


def peer_section(repeats: int) -> list[str]:
    """Mitsuba 3's inverse-rendering loop against wavelight on the Lambertian Mitsuba scenes."""
    lines = ["## Peer: Mitsuba 3 inverse rendering (issue 7)", ""]
    try:
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
    except Exception as exc:  # not installed, or its LLVM variant lacks libLLVM
        return lines + [f"Skipped: Mitsuba 3's llvm_ad_rgb variant is not available ({str(exc).splitlines()[0]}). "
                        "Install it with `pip install mitsuba` (the `bench` extra does) and Debian's LLVM with "
                        "`apt-get install libllvm19`.", ""]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines += ["Same photo, same mesh, the TRUE material on both sides (the peer's best case). Mitsuba "
              f"{mi.__version__}, `llvm_ad_rgb`: a 64 x 32 envmap optimised by Adam (lr = 1.0 x the starting "
              "radiance, the level that matches the photo's mean), `prb` with max_depth 2 (direct light, as the "
              "reference renders), spp 4, 300 iterations, clamped at zero; its scene conversion renders the true "
              "light within 2.4 % of the reference. wavelight: `solve --material truth` at R = 8, 16, 32 (the "
              "whole stage from an empty cache). Light error: relative RMSE of the irradiance (the light after a "
              "cosine blur: what a diffuse scene determines) over 288 upward normals, against the true light. "
              "Image error: relative RMSE against the photo over the mask (Mitsuba: its final light rendered at "
              "256 spp). teapot_sun_phong is left out: Mitsuba has no Blinn-Phong BSDF built in.", "",
              f"Each scene is run {repeats} times (each run: wavelight's three solves, then Mitsuba's loop, in a "
              "fresh process); times are min / median / max over the runs, the errors are those of the first run "
              "(Mitsuba's seeds are fixed; wavelight is deterministic). Mitsuba's curve is placed on the median "
              "time of each iteration.", "",
              "| scene | wavelight R | time s (min / med / max) | light error | image error | Mitsuba best light "
              "error (at s) | Mitsuba final light / image error | Mitsuba 300 iterations s (min / med / max) | "
              "Mitsuba time to wavelight's error | time ratio |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    goals = []
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, name in zip(axes, ("spot_overcast", "bunny_sun")):
        work = ROOT / "build" / "bench_peer" / name
        runs = [measure([str(ROOT / "tests" / "data" / "scenes" / name), str(work)], "bench_mitsuba.py")
                for _ in range(repeats)]
        r = runs[0]
        curve = [[statistics.median(x["mitsuba"]["curve"][i][0] for x in runs), *c[1:]]
                 for i, c in enumerate(r["mitsuba"]["curve"])]
        m_total = [x["mitsuba"]["curve"][-1][0] for x in runs]
        best = min(curve, key=lambda c: c[2])
        final = curve[-1]
        ratios = []
        for i, row in enumerate(r["wavelight"]):
            times = [x["wavelight"][i]["seconds"] for x in runs]
            t = statistics.median(times)
            reach = next((c[0] for c in curve if c[2] <= row["light_err"]), None)
            if row["light_err"] < best[2]:
                ratios.append(((final[0] if reach is None else reach) / t, reach is None))
            lines.append(f"| {name} | {row['R']} | {spread(times, '{:.1f}')} | {100 * row['light_err']:.2f} % | "
                         f"{100 * row['image_err']:.2f} % | {100 * best[2]:.1f} % ({best[0]:.0f} s) | "
                         f"{100 * final[2]:.1f} % / {100 * r['mitsuba']['final_image_err_256spp']:.1f} % | "
                         f"{spread(m_total, '{:.1f}')} | "
                         + (f"{reach:.0f} s | {reach / t:.1f}x |" if reach is not None else
                            f"never (> {final[0]:.0f} s) | > {final[0] / t:.1f}x |"))
        ratio, bound = max(ratios, default=(0.0, False))
        goals.append(f"{name}: {'met' if ratio >= 20 else 'NOT met'} — wavelight's best ratio among its solves "
                     f"below Mitsuba's best light error ({100 * best[2]:.1f} %) is {ratio:.1f}x"
                     + (" (a lower bound: Mitsuba never reached that solve's error)" if bound else ""))
        ax.plot([c[0] for c in curve], [100 * c[2] for c in curve], label="Mitsuba 3 (Adam)")
        ax.plot([statistics.median(x["wavelight"][i]["seconds"] for x in runs) for i in range(len(r["wavelight"]))],
                [100 * w["light_err"] for w in r["wavelight"]], "o-",
                label="wavelight (R = 8, 16, 32)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("seconds")
        ax.set_ylabel("light error (irradiance, %)")
        ax.set_title(name, fontsize=9)
        ax.legend(fontsize=8)
    path = ROOT / "benchmarks" / "peer_mitsuba.png"
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    lines += ["", "![light error against time, both methods](peer_mitsuba.png)", "",
              "Goal (issue 7): a lower light error than the Mitsuba loop at >= 20x less time. The last column is "
              "Mitsuba's time to reach wavelight's light error over wavelight's time (\"never\": not within its "
              "300 iterations, and the ratio is its whole run over wavelight's time).", ""]
    lines += [f"**Goal** (lower light error at >= 20x less time): {g}." for g in goals] + [""]
    return lines


def bases_section(repeats: int) -> list[str]:
    """Speed against error across our bases and the wavelet levels, on each Mitsuba scene."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ("spot_overcast", "bunny_sun", "teapot_sun_phong")
    lines = ["## Bases and levels: speed against error (issue 7)", "",
             f"Each Mitsuba scene at R = 32 with its TRUE material (`solve`, then `compare`, from an empty cache), "
             f"{repeats} runs. Time: the solve after the normal equations (their one pass is given per scene), median "
             "of the runs (the errors do not change between runs). Fit / held-out: relative RMSE over the fitted / "
             "held-out pixels. Light error: relative RMSE of the irradiance (the light after a cosine blur) over 288 "
             "upward normals against the true light; negative SH radiance is clipped first, as a renderer would. "
             "Probes: a unit sphere at the world origin seen from the photo's camera, relit by the recovered light "
             "and by the true light (resampled to a cube of R >= 64), relative RMSE over its disc: *diffuse* "
             "(kd 0.8) and *glossy* (Blinn-Phong kd 0.2, ks 0.8, n 100), the same transport as every solver.", ""]
    fig, axes = plt.subplots(1, len(names), figsize=(5 * len(names), 3.8))
    for ax, name in zip(axes, names):
        runs = [measure([str(ROOT / "tests" / "data" / "scenes" / name), str(ROOT / "build" / "bench_bases")],
                        "bench_bases.py") for _ in range(repeats)]
        r = runs[0]

        def med(kind, i):
            return statistics.median(x[kind][i]["seconds"] for x in runs)

        lines += [f"**{name}**: {r['pixels']['used']} pixels; normal equations "
                  f"{spread([x['normal_equations_seconds'] for x in runs], '{:.1f}')} s; whole solve stage "
                  f"{spread([x['solve_stage_seconds'] for x in runs], '{:.1f}')} s, compare stage "
                  f"{spread([x['compare_stage_seconds'] for x in runs], '{:.1f}')} s (min / median / max).",
                  "", "| basis / level | coefficients | time (s) | fit | held-out | light error | diffuse probe | "
                  "glossy probe |", "|---|---:|---:|---:|---:|---:|---:|---:|"]

        def row(label, x, seconds):
            return (f"| {label} | {x['coefficients']} | {seconds:.3f} | {100 * x['fit_rmse']:.2f} % | "
                    f"{100 * x['held_out_rmse']:.2f} % | {100 * x['light_err']:.2f} % | "
                    f"{100 * x['probe_err']['diffuse']:.2f} % | {100 * x['probe_err']['glossy']:.2f} % |")

        for i, lv in enumerate(r["levels"]):
            lines.append(row(f"wavelet level {lv['level']}", lv, med("levels", i)))
        for i, b in enumerate(r["bases"]):
            lines.append(row(f"**{b['basis']}** (chosen size)", b, med("bases", i)))
        lines.append("")
        ax.plot([med("levels", i) for i in range(len(r["levels"]))],
                [100 * lv["held_out_rmse"] for lv in r["levels"]], "o-", label="wavelet levels")
        for i, b in enumerate(r["bases"]):
            ax.plot(med("bases", i), 100 * b["held_out_rmse"], "s")
            ax.annotate(b["basis"], (med("bases", i), 100 * b["held_out_rmse"]), fontsize=7)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("solve seconds (after the normal equations)")
        ax.set_ylabel("held-out error (%)")
        ax.set_title(name, fontsize=9)
    path = ROOT / "benchmarks" / "bases_speed_error.png"
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    lines += ["![held-out error against solve time](bases_speed_error.png)", ""]
    return lines


def _exponent(x: list[float], y: list[float]) -> float:
    """k of the least-squares fit y = a x^k (log-log)."""
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


SCALING_SCALES = (1, 2, 3)
SCALING_RESOLUTIONS = (8, 16, 32, 64)


def scaling_section(repeats: int) -> list[str]:
    """How visibility, the G pass and the solves grow with pixel count and texel count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pixel_sweep = [(scale, 16) for scale in SCALING_SCALES]
    texel_sweep = [(1, R) for R in SCALING_RESOLUTIONS]
    configs = list(dict.fromkeys(pixel_sweep + texel_sweep))
    runs: dict[tuple, list[dict]] = {c: [] for c in configs}
    for i in range(repeats):  # interleaved: machine noise hits every configuration alike
        for scale, R in configs:
            if i and (R >= 64 or scale >= 3):  # the two largest are measured once (minutes each)
                continue
            runs[scale, R].append(measure(["--scene", str(SCENE), "--scale", str(scale), "--resolution", str(R)],
                                          "bench_scaling.py"))
    stages = ("visibility", "g_pass", "solve_wavelet", "solve_discrete", "solve_sh")

    def med(c, st):
        vals = [r["stages"][st]["seconds"] for r in runs[c] if st in r["stages"]]
        return statistics.median(vals) if vals else None

    lines = ["## Scaling (issue 7)", "",
             f"Scene `tests/data/scenes/spot_overcast`, camera scaled by 1, 2, 3 (each pixel split into scale x scale, "
             "photo and mask repeated: the same problem sampled more densely) at R = 16, and R = 8 ... 64 at scale 1. "
             "Each configuration in a fresh process (`benchmarks/bench_scaling.py`): visibility (2 threads), the G pass "
             "(normal equations, white Lambert), then the solves on G alone: wavelet (all levels), discrete (R <= 32) "
             f"and 9 SH. Times are min / median / max over {repeats} interleaved runs (scale 3 and R = 64: one run). "
             "Peak memory: the process' resident set sampled every 5 ms during each stage.", "",
             "| scale | pixels | R | texels | visibility s | G pass s | wavelet s | discrete s | SH s | "
             "peak RSS MB vis / G / solves | V in memory MB |",
             "|---|---:|---:|---:|---|---|---|---|---|---|---:|"]
    for c in sorted(configs, key=lambda c: (c[1], c[0])):
        r = runs[c][0]

        def cell(st):
            vals = [x["stages"][st]["seconds"] for x in runs[c] if st in x["stages"]]
            return spread(vals, "{:.3g}") if vals else "—"

        rss = " / ".join(f"{max(x['stages'][st]['peak_rss_mb'] for x in runs[c]):.0f}"
                         for st in ("visibility", "g_pass", "solve_wavelet"))
        lines.append(f"| {c[0]} | {r['pixels']} | {c[1]} | {r['texels']} | " + " | ".join(cell(st) for st in stages)
                     + f" | {rss} | {r['visibility_mb']:.1f} |")
        print(lines[-1], flush=True)
    px = [runs[c][0]["pixels"] for c in pixel_sweep]
    tx = [runs[c][0]["texels"] for c in texel_sweep]
    fits = []
    for st, label in zip(stages, ("visibility", "G pass", "wavelet solve", "discrete solve", "SH solve")):
        kp = _exponent(px, [med(c, st) for c in pixel_sweep])
        pairs = [(t, med(c, st)) for t, c in zip(tx, texel_sweep) if med(c, st) is not None]
        kt = _exponent([a for a, _ in pairs], [b for _, b in pairs])
        fits.append((label, kp, kt))
    lines += ["", "Fitted exponents, time ∝ pixels^a (R = 16) and time ∝ texels^b (scale 1); "
              "expected: visibility a = 1, b = 1; G pass a = 1, b = 2 (a dense T'T); solves a = 0.", "",
              "| stage | a (pixels) | b (texels) |", "|---|---:|---:|"]
    lines += [f"| {label} | {kp:.2f} | {kt:.2f} |" for label, kp, kt in fits]
    k = fits[2][1]
    spread_px = [med(c, "solve_wavelet") for c in pixel_sweep]
    lines += ["", f"**Goal** (solve time after the G pass independent of the pixel count): "
              f"{'met' if abs(k) <= 0.1 else 'NOT met'} — the wavelet solve's exponent in pixels is {k:.2f} "
              f"(criterion |a| <= 0.1), its median time {min(spread_px):.3f} ... {max(spread_px):.3f} s over "
              f"{min(px)} ... {max(px)} pixels ({max(px) / min(px):.1f}x).", ""]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for st, label, _ in zip(stages, ("visibility", "G pass", "wavelet", "discrete", "SH"), stages):
        ax_p = [(p, med(c, st)) for p, c in zip(px, pixel_sweep) if med(c, st) is not None]
        ax_t = [(t, med(c, st)) for t, c in zip(tx, texel_sweep) if med(c, st) is not None]
        axes[0].plot(*zip(*ax_p), "o-", label=label)
        axes[1].plot(*zip(*ax_t), "o-", label=label)
    for ax, xl in zip(axes, ("used pixels (R = 16)", "texels (scale 1)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xl)
        ax.set_ylabel("seconds (median)")
        ax.legend(fontsize=7)
    fig.savefig(ROOT / "benchmarks" / "scaling.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    lines += ["![stage time against pixels and texels](scaling.png)", ""]
    return lines



E2E_CONFIGS = [("spot_sun", 1, 32), ("spot_overcast", 1, 32), ("bunny_sun", 1, 32), ("teapot_sun_phong", 1, 32),
               ("spot_overcast", 2, 32), ("bunny_sun", 2, 32), ("spot_overcast", 1, 64), ("bunny_sun", 1, 64)]


def _scene_dir(name: str) -> Path:
    return ROOT / "sample_data" / name if name == "spot_sun" else ROOT / "tests" / "data" / "scenes" / name


def e2e_section(repeats: int) -> list[str]:
    """The whole `wavelight solve` with its defaults, from an empty cache (issue 15)."""
    work = ROOT / "build" / "bench_e2e"
    fast: dict = {c: [] for c in E2E_CONFIGS}
    for _ in range(repeats):  # interleaved: every configuration once per round
        for c in E2E_CONFIGS:
            name, scale, R = c
            args = [str(_scene_dir(name)), str(work), "--scale", str(scale), "--resolution", str(R)]
            fast[c].append(measure(args, "bench_e2e.py"))
            print(f"e2e {c}: {fast[c][-1]['seconds']:.2f} s", flush=True)
    exact = {}
    for name in ("spot_sun", "spot_overcast", "bunny_sun", "teapot_sun_phong"):
        exact[name] = measure([str(_scene_dir(name)), str(work), "--exact"], "bench_e2e.py")
        print(f"e2e exact {name}: {exact[name]['seconds']:.1f} s", flush=True)
    peer = {}
    try:
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
        for name in ("spot_overcast", "bunny_sun"):
            peer[name] = measure([str(_scene_dir(name)), str(work / "peer" / name), "--skip-wavelight"],
                                 "bench_mitsuba.py")["mitsuba"]
    except Exception as exc:  # not installed, or its LLVM variant lacks libLLVM
        peer_note = f"the peer was not run: Mitsuba 3's llvm_ad_rgb variant is not available ({str(exc).splitlines()[0]})"
    else:
        peer_note = ""
    med = {c: statistics.median(r["seconds"] for r in runs) for c, runs in fast.items()}

    def pct(x):
        return "-" if x is None else f"{100 * x:.2f} %"

    lines = ["## Whole solve, defaults, from an empty cache (e2e, issue 15)", "",
             "`wavelight -s SCENE solve` (R = 32, `--levels auto`, `--reflectance auto`, adaptive visibility, the "
             "weighted pixel sample) on a copy of each scene without its truth, in a fresh process, from an empty "
             "cache: the whole command's wall time (process start, visibility, the solve, every output) and its "
             f"peak resident memory. {repeats} runs per configuration, interleaved; min / median / max. "
             "*exact*: the same command with `--exact` (every shadow ray, dense normal equations over every pixel: "
             "the route before this one), once. x2: the camera scaled to 640 x 480 (photo and mask repeated 2 x 2). "
             "Probe errors: a matte and a glossy sphere relit by the recovered and by the true light "
             "(scale-invariant). Sun: angle of the brightest region's energy centroid to the truth's dominant "
             "direction.", "",
             "| scene | size | R | seconds (min / med / max) | peak MB | held-out | probes matte / glossy | sun | "
             "reflectance | exact: seconds | exact: held-out | exact: probes | exact: sun | exact: reflectance |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def refl(r):
        if r["model"] == "lambert":
            return "lambert"
        return f"{r['model']} ks/kd {r['ks_over_kd']:.3f}, n {r['n']:.1f}"

    def probes(r):
        return "-" if not r.get("probes") else f"{pct(r['probes']['diffuse'])} / {pct(r['probes']['glossy'])}"

    def sun(r):
        return "-" if r.get("sun_error_deg") is None else f"{r['sun_error_deg']:.2f} deg"

    for c in E2E_CONFIGS:
        name, scale, R = c
        runs, first = fast[c], fast[c][0]
        e = exact.get(name) if scale == 1 and R == 32 else None
        size = f"{320 * scale}x{240 * scale}" if name != "spot_sun" else "192x144"
        lines.append(f"| {name} | {size} | {R} | {spread([r['seconds'] for r in runs])} | "
                     f"{max(r['peak_rss_mb'] for r in runs):.0f} | {pct(first['held_out'])} | {probes(first)} | "
                     f"{sun(first)} | {refl(first)} | "
                     + (f"{e['seconds']:.1f} | {pct(e['held_out'])} | {probes(e)} | {sun(e)} | {refl(e)} |" if e else
                        "| | | | |"))
    goals = []
    lam = [("spot_sun", 1, 32), ("spot_overcast", 1, 32), ("bunny_sun", 1, 32)]
    worst = max(med[c] for c in lam)
    goals.append((f"320x240 Lambertian scenes <= 3 s (aim 1.5 s): {'met' if worst <= 3 else 'NOT met'} — medians "
                  + ", ".join(f"{c[0]} {med[c]:.2f} s" for c in lam)))
    for name in ("spot_overcast", "bunny_sun"):
        if name in peer:
            t_peer = peer[name]["curve"][-1][0]
            ratio = t_peer / med[(name, 1, 32)]
            goals.append(f"{name} >= 10x faster than the Mitsuba peer in the same run: {'met' if ratio >= 10 else 'NOT met'}"
                         f" — {ratio:.1f}x ({t_peer:.0f} s for its 300 iterations, best light error "
                         f"{100 * min(x[2] for x in peer[name]['curve']):.1f} %, against wavelight's median "
                         f"{med[(name, 1, 32)]:.2f} s)")
    t = med[("teapot_sun_phong", 1, 32)]
    goals.append(f"teapot_sun_phong (glossy, auto) <= 10 s: {'met' if t <= 10 else 'NOT met'} — {t:.2f} s")
    for name in ("spot_overcast", "bunny_sun"):
        ratio = med[(name, 2, 32)] / med[(name, 1, 32)]
        goals.append(f"{name} at 640x480 <= 1.5x its 320x240 time: {'met' if ratio <= 1.5 else 'NOT met'} — "
                     f"{ratio:.2f}x ({med[(name, 2, 32)]:.2f} s)")
        ratio64 = med[(name, 1, 64)] / med[(name, 1, 32)]
        peak64 = max(r["peak_rss_mb"] for r in fast[(name, 1, 64)])
        goals.append(f"{name} at R = 64 <= 4 GB and <= 4x the R = 32 time: "
                     f"{'met' if ratio64 <= 4 and peak64 <= 4096 else 'NOT met'} — {ratio64:.2f}x, {peak64:.0f} MB")
    peak32 = max(r["peak_rss_mb"] for c in E2E_CONFIGS if c[2] == 32 for r in fast[c])
    goals.append(f"peak memory <= 1 GB at R = 32: {'met' if peak32 <= 1024 else 'NOT met'} — {peak32:.0f} MB")
    acc = []
    for name, e in exact.items():
        f = fast[(name, 1, 32)][0]
        ok_held = f["held_out"] <= 1.05 * e["held_out"]
        ok_probe = all(f["probes"][k] <= 1.10 * e["probes"][k] for k in f["probes"]) if f.get("probes") and e.get("probes") else True
        angle = float(np.degrees(np.arccos(np.clip(np.dot(f["brightest"], e["brightest"]), -1, 1))))
        ok_sun = angle <= 1.0 if f.get("sun_error_deg") is not None else True
        ok_refl = True
        if e["model"] != "lambert" or f["model"] != "lambert":
            ok_refl = (f["model"] == e["model"] and abs(f["ks_over_kd"] / e["ks_over_kd"] - 1) <= 0.05
                       and abs(f["n"] / e["n"] - 1) <= 0.05)
        acc.append((name, ok_held and ok_probe and ok_sun and ok_refl,
                    f"{name}: held-out {100 * (f['held_out'] / e['held_out'] - 1):+.1f} %"
                    + ("" if not f.get("probes") or not e.get("probes") else
                       f", probes {100 * (f['probes']['diffuse'] / e['probes']['diffuse'] - 1):+.1f} % / "
                       f"{100 * (f['probes']['glossy'] / e['probes']['glossy'] - 1):+.1f} %")
                    + (f", sun {angle:.2f} deg from exact's" if f.get("sun_error_deg") is not None else "")
                    + ("" if e["model"] == "lambert" and f["model"] == "lambert" else
                       f", ks/kd {100 * (f['ks_over_kd'] / e['ks_over_kd'] - 1):+.1f} %, n {100 * (f['n'] / e['n'] - 1):+.1f} %")))
    goals.append(f"accuracy no worse than the exact route (held-out within 5 %, probes within 10 %, sun within 1 deg, "
                 f"ks and n within 5 %): {'met' if all(a[1] for a in acc) else 'NOT met'} — " + "; ".join(a[2] for a in acc))
    lines += [""] + ([f"Note: {peer_note}.", ""] if peer_note else [])
    lines += [f"**Goal** {g}." for g in goals] + [""]
    return lines

MATERIAL_SCENES = (("bunny_plastic_overcast", "plastic"), ("spot_plastic_sun", "plastic"),
                   ("suzanne_plastic_sun", "plastic"), ("teapot_plastic_sun", "plastic"),
                   ("teapot_smoothplastic_overcast", "plastic"), ("teapot_sun_phong", "blinn-phong"),
                   ("bunny_sun", "lambert"))  # (scene, the model auto must choose)


def materials_section(repeats: int) -> list[str]:
    """Issue 17's acceptance table: `bench_materials.py` (a default solve, then the probes, the new
    view, the sun and the fitted material against the truth) on the five Mitsuba roughplastic /
    plastic scenes and two controls, once each (~15 min on 2 cores: the errors do not vary between
    runs, the times are single runs), and again at the R its warning names for a scene whose fitted
    lobe is narrower than a texel under a sun (`controllers.solve.narrow_lobe_note`: ~2.5 min more)."""
    import re
    import tempfile

    goals = {"auto": [], "diffuse": [], "glossy": [], "novel": [], "alpha": []}
    lines = ["## Glossy materials: acceptance (issue 17)", "",
             "`benchmarks/bench_materials.py` per scene: `wavelight solve` with nothing given but the inputs "
             "(photo, mesh, camera, pose; `--reflectance auto`, R = 32), then against the truth: the probe "
             "spheres (matte and glossy, scale-invariant relative RMSE, `pipelines.metrics.probe_errors`), the "
             "new view (`wavelight relight --view truth/novel_view`, relative RMSE over its mask), the sun "
             "(energy centroid of the brightest region against the truth's brightest 1 %), the model `auto` "
             "chose and alpha against truth/material.json. Goals: diffuse probe <= 2 %, glossy <= 5 %, new view "
             "<= 5 %, alpha within 15 % (smooth truth: alpha <= 0.02, below what R = 32 resolves), auto right on every "
             "scene (controls keep theirs). One run each; solve "
             "s is the whole `solve` command (visibility included). A scene whose solve warns that its lobe is "
             "narrower than a texel under a sun gets a second row, solved again at the R the warning names "
             "(what a user who follows it gets; not counted in the goals).", "",
             "| scene | truth | auto chose | diffuse probe | glossy probe | new view | sun error | alpha (truth) | "
             "solve s |", "|---|---|---|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory(prefix="wavelight-materials-") as work:
        runs = []
        for name, expected in MATERIAL_SCENES:
            r = measure([str(ROOT / "tests" / "data" / "scenes" / name), work], "bench_materials.py")
            runs.append((name, expected, r, True))
            advice = [m for w in r.get("warnings", []) if "narrower than a texel" in w
                      for m in re.findall(r"-R (\d+)", w)]
            if advice:
                again = measure([str(ROOT / "tests" / "data" / "scenes" / name), work, "-R", advice[0]],
                                "bench_materials.py")
                runs.append((f"{name}, -R {advice[0]} (its warning's advice)", expected, again, False))
        for name, expected, r, counted in runs:
            t = r["truth"]
            smooth = t.get("type") == "plastic"
            t_alpha = 0.0 if smooth else t.get("alpha")
            truth = " ".join(str(x) for x in (t.get("type", "?"), t.get("distribution"),
                                              None if t_alpha is None else f"alpha {t_alpha:g}") if x)
            chosen = r["model"] + (f" {r['distribution']}" if r.get("distribution") else "")
            ok_model = r["model"] == expected
            if counted:
                goals["auto"].append((name, ok_model))
            if r.get("alpha") is not None:
                a = r["alpha"]
                if t_alpha:
                    within = abs(a / t_alpha - 1) <= 0.15
                    alpha = f"{a:.3f} ({t_alpha:g}, {100 * (a / t_alpha - 1):+.0f} %)"
                else:
                    within = a <= 0.02  # smooth: below what R = 32 resolves (the texel blur alone is ~0.016)
                    alpha = f"{a:.3f} (smooth)"
            else:
                within = None
                alpha = f"n {r['n']:.1f}" if r.get("n") and r["model"] != "lambert" else "-"
            pr, nv, sun = r["probes"], r["novel_view"], r["sun_error_deg"]
            if expected == "plastic" and counted:
                goals["diffuse"].append((name, pr["diffuse"] <= 0.02))
                goals["glossy"].append((name, pr["glossy"] <= 0.05))
                goals["novel"].append((name, nv is not None and nv <= 0.05))
                goals["alpha"].append((name, bool(within)))
            lines.append(f"| {name} | {truth} | {chosen}{'' if ok_model else ' (wrong)'} | {100 * pr['diffuse']:.2f} % | "
                         f"{100 * pr['glossy']:.2f} % | {'-' if nv is None else f'{100 * nv:.2f} %'} | "
                         f"{'-' if sun is None else f'{sun:.2f} deg'} | {alpha} | {r['seconds']:.0f} |")
            print(lines[-1], flush=True)
    lines.append("")

    def goal(text, key):
        bad = [n for n, ok in goals[key] if not ok]
        return (f"**Goal** {text}: " + ("met" if not bad else f"NOT met ({', '.join(bad)})") +
                f" — {len(goals[key]) - len(bad)} of {len(goals[key])} scenes.")

    lines += [goal("auto chooses the truth's model (plastic scenes: plastic; controls keep theirs)", "auto"),
              goal("plastic scenes: diffuse probe <= 2 %", "diffuse"), goal("plastic scenes: glossy probe <= 5 %", "glossy"),
              goal("plastic scenes: new view <= 5 %", "novel"), goal("plastic scenes: alpha within 15 % of the truth", "alpha"),
              ""]
    return lines


VIEW_SCENES = ("spot_textured_sun", "spot_textured_overcast")  # main + left + right; Spot textured on a coloured ground


def views_section(repeats: int) -> list[str]:
    """Parts and views: cost against one (issue 19): `bench_views.py` on the textured Mitsuba scenes."""
    import tempfile

    lines = ["## Parts and views: cost against one (issue 19)", "",
             "`benchmarks/bench_views.py` per scene: the whole `wavelight -s SCENE solve` (defaults: R = 32, "
             "`--reflectance auto`), from an empty cache, in four configurations on copies of the scene, "
             f"interleaved, {repeats} run(s) each: the main photo alone with one uniform material "
             "(`--single-view --single-material`), the main photo with the mesh's parts and Spot's texture "
             "(`--single-view`), the three photos with one material (`--single-material`) and the three with "
             "parts (the defaults). Time ratios against the first configuration; probe errors as the e2e "
             "section's (scale-invariant, against the true light).", "",
             "| scene | configuration | views | parts | pixels | seconds (min / med / max) | ratio (pixels) | "
             "per view s | model | probes matte / glossy | sun |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    goals = []
    with tempfile.TemporaryDirectory(prefix="wavelight-views-") as work:
        for name in VIEW_SCENES:
            r = measure([str(ROOT / "tests" / "data" / "scenes" / name), work, "--repeats", str(repeats)],
                        "bench_views.py")
            for label, c in r["configs"].items():
                per_view = c["median_seconds"] / len(c["views"])
                p = c.get("probes") or {}
                probes = "-" if not p else f"{100 * p['diffuse']:.2f} % / {100 * p['glossy']:.2f} %"
                sun = "-" if c.get("sun_angle_deg") is None else f"{c['sun_angle_deg']:.2f} deg"
                lines.append(f"| {name} | {label} | {len(c['views'])} | {c['parts']} | {c['pixels']} | "
                             f"{spread(c['seconds'])} | {c['ratio_seconds']:.2f}x ({c['ratio_pixels']:.2f}x) | "
                             f"{per_view:.1f} | {c['model']} | {probes} | {sun} |")
                if label == "views, parts":
                    goals.append((name, per_view))
            print(f"views {name}: " + ", ".join(f"{k} {v['median_seconds']:.1f} s" for k, v in r["configs"].items()),
                  flush=True)
    worst = max(p for _, p in goals)
    lines += ["", f"**Goal** (the speed issue's 320x240 goal per view: <= 3 s of the whole command per view): "
                  f"{'met' if worst <= 3.0 else 'NOT met'} — views with parts: "
                  + ", ".join(f"{n} {p:.1f} s per view" for n, p in goals) + "."]
    return lines


ROBUST_SCENES = ("bunny_sun", "teapot_sun_phong")  # a Lambertian and a glossy Mitsuba scene


def robust_section(repeats: int) -> list[str]:
    """Robust fit: what it costs on a clean photo and buys on a spoiled one (issue 17, item 4)."""
    import tempfile

    lines = ["## Robust fit: what it costs on a clean photo and buys on a spoiled one (issue 17)", "",
             "`benchmarks/bench_robust.py` per scene: the whole `wavelight -s SCENE solve` (defaults: R = 32, "
             "`--reflectance auto`), from an empty cache, on the photo as it is and with 2 % of its masked pixels "
             "spoiled (dark specks and bright glints in 3 x 3 blobs, a fixed seed), each with the robust pass (the "
             f"default) and with `--no-robust`, interleaved, {repeats} run(s) each. Probe errors as the e2e "
             "section's (scale-invariant, against the true light); the sun's angle to the truth's dominant "
             "direction.", "",
             "| scene | photo | robust pass | seconds (min / med / max) | time vs plain | model | probes matte / glossy "
             "| sun | rounds | down-weighted pixels |", "|---|---|---|---|---|---|---|---|---|---|"]
    overhead, recovered = [], []
    with tempfile.TemporaryDirectory(prefix="wavelight-robust-") as work:
        for name in ROBUST_SCENES:
            r = measure([str(ROOT / "tests" / "data" / "scenes" / name), work, "--repeats", str(repeats)],
                        "bench_robust.py")
            c = r["configs"]
            for label, v in c.items():
                photo, mode = label.split(", ")
                p = v["probes"]
                sun = "-" if v.get("sun_angle_deg") is None else f"{v['sun_angle_deg']:.2f} deg"
                ratio = f"{v['ratio_seconds']:.2f}x" if "ratio_seconds" in v else "1"
                lines.append(f"| {name} | {photo} | {'yes' if mode == 'robust' else 'no (`--no-robust`)'} | "
                             f"{spread(v['seconds'])} | {ratio} | {v['model']} | {100 * p['diffuse']:.2f} % / "
                             f"{100 * p['glossy']:.2f} % | {sun} | {v['robust_rounds'] if mode == 'robust' else '-'} "
                             f"| {v['down_weighted_pixels'] if mode == 'robust' else '-'} |")
            overhead.append((name, c["clean, robust"]["ratio_seconds"]))
            clean, fixed = c["clean, robust"]["probes"]["diffuse"], c["spoiled, robust"]["probes"]["diffuse"]
            recovered.append((name, fixed / clean))
            print(f"robust {name}: " + ", ".join(f"{k} {v['median_seconds']:.1f} s" for k, v in c.items()), flush=True)
    worst_cost, worst_probe = max(o for _, o in overhead), max(p for _, p in recovered)
    lines += ["", f"**Goal** (robust fit: <= 5 % more time on a clean photo, and on a 2 % spoiled one a matte probe "
                  f"within 1.5x of the clean photo's): {'met' if worst_cost <= 1.05 and worst_probe <= 1.5 else 'NOT met'}"
                  " — time on the clean photo " + ", ".join(f"{n} {o:.2f}x" for n, o in overhead)
                  + "; spoiled / clean matte probe " + ", ".join(f"{n} {p:.2f}x" for n, p in recovered) + "."]
    return lines


SECTIONS = {"visibility": visibility_section, "solve": solve_section, "reflectance": reflectance_section,
            "peer": peer_section, "bases": bases_section, "scaling": scaling_section, "e2e": e2e_section,
            "materials": materials_section, "views": views_section, "robust": robust_section}


TITLES = {"visibility": "Visibility throughput", "solve": "Light solve", "reflectance": "Reflectance (",
          "peer": "Peer:", "bases": "Bases and levels", "scaling": "Scaling", "e2e": "Whole solve",
          "materials": "Glossy materials", "views": "Parts and views", "robust": "Robust fit"}  # how each section's heading starts (its function's first line)


def _existing_sections(path: Path) -> dict[str, str]:
    """'## ' sections of an earlier RESULTS.md by how their heading starts (`TITLES`: "solve" must
    not take "Whole solve", the e2e section's heading)."""
    if not path.is_file():
        return {}
    parts = path.read_text().split("\n## ")[1:]
    found = {}
    for part in parts:
        title = part.splitlines()[0]
        for name, start in TITLES.items():
            if title.startswith(start):
                found[name] = "## " + part.rstrip() + "\n"
    return found


NOT_RERUN = re.compile(r"\*Not rerun by this run \(`--only`\): measured by the run of ([^.]*)\.\*\n*")


def _not_rerun(rest: str, previous: str) -> str:
    """A kept section's text under one line that says when it was measured: the date it already
    carries (kept by an earlier --only run: its oldest such line, the run that measured it), else
    the previous file's date."""
    dates = NOT_RERUN.findall(rest)
    when = dates[-1] if dates else previous
    return f"*Not rerun by this run (`--only`): measured by the run of {when}.*\n\n" + NOT_RERUN.sub("", rest).lstrip("\n")


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
    load_start = os.getloadavg()
    kept = _existing_sections(args.out)
    old = args.out.read_text().split("Generated by `make bench` on ")[1].split(" — ")[0] if kept else "?"
    body = []
    for name, section in SECTIONS.items():
        if args.only and name not in args.only and name in kept:
            title, _, rest = kept[name].partition("\n")
            body += [f"{title}\n\n{_not_rerun(rest, old)}"]
        else:
            body += section(args.repeats) + [""]
    goals = [line for part in body for line in part.splitlines() if line.startswith("**Goal**")]
    load_end = os.getloadavg()
    header += [f"Load average (1 / 5 / 15 min) at the start {' / '.join(f'{x:.1f}' for x in load_start)}, at the end "
               f"{' / '.join(f'{x:.1f}' for x in load_end)} (a value above the 2 cores means other work shared the "
               "machine: absolute times are inflated; the ratios, measured interleaved, much less).", ""]
    summary = ["## Goals tracked", "", "Each line is repeated from its section below (a section not rerun by this "
               "run says when it was measured).", ""]
    summary += [f"- {g[len('**Goal** '):]}" for g in goals] + [""]
    args.out.write_text("\n".join(header + summary + body).rstrip() + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
