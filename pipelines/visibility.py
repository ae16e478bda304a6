"""Shadow visibility of every light texel from every used pixel, and its HDF5 file format.

V[j, i] = 1 when texel i's direction is unoccluded from pixel j's surface point (and N_j . d_i > 0;
texels behind the shading normal are stored as 0, they never contribute). With supersampling k,
each texel is probed by k x k sub-directions and V is the visible fraction (stored as uint8 /255).

File layout (`visibility.h5`, all datasets chunked by pixel rows and compressed):
  attrs: format, resolution, hemisphere, supersample, n_pixels, n_texels, encoding ('bits'|'fraction')
  pixels/{pixel, position, normal, geometric_normal, view, face}
  texels/{direction, solid_angle}
  visibility: (P, ceil(N/8)) uint8 bit-packed (little bit order) or (P, N) uint8 fractions
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from .camera import PixelSamples
from .cubemap import CubeMap
from .errors import InputError
from .fileio import h5_file

FORMAT = "wavelight-visibility-1"
PIXEL_FIELDS = ("pixel", "position", "normal", "geometric_normal", "view", "face")


def facing(normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(P, N) cosines max(0, N . d) between shading normals and texel directions (float32)."""
    return np.maximum(normals.astype(np.float32) @ directions.astype(np.float32).T, 0.0)


