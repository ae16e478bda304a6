"""Shared fixtures: the Mitsuba 3 reference scenes in tests/data/scenes (see tests/data/README.md).

Loading a scene, casting its pixel rays and, above all, computing its visibility are expensive, so
they happen once per session: `mitsuba_scene(name)` loads a scene, `forward_render(name, R, step)`
computes the visibility at cube-map resolution R for every `step`-th used pixel and renders the
scene's true light and material through our forward model. Both are cached per argument tuple.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import pytest

DATA_DIR = Path(__file__).parent / "data"


def pytest_configure(config):
    """The allocator as the CLI sets it (`threads.configure_malloc`), for the tests that call the
    pipelines directly."""
    from pipelines.threads import configure_malloc

    configure_malloc()


@pytest.fixture(scope="session", autouse=True)
def _private_user_cache(tmp_path_factory):
    """The user cache folder (derived data kept between runs, `cubemap._user_cache_dir`) is the
    session's own: no test reads what another run left in ~/.cache (subprocesses inherit it)."""
    import os

    old = os.environ.get("WAVELIGHT_CACHE_DIR")
    os.environ["WAVELIGHT_CACHE_DIR"] = str(tmp_path_factory.mktemp("user-cache"))
    yield
    if old is None:
        os.environ.pop("WAVELIGHT_CACHE_DIR", None)
    else:
        os.environ["WAVELIGHT_CACHE_DIR"] = old
SCENES_DIR = DATA_DIR / "scenes"
MITSUBA_SCENES = ("spot_overcast", "bunny_sun", "teapot_sun_phong")


@dataclass(frozen=True)
class MitsubaScene:
    """A reference scene with its used pixels (mask.png ∩ `pixel_samples`, edge margin 1).

    reference : (P, 3) float64 noise-free Mitsuba radiance (truth/image_clean.exr) at the used pixels.
    on_object : (P,) bool, used pixels whose surface point lies on the object (not the ground plane).
    """

    name: str
    path: Path
    camera: object
    pose: object
    mesh: object
    backend: object
    samples: object
    diagnostics: dict
    light_latlong: np.ndarray
    material: object
    reference: np.ndarray
    on_object: np.ndarray


@dataclass(frozen=True)
class ForwardRender:
    """Our render of a scene under its true light and material, on every `step`-th used pixel."""

    scene: MitsubaScene
    resolution: int
    step: int
    visibility: object
    light: np.ndarray  # (N, 3) texel radiances of the true light
    rendered: np.ndarray  # (p, 3)
    reference: np.ndarray  # (p, 3)
    on_object: np.ndarray  # (p,)

    def relative_rmse(self, select: np.ndarray | None = None) -> float:
        """sqrt(mean((ours - Mitsuba)^2)) / sqrt(mean(Mitsuba^2)) over all channels of the pixels."""
        ours, ref = (self.rendered, self.reference) if select is None else (
            self.rendered[select], self.reference[select])
        return float(np.sqrt(np.mean((ours - ref) ** 2)) / np.sqrt(np.mean(ref**2)))

    def render(self, material) -> np.ndarray:
        """(p, 3) radiance of the same pixels and light with another material."""
        from pipelines.model import render

        return render.render(self.visibility, self.light, material)

    def brightness_ratio(self) -> float:
        """Mean of our radiance over the mean of Mitsuba's (1 = no bias)."""
        return float(self.rendered.mean() / self.reference.mean())


def object_face_count(scene_dir: Path) -> int:
    """The scene meshes hold the object's faces first, then the ground plane's; README.txt says
    how many are the object's ("mesh.obj  object (first V vertices / F faces) + ground plane")."""
    found = re.search(r"first (\d+) vertices / (\d+) faces", (scene_dir / "README.txt").read_text())
    if found is None:
        raise ValueError(f"{scene_dir / 'README.txt'} does not give the object's face count")
    return int(found.group(2))


def _load_scene(name: str) -> MitsubaScene:
    from pipelines.geometry import camera as cam
    from pipelines.io import images
    from pipelines.geometry import raycast
    from pipelines.model import materials
    from pipelines.io import scene_files as sc

    path = SCENES_DIR / name
    camera = sc.read_camera(path / "camera.json")
    pose = sc.read_pose(path / "pose.json")
    mesh = sc.load_mesh(path / "mesh.ply")
    backend = raycast.make_backend(mesh)
    samples, diagnostics = cam.pixel_samples(camera, pose, mesh, backend, images.read_mask(path / "mask.png"),
                                             edge_margin=1)
    rows, cols = samples.pixel[:, 0], samples.pixel[:, 1]
    reference = images.read_image(path / "truth" / "image_clean.exr").pixels[rows, cols].astype(np.float64)
    on_object = samples.face < object_face_count(path)
    material = materials.Material.from_json(json.loads((path / "truth" / "material.json").read_text()))
    return MitsubaScene(name, path, camera, pose, mesh, backend, samples, diagnostics,
                        images.read_latlong(path / "truth" / "env_latlong.exr"), material, reference, on_object)


def _every(samples, step: int):
    if step == 1:
        return samples
    return type(samples)(**{f.name: getattr(samples, f.name)[::step] for f in fields(samples)})


@pytest.fixture(scope="session")
def mitsuba_scene():
    """`mitsuba_scene(name) -> MitsubaScene`, loaded once per session."""
    cache: dict[str, MitsubaScene] = {}

    def get(name: str) -> MitsubaScene:
        if name not in cache:
            cache[name] = _load_scene(name)
        return cache[name]

    return get


@pytest.fixture(scope="session")
def forward_render(mitsuba_scene):
    """`forward_render(name, resolution, step=1) -> ForwardRender`, computed once per session."""
    from pipelines.light import cubemap
    from pipelines.model import render
    from pipelines.geometry import visibility as vis

    cache: dict[tuple[str, int, int], ForwardRender] = {}

    def get(name: str, resolution: int, step: int = 1) -> ForwardRender:
        key = (name, resolution, step)
        if key not in cache:
            scene = mitsuba_scene(name)
            samples = _every(scene.samples, step)
            cube = cubemap.CubeMap(resolution)
            visibility = vis.compute_visibility(scene.backend, samples, cube)
            light = cubemap.latlong_to_cube(scene.light_latlong, cube)
            rendered = render.render(visibility, light, scene.material)
            cache[key] = ForwardRender(scene, resolution, step, visibility, light, rendered,
                                       scene.reference[::step], scene.on_object[::step])
        return cache[key]

    return get


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    """The sample scene with visibility (R=8) and a render up to date (built once per module)."""
    from cli_helpers import baseline_scene

    return baseline_scene(tmp_path_factory)


@pytest.fixture
def scene(baseline, tmp_path):
    """A private copy of the baseline scene (cache and results included)."""
    from cli_helpers import copy_scene

    return copy_scene(baseline, tmp_path / "scene")


@pytest.fixture(scope="session")
def lambert_solved(tmp_path_factory):
    """The sample scene after `solve -R 8 --reflectance lambert` (made once per session; read-only:
    copy it with cli_helpers.copy_scene before changing anything)."""
    from cli_helpers import RES, copy_sample, invoke, ok

    scene = copy_sample(tmp_path_factory.mktemp("lambert_solved") / "scene")
    ok(invoke(scene, "solve", "--resolution", RES, "--reflectance", "lambert"))
    return scene


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """One folder per module for the property tests: each example overwrites its files
    (module-scoped, so hypothesis needs no health-check exemption for a function-scoped fixture)."""
    return tmp_path_factory.mktemp("props")
