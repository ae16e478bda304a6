"""The figures of `wavelight report` (out/report/*.png), drawn from the images and files the stages
wrote: nothing is solved or rendered again. Heat maps get colour bars with their scale (read from the
PNG's text, `outputs.write_heat_png`); lights are log tone-mapped (`outputs.log_display`) with the
radiance at the colour bar's ticks.

Each figure function returns a `Figure` (its path and what a caption needs), or None when its inputs
are not on disk.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipelines.io.files import atomic_output

from ..outputs import heat_colours, log_colours, log_display, log_range, photo_exposure, read_png_text, read_rgba

DEAD = (1.0, 1.0, 1.0)  # figure pixels that hold no texel
OUTLINE = (0.1, 0.9, 0.3)  # the tree's leaf boundaries
UNOBSERVABLE = (0.6, 0.0, 0.6)
OBSERVABILITY_NOTE = "sqrt(G_ii / max G_ii)"
# `wavelight insert` draws NAME_shadow.png as heat_map(relative darkening, 0.5); insert stage
# version 2 did not record the scale in the PNG's text: used when the text does not say.
INSERT_SHADOW_WHITE = 0.5


@dataclass
class Figure:
    path: Path | None  # None: not saved (dest None), the matplotlib figure is info["figure"]
    info: dict = field(default_factory=dict)


def _done(fig, dest: Path | None, info: dict) -> Figure:
    """Save and close `fig` at `dest`; with dest None keep it open in the result (for tests)."""
    if dest is None:
        return Figure(None, info | {"figure": fig})
    return Figure(save(fig, dest), info)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: Path, dpi: int = 110) -> Path:
    plt = _plt()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png", facecolor="white")
    plt.close(fig)
    return path


def save_display(image: np.ndarray, path: Path) -> Path:
    """An image of display values in [0, 1] as it is (no figure around it)."""
    from ..outputs import write_display_png

    path.parent.mkdir(parents=True, exist_ok=True)
    return write_display_png(path, image)


def heat_cmap():
    from matplotlib.colors import ListedColormap

    return ListedColormap(heat_colours(256), name="wavelight-heat")


def _read_display(path: Path) -> np.ndarray | None:
    from pipelines.io import images

    return images.read_image(path, linear=True).pixels if path.is_file() else None


def heat_scale(path: Path, default: float | None = None) -> tuple[float | None, str, str]:
    """(value shown white, what, units) of a heat-map PNG, from its text; `default` when it has none."""
    text = read_png_text(path) if path.is_file() else {}
    try:
        scale = float(text["wavelight:heat_scale"])
    except (KeyError, ValueError):
        scale = default
    return scale, text.get("wavelight:heat_what", ""), text.get("wavelight:heat_units", "")


def _colour_bar(fig, ax, scale: float | None, label: str):
    """A heat-map colour bar beside `ax`: 0 .. scale (or 0 .. 1 of an unrecorded scale)."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    from mpl_toolkits.axes_grid1 import make_axes_locatable

    top = 1.0 if scale is None else scale
    sm = ScalarMappable(Normalize(0.0, top), heat_cmap())
    cax = make_axes_locatable(ax).append_axes("right", size="5%", pad=0.05)  # as tall as the image
    bar = fig.colorbar(sm, cax=cax)
    bar.set_ticks(np.linspace(0.0, top, 5))
    bar.ax.tick_params(labelsize=7)
    bar.set_label(label if scale is not None else f"{label} (fraction of an unrecorded scale)", fontsize=7)
    return bar


def _log_colour_bar(fig, ax, lo: float, hi: float, label: str, **kw):
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import FuncFormatter

    from matplotlib.colors import ListedColormap

    sm = ScalarMappable(LogNorm(lo, hi), ListedColormap(log_colours(256), name="wavelight-log"))
    bar = fig.colorbar(sm, ax=ax, **({"fraction": 0.046, "pad": 0.03} | kw))
    ticks = log_ticks(lo, hi)
    bar.set_ticks(ticks)
    bar.ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}" if v < 1000 else f"{v:.0f}"))
    bar.ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
    bar.ax.tick_params(labelsize=7)
    bar.set_label(label, fontsize=7)
    return bar


