"""Which pixels the light is fitted to: a weighted sample that keeps the information, and the held-out set.

A light of a few hundred coefficients does not need 50,000 pixels, but neither is every pixel
worth the same: where shadows change across the image (a pixel's visibility differs from its
neighbours') the pixels tell the light's detail, in uniformly lit areas each pixel repeats its
neighbours. The fit sample therefore takes the pixels whose visibility differs most from their
neighbours' (weight 1) and a spatially stratified share of the rest, each weighted by the pixels
it stands for, so that the weighted least-squares objective estimates the all-pixel one without
bias (Horvitz-Thompson).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FIT_ROWS = 16384  # the fit sample's size (all fit pixels when there are fewer): see `fit_sample`
BOUNDARY_SHARE = 0.25  # the share of the sample given to the pixels where visibility changes most
MAX_HELD_OUT_ROWS = 8192  # held-out pixels evaluated (a stratified subset when there are more)


def _bit_reverse(x: np.ndarray, bits: int = 16) -> np.ndarray:
    x = x.astype(np.uint64)
    out = np.zeros_like(x)
    for b in range(bits):
        out |= ((x >> np.uint64(b)) & np.uint64(1)) << np.uint64(bits - 1 - b)
    return out


def stratified_order(pixels: np.ndarray) -> np.ndarray:
    """A permutation of the pixels ((P, 2) row, col) whose every prefix is spread evenly over the
    image: pixels sorted by the interleaved bits of their bit-reversed row and column, so the
    first 1/4 is every 2nd row and column, the first 1/16 every 4th, and so on."""
    r, c = _bit_reverse(pixels[:, 0]), _bit_reverse(pixels[:, 1])
    key = np.zeros(len(pixels), np.uint64)
    for b in range(16):
        key |= ((r >> np.uint64(15 - b)) & np.uint64(1)) << np.uint64(2 * (15 - b) + 1)
        key |= ((c >> np.uint64(15 - b)) & np.uint64(1)) << np.uint64(2 * (15 - b))
    return np.argsort(key, kind="stable")


def visibility_change(pixels: np.ndarray, stored: np.ndarray, encoding: str = "bits") -> np.ndarray:
    """(P,) how many texels' visibility differ between a pixel and its 4 neighbours, summed (rows
    as stored: bit-packed, or uint8 fractions). Pixels without a neighbour count 0.

    Each neighbouring pair is compared once (right and down; the count goes to both pixels), in
    blocks on both cores."""
    from ..threads import parallel_blocks

    P = len(pixels)
    H, W = int(pixels[:, 0].max()) + 2, int(pixels[:, 1].max()) + 2
    index = np.full((H + 1, W + 1), -1, np.int64)
    index[pixels[:, 0] + 1, pixels[:, 1] + 1] = np.arange(P)
    score = np.zeros(P, np.int64)
    for dr, dc in ((0, 1), (1, 0)):
        k = index[pixels[:, 0] + 1 + dr, pixels[:, 1] + 1 + dc]
        ok = np.flatnonzero(k >= 0)
        differ = np.empty(len(ok), np.int64)

        def run(starts):
            for a in starts:
                sel = ok[a:a + 8192]
                mine, theirs = np.asarray(stored[sel]), np.asarray(stored[k[sel]])
                if encoding == "bits":
                    differ[a:a + len(sel)] = np.bitwise_count(mine ^ theirs).sum(axis=1, dtype=np.int64)
                else:
                    differ[a:a + len(sel)] = (mine != theirs).sum(axis=1, dtype=np.int64)

        parallel_blocks(run, list(range(0, len(ok), 8192)))
        score += np.bincount(ok, differ, P).astype(np.int64) + np.bincount(k[ok], differ, P).astype(np.int64)
    return score


@dataclass(frozen=True)
class Sample:
    """Rows (indices into the used pixels) with their weights, and why this many."""

    rows: np.ndarray
    weights: np.ndarray
    candidates: int  # pixels the sample stands for
    boundary: int  # rows taken for their changing visibility
    reason: str

    def summary(self) -> dict:
        return {"rows": int(len(self.rows)), "stands_for": self.candidates, "boundary_rows": self.boundary,
                "reason": self.reason}


def fit_sample(pixels: np.ndarray, candidates: np.ndarray, change: np.ndarray, size: int = FIT_ROWS) -> Sample:
    """The fit sample among the `candidates` (bool over the used pixels): `size` rows, or every
    candidate (weight 1) when there are no more.

    The size: a light of up to ~1,500 coefficients (what R = 32 refines to on the test scenes)
    fitted to 16,384 rows of which a quarter are where visibility changes gives the all-pixel
    light's held-out and probe errors within a few per cent (benchmarks/RESULTS.md); the rows'
    transport takes rows x texels x 4 bytes x 4/3 (the pyramid), 0.27 GB at R = 32, 1.1 GB at 64.
    """
    idx = np.flatnonzero(candidates)
    want = int(size)
    if len(idx) <= want:  # every candidate, in stratified order: a head is still spread
        return Sample(idx[stratified_order(pixels[idx])], np.ones(len(idx)), len(idx), 0,
                      f"all {len(idx)} fit pixels (at most {want} rows)")
    n_boundary = int(BOUNDARY_SHARE * want)
    order = np.argsort(-change[idx], kind="stable")
    boundary = idx[order[:n_boundary]]
    rest = np.setdiff1d(idx, boundary, assume_unique=True)
    spread = stratified_order(pixels[rest])
    m = want - n_boundary
    taken = rest[spread[:m]]
    # every prefix of the sample is spread like the whole (so that a smaller sample is its head):
    # each group in stratified order, the two interleaved in proportion
    boundary = boundary[stratified_order(pixels[boundary])]
    position = np.concatenate([(np.arange(n_boundary) + 0.5) / max(n_boundary, 1), (np.arange(m) + 0.5) / m])
    rows = np.concatenate([boundary, taken])
    weights = np.concatenate([np.ones(n_boundary), np.full(m, len(rest) / m)])
    order = np.argsort(position, kind="stable")
    return Sample(rows[order], weights[order], len(idx), n_boundary,
                  f"{want} of {len(idx)} fit pixels: the {n_boundary} whose visibility changes most "
                  f"from their neighbours', and {m} spread over the rest, each standing for {len(rest) / m:.2f}")


def held_out_sample(pixels: np.ndarray, held_out: np.ndarray, max_rows: int = MAX_HELD_OUT_ROWS) -> Sample:
    """The held-out pixels evaluated: all of them, or a stratified `max_rows` of them; in
    stratified order either way, so that every head (the reflectance probe's, the LM's) is spread
    over the image like the whole."""
    idx = np.flatnonzero(held_out)
    order = stratified_order(pixels[idx])
    if len(idx) <= max_rows:
        return Sample(idx[order], np.ones(len(idx)), len(idx), 0, f"all {len(idx)} held-out pixels")
    taken = idx[order[:max_rows]]
    return Sample(taken, np.full(len(taken), len(idx) / max_rows), len(idx), 0,
                  f"{max_rows} of {len(idx)} held-out pixels, spread over the image")


def with_bounds(sample: Sample, bounds: np.ndarray) -> Sample:
    """The sample with the clipped pixels `bounds` appended, each standing for itself (lower bounds
    that the robust pass fits: `light.robust`). The heads of the sample are unchanged."""
    bounds = np.asarray(bounds, np.int64)
    if not len(bounds):
        return sample
    return Sample(np.concatenate([sample.rows, bounds]), np.concatenate([sample.weights, np.ones(len(bounds))]),
                  sample.candidates + len(bounds), sample.boundary,
                  f"{sample.reason}; and the {len(bounds)} clipped pixels (lower bounds), each standing for itself")
