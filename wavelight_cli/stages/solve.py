"""`wavelight solve` and `wavelight compare`: plan, run the controller, write, record.

solve -> out/light_latlong.exr, light_cross.exr/png, observability.png, coefficients.h5,
relit.exr/png, residual.png, robust_weights.png, reflectance.json, solve_report.json; compare -> out/compare.json,
compare.md, compare.png, compare_lights.png, compare_lights.h5. The numerics and their policy are
in `pipelines.controllers.solve` / `.compare`.
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from pipelines.controllers.solve import ReflectanceOptions, SolveOptions, material_text
from pipelines.controllers.visibility import VisibilityOptions
from pipelines.errors import option_errors

from ..cache import Ran, SceneCache, Stage, run_stage
from ..console import Console
from ..outputs import (jsonable, read_rgba, view_png, write_cross_heat_png, write_json, write_light, write_residual,
                       write_robust_weights, write_view)
from ..scene import (MAIN_VIEW, SceneFiles, load_photo, load_view_photo, mesh_coverage, require, scene_backend,
                     scene_mesh, scene_views)
from .visibility import read_kept, visibility_stage

VERSION = 15  # 4: the sampled route; reflectance rounds compare their own held-out errors; 5: relit.exr has
#   alpha, relit.png the photo where nothing was rendered and the photo's exposure; 6: levels chosen again
#   after the exact recast; 7: sample heads spread over the image when every pixel is taken, level fit errors
#   from the rows, forced specular rounds all on the same rows; auto also considers the microfacet `plastic`
#   (candidates, decision), plastic fields in reflectance.json; 8: several views (views/NAME) under one light,
#   their rows together, whole-view hold-out from 3 views, per-view results (solve_report.json "views",
#   out/views/NAME/); 9: several parts and textures (the mesh's materials, materials.toml: per-part kd fitted
#   with the light), reflectance.json's `parts`; 10: auto gives a significant probe that its own held-out rows
#   do not reward its own light before it stays Lambertian; 11: (a coarse light's bright directions cast
#   before the solve, tried in 10, taken out again: it moved glossy fits to worse optima); 12: the exact recast
#   corrects the system in place (the rows it changed; the same light), solve_report.json's exact_directions.changed;
#   13: the robust pass (--robust: rows the model cannot explain down-weighted; --clipped bound: clipped pixels
#   as lower bounds), solve_report.json's `robust`; 14: reflectance rounds chosen by held-out error,
#   --view-exposure, views' exposure and gain_left; 15: the robust pass judges a pixel near an edge by its
#   distance to the prediction's range there (not the range added to the noise), at most 5 % down-weighted,
#   a peak or trough of the prediction allowed its range's width beyond it, and auto chooses its model again
#   under the weights
COMPARE_VERSION = 7  # 4: the bases solved on the system solve ends on (bright directions cast exactly); 5, 6: as solve
#   10, 11; 7: as solve 12


class ConsoleProgress:
    """A controller's progress, printed as the stage's lines."""

    def __init__(self, console: Console, stage: str):
        self.console, self.stage, self._tasks = console, stage, {}

    def note(self, message: str) -> None:
        self.console.say(f"{self.stage}: {message}")

    def advance(self, what: str, done: int, total: int, unit: str = "") -> None:
        task = self._tasks.get(what)
        if task is None:
            task = self._tasks[what] = self.console.task(self.stage, what, total, unit or "steps")
        task.update(done)
        if done >= total:
            task.close()
            self._tasks.pop(what, None)


def _inputs(scene: SceneFiles, vis_opts: VisibilityOptions, opts: SolveOptions):
    """Check the options and load the camera and photo: (visibility options, camera, photo path, photo)."""
    from pipelines.io.scene_files import read_camera

    if opts.exact:
        vis_opts = replace(vis_opts, method="exact")
    vis_opts.check()
    with option_errors():  # the light and solve options' checks look at the options only
        opts.check(vis_opts.resolution, vis_opts.hemisphere)
    camera = read_camera(scene.camera)
    photo_path, photo = load_photo(scene, camera, True if opts.linear_input else None)
    return vis_opts, camera, photo_path, photo


def solve_stage(scene: SceneFiles, vis_opts: VisibilityOptions, opts: SolveOptions, material, exposure,
                console: Console, force: bool = False, lock_wait: float = 600.0,
                refl: ReflectanceOptions = ReflectanceOptions("given"), given: set | None = None,
                select: str | None = None, parts=None):
    """Recover the light (and the reflectance, by `refl`) from the scene's photos (`select`: a
    comma-separated subset of the views, default all); see the module docstring for the outputs."""
    from pipelines.controllers import solve as ctl
    from pipelines.controllers import views as mv
    from pipelines.io import light_file
    from pipelines.io.scene_files import read_camera
    from pipelines.model.parts import PartsOptions, parts_files

    given = given or set()
    parts = parts or PartsOptions()
    with option_errors():  # --reflectance and the fit's start (--shininess)
        refl.check()
        start = refl.start(material, given) if refl.fits else None
    views = scene_views(scene, select)
    params = {**opts.cache_params(), "reflectance": refl.cache_params(), "material": material.to_json(),
              "views": [v.label for v in views]}
    if start is not None:
        params["start"] = start.to_json()
    params["parts"] = parts.cache_params()
    vis_opts, camera, photo_path, photo = _inputs(scene, vis_opts, opts)
    cameras, photos = [camera], [(photo_path, photo)]
    for v in views[1:]:
        cameras.append(read_camera(require(v.camera, "write the view's camera.json (or the scene's shared one)")))
        photos.append(load_view_photo(v, cameras[-1], True if opts.linear_input else None))
    part_inputs = parts_files(scene.mesh, scene.root) if parts.parts else {}
    # a missing .mtl or texture (None in part_inputs) is refused before visibility is cast and cached:
    # the parts are then read now (`scene_parts` says what is missing), else only when the stage runs
    missing = [k for k, v in part_inputs.items() if v is None and (k == "mtl" or (k.startswith("texture ")
                                                                                  and parts.texture))]
    early = [_scene_parts(scene, parts)] if missing else []
    cache = SceneCache(scene.root)
    out = scene.out
    with cache.lock(lock_wait, console.say):
        vis_runs = [visibility_stage(scene, vis_opts, console, lock_wait=lock_wait, view=v) for v in views]
        inputs = {("photo" if v.label == MAIN_VIEW else f"photo:{v.label}"): p for v, (p, _) in zip(views, photos)}
        inputs.update(part_inputs)
        stage = Stage("solve", VERSION, params, inputs, {r.stage: r.key for r in vis_runs}, {"exposure": exposure})

        def work(d) -> Ran:
            t0 = time.monotonic()
            datas = [read_kept(r.path) for r in vis_runs]
            data, layout = mv.combine(datas, [v.label for v in views], [(c.height, c.width) for c in cameras])
            stacked = mv.stacked_photo([ph for _, ph in photos], layout)
            held, holdout = mv.holdout(layout, opts.held_out, MAIN_VIEW)
            mesh = scene_mesh(scene.mesh)  # (read once when the visibility stage ran in this process)
            albedo = (_pixel_albedo(early[0] if early else _scene_parts(scene, parts), mesh, data, views, cameras,
                                    layout, console, parts.shared_ks) if parts.parts else None)
            gains, exposure_info = np.ones(len(views)), None
            if len(views) > 1 and opts.view_exposure == "fit":  # (photos of another exposure: their gains first)
                gains, exposure_info = mv.fit_exposures(data, *ctl.prepare_photo(data, stacked, opts, photo_path)[:2],
                                                        layout, albedo)
                stacked = mv.apply_exposures(stacked, layout, gains)
                console.say("solve: exposure of each photo relative to main (fitted): " + ", ".join(
                    f"{v.label} {g:.4g}" for v, g in zip(views, gains)))
            backend = scene_backend(mesh, vis_opts.backend)
            result = ctl.solve_scene(data, stacked, material, opts, refl, given,
                                     backend if data.method == "adaptive" else None, photo_path,
                                     ConsoleProgress(console, "solve"), adaptive=data.method == "adaptive",
                                     held_out=held, albedo=albedo)
            m, sol, cube = result.material, result.solution, data.cube
            result.context = None  # (the light's system: its transport rows go before the outputs are drawn, memory)
            outputs = write_light(out, "light", sol.light, cube, unobservable=result.unobservable)
            outputs.append(write_cross_heat_png(out / "observability.png", result.observability, cube, 1.0,
                                                "sqrt(G_ii / max G_ii): how strongly the used pixels respond to "
                                                "the texel's radiance; black = unobservable", "fraction of the best"))
            outputs.append(out / "coefficients.h5")
            light_file.write_solution(outputs[-1], sol, cube, result.unobservable, {"material": str(m.to_json())})
            values, usable, held_rows = ctl.prepare_photo(data, stacked, opts, photo_path, held)
            by_view = per_view = None
            if len(views) > 1:
                resp = mv.responses(result.vis, layout)
                by_view = mv.observability_by_view(resp, layout)
                per_view = mv.per_view_errors(result, values, usable, held_rows, layout, holdout, opts.bounds)
                left = mv.final_gains(result.relit, values, usable, layout)
                for k, v in enumerate(views):
                    per_view[v.label]["exposure"] = float(gains[k])
                    per_view[v.label]["gain_left"] = float(left[k])
                off = [f"{v.label} {left[k]:.3f}" for k, v in enumerate(views) if abs(left[k] - 1) > mv.EXPOSURE_WARN]
                if off:
                    console.say("solve: warning: the final light predicts some photos brighter or darker than they are "
                                f"(least-squares gain, main = 1: {', '.join(off)})" + (
                                    "; photos of different exposure? try --view-exposure fit"
                                    if opts.view_exposure == "same" else ""))
            for k, (v, cam, (_, ph)) in enumerate(zip(views, cameras, photos)):
                sl = layout.rows(k)
                pix = layout.image_pixels(data.samples.pixel, k)
                vdir = out if k == 0 else out / "views" / v.label
                cover = mesh_coverage(v, cam, backend)
                relit_k = result.relit[sl] * gains[k]  # (at the view's own exposure, as its photo)
                outputs += write_view(vdir, "relit", relit_k, pix, (cam.height, cam.width), ph.pixels,
                                      exposure, cover=cover)
                outputs.append(write_residual(vdir / "residual.png", relit_k, ph.pixels[pix[:, 0], pix[:, 1]],
                                              pix, (cam.height, cam.width), ~ph.saturated[pix[:, 0], pix[:, 1]]))
                if result.robust_weights is not None:
                    outputs.append(write_robust_weights(vdir / "robust_weights.png", result.robust_weights[sl], pix,
                                                        (cam.height, cam.width)))
                else:  # (--no-robust, --exact: an earlier run's map would tell of weights this light never had)
                    (vdir / "robust_weights.png").unlink(missing_ok=True)
                if by_view is not None:
                    top = max(float(resp.sum(axis=0).max(initial=0.0)), 1e-300)
                    outputs.append(write_cross_heat_png(vdir / "observability_view.png", np.sqrt(resp[k] / top), cube,
                                                        1.0, "this view's pixels alone (kd = 1), on the scale of "
                                                        "all views together; black = unobservable",
                                                        "fraction of the best of all views"))
            reflectance = {"format": "wavelight-reflectance-1", **result.reflectance.summary(),
                           "scale_ambiguity": ctl.SCALE_NOTE}
            if albedo is not None:
                from pipelines.model.parts import parts_summary

                sp = albedo.parts
                reflectance["parts"] = parts_summary(albedo, mesh, m.kd, specular_model=m.specular, material_ks=m.ks)
                reflectance["parts_options"] = parts.cache_params()
                reflectance["reference_part"] = {"name": sp.names[sp.reference], "chosen_by": sp.reference_source}
                reflectance["scale_ambiguity"] = (
                    f"light x albedo is only known as a product: the reference part {sp.names[sp.reference]!r} keeps "
                    "its start colour (its texture or .mtl Kd, times kd), the light takes the rest; the other parts' "
                    "albedo relative to it (relative_to_reference) is what the photo tells")
            outputs.append(write_json(out / "reflectance.json", reflectance))
            report = {"format": "wavelight-solve-report-1", "scene": str(scene.root), "photo": photo_path.name,
                      "basis": sol.basis,
                      "options": {**asdict(opts.light), "held_out": opts.held_out, "linear_input": opts.linear_input,
                                  "exact": opts.exact, "robust": opts.robust, "clipped": opts.clipped,
                                  "view_exposure": opts.view_exposure,
                                  "resolution": vis_opts.resolution,
                                  "hemisphere": vis_opts.hemisphere, "supersample": vis_opts.supersample,
                                  "visibility": data.method, "reflectance": asdict(refl),
                                  "views": [v.label for v in views]},
                      **{k: v for k, v in result.report.items() if k != "basis"},
                      "held_out": holdout,
                      "reflectance": reflectance, "seconds": time.monotonic() - t0}
            if per_view is not None:
                for v, (p, _) in zip(views, photos):
                    per_view[v.label]["photo"] = cache.relative(p)
                    per_view[v.label]["outputs"] = cache.relative(out if v.label == MAIN_VIEW
                                                                  else out / "views" / v.label)
                report["views"] = per_view
                report["view_exposure"] = exposure_info or {
                    "mode": "same", "note": "the photos are taken to be of one exposure (--view-exposure same)"}
                report["view_exposure"]["note_gains"] = (
                    "views.NAME.exposure: the gain the photo was divided by before the solve (main = 1); "
                    "views.NAME.gain_left: the final light's least-squares gain against the corrected photo "
                    "(1: nothing left to explain)")
                report["observability_by_view"] = by_view
                report["relit_note"] = "relit: the final light over the used pixels of every view together"
            outputs.append(write_json(out / "solve_report.json", report))
            summary = {"basis": sol.basis, "coefficients": sol.n_coefficients,
                       "relative_rmse_vs_photo": result.versus["relative_rmse_vs_photo"],
                       "held_out_rmse": sol.held_out_rmse, "unobservable_texels": int(result.unobservable.sum()),
                       "reflectance": m.to_json(), "line": _result_line(sol, result, report, cache, outputs[0]),
                       "decision_line": f"solve: reflectance {material_text(m)} ({result.reflectance.decision})",
                       "view_lines": _view_lines(report), "warnings": result.warnings}
            return Ran(outputs, jsonable(summary))

        def redisplay() -> list:
            done = [view_png(out / "relit.png", read_rgba(out / "relit.exr"), photo.pixels, exposure)]
            for v, (_, ph) in zip(views[1:], photos[1:]):
                vdir = out / "views" / v.label
                done.append(view_png(vdir / "relit.png", read_rgba(vdir / "relit.exr"), ph.pixels, exposure))
            return done

        d = run_stage(cache, stage, console, force, work, redisplay)
        rec = cache.record_of("solve") or {}
    summary = rec.get("summary", {})
    if "line" in summary:  # results print even when the stage was up to date, and with --quiet
        console.result(summary["line"])
        console.result(summary["decision_line"])
        for line in summary.get("view_lines", []):
            console.result(line)
        if d.run:
            for w in summary.get("warnings", []):
                console.say(f"solve: warning: {w}")
            for p in rec.get("outputs", {}):
                console.say(f"solve: wrote {p}")
    return d


def _view_lines(report: dict) -> list[str]:
    """One result line per view (several views), and how the model choice held out pixels."""
    views = report.get("views")
    if not views:
        return []

    def pct(v):
        return "-" if v is None else f"{100 * v:.2f} %"

    obs = report["observability_by_view"]
    lines = [f"solve: {len(views)} views under one light; held out for the model choice: "
             + (f"the whole view {report['held_out']['view']}" if report["held_out"]["mode"] == "view"
                else report["held_out"]["mode"])]
    for name, v in views.items():
        o = obs["views"][name]
        lines.append(f"solve: view {name}: {v['pixels']['used']} pixels, relit error {pct(v['relit_rmse'])}, held-out "
                     f"{pct(v['held_out_rmse'])}{' (the whole view)' if v.get('held_out_whole') else ''}; "
                     f"weakly observed texels {o['weakly_observed']} alone, it adds {o['adds']['well_observed']}")
    u = obs["union"]
    lines.append(f"solve: all views: {u['unobservable']} unobservable and {u['weakly_observed']} weakly observed "
                 f"(< {obs['weak_threshold']:g}) of {obs['texels']} texels")
    return lines
def _scene_parts(scene: SceneFiles, parts):
    """The mesh's parts and textures (`model.parts.scene_parts`; None: one uniform material)."""
    from pipelines.model import parts as pm

    return pm.scene_parts(scene_mesh(scene.mesh), scene.mesh, scene.root, parts.texture, parts.texture_colour)


