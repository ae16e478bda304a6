"""Shadow visibility of every light texel from every used pixel (the ray-casting kernels).

V[j, i] = 1 when texel i's direction is unoccluded from pixel j's surface point (and N_j . d_i > 0;
texels behind the shading normal are stored as 0, they never contribute). With supersampling k,
each texel is probed by k x k sub-directions and V is the visible fraction (stored as uint8 /255).
Rows are stored bit-packed (little bit order) or as uint8 fractions; `pipelines.io.visibility_file`
writes and reads them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np

from ..light.cubemap import CubeMap
from .camera import PixelSamples

def castable(normals: np.ndarray, geometric_normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(P, N) bool: texels worth a shadow ray, in front of both the shading normal and the facet.

    Light from behind the geometric facet cannot reach its front side (the facet itself is
    opaque), so those texels are V = 0 without casting, for closed and open meshes alike.
    """
    d = directions.astype(np.float32).T
    return ((normals.astype(np.float32) @ d) > 0) & ((geometric_normals.astype(np.float32) @ d) > 0)


def castable_bits(normals: np.ndarray, geometric_normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """`castable`, bit-packed (little bit order): (P, ceil(N/8)) uint8, in blocks on both cores."""
    from ..threads import parallel_blocks

    P, N = len(normals), len(directions)
    out = np.empty((P, (N + 7) // 8), np.uint8)
    d = directions.astype(np.float32).T
    nrm, geo = normals.astype(np.float32), geometric_normals.astype(np.float32)
    b = 256

    def run(starts):
        x, y, up = np.empty((b, N), np.float32), np.empty((b, N), np.float32), np.empty((b, N), bool)
        for a in starts:
            sl = slice(a, min(P, a + b))
            k = sl.stop - sl.start
            np.matmul(nrm[sl], d, out=x[:k])
            np.matmul(geo[sl], d, out=y[:k])
            np.minimum(x[:k], y[:k], out=x[:k])  # (both above the horizon: the smaller one is; 2.6x the `&` of two
            np.greater(x[:k], 0, out=up[:k])  # comparisons, which made three temporaries per block)
            out[sl] = np.packbits(up[:k], axis=1, bitorder="little")

    parallel_blocks(run, list(range(0, P, b)))
    return out


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


def visibility_rows(backend, samples: PixelSamples, rows: slice | np.ndarray, cube: CubeMap,
                    supersample: int = 1) -> np.ndarray:
    """Visibility of pixels `rows` against all texels, encoded for storage.

    Rays of one pixel are cast together (coherent), only towards texels in front of the shading
    normal and the facet (`castable`); the pixels are split over the backend's threads.

    Returns
    -------
    (p, ceil(N/8)) uint8 bit-packed visibility when supersample == 1, else (p, N) uint8 fractions.
    """
    from concurrent.futures import ThreadPoolExecutor

    origins = backend.shadow_origins(samples.position[rows], samples.geometric_normal[rows], samples.face[rows])
    geo = samples.geometric_normal[rows].astype(np.float32)
    dirs = cube.directions.astype(np.float32)
    mask = castable(samples.normal[rows], geo, dirs)  # (p, N)
    if supersample == 1:
        table, tfar = dirs, np.where(mask, np.float32(np.inf), np.float32(-1.0))
    else:
        sub = cube.subtexel_directions(supersample).astype(np.float32)  # (N, k*k, 3)
        # a sub-direction behind the facet is blocked by the facet itself
        live = (np.einsum("pk,nsk->pns", geo, sub) > 0) & mask[:, :, None]
        table = sub.reshape(-1, 3)
        tfar = np.where(live, np.float32(np.inf), np.float32(-1.0)).reshape(len(origins), -1)
    n = len(origins)
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


def decode(block: np.ndarray, n_texels: int, encoding: str, raw: bool = False) -> np.ndarray:
    """Stored rows -> (p, N) float32 visibility in [0, 1] (`raw` and bits: the 0/1 uint8, no copy to float)."""
    if encoding == "bits":
        bits = np.unpackbits(block, axis=1, count=n_texels, bitorder="little")
        return bits if raw else bits.astype(np.float32)
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
    method: str = "exact"  # how it was computed: "exact" (every ray) or "adaptive" (`coherent_visibility`)
    # V is 0 wherever a texel is not `castable` (behind the shading normal or the facet), as in every
    # visibility wavelight casts and stores: the diffuse radiance is then linear in N (`lambert_radiance`)
    castable_only: bool = False

    @property
    def encoding(self) -> str:
        return "bits" if self.supersample == 1 else "fraction"

    @property
    def n_pixels(self) -> int:
        return len(self.samples)

    def blocks(self, rows: int = 2048, raw: bool = False) -> Iterator[tuple[slice, np.ndarray]]:
        """(row slice, (p, N) V) blocks; `raw`: bit-packed rows as 0/1 uint8 (see `decode`)."""
        n = self.n_pixels
        for a in range(0, n, rows):
            sl = slice(a, min(n, a + rows))
            yield sl, decode(np.asarray(self.stored[sl]), self.cube.n_texels, self.encoding, raw)

    def block(self, rows: slice, raw: bool = False) -> np.ndarray:
        """(p, N) float32 V of a slice of pixel rows; `raw` as in `blocks`."""
        return decode(np.asarray(self.stored[rows]), self.cube.n_texels, self.encoding, raw)

    def dense(self) -> np.ndarray:
        """(P, N) float32 V (small scenes and tests only)."""
        return decode(np.asarray(self.stored[:]), self.cube.n_texels, self.encoding)


def compute_visibility(backend, samples: PixelSamples, cube: CubeMap, supersample: int = 1,
                       rows_per_chunk: int = 512, progress=None) -> VisibilityData:
    """Whole visibility in memory (the cached stage instead writes chunk by chunk, resumably)."""
    width = (cube.n_texels + 7) // 8 if supersample == 1 else cube.n_texels
    parts = [np.zeros((0, width), np.uint8)]
    for a in range(0, len(samples), rows_per_chunk):
        parts.append(visibility_rows(backend, samples, slice(a, min(len(samples), a + rows_per_chunk)),
                                     cube, supersample))
        if progress:
            progress(min(len(samples), a + rows_per_chunk), len(samples))
    return VisibilityData(samples, cube, supersample, np.concatenate(parts, axis=0), castable_only=True)


# -- adaptive visibility: cast where the image says the shadows change ------------------------------
CAST_CHUNK = 1 << 16  # shadow rays gathered and traced together (per thread)
BASE_PIXELS = 800  # the base grid of `coherent_visibility` has about this many pixels
STEP_PIXELS = 1024  # pixels of a refinement step inferred and settled together (one thread's block)
CHECK_ENTRIES = 20_000  # inferred (pixel, texel) entries re-cast to measure the inference's error


def base_spacing(n_pixels: int) -> int:
    """The power-of-two pixel spacing of the base grid for `n_pixels` used pixels (~BASE_PIXELS on it)."""
    s = np.sqrt(max(n_pixels, 1) / BASE_PIXELS)
    return int(2 ** max(0, int(round(np.log2(max(s, 1.0))))))


@dataclass
class AdaptiveStats:
    """What `coherent_visibility` did: rays cast, entries inferred, and the measured error of the
    inference (re-cast entries that disagree with the inferred value)."""

    spacing: int
    castable: int  # (pixel, texel) entries in front of both normals (what the exhaustive route casts)
    cast: int  # entries traced (rays for supersample 1; sub-rays are counted once per entry)
    inferred: int
    checked: int
    wrong: int
    inferred_last: int = 0  # inferred entries of the latest step

    @property
    def error_rate(self) -> float:
        return self.wrong / self.checked if self.checked else 0.0

    def as_dict(self) -> dict:
        return {"method": "adaptive", "base_spacing_px": self.spacing, "castable_entries": self.castable,
                "cast_entries": self.cast, "inferred_entries": self.inferred,
                "inferred_fraction": self.inferred / max(self.castable, 1), "checked_entries": self.checked,
                "wrong_in_check": self.wrong, "check_error_rate": self.error_rate}


def _cast_entries(backend, origins: np.ndarray, geo: np.ndarray, pixel: np.ndarray, texel: np.ndarray,
                  cube: CubeMap, supersample: int, threads: bool = True) -> np.ndarray:
    """Visibility of selected (pixel, texel) entries: bool for supersample 1, else uint8 fractions.
    `origins` and `geo` are per pixel (already offset, in the backend's frame); `threads` False
    casts on the calling thread (a caller that is itself one of `parallel_blocks`' workers)."""
    from concurrent.futures import ThreadPoolExecutor

    from ..threads import parallel_blocks

    if len(pixel) == 0:
        return np.zeros(0, bool if supersample == 1 else np.uint8)
    if supersample == 1:  # chunks of rays gathered and traced on each thread (no full-size copies)
        dirs32 = cube.directions.astype(np.float32)
        n = len(pixel)
        out = np.empty(n, bool)

        def run(mine):
            # (gathered by np.take into this thread's buffers: fancy indexing allocates each chunk and
            # took a third of the kernel's time, 91 against 28 ms for 2 M rays)
            o = np.empty((min(n, CAST_CHUNK), 3), np.float32)
            d = np.empty_like(o)
            for a in mine:
                sl = slice(a, min(n, a + CAST_CHUNK))
                k = sl.stop - sl.start
                np.take(origins, pixel[sl], axis=0, out=o[:k])
                np.take(dirs32, texel[sl], axis=0, out=d[:k])
                out[sl] = ~backend.occluded_local(o[:k], d[:k])

        starts = list(range(0, n, CAST_CHUNK))
        if not threads or backend.threads == 1 or len(starts) == 1:
            run(starts)
        else:
            parallel_blocks(run, starts)
        return out
    # supersampled: each entry's sub-rays, those behind the geometric normal not traced
    sub = cube.subtexel_directions(supersample).astype(np.float32)[texel]  # (n, kk, 3)
    kk = sub.shape[1]
    live = np.where(np.einsum("nk,nsk->ns", geo[pixel], sub) > 0, np.float32(np.inf), np.float32(-1.0)).ravel()
    dirs = sub.reshape(-1, 3)
    o = np.repeat(origins[pixel], kk, axis=0)
    bounds = np.linspace(0, len(o), min(backend.threads if threads else 1, len(o)) + 1).astype(int)
    parts = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]

    def trace(sl):
        return ~backend.occluded_local(o[sl], dirs[sl], live[sl])

    if len(parts) == 1:
        visible = trace(parts[0])
    else:
        with ThreadPoolExecutor(len(parts)) as pool:
            visible = np.concatenate(list(pool.map(trace, parts)))
    counts = (visible & (live > 0)).reshape(-1, kk).sum(axis=1)
    return np.round(255.0 * counts / kk).astype(np.uint8)


def _set_bits(packed: np.ndarray):
    """The set bits of bit-packed rows (little bit order).

    Returns (row, texel) of each set bit in row-major order, and `where`: the (row, byte) of each
    non-zero byte with, per set bit, its byte's position in that list and its bit (for `_pack_bits`).
    """
    flat = np.flatnonzero(packed)  # (flat indices and shifts: ~2x numpy's 2-D nonzero)
    byte_rows, byte_cols = np.divmod(flat, packed.shape[1])
    bits = np.flatnonzero(np.unpackbits(packed.ravel()[flat], bitorder="little"))  # byte k's bit b: 8 k + b
    k, b = bits >> 3, bits & 7
    return byte_rows[k], byte_cols[k] * 8 + b, (byte_rows, byte_cols, k, b)


def _pack_bits(values: np.ndarray, where) -> np.ndarray:
    """One bool per set bit (in `_set_bits` order) packed into the bytes `_set_bits` listed; bits
    that were not set are 0."""
    byte_rows, _, k, b = where
    if len(k) == 0:
        return np.zeros(len(byte_rows), np.uint8)
    first = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])  # every listed byte has a set bit
    return np.add.reduceat(values.astype(np.uint8) << b.astype(np.uint8), first).astype(np.uint8)


