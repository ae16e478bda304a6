"""Wavelight scene folders from the real photos of DiLiGenT's shiny ball (tests/data/photometric).

The data set gives, per photo, the direction toward its LED and the LED's RGB intensity, plus one
mask of the ball. `build_ball_scene` makes the scene folder a user would make from only the photo,
the mask and the knowledge that the object is a ball seen through a long lens:

- `image.png`: the photo as it is (16-bit, linear), with `linear_input = true` in scene.toml's
  [solve] and [compare] (`image_format="exr"` writes the same values, code / 65535, as a float EXR
  instead: the commands without `--linear-input`, e.g. relight, insert and report, would sRGB-decode
  the PNG);
- `mask.png`: the data set's mask, unchanged;
- `mesh.ply`: an icosphere fitted to the mask's outline (least-squares circle through the midpoints
  of the cracks between mask and background pixels), with exact vertex normals (the unit radial
  directions), binary, float64; no ground plane;
- `camera.json`, `pose.json`: a pinhole camera with a long focal length (`focal_px`) far away
  (`distance` from the ball's centre), principal point at the image centre, no distortion.

World frame = the data set's camera frame: x right, y up, z toward the camera, so that the LED
directions (all with z > 0) are in wavelight's upper hemisphere. The camera sits on the +Z axis at
(0, 0, distance) and looks along -Z. OpenCV's camera axes (x right, y down, z forward) are then
x_cam = X, y_cam = -Y, z_cam = -(Z - distance): R = diag(1, -1, -1), t = (0, 0, distance). The
ball's centre is put in the plane Z = 0, on the ray through the fitted circle's centre, and its
radius makes the limb's cone (half-angle atan(rho / f) for an image radius rho) touch the mask's
circle: radius = D rho / sqrt(f^2 + rho^2), D the camera-to-centre distance.

Nothing here reads /work/shared: the data were copied into tests/data/photometric (see
tests/data/README.md for the attribution and licence caveat).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DATA = Path(__file__).parent / "data" / "photometric" / "diligent_ball_dev"
FOCAL_PX = 50_000.0  # long lens: the ball (radius ~71 px) spans 0.16 degrees
DISTANCE = 1_000.0  # camera to ball centre, world units: radius ~1.42 units
SUBDIVISIONS = 5  # icosphere level: 20,480 faces, edges ~2.0 degrees of arc


@dataclass(frozen=True)
class Circle:
    """A circle in pixel coordinates (u = column, v = row; pixel (0, 0)'s centre at (0, 0))."""

    u: float
    v: float
    radius: float
    rms: float  # RMS distance of the outline points from the circle, px
    n_points: int


@dataclass(frozen=True)
class BallView:
    """The fitted ball and the camera that sees it as the photos do."""

    circle: Circle
    centre: np.ndarray  # (3,) world
    radius: float  # world units
    focal_px: float
    distance: float
    width: int
    height: int

    @property
    def R(self) -> np.ndarray:
        return np.diag([1.0, -1.0, -1.0])

    @property
    def t(self) -> np.ndarray:
        return np.array([0.0, 0.0, self.distance])

    @property
    def camera_json(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.focal_px, "fy": self.focal_px,
                "cx": (self.width - 1) / 2.0, "cy": (self.height - 1) / 2.0, "dist": [0.0] * 5}

    @property
    def pose_json(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist()}


# --- the data set ---------------------------------------------------------------------------------

def filenames() -> list[str]:
    return (DATA / "filenames.txt").read_text().split()


def light_directions() -> np.ndarray:
    """(16, 3) unit vectors toward each photo's LED, in the world (= data set camera) frame."""
    d = np.loadtxt(DATA / "light_directions.txt", dtype=np.float64).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)  # given to 4 decimals: |d| = 1 +- 1e-4


def light_intensities() -> np.ndarray:
    """(16, 3) RGB intensity of each photo's LED."""
    return np.loadtxt(DATA / "light_intensities.txt", dtype=np.float64).reshape(-1, 3)


def read_mask() -> np.ndarray:
    """(H, W) bool, the ball's pixels."""
    from pipelines.io import images

    return images.read_mask(DATA / "mask.png")


def read_photo(index: int) -> np.ndarray:
    """(H, W, 3) float64 linear RGB of photo `index` (code / 65535; 1.0 = clipped)."""
    from pipelines.io import images

    return images.read_image(DATA / "images" / filenames()[index], linear=True).pixels.astype(np.float64)


def normal_gt() -> np.ndarray:
    """(H, W, 3) the data set's true unit normals (x right, y up, z toward the camera), 0 off the ball."""
    from scipy.io import loadmat

    return np.asarray(loadmat(DATA / "Normal_gt.mat")["Normal_gt"], dtype=np.float64)


