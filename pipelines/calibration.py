"""Camera intrinsics from photos of a calibration target (OpenCV), as pure functions over images.

Targets (OpenCV's conventions, points ordered row by row as OpenCV returns them):
  chessboard  cols x rows inner corners, `spacing` = square size
  circles     symmetric grid of cols x rows dots, `spacing` = centre distance
  acircles    asymmetric grid, OpenCV's pattern size (cols, rows) = (dots per row, rows); dot
              (i, j) sits at ((2j + i mod 2) s, i s): `spacing` s is HALF the centre distance of
              two neighbouring dots in a row (OpenCV's sample convention)

Dot detection: OpenCV's default blob detector keeps only dark blobs up to ~80 px across (its
maxArea is 5000 px^2). Here the area range scales with the image, dark and light dots are both
tried, and blobs are kept only in the largest size class that has enough members for the grid
(specks of dust or text next to the target are a different size), so findCirclesGrid sees only
candidate dots. Chessboard corners are refined to sub-pixel by cornerSubPix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PATTERNS = ("chessboard", "circles", "acircles")


@dataclass(frozen=True)
class Target:
    pattern: str
    cols: int
    rows: int
    spacing: float  # in the units the camera's translations will be in (e.g. metres)

    def __post_init__(self):
        if self.pattern not in PATTERNS:
            raise ValueError(f"unknown pattern {self.pattern!r}; use one of {', '.join(PATTERNS)}")
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"a {self.pattern} needs at least 2 x 2 points, got {self.cols} x {self.rows}")
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise ValueError(f"the spacing must be a positive number, got {self.spacing}")

    @property
    def size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    @property
    def n_points(self) -> int:
        return self.cols * self.rows

    def object_points(self) -> np.ndarray:
        """(cols * rows, 3) float32 target coordinates (z = 0) in detection order."""
        i, j = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        x = (2 * j + i % 2) if self.pattern == "acircles" else j
        pts = np.stack([x.ravel(), i.ravel(), np.zeros(self.n_points)], axis=1) * self.spacing
        return pts.astype(np.float32)


def blob_detector(shape: tuple[int, int], dark: bool):
    """A SimpleBlobDetector for dots from ~3 px to a quarter of the image across."""
    import cv2

    p = cv2.SimpleBlobDetector_Params()
    h, w = shape[:2]
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
    return [k for k in keypoints if abs(np.log(k.size / ref)) < np.log(1.5)]


def _find_circles(gray: np.ndarray, target: Target) -> np.ndarray | None:
    import cv2

    base = cv2.CALIB_CB_SYMMETRIC_GRID if target.pattern == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
    for dark in (True, False):
        kps = _dominant_size_class(blob_detector(gray.shape, dark).detect(gray), target.n_points)
        if len(kps) < target.n_points:
            continue
        # findCirclesGrid takes an image, not points: draw the kept blobs alone, black on white
        canvas = np.full(gray.shape[:2], 255, np.uint8)
        for k in kps:
            cv2.circle(canvas, (int(round(k.pt[0] * 16)), int(round(k.pt[1] * 16))),
                       max(1, int(round(k.size * 8))), 0, -1, lineType=cv2.LINE_AA, shift=4)
        detector = blob_detector(gray.shape, dark=True)
        for flags in (base, base | cv2.CALIB_CB_CLUSTERING):
            found, centres = cv2.findCirclesGrid(canvas, target.size, flags=flags, blobDetector=detector)
            if found:
                pts = np.array([k.pt for k in kps])
                c = centres.reshape(-1, 2)
                nearest = np.linalg.norm(c[:, None, :] - pts[None], axis=2).argmin(axis=1)
                return pts[nearest].astype(np.float32)  # the blob centres measured on the photo
    return None


def _find_chessboard(gray: np.ndarray, target: Target) -> np.ndarray | None:
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, target.size, flags=flags)
    if not found:
        found, corners = cv2.findChessboardCornersSB(gray, target.size)
        return corners.reshape(-1, 2).astype(np.float32) if found else None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(np.float32)


def detect(gray: np.ndarray, target: Target) -> np.ndarray | None:
    """(cols * rows, 2) float32 image points of the target in an 8-bit grey image, or None."""
    gray = np.ascontiguousarray(gray)
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"detect needs an 8-bit grey image, got {gray.dtype} {gray.shape}")
    if target.pattern == "chessboard":
        return _find_chessboard(gray, target)
    return _find_circles(gray, target)


@dataclass
class Calibration:
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    rms: float
    per_view_rms: np.ndarray  # (V,) over the used views
    used: list[int]  # indices into the views given
    rejected: dict  # index -> reason
    image_size: tuple[int, int]  # (width, height)


def _calibrate_once(obj, img, image_size, flags):
    import cv2

    K0 = np.eye(3)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, image_size, K0, np.zeros(5), flags=flags)
    per_view = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - i.reshape(-1, 2)) ** 2, axis=1)))))
    return float(rms), K, dist.ravel()[:5], np.array(per_view)


def calibrate(image_points: list[np.ndarray], target: Target, image_size: tuple[int, int],
              fix_k3: bool = False, zero_tangent: bool = False, fix_aspect: bool = False,
              outlier_factor: float = 5.0, min_px: float = 2.0, min_views: int = 3) -> Calibration:
    """cv2.calibrateCamera over the views, dropping views whose RMS is an outlier and redoing it.

    A view is an outlier when its RMS exceeds `outlier_factor` x the median view RMS and `min_px`
    (a misdetected or misordered grid is off by many pixels; a steep, well detected view may be
    at a few times the median and carries the most information on distortion: OpenCV's left02
    is at 6x the median, 1.2 px, and dropping it moves cy by 0.8 %). The worst view goes first;
    rejection repeats until no view is dropped, never below `min_views` views.
    """
    import cv2

    if len(image_points) < min_views:
        raise ValueError(f"calibration needs at least {min_views} views with the target, got {len(image_points)}")
    flags = ((cv2.CALIB_FIX_K3 if fix_k3 else 0) | (cv2.CALIB_ZERO_TANGENT_DIST if zero_tangent else 0)
             | (cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect else 0))
    obj = target.object_points()
    used = list(range(len(image_points)))
    rejected: dict[int, str] = {}
    while True:
        rms, K, dist, per_view = _calibrate_once([obj] * len(used), [image_points[i] for i in used],
                                                 image_size, flags)
        limit = max(outlier_factor * float(np.median(per_view)), min_px)
        worst = int(np.argmax(per_view))
        if per_view[worst] <= limit or len(used) <= min_views:
            return Calibration(K, dist, rms, per_view, used, rejected, image_size)
        rejected[used[worst]] = (f"reprojection RMS {per_view[worst]:.2f} px > {limit:.2f} px "
                                 f"({outlier_factor:g} x the median view)")
        used.pop(worst)
