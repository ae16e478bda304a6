"""The light in other tools' conventions, each with the lookup that tool does, so that an export
can be checked by reading it back the way that tool reads it.

Our exchange format (DESIGN §2): lat-long, row 0 = zenith, theta = pi (r + 1/2) / H from +Z,
phi = 2 pi (c + 1/2) / W from +X towards +Y; world +Z up.

- Mitsuba 3 `envmap`: its local frame is +Y up; a direction v (local) reads the image at
  u = atan2(v.x, -v.z) / 2pi (wrapped to [0, 1)), v = acos(v.y) / pi, bilinearly, with column c at
  u = (c + 1/2) / W (wrapping) but row r at v = r / (H - 1): its first and last rows sit on the
  poles, not at pixel centres (src/emitters/envmap.cpp: uv.x -= 0.5 / W; uv *= (W, H - 1)). Our
  image as it is would be read up to half a row towards the poles (0.6 deg at 50 deg from the
  zenith on a 64-row map; a glossy sphere 1.9 % off). So the export has 2H + 1 rows: row 2r + 1 is
  our row r (at its centre theta, exactly), row 2r our edge between rows r - 1 and r (their mean;
  the poles repeat rows 0 and H - 1). Mitsuba then reads our radiance exactly at our pixel centres
  and interpolates between them as Blender's Linear does. With the emitter's to_world =
  MITSUBA_TO_WORLD (local +Y -> world +Z, local -Z -> world +X) the columns are ours mirrored.
- Blender (Cycles/EEVEE world, Environment Texture, equirectangular): world +Z up;
  u = 0.5 - atan2(d.y, d.x) / 2pi, v = 0.5 + atan2(d.z, hypot(d.x, d.y)) / pi with v = 0 at the
  image's bottom row: our image with columns mirrored and turned by half a turn.
- OpenGL cube map faces (GL_TEXTURE_CUBE_MAP_POSITIVE_X ... NEGATIVE_Z; three.js CubeTexture
  takes the same six images in the order px, nx, py, ny, pz, nz): a Y-up world, here
  (x, y, z)_gl = (x, z, -y)_world; the major axis picks the face, and
  s = (sc / |ma| + 1) / 2 (column), t = (tc / |ma| + 1) / 2 (row, row 0 first in the file), with
  +X: sc = -z, tc = -y; -X: sc = z, tc = -y; +Y: sc = x, tc = z; -Y: sc = x, tc = -z;
  +Z: sc = x, tc = -y; -Z: sc = -x, tc = -y (the GL specification's table).
  Face pixels of size R coincide with our cube map's texels, so the export is exact.
- The fitted material (`material_mapping`, below): Mitsuba 3's diffuse / roughplastic / plastic BSDF
  (`mitsuba_bsdf_xml`) and Blender's Principled BSDF (`blender_material_description`,
  `blender_material_script`); exact for lambert and plastic in Mitsuba, approximate otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..light.cubemap import CubeMap, face_rectangle_solid_angle

MITSUBA_TO_WORLD = np.array([[0.0, 0.0, -1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
GL_FACES = ("px", "nx", "py", "ny", "pz", "nz")


def _wrap01(u):
    return u - np.floor(u)


def _read(image: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    H, W = image.shape[:2]
    return image[np.clip(rows, 0, H - 1), np.clip(cols, 0, W - 1)]


# -- our own lat-long (the reference the exports are checked against) --------------------------------

def latlong_lookup(image: np.ndarray, directions: np.ndarray) -> np.ndarray:
    H, W = image.shape[:2]
    d = np.asarray(directions, np.float64)
    theta = np.arccos(np.clip(d[..., 2], -1, 1))
    phi = _wrap01(np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi))
    return _read(image, np.floor(theta / np.pi * H).astype(int), np.floor(phi * W).astype(int))


# -- Mitsuba 3 -------------------------------------------------------------------------------------------

def to_mitsuba(latlong: np.ndarray) -> np.ndarray:
    """The image for Mitsuba's envmap with to_world = MITSUBA_TO_WORLD: (2H + 1, W) rows on
    Mitsuba's row grid (see the module's docstring), columns mirrored."""
    img = np.asarray(latlong)
    H = img.shape[0]
    out = np.empty((2 * H + 1,) + img.shape[1:], dtype=np.result_type(img.dtype, np.float32))
    out[1::2] = img
    out[2:-1:2] = 0.5 * (img[:-1] + img[1:])
    out[0], out[-1] = img[0], img[-1]
    return np.ascontiguousarray(out[:, ::-1])


def mitsuba_lookup(image: np.ndarray, directions: np.ndarray, to_world: np.ndarray = MITSUBA_TO_WORLD) -> np.ndarray:
    """What Mitsuba's envmap reads for world directions: its bilinear lookup (columns at
    u = (c + 1/2) / W, wrapping; rows at v = r / (H - 1))."""
    img = np.asarray(image, np.float64)
    H, W = img.shape[:2]
    local = np.asarray(directions, np.float64) @ to_world[:3, :3]  # R^T d for each row
    u = _wrap01(np.arctan2(local[..., 0], -local[..., 2]) / (2 * np.pi) - 0.5 / W) * W
    v = np.arccos(np.clip(local[..., 1], -1, 1)) / np.pi * (H - 1)
    c0 = np.minimum(np.floor(u).astype(int), W - 1)
    r0 = np.minimum(np.floor(v).astype(int), H - 2)
    wu, wv = u - c0, v - r0
    if img.ndim == 3:
        wu, wv = wu[..., None], wv[..., None]
    c1 = (c0 + 1) % W
    top = (1 - wu) * img[r0, c0] + wu * img[r0, c1]
    bottom = (1 - wu) * img[r0 + 1, c0] + wu * img[r0 + 1, c1]
    return (1 - wv) * top + wv * bottom


def mitsuba_xml(filename: str, scale: float = 1.0) -> str:
    """The envmap emitter as a file Mitsuba 3 loads by itself (`mi.load_file`) or from a scene
    (`<include filename="emitter.xml"/>`; `filename` then resolves next to it). Mitsuba's parser
    requires a `version` on a file's root element (3.9: "missing version attribute in root element
    <emitter>" without it) and refuses one on an inner element ("unexpected attribute"), so pasted
    into a scene the element loses it (the comment says so)."""
    m = " ".join(f"{x:g}" for x in MITSUBA_TO_WORLD.ravel())
    return (f'<emitter type="envmap" version="3.0.0">\n'
            f'    <!-- wavelight light (world +Z up); to_world puts the map\'s up (local +Y) on world +Z.\n'
            f'         Load this file (mi.load_file) or <include filename="emitter.xml"/> it; pasted into a\n'
            f'         scene, drop version="3.0.0" above. -->\n'
            f'    <string name="filename" value="{filename}"/>\n'
            f'    <float name="scale" value="{scale:g}"/>\n'
            f'    <transform name="to_world"><matrix value="{m}"/></transform>\n'
            f'</emitter>\n')


# -- Blender ------------------------------------------------------------------------------------------------

def to_blender(latlong: np.ndarray) -> np.ndarray:
    """The image for Blender's Environment Texture (equirectangular, world +Z up)."""
    img = np.asarray(latlong)
    W = img.shape[1]
    cols = (W // 2 - 1 - np.arange(W)) % W
    return np.ascontiguousarray(img[:, cols])


def blender_lookup(image: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """What Blender's equirectangular Environment Texture reads for world directions (nearest)."""
    H, W = image.shape[:2]
    d = np.asarray(directions, np.float64)
    u = _wrap01(0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi))
    v = 0.5 + np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1])) / np.pi
    row_from_bottom = np.floor(v * H).astype(int)
    return _read(image, H - 1 - row_from_bottom, np.floor(u * W).astype(int))


