"""Tests for the scene file readers in pipelines.scene: camera.json, pose.json,
correspondences.csv and mesh loading."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, event, given
from hypothesis import strategies as st

from pipelines.errors import InputError
from pipelines.geometry import camera
from pipelines.geometry.camera import Camera, Pose
from pipelines.io import scene_files as sc
from pipelines.io.scene_files import find_mesh, load_mesh, read_camera, read_correspondences, read_pose
from property_helpers import (HUGE, anyfloat, assert_names_file, finite_real, is_real, json_numbers, json_values,
                              mutate, props, same_json, text, wrong_values)
from wavelight_cli.cache import write_json_atomic

CAMERA = {"width": 640, "height": 480, "fx": 525.5, "fy": 520.25, "cx": 319.5, "cy": 239.5,
          "dist": [0.1, -0.05, 0.001, -0.002, 0.01]}


def rotation(seed):
    q = np.random.default_rng(seed).normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def write_json(path, data):
    path.write_text(json.dumps(data))  # json.dumps writes NaN / Infinity tokens as Python does
    return path


def assert_input_error(func, path, *words):
    with pytest.raises(InputError) as info:
        func(path)
    msg = str(info.value)
    assert path.name in msg, msg
    assert info.value.path == path
    for w in words:
        assert w in msg, msg
    return msg


# -- camera.json ---------------------------------------------------------------------------------
def test_camera_round_trip(tmp_path):
    cam = read_camera(write_json(tmp_path / "camera.json", {**CAMERA, "rms": 0.31}))
    assert (cam.width, cam.height) == (640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (525.5, 520.25, 319.5, 239.5)
    assert cam.dist == (0.1, -0.05, 0.001, -0.002, 0.01)
    np.testing.assert_array_equal(cam.K, [[525.5, 0, 319.5], [0, 520.25, 239.5], [0, 0, 1]])
    assert cam.extra == {"rms": 0.31}
    again = read_camera(write_json(tmp_path / "camera2.json", cam.to_json()))
    assert again == cam and again.extra == cam.extra


def test_camera_without_dist_has_zero_distortion(tmp_path):
    data = {k: v for k, v in CAMERA.items() if k != "dist"}
    cam = read_camera(write_json(tmp_path / "camera.json", data))
    assert cam.dist == (0.0,) * 5
    four = read_camera(write_json(tmp_path / "c4.json", {**data, "dist": [0.1, 0.2, 0.3, 0.4]}))
    assert four.dist == (0.1, 0.2, 0.3, 0.4, 0.0)


BAD_CAMERAS = {
    "missing-fx": ({k: v for k, v in CAMERA.items() if k != "fx"}, "'fx'"),
    "missing-width": ({k: v for k, v in CAMERA.items() if k != "width"}, "'width'"),
    "fx-string": ({**CAMERA, "fx": "525"}, "'fx'"),
    "fx-bool": ({**CAMERA, "fx": True}, "'fx'"),
    "cx-list": ({**CAMERA, "cx": [1, 2]}, "'cx'"),
    "fx-negative": ({**CAMERA, "fx": -525.0}, "'fx'"),
    "fy-zero": ({**CAMERA, "fy": 0}, "'fy'"),
    # (fx 0.5 where 500 was meant was read, and every ray fanned out sideways: bad-input sweep)
    "fx-field-of-view-179-deg": ({**CAMERA, "fx": 0.5}, "179.8 deg field of view"),
    "fy-field-of-view-176-deg": ({**CAMERA, "fy": 0.5 * CAMERA["height"] / math.tan(math.radians(88))}, "fy = "),
    "fx-nan": ({**CAMERA, "fx": math.nan}, "'fx'"),
    "cy-inf": ({**CAMERA, "cy": math.inf}, "'cy'"),
    "width-fraction": ({**CAMERA, "width": 640.5}, "whole"),
    "height-negative": ({**CAMERA, "height": -480}, "'height'"),
    "dist-3": ({**CAMERA, "dist": [0.1, 0.2, 0.3]}, "'dist'"),
    "dist-nested": ({**CAMERA, "dist": [[0.1, 0.2], [0.3, 0.4]]}, "'dist'"),
    "dist-string": ({**CAMERA, "dist": "none"}, "'dist'"),
    "dist-nan": ({**CAMERA, "dist": [0.1, math.nan, 0, 0, 0]}, "'dist'"),
    "dist-text-cell": ({**CAMERA, "dist": [0.1, "a", 0, 0, 0]}, "'dist'"),
}


@pytest.mark.parametrize("case", list(BAD_CAMERAS))
def test_bad_camera_raises_naming_the_file(tmp_path, case):
    data, word = BAD_CAMERAS[case]
    assert_input_error(read_camera, write_json(tmp_path / "camera.json", data), word)


@pytest.mark.parametrize("reader", [read_camera, read_pose], ids=["camera", "pose"])
def test_missing_json_file(tmp_path, reader):
    assert_input_error(reader, tmp_path / "absent.json", "not found")


@pytest.mark.parametrize("text", ["{\"width\": 640,", "", "not json", "[1, 2, 3]", "42"],
                         ids=["truncated", "empty", "text", "list", "number"])
@pytest.mark.parametrize("reader", [read_camera, read_pose], ids=["camera", "pose"])
def test_invalid_json(tmp_path, reader, text):
    path = tmp_path / "broken.json"
    path.write_text(text)
    assert_input_error(reader, path)


@pytest.mark.parametrize("reader", [read_camera, read_pose], ids=["camera", "pose"])
def test_binary_json(tmp_path, reader):
    path = tmp_path / "binary.json"
    path.write_bytes(b"\xff\xfe\x00\x81garbage")
    assert_input_error(reader, path)


# -- pose.json -----------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pose_round_trip(tmp_path, seed):
    R = rotation(seed)
    t = np.random.default_rng(seed).normal(size=3) * 10
    pose = read_pose(write_json(tmp_path / "pose.json", {"R": R.tolist(), "t": t.tolist(), "rms": 0.5}))
    np.testing.assert_allclose(pose.R, R, atol=1e-14)
    np.testing.assert_array_equal(pose.t, t)
    assert pose.extra == {"rms": 0.5}
    np.testing.assert_allclose(pose.camera_centre, -R.T @ t, atol=1e-12)
    again = read_pose(write_json(tmp_path / "pose2.json", pose.to_json()))
    np.testing.assert_allclose(again.R, pose.R, atol=1e-15)


def test_pose_slightly_off_rotation_is_reorthonormalised(tmp_path):
    R = rotation(4) + 2e-5 * np.random.default_rng(4).normal(size=(3, 3))
    pose = read_pose(write_json(tmp_path / "pose.json", {"R": R.tolist(), "t": [0, 0, 1]}))
    np.testing.assert_allclose(pose.R @ pose.R.T, np.eye(3), atol=1e-13)
    assert abs(np.linalg.det(pose.R) - 1.0) < 1e-13
    np.testing.assert_allclose(pose.R, R, atol=1e-4)


R0 = rotation(9)
BAD_POSES = {
    "missing-R": ({"t": [0, 0, 1]}, "'R'"),
    "missing-t": ({"R": R0.tolist()}, "'t'"),
    "R-string": ({"R": "identity", "t": [0, 0, 1]}, "'R'"),
    "R-object": ({"R": {"a": 1}, "t": [0, 0, 1]}, "'R'"),
    "R-2x3": ({"R": R0[:2].tolist(), "t": [0, 0, 1]}, "'R'"),
    "R-ragged": ({"R": [[1, 0, 0], [0, 1], [0, 0, 1]], "t": [0, 0, 1]}, "'R'"),
    "R-flat9": ({"R": R0.ravel().tolist(), "t": [0, 0, 1]}, "'R'"),
    "t-2": ({"R": R0.tolist(), "t": [0, 1]}, "'t'"),
    "t-text-cell": ({"R": R0.tolist(), "t": [0, "one", 1]}, "'t'"),
    "R-nan": ({"R": (R0 * np.array([[1, 1, math.nan], [1, 1, 1], [1, 1, 1]])).tolist(), "t": [0, 0, 1]}, "'R'"),
    "t-inf": ({"R": R0.tolist(), "t": [0, math.inf, 1]}, "'t'"),
    "R-scaled": ({"R": (1.1 * R0).tolist(), "t": [0, 0, 1]}, "rotation"),
    "R-sheared": ({"R": (R0 + np.array([[0, 0.01, 0], [0, 0, 0], [0, 0, 0]])).tolist(), "t": [0, 0, 1]}, "rotation"),
    "R-zero": ({"R": np.zeros((3, 3)).tolist(), "t": [0, 0, 1]}, "rotation"),
    "R-reflection": ({"R": (R0 @ np.diag([1.0, 1.0, -1.0])).tolist(), "t": [0, 0, 1]}, "reflection"),
    "R-minus-identity": ({"R": (-np.eye(3)).tolist(), "t": [0, 0, 1]}, "reflection"),
}


@pytest.mark.parametrize("case", list(BAD_POSES))
def test_bad_pose_raises_naming_the_file(tmp_path, case):
    data, word = BAD_POSES[case]
    assert_input_error(read_pose, write_json(tmp_path / "pose.json", data), word)


# -- correspondences.csv -------------------------------------------------------------------------
def write_csv(path, rows, header="u,v,x,y,z"):
    lines = ([header] if header is not None else []) + [",".join(str(c) for c in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("n", [4, 6, 50])
def test_correspondences_round_trip(tmp_path, n):
    rng = np.random.default_rng(n)
    uv = rng.uniform(0, 640, size=(n, 2))
    xyz = rng.normal(size=(n, 3))
    rows = [[repr(float(v)) for v in r] for r in np.hstack([uv, xyz])]
    got_uv, got_xyz = read_correspondences(write_csv(tmp_path / "correspondences.csv", rows))
    np.testing.assert_array_equal(got_uv, uv)
    np.testing.assert_array_equal(got_xyz, xyz)
    assert got_uv.shape == (n, 2) and got_xyz.shape == (n, 3)


def test_correspondences_tolerate_spaces_case_and_blank_lines(tmp_path):
    path = tmp_path / "correspondences.csv"
    path.write_text(" U , V ,X,Y,Z\n\n1,2,3,4,5\n 6 , 7 ,8,9,10\n\n11,12,13,14,15\n16,17,18,19,20\n\n")
    uv, xyz = read_correspondences(path)
    np.testing.assert_array_equal(uv[:, 0], [1, 6, 11, 16])
    np.testing.assert_array_equal(xyz[-1], [18, 19, 20])


SHEET_ROWS = [[12.5, 7.25, 0.1, -0.2, 0.3], [100.0, 50.5, 1.0, 2.0, 3.0], [3.0, 4.0, -1.5, 0.0, 2.25],
              [640.0, 480.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0, 5.0]]


def _sheet(delimiter=",", decimal=".", bom="\ufeff", end="\r\n", encoding="utf-8"):
    def cell(v):
        return repr(v).replace(".", decimal)
    lines = [delimiter.join("uvxyz")] + [delimiter.join(cell(v) for v in r) for r in SHEET_ROWS]
    return (bom + end.join(lines) + end + end).encode(encoding)  # a trailing empty line


@pytest.mark.parametrize("content", [
    pytest.param(_sheet(), id="bom-crlf-trailing-empty-line"),
    pytest.param(_sheet(bom="", end="\r"), id="cr-only"),
    pytest.param(_sheet(";", ","), id="semicolons-decimal-commas"),
    pytest.param(_sheet(";", "."), id="semicolons-decimal-points"),
    pytest.param(_sheet("\t"), id="tabs"),
    pytest.param(_sheet(bom="", encoding="utf-16"), id="utf-16"),  # the codec writes the BOM
    pytest.param(_sheet().replace(b"u,v,x,y,z", b'"u","v","x","y","z"'), id="quoted-header"),
])
def test_correspondences_saved_by_a_spreadsheet(tmp_path, content):
    """Was: a spreadsheet's byte-order mark made the header '\ufeffu,v,x,y,z' and the file was
    refused. The BOM, CRLF / CR line ends, a trailing empty line, ';' separators (with decimal
    commas, as European spreadsheets write) and tabs are read to the same numbers."""
    path = tmp_path / "correspondences.csv"
    path.write_bytes(content)
    uv, xyz = read_correspondences(path)
    np.testing.assert_array_equal(np.hstack([uv, xyz]), SHEET_ROWS)


@pytest.mark.parametrize("header, shown", [("\ufeffx,y,z,u,v", "x,y,z,u,v"), ("\ufeffu;v;x;y", "u;v;x;y"),
                                           ("u,v,x,y;z", "u,v,x,y;z")])
def test_correspondences_wrong_header_is_still_refused(tmp_path, header, shown):
    path = tmp_path / "correspondences.csv"
    path.write_bytes((header + "\r\n" + "\r\n".join(",".join(map(repr, r)) for r in SHEET_ROWS) + "\r\n").encode())
    msg = assert_input_error(read_correspondences, path, f"header must be 'u,v,x,y,z', got {shown!r}")
    assert "\ufeff" not in msg


def test_correspondences_errors_give_the_file_line_number(tmp_path):
    """Blank lines count: the error names the line a text editor shows."""
    path = tmp_path / "correspondences.csv"
    path.write_text("u,v,x,y,z\n\n1,2,3,4,5\n\n6,7,8,9\n")
    assert_input_error(read_correspondences, path, "line 5 has 4 cells")


GOOD_ROWS = [[10 * i + 1, 10 * i + 2, i, i * i, 1.5 * i] for i in range(5)]
BAD_CSV = {
    "header-order": (GOOD_ROWS, "x,y,z,u,v", "header"),
    "header-missing": (GOOD_ROWS, None, "header"),
    "header-short": (GOOD_ROWS, "u,v,x,y", "header"),
    "empty": ([], "", "header"),
    "non-numeric": (GOOD_ROWS[:2] + [[1, "abc", 3, 4, 5]] + GOOD_ROWS[3:], "u,v,x,y,z", "line 4"),
    "short-row": (GOOD_ROWS[:3] + [[1, 2, 3, 4]] + GOOD_ROWS[4:], "u,v,x,y,z", "line 5"),
    "long-row": (GOOD_ROWS + [[1, 2, 3, 4, 5, 6]], "u,v,x,y,z", "line 7"),
    "nan": (GOOD_ROWS + [[1, 2, "nan", 4, 5]], "u,v,x,y,z", "non-finite"),
    "inf": (GOOD_ROWS + [["inf", 2, 3, 4, 5]], "u,v,x,y,z", "non-finite"),
    "three-rows": (GOOD_ROWS[:3], "u,v,x,y,z", "3 correspondences"),
    "no-rows": ([], "u,v,x,y,z", "0 correspondences"),
    "duplicate": (GOOD_ROWS + [GOOD_ROWS[2]], "u,v,x,y,z", "duplicate"),
}


@pytest.mark.parametrize("case", list(BAD_CSV))
def test_bad_correspondences_raise_naming_the_file(tmp_path, case):
    rows, header, word = BAD_CSV[case]
    path = write_csv(tmp_path / "correspondences.csv", rows, header)
    assert_input_error(read_correspondences, path, word)


def test_missing_and_binary_correspondences(tmp_path):
    assert_input_error(read_correspondences, tmp_path / "correspondences.csv", "not found")
    path = tmp_path / "bin.csv"
    path.write_bytes(b"\xff\xfe\x00\x81\x82")
    assert_input_error(read_correspondences, path)


# -- meshes --------------------------------------------------------------------------------------
def box_mesh():
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    box.apply_translation((0.5, 1.0, 1.5))
    return box


def total_area(mesh):
    v = mesh.vertices[mesh.faces]
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "glb", "off"])
def test_trimesh_written_mesh_loads(tmp_path, ext):
    path = tmp_path / f"mesh.{ext}"
    box_mesh().export(path)
    mesh = load_mesh(path)
    assert mesh.faces.shape == (12, 3) and mesh.faces.dtype == np.int64
    assert mesh.vertices.dtype == np.float64
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [1, 2, 3], atol=1e-6)
    assert abs(total_area(mesh) - 2 * (1 * 2 + 2 * 3 + 1 * 3)) < 1e-5
    assert abs(mesh.scale - math.sqrt(14.0)) < 1e-6
    np.testing.assert_allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1.0, atol=1e-9)
    # face normals point out of the box (volume-weighted: sum of n . (centroid - centre) > 0)
    cent = mesh.vertices[mesh.faces].mean(axis=1) - np.array([0.5, 1.0, 1.5])
    assert np.all(np.einsum("ij,ij->i", mesh.face_normals, cent) > 0)
    assert mesh.notes == ()
    assert find_mesh(tmp_path) == path


def test_multi_part_glb_becomes_one_mesh(tmp_path):
    import trimesh

    scene = trimesh.Scene()
    scene.add_geometry(box_mesh(), node_name="box")
    T = np.eye(4)
    T[:3, 3] = (5.0, 0.0, 0.0)
    scene.add_geometry(trimesh.creation.icosphere(subdivisions=1, radius=0.5), node_name="ball", transform=T)
    path = tmp_path / "mesh.glb"
    scene.export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 12 + 80
    # the node transform is applied: the ball sits around x = 5
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [5.5, 2.0, 3.0], atol=1e-6)
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [0.0, -0.5, -0.5], atol=1e-6)
    assert mesh.faces.max() < len(mesh.vertices)


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_nonfinite_vertices_raise(tmp_path, bad):
    path = tmp_path / "mesh.obj"
    path.write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\nv {bad} 1 0\nf 1 2 3\nf 2 4 3\n")
    assert_input_error(load_mesh, path, "NaN")


def test_degenerate_and_duplicate_faces_removed_and_noted(tmp_path):
    path = tmp_path / "mesh.obj"
    path.write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\n"
        "f 1 2 3\nf 1 3 4\n"  # the square
        "f 1 2 3\n"  # duplicate
        "f 3 2 1\n"  # duplicate (reversed)
        "f 1 2 5\n"  # collinear: zero area
        "f 1 1 2\n"  # repeated vertex: zero area
    )
    mesh = load_mesh(path)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
    assert abs(total_area(mesh) - 1.0) < 1e-12
    assert "removed 2 zero-area faces" in mesh.notes
    assert "removed 2 duplicate faces" in mesh.notes


@pytest.mark.parametrize("ext,content", [("obj", ""), ("ply", ""), ("stl", ""), ("glb", ""),
                                         ("obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
                                         ("obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")],
                         ids=["obj", "ply", "stl", "glb", "obj-no-faces", "obj-all-degenerate"])
def test_empty_mesh_raises(tmp_path, ext, content):
    path = tmp_path / f"mesh.{ext}"
    path.write_text(content)
    assert_input_error(load_mesh, path)


def test_missing_mesh(tmp_path):
    assert_input_error(load_mesh, tmp_path / "mesh.obj", "not found")
    with pytest.raises(InputError, match="mesh"):
        find_mesh(tmp_path)


def test_dataclasses_expose_geometry():
    cam = Camera(64, 48, 60.0, 61.0, 31.5, 23.5)
    assert cam.dist_coeffs.shape == (5,) and not cam.dist_coeffs.any()
    R = rotation(3)
    pose = Pose(R, np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(R @ pose.camera_centre + pose.t, 0.0, atol=1e-12)


# == properties (hypothesis): random documents, text and bytes ======================================
# Each reader either returns a valid object or raises InputError naming the file; nothing else
# may escape. Documents valid by the README's rules are accepted with the values they hold, and
# round trips through the project's own writers give back what was written.

def dist_lists():
    coeff = st.one_of(st.floats(-1, 1), st.integers(-2, 2))
    bad = st.one_of(coeff, anyfloat, json_values)
    return st.one_of(
        st.sampled_from([4, 5, 8, 12, 14]).flatmap(lambda n: st.lists(coeff, min_size=n, max_size=n)),
        st.lists(coeff, max_size=16),  # every length, the valid ones included
        st.lists(bad, max_size=6),
        st.lists(st.lists(coeff, max_size=3), max_size=5))


def write_doc(path: Path, doc) -> None:
    """`doc` is a JSON-able value (NaN/Infinity written as Python's json does), raw text or bytes."""
    if isinstance(doc, bytes):
        path.write_bytes(doc)
    elif isinstance(doc, tuple) and doc and doc[0] == "text":
        path.write_text(doc[1])
    else:
        path.write_text(json.dumps(doc))


CAMERA_FIELDS = {
    "width": st.one_of(st.integers(1, 10000), st.integers(1, 10000).map(float)),
    "height": st.one_of(st.integers(1, 10000), st.integers(1, 10000).map(float)),
    "fx": st.floats(1e-3, 1e5), "fy": st.floats(1e-3, 1e5),
    "cx": st.floats(-1e4, 1e4), "cy": st.floats(-1e4, 1e4), "dist": dist_lists(),
}


@st.composite
def camera_docs(draw):
    doc = {key: draw(valid) for key, valid in CAMERA_FIELDS.items()}
    if draw(st.booleans()):
        del doc["dist"]  # optional
    wrong = st.one_of(wrong_values, st.sampled_from([0, -1, 0.5, 1e-320, math.nan, math.inf, True, "640"]))
    return mutate(draw, doc, list(CAMERA_FIELDS), wrong)


def other_content():
    """Files that are not a JSON object at all."""
    return st.one_of(json_values.filter(lambda v: not isinstance(v, dict)),
                     st.binary(max_size=40),
                     st.tuples(st.just("text"), st.text(max_size=40)))


def camera_is_valid_by_the_readme(doc) -> bool:
    """The strict rules: required numbers finite, sizes positive whole, focal lengths positive,
    dist (optional) a list of 4, 5, 8, 12 or 14 finite numbers."""
    if not isinstance(doc, dict):
        return False
    if not all(k in doc and finite_real(doc[k]) for k in ("width", "height", "fx", "fy", "cx", "cy")):
        return False
    if any(doc[k] <= 0 for k in ("width", "height", "fx", "fy")):
        return False
    if any(doc[k] != int(doc[k]) for k in ("width", "height")):
        return False
    if any(2 * math.degrees(math.atan(0.5 * doc[s] / doc[f])) > 175 for f, s in (("fx", "width"), ("fy", "height"))):
        return False  # (a field of view beyond 175 deg: a focal length not in pixels)
    dist = doc.get("dist", [0.0] * 5)
    return isinstance(dist, list) and len(dist) in (4, 5, 8, 12, 14) and all(finite_real(v) for v in dist)


@props(150)
@given(doc=st.one_of(camera_docs(), camera_docs(), other_content()))
def test_read_camera_accepts_valid_files_only(workdir, doc):
    path = workdir / "camera.json"
    write_doc(path, doc)
    try:
        cam = sc.read_camera(path)
    except InputError as exc:
        assert_names_file(exc, path)
        assert not camera_is_valid_by_the_readme(doc), f"a valid camera was rejected: {exc}"
        event("rejected")
        return
    event("accepted")
    # accepted: a valid camera holding exactly the file's numbers
    assert isinstance(doc, dict)
    assert type(cam.width) is int and type(cam.height) is int and cam.width > 0 and cam.height > 0
    assert cam.width == doc["width"] and cam.height == doc["height"]
    for k in ("fx", "fy", "cx", "cy"):
        assert is_real(doc[k]) and getattr(cam, k) == float(doc[k]), k
        assert math.isfinite(getattr(cam, k))
    assert cam.fx > 0 and cam.fy > 0
    assert len(cam.dist) == 5 and all(type(v) is float and math.isfinite(v) for v in cam.dist)
    given_dist = np.asarray(doc.get("dist", [0.0] * 5), dtype=np.float64)
    assert given_dist.ndim == 1 and given_dist.size in (4, 5, 8, 12, 14)
    expect = np.zeros(5)
    expect[:min(5, given_dist.size)] = given_dist[:5]
    assert np.array_equal(cam.dist_coeffs, expect)
    assert np.all(np.isfinite(cam.K)) and cam.K.shape == (3, 3)
    assert same_json(cam.extra, {k: v for k, v in doc.items()
                                 if k not in {"width", "height", "fx", "fy", "cx", "cy", "dist"}})


# -- pose.json ------------------------------------------------------------------------------------

unit_quaternions = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: sum(c * c for c in q) > 1e-3)


