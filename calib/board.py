"""Rig calibration from a recording of a ChArUco or checkerboard board (`intercap calibrate`).

Input: a session folder of ours whose calibration.json has each camera's
intrinsics (K, dist, size; its poses are ignored) and, per camera, color/ (and
depth/) frames of a board moved through the shared view.

1. Per camera and frame: the board's corners (cv2.aruco CharucoDetector, or
   findChessboardCornersSB with the corner order fixed by the squares' colours)
   and the board pose by solvePnP (IPPE, then Levenberg-Marquardt) with the
   camera's own distortion.
2. Per pair of cameras, their relative pose from the frames both see (rotation
   mean, translation median). A maximum spanning tree over the camera graph,
   weighted by the number of shared frames, chains them into one frame.
3. One least-squares bundle adjustment (scipy, soft-L1) over every camera pose
   and every board pose shared by two or more cameras, minimising the corner
   reprojection error in pixels.
4. The depth ICP check (intercap.calib.alignment.check_calibration) of each
   neighbouring pair's fused depth clouds gives the depth agreement (mm); with
   depth refinement, the pairs' ICP corrections are spread over the cameras by
   least squares and kept where they make the depth agree better.

World frame: `camera` (default) = the first camera of calibration.json
(identity pose); `board` = the board's pose in the first frame seen by two or
more cameras (origin at the pattern's outer top-left corner, x along its
columns, y along its rows, z into the board: flip z to get "up" when the board
lay flat on the floor face up).
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from intercap.calib.alignment import check_calibration, neighbour_pairs, rotation_angle_deg
from intercap.calib.options import add_calibrate_arguments  # noqa: F401 - re-exported

log = logging.getLogger(__name__)
IMAGE_EXTS = (".png", ".jpg", ".jpeg")


class CalibrationError(ValueError):
    """The recording cannot calibrate the rig (a camera never sees the board, ...)."""


# ----------------------------------------------------------------------------- boards
@dataclass
class Board:
    """A calibration board: squares = (columns, rows) of chessboard squares, lengths in metres.
    Board frame (OpenCV's): origin at the outer top-left corner, x along the columns, y along
    the rows, z into the board. object_points (N, 3): inner corner k (row-major) in that frame."""

    kind: str = "charuco"
    squares: tuple = (7, 5)
    square_m: float = 0.04
    marker_m: float = 0.03
    dictionary: str = "DICT_5X5_100"
    object_points: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        cols, rows = (int(v) for v in self.squares)
        if cols < 3 or rows < 3:
            raise ValueError(f"board squares must be at least 3x3, got {cols}x{rows}")
        self.squares = (cols, rows)
        i, j = np.meshgrid(np.arange(1, cols), np.arange(1, rows))
        self.object_points = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], -1) * self.square_m
        if self.kind == "charuco":
            if not hasattr(cv2.aruco, self.dictionary):
                raise ValueError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_5X5_100, DICT_4X4_50)")
            if not 0 < self.marker_m < self.square_m:
                raise ValueError(f"marker size {self.marker_m} m must be below the square size {self.square_m} m")
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
            self._board = cv2.aruco.CharucoBoard((cols, rows), self.square_m, self.marker_m, dictionary)
            self._detector = cv2.aruco.CharucoDetector(self._board)
            self.object_points = np.asarray(self._board.getChessboardCorners(), np.float64).reshape(-1, 3)
        elif self.kind == "checkerboard":
            if cols % 2 == 1 and rows % 2 == 1:
                raise ValueError(f"a {cols}x{rows} checkerboard looks the same turned by 180 deg: "
                                 "use an even number of squares along one side")
        else:
            raise ValueError(f"unknown board kind {self.kind!r}; use charuco or checkerboard")

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corner ids (N,) and sub-pixel image positions (N, 2) found in a grey image (N may be 0)."""
        if self.kind == "charuco":
            corners, ids, _, _ = self._detector.detectBoard(gray)
            if ids is None or len(ids) == 0:
                return np.zeros(0, int), np.zeros((0, 2))
            return ids.ravel().astype(int), corners.reshape(-1, 2).astype(np.float64)
        cols, rows = self.squares
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCornersSB(gray, (cols - 1, rows - 1), flags=flags)
        if not found:
            return np.zeros(0, int), np.zeros((0, 2))
        grid = corners.reshape(rows - 1, cols - 1, 2).astype(np.float64)
        return np.arange(grid.shape[0] * grid.shape[1]), self._checker_order(gray, grid).reshape(-1, 2)

    def _checker_order(self, gray: np.ndarray, grid: np.ndarray) -> np.ndarray:
        """The detected corner grid (rows-1, cols-1, 2) reordered to match the board: of the
        orderings that keep the board's handedness (seen from its printed side), the one whose
        squares' sampled brightness best matches the pattern (top-left square black)."""
        cols, rows = self.squares
        best, best_score = grid, -np.inf
        for g in (grid, grid[::-1, ::-1], grid[::-1, :], grid[:, ::-1]):
            ex, ey = g[0, 1] - g[0, 0], g[1, 0] - g[0, 0]
            if ex[0] * ey[1] - ex[1] * ey[0] <= 0:  # mirrored
                continue
            H, _ = cv2.findHomography(self.object_points[:, :2], g.reshape(-1, 2))
            i, j = np.meshgrid(np.arange(cols), np.arange(rows))
            centres = np.stack([i.ravel() + 0.5, j.ravel() + 0.5], -1) * self.square_m
            uv = cv2.perspectiveTransform(centres[:, None], H)[:, 0]
            inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < gray.shape[1] - 1) & (uv[:, 1] < gray.shape[0] - 1)
            if inside.sum() < 4:
                continue
            value = gray[uv[inside, 1].round().astype(int), uv[inside, 0].round().astype(int)].astype(float)
            expected = np.where(((i + j).ravel() % 2 == 0), -1.0, 1.0)[inside]  # black = -1
            score = float(np.corrcoef(value, expected)[0, 1]) if value.std() > 0 else -np.inf
            if score > best_score:
                best, best_score = g, score
        return best