BLENDER_WORLD_SCRIPT = '''"""wavelight: light this Blender scene with the exported light.

    blender --python setup_world.py                  a new scene lit by it
    blender my.blend --python setup_world.py         an existing scene (then save it)
    or open this file in Blender's Text Editor and press Run Script.

Makes the scene's World "wavelight": Texture Coordinate (Generated) -> Mapping -> Environment
Texture of {image!r} (the file next to this script, equirectangular, linear) -> Background
(strength STRENGTH below) -> World Output. The image is wavelight's light in Blender's convention (world +Z
up, linear radiance: a white diffuse patch facing up under a uniform sky of 1 renders 1); the
Mapping node's Z rotation turns the light about +Z (0 = as recovered). Rerunning replaces the
world's nodes.
"""

import os

import bpy

IMAGE = {image!r}
WORLD = "wavelight"
STRENGTH = {strength!r}  # 1, or the factor the exported material's colours were divided by (material.json)


def script_folder():
    """This script's folder: from __file__ (blender --python, runpy), or, in the Text Editor,
    from the text block's file (__file__ is then its name or its path, maybe //-relative)."""
    name = globals().get("__file__") or ""
    for candidate in (name, bpy.path.abspath(name)):
        if candidate and os.path.isfile(candidate):
            return os.path.dirname(os.path.abspath(candidate))
    for text in bpy.data.texts:
        path = bpy.path.abspath(text.filepath) if text.filepath else ""
        if path and os.path.isfile(path) and (text.name == os.path.basename(name) or path == name):
            return os.path.dirname(os.path.abspath(path))
    raise RuntimeError("wavelight: cannot tell where setup_world.py is; run it from its file "
                       "(blender --python setup_world.py) or open it from disk in the Text Editor")


def setup_world(scene=None, image_path=None):
    scene = scene or bpy.context.scene
    image_path = image_path or os.path.join(script_folder(), IMAGE)
    if not os.path.isfile(image_path):
        raise FileNotFoundError(f"wavelight: {{image_path}} not found (keep it next to setup_world.py)")
    world = bpy.data.worlds.get(WORLD) or bpy.data.worlds.new(WORLD)
    if world.node_tree is None:  # Blender < 5: a world needs use_nodes for its tree
        world.use_nodes = True
    nodes, links = world.node_tree.nodes, world.node_tree.links
    nodes.clear()
    coords = nodes.new("ShaderNodeTexCoord")
    mapping = nodes.new("ShaderNodeMapping")
    mapping.vector_type = "POINT"
    env = nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(image_path, check_existing=True)
    env.image.reload()  # a rerun after a new export reads the new file
    for space in ("Linear Rec.709", "Linear"):  # the colour space's name in Blender >= 4 / < 4
        try:
            env.image.colorspace_settings.name = space
            break
        except TypeError:
            continue
    env.projection = "EQUIRECTANGULAR"
    env.interpolation = "Linear"
    background = nodes.new("ShaderNodeBackground")
    background.inputs["Strength"].default_value = STRENGTH
    output = nodes.new("ShaderNodeOutputWorld")
    links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    links.new(env.outputs["Color"], background.inputs["Color"])
    links.new(background.outputs["Background"], output.inputs["Surface"])
    for x, node in zip(range(0, 1000, 250), (coords, mapping, env, background)):
        node.location = (x - 800, 0)
    output.location = (200, 0)
    scene.world = world
    print(f"wavelight: world {{world.name!r}} lit by {{image_path}}")
    return world


if __name__ == "__main__":
    setup_world()
'''


