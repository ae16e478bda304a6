"""Several materials in one scene and known albedo textures (issue 19, items 1, 2 and 4).

A mesh may carry parts (OBJ `usemtl` groups with their `.mtl`, glTF primitives' materials, a PLY's face
labels; or `materials.toml` in the scene folder naming them): each part has a start colour (the `.mtl` Kd,
glTF's baseColorFactor, the toml's `kd`, else 1) and possibly a known relative albedo over its
surface (`map_Kd` / baseColorTexture, sampled at each pixel's surface point, sRGB-decoded and
filtered to the pixel's footprint by a mip pyramid; or vertex colours).

Every quantity here is computed per used pixel from that pixel's surface sample (its face and
position; the footprint from the pixel's own camera), never from an image grid, so the samples of
several views can simply be concatenated.

Per pixel the diffuse albedo is  kd_j = material.kd x base_j x scale[part_j]  (per channel):
base_j the texture (or vertex colour, or the part's start colour), scale a per-part factor the solve
fits in closed form given the light (`fit_scales`), alternating with the light. The reference part's
scale stays 1: light x albedo is known only as a product, so only the ratios between parts are
observable.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError

UV_SLACK = 0.25  # UVs may reach this far outside [0, 1] (seams, a little wrap) ...
UV_OUTSIDE_SHARE = 0.01  # ... on at most this share of a textured part's face corners
FIT_MODES = ("reference", "colour", "scale")


@dataclass(frozen=True)
class PartsOptions:
    """solve's --single-material (parts False), --no-texture (texture False), --texture-colour,
    --shared-ks (the glossy parts' one ks: no specular weight of their own)."""

    parts: bool = True
    texture: bool = True
    texture_colour: bool = False
    shared_ks: bool = False

    def cache_params(self) -> dict:
        out = {"parts": self.parts, "texture": self.texture, "texture_colour": self.texture_colour}
        if self.shared_ks:
            out["shared_ks"] = True
        return out


def parts_files(mesh_path: Path, scene_dir: Path) -> dict:
    """The files the parts are read from, for a stage's cache inputs (name -> path, None: absent):
    materials.toml, the OBJ's .mtl and the textures it and the toml name (missing ones are absent
    here and refused when the parts are read)."""
    mesh_path, scene_dir = Path(mesh_path), Path(scene_dir)
    out = {"materials.toml": scene_dir / "materials.toml" if (scene_dir / "materials.toml").is_file() else None}
    mtl = _mtl_of(mesh_path)
    names = []
    if mtl is not None:  # (named by the mesh: None when it is not there)
        out["mtl"] = mtl if mtl.is_file() else None
    if mtl is not None and mtl.is_file():
        names += [(mtl.parent, m["map_Kd"]) for m in _parse_mtl(mtl).values() if m.get("map_Kd")]
    if out["materials.toml"] is not None:
        try:
            toml = _read_toml(out["materials.toml"])
        except InputError:
            toml = {}
        names += [(scene_dir, p["texture"]) for p in toml.get("parts", {}).values() if isinstance(p.get("texture"), str)]
    for folder, name in names:
        path = folder / name
        out[f"texture {name}"] = path if path.is_file() else None
    return out


@dataclass
class Texture:
    """A texture as a mip pyramid of linear RGB (level 0 the image, each next a 2 x 2 box mean)."""

    path: str  # the file (or "embedded" for a glTF image)
    levels: list = field(default_factory=list)  # [(H, W, 3) float32]

    @classmethod
    def from_pixels(cls, pixels: np.ndarray, path: str) -> "Texture":
        levels = [np.ascontiguousarray(pixels, np.float32)]
        while min(levels[-1].shape[:2]) > 1:
            a = levels[-1]
            h, w = (a.shape[0] // 2) * 2, (a.shape[1] // 2) * 2
            a = a[:h, :w]
            levels.append(0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]))
        return cls(path, levels)

    @property
    def size(self) -> tuple[int, int]:
        return self.levels[0].shape[1], self.levels[0].shape[0]  # (width, height)

    def bilinear(self, uv: np.ndarray, level: int) -> np.ndarray:
        """(n, 3) the level's bilinear lookup at UVs (OBJ / glTF convention: v = 0 at the image's
        bottom row for OBJ; the caller flips glTF), wrapping around (repeat)."""
        img = self.levels[level]
        h, w = img.shape[:2]
        x = uv[:, 0] * w - 0.5
        y = (1.0 - uv[:, 1]) * h - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        x1, y1 = (x0 + 1) % w, (y0 + 1) % h
        x0, y0 = x0 % w, y0 % h
        return ((img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy)
                + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy)

    def sample(self, uv: np.ndarray, texel_area: np.ndarray) -> np.ndarray:
        """(n, 3) trilinear lookup: the mip level whose texels match the footprint's area (in level-0
        texels), blended between the two nearest levels."""
        lod = np.clip(0.5 * np.log2(np.maximum(texel_area, 1e-12)), 0.0, len(self.levels) - 1)
        lo = np.floor(lod).astype(np.int64)
        out = np.empty((len(uv), 3))
        for level in np.unique(lo):
            sel = lo == level
            f = (lod[sel] - level)[:, None]
            a = self.bilinear(uv[sel], int(level))
            hi = min(int(level) + 1, len(self.levels) - 1)
            out[sel] = a if hi == level else a * (1 - f) + self.bilinear(uv[sel], hi) * f
        return out