# ----------------------------------------------------------------------------- recording
@dataclass
class RigCamera:
    name: str
    width: int
    height: int
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (n,)
    color: dict  # frame id -> Path
    depth: dict  # frame id -> Path


def load_recording(session_dir) -> tuple[list[RigCamera], dict]:
    """Cameras (intrinsics and frame files) of a calibration recording and its calibration.json."""
    root = Path(session_dir)
    calib_path = root / "calibration.json"
    if not calib_path.exists():
        raise FileNotFoundError(f"{calib_path}: missing (the cameras' intrinsics are needed)")
    try:
        calib = json.loads(calib_path.read_text())
        entries = calib["cameras"]
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{calib_path}: not a calibration.json with a 'cameras' list ({exc})") from None
    cams = []
    for i, e in enumerate(entries):
        try:
            K = np.asarray(e["K"], np.float64).reshape(3, 3)
            dist = np.asarray(e.get("dist") or [], np.float64).ravel()
            name, width, height = str(e["name"]), int(e["width"]), int(e["height"])
        except (KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"{calib_path}: camera {i}: bad or missing intrinsics ({exc})") from None

        def frames(kind):
            folder = root / name / kind
            files = sorted(p for p in folder.glob("*") if p.suffix.lower() in IMAGE_EXTS) if folder.is_dir() else []
            return {int(p.stem): p for p in files if p.stem.isdigit()}

        cams.append(RigCamera(name, width, height, K, dist, frames("color"), frames("depth")))
        if not cams[-1].color:
            raise FileNotFoundError(f"{root / name / 'color'}: no colour frames for camera {name}")
    if len(cams) < 2:
        raise ValueError(f"{calib_path}: a rig needs two or more cameras, found {len(cams)}")
    return cams, calib


# ----------------------------------------------------------------------------- poses
def to_T(rvec, tvec) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.ravel(rvec)).as_matrix()
    T[:3, 3] = np.ravel(tvec)
    return T


def board_pose(obj: np.ndarray, uv: np.ndarray, cam: RigCamera, min_corners: int) -> tuple[np.ndarray, float] | None:
    """(T_cam_from_board (4, 4), RMS reprojection px) of one view, or None when too few or
    collinear corners make the pose unreliable."""
    if len(uv) < min_corners:
        return None
    spread = np.linalg.svd(obj[:, :2] - obj[:, :2].mean(0), compute_uv=False)
    if spread[1] < 0.1 * spread[0]:  # (nearly) one row of corners: the pose is ill-posed
        return None
    ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, uv, cam.K, cam.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok or not len(rvecs):
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, uv, cam.K, cam.dist, rvecs[0], tvecs[0])
    proj, _ = cv2.projectPoints(obj, rvec, tvec, cam.K, cam.dist)
    rms = float(np.sqrt(((proj.reshape(-1, 2) - uv) ** 2).sum(1).mean()))
    return to_T(rvec, tvec), rms


