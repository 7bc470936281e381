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
from intercap.session.format import load_mesh_file

# Ground-truth files that hold no world coordinates: copied as they are.
_FRAME_FREE = ("body_faces.npy", "contact.npy")
# physics.npz's world vectors (the generator's keys), turned with the frame; its other keys are frame-free
_PHYSICS_VECTORS = ("gravity", "hand_force", "ground_reaction", "object_ground_force", "flight_acceleration")


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


def _rigid(T_new_from_old) -> np.ndarray:
    T = np.asarray(T_new_from_old, np.float64)
    if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9):
        raise ValueError("T_new_from_old must be a rigid 4x4 transform")
    return T


def reexpress(session_dir, out_dir, T_new_from_old: np.ndarray) -> Path:
    """Write a copy of the session at `out_dir` whose world frame is `T_new_from_old` (4, 4) applied
    to the old one: camera poses, the ground, the object's initial pose and the ground truth's world
    arrays (physics.npz's vectors too) are moved; images, masks, keypoints, meshes and contact labels
    are the same files.
    The ground truth's body_params.npz (model parameters, whose root convention is the model's own)
    is left out of the copy; evaluation compares surfaces, keypoints and poses, never parameters."""
    src, dst = Path(session_dir), Path(out_dir)
    T = _rigid(T_new_from_old)
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
    _write_moved_world(src, dst, T)
    return dst


def reexpress_in_place(session_dir, T_new_from_old: np.ndarray) -> Path:
    """`reexpress` without a copy: the session's own world files are rewritten in the new frame (and its
    ground-truth body_params.npz removed); the frame files are not touched."""
    session = Path(session_dir)
    _write_moved_world(session, session, _rigid(T_new_from_old))
    (session / "ground_truth" / "body_params.npz").unlink(missing_ok=True)
    return session


def _write_moved_world(src: Path, dst: Path, T: np.ndarray) -> None:
    """calibration.json, session.yaml and ground_truth/ of `src` written to `dst` (may be `src`) in the
    frame T (4, 4): every file is read before it is written."""
    calib = read_json(src / "calibration.json")
    for cam in calib["cameras"]:
        cam["T_world_from_cam"] = (T @ np.asarray(cam["T_world_from_cam"], np.float64)).tolist()
    write_json(dst / "calibration.json", calib)

    cfg = yaml.safe_load((src / "session.yaml").read_text())
    if cfg.get("ground"):
        cfg["ground"] = _moved_plane(cfg["ground"], T)
    pose = (cfg.get("object") or {}).get("initial_pose")
    if pose:
        pose["R"] = (T[:3, :3] @ np.asarray(pose["R"], float)).tolist()
        pose["t"] = _moved_points(np.asarray(pose["t"], float), T).tolist()
    (dst / "session.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    for entry in cfg.get("supports") or []:  # support meshes are in world coordinates
        mesh = load_mesh_file(src / entry["mesh"])
        mesh.apply_transform(T)
        target = dst / entry["mesh"]
        if target.exists() or target.is_symlink():
            target.unlink()  # a hard link of the source's file: never written through
        target.parent.mkdir(parents=True, exist_ok=True)
        mesh.export(target)
    if (src / "ground_truth").is_dir():
        _write_moved_ground_truth(src / "ground_truth", dst / "ground_truth", T)


def _moved_plane(plane: dict, T: np.ndarray) -> dict:
    return {"point": _moved_points(np.asarray(plane["point"], float), T).tolist(),
            "normal": (T[:3, :3] @ np.asarray(plane["normal"], float)).tolist()}


def _write_moved_ground_truth(gt: Path, out: Path, T: np.ndarray) -> None:
    """The ground truth's world arrays (bodies, keypoints, object poses, ground, physics vectors) moved by T."""
    out.mkdir(exist_ok=True)
    if out != gt:
        for name in _FRAME_FREE:
            if (gt / name).exists():
                shutil.copy2(gt / name, out / name)
    for name in ("body_vertices.npy", "keypoints3d.npy"):
        if (gt / name).exists():
            save_npy(out / name, _moved_points(np.load(gt / name), T))
    if (gt / "object_poses.npz").exists():
        with np.load(gt / "object_poses.npz") as poses:
            R, t = poses["R"], poses["t"]
        save_npz(out / "object_poses.npz", R=np.einsum("ij,tjk->tik", T[:3, :3], R).astype(R.dtype),
                 t=_moved_points(t, T))
    if (gt / "physics.npz").exists():  # its world vectors turn with the frame (gravity too)
        with np.load(gt / "physics.npz") as physics:
            arrays = {k: physics[k] for k in physics.files}
        for k in _PHYSICS_VECTORS:
            if k in arrays:
                arrays[k] = (arrays[k] @ T[:3, :3].T).astype(arrays[k].dtype)
        save_npz(out / "physics.npz", **arrays)
    if (gt / "ground.json").exists():
        write_json(out / "ground.json", _moved_plane(read_json(gt / "ground.json"), T))
    if (gt / "info.json").exists():
        info = read_json(gt / "info.json")
        if isinstance(info.get("ground"), dict):
            info["ground"] = _moved_plane(info["ground"], T)
        info["reexpressed"] = {"T_new_from_old": T.tolist()}
        write_json(out / "info.json", info)


def camera_frame(session_dir, camera: int | str = 0) -> np.ndarray:
    """T_new_from_old (4, 4) that makes one camera (index or name) of the session the world."""
    cams = read_json(Path(session_dir) / "calibration.json")["cameras"]
    cam = cams[camera] if isinstance(camera, int) else next(c for c in cams if c["name"] == camera)
    return np.linalg.inv(np.asarray(cam["T_world_from_cam"], np.float64))


def camera_as_world(session_dir, out_dir, camera: int | str = 0) -> tuple[Path, np.ndarray]:
    """Re-express a session with one camera as the world (OpenCV axes: x right, y down, z forward),
    as BEHAVE, InterCap and most Kinect rigs do. Returns the new folder and T_new_from_old."""
    T = camera_frame(session_dir, camera)
    return reexpress(session_dir, out_dir, T), T
