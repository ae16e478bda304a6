"""The scenes of tests/test_exports_tools.py on wavelight's side, and how to render them in the tools.

A camera (Blender's convention: it looks along its local -Z with +Y up, horizontal sensor fit, the
principal point at the image's centre) and unit spheres, lit by a light given as wavelight's
lat-long (README: Conventions). Here: the rays through each pixel's footprint (both tools integrate
the pixel's area), the spheres' normals and view directions there, wavelight's render of them
(`pipelines.model.render.transport` with V = 1: a lone sphere does not shadow itself), a numerical
GGX reference for glossy spheres (isolated in `GLOSSY_REFERENCE` so that it can later be pointed at
wavelight's own microfacet model), the sun's direction from a ball's shadow and its prediction from
a lat-long, and the runners: Blender (Cycles, CPU) in a subprocess of a Python that has `bpy`
(tests/blender_render.py), and Mitsuba 3 (scalar_rgb) in process.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from pipelines.light import cubemap
from pipelines.model import render as model
from pipelines.model.materials import Material

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
BLENDER_SCRIPT = TESTS / "blender_render.py"


# -- camera and sphere -----------------------------------------------------------------------------

def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """4x4 camera -> world of a camera at `eye` looking at `target` (columns: right, up, back)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(back, right), back, eye
    return m


def pixel_rays(camera: dict, width: int, height: int, offsets=((0.5, 0.5),)):
    """World ray origins and unit directions (K, H, W, 3) through the given offsets inside each pixel
    (column, row from the top-left corner; (0.5, 0.5) = the centre) for a camera spec."""
    m = np.asarray(camera["matrix"], np.float64)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    origins, dirs = [], []
    for dc, dr in offsets:
        # image plane coordinates, x right and y up, in units of the image's width
        x = (cols + dc - width / 2) / width
        y = (height / 2 - rows - dr) / width
        if camera["type"] == "PERSP":
            f = camera["lens_mm"] / camera["sensor_mm"]
            local = np.stack([x, y, -f * np.ones_like(x)], -1)
            o = np.broadcast_to(m[:3, 3], local.shape)
        else:
            s = camera["ortho_scale"]
            local = np.broadcast_to(np.array([0.0, 0.0, -1.0]), x.shape + (3,))
            o = m[:3, 3] + (s * x)[..., None] * m[:3, 0] + (s * y)[..., None] * m[:3, 1]
        d = local @ m[:3, :3].T
        dirs.append(d / np.linalg.norm(d, axis=-1, keepdims=True))
        origins.append(np.array(o))
    return np.stack(origins), np.stack(dirs)


def hit_sphere(origins, dirs, center, radius):
    """Distance along each ray to the sphere (nan where it misses) and the impact parameter / radius."""
    oc = origins - np.asarray(center, np.float64)
    b = np.einsum("...k,...k->...", oc, dirs)
    c = np.einsum("...k,...k->...", oc, oc) - radius**2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.nan)
    impact = np.sqrt(np.maximum(np.einsum("...k,...k->...", oc, oc) - b * b, 0)) / radius
    return t, impact


def footprint_offsets(k: int):
    """k x k sub-pixel positions (column, row offsets from the pixel's top-left corner) of equal
    weight: the midpoint rule over the pixel's square, which both tools integrate (Cycles' box
    pixel filter is one pixel wide whatever its width says -- its Normal pass is the pixel-area
    mean of the sphere's normals to 2e-5, not the centre's; Mitsuba's box rfilter, radius 0.5)."""
    c = (np.arange(k) + 0.5) / k
    return [(dc, dr) for dr in c for dc in c]


def sphere_view(camera: dict, width: int, height: int, center=(0.0, 0.0, 0.0), radius: float = 1.0,
                k: int = 3, margin: float = 1.0):
    """The sphere seen through each pixel's footprint: normals and view directions (H, W, K, 3) at
    K = k x k sub-pixel positions, and `inside` (H, W): pixels whose centre is at least `margin`
    pixels from the silhouette (their whole footprint sees the sphere; mixed pixels are left
    out, as from wavelight's own used pixels)."""
    o, d = pixel_rays(camera, width, height, footprint_offsets(k))
    t, impact = hit_sphere(o, d, center, radius)
    hit = np.isfinite(t)
    p = o + np.where(hit, t, 0.0)[..., None] * d
    normals = np.moveaxis((p - np.asarray(center)) / radius, 0, 2)
    views = np.moveaxis(-d, 0, 2)
    oc, dc = pixel_rays(camera, width, height)
    tc, ic = hit_sphere(oc[0], dc[0], center, radius)
    gy, gx = np.gradient(ic)  # pixels per unit impact parameter -> distance to the silhouette in pixels
    inside = hit.all(axis=0) & np.isfinite(tc) & ((1.0 - ic) > margin * np.hypot(gx, gy))
    return normals, views, inside


