"""Hit points and shadow-ray origins for any camera distance and scene scale (issue 17).

An icosphere (level 5, radius = the scene scale, centred off the origin) seen by a camera 2 to 10^5
radii away, the focal length scaled so that the sphere is ~100 px wide in a 128 x 128 image (a long
lens far away, as the DiLiGenT photos are taken). The mesh is a convex polyhedron, so the exact
answers are known:

- the first hit of a pixel's ray is where it enters the polyhedron (the largest entry distance over
  the face planes it crosses inward), computed here in float64 in the sphere's own frame;
- a point on a facet sees every direction in front of the facet (nothing else of a convex
  polyhedron lies outside the facet's plane): no castable shadow ray may be blocked, and every
  direction more than the facets' tilt (~1.2 deg at level 5) above the exact sphere's horizon is
  castable and lit.

Before the float64 hit points and the float32-precision shadow offset, hit points were off by
~eps32 x the camera distance, and from 150 radii on some pixels started their shadow rays under
their own facet (22 % of them all-shadowed at 1,000 radii, 40 % at 10^4).
"""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.geometry.camera import Camera, Pose, mesh_hits, pixel_rays, pixel_samples
from pipelines.geometry.mesh import place, sphere
from pipelines.geometry.raycast import make_backend
from pipelines.geometry.visibility import castable, compute_visibility
from pipelines.light.cubemap import CubeMap

SUBDIVISIONS = 5
IMAGE = 128  # px square
RHO = 50.0  # the sphere's image radius, px
CENTRE = np.array([0.31, -0.23, 0.17])  # x scale: off the origin, so the recentred frame matters
VIEW = np.array([0.42, -0.71, 0.56])  # from the sphere toward the camera
HORIZON_DEG = 2.0  # the facets' tilt from the exact sphere normal (<= 1.2 deg at level 5) and a margin
RATIOS = [2, 10, 100, 1e3, 1e4, 1e5]
SCALES = [1e-3, 1.0, 1e3]


look_at = Pose.look_at


def sphere_view(ratio: float, scale: float):
    """(camera, pose, mesh, centre, radius): the sphere `ratio` radii from the camera, ~2 RHO px wide."""
    radius = scale
    centre = scale * CENTRE
    mesh = place(sphere(radius, SUBDIVISIONS), centre)
    u = VIEW / np.linalg.norm(VIEW)
    focal = RHO * np.sqrt(ratio**2 - 1.0)  # the limb's cone, half-angle asin(1 / ratio), at RHO px
    c = (IMAGE - 1) / 2.0
    return Camera(IMAGE, IMAGE, focal, focal, c, c), look_at(centre + ratio * radius * u, centre), mesh, centre, radius


def polyhedron_entry(mesh, centre, origins, directions, block: int = 256):
    """(n, 3) float64 points where rays enter the convex mesh (NaN: a miss), in the sphere's frame."""
    v = mesh.vertices[mesh.faces] - centre
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = np.einsum("fk,fk->f", n, v[:, 0])  # planes n.x = h
    o = origins - centre
    out = np.full(o.shape, np.nan)
    for a in range(0, len(o), block):
        ob, db = o[a:a + block], directions[a:a + block]
        nd = db @ n.T  # (b, F)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (h[None] - ob @ n.T) / nd
        enter = np.where(nd < 0, t, -np.inf).max(axis=1)
        leave = np.where(nd > 0, t, np.inf).min(axis=1)
        ok = enter <= leave
        out[a:a + block][ok] = ob[ok] + enter[ok, None] * db[ok]
    return out


