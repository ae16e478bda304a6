"""Pose from 2D-3D correspondences (pipelines.registration) on the Mitsuba scenes' correspondences
(16 object vertices, projections + N(0, 0.3 px) noise) against their true pose. Numbers in the
docstrings are measured with the code as of this writing."""

from pathlib import Path

import numpy as np
import pytest

from pipelines.geometry import camera as cam
from pipelines.geometry import registration as reg
from pipelines.errors import InputError
from pipelines.io.scene_files import read_camera, read_correspondences, read_pose

SCENES = Path(__file__).parent / "data" / "scenes"
NAMES = ("teapot_sun_phong", "bunny_sun", "spot_overcast")


def load(name):
    d = SCENES / name
    camera, pose = read_camera(d / "camera.json"), read_pose(d / "pose.json")
    uv, xyz = read_correspondences(d / "correspondences.csv")
    return camera, pose, uv, xyz


def errors(r, pose):
    """Rotation error (deg) and translation error as a fraction of the camera distance |t|."""
    return reg.rotation_angle_deg(r.R, pose.R), float(np.linalg.norm(r.t - pose.t) / np.linalg.norm(pose.t))


@pytest.mark.parametrize("name", NAMES)
def test_noise_free_projections_give_the_exact_pose(name):
    camera, pose, _, xyz = load(name)
    uv = cam.project(camera, pose, xyz)
    for method in ("sqpnp", "iterative"):
        r = reg.register(uv, xyz, camera.K, camera.dist_coeffs, method)
        rot, trans = errors(r, pose)
        assert rot < 1e-4 and trans < 1e-6, (method, rot, trans)
        assert r.rms < 1e-4 and r.inliers.all() and r.method == method


@pytest.mark.parametrize("name", NAMES)
def test_noisy_correspondences_pose_within_its_uncertainty(name):
    """Measured: rotation 0.34 / 0.30 / 0.39 deg, |t| error 0.41 / 0.09 / 0.20 %, reported 1-sigma
    rotation 0.24 / 0.24 / 0.28 deg. The translation meets the issue's 0.5 %; the rotation misses
    its 0.2 deg because 16 points at 0.3 px cannot do better: over 300 noise draws the median
    rotation error of this (maximum-likelihood) fit is 0.21 / 0.21 / 0.32 deg (see the test below)."""
    camera, pose, uv, xyz = load(name)
    r = reg.register(uv, xyz, camera.K, camera.dist_coeffs, threshold=reg.default_threshold(camera.width, camera.height))
    rot, trans = errors(r, pose)
    assert trans < 0.005, trans
    assert rot < 2.5 * r.sigma_rotation_deg and rot < 0.5, (rot, r.sigma_rotation_deg)
    assert r.method == "sqpnp" and r.inliers.all()  # no outliers, no RANSAC
    assert 0.2 < r.rms < 0.6  # 0.3 px per coordinate -> ~0.42 px per point, less 6 fitted dof


def test_reported_uncertainty_matches_the_scatter_over_noise_draws():
    """The 1-sigma the fit reports (largest axis) is the spread of the rotation error over noise
    draws: the median error over 60 draws lies between 0.5 and 1.5 times the median reported
    sigma (measured 0.80 for the teapot)."""
    camera, pose, _, xyz = load("teapot_sun_phong")
    clean = cam.project(camera, pose, xyz)
    rng = np.random.default_rng(7)
    rots, sigmas = [], []
    for _ in range(60):
        r = reg.register(clean + rng.normal(scale=0.3, size=clean.shape), xyz, camera.K, camera.dist_coeffs)
        rots.append(errors(r, pose)[0])
        sigmas.append(r.sigma_rotation_deg)
    ratio = np.median(rots) / np.median(sigmas)
    assert 0.5 < ratio < 1.5, ratio


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_twenty_percent_gross_outliers_are_found_and_left_out(name, seed):
    """3 of the 16 clicks moved by 15-60 px: RANSAC (started automatically because the plain fit's
    residuals exceed the threshold) leaves out exactly those, and the pose is the one fitted to the
    13 good points alone (to 1e-4 deg). That pose is as good as 13 noisy points allow: |t| error
    0.1-0.54 % over these 9 cases (the issue's 0.5 % is at the noise floor of 13 points), rotation
    within 2.5 sigma."""
    camera, pose, uv, xyz = load(name)
    rng = np.random.default_rng(seed)
    bad = rng.choice(len(uv), 3, replace=False)
    uv2 = uv.copy()
    uv2[bad] += rng.uniform(15, 60, size=(3, 2)) * rng.choice([-1, 1], size=(3, 2))
    thr = reg.default_threshold(camera.width, camera.height)
    r = reg.register(uv2, xyz, camera.K, camera.dist_coeffs, threshold=thr)
    assert r.method == "sqpnp+ransac"
    assert sorted(np.flatnonzero(~r.inliers)) == sorted(bad)
    good = np.setdiff1d(np.arange(len(uv)), bad)
    ref = reg.register(uv[good], xyz[good], camera.K, camera.dist_coeffs)
    assert reg.rotation_angle_deg(r.R, ref.R) < 1e-4
    rot, trans = errors(r, pose)
    assert trans < 0.0075 and rot < 2.5 * r.sigma_rotation_deg


