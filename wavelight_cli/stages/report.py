"""`wavelight report`: out/report.md and its figures (out/report/*.png) from what the stages wrote.

Every number in the report is read from the stages' JSON files (solve_report.json,
reflectance.json, compare.json, relight/insert JSONs, camera.json, pose.json); the figures are drawn
from their images and from out/coefficients.h5. Nothing is recomputed, so the report always shows
the results as they are on disk.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from pipelines.errors import InputError
from pipelines.io.files import atomic_output

from ..console import Console
from ..scene import SceneFiles, require


def _json(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read ({exc})", path, "rerun the stage that writes it (--force)") from None
    return data if isinstance(data, dict) else None


def _pct(x) -> str:
    return "–" if x is None else f"{100 * float(x):.2f} %"


def _img(path: Path):
    from pipelines.io import images

    return images.read_image(path).pixels if path.is_file() else None


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)
    return path


def _display(image):
    from pipelines.io import images

    return images.tonemap(image)


def overview_figure(out: Path, dest: Path) -> Path | None:
    """input | relit | residual | recovered light | observability."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipelines.io import images

    panels = []
    photo = None
    relit = _img(out / "relit.exr")
    if relit is None:
        return None
    report = _json(out / "solve_report.json") or {}
    scene_dir = out.parent
    photo_name = report.get("photo")
    if photo_name and (scene_dir / photo_name).is_file():
        photo = images.read_image(scene_dir / photo_name).pixels
    scale = np.percentile(photo[photo > 0], 99.5) if photo is not None and np.any(photo > 0) else None
    exposure = None if scale is None else -np.log2(scale)
    if photo is not None:
        panels.append(("input photo", images.tonemap(photo, exposure)))
    panels.append(("relit (recovered light)", images.tonemap(relit, exposure)))
    for title, name in (("|relit - photo|", "residual.png"), ("recovered light", "light_cross.png"),
                        ("observability", "observability.png")):
        if (out / name).is_file():
            panels.append((title, images.read_image(out / name, linear=True).pixels))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.0))
    for ax, (title, img) in zip(np.atleast_1d(axes), panels):
        ax.imshow(np.clip(img, 0, 1))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    return _save(fig, dest)