def blender_world_script(image_name: str, strength: float = 1.0) -> str:
    """setup_world.py for Blender: sets the scene's World to the exported equirectangular image
    `image_name`, looked up next to the script (see the script's docstring for how to run it), with
    the Background's Strength `strength` (1, or the exported material's light_scale)."""
    if any(c in image_name for c in "/\\\n\r") or not image_name:
        raise ValueError(f"image_name must be a bare file name, got {image_name!r}")
    return BLENDER_WORLD_SCRIPT.format(image=image_name, strength=float(strength))


# -- OpenGL / three.js cube faces ----------------------------------------------------------------------------

def _world_to_gl(d):
    return np.stack([d[..., 0], d[..., 2], -d[..., 1]], axis=-1)


def _gl_to_world(g):
    return np.stack([g[..., 0], -g[..., 2], g[..., 1]], axis=-1)


def gl_face_directions(face: str, size: int) -> np.ndarray:
    """(size, size, 3) world directions of a GL face's pixel centres (row = t, col = s)."""
    t, s = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    sc, tc = 2 * s - 1, 2 * t - 1
    one = np.ones_like(sc)
    g = {"px": (one, -tc, -sc), "nx": (-one, -tc, sc), "py": (sc, one, tc), "ny": (sc, -one, -tc),
         "pz": (sc, -tc, one), "nz": (-sc, -tc, -one)}[face]
    g = np.stack(g, axis=-1)
    return _gl_to_world(g / np.linalg.norm(g, axis=-1, keepdims=True))


def gl_face_solid_angles(size: int) -> np.ndarray:
    """(size, size) exact solid angle of each pixel of a cube face."""
    e = -1.0 + 2.0 * np.arange(size + 1) / size
    return face_rectangle_solid_angle(e[None, :-1], e[None, 1:], e[:-1, None], e[1:, None])


def to_gl_faces(texels: np.ndarray, cube: CubeMap) -> dict[str, np.ndarray]:
    """Six (R, R, C) faces of a cube-map light (R = its face resolution): each face pixel is one of
    our texels (the same cube), so radiance and solid angle carry over exactly; faces or halves the
    light does not cover (hemisphere mode: below the horizon) are 0."""
    tex = np.asarray(texels, np.float64)
    R = cube.resolution
    out = {}
    for face in GL_FACES:
        idx = cube.lookup(gl_face_directions(face, R))
        out[face] = np.where((idx >= 0)[..., None], tex[np.where(idx >= 0, idx, 0)], 0.0)
    return out


def gl_lookup(faces: dict[str, np.ndarray], directions: np.ndarray) -> np.ndarray:
    """What an OpenGL cube-map sampler reads for world directions (nearest texel)."""
    g = _world_to_gl(np.asarray(directions, np.float64))
    x, y, z = g[..., 0], g[..., 1], g[..., 2]
    ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
    size = next(iter(faces.values())).shape[0]
    out = np.zeros(g.shape[:-1] + next(iter(faces.values())).shape[2:])
    major_x = (ax >= ay) & (ax >= az)
    major_y = ~major_x & (ay >= az)
    major_z = ~major_x & ~major_y
    cases = [("px", major_x & (x >= 0), -z, -y, ax), ("nx", major_x & (x < 0), z, -y, ax),
             ("py", major_y & (y >= 0), x, z, ay), ("ny", major_y & (y < 0), x, -z, ay),
             ("pz", major_z & (z >= 0), x, -y, az), ("nz", major_z & (z < 0), -x, -y, az)]
    for face, sel, sc, tc, ma in cases:
        if not np.any(sel):
            continue
        s = (sc[sel] / ma[sel] + 1) / 2
        t = (tc[sel] / ma[sel] + 1) / 2
        out[sel] = _read(faces[face], np.floor(t * size).astype(int), np.floor(s * size).astype(int))
    return out