# --- fitting the ball -----------------------------------------------------------------------------

def outline_points(mask: np.ndarray) -> np.ndarray:
    """(n, 2) (u, v) midpoints of the cracks between 4-neighbouring mask and background pixels:
    the outline at sub-pixel positions, without the half-pixel inward bias of boundary pixel centres."""
    horizontal = mask[:, 1:] != mask[:, :-1]  # between columns c and c + 1
    vertical = mask[1:, :] != mask[:-1, :]  # between rows r and r + 1
    r, c = np.nonzero(horizontal)
    a = np.column_stack([c + 0.5, r])
    r, c = np.nonzero(vertical)
    b = np.column_stack([c, r + 0.5])
    return np.concatenate([a, b]).astype(np.float64)


def fit_circle(points: np.ndarray, iterations: int = 20) -> Circle:
    """Least-squares circle: the algebraic (Kasa) fit, refined by Gauss-Newton on the geometric
    distances |p - c| - r."""
    p = np.asarray(points, dtype=np.float64)
    A = np.column_stack([2.0 * p[:, 0], 2.0 * p[:, 1], np.ones(len(p))])
    x = np.linalg.lstsq(A, (p**2).sum(axis=1), rcond=None)[0]
    u, v, r = x[0], x[1], np.sqrt(x[2] + x[0] ** 2 + x[1] ** 2)
    for _ in range(iterations):
        dx, dy = p[:, 0] - u, p[:, 1] - v
        dist = np.hypot(dx, dy)
        res = dist - r
        J = np.column_stack([-dx / dist, -dy / dist, -np.ones(len(p))])
        step = np.linalg.lstsq(J, -res, rcond=None)[0]
        u, v, r = u + step[0], v + step[1], r + step[2]
        if np.abs(step).max() < 1e-12:
            break
    res = np.hypot(p[:, 0] - u, p[:, 1] - v) - r
    return Circle(float(u), float(v), float(r), float(np.sqrt(np.mean(res**2))), len(p))


def ball_view(mask: np.ndarray | None = None, focal_px: float = FOCAL_PX, distance: float = DISTANCE) -> BallView:
    """The ball (centre, radius in world units) and camera matching the mask's circle."""
    mask = read_mask() if mask is None else mask
    circle = fit_circle(outline_points(mask))
    H, W = mask.shape
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
    a = np.array([(circle.u - cx) / focal_px, (circle.v - cy) / focal_px, 1.0])  # camera ray to the centre
    x_cam = distance * a  # depth `distance`: world Z = 0
    R, t = np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, distance])
    centre = R.T @ (x_cam - t)
    D = float(np.linalg.norm(x_cam))
    radius = D * circle.radius / np.hypot(focal_px, circle.radius)
    return BallView(circle, centre, float(radius), float(focal_px), float(distance), W, H)


# --- the mesh ---------------------------------------------------------------------------------------

def icosphere(subdivisions: int = SUBDIVISIONS) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: (V, 3) vertices on the sphere, (20 * 4^s, 3) faces, counter-clockwise seen from
    outside (outward face normals). Each level splits every triangle into four at its edge midpoints,
    pushed onto the sphere."""
    g = (1.0 + 5.0**0.5) / 2.0
    v = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
                  [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # (3F, 2): edge k of face i at k*F+i
        unique, inverse = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
        mid = v[unique[:, 0]] + v[unique[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = (len(v) + inverse.reshape(3, -1)).T  # (F, 3): midpoints of edges 01, 12, 20
        v = np.concatenate([v, mid])
        f = np.concatenate([np.column_stack([f[:, 0], m[:, 0], m[:, 2]]),
                            np.column_stack([f[:, 1], m[:, 1], m[:, 0]]),
                            np.column_stack([f[:, 2], m[:, 2], m[:, 1]]),
                            m])
    return v, f


def write_ply(path: Path, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY: float64 positions and normals, int32 triangles."""
    vdt = np.dtype([(k, "<f8") for k in ("x", "y", "z", "nx", "ny", "nz")])
    vrec = np.empty(len(vertices), dtype=vdt)
    for k, name in enumerate("xyz"):
        vrec[name] = vertices[:, k]
        vrec["n" + name] = normals[:, k]
    frec = np.empty(len(faces), dtype=np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    frec["n"] = 3
    frec["i"] = faces
    header = ("ply\nformat binary_little_endian 1.0\n"
              "comment icosphere fitted to the DiLiGenT ball mask (tests/photometric.py)\n"
              f"element vertex {len(vertices)}\n"
              + "".join(f"property double {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz"))
              + f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())