def log_ticks(lo: float, hi: float) -> list[float]:
    """Colour-bar ticks of a log scale from lo to hi: the ends and the powers of ten between them
    (1-2-5 steps when fewer than two decades)."""
    ticks = [lo]
    steps = (1.0,) if np.log10(hi / lo) >= 2 else (1.0, 2.0, 5.0)
    for k in range(int(np.floor(np.log10(lo))), int(np.ceil(np.log10(hi))) + 1):
        for s in steps:
            v = s * 10.0 ** k
            if lo * 2.5 < v < hi / 2.5:  # not crowding the ends' labels
                ticks.append(v)
    return ticks + [hi]


# -- photo, relit, residual, observability -----------------------------------------------------------------

def photo_and_relit(out: Path, solve: dict) -> tuple[np.ndarray | None, np.ndarray | None, float | None]:
    """(photo, relit) as display images at one exposure (the photo's: `outputs.photo_exposure`, as
    relit.png), and that exposure in stops; None for what is not on disk. The relit view shows the
    photo where nothing was rendered (relit.exr's alpha), as relit.png does."""
    from pipelines.io import images

    rgba = read_rgba(out / "relit.exr") if (out / "relit.exr").is_file() else None
    photo = None
    name = solve.get("photo")
    if name and (out.parent / name).is_file():
        photo = images.read_image(out.parent / name).pixels
    if rgba is None and photo is None:
        return None, None, None
    relit = None if rgba is None else rgba[..., :3]
    if relit is not None and photo is not None and photo.shape == relit.shape:
        relit = np.where(rgba[..., 3:] > 0.5, relit, photo)
    exposure = photo_exposure(photo if photo is not None else relit)
    show = lambda img: None if img is None else images.tonemap(img, exposure)  # noqa: E731
    return show(photo), show(relit), exposure


def crop_to(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    rows, cols = np.nonzero(valid)
    return image[rows.min():rows.max() + 1, cols.min():cols.max() + 1]


def observability_image(out: Path, cube) -> np.ndarray | None:
    """out/observability.png (an enlarged cross) cropped to the cross' texels, DEAD where no texel
    is (the PNG is already cropped, transparent there: `outputs.cross_preview`; an older one is the
    whole cross, cropped here)."""
    from pipelines.light import cubemap

    path = out / "observability.png"
    if not path.is_file():
        return None
    rgba = read_rgba(path)
    if read_png_text(path).get("wavelight:layout"):
        img = rgba[..., :3].astype(np.float64)
        img[rgba[..., 3] < 0.5] = DEAD
        return img
    img = _read_display(path)
    _, valid = cubemap.cross_image(np.zeros(cube.n_texels), cube)
    k = img.shape[1] // valid.shape[1]
    if k < 1 or img.shape[0] != k * valid.shape[0]:
        return img  # not the layout we know: as it is
    big = np.repeat(np.repeat(valid, k, axis=0), k, axis=1)
    img = img.copy()
    img[~big] = DEAD
    return crop_to(img, big)


def overview_figure(out: Path, solve: dict, cube, dest: Path | None) -> Figure | None:
    """input | relit | residual (colour bar) | observability (colour bar)."""
    plt = _plt()
    photo, relit, exposure = photo_and_relit(out, solve)
    if relit is None:
        return None
    panels = []
    if photo is not None:
        panels.append(("input photo", photo, None))
    panels.append(("relit (recovered light)", relit, None))
    info = {"exposure": exposure}
    if (out / "residual.png").is_file():
        scale, _, units = heat_scale(out / "residual.png")
        info["residual_white"] = scale
        panels.append(("|relit - photo|", _read_display(out / "residual.png"), (scale, f"{units or 'radiance'}")))
    obs = observability_image(out, cube) if cube is not None else None
    if obs is not None:
        panels.append(("observability", obs, (1.0, OBSERVABILITY_NOTE)))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.4 * len(panels), 3.0))
    for ax, (title, img, heat) in zip(np.atleast_1d(axes), panels):
        ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        if heat is not None:
            _colour_bar(fig, ax, heat[0], heat[1])
    fig.tight_layout()
    return _done(fig, dest, info)


