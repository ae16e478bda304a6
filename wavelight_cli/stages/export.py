"""`wavelight export`: the recovered (or a given) light in other tools' conventions -> out/export/."""

from __future__ import annotations

from pathlib import Path

from pipelines.errors import OptionError

from ..cache import Ran, SceneCache, Stage, run_stage
from ..console import Console
from ..outputs import write_json
from ..scene import SceneFiles, material_from_options, require, solved_light

VERSION = 6  # 6: a textured part as a bitmap (mitsuba/kd_<part>.exr, blender/base_<part>.exr), one light scale for all parts, material.json parts; 5: mitsuba/bsdf_<part>.xml per part (reflectance.json parts); 3: Mitsuba rows on its own grid (2H + 1), emitter.xml loadable by itself, blender/setup_world.py;
# 4: the fitted material too: mitsuba/bsdf.xml, blender/material.json + setup_material.py
FORMATS = ("mitsuba", "blender", "opengl")


def export_stage(scene: SceneFiles, formats: tuple[str, ...], light_path: Path | None, height: int | None,
                 face_size: int | None, console: Console, force: bool = False, lock_wait: float = 600.0,
                 material_path: Path | None = None):
    """The light (and the material: --material, else the one solve fitted, out/reflectance.json, when
    there is one) in each format's files under out/export/."""
    from pipelines.io import exports as ex
    from pipelines.io import images
    from pipelines.io.files import atomic_output
    from pipelines.light import cubemap

    if height is not None and not 8 <= height <= 8192:
        raise OptionError(f"--height must be 8..8192 rows, got {height}", None, "e.g. --height 256")
    if face_size is not None and (face_size < 2 or face_size > 4096 or face_size & (face_size - 1)):
        raise OptionError(f"--face-size must be a power of two from 2 to 4096, got {face_size}", None, "e.g. 64")
    if light_path is not None and height is not None:
        raise OptionError("--height applies to the recovered light; a --light file keeps its own rows", None,
                         "drop --height (or resample the file)")
    source = light_path if light_path is not None else scene.out / "coefficients.h5"
    require(source, "run wavelight solve first, or pass --light")
    if material_path is None and (scene.out / "reflectance.json").is_file():
        material_path = scene.out / "reflectance.json"
    material = material_from_options(material_path, None, None, None, None) if material_path is not None else None
    cache = SceneCache(scene.root)
    out = scene.out / "export"
    with cache.lock(lock_wait, console.say):
        upstream = {} if light_path is not None else {"solve": cache.key_of("solve") or "none"}
        stage = Stage("export", VERSION, {"formats": list(formats), "height": height, "face_size": face_size},
                      {"light": source, **({"material": material_path} if material_path is not None else {})},
                      upstream)

        def work(d) -> Ran:
            if light_path is not None:
                env = images.read_latlong(light_path)  # lat-long exports keep its resolution
                cube = cubemap.CubeMap(face_size or 64, hemisphere=False)
                # only the OpenGL faces need the cube map (its resampling: ~40 s at 64 x 64 faces)
                texels = cubemap.latlong_to_cube(env, cube) if "opengl" in formats else None
            else:
                texels, cube, _ = solved_light(scene)
                env = cubemap.cube_to_latlong(texels, cube, height or max(64, 4 * cube.resolution))
                if face_size is not None and face_size != cube.resolution:
                    target = cubemap.CubeMap(face_size, cube.hemisphere)
                    texels, cube = cubemap.resample_cube(texels, cube, target), target
            outputs: list[Path] = []
            parts = _parts(scene, material, material_path) if material is not None else []
            shared = ex.parts_light_scale(material, parts) if parts else None  # one light for every part
            mapping = ex.material_mapping(material, shared) if material is not None else None
            scale = mapping["light_scale"] if mapping else 1.0
            omega = cubemap.latlong_solid_angles(env.shape[0])[..., None]
            summary = {"source": "recovered" if light_path is None else str(light_path),
                       "energy_rgb": (env * omega).sum(axis=(0, 1)).tolist(), "latlong_height": env.shape[0],
                       "face_size": cube.resolution}
            if "mitsuba" in formats:
                outputs.append(images.write_exr(out / "mitsuba" / "light.exr", ex.to_mitsuba(env)))
                xml = out / "mitsuba" / "emitter.xml"
                with atomic_output(xml) as tmp:
                    tmp.write_text(ex.mitsuba_xml("light.exr", scale))
                outputs.append(xml)
                if material is not None:
                    bsdf = out / "mitsuba" / "bsdf.xml"
                    with atomic_output(bsdf) as tmp:
                        tmp.write_text(ex.mitsuba_bsdf_xml(material, light_scale=shared))
                    outputs.append(bsdf)
                    outputs += _part_bsdfs(out / "mitsuba", parts, scale, summary)
            if "blender" in formats:
                outputs.append(images.write_exr(out / "blender" / "light_equirect.exr", ex.to_blender(env)))
                script = out / "blender" / "setup_world.py"
                with atomic_output(script) as tmp:
                    tmp.write_text(ex.blender_world_script("light_equirect.exr", scale))
                outputs.append(script)
                if material is not None:
                    images_of = []
                    for part in parts:
                        name = None
                        if part.texture is not None:
                            name = f"base_{part.file_stem}.exr"
                            outputs.append(images.write_exr(out / "blender" / name,
                                                            ex.textured_images(part.material, part.texture, scale)[1]))
                        images_of.append((part, name))
                    outputs.append(write_json(out / "blender" / "material.json",
                                              ex.blender_material_description(material, shared, images_of)))
                    script = out / "blender" / "setup_material.py"
                    with atomic_output(script) as tmp:
                        tmp.write_text(ex.blender_material_script())
                    outputs.append(script)
            if "opengl" in formats:
                for name, face in ex.to_gl_faces(texels, cube).items():
                    outputs.append(images.write_exr(out / "opengl" / f"{name}.exr", face))
            listed = summary.pop("parts", None)
            if mapping is not None:
                summary["material"] = {
                    "source": cache.relative(material_path), "model": material.model,
                    "approximate": not mapping["exact"], "light_scale": scale, "notes": mapping["notes"]}
                if "mitsuba" in formats:
                    summary["material"]["mitsuba"] = {
                        "file": "mitsuba/bsdf.xml", "bsdf": mapping["mitsuba"]["type"], "exact": mapping["exact"],
                        "what": "the material as a Mitsuba 3 BSDF (mi.load_file, or paste into a <shape>)"}
                if "blender" in formats:
                    summary["material"]["blender"] = {
                        "files": ["blender/material.json", "blender/setup_material.py"], "exact": mapping["blender_exact"],
                        "what": "a Principled BSDF: its inputs and the settings in words (material.json); "
                                "setup_material.py makes it on the active object"}
                if listed:
                    summary["material"]["parts"] = listed
            else:
                summary["material"] = {"source": None, "note": "no material: run wavelight solve (out/reflectance.json) "
                                                               "or pass --material to export one"}
            outputs.append(write_json(out / "export.json", {
                **summary, "files": [cache.relative(p) for p in outputs],
                "what": {"mitsuba/light.exr, mitsuba/emitter.xml": "the light as Mitsuba 3's envmap",
                         "mitsuba/bsdf.xml": "the material as a Mitsuba 3 BSDF",
                         "mitsuba/bsdf_<part>.xml, mitsuba/kd_<part>.exr": "each part's BSDF (a textured part's "
                                                                           "diffuse parameter as a linear bitmap)",
                         "blender/base_<part>.exr": "a textured part's Base Color image (linear)",
                         "blender/light_equirect.exr, blender/setup_world.py": "the light as Blender's World",
                         "blender/material.json, blender/setup_material.py": "the material as a Principled BSDF",
                         "opengl/*.exr": "the light as OpenGL / three.js cube faces"},
                "conventions": "README: Relight, insert, export, report (export) and pipelines/io/exports.py"}))
            summary["line"] = (f"export: {', '.join(formats)} -> {cache.relative(out)}/ "
                               f"(energy {' '.join(f'{e:.4g}' for e in summary['energy_rgb'])}"
                               + (f"; material {material.model}: {'exact' if mapping['exact'] else 'approximate'} in "
                                  f"Mitsuba" if mapping is not None and ({"mitsuba", "blender"} & set(formats)) else "")
                               + ")")
            return Ran(outputs, summary)

        d = run_stage(cache, stage, console, force, work)
        rec = cache.record_of("export") or {}
    if "line" in rec.get("summary", {}):
        console.result(rec["summary"]["line"])
    return d