def quaternion_rotation(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@st.composite
def rotation_like(draw):
    """Rotations, slightly or badly perturbed rotations, reflections, arbitrary 3 x 3 numbers."""
    R = quaternion_rotation(draw(unit_quaternions))
    kind = draw(st.sampled_from(["rotation", "rotation", "perturbed", "reflection", "numbers"]))
    if kind == "perturbed":
        eps = 10.0 ** draw(st.integers(-9, -1))
        R = R + eps * np.asarray(draw(st.lists(st.floats(-1, 1), min_size=9, max_size=9))).reshape(3, 3)
    elif kind == "reflection":
        R = R * np.array([[1.0], [1.0], [-1.0]])
    elif kind == "numbers":
        R = np.asarray(draw(st.lists(json_numbers, min_size=9, max_size=9)), dtype=object).reshape(3, 3)
    return R.tolist()


@st.composite
def pose_docs(draw):
    doc = {"R": draw(rotation_like()), "t": draw(st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3))}
    wrong_shape = st.lists(st.floats(-10, 10), max_size=5) | st.lists(st.lists(st.floats(-1, 1), max_size=4),
                                                                       max_size=4)
    return mutate(draw, doc, ["R", "t"], st.one_of(wrong_values, wrong_shape,
                                                    st.lists(json_numbers, min_size=3, max_size=3)), most=1)


