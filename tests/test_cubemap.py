"""Tests for the cube-map light layout and lat-long conversion in pipelines.cubemap."""

import numpy as np
import pytest

from pipelines.light.cubemap import CROSS_BLOCKS, FACE_NAMES, CubeMap, cross_image, cube_to_latlong, direction_to_spherical, face_rectangle_solid_angle, latlong_directions, latlong_solid_angles, latlong_to_cube, spherical_to_direction
from pipelines.light import cubemap

RESOLUTIONS = [2, 4, 8, 16, 32, 64, 128]
MODES = [pytest.param(True, id="hemisphere"), pytest.param(False, id="sphere")]


def random_directions(n, seed):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def angle(a, b):
    return np.arccos(np.clip(np.einsum("...k,...k->...", a, b), -1.0, 1.0))


def energy_latlong(img):
    H = img.shape[0]
    return float(np.einsum("hw,hw...->...", latlong_solid_angles(H), img).sum())


def energy_cube(tex, cube):
    return float(np.einsum("n,n...->...", cube.solid_angles, tex).sum())


# -- layout and solid angles ---------------------------------------------------------------------
@pytest.mark.parametrize("R", RESOLUTIONS)
@pytest.mark.parametrize("hemisphere", MODES)
def test_solid_angles_sum_to_hemisphere_or_sphere(R, hemisphere):
    cube = CubeMap(R, hemisphere)
    assert cube.n_texels == (3 if hemisphere else 6) * R * R
    assert cube.solid_angles.shape == (cube.n_texels,)
    assert np.all(cube.solid_angles > 0)
    total = (2.0 if hemisphere else 4.0) * np.pi
    assert abs(cube.solid_angles.sum() - total) < 1e-9


@pytest.mark.parametrize("R", RESOLUTIONS)
@pytest.mark.parametrize("hemisphere", MODES)
def test_texel_centres_look_up_to_their_own_texel(R, hemisphere):
    cube = CubeMap(R, hemisphere)
    d = cube.directions
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(cube.lookup(d), np.arange(cube.n_texels))
    # a (..., 3) batch keeps its shape
    assert cube.lookup(d.reshape(-1, 1, 3)).shape == (cube.n_texels, 1)


@pytest.mark.parametrize("R", [2, 4, 16, 64])
def test_hemisphere_texels_are_all_in_the_upper_hemisphere(R):
    cube = CubeMap(R, True)
    assert np.all(cube.directions[:, 2] > 0)
    # every point of every texel (sub-texel grid reaching the corners' neighbourhood) has z >= 0
    sub = cube.subtexel_directions(4)
    assert sub.shape == (cube.n_texels, 16, 3)
    assert np.all(sub[..., 2] >= 0)
    # sub-texel directions look up to the texel that contains them
    np.testing.assert_array_equal(cube.lookup(sub), np.repeat(np.arange(cube.n_texels)[:, None], 16, 1))


@pytest.mark.parametrize("R", [2, 8, 32])
def test_hemisphere_lookup_covers_upper_and_rejects_lower(R):
    cube = CubeMap(R, True)
    d = random_directions(200_000, seed=R)
    # include directions very close to the horizon and to face edges
    near = random_directions(20_000, seed=R + 1)
    near[:, 2] = np.sign(near[:, 2]) * 1e-7
    d = np.vstack([d, near / np.linalg.norm(near, axis=1, keepdims=True)])
    idx = cube.lookup(d)
    up = d[:, 2] > 0
    assert np.all(idx[up] >= 0)
    assert np.all(idx[~up] == -1)
    # the texel found contains the direction: within a half texel diagonal of its centre
    assert angle(d[up], cube.directions[idx[up]]).max() <= np.sqrt(2.0) / R + 1e-12
    # every texel is hit by some upper direction at these sample counts
    assert len(np.unique(idx[up])) == cube.n_texels


@pytest.mark.parametrize("R", [2, 8, 32])
def test_sphere_lookup_finds_every_direction(R):
    cube = CubeMap(R, False)
    d = random_directions(200_000, seed=10 + R)
    idx = cube.lookup(d)
    assert np.all(idx >= 0)
    assert angle(d, cube.directions[idx]).max() <= np.sqrt(2.0) / R + 1e-12
    # -z face texels look down, +z face texels look up
    faces = np.array(FACE_NAMES)[cube.texel_face]
    assert np.all(cube.directions[faces == "-z", 2] < 0)
    assert np.all(cube.directions[faces == "+z", 2] > 0)
    assert np.all(cube.lookup(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])) >= 0)