def castable(normals: np.ndarray, geometric_normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(P, N) bool: texels worth a shadow ray, in front of both the shading normal and the facet.

    Light from behind the geometric facet cannot reach its front side (the facet itself is
    opaque), so those texels are V = 0 without casting, for closed and open meshes alike.
    """
    d = directions.astype(np.float32).T
    return ((normals.astype(np.float32) @ d) > 0) & ((geometric_normals.astype(np.float32) @ d) > 0)


PIXELS_PER_CALL = 16  # pixels traced per Embree call: amortises the call, keeps batches small


def _trace_rows(backend, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> np.ndarray:
    """Trace every (pixel, direction) pair of a few pixels -> (p, n) bool visible.

    One call covers PIXELS_PER_CALL pixels: their rays are each pixel's origin repeated against the
    same direction table (pixel-major: coherent), so a batch needs no gathers; rays with a
    negative tfar are discarded by Embree before traversal.
    """
    n = len(directions)
    table = np.tile(directions, (PIXELS_PER_CALL, 1))
    out = np.empty(tfar.shape, dtype=bool)
    for j in range(0, len(origins), PIXELS_PER_CALL):
        k = min(PIXELS_PER_CALL, len(origins) - j)
        o = np.repeat(origins[j:j + k], n, axis=0)
        out[j:j + k] = ~backend.occluded_local(o, table[:k * n], tfar[j:j + k].ravel()).reshape(k, n)
    return out


def visibility_rows(backend, samples: PixelSamples, rows: slice, cube: CubeMap,
                    supersample: int = 1) -> np.ndarray:
    """Visibility of pixels `rows` against all texels, encoded for storage.

    Rays of one pixel are cast together (coherent), only towards texels in front of the shading
    normal and the facet (`castable`); the pixels are split over the backend's threads.

    Returns
    -------
    (p, ceil(N/8)) uint8 bit-packed visibility when supersample == 1, else (p, N) uint8 fractions.
    """
    from concurrent.futures import ThreadPoolExecutor

    pos = backend.to_local(samples.position[rows])
    geo = samples.geometric_normal[rows].astype(np.float32)
    dirs = cube.directions.astype(np.float32)
    mask = castable(samples.normal[rows], geo, dirs)  # (p, N)
    origins = pos + np.float32(backend.offset) * geo  # off the surface, on the lit side
    if supersample == 1:
        table, tfar = dirs, np.where(mask, np.float32(np.inf), np.float32(-1.0))
    else:
        sub = cube.subtexel_directions(supersample).astype(np.float32)  # (N, k*k, 3)
        # a sub-direction behind the facet is blocked by the facet itself
        live = (np.einsum("pk,nsk->pns", geo, sub) > 0) & mask[:, :, None]
        table = sub.reshape(-1, 3)
        tfar = np.where(live, np.float32(np.inf), np.float32(-1.0)).reshape(len(pos), -1)
    n = len(pos)
    bounds = np.linspace(0, n, min(backend.threads, max(1, n)) + 1).astype(int)
    parts = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    if len(parts) == 1:
        visible = _trace_rows(backend, origins, table, tfar)
    else:
        with ThreadPoolExecutor(len(parts)) as pool:
            visible = np.concatenate(list(pool.map(
                lambda sl: _trace_rows(backend, origins[sl], table, tfar[sl]), parts)))
    if supersample == 1:
        return np.packbits(visible & mask, axis=1, bitorder="little")
    kk = supersample**2
    counts = (visible & (tfar > 0)).reshape(n, -1, kk).sum(axis=2)
    frac = np.round(255.0 * counts / kk).astype(np.uint8)
    frac[~mask] = 0
    return frac


def decode(block: np.ndarray, n_texels: int, encoding: str) -> np.ndarray:
    """Stored rows -> (p, N) float32 visibility in [0, 1]."""
    if encoding == "bits":
        return np.unpackbits(block, axis=1, count=n_texels, bitorder="little").astype(np.float32)
    return block.astype(np.float32) * np.float32(1.0 / 255.0)


@dataclass
class VisibilityData:
    """Visibility with its pixel samples and texel layout; in memory or backed by an HDF5 file.

    `blocks()` yields (row slice, (p, N) float32 V) so that consumers never need all of V at once.
    """

    samples: PixelSamples
    cube: CubeMap
    supersample: int
    stored: object  # (P, width) uint8 array or h5py dataset

    @property
    def encoding(self) -> str:
        return "bits" if self.supersample == 1 else "fraction"

    @property
    def n_pixels(self) -> int:
        return len(self.samples)

    def blocks(self, rows: int = 2048, pixels: np.ndarray | None = None) -> Iterator[tuple[slice, np.ndarray]]:
        n = self.n_pixels
        for a in range(0, n, rows):
            sl = slice(a, min(n, a + rows))
            yield sl, decode(np.asarray(self.stored[sl]), self.cube.n_texels, self.encoding)

    def block(self, rows: slice) -> np.ndarray:
        """(p, N) float32 V of a slice of pixel rows."""
        return decode(np.asarray(self.stored[rows]), self.cube.n_texels, self.encoding)

    def dense(self) -> np.ndarray:
        """(P, N) float32 V (small scenes and tests only)."""
        return decode(np.asarray(self.stored[:]), self.cube.n_texels, self.encoding)


def compute_visibility(backend, samples: PixelSamples, cube: CubeMap, supersample: int = 1,
                       rows_per_chunk: int = 512, progress=None) -> VisibilityData:
    """Whole visibility in memory (the cached stage instead writes chunk by chunk, resumably)."""
    parts = []
    for a in range(0, len(samples), rows_per_chunk):
        parts.append(visibility_rows(backend, samples, slice(a, min(len(samples), a + rows_per_chunk)),
                                     cube, supersample))
        if progress:
            progress(min(len(samples), a + rows_per_chunk), len(samples))
    return VisibilityData(samples, cube, supersample, np.concatenate(parts, axis=0))


def write_visibility(path: str | Path, samples: PixelSamples, cube: CubeMap, supersample: int,
                     chunks: Iterator[np.ndarray], rows_per_chunk: int, attrs: dict | None = None) -> None:
    """Write the file at `path` (the caller renames it into place) from stored-row chunks."""

    n_tex = cube.n_texels
    width = (n_tex + 7) // 8 if supersample == 1 else n_tex
    with h5_file(path, track_order=True) as f:
        f.attrs.update({"format": FORMAT, "resolution": cube.resolution, "hemisphere": cube.hemisphere,
                        "supersample": supersample, "n_pixels": len(samples), "n_texels": n_tex,
                        "encoding": "bits" if supersample == 1 else "fraction", **(attrs or {})})
        for name in PIXEL_FIELDS:
            arr = getattr(samples, name)
            f.create_dataset(f"pixels/{name}", data=arr, compression="gzip", compression_opts=4, shuffle=True)
        f.create_dataset("texels/direction", data=cube.directions)
        f.create_dataset("texels/solid_angle", data=cube.solid_angles)
        chunk_rows = max(1, min(len(samples), rows_per_chunk))
        ds = f.create_dataset("visibility", shape=(len(samples), width), dtype=np.uint8,
                              chunks=(chunk_rows, width), compression="gzip", compression_opts=4,
                              shuffle=False)
        a = 0
        for block in chunks:
            ds[a:a + len(block)] = block
            a += len(block)
        if a != len(samples):
            raise RuntimeError(f"visibility chunks cover {a} of {len(samples)} pixels")


def read_visibility(path: str | Path, in_memory: bool = True) -> VisibilityData:
    """Open a visibility file; raises InputError if it is not one of ours or is damaged."""
    import h5py

    path = Path(path)
    try:
        f = h5py.File(path, "r")
        if f.attrs.get("format") != FORMAT:
            raise InputError(f"not a {FORMAT} file", path, "delete it; the next run rebuilds it")
        samples = PixelSamples(**{name: f[f"pixels/{name}"][:] for name in PIXEL_FIELDS})
        cube = CubeMap(int(f.attrs["resolution"]), bool(f.attrs["hemisphere"]))
        if cube.n_texels != int(f.attrs["n_texels"]):
            raise InputError("texel count does not match its layout", path, "delete it; the next run rebuilds it")
        stored = f["visibility"][:] if in_memory else f["visibility"]
        data = VisibilityData(samples, cube, int(f.attrs["supersample"]), stored)
        if in_memory:
            f.close()
        return data
    except (OSError, KeyError) as exc:
        raise InputError(f"damaged visibility cache ({exc})", path, "delete it; the next run rebuilds it") from None