def numeric_matrix(v, shape) -> np.ndarray | None:
    """`v` as a float array if it is nested lists of finite JSON numbers of `shape`, else None."""
    def ok(x, shape):
        if not shape:
            return finite_real(x)
        return isinstance(x, list) and len(x) == shape[0] and all(ok(y, shape[1:]) for y in x)
    return np.asarray(v, dtype=np.float64) if ok(v, shape) else None


@props(150)
@given(doc=st.one_of(pose_docs(), pose_docs(), other_content()))
def test_read_pose_accepts_rotations_only(workdir, doc):
    path = workdir / "pose.json"
    write_doc(path, doc)
    R_in = numeric_matrix(doc.get("R"), (3, 3)) if isinstance(doc, dict) else None
    t_in = numeric_matrix(doc.get("t"), (3,)) if isinstance(doc, dict) else None
    # how far R is from a rotation (the README: orthonormal, det +1)
    ortho = None if R_in is None else float(np.abs(R_in @ R_in.T - np.eye(3)).max())
    try:
        pose = sc.read_pose(path)
    except InputError as exc:
        assert_names_file(exc, path)
        clearly_valid = R_in is not None and t_in is not None and ortho <= 1e-6 and np.linalg.det(R_in) > 0
        assert not clearly_valid, f"a valid pose was rejected: {exc}"
        event("rejected")
        return
    event("accepted")
    R, t = pose.R, pose.t
    assert R.shape == (3, 3) and t.shape == (3,) and R.dtype == np.float64 and t.dtype == np.float64
    assert np.all(np.isfinite(R)) and np.all(np.isfinite(t))
    assert np.abs(R @ R.T - np.eye(3)).max() <= 1e-12, "R must be re-orthonormalised"
    assert abs(np.linalg.det(R) - 1.0) <= 1e-12
    # the file's R was a rotation up to the reader's 1e-4 (max |R R' - I|); the nearest rotation
    # (polar factor) then differs from it by |sigma - 1| <= |sigma^2 - 1| <= ||RR' - I||_2 <= 3e-4
    R_file = np.asarray(doc["R"], dtype=np.float64)
    t_file = np.asarray(doc["t"], dtype=np.float64)
    assert np.abs(R - R_file).max() <= 3.1e-4
    assert np.array_equal(t, t_file)
    assert same_json(pose.extra, {k: v for k, v in doc.items() if k not in ("R", "t")})
    if R_in is not None and ortho > 2e-4:  # well beyond the tolerance: the reader must not accept
        pytest.fail(f"R with |RR' - I| = {ortho:.3g} was accepted")
    assert np.all(np.isfinite(pose.camera_centre))