@pytest.mark.parametrize("bad", [pytest.param([0.0, 0.0, 0.0], id="zero"),
                                 pytest.param([np.nan, 0.0, 1.0], id="nan")])
@pytest.mark.parametrize("hemisphere", MODES)
def test_zero_and_nan_directions_have_no_texel(bad, hemisphere):
    """lookup documents -1 where there is no texel; a degenerate direction has none."""
    cube = CubeMap(4, hemisphere)
    idx = cube.lookup(np.array([bad, [0.0, 0.0, 1.0]]))
    assert idx[0] == -1
    assert idx[1] == cube.lookup(np.array([0.0, 0.0, 1.0])) >= 0


@pytest.mark.parametrize("R,hemisphere", [(2, True), (4, True), (8, False), (16, True)])
def test_texel_solid_angle_matches_fine_grid_quadrature(R, hemisphere):
    """dOmega = ds dt / (1 + s^2 + t^2)^(3/2) on a face, integrated on a 256 x 256 midpoint grid."""
    cube = CubeMap(R, hemisphere)
    m = 256
    rng = np.random.default_rng(R)
    picks = rng.choice(cube.n_texels, size=min(cube.n_texels, 12), replace=False)
    for i in picks:
        s0 = -1.0 + 2.0 * cube.texel_col[i] / R
        t0 = -1.0 + 2.0 * cube.texel_row[i] / R
        h = 2.0 / R / m
        s = s0 + h * (np.arange(m) + 0.5)
        t = t0 + h * (np.arange(m) + 0.5)
        S, T = np.meshgrid(s, t)
        estimate = np.sum(h * h / (1.0 + S * S + T * T) ** 1.5)
        assert abs(estimate - cube.solid_angles[i]) <= 1e-5 * cube.solid_angles[i]



@pytest.mark.parametrize("R,hemisphere", [(2, True), (8, False), (32, True)])
def test_vector_solid_angle_is_the_integral_of_the_direction(R, hemisphere):
    """The closed form (Lambert's polygon formula) against a 256 x 256 midpoint grid of
    d dOmega = (n + s a + t b) ds dt / (1 + s^2 + t^2)^2 on a few texels, and its sums: the
    hemisphere's cosine integral is (0, 0, pi), the sphere's is 0."""
    cube = CubeMap(R, hemisphere)
    m_all = cube.vector_solid_angles
    np.testing.assert_allclose(m_all.sum(axis=0), [0.0, 0.0, np.pi if hemisphere else 0.0], atol=1e-12)
    frames = np.array([cubemap.FACE_FRAMES[f] for f in FACE_NAMES])
    m = 256
    rng = np.random.default_rng(R)
    for i in rng.choice(cube.n_texels, size=min(cube.n_texels, 10), replace=False):
        h = 2.0 / R / m
        s = -1.0 + 2.0 * cube.texel_col[i] / R + h * (np.arange(m) + 0.5)
        t = -1.0 + 2.0 * cube.texel_row[i] / R + h * (np.arange(m) + 0.5)
        S, T = np.meshgrid(s, t)
        n, a, b = frames[cube.texel_face[i]]
        w = h * h / (1.0 + S * S + T * T) ** 2
        estimate = np.array([np.sum(w * (n[k] + S * a[k] + T * b[k])) for k in range(3)])
        np.testing.assert_allclose(m_all[i], estimate, rtol=0, atol=2e-6 * np.linalg.norm(estimate))
        assert np.linalg.norm(m_all[i]) <= cube.solid_angles[i]

def test_face_rectangle_solid_angle_of_whole_face_is_4pi_over_6():
    assert abs(face_rectangle_solid_angle(-1.0, 1.0, -1.0, 1.0) - 4.0 * np.pi / 6.0) < 1e-12
    # the half face above the horizon of a side face
    assert abs(face_rectangle_solid_angle(-1.0, 1.0, -1.0, 0.0) - np.pi / 3.0) < 1e-12


