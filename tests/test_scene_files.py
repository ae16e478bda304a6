"""Tests for the scene file readers in pipelines.scene: camera.json, pose.json,
correspondences.csv and mesh loading."""

import json
import math

import numpy as np
import pytest

from pipelines.errors import InputError
from pipelines.geometry.camera import Camera, Pose
from pipelines.io.scene_files import find_mesh, load_mesh, read_camera, read_correspondences, read_pose

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