def sphere_mesh(centre: np.ndarray, radius: float, subdivisions: int = SUBDIVISIONS):
    """(vertices, exact unit normals, faces) of an icosphere of `radius` around `centre`."""
    unit, faces = icosphere(subdivisions)
    return np.asarray(centre, np.float64) + radius * unit, unit, faces


# --- the scene folder -------------------------------------------------------------------------------

def build_ball_scene(dst: str | Path, index: int, *, focal_px: float = FOCAL_PX, distance: float = DISTANCE,
                     subdivisions: int = SUBDIVISIONS, image_format: str = "png",
                     view: BallView | None = None) -> tuple[Path, np.ndarray, np.ndarray]:
    """Make the scene folder `dst` for photo `index` (0..15, the order of filenames.txt).

    Returns (scene path, unit direction toward the LED in the world frame, the LED's RGB intensity).
    `view` reuses a `ball_view` (the fit depends only on the mask, focal_px and distance).
    """
    names = filenames()
    if not 0 <= index < len(names):
        raise IndexError(f"photo index {index} outside 0..{len(names) - 1}")
    if image_format not in ("png", "exr"):
        raise ValueError(f"image_format must be 'png' or 'exr', got {image_format!r}")
    dst = Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    view = ball_view(focal_px=focal_px, distance=distance) if view is None else view
    if image_format == "png":
        shutil.copyfile(DATA / "images" / names[index], dst / "image.png")
        (dst / "scene.toml").write_text("# the 16-bit PNG holds linear values (DiLiGenT: no gamma)\n"
                                        "[solve]\nlinear_input = true\n[compare]\nlinear_input = true\n")
    else:
        from pipelines.io import images

        images.write_exr(dst / "image.exr", read_photo(index).astype(np.float32))
    shutil.copyfile(DATA / "mask.png", dst / "mask.png")
    vertices, normals, faces = sphere_mesh(view.centre, view.radius, subdivisions)
    write_ply(dst / "mesh.ply", vertices, normals, faces)
    (dst / "camera.json").write_text(json.dumps(view.camera_json, indent=2) + "\n")
    (dst / "pose.json").write_text(json.dumps(view.pose_json, indent=2) + "\n")
    (dst / "truth.json").write_text(json.dumps({
        "photo": names[index], "light_direction": light_directions()[index].tolist(),
        "light_intensity": light_intensities()[index].tolist(),
        "ball": {"centre": view.centre.tolist(), "radius": view.radius, "circle_px": [view.circle.u, view.circle.v,
                                                                                     view.circle.radius]},
        "frame": "world = DiLiGenT camera frame: x right, y up, z toward the camera"}, indent=2) + "\n")
    return dst, light_directions()[index].copy(), light_intensities()[index].copy()


# --- checks ---------------------------------------------------------------------------------------

def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between (..., 3) vectors, degrees (robust near 0 and 180)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))


LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance of linear RGB


def region_centroid(radiance: np.ndarray, directions: np.ndarray, solid_angles: np.ndarray,
                    threshold: float = 0.5, radius_deg: float = 30.0) -> np.ndarray:
    """Power-weighted mean direction of a light's brightest region: the samples (texels or lat-long
    pixels: (n, 3) radiance, unit directions, solid angles) with luminance >= threshold x the peak's
    and within radius_deg of the peak's direction."""
    lum = radiance @ LUMA
    peak = int(np.argmax(lum))
    near = angle_deg(directions, directions[peak][None]) <= radius_deg
    sel = near & (lum >= threshold * lum[peak])
    v = ((lum * solid_angles)[sel, None] * directions[sel]).sum(axis=0)
    return v / np.linalg.norm(v)


def power_direction(radiance: np.ndarray, directions: np.ndarray, solid_angles: np.ndarray) -> np.ndarray:
    """Direction of a light's whole power vector (sum of luminance x solid angle x direction)."""
    v = ((radiance @ LUMA) * solid_angles)[:, None] * directions
    v = v.sum(axis=0)
    return v / np.linalg.norm(v)


def scene_samples(scene: Path, edge_margin: int = 1):
    """wavelight's used pixels of a built scene (`pipelines.camera.pixel_samples`) and diagnostics."""
    from pipelines.geometry import camera as cam
    from pipelines.io import images
    from pipelines.geometry import raycast
    from pipelines.io import scene_files as sc

    camera = sc.read_camera(scene / "camera.json")
    pose = sc.read_pose(scene / "pose.json")
    mesh = sc.load_mesh(scene / "mesh.ply")
    backend = raycast.make_backend(mesh)
    return cam.pixel_samples(camera, pose, mesh, backend, images.read_mask(scene / "mask.png"),
                             edge_margin=edge_margin)
