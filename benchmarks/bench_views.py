"""The cost of several photos and several parts against one: `wavelight solve` on a scene with
views/ and parts (e.g. tests/data/scenes/spot_textured_sun: main + left + right; Spot textured on a
ground of another colour), from an empty cache, each configuration on its own copy of the scene,
interleaved over `--repeats` rounds (same machine load):

    one view, one material   --single-view --single-material
    one view, parts          --single-view
    views, one material      --single-material
    views, parts             (the defaults)

    python benchmarks/bench_views.py SCENE_DIR WORK_DIR [--resolution 32] [--reflectance auto] [--repeats 1]

Prints one JSON line: per configuration the wall times of the whole command (visibility of every
view, solve, outputs), its used pixels, the solve's own time, the sun's angle to the truth's
dominant direction and the probe errors (as bench_e2e.py), and the ratios of the medians to the
one-view, one-material configuration. Not a test: timings depend on the machine.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_e2e import dominant_direction, probe_errors, timed_solve  # noqa: E402


def run(scene: Path, work: Path, tag: str, extra: list[str], resolution: int, reflectance: str) -> dict:
    dst = work / f"{scene.name}-{tag}"
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(scene, dst, ignore=shutil.ignore_patterns(".wavelight", "out"))
    seconds, report = timed_solve(dst, ["-R", str(resolution), "--reflectance", reflectance, *extra])
    truth = dominant_direction(scene)
    c = np.array(report["brightest_direction"]["centroid"]["direction"])
    angle = None if truth is None else float(np.degrees(np.arccos(np.clip(c @ truth, -1, 1))))
    obs = report.get("observability_by_view", {})
    return {"seconds": round(seconds, 2), "solve_seconds": round(report["seconds"], 2),
            "pixels": report["pixels"]["used"], "views": report["options"]["views"],
            "parts": len(report["reflectance"].get("parts") or [None]), "model": report["material"]["model"],
            "held_out": report["held_out"]["mode"], "sun_angle_deg": angle,
            "probes": probe_errors(dst / "out" / "coefficients.h5", scene),
            "weakly_observed_union": obs.get("union", {}).get("weakly_observed"),
            "weakly_observed_main_alone": obs.get("views", {}).get("main", {}).get("weakly_observed")}


CONFIGS = (("one view, one material", "1view-1mat", ["--single-view", "--single-material"]),
           ("one view, parts", "1view-parts", ["--single-view"]),
           ("views, one material", "views-1mat", ["--single-material"]),
           ("views, parts", "views-parts", []))


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("scene", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--reflectance", default="auto")
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    runs: dict = {label: [] for label, _, _ in CONFIGS}
    for _ in range(args.repeats):
        for label, tag, extra in CONFIGS:
            runs[label].append(run(args.scene, args.work, tag, extra, args.resolution, args.reflectance))
    out = {}
    for label, rs in runs.items():
        seconds = sorted(r["seconds"] for r in rs)
        out[label] = {**rs[0], "seconds": seconds, "median_seconds": seconds[len(seconds) // 2]}
    base = out[CONFIGS[0][0]]
    for label in out:
        out[label]["ratio_seconds"] = round(out[label]["median_seconds"] / base["median_seconds"], 2)
        out[label]["ratio_pixels"] = round(out[label]["pixels"] / base["pixels"], 2)
    print(json.dumps({"scene": args.scene.name, "resolution": args.resolution, "reflectance": args.reflectance,
                      "configs": out}))


if __name__ == "__main__":
    main()