# -- round trips through the project's writer -----------------------------------------------------

extra_values = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(-1000, 1000),
                                      st.floats(allow_nan=False, allow_infinity=False), text),
                            lambda kids: st.lists(kids, max_size=3) | st.dictionaries(text, kids, max_size=3),
                            max_leaves=6)


@props(100)
@given(width=st.integers(1, 20000), height=st.integers(1, 20000), fx=st.floats(1e-3, 1e6), fy=st.floats(1e-3, 1e6),
       cx=st.floats(-1e5, 1e5), cy=st.floats(-1e5, 1e5), dist=st.lists(st.floats(-10, 10), min_size=5, max_size=5),
       extra=st.dictionaries(text.filter(lambda k: k not in {"width", "height", "fx", "fy", "cx", "cy", "dist"}),
                             extra_values, max_size=3))
def test_camera_round_trip_through_the_writer(workdir, width, height, fx, fy, cx, cy, dist, extra):
    assume(fx >= 0.03 * width and fy >= 0.03 * height)  # (a field of view within 175 deg: read_camera's rule)
    cam = camera.Camera(width, height, fx, fy, cx, cy, tuple(dist), extra)
    path = workdir / "camera_rt.json"
    write_json_atomic(path, cam.to_json())
    back = sc.read_camera(path)
    assert back == cam  # every field but extra (compare=False), exactly: JSON floats round-trip
    assert back.extra == extra