@dataclass
class Part:
    name: str
    kd: tuple  # the start colour (linear RGB)
    kd_source: str  # where it came from
    texture: Texture | None = None
    vertex_colours: bool = False
    faces: int = 0
    fit: str = "colour"  # reference (kept), colour (an RGB scale), scale (one grey scale)
    specular: bool | None = None  # materials.toml `specular`: the scene's lobe on this part (True), not (False),
    # or decided by the solve (None: `--reflectance auto` tests each part, `glossy_parts`)


@dataclass
class SceneParts:
    """The scene's parts: per-face part index and UVs (the mesh's), the parts, the reference part
    and the files they were read from (for the cache)."""

    parts: list
    face_part: np.ndarray
    face_uv: np.ndarray | None
    face_colour: np.ndarray | None
    reference: int
    files: list  # Paths the parts depend on (mtl, textures, materials.toml)
    reference_source: str = ""

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.parts]

    def fingerprint(self) -> str:
        h = hashlib.sha256()
        for f in self.files:
            h.update(str(Path(f).name).encode())
            h.update(Path(f).read_bytes())
        return h.hexdigest()


def _parse_mtl(path: Path) -> dict:
    """{name: {"kd": (3,) or None, "map_Kd": file name or None}} of a .mtl file."""
    out, cur = {}, None
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read it ({exc.strerror})", path, "check its permissions") from None
    for line in text.splitlines():
        tok = line.strip().split()
        if not tok or tok[0].startswith("#"):
            continue
        key = tok[0]
        if key == "newmtl":
            cur = " ".join(tok[1:])
            out[cur] = {"kd": None, "map_Kd": None}
        elif cur is None:
            continue
        elif key == "Kd" and len(tok) >= 4:
            try:
                out[cur]["kd"] = tuple(float(v) for v in tok[1:4])
            except ValueError:
                raise InputError(f"material '{cur}': Kd is not 3 numbers ({line.strip()!r})", path,
                                 "fix that line") from None
        elif key == "map_Kd" and len(tok) >= 2:
            out[cur]["map_Kd"] = tok[-1]  # options (-s, -o, ...) come before the file name
    return out


def _mtl_of(mesh_path: Path) -> Path | None:
    if mesh_path.suffix.lower() != ".obj":
        return None
    with open(mesh_path, "rb") as f:
        for line in f:
            if line.startswith(b"mtllib"):
                name = line.split(None, 1)[1].decode(errors="replace").strip()
                return mesh_path.parent / name
    return None


def _read_toml(path: Path) -> dict:
    import tomllib

    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid TOML ({exc})", path, "fix the syntax (README: Scene folder)") from None
    unknown = set(data) - {"reference", "parts"}
    if unknown:
        raise InputError(f"unknown key(s) {sorted(unknown)}", path, "use `reference = \"NAME\"` and [parts.NAME] tables")
    parts = data.get("parts", {})
    if not isinstance(parts, dict) or not all(isinstance(v, dict) for v in parts.values()):
        raise InputError("`parts` must hold one [parts.NAME] table per part", path, "see README: Scene folder")
    for name, p in parts.items():
        bad = set(p) - {"kd", "texture", "fit", "specular"}
        if bad:
            raise InputError(f"[parts.{name}]: unknown key(s) {sorted(bad)}", path, "use kd, texture, fit and specular")
        if "specular" in p and not isinstance(p["specular"], bool):
            raise InputError(f"[parts.{name}]: specular must be true or false, got {p['specular']!r}", path,
                             "specular = false: a matte part (no lobe); true: the scene's lobe; leave it out: decided "
                             "by the solve")
        if "kd" in p:
            kd = p["kd"]
            kd = [kd] * 3 if isinstance(kd, (int, float)) and not isinstance(kd, bool) else kd
            if not (isinstance(kd, list) and len(kd) == 3 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                                 and v >= 0 for v in kd)):
                raise InputError(f"[parts.{name}]: kd must be 3 non-negative numbers, got {p['kd']!r}", path,
                                 "e.g. kd = [0.5, 0.4, 0.3]")
            p["kd"] = tuple(float(v) for v in kd)
        if "texture" in p and not (p["texture"] is False or isinstance(p["texture"], str)):
            raise InputError(f"[parts.{name}]: texture must be a file name or false", path, "fix the value")
        if "fit" in p and p["fit"] not in FIT_MODES:
            raise InputError(f"[parts.{name}]: fit must be one of {FIT_MODES}, got {p['fit']!r}", path, "fix the value")
    if "reference" in data and not isinstance(data["reference"], str):
        raise InputError("reference must be a part's name", path, "e.g. reference = \"body\"")
    return data


def _load_texture(path: Path, part: str, referrer: Path) -> Texture:
    from ..io.images import read_image

    if not path.is_file():
        raise InputError(f"part '{part}' names the texture {path.name}, which does not exist", referrer,
                         f"put {path.name} next to {referrer.name}, fix the texture's name there, or pass --no-texture")
    try:
        img = read_image(path)
    except InputError as exc:
        raise InputError(f"part '{part}': cannot read its texture ({exc.problem})", path,
                         "re-save it as PNG, JPEG or EXR, or pass --no-texture") from None
    return Texture.from_pixels(img.pixels, str(path))


