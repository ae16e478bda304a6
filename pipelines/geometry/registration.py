"""The mesh's pose from manual 2D-3D correspondences (OpenCV solvePnP), as pure functions over arrays.

The pose maps world to camera, x_cam = R X + t (DESIGN §2). The fit:
  1. check the points: enough of them (4 if the 3D points are coplanar, else 6: five clicks give a
     pose but no redundancy to see a bad click), not coincident, not collinear in 3D or in the image;
  2. SQPnP (a global solver, no initial guess) or OpenCV's iterative solver, then Levenberg-Marquardt
     on the reprojection error;
  3. RANSAC (cv2.solvePnPRansac with a fixed seed, so reruns agree) when asked, or when a point's
     residual exceeds the outlier threshold after step 2; the inliers are refined by LM again and the
     inlier set is recomputed until it stops changing;
  4. checks on the result: every point in front of the camera; the uncertainty of the pose from the
     Jacobian of the residuals.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

MIN_PLANAR, MIN_GENERAL = 4, 6
RANSAC_SEED = 20261123


@dataclass
class Registration:
    R: np.ndarray  # (3, 3) world -> camera
    t: np.ndarray  # (3,)
    residuals: np.ndarray  # (n, 2) projected - observed, pixels, for every point
    inliers: np.ndarray  # (n,) bool: the points the pose was fitted to
    method: str  # 'sqpnp' / 'iterative', with '+ransac' when RANSAC chose the inliers
    planar: bool
    threshold: float  # outlier threshold in pixels
    sigma_rotation_deg: float  # 1-sigma rotation uncertainty (largest axis), from the Jacobian
    sigma_translation: float  # 1-sigma uncertainty of the camera centre (largest axis), world units
    warnings: list[str] = field(default_factory=list)

    @property
    def errors(self) -> np.ndarray:
        return np.linalg.norm(self.residuals, axis=1)

    @property
    def rms(self) -> float:
        """Reprojection RMS over the inliers, pixels."""
        return float(np.sqrt(np.mean(self.errors[self.inliers] ** 2)))

    @property
    def rms_all(self) -> float:
        return float(np.sqrt(np.mean(self.errors**2)))

    @property
    def camera_centre(self) -> np.ndarray:
        return -self.R.T @ self.t


def default_threshold(width: int, height: int) -> float:
    """Outlier threshold: 0.5 % of the image diagonal, at least 3 px (a careful click is within a
    pixel or two at any resolution; a wrong click is off by tens)."""
    return max(3.0, 0.005 * float(np.hypot(width, height)))


def check_points(uv: np.ndarray, xyz: np.ndarray) -> bool:
    """Raise InputError for point sets no pose can come from; return whether the 3D points are coplanar."""
    n = len(uv)
    if n < MIN_PLANAR:
        raise InputError(f"{n} correspondences, at least {MIN_PLANAR} are needed (6 unless the points are "
                         "coplanar)", None, "click more 2D-3D point pairs")
    scale = float(np.linalg.norm(xyz.max(0) - xyz.min(0)))
    d3 = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
    d2 = np.linalg.norm(uv[:, None] - uv[None], axis=2)
    i, j = np.nonzero(np.triu((d3 <= 1e-9 * max(scale, 1e-30)) | (d2 < 1e-3), 1))
    if len(i):
        pairs = ", ".join(f"{a + 2} and {b + 2}" for a, b in list(zip(i, j))[:3])
        what = "3D" if d3[i[0], j[0]] <= 1e-9 * max(scale, 1e-30) else "image"
        raise InputError(f"coincident {what} points on lines {pairs}", None,
                         "each correspondence must be a different point; remove or fix the repeats")
    s3 = np.linalg.svd(xyz - xyz.mean(0), compute_uv=False)
    s2 = np.linalg.svd(uv - uv.mean(0), compute_uv=False)
    if s3[1] <= 1e-3 * s3[0]:
        raise InputError("the 3D points are (nearly) collinear: the rotation about their line is unknown", None,
                         "add points off that line")
    if s2[1] <= 1e-3 * s2[0]:
        raise InputError("the image points are (nearly) collinear", None, "add points off that line in the image")
    planar = bool(s3[2] <= 1e-3 * s3[0])
    if not planar and n < MIN_GENERAL:
        raise InputError(f"{n} correspondences of non-coplanar points, at least {MIN_GENERAL} are needed", None,
                         "click more 2D-3D point pairs (with 6 or more, one bad click shows in the residuals)")
    return planar


def _project(xyz, rvec, tvec, K, dist):
    import cv2

    uv, J = cv2.projectPoints(xyz.reshape(-1, 1, 3), rvec, tvec, K, dist)
    return uv.reshape(-1, 2), J[:, :6]


def _solve(uv, xyz, K, dist, method, guess=None):
    import cv2

    flag = cv2.SOLVEPNP_SQPNP if method == "sqpnp" else cv2.SOLVEPNP_ITERATIVE
    if guess is None:
        ok, rvec, tvec = cv2.solvePnP(xyz, uv, K, dist, flags=flag)
        if not ok:
            raise InputError("solvePnP found no pose", None, "check that the points match (u,v = column,row)")
    else:
        rvec, tvec = guess
    return _refine(uv, xyz, K, dist, np.ravel(rvec), np.ravel(tvec))


def _refine(uv, xyz, K, dist, rvec, tvec):
    """Levenberg-Marquardt on the reprojection error (scipy, analytic Jacobian from projectPoints),
    run to convergence: cv2.solvePnPRefineLM stops early (measured: its pose after RANSAC is
    0.05 deg from the optimum)."""
    from scipy.optimize import least_squares

    def residual(x):
        return (_project(xyz, x[:3], x[3:], K, dist)[0] - uv).ravel()

    def jacobian(x):
        return _project(xyz, x[:3], x[3:], K, dist)[1]

    x = least_squares(residual, np.concatenate([rvec, tvec]).astype(np.float64), jac=jacobian, method="lm",
                      xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=1000).x
    return x[:3].copy(), x[3:].copy()


def _ransac(uv, xyz, K, dist, method, threshold):
    import cv2

    cv2.setRNGSeed(RANSAC_SEED)
    flag = cv2.SOLVEPNP_SQPNP if method == "sqpnp" else cv2.SOLVEPNP_EPNP
    ok, rvec, tvec, idx = cv2.solvePnPRansac(xyz, uv, K, dist, iterationsCount=5000, reprojectionError=threshold,
                                             confidence=0.9999, flags=flag)
    if not ok or idx is None:
        return None
    return rvec.reshape(3), tvec.reshape(3)


def register(uv: np.ndarray, xyz: np.ndarray, K: np.ndarray, dist: np.ndarray, method: str = "sqpnp",
             ransac: bool | None = None, threshold: float = 3.0) -> Registration:
    """Pose of the world points `xyz` (n, 3) seen at pixels `uv` (n, 2) by camera (K, dist).

    ransac: True always, False never, None when a residual of the plain fit exceeds `threshold`.
    Raises InputError for degenerate point sets and for a pose with points behind the camera.
    """
    uv = np.ascontiguousarray(uv, np.float64).reshape(-1, 2)
    xyz = np.ascontiguousarray(xyz, np.float64).reshape(-1, 3)
    if method not in ("sqpnp", "iterative"):
        raise ValueError(f"unknown method {method!r}")
    planar = check_points(uv, xyz)
    dist = np.asarray(dist, np.float64)
    rvec, tvec = _solve(uv, xyz, K, dist, method)
    err = np.linalg.norm(_project(xyz, rvec, tvec, K, dist)[0] - uv, axis=1)
    used = "+ransac" if ransac else ""
    if ransac or (ransac is None and err.max() > threshold):
        guess = _ransac(uv, xyz, K, dist, method, threshold)
        if guess is not None:
            used = "+ransac"
            rvec, tvec = guess
    need = MIN_PLANAR if planar else MIN_GENERAL
    inliers = np.ones(len(uv), bool)
    for _ in range(10):
        err = np.linalg.norm(_project(xyz, rvec, tvec, K, dist)[0] - uv, axis=1)
        new = err <= threshold if used else np.ones(len(uv), bool)
        if new.sum() < need:  # RANSAC found no consensus: keep every point, the RMS will say so
            new = np.ones(len(uv), bool)
        if np.array_equal(new, inliers) and _ > 0:
            break
        inliers = new
        rvec, tvec = _solve(uv[inliers], xyz[inliers], K, dist, method, guess=(rvec, tvec))
    proj, J = _project(xyz, rvec, tvec, K, dist)
    residuals = proj - uv
    import cv2

    R, _ = cv2.Rodrigues(rvec)
    z = xyz @ R[2] + tvec[2]
    if np.any(z <= 0):
        rows = ", ".join(str(k + 2) for k in np.flatnonzero(z <= 0)[:5])
        raise InputError(f"the fitted pose puts points behind the camera (lines {rows})", None,
                         "check that u,v are pixel column,row and that x,y,z are in the mesh's world frame")
    s_rot, s_t = _uncertainty(residuals[inliers], J.reshape(-1, 2, 6)[inliers].reshape(-1, 6), R, tvec)
    return Registration(R, tvec, residuals, inliers, method + used, planar, float(threshold), s_rot, s_t)


def _uncertainty(residuals, J, R, t):
    """1-sigma rotation (deg, largest axis) and camera-centre (largest axis) uncertainty from the
    Gauss-Newton covariance sigma^2 (J^T J)^-1, sigma^2 = SSR / (2n - 6)."""
    dof = residuals.size - 6
    if dof <= 0:
        return float("nan"), float("nan")
    s2 = float(np.sum(residuals**2)) / dof
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return float("inf"), float("inf")
    rot = np.degrees(np.sqrt(np.linalg.eigvalsh(cov[:3, :3]).max()))
    # camera centre c = -R^T t: linearised in t only (rotation's share is in sigma_rotation)
    cc = R.T @ cov[3:, 3:] @ R
    return float(rot), float(np.sqrt(np.linalg.eigvalsh(cc).max()))


def reprojection(R: np.ndarray, t: np.ndarray, uv: np.ndarray, xyz: np.ndarray, K: np.ndarray,
                 dist: np.ndarray) -> np.ndarray:
    """(n, 2) residuals projected - observed (pixels) of a pose."""
    import cv2

    rvec = cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()
    return _project(np.ascontiguousarray(xyz, np.float64), rvec, np.asarray(t, np.float64), K, dist)[0] - uv


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of the rotation between two rotation matrices, degrees."""
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Exact distance of each point (n, 3) to a triangle mesh.

    Triangles are pruned by a bound: a triangle is no closer than |p - centroid| - its radius, and
    no triangle can matter beyond the distance to the nearest vertex."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64).reshape(-1, 3)
    tri = vertices[faces]
    centroid = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centroid[:, None], axis=2).max(axis=1)
    upper, _ = cKDTree(vertices).query(points)
    out = np.empty(len(points))
    for k, p in enumerate(points):
        cand = np.flatnonzero(np.linalg.norm(centroid - p, axis=1) - radius <= upper[k] + 1e-12)
        out[k] = min(upper[k], float(_point_triangle_distance(p, tri[cand]).min())) if len(cand) else upper[k]
    return out


