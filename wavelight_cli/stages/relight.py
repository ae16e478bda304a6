"""`wavelight relight`: the scene under the recovered (or any lat-long) light, from the photo's view
or another one, with the fitted (or given) reflectance -> out/NAME.exr/png, NAME.json and the error
against the photo or a reference image."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.controllers.visibility import VisibilityOptions
from pipelines.errors import InputError, OptionError

from ..cache import Ran, SceneCache, Stage, run_stage
from ..console import Console
from ..outputs import read_rgba, view_png, write_json, write_residual, write_view
from ..scene import (SceneFiles, View, load_view_photo, mesh_coverage, other_view, photo_view, require,
                     scene_albedo, scene_backend, scene_mesh, scene_views, solved_light, view_gain, view_named)
from .visibility import read_kept, visibility_stage

VERSION = 8  # 8: a named view at its own exposure (solve --view-exposure); 7: --view NAME (a view of the scene's: its photo behind and compared); 5, 6: the bright directions' neighbouring texels cast too (5), no longer (6); 4: each part's material and texture (reflectance.json's parts); 3: NAME.exr has alpha; NAME.png at the photo's exposure, the photo (or transparency) where nothing was rendered


@dataclass(frozen=True)
class RelightOptions:
    light: Path | None = None  # a lat-long light; None = the light `solve` recovered
    rotate: float = 0.0  # degrees about +Z (phi -> phi + rotate)
    light_exposure: float = 0.0  # stops: the light is multiplied by 2**light_exposure
    view_pose: Path | None = None  # another view: its pose.json, or a view of the scene's by name (views/NAME, main)
    view_camera: Path | None = None  # and its camera.json (default: the scene's)
    reference: Path | None = None  # an image to compare with (default: the photo, for its own view and light)
    reference_mask: Path | None = None  # where to compare (white = compare)
    exposure: float | None = None  # PNG exposure in stops (None = the photo's, `outputs.photo_exposure`)
    name: str = "relight"

    def check(self) -> None:
        if not self.name or not all(c.isalnum() or c in "-_" for c in self.name):
            raise OptionError(f"--name must be letters, digits, - or _, got {self.name!r}", None, "e.g. --name sunset")
        if not np.isfinite(self.rotate) or not np.isfinite(self.light_exposure):
            raise OptionError("--rotate and --light-exposure must be finite numbers", None, "fix the option")
        if self.view_camera is not None and self.view_pose is None:
            raise OptionError("--view-camera needs --view (the new view's pose.json)", None, "add --view POSE.json")


def _light(scene: SceneFiles, opts: RelightOptions, cube):
    """(N, 3) texel radiance on `cube`, and a description."""
    from pipelines.io import images
    from pipelines.light import cubemap

    if opts.light is not None:
        env = images.read_latlong(require(opts.light, "pass a lat-long EXR/HDR with --light"))
        env = cubemap.rotate_latlong(env, opts.rotate) * 2.0 ** opts.light_exposure
        return cubemap.latlong_to_cube(env, cube), str(opts.light)
    texels, sol_cube, _ = solved_light(scene)
    light = cubemap.resample_cube(texels, sol_cube, cube, opts.rotate)
    return light * 2.0 ** opts.light_exposure, "recovered"


def _display_photos(scene: SceneFiles, opts: RelightOptions, camera, loaded=None):
    """(the photo behind the render: the scene's photo for its own view, else None; the photo whose
    exposure the PNG takes: the scene's, None without one). `loaded`: the photo when already read."""
    from pipelines.io import images

    view = relight_view(scene, opts)
    if view.image is not None:  # a photo of the scene's: behind the render
        photo = loaded if loaded is not None else load_view_photo(view, camera)[1]
        return photo.pixels, photo.pixels
    if scene.image is None:
        return None, None
    return None, images.read_image(scene.image).pixels


def relight_view(scene: SceneFiles, opts: RelightOptions) -> View:
    """The view `--view` names: none, the photo's; a view of the scene's by its name (a folder under
    views/, or main): its camera, pose and photo; else another view's pose.json (no photo)."""
    if opts.view_pose is None:
        return photo_view(scene)
    arg = str(opts.view_pose)
    if not Path(arg).is_file() and "/" not in arg and not arg.endswith(".json"):
        names = [v.label for v in scene_views(scene)]
        if arg not in names:
            raise OptionError(f"--view {arg}: no such file, and the scene has no view of that name (its views: "
                              f"{', '.join(names)})", None, "pass a view's pose.json, or the name of a folder under "
                              "views/ (main: the scene folder's own photo)")
        if opts.view_camera is not None:
            raise OptionError(f"--view-camera goes with a pose.json; the view {arg!r} has its own camera", None,
                              "leave out --view-camera")
        return view_named(scene, arg)
    return other_view(scene, opts.view_pose, opts.view_camera)


def relight_stage(scene: SceneFiles, vis_opts: VisibilityOptions, opts: RelightOptions, material, material_path,
                  console: Console, force: bool = False, lock_wait: float = 600.0):
    from pipelines.controllers.render import render_view
    from pipelines.io import images
    from pipelines.io.scene_files import read_camera, read_pose
    from pipelines.metrics import versus_photo
    from pipelines.model.parts import parts_files

    opts.check()
    if opts.light is not None:
        require(opts.light, "pass a lat-long EXR/HDR with --light")
    else:
        require(scene.out / "coefficients.h5", "run wavelight solve first, or pass --light")
    for path in (opts.reference, opts.reference_mask):
        if path is not None:
            require(path, "check the path")
    view = relight_view(scene, opts)
    camera = read_camera(require(view.camera, "write camera.json or run wavelight calibrate"))
    reference = opts.reference
    same_light = opts.light is None and opts.rotate % 360 == 0 and opts.light_exposure == 0
    own_photo = view.image is not None  # the view of one of the scene's photos
    if reference is None and own_photo and same_light:
        reference = view.image  # a photo's own view and light: how well the model explains that photo
    mask_path = opts.reference_mask
    if mask_path is not None and reference is None:
        raise OptionError("--reference-mask needs a reference (a photo is one only for its own view and light)",
                         None, "add --reference IMAGE")
    cache = SceneCache(scene.root)
    name = "relight" if opts.name == "relight" else f"relight-{opts.name}"
    out = scene.out
    with cache.lock(lock_wait, console.say):
        vis = visibility_stage(scene, vis_opts, console, lock_wait=lock_wait, view=view)
        upstream = {vis.stage: vis.key}
        if opts.light is None:
            upstream["solve"] = cache.key_of("solve") or "none"
        inputs = {"light": opts.light if opts.light is not None else scene.out / "coefficients.h5",
                  "material": material_path, "reference": reference, "reference_mask": mask_path,
                  "photo": scene.image, "view_photo": view.image,  # the PNG's backdrop and exposure
                  **parts_files(scene.mesh, scene.root)}  # the parts' materials and textures
        params = {"rotate": opts.rotate, "light_exposure": opts.light_exposure, "material": material.to_json(),
                  "view": view.name}
        stage = Stage(name, VERSION, params, inputs, upstream, {"exposure": opts.exposure})

        def work(d) -> Ran:
            ref_path = ref = mask = None  # read and checked before anything is written
            if reference is not None:
                if own_photo and Path(reference) == Path(view.image):
                    ref_path, ref = load_view_photo(view, camera)
                else:
                    ref_path, ref = Path(reference), images.read_image(reference)
                    if (ref.width, ref.height) != (camera.width, camera.height):
                        raise InputError(f"reference is {ref.width}x{ref.height}, the view's camera is "
                                         f"{camera.width}x{camera.height}", ref_path, "pass the image taken from that view")
                if mask_path is not None:
                    mask = images.read_mask(mask_path)
                    if mask.shape != (camera.height, camera.width):
                        raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]}, the view is "
                                         f"{camera.width}x{camera.height}", mask_path, "use a mask of the view's size")
            data = read_kept(vis.path)
            light, source = _light(scene, opts, data.cube)
            mesh = scene_mesh(scene.mesh)
            backend = scene_backend(mesh, vis_opts.backend)
            values, _ = render_view(data, light, material, backend,
                                    scene_albedo(scene, material_path, mesh, camera, read_pose(view.pose)))
            gain = view_gain(scene, view) if opts.light is None else 1.0
            values = values * gain  # (another photo of the scene: at its own exposure, as solve fitted it)
            backdrop, scale_ref = _display_photos(scene, opts, camera, ref if own_photo and ref_path == view.image else None)
            outputs = write_view(out, opts.name, values, data.samples.pixel, (camera.height, camera.width), backdrop,
                                 opts.exposure, scale_ref, mesh_coverage(view, camera, backend))
            summary = {"light": source, "rotate_deg": opts.rotate, "light_exposure_stops": opts.light_exposure,
                       "view": view.name, "view_exposure": gain, "material": material.to_json(),
                       "pixels": int(len(values)),
                       "resolution": data.cube.resolution}
            residual = out / f"{opts.name}_residual.png"
            if ref is not None:
                px = data.samples.pixel
                keep = np.ones(len(values), bool) if mask is None else mask[px[:, 0], px[:, 1]]
                usable = keep & ~ref.saturated[px[:, 0], px[:, 1]]
                reference_values = ref.pixels[px[:, 0], px[:, 1]]
                outputs.append(write_residual(residual, values, reference_values, px, (camera.height, camera.width),
                                              usable))
                summary.update(versus_photo(values, reference_values, usable), reference=str(ref_path),
                               reference_mask=str(mask_path) if mask_path else None)
            else:
                from pipelines.io.files import output_set

                with output_set() as files:
                    files.discard(residual)  # it belonged to an earlier comparison
            outputs.append(write_json(out / f"{opts.name}.json", summary))
            what = "recovered light" if source == "recovered" else Path(source).name
            if opts.rotate:
                what += f" turned {opts.rotate:g} deg"
            if opts.light_exposure:
                what += f" {opts.light_exposure:+g} stops"
            seen = "photo view" if view.name == "photo" else f"view {view.label}" if own_photo else view.name
            line = f"relight: {what}, {seen}, {len(values)} pixels"
            if ref is not None:
                line += (f": relative RMSE vs {Path(summary['reference']).name} "
                         f"{100 * summary['relative_rmse_vs_photo']:.2f} % over {summary['compared_pixels']} pixels")
            summary["line"] = line + f" -> {cache.relative(outputs[1])}"
            return Ran(outputs, summary)

        def redisplay() -> list:
            backdrop, scale_ref = _display_photos(scene, opts, camera)
            return [view_png(out / f"{opts.name}.png", read_rgba(out / f"{opts.name}.exr"), backdrop, opts.exposure,
                             scale_ref)]

        d = run_stage(cache, stage, console, force, work, redisplay)
        rec = cache.record_of(name) or {}
    if "line" in rec.get("summary", {}):
        console.result(rec["summary"]["line"])
    return d