def _embedded_texture(image, part: str, mesh_path: Path) -> Texture:
    from ..io.images import srgb_to_linear

    try:
        px = np.asarray(image.convert("RGB"), np.float64) / 255.0
    except Exception as exc:  # PIL raises many kinds for a broken embedded image
        raise InputError(f"part '{part}': cannot read its embedded texture ({exc})", mesh_path,
                         "re-export the mesh with a PNG or JPEG texture, or pass --no-texture") from None
    return Texture.from_pixels(srgb_to_linear(px).astype(np.float32), f"{mesh_path.name} (embedded)")


def scene_parts(mesh, mesh_path: Path, scene_dir: Path, use_texture: bool = True, texture_colour: bool = False
                ) -> SceneParts | None:
    """The scene's parts (None: one uniform material, as without parts). `use_texture` False ignores
    every texture and vertex colour (--no-texture); `texture_colour` fits an RGB colour on top of
    each texture instead of one grey scale (--texture-colour)."""
    mesh_path, scene_dir = Path(mesh_path), Path(scene_dir)
    toml_path = scene_dir / "materials.toml"
    toml = _read_toml(toml_path) if toml_path.is_file() else {}
    names = list(mesh.part_names)
    if not names:
        if toml.get("parts"):
            raise InputError(f"names parts {sorted(toml['parts'])}, but {mesh_path.name} has no material groups",
                             toml_path, f"give {mesh_path.name} `usemtl` groups (OBJ), materials (glTF) or a face "
                                        "label property (PLY), or remove materials.toml")
        return None
    files: list[Path] = []
    if toml:
        files.append(toml_path)
        unknown = sorted(set(toml.get("parts", {})) - set(names))
        if unknown:
            raise InputError(f"names part(s) {unknown} that {mesh_path.name} does not have (it has {names})",
                             toml_path, "use the mesh's material names")
    mtl_path = _mtl_of(mesh_path)
    mtl = {}
    if mtl_path is not None:
        if not mtl_path.is_file():
            raise InputError(f"names the material library {mtl_path.name}, which does not exist", mesh_path,
                             f"put {mtl_path.name} next to {mesh_path.name}, or remove its mtllib line")
        files.append(mtl_path)
        mtl = _parse_mtl(mtl_path)
    counts = np.bincount(mesh.face_part, minlength=len(names))
    parts = []
    for k, name in enumerate(names):
        given = toml.get("parts", {}).get(name, {})
        info = mesh.part_materials[k] if k < len(mesh.part_materials) else {"kd": None, "image": None}
        m = mtl.get(name, {})
        kd, src = (1.0, 1.0, 1.0), "default (1)"
        if info.get("kd") is not None:
            kd, src = tuple(info["kd"]), "glTF baseColorFactor"
        if m.get("kd") is not None:
            kd, src = tuple(m["kd"]), f"{mtl_path.name} Kd"
        if "kd" in given:
            kd, src = given["kd"], "materials.toml kd"
        part = Part(name, kd, src, faces=int(counts[k]), specular=given.get("specular"))
        if use_texture:
            tex_name = given.get("texture", m.get("map_Kd"))
            referrer = toml_path if "texture" in given else mtl_path
            if tex_name:
                tex_path = (toml_path.parent if "texture" in given else mtl_path.parent) / tex_name
                part.texture = _load_texture(tex_path, name, referrer)
                files.append(tex_path)
            elif tex_name is None and info.get("image") is not None:
                part.texture = _embedded_texture(info["image"], name, mesh_path)
            elif tex_name is None and mesh.face_colour is not None and np.isfinite(
                    mesh.face_colour[mesh.face_part == k]).all():
                part.vertex_colours = True
            if part.texture is not None:
                _check_uvs(mesh, k, name, mesh_path, part.texture)
        textured = part.texture is not None or part.vertex_colours
        part.fit = given.get("fit", "colour" if (texture_colour or not textured) else "scale")
        parts.append(part)
    if len(parts) == 1 and parts[0].texture is None and not parts[0].vertex_colours:
        return None  # one plain part: the uniform model, exactly as without parts
    ref_name = toml.get("reference")
    if ref_name is not None:
        if ref_name not in names:
            raise InputError(f"reference = {ref_name!r} is not one of the mesh's parts {names}", toml_path,
                             "name one of them")
        reference, why = names.index(ref_name), "materials.toml reference"
    else:
        reference, why = None, ""
    sp = SceneParts(parts, np.asarray(mesh.face_part), mesh.face_uv, mesh.face_colour, -1, files)
    sp.reference, sp.reference_source = (reference, why) if reference is not None else (-1, "")
    return sp


