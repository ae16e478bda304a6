"""Camera intrinsics from photos of a calibration target (OpenCV), as pure functions over images.

Targets (OpenCV's conventions, points ordered row by row as OpenCV returns them):
  chessboard  cols x rows inner corners, `spacing` = square size
  circles     symmetric grid of cols x rows dots, `spacing` = centre distance
  acircles    asymmetric grid, OpenCV's pattern size (cols, rows) = (dots per row, rows); dot
              (i, j) sits at ((2j + i mod 2) s, i s): `spacing` s is HALF the centre distance of
              two neighbouring dots in a row (OpenCV's sample convention)
  charuco     cols x rows squares with ArUco markers (OpenCV's CharucoBoard), `spacing` = square,
              `marker` = marker side; a view may show part of the board (points carry corner ids)

Dot detection: OpenCV's default blob detector keeps only dark blobs up to ~80 px across (its
maxArea is 5000 px^2). Here the area range scales with the image, dark and light dots are both
tried, and blobs are kept only in the largest size class that has enough members for the grid
(specks of dust or text next to the target are a different size), so findCirclesGrid sees only
candidate dots. Dot centres are refined to the centroid of their ink (refine_dots) and, in
calibrate, corrected for the offset of a projected disc's centroid from its projected centre.
Chessboard corners are refined by cornerSubPix, ChArUco corners again in a window that stays
clear of the markers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

PATTERNS = ("chessboard", "circles", "acircles", "charuco")
MIN_CHARUCO_CORNERS = 6  # a view with fewer interpolated ChArUco corners is not used


@dataclass(frozen=True)
class Target:
    pattern: str
    cols: int  # charuco: squares per row
    rows: int  # charuco: squares per column
    spacing: float  # in the units the camera's translations will be in (e.g. metres)
    marker: float | None = None  # charuco: the ArUco marker's side (same units)
    dictionary: str = "DICT_5X5_100"  # charuco: OpenCV's predefined ArUco dictionary

    def __post_init__(self):
        if self.pattern not in PATTERNS:
            raise ValueError(f"unknown pattern {self.pattern!r}; use one of {', '.join(PATTERNS)}")
        low = 3 if self.pattern == "charuco" else 2
        if self.cols < low or self.rows < low:
            raise ValueError(f"a {self.pattern} needs at least {low} x {low} {'squares' if low == 3 else 'points'}, "
                             f"got {self.cols} x {self.rows}")
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise ValueError(f"the spacing must be a positive number, got {self.spacing}")
        if self.pattern == "charuco":
            import cv2

            if self.marker is None or not (0 < self.marker < self.spacing):
                raise ValueError(f"a ChArUco marker must be smaller than its square ({self.spacing:g}), got "
                                 f"{self.marker}")
            if not (self.dictionary.startswith("DICT_") and hasattr(cv2.aruco, self.dictionary)):
                raise ValueError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_5X5_100, DICT_6X6_250)")

    @property
    def size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    @property
    def n_points(self) -> int:
        if self.pattern == "charuco":
            return (self.cols - 1) * (self.rows - 1)
        return self.cols * self.rows

    def board(self):
        """The cv2.aruco.CharucoBoard of a charuco target."""
        import cv2

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(self.size, float(self.spacing), float(self.marker), d)

    def object_points(self) -> np.ndarray:
        """(n_points, 3) float32 target coordinates (z = 0) in detection order (charuco: by corner id)."""
        if self.pattern == "charuco":
            return np.asarray(self.board().getChessboardCorners(), np.float32).reshape(-1, 3)
        i, j = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        x = (2 * j + i % 2) if self.pattern == "acircles" else j
        pts = np.stack([x.ravel(), i.ravel(), np.zeros(self.n_points)], axis=1) * self.spacing
        return pts.astype(np.float32)


class Detection(NamedTuple):
    points: np.ndarray | None  # (n, 2) float32, OpenCV's order; None if not found
    areas: np.ndarray | None  # dots: (n,) ink area of each dot in pixels (NaN: not measured)
    reason: str  # why it was not found ("" if found)
    ids: np.ndarray | None = None  # charuco: the corner id of each point (a view may see part of the board)


def blob_detector(shape: tuple[int, int], dark: bool):
    """A SimpleBlobDetector for dots from ~3 px to a quarter of the image across."""
    import cv2

    p = cv2.SimpleBlobDetector_Params()
    h, w = shape[:2]
    p.minDistBetweenBlobs = 2.0  # small dots of a steep view sit ~10 px apart (default 10 merges them)
    p.filterByArea = True
    p.minArea = 9.0
    p.maxArea = float((min(h, w) / 4.0) ** 2)
    p.filterByColor = True
    p.blobColor = 0 if dark else 255
    p.filterByCircularity = True
    p.minCircularity = 0.6  # dots seen at a slant are ellipses
    p.filterByConvexity = True
    p.minConvexity = 0.8
    p.filterByInertia = True
    p.minInertiaRatio = 0.1
    p.minThreshold, p.maxThreshold, p.thresholdStep = 10.0, 240.0, 10.0
    return cv2.SimpleBlobDetector_create(p)


def _dominant_size_class(keypoints, need: int) -> list:
    """Keypoints of the largest blob size that has at least `need` blobs within +-30 % of it."""
    if not keypoints:
        return []
    s = np.array([k.size for k in keypoints])
    members = np.array([(np.abs(np.log(s / x)) < np.log(1.3)).sum() for x in s])
    if not (members >= need).any():
        return list(keypoints)
    ref = s[members >= need].max()
    return [k for k in keypoints if abs(np.log(k.size / ref)) < np.log(2.0)]  # perspective: near dots look bigger


def refine_dots(gray: np.ndarray, points: np.ndarray, dark: bool) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel dot centres: the centroid of the dot's ink, each pixel weighted by its grey level
    scaled between the paper and the dot's core (anti-aliased edge pixels count by their coverage),
    over the dot's own region (its connected component at mid-grey, grown by 2 px) so that neither a
    neighbour nor the cut of a window biases it; a dot at the image border keeps the detector's centre.
    Returns the centres (n, 2) float32 and each dot's ink area in pixels (NaN where not measured)."""
    import cv2

    img = gray.astype(np.float64)
    if not dark:
        img = 255.0 - img
    pts = np.asarray(points, np.float64).copy()
    areas = np.full(len(pts), np.nan)
    if len(pts) < 2:
        return pts.astype(np.float32), areas
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(d, np.inf)
    H, W = img.shape
    grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    for k in range(len(pts)):
        r = d[k].min()  # the region search reaches to the nearest neighbour's centre
        x0, x1 = int(np.floor(pts[k, 0] - r)), int(np.ceil(pts[k, 0] + r)) + 1
        y0, y1 = int(np.floor(pts[k, 1] - r)), int(np.ceil(pts[k, 1] + r)) + 1
        if x0 < 0 or y0 < 0 or x1 > W or y1 > H:
            continue
        patch = img[y0:y1, x0:x1]
        cx, cy = int(round(pts[k, 0])) - x0, int(round(pts[k, 1])) - y0
        bg, core = np.percentile(patch, 90), patch[max(cy - 1, 0):cy + 2, max(cx - 1, 0):cx + 2].min()
        if bg - core < 10:
            continue
        ink = (patch < 0.5 * (bg + core)).astype(np.uint8)
        _, labels = cv2.connectedComponents(ink, connectivity=8)
        if labels[cy, cx] == 0:
            continue
        region = cv2.dilate((labels == labels[cy, cx]).astype(np.uint8), grow).astype(bool)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        # the paper's brightness as a plane over the window (light falls off across a target):
        # dividing by it keeps a slope of the light from pulling the centroid sideways
        paper = ~cv2.dilate(ink, grow).astype(bool)
        level = np.full(patch.shape, bg)
        if paper.sum() >= 12:
            A = np.column_stack([np.ones(paper.sum()), xx[paper] - pts[k, 0], yy[paper] - pts[k, 1]])
            coef = np.linalg.lstsq(A, patch[paper], rcond=None)[0]
            level = coef[0] + coef[1] * (xx - pts[k, 0]) + coef[2] * (yy - pts[k, 1])
            if np.any(level <= core):
                level = np.full(patch.shape, bg)
        ratio = patch / level
        core_ratio = min(ratio[max(cy - 1, 0):cy + 2, max(cx - 1, 0):cx + 2].min(), 0.95)
        w = np.clip((1.0 - ratio) / (1.0 - core_ratio), 0.0, 1.0) * region
        if w.sum() > 0:
            pts[k] = (np.sum(w * xx) / w.sum(), np.sum(w * yy) / w.sum())
            areas[k] = w.sum()
    return pts.astype(np.float32), areas