# -- the fitted material ----------------------------------------------------------------------------------
# What each of our reflectance models is in Mitsuba 3 and in Blender's Principled BSDF (README: Relight, insert, export, report).
#
# - lambert: Mitsuba `diffuse` (reflectance kd), exact; Blender Principled with Specular IOR Level 0
#   (no specular reflection at all: the base is Lambert, kd / pi), exact.
# - plastic: Mitsuba `roughplastic` (alpha > 0) / `plastic` (alpha = 0) with diffuse_reflectance kd,
#   specular_reflectance ks, int_ior = ior, ext_ior = 1 (our ior is relative to the outside; Mitsuba's
#   default ext_ior is air's 1.000277), the same distribution and alpha, nonlinear false,
#   sample_visible true: exactly our model (pipelines/model/microfacet.py, checked in
#   tests/test_plastic_mitsuba.py). Blender: Principled BSDF, GGX, Roughness = sqrt(alpha)
#   (Cycles' alpha = roughness^2), IOR = ior, Specular IOR Level 0.5 x mean(ks) (0.5: the IOR's own
#   Fresnel) with Specular Tint ks / mean(ks), Base Color = our diffuse base's albedo at normal view
#   over (1 - F0) (Principled's base is weighted by 1 - the coating's albedo, not by our
#   t(N.v) t(N.d) / (eta^2 (1 - Fdr))): approximate; Beckmann is GGX there (Principled has no Beckmann).
# - blinn-phong, phong, phong-classic: no equivalent in either tool. The closest roughplastic: Beckmann
#   of alpha = sqrt(2 / (n' + 2)) (Walter et al. 2007's Phong-Beckmann correspondence; n' = n for
#   Blinn-Phong's N.H lobe, 4n for Phong's R.d lobe, whose exponent is ~4x a half-vector lobe's), the
#   lobe's peak at normal incidence kept: F0 x specular_reflectance = ks P 4 alpha^2 (from
#   F0 s D(0) / 4 = ks P / pi, D(0) = 1 / (pi alpha^2); P = (n + 8) / 8 Blinn-Phong, (n + 2) / 2 Phong,
#   pi phong-classic), with the IOR whose F0 is the largest channel's (1.05..3) and
#   specular_reflectance the rest; diffuse_reflectance such that the albedo head on is kd.
#   Off the peak and at grazing angles the Fresnel and 1 / (N.v N.d) of the microfacet lobe differ
#   from a Phong lobe: approximate (export.json and the XML's comment say so).
# - Colours above 1 (Mitsuba refuses RGB reflectances > 1): every colour is divided by their largest
#   value s and the exported light multiplied by s (`light_scale`): the product, the render, is the same.

def _f0(ior: float) -> float:
    return float(((ior - 1.0) / (ior + 1.0)) ** 2)


def diffuse_albedo_factor(alpha: float, ior: float, distribution: str) -> float:
    """The directional albedo at normal view of our plastic's diffuse base per unit kd:
    t(1) / (eta^2 (1 - Fdr)) 2 int_0^1 t(mu) mu dmu (the light reflected by the base of a kd = 1
    plastic seen head on under a uniform sky of 1)."""
    from ..model.microfacet import coating

    c = coating(float(alpha), float(ior), distribution)
    mu = (np.arange(4096) + 0.5) / 4096
    return float(c.transmittance(np.array(1.0)) * c.base_scale * 2.0 * np.mean(c.transmittance(mu) * mu))


def _phong_lobe(material) -> tuple[float, float, str]:
    """(n' the half-vector exponent, the peak factor: the lobe's BRDF at normal incidence per ks x pi, name)."""
    n = float(material.shininess)
    if material.model == "blinn-phong":
        return n, (n + 8) / 8.0, f"Blinn-Phong n = {n:g}"
    if material.model == "phong":
        return 4.0 * n, (n + 2) / 2.0, f"Phong n = {n:g} (a half-vector exponent of ~4n = {4 * n:g})"
    return 4.0 * n, np.pi, f"the paper's unnormalised Phong n = {n:g} (a half-vector exponent of ~4n = {4 * n:g})"


