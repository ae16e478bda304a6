"""What the robust pass costs and buys: `wavelight solve` on a scene's photo as it is and with 2 % of
its used pixels spoiled (dark specks and bright glints, 3 x 3 blobs, a fixed seed), each with the
defaults (the robust pass) and with `--no-robust`, from an empty cache, interleaved over `--repeats`
rounds (same machine load):

    python benchmarks/bench_robust.py SCENE_DIR WORK_DIR [--resolution 32] [--share 0.02] [--repeats 1]

Prints one JSON line: per configuration the wall times of the whole command, the probe errors and
the sun's angle to the truth (as bench_e2e.py), the robust pass's rounds and down-weighted pixels,
and the ratio of the robust run's median time to the plain one's on the same photo. Not a test:
timings depend on the machine.
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
from pipelines.io import images  # noqa: E402


def spoil(scene: Path, share: float, seed: int = 1) -> int:
    """Dark specks (0.05 x the mean) and bright glints (8 x) in 3 x 3 blobs over `share` of the
    pixels of mask.png; returns how many blobs."""
    img = images.read_image(scene / "image.exr").pixels.copy()
    ys, xs = np.nonzero(images.read_mask(scene / "mask.png") > 0)
    rng = np.random.default_rng(seed)
    mean = float(img[ys, xs].mean())
    pick = rng.choice(len(ys), int(share * len(ys) / 9), replace=False)
    for k, i in enumerate(pick):
        img[max(ys[i] - 1, 0):ys[i] + 2, max(xs[i] - 1, 0):xs[i] + 2] = 0.05 * mean if k % 2 else 8.0 * mean
    images.write_exr(scene / "image.exr", img)
    return len(pick)


def run(source: Path, truth: Path, work: Path, tag: str, extra: list[str], resolution: int) -> dict:
    dst = work / tag
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(source, dst, ignore=shutil.ignore_patterns(".wavelight", "out"))
    seconds, report = timed_solve(dst, ["-R", str(resolution), *extra])
    sun = dominant_direction(truth)
    c = np.array(report["brightest_direction"]["centroid"]["direction"])
    rob = report.get("robust", {})
    return {"seconds": round(seconds, 2), "model": report["material"]["model"],
            "relit": report["relit"]["relative_rmse_vs_photo"],
            "sun_angle_deg": None if sun is None else float(np.degrees(np.arccos(np.clip(c @ sun, -1, 1)))),
            "probes": probe_errors(dst / "out" / "coefficients.h5", truth),
            "robust_rounds": rob.get("rounds"), "down_weighted_pixels": rob.get("down_weighted_pixels"),
            "pixels": report["pixels"]["used"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("scene", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--share", type=float, default=0.02)
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    spoiled = args.work / "spoiled-source"
    shutil.rmtree(spoiled, ignore_errors=True)
    shutil.copytree(args.scene, spoiled, ignore=shutil.ignore_patterns(".wavelight", "out"))
    blobs = spoil(spoiled, args.share)
    configs = [("clean, plain", args.scene, ["--no-robust"]), ("clean, robust", args.scene, []),
               ("spoiled, plain", spoiled, ["--no-robust"]), ("spoiled, robust", spoiled, [])]
    runs: dict = {label: [] for label, _, _ in configs}
    for _ in range(args.repeats):
        for k, (label, source, extra) in enumerate(configs):
            runs[label].append(run(source, args.scene, args.work, f"c{k}", extra, args.resolution))
    out = {}
    for label, rs in runs.items():
        seconds = sorted(r["seconds"] for r in rs)
        out[label] = {**rs[0], "seconds": seconds, "median_seconds": seconds[len(seconds) // 2]}
    for photo in ("clean", "spoiled"):
        out[f"{photo}, robust"]["ratio_seconds"] = round(
            out[f"{photo}, robust"]["median_seconds"] / out[f"{photo}, plain"]["median_seconds"], 3)
    print(json.dumps({"scene": args.scene.name, "resolution": args.resolution, "share": args.share,
                      "blobs": blobs, "configs": out}))


if __name__ == "__main__":
    main()
