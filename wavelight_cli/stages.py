"""The cached stages: each loads its inputs, asks the cache whether to run, runs `pipelines`, and
writes its outputs atomically before recording them. Printing goes through `Console`."""

from __future__ import annotations

import json
import shutil
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipelines.errors import InputError, require_file

from .cache import Decision, SceneCache, atomic_output, output_set
from .scenefiles import SceneFiles

VISIBILITY_VERSION = 2
RENDER_VERSION = 2
CHUNK_PIXELS = 1024


class Console:
    """Plain, greppable progress on stderr: `stage: message`."""

    def __init__(self, quiet: bool = False, stream=None):
        self.quiet = quiet
        self.stream = stream or sys.stderr
        self._last = 0.0

    def say(self, message: str) -> None:
        if not self.quiet:
            print(message, file=self.stream, flush=True)

    def result(self, message: str) -> None:
        """A result line: printed on stdout even with --quiet."""
        print(message, file=sys.stdout, flush=True)

    def decision(self, d: Decision) -> None:
        self.say(f"{d.stage}: running ({d.reason})" if d.run else f"{d.stage}: skipped, {d.reason}")

    def progress(self, stage: str, done: int, total: int, extra: str = "", every: float = 1.0) -> None:
        now = time.monotonic()
        if done < total and now - self._last < every:
            return
        self._last = now
        self.say(f"{stage}: [{done}/{total}] {100.0 * done / max(total, 1):.0f}%{(' ' + extra) if extra else ''}")


@dataclass(frozen=True)
class VisibilityOptions:
    resolution: int = 32
    hemisphere: bool = True
    supersample: int = 1
    edge_margin: int = 1
    backend: str = "embree"

    def check(self) -> None:
        R = self.resolution
        if R < 2 or R > 512 or (R & (R - 1)):
            raise InputError(f"--resolution must be a power of two from 2 to 512, got {R}", None,
                             "use e.g. --resolution 32")
        if not 1 <= self.supersample <= 8:
            raise InputError(f"--supersample must be 1..8, got {self.supersample}", None, "use 1 (off) to 4")
        if not 0 <= self.edge_margin <= 32:
            raise InputError(f"--edge-margin must be 0..32 pixels, got {self.edge_margin}", None, "use 0 to 3")


def _require(path: Path | None, what: str, fix: str) -> Path:
    require_file(path, fix)
    return Path(path)


@dataclass(frozen=True)
class View:
    """A camera looking at the scene's mesh: the photo's own (camera.json, pose.json, mask.png) or
    another one (relight --view). Each view has its own visibility stage and file in the cache."""

    camera: Path
    pose: Path
    mask: Path | None = None
    name: str = ""  # "" = the photo's view

    @property
    def stage(self) -> str:
        return "visibility" + (f"-{self.name}" if self.name else "")

    @property
    def file(self) -> str:
        return self.stage + ".h5"


def photo_view(scene: SceneFiles) -> View:
    return View(scene.camera, scene.pose, scene.mask)


def visibility_inputs(scene: SceneFiles, view: View | None = None) -> dict[str, Path | None]:
    view = view or photo_view(scene)
    _require(view.camera, "camera", "write camera.json or run wavelight calibrate")
    _require(view.pose, "pose", "write pose.json or run wavelight register")
    mesh = scene.mesh
    return {"camera.json": view.camera, "pose.json": view.pose, mesh.name: mesh, "mask.png": view.mask}


def _load_samples(scene: SceneFiles, opts: VisibilityOptions, view: View | None = None):
    from pipelines import camera as cam
    from pipelines import images, raycast
    from pipelines.scene import load_mesh, read_camera, read_pose

    view = view or photo_view(scene)
    camera = read_camera(view.camera)
    pose = read_pose(view.pose)
    mesh = load_mesh(scene.mesh)
    mask = images.read_mask(view.mask) if view.mask else None
    backend = raycast.make_backend(mesh, opts.backend)
    try:
        samples, diag = cam.pixel_samples(camera, pose, mesh, backend, mask, opts.edge_margin, mask_path=view.mask)
    except InputError as exc:
        if exc.path is None:  # geometric problem: blame the pose
            raise InputError(exc.problem, view.pose, exc.fix) from None
        raise
    return camera, mesh, backend, samples, diag


