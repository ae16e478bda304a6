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


CROSS_PREVIEW = "the cube cross (row block 0: +Z; 1: +X, +Y, -X, -Y; 2: -Z) cropped to its texels; transparent: no texel"


def cross_preview(display: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(3R, 4R, 3) display values of a cube cross -> RGBA cropped to the rows and columns that hold
    texels (a hemisphere keeps the top 1.5R rows), transparent (A = 0) where the layout has no
    texel: the unused area reads as background, not as a dark part of the light."""
    rows, cols = np.nonzero(valid)
    crop = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    rgba = np.concatenate([np.asarray(display, np.float64), valid[..., None].astype(np.float64)], axis=-1)[crop]
    rgba[rgba[..., 3] == 0, :3] = 0.0
    return rgba


def write_light(out_dir: Path, stem: str, texels: np.ndarray, cube, height: int | None = None,
                unobservable: np.ndarray | None = None) -> list[Path]:
    """A cube-map light as <stem>_latlong.exr (exchange format), <stem>_cross.exr and a preview PNG
    of the cross (`cross_preview`: cropped, transparent where no texel is; unobservable texels dark
    magenta).

    The preview is log tone-mapped (`log_display`): a sun does not push the sky to black. The
    radiance at black and at white is in the PNG's text (`wavelight:log_black`, `wavelight:log_white`)."""
    from pipelines.io import images
    from pipelines.light import cubemap

    height = height or max(64, 2 * cube.resolution)
    paths = [out_dir / f"{stem}_latlong.exr", out_dir / f"{stem}_cross.exr", out_dir / f"{stem}_cross.png"]
    images.write_exr(paths[0], cubemap.cube_to_latlong(texels, cube, height))
    cross, valid = cubemap.cross_image(texels, cube)
    images.write_exr(paths[1], cross)
    preview, lo, hi = log_display(cross)
    if unobservable is not None and np.any(unobservable):
        marked, _ = cubemap.cross_image(np.asarray(unobservable, np.float64), cube)
        preview[marked > 0.5] = (0.35, 0.0, 0.35)
    write_display_png(paths[2], upscale(cross_preview(preview, valid)), {
        "wavelight:display": "log: brightness proportional to log of the brightest channel's radiance",
        "wavelight:log_black": f"{lo:.6g}", "wavelight:log_white": f"{hi:.6g}", "wavelight:layout": CROSS_PREVIEW})
    return paths


def write_cross_heat_png(path: Path, values: np.ndarray, cube, scale: float, what: str, units: str) -> Path:
    """Per-texel values (N,) as a heat map on the cube cross (`cross_preview`), its scale in the
    PNG's text as `write_heat_png` records it."""
    from pipelines.light import cubemap

    cross, valid = cubemap.cross_image(np.asarray(values, np.float64), cube)
    return write_display_png(path, upscale(cross_preview(heat_map(cross, scale), valid)), {
        "wavelight:heat_scale": f"{scale:.6g}", "wavelight:heat_what": what, "wavelight:heat_units": units,
        "wavelight:layout": CROSS_PREVIEW})


def log_range(values: np.ndarray, decades: float = 6.0, percentile: float = 2.0,
              margin: float = 4.0) -> tuple[float, float]:
    """(black, white) radiance of `log_display` for these values: white at the brightest channel's
    maximum, black `margin` times below the `percentile` of the positive values (a uniform sky
    shows two stops above black, not at it), that percentile taken at most `decades` below white
    (specks of numerical dust stay black)."""
    m = np.clip(np.nan_to_num(np.asarray(values, np.float64), nan=0.0, posinf=0.0), 0.0, None)
    m = m.max(axis=-1) if m.ndim > 1 and m.shape[-1] == 3 else m
    pos = m[m > 0]
    if pos.size == 0:
        return 0.1, 1.0
    hi = float(pos.max())
    lo = max(float(np.percentile(pos, percentile)), hi * 10.0 ** -decades) / margin
    if not lo < hi:
        lo = hi / 10.0
    return lo, hi


def log_display(image: np.ndarray, lo: float | None = None, hi: float | None = None
                ) -> tuple[np.ndarray, float, float]:
    """(..., 3) linear radiance -> ((..., 3) display values in [0, 1], black, white).

    A pixel's display luminance is t = log(m / black) / log(white / black) (clipped to [0, 1],
    sRGB-encoded) with m its brightest channel, and its colour is rgb / m: the hue of a dim sky
    shows beside a sun thousands of times brighter. Radiance at or below `black` (and zero) is
    black. Missing bounds come from `log_range`. `log_colours` are the colours of a grey ramp, for
    a colour bar with LogNorm(black, white)."""
    from pipelines.io.images import linear_to_srgb

    img = np.clip(np.nan_to_num(np.asarray(image, np.float64), nan=0.0, posinf=0.0), 0.0, None)
    if lo is None or hi is None:
        auto = log_range(img)
        lo, hi = (auto[0] if lo is None else lo), (auto[1] if hi is None else hi)
    m = img.max(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.log(np.maximum(m, 1e-300) / lo) / np.log(hi / lo), 0.0, 1.0)
        hue = np.where(m[..., None] > 0, img / m[..., None], 0.0)
    return np.clip(linear_to_srgb(hue * t[..., None]), 0.0, 1.0), float(lo), float(hi)


def log_colours(n: int = 256) -> np.ndarray:
    """(n, 3) colours of `log_display` from black to white (for a colour bar: ListedColormap with
    LogNorm(black, white))."""
    from pipelines.io.images import linear_to_srgb

    return np.repeat(np.clip(linear_to_srgb(np.linspace(0.0, 1.0, n)), 0.0, 1.0)[:, None], 3, axis=1)


def write_display_png(path: Path, display: np.ndarray, text: dict[str, str] | None = None) -> Path:
    """An 8-bit PNG of display values in [0, 1] with text chunks (`read_png_text` reads them back)."""
    import OpenImageIO as oiio

    arr = np.ascontiguousarray(np.round(np.clip(display, 0.0, 1.0) * 255.0).astype(np.uint8))
    if arr.ndim == 2:
        arr = arr[..., None]
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], oiio.UINT8)
    for key, value in (text or {}).items():
        spec.attribute(key, str(value))
    from pipelines.io.images import write_error

    with atomic_output(Path(path)) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise write_error(Path(path), oiio.geterror())
        ok = out.write_image(arr)
        out.close()
        if not ok:
            raise write_error(Path(path), out.geterror())
    return Path(path)


