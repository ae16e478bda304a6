"""The solved light's file (`out/coefficients.h5`): its writer and the one reader every command uses."""

from __future__ import annotations

import numpy as np

from ..light.cubemap import CubeMap
from ..light.haar import HaarTree
from .files import h5_file

SOLUTION_FORMAT = "wavelight-light-1"
_KIND_CODES = {"scaling": 0, "h": 1, "v": 2, "d": 3}


def _tree_nodes(tree: HaarTree) -> np.ndarray:
    rows = [(t, *n) for t, nodes in enumerate(tree.subdivided) for n in sorted(nodes)]
    return np.array(rows, dtype=np.int32).reshape(-1, 4)


def _write_tree(group, tree: HaarTree) -> None:
    group.create_dataset("tile_sizes", data=np.array(tree.tile_sizes, dtype=np.int32))
    group.create_dataset("subdivided", data=_tree_nodes(tree))
    index = tree.coefficient_index()
    group.create_dataset("coefficient_index", data=np.array(
        [(t, _KIND_CODES[k], lv, i, j) for t, k, lv, i, j in index], dtype=np.int32).reshape(-1, 5))
    group.create_dataset("leaves", data=np.array(tree.leaves(), dtype=np.int32).reshape(-1, 4))


def read_tree(group) -> HaarTree:
    sizes = [int(s) for s in group["tile_sizes"][:]]
    nodes: list[set] = [set() for _ in sizes]
    for t, lv, i, j in group["subdivided"][:]:
        nodes[int(t)].add((int(lv), int(i), int(j)))
    return HaarTree(tuple(sizes), tuple(frozenset(n) for n in nodes))


def write_solution(path, solution, cube: CubeMap, unobservable: np.ndarray,
                   attrs: dict | None = None) -> None:
    """The solved light as HDF5: texels, coefficients (with the tree), every level, the mask.

    Layout: attrs format/basis/resolution/hemisphere; `light` (N, 3) texel radiance (the output
    light, unobservable texels zero); `coefficients` (k, 3) in the basis' terms (wavelet: Haar
    coefficients of `tree`, orthonormal in the texel inner product, rows in `tree/coefficient_index`
    order (tile, kind 0=scaling 1=h 2=v 3=d, level, i, j); quadtree/discrete: leaf values in
    `tree/leaves` order; sh: real SH coefficients; points: irradiance per light; they describe the
    light before unobservable texels are zeroed, `light` after); `unobservable`
    (N,) bool; `levels/NN/` the same per refinement level, with its errors as attributes.
    """
    with h5_file(path) as f:
        f.attrs.update({"format": SOLUTION_FORMAT, "basis": solution.basis, "resolution": cube.resolution,
                        "hemisphere": cube.hemisphere, "chosen_level": solution.chosen,
                        "units": "linear radiance per texel (light x albedo when kd = 1)"})
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
        f.create_dataset("light", data=solution.light.astype(np.float32))
        f.create_dataset("coefficients", data=solution.coefficients)
        f.create_dataset("unobservable", data=np.asarray(unobservable, bool))
        f.create_dataset("texel_directions", data=cube.directions.astype(np.float32))
        f.create_dataset("texel_solid_angles", data=cube.solid_angles)
        if solution.tree is not None:
            _write_tree(f.create_group("tree"), solution.tree)
        if "points" in solution.details:
            pts = solution.details["points"]
            f.create_dataset("points/direction", data=np.array([p["direction"] for p in pts]).reshape(-1, 3))
            f.create_dataset("points/irradiance", data=np.array([p["irradiance_rgb"] for p in pts]).reshape(-1, 3))
        for lv in solution.levels:
            g = f.create_group(f"levels/{lv.index:02d}")
            g.attrs["fit_rmse"] = lv.fit_rmse
            g.attrs["held_out_rmse"] = np.nan if lv.held_out_rmse is None else lv.held_out_rmse
            g.attrs["seconds"] = lv.seconds
            g.create_dataset("coefficients", data=lv.coefficients)
            if lv.tree is not None:
                _write_tree(g.create_group("tree"), lv.tree)


def read_solution_light(path) -> tuple[np.ndarray, CubeMap, dict]:
    """(N, 3) texel light, its cube map and the file's attributes, from `write_solution`'s file."""
    import h5py

    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != SOLUTION_FORMAT:
            raise ValueError(f"not a {SOLUTION_FORMAT} file")
        cube = CubeMap(int(f.attrs["resolution"]), bool(f.attrs["hemisphere"]))
        return f["light"][:].astype(np.float64), cube, dict(f.attrs)
