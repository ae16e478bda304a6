"""The light-solve stages: `solve` (one basis -> light, relit view, report) and `compare` (all bases
on one scene -> table and speed-vs-error plot). The numerics are in `pipelines.light`."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipelines.errors import InputError
from pipelines.fileio import h5_file

from .cache import SceneCache, atomic_output, output_set, write_json_atomic
from .scenefiles import SceneFiles
from .stages import (Console, VisibilityOptions, compare_to_photo, heat_map, load_photo, upscale, visibility_stage,
                     write_light)

SOLVE_VERSION = 2
COMPARE_VERSION = 2
BASES = ("wavelet", "quadtree", "discrete", "sh", "points")
SCALE_NOTE = ("light x albedo is only known as a product: with the default kd = 1 the light absorbs "
              "the albedo (DESIGN §2)")


@dataclass(frozen=True)
class SolveOptions:
    basis: str = "wavelet"
    levels: str = "auto"  # "auto" or a count: refinement levels (wavelet, quadtree) / lights (points)
    face_resolution: int | None = None  # discrete: face resolution (default: the visibility's R)
    sh_order: int = 2
    sh_nonnegative: bool = False
    held_out: float = 0.1
    min_gain: float = 0.01
    linear_input: bool = False

    def check(self, vis: VisibilityOptions) -> None:
        if self.basis not in BASES:
            raise InputError(f"unknown --basis {self.basis!r}", None, f"use one of {', '.join(BASES)}")
        if self.levels != "auto":
            try:
                n = int(self.levels)
            except ValueError:
                n = 0
            if n < 1:
                raise InputError(f"--levels must be 'auto' or a positive count, got {self.levels!r}", None,
                                 "use --levels auto (default) or e.g. --levels 4")
            # the coarse-to-fine tree: the tile roots, one level per halving of the largest tile,
            # and one more where pruned leaves are split again; points: at most one per texel
            most = (vis.resolution.bit_length() + 1 if self.basis in ("wavelet", "quadtree") else
                    3 * vis.resolution**2 * (1 if vis.hemisphere else 2))
            if self.basis in ("wavelet", "quadtree", "points") and n > most:
                what = (f"the {most} levels a cube map of R = {vis.resolution} can be refined to"
                        if self.basis != "points" else f"the {most} light directions at R = {vis.resolution}")
                raise InputError(f"--levels {n} is more than {what}", None,
                                 f"use --levels auto, or at most {most}")
        if not 0 <= self.held_out <= 0.5:
            raise InputError(f"--held-out must be a fraction from 0 to 0.5, got {self.held_out}", None,
                             "use e.g. --held-out 0.1")
        if self.levels == "auto" and self.held_out == 0 and self.basis in ("wavelet", "quadtree", "points"):
            raise InputError("--levels auto needs held-out pixels, but --held-out is 0", None,
                             "use --held-out 0.1, or give a fixed --levels N")
        if not 0 <= self.min_gain < 1:
            raise InputError(f"--min-gain must be in [0, 1), got {self.min_gain}", None, "use e.g. 0.01")
        if not 0 <= self.sh_order <= 8:
            raise InputError(f"--sh-order must be 0..8, got {self.sh_order}", None, "use 2 (9 coefficients)")
        r = self.face_resolution
        if r is not None and (r < 1 or r > vis.resolution or r & (r - 1)):
            raise InputError(f"--face-resolution must be a power of two up to --resolution ({vis.resolution}), "
                             f"got {r}", None, f"use e.g. --face-resolution {vis.resolution}")

    def cache_params(self) -> dict:
        """The options that can change this basis' result (others do not rerun the stage)."""
        p = asdict(self)
        if self.basis not in ("wavelet", "quadtree", "points"):
            p.pop("levels"), p.pop("min_gain")
        if self.basis != "discrete":
            p.pop("face_resolution")
        if self.basis != "sh":
            p.pop("sh_order"), p.pop("sh_nonnegative")
        return p

    @property
    def levels_value(self) -> int | str:
        return "auto" if self.levels == "auto" else int(self.levels)


