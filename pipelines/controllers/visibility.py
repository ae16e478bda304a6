"""The visibility stage: camera, pose, mesh and mask -> the used pixels and the shadow of every
light direction at each of them.

`options.method` "adaptive" (the default) casts the base grid of pixels in full and infers the
rest from neighbouring pixels where they agree (`geometry.visibility.coherent_visibility`);
"exact" casts every ray (the caller runs it in resumable chunks: `exact_rows`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import InputError, OptionError

DEFAULT_RESOLUTION = 32  # the one default of R (every command that needs one reads it from here)


@dataclass(frozen=True)
class VisibilityOptions:
    resolution: int = DEFAULT_RESOLUTION
    hemisphere: bool = True
    supersample: int = 1
    edge_margin: int = 1
    backend: str = "embree"
    method: str = "adaptive"  # adaptive: cast where the image says shadows change; exact: every ray

    def check(self) -> None:
        R = self.resolution
        if R < 2 or R > 512 or (R & (R - 1)):
            raise OptionError(f"--resolution must be a power of two from 2 to 512, got {R}", None,
                             "use e.g. --resolution 32")
        if not 1 <= self.supersample <= 8:
            raise OptionError(f"--supersample must be 1..8, got {self.supersample}", None, "use 1 (off) to 4")
        if not 0 <= self.edge_margin <= 32:
            raise OptionError(f"--edge-margin must be 0..32 pixels, got {self.edge_margin}", None, "use 0 to 3")
        if self.method not in ("adaptive", "exact"):
            raise OptionError(f"unknown --visibility {self.method!r}", None, "use adaptive (default) or exact")

    def params(self) -> dict:
        return asdict(self)

    @property
    def slot(self) -> str:
        """A readable name for these options (visibility results of several options coexist)."""
        parts = [f"R{self.resolution}"]
        if not self.hemisphere:
            parts.append("sphere")
        if self.supersample != 1:
            parts.append(f"ss{self.supersample}")
        if self.edge_margin != 1:
            parts.append(f"margin{self.edge_margin}")
        if self.backend != "embree":
            parts.append(self.backend)
        if self.method != "adaptive":
            parts.append(self.method)
        return "-".join(parts)


def used_pixels(camera, pose, mesh, mask, options: VisibilityOptions, pose_path=None, mask_path=None, backend=None,
                with_hits: bool = False):
    """The used pixels' surface samples: (samples, diagnostics, the ray caster: `backend`, or one
    built for the mesh), and with `with_hits` the (H, W) centre-ray hits (`pixel_samples`)."""
    from ..geometry import camera as cam
    from ..geometry import raycast

    backend = raycast.make_backend(mesh, options.backend) if backend is None else backend
    try:
        found = cam.pixel_samples(camera, pose, mesh, backend, mask, options.edge_margin, mask_path=mask_path,
                                  with_hits=with_hits)
    except InputError as exc:
        if exc.path is None:  # geometric problem: blame the pose
            raise InputError(exc.problem, pose_path, exc.fix) from None
        raise
    return (*found[:2], backend, *found[2:])


def adaptive_visibility(backend, samples, cube, options: VisibilityOptions, progress=None, image_size=None):
    """The stored rows of every used pixel by `coherent_visibility`, and its statistics; `image_size`
    (height, width) of the image the samples are pixels of."""
    from ..geometry.visibility import coherent_visibility

    return coherent_visibility(backend, samples, cube, options.supersample, progress=progress, image_size=image_size)


def exact_rows(backend, samples, cube, options: VisibilityOptions, rows: slice) -> tuple[np.ndarray, int]:
    """Every ray of some pixel rows: (stored rows, rays cast)."""
    from ..geometry import visibility as vis

    block = vis.visibility_rows(backend, samples, rows, cube, options.supersample)
    rays = int(np.count_nonzero(vis.castable(samples.normal[rows], samples.geometric_normal[rows],
                                             cube.directions))) * options.supersample**2
    return block, rays
