"""Image input/output through OpenImageIO, linearisation, saturation and tone mapping.

Float formats (EXR, HDR, PFM, float TIFF) are linear radiance. Integer formats (8/16-bit PNG, JPEG,
TIFF) are sRGB-encoded unless the caller says they are linear; their maximum code value marks a
clipped (saturated) pixel, which the solvers must not fit as if exact (DESIGN §2).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError, require_file
from .files import atomic_output

FLOAT_FORMATS = ("half", "float", "double")


@dataclass(frozen=True)
class LoadedImage:
    """A photo in linear radiance.

    Attributes
    ----------
    pixels : (H, W, 3) float32 linear RGB.
    saturated : (H, W) bool, pixels with a channel at the format's maximum (always False for float).
    linear_source : whether the file stored linear values (float formats or `linear=True`).
    bit_depth : bits per channel of the file ('float' for float formats).
    """

    pixels: np.ndarray
    saturated: np.ndarray
    linear_source: bool
    bit_depth: str

    @property
    def height(self) -> int:
        return self.pixels.shape[0]

    @property
    def width(self) -> int:
        return self.pixels.shape[1]


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    v = np.clip(np.asarray(v, dtype=np.float64), 0.0, None)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1.0 / 2.4) - 0.055)


def _open(path: Path):
    import OpenImageIO as oiio

    require_file(path, "check the path, or put the file in the scene folder")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # keep colour as stored: alpha is dropped, not multiplied in
    buf = oiio.ImageBuf(str(path), 0, 0, config)
    if buf.has_error:
        detail = (buf.geterror().splitlines() or ["unknown format"])[0]
        raise InputError(f"cannot read image ({detail})", path, "re-export it as EXR, PNG or JPEG")
    _check_format_matches_name(path, buf.file_format_name)
    if path.suffix.lower() in (".jpg", ".jpeg") and not _jpeg_complete(path):
        raise InputError("JPEG file is truncated (no end-of-image marker)", path, "copy or export the photo again")
    return buf


_FORMAT_LABELS = {"openexr": "EXR", "jpeg2000": "JPEG 2000", "jpegxl": "JPEG XL", "pnm": "PNM/PFM"}


@functools.cache
def _format_extensions() -> dict[str, list[str]]:
    """OpenImageIO's formats and their file extensions ({'openexr': ['exr', 'sxr', 'mxr'], ...})."""
    import OpenImageIO as oiio

    found = {}
    for item in oiio.get_string_attribute("extension_list").split(";"):
        fmt, _, exts = item.partition(":")
        found[fmt] = [e.lower() for e in exts.split(",") if e]
    return found


def _check_format_matches_name(path: Path, fmt: str) -> None:
    """Refuse a file whose content is another format than its name says (a JPEG renamed .exr
    would be read as 8-bit sRGB where the name promises linear radiance)."""
    suffix = path.suffix.lower().lstrip(".")
    formats = _format_extensions()
    named = [f for f, exts in formats.items() if suffix in exts]
    if not fmt or not named or fmt in named:
        return
    label = _FORMAT_LABELS.get(fmt, fmt.upper())
    expected = _FORMAT_LABELS.get(named[0], named[0].upper())
    ext = (formats.get(fmt) or [fmt])[0]
    raise InputError(f"the file holds {label} data, not {expected} as its name (.{suffix}) says", path,
                     f"rename it to {path.stem}.{ext}, or convert it to {expected}")


def _jpeg_complete(path: Path) -> bool:
    # libjpeg pads a truncated stream with grey and reports nothing; the EOI marker tells.
    with open(path, "rb") as f:
        f.seek(0, 2)
        size = f.tell()
        f.seek(max(0, size - 4096))
        tail = f.read().rstrip(b"\x00")
    return tail.endswith(b"\xff\xd9")


def _pixels(buf, path: Path, fmt) -> np.ndarray:
    import OpenImageIO as oiio

    px = buf.get_pixels(fmt)
    if buf.has_error or px is None or np.size(px) == 0:
        # geterror() also clears the error (else OpenImageIO prints it when the buffer dies)
        detail = (buf.geterror().splitlines() or [""])[0]
        raise InputError("image data is truncated or corrupt" + (f" ({detail})" if detail else ""), path,
                         "re-export the image")
    px = np.asarray(px)
    if px.ndim == 2:
        px = px[..., None]
    if px.ndim == 4:  # volume images: not a photo
        raise InputError("image has depth (a volume), expected a 2-D photo", path, "export a 2-D image")
    return px if fmt != oiio.FLOAT else px.astype(np.float32, copy=False)


