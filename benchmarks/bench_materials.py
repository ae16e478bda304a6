"""The reflectance acceptance numbers of one scene (issue 17): a default `wavelight solve` on a copy of
the scene without its truth, then, against the truth:

- the probe spheres (`pipelines.metrics.probe_errors`, the benchmarks' protocol: a matte and a glossy
  unit sphere seen from the photo's camera under the recovered and the true light, scale-invariant);
- the new view: `wavelight relight --view truth/novel_view/pose.json` against that view's image
  over its mask (the fitted material and light as they are);
- the sun's direction (energy centroid of the brightest region against the truth's dominant
  direction), the model `auto` chose, and its parameters (alpha against truth/material.json).

    python benchmarks/bench_materials.py SCENE_DIR WORK_DIR [extra solve options ...]

Prints one JSON line. The solve's wall time is the whole command's (visibility included).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_e2e import dominant_direction, prepare, probe_errors  # noqa: E402


def run(cmd):
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"{' '.join(map(str, cmd))} failed:\n{p.stderr[-3000:]}")
    return time.perf_counter() - t0, p


def main():
    src, work = Path(sys.argv[1]).resolve(), Path(sys.argv[2]).resolve()
    extra = sys.argv[3:]
    scene = prepare(src, work / src.name, 1)
    base = [sys.executable, "-c", "import sys; from wavelight_cli.main import cli; sys.exit(cli())", "-q", "-s",
            str(scene)]
    seconds, _ = run(base + ["solve", *extra])
    report = json.loads((scene / "out" / "solve_report.json").read_text())
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    nv = src / "truth" / "novel_view"
    novel = None
    if nv.is_dir():
        run(base + ["relight", "--view", str(nv / "pose.json"), "--view-camera", str(nv / "camera.json"),
                    "--reference", str(nv / "image.exr"), "--reference-mask", str(nv / "mask.png"), "--name", "novel"])
        novel = json.loads((scene / "out" / "novel.json").read_text()).get("relative_rmse_vs_photo")
    truth_dir = dominant_direction(src)
    centroid = report["brightest_direction"]["centroid"]["direction"]
    sun = None if truth_dir is None else float(np.degrees(np.arccos(np.clip(np.dot(centroid, truth_dir), -1, 1))))
    truth = json.loads((src / "truth" / "material.json").read_text())
    out = {"scene": src.name, "seconds": seconds, "model": refl["model"], "decision": refl.get("decision"),
           "candidates": {k: v.get("held_out_rmse") for k, v in (refl.get("candidates") or {}).items()
                          if isinstance(v, dict)},
           "probes": probe_errors(scene / "out" / "coefficients.h5", src), "novel_view": novel,
           "relit": report["relit"]["relative_rmse_vs_photo"], "held_out": report["solution"]["held_out_rmse"],
           "sun_error_deg": sun, "warnings": report.get("warnings", []), "kd": refl.get("kd"),
           "ks_over_kd": refl.get("ks_over_kd"), "n": refl.get("n"),
           "alpha": refl.get("alpha"), "distribution": refl.get("distribution"),
           "truth": {k: truth.get(k) for k in ("type", "distribution", "alpha", "kd", "ks", "n", "diffuse_reflectance")
                     if k in truth}}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
