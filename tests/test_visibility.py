"""The adaptive visibility (`geometry.visibility.coherent_visibility`) against every ray cast
(`compute_visibility`) on a Mitsuba scene: the same bits but for the few its inference misses, and
what it reports of them (the re-cast check) is what it gets wrong."""

import numpy as np
import pytest

from pipelines.geometry.visibility import coherent_visibility, compute_visibility, decode
from pipelines.light.cubemap import CubeMap


@pytest.mark.parametrize("supersample", [1, 2])
def test_adaptive_visibility_matches_every_ray_cast(mitsuba_scene, supersample):
    scene = mitsuba_scene("bunny_sun")
    cube = CubeMap(8)
    exact = compute_visibility(scene.backend, scene.samples, cube, supersample)
    stored, stats = coherent_visibility(scene.backend, scene.samples, cube, supersample)
    encoding = "bits" if supersample == 1 else "fraction"
    a = decode(stored, cube.n_texels, encoding)
    b = decode(np.asarray(exact.stored), cube.n_texels, encoding)
    castable = stats.castable
    assert stats.cast < 0.5 * castable  # most entries were inferred
    wrong = int(np.count_nonzero(np.abs(a - b) > 1e-6))
    assert wrong <= 2e-3 * castable
    assert stats.wrong <= max(5, 5 * stats.checked * wrong / max(stats.inferred, 1) + 5)


@pytest.mark.parametrize("supersample", [1, 2])
def test_adaptive_visibility_is_the_same_on_one_thread_and_in_small_blocks(mitsuba_scene, monkeypatch, supersample):
    """A refinement step's pixels go in blocks on two threads: the bits and the statistics (the
    check's random sample included) do not depend on the threads or the block size."""
    from pipelines.geometry import raycast
    from pipelines.geometry import visibility as gv

    scene = mitsuba_scene("bunny_sun")
    cube = CubeMap(8)
    stored, stats = coherent_visibility(scene.backend, scene.samples, cube, supersample)
    one = raycast.make_backend(scene.mesh, threads=1)
    monkeypatch.setattr(gv, "STEP_PIXELS", 64)
    stored1, stats1 = coherent_visibility(one, scene.samples, cube, supersample)
    assert np.array_equal(stored, stored1)
    assert stats.as_dict() == stats1.as_dict()
    assert stats.checked > 1000 and stats.inferred > stats.cast  # (the check and the inference ran)


def test_castable_bits_are_the_packed_castable_mask():
    """`castable_bits` (blocks on two threads, one comparison of the smaller dot product) packs
    exactly `castable`: random normals, a NaN, a zero normal, sizes off the block and the byte."""
    from pipelines.geometry.visibility import castable, castable_bits

    rng = np.random.default_rng(3)
    for P, N in ((1, 5), (700, 3 * 8 * 8 + 3), (1029, 3072)):
        n = rng.normal(size=(P, 3))
        g = n + 0.5 * rng.normal(size=(P, 3))
        d = rng.normal(size=(N, 3))
        n[0, 1] = np.nan
        if P > 2:
            g[1] = 0.0
        bits = castable_bits(n, g, d)
        assert bits.shape == (P, (N + 7) // 8)
        np.testing.assert_array_equal(bits, np.packbits(castable(n, g, d), axis=1, bitorder="little"))
        if P > 2:
            assert np.unpackbits(bits[2:], axis=1, count=N, bitorder="little").mean() > 0.2
