"""`intercap calibrate`: rig extrinsics from synthetic board recordings with known truth."""
import json

import cv2
import numpy as np
import pytest

from intercap.calib.board import Board, CalibrationError, calibrate_rig, pose_errors
from intercap.cli import main
from intercap.synth.boards import (
    BoardSpec,
    board_poses,
    board_rig,
    board_texture,
    camera_rays,
    floor_view,
    render_board_session,
    render_board_view,
)

SPEC = BoardSpec("charuco", (7, 5), 0.1, 0.075, "DICT_5X5_100")  # a 70 x 50 cm print


def true_poses(session):
    cams = json.loads((session / "ground_truth" / "calibration.json").read_text())["cameras"]
    return np.array([c["T_world_from_cam"] for c in cams])


@pytest.fixture(scope="module")
def ring_session(tmp_path_factory):
    """4 cameras on a ring (640x480, real distortion), a ChArUco board in 10 poses."""
    return render_board_session(board_rig(4), SPEC, tmp_path_factory.mktemp("boards") / "rec", poses=10)


def test_calibrate_recovers_ring_extrinsics(ring_session, tmp_path, capsys):
    out = tmp_path / "calibration.json"
    assert main(["calibrate", str(ring_session), "--squares", "7x5", "--square-m", "0.1", "--marker-m", "0.075",
                 "--out", str(out)]) == 0
    written = json.loads(out.read_text())
    T = np.array([c["T_world_from_cam"] for c in written["cameras"]])
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-9)  # world = the first camera
    trans_mm, rot_deg = pose_errors(T, true_poses(ring_session))
    assert trans_mm.max() < 5.0, trans_mm
    assert rot_deg.max() < 0.3, rot_deg
    # intrinsics are passed through untouched; figures per camera are reported
    given = json.loads((ring_session / "calibration.json").read_text())["cameras"]
    assert [c["K"] for c in written["cameras"]] == [c["K"] for c in given]
    figures = written["board_calibration"]["cameras"]
    assert all(f["reprojection_px"] < 0.5 for f in figures.values())
    assert all(f["depth_agreement_mm"] < 3.0 for f in figures.values())
    table = capsys.readouterr().out
    assert "reproj px" in table and "cam3" in table


def test_world_on_the_board(ring_session):
    """--world board: the world is the board's first shared pose, so cameras are seen from it."""
    result, _, _ = calibrate_rig(ring_session, Board("charuco", (7, 5), 0.1, 0.075), world="board",
                                 depth_refine=False)
    T_board = np.load(ring_session / "ground_truth" / "board_poses.npz")["T_world_from_board"]
    expected = np.linalg.inv(T_board[result.shared_frame_ids[0]]) @ true_poses(ring_session)
    assert np.abs(result.T_world_from_cam[:, :3, 3] - expected[:, :3, 3]).max() < 0.01  # m
    trans_mm, rot_deg = pose_errors(result.T_world_from_cam, true_poses(ring_session))
    assert trans_mm.max() < 5.0 and rot_deg.max() < 0.3


def test_camera_that_never_sees_the_board_is_named(tmp_path):
    session = render_board_session(board_rig(3), SPEC, tmp_path / "rec", poses=3, supersample=1, hidden=("cam1",))
    with pytest.raises(CalibrationError, match="cam1 never sees the board"):
        calibrate_rig(session, Board("charuco", (7, 5), 0.1, 0.075))
    assert main(["calibrate", str(session), "--square-m", "0.1", "--marker-m", "0.075"]) == 2


def test_checkerboard_corner_order_survives_a_half_turn():
    """findChessboardCornersSB may list the corners from either end; the board's colours fix it."""
    spec = BoardSpec("checkerboard", (8, 5), 0.08)
    board = Board("checkerboard", (8, 5), 0.08)
    cam = board_rig(1)[0]
    rays = camera_rays(cam)
    floor = floor_view(cam, rays)
    texture = cv2.GaussianBlur(board_texture(spec, 80), (0, 0), 1.0)
    T_board = board_poses([cam], spec, 1)[0]
    for roll in (0.0, 180.0):
        flip = np.eye(4)  # turn the board in its own plane about its centre
        c, s = np.cos(np.radians(roll)), np.sin(np.radians(roll))
        centre = np.array([0.32, 0.2, 0.0])
        flip[:2, :2] = [[c, -s], [s, c]]
        flip[:3, 3] = centre - flip[:3, :3] @ centre
        T = T_board @ flip
        rgb, _ = render_board_view(cam, rays, floor, spec, texture, T, 80)
        ids, uv = board.detect(cv2.cvtColor(rgb.astype(np.uint8), cv2.COLOR_RGB2GRAY))
        assert len(ids) == 7 * 4
        P = (np.linalg.inv(cam.T_world_from_cam) @ T)[:3]
        P_cam = board.object_points[ids] @ P[:, :3].T + P[:, 3]
        expected, _ = cv2.projectPoints(P_cam, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        assert np.abs(expected.reshape(-1, 2) - uv).max() < 1.0, roll
