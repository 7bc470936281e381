"""Azure Kinect import: calibration parsing against the file, depth byte order,
registration against a synthetic scene, frame alignment, import + validate, bad input."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy import ndimage

from intercap.cli import main
from intercap.geometry.cameras import pixel_grid, remove_intrinsics, undistort
from intercap.io.k4a import K4AError, K4AMissingError, decode_depth, import_k4a, open_recording
from intercap.io.k4a_calibration import DepthRegistration, parse_device_calibration, undistorted_rays
from intercap.session import validate
from intercap.synth.k4a_mkv import device_calibration_json, write_k4a_mkv

DATA = Path(__file__).parents[2].parent / "shared" / "data" / "azure_kinect"
REC, CALIB = DATA / "recording.mkv", DATA / "calibration.json"
needs_data = pytest.mark.skipif(not REC.exists() or not CALIB.exists(), reason=f"real Azure Kinect data absent ({DATA})")

# realistic normalised Brown-Conrady parameters (cx, cy, fx, fy, k1..k6, codx, cody, p2, p1)
DEPTH_P = [0.513, 0.517, 0.4928, 0.4929, 0.548, -0.021, -0.0027, 0.890, 0.086, -0.014, 0, 0, -7e-5, 2e-5]
COLOR_P = [0.4998, 0.5066, 0.478, 0.637, 0.33, -2.49, 1.45, 0.209, -2.30, 1.375, 0, 0, -1.3e-4, -1.6e-4]


def _rot_x(deg):
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


R_CD = _rot_x(5.0)  # depth -> colour rotation (the depth camera of an Azure Kinect is tilted ~6 deg)
T_CD = np.array([-0.030, -0.002, 0.004])  # 3 cm baseline


@needs_data
def test_parsed_intrinsics_equal_the_file():
    raw = json.loads(CALIB.read_text())["CalibrationInformation"]["Cameras"]
    p_depth = next(c for c in raw if c["Purpose"].endswith("Depth"))["Intrinsics"]["ModelParameters"]
    p_color = next(c for c in raw if c["Purpose"].endswith("PhotoVideo"))
    calib = parse_device_calibration(CALIB.read_bytes(), "MJPG_720P", "NFOV_UNBINNED")
    c = p_color["Intrinsics"]["ModelParameters"]
    # colour 720P: calibration image 1280x960 cropped by 120 rows; pixel centres at integers
    assert calib.color.K[0, 0] == pytest.approx(c[2] * 1280)
    assert calib.color.K[1, 1] == pytest.approx(c[3] * 960)
    assert calib.color.K[0, 2] == pytest.approx(c[0] * 1280 - 0.5)
    assert calib.color.K[1, 2] == pytest.approx(c[1] * 960 - 120 - 0.5)
    assert (calib.color.width, calib.color.height) == (1280, 720)
    # OpenCV order k1, k2, p1, p2, k3, k4, k5, k6 from the file's k1..k6, codx, cody, p2, p1
    assert calib.color.dist.tolist() == pytest.approx([c[4], c[5], c[13], c[12], c[6], c[7], c[8], c[9]])
    d = p_depth
    assert calib.depth.K[0, 0] == pytest.approx(d[2] * 1024)
    assert calib.depth.K[0, 2] == pytest.approx(d[0] * 1024 - 192 - 0.5)
    assert calib.depth.K[1, 2] == pytest.approx(d[1] * 1024 - 180 - 0.5)
    assert calib.depth.dist.tolist() == pytest.approx([d[4], d[5], d[13], d[12], d[6], d[7], d[8], d[9]])
    Rt = p_color["Rt"]
    assert calib.T_color_from_depth[:3, :3] == pytest.approx(np.reshape(Rt["Rotation"], (3, 3)))
    assert calib.T_color_from_depth[:3, 3] == pytest.approx(Rt["Translation"])
    # the recording's own attachment is the same device calibration
    rec = open_recording(REC)
    assert rec.serial == "001514394512" and rec.calibration.color.K == pytest.approx(calib.color.K)


@needs_data
def test_depth_byte_order_gives_metric_depth():
    import av

    rec = open_recording(REC)
    with av.open(str(REC)) as c:
        data = next(bytes(p) for p in c.demux(c.streams[rec.depth_index]) if p.size)
    depth = decode_depth(rec, data)
    valid = depth[depth > 0]
    assert valid.size > 0.5 * depth.size
    assert 300 < np.median(valid) < 6000  # byte-swapped values would sit around 33000
    assert 300 < np.median(depth.byteswap()[depth > 0]) or np.median(depth.byteswap()[depth > 0]) > 6000


def test_old_yuy2_tagged_depth_is_little_endian(tmp_path):
    depth = np.full((576, 640), 1234, np.uint16)
    depth[:10] = 4321
    jpg = cv2.imencode(".jpg", np.zeros((720, 1280, 3), np.uint8))[1].tobytes()
    calib = device_calibration_json(DEPTH_P, COLOR_P, R_CD, T_CD)
    path = write_k4a_mkv(tmp_path / "old.mkv", [jpg], [depth], [0], calib, depth_tag="YUY2")
    rec = open_recording(path)
    import av

    with av.open(str(path)) as c:
        data = next(bytes(p) for p in c.demux(c.streams[rec.depth_index]) if p.size)
    assert not rec.depth_big_endian
    assert np.array_equal(decode_depth(rec, data), depth)


# ---------------------------------------------------------------- registration on a synthetic scene

# planes n . p = c in depth-camera coordinates, with rectangular bounds on (x, y) (None = unbounded)
SCENE = [
    (np.array([0.08, 0.0, 1.0]), 2.5, None),  # back wall, slightly slanted
    (np.array([0.0, 0.0, 1.0]), 1.2, (-0.35, 0.05, -0.2, 0.25)),  # box front face
    (np.array([0.0, -0.5, 1.0]), 1.7, (0.15, 0.6, -0.4, 0.1)),  # tilted panel
]


def _trace(origins, dirs):
    """Nearest hit distance parameter s (points = o + s d) of rays with the scene; inf = none."""
    best = np.full(dirs.shape[0], np.inf)
    for n, c, box in SCENE:
        denom = dirs @ n
        s = (c - origins @ n) / np.where(np.abs(denom) > 1e-9, denom, np.nan)
        p = origins + s[:, None] * dirs
        ok = np.isfinite(s) & (s > 0)
        if box is not None:
            ok &= (p[:, 0] > box[0]) & (p[:, 0] < box[1]) & (p[:, 1] > box[2]) & (p[:, 1] < box[3])
        best = np.where(ok & (s < best), s, best)
    return best


def _rays(lens):
    """(N, 3) undistorted rays (x, y, 1) of every pixel, row-major."""
    xy = undistorted_rays(lens)
    return np.concatenate([xy, np.ones((xy.shape[0], 1))], 1)


def test_numpy_undistortion_matches_the_camera_model():
    """The importer's numpy rays equal geometry.cameras' (torch, OpenCV-exact) inversion."""
    calib = parse_device_calibration(device_calibration_json(DEPTH_P, COLOR_P, R_CD, T_CD), "720P", "NFOV_UNBINNED")
    for lens in (calib.depth, calib.color):
        pix = pixel_grid(lens.height, lens.width, stride=7, dtype=torch.float64)[None]
        ref = undistort(remove_intrinsics(pix, torch.as_tensor(lens.K[None])), torch.as_tensor(lens.dist[None]))
        ours = undistorted_rays(lens, pix[0].numpy())
        ok = np.isfinite(ours).all(1)
        assert ok.mean() > 0.99
        assert np.abs(ours[ok] - ref[0].numpy()[ok]).max() < 1e-9


def test_registration_matches_the_colour_cameras_own_depth():
    calib = parse_device_calibration(device_calibration_json(DEPTH_P, COLOR_P, R_CD, T_CD), "720P", "NFOV_UNBINNED")
    dl, cl = calib.depth, calib.color
    # depth camera's view: z of the hit along each pixel's ray (d has z = 1, so s is z)
    d_rays = _rays(dl)
    z_depth = _trace(np.zeros_like(d_rays), d_rays).reshape(dl.height, dl.width)
    depth_mm = np.where(np.isfinite(z_depth), np.rint(z_depth * 1000), 0).astype(np.uint16)
    # colour camera's own depth: rays moved into the depth frame, hit, z in the colour frame
    c_rays = _rays(cl)
    origin = -R_CD.T @ T_CD
    s = _trace(np.broadcast_to(origin, c_rays.shape), c_rays @ R_CD)  # R^T d for each ray
    truth = (s * 1000).reshape(cl.height, cl.width)  # colour-frame z = s (ray z = 1)

    reg = DepthRegistration(dl, cl, calib.T_color_from_depth)(depth_mm).astype(np.float64)
    both = (reg > 0) & np.isfinite(truth)
    # the depth camera's view covers most of the colour image's middle
    assert both[200:520, 400:880].mean() > 0.97
    err = np.abs(reg[both] - truth[both])
    assert np.median(err) < 3.0, np.median(err)
    # edges: the box / panel (nearer than 2 m) silhouettes agree within 1 px: every pixel where they
    # differ touches the true silhouette's edge (8-neighbourhood), i.e. no edge moved by 2 px or more
    fg_true = truth < 2000
    fg_reg = reg < 2000
    wrong = both & (fg_true != fg_reg)
    k = np.ones((3, 3), bool)
    edge = (fg_true & ~ndimage.binary_erosion(fg_true, k)) | (ndimage.binary_dilation(fg_true, k) & ~fg_true)
    assert fg_true[both].mean() > 0.1
    assert wrong.sum() < 0.5 * edge.sum()
    assert not (wrong & ~edge).any(), np.argwhere(wrong & ~edge)[:10]


# ---------------------------------------------------------------- import, alignment, bad input


def _synthetic_rig(tmp_path, n=5, offsets_ns=(0, 120_000), drop=None):
    """Two synchronised devices: depth value 1000 + 100 k mm encodes frame k; `drop` = (device, k) left out."""
    calib = device_calibration_json(DEPTH_P, COLOR_P, R_CD, T_CD)
    jpg = cv2.imencode(".jpg", np.full((720, 1280, 3), 128, np.uint8))[1].tobytes()
    paths = []
    for d, off in enumerate(offsets_ns):
        ks = [k for k in range(n) if drop != (d, k)]
        depth = [np.full((576, 640), 1000 + 100 * k, np.uint16) for k in ks]
        ts = [int(round(k * 1e6 / 30)) for k in ks]
        paths.append(write_k4a_mkv(tmp_path / f"dev{d}.mkv", [jpg] * len(ks), depth, ts, calib, serial=f"S{d}",
                                   start_offset_ns=5_000_000_000 + off, sync_mode="MASTER" if d == 0 else "SUBORDINATE"))
    return paths


def test_rig_alignment_reports_drops_and_never_shifts_frames(tmp_path):
    paths = _synthetic_rig(tmp_path, n=5, drop=(1, 2))
    out = tmp_path / "session"
    r = import_k4a(out, paths, uncalibrated=True, color_resolution="360")
    assert r["frames"] == 5 and r["dropped"] == {"cam0": [], "cam1": [2]}
    assert not (out / "cam1" / "depth" / "000002.png").exists()
    for cam in ("cam0", "cam1"):
        for k in (0, 1, 3, 4):
            reg = cv2.imread(str(out / cam / "depth" / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED)
            assert reg.shape == (360, 640)
            # a fronto-parallel plane at z0 in the depth frame, seen from the colour camera: z within ~10 %
            assert abs(np.median(reg[reg > 0]) - (1000 + 100 * k)) < 0.1 * (1000 + 100 * k)
        med = [np.median(cv2.imread(str(out / cam / "depth" / f"{k:06d}.png"), -1)) for k in (3, 4)]
        assert med[1] > med[0]
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["extrinsics_unknown"] == ["cam1"] and cal["cameras"][0]["width"] == 640
    _, problems = validate(out)
    assert not any(p.fatal for p in problems), [str(p) for p in problems]


@pytest.mark.parametrize("devices", [1, 2])
def test_a_frame_every_camera_dropped_keeps_its_time(tmp_path, devices):
    """One recording's drop (or a rig's common one) is a session frame without files:
    frame k keeps time k / fps, so later frames are not shifted (depth 1000 + 100 k mm
    encodes the recorded frame)."""
    offsets = (0, 120_000)[:devices]
    calib = device_calibration_json(DEPTH_P, COLOR_P, R_CD, T_CD)
    jpg = cv2.imencode(".jpg", np.full((720, 1280, 3), 128, np.uint8))[1].tobytes()
    paths = []
    for d, off in enumerate(offsets):
        ks = [k for k in range(6) if k not in (2, 3)]
        paths.append(write_k4a_mkv(tmp_path / f"dev{d}.mkv", [jpg] * len(ks),
                                   [np.full((576, 640), 1000 + 100 * k, np.uint16) for k in ks],
                                   [int(round(k * 1e6 / 30)) for k in ks], calib, serial=f"S{d}",
                                   start_offset_ns=5_000_000_000 + off))
    out = tmp_path / "session"
    r = import_k4a(out, paths, uncalibrated=True, color_resolution="360")
    names = [f"cam{d}" for d in range(devices)]
    assert r["frames"] == 6 and r["dropped"] == {n: [2, 3] for n in names}
    for n in names:
        assert sorted(p.name for p in (out / n / "depth").iterdir()) == [f"{k:06d}.png" for k in (0, 1, 4, 5)]
        for k in (1, 4, 5):
            reg = cv2.imread(str(out / n / "depth" / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED)
            assert abs(np.median(reg[reg > 0]) - (1000 + 100 * k)) < 0.1 * (1000 + 100 * k)
    times = json.loads((out / "k4a_import.json").read_text())["frame_time_ns"]
    assert np.allclose(np.diff(times), 1e9 / 30, atol=1e5)
    _, problems = validate(out)
    assert not any(p.fatal for p in problems), [str(p) for p in problems]


def test_several_devices_need_their_poses(tmp_path):
    paths = _synthetic_rig(tmp_path, n=2)
    with pytest.raises(K4AError, match="intercap calibrate"):
        import_k4a(tmp_path / "s", paths)
    assert not (tmp_path / "s").exists()
    rig = {"cameras": [{"name": "cam0", "T_world_from_cam": np.eye(4).tolist()},
                       {"name": "cam1", "T_world_from_cam": [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    import_k4a(tmp_path / "s", paths, calibration=tmp_path / "rig.json", end=0)
    cal = json.loads((tmp_path / "s" / "calibration.json").read_text())
    assert cal["cameras"][1]["T_world_from_cam"][0][3] == 0.5 and "extrinsics_unknown" not in cal


@needs_data
def test_import_real_recording_then_validate(tmp_path, capsys):
    out = tmp_path / "k4a_session"
    assert main(["import", "k4a", str(out), str(REC)]) == 0
    session, problems = validate(out)
    assert not any(p.fatal for p in problems), [str(p) for p in problems]
    cal = json.loads((out / "calibration.json").read_text())["cameras"][0]
    assert cal["T_world_from_cam"] == np.eye(4).tolist() and (cal["width"], cal["height"]) == (1280, 720)
    reg = cv2.imread(str(out / "cam0" / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert reg.dtype == np.uint16 and (reg > 0).mean() > 0.4 and 300 < np.median(reg[reg > 0]) < 6000
    assert (out / "cam0" / "color" / "000000.jpg").read_bytes()[:2] == b"\xff\xd8"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left


@needs_data
def test_truncated_recording_is_one_clear_error(tmp_path, capsys):
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(REC.read_bytes()[: int(REC.stat().st_size * 0.3)])
    out = tmp_path / "s"
    assert main(["import", "k4a", str(out), str(cut)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(cut) in err and "truncated" in err
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_bad_recordings_name_the_file(tmp_path):
    calib = device_calibration_json(DEPTH_P, COLOR_P, R_CD, T_CD)
    jpg = cv2.imencode(".jpg", np.zeros((720, 1280, 3), np.uint8))[1].tobytes()
    depth = [np.full((576, 640), 1500, np.uint16)]
    no_depth = write_k4a_mkv(tmp_path / "nodepth.mkv", [jpg], None, [0], calib)
    with pytest.raises(K4AMissingError, match=r"nodepth\.mkv.*no DEPTH track"):
        import_k4a(tmp_path / "s", [no_depth])
    no_cal = write_k4a_mkv(tmp_path / "nocal.mkv", [jpg], depth, [0], None)
    with pytest.raises(K4AMissingError, match=r"nocal\.mkv.*calibration\.json attachment"):
        import_k4a(tmp_path / "s", [no_cal])
    a = write_k4a_mkv(tmp_path / "a.mkv", [jpg] * 2, depth * 2, [0, 33333], calib, start_offset_ns=0)
    b = write_k4a_mkv(tmp_path / "b.mkv", [jpg] * 2, depth * 2, [0, 33333], calib, start_offset_ns=10 ** 10)
    with pytest.raises(K4AError, match=r"a\.mkv.*do not overlap"):
        import_k4a(tmp_path / "s", [a, b], uncalibrated=True)
    with pytest.raises(K4AMissingError, match="not found"):
        import_k4a(tmp_path / "s", [tmp_path / "missing.mkv"])
    assert not (tmp_path / "s").exists()


def test_frame_range_in_frames_or_seconds():
    from intercap.io.k4a import frame_selection

    assert frame_selection(100, 30.0, None, None, 1).tolist() == list(range(100))
    assert frame_selection(100, 30.0, "1s", "2s", 10).tolist() == [30, 40, 50, 60]
    assert frame_selection(100, 30.0, 5, 500, 40).tolist() == [5, 45, 85]
    with pytest.raises(K4AError, match="selects no frame"):
        frame_selection(100, 30.0, 200, None, 1)