@pytest.mark.parametrize("hemisphere", MODES)
def test_texel_solid_angle_matches_monte_carlo(hemisphere):
    """Counts of uniform random directions per texel estimate 4 pi x fraction (checks lookup too)."""
    cube = CubeMap(4, hemisphere)
    n = 2_000_000
    d = random_directions(n, seed=2024)
    idx = cube.lookup(d)
    counts = np.bincount(idx[idx >= 0], minlength=cube.n_texels)
    p = cube.solid_angles / (4.0 * np.pi)
    sigma = np.sqrt(p * (1 - p) / n) * 4.0 * np.pi
    estimate = 4.0 * np.pi * counts / n
    assert np.all(np.abs(estimate - cube.solid_angles) <= 5.0 * sigma)
    # and the coverage fraction: half the sphere (hemisphere) or all of it
    frac = np.count_nonzero(idx >= 0) / n
    assert abs(frac - (0.5 if hemisphere else 1.0)) <= 5.0 * np.sqrt(0.25 / n)


def test_bad_resolution_is_rejected():
    for R in (0, 1, 3, 12, 2.0):
        with pytest.raises(ValueError):
            CubeMap(R)


# -- lat-long ------------------------------------------------------------------------------------
@pytest.mark.parametrize("H", [1, 2, 7, 16, 100])
def test_latlong_solid_angles_sum_to_4pi(H):
    omega = latlong_solid_angles(H)
    assert omega.shape == (H, 2 * H)
    assert abs(omega.sum() - 4.0 * np.pi) < 1e-9
    if H % 2 == 0:  # the upper half rows are exactly the upper hemisphere
        assert abs(omega[: H // 2].sum() - 2.0 * np.pi) < 1e-9


def test_latlong_directions_follow_the_convention():
    H = 8
    d = latlong_directions(H)
    assert d.shape == (H, 2 * H, 3)
    theta, phi = direction_to_spherical(d)
    np.testing.assert_allclose(theta[:, 0], np.pi * (np.arange(H) + 0.5) / H, atol=1e-12)
    np.testing.assert_allclose(phi[0], 2.0 * np.pi * (np.arange(2 * H) + 0.5) / (2 * H), atol=1e-12)
    # phi from +X towards +Y: a quarter turn is +Y
    np.testing.assert_allclose(spherical_to_direction(np.pi / 2, np.pi / 2), [0.0, 1.0, 0.0], atol=1e-12)
    assert d[0, 0, 2] > 0.99 * np.cos(np.pi / H)  # row 0 is the zenith


def smooth_sky(H, hemisphere):
    d = latlong_directions(H)
    sky = np.stack([1.0 + 0.5 * d[..., 2] + 0.3 * d[..., 0],
                    2.0 + np.sin(2 * d[..., 1]),
                    0.5 + d[..., 2] ** 2], axis=-1)
    if hemisphere:
        sky[H // 2:] = 0.0
    return sky


@pytest.mark.parametrize("hemisphere", MODES)
@pytest.mark.parametrize("R,H", [(8, 32), (16, 64), (32, 64)])
def test_latlong_cube_latlong_keeps_energy_of_smooth_sky(R, H, hemisphere):
    cube = CubeMap(R, hemisphere)
    sky = smooth_sky(H, hemisphere)
    tex = latlong_to_cube(sky, cube)
    assert tex.shape == (cube.n_texels, 3)
    back = cube_to_latlong(tex, cube, H)
    assert back.shape == sky.shape
    for c in range(3):
        e0 = energy_latlong(sky[..., c])
        assert abs(energy_cube(tex[:, c], cube) - e0) <= 5e-3 * e0
        assert abs(energy_latlong(back[..., c]) - e0) <= 5e-3 * e0
    if hemisphere:
        assert np.all(back[H // 2:] == 0.0)


@pytest.mark.parametrize("hemisphere", MODES)
@pytest.mark.parametrize("R,H,texel", [(8, 256, 5), (8, 256, 100), (16, 256, 400)])
def test_sun_keeps_energy_and_lands_in_its_texel(R, H, texel, hemisphere):
    cube = CubeMap(R, hemisphere)
    texel = texel % cube.n_texels
    sun_dir = cube.directions[texel]
    theta, phi = direction_to_spherical(sun_dir)
    r = int(theta / np.pi * H)
    c = int(phi / (2 * np.pi) * 2 * H)
    img = np.zeros((H, 2 * H))
    img[r:r + 2, c:c + 2] = 1000.0  # a 2 x 2 pixel sun next to the texel centre
    e0 = energy_latlong(img)
    tex = latlong_to_cube(img, cube)
    assert abs(energy_cube(tex, cube) - e0) <= 5e-3 * e0
    # the texel `lookup` gives for the sun's direction holds (almost) all of the sun's power
    sun_centre = spherical_to_direction(np.pi * (r + 1) / H, 2 * np.pi * (c + 1) / (2 * H))
    k = int(cube.lookup(sun_centre))
    assert k == texel
    assert tex[k] * cube.solid_angles[k] >= 0.99 * e0
    back = cube_to_latlong(tex, cube, H)
    assert abs(energy_latlong(back) - e0) <= 5e-3 * e0


@pytest.mark.parametrize("hemisphere", MODES)
def test_one_texel_sun_keeps_its_power_in_latlong(hemisphere):
    cube = CubeMap(16, hemisphere)
    tex = np.zeros(cube.n_texels)
    tex[37] = 500.0
    img = cube_to_latlong(tex, cube, 64)
    e0 = 500.0 * cube.solid_angles[37]
    assert abs(energy_latlong(img) - e0) <= 1e-6 * e0
    # the brightest lat-long pixel is in the direction of the texel
    r, c = np.unravel_index(np.argmax(img), img.shape)
    assert angle(latlong_directions(64)[r, c], cube.directions[37]) < 2.0 / 16


@pytest.mark.parametrize("hemisphere", MODES)
@pytest.mark.parametrize("R,H", [(8, 32), (16, 64), (32, 64)])
def test_constant_cube_map_gives_constant_latlong(R, H, hemisphere):
    """Radiance resampling must keep a uniform sky uniform (2 % at worst, 0.7 % rms: the overlap
    areas of boundary cells are approximate; total power is exact, see the energy tests)."""
    cube = CubeMap(R, hemisphere)
    img = cube_to_latlong(np.full(cube.n_texels, 2.0), cube, H)
    covered = img[: H // 2] if hemisphere else img
    np.testing.assert_allclose(covered, 2.0, rtol=2e-2)
    assert np.sqrt(np.mean((covered / 2.0 - 1.0) ** 2)) < 7e-3
    if hemisphere:
        assert np.all(img[H // 2:] == 0.0)


@pytest.mark.parametrize("hemisphere", MODES)
@pytest.mark.parametrize("R,H", [(8, 32), (16, 64), (32, 64), (32, 512)])
def test_constant_latlong_gives_constant_cube_map(R, H, hemisphere):
    """A uniform lat-long sky must become a uniform cube map (2 % at worst, 0.7 % rms)."""
    cube = CubeMap(R, hemisphere)
    tex = latlong_to_cube(np.full((H, 2 * H), 3.0), cube)
    np.testing.assert_allclose(tex, 3.0, rtol=2e-2)
    assert np.sqrt(np.mean((tex / 3.0 - 1.0) ** 2)) < 7e-3


# -- cross image ---------------------------------------------------------------------------------
@pytest.mark.parametrize("R", [2, 4, 16])
@pytest.mark.parametrize("hemisphere", MODES)
def test_cross_image_puts_each_face_in_its_block(R, hemisphere):
    cube = CubeMap(R, hemisphere)
    face_ids = (cube.texel_face + 1).astype(np.float64)
    img, valid = cross_image(face_ids, cube, fill=-5.0)
    assert img.shape == (3 * R, 4 * R) and valid.shape == (3 * R, 4 * R)
    assert valid.sum() == cube.n_texels
    assert np.all(img[~valid] == -5.0)
    for f, name in enumerate(FACE_NAMES):
        br, bc = CROSS_BLOCKS[name]
        block = img[br * R:(br + 1) * R, bc * R:(bc + 1) * R]
        vblock = valid[br * R:(br + 1) * R, bc * R:(bc + 1) * R]
        assert np.all(block[vblock] == f + 1)
        if hemisphere:
            expected = {"+z": R * R, "-z": 0}.get(name, R * R // 2)
            assert vblock.sum() == expected
            if name in ("+x", "+y", "-x", "-y"):
                assert vblock[: R // 2].all() and not vblock[R // 2:].any()  # upper half on top
        else:
            assert vblock.all()
    # RGB texels keep their channels
    rgb, _ = cross_image(np.stack([face_ids, 2 * face_ids, 3 * face_ids], axis=1), cube)
    assert rgb.shape == (3 * R, 4 * R, 3)
    np.testing.assert_array_equal(rgb[valid][:, 1], 2 * img[valid])


@pytest.mark.parametrize("R", [4, 8, 32])
@pytest.mark.parametrize("hemisphere", MODES)
def test_cross_image_faces_join_edge_to_edge(R, hemisphere):
    cube = CubeMap(R, hemisphere)
    idx_img, valid = cross_image(np.arange(cube.n_texels), cube, fill=-1)
    idx_img = idx_img.astype(np.int64)
    texel_angle = 2.0 / R
    pairs = []
    # all vertically and horizontally adjacent pixels, plus the wrap of the middle band
    pairs.append((idx_img[:-1], idx_img[1:]))
    pairs.append((idx_img[:, :-1], idx_img[:, 1:]))
    pairs.append((idx_img[R:2 * R, -1], idx_img[R:2 * R, 0]))
    n_seam = 0
    for a, b in pairs:
        a, b = a.ravel(), b.ravel()
        ok = (a >= 0) & (b >= 0)
        ang = angle(cube.directions[a[ok]], cube.directions[b[ok]])
        assert ang.max() <= 1.5 * texel_angle
        n_seam += np.count_nonzero(cube.texel_face[a[ok]] != cube.texel_face[b[ok]])
    # seams: +z/+x, +x/+y, +y/-x, -x/-y, -y/+x (wrap) [+ +x/-z in sphere mode]
    rows_per_side = R // 2 if hemisphere else R
    expected = R + 4 * rows_per_side + (0 if hemisphere else R)
    assert n_seam == expected


@pytest.mark.parametrize("hemisphere", MODES)
def test_sphere_and_hemisphere_share_the_upper_texels(hemisphere):
    """The same direction gets texels with the same centre in both modes."""
    R = 8
    cube = CubeMap(R, hemisphere)
    other = CubeMap(R, not hemisphere)
    d = cube.directions[cube.directions[:, 2] > 0]
    k = other.lookup(d)
    assert np.all(k >= 0)
    np.testing.assert_allclose(other.directions[k], d, atol=1e-12)
    np.testing.assert_allclose(other.solid_angles[k], cube.solid_angles[cube.lookup(d)], rtol=1e-12)


def test_latlong_overlap_is_kept_between_runs_and_rebuilt_when_damaged(tmp_path, monkeypatch):
    """The lat-long overlap is stored in the user cache folder: a later process reads the same
    matrix; a damaged or wrong-shaped file is rebuilt; WAVELIGHT_CACHE_DIR='' keeps nothing."""
    from scipy import sparse

    monkeypatch.setenv("WAVELIGHT_CACHE_DIR", str(tmp_path))
    cube = cubemap.CubeMap(4)
    built = cubemap._build_latlong_overlap(16, cube)
    cubemap.latlong_overlap.cache_clear()
    first = cubemap.latlong_overlap(16, cube)
    files = list(tmp_path.glob("latlong-overlap-*H16-R4-hemi.npz"))
    assert len(files) == 1 and (first != built).nnz == 0
    cubemap.latlong_overlap.cache_clear()
    assert (cubemap.latlong_overlap(16, cube) != built).nnz == 0  # read back
    files[0].write_bytes(b"not a matrix")
    cubemap.latlong_overlap.cache_clear()
    assert (cubemap.latlong_overlap(16, cube) != built).nnz == 0  # rebuilt
    sparse.save_npz(files[0], sparse.csr_matrix((3, 3)))  # a readable file of the wrong shape
    cubemap.latlong_overlap.cache_clear()
    assert (cubemap.latlong_overlap(16, cube) != built).nnz == 0
    monkeypatch.setenv("WAVELIGHT_CACHE_DIR", "")
    cubemap.latlong_overlap.cache_clear()
    assert cubemap._user_cache_dir() is None and (cubemap.latlong_overlap(8, cube) != cubemap._build_latlong_overlap(8, cube)).nnz == 0
    assert not list(tmp_path.glob("*H8-*"))
    cubemap.latlong_overlap.cache_clear()
