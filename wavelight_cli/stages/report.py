"""`wavelight report`: out/report.md, out/report.html and their figures (out/report/*.png) from what
the stages wrote.

Every number in the report is read from the stages' JSON files (solve_report.json,
reflectance.json, compare.json, relight/insert JSONs, export/export.json, camera.json, pose.json);
the figures are drawn from their images and from out/coefficients.h5 (`report_figures`). Nothing is
recomputed, so the report always shows the results as they are on disk.

The report is built once as a list of sections of blocks (`Doc`) and written twice: as Markdown
(images linked, relative to out/) and as one self-contained HTML page (`report_html`: every image a
data URI, no script, style or font from elsewhere).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from pipelines.errors import InputError
from pipelines.io.files import atomic_output, discard

from ..console import Console
from ..scene import SceneFiles, require
from . import report_figures as figs

SOURCES = ("solve_report.json", "reflectance.json", "compare.json", "report.json")
OUTPUT_PREFIX = "output-"  # out/report/output-NAME-*.png: figures of relight / insert outputs


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


def _num(x, fmt: str = ".4g") -> str:
    try:
        return format(float(x), fmt)
    except (TypeError, ValueError):
        return "–"


def _rgb(v) -> str:
    if isinstance(v, (list, tuple)):
        return "(" + ", ".join(_num(x, ".3g") for x in v) + ")"
    return _num(v, ".3g")


# -- the document ------------------------------------------------------------------------------------------

@dataclass
class Section:
    anchor: str
    title: str
    blocks: list = field(default_factory=list)

    def p(self, text: str):
        self.blocks.append(("p", text))

    def fig(self, rel: str, alt: str, caption: str = ""):
        self.blocks.append(("figs", [(rel, alt, caption)]))

    def figs(self, items: list[tuple[str, str, str]]):
        if items:
            self.blocks.append(("figs", items))

    def table(self, head: list[str], rows: list[list[str]], align: str):
        self.blocks.append(("table", head, rows, align))

    def numbers(self, pairs: list[tuple[str, str]]):
        self.blocks.append(("numbers", pairs))

    def items(self, entries: list[str]):
        self.blocks.append(("list", entries))

    def h3(self, text: str, anchor: str = ""):
        self.blocks.append(("h3", text, anchor))

    def slider(self, under: str, over: str, labels: tuple[str, str], caption: str):
        self.blocks.append(("slider", under, over, labels, caption))


@dataclass
class Doc:
    title: str
    intro: list = field(default_factory=list)  # blocks before the first section
    sections: list[Section] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)  # files the report read (relative to the scene)

    def section(self, anchor: str, title: str) -> Section:
        s = Section(anchor, title)
        self.sections.append(s)
        return s


def to_markdown(doc: Doc) -> str:
    lines = [f"# {doc.title}", ""]

    def block(b):
        kind = b[0]
        if kind == "p":
            lines.extend([b[1], ""])
        elif kind == "figs":
            for rel, alt, caption in b[1]:
                lines.extend([f"![{alt}]({rel})", ""])
                if caption:
                    lines.extend([f"*{caption}*", ""])
        elif kind == "table":
            _, head, rows, align = b
            lines.append("| " + " | ".join(head) + " |")
            lines.append("|" + "|".join("---:" if a == "r" else "---" for a in align) + "|")
            lines.extend("| " + " | ".join(r) + " |" for r in rows)
            lines.append("")
        elif kind == "numbers":
            lines.extend(["| | |", "|---|---|"] + [f"| {k} | {v} |" for k, v in b[1]] + [""])
        elif kind == "list":
            lines.extend([f"- {e}" for e in b[1]] + [""])
        elif kind == "h3":
            lines.extend([f"### {b[1]}", ""])
        elif kind == "slider":
            pass  # report.html only; the overview figure shows both images

    for b in doc.intro:
        block(b)
    for s in doc.sections:
        lines.extend([f"## {s.title}", ""])
        for b in s.blocks:
            block(b)
    if doc.sources:
        lines.extend([f"Read from: {', '.join(f'`{p}`' for p in doc.sources)}.", ""])
    return "\n".join(lines).rstrip("\n") + "\n"


# -- the report's content ----------------------------------------------------------------------------------

def _intro(doc: Doc, solve: dict, camera: dict | None, pose: dict | None):
    px = solve.get("pixels", {})
    opts = solve.get("options", {})
    doc.intro.append(("p", f"Photo `{solve.get('photo')}`; {px.get('used')} pixels used ({px.get('fit')} fitted, "
                           f"{px.get('held_out')} held out); light on a cube map of R = {opts.get('resolution')} "
                           f"({'hemisphere' if opts.get('hemisphere') else 'sphere'}). "
                           f"{solve.get('scale_ambiguity', '')}."))
    if camera and "calibration" in camera:
        c = camera["calibration"]
        doc.intro.append(("p", f"**Camera** (wavelight calibrate): fx {camera['fx']:.2f}, fy {camera['fy']:.2f}, "
                               f"cx {camera['cx']:.2f}, cy {camera['cy']:.2f}; RMS {c['rms_px']:.3f} px over "
                               f"{len(c['used'])} photos"
                               + (f"; rejected: {', '.join(c['rejected'])}" if c.get("rejected") else "")
                               + (f"; warnings: {'; '.join(c['warnings'])}" if c.get("warnings") else "") + "."))
    if pose and "registration" in pose:
        g = pose["registration"]
        e = g.get("edge_refinement") or {}
        doc.intro.append(("p", f"**Pose** (wavelight register): {g['method']}, {g['inliers']} of {g['points']} "
                               f"points, RMS {g['rms_px']:.3f} px"
                               + (f"; refined against the photo's edges (outline on edges "
                                  f"{100 * e['outline_on_edges_before']:.0f} -> "
                                  f"{100 * e['outline_on_edges_after']:.0f} %)" if e.get("accepted") else "") + "."))


def _result(doc: Doc, solve: dict, made: dict):
    s = doc.section("result", "Result")
    sol = solve.get("solution", {})
    if "overview" in made:
        info = made["overview"].info
        white = info.get("residual_white")
        parts = [f"Photo and relit view at one exposure ({info['exposure']:+.2f} stops: white = the photo's "
                 f"99.5th percentile)."]
        parts.append("Residual |relit - photo| per used pixel (mean of R, G, B), white = "
                     + (f"{white:.4g} (10 % of the photo's 95th-percentile radiance)." if white is not None else
                        "10 % of the photo's 95th-percentile radiance (the value is not recorded in this "
                        "residual.png: rerun wavelight solve --force)."))
        parts.append(f"Observability per texel on the cube cross: {figs.OBSERVABILITY_NOTE}, white = 1 "
                     "(the best-observed texel), black = unobservable.")
        s.fig(made["overview"].rel, "input, relit, residual, observability", " ".join(parts))
    if "photo" in made and "relit" in made:
        s.slider(made["photo"].rel, made["relit"].rel, ("photo", "relit"),
                 "Drag the slider: the input photo on the left of the line, the view relit by the recovered "
                 "light on the right (same exposure).")
    bd = solve.get("brightest_direction", {})
    relit = solve.get("relit", {})
    s.numbers([
        ("basis", f"{solve.get('basis')} ({sol.get('coefficients')} coefficients, level {sol.get('chosen_level')})"),
        ("relit error (all used pixels)", _pct(relit.get("relative_rmse_vs_photo"))),
        ("held-out error", _pct(sol.get("held_out_rmse"))),
        ("brightest direction (the brightest region's energy centroid)",
         f"theta {bd.get('centroid', bd).get('theta_deg', float('nan')):.1f} deg, "
         f"phi {bd.get('centroid', bd).get('phi_deg', float('nan')):.1f} deg"),
        ("robust fit", _robust_text(solve.get("robust", {}))),
        ("unobservable texels", f"{solve.get('observability', {}).get('unobservable')} of "
                                f"{solve.get('observability', {}).get('texels')}"),
        ("time", f"normal equations {solve.get('normal_equations_seconds', 0):.1f} s, light "
                 f"{sol.get('seconds', 0):.2f} s, whole solve {solve.get('seconds', 0):.1f} s")])
    if solve.get("warnings"):
        s.p("**What the photo cannot tell:**")
        s.items(list(solve["warnings"]))


def _robust_text(rob: dict) -> str:
    """solve_report.json's `robust` in a few words (a report of an older solve has none)."""
    if not rob:
        return "–"
    if not rob.get("applied"):
        return rob.get("note", "not applied")
    text = (f"{rob.get('down_weighted_pixels')} of {rob.get('pixels')} pixels down-weighted "
            f"({rob.get('left_out_pixels')} to zero), light solved again {rob.get('rounds')} time(s); "
            f"relit error with the weights {_pct(rob.get('relative_rmse_robust_weighted'))}")
    if rob.get("clipped_pixels"):
        text += (f"; {rob['clipped_pixels']} clipped pixels {rob.get('clipped')}"
                 + (f", {rob['clipped_pixels_below_bound']} left below their bound"
                    if "clipped_pixels_below_bound" in rob else ""))
    return text