def read_image(path: str | Path, linear: bool | None = None, mask: str | Path | None = None) -> LoadedImage:
    """Read a photo as linear RGB radiance.

    Parameters
    ----------
    path : image file (EXR/HDR/PFM/TIFF/PNG/JPEG, anything OpenImageIO reads).
    linear : treat integer formats as linear (default: sRGB-decode them). Ignored for float files.
    mask : the photo's mask.png (white = used), read only if the photo has non-finite pixels:
        NaN/Inf pixels the mask leaves out are not refused (they become 0).

    Raises
    ------
    InputError
        Missing, unreadable or truncated file; non-finite pixels that are used (no mask, or inside
        it); a mask of another size; wrong channel count.
    """
    import OpenImageIO as oiio

    path = Path(path)
    buf = _open(path)
    spec = buf.spec()
    base = str(spec.format).lower()
    is_float = any(f in base for f in FLOAT_FORMATS)
    if is_float:
        px = _pixels(buf, path, oiio.FLOAT).astype(np.float32)
        max_code = None
    else:
        px = _pixels(buf, path, spec.format)
        max_code = np.iinfo(px.dtype).max if np.issubdtype(px.dtype, np.integer) else None
    nch = px.shape[2]
    if nch in (2, 4) and spec.alpha_channel != nch - 1:  # (e.g. an EXR of R and G: not grey and alpha)
        names = ", ".join(spec.channelnames) or f"{nch} channels"
        raise InputError(f"image has {nch} channels ({names}), the last not an alpha channel: expected grey, "
                         "grey + alpha, RGB or RGBA", path, "export it as an RGB image")
    if nch in (2, 4):  # grey+alpha or RGBA: drop alpha
        px = px[..., : nch - 1]
    elif nch not in (1, 3):
        raise InputError(f"image has {nch} channels, expected 1 (grey), 3 (RGB) or 4 (RGBA)", path,
                         "export it as an RGB image")
    if px.shape[2] == 1:
        px = np.repeat(px, 3, axis=2)
    if is_float:
        bad = ~np.isfinite(px).all(axis=2)
        if bad.any():
            _check_nonfinite(path, bad, mask)
            px[bad] = 0.0  # left out by the mask: never used
        if np.any(px < 0):
            px = np.clip(px, 0.0, None)  # small negatives come from denoisers/subtraction
        saturated = np.zeros(px.shape[:2], dtype=bool)
        pixels = px
        linear_source = True
        depth = "float"
    else:
        saturated = np.any(px >= max_code, axis=2) if max_code is not None else np.zeros(px.shape[:2], bool)
        values = px.astype(np.float64) / float(max_code or 1)
        linear_source = bool(linear)
        pixels = (values if linear_source else srgb_to_linear(values)).astype(np.float32)
        depth = str(8 * px.dtype.itemsize)
    return LoadedImage(pixels=np.ascontiguousarray(pixels), saturated=saturated,
                       linear_source=linear_source, bit_depth=depth)


def _check_nonfinite(path: Path, bad: np.ndarray, mask: str | Path | None) -> None:
    """Refuse the photo's NaN/Inf pixels (`bad`, (H, W)) unless the mask leaves every one out."""
    if mask is None:
        raise InputError(f"{int(bad.sum())} pixels are NaN or infinite", path,
                         "fix the render or merge that produced them, or leave them out with a mask.png "
                         "(black = not used)")
    used = read_mask(mask)
    if used.shape != bad.shape:
        raise InputError(f"mask is {used.shape[1]}x{used.shape[0]}, the photo {path.name} is "
                         f"{bad.shape[1]}x{bad.shape[0]}", mask, "use a mask of the photo's size")
    inside = bad & used
    if inside.any():
        r, c = np.argwhere(inside)[0]
        raise InputError(f"{int(inside.sum())} pixels inside {Path(mask).name} are NaN or infinite (the first at "
                         f"row {r}, column {c})", path,
                         f"fix the render or merge that produced them, or paint them black in {Path(mask).name}")


def read_grey8(path: str | Path) -> np.ndarray:
    """A photo as (H, W) uint8 grey levels in its display encoding (what a target detector wants):
    8-bit files as stored, 16-bit scaled down, float files clipped to [0, 1] and sRGB-encoded."""
    import OpenImageIO as oiio

    path = Path(path)
    buf = _open(path)
    base = str(buf.spec().format).lower()
    if any(f in base for f in FLOAT_FORMATS):
        px = _pixels(buf, path, oiio.FLOAT).astype(np.float64)
        if not np.all(np.isfinite(px)):
            raise InputError("image has NaN or infinite pixels", path, "re-export the photo")
        px = linear_to_srgb(np.clip(px, 0.0, 1.0)) * 255.0
    else:
        px = _pixels(buf, path, oiio.UINT8).astype(np.float64)
    nch = px.shape[2]
    if nch in (2, 4):
        px = px[..., : nch - 1]
    grey = px[..., 0] if px.shape[2] == 1 else px[..., :3] @ np.array([0.299, 0.587, 0.114])
    return np.clip(np.round(grey), 0, 255).astype(np.uint8)


