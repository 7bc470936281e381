"""`intercap calibrate` when cameras do not all see the board together: a camera that never
shares a board frame with the reference camera is chained through another one; a camera
that shares no board frame with any other is a one-line error naming it, and nothing is
written. Synthetic board recordings (intercap.synth.boards) at small resolution."""
import json
import shutil

import numpy as np
import pytest

from intercap.calib.board import pose_errors
from intercap.cli import main
from intercap.synth.boards import BoardSpec, board_rig, render_board_session

SPEC = BoardSpec("charuco", (7, 5), 0.1, 0.075, "DICT_5X5_100")
BOARD_ARGS = ["--squares", "7x5", "--square-m", "0.1", "--marker-m", "0.075"]
SIZE = (640, 480)


def facing(session) -> np.ndarray:
    """(F, C) bool: camera c sees the printed side of the board in frame f (its centre lies on
    the board's -z side), from the ground truth."""
    cams = json.loads((session / "calibration.json").read_text())["cameras"]
    gt = {c["name"]: c for c in json.loads((session / "ground_truth" / "calibration.json").read_text())["cameras"]}
    centres = np.array([np.array(gt[c["name"]]["T_world_from_cam"])[:3, 3] for c in cams])  # (C, 3)
    boards = np.load(session / "ground_truth" / "board_poses.npz")["T_world_from_board"]  # (F, 4, 4)
    to_cam = centres[None] - boards[:, None, :3, 3]  # (F, C, 3)
    return np.einsum("fci,fi->fc", to_cam, -boards[:, :3, 2]) > 0


def drop_camera(session, name):
    """Remove a camera from a recording (its folder and its calibration.json entries)."""
    for path in (session / "calibration.json", session / "ground_truth" / "calibration.json"):
        data = json.loads(path.read_text())
        data["cameras"] = [c for c in data["cameras"] if c["name"] != name]
        path.write_text(json.dumps(data))
    shutil.rmtree(session / name)


@pytest.fixture(scope="module")
def three_of_a_ring(tmp_path_factory):
    """A ring of 4 cameras (the board faces each neighbouring pair in turn) with cam3 removed:
    cam2, opposite cam0, sees the board only together with cam1 (or alone)."""
    session = render_board_session(board_rig(4, *SIZE), SPEC, tmp_path_factory.mktemp("chain") / "rec", poses=12,
                                   supersample=1)
    drop_camera(session, "cam3")
    return session


def true_poses(session):
    return np.array([c["T_world_from_cam"] for c in
                     json.loads((session / "ground_truth" / "calibration.json").read_text())["cameras"]])


def test_camera_never_seen_with_the_reference_is_chained_through_another(three_of_a_ring, tmp_path):
    seen = facing(three_of_a_ring)
    assert not (seen[:, 0] & seen[:, 2]).any()  # the premise: cam2 and cam0 never see the board together
    assert (seen[:, 1] & seen[:, 2]).any() and (seen[:, 0] & seen[:, 1]).any()
    out = tmp_path / "calibration.json"
    assert main(["calibrate", str(three_of_a_ring), *BOARD_ARGS, "--no-depth-refine", "--out", str(out)]) == 0
    written = json.loads(out.read_text())
    T = np.array([c["T_world_from_cam"] for c in written["cameras"]])
    assert [c["name"] for c in written["cameras"]] == ["cam0", "cam1", "cam2"]
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-9)
    trans_mm, rot_deg = pose_errors(T, true_poses(three_of_a_ring))
    assert trans_mm.max() < 5.0, trans_mm
    assert rot_deg.max() < 0.3, rot_deg
    assert written["board_calibration"]["cameras"]["cam2"]["reprojection_px"] < 0.5


def test_camera_sharing_no_frame_with_any_other_is_named(three_of_a_ring, tmp_path, capsys):
    session = tmp_path / "rec"
    shutil.copytree(three_of_a_ring, session)
    seen = facing(session)
    for f in np.flatnonzero(seen[:, 1] & seen[:, 2]):  # cam2 keeps only the frames it sees alone
        (session / "cam2" / "color" / f"{f:06d}.png").unlink()
    assert (seen[:, 2] & ~seen[:, 1]).any()  # so cam2 still sees the board, never with another camera
    before = (session / "calibration.json").read_bytes()
    out = tmp_path / "out" / "calibration.json"
    capsys.readouterr()
    assert main(["calibrate", str(session), *BOARD_ARGS, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("intercap calibrate")]  # (log lines aside)
    assert len(errors) == 1 and "camera cam2 shares no board frame with cam0, cam1" in errors[0], err
    assert not out.exists() and not out.parent.exists()
    assert (session / "calibration.json").read_bytes() == before  # the default output untouched too