def visibility_stage(scene: SceneFiles, opts: VisibilityOptions, console: Console, force: bool = False,
                     lock_wait: float = 600.0, view: View | None = None) -> Decision:
    """Shadow visibility of every used pixel towards every texel -> .wavelight/visibility.h5
    (another view: .wavelight/visibility-<name>.h5, its own stage).

    Resumable: finished chunks are kept in .wavelight/partial/<stage>-<key>/ until the file is
    assembled, so an interrupted run continues where it stopped and gives identical bits.
    """
    from pipelines import visibility as vis
    from pipelines.cubemap import CubeMap

    opts.check()
    view = view or photo_view(scene)
    cache = SceneCache(scene.root)
    inputs = visibility_inputs(scene, view)
    stage = view.stage
    with cache.lock(lock_wait, console.say):
        d = cache.plan(stage, VISIBILITY_VERSION, asdict(opts), inputs, {}, force)
        console.decision(d)
        if not d.run:
            return d
        t0 = time.monotonic()
        camera, mesh, backend, samples, diag = _load_samples(scene, opts, view)
        for note in mesh.notes:
            console.say(f"{stage}: mesh: {note}")
        cube = CubeMap(opts.resolution, opts.hemisphere)
        partial_root = cache.dir / "partial"
        partial = partial_root / f"{stage}-{d.key[:16]}"
        if partial_root.is_dir():
            for other in partial_root.glob(f"{stage}-*"):
                if other != partial and other.name[len(stage) + 1:].isalnum():
                    shutil.rmtree(other, ignore_errors=True)
        partial.mkdir(parents=True, exist_ok=True)
        n = len(samples)
        n_chunks = (n + CHUNK_PIXELS - 1) // CHUNK_PIXELS
        done = sum((partial / f"chunk_{i:05d}.npy").is_file() for i in range(n_chunks))
        if done:
            console.say(f"{stage}: resuming, {done}/{n_chunks} chunks already done")
        console.say(f"{stage}: {n} pixels x {cube.n_texels} texels (R={opts.resolution}, "
                    f"{'hemisphere' if opts.hemisphere else 'sphere'}, supersample {opts.supersample}, "
                    f"{opts.backend})")
        rays = 0
        t_cast = time.monotonic()
        for i in range(n_chunks):
            chunk_path = partial / f"chunk_{i:05d}.npy"
            if chunk_path.is_file():
                continue
            rows = slice(i * CHUNK_PIXELS, min(n, (i + 1) * CHUNK_PIXELS))
            block = vis.visibility_rows(backend, samples, rows, cube, opts.supersample)
            with atomic_output(chunk_path) as tmp:
                with open(tmp, "wb") as f:
                    np.save(f, block, allow_pickle=False)
            rays += int(np.count_nonzero(vis.castable(samples.normal[rows], samples.geometric_normal[rows],
                                                      cube.directions))) * opts.supersample**2
            rate = rays / max(time.monotonic() - t_cast, 1e-9) / 1e6
            console.progress(stage, i + 1, n_chunks, f"{rate:.1f} Mrays/s")

        def chunks():
            for i in range(n_chunks):
                yield np.load(partial / f"chunk_{i:05d}.npy", allow_pickle=False)

        out = cache.dir / view.file
        with atomic_output(out) as tmp:
            vis.write_visibility(tmp, samples, cube, opts.supersample, chunks(), CHUNK_PIXELS,
                                 attrs={"key": d.key, "backend": opts.backend})
        seconds = time.monotonic() - t0
        summary = {**diag, "texels": cube.n_texels, "rays_cast_this_run": rays}
        cache.record(d, [out], seconds, summary)
        shutil.rmtree(partial, ignore_errors=True)
        if partial_root.is_dir() and not any(partial_root.iterdir()):
            partial_root.rmdir()
        console.result(f"{stage}: done in {seconds:.1f} s ({rays / 1e6:.1f} M rays cast) -> {cache.relative(out)}")
    return d


