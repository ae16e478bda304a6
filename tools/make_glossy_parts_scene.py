"""Make tests/data/scenes/spot_glossy_sun: spot_textured_sun's geometry, cameras and light, with Spot
under a glossy coating (Mitsuba `roughplastic`, GGX alpha 0.15, IOR 1.49, its colour texture the
coating's diffuse base) on the same matte ground: a scene of two parts of which one is glossy.
With --split-ks KS, tests/data/scenes/spot_two_coats_sun: Spot's faces in two parts (split at a column of
the main photo through its highlight), the second under the same coating at specular_reflectance KS:
two glossy parts of different ks. (--ground-ks KS puts the ground under the coating instead; in these
cameras its highlight is out of view, so auto rightly calls it matte: not kept in tests/data.)

Usage:
    PYTHONPATH=. .venv/bin/python tools/make_glossy_parts_scene.py [--spp 1024] [--dest tests/data/scenes]
        [--split-ks 0.3 | --ground-ks 0.3]

Mitsuba 3 renders it with its `scalar_rgb` variant (`direct` integrator, Mitsuba's own OBJ loader,
`tests/tool_scenes.render_mitsuba_parts`): the LLVM variants that tools/render_mitsuba_scenes.py
uses cannot compile on this machine's LLVM 15/16 ("Cannot select fminimum"), and that script's
vectorised camera and coverage code needs them. Everything but the photos is spot_textured_sun's
(masks, correspondences, poses: the geometry is the same); the light goes to Mitsuba as wavelight
exports it (each lat-long pixel 16 x 16 times, `exports.to_mitsuba`, `exports.mitsuba_xml`). The
noise added is the shared scenes': N(0, sigma), sigma = 0.5 % of the mean clean radiance over mask.png.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE / "tests"))

from pipelines.io import exports, images  # noqa: E402

SOURCE = "spot_textured_sun"
NAME = "spot_glossy_sun"
GROUND_COATED = "spot_glossy_ground_sun"
TWO_COATS = "spot_two_coats_sun"  # --split-ks: Spot's faces in two parts, the second at a weaker coating
SPLIT_PART = "spot_flank"
SPLIT_COLUMN = 164.0  # the main photo's column through the median of Spot's highlight pixels (spot_glossy_sun's
# clean image over spot_textured_sun's above 1.3: 380 pixels, columns 143-190): faces whose centroid projects
# left of it go to the second part, so that each part has about half of the highlight


def split_spot(folder: Path, camera: Path, pose: Path) -> int:
    """Rewrite folder/mesh.obj and mesh.mtl: Spot's faces whose centroid the main camera sees left
    of SPLIT_COLUMN go to a part of their own (SPLIT_PART, the same texture). Returns its faces."""
    cam, ps = json.loads(camera.read_text()), json.loads(pose.read_text())
    R, t = np.array(ps["R"]), np.array(ps["t"])
    lines = (folder / "mesh.obj").read_text().splitlines()
    verts = np.array([[float(x) for x in ln.split()[1:4]] for ln in lines if ln.startswith("v ")])
    out, flank, group = [], [], None
    for ln in lines:
        if ln.startswith("usemtl "):
            group = ln.split()[1]
        if ln.startswith("g ground"):  # (Spot's group ends: its split faces go before the ground)
            out += ["g " + SPLIT_PART, "usemtl " + SPLIT_PART] + flank
        if group == "spot" and ln.startswith("f "):
            idx = [int(tok.split("/")[0]) - 1 for tok in ln.split()[1:4]]
            xc = R @ verts[idx].mean(axis=0) + t
            if cam["fx"] * xc[0] / xc[2] + cam["cx"] < SPLIT_COLUMN:
                flank.append(ln)
                continue
        out.append(ln)
    (folder / "mesh.obj").write_text("\n".join(out) + "\n")
    mtl = (folder / "mesh.mtl").read_text()
    block = mtl[mtl.index("newmtl spot"):mtl.index("newmtl ground")].replace("newmtl spot", "newmtl " + SPLIT_PART)
    (folder / "mesh.mtl").write_text(mtl.rstrip("\n") + "\n\n" + block.rstrip("\n") + "\n")
    return len(flank)
ALPHA, DISTRIBUTION, INT_IOR, EXT_IOR = 0.15, "ggx", 1.49, 1.000277
GROUND = (0.35, 0.45, 0.6)
ENV_SUPERSAMPLE = 16
NOISE_REL = 0.005
SEED = 32400


def coating_xml(diffuse: str, ks: float | None = None) -> str:
    """Mitsuba roughplastic with the scenes' coating over `diffuse` (its diffuse_reflectance element),
    at specular_reflectance `ks` (None: Mitsuba's default 1)."""
    weight = "" if ks is None else f"""
    <float name="specular_reflectance" value="{ks}"/>"""
    return f"""<bsdf type="roughplastic" version="3.0.0">
    <string name="distribution" value="{DISTRIBUTION}"/>
    <float name="alpha" value="{ALPHA}"/>
    <float name="int_ior" value="{INT_IOR}"/>
    <float name="ext_ior" value="{EXT_IOR}"/>
    <boolean name="nonlinear" value="false"/>{weight}
    {diffuse}
</bsdf>
"""


def bsdf_files(folder: Path, texture: Path, ground_ks: float | None = None, split_ks: float | None = None) -> dict:
    """The parts' BSDF files: Spot coated over its texture (and its split part at `split_ks`), the
    ground diffuse, or coated at `ground_ks`."""
    textured = f"""<texture type="bitmap" name="diffuse_reflectance">
        <string name="filename" value="{texture}"/>
        <boolean name="raw" value="false"/>
        <string name="filter_type" value="bilinear"/>
        <string name="wrap_mode" value="repeat"/>
    </texture>"""
    colour = f'{GROUND[0]} {GROUND[1]} {GROUND[2]}'
    texts = {"spot": coating_xml(textured),
             "ground": f"""<bsdf type="diffuse" version="3.0.0">
    <rgb name="reflectance" value="{colour}"/>
</bsdf>
""" if ground_ks is None else coating_xml(f'<rgb name="diffuse_reflectance" value="{colour}"/>', ground_ks)}
    if split_ks is not None:  # the second part: the same coating and texture at specular_reflectance split_ks
        texts[SPLIT_PART] = coating_xml(textured, split_ks)
    out = {}
    for name, text in texts.items():
        out[name] = folder / f"bsdf_{name}.xml"
        out[name].write_text(text)
    return out


def render_view(src: Path, camera: Path, pose: Path, work: Path, bsdfs: dict, spp: int, seed: int) -> np.ndarray:
    """Mitsuba's render of the mesh in folder `src` from one camera and pose (a folder for
    render_mitsuba_parts)."""
    from tool_scenes import render_mitsuba_parts

    view = work / f"view_{seed}"
    view.mkdir()
    shutil.copyfile(src / "mesh.obj", view / "mesh.obj")
    shutil.copyfile(src / "mesh.mtl", view / "mesh.mtl")
    shutil.copyfile(src / "spot_texture.png", view / "spot_texture.png")
    shutil.copyfile(camera, view / "camera.json")
    shutil.copyfile(pose, view / "pose.json")
    return render_mitsuba_parts(view, work, spp, bsdf_files=bsdfs, seed=seed)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spp", type=int, default=2048)
    parser.add_argument("--dest", type=Path, default=HERE / "tests" / "data" / "scenes")
    parser.add_argument("--ground-ks", type=float, default=None,
                        help="the ground under Spot's coating too, at this specular_reflectance (scene "
                             f"{GROUND_COATED}: two glossy parts of different specular weight)")
    parser.add_argument("--split-ks", type=float, default=None,
                        help=f"Spot's faces left of the main photo's column {SPLIT_COLUMN:g} a part of their own "
                             f"({SPLIT_PART}) at this specular_reflectance (scene {TWO_COATS})")
    args = parser.parse_args()
    name = TWO_COATS if args.split_ks is not None else NAME if args.ground_ks is None else GROUND_COATED
    src = HERE / "tests" / "data" / "scenes" / SOURCE
    dst = args.dest / name
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(".wavelight", "out", "image.png"))
    flank_faces = split_spot(dst, src / "camera.json", src / "pose.json") if args.split_ks is not None else 0
    light = images.read_image(src / "truth" / "env_latlong.exr").pixels
    rng = np.random.default_rng(SEED)
    t0 = time.time()
    noise = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        (work / "mitsuba").mkdir()
        big = np.repeat(np.repeat(light, ENV_SUPERSAMPLE, axis=0), ENV_SUPERSAMPLE, axis=1)
        images.write_exr(work / "mitsuba" / "light.exr", exports.to_mitsuba(big))
        (work / "mitsuba" / "emitter.xml").write_text(exports.mitsuba_xml("light.exr"))
        bsdfs = bsdf_files(work, src / "spot_texture.png", args.ground_ks, args.split_ks)
        views = [("main", src, dst, dst / "truth")]
        views += [(p.name, p, dst / "views" / p.name, None) for p in sorted((src / "views").iterdir())]
        for k, (view_name, folder, out, truth) in enumerate(views):
            camera = folder / "camera.json" if (folder / "camera.json").is_file() else src / "camera.json"
            clean = render_view(dst, camera, folder / "pose.json", work, bsdfs, args.spp, SEED + k).astype(np.float32)
            mask = images.read_mask(folder / "mask.png")
            sigma = NOISE_REL * float(clean[mask].mean())
            noisy = np.clip(clean + rng.normal(0.0, sigma, clean.shape), 0.0, None).astype(np.float32)
            images.write_exr(out / "image.exr", noisy)
            if truth is not None:
                images.write_exr(truth / "image_clean.exr", clean)
            noise[view_name] = sigma
            print(f"  {view_name}: {time.time() - t0:.0f} s, noise sigma {sigma:.3g}")
        novel = src / "truth" / "novel_view"
        clean = render_view(dst, novel / "camera.json", novel / "pose.json", work, bsdfs, args.spp, SEED + 50)
        images.write_exr(dst / "truth" / "novel_view" / "image.exr", clean.astype(np.float32))
        print(f"  novel view: {time.time() - t0:.0f} s")
    material = json.loads((src / "truth" / "material.json").read_text())
    material["parts"]["spot"] = {
        "type": "roughplastic", "distribution": DISTRIBUTION, "alpha": ALPHA, "int_ior": INT_IOR, "ext_ior": EXT_IOR,
        "nonlinear": False, "diffuse_reflectance": "spot_texture.png (bitmap, sRGB decoded, bilinear, repeat)",
        "kd_mean": material["parts"]["spot"]["kd_mean"],
        "formula": "Mitsuba roughplastic: specular = microfacet F D G / (4 cos_i cos_o), GGX, Smith G; diffuse = "
                   "texture(uv) / (1 - Fdr_int) / eta^2 / pi * (1 - F(cos_i)) (1 - F(cos_o)) (nonlinear=false)"}
    if args.split_ks is not None:
        material["parts"][SPLIT_PART] = dict(material["parts"]["spot"], specular_reflectance=args.split_ks,
                                             faces=flank_faces, note=f"Spot's faces left of the main photo's column "
                                             f"{SPLIT_COLUMN:g} (tools/make_glossy_parts_scene.py --split-ks)")
        material["parts"]["spot"]["specular_reflectance"] = 1.0
    if args.ground_ks is not None:
        material["parts"]["ground"] = {
            "type": "roughplastic", "distribution": DISTRIBUTION, "alpha": ALPHA, "int_ior": INT_IOR,
            "ext_ior": EXT_IOR, "nonlinear": False, "diffuse_reflectance": list(GROUND),
            "specular_reflectance": args.ground_ks, "kd_mean": material["parts"]["ground"].get("kd_mean", list(GROUND))}
    (dst / "truth" / "material.json").write_text(json.dumps(material, indent=1) + "\n")
    params = json.loads((src / "truth" / "scene_params.json").read_text())
    params.update(name=name, set="glossy parts", material=material, mitsuba={"variant": "scalar_rgb"},
                  render={"integrator": "direct (Mitsuba's default: MIS of emitter and BSDF samples)",
                          "sampler": "independent", "spp": args.spp, "noise_sigma": noise, "noise_rel": NOISE_REL,
                          "made_by": "tools/make_glossy_parts_scene.py from " + SOURCE,
                          "render_time_s": time.time() - t0})
    params.pop("verification", None)
    (dst / "truth" / "scene_params.json").write_text(json.dumps(params, indent=1) + "\n")
    (dst / "README.txt").write_text(
        f"Scene {name}: {SOURCE}'s mesh (mesh.obj, mesh.mtl: parts spot"
        f"{', ' + SPLIT_PART if args.split_ks is not None else ''} and ground), cameras, poses, masks and\n"
        f"correspondences (main photo and views/left, views/right), under the same light (truth/env_latlong.exr),\n"
        f"with Spot under a glossy coating: Mitsuba roughplastic ({DISTRIBUTION}, alpha {ALPHA}, int_ior {INT_IOR}),\n"
        f"spot_texture.png (sRGB) its diffuse base; the ground " + (
            f"Mitsuba diffuse {list(GROUND)}" if args.ground_ks is None else
            f"under the same coating, specular_reflectance {args.ground_ks}, its diffuse base {list(GROUND)}") +
        ". Rendered by\n"
        f"tools/make_glossy_parts_scene.py (Mitsuba 3 scalar_rgb, direct, {args.spp} spp) + N(0, 0.5 % of the mean\n"
        f"over mask.png). truth/: image_clean.exr (main), novel_view/image.exr (clean), material.json, scene_params.json.\n"
        + (f"Spot's faces left of the main photo's column {SPLIT_COLUMN:g} are a part of their own ({SPLIT_PART}, "
           f"{flank_faces} faces,\nthe same texture and coating at specular_reflectance {args.split_ks}; Spot's "
           "at 1).\n" if args.split_ks is not None else "")
        + "Nothing in the scene folder says which part is glossy (mesh.mtl is the diffuse scene's).\n")
    print(f"{name}: written to {dst} in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
