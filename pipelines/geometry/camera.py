"""Camera rays (OpenCV model) and the per-pixel surface samples the solver fits.

A *used pixel* is a pixel whose centre ray hits the mesh, that the optional mask keeps, and that is
not within `edge_margin` pixels of a silhouette or depth discontinuity (mixed pixels there blend
two surfaces, which no per-pixel model can fit).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .mesh import Mesh


@dataclass(frozen=True)
class Camera:
    """OpenCV pinhole camera with distortion (k1, k2, p1, p2, k3); pixel (0, 0)'s centre at (0, 0)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=np.float64)

    def to_json(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "dist": list(self.dist), **self.extra}


@dataclass(frozen=True)
class Pose:
    """World -> camera transform x_cam = R X + t."""

    R: np.ndarray
    t: np.ndarray
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def camera_centre(self) -> np.ndarray:
        return -self.R.T @ self.t

    def to_json(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist(), **self.extra}

    @classmethod
    def look_at(cls, eye, target) -> "Pose":
        """A camera at `eye` looking at `target`, +Z up in the image (OpenCV axes: x right, y down,
        z forward); `eye - target` must not be vertical."""
        eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
        f = target - eye
        f /= np.linalg.norm(f)
        r = np.cross(f, [0.0, 0.0, 1.0])
        r /= np.linalg.norm(r)
        R = np.stack([r, np.cross(f, r), f])
        return cls(R, -R @ eye)


def project(camera: Camera, pose: Pose, points: np.ndarray) -> np.ndarray:
    """(n, 3) world points -> (n, 2) pixel coordinates (u, v) with distortion."""
    import cv2

    rvec, _ = cv2.Rodrigues(pose.R)
    uv, _ = cv2.projectPoints(np.asarray(points, np.float64).reshape(-1, 1, 3), rvec, pose.t,
                              camera.K, camera.dist_coeffs)
    return uv.reshape(-1, 2)


def pixel_rays(camera: Camera, pose: Pose, rows: np.ndarray, cols: np.ndarray):
    """World-space rays through pixel centres (u = col, v = row), undoing lens distortion.

    Returns origins (n, 3) (all the camera centre) and unit directions (n, 3).
    """
    uv = np.stack([cols, rows], axis=-1).astype(np.float64).reshape(-1, 1, 2)
    if np.any(camera.dist_coeffs != 0):
        import cv2  # (only here: its import is ~40 ms of a solve)

        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        xy = cv2.undistortPoints(uv, camera.K, camera.dist_coeffs, R=np.eye(3), P=np.eye(3),
                                 criteria=criteria).reshape(-1, 2)
    else:
        xy = np.column_stack([(uv[:, 0, 0] - camera.cx) / camera.fx, (uv[:, 0, 1] - camera.cy) / camera.fy])
    d_cam = np.column_stack([xy, np.ones(len(xy))])
    d = d_cam @ pose.R  # R^T d for each row
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(pose.camera_centre, d.shape).copy()
    return o, d


@dataclass(frozen=True)
class PixelSamples:
    """Surface samples of the used pixels, in world coordinates.

    pixel : (P, 2) int32 (row, col); position, normal (smooth shading), geometric_normal (facing
    the camera), view (unit, towards the camera): (P, 3) float64; face : (P,) int64;
    normal_jacobian : (P, 3, 2) float32 or None, how the shading normal turns across the pixel: its
    change over one pixel along the image's columns (u) and rows (v) (`normal_jacobian`), which
    widens a glossy lobe seen through the pixel (`microfacet.footprint_roughness`).
    """

    pixel: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    geometric_normal: np.ndarray
    view: np.ndarray
    face: np.ndarray
    normal_jacobian: np.ndarray | None = None

    FIELDS = ("pixel", "position", "normal", "geometric_normal", "view", "face", "normal_jacobian")

    def __len__(self) -> int:
        return len(self.pixel)

    def take(self, rows) -> "PixelSamples":
        """The samples of some rows (indices, a mask or a slice)."""
        return PixelSamples(**{f: None if getattr(self, f) is None else np.asarray(getattr(self, f))[rows]
                               for f in self.FIELDS})

    @staticmethod
    def concatenate(parts: list["PixelSamples"], pixels: np.ndarray) -> "PixelSamples":
        """Several views' samples one after the other, with their `pixels` (row, col) as given."""
        fields = {f: np.concatenate([getattr(s, f) for s in parts]) for f in PixelSamples.FIELDS[1:-1]}
        jac = None
        if any(s.normal_jacobian is not None for s in parts):  # (a view without it: its pixels' normals do not turn)
            jac = np.concatenate([np.zeros((len(s), 3, 2), np.float32) if s.normal_jacobian is None
                                  else s.normal_jacobian for s in parts])
        return PixelSamples(pixel=pixels, **fields, normal_jacobian=jac)