def _check_uvs(mesh, k: int, name: str, mesh_path: Path, texture: Texture) -> None:
    sel = mesh.face_part == k
    uv = None if mesh.face_uv is None else mesh.face_uv[sel].reshape(-1, 2)
    if uv is None or not np.isfinite(uv).all():
        raise InputError(f"part '{name}' has a texture but its faces have no UV coordinates (vt)", mesh_path,
                         "export the mesh with its UVs, or pass --no-texture")
    outside = ((uv < -UV_SLACK) | (uv > 1 + UV_SLACK)).any(axis=1).mean()
    if outside > UV_OUTSIDE_SHARE:
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        raise InputError(f"part '{name}': {100 * outside:.0f} % of its UVs lie far outside the texture "
                         f"{Path(texture.path).name} (u {lo[0]:.3g}..{hi[0]:.3g}, v {lo[1]:.3g}..{hi[1]:.3g}; "
                         f"[0, 1] covers it): these UVs do not belong to it", mesh_path,
                         "re-export the mesh with the texture's UVs, or pass --no-texture")
    if np.ptp(uv, axis=0).max() <= 0:
        raise InputError(f"part '{name}': every UV is the same point, so the texture shows one colour", mesh_path,
                         "re-export the mesh with the texture's UVs, or pass --no-texture")


# -- per pixel ------------------------------------------------------------------------------------
def pixel_footprint(samples, camera, pose) -> np.ndarray:
    """(P,) the surface area each pixel sees, from its own camera: solid angle cos^3(a) / (fx fy)
    at distance d on a facet tilted by the view angle: d^2 cos^3(a) / (fx fy |n . v|)."""
    R, t = np.asarray(pose.R, float), np.asarray(pose.t, float)
    centre = -R.T @ t
    d = samples.position - centre[None, :]
    dist = np.linalg.norm(d, axis=1)
    cos_a = np.clip((d @ R[2]) / np.maximum(dist, 1e-300), 1e-3, 1.0)
    nv = np.abs(np.einsum("pk,pk->p", samples.geometric_normal, samples.view))
    return dist**2 * cos_a**3 / (camera.fx * camera.fy * np.maximum(nv, 0.05))


def _barycentric(mesh_vertices: np.ndarray, tri: np.ndarray, points: np.ndarray) -> np.ndarray:
    a, b, c = (mesh_vertices[tri[:, i]] for i in range(3))
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = np.maximum(d00 * d11 - d01 * d01, 1e-300)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary = np.stack([1 - v - w, v, w], axis=1)
    return np.clip(bary, 0.0, 1.0) / np.clip(bary, 0.0, 1.0).sum(1, keepdims=True).clip(1e-12)


@dataclass
class PixelAlbedo:
    """The used pixels' known relative albedo: base (P, 3), part (P,) and the fitted per-part
    scales (parts, 3); kd_j = base_j x scales[part_j] (the material's kd multiplies it)."""

    base: np.ndarray
    part: np.ndarray
    scales: np.ndarray
    parts: SceneParts
    glossy: np.ndarray | None = None  # (parts,) bool: which parts have the specular term (None: all)
    glossy_source: list | None = None  # per part, how that was decided
    # (parts,) each glossy part's specular weight: its ks is the material's x this (`fit_scales`); None: 1
    ks_scales: np.ndarray | None = None
    own_ks: bool = True  # False (--shared-ks): the weights stay 1, the glossy parts share the material's ks

    def values(self, rows=None) -> np.ndarray:
        sl = slice(None) if rows is None else rows
        return self.base[sl] * self.scales[self.part[sl]]

    def part_ks(self) -> np.ndarray:
        """(parts,) the factor on the material's ks of each part: 0 for matte parts, else its weight."""
        g = np.ones(len(self.parts.parts)) if self.glossy is None else np.asarray(self.glossy, float)
        return g if self.ks_scales is None else g * self.ks_scales

    def glossy_weight(self, rows=None) -> np.ndarray | None:
        """(P,) 1 for the pixels of glossy parts, 0 for matte ones (which transport rows carry the
        lobe); None when every part has the specular term."""
        if self.glossy is None or np.all(self.glossy):
            return None
        sl = slice(None) if rows is None else rows
        return self.glossy[self.part[sl]].astype(np.float32)

    def specular_weight(self, rows=None) -> np.ndarray | None:
        """(P,) each pixel's factor on ks (`render.transport`'s `specular`): 0 for the pixels of matte
        parts, its part's specular weight for glossy ones; None when every part has the term at 1."""
        g = self.part_ks()
        if np.all(g == 1):
            return None
        sl = slice(None) if rows is None else rows
        return g[self.part[sl]].astype(np.float32)


def pixel_base(sp: SceneParts, mesh, face: np.ndarray, position: np.ndarray, footprint: np.ndarray):
    """(base (P, 3), part (P,)) for pixels given by their surface sample (face, position) and the
    surface area they see (`pixel_footprint`)."""
    face = np.asarray(face, np.int64)
    part = sp.face_part[face].astype(np.int64)
    base = np.empty((len(face), 3))
    for k, p in enumerate(sp.parts):
        sel = np.flatnonzero(part == k)
        if not len(sel):
            continue
        if p.texture is None and not p.vertex_colours:
            base[sel] = p.kd
            continue
        f = face[sel]
        bary = _barycentric(mesh.vertices, mesh.faces[f], position[sel])
        if p.vertex_colours:
            base[sel] = np.einsum("pk,pkc->pc", bary, sp.face_colour[f])
            continue
        uv_tri = sp.face_uv[f]
        uv = np.einsum("pk,pkc->pc", bary, uv_tri)
        # footprint in texels: the face's UV area per surface area x the pixel's surface area
        e1, e2 = uv_tri[:, 1] - uv_tri[:, 0], uv_tri[:, 2] - uv_tri[:, 0]
        uv_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        v = mesh.vertices[mesh.faces[f]]
        area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
        w, h = p.texture.size
        texel_area = footprint[sel] * uv_area / np.maximum(area, 1e-300) * w * h
        base[sel] = p.texture.sample(uv, texel_area)
    return base, part


