"""The relight stage: render the scene under the recovered (or any lat-long) light, from the photo's
view or another one, with the fitted (or given) reflectance -> out/<name>.exr/png, and the error
against the photo or a reference image."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.errors import InputError

from .cache import SceneCache, file_digest, output_set, write_json_atomic
from .scenefiles import SceneFiles
from .stages import (Console, View, VisibilityOptions, _require, compare_to_photo, load_photo, photo_view,
                     visibility_stage)

RELIGHT_VERSION = 1


@dataclass(frozen=True)
class RelightOptions:
    light: Path | None = None  # a lat-long light; None = the light `solve` recovered
    rotate: float = 0.0  # degrees about +Z (phi -> phi + rotate)
    light_exposure: float = 0.0  # stops: the light is multiplied by 2**light_exposure
    view_pose: Path | None = None  # another view: its pose.json
    view_camera: Path | None = None  # and its camera.json (default: the scene's)
    reference: Path | None = None  # an image to compare with (default: the photo, for its own view and light)
    reference_mask: Path | None = None  # where to compare (white = compare)
    exposure: float | None = None  # PNG exposure in stops (None = automatic)
    name: str = "relight"

    def check(self) -> None:
        if not self.name or not all(c.isalnum() or c in "-_" for c in self.name):
            raise InputError(f"--name must be letters, digits, - or _, got {self.name!r}", None, "e.g. --name sunset")
        if not np.isfinite(self.rotate) or not np.isfinite(self.light_exposure):
            raise InputError("--rotate and --light-exposure must be finite numbers", None, "fix the option")
        if self.view_camera is not None and self.view_pose is None:
            raise InputError("--view-camera needs --view (the new view's pose.json)", None, "add --view POSE.json")


def view_of(scene: SceneFiles, opts: RelightOptions) -> View:
    if opts.view_pose is None:
        return photo_view(scene)
    camera = _require(opts.view_camera or scene.camera, "camera", "pass --view-camera or write camera.json")
    pose = _require(opts.view_pose, "pose", "pass the new view's pose.json with --view")
    name = hashlib.sha256((file_digest(camera) + file_digest(pose)).encode()).hexdigest()[:10]
    return View(camera, pose, None, f"view-{name}")


def _light(scene: SceneFiles, opts: RelightOptions, cube):
    """(N, 3) texel radiance on `cube`, and a description."""
    from pipelines import cubemap, images
    from pipelines import light as lt

    if opts.light is not None:
        env = images.read_latlong(_require(opts.light, "light", "pass a lat-long EXR/HDR with --light"))
        source = str(opts.light)
    else:
        path = scene.out / "coefficients.h5"
        _require(path, "solution", "run wavelight solve first (or pass --light)")
        try:
            texels, sol_cube, _ = lt.read_solution_light(path)
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(f"cannot read the solved light ({exc})", path, "rerun wavelight solve --force") from None
        light = cubemap.resample_cube(texels, sol_cube, cube, opts.rotate)
        return light * 2.0 ** opts.light_exposure, "recovered"
    env = cubemap.rotate_latlong(env, opts.rotate) * 2.0 ** opts.light_exposure
    return cubemap.latlong_to_cube(env, cube), source


class _Pixels:
    """The subset of samples compare_to_photo needs (their pixel coordinates)."""

    def __init__(self, pixel):
        self.pixel = pixel


def relight_stage(scene: SceneFiles, vis_opts: VisibilityOptions, opts: RelightOptions, material, material_path,
                  console: Console, force: bool = False, lock_wait: float = 600.0):
    from pipelines import images
    from pipelines import render as rd
    from pipelines import visibility as vis
    from pipelines.scene import read_camera

    opts.check()
    if opts.light is not None:
        _require(opts.light, "light", "pass a lat-long EXR/HDR with --light")
    else:
        _require(scene.out / "coefficients.h5", "solution", "run wavelight solve first, or pass --light")
    for path in (opts.reference, opts.reference_mask):
        if path is not None:
            _require(path, "reference", "check the path")
    view = view_of(scene, opts)
    camera = read_camera(_require(view.camera, "camera", "write camera.json or run wavelight calibrate"))
    reference = opts.reference
    same_light = opts.light is None and opts.rotate % 360 == 0 and opts.light_exposure == 0
    if reference is None and opts.view_pose is None and same_light:
        reference = scene.image  # the photo's own view and light: how well the model explains the photo
    mask_path = opts.reference_mask
    if mask_path is not None and reference is None:
        raise InputError("--reference-mask needs a reference (the photo is one only for its own view and light)",
                         None, "add --reference IMAGE")
    cache = SceneCache(scene.root)
    stage = "relight" if opts.name == "relight" else f"relight-{opts.name}"
    with cache.lock(lock_wait, console.say):
        vdec = visibility_stage(scene, vis_opts, console, force=False, lock_wait=lock_wait, view=view)
        inputs = {"light": opts.light if opts.light is not None else scene.out / "coefficients.h5",
                  "material": material_path, "reference": reference, "reference_mask": mask_path}
        params = {"rotate": opts.rotate, "light_exposure": opts.light_exposure, "exposure": opts.exposure,
                  "material": material.to_json(), "view": view.name or "photo"}
        d = cache.plan(stage, RELIGHT_VERSION, params, inputs, {view.stage: vdec.key}, force)
        console.decision(d)
        if not d.run:
            return d
        t0 = time.monotonic()
        ref_path = ref = mask = None  # read and checked before anything is written
        if reference is not None:
            if opts.view_pose is None and reference == scene.image:
                ref_path, ref = load_photo(scene, camera)
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
        data = vis.read_visibility(cache.dir / view.file)
        light, source = _light(scene, opts, data.cube)
        values = rd.render(data, light, material)
        img = rd.pixels_to_image(values, data.samples.pixel, camera.height, camera.width)
        with output_set():  # the stage's files replace the old ones together, or not at all
            out = scene.out
            outputs = [out / f"{opts.name}.exr", out / f"{opts.name}.png"]
            images.write_exr(outputs[0], img)
            images.write_png(outputs[1], img, opts.exposure)
            summary = {"light": source, "rotate_deg": opts.rotate, "light_exposure_stops": opts.light_exposure,
                       "view": view.name or "photo", "material": material.to_json(), "pixels": int(len(values)),
                       "resolution": data.cube.resolution}
            if ref is not None:
                keep = np.ones(len(values), bool)
                if mask is not None:
                    keep = mask[data.samples.pixel[:, 0], data.samples.pixel[:, 1]]
                outputs.append(out / f"{opts.name}_residual.png")
                versus = compare_to_photo(values[keep], ref, _Pixels(data.samples.pixel[keep]), camera, outputs[-1])
                summary.update(versus, reference=str(ref_path), reference_mask=str(mask_path) if mask_path else None)
            elif (out / f"{opts.name}_residual.png").exists():
                (out / f"{opts.name}_residual.png").unlink()  # it belonged to an earlier comparison
            outputs.append(out / f"{opts.name}.json")
            write_json_atomic(outputs[-1], summary)
        seconds = time.monotonic() - t0
        cache.record(d, outputs, seconds, summary)
        what = f"{'recovered light' if source == 'recovered' else Path(source).name}"
        if opts.rotate:
            what += f" turned {opts.rotate:g} deg"
        if opts.light_exposure:
            what += f" {opts.light_exposure:+g} stops"
        line = f"relight: {what}, {'photo view' if not view.name else view.name}, {len(values)} pixels"
        if reference is not None:
            line += (f": relative RMSE vs {Path(summary['reference']).name} {100 * summary['relative_rmse_vs_photo']:.2f} %"
                     f" over {summary['compared_pixels']} pixels")
        console.result(line + f" -> {cache.relative(outputs[1])}")
    return d
