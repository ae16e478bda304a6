"""The fit sample and the held-out sample (`light.sampling`): nothing in them depends on the scene
being one of ours. They are built here on synthetic pixel sets of other sizes, shapes, masks and
orders, and must keep what the weighted least squares relies on: weights that make the sample's
sums estimate the all-pixel ones without bias, the pixels where shadows change, heads spread over
the whole image (a smaller sample is the head of a larger one), and no dependence on pixel order.
"""

import numpy as np
import pytest

from pipelines.light import sampling


def _pixels(shape: str, rng) -> np.ndarray:
    """(P, 2) row, col of a synthetic used-pixel set."""
    if shape == "wide strip":  # 37 x 2000: nothing like a 4:3 photo
        r, c = np.mgrid[0:37, 0:2000]
        return np.stack([r.ravel(), c.ravel()], 1)
    if shape == "large disc":  # a 1000 x 1400 photo's central disc
        r, c = np.mgrid[0:1000, 0:1400]
        keep = (r - 500) ** 2 + (c - 700) ** 2 < 450**2
        return np.stack([r[keep], c[keep]], 1)
    if shape == "random mask":  # 480 x 640 with a third of the pixels masked out at random
        r, c = np.mgrid[0:480, 0:640]
        keep = rng.random(r.shape) > 0.33
        return np.stack([r[keep], c[keep]], 1)
    if shape == "two blobs":  # two far-apart objects in a big frame
        r, c = np.mgrid[0:300, 0:300]
        a = np.stack([r.ravel() + 100, c.ravel() + 50], 1)
        b = np.stack([r.ravel() + 2500, c.ravel() + 3000], 1)
        return np.concatenate([a, b])
    raise ValueError(shape)


SHAPES = ["wide strip", "large disc", "random mask", "two blobs"]


def _field(pixels: np.ndarray) -> np.ndarray:
    """A smooth positive per-pixel quantity (what a squared residual looks like, roughly)."""
    r, c = pixels[:, 0] / 97.0, pixels[:, 1] / 131.0
    return 1.5 + np.sin(r) * np.cos(c) + 0.3 * np.sin(3 * r + c)


@pytest.mark.parametrize("shape", SHAPES)
def test_weighted_sample_estimates_the_all_pixel_sum(shape):
    rng = np.random.default_rng(1)
    pixels = _pixels(shape, rng)
    P = len(pixels)
    candidates = rng.random(P) > 0.1
    change = rng.poisson(0.2, P) * (rng.random(P) < 0.05)  # a few pixels where shadows change
    s = sampling.fit_sample(pixels, candidates, change)
    assert len(s.rows) == sampling.FIT_ROWS < candidates.sum()
    assert len(np.unique(s.rows)) == len(s.rows) and candidates[s.rows].all()
    assert s.candidates == candidates.sum()
    assert np.isclose(s.weights.sum(), candidates.sum())  # the weights count every candidate once
    f = _field(pixels)
    f[change > 0] *= 5.0  # the boundary pixels differ from the rest: their weight must be 1
    truth = f[candidates].sum()
    assert abs((s.weights * f[s.rows]).sum() / truth - 1) < 0.01
    # a head of the sample stands for all of it too (the refinement levels use one)
    head = slice(0, 4096)
    w = s.weights[head] * s.weights.sum() / s.weights[head].sum()
    assert abs((w * f[s.rows[head]]).sum() / truth - 1) < 0.03


@pytest.mark.parametrize("shape", SHAPES)
def test_sample_takes_the_pixels_where_visibility_changes(shape):
    rng = np.random.default_rng(2)
    pixels = _pixels(shape, rng)
    P = len(pixels)
    change = np.zeros(P, np.int64)
    hot = rng.choice(P, 1000, replace=False)
    change[hot] = rng.integers(1, 50, len(hot))
    s = sampling.fit_sample(pixels, np.ones(P, bool), change)
    assert set(hot) <= set(s.rows.tolist())
    assert np.all(s.weights[np.isin(s.rows, hot)] == 1.0)


