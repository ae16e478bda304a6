"""Add calibration photos to sample_data/spot_sun: synthetic photos of OpenCV's asymmetric circle grid
(4 x 11 dots, spacing 10 mm, i.e. 20 mm between neighbours in a row) taken by the sample scene's camera,
lens distortion included, so that `make demo` calibrates for real.

The true camera and pose live in truth/ (camera.json, pose.json); the scene folder itself has no
camera.json or pose.json: `wavelight calibrate` and `wavelight register` write them.

Run once by a developer:
    PYTHONPATH=. .venv/bin/python tools/make_sample_calibration.py --scene sample_data/spot_sun
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from pipelines.geometry import calibration as cal
from pipelines.io import images

PATTERN = cal.Target("acircles", 4, 11, 0.010)
N_VIEWS = 15
NOISE_LEVELS = 1.0  # 8-bit grey levels
SEED = 20261124


def main():
    import cv2

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", type=Path, required=True)
    args = ap.parse_args()
    scene = args.scene
    truth = scene / "truth"
    for name in ("camera.json", "pose.json"):
        if (scene / name).is_file():
            shutil.move(scene / name, truth / name)
    camera = json.loads((truth / "camera.json").read_text())
    K = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1.0]])
    dist = np.array(camera["dist"], float)
    size = (camera["width"], camera["height"])
    obj = PATTERN.object_points().astype(np.float64)
    centre = obj.mean(axis=0)
    rng = np.random.default_rng(SEED)
    calib = scene / "calib"
    shutil.rmtree(calib, ignore_errors=True)
    calib.mkdir()
    views = []
    while len(views) < N_VIEWS:
        rvec = rng.normal(scale=0.35, size=3)
        z = rng.uniform(0.12, 0.19)
        R, _ = cv2.Rodrigues(rvec)
        tvec = np.array([rng.uniform(-0.3, 0.3) * z, rng.uniform(-0.22, 0.22) * z, z]) - R @ centre
        true = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
        if not np.all((true > 6) & (true < np.array(size) - 7)):
            continue
        img = cal.render_target(PATTERN, K, dist, rvec, tvec, size, noise=NOISE_LEVELS, seed=len(views))
        if cal.detect(img, PATTERN) is None:  # keep views a user would keep (the target found)
            continue
        path = calib / f"view_{len(views):02d}.png"
        images.write_png(path, img[..., None].repeat(3, axis=2) / 255.0, already_display=True)
        views.append({"file": path.name, "rvec": rvec.tolist(), "tvec": tvec.tolist()})
    (truth / "calibration_views.json").write_text(json.dumps(
        {"pattern": "acircles", "pattern_size": [PATTERN.cols, PATTERN.rows], "spacing_m": PATTERN.spacing,
         "noise_grey_levels": NOISE_LEVELS, "seed": SEED, "views": views}, indent=1) + "\n")
    print(f"{len(views)} views in {calib}")


if __name__ == "__main__":
    main()
