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
"""

from __future__ import annotations

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
(strength 1) -> World Output. The image is wavelight's light in Blender's convention (world +Z
up, linear radiance: a white diffuse patch facing up under a uniform sky of 1 renders 1); the
Mapping node's Z rotation turns the light about +Z (0 = as recovered). Rerunning replaces the
world's nodes.
"""

import os

import bpy

IMAGE = {image!r}
WORLD = "wavelight"


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
    background.inputs["Strength"].default_value = 1.0
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


def blender_world_script(image_name: str) -> str:
    """setup_world.py for Blender: sets the scene's World to the exported equirectangular image
    `image_name`, looked up next to the script (see the script's docstring for how to run it)."""
    if any(c in image_name for c in "/\\\n\r") or not image_name:
        raise ValueError(f"image_name must be a bare file name, got {image_name!r}")
    return BLENDER_WORLD_SCRIPT.format(image=image_name)


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