def part_mean_base(sp: SceneParts, mesh, k: int) -> np.ndarray:
    """(3,) the area-weighted mean of part k's base albedo over its surface (6 points per face)."""
    p = sp.parts[k]
    if p.texture is None and not p.vertex_colours:
        return np.asarray(p.kd, float)
    f = np.flatnonzero(sp.face_part == k)
    v = mesh.vertices[mesh.faces[f]]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    pts = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3],
                    [0.4, 0.4, 0.2], [0.4, 0.2, 0.4], [0.2, 0.4, 0.4]])
    total = np.zeros(3)
    for b in pts:
        if p.vertex_colours:
            val = np.einsum("k,pkc->pc", b, sp.face_colour[f])
        else:
            val = p.texture.bilinear(np.einsum("k,pkc->pc", b, sp.face_uv[f]), 0)
        total += (area[:, None] * val).sum(axis=0)
    return total / (len(pts) * max(area.sum(), 1e-300))


def choose_reference(sp: SceneParts, part: np.ndarray) -> None:
    """The reference part, unless materials.toml named it: the textured part seen by the most used
    pixels, else the part seen by the most (ties: the first)."""
    if sp.reference >= 0:
        sp.parts[sp.reference].fit = "reference"
        return
    seen = np.bincount(part, minlength=len(sp.parts))
    textured = [k for k, p in enumerate(sp.parts) if (p.texture is not None or p.vertex_colours) and seen[k]]
    pool = textured or [k for k in range(len(sp.parts)) if seen[k]] or [0]
    sp.reference = max(pool, key=lambda k: (seen[k], -k))
    sp.reference_source = ("the textured part seen by the most pixels" if textured else
                           "the part seen by the most pixels")
    sp.parts[sp.reference].fit = "reference"