def read_mask(path: str | Path) -> np.ndarray:
    """Read a mask image: (H, W) bool, True where any colour channel is above half its range and,
    when it has an alpha channel, the alpha too (transparent = not used). (An opaque alpha counted as
    a channel made every pixel of an RGBA mask used.)"""
    import OpenImageIO as oiio

    path = Path(path)
    buf = _open(path)
    px = np.asarray(_pixels(buf, path, oiio.FLOAT))
    alpha = buf.spec().alpha_channel
    if 0 <= alpha < px.shape[2] and px.shape[2] > 1:
        colour = np.delete(px, alpha, axis=2)
        return (colour.max(axis=2) > 0.5) & (px[..., alpha] > 0.5)
    return px.max(axis=2) > 0.5


def read_latlong(path: str | Path) -> np.ndarray:
    """Read a lat-long light image (H, 2H, 3) float64 linear radiance (DESIGN §2)."""
    path = Path(path)
    try:
        img = read_image(path, linear=True)
    except InputError as exc:  # (a photo's fixes name masks and PNG/JPEG: a light's are its own)
        if "NaN or infinite" in exc.problem:
            raise InputError(exc.problem, exc.path or path, "fix the light: every pixel of a light is used (no mask)"
                             ) from None
        if exc.problem.startswith("cannot read image"):  # (not an image at all: a truncated one keeps its fix)
            raise InputError(exc.problem, exc.path or path, "give a lat-long light as EXR or HDR (linear radiance)"
                             ) from None
        raise
    h, w = img.pixels.shape[:2]
    if w != 2 * h:
        raise InputError(f"lat-long light must be twice as wide as high, got {w}x{h}", path,
                         "resample it to a 2:1 equirectangular image")
    if not np.any(img.pixels > 0):  # (negative values are read as 0: a negated map is black too)
        raise InputError("the light has no positive radiance (black, or negative values only)", path,
                         "give a light whose radiance is > 0 somewhere")
    return img.pixels.astype(np.float64)


def _write(path: str | Path, array: np.ndarray, fmt) -> Path:
    import OpenImageIO as oiio

    path = Path(path)
    arr = np.ascontiguousarray(array)
    if arr.ndim == 2:
        arr = arr[..., None]
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], fmt)
    if fmt == oiio.HALF or fmt == oiio.FLOAT:
        spec.attribute("compression", "zip")
    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise write_error(path, oiio.geterror())
        ok = out.write_image(arr)
        out.close()
        if not ok:
            raise write_error(path, out.geterror())
    return path


def write_error(path: Path, detail: str) -> OSError:
    """OpenImageIO reports a failed write as text: an OSError that says why (with its errno when the
    cause is known: a full disk, a missing permission), naming the final file."""
    import errno
    import os
    import shutil

    text = detail.lower()
    try:
        full = shutil.disk_usage(path.parent).free < 1 << 20
    except OSError:
        full = False
    if full or "no space" in text:
        code = errno.ENOSPC
    elif "permission" in text:
        code = errno.EACCES
    else:
        return OSError(errno.EIO, f"cannot write the image ({detail.splitlines()[0] if detail else 'unknown error'})",
                       str(path))
    return OSError(code, os.strerror(code), str(path))


def write_exr(path: str | Path, image: np.ndarray) -> Path:
    """Write a linear float32 EXR (atomically: temp file, then rename)."""
    import OpenImageIO as oiio

    return _write(path, np.asarray(image, dtype=np.float32), oiio.FLOAT)


def tonemap(image: np.ndarray, exposure: float | None = None, percentile: float = 99.5) -> np.ndarray:
    """Linear radiance -> display values in [0, 1] (sRGB-encoded).

    With ``exposure=None`` the image is scaled so that its `percentile` maps to 1 (auto exposure);
    otherwise it is multiplied by 2**exposure. Values above 1 are clipped.
    """
    img = np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0, posinf=0.0)
    if exposure is None:
        ref = np.percentile(img[img > 0], percentile) if np.any(img > 0) else 1.0
        scale = 1.0 / ref
    else:
        scale = 2.0**exposure
    return np.clip(linear_to_srgb(img * scale), 0.0, 1.0)


def write_png(path: str | Path, image: np.ndarray, exposure: float | None = None,
              already_display: bool = False) -> Path:
    """Write an 8-bit sRGB PNG preview of a linear image (or of display values in [0, 1])."""
    import OpenImageIO as oiio

    disp = np.clip(image, 0, 1) if already_display else tonemap(image, exposure)
    return _write(path, np.round(disp * 255.0).astype(np.uint8), oiio.UINT8)