def material_mapping(material, light_scale: float | None = None) -> dict:
    """Our material as the parameters of Mitsuba 3's BSDF and Blender's Principled BSDF.

    Returns {"model", "exact": whether Mitsuba's BSDF is our model exactly, "mitsuba": {"type", ...
    parameters}, "blender": {Principled BSDF input name: value, "distribution"}, "light_scale",
    "raw_peak": the largest colour before that scale, "notes": [...]}. `light_scale`: the factor the
    exported light carries and every colour is divided by (default: the largest colour, at least 1;
    a scene of several parts passes the one they share, `parts_light_scale`)."""
    kd, ks = np.asarray(material.kd, np.float64), np.asarray(material.ks, np.float64)
    notes: list[str] = []
    if material.model == "lambert" or not material.specular:
        mitsuba = {"type": "diffuse", "reflectance": kd.tolist()}
        blender = {"Base Color": kd.tolist(), "Metallic": 0.0, "Roughness": 0.5, "IOR": 1.5,
                   "Specular IOR Level": 0.0, "Specular Tint": [1.0, 1.0, 1.0], "Coat Weight": 0.0,
                   "distribution": "GGX"}
        exact, blender_exact = True, True
        if material.model != "lambert":
            notes.append(f"{material.model} with ks = 0 is Lambert")
    elif material.model == "plastic":
        alpha, ior, dist = material.roughness, material.ior, material.distribution
        mitsuba = {"type": "plastic" if alpha <= 0 else "roughplastic"}
        if alpha > 0:
            mitsuba.update(distribution=dist, alpha=alpha, sample_visible=True)
        mitsuba.update(int_ior=ior, ext_ior=1.0, diffuse_reflectance=kd.tolist(), specular_reflectance=ks.tolist(),
                       nonlinear=False)
        exact, blender_exact = True, False
        weight = ks
        base = kd * diffuse_albedo_factor(alpha, ior, dist) / (1.0 - _f0(ior))
        blender = _principled(base, alpha, ior, weight)
        if dist == "beckmann":
            notes.append("Blender's Principled BSDF has no Beckmann: GGX of the same alpha")
        notes.append("Blender: Principled's diffuse base is weighted by 1 - the coating's albedo, not by wavelight's "
                     "(and Mitsuba's) t(N.v) t(N.d) / (eta^2 (1 - Fdr)); Base Color gives the same albedo head on")
    else:
        n_half, peak, what = _phong_lobe(material)
        alpha = material.lobe_alpha
        # the specular F0 x weight that gives the lobe's peak: s F0 D(0) / 4 = ks peak / pi, D(0) = 1 / (pi alpha^2)
        target = ks * peak * 4.0 * alpha**2
        ior = _ior_of_f0(float(np.max(target)))
        f0 = _f0(ior)
        weight = target / f0
        diffuse = kd / diffuse_albedo_factor(alpha, ior, "beckmann")
        mitsuba = {"type": "roughplastic", "distribution": "beckmann", "alpha": alpha, "sample_visible": True,
                   "int_ior": ior, "ext_ior": 1.0, "diffuse_reflectance": diffuse.tolist(),
                   "specular_reflectance": weight.tolist(), "nonlinear": False}
        exact, blender_exact = False, False
        blender = _principled(kd / (1.0 - f0), alpha, ior, weight)
        notes.append(f"approximate: {what} has no equivalent in Mitsuba or Blender; the closest roughplastic is "
                     f"Beckmann alpha = sqrt(2 / (n' + 2)) = {alpha:.4g} (Walter et al. 2007), the IOR {ior:.4g} whose "
                     f"F0 = {f0:.4g} with specular_reflectance gives the lobe's peak at normal incidence, and the "
                     f"diffuse_reflectance that gives kd as the albedo head on; off the peak and at grazing angles "
                     f"they differ (Fresnel, the microfacet 1 / (N.v N.d))")
        notes.append("Blender's Principled BSDF has no Beckmann: GGX of the same alpha")
    # Mitsuba's RGB reflectances must be <= 1 (Blender's Base Color too): a larger colour (the light holds
    # the albedo's scale, README: Conventions) goes into the light, which the export then multiplies by s
    colours = [np.max(v) for k, v in mitsuba.items() if isinstance(v, list)] + [np.max(blender["Base Color"])]
    peak = float(max(colours))
    scale = float(max(1.0, peak)) if light_scale is None else float(light_scale)
    if scale != 1.0:
        for k, v in mitsuba.items():
            if isinstance(v, list):
                mitsuba[k] = (np.asarray(v) / scale).tolist()
        blender["Base Color"] = (np.asarray(blender["Base Color"]) / scale).tolist()
        blender["Specular IOR Level"] /= scale
        why = ("colours above 1" if light_scale is None else
               "the largest colour of the scene's parts (their textures included) above 1")
        notes.append(f"{why} (the light holds the albedo's scale, README: Conventions): the material's "
                     f"colours are divided by {scale:.6g} and the exported light multiplied by it (emitter.xml's "
                     f"scale, setup_world.py's Background Strength): the render is the same")
    return {"model": material.model, "exact": exact, "blender_exact": blender_exact, "light_scale": scale,
            "raw_peak": peak, "mitsuba": mitsuba, "blender": blender, "notes": notes}


DIFFUSE_KEYS = ("reflectance", "diffuse_reflectance")  # the Mitsuba parameter a diffuse texture replaces


def _diffuse_key(mitsuba: dict) -> str:
    return next(k for k in DIFFUSE_KEYS if k in mitsuba)


