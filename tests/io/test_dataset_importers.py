"""BEHAVE and InterCap importers on small fixture folders written here in each dataset's layout
from the sample session's first frames, its calibration re-expressed in their conventions."""
import json
import pickle
import shutil

import cv2
import numpy as np
import pytest
import trimesh
from conftest import SAMPLE_SESSION
from scipy.spatial.transform import Rotation

from intercap.cli import main
from intercap.io.behave import import_behave
from intercap.io.importing import DatasetImportError
from intercap.io.intercap_dataset import calibration_set, import_intercap
from intercap.session import Session, validate
from intercap.stages.export.stage import behave_frame_names

FRAMES = 3
SAMPLE = json.loads((SAMPLE_SESSION / "calibration.json").read_text())["cameras"]
GT_POSES = np.load(SAMPLE_SESSION / "ground_truth" / "object_poses.npz")


def sample_T(c):
    return np.array(SAMPLE[c]["T_world_from_cam"], np.float64)


def to_cam1(c):
    """The sample's camera c pose in a world that is camera 1's frame (BEHAVE's and InterCap's world)."""
    return np.linalg.inv(sample_T(1)) @ sample_T(c)


def sample_file(c, kind, f):
    ext = {"color": ".jpg", "depth": ".png", "masks/person": ".png", "masks/object": ".png"}[kind]
    return SAMPLE_SESSION / f"cam{c}" / kind / f"{f:06d}{ext}"


def object_in_cam1(f):
    """(R, t) of the sample's object at frame f in camera 1's frame, for the template centred on its vertex mean."""
    verts = trimesh.load(SAMPLE_SESSION / "object.ply", process=False).vertices
    center = verts.mean(0)
    A = np.linalg.inv(sample_T(1))
    R = A[:3, :3] @ GT_POSES["R"][f]
    t = A[:3, :3] @ (GT_POSES["R"][f] @ center + GT_POSES["t"][f]) + A[:3, 3]
    return R, t


def posed_sample_object_in_cam1(f):
    verts = trimesh.load(SAMPLE_SESSION / "object.ply", process=False).vertices
    world = verts @ GT_POSES["R"][f].T + GT_POSES["t"][f]
    A = np.linalg.inv(sample_T(1))
    return world @ A[:3, :3].T + A[:3, 3]


# -- BEHAVE ------------------------------------------------------------------------------------
def write_behave(root):
    """sequences/Date01_Sub01_box/, calibs/Date01/{config,intrinsics}/<k>/, objects/box/."""
    seq = root / "sequences" / "Date01_Sub01_box"
    for f in range(FRAMES):
        folder = seq / f"t{f * 0.2:08.3f}"
        folder.mkdir(parents=True)
        for c in range(4):
            shutil.copy(sample_file(c, "color", f), folder / f"k{c}.color.jpg")
            shutil.copy(sample_file(c, "depth", f), folder / f"k{c}.depth.png")
            person = cv2.imread(str(sample_file(c, "masks/person", f)), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(folder / f"k{c}.person_mask.jpg"), person, [cv2.IMWRITE_JPEG_QUALITY, 95])
            shutil.copy(sample_file(c, "masks/object", f), folder / f"k{c}.obj_rend_mask.png")
        R, t = object_in_cam1(f)
        (folder / "box" / "fit01").mkdir(parents=True)
        with open(folder / "box" / "fit01" / "box_fit.pkl", "wb") as fh:
            pickle.dump({"angle": Rotation.from_matrix(R).as_rotvec(), "trans": t}, fh)
    (seq / "info.json").write_text(json.dumps({"cat": "box", "gender": "male", "kinects": [0, 1, 2, 3],
                                               "config": "../../calibs/Date01/config",
                                               "intrinsic": "../../calibs/Date01/intrinsics", "empty": None, "beta": None}))
    for c, cam in enumerate(SAMPLE):
        T = to_cam1(c)
        (root / "calibs" / "Date01" / "config" / str(c)).mkdir(parents=True)
        (root / "calibs" / "Date01" / "config" / str(c) / "config.json").write_text(
            json.dumps({"rotation": T[:3, :3].reshape(-1).tolist(), "translation": T[:3, 3].tolist()}))
        K = np.array(cam["K"])
        dist = list(cam["dist"]) + [0.0] * (8 - len(cam["dist"]))
        color = {"width": cam["width"], "height": cam["height"], "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2],
                 "cy": K[1, 2], "opencv": [K[0, 2], K[1, 2], K[0, 0], K[1, 1], *dist]}
        (root / "calibs" / "Date01" / "intrinsics" / str(c)).mkdir(parents=True)
        (root / "calibs" / "Date01" / "intrinsics" / str(c) / "calibration.json").write_text(
            json.dumps({"color": color, "depth": color}))
    (root / "objects" / "box").mkdir(parents=True)
    shutil.copy(SAMPLE_SESSION / "object.ply", root / "objects" / "box" / "box_f1000.ply")
    return seq