def average_transforms(Ts: list[np.ndarray]) -> np.ndarray:
    """Robust mean of rigid transforms: rotation mean, per-axis median translation."""
    Ts = np.stack(Ts)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_matrix(Ts[:, :3, :3]).mean().as_matrix()
    T[:3, 3] = np.median(Ts[:, :3, 3], axis=0)
    return T


def chain_cameras(names: list[str], views: dict, root: int = 0) -> np.ndarray:
    """(C, 4, 4) T_root_from_cam by a maximum spanning tree over the camera graph (edge weight:
    frames both cameras see), each edge's relative pose averaged over those frames.
    views: (camera, frame) -> T_cam_from_board. Raises CalibrationError naming cameras that
    never see the board or share no frame with the rest."""
    C = len(names)
    per_cam = [{f: T for (c, f), T in views.items() if c == i} for i in range(C)]
    blind = [names[i] for i in range(C) if not per_cam[i]]
    if blind:
        raise CalibrationError(f"camera{'s' if len(blind) > 1 else ''} {', '.join(blind)} never "
                               f"{'see' if len(blind) > 1 else 'sees'} the board (no frame with a usable detection)")
    shared = np.zeros((C, C), int)
    for a in range(C):
        for b in range(a + 1, C):
            shared[a, b] = shared[b, a] = len(per_cam[a].keys() & per_cam[b].keys())
    T = np.full((C, 4, 4), np.nan)
    T[root] = np.eye(4)
    in_tree = {root}
    while len(in_tree) < C:
        best = max(((shared[a, b], a, b) for a in in_tree for b in range(C) if b not in in_tree), default=(0, 0, 0))
        n, a, b = best
        if n == 0:
            lost = [names[i] for i in range(C) if i not in in_tree]
            raise CalibrationError(f"camera{'s' if len(lost) > 1 else ''} {', '.join(lost)} "
                                   f"share{'' if len(lost) > 1 else 's'} no board frame with "
                                   f"{', '.join(names[i] for i in sorted(in_tree))}: show the board to both at once")
        common = sorted(per_cam[a].keys() & per_cam[b].keys())
        T_a_from_b = average_transforms([per_cam[a][f] @ np.linalg.inv(per_cam[b][f]) for f in common])
        T[b] = T[a] @ T_a_from_b
        in_tree.add(b)
    return T


# ----------------------------------------------------------------------------- bundle adjustment
def project_points(P_cam: np.ndarray, cam: RigCamera) -> np.ndarray:
    """Camera-frame points (N, 3) -> distorted pixels (N, 2) (OpenCV's model, any length of dist)."""
    uv, _ = cv2.projectPoints(P_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    return uv.reshape(-1, 2)


def bundle_adjust(cams: list[RigCamera], board: Board, obs: dict, T_world_from_cam: np.ndarray,
                  T_world_from_board: dict, fixed: int = 0) -> tuple[np.ndarray, dict, np.ndarray, np.ndarray]:
    """Joint refinement of camera poses (all but `fixed`) and board poses by reprojection error.

    obs: (camera, frame) -> (ids (N,), uv (N, 2)). Returns refined T_world_from_cam (C, 4, 4),
    T_world_from_board {frame: (4, 4)}, and per observation its camera (M,) and pixel error (M,)."""
    C = len(cams)
    frames = sorted(T_world_from_board)
    frame_index = {f: i for i, f in enumerate(frames)}
    keys = [k for k in sorted(obs) if k[1] in frame_index]
    cam_of = np.concatenate([np.full(len(obs[k][0]), k[0]) for k in keys])  # (M,)
    frame_of = np.concatenate([np.full(len(obs[k][0]), frame_index[k[1]]) for k in keys])
    pts = np.concatenate([board.object_points[obs[k][0]] for k in keys])  # (M, 3)
    uv = np.concatenate([obs[k][1] for k in keys])  # (M, 2)
    free = [c for c in range(C) if c != fixed]
    slot = {c: i for i, c in enumerate(free)}

    def pack():
        x = []
        for c in free:
            T = np.linalg.inv(T_world_from_cam[c])  # cam_from_world
            x += [Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]]
        for f in frames:
            T = T_world_from_board[f]
            x += [Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]]
        return np.concatenate(x)

    T_fixed = np.linalg.inv(T_world_from_cam[fixed])

    def unpack(x):
        cam_params = x[: 6 * len(free)].reshape(-1, 6)
        board_params = x[6 * len(free):].reshape(-1, 6)
        R_c = np.repeat(T_fixed[None, :3, :3], C, 0)
        t_c = np.repeat(T_fixed[None, :3, 3], C, 0)
        if free:
            R_c[free] = Rotation.from_rotvec(cam_params[:, :3]).as_matrix()
            t_c[free] = cam_params[:, 3:]
        return R_c, t_c, Rotation.from_rotvec(board_params[:, :3]).as_matrix(), board_params[:, 3:]

    def residuals(x):
        R_c, t_c, R_b, t_b = unpack(x)
        P_w = np.einsum("mij,mj->mi", R_b[frame_of], pts) + t_b[frame_of]  # (M, 3)
        P_c = np.einsum("mij,mj->mi", R_c[cam_of], P_w) + t_c[cam_of]
        out = np.empty_like(uv)
        for c in range(C):
            sel = cam_of == c
            out[sel] = project_points(P_c[sel], cams[c]) - uv[sel]
        return out.ravel()

    M = len(uv)
    n_params = 6 * (len(free) + len(frames))
    sparsity = lil_matrix((2 * M, n_params), dtype=np.int8)
    rows = np.arange(2 * M)
    for m_off in (0, 1):
        r = rows[m_off::2]
        for k in range(6):
            sparsity[r, 6 * len(free) + 6 * frame_of + k] = 1
            has = cam_of != fixed
            sparsity[r[has], 6 * np.array([slot.get(c, 0) for c in cam_of[has]]) + k] = 1
    result = least_squares(residuals, pack(), jac_sparsity=sparsity, loss="soft_l1", f_scale=1.0,
                           x_scale="jac", method="trf", max_nfev=200)
    R_c, t_c, R_b, t_b = unpack(result.x)
    T_cw = np.tile(np.eye(4), (C, 1, 1))
    T_cw[:, :3, :3], T_cw[:, :3, 3] = R_c, t_c
    boards = {}
    for f, i in frame_index.items():
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_b[i], t_b[i]
        boards[f] = T
    err = np.linalg.norm(residuals(result.x).reshape(-1, 2), axis=1)  # plain pixels, not the robust loss
    return np.linalg.inv(T_cw), boards, cam_of, err