REFLECTANCE_MODES = ("auto", "lambert", "blinn-phong", "phong", "phong-classic", "given")
DEFAULT_START_KS = 0.25  # start of a specular fit: ks = 0.25 x mean(kd), unless --ks is given
DEFAULT_START_SHININESS = 20.0  # and n = 20, unless --shininess is given


@dataclass(frozen=True)
class ReflectanceOptions:
    """What `solve` does about the reflectance: fit it (a model or auto) or take it as given."""

    mode: str = "auto"
    max_rounds: int = 8
    min_specular_gain: float = 0.05

    def check(self) -> None:
        if self.mode not in REFLECTANCE_MODES:
            raise InputError(f"unknown --reflectance {self.mode!r}", None, f"use one of {', '.join(REFLECTANCE_MODES)}")
        if not 1 <= self.max_rounds <= 100:
            raise InputError(f"--max-rounds must be 1..100, got {self.max_rounds}", None, "use e.g. --max-rounds 8")
        if not 0 <= self.min_specular_gain < 1:
            raise InputError(f"--min-specular-gain must be in [0, 1), got {self.min_specular_gain}", None,
                             "use e.g. --min-specular-gain 0.05")

    @property
    def fits(self) -> bool:
        return self.mode not in ("lambert", "given")

    def cache_params(self) -> dict:
        p = asdict(self)
        if not self.fits:
            p.pop("max_rounds"), p.pop("min_specular_gain")
        if self.mode != "auto":
            p.pop("min_specular_gain", None)
        return p

    def start(self, material, given: set):
        """The fit's start: the given material's kd; its ks and n if the user gave them, else
        ks = DEFAULT_START_KS x mean(kd) and n = DEFAULT_START_SHININESS; the model of --reflectance
        (auto: the given specular model, else blinn-phong)."""
        from dataclasses import replace

        from pipelines.render import SPECULAR_MODELS

        model = self.mode if self.mode in SPECULAR_MODELS else (
            material.model if material.model in SPECULAR_MODELS else "blinn-phong")
        ks = material.ks if "ks" in given and any(material.ks) else (DEFAULT_START_KS * float(np.mean(material.kd)),) * 3
        if "n" in given and not material.shininess > 0:
            raise InputError(f"--shininess must be > 0 to start a fit, got {material.shininess:g}", None,
                             f"use e.g. --shininess {DEFAULT_START_SHININESS:g}, or leave it out")
        n = material.shininess if "n" in given else DEFAULT_START_SHININESS
        return replace(material, model=model, ks=tuple(ks), shininess=float(n))


@dataclass
class Problem:
    """Everything a solve needs, loaded once: visibility, photo values, normal equations."""

    camera: object
    photo_path: Path
    photo: object
    data: object  # VisibilityData
    values: np.ndarray  # (P, 3) photo radiance at the used pixels
    saturated: np.ndarray  # (P,) bool
    held_out: np.ndarray  # (P,) bool
    ne: object  # NormalEquations of the current material (None until `_normal_equations`)
    unobservable: np.ndarray | None
    observability: np.ndarray | None

    def pixel_counts(self) -> dict:
        return {"used": int(len(self.values)), "saturated_excluded": int(self.saturated.sum()),
                "fit": int(self.ne.fit.n_pixels), "held_out": int(self.ne.held_out.n_pixels)}

    def observability_summary(self) -> dict:
        n = len(self.unobservable)
        return {"texels": n, "unobservable": int(self.unobservable.sum()),
                "unobservable_fraction": float(self.unobservable.mean()),
                "weakly_observed": int(((self.observability < 1e-3) & ~self.unobservable).sum()),
                "note": "observability = sqrt(G_ii / max G_ii): how strongly the used pixels respond to a "
                        "texel's radiance; unobservable texels (0) get no light"}


def _inputs(scene: SceneFiles, vis_opts: VisibilityOptions, opts: SolveOptions):
    """Check the options and load the camera and photo: (camera, photo path, photo, cache)."""
    from pipelines.scene import read_camera

    vis_opts.check()
    opts.check(vis_opts)
    camera = read_camera(scene.camera)
    photo_path, photo = load_photo(scene, camera, True if opts.linear_input else None)
    return camera, photo_path, photo, SceneCache(scene.root)


