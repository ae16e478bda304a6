"""The insert stage: a virtual object composited into the photo by differential rendering under
the recovered (or a given) light -> out/<name>.exr/png and its shadow map."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.errors import InputError

from .cache import SceneCache, output_set, write_json_atomic
from .scenefiles import SceneFiles
from .stages import Console, _require, heat_map, load_photo

INSERT_VERSION = 1


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
    exposure: float | None = None
    name: str = "insert"

    def check(self) -> None:
        if not all(np.isfinite(self.at)):
            raise InputError("--at must be three finite numbers (world x y z)", None, "fix --at")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise InputError(f"--scale must be positive, got {self.scale}", None, "fix --scale")
        if self.radius is not None and not (np.isfinite(self.radius) and self.radius > 0):
            raise InputError(f"--radius must be positive, got {self.radius}", None, "fix --radius")
        if not self.name or not all(c.isalnum() or c in "-_" for c in self.name):
            raise InputError(f"--name must be letters, digits, - or _, got {self.name!r}", None, "e.g. --name ball")
        if not 1 <= self.supersample <= 8:
            raise InputError(f"--supersample must be 1..8, got {self.supersample}", None, "use 1 to 4")


def insert_stage(scene: SceneFiles, opts: InsertOptions, material, material_path, console: Console,
                 force: bool = False, lock_wait: float = 600.0):
    from pipelines import cubemap, images, raycast
    from pipelines import insert as ins
    from pipelines import light as lt
    from pipelines.scene import load_mesh, read_camera, read_pose

    from .stages import material_from_options

    opts.check()
    camera = read_camera(_require(scene.camera, "camera", "write camera.json or run wavelight calibrate"))
    pose = read_pose(_require(scene.pose, "pose", "write pose.json or run wavelight register"))
    photo_path, photo = load_photo(scene, camera)
    light_source = opts.light if opts.light is not None else scene.out / "coefficients.h5"
    _require(light_source, "light", "run wavelight solve first, or pass --light")
    obj_path = None if opts.object == "sphere" else _require(Path(opts.object), "object",
                                                               "pass a mesh file (OBJ, PLY, GLB, STL) or 'sphere'")
    if opts.object_material is not None:
        _require(opts.object_material, "material", "check the path")
    obj_material = material_from_options(opts.object_material, None, opts.object_kd or (
        None if opts.object_material else (0.8, 0.8, 0.8)), None, None)
    cache = SceneCache(scene.root)
    stage = "insert" if opts.name == "insert" else f"insert-{opts.name}"
    with cache.lock(lock_wait, console.say):
        inputs = {"camera.json": scene.camera, "pose.json": scene.pose, "photo": photo_path, "mesh": scene.mesh,
                  "object": obj_path, "light": light_source, "material": material_path,
                  "object_material": opts.object_material}
        params = {"object": "sphere" if obj_path is None else "file", "at": list(opts.at), "scale": opts.scale,
                  "rotate_z": opts.rotate_z, "radius": opts.radius, "object_kd": opts.object_kd,
                  "resolution": opts.resolution, "supersample": opts.supersample, "exposure": opts.exposure,
                  "material": material.to_json(), "object_material_json": obj_material.to_json()}
        d = cache.plan(stage, INSERT_VERSION, params, inputs, {}, force)
        console.decision(d)
        if not d.run:
            return d
        t0 = time.monotonic()
        mesh = load_mesh(scene.mesh)
        if obj_path is None:
            obj = ins.sphere(opts.radius or 0.1 * mesh.scale)
        else:
            obj = load_mesh(obj_path)
        obj = ins.place(obj, opts.at, opts.scale, opts.rotate_z)
        if opts.light is not None:
            cube = cubemap.CubeMap(opts.resolution or 32)
            light = cubemap.latlong_to_cube(images.read_latlong(opts.light), cube)
        else:
            try:
                light, cube, _ = lt.read_solution_light(light_source)
            except (OSError, ValueError, KeyError) as exc:
                raise InputError(f"cannot read the solved light ({exc})", light_source,
                                 "rerun wavelight solve --force") from None
            if opts.resolution and opts.resolution != cube.resolution:
                target = cubemap.CubeMap(opts.resolution, cube.hemisphere)
                light, cube = cubemap.resample_cube(light, cube, target), target
        if (obj.vertices @ pose.R[2] + pose.t[2]).max() <= 0:
            raise InputError("the object is behind the camera", None, "place it in front of the camera with --at")
        console.say(f"insert: {len(obj.faces)} object faces at {tuple(opts.at)}, R = {cube.resolution}")

        def progress(done, total):
            console.progress("insert", done, total)

        r = ins.insert(camera, pose, mesh, obj, light, cube, material, obj_material, photo.pixels,
                       lambda m: raycast.make_backend(m), opts.supersample, progress)
        if not r.object_mask.any():
            raise InputError(f"the object at {tuple(opts.at)} is not in the photo", None,
                             "place it where the camera sees it (--at, world coordinates)")
        with output_set():  # the stage's files replace the old ones together, or not at all
            out = scene.out
            outputs = [out / f"{opts.name}.exr", out / f"{opts.name}.png", out / f"{opts.name}_render.exr",
                       out / f"{opts.name}_shadow.png"]
            images.write_exr(outputs[0], r.composite)
            images.write_png(outputs[1], r.composite, opts.exposure)
            images.write_exr(outputs[2], r.with_object)
            images.write_png(outputs[3], heat_map(np.clip(-r.shadow, 0, None), 0.5), already_display=True)
            summary = {"object": opts.object, "at": list(opts.at), "object_pixels": int(r.object_mask.sum()),
                       "shadowed_pixels_5pct": int((r.shadow < -0.05).sum()), "darkest_shadow": float(r.shadow.min()),
                       "resolution": cube.resolution, "light": "recovered" if opts.light is None else str(opts.light),
                       "object_material": obj_material.to_json(), "scene_material": material.to_json()}
            outputs.append(out / f"{opts.name}.json")
            write_json_atomic(outputs[-1], summary)
        cache.record(d, outputs, time.monotonic() - t0, summary)
        console.result(f"insert: {summary['object_pixels']} object pixels, shadow (> 5 % darker) on "
                       f"{summary['shadowed_pixels_5pct']} pixels -> {cache.relative(outputs[1])}")
    return d