def texture_peak(material, texture: np.ndarray) -> float:
    """The largest colour a textured part's export holds before the light scale: its BSDF's other
    colours, and each channel's diffuse parameter (the mapping of kd = the part's multiplier) times
    the texture's largest value in that channel."""
    m = material_mapping(material, light_scale=1.0)
    peaks = [float(np.max(v)) for k, v in m["mitsuba"].items() if isinstance(v, list) and k not in DIFFUSE_KEYS]
    tex_max = np.asarray(texture, np.float64).reshape(-1, 3).max(axis=0)
    peaks.append(float(np.max(np.asarray(m["mitsuba"][_diffuse_key(m["mitsuba"])]) * tex_max)))
    peaks.append(float(np.max(np.asarray(m["blender"]["Base Color"]) * tex_max)))
    return max(peaks)


def textured_images(material, texture: np.ndarray, light_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(Mitsuba's diffuse bitmap, Blender's Base Color image) of a textured part: the linear texture
    times the part's diffuse parameter in each tool, over the shared light scale (float32, linear:
    Mitsuba loads it raw, Blender as Linear Rec.709)."""
    m = material_mapping(material, light_scale=light_scale)
    t = np.asarray(texture, np.float32)
    d = np.asarray(m["mitsuba"][_diffuse_key(m["mitsuba"])], np.float32)
    b = np.asarray(m["blender"]["Base Color"], np.float32)
    return t * d, t * b


def _ior_of_f0(f0: float) -> float:
    """The dielectric IOR of normal-incidence reflectance f0, within our IOR range."""
    from ..model.microfacet import IOR_RANGE

    r = np.sqrt(max(f0, 0.0))
    ior = (1 + r) / (1 - r) if r < 1 else np.inf
    return float(np.clip(ior, *IOR_RANGE))


def _principled(base, alpha: float, ior: float, weight) -> dict:
    """Principled BSDF inputs of a dielectric of roughness alpha whose specular Fresnel is `weight`
    (RGB) x the IOR's."""
    w = np.asarray(weight, np.float64)
    level = float(np.mean(w))
    tint = (w / level).tolist() if level > 0 else [1.0, 1.0, 1.0]
    return {"Base Color": np.asarray(base, np.float64).tolist(), "Metallic": 0.0,
            "Roughness": float(np.sqrt(alpha)), "IOR": float(ior), "Specular IOR Level": 0.5 * level,
            "Specular Tint": tint, "Coat Weight": 0.0, "distribution": "GGX"}


def _xml_value(name: str, value) -> str:
    if isinstance(value, tuple) and value and value[0] == "bitmap":
        return (f'<texture type="bitmap" name="{name}"><string name="filename" value="{value[1]}"/>'
                f'<boolean name="raw" value="true"/><string name="filter_type" value="bilinear"/>'
                f'<string name="wrap_mode" value="repeat"/></texture>')
    if isinstance(value, bool):
        return f'<boolean name="{name}" value="{str(value).lower()}"/>'
    if isinstance(value, str):
        return f'<string name="{name}" value="{value}"/>'
    if isinstance(value, (list, tuple)):
        return f'<rgb name="{name}" value="{", ".join(f"{float(x):.9g}" for x in value)}"/>'
    return f'<float name="{name}" value="{float(value):.9g}"/>'


def mitsuba_bsdf_xml(material, bsdf_id: str = "wavelight", light_scale: float | None = None,
                     texture: str | None = None, note: str | None = None) -> str:
    """The material as a Mitsuba 3 BSDF element, a file `mi.load_file` loads by itself (its root
    has version="3.0.0"; pasted into a shape, drop it, as for emitter.xml). `texture`: a linear
    bitmap (next to the file; `textured_images`) as the diffuse parameter instead of the RGB value."""
    m = material_mapping(material, light_scale)
    p = dict(m["mitsuba"])
    if texture is not None:
        p[_diffuse_key(p)] = ("bitmap", texture)
    kind = p.pop("type")
    what = ("exactly wavelight's model" if m["exact"] else
            "an APPROXIMATION (no Mitsuba BSDF is this model)")
    lines = [f'<bsdf type="{kind}" id="{bsdf_id}" version="3.0.0">',
             f'    <!-- wavelight material: {material.model}; this BSDF is {what}.',
             '         Load this file (mi.load_file), or paste it into a <shape> (then drop version="3.0.0").']
    lines += [f'         {n}'.replace("--", "-") for n in m["notes"] if not n.startswith("Blender")]
    if note:
        lines.append(f"         {note}".replace("--", "-"))
    lines[-1] += " -->"
    lines += [f"    {_xml_value(k, v)}" for k, v in p.items()]
    lines.append("</bsdf>")
    return "\n".join(lines) + "\n"


