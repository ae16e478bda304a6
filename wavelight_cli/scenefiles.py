"""Where a scene folder keeps its files (DESIGN §5), and loading them with clear errors."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipelines.errors import InputError

IMAGE_NAMES = ("image.exr", "image.hdr", "image.pfm", "image.tif", "image.tiff", "image.png",
               "image.jpg", "image.jpeg")


@dataclass(frozen=True)
class SceneFiles:
    root: Path

    @property
    def camera(self) -> Path:
        return self.root / "camera.json"

    @property
    def pose(self) -> Path:
        return self.root / "pose.json"

    @property
    def correspondences(self) -> Path:
        return self.root / "correspondences.csv"

    @property
    def mask(self) -> Path | None:
        p = self.root / "mask.png"
        return p if p.exists() else None

    @property
    def image(self) -> Path | None:
        for name in IMAGE_NAMES:
            if (self.root / name).exists():
                return self.root / name
        return None

    def require_image(self) -> Path:
        path = self.image
        if path is None:
            raise InputError("no photo in the scene folder", self.root / "image.exr",
                             f"add the photo as one of {', '.join(IMAGE_NAMES)}")
        return path

    @property
    def mesh(self) -> Path:
        from pipelines.scene import find_mesh

        return find_mesh(self.root)

    @property
    def out(self) -> Path:
        return self.root / "out"


def scene_folder(path: str | Path) -> SceneFiles:
    root = Path(path)
    if not root.is_dir():
        raise InputError("scene folder not found", root, "pass an existing folder with --scene/-s")
    return SceneFiles(root)