def _on_threads(fn, blocks: list, threads: int) -> list:
    """[fn(b) for b in blocks] on up to `threads` threads (at most 2: the machine's cores), each
    taking the next block when it finishes one (the blocks' costs differ: shadow boundaries)."""
    import os

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    workers = min(2, threads, cores, len(blocks))
    if workers <= 1:
        return [fn(b) for b in blocks]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(fn, blocks))


def coherent_visibility(backend, samples: PixelSamples, cube: CubeMap, supersample: int = 1,
                        spacing: int | None = None, check_entries: int = CHECK_ENTRIES, seed: int = 0,
                        progress=None, image_size: tuple[int, int] | None = None) -> tuple[np.ndarray, AdaptiveStats]:
    """Visibility of every used pixel, casting rays only where the shadows change across the image.

    Neighbouring pixels see nearly the same occluders: a shadow boundary is a curve in the image
    for each light direction, and away from it a pixel's visibility equals its neighbours'. The
    pixels on a grid of `spacing` pixels (a power of two; default `base_spacing`) are cast in
    full. Then, halving the spacing, the centres of the grid's squares, then the midpoints of their
    vertical edges, then of their horizontal ones, each take a texel's value from their known
    neighbours among the 8 at that spacing when at least 4 of them are known (or, with
    `image_size` (height, width) given, 3 with the others beyond the image's border: a pixel on the
    border between two known ones, where the grid's last cell is cut off), all of them could
    see the texel (it is in front of their normals) and they agree on it (all lit, or all in
    shadow); every other texel the pixel could see is cast. Pixels at silhouettes and mask edges,
    and texels near a pixel's horizon, are therefore cast, and a shadow narrower than the
    grid is found wherever it touches a known pixel at some spacing.

    What this misses (an occluder whose shadow slips between all the known pixels) is measured: a
    fixed random sample of `check_entries` inferred entries is cast again and the disagreement
    counted (`AdaptiveStats.error_rate`). On the Mitsuba test scenes ~1e-4 of the entries are
    wrong and the relit view differs from the exhaustive one by ~0.1 % (its noise is 0.5 %);
    directions that carry a large share of a light (a sun) are cast exactly before rendering
    (`recast_columns`).

    Returns
    -------
    (P, ceil(N/8)) uint8 bit-packed rows (supersample 1) or (P, N) uint8 fractions, as
    `visibility_rows` stores them, and the statistics.
    """
    P = len(samples)
    N = cube.n_texels
    nb = (N + 7) // 8
    spacing = base_spacing(P) if spacing is None else int(spacing)
    if spacing < 1 or spacing & (spacing - 1):
        raise ValueError(f"spacing must be a power of two, got {spacing}")
    pix = samples.pixel.astype(np.int64)
    H, W = int(pix[:, 0].max()) + 1, int(pix[:, 1].max()) + 1
    index = np.full((H + 2 * spacing, W + 2 * spacing), -1, np.int64)  # padded: neighbours off the image are absent
    index[pix[:, 0] + spacing, pix[:, 1] + spacing] = np.arange(P)
    geo = samples.geometric_normal.astype(np.float32)
    origins = backend.shadow_origins(samples.position, samples.geometric_normal, samples.face)
    dirs = cube.directions.astype(np.float32)
    # castable entries, bit-packed (the stored rows hold V = 0 where a texel is not castable)
    can = castable_bits(samples.normal, geo, dirs)
    lit = np.zeros((P, nb), np.uint8)  # fully visible
    dark = np.zeros((P, nb), np.uint8)  # castable and fully occluded
    frac = None if supersample == 1 else np.zeros((P, N), np.uint8)
    known = np.zeros(P, bool)
    stats = AdaptiveStats(spacing, int(np.bitwise_count(can).sum(dtype=np.int64)), 0, 0, 0, 0)
    rng = np.random.default_rng(seed)
    check = []  # (pixel, texel, inferred lit) of sampled inferred entries

    def settle(j: np.ndarray, need: np.ndarray, inferred_lit: np.ndarray, threads: bool = True) -> int:
        """Cast the `need` bits of pixels j (packed rows), take the inferred values elsewhere;
        returns the number of entries cast."""
        rows, texels, where = _set_bits(need)
        value = _cast_entries(backend, origins, geo, j[rows], texels, cube, supersample, threads)
        full = value if supersample == 1 else value == 255
        lit[j] = inferred_lit & ~need
        dark[j] = can[j] & ~need & ~inferred_lit
        target = (j[where[0]], where[1])
        lit[target] |= _pack_bits(full, where)
        dark[target] |= _pack_bits(~full if supersample == 1 else value == 0, where)
        if supersample > 1:
            frac[j] = np.where(np.unpackbits(lit[j], axis=1, count=N, bitorder="little").astype(bool), np.uint8(255),
                               np.uint8(0))
            frac[j[rows], texels] = value
        known[j] = True
        return len(rows)

    # the base grid: every castable texel is cast
    base = np.flatnonzero((pix[:, 0] % spacing == 0) & (pix[:, 1] % spacing == 0))
    if len(base):
        rows = visibility_rows(backend, samples, base, cube, supersample)
        stats.cast += int(np.bitwise_count(can[base]).sum(dtype=np.int64))
        if supersample == 1:
            lit[base] = rows
        else:
            frac[base] = rows
            lit[base] = np.packbits(rows == 255, axis=1, bitorder="little")
            rows = np.packbits(rows == 0, axis=1, bitorder="little")
        dark[base] = can[base] & ~(lit[base] if supersample == 1 else ~rows)
        known[base] = True
    h = spacing // 2
    steps = []
    while h >= 1:
        steps += [(h, "centres"), (h, "columns"), (h, "rows")]
        h //= 2
    ring = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]
    for done, (h, kind) in enumerate(steps):
        r, c = pix[:, 0], pix[:, 1]
        on = (r % h == 0) & (c % h == 0)
        odd_r, odd_c = r % (2 * h) == h, c % (2 * h) == h
        sel = on & {"centres": odd_r & odd_c, "columns": odd_r & ~odd_c, "rows": ~odd_r & odd_c}[kind]
        offsets = [(h * dr, h * dc) for dr, dc in ring]  # every known one of the 8 at distance h
        j = np.flatnonzero(sel & ~known)
        if len(j):
            m = len(j)
            need = np.empty((m, nb), np.uint8)  # cast these
            inferred = np.empty((m, nb), np.uint8)  # take these from the neighbours
            inferred_lit = np.empty((m, nb), np.uint8)  # (those of them lit)
            blocks = [slice(a, min(m, a + STEP_PIXELS)) for a in range(0, m, STEP_PIXELS)]

            def infer(b: slice):
                # the AND over the known neighbours of their lit and dark bits: a texel every known
                # neighbour sees lit (or dark) is castable from each of them (lit and dark are subsets
                # of castable), so the neighbours agree on it and could all see it
                jb = j[b]
                all_lit = np.full((len(jb), nb), 0xFF, np.uint8)
                all_dark = np.full((len(jb), nb), 0xFF, np.uint8)
                present = np.zeros(len(jb), np.int64)
                beyond = np.zeros(len(jb), np.int64)  # neighbours beyond the image's border
                for dr, dc in offsets:
                    if image_size is not None:
                        rr, cc = pix[jb, 0] + dr, pix[jb, 1] + dc
                        beyond += (rr < 0) | (rr >= image_size[0]) | (cc < 0) | (cc >= image_size[1])
                    k = index[pix[jb, 0] + spacing + dr, pix[jb, 1] + spacing + dc]
                    ok = k >= 0
                    ok[ok] = known[k[ok]]
                    kk = k[ok]
                    present += ok
                    all_lit[ok] &= lit[kk]
                    all_dark[ok] &= dark[kk]
                agree = all_lit | all_dark
                # 4 known neighbours, or at the image's border 3 with the others beyond it (a pixel on
                # the border between two known ones: the grid's last cell there is cut off)
                agree[(present < 4) & ((present < 3) | (present + beyond < 4))] = 0
                cj = can[jb]
                need[b] = cj & ~agree
                np.bitwise_and(cj, agree, out=inferred[b])
                np.bitwise_and(inferred[b], all_lit, out=inferred_lit[b])
                return int(np.bitwise_count(inferred[b]).sum(dtype=np.int64))

            stats.inferred_last = sum(_on_threads(infer, blocks, backend.threads))
            stats.inferred += stats.inferred_last
            # sample a few inferred entries for the check (re-cast below)
            if check_entries > 0:
                total = stats.inferred_last
                take = min(total, int(np.ceil(check_entries * total / max(stats.castable, 1))) + 1)
                if take:  # random (pixel, texel) entries of this step, kept where they were inferred
                    tries = int(take * (len(j) * N) / max(total, 1) * 1.5) + 16
                    pr = rng.integers(0, len(j), tries)
                    pt = rng.integers(0, N, tries)
                    byte, bit = pt >> 3, (pt & 7).astype(np.uint8)
                    hit = ((inferred[pr, byte] >> bit) & 1).astype(bool)
                    pr, pt, byte, bit = pr[hit][:take], pt[hit][:take], byte[hit][:take], bit[hit][:take]
                    want = ((inferred_lit[pr, byte] >> bit) & 1).astype(bool)
                    check.append((j[pr], pt, want))
            # each block's bookkeeping and rays on one thread: the bit work runs on both cores too
            stats.cast += sum(_on_threads(lambda b: settle(j[b], need[b], inferred_lit[b], threads=False), blocks,
                                          backend.threads))
        if progress:
            progress(done + 1, len(steps))
    if not known.all():  # pixels whose grid position no step reaches (cannot happen: every pixel is on the finest grid)
        j = np.flatnonzero(~known)
        stats.cast += settle(j, can[j], np.zeros((len(j), nb), np.uint8))
    if check:
        pj = np.concatenate([c[0] for c in check])
        pt = np.concatenate([c[1] for c in check])
        want = np.concatenate([c[2] for c in check])
        got = _cast_entries(backend, origins, geo, pj, pt, cube, supersample)
        got = got if supersample == 1 else got == 255
        stats.checked, stats.wrong = len(pj), int(np.count_nonzero(got != want))
    if supersample == 1:
        return lit, stats
    return frac, stats


def recast_columns(backend, samples: PixelSamples, cube: CubeMap, stored: np.ndarray, texels: np.ndarray,
                   supersample: int = 1) -> np.ndarray:
    """A copy of the stored rows with the visibility toward some texels cast for every pixel
    (where castable): what an adaptive visibility inferred for those directions becomes exact."""
    texels = np.asarray(texels, np.int64)
    out = np.array(stored, copy=True)
    if len(texels) == 0:
        return out
    geo = samples.geometric_normal.astype(np.float32)
    origins = backend.shadow_origins(samples.position, samples.geometric_normal, samples.face)
    can = castable(samples.normal, geo, cube.directions[texels])  # (P, t)
    for k, t in enumerate(texels):
        rows = np.flatnonzero(can[:, k])
        value = _cast_entries(backend, origins, geo, rows, np.full(len(rows), t), cube, supersample)
        if supersample == 1:
            byte, bit = t >> 3, np.uint8(1 << (t & 7))
            out[:, byte] &= ~bit
            out[rows, byte] |= np.where(value, bit, np.uint8(0))
        else:
            out[:, t] = 0
            out[rows, t] = value
    return out
