"""The light in other tools' conventions, each with the lookup that tool does, so that an export
can be checked by reading it back the way that tool reads it.

Our exchange format (DESIGN §2): lat-long, row 0 = zenith, theta = pi (r + 1/2) / H from +Z,
phi = 2 pi (c + 1/2) / W from +X towards +Y; world +Z up.

- Mitsuba 3 `envmap`: its local frame is +Y up; a direction v (local) reads the image at
  u = atan2(v.x, -v.z) / 2pi (wrapped to [0, 1)), v = acos(v.y) / pi (row 0 at the top). With the
  emitter's to_world = MITSUBA_TO_WORLD (local +Y -> world +Z, local -Z -> world +X) our image
  needs only its columns mirrored.
- Blender (Cycles/EEVEE world, Environment Texture, equirectangular): world +Z up;
  u = 0.5 - atan2(d.y, d.x) / 2pi, v = 0.5 + atan2(d.z, hypot(d.x, d.y)) / pi with v = 0 at the
  image's bottom row: our image with columns mirrored and turned by half a turn.
- OpenGL cube map faces (GL_TEXTURE_CUBE_MAP_POSITIVE_X ... NEGATIVE_Z; three.js CubeTexture
  takes the same six images in the order px, nx, py, ny, pz, nz): a Y-up world, here
  (x, y, z)_gl = (x, z, -y)_world; the major axis picks the face, and
  s = (sc / |ma| + 1) / 2 (column), t = (tc / |ma| + 1) / 2 (row, row 0 first in the file), with
  +X: sc = -z, tc = -y; -X: sc = z, tc = -y; +Y: sc = x, tc = z; -Y: sc = x, tc = -z;
  +Z: sc = x, tc = -y; -Z: sc = -x, tc = -y (the GL specification's table).
  Face pixels of size R coincide with our cube map's texels, so the export is exact.
"""

from __future__ import annotations

import numpy as np

from ..light.cubemap import CubeMap, face_rectangle_solid_angle