def _views(doc: Doc, solve: dict):
    """Several photos under one light: per view its pixels, errors and what it adds to the map."""
    views = solve.get("views")
    if not views:
        return
    s = doc.section("views", "Views")
    obs = solve.get("observability_by_view", {})
    held = solve.get("held_out", {})
    s.p(f"One light fitted to the used pixels of {len(views)} photos together. Model choice: "
        f"{held.get('note', '')}. Relit error: the final light over the view's used pixels; held-out error: "
        "over the view's held-out pixels, of the light the model choice kept (fitted without them).")
    rows = []
    for name, v in views.items():
        o = obs.get("views", {}).get(name, {})
        px = v["pixels"]
        rows.append([name + (" (held out)" if v.get("held_out_whole") else ""), str(px["used"]), str(px["fit"]),
                     str(px["held_out"]), _pct(v.get("relit_rmse")), _pct(v.get("held_out_rmse")),
                     str(o.get("weakly_observed", "–")), str(o.get("adds", {}).get("well_observed", "–")),
                     f"`{v.get('outputs', '')}`"])
    s.table(["view", "pixels", "fit", "held out", "relit error", "held-out error", "weak texels alone",
             "texels it adds", "relit / residual in"], rows, "lrrrrrrrl")
    u = obs.get("union", {})
    s.p(f"All views together: {u.get('unobservable')} unobservable and {u.get('weakly_observed')} weakly observed "
        f"(sqrt(G_ii / max) < {obs.get('weak_threshold')}) of {obs.get('texels')} texels. 'Texels it adds': weakly "
        "observed without the view, not with it. Each view's own map: `observability_view.png` in its folder.")