@pytest.mark.parametrize("shape", SHAPES)
def test_every_head_is_spread_over_the_image(shape):
    """The first k rows cover the used pixels like a grid of k points would: no used pixel is far
    from a head pixel (within a few grid spacings of sqrt(area / k))."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    pixels = _pixels(shape, rng)
    P = len(pixels)
    s = sampling.fit_sample(pixels, np.ones(P, bool), np.zeros(P, np.int64))
    probe = pixels[rng.choice(P, 4000, replace=False)]
    for k in (1024, 4096, 16384):
        tree = cKDTree(pixels[s.rows[:k]])
        dist, _ = tree.query(probe)
        assert dist.max() < 4.0 * np.sqrt(P / k), (k, dist.max())


def test_sample_does_not_depend_on_pixel_order():
    rng = np.random.default_rng(4)
    pixels = _pixels("random mask", rng)
    P = len(pixels)
    change = rng.integers(0, 3, P) * (rng.random(P) < 0.1)
    a = sampling.fit_sample(pixels, np.ones(P, bool), change)
    perm = rng.permutation(P)
    b = sampling.fit_sample(pixels[perm], np.ones(P, bool), change[perm])
    ka = {tuple(p): w for p, w in zip(pixels[a.rows].tolist(), a.weights)}
    kb = {tuple(p): w for p, w in zip(pixels[perm][b.rows].tolist(), b.weights)}
    # the same pixels with the same weights (ties in `change` may pick other boundary pixels of
    # equal change, so compare the spread part and the boundary count)
    assert a.boundary == b.boundary
    spread_a = {p for p, w in ka.items() if w != 1.0}
    spread_b = {p for p, w in kb.items() if w != 1.0}
    assert len(spread_a ^ spread_b) < 0.02 * len(spread_a)


def test_small_scenes_use_every_pixel():
    rng = np.random.default_rng(5)
    r, c = np.mgrid[0:60, 0:80]
    pixels = np.stack([r.ravel(), c.ravel()], 1)
    s = sampling.fit_sample(pixels, np.ones(len(pixels), bool), np.zeros(len(pixels), np.int64))
    assert len(s.rows) == len(pixels) and np.all(s.weights == 1.0)
    assert np.array_equal(np.sort(s.rows), np.arange(len(pixels)))
    held = rng.random(len(pixels)) < 0.1
    h = sampling.held_out_sample(pixels, held)
    assert np.array_equal(np.sort(h.rows), np.flatnonzero(held)) and np.all(h.weights == 1.0)
    # taken whole, the rows still come in stratified order: a head (what the explore set, the
    # reflectance rounds and the probe take) spans the image, not its top rows
    for rows, k in ((s.rows, 512), (h.rows, 120)):
        head = pixels[rows[:k]]
        assert head[:, 0].max() - head[:, 0].min() >= 50 and head[:, 1].max() - head[:, 1].min() >= 70, k
        assert abs(head[:, 0].mean() - 29.5) < 4 and abs(head[:, 1].mean() - 39.5) < 5


@pytest.mark.parametrize("shape", SHAPES)
def test_held_out_sample_is_spread_and_unbiased(shape):
    rng = np.random.default_rng(6)
    pixels = _pixels(shape, rng)
    held = rng.random(len(pixels)) < 0.2
    h = sampling.held_out_sample(pixels, held)
    n = int(held.sum())
    assert len(h.rows) == min(n, sampling.MAX_HELD_OUT_ROWS) and held[h.rows].all()
    assert np.isclose(h.weights.sum(), n)
    f = _field(pixels)
    assert abs((h.weights * f[h.rows]).sum() / f[held].sum() - 1) < 0.01
    # its head is spread too: the first 1,024 rows' rows of the image span what the whole does
    head, whole = pixels[h.rows[:1024]], pixels[h.rows]
    assert np.ptp(head[:, 0]) > 0.9 * np.ptp(whole[:, 0]) and np.ptp(head[:, 1]) > 0.9 * np.ptp(whole[:, 1])


def test_visibility_change_counts_differing_texels():
    """Two 3 x 3 images of bit-packed rows: the centre pixel differs from its 4 neighbours in
    exactly the bits set here; pixels without a neighbour on a side count only the others."""
    r, c = np.mgrid[0:3, 0:3]
    pixels = np.stack([r.ravel(), c.ravel()], 1)
    stored = np.zeros((9, 2), np.uint8)
    stored[4] = [0b1011, 0b1]  # 4 bits set at the centre
    change = sampling.visibility_change(pixels, stored)
    assert change[4] == 4 * 4  # differs from each of its 4 neighbours by 4 bits
    assert change[1] == change[3] == change[5] == change[7] == 4  # the edge pixels touch the centre once
    assert change[0] == change[2] == change[6] == change[8] == 0


def test_visibility_change_matches_a_pixel_by_pixel_count():
    """Against the definition, pixel by pixel (each of its 4 neighbours compared), on a 150 x 120
    image with holes (more pairs than one block: both threads), bit-packed and fraction rows."""
    rng = np.random.default_rng(5)
    keep = rng.random((150, 120)) > 0.2
    pixels = np.argwhere(keep)
    at = {tuple(p): i for i, p in enumerate(pixels)}
    for encoding, width in (("bits", 7), ("fraction", 12)):
        stored = rng.integers(0, 256 if encoding == "bits" else 3, size=(len(pixels), width)).astype(np.uint8)
        want = np.zeros(len(pixels), np.int64)
        for i, (r, c) in enumerate(pixels):
            for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
                j = at.get((r + dr, c + dc))
                if j is not None:
                    want[i] += (np.unpackbits(stored[i] ^ stored[j]).sum() if encoding == "bits"
                                else (stored[i] != stored[j]).sum())
        got = sampling.visibility_change(pixels, stored, encoding)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, want)