def test_ransac_off_keeps_the_outliers_and_the_rms_shows_them():
    camera, pose, uv, xyz = load("bunny_sun")
    uv2 = uv.copy()
    uv2[[2, 7, 11]] += 40.0
    r = reg.register(uv2, xyz, camera.K, camera.dist_coeffs, ransac=False)
    assert r.inliers.all() and r.method == "sqpnp" and r.rms > 10


@pytest.mark.parametrize("case, message", [
    ("three", "at least 4"),
    ("five-nonplanar", "at least 6"),
    ("collinear", "collinear"),
    ("coincident-3d", "coincident 3D"),
    ("coincident-image", "coincident image"),
    ("image-collinear", "image points are (nearly) collinear"),
])
def test_degenerate_point_sets_are_refused(case, message):
    camera, pose, uv, xyz = load("teapot_sun_phong")
    if case == "three":
        uv, xyz = uv[:3], xyz[:3]
    elif case == "five-nonplanar":
        uv, xyz = uv[:5], xyz[:5]
    elif case == "collinear":
        xyz = np.outer(np.linspace(0, 1, 8), [0.3, 0.2, 0.5])
        uv = cam.project(camera, pose, xyz) + np.random.default_rng(0).normal(scale=0.5, size=(8, 2))
    elif case == "coincident-3d":
        xyz = xyz.copy()
        xyz[5] = xyz[3]
    elif case == "coincident-image":
        uv = uv.copy()
        uv[5] = uv[3]
    elif case == "image-collinear":
        uv = np.column_stack([np.linspace(10, 200, len(uv)), np.linspace(20, 100, len(uv))])
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        reg.register(uv, xyz, camera.K, camera.dist_coeffs)


def test_four_coplanar_points_are_enough():
    camera, pose, _, _ = load("spot_overcast")
    xyz = np.array([[-0.8, -0.6, 0.0], [0.7, -0.5, 0.0], [0.6, 0.8, 0.0], [-0.7, 0.5, 0.0]])
    uv = cam.project(camera, pose, xyz)
    r = reg.register(uv, xyz, camera.K, camera.dist_coeffs)
    assert r.planar and errors(r, pose)[0] < 1e-3


