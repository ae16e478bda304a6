"""Cube-map light layout: texel directions, exact solid angles, lookups and lat-long conversion.

The light is a set of texels on the cube [-1, 1]^3 (DESIGN §3). In hemisphere mode (the paper's
Fig. 2) the +Z face is kept whole (R x R) and each side face keeps its upper half (R x R/2), split
into two R/2 x R/2 squares: nine square *tiles* and 3R^2 texels covering z >= 0 exactly. Sphere
mode keeps the six faces as six R x R tiles (6R^2 texels).

Texels are ordered tile by tile, row-major inside a tile. Every solver, the Haar basis and the
renderer use this order; only `tiles` describes it.

Face frames: a face has a centre axis ``n`` and in-face axes ``a`` (columns) and ``b`` (rows); the
point with face coordinates (s, t) in [-1, 1]^2 looks along ``n + s a + t b``. Side faces have
``b = -Z`` so their row 0 is at the top (towards the zenith). The frames are chosen so that the
faces join edge to edge in the horizontal-cross image (`cross_image`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

# name: (centre axis n, column axis a, row axis b)
FACE_FRAMES: dict[str, tuple[tuple[int, int, int], ...]] = {
    "+z": ((0, 0, 1), (0, 1, 0), (1, 0, 0)),
    "+x": ((1, 0, 0), (0, 1, 0), (0, 0, -1)),
    "+y": ((0, 1, 0), (-1, 0, 0), (0, 0, -1)),
    "-x": ((-1, 0, 0), (0, -1, 0), (0, 0, -1)),
    "-y": ((0, -1, 0), (1, 0, 0), (0, 0, -1)),
    "-z": ((0, 0, -1), (0, 1, 0), (-1, 0, 0)),
}
FACE_NAMES: tuple[str, ...] = tuple(FACE_FRAMES)
SIDE_FACES: tuple[str, ...] = ("+x", "+y", "-x", "-y")
# (row block, column block) of each face in the 3R x 4R horizontal cross
CROSS_BLOCKS: dict[str, tuple[int, int]] = {
    "+z": (0, 0), "+x": (1, 0), "+y": (1, 1), "-x": (1, 2), "-y": (1, 3), "-z": (2, 0),
}


@dataclass(frozen=True)
class Tile:
    """A square block of texels on one face: rows row0.., cols col0.. of that face, side `size`."""

    face: str
    row0: int
    col0: int
    size: int


def _solid_angle_primitive(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    # Solid angle subtended by [0, x] x [0, y] on the plane at distance 1 (signed).
    return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))


def face_rectangle_solid_angle(s0, s1, t0, t1) -> np.ndarray:
    """Exact solid angle of the face rectangle [s0, s1] x [t0, t1] (face coordinates in [-1, 1])."""
    F = _solid_angle_primitive
    return F(s1, t1) - F(s0, t1) - F(s1, t0) + F(s0, t0)


@dataclass(frozen=True)
class CubeMap:
    """Texel layout of a hemisphere (default) or full-sphere cube map of face resolution R.

    Parameters
    ----------
    resolution : int
        Face resolution R (a power of two, >= 2).
    hemisphere : bool
        Keep only z >= 0 (9 tiles, 3R^2 texels) or the full sphere (6 tiles, 6R^2 texels).
    """

    resolution: int
    hemisphere: bool = True

    def __post_init__(self):
        R = self.resolution
        if not isinstance(R, (int, np.integer)) or R < 2 or (R & (R - 1)) != 0:
            raise ValueError(f"cube-map resolution must be a power of two >= 2, got {R!r}")

    # -- layout ---------------------------------------------------------------------------------
    @cached_property
    def tiles(self) -> tuple[Tile, ...]:
        R = self.resolution
        if not self.hemisphere:
            return tuple(Tile(f, 0, 0, R) for f in ("+z", *SIDE_FACES, "-z"))
        half = R // 2
        tiles = [Tile("+z", 0, 0, R)]
        for f in SIDE_FACES:
            tiles += [Tile(f, 0, 0, half), Tile(f, 0, half, half)]
        return tuple(tiles)

    @property
    def tile_sizes(self) -> tuple[int, ...]:
        return tuple(t.size for t in self.tiles)

    @property
    def n_texels(self) -> int:
        return sum(t.size**2 for t in self.tiles)

    @cached_property
    def _texel_face_rc(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        faces, rows, cols = [], [], []
        for tile in self.tiles:
            r, c = np.meshgrid(np.arange(tile.size), np.arange(tile.size), indexing="ij")
            faces.append(np.full(tile.size**2, FACE_NAMES.index(tile.face)))
            rows.append(tile.row0 + r.ravel())
            cols.append(tile.col0 + c.ravel())
        return np.concatenate(faces), np.concatenate(rows), np.concatenate(cols)

    @property
    def texel_face(self) -> np.ndarray:
        """(N,) index into FACE_NAMES of each texel."""
        return self._texel_face_rc[0]

    @property
    def texel_row(self) -> np.ndarray:
        return self._texel_face_rc[1]

    @property
    def texel_col(self) -> np.ndarray:
        return self._texel_face_rc[2]

    @cached_property
    def _face_lookup(self) -> np.ndarray:
        """(6, R, R) texel index of each face texel, -1 where the layout does not cover it."""
        R = self.resolution
        table = np.full((6, R, R), -1, dtype=np.int64)
        table[self.texel_face, self.texel_row, self.texel_col] = np.arange(self.n_texels)
        return table

    # -- geometry -------------------------------------------------------------------------------
    def face_coordinates(self, offset_row=0.5, offset_col=0.5) -> tuple[np.ndarray, np.ndarray]:
        """Face coordinates (s, t) of a point inside every texel (0.5, 0.5 = texel centre)."""
        R = self.resolution
        s = -1.0 + 2.0 * (self.texel_col + offset_col) / R
        t = -1.0 + 2.0 * (self.texel_row + offset_row) / R
        return s, t

    def face_directions(self, s: np.ndarray, t: np.ndarray, faces: np.ndarray | None = None):
        """Unit directions of face points (s, t) on `faces` (default: each texel's face)."""
        faces = self.texel_face if faces is None else faces
        frames = np.array([FACE_FRAMES[f] for f in FACE_NAMES], dtype=np.float64)  # (6, 3, 3)
        n, a, b = frames[faces, 0], frames[faces, 1], frames[faces, 2]
        d = n + s[..., None] * a + t[..., None] * b
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    @cached_property
    def directions(self) -> np.ndarray:
        """(N, 3) float64 unit direction of each texel centre."""
        return self.face_directions(*self.face_coordinates())

    @cached_property
    def solid_angles(self) -> np.ndarray:
        """(N,) float64 exact solid angle of each texel; they sum to 2 pi (hemisphere) or 4 pi."""
        R = self.resolution
        s0 = -1.0 + 2.0 * self.texel_col / R
        t0 = -1.0 + 2.0 * self.texel_row / R
        return face_rectangle_solid_angle(s0, s0 + 2.0 / R, t0, t0 + 2.0 / R)

    def subtexel_directions(self, k: int) -> np.ndarray:
        """(N, k*k, 3) directions of a k x k grid of sub-texel centres (for supersampling)."""
        offsets = (np.arange(k) + 0.5) / k
        dirs = [self.face_directions(*self.face_coordinates(orow, ocol))
                for orow in offsets for ocol in offsets]
        return np.stack(dirs, axis=1)

    def lookup(self, directions: np.ndarray) -> np.ndarray:
        """Texel index of each direction ((..., 3) array), -1 where the layout has no texel."""
        d = np.asarray(directions, dtype=np.float64)
        shape = d.shape[:-1]
        d = d.reshape(-1, 3)
        axis = np.argmax(np.abs(d), axis=1)
        sign = np.sign(d[np.arange(len(d)), axis])
        sign[sign == 0] = 1.0
        # face index in FACE_NAMES from (axis, sign)
        face_of = {(0, 1): "+x", (0, -1): "-x", (1, 1): "+y", (1, -1): "-y", (2, 1): "+z", (2, -1): "-z"}
        table = np.zeros((3, 2), dtype=np.int64)
        for (ax, sg), name in face_of.items():
            table[ax, 0 if sg > 0 else 1] = FACE_NAMES.index(name)
        faces = table[axis, (sign < 0).astype(int)]
        frames = np.array([FACE_FRAMES[f] for f in FACE_NAMES], dtype=np.float64)
        n, a, b = frames[faces, 0], frames[faces, 1], frames[faces, 2]
        depth = np.einsum("ij,ij->i", d, n)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.einsum("ij,ij->i", d, a) / depth
            t = np.einsum("ij,ij->i", d, b) / depth
        R = self.resolution
        col = np.clip(np.floor((s + 1.0) * 0.5 * R), 0, R - 1).astype(np.int64)
        row = np.clip(np.floor((t + 1.0) * 0.5 * R), 0, R - 1).astype(np.int64)
        idx = self._face_lookup[faces, row, col]
        idx[~np.isfinite(depth) | (depth <= 0)] = -1
        return idx.reshape(shape)


# -- lat-long exchange format (DESIGN §2) ---------------------------------------------------------
def latlong_directions(height: int, width: int | None = None) -> np.ndarray:
    """(H, W, 3) pixel-centre directions of the lat-long layout (row 0 = zenith)."""
    width = 2 * height if width is None else width
    theta = np.pi * (np.arange(height) + 0.5) / height
    phi = 2.0 * np.pi * (np.arange(width) + 0.5) / width
    return spherical_to_direction(theta[:, None], phi[None, :])


def spherical_to_direction(theta, phi) -> np.ndarray:
    theta, phi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(phi, float))
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


