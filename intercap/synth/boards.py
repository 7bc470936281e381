"""Synthetic calibration recordings: a ChArUco or checkerboard board moved through a camera rig.

Every output pixel is traced backwards (undistort it with the camera's own
lens model, intersect its ray with the board plane and the floor, sample the
board texture), so the images carry the exact distortion the calibration must
model. Depth is the traced surface's camera z (uint16 mm), so the depth ICP
check has data. The session holds intrinsics only (identity poses); the truth
lies in ground_truth/calibration.json and ground_truth/board_poses.npz.

    from intercap.synth.boards import BoardSpec, board_rig, render_board_session
    render_board_session(board_rig(cameras=4), BoardSpec(), "out/boards", poses=10)
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from intercap.synth.generator import WORLD_NOTE, Camera, SynthConfig, ring_cameras


@dataclass
class BoardSpec:
    """A calibration board. squares = (columns, rows) of chessboard squares; lengths in metres.
    Board frame (OpenCV's): origin at the outer corner of the top-left square, x along the
    columns, y along the rows, z into the board (its printed side faces -z)."""

    kind: str = "charuco"  # charuco | checkerboard
    squares: tuple = (7, 5)
    square_m: float = 0.04
    marker_m: float = 0.03
    dictionary: str = "DICT_5X5_100"

    def size_m(self) -> tuple[float, float]:
        return self.squares[0] * self.square_m, self.squares[1] * self.square_m


def board_texture(spec: BoardSpec, px_per_square: int = 80) -> np.ndarray:
    """(H, W) uint8 image of the printed pattern, exactly squares x px_per_square pixels
    (the white print margin is added by the renderer)."""
    cols, rows = spec.squares
    size = (cols * px_per_square, rows * px_per_square)
    if spec.kind == "charuco":
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
        board = cv2.aruco.CharucoBoard((cols, rows), spec.square_m, spec.marker_m, dictionary)
        return board.generateImage(size, marginSize=0, borderBits=1)
    if spec.kind == "checkerboard":
        i, j = np.meshgrid(np.arange(size[0]) // px_per_square, np.arange(size[1]) // px_per_square)
        return np.where((i + j) % 2 == 0, 0, 255).astype(np.uint8)  # top-left square black
    raise ValueError(f"unknown board kind {spec.kind!r}; use charuco or checkerboard")


def board_rig(cameras: int = 4, width: int = 640, height: int = 480, radius: float = 1.8, seed: int = 0) -> list[Camera]:
    """A ring of cameras (the generator's ring_cameras, closer in) around a board held at ~1 m."""
    cfg = SynthConfig(cameras=cameras, width=width, height=height, ring_radius=radius, ring_height=1.5,
                      look_at=(0.0, 0.0, 1.0), focal_scale=0.8, seed=seed)
    return ring_cameras(cfg)


def board_poses(cams: list[Camera], spec: BoardSpec, n: int, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) T_world_from_board: the board's printed side faces, in turn, each pair of
    neighbouring cameras (around the ring), tilted and moved a little at random."""
    rng = np.random.default_rng([seed, 202])
    centres = np.array([c.T_world_from_cam[:3, 3] for c in cams])
    middle = centres.mean(axis=0)
    az = np.arctan2(centres[:, 1] - middle[1], centres[:, 0] - middle[0])
    order = np.argsort(az)
    w, h = spec.size_m()
    poses = []
    for k in range(n):
        if len(cams) == 1:
            facing = az[0]
        else:
            a, b = order[k % len(cams)], order[(k + 1) % len(cams)]
            facing = np.angle(np.exp(1j * az[a]) + np.exp(1j * az[b]))  # bisector of a neighbouring pair
        facing += np.radians(rng.uniform(-6, 6))
        front = np.array([np.cos(facing), np.sin(facing), 0.0])  # printed side's outward normal
        z_b = -front
        down = np.array([0.0, 0.0, -1.0])
        y_b = down - (down @ z_b) * z_b
        y_b /= np.linalg.norm(y_b)
        R = np.column_stack([np.cross(y_b, z_b), y_b, z_b])
        tilt = Rotation.from_euler("xyz", rng.uniform(-10, 10, 3) * np.array([1, 1, 3]), degrees=True).as_matrix()
        R = R @ tilt  # tilted about its own axes, rolled a little more in its plane
        centre = np.array([0.0, 0.0, 1.0]) + rng.uniform(-0.15, 0.15, 3)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = centre - R @ np.array([w / 2, h / 2, 0.0])
        poses.append(T)
    return np.stack(poses)


def camera_rays(cam: Camera) -> np.ndarray:
    """(H*W, 3) float32 undistorted ray of each pixel (row-major) in camera coordinates (z = 1)."""
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel()], -1)[:, None, :]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    xy = cv2.undistortPoints(pix, cam.K, np.asarray(cam.dist, float), None, None, None, crit)[:, 0]
    return np.concatenate([xy, np.ones_like(xy[:, :1])], axis=-1).astype(np.float32)


def _plane_hit(rays: np.ndarray, T_cam_from_plane: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays (N, 3) from the camera centre against the plane z=0 of a frame: camera depth z
    (N,) (inf where missed or behind), plane coordinates (N, 2), and whether the ray
    meets the plane's +z side (N,) bool (seen from behind, for a board)."""
    T = T_cam_from_plane.astype(np.float32)
    n, p0 = T[:3, 2], T[:3, 3]
    denom = rays @ n  # (N,)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (p0 @ n) / denom  # ray parameter = camera z since rays have z = 1
    ok = np.isfinite(s) & (s > 1e-3)
    s = np.where(ok, s, np.float32(np.inf))
    local = (rays * np.where(ok, s, 0)[:, None] - p0) @ T[:3, :2]  # (N, 2) in the plane's frame
    return s, local, denom < 0


def floor_view(cam: Camera, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 colour and (N,) depth (m, 0 = none) of the mottled grey floor z = 0
    (4 m around the origin) against a plain background."""
    z_floor, xy, _ = _plane_hit(rays, np.linalg.inv(cam.T_world_from_cam))
    rgb = np.empty((len(rays), 3), np.float32)
    rgb[:] = (150, 160, 170)
    fl = np.isfinite(z_floor) & (np.abs(xy) < 4.0).all(axis=1)
    mottle = 128 + 18 * np.sin(7.3 * xy[fl, 0]) * np.cos(5.1 * xy[fl, 1]) + 8 * np.sin(23 * xy[fl].sum(1))
    rgb[fl] = mottle[:, None] * np.array([0.9, 0.85, 0.8], np.float32)
    return rgb, np.where(fl, z_floor, 0).astype(np.float32)


def render_board_view(cam: Camera, rays: np.ndarray, floor: tuple, spec: BoardSpec, texture: np.ndarray,
                      T_world_from_board, px_per_square: int) -> tuple[np.ndarray, np.ndarray]:
    """One camera's (H, W, 3) float colour and (H, W) depth in metres (0 = none): the board
    (T_world_from_board None: none) in front of `floor` (floor_view's colour and depth)."""
    H, W = cam.height, cam.width
    rgb, depth = floor[0].copy(), floor[1].copy()
    if T_world_from_board is not None:
        z_b, bxy, back = _plane_hit(rays, np.linalg.inv(cam.T_world_from_cam) @ T_world_from_board)
        w, h = spec.size_m()
        margin = spec.square_m * 0.75  # white print margin around the pattern
        on = (np.isfinite(z_b) & (bxy[:, 0] > -margin) & (bxy[:, 0] < w + margin) & (bxy[:, 1] > -margin)
              & (bxy[:, 1] < h + margin) & ((depth == 0) | (z_b < depth)))
        ppm = px_per_square / spec.square_m
        mx = (bxy[:, 0] * ppm - 0.5).reshape(H, W)
        my = (bxy[:, 1] * ppm - 0.5).reshape(H, W)
        shade = cv2.remap(texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=255)
        shade = 20 + shade.reshape(-1).astype(np.float32) * (215 / 255)  # printed black is not 0, paper not 255
        front = on & ~back
        rgb[front] = shade[front, None]
        rgb[on & back] = (60, 55, 50)  # the board's unprinted back
        depth[on] = z_b[on]
    return rgb.reshape(H, W, 3), depth.reshape(H, W)


def render_board_session(cams: list[Camera], spec: BoardSpec, out_dir, poses: int = 10, seed: int = 0,
                         supersample: int = 2, hidden: tuple = (), depth_sigma_m: float = 0.0) -> Path:
    """Write a calibration recording of `poses` board poses seen by `cams` as a session folder.

    calibration.json holds the intrinsics and identity poses (unknown); ground_truth/ holds
    calibration.json (the true poses) and board_poses.npz (T_world_from_board (F, 4, 4)).
    Cameras named in `hidden` never see the board (it is left out of their images).
    Images are rendered `supersample` times larger and shrunk (anti-aliasing)."""
    out = Path(out_dir)
    T_boards = board_poses(cams, spec, poses, seed)
    px = 80
    texture = board_texture(spec, px)
    texture = cv2.GaussianBlur(texture, (0, 0), 1.0)
    rng = np.random.default_rng([seed, 303])
    s = int(supersample)
    for cam in cams:
        big = Camera(cam.name, cam.width * s, cam.height * s,
                     np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1]]) @ cam.K, cam.dist,
                     cam.T_world_from_cam)
        big_rays, rays = camera_rays(big), camera_rays(cam)
        big_floor, floor = floor_view(big, big_rays), floor_view(cam, rays)
        (out / cam.name / "color").mkdir(parents=True, exist_ok=True)
        (out / cam.name / "depth").mkdir(parents=True, exist_ok=True)
        for f, T in enumerate(T_boards):
            T = None if cam.name in hidden else T
            colour, _ = render_board_view(big, big_rays, big_floor, spec, texture, T, px)
            colour = cv2.resize(colour, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
            colour = np.clip(colour + rng.normal(0, 1.5, colour.shape), 0, 255).astype(np.uint8)
            # depth traced at the camera's own pixels: no blending across edges
            _, depth = render_board_view(cam, rays, floor, spec, texture, T, px)
            if depth_sigma_m > 0:
                depth = np.where(depth > 0, depth + rng.normal(0, depth_sigma_m, depth.shape), 0.0)
            depth = np.clip(np.round(depth * 1000), 0, 65535).astype(np.uint16)
            cv2.imwrite(str(out / cam.name / "color" / f"{f:06d}.png"), cv2.cvtColor(colour, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(out / cam.name / "depth" / f"{f:06d}.png"), depth)
    unknown = [{**c.to_json(), "T_world_from_cam": np.eye(4).tolist()} for c in cams]
    (out / "calibration.json").write_text(json.dumps({"world": WORLD_NOTE, "cameras": unknown}, indent=2) + "\n")
    (out / "session.yaml").write_text(yaml.safe_dump({"fps": 5}))
    gt = out / "ground_truth"
    gt.mkdir(exist_ok=True)
    (gt / "calibration.json").write_text(json.dumps({"world": WORLD_NOTE, "cameras": [c.to_json() for c in cams]},
                                                    indent=2) + "\n")
    np.savez(gt / "board_poses.npz", T_world_from_board=T_boards, kind=spec.kind, squares=np.array(spec.squares),
             square_m=spec.square_m, marker_m=spec.marker_m, dictionary=spec.dictionary)
    return out
