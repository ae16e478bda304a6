"""`wavelight insert`: a virtual object composited into the photo by differential rendering under
the recovered (or a given) light -> out/NAME.exr/png, NAME_render.exr, NAME_shadow.png, NAME.json."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.controllers.visibility import DEFAULT_RESOLUTION, VisibilityOptions
from pipelines.errors import InputError, OptionError

from ..cache import Ran, SceneCache, Stage, run_stage
from ..console import Console
from ..outputs import photo_exposure, write_heat_png, write_json
from ..scene import (SceneFiles, load_view_photo, material_from_options, photo_view, require, scene_albedo,
                     solved_light, view_gain, view_named)
from .visibility import read_kept, visibility_stage

VERSION = 6  # 6: a named view at its own exposure (solve --view-exposure); 5: --view NAME (one of the scene's photos); 4: the scene's parts and textures (reflectance.json's parts); 3: NAME_shadow.png records its scale; NAME.png at the photo's exposure
SHADOW_WHITE = 0.5  # NAME_shadow.png: white = 50 % darker


@dataclass(frozen=True)
class InsertOptions:
    object: str  # a mesh file, or "sphere"
    at: tuple[float, float, float]
    scale: float = 1.0
    rotate_z: float = 0.0
    radius: float | None = None  # sphere: radius (default 10 % of the scene's size)
    object_material: Path | None = None
    object_kd: tuple[float, float, float] | None = None
    light: Path | None = None
    resolution: int | None = None
    supersample: int = 1
    exposure: float | None = None  # PNG exposure in stops (None: the photo's, `outputs.photo_exposure`)
    name: str = "insert"
    view: str | None = None  # one of the scene's photos by name (views/NAME, main); None: the main photo

    def check(self) -> None:
        if not all(np.isfinite(self.at)):
            raise OptionError("--at must be three finite numbers (world x y z)", None, "fix --at")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise OptionError(f"--scale must be positive, got {self.scale}", None, "fix --scale")
        if self.object_kd is not None and not all(np.isfinite(v) and v >= 0 for v in self.object_kd):
            raise OptionError(f"--object-kd must be 3 finite values >= 0, got {' '.join(map(str, self.object_kd))}",
                              None, "fix --object-kd")
        if self.radius is not None and not (np.isfinite(self.radius) and self.radius > 0):
            raise OptionError(f"--radius must be positive, got {self.radius}", None, "fix --radius")
        if not self.name or not all(c.isalnum() or c in "-_" for c in self.name):
            raise OptionError(f"--name must be letters, digits, - or _, got {self.name!r}", None, "e.g. --name ball")
        if not 1 <= self.supersample <= 8:
            raise OptionError(f"--supersample must be 1..8, got {self.supersample}", None, "use 1 to 4")


def insert_stage(scene: SceneFiles, opts: InsertOptions, material, material_path, console: Console,
                 force: bool = False, lock_wait: float = 600.0, visibility: str = "adaptive"):
    from pipelines.geometry import mesh as meshes
    from pipelines.geometry import raycast
    from pipelines.io import images
    from pipelines.io.scene_files import load_mesh, read_camera, read_pose
    from pipelines.light import cubemap
    from pipelines.model import insert as ins
    from pipelines.model.parts import parts_files

    opts.check()
    view = photo_view(scene) if opts.view is None else view_named(scene, opts.view)
    camera = read_camera(require(view.camera, "write camera.json or run wavelight calibrate"))
    pose = read_pose(require(view.pose, "write pose.json or run wavelight register"))
    photo_path, photo = load_view_photo(view, camera)
    light_source = opts.light if opts.light is not None else scene.out / "coefficients.h5"
    require(light_source, "run wavelight solve first, or pass --light")
    obj_path = None if opts.object == "sphere" else require(Path(opts.object), "pass a mesh file (OBJ, PLY, GLB, STL) "
                                                                                "or 'sphere'")
    if opts.object_material is not None:
        require(opts.object_material, "check the path")
    try:
        obj_material = material_from_options(opts.object_material, None, opts.object_kd or (
            None if opts.object_material else (0.8, 0.8, 0.8)), None, None)
    except OptionError as exc:  # (its value is --object-kd's, not the scene material's --kd)
        raise OptionError(exc.problem, None, "fix --object-kd (3 values >= 0)") from None
    if opts.light is not None:
        resolution = opts.resolution or DEFAULT_RESOLUTION
    else:
        _, solved_cube, _ = solved_light(scene)
        resolution = opts.resolution or solved_cube.resolution
    png_exposure = opts.exposure if opts.exposure is not None else photo_exposure(photo.pixels)
    cache = SceneCache(scene.root)
    name = "insert" if opts.name == "insert" else f"insert-{opts.name}"
    out = scene.out
    with cache.lock(lock_wait, console.say):
        vis_opts = VisibilityOptions(resolution=resolution, method=visibility)
        vis = visibility_stage(scene, vis_opts, console, lock_wait=lock_wait, view=view)
        upstream = {vis.stage: vis.key}
        if opts.light is None:
            upstream["solve"] = cache.key_of("solve") or "none"
        inputs = {"object": obj_path, "light": light_source, "material": material_path,
                  "object_material": opts.object_material, **parts_files(scene.mesh, scene.root)}
        params = {"object": "sphere" if obj_path is None else "file", "at": list(opts.at), "scale": opts.scale,
                  "rotate_z": opts.rotate_z, "radius": opts.radius, "object_kd": opts.object_kd,
                  "resolution": resolution, "supersample": opts.supersample, "material": material.to_json(),
                  "object_material_json": obj_material.to_json(), "view": view.name}
        stage = Stage(name, VERSION, params, {"photo": photo_path, **inputs}, upstream, {"exposure": opts.exposure})

        def work(d) -> Ran:
            mesh = load_mesh(scene.mesh)
            obj = meshes.sphere(opts.radius or 0.1 * mesh.scale) if obj_path is None else load_mesh(obj_path)
            obj = meshes.place(obj, opts.at, opts.scale, opts.rotate_z)
            cube = cubemap.CubeMap(resolution)
            if opts.light is not None:
                light = cubemap.latlong_to_cube(images.read_latlong(opts.light), cube)
            else:
                texels, solved_cube, _ = solved_light(scene)
                light = texels if solved_cube == cube else cubemap.resample_cube(texels, solved_cube, cube)
                light = light * view_gain(scene, view)  # (another photo: at its own exposure, as solve fitted it)
            if (obj.vertices @ pose.R[2] + pose.t[2]).max() <= 0:
                raise InputError("the object is behind the camera", None, "place it in front of the camera with --at")
            console.say(f"insert: {len(obj.faces)} object faces at {tuple(opts.at)}, R = {cube.resolution}")
            scene_vis = read_kept(vis.path)
            task = console.task("insert", "casting", 1, "pixel blocks")

            def progress(done, total):
                task.total = total
                task.update(done)

            r = ins.insert(camera, pose, mesh, obj, light, cube, material, obj_material, photo.pixels,
                           lambda m: raycast.make_backend(m), scene_vis, opts.supersample, progress,
                           scene_albedo(scene, material_path, mesh, camera, pose))
            task.close()
            if not r.object_mask.any():
                raise InputError(f"the object at {tuple(opts.at)} is not in the photo", None,
                                 "place it where the camera sees it (--at, world coordinates)")
            outputs = [images.write_exr(out / f"{opts.name}.exr", r.composite),
                       images.write_png(out / f"{opts.name}.png", r.composite, png_exposure),
                       images.write_exr(out / f"{opts.name}_render.exr", r.with_object),
                       write_heat_png(out / f"{opts.name}_shadow.png", np.clip(-r.shadow, 0, None), SHADOW_WHITE,
                                      "relative darkening the object casts on the known geometry",
                                      "fraction of the radiance without the object")]
            summary = {"object": opts.object, "at": list(opts.at), "object_pixels": int(r.object_mask.sum()),
                       "shadowed_pixels_5pct": int((r.shadow < -0.05).sum()), "darkest_shadow": float(r.shadow.min()),
                       "resolution": cube.resolution, "light": "recovered" if opts.light is None else str(opts.light),
                       "object_material": obj_material.to_json(), "scene_material": material.to_json(),
                       "view": view.label, "photo": str(photo_path)}
            outputs.append(write_json(out / f"{opts.name}.json", summary))
            seen = "" if opts.view is None else f"view {view.label}: "
            summary["line"] = (f"insert: {seen}{summary['object_pixels']} object pixels, shadow (> 5 % darker) on "
                               f"{summary['shadowed_pixels_5pct']} pixels -> {cache.relative(outputs[1])}")
            return Ran(outputs, summary)

        def redisplay() -> list:
            img = images.read_image(out / f"{opts.name}.exr").pixels
            return [images.write_png(out / f"{opts.name}.png", img, png_exposure)]

        d = run_stage(cache, stage, console, force, work, redisplay)
        rec = cache.record_of(name) or {}
    if "line" in rec.get("summary", {}):
        console.result(rec["summary"]["line"])
    return d
