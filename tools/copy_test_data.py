"""Copy the pieces of the shared Mitsuba scenes that the tests need into tests/data/scenes/.

Usage:
    PYTHONPATH=. .venv/bin/python tools/copy_test_data.py /path/to/shared/data/scenes [--dest DIR]
        [--scene NAME ...] [--check-render]

The project must never read the shared data at run or test time, so this script is the only link:
it copies the small files verbatim and converts each scene's 2-6 MB text mesh.obj into a compact
binary little-endian PLY (float64 positions, float32 per-vertex normals, int32 triangle indices).
Positions stay float64 because `load_mesh` may recompute normals from the faces (trimesh 4 drops
file normals when it coerces a scene into one mesh), and float32 positions move those normals by
up to 5e-6 on the small Spot triangles. It then checks that
  - `pipelines.scene.load_mesh` returns the same vertices, faces and normals from both files, and
  - trimesh reads the same file normals (the OBJ's `vn`) from both files,
(max abs difference < 1e-6) and, with --check-render, that the relative RMSE of our renderer against
truth/image_clean.exr at R=32 is unchanged (to 1e-4) when the PLY replaces the OBJ.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

SCENES = ("spot_overcast", "bunny_sun", "teapot_sun_phong")
FILES = (
    "camera.json", "pose.json", "mask.png", "mask_object.png", "image.exr", "correspondences.csv",
    "truth/env_latlong.exr", "truth/material.json", "truth/image_clean.exr",
    "truth/novel_view/camera.json", "truth/novel_view/pose.json", "truth/novel_view/mask.png",
    "truth/novel_view/image.exr",
)
MESH_TOLERANCE = 1e-6
RENDER_TOLERANCE = 1e-4


def write_ply(path: Path, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray,
              comments: tuple[str, ...] = ()) -> None:
    """Binary little-endian PLY: float64 x y z, float32 nx ny nz per vertex, uchar-counted int32
    triangles."""
    vertices = np.asarray(vertices, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3) triangles, got {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(vertices) or len(vertices) >= 2**31:
        raise ValueError("face indices out of range")
    vdt = np.dtype([(name, "<f8") for name in ("x", "y", "z")]
                   + [(name, "<f4") for name in ("nx", "ny", "nz")])
    vrec = np.empty(len(vertices), dtype=vdt)
    for k, name in enumerate(("x", "y", "z")):
        vrec[name] = vertices[:, k]
        vrec["n" + name] = normals[:, k]
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    frec = np.empty(len(faces), dtype=fdt)
    frec["n"] = 3
    frec["i"] = faces
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {c}" for c in comments]
    header += [f"element vertex {len(vertices)}"]
    header += [f"property double {name}" for name in ("x", "y", "z")]
    header += [f"property float {name}" for name in ("nx", "ny", "nz")]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vrec.tobytes())
        f.write(frec.tobytes())
    tmp.replace(path)


def convert_mesh(src: Path, dst: Path, comment: str) -> dict:
    """OBJ -> PLY with the raw arrays trimesh reads (load_mesh's own cleaning then runs on both)."""
    import trimesh

    from pipelines.io import scene_files as sc

    # Without force="mesh" a one-object OBJ comes back as that object with its `vn` normals.
    raw = trimesh.load(str(src), process=False)
    if not isinstance(raw, trimesh.Trimesh):
        raise SystemExit(f"{src}: expected a single mesh, got {type(raw).__name__}")
    write_ply(dst, raw.vertices, raw.vertex_normals, raw.faces, comments=(comment,))
    back = trimesh.load(str(dst), process=False)
    dn_file = float(np.abs(np.asarray(back.vertex_normals) - np.asarray(raw.vertex_normals)).max())
    if dn_file >= MESH_TOLERANCE or not np.array_equal(back.faces, raw.faces):
        raise SystemExit(f"{dst}: file normals/faces differ from {src} (max {dn_file:.3g})")
    a, b = sc.load_mesh(src), sc.load_mesh(dst)
    if a.faces.shape != b.faces.shape or not np.array_equal(a.faces, b.faces):
        raise SystemExit(f"{dst}: faces differ from {src}")
    dv = float(np.abs(a.vertices - b.vertices).max())
    dn = float(np.abs(a.vertex_normals - b.vertex_normals).max())
    if a.vertices.shape != b.vertices.shape or dv >= MESH_TOLERANCE or dn >= MESH_TOLERANCE:
        raise SystemExit(f"{dst}: vertices/normals differ from {src} (max {dv:.3g} / {dn:.3g})")
    if a.notes != b.notes:
        raise SystemExit(f"{dst}: load notes differ: {a.notes} vs {b.notes}")
    return {"vertices": len(b.vertices), "faces": len(b.faces), "max_vertex_diff": dv,
            "max_normal_diff": dn, "max_file_normal_diff": dn_file,
            "obj_bytes": src.stat().st_size, "ply_bytes": dst.stat().st_size}


def rendered_rel_rmse(scene_dir: Path, mesh_path: Path, resolution: int = 32) -> float:
    """Relative RMSE of our forward model against truth/image_clean.exr over the used pixels."""
    from pipelines.geometry import camera as cam
    from pipelines.light import cubemap
    from pipelines.io import images
    from pipelines.geometry import raycast
    from pipelines.model import render
    from pipelines.model import materials
    from pipelines.io import scene_files as sc
    from pipelines.geometry import visibility as vis

    C = sc.read_camera(scene_dir / "camera.json")
    P = sc.read_pose(scene_dir / "pose.json")
    M = sc.load_mesh(mesh_path)
    be = raycast.make_backend(M)
    S, _ = cam.pixel_samples(C, P, M, be, images.read_mask(scene_dir / "mask.png"), edge_margin=1)
    cube = cubemap.CubeMap(resolution)
    V = vis.compute_visibility(be, S, cube)
    L = cubemap.latlong_to_cube(images.read_latlong(scene_dir / "truth/env_latlong.exr"), cube)
    mat = materials.Material.from_json(json.loads((scene_dir / "truth/material.json").read_text()))
    img = render.render(V, L, mat)
    ref = images.read_image(scene_dir / "truth/image_clean.exr").pixels[S.pixel[:, 0], S.pixel[:, 1]]
    return float(np.sqrt(np.mean((img - ref) ** 2)) / np.sqrt(np.mean(ref.astype(np.float64) ** 2)))


def copy_scene(src: Path, dst: Path, check_render: bool) -> None:
    name = src.name
    for rel in FILES:
        target = dst / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src / rel, target)
    shutil.copyfile(src / "README.txt", dst / "README.txt")
    info = convert_mesh(src / "mesh.obj", dst / "mesh.ply",
                        f"{name} mesh.obj (object + ground plane) converted by tools/copy_test_data.py")
    print(f"{name}: mesh {info['vertices']} vertices / {info['faces']} faces, "
          f"{info['obj_bytes'] / 1e6:.2f} MB obj -> {info['ply_bytes'] / 1e6:.2f} MB ply, "
          f"load_mesh max |dv| {info['max_vertex_diff']:.2g}, |dn| {info['max_normal_diff']:.2g}; "
          f"file normals max |dn| {info['max_file_normal_diff']:.2g}")
    if check_render:
        e_obj = rendered_rel_rmse(src, src / "mesh.obj")
        e_ply = rendered_rel_rmse(dst, dst / "mesh.ply")
        status = "ok" if abs(e_obj - e_ply) < RENDER_TOLERANCE else "CHANGED"
        print(f"{name}: rel. RMSE at R=32 obj {e_obj:.6f}, ply {e_ply:.6f} ({status})")
        if status != "ok":
            raise SystemExit(f"{name}: the PLY changes the render by more than {RENDER_TOLERANCE}")


def main(argv=None) -> int:
    here = Path(__file__).resolve().parents[1]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("shared_scenes", type=Path, help="the shared scenes folder (holds bunny_sun/, ...)")
    parser.add_argument("--dest", type=Path, default=here / "tests" / "data" / "scenes")
    parser.add_argument("--scene", action="append", choices=SCENES, help="copy only this scene (repeatable)")
    parser.add_argument("--check-render", action="store_true",
                        help="also compare the rendered relative RMSE with the OBJ and the PLY (slow)")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(here))
    for name in args.scene or SCENES:
        src = args.shared_scenes / name
        if not (src / "mesh.obj").is_file():
            parser.error(f"{src} is not a shared scene folder (no mesh.obj)")
        copy_scene(src, args.dest / name, args.check_render)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
