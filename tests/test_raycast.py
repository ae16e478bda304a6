"""Tests for the ray-casting backends (pipelines.raycast) through the visibility stage.

A small synthetic scene: a 4 x 4 ground grid at z = 0 (72 triangles), a unit box floating at
z in [0.5, 1.5] above the origin and an icosphere (radius 0.4) at (1, -1, 0.6).
"""

import numpy as np
import pytest

from pipelines.geometry.camera import PixelSamples, pixel_rays, pixel_samples
from pipelines.light.cubemap import CubeMap
from pipelines.geometry.raycast import MISS, make_backend
from pipelines.geometry.camera import Camera, Pose
from pipelines.geometry.mesh import Mesh
from pipelines.geometry.visibility import compute_visibility, decode

BACKENDS = ["embree", "reference"]
BOX_LO, BOX_HI = np.array([-0.5, -0.5, 0.5]), np.array([0.5, 0.5, 1.5])
BALL_C, BALL_R = np.array([1.0, -1.0, 0.6]), 0.4
GROUND_N = 6  # grid cells per side
FAR = np.array([1.0e6, -1.0e6, 1.0e6])


def build_mesh(offset=np.zeros(3)) -> Mesh:
    import trimesh

    xs = np.linspace(-2.0, 2.0, GROUND_N + 1)
    X, Y = np.meshgrid(xs, xs)
    V = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    F = []
    for i in range(GROUND_N):
        for j in range(GROUND_N):
            a = i * (GROUND_N + 1) + j
            F += [[a, a + 1, a + GROUND_N + 2], [a, a + GROUND_N + 2, a + GROUND_N + 1]]
    ground = trimesh.Trimesh(V, np.array(F), process=False)
    box = trimesh.creation.box(bounds=np.stack([BOX_LO, BOX_HI]))
    ball = trimesh.creation.icosphere(subdivisions=2, radius=BALL_R)
    ball.apply_translation(BALL_C)
    m = trimesh.util.concatenate([ground, box, ball])
    vertices = np.asarray(m.vertices, np.float64) + offset
    return Mesh(vertices, np.asarray(m.faces, np.int64), np.asarray(m.vertex_normals, np.float64))


N_GROUND_FACES = 2 * GROUND_N * GROUND_N
CAMERA = Camera(64, 48, 45.0, 45.0, 31.5, 23.5)


look_at = Pose.look_at


POSE = look_at([2.0, -2.6, 2.4], [0.0, 0.0, 0.3])
POSE_FAR = look_at(np.array([2.0, -2.6, 2.4]) + FAR, np.array([0.0, 0.0, 0.3]) + FAR)


@pytest.fixture(scope="module")
def mesh():
    return build_mesh()


@pytest.fixture(scope="module")
def mesh_far():
    return build_mesh(FAR)


@pytest.fixture(scope="module")
def backends(mesh):
    return {name: make_backend(mesh, name) for name in BACKENDS}


@pytest.fixture(scope="module")
def samples(mesh, backends):
    s, diag = pixel_samples(CAMERA, POSE, mesh, backends["embree"])
    return s, diag


@pytest.fixture(scope="module")
def visibility(backends, samples):
    cube = CubeMap(8)
    return {name: compute_visibility(backends[name], samples[0], cube).dense() for name in BACKENDS}


def sample_subset(s: PixelSamples, idx) -> PixelSamples:
    return s.take(idx)


# -- analytic occluders --------------------------------------------------------------------------
def hits_box(p, d):
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (BOX_LO - p) / d
        t1 = (BOX_HI - p) / d
    tmin = np.nanmax(np.minimum(t0, t1), axis=-1)
    tmax = np.nanmin(np.maximum(t0, t1), axis=-1)
    return (tmax >= np.maximum(tmin, 0.0))


