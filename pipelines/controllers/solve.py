"""The solve stage: photo + visibility -> the light, the reflectance, the relit view and what the
photo cannot tell.

Two routes share everything but the system the bases solve (`SolveOptions.exact`):
- the default: the transport rows of a weighted sample of the pixels (`light.sampling`,
  `light.rows`), the refinement levels chosen on a smaller head of it, the chosen model re-solved
  on the whole sample and the held-out pixels; directions that carry much of the recovered light
  are then cast exactly for every pixel when the visibility was inferred (`AdaptiveVisibility`),
  and the light re-solved on that;
- `exact`: dense normal equations over every used pixel (the reference the tests and the
  benchmark compare with).
The relit view is rendered for every used pixel by the one forward model (`model.render`).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..errors import InputError
from ..metrics import versus_photo
from ..light.bases import REFINED, LightOptions
from ..model.materials import PLASTIC, SPECULAR_MODELS, Material

CLIPPED_MODES = ("bound", "drop")
CLIP_VALUE = 1.0 - 1e-6  # an integer photo's maximum code reads as 1 (io.images)
REFLECTANCE_MODES = ("auto", "lambert", "blinn-phong", "phong", "phong-classic", "plastic", "given")
DEFAULT_START_KS = 0.25  # start of a specular fit: ks = 0.25 x mean(kd), unless --ks is given
DEFAULT_START_SHININESS = 20.0  # and n = 20, unless --shininess is given
DEFAULT_START_ALPHA = 0.1  # a plastic fit starts at alpha 0.1 (--alpha), ks = 1 x mean(kd) (--ks), IOR 1.49 (--ior)
DEFAULT_START_PLASTIC_KS = 1.0
EXPLORE_ROWS = 8192  # refinement levels are chosen on this many of the fit sample's rows
PROBE_ROWS = 2048  # --reflectance auto probes a specular term on this many fit rows (and half as many held out)
LM_ROWS = 8192  # the reflectance rounds' LM fits this many rows (a quarter of them where highlights are)
ROUND_ROWS = 8192  # and their light is re-solved on this many of the fit sample's rows (and every held-out row)
RATIO_MIN_DROP = 1e-4  # a round's ks / kd searched with its light re-solved is kept if it lowers the residual this much
RATIO_CONVERGED = 1e-3  # and is not searched again in that model's later rounds once a step lowered it by less
BRIGHT_SHARE_SQ = 1e-3  # directions are cast exactly until the rest's squared power shares sum below this
MAX_BRIGHT = 64
SUN_SHARE = 0.3  # `narrow_lobe_note`: a compact source holding this share of the light's power (a sun)
ROBUST_ROUNDS = 3  # the robust pass: weights -> light (and reflectance) again, at most this many times
ROBUST_TRIGGER = 0.01  # ... while the new weights and targets move at least this share of the squared error
ROBUST_LM_ROUNDS = 2  # a fitted specular term is refitted under the robust weights in this many LM rounds
ROBUST_STILL = 0.1  # ... and the chosen tree refitted alone when that moves the prediction by less than this of the noise
ROBUST_ACCEPT = 0.02  # the robust solve is kept if its plain error over every usable pixel rises by at most this
PART_ROUNDS = 12  # several parts / textures: light <-> per-part albedo scales, at most this many rounds
PART_TOL = 1e-3  # ... until no part's scale changes by more than this (relative)
SCALE_NOTE = ("light x albedo is only known as a product: with the default kd = 1 the light absorbs "
              "the albedo (README: Conventions)")


@dataclass(frozen=True)
class SolveOptions:
    light: LightOptions = LightOptions()
    held_out: float = 0.1
    linear_input: bool = False
    exact: bool = False  # dense normal equations over every used pixel (the reference route)
    robust: bool = True  # down-weight the few pixels the model cannot explain, clipped pixels as lower bounds
    clipped: str = "bound"  # clipped (saturated) channels: lower bounds ("bound"), or left out ("drop")
    view_exposure: str = "fit"  # several photos: one gain per photo fitted relative to the main one ("fit"), or one exposure ("same")

    def check(self, resolution: int, hemisphere: bool = True) -> None:
        self.light.check(resolution, hemisphere)
        if not 0 <= self.held_out <= 0.5:
            raise InputError(f"--held-out must be a fraction from 0 to 0.5, got {self.held_out}", None,
                             "use e.g. --held-out 0.1")
        if self.clipped not in CLIPPED_MODES:
            raise InputError(f"unknown --clipped {self.clipped!r}", None, f"use one of {', '.join(CLIPPED_MODES)}")
        if self.view_exposure not in ("same", "fit"):
            raise InputError(f"unknown --view-exposure {self.view_exposure!r}", None, "use same or fit")
        if self.light.levels == "auto" and self.held_out == 0 and self.light.basis in REFINED:
            raise InputError("--levels auto needs held-out pixels, but --held-out is 0", None,
                             "use --held-out 0.1, or give a fixed --levels N")

    def cache_params(self) -> dict:
        return {**self.light.cache_params(), "held_out": self.held_out, "linear_input": self.linear_input,
                "exact": self.exact, "robust": self.robust, "clipped": self.clipped, "view_exposure": self.view_exposure}

    @property
    def bounds(self) -> bool:
        """Whether clipped pixels are fitted as lower bounds (the sampled route's robust pass)."""
        return self.robust and self.clipped == "bound" and not self.exact


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

    def start(self, material: Material, given: set) -> Material:
        """The fit's start: the given material's kd; its ks and n if the user gave them, else
        ks = DEFAULT_START_KS x mean(kd) and n = DEFAULT_START_SHININESS; the model of --reflectance
        (auto: the given specular model, else blinn-phong)."""
        if self.mode == PLASTIC:
            return self.plastic_start(material, given)
        model = self.mode if self.mode in SPECULAR_MODELS else (
            material.model if material.model in SPECULAR_MODELS and material.model != PLASTIC else "blinn-phong")
        ks = material.ks if "ks" in given and any(material.ks) else (DEFAULT_START_KS * float(np.mean(material.kd)),) * 3
        if "n" in given and not material.shininess > 0:
            raise InputError(f"--shininess must be > 0 to start a fit, got {material.shininess:g}", None,
                             f"use e.g. --shininess {DEFAULT_START_SHININESS:g}, or leave it out")
        n = material.shininess if "n" in given else DEFAULT_START_SHININESS
        return replace(material, model=model, ks=tuple(ks), shininess=float(n))

    def plastic_start(self, material: Material, given: set) -> Material:
        """A plastic fit's start: kd as given; ks, alpha, IOR and distribution as given, else
        DEFAULT_START_PLASTIC_KS x mean(kd), DEFAULT_START_ALPHA, 1.49 and ggx. The IOR and the
        distribution are kept by the fit."""
        m = material
        ks = m.ks if "ks" in given and any(m.ks) else (DEFAULT_START_PLASTIC_KS * float(np.mean(m.kd)),) * 3
        plastic = m.model == PLASTIC
        opts = {} if plastic else dict(m.extra.get("plastic_start", {}))  # --alpha/--ior/--distribution
        if plastic:
            opts = {k: getattr(m, f) for k, f in (("alpha", "roughness"), ("ior", "ior"), ("distribution", "distribution"))
                    if k in given}
        alpha = opts.get("alpha") or DEFAULT_START_ALPHA
        return Material(kd=m.kd, ks=tuple(ks), model=PLASTIC, roughness=float(alpha), ior=float(opts.get("ior", 1.49)),
                        distribution=str(opts.get("distribution", "ggx")))


class Progress:
    """What a controller tells its caller while it works (the CLI prints it). Silent by default."""

    def note(self, message: str) -> None:
        pass

    def advance(self, what: str, done: int, total: int, unit: str = "") -> None:
        pass


def material_text(m: Material) -> str:
    kd = " ".join(f"{v:.3g}" for v in m.kd)
    if m.model == PLASTIC:
        return (f"plastic kd {kd}, ks {float(np.mean(m.ks)):.3g}, alpha {m.roughness:.3g} ({m.distribution}, "
                f"IOR {m.ior:.3g})")
    if not m.specular:
        return f"{m.model} kd {kd}"
    return f"{m.model} kd {kd}, ks {float(np.mean(m.ks)):.3g}, n {m.shininess:.3g}"


# -- the systems ----------------------------------------------------------------------------------
def _same_material(a: Material, b: Material) -> bool:
    return (np.array_equal(a.kd, b.kd) and np.array_equal(a.ks, b.ks)
            and (a.model, a.shininess, a.roughness, a.distribution, a.ior)
            == (b.model, b.shininess, b.roughness, b.distribution, b.ior))


class _Systems:
    """Builds the light system of a material on the chosen route (dense, or sampled rows)."""

    def __init__(self, vis, values, usable, held, options: SolveOptions, progress: Progress, albedo=None,
                 clipped=None):
        from ..light import sampling

        self.vis, self.values, self.usable, self.held = vis, values, usable, held
        self.albedo = albedo  # model.parts.PixelAlbedo or None (uniform)
        self.options, self.progress = options, progress
        self.sample_info = None
        self._reweighted = None  # the system solved before the robust pass's new weights (`robust`)
        # what the rows are fitted to: the photo; after the robust pass (`robust`) a clipped channel's
        # bound, or its prediction where that is brighter (a pixel with another channel below its bound)
        self.targets = values
        self.clipped = np.zeros(values.shape, bool) if clipped is None else np.asarray(clipped, bool)
        if options.exact:
            return
        from ..light.rows import TransportRows

        pixels = vis.samples.pixel
        change = sampling.visibility_change(pixels, np.asarray(vis.stored), vis.encoding)
        self.fit_sample = sampling.fit_sample(pixels, usable & ~held, change)
        self.held_sample = sampling.held_out_sample(pixels, usable & held)
        # the clipped pixels (lower bounds) follow the fit sample, every one standing for itself, at weight
        # 0 until the robust pass (`robust`) gives them theirs: the first solve is the one without them.
        # The held-out ones too: a held-out error is a plain squared error, and a bound is not a value
        bounds = np.flatnonzero(self.clipped.any(axis=1) & ~usable) if options.bounds else np.zeros(0, np.int64)
        self.fit_sample = sampling.with_bounds(self.fit_sample, bounds)
        # the rows' weights: the sample's (the pixels each stands for) x the robust weight
        self.fit_w = np.where(np.isin(self.fit_sample.rows, bounds), 0.0, self.fit_sample.weights)
        self.held_w = self.held_sample.weights
        self.fit_rows = TransportRows(vis, self.fit_sample.rows)
        self.held_rows = TransportRows(vis, self.held_sample.rows)
        if albedo is not None:  # (parts declared matte in materials.toml: no lobe on their rows)
            self.set_glossy(albedo.glossy, albedo.glossy_source)
        self.sample_info = {"fit": self.fit_sample.summary(), "held_out": self.held_sample.summary(),
                            "explore_rows": min(EXPLORE_ROWS, len(self.fit_sample.rows))}

    def system(self, material: Material, round_rows: int | None = None, rows: int | None = None):
        """The light system under `material`; `round_rows`: a specular round's, on that many rows
        of the fit sample (its head: spread like the whole) and the whole held-out sample; `rows`:
        likewise on the fit sample's head, for a system that is not a round's (its parts' pieces are
        not kept apart: `RowsPart.split_specular`)."""
        from ..light.system import LightSystem, build_normal_equations

        if self.options.exact:
            self.progress.note(f"normal equations over {int(self.usable.sum())} pixels x {self.vis.cube.n_texels} texels")
            ne = build_normal_equations(self.vis, self.values, material, use=self.usable, held_out=self.held,
                                        progress=lambda done, total: self.progress.advance("normal equations", done,
                                                                                           total, "pixels"),
                                        albedo=None if self.albedo is None else self.albedo.values(),
                                        specular=self.specular_weight())
            self.progress.note(f"normal equations in {ne.seconds:.1f} s")
            return ne
        t0 = time.perf_counter()
        fs, hs = self.fit_sample, self.held_sample
        # the system solved before the robust pass's weights, if of this material: its tree systems are
        # taken over (any other goes before this one's transport is built: memory)
        before, self._reweighted = self._reweighted, None
        if before is not None and (round_rows is not None or rows is not None or not _same_material(before[0], material)):
            before = None
        before = None if before is None else before[1]
        a = self.albedo
        # several parts: the rows keep each part's known albedo and the factors apart (`RowsPart.group`),
        # so that a Lambertian system serves other factors without a pass over the rows (`rows.with_scales`)
        # (a specular system's pieces per part pay off only for a round's system, re-solved under new factors)
        grouped = {} if a is None else {"scales": a.scales, "split_specular": round_rows is not None,
                                        "ks_scales": a.ks_scales}
        fit = self.fit_rows.part(material, self.targets[fs.rows], self.fit_w, fs.candidates,
                                 round_rows if rows is None else rows,
                                 None if a is None else a.base[fs.rows],
                                 group=None if a is None else a.part[fs.rows], **grouped)
        held = self.held_rows.part(material, self.targets[hs.rows], self.held_w, hs.candidates,
                                   albedo=None if a is None else a.base[hs.rows],
                                   group=None if a is None else a.part[hs.rows], **grouped)
        out = LightSystem(fit, held, time.perf_counter() - t0, fit.head(EXPLORE_ROWS, "single"))
        if before is not None:  # (the robust pass: the same rows under new weights, `robust`)
            for mine, theirs in ((out.fit, before.fit), (out.held_out, before.held_out), (out.explore, before.explore)):
                if hasattr(mine, "adopt"):
                    mine.adopt(theirs)
        return out

    def keep_only(self, material: Material) -> None:
        """Once the model is chosen: the kept transports of the other candidates go (memory)."""
        if not self.options.exact:
            self.fit_rows.keep_only(material)
            self.held_rows.keep_only(material)

    def specular_weight(self, rows=None) -> np.ndarray | None:
        """(P,) (or of `rows`) 0 for the pixels of matte parts, None when every pixel has the lobe."""
        return None if self.albedo is None else self.albedo.specular_weight(rows)

    def set_glossy(self, glossy: np.ndarray | None, sources: list | None = None) -> None:
        """Which parts have the specular term ((parts,) bool; `parts.glossy_parts`): the transport rows
        of matte parts lose the lobe (and a coating), and the reflectance fits leave them out."""
        self.albedo.glossy, self.albedo.glossy_source = glossy, sources
        if not self.options.exact:  # (the rows carry the lobe at weight 1: a part's own weight is its group's)
            w = self.albedo.glossy_weight()
            self.fit_rows.set_specular(None if w is None else w[self.fit_sample.rows])
            self.held_rows.set_specular(None if w is None else w[self.held_sample.rows])

    def glossy_rows(self, rows):
        """(rows, weights) for a reflectance fit without the rows of matte parts."""
        w = self.specular_weight()
        if rows is None or w is None:
            return rows
        keep = w[rows[0]] > 0
        return rows[0][keep], rows[1][keep]

    def highlight_rows(self, light: np.ndarray, kd, n_fit: int, n_held: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows for a reflectance fit, with the weights that make them stand for all used pixels: the
        n_fit // 4 fit rows the diffuse light explains least from above (where highlights are, if
        any: a stratum of their own, each row standing for itself), a spread head of the other fit
        rows standing for all of those, and a head of n_held held-out rows standing for all of them."""
        fs, hs = self.fit_sample, self.held_sample
        pred = self.fit_rows.diffuse_shading(light) * np.asarray(kd)[None, :]
        if self.albedo is not None:
            pred *= self.albedo.values(fs.rows)
        values = self.targets[fs.rows]
        fw, hw = self.fit_w, self.held_w
        excess = (values - pred).sum(axis=1) / np.maximum(values.sum(axis=1), 1e-12)
        excess[fw == 0] = -np.inf  # (rows without weight: rejected, or clipped before the robust pass)
        excess[(fw > 0) & self.clipped[fs.rows].any(axis=1)] = np.inf  # lower bounds: where the highlight's core is
        top = np.argsort(-excess, kind="stable")[:n_fit // 4]
        others = np.setdiff1d(np.arange(len(fs.rows)), top)  # in sample order: every head is spread
        rest = others[: max(0, n_fit - len(top))]
        w_rest = fw[rest] * fw[others].sum() / max(fw[rest].sum(), 1e-300)
        nh = min(n_held, len(hs.rows))
        w_held = hw[:nh] * hw.sum() / max(hw[:nh].sum(), 1e-300)
        return (np.concatenate([fs.rows[top], fs.rows[rest], hs.rows[:nh]]),
                np.concatenate([fw[top], w_rest, w_held]))

    def robust(self, weights: np.ndarray, targets: np.ndarray, system=None, material: Material | None = None) -> None:
        """Fit the sampled rows with per-pixel robust weights (P,) and targets (P, C) (`light.robust`:
        the pixel's weight multiplies the pixels its row stands for). `system`: the sampled system of
        `material` solved under the weights before; the next system built of that material takes
        over its memoised tree systems, corrected for the rows whose weight or target changed
        (`rows.RowsPart.adopt`: a few, so exploring the levels again needs no pass over the rows)."""
        self._reweighted = (material, system) if (system is not None and material is not None
                                                  and not self.options.exact) else None
        self.targets = targets
        self.fit_w = self.fit_sample.weights * weights[self.fit_sample.rows]
        self.held_w = self.held_sample.weights * weights[self.held_sample.rows]

    def part_scales(self, light: np.ndarray, material: Material):
        """The per-part albedo scales that fit the photo best under `light` (`parts.fit_scales`), over
        the rows the light is fitted to (the fit sample; on the exact route every fit pixel). Under a
        specular material, with the glossy parts' specular weights: (scales, ks_scales)."""
        from ..model.parts import fit_scales
        from ..model.render import render

        L = np.asarray(light, np.float64)
        kd = np.asarray(material.kd, float)[None, :]
        if self.options.exact:
            rows = np.flatnonzero(self.usable & ~self.held)
            weights = np.ones(len(rows))
            diffuse = render(self.vis, L, replace(material, ks=(0.0, 0.0, 0.0)), specular=self.specular_weight())[rows]
            spec = render(self.vis, L, replace(material, kd=(0.0, 0.0, 0.0)),
                          specular=self.specular_weight())[rows] if material.specular else None
        else:
            rows, weights = self.fit_sample.rows, self.fit_w
            Lf = L.astype(np.float32)
            diffuse = kd * (self.fit_rows.diffuse(material).rows @ Lf).astype(np.float64)
            spec = None
            if material.specular:
                spec = np.asarray(material.ks)[None, :] * (self.fit_rows.specular(material).rows @ Lf).astype(np.float64)
                if self.albedo.ks_scales is not None:  # (the rows carry the lobe at weight 1)
                    spec *= self.albedo.ks_scales[self.albedo.part[rows]][:, None]
        if material.specular and not self.albedo.own_ks:  # (--shared-ks: the weights stay)
            kept = self.albedo.ks_scales
            return (fit_scales(self.albedo, rows, weights, diffuse, spec, self.targets[rows]),
                    np.ones(len(self.albedo.parts.parts)) if kept is None else kept)
        return fit_scales(self.albedo, rows, weights, diffuse, spec, self.targets[rows], ks=material.specular)

    def part_leaf_systems(self, tree, material: Material, system=None) -> list:
        """Per part, the leaf-space normal equations of its fit rows (G (3, k, k), h (k, 3), bb (3,))
        with kd = material.kd x base (the part's factor 1), for `parts.varpro_scales`; None for a part
        no fit row sees. The sampled route: the fit sample's rows (from `system`, the Lambertian
        system the tree was solved on, when given: its per-part tree systems are kept); exact: every
        fit pixel."""
        from ..light import haar
        from ..light.rows import _gram

        a = self.albedo
        out = []
        if system is not None and not self.options.exact and getattr(system.fit, "_per_group", False):
            kept = system.fit.group_systems(tree)
            for q in range(len(a.parts.parts)):
                part = kept.get(q)
                out.append(None if part is None else (np.stack([part.gram(c) for c in range(3)]),
                                                      np.asarray(part.h), np.asarray(part.bb)))
            return out
        if self.options.exact:
            from ..light.system import build_normal_equations

            P = haar.leaf_matrix(tree)
            for q in range(len(a.parts.parts)):
                use = self.usable & ~self.held & (a.part == q)
                if not use.any():
                    out.append(None)
                    continue
                part = build_normal_equations(self.vis, self.values, material, use=use, albedo=a.base).fit.project(P)
                out.append((np.stack([part.gram(c) for c in range(3)]), np.asarray(part.h), part.bb))
            return out
        fs = self.fit_sample
        A = self.fit_rows.diffuse(material).leaf_sums(tree)
        kd = np.asarray(material.kd, float)[None, :]
        base, b, part = a.base[fs.rows] * kd, self.targets[fs.rows], a.part[fs.rows]
        sw = np.sqrt(self.fit_w)
        for q in range(len(a.parts.parts)):
            sel = np.flatnonzero(part == q)
            if not len(sel):
                out.append(None)
                continue
            G, h = [], []
            for c in range(3):
                M = A[sel] * (sw[sel] * base[sel, c]).astype(np.float32)[:, None]
                G.append(_gram(M))
                h.append(M.T.astype(np.float64) @ (sw[sel] * b[sel, c]))
            out.append((np.stack(G), np.column_stack(h), (self.fit_w[sel, None] * b[sel] ** 2).sum(axis=0)))
        return out

    def recast(self, backend, texels: np.ndarray, system=None) -> dict:
        """Cast the visibility toward `texels` for every pixel; later systems use it. On the sampled
        route the transport rows whose visibility changed (few: the inference is rarely wrong) are
        rebuilt in place, and `system` (a sampled `LightSystem` on these rows) is corrected by their
        change: its tree systems stay exact without a second pass over the rows. Returns how many
        rows changed."""
        from ..geometry.visibility import VisibilityData, recast_columns

        v = self.vis
        old = np.asarray(v.stored)
        stored = recast_columns(backend, v.samples, v.cube, old, texels, v.supersample)
        changed = np.flatnonzero((stored != old).any(axis=1))
        self.vis = VisibilityData(v.samples, v.cube, v.supersample, stored, castable_only=v.castable_only)
        out = {"pixels": int(len(changed))}
        if self.options.exact:
            return out
        # without a system to correct, the kept transports' rows are still rebuilt in place (the
        # systems projected from them before are stale by their version and projected again)
        parts = {id(self.fit_rows): [] if system is None else [system.fit] + (
                     [system.explore] if system.explore is not None else []),
                 id(self.held_rows): [] if system is None else [system.held_out]}
        for tr in (self.fit_rows, self.held_rows):
            local = np.flatnonzero(np.isin(tr.rows, changed))
            out["fit_rows" if tr is self.fit_rows else "held_out_rows"] = int(len(local))
            before = []
            for part in parts[id(tr)]:
                mine = local[local < part.n_rows]
                before.append((part, mine, part.D.rows[mine].copy(), None if part.S is None else part.S.rows[mine].copy(),
                               part._versions()))
            tr.update(stored[tr.rows[local]], local)
            for part, mine, old_D, old_S, versions in before:
                part.correct(mine, old_D, old_S, versions)
        return out


def recast_bright(systems: _Systems, backend, texels: np.ndarray, material: Material, light_options: LightOptions,
                  progress: Progress, resolve: bool = True, system=None, previous=None):
    """Cast `texels` (`bright_texels` of a light: the directions that carry much of it) exactly for
    every pixel (the visibility was inferred there from neighbours) and solve the light again on
    the corrected system, the level chosen afresh, so the report's levels and errors are all of the
    system the light is solved on. Returns (solution, system, what changed), the solution None
    unless `resolve`.

    `system`: the sampled system of `material` the light was solved on; it is corrected in place
    for the few rows whose visibility changed (`_Systems.recast`), so that solving the levels again
    re-solves the trees it has already projected without a pass over the rows: with `previous` (the
    light solved on it before the cast) its levels' trees are followed (`bases.replay`), else they
    are explored afresh. Without it (and on the exact route) the system is built again and the
    levels explored afresh: the caller drops its old one first, as the transport rows are large
    (~1 GB at R = 32 for a glossy material)."""
    from ..light import bases

    progress.note(f"casting the {len(texels)} brightest light directions exactly for every pixel")
    exact = systems.options.exact
    corrected = not exact and system is not None
    changed = systems.recast(backend, texels, system if corrected else None)
    if not corrected:
        system = systems.system(material)
    if not resolve:
        return None, system, changed
    o = light_options
    sol = bases.replay(system, systems.vis.cube, previous, o.levels_value, o.min_gain) if (
        corrected and previous is not None) else None
    if sol is None:
        sol = bases.solve(system, systems.vis.cube, o.basis, o.levels_value, o.min_gain, o.face_resolution,
                          o.sh_order, o.sh_nonnegative)
    return sol, system, changed


def bright_texels(light: np.ndarray, cube, share_sq: float = BRIGHT_SHARE_SQ, most: int = MAX_BRIGHT) -> np.ndarray:
    """The texels that carry so much of the light that a wrong visibility bit toward them shows: by
    decreasing power share s_i (radiance x solid angle), until the rest's sum of s_i^2 is below
    `share_sq` (an overcast sky: none; a sun: its few texels)."""
    power = np.maximum(np.asarray(light, np.float64), 0).sum(axis=1) * cube.solid_angles
    total = power.sum()
    if total <= 0:
        return np.zeros(0, np.int64)
    share = power / total
    order = np.argsort(-share, kind="stable")
    rest = np.cumsum((share[order] ** 2)[::-1])[::-1]  # rest[k]: sum of s^2 from the k-th brightest on
    k = int(np.searchsorted(-rest, -share_sq))  # the first k with rest[k] <= share_sq
    return np.sort(order[:min(k, most)])


# -- results --------------------------------------------------------------------------------------
@dataclass
class SolveResult:
    material: Material
    solution: object  # light.solution.LightSolution
    reflectance: object  # model.reflectance.Reflectance
    system: object  # the LightSystem the final light was solved on
    vis: object  # the visibility the relit view was rendered with (bright directions exact)
    relit: np.ndarray  # (P, 3) every used pixel under the light
    versus: dict  # relit against the photo
    observability: np.ndarray
    unobservable: np.ndarray
    warnings: list
    report: dict = field(default_factory=dict)
    albedo: object = None  # model.parts.PixelAlbedo with the fitted per-part scales (None: uniform)
    robust_weights: np.ndarray | None = None  # (P,) the robust pass's weights under the final light (None: no pass)


BRIGHT_REGION_DEG = 20.0  # the brightest region: texels this close to the brightest one, at least half as bright
BRIGHT_WINDOW_TEXELS = 1.5  # its centroid is then refined over the texels this many texel widths from it
BRIGHT_JOIN_TEXELS = 2.5  # the region's texels are joined through others at most this many texel widths apart


def _connected(d: np.ndarray, seed: int, candidates: np.ndarray, resolution: int) -> np.ndarray:
    """(N,) bool: the candidate texels joined to `seed` through candidates closer than
    BRIGHT_JOIN_TEXELS face-centre texel widths to each other (diagonals, across face edges, and
    over one texel between: an NNLS light can spread a sun over texels two apart, the one between
    dark)."""
    idx = np.flatnonzero(candidates | (np.arange(len(d)) == seed))
    near = (d[idx] @ d[idx].T) >= np.cos(BRIGHT_JOIN_TEXELS * 0.5 * np.pi / resolution)
    reached = idx == seed
    while True:
        grown = reached | near[reached].any(axis=0)
        if grown.sum() == reached.sum():
            break
        reached = grown
    out = np.zeros(len(d), bool)
    out[idx[reached]] = True
    return out


def brightest(light: np.ndarray, cube) -> dict:
    """The brightest texel (ties: the lowest index) and the energy centroid of the region around it.

    The luminance's excess over the median of the BRIGHT_REGION_DEG disc around the brightest texel
    (the sky around a sun) is the weight. The region: the texels of that disc at least half the
    peak's excess, joined to it through such texels at most BRIGHT_JOIN_TEXELS apart (a coarse
    solve's constant block: its centre; a sun split over texels two apart: between them). Its centroid is then
    refined over every texel within BRIGHT_WINDOW_TEXELS texel widths of it (twice): a sun between
    texel centres spreads over up to four texels (e.g. 0.26 / 0.11 / 0.11 / 0.11 of the light's
    power), of which the half-as-bright region keeps the peak alone (1.8 deg off that sun; the
    window, 0.2 deg), while a wider threshold reaches into a coarse light's blur around the sun.
    When nothing stands above the median (a block covering most of the disc), the texels at least
    half as bright as the peak, unrefined. A region wider than the window (a coarse light's constant
    blocks, a sun wide enough for the texels to resolve) is its own centroid."""
    from ..light.cubemap import direction_to_spherical

    lum = np.asarray(light, np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    i = int(np.argmax(lum))
    d = cube.directions
    near = (d @ d[i]) >= np.cos(np.radians(BRIGHT_REGION_DEG))
    excess = lum - np.median(lum[near])
    power = lum * cube.solid_angles

    def centroid(sel, weight):
        v = (weight[sel, None] * d[sel]).sum(axis=0)
        return v / np.linalg.norm(v) if np.linalg.norm(v) > 0 else d[i]

    if excess[i] > 0:
        weight = np.maximum(excess, 0.0) * cube.solid_angles
        region = _connected(d, i, near & (excess >= 0.5 * excess[i]), cube.resolution)
        centre = centroid(region, weight)
        cos_w = np.cos(BRIGHT_WINDOW_TEXELS * 0.5 * np.pi / cube.resolution)
        # (a region wider than the window is a coarse light's blocks, or a sun the texels resolve: kept)
        refine = float((d[region] @ centre).min()) >= cos_w
        for _ in range(2 if refine else 0):
            region = near & ((d @ centre) >= cos_w) & (excess > 0)
            if not region.any():
                break
            centre = centroid(region, weight)
        how = (f"energy centroid of the brightest region: the texels within {BRIGHT_REGION_DEG:g} deg of the brightest one "
               "at least half its excess over that disc's median, joined to it"
               + (f", then those within {BRIGHT_WINDOW_TEXELS:g} texel widths of their centroid (twice)" if refine else
                  f" (wider than {BRIGHT_WINDOW_TEXELS:g} texel widths: not refined)") + ", weighted by the excess")
    else:
        region = near & (lum >= 0.5 * lum[i]) & (lum > 0)
        centre = centroid(region, power)
        how = (f"energy centroid of the texels within {BRIGHT_REGION_DEG:g} deg of the brightest one and at least "
               "half as bright (nothing stands above that disc's median)")
    theta, phi = direction_to_spherical(np.stack([d[i], centre]))
    return {"texel": i, "direction": d[i].tolist(), "theta_deg": float(np.degrees(theta[0])),
            "phi_deg": float(np.degrees(phi[0]) % 360.0), "radiance_rgb": np.asarray(light)[i].tolist(),
            "centroid": {"direction": centre.tolist(), "theta_deg": float(np.degrees(theta[1])),
                         "phi_deg": float(np.degrees(phi[1]) % 360.0), "texels": int(region.sum()),
                         "power_share": float(power[region].sum() / max(power.sum(), 1e-300)),
                         "note": how}}


def narrow_lobe_note(material: Material, bright: dict, resolution: int) -> str | None:
    """A warning when the fitted lobe is narrower than a texel of the cube map and a compact source
    (`brightest`'s region) holds at least SUN_SHARE of the light's power: the sun sits at its texels'
    centres, up to half a texel from where it is, and a highlight that narrow moves with it (the fit
    makes up for it with the lobe's width: teapot_plastic_sun, Beckmann alpha 0.05, fits 0.036 at
    R = 32 and 0.044 at R = 64, its new view 8.9 -> 4.8 % off; suzanne_plastic_sun's alpha 0.1, twice
    a texel, gains nothing from R = 64). None otherwise."""
    alpha = material.lobe_alpha
    texel = 0.5 * np.pi / resolution  # a texel's width at a face's centre (radians)
    share = float(bright.get("centroid", {}).get("power_share", 0.0))
    if alpha is None or alpha >= texel or share < SUN_SHARE:
        return None
    lobe = f"alpha {alpha:.3g}" if material.model == PLASTIC else f"n {material.shininess:.4g}, as wide as alpha {alpha:.3g}"
    return (f"the lobe ({lobe}) is narrower than a texel of the light ({np.degrees(texel):.1f} deg at "
            f"R = {resolution}) and a compact source holds {100 * share:.0f} % of its power: the source sits at "
            f"its texels' centres, up to half a texel off, and so does its highlight (the fit bends the lobe's "
            f"width to make up for it); a larger R (-R {2 * resolution}: ~3x the time) resolves it better")


# -- the controller -----------------------------------------------------------------------------
def prepare_photo(vis, photo, options: SolveOptions, photo_path=None, held_out: np.ndarray | None = None):
    """The photo at the used pixels: (values (P, 3), usable (not saturated), held out), with the
    checks that the photo holds something to fit; `held_out` (P,) bool replaces the scattered
    held-out pixels (several views: a whole view, `controllers.views.holdout`)."""
    from ..light.system import holdout_mask

    rows, cols = vis.samples.pixel[:, 0], vis.samples.pixel[:, 1]
    values = photo.pixels[rows, cols].astype(np.float64)
    saturated = photo.saturated[rows, cols]
    if saturated.all():
        raise InputError("every used pixel is saturated (clipped)", photo_path,
                         "use a darker exposure or an HDR (EXR) photo")
    if not np.any(values[~saturated] > 0):
        raise InputError(f"the photo is black (nothing above 0: negative values read as 0) over all {len(values)} "
                         "used pixels: there is no light to recover", photo_path,
                         "check the exposure, the lens cap, the mask and that this is the right photo")
    if held_out is not None:
        held = np.asarray(held_out, bool)
    else:
        held = holdout_mask(vis.samples.pixel, options.held_out) if options.held_out > 0 else np.zeros(len(values), bool)
    return values, ~saturated, held


def pixel_counts(usable: np.ndarray, held: np.ndarray, bounds: bool) -> dict:
    """solve_report.json's `pixels`: used, saturated (left out, or lower bounds), fit and held out."""
    n_sat = int((~usable).sum())
    return {"used": int(len(usable)), "saturated": n_sat, "saturated_excluded": 0 if bounds else n_sat,
            "saturated_as_lower_bounds": n_sat if bounds else 0,
            "fit": int((usable & ~held).sum()), "held_out": int((usable & held).sum())}


def robust_counts(w, counted, bound, clipped, values, relit, usable) -> dict:
    """What the robust weights `w` (P,) of the final pass do over every used pixel."""
    from ..light.robust import below_bound
    from ..metrics import relative_rmse

    below = bound & below_bound(values, clipped, relit)
    judged = counted & ~(bound & ~below)  # (a clipped pixel the light predicts at least as bright: satisfied)
    out = {"pixels": int(counted.sum()), "down_weighted_pixels": int((judged & (w < 1)).sum()),
           "left_out_pixels": int((judged & (w == 0)).sum()),
           "relative_rmse_robust_weighted": relative_rmse(relit[usable], values[usable], w[usable])}
    if bound.any():
        out["clipped_pixels_below_bound"] = int(below.sum())
        out["clipped_pixels_below_bound_down_weighted"] = int((below & (w < 1)).sum())
    return out


def robust_summary(options: SolveOptions, info: dict | None, saturated: np.ndarray) -> dict:
    """solve_report.json's `robust`: what the robust pass did (`info`), with its line for the console."""
    from ..light.robust import MAX_DOWN_SHARE

    n_sat = int(np.sum(saturated))
    if info is None:
        why = "--exact (the reference route is plain least squares)" if options.exact else "--no-robust"
        return {"applied": False, "note": f"not applied: {why}; clipped pixels left out", "clipped_pixels": n_sat}
    mode = ("lower bounds" if options.bounds else "left out") if n_sat else "none in the photo"
    rep = {"applied": True, **info, "clipped_pixels": n_sat, "clipped": mode,
           "note": ("a pixel whose distance to the range its prediction takes within edge_pixels (widened by "
                    "edge_slack of it each way, and by peak_widths of it past a peak or trough) is beyond threshold_sigmas of its noise (sigma by predicted "
                    "brightness) is down-weighted, to 0 at twice that; at most "
                    f"{100 * MAX_DOWN_SHARE:g} % of the pixels; the light is solved again (auto's model chosen "
                    "again the first time) when the weights move at least "
                    f"{100 * ROBUST_TRIGGER:g} % of the squared error (influence), and that solve is kept only if "
                    f"its plain relit error is at most {100 * ROBUST_ACCEPT:g} % above the plain solve's (kept, "
                    "plain_relit_rmse); a clipped channel is a lower bound: only a prediction below it is an error")}
    solved = f"solved again {info['rounds']} time(s)" if info["rounds"] else "nothing to solve again"
    if info.get("kept") is False:
        p = info["plain_relit_rmse"]
        solved += (f", not kept (the plain relit error would rise {100 * p['before']:.2f} -> {100 * p['after']:.2f} %: "
                   "the pixels it down-weighted carry the light)")
    rep["line"] = (f"robust fit: {info['down_weighted_pixels']} of {info['pixels']} pixels down-weighted "
                   f"({info['left_out_pixels']} to zero), {solved}"
                   + (f"; {n_sat} clipped pixels as lower bounds, {info.get('clipped_pixels_below_bound', 0)} of "
                      f"them left below it ({info.get('clipped_pixels_below_bound_down_weighted', 0)} of those "
                      "down-weighted: a clipped core the model cannot reach)" if n_sat and options.bounds else
                      (f"; {n_sat} clipped pixels left out" if n_sat else "")))
    return rep


def clipped_channels(values: np.ndarray, saturated: np.ndarray) -> np.ndarray:
    """(P, 3) the channels of saturated pixels that are at the format's maximum (1 after reading):
    what a lower bound holds for. A saturated pixel's other channels are measurements."""
    top = values >= CLIP_VALUE
    clipped = np.asarray(saturated, bool)[:, None] & top
    lost = np.asarray(saturated, bool) & ~clipped.any(axis=1)  # (not at 1: a pixel scaled after reading)
    clipped[lost] = True
    return clipped


def plastic_starts(start: Material, given: set) -> list[Material]:
    """The plastic fits `auto` probes: the start's distribution if given, else GGX and Beckmann."""
    if "distribution" in given:
        return [start]
    return [start, replace(start, distribution="beckmann" if start.distribution == "ggx" else "ggx")]


def solve_scene(vis, photo, material: Material, options: SolveOptions, reflectance: ReflectanceOptions,
                given: set | None = None, backend=None, photo_path=None, progress: Progress | None = None,
                adaptive: bool = False, held_out: np.ndarray | None = None, albedo=None) -> SolveResult:
    """Recover the light and the reflectance from a photo.

    vis : the used pixels' visibility (`geometry.visibility.VisibilityData`); `adaptive`: it was
        inferred where neighbours agree (the bright directions are then cast again with `backend`).
    photo : `io.images.LoadedImage` of the camera's size; photo_path names it in error messages.
    material : the given material (its kd sets the light's scale; a fit starts from it).
    held_out : (P,) bool, the rows held out for the model choice (default: a hash of the pixel
        positions, `options.held_out` of them).
    albedo : `model.parts.PixelAlbedo` of the used pixels (several parts, textures), or None (one
        uniform material). Its per-part scales are fitted with the light (alternating, closed form);
        the reference part's stays (the light x albedo scale).
    """
    from ..light import bases
    from ..light import solution as ls
    from ..light.rows import with_scales
    from ..model import reflectance as rf
    from ..model.render import render

    progress = progress or Progress()
    given = given or set()
    reflectance.check()
    if reflectance.fits:
        reflectance.start(material, given)
    t0 = time.monotonic()
    values, usable, held = prepare_photo(vis, photo, options, photo_path, held_out)
    saturated = ~usable
    clipped = clipped_channels(values, saturated)
    if saturated.any():
        what = ("fitted as lower bounds after the first solve" if options.bounds else "left out")
        progress.note(f"{len(values)} used pixels ({int(saturated.sum())} saturated pixels {what})")
    systems = _Systems(vis, values, usable, held, options, progress, albedo, clipped)
    kd_reference = material.kd
    light_options = options.light

    def on_level(rec):
        h = "" if rec.held_out_rmse is None else f", held-out {100 * rec.held_out_rmse:.3f} %"
        progress.note(f"{light_options.basis} level {rec.index}: {rec.n_coefficients} coefficients, "
                      f"fit {100 * rec.fit_rmse:.3f} %{h}")

    refined: dict = {}  # the latest refinement: reflectance rounds re-solve its model, not refine again

    def full_solve(m: Material, ne, all_pixels: bool = False):
        """The levels explored on `ne`. Not re-solved on all its pixels unless `all_pixels`: most
        lights are intermediate (a first light the reflectance rounds re-solve, a Lambertian light
        the bright-direction cast solves again); the final one is re-solved by `finished`."""
        o = light_options
        sol = bases.solve(ne, vis.cube, o.basis, o.levels_value, o.min_gain, o.face_resolution, o.sh_order,
                          o.sh_nonnegative, on_level, all_pixels)
        refined["solution"] = refined[("model", m.model)] = sol
        return sol

    part_scales: dict = {}  # id(light solution) -> the per-part scales it was solved with

    def solve_light(m: Material):
        sol, ne = solve_light_only(m)
        if albedo is None:
            return sol, ne
        # light <-> per-part albedo scales: the intermediate lights re-solve the first one's tree
        # (warm started), and steady steps of the log scales jump towards their limit (the light
        # and the scales trade off along a slow direction); the last round refines afresh
        if getattr(sol, "tree", None) is not None and not m.specular:
            # a Lambertian light on a tree: the factors with the light re-solved for each (variable
            # projection on the tree's leaves), the light re-solved on its tree, the factors once
            # more, then the light refined afresh
            from ..model.parts import varpro_scales

            # (sampled route: the step between re-solves the tree under the new factors, its per-part
            # systems kept, and only the last one explores the levels afresh)
            for k in range(2):
                new = varpro_scales(albedo, systems.part_leaf_systems(sol.tree, m, ne))
                change = float(np.max(np.abs(new / albedo.scales - 1)))
                albedo.scales = new
                last = k == 1 or change < 10 * PART_TOL
                if not last and not options.exact:
                    ne = with_scales(ne, albedo.scales)
                    quick = bases.refit(ne, vis.cube, sol, all_pixels=False)
                    if quick is not None:
                        sol = quick
                        continue
                sol, ne = solve_light_only(m, ne)
                if last:
                    break
            return _parts_done(sol, ne, k)
        history = [np.log(albedo.scales)]
        first = sol
        for k in range(PART_ROUNDS):
            new = systems.part_scales(sol.light, m)
            if m.specular:  # (and the glossy parts' specular weights: `parts.fit_scales`)
                new, ks_new = new
                before = albedo.part_ks()
                albedo.ks_scales = None if np.all(ks_new == 1) else ks_new
                after = albedo.part_ks()
                ks_change = float(np.max(np.abs(after - before) / np.maximum(before, 1e-12)))
            else:
                ks_change = 0.0
            change = max(float(np.max(np.abs(new / albedo.scales - 1))), ks_change)
            history.append(np.log(new))
            if len(history) >= 3:
                d_prev, d = history[-2] - history[-3], history[-1] - history[-2]
                denom = float((d_prev * d_prev).sum())
                rho = float((d * d_prev).sum()) / denom if denom > 0 else 0.0
                if 0.0 < rho < 1.0:
                    rho = min(rho, 0.9)
                    history[-1] = history[-1] + d * rho / (1.0 - rho)
                    new = np.exp(np.clip(history[-1], -20, 20))
            albedo.scales = new
            if change < PART_TOL or k == PART_ROUNDS - 1:
                sol, ne = solve_light_only(m)
                break
            if options.exact:
                ne = systems.system(m)
            elif k == 0:
                ne = systems.system(m) if not m.specular else systems.system(m, ROUND_ROWS)
            else:  # the same rows under the new factors: their tree systems are kept per part
                ne = with_scales(ne, albedo.scales, np.ones(len(albedo.scales)) if albedo.ks_scales is None else
                                 albedo.ks_scales)
            quick = bases.refit(ne, vis.cube, first)  # (its light feeds the next factors: all pixels)
            if quick is None:
                sol, ne = solve_light_only(m)
            else:
                sol = quick
        return _parts_done(sol, ne, k)

    def _parts_done(sol, ne, k):
        part_scales[id(sol)] = (albedo.scales.copy(), None if albedo.ks_scales is None else albedo.ks_scales.copy())
        names = albedo.parts.names
        progress.note(f"part albedo after {k + 1} round(s) (relative to {names[albedo.parts.reference]}): " + ", ".join(
            f"{n} {' '.join(f'{v:.3g}' for v in albedo.scales[i])}" for i, n in enumerate(names)))
        return sol, ne

    def solve_light_only(m: Material, previous=None):
        if previous is not None and albedo is not None and not options.exact and not m.specular:
            # the Lambertian system of the part factors before: its tree systems are kept per part, so
            # the levels are explored again under the new factors without a pass over the rows
            ne = with_scales(previous, albedo.scales)
            return full_solve(m, ne), ne
        if not options.exact and m.specular and bases.BASES[light_options.basis].module == "tree":
            # a reflectance round: the tree refined under this model re-solved on a smaller system (the
            # rounds fit a handful of material parameters; the final light is refined on the whole
            # sample). A model's first light refines first (the levels explored under it: a tree
            # refined under Lambert, bent towards the highlights, cannot hold a lobe's light: DiLiGenT
            # 092's plastic rounds fitted 18 % on it against 9 % on their own), then re-solves on the
            # same smaller system, so that every round's errors are over the same rows
            # (the round's system before holds its lobe's transports (heads of them): they go before
            # this one's are built, or both are held at once: memory). The bases without a tree solve
            # every round's light afresh, below.
            # The first light's exploration is on the explore rows (the fit sample's head) and the
            # held-out ones, and only its tree is kept: its system is built on that head alone, which
            # the round's system then shares (the same lobe's transport, not built again), instead of
            # the lobe's transport for every fit row (teapot_sun_phong: 16 k rows under each of three
            # lobes) that only the exploration's last fit error over all of them would have read
            last_round.clear()
            if ("model", m.model) not in refined:
                full_solve(m, systems.system(m, rows=max(ROUND_ROWS, EXPLORE_ROWS)))
            # (re-solved on its held-out rows too: the round's light feeds the next LM fit, which a
            # light fitted to fewer rows leads astray: suzanne_plastic_sun's alpha 0.1285 -> 0.1321,
            # its sun 1.4 -> 5.5 deg off, with the fit rows' light alone)
            ne = systems.system(m, ROUND_ROWS)
            sol = bases.refit(ne, vis.cube, refined[("model", m.model)])
            if sol is not None:
                last_round.update(solution=sol, system=ne)
                return sol, ne
        ne = systems.system(m)
        # (a specular light here is a round's on the exact route: it feeds the next LM fit, so it is
        # re-solved on all pixels, as the sampled route's rounds are)
        return full_solve(m, ne, m.specular), ne

    last_round: dict = {}  # the last reflectance round's light and its (sampled) system
    ratio_drops: dict = {}  # model -> the residual drop of its last ratio step (`lobe_ratio`)

    def lobe_ratio(m: Material, sol):
        """A glossy round's kd colour and ks with the light re-solved for each (`reflectance.lobe_ratio`,
        on the round's tree and fit rows), and its light: (material, solution, None, what was found), or None when the
        round's system is not at hand (the exact route; parts and textures, whose factors are fitted
        per part), it does not lower the round's fit error, or the model's step before lowered the
        residual by less than RATIO_CONVERGED (the ratio has settled: later rounds move the lobe)."""
        from ..light.rows import lobe_pieces

        if albedo is not None or options.exact or not m.specular or getattr(sol, "tree", None) is None:
            last_round.clear()
            return None
        if ratio_drops.get(m.model, 1.0) < RATIO_CONVERGED:
            last_round.clear()
            return None  # (its last step hardly moved it: the LM's ks under that light is the light's own)
        # the rows the round's light was solved on (a candidate's first light, solved before the
        # others': the same sample of rows, its transports built again when another candidate's
        # replaced them)
        t0 = time.perf_counter()
        system = last_round.get("system") if last_round.get("solution") is sol else None
        # (the system's transport rows go once the pieces are out; another candidate's, still kept
        # when this round's light is a first light solved before it, goes before this one is built:
        # memory, on teapot_sun_phong its peak of live arrays 1.34 -> 1.23 GB)
        last_round.clear()
        if system is None:
            system = systems.system(m, ROUND_ROWS)
        pieces = lobe_pieces(system.fit, sol.tree)
        system = None
        if pieces is None:
            return None
        t1 = time.perf_counter()
        m2, info = rf.lobe_ratio(pieces, m, material.kd)
        t2 = time.perf_counter()
        ratio_drops[m.model] = info["residual_drop"]
        if not info["residual_drop"] > RATIO_MIN_DROP:
            return None
        sol2, ne2 = round_light(m2)
        last_round.clear()
        info["seconds"] = {"pieces": t1 - t0, "search": t2 - t1, "light": time.perf_counter() - t2}
        if not sol2.fit_rmse < sol.fit_rmse:
            return None
        return m2, sol2, ne2, info

    def round_light(m: Material):
        """`solve_light` for the reflectance fits: a specular round's light on the sampled route is a
        re-solve on a smaller system, and `refine_chosen` builds the chosen material's system anew, so
        the round's system is not returned (its transport rows held through the rounds: memory)."""
        sol, ne = solve_light(m)
        if not options.exact and m.specular and sol is not refined.get("solution"):
            ne = None
        return sol, ne

    def on_round(r):
        h = "" if r.held_out_rmse is None else f", held-out {100 * r.held_out_rmse:.3f} %"
        lm = "" if r.fit is None else f" (LM: {r.fit.evaluations} evaluations, {r.fit.seconds:.1f} s)"
        progress.note(f"reflectance round {r.index}: {material_text(r.material)}{lm}: error {100 * r.fit_rmse:.3f} %{h}")

    def current_albedo():
        return None if albedo is None else albedo.values()

    lm_rows = probe_rows = None
    if not options.exact:  # the LM fits the same pixels the light is fitted to; the probe a few of them
        def lm_rows(light, kd):  # (of the glossy parts: `decide_glossy`)
            # (an LM fit follows: the round's lobe transports go, the next round's lobe is another: memory)
            systems.fit_rows.release_lobe(), systems.held_rows.release_lobe()
            return systems.glossy_rows(systems.highlight_rows(light, kd, LM_ROWS, LM_ROWS // 4))

        def probe_rows(light):
            return systems.glossy_rows(systems.highlight_rows(light, kd_reference, PROBE_ROWS, PROBE_ROWS // 2))

    def fit_use():  # the pixels a reflectance fit may use: not those of matte parts
        w = systems.specular_weight()
        return usable if w is None else usable & (w > 0)

    def decide_glossy(data, probe):
        """auto, several parts: which parts the probe's lobe belongs on (`parts.glossy_parts`); their
        rows alone are fitted from now on. Returns the (P,) glossy pixels and a note, or None when
        there is nothing to decide (one part, or every part declared in materials.toml)."""
        from ..model.parts import glossy_parts
        from ..model.reflectance import SpecularData

        if albedo is None or len(albedo.parts.parts) < 2 or all(p.specular is not None for p in albedo.parts.parts):
            return None
        # the probe's shading with the Lambertian light fixed: its base and its lobe at the fitted width
        if isinstance(data, SpecularData):
            D, S = data.diffuse, data.specular(probe.material.shininess)
            plain = None
        else:  # (plastic: a matte part has no coating either, its shading the Lambertian one)
            D, S = data.evaluate(probe.material.roughness)
            plain = data.lambert
        glossy, sources, info = glossy_parts(albedo.parts, albedo.part[data.rows], D, S, data.photo,
                                             reflectance.min_specular_gain, plain)
        systems.set_glossy(glossy, sources)
        note = "specular term per part: " + ", ".join(
            f"{p.name} {'glossy' if g else 'matte'} ({src})" for p, g, src in zip(albedo.parts.parts, glossy, sources))
        progress.note(note)
        w = systems.specular_weight()
        return (np.ones(len(values), bool) if w is None else w > 0), info

    def decide_given(start: Material):
        """A given model (--reflectance blinn-phong / plastic) on several undeclared parts: which of them
        wear its lobe, decided as `auto` does (`decide_glossy`) on a probe of the model with the
        Lambertian light fixed (a light solved under the lobe has bent to it on every part); when
        none would, every part keeps it (the model was asked for). Returns the parts' numbers or None."""
        if albedo is None or len(albedo.parts.parts) < 2 or all(p.specular is not None for p in albedo.parts.parts):
            return None
        progress.note(f"reflectance {reflectance.mode}: which parts wear its lobe: a probe with the Lambertian "
                      "light fixed")
        sol0, _ = round_light(Material(kd=material.kd))
        chosen = probe_rows(sol0.light) if probe_rows is not None else None
        data = rf.lm_data(vis, values, sol0.light, start, fit_use(), held, albedo=current_albedo(),
                          lobe=systems.specular_weight(), **({} if chosen is None else
                                                             {"rows": chosen[0], "weights": chosen[1]}))
        before = (albedo.glossy, albedo.glossy_source)
        decided = decide_glossy(data, rf.lm_fit(data, start))
        if decided is not None and not decided[0].any():
            systems.set_glossy(*before)
            progress.note("specular term per part: no part's own lobe is significant; every part keeps the "
                          "given model's")
        return None if decided is None else decided[1]

    auto_select = None  # auto's choice among the models, run again by the robust pass under its weights
    try:
        if reflectance.mode == "given":
            result = rf.fixed(material, round_light, "given", "given by the user (--material/--model/--kd/--ks/"
                              "--shininess): not fitted", on_round)
        elif reflectance.mode == "lambert":
            result = rf.fixed(Material(kd=material.kd), round_light, "lambert", "lambert: chosen by --reflectance",
                              on_round)
        elif not fit_use().any() and systems.specular_weight() is not None:
            result = rf.fixed(Material(kd=material.kd), round_light, reflectance.mode,
                              "lambert: every part is matte (materials.toml: specular = false)", on_round)
        else:
            start = reflectance.start(material, given)
            progress.note(f"reflectance {reflectance.mode}: start {material_text(start)}")
            if reflectance.mode == "auto":
                def auto_select(photo_values, use, held_out, start=start, kd=material.kd,
                                starts=plastic_starts(reflectance.plastic_start(material, given), given)):
                    return rf.select(vis, photo_values, start, round_light, use, held_out, kd,
                                     reflectance.min_specular_gain, reflectance.max_rounds, progress=on_round,
                                     rows=lm_rows, probe_rows=probe_rows, plastic_starts=starts,
                                     note=progress.note, albedo=current_albedo, per_part=decide_glossy,
                                     lobe=systems.specular_weight, ratio=lobe_ratio)

                result = auto_select(values, fit_use(), held)
            else:
                decided = decide_given(start)
                result = rf.alternate(vis, values, start, round_light, fit_use(), held, material.kd,
                                      reflectance.max_rounds, progress=on_round, rows=lm_rows, albedo=current_albedo,
                                      lobe=systems.specular_weight, ratio=lobe_ratio)
                if decided is not None:
                    result.candidates["parts"] = decided
    except rf.FitError as exc:
        raise InputError(f"cannot fit the reflectance: {exc}", photo_path,
                         "use --reflectance lambert, or check the photo and the pose") from None
    last_round.clear()  # (a round's transport rows: memory)
    material, sol, system = result.material, result.solution, result.context
    systems.keep_only(material)
    if albedo is not None:  # the chosen light's own scales (a later round may have refitted them)
        albedo.scales, albedo.ks_scales = part_scales.get(id(sol), (albedo.scales, albedo.ks_scales))

    recast, changed = np.zeros(0, np.int64), None

    def cast(sol, system, done, resolve):
        """The recast of the light's bright directions not cast yet (`recast_bright`): (solution or
        None, system, the directions cast so far)."""
        nonlocal changed
        if not (adaptive and backend is not None):
            return None, system, done
        texels = np.setdiff1d(bright_texels(sol.light, systems.vis.cube), done)
        if not len(texels):
            return None, system, done
        keep = None if options.exact else system  # corrected in place (the exact route builds anew)
        if resolve:
            result.context = system = None  # (on the exact route the old G goes before the new one is built)
            sol, system, counts = recast_bright(systems, backend, texels, material, light_options, progress,
                                                system=keep, previous=sol)
        else:  # (the rows alone: the caller builds its system next)
            progress.note(f"casting the {len(texels)} brightest light directions exactly for every pixel")
            sol, counts = None, systems.recast(backend, texels, keep)
        changed = counts if changed is None else {k: changed.get(k, 0) + counts.get(k, 0)
                                                  for k in {**changed, **counts}}
        return sol, system, np.union1d(done, texels)

    def cast_bright(sol, system, done):
        """The light re-solved after its bright directions are cast, when some were not yet."""
        again, system, done = cast(sol, system, done, True)
        return (sol if again is None else again), system, done

    def refine_chosen(material, sol, system, done):
        if not options.exact and material.specular and sol is not refined.get("solution"):
            # the rounds re-solved the refinement of an earlier material on a smaller system: refine once
            # more under the chosen one, on the whole sample. The round's light has the refined one's
            # bright directions (the same sun): they are cast first, its rows corrected in place, so
            # the refinement is the final solve instead of one more exploration of the levels after it
            # (a bright direction only the refined light has is still cast after it: `cast_bright`)
            _, _, done = cast(sol, system, done, False)
            progress.note(f"refining the light under {material_text(material)}")
            system = systems.system(material)
            sol = full_solve(material, system)
        elif system is None and not options.exact:
            # (auto let the Lambertian system go while it tried the lobes: memory) built again, so that
            # the bright-direction cast corrects it in place and replays the light's levels on it (the
            # exact route's cast builds its system anew in any case: `finished` builds it otherwise)
            system = systems.system(material)
        return sol, system, done

    sol, system, recast = refine_chosen(material, sol, system, recast)
    result.solution, result.context = sol, system

    def finished(sol, system):
        """The final light: re-solved on all pixels of the system it was solved on when it is an
        intermediate one (`full_solve`)."""
        return sol if system is None else bases.finish(system, vis.cube, sol)

    def relit_view(sol):
        return render(systems.vis, sol.light, material, albedo=None if albedo is None else albedo.values(),
                      specular=systems.specular_weight())

    sol, system, recast = cast_bright(sol, system, recast)
    if system is None:  # (the exact route's Lambertian system, let go by auto and not built by a cast)
        system = systems.system(material)
    sol = finished(sol, system)
    relit = relit_view(sol)
    robust_info = robust_weights = None
    if options.robust and not options.exact:
        # the robust pass (`light.robust`): the pixels the model cannot explain down-weighted, clipped
        # channels fitted as lower bounds; the light (and a fitted specular term) solved again under
        # those weights, until they settle
        from ..light import robust

        bound = clipped.any(axis=1) & saturated if options.bounds else np.zeros(len(values), bool)
        counted = usable | bound
        weights, targets = usable.astype(np.float64), values
        plain = (material, sol, relit, None if albedo is None else albedo.scales.copy(), result.material,
                 list(result.rounds), result.chosen_round, result.decision, dict(result.candidates))
        refits = []
        # auto's choice is made again under the weights once (`choose_again`): False until the weights
        # steer the light, True while it waits for them to settle, "now" on the pass that makes it,
        # None once made (or when there is none to make: no auto, several parts)
        choose_again = False if (auto_select is not None and (albedo is None or len(albedo.parts.parts) < 2)) else None
        for k in range(ROBUST_ROUNDS + 1):
            # (a bound says how bright, not where: a clipped pixel's hinge is judged by the noise alone,
            # so a clipped highlight the model cannot reach is an outlier, not a pull on the light)
            span = robust.edge_span(vis.samples.pixel, relit, exempt=bound)
            noise = robust.noise_model(values[counted], clipped[counted], relit[counted], span[counted])
            w = np.where(counted, robust.weights(noise, values, clipped, relit, span), 0.0)
            # a clipped pixel the light already predicts at least as bright is not fitted (an active set:
            # pinned to its prediction, it would hold the light to a value the photo does not know)
            satisfied = bound & ~robust.below_bound(values, clipped, relit)
            w[satisfied] = 0.0
            t = robust.lower_bound_targets(values, clipped, relit)
            e2 = robust.residual_rms(values, clipped, relit) ** 2
            # how much of the fit's squared error the new weights and targets move (a clipped pixel's
            # target moves with the prediction: that counts once it has its weight)
            moved = (np.abs(w - weights) * e2).sum()
            moved += (np.minimum(w, weights) * ((t - targets) ** 2).mean(axis=1))[bound].sum()
            influence = float(moved / max((weights * e2).sum(), (w * e2).sum(), 1e-300))
            robust_info = {"rounds": k, "influence": influence, "noise": noise.summary()}
            if (influence < ROBUST_TRIGGER and not choose_again) or k == ROBUST_ROUNDS:
                break
            weights, targets = w, t
            down = counted & ~satisfied & (w < 1)
            progress.note(f"robust pass {k + 1}: {int(down.sum())} of {int(counted.sum())} pixels down-weighted "
                          f"({int((down & (w == 0)).sum())} to zero)"
                          + (f", {int((bound & ~satisfied).sum())} clipped pixels below their bound"
                             if bound.any() else "")
                          + f" ({100 * influence:.1f} % of the squared error moved): solving again")
            systems.robust(w, t, system, material)
            # (the system under the weights before is stale: every branch below builds its own; the
            # first one built takes over its tree systems if of the same material and all rows (a
            # Lambertian re-solve, auto's Lambertian light; not a reflectance round's smaller one);
            # else it goes before the next transport rows are built: memory)
            result.context = system = None
            again = quick = None
            if not material.specular and albedo is None and not bound.any():
                # the chosen level's tree refitted under the new weights first (its systems taken over,
                # corrected at the changed rows: cheap). When its prediction moves by less than
                # ROBUST_STILL of the noise (RMS over the counted pixels of the change over sigma(y)),
                # the pixels the weights changed were not steering the light: the levels and the model
                # chosen under the old weights stand, and exploring them again (auto's choice made
                # again) would find what they found (spot_sun: 3 of 14,334 pixels down-weighted, the
                # same level and model, probes within 1 %). Else that system is the next one's start
                ne = systems.system(material)
                quick = bases.refit(ne, vis.cube, sol)
                relit_q = relit_view(quick)
                sigma = np.interp(robust.brightness(relit[counted]), noise.brightness, noise.sigma)
                change = float(np.sqrt(np.mean(((relit_q[counted] - relit[counted]) ** 2).mean(axis=1)
                                               / sigma ** 2)))
                refits.append(round(change, 4))
                if change < ROBUST_STILL and not choose_again:
                    progress.note(f"robust pass {k + 1}: the light refitted on its tree moved the prediction "
                                  f"by {change:.3f} of the noise (< {ROBUST_STILL:g}): its levels and model kept")
                    sol, system = quick, ne
                else:
                    systems.robust(w, t, ne, material)  # (the next system takes over the refit's)
                    quick = ne = None
                    if choose_again is False and k + 1 < ROBUST_ROUNDS:
                        # the weights moved the light: auto's choice is due, but it waits until they settle
                        # (this pass's weights were judged against a light the spoiled pixels bent, and catch
                        # only some of them: bunny_sun with 2 % spoiled, 557 of the 1,029 a later pass
                        # down-weights, and the glints left let a lobe's probe look significant, so every
                        # candidate's light was solved for nothing). Until then the Lambertian light alone
                        # is solved again (its levels explored afresh: cheap), below
                        choose_again = True
                        progress.note(f"robust pass {k + 1}: the light moved by {change:.3f} of the noise: the "
                                      "model is chosen again once the weights settle")
                    elif choose_again is not None and (change < ROBUST_STILL or k + 1 >= ROBUST_ROUNDS):
                        choose_again = "now"  # (settled: the refit hardly moved; or the last pass)
                        progress.note(f"robust pass {k + 1}: the light moved by {change:.3f} of the noise: the model "
                                      "is chosen again under these weights")
            elif choose_again is False:
                choose_again = "now"  # (no quick refit to tell whether the weights settled: a lobe's scene)
            if quick is None and choose_again == "now":
                choose_again = None
                # auto's choice made again under the weights: the pixels they take weight off decided it
                # too (teapot_sun_phong, Blinn-Phong, with 2 % of its pixels spoiled: the glints chose
                # plastic, whose parameters alone the weights then refitted); each model's tree is
                # refined afresh, as a tree bent towards the glints would hold them. (Several parts:
                # which of them wear the lobe was decided with the first choice; the chosen model is
                # refitted, below.)
                refined.clear(), ratio_drops.clear(), last_round.clear()
                try:
                    again = auto_select(t, counted, held & ~bound)
                except rf.FitError as exc:
                    progress.note(f"robust pass: auto's choice not made again ({exc}): the chosen model is refitted")
                last_round.clear()
            if quick is not None:
                pass
            elif again is not None:
                material = again.material
                systems.keep_only(material)
                sol, system, recast = refine_chosen(material, again.solution, again.context, recast)
                n0 = len(result.rounds)
                result.rounds += [replace(r, index=n0 + r.index, kind="robust") for r in again.rounds]
                result.chosen_round = n0 + again.chosen_round
                result.material, result.candidates = material, again.candidates
                result.decision += f"; chosen again under the robust weights: {again.decision}"
            elif k == 0 and material.specular and reflectance.fits:
                again = rf.alternate(vis, t, material, round_light, counted, held & ~bound, kd_reference,
                                     ROBUST_LM_ROUNDS, progress=on_round, rows=lm_rows, albedo=current_albedo,
                                     lobe=systems.specular_weight)
                material = again.material
                sol, system, recast = refine_chosen(material, again.solution, again.context, recast)
                n0 = len(result.rounds)
                result.rounds += [replace(r, index=n0 + r.index, kind="robust") for r in again.rounds]
                result.chosen_round = n0 + again.chosen_round
                result.material = material
                result.decision += (f"; then refitted under the robust weights: {material_text(material)} "
                                    f"({again.decision})")
            elif material.specular:
                system = systems.system(material)
                sol = full_solve(material, system)
            else:
                sol, system = solve_light(material)
            if albedo is not None:
                albedo.scales, albedo.ks_scales = part_scales.get(id(sol), (albedo.scales, albedo.ks_scales))
            done = sol
            sol, system, recast = cast_bright(sol, system, recast)
            sol = finished(sol, system)
            relit = relit_q if (quick is not None and sol is done) else relit_view(sol)
        if refits:
            robust_info["refit_change_sigmas"] = refits  # (each round's refit on the kept tree, `ROBUST_STILL`)
        robust_info.update(robust_counts(w, counted, bound, clipped, values, relit, usable))
        robust_weights = np.where(satisfied, 1.0, w)  # (a satisfied bound is not a down-weighted pixel)
        if robust_info["rounds"]:
            # the check: down-weighting a few spoiled pixels hardly changes how well the light explains the
            # whole photo; when the plain error over every usable pixel rises by more than ROBUST_ACCEPT,
            # the pixels it took weight off were carrying the light (a texture or a highlight the model
            # cannot follow, not specks): the plain solve is kept, and the report says so
            before = versus_photo(plain[2], values, usable)["relative_rmse_vs_photo"]
            after = versus_photo(relit, values, usable)["relative_rmse_vs_photo"]
            robust_info["plain_relit_rmse"] = {"before": before, "after": after}
            if after > (1.0 + ROBUST_ACCEPT) * before:
                (material, sol, relit, scales, result.material, result.rounds, result.chosen_round, result.decision,
                 result.candidates) = plain
                if albedo is not None:
                    albedo.scales = scales
                systems.robust(usable.astype(np.float64), values)
                system = None  # (the robust solve's system goes before the plain one is built: memory)
                system = systems.system(material)
                robust_info["kept"] = False
                robust_info.update(robust_counts(np.where(counted, 1.0, 0.0), counted, bound, clipped, values, relit,
                                                 usable))
                progress.note(f"robust pass not kept: the plain relit error would rise from {100 * before:.2f} % to "
                              f"{100 * after:.2f} % (> {100 * ROBUST_ACCEPT:g} %): the pixels it down-weighted carry "
                              "the light (a texture or highlight the model cannot follow), not spoil it")
                robust_weights = None
            else:
                robust_info["kept"] = True
    result.solution, result.context = sol, system
    observability, unobservable = ls.observability(system)
    versus = versus_photo(relit, values, usable)
    robust_report = robust_summary(options, robust_info, saturated)
    if robust_info is not None:
        versus["relative_rmse_robust_weighted"] = robust_report["relative_rmse_robust_weighted"]
        progress.note(robust_report["line"])
    warnings = ls.diagnose(system, sol, vis.cube, versus["relative_rmse_vs_photo"])
    n_range = rf.SHININESS_RANGE
    if material.model == PLASTIC:
        a_range = rf.lobe_range(PLASTIC)
        if material.specular and not a_range[0] * 1.001 < material.roughness < a_range[1] * 0.999:
            warnings.append(f"the roughness alpha = {material.roughness:g} is at the end of its range {a_range}: "
                            "the highlight is not resolved (try a larger R, or --reflectance lambert)")
    elif material.specular and not n_range[0] * 1.001 < material.shininess < n_range[1] * 0.999:
        warnings.append(f"the shininess n = {material.shininess:g} is at the end of its range {n_range}: "
                        "the highlight is not resolved (try a larger R, or --reflectance lambert)")
    bright = brightest(sol.light, vis.cube)
    note = narrow_lobe_note(material, bright, vis.cube.resolution)
    if note:
        warnings.append(note)
    n_unobs = int(unobservable.sum())
    if n_unobs:
        progress.note(f"{n_unobs} of {vis.cube.n_texels} light directions are unobservable (no pixel the "
                      "light is fitted to sees them): they stay at zero, drawn magenta")
    if sol.details.get("min_radiance", 0.0) < 0:
        progress.note(f"warning: the {sol.basis} light goes negative (min {sol.details['min_radiance']:.4g}, "
                      f"{100 * sol.details['negative_fraction']:.0f} % of the texels): it is kept as solved; "
                      "tools that clip it get a different light (use --sh-nonnegative for a physical one)")
    n = len(observability)
    report = {
        "basis": sol.basis,
        "route": "exact" if options.exact else "sampled",
        "material": material.to_json(), "scale_ambiguity": SCALE_NOTE,
        "pixels": pixel_counts(usable, held, options.bounds),
        "sample": systems.sample_info,
        "robust": robust_report,
        "exact_directions": {"texels": recast.tolist(), **({"changed": changed} if changed else {}),
                             "note": "directions that carry much of the light, cast for every pixel"
                                     + ("; changed: the used pixels whose visibility toward them the cast corrected, "
                                        "and how many of them are fitted or held-out rows (summed over the casts)" if changed else "")},
        "normal_equations_seconds": getattr(system, "seconds", 0.0),
        "observability": {"texels": n, "unobservable": n_unobs, "unobservable_fraction": n_unobs / max(n, 1),
                          "weakly_observed": int(((observability < 1e-3) & ~unobservable).sum()),
                          "note": "observability = sqrt(G_ii / max G_ii): how strongly the used pixels respond to a "
                                  "texel's radiance; unobservable texels (0) get no light"},
        "relit": versus,
        "warnings": warnings,
        "brightest_direction": bright,
        "solution": sol.summary(),
        "seconds": time.monotonic() - t0,
    }
    return SolveResult(material, sol, result, system, systems.vis, relit, versus, observability, unobservable,
                       warnings, report, albedo, robust_weights)