def _edges(hit: np.ndarray, depth: np.ndarray, face_normal_dot: np.ndarray, tolerance: float) -> np.ndarray:
    """Pixels next to a silhouette (hit/miss change) or a depth jump larger than expected for the
    local surface slope (a surface seen at grazing angle changes depth fast without an edge)."""
    edge = np.zeros_like(hit)
    for axis in (0, 1):
        h0 = np.take(hit, range(hit.shape[axis] - 1), axis=axis)
        h1 = np.take(hit, range(1, hit.shape[axis]), axis=axis)
        d0 = np.take(depth, range(depth.shape[axis] - 1), axis=axis)
        d1 = np.take(depth, range(1, depth.shape[axis]), axis=axis)
        c0 = np.take(face_normal_dot, range(depth.shape[axis] - 1), axis=axis)
        c1 = np.take(face_normal_dot, range(1, depth.shape[axis]), axis=axis)
        with np.errstate(invalid="ignore", divide="ignore"):
            # depth step of a plane seen at cosine c across one pixel ~ depth * pixel_angle / c
            allowed = tolerance * np.maximum(d0, d1) / np.maximum(np.minimum(c0, c1), 0.05)
            jump = (h0 != h1) | (h0 & h1 & (np.abs(d1 - d0) > allowed))
        sl0 = [slice(None)] * 2
        sl1 = [slice(None)] * 2
        sl0[axis] = slice(0, -1)
        sl1[axis] = slice(1, None)
        edge[tuple(sl0)] |= jump
        edge[tuple(sl1)] |= jump
    return edge


def _cast(camera: Camera, pose: Pose, mesh: Mesh, backend):
    """One ray per pixel centre: rows, cols, origins, directions, hit distance, face, barycentrics
    (n, 3), hit points (n, 3) (float64 on the hit face: `first_hits`), the (H, W) hit mask and the
    (H, W) silhouette / depth-jump edges."""
    H, W = camera.height, camera.width
    rows, cols = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    rows, cols = rows.ravel(), cols.ravel()
    o, d = pixel_rays(camera, pose, rows, cols)
    t, face, bary, points = backend.first_hits(o, d)
    hit = (face >= 0).reshape(H, W)
    depth = np.where(hit.ravel(), t, np.inf).reshape(H, W)
    ng = mesh.face_normals[np.where(face >= 0, face, 0)]
    cos_view = np.abs(np.einsum("ij,ij->i", ng, -d)).reshape(H, W)
    pixel_angle = 1.0 / max(camera.fx, camera.fy)
    edge = _edges(hit, depth, cos_view, tolerance=4.0 * pixel_angle)
    return rows, cols, o, d, t, face, bary, points, hit, edge


def mesh_outline(camera: Camera, pose: Pose, mesh: Mesh, backend) -> np.ndarray:
    """(H, W) bool: pixels on the mesh's silhouette or on a depth jump, as the pose puts them
    (for overlays that show how well the mesh sits on the photo)."""
    return _cast(camera, pose, mesh, backend)[-1]


def mesh_hits(camera: Camera, pose: Pose, backend) -> np.ndarray:
    """(H, W) bool: the pixels whose centre ray hits the mesh (`pixel_samples` with no edge margin
    and no mask keeps exactly these), without building their samples."""
    H, W = camera.height, camera.width
    rows, cols = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    o, d = pixel_rays(camera, pose, rows.ravel(), cols.ravel())
    return (backend.first_hits(o, d)[1] >= 0).reshape(H, W)


def pixel_samples(camera: Camera, pose: Pose, mesh: Mesh, backend, mask: np.ndarray | None = None,
                  edge_margin: int = 1, mask_path=None, with_hits: bool = False):
    """Cast one ray per pixel centre and keep the used pixels.

    Returns the samples and diagnostics (pixel counts at each step), and with `with_hits` also
    the (H, W) mask of the pixels whose centre ray hits the mesh (`mesh_hits`'s).
    """
    from scipy import ndimage

    H, W = camera.height, camera.width
    if mask is not None and mask.shape != (H, W):
        raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]}, camera.json says {W}x{H}", mask_path,
                         "use a mask of the photo's size")
    z_cam = mesh.vertices @ pose.R[2] + pose.t[2]
    if np.all(z_cam <= 0):
        raise InputError("the pose puts the whole mesh behind the camera", None,
                         "check pose.json (world->camera, x_cam = R X + t) or rerun wavelight register")
    rows, cols, o, d, t, face, bary, points, hit, edge = _cast(camera, pose, mesh, backend)
    if not hit.any():
        raise InputError("no pixel of the image sees the mesh", None,
                         "check pose.json and camera.json (does the mesh project into the image?)")
    fn = mesh.face_normals
    if edge_margin > 0:
        edge = ndimage.binary_dilation(edge, iterations=edge_margin)
    used = hit & ~edge if edge_margin >= 0 else hit
    diagnostics = {"pixels": H * W, "hit": int(hit.sum()), "after_edges": int(used.sum())}
    if mask is not None:
        used &= mask
        diagnostics["mask"] = int(mask.sum())
    diagnostics["used"] = int(used.sum())
    if not used.any():
        raise InputError("no usable pixel: the mask and the mesh's image do not overlap", mask_path,
                         "check mask.png (white = use) and the pose")
    sel = np.flatnonzero(used.ravel())
    f = face[sel]
    w = bary[sel]
    tri = mesh.faces[f]
    position = points[sel]
    normal = np.einsum("ik,ikj->ij", w, mesh.vertex_normals[tri])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True).clip(1e-12)
    view = -d[sel]
    geo = fn[f]
    geo[np.einsum("ij,ij->i", geo, view) < 0] *= -1  # orient towards the camera
    # Surfaces seen from their back side (normals pointing away from the camera) reflect nothing
    # under one-sided shading, as in physically based renderers; count them for the report.
    diagnostics["back_facing"] = int(np.count_nonzero(np.einsum("ij,ij->i", normal, view) < 0))
    jac = normal_jacobian(camera, pose, mesh, rows[sel], cols[sel], f, position)
    samples = PixelSamples(pixel=np.column_stack([rows[sel], cols[sel]]).astype(np.int32), position=position,
                           normal=normal, geometric_normal=geo, view=view, face=f, normal_jacobian=jac)
    return (samples, diagnostics, hit) if with_hits else (samples, diagnostics)


