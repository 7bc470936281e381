"""Session layer: loading the tiny session round-trips what was written, and every bad input is reported."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
import yaml
from conftest import (
    LABEL_OBJECT,
    LABEL_PERSON,
    TINY_COLORS,
    render_tiny_view,
    tiny_camera,
    tiny_keypoints3d,
    tiny_object_pose,
    tiny_openpose,
    tiny_person_mesh,
    write_tiny_session,
)

from intercap.session import (
    NUM_KEYPOINTS_2D,
    Problem,
    Session,
    SessionError,
    format_report,
    openpose_to_array,
    validate,
)

# --------------------------------------------------------------------------- round trip


def test_round_trip(tiny_session: Path):
    s = Session.load(tiny_session)
    assert s.problems == []
    assert s.fps == 30.0
    assert s.camera_names == ["cam0", "cam1"] and s.num_cameras == 2
    assert s.num_frames == 3 and s.frame_ids.tolist() == [0, 1, 2]
    assert s.body_model == "anny"
    for i, cam in enumerate(s.cameras):
        K, T = tiny_camera(i, 2)
        assert (cam.width, cam.height) == (64, 48)
        np.testing.assert_allclose(cam.K, K)
        np.testing.assert_allclose(cam.T_world_from_cam, T)
        np.testing.assert_allclose(cam.T_cam_from_world @ cam.T_world_from_cam, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(cam.center, T[:3, 3])
        assert cam.K.dtype == np.float64 and cam.T_world_from_cam.dtype == np.float64
    assert s.camera("cam1") is s.cameras[1] and s.camera(0) is s.cameras[0]
    assert s.camera(1).dist.shape == (5,) and s.camera(0).dist.shape == (0,)
    with pytest.raises(KeyError, match="cam7"):
        s.camera("cam7")

    # depth: metres = written millimetres / 1000, 0 where the ray hit nothing
    K1, T1 = tiny_camera(1, 2)
    depth_mm, label = render_tiny_view(K1, T1, 64, 48, 2)
    depth = s.read_depth("cam1", 2)
    assert depth.dtype == np.float32 and depth.shape == (48, 64)
    np.testing.assert_allclose(depth, depth_mm / 1000.0, rtol=1e-6)
    assert (depth == 0).any() and (depth > 0).any()

    batch = s.read_depth_batch(s.frame_ids)  # (T, C, H, W)
    assert batch.shape == (3, 2, 48, 64) and batch.dtype == np.float32
    np.testing.assert_array_equal(batch[2, 1], depth)

    # masks and colour
    np.testing.assert_array_equal(s.read_mask("cam1", 2, "person"), label == LABEL_PERSON)
    np.testing.assert_array_equal(s.read_mask("cam1", 2, "object"), label == LABEL_OBJECT)
    png = s.read_color("cam1", 2)  # PNG: exact, RGB order
    assert png.shape == (48, 64, 3) and png.dtype == np.uint8
    np.testing.assert_array_equal(png[label == LABEL_OBJECT][0], TINY_COLORS[LABEL_OBJECT])
    K0, T0 = tiny_camera(0, 2)
    _, label0 = render_tiny_view(K0, T0, 64, 48, 0)
    jpg = s.read_color("cam0", 0)  # JPEG: close; the red/blue order proves BGR -> RGB
    person_rgb = jpg[label0 == LABEL_PERSON].astype(float).mean(0)
    assert np.abs(person_rgb - TINY_COLORS[LABEL_PERSON]).max() < 30
    assert s.frame_path("cam0", "color", 0).name == "000000.jpg"
    assert s.frame_path("cam1", "color", 0).name == "000000.png"
    assert s.frame_path("cam1", "mask_object", 1) == tiny_session / "cam1/masks/object/000001.png"

    # keypoints: (137, 3); body and left hand written, right hand empty, face absent -> conf 0
    kp = s.read_keypoints("cam0", 1)
    assert kp.shape == (NUM_KEYPOINTS_2D, 3) and kp.dtype == np.float32
    expected = openpose_to_array(tiny_openpose(K0, T0, tiny_keypoints3d(3)[1]))[0]
    np.testing.assert_allclose(kp, expected)
    np.testing.assert_allclose(kp[:25, 2], 0.8)
    np.testing.assert_allclose(kp[25:46, 2], 0.8)
    assert np.all(kp[46:] == 0)
    assert s.read_keypoints("cam1", 1) is None  # cam1 has no keypoints folder

    avail = s.availability()
    assert set(avail) == {"color", "depth", "keypoints", "mask_person", "mask_object"}
    assert avail["color"].shape == (2, 3) and avail["color"].all()
    assert avail["keypoints"].tolist() == [[True] * 3, [False] * 3]

    # object and annotations
    assert s.object.name == "box" and s.object.mass_kg == 1.2
    assert s.object.contact_vertices.tolist() == [0, 1, 2, 3]
    R0, t0 = tiny_object_pose(0)
    np.testing.assert_allclose(s.object.initial_pose[0], R0)
    np.testing.assert_allclose(s.object.initial_pose[1], t0)
    mesh = s.object.load_mesh()
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) == 12
    np.testing.assert_allclose(mesh.extents, [0.3, 0.2, 0.2])
    assert s.contact_frames == [(2, 2)]
    np.testing.assert_allclose(s.ground[1], [0, 0, 1])

    # ground truth
    gt = s.ground_truth()
    person = tiny_person_mesh()
    assert gt.body_vertices.shape == (3, len(person.vertices), 3) and gt.body_vertices.dtype == np.float32
    np.testing.assert_allclose(gt.body_vertices[1], person.vertices, atol=1e-6)
    np.testing.assert_array_equal(gt.body_faces, person.faces)
    np.testing.assert_allclose(gt.object_R[2], tiny_object_pose(2)[0])
    np.testing.assert_allclose(gt.object_t[2], tiny_object_pose(2)[1])
    assert gt.contact.tolist() == [False, False, True]
    assert gt.keypoints3d.shape == (3, 67, 3)

    text = s.summary()
    assert "cam0" in text and "64x48" in text and "3 frames" in text and "box" in text
    report = format_report(*validate(tiny_session))
    assert report.endswith("0 problems (0 fatal)") and "cam1" in report


def test_depth_is_consistent_with_geometry(tiny_session: Path):
    """Back-projected ground pixels of the tiny session lie on the plane z = 0 (the fixture is a real scene)."""
    s = Session.load(tiny_session)
    cam = s.camera(0)
    _, label = render_tiny_view(cam.K, cam.T_world_from_cam, 64, 48, 0)
    depth = s.read_depth(0, 0)
    v, u = np.nonzero(label == 1)
    z = depth[v, u]
    pts_cam = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0] * z, (v - cam.K[1, 2]) / cam.K[1, 1] * z, z], -1)
    pts = pts_cam @ cam.T_world_from_cam[:3, :3].T + cam.T_world_from_cam[:3, 3]
    assert np.abs(pts[:, 2]).max() < 0.005


def test_body_only_session_without_frames_block(tmp_path: Path):
    root = write_tiny_session(tmp_path / "s", with_object=False, frames_block=False, ground_truth=False, masks=False)
    s = Session.load(root)
    assert s.object is None and s.ground_truth() is None and s.contact_frames is None
    assert s.frame_ids.tolist() == [0, 1, 2]
    assert s.read_mask(0, 0, "person") is None
    assert "body only" in s.summary()


def test_read_depth_batch_needs_equal_sizes(tiny_session: Path):
    calib = json.loads((tiny_session / "calibration.json").read_text())
    calib["cameras"][1]["width"] = 32
    calib["cameras"][1]["K"][0][2] = 16.0  # the principal point stays near the centre of the narrower image
    (tiny_session / "calibration.json").write_text(json.dumps(calib))
    for f in range(3):  # make the files agree with the new calibration so the session loads
        for sub in ("color", "depth", "masks/person", "masks/object"):
            path = next((tiny_session / "cam1" / sub).glob(f"{f:06d}.*"))
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(path), img[:, :32].copy())
    s = Session.load(tiny_session)
    assert s.read_depth(1, 0).shape == (48, 32)
    with pytest.raises(ValueError, match="equal image sizes"):
        s.read_depth_batch([0])


# --------------------------------------------------------------------------- mutations


def edit_yaml(root: Path, fn) -> None:
    cfg = yaml.safe_load((root / "session.yaml").read_text())
    fn(cfg)
    (root / "session.yaml").write_text(yaml.safe_dump(cfg))


def edit_calib(root: Path, fn) -> None:
    calib = json.loads((root / "calibration.json").read_text())
    fn(calib)
    (root / "calibration.json").write_text(json.dumps(calib))


def cam1(fn):
    return lambda c: fn(c["cameras"][1])


def setitem(d: dict, key, value):
    d[key] = value


def write_gt(root: Path, name: str, arr) -> None:
    np.save(root / "ground_truth" / name, arr)


def unlink_frame_everywhere(root: Path, frame: int) -> None:
    for path in root.glob(f"cam*/**/{frame:06d}.*"):
        path.unlink()


def write_mesh(root: Path, mesh) -> None:
    mesh.export(root / "object.ply")


def open_box():
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.2))
    return trimesh.Trimesh(box.vertices, box.faces[:-1], process=False)


def point_cloud_ply() -> trimesh.PointCloud:
    return trimesh.PointCloud(np.random.default_rng(0).random((10, 3)))


def reflect_T(c):
    T = np.asarray(c["T_world_from_cam"])
    T[:3, 0] *= -1  # det -1
    c["T_world_from_cam"] = T.tolist()


def scale_T(c):
    T = np.asarray(c["T_world_from_cam"])
    T[:3, :3] *= 1.01
    c["T_world_from_cam"] = T.tolist()


def add_support(root: Path, entry: dict, scale: float = 1.0, write: bool = True) -> None:
    """A 0.4 m box seat (scaled by `scale`) as stool.ply and `supports: [entry]` in session.yaml."""
    if write:
        trimesh.creation.box(extents=(0.4 * scale, 0.4 * scale, 0.45 * scale)).export(root / "stool.ply")
    edit_yaml(root, lambda c: setitem(c, "supports", [entry]))


def corrupt_jpeg(root: Path) -> None:
    path = root / "cam0/color/000001.jpg"
    path.write_bytes(path.read_bytes()[:200])  # truncated


# (id, mutation, expected path, words the message must contain, fatal)
CASES = [
    ("no_session_yaml", lambda r: (r / "session.yaml").unlink(), "session.yaml", ["missing"], True),
    ("bad_yaml", lambda r: (r / "session.yaml").write_text("fps: [30\n"), "session.yaml", ["YAML"], True),
    ("no_calibration", lambda r: (r / "calibration.json").unlink(), "calibration.json", ["missing"], True),
    ("bad_calibration_json", lambda r: (r / "calibration.json").write_text("{cameras: "), "calibration.json", ["JSON"], True),
    ("no_fps", lambda r: edit_yaml(r, lambda c: c.pop("fps")), "session.yaml", ["fps"], True),
    ("negative_fps", lambda r: edit_yaml(r, lambda c: setitem(c, "fps", -5)), "session.yaml", ["fps", "positive"], True),
    ("no_cameras", lambda r: edit_calib(r, lambda c: setitem(c, "cameras", [])), "calibration.json", ["no cameras"], True),
    (
        "duplicate_camera",
        lambda r: edit_calib(r, lambda c: setitem(c["cameras"][1], "name", "cam0")),
        "calibration.json",
        ["duplicate", "cam0"],
        True,
    ),
    ("no_width", lambda r: edit_calib(r, cam1(lambda c: c.pop("width"))), "calibration.json", ["cam1", "missing", "width"], True),
    ("no_height", lambda r: edit_calib(r, cam1(lambda c: c.pop("height"))), "calibration.json", ["missing", "height"], True),
    ("no_K", lambda r: edit_calib(r, cam1(lambda c: c.pop("K"))), "calibration.json", ["missing", "K"], True),
    ("no_T", lambda r: edit_calib(r, cam1(lambda c: c.pop("T_world_from_cam"))), "calibration.json", ["missing", "T_world_from_cam"], True),
    ("K_2x3", lambda r: edit_calib(r, cam1(lambda c: setitem(c, "K", c["K"][:2]))), "calibration.json", ["K", "3x3"], True),
    (
        "K_bad_form",
        lambda r: edit_calib(r, cam1(lambda c: setitem(c, "K", [[50, 0, 30], [0, 50, 20], [0.1, 0, 1]]))),
        "calibration.json",
        ["K", "form"],
        True,
    ),
    (
        "K_negative_focal",
        lambda r: edit_calib(r, cam1(lambda c: setitem(c, "K", [[-50, 0, 30], [0, 50, 20], [0, 0, 1]]))),
        "calibration.json",
        ["focal"],
        True,
    ),
    ("dist_length_3", lambda r: edit_calib(r, cam1(lambda c: setitem(c, "dist", [0.1, 0.0, 0.0]))), "calibration.json", ["dist"], True),
    (
        "T_3x4",
        lambda r: edit_calib(r, cam1(lambda c: setitem(c, "T_world_from_cam", c["T_world_from_cam"][:3]))),
        "calibration.json",
        ["T_world_from_cam", "4x4"],
        True,
    ),
    ("T_not_orthonormal", lambda r: edit_calib(r, cam1(scale_T)), "calibration.json", ["orthonormal"], True),
    ("T_reflection", lambda r: edit_calib(r, cam1(reflect_T)), "calibration.json", ["determinant"], True),
    (
        "T_last_row",
        lambda r: edit_calib(r, cam1(lambda c: c["T_world_from_cam"][3].__setitem__(0, 0.5))),
        "calibration.json",
        ["last row"],
        True,
    ),
    ("camera_folder_missing", lambda r: shutil.rmtree(r / "cam1"), "cam1", ["camera folder missing"], True),
    ("color_folder_missing", lambda r: shutil.rmtree(r / "cam1/color"), "cam1/color", ["color folder missing"], True),
    ("depth_folder_missing", lambda r: shutil.rmtree(r / "cam1/depth"), "cam1/depth", ["depth folder missing"], True),
    (
        "camera_without_frames",
        lambda r: [p.unlink() for p in (r / "cam1/depth").iterdir()],
        "cam1/depth",
        ["no depth frames"],
        True,
    ),
    (
        "misnamed_frame",
        lambda r: (r / "cam0/color/000001.jpg").rename(r / "cam0/color/1.jpg"),
        "cam0/color/1.jpg",
        ["6-digit"],
        False,
    ),
    ("dropped_frame", lambda r: (r / "cam1/depth/000001.png").unlink(), "cam1/depth", ["dropped", "1"], False),
    ("gap_all_views", lambda r: unlink_frame_everywhere(r, 1), ".", ["gap", "1"], False),
    (
        "depth_not_uint16",
        lambda r: cv2.imwrite(str(r / "cam1/depth/000001.png"), np.zeros((48, 64), np.uint8)),
        "cam1/depth/000001.png",
        ["uint16", "dropped"],
        False,
    ),
    (
        "first_depth_not_uint16",
        lambda r: cv2.imwrite(str(r / "cam1/depth/000000.png"), np.zeros((48, 64), np.uint8)),
        "cam1/depth/000000.png",
        ["uint16"],
        True,
    ),
    ("corrupt_jpeg", corrupt_jpeg, "cam0/color/000001.jpg", ["unreadable"], False),
    (
        "garbage_png",
        lambda r: (r / "cam1/masks/person/000002.png").write_bytes(b"not a png"),
        "cam1/masks/person/000002.png",
        ["unreadable"],
        False,
    ),
    (
        "color_wrong_size",
        lambda r: cv2.imwrite(str(r / "cam1/color/000001.png"), np.zeros((24, 32, 3), np.uint8)),
        "cam1/color/000001.png",
        ["32x24", "64x48"],
        True,
    ),
    (
        "first_depth_wrong_size",
        lambda r: cv2.imwrite(str(r / "cam0/depth/000000.png"), np.zeros((24, 32), np.uint16)),
        "cam0/depth/000000.png",
        ["32x24", "64x48"],
        True,
    ),
    (
        "bad_keypoints_json",
        lambda r: (r / "cam0/keypoints/000001.json").write_text("{people: oops"),
        "cam0/keypoints/000001.json",
        ["unreadable"],
        False,
    ),
    ("mesh_missing", lambda r: (r / "object.ply").unlink(), "object.ply", ["missing"], True),
    ("mesh_unreadable", lambda r: (r / "object.ply").write_bytes(b"ply\nformat garbage\n"), "object.ply", ["unreadable"], True),
    ("mesh_not_watertight", lambda r: write_mesh(r, open_box()), "object.ply", ["watertight"], False),
    ("mesh_no_faces", lambda r: write_mesh(r, point_cloud_ply()), "object.ply", ["no faces"], True),
    ("object_without_mesh_key", lambda r: edit_yaml(r, lambda c: c["object"].pop("mesh")), "session.yaml", ["object.mesh"], True),
    (
        "contacts_malformed",
        lambda r: (r / "object_contacts.json").write_text(json.dumps({"verts": [1]})),
        "object_contacts.json",
        ["malformed"],
        True,
    ),
    (
        "contacts_out_of_range",
        lambda r: (r / "object_contacts.json").write_text(json.dumps({"vertices": [0, 8]})),
        "object_contacts.json",
        ["out of range", "8"],
        True,
    ),
    (
        "initial_pose_not_rotation",
        lambda r: edit_yaml(r, lambda c: setitem(c["object"]["initial_pose"], "R", [[2, 0, 0], [0, 1, 0], [0, 0, 1]])),
        "session.yaml",
        ["initial_pose", "rotation"],
        True,
    ),
    ("contact_frames_malformed", lambda r: edit_yaml(r, lambda c: setitem(c, "contact_frames", [[1]])), "session.yaml", ["contact_frames", "malformed"], True),
    ("contact_frames_reversed", lambda r: edit_yaml(r, lambda c: setitem(c, "contact_frames", [[2, 1]])), "session.yaml", ["contact_frames", "start after end"], True),
    ("contact_frames_outside", lambda r: edit_yaml(r, lambda c: setitem(c, "contact_frames", [[1, 9]])), "session.yaml", ["contact_frames", "outside"], True),
    ("ground_normal_zero", lambda r: edit_yaml(r, lambda c: setitem(c["ground"], "normal", [0, 0, 0])), "session.yaml", ["normal", "zero"], True),
    ("body_model_unknown", lambda r: edit_yaml(r, lambda c: setitem(c, "body", {"model": "smpl"})), "session.yaml", ["body.model", "smpl"], True),
    ("frames_start_after_end", lambda r: edit_yaml(r, lambda c: setitem(c, "frames", {"start": 2, "end": 1})), "session.yaml", ["frames", "after end"], True),
    ("frames_beyond_found", lambda r: edit_yaml(r, lambda c: setitem(c, "frames", {"start": 0, "end": 5})), "session.yaml", ["frames", "outside"], True),
    (
        "gt_T_mismatch",
        lambda r: write_gt(r, "body_vertices.npy", np.zeros((2, len(tiny_person_mesh().vertices), 3), np.float32)),
        "ground_truth/body_vertices.npy",
        ["2 frames", "3"],
        True,
    ),
    ("gt_contact_shape", lambda r: write_gt(r, "contact.npy", np.zeros((3, 2), bool)), "ground_truth/contact.npy", ["shape"], True),
    ("gt_keypoints_shape", lambda r: write_gt(r, "keypoints3d.npy", np.zeros((3, 25, 3), np.float32)), "ground_truth/keypoints3d.npy", ["shape"], True),
    (
        "gt_object_poses_shape",
        lambda r: np.savez(r / "ground_truth/object_poses.npz", R=np.zeros((3, 3)), t=np.zeros((3, 3))),
        "ground_truth/object_poses.npz",
        ["shape"],
        True,
    ),
    ("supports_not_a_list", lambda r: edit_yaml(r, lambda c: setitem(c, "supports", "stool.ply")), "session.yaml",
     ["supports", "list"], True),
    ("support_mesh_missing", lambda r: add_support(r, {"mesh": "stool.ply"}, write=False), "stool.ply",
     ["support mesh missing"], True),
    ("support_in_millimetres", lambda r: add_support(r, {"mesh": "stool.ply"}, scale=1000.0), "stool.ply",
     ["millimetres"], True),
    ("support_grip_not_bool", lambda r: add_support(r, {"mesh": "stool.ply", "grip": "yes"}), "session.yaml",
     ["supports[0].grip", "true or false"], True),
    ("support_outside_session", lambda r: add_support(r, {"mesh": "../stool.ply"}, write=False), "session.yaml",
     ["supports[0].mesh", "outside"], True),
    ("support_unknown_key", lambda r: add_support(r, {"mesh": "stool.ply", "colour": "red"}), "session.yaml",
     ["supports[0].colour"], False),
    ("object_static_not_bool", lambda r: edit_yaml(r, lambda c: setitem(c["object"], "static", "yes")), "session.yaml",
     ["object.static", "true or false"], True),
    ("gt_faces_out_of_range", lambda r: write_gt(r, "body_faces.npy", np.array([[0, 1, 9999]])), "ground_truth/body_faces.npy", ["out of range"], True),
]


# fatal problems that only validate finds: load decodes only the first colour/depth frame of each camera
VALIDATE_ONLY = {"color_wrong_size"}


@pytest.mark.parametrize("case, mutate, path, words, fatal", CASES, ids=[c[0] for c in CASES])
def test_validate_reports_bad_input(tmp_path: Path, case, mutate, path, words, fatal):
    root = write_tiny_session(tmp_path / "s")
    mutate(root)
    session, problems = validate(root)
    matching = [p for p in problems if p.path == path and all(w in p.message for w in words)]
    assert matching, f"no problem at {path!r} mentioning {words}; got:\n" + "\n".join(map(str, problems))
    assert matching[0].fatal == fatal
    assert all(isinstance(p, Problem) and str(p) == f"{p.path}: {p.message}" for p in problems)
    report = format_report(session, problems)
    assert str(matching[0]) in report
    noun = "problem" if len(problems) == 1 else "problems"
    assert report.splitlines()[-1] == f"{len(problems)} {noun} ({sum(p.fatal for p in problems)} fatal)"
    if fatal:
        assert session is None
        if case in VALIDATE_ONLY:
            Session.load(root)
        else:
            with pytest.raises(SessionError) as err:
                Session.load(root)
            assert any(p.path == path and p.fatal for p in err.value.problems)
            assert path in str(err.value)
    else:
        assert session is not None and not any(p.fatal for p in problems)
        Session.load(root)  # a warning never stops loading


def test_supports_and_a_static_object_load(tiny_session: Path):
    add_support(tiny_session, {"name": "stool", "mesh": "stool.ply"})
    edit_yaml(tiny_session, lambda c: setitem(c["object"], "static", True))
    session = Session.load(tiny_session)
    assert [(s.name, s.grip, len(s.mesh.faces)) for s in session.supports] == [("stool", False, 12)]
    assert session.object.static
    assert "supports: stool (stool.ply)" in session.summary() and "static (a support)" in session.summary()
    add_support(tiny_session, {"mesh": "stool.ply", "grip": True})
    assert [(s.name, s.grip) for s in Session.load(tiny_session).supports] == [("stool", True)]


def test_load_lists_every_fatal_problem_at_once(tiny_session: Path):
    edit_yaml(tiny_session, lambda c: (c.pop("fps"), setitem(c, "body", {"model": "smpl"})))
    edit_calib(tiny_session, cam1(lambda c: c.pop("K")))
    (tiny_session / "object.ply").unlink()
    with pytest.raises(SessionError) as err:
        Session.load(tiny_session)
    fatal = {(p.path, p.message.split(" ")[0]) for p in err.value.problems if p.fatal}
    assert {path for path, _ in fatal} == {"session.yaml", "calibration.json", "object.ply"}
    assert len([p for p in err.value.problems if p.fatal]) == 4


def test_dropped_frame_in_one_view_is_a_warning_and_reads_as_none(tiny_session: Path):
    (tiny_session / "cam1/depth/000001.png").unlink()
    s = Session.load(tiny_session)
    assert [str(p) for p in s.problems] == ["cam1/depth: 1 dropped frame(s) (file missing): 1"]
    assert s.read_depth("cam1", 1) is None and s.read_depth("cam0", 1) is not None
    assert s.availability()["depth"].tolist() == [[True, True, True], [True, False, True]]
    batch = s.read_depth_batch([0, 1, 2])
    assert np.all(batch[1, 1] == 0) and np.any(batch[1, 0] > 0)
    assert "1 dropped" in s.summary()


def test_corrupt_jpeg_is_unreadable_and_dropped(tiny_session: Path):
    corrupt_jpeg(tiny_session)
    s = Session.load(tiny_session)  # load does not decode every file ...
    assert s.read_color("cam0", 1) is None  # ... but reading finds it and records it
    assert any(p.path == "cam0/color/000001.jpg" and "unreadable" in p.message for p in s.problems)
    assert s.read_color("cam0", 0) is not None
    session, problems = validate(tiny_session)
    assert session is not None and not session.availability()["color"][0, 1]
    assert [p.path for p in problems] == ["cam0/color/000001.jpg"]


def test_non_uint16_depth_read_is_dropped(tiny_session: Path):
    cv2.imwrite(str(tiny_session / "cam0/depth/000002.png"), np.zeros((48, 64, 3), np.uint8))
    s = Session.load(tiny_session)
    assert s.read_depth(0, 2) is None
    assert any("uint16" in p.message and p.path == "cam0/depth/000002.png" for p in s.problems)


def test_openpose_parsing_first_person_and_bad_parts():
    data = {
        "people": [
            {"pose_keypoints_2d": list(range(75)), "face_keypoints_2d": [1.0] * 12},
            {"pose_keypoints_2d": [9.0] * 75},
        ]
    }
    kp, issues = openpose_to_array(data)
    np.testing.assert_array_equal(kp[:25].reshape(-1), np.arange(75))
    assert np.all(kp[25:] == 0)  # wrong-sized face is ignored, hands absent
    assert len(issues) == 1 and "face_keypoints_2d" in issues[0]
    kp, issues = openpose_to_array({"people": []})
    assert kp.shape == (137, 3) and not kp.any() and not issues
    with pytest.raises(ValueError):
        openpose_to_array([1, 2])


def test_missing_session_folder(tmp_path: Path):
    session, problems = validate(tmp_path / "nope")
    assert session is None and problems[0].fatal and "does not exist" in problems[0].message
    with pytest.raises(SessionError):
        Session.load(tmp_path / "nope")
