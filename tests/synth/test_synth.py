"""The synthetic session generator: determinism, the session format, and that
what it writes agrees with its own ground truth (keypoints, depth, masks).

Three tiny sessions (2 cameras, 96x80, 4 frames) are generated once per module.
"""
from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
import trimesh
import yaml

from intercap.synth.generator import (
    PRESETS,
    SynthConfig,
    build_arg_parser,
    config_from_args,
    distort_normalized,
    flying_pixels,
    generate_session,
    kinect_depth,
    look_at_pose,
    save_npz_deterministic,
    undistort_normalized,
)

TINY = SynthConfig(**PRESETS["tiny"], quiet=True)
FILES_DETERMINISTIC = ("*.npy", "*.npz", "*.json", "*.png", "*.yaml", "*.ply")


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    a = generate_session(TINY, root / "a")
    b = generate_session(TINY, root / "b")
    c = generate_session(dataclasses.replace(TINY, seed=1, clean_depth=True, drop_rate=0.5, drop_view=1,
                                             annotate=True), root / "c")
    return a, b, c


def load_cameras(session):
    return json.loads((session / "calibration.json").read_text())["cameras"]


def frame_files(session, cam, sub, ext):
    return sorted((session / cam / sub).glob(f"*.{ext}"))


def relative_files(session):
    return sorted(p.relative_to(session) for pattern in FILES_DETERMINISTIC for p in session.rglob(pattern))


# ----------------------------------------------------------------------------- determinism
def test_same_seed_gives_identical_files(sessions):
    a, b, _ = sessions
    files = relative_files(a)
    assert files == relative_files(b)
    assert any(str(f).endswith(".png") for f in files) and any(str(f).endswith(".json") for f in files)
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f"{f} differs between two runs with the same seed"
    for jpg in sorted(a.rglob("*.jpg")):  # JPEG: compare decoded pixels
        assert np.array_equal(cv2.imread(str(jpg)), cv2.imread(str(b / jpg.relative_to(a))))


def test_other_seed_differs(sessions):
    a, _, c = sessions
    assert not np.allclose(np.load(a / "ground_truth/body_vertices.npy"), np.load(c / "ground_truth/body_vertices.npy"))
    assert (a / "cam0/keypoints/000000.json").read_bytes() != (c / "cam0/keypoints/000000.json").read_bytes()


# ----------------------------------------------------------------------------- format
def test_session_layout_and_ground_truth_shapes(sessions):
    a, _, _ = sessions
    T = TINY.frames
    doc = yaml.safe_load((a / "session.yaml").read_text())
    assert doc["fps"] == TINY.fps
    assert doc["frames"] == {"start": 0, "end": T - 1}
    assert "contact_frames" not in doc and "ground" not in doc and "initial_pose" not in doc["object"]
    mesh = trimesh.load(a / doc["object"]["mesh"], process=False)
    assert mesh.is_watertight
    contacts = json.loads((a / doc["object"]["contact_vertices"]).read_text())["vertices"]
    assert len(contacts) > 0 and max(contacts) < len(mesh.vertices)

    cams = load_cameras(a)
    assert [c["name"] for c in cams] == ["cam0", "cam1"]
    for cam in cams:
        assert set(cam) >= {"name", "width", "height", "K", "dist", "T_world_from_cam"}
        assert np.asarray(cam["K"]).shape == (3, 3) and len(cam["dist"]) == 5
        T_wc = np.asarray(cam["T_world_from_cam"])
        assert T_wc.shape == (4, 4) and np.allclose(T_wc[:3, :3] @ T_wc[:3, :3].T, np.eye(3), atol=1e-6)
        for sub, ext in (("color", "jpg"), ("depth", "png"), ("keypoints", "json"), ("masks/person", "png"),
                         ("masks/object", "png")):
            names = [p.name for p in frame_files(a, cam["name"], sub, ext)]
            assert names == [f"{i:06d}.{ext}" for i in range(T)], (cam["name"], sub)
        depth = cv2.imread(str(a / cam["name"] / "depth/000000.png"), cv2.IMREAD_UNCHANGED)
        colour = cv2.imread(str(a / cam["name"] / "color/000000.jpg"))
        assert depth.dtype == np.uint16 and depth.shape == (cam["height"], cam["width"])
        assert colour.shape == (cam["height"], cam["width"], 3)
        people = json.loads((a / cam["name"] / "keypoints/000000.json").read_text())["people"]
        assert len(people) == 1
        lengths = {k: len(v) for k, v in people[0].items()}
        assert lengths == {"pose_keypoints_2d": 75, "hand_left_keypoints_2d": 63, "hand_right_keypoints_2d": 63,
                           "face_keypoints_2d": 210}

    gt = a / "ground_truth"
    verts = np.load(gt / "body_vertices.npy")
    faces = np.load(gt / "body_faces.npy")
    poses = np.load(gt / "object_poses.npz")
    contact = np.load(gt / "contact.npy")
    kp = np.load(gt / "keypoints3d.npy")
    assert verts.dtype == np.float32 and verts.ndim == 3 and verts.shape[0] == T and verts.shape[2] == 3
    assert np.issubdtype(faces.dtype, np.integer) and faces.shape[1] == 3 and faces.max() < verts.shape[1]
    assert poses["R"].shape == (T, 3, 3) and poses["t"].shape == (T, 3)
    assert np.allclose(poses["R"] @ poses["R"].transpose(0, 2, 1), np.eye(3), atol=1e-6)
    assert contact.dtype == bool and contact.shape == (T,) and contact.any() and not contact.all()
    assert kp.dtype == np.float32 and kp.shape == (T, 67, 3)
    # feet on the floor z = 0, body above it
    assert abs(verts.min(axis=1)[:, 2]).max() < 1e-3