@props(100)
@given(q=unit_quaternions, t=st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3),
       extra=st.dictionaries(text.filter(lambda k: k not in {"R", "t"}), extra_values, max_size=3))
def test_pose_round_trip_through_the_writer(workdir, q, t, extra):
    pose = camera.Pose(quaternion_rotation(q), np.asarray(t, dtype=np.float64), extra)
    path = workdir / "pose_rt.json"
    write_json_atomic(path, pose.to_json())
    back = sc.read_pose(path)
    assert np.abs(back.R - pose.R).max() <= 1e-14  # re-orthonormalised: rounding only
    assert np.array_equal(back.t, pose.t)
    assert back.extra == extra


# -- correspondences.csv --------------------------------------------------------------------------

number_cells = st.one_of(
    st.floats(-1e4, 1e4).map(repr), st.integers(-5000, 5000).map(str),
    st.floats(-1e4, 1e4).map(lambda v: f" {v:.6g} "))
odd_cells = st.one_of(
    st.sampled_from(["nan", "inf", "-inf", "1e999", "1_000", "+3", "0x10", ".5", "5.", "1e-400", "", " ", '"1"',
                     "1,5"]),
    st.text(st.characters(exclude_categories=("Cs",), exclude_characters="\x00"), max_size=6))
CSV_MUTATIONS = ["odd cell", "odd cell", "drop rows", "repeat row", "extra cell", "missing cell", "header",
                 "blank line", "stray quote"]