# ----------------------------------------------------------------------------- depth
def depth_clouds(cams: list[RigCamera], T_world_from_cam: np.ndarray, frames: list[int], stride: int = 4,
                 max_depth_m: float = 6.0) -> list[np.ndarray]:
    """Per camera, the world points (N_c, 3) of its depth maps over `frames`, fused."""
    clouds = []
    for c, cam in enumerate(cams):
        v, u = np.mgrid[0:cam.height:stride, 0:cam.width:stride]
        pix = np.stack([u.ravel(), v.ravel()], -1).astype(np.float64)[:, None]
        rays = cv2.undistortPoints(pix, cam.K, cam.dist).reshape(-1, 2)
        pts = []
        for f in frames:
            path = cam.depth.get(f)
            depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path else None
            if depth is None or depth.shape[:2] != (cam.height, cam.width):
                continue
            z = depth[::stride, ::stride].ravel().astype(np.float64) / 1000.0
            ok = (z > 0.2) & (z < max_depth_m)
            P = np.column_stack([rays[ok] * z[ok, None], z[ok]])
            pts.append(P @ T_world_from_cam[c][:3, :3].T + T_world_from_cam[c][:3, 3])
        clouds.append(np.concatenate(pts) if pts else np.zeros((0, 3)))
    return clouds


def depth_agreement(cams, T_world_from_cam, frames, voxel_size=0.02, max_distance=0.05):
    """The ICP check's pairs and, per camera, the mean over its pairs of their median
    point-to-plane distance before ICP (mm; NaN without overlapping depth)."""
    clouds = depth_clouds(cams, T_world_from_cam, frames)
    names = [c.name for c in cams]
    pairs = check_calibration(clouds, names, T_world_from_cam[:, :3, 3], max_distance=max_distance,
                              voxel_size=voxel_size)
    per_cam = []
    for name in names:
        vals = [p.median_distance_mm for p in pairs if name in (p.cam_a, p.cam_b) and np.isfinite(p.median_distance_mm)]
        per_cam.append(float(np.mean(vals)) if vals else float("nan"))
    return pairs, np.array(per_cam)


