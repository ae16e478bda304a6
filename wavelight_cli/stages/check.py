"""`wavelight check`: validate every file the scene folder has, writing nothing."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipelines.controllers.visibility import VisibilityOptions
from pipelines.errors import InputError

from ..scene import IMAGE_NAMES, SceneFiles, load_photo, photo_view, require
from .visibility import load_samples


def check_scene(scene: SceneFiles, opts: VisibilityOptions, parts: bool = True, texture: bool = True) -> list[str]:
    """One summary line per file of the scene folder; bad files raise InputError. `parts`, `texture`:
    whether solve reads the mesh's parts and their textures (its --single-material, --no-texture)."""
    from pipelines.io import images
    from pipelines.io.scene_files import MESH_SUFFIXES, load_mesh, read_camera, read_correspondences, read_pose
    from pipelines.model.parts import scene_parts

    lines = []
    camera = read_camera(require(scene.camera, "write camera.json or run wavelight calibrate"))
    lines.append(f"camera.json: {camera.width}x{camera.height}, fx {camera.fx:g}, fy {camera.fy:g}")
    if scene.image is not None:
        path, img = load_photo(scene, camera)
        depth = "float" if img.bit_depth == "float" else f"{img.bit_depth}-bit"
        others = [n for n in IMAGE_NAMES if n != path.name and (scene.root / n).exists()]
        lines.append(f"{path.name}: {img.width}x{img.height}, {depth}, {int(img.saturated.sum())} saturated pixels"
                     + (f" ({', '.join(others)} also here, not used: {path.name} comes first)" if others else ""))
    else:
        lines.append("photo: none (needed by solve)")
    if scene.correspondences.exists():
        uv, _ = read_correspondences(scene.correspondences)
        lines.append(f"correspondences.csv: {len(uv)} points")
    mesh = load_mesh(scene.mesh)
    unused = [f"mesh{e}" for e in MESH_SUFFIXES
              if (scene.root / f"mesh{e}").is_file() and f"mesh{e}" != scene.mesh.name]
    notes = list(mesh.notes) + ([f"{', '.join(unused)} also here, not used: {scene.mesh.name} comes first"]
                                if unused else [])
    lines.append(f"{scene.mesh.name}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces"
                 + (f" ({'; '.join(notes)})" if notes else ""))
    try:  # (a missing .mtl or texture, wrong UVs: as solve refuses them)
        sp = scene_parts(mesh, scene.mesh, scene.root, use_texture=texture) if parts else None
    except InputError as exc:
        if exc.fix is None or "--no-texture" not in exc.fix:
            raise
        raise InputError(exc.problem, exc.path, f"{exc.fix} (of solve; or [solve] no-texture = true in "
                         "scene.toml)") from None
    if sp is not None:
        lines.append("parts: " + ", ".join(
            p.name + (f" (texture {Path(p.texture.path).name})" if p.texture is not None else "") for p in sp.parts))
    if scene.mask is not None:
        mask = images.read_mask(scene.mask)
        if mask.shape != (camera.height, camera.width):
            raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]}, camera.json says "
                             f"{camera.width}x{camera.height}", scene.mask, "use a mask of the photo's size")
        if not mask.any():
            raise InputError("mask is empty (no white pixel)", scene.mask, "paint the pixels to use white")
        lines.append(f"mask.png: {int(mask.sum())} pixels")
    if scene.pose.exists():
        read_pose(scene.pose)
        opts.check()
        _, _, _, samples, diag = load_samples(scene, opts, photo_view(scene))
        lines.append(f"pose.json: {diag['used']} used pixels of {diag['hit']} that see the mesh")
        if scene.image is not None and len(samples):
            rows, cols = samples.pixel[:, 0], samples.pixel[:, 1]
            if not np.any(img.pixels[rows, cols] > 0):  # (as solve refuses it)
                raise InputError(f"the photo is black (nothing above 0: negative values read as 0) over all "
                                 f"{len(samples)} used pixels: there is no light to recover", path,
                                 "check the exposure, the lens cap, the mask and that this is the right photo")
    else:
        lines.append("pose.json: none (run wavelight register)")
    return lines
