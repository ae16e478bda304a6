"""The compare stage: every basis on one scene, on the same pixels and transport -> a table of
size, fit and held-out error, time and the lowest radiance, and each basis' light."""

from __future__ import annotations

from dataclasses import dataclass, replace


from ..light.bases import COMPARE_RUNS
from ..model.materials import Material
from .solve import Progress, SolveOptions, _Systems, bright_texels, pixel_counts, prepare_photo, recast_bright

COLUMNS = {"fit_rmse": "relative RMSE over the fit pixels at the chosen level",
           "held_out_rmse": "relative RMSE over the held-out pixels (not fitted)",
           "all_pixels_rmse": "relative RMSE of the final light (re-solved on all fitted and held-out pixels)",
           "seconds": "solve time after the system is built",
           "min_radiance_relative": "lowest texel radiance / highest (negative: not a light)"}


@dataclass
class CompareResult:
    rows: list  # one dict per run
    lights: list  # (label, (N, 3) texel light) per run
    pixels: dict
    sample: dict | None
    system_seconds: float
    observability: dict


def compare_scene(vis, photo, material: Material, options: SolveOptions, photo_path=None,
                  progress: Progress | None = None, backend=None, adaptive: bool = False) -> CompareResult:
    """Solve the light in every basis (`bases.COMPARE_RUNS`) on one system of `material`: the
    system `solve` ends on (with `adaptive`, the default wavelet light's brightest directions cast
    exactly for every pixel by `backend`), so the wavelet row is the default solve's light."""
    from ..light import bases
    from ..light import solution as ls

    progress = progress or Progress()
    values, usable, held = prepare_photo(vis, photo, options, photo_path)
    systems = _Systems(vis, values, usable, held, options, progress)
    ne = systems.system(material)
    first = None  # the default light before the cast, when the cast corrected its system in place
    if adaptive and backend is not None:
        o = options.light
        first = bases.solve(ne, vis.cube, o.basis, o.levels_value, o.min_gain, o.face_resolution, o.sh_order,
                            o.sh_nonnegative)
        texels = bright_texels(first.light, systems.vis.cube)
        if len(texels):  # (corrected in place on the sampled route, as solve's)
            keep = None if options.exact else ne
            ne = None
            _, ne, _ = recast_bright(systems, backend, texels, material, o, progress, resolve=False, system=keep)
        if options.exact or not len(texels):
            first = None
    observability, unobservable = ls.observability(ne)
    rows, lights = [], []
    for basis, variant in COMPARE_RUNS:
        o = replace(options.light, basis=basis, **variant)
        # the default basis follows the levels of its light before the cast, as `solve` does (`recast_bright`)
        sol = bases.replay(ne, vis.cube, first, o.levels_value, o.min_gain) if (
            first is not None and o == options.light) else None
        if sol is None:
            sol = bases.solve(ne, vis.cube, o.basis, o.levels_value, o.min_gain, o.face_resolution, o.sh_order,
                              o.sh_nonnegative)
        lights.append((f"{sol.basis} ({sol.n_coefficients})", sol.light))
        min_rel = sol.details.get("min_radiance_relative", float(sol.light.min() / max(sol.light.max(), 1e-300)))
        rows.append({"basis": sol.basis, "coefficients": sol.n_coefficients, "levels": len(sol.levels),
                     "fit_rmse": sol.levels[sol.chosen].fit_rmse, "held_out_rmse": sol.held_out_rmse,
                     "all_pixels_rmse": sol.fit_rmse, "seconds": sol.seconds, "min_radiance_relative": min_rel,
                     "kkt_residual": sol.solver.get("kkt_residual")})
        progress.note(f"{sol.basis}: {sol.n_coefficients} coefficients, {100 * sol.fit_rmse:.2f} % in {sol.seconds:.2f} s")
    n = len(observability)
    n_unobs = int(unobservable.sum())
    return CompareResult(rows, lights, pixel_counts(usable, held, False),
                         systems.sample_info,
                         getattr(ne, "seconds", 0.0),
                         {"texels": n, "unobservable": n_unobs, "unobservable_fraction": n_unobs / max(n, 1),
                          "weakly_observed": int(((observability < 1e-3) & ~unobservable).sum())})