def _point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance from one point to each triangle (m, 3, 3): the plane's foot if it falls inside,
    else the nearest of the three edges."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    nn = np.einsum("ij,ij->i", n, n)
    ok = nn > 0
    nn = np.where(ok, nn, 1.0)
    foot = p - (np.einsum("ij,ij->i", p - a, n) / nn)[:, None] * n
    inside = ok.copy()
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(v - u, foot - u), n) >= 0
    best = np.where(inside, np.linalg.norm(p - foot, axis=1), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        ee = np.einsum("ij,ij->i", e, e)
        s = np.clip(np.einsum("ij,ij->i", p - u, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(p - (u + s[:, None] * e), axis=1))
    return best


# -- refinement against the photo's edges ---------------------------------------------------------

@dataclass
class PhotoEdges:
    """Edge points of a photo at sub-pixel positions with their unit normals (the grey-level
    gradient direction), and a tree to find the nearest ones."""

    points: np.ndarray  # (m, 2) u, v
    normals: np.ndarray  # (m, 2)
    shape: tuple[int, int]

    def __post_init__(self):
        from scipy.spatial import cKDTree

        self.tree = cKDTree(self.points) if len(self.points) else None

    def distance(self, uv: np.ndarray, cap: float) -> np.ndarray:
        """Distance from each point to the tangent line of its nearest edge point (px), at most `cap`."""
        if self.tree is None:
            return np.full(len(uv), cap)
        d, i = self.tree.query(uv, distance_upper_bound=2 * cap)
        ok = np.isfinite(d)
        out = np.full(len(uv), cap)
        j = i[ok]
        out[ok] = np.abs(np.einsum("ij,ij->i", uv[ok] - self.points[j], self.normals[j]))
        return np.minimum(out, cap)


def photo_edges(image: np.ndarray, low: float = 30.0, high: float = 90.0) -> PhotoEdges:
    """Edges of a linear RGB photo: Canny on the tone-mapped grey image (hysteresis thresholds
    `low`/`high` in 8-bit levels), each edge pixel moved to the peak of the gradient magnitude along
    the gradient (a parabola through three samples), so that edges are located to a fraction of a
    pixel and the choice of pixel Canny makes on either side of a step does not bias them."""
    import cv2
    from scipy import ndimage

    from ..io.images import tonemap

    grey = np.round(tonemap(image) @ np.array([0.299, 0.587, 0.114]) * 255.0).astype(np.uint8)
    blurred = cv2.GaussianBlur(grey, (3, 3), 0)
    edges = cv2.Canny(blurred, low, high)
    g = blurred.astype(np.float64)
    gx = cv2.Sobel(g, cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_64F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    v, u = np.nonzero(edges)
    n = np.column_stack([gx[v, u], gy[v, u]])
    norm = np.linalg.norm(n, axis=1)
    keep = norm > 0
    u, v, n = u[keep], v[keep], n[keep] / norm[keep, None]
    m0 = mag[v, u]
    mp = ndimage.map_coordinates(mag, [v + n[:, 1], u + n[:, 0]], order=1, mode="nearest")
    mm = ndimage.map_coordinates(mag, [v - n[:, 1], u - n[:, 0]], order=1, mode="nearest")
    curv = mm - 2 * m0 + mp
    delta = np.where(curv < 0, 0.5 * (mm - mp) / np.where(curv < 0, curv, -1.0), 0.0)
    delta = np.clip(delta, -0.5, 0.5)
    pts = np.column_stack([u, v]).astype(np.float64) + delta[:, None] * n
    return PhotoEdges(pts, n, grey.shape)


def outline_points(vertices: np.ndarray, faces: np.ndarray, R: np.ndarray, t: np.ndarray, backend,
                   spacing: float) -> np.ndarray:
    """3D points every `spacing` (world units) along the mesh's outline as the camera (R, t) sees
    it: the contour generator (edges between a face turned towards the camera and one turned
    away) and the open boundary, kept where the camera sees them (a ray from the camera reaches them)."""
    c = -R.T @ t
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    front = np.einsum("ij,ij->i", normal, tri[:, 0] - c) < 0
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    face_of = np.tile(np.arange(len(faces)), 3)
    edges = np.sort(edges, axis=1)
    key = edges[:, 0] * len(vertices) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    key, edges, face_of = key[order], edges[order], face_of[order]
    _, start, count = np.unique(key, return_index=True, return_counts=True)
    boundary = start[count == 1]
    pair = start[count == 2]
    contour = pair[front[face_of[pair]] != front[face_of[pair + 1]]]
    chosen = edges[np.concatenate([boundary, contour])]
    a, b = vertices[chosen[:, 0]], vertices[chosen[:, 1]]
    n = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / spacing).astype(np.int64))
    which = np.repeat(np.arange(len(chosen)), n)
    s = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n) + 0.5) / np.repeat(n, n)
    pts = a[which] + s[:, None] * (b - a)[which]
    if len(pts) == 0:
        return pts
    d = pts - c
    dist = np.linalg.norm(d, axis=1)
    hit_t, face, _, _ = backend.intersect(np.broadcast_to(c, pts.shape).copy(), d / dist[:, None])
    scale = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    return pts[(face < 0) | (hit_t >= dist - 2e-3 * scale)]


