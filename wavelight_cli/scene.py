"""Where a scene folder keeps its files (README: Scene folder), the views of it, and loading the
photo, the materials and the solved light with clear errors."""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path

from pipelines.errors import InputError, OptionError, require_file

MAIN_VIEW = "main"  # the name of the scene folder's own photo among its views
VIEWS_DIR = "views"  # views/NAME/: more photos of the scene under the same light
VIEW_NAME = re.compile(r"[A-Za-z0-9_.-]+")
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
        from pipelines.io.scene_files import find_mesh

        return find_mesh(self.root)

    @property
    def out(self) -> Path:
        return self.root / "out"


def scene_folder(path: str | Path) -> SceneFiles:
    root = Path(path)
    if not root.is_dir():
        raise InputError("scene folder not found", root, "pass an existing folder with --scene/-s")
    return SceneFiles(root)


def require(path: Path | None, fix: str) -> Path:
    require_file(path, fix)
    return Path(path)


@dataclass(frozen=True)
class View:
    """A camera looking at the scene's mesh: the photo's own (camera.json, pose.json, mask.png), a
    photo of `views/NAME/`, or a camera without a photo (relight --view). Each view has its own
    visibility results in the cache, under `name` ("photo" for the main photo, "views-NAME" for
    views/NAME); `label` is the name users see ("main", "NAME")."""

    camera: Path
    pose: Path
    mask: Path | None = None
    name: str = "photo"
    label: str = MAIN_VIEW
    image: Path | None = None
    correspondences: Path | None = None
    folder: Path | None = None  # where the view's own files are (the scene folder for the main photo)

    def require_image(self) -> Path:
        if self.image is None:
            where = "scene folder" if self.label == MAIN_VIEW else "view's folder"
            raise InputError(f"no photo in the {where}", (self.folder or Path(".")) / "image.exr",
                             f"add the photo as one of {', '.join(IMAGE_NAMES)}")
        return self.image


def photo_view(scene: SceneFiles) -> View:
    return View(scene.camera, scene.pose, scene.mask, "photo", MAIN_VIEW, scene.image, scene.correspondences,
                scene.root)


def _find_image(folder: Path) -> Path | None:
    for name in IMAGE_NAMES:
        if (folder / name).is_file():
            return folder / name
    return None


def named_view(scene: SceneFiles, folder: Path) -> View:
    """The view of `views/NAME/`: its own camera.json or else the scene's, its pose.json (or the one
    register will write from its correspondences.csv), its mask.png if any."""
    name = folder.name
    if name == MAIN_VIEW or not VIEW_NAME.fullmatch(name):
        raise InputError(f"a view's folder name must be letters, digits, '_', '-' or '.', and not {MAIN_VIEW!r} "
                         "(the scene folder's own photo)", folder, "rename the folder")
    image = _find_image(folder)
    if image is None:
        raise InputError("a view without a photo", folder / "image.exr",
                         f"add the view's photo as one of {', '.join(IMAGE_NAMES)}, or remove the folder")
    own_camera = folder / "camera.json"
    pose, corr = folder / "pose.json", folder / "correspondences.csv"
    if not pose.is_file() and not corr.is_file():
        raise InputError("the view has neither pose.json nor correspondences.csv", pose,
                         "write the view's pose.json (world -> camera) by hand, or add its correspondences.csv "
                         "(u,v,x,y,z) and run wavelight register")
    mask = folder / "mask.png"
    return View(own_camera if own_camera.is_file() else scene.camera, pose, mask if mask.is_file() else None,
                f"views-{name}", name, image, corr, folder)