def blender_material_description(material, light_scale: float | None = None, parts=None) -> dict:
    """material.json: the Principled BSDF's inputs, and the settings a user types in, in words.
    `parts`: [(PartExport, Base Color image file name or None)]: one Principled BSDF per part too
    ("parts"), each a material named as the part (setup_material.py rebuilds the one of that name,
    e.g. the OBJ's usemtl material Blender imported, or makes it)."""
    m = material_mapping(material, light_scale)
    b = m["blender"]

    def rgb(v):
        return " ".join(f"{x:.4g}" for x in v)

    steps = ["Shader Editor: select the object, add a material (New): a Principled BSDF",
             f"Principled BSDF: distribution {b['distribution']}",
             f"Base Color: RGB {rgb(b['Base Color'])} (linear: the Color picker's RGB tab, values as typed)",
             "Metallic: 0",
             f"Roughness: {b['Roughness']:.4g}",
             f"IOR: {b['IOR']:.4g}",
             f"Specular > IOR Level: {b['Specular IOR Level']:.4g}",
             f"Specular > Tint: RGB {rgb(b['Specular Tint'])}",
             "Coat > Weight: 0; everything else at its default (Subsurface, Transmission, Sheen, Emission 0)"]
    out = {"format": "wavelight-blender-material-1", "name": "wavelight", "node": "ShaderNodeBsdfPrincipled",
           "model": material.model, "exact": m["blender_exact"], "inputs": {k: v for k, v in b.items() if k != "distribution"},
           "distribution": b["distribution"], "settings": steps, "notes": m["notes"],
           "wavelight_material": material.to_json(),
           "script": "setup_material.py (next to this file) makes this material on the active object"}
    if parts:
        listed = []
        for part, image in parts:
            pm = material_mapping(part.material, light_scale)
            inputs = {k: v for k, v in pm["blender"].items() if k != "distribution"}
            colour = (f"Base Color: an Image Texture node with {image} (Color Space: Linear Rec.709, "
                      "Interpolation Linear, Extension Repeat; the mesh's UVs) into Base Color" if image else
                      f"Base Color: RGB {rgb(inputs['Base Color'])}")
            listed.append({"name": part.name, "inputs": inputs, "distribution": pm["blender"]["distribution"],
                           "base_color_image": image, "exact": pm["blender_exact"] and part.exact,
                           "settings": [f"the material named {part.name!r} (the mesh's part): a Principled BSDF as "
                                        "above, with", colour]})
        out["parts"] = listed
        out["script"] = ("setup_material.py (next to this file) makes one material per part, named as the part (it "
                         "rebuilds an existing material of that name, e.g. the one the OBJ import made), and the "
                         "material 'wavelight' on the active object when it has no part's material")
    return out


BLENDER_MATERIAL_SCRIPT = '''"""wavelight: the fitted material as a Blender material, on the active object.

    blender my.blend --python setup_material.py      (then save), or Run Script in the Text Editor

Reads material.json (next to this script): a Principled BSDF with the inputs listed there, in a
material named "wavelight" (rerunning replaces its nodes), given to the active object (its first
material slot). A scene of several parts (material.json "parts") gets one material per part, named
as the part: an existing material of that name (the one Blender's OBJ import made for the part's
usemtl group) is rebuilt in place, so every face already using it follows; a textured part's Base
Color is an Image Texture of its base_<part>.exr (next to this script). material.json's "settings"
say the same in words, for typing them in by hand.
"""

import json
import os

import bpy

JSON = "material.json"


def script_folder():
    name = globals().get("__file__") or ""
    for candidate in (name, bpy.path.abspath(name)):
        if candidate and os.path.isfile(candidate):
            return os.path.dirname(os.path.abspath(candidate))
    for text in bpy.data.texts:
        path = bpy.path.abspath(text.filepath) if text.filepath else ""
        if path and os.path.isfile(path) and (text.name == os.path.basename(name) or path == name):
            return os.path.dirname(os.path.abspath(path))
    raise RuntimeError("wavelight: cannot tell where setup_material.py is; run it from its file")


def build_material(name, distribution, inputs, image_path=None):
    """The material `name` (made, or its nodes replaced): a Principled BSDF -> Material Output, with
    an Image Texture (linear) into Base Color when `image_path` is given."""
    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5 needs use_nodes for a tree
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    bsdf = nodes.new("ShaderNodeBsdfPrincipled")
    out = nodes.new("ShaderNodeOutputMaterial")
    bsdf.location, out.location = (-300, 0), (100, 0)
    bsdf.distribution = distribution
    inputs = dict(inputs)
    if "Specular IOR Level" not in bsdf.inputs:  # Blender < 4: "Specular" 0.5 = F0 0.04, "Clearcoat"
        level = inputs.pop("Specular IOR Level")
        ior = inputs["IOR"]
        inputs["Specular"] = 2.0 * level * ((ior - 1) / (ior + 1)) ** 2 / 0.08
        inputs.pop("Specular Tint")
        inputs["Clearcoat"] = inputs.pop("Coat Weight")
    for key, value in inputs.items():
        socket = bsdf.inputs[key]
        if isinstance(value, list) and len(socket.default_value) == 4:
            value = list(value) + [1.0]
        socket.default_value = value
    if image_path is not None:
        tex = nodes.new("ShaderNodeTexImage")
        tex.location = (-700, 0)
        tex.image = bpy.data.images.load(image_path, check_existing=True)
        tex.image.colorspace_settings.name = "Linear Rec.709"
        tex.interpolation, tex.extension = "Linear", "REPEAT"
        links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return mat


def make_material(json_path=None):
    """The material "wavelight" from material.json (a Principled BSDF -> Material Output)."""
    json_path = json_path or os.path.join(script_folder(), JSON)
    with open(json_path) as f:
        desc = json.load(f)
    return build_material(desc["name"], desc["distribution"], desc["inputs"])


def make_part_materials(json_path=None):
    """One material per part of material.json (none without parts), named as the part."""
    json_path = json_path or os.path.join(script_folder(), JSON)
    with open(json_path) as f:
        desc = json.load(f)
    folder = os.path.dirname(os.path.abspath(json_path))
    made = []
    for part in desc.get("parts", []):
        image = part.get("base_color_image")
        made.append(build_material(part["name"], part["distribution"], part["inputs"],
                                   os.path.join(folder, image) if image else None))
    return made


def setup_material(obj=None, json_path=None):
    parts = make_part_materials(json_path)
    obj = obj or bpy.context.view_layer.objects.active
    if parts:
        names = [m.name for m in parts]
        used = [m.name for m in (getattr(obj.data, "materials", None) or []) if m is not None] if obj else []
        print(f"wavelight: part materials {{names}}" + (
            f" ({{len([n for n in names if n in used])}} of them on {{obj.name!r}})" if obj else "")
            + "; give a part's faces its material where the mesh did not name it")
        if obj is None or any(n in used for n in names) or not hasattr(obj.data, "materials"):
            return parts
    mat = make_material(json_path)
    if obj is None or not hasattr(obj.data, "materials"):
        print(f"wavelight: made material {{mat.name!r}}; no active object to give it to")
        return mat
    if obj.data.materials:
        obj.data.materials[0] = mat
    else:
        obj.data.materials.append(mat)
    print(f"wavelight: material {{mat.name!r}} on {{obj.name!r}}")
    return mat


if __name__ == "__main__":
    setup_material()
'''


