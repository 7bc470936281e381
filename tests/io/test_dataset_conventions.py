"""The BEHAVE and InterCap importers against each dataset's own documented conventions.

Each fixture is one frame written in the dataset's layout with a random calibration
(rotations far from identity, all 8 distortion coefficients non-zero and distinct, so a
swapped order or an inverted pose shows). The expected pixels and world points are
computed here straight from the dataset code's convention, without our camera code:

* BEHAVE (github xiexh20/behave-dataset, data/kinect_transform.py `local2world` and
  data/kinect_calib.py): config.json `rotation` (row-major) and `translation` map the
  colour camera's points to the world (world = p @ R.T + t); the distortion handed to
  cv2.projectPoints is `color.opencv[4:]` with K from fx, fy, cx, cy.
* InterCap (github YinghaoHuang91/InterCap, prox_first/prox/camera.py and
  obj_track/utils.py `create_renderers`): Color*.json `R` (Rodrigues) and `T` map world
  points into the camera (x_cam = Rodrigues(R) @ x + T); `k` is OpenCV's order.
"""
import json

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from intercap.geometry.cameras import Cameras, backproject, project
from intercap.io.behave import import_behave
from intercap.io.intercap_dataset import import_intercap
from intercap.session import Session, validate

W, H = 64, 48
DIST = [0.11, -0.052, 0.0021, -0.0034, 0.013, 0.047, -0.021, 0.0052]  # k1 k2 p1 p2 k3 k4 k5 k6 (OpenCV)
PIXELS = np.array([[10.0, 7.0], [31.0, 23.0], [55.0, 40.0], [3.0, 44.0]])  # (P, 2) where depth is written
DEPTH_MM = np.array([812, 1500, 2345, 3999], np.uint16)  # (P,)


def random_camera(rng, k):
    K = np.array([[60.0 + 3 * k, 0.0, 31.2 + k], [0.0, 61.5 + 2 * k, 23.7 - k], [0.0, 0.0, 1.0]])
    R = Rotation.from_rotvec(rng.normal(0, 1.2, 3)).as_matrix()
    t = rng.uniform(-2, 2, 3)
    return K, R, t


def write_frame_images(folder, prefix_color, prefix_depth):
    """A grey colour image and a depth map with DEPTH_MM at PIXELS (0 elsewhere)."""
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(prefix_color), np.full((H, W, 3), 128, np.uint8))
    depth = np.zeros((H, W), np.uint16)
    depth[PIXELS[:, 1].astype(int), PIXELS[:, 0].astype(int)] = DEPTH_MM
    cv2.imwrite(str(prefix_depth), depth)