def ball_distance(p, d):
    """Distance from the ball centre to the ray (inf if the ball is behind)."""
    c = BALL_C - p
    tc = d @ c
    dist = np.linalg.norm(c - tc[:, None] * d, axis=1)
    return np.where(tc > 0, dist, np.inf)


def analytic_visible(p, d):
    """(visible, certain): certain where the ray is clear of every silhouette by a margin."""
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    occl = hits_box(p, d) | (ball_distance(p, d) < BALL_R)
    certain = np.abs(ball_distance(p, d) - BALL_R) > 0.03
    rng = np.random.default_rng(0)
    for _ in range(16):  # a box silhouette within ~0.02 rad makes the texel uncertain
        q = d + 0.02 * rng.normal(size=d.shape) / np.sqrt(3)
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        certain &= hits_box(p, q) == hits_box(p, d)
    return ~occl, certain


def ground_sample(points) -> PixelSamples:
    P = np.asarray(points, float)
    n = len(P)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    return PixelSamples(pixel=np.column_stack([np.zeros(n), np.arange(n)]).astype(np.int32), position=P,
                        normal=up, geometric_normal=up, view=up.copy(), face=np.zeros(n, np.int64))


# -- the two backends agree ----------------------------------------------------------------------
def test_scene_is_what_the_tests_assume(mesh, samples):
    s, diag = samples
    assert 300 <= len(mesh.faces) <= 600
    assert diag["used"] >= 500, diag
    # the camera sees ground, box and ball
    assert np.any(s.face < N_GROUND_FACES) and np.any(s.face >= N_GROUND_FACES + 12)
    assert np.any((s.face >= N_GROUND_FACES) & (s.face < N_GROUND_FACES + 12))


def test_backends_agree_on_shadow_bits(visibility, samples):
    Ve, Vr = visibility["embree"], visibility["reference"]
    assert Ve.shape == Vr.shape == (len(samples[0]), CubeMap(8).n_texels)
    agree = np.mean(Ve == Vr)
    assert agree >= 0.999, agree
    # and the shadows are not trivial: a real fraction of facing texels is occluded
    facing = (samples[0].normal @ CubeMap(8).directions.T) > 0
    occluded = np.mean(Ve[facing] == 0)
    assert 0.05 < occluded < 0.6, occluded
    assert np.all(Ve[~facing] == 0)


def test_backends_agree_on_primary_hits(mesh, backends):
    rows, cols = np.meshgrid(np.arange(CAMERA.height), np.arange(CAMERA.width), indexing="ij")
    o, d = pixel_rays(CAMERA, POSE, rows.ravel(), cols.ravel())
    te, fe, ue, ve = backends["embree"].intersect(o, d)
    tr, fr, ur, vr = backends["reference"].intersect(o, d)
    assert np.count_nonzero(fr >= 0) > 500
    # rays that are not near a triangle edge (by the reference barycentrics) hit the same face
    margin = np.minimum(np.minimum(ur, vr), 1.0 - ur - vr)
    clear = (fr == MISS) | (margin > 1e-3)
    assert np.count_nonzero(clear) >= 0.9 * len(fr)
    np.testing.assert_array_equal(fe[clear], fr[clear])
    hit = clear & (fr >= 0)
    np.testing.assert_allclose(te[hit], tr[hit], rtol=1e-5)
    np.testing.assert_allclose(ue[hit], ur[hit], atol=1e-4)
    np.testing.assert_allclose(ve[hit], vr[hit], atol=1e-4)