def check_scene(scene: SceneFiles, opts: VisibilityOptions) -> list[str]:
    """Validate every file the scene folder has (without writing anything); return summary lines."""
    from pipelines import images
    from pipelines.scene import load_mesh, read_camera, read_correspondences, read_pose

    lines = []
    camera = read_camera(_require(scene.camera, "camera", "write camera.json or run wavelight calibrate"))
    lines.append(f"camera.json: {camera.width}x{camera.height}, fx {camera.fx:g}, fy {camera.fy:g}")
    if scene.image is not None:
        path, img = load_photo(scene, camera)
        depth = "float" if img.bit_depth == "float" else f"{img.bit_depth}-bit"
        lines.append(f"{path.name}: {img.width}x{img.height}, {depth}, "
                     f"{int(img.saturated.sum())} saturated pixels")
    else:
        lines.append("photo: none (needed by solve)")
    if scene.correspondences.exists():
        uv, _ = read_correspondences(scene.correspondences)
        lines.append(f"correspondences.csv: {len(uv)} points")
    mesh = load_mesh(scene.mesh)
    lines.append(f"{scene.mesh.name}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces"
                 + (f" ({'; '.join(mesh.notes)})" if mesh.notes else ""))
    if scene.mask is not None:
        mask = images.read_mask(scene.mask)
        if mask.shape != (camera.height, camera.width):
            raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]}, camera.json says "
                             f"{camera.width}x{camera.height}", scene.mask, "use a mask of the photo's size")
        if not mask.any():
            raise InputError("mask is empty (no white pixel)", scene.mask, "paint the pixels to use white")
        lines.append(f"mask.png: {int(mask.sum())} pixels")
    if scene.pose.exists():
        read_pose(scene.pose)
        opts.check()
        *_, diag = _load_samples(scene, opts)
        lines.append(f"pose.json: {diag['used']} used pixels of {diag['hit']} that see the mesh")
    else:
        lines.append("pose.json: none (run wavelight register)")
    return lines


def load_photo(scene: SceneFiles, camera, linear: bool | None = None):
    from pipelines import images

    path = scene.require_image()
    img = images.read_image(path, linear=linear)
    if (img.width, img.height) != (camera.width, camera.height):
        raise InputError(f"image is {img.width}x{img.height} but camera.json says {camera.width}x{camera.height}",
                         path, "use the photo the camera was calibrated for, or fix camera.json")
    return path, img