def _light(doc: Doc, solve: dict, made: dict):
    if "light" not in made:
        return
    s = doc.section("light", "Recovered light")
    info = made["light"].info
    bd = solve.get("brightest_direction", {})
    ticks = ", ".join(f"{t:.3g}" for t in info["ticks"])
    caption = (f"Log tone mapping: a texel's brightness is the log of its brightest channel's radiance from "
               f"{info['black']:.3g} (black, and anything dimmer) to {info['white']:.4g} (white), its colour that of "
               f"its RGB; the colour bar's ticks are radiance values ({ticks}). Left: the lat-long exchange format "
               f"(`light_latlong.exr`), theta from the zenith, phi from +X towards +Y"
               + (", the upper half (the hemisphere)" if info["hemisphere"] else "") + f". Right: {info['layout']}.")
    if "theta_deg" in bd:
        caption += (f" Circle: the brightest direction (theta {bd['theta_deg']:.1f} deg, phi {bd['phi_deg']:.1f} "
                    f"deg, radiance {_rgb(bd.get('radiance_rgb'))}).")
    if info["unobservable"]:
        caption += f" Magenta: the {info['unobservable']} unobservable texels (no light)."
    s.fig(made["light"].rel, "the recovered light: lat-long and cube map", caption)
    s.p("Files: `light_latlong.exr` (linear radiance, the exchange format), `light_cross.exr` and "
        "`light_cross.png` (the cube cross), `coefficients.h5` (the basis' coefficients and every level).")


def _levels(doc: Doc, solve: dict, made: dict):
    s = doc.section("levels", "Refinement, level by level")
    if "levels" in made:
        info = made["levels"].info
        s.fig(made["levels"].rel, "levels",
              f"Each panel: that level's light on the cube cross, cropped to its texels ({info['caption']}); green "
              f"lines are the boundaries of the level's tree's leaves. One log scale for all panels: "
              f"{info['black']:.3g} (black) to {info['white']:.4g} (white), radiance at the colour bar's ticks.")
    s.table(["level", "coefficients", "leaves", "fit", "held-out", "seconds"],
            [[str(lv["level"]), str(lv["coefficients"]), str(lv.get("leaves", "–")), _pct(lv["fit_rmse"]),
              _pct(lv.get("held_out_rmse")), f"{lv['seconds']:.3f}"]
             for lv in solve.get("solution", {}).get("levels", [])], "rrrrrr")