@st.composite
def csv_texts(draw):
    """A file of 1..8 rows of 5 numbers (u made distinct so that rows are; valid from 4 rows on)
    with up to two mistakes."""
    n = draw(st.sampled_from([1, 3, 4, 4, 5, 8]))
    rows = [[f"{10 * i + draw(st.integers(0, 9))}"] + [draw(number_cells) for _ in range(4)] for i in range(n)]
    header = draw(st.sampled_from(["u,v,x,y,z", "U, V, X, Y, Z", " u ,v,x,y,z"]))
    blank = []
    for mutation in draw(st.lists(st.sampled_from(CSV_MUTATIONS), max_size=2)):
        r = draw(st.integers(0, len(rows) - 1)) if rows else None
        if mutation == "odd cell" and rows and rows[r]:
            rows[r][draw(st.integers(0, len(rows[r]) - 1))] = draw(odd_cells)
        elif mutation == "drop rows":
            del rows[draw(st.integers(0, len(rows))):]
        elif mutation == "repeat row" and rows:
            rows.insert(draw(st.integers(0, len(rows))), list(rows[r]))
        elif mutation == "extra cell" and rows:
            rows[r].append(draw(number_cells))
        elif mutation == "missing cell" and rows and rows[r]:
            rows[r].pop()
        elif mutation == "header":
            header = draw(st.sampled_from(["u,v,x,y", "u,v,x,y,z,w", "x,y,z,u,v", "", "uv,x,y,z"])
                          | st.text(max_size=12))
        elif mutation == "blank line":
            blank.append(draw(st.sampled_from(["", " ", ",,,,", "\t"])))
        elif mutation == "stray quote" and rows:
            rows[r][0] = '"' + rows[r][0]
    lines = [header] + [",".join(row) for row in rows]
    for b in blank:
        lines.insert(draw(st.integers(0, len(lines))), b)
    return draw(st.sampled_from(["\n", "\r\n"])).join(lines) + draw(st.sampled_from(["", "\n"]))