def spread_corrections(pairs, names: list[str], fixed: int) -> np.ndarray:
    """(C, 4, 4) world-frame corrections D_c (D_fixed = I) that best explain the pairs' ICP
    corrections (a onto b ~ D_b^-1 D_a), linearised as twists about the world origin."""
    C = len(names)
    index = {n: i for i, n in enumerate(names)}
    rows, rhs = [], []
    for p in pairs:
        if not np.isfinite(p.median_distance_mm):
            continue
        a, b = index[p.cam_a], index[p.cam_b]
        row = np.zeros((6, 6 * C))
        row[:, 6 * a:6 * a + 6] += np.eye(6)
        row[:, 6 * b:6 * b + 6] -= np.eye(6)
        rows.append(row)
        rhs.append(np.concatenate([Rotation.from_matrix(p.correction[:3, :3]).as_rotvec(), p.correction[:3, 3]]))
    gauge = np.zeros((6, 6 * C))
    gauge[:, 6 * fixed:6 * fixed + 6] = np.eye(6)
    A = np.vstack(rows + [gauge * 10])
    y = np.concatenate(rhs + [np.zeros(6)])
    x = np.linalg.lstsq(A, y, rcond=None)[0].reshape(C, 6)
    return np.stack([to_T(xi[:3], xi[3:]) for xi in x])


# ----------------------------------------------------------------------------- driver
@dataclass
class RigCalibration:
    names: list
    T_world_from_cam: np.ndarray  # (C, 4, 4)
    reprojection_px: np.ndarray  # (C,) RMS over the camera's corners in the bundle adjustment
    views: np.ndarray  # (C,) frames in which the camera found the board
    depth_mm: np.ndarray  # (C,) depth agreement with its neighbours (mean median point-to-plane, mm)
    depth_refined: bool
    frames_used: int  # board frames seen by two or more cameras
    seconds: float
    pairs: list = field(default_factory=list, repr=False)
    shared_frame_ids: list = field(default_factory=list)  # frames two or more cameras see (the first: --world board)


def calibrate_rig(session_dir, board: Board, world: str = "camera", depth_refine: bool = True,
                  depth_frames: int = 6, min_corners: int = 6, max_view_error_px: float = 3.0,
                  progress=None) -> tuple[RigCalibration, list[RigCamera], dict]:
    """Extrinsics of the rig recorded in session_dir (see the module's docstring)."""
    if world not in ("camera", "board"):
        raise ValueError(f"world must be 'camera' or 'board', got {world!r}")
    start = time.perf_counter()
    cams, calib = load_recording(session_dir)
    names = [c.name for c in cams]
    obs, views = {}, {}
    for c, cam in enumerate(cams):
        for f, path in sorted(cam.color.items()):
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                log.warning("%s: unreadable image, skipped", path)
                continue
            ids, uv = board.detect(gray)
            pose = board_pose(board.object_points[ids], uv, cam, min_corners) if len(ids) else None
            if pose is None or pose[1] > max_view_error_px:
                continue
            obs[(c, f)] = (ids, uv)
            views[(c, f)] = pose[0]
        log.info("%s: board found in %d of %d frames", cam.name, sum(k[0] == c for k in views), len(cam.color))
    T_world_from_cam = chain_cameras(names, views)
    # board poses of frames two or more cameras see, from the view with most corners
    seen_by: dict = {}
    for c, f in views:
        seen_by.setdefault(f, []).append(c)
    shared = sorted(f for f, cs in seen_by.items() if len(cs) >= 2)
    boards = {}
    for f in shared:
        c = max(seen_by[f], key=lambda c: len(obs[(c, f)][0]))
        boards[f] = T_world_from_cam[c] @ views[(c, f)]
    T_world_from_cam, boards, cam_of, err = bundle_adjust(cams, board, obs, T_world_from_cam, boards)
    if world == "board":
        T_new_from_old = np.linalg.inv(boards[shared[0]])
        T_world_from_cam = T_new_from_old @ T_world_from_cam
    reproj = np.array([np.sqrt(np.mean(err[cam_of == c] ** 2)) if (cam_of == c).any() else np.nan
                       for c in range(len(cams))])
    n_views = np.array([sum(k[0] == c for k in views) for c in range(len(cams))])

    has_depth = [f for f in shared if all(f in cam.depth for cam in cams)] or shared
    pick = [has_depth[i] for i in np.unique(np.linspace(0, len(has_depth) - 1, min(depth_frames, len(has_depth))).round().astype(int))]
    pairs, depth_mm = depth_agreement(cams, T_world_from_cam, pick)
    refined = False
    if depth_refine and any(np.isfinite(p.median_distance_mm) for p in pairs):
        fixed = 0
        D = spread_corrections(pairs, names, fixed)  # the first camera keeps its pose
        candidate = D @ T_world_from_cam
        pairs2, depth2 = depth_agreement(cams, candidate, pick)
        if np.nanmean(depth2) < np.nanmean(depth_mm):
            T_world_from_cam, pairs, depth_mm, refined = candidate, pairs2, depth2, True
    result = RigCalibration(names, T_world_from_cam, reproj, n_views, depth_mm, refined, len(shared),
                            time.perf_counter() - start, pairs, shared)
    return result, cams, calib


