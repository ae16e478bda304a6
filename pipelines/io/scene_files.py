"""Scene files (DESIGN §2): camera.json, pose.json, correspondences.csv and the mesh.

Readers validate everything a later stage relies on and raise `InputError` naming the file, the
problem and the fix. They return plain frozen dataclasses of numpy arrays.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from ..errors import InputError, require_file
from ..geometry.camera import Camera, Pose
from ..geometry.mesh import Mesh

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")


def _load_json(path: Path, what: str) -> dict:
    require_file(path, f"create the {what} file (see README: scene folder)")
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", path, "fix the syntax") from None
    except OSError as exc:
        raise InputError(f"cannot read it ({exc.strerror})", path, "check its permissions") from None
    if not isinstance(data, dict):
        raise InputError("expected a JSON object", path, "see README for the file format")
    return data


def _number(data: dict, key: str, path: Path, positive: bool = False) -> float:
    if key not in data:
        raise InputError(f"missing field '{key}'", path, "see README for the file format")
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"field '{key}' must be a number, got {value!r}", path, "fix the value")
    try:
        number = float(value)  # a JSON integer beyond float64 overflows
    except OverflowError:
        number = math.inf
    if not math.isfinite(number) or (positive and number <= 0):
        need = "a positive finite number" if positive else "finite"
        shown = (value if math.isfinite(number) or not isinstance(value, int)
                 else f"an integer of {len(str(value))} digits")
        raise InputError(f"field '{key}' must be {need}, got {shown!r}", path, "fix the value")
    return number


def _array(data: dict, key: str, shape: tuple[int, ...], path: Path) -> np.ndarray:
    if key not in data:
        raise InputError(f"missing field '{key}'", path, "see README for the file format")
    try:
        arr = np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"field '{key}' must be numbers of shape {shape}", path, "fix the value") from None
    if arr.shape != shape:
        raise InputError(f"field '{key}' has shape {arr.shape}, expected {shape}", path, "fix the value")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"field '{key}' has non-finite values", path, "fix the value")
    return arr


MAX_FIELD_OF_VIEW = 175.0  # degrees, across the image: a camera.json beyond it has its focal length wrong


def read_camera(path: str | Path) -> Camera:
    path = Path(path)
    data = _load_json(path, "camera.json")
    width, height = _number(data, "width", path, True), _number(data, "height", path, True)
    if width != int(width) or height != int(height):
        raise InputError("width and height must be whole numbers of pixels", path, "fix the values")
    dist = data.get("dist", [0.0] * 5)
    dist_arr = _array({"dist": dist}, "dist", (len(dist),) if isinstance(dist, list) else (5,), path)
    if dist_arr.size not in (4, 5, 8, 12, 14):
        raise InputError(f"field 'dist' has {dist_arr.size} coefficients, expected 5 (k1, k2, p1, p2, k3)",
                         path, "fix the value")
    dist5 = np.zeros(5)
    dist5[: min(5, dist_arr.size)] = dist_arr[:5]
    known = {"width", "height", "fx", "fy", "cx", "cy", "dist"}
    fx, fy = _number(data, "fx", path, True), _number(data, "fy", path, True)
    for key, f, size in (("fx", fx, width), ("fy", fy, height)):
        fov = 2.0 * np.degrees(np.arctan(0.5 * size / f))
        if fov > MAX_FIELD_OF_VIEW:  # (fx 0.5 for 500: the rays fan out sideways, the solve is nonsense)
            raise InputError(f"{key} = {f:g} px gives a {fov:.1f} deg field of view over {size:g} pixels (a pinhole "
                             f"camera's is below {MAX_FIELD_OF_VIEW:g} deg)", path,
                             "give the focal length in pixels (about the image width for a normal lens), "
                             "or rerun wavelight calibrate")
    return Camera(int(width), int(height), fx, fy,
                  _number(data, "cx", path), _number(data, "cy", path), tuple(float(x) for x in dist5),
                  extra={k: v for k, v in data.items() if k not in known})


def read_pose(path: str | Path) -> Pose:
    path = Path(path)
    data = _load_json(path, "pose.json")
    R = _array(data, "R", (3, 3), path)
    t = _array(data, "t", (3,), path)
    ortho_err = np.abs(R @ R.T - np.eye(3)).max()
    if ortho_err > 1e-4 or np.linalg.det(R) < 0:
        problem = (f"R is not a rotation (|R Rt - I| = {ortho_err:.2g})" if ortho_err > 1e-4
                   else "R is a reflection (det < 0)")
        raise InputError(problem, path, "write an orthonormal R with det +1 (or rerun wavelight register)")
    # Re-orthonormalise the small residue so that downstream geometry is exact.
    u, _, vt = np.linalg.svd(R)
    known = {"R", "t"}
    return Pose(u @ vt, t, extra={k: v for k, v in data.items() if k not in known})


CSV_HEADER = ["u", "v", "x", "y", "z"]


def _csv_text(path: Path) -> str:
    """The file's text: UTF-8 with or without a byte-order mark (what spreadsheets save), or
    UTF-16 with one (Excel's "Unicode text")."""
    raw = path.read_bytes()
    return raw.decode("utf-16") if raw.startswith((b"\xff\xfe", b"\xfe\xff")) else raw.decode("utf-8-sig")


def read_correspondences(path: str | Path, min_points: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Read `u,v,x,y,z` rows -> (uv (n, 2), xyz (n, 3)) float64.

    As spreadsheets save it too: a byte-order mark, CRLF line ends, blank lines, and `;` (with
    decimal commas) or tab separators, which the header line tells."""
    path = Path(path)
    require_file(path, "create correspondences.csv with header u,v,x,y,z")
    try:
        lines = _csv_text(path).splitlines()
        first = next((ln for ln in lines if ln.strip(" \t,;")), "")
        delimiter = next((d for d in (",", ";", "\t")
                          if [c.strip().lower() for c in next(csv.reader([first], delimiter=d), [])] == CSV_HEADER),
                         ",")
        reader = csv.reader(lines, delimiter=delimiter)
        # (file line number, cells) of the rows that are not blank
        rows = [(reader.line_num, r) for r in reader if r and any(c.strip() for c in r)]
    except (UnicodeDecodeError, csv.Error) as exc:  # csv.Error: e.g. an unclosed quote swallowing the file
        what = "not a text CSV file" if isinstance(exc, UnicodeDecodeError) else f"not valid CSV ({exc})"
        raise InputError(what, path, "save it as plain CSV with header u,v,x,y,z") from None
    except OSError as exc:
        raise InputError(f"cannot read it ({exc.strerror})", path, "check its permissions") from None
    header = [c.strip().lower() for c in rows[0][1]] if rows else []
    if header != CSV_HEADER:
        raise InputError(f"header must be 'u,v,x,y,z', got {','.join(header) or 'nothing'!r}", path,
                         "fix the first line")
    values = []
    for lineno, row in rows[1:]:
        if len(row) != 5:
            raise InputError(f"line {lineno} has {len(row)} cells, expected 5", path, "fix that line")
        try:
            vals = [float(c.replace(",", ".") if delimiter == ";" else c) for c in row]
        except ValueError:
            raise InputError(f"line {lineno} has a non-numeric cell", path, "fix that line") from None
        if not all(math.isfinite(v) for v in vals):
            raise InputError(f"line {lineno} has a non-finite value", path, "fix that line")
        values.append(vals)
    arr = np.asarray(values, dtype=np.float64).reshape(-1, 5)
    if len(np.unique(arr, axis=0)) != len(arr):
        raise InputError("duplicate rows", path, "remove the repeated correspondences")
    if len(arr) < min_points:
        raise InputError(f"{len(arr)} correspondences, at least {min_points} are needed", path,
                         "click more 2D-3D point pairs")
    return arr[:, :2], arr[:, 2:]


def find_mesh(scene_dir: Path) -> Path:
    """The scene's mesh file: mesh.<ext> for the supported extensions."""
    found = [scene_dir / f"mesh{ext}" for ext in MESH_SUFFIXES if (scene_dir / f"mesh{ext}").is_file()]
    if not found:
        raise InputError("no mesh file", scene_dir / "mesh.obj",
                         f"put the geometry in the scene folder as mesh{{{','.join(MESH_SUFFIXES)}}}")
    return found[0]


def load_mesh(path: str | Path) -> Mesh:
    """Load a mesh (a plain one directly, `plain_mesh`, else with trimesh); a multi-part file
    (scene) becomes one mesh.

    Vertex normals from the file are kept as shading normals (else area-weighted face normals).
    Degenerate (zero-area) and duplicate faces are removed, and OBJ polygons split into triangles,
    with a note each.
    """
    from .plain_mesh import read_plain

    path = Path(path)
    require_file(path, "check the mesh path")
    plain = read_plain(path)
    if plain is None:
        vertices, faces, normals, (names, face_part, face_uv, face_colour, materials) = _trimesh_load(path)
    else:  # (no parts, UVs or colours: one uniform part)
        (vertices, faces, normals), names, face_part, face_uv, face_colour, materials = plain, (), None, None, None, ()
        if not np.all(np.isfinite(vertices)):
            raise InputError("mesh has NaN or infinite vertex coordinates", path, "repair the mesh")
    notes = []
    if plain is None and path.suffix.lower() == ".obj":  # the loader splits polygons into triangles silently: say so
        with open(path, "rb") as f:
            polygons = sum(1 for line in f if line.startswith(b"f ") and len(line.split()) > 4)
        if polygons:
            notes.append(f"split {polygons} polygons of more than 3 corners into triangles")
    v = vertices[faces]
    area2 = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    scale = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    degenerate = area2 <= (1e-12 * scale) ** 2
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    duplicate = np.ones(len(faces), dtype=bool)
    duplicate[first] = False
    drop = degenerate | duplicate
    if drop.all():
        raise InputError("every triangle of the mesh is degenerate", path, "repair the mesh")
    if degenerate.any():
        notes.append(f"removed {int(degenerate.sum())} zero-area faces")
    if (duplicate & ~degenerate).any():
        notes.append(f"removed {int((duplicate & ~degenerate).sum())} duplicate faces")
    faces = faces[~drop]
    if face_part is not None:
        face_part = face_part[~drop]
        face_uv = None if face_uv is None else face_uv[~drop]
        face_colour = None if face_colour is None else face_colour[~drop]
    bad_n = ~np.all(np.isfinite(normals), axis=1) | (np.linalg.norm(normals, axis=1) < 0.5)
    if bad_n.any():
        import trimesh

        normals = np.array(trimesh.Trimesh(vertices, faces, process=False).vertex_normals, dtype=np.float64)
        flat = ~np.all(np.isfinite(normals), axis=1) | (np.linalg.norm(normals, axis=1) < 0.5)
        if flat.any():  # faces around the vertex cancel (a sheet folded onto itself): take one face's normal
            v = vertices[faces]
            fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            first = np.full(len(vertices), -1)
            first[faces[::-1].ravel()] = np.repeat(np.arange(len(faces))[::-1], 3)
            normals[flat] = np.where(first[flat, None] >= 0, fn[first[flat]], [0.0, 0.0, 1.0])
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)
    return Mesh(vertices, faces, normals, tuple(notes), names, face_part, face_uv, face_colour, materials)


def _trimesh_load(path: Path):
    """(vertices, faces, vertex normals, `_file_parts`) of any mesh file trimesh reads."""
    import trimesh

    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many types for malformed files
        # an ImportError here is trimesh reaching for an optional text-encoding detector on binary junk
        msg = ("unrecognised content" if isinstance(exc, ImportError) or not str(exc)
               else str(exc).splitlines()[0])
        raise InputError(f"cannot read mesh ({msg})", path, "re-export it as OBJ, PLY, GLB or STL") from None
    # A scene (multi-part file) becomes one mesh; each part keeps the normals its file gives
    # (trimesh's force="mesh" would drop them and recompute normals from the faces).
    parts = [loaded] if isinstance(loaded, trimesh.Trimesh) else (
        [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if isinstance(loaded, trimesh.Scene) else [])
    parts = [m for m in parts if len(m.faces)]
    if not parts:
        raise InputError("mesh has no triangles", path, "export the geometry as a triangle mesh")
    vertices = np.concatenate([np.asarray(m.vertices, dtype=np.float64) for m in parts])
    offsets = np.cumsum([0] + [len(m.vertices) for m in parts[:-1]])
    faces = np.concatenate([np.asarray(m.faces, dtype=np.int64) + o for m, o in zip(parts, offsets)])
    if not np.all(np.isfinite(vertices)):
        raise InputError("mesh has NaN or infinite vertex coordinates", path, "repair the mesh")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"a face refers to vertex {int(faces.max() if faces.max() >= len(vertices) else faces.min())}"
                         f" of {len(vertices)}", path, "repair or re-export the mesh")
    normals = np.concatenate([np.asarray(m.vertex_normals, dtype=np.float64) for m in parts])
    # a PLY with UVs but no `comment TextureFile` gets a grey placeholder image from trimesh: not a texture
    images = path.suffix.lower() != ".ply" or _ply_names_texture(path)
    return vertices, faces, normals, _file_parts(parts, faces, images)


def _file_parts(parts: list, faces: np.ndarray, images: bool = True):
    """The parts the file carries, from trimesh's geometries (one per OBJ `usemtl` group or glTF
    primitive; a PLY's face labels, `PLY_LABELS`, split a geometry into one part per value): (names,
    face part index, face-corner UVs, face-corner linear vertex colours, what the file says of each
    part's material: {"kd", "image", "source"}). All empty / None when the file names no material,
    has no face labels and has no UVs or vertex colours (one uniform part: today's model). `images`
    False: the file names no texture (its materials' images are the loader's placeholders)."""
    from .images import srgb_to_linear

    names: list[str] = []
    materials: list[dict] = []
    per_face, uvs, colours = [], [], []
    any_uv = any_colour = False
    labelled = False
    for k, m in enumerate(parts):
        visual = getattr(m, "visual", None)
        mat = getattr(visual, "material", None)
        info = {"kd": None, "image": None, "source": ""}
        if mat is not None:
            if hasattr(mat, "baseColorFactor") or hasattr(mat, "baseColorTexture"):  # glTF PBR
                f = getattr(mat, "baseColorFactor", None)
                if f is not None:  # glTF's factor is linear; trimesh may hold it as uint8
                    f = np.asarray(f)
                    f = f[:3] / 255.0 if f.dtype.kind in "ui" else f[:3].astype(float)
                    info["kd"] = tuple(float(v) for v in f)
                if getattr(mat, "baseColorTexture", None) is not None:
                    info["image"], info["source"] = mat.baseColorTexture, "glTF baseColorTexture"
            elif images and getattr(mat, "image", None) is not None:
                info["image"], info["source"] = mat.image, "texture"
        labels = _ply_face_labels(m)
        if labels is None:
            label_names = [getattr(mat, "name", None) or m.metadata.get("name") or f"part{k}"]
        else:  # a PLY's face labels: one part per value, named <property>_<value>, each with the file's texture
            labelled = True
            prop, values = labels
            label_names = [f"{prop}_{int(v)}" for v in np.unique(values)]
        for name in label_names:
            if name not in names:
                names.append(name)
                materials.append(dict(info))
        if labels is None:
            per_face.append(np.full(len(m.faces), names.index(label_names[0]), np.int32))
        else:
            unique = np.unique(values)
            per_face.append(np.array([names.index(n) for n in label_names], np.int32)[np.searchsorted(unique, values)])
        uv = getattr(visual, "uv", None)
        f = np.asarray(m.faces, np.int64)
        if uv is not None and len(uv) == len(m.vertices):
            uvs.append(np.asarray(uv, np.float64)[f])
            any_uv = True
        else:
            uvs.append(np.full((len(f), 3, 2), np.nan))
        vc = getattr(visual, "vertex_colors", None) if getattr(visual, "kind", None) == "vertex" else None
        if vc is not None and len(vc) == len(m.vertices):
            colours.append(srgb_to_linear(np.asarray(vc, np.float64)[:, :3] / 255.0)[f])
            any_colour = True
        else:
            colours.append(np.full((len(f), 3, 3), np.nan))
    named = any(getattr(getattr(getattr(m, "visual", None), "material", None), "name", None) for m in parts)
    if not (named or labelled or any_uv or any_colour):
        return (), None, None, None, ()
    return (tuple(names), np.concatenate(per_face), np.concatenate(uvs) if any_uv else None,
            np.concatenate(colours) if any_colour else None, tuple(materials))


PLY_LABELS = ("label", "labels", "material", "material_index", "material_id", "part", "part_id", "segment",
              "segment_id", "object", "object_id", "object_index", "group", "group_id")  # face properties read as parts


def _ply_face_labels(m) -> tuple[str, np.ndarray] | None:
    """A PLY's face labels: the first integer face property named as in PLY_LABELS (trimesh keeps a
    PLY's face properties in metadata['_ply_raw']), as (name, (faces,) int64), or None."""
    raw = (getattr(m, "metadata", None) or {}).get("_ply_raw") or {}
    data = (raw.get("face") or {}).get("data")
    fields = getattr(getattr(data, "dtype", None), "names", None) or ()
    for prop in PLY_LABELS:
        name = next((f for f in fields if f.lower() == prop), None)
        if name is None:
            continue
        values = np.asarray(data[name]).ravel()
        if values.dtype.kind not in "iu" or len(values) != len(m.faces):
            continue
        return prop, values.astype(np.int64)
    return None


def _ply_names_texture(path: Path) -> bool:
    """Whether a PLY's header names a texture (`comment TextureFile NAME`, as trimesh reads it)."""
    with open(path, "rb") as f:
        for _ in range(10000):
            line = f.readline()
            if not line or line.strip() == b"end_header":
                return False
            if b"texturefile" in line.lower():
                return True
    return False