def _pixel_albedo(sp, mesh, data, views, cameras, layout, console: Console, shared_ks: bool = False):
    """The used pixels' known relative albedo from the mesh's parts and textures `sp` (`_scene_parts`;
    None: one uniform material), each pixel's texture lookup filtered to its footprint in its own
    view's camera (`model.parts`)."""
    from pipelines.io.scene_files import read_pose
    from pipelines.model import parts as pm

    if sp is None:
        return None
    s = data.samples
    footprint = np.empty(data.n_pixels)
    for k, (v, cam) in enumerate(zip(views, cameras)):
        sl = layout.rows(k)
        rows = s.take(sl)
        footprint[sl] = pm.pixel_footprint(rows, cam, read_pose(v.pose))
    base, part = pm.pixel_base(sp, mesh, s.face, s.position, footprint)
    pm.choose_reference(sp, part)
    seen = np.bincount(part, minlength=len(sp.parts))
    console.say("solve: parts: " + ", ".join(
        f"{p.name} ({p.faces} faces, {int(seen[k])} pixels, "
        f"{'texture ' + Path(p.texture.path).name if p.texture is not None else 'vertex colours' if p.vertex_colours else 'kd'}"
        f"{', reference' if k == sp.reference else ''})" for k, p in enumerate(sp.parts)))
    return pm.PixelAlbedo(base, part, np.ones((len(sp.parts), 3)), sp, *pm.declared_glossy(sp),
                          own_ks=not shared_ks)