def solved_resolution(path: Path) -> int:
    """The cube-map resolution of the light `solve` wrote (out/coefficients.h5)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return int(f.attrs["resolution"])
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(f"cannot read the solved light ({str(exc).splitlines()[0]})", path,
                         "rerun wavelight solve --force") from None


def material_from_options(material_file: Path | None, model: str | None, kd, ks, shininess,
                          given: set | None = None):
    """The material of --material/--model/--kd/--ks/--shininess; `given` (if a set) receives the
    names of the fields the user set ('model', 'kd', 'ks', 'n', 'file')."""
    from pipelines.render import Material

    data: dict = {}
    if material_file is not None:
        try:
            data = json.loads(Path(material_file).read_text())
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read material JSON ({exc})", material_file, "fix the file") from None
        if not isinstance(data, dict):
            raise InputError("a material must be a JSON object", material_file,
                             'write e.g. {"model": "lambert", "kd": [0.8, 0.8, 0.8]}')
    if model is not None:
        data["model"] = model
        data.pop("type", None)
    if kd is not None:
        data["kd"] = list(kd)
    if ks is not None:
        data["ks"] = list(ks)
    if shininess is not None:
        data["n"] = shininess
    if given is not None:
        given.update(k for k in ("kd", "ks") if k in data)
        given.update({"model"} if "model" in data or "type" in data else set())
        given.update({"n"} if "n" in data or "shininess" in data else set())
        given.update({"file"} if material_file is not None else set())
    try:
        return Material.from_json(data)
    except (ValueError, TypeError) as exc:
        raise InputError(str(exc), material_file, "fix the material values") from None


def render_stage(scene: SceneFiles, vis_opts: VisibilityOptions, light_path: Path, material, exposure: float | None,
                 console: Console, force: bool = False, lock_wait: float = 600.0) -> Decision:
    """Render the input view under a lat-long light with a material -> out/render.exr/png
    (and, if the scene has its photo, the error against it and a residual heat map)."""
    from pipelines import cubemap, images
    from pipelines import render as rd
    from pipelines import visibility as vis
    from pipelines.scene import read_camera

    light_path = _require(Path(light_path), "light", "pass a lat-long EXR/HDR with --light")
    camera = read_camera(scene.camera)
    photo_path, photo = load_photo(scene, camera) if scene.image is not None else (None, None)
    env = images.read_latlong(light_path)
    cache = SceneCache(scene.root)
    with cache.lock(lock_wait, console.say):  # one lock across visibility and render
        vdec = visibility_stage(scene, vis_opts, console, force=False, lock_wait=lock_wait)
        params = {"material": material.to_json(), "exposure": exposure}
        inputs = {"light": light_path, "photo": photo_path}
        d = cache.plan("render", RENDER_VERSION, params, inputs, {"visibility": vdec.key}, force)
        console.decision(d)
        if not d.run:
            return d
        t0 = time.monotonic()
        data = vis.read_visibility(cache.dir / "visibility.h5")
        light = cubemap.latlong_to_cube(env, data.cube)
        values = rd.render(data, light, material)
        img = rd.pixels_to_image(values, data.samples.pixel, camera.height, camera.width)
        with output_set():  # the stage's files replace the old ones together, or not at all
            outputs = [scene.out / "render.exr", scene.out / "render.png"]
            images.write_exr(outputs[0], img)
            images.write_png(outputs[1], img, exposure)
            outputs += write_light(scene.out, "render_light", light, data.cube)
            summary = {"pixels": int(len(values)), "mean_radiance": float(values.mean())}
            residual_path = scene.out / "render_residual.png"
            if photo is None and residual_path.exists():
                residual_path.unlink()  # it belonged to a photo that is gone
            if photo is not None:
                outputs.append(residual_path)
                summary.update(compare_to_photo(values, photo, data.samples, camera, residual_path))
                console.result(f"render: relative RMSE vs {photo_path.name}: "
                               f"{100 * summary['relative_rmse_vs_photo']:.2f} % over {summary['compared_pixels']} pixels")
        seconds = time.monotonic() - t0
        cache.record(d, outputs, seconds, summary)
        for p in outputs:
            console.say(f"render: wrote {cache.relative(p)}")
    return d


def write_light(out_dir: Path, stem: str, texels: np.ndarray, cube, height: int | None = None,
                unobservable: np.ndarray | None = None) -> list[Path]:
    """A cube-map light as <stem>_latlong.exr (exchange format), <stem>_cross.exr and a preview PNG
    of the cross (texels outside the layout dark grey, unobservable texels dark magenta)."""
    from pipelines import cubemap, images

    height = height or max(64, 2 * cube.resolution)
    paths = [out_dir / f"{stem}_latlong.exr", out_dir / f"{stem}_cross.exr", out_dir / f"{stem}_cross.png"]
    images.write_exr(paths[0], cubemap.cube_to_latlong(texels, cube, height))
    cross, valid = cubemap.cross_image(texels, cube)
    images.write_exr(paths[1], cross)
    preview = images.tonemap(cross)
    preview[~valid] = 0.15
    if unobservable is not None and np.any(unobservable):
        marked, _ = cubemap.cross_image(np.asarray(unobservable, np.float64), cube)
        preview[marked > 0.5] = (0.35, 0.0, 0.35)
    images.write_png(paths[2], upscale(preview), already_display=True)
    return paths


def upscale(image: np.ndarray, width: int = 512) -> np.ndarray:
    """Nearest-neighbour enlargement of a small preview to about `width` pixels across."""
    k = max(1, width // image.shape[1])
    return np.repeat(np.repeat(image, k, axis=0), k, axis=1)


def compare_to_photo(values: np.ndarray, photo, samples, camera, heat_path: Path) -> dict:
    """Relative RMSE and bias of rendered pixel values against the photo (saturated pixels left
    out), and a residual heat map (white = an error of 10 % of the 95th-percentile radiance)."""
    from pipelines import images
    from pipelines import render as rd

    rows, cols = samples.pixel[:, 0], samples.pixel[:, 1]
    ref = photo.pixels[rows, cols].astype(np.float64)
    ok = ~photo.saturated[rows, cols]
    err = values[ok] - ref[ok]
    rel = float(np.sqrt(np.mean(err**2)) / max(np.sqrt(np.mean(ref[ok] ** 2)), 1e-30)) if ok.any() else float("nan")
    bias = float(values[ok].mean() / max(ref[ok].mean(), 1e-30) - 1) if ok.any() else float("nan")
    heat = rd.pixels_to_image(np.abs(err).mean(axis=1), samples.pixel[ok], camera.height, camera.width)
    scale = 0.1 * float(np.percentile(np.abs(ref[ok]).mean(axis=1), 95)) if ok.any() else 1.0
    images.write_png(heat_path, heat_map(heat, scale), already_display=True)
    return {"relative_rmse_vs_photo": rel, "bias_vs_photo": bias, "compared_pixels": int(ok.sum())}


def heat_map(values: np.ndarray, scale: float) -> np.ndarray:
    """(H, W) non-negative values -> (H, W, 3) display colours (black -> red -> yellow -> white at `scale`)."""
    x = np.clip(np.nan_to_num(values) / max(scale, 1e-30), 0.0, 1.0)
    return np.stack([np.clip(3 * x, 0, 1), np.clip(3 * x - 1, 0, 1), np.clip(3 * x - 2, 0, 1)], axis=-1)
