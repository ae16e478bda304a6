"""Render Mitsuba 3 reference scenes (ground truth for the tests) into tests/data.

Usage:
    PYTHONPATH=. .venv/bin/python tools/render_mitsuba_scenes.py --set plastic|forward|textured|all
        [--scene NAME ...] [--dest tests/data] [--shared /work/shared/data] [--variant llvm_ad_rgb] [--quick]
    PYTHONPATH=. .venv/bin/python tools/render_mitsuba_scenes.py --list
    PYTHONPATH=. .venv/bin/python tools/render_mitsuba_scenes.py --diffuse-check NAME [-R 64]

Sets:
  plastic   glossy dielectrics (Mitsuba `roughplastic`, one `plastic`): scenes/<name>/, one mesh.ply
  forward   a lone unit sphere under a sunny and an overcast light, six dielectric materials:
            forward/<light>_<material>/ (noise-free, for checking a forward model)
  textured  Spot with its colour texture (textured `diffuse`) on a coloured diffuse ground, three
            input views: scenes/spot_textured_{sun,overcast}/, mesh.obj + mesh.mtl + texture
`--scene NAME` re-renders only that scene (or forward render); `--quick` renders at 2 x 16 spp for a
dry run (use it with another --dest). `--diffuse-check NAME` renders NAME's input view once more
with Mitsuba `diffuse` 0.7 (into a temporary folder) and compares it with wavelight's forward model
(pipelines.render at cube-map resolution R), the harness' sanity check; nothing is kept.

Only this script reads the shared data; the tests read what it writes. Conventions (README.md):
world +Z up, right-handed; OpenCV pinhole cameras, pixel (0, 0)'s centre at (0, 0); lat-long light
with row 0 = zenith, theta = pi (r + 1/2) / H, phi = 2 pi (c + 1/2) / W from +X towards +Y.

The source HDRs (Poly Haven, 1024 x 512) are in the y-up convention Mitsuba's `envmap` reads: a
local direction v is at u = atan2(v.x, -v.z) / 2 pi, v = acos(v.y) / pi. Put on our world by
wavelight's own MITSUBA_TO_WORLD (local +Y -> world +Z, local -Z -> world +X) a source column at u
looks at azimuth phi = 2 pi (1 - u): our image is the source with its columns mirrored (no shift),
rows unchanged (row 0 = up). So the photo is not mirrored (seen from inside, a panorama turns
clockwise from left to right; our phi turns counter-clockwise). The shared scenes used the same
mapping (spot_overcast, rotation 0, equals the mirrored, 4 x 4 box-averaged source to 0.07 %).
Then: rotate about +Z by the scene's azimuth at full resolution (cubemap.rotate_latlong: what was at
phi goes to phi + azimuth), average 4 x 4 blocks to 256 x 128, zero the lower hemisphere, and scale
so that the largest irradiance of the luminance (Rec. 709 weights) over upward normals is pi (a white
Lambertian patch facing the best direction has radiance 1).

The light goes to Mitsuba through wavelight's export (pipelines/io/exports.py): each pixel repeated
ENV_SUPERSAMPLE x ENV_SUPERSAMPLE (Mitsuba interpolates bilinearly; a sun pixel keeps its value and
power), `to_mitsuba` (column mirror) and the emitter XML of `mitsuba_xml` (to_world =
MITSUBA_TO_WORLD) loaded as is.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE / "tools"))

from pipelines.light import cubemap as cm  # noqa: E402
from pipelines.io import exports
from pipelines.io import images  # noqa: E402

# -- fixed parameters ------------------------------------------------------------------------------
WIDTH, HEIGHT, FOCAL = 320, 240, 400.0
TARGET = (0.0, 0.0, 0.42)
ENV_HEIGHT = 128                 # 256 x 128 lat-long truth light
ENV_SUPERSAMPLE = 16             # each light pixel -> 16 x 16 Mitsuba pixels (see envmap_check)
PLANE_SIZE, PLANE_CELLS = 4.0, 100
PASS_SPP = 256                   # multijitter needs a square count (it rounds 2048 up to 2070)
SPP_INPUT, SPP_NOVEL, SPP_FORWARD = 2048, 1024, 4096
NOISE_REL = 0.005                # input noise sigma = 0.5 % of the mean clean radiance over mask.png
CLICK_NOISE_PX = 0.3
N_CORRESPONDENCES = 16
SUBSAMPLES = 4                   # 4 x 4 rays per pixel for the coverage masks
INT_IOR, EXT_IOR = 1.49, 1.000277
LUMA = np.array([0.2126, 0.7152, 0.0722])
NOVEL_AZIMUTH_OFFSET = 40.0

SUN = "rooitou_park_1k.hdr"
OVERCAST = "potsdamer_platz_1k.hdr"
GROUND_TEXTURED = [0.35, 0.45, 0.6]


# -- scene descriptions ----------------------------------------------------------------------------
@dataclass(frozen=True)
class View:
    name: str
    azimuth_deg: float
    elevation_deg: float
    distance: float
    cx: float
    cy: float
    width: int = WIDTH
    height: int = HEIGHT
    focal: float = FOCAL
    target: tuple = TARGET


@dataclass(frozen=True)
class Scene:
    name: str
    set: str
    mesh: str                      # under shared/meshes/
    light: str                     # under shared/envmaps/
    light_azimuth_deg: float
    material: dict                 # truth/material.json (object and plane share it), or the parts
    view: View
    seed: int
    extra_views: tuple = ()
    textured: bool = False


def roughplastic(distribution: str, alpha: float, kd) -> dict:
    return {"type": "roughplastic", "distribution": distribution, "alpha": alpha, "int_ior": INT_IOR,
            "ext_ior": EXT_IOR, "diffuse_reflectance": list(kd), "specular_reflectance": [1.0, 1.0, 1.0],
            "nonlinear": False}


def plastic(kd) -> dict:
    return {"type": "plastic", "int_ior": INT_IOR, "ext_ior": EXT_IOR, "diffuse_reflectance": list(kd),
            "specular_reflectance": [1.0, 1.0, 1.0], "nonlinear": False}


PLASTIC_SCENES = (
    Scene("teapot_plastic_sun", "plastic", "teapot.obj", SUN, 36.0,
          roughplastic("beckmann", 0.05, [0.6, 0.45, 0.3]), View("main", 120.0, 30.0, 3.8, 160.9, 118.4), 31100),
    Scene("spot_plastic_sun", "plastic", "spot/spot_triangulated.obj", SUN, 76.0,
          roughplastic("ggx", 0.15, [0.3, 0.5, 0.6]), View("main", 300.0, 25.0, 3.2, 158.6, 121.3), 31200),
    Scene("suzanne_plastic_sun", "plastic", "suzanne.obj", SUN, 206.0,
          roughplastic("ggx", 0.1, [0.55, 0.6, 0.3]), View("main", 250.0, 20.0, 3.4, 161.2, 117.6), 31300),
    Scene("bunny_plastic_overcast", "plastic", "stanford-bunny.obj", OVERCAST, 150.0,
          roughplastic("beckmann", 0.3, [0.6, 0.35, 0.4]), View("main", 60.0, 35.0, 3.2, 159.7, 120.5), 31400),
    Scene("teapot_smoothplastic_overcast", "plastic", "teapot.obj", OVERCAST, 270.0,
          plastic([0.6, 0.45, 0.3]), View("main", 210.0, 30.0, 3.8, 160.3, 119.8), 31500),
)

# Spot's head points to +Y: the main view (azimuth 70) sees its face and flank
_TEXTURED_VIEWS = dict(view=View("main", 70.0, 30.0, 3.2, 160.6, 118.7),
                       extra_views=(View("left", 10.0, 20.0, 3.4, 159.4, 120.2),
                                    View("right", 145.0, 45.0, 3.0, 161.1, 119.3)))
_TEXTURED_MATERIAL = {"parts": {
    "spot": {"type": "diffuse", "texture": "spot_texture.png", "texture_encoding": "sRGB (decoded to linear)",
             "filter": "bilinear", "wrap": "repeat"},
    "ground": {"type": "diffuse", "kd": GROUND_TEXTURED}}}
TEXTURED_SCENES = (
    Scene("spot_textured_sun", "textured", "spot/spot_triangulated.obj", SUN, 196.0, _TEXTURED_MATERIAL,
          seed=32100, textured=True, **_TEXTURED_VIEWS),
    Scene("spot_textured_overcast", "textured", "spot/spot_triangulated.obj", OVERCAST, 100.0, _TEXTURED_MATERIAL,
          seed=32200, textured=True, **_TEXTURED_VIEWS),
)

FORWARD_VIEW = View("forward", 30.0, 20.0, 4.0, 79.8, 79.1, width=160, height=160, focal=260.0, target=(0, 0, 0))
FORWARD_KD = [0.6, 0.45, 0.3]
FORWARD_LIGHTS = {"sun": (SUN, 316.0), "overcast": (OVERCAST, 0.0)}
FORWARD_MATERIALS = {
    "beckmann_0.05": roughplastic("beckmann", 0.05, FORWARD_KD),
    "beckmann_0.15": roughplastic("beckmann", 0.15, FORWARD_KD),
    "beckmann_0.3": roughplastic("beckmann", 0.3, FORWARD_KD),
    "ggx_0.1": roughplastic("ggx", 0.1, FORWARD_KD),
    "ggx_0.3": roughplastic("ggx", 0.3, FORWARD_KD),
    "plastic": plastic(FORWARD_KD),
}
FORWARD_SEED = 33000
FORWARD_NAMES = tuple(f"{light}_{mat}" for light in FORWARD_LIGHTS for mat in FORWARD_MATERIALS)

ALL_SCENES = {s.name: s for s in PLASTIC_SCENES + TEXTURED_SCENES}


# -- small helpers ---------------------------------------------------------------------------------
def write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1) + "\n")


def write_mask(path: Path, mask: np.ndarray) -> None:
    """One-channel 8-bit PNG, white = True (the scenes' mask format)."""
    import OpenImageIO as oiio

    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.ascontiguousarray(np.where(mask, 255, 0).astype(np.uint8)[..., None])
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), oiio.ImageSpec(arr.shape[1], arr.shape[0], 1, oiio.UINT8)):
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    out.write_image(arr)
    out.close()