def heat_figure(png: Path, title: str, dest: Path | None, default_scale: float | None = None,
                label: str | None = None) -> Figure | None:
    """One heat-map PNG with its colour bar."""
    plt = _plt()
    img = _read_display(png)
    if img is None:
        return None
    scale, what, units = heat_scale(png, default_scale)
    fig, ax = plt.subplots(figsize=(4.6, 3.2))
    ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.axis("off")
    _colour_bar(fig, ax, scale, label or units or "value")
    return _done(fig, dest, {"white": scale, "what": what, "units": units})


# -- the light ---------------------------------------------------------------------------------------------

def hemisphere_layout(cube) -> np.ndarray:
    """(2R, 2R) texel index (-1: no texel) of the hemisphere unfolded around the zenith, seen from
    above: +Z in the centre square (rows along +X, columns along +Y, as in the cross), each side
    face's upper half folded out beside the +Z edge it shares (+X below, +Y right, -X above, -Y
    left), the horizon at the outer edges, the four corners empty."""
    R = cube.resolution
    c = (np.arange(2 * R) + 0.5 - R) * (2.0 / R)  # face units: [-2, 2], the +Z face is [-1, 1]
    U, V = np.meshgrid(c, c, indexing="ij")  # U along +X (rows), V along +Y (columns)
    one = np.ones_like(U)
    d = np.full(U.shape + (3,), np.nan)
    top = (np.abs(U) <= 1) & (np.abs(V) <= 1)
    d[top] = np.stack([U, V, one], -1)[top]
    for sel, vec in (((U > 1) & (np.abs(V) <= 1), (one, V, 2 - U)), ((U < -1) & (np.abs(V) <= 1), (-one, V, 2 + U)),
                     ((V > 1) & (np.abs(U) <= 1), (U, one, 2 - V)), ((V < -1) & (np.abs(U) <= 1), (U, -one, 2 + V))):
        d[sel] = np.stack(vec, -1)[sel]
    return cube.lookup(d)


def hemisphere_position(direction, R: int) -> tuple[float, float] | None:
    """(row, column) in `hemisphere_layout`'s image (pixel centres at integers) of a direction."""
    x, y, z = (float(v) for v in direction)
    if z < 0:
        return None
    ax, ay = abs(x), abs(y)
    if z >= ax and z >= ay:
        U, V = x / z, y / z
    elif ax >= ay:
        U, V = np.sign(x) * (2 - z / ax), y / ax
    else:
        U, V = x / ay, np.sign(y) * (2 - z / ay)
    return U * R / 2 + R - 0.5, V * R / 2 + R - 0.5


def layout_image(texels: np.ndarray, index: np.ndarray, dead=DEAD) -> np.ndarray:
    img = np.asarray(texels)[np.clip(index, 0, None)].astype(np.float64)
    img[index < 0] = dead
    return img


def cross_crop(cube):
    """(texel index of the cross (3R, 4R) cropped to the rows and columns that hold texels)."""
    from pipelines.light import cubemap

    ids, valid = cubemap.cross_image(np.arange(cube.n_texels, dtype=np.float64), cube, fill=-1)
    return crop_to(ids.astype(np.int64), valid)


