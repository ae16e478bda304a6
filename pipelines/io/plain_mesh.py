"""A fast reader for the plainest mesh files: triangles with per-vertex normals and nothing else.

Importing trimesh costs ~0.7 s, a tenth of a whole `solve` on a 320x240 scene. Most scene meshes
are plain: a binary PLY with `x y z nx ny nz` and a triangle list, or an OBJ with only `v`, `vn`
and `f a//a` lines. `read_plain` reads exactly those, giving the arrays trimesh gives for them
(`load_mesh` then treats them alike; `tests/test_plain_mesh.py` checks the two agree), and returns
None for anything else (UVs, colours, materials, groups, polygons, faces without normals, other
elements, a damaged file): trimesh reads those, and reports what is wrong with a damaged one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_XYZN = ("x", "y", "z", "nx", "ny", "nz")


def read_plain(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(vertices (V, 3) float64, faces (F, 3) int64, vertex normals (V, 3) float64) of a plain
    PLY or OBJ, or None when the file is anything more (or less) than plain."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".ply":
            return _plain_ply(path)
        if suffix == ".obj":
            return _plain_obj(path)
    except (OSError, ValueError, KeyError, IndexError, TypeError, UnicodeDecodeError):
        return None  # (trimesh reads it again and says what is wrong)
    return None


def _plain_ply(path: Path):
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            return None
        fmt, elements = None, []
        while True:
            line = f.readline()
            if not line:
                return None
            words = line.decode("ascii").split()
            if not words or words[0] in ("comment", "obj_info"):
                if "texturefile" in line.lower().decode("ascii", "replace"):
                    return None
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                elements[-1][2].append(words[1:])
            else:
                return None
        body = f.read()
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    if order is None or [e[0] for e in elements] != ["vertex", "face"]:
        return None
    (_, nv, vprops), (_, nf, fprops) = elements
    names = [p[-1] for p in vprops]
    if sorted(names) != sorted(_XYZN) or any(p[0] == "list" for p in vprops):
        return None
    vdtype = np.dtype([(p[1], order + _PLY_TYPES[p[0]]) for p in vprops])
    if len(fprops) != 1 or fprops[0][0] != "list" or fprops[0][3] not in ("vertex_indices", "vertex_index"):
        return None
    count, index = _PLY_TYPES[fprops[0][1]], _PLY_TYPES[fprops[0][2]]
    if index[0] not in "iu" or count[0] not in "iu":
        return None
    fdtype = np.dtype([("n", order + count), ("i", order + index, (3,))])
    if len(body) != nv * vdtype.itemsize + nf * fdtype.itemsize:
        return None  # (polygons, or a truncated or padded file)
    v = np.frombuffer(body, vdtype, nv)
    fc = np.frombuffer(body, fdtype, nf, offset=nv * vdtype.itemsize)
    if not np.all(fc["n"] == 3) or (nf and (fc["i"].min() < 0 or fc["i"].max() >= nv)):
        return None
    vertices = np.stack([v[k] for k in _XYZN[:3]], axis=1).astype(np.float64)
    normals = np.stack([v[k] for k in _XYZN[3:]], axis=1).astype(np.float64)
    return vertices, fc["i"].astype(np.int64), normals


def _plain_obj(path: Path):
    data = path.read_bytes()
    kinds: dict[bytes, list[bytes]] = {b"v": [], b"vn": [], b"f": []}
    for line in data.splitlines():
        line = line.strip()
        if not line or line.startswith(b"#"):
            continue
        key, _, rest = line.partition(b" ")
        rows = kinds.get(key)
        if rows is None:
            return None  # (vt, mtllib, usemtl, o, g, s, l, ...: trimesh's to read)
        rows.append(rest)
    v, vn, f = kinds[b"v"], kinds[b"vn"], kinds[b"f"]
    if not f or len(vn) != len(v):
        return None
    vertices = np.array(b" ".join(v).split(), dtype=np.float64)
    normals = np.array(b" ".join(vn).split(), dtype=np.float64)
    if vertices.size != 3 * len(v) or normals.size != 3 * len(vn):
        return None  # (vertex colours, w, or a damaged line)
    corners = b" ".join(f).split()
    if len(corners) != 3 * len(f) or any(c.count(b"//") != 1 for c in corners):
        return None  # (polygons, UVs, or corners without normals)
    ij = np.array(b" ".join(corners).replace(b"//", b" ").split(), dtype=np.int64).reshape(-1, 2)
    if not np.array_equal(ij[:, 0], ij[:, 1]) or ij.min() < 1 or ij.max() > len(v):
        return None  # (a normal index of its own, or relative / out-of-range indices)
    if np.bincount(ij[:, 0], minlength=len(v) + 1)[1:].min() == 0:
        return None  # (a vertex no face uses: how trimesh keeps those is its own business)
    return vertices.reshape(-1, 3), ij[:, 0].reshape(-1, 3) - 1, normals.reshape(-1, 3)