def calibration_json(result: RigCalibration, calib: dict, world: str) -> dict:
    """Our calibration.json: the input's cameras with the solved poses (and a summary of how)."""
    note = ("metres; world = the first camera's frame (OpenCV axes)" if world == "camera" else
            "metres; world = the calibration board's first shared pose (x columns, y rows, z into the board)")
    cams = []
    for entry, T in zip(calib["cameras"], result.T_world_from_cam):
        cams.append({**entry, "T_world_from_cam": np.round(T, 9).tolist()})
    summary = {"cameras": {n: {"reprojection_px": round(float(r), 4), "board_frames": int(v),
                               "depth_agreement_mm": None if not np.isfinite(d) else round(float(d), 3)}
                           for n, r, v, d in zip(result.names, result.reprojection_px, result.views, result.depth_mm)},
               "shared_frames": result.frames_used, "depth_refined": result.depth_refined}
    return {**{k: v for k, v in calib.items() if k != "cameras"}, "world": note, "cameras": cams,
            "board_calibration": summary}


def format_result(result: RigCalibration) -> str:
    """Per-camera table a person reads."""
    lines = [f"{'camera':<12} {'frames':>6} {'reproj px':>10} {'depth mm':>9}  position (m)"]
    for n, v, r, d, T in zip(result.names, result.views, result.reprojection_px, result.depth_mm,
                             result.T_world_from_cam):
        lines.append(f"{n:<12} {v:>6d} {r:>10.3f} {d:>9.2f}  {np.array2string(T[:3, 3], precision=3)}")
    lines.append(f"{result.frames_used} frames seen by two or more cameras; depth refinement "
                 f"{'applied' if result.depth_refined else 'not applied'}; {result.seconds:.1f} s")
    return "\n".join(lines)


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per camera translation (mm) and rotation (deg) errors of T_world_from_cam (C, 4, 4) after
    expressing both in their first camera's frame (the gauge a board calibration fixes)."""
    A = np.linalg.inv(T_est[0]) @ T_est
    B = np.linalg.inv(T_true[0]) @ T_true
    trans = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1) * 1000
    rot = np.array([rotation_angle_deg(a[:3, :3].T @ b[:3, :3]) for a, b in zip(A, B)])
    return trans, rot


__all__ = ["Board", "CalibrationError", "RigCalibration", "calibrate_rig", "calibration_json", "format_result",
           "pose_errors", "load_recording", "neighbour_pairs"]


# ----------------------------------------------------------------------------- command line
def board_from_args(args) -> Board:
    """The `Board` of the command line's board options (`intercap.calib.options.add_board_arguments`)."""
    try:
        cols, rows = (int(v) for v in str(args.squares).lower().split("x"))
    except ValueError:
        raise ValueError(f"--squares must look like 7x5, got {args.squares!r}") from None
    return Board(args.board, (cols, rows), args.square_m, args.marker_m, args.dictionary)


def board_command(args) -> int:
    """Run `intercap board`: write the board to print at its true size, say its size."""
    from intercap.calib.print_board import write_board

    written = write_board(board_from_args(args), args.out, args.dpi, args.margin_m)
    width, height = written["size_mm"]
    print(f"written {written['path']}: {width:.1f} x {height:.1f} mm, squares of {written['square_mm']:.2f} mm "
          f"({written['pixels'][0]} x {written['pixels'][1]} dots at {args.dpi:g} dpi); print at 100 %, then measure "
          "a square and a marker for `intercap calibrate`")
    return 0


def calibrate_command(args) -> int:
    """Run `intercap calibrate`: print the per-camera table, write calibration.json atomically."""
    from intercap.io.files import write_json

    board = board_from_args(args)
    result, _, calib = calibrate_rig(args.session, board, world=args.world, depth_refine=not args.no_depth_refine)
    print(format_result(result))
    out = Path(args.out) if args.out else Path(args.session) / "calibration.json"
    write_json(out, calibration_json(result, calib, args.world))
    print(f"written {out}")
    return 0