@pytest.fixture(scope="module")
def behave(tmp_path_factory):
    root = tmp_path_factory.mktemp("behave")
    seq = write_behave(root)
    out = root / "session"
    summary = import_behave(seq, out, calib_dir=root / "calibs", objects_dir=root / "objects")
    return root, seq, out, summary


def test_behave_import_round_trips_calibration(behave):
    root, seq, out, summary = behave
    session, problems = validate(out)
    assert session is not None and not [p for p in problems if p.fatal], problems
    assert summary["frames"] == FRAMES and summary["object_fits"] == FRAMES
    assert session.camera_names == ["k0", "k1", "k2", "k3"] and session.num_frames == FRAMES
    assert session.fps == pytest.approx(5.0)
    for c, cam in enumerate(session.cameras):
        conf = json.loads((root / "calibs" / "Date01" / "config" / str(c) / "config.json").read_text())
        assert np.array_equal(cam.T_world_from_cam[:3, :3], np.reshape(conf["rotation"], (3, 3)))  # exactly
        assert np.array_equal(cam.T_world_from_cam[:3, 3], conf["translation"])
        assert np.abs(cam.T_world_from_cam - to_cam1(c)).max() < 1e-12
        assert np.array_equal(cam.K, SAMPLE[c]["K"])
        assert np.array_equal(cam.dist[:5], SAMPLE[c]["dist"]) and not cam.dist[5:].any()
        assert (cam.width, cam.height) == (SAMPLE[c]["width"], SAMPLE[c]["height"])
    assert np.abs(session.camera("k1").T_world_from_cam - np.eye(4)).max() < 1e-12  # k1 is the world


def test_behave_import_copies_frames_and_object_fits(behave):
    root, seq, out, _ = behave
    session = Session.load(out)
    for f in range(FRAMES):
        for c in range(4):
            assert (out / f"k{c}" / "color" / f"{f:06d}.jpg").read_bytes() == sample_file(c, "color", f).read_bytes()
            assert np.array_equal(session.read_depth(c, f), Session.load(SAMPLE_SESSION).read_depth(c, f))
            person = session.read_mask(c, f, "person")
            truth = cv2.imread(str(sample_file(c, "masks/person", f)), cv2.IMREAD_GRAYSCALE) > 127
            assert (person != truth).mean() < 0.01  # through BEHAVE's JPEG masks
            assert np.array_equal(session.read_mask(c, f, "object"),
                                  cv2.imread(str(sample_file(c, "masks/object", f)), cv2.IMREAD_GRAYSCALE) > 127)
    gt = session.ground_truth()
    mesh = session.object.load_mesh()
    for f in range(FRAMES):
        posed = mesh.vertices @ gt.object_R[f].T + gt.object_t[f]
        assert np.abs(posed - posed_sample_object_in_cam1(f)).max() < 1e-6
    frames = json.loads((out / "behave_frames.json").read_text())["frames"]
    assert [x["folder"] for x in frames] == ["t0000.000", "t0000.200", "t0000.400"]