def _load(scene: SceneFiles, cache: SceneCache, opts: SolveOptions, camera, photo_path, photo) -> Problem:
    """Visibility, photo values, saturated and held-out pixels; normal equations not yet built."""
    from pipelines import visibility as vis
    from pipelines.normal_equations import holdout_mask

    data = vis.read_visibility(cache.dir / "visibility.h5")
    rows, cols = data.samples.pixel[:, 0], data.samples.pixel[:, 1]
    values = photo.pixels[rows, cols].astype(np.float64)
    saturated = photo.saturated[rows, cols]
    if saturated.all():
        raise InputError("every used pixel is saturated (clipped)", photo_path,
                         "use a darker exposure or an HDR (EXR) photo")
    if not np.any(values[~saturated] > 0):
        raise InputError(f"the photo is black over all {len(values)} used pixels: there is no light to recover",
                         photo_path, "check the exposure, the lens cap, the mask and that this is the right photo")
    held = holdout_mask(data.samples.pixel, opts.held_out) if opts.held_out > 0 else np.zeros(len(values), bool)
    return Problem(camera, photo_path, photo, data, values, saturated, held, None, None, None)


def _normal_equations(problem: Problem, material, console: Console, stage: str) -> Problem:
    """Build the normal equations of `material` into the problem (and its observability)."""
    from pipelines import light as lt
    from pipelines.normal_equations import build_normal_equations

    n_sat = int(problem.saturated.sum())
    console.say(f"{stage}: normal equations over {len(problem.values)} pixels x {problem.data.cube.n_texels} texels"
                + (f" ({n_sat} saturated pixels left out)" if n_sat else ""))
    ne = build_normal_equations(problem.data, problem.values, material, use=~problem.saturated,
                                held_out=problem.held_out,
                                progress=lambda done, total: console.progress(stage, done, total))
    console.say(f"{stage}: normal equations in {ne.seconds:.1f} s")
    problem.ne = ne
    problem.observability, problem.unobservable = lt.observability(ne)
    return problem


def _problem(scene: SceneFiles, cache: SceneCache, material, opts: SolveOptions, console: Console, stage: str,
             camera, photo_path, photo) -> Problem:
    problem = _load(scene, cache, opts, camera, photo_path, photo)
    return _normal_equations(problem, material, console, stage)


def _solve(problem: Problem, opts: SolveOptions, basis: str, console: Console, stage: str, nonneg=None):
    from pipelines import light as lt

    def progress(rec):
        held = "" if rec.held_out_rmse is None else f", held-out {100 * rec.held_out_rmse:.3f} %"
        console.say(f"{stage}: {basis} level {rec.index}: {rec.n_coefficients} coefficients, "
                    f"fit {100 * rec.fit_rmse:.3f} %{held}")

    return lt.solve(problem.ne, problem.data.cube, basis, opts.levels_value, opts.face_resolution, opts.sh_order,
                    opts.sh_nonnegative if nonneg is None else nonneg, opts.min_gain, progress)


def _brightest(solution, cube) -> dict:
    from pipelines.cubemap import direction_to_spherical

    lum = solution.light @ np.array([0.2126, 0.7152, 0.0722])
    i = int(np.argmax(lum))
    theta, phi = direction_to_spherical(cube.directions[i:i + 1])
    return {"texel": i, "direction": cube.directions[i].tolist(), "theta_deg": float(np.degrees(theta[0])),
            "phi_deg": float(np.degrees(phi[0]) % 360.0), "radiance_rgb": solution.light[i].tolist()}


def material_text(m) -> str:
    kd = " ".join(f"{v:.3g}" for v in m.kd)
    if not m.specular:
        return f"{m.model} kd {kd}"
    return f"{m.model} kd {kd}, ks {float(np.mean(m.ks)):.3g}, n {m.shininess:.3g}"