def cross_caption(cube) -> str:
    """Where the faces are in `cross_crop`'s image, from the cross layout itself (CROSS_BLOCKS)."""
    from pipelines.light import cubemap

    blocks = {f: cubemap.CROSS_BLOCKS[f] for f in (cubemap.FACE_NAMES if not cube.hemisphere
                                                   else ("+z",) + cubemap.SIDE_FACES)}
    cols = sorted({c for _, c in blocks.values()})
    rows = sorted({r for r, _ in blocks.values()})

    def where(face):
        r, c = blocks[face]
        vert = "top" if r == rows[0] else ("bottom" if r == rows[-1] else "middle")
        horiz = "left" if c == cols[0] else ("right" if c == cols[-1] else f"column {cols.index(c) + 1} of {len(cols)}")
        below = [f for f, (rr, cc) in blocks.items() if cc == c and rr == r + 1]
        return f"{face.upper()} at the {vert} {horiz}" + (f", above {below[0].upper()}" if below else "")

    sides = sorted(cubemap.SIDE_FACES, key=lambda f: blocks[f][1])
    text = (f"{where('+z')}; the side faces {', '.join(f.upper() for f in sides)} left to right in the row "
            f"below it" + (" (their upper halves: the hemisphere)" if cube.hemisphere else ""))
    if not cube.hemisphere:
        text += f"; {where('-z')}"
    return text


HEMISPHERE_CAPTION = ("the hemisphere unfolded around the zenith, seen from above: +Z in the centre square, "
                      "the side faces' upper halves folded out around it (+X below, +Y right, -X above, -Y left), "
                      "the horizon at the outer edges")


def _light_info(lo, hi):
    return {"black": lo, "white": hi, "ticks": log_ticks(lo, hi)}


def light_figure(out: Path, solve: dict, dest: Path | None) -> Figure | None:
    """The recovered light as a lat-long image and on the cube (hemisphere: unfolded around the
    zenith; sphere: the cross), log tone-mapped at one scale, with its colour bar."""
    from pipelines.io import images
    from pipelines.io.light_file import read_solution_light

    plt = _plt()
    path = out / "coefficients.h5"
    if not path.is_file():
        return None
    texels, cube, _ = read_solution_light(path)
    import h5py

    with h5py.File(path, "r") as f:
        unobservable = f["unobservable"][:].astype(bool) if "unobservable" in f else np.zeros(cube.n_texels, bool)
    lo, hi = log_range(texels)
    latlong = images.read_latlong(out / "light_latlong.exr") if (out / "light_latlong.exr").is_file() else None
    if cube.hemisphere:
        index = hemisphere_layout(cube)
        layout = HEMISPHERE_CAPTION
    else:
        index = cross_crop(cube)
        layout = "the cube cross: " + cross_caption(cube)
    disp, _, _ = log_display(layout_image(texels, index, (0, 0, 0)), lo, hi)
    disp[index < 0] = DEAD
    disp[(index >= 0) & unobservable[np.clip(index, 0, None)]] = UNOBSERVABLE
    bd = solve.get("brightest_direction") or {}
    ratios = [2.4, 1.25] if latlong is not None else [1.25]
    fig, axes = plt.subplots(1, len(ratios), figsize=(3.3 * sum(ratios) + 0.8, 3.3),
                             gridspec_kw={"width_ratios": ratios}, squeeze=False)
    axes = list(axes[0])
    if latlong is not None:
        ax = axes.pop(0)
        H = latlong.shape[0]
        rows = H // 2 if cube.hemisphere else H
        ll, _, _ = log_display(latlong[:rows], lo, hi)
        ax.imshow(ll, extent=(0, 360, 180.0 * rows / H, 0), aspect="auto", interpolation="nearest")
        ax.set_xlabel("phi (deg, from +X towards +Y)", fontsize=8)
        ax.set_ylabel("theta (deg from the zenith)", fontsize=8)
        ax.set_xticks(range(0, 361, 90))
        ax.tick_params(labelsize=7)
        ax.set_title("lat-long (exchange format)", fontsize=9)
        if "theta_deg" in bd:
            ax.plot([bd["phi_deg"]], [bd["theta_deg"]], "o", ms=11, mfc="none", mec=(0.1, 0.9, 1.0), mew=1.2)
    ax = axes[0]
    ax.imshow(disp, interpolation="nearest")
    ax.set_title("cube map (hemisphere, from above)" if cube.hemisphere else "cube cross", fontsize=9,
                 pad=14 if cube.hemisphere else 6)
    ax.set_xticks([])
    ax.set_yticks([])
    for s in ax.spines.values():
        s.set_visible(False)
    if cube.hemisphere:
        R = cube.resolution
        for label, (r, c), off in (("-X", (-0.5, R - 0.5), (0, 7)), ("+X", (2 * R - 0.5, R - 0.5), (0, -7)),
                                   ("+Y", (R - 0.5, 2 * R - 0.5), (9, 0)), ("-Y", (R - 0.5, -0.5), (-9, 0))):
            ax.annotate(label, (c, r), xytext=off, textcoords="offset points", ha="center", va="center",
                        fontsize=8, annotation_clip=False)
        if "direction" in bd:
            pos = hemisphere_position(bd["direction"], R)
            if pos is not None:
                ax.plot([pos[1]], [pos[0]], "o", ms=11, mfc="none", mec=(0.1, 0.9, 1.0), mew=1.2)
    _log_colour_bar(fig, fig.axes, lo, hi, "radiance (brightest channel, linear; log scale)", fraction=0.03, pad=0.03)
    info = _light_info(lo, hi) | {"layout": layout, "unobservable": int(unobservable.sum()),
                                  "texels": cube.n_texels, "hemisphere": cube.hemisphere}
    return _done(fig, dest, info)