def csv_rows_by_the_readme(content) -> np.ndarray | None:
    """The (n, 5) values if the file is valid by the strict rules (header u,v,x,y,z, every other
    non-blank line 5 finite numbers, no repeats, at least 4), else None. Exotic number spellings
    (1_000, '1e-400') are left to the reader."""
    if not isinstance(content, str):
        return None
    lines = [ln for ln in content.splitlines() if ln.strip(" ,")]
    if not lines or [c.strip().lower() for c in lines[0].split(",")] != ["u", "v", "x", "y", "z"]:
        return None
    values = []
    for ln in lines[1:]:
        cells = ln.split(",")
        if len(cells) != 5 or any('"' in c or "_" in c for c in cells):
            return None
        try:
            row = [float(c) for c in cells]
        except ValueError:
            return None
        if not all(math.isfinite(v) for v in row):
            return None
        values.append(row)
    arr = np.asarray(values, dtype=np.float64).reshape(-1, 5)
    if len(arr) < 4 or len(np.unique(arr, axis=0)) != len(arr):
        return None
    return arr


@props(150)
@given(content=st.one_of(csv_texts(), csv_texts(), csv_texts(), csv_texts(), st.text(max_size=60),
                        st.binary(max_size=60)))
def test_read_correspondences_accepts_valid_files_only(workdir, content):
    path = workdir / "correspondences.csv"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_bytes(content.encode("utf-8"))  # no newline translation: \r\n stays \r\n
    valid = csv_rows_by_the_readme(content)
    try:
        uv, xyz = sc.read_correspondences(path)
    except InputError as exc:
        assert_names_file(exc, path)
        assert valid is None, f"a valid file was rejected: {exc}"
        event("rejected")
        return
    event(f"accepted ({len(uv)} rows)")
    assert uv.dtype == np.float64 and xyz.dtype == np.float64
    assert uv.ndim == 2 and uv.shape[1] == 2 and xyz.shape == (len(uv), 3)
    assert len(uv) >= 4
    rows = np.hstack([uv, xyz])
    assert np.all(np.isfinite(rows))
    assert len(np.unique(rows, axis=0)) == len(rows), "duplicate rows accepted"
    if valid is not None:
        assert np.array_equal(rows, valid)


# -- mesh -------------------------------------------------------------------------------------------

coord = st.floats(-100, 100, allow_subnormal=False) | st.integers(-3, 3)
MESH_MUTATIONS = ["nan vertex", "degenerate face", "duplicate face", "reversed face", "no faces", "unused vertex"]


@st.composite
def mesh_parts(draw, mutations):
    """3..6 vertices and 1..5 triangles or quads with valid indices, then up to two mistakes."""
    nv = draw(st.integers(3, 6))
    V = [[repr(float(draw(coord))) for _ in range(3)] for _ in range(nv)]
    F = draw(st.lists(st.lists(st.integers(0, nv - 1), min_size=3, max_size=4, unique=True), min_size=1, max_size=5))
    for mutation in draw(st.lists(st.sampled_from(mutations), max_size=2)):
        if mutation == "nan vertex":
            V[draw(st.integers(0, nv - 1))][draw(st.integers(0, 2))] = draw(st.sampled_from(["nan", "inf", "-inf"]))
        elif mutation == "degenerate face":
            i = draw(st.integers(0, nv - 1))
            F.append([i, i, draw(st.integers(0, nv - 1))])
        elif mutation in ("duplicate face", "reversed face") and F:
            f = F[draw(st.integers(0, len(F) - 1))]
            F.append(list(f) if mutation == "duplicate face" else f[::-1])
        elif mutation == "no faces":
            F = []
        elif mutation == "unused vertex":
            V.append([repr(float(draw(coord))) for _ in range(3)])
        elif mutation == "index out of range" and F:
            F[draw(st.integers(0, len(F) - 1))][0] = draw(st.sampled_from([len(V), len(V) + 5, -1]))
        elif mutation == "short face":
            F.append(draw(st.lists(st.integers(0, nv - 1), min_size=1, max_size=2)))
        elif mutation in ("junk line", "normals"):
            pass  # OBJ only (obj_texts)
    return V, F


@st.composite
def obj_texts(draw):
    extra = ["index out of range", "short face", "junk line", "normals"]
    V, F = draw(mesh_parts(MESH_MUTATIONS + extra))
    negative = draw(st.booleans())  # OBJ's relative indices: -1 is the last vertex

    def ref(i):
        return str(i - len(V) if negative and 0 <= i < len(V) else i + 1 if i >= 0 else i)
    lines = ["v " + " ".join(v) for v in V]
    if draw(st.booleans()):
        normals = [[repr(float(draw(coord))) for _ in range(3)] for _ in range(draw(st.integers(1, 3)))]
        lines += ["vn " + " ".join(n) for n in normals]
        lines += ["f " + " ".join(f"{ref(i)}//{draw(st.integers(1, len(normals)))}" for i in f) for f in F]
    else:
        lines += ["f " + " ".join(ref(i) for i in f) for f in F]
    for _ in range(draw(st.integers(0, 1))):
        lines.insert(draw(st.integers(0, len(lines))),
                     draw(st.sampled_from(["# comment", "o part", "g group", "s 1", "vt 0 0", "usemtl x"])
                          | st.text(st.characters(exclude_categories=("Cs",), exclude_characters="\n\r\x00"),
                                    max_size=10)))
    return "\n".join(lines) + "\n"


