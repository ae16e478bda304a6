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

from ..geometry.camera import Camera, Pose, pixel_samples
from ..geometry.mesh import Mesh, combine
from ..geometry.visibility import VisibilityData, compute_visibility
from ..light.cubemap import CubeMap
from .materials import Material
from .render import pixels_to_image, render


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
           scene_vis=None, supersample: int = 1, progress=None, scene_albedo=None) -> Insertion:
    """Differential rendering of `obj` (world coordinates) into `photo` under `light` (texels of
    `cube`). make_backend(mesh) -> a ray caster (`geometry.raycast.make_backend`).

    scene_vis : the photo view's visibility of the scene alone (the cached stage), reused for the
        pixels it has: with the object, a pixel's visibility is the scene's minus the rays the
        object blocks, and only rays toward the object's bounding sphere are cast against it.
    scene_albedo : the scene's per-pixel relative albedo, a function of pixel samples (its parts and
        textures: `parts.view_albedo`), or None (one uniform material).
    """
    both = combine(scene_mesh, obj)
    backend_both = make_backend(both)
    H, W = camera.height, camera.width
    samples, _ = pixel_samples(camera, pose, both, backend_both, None, edge_margin=-1)
    on_object = samples.face >= len(scene_mesh.faces)
    scene_rows = np.flatnonzero(~on_object)
    scene_samples = _subset_samples(samples, scene_rows)
    if supersample == 1:
        backend_scene = make_backend(scene_mesh)
        without_stored = _scene_visibility(scene_samples, scene_vis, cube, backend_scene, progress)
        with_stored = _minus_object(without_stored, scene_samples, cube, obj, make_backend(obj), backend_scene)
        obj_rows = np.flatnonzero(on_object)
        obj_stored = compute_visibility(backend_both, _subset_samples(samples, obj_rows), cube).stored
    else:  # fractional visibility: cast everything, with and without the object
        full_with = compute_visibility(backend_both, samples, cube, supersample, progress=progress).stored
        with_stored = np.asarray(full_with)[scene_rows]
        obj_rows = np.flatnonzero(on_object)
        obj_stored = np.asarray(full_with)[obj_rows]
        without_stored = compute_visibility(make_backend(scene_mesh), scene_samples, cube, supersample).stored
    albedo = None if scene_albedo is None else scene_albedo(scene_samples)
    spec = getattr(scene_albedo, "specular", None)
    spec = None if spec is None else spec(scene_samples)  # (the parts without a lobe: `parts.ViewShading`)
    with_obj = np.zeros((len(samples), 3))
    with_obj[scene_rows] = render(VisibilityData(scene_samples, cube, supersample, with_stored), light, scene_material,
                                  albedo=albedo, specular=spec)
    if len(obj_rows):
        with_obj[obj_rows] = render(VisibilityData(_subset_samples(samples, obj_rows), cube, supersample, obj_stored),
                                    light, obj_material)
    without = np.zeros((len(samples), 3))
    without[scene_rows] = render(VisibilityData(scene_samples, cube, supersample, without_stored), light,
                                 scene_material, albedo=albedo, specular=spec)
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


def _subset_samples(samples, rows: np.ndarray):
    return samples.take(rows)


def _scene_visibility(samples, scene_vis, cube: CubeMap, backend, progress=None) -> np.ndarray:
    """The scene's bit-packed visibility at these pixels: the cached rows of the pixels the cache
    has at the same point, the others cast."""
    width = (cube.n_texels + 7) // 8
    out = np.zeros((len(samples), width), np.uint8)
    have = np.zeros(len(samples), bool)
    if scene_vis is not None and scene_vis.cube == cube and scene_vis.supersample == 1:
        cached = scene_vis.samples
        H = int(max(cached.pixel[:, 0].max(), samples.pixel[:, 0].max())) + 1
        W = int(max(cached.pixel[:, 1].max(), samples.pixel[:, 1].max())) + 1
        index = np.full((H, W), -1, np.int64)
        index[cached.pixel[:, 0], cached.pixel[:, 1]] = np.arange(len(cached))
        k = index[samples.pixel[:, 0], samples.pixel[:, 1]]
        ok = k >= 0
        ok[ok] = np.linalg.norm(cached.position[k[ok]] - samples.position[ok], axis=1) <= 1e-6 * max(
            1.0, float(np.abs(samples.position).max()))
        out[ok] = np.asarray(scene_vis.stored)[k[ok]]
        have = ok
    rest = np.flatnonzero(~have)
    if len(rest):
        out[rest] = compute_visibility(backend, _subset_samples(samples, rest), cube, progress=progress).stored
    return out


def _minus_object(stored: np.ndarray, samples, cube: CubeMap, obj: Mesh, obj_backend, scene_backend) -> np.ndarray:
    """The visibility with `obj` added: the lit bits whose rays hit it cleared. Only directions
    inside the cone of the object's bounding sphere (widened by a texel) are cast against it, from
    the origins the scene's own shadow rays start at (`scene_backend.shadow_origins`; `samples`
    are on the scene mesh)."""
    lo, hi = obj.vertices.min(axis=0), obj.vertices.max(axis=0)
    centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    dirs = cube.directions
    half_texel = np.pi / (2 * cube.resolution) * np.sqrt(2.0)
    out = stored.copy()
    origins = scene_backend.shadow_origins(samples.position, samples.geometric_normal, samples.face, local=False)
    for a in range(0, len(samples), 2048):
        sl = slice(a, min(len(samples), a + 2048))
        axis = centre[None, :] - origins[sl]
        dist = np.linalg.norm(axis, axis=1)
        axis /= np.maximum(dist, 1e-300)[:, None]
        cone = np.arcsin(np.clip(radius / np.maximum(dist, 1e-300), 0.0, 1.0)) + half_texel
        cone[dist <= radius] = np.pi
        near = (axis @ dirs.T) >= np.cos(np.minimum(cone, np.pi))[:, None]
        lit = np.unpackbits(stored[sl], axis=1, count=cube.n_texels, bitorder="little").astype(bool)
        rows, texels = np.nonzero(near & lit)
        if len(rows) == 0:
            continue
        blocked = obj_backend.occluded(origins[sl][rows], dirs[texels])
        V = lit.copy()
        V[rows[blocked], texels[blocked]] = False
        out[sl] = np.packbits(V, axis=1, bitorder="little")
    return out
