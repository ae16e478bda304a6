"""`wavelight solve` and `wavelight compare`: plan, run the controller, write, record.

solve -> out/light_latlong.exr, light_cross.exr/png, observability.png, coefficients.h5,
relit.exr/png, residual.png, reflectance.json, solve_report.json; compare -> out/compare.json,
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

from ..cache import Ran, SceneCache, Stage, run_stage
from ..console import Console
from ..outputs import heat_map, jsonable, upscale, write_json, write_light, write_residual
from ..scene import SceneFiles, load_photo
from .visibility import visibility_stage

VERSION = 3
COMPARE_VERSION = 3


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
    opts.check(vis_opts.resolution, vis_opts.hemisphere)
    camera = read_camera(scene.camera)
    photo_path, photo = load_photo(scene, camera, True if opts.linear_input else None)
    return vis_opts, camera, photo_path, photo


def solve_stage(scene: SceneFiles, vis_opts: VisibilityOptions, opts: SolveOptions, material, exposure,
                console: Console, force: bool = False, lock_wait: float = 600.0,
                refl: ReflectanceOptions = ReflectanceOptions("given"), given: set | None = None):
    """Recover the light (and the reflectance, by `refl`); see the module docstring for the outputs."""
    from pipelines.controllers import solve as ctl
    from pipelines.io import images, light_file, visibility_file
    from pipelines.io.scene_files import load_mesh
    from pipelines.geometry import raycast
    from pipelines.light.cubemap import cross_image
    from pipelines.model import render as rd

    given = given or set()
    refl.check()
    params = {**opts.cache_params(), "reflectance": refl.cache_params(), "material": material.to_json()}
    if refl.fits:
        params["start"] = refl.start(material, given).to_json()
    vis_opts, camera, photo_path, photo = _inputs(scene, vis_opts, opts)
    cache = SceneCache(scene.root)
    out = scene.out
    with cache.lock(lock_wait, console.say):
        vis = visibility_stage(scene, vis_opts, console, lock_wait=lock_wait)
        stage = Stage("solve", VERSION, params, {"photo": photo_path}, {vis.stage: vis.key}, {"exposure": exposure})

        def work(d) -> Ran:
            t0 = time.monotonic()
            data = visibility_file.read_visibility(vis.path)
            backend = raycast.make_backend(load_mesh(scene.mesh), vis_opts.backend) if data.method == "adaptive" else None
            result = ctl.solve_scene(data, photo, material, opts, refl, given, backend, photo_path,
                                     ConsoleProgress(console, "solve"), adaptive=data.method == "adaptive")
            m, sol, cube = result.material, result.solution, data.cube
            outputs = write_light(out, "light", sol.light, cube, unobservable=result.unobservable)
            obs_cross, valid = cross_image(result.observability, cube)
            obs_img = heat_map(obs_cross, 1.0)
            obs_img[~valid] = 0.15
            outputs.append(images.write_png(out / "observability.png", upscale(obs_img), already_display=True))
            outputs.append(out / "coefficients.h5")
            light_file.write_solution(outputs[-1], sol, cube, result.unobservable, {"material": str(m.to_json())})
            img = rd.pixels_to_image(result.relit, data.samples.pixel, camera.height, camera.width)
            outputs.append(images.write_exr(out / "relit.exr", img))
            outputs.append(images.write_png(out / "relit.png", img, exposure))
            rows, cols = data.samples.pixel[:, 0], data.samples.pixel[:, 1]
            outputs.append(write_residual(out / "residual.png", result.relit, photo.pixels[rows, cols],
                                          data.samples.pixel, (camera.height, camera.width),
                                          ~photo.saturated[rows, cols]))
            reflectance = {"format": "wavelight-reflectance-1", **result.reflectance.summary(),
                           "scale_ambiguity": ctl.SCALE_NOTE}
            outputs.append(write_json(out / "reflectance.json", reflectance))
            report = {"format": "wavelight-solve-report-1", "scene": str(scene.root), "photo": photo_path.name,
                      "basis": sol.basis,
                      "options": {**asdict(opts.light), "held_out": opts.held_out, "linear_input": opts.linear_input,
                                  "exact": opts.exact, "resolution": vis_opts.resolution,
                                  "hemisphere": vis_opts.hemisphere, "supersample": vis_opts.supersample,
                                  "visibility": data.method, "reflectance": asdict(refl)},
                      **{k: v for k, v in result.report.items() if k != "basis"},
                      "reflectance": reflectance, "seconds": time.monotonic() - t0}
            outputs.append(write_json(out / "solve_report.json", report))
            summary = {"basis": sol.basis, "coefficients": sol.n_coefficients,
                       "relative_rmse_vs_photo": result.versus["relative_rmse_vs_photo"],
                       "held_out_rmse": sol.held_out_rmse, "unobservable_texels": int(result.unobservable.sum()),
                       "reflectance": m.to_json(), "line": _result_line(sol, result, report, cache, outputs[0]),
                       "decision_line": f"solve: reflectance {material_text(m)} ({result.reflectance.decision})",
                       "warnings": result.warnings}
            return Ran(outputs, jsonable(summary))

        def redisplay() -> list:
            relit = images.read_image(out / "relit.exr").pixels
            return [images.write_png(out / "relit.png", relit, exposure)]

        d = run_stage(cache, stage, console, force, work, redisplay)
        rec = cache.record_of("solve") or {}
    summary = rec.get("summary", {})
    if "line" in summary:  # results print even when the stage was up to date, and with --quiet
        console.result(summary["line"])
        console.result(summary["decision_line"])
        if d.run:
            for w in summary.get("warnings", []):
                console.say(f"solve: warning: {w}")
            for p in rec.get("outputs", {}):
                console.say(f"solve: wrote {p}")
    return d


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
    from pipelines.io import visibility_file

    vis_opts, camera, photo_path, photo = _inputs(scene, vis_opts, opts)
    cache = SceneCache(scene.root)
    out = scene.out
    params = {**opts.cache_params(), "material": material.to_json()}
    params.pop("basis")
    with cache.lock(lock_wait, console.say):
        vis = visibility_stage(scene, vis_opts, console, lock_wait=lock_wait)
        stage = Stage("compare", COMPARE_VERSION, params, {"photo": photo_path}, {vis.stage: vis.key})

        def work(d) -> Ran:
            data = visibility_file.read_visibility(vis.path)
            result = compare_scene(data, photo, material, opts, photo_path, ConsoleProgress(console, "compare"))
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
    """Each basis' light on the cube cross, side by side, at one exposure (negative radiance of a
    plain SH fit shown in blue)."""
    from pipelines.io.files import atomic_output

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipelines.light import cubemap
    from pipelines.io import images

    # one exposure for all: the sky's level (a sun saturates; its place shows)
    top = max(float(np.percentile(np.abs(t[t != 0]), 95)) if np.any(t != 0) else 1.0 for _, t in lights)
    fig, axes = plt.subplots(2, (len(lights) + 1) // 2, figsize=(3.4 * ((len(lights) + 1) // 2), 5.4), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (label, texels) in zip(axes.ravel(), lights):
        cross, valid = cubemap.cross_image(texels, cube)
        disp = images.tonemap(np.clip(cross, 0, None), -np.log2(top))
        negative = valid & (np.asarray(cross).min(axis=-1) < -1e-6 * top)
        disp[negative] = (0.1, 0.2, 0.9)
        disp[~valid] = 0.15
        ax.imshow(np.clip(disp, 0, 1), interpolation="nearest")
        ax.set_title(label, fontsize=9)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)
    return path


def compare_plot(table: dict, path: Path) -> Path:
    from pipelines.io.files import atomic_output

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import FuncFormatter, LogLocator

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=100)
    for k, r in enumerate(table["rows"]):
        err = r["held_out_rmse"] if r["held_out_rmse"] is not None else r["all_pixels_rmse"]
        ax.scatter(max(r["seconds"], 1e-4), 100 * err, s=30 + 4 * np.sqrt(r["coefficients"]))
        ax.annotate(f"{r['basis']} ({r['coefficients']})", (max(r["seconds"], 1e-4), 100 * err),
                    textcoords="offset points", xytext=(6, 4 + 9 * (k % 3)), fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(plain)
        axis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))
        axis.set_minor_formatter(plain)
    ax.set_xlabel("solve time after the normal equations (s)")
    ax.set_ylabel("held-out relative RMSE (%, log)")
    ax.set_title(f"{Path(table['scene']).name}, R = {table['resolution']}")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
