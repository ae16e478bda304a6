"""Several photos under one light: their used pixels as the rows of one system.

Each view's visibility (`geometry.visibility.VisibilityData`, cached per view) is concatenated
into one: the rows of view k follow those of view k - 1. The solve sees a single set of pixels,
so everything that works on rows (transport, reflectance, rendering, per-pixel albedo from each
row's surface sample) works unchanged. What looks at pixel positions (the held-out hash, the
visibility change between neighbours, the stratified sample order) sees each view in its own band
of a stacked layout: view k's pixel (r, c) is at (r + k * stride, c), stride a power of two
larger than every view's height, so that no two views' pixels collide or neighbour each other and
the bit-reversed sample order spreads every head of the sample over all the views.

With 3 or more views the model choice (levels auto, reflectance auto) holds out one whole view
(`held_out_view`) instead of scattered pixels: the held-out error then says how well the light
predicts a photo it was not fitted to, which is what a new view needs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

WHOLE_VIEW_HOLDOUT = 3  # from this many views the model choice holds out a whole view
WEAK = 0.05  # a texel is weakly observed when sqrt(G_ii / max G_ii) over the union is below this


@dataclass(frozen=True)
class Layout:
    """Where each view's rows are in the combined rows, and their place in the stacked layout."""

    names: list  # the views' labels, in row order
    starts: np.ndarray  # (V + 1,) row offsets: view k's rows are starts[k]:starts[k + 1]
    shapes: list  # (H, W) of each view's image
    stride: int  # stacked-layout rows per view

    @property
    def view_of_row(self) -> np.ndarray:
        return np.repeat(np.arange(len(self.names)), np.diff(self.starts))

    def rows(self, k: int) -> slice:
        return slice(int(self.starts[k]), int(self.starts[k + 1]))

    def image_pixels(self, pixel: np.ndarray, k: int) -> np.ndarray:
        """View k's rows' (row, col) in its own image (from the stacked layout)."""
        p = np.array(pixel[self.rows(k)], copy=True)
        p[:, 0] -= k * self.stride
        return p


def combine(datas: list, names: list, shapes: list):
    """One VisibilityData of the views' rows, in the stacked layout, and its `Layout`."""
    from ..geometry.camera import PixelSamples
    from ..geometry.visibility import VisibilityData

    first = datas[0]
    for d in datas[1:]:
        if d.cube.n_texels != first.cube.n_texels or d.supersample != first.supersample:
            raise ValueError("the views' visibility must share the cube map and the supersampling")
    stride = 1 << int(np.ceil(np.log2(max(h for h, _ in shapes) + 1)))
    starts = np.concatenate([[0], np.cumsum([d.n_pixels for d in datas])])
    if len(datas) == 1:
        return first, Layout(list(names), starts, list(shapes), stride)
    pixel = [np.asarray(d.samples.pixel).copy() for d in datas]
    for k, p in enumerate(pixel):
        p[:, 0] += k * stride
    samples = PixelSamples.concatenate([d.samples for d in datas], np.concatenate(pixel).astype(np.int32))
    stored = np.concatenate([np.asarray(d.stored) for d in datas])
    method = "adaptive" if any(d.method == "adaptive" for d in datas) else first.method
    return (VisibilityData(samples, first.cube, first.supersample, stored, method, all(d.castable_only for d in datas)),
            Layout(list(names), starts, list(shapes), stride))


def stacked_photo(photos: list, layout: Layout):
    """The views' photos stacked in the layout (one `LoadedImage` that the solve indexes by the
    combined rows' pixels)."""
    if len(photos) == 1:
        return photos[0]
    W = max(w for _, w in layout.shapes)
    pixels = np.zeros((layout.stride * len(photos), W, 3), photos[0].pixels.dtype)
    saturated = np.zeros(pixels.shape[:2], bool)
    for k, ph in enumerate(photos):
        h, w = ph.pixels.shape[:2]
        pixels[k * layout.stride:k * layout.stride + h, :w] = ph.pixels
        saturated[k * layout.stride:k * layout.stride + h, :w] = ph.saturated
    return replace(photos[0], pixels=pixels, saturated=saturated)


def held_out_view(layout: Layout, main: str = "main") -> int:
    """The view held out for the model choice with >= WHOLE_VIEW_HOLDOUT views: of the views other
    than the main photo, the one with the fewest used pixels (the model choice keeps the most rows)."""
    counts = np.diff(layout.starts)
    others = [k for k, n in enumerate(layout.names) if n != main] or list(range(len(layout.names)))
    return min(others, key=lambda k: (counts[k], k))


