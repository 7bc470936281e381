"""Analytic physics cases written straight into a results folder (no rendering): the tests and
tools/bench_physics.py check the `physics` stage against them.

`write_static_hold`: an anny body standing still in its rest pose on the floor z = 0 (world z
up), holding a box of known mass still between its hands, with Kinect-like noise on the fitted
trajectories (`noise_m` on the body's and object's translations, `noise_rad` on their rotations
and the body's joints). Truth: the hands carry m g, the floor (M + m) g. The session folder is a
tiny valid one (one 64x48 camera) whose session.yaml gives the floor and the masses.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh
import yaml

from intercap.io.files import save_npy, save_npz, write_json

BOX = (0.2, 0.15, 0.15)


def write_tiny_camera_session(root: Path, num_frames: int, *, object_mass_kg: float | None = 2.0,
                              body_mass_kg: float | None = None, ground: bool = True, density: float | None = None) -> Path:
    """A minimal valid session: one 64x48 camera with blank frames, a box object, the floor z = 0."""
    import cv2

    root = Path(root)
    for sub in ("color", "depth"):
        (root / "cam0" / sub).mkdir(parents=True, exist_ok=True)
    for f in range(num_frames):
        cv2.imwrite(str(root / "cam0" / "color" / f"{f:06d}.png"), np.zeros((48, 64, 3), np.uint8))
        cv2.imwrite(str(root / "cam0" / "depth" / f"{f:06d}.png"), np.full((48, 64), 2000, np.uint16))
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # looking along +y
    T[:3, 3] = [0, -3, 1]
    calib = {"cameras": [{"name": "cam0", "width": 64, "height": 48, "K": [[70, 0, 31.5], [0, 70, 23.5], [0, 0, 1]],
                          "dist": [], "T_world_from_cam": T.tolist()}]}
    (root / "calibration.json").write_text(json.dumps(calib))
    trimesh.creation.box(extents=BOX).export(root / "object.ply")
    obj = {"mesh": "object.ply", "name": "box"}
    if object_mass_kg is not None:
        obj["mass_kg"] = float(object_mass_kg)
    if density is not None:
        obj["density_kg_m3"] = float(density)
    cfg = {"fps": 30, "object": obj, "frames": {"start": 0, "end": num_frames - 1}, "body": {"model": "anny"}}
    if body_mass_kg is not None:
        cfg["body"]["mass_kg"] = float(body_mass_kg)
    if ground:
        cfg["ground"] = {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]}
    (root / "session.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return root


def _small_rotations(rng, n: int, sigma: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rng.normal(0, sigma, (n, 3))).as_matrix()


def write_static_hold(model, out_dir: Path, num_frames: int = 30, noise_m: float = 0.002, noise_rad: float = 0.002,
                      seed: int = 0, ground_json: bool = True) -> dict:
    """The fitted results of a still body holding the box still (see the module docstring) in
    OUT/: body_params.npz, body_vertices.npy, object_poses.npz, contact.npy, contact/contact.npz
    and prepare/ground.json. Returns the truth: rest_min_z, hands (2, 3) palm centres."""
    import torch

    rng = np.random.default_rng(seed)
    out_dir = Path(out_dir)
    T = num_frames
    p = model.init_params(T)
    with torch.no_grad():
        rest = model(model.init_params(1))
    v0 = rest.vertices[0].double().numpy()
    lift = -v0[:, 2].min()
    hands = np.stack([v0[model.contact_regions[r].numpy()].mean(0) for r in ("left_hand", "right_hand")])
    p.transl[:] = torch.as_tensor([0.0, 0.0, lift]) + torch.as_tensor(rng.normal(0, noise_m, (T, 3)), dtype=p.transl.dtype)
    p.global_orient[:] = torch.as_tensor(rng.normal(0, noise_rad, (T, 3)), dtype=p.transl.dtype)
    p.body_pose[:] = torch.as_tensor(rng.normal(0, noise_rad, p.body_pose.shape), dtype=p.transl.dtype)
    arrays = p.to_numpy_dict()
    with torch.no_grad():
        verts = model(p).vertices.numpy()
    save_npz(out_dir / "body_params.npz", model=np.array(model.name), valid=np.ones(T, bool),
             shape_mean=arrays["shape"][0], **arrays)
    save_npy(out_dir / "body_vertices.npy", verts.astype(np.float32))
    centre = hands.mean(0) + np.array([0.0, 0.0, lift])
    R = _small_rotations(rng, T, noise_rad)
    t = centre + rng.normal(0, noise_m, (T, 3))
    save_npz(out_dir / "object_poses.npz", R=R, t=t, valid=np.ones(T, bool), frame_ids=np.arange(T))
    save_npy(out_dir / "contact.npy", np.ones(T, bool))
    names = list(model.contact_regions)
    region_contact = np.zeros((T, len(names)), bool)
    region_contact[:, [names.index("left_hand"), names.index("right_hand")]] = True
    save_npz(out_dir / "contact" / "contact.npz", contact=np.ones(T, bool), method=np.array("annotated"),
             frame_ids=np.arange(T), region_names=np.array(names), region_contact=region_contact,
             region_distance_m=np.zeros((T, len(names))), invalid=np.zeros(T, bool))
    if ground_json:
        write_json(out_dir / "prepare" / "ground.json", {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0],
                                                         "inlier_ratio": 1.0, "rmse_m": 0.0, "source": "test"})
    return {"lift": lift, "hands": hands + [0, 0, lift]}