def _parts_table(s: Section, refl: dict):
    """One row per part of the scene (reflectance.json's `parts`)."""
    def rgb(v):
        return " ".join(f"{x:.3g}" for x in v) if v else "–"

    ref = (refl.get("reference_part") or {}).get("name")
    s.p(f"Parts: one {refl.get('model')} model for the scene, a diffuse colour per part (kd: the mean over the "
        f"part's surface); the glossy parts wear its specular term (at their own ks where their pixels tell it), "
        f"the matte ones none. The reference part "
        f"**{ref}** keeps its start colour; light × albedo is known only as a product, so what the photo tells is "
        "each part's albedo relative to it.")
    s.table(["part", "faces", "pixels", "texture", "fit", "kd (mean)", "scale", "relative to reference", "specular"],
            [[p["name"], str(p["faces"]), str(p["pixels"]), p["texture"] or "–", p["fit"], rgb(p["kd"]),
              rgb(p["scale"]), rgb(p["relative_to_reference"]),
              ("yes" if p.get("specular", True) else "no")
              + (f", ks {sum(p['ks']) / 3:.3g}" if p.get("specular", True) and p.get("ks") else "")
              + (f" ({p['specular_decided_by']})" if p.get("specular_decided_by") else "")]
             for p in refl["parts"]], "lrrllrrrl")


def _reflectance(doc: Doc, refl: dict, made: dict):
    s = doc.section("reflectance", "Reflectance")
    if not refl:
        s.p("No reflectance.json.")
        return
    lobe = (f"alpha {refl.get('alpha')} ({refl.get('distribution')}, IOR {refl.get('ior')})"
            if refl.get("model") == "plastic" else f"n {refl.get('n')}")
    s.p(f"Model **{refl.get('model')}**: kd {refl.get('kd')}, ks {refl.get('ks')}, {lobe}, "
        f"ks/kd {refl.get('ks_over_kd')}. Decision: {refl.get('decision', '–')}.")
    if refl.get("parts"):
        _parts_table(s, refl)
    rounds = figs.reflectance_rounds(refl)
    probe = figs.probe_result(refl)
    probe_text = ""
    if probe is not None:
        probe_text = (f"The probe (`--reflectance auto`) fits a {probe['model']} term by LM with round 0's light "
                      f"fixed, on {probe['pixels']} pixels; no light is solved for it, so its errors are over its own "
                      f"rows: on the {probe['compared_on']} it has {_pct(probe['error'])} against Lambert's "
                      f"{_pct(probe['lambert'])} on the same rows"
                      + (f" (gain {100 * probe['gain']:.2f} %)" if probe["gain"] is not None else "")
                      + (". The light rounds followed from its material." if probe["followed"] else
                         "; it was not kept."))
    if "reflectance" in made:
        caption = ("Left: relative RMSE per light round; the ring marks the round kept (reflectance.json: "
                   f"chosen_round {refl.get('chosen_round')}).")
        if probe is not None:
            caption += " Right: t" + probe_text[1:]
        s.fig(made["reflectance"].rel, "reflectance rounds", caption)
    elif probe_text:
        s.p(probe_text)
    if rounds:
        what = {"light": "light solved under this material", "probe": "probe (LM, light of round 0 fixed)"}

        def held(r):
            if r["kind"] == "probe" and r["lambert_same_rows"] is not None:
                return f"{_pct(r['held_out_rmse'])} (Lambert on these rows: {_pct(r['lambert_same_rows'])})"
            return _pct(r["held_out_rmse"])

        s.table(["round", "what", "material", "fit", "held-out", "kept"],
                [[str(r["round"]) if r["kind"] == "light" else "probe", what[r["kind"]],
                  f"{r['model']} kd {_rgb(r['material'].get('kd'))}"
                  + (f", ks {_rgb(r['material'].get('ks'))}, " + _lobe(r["material"]) if r["model"] != "lambert" else ""),
                  _pct(r["fit_rmse"]), held(r), "**kept**" if r["kept"] else "not kept"]
                 for r in rounds], "rlllrl")