def _canvas(shape, keypoints) -> np.ndarray:
    """The given blobs alone, black on white (findCirclesGrid takes an image, not points)."""
    import cv2

    canvas = np.full(shape[:2], 255, np.uint8)
    for k in keypoints:
        cv2.circle(canvas, (int(round(k.pt[0] * 16)), int(round(k.pt[1] * 16))),
                   max(1, int(round(k.size * 8))), 0, -1, lineType=cv2.LINE_AA, shift=4)
    return canvas


def _find_circles(gray: np.ndarray, target: Target) -> Detection:
    """Try the photo itself, then a canvas of the dominant dot size only (specks and text beside
    the target confuse the grid search); snap the grid to the measured blob centres and refine."""
    import cv2

    base = cv2.CALIB_CB_SYMMETRIC_GRID if target.pattern == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
    counts = []
    for dark in (True, False):
        detector = blob_detector(gray.shape, dark)
        kps = detector.detect(gray)
        dominant = _dominant_size_class(kps, target.n_points)
        counts.append(len(dominant))
        if len(kps) < target.n_points:
            continue
        attempts = [(gray, detector)]
        if len(dominant) >= target.n_points and len(dominant) < len(kps):
            attempts.append((_canvas(gray.shape, dominant), blob_detector(gray.shape, dark=True)))
        pts = np.array([k.pt for k in kps])
        for image, det in attempts:
            for flags in (base, base | cv2.CALIB_CB_CLUSTERING):
                found, centres = cv2.findCirclesGrid(image, target.size, flags=flags, blobDetector=det)
                if found:
                    c = centres.reshape(-1, 2)
                    nearest = np.linalg.norm(c[:, None, :] - pts[None], axis=2).argmin(axis=1)
                    return Detection(*refine_dots(gray, pts[nearest], dark), "")
    best = max(counts)
    if best < target.n_points:
        return Detection(None, None, f"{best} dots of one size found, the {target.cols}x{target.rows} grid has "
                         f"{target.n_points}")
    return Detection(None, None, f"{best} dots found but no {target.cols}x{target.rows} {target.pattern} grid "
                     "among them")