def fit_scales(albedo: PixelAlbedo, rows: np.ndarray, weights: np.ndarray, diffuse: np.ndarray,
               specular: np.ndarray | None, photo: np.ndarray, ks: bool = False):
    """New per-part scales (parts, 3) given the light: for each part, per channel (fit "colour") or
    shared (fit "scale"), the least-squares factor k of  k x base x scale x diffuse + specular = photo
    over the given rows (weights w). `diffuse`: (n, 3) material.kd x D L of the rows (kd = 1
    albedo), `specular` the ks S L term (each row's part weight applied) or None. The reference part
    keeps its scale.

    The light and a part's scale trade off freely but for the other parts' pixels, which makes plain
    alternation creep (the light fits the part with the most pixels whatever its scale). So the
    light's own per-channel factor t is fitted too, on the reference part's pixels, and each other
    part's factor is taken relative to it: the step moves along that slow direction at once (the
    next light solve then takes the factor t).

    With `ks` (and a specular term), each glossy part's specular weight (`PixelAlbedo.ks_scales`) is
    fitted jointly with its factor (a factor h on its lobe), but for the part whose lobe carries the
    most signal (its weight stays: the material's ks is its own), and kept where the part's rows
    cannot tell it (h's standard error above KS_PRECISION: its highlight out of view). A step moves
    the weight by h within [KS_STEP_MIN, KS_STEP_MAX] (the light moves with it; a part whose rows
    tell h ~ 0, a matte part under a given model, goes towards 0 over the rounds). Returns
    (scales, ks_scales) then."""
    p = albedo.values(rows) * diffuse
    part = albedo.part[rows]
    new = albedo.scales.copy()
    w = np.asarray(weights, float)
    n_parts = len(albedo.parts.parts)
    g = albedo.part_ks()
    spec = None if specular is None else np.asarray(specular, float)
    fit_ks = ks and spec is not None
    r_all = photo - (0.0 if spec is None else spec)
    sel_of = {k: np.flatnonzero((part == k) & (w > 0)) for k in range(n_parts)}
    sel_of = {k: v for k, v in sel_of.items() if len(v)}
    lobe_ref = -1
    if fit_ks:  # the glossy part whose lobe carries the most signal keeps its weight
        energy = {k: float((w[v, None] * spec[v] ** 2).sum()) for k, v in sel_of.items() if g[k] > 0}
        lobe_ref = max(energy, key=energy.get) if energy else -1
    new_ks = None if albedo.ks_scales is None else np.array(albedo.ks_scales, float)
    if fit_ks and new_ks is None:
        new_ks = np.ones(n_parts)

    def solve(k: int, columns: list, sel: np.ndarray):
        """Weighted least squares of part k's rows over `columns` ((n, 3) each; a column without
        signal keeps 1) and, when its lobe is fitted, a factor h on it: (coefficients, h or None)."""
        sw = np.sqrt(w[sel] / max(float(w[sel].mean()), 1e-300))[:, None]  # (mean 1: the errors' scale)
        X = np.stack([(c * sw).T.ravel() for c in columns], axis=1)
        live = np.sqrt((X**2).sum(axis=0)) > 0
        x = np.ones(len(columns))
        if fit_ks and k != lobe_ref and g[k] > 0:
            M = np.column_stack([X[:, live], (spec[sel] * sw).T.ravel()])
            y = (photo[sel] * sw).T.ravel()
            norm = np.sqrt(np.maximum((M**2).sum(axis=0), 1e-300))
            coef, *_ = np.linalg.lstsq(M / norm, y, rcond=None)
            coef /= norm
            resid = y - M @ coef
            dof = max(len(y) - M.shape[1], 1)
            try:
                cov = np.linalg.inv((M / norm).T @ (M / norm))[-1, -1] / norm[-1] ** 2
                sd = float(np.sqrt(max(cov * (resid @ resid) / dof, 0.0)))
            except np.linalg.LinAlgError:
                sd = float("inf")
            if sd <= KS_PRECISION:  # (else the rows cannot tell the part's lobe: its weight stays)
                x[live] = coef[:-1]
                return x, float(coef[-1])
        y = (r_all[sel] * sw).T.ravel()
        if live.any():
            x[live] = np.linalg.lstsq(X[:, live], y, rcond=None)[0]
        return x, None

    def channel_columns(base: np.ndarray) -> list:
        cols = []
        for c in range(3):
            col = np.zeros_like(base)
            col[:, c] = base[:, c]
            cols.append(col)
        return cols

    ref = albedo.parts.reference
    t = np.ones(3)
    if ref in sel_of:
        x, h = solve(ref, channel_columns(p[sel_of[ref]]), sel_of[ref])
        t = np.maximum(np.where(np.isfinite(x), x, 1.0), 1e-6)  # (the light's factor, not the part's)
        if h is not None:
            new_ks[ref] = new_ks[ref] * np.clip(h, KS_STEP_MIN, KS_STEP_MAX)
    for k, pt in enumerate(albedo.parts.parts):
        if k not in sel_of or k == ref:
            continue
        sel = sel_of[k]
        if pt.fit == "reference":
            continue
        tp = p[sel] * t[None, :]
        if pt.fit == "scale":  # one grey factor on t x p
            x, h = solve(k, [tp], sel)
            factor = np.full(3, float(x[0]))
        else:
            x, h = solve(k, channel_columns(tp), sel)
            factor = np.asarray(x, float)
        new[k] = albedo.scales[k] * np.maximum(np.where(np.isfinite(factor), factor, 1.0), 1e-6)
        if h is not None:
            new_ks[k] = new_ks[k] * np.clip(h, KS_STEP_MIN, KS_STEP_MAX)
    if not ks:
        return new
    return new, new_ks


KS_PRECISION = 0.1  # a part's own specular weight moves where its rows tell the factor on it this well
KS_STEP_MIN, KS_STEP_MAX = 0.25, 4.0  # ... by at most this factor per step (the light moves with it)


GLOSSY_SIGMAS = 3.0  # a part keeps the lobe when its own ks is this many sigmas above 0 ...
GLOSSY_MIN_ROWS = 30  # ... on at least this many probe rows (fewer: it keeps the lobe, undecided)


def declared_glossy(sp: SceneParts) -> tuple[np.ndarray | None, list | None]:
    """The parts' specular term as materials.toml declares it (`specular`; undeclared: on, until the
    solve decides): ((parts,) bool or None when all are on, per part its source or None)."""
    glossy = np.array([p.specular is not False for p in sp.parts])
    sources = ["materials.toml" if p.specular is not None else None for p in sp.parts]
    if glossy.all() and not any(sources):
        return None, None
    return glossy, sources


