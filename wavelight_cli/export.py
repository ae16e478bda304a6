"""The export stage: the recovered (or a given) light in other tools' conventions -> out/export/."""

from __future__ import annotations

import time
from pathlib import Path


from pipelines.errors import InputError

from .cache import SceneCache, atomic_output, output_set, write_json_atomic
from .scenefiles import SceneFiles
from .stages import Console, _require

EXPORT_VERSION = 1
FORMATS = ("mitsuba", "blender", "opengl")


def export_stage(scene: SceneFiles, formats: tuple[str, ...], light_path: Path | None, height: int | None,
                 face_size: int | None, console: Console, force: bool = False, lock_wait: float = 600.0):
    from pipelines import cubemap, images
    from pipelines import exports as ex
    from pipelines import light as lt

    if height is not None and not 8 <= height <= 8192:
        raise InputError(f"--height must be 8..8192 rows, got {height}", None, "e.g. --height 256")
    if face_size is not None and (face_size < 2 or face_size > 4096 or face_size & (face_size - 1)):
        raise InputError(f"--face-size must be a power of two from 2 to 4096, got {face_size}", None, "e.g. 64")
    if light_path is not None and height is not None:
        raise InputError("--height applies to the recovered light; a --light file keeps its own rows", None,
                         "drop --height (or resample the file)")
    source = light_path if light_path is not None else scene.out / "coefficients.h5"
    _require(source, "light", "run wavelight solve first, or pass --light")
    cache = SceneCache(scene.root)
    with cache.lock(lock_wait, console.say):
        params = {"formats": list(formats), "height": height, "face_size": face_size}
        d = cache.plan("export", EXPORT_VERSION, params, {"light": source}, {}, force)
        console.decision(d)
        if not d.run:
            return d
        t0 = time.monotonic()
        if light_path is not None:
            env = images.read_latlong(light_path)  # lat-long exports keep its resolution
            cube = cubemap.CubeMap(face_size or 64, hemisphere=False)
            texels = cubemap.latlong_to_cube(env, cube)
        else:
            try:
                texels, cube, _ = lt.read_solution_light(source)
            except (OSError, ValueError, KeyError) as exc:
                raise InputError(f"cannot read the solved light ({exc})", source, "rerun wavelight solve --force") \
                    from None
            env = cubemap.cube_to_latlong(texels, cube, height or max(64, 4 * cube.resolution))
            if face_size is not None and face_size != cube.resolution:
                target = cubemap.CubeMap(face_size, cube.hemisphere)
                texels, cube = cubemap.resample_cube(texels, cube, target), target
        out = scene.out / "export"
        outputs: list[Path] = []
        omega = cubemap.latlong_solid_angles(env.shape[0])[..., None]
        summary = {"source": "recovered" if light_path is None else str(light_path),
                   "energy_rgb": (env * omega).sum(axis=(0, 1)).tolist(), "latlong_height": env.shape[0],
                   "face_size": cube.resolution}
        with output_set():  # the stage's files replace the old ones together, or not at all
            if "mitsuba" in formats:
                outputs.append(images.write_exr(out / "mitsuba" / "light.exr", ex.to_mitsuba(env)))
                xml = out / "mitsuba" / "emitter.xml"
                with atomic_output(xml) as tmp:
                    tmp.write_text(ex.mitsuba_xml("light.exr"))
                outputs.append(xml)
            if "blender" in formats:
                outputs.append(images.write_exr(out / "blender" / "light_equirect.exr", ex.to_blender(env)))
            if "opengl" in formats:
                for name, face in ex.to_gl_faces(texels, cube).items():
                    outputs.append(images.write_exr(out / "opengl" / f"{name}.exr", face))
            outputs.append(out / "export.json")
            write_json_atomic(outputs[-1], {**summary, "files": [cache.relative(p) for p in outputs[:-1]],
                                            "conventions": "see pipelines/exports.py and README (Exports)"})
        cache.record(d, outputs, time.monotonic() - t0, summary)
        console.result(f"export: {', '.join(formats)} -> {cache.relative(out)}/ "
                       f"(energy {' '.join(f'{e:.4g}' for e in summary['energy_rgb'])})")
    return d
