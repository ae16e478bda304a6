"""Transport rows changed in place (`light.rows`): the systems already projected are corrected by the
rows' change, and the result is the system projected afresh.

After the light is solved, `solve` casts the directions that carry it exactly for every pixel (the
adaptive visibility inferred them from neighbours) and explores the levels again on the corrected
system. Only the few rows whose visibility changed are rebuilt (`TransportRows.update`), and every
tree system the exploration memoised is corrected by them (`RowsPart.correct`), so the second
exploration needs no pass over the rows. These tests hold that shortcut to the long way round.
"""

import numpy as np
import pytest

from pipelines.controllers.solve import SolveOptions, _Systems, bright_texels, prepare_photo
from pipelines.light import bases
from pipelines.light.cubemap import CubeMap
from pipelines.light.haar import HaarTree, subdivide
from pipelines.light import rows as rows_module
from pipelines.light.rows import TransportRows
from pipelines.geometry.visibility import VisibilityData, compute_visibility
from pipelines.io import images
from pipelines.model.materials import Material


def _trees(cube):
    """Three nested trees: the roots, every root split, and one tile split once more."""
    roots = HaarTree.roots(cube.tile_sizes)
    one = subdivide(roots, np.ones(roots.n_leaves, bool))
    grow = np.zeros(one.n_leaves, bool)
    grow[:4] = True
    return [roots, one, subdivide(one, grow)]


def _small_vis(mitsuba_scene, resolution=8, step=7):
    scene = mitsuba_scene("bunny_sun")
    samples = type(scene.samples)(**{f: getattr(scene.samples, f)[::step] for f in
                                     ("pixel", "position", "normal", "geometric_normal", "view", "face")})
    cube = CubeMap(resolution)
    return scene, compute_visibility(scene.backend, samples, cube)


def _assert_same_system(a, b, rtol):
    scale = max(float(np.abs(b.G).max()), 1e-300)
    assert np.abs(a.G - b.G).max() <= rtol * scale
    assert np.abs(a.h - b.h).max() <= rtol * max(float(np.abs(b.h).max()), 1e-300)
    np.testing.assert_allclose(a.bb, b.bb, rtol=1e-12)


def _memoised_parts(mitsuba_scene, material, albedo_kind: str, seed: int, unweighted=()):
    """600 random rows of a small bunny_sun with random photo values, weights (0 at `unweighted`) and
    albedo of `albedo_kind` ("parts-joint": a glossy system kept for its part factors, not per part),
    their part and its float32 head of 256 rows with the three `_trees` projected (memoised).
    Returns (vis, rng, rows, photo, weights, albedo, grouped, trees, transport rows, part, head)."""
    _, vis = _small_vis(mitsuba_scene)
    rng = np.random.default_rng(seed)
    rows = rng.permutation(vis.n_pixels)[:600]
    photo = rng.uniform(0.1, 1.0, (len(rows), 3))
    weights = rng.uniform(0.5, 2.0, len(rows))
    weights[list(unweighted)] = 0.0
    albedo = None if albedo_kind == "uniform" else rng.uniform(0.3, 1.2, (len(rows), 3))
    grouped = {}
    if albedo_kind == "parts":
        grouped = {"group": rng.integers(0, 3, len(rows)), "scales": rng.uniform(0.5, 2.0, (3, 3))}
    elif albedo_kind == "parts-joint":
        grouped = {"group": rng.integers(0, 3, len(rows)), "scales": rng.uniform(0.5, 2.0, (3, 3)),
                   "split_specular": False}
    trees = _trees(vis.cube)
    tr = TransportRows(vis, rows)
    fit = tr.part(material, photo, weights, 5000, albedo=albedo, **grouped)
    head = fit.head(256, "single")
    for t in trees:
        fit.project_tree(t), head.project_tree(t)
    return vis, rng, rows, photo, weights, albedo, grouped, trees, tr, fit, head


@pytest.mark.parametrize("material", [
    Material(kd=(0.8, 0.5, 0.3)),
    Material(kd=(0.6, 0.6, 0.6), ks=(0.3, 0.3, 0.3), shininess=40.0, model="blinn-phong"),
    Material(kd=(0.5, 0.4, 0.3), ks=(1.0, 1.0, 1.0), model="plastic", roughness=0.2),
], ids=["lambert", "blinn-phong", "plastic"])
@pytest.mark.parametrize("albedo_kind", ["uniform", "per-row", "parts"])
def test_corrected_tree_systems_equal_systems_projected_afresh(mitsuba_scene, material, albedo_kind):
    vis, rng, rows, photo, weights, albedo, grouped, trees, tr, fit, head = _memoised_parts(
        mitsuba_scene, material, albedo_kind, 3)
    untouched = tr.part(material, photo, weights, 5000, albedo=albedo, **grouped)  # memoises, is not corrected
    untouched.project_tree(trees[1])

    # new visibility for a few rows, some inside the head and some beyond it
    local = np.array([3, 70, 255, 256, 400, 599])
    new = np.asarray(tr.vis.stored)[local].copy()
    new ^= rng.integers(0, 256, new.shape, dtype=np.uint8)
    stored = np.asarray(vis.stored).copy()
    stored[rows[local]] = new
    before = [(p, local[local < p.n_rows], p.D.rows[local[local < p.n_rows]].copy(),
               None if p.S is None else p.S.rows[local[local < p.n_rows]].copy(), p._versions()) for p in (fit, head)]
    tr.update(new, local)
    for p, mine, old_D, old_S, versions in before:
        p.correct(mine, old_D, old_S, versions)

    fresh_tr = TransportRows(VisibilityData(vis.samples, vis.cube, vis.supersample, stored), rows)
    fresh = fresh_tr.part(material, photo, weights, 5000, albedo=albedo, **grouped)
    fresh_head = fresh.head(256, "single")
    np.testing.assert_array_equal(fit.D.rows, fresh.D.rows)
    for t in trees:
        assert fit.memo[fit._tree_key(t)][0] == fit._versions()  # corrected, not dropped
        _assert_same_system(fit.project_tree(t), fresh.project_tree(t), 1e-9)
        _assert_same_system(head.project_tree(t), fresh_head.project_tree(t), 1e-5)  # float32 sums
    # a part that was not corrected does not use its stale system
    _assert_same_system(untouched.project_tree(trees[1]), fresh.project_tree(trees[1]), 1e-9)
    kept = untouched._combined(untouched.memo[untouched._tree_key(trees[1])][1])
    assert np.abs(kept.G - fresh.project_tree(trees[1]).G).max() == 0.0  # projected again, not corrected