def test_annotate_and_dropped_frames(sessions):
    _, _, c = sessions
    doc = yaml.safe_load((c / "session.yaml").read_text())
    contact = np.load(c / "ground_truth/contact.npy")
    annotated = np.zeros_like(contact)
    for start, end in doc["contact_frames"]:
        annotated[start:end + 1] = True
    assert np.array_equal(annotated, contact)
    assert doc["ground"]["normal"] == [0.0, 0.0, 1.0]
    missing = {f"{i:06d}.jpg" for i in range(TINY.frames)} - {p.name for p in frame_files(c, "cam1", "color", "jpg")}
    assert len(missing) == round(0.5 * TINY.frames) and "000000.jpg" not in missing
    assert len(frame_files(c, "cam0", "color", "jpg")) == TINY.frames


# ----------------------------------------------------------------------------- agreement with ground truth
def test_contact_labels_agree_with_hand_object_geometry(sessions):
    """Hands touch the object (< 1 cm, not sunk in > 1 cm) in contact frames and are far from it at both ends."""
    a, _, _ = sessions
    contact = np.load(a / "ground_truth/contact.npy")
    info = json.loads((a / "ground_truth/info.json").read_text())
    distance = np.array(info["hand_object_distance_m"])
    assert distance.shape == contact.shape
    assert (np.abs(distance[contact]) < 0.01).all(), distance
    assert distance[0] > 0.05 and distance[-1] > 0.05
    for hand in info["hand_object"].values():
        assert hand["palm_gap_max_m"] < 0.01 and hand["penetration_max_m"] < 0.01



def opencv_camera(cam):
    T_cw = np.linalg.inv(np.asarray(cam["T_world_from_cam"]))
    rvec, _ = cv2.Rodrigues(T_cw[:3, :3])
    return rvec, T_cw[:3, 3], np.asarray(cam["K"], float), np.asarray(cam["dist"], float)


def test_keypoints_match_projected_ground_truth(sessions):
    """OpenCV's own projection of the true 3D keypoints lands within the noise of confident 2D detections."""
    a, _, _ = sessions
    kp3d = np.load(a / "ground_truth/keypoints3d.npy")
    checked = 0
    for cam in load_cameras(a):
        rvec, tvec, K, dist = opencv_camera(cam)
        scale = cam["width"] / 640
        for f in range(TINY.frames):
            people = json.loads((a / cam["name"] / f"keypoints/{f:06d}.json").read_text())["people"]
            if not people:
                continue
            p = people[0]
            det = np.array(p["pose_keypoints_2d"] + p["hand_left_keypoints_2d"] + p["hand_right_keypoints_2d"]).reshape(67, 3)
            uv, _ = cv2.projectPoints(kp3d[f].astype(np.float64), rvec, tvec, K, dist)
            uv = uv.reshape(67, 2)
            sigma = np.where(np.arange(67) < 25, TINY.kp_sigma_body, TINY.kp_sigma_hand) * scale
            confident = det[:, 2] >= 0.5
            err = np.linalg.norm(det[confident, :2] - uv[confident], axis=1)
            assert (err < 5 * sigma[confident] + 0.02).all(), (cam["name"], f, err.max())
            checked += int(confident.sum())
            dropped = det[:, 2] == 0
            assert (det[dropped, :2] == 0).all()
    assert checked > 50


