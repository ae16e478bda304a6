"""Ray casting against the scene mesh: Embree (through embreex) and a slow reference backend.

Both backends share one API (`intersect`, `occluded`, `first_hits`, `shadow_origins`) and the same
precision policy:
- the mesh is recentred on its bounding-box centre before it is handed to the ray caster, so
  float32 keeps its precision for meshes far from the origin (e.g. survey coordinates);
- the kernel (float32) only chooses the face a camera ray hits; `first_hits` then locates the hit
  in float64 on that face (the float64 ray meets the face's plane, barycentrics clamped into the
  triangle). Embree's float32 distance t is off by ~eps32 x the camera's distance from the mesh,
  which with a long lens far away (D = 700 radii of a ball) put hit points below their facet;
- shadow rays start at the surface point pushed along the geometric normal (towards the side the
  ray leaves on) by `shadow_origins`, the one place shadow-ray origins are made:
  offset = OFFSET_ULPS x eps32 x (max |p| in the recentred frame + the hit triangle's longest edge),
  added in float64 before the origin is rounded to float32. It exceeds the float32 rounding of the
  origin and of the triangle's vertices at any camera distance and scene scale, and is small
  (at most ~2e-6 x the scene's size for small triangles) so light does not leak through contacts.

`make_backend(name)` is the one place a backend is chosen.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import cached_property

import numpy as np

from .mesh import Mesh

EPS32 = float(np.finfo(np.float32).eps)  # 2^-23
OFFSET_ULPS = 32.0  # shadow-ray offset in float32 ulps of the coordinates where the ray starts
RESTART_ULPS = 64.0  # the second first-hit query starts this many float32 ulps (of the first one's reach) short
MISS = -1
LOCATE_BLOCK = 1 << 18  # hits located per block by `first_hits` (bounds its float64 scratch)


class _Backend:
    """Common frame handling: world coordinates in, recentred float32 to the kernel."""

    name = "base"

    def __init__(self, mesh: Mesh, threads: int = 2):
        self.mesh = mesh
        self.centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
        self.scale = mesh.scale
        self.threads = max(1, int(threads))
        self.triangles = (mesh.vertices - self.centre)[mesh.faces].astype(np.float32)  # (F, 3, 3)

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """World points -> float32 points in the recentred frame the kernel works in."""
        return (np.asarray(points, dtype=np.float64) - self.centre).astype(np.float32)

    @cached_property
    def longest_edges(self) -> np.ndarray:
        """(F,) float64 length of each face's longest edge."""
        v = self.mesh.vertices[self.mesh.faces]
        return np.sqrt(np.max(np.stack([np.sum((v[:, 1] - v[:, 0]) ** 2, axis=1), np.sum((v[:, 2] - v[:, 1]) ** 2, axis=1),
                                        np.sum((v[:, 0] - v[:, 2]) ** 2, axis=1)]), axis=0))

    def shadow_origins(self, positions: np.ndarray, geometric_normals: np.ndarray, faces: np.ndarray,
                       local: bool = True) -> np.ndarray:
        """Where shadow rays from surface points start: each point pushed along its (unit) geometric
        normal by OFFSET_ULPS x eps32 x (max |p| in the recentred frame + its face's longest edge),
        in float64, so that the origin after its rounding to float32 is still above the float32
        triangle (both are off by ~eps32 x their coordinates). The one definition of the offset.

        positions : (n, 3) world points on faces `faces` (n,); geometric_normals : (n, 3), on the side
        the rays leave on. Returns (n, 3) float32 in the recentred frame (for `occluded_local`), or
        with `local=False` float64 world points (for `occluded`, e.g. of another backend).
        """
        p = np.asarray(positions, np.float64) - self.centre
        offset = OFFSET_ULPS * EPS32 * (np.abs(p).max(axis=1, initial=0.0) + self.longest_edges[np.asarray(faces)])
        o = p + offset[:, None] * np.asarray(geometric_normals, np.float64)
        return o.astype(np.float32) if local else o + self.centre

    def first_hits(self, origins: np.ndarray, directions: np.ndarray):
        """First hits of world rays located in float64: (t (n,), face (n,) with -1 for a miss,
        barycentrics (n, 3) of the face's vertices, world points (n, 3); t = inf and points NaN on a miss).

        The kernel chooses the face in two queries: the ray as given, then again from just short of
        that hit (RESTART_ULPS x eps32 x the first query's reach, over the cosine with the face), so
        that a camera far from the mesh (whose float32 origin and direction are off by ~eps32 x the
        distance) takes the face that a float32 ray starting near the surface hits. The point is
        where the float64 ray meets that face's plane (float64 vertices), its barycentrics clamped
        into the triangle: on its face to float64 rounding, whatever the camera's distance.
        """
        o = np.asarray(origins, np.float64)
        d = np.asarray(directions, np.float64)
        t, face, _, _ = self.intersect(o, d)
        n = len(face)
        w = np.zeros((n, 3))
        points = np.full((n, 3), np.nan)
        hits = np.flatnonzero(face != MISS)
        for a in range(0, len(hits), LOCATE_BLOCK):
            hit = hits[a:a + LOCATE_BLOCK]
            oh, dh, th = o[hit] - self.centre, d[hit], t[hit]
            v = self.mesh.vertices[self.mesh.faces[face[hit]]]
            normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            with np.errstate(divide="ignore", invalid="ignore"):
                cos = np.abs(np.einsum("ij,ij->i", normal, dh)) / np.linalg.norm(normal, axis=1)
            cos = np.nan_to_num(cos, nan=1.0)
            back = np.minimum(RESTART_ULPS * EPS32 * (np.abs(oh).max(axis=1) + th) / np.maximum(cos, 1e-3), th)
            _, again, _, _ = self.intersect(o[hit] + (th - back)[:, None] * dh, dh)
            keep = again != MISS  # (a miss: the first hit grazed a silhouette; its face stays)
            face[hit[keep]] = again[keep]
            t[hit], w[hit], points[hit] = self._on_faces(oh, dh, face[hit])
        return t, face, w, points

    def _on_faces(self, o: np.ndarray, d: np.ndarray, faces: np.ndarray):
        """(t, barycentrics, world points) where float64 rays (origins in the recentred frame) meet
        the planes of `faces`, the barycentrics clamped into the triangles."""
        tri = self.mesh.vertices[self.mesh.faces[faces]] - self.centre  # (n, 3, 3) float64, recentred
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        normal = np.cross(e1, e2)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("ij,ij->i", normal, tri[:, 0] - o) / np.einsum("ij,ij->i", normal, d)
        t = np.where(np.isfinite(t), t, 0.0)  # a ray in the face's plane: from its origin
        q = o + t[:, None] * d - tri[:, 0]
        d00, d01, d11 = (np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e1, e2), np.einsum("ij,ij->i", e2, e2))
        d20, d21 = np.einsum("ij,ij->i", q, e1), np.einsum("ij,ij->i", q, e2)
        det = d00 * d11 - d01 * d01
        with np.errstate(divide="ignore", invalid="ignore"):
            w1 = (d11 * d20 - d01 * d21) / det
            w2 = (d00 * d21 - d01 * d20) / det
        w = np.column_stack([1.0 - w1 - w2, w1, w2])
        w[~np.isfinite(w).all(axis=1)] = 1.0 / 3.0  # a degenerate face: its centroid
        outside = (w < 0).any(axis=1)
        if outside.any():  # the float64 ray just past an edge of the face the kernel chose
            wc = np.clip(w[outside], 0.0, None)
            w[outside] = wc / wc.sum(axis=1, keepdims=True)
        p = np.einsum("ik,ikj->ij", w, tri)
        return np.einsum("ij,ij->i", p - o, d) / np.einsum("ij,ij->i", d, d), w, p + self.centre

    def occluded_local(self, origins: np.ndarray, directions: np.ndarray,
                       tfar: np.ndarray | None = None) -> np.ndarray:
        """`occluded` for float32 origins already in the recentred frame, on the calling thread.
        Rays with tfar <= 0 are not traced (reported unoccluded)."""
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        if tfar is None:
            return self._occluded(o, d)
        return self._occluded(o, d, np.ascontiguousarray(tfar, dtype=np.float32))

    def intersect(self, origins: np.ndarray, directions: np.ndarray):
        """First hits: (t (n,), face (n,) with -1 for a miss, barycentric u (n,), v (n,))."""
        o = self.to_local(origins)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        return self._intersect(o, d)

    def occluded(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(n,) bool: does the ray (origin already offset) hit anything? Rays are split over threads."""
        o = self.to_local(origins)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        n = len(o)
        if self.threads == 1 or n < 4096:
            return self._occluded(o, d)
        bounds = np.linspace(0, n, self.threads + 1).astype(int)
        out = np.empty(n, dtype=bool)

        def work(i):
            a, b = bounds[i], bounds[i + 1]
            out[a:b] = self._occluded(o[a:b], d[a:b])

        with ThreadPoolExecutor(self.threads) as pool:
            list(pool.map(work, range(self.threads)))
        return out


class EmbreeBackend(_Backend):
    """Embree occlusion/intersection queries via embreex (releases the GIL: threads scale)."""

    name = "embree"

    def __init__(self, mesh: Mesh, threads: int = 2):
        super().__init__(mesh, threads)
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self._scene = rtcore_scene.EmbreeScene()
        self._geometry = TriangleMesh(self._scene, self.triangles)

    def _intersect(self, o, d):
        res = self._scene.run(o, d, query="INTERSECT", output=1)
        face = np.asarray(res["primID"], dtype=np.int64)
        t = np.asarray(res["tfar"], np.float64)
        t[face == MISS] = np.inf  # Embree leaves its initial 1e37 on a miss
        return t, face, np.asarray(res["u"], np.float64), np.asarray(res["v"], np.float64)

    def _occluded(self, o, d, tfar=None):
        return np.asarray(self._scene.run(o, d, dists=tfar, query="OCCLUDED")) != MISS


class ReferenceBackend(_Backend):
    """Brute-force Moller-Trumbore over all triangles in numpy: slow, obviously correct (tests)."""

    name = "reference"

    def _hits(self, o, d, block: int = 64):
        tri = self.triangles.astype(np.float64)
        v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        o = o.astype(np.float64)
        d = d.astype(np.float64)
        n = len(o)
        best_t = np.full(n, np.inf)
        best_f = np.full(n, MISS, dtype=np.int64)
        best_u = np.zeros(n)
        best_v = np.zeros(n)
        eps = 1e-12
        for a in range(0, n, block):
            ob, db = o[a:a + block, None, :], d[a:a + block, None, :]
            p = np.cross(db, e2[None])
            det = np.einsum("rfk,fk->rf", p, e1)
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / det
                s = ob - v0[None]
                u = np.einsum("rfk,rfk->rf", s, p) * inv
                q = np.cross(s, e1[None])
                v = np.einsum("rfk,rfk->rf", db, q) * inv
                t = np.einsum("fk,rfk->rf", e2, q) * inv
                ok = (np.abs(det) > eps) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
            t = np.where(ok, t, np.inf)
            f = np.argmin(t, axis=1)
            rows = np.arange(len(f))
            tb = t[rows, f]
            hit = np.isfinite(tb)
            best_t[a:a + block] = tb
            best_f[a:a + block] = np.where(hit, f, MISS)
            best_u[a:a + block] = np.where(hit, u[rows, f], 0.0)
            best_v[a:a + block] = np.where(hit, v[rows, f], 0.0)
        return best_t, best_f, best_u, best_v

    def _intersect(self, o, d):
        t, f, u, v = self._hits(o, d)
        t[f == MISS] = np.inf
        return t, f, u, v

    def _occluded(self, o, d, tfar=None):
        if tfar is None:
            return self._hits(o, d)[1] != MISS
        out = np.zeros(len(o), dtype=bool)
        live = tfar > 0
        t, face, _, _ = self._hits(o[live], d[live])
        out[live] = (face != MISS) & (t < tfar[live])
        return out


BACKENDS = {"embree": EmbreeBackend, "reference": ReferenceBackend}


def make_backend(mesh: Mesh, name: str = "embree", threads: int = 2) -> _Backend:
    if name not in BACKENDS:
        raise ValueError(f"unknown ray backend {name!r}; choose one of {sorted(BACKENDS)}")
    return BACKENDS[name](mesh, threads=threads)

