"""Insert a virtual object into the photo by differential rendering (Debevec 1998): the object is
shaded by the recovered light with its own shadows, and what it changes on the known geometry
(its shadow, light it blocks) is added to the photo as render_with - render_without, so the
photo's own detail (texture, noise, what the model misses) is kept.

    composite = object pixels:            render of the object
                known geometry pixels:    photo + render_with(object) - render_without(object)
                other pixels:             photo

All three renders use the one forward model (pipelines.render) on visibility cast against the
scene with and without the object.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import pixel_samples
from .cubemap import CubeMap
from .render import Material, pixels_to_image, render
from .scene import Camera, Mesh, Pose
from .visibility import compute_visibility


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


@dataclass
class Insertion:
    composite: np.ndarray  # (H, W, 3) the photo with the object
    with_object: np.ndarray  # (H, W, 3) our render of scene + object (0 where nothing is hit)
    without_object: np.ndarray  # (H, W, 3) our render of the scene alone, same pixels
    object_mask: np.ndarray  # (H, W) pixels that see the object
    scene_mask: np.ndarray  # (H, W) pixels that see the known geometry (in front of nothing inserted)
    shadow: np.ndarray  # (H, W) relative change the object makes on the known geometry (with / without - 1)


def insert(camera: Camera, pose: Pose, scene_mesh: Mesh, obj: Mesh, light: np.ndarray, cube: CubeMap,
           scene_material: Material, obj_material: Material, photo: np.ndarray, make_backend,
           supersample: int = 1, progress=None) -> Insertion:
    """Differential rendering of `obj` (world coordinates) into `photo` under `light` (texels of
    `cube`). make_backend(mesh) -> a ray caster (pipelines.raycast.make_backend)."""
    both = combine(scene_mesh, obj)
    backend_both = make_backend(both)
    backend_scene = make_backend(scene_mesh)
    H, W = camera.height, camera.width
    samples, _ = pixel_samples(camera, pose, both, backend_both, None, edge_margin=-1)
    on_object = samples.face >= len(scene_mesh.faces)
    vis_with = compute_visibility(backend_both, samples, cube, supersample, progress=progress)
    with_obj = np.zeros((len(samples), 3))
    with_obj[~on_object] = render(_subset(vis_with, ~on_object), light, scene_material)
    if on_object.any():
        with_obj[on_object] = render(_subset(vis_with, on_object), light, obj_material)
    scene_samples = _subset(vis_with, ~on_object).samples
    vis_without = compute_visibility(backend_scene, scene_samples, cube, supersample)
    without = np.zeros((len(samples), 3))
    without[~on_object] = render(vis_without, light, scene_material)
    img_with = pixels_to_image(with_obj, samples.pixel, H, W)
    img_without = pixels_to_image(without, samples.pixel, H, W)
    object_mask = np.zeros((H, W), bool)
    object_mask[samples.pixel[on_object, 0], samples.pixel[on_object, 1]] = True
    scene_mask = np.zeros((H, W), bool)
    scene_mask[samples.pixel[~on_object, 0], samples.pixel[~on_object, 1]] = True
    composite = np.asarray(photo, np.float64).copy()
    composite[scene_mask] += img_with[scene_mask] - img_without[scene_mask]
    composite[object_mask] = img_with[object_mask]
    composite = np.clip(composite, 0.0, None)
    with np.errstate(divide="ignore", invalid="ignore"):
        shadow = np.where(scene_mask, img_with.mean(axis=2) / img_without.mean(axis=2) - 1.0, 0.0)
    shadow = np.nan_to_num(shadow)
    return Insertion(composite, img_with, img_without, object_mask, scene_mask, shadow)


def _subset(vis, keep: np.ndarray):
    """The visibility of some of its pixels (in memory)."""
    from .camera import PixelSamples
    from .visibility import VisibilityData

    s = vis.samples
    samples = PixelSamples(s.pixel[keep], s.position[keep], s.normal[keep], s.geometric_normal[keep], s.view[keep],
                           s.face[keep])
    return VisibilityData(samples, vis.cube, vis.supersample, np.asarray(vis.stored)[keep])