def normal_jacobian(camera: Camera, pose: Pose, mesh: Mesh, rows: np.ndarray, cols: np.ndarray, face: np.ndarray,
                    position: np.ndarray) -> np.ndarray:
    """(P, 3, 2) float32: how the unit shading normal changes across each pixel, d n / d u (one
    column) and d n / d v (one row), on the pixel's own facet.

    On a facet the interpolated normal sum_i b_i n_i is affine in the surface point, and the point
    moves with the pixel as the facet's plane cut by the rays through the pixel's neighbours
    (half a pixel either side: a ray differential, lens distortion included). A low-poly mesh with
    smooth normals turns its normal fast where it curves (suzanne_plastic_sun at 320 x 240: over 0.2
    per pixel on a tenth of the object's pixels), and a highlight there is the average of the lobe over
    those normals (what a renderer's pixel filter sees).

    A pixel's turn is capped at its facet's own: the largest difference of its vertex normals (a
    facet seen edge-on, or a sliver, would extrapolate its plane far beyond the facet); a
    half-pixel ray parallel to the facet's plane gives no turn along that axis."""
    # the facets' own quantities once per facet (a facet covers many pixels), then per pixel
    facets, at = np.unique(face, return_inverse=True)
    tri = mesh.faces[facets]
    p0, p1, p2 = (mesh.vertices[tri[:, i]] for i in range(3))
    n0, n1, n2 = (mesh.vertex_normals[tri[:, i]] for i in range(3))
    E = np.stack([p1 - p0, p2 - p0], axis=2)  # (F, 3, 2)
    M = np.stack([n1 - n0, n2 - n0], axis=2)
    g = np.cross(E[:, :, 0], E[:, :, 1])
    area2 = np.linalg.norm(g, axis=1)
    ok = area2 > 1e-12 * np.maximum(np.einsum("pij,pij->p", E, E), 1e-300)
    g = g / np.maximum(area2, 1e-300)[:, None]
    EtE = np.einsum("pki,pkj->pij", E, E)
    EtE[~ok] = np.eye(2)
    pinv = np.linalg.solve(EtE, np.transpose(E, (0, 2, 1)))  # (F, 2, 3): barycentrics (b1, b2) per unit of point
    Mp = M @ pinv  # (F, 3, 3): the raw normal's change per unit of point
    spread = np.max([np.linalg.norm(a - b, axis=1) for a, b in ((n0, n1), (n1, n2), (n2, n0))], axis=0)[at]
    plane = np.einsum("pk,pk->p", p0 - pose.camera_centre, g)[at]  # the facet's plane: g . x = g . p0
    ok, g, Mp = ok[at], g[at], Mp[at]
    raw = n0[at] + np.einsum("pij,pj->pi", Mp, position - p0[at])  # the interpolated normal before normalising
    length = np.maximum(np.linalg.norm(raw, axis=1), 1e-12)
    unit = raw / length[:, None]
    out = np.zeros((len(face), 3, 2), np.float64)
    o = pose.camera_centre
    for k, (dr, dc) in enumerate(((0.0, 0.5), (0.5, 0.0))):
        ends, hit = [], np.ones(len(face), bool)
        for sgn in (-1.0, 1.0):
            _, d = pixel_rays(camera, pose, rows + sgn * dr, cols + sgn * dc)
            den = np.einsum("pk,pk->p", d, g)
            front = np.abs(den) > 1e-9
            s = plane / np.where(front, den, 1.0)
            hit &= front & (s > 0)
            ends.append(o + s[:, None] * d)
        dx = ends[1] - ends[0]  # the surface point's move across the pixel, on the facet's plane
        dn = np.einsum("pij,pj->pi", Mp, dx)  # of the raw normal
        dn -= np.einsum("pk,pk->p", dn, unit)[:, None] * unit  # of the unit normal
        out[:, :, k] = np.where(hit[:, None], dn / length[:, None], 0.0)
    out[~ok] = 0.0
    turn = np.linalg.norm(out, axis=1)  # (P, 2)
    out *= (np.minimum(turn, spread[:, None]) / np.maximum(turn, 1e-300))[:, None, :]
    return np.nan_to_num(out).astype(np.float32)