def footprint_mean(render, normals: np.ndarray, views: np.ndarray, *args, **kwargs) -> np.ndarray:
    """(P, 3) a per-direction render ((n, 3) normals, views -> (n, 3)) averaged over each pixel's
    K sub-samples ((P, K, 3) normals and views)."""
    P, K = normals.shape[:2]
    out = render(*args[:1], normals.reshape(-1, 3), views.reshape(-1, 3), *args[1:], **kwargs)
    return out.reshape(P, K, -1).mean(axis=1)


# -- lights --------------------------------------------------------------------------------------------

def sun_direction(theta_deg: float, phi_deg: float) -> np.ndarray:
    return cubemap.spherical_to_direction(np.radians(theta_deg), np.radians(phi_deg))


def sky_with_sun(height: int = 128, sun_theta_deg: float = 50.0, sun_phi_deg: float = 65.0,
                 sun_radius_deg: float = 2.5, sun_irradiance: float = 3.0, sky: bool = True) -> np.ndarray:
    """A lat-long light (H, 2H, 3), zero below the horizon: a smooth sky whose colour and brightness
    change with azimuth and elevation (so a mirrored, turned or flipped map renders differently) and
    a disc-shaped sun whose irradiance at normal incidence is `sun_irradiance` (each pixel holds the
    sun's radiance times the share of its area inside the disc, 8 x 8 sub-samples)."""
    H, W = height, 2 * height
    d = cubemap.latlong_directions(H)
    img = np.zeros((H, W, 3))
    if sky:
        up = np.clip(d[..., 2], 0, None)
        img = np.stack([0.30 + 0.15 * d[..., 0] + 0.05 * up, 0.35 + 0.10 * d[..., 1] + 0.05 * up,
                        0.45 + 0.25 * up - 0.05 * d[..., 0]], -1) * (d[..., 2:3] > 0)
    if sun_irradiance > 0:
        s = sun_direction(sun_theta_deg, sun_phi_deg)
        k = 8
        r, c = np.mgrid[0:H * k, 0:W * k]
        theta = np.pi * (r + 0.5) / (H * k)
        phi = 2 * np.pi * (c + 0.5) / (W * k)
        sub = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
        cover = (sub @ s > np.cos(np.radians(sun_radius_deg))).reshape(H, k, W, k).mean(axis=(1, 3))
        omega = cubemap.latlong_solid_angles(H)
        # irradiance of the disc as the map holds it: sum L cover omega cos
        cos = np.clip(d @ s, 0, None)
        radiance = sun_irradiance / np.sum(cover * omega * cos)
        img = img + (radiance * cover)[..., None] * np.array([1.0, 0.95, 0.85])
    return img


# -- wavelight's render and the glossy reference -------------------------------------------------------