def _result_line(sol, result, report, cache, light_path) -> str:
    versus = result.versus
    held = "" if sol.held_out_rmse is None else f", held-out {100 * sol.held_out_rmse:.2f} %"
    b = report["brightest_direction"]["centroid"]
    kept = f"level {sol.chosen} kept of 0-{len(sol.levels) - 1}" if len(sol.levels) > 1 else "one solve"
    return (f"solve: {sol.basis}, {sol.n_coefficients} coefficients ({kept}): relit error "
            f"{100 * versus['relative_rmse_vs_photo']:.2f} % over {versus['compared_pixels']} pixels{held}; "
            f"brightest light theta {b['theta_deg']:.1f} deg, phi {b['phi_deg']:.1f} deg -> "
            f"{cache.relative(light_path)}")


def compare_stage(scene: SceneFiles, vis_opts: VisibilityOptions, opts: SolveOptions, material,
                  console: Console, force: bool = False, lock_wait: float = 600.0):
    """Every basis on one scene at one resolution -> out/compare.json, compare.md, compare.png, ..."""
    from pipelines.controllers.compare import COLUMNS, compare_scene

    vis_opts, camera, photo_path, photo = _inputs(scene, vis_opts, opts)
    cache = SceneCache(scene.root)
    out = scene.out
    # every basis' options that compare's runs read (not only the default basis')
    light = opts.light
    params = {**opts.cache_params(), "material": material.to_json(), "sh_order": light.sh_order,
              "face_resolution": light.face_resolution, "levels": light.levels, "min_gain": light.min_gain}
    params.pop("basis")
    with cache.lock(lock_wait, console.say):
        vis = visibility_stage(scene, vis_opts, console, lock_wait=lock_wait)
        stage = Stage("compare", COMPARE_VERSION, params, {"photo": photo_path}, {vis.stage: vis.key})

        def work(d) -> Ran:
            data = read_kept(vis.path)
            backend = scene_backend(scene_mesh(scene.mesh), vis_opts.backend) if data.method == "adaptive" else None
            result = compare_scene(data, photo, material, opts, photo_path, ConsoleProgress(console, "compare"),
                                   backend, adaptive=data.method == "adaptive")
            table = {"format": "wavelight-compare-1", "scene": str(scene.root), "resolution": vis_opts.resolution,
                     "hemisphere": vis_opts.hemisphere, "pixels": result.pixels, "sample": result.sample,
                     "normal_equations_seconds": result.system_seconds, "observability": result.observability,
                     "rows": result.rows, "columns": COLUMNS}
            text = compare_markdown(table)
            outputs = [write_json(out / "compare.json", table), _write_text(out / "compare.md", text)]
            outputs.append(compare_plot(table, out / "compare.png"))
            outputs.append(compare_lights_figure(result.lights, data.cube, out / "compare_lights.png"))
            outputs.append(_write_lights(out / "compare_lights.h5", result.lights, data.cube))
            return Ran(outputs, {"rows": len(result.rows), "table": text})

        d = run_stage(cache, stage, console, force, work)
        rec = cache.record_of("compare") or {}
    if "table" in rec.get("summary", {}):
        console.result(rec["summary"]["table"].rstrip())
    if d.run:
        for p in rec.get("outputs", {}):
            console.say(f"compare: wrote {p}")
    return d