@dataclass
class EdgeRefinement:
    R: np.ndarray
    t: np.ndarray
    accepted: bool
    reason: str
    outline_points: int
    aligned_before: float  # fraction of outline samples within 1 px of a photo edge
    aligned_after: float
    rms_clicks_before: float  # reprojection RMS of the inlier clicks, px
    rms_clicks_after: float
    rotation_change_deg: float
    translation_change: float  # |t' - t| / |t|


def refine_with_edges(r: Registration, uv: np.ndarray, xyz: np.ndarray, K: np.ndarray, dist: np.ndarray,
                      vertices: np.ndarray, faces: np.ndarray, backend, edges: PhotoEdges,
                      schedule: tuple[float, ...] = (8.0, 4.0, 2.0), max_click_rms: float | None = None
                      ) -> EdgeRefinement:
    """Refine a pose so that the mesh's outline falls on the photo's edges while the clicked points
    stay put (16 clicks at 0.3 px leave ~0.3 deg of rotation undetermined; a few hundred outline
    samples pin it down).

    Minimises sum soft_l1(d_k) + sum |click residual / sigma|^2 over the 6 pose parameters, with
    d_k the distance (px, capped at the schedule's value, which shrinks 8 -> 4 -> 2 px over the
    rounds) from outline sample k to the nearest photo edge, and sigma the clicks' own RMS per
    coordinate. Edges of shadows and highlights and outline parts without image contrast are
    outliers the robust loss and the cap absorb. The result is kept only if the clicks' RMS stays
    below `max_click_rms` and more of the outline lies on edges than before.
    """
    import cv2
    from scipy.optimize import least_squares

    uv = np.ascontiguousarray(uv, np.float64)
    xyz = np.ascontiguousarray(xyz, np.float64)
    use = r.inliers
    H, W = edges.shape
    sigma = max(r.rms / np.sqrt(2.0), 0.1)
    x0 = np.concatenate([cv2.Rodrigues(r.R)[0].ravel(), r.t])
    x = x0.copy()
    centre = np.mean(xyz[use], axis=0)

    def outline(x):
        R = cv2.Rodrigues(x[:3])[0]
        depth = float(np.linalg.norm(R @ centre + x[3:]))
        pts = outline_points(vertices, faces, R, x[3:], backend, 0.7 * depth / K[0, 0])
        if len(pts) == 0:
            return pts
        p = _project(pts, x[:3], x[3:], K, dist)[0]
        return pts[(p[:, 0] > 2) & (p[:, 0] < W - 3) & (p[:, 1] > 2) & (p[:, 1] < H - 3)]

    def aligned(x, pts):
        p = _project(pts, x[:3], x[3:], K, dist)[0]
        return float(np.mean(edges.distance(p, 2.0) <= 1.0))

    pts = outline(x)
    if len(pts) < 50:
        return EdgeRefinement(r.R, r.t, False, f"too little outline in the image ({len(pts)} samples)", len(pts),
                              float("nan"), float("nan"), r.rms, r.rms, 0.0, 0.0)
    before = aligned(x, pts)
    for cap in schedule:
        pts = outline(x)

        def residual(x):
            p = _project(pts, x[:3], x[3:], K, dist)[0]
            e = edges.distance(p, cap)
            q = (_project(xyz[use], x[:3], x[3:], K, dist)[0] - uv[use]).ravel() / sigma
            return np.concatenate([e, q])

        x = least_squares(residual, x, loss="soft_l1", f_scale=1.0, diff_step=1e-7, max_nfev=200).x
    pts = outline(x)
    after = aligned(x, pts)
    R = cv2.Rodrigues(x[:3])[0]
    t = x[3:].copy()
    rms_after = float(np.sqrt(np.mean(np.sum((_project(xyz[use], x[:3], t, K, dist)[0] - uv[use]) ** 2, axis=1))))
    limit = max_click_rms if max_click_rms is not None else 2.0 * max(r.rms, 0.5)
    change = (rotation_angle_deg(R, r.R), float(np.linalg.norm(t - r.t) / np.linalg.norm(r.t)))
    if rms_after > limit:
        return EdgeRefinement(r.R, r.t, False, f"the clicks would move by {rms_after:.2f} px RMS (> {limit:.2f})",
                              len(pts), before, after, r.rms, rms_after, *change)
    if after <= before:
        return EdgeRefinement(r.R, r.t, False, "the outline does not fit the photo's edges better", len(pts),
                              before, after, r.rms, rms_after, *change)
    return EdgeRefinement(R, t, True, "", len(pts), before, after, r.rms, rms_after, *change)
