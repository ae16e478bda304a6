"""`wavelight visibility`: the used pixels and their shadow toward every light direction, cached per
view and options.

Results of several options and views coexist: each is the stage `visibility/<view>/<options>`
(e.g. `visibility/photo/R32`, `visibility/photo/R16-exact`) with its file
`.wavelight/visibility/<view>-<options>.h5`. Of each view the KEEP most recently computed results
are kept; older ones are deleted when a new one is computed (DESIGN §6). The exact method runs in resumable chunks: an
interrupted run continues where it stopped and gives identical bits.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.controllers.visibility import VisibilityOptions

from ..cache import Decision, Ran, SceneCache, Stage, run_stage
from ..console import Console
from ..scene import SceneFiles, View, photo_view, require

VERSION = 6  # 6: the adaptive inference at the image border (3 known neighbours, the rest beyond the image); 5: each pixel's normal Jacobian (the normal's turn across the pixel: a glossy lobe's footprint widening); 4: hit points located in float64 on the hit face, shadow offset from float32 precision (issue 17)
KEEP = 4  # visibility results kept per view
CHUNK_PIXELS = 1024  # rows per resumable chunk of the exact method
KEEP_IN_MEMORY = 8  # adaptive results kept in memory for a solve in the same process (`read_kept`)


@dataclass(frozen=True)
class VisibilityResult:
    decision: Decision
    path: Path  # the visibility file
    stage: str

    @property
    def key(self) -> str:
        return self.decision.key


def stage_name(view: View, opts: VisibilityOptions) -> str:
    return f"visibility/{view.name}/{opts.slot}"


def file_of(cache: SceneCache, view: View, opts: VisibilityOptions) -> Path:
    return cache.dir / "visibility" / f"{view.name}-{opts.slot}.h5"


def inputs_of(scene: SceneFiles, view: View) -> dict:
    require(view.camera, "write camera.json or run wavelight calibrate")
    require(view.pose, "write pose.json or run wavelight register")
    mesh = scene.mesh
    return {"camera.json": view.camera, "pose.json": view.pose, mesh.name: mesh, "mask.png": view.mask}


_KEPT: dict = {}  # visibility file -> (its size, mtime and inode when written, the data written to it)


def read_kept(path: Path):
    """`read_visibility(path)`, or the data the visibility stage of this process has just written
    there (once: the reader takes it over), while the file is the one it wrote."""
    from pipelines.io import visibility_file

    sig, data = _KEPT.pop(str(path), (None, None))
    return data if sig is not None and sig == _signature(path) else visibility_file.read_visibility(path)


def _signature(path: Path):
    try:
        st = Path(path).stat()
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns, st.st_ino


def load_samples(scene: SceneFiles, opts: VisibilityOptions, view: View):
    """(camera, mesh, ray caster, used-pixel samples, diagnostics) of a view (its centre-ray hits
    kept for `mesh_coverage`)."""
    from pipelines.controllers.visibility import used_pixels
    from pipelines.io import images
    from pipelines.io.scene_files import read_camera, read_pose

    from ..scene import keep_hits, scene_backend, scene_mesh

    camera = read_camera(view.camera)
    pose = read_pose(view.pose)
    mesh = scene_mesh(scene.mesh)
    mask = images.read_mask(view.mask) if view.mask else None
    samples, diag, backend, hits = used_pixels(camera, pose, mesh, mask, opts, view.pose, view.mask,
                                               scene_backend(mesh, opts.backend), with_hits=True)
    keep_hits(camera, pose, backend, hits)
    return camera, mesh, backend, samples, diag


def visibility_stage(scene: SceneFiles, opts: VisibilityOptions, console: Console, force: bool = False,
                     lock_wait: float = 600.0, view: View | None = None) -> VisibilityResult:
    """The view's visibility at these options -> .wavelight/visibility/<view>-<options>.h5."""
    from pipelines.io import visibility_file
    from pipelines.light.cubemap import CubeMap

    opts.check()
    view = view or photo_view(scene)
    cache = SceneCache(scene.root)
    name = stage_name(view, opts)
    out = file_of(cache, view, opts)
    stage = Stage(name, VERSION, opts.params(), inputs_of(scene, view))
    with cache.lock(lock_wait, console.say):

        def work(d: Decision) -> Ran:
            camera, mesh, backend, samples, diag = load_samples(scene, opts, view)
            for note in mesh.notes:
                console.say(f"{name}: mesh: {note}")
            cube = CubeMap(opts.resolution, opts.hemisphere)
            console.say(f"{name}: {len(samples)} pixels x {cube.n_texels} texels (R={opts.resolution}, "
                        f"{'hemisphere' if opts.hemisphere else 'sphere'}, supersample {opts.supersample}, "
                        f"{opts.method}, {opts.backend})")
            t0 = time.monotonic()
            if opts.method == "adaptive":
                stored, summary = _adaptive(backend, samples, cube, opts, console, name, (camera.height, camera.width))
                chunks, rows_per_chunk = iter([stored]), CHUNK_PIXELS
            else:
                chunks, rows_per_chunk, summary = _exact(cache, d, backend, samples, cube, opts, console, name)
            with_record = {"key": d.key, "backend": opts.backend, "method": opts.method,
                           "base_spacing_px": summary.get("base_spacing_px", 1)}
            visibility_file.write_visibility(out, samples, cube, opts.supersample, chunks, rows_per_chunk,
                                             attrs=with_record)
            if opts.method == "adaptive":  # (its rows are in memory: the solve in this process takes them)
                from pipelines.geometry.visibility import VisibilityData

                _KEPT.pop(str(out), None)
                while len(_KEPT) >= KEEP_IN_MEMORY:  # (a process that casts and never solves: the oldest go)
                    _KEPT.pop(next(iter(_KEPT)))
                _KEPT[str(out)] = (None, VisibilityData(_as_read(samples), cube, opts.supersample,
                                                        np.ascontiguousarray(stored), opts.method, castable_only=True))
            summary = {**diag, "texels": cube.n_texels, **summary, "seconds_casting": time.monotonic() - t0}
            console.result(_result_line(name, summary, cache.relative(out)))
            return Ran([out], summary)

        d = run_stage(cache, stage, console, force, work)
        kept = _KEPT.get(str(out))
        if kept is not None and kept[0] is None:  # stamped once the file is in place (after a run), else stale
            if d.run:
                _KEPT[str(out)] = (_signature(out), kept[1])
            else:
                del _KEPT[str(out)]
        if d.run:
            partial = cache.dir / "partial"
            shutil.rmtree(partial / f"{view.name}-{opts.slot}-{d.key[:16]}", ignore_errors=True)
            if partial.is_dir() and not any(partial.iterdir()):
                partial.rmdir()
            _prune(cache, view)
    return VisibilityResult(d, out, name)