def test_behave_missing_frame_folder_keeps_later_frames_in_time(tmp_path):
    """A frame folder missing from the sequence is a session frame without files (the
    velocity and acceleration terms assume one period per frame), not a shift."""
    seq = write_behave(tmp_path)
    for f in range(FRAMES, FRAMES + 2):  # two more frames on the 5 fps timeline, then drop the middle one
        shutil.copytree(seq / f"t{(f - FRAMES) * 0.2:08.3f}", seq / f"t{f * 0.2:08.3f}")
    shutil.rmtree(seq / "t0000.200")
    out = tmp_path / "session"
    summary = import_behave(seq, out, calib_dir=tmp_path / "calibs", objects_dir=tmp_path / "objects")
    assert summary["frames"] == FRAMES + 2 and summary["gaps"] == [1] and summary["fps"] == pytest.approx(5.0)
    session, problems = validate(out)
    assert session is not None and not [p for p in problems if p.fatal], problems
    assert session.num_frames == FRAMES + 2 and not session.availability()["color"][:, 1].any()
    for f, src in ((0, 0), (2, 2), (3, 0), (4, 1)):
        assert (out / "k0" / "color" / f"{f:06d}.jpg").read_bytes() == sample_file(0, "color", src).read_bytes()
    frames = json.loads((out / "behave_frames.json").read_text())["frames"]
    assert [(x["frame"], x["folder"]) for x in frames] == [
        (0, "t0000.000"), (2, "t0000.400"), (3, "t0000.600"), (4, "t0000.800")]
    fits = np.load(out / "behave_object_fits.npz")
    assert fits["valid"].tolist() == [True, False, True, True, True]
    # the BEHAVE export names each frame as the source did (the gap by its time), also from a later start
    assert behave_frame_names(session) == ["t0000.000", "t0000.200", "t0000.400", "t0000.600", "t0000.800"]
    import_behave(seq, tmp_path / "later", calib_dir=tmp_path / "calibs", objects_dir=tmp_path / "objects", start=2)
    assert behave_frame_names(Session.load(tmp_path / "later")) == ["t0000.600", "t0000.800"]


def test_behave_missing_camera_is_one_line_error_and_leaves_nothing(tmp_path):
    seq = write_behave(tmp_path)
    (seq / "t0000.200" / "k2.color.jpg").unlink()
    out = tmp_path / "session"
    with pytest.raises(DatasetImportError) as err:
        import_behave(seq, out, calib_dir=tmp_path / "calibs", objects_dir=tmp_path / "objects")
    message = str(err.value)
    assert "\n" not in message and str(seq / "t0000.200" / "k2.color.jpg") in message
    assert not out.exists() and not list(tmp_path.glob(".session.importing-*"))
    (seq / "t0000.200" / "k2.color.jpg").write_bytes(b"")
    shutil.rmtree(tmp_path / "calibs" / "Date01" / "intrinsics" / "3")
    code = main(["import", "behave", str(seq), str(out), "--calib", str(tmp_path / "calibs"),
                 "--objects", str(tmp_path / "objects")])
    assert code == 2 and not out.exists()


# -- InterCap ----------------------------------------------------------------------------------
SOURCES = [0, 1, 2, 3, 0, 1]  # InterCap camera k (1..6) shows the sample's camera SOURCES[k - 1]


def write_intercap(root, subject="05", motion="03"):
    """RGBD_Images/<subject>/<motion>/Seg_0/Frames_Cam<k>/, Data/calibration_*/, objs/<motion>.ply, res_tuned.pkl."""
    seq = root / "RGBD_Images" / subject / motion / "Seg_0"
    for k, c in enumerate(SOURCES, start=1):
        for kind, ext in (("color", ".jpg"), ("depth", ".png")):
            (seq / f"Frames_Cam{k}" / kind).mkdir(parents=True)
            for f in range(FRAMES):
                shutil.copy(sample_file(c, kind, f), seq / f"Frames_Cam{k}" / kind / f"{f:05d}{ext}")
    for which, shift in (("first", 1.0), ("second", 2.0), ("third", 0.0)):  # only "third" is right for 05/03
        folder = root / "Data" / f"calibration_{which}"
        folder.mkdir(parents=True)
        for k, c in enumerate(SOURCES, start=1):
            T_cw = np.linalg.inv(to_cam1(c))
            K = np.array(SAMPLE[c]["K"])
            data = {"f": [K[0, 0], K[1, 1]], "c": [K[0, 2], K[1, 2]], "k": list(SAMPLE[c]["dist"]) + [0.0] * 3,
                    "R": cv2.Rodrigues(T_cw[:3, :3])[0].reshape(-1).tolist(), "T": (T_cw[:3, 3] + shift).tolist()}
            (folder / ("Color.json" if k == 1 else f"Color_{k}.json")).write_text(json.dumps(data))
    (root / "objs").mkdir()
    shutil.copy(SAMPLE_SESSION / "object.ply", root / "objs" / f"{motion}.ply")
    fits = []
    for f in range(FRAMES):
        R, t = object_in_cam1(f)
        fits.append({"ob_pose": Rotation.from_matrix(R).as_rotvec(), "ob_trans": t, "betas": np.zeros(10)})
    with open(root / "res_tuned.pkl", "wb") as fh:
        pickle.dump(fits, fh)
    return seq


