"""Ray casting against the scene mesh: Embree (through embreex) and a slow reference backend.

Both backends share one API (`intersect`, `occluded`) and the same precision policy:
- the mesh is recentred on its bounding-box centre before it is handed to the ray caster, so
  float32 keeps its precision for meshes far from the origin (e.g. survey coordinates);
- shadow rays start at the surface point pushed along the geometric normal by
  `offset = 1e-5 x scene size` (towards the side the ray leaves on), which clears float32
  self-intersection without letting light leak through contact points.

`make_backend(name)` is the one place a backend is chosen.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .mesh import Mesh

RAY_OFFSET = 1e-5  # x scene size
MISS = -1


class _Backend:
    """Common frame handling: world coordinates in, recentred float32 to the kernel."""

    name = "base"

    def __init__(self, mesh: Mesh, threads: int = 2):
        self.mesh = mesh
        self.centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
        self.scale = mesh.scale
        self.offset = RAY_OFFSET * self.scale
        self.threads = max(1, int(threads))
        self.triangles = (mesh.vertices - self.centre)[mesh.faces].astype(np.float32)  # (F, 3, 3)

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """World points -> float32 points in the recentred frame the kernel works in."""
        return (np.asarray(points, dtype=np.float64) - self.centre).astype(np.float32)

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