def _compare(doc: Doc, compare: dict | None, out: Path):
    if not compare:
        return
    s = doc.section("bases", "The bases side by side")
    s.p(f"Same pixels and normal equations ({compare.get('normal_equations_seconds', 0):.1f} s, not in the "
        f"times below); R = {compare.get('resolution')}.")
    s.table(["basis", "coefficients", "fit", "held-out", "all pixels", "time (s)"],
            [[row["basis"], str(row["coefficients"]), _pct(row["fit_rmse"]), _pct(row["held_out_rmse"]),
              _pct(row["all_pixels_rmse"]), f"{row['seconds']:.3f}"] for row in compare.get("rows", [])], "lrrrrr")
    items = []
    if (out / "compare.png").is_file():
        items.append(("compare.png", "speed against error",
                      "Held-out error against the solve's time (log-log); marker size grows with the coefficients."))
    if (out / "compare_lights.png").is_file():
        items.append(("compare_lights.png", "the bases' lights side by side",
                      "Each basis' light on the cube cross (cropped to its texels), log tone-mapped at one scale "
                      "(radiance at the colour bar's ticks); blue: negative radiance (a plain SH fit)."))
    s.figs(items)


def _outputs(out: Path) -> list[tuple[Path, dict, str]]:
    """The relight and insert outputs: (json path, its data, 'relight' | 'insert')."""
    found = []
    for p in sorted(out.glob("*.json")):
        if p.name in SOURCES:
            continue
        d = _json(p)
        if not d:
            continue
        if "object_pixels" in d:
            found.append((p, d, "insert"))
        elif "view" in d and "light" in d:
            found.append((p, d, "relight"))
    return found


def _relight_insert(doc: Doc, out: Path, figdir: Path, made: dict, keep: set):
    found = _outputs(out)
    if not found:
        return
    s = doc.section("outputs", "Relighting and insertion")
    for p, d, kind in found:
        name = p.stem
        png = out / f"{name}.png"
        if kind == "relight":
            turned = (f", turned {d['rotate_deg']:g} deg" if d.get("rotate_deg") else "") + (
                f", {d['light_exposure_stops']:+g} stops" if d.get("light_exposure_stops") else "")
            light = "recovered" if d.get("light") == "recovered" else f"`{Path(str(d.get('light'))).name}`"
            what = f"{light} light{turned}, " + ("the photo's view" if d.get("view") == "photo" else f"view {d.get('view')}")
            s.h3(f"`{name}.png`: {what}", f"output-{name}")
            items = [(png.name, f"{name}.png", f"the render ({d.get('pixels')} pixels, R = {d.get('resolution')})")] \
                if png.is_file() else []
            heat = figs.heat_figure(out / f"{name}_residual.png", f"{name}: |render - reference|",
                                    figdir / f"{OUTPUT_PREFIX}{name}-residual.png", label="radiance")
            if heat is not None:
                made[f"{name}-residual"] = _rel(heat, out)
                keep.add(heat.path.name)
                white = heat.info["white"]
                items.append((made[f"{name}-residual"].rel, f"{name}_residual.png",
                              "|render - reference| (mean of R, G, B), white = "
                              + (f"{white:.4g}" if white is not None else "10 % of the reference's 95th percentile")))
            s.figs(items)
            rows = [("light", f"{d.get('light')}{turned}"), ("view", str(d.get("view"))),
                    ("pixels", str(d.get("pixels"))), ("cube map R", str(d.get("resolution"))),
                    ("material", _material(d.get("material")))]
            if "relative_rmse_vs_photo" in d:
                rows += [("error vs reference", f"{_pct(d['relative_rmse_vs_photo'])} "
                                                f"({Path(str(d.get('reference'))).name}, "
                                                f"{d.get('compared_pixels')} pixels)"),
                         ("bias vs reference", _pct(d.get("bias_vs_photo")))]
            else:
                rows.append(("error vs reference", "– (no reference: another light or view than the photo's)"))
            s.numbers(rows)
        else:
            s.h3(f"`{name}.png`: {d.get('object')} inserted at {d.get('at')}", f"output-{name}")
            items = [(png.name, f"{name}.png", "the photo with the object and its shadows")] if png.is_file() else []
            heat = figs.heat_figure(out / f"{name}_shadow.png", f"{name}: shadow (relative darkening)",
                                    figdir / f"{OUTPUT_PREFIX}{name}-shadow.png",
                                    default_scale=figs.INSERT_SHADOW_WHITE, label="relative darkening")
            if heat is not None:
                made[f"{name}-shadow"] = _rel(heat, out)
                keep.add(heat.path.name)
                items.append((made[f"{name}-shadow"].rel, f"{name}_shadow.png",
                              f"the darkening the object casts on the known geometry, white = "
                              f"{100 * heat.info['white']:.0f} % darker"))
            s.figs(items)
            s.numbers([("object", f"{d.get('object')} at {d.get('at')}"),
                       ("object pixels", f"{d['object_pixels']} px, shadow on {d.get('shadowed_pixels_5pct')} px "
                                         f"(> 5 % darker)"),
                       ("darkest shadow", _pct(-d["darkest_shadow"]) + " darker" if "darkest_shadow" in d else "–"),
                       ("cube map R", str(d.get("resolution"))), ("light", str(d.get("light"))),
                       ("object material", _material(d.get("object_material"))),
                       ("scene material", _material(d.get("scene_material")))])