def scene_views(scene: SceneFiles, select: str | None = None, need_main: bool = True) -> list[View]:
    """The scene's photos: the main one (the scene folder's image) first, then views/NAME/ in name
    order; `select`: a comma-separated subset of their names (README: Scene folder), which must
    name the main photo when `need_main` (the light is solved with it)."""
    views = [photo_view(scene)]
    root = scene.root / VIEWS_DIR
    if root.is_dir():
        views += [named_view(scene, d) for d in sorted(root.iterdir()) if d.is_dir() and not d.name.startswith(".")]
    if select is None:
        return views
    names = [s.strip() for s in str(select).split(",") if s.strip()]
    known = {v.label: v for v in views}
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise OptionError(f"--views names {', '.join(unknown) or 'no view'}, but the scene's views are "
                          f"{', '.join(known)}", None, "name views by their folder under views/ (main: the scene "
                          "folder's own photo)")
    if need_main and MAIN_VIEW not in names:
        raise OptionError(f"--views {select} leaves out {MAIN_VIEW} (the scene folder's own photo)", None,
                          f"add {MAIN_VIEW}, e.g. --views {MAIN_VIEW},{names[0]}")
    return [v for v in views if v.label in dict.fromkeys(names)]


def view_named(scene: SceneFiles, name: str, option: str = "--view") -> View:
    """One of the scene's photos by its name (a folder under views/, or main), registered: its pose.json
    must exist. An unknown name is an OptionError naming `option`."""
    views = {v.label: v for v in scene_views(scene)}
    if name not in views:
        raise OptionError(f"{option} {name}: the scene has no view of that name (its views: {', '.join(views)})",
                          None, "name a folder under views/, or main (the scene folder's own photo)")
    view = views[name]
    require(view.pose, "run wavelight register (it writes the view's pose.json from its correspondences.csv)")
    return view


def view_gain(scene: SceneFiles, view: View) -> float:
    """The exposure of one of the scene's photos relative to the main one, as the last solve fitted it
    (solve_report.json's views.NAME.exposure; `solve --view-exposure`): the recovered light renders
    that photo at its own exposure times this. 1 for the main photo, a view the solve did not use,
    or no solve report."""
    import json

    if view.image is None or view.label == MAIN_VIEW:
        return 1.0
    try:
        report = json.loads((scene.out / "solve_report.json").read_text())
        return float(report["views"][view.label]["exposure"])
    except (OSError, ValueError, KeyError, TypeError):
        return 1.0


def other_view(scene: SceneFiles, pose: Path, camera: Path | None = None) -> View:
    """A view named by its files' contents (the same files are the same view)."""
    camera = require(camera or scene.camera, "pass --view-camera or write camera.json")
    pose = require(pose, "pass the new view's pose.json with --view")
    digest = hashlib.sha256(camera.read_bytes() + b"\0" + pose.read_bytes()).hexdigest()[:10]
    return View(camera, pose, None, f"view-{digest}")


_LOADED: dict = {}  # the mesh read last (by path, size and mtime), its ray casters and the views' centre-ray hits


def scene_mesh(path: Path):
    """`load_mesh(path)`, kept for the next call in this process while the file is unchanged: a
    `solve` that runs its visibility stages first reads the mesh once."""
    from pipelines.io.scene_files import load_mesh

    path = Path(path)
    try:
        st = path.stat()
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    except OSError:
        return load_mesh(path)  # (its error names the file)
    if _LOADED.get("key") != key:
        _LOADED.clear()
        _LOADED.update(key=key, mesh=load_mesh(path), backends={})
    return _LOADED["mesh"]


def scene_backend(mesh, name: str = "embree"):
    """A ray caster for `mesh`, built once per mesh `scene_mesh` keeps."""
    from pipelines.geometry import raycast

    if _LOADED.get("mesh") is not mesh:
        return raycast.make_backend(mesh, name)
    kept = _LOADED["backends"]
    if name not in kept:
        kept[name] = raycast.make_backend(mesh, name)
    return kept[name]