def camera_points(K, dist):
    """(P, 3) camera-frame points of PIXELS at DEPTH_MM, through OpenCV's own undistortion."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    xy = cv2.undistortPoints(PIXELS[:, None], K, np.array(dist), None, None, None, crit)[:, 0]
    z = DEPTH_MM / 1000.0
    return np.column_stack([xy * z[:, None], z])


def in_view(rng, n=20):
    """(n, 3) camera-frame points in front of a camera, within its small field of view."""
    return rng.uniform([-0.4, -0.3, 1.0], [0.4, 0.3, 3.0], (n, 3))


def ours(session, c):
    """(our Cameras, (P, 3) world points of the session's depth pixels), with our camera code."""
    cams = Cameras.from_infos([session.cameras[c]], dtype=torch.float64)
    depth = session.read_depth(c, int(session.frame_ids[0]))
    z = depth[PIXELS[:, 1].astype(int), PIXELS[:, 0].astype(int)].astype(np.float64)  # (P,) metres
    world = backproject(torch.from_numpy(PIXELS)[None], torch.from_numpy(z)[None], cams)[0].numpy()
    return cams, world


def test_behave_world_points_follow_their_local2world(tmp_path):
    rng = np.random.default_rng(12)
    seq = tmp_path / "sequences" / "Date03_Sub04"  # no object in the name: a camera-only fixture
    calib = tmp_path / "calibs"
    truth = []
    for k in range(2):
        K, R, t = random_camera(rng, k)
        truth.append((K, R, t))
        write_frame_images(seq / "t0010.000", seq / "t0010.000" / f"k{k}.color.jpg", seq / "t0010.000" / f"k{k}.depth.png")
        (calib / "Date03" / "config" / str(k)).mkdir(parents=True)
        (calib / "Date03" / "config" / str(k) / "config.json").write_text(
            json.dumps({"rotation": R.reshape(-1).tolist(), "translation": t.tolist()}))
        color = {"width": W, "height": H, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
                 "opencv": [K[0, 2], K[1, 2], K[0, 0], K[1, 1], *DIST]}
        (calib / "Date03" / "intrinsics" / str(k)).mkdir(parents=True)
        (calib / "Date03" / "intrinsics" / str(k) / "calibration.json").write_text(json.dumps({"color": color}))
    (seq / "info.json").write_text(json.dumps({"kinects": [0, 1]}))
    out = tmp_path / "session"
    import_behave(seq, out, calib_dir=calib)
    session, problems = validate(out)
    assert session is not None and not [p for p in problems if p.fatal], problems
    session = Session.load(out)
    for k, (K, R, t) in enumerate(truth):
        world_pts = in_view(rng) @ R.T + t  # (N, 3) points in front of camera k
        # their convention: colour-camera points -> world by local2world, pixels by projectPoints(opencv[4:])
        expected_world = camera_points(K, DIST) @ R.T + t
        local = (world_pts - t) @ R  # world2local: R^T (x - t)
        in_front = local[:, 2] > 0.1
        expected_px = cv2.projectPoints(local[in_front], np.zeros(3), np.zeros(3), K, np.array(DIST))[0][:, 0]
        cams, world = ours(session, k)
        np.testing.assert_allclose(world, expected_world, atol=1e-6)
        px, _ = project(torch.from_numpy(world_pts[in_front]), cams)
        np.testing.assert_allclose(px[0].numpy(), expected_px, atol=1e-6)


def test_intercap_world_points_follow_their_camera_model(tmp_path):
    rng = np.random.default_rng(34)
    seq = tmp_path / "RGBD_Images" / "02" / "09" / "Seg_1"  # subject 2, motion 9: calibration_second
    data = tmp_path / "Data" / "calibration_second"
    data.mkdir(parents=True)
    truth = []
    for k in range(1, 7):
        K, R_cw, T_cw = random_camera(rng, k)  # world -> camera, as their files store it
        truth.append((K, R_cw, T_cw))
        (seq / f"Frames_Cam{k}" / "color").mkdir(parents=True)
        (seq / f"Frames_Cam{k}" / "depth").mkdir(parents=True)
        write_frame_images(seq, seq / f"Frames_Cam{k}" / "color" / "00042.jpg",
                           seq / f"Frames_Cam{k}" / "depth" / "00042.png")
        (data / ("Color.json" if k == 1 else f"Color_{k}.json")).write_text(json.dumps(
            {"f": [K[0, 0], K[1, 1]], "c": [K[0, 2], K[1, 2]], "k": DIST,
             "R": cv2.Rodrigues(R_cw)[0].ravel().tolist(), "T": T_cw.tolist()}))
    out = tmp_path / "session"
    summary = import_intercap(seq, out, tmp_path / "Data")
    assert summary["calibration"] == "calibration_second"
    session, problems = validate(out)
    assert session is not None and not [p for p in problems if p.fatal], problems
    session = Session.load(out)
    assert session.frame_ids.tolist() == [42]
    for c, (K, R_cw, T_cw) in enumerate(truth):
        world_pts = (in_view(rng) - T_cw) @ R_cw  # (N, 3) points in front of camera c
        # their convention: x_cam = R x + T, so x = R^T (x_cam - T); pixels by projectPoints(R, T, k)
        expected_world = (camera_points(K, DIST) - T_cw) @ R_cw
        in_front = (world_pts @ R_cw.T + T_cw)[:, 2] > 0.1
        expected_px = cv2.projectPoints(world_pts[in_front], cv2.Rodrigues(R_cw)[0], T_cw, K, np.array(DIST))[0][:, 0]
        cams, world = ours(session, c)
        np.testing.assert_allclose(world, expected_world, atol=1e-6)
        px, _ = project(torch.from_numpy(world_pts[in_front]), cams)
        np.testing.assert_allclose(px[0].numpy(), expected_px, atol=1e-6)


@pytest.mark.parametrize("swap", ["inverse", "dist_order"])
def test_the_convention_checks_would_catch_a_wrong_importer(swap):
    """The comparison above fails for an inverted pose or a reordered distortion (so it can fail)."""
    rng = np.random.default_rng(12)
    K, R, t = random_camera(rng, 0)
    world_pts = rng.uniform(-1, 1, (20, 3))
    local = (world_pts - t) @ R
    keep = local[:, 2] > 0.1
    right = cv2.projectPoints(local[keep], np.zeros(3), np.zeros(3), K, np.array(DIST))[0][:, 0]
    if swap == "inverse":
        wrong_local = world_pts @ R.T + t
        keep2 = keep & (wrong_local[:, 2] > 0.1)
        wrong = cv2.projectPoints(wrong_local[keep2], np.zeros(3), np.zeros(3), K, np.array(DIST))[0][:, 0]
        right = right[keep2[keep]]
    else:
        d = list(DIST)
        d[2], d[3], d[4] = d[4], d[2], d[3]  # k3 where p1 is (an order like Azure Kinect's)
        wrong = cv2.projectPoints(local[keep], np.zeros(3), np.zeros(3), K, np.array(d))[0][:, 0]
    assert np.abs(wrong - right).max() > 0.01