def holdout(layout: Layout, fraction: float, main: str = "main") -> tuple[np.ndarray | None, dict]:
    """The held-out rows (None: the solve's own scattered pixels) and how they were chosen."""
    n = len(layout.names)
    if fraction <= 0:
        return None, {"mode": "none", "note": "--held-out 0: nothing held out"}
    if n < WHOLE_VIEW_HOLDOUT:
        return None, {"mode": "pixels", "fraction": fraction,
                      "note": f"{100 * fraction:g} % of each view's pixels (a hash of their position) held out; "
                              f"whole views are held out from {WHOLE_VIEW_HOLDOUT} views on"}
    k = held_out_view(layout, main)
    mask = layout.view_of_row == k
    return mask, {"mode": "view", "view": layout.names[k],
                  "note": f"the whole view {layout.names[k]!r} (of the views other than {main!r}, the one with the "
                          "fewest used pixels) is held out to choose the light's levels and the reflectance model; "
                          "the chosen model is then fitted to every view"}


def texel_response(vis, rows: slice | None = None, block: int = 512) -> np.ndarray:
    """(N,) sum over the rows' pixels of (V_ji max(0, N_j . d_i) omega_i)^2: the diagonal of the
    Lambertian (kd = 1) G = T'T of these pixels alone, what the observability map shows. (V is 0 or
    1 or a fraction: V^2 cos^2 summed per texel, omega^2 after; blocks in place on both cores.)"""
    from ..geometry.visibility import decode
    from ..threads import parallel_blocks

    rows = rows or slice(0, vis.n_pixels)
    N = vis.cube.n_texels
    dirs = vis.cube.directions.astype(np.float32)
    normals = vis.samples.normal
    partial = {}

    def run(starts):
        acc = np.zeros(N, np.float64)
        c = np.empty((block, N), np.float32)
        for a in starts:
            sl = slice(a, min(rows.stop, a + block))
            k = sl.stop - sl.start
            cos = c[:k]
            np.matmul(normals[sl].astype(np.float32), dirs.T, out=cos)
            np.maximum(cos, 0.0, out=cos)
            cos *= cos
            V = decode(np.asarray(vis.stored[sl]), N, vis.encoding, raw=True)  # (bits: 0/1, V^2 = V)
            cos *= V if vis.encoding == "bits" else V * V
            acc += cos.sum(axis=0, dtype=np.float64)
        partial[starts[0] if starts else -1] = acc

    parallel_blocks(run, list(range(rows.start, rows.stop, block)))
    out = sum(partial.values()) if partial else np.zeros(N, np.float64)
    return out * vis.cube.solid_angles.astype(np.float64) ** 2


def responses(vis, layout: Layout) -> np.ndarray:
    """(V, N) `texel_response` of each view's rows."""
    return np.stack([texel_response(vis, layout.rows(k)) for k in range(len(layout.names))])


def observability_by_view(per: np.ndarray, layout: Layout) -> dict:
    """How each view observes the light, on one scale (the union's best-observed texel = 1), from
    the views' `responses`: per view its unobservable and weakly observed (< WEAK) texels alone, and
    what it adds to the others (texels that are unobservable / weak without it)."""
    union = per.sum(axis=0)
    top = max(float(union.max(initial=0.0)), 1e-300)

    def counts(d):
        obs = np.sqrt(np.maximum(d, 0) / top)
        return int((d <= 0).sum()), int((obs < WEAK).sum())

    views = {}
    for k, name in enumerate(layout.names):
        u, w = counts(per[k])
        ou, ow = counts(union - per[k]) if len(layout.names) > 1 else (len(union), len(union))
        views[name] = {"unobservable": u, "weakly_observed": w, "without_it": {"unobservable": ou, "weakly_observed": ow},
                       "adds": {"observable": ou - counts(union)[0], "well_observed": ow - counts(union)[1]}}
    u, w = counts(union)
    return {"texels": int(len(union)), "weak_threshold": WEAK,
            "union": {"unobservable": u, "weakly_observed": w}, "views": views,
            "note": "per texel sqrt(G_ii / max G_ii) of the Lambertian transport (kd = 1) over every used pixel of "
                    "a view, on the union's scale; unobservable: no pixel responds; weakly observed: below "
                    f"{WEAK:g}; 'adds': texels that are unobservable / weakly observed without the view and not "
                    "with it"}


def subset(vis, rows: np.ndarray):
    """The VisibilityData of some rows (indices) of `vis`."""
    from ..geometry.visibility import VisibilityData

    rows = np.asarray(rows)
    samples = vis.samples.take(rows)
    return VisibilityData(samples, vis.cube, vis.supersample, np.asarray(vis.stored)[rows], vis.method, vis.castable_only)


