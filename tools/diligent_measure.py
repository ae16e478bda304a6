"""Measure today's `wavelight solve` on the DiLiGenT ball photos (tests/photometric.py builds the scenes).

Usage:
    .venv/bin/python tools/diligent_measure.py OUTDIR [--photos 0 1 2 ...] [--solve-args "-R 16"]
        [--no-run]

Per photo: builds OUTDIR/pNN (if missing), runs `wavelight -s OUTDIR/pNN solve SOLVE_ARGS` (unless
--no-run; wavelight's cache skips a finished solve), then reads the results and prints one table row:
  - the angle between the LED direction and solve_report.json's `brightest_direction` (one texel),
  - the angle to the power-weighted centroid of the brightest region (luminance >= half the peak,
    within 30 deg of the peak) of out/light_latlong.exr and of the texel light in out/coefficients.h5,
  - the angle to the direction of the light's whole power vector (sum of power x direction: what a
    Lambertian convex object determines best),
  - the relit error (solve_report.json), what `--reflectance auto` chose (out/reflectance.json),
  - the used pixels whose visibility is zero toward every texel (.wavelight/visibility/photo-R<R>.h5).
Writes OUTDIR/summary.json and OUTDIR/summary.md. (The hit-point / shadow-offset fix that
--patch-hits used to monkeypatch in is now in pipelines/geometry/raycast.py.)
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "tools"))

import photometric as ph  # noqa: E402

region_centroid = ph.region_centroid  # the measures the tests use (tests/photometric.py)
power_direction = ph.power_direction


def latlong_samples(latlong: np.ndarray):
    """(H*W, 3) radiance, directions and solid angles of a lat-long map (README's convention)."""
    from pipelines.light.cubemap import latlong_solid_angles

    H, W = latlong.shape[:2]
    theta = np.pi * (np.arange(H) + 0.5) / H
    phi = 2.0 * np.pi * (np.arange(W) + 0.5) / W
    t, p = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    return latlong.reshape(-1, 3), d, np.asarray(latlong_solid_angles(H, W)).reshape(-1)


def all_shadowed(scene: Path, resolution: int) -> tuple[int, int]:
    from pipelines.io import visibility_file as vis

    data = vis.read_visibility(scene / ".wavelight" / "visibility" / f"photo-R{resolution}.h5")
    zero = 0
    for _, block in data.blocks():
        zero += int(np.count_nonzero(block.sum(axis=1) == 0))
    return zero, data.n_pixels


def measure(scene: Path, led: np.ndarray) -> dict:
    from pipelines.io import images
    from pipelines.io import light_file as lt

    report = json.loads((scene / "out" / "solve_report.json").read_text())
    refl = json.loads((scene / "out" / "reflectance.json").read_text())
    texels, cube, _ = lt.read_solution_light(scene / "out" / "coefficients.h5")
    ll = images.read_latlong(scene / "out" / "light_latlong.exr")
    rad, d, sa = latlong_samples(ll)
    brightest = np.asarray(report["brightest_direction"]["direction"])
    zero, n = all_shadowed(scene, cube.resolution)
    return {
        "scene": scene.name,
        "resolution": cube.resolution,
        "err_brightest_deg": float(ph.angle_deg(brightest, led)),
        "err_latlong_region_deg": float(ph.angle_deg(region_centroid(rad, d, sa), led)),
        "err_texel_region_deg": float(ph.angle_deg(region_centroid(texels, cube.directions, cube.solid_angles), led)),
        "err_power_direction_deg": float(ph.angle_deg(power_direction(texels, cube.directions, cube.solid_angles),
                                                      led)),
        "relit_error": report["relit"]["relative_rmse_vs_photo"],
        "auto_decision": refl["decision"],
        "model": refl["model"],
        "brightest_theta_phi": [report["brightest_direction"]["theta_deg"], report["brightest_direction"]["phi_deg"]],
        "all_shadowed_pixels": zero,
        "used_pixels": n,
        "solve_seconds": report.get("seconds"),
    }


def run_solve(scene: Path, args: list[str]) -> float:
    t0 = time.monotonic()
    cmd = [str(Path(sys.executable).parent / "wavelight"), "-s", str(scene), "solve", *args]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{scene}: solve failed\n{done.stderr[-2000:]}")
    (scene / "solve.log").write_text(done.stderr)
    return time.monotonic() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("outdir", type=Path)
    ap.add_argument("--photos", type=int, nargs="*", default=list(range(16)))
    ap.add_argument("--solve-args", default="")
    ap.add_argument("--no-run", action="store_true")
    a = ap.parse_args(argv)
    view = ph.ball_view()
    leds = ph.light_directions()
    rows = []
    for k in a.photos:
        scene = a.outdir / f"p{k:02d}"
        if not (scene / "pose.json").exists():
            ph.build_ball_scene(scene, k, view=view)
        wall = None if a.no_run else run_solve(scene, shlex.split(a.solve_args))
        row = {"photo": ph.filenames()[k], **measure(scene, leds[k]), "wall_seconds": wall}
        rows.append(row)
        print(f"{row['photo']}: brightest {row['err_brightest_deg']:.1f} deg, region {row['err_latlong_region_deg']:.1f}"
              f" / {row['err_texel_region_deg']:.1f} deg, power {row['err_power_direction_deg']:.1f} deg, relit "
              f"{100 * row['relit_error']:.2f} %, {row['model']}, all-shadowed {row['all_shadowed_pixels']}"
              f"/{row['used_pixels']}" + (f", {wall:.0f} s" if wall else ""), flush=True)
    (a.outdir / "summary.json").write_text(json.dumps(rows, indent=2) + "\n")
    lines = ["| photo | R | brightest texel (deg) | region centroid latlong / texels (deg) | power direction (deg) "
             "| relit error | auto chose | all-shadowed pixels |", "|---|---:|---:|---:|---:|---:|---|---:|"]
    for r in rows:
        lines.append(f"| {r['photo']} | {r['resolution']} | {r['err_brightest_deg']:.1f} | "
                     f"{r['err_latlong_region_deg']:.1f} / {r['err_texel_region_deg']:.1f} | "
                     f"{r['err_power_direction_deg']:.1f} | {100 * r['relit_error']:.2f} % | {r['model']} | "
                     f"{r['all_shadowed_pixels']} / {r['used_pixels']} |")
    med = {k: float(np.median([r[k] for r in rows])) for k in ("err_brightest_deg", "err_latlong_region_deg",
                                                               "err_texel_region_deg", "err_power_direction_deg",
                                                               "relit_error")}
    lines.append(f"| median | | {med['err_brightest_deg']:.1f} | {med['err_latlong_region_deg']:.1f} / "
                 f"{med['err_texel_region_deg']:.1f} | {med['err_power_direction_deg']:.1f} | "
                 f"{100 * med['relit_error']:.2f} % | | |")
    (a.outdir / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