def keep_hits(camera, pose, backend, hits) -> None:
    """Remember the (H, W) centre-ray hits that the visibility stage cast for this camera, pose and
    ray caster (of the kept mesh), for `mesh_coverage` later in this process."""
    if _LOADED.get("backends") and any(b is backend for b in _LOADED["backends"].values()):
        kept = [k for k in _LOADED.setdefault("hits", []) if not (k[0] is backend and k[1] == camera and _same_pose(
            k[2], pose))]
        _LOADED["hits"] = kept[-7:] + [(backend, camera, pose, hits)]


def _same_pose(a, b) -> bool:
    import numpy as np

    return np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)


def mesh_coverage(view: View, camera, backend):
    """(H, W) bool: the pixels of `view` whose centre ray hits the mesh and that its mask keeps
    (what a render covers when no edge margin is left out; `outputs.view_image` fills that margin).
    The hits the visibility stage cast in this process are not cast again (`keep_hits`)."""
    from pipelines.geometry.camera import mesh_hits
    from pipelines.io import images
    from pipelines.io.scene_files import read_pose

    pose = read_pose(view.pose)
    kept = [h for b, c, p, h in _LOADED.get("hits", []) if b is backend and c == camera and _same_pose(p, pose)]
    cover = kept[-1].copy() if kept else mesh_hits(camera, pose, backend)
    if view.mask is not None:
        mask = images.read_mask(view.mask)
        if mask.shape == cover.shape:
            cover &= mask
    return cover


def load_photo(scene: SceneFiles, camera, linear: bool | None = None):
    """(path, `LoadedImage`) of the scene's photo, checked against the camera's size. NaN/Inf
    pixels that mask.png leaves out are not refused (they read as 0)."""

    return load_view_photo(photo_view(scene), camera, linear)


def load_view_photo(view: View, camera, linear: bool | None = None):
    """`load_photo` of any view with a photo: (path, `LoadedImage`), checked against its camera."""
    from pipelines.io import images

    path = view.require_image()
    img = images.read_image(path, linear=linear, mask=view.mask)
    if (img.width, img.height) != (camera.width, camera.height):
        cam = view.camera.name if view.camera.parent == path.parent else str(view.camera)
        fix = "or fix camera.json" if view.label == MAIN_VIEW else (
            "or fix its camera.json" if cam == "camera.json" else "or give the view its own camera.json")
        raise InputError(f"image is {img.width}x{img.height} but {cam} says {camera.width}x{camera.height}",
                         path, f"use the photo the camera was calibrated for, {fix}")
    return path, img


# the keys a material file may name (ours, reflectance.json's, the scenes' truth, Mitsuba's plastics)
MATERIAL_KEYS = ("model", "type", "kd", "ks", "n", "shininess", "alpha", "roughness", "distribution", "ior",
                 "int_ior", "ext_ior", "diffuse_reflectance", "specular_reflectance", "nonlinear", "alpha_u",
                 "alpha_v")
# the other keys of the files a material comes from (reflectance.json's report, a truth's formula)
MATERIAL_FILE_KEYS = ("format", "mode", "decision", "candidates", "uncertainty", "uncertainty_note",
                      "kd_colour_observable", "chosen_round", "rounds", "seconds", "ks_over_kd", "scale_ambiguity",
                      "parts", "parts_options", "reference_part", "formula")


def _check_material_keys(data: dict, path) -> None:
    """A material file names a material (one of MATERIAL_KEYS: another JSON file, e.g. camera.json,
    names none) and no key one typo away from one (`shinyness` would leave n at its default)."""
    import difflib

    if not any(k in data for k in MATERIAL_KEYS):
        raise InputError("names no material (none of model, kd, ks, n, alpha, ...)", path,
                         'give a material file, e.g. {"model": "lambert", "kd": [0.8, 0.8, 0.8]}')
    for key in data:
        known = key in MATERIAL_KEYS or key in MATERIAL_FILE_KEYS
        near = [] if known else difflib.get_close_matches(str(key), MATERIAL_KEYS, 1, 0.8)
        if near:
            raise InputError(f"unknown key {key!r}", path, f"did you mean {near[0]!r}? (README: the reflectance fit)")