# -- analytic checks on both backends ------------------------------------------------------------
@pytest.mark.parametrize("name", BACKENDS)
@pytest.mark.parametrize("x,y,z0,expected_t,part", [
    (-1.3, 1.2, 5.0, 5.0, "ground"),
    (1.7, 0.35, 2.5, 2.5, "ground"),
    (0.1, 0.2, 5.0, 3.5, "box"),
    (1.0, -1.0, 3.0, 3.0 - (0.6 + 0.4), "ball"),
])
def test_ray_straight_down_hits_at_the_right_distance(backends, name, x, y, z0, expected_t, part):
    be = backends[name]
    t, f, u, v = be.intersect(np.array([[x, y, z0]]), np.array([[0.0, 0.0, -1.0]]))
    tol = 3e-3 if part == "ball" else 1e-5  # the icosphere's pole vertex is on the sphere
    assert abs(t[0] - expected_t) <= tol
    ranges = {"ground": (0, N_GROUND_FACES), "box": (N_GROUND_FACES, N_GROUND_FACES + 12),
              "ball": (N_GROUND_FACES + 12, len(be.mesh.faces))}
    lo, hi = ranges[part]
    assert lo <= f[0] < hi
    # the barycentrics reconstruct the hit point
    tri = be.mesh.vertices[be.mesh.faces[f[0]]]
    point = (1 - u[0] - v[0]) * tri[0] + u[0] * tri[1] + v[0] * tri[2]
    np.testing.assert_allclose(point, [x, y, z0 - t[0]], atol=1e-5)


