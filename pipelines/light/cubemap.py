"""Cube-map light layout: texel directions, exact solid angles, lookups and lat-long conversion.

The light is a set of texels on the cube [-1, 1]^3 (DESIGN §2). In hemisphere mode (the paper's
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
from functools import cache as functools_cache
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

    @cached_property
    def vector_solid_angles(self) -> np.ndarray:
        """(N, 3) integral of the direction over each texel, in closed form: for a spherical
        polygon with vertices v_k, m = 1/2 sum_k theta_k u_k, theta_k the angle between v_k and
        v_k+1 and u_k the unit normal of their great circle (Lambert's formula for a polygon's
        vector irradiance; Arvo 1995). For a normal N with N.d > 0 over the whole texel, N . m_i is
        exactly the texel's projected solid angle, the integral of the cosine: the diffuse transport."""
        corners = [self.face_directions(*self.face_coordinates(r, c)) for r, c in ((0, 0), (0, 1), (1, 1), (1, 0))]
        m = np.zeros((self.n_texels, 3))
        for k in range(4):
            a, b = corners[k], corners[(k + 1) % 4]
            cross = np.cross(a, b)
            sine = np.linalg.norm(cross, axis=1)
            m += 0.5 * (np.arctan2(sine, np.einsum("nk,nk->n", a, b)) / np.maximum(sine, 1e-300))[:, None] * cross
        return m * np.sign(np.einsum("nk,nk->n", m, self.directions))[:, None]  # towards the texel

    def quadrature(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """k x k sub-texel quadrature: directions (N, k*k, 3) float32 and exact solid angles
        (N, k*k) float32 summing to each texel's solid angle."""
        return self._quadrature(int(k))

    @functools_cache
    def _quadrature(self, k: int):
        R = self.resolution
        dirs = self.subtexel_directions(k).astype(np.float32)
        offsets = np.arange(k) / k
        weights = []
        for orow in offsets:
            for ocol in offsets:
                s0 = -1.0 + 2.0 * (self.texel_col + ocol) / R
                t0 = -1.0 + 2.0 * (self.texel_row + orow) / R
                weights.append(face_rectangle_solid_angle(s0, s0 + 2.0 / (R * k), t0, t0 + 2.0 / (R * k)))
        return dirs, np.stack(weights, axis=1).astype(np.float32)

    def lookup(self, directions: np.ndarray) -> np.ndarray:
        """Texel index of each direction ((..., 3) array), -1 where the layout has no texel
        (and for zero or non-finite directions)."""
        d = np.asarray(directions, dtype=np.float64)
        shape = d.shape[:-1]
        x, y, z = (d[..., i].ravel() for i in range(3))
        ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
        # major axis -> face index (FACE_NAMES order) and the face's (s, t) numerators
        is_x = (ax >= ay) & (ax >= az)
        is_y = ~is_x & (ay >= az)
        face = np.where(is_x, np.where(x >= 0, _FACE["+x"], _FACE["-x"]),
                        np.where(is_y, np.where(y >= 0, _FACE["+y"], _FACE["-y"]),
                                 np.where(z >= 0, _FACE["+z"], _FACE["-z"])))
        depth = np.where(is_x, ax, np.where(is_y, ay, az))
        num_s = _S_COEF[face, 0] * x + _S_COEF[face, 1] * y + _S_COEF[face, 2] * z
        num_t = _T_COEF[face, 0] * x + _T_COEF[face, 1] * y + _T_COEF[face, 2] * z
        bad = ~np.isfinite(depth + num_s + num_t) | (depth <= 0)
        depth[bad] = 1.0
        R = self.resolution
        col = np.clip(np.floor((num_s / depth + 1.0) * (0.5 * R)), 0, R - 1)
        row = np.clip(np.floor((num_t / depth + 1.0) * (0.5 * R)), 0, R - 1)
        col[bad] = row[bad] = 0
        idx = self._face_lookup[face, row.astype(np.int64), col.astype(np.int64)]
        idx[bad] = -1
        return idx.reshape(shape)


_FACE = {name: i for i, name in enumerate(FACE_NAMES)}
_S_COEF = np.array([FACE_FRAMES[f][1] for f in FACE_NAMES], dtype=np.float64)  # column axis a
_T_COEF = np.array([FACE_FRAMES[f][2] for f in FACE_NAMES], dtype=np.float64)  # row axis b


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


OVERLAP_FORMAT = 1  # bump when `_build_latlong_overlap` changes: stored overlaps of older formats are not read


def _user_cache_dir():
    """Where derived data that depends only on its parameters is kept between runs
    ($WAVELIGHT_CACHE_DIR, else $XDG_CACHE_HOME/wavelight, else ~/.cache/wavelight); None to not keep it."""
    import os
    from pathlib import Path

    if os.environ.get("WAVELIGHT_CACHE_DIR") == "":
        return None
    base = os.environ.get("WAVELIGHT_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "wavelight")
    return Path(base)


@functools_cache
def latlong_overlap(height: int, cube: CubeMap):
    """`_build_latlong_overlap`, kept in memory and in the user's cache folder (`_user_cache_dir`):
    it depends on (H, R, hemisphere) alone and takes ~1 s at R = 32, tens of seconds at R = 128.
    A stored matrix that cannot be read, or has the wrong shape, is rebuilt."""
    from scipy import sparse

    folder = _user_cache_dir()
    name = f"latlong-overlap-v{OVERLAP_FORMAT}-H{int(height)}-R{cube.resolution}-{'hemi' if cube.hemisphere else 'sphere'}.npz"
    if folder is not None:
        try:
            m = sparse.load_npz(folder / name).tocsr()
            if m.shape == (int(height) * 2 * int(height), cube.n_texels):
                return m
        except Exception:  # absent, unreadable, or from another scipy: rebuild it
            pass
    m = _build_latlong_overlap(height, cube)
    if folder is not None:
        try:
            from ..io.files import atomic_output

            folder.mkdir(parents=True, exist_ok=True)
            with atomic_output(folder / name, now=True) as tmp:
                sparse.save_npz(tmp, m, compressed=False)
        except OSError:  # a read-only or full home: the matrix is only kept in memory
            pass
    return m


def _build_latlong_overlap(height: int, cube: CubeMap):
    """Sparse (H*2H, N) matrix of the solid angle each lat-long pixel shares with each texel.

    Pixels are cut into cells no larger than about half a texel; a cell whose corners and centre
    all fall in one texel goes to it whole; other cells are split in four until they are ~1/64 of
    a texel (at least twice), and the last ones go by their centre. Cell areas are exact, so every
    row sums to its pixel's solid angle exactly (in hemisphere mode, the part above the horizon);
    column sums match the texel solid angles to ~0.7 % rms, 2 % at worst (cells that pass the
    corner test but clip a texel boundary between their corners, and the last centre
    assignments). The matrix is cached per (H, cube); building it takes ~1 s at R = 32 and tens
    of seconds at R = 128.
    """
    from scipy import sparse

    H, W = height, 2 * height
    texel_angle = 0.5 * np.pi / cube.resolution  # at a face centre; corner texels are ~0.6x as wide
    k = int(max(1, np.ceil(2.0 * (np.pi / H) / (0.6 * texel_angle))))
    max_depth = int(max(2, np.ceil(np.log2((np.pi / (H * k)) / (texel_angle / 64.0)))))
    rows, cols = np.meshgrid(np.arange(H * k), np.arange(W * k), indexing="ij")
    theta0 = np.pi * rows.ravel() / (H * k)
    phi0 = 2.0 * np.pi * cols.ravel() / (W * k)
    pixel = (rows.ravel() // k) * W + cols.ravel() // k
    dtheta, dphi = np.pi / (H * k), 2.0 * np.pi / (W * k)
    corners = (1e-7, 1.0 - 1e-7)  # nudged inside the cell: poles, horizon and seams
    out_p, out_t, out_w = [], [], []
    for depth in range(max_depth + 1):
        centre = cube.lookup(spherical_to_direction(theta0 + 0.5 * dtheta, phi0 + 0.5 * dphi))
        same = np.ones(len(centre), dtype=bool)
        if depth < max_depth:
            for ft in corners:
                for fp in corners:
                    same &= cube.lookup(spherical_to_direction(theta0 + ft * dtheta, phi0 + fp * dphi)) == centre
        area = dphi * (np.cos(theta0) - np.cos(theta0 + dtheta))
        keep = same & (centre >= 0)
        out_p.append(pixel[keep])
        out_t.append(centre[keep])
        out_w.append(area[keep])
        split = ~same
        if not split.any():
            break
        theta0, phi0, pixel = theta0[split], phi0[split], pixel[split]
        dtheta, dphi = dtheta / 2, dphi / 2
        theta0 = np.concatenate([theta0, theta0, theta0 + dtheta, theta0 + dtheta])
        phi0 = np.concatenate([phi0, phi0 + dphi, phi0, phi0 + dphi])
        pixel = np.tile(pixel, 4)
    p, t, w = np.concatenate(out_p), np.concatenate(out_t), np.concatenate(out_w)
    key = p * cube.n_texels + t  # merge the pieces of one (pixel, texel) pair
    key, inverse = np.unique(key, return_inverse=True)
    w = np.bincount(inverse, weights=w)
    p, t = key // cube.n_texels, key % cube.n_texels
    overlap = sparse.csr_matrix((w, (p, t)), shape=(H * W, cube.n_texels))
    return overlap


def latlong_to_cube(latlong: np.ndarray, cube: CubeMap) -> np.ndarray:
    """Resample a lat-long radiance image onto the cube map, preserving power.

    Texel radiance = (sum over lat-long pixels of radiance x overlap solid angle) / texel solid
    angle (`latlong_overlap`). Total power is preserved exactly (in hemisphere mode, power below
    the horizon is dropped), a small bright source keeps its energy and lands in the texel that
    contains it, and a constant map stays constant to ~2 % (see `latlong_overlap`).

    Parameters
    ----------
    latlong : (H, 2H) or (H, 2H, C) array

    Returns
    -------
    (N,) or (N, C) float64 texel radiances.
    """
    img = np.asarray(latlong, dtype=np.float64)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[..., None]
    if img.ndim != 3 or img.shape[1] != 2 * img.shape[0]:
        raise ValueError(f"lat-long image must have shape (H, 2H) or (H, 2H, C), got {latlong.shape}")
    H, W, C = img.shape
    overlap = latlong_overlap(H, cube)
    power = overlap.T @ img.reshape(H * W, C)
    out = power / cube.solid_angles[:, None]
    return out[:, 0] if squeeze else out


def cube_to_latlong(texels: np.ndarray, cube: CubeMap, height: int) -> np.ndarray:
    """Resample texel radiances to an (H, 2H[, C]) lat-long image, preserving power.

    Pixel radiance = (sum over texels of radiance x overlap solid angle) / pixel solid angle, with
    each texel's overlaps rescaled to its exact solid angle, so total power is exact and a
    constant map stays constant to ~2 % (zero where the layout has no texel).
    """
    tex = np.asarray(texels, dtype=np.float64)
    squeeze = tex.ndim == 1
    if squeeze:
        tex = tex[:, None]
    if tex.shape[0] != cube.n_texels:
        raise ValueError(f"texels must have shape ({cube.n_texels}, C), got {texels.shape}")
    overlap = latlong_overlap(height, cube)
    assigned = np.asarray(overlap.sum(axis=0)).ravel()
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(assigned > 0, cube.solid_angles / assigned, 0.0)
    pix_omega = latlong_solid_angles(height).reshape(-1, 1)
    out = (overlap @ (tex * scale[:, None])) / pix_omega
    out = out.reshape(height, 2 * height, -1)
    return out[..., 0] if squeeze else out


def rotate_latlong(latlong: np.ndarray, degrees: float) -> np.ndarray:
    """Turn a lat-long light about +Z by `degrees` (counter-clockwise seen from above: what was at
    azimuth phi moves to phi + degrees). Whole columns move exactly; the fractional part blends two
    neighbouring shifts, which keeps the total power exact (every column of a row has the same
    solid angle)."""
    img = np.asarray(latlong)
    W = img.shape[1]
    shift = (float(degrees) / 360.0 * W) % W
    k = int(np.floor(shift))
    f = shift - k
    a = np.roll(img, k, axis=1)
    return a if f == 0 else (1.0 - f) * a + f * np.roll(img, k + 1, axis=1)


def resample_cube(texels: np.ndarray, source: CubeMap, target: CubeMap, rotate_deg: float = 0.0,
                  k: int = 8) -> np.ndarray:
    """A cube-map light on another cube map (another R, hemisphere or sphere), turned about +Z by
    `rotate_deg` (phi -> phi + rotate_deg): each target texel averages the source radiance over a
    k x k sub-texel quadrature of its footprint (exact solid-angle weights), turned back into the
    source. Directions the source does not cover get 0. Unlike a trip through a lat-long image it
    does not blur: turned by 360 deg or resampled to the same cube, a light comes back exactly."""
    tex = np.asarray(texels, dtype=np.float64)
    if tex.shape[0] != source.n_texels:
        raise ValueError(f"texels must have {source.n_texels} rows, got {tex.shape[0]}")
    turns = float(rotate_deg) % 360.0
    if source == target and turns == 0.0:
        return tex.copy()
    dirs, weights = target.quadrature(k)
    a = -np.radians(turns)
    c, s_ = np.cos(a), np.sin(a)
    d = dirs.astype(np.float64)
    back = np.stack([c * d[..., 0] - s_ * d[..., 1], s_ * d[..., 0] + c * d[..., 1], d[..., 2]], axis=-1)
    idx = source.lookup(back)
    w = weights.astype(np.float64) * (idx >= 0)
    vals = tex[np.where(idx >= 0, idx, 0)]
    return np.einsum("nsc,ns->nc", vals.reshape(*idx.shape, -1), w).reshape(len(idx), *tex.shape[1:]) / \
        target.solid_angles.reshape(-1, *([1] * (tex.ndim - 1)))


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