def _material(m) -> str:
    if not isinstance(m, dict):
        return "–"
    text = f"{m.get('model')} kd {_rgb(m.get('kd'))}"
    if m.get("model") != "lambert":
        text += f", ks {_rgb(m.get('ks'))}, " + _lobe(m)
    return text


def _lobe(m: dict) -> str:
    if m.get("model") == "plastic":
        return f"alpha {_num(m.get('alpha'), '.3g')} ({m.get('distribution')})"
    return f"n {_num(m.get('n'), '.3g')}"


EXPORT_TOOLS = (  # folder, tool, how to use (README: Relight, insert, export, report; pipelines/io/exports.py)
    ("mitsuba", "Mitsuba 3",
     "put `emitter.xml`'s `<emitter>` into the scene's XML, with `light.exr` beside the scene file "
     "(its `to_world` turns Mitsuba's +Y-up map to our +Z up); `bsdf.xml`'s `<bsdf>` into the object's `<shape>`"),
    ("blender", "Blender",
     "World > Surface: Environment Texture (Equirectangular), open `light_equirect.exr` (world +Z up, "
     "no rotation needed), or run `setup_world.py`; `setup_material.py` (or `material.json`'s settings) "
     "makes the material on the active object"),
    ("opengl", "OpenGL / three.js",
     "the six faces are GL_TEXTURE_CUBE_MAP_POSITIVE_X ... NEGATIVE_Z in the order px, nx, py, ny, pz, nz "
     "for a Y-up world ((x, y, z)_gl = (x, z, -y)); three.js: load them (EXRLoader) into a CubeTexture in "
     "that order"),
)


def _exports(doc: Doc, out: Path):
    ex = _json(out / "export" / "export.json")
    if not ex:
        return
    s = doc.section("exports", "Exports")
    energy = " ".join(_num(e) for e in ex.get("energy_rgb", []))
    s.p(f"The {'recovered light' if ex.get('source') == 'recovered' else '`' + str(ex.get('source')) + '`'} "
        f"in other tools' conventions, in `out/export/` (energy RGB {energy}; lat-long {ex.get('latlong_height')} "
        f"rows, cube faces {ex.get('face_size')} px).")
    files = [str(f) for f in ex.get("files", [])]
    rows = []
    for folder, tool, how in EXPORT_TOOLS:
        mine = [f.split("/export/", 1)[-1] for f in files if f"/export/{folder}/" in f or f.startswith(f"{folder}/")]
        if mine:
            rows.append([tool, ", ".join(f"`{m}`" for m in mine), how])
    s.table(["tool", "files (in out/export/)", "how to use"], rows, "lll")
    mat = ex.get("material") if isinstance(ex.get("material"), dict) else {}
    if mat.get("model"):
        s.p(f"The material ({mat['model']}, from `{mat.get('source')}`) is exported too: "
            + ("exactly, in Mitsuba." if not mat.get("approximate") else
               "as the closest Mitsuba roughplastic, an approximation (export.json's notes say how).")
            + (f" Its colours were divided by {_num(mat.get('light_scale'))} and the light multiplied by it."
               if (mat.get("light_scale") or 1) > 1 else ""))