def _parts(scene: SceneFiles, material, material_path):
    """The parts of the solve's reflectance.json (pipelines.io.exports.part_exports), their textures
    from the scene's mesh as the solve read them; [] for one uniform material."""
    import json

    from pipelines.io import exports as ex
    from pipelines.io.scene_files import load_mesh
    from pipelines.model.parts import scene_parts

    try:
        refl = json.loads(Path(material_path).read_text()) if material_path is not None else {}
    except (OSError, ValueError):
        refl = {}
    listed = refl.get("parts") if isinstance(refl, dict) else None
    if not listed:
        return []
    sp = None
    if any(p.get("textured") for p in listed):
        o = refl.get("parts_options", {})
        sp = scene_parts(load_mesh(scene.mesh), scene.mesh, scene.root, o.get("texture", True),
                         o.get("texture_colour", False))
    return ex.part_exports(material, listed, sp)


def _part_bsdfs(folder: Path, parts, light_scale: float, summary: dict) -> list[Path]:
    """One Mitsuba BSDF per part (mitsuba/bsdf_<part>.xml): the scene's model with the part's colour,
    a textured part's as a linear bitmap (mitsuba/kd_<part>.exr: its texture times its diffuse
    parameter), all under the light scale they share. Records the parts in summary["parts"]."""
    from pipelines.io import exports as ex
    from pipelines.io import images
    from pipelines.io.files import atomic_output

    written, listed = [], []
    for p in parts:
        texture = None
        if p.texture is not None:
            texture = f"kd_{p.file_stem}.exr"
            written.append(images.write_exr(folder / texture, ex.textured_images(p.material, p.texture, light_scale)[0]))
            note = f"part {p.name}: its texture {p.texture_name} (linear, x its fitted scale) as {texture}"
        elif not p.exact:
            note = f"part {p.name}: APPROXIMATE: its mean colour over its surface (its vertex colours are not exported)"
        else:
            note = f"part {p.name}"
        path = folder / f"bsdf_{p.file_stem}.xml"
        with atomic_output(path) as tmp:
            tmp.write_text(ex.mitsuba_bsdf_xml(p.material, f"wavelight_{p.file_stem}", light_scale, texture, note))
        written.append(path)
        listed.append({"name": p.name, "file": f"mitsuba/{path.name}", "kd": list(p.material.kd),
                       "texture": p.texture_name, "bitmap": f"mitsuba/{texture}" if texture else None,
                       "scale": list(p.material.kd) if texture else None, "exact": p.exact})
    summary["parts"] = listed
    return written