def _find_chessboard(gray: np.ndarray, target: Target) -> Detection:
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, target.size, flags=flags)
    if not found:
        found, corners = cv2.findChessboardCornersSB(gray, target.size)
        if not found:
            return Detection(None, None, f"no {target.cols}x{target.rows} inner chessboard corners found")
        return Detection(corners.reshape(-1, 2).astype(np.float32), None, "")
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria)
    return Detection(corners.reshape(-1, 2).astype(np.float32), None, "")


def _find_charuco(gray: np.ndarray, target: Target) -> Detection:
    """ArUco markers, then the chessboard corners between them (sub-pixel), by OpenCV's
    CharucoDetector; part of the board may be hidden or outside the photo."""
    import cv2

    corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(target.board()).detectBoard(gray)
    n = 0 if ids is None else len(ids)
    if n < MIN_CHARUCO_CORNERS:
        markers = 0 if marker_ids is None else len(marker_ids)
        return Detection(None, None, f"{markers} ArUco markers and {n} ChArUco corners found, need "
                         f"{MIN_CHARUCO_CORNERS} corners ({target.dictionary}, {target.cols}x{target.rows} squares?)")
    order = np.argsort(ids.ravel())
    pts = corners.reshape(-1, 2)[order].astype(np.float32)
    ids = ids.ravel()[order].astype(np.int64)
    # OpenCV interpolates the corners from the markers and refines them in a fixed window; refine
    # again in a window scaled to this photo's squares (measured on synthetic views with distortion:
    # 0.24 px RMS, 0.8 px max from OpenCV alone -> 0.07 / 0.2 px)
    obj = target.object_points()[ids, :2]
    H, _ = cv2.findHomography(obj, pts)
    if H is not None:
        unit = cv2.perspectiveTransform(np.array([[[0, 0]], [[target.spacing, 0]], [[0, target.spacing]]],
                                                 np.float32) + obj[:1, None, :], H).reshape(-1, 2)
        square = min(np.linalg.norm(unit[1] - unit[0]), np.linalg.norm(unit[2] - unit[0]))
        gap = 0.5 * (target.spacing - target.marker) / target.spacing * square  # corner to marker, px
        win = int(np.clip(0.75 * gap, 2, 15))  # the window must not reach the markers' edges
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        pts = cv2.cornerSubPix(gray, pts.reshape(-1, 1, 2), (win, win), (-1, -1), criteria).reshape(-1, 2)
    return Detection(pts.astype(np.float32), None, "", ids)


