"""The visibility cache file (`visibility.h5`): pixel samples, texel layout and the stored rows.

Layout (the visibility chunked by pixel rows and deflated; the pixel samples stored plain: floats
that deflate only ~3.5x, at ~0.3 s per 200,000 pixels):
  attrs: format, resolution, hemisphere, supersample, n_pixels, n_texels, encoding ('bits'|'fraction')
  pixels/{pixel, position, normal, geometric_normal, view, face, normal_jacobian (optional)}
  texels/{direction, solid_angle}
  visibility: (P, ceil(N/8)) uint8 bit-packed (little bit order) or (P, N) uint8 fractions
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import InputError
from ..geometry.camera import PixelSamples
from ..geometry.visibility import VisibilityData
from ..light.cubemap import CubeMap
from .files import h5_file

FORMAT = "wavelight-visibility-1"
PIXEL_FIELDS = PixelSamples.FIELDS
OPTIONAL_FIELDS = ("normal_jacobian",)  # (files written before it: the samples have none)


def write_visibility(path: str | Path, samples: PixelSamples, cube: CubeMap, supersample: int,
                     chunks: Iterator[np.ndarray], rows_per_chunk: int, attrs: dict | None = None) -> None:
    """Write the file at `path` (atomically: `files.h5_file`) from stored-row chunks."""

    n_tex = cube.n_texels
    width = (n_tex + 7) // 8 if supersample == 1 else n_tex
    with h5_file(path, track_order=True) as f:
        f.attrs.update({"format": FORMAT, "resolution": cube.resolution, "hemisphere": cube.hemisphere,
                        "supersample": supersample, "n_pixels": len(samples), "n_texels": n_tex,
                        "encoding": "bits" if supersample == 1 else "fraction", **(attrs or {})})
        for name in PIXEL_FIELDS:
            arr = getattr(samples, name)
            if arr is None:
                continue
            f.create_dataset(f"pixels/{name}", data=arr)
        f.create_dataset("texels/direction", data=cube.directions)
        f.create_dataset("texels/solid_angle", data=cube.solid_angles)
        chunk_rows = max(1, min(len(samples), rows_per_chunk))
        ds = f.create_dataset("visibility", shape=(len(samples), width), dtype=np.uint8,
                              chunks=(chunk_rows, width), compression="gzip", compression_opts=DEFLATE_LEVEL,
                              shuffle=False)
        a = 0
        with ThreadPoolExecutor(DEFLATE_THREADS) as pool:
            for block in chunks:
                _write_rows(ds, a, np.asarray(block, np.uint8), chunk_rows, pool)
                a += len(block)
        if a != len(samples):
            raise RuntimeError(f"visibility chunks cover {a} of {len(samples)} pixels")


DEFLATE_THREADS = 2  # chunks deflated side by side (zlib releases the GIL; HDF5's own filter runs on one core)
DEFLATE_LEVEL = 1  # the visibility's gzip level: its bits deflate ~7x at level 1


def _write_rows(ds, start: int, block: np.ndarray, chunk_rows: int, pool) -> None:
    """`block` into rows start.. of the deflated dataset `ds`: the whole chunks it covers deflated
    on `pool`'s threads and written as they are stored (`write_direct_chunk`: the same gzip stream
    HDF5's filter writes; the last chunk padded with the fill value 0), anything else through h5py."""
    import zlib

    n, width = len(ds), ds.shape[1]
    if start % chunk_rows or block.shape[1:] != (width,) or not len(block):
        ds[start:start + len(block)] = block
        return
    whole = len(block) if start + len(block) == n else len(block) // chunk_rows * chunk_rows
    offsets = range(0, whole, chunk_rows)

    def deflated(a: int) -> bytes:
        piece = block[a:a + chunk_rows]
        if len(piece) < chunk_rows:
            piece = np.concatenate([piece, np.zeros((chunk_rows - len(piece), width), np.uint8)])
        return zlib.compress(np.ascontiguousarray(piece).tobytes(), DEFLATE_LEVEL)

    for a, data in zip(offsets, pool.map(deflated, offsets)):
        ds.id.write_direct_chunk((start + a, 0), data)
    if whole < len(block):
        ds[start + whole:start + len(block)] = block[whole:]


def read_visibility(path: str | Path, in_memory: bool = True) -> VisibilityData:
    """Open a visibility file; raises InputError if it is not one of ours or is damaged."""
    import h5py

    path = Path(path)
    try:
        f = h5py.File(path, "r")
        if f.attrs.get("format") != FORMAT:
            raise InputError(f"not a {FORMAT} file", path, "delete it; the next run rebuilds it")
        samples = PixelSamples(**{name: f[f"pixels/{name}"][:] for name in PIXEL_FIELDS
                                  if name not in OPTIONAL_FIELDS or f"pixels/{name}" in f})
        cube = CubeMap(int(f.attrs["resolution"]), bool(f.attrs["hemisphere"]))
        if cube.n_texels != int(f.attrs["n_texels"]):
            raise InputError("texel count does not match its layout", path, "delete it; the next run rebuilds it")
        stored = f["visibility"][:] if in_memory else f["visibility"]
        # (the stored rows hold V = 0 wherever a texel is not castable: `castable_only`)
        data = VisibilityData(samples, cube, int(f.attrs["supersample"]), stored, str(f.attrs.get("method", "exact")),
                              castable_only=True)
        if in_memory:
            f.close()
        return data
    except (OSError, KeyError) as exc:
        raise InputError(f"damaged visibility cache ({exc})", path, "delete it; the next run rebuilds it") from None