def levels_figure(out: Path, dest: Path) -> Path | None:
    """The light of each refinement level on the cube cross, with its tree's leaves outlined."""
    import h5py
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipelines.light import cubemap
    from pipelines.light import haar
    from pipelines.io import images
    from pipelines.io import light_file as lt

    path = out / "coefficients.h5"
    if not path.is_file():
        return None
    with h5py.File(path, "r") as f:
        basis = str(f.attrs.get("basis"))
        cube = cubemap.CubeMap(int(f.attrs["resolution"]), bool(f.attrs["hemisphere"]))
        levels = []
        for key in sorted(f.get("levels", {})):
            g = f["levels"][key]
            if "tree" not in g:
                continue
            tree = lt.read_tree(g["tree"])
            coef = g["coefficients"][:]
            if basis == "wavelet":
                texels = haar.synthesise(coef, tree)
            else:
                texels = haar.leaf_matrix(tree) @ coef
            leaf_id = np.asarray(haar.leaf_matrix(tree).argmax(axis=1)).ravel()  # one leaf per texel
            levels.append((int(key), texels, leaf_id, float(g.attrs["held_out_rmse"]), coef.shape[0]))
    if not levels:
        return None
    n = len(levels)
    cols = min(n, 4)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.9 * rows), squeeze=False)
    top = max(float(np.percentile(t[t > 0], 99.5)) if np.any(t > 0) else 1.0 for _, t, _, _, _ in levels)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (lv, texels, leaf_id, held, k) in zip(axes.ravel(), levels):
        cross, valid = cubemap.cross_image(texels, cube)
        disp = images.tonemap(cross, -np.log2(top))
        disp[~valid] = 0.15
        ids, _ = cubemap.cross_image(leaf_id.astype(np.float64), cube, fill=-1)
        up = max(1, 512 // disp.shape[1])  # enlarged, so that leaf outlines are thin lines between texels
        disp = np.repeat(np.repeat(disp, up, axis=0), up, axis=1)
        vert = (ids[:, 1:] != ids[:, :-1]) & valid[:, 1:] & valid[:, :-1]  # between columns c and c + 1
        horiz = (ids[1:, :] != ids[:-1, :]) & valid[1:, :] & valid[:-1, :]
        for r, c in zip(*np.nonzero(vert)):
            disp[r * up:(r + 1) * up, (c + 1) * up] = (0.0, 0.8, 1.0)
        for r, c in zip(*np.nonzero(horiz)):
            disp[(r + 1) * up, c * up:(c + 1) * up] = (0.0, 0.8, 1.0)
        ax.imshow(np.clip(disp, 0, 1), interpolation="nearest")
        ax.set_title(f"level {lv}: {k} coefficients, held-out {100 * held:.2f} %", fontsize=8)
    return _save(fig, dest)


def reflectance_figure(refl: dict, dest: Path) -> Path | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rounds = refl.get("rounds") or []
    if len(rounds) < 2:
        return None
    fig, ax = plt.subplots(figsize=(5, 3))
    r = [x["round"] for x in rounds]
    ax.plot(r, [100 * x["fit_rmse"] for x in rounds], "o-", label="fit")
    ax.plot(r, [100 * x["held_out_rmse"] for x in rounds], "s--", label="held-out")
    ax.set_xlabel("round (light, then reflectance)")
    ax.set_ylabel("relative RMSE (%)")
    ax.set_title(f"reflectance: {refl.get('model')}", fontsize=9)
    ax.legend()
    return _save(fig, dest)


def report_stage(scene: SceneFiles, console: Console) -> Path:
    out = scene.out
    solve = _json(require(out / "solve_report.json", "run wavelight solve first"))
    refl = _json(out / "reflectance.json") or solve.get("reflectance") or {}
    compare = _json(out / "compare.json")
    camera = _json(scene.camera) if scene.camera.is_file() else None
    pose = _json(scene.pose) if scene.pose.is_file() else None
    t0 = time.monotonic()
    figdir = out / "report"
    figures = {}
    for key, make in (("overview", lambda p: overview_figure(out, p)), ("levels", lambda p: levels_figure(out, p)),
                      ("reflectance", lambda p: reflectance_figure(refl, p))):
        path = make(figdir / f"{key}.png")
        if path is not None:
            figures[key] = path.relative_to(out).as_posix()
    sol = solve.get("solution", {})
    lines = [f"# wavelight report: {scene.root.name}", ""]
    lines += [f"Photo `{solve.get('photo')}`; {solve.get('pixels', {}).get('used')} pixels used "
              f"({solve.get('pixels', {}).get('fit')} fitted, {solve.get('pixels', {}).get('held_out')} held out); "
              f"light on a cube map of R = {solve.get('options', {}).get('resolution')} "
              f"({'hemisphere' if solve.get('options', {}).get('hemisphere') else 'sphere'}). "
              f"{solve.get('scale_ambiguity', '')}.", ""]
    if camera and "calibration" in camera:
        c = camera["calibration"]
        lines += [f"**Camera** (wavelight calibrate): fx {camera['fx']:.2f}, fy {camera['fy']:.2f}, cx {camera['cx']:.2f}, "
                  f"cy {camera['cy']:.2f}; RMS {c['rms_px']:.3f} px over {len(c['used'])} photos"
                  + (f"; rejected: {', '.join(c['rejected'])}" if c.get("rejected") else "")
                  + (f"; warnings: {'; '.join(c['warnings'])}" if c.get("warnings") else "") + ".", ""]
    if pose and "registration" in pose:
        g = pose["registration"]
        e = g.get("edge_refinement") or {}
        lines += [f"**Pose** (wavelight register): {g['method']}, {g['inliers']} of {g['points']} points, RMS "
                  f"{g['rms_px']:.3f} px" + (f"; refined against the photo's edges (outline on edges "
                                             f"{100 * e['outline_on_edges_before']:.0f} -> "
                                             f"{100 * e['outline_on_edges_after']:.0f} %)" if e.get("accepted") else "")
                  + ".", ""]
    lines += ["## Result", ""]
    if "overview" in figures:
        lines += [f"![input, relit, residual, light, observability]({figures['overview']})", ""]
    bd = solve.get("brightest_direction", {})
    relit = solve.get("relit", {})
    lines += ["| | |", "|---|---|",
              f"| basis | {solve.get('basis')} ({sol.get('coefficients')} coefficients, level {sol.get('chosen_level')}) |",
              f"| relit error (all used pixels) | {_pct(relit.get('relative_rmse_vs_photo'))} |",
              f"| held-out error | {_pct(sol.get('held_out_rmse'))} |",
              f"| brightest direction | theta {bd.get('theta_deg', float('nan')):.1f} deg, "
              f"phi {bd.get('phi_deg', float('nan')):.1f} deg |",
              f"| unobservable texels | {solve.get('observability', {}).get('unobservable')} of "
              f"{solve.get('observability', {}).get('texels')} |",
              f"| time | normal equations {solve.get('normal_equations_seconds', 0):.1f} s, light "
              f"{sol.get('seconds', 0):.2f} s, whole solve {solve.get('seconds', 0):.1f} s |", ""]
    if solve.get("warnings"):
        lines += ["**What the photo cannot tell:**", ""] + [f"- {w}" for w in solve["warnings"]] + [""]
    lines += ["## Refinement, level by level", ""]
    if "levels" in figures:
        lines += [f"![levels]({figures['levels']})", "",
                  "Each panel: that level's light on the cube cross (+Z in the middle of the top row's block, "
                  "the four sides below it); blue lines are the tree's leaves.", ""]
    lines += ["| level | coefficients | leaves | fit | held-out | seconds |", "|---:|---:|---:|---:|---:|---:|"]
    for lv in sol.get("levels", []):
        lines.append(f"| {lv['level']} | {lv['coefficients']} | {lv.get('leaves', '–')} | {_pct(lv['fit_rmse'])} | "
                     f"{_pct(lv.get('held_out_rmse'))} | {lv['seconds']:.3f} |")
    lines += ["", "## Reflectance", ""]
    if refl:
        lines += [f"Model **{refl.get('model')}**: kd {refl.get('kd')}, ks {refl.get('ks')}, n {refl.get('n')}, "
                  f"ks/kd {refl.get('ks_over_kd')}. Decision: {refl.get('decision', '–')}.", ""]
        if "reflectance" in figures:
            lines += [f"![reflectance rounds]({figures['reflectance']})", ""]
    if compare:
        lines += ["## The bases side by side", "",
                  f"Same pixels and normal equations ({compare.get('normal_equations_seconds', 0):.1f} s, not in the "
                  f"times below).", "", "| basis | coefficients | fit | held-out | all pixels | time (s) |",
                  "|---|---:|---:|---:|---:|---:|"]
        for row in compare.get("rows", []):
            lines.append(f"| {row['basis']} | {row['coefficients']} | {_pct(row['fit_rmse'])} | "
                         f"{_pct(row['held_out_rmse'])} | {_pct(row['all_pixels_rmse'])} | {row['seconds']:.3f} |")
        if (out / "compare_lights.png").is_file():
            lines += ["", "![the bases' lights side by side](compare_lights.png)"]
        if (out / "compare.png").is_file():
            lines += ["", "![speed against error](compare.png)"]
        lines.append("")
    extras = sorted(p for p in out.glob("*.json") if p.name not in (
        "solve_report.json", "reflectance.json", "compare.json", "report.json"))
    shown = [(p, _json(p)) for p in extras]
    shown = [(p, d) for p, d in shown if d and (("view" in d and "light" in d) or "object_pixels" in d)]
    if shown:
        lines += ["## Relighting and insertion", "", "| output | what | error vs reference |", "|---|---|---:|"]
        for p, d in shown:
            turned = (f", turned {d['rotate_deg']:g} deg" if d.get("rotate_deg") else "") + (
                f", {d['light_exposure_stops']:+g} stops" if d.get("light_exposure_stops") else "")
            what = (f"object at {d['at']}, {d['object_pixels']} px, shadow on {d['shadowed_pixels_5pct']} px"
                    if "object_pixels" in d else f"{d.get('light')} light{turned}, view {d.get('view')}")
            ref = f"{_pct(d.get('relative_rmse_vs_photo'))} ({Path(d['reference']).name})" \
                if "relative_rmse_vs_photo" in d else "–"
            lines.append(f"| `{p.stem}.png` | {what} | {ref} |")
        lines.append("")
    md = out / "report.md"
    with atomic_output(md) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    console.result(f"report: {md} ({len(figures)} figures in {figdir.name}/, {time.monotonic() - t0:.1f} s)")
    return md