def write_srgb_png(path: Path, linear: np.ndarray) -> None:
    """sRGB 8-bit, clipped at 1 (no exposure change)."""
    images.write_png(path, images.linear_to_srgb(np.clip(linear, 0.0, 1.0)), already_display=True)


def write_exr(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    images.write_exr(path, image)  # float32, zip compression


def stats(values: np.ndarray) -> dict:
    v = np.asarray(values, float)
    return {"n": int(v.size), "median": float(np.median(v)), "p95": float(np.percentile(v, 95)),
            "max": float(v.max()), "fraction_below_1": float(np.mean(v < 1.0))}


# -- light -----------------------------------------------------------------------------------------
def luminance_irradiance_max(latlong: np.ndarray) -> tuple[float, np.ndarray]:
    """Largest irradiance of the luminance, E(n) = sum L_lum omega max(0, n.d), over upward normals
    (theta <= 90 deg): a 2 deg grid (E is a cosine-blurred light: smooth), then three finer grids
    around its best normal."""
    h = latlong.shape[0]
    dirs = cm.latlong_directions(h).reshape(-1, 3)
    power = (latlong.reshape(-1, 3) @ LUMA) * cm.latlong_solid_angles(h).reshape(-1)
    keep = power > 0
    dirs, power = dirs[keep], power[keep]

    def irradiance(theta_deg, phi_deg):
        t, p = np.meshgrid(np.radians(theta_deg), np.radians(phi_deg), indexing="ij")
        n = cm.spherical_to_direction(t.ravel(), p.ravel())
        e = np.concatenate([np.clip(n[i:i + 1024] @ dirs.T, 0, None) @ power for i in range(0, len(n), 1024)])
        k = int(e.argmax())
        return float(e[k]), float(np.degrees(np.arccos(np.clip(n[k, 2], -1, 1)))), \
            float(np.degrees(np.arctan2(n[k, 1], n[k, 0])) % 360)

    best, th, ph = irradiance(np.arange(0.0, 90.01, 2.0), np.arange(0.0, 360.0, 2.0))
    for half, step in ((3.0, 0.25), (0.3, 0.025), (0.03, 0.0025)):
        t = np.clip(np.arange(th - half, th + half + step / 2, step), 0.0, 90.0)
        best, th, ph = irradiance(t, np.arange(ph - half, ph + half + step / 2, step))
    return best, np.array([th, ph])


def build_light(shared: Path, source: str, azimuth_deg: float) -> tuple[np.ndarray, dict]:
    """The 256 x 128 truth light (float32) and its parameters."""
    src = images.read_image(shared / "envmaps" / source).pixels.astype(np.float64)
    if src.shape[:2] != (4 * ENV_HEIGHT, 8 * ENV_HEIGHT):
        raise SystemExit(f"{source}: expected a 1024 x 512 map, got {src.shape[1]} x {src.shape[0]}")
    ours = cm.rotate_latlong(src[:, ::-1], azimuth_deg)  # y-up source -> our phi, then turned
    light = ours.reshape(ENV_HEIGHT, 4, 2 * ENV_HEIGHT, 4, 3).mean(axis=(1, 3))
    light[ENV_HEIGHT // 2:] = 0.0
    e_max, _ = luminance_irradiance_max(light)
    scale = np.pi / e_max
    light = (light * scale).astype(np.float32)
    stored = light.astype(np.float64)
    e_check, normal = luminance_irradiance_max(stored)
    omega = cm.latlong_solid_angles(ENV_HEIGHT)
    energy = (stored * omega[..., None]).sum(axis=(0, 1))
    lum = stored @ LUMA
    top = np.argsort(lum.ravel())[::-1][: int(np.ceil(0.01 * lum.size))]
    d = cm.latlong_directions(ENV_HEIGHT).reshape(-1, 3)[top]
    w = (lum.ravel() * omega.ravel())[top]
    dom = (d * w[:, None]).sum(0)
    dom /= np.linalg.norm(dom)
    theta, phi = cm.direction_to_spherical(dom)
    info = {
        "source": f"data/envmaps/{source}",
        "azimuth_rotation_deg": float(azimuth_deg),
        "scale_applied": float(scale),
        "resolution": [2 * ENV_HEIGHT, ENV_HEIGHT],
        "lower_hemisphere": "zeroed",
        "source_mapping": "columns mirrored (phi = 2 pi (1 - u)), rows as is; rotated at 1024 x 512 "
                          "(cubemap.rotate_latlong), 4x4 box average, lower half zeroed, scaled",
        "max_luminance_irradiance_over_upward_normals": e_check,
        "max_irradiance_normal_theta_phi_deg": normal.tolist(),
        "energy_rgb": energy.tolist(),
        "dominant_direction": dom.tolist(),
        "dominant_theta_deg": float(np.degrees(theta)),
        "dominant_phi_deg": float(np.degrees(phi)),
        "dominant_definition": "power-weighted (luminance x solid angle) mean direction of the brightest 1 % texels",
    }
    return light, info


def mitsuba_emitter(light: np.ndarray, workdir: Path):
    """The envmap emitter exactly as wavelight exports it (exports.to_mitsuba + exports.mitsuba_xml)."""
    import mitsuba as mi

    big = np.repeat(np.repeat(light, ENV_SUPERSAMPLE, axis=0), ENV_SUPERSAMPLE, axis=1)
    path = workdir / "envmap_mitsuba.exr"
    images.write_exr(path, exports.to_mitsuba(big))
    path_xml = workdir / "emitter.xml"  # (the file as exported: a standalone element with its version)
    path_xml.write_text(exports.mitsuba_xml(str(path)))
    return mi.load_file(str(path_xml))


def emitter_eval(emitter, directions: np.ndarray) -> np.ndarray:
    """(N, 3) radiance Mitsuba's emitter sends along world directions (arriving from them)."""
    import drjit as dr
    import mitsuba as mi

    out = []
    for i in range(0, len(directions), 1 << 21):
        d = directions[i:i + (1 << 21)].astype(np.float32)
        si = dr.zeros(mi.SurfaceInteraction3f, len(d))
        si.wi = mi.Vector3f(-d[:, 0], -d[:, 1], -d[:, 2])
        out.append(to_numpy3(emitter.eval(si)))
    return np.concatenate(out).astype(np.float64)


def check_emitter(emitter, light: np.ndarray) -> dict:
    """What Mitsuba's emitter returns at our pixel centres (upper half), and its energy integrated on
    a grid with 2 x 2 points per Mitsuba pixel (the midpoint rule on its bilinear pieces)."""
    h = light.shape[0]
    ref = light.astype(np.float64)[: h // 2].reshape(-1, 3)
    got = emitter_eval(emitter, cm.latlong_directions(h)[: h // 2].reshape(-1, 3))
    lit = ref.max(axis=1) > 0
    rel = np.abs(got[lit] - ref[lit]) / ref[lit].clip(1e-12)
    fine = 2 * ENV_SUPERSAMPLE * h
    energy = np.zeros(3)
    omega = cm.latlong_solid_angles(fine)
    phi = 2 * np.pi * (np.arange(2 * fine) + 0.5) / (2 * fine)
    for r0 in range(0, fine // 2, 256):
        rows = np.arange(r0, min(r0 + 256, fine // 2))
        theta = np.pi * (rows + 0.5) / fine
        d = cm.spherical_to_direction(theta[:, None], phi[None, :]).reshape(-1, 3)
        energy += (emitter_eval(emitter, d) * omega[rows].reshape(-1, 1)).sum(axis=0)
    truth = (light.astype(np.float64) * cm.latlong_solid_angles(h)[..., None]).sum(axis=(0, 1))
    return {"pixel_centre_max_rel_diff": float(rel.max()), "pixel_centre_median_rel_diff": float(np.median(rel)),
            "energy_ratio_rgb": (energy / truth).tolist(), "supersampling_f": ENV_SUPERSAMPLE}


# -- geometry --------------------------------------------------------------------------------------
@dataclass
class ObjectMesh:
    """The object in world units: positions merged by value (one vertex per position), faces, smooth
    normals; with UVs, `corner_uv` indexes `uv` per face corner (the OBJ's vt)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    source_faces: int
    dropped_faces: int
    uv: np.ndarray | None = None
    corner_uv: np.ndarray | None = None
    notes: list = field(default_factory=list)


def load_object(path: Path, with_uv: bool = False) -> ObjectMesh:
    """Merge coincident vertices, turn y-up into z-up ((x, y, z) -> (x, -z, y)), scale to height 1,
    centre the bounding box in x, y and stand it on z = 0 (as the shared scenes); drop faces that
    wavelight's loader would drop (zero-area, duplicate) so the face count is what it reads."""
    import trimesh

    raw = trimesh.load(str(path), process=False, force="mesh")
    v = np.asarray(raw.vertices, np.float64)
    f = np.asarray(raw.faces, np.int64)
    uniq, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    to_merged = rank[inverse.ravel()]
    pos = uniq[order]
    faces = to_merged[f]
    corner_uv = f.copy() if with_uv else None
    p = np.column_stack([pos[:, 0], -pos[:, 2], pos[:, 1]])
    lo, hi = p.min(0), p.max(0)
    p = (p - [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]) / (hi[2] - lo[2])
    tri = p[faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    degenerate = area2 <= (1e-12 * np.linalg.norm(p.max(0) - p.min(0))) ** 2
    _, keep_first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    duplicate = np.ones(len(faces), bool)
    duplicate[keep_first] = False
    keep = ~(degenerate | duplicate)
    faces = faces[keep]
    notes = []
    if (~keep).any():
        notes.append(f"dropped {int(degenerate.sum())} zero-area and {int((duplicate & ~degenerate).sum())} "
                     f"duplicate faces of the source")
    used = np.unique(faces)
    if len(used) < len(p):
        remap = -np.ones(len(p), np.int64)
        remap[used] = np.arange(len(used))
        notes.append(f"dropped {len(p) - len(used)} vertices no face uses")
        p, faces = p[used], remap[faces]
    normals = np.asarray(trimesh.Trimesh(p, faces, process=False).vertex_normals, np.float64)
    mesh = ObjectMesh(p, faces, normals, len(f), int((~keep).sum()), notes=notes)
    if with_uv:
        if not hasattr(raw.visual, "uv") or raw.visual.uv is None or len(used) < len(pos):
            raise SystemExit(f"{path}: expected UVs on every vertex")
        mesh.uv = np.asarray(raw.visual.uv, np.float64)
        mesh.corner_uv = corner_uv[keep]
    return mesh


def ground_plane() -> tuple[np.ndarray, np.ndarray]:
    """4 x 4 plane at z = 0, 100 x 100 cells, two counter-clockwise (seen from +Z) triangles per cell."""
    n = PLANE_CELLS + 1
    g = np.linspace(-PLANE_SIZE / 2, PLANE_SIZE / 2, n)
    gy, gx = np.meshgrid(g, g, indexing="ij")
    v = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(n * n)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    f = np.stack([np.column_stack([a, b, d]), np.column_stack([a, d, c])], axis=1).reshape(-1, 3)
    return v, f


def mitsuba_mesh(name: str, vertices, faces, normals, bsdf, uv=None):
    """A Mitsuba mesh from arrays (float32 as Mitsuba stores them); `uv` in OBJ convention (v up),
    flipped here as Mitsuba's own OBJ loader does (its bitmap rows start at the top)."""
    import mitsuba as mi

    props = mi.Properties()
    props["bsdf"] = bsdf
    m = mi.Mesh(name, len(vertices), len(faces), props=props, has_vertex_normals=True,
                has_vertex_texcoords=uv is not None)
    params = mi.traverse(m)
    params["vertex_positions"] = mi.Float(np.asarray(vertices, np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(faces, np.uint32).ravel())
    params["vertex_normals"] = mi.Float(np.asarray(normals, np.float32).ravel())
    if uv is not None:
        t = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
        params["vertex_texcoords"] = mi.Float(np.asarray(t, np.float32).ravel())
    params.update()
    return m


def mitsuba_bsdf(material: dict, texture: Path | None = None):
    import mitsuba as mi

    kind = material["type"]
    if kind == "diffuse":
        if texture is not None:
            refl = {"type": "bitmap", "filename": str(texture), "raw": False, "filter_type": "bilinear",
                    "wrap_mode": "repeat"}
        else:
            refl = {"type": "rgb", "value": list(material["kd"])}
        return mi.load_dict({"type": "diffuse", "reflectance": refl})
    d = {"type": kind, "int_ior": material["int_ior"], "ext_ior": material["ext_ior"],
         "diffuse_reflectance": {"type": "rgb", "value": list(material["diffuse_reflectance"])},
         "specular_reflectance": {"type": "rgb", "value": list(material["specular_reflectance"])},
         "nonlinear": material["nonlinear"]}
    if kind == "roughplastic":
        d.update(distribution=material["distribution"], alpha=material["alpha"])
    return mi.load_dict(d)


# -- cameras ---------------------------------------------------------------------------------------
def look_at(view: View) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera (OpenCV: x right, y down, z forward) for a camera on a sphere around the target."""
    az, el = np.radians(view.azimuth_deg), np.radians(view.elevation_deg)
    target = np.asarray(view.target, float)
    eye = target + view.distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def camera_json(view: View) -> dict:
    return {"width": view.width, "height": view.height, "fx": view.focal, "fy": view.focal,
            "cx": view.cx, "cy": view.cy, "dist": [0.0] * 5}


def mitsuba_sensor(view: View, R: np.ndarray, t: np.ndarray, spp: int):
    """Mitsuba perspective camera = the OpenCV camera: Mitsuba's camera frame is (left, up, forward),
    its film pixel j spans [j, j + 1) (centre j + 1/2, ours j), and principal_point_offset moves the
    principal point by -offset x film size (found by tracing rays: 2e-5 px)."""
    import mitsuba as mi

    eye = -R.T @ t
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = -R[0], -R[1], R[2], eye
    return mi.load_dict({
        "type": "perspective", "fov_axis": "x",
        "fov": float(np.degrees(2 * np.arctan(view.width / (2 * view.focal)))),
        "principal_point_offset_x": -(view.cx + 0.5 - view.width / 2) / view.width,
        "principal_point_offset_y": -(view.cy + 0.5 - view.height / 2) / view.height,
        "to_world": mi.ScalarTransform4f(M.tolist()),
        "sampler": {"type": "multijitter", "sample_count": spp},
        "film": {"type": "hdrfilm", "width": view.width, "height": view.height, "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
    })


def camera_rays(sensor, u: np.ndarray, v: np.ndarray):
    """Mitsuba's camera rays through OpenCV pixel positions (u, v) (the ray the position AOV records)."""
    import mitsuba as mi

    w, h = sensor.film().size()
    pos = mi.Point2f(((u + 0.5) / w).astype(np.float32), ((v + 0.5) / h).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    return ray


def to_numpy3(vec) -> np.ndarray:
    """(N, 3) float64 from a Dr.Jit 3-vector array (which numpy sees as (3, N))."""
    return np.array(vec, dtype=np.float64).reshape(3, -1).T


# -- rendering -------------------------------------------------------------------------------------
@dataclass
class Render:
    image: np.ndarray          # (H, W, 3) float32 mean of the passes
    mc_var: np.ndarray         # (H, W, 3) variance of that mean, from the spread of the passes
    spp: int
    passes: int
    seed: int
    seconds: float


def render(scene, sensor_index: int, spp: int, seed: int, pass_spp: int) -> Render:
    """`spp` samples per pixel in passes of `pass_spp` (multijitter, seeds seed, seed + 1, ...)."""
    import mitsuba as mi

    passes = max(2, spp // pass_spp)
    t0 = time.time()
    acc = acc2 = None
    for k in range(passes):
        img = np.array(mi.render(scene, sensor=sensor_index, seed=seed + k), dtype=np.float64)[..., :3]
        acc = img if acc is None else acc + img
        acc2 = img**2 if acc2 is None else acc2 + img**2
    mean = acc / passes
    var = np.clip(acc2 / passes - mean**2, 0, None) * passes / (passes - 1) / passes
    return Render(mean.astype(np.float32), var, passes * pass_spp, passes, seed, time.time() - t0)


def spp_for(nominal: int, pass_spp: int) -> int:
    """The nominal count, or two passes in a --quick dry run."""
    return nominal if pass_spp == PASS_SPP else 2 * pass_spp


def mc_noise(r: Render, mask: np.ndarray) -> float:
    """sqrt(mean MC variance of the pixel means over `mask`) / mean radiance over `mask`."""
    return float(np.sqrt(r.mc_var[mask].mean()) / r.image[mask].mean())


def coverage(scene, sensor, is_object) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: how many of 4 x 4 sub-pixel rays hit the scene / the object."""
    w, h = sensor.film().size()
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    hits = np.zeros((h, w), int)
    obj = np.zeros((h, w), int)
    for a in range(SUBSAMPLES):
        for b in range(SUBSAMPLES):
            u = cols.ravel() - 0.5 + (a + 0.5) / SUBSAMPLES
            v = rows.ravel() - 0.5 + (b + 0.5) / SUBSAMPLES
            si = scene.ray_intersect(camera_rays(sensor, u, v))
            valid = np.array(si.is_valid())
            hits += valid.reshape(h, w)
            obj += (valid & np.array(is_object(si))).reshape(h, w)
    return hits, obj


@dataclass
class SurfacePoints:
    """Per visible object vertex: the face used (the one facing the camera most), the barycentric
    weights of a point 1 % of the way from the vertex to that face's centroid, the point itself
    and its distance to Mitsuba's hit in pixel footprints."""

    vertex: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    point: np.ndarray
    err: np.ndarray


def verify_geometry(scene, sensor, view: View, R, t, vertices: np.ndarray, faces: np.ndarray,
                    plane_pixels: np.ndarray, is_plane) -> tuple[dict, SurfacePoints]:
    """cv2.projectPoints of points on the visible object against Mitsuba's surface point along its own
    camera ray through that sub-pixel position (distance and depth error in pixel footprints,
    depth / f), and the plane pixels' Mitsuba points re-projected by cv2 (px from the pixel centre).

    The points sit next to the vertices, 1 % of the way to the centroid of the vertex's face that
    faces the camera most: a ray aimed exactly at a vertex (or an edge) passes between its triangles
    at float32 precision now and then (Embree is not watertight there; aimed at the teapot's
    vertices 23 % of them "miss" and land on what lies behind). Visible: inside the image, that face
    facing the camera (cosine > 0.05) and the point unoccluded from the camera centre (a ray
    stopping 1e-5 of the distance short of it)."""
    import cv2
    import mitsuba as mi

    K = np.array([[view.focal, 0, view.cx], [0, view.focal, view.cy], [0, 0, 1.0]])
    rvec = cv2.Rodrigues(R)[0]
    eye = -R.T @ t
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True).clip(1e-300)
    to_eye = eye - tri.mean(axis=1)
    cos = np.einsum("ij,ij->i", fn, to_eye / np.linalg.norm(to_eye, axis=1, keepdims=True))
    best = np.full(len(vertices), -1)
    corner = np.zeros(len(vertices), int)
    for f in np.argsort(cos):  # later (more facing) faces overwrite
        best[faces[f]] = f
        corner[faces[f]] = (0, 1, 2)
    has = best >= 0
    vid = np.nonzero(has)[0]
    f_of = best[vid]
    bary = np.full((len(vid), 3), 0.01 / 3)
    bary[np.arange(len(vid)), corner[vid]] += 0.99
    P = np.einsum("nk,nkc->nc", bary, vertices[faces[f_of]])
    uv = cv2.projectPoints(P, rvec, t, K, np.zeros(5))[0][:, 0]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= view.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= view.height - 1)
    to = P - eye
    dist = np.linalg.norm(to, axis=1)
    d = to / dist[:, None]
    ray = mi.Ray3f(mi.Point3f(*(np.full(len(P), c, np.float32) for c in eye)), mi.Vector3f(*d.T.astype(np.float32)))
    ray.maxt = mi.Float((dist * (1 - 1e-5)).astype(np.float32))
    visible = inside & (cos[f_of] > 0.05) & ~np.array(scene.ray_test(ray))
    sel = np.nonzero(visible)[0]
    si = scene.ray_intersect(camera_rays(sensor, uv[sel, 0], uv[sel, 1]))
    p = to_numpy3(si.p)
    depth = (P[sel] - eye) @ R[2]
    footprint = depth / view.focal
    err = np.linalg.norm(p - P[sel], axis=1) / footprint
    derr = np.abs((p - eye) @ R[2] - depth) / footprint
    hit = np.array(si.is_valid())
    err[~hit] = np.inf
    out = {"vertex_to_aov_position_distance_in_pixel_footprints": {
        **stats(err), "depth_error_median": float(np.median(derr[hit])), "missed": int((~hit).sum()),
        "method": "points 1 % from each visible object vertex towards the centroid of its most camera-facing face; "
                  "cv2.projectPoints, then Mitsuba's camera ray (sensor.sample_ray, the ray the position AOV "
                  "records) through that sub-pixel location and scene.ray_intersect; distance to the point / "
                  "(depth / f)"}}
    rows, cols = plane_pixels[:, 0], plane_pixels[:, 1]
    si = scene.ray_intersect(camera_rays(sensor, cols.astype(float), rows.astype(float)))
    on_plane = np.array(si.is_valid()) & np.array(is_plane(si))
    q = to_numpy3(si.p)[on_plane]
    back = cv2.projectPoints(q, rvec, t, K, np.zeros(5))[0][:, 0]
    e = np.linalg.norm(back - np.column_stack([cols, rows])[on_plane], axis=1)
    out["plane_pixel_reprojection_error_px"] = {"n": int(e.size), "mean": float(e.mean()),
                                                "median": float(np.median(e)), "p99": float(np.percentile(e, 99)),
                                                "max": float(e.max())}
    return out, SurfacePoints(vid[sel], f_of[sel], bary[sel], P[sel], err)


def pick_correspondences(vertices: np.ndarray, points: SurfacePoints, view: View, R, t, rng) -> np.ndarray:
    """16 visible object vertices spread over the image (farthest-point order from a random start),
    where Mitsuba's surface next to them is within 0.25 pixel footprints, 5 px inside the image."""
    import cv2

    K = np.array([[view.focal, 0, view.cx], [0, view.focal, view.cy], [0, 0, 1.0]])
    visible = points.vertex
    uv = cv2.projectPoints(vertices[visible], cv2.Rodrigues(R)[0], t, K, np.zeros(5))[0][:, 0]
    ok = ((points.err < 0.25) & (uv[:, 0] > 5) & (uv[:, 0] < view.width - 6) & (uv[:, 1] > 5)
          & (uv[:, 1] < view.height - 6))
    cand, uv = visible[ok], uv[ok]
    chosen = [int(rng.integers(len(cand)))]
    d = np.linalg.norm(uv - uv[chosen[0]], axis=1)
    while len(chosen) < N_CORRESPONDENCES:
        k = int(d.argmax())
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(uv - uv[k], axis=1))
    return cand[chosen]


def write_correspondences(folder: Path, truth_folder: Path, vertices, indices, view: View, R, t, rng) -> dict:
    import cv2

    K = np.array([[view.focal, 0, view.cx], [0, view.focal, view.cy], [0, 0, 1.0]])
    X = vertices[indices]
    uv = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, np.zeros(5))[0][:, 0]
    noisy = uv + rng.normal(0.0, CLICK_NOISE_PX, uv.shape)
    for path, pts, extra in ((folder / "correspondences.csv", noisy, False),
                             (truth_folder / "correspondences_clean.csv", uv, True)):
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(["u", "v", "x", "y", "z"] + (["vertex_index"] if extra else []))
            for (u, v), p, i in zip(pts, X, indices):
                w.writerow([f"{u:.4f}", f"{v:.4f}"] + [f"{c:.7f}" for c in p] + ([int(i)] if extra else []))
    return {"n": len(indices), "rms_noise_px": float(np.sqrt(np.mean(np.sum((noisy - uv) ** 2, axis=1))))}


def add_noise(clean: np.ndarray, mask: np.ndarray, rng) -> tuple[np.ndarray, float]:
    """clean + N(0, sigma) everywhere, sigma = 0.5 % of the mean clean radiance over the mask, clipped
    at 0 (a sensor records no negative light; as the shared scenes)."""
    sigma = NOISE_REL * float(clean[mask].mean())
    noisy = np.clip(clean + rng.normal(0.0, sigma, clean.shape), 0.0, None).astype(np.float32)
    return noisy, sigma


# -- one view of a scene ---------------------------------------------------------------------------
@dataclass
class ViewResult:
    view: View
    R: np.ndarray
    t: np.ndarray
    render: Render
    mask: np.ndarray
    mask_object: np.ndarray
    verification: dict
    points: SurfacePoints | None = None    # the verification points next to the visible object vertices
    corr_indices: np.ndarray | None = None
    corr_info: dict | None = None
    noise_sigma: float | None = None


def shoot_view(scene, sensor_index: int, view: View, spp: int, seed: int, pass_spp: int, vertices, faces,
               is_object, is_plane, rng=None) -> ViewResult:
    R, t = look_at(view)
    sensor = scene.sensors()[sensor_index]
    hits, obj = coverage(scene, sensor, is_object)
    mask = hits == SUBSAMPLES**2
    mask_object = obj * 2 >= SUBSAMPLES**2
    r = render(scene, sensor_index, spp, seed, pass_spp)
    plane_px = np.argwhere(mask)
    ver, points = verify_geometry(scene, sensor, view, R, t, vertices, faces, plane_px, is_plane)
    res = ViewResult(view, R, t, r, mask, mask_object, ver, points)
    if rng is not None:
        res.corr_indices = pick_correspondences(vertices, points, view, R, t, rng)
        k = np.searchsorted(points.vertex, res.corr_indices)
        ver["correspondence_vertices"] = {**stats(points.err[k]),
                                          "definition": "the same distance next to the 16 chosen vertices"}
    print(f"    {view.name}: {r.spp} spp in {r.passes} passes, {r.seconds:.1f} s; mask {int(mask.sum())} px, "
          f"object {int(mask_object.sum())} px; MC noise {100 * mc_noise(r, mask):.2f} %; vertices vs Mitsuba: "
          f"median {ver['vertex_to_aov_position_distance_in_pixel_footprints']['median']:.2g} / max "
          f"{ver['vertex_to_aov_position_distance_in_pixel_footprints']['max']:.2g} footprints; plane "
          f"re-projection median {ver['plane_pixel_reprojection_error_px']['median']:.2g} px")
    return res


def write_view_files(folder: Path, res: ViewResult, image: np.ndarray, with_object_mask: bool = True) -> None:
    write_json(folder / "camera.json", camera_json(res.view))
    write_json(folder / "pose.json", {"R": res.R.tolist(), "t": res.t.tolist()})
    write_mask(folder / "mask.png", res.mask)
    if with_object_mask:
        write_mask(folder / "mask_object.png", res.mask_object)
    write_exr(folder / "image.exr", image)


# -- texture (the textured set) --------------------------------------------------------------------
def bilinear(texture: np.ndarray, uv_mitsuba: np.ndarray) -> np.ndarray:
    """Mitsuba's `bitmap` lookup (bilinear, repeat; texel (i, j)'s centre at ((j + 1/2) / W, (i + 1/2) / H),
    row 0 at v = 0 = the image's top) on the linear texture."""
    h, w = texture.shape[:2]
    x = uv_mitsuba[:, 0] * w - 0.5
    y = uv_mitsuba[:, 1] * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    t = lambda r, c: texture[r % h, c % w]  # noqa: E731
    return ((1 - fy) * ((1 - fx) * t(y0, x0) + fx * t(y0, x0 + 1))
            + fy * ((1 - fx) * t(y0 + 1, x0) + fx * t(y0 + 1, x0 + 1)))


def texture_means(obj: ObjectMesh, texture: np.ndarray, rng, n: int = 2_000_000) -> dict:
    """The texture's mean linear albedo: over all texels, and over Spot's surface (area-weighted:
    uniform random surface points, their interpolated UVs, Mitsuba's bilinear lookup)."""
    tri = obj.vertices[obj.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    f = rng.choice(len(area), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    bary = np.column_stack([1 - s, s * (1 - r2), s * r2])
    uv = np.einsum("nk,nkc->nc", bary, obj.uv[obj.corner_uv[f]])
    vals = bilinear(texture, np.column_stack([uv[:, 0], 1 - uv[:, 1]]))
    return {"texel_mean_linear": texture.reshape(-1, 3).mean(0).tolist(),
            "surface_mean_linear": vals.mean(0).tolist(),
            "surface_mean_samples": n,
            "surface_mean_mc_error": (vals.std(0) / np.sqrt(n)).tolist()}


def split_vertices(obj: ObjectMesh) -> np.ndarray:
    """For each UV vertex (an OBJ vt; trimesh's vertex after it splits the seams) its position index."""
    to_pos = np.zeros(len(obj.uv), np.int64)
    to_pos[obj.corner_uv.ravel()] = obj.faces.ravel()
    return to_pos


def write_obj(path: Path, name: str, obj: ObjectMesh, plane_v, plane_f) -> None:
    """Spot then the ground: v (positions), vt, vn, two material groups."""
    pv = np.vstack([obj.vertices, plane_v])
    pn = np.vstack([obj.normals, np.tile([0.0, 0.0, 1.0], (len(plane_v), 1))])
    ground_uv = (plane_v[:, :2] + PLANE_SIZE / 2) / PLANE_SIZE
    uv = np.vstack([obj.uv, ground_uv])
    nv, nt = len(obj.vertices), len(obj.uv)
    lines = [f"# {name}: Spot (usemtl spot, {len(obj.faces)} faces, first {nv} v / {nt} vt / {nv} vn) then "
             f"the ground plane {PLANE_SIZE:g}x{PLANE_SIZE:g} at z=0, {PLANE_CELLS}x{PLANE_CELLS} cells "
             f"(usemtl ground). Z up. Written by tools/render_mitsuba_scenes.py", "mtllib mesh.mtl"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in pv]
    lines += [f"vt {u:.9g} {v:.9g}" for u, v in uv]
    lines += [f"vn {x:.7g} {y:.7g} {z:.7g}" for x, y, z in pn]
    lines += ["g spot", "usemtl spot"]
    lines += [f"f {a + 1}/{ta + 1}/{a + 1} {b + 1}/{tb + 1}/{b + 1} {c + 1}/{tc + 1}/{c + 1}"
              for (a, b, c), (ta, tb, tc) in zip(obj.faces, obj.corner_uv)]
    lines += ["g ground", "usemtl ground"]
    lines += [f"f {a}/{a - nv + nt}/{a} {b}/{b - nv + nt}/{b} {c}/{c - nv + nt}/{c}"
              for a, b, c in (plane_f + nv + 1)]
    path.write_text("\n".join(lines) + "\n")


def write_mtl(path: Path, spot_kd, ground_kd) -> None:
    path.write_text(
        "# Kd are linear RGB. spot: the area-weighted mean of its texture (sRGB-decoded); the texture is the albedo\n"
        "newmtl spot\nKa 0 0 0\n" + "Kd {:.6f} {:.6f} {:.6f}\n".format(*spot_kd)
        + "Ks 0 0 0\nillum 1\nmap_Kd spot_texture.png\n\n"
        "newmtl ground\nKa 0 0 0\n" + "Kd {:.6f} {:.6f} {:.6f}\n".format(*ground_kd) + "Ks 0 0 0\nillum 1\n")


def check_obj_loading(path: Path, spot: ObjectMesh, n_ground_faces: int) -> dict:
    """How trimesh and wavelight's load_mesh read the two-material OBJ."""
    import trimesh

    from pipelines.io import scene_files as sc

    loaded = trimesh.load(str(path), process=False)
    info = {"trimesh_version": trimesh.__version__, "trimesh_load_type": type(loaded).__name__}
    if isinstance(loaded, trimesh.Scene):
        info["geometries"] = {}
        for key, g in loaded.geometry.items():
            vis = g.visual
            mat = getattr(vis, "material", None)
            info["geometries"][key] = {
                "faces": len(g.faces), "vertices": len(g.vertices), "visual": type(vis).__name__,
                "material": type(mat).__name__ if mat is not None else None,
                "material_name": getattr(mat, "name", None),
                "uv": None if getattr(vis, "uv", None) is None else list(np.asarray(vis.uv).shape),
                "has_image": getattr(mat, "image", None) is not None
                or getattr(mat, "baseColorTexture", None) is not None,
            }
        info["dump_order"] = [getattr(getattr(g.visual, "material", None), "name", None) for g in loaded.dump()]
    mesh = sc.load_mesh(path)
    F, G = len(spot.faces), n_ground_faces
    ours = spot.vertices[spot.faces]
    if len(mesh.faces) != F + G:
        raise SystemExit(f"{path}: load_mesh reads {len(mesh.faces)} faces, not {F + G} ({mesh.notes})")
    spot_first = np.abs(mesh.vertices[mesh.faces[:F]] - ours).max() < 1e-6
    spot_last = np.abs(mesh.vertices[mesh.faces[G:]] - ours).max() < 1e-6
    if not (spot_first or spot_last):
        raise SystemExit(f"{path}: load_mesh does not keep Spot's faces together and in order")
    info["load_mesh"] = {"vertices": len(mesh.vertices), "faces": len(mesh.faces), "notes": list(mesh.notes),
                         "part_order": ["spot", "ground"] if spot_first else ["ground", "spot"],
                         "spot_faces": [0, F - 1] if spot_first else [G, G + F - 1],
                         "ground_faces": [F, F + G - 1] if spot_first else [0, G - 1],
                         "spot_faces_in_file_order": True}
    return info


def texture_check(scene, sensor, view: View, R, t, spot: ObjectMesh, texture, points: SurfacePoints) -> dict:
    """Mitsuba's albedo (bsdf.eval_diffuse_reflectance at its own hit) at the verification points on
    Spot against our bilinear lookup of the linear texture at their UV (interpolated from the face's
    own corner UVs): the UV flip and the sRGB decoding agree."""
    import cv2

    ok = points.err < 0.25
    P, f, bary = points.point[ok], points.face[ok], points.bary[ok]
    K = np.array([[view.focal, 0, view.cx], [0, view.focal, view.cy], [0, 0, 1.0]])
    uv_px = cv2.projectPoints(P, cv2.Rodrigues(R)[0], t, K, np.zeros(5))[0][:, 0]
    si = scene.ray_intersect(camera_rays(sensor, uv_px[:, 0], uv_px[:, 1]))
    got = to_numpy3(si.bsdf().eval_diffuse_reflectance(si))
    vt = np.einsum("nk,nkc->nc", bary, spot.uv[spot.corner_uv[f]])
    ref = bilinear(texture, np.column_stack([vt[:, 0], 1 - vt[:, 1]]))
    unflipped = bilinear(texture, vt)
    rel = np.abs(got - ref).max(axis=1) / ref.max(axis=1).clip(1e-6)
    rel_unflipped = np.abs(got - unflipped).max(axis=1) / unflipped.max(axis=1).clip(1e-6)
    return {"n": int(len(P)), "median_rel_diff": float(np.median(rel)), "p95_rel_diff": float(np.percentile(rel, 95)),
            "max_rel_diff": float(rel.max()), "fraction_above_1pct": float(np.mean(rel > 0.01)),
            "fraction_above_1pct_if_v_not_flipped": float(np.mean(rel_unflipped > 0.01)),
            "note": "most of Spot's texture is one skin colour, so only the spots and the face tell a flip"}


# -- scenes ----------------------------------------------------------------------------------------
def mitsuba_info() -> dict:
    import drjit as dr
    import mitsuba as mi

    return {"version": mi.__version__, "drjit": dr.__version__, "variant": mi.variant()}


def render_settings(pass_spp: int) -> dict:
    return {"integrator": "direct (direct illumination only, shadows, no interreflection), hide_emitters=true",
            "sampler": f"multijitter, passes of {pass_spp} spp, seeds seed + k", "reconstruction_filter": "box",
            "envmap_supersampling_f": ENV_SUPERSAMPLE, "envmap_emitter": "exports.mitsuba_xml (to_world = "
            "MITSUBA_TO_WORLD), image exports.to_mitsuba(supersampled light)"}


def view_params(res: ViewResult, spp_nominal: int) -> dict:
    v = res.view
    return {"azimuth_deg": v.azimuth_deg, "elevation_deg": v.elevation_deg, "distance": v.distance,
            "target": list(v.target), "intrinsics": camera_json(v), "spp": res.render.spp, "passes": res.render.passes,
            "seed": res.render.seed, "render_time_s": res.render.seconds,
            "mc_noise_rel_mask": mc_noise(res.render, res.mask),
            "mc_noise_rel_object": mc_noise(res.render, res.mask_object),
            "mean_clean_radiance_mask": float(res.render.image[res.mask].mean()),
            "mask_pixels": int(res.mask.sum()), "object_pixels": int(res.mask_object.sum()),
            **({"added_noise_sigma": res.noise_sigma, "added_noise_rel": NOISE_REL} if res.noise_sigma else {})}


def fmt_material(material: dict) -> str:
    return json.dumps({k: v for k, v in material.items() if k != "formula"})


def formula(material: dict) -> str:
    if material["type"] == "diffuse":
        return "f = kd/pi (Mitsuba diffuse)"
    spec = ("microfacet F(wi.h) D(h) G(wi, wo) / (4 cos_i cos_o), Smith G, sample_visible" if material["type"] ==
            "roughplastic" else "ideal mirror reflection weighted by F(cos_i)")
    return (f"Mitsuba {material['type']}: specular = {spec} (F: dielectric Fresnel, eta = int_ior/ext_ior); "
            "diffuse = diffuse_reflectance / (1 - Fdr_int) / eta^2 / pi * (1 - F_ext(cos_i)) (1 - F_ext(cos_o)), "
            "with F_ext the interface's (rough) reflectance and Fdr_int its mean internal reflectance "
            "(nonlinear=false: the 1/(1 - Fdr_int) does not depend on the albedo)")


def scene_mesh_arrays(obj: ObjectMesh):
    pv, pf = ground_plane()
    V = np.vstack([obj.vertices, pv])
    F = np.vstack([obj.faces, pf + len(obj.vertices)])
    N = np.vstack([obj.normals, np.tile([0.0, 0.0, 1.0], (len(pv), 1))])
    return V, F, N, pv, pf


def render_scene(spec: Scene, dest: Path, shared: Path, pass_spp: int) -> None:
    import mitsuba as mi

    from copy_test_data import write_ply
    from pipelines.io import scene_files as sc

    t_start = time.time()
    final = dest / "scenes" / spec.name
    out = final.with_name(spec.name + ".partial")
    shutil.rmtree(out, ignore_errors=True)
    (out / "truth").mkdir(parents=True)
    work = Path(tempfile.mkdtemp(prefix="wavelight_mitsuba_"))
    print(f"== {spec.name} ({spec.set}): {spec.mesh}, {spec.light} turned {spec.light_azimuth_deg:g} deg ==")
    light, linfo = build_light(shared, spec.light, spec.light_azimuth_deg)
    write_exr(out / "truth" / "env_latlong.exr", light)
    emitter = mitsuba_emitter(light, work)
    echeck = check_emitter(emitter, light)
    print(f"    light: scale {linfo['scale_applied']:.6f}, dominant theta {linfo['dominant_theta_deg']:.1f} phi "
          f"{linfo['dominant_phi_deg']:.1f}; Mitsuba's envmap at our pixel centres max rel "
          f"{echeck['pixel_centre_max_rel_diff']:.1e}, energy ratio "
          f"{', '.join(f'{x:.5f}' for x in echeck['energy_ratio_rgb'])}")

    obj = load_object(shared / "meshes" / spec.mesh, with_uv=spec.textured)
    V, F, N, pv, pf = scene_mesh_arrays(obj)
    n_obj_v, n_obj_f = len(obj.vertices), len(obj.faces)
    geometry = {"mesh_source": f"data/meshes/{spec.mesh}", "source_faces": obj.source_faces,
                "object_vertices": n_obj_v, "object_faces": n_obj_f, "plane_size": PLANE_SIZE,
                "plane_cells": PLANE_CELLS, "total_vertices": len(V), "total_faces": len(F),
                "placement": "merged coincident vertices, (x, y, z) -> (x, -z, y), height 1, bbox centred in x, y, "
                             "on z = 0; normals: trimesh vertex_normals of the merged object; plane normal +Z",
                "notes": obj.notes}
    if spec.textured:
        texture_file = out / "spot_texture.png"
        shutil.copyfile(shared / "meshes" / "spot" / "spot_texture.png", texture_file)
        texture = images.read_image(texture_file).pixels.astype(np.float64)
        tex_info = texture_means(obj, texture, np.random.default_rng(spec.seed + 5))
        ground_kd = spec.material["parts"]["ground"]["kd"]
        spot_mean = np.array(tex_info["surface_mean_linear"])
        tex_info["ground_over_spot_albedo_rgb"] = (np.array(ground_kd) / spot_mean).tolist()
        tex_info["ground_over_spot_albedo_luminance"] = float(np.dot(ground_kd, LUMA) / np.dot(spot_mean, LUMA))
        write_obj(out / "mesh.obj", spec.name, obj, pv, pf)
        write_mtl(out / "mesh.mtl", spot_mean, ground_kd)
        geometry["obj_loading"] = check_obj_loading(out / "mesh.obj", obj, len(pf))
        geometry["uv_vertices"] = len(obj.uv)
        split = split_vertices(obj)
        spot_shape = mitsuba_mesh("spot", obj.vertices[split], obj.corner_uv, obj.normals[split],
                                  mitsuba_bsdf({"type": "diffuse"}, texture=texture_file), uv=obj.uv)
        ground_shape = mitsuba_mesh("ground", pv, pf, np.tile([0.0, 0.0, 1.0], (len(pv), 1)),
                                    mitsuba_bsdf(spec.material["parts"]["ground"]))
        shapes = {"spot": spot_shape, "ground": ground_shape}
        spot_ptr, ground_ptr = mi.ShapePtr(spot_shape), mi.ShapePtr(ground_shape)

        def is_object(si):
            return si.shape == spot_ptr

        def is_plane(si):
            return si.shape == ground_ptr
        print(f"    OBJ: trimesh -> {geometry['obj_loading']['trimesh_load_type']}; load_mesh part order "
              f"{geometry['obj_loading']['load_mesh']['part_order']}; ground/spot albedo (lum) "
              f"{tex_info['ground_over_spot_albedo_luminance']:.4f}")
    else:
        write_ply(out / "mesh.ply", V, N, F, comments=(
            f"{spec.name}: object (first {n_obj_v} vertices / {n_obj_f} faces) then the ground plane; "
            f"tools/render_mitsuba_scenes.py",))
        back = sc.load_mesh(out / "mesh.ply")
        geometry["load_mesh_check"] = {
            "same_faces": bool(np.array_equal(back.faces, F)), "notes": list(back.notes),
            "max_vertex_diff": float(np.abs(back.vertices - V).max()),
            "max_normal_diff": float(np.abs(back.vertex_normals - N / np.linalg.norm(N, axis=1, keepdims=True)).max())}
        if not geometry["load_mesh_check"]["same_faces"]:
            raise SystemExit(f"{spec.name}: load_mesh does not read the faces written ({back.notes})")
        shapes = {"mesh": mitsuba_mesh("scene", V, F, N, mitsuba_bsdf(spec.material))}

        def is_object(si):
            return np.array(si.prim_index) < n_obj_f

        def is_plane(si):
            return np.array(si.prim_index) >= n_obj_f

    novel = View("novel", spec.view.azimuth_deg + NOVEL_AZIMUTH_OFFSET, spec.view.elevation_deg, spec.view.distance,
                 spec.view.cx, spec.view.cy)
    views = [spec.view, *spec.extra_views, novel]
    sensors = {f"sensor_{i}": mitsuba_sensor(v, *look_at(v), pass_spp) for i, v in enumerate(views)}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct", "hide_emitters": True},
                          "emitter": emitter, **shapes, **sensors})
    for i, v in enumerate(views):  # the scene keeps the sensors in the order given
        eye = -look_at(v)[0].T @ look_at(v)[1]
        got = np.array(scene.sensors()[i].world_transform().matrix)[:3, 3].ravel()
        assert np.allclose(got, eye, atol=1e-4), (v.name, got, eye)

    obj_vertices = obj.vertices
    results = []
    for i, v in enumerate(views):
        is_novel = v is novel
        spp = SPP_NOVEL if is_novel else SPP_INPUT
        seed = spec.seed + (100 if is_novel else 200 * i)
        rng = None if is_novel else np.random.default_rng([spec.seed, i, 2])
        res = shoot_view(scene, i, v, spp_for(spp, pass_spp), seed, pass_spp, obj_vertices, obj.faces, is_object,
                         is_plane, rng)
        if not is_novel:
            noisy, res.noise_sigma = add_noise(res.render.image, res.mask, np.random.default_rng([spec.seed, i, 1]))
            folder = out if i == 0 else out / "views" / v.name
            truth_folder = out / "truth" if i == 0 else out / "truth" / "views" / v.name
            write_view_files(folder, res, noisy)
            if i == 0:
                write_srgb_png(out / "image.png", noisy)
            if i == 0:  # the extra views' clean renders are left out to keep the data small (~0.6 MB each)
                write_exr(truth_folder / "image_clean.exr", res.render.image)
            res.corr_info = write_correspondences(folder, truth_folder, obj_vertices, res.corr_indices, v,
                                                  res.R, res.t, rng)
        else:
            write_view_files(out / "truth" / "novel_view", res, res.render.image)
        results.append(res)

    material = dict(spec.material)
    if not spec.textured:
        material["formula"] = formula(material)
    else:
        material = json.loads(json.dumps(material))
        material["parts"]["spot"]["kd_mean"] = tex_info["surface_mean_linear"]
        material["parts"]["spot"]["formula"] = "f = texture(uv)/pi (Mitsuba diffuse, bitmap raw=false)"
        material["parts"]["ground"]["formula"] = formula(material["parts"]["ground"])
        material["ground_over_spot_albedo_rgb"] = tex_info["ground_over_spot_albedo_rgb"]
    write_json(out / "truth" / "material.json", material)

    main = results[0]
    params = {"name": spec.name, "set": spec.set, "mitsuba": mitsuba_info(), "light": linfo, "envmap_check": echeck,
              "geometry": geometry,
              "camera": {k: view_params(main, SPP_INPUT)[k] for k in ("azimuth_deg", "elevation_deg", "distance",
                                                                     "target", "intrinsics")},
              "render": {**render_settings(pass_spp), **{k: x for k, x in view_params(main, SPP_INPUT).items()
                                                          if k not in ("azimuth_deg", "elevation_deg", "distance",
                                                                       "target", "intrinsics")}},
              "verification": {**main.verification, "correspondences": main.corr_info},
              "novel_view": {**view_params(results[-1], SPP_NOVEL), "verification": results[-1].verification},
              "material": material}
    if spec.extra_views:
        params["views"] = {r.view.name: {**view_params(r, SPP_INPUT), "verification": r.verification,
                                         "correspondences": r.corr_info} for r in results[1:-1]}
        params["texture"] = tex_info
        params["texture_check"] = texture_check(scene, scene.sensors()[0], main.view, main.R, main.t, obj, texture,
                                                main.points)
        tc = params["texture_check"]
        print(f"    texture check: Mitsuba albedo vs our lookup at {tc['n']} points: max rel {tc['max_rel_diff']:.2g}, "
              f"{100 * tc['fraction_above_1pct']:.1f} % above 1 % (with v not flipped: "
              f"{100 * tc['fraction_above_1pct_if_v_not_flipped']:.1f} %)")
    params["render_time_s"] = time.time() - t_start
    write_json(out / "truth" / "scene_params.json", params)
    (out / "README.txt").write_text(scene_readme(spec, params, results))
    shutil.rmtree(work, ignore_errors=True)
    shutil.rmtree(final, ignore_errors=True)
    out.rename(final)
    print(f"    -> {final} ({dir_size(final) / 1e6:.2f} MB, {params['render_time_s']:.0f} s)")


def dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


# -- README.txt ------------------------------------------------------------------------------------
LATLONG_TEXT = ("256x128 lat-long (theta=pi(r+.5)/H from +Z, phi=2pi(c+.5)/W from +X to +Y), "
                "lower hemisphere zeroed")


def light_lines(linfo: dict, indent: int) -> list[str]:
    pad = " " * indent
    return [f"{pad}source {linfo['source']} (y-up; columns mirrored: phi = 2pi(1-u)), azimuth rotation "
            f"{linfo['azimuth_rotation_deg']:g} deg, scale {linfo['scale_applied']:.6f} (max luminance irradiance "
            f"over upward normals = pi)",
            f"{pad}dominant light (brightest 1% texels) theta={linfo['dominant_theta_deg']:.1f} "
            f"phi={linfo['dominant_phi_deg']:.1f} deg"]


def pose_text(v: View) -> str:
    return (f"camera azimuth {v.azimuth_deg % 360:g} deg, elevation {v.elevation_deg:g} deg, distance {v.distance:g}, "
            f"looking at ({','.join(f'{x:g}' for x in v.target)})")


def verification_text(ver: dict) -> str:
    a = ver["vertex_to_aov_position_distance_in_pixel_footprints"]
    p = ver["plane_pixel_reprojection_error_px"]
    return (f"cv2.projectPoints of points next to {a['n']} visible object vertices (1% towards a face centroid) vs "
            f"Mitsuba's surface point on its camera ray\n  through that sub-pixel location: median {a['median']:.2g} / "
            f"max {a['max']:.2g} pixel footprints; "
            f"plane pixels: Mitsuba's point re-projected with cv2 lands {p['median']:.2g} px (median, max "
            f"{p['max']:.2g}) from the pixel centre")


def scene_readme(spec: Scene, params: dict, results: list[ViewResult]) -> str:
    main, novel = results[0], results[-1]
    r, g, m = params["render"], params["geometry"], params["mitsuba"]
    v = spec.view
    lines = [f"Scene {spec.name}  (set {spec.set})  -- rendered with Mitsuba {m['version']} {m['variant']} by "
             f"tools/render_mitsuba_scenes.py", "", "INPUTS (what the tool gets)",
             f"  image.exr            linear float32 RGB, {v.width}x{v.height}, clean render + Gaussian noise "
             f"sigma={main.noise_sigma:.3g} (0.5% of mean radiance over mask.png), clipped at 0",
             "  image.png            sRGB 8-bit of image.exr (clipped at 1)"]
    plane = f"ground plane {PLANE_SIZE:g}x{PLANE_SIZE:g} at z=0 ({PLANE_CELLS}x{PLANE_CELLS} cells)"
    if spec.textured:
        nf = g["object_faces"]
        lines += [f"  mesh.obj             object (first {g['object_vertices']} vertices / {nf} faces) + {plane}; "
                  f"v/vt/vn per corner,",
                  f"                       two material groups: faces 0-{nf - 1} 'usemtl spot' (Spot, {g['uv_vertices']} "
                  f"vt; trimesh splits its UV seams into {g['uv_vertices']} vertices),",
                  f"                       faces {nf}-{g['total_faces'] - 1} 'usemtl ground'; per-vertex normals (vn)",
                  "  mesh.mtl             Kd of each part (linear RGB; spot: the texture's area-weighted mean), "
                  "map_Kd spot_texture.png for spot",
                  "  spot_texture.png     Spot's colour texture (sRGB 8-bit, 1024x1024), byte for byte from the source"]
        lm = g["obj_loading"]["load_mesh"]
        if lm["part_order"][0] != "spot":
            lines += [f"  NOTE                 trimesh {g['obj_loading']['trimesh_version']} returns the OBJ's material "
                      "groups in reverse file order (a Scene of two",
                      "                       geometries 'ground', 'spot'), so pipelines.scene.load_mesh(mesh.obj) lists "
                      f"the ground first: faces {lm['ground_faces'][0]}-{lm['ground_faces'][1]}",
                      f"                       ground, {lm['spot_faces'][0]}-{lm['spot_faces'][1]} Spot (in file "
                      f"order; {lm['vertices']} vertices). Take the parts by material name, not by position."]
    else:
        lines += [f"  mesh.ply             object (first {g['object_vertices']} vertices / {g['object_faces']} faces) + "
                  f"{plane}; per-vertex normals;",
                  "                       binary PLY (float64 positions, float32 normals, int32 triangles)"]
    lines += [f"  camera.json          OpenCV intrinsics, pixel (0,0) centre at u=v=0: fx=fy={v.focal:g} cx={v.cx:g} "
              f"cy={v.cy:g}, dist=0",
              f"  pose.json            world->camera x_cam = R X + t ({pose_text(v)})",
              f"  mask.png             pixels fully covered ({SUBSAMPLES**2}/{SUBSAMPLES**2} sub-samples) by "
              f"object+plane; mask_object.png: object at >= 50% coverage",
              f"  correspondences.csv  u,v,x,y,z: {N_CORRESPONDENCES} visible object vertices, projections + "
              f"N(0, {CLICK_NOISE_PX} px) noise"]
    if spec.extra_views:
        lines += ["  views/NAME/          more photos under the same light, same protocol (image.exr camera.json "
                  "pose.json mask.png mask_object.png correspondences.csv):"]
        for res in results[1:-1]:
            lines += [f"                         {res.view.name}: {pose_text(res.view)}, cx={res.view.cx:g} "
                      f"cy={res.view.cy:g}, noise sigma={res.noise_sigma:.3g}"]
    lines += ["", "TRUTH (not for the tool)", f"  truth/env_latlong.exr   {LATLONG_TEXT}", *light_lines(params["light"], 26)]
    if spec.textured:
        t = params["texture"]
        gk = spec.material["parts"]["ground"]["kd"]
        sm = t["surface_mean_linear"]
        lines += ["  truth/material.json     parts: spot = Mitsuba diffuse with spot_texture.png as bitmap (sRGB, decoded to "
                  "linear, bilinear, repeat)",
                  f"                          ground = Mitsuba diffuse kd={gk} (plain coloured Lambertian)",
                  "  relative albedo         ground over Spot = kd_ground / mean_S(albedo), per channel, where mean_S is "
                  "the area-weighted mean",
                  "                          over Spot's surface of the linear (sRGB-decoded, bilinearly filtered) "
                  "texture albedo:",
                  f"                          mean_S = ({sm[0]:.4f}, {sm[1]:.4f}, {sm[2]:.4f}) -> ratio "
                  f"({', '.join(f'{x:.4f}' for x in t['ground_over_spot_albedo_rgb'])}); "
                  f"luminance ratio {t['ground_over_spot_albedo_luminance']:.4f}",
                  f"                          (mean over all texels instead: ({', '.join(f'{x:.4f}' for x in t['texel_mean_linear'])}))"]
    else:
        lines += [f"  truth/material.json     {fmt_material(spec.material)}",
                  "                          (object and plane share it)"]
    lines += [f"  truth/image_clean.exr   noise-free render (MC noise {100 * r['mc_noise_rel_mask']:.2f}% of mean over "
              f"mask; multijitter, {r['spp']} spp)"]
    if spec.extra_views:
        lines += ["  truth/views/NAME/       correspondences_clean.csv of each extra view (its MC noise: scene_params.json "
                  "views; no clean render kept)"]
    nv = params["novel_view"]
    lines += [f"  truth/novel_view/       image.exr camera.json pose.json mask.png mask_object.png: camera azimuth "
              f"{novel.view.azimuth_deg % 360:g} deg (+{NOVEL_AZIMUTH_OFFSET:g}), {nv['spp']} spp, noise-free "
              f"(MC noise {100 * nv['mc_noise_rel_mask']:.2f}%)",
              "  truth/scene_params.json every parameter + verification numbers",
              "  truth/correspondences_clean.csv  noise-free projections and vertex indices (0-based, into the mesh "
              "file's vertex list" + (" = the OBJ's v lines)" if spec.textured else ")"),
              "",
              "RENDERING: integrator \"direct\" (direct light only, shadowed, no interreflection), hide_emitters, "
              "box pixel filter, multijitter",
              f"  in passes of {PASS_SPP} spp; light handed to Mitsuba by wavelight's pipelines/io/exports.py "
              f"(f={ENV_SUPERSAMPLE} supersampling, to_mitsuba column mirror,",
              "  mitsuba_xml emitter with to_world = MITSUBA_TO_WORLD); Mitsuba's envmap returns our pixel values at "
              f"our pixel centres to {params['envmap_check']['pixel_centre_max_rel_diff']:.1g}"
              f" and their energy to {max(abs(x - 1) for x in params['envmap_check']['energy_ratio_rgb']):.1g}.",
              f"VERIFICATION: {verification_text(params['verification'])}"]
    if spec.textured:
        tc = params["texture_check"]
        lines += [f"  texture: Mitsuba's albedo at those {tc['n']} points = our bilinear lookup of the linear texture at "
                  f"their UV to {tc['max_rel_diff']:.1g} (max; with v not flipped {100 * tc['fraction_above_1pct_if_v_not_flipped']:.0f}% "
                  "of them would be > 1% off)"]
    return "\n".join(lines) + "\n"


# -- the forward-model set: a lone sphere ----------------------------------------------------------
def sphere_mesh(subdivisions: int = 5):
    """The tessellation a forward model can use instead of Mitsuba's exact sphere (not stored: the
    recipe is in the README): an icosphere on the unit sphere, normals = positions."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = np.asarray(ico.vertices, np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    f = np.asarray(ico.faces, np.int64)
    sag = 1.0 - np.linalg.norm(v[f].mean(axis=1), axis=1).min()
    return v, f, float(sag)


def forward_readme(out: Path, lights: dict, sag: float, nv: int, nf: int, view_check: dict) -> str:
    v = FORWARD_VIEW
    lines = ["Forward-model check set  -- rendered with Mitsuba by tools/render_mitsuba_scenes.py --set forward", "",
             "A lone sphere (radius 1 at the origin, NO ground plane) seen by one camera, under a sunny and an "
             "overcast light,", "for six dielectric materials; noise-free renders for checking a forward model "
             "(BRDF, light units, Fresnel).", "",
             f"  camera.json          OpenCV intrinsics {v.width}x{v.height}, fx=fy={v.focal:g} cx={v.cx:g} cy={v.cy:g}, "
             "dist=0 (pixel (0,0) centre at u=v=0)",
             f"  pose.json            world->camera x_cam = R X + t ({pose_text(v)})",
             f"  mask.png             pixels fully covered ({SUBSAMPLES**2}/{SUBSAMPLES**2} sub-samples) by the sphere",
             "  light_sun.exr, light_overcast.exr   " + LATLONG_TEXT]
    for name, info in lights.items():
        lines += [f"    {name}:", *light_lines(info, 6)]
    lines += ["  geometry             Mitsuba's analytic `sphere` shape: exact positions and normals, no mesh file. "
              "Intersect the sphere",
              "                       analytically, or tessellate it, e.g. trimesh.creation.icosphere(subdivisions=5) "
              f"({nv} vertices / {nf} faces;",
              f"                       its facets sag up to {sag:.1e} inside; use normals = positions)",
              "  NAME/image.exr       linear float32 RGB, noise-free, multijitter "
              f"{SPP_FORWARD} spp; NAME/params.json: material, light file, camera, MC noise",
              "", "  all: diffuse_reflectance " + str(FORWARD_KD) + ", int_ior 1.49, ext_ior 1.000277, "
              "specular_reflectance 1, nonlinear false; glint px: luminance > 10 x the mask's median",
              "  NAME                    material                            MC noise (of the mean over mask.png)"]
    for name in FORWARD_NAMES:
        p = out / name / "params.json"
        if p.is_file():
            prm = json.loads(p.read_text())
            mat = prm["material"]
            desc = mat["type"] + (f" {mat['distribution']} alpha={mat['alpha']:g}" if "alpha" in mat else "")
            rr = prm["render"]
            lines += [f"  {name:<24}{desc:<36}{100 * rr['mc_noise_rel_mask']:.2f}%"
                      + (f" ({rr['glint_pixels']} glint px: {100 * rr['mc_noise_rel_glints']:.1f}%; others "
                         f"{100 * rr['mc_noise_rel_mask_without_glints']:.2f}%)" if rr["glint_pixels"] else "")]
    lines += ["", "RENDERING: integrator \"direct\", hide_emitters, box filter, light via pipelines/io/exports.py "
              f"(f={ENV_SUPERSAMPLE}, to_mitsuba, mitsuba_xml).",
              f"VERIFICATION: Mitsuba's hit along its camera ray through each mask pixel centre vs the analytic "
              f"intersection of the OpenCV ray: max {view_check['max_footprints']:.1g} pixel footprints."]
    return "\n".join(lines) + "\n"


def render_forward(names, dest: Path, shared: Path, pass_spp: int) -> None:
    import mitsuba as mi

    out = dest / "forward"
    out.mkdir(parents=True, exist_ok=True)
    view = FORWARD_VIEW
    R, t = look_at(view)
    write_json(out / "camera.json", camera_json(view))
    write_json(out / "pose.json", {"R": R.tolist(), "t": t.tolist()})
    sv, sf, sag = sphere_mesh()
    work = Path(tempfile.mkdtemp(prefix="wavelight_mitsuba_"))
    lights, emitters, checks = {}, {}, {}
    for lname, (source, az) in FORWARD_LIGHTS.items():
        light, lights[lname] = build_light(shared, source, az)
        write_exr(out / f"light_{lname}.exr", light)
        (work / lname).mkdir()
        emitters[lname] = mitsuba_emitter(light, work / lname)
        checks[lname] = check_emitter(emitters[lname], light)
    mask, view_check = None, None
    for k, name in enumerate(FORWARD_NAMES):
        if name not in names:
            continue
        lname, mname = name.split("_", 1)
        material = FORWARD_MATERIALS[mname]
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct", "hide_emitters": True},
                              "emitter": emitters[lname],
                              "sphere": {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0,
                                         "bsdf": mitsuba_bsdf(material)},
                              "sensor": mitsuba_sensor(view, R, t, pass_spp)})
        sensor = scene.sensors()[0]
        if mask is None:
            hits, _ = coverage(scene, sensor, lambda si: np.array(si.is_valid()))
            mask = hits == SUBSAMPLES**2
            write_mask(out / "mask.png", mask)
            px = np.argwhere(mask)
            si = scene.ray_intersect(camera_rays(sensor, px[:, 1].astype(float), px[:, 0].astype(float)))
            p = to_numpy3(si.p)
            K = np.array([[view.focal, 0, view.cx], [0, view.focal, view.cy], [0, 0, 1.0]])
            rays = np.linalg.solve(K, np.column_stack([px[:, 1], px[:, 0], np.ones(len(px))]).T).T @ R
            rays /= np.linalg.norm(rays, axis=1, keepdims=True)
            eye = -R.T @ t
            b = rays @ eye
            tt = -b - np.sqrt(b**2 - (eye @ eye - 1.0))
            exact = eye + tt[:, None] * rays
            depth = (exact - eye) @ R[2]
            d = np.linalg.norm(p - exact, axis=1) / (depth / view.focal)
            view_check = {"n": int(len(d)), "median_footprints": float(np.median(d)), "max_footprints": float(d.max())}
        r = render(scene, 0, spp_for(SPP_FORWARD, pass_spp), FORWARD_SEED + 100 * k, pass_spp)
        write_exr(out / name / "image.exr", r.image)
        lum = r.image @ LUMA
        glint = mask & (lum > 10 * np.median(lum[mask]))
        write_json(out / name / "params.json", {
            "name": name, "mitsuba": mitsuba_info(),
            "material": {**material, "formula": formula(material)},
            "light": {"file": f"light_{lname}.exr", **lights[lname]}, "envmap_check": checks[lname],
            "camera": {"camera": "camera.json", "pose": "pose.json", "mask": "mask.png",
                       **{k2: x for k2, x in view.__dict__.items() if k2 != "name"}},
            "geometry": {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0, "ground_plane": False,
                         "mitsuba_shape": "sphere (analytic: exact positions and normals)",
                         "tessellation": {"recipe": "trimesh.creation.icosphere(subdivisions=5, radius=1), "
                                                    "normals = positions", "vertices": len(sv), "faces": len(sf),
                                          "max_sag": sag}},
            "render": {**render_settings(pass_spp), "spp": r.spp, "passes": r.passes, "seed": r.seed,
                       "render_time_s": r.seconds, "mc_noise_rel_mask": mc_noise(r, mask),
                       "glint_pixels": int(glint.sum()), "glint_definition": "luminance > 10 x the median over the mask",
                       "mc_noise_rel_mask_without_glints": mc_noise(r, mask & ~glint),
                       "mc_noise_rel_glints": mc_noise(r, glint) if glint.any() else None,
                       "mean_radiance_mask": float(r.image[mask].mean()), "mask_pixels": int(mask.sum())},
            "verification": view_check})
        print(f"    forward/{name}: {r.spp} spp, {r.seconds:.1f} s, MC noise {100 * mc_noise(r, mask):.2f} % "
              f"({int(glint.sum())} glint pixels; without them {100 * mc_noise(r, mask & ~glint):.2f} %)")
    if view_check is None:  # nothing rendered: keep the README's verification from an earlier run
        prm = next((json.loads((out / n / "params.json").read_text()) for n in FORWARD_NAMES
                    if (out / n / "params.json").is_file()), None)
        view_check = prm["verification"] if prm else {"max_footprints": float("nan")}
    (out / "README.txt").write_text(forward_readme(out, lights, sag, len(sv), len(sf), view_check))
    shutil.rmtree(work, ignore_errors=True)


# -- harness sanity: a diffuse render against wavelight's forward model ------------------------------
def diffuse_check(name: str, dest: Path, resolution: int, pass_spp: int) -> dict:
    """Render scene NAME's input view with Mitsuba `diffuse` 0.7 (its mesh, camera and light from the
    scene folder) and compare with wavelight's forward model as tests/conftest.py does it."""
    import mitsuba as mi

    from pipelines.geometry import camera as cam
    from pipelines.geometry import raycast
    from pipelines.model import materials as rd
    from pipelines.model import render
    from pipelines.io import scene_files as sc
    from pipelines.geometry import visibility as vis

    spec = ALL_SCENES[name]
    if spec.textured:
        raise SystemExit("--diffuse-check takes a scene with one mesh.ply (set plastic)")
    folder = dest / "scenes" / name
    light = images.read_latlong(folder / "truth" / "env_latlong.exr")
    work = Path(tempfile.mkdtemp(prefix="wavelight_mitsuba_"))
    emitter = mitsuba_emitter(light.astype(np.float32), work)
    mesh = sc.load_mesh(folder / "mesh.ply")
    shape = mitsuba_mesh("scene", mesh.vertices, mesh.faces, mesh.vertex_normals,
                         mitsuba_bsdf({"type": "diffuse", "kd": [0.7] * 3}))
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct", "hide_emitters": True},
                          "emitter": emitter, "mesh": shape,
                          "sensor": mitsuba_sensor(spec.view, *look_at(spec.view), pass_spp)})
    r = render(scene, 0, spp_for(SPP_INPUT, pass_spp), spec.seed + 900, pass_spp)
    mask = images.read_mask(folder / "mask.png")
    t0 = time.time()
    camera, pose = sc.read_camera(folder / "camera.json"), sc.read_pose(folder / "pose.json")
    backend = raycast.make_backend(mesh)
    samples, diag = cam.pixel_samples(camera, pose, mesh, backend, mask, edge_margin=1)
    cube = cm.CubeMap(resolution)
    V = vis.compute_visibility(backend, samples, cube)
    ours = render.render(V, cm.latlong_to_cube(light, cube), rd.Material(kd=(0.7, 0.7, 0.7)))
    ref = r.image[samples.pixel[:, 0], samples.pixel[:, 1]].astype(np.float64)
    n_obj = json.loads((folder / "truth" / "scene_params.json").read_text())["geometry"]["object_faces"]
    on_obj = samples.face < n_obj

    def rel(sel):
        return float(np.sqrt(np.mean((ours[sel] - ref[sel]) ** 2)) / np.sqrt(np.mean(ref[sel] ** 2)))

    result = {"scene": name, "resolution": resolution, "used_pixels": int(len(ref)),
              "relative_rmse": rel(slice(None)), "relative_rmse_object": rel(on_obj),
              "relative_rmse_plane": rel(~on_obj), "brightness_ratio": float(ours.mean() / ref.mean()),
              "mitsuba_mc_noise_rel_mask": mc_noise(r, mask), "mitsuba_spp": r.spp, "mitsuba_seconds": r.seconds,
              "wavelight_seconds": time.time() - t0}
    print(json.dumps(result, indent=1))
    shutil.rmtree(work, ignore_errors=True)
    return result


# -- command line ----------------------------------------------------------------------------------
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[1:20]))
    parser.add_argument("--set", choices=("plastic", "forward", "textured", "all"), help="render this set")
    parser.add_argument("--scene", action="append", default=[], metavar="NAME",
                        help="render only this scene or forward render (repeatable); see --list")
    parser.add_argument("--dest", type=Path, default=HERE / "tests" / "data", help="default: tests/data")
    parser.add_argument("--shared", type=Path, default=Path("/work/shared/data"),
                        help="the shared data (envmaps/, meshes/); read only here")
    parser.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (scalar_rgb if LLVM fails)")
    parser.add_argument("--quick", action="store_true", help="dry run: 2 passes of 16 spp (use another --dest)")
    parser.add_argument("--list", action="store_true", help="list the scene names and exit")
    parser.add_argument("--diffuse-check", metavar="NAME", help="harness sanity check on a rendered plastic scene")
    parser.add_argument("-R", "--resolution", type=int, default=64, help="cube-map resolution for --diffuse-check")
    parser.add_argument("--json", type=Path, help="--diffuse-check: also write the numbers here")
    args = parser.parse_args(argv)
    sets = {"plastic": [s.name for s in PLASTIC_SCENES], "textured": [s.name for s in TEXTURED_SCENES],
            "forward": list(FORWARD_NAMES)}
    if args.list:
        for k, v in sets.items():
            print(f"{k}: {' '.join(v)}")
        return 0
    import mitsuba as mi

    try:
        mi.set_variant(args.variant)
    except Exception as exc:  # LLVM missing: say so, the caller may pass --variant scalar_rgb
        parser.error(f"Mitsuba variant {args.variant} unavailable ({exc}); try --variant scalar_rgb")
    pass_spp = 16 if args.quick else PASS_SPP
    if args.diffuse_check:
        result = diffuse_check(args.diffuse_check, args.dest, args.resolution, pass_spp)
        if args.json:
            write_json(args.json, result)
        return 0
    if not args.set and not args.scene:
        parser.error("give --set, --scene or --diffuse-check")
    wanted = [n for k in (("plastic", "forward", "textured") if args.set == "all" else (args.set,) if args.set else ())
              for n in sets[k]]
    known = {n for v in sets.values() for n in v}
    for n in args.scene:
        if n not in known:
            parser.error(f"unknown scene {n!r}; see --list")
    if args.scene:
        wanted = [n for n in wanted if n in args.scene] if args.set else list(args.scene)
    t0 = time.time()
    for n in wanted:
        if n in ALL_SCENES:
            render_scene(ALL_SCENES[n], args.dest, args.shared, pass_spp)
    forward = [n for n in wanted if n in FORWARD_NAMES]
    if forward:
        print(f"== forward set: {len(forward)} renders ==")
        render_forward(forward, args.dest, args.shared, pass_spp)
    print(f"done in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