def _reflectance(problem: Problem, opts: SolveOptions, refl: ReflectanceOptions, material, given: set,
                 console: Console):
    """Light and reflectance by --reflectance: given, lambert, a specular model (alternation) or auto."""
    from pipelines import reflectance as rf
    from pipelines.render import Material

    def solve_light(m):
        _normal_equations(problem, m, console, "solve")
        return _solve(problem, opts, opts.basis, console, "solve"), problem.ne

    def progress(r):
        held = "" if r.held_out_rmse is None else f", held-out {100 * r.held_out_rmse:.3f} %"
        lm = "" if r.fit is None else f" (LM: {r.fit.evaluations} evaluations, {r.fit.seconds:.1f} s)"
        console.say(f"solve: reflectance round {r.index}: {material_text(r.material)}{lm}: "
                    f"error {100 * r.fit_rmse:.3f} %{held}")

    use = ~problem.saturated
    try:
        if refl.mode == "given":
            return rf.fixed(material, solve_light, "given", "given by the user (--material/--model/--kd/--ks/"
                            "--shininess): not fitted", progress)
        if refl.mode == "lambert":
            return rf.fixed(Material(kd=material.kd), solve_light, "lambert", "lambert: chosen by --reflectance",
                            progress)
        start = refl.start(material, given)
        console.say(f"solve: reflectance {refl.mode}: start {material_text(start)}")
        if refl.mode == "auto":
            return rf.select(problem.data, problem.values, start, solve_light, use, problem.held_out, material.kd,
                             refl.min_specular_gain, refl.max_rounds, progress=progress)
        return rf.alternate(problem.data, problem.values, start, solve_light, use, problem.held_out, material.kd,
                            refl.max_rounds, progress=progress)
    except rf.FitError as exc:
        raise InputError(f"cannot fit the reflectance: {exc}", problem.photo_path,
                         "use --reflectance lambert, or check the photo and the pose") from None


