"""The plain-mesh reader (pipelines/io/plain_mesh.py) against trimesh: for every file it takes,
`load_mesh` gives the same vertices, faces, normals and notes as through trimesh, and whatever it
does not take (anything beyond triangles with per-vertex normals, a damaged file) goes to trimesh."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st

from pipelines.errors import InputError
from pipelines.io import plain_mesh, scene_files
from property_helpers import props

ROOT = Path(__file__).resolve().parents[1]
FILES = sorted([*ROOT.glob("tests/data/scenes/*/mesh.ply"), *ROOT.glob("tests/data/scenes/*/mesh.obj"), *ROOT.glob("sample_data/*/mesh.obj")])


def through(path: Path, plain: bool):
    """`load_mesh(path)` with the plain reader (plain) or with trimesh only; an InputError is returned."""
    with pytest.MonkeyPatch.context() as m:
        if not plain:
            m.setattr(plain_mesh, "read_plain", lambda p: None)
        try:
            return scene_files.load_mesh(path)
        except InputError as exc:
            return exc


def assert_same(a, b):
    if isinstance(a, InputError) or isinstance(b, InputError):
        assert isinstance(a, InputError) and isinstance(b, InputError), (a, b)
        assert a.path == b.path
        return
    for k in ("vertices", "faces", "vertex_normals"):
        x, y = getattr(a, k), getattr(b, k)
        assert x.dtype == y.dtype and np.array_equal(x, y), k
    assert (a.notes, a.part_names) == (b.notes, b.part_names)
    for k in ("face_part", "face_uv", "face_colour"):
        x, y = getattr(a, k), getattr(b, k)
        assert (x is None) == (y is None) and (x is None or np.array_equal(x, y, equal_nan=True)), k


@pytest.mark.parametrize("path", FILES, ids=[f"{p.parent.name}/{p.name}" for p in FILES])
def test_project_meshes_read_alike(path):
    plain = plain_mesh.read_plain(path)
    if path.suffix == ".ply":
        assert plain is not None, "the test scenes' PLY files are plain"
    if plain is None:  # (a textured OBJ: trimesh's)
        assert "mtllib" in path.read_text(errors="replace")
        return
    assert_same(through(path, True), through(path, False))


def ply_bytes(V, N, F, order="<", coord="f8", index="i4", count="u1", extra_vertex=(), comment=""):
    names = ["x", "y", "z", "nx", "ny", "nz", *extra_vertex]
    kinds = {"f8": "double", "f4": "float", "i4": "int", "u4": "uint", "u1": "uchar", "u2": "ushort"}
    head = ["ply", f"format binary_{'little' if order == '<' else 'big'}_endian 1.0"]
    if comment:
        head.append(f"comment {comment}")
    head.append(f"element vertex {len(V)}")
    head += [f"property {kinds[coord if k in 'xyz' else 'f4']} {k}" for k in names]
    head += [f"element face {len(F)}", f"property list {kinds[count]} {kinds[index]} vertex_indices", "end_header"]
    vdt = np.dtype([(k, order + (coord if k in "xyz" else "f4")) for k in names])
    v = np.zeros(len(V), vdt)
    for j, k in enumerate("xyz"):
        v[k] = V[:, j]
    for j, k in enumerate(("nx", "ny", "nz")):
        v[k] = N[:, j]
    fdt = np.dtype([("n", order + count), ("i", order + index, (F.shape[1],))])
    f = np.zeros(len(F), fdt)
    f["n"], f["i"] = F.shape[1], F
    return ("\n".join(head) + "\n").encode() + v.tobytes() + f.tobytes()


def obj_text(V, N, F, corner="{i}//{i}"):
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in V.tolist()] + [f"vn {x!r} {y!r} {z!r}" for x, y, z in N.tolist()]
    lines += ["f " + " ".join(corner.format(i=i + 1) for i in f) for f in F]
    return "\n".join(lines) + "\n"


@st.composite
def meshes(draw):
    n = draw(st.integers(3, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    V = rng.normal(size=(n, 3)) * 10.0 ** draw(st.integers(-3, 3))
    N = rng.normal(size=(n, 3))
    ring = (np.arange(n)[:, None] + np.arange(3)) % n  # (every vertex used by some face)
    more = [rng.choice(n, 3, replace=False) for _ in range(draw(st.integers(0, n)))]
    F = np.concatenate([ring, np.reshape(more, (-1, 3))]).astype(np.int64)
    return V, N, F


PLY_CHANGES = ["none", "big endian", "float coords", "uint index", "ushort count", "truncated", "padded",
               "index out of range", "nan vertex", "quad", "uv property", "texture comment", "plain comment"]
OBJ_CHANGES = ["none", "own normal index", "uv corner", "no normal", "quad", "index out of range", "vt line",
               "usemtl", "nan vertex", "negative index", "comment", "unused vertex", "missing normal line"]


@pytest.mark.parametrize("fmt, change", [("ply", c) for c in PLY_CHANGES] + [("obj", c) for c in OBJ_CHANGES])
@props(8)
@given(data=st.data())
def test_plain_files_read_as_trimesh_reads_them(workdir, fmt, change, data):
    V, N, F = data.draw(meshes())
    if change == "nan vertex":
        V[1, 0] = np.nan
    if change == "index out of range":
        F[0, 1] = len(V) + (fmt == "obj")
    if change == "quad":
        F = np.concatenate([F, F[:, :1]], axis=1)
    if fmt == "ply":
        kw = {"big endian": {"order": ">"}, "float coords": {"coord": "f4"}, "uint index": {"index": "u4"},
              "ushort count": {"count": "u2"}, "uv property": {"extra_vertex": ("s", "t")},
              "texture comment": {"comment": "TextureFile albedo.png"},
              "plain comment": {"comment": "made by hand"}}.get(change, {})
        body = ply_bytes(V, N, F, **kw)
        body = body[:-5] if change == "truncated" else body + b"\0" * 7 if change == "padded" else body
        path = workdir / "mesh.ply"
        path.write_bytes(body)
    else:
        corner = {"own normal index": "{i}//1", "uv corner": "{i}/{i}/{i}", "no normal": "{i}",
                  "negative index": "-1//-1"}.get(change, "{i}//{i}")
        text = obj_text(V, N, F, corner)
        text = {"vt line": "vt 0.5 0.5\n" + text, "usemtl": "usemtl red\n" + text,
                "comment": "# made by hand\n" + text, "unused vertex": text + "v 9 9 9\nvn 0 0 1\n",
                "missing normal line": text.replace("vn ", "# vn ", 1)}.get(change, text)
        path = workdir / "mesh.obj"
        path.write_text(text)
    plain = plain_mesh.read_plain(path)
    event(f"{fmt} {change}: {'plain' if plain is not None else 'trimesh'}")
    if change in ("none", "big endian", "float coords", "uint index", "ushort count", "plain comment", "comment"):
        assert plain is not None, "a plain file must take the fast path"
    if change in ("truncated", "padded", "quad", "uv property", "texture comment", "own normal index", "uv corner",
                  "no normal", "vt line", "usemtl", "unused vertex", "missing normal line", "negative index",
                  "index out of range"):
        assert plain is None, "anything beyond a plain file goes to trimesh"
    assert_same(through(path, True), through(path, False))
