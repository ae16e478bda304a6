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


def _rows_kernel(backend, pos: np.ndarray, nrm: np.ndarray, geo: np.ndarray, dirs: np.ndarray,
                 sub: np.ndarray | None) -> np.ndarray:
    """Visibility of a few pixels (float32 arrays in the backend's recentred frame).

    Every pixel gets one ray per texel (or sub-direction) laid out pixel-major, so building the
    batch is a tile and a repeat rather than gathers; rays that need no cast get a negative
    ray length, which Embree discards before traversal.
    """
    mask = castable(nrm, geo, dirs)  # (p, N)
    origins = pos + np.float32(backend.offset) * geo  # off the surface, on the lit side
    if sub is None:
        d = np.tile(dirs, (len(pos), 1))
        o = np.repeat(origins, len(dirs), axis=0)
        tfar = np.where(mask.ravel(), np.float32(np.inf), np.float32(-1.0))
        visible = ~backend.occluded_local(o, d, tfar).reshape(mask.shape) & mask
        return np.packbits(visible, axis=1, bitorder="little")
    kk = sub.shape[1]
    d = np.tile(sub.reshape(-1, 3), (len(pos), 1))
    o = np.repeat(origins, len(dirs) * kk, axis=0)
    # a sub-direction behind the facet is blocked by the facet itself
    sub_front = (np.einsum("pk,nsk->pns", geo, sub) > 0) & mask[:, :, None]
    tfar = np.where(sub_front.ravel(), np.float32(np.inf), np.float32(-1.0))
    visible = ~backend.occluded_local(o, d, tfar).reshape(sub_front.shape) & sub_front
    frac = np.round(255.0 * visible.sum(axis=2) / kk).astype(np.uint8)
    frac[~mask] = 0
    return frac


def visibility_rows(backend, samples: PixelSamples, rows: slice, cube: CubeMap,
                    supersample: int = 1) -> np.ndarray:
    """Visibility of pixels `rows` against all texels, encoded for storage.

    Rays of one pixel are cast together (coherent), only towards texels in front of the shading
    normal and the facet (`castable`); the pixels are split over the backend's threads, each
    preparing and casting its own rays.

    Returns
    -------
    (p, ceil(N/8)) uint8 bit-packed visibility when supersample == 1, else (p, N) uint8 fractions.
    """
    from concurrent.futures import ThreadPoolExecutor

    pos = backend.to_local(samples.position[rows])
    nrm = samples.normal[rows].astype(np.float32)
    geo = samples.geometric_normal[rows].astype(np.float32)
    dirs = cube.directions.astype(np.float32)
    sub = cube.subtexel_directions(supersample).astype(np.float32) if supersample > 1 else None
    n = len(pos)
    bounds = np.linspace(0, n, min(backend.threads, max(1, n)) + 1).astype(int)
    parts = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    if len(parts) == 1:
        return _rows_kernel(backend, pos, nrm, geo, dirs, sub)
    with ThreadPoolExecutor(len(parts)) as pool:
        out = list(pool.map(lambda sl: _rows_kernel(backend, pos[sl], nrm[sl], geo[sl], dirs, sub), parts))
    return np.concatenate(out, axis=0)


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
    import h5py

    n_tex = cube.n_texels
    width = (n_tex + 7) // 8 if supersample == 1 else n_tex
    with h5py.File(path, "w", track_order=True) as f:
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