def material_from_options(material_file: Path | None, model: str | None, kd, ks, shininess,
                          given: set | None = None, alpha=None, ior=None, distribution=None):
    """The material of --material/--model/--kd/--ks/--shininess (and plastic's --alpha, --ior,
    --distribution); `given` (if a set) receives the names of the fields the user set ('model', 'kd',
    'ks', 'n', 'alpha', 'ior', 'distribution', 'file')."""
    from pipelines.model.materials import Material

    data: dict = {}
    if material_file is not None:
        if not Path(material_file).exists() or Path(material_file).is_dir():  # (a pipe is read as it is)
            require(material_file, "check the path of the material JSON")
        try:
            data = json.loads(Path(material_file).read_text())
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read material JSON ({exc})", material_file, "fix the file") from None
        if not isinstance(data, dict):
            raise InputError("a material must be a JSON object", material_file,
                             'write e.g. {"model": "lambert", "kd": [0.8, 0.8, 0.8]}')
        if isinstance(data.get("wavelight_material"), dict):  # the Blender export's material.json
            data = dict(data["wavelight_material"])
        _check_material_keys(data, material_file)
    if model is not None:
        data["model"] = model
        data.pop("type", None)
    if kd is not None:
        data["kd"] = list(kd)
    if ks is not None:
        data["ks"] = list(ks)
    if shininess is not None:
        data["n"] = shininess
    for name, value in (("alpha", alpha), ("ior", ior), ("distribution", distribution)):
        if value is not None:
            data[name] = value
            data.pop("roughness" if name == "alpha" else "", None)
    if given is not None:
        given.update(k for k in ("alpha", "ior", "distribution") if k in data or (k == "alpha" and "roughness" in data))
        given.update(k for k in ("kd", "ks") if k in data)
        given.update({"model"} if "model" in data or "type" in data else set())
        given.update({"n"} if "n" in data or "shininess" in data else set())
        given.update({"file"} if material_file is not None else set())
    try:
        material = Material.from_json(data)
        extra = {k: v for k, v in (("alpha", alpha), ("ior", ior), ("distribution", distribution)) if v is not None}
        if extra and material.model != "plastic":  # plastic's options for a fit's start (solve --reflectance)
            from dataclasses import replace

            Material.from_json({"model": "plastic", **extra})  # (checked as a plastic material would be)
            material = replace(material, extra={**material.extra, "plastic_start": extra})
        return material
    except (ValueError, TypeError) as exc:
        if material_file is None:  # the values are the options' (--kd, --ks, --shininess)
            raise OptionError(str(exc), None, "fix --kd / --ks / --shininess / --alpha / --ior") from None
        raise InputError(str(exc), material_file, "fix the material values") from None


def solved_light(scene: SceneFiles):
    """(texel light, its cube map, the file's attributes) of the light `solve` wrote."""
    from pipelines.io.light_file import read_solution_light

    path = require(scene.out / "coefficients.h5", "run wavelight solve first (or pass --light)")
    try:
        return read_solution_light(path)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"cannot read the solved light ({str(exc).splitlines()[0]})", path,
                         "rerun wavelight solve --force") from None


def scene_albedo(scene: SceneFiles, material_path, mesh, camera, pose):
    """The per-pixel albedo function of the solve's parts and textures (`model.parts.view_albedo`),
    when the material is a reflectance.json that lists parts; else None (one uniform material)."""
    from pipelines.model.parts import view_albedo

    if material_path is None or Path(material_path).suffix.lower() != ".json":
        return None
    try:
        data = json.loads(Path(material_path).read_text())
    except (OSError, ValueError):
        return None  # the material reader has already refused a broken file
    return view_albedo(data if isinstance(data, dict) else None, mesh, scene.mesh, scene.root, camera, pose)
