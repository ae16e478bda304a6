"""The light bases (DESIGN §4): the one registry the CLI, compare, the report and the tests read.

One module per basis; a new basis is one module with a `solve(ne, cube, basis, options, progress)`
function plus one entry in `BASES`. Importing this package is cheap (the basis modules load when a
basis is solved), so the command line can list the choices without loading numpy.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from ...errors import InputError


@dataclass(frozen=True)
class BasisInfo:
    name: str  # what users type: --basis NAME
    description: str  # one line for --help and the report
    module: str  # the module in this package that solves it
    options: tuple[str, ...]  # the LightOptions fields that change its result
    variants: tuple[dict, ...] = ({},)  # what `compare` runs of it (option overrides)


BASES: dict[str, BasisInfo] = {b.name: b for b in (
    BasisInfo("wavelet", "the paper's adaptive Haar wavelets, refined coarse to fine", "tree", ("levels", "min_gain")),
    BasisInfo("quadtree", "the same refinement with one constant per leaf (the paper's rival)", "tree",
              ("levels", "min_gain")),
    BasisInfo("discrete", "one value per texel at --face-resolution", "discrete", ("face_resolution",)),
    BasisInfo("sh", "real spherical harmonics to --sh-order (plain least squares, or non-negative)", "sh",
              ("sh_order", "sh_nonnegative"), ({"sh_nonnegative": False}, {"sh_nonnegative": True})),
    BasisInfo("points", "a few directional lights added greedily", "points", ("levels", "min_gain")),
)}
REFINED = tuple(name for name, b in BASES.items() if "levels" in b.options)  # bases whose size --levels sets
COMPARE_RUNS = tuple((name, v) for name, b in BASES.items() for v in b.variants)  # every basis, as compare runs them


@dataclass(frozen=True)
class LightOptions:
    """How one basis is solved: its size (`levels`: "auto" or a count of refinement levels / lights)
    and the options of the other bases."""

    basis: str = "wavelet"
    levels: str = "auto"
    min_gain: float = 0.01  # levels auto: a level must lower the held-out error by this fraction
    face_resolution: int | None = None  # discrete: face resolution (default: the cube map's R)
    sh_order: int = 2
    sh_nonnegative: bool = False

    @property
    def levels_value(self) -> int | str:
        return "auto" if self.levels == "auto" else int(self.levels)

    def check(self, resolution: int, hemisphere: bool = True) -> None:
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
            tree = BASES[self.basis].module == "tree"
            most = resolution.bit_length() + 1 if tree else 3 * resolution**2 * (1 if hemisphere else 2)
            if self.basis in REFINED and n > most:
                what = (f"the {most} levels a cube map of R = {resolution} can be refined to" if tree
                        else f"the {most} light directions at R = {resolution}")
                raise InputError(f"--levels {n} is more than {what}", None, f"use --levels auto, or at most {most}")
        if not 0 <= self.min_gain < 1:
            raise InputError(f"--min-gain must be in [0, 1), got {self.min_gain}", None, "use e.g. 0.01")
        if not 0 <= self.sh_order <= 8:
            raise InputError(f"--sh-order must be 0..8, got {self.sh_order}", None, "use 2 (9 coefficients)")
        r = self.face_resolution
        if r is not None and (r < 1 or r > resolution or r & (r - 1)):
            raise InputError(f"--face-resolution must be a power of two up to --resolution ({resolution}), "
                             f"got {r}", None, f"use e.g. --face-resolution {resolution}")

    def cache_params(self) -> dict:
        """The options that can change this basis' result (others do not rerun a solve)."""
        keep = ("basis",) + BASES[self.basis].options
        return {k: getattr(self, k) for k in keep}


def solve(ne, cube, basis: str = "wavelet", levels: int | str = "auto", min_gain: float = 0.01,
          face_resolution: int | None = None, sh_order: int = 2, sh_nonnegative: bool = False, progress=None,
          all_pixels: bool = True):
    """Solve the light in one basis on the normal equations `ne` -> `solution.LightSolution`.

    levels : "auto" (refine, or add lights, until the held-out error stops falling by `min_gain`)
        or a count of levels (wavelet, quadtree) / lights (points).
    progress : called with each refinement level's record.
    all_pixels : False: a tree basis' light may stay the chosen level's, fitted on the exploration's
        rows (an intermediate light; `finish` makes it the final one). The other bases ignore it.
    """
    info = BASES.get(basis)
    if info is None:
        raise ValueError(f"unknown basis {basis!r}; use one of {', '.join(BASES)}")
    options = LightOptions(basis, "auto" if levels == "auto" else str(int(levels)), min_gain, face_resolution,
                           sh_order, sh_nonnegative)
    module = importlib.import_module(f"{__name__}.{info.module}")
    if info.module == "tree":
        return module.solve(ne, cube, options, progress, all_pixels)
    return module.solve(ne, cube, options, progress)


def finish(ne, cube, solution):
    """An intermediate light (`solve(all_pixels=False)`, `refit(all_pixels=False)`) re-solved on all
    pixels of `ne`, the system it was solved on: the final light (others are returned as they are)."""
    info = BASES.get(solution.basis)
    if info is not None and info.module == "tree":
        from .tree import finish as finish_tree

        return finish_tree(ne, cube, solution)
    return solution


def replay(ne, cube, solution, levels: int | str = "auto", min_gain: float = 0.01, progress=None):
    """`solution`'s refinement levels solved again on a corrected system, its trees followed and the
    level chosen afresh (`tree.replay`), or None for the bases without levels of trees (solve them
    again)."""
    info = BASES.get(solution.basis)
    if info is not None and info.module == "tree" and solution.levels and solution.levels[0].tree is not None:
        from .tree import replay as replay_tree

        return replay_tree(ne, cube, solution, levels, min_gain, progress)
    return None


def refit(ne, cube, solution, all_pixels: bool = True):
    """`solution` re-solved on another system with its structure kept (a tree basis' tree, warm
    started), or solved again from scratch for the bases without one. Used when the transport
    changes but the model size should not (corrected visibility, a reflectance round)."""
    info = BASES.get(solution.basis)
    if info is not None and info.module == "tree":
        from .tree import refit as refit_tree

        return refit_tree(ne, cube, solution, all_pixels)
    return None