def direction_to_spherical(d) -> tuple[np.ndarray, np.ndarray]:
    d = np.asarray(d, float)
    theta = np.arccos(np.clip(d[..., 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(d[..., 1], d[..., 0]), 2.0 * np.pi)
    return theta, phi


def latlong_solid_angles(height: int, width: int | None = None) -> np.ndarray:
    """(H, W) exact solid angle of each lat-long pixel."""
    width = 2 * height if width is None else width
    edges = np.pi * np.arange(height + 1) / height
    band = np.cos(edges[:-1]) - np.cos(edges[1:])
    return np.repeat((band * 2.0 * np.pi / width)[:, None], width, axis=1)


def _supersampling(cube: CubeMap, height: int) -> int:
    # Sub-cells must be well below a texel (corner texels are ~0.44x as wide as centre ones).
    return int(max(2, np.ceil(8.0 * cube.resolution / height)))


def _latlong_subcells(height: int, width: int, k: int, rows: slice):
    """Directions (h, W, k*k, 3) and exact solid angles (h, W, k*k) of sub-cells of `rows`."""
    r = np.arange(height)[rows]
    sub = np.arange(k)
    theta_edges = np.pi * (r[:, None] * k + np.arange(k + 1)[None, :]) / (height * k)  # (h, k+1)
    band = np.cos(theta_edges[:, :-1]) - np.cos(theta_edges[:, 1:])  # (h, k)
    theta_c = 0.5 * (theta_edges[:, :-1] + theta_edges[:, 1:])
    phi_c = 2.0 * np.pi * (np.arange(width)[:, None] * k + sub[None, :] + 0.5) / (width * k)  # (W, k)
    theta = np.broadcast_to(theta_c[:, None, :, None], (len(r), width, k, k))
    phi = np.broadcast_to(phi_c[None, :, None, :], (len(r), width, k, k))
    omega = np.broadcast_to(band[:, None, :, None] * (2.0 * np.pi / (width * k)), theta.shape)
    dirs = spherical_to_direction(theta, phi).reshape(len(r), width, k * k, 3)
    return dirs, omega.reshape(len(r), width, k * k)


def latlong_to_cube(latlong: np.ndarray, cube: CubeMap, supersample: int | None = None) -> np.ndarray:
    """Resample a lat-long radiance image onto the cube map, preserving power.

    Each lat-long pixel is split into k x k sub-cells with exact solid angles; each sub-cell's power
    (radiance x solid angle) goes to the texel its centre falls in, and texel radiance is the
    collected power over the texel's solid angle. Total power is preserved exactly (in hemisphere
    mode, power below the horizon is dropped), and a small bright source keeps its energy and lands
    in the texel that contains it.

    Parameters
    ----------
    latlong : (H, W) or (H, W, C) array
    cube : CubeMap
    supersample : int, optional
        Sub-cells per pixel side; default is chosen from the resolutions.

    Returns
    -------
    (N,) or (N, C) float64 texel radiances.
    """
    img = np.asarray(latlong, dtype=np.float64)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[..., None]
    if img.ndim != 3:
        raise ValueError(f"lat-long image must have shape (H, W) or (H, W, C), got {latlong.shape}")
    H, W, C = img.shape
    k = supersample or _supersampling(cube, H)
    power = np.zeros((cube.n_texels, C))
    rows_per_chunk = max(1, 2_000_000 // (W * k * k))
    for start in range(0, H, rows_per_chunk):
        rows = slice(start, min(H, start + rows_per_chunk))
        dirs, omega = _latlong_subcells(H, W, k, rows)
        idx = cube.lookup(dirs).ravel()
        w = (omega[..., None] * img[rows, :, None, :]).reshape(-1, C)
        keep = idx >= 0
        for c in range(C):
            power[:, c] += np.bincount(idx[keep], weights=w[keep, c], minlength=cube.n_texels)
    out = power / cube.solid_angles[:, None]
    return out[:, 0] if squeeze else out


def cube_to_latlong(texels: np.ndarray, cube: CubeMap, height: int,
                    supersample: int | None = None) -> np.ndarray:
    """Resample texel radiances to an (H, 2H[, C]) lat-long image, preserving power.

    Each lat-long pixel is the solid-angle-weighted mean radiance of its k x k sub-cells, each
    taking the radiance of the texel it falls in (zero where the layout has no texel), corrected
    so that every texel hands out exactly its power (radiance x exact solid angle).
    """
    tex = np.asarray(texels, dtype=np.float64)
    squeeze = tex.ndim == 1
    if squeeze:
        tex = tex[:, None]
    if tex.shape[0] != cube.n_texels:
        raise ValueError(f"texels must have shape ({cube.n_texels}, C), got {texels.shape}")
    H, W = height, 2 * height
    k = supersample or _supersampling(cube, H)
    rows_per_chunk = max(1, 2_000_000 // (W * k * k))
    chunks = [slice(s, min(H, s + rows_per_chunk)) for s in range(0, H, rows_per_chunk)]
    # Pass 1: the solid angle the sub-cells assign to each texel. Scaling texels by
    # (exact / assigned) makes the resampling conserve power exactly, even for a one-texel sun.
    assigned = np.zeros(cube.n_texels)
    for rows in chunks:
        dirs, omega = _latlong_subcells(H, W, k, rows)
        idx = cube.lookup(dirs).ravel()
        keep = idx >= 0
        assigned += np.bincount(idx[keep], weights=omega.ravel()[keep], minlength=cube.n_texels)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(assigned > 0, cube.solid_angles / assigned, 0.0)
    tex0 = np.vstack([tex * scale[:, None], np.zeros((1, tex.shape[1]))])  # index -1 -> zero row
    out = np.zeros((H, W, tex.shape[1]))
    for rows in chunks:
        dirs, omega = _latlong_subcells(H, W, k, rows)
        idx = cube.lookup(dirs)
        out[rows] = np.einsum("hwk,hwkc->hwc", omega, tex0[idx]) / omega.sum(axis=2)[..., None]
    return out[..., 0] if squeeze else out


def cross_image(texels: np.ndarray, cube: CubeMap, fill: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Lay the texels out as a 3R x 4R horizontal cross (see CROSS_BLOCKS).

    Returns the image ((3R, 4R) or (3R, 4R, C)) and a boolean mask of the pixels that hold texels.
    """
    tex = np.asarray(texels)
    R = cube.resolution
    img = np.full((3 * R, 4 * R) + tex.shape[1:], fill, dtype=np.result_type(tex, np.float32))
    valid = np.zeros((3 * R, 4 * R), dtype=bool)
    blocks = np.array([CROSS_BLOCKS[f] for f in FACE_NAMES])
    rows = blocks[cube.texel_face, 0] * R + cube.texel_row
    cols = blocks[cube.texel_face, 1] * R + cube.texel_col
    img[rows, cols] = tex
    valid[rows, cols] = True
    return img, valid
