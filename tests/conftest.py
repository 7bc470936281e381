"""Shared test fixtures: a tiny, valid, geometrically consistent capture session written by hand.

The tiny scene (world z up, metres):
  * ground plane z = 0 (session.yaml gives it: point [0,0,0], normal [0,0,1]);
  * the object: a box with extents (0.3, 0.2, 0.2) standing on the ground, pose per
    frame f: rotation about z by 10*f degrees, translation (0.25 - 0.1 f, 0, 0.1)
    (`tiny_object_pose`); object.ply is that box in object coordinates;
  * the "person": a vertical cylinder at (-0.3, 0), radius 0.2, height 1.7 (static);
  * cameras on a circle of radius 3 around the origin at height 1.5, looking at
    (0, 0, 0.8); cam0 at (0, -3, 1.5); fx = fy = 70 for 64x48 images.
Depth is ray-cast analytically (`render_tiny_view`), so back-projected depth lies
exactly on the plane / box / cylinder surfaces (up to the 1 mm quantisation);
pixels whose ray hits nothing within 8 m have depth 0. Masks are the visible box / cylinder
pixels. cam0 stores JPEG colour, the other cameras PNG. Keypoints (OpenPose JSON) are
written for cam0 only: BODY_25 and left hand are projections of the ground-truth
keypoints3d, right hand is an empty list and face is absent (so it reads as conf 0).

Use `write_tiny_session(root, ...)` to write variants and the `tiny_*` helpers to
know the truth that was written.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
import yaml

TINY_BOX_EXTENTS = (0.3, 0.2, 0.2)
TINY_PERSON_CENTER = (-0.3, 0.0)
TINY_PERSON_RADIUS = 0.2
TINY_PERSON_HEIGHT = 1.7
TINY_FOCAL = 70.0
TINY_MAX_DEPTH = 8.0  # metres; farther hits read as 0 (no measurement), like a real sensor
TINY_CAMERA_RADIUS = 3.0
TINY_CAMERA_HEIGHT = 1.5
TINY_LOOK_AT = (0.0, 0.0, 0.8)
TINY_CONTACT = (False, False, True)  # ground-truth contact for frames 0, 1, 2 (and False after)
TINY_COLORS = {0: (0, 0, 0), 1: (120, 120, 120), 2: (200, 40, 40), 3: (40, 60, 200)}  # label -> RGB
LABEL_NONE, LABEL_GROUND, LABEL_OBJECT, LABEL_PERSON = 0, 1, 2, 3


def pytest_configure(config):
    """A pytest-xdist worker (setup.cfg starts one per core) takes its share of the cores for torch's
    threads, and the processes it starts inherit it: workers each running all cores' threads slow
    each other badly."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if workers > 1:
        import torch

        from intercap.parallel import cpu_count

        threads = max(1, cpu_count() // workers)
        os.environ["OMP_NUM_THREADS"] = str(threads)
        torch.set_num_threads(threads)


def rot_z(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def tiny_object_pose(frame: int) -> tuple[np.ndarray, np.ndarray]:
    """Object -> world (R (3,3), t (3,)) of the tiny box at a frame."""
    return rot_z(10.0 * frame), np.array([0.25 - 0.1 * frame, 0.0, 0.1])


def tiny_camera(index: int, num_cameras: int, width: int = 64, height: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """(K (3,3), T_world_from_cam (4,4)) of camera `index`: on a circle, looking at TINY_LOOK_AT."""
    angle = np.deg2rad(-90.0 + index * 360.0 / max(num_cameras, 4))
    center = np.array([TINY_CAMERA_RADIUS * np.cos(angle), TINY_CAMERA_RADIUS * np.sin(angle), TINY_CAMERA_HEIGHT])
    z = np.asarray(TINY_LOOK_AT) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # OpenCV: x right, y down, z forward
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = center
    K = np.array([[TINY_FOCAL, 0.0, (width - 1) / 2], [0.0, TINY_FOCAL, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return K, T


def render_tiny_view(K: np.ndarray, T_world_from_cam: np.ndarray, width: int, height: int, frame: int):
    """Ray-cast the tiny scene: (depth_mm (H,W) uint16, label (H,W) uint8 in LABEL_*)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # (H,W,3), z = 1
    R, o = T_world_from_cam[:3, :3], T_world_from_cam[:3, 3]
    d = d_cam @ R.T  # (H,W,3) world directions; the ray parameter s is the camera-frame depth
    inf = np.inf
    with np.errstate(divide="ignore", invalid="ignore"):
        # ground plane z = 0
        s_ground = np.where(d[..., 2] < 0, -o[2] / d[..., 2], inf)
        # box: slab test in object coordinates
        R_o, t_o = tiny_object_pose(frame)
        o_obj = R_o.T @ (o - t_o)
        d_obj = d @ R_o  # (H,W,3) = R_o^T d
        h = np.asarray(TINY_BOX_EXTENTS) / 2
        t1, t2 = (-h - o_obj) / d_obj, (h - o_obj) / d_obj
        t_near, t_far = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
        s_box = np.where((t_far >= t_near) & (t_near > 0), t_near, inf)
        # person: vertical cylinder side + top cap
        cx, cy = TINY_PERSON_CENTER
        ox, oy = o[0] - cx, o[1] - cy
        a = d[..., 0] ** 2 + d[..., 1] ** 2
        b = 2 * (ox * d[..., 0] + oy * d[..., 1])
        c = ox**2 + oy**2 - TINY_PERSON_RADIUS**2
        disc = b**2 - 4 * a * c
        s_side = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        z_side = o[2] + s_side * d[..., 2]
        s_side = np.where((disc >= 0) & (s_side > 0) & (z_side >= 0) & (z_side <= TINY_PERSON_HEIGHT), s_side, inf)
        s_cap = (TINY_PERSON_HEIGHT - o[2]) / d[..., 2]
        px, py = ox + s_cap * d[..., 0], oy + s_cap * d[..., 1]
        s_cap = np.where((s_cap > 0) & (px**2 + py**2 <= TINY_PERSON_RADIUS**2), s_cap, inf)
    s_all = np.stack([np.full_like(s_ground, inf), s_ground, s_box, np.minimum(s_side, s_cap)], 0)  # (4,H,W)
    label = np.argmin(s_all, 0).astype(np.uint8)
    s = s_all.min(0)
    depth_mm = np.where(s <= TINY_MAX_DEPTH, np.round(s * 1000.0), 0).clip(0, 65535).astype(np.uint16)
    label[depth_mm == 0] = LABEL_NONE
    return depth_mm, label


def tiny_keypoints3d(num_frames: int) -> np.ndarray:
    """(T, 67, 3) float32 ground-truth keypoints: points up the person's axis."""
    cx, cy = TINY_PERSON_CENTER
    z = 0.1 + 1.5 * np.arange(67) / 66
    one = np.stack([np.full(67, cx), np.full(67, cy), z], -1)
    return np.repeat(one[None], num_frames, 0).astype(np.float32)


def project(K: np.ndarray, T_world_from_cam: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) pixel coordinates of world points (N, 3)."""
    R, t = T_world_from_cam[:3, :3], T_world_from_cam[:3, 3]
    pc = (points - t) @ R  # (N, 3) camera coordinates
    uv = pc @ K.T
    return uv[:, :2] / uv[:, 2:3]


def tiny_openpose(K: np.ndarray, T_world_from_cam: np.ndarray, keypoints3d: np.ndarray, conf: float = 0.8) -> dict:
    """OpenPose JSON for one frame: BODY_25 and left hand projected; right hand empty; no face key."""
    uv = project(K, T_world_from_cam, keypoints3d.astype(np.float64))  # (67, 2)
    xyc = np.concatenate([uv, np.full((67, 1), conf)], 1)
    return {
        "version": 1.3,
        "people": [
            {
                "person_id": [-1],
                "pose_keypoints_2d": xyc[:25].reshape(-1).tolist(),
                "hand_left_keypoints_2d": xyc[25:46].reshape(-1).tolist(),
                "hand_right_keypoints_2d": [],
            }
        ],
    }


def tiny_person_mesh() -> trimesh.Trimesh:
    """The ground-truth body: the person cylinder as a mesh, world coordinates."""
    mesh = trimesh.creation.cylinder(radius=TINY_PERSON_RADIUS, height=TINY_PERSON_HEIGHT, sections=16)
    mesh.apply_translation([*TINY_PERSON_CENTER, TINY_PERSON_HEIGHT / 2])
    return mesh


def write_tiny_session(
    root: Path,
    *,
    cameras: tuple[str, ...] = ("cam0", "cam1"),
    width: int = 64,
    height: int = 48,
    num_frames: int = 3,
    jpeg_cameras: tuple[str, ...] = ("cam0",),
    keypoint_cameras: tuple[str, ...] = ("cam0",),
    masks: bool = True,
    with_object: bool = True,
    ground_truth: bool = True,
    frames_block: bool = True,
) -> Path:
    """Write a small valid session (see the module docstring) into `root`; returns `root`."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    cfg: dict = {"fps": 30}
    if with_object:
        box = trimesh.creation.box(extents=TINY_BOX_EXTENTS)
        box.export(root / "object.ply")
        (root / "object_contacts.json").write_text(json.dumps({"vertices": [0, 1, 2, 3]}))
        R0, t0 = tiny_object_pose(0)
        cfg["object"] = {
            "mesh": "object.ply",
            "name": "box",
            "mass_kg": 1.2,
            "contact_vertices": "object_contacts.json",
            "initial_pose": {"R": R0.tolist(), "t": t0.tolist()},
        }
        cfg["contact_frames"] = [[i, i] for i in range(num_frames) if i < len(TINY_CONTACT) and TINY_CONTACT[i]]
    if frames_block:
        cfg["frames"] = {"start": 0, "end": num_frames - 1}
    cfg["ground"] = {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]}
    cfg["body"] = {"model": "anny"}
    (root / "session.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))

    calib = {"world": "metres; z up; ground z = 0", "cameras": []}
    kp3d = tiny_keypoints3d(num_frames)
    for i, name in enumerate(cameras):
        K, T = tiny_camera(i, len(cameras), width, height)
        calib["cameras"].append(
            {
                "name": name,
                "width": width,
                "height": height,
                "K": K.tolist(),
                "dist": [] if i == 0 else [0.0, 0.0, 0.0, 0.0, 0.0],
                "T_world_from_cam": T.tolist(),
            }
        )
        cam = root / name
        for sub in ("color", "depth") + (("masks/person", "masks/object") if masks else ()):
            (cam / sub).mkdir(parents=True, exist_ok=True)
        if name in keypoint_cameras:
            (cam / "keypoints").mkdir(parents=True, exist_ok=True)
        for f in range(num_frames):
            depth_mm, label = render_tiny_view(K, T, width, height, f)
            rgb = np.zeros((height, width, 3), np.uint8)
            for lab, color in TINY_COLORS.items():
                rgb[label == lab] = color
            ext = ".jpg" if name in jpeg_cameras else ".png"
            cv2.imwrite(str(cam / "color" / f"{f:06d}{ext}"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(cam / "depth" / f"{f:06d}.png"), depth_mm)
            if masks:
                cv2.imwrite(str(cam / "masks/person" / f"{f:06d}.png"), np.where(label == LABEL_PERSON, 255, 0).astype(np.uint8))
                cv2.imwrite(str(cam / "masks/object" / f"{f:06d}.png"), np.where(label == LABEL_OBJECT, 255, 0).astype(np.uint8))
            if name in keypoint_cameras:
                (cam / "keypoints" / f"{f:06d}.json").write_text(json.dumps(tiny_openpose(K, T, kp3d[f])))
    (root / "calibration.json").write_text(json.dumps(calib, indent=1))

    if ground_truth:
        gt = root / "ground_truth"
        gt.mkdir(exist_ok=True)
        person = tiny_person_mesh()
        verts = np.repeat(np.asarray(person.vertices, np.float32)[None], num_frames, 0)  # (T, V, 3)
        np.save(gt / "body_vertices.npy", verts)
        np.save(gt / "body_faces.npy", np.asarray(person.faces, np.int64))
        np.save(gt / "contact.npy", np.array([i < len(TINY_CONTACT) and TINY_CONTACT[i] for i in range(num_frames)]))
        np.save(gt / "keypoints3d.npy", kp3d)
        if with_object:
            poses = [tiny_object_pose(f) for f in range(num_frames)]
            np.savez(gt / "object_poses.npz", R=np.stack([p[0] for p in poses]), t=np.stack([p[1] for p in poses]))
    return root


@pytest.fixture
def replay_on_cpu(monkeypatch):
    """The fits' CUDA-graph recordings made and replayed on the CPU (graph_replay.py); the replays made."""
    from graph_replay import replaying_on_cpu

    yield from replaying_on_cpu(monkeypatch)


@pytest.fixture
def tiny_session(tmp_path: Path) -> Path:
    """A fresh tiny valid session (2 cameras cam0/cam1, 64x48, 3 frames, box object); its folder."""
    return write_tiny_session(tmp_path / "session")


SAMPLE_SESSION = Path(__file__).resolve().parents[1] / "data_samples" / "sample"


def trimmed_copy(src: Path, dst: Path, frames: int) -> Path:
    """The first `frames` frames of a session, ground truth sliced to match."""
    import shutil

    shutil.copytree(src, dst, ignore=lambda d, names: [
        n for n in names if n.endswith((".png", ".jpg", ".json")) and n[:6].isdigit() and int(n[:6]) >= frames])
    doc = yaml.safe_load((dst / "session.yaml").read_text())
    doc["frames"] = {"start": 0, "end": frames - 1}
    (dst / "session.yaml").write_text(yaml.safe_dump(doc))
    gt = dst / "ground_truth"
    for name in ("body_vertices.npy", "contact.npy", "keypoints3d.npy"):
        np.save(gt / name, np.load(gt / name)[:frames])
    poses = np.load(gt / "object_poses.npz")
    np.savez(gt / "object_poses.npz", R=poses["R"][:frames], t=poses["t"][:frames])
    if (gt / "body_params.npz").exists():
        params = dict(np.load(gt / "body_params.npz"))
        np.savez(gt / "body_params.npz", **{k: (v[:frames] if v.ndim else v) for k, v in params.items()})
    (gt / "info.json").unlink(missing_ok=True)
    return dst


# A tilted floor (up is not a world axis): ground-plane and calibration tests share it.
FLOOR_NORMAL = np.array([0.1, -0.98, 0.15]) / np.linalg.norm([0.1, -0.98, 0.15])  # up, not a world axis
FLOOR_POINT = np.array([0.3, 1.1, -0.4])


def floor_basis(up):
    e1 = np.cross(up, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


class SessionKeypoints:
    """The `KeypointSource` a raw copy's run would have: the keypoints of the session it was copied from."""

    def __init__(self, session):
        self.session = session

    def read(self, c: int, frame_id: int):
        return self.session.read_keypoints(c, frame_id)