@pytest.mark.parametrize("name", BACKENDS)
def test_ray_from_below_hits_the_ground_and_rays_out_miss(backends, name):
    be = backends[name]
    o = np.array([[-1.3, 1.2, -1.0], [-1.3, 1.2, 5.0], [3.0, 3.0, 0.5]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    t, f, _, _ = be.intersect(o, d)
    assert abs(t[0] - 1.0) <= 1e-5 and 0 <= f[0] < N_GROUND_FACES
    np.testing.assert_array_equal(f[1:], [MISS, MISS])
    np.testing.assert_array_equal(be.occluded(o, d), [True, False, False])


@pytest.mark.parametrize("name", BACKENDS)
def test_miss_distance_is_infinite(backends, name):
    """Both backends share one API: a miss has face -1 and t = inf (not a large finite number)."""
    t, f, _, _ = backends[name].intersect(np.array([[0.0, 0.0, 5.0]]), np.array([[0.0, 0.0, 1.0]]))
    assert f[0] == MISS
    assert t[0] == np.inf


@pytest.mark.parametrize("name", BACKENDS)
def test_point_under_the_box_is_shadowed_at_zenith_not_at_horizon(backends, name):
    be = backends[name]
    t, face, _, point = be.first_hits(np.array([[0.0, 0.0, -1.0]]), np.array([[0.0, 0.0, 1.0]]))  # from below
    assert 0 <= face[0] < N_GROUND_FACES and t[0] == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(point[0], 0.0, atol=1e-12)
    up = np.array([[0.0, 0.0, 1.0]])
    p = be.shadow_origins(point, up, face, local=False)[0]
    # the offset: 32 float32 ulps of (max |p| in the recentred frame + the ground cell's diagonal)
    centre_z = 0.5 * be.mesh.vertices[:, 2].max()
    edge = np.hypot(4.0 / GROUND_N, 4.0 / GROUND_N)
    np.testing.assert_allclose(p[:2], 0.0, atol=1e-12)
    assert p[2] == pytest.approx(32 * np.finfo(np.float32).eps * (centre_z + edge), rel=1e-6)
    dirs = np.array([[0.0, 0.0, 1.0], [0.3, -0.2, 1.0], [1.0, 0.0, 0.1], [-1.0, 0.3, 0.05],
                     [0.0, 1.0, 0.9], [0.0, -1.0, 0.2], [0.7, 0.7, 0.95]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    occ = be.occluded(np.repeat(p[None], len(dirs), 0), dirs)
    # occluded exactly when max(|dx|, |dy|) <= dz (see test_visibility_matches_analytic_occluders)
    np.testing.assert_array_equal(occ, [True, True, False, False, False, False, True])


@pytest.mark.parametrize("name", BACKENDS)
def test_visibility_matches_analytic_occluders(backends, name):
    """Bit by bit, away from silhouettes, for ground points around and under the occluders."""
    points = [[0.0, 0.0, 0.0], [-1.5, 1.5, 0.0], [1.5, 0.3, 0.0], [1.0, -1.0, 0.0], [-0.2, -1.1, 0.0]]
    cube = CubeMap(8)
    vis = compute_visibility(backends[name], ground_sample(points), cube)
    V = vis.dense()
    assert V.shape == (len(points), cube.n_texels) and vis.encoding == "bits"
    facing = cube.directions[:, 2] > 0
    assert facing.all()
    for j, p in enumerate(points):
        expected, certain = analytic_visible(np.array(p), cube.directions)
        assert np.count_nonzero(certain) >= 0.8 * cube.n_texels
        np.testing.assert_array_equal(V[j, certain], expected[certain].astype(np.float32))
    # under the box: exactly the +z face is hidden (the box spans max(|dx|, |dy|) <= dz)
    plus_z = cube.texel_face == 0
    assert np.all(V[0, plus_z] == 0) and np.mean(V[0, ~plus_z]) > 0.9
    # under the ball: the zenith is hidden
    assert V[3, cube.lookup(np.array([0.0, 0.0, 1.0]))] == 0


@pytest.mark.parametrize("name", BACKENDS)
def test_supersampled_visibility_is_a_fraction(backends, name):
    cube = CubeMap(4)
    vis = compute_visibility(backends[name], ground_sample([[0.0, 0.0, 0.0], [-1.5, 1.5, 0.0]]), cube,
                             supersample=3)
    V = vis.dense()
    assert vis.encoding == "fraction"
    # fractions are multiples of 1/9 (stored as round(255 k / 9) / 255)
    k = V * 9.0
    np.testing.assert_allclose(k, np.round(k), atol=9 * 0.5 / 255 + 1e-6)
    assert np.all(V[0, cube.texel_face == 0] == 0)  # under the box
    assert np.any((V[1] > 0) & (V[1] < 1)) or np.all(V[1] == 1)
    # stored encoding decodes to the same values
    np.testing.assert_array_equal(decode(vis.stored, cube.n_texels, "fraction"), V)


@pytest.mark.parametrize("name", BACKENDS)
def test_scene_far_from_origin_gives_the_same_shadows(mesh_far, samples, visibility, name):
    be_far = make_backend(mesh_far, name)
    s_far, _ = pixel_samples(CAMERA, POSE_FAR, mesh_far, be_far)
    s0 = samples[0]
    key0 = {tuple(p): i for i, p in enumerate(s0.pixel)}
    common = [(key0[tuple(p)], i) for i, p in enumerate(s_far.pixel) if tuple(p) in key0]
    assert len(common) >= 0.98 * len(s0)
    i0, i1 = np.array(common).T
    np.testing.assert_allclose(s_far.position[i1] - FAR, s0.position[i0], atol=1e-4)
    np.testing.assert_array_equal(s_far.face[i1], s0.face[i0])
    if name == "reference":  # keep the brute-force backend quick: every third pixel
        i0, i1 = i0[::3], i1[::3]
    V_far = compute_visibility(be_far, sample_subset(s_far, i1), CubeMap(8)).dense()
    agree = np.mean(V_far == visibility[name][i0])
    assert agree >= 0.999, agree


@pytest.mark.parametrize("name", BACKENDS)
def test_backend_threads_give_the_same_answer(mesh, name):
    rng = np.random.default_rng(11)
    n = 5000 if name == "embree" else 4200
    o = rng.uniform([-2, -2, 0.01], [2, 2, 2], size=(n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    one = make_backend(mesh, name, threads=1).occluded(o, d)
    two = make_backend(mesh, name, threads=2).occluded(o, d)
    np.testing.assert_array_equal(one, two)
    assert 0.2 < one.mean() < 0.9


def test_unknown_backend_is_rejected(mesh):
    with pytest.raises(ValueError, match="unknown ray backend"):
        make_backend(mesh, "optix")