def solve_stage(scene: SceneFiles, vis_opts: VisibilityOptions, opts: SolveOptions, material, exposure,
                console: Console, force: bool = False, lock_wait: float = 600.0,
                refl: ReflectanceOptions = ReflectanceOptions("given"), given: set | None = None):
    """Recover the light (and the reflectance, by `refl`) -> out/light_latlong.exr, light_cross.exr/png,
    observability.png, coefficients.h5, relit.exr/png, residual.png, reflectance.json, solve_report.json."""
    from pipelines import images
    from pipelines import light as lt
    from pipelines import reflectance as rf
    from pipelines import render as rd
    from pipelines.cubemap import cross_image

    refl.check()
    if refl.fits:
        refl.start(material, given or set())
    camera, photo_path, photo, cache = _inputs(scene, vis_opts, opts)
    with cache.lock(lock_wait, console.say):
        vdec = visibility_stage(scene, vis_opts, console, force=False, lock_wait=lock_wait)
        params = {**opts.cache_params(), "reflectance": refl.cache_params(), "material": material.to_json(),
                  "exposure": exposure}
        if refl.fits:
            params["start"] = refl.start(material, given or set()).to_json()
        d = cache.plan("solve", SOLVE_VERSION, params, {"photo": photo_path}, {"visibility": vdec.key}, force)
        console.decision(d)
        if not d.run:
            return d
        t0 = time.monotonic()
        problem = _load(scene, cache, opts, camera, photo_path, photo)
        result = _reflectance(problem, opts, refl, material, given or set(), console)
        material, sol = result.material, result.solution
        problem.ne = result.context
        problem.observability, problem.unobservable = lt.observability(problem.ne)
        cube = problem.data.cube
        if problem.unobservable.any():
            console.say(f"solve: {int(problem.unobservable.sum())} of {cube.n_texels} light directions are "
                        "unobservable (no used pixel sees them): they stay at zero, drawn magenta")
        if sol.details.get("min_radiance", 0.0) < 0:
            console.say(f"solve: warning: the {sol.basis} light goes negative (min {sol.details['min_radiance']:.4g}, "
                        f"{100 * sol.details['negative_fraction']:.0f} % of the texels): it is kept as solved; "
                        "tools that clip it get a different light (use --sh-nonnegative for a physical one)")
        with output_set():  # the stage's files replace the old ones together, or not at all
            out = scene.out
            outputs = write_light(out, "light", sol.light, cube, unobservable=problem.unobservable)
            obs_cross, valid = cross_image(problem.observability, cube)
            obs_img = heat_map(obs_cross, 1.0)
            obs_img[~valid] = 0.15
            outputs.append(out / "observability.png")
            images.write_png(outputs[-1], upscale(obs_img), already_display=True)
            outputs.append(out / "coefficients.h5")
            with atomic_output(outputs[-1]) as tmp:
                lt.write_solution(tmp, sol, cube, problem.unobservable, {"material": str(material.to_json())})
            relit = rd.render(problem.data, sol.light, material)
            img = rd.pixels_to_image(relit, problem.data.samples.pixel, camera.height, camera.width)
            outputs += [out / "relit.exr", out / "relit.png", out / "residual.png"]
            images.write_exr(outputs[-3], img)
            images.write_png(outputs[-2], img, exposure)
            versus = compare_to_photo(relit, photo, problem.data.samples, camera, outputs[-1])
            warnings = lt.diagnose(problem.ne, sol, cube, versus["relative_rmse_vs_photo"])
            n_range = rf.SHININESS_RANGE
            if material.specular and not n_range[0] * 1.001 < material.shininess < n_range[1] * 0.999:
                warnings.append(f"the shininess n = {material.shininess:g} is at the end of its range {n_range}: "
                                "the highlight is not resolved (try a larger R, or --reflectance lambert)")
            reflectance = {"format": "wavelight-reflectance-1", **result.summary(), "scale_ambiguity": SCALE_NOTE}
            outputs.append(out / "reflectance.json")
            write_json_atomic(outputs[-1], _jsonable(reflectance))
            report = {
                "format": "wavelight-solve-report-1",
                "scene": str(scene.root), "photo": photo_path.name, "basis": sol.basis,
                "options": {**asdict(opts), "resolution": vis_opts.resolution, "hemisphere": vis_opts.hemisphere,
                            "supersample": vis_opts.supersample, "reflectance": asdict(refl)},
                "material": material.to_json(), "scale_ambiguity": SCALE_NOTE,
                "reflectance": reflectance,
                "pixels": problem.pixel_counts(),
                "normal_equations_seconds": problem.ne.seconds,
                "observability": problem.observability_summary(),
                "relit": versus,
                "warnings": warnings,
                "brightest_direction": _brightest(sol, cube),
                "solution": sol.summary(),
                "seconds": time.monotonic() - t0,
            }
            outputs.append(out / "solve_report.json")
            write_json_atomic(outputs[-1], _jsonable(report))
        summary = {"basis": sol.basis, "coefficients": sol.n_coefficients,
                   "relative_rmse_vs_photo": versus["relative_rmse_vs_photo"],
                   "held_out_rmse": sol.held_out_rmse, "unobservable_texels": int(problem.unobservable.sum()),
                   "reflectance": material.to_json()}
        cache.record(d, outputs, report["seconds"], summary)
        held = "" if sol.held_out_rmse is None else f", held-out {100 * sol.held_out_rmse:.2f} %"
        b = report["brightest_direction"]
        kept = f"level {sol.chosen} kept of 0-{len(sol.levels) - 1}" if len(sol.levels) > 1 else "one solve"
        console.result(f"solve: {sol.basis}, {sol.n_coefficients} coefficients ({kept}): relit error {100 * versus['relative_rmse_vs_photo']:.2f} % over "
                       f"{versus['compared_pixels']} pixels{held}; brightest direction theta "
                       f"{b['theta_deg']:.1f} deg, phi {b['phi_deg']:.1f} deg -> {cache.relative(outputs[0])}")
        console.result(f"solve: reflectance {material_text(material)} ({result.decision})")
        for w in warnings:
            console.say(f"solve: warning: {w}")
        for p in outputs:
            console.say(f"solve: wrote {cache.relative(p)}")
    return d


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if np.isfinite(v) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


