"""The report's figures (wavelight_cli/stages/report_figures.py), the compare plot and the heat-map
and light helpers they use (wavelight_cli/outputs.py): each test pins one defect the report had.

The figure functions are called with dest=None: the matplotlib figure is returned open (in
Figure.info["figure"]) and inspected, nothing is written.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from wavelight_cli import outputs
from wavelight_cli.stages import report_figures as rf


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import matplotlib.pyplot as plt

    plt.close("all")


def _solved(lambert_solved):
    out = lambert_solved / "out"
    solve = json.loads((out / "solve_report.json").read_text())
    from pipelines.light.cubemap import CubeMap

    return out, solve, CubeMap(int(solve["options"]["resolution"]), bool(solve["options"]["hemisphere"]))


def _colour_bars(fig):
    return [a._colorbar for a in fig.axes if hasattr(a, "_colorbar")]


def _image_axes(fig, title):
    found = [a for a in fig.axes if a.get_title() == title and a.images]
    assert len(found) == 1, [a.get_title() for a in fig.axes]
    return found[0]


def _bar_beside(fig, ax):
    """The colour bar right of `ax` at its height."""
    fig.canvas.draw()  # the axes locators place the bars
    box = ax.get_position()
    near = [b for b in _colour_bars(fig) if b.ax.get_position().x0 >= box.x1 - 1e-6
            and b.ax.get_position().x0 - box.x1 < 0.1
            and abs(b.ax.get_position().y0 - box.y0) < 0.02 and abs(b.ax.get_position().y1 - box.y1) < 0.02]
    assert len(near) == 1, f"no colour bar beside {ax.get_title()!r}"
    return near[0]


# -- heat maps: colour bars and their scale ------------------------------------------------------------------

def test_a_residual_png_records_its_scale(tmp_path):
    rng = np.random.default_rng(1)
    reference = rng.uniform(0.0, 2.0, (50, 3))
    values = reference + rng.normal(0, 0.05, (50, 3))
    pixels = np.stack(np.unravel_index(np.arange(50), (5, 10)), axis=1)
    path = outputs.write_residual(tmp_path / "r.png", values, reference, pixels, (5, 10))
    scale, what, units = rf.heat_scale(path)
    assert scale == pytest.approx(0.1 * np.percentile(reference.mean(axis=1), 95), rel=1e-5)
    assert "white = 10 %" in what and units == "linear radiance"
    assert rf.heat_scale(tmp_path / "missing.png", 0.5) == (0.5, "", "")


def test_overview_heat_maps_have_colour_bars_with_their_scale(lambert_solved):
    out, solve, cube = _solved(lambert_solved)
    fig = rf.overview_figure(out, solve, cube, None).info["figure"]
    residual = _image_axes(fig, "|relit - photo|")
    bar = _bar_beside(fig, residual)
    white = float(outputs.read_png_text(out / "residual.png")["wavelight:heat_scale"])
    assert bar.mappable.norm.vmin == 0 and bar.mappable.norm.vmax == pytest.approx(white)
    assert np.allclose(bar.cmap(np.linspace(0, 1, 256))[:, :3], outputs.heat_colours(256), atol=1e-6)
    obs = _bar_beside(fig, _image_axes(fig, "observability"))
    assert obs.mappable.norm.vmax == 1.0 and "sqrt(G_ii / max G_ii)" in obs.ax.get_ylabel()
    # the observability cross is cropped to its texels: no row or column of only dead pixels
    img = _image_axes(fig, "observability").images[0].get_array()
    dead = np.all(np.asarray(img)[..., :3] == 1.0, axis=-1)
    assert not dead.all(axis=1).any() and not dead.all(axis=0).any()
    for title in ("input photo", "relit (recovered light)"):  # photos get no colour bar
        ax = _image_axes(fig, title)
        fig.canvas.draw()
        assert not any(abs(b.ax.get_position().y0 - ax.get_position().y0) < 0.02
                       and 0 <= b.ax.get_position().x0 - ax.get_position().x1 < 0.02 for b in _colour_bars(fig))


def test_an_insert_shadow_gets_a_colour_bar_at_inserts_scale(tmp_path):
    png = outputs.write_display_png(tmp_path / "insert_shadow.png", outputs.heat_map(np.eye(8), 0.5))  # no text
    fig = rf.heat_figure(png, "shadow", None, default_scale=rf.INSERT_SHADOW_WHITE,
                         label="relative darkening").info["figure"]
    bar = _bar_beside(fig, _image_axes(fig, "shadow"))
    assert bar.mappable.norm.vmax == 0.5 and bar.ax.get_ylabel() == "relative darkening"


# -- the light: readable tone mapping, compact layout, scale stated ------------------------------------------

def test_the_hemisphere_layout_holds_every_texel_once_and_unfolds_edge_to_edge():
    from pipelines.light.cubemap import CubeMap

    for R in (4, 8, 32):
        cube = CubeMap(R)
        index = rf.hemisphere_layout(cube)
        assert index.shape == (2 * R, 2 * R)
        assert sorted(index[index >= 0].tolist()) == list(range(cube.n_texels))
        assert (index < 0).mean() == 0.25  # only the four corners are empty (the cross: 3/4 of it)
        d = cube.directions[np.clip(index, 0, None)]
        step = np.degrees(2 * np.arctan(1 / R))  # at most ~ a texel between neighbours, across folds too
        for a, b, ok in ((d[1:], d[:-1], (index[1:] >= 0) & (index[:-1] >= 0)),
                         (d[:, 1:], d[:, :-1], (index[:, 1:] >= 0) & (index[:, :-1] >= 0))):
            angle = np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))[ok]
            assert angle.max() < 1.6 * step
        # +Z in the centre with the cross' frame: rows along +X, columns along +Y
        centre = cube.directions[index[R // 2:3 * R // 2, R // 2:3 * R // 2]]
        assert np.all(centre[..., 2] >= np.abs(centre[..., :2]).max(axis=-1))
        assert np.all(np.diff(centre[..., 0], axis=0) > 0) and np.all(np.diff(centre[..., 1], axis=1) > 0)
        assert cube.directions[index[-1, R]][0] > 0.9 and cube.directions[index[0, R]][0] < -0.9  # +X below
        for direction in cube.directions[::7]:
            r, c = rf.hemisphere_position(direction, R)
            assert index[int(round(r)), int(round(c))] == cube.lookup(direction)


def test_the_light_figure_shows_the_sky_beside_the_sun(lambert_solved):
    from pipelines.io import images
    from pipelines.io.light_file import read_solution_light
    from pipelines.light import cubemap

    out, solve, _ = _solved(lambert_solved)
    texels, cube, _ = read_solution_light(out / "coefficients.h5")
    made = rf.light_figure(out, solve, None)
    fig = made.info["figure"]
    panel = _image_axes(fig, "cube map (hemisphere, from above)")
    shown = np.asarray(panel.images[0].get_array())[..., :3]
    index = rf.hemisphere_layout(cube)
    dead = np.all(shown == 1.0, axis=-1)
    assert np.array_equal(dead, index < 0)  # 1/4 empty, against 3/4 of the uncropped hemisphere cross
    lit = (index >= 0) & (texels.max(axis=1)[np.clip(index, 0, None)] > 0)
    brightness = shown.max(axis=-1)[lit]
    assert (brightness > 0.1).mean() > 0.75, "the sky is tone-mapped to black"
    assert (brightness > 0.98).mean() < 0.05, "the sun is blown into a blob"
    # the old preview (auto exposure on the cross) left most of the sky black: what the test catches
    cross, valid = cubemap.cross_image(texels, cube)
    old = images.tonemap(cross).max(axis=-1)[valid & (cross.max(axis=-1) > 0)]
    assert (old > 0.1).mean() < 0.75
    # its scale: one log colour bar, from the dimmest shown radiance to the brightest texel
    (bar,) = _colour_bars(fig)
    lo, hi = outputs.log_range(texels)
    assert hi == pytest.approx(texels.max(), rel=1e-6)
    assert (bar.mappable.norm.vmin, bar.mappable.norm.vmax) == pytest.approx((lo, hi))
    assert np.allclose(bar.get_ticks(), rf.log_ticks(lo, hi))
    assert made.info["black"] == pytest.approx(lo) and made.info["white"] == pytest.approx(hi)
    _image_axes(fig, "lat-long (exchange format)")


def _rgba_png(path):
    import OpenImageIO as oiio

    return np.asarray(oiio.ImageBuf(str(path)).get_pixels(oiio.FLOAT))


@pytest.mark.parametrize("hemisphere", [True, False])
def test_the_light_cross_png_shows_the_sky_and_draws_no_texel_as_background(tmp_path, hemisphere):
    """solve's light_cross.png: a sky 1/100 of a sun (the sun blurred over 2 % of the texels, as a
    solve spreads it) keeps the sky visible, and the cross' unused area is transparent background
    and at most half the image (it was 3/4 of it, dark grey, for a hemisphere)."""
    from pipelines.io import images
    from pipelines.light import cubemap

    cube = cubemap.CubeMap(16, hemisphere)
    sun_dir = np.array([0.5, 0.2, 0.8]) / np.linalg.norm([0.5, 0.2, 0.8])
    sun = np.argsort(-(cube.directions @ sun_dir))[: int(0.02 * cube.n_texels)]
    texels = np.ones((cube.n_texels, 3)) * (0.6, 0.7, 1.0)  # a blue sky
    texels[sun] = 100.0
    path = outputs.write_light(tmp_path, "light", texels, cube)[2]
    png = _rgba_png(path)
    assert png.shape[2] == 4
    # which texel each PNG pixel shows: the same crop and enlargement applied to the texel index
    ids, valid = cubemap.cross_image(np.arange(cube.n_texels, dtype=np.float64), cube, fill=-1)
    index = np.round(outputs.upscale(outputs.cross_preview(np.repeat(ids[..., None], 3, -1), valid))[..., 0])
    used = outputs.upscale(outputs.cross_preview(np.zeros(valid.shape + (3,)), valid))[..., 3] > 0
    assert png.shape[:2] == used.shape
    np.testing.assert_array_equal(png[..., 3] > 0.5, used)  # opaque exactly on the texels
    assert (~used).mean() <= 0.5 + 1e-9, "most of the preview holds no texel"
    assert np.all(png[~used, :3] == 0)
    sky = used & ~np.isin(index, sun)
    brightness = png[..., :3].max(axis=-1)
    assert brightness[sky].mean() > 0.3, "the sky is tone-mapped to black"
    assert brightness[used & np.isin(index, sun)].min() > 0.98
    assert png[sky][:, 2].mean() > png[sky][:, 0].mean()  # and it stays blue
    # what the old preview (auto exposure on the cross) showed of that sky
    cross, _ = cubemap.cross_image(texels, cube)
    old = images.tonemap(cross).max(axis=-1)[valid & (cross.max(axis=-1) < 50)]
    assert old.mean() < 0.15
    text = outputs.read_png_text(path)
    assert float(text["wavelight:log_white"]) == pytest.approx(100.0)
    assert float(text["wavelight:log_black"]) <= 0.6 * 1.0001


def test_the_observability_png_is_a_cropped_cross_with_its_scale(tmp_path):
    from pipelines.light import cubemap

    cube = cubemap.CubeMap(8)
    values = np.linspace(0, 0.9, cube.n_texels)  # white (1) is the report's colour for no texel
    path = outputs.write_cross_heat_png(tmp_path / "observability.png", values, cube, 1.0, "obs", "fraction")
    png = _rgba_png(path)
    assert (png[..., 3] == 0).mean() <= 0.5
    assert rf.heat_scale(path) == (1.0, "obs", "fraction")
    shown = rf.observability_image(tmp_path, cube)  # the report's panel: no texel = DEAD, same size
    assert shown.shape == png.shape[:2] + (3,)
    assert np.all(shown[png[..., 3] == 0] == 1.0) and not np.any(np.all(shown[png[..., 3] > 0] == 1.0, axis=-1))


def test_log_display_keeps_the_hue_and_maps_the_bounds():
    img = np.array([[[0.25, 0.5, 1.0], [2000.0, 1800.0, 1000.0], [0.0, 0.0, 0.0], [1e-9, 0, 0]]])
    disp, lo, hi = outputs.log_display(img, 0.01, 2000.0)
    assert (lo, hi) == (0.01, 2000.0)
    assert disp[0, 1].max() == pytest.approx(1.0) and np.all(disp[0, 2:] == 0)
    assert disp[0, 0, 2] > 0.5 and disp[0, 0, 0] < disp[0, 0, 1] < disp[0, 0, 2]  # a blue sky stays blue, visible
    grey = outputs.log_colours(5)
    assert np.allclose(grey[0], 0) and np.allclose(grey[-1], 1) and np.all(np.diff(grey[:, 0]) > 0)
    assert rf.log_ticks(0.05, 745.0) == [0.05, 1.0, 10.0, 100.0, 745.0]


# -- the levels figure's caption -------------------------------------------------------------------------------

@pytest.mark.parametrize("hemisphere", [True, False])
def test_the_levels_caption_says_where_the_cross_puts_each_face(hemisphere):
    from pipelines.light import cubemap

    cube = cubemap.CubeMap(8, hemisphere)
    index = rf.cross_crop(cube)
    face = np.where(index >= 0, cube.texel_face[np.clip(index, 0, None)], -1)
    R = cube.resolution
    z = cubemap.FACE_NAMES.index("+z")
    rows, cols = np.nonzero(face == z)
    # where +Z is drawn: block (row, col) of the cross, found from the image itself
    block = (rows.min() // R, cols.min() // R)
    nblocks = (-(-index.shape[0] // R), index.shape[1] // R)
    caption = rf.cross_caption(cube)
    assert block == (0, 0) and nblocks[1] == 4
    assert caption.startswith("+Z at the top left"), caption
    assert "middle" not in caption
    below = face[R + R // 4, cols.min()]  # the face under +Z
    assert f"above {cubemap.FACE_NAMES[below].upper()}" in caption
    order = [cubemap.FACE_NAMES[f].upper() for f in face[R + 1, ::R]]
    assert ", ".join(order) in caption
    if not hemisphere:
        assert "-Z at the bottom left" in caption


def test_the_hemisphere_caption_says_where_the_layout_puts_each_side_face():
    """HEMISPHERE_CAPTION names the side each face is folded out to ('+X below', ...): each claim
    is checked against `hemisphere_layout` (the face drawn in the middle of that side's band)."""
    import re

    from pipelines.light import cubemap

    R = 8
    cube = cubemap.CubeMap(R)
    index = rf.hemisphere_layout(cube)
    claims = re.findall(r"([+-][XYZ]) (below|above|right|left|in the centre)", rf.HEMISPHERE_CAPTION)
    assert len(claims) == 5, claims
    where = {"below": (2 * R - 1, R), "above": (0, R), "right": (R, 2 * R - 1), "left": (R, 0),
             "in the centre": (R, R)}
    for face, side in claims:
        r, c = where[side]
        assert cubemap.FACE_NAMES[cube.texel_face[index[r, c]]] == face.lower(), (face, side)


# -- reflectance rounds ---------------------------------------------------------------------------------------

def _round(k, model, fit, held, lm=None, seconds=1.0):
    r = {"round": k, "material": {"model": model, "kd": [1, 1, 1], "ks": [0.1] * 3 if model != "lambert" else [0] * 3,
                                  "n": 20.0}, "fit_rmse": fit, "held_out_rmse": held, "light_seconds": seconds}
    if lm is not None:
        r["lm"] = lm
    return r


PROBE_REJECTED = {  # what `solve --reflectance auto` writes when the probe is not significant (the demo)
    "model": "lambert", "mode": "auto", "chosen_round": 0,
    "decision": "lambert: a blinn-phong term fitted with the Lambertian light fixed is not significant",
    "candidates": {"lambert": {"held_out_rmse": 0.0306, "fit_rmse": 0.0327},
                   "probe": {"pixels": 5580, "fit_rmse": 0.0278, "held_out_rmse": 0.0369, "gain": 0.0014,
                             "compared_on": "held-out rows of the probe", "lambert_rmse_same_rows": 0.036952,
                             "ks_significant": False}},
    "rounds": [_round(0, "lambert", 0.0327, 0.0306, seconds=8.0) | {"kind": "round"},
               _round(1, "blinn-phong", 0.0278, 0.0369, lm={"pixels": 5580}, seconds=0.0)
               | {"kind": "probe", "lambert_rmse_same_rows": 0.036952}]}

ALTERNATED = {  # the probe accepted: light under its material, then LM rounds; round 3 kept
    "model": "blinn-phong", "mode": "auto", "chosen_round": 3, "decision": "blinn-phong: lowers the held-out error",
    "candidates": {"lambert": {}, "blinn-phong": {},
                   "probe": {"pixels": 900, "fit_rmse": 0.07, "held_out_rmse": 0.075, "gain": 0.3,
                             "compared_on": "held-out rows of the probe", "lambert_rmse_same_rows": 0.107,
                             "ks_significant": True}},
    "rounds": [_round(0, "lambert", 0.10, 0.11), _round(1, "blinn-phong", 0.07, 0.08),
               _round(2, "blinn-phong", 0.05, 0.06, lm={"pixels": 900}), _round(3, "blinn-phong", 0.045, 0.055,
                                                                               lm={"pixels": 900}),
               _round(4, "blinn-phong", 0.046, 0.056, lm={"pixels": 900})]}
for _r in ALTERNATED["rounds"]:
    _r["kind"] = "round"


def _xticklabels(fig, ax):
    fig.canvas.draw()
    return [t.get_text() for t in ax.get_xticklabels() if t.get_text()]


def _bars(ax):
    return [(p.get_x() + p.get_width() / 2, p.get_height()) for p in ax.patches]


def test_a_rejected_probe_is_drawn_as_a_probe_against_lambert_on_its_rows():
    rounds = rf.reflectance_rounds(PROBE_REJECTED)
    assert [(r["round"], r["kind"], r["kept"]) for r in rounds] == [(0, "light", True), (1, "probe", False)]
    fig, (ax, pax) = rf.reflectance_axes(PROBE_REJECTED)
    # the light rounds: only round 0, an integer tick; the probe is not drawn there
    assert _xticklabels(fig, ax) == ["0"]
    for ln in ax.get_lines():
        assert set(np.asarray(ln.get_xdata()).tolist()) <= {0}, "the probe is drawn as a round of the light"
    assert "round 0 kept" in ax.get_title()
    # the probe's panel: Lambert's error and the probe's on the same rows (not round 0's 3.06 %)
    assert _xticklabels(fig, pax) == ["lambert", "blinn-phong"]
    assert [h for _, h in _bars(pax)] == [pytest.approx(3.6952), pytest.approx(3.69)]
    assert "not kept" in pax.get_title()
    label = pax.get_xlabel()
    assert "held-out rows of the probe" in label and "5580 LM pixels" in label and "gain 0.14 %" in label
    texts = [t.get_text() for t in pax.texts]
    assert texts == ["3.70 %", "3.69 %"]


def test_an_accepted_probe_is_shown_beside_the_rounds_it_led_to():
    rounds = rf.reflectance_rounds(ALTERNATED)
    assert [r["kind"] for r in rounds] == ["light"] * 5 and [r["kept"] for r in rounds] == [False] * 3 + [True, False]
    fig, (ax, pax) = rf.reflectance_axes(ALTERNATED)
    assert _xticklabels(fig, ax) == ["0", "1", "2", "3", "4"]
    joined = [ln for ln in ax.get_lines() if ln.get_linestyle() not in ("None", "")]
    assert [list(ln.get_xdata()) for ln in joined] == [[0, 1, 2, 3, 4]] * 2
    kept = [ln for ln in ax.get_lines() if (ln.get_label() or "").startswith("kept")]
    assert len(kept) == 1 and list(kept[0].get_xdata()) == [3] and list(kept[0].get_ydata()) == [pytest.approx(5.5)]
    assert [h for _, h in _bars(pax)] == [pytest.approx(10.7), pytest.approx(7.5)]
    assert "followed by light rounds" in pax.get_title()


def test_rounds_without_a_probe_and_a_single_round():
    lm_only = {k: v for k, v in ALTERNATED.items() if k != "candidates"} | {"mode": "blinn-phong"}
    fig, (ax, pax) = rf.reflectance_axes(lm_only)
    assert pax is None and len(fig.axes) == 1 and _xticklabels(fig, ax) == ["0", "1", "2", "3", "4"]
    assert rf.reflectance_axes({"rounds": [_round(0, "lambert", 0.1, 0.1)], "chosen_round": 0}) is None


def test_reflectance_json_before_rounds_had_a_kind():
    """A reflectance.json of solve version < 5 (no `kind`): its probe round is still found."""
    old = json.loads(json.dumps(PROBE_REJECTED))
    for r in old["rounds"]:
        r.pop("kind")
        r.pop("lambert_rmse_same_rows", None)
    assert [r["kind"] for r in rf.reflectance_rounds(old)] == ["light", "probe"]


# -- compare.png: labels clear of each other -------------------------------------------------------------------

def _compare_table(rows):
    return {"scene": "/x/spot_sun", "resolution": 32,
            "rows": [{"basis": b, "coefficients": k, "seconds": s, "held_out_rmse": e, "all_pixels_rmse": e}
                     for b, k, s, e in rows]}


COMPARE_CASES = {
    "demo": [("wavelet", 906, 7.555, 0.0306), ("quadtree", 906, 8.375, 0.0306), ("discrete", 3072, 43.2, 0.0297),
             ("sh", 9, 1.804, 0.14), ("sh+", 9, 14.27, 0.2057), ("points", 27, 5.116, 0.033)],
    "identical pairs": [("wavelet", 906, 2.0, 0.03), ("quadtree", 906, 2.0, 0.03), ("discrete", 3072, 2.1, 0.03),
                        ("sh", 9, 0.5, 0.2), ("sh+", 9, 0.5, 0.2), ("points", 27, 1.9, 0.031)],
    # bunny_sun at R = 64 (README: Speed): the times span four decades, the errors one and a half
    "wide": [("wavelet", 750, 2.8, 0.0344), ("quadtree", 750, 2.9, 0.0344), ("discrete", 12288, 54.0, 0.0343),
             ("sh", 9, 0.007, 0.1333), ("sh+", 9, 1.3, 0.2572), ("points", 27, 11.0, 0.0361)],
}


def label_overlaps(fig, ax) -> list[str]:
    """Labels (text boxes) that overlap another label or a marker, or leave the axes."""
    from matplotlib.text import Text

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    boxes = [(t.get_text(), Text.get_window_extent(t, renderer)) for t in ax.texts]
    markers = []
    for c in ax.collections:
        for (x, y), s in zip(ax.transData.transform(c.get_offsets()), np.broadcast_to(c.get_sizes(), len(c.get_offsets()))):
            r = 0.5 * np.sqrt(s) * fig.dpi / 72
            markers.append((x - r, y - r, x + r, y + r))
    bad = []
    for i, (text, b) in enumerate(boxes):
        if b.x0 < frame.x0 or b.x1 > frame.x1 or b.y0 < frame.y0 or b.y1 > frame.y1:
            bad.append(f"{text}: outside the axes")
        for other, o in boxes[i + 1:]:
            if b.overlaps(o):
                bad.append(f"{text} / {other}")
        for x0, y0, x1, y1 in markers:
            if b.x0 < x1 and x0 < b.x1 and b.y0 < y1 and y0 < b.y1:
                bad.append(f"{text}: on a marker")
    return bad


@pytest.mark.parametrize("case", sorted(COMPARE_CASES))
def test_compare_labels_do_not_overlap(case):
    from wavelight_cli.stages.solve import compare_figure

    table = _compare_table(COMPARE_CASES[case])
    fig = compare_figure(table)
    (ax,) = fig.axes
    assert sorted(t.get_text() for t in ax.texts) == sorted(f"{r['basis']} ({r['coefficients']})" for r in table["rows"])
    assert label_overlaps(fig, ax) == []


def tick_label_overlaps(fig, ax) -> list[str]:
    """Tick labels (major and minor, those drawn) of one axis that overlap each other."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    bad = []
    for name, axis in (("x", ax.xaxis), ("y", ax.yaxis)):
        lo, hi = sorted(axis.get_view_interval())
        drawn = []
        for locs, ticks in ((axis.get_majorticklocs(), axis.get_major_ticks()),
                            (axis.get_minorticklocs(), axis.get_minor_ticks())):
            for loc, tick in zip(locs, ticks):
                label = tick.label1
                if lo <= loc <= hi and label.get_visible() and label.get_text():
                    drawn.append((label.get_text(), label.get_window_extent(renderer)))
        for i, (text, box) in enumerate(drawn):
            bad += [f"{name}: {text} / {other}" for other, o in drawn[i + 1:] if box.overlaps(o)]
    return bad


@pytest.mark.parametrize("case", sorted(COMPARE_CASES))
def test_compare_tick_labels_do_not_overlap(case):
    """The log axes label their minor ticks (2, 3, 5) only where a decade has room for them."""
    from wavelight_cli.stages.solve import compare_figure

    fig = compare_figure(_compare_table(COMPARE_CASES[case]))
    (ax,) = fig.axes
    assert tick_label_overlaps(fig, ax) == []
    assert len(ax.xaxis.get_majorticklocs()) >= 2 or len(ax.xaxis.get_minorticklocs()) >= 2


def test_compare_plot_writes_its_png(tmp_path):
    from wavelight_cli.stages.solve import compare_plot

    path = compare_plot(_compare_table(COMPARE_CASES["demo"]), tmp_path / "compare.png")
    assert path.stat().st_size > 5000