@pytest.fixture(scope="module")
def cube():
    return CubeMap(8, hemisphere=False)  # the whole sphere of directions: every facet has its hemisphere


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("ratio", RATIOS)
def test_hit_points_and_shadows_of_a_convex_sphere_at_any_distance_and_scale(ratio, scale, cube):
    camera, pose, mesh, centre, radius = sphere_view(ratio, scale)
    backend = make_backend(mesh)
    samples, diag = pixel_samples(camera, pose, mesh, backend)
    assert 7000 < diag["used"] < diag["hit"] < 8100  # pi 50^2 = 7854 pixels see the sphere
    # hit points: on the exact ray-polyhedron intersection to 1e-6 of the radius
    o, d = pixel_rays(camera, pose, samples.pixel[:, 0], samples.pixel[:, 1])
    pick = np.arange(0, len(samples), 7)
    exact = polyhedron_entry(mesh, centre, o[pick], d[pick])
    assert np.isfinite(exact).all()
    err = np.linalg.norm(samples.position[pick] - centre - exact, axis=1) / radius
    assert err.max() < 1e-6, (err.max(), np.median(err))
    # ... on the sphere to the facets' sagitta (level 5: 1 - cos(1.2 deg) ~ 2.2e-4)
    assert np.abs(np.linalg.norm(samples.position - centre, axis=1) / radius - 1.0).max() < 3e-4
    # shadows: a convex polyhedron blocks no castable ray ...
    V = compute_visibility(backend, samples, cube).dense() > 0
    can = castable(samples.normal, samples.geometric_normal, cube.directions)
    blocked = can & ~V
    assert np.count_nonzero(blocked) == 0, (f"{np.count_nonzero(blocked.any(axis=1))} of {len(samples)} pixels "
                                            f"have blocked rays, {np.count_nonzero(V.sum(axis=1) == 0)} all-shadowed")
    # ... and every direction above the exact sphere's horizon (by more than the facets' tilt) is lit
    radial = (samples.position - centre) / radius
    above = (radial @ cube.directions.T) > np.sin(np.radians(HORIZON_DEG))
    assert np.all(V[above]), np.count_nonzero(above & ~V)
    assert np.all(V.sum(axis=1) >= above.sum(axis=1)) and above.sum(axis=1).min() > 0.4 * cube.n_texels


@pytest.mark.parametrize("ratio", [10, 1e3, 1e5])
def test_shadow_origins_clear_the_float32_triangle(ratio):
    """Each shadow-ray origin, as float32 in the recentred frame, is above the plane of its float32
    triangle (the one the kernel traces) by more than float32 can resolve there."""
    camera, pose, mesh, centre, radius = sphere_view(ratio, 1.0)
    backend = make_backend(mesh)
    samples, _ = pixel_samples(camera, pose, mesh, backend)
    origins = backend.shadow_origins(samples.position, samples.geometric_normal, samples.face).astype(np.float64)
    tri = backend.triangles[samples.face].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    height = np.einsum("ij,ij->i", origins - tri[:, 0], n) * np.sign(np.einsum("ij,ij->i", n, samples.geometric_normal))
    ulp = np.finfo(np.float32).eps * np.abs(origins).max(axis=1)
    assert height.min() > 8 * ulp.max(), (height.min(), ulp.max())
    # and the offset is small: below 1e-5 of the radius (the old 1e-5 x scene size was 3.5e-5 here)
    assert height.max() < 1e-5 * radius


@pytest.mark.parametrize("ratio", [2, 1e4])
def test_mesh_hits_are_the_pixels_sampled_without_edge_margin(ratio):
    """`mesh_hits` (what `mesh_coverage` fills for the outputs) is the set of pixels `pixel_samples`
    keeps with no edge margin and no mask, near and far: ~pi RHO^2 of them, the rim included."""
    camera, pose, mesh, _, _ = sphere_view(ratio, 1.0)
    backend = make_backend(mesh)
    hits = mesh_hits(camera, pose, backend)
    samples, diag = pixel_samples(camera, pose, mesh, backend, edge_margin=-1)
    sampled = np.zeros_like(hits)
    sampled[samples.pixel[:, 0], samples.pixel[:, 1]] = True
    assert hits.shape == (IMAGE, IMAGE) and np.array_equal(hits, sampled)
    assert hits.sum() == diag["hit"] and 7700 < hits.sum() < 8100  # pi 50^2 = 7854