def find_target(gray: np.ndarray, target: Target) -> Detection:
    """The target in an 8-bit grey image: its (cols * rows, 2) float32 image points (None if not
    found, with the reason), and for dots each dot's ink area in pixels."""
    gray = np.ascontiguousarray(gray)
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"detect needs an 8-bit grey image, got {gray.dtype} {gray.shape}")
    if target.pattern == "chessboard":
        return _find_chessboard(gray, target)
    if target.pattern == "charuco":
        return _find_charuco(gray, target)
    return _find_circles(gray, target)


def detect(gray: np.ndarray, target: Target) -> np.ndarray | None:
    """(cols * rows, 2) float32 image points of the target in an 8-bit grey image, or None."""
    return find_target(gray, target).points


@dataclass
class Calibration:
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    rms: float
    per_view_rms: np.ndarray  # (V,) over the used views
    used: list[int]  # indices into the views given
    rejected: dict  # index -> reason
    image_size: tuple[int, int]  # (width, height)
    std: np.ndarray  # (9,) 1-sigma of fx fy cx cy k1 k2 p1 p2 k3 (OpenCV's estimate; 0 = fixed)
    projected: list[np.ndarray]  # per used view, the model's image points (for overlays)
    dot_radius: float | None = None  # dots: the radius estimated from their ink areas (target units)
    dot_bias_px: float | None = None  # dots: RMS of the centroid-vs-centre correction applied, pixels


def _calibrate_once(obj, img, image_size, flags):
    import cv2

    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms, K, dist, rvecs, tvecs, std, _, _ = cv2.calibrateCameraExtended(
        obj, img, image_size, np.eye(3), np.zeros(5), flags=flags, criteria=criteria)
    per_view, projected = [], []
    for o, i, r, t in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        proj = proj.reshape(-1, 2)
        projected.append(proj)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj - i.reshape(-1, 2)) ** 2, axis=1)))))
    return float(rms), K, dist.ravel()[:5], np.array(per_view), np.asarray(std).ravel()[:9], projected, \
        [(np.ravel(r), np.ravel(t)) for r, t in zip(rvecs, tvecs)]