@st.composite
def ply_texts(draw):
    """ASCII PLY (face indices may point outside the vertex list)."""
    V, F = draw(mesh_parts(MESH_MUTATIONS + ["index out of range"]))
    head = ["ply", "format ascii 1.0", f"element vertex {len(V)}", "property float x", "property float y",
            "property float z", f"element face {len(F)}", "property list uchar int vertex_indices", "end_header"]
    return "\n".join(head + [" ".join(v) for v in V] + [f"{len(f)} " + " ".join(map(str, f)) for f in F]) + "\n"


@props(150)
@given(kind=st.sampled_from(["obj", "obj", "ply", "bytes"]), data=st.data())
def test_load_mesh_returns_a_clean_triangle_mesh_or_input_error(workdir, kind, data):
    if kind == "bytes":
        suffix = data.draw(st.sampled_from(sc.MESH_SUFFIXES))
        path = workdir / f"mesh{suffix}"
        path.write_bytes(data.draw(st.binary(max_size=80)))
    else:
        path = workdir / f"mesh.{kind}"
        path.write_text(data.draw(obj_texts() if kind == "obj" else ply_texts()))
    try:
        mesh = sc.load_mesh(path)
    except InputError as exc:
        assert_names_file(exc, path)
        event(f"{kind}: rejected")
        return
    event(f"{kind}: accepted")
    V, F, N = mesh.vertices, mesh.faces, mesh.vertex_normals
    assert V.dtype == np.float64 and V.ndim == 2 and V.shape[1] == 3 and np.all(np.isfinite(V))
    assert F.dtype == np.int64 and F.ndim == 2 and F.shape[1] == 3 and len(F) >= 1
    assert F.min() >= 0 and F.max() < len(V)
    assert N.shape == V.shape and np.all(np.isfinite(N))
    area2 = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    assert np.all(area2 > 0), "a zero-area face was kept"
    assert len(np.unique(np.sort(F, axis=1), axis=0)) == len(F), "a duplicate face was kept"
    assert np.all(np.isfinite(mesh.face_normals))
    used = np.unique(F)  # (a vertex no face uses may keep any normal: it is never shaded)
    assert np.allclose(np.linalg.norm(N[used], axis=1), 1.0, atol=1e-9), "shading normals must be unit"


# -- regressions: bugs these properties found, each with its minimal input ----------------------
# Each failed on commit 40420ef (a traceback, or a wrong acceptance); each passes once its bug is fixed.


@pytest.mark.parametrize("name, doc", [
    ("camera.json", {"width": HUGE, "height": 480, "fx": 500, "fy": 500, "cx": 320, "cy": 240}),
    ("camera.json", {"width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 320, "cy": 240, "dist": [HUGE]}),
    ("pose.json", {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [HUGE, 0, 0]}),
])
def test_huge_json_integers_are_input_errors(workdir, name, doc):
    """Was: scene._number / scene._array converted with float(), which overflows for an integer
    beyond float64; OverflowError was not caught (a traceback)."""
    path = workdir / name
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as info:
        (sc.read_camera if name == "camera.json" else sc.read_pose)(path)
    assert_names_file(info.value, path)


def test_correspondences_stray_quote_is_input_error(workdir):
    """Was: csv's 128 KiB field limit raised _csv.Error, uncaught: a stray quote at the top of a
    long file swallowed the rest into one field and escaped as a traceback."""
    path = workdir / "correspondences.csv"
    rows = "\n".join(f"{i},{i},{i},{i},{i}" for i in range(20000))
    path.write_text('u,v,x,y,z\n"' + rows + "\n")
    with pytest.raises(InputError) as info:
        sc.read_correspondences(path)
    assert_names_file(info.value, path)


def test_ply_face_index_out_of_range_is_input_error(workdir):
    """Was: load_mesh indexed vertices[faces] without checking the indices (IndexError)."""
    path = workdir / "mesh.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n")
    with pytest.raises(InputError) as info:
        sc.load_mesh(path)
    assert_names_file(info.value, path)


def test_folded_mesh_gets_unit_vertex_normals(workdir):
    """Was: the fallback recomputed the vertex normals from the same faces; at a vertex whose
    faces cancel (a sheet folded back onto itself, sharing vertices) the normal stayed ~0 (1e-8
    after the 1e-12 clip), not unit as Mesh promises."""
    path = workdir / "folded.obj"
    path.write_text("v 0 0 1\nv 0 0 0\nv 0 1 0\nv 0 0 0\nf 1 2 3\nf 3 4 1\n")
    mesh = sc.load_mesh(path)
    assert len(mesh.faces) == 2  # two distinct faces, neither degenerate nor a duplicate by index
    assert np.allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1.0)


def test_ply_with_a_vertex_no_face_uses_loads(workdir):
    """A vertex no face uses (common in exported PLY) sends load_mesh into its normal fallback;
    the fallback must not write into trimesh's cached, read-only normals array (ValueError)."""
    path = workdir / "loose.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n5 5 5\n3 0 1 2\n")
    mesh = sc.load_mesh(path)
    assert mesh.faces.tolist() == [[0, 1, 2]]
    assert np.allclose(np.abs(mesh.vertex_normals[:3, 2]), 1.0)