def _check_solve_files(out: Path) -> None:
    """The solve's light and images the figures read, read once before any figure is drawn: a damaged
    one is refused naming it (a truncated coefficients.h5 named the scene folder and the disk, and
    left the figures drawn before it without their pages)."""
    from pipelines.io import images
    from pipelines.io.light_file import read_solution_light

    fix = "rerun wavelight solve --force"
    path = out / "coefficients.h5"
    if path.is_file():
        try:
            read_solution_light(path)
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(f"cannot read the solved light ({(str(exc).splitlines() or [''])[0]})", path, fix) from None
    for name in ("light_latlong.exr", "relit.exr", "residual.png", "observability.png"):
        if (out / name).is_file():
            try:
                images.read_latlong(out / name) if name == "light_latlong.exr" else images.read_image(
                    out / name, linear=True)
            except InputError as exc:
                raise InputError(exc.problem, out / name, fix) from None


@dataclass
class Made:
    path: Path
    rel: str
    info: dict


def _rel(fig: figs.Figure, out: Path) -> Made:
    return Made(fig.path, fig.path.relative_to(out).as_posix(), fig.info)


def build(scene: SceneFiles) -> tuple[Doc, dict]:
    """Read the results, draw the figures into out/report/ and lay out the report."""
    from pipelines.light.cubemap import CubeMap

    out = scene.out
    solve = _json(require(out / "solve_report.json", "run wavelight solve first"))
    refl = _json(out / "reflectance.json") or solve.get("reflectance") or {}
    compare = _json(out / "compare.json")
    camera = _json(scene.camera) if scene.camera.is_file() else None
    pose = _json(scene.pose) if scene.pose.is_file() else None
    _outputs(out)  # a corrupt relight/insert JSON is an error before anything is drawn
    _json(out / "export" / "export.json")
    _check_solve_files(out)  # (and a damaged light or image: nothing is drawn of a report that cannot be made)
    figdir = out / "report"
    opts = solve.get("options", {})
    try:
        cube = CubeMap(int(opts["resolution"]), bool(opts.get("hemisphere", True)))
    except (KeyError, TypeError, ValueError):
        cube = None
    made: dict[str, Made] = {}
    keep: set[str] = set()

    def add(key, fig):
        if fig is not None:
            made[key] = _rel(fig, out)
            keep.add(fig.path.name)

    add("overview", figs.overview_figure(out, solve, cube, figdir / "overview.png"))
    photo, relit, _ = figs.photo_and_relit(out, solve)
    if photo is not None and relit is not None:
        add("photo", figs.Figure(figs.save_display(photo, figdir / "photo.png")))
        add("relit", figs.Figure(figs.save_display(relit, figdir / "relit.png")))
    add("light", figs.light_figure(out, solve, figdir / "light.png"))
    add("levels", figs.levels_figure(out, figdir / "levels.png"))
    add("reflectance", figs.reflectance_figure(refl, figdir / "reflectance.png"))
    doc = Doc(f"wavelight report: {scene.root.name}")
    _intro(doc, solve, camera, pose)
    _result(doc, solve, made)
    _views(doc, solve)
    _light(doc, solve, made)
    _levels(doc, solve, made)
    _reflectance(doc, refl, made)
    _compare(doc, compare, out)
    _relight_insert(doc, out, figdir, made, keep)
    _exports(doc, out)
    # figures of earlier runs whose inputs are gone: removed once the pages are written
    made["_stale"] = [old for old in figdir.glob("*.png") if old.name not in keep]
    root = scene.root
    read = [out / n for n in SOURCES[:3]] + [p for p, _, _ in _outputs(out)] + [out / "export" / "export.json",
                                                                                  scene.camera, scene.pose]
    doc.sources = [p.relative_to(root).as_posix() for p in read if p.is_file()]
    return doc, made


def report_stage(scene: SceneFiles, console: Console, lock_wait: float = 600.0) -> Path:
    """out/report.md, report.html and report/*.png, under the scene lock (no stage changes what it
    reads meanwhile). Each file is replaced atomically; the pages embed the figures just written,
    so those are in place first, and stale figures go only after the pages are."""
    from ..cache import SceneCache
    from .report_html import to_html

    t0 = time.monotonic()
    out = scene.out
    md = out / "report.md"
    page = out / "report.html"
    with SceneCache(scene.root).lock(lock_wait, console.say):
        doc, made = build(scene)
        with atomic_output(md) as tmp:
            tmp.write_text(to_markdown(doc))
        with atomic_output(page) as tmp:
            tmp.write_text(to_html(doc, out), encoding="utf-8")
        for old in made.pop("_stale", []):
            discard(old)
    n = len(list((out / "report").glob("*.png")))
    console.result(f"report: {md} and {page.name} ({n} figures in report/, {time.monotonic() - t0:.1f} s)")
    return md