@pytest.mark.parametrize("material", [
    Material(kd=(0.8, 0.5, 0.3)),
    Material(kd=(0.6, 0.6, 0.6), ks=(0.3, 0.3, 0.3), shininess=40.0, model="blinn-phong"),
    Material(kd=(0.5, 0.4, 0.3), ks=(1.0, 1.0, 1.0), model="plastic", roughness=0.2),
], ids=["lambert", "blinn-phong", "plastic"])
@pytest.mark.parametrize("albedo_kind", ["uniform", "per-row", "parts", "parts-joint"])
def test_systems_taken_over_under_new_weights_equal_systems_projected_afresh(mitsuba_scene, material, albedo_kind):
    """The robust pass gives a few rows other weights (and a clipped pixel's row another target): the
    systems memoised under the old ones, taken over (`RowsPart.adopt`), are the systems of the new
    weights projected afresh; a head's, whose weights all scale with the changed ones, too. Parts
    "joint": a glossy system kept for its part factors (not per part), whose memo also holds a
    system of other factors (`with_scales`): that one is not taken over, and the copy that
    shares the memo keeps its systems as they were."""
    # (rows 10 and 500 without weight before: a clipped pixel's bound, not yet fitted)
    vis, rng, rows, photo, weights, albedo, grouped, trees, tr, fit, head = _memoised_parts(
        mitsuba_scene, material, albedo_kind, 5, unweighted=(10, 500))
    sibling = None
    if albedo_kind == "parts-joint":  # (other factors, the memo shared; Lambert's systems are per part)
        sibling = fit.with_scales(rng.uniform(0.5, 2.0, (3, 3)))
        kept = {t.subdivided: sibling.project_tree(t) for t in trees}
        assert sibling.memo is fit.memo and len(fit.memo) == (3 if fit._per_group else 6)

    new_w, new_photo = weights.copy(), photo.copy()
    down = np.array([3, 70, 255, 256, 400, 599])  # inside the head and beyond it
    new_w[down] *= np.array([0.0, 0.3, 0.0, 0.5, 0.0, 0.9])
    new_w[[10, 500]] = 1.0
    new_photo[[10, 77]] *= 1.3  # (a bound's target moves with the prediction)
    fit2 = tr.part(material, new_photo, new_w, 5000, albedo=albedo, **grouped)
    head2 = fit2.head(256, "single")
    assert fit2.adopt(fit) == 9 and not fit.memo  # 6 down, 2 given weight, 77 moved
    assert head2.adopt(head) == 5  # 3, 10, 70, 77, 255: the rest of the head only rescaled
    fresh = tr.part(material, new_photo, new_w, 5000, albedo=albedo, **grouped)
    fresh_head = fresh.head(256, "single")
    for t in trees:
        assert fit2._tree_key(t) in fit2.memo and head2._tree_key(t) in head2.memo  # taken over
        _assert_same_system(fit2.project_tree(t), fresh.project_tree(t), 1e-9)
        _assert_same_system(head2.project_tree(t), fresh_head.project_tree(t), 2e-6)  # float32 sums
        if fit2._per_group:  # every piece, bb included
            for q, e in fit2._tree_entry(t).items():
                for name, v in e.items():
                    ref = fresh._tree_entry(t)[q][name]
                    if v is not None:
                        assert np.abs(v - ref).max() <= 1e-9 * max(float(np.abs(ref).max()), 1e-300), name
    if sibling is not None:  # (its systems, of other factors, are neither taken over nor changed)
        assert len(fit2.memo) == 3
        for t in trees:
            got = sibling._combined(sibling.memo[sibling._tree_key(t)][1])
            np.testing.assert_array_equal(got.G, kept[t.subdivided].G)
    # nothing taken over: another material, or so many rows changed that projecting afresh is cheaper
    other = tr.part(Material(kd=(0.3, 0.3, 0.3)), new_photo, new_w, 5000, albedo=albedo, **grouped)
    assert other.adopt(fit2) is None and fit2.memo
    many = weights.copy()
    many[: len(rows) // 3] *= 0.5
    assert tr.part(material, photo, many, 5000, albedo=albedo, **grouped).adopt(fit2) is None


def _sun_with_wrong_bits(mitsuba_scene, n_wrong: int, seed: int):
    """bunny_sun at R = 16 (every 3rd pixel), its sun's texels (`bright_texels` of a first light), and
    its visibility with the bit toward the sun flipped in `n_wrong` random pixels that face it (what
    the adaptive inference can get wrong). Returns (scene, vis, texels, (values, usable, held,
    options), the corrupted VisibilityData)."""
    scene, vis = _small_vis(mitsuba_scene, resolution=16, step=3)
    photo = images.read_image(scene.path / "image.exr")
    options = SolveOptions()
    values, usable, held = prepare_photo(vis, photo, options)
    light = bases.solve(_Systems(vis, values, usable, held, options, _quiet()).system(Material()), vis.cube).light
    texels = bright_texels(light, vis.cube)
    assert 1 <= len(texels) <= 8  # the sun
    stored = np.asarray(vis.stored).copy()
    wrong = np.random.default_rng(seed).choice(vis.n_pixels, n_wrong, replace=False)
    for t in texels:
        can = (vis.samples.normal[wrong] @ vis.cube.directions[t]) > 0.05
        stored[wrong[can], t >> 3] ^= np.uint8(1 << (t & 7))
    corrupt = VisibilityData(vis.samples, vis.cube, vis.supersample, stored)
    return scene, vis, texels, (values, usable, held, options), corrupt


@pytest.mark.parametrize("grown", [False, True], ids=["afresh", "grown"])
@pytest.mark.parametrize("mode", ["system corrected", "rows updated"])
def test_recast_in_place_gives_the_light_of_a_system_built_anew(mitsuba_scene, mode, grown, monkeypatch):
    """bunny_sun's sun, with wrong visibility bits toward it in some fitted and held-out rows (what
    the adaptive inference can get wrong): casting the bright directions again and exploring the
    levels on the system corrected in place ("system corrected"), or on a system built after the
    kept transport rows were updated in place ("rows updated": the controller's cast before a
    glossy model's refinement), gives the light, levels and errors of a system built from scratch
    on the corrected visibility: every level, when each tree's system is projected afresh. Grown
    from the level before (`RowsPart._grown`, the default) the two routes add the same float32 sums
    in other orders, and a refinement on the edge of its threshold can go either way: then the
    light, the chosen level and the levels up to it are the same (their errors to the float32 sums'
    rounding), and a later level may refine a few leaves differently."""
    if not grown:
        monkeypatch.setattr(rows_module, "GROWN_SHARE", 0.0)
    scene, vis, texels, (values, usable, held, options), corrupt = _sun_with_wrong_bits(mitsuba_scene, 400, 0)
    systems = _Systems(corrupt, values, usable, held, options, _quiet())
    system = systems.system(Material())
    first = bases.solve(system, vis.cube)
    kept_D = systems.fit_rows.diffuse().rows
    changed = systems.recast(scene.backend, texels, system if mode == "system corrected" else None)
    if mode == "rows updated":
        system = systems.system(Material())
        assert systems.fit_rows.diffuse().rows is kept_D  # updated in place, not rebuilt
    a = bases.solve(system, vis.cube)
    b = bases.solve(_Systems(systems.vis, values, usable, held, options, _quiet()).system(Material()), vis.cube)
    assert changed["fit_rows"] > 20 and changed["held_out_rows"] > 2
    assert first.held_out_rmse > 1.01 * b.held_out_rmse  # the wrong bits mattered
    # (the final solve takes the exploration head's memoised system of its tree, corrected in place on
    # one side, grown from the level before on the other: float32 sums in other orders, which the NNLS
    # passes on to the light at ~1e-4 of its peak; its errors agree to ~1e-6)
    np.testing.assert_allclose(a.light, b.light, rtol=1e-6, atol=(2e-3 if grown else 1e-9) * float(np.abs(b.light).max()))
    assert a.fit_rmse == pytest.approx(b.fit_rmse, rel=1e-5) and a.held_out_rmse == pytest.approx(b.held_out_rmse, rel=1e-5)
    assert a.chosen == b.chosen
    upto = None if not grown else a.chosen + 1
    assert [lv.n_coefficients for lv in a.levels[:upto]] == [lv.n_coefficients for lv in b.levels[:upto]]
    np.testing.assert_allclose([lv.held_out_rmse for lv in a.levels[:upto]],
                               [lv.held_out_rmse for lv in b.levels[:upto]], rtol=1e-5 if grown else 1e-6)
    if mode == "system corrected":  # the second exploration reused the first one's tree systems, corrected
        assert len(system.explore.memo) >= len(first.levels) - 1


def test_replaying_the_levels_on_a_corrected_system_needs_no_pass_over_the_rows(mitsuba_scene, monkeypatch):
    """After the recast corrects the system in place, `bases.replay` solves the first light's levels
    again along its trees: no tree is projected again (the memo holds the large ones: the smallest
    go first), every level's errors are the corrected system's, and the light is as good as a fresh
    exploration's on a system built from scratch (held-out error within 1 %)."""
    from pipelines.light import rows as rows_module

    scene, vis, texels, (values, usable, held, options), corrupt = _sun_with_wrong_bits(mitsuba_scene, 400, 0)
    monkeypatch.setattr(rows_module, "MEMO_TREES", 3)  # fewer than the levels (R = 16 has few)
    systems = _Systems(corrupt, values, usable, held, options, _quiet())
    system = systems.system(Material())
    first = bases.solve(system, vis.cube)
    assert len(first.levels) > 3
    systems.recast(scene.backend, texels, system)
    passes = []
    original = rows_module.Pyramid.leaf_sums
    monkeypatch.setattr(rows_module.Pyramid, "leaf_sums", lambda self, tree, *rows: passes.append(tree) or original(self, tree, *rows))
    again = bases.replay(system, vis.cube, first)
    monkeypatch.setattr(rows_module.Pyramid, "leaf_sums", original)
    fresh = bases.solve(_Systems(systems.vis, values, usable, held, options, _quiet()).system(Material()), vis.cube)
    trees = [lv.tree.subdivided for lv in first.levels]
    assert [lv.tree.subdivided for lv in again.levels] == trees[:len(again.levels)]
    # only the trees no memo kept are projected: the explore memo keeps the largest of the first's levels
    # (the small first levels are cheap), and the final all-pixel solve reuses its tree's if it is the same
    big = sorted(lv.tree.n_leaves for lv in first.levels)[-3:]
    assert not any(t.n_leaves in big for t in passes if t.subdivided != again.tree.subdivided)
    assert first.held_out_rmse > 1.01 * fresh.held_out_rmse  # the wrong bits mattered
    assert again.held_out_rmse <= 1.01 * fresh.held_out_rmse
    corrected = systems.system(Material())  # the held-out error of each replayed level is the corrected system's
    for lv in again.levels:
        assert lv.held_out_rmse == pytest.approx(corrected.held_out.relative_rmse(lv.light), rel=1e-6)


def test_an_intermediate_light_finished_is_the_all_pixel_solve(mitsuba_scene):
    """`solve(all_pixels=False)` keeps the chosen level's light as the exploration fitted it (the
    controller's intermediate lights: a reflectance round re-solves them, a bright-direction cast
    solves them again); `finish` re-solves it on every pixel of its system: the light `solve` gives
    at once, no worse over all pixels, its levels and held-out errors unchanged."""
    vis, system = _bunny_system(mitsuba_scene)
    lazy = bases.solve(system, vis.cube, all_pixels=False)
    full = bases.solve(system, vis.cube)
    assert not lazy.details["all_pixels"] and full.details["all_pixels"]
    np.testing.assert_array_equal(lazy.light, lazy.levels[lazy.chosen].light)
    done = bases.finish(system, vis.cube, lazy)
    assert done.details["all_pixels"] and bases.finish(system, vis.cube, done) is done
    scale = float(np.abs(full.light).max())
    assert float(np.abs(done.light - lazy.light).max()) > 1e-4 * scale  # the re-solve changed it
    np.testing.assert_allclose(done.light, full.light, rtol=1e-6, atol=1e-9 * scale)
    both = system.fit.combine(system.held_out)
    assert both.relative_rmse(done.light) <= both.relative_rmse(lazy.light) + 1e-9
    assert done.fit_rmse == pytest.approx(both.relative_rmse(done.light), rel=1e-9)
    assert done.held_out_rmse == lazy.held_out_rmse and done.chosen == lazy.chosen


def test_the_final_light_solved_in_single_precision_fits_as_the_double_ones(mitsuba_scene, monkeypatch):
    """`finish` projects the chosen tree of the sampled rows in float32 (half the time of float64):
    the light it solves explains every row of the system as the light of the float64 system does
    (the reference), its residuals measured on the rows."""
    from pipelines.light import haar
    from pipelines.light.rows import RowsPart
    from pipelines.light.solution import solve_nonnegative

    seen = []
    system_of = RowsPart._system
    monkeypatch.setattr(RowsPart, "_system", lambda self, *a, **k: seen.append(self.precision) or system_of(
        self, *a, **k))

    vis, system = _bunny_system(mitsuba_scene)
    lazy = bases.solve(system, vis.cube, all_pixels=False)
    seen.clear()
    done = bases.finish(system, vis.cube, lazy)
    assert seen and set(seen) == {"single"}  # (the fit and held-out rows, projected in float32)
    both = system.fit.combine(system.held_out)
    assert {p.precision for p in both.parts} == {"double"}
    assert {p.precision for p in both.in_single().parts} == {"single"}
    P = haar.leaf_matrix(done.tree)
    x, _ = solve_nonnegative(both.project_tree(done.tree))  # (the parts' own precision: float64)
    ref = np.asarray(P @ x)
    ref[done.unobservable] = 0.0
    e_single, e_double = both.relative_rmse(done.light), both.relative_rmse(ref)
    assert e_double > 0.005  # (a photo with noise: the test is not on an exact fit)
    assert e_single <= e_double * (1.0 + 1e-4)
    relit = np.concatenate([p.predict(done.light) for p in both.parts])
    relit_ref = np.concatenate([p.predict(ref) for p in both.parts])
    assert np.abs(relit - relit_ref).max() <= 2e-3 * np.abs(relit_ref).max()


def test_the_final_solve_takes_the_explored_heads_systems_from_its_memo(mitsuba_scene, monkeypatch):
    """`rows.all_rows` (what `finish` solves on): the exploration's head stands for its own rows again
    (its weights divided by the head's factor) and its memoised tree system is reused, so only the
    other fit rows and the held-out ones are projected; the system is the one of every row projected
    afresh in float32, to the float32 sums' rounding. A head of other weights is not taken."""
    from dataclasses import replace

    from pipelines.light.rows import ScaledPart, all_rows

    vis, system = _bunny_system(mitsuba_scene)
    lazy = bases.solve(system, vis.cube, all_pixels=False)
    fit, held, explore = system.fit, system.held_out, system.explore
    assert 0 < explore.n_rows < fit.n_rows
    both = all_rows(fit, held, explore)
    assert isinstance(both.parts[0], ScaledPart) and [p.n_rows for p in both.parts[1:]] == [
        fit.n_rows - explore.n_rows, held.n_rows]
    projected = []
    original = rows_module.Pyramid.leaf_sums
    monkeypatch.setattr(rows_module.Pyramid, "leaf_sums",
                        lambda self, tree, *a: projected.append(len(self.rows)) or original(self, tree, *a))
    got = both.project_tree(lazy.tree)
    assert set(projected) == {fit.n_rows - explore.n_rows, held.n_rows}  # (the head's rows: none)
    monkeypatch.setattr(rows_module.Pyramid, "leaf_sums", original)
    ref = fit.combine(held).in_single().project_tree(lazy.tree)
    assert np.abs(got.G - ref.G).max() <= 1e-5 * np.abs(ref.G).max()
    assert np.abs(got.h - ref.h).max() <= 1e-5 * np.abs(ref.h).max()
    np.testing.assert_allclose(got.bb, ref.bb, rtol=1e-9)
    np.testing.assert_allclose(both.relative_rmse(lazy.light), fit.combine(held).relative_rmse(lazy.light), rtol=1e-6)
    other = replace(explore, w=explore.w * np.linspace(0.5, 1.5, explore.n_rows), memo=explore.memo)
    assert not any(isinstance(p, ScaledPart) for p in all_rows(fit, held, other).parts)
    assert not any(isinstance(p, ScaledPart) for p in all_rows(fit, held, None).parts)


def test_leaf_sums_in_leaf_order_are_the_tree_orders_reordered(mitsuba_scene):
    """`Pyramid.leaf_sums(grouped=True)` (one gather per level and tile) holds the tree-order sums'
    columns in `leaf_order`; both are the rows summed over each leaf, and a tree system projected
    from them is the one of the rows' leaf sums in tree order."""
    from pipelines.light import haar
    from pipelines.light.rows import Pyramid, RowsPart, _gram, leaf_order

    _, vis = _small_vis(mitsuba_scene, resolution=16)
    rng = np.random.default_rng(5)
    rows = rng.permutation(vis.n_pixels)[:500]
    D = TransportRows(vis, rows).diffuse()
    roots = HaarTree.roots(vis.cube.tile_sizes)
    deep = subdivide(roots, np.ones(roots.n_leaves, bool))
    for _ in range(2):  # leaves at three levels, in every tile
        deep = subdivide(deep, rng.random(deep.n_leaves) < 0.4)
    for tree in _trees(vis.cube) + [deep]:
        A = D.leaf_sums(tree)
        np.testing.assert_allclose(A, D.rows @ haar.leaf_matrix(tree).toarray(), rtol=1e-5, atol=1e-6 * A.max())
        np.testing.assert_array_equal(D.leaf_sums(tree, grouped=True), A[:, leaf_order(tree)])
        np.testing.assert_array_equal(D.leaf_sums(tree, slice(100, 300), grouped=True),
                                      A[100:300][:, leaf_order(tree)])
        w = rng.uniform(0.5, 2.0, len(rows))
        b = rng.uniform(0, 1, (len(rows), 3))
        part = RowsPart(D, None, np.array([0.8, 0.6, 0.4]), np.zeros(3), b, w, len(rows))
        got = part.project_tree(tree)
        ref = _gram(A.astype(np.float64) * np.sqrt(w)[:, None] * 0.8)
        np.testing.assert_allclose(got.G, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
        np.testing.assert_allclose(got.h[:, 0], 0.8 * A.astype(np.float64).T @ (w * b[:, 0]), rtol=1e-6)
        # a glossy material's rows grouped by part (the pieces of each part, put in tree order) give
        # the system of the dense projection through the leaf matrix
        S = Pyramid(np.ascontiguousarray(D.rows[:, ::-1]), vis.cube.tile_sizes)
        grouped = RowsPart(D, S, np.array([0.8, 0.6, 0.4]), np.array([0.3, 0.2, 0.1]), b, w, len(rows),
                           group=rng.integers(0, 2, len(rows)), group_scales=np.array([[1.0] * 3, [0.5, 0.7, 0.9]]))
        dense = grouped.project(haar.leaf_matrix(tree))
        tree_sys = grouped.project_tree(tree)
        np.testing.assert_allclose(tree_sys.G, dense.G, rtol=1e-5, atol=1e-6 * np.abs(dense.G).max())
        np.testing.assert_allclose(tree_sys.h, dense.h, rtol=1e-5, atol=1e-6 * np.abs(dense.h).max())


def _bunny_system(mitsuba_scene):
    """(visibility, the sampled Lambertian system) of a third of bunny_sun's pixels at R = 16."""
    scene, vis = _small_vis(mitsuba_scene, resolution=16, step=3)
    photo = images.read_image(scene.path / "image.exr")
    options = SolveOptions()
    values, usable, held = prepare_photo(vis, photo, options)
    return vis, _Systems(vis, values, usable, held, options, _quiet()).system(Material())


def _quiet():
    from pipelines.controllers.solve import Progress

    return Progress()


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("material", [
    Material(kd=(0.9, 0.7, 0.5)),
    Material(kd=(0.9, 0.7, 0.5), ks=(0.4, 0.3, 0.2), shininess=30.0, model="blinn-phong"),
], ids=["lambert", "blinn-phong"])
def test_part_factors_change_without_a_pass_over_the_rows(mitsuba_scene, precision, material):
    """Rows of several parts keep each part's tree system at factor 1 (with a specular term, its
    diffuse, cross and specular pieces): the system under any factors is the one of rows whose kd
    has those factors applied, and `with_scales` serves it from the kept pieces (the rows' leaf
    sums are not formed again); a uniform part's pieces (one Gram matrix) equal a textured one's."""
    from pipelines.light import rows as rows_module

    _, vis = _small_vis(mitsuba_scene)
    rng = np.random.default_rng(5)
    rows = rng.permutation(vis.n_pixels)[:500]
    photo = rng.uniform(0.1, 1.0, (len(rows), 3))
    weights = rng.uniform(0.5, 2.0, len(rows))
    base = rng.uniform(0.3, 1.2, (len(rows), 3))
    group = rng.integers(0, 3, len(rows))
    base[group == 0] = (0.8, 0.5, 0.3)  # part 0 uniform (one Gram matrix for its channels), 1 and 2 textured
    s1, s2 = rng.uniform(0.5, 2.0, (3, 3)), rng.uniform(0.5, 2.0, (3, 3))
    tr = TransportRows(vis, rows)
    grouped = tr.part(material, photo, weights, 5000, albedo=base, group=group, scales=s1)
    grouped = grouped if precision == "double" else grouped.head(len(rows), "single")
    trees = _trees(vis.cube)
    for t in trees:
        grouped.project_tree(t)
    rtol = 1e-9 if precision == "double" else 2e-5

    calls = []
    original = rows_module.Pyramid.leaf_sums
    try:
        rows_module.Pyramid.leaf_sums = lambda self, tree: calls.append(tree) or original(self, tree)
        moved = grouped.with_scales(s2)
        got = [moved.project_tree(t) for t in trees]
    finally:
        rows_module.Pyramid.leaf_sums = original
    assert calls == []
    for s, systems in ((s2, got), (s1, [grouped.project_tree(t) for t in trees])):
        plain = tr.part(material, photo, weights, 5000, albedo=base * s[group])
        plain = plain if precision == "double" else plain.head(len(rows), "single")
        for t, g in zip(trees, systems):
            _assert_same_system(g, plain.project_tree(t), rtol)
        np.testing.assert_allclose(moved.predict(np.ones((vis.cube.n_texels, 3))) if s is s2 else
                                   grouped.predict(np.ones((vis.cube.n_texels, 3))),
                                   plain.predict(np.ones((vis.cube.n_texels, 3))), rtol=1e-6)
    if not material.specular:
        return
    # each part's own specular weight (`group_ks`) from the same kept pieces: the system of rows whose
    # lobe is scaled by their part's weight (the transport rows built so, `set_specular`: the float32
    # rows scaled, hence 1e-6)
    g = np.array([0.3, 1.0, 2.5])
    rtol = max(rtol, 1e-6)
    with_ks = grouped.with_scales(s2, g)
    light = rng.uniform(0.0, 1.0, (vis.cube.n_texels, 3))
    scaled = TransportRows(vis, rows)
    scaled.set_specular(g[group])
    plain = scaled.part(material, photo, weights, 5000, albedo=base * s2[group])
    plain = plain if precision == "double" else plain.head(len(rows), "single")
    for t in trees:
        _assert_same_system(with_ks.project_tree(t), plain.project_tree(t), rtol)
    np.testing.assert_allclose(with_ks.predict(light), plain.predict(light), rtol=1e-5)
    np.testing.assert_allclose(with_ks.gradient(light), plain.gradient(light), rtol=1e-4, atol=1e-6)
    # and a system whose rows carry the weights per row (not kept per part) agrees as well
    per_row = tr.part(material, photo, weights, 5000, albedo=base, group=group, scales=s2, split_specular=False,
                      ks_scales=g)
    per_row = per_row if precision == "double" else per_row.head(len(rows), "single")
    for t in trees:
        _assert_same_system(per_row.project_tree(t), plain.project_tree(t), rtol)
    assert not np.allclose(with_ks.project_tree(trees[-1]).h, grouped.with_scales(s2).project_tree(trees[-1]).h)


@pytest.mark.parametrize("material", [
    Material(kd=(0.6, 0.6, 0.6), ks=(0.3, 0.3, 0.3), shininess=40.0, model="blinn-phong"),
    Material(kd=(0.5, 0.4, 0.3), ks=(1.0, 1.0, 1.0), model="plastic", roughness=0.2),
], ids=["blinn-phong", "plastic"])
def test_a_rounds_system_builds_the_transport_of_its_head_rows_alone(mitsuba_scene, material):
    """A specular round's smaller system (`n_rows`) builds its lobe's S, and a plastic's D seen through
    the coating, for those rows only (memory and time per round): the same numbers as the head of
    the whole rows' transport, and a later request for every row builds them all."""
    _, vis = _small_vis(mitsuba_scene)
    rng = np.random.default_rng(5)
    rows = rng.permutation(vis.n_pixels)[:600]
    photo = rng.uniform(0.1, 1.0, (len(rows), 3))
    weights = np.ones(len(rows))
    tr = TransportRows(vis, rows)
    small = tr.part(material, photo, weights, len(rows), n_rows=200)
    assert len(small.S.rows) == 200
    plastic = material.model == "plastic"
    if plastic:
        assert len(tr._coated[1].rows) == 200  # the coated D of the head alone
    assert len(tr.diffuse().rows) == 600  # the Lambertian D is kept for every row
    whole = TransportRows(vis, rows).part(material, photo, weights, len(rows))
    np.testing.assert_array_equal(small.S.rows, whole.S.rows[:200])
    np.testing.assert_array_equal(small.D.rows, whole.D.rows[:200])
    full = tr.part(material, photo, weights, len(rows))  # every row: built anew, no head served
    assert len(full.S.rows) == 600 and len(full.D.rows) == 600
    np.testing.assert_array_equal(full.D.rows, whole.D.rows)
    if plastic:  # the coated D differs from the Lambertian one (the test sees the coated one)
        assert not np.allclose(full.D.rows, tr.diffuse().rows)


def test_keeping_only_the_chosen_models_transport_drops_the_others_and_rebuilds_on_demand(mitsuba_scene):
    """Once `auto` has chosen, the other candidates' kept transports go (`TransportRows.keep_only`):
    the chosen model's stay the same arrays, the others' are gone, and a later request builds
    them again with the same numbers."""
    _, vis = _small_vis(mitsuba_scene)
    rng = np.random.default_rng(7)
    rows = rng.permutation(vis.n_pixels)[:400]
    photo = rng.uniform(0.1, 1.0, (len(rows), 3))
    weights = np.ones(len(rows))
    phong = Material(kd=(0.6, 0.6, 0.6), ks=(0.3, 0.3, 0.3), shininess=40.0, model="blinn-phong")
    plastic = Material(kd=(0.5, 0.4, 0.3), ks=(1.0, 1.0, 1.0), model="plastic", roughness=0.2)
    tr = TransportRows(vis, rows)
    lambert_D = tr.part(Material(), photo, weights, len(rows)).D.rows.copy()
    coated = tr.part(plastic, photo, weights, len(rows))
    tr.keep_only(plastic)  # plastic chosen: its coated D and its S stay, the Lambertian D goes
    assert tr._diffuse is None
    again = tr.part(plastic, photo, weights, len(rows))
    assert again.D.rows is coated.D.rows and again.S.rows is coated.S.rows
    np.testing.assert_array_equal(tr.diffuse().rows, lambert_D)  # built again, the same
    chosen = tr.part(phong, photo, weights, len(rows))
    tr.keep_only(phong)  # blinn-phong chosen: the coating and any other lobe go, its S stays
    assert tr._coated is None and tr._diffuse is not None
    assert tr.part(phong, photo, weights, len(rows)).S.rows is chosen.S.rows
    tr.keep_only(Material())  # lambert chosen: no lobe kept
    assert tr._specular == {} and tr.diffuse().rows is chosen.D.rows
    np.testing.assert_array_equal(tr.part(plastic, photo, weights, len(rows)).D.rows, coated.D.rows)


def test_one_materials_transports_are_kept_and_every_held_one_follows_a_recast(mitsuba_scene):
    """auto's candidates in turn (memory): `part` keeps one material's transports, so once a plastic
    system is built the rows hold neither the Lambertian D nor the Phong S. A system built before
    still holds its own (a round's system a head of them), and a recast's new visibility
    (`update`) rebuilds their rows too: each system's transports equal those built afresh on the new
    visibility. Once no system holds them, they are gone."""
    import gc

    _, vis = _small_vis(mitsuba_scene)
    rng = np.random.default_rng(11)
    rows = np.sort(rng.permutation(vis.n_pixels)[:400])
    photo = rng.uniform(0.1, 1.0, (len(rows), 3))
    weights = np.ones(len(rows))
    phong = Material(kd=(0.6, 0.6, 0.6), ks=(0.3, 0.3, 0.3), shininess=40.0, model="blinn-phong")
    plastic = Material(kd=(0.5, 0.4, 0.3), ks=(1.0, 1.0, 1.0), model="plastic", roughness=0.2)
    tr = TransportRows(vis, rows)
    lam = tr.part(Material(), photo, weights, len(rows))
    whole = tr.part(phong, photo, weights, len(rows))
    head = tr.part(phong, photo, weights, len(rows), n_rows=150)  # a round's system: a head of the S
    assert head.S.rows.base is whole.S.rows
    whole = None
    coated = tr.part(plastic, photo, weights, len(rows))
    assert tr._diffuse is None and [k[0] for k in tr._specular] == ["plastic"]
    assert len(tr.pyramids()) == 4  # Lambert's D, Phong's S (held by the head), plastic's D and S
    stored = np.asarray(vis.stored).copy()
    local = np.arange(0, len(rows), 5)
    for t in rng.choice(vis.cube.n_texels, 40, replace=False):
        stored[rows[local], t >> 3] ^= np.uint8(1 << (t & 7))
    held = ((lam, Material(), None), (head, phong, 150), (coated, plastic, None))
    before = [(p.D.rows.copy(), None if p.S is None else p.S.rows.copy()) for p, _, _ in held]
    tr.update(stored[rows[local]], local)
    fresh = TransportRows(VisibilityData(vis.samples, vis.cube, vis.supersample, stored), rows)
    for (system, material, n), (D0, S0) in zip(held, before):
        again = fresh.part(material, photo, weights, len(rows), n_rows=n)
        np.testing.assert_allclose(system.D.rows, again.D.rows, rtol=1e-6, atol=1e-7)
        changed = np.abs(system.D.rows - D0).max()
        if material.specular:
            np.testing.assert_allclose(system.S.rows, again.S.rows, rtol=1e-5, atol=1e-7)
            changed = max(changed, np.abs(system.S.rows - S0).max())
        assert changed > 1e-3 * np.abs(again.D.rows).max()  # (the flips reached every held transport)
    lam = head = held = system = None
    gc.collect()
    assert len(tr.pyramids()) == 2  # plastic's, still kept by the rows


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("material", [
    Material(kd=(0.9, 0.7, 0.5), ks=(0.4, 0.4, 0.4), shininess=30.0, model="blinn-phong"),
    Material(kd=(0.5, 0.4, 0.3), ks=(1.0, 1.0, 1.0), model="plastic", roughness=0.2),
], ids=["blinn-phong", "plastic"])
def test_lobe_pieces_give_the_system_of_any_ks_over_kd(mitsuba_scene, precision, material):
    """`rows.lobe_pieces` (what a round's ks / kd_c search re-solves the light on): channel c's system
    of the same rows under kd_c and ks is kd_c^2 (DD + t (X + X') + t^2 SS), kd_c (hD_c + t hS_c) with
    t = ks / kd_c, for a fit part and for its union with the held-out one; rows that are not of one
    uniform glossy material (a per-row albedo, parts, no lobe) have none."""
    from pipelines.light.rows import lobe_pieces

    _, vis = _small_vis(mitsuba_scene)
    rng = np.random.default_rng(11)
    rows = rng.permutation(vis.n_pixels)[:500]
    photo = rng.uniform(0.1, 1.0, (len(rows), 3))
    weights = rng.uniform(0.5, 2.0, len(rows))
    tr, ta, tb = TransportRows(vis, rows), TransportRows(vis, rows[:300]), TransportRows(vis, rows[300:])
    tree = _trees(vis.cube)[2]
    a = ta.part(material, photo[:300], weights[:300], 5000)
    b = tb.part(material, photo[300:], weights[300:], 2000)
    if precision == "single":
        a = a.head(a.n_rows, "single")
    for part in (a, a.combine(b)):
        pieces = lobe_pieces(part, tree)
        for kd, ks in (((0.9, 0.6, 0.3), 0.5), ((0.2, 0.5, 1.0), 2.0)):
            m = Material(kd=kd, ks=(ks,) * 3, shininess=material.shininess, model=material.model,
                         roughness=material.roughness)
            direct = ta.part(m, photo[:300], weights[:300], 5000)
            direct = direct if precision == "double" else direct.head(direct.n_rows, "single")
            if part is not a:
                direct = direct.combine(tb.part(m, photo[300:], weights[300:], 2000))
            system = direct.project_tree(tree)
            G = [system.gram(c) for c in range(3)]
            for c in range(3):
                t = ks / kd[c]
                want_G = kd[c] ** 2 * (pieces["DD"] + t * (pieces["X"] + pieces["X"].T) + t * t * pieces["SS"])
                want_h = kd[c] * (pieces["hD"][:, c] + t * pieces["hS"][:, c])
                tol = 1e-9 if precision == "double" else 1e-5
                assert np.abs(G[c] - want_G).max() <= tol * np.abs(want_G).max()
                h = np.asarray(system.h)[:, c]
                assert np.abs(h - want_h).max() <= tol * np.abs(want_h).max()
            np.testing.assert_allclose(pieces["bb"], system.bb, rtol=1e-12)
    assert lobe_pieces(tr.part(Material(kd=(0.9, 0.7, 0.5)), photo, weights, 5000), tree) is None
    assert lobe_pieces(tr.part(material, photo, weights, 5000, albedo=rng.uniform(0.5, 1.0, (500, 3))), tree) is None
    assert lobe_pieces(tr.part(material, photo, weights, 5000, albedo=np.ones((500, 3)),
                               group=rng.integers(0, 2, 500), scales=np.ones((2, 3))), tree) is None


@pytest.mark.parametrize("n", [1, 7, 256, 300, 600])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_gram_matrices_are_the_products_of_the_rows(n, dtype):
    """`_gram` (syrk's upper triangle mirrored block by block, `_symmetric`) is A'A, symmetric to the
    bit, over block edges (SYMMETRIC_BLOCK = 256) and in both precisions; a lower triangle that is
    not 0 is ignored."""
    from pipelines.light.rows import _gram, _symmetric

    rng = np.random.default_rng(n)
    A = rng.random((n + 40, n)).astype(dtype)
    G = _gram(A)
    assert G.dtype == np.float64 and np.array_equal(G, G.T)
    ref = A.astype(np.float64).T @ A.astype(np.float64)
    assert np.allclose(G, ref, rtol=1e-5 if dtype == np.float32 else 1e-12)
    upper = np.triu(rng.random((n, n)))
    junk = upper + np.tril(rng.random((n, n)) + 1.0, -1)
    want = upper + np.triu(upper, 1).T
    assert np.array_equal(_symmetric(upper), want) and np.array_equal(_symmetric(junk), want)


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("material, albedo_kind", [
    (Material(kd=(0.8, 0.5, 0.3)), "uniform"),
    (Material(kd=(0.8, 0.5, 0.3)), "per-row"),
    (Material(kd=(0.6, 0.6, 0.6), ks=(0.3, 0.3, 0.3), shininess=40.0, model="blinn-phong"), "uniform"),
    (Material(kd=(0.8, 0.5, 0.3)), "parts"),
    (Material(kd=(0.6, 0.6, 0.6), ks=(0.3, 0.2, 0.1), shininess=40.0, model="blinn-phong"), "parts"),
    (Material(kd=(0.6, 0.6, 0.6), ks=(0.3, 0.2, 0.1), shininess=40.0, model="blinn-phong"), "textured parts"),
], ids=["lambert", "lambert-per-row", "blinn-phong", "lambert-parts", "blinn-phong-parts",
        "blinn-phong-textured-parts"])
def test_a_refined_trees_system_grown_from_the_level_before_is_the_system_projected_afresh(
        mitsuba_scene, monkeypatch, precision, material, albedo_kind):
    """A coarse-to-fine solve refines a few leaves per level: the next tree's system is the memoised
    one's, with only the new leaves' rows and columns projected (`RowsPart._grown`). It is the system
    the rows give when projected afresh, to the rounding of the precision its sums are taken in: over
    several blocks of rows, and for a tree that also drops leaves of the one it grows from (pruned)."""
    monkeypatch.setattr(rows_module, "SYSTEM_BLOCK_VALUES", 2**14)  # (several blocks of rows a system)
    _, vis = _small_vis(mitsuba_scene, resolution=16, step=3)
    rng = np.random.default_rng(11)
    rows = rng.permutation(vis.n_pixels)[:900]
    photo = rng.uniform(0.1, 1.0, (len(rows), 3))
    weights = rng.uniform(0.5, 2.0, len(rows))
    albedo = None if albedo_kind == "uniform" else rng.uniform(0.3, 1.2, (len(rows), 3))
    if albedo_kind == "parts":  # (each part's albedo uniform: one Gram matrix a part)
        group = rng.integers(0, 3, len(rows))
        albedo = np.array([[1.0, 0.9, 0.8], [0.5, 0.5, 0.5], [0.2, 0.6, 1.0]])[group]
    grouped = {} if "parts" not in albedo_kind else {"group": rng.integers(0, 3, len(rows)) if albedo_kind != "parts"
                                                     else group, "scales": rng.uniform(0.5, 2.0, (3, 3))}
    tr = TransportRows(vis, rows)

    def part():
        p = tr.part(material, photo, weights, 5000, albedo=albedo, **grouped)
        return p.in_single() if precision == "single" else p

    grown_part = part()
    tree = subdivide(HaarTree.roots(vis.cube.tile_sizes), np.ones(9, bool))
    tree = subdivide(tree, rng.random(tree.n_leaves) < 0.5)
    grown_part.project_tree(tree)
    base = tree
    taken = 0
    for k in range(4):  # a few leaves refined per level, as `solve_tree` does; then a sibling refinement
        if k < 3:
            tree = subdivide(tree, rng.random(tree.n_leaves) < 0.08)
        else:  # (the last level's tree refined elsewhere: its new leaves go, others come)
            before = set(tree.leaves())
            tree = subdivide(base, rng.random(base.n_leaves) < 0.12)
            assert before - set(tree.leaves()) and set(tree.leaves()) - before
        taken += grown_part._grown(tree, grown_part._tree_key(tree)) is not None
        got = grown_part.project_tree(tree)
        fresh = part()
        afresh = fresh.project_tree(tree)
        assert got.G.shape == afresh.G.shape and got.h.shape == afresh.h.shape
        _assert_same_system(got, afresh, 1e-10 if precision == "double" else 2e-6)
        np.testing.assert_array_equal(got.G, np.swapaxes(got.G, -1, -2))  # symmetric, exactly
        if grown_part._per_group:  # every piece (the lobe's cross term X is not symmetric)
            for q, e in grown_part._tree_entry(tree).items():
                for name, v in e.items():
                    ref = fresh._tree_entry(tree)[q][name]
                    assert (v is None) == (ref is None)
                    if v is not None:
                        scale = max(float(np.abs(ref).max()), 1e-300)
                        assert np.abs(v - ref).max() <= (1e-10 if precision == "double" else 2e-6) * scale, name
    assert taken == 4