def glossy_parts(sp: SceneParts, part: np.ndarray, diffuse: np.ndarray, lobe: np.ndarray, photo: np.ndarray,
                 min_gain: float, plain: np.ndarray | None = None) -> tuple[np.ndarray, list, list]:
    """Which parts have a specular term: `--reflectance auto`'s test of each part, on the probe's rows
    (the Lambertian light fixed, the lobe's width as the probe fitted it).

    diffuse, lobe, photo : (rows, 3) the rows' base shading (kd = 1), lobe shading (ks = 1) and photo
        (each row scaled by sqrt(its weight)); part : (rows,) each row's part.
    Per part, kd (RGB) and one grey ks >= 0 are fitted to its rows alone (NNLS); the part is glossy
    when ks exceeds GLOSSY_SIGMAS standard errors and the lobe lowers the part's error by `min_gain`
    against kd alone (on `plain`, the rows' Lambertian shading, when the glossy base differs from it:
    a coating's, which a matte part has not). A part declared in materials.toml (`specular`) keeps
    its declaration; one with fewer than GLOSSY_MIN_ROWS rows keeps the lobe (its pixels cannot
    tell). Returns the (parts,) flags, each part's source, and per part the numbers."""
    from scipy.optimize import nnls

    glossy = np.ones(len(sp.parts), bool)
    sources, info = [], []
    for k, p in enumerate(sp.parts):
        sel = np.flatnonzero(part == k)
        rec = {"name": p.name, "rows": int(len(sel))}
        if p.specular is not None:
            glossy[k] = p.specular
            sources.append("materials.toml")
        elif len(sel) < GLOSSY_MIN_ROWS:
            sources.append(f"too few probe rows to tell ({len(sel)}): kept")
        else:
            m = len(sel)
            X = np.zeros((3 * m, 4))
            for c in range(3):
                X[c * m:(c + 1) * m, c] = diffuse[sel, c]
                X[c * m:(c + 1) * m, 3] = lobe[sel, c]
            y = photo[sel].T.ravel()
            scale = np.sqrt((X**2).sum(axis=0))
            scale[scale == 0] = 1.0
            x, r_with = nnls(X / scale, y, maxiter=200)
            x /= scale
            if plain is None:
                _, r_without = nnls(X[:, :3] / scale[:3], y, maxiter=200)
            else:
                Xp = np.zeros((3 * m, 3))
                for c in range(3):
                    Xp[c * m:(c + 1) * m, c] = plain[sel, c]
                norm = np.sqrt((Xp**2).sum(axis=0))
                norm[norm == 0] = 1.0
                _, r_without = nnls(Xp / norm, y, maxiter=200)
            dof = max(3 * m - 4, 1)
            try:
                cov = np.linalg.inv(X.T @ X) * (r_with**2 / dof)
                sd = float(np.sqrt(max(cov[3, 3], 0.0)))
            except np.linalg.LinAlgError:
                sd = float("inf")
            gain = 1.0 - r_with / r_without if r_without > 0 else 0.0
            glossy[k] = bool(x[3] > GLOSSY_SIGMAS * sd and gain >= min_gain)
            rec.update(ks=float(x[3]), ks_sigma=sd, gain=float(gain))
            sources.append(f"auto: its own ks {x[3]:.3g} +- {sd:.2g}, lowers its error by {100 * gain:.1f} %")
        rec["specular"] = bool(glossy[k])
        info.append(rec)
    return glossy, sources, info


def parts_summary(albedo: PixelAlbedo, mesh, material_kd, pixels_per_part=None, specular_model: bool = True,
                  material_ks=None) -> list[dict]:
    """reflectance.json's `parts`: each part's name, faces, kd (mean over its surface), texture, the
    fitted scale, its fit mode, its albedo relative to the reference part's, whether it has the
    scene's specular term (`specular_model` False: the scene's model has none) and its specular
    weight (the factor on the material's ks, `material_ks`: its own ks)."""
    sp = albedo.parts
    kd = np.asarray(material_kd, float)
    means = [kd * albedo.scales[k] * part_mean_base(sp, mesh, k) for k in range(len(sp.parts))]
    ref = means[sp.reference]
    seen = np.bincount(albedo.part, minlength=len(sp.parts)) if pixels_per_part is None else pixels_per_part
    weight = albedo.part_ks()
    out = []
    for k, p in enumerate(sp.parts):
        glossy = specular_model and (albedo.glossy is None or bool(albedo.glossy[k]))
        lobe = {"specular_weight": float(weight[k]) if glossy else 0.0}
        if glossy and material_ks is not None:
            lobe["ks"] = (np.asarray(material_ks, float) * weight[k]).tolist()
        tex = p.texture.path if p.texture is not None else ("vertex colours" if p.vertex_colours else None)
        out.append({"name": p.name, "faces": p.faces, "pixels": int(seen[k]), "fit": p.fit,
                    "kd": means[k].tolist(), "kd_start": list(p.kd), "kd_start_source": p.kd_source,
                    "texture": None if tex is None else Path(tex).name if p.texture is not None else tex,
                    "textured": tex is not None, "scale": (kd * albedo.scales[k]).tolist(),
                    "albedo_scale": albedo.scales[k].tolist(),
                    "relative_to_reference": (means[k] / np.where(ref > 0, ref, 1.0)).tolist(),
                    "specular": glossy, **lobe,
                    "specular_decided_by": "the scene's model has no specular term" if not specular_model else (
                        (albedo.glossy_source or [None] * len(sp.parts))[k] or (
                            "materials.toml" if p.specular is not None else "every part (one model for the scene)"))})
    return out


def view_albedo(reflectance: dict | None, mesh, mesh_path: Path, scene_dir: Path, camera, pose):
    """For relight / insert: a function (samples -> (P, 3) relative albedo) from a solve's
    reflectance.json `parts` (their fitted `albedo_scale`, by name) and the mesh's parts and textures,
    each pixel filtered to its footprint in the given camera; None when the solve used one uniform
    material."""
    if not reflectance or not reflectance.get("parts"):
        return None
    o = reflectance.get("parts_options", {})
    sp = scene_parts(mesh, mesh_path, scene_dir, o.get("texture", True), o.get("texture_colour", False))
    if sp is None:
        return None
    fitted = {p["name"]: p.get("albedo_scale", [1.0, 1.0, 1.0]) for p in reflectance["parts"]}
    scales = np.array([fitted.get(n, [1.0, 1.0, 1.0]) for n in sp.names], float)
    on = {p["name"]: float(p.get("specular_weight", 1.0)) if p.get("specular", True) else 0.0
          for p in reflectance["parts"]}
    glossy = np.array([on.get(n, 1.0) for n in sp.names])
    return ViewShading(sp, mesh, scales, None if np.all(glossy == 1) else glossy, camera, pose)