def read_png_text(path: Path) -> dict[str, str]:
    """The `wavelight:*` text of a PNG written by `write_display_png` ({} for other files)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()
        return {}
    try:
        return {a.name: str(a.value) for a in inp.spec().extra_attribs if a.name.startswith("wavelight:")}
    finally:
        inp.close()


def upscale(image: np.ndarray, width: int = 512) -> np.ndarray:
    """Nearest-neighbour enlargement of a small preview to about `width` pixels across."""
    k = max(1, width // image.shape[1])
    return np.repeat(np.repeat(image, k, axis=0), k, axis=1)


def heat_map(values: np.ndarray, scale: float) -> np.ndarray:
    """(H, W) non-negative values -> (H, W, 3) display colours (black -> red -> yellow -> white at
    `scale`). `heat_colours(n)` are the same colours for a colour bar."""
    x = np.clip(np.nan_to_num(values) / max(scale, 1e-30), 0.0, 1.0)
    return np.stack([np.clip(3 * x, 0, 1), np.clip(3 * x - 1, 0, 1), np.clip(3 * x - 2, 0, 1)], axis=-1)


def heat_colours(n: int = 256) -> np.ndarray:
    """(n, 3) colours of `heat_map` from 0 to its scale (for a colour bar: ListedColormap)."""
    return heat_map(np.linspace(0.0, 1.0, n), 1.0)


def write_heat_png(path: Path, values: np.ndarray, scale: float, what: str, units: str) -> Path:
    """`heat_map(values, scale)` as a PNG whose text records the scale (`wavelight:heat_scale`: the
    value shown white), what is shown and its units, so that a report can draw its colour bar."""
    return write_display_png(path, heat_map(values, scale), {
        "wavelight:heat_scale": f"{scale:.6g}", "wavelight:heat_what": what, "wavelight:heat_units": units})


def write_residual(path: Path, values: np.ndarray, reference: np.ndarray, pixels: np.ndarray, shape,
                   usable: np.ndarray | None = None) -> Path:
    """|values - reference| of the used pixels as a heat map (white = an error of 10 % of the
    reference's 95th-percentile radiance, recorded in the PNG's text)."""
    from pipelines.model.render import pixels_to_image

    ok = np.ones(len(values), bool) if usable is None else np.asarray(usable, bool)
    err = np.abs(np.asarray(values, np.float64)[ok] - np.asarray(reference, np.float64)[ok]).mean(axis=1)
    heat = pixels_to_image(err, pixels[ok], *shape)
    scale = 0.1 * float(np.percentile(np.abs(reference[ok]).mean(axis=1), 95)) if ok.any() else 1.0
    return write_heat_png(path, heat, scale, "|render - reference| (mean of R, G, B); white = 10 % of the "
                          "reference's 95th-percentile radiance", "linear radiance")


def write_robust_weights(path: Path, weights: np.ndarray, pixels: np.ndarray, shape) -> Path:
    """1 - the robust pass's weight of each used pixel as a heat map: black = full weight, white =
    left out (solve_report.json's `robust`)."""
    from pipelines.model.render import pixels_to_image

    heat = pixels_to_image(1.0 - np.asarray(weights, np.float64), pixels, *shape)
    return write_heat_png(path, heat, 1.0, "1 - the robust fit's weight: black = full weight, white = left out",
                          "weight taken off")


# -- renders of a view: EXR with alpha, PNG at the photo's exposure -------------------------------------------

PHOTO_PERCENTILE = 99.5  # the photo's preview: this percentile of its positive radiance is white


def photo_exposure(photo: np.ndarray) -> float:
    """Stops that map the photo's 99.5th-percentile radiance to white: the exposure of the photo's
    preview (`images.tonemap(photo)`), used for every render of the scene, so that a render under
    a light one stop darker looks one stop darker."""
    px = np.nan_to_num(np.asarray(photo, np.float64), nan=0.0, posinf=0.0)
    pos = px[px > 0]
    return -float(np.log2(np.percentile(pos, PHOTO_PERCENTILE))) if pos.size else 0.0


def view_image(values: np.ndarray, pixels: np.ndarray, shape, cover: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 4) linear RGBA of a render of the used pixels (P, 3) at `pixels` (P, 2: rows, cols).

    A = 1 where rendered. `cover` (H, W) bool: the pixels the view's mesh covers within its mask;
    those the render left out (the edge margin: pixels near silhouettes and depth jumps, whose
    visibility is not computed) take the value of the nearest rendered pixel, with A = 1. Every
    other pixel (off the mesh, masked out) is RGB = A = 0: transparent, as compositing tools read
    an EXR's alpha."""
    from scipy import ndimage

    H, W = shape
    rgba = np.zeros((H, W, 4), np.float32)
    rgba[pixels[:, 0], pixels[:, 1], :3] = values
    rgba[pixels[:, 0], pixels[:, 1], 3] = 1.0
    if cover is not None and len(pixels):
        rendered = rgba[..., 3] > 0
        fill = np.asarray(cover, bool) & ~rendered
        if fill.any():
            _, (rows, cols) = ndimage.distance_transform_edt(~rendered, return_indices=True)
            rgba[fill, :3] = rgba[rows[fill], cols[fill], :3]
            rgba[fill, 3] = 1.0
    return rgba


def write_view(out_dir: Path, stem: str, values: np.ndarray, pixels: np.ndarray, shape,
               photo: np.ndarray | None = None, exposure: float | None = None,
               exposure_photo: np.ndarray | None = None, cover: np.ndarray | None = None) -> list[Path]:
    """A render of the used pixels -> [<stem>.exr, <stem>.png] (README: Outputs).

    EXR: `view_image` (linear RGBA: the render, its edge margin on the mesh filled from the
    nearest rendered pixel, transparent elsewhere). PNG: with `photo` (the render is of the
    photo's view) the photo where the EXR is transparent; without it, RGBA with those pixels
    transparent. Its exposure: `exposure` stops when given, else the photo's (`photo_exposure` of
    `exposure_photo`, else of `photo`), else automatic (the render's 99.5th percentile white); the
    PNG's text says which (`wavelight:exposure_stops`, `wavelight:exposure`)."""
    from pipelines.io import images

    rgba = view_image(values, pixels, shape, cover)
    exr = images.write_exr(Path(out_dir) / f"{stem}.exr", rgba)
    return [exr, view_png(Path(out_dir) / f"{stem}.png", rgba, photo, exposure, exposure_photo)]


def read_rgba(path: Path) -> np.ndarray:
    """(H, W, 4) float32 of an EXR written by `write_view` (an RGB file gets A = 1 where any
    channel is non-zero: how renders were written before they had alpha)."""
    import OpenImageIO as oiio

    from pipelines.errors import InputError

    buf = oiio.ImageBuf(str(path))
    px = buf.get_pixels(oiio.FLOAT)
    if buf.has_error or px is None:
        raise InputError(f"cannot read the render ({(buf.geterror().splitlines() or [''])[0]})", path,
                         "rerun the command with --force")
    px = np.asarray(px, np.float32)
    if px.ndim == 2:
        px = px[..., None]
    if px.shape[2] >= 4:
        return np.ascontiguousarray(px[..., :4])
    rgb = np.repeat(px, 3, axis=2) if px.shape[2] == 1 else px[..., :3]
    return np.concatenate([rgb, (rgb.max(axis=2, keepdims=True) > 0).astype(np.float32)], axis=2)


def view_png(path: Path, rgba: np.ndarray, photo: np.ndarray | None = None, exposure: float | None = None,
             exposure_photo: np.ndarray | None = None) -> Path:
    """The PNG of `write_view` from its RGBA render (also what an `--exposure` change redraws)."""
    from pipelines.io import images

    rgb, alpha = rgba[..., :3].astype(np.float64), rgba[..., 3] > 0.5
    ref = exposure_photo if exposure_photo is not None else photo
    if exposure is not None:
        stops, how = float(exposure), "--exposure"
    elif ref is not None:
        stops, how = photo_exposure(ref), "the photo's: its 99.5th-percentile radiance is white"
    else:
        pos = rgb[alpha][rgb[alpha] > 0]
        stops = -float(np.log2(np.percentile(pos, PHOTO_PERCENTILE))) if pos.size else 0.0
        how = "automatic: the render's 99.5th-percentile radiance is white"
    text = {"wavelight:exposure_stops": f"{stops:.6g}", "wavelight:exposure": how}
    if photo is not None:
        shown = np.where(alpha[..., None], rgb, np.asarray(photo, np.float64))
        text["wavelight:unrendered"] = "the photo"
        return write_display_png(path, images.tonemap(shown, stops), text)
    text["wavelight:unrendered"] = "transparent"
    display = np.concatenate([images.tonemap(rgb, stops), alpha[..., None].astype(np.float64)], axis=2)
    return write_display_png(path, display, text)