def per_view_errors(result, values: np.ndarray, usable: np.ndarray, held: np.ndarray, layout: Layout,
                    holdout_info: dict, bounds: bool = False) -> dict:
    """Per view: pixels (used / fit / held out / saturated), the relit error of the final light over
    its used pixels, and the held-out error over its held-out pixels of the light the model choice
    kept (fitted without them: the chosen level before the final re-solve on every row)."""
    from ..metrics import versus_photo
    from ..model.render import render
    from .solve import pixel_counts

    sol = result.solution
    levels = getattr(sol, "levels", None) or []
    held_light = levels[sol.chosen].light if levels and 0 <= sol.chosen < len(levels) else None
    held_rows = np.flatnonzero(held & usable)
    held_relit = None
    if held_light is not None and len(held_rows):
        held_relit = np.zeros_like(values)
        a = getattr(result, "albedo", None)  # the parts' per-pixel albedo (their fitted scales)
        held_relit[held_rows] = render(subset(result.vis, held_rows), held_light, result.material,
                                       albedo=None if a is None else a.values(held_rows),
                                       specular=None if a is None else a.specular_weight(held_rows))
    out = {}
    for k, name in enumerate(layout.names):
        sl = layout.rows(k)
        u, h = usable[sl], held[sl]
        v = versus_photo(result.relit[sl], values[sl], u)
        rec = {"pixels": pixel_counts(u, h, bounds),
               "relit_rmse": v["relative_rmse_vs_photo"], "bias": v["bias_vs_photo"],
               "held_out_rmse": None}
        if held_relit is not None and (u & h).any():
            rec["held_out_rmse"] = versus_photo(held_relit[sl], values[sl], u & h)["relative_rmse_vs_photo"]
        if holdout_info.get("mode") == "view":
            rec["held_out_whole"] = name == holdout_info["view"]
        out[name] = rec
    return out


# -- photos of different exposure: one gain per view ------------------------------------------------
EXPOSURE_MODES = ("same", "fit")
EXPOSURE_ROWS = 4096  # the exposure fit uses at most this many used pixels of each view (spread over it)
EXPOSURE_FACE = 4  # ... under a Lambertian light of this cube-map face resolution (a hemisphere: 48 leaves)
EXPOSURE_CYCLES = 4  # ... searching each unknown in turn, this many times at most
EXPOSURE_SPAN = 3.0  # ... each within a factor e^3 (20) of where it stands
EXPOSURE_EVALUATIONS = 20
EXPOSURE_TRIM = 3.5  # rows whose residual exceeds this many robust sigmas (highlights) are left out of a refit
EXPOSURE_WARN = 0.02  # the final light's per-view gain differs from 1 by more than this: said in the report


