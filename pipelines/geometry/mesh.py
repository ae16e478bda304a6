"""The scene's triangle mesh (world coordinates, +Z up) and the small operations on it that
placing a virtual object needs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mesh:
    """Triangle mesh in world coordinates with smooth per-vertex shading normals."""

    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    vertex_normals: np.ndarray  # (V, 3) float64 unit
    notes: tuple[str, ...] = ()
    # the parts the file carries (OBJ usemtl groups, glTF primitives' materials, PLY face labels): their names, each
    # face's part index, each face corner's UV (NaN where the part has none) and vertex colour
    # (linear RGB; None when the file has none); `part_materials`: what the file says of each part
    # (`parts.FileMaterial`). Empty / None for a file without parts.
    part_names: tuple[str, ...] = ()
    face_part: np.ndarray | None = None  # (F,) int32
    face_uv: np.ndarray | None = None  # (F, 3, 2) float64
    face_colour: np.ndarray | None = None  # (F, 3, 3) float64
    part_materials: tuple = ()

    @property
    def scale(self) -> float:
        """Diagonal of the bounding box (sets ray offsets and tolerances)."""
        return float(np.linalg.norm(self.vertices.max(axis=0) - self.vertices.min(axis=0)))

    @property
    def face_normals(self) -> np.ndarray:
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def place(mesh: Mesh, position, scale: float = 1.0, rotate_z_deg: float = 0.0) -> Mesh:
    """A mesh scaled about its origin, turned about +Z, and moved to `position` (world)."""
    a = np.radians(rotate_z_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    v = (mesh.vertices * scale) @ Rz.T + np.asarray(position, np.float64)
    n = mesh.vertex_normals @ Rz.T
    return Mesh(v, mesh.faces, n, mesh.notes)


def sphere(radius: float = 1.0, subdivisions: int = 4) -> Mesh:
    """An icosphere with exact unit normals."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = np.asarray(s.vertices, np.float64)
    return Mesh(v, np.asarray(s.faces, np.int64), v / np.linalg.norm(v, axis=1, keepdims=True))


def combine(scene: Mesh, obj: Mesh) -> Mesh:
    return Mesh(np.vstack([scene.vertices, obj.vertices]), np.vstack([scene.faces, obj.faces + len(scene.vertices)]),
                np.vstack([scene.vertex_normals, obj.vertex_normals]))