def test_distance_to_mesh_is_exact():
    # a unit square in z = 0 made of two triangles, and a tall thin triangle
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [5, 5, 0], [5, 5, 10], [5.01, 5, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    p = np.array([[0.3, 0.6, 0.25],  # above the square: its height
                  [2.0, 0.5, 0.0],  # beside an edge: distance to the edge
                  [-3.0, -4.0, 0.0],  # beyond a corner: distance to the corner
                  [5.0, 4.0, 5.0]])  # beside the middle of the long triangle, far from its vertices
    d = reg.distance_to_mesh(p, v, f)
    np.testing.assert_allclose(d, [0.25, 1.0, 5.0, 1.0], atol=1e-9)


# -- refinement against the photo's edges -----------------------------------------------------------

def _edges_setup(name):
    from pipelines.io import images
    from pipelines.geometry import raycast
    from pipelines.io.scene_files import load_mesh

    d = SCENES / name
    mesh = load_mesh(d / "mesh.ply")
    return mesh, raycast.make_backend(mesh), images.read_image(d / "image.exr").pixels


@pytest.mark.parametrize("name", NAMES)
def test_edge_refinement_meets_the_pose_goal(name):
    """The clicks alone leave 0.30-0.39 deg of rotation error (their noise floor); fitting the mesh's
    outline to the photo's edges as well brings it under the issue's 0.2 deg and keeps |t| within
    0.5 %. Measured: 0.15 / 0.09 / 0.05 deg, |t| 0.12 / 0.14 / 0.30 %."""
    camera, pose, uv, xyz = load(name)
    mesh, backend, photo = _edges_setup(name)
    r = reg.register(uv, xyz, camera.K, camera.dist_coeffs)
    e = reg.refine_with_edges(r, uv, xyz, camera.K, camera.dist_coeffs, mesh.vertices, mesh.faces, backend,
                              reg.photo_edges(photo))
    assert e.accepted, e.reason
    rot, trans = reg.rotation_angle_deg(e.R, pose.R), np.linalg.norm(e.t - pose.t) / np.linalg.norm(pose.t)
    assert rot < 0.2 and trans < 0.005, (rot, trans)
    assert rot < 0.6 * reg.rotation_angle_deg(r.R, pose.R)  # better than the clicks alone
    assert e.aligned_after > e.aligned_before and e.rms_clicks_after < 1.0


@pytest.mark.parametrize("name", NAMES)
def test_edge_refinement_after_ransac_with_twenty_percent_outliers(name):
    camera, pose, uv, xyz = load(name)
    mesh, backend, photo = _edges_setup(name)
    rng = np.random.default_rng(5)
    bad = rng.choice(len(uv), 3, replace=False)
    uv2 = uv.copy()
    uv2[bad] += rng.uniform(15, 60, size=(3, 2)) * rng.choice([-1, 1], size=(3, 2))
    r = reg.register(uv2, xyz, camera.K, camera.dist_coeffs, threshold=reg.default_threshold(camera.width,
                                                                                            camera.height))
    assert sorted(np.flatnonzero(~r.inliers)) == sorted(bad)
    e = reg.refine_with_edges(r, uv2, xyz, camera.K, camera.dist_coeffs, mesh.vertices, mesh.faces, backend,
                              reg.photo_edges(photo))
    assert e.accepted, e.reason
    rot, trans = reg.rotation_angle_deg(e.R, pose.R), np.linalg.norm(e.t - pose.t) / np.linalg.norm(pose.t)
    assert rot < 0.2 and trans < 0.005, (rot, trans)


def test_edge_refinement_cannot_drag_the_pose_away_from_the_clicks():
    """A black photo has no edges: refused with the reason, the clicks' pose kept. A photo of pure
    noise has edges everywhere: the clicks hold the pose (measured: it moves 0.008 deg, the clicks'
    RMS 0.43 px as before)."""
    camera, pose, uv, xyz = load("teapot_sun_phong")
    mesh, backend, photo = _edges_setup("teapot_sun_phong")
    noise = np.random.default_rng(0).uniform(0, 1, size=photo.shape).astype(np.float32)
    r = reg.register(uv, xyz, camera.K, camera.dist_coeffs)
    blank = reg.refine_with_edges(r, uv, xyz, camera.K, camera.dist_coeffs, mesh.vertices, mesh.faces, backend,
                                  reg.photo_edges(np.zeros_like(photo)))
    assert not blank.accepted and np.array_equal(blank.R, r.R)
    e = reg.refine_with_edges(r, uv, xyz, camera.K, camera.dist_coeffs, mesh.vertices, mesh.faces, backend,
                              reg.photo_edges(noise))
    if e.accepted:  # the clicks hold the pose: it may move only within their noise
        assert e.rotation_change_deg < 2 * r.sigma_rotation_deg and e.rms_clicks_after < 2 * r.rms
    else:
        assert np.array_equal(e.R, r.R) and e.reason
