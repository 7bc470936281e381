"""Re-express a session in another world frame: the same images, calibration, ground truth and
annotations, with every world quantity moved by one rigid transform.

Real rigs put the world anywhere (BEHAVE, InterCap and most Kinect rigs: at camera 1, OpenCV axes,
y down); our generator writes a z-up world. `camera_as_world` makes a generated session look like
such a capture, so tests can check that results do not depend on the world frame.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import yaml

from intercap.io.files import read_json, save_npy, save_npz, write_json

# Ground-truth files that hold no world coordinates: copied as they are.
_FRAME_FREE = ("body_faces.npy", "contact.npy")


def link_tree(src: Path, dst: Path) -> None:
    """Copy a folder of frame files by hard links where the file system allows (fast, no extra space)."""
    for path in src.rglob("*"):
        target = dst / path.relative_to(src)
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path, target)
        except OSError:
            shutil.copy2(path, target)


def _moved_points(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(..., 3) points moved by the rigid transform T (4, 4); NaN stays NaN."""
    return (points @ T[:3, :3].T + T[:3, 3]).astype(points.dtype)


def reexpress(session_dir, out_dir, T_new_from_old: np.ndarray) -> Path:
    """Write a copy of the session at `out_dir` whose world frame is `T_new_from_old` (4, 4) applied
    to the old one: camera poses, the ground, the object's initial pose and the ground truth's world
    arrays are moved; images, masks, keypoints, meshes and contact labels are the same files.
    The ground truth's body_params.npz (model parameters, whose root convention is the model's own)
    is left out of the copy; evaluation compares surfaces, keypoints and poses, never parameters."""
    src, dst = Path(session_dir), Path(out_dir)
    T = np.asarray(T_new_from_old, np.float64)
    if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9):
        raise ValueError("T_new_from_old must be a rigid 4x4 transform")
    if dst.exists():
        raise FileExistsError(f"{dst} exists; choose a new folder")
    dst.mkdir(parents=True)
    for path in src.iterdir():
        if path.name in ("calibration.json", "session.yaml", "ground_truth"):
            continue
        if path.is_dir():
            link_tree(path, dst / path.name)
        else:
            shutil.copy2(path, dst / path.name)

    calib = read_json(src / "calibration.json")
    for cam in calib["cameras"]:
        cam["T_world_from_cam"] = (T @ np.asarray(cam["T_world_from_cam"], np.float64)).tolist()
    write_json(dst / "calibration.json", calib)

    cfg = yaml.safe_load((src / "session.yaml").read_text())
    if cfg.get("ground"):
        cfg["ground"] = {"point": _moved_points(np.asarray(cfg["ground"]["point"], float), T).tolist(),
                         "normal": (T[:3, :3] @ np.asarray(cfg["ground"]["normal"], float)).tolist()}
    pose = (cfg.get("object") or {}).get("initial_pose")
    if pose:
        pose["R"] = (T[:3, :3] @ np.asarray(pose["R"], float)).tolist()
        pose["t"] = _moved_points(np.asarray(pose["t"], float), T).tolist()
    (dst / "session.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))

    gt = src / "ground_truth"
    if gt.is_dir():
        out = dst / "ground_truth"
        out.mkdir()
        for name in _FRAME_FREE:
            if (gt / name).exists():
                shutil.copy2(gt / name, out / name)
        for name in ("body_vertices.npy", "keypoints3d.npy"):
            if (gt / name).exists():
                save_npy(out / name, _moved_points(np.load(gt / name), T))
        if (gt / "object_poses.npz").exists():
            poses = np.load(gt / "object_poses.npz")
            save_npz(out / "object_poses.npz", R=np.einsum("ij,tjk->tik", T[:3, :3], poses["R"]).astype(poses["R"].dtype),
                     t=_moved_points(poses["t"], T))
        if (gt / "ground.json").exists():
            ground = read_json(gt / "ground.json")
            write_json(out / "ground.json", {"point": _moved_points(np.asarray(ground["point"], float), T).tolist(),
                                             "normal": (T[:3, :3] @ np.asarray(ground["normal"], float)).tolist()})
        if (gt / "info.json").exists():
            info = read_json(gt / "info.json")
            info["reexpressed"] = {"T_new_from_old": T.tolist()}
            write_json(out / "info.json", info)
    return dst


def camera_as_world(session_dir, out_dir, camera: int | str = 0) -> tuple[Path, np.ndarray]:
    """Re-express a session with one camera as the world (OpenCV axes: x right, y down, z forward),
    as BEHAVE, InterCap and most Kinect rigs do. Returns the new folder and T_new_from_old."""
    calib = read_json(Path(session_dir) / "calibration.json")
    cams = calib["cameras"]
    cam = cams[camera] if isinstance(camera, int) else next(c for c in cams if c["name"] == camera)
    T = np.linalg.inv(np.asarray(cam["T_world_from_cam"], np.float64))
    return reexpress(session_dir, out_dir, T), T