def _as_read(samples):
    """The samples as `read_visibility` gives them back (C-ordered arrays; the fields the file has)."""
    from dataclasses import replace

    return replace(samples, **{n: np.ascontiguousarray(getattr(samples, n)) for n in samples.FIELDS
                               if getattr(samples, n) is not None})


def _result_line(name: str, summary: dict, rel: str) -> str:
    if summary.get("method") == "adaptive":
        return (f"{name}: done in {summary['seconds_casting']:.1f} s ({summary['cast_entries'] / 1e6:.1f} M of "
                f"{summary['castable_entries'] / 1e6:.1f} M shadow rays cast, the rest inferred from neighbouring "
                f"pixels; check: {summary['wrong_in_check']} of {summary['checked_entries']} wrong) -> {rel}")
    return f"{name}: done in {summary['seconds_casting']:.1f} s ({summary['rays_cast_this_run'] / 1e6:.1f} M rays cast) -> {rel}"


def _adaptive(backend, samples, cube, opts, console, name, image_size):
    from pipelines.controllers.visibility import adaptive_visibility

    task = console.task(name, "casting", 1, "refinement steps")

    def progress(done, total):
        task.total = total
        task.update(done)

    stored, stats = adaptive_visibility(backend, samples, cube, opts, progress, image_size)
    task.close()
    return stored, {**stats.as_dict(), "rays_cast_this_run": stats.cast * opts.supersample**2}