def levels_figure(out: Path, dest: Path | None) -> Figure | None:
    """The light of each refinement level on the cube cross (cropped to its texels), log tone-mapped
    at one scale, with the level's tree's leaves outlined."""
    import h5py

    from pipelines.io import light_file as lt
    from pipelines.light import cubemap, haar

    plt = _plt()
    path = out / "coefficients.h5"
    if not path.is_file():
        return None
    with h5py.File(path, "r") as f:
        basis = str(f.attrs.get("basis"))
        cube = cubemap.CubeMap(int(f.attrs["resolution"]), bool(f.attrs["hemisphere"]))
        chosen = int(f.attrs["chosen_level"]) if "chosen_level" in f.attrs else None
        levels = []
        for key in sorted(f.get("levels", {})):
            g = f["levels"][key]
            if "tree" not in g:
                continue
            tree = lt.read_tree(g["tree"])
            coef = g["coefficients"][:]
            leaves = haar.leaf_matrix(tree)
            texels = haar.synthesise(coef, tree) if basis == "wavelet" else leaves @ coef
            leaf_id = np.asarray(leaves.argmax(axis=1)).ravel()  # one leaf per texel
            levels.append((int(key), texels, leaf_id, float(g.attrs["held_out_rmse"]), coef.shape[0]))
    if not levels:
        return None
    lo = min(log_range(t)[0] for _, t, _, _, _ in levels)
    hi = max(log_range(t)[1] for _, t, _, _, _ in levels)
    index = cross_crop(cube)
    valid = index >= 0
    n = len(levels)
    cols = min(n, 3 if cube.hemisphere else 4)
    rows = (n + cols - 1) // cols
    aspect = index.shape[0] / index.shape[1]
    fig, axes = plt.subplots(rows, cols, figsize=(3.7 * cols + 0.6, (3.7 * aspect + 0.45) * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    up = max(1, 512 // index.shape[1])  # enlarged, so that leaf outlines are thin lines between texels
    for ax, (lv, texels, leaf_id, held, k) in zip(axes.ravel(), levels):
        disp, _, _ = log_display(layout_image(texels, index, (0, 0, 0)), lo, hi)
        disp[~valid] = DEAD
        ids = np.where(valid, leaf_id[np.clip(index, 0, None)], -1)
        disp = np.repeat(np.repeat(disp, up, axis=0), up, axis=1)
        vert = (ids[:, 1:] != ids[:, :-1]) & valid[:, 1:] & valid[:, :-1]  # between columns c and c + 1
        horiz = (ids[1:, :] != ids[:-1, :]) & valid[1:, :] & valid[:-1, :]
        for r, c in zip(*np.nonzero(vert)):
            disp[r * up:(r + 1) * up, (c + 1) * up] = OUTLINE
        for r, c in zip(*np.nonzero(horiz)):
            disp[(r + 1) * up, c * up:(c + 1) * up] = OUTLINE
        ax.imshow(np.clip(disp, 0, 1), interpolation="nearest")
        held_text = "–" if not np.isfinite(held) else f"{100 * held:.2f} %"
        kept = " (kept)" if lv == chosen else ""
        ax.set_title(f"level {lv}{kept}: {k} coefficients, held-out {held_text}", fontsize=8,
                     fontweight="bold" if kept else "normal")
    _log_colour_bar(fig, list(axes.ravel()), lo, hi, "radiance (brightest channel; log scale)", fraction=0.02, pad=0.02)
    return _done(fig, dest, _light_info(lo, hi) | {"caption": cross_caption(cube), "chosen": chosen,
                                                          "levels": n})


# -- reflectance rounds --------------------------------------------------------------------------------------

def reflectance_rounds(refl: dict) -> list[dict]:
    """reflectance.json's rounds with what each was: `light` (a light solved under the round's
    material) or `probe` (auto mode's LM fit with round 0's light fixed: no light of its own, its
    errors over the probe's rows, `lambert_same_rows` Lambert's error over the same rows), and
    whether it is the round kept (`chosen_round`). Rounds without `kind` (reflectance.json before
    solve version 5): a probe is the auto round 1 with an LM and no light."""
    rounds = refl.get("rounds") or []
    chosen = refl.get("chosen_round")
    old_probe = refl.get("mode") == "auto" and "probe" in (refl.get("candidates") or {})
    rows = []
    for r in rounds:
        kind = r.get("kind")
        if kind is None:
            kind = "probe" if old_probe and r.get("round") == 1 and "lm" in r and not r.get("light_seconds") else "light"
        kind = "probe" if kind == "probe" else "light"
        rows.append({"round": int(r.get("round", len(rows))), "kind": kind, "kept": r.get("round") == chosen,
                     "model": (r.get("material") or {}).get("model"), "material": r.get("material") or {},
                     "fit_rmse": r.get("fit_rmse"), "held_out_rmse": r.get("held_out_rmse"),
                     "lambert_same_rows": r.get("lambert_rmse_same_rows"),
                     "pixels": (r.get("lm") or {}).get("pixels")})
    return rows


def probe_result(refl: dict) -> dict | None:
    """auto mode's probe (reflectance.json: candidates.probe, and its round when it was not
    followed): the model, its error and Lambert's over the same rows (`compared_on`), the gain, the
    LM's rows, and whether the alternation followed it. None without a probe."""
    cand = (refl.get("candidates") or {}).get("probe")
    if refl.get("mode") != "auto" or not isinstance(cand, dict):
        return None
    probe_rounds = [r for r in reflectance_rounds(refl) if r["kind"] == "probe"]
    held = "held" in str(cand.get("compared_on", "held-out"))
    error = cand.get("held_out_rmse") if held else cand.get("fit_rmse")
    model = probe_rounds[0]["model"] if probe_rounds else next(
        (m for m in refl["candidates"] if m not in ("lambert", "probe")), "specular")
    return {"model": model, "error": error, "lambert": cand.get("lambert_rmse_same_rows"),
            "compared_on": cand.get("compared_on", "the probe's rows"), "gain": cand.get("gain"),
            "pixels": cand.get("pixels"), "significant": cand.get("ks_significant"),
            "followed": not probe_rounds}


def reflectance_axes(refl: dict):
    """(figure, (rounds axes, probe axes or None)): the light rounds' errors per round (integer
    ticks), the kept round ringed; auto's probe in a panel of its own, its error against Lambert's
    on the same rows (not a round of the light). None with fewer than two light rounds and no probe."""
    from matplotlib.ticker import FixedLocator, FuncFormatter

    plt = _plt()
    rows = reflectance_rounds(refl)
    light = [r for r in rows if r["kind"] == "light"]
    probe = probe_result(refl)
    if not light or (len(light) < 2 and probe is None):
        return None
    pct = lambda v: np.nan if v is None else 100 * float(v)  # noqa: E731
    if probe is not None:
        fig, (ax, pax) = plt.subplots(1, 2, figsize=(7.6, 3.6), gridspec_kw={"width_ratios": [3, 1.25]})
    else:
        fig, ax = plt.subplots(figsize=(6.4, 3.6))
        pax = None
    x = [r["round"] for r in light]
    ax.plot(x, [pct(r["fit_rmse"]) for r in light], "o-", color="C0", label="fit error (all used pixels)")
    if any(r["held_out_rmse"] is not None for r in light):
        ax.plot(x, [pct(r["held_out_rmse"]) for r in light], "s--", color="C1", label="held-out error")
    kept = [r for r in light if r["kept"]]
    for r in kept:
        v = r["held_out_rmse"] if r["held_out_rmse"] is not None else r["fit_rmse"]
        ax.plot([r["round"]], [pct(v)], "o", ms=17, mfc="none", mec="goldenrod", mew=2.5, zorder=5,
                label=f"kept: round {r['round']} ({r['model']})")
    ax.xaxis.set_major_locator(FixedLocator(x))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{int(round(v))}"))
    ax.set_xlim(min(x) - 0.5, max(x) + 0.5)
    ax.set_xlabel("light round (0: the light under Lambert; then reflectance, light, ...)", fontsize=8)
    ax.set_ylabel("relative RMSE (%)", fontsize=8)
    ax.tick_params(labelsize=8)
    chosen = kept[0]["round"] if kept else "?"
    ax.set_title(f"reflectance: {refl.get('model')} (round {chosen} kept)", fontsize=9)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, frameon=False)
    ax.margins(y=0.15)
    ax.grid(True, alpha=0.3)
    if pax is not None:
        values = [pct(probe["lambert"]), pct(probe["error"])]
        pax.bar([0, 1], values, width=0.55, color=["C0", "0.6"], edgecolor="0.3")
        for k, v in enumerate(values):
            if np.isfinite(v):
                pax.annotate(f"{v:.2f} %", (k, v), xytext=(0, 3), textcoords="offset points", ha="center",
                             va="bottom", fontsize=7)
        pax.xaxis.set_major_locator(FixedLocator([0, 1]))
        pax.set_xticklabels(["lambert", probe["model"]], fontsize=8)
        pax.set_xlim(-0.6, 1.6)
        finite = [v for v in values if np.isfinite(v)]
        pax.set_ylim(0, 1.25 * max(finite) if finite else 1)
        pax.tick_params(labelsize=8)
        gain = "" if probe["gain"] is None else f"gain {100 * probe['gain']:.2f} %, "
        state = "followed by light rounds" if probe["followed"] else "not kept"
        pax.set_title(f"probe ({state})", fontsize=9)
        pax.set_xlabel(f"{gain}on the {probe['compared_on']}\n({probe['pixels'] or '?'} LM pixels, "
                       "round 0's light fixed)", fontsize=7)
        pax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    return fig, (ax, pax)


def reflectance_figure(refl: dict, dest: Path | None) -> Figure | None:
    made = reflectance_axes(refl)
    if made is None:
        return None
    return _done(made[0], dest, {"rounds": reflectance_rounds(refl), "probe": probe_result(refl)})