MITSUBA_TO_WORLD = np.array([[0.0, 0.0, -1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
GL_FACES = ("px", "nx", "py", "ny", "pz", "nz")


def _wrap01(u):
    return u - np.floor(u)


def _read(image: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    H, W = image.shape[:2]
    return image[np.clip(rows, 0, H - 1), np.clip(cols, 0, W - 1)]


# -- our own lat-long (the reference the exports are checked against) --------------------------------

def latlong_lookup(image: np.ndarray, directions: np.ndarray) -> np.ndarray:
    H, W = image.shape[:2]
    d = np.asarray(directions, np.float64)
    theta = np.arccos(np.clip(d[..., 2], -1, 1))
    phi = _wrap01(np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi))
    return _read(image, np.floor(theta / np.pi * H).astype(int), np.floor(phi * W).astype(int))


# -- Mitsuba 3 -------------------------------------------------------------------------------------------

def to_mitsuba(latlong: np.ndarray) -> np.ndarray:
    """The image for Mitsuba's envmap with to_world = MITSUBA_TO_WORLD."""
    return np.ascontiguousarray(np.asarray(latlong)[:, ::-1])


def mitsuba_lookup(image: np.ndarray, directions: np.ndarray, to_world: np.ndarray = MITSUBA_TO_WORLD) -> np.ndarray:
    """What Mitsuba's envmap reads for world directions (nearest pixel)."""
    H, W = image.shape[:2]
    local = np.asarray(directions, np.float64) @ to_world[:3, :3]  # R^T d for each row
    u = _wrap01(np.arctan2(local[..., 0], -local[..., 2]) / (2 * np.pi))
    v = np.arccos(np.clip(local[..., 1], -1, 1)) / np.pi
    return _read(image, np.floor(v * H).astype(int), np.floor(u * W).astype(int))


def mitsuba_xml(filename: str, scale: float = 1.0) -> str:
    m = " ".join(f"{x:g}" for x in MITSUBA_TO_WORLD.ravel())
    return (f'<emitter type="envmap">\n'
            f'    <!-- wavelight light (world +Z up); to_world puts the map\'s up (local +Y) on world +Z -->\n'
            f'    <string name="filename" value="{filename}"/>\n'
            f'    <float name="scale" value="{scale:g}"/>\n'
            f'    <transform name="to_world"><matrix value="{m}"/></transform>\n'
            f'</emitter>\n')


# -- Blender ------------------------------------------------------------------------------------------------

def to_blender(latlong: np.ndarray) -> np.ndarray:
    """The image for Blender's Environment Texture (equirectangular, world +Z up)."""
    img = np.asarray(latlong)
    W = img.shape[1]
    cols = (W // 2 - 1 - np.arange(W)) % W
    return np.ascontiguousarray(img[:, cols])


def blender_lookup(image: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """What Blender's equirectangular Environment Texture reads for world directions (nearest)."""
    H, W = image.shape[:2]
    d = np.asarray(directions, np.float64)
    u = _wrap01(0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi))
    v = 0.5 + np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1])) / np.pi
    row_from_bottom = np.floor(v * H).astype(int)
    return _read(image, H - 1 - row_from_bottom, np.floor(u * W).astype(int))


# -- OpenGL / three.js cube faces ----------------------------------------------------------------------------

def _world_to_gl(d):
    return np.stack([d[..., 0], d[..., 2], -d[..., 1]], axis=-1)


def _gl_to_world(g):
    return np.stack([g[..., 0], -g[..., 2], g[..., 1]], axis=-1)


def gl_face_directions(face: str, size: int) -> np.ndarray:
    """(size, size, 3) world directions of a GL face's pixel centres (row = t, col = s)."""
    t, s = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    sc, tc = 2 * s - 1, 2 * t - 1
    one = np.ones_like(sc)
    g = {"px": (one, -tc, -sc), "nx": (-one, -tc, sc), "py": (sc, one, tc), "ny": (sc, -one, -tc),
         "pz": (sc, -tc, one), "nz": (-sc, -tc, -one)}[face]
    g = np.stack(g, axis=-1)
    return _gl_to_world(g / np.linalg.norm(g, axis=-1, keepdims=True))


def gl_face_solid_angles(size: int) -> np.ndarray:
    """(size, size) exact solid angle of each pixel of a cube face."""
    e = -1.0 + 2.0 * np.arange(size + 1) / size
    return face_rectangle_solid_angle(e[None, :-1], e[None, 1:], e[:-1, None], e[1:, None])


def to_gl_faces(texels: np.ndarray, cube: CubeMap) -> dict[str, np.ndarray]:
    """Six (R, R, C) faces of a cube-map light (R = its face resolution): each face pixel is one of
    our texels (the same cube), so radiance and solid angle carry over exactly; faces or halves the
    light does not cover (hemisphere mode: below the horizon) are 0."""
    tex = np.asarray(texels, np.float64)
    R = cube.resolution
    out = {}
    for face in GL_FACES:
        idx = cube.lookup(gl_face_directions(face, R))
        out[face] = np.where((idx >= 0)[..., None], tex[np.where(idx >= 0, idx, 0)], 0.0)
    return out


def gl_lookup(faces: dict[str, np.ndarray], directions: np.ndarray) -> np.ndarray:
    """What an OpenGL cube-map sampler reads for world directions (nearest texel)."""
    g = _world_to_gl(np.asarray(directions, np.float64))
    x, y, z = g[..., 0], g[..., 1], g[..., 2]
    ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
    size = next(iter(faces.values())).shape[0]
    out = np.zeros(g.shape[:-1] + next(iter(faces.values())).shape[2:])
    major_x = (ax >= ay) & (ax >= az)
    major_y = ~major_x & (ay >= az)
    major_z = ~major_x & ~major_y
    cases = [("px", major_x & (x >= 0), -z, -y, ax), ("nx", major_x & (x < 0), z, -y, ax),
             ("py", major_y & (y >= 0), x, z, ay), ("ny", major_y & (y < 0), x, -z, ay),
             ("pz", major_z & (z >= 0), x, -y, az), ("nz", major_z & (z < 0), -x, -y, az)]
    for face, sel, sc, tc, ma in cases:
        if not np.any(sel):
            continue
        s = (sc[sel] / ma[sel] + 1) / 2
        t = (tc[sel] / ma[sel] + 1) / 2
        out[sel] = _read(faces[face], np.floor(t * size).astype(int), np.floor(s * size).astype(int))
    return out