@dataclass
class ViewShading:
    """A solve's parts seen from a camera (relight, insert): called on pixel samples it gives their
    relative albedo (P, 3); `specular(samples)` their specular weights (`render.transport`: 0 for a
    matte part, else the part's factor on ks), None when every part has the lobe at weight 1."""

    sp: SceneParts
    mesh: object
    scales: np.ndarray
    glossy: np.ndarray | None
    camera: object
    pose: object

    def __call__(self, samples) -> np.ndarray:
        base, part = pixel_base(self.sp, self.mesh, samples.face, samples.position,
                                pixel_footprint(samples, self.camera, self.pose))
        return base * self.scales[part]

    def specular(self, samples) -> np.ndarray | None:
        if self.glossy is None:
            return None
        return self.glossy[self.sp.face_part[np.asarray(samples.face, np.int64)]].astype(np.float32)


# -- the per-part factors with the light re-solved: variable projection on a fixed tree -------------
def bounded_search(f, x0: float, span: float, evaluations: int) -> float:
    """The minimum of f over [x0 - span, x0 + span] (x0 when f(x0) is below the minimum found), to
    the precision `evaluations` steps of golden-section search reach (the interval shrunk by
    0.618^evaluations).

    Brent's bounded method (golden sections where a parabola through three points is not trusted)
    reaches it in about half the evaluations on these smooth objectives, each an NNLS solve."""
    from scipy.optimize import minimize_scalar

    g = (np.sqrt(5.0) - 1.0) / 2.0
    tol = 0.5 * (2.0 * span) * g ** evaluations
    res = minimize_scalar(f, bounds=(x0 - span, x0 + span), method="bounded",
                          options={"xatol": tol, "maxiter": 2 * evaluations + 10})
    x = float(res.x)
    return x if float(res.fun) <= f(x0) else x0


def varpro_scales(albedo: PixelAlbedo, systems: list, max_cycles: int = 3, span: float = 2.0,
                  evaluations: int = 24) -> np.ndarray:
    """Per-part factors that minimise the photo's residual with the light re-solved for each (a
    Lambertian light on a fixed set of leaves, >= 0): the variable projection of the bilinear
    problem, which plain alternation only creeps towards (the light trades a part's colour against
    the directions that part sees).

    systems : per part q, (G (C, k, k), h (k, C), bb (C,)): the leaf-space normal equations of that
        part's rows with kd = material.kd x base (factor 1). Channel c's system at factors s is
        (sum_q s_qc^2 G_qc, sum_q s_qc h_qc), solved by NNLS; each non-reference part's factor is
        found by a bounded search in log s (per channel for fit "colour", one shared factor
        for "scale"), part after part, for up to `max_cycles` cycles.
    """
    return varpro_factors(systems, albedo.scales, [p.fit for p in albedo.parts.parts], max_cycles, span, evaluations)


def varpro_factors(systems: list, factors: np.ndarray, modes: list, max_cycles: int = 3, span: float = 2.0,
                   evaluations: int = 24) -> np.ndarray:
    """`varpro_scales` for any groups of rows: per group q its system (or None) and a factor
    (factors (groups, C)) multiplying its rows' prediction, held ("reference"), one grey factor
    ("scale") or one per channel ("colour") by `modes[q]`. Also what fits several photos'
    exposures (`controllers.views.fit_exposures`: a view's rows are its group)."""
    from ..light.nnls import nnls_gram

    scales = np.array(factors, np.float64)
    present = [q for q, s in enumerate(systems) if s is not None]
    C = scales.shape[1]
    free = [None] * C

    def objective(c: int, s: np.ndarray) -> float:
        G = sum(s[q, c] ** 2 * systems[q][0][c] for q in present)
        h = sum(s[q, c] * systems[q][1][:, c] for q in present)
        bb = sum(systems[q][2][c] for q in present)
        r = nnls_gram(G, h, initial_free=free[c])
        free[c] = r.x > 0
        return float(bb + 2.0 * r.objective)

    def search(f, x0: float) -> float:
        return bounded_search(f, x0, span, evaluations)

    movable = [q for q in present if modes[q] != "reference"]
    for _ in range(max_cycles if len(movable) > 1 else 1):
        before = scales.copy()
        for q in movable:
            if modes[q] == "scale":
                def f(x, q=q):
                    s = scales.copy()
                    s[q] = np.exp(x)
                    return sum(objective(c, s) for c in range(C))
                scales[q] = np.exp(search(f, float(np.log(scales[q]).mean())))
            else:
                for c in range(C):
                    def f(x, q=q, c=c):
                        s = scales.copy()
                        s[q, c] = np.exp(x)
                        return objective(c, s)
                    scales[q, c] = np.exp(search(f, float(np.log(scales[q, c]))))
        if np.max(np.abs(scales / before - 1)) < 1e-4:
            break
    return scales