def test_intercap_calibration_set_follows_their_mapping():
    assert calibration_set(1, 1) == "first" and calibration_set(4, 4) == "first"
    assert calibration_set(2, 9) == "second" and calibration_set(9, 1) == "second" and calibration_set(7, 10) == "second"
    assert calibration_set(3, 8) == "third" and calibration_set(5, 3) == "third" and calibration_set(6, 7) == "third"
    assert calibration_set(3, 7) == "first" and calibration_set(4, 6) == "first"


def test_intercap_import_round_trips_calibration(tmp_path):
    seq = write_intercap(tmp_path)
    (seq / "Frames_Cam3" / "color" / "00001.jpg").unlink()  # a dropped frame of one view
    out = tmp_path / "session"
    code = main(["import", "intercap", str(seq), str(out), "--calib", str(tmp_path / "Data"),
                 "--objects", str(tmp_path / "objs"), "--fits", str(tmp_path / "res_tuned.pkl")])
    assert code == 0
    session, problems = validate(out)
    assert session is not None and not [p for p in problems if p.fatal], problems
    assert session.camera_names == [f"cam{k}" for k in range(1, 7)] and session.num_frames == FRAMES
    for k, c in enumerate(SOURCES, start=1):
        cam = session.camera(f"cam{k}")
        data = json.loads((tmp_path / "Data" / "calibration_third" / ("Color.json" if k == 1 else f"Color_{k}.json")).read_text())
        R_cw = cv2.Rodrigues(np.array(data["R"]))[0]
        assert np.abs(cam.T_cam_from_world[:3, :3] - R_cw).max() < 1e-12
        assert np.abs(cam.T_cam_from_world[:3, 3] - data["T"]).max() < 1e-12
        # the sample's rotations carry 9 decimals (orthonormal to ~1e-9); Rodrigues keeps the nearest rotation
        assert np.abs(cam.T_world_from_cam - to_cam1(c)).max() < 1e-8
        assert np.array_equal(cam.K, SAMPLE[c]["K"]) and np.array_equal(cam.dist, data["k"])
    assert session.availability()["color"][2].tolist() == [True, False, True]
    report = json.loads((out / "intercap_import.json").read_text())
    assert report["calibration"] == "calibration_third" and report["dropped"]["cam3"] == [1]
    gt = session.ground_truth()
    mesh = session.object.load_mesh()
    for f in range(FRAMES):
        posed = mesh.vertices @ gt.object_R[f].T + gt.object_t[f]
        assert np.abs(posed - posed_sample_object_in_cam1(f)).max() < 1e-6
    assert np.array_equal(session.read_depth("cam4", 2), Session.load(SAMPLE_SESSION).read_depth(3, 2))


def test_intercap_missing_calibration_names_the_file(tmp_path):
    seq = write_intercap(tmp_path, subject="09", motion="02")  # second set
    (tmp_path / "Data" / "calibration_second" / "Color_4.json").unlink()
    with pytest.raises(DatasetImportError, match="calibration_second/Color_4.json: missing"):
        import_intercap(seq, tmp_path / "session", tmp_path / "Data")
    assert not (tmp_path / "session").exists()