def backproject(depth_m, pixels, cam):
    """Pixels (N, 2) with depth (N,) -> world points (N, 3) using K, dist and T_world_from_cam."""
    K, dist = np.asarray(cam["K"], float), np.asarray(cam["dist"], float)
    xy = cv2.undistortPoints(pixels.reshape(-1, 1, 2).astype(np.float64), K, dist,
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(-1, 2)
    pc = np.concatenate([xy * depth_m[:, None], depth_m[:, None]], 1)
    T = np.asarray(cam["T_world_from_cam"])
    return pc @ T[:3, :3].T + T[:3, 3]


def object_mask_surface_distances(session):
    """Distances (m) from back-projected object-mask depth pixels to the posed object surface."""
    from intercap.synth.objects import SurfaceDistance

    mesh = trimesh.load(session / "object.ply", process=False)
    sdf = SurfaceDistance(mesh)
    poses = np.load(session / "ground_truth/object_poses.npz")
    dists = []
    for cam in load_cameras(session):
        for path in frame_files(session, cam["name"], "depth", "png"):
            f = int(path.stem)
            depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0
            mask = cv2.imread(str(session / cam["name"] / "masks/object" / path.name), cv2.IMREAD_GRAYSCALE) > 127
            v, u = np.nonzero(mask & (depth > 0))
            if len(u) == 0:
                continue
            world = backproject(depth[v, u], np.stack([u, v], 1), cam)
            local = (world - poses["t"][f]) @ poses["R"][f]
            dists.append(np.abs(sdf(local)))
    return np.concatenate(dists)


def test_clean_object_depth_agrees_with_ground_truth_pose(sessions):
    _, _, c = sessions
    d = object_mask_surface_distances(c)
    assert len(d) >= 10
    assert np.median(d) < 0.003, np.median(d)  # about 1-2 mm at 96x80; half a pixel off gives > 5 mm


def test_noisy_object_depth_agrees_within_noise(sessions):
    a, _, _ = sessions
    d = object_mask_surface_distances(a)
    sigma_at_4m = TINY.depth_sigma_base + TINY.depth_sigma_quad * 16
    assert len(d) >= 10 and np.median(d) < sigma_at_4m, np.median(d)


def test_masks_cover_the_projected_object(sessions):
    """Where the object projects into a view and the mask is not empty, the mask lies on its projection;
    every frame shows the object in at least one view and the person in every view."""
    a, _, _ = sessions
    mesh = trimesh.load(a / "object.ply", process=False)
    poses = np.load(a / "ground_truth/object_poses.npz")
    for f in range(TINY.frames):
        seen = 0
        for cam in load_cameras(a):
            rvec, tvec, K, dist = opencv_camera(cam)
            world = mesh.vertices @ poses["R"][f].T + poses["t"][f]
            uv, _ = cv2.projectPoints(world, rvec, tvec, K, dist)
            uv = uv.reshape(-1, 2)
            obj = cv2.imread(str(a / cam["name"] / f"masks/object/{f:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
            person = cv2.imread(str(a / cam["name"] / f"masks/person/{f:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
            assert person.any(), (cam["name"], f)
            if obj.any():
                seen += 1
                v, u = np.nonzero(obj)
                lo, hi = uv.min(0) - 1.5, uv.max(0) + 1.5
                assert (u >= lo[0]).all() and (u <= hi[0]).all() and (v >= lo[1]).all() and (v <= hi[1]).all()
        assert seen >= 1, f"object invisible in every view at frame {f}"


# ----------------------------------------------------------------------------- pure functions
def test_distortion_round_trip_and_opencv_agreement():
    dist = np.array([0.05, -0.02, 0.0005, -0.0003, 0.001])
    xy = np.random.default_rng(0).uniform(-0.6, 0.6, (200, 2))
    assert np.abs(undistort_normalized(distort_normalized(xy, dist), dist) - xy).max() < 1e-9
    K = np.array([[500.0, 0, 320], [0, 500, 288], [0, 0, 1]])
    pts = np.concatenate([xy, np.ones((200, 1))], 1)
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    ours = distort_normalized(xy, dist) * 500 + np.array([320, 288])
    assert np.abs(uv.reshape(-1, 2) - ours).max() < 1e-9


def test_look_at_is_an_opencv_camera():
    eye, target = np.array([3.0, 1.0, 1.6]), np.array([0.0, 0.0, 0.8])
    T = look_at_pose(eye, target)
    pc = np.linalg.inv(T) @ np.append(target, 1)
    assert pc[2] > 0 and np.allclose(pc[:2], 0, atol=1e-12)  # target straight ahead (+z)
    above = np.linalg.inv(T) @ np.append(target + [0, 0, 0.5], 1)
    assert above[1] < 0  # world up is image up (-y)


def test_kinect_depth_noise_and_dropouts():
    cfg = SynthConfig()
    depth = np.full((120, 160), 2.0, np.float32)
    depth[:, 80:] = 3.0  # a step: an edge to lose pixels on
    colour = np.full((120, 160, 3), 150, np.uint8)
    colour[:20] = 10  # dark band
    mm = kinect_depth(depth, colour, np.random.default_rng(0), dataclasses.replace(cfg, holes=0))
    assert mm.dtype == np.uint16
    flat = mm[40:, 10:70].astype(float)
    flat = flat[flat > 0]
    sigma = (cfg.depth_sigma_base + cfg.depth_sigma_quad * 4) * 1000
    assert abs(flat.mean() - 2000) < 2 and abs(flat.std() - sigma) < 0.15 * sigma
    assert (mm[20:, 78:82] == 0).mean() > 0.3  # edge pixels lost
    assert (mm[40:, 10:70] == 0).mean() < 0.01
    assert (mm[:20, 10:70] == 0).mean() > 0.25  # dark pixels lost


def test_flying_pixels_lie_between_the_two_sides_of_an_edge():
    """A time-of-flight pixel on a depth edge reads a mix of both surfaces: with every edge pixel
    flying, the two columns beside a 2 m -> 3 m step read depths strictly between them, and nothing
    away from the edge moves; with none, the depth is unchanged."""
    depth = np.full((60, 80), 2.0)
    depth[:, 40:] = 3.0
    depth[:5, :5] = 0.0  # no measurement: never mixed
    mixed = flying_pixels(depth, np.random.default_rng(1), jump=0.04, fraction=1.0)
    edge = mixed[:, 39:41]
    assert ((edge > 2.0) & (edge < 3.0)).all() and 2.3 < edge.mean() < 2.7
    away = np.ones_like(depth, bool)
    away[:, 39:41] = False
    assert np.array_equal(mixed[away], depth[away])
    assert np.array_equal(flying_pixels(depth, np.random.default_rng(1), 0.04, 0.0), depth)
    args = build_arg_parser().parse_args(["OUT", "--flying-pixels", "0.5"])
    assert config_from_args(args).flying_pixels == 0.5


def test_deterministic_npz_and_cli(tmp_path):
    save_npz_deterministic(tmp_path / "a.npz", R=np.eye(3)[None], t=np.zeros((1, 3)))
    save_npz_deterministic(tmp_path / "b.npz", R=np.eye(3)[None], t=np.zeros((1, 3)))
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    assert np.array_equal(np.load(tmp_path / "a.npz")["R"], np.eye(3)[None])
    args = build_arg_parser().parse_args(["OUT", "--preset", "sample", "--seed", "3", "--depth-sigma", "0.001,0.002"])
    cfg = config_from_args(args)
    assert (cfg.cameras, cfg.width, cfg.height, cfg.frames, cfg.seed) == (4, 320, 288, 30, 3)
    assert (cfg.depth_sigma_base, cfg.depth_sigma_quad) == (0.001, 0.002)


# ----------------------------------------------------------------------------- variety
def test_outfits_vary_skin_and_clothes_deterministically():
    from intercap.synth.generator import BODY_COLOURS, SKIN_TONES, outfit

    assert outfit(0) == BODY_COLOURS and outfit(7) == outfit(7)
    looks = [outfit(n) for n in range(1, 31)]
    assert len({look["skin"] for look in looks}) >= 4  # light to dark skin over a few seeds
    assert all(look["shirt"] != look["pants"] for look in looks)
    assert {look["skin"] for look in looks} <= set(SKIN_TONES)


def test_appearance_and_light_change_the_images(tmp_path):
    """Same motion and cameras; another outfit changes the person's pixels, a dimmer light darkens the image."""
    base = dataclasses.replace(TINY, frames=1, masks=True)
    images = {}
    for name, change in (("default", {}), ("outfit", {"appearance": 4}), ("dim", {"light": 0.4})):
        session = generate_session(dataclasses.replace(base, **change), tmp_path / name)
        images[name] = cv2.imread(str(session / "cam0" / "color" / "000000.jpg")).astype(float)
        person = cv2.imread(str(session / "cam0" / "masks" / "person" / "000000.png"), cv2.IMREAD_GRAYSCALE) > 0
    assert person.sum() > 50
    assert np.abs(images["outfit"][person] - images["default"][person]).mean() > 20
    assert np.abs(images["outfit"][~person] - images["default"][~person]).mean() < 5  # the scene is the same
    assert images["dim"].mean() < 0.7 * images["default"].mean()
    with pytest.raises(ValueError, match="light"):
        generate_session(dataclasses.replace(base, light=0.0), tmp_path / "dark")


def test_upper_body_preset_frames_the_trunk_not_the_feet(tmp_path):
    from intercap.synth.generator import apply_preset

    cfg = dataclasses.replace(apply_preset(TINY, "upper1"), script="hold", frames=1, width=128, height=112)
    session = generate_session(cfg, tmp_path / "upper")
    cam = load_cameras(session)[0]
    points = np.load(session / "ground_truth" / "keypoints3d.npy")[0]
    T = np.linalg.inv(np.array(cam["T_world_from_cam"]))
    pc = points @ T[:3, :3].T + T[:3, 3]
    v = np.array(cam["K"])[1, 1] * pc[:, 1] / pc[:, 2] + np.array(cam["K"])[1, 2]
    neck, ankles = 1, [11, 14]  # BODY_25
    assert 0 < v[neck] < cfg.height
    assert (v[ankles] > cfg.height).all()  # below the image


def test_hand_solvers_see_the_same_hands_on_the_sparse_forward():
    """The IK and grasp solvers skin only the hands' vertices (`hand_vertices`): re-indexed, the palm
    frames and the hand and finger vertices equal the full forward's on a random posed body."""
    import torch

    from intercap.synth.generator import cached_body_model
    from intercap.synth.motions import hand_geometry, hand_vertices, palm_frames

    model = cached_body_model()
    rest = model(model.init_params(1))
    geom = hand_geometry(model, rest.vertices[0].numpy(), rest.keypoints[0].numpy())
    ids, local = hand_vertices(geom)
    params = model.init_params(3)
    generator = torch.Generator().manual_seed(0)
    params.body_pose[:] = 0.3 * torch.randn(params.body_pose.shape, generator=generator)
    params.left_hand_pose[:] = 0.3 * torch.randn(params.left_hand_pose.shape, generator=generator)
    full = model(params)
    sparse = model.sparse_forward(params, ids, model.rest_state(params, ids))
    assert len(ids) < model.num_vertices / 3
    for side in geom:
        for a, b in zip(palm_frames(full.keypoints, full.vertices, geom[side], side),
                        palm_frames(sparse.keypoints, sparse.vertices, local[side], side)):
            assert torch.allclose(a, b, atol=1e-4)
        assert torch.allclose(full.vertices[:, geom[side].whole], sparse.vertices[:, local[side].whole], atol=1e-5)


def test_a_thin_board_is_carried_by_its_edges(tmp_path):
    """The 2 cm board (a thin object for held-out runs): a closed mesh whose grasped edges are its
    contact vertices, and in contact frames both palms lie on those edges without sinking in."""
    from intercap.synth.objects import make_object

    board = make_object("board")
    assert board.mesh.is_watertight and np.ptp(board.mesh.vertices[:, 2]) == pytest.approx(0.02)
    edge_x = np.abs(board.mesh.vertices[board.contact_vertices, 0])
    assert len(edge_x) > 4 and np.allclose(edge_x, 0.20)
    session = generate_session(dataclasses.replace(TINY, object="board", frames=12), tmp_path / "board")
    contact = np.load(session / "ground_truth/contact.npy")
    info = json.loads((session / "ground_truth/info.json").read_text())
    assert contact.any() and (np.abs(np.array(info["hand_object_distance_m"])[contact]) < 0.01).all()
    for hand in info["hand_object"].values():
        assert hand["palm_gap_max_m"] < 0.01 and hand["penetration_max_m"] < 0.01