def blender_material_script() -> str:
    return BLENDER_MATERIAL_SCRIPT.format()


# -- several parts (reflectance.json `parts`) --------------------------------------------------------
# Each part's material is the scene's model (Lambertian for a part whose `specular` is false) with the
# part's diffuse colour: kd x its fitted scale x
# its base (the .mtl / glTF colour of a plain part; the texture of a textured one, exported as a
# linear bitmap: mitsuba/kd_<part>.exr, blender/base_<part>.exr, the texture times the part's diffuse
# parameter in that tool). Every part shares one light, so one light scale covers all their colours.
# A vertex-coloured part is exported with its mean colour (approximate: neither file format here
# carries per-vertex colour).

@dataclass
class PartExport:
    name: str
    file_stem: str  # the part's name made safe for a file name
    material: object  # the part's Material (a textured part's kd: the multiplier of its texture)
    texture: np.ndarray | None  # (H, W, 3) linear texture (a textured part), else None
    texture_name: str | None  # the source texture's file name
    exact: bool  # its colour is the solve's per-pixel colour (False: a vertex-coloured part's mean)


def part_exports(material, parts: list[dict], scene_parts=None) -> list[PartExport]:
    """The parts of a reflectance.json as exports: `scene_parts` (pipelines.model.parts.SceneParts of
    the scene's mesh) gives the textures; without it (or a part not found in it) a textured part
    falls back to its mean colour."""
    import re
    from dataclasses import replace

    by_name = {} if scene_parts is None else {p.name: p for p in scene_parts.parts}
    out = []
    for p in parts:
        sp = by_name.get(p["name"])
        tex = sp.texture if sp is not None and p.get("textured") else None
        if tex is not None:
            kd, pixels, exact = tuple(float(v) for v in p["scale"]), tex.levels[0], True
        else:
            kd, pixels, exact = tuple(float(v) for v in p["kd"]), None, not p.get("textured")
        # (a matte part of a glossy scene, reflectance.json's "specular": false: Lambertian, its colour;
        # a glossy part its own ks: the material's x its specular weight)
        if p.get("specular", True):
            weight = float(p.get("specular_weight", 1.0))
            m = replace(material, kd=kd, ks=tuple(float(v) * weight for v in material.ks))
        else:
            m = type(material)(kd=kd)
        out.append(PartExport(p["name"], re.sub(r"[^A-Za-z0-9_.-]", "_", p["name"]), m,
                              pixels, p.get("texture") if tex is not None else None, exact))
    return out


def parts_light_scale(material, parts: list[PartExport]) -> float:
    """The light scale every part's export shares: the largest colour of any part (a texture's largest
    texel times its diffuse parameter), at least 1 and at least the scene material's own."""
    peaks = [material_mapping(material)["light_scale"]]
    for p in parts:
        peaks.append(texture_peak(p.material, p.texture) if p.texture is not None else
                     material_mapping(p.material, light_scale=1.0)["raw_peak"])
    return float(max(1.0, *peaks))
