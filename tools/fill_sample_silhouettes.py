"""One-off repair of sample_data/spot_sun (kept for the record): the first version of
tools/make_sample_scene.py rendered only the pixels the solver uses at edge_margin 0, so every
silhouette and depth-jump pixel of image.exr was black, a ring no photo has, which pulls the
photo's edges one pixel inwards. This fills those pixels (and only those) with the current forward
model's render (+ the same noise level), leaving every other pixel bit-identical, so that numbers
measured on the sample scene stay comparable. tools/make_sample_scene.py now renders every pixel.

    PYTHONPATH=. .venv/bin/python tools/fill_sample_silhouettes.py --scene sample_data/spot_sun \
        --spot path/to/spot_triangulated.obj --envmap path/to/rooitou_park_1k.hdr
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from pipelines.io import images


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--spot", type=Path, required=True)
    ap.add_argument("--envmap", type=Path, required=True)
    args = ap.parse_args()
    scene = args.scene
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, str(Path(__file__).with_name("make_sample_scene.py")), "--spot", str(args.spot),
                        "--envmap", str(args.envmap), "--out", tmp], check=True, capture_output=True)
        new_clean = images.read_image(Path(tmp) / "truth" / "image_clean.exr").pixels
    old_clean = images.read_image(scene / "truth" / "image_clean.exr").pixels
    old = images.read_image(scene / "image.exr").pixels
    fill = (old_clean.max(axis=2) == 0) & (new_clean.max(axis=2) > 0)
    params = json.loads((scene / "truth" / "scene_params.json").read_text())
    rng = np.random.default_rng(params["seed"] + 1)
    clean = old_clean.copy()
    clean[fill] = new_clean[fill]
    noisy = old.copy()
    noisy[fill] = np.clip(new_clean[fill] + rng.normal(0.0, params["noise_sigma"], new_clean[fill].shape), 0, None)
    images.write_exr(scene / "truth" / "image_clean.exr", clean)
    images.write_exr(scene / "image.exr", noisy.astype(np.float32))
    images.write_png(scene / "image.png", np.clip(noisy, 0, 1), exposure=0.0)
    params["silhouette_pixels_filled"] = int(fill.sum())
    (scene / "truth" / "scene_params.json").write_text(json.dumps(params, indent=1) + "\n")
    print(f"filled {int(fill.sum())} silhouette pixels")


if __name__ == "__main__":
    main()
