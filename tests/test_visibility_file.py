"""The visibility cache file: rows written in any blocks read back bit for bit, through HDF5's own
gzip filter (the chunks are deflated on threads and written as stored: `_write_rows`)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from pipelines.geometry.camera import PixelSamples
from pipelines.io.visibility_file import read_visibility, write_visibility
from pipelines.light.cubemap import CubeMap


def _samples(n: int, rng) -> PixelSamples:
    def unit(v):
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    return PixelSamples(pixel=np.stack([np.arange(n) // 50, np.arange(n) % 50], axis=1).astype(np.int32),
                        position=rng.normal(size=(n, 3)), normal=unit(rng.normal(size=(n, 3))),
                        geometric_normal=unit(rng.normal(size=(n, 3))), view=unit(rng.normal(size=(n, 3))),
                        face=rng.integers(0, 1000, n), normal_jacobian=rng.normal(size=(n, 3, 2)).astype(np.float32))


@pytest.mark.parametrize("n, cuts, chunk", [
    (2500, [], 1024),  # one block: two whole chunks and a partial last one
    (2500, [1024, 2048], 1024),  # chunk-aligned blocks
    (2500, [700, 1500, 2100], 1024),  # blocks across chunk boundaries
    (3072, [], 1024),  # whole chunks only
    (37, [], 1024),  # fewer rows than a chunk
])
def test_rows_and_samples_read_back_exactly(tmp_path, n, cuts, chunk):
    rng = np.random.default_rng(n + len(cuts))
    cube = CubeMap(8)
    width = (cube.n_texels + 7) // 8
    # shadow-like rows (runs of lit and dark bytes, that deflate) and some noise
    rows = np.where(rng.random((n, 1)) < 0.5, np.uint8(0xFF), np.uint8(0)) * np.ones((1, width), np.uint8)
    noise = rng.random((n, width)) < 0.1
    rows[noise] = rng.integers(0, 256, int(noise.sum()), dtype=np.uint8)
    samples = _samples(n, rng)
    blocks = np.split(rows, cuts)
    write_visibility(tmp_path / "v.h5", samples, cube, 1, iter(blocks), chunk)
    back = read_visibility(tmp_path / "v.h5")
    np.testing.assert_array_equal(back.stored, rows)
    for name in PixelSamples.FIELDS:
        np.testing.assert_array_equal(getattr(back.samples, name), getattr(samples, name))
    with h5py.File(tmp_path / "v.h5", "r") as f:  # (a plain gzip dataset: any HDF5 reader opens it)
        ds = f["visibility"]
        assert ds.compression == "gzip" and ds.chunks == (min(n, chunk), width)
        np.testing.assert_array_equal(ds[:], rows)
        assert ds.id.get_storage_size() < rows.nbytes / 2  # (deflated)