def fit_exposures(vis, values: np.ndarray, usable: np.ndarray, layout: Layout, albedo=None,
                  main: int = 0) -> tuple[np.ndarray, dict]:
    """Each view's exposure relative to the main view's, from the photos alone: (V,) gains e_v with
    photo_v ~ e_v x the radiance the main view's photo is in, and what was done.

    A Lambertian light of EXPOSURE_FACE x EXPOSURE_FACE texels a face (>= 0) and the gains (and,
    with several parts, the parts' albedo factors: a row of part p in view v is predicted
    s_p e_v kd_p D L) are fitted together by variable projection: the light is re-solved for every
    trial value in a bounded search (`parts.bounded_search`) over each unknown in turn (as
    `parts.varpro_scales`), on up to EXPOSURE_ROWS used pixels of each view; the rows the fit
    explains worst (a highlight: beyond EXPOSURE_TRIM robust sigmas) are then left out and the fit
    repeated.
    """
    import time

    from ..geometry.visibility import decode
    from ..light.haar import uniform_tree
    from ..light.nnls import nnls_gram
    from ..light.rows import Pyramid, _gram
    from ..model.parts import bounded_search
    from ..model.render import diffuse_transport

    t0 = time.perf_counter()
    V = len(layout.names)
    picked = []
    for k in range(V):
        r = np.flatnonzero(usable[layout.rows(k)]) + int(layout.starts[k])
        picked.append(r[:: max(1, len(r) // EXPOSURE_ROWS)][:EXPOSURE_ROWS])
    rows = np.concatenate(picked)
    cube = vis.cube
    tree = uniform_tree(cube, min(EXPOSURE_FACE, cube.resolution))
    D = diffuse_transport(decode(np.asarray(vis.stored)[rows], cube.n_texels, vis.encoding, raw=True),
                          vis.samples.normal[rows], cube, None, vis.samples.view[rows])
    A = Pyramid(D, cube.tile_sizes).leaf_sums(tree).astype(np.float64)
    del D
    base = np.ones((len(rows), 3)) if albedo is None else albedo.base[rows]
    y = np.asarray(values, np.float64)[rows]
    view = layout.view_of_row[rows]
    part = np.zeros(len(rows), np.int64) if albedo is None else albedo.part[rows]
    n_parts = 1 if albedo is None else len(albedo.parts.parts)
    ref = 0 if albedo is None else albedo.parts.reference
    colour = [albedo is not None and p != ref and albedo.parts.parts[p].fit == "colour" for p in range(n_parts)]
    group = part * V + view  # (part, view) pairs: a row's factor is s[part] x e[view]
    e = np.ones(V)
    s = np.ones((n_parts, 3)) if albedo is None else albedo.scales.copy()
    keep = np.ones(len(rows), bool)
    free = [None] * 3

    def light_of(systems, c, f):
        G = sum(f[g, c] ** 2 * systems[g][0][c] for g in systems)
        h = sum(f[g, c] * systems[g][1][:, c] for g in systems)
        r = nnls_gram(G, h, initial_free=free[c])
        free[c] = r.x > 0
        return r

    def objective(systems, e_, s_, channels=range(3)):
        f = (s_[:, None, :] * e_[None, :, None]).reshape(-1, 3)
        return sum(float(sum(systems[g][2][c] for g in systems) + 2.0 * light_of(systems, c, f).objective)
                   for c in channels)

    for attempt in range(2):
        systems = {}
        for g in np.unique(group[keep]):
            sel = np.flatnonzero((group == g) & keep)
            M = [A[sel] * base[sel, c][:, None] for c in range(3)]
            systems[int(g)] = (np.stack([_gram(m) for m in M]), np.column_stack([m.T @ y[sel, c] for c, m in enumerate(M)]),
                               (y[sel] ** 2).sum(axis=0))
        seen = {(g // V, g % V) for g in systems}
        for _ in range(EXPOSURE_CYCLES):
            before = np.concatenate([e, s.ravel()])
            for k in range(V):
                if k != main and any(v == k for _, v in seen):
                    def fe(x, k=k):
                        e2 = e.copy()
                        e2[k] = np.exp(x)
                        return objective(systems, e2, s)
                    e[k] = np.exp(bounded_search(fe, float(np.log(e[k])), EXPOSURE_SPAN, EXPOSURE_EVALUATIONS))
            for p in range(n_parts):
                if p == ref or not any(q == p for q, _ in seen):
                    continue
                for c in (range(3) if colour[p] else [None]):
                    def fs(x, p=p, c=c):
                        s2 = s.copy()
                        s2[p] = np.exp(x) if c is None else s2[p]
                        if c is not None:
                            s2[p, c] = np.exp(x)
                        return objective(systems, e, s2, range(3) if c is None else [c])
                    x0 = float(np.log(s[p]).mean() if c is None else np.log(s[p, c]))
                    x = bounded_search(fs, x0, EXPOSURE_SPAN, EXPOSURE_EVALUATIONS)
                    if c is None:
                        s[p] = np.exp(x)
                    else:
                        s[p, c] = np.exp(x)
            if np.max(np.abs(np.concatenate([e, s.ravel()]) / before - 1)) < 1e-4:
                break
        if attempt:
            break
        f = (s[:, None, :] * e[None, :, None]).reshape(-1, 3)
        light = np.column_stack([light_of(systems, c, f).x for c in range(3)])
        pred = f[group] * base * (A @ light)
        res = np.abs(y - pred).sum(axis=1)
        sigma = 1.4826 * np.median(np.abs(res - np.median(res)))
        keep = res <= np.median(res) + EXPOSURE_TRIM * max(sigma, 1e-12)
    unseen = [layout.names[k] for k in range(V) if not np.any(keep & (view == k))]
    info = {"mode": "fit", "rows_per_view": {n: int(len(p)) for n, p in zip(layout.names, picked)},
            "rows_left_out": int((~keep).sum()), "light": f"Lambertian, {tree.n_leaves} leaves (>= 0)",
            "seconds": time.perf_counter() - t0}
    if unseen:
        info["note"] = f"view(s) {', '.join(unseen)} have no usable pixel: their gain is kept at 1"
    return e, info


def apply_exposures(photo, layout: Layout, gains: np.ndarray):
    """The stacked photo with each view's band divided by its gain (saturation flags kept)."""
    if np.allclose(gains, 1.0):
        return photo
    pixels = np.array(photo.pixels, np.float32, copy=True)
    for k, g in enumerate(gains):
        pixels[k * layout.stride:(k + 1) * layout.stride] /= np.float32(g)
    return replace(photo, pixels=pixels)


def final_gains(relit: np.ndarray, values: np.ndarray, usable: np.ndarray, layout: Layout) -> np.ndarray:
    """(V,) each view's least-squares gain of the final relit view against its (exposure-corrected)
    photo, relative to the main view's: what is left of an exposure difference (1 when none is)."""
    g = np.ones(len(layout.names))
    for k in range(len(layout.names)):
        sl = layout.rows(k)
        u = usable[sl]
        f, y = relit[sl][u], values[sl][u]
        g[k] = float((f * y).sum() / max((f * f).sum(), 1e-300))
    return g / g[0]
