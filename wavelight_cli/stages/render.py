"""`wavelight render`: the input view under a given lat-long light and material -> out/render.exr,
render.png, the light as the cube map sees it, and (with a photo) the error against it."""

from __future__ import annotations

from pathlib import Path

from pipelines.controllers.visibility import VisibilityOptions

from ..cache import Ran, SceneCache, Stage, run_stage
from ..console import Console
from ..outputs import read_rgba, view_png, write_light, write_residual, write_view
from ..scene import SceneFiles, load_photo, mesh_coverage, photo_view, require, scene_backend, scene_mesh
from .visibility import read_kept, visibility_stage

VERSION = 6  # 5, 6: the bright directions' neighbouring texels cast too (5), no longer (6); 4: render.exr has alpha, render.png the photo where nothing was rendered


def render_stage(scene: SceneFiles, vis_opts: VisibilityOptions, light_path: Path, material, exposure: float | None,
                 console: Console, force: bool = False, lock_wait: float = 600.0):
    from pipelines.controllers.render import render_view
    from pipelines.io import images
    from pipelines.io.scene_files import read_camera
    from pipelines.light import cubemap
    from pipelines.metrics import versus_photo

    light_path = require(Path(light_path), "pass a lat-long EXR/HDR with --light")
    camera = read_camera(scene.camera)
    photo_path, photo = load_photo(scene, camera) if scene.image is not None else (None, None)
    env = images.read_latlong(light_path)
    cache = SceneCache(scene.root)
    out = scene.out
    with cache.lock(lock_wait, console.say):  # one lock across visibility and render
        vis = visibility_stage(scene, vis_opts, console, lock_wait=lock_wait)
        stage = Stage("render", VERSION, {"material": material.to_json()}, {"light": light_path, "photo": photo_path},
                      {vis.stage: vis.key}, {"exposure": exposure})

        def work(d) -> Ran:
            data = read_kept(vis.path)
            light = cubemap.latlong_to_cube(env, data.cube)
            backend = scene_backend(scene_mesh(scene.mesh), vis_opts.backend)
            values, _ = render_view(data, light, material, backend)
            outputs = write_view(out, "render", values, data.samples.pixel, (camera.height, camera.width),
                                 None if photo is None else photo.pixels, exposure,
                                 cover=mesh_coverage(photo_view(scene), camera, backend))
            outputs += write_light(out, "render_light", light, data.cube)
            summary = {"pixels": int(len(values)), "mean_radiance": float(values.mean())}
            residual = out / "render_residual.png"
            if photo is None:
                from pipelines.io.files import output_set

                with output_set() as files:
                    files.discard(residual)  # it belonged to a photo that is gone
            else:
                rows, cols = data.samples.pixel[:, 0], data.samples.pixel[:, 1]
                usable = ~photo.saturated[rows, cols]
                outputs.append(write_residual(residual, values, photo.pixels[rows, cols], data.samples.pixel,
                                              (camera.height, camera.width), usable))
                summary.update(versus_photo(values, photo.pixels[rows, cols], usable))
                console.result(f"render: relative RMSE vs {photo_path.name}: "
                               f"{100 * summary['relative_rmse_vs_photo']:.2f} % over {summary['compared_pixels']} pixels")
            for p in outputs:
                console.say(f"render: wrote {cache.relative(p)}")
            return Ran(outputs, summary)

        def redisplay() -> list:
            return [view_png(out / "render.png", read_rgba(out / "render.exr"), None if photo is None else photo.pixels,
                             exposure)]

        return run_stage(cache, stage, console, force, work, redisplay)