def _exact(cache, d, backend, samples, cube, opts, console, name):
    """Every ray, in chunk files that survive an interrupted run (resumed on the next one)."""
    from pipelines.controllers.visibility import exact_rows
    from pipelines.io.files import atomic_output

    partial_root = cache.dir / "partial"
    slot = f"{name.split('/')[1]}-{opts.slot}"
    partial = partial_root / f"{slot}-{d.key[:16]}"
    if partial_root.is_dir():  # chunks of runs with other inputs are of no use
        for other in partial_root.glob(f"{slot}-*"):
            if other != partial and other.name[len(slot) + 1:].isalnum():
                shutil.rmtree(other, ignore_errors=True)
    partial.mkdir(parents=True, exist_ok=True)
    n = len(samples)
    n_chunks = (n + CHUNK_PIXELS - 1) // CHUNK_PIXELS
    width = (cube.n_texels + 7) // 8 if opts.supersample == 1 else cube.n_texels  # (bits, or fractions)
    damaged = [i for i in range(n_chunks) if not _chunk_ok(partial / f"chunk_{i:05d}.npy",
                                                          (min(n, (i + 1) * CHUNK_PIXELS) - i * CHUNK_PIXELS, width))]
    for i in damaged:  # (a chunk damaged on disk is cast again, not read)
        (partial / f"chunk_{i:05d}.npy").unlink(missing_ok=True)
    if damaged:
        console.say(f"{name}: {len(damaged)} damaged chunk(s) of an interrupted run are cast again")
    done = sum((partial / f"chunk_{i:05d}.npy").is_file() for i in range(n_chunks))
    if done:
        console.say(f"{name}: resuming, {done}/{n_chunks} chunks already done")
    rays = 0
    t0 = time.monotonic()
    task = console.task(name, "casting", n_chunks, "chunks")
    for i in range(n_chunks):
        chunk_path = partial / f"chunk_{i:05d}.npy"
        if chunk_path.is_file():
            continue
        rows = slice(i * CHUNK_PIXELS, min(n, (i + 1) * CHUNK_PIXELS))
        block, cast = exact_rows(backend, samples, cube, opts, rows)
        with atomic_output(chunk_path, now=True) as tmp:  # kept even if the stage fails: the next run resumes
            with open(tmp, "wb") as f:
                np.save(f, block, allow_pickle=False)
        rays += cast
        task.update(i + 1, f"{rays / max(time.monotonic() - t0, 1e-9) / 1e6:.1f} Mrays/s")
    task.close()

    def chunks():
        for i in range(n_chunks):
            yield np.load(partial / f"chunk_{i:05d}.npy", allow_pickle=False)

    return chunks(), CHUNK_PIXELS, {"method": "exact", "rays_cast_this_run": rays}


def _chunk_ok(path, shape: tuple[int, int]) -> bool:
    """Whether a resume chunk is absent (to be cast) or whole: a uint8 array of `shape` (its rows,
    the stored row width) whose data the file holds in full (a chunk cut short or overwritten on disk
    is not)."""
    if not path.is_file():
        return True
    try:
        a = np.load(path, mmap_mode="r", allow_pickle=False)
        return a.shape == tuple(shape) and a.dtype == np.uint8
    except (OSError, ValueError, EOFError):
        return False


def _prune(cache: SceneCache, view: View) -> None:
    """Keep the KEEP most recently computed visibility results of the view; delete the others."""
    stages = cache.manifest()["stages"]
    mine = [(_finished(rec), name) for name, rec in stages.items() if name.startswith(f"visibility/{view.name}/")]
    for _, name in sorted(mine, reverse=True)[KEEP:]:
        files = [cache.scene_dir / rel for rel in stages[name].get("outputs", {})]
        cache.forget(name, files)


def _finished(rec: dict) -> float:
    try:
        return time.mktime(time.strptime(rec.get("finished", "")[:19], "%Y-%m-%dT%H:%M:%S"))
    except ValueError:
        return 0.0