# -- compare -----------------------------------------------------------------------------------
def compare_stage(scene: SceneFiles, vis_opts: VisibilityOptions, opts: SolveOptions, material,
                  console: Console, force: bool = False, lock_wait: float = 600.0):
    """Every basis on one scene at one resolution -> out/compare.json, compare.md, compare.png."""
    camera, photo_path, photo, cache = _inputs(scene, vis_opts, opts)
    with cache.lock(lock_wait, console.say):
        vdec = visibility_stage(scene, vis_opts, console, force=False, lock_wait=lock_wait)
        params = {**asdict(opts), "material": material.to_json()}
        params.pop("basis")
        d = cache.plan("compare", COMPARE_VERSION, params, {"photo": photo_path}, {"visibility": vdec.key}, force)
        console.decision(d)
        if not d.run:
            return d
        t0 = time.monotonic()
        problem = _problem(scene, cache, material, opts, console, "compare", camera, photo_path, photo)
        rows, lights = [], []
        runs = [("wavelet", None), ("quadtree", None), ("discrete", None), ("sh", False), ("sh", True),
                ("points", None)]
        for basis, nonneg in runs:
            sol = _solve(problem, opts, basis, console, "compare", nonneg)
            lights.append((f"{sol.basis} ({sol.n_coefficients})", sol.light))
            min_rel = sol.details.get("min_radiance_relative", float(sol.light.min() / max(sol.light.max(), 1e-300)))
            rows.append({"basis": sol.basis, "coefficients": sol.n_coefficients,
                         "levels": len(sol.levels), "fit_rmse": sol.levels[sol.chosen].fit_rmse,
                         "held_out_rmse": sol.held_out_rmse, "all_pixels_rmse": sol.fit_rmse,
                         "seconds": sol.seconds, "min_radiance_relative": min_rel,
                         "kkt_residual": sol.solver.get("kkt_residual")})
            console.say(f"compare: {sol.basis}: {sol.n_coefficients} coefficients, "
                        f"{100 * sol.fit_rmse:.2f} % in {sol.seconds:.2f} s")
        out = scene.out
        table = {"format": "wavelight-compare-1", "scene": str(scene.root), "resolution": vis_opts.resolution,
                 "hemisphere": vis_opts.hemisphere, "pixels": problem.pixel_counts(),
                 "normal_equations_seconds": problem.ne.seconds,
                 "observability": problem.observability_summary(), "rows": rows,
                 "columns": {"fit_rmse": "relative RMSE over the fit pixels at the chosen level",
                             "held_out_rmse": "relative RMSE over the held-out pixels (not fitted)",
                             "all_pixels_rmse": "relative RMSE of the final light (re-solved on all pixels)",
                             "seconds": "solve time after the normal equations",
                             "min_radiance_relative": "lowest texel radiance / highest (negative: not a light)"}}
        outputs = [out / "compare.json", out / "compare.md", out / "compare.png", out / "compare_lights.png",
                   out / "compare_lights.h5"]
        with output_set():  # the stage's files replace the old ones together, or not at all
            write_json_atomic(outputs[0], _jsonable(table))
            text = compare_markdown(table)
            with atomic_output(outputs[1]) as tmp:
                tmp.write_text(text)
            compare_plot(table, outputs[2])
            compare_lights_figure(lights, problem.data.cube, outputs[3])
            _write_lights(outputs[4], lights, problem.data.cube)
        seconds = time.monotonic() - t0
        cache.record(d, outputs, seconds, {"rows": len(rows)})
        console.result(text.rstrip())
        for p in outputs:
            console.say(f"compare: wrote {cache.relative(p)}")
    return d


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


def _write_lights(path: Path, lights: list, cube) -> None:
    """Each basis' texel light (datasets in the table's row order, named by basis) with the cube map."""
    with atomic_output(path) as tmp:
        with h5_file(tmp) as f:
            f.attrs.update({"format": "wavelight-compare-lights-1", "resolution": cube.resolution,
                            "hemisphere": cube.hemisphere, "units": "linear radiance per texel"})
            for k, (label, texels) in enumerate(lights):
                ds = f.create_dataset(f"{k:02d}_{label.split(' ')[0]}", data=np.asarray(texels, np.float32))
                ds.attrs["label"] = label


def compare_lights_figure(lights: list, cube, path: Path) -> None:
    """Each basis' light on the cube cross, side by side, at one exposure (negative radiance of a
    plain SH fit shown in blue)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipelines import cubemap, images

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


def compare_plot(table: dict, path: Path) -> None:
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