def _disc_images(target: Target, radius: float, K, dist, rvec, tvec, n: int = 48):
    """For each dot of the target as a disc of `radius`: the area and centroid of its image (the
    projected, distorted outline as a polygon) and the image of its centre."""
    import cv2

    obj = target.object_points().astype(np.float64)
    a = 2 * np.pi * np.arange(n) / n
    ring = np.stack([np.cos(a), np.sin(a), np.zeros(n)], axis=1) * radius
    outline = (obj[:, None, :] + ring[None]).reshape(-1, 3)
    poly = cv2.projectPoints(outline, rvec, tvec, K, dist)[0].reshape(len(obj), n, 2)
    centre = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
    x, y = poly[..., 0] - centre[:, None, 0], poly[..., 1] - centre[:, None, 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum(axis=1)
    cx = ((x + xn) * cross).sum(axis=1) / (6 * area)
    cy = ((y + yn) * cross).sum(axis=1) / (6 * area)
    return np.abs(area), centre + np.column_stack([cx, cy]), centre


def _dot_bias(target, areas, K, dist, poses):
    """The offset of each measured dot centroid from the image of the dot's centre (perspective and
    lens distortion move the centroid of an ellipse off the projected centre by up to ~0.1 px at
    steep views), for a dot radius estimated from the measured ink areas (area ~ radius^2)."""
    spacing = target.spacing * (np.sqrt(2.0) if target.pattern == "acircles" else 1.0)
    r0 = 0.25 * spacing
    ratios = []
    for (rvec, tvec), a in zip(poses, areas):
        area0, _, _ = _disc_images(target, r0, K, dist, rvec, tvec)
        ratios.append(a / area0)
    ratio = np.concatenate(ratios)
    ratio = ratio[np.isfinite(ratio)]
    if len(ratio) == 0:
        return None, None
    radius = float(r0 * np.sqrt(np.median(ratio)))
    if not 0 < radius < 0.5 * spacing:
        return None, None
    bias = []
    for rvec, tvec in poses:
        _, centroid, centre = _disc_images(target, radius, K, dist, rvec, tvec)
        bias.append((centroid - centre).astype(np.float32))
    return radius, bias


def calibrate(image_points: list[np.ndarray], target: Target, image_size: tuple[int, int],
              fix_k3: bool = False, zero_tangent: bool = False, fix_aspect: bool = False,
              outlier_factor: float = 5.0, min_px: float = 2.0, min_views: int = 3,
              dot_areas: list[np.ndarray] | None = None, ids: list[np.ndarray] | None = None) -> Calibration:
    """cv2.calibrateCamera over the views, dropping views whose RMS is an outlier and redoing it.

    A view is an outlier when its RMS exceeds `outlier_factor` x the median view RMS and `min_px`
    (a misdetected or misordered grid is off by many pixels; a steep, well detected view may be
    at a few times the median and carries the most information on distortion: OpenCV's left02
    is at 6x the median, 1.2 px, and dropping it moves cy by 0.8 %). The worst view goes first;
    rejection repeats until no view is dropped, never below `min_views` views.

    With `dot_areas` (dot targets: each dot's ink area from find_target), the measured centroids are
    then corrected for the offset of a projected disc's centroid from its projected centre, and the
    camera is calibrated again (three rounds; the radius comes from the areas).
    `ids` (charuco): the corner ids of each view's points (views may see different parts).
    """
    import cv2

    if len(image_points) < min_views:
        raise ValueError(f"calibration needs at least {min_views} views with the target, got {len(image_points)}")
    flags = ((cv2.CALIB_FIX_K3 if fix_k3 else 0) | (cv2.CALIB_ZERO_TANGENT_DIST if zero_tangent else 0)
             | (cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect else 0))
    obj = target.object_points()
    view_obj = [obj[np.asarray(v)] for v in ids] if ids is not None else [obj] * len(image_points)
    used = list(range(len(image_points)))
    rejected: dict[int, str] = {}
    while True:
        rms, K, dist, per_view, std, projected, poses = _calibrate_once(
            [view_obj[i] for i in used], [image_points[i] for i in used], image_size, flags)
        limit = max(outlier_factor * float(np.median(per_view)), min_px)
        worst = int(np.argmax(per_view))
        if per_view[worst] <= limit or len(used) <= min_views:
            break
        rejected[used[worst]] = (f"reprojection RMS {per_view[worst]:.2f} px > {limit:.2f} px "
                                 f"({outlier_factor:g} x the median view)")
        used.pop(worst)
    radius = bias_rms = None
    if dot_areas is not None and target.pattern in ("circles", "acircles"):
        measured = [np.asarray(image_points[i], np.float32) for i in used]
        for _ in range(3):
            radius, bias = _dot_bias(target, [dot_areas[i] for i in used], K, dist, poses)
            if bias is None:
                break
            corrected = [m - b for m, b in zip(measured, bias)]
            rms, K, dist, per_view, std, projected, poses = _calibrate_once(
                [view_obj[i] for i in used], corrected, image_size, flags)
            bias_rms = float(np.sqrt(np.mean(np.concatenate(bias) ** 2) * 2))
    return Calibration(K, dist, rms, per_view, list(used), rejected, image_size, std, projected, radius, bias_rms)


def render_target(target: Target, K: np.ndarray, dist: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
                  size: tuple[int, int], dot_radius: float | None = None, supersample: int = 4,
                  noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """A synthetic 8-bit grey photo of a dot target (circles / acircles) or a ChArUco board seen by
    camera (K, dist) at pose (rvec, tvec) (target -> camera): the target printed on white paper
    under a soft light gradient, each pixel the mean of supersample^2 sub-pixel rays
    (anti-aliasing), plus Gaussian noise (`noise` in 8-bit levels). For tests and sample data: the
    true points are cv2.projectPoints(target.object_points(), ...).
    """
    import cv2
    from scipy import ndimage
    from scipy.spatial import cKDTree

    if target.pattern not in ("circles", "acircles", "charuco"):
        raise ValueError("render_target draws dot targets (circles, acircles) and ChArUco boards")
    w, h = size
    obj = target.object_points().astype(np.float64)
    if target.pattern == "charuco":
        ppu = 40.0 / target.spacing  # texture: 40 pixels per square
        tex = target.board().generateImage((int(round(target.cols * 40)), int(round(target.rows * 40))),
                                           marginSize=0, borderBits=1).astype(np.float64) / 255.0
        margin = np.array([0.0, 0.0, target.cols * target.spacing, target.rows * target.spacing]) + \
            np.array([-1, -1, 1, 1]) * 0.5 * target.spacing
    else:
        if dot_radius is None:
            nn = target.spacing * (np.sqrt(2.0) if target.pattern == "acircles" else 1.0)
            dot_radius = 0.3 * nn
        tree = cKDTree(obj[:, :2])
        margin = np.array([obj[:, 0].min(), obj[:, 1].min(), obj[:, 0].max(), obj[:, 1].max()]) + \
            np.array([-1, -1, 1, 1]) * 2.5 * dot_radius
    k = supersample
    off = (np.arange(k) + 0.5) / k - 0.5
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
    t = np.asarray(tvec, np.float64).reshape(3)
    acc = np.zeros((h, w))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    for dy in off:
        for dx in off:
            pix = np.stack([uu + dx, vv + dy], axis=-1).reshape(-1, 1, 2)
            xy = cv2.undistortPoints(pix, K, dist, R=np.eye(3), P=np.eye(3), criteria=criteria).reshape(-1, 2)
            ray = np.column_stack([xy, np.ones(len(xy))]) @ R  # direction in target frame (R^T d)
            origin = -R.T @ t
            with np.errstate(divide="ignore", invalid="ignore"):
                s = -origin[2] / ray[:, 2]
            p = origin[None, :2] + s[:, None] * ray[:, :2]
            hit = (s > 0) & np.isfinite(s)
            p = np.where(hit[:, None], p, 1e9)
            on_paper = hit & (p[:, 0] > margin[0]) & (p[:, 1] > margin[1]) & (p[:, 0] < margin[2]) & \
                (p[:, 1] < margin[3])
            if target.pattern == "charuco":
                # texel (i, j) covers [j, j+1) x [i, i+1) / ppu on the board: nearest texel (sharp print)
                ink = ndimage.map_coordinates(tex, [p[:, 1] * ppu - 0.5, p[:, 0] * ppu - 0.5], order=0, mode="nearest",
                                              cval=1.0) < 0.5
                inside = (p[:, 0] >= 0) & (p[:, 1] >= 0) & (p[:, 0] < target.cols * target.spacing) & \
                    (p[:, 1] < target.rows * target.spacing)
                ink &= inside & on_paper
            else:
                d, _ = tree.query(p, distance_upper_bound=4 * dot_radius)
                ink = hit & (d <= dot_radius)
            value = np.where(ink, 0.06, np.where(on_paper, 0.92, 0.45))
            acc += value.reshape(h, w)
    img = acc / k**2
    shade = 0.85 + 0.15 * (uu / max(w - 1, 1))  # light falls off across the image
    img = 255.0 * img * shade
    if noise > 0:
        img = img + np.random.default_rng(seed).normal(scale=noise, size=img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)