def _write_text(path: Path, text: str) -> Path:
    from pipelines.io.files import atomic_output

    with atomic_output(path) as tmp:
        tmp.write_text(text)
    return path


def compare_markdown(table: dict) -> str:
    def pct(v):
        return "-" if v is None else f"{100 * v:.2f} %"

    lines = [f"Light bases on {Path(table['scene']).name} at R = {table['resolution']} "
             f"({table['pixels']['fit']} fit / {table['pixels']['held_out']} held-out pixels; "
             f"normal equations {table['normal_equations_seconds']:.1f} s, not included below)", "",
             "| basis | coefficients | fit error | held-out error | all-pixel error | time (s) | min radiance |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in table["rows"]:
        lines.append(f"| {r['basis']} | {r['coefficients']} | {pct(r['fit_rmse'])} | {pct(r['held_out_rmse'])} | "
                     f"{pct(r['all_pixels_rmse'])} | {r['seconds']:.3f} | {round(r['min_radiance_relative'], 3) + 0.0:+.3f} |")
    return "\n".join(lines) + "\n"


def _write_lights(path: Path, lights: list, cube) -> Path:
    """Each basis' texel light (datasets in the table's row order, named by basis) with the cube map."""
    from pipelines.io.files import h5_file

    with h5_file(path) as f:
        f.attrs.update({"format": "wavelight-compare-lights-1", "resolution": cube.resolution,
                        "hemisphere": cube.hemisphere, "units": "linear radiance per texel"})
        for k, (label, texels) in enumerate(lights):
            ds = f.create_dataset(f"{k:02d}_{label.split(' ')[0]}", data=np.asarray(texels, np.float32))
            ds.attrs["label"] = label
    return path


def compare_lights_figure(lights: list, cube, path: Path) -> Path:
    """Each basis' light on the cube cross (cropped to its texels), side by side, log tone-mapped at
    one scale (`outputs.log_display`) with its colour bar; negative radiance of a plain SH fit in blue."""
    from pipelines.io.files import atomic_output

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import ListedColormap, LogNorm
    from matplotlib.ticker import FuncFormatter

    from pipelines.light import cubemap

    from ..outputs import log_colours, log_display, log_range

    ranges = [log_range(np.clip(t, 0, None)) for _, t in lights if np.any(np.asarray(t) > 0)] or [(0.1, 1.0)]
    lo, hi = min(r[0] for r in ranges), max(r[1] for r in ranges)
    _, valid = cubemap.cross_image(np.zeros(cube.n_texels), cube)
    rows, cols = np.nonzero(valid)
    crop = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    ncol = (len(lights) + 1) // 2
    aspect = (rows.max() + 1 - rows.min()) / (cols.max() + 1 - cols.min())
    fig, axes = plt.subplots(2, ncol, figsize=(3.4 * ncol + 0.8, 2 * (3.4 * aspect + 0.4)), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (label, texels) in zip(axes.ravel(), lights):
        cross, _ = cubemap.cross_image(texels, cube)
        disp, _, _ = log_display(np.clip(cross, 0, None), lo, hi)
        negative = valid & (np.asarray(cross).min(axis=-1) < -1e-6 * hi)
        disp[negative] = (0.1, 0.2, 0.9)
        disp[~valid] = 1.0
        ax.imshow(np.clip(disp[crop], 0, 1), interpolation="nearest")
        ax.set_title(label, fontsize=9)
    bar = fig.colorbar(ScalarMappable(LogNorm(lo, hi), ListedColormap(log_colours(256))), ax=list(axes.ravel()),
                       fraction=0.025, pad=0.02)
    bar.ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}" if v < 1000 else f"{v:.0f}"))
    bar.ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
    bar.ax.tick_params(labelsize=7)
    bar.set_label("radiance (brightest channel; log scale)", fontsize=7)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png", facecolor="white")
    plt.close(fig)
    return path


def compare_plot(table: dict, path: Path) -> Path:
    """Held-out error against solve time, one labelled marker per basis (`compare_figure`)."""
    from pipelines.io.files import atomic_output

    import matplotlib.pyplot as plt

    fig = compare_figure(table)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def compare_figure(table: dict):
    """The compare plot as a matplotlib figure: markers sized by the coefficients, each labelled
    with its basis where the label overlaps no other label, no marker and stays inside the axes
    (`place_labels`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import FuncFormatter, LogLocator

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=100)
    points = []
    for k, r in enumerate(table["rows"]):
        err = r["held_out_rmse"] if r["held_out_rmse"] is not None else r["all_pixels_rmse"]
        x, y, size = max(r["seconds"], 1e-4), 100 * err, 30 + 4 * np.sqrt(r["coefficients"])
        ax.scatter(x, y, s=size, color=f"C{k}", zorder=3)
        points.append((x, y, size, f"{r['basis']} ({r['coefficients']})", f"C{k}"))
    ax.set_xscale("log")
    ax.set_yscale("log")
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(plain)
        axis.set_minor_locator(LogLocator(subs=(2.0, 3.0, 5.0)))
        axis.set_minor_formatter(plain)
    ax.margins(x=0.25, y=0.2)  # room for the labels inside the axes
    ax.set_xlabel("solve time after the normal equations (s)")
    ax.set_ylabel("held-out relative RMSE (%, log)")
    ax.set_title(f"{Path(table['scene']).name}, R = {table['resolution']}")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    thin_tick_labels(fig, ax)
    place_labels(fig, ax, points)
    return fig


def thin_tick_labels(fig, ax) -> None:
    """Drop an axis' minor tick labels (2, 3, 5 in each decade) where any two of its tick labels
    would overlap: an axis over several decades (solve times from 0.01 s to a minute) keeps only
    the decades' labels."""
    from matplotlib.ticker import NullFormatter

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for axis in (ax.xaxis, ax.yaxis):
        lo, hi = sorted(axis.get_view_interval())
        boxes = [tick.label1.get_window_extent(renderer)
                 for locs, ticks in ((axis.get_majorticklocs(), axis.get_major_ticks()),
                                     (axis.get_minorticklocs(), axis.get_minor_ticks()))
                 for loc, tick in zip(locs, ticks) if lo <= loc <= hi and tick.label1.get_text()]
        if any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:]):
            axis.set_minor_formatter(NullFormatter())