def wavelight_render(latlong: np.ndarray, normals: np.ndarray, views: np.ndarray, material: Material,
                     resolution: int = 32, chunk: int = 2048) -> np.ndarray:
    """(P, 3) radiance of pixels with these normals and view directions under the lat-long light, by
    wavelight's forward model: the light on wavelight's cube map (`latlong_to_cube`, the resampling
    every wavelight command does) and `transport` with V = 1."""
    cube = cubemap.CubeMap(resolution, hemisphere=not np.any(latlong[latlong.shape[0] // 2:]))
    texels = cubemap.latlong_to_cube(latlong, cube)
    out = np.zeros((len(normals), 3))
    for s in range(0, len(normals), chunk):
        sl = slice(s, s + chunk)
        V = np.ones((len(normals[sl]), cube.n_texels), np.float32)
        D, S = model.transport(V, normals[sl], views[sl], cube, material)
        out[sl] = (D.astype(np.float64) @ texels) * np.asarray(material.kd)
        if S is not None:
            out[sl] += (S.astype(np.float64) @ texels) * np.asarray(material.ks)
    return out


def smith_lambda_ggx(alpha: float, cos: np.ndarray) -> np.ndarray:
    """Smith's Lambda for GGX: (sqrt(1 + alpha^2 tan^2) - 1) / 2."""
    c2 = np.clip(cos, 1e-6, 1.0) ** 2
    return 0.5 * (np.sqrt(1.0 + alpha**2 * (1.0 - c2) / c2) - 1.0)


def ggx_numeric(latlong: np.ndarray, normals: np.ndarray, views: np.ndarray, alpha: float,
                shadowing: str = "height-correlated", sub: int = 1, chunk: int = 1024) -> np.ndarray:
    """(P, 3) radiance of a white GGX conductor (F = 1) under the lat-long light, integrated
    numerically over the light's pixels (each split into sub x sub directions with their share of
    its solid angle): sum over l of L(l) omega(l) f(l, v) (N.l), with f = D G / (4 (N.l)(N.v)).

    D = alpha^2 / (pi ((N.h)^2 (alpha^2 - 1) + 1)^2), N.h = (N.l + N.v) / |l + v|. `shadowing`:
    "height-correlated" G = 1 / (1 + Lambda(l) + Lambda(v)) (Cycles' GGX) or "separable"
    G = G1(l) G1(v), G1 = 1 / (1 + Lambda) (Mitsuba's microfacet distribution). float32 inside."""
    H, W = latlong.shape[:2]
    r, c = np.mgrid[0:H * sub, 0:W * sub]
    theta = np.pi * (r + 0.5) / (H * sub)
    phi = 2 * np.pi * (c + 0.5) / (W * sub)
    dirs = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    edges = np.pi * np.arange(H * sub + 1) / (H * sub)  # exact solid angle of each sub-pixel
    omega = (2 * np.pi / (W * sub)) * (np.cos(edges[:-1]) - np.cos(edges[1:]))
    weight = np.repeat(np.repeat(latlong, sub, axis=0), sub, axis=1) * omega[:, None, None]
    keep = np.any(weight > 0, axis=-1)
    L, Lw = dirs[keep].astype(np.float32), weight[keep].astype(np.float32)
    a2 = np.float32(alpha**2)
    out = np.zeros((len(normals), 3))
    for s in range(0, len(normals), chunk):
        n, v = normals[s:s + chunk].astype(np.float32), views[s:s + chunk].astype(np.float32)
        nl = n @ L.T
        nv = np.einsum("pk,pk->p", n, v)[:, None]
        nh = (nl + nv) / np.sqrt(np.maximum(2.0 + 2.0 * (v @ L.T), 1e-12))
        D = a2 / (np.float32(np.pi) * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
        lam_l, lam_v = smith_lambda_ggx(alpha, nl).astype(np.float32), smith_lambda_ggx(alpha, nv).astype(np.float32)
        if shadowing == "height-correlated":
            G = 1.0 / (1.0 + lam_l + lam_v)
        elif shadowing == "separable":
            G = 1.0 / ((1.0 + lam_l) * (1.0 + lam_v))
        else:
            raise ValueError(f"unknown shadowing {shadowing!r}")
        f = np.where((nl > 0) & (nv > 0), D * G / (4.0 * np.maximum(nv, 1e-6)), 0.0).astype(np.float32)
        out[s:s + chunk] = f @ Lw
    return out


# The glossy sphere's reference, in one place: today the numerical GGX above; when wavelight has its
# own microfacet model, point this at `wavelight_render` with that material.
def GLOSSY_REFERENCE(latlong, normals, views, alpha, shadowing):
    return ggx_numeric(latlong, normals, views, alpha, shadowing)


# -- errors --------------------------------------------------------------------------------------------

def relative_rmse(values: np.ndarray, reference: np.ndarray) -> float:
    """sqrt(mean((values - reference)^2)) / sqrt(mean(reference^2)) over all pixels and channels."""
    return float(np.sqrt(np.mean((values - reference) ** 2)) / np.sqrt(np.mean(reference**2)))


def noise_level(first: np.ndarray, second: np.ndarray, reference: np.ndarray) -> float:
    """The relative RMS noise of one render, from two renders with different seeds:
    E[(A - B)^2] = 2 sigma^2."""
    return float(np.sqrt(np.mean((first - second) ** 2) / 2) / np.sqrt(np.mean(reference**2)))


def angle_deg(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


# -- Blender -------------------------------------------------------------------------------------------

def blender_python() -> tuple[str | None, str]:
    """A Python interpreter that has `bpy` (Blender as a module), and where it was found, or
    (None, why not). bpy pins numpy < 2 while wavelight needs numpy >= 2, so it lives in its own
    venv: `make venv-blender` -> .venv-blender; WAVELIGHT_BPY_PYTHON names another."""
    env = os.environ.get("WAVELIGHT_BPY_PYTHON")
    if env:
        return (env, "WAVELIGHT_BPY_PYTHON") if Path(env).is_file() else (None, f"WAVELIGHT_BPY_PYTHON={env} not found")
    local = REPO / ".venv-blender" / "bin" / "python"
    if local.is_file():
        return str(local), str(local)
    if importlib.util.find_spec("bpy") is not None:
        return sys.executable, "this interpreter"
    return None, ("bpy (Blender as a Python module) is not installed: `make venv-blender` installs it into "
                  ".venv-blender (~375 MB download, ~1 GB on disk), or set WAVELIGHT_BPY_PYTHON")


def render_blender(jobs: dict[str, dict], workdir: Path, timeout: float = 600.0) -> dict[str, dict]:
    """Run tests/blender_render.py on the named job specs in one bpy process (bpy's import is most
    of a small render's time). Returns per job {"passes": {"Combined": (H, W, 3), "Normal": ...}
    (if rendered), "world": the world's description}."""
    python, where = blender_python()
    if python is None:
        raise RuntimeError(where)
    workdir.mkdir(parents=True, exist_ok=True)
    specs = []
    for name, spec in jobs.items():
        specs.append(dict(spec, output=str(workdir / f"{name}.exr"), output_world=str(workdir / f"{name}_world.json")))
    jobs_path = workdir / "jobs.json"
    jobs_path.write_text(json.dumps({"jobs": specs}, indent=1))
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    proc = subprocess.run([python, str(BLENDER_SCRIPT), str(jobs_path)], capture_output=True, text=True,
                          timeout=timeout, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"Blender failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    out = {}
    for name, spec in zip(jobs, specs):
        out[name] = {"world": json.loads(Path(spec["output_world"]).read_text()), "log": proc.stdout}
        if spec.get("render", True):
            out[name]["passes"] = read_layers(spec["output"])
    return out


def read_layers(path) -> dict[str, np.ndarray]:
    """The RGB / XYZ passes of a Blender multilayer EXR by pass name (channels 'Layer.Pass.C')."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(oiio.geterror())
    out: dict[str, dict[str, np.ndarray]] = {}
    try:
        subimage = 0
        while inp.seek_subimage(subimage, 0):
            spec = inp.spec()
            px = inp.read_image(subimage, 0, 0, spec.nchannels, oiio.FLOAT)
            for i, ch in enumerate(spec.channelnames):
                parts = ch.split(".")
                out.setdefault(parts[-2] if len(parts) >= 2 else "", {})[parts[-1]] = px[..., i]
            subimage += 1
    finally:
        inp.close()
    layers = {}
    for name, chans in out.items():
        keys = [k for k in ("R", "G", "B") if k in chans] or [k for k in ("X", "Y", "Z") if k in chans]
        if len(keys) == 3:
            layers[name] = np.stack([chans[k] for k in keys], -1).astype(np.float64)
    return layers


# -- Mitsuba 3 -----------------------------------------------------------------------------------------

def mitsuba_camera(camera: dict, width: int, height: int, spp: int, seed: int) -> dict:
    """The camera spec (Blender's convention, horizontal fit) as Mitsuba's perspective sensor: the
    same eye, forward and up, horizontal field of view 2 atan(sensor / 2 lens), box pixel filter,
    a low-discrepancy sampler (like Cycles' Sobol; each seed scrambles it anew, so two seeds are
    two independent renders)."""
    import mitsuba as mi

    m = np.asarray(camera["matrix"], np.float64)
    eye, forward, up = m[:3, 3], -m[:3, 2], m[:3, 1]
    fov = float(np.degrees(2 * np.arctan(0.5 * camera["sensor_mm"] / camera["lens_mm"])))
    return {"type": "perspective", "fov": fov, "fov_axis": "x", "near_clip": 0.01, "far_clip": 1000.0,
            "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=(eye + forward).tolist(),
                                                       up=up.tolist()),
            "sampler": {"type": "ldsampler", "sample_count": spp, "seed": seed},
            "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                     "pixel_format": "rgb"}}


def mitsuba_bsdf(material: dict):
    if material["type"] == "file":  # a BSDF file as a user loads it (the export's bsdf.xml)
        import mitsuba as mi

        return mi.load_file(str(material["path"]))
    if material["type"] == "diffuse":
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(material.get("color", (1, 1, 1)))}}
    if material["type"] == "roughconductor":  # material "none": eta 0, k 1, so F = 1 (a white GGX lobe)
        return {"type": "roughconductor", "material": "none", "distribution": "ggx", "alpha": float(material["alpha"])}
    if material["type"] in ("roughplastic", "plastic"):  # the microfacet dielectric (wavelight's `plastic`)
        out = {"type": material["type"], "int_ior": float(material.get("ior", 1.49)), "ext_ior": 1.0,
               "nonlinear": False, "diffuse_reflectance": {"type": "rgb", "value": list(material.get("color", (1, 1, 1)))}}
        if material["type"] == "roughplastic":
            out.update(distribution=material.get("distribution", "ggx"), alpha=float(material["alpha"]))
        return out
    raise ValueError(f"unknown material {material['type']!r}")


def mitsuba_shape(obj: dict) -> dict:
    import mitsuba as mi

    if obj["kind"] == "sphere":
        return {"type": "sphere", "center": list(obj["center"]), "radius": float(obj["radius"]),
                "bsdf": mitsuba_bsdf(obj["material"])}
    h = float(obj["size"]) / 2  # Mitsuba's rectangle: [-1, 1]^2 at z = 0, normal +Z
    return {"type": "rectangle", "bsdf": mitsuba_bsdf(obj["material"]),
            "to_world": mi.ScalarTransform4f().translate([0, 0, float(obj.get("z", 0.0))]).scale([h, h, 1])}


def render_mitsuba(emitter_xml: Path, camera: dict, width: int, height: int, objects: list[dict], spp: int,
                   seeds=(1, 2), aov_spp: int = 0) -> dict[str, np.ndarray]:
    """Render objects lit by the exported emitter, loaded from its file as a user would
    (`mi.load_file("emitter.xml")`, which finds light.exr next to it), with Mitsuba's `direct`
    integrator (one emitter and one BSDF sample per pass, combined by MIS), once per seed
    ("seed1", ...); with aov_spp > 0 also the pixel means of the shading normal ("normal") and
    the position ("position") of what each pixel sees."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    emitter = mi.load_file(str(emitter_xml))
    shapes = {f"shape{i}": mitsuba_shape(o) for i, o in enumerate(objects)}
    out = {}

    def render(integrator, samples, seed):
        scene = mi.load_dict({"type": "scene", "emitter": emitter, **shapes, "integrator": integrator,
                              "sensor": mitsuba_camera(camera, width, height, samples, seed)})
        return np.array(mi.render(scene, spp=samples), dtype=np.float64)

    for seed in seeds:
        out[f"seed{seed}"] = render({"type": "direct", "emitter_samples": 1, "bsdf_samples": 1}, spp, seed)[..., :3]
    if aov_spp:
        aov = render({"type": "aov", "aovs": "nn:sh_normal,pos:position"}, aov_spp, 0)
        out["normal"], out["position"] = aov[..., 0:3], aov[..., 3:6]
    return out


# -- the scenes ----------------------------------------------------------------------------------------

LIGHT_HEIGHT = 64  # rows of the test light (2.8 deg pixels)
SUN = (50.0, 65.0)  # the sun's theta (from the zenith) and phi (from +X towards +Y), degrees


def scene_light() -> np.ndarray:
    return sky_with_sun(LIGHT_HEIGHT, *SUN)


def sun_light() -> np.ndarray:
    """The same sun without the sky (for the shadow scenes: nothing but the sun darkens there)."""
    return sky_with_sun(LIGHT_HEIGHT, *SUN, sky=False)


def pair_camera(width: int = 128, height: int = 64) -> tuple[dict, list[np.ndarray]]:
    """A camera 15 deg above the horizon at azimuth 20 deg (so the sun, 45 deg round, lights part
    of what it sees and its terminator shows), looking at two unit spheres side by side
    (centres +-1.25 along the camera's right): each ~25 px in radius in a 128 x 64 image."""
    m = look_at(7.0 * sun_direction(75.0, 20.0), [0.0, 0.0, 0.0])
    centres = [-1.25 * m[:3, 0], 1.25 * m[:3, 0]]
    return {"type": "PERSP", "lens_mm": 48.0, "sensor_mm": 36.0, "matrix": m.tolist()}, centres


def shadow_camera() -> dict:
    """Straight down from 12 above the origin, seeing the plane z = 0 over about -4..4."""
    return {"type": "PERSP", "lens_mm": 54.0, "sensor_mm": 36.0,
            "matrix": look_at([0.0, 0.0, 12.0], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0)).tolist()}


SHADOW_CENTER = np.array([0.0, 0.0, 2.0])  # a black ball of radius 0.5 over a white ground plane
SHADOW_OBJECTS = [{"kind": "plane", "size": 40.0, "z": 0.0, "material": {"type": "diffuse", "color": [1, 1, 1]}},
                  {"kind": "sphere", "center": SHADOW_CENTER.tolist(), "radius": 0.5,
                   "material": {"type": "diffuse", "color": [0, 0, 0]}}]


def sun_from_shadow(radiance: np.ndarray, position: np.ndarray, center=SHADOW_CENTER,
                    window: float = 1.5) -> tuple[np.ndarray, int]:
    """The sun's direction as a ball's shadow on the ground shows it, under a light that is a sun
    alone. The ball's shadow for one direction s is an ellipse of area pi r^2 / s_z centred at
    c - c_z s / s_z (c the ball's centre), so the darkness-weighted centroid of the ground (the
    darkness of a point: the sun's irradiance it misses) is c - c_z E[s / s_z], E over the sun's
    radiance (`shadow_direction` predicts it from a lat-long). Positions come from the renderer
    itself (its Position pass / AOV). The lit level is the ground's median outside the shadow;
    the centroid is taken over a window of `window` around the umbra's centre (noise in it
    averages out, unclipped; outside it would pull towards the image's centre).
    Returns (unit direction from the shadow's centre to the ball's, number of umbra pixels)."""
    lum = radiance @ np.array([0.2126, 0.7152, 0.0722])
    ground = np.abs(position[..., 2]) < 1e-3
    lit = np.median(lum[ground])
    umbra = ground & (lum < 0.5 * lit)
    near = np.hypot(*(position[..., :2] - position[umbra][:, :2].mean(axis=0)).transpose(2, 0, 1)) < window
    lit = np.median(lum[ground & ~near])
    sel = ground & near
    dark = lit - lum[sel]
    p = (dark[:, None] * position[sel]).sum(axis=0) / dark.sum()
    d = np.asarray(center) - p
    return d / np.linalg.norm(d), int(umbra.sum())


def shadow_direction(latlong: np.ndarray) -> np.ndarray:
    """The direction `sun_from_shadow` finds for an exact render of a lat-long sun: from the point
    c - c_z E[s / s_z] to c, i.e. normalize(E[s / s_z]), E weighted by each pixel's luminance x
    solid angle (pixels above the horizon)."""
    H = latlong.shape[0]
    d = cubemap.latlong_directions(H)
    w = (latlong @ np.array([0.2126, 0.7152, 0.0722])) * cubemap.latlong_solid_angles(H)
    up = (d[..., 2] > 1e-6) & (w > 0)
    m = (w[up][:, None] * d[up] / d[up][:, 2:3]).sum(axis=0)
    return m / np.linalg.norm(m)


def mean_direction(latlong: np.ndarray) -> np.ndarray:
    """The light's mean direction: normalize(sum of luminance x solid angle x direction)."""
    H = latlong.shape[0]
    w = (latlong @ np.array([0.2126, 0.7152, 0.0722])) * cubemap.latlong_solid_angles(H)
    m = (w[..., None] * cubemap.latlong_directions(H)).sum(axis=(0, 1))
    return m / np.linalg.norm(m)


def agreement(first, second, reference):
    """Two renders with different seeds against a reference: the relative RMSE of their mean, the
    mean's own noise, the bias left beyond that noise, and the brightness ratio."""
    mean = 0.5 * (first + second)
    err = relative_rmse(mean, reference)
    noise = noise_level(first, second, reference) / np.sqrt(2)
    return {"error": err, "noise": noise, "bias": float(np.sqrt(max(0.0, err**2 - noise**2))),
            "ratio": float(mean.mean() / reference.mean())}


def mitsuba_opencv_sensor(camera: dict, pose: dict, spp: int, seed: int = 0) -> dict:
    """A scene folder's OpenCV camera (camera.json, pose.json: x_cam = R X + t) as Mitsuba's perspective
    sensor: Mitsuba's camera frame is (left, up, forward), its film pixel j spans [j, j + 1) (our pixel
    centre j), principal_point_offset moves the principal point by -offset x film size."""
    import mitsuba as mi

    R, t = np.asarray(pose["R"], np.float64), np.asarray(pose["t"], np.float64)
    w, h = int(camera["width"]), int(camera["height"])
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = -R[0], -R[1], R[2], -R.T @ t
    return {"type": "perspective", "fov_axis": "x", "fov": float(np.degrees(2 * np.arctan(w / (2 * camera["fx"])))),
            "principal_point_offset_x": -(camera["cx"] + 0.5 - w / 2) / w,
            "principal_point_offset_y": -(camera["cy"] + 0.5 - h / 2) / h,
            "to_world": mi.ScalarTransform4f(m.tolist()), "sampler": {"type": "independent", "sample_count": spp,
                                                                      "seed": seed},
            "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}, "pixel_format": "rgb"}}


def render_mitsuba_parts(scene: Path, export: Path, spp: int, bsdf_files: dict | None = None, seed: int = 0
                         ) -> np.ndarray:
    """The scene folder's mesh, one Mitsuba shape per part (written as an OBJ with its UVs, loaded by
    Mitsuba's own OBJ loader as a user would) with the part's exported BSDF file
    (export/mitsuba/bsdf_<part>.xml, or `bsdf_files[part]`), lit by export/mitsuba/emitter.xml, seen
    by the scene's camera: Mitsuba's `direct` render, (H, W, 3) (`seed`: its sampler's)."""
    import mitsuba as mi

    from pipelines.io.scene_files import load_mesh

    mi.set_variant("scalar_rgb")
    mesh = load_mesh(scene / "mesh.obj")
    shapes = {}
    for k, name in enumerate(mesh.part_names):
        tri = mesh.faces[mesh.face_part == k]
        v, n = mesh.vertices[tri].reshape(-1, 3), mesh.vertex_normals[tri].reshape(-1, 3)
        uv = mesh.face_uv[mesh.face_part == k].reshape(-1, 2)
        lines = [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in v] + [f"vn {a:.9g} {b:.9g} {c:.9g}" for a, b, c in n]
        if np.isfinite(uv).all():
            lines += [f"vt {a:.9g} {b:.9g}" for a, b in uv]
            lines += [" ".join(["f"] + [f"{i}/{i}/{i}" for i in (j, j + 1, j + 2)]) for j in range(1, len(v), 3)]
        else:
            lines += [" ".join(["f"] + [f"{i}//{i}" for i in (j, j + 1, j + 2)]) for j in range(1, len(v), 3)]
        obj = scene / f"roundtrip_{k}.obj"
        obj.write_text("\n".join(lines) + "\n")
        bsdf = (bsdf_files or {}).get(name, export / "mitsuba" / f"bsdf_{name}.xml")
        shapes[f"part{k}"] = {"type": "obj", "filename": str(obj), "face_normals": False,
                              "bsdf": mi.load_file(str(bsdf))}
    camera = json.loads((scene / "camera.json").read_text())
    pose = json.loads((scene / "pose.json").read_text())
    sc = mi.load_dict({"type": "scene", "emitter": mi.load_file(str(export / "mitsuba" / "emitter.xml")), **shapes,
                       "integrator": {"type": "direct"}, "sensor": mitsuba_opencv_sensor(camera, pose, spp, seed)})
    return np.array(mi.render(sc, spp=spp), dtype=np.float64)[..., :3]
