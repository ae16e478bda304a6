"""Writing a stage's results: lights in the exchange format and as previews, heat maps, JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipelines.io.files import atomic_output


def write_json(path: Path, data) -> Path:
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(jsonable(data), indent=1, sort_keys=False) + "\n")
    return Path(path)


def jsonable(value):
    """numpy scalars and arrays as plain JSON values (non-finite numbers as null)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if np.isfinite(v) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def write_light(out_dir: Path, stem: str, texels: np.ndarray, cube, height: int | None = None,
                unobservable: np.ndarray | None = None) -> list[Path]:
    """A cube-map light as <stem>_latlong.exr (exchange format), <stem>_cross.exr and a preview PNG
    of the cross (texels outside the layout dark grey, unobservable texels dark magenta)."""
    from pipelines.io import images
    from pipelines.light import cubemap

    height = height or max(64, 2 * cube.resolution)
    paths = [out_dir / f"{stem}_latlong.exr", out_dir / f"{stem}_cross.exr", out_dir / f"{stem}_cross.png"]
    images.write_exr(paths[0], cubemap.cube_to_latlong(texels, cube, height))
    cross, valid = cubemap.cross_image(texels, cube)
    images.write_exr(paths[1], cross)
    preview = images.tonemap(cross)
    preview[~valid] = 0.15
    if unobservable is not None and np.any(unobservable):
        marked, _ = cubemap.cross_image(np.asarray(unobservable, np.float64), cube)
        preview[marked > 0.5] = (0.35, 0.0, 0.35)
    images.write_png(paths[2], upscale(preview), already_display=True)
    return paths


def upscale(image: np.ndarray, width: int = 512) -> np.ndarray:
    """Nearest-neighbour enlargement of a small preview to about `width` pixels across."""
    k = max(1, width // image.shape[1])
    return np.repeat(np.repeat(image, k, axis=0), k, axis=1)


def heat_map(values: np.ndarray, scale: float) -> np.ndarray:
    """(H, W) non-negative values -> (H, W, 3) display colours (black -> red -> yellow -> white at `scale`)."""
    x = np.clip(np.nan_to_num(values) / max(scale, 1e-30), 0.0, 1.0)
    return np.stack([np.clip(3 * x, 0, 1), np.clip(3 * x - 1, 0, 1), np.clip(3 * x - 2, 0, 1)], axis=-1)


def write_residual(path: Path, values: np.ndarray, reference: np.ndarray, pixels: np.ndarray, shape,
                   usable: np.ndarray | None = None) -> Path:
    """|values - reference| of the used pixels as a heat map (white = an error of 10 % of the
    reference's 95th-percentile radiance)."""
    from pipelines.io import images
    from pipelines.model.render import pixels_to_image

    ok = np.ones(len(values), bool) if usable is None else np.asarray(usable, bool)
    err = np.abs(np.asarray(values, np.float64)[ok] - np.asarray(reference, np.float64)[ok]).mean(axis=1)
    heat = pixels_to_image(err, pixels[ok], *shape)
    scale = 0.1 * float(np.percentile(np.abs(reference[ok]).mean(axis=1), 95)) if ok.any() else 1.0
    images.write_png(path, heat_map(heat, scale), already_display=True)
    return Path(path)