def place_labels(fig, ax, points) -> list:
    """Label each (x, y, marker size, text, colour) point at the first of a ring of positions
    around it, nearest first, whose text box is inside the axes and clear of every marker and of
    the labels placed before; a label away from its marker gets a leader line. Returns the labels."""
    from matplotlib.transforms import Bbox

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    px_per_pt = fig.dpi / 72.0
    centres = ax.transData.transform([(x, y) for x, y, *_ in points])
    radii = [0.5 * np.sqrt(size) * px_per_pt for _, _, size, *_ in points]
    markers = [Bbox.from_extents(cx - r, cy - r, cx + r, cy + r) for (cx, cy), r in zip(centres, radii)]
    pad = 2.0

    def overlap(a, b) -> float:
        w = min(a.x1, b.x1) - max(a.x0, b.x0) + pad
        h = min(a.y1, b.y1) - max(a.y0, b.y0) + pad
        return max(w, 0.0) * max(h, 0.0)

    def outside(box) -> float:
        return sum(max(v, 0.0) for v in (frame.x0 - box.x0, box.x1 - frame.x1, frame.y0 - box.y0, box.y1 - frame.y1))

    directions = [(1, 0, "left", "center"), (-1, 0, "right", "center"), (0, 1, "center", "bottom"),
                  (0, -1, "center", "top"), (0.7, 0.7, "left", "bottom"), (-0.7, 0.7, "right", "bottom"),
                  (0.7, -0.7, "left", "top"), (-0.7, -0.7, "right", "top")]
    placed, labels = [], []
    for k, (x, y, size, text, colour) in enumerate(points):
        r_pt = 0.5 * np.sqrt(size)
        best = None
        for gap in (3, 10, 20, 32, 48, 66):
            for dx, dy, ha, va in directions:
                off = ((r_pt + gap) * dx, (r_pt + gap) * dy)
                label = ax.annotate(text, (x, y), xytext=off, textcoords="offset points", ha=ha, va=va,
                                    fontsize=8, color=colour)
                box = label.get_window_extent(renderer)
                cost = (sum(overlap(box, b) for b in placed) + sum(overlap(box, m) for m in markers)
                        + 1e3 * outside(box))
                if best is None or cost < best[0]:
                    if best is not None:
                        best[1].remove()
                    best = (cost, label, box, gap, off, ha, va)
                else:
                    label.remove()
                if best[0] == 0:
                    break
            if best[0] == 0:
                break
        _, label, box, gap, off, ha, va = best
        if gap > 10:  # away from its marker: a leader line
            label.remove()
            label = ax.annotate(text, (x, y), xytext=off, textcoords="offset points", ha=ha, va=va, fontsize=8,
                                color=colour, arrowprops={"arrowstyle": "-", "color": colour, "lw": 0.7,
                                                          "shrinkA": 1, "shrinkB": radii[k] / px_per_pt})
        placed.append(box)
        labels.append(label)
    return labels
