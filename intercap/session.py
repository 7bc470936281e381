"""The session layer: read and check one capture session folder.

The folder layout is the contract in SESSION_FORMAT.md. Two entry points:

* `Session.load(path)` checks structure and existence (YAML/JSON content,
  calibration matrices, camera folders, frame files, the object mesh, ground
  truth shapes) plus the first colour and depth frame of each camera, and
  raises `SessionError` listing every fatal problem at once.
* `validate(path)` does the same and also decodes every frame file once, so a
  corrupt JPEG, a depth PNG that is not uint16 or an image of the wrong size is
  found before a long run. It never raises for problems in the session's
  content; it returns them all.

A missing or unreadable frame file is a dropped frame for that view: a warning,
never fatal. The readers return None for it.
"""
from __future__ import annotations

import json
import os
import re
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, NamedTuple

import cv2
import numpy as np
import trimesh
import yaml

KINDS = ("color", "depth", "keypoints", "mask_person", "mask_object")
OPTIONAL_KINDS = ("keypoints", "mask_person", "mask_object")
KIND_DIRS = {
    "color": "color",
    "depth": "depth",
    "keypoints": "keypoints",
    "mask_person": "masks/person",
    "mask_object": "masks/object",
}
KIND_EXTS = {
    "color": (".jpg", ".png", ".jpeg"),
    "depth": (".png",),
    "keypoints": (".json",),
    "mask_person": (".png",),
    "mask_object": (".png",),
}
BODY_MODELS = ("anny", "smplx")
DIST_LENGTHS = (0, 4, 5, 8)
# OpenPose JSON parts, in the order of the (137, 3) keypoint array.
OPENPOSE_PARTS = (
    ("pose_keypoints_2d", 25),
    ("hand_left_keypoints_2d", 21),
    ("hand_right_keypoints_2d", 21),
    ("face_keypoints_2d", 70),
)
NUM_KEYPOINTS_2D = sum(n for _, n in OPENPOSE_PARTS)  # 137
NUM_KEYPOINTS_3D = 67  # BODY_25 + left hand 21 + right hand 21
ROTATION_TOL = 1e-4  # calibration and initial poses: orthonormality / det tolerance
GT_ROTATION_TOL = 1e-3  # ground-truth poses may be stored as float32
SESSION_KEYS = ("fps", "object", "frames", "contact_frames", "ground", "body")
OBJECT_KEYS = ("mesh", "name", "mass_kg", "contact_vertices", "initial_pose")
_FRAME_NAME = re.compile(r"^(\d{6})(\.[^.]+)$")
_FIRST_FRAME_TRIES = 5  # load: how many leading frames to try when the first ones do not decode
_IO_WORKERS = max(1, min(8, (os.cpu_count() or 2) * 2))


# --------------------------------------------------------------------------- problems


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a session: which file (relative to the session root) and what."""

    path: str
    message: str
    fatal: bool

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"


class SessionError(Exception):
    """The session cannot be used; `.problems` lists every fatal problem found (and the warnings)."""

    def __init__(self, root: Path | str, problems: list[Problem]):
        self.root = Path(root)
        self.problems = list(problems)
        fatal = [p for p in self.problems if p.fatal]
        lines = [f"session {self.root} cannot be used ({len(fatal)} fatal problems):"]
        lines += [f"  {p}" for p in fatal]
        super().__init__("\n".join(lines))


class _Problems(list):
    """A list of Problem with shorthands; paths are made relative to the session root."""

    def __init__(self, root: Path):
        super().__init__()
        self.root = root

    def rel(self, path: Path | str) -> str:
        path = Path(path)
        try:
            rel = path.relative_to(self.root)
        except ValueError:
            return str(path)
        return rel.as_posix() if rel.parts else "."

    def fatal(self, path: Path | str, message: str) -> None:
        self.append(Problem(self.rel(path), message, True))

    def warn(self, path: Path | str, message: str) -> None:
        self.append(Problem(self.rel(path), message, False))

    @property
    def any_fatal(self) -> bool:
        return any(p.fatal for p in self)


# --------------------------------------------------------------------------- data classes


@dataclass
class CameraInfo:
    """One calibrated camera; the camera frame is OpenCV's (x right, y down, z forward)."""

    name: str
    width: int
    height: int
    K: np.ndarray  # (3, 3) float64
    dist: np.ndarray  # (D,) float64, D in {0, 4, 5, 8}
    T_world_from_cam: np.ndarray  # (4, 4) float64

    @property
    def T_cam_from_world(self) -> np.ndarray:
        """(4, 4) inverse of the rigid camera pose, computed with R^T (exact for rotations)."""
        R, t = self.T_world_from_cam[:3, :3], self.T_world_from_cam[:3, 3]
        T = np.eye(4)
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ t
        return T

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return self.T_world_from_cam[:3, 3].copy()


@dataclass
class ObjectInfo:
    """The rigid object of the session (mesh in metres, object coordinates)."""

    name: str
    mesh_path: Path
    mass_kg: float | None = None
    contact_vertices: np.ndarray | None = None  # (K,) int64 vertex ids
    initial_pose: tuple[np.ndarray, np.ndarray] | None = None  # R (3, 3), t (3,): object -> world at frames.start
    _mesh: trimesh.Trimesh | None = field(default=None, init=False, repr=False, compare=False)

    def load_mesh(self) -> trimesh.Trimesh:
        """The mesh as stored (no merging or reordering, so vertex ids match the file); a fresh copy each call."""
        if self._mesh is None:
            self._mesh = load_mesh_file(self.mesh_path)
        return self._mesh.copy()


@dataclass
class GroundTruth:
    """ground_truth/ of a synthetic or annotated session; row t is frame frames.start + t."""

    body_vertices: np.ndarray | None = None  # (T, V, 3) float32, world
    body_faces: np.ndarray | None = None  # (F, 3) int64
    object_R: np.ndarray | None = None  # (T, 3, 3) float64, object -> world
    object_t: np.ndarray | None = None  # (T, 3) float64
    contact: np.ndarray | None = None  # (T,) bool
    keypoints3d: np.ndarray | None = None  # (T, 67, 3) float32, world


def load_mesh_file(path: Path | str) -> trimesh.Trimesh:
    """Read a .ply/.obj as one Trimesh without processing, so vertex ids are the file's."""
    mesh = trimesh.load(str(path), process=False, force="mesh", maintain_order=True, skip_materials=True)
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{path}: not a triangle mesh")
    return mesh


# --------------------------------------------------------------------------- small pure checks


def intrinsics_issue(K: Any) -> str | None:
    """Why K is not a pinhole matrix [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0 (None if it is)."""
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        return "K is not a 3x3 matrix of numbers"
    if K.shape != (3, 3):
        return f"K is not 3x3 (shape {K.shape})"
    if not np.all(np.isfinite(K)):
        return "K has non-finite entries"
    zeros = np.array([K[0, 1], K[1, 0], K[2, 0], K[2, 1]])
    if np.any(np.abs(zeros) > 1e-9) or abs(K[2, 2] - 1.0) > 1e-9:
        return "K is not of the form [[fx,0,cx],[0,fy,cy],[0,0,1]]"
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return f"K has non-positive focal length (fx={K[0, 0]:g}, fy={K[1, 1]:g})"
    return None


def rotation_issue(R: Any, tol: float = ROTATION_TOL) -> str | None:
    """Why R is not a rotation matrix (orthonormal, det +1), or None."""
    try:
        R = np.asarray(R, dtype=np.float64)
    except (TypeError, ValueError):
        return "is not a 3x3 matrix of numbers"
    if R.shape != (3, 3):
        return f"is not 3x3 (shape {R.shape})"
    if not np.all(np.isfinite(R)):
        return "has non-finite entries"
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > tol:
        return f"is not orthonormal (max |R^T R - I| = {err:.2g})"
    det = np.linalg.det(R)
    if abs(det - 1.0) > tol:
        return f"has determinant {det:.4g}, not +1 (a reflection)"
    return None


def rigid_transform_issue(T: Any, tol: float = ROTATION_TOL) -> str | None:
    """Why T is not a 4x4 rigid transform [[R, t], [0, 0, 0, 1]], or None."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        return "is not a 4x4 matrix of numbers"
    if T.shape != (4, 4):
        return f"is not 4x4 (shape {T.shape})"
    if not np.all(np.isfinite(T)):
        return "has non-finite entries"
    if np.abs(T[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        return f"last row is {T[3].tolist()}, not [0, 0, 0, 1]"
    issue = rotation_issue(T[:3, :3], tol)
    return None if issue is None else f"rotation part {issue}"


def format_frame_list(ids: Iterable[int], limit: int = 20) -> str:
    """'3, 7-9, 12' for [3, 7, 8, 9, 12]; long lists are cut after `limit` runs."""
    ids = sorted(int(i) for i in ids)
    runs: list[tuple[int, int]] = []
    for i in ids:
        if runs and i == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], i)
        else:
            runs.append((i, i))
    parts = [str(a) if a == b else f"{a}-{b}" for a, b in runs[:limit]]
    if len(runs) > limit:
        parts.append("...")
    return ", ".join(parts)


def openpose_to_array(data: Any) -> tuple[np.ndarray, list[str]]:
    """(137, 3) float32 [x, y, conf] of the first person in an OpenPose JSON object, and issues found.

    Order: BODY_25 (25), left hand (21), right hand (21), face (70). Missing or
    badly sized parts are left at zero (confidence 0 = not detected); no person
    gives all zeros. Raises ValueError when the object is not OpenPose JSON at all."""
    if not isinstance(data, dict) or not isinstance(data.get("people"), list):
        raise ValueError('not OpenPose JSON (expected {"people": [...]})')
    out = np.zeros((NUM_KEYPOINTS_2D, 3), np.float32)
    issues: list[str] = []
    if not data["people"]:
        return out, issues
    person = data["people"][0]
    if not isinstance(person, dict):
        raise ValueError("people[0] is not an object")
    start = 0
    for key, n in OPENPOSE_PARTS:
        values = person.get(key)
        if values is not None and len(values) > 0:
            try:
                arr = np.asarray(values, dtype=np.float32).reshape(-1)
            except (TypeError, ValueError):
                arr = None
            if arr is None or arr.size != 3 * n:
                size = "non-numeric" if arr is None else f"{arr.size} numbers"
                issues.append(f"{key} has {size}, expected {3 * n} ({n} points x [x, y, conf]); part ignored")
            else:
                out[start : start + n] = arr.reshape(n, 3)
        start += n
    return out, issues


# --------------------------------------------------------------------------- file decoding


def _decode_image(path: Path, flags: int) -> tuple[np.ndarray | None, str | None]:
    """Decode an image file; (None, reason) when it is missing, corrupt or truncated."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        return None, f"cannot be read ({exc.strerror or exc})"
    if path.suffix.lower() in (".jpg", ".jpeg") and b"\xff\xd9" not in data[-64:]:
        # libjpeg decodes truncated files into grey-filled images with a warning only
        return None, "unreadable: truncated JPEG (no end-of-image marker); treated as a dropped frame"
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    if img is None:
        return None, "unreadable: cannot be decoded (corrupt or not an image); treated as a dropped frame"
    return img, None


def _depth_format_issue(img: np.ndarray) -> str | None:
    """Why a decoded depth image is not single-channel uint16 millimetres, or None."""
    if img.dtype == np.uint16 and img.ndim == 2:
        return None
    channels = 1 if img.ndim == 2 else img.shape[2]
    return f"depth PNG is {img.dtype} with {channels} channel(s), expected single-channel uint16 millimetres"


def _size_issue(img: np.ndarray, cam: CameraInfo) -> str | None:
    h, w = img.shape[:2]
    if (w, h) != (cam.width, cam.height):
        return f"image is {w}x{h} but calibration.json gives {cam.width}x{cam.height} for camera {cam.name}"
    return None


class _FileIssue(NamedTuple):
    message: str
    fatal: bool
    dropped: bool  # the file cannot be used: the frame counts as dropped for this view


def _check_frame_file(kind: str, path: Path, cam: CameraInfo | None) -> _FileIssue | None:
    """Decode one frame file and say what is wrong with it, or None if it is usable."""
    if kind == "keypoints":
        try:
            data = json.loads(path.read_text())
            _, issues = openpose_to_array(data)
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            return _FileIssue(f"unreadable keypoints: {exc}; treated as a dropped frame", False, True)
        return _FileIssue("; ".join(issues), False, False) if issues else None
    flags = cv2.IMREAD_COLOR if kind == "color" else cv2.IMREAD_UNCHANGED
    img, reason = _decode_image(path, flags)
    if img is None:
        return _FileIssue(reason, False, True)
    if kind == "depth":
        issue = _depth_format_issue(img)
        if issue is not None:
            return _FileIssue(issue + "; treated as a dropped frame", False, True)
    if cam is not None:
        issue = _size_issue(img, cam)
        if issue is not None:
            return _FileIssue(issue, True, True)
    return None


# --------------------------------------------------------------------------- parsing the two required files


def _yaml_error_text(exc: Exception) -> str:
    """One line: what PyYAML found wrong and where."""
    problem, mark = getattr(exc, "problem", None), getattr(exc, "problem_mark", None)
    if problem and mark is not None:
        context = getattr(exc, "context", None)
        return f"{problem} at line {mark.line + 1}, column {mark.column + 1}" + (f" ({context})" if context else "")
    return " ".join(str(exc).split()) or type(exc).__name__


def _read_session_yaml(root: Path, out: _Problems) -> dict | None:
    path = root / "session.yaml"
    if not path.is_file():
        out.fatal(path, "missing (required: at least `fps`)")
        return None
    try:
        cfg = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        out.fatal(path, f"cannot be parsed as YAML: {_yaml_error_text(exc)}")
        return None
    if cfg is None:
        cfg = {}
    if not isinstance(cfg, dict):
        out.fatal(path, f"top level must be a mapping of keys, got {type(cfg).__name__}")
        return None
    for key in cfg:
        if key not in SESSION_KEYS:
            out.warn(path, f"unknown key `{key}` ignored (known: {', '.join(SESSION_KEYS)})")
    return cfg


def _parse_fps(cfg: dict, path: Path, out: _Problems) -> float | None:
    if "fps" not in cfg:
        out.fatal(path, "missing `fps` (frames per second, required)")
        return None
    fps = cfg["fps"]
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not np.isfinite(fps) or fps <= 0:
        out.fatal(path, f"`fps` must be a positive number, got {fps!r}")
        return None
    return float(fps)


def _is_int(x: Any) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def _camera_from_json(entry: Any, i: int, path: Path, names: set, out: _Problems) -> tuple[str | None, CameraInfo | None]:
    """One calibration entry -> (name usable for folders, CameraInfo if every field is valid)."""
    where = f"cameras[{i}]"
    if not isinstance(entry, dict):
        out.fatal(path, f"{where} is not an object")
        return None, None
    name = entry.get("name")
    if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name:
        out.fatal(path, f"{where}: missing or invalid `name` {name!r} (must be a folder name)")
        return None, None
    where = f"camera '{name}' ({where})"
    ok = True
    if name in names:
        out.fatal(path, f"duplicate camera name '{name}'")
        ok = False
    names.add(name)
    for key in ("width", "height", "K", "T_world_from_cam"):
        if key not in entry:
            out.fatal(path, f"{where}: missing `{key}`")
            ok = False
    for key in ("width", "height"):
        if key in entry and (not _is_int(entry[key]) or entry[key] <= 0):
            out.fatal(path, f"{where}: `{key}` must be a positive integer, got {entry[key]!r}")
            ok = False
    if "K" in entry:
        issue = intrinsics_issue(entry["K"])
        if issue:
            out.fatal(path, f"{where}: {issue}")
            ok = False
    dist = entry.get("dist", [])
    if dist is None:
        dist = []
    try:
        dist = np.asarray(dist, dtype=np.float64).reshape(-1)
        if dist.size not in DIST_LENGTHS or not np.all(np.isfinite(dist)):
            raise ValueError
    except (TypeError, ValueError):
        out.fatal(path, f"{where}: `dist` must be a list of 0, 4, 5 or 8 numbers, got {entry.get('dist')!r}")
        ok = False
    if "T_world_from_cam" in entry:
        issue = rigid_transform_issue(entry["T_world_from_cam"])
        if issue:
            out.fatal(path, f"{where}: T_world_from_cam {issue}")
            ok = False
    if not ok:
        return name, None
    return name, CameraInfo(
        name=name,
        width=int(entry["width"]),
        height=int(entry["height"]),
        K=np.asarray(entry["K"], dtype=np.float64),
        dist=dist,
        T_world_from_cam=np.asarray(entry["T_world_from_cam"], dtype=np.float64),
    )


def _read_calibration(root: Path, out: _Problems) -> list[tuple[str | None, CameraInfo | None]]:
    """calibration.json -> one (name, CameraInfo or None) per entry; problems go to `out`."""
    path = root / "calibration.json"
    if not path.is_file():
        out.fatal(path, "missing (required: the cameras' intrinsics and poses)")
        return []
    try:
        calib = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        out.fatal(path, f"cannot be parsed as JSON: {exc}")
        return []
    cams = calib.get("cameras") if isinstance(calib, dict) else None
    if not isinstance(cams, list) or not cams:
        out.fatal(path, "no cameras (expected a non-empty list `cameras`)")
        return []
    names: set = set()
    return [_camera_from_json(entry, i, path, names, out) for i, entry in enumerate(cams)]


# --------------------------------------------------------------------------- frame files


def _scan_kind_folder(folder: Path, kind: str, out: _Problems) -> dict[int, Path]:
    """Frame index -> file in one kind folder; misnamed files are warned about and ignored."""
    files: dict[int, Path] = {}
    misnamed: list[str] = []
    exts = KIND_EXTS[kind]
    try:
        with os.scandir(folder) as it:
            entries = sorted((e.name, e.is_file()) for e in it)
    except OSError as exc:
        out.fatal(folder, f"cannot list folder: {exc.strerror or exc}")
        return files
    for name, is_file in entries:
        if name.startswith(".") or not is_file:
            continue
        m = _FRAME_NAME.match(name)
        if m is None or m.group(2) not in exts:
            misnamed.append(name)
            continue
        idx = int(m.group(1))
        if idx in files:
            out.warn(folder / name, f"frame {idx} also stored as {files[idx].name}; using {files[idx].name}")
            continue
        files[idx] = folder / name
    if misnamed:
        expected = f"6-digit frame index + {'/'.join(exts)}, e.g. 000000{exts[0]}"
        where = folder / misnamed[0] if len(misnamed) == 1 else folder
        shown = ", ".join(misnamed[:5]) + (", ..." if len(misnamed) > 5 else "")
        out.warn(where, f"{len(misnamed)} file(s) not named as frames ({expected}) are ignored: {shown}")
    return files


def _scan_camera(root: Path, name: str, out: _Problems) -> dict[str, dict[int, Path] | None]:
    """kind -> {frame index: path} for one camera; None for a kind whose folder is absent."""
    cam_dir = root / name
    files: dict[str, dict[int, Path] | None] = {kind: None for kind in KINDS}
    if not cam_dir.is_dir():
        out.fatal(cam_dir, f"camera folder missing for camera '{name}' listed in calibration.json")
        return files
    for kind in KINDS:
        folder = cam_dir / KIND_DIRS[kind]
        if folder.is_dir():
            files[kind] = _scan_kind_folder(folder, kind, out)
        elif kind in ("color", "depth"):
            out.fatal(folder, f"{kind} folder missing (required for every camera)")
    return files


def _frame_range(cfg: dict, found: np.ndarray, path: Path, out: _Problems) -> np.ndarray | None:
    """frame_ids: frames.start..frames.end (inclusive) or first..last frame found; always contiguous
    so that frame k is at time k / fps."""
    frames = cfg.get("frames")
    if frames is None:
        return np.arange(found[0], found[-1] + 1, dtype=np.int64) if found.size else None
    if not isinstance(frames, dict) or not set(frames) <= {"start", "end"}:
        out.fatal(path, f"`frames` must be {{start: int, end: int}}, got {frames!r}")
        return None
    start = frames.get("start", int(found[0]) if found.size else 0)
    end = frames.get("end", int(found[-1]) if found.size else 0)
    if not _is_int(start) or not _is_int(end) or start < 0:
        out.fatal(path, f"`frames` start/end must be non-negative integers, got {frames!r}")
        return None
    if start > end:
        out.fatal(path, f"`frames`: start {start} is after end {end}")
        return None
    if found.size and (start < found[0] or end > found[-1]):
        out.fatal(path, f"`frames` {start}..{end} is outside the frames found ({found[0]}..{found[-1]})")
        return None
    return np.arange(start, end + 1, dtype=np.int64)


def _report_missing_frames(
    root: Path,
    names: list[str],
    files: list[dict[str, dict[int, Path] | None]],
    frame_ids: np.ndarray,
    out: _Problems,
) -> None:
    """Warn about gaps (frames missing in every view) and dropped frames (missing in some views)."""
    present = np.zeros(len(frame_ids), bool)
    for cam_files in files:
        for kind in ("color", "depth"):
            if cam_files[kind]:
                present |= np.isin(frame_ids, list(cam_files[kind]))
    gap = frame_ids[~present]
    if gap.size:
        out.warn(root, f"gap in the recording: frame(s) {format_frame_list(gap)} missing in every camera")
    wanted = frame_ids[present]
    for name, cam_files in zip(names, files):
        for kind in KINDS:
            have = cam_files[kind]
            if have is None:
                continue
            missing = wanted[~np.isin(wanted, list(have))]
            if missing.size == wanted.size and kind in ("color", "depth") and wanted.size:
                out.fatal(root / name / KIND_DIRS[kind], f"no {kind} frames in the frame range")
            elif missing.size:
                out.warn(
                    root / name / KIND_DIRS[kind],
                    f"{missing.size} dropped frame(s) (file missing): {format_frame_list(missing)}",
                )


# --------------------------------------------------------------------------- optional blocks


def _parse_object(root: Path, block: Any, path: Path, out: _Problems) -> ObjectInfo | None:
    if block is None:
        return None
    if not isinstance(block, dict):
        out.fatal(path, f"`object` must be a mapping, got {block!r}")
        return None
    for key in block:
        if key not in OBJECT_KEYS:
            out.warn(path, f"unknown key `object.{key}` ignored")
    mesh_name = block.get("mesh")
    if not isinstance(mesh_name, str) or not mesh_name:
        out.fatal(path, "`object.mesh` missing: an object block needs its mesh file (e.g. object.ply)")
        return None
    mesh_path = root / mesh_name
    obj = ObjectInfo(name=str(block.get("name") or mesh_path.stem), mesh_path=mesh_path)
    ok = True

    mesh = None
    if not mesh_path.is_file():
        out.fatal(mesh_path, "object mesh missing (named by `object.mesh` in session.yaml)")
        ok = False
    else:
        try:
            mesh = load_mesh_file(mesh_path)
        except Exception as exc:  # trimesh raises many kinds on bad files
            out.fatal(mesh_path, f"object mesh unreadable ({type(exc).__name__}: {exc})")
            ok = False
    if mesh is not None:
        if len(mesh.faces) == 0:
            out.fatal(mesh_path, "object mesh has no faces (the tracker renders its silhouette)")
            ok = False
            mesh = None  # nothing to check contact vertex ids against
        elif not mesh.is_watertight:
            out.warn(mesh_path, "object mesh is not watertight; its rendered silhouette and depth may have holes")
        obj._mesh = mesh

    mass = block.get("mass_kg")
    if mass is not None:
        if isinstance(mass, bool) or not isinstance(mass, (int, float)) or not mass > 0:
            out.fatal(path, f"`object.mass_kg` must be a positive number, got {mass!r}")
            ok = False
        else:
            obj.mass_kg = float(mass)

    contacts = block.get("contact_vertices")
    if contacts is not None:
        obj.contact_vertices = _read_contact_vertices(root, contacts, mesh, path, out)
        ok = ok and obj.contact_vertices is not None

    pose = block.get("initial_pose")
    if pose is not None:
        obj.initial_pose = _parse_pose(pose, path, out)
        ok = ok and obj.initial_pose is not None
    return obj if ok else None


def _read_contact_vertices(root: Path, name: Any, mesh: trimesh.Trimesh | None, yaml_path: Path, out: _Problems):
    if not isinstance(name, str) or not name:
        out.fatal(yaml_path, f"`object.contact_vertices` must name a JSON file, got {name!r}")
        return None
    path = root / name
    if not path.is_file():
        out.fatal(path, "contact vertex file missing (named by `object.contact_vertices`)")
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        out.fatal(path, f"malformed: cannot be parsed as JSON: {exc}")
        return None
    ids = data.get("vertices") if isinstance(data, dict) else None
    if not isinstance(ids, list) or not all(_is_int(i) for i in ids):
        out.fatal(path, 'malformed: expected {"vertices": [vertex ids as integers]}')
        return None
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    if mesh is not None and ids.size:
        n = len(mesh.vertices)
        bad = ids[(ids < 0) | (ids >= n)]
        if bad.size:
            shown = ", ".join(str(i) for i in bad[:5])
            out.fatal(path, f"{bad.size} vertex id(s) out of range (mesh has {n} vertices): {shown}")
            return None
    return ids


def _parse_pose(pose: Any, path: Path, out: _Problems) -> tuple[np.ndarray, np.ndarray] | None:
    if not isinstance(pose, dict) or "R" not in pose or "t" not in pose:
        out.fatal(path, "`object.initial_pose` must have `R` (3x3) and `t` (3)")
        return None
    issue = rotation_issue(pose["R"])
    if issue:
        out.fatal(path, f"`object.initial_pose.R` {issue}; it must be a rotation")
        return None
    try:
        t = np.asarray(pose["t"], dtype=np.float64)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError
    except (TypeError, ValueError):
        out.fatal(path, f"`object.initial_pose.t` must be 3 numbers, got {pose['t']!r}")
        return None
    return np.asarray(pose["R"], dtype=np.float64), t


def _parse_contact_frames(value: Any, frame_ids: np.ndarray | None, path: Path, out: _Problems):
    if value is None:
        return None
    if not isinstance(value, list):
        out.fatal(path, f"`contact_frames` must be a list of [start, end] ranges, got {value!r}")
        return None
    ranges = []
    ok = True
    for r in value:
        if not isinstance(r, (list, tuple)) or len(r) != 2 or not all(_is_int(x) for x in r):
            out.fatal(path, f"`contact_frames`: range {r!r} is malformed (expected [start, end] integers)")
            ok = False
        elif r[0] > r[1]:
            out.fatal(path, f"`contact_frames`: range {list(r)} has start after end")
            ok = False
        elif frame_ids is not None and frame_ids.size and (r[0] < frame_ids[0] or r[1] > frame_ids[-1]):
            out.fatal(
                path,
                f"`contact_frames`: range {list(r)} is outside the frame range {frame_ids[0]}..{frame_ids[-1]}",
            )
            ok = False
        else:
            ranges.append((int(r[0]), int(r[1])))
    return ranges if ok else None


def _vector3(x: Any) -> np.ndarray | None:
    try:
        v = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return v if v.shape == (3,) and np.all(np.isfinite(v)) else None


def _parse_ground(value: Any, path: Path, out: _Problems):
    if value is None:
        return None
    if not isinstance(value, dict):
        out.fatal(path, f"`ground` must be {{point: [x,y,z], normal: [x,y,z]}}, got {value!r}")
        return None
    point, normal = _vector3(value.get("point")), _vector3(value.get("normal"))
    if point is None or normal is None:
        out.fatal(path, "`ground` needs `point` and `normal`, each 3 numbers")
        return None
    norm = np.linalg.norm(normal)
    if norm < 1e-9:
        out.fatal(path, "`ground.normal` is zero; it must be a non-zero direction")
        return None
    return point, normal / norm


def _parse_body(value: Any, path: Path, out: _Problems) -> str:
    if value is None:
        return "anny"
    model = value.get("model", "anny") if isinstance(value, dict) else None
    if model not in BODY_MODELS:
        got = model if isinstance(value, dict) else value
        out.fatal(path, f"`body.model` must be one of {', '.join(BODY_MODELS)} (body: {{model: anny}}), got {got!r}")
        return "anny"
    return model


# --------------------------------------------------------------------------- ground truth

_GT_FILES = ("body_vertices.npy", "body_faces.npy", "object_poses.npz", "contact.npy", "keypoints3d.npy")


def _check_ground_truth(root: Path, T: int | None, has_object: bool, out: _Problems) -> bool:
    """Check shapes of ground_truth/ arrays (headers only for the big ones); True when any is present."""
    gt = root / "ground_truth"
    if not gt.is_dir():
        return False
    present = {name: (gt / name).is_file() for name in _GT_FILES}
    if not any(present.values()):
        out.warn(gt, "folder present but holds none of " + ", ".join(_GT_FILES))
        return False

    def check_T(path: Path, n: int) -> None:
        if T is not None and n != T:
            out.fatal(path, f"has {n} frames but the session has {T} (frames counted from frames.start)")

    def load(name: str, mmap: bool = True):
        try:
            return np.load(gt / name, mmap_mode="r" if mmap else None, allow_pickle=False)
        except Exception as exc:
            out.fatal(gt / name, f"unreadable: {exc}")
            return None

    V = None
    if present["body_vertices.npy"]:
        v = load("body_vertices.npy")
        if v is not None:
            if v.ndim != 3 or v.shape[2] != 3 or not np.issubdtype(v.dtype, np.floating):
                out.fatal(gt / "body_vertices.npy", f"bad shape/dtype {v.shape} {v.dtype}, expected float (T, V, 3)")
            else:
                V = v.shape[1]
                check_T(gt / "body_vertices.npy", v.shape[0])
    if present["body_faces.npy"] != present["body_vertices.npy"]:
        have, lack = ("body_faces.npy", "body_vertices.npy")[:: 1 if present["body_faces.npy"] else -1]
        out.fatal(gt / have, f"present without {lack}; both are needed")
    if present["body_faces.npy"]:
        f = load("body_faces.npy", mmap=False)
        if f is not None:
            if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
                out.fatal(gt / "body_faces.npy", f"bad shape/dtype {f.shape} {f.dtype}, expected int (F, 3)")
            elif V is not None and f.size and (f.min() < 0 or f.max() >= V):
                out.fatal(gt / "body_faces.npy", f"vertex ids out of range (body_vertices has {V} vertices)")
    if present["object_poses.npz"]:
        path = gt / "object_poses.npz"
        z = load("object_poses.npz", mmap=False)
        if z is not None:
            if not has_object:
                out.warn(path, "object poses given but session.yaml has no object block")
            R, t = (z["R"] if "R" in z.files else None), (z["t"] if "t" in z.files else None)
            if R is None or t is None:
                out.fatal(path, "must hold arrays `R` (T, 3, 3) and `t` (T, 3)")
            elif R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (R.shape[0], 3):
                out.fatal(path, f"bad shapes R {R.shape}, t {t.shape}; expected (T, 3, 3) and (T, 3)")
            else:
                check_T(path, R.shape[0])
                bad = [i for i in range(len(R)) if rotation_issue(R[i], GT_ROTATION_TOL)]
                if bad:
                    out.fatal(path, f"R is not a rotation in {len(bad)} frame(s) (rows {format_frame_list(bad)})")
    if present["contact.npy"]:
        c = load("contact.npy", mmap=False)
        if c is not None:
            if c.ndim != 1 or not (c.dtype == bool or (np.issubdtype(c.dtype, np.integer) and np.isin(c, (0, 1)).all())):
                out.fatal(gt / "contact.npy", f"bad shape/dtype {c.shape} {c.dtype}, expected bool (T,)")
            else:
                check_T(gt / "contact.npy", c.shape[0])
    if present["keypoints3d.npy"]:
        k = load("keypoints3d.npy")
        if k is not None:
            if k.ndim != 3 or k.shape[1:] != (NUM_KEYPOINTS_3D, 3):
                out.fatal(gt / "keypoints3d.npy", f"bad shape {k.shape}, expected (T, {NUM_KEYPOINTS_3D}, 3)")
            else:
                check_T(gt / "keypoints3d.npy", k.shape[0])
    return True


# --------------------------------------------------------------------------- the session


class Session:
    """A loaded capture session; read frames with the read_* methods (None = dropped frame)."""

    def __init__(
        self,
        *,
        root: Path,
        fps: float,
        cameras: list[CameraInfo],
        frame_ids: np.ndarray,
        object: ObjectInfo | None,
        contact_frames: list[tuple[int, int]] | None,
        ground: tuple[np.ndarray, np.ndarray] | None,
        body_model: str,
        problems: list[Problem],
        files: list[dict[str, dict[int, Path] | None]],
        has_ground_truth: bool,
    ):
        self.root = root
        self.fps = fps
        self.cameras = cameras
        self.frame_ids = frame_ids  # (T,) int64, contiguous
        self.object = object
        self.contact_frames = contact_frames
        self.ground = ground
        self.body_model = body_model
        self.problems = problems  # non-fatal warnings; read_* append files they find unusable
        self._files = files  # per camera: kind -> {frame index: path} (None: folder absent)
        self._has_ground_truth = has_ground_truth
        self._bad: set[Path] = set()  # files found unusable (dropped)
        self._reported: set[Problem] = set(problems)
        self._lock = threading.Lock()

    # -- loading ----------------------------------------------------------------
    @classmethod
    def load(cls, path: Path | str) -> "Session":
        """Load a session folder; raises SessionError listing every fatal problem at once."""
        session, problems = _inspect(Path(path), deep=False)
        if session is None:
            raise SessionError(path, problems)
        return session

    def __repr__(self) -> str:
        return f"Session({str(self.root)!r}, {self.num_cameras} cameras, {self.num_frames} frames, {self.fps:g} fps)"

    # -- basic facts ------------------------------------------------------------
    @property
    def num_frames(self) -> int:
        return int(len(self.frame_ids))

    @property
    def num_cameras(self) -> int:
        return len(self.cameras)

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def _cam_index(self, cam: str | int | CameraInfo) -> int:
        if isinstance(cam, CameraInfo):
            cam = cam.name
        if _is_int(cam):
            if not -self.num_cameras <= cam < self.num_cameras:
                raise IndexError(f"camera index {cam} out of range ({self.num_cameras} cameras)")
            return int(cam) % self.num_cameras
        for i, c in enumerate(self.cameras):
            if c.name == cam:
                return i
        raise KeyError(f"no camera {cam!r} in {self.root} (cameras: {', '.join(self.camera_names)})")

    def camera(self, name_or_index: str | int) -> CameraInfo:
        return self.cameras[self._cam_index(name_or_index)]

    # -- files ------------------------------------------------------------------
    def frame_path(self, cam: str | int, kind: str, frame_id: int) -> Path:
        """Where a frame file is (or would be); color: the .jpg or .png that exists (.jpg if neither)."""
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
        c = self._cam_index(cam)
        have = self._files[c][kind]
        if have is not None and int(frame_id) in have:
            return have[int(frame_id)]
        folder = self.root / self.cameras[c].name / KIND_DIRS[kind]
        stem = f"{int(frame_id):06d}"
        for ext in KIND_EXTS[kind]:
            if (folder / (stem + ext)).is_file():
                return folder / (stem + ext)
        return folder / (stem + KIND_EXTS[kind][0])

    def _usable_path(self, c: int, kind: str, frame_id: int) -> Path | None:
        have = self._files[c][kind]
        path = None if have is None else have.get(int(frame_id))
        return None if path is None or path in self._bad else path

    def _drop(self, path: Path, message: str) -> None:
        """Record a file found unusable while reading: it becomes a dropped frame, with a warning."""
        with self._lock:
            if path in self._bad:
                return
            self._bad.add(path)
            self.problems.append(Problem(_Problems(self.root).rel(path), message, False))

    def _read_image(self, c: int, kind: str, frame_id: int, flags: int) -> np.ndarray | None:
        path = self._usable_path(c, kind, frame_id)
        if path is None:
            return None
        img, reason = _decode_image(path, flags)
        if img is None:
            self._drop(path, reason)
            return None
        if kind == "depth":
            issue = _depth_format_issue(img)
            if issue:
                self._drop(path, issue + "; treated as a dropped frame")
                return None
        issue = _size_issue(img, self.cameras[c])
        if issue:
            self._drop(path, issue + "; treated as a dropped frame")
            return None
        return img

    def read_color(self, cam: str | int, frame_id: int) -> np.ndarray | None:
        """(H, W, 3) uint8 RGB, or None for a dropped/unreadable frame."""
        img = self._read_image(self._cam_index(cam), "color", frame_id, cv2.IMREAD_COLOR)
        return None if img is None else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def read_depth(self, cam: str | int, frame_id: int) -> np.ndarray | None:
        """(H, W) float32 metres (0 = no measurement), or None for a dropped/unreadable frame."""
        img = self._read_image(self._cam_index(cam), "depth", frame_id, cv2.IMREAD_UNCHANGED)
        return None if img is None else img.astype(np.float32) / np.float32(1000.0)

    def read_mask(self, cam: str | int, frame_id: int, kind: str) -> np.ndarray | None:
        """(H, W) bool (pixel > 127) for kind 'person' or 'object'; None when absent/unreadable."""
        if kind not in ("person", "object"):
            raise ValueError(f"mask kind must be 'person' or 'object', got {kind!r}")
        img = self._read_image(self._cam_index(cam), f"mask_{kind}", frame_id, cv2.IMREAD_GRAYSCALE)
        return None if img is None else img > 127

    def read_keypoints(self, cam: str | int, frame_id: int) -> np.ndarray | None:
        """(137, 3) float32 [x, y, conf] of the first person (BODY_25, left hand, right hand, face);
        missing parts have confidence 0; None when the file is absent or unreadable."""
        path = self._usable_path(self._cam_index(cam), "keypoints", frame_id)
        if path is None:
            return None
        try:
            kp, issues = openpose_to_array(json.loads(path.read_text()))
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            self._drop(path, f"unreadable keypoints: {exc}; treated as a dropped frame")
            return None
        if issues:
            problem = Problem(_Problems(self.root).rel(path), "; ".join(issues), False)
            with self._lock:
                if problem not in self._reported:
                    self._reported.add(problem)
                    self.problems.append(problem)
        return kp

    def read_depth_batch(self, frame_ids: Iterable[int]) -> np.ndarray:
        """(T, C, H, W) float32 metres for the given frames, 0 where a view dropped the frame.
        All cameras must share one image size (else ValueError: read per camera instead)."""
        ids = np.asarray(list(frame_ids) if not isinstance(frame_ids, np.ndarray) else frame_ids, np.int64)
        ids = ids.reshape(-1)
        sizes = {(c.height, c.width) for c in self.cameras}
        if len(sizes) != 1:
            listed = ", ".join(f"{c.name} {c.width}x{c.height}" for c in self.cameras)
            raise ValueError(f"read_depth_batch needs equal image sizes, cameras differ ({listed}); use read_depth")
        H, W = sizes.pop()
        out = np.zeros((len(ids), self.num_cameras, H, W), np.float32)  # (T, C, H, W)

        def fill(job: tuple[int, int]) -> None:
            t, c = job
            depth = self.read_depth(c, int(ids[t]))
            if depth is not None:
                out[t, c] = depth

        jobs = [(t, c) for t in range(len(ids)) for c in range(self.num_cameras)]
        if len(jobs) <= 4:
            for job in jobs:
                fill(job)
        else:
            with ThreadPoolExecutor(max_workers=_IO_WORKERS) as pool:  # cv2 decodes without the GIL
                list(pool.map(fill, jobs))
        return out

    def availability(self) -> dict[str, np.ndarray]:
        """kind -> (C, T) bool: which frame files exist (and were not found unusable) per camera and frame."""
        result = {}
        for kind in KINDS:
            avail = np.zeros((self.num_cameras, self.num_frames), bool)
            for c in range(self.num_cameras):
                have = self._files[c][kind]
                if have:
                    usable = [i for i, p in have.items() if p not in self._bad]
                    avail[c] = np.isin(self.frame_ids, usable)
            result[kind] = avail
        return result

    def has_kind(self, kind: str) -> list[bool]:
        """Per camera: whether its folder for `kind` exists (optional inputs may be absent)."""
        return [self._files[c][kind] is not None for c in range(self.num_cameras)]

    # -- ground truth -------------------------------------------------------------
    def ground_truth(self) -> GroundTruth | None:
        """The arrays of ground_truth/ (None if the session has none); shapes were checked at load."""
        if not self._has_ground_truth:
            return None
        gt = self.root / "ground_truth"
        gt_data = GroundTruth()
        if (gt / "body_vertices.npy").is_file():
            gt_data.body_vertices = np.load(gt / "body_vertices.npy").astype(np.float32, copy=False)
        if (gt / "body_faces.npy").is_file():
            gt_data.body_faces = np.load(gt / "body_faces.npy").astype(np.int64, copy=False)
        if (gt / "object_poses.npz").is_file():
            with np.load(gt / "object_poses.npz") as z:
                gt_data.object_R = z["R"].astype(np.float64)
                gt_data.object_t = z["t"].astype(np.float64)
        if (gt / "contact.npy").is_file():
            gt_data.contact = np.load(gt / "contact.npy").astype(bool)
        if (gt / "keypoints3d.npy").is_file():
            gt_data.keypoints3d = np.load(gt / "keypoints3d.npy").astype(np.float32, copy=False)
        return gt_data

    # -- report -------------------------------------------------------------------
    def summary(self) -> str:
        """Human-readable overview: cameras, frames, dropped frames per view and kind, inputs, object, gt."""
        T = self.num_frames
        avail = self.availability()
        lines = [f"Session {self.root}"]
        lines.append(
            f"  {T} frames ({self.frame_ids[0]}..{self.frame_ids[-1]}) at {self.fps:g} fps"
            if T
            else "  no frames"
        )
        everywhere_missing = ~(avail["color"] | avail["depth"]).any(axis=0)
        if everywhere_missing.any():
            lines.append(f"  gap (no view has the frame): {format_frame_list(self.frame_ids[everywhere_missing])}")
        lines.append(f"  {self.num_cameras} cameras:")
        width = max(len(n) for n in self.camera_names)
        for c, cam in enumerate(self.cameras):
            parts = []
            for kind in KINDS:
                if self._files[c][kind] is None:
                    continue
                dropped = self.frame_ids[~avail[kind][c] & ~everywhere_missing]
                label = KIND_DIRS[kind]
                parts.append(f"{label} " + (f"{dropped.size} dropped ({format_frame_list(dropped, 6)})" if dropped.size else "ok"))
            dist = f"dist {cam.dist.size}" if cam.dist.size else "no distortion"
            lines.append(f"    {cam.name:<{width}}  {cam.width}x{cam.height}  {dist}  " + "; ".join(parts))
        optional = []
        for kind in OPTIONAL_KINDS:
            n = sum(self.has_kind(kind))
            optional.append(f"{KIND_DIRS[kind]} {n}/{self.num_cameras} cameras")
        lines.append("  optional inputs: " + ", ".join(optional))
        if self.object is None:
            lines.append("  object: none (body only)")
        else:
            o = self.object
            mesh = o.load_mesh()
            extra = [f"{len(mesh.vertices)} vertices", f"{len(mesh.faces)} faces"]
            if o.mass_kg is not None:
                extra.append(f"{o.mass_kg:g} kg")
            if o.contact_vertices is not None:
                extra.append(f"{len(o.contact_vertices)} contact vertices")
            extra.append("initial pose given" if o.initial_pose is not None else "initial pose estimated")
            lines.append(f"  object: {o.name} ({o.mesh_path.name}; {', '.join(extra)})")
        if self.contact_frames is not None:
            lines.append("  contact frames (annotated): " + ", ".join(f"{a}-{b}" for a, b in self.contact_frames))
        if self.ground is not None:
            p, n = self.ground
            lines.append(f"  ground: given (point {np.round(p, 3).tolist()}, normal {np.round(n, 3).tolist()})")
        else:
            lines.append("  ground: estimated from the data")
        lines.append(f"  body model: {self.body_model}")
        if self._has_ground_truth:
            gt = self.root / "ground_truth"
            have = [name.split(".")[0] for name in _GT_FILES if (gt / name).is_file()]
            lines.append("  ground truth: " + ", ".join(have))
        else:
            lines.append("  ground truth: none")
        return "\n".join(lines)


# --------------------------------------------------------------------------- inspection (load and validate)


def _check_first_frames(
    cams: list[CameraInfo | None], files: list[dict], frame_ids: np.ndarray | None, bad: set, out: _Problems
) -> None:
    """load's image check: the first decodable colour and depth frame of each camera (size, depth dtype)."""
    for cam, cam_files in zip(cams, files):
        for kind in ("color", "depth"):
            have = cam_files[kind]
            if not have:
                continue
            ids = sorted(have) if frame_ids is None else [int(i) for i in frame_ids if int(i) in have]
            for idx in ids[:_FIRST_FRAME_TRIES]:
                path = have[idx]
                flags = cv2.IMREAD_COLOR if kind == "color" else cv2.IMREAD_UNCHANGED
                img, reason = _decode_image(path, flags)
                if img is None:
                    out.warn(path, reason)
                    bad.add(path)
                    continue
                if kind == "depth":
                    issue = _depth_format_issue(img)
                    if issue:
                        out.fatal(path, issue + " (first depth frame of this camera: its depth is taken to be "
                                  "written in the wrong format)")
                        bad.add(path)
                if cam is not None:
                    issue = _size_issue(img, cam)
                    if issue:
                        out.fatal(path, issue)
                        bad.add(path)
                break


def _check_all_frames(
    names: list[str], cams: list[CameraInfo | None], files: list[dict], frame_ids: np.ndarray,
    bad: set, out: _Problems,
) -> None:
    """validate's deep check: decode every frame file in the range once (threads: cv2 drops the GIL)."""
    jobs = []
    for cam, cam_files in zip(cams, files):
        for kind in KINDS:
            have = cam_files[kind]
            if not have:
                continue
            for idx in frame_ids:
                path = have.get(int(idx))
                if path is not None and path not in bad:
                    jobs.append((kind, path, cam))
    with ThreadPoolExecutor(max_workers=_IO_WORKERS) as pool:
        results = list(pool.map(lambda job: _check_frame_file(*job), jobs))
    for (_, path, _), issue in zip(jobs, results):
        if issue is None:
            continue
        (out.fatal if issue.fatal else out.warn)(path, issue.message)
        if issue.dropped:
            bad.add(path)
    for name, cam_files in zip(names, files):
        for kind in ("color", "depth"):
            have = cam_files[kind]
            in_range = [have[int(i)] for i in frame_ids if have and int(i) in have]
            if in_range and all(p in bad for p in in_range):
                out.fatal(out.root / name / KIND_DIRS[kind], f"no usable {kind} frame: every file is unreadable")


def _inspect(root: Path, deep: bool) -> tuple[Session | None, list[Problem]]:
    """Every check on a session folder; the Session when nothing fatal was found."""
    out = _Problems(root)
    if not root.is_dir():
        out.fatal(root, f"session folder {root} does not exist or is not a folder")
        return None, list(out)
    yaml_path = root / "session.yaml"
    cfg = _read_session_yaml(root, out)
    fps = _parse_fps(cfg, yaml_path, out) if cfg is not None else None
    has_object = cfg is None or "object" in cfg  # unreadable yaml: do not guess
    cfg = cfg or {}
    entries = _read_calibration(root, out)

    names = [name for name, _ in entries if name is not None]
    cams = [cam for name, cam in entries if name is not None]
    names_seen: set = set()
    scan_names, scan_cams = [], []
    for name, cam in zip(names, cams):  # duplicates were reported already; scan each folder once
        if name not in names_seen:
            names_seen.add(name)
            scan_names.append(name)
            scan_cams.append(cam)
    files = [_scan_camera(root, name, out) for name in scan_names]

    found_set: set = set()
    for cam_files in files:
        for kind in ("color", "depth"):
            found_set.update(cam_files[kind] or ())
    found = np.array(sorted(found_set), dtype=np.int64)
    if entries and not found.size and all(f["color"] is not None for f in files):
        out.fatal(root, "no frames found in any camera's color or depth folder")
    frame_ids = _frame_range(cfg, found, yaml_path, out)
    if frame_ids is not None and files:
        _report_missing_frames(root, scan_names, files, frame_ids, out)

    obj = _parse_object(root, cfg.get("object"), yaml_path, out)
    contact_frames = _parse_contact_frames(cfg.get("contact_frames"), frame_ids, yaml_path, out)
    ground = _parse_ground(cfg.get("ground"), yaml_path, out)
    body_model = _parse_body(cfg.get("body"), yaml_path, out)
    has_gt = _check_ground_truth(root, None if frame_ids is None else len(frame_ids), has_object, out)

    bad: set = set()
    _check_first_frames(scan_cams, files, frame_ids, bad, out)
    if deep and frame_ids is not None:
        _check_all_frames(scan_names, scan_cams, files, frame_ids, bad, out)

    if out.any_fatal or fps is None or frame_ids is None or any(c is None for c in cams):
        if not out.any_fatal:  # defensive: never return None without saying why
            out.fatal(root, "session cannot be loaded")
        return None, list(out)
    session = Session(
        root=root,
        fps=fps,
        cameras=list(scan_cams),
        frame_ids=frame_ids,
        object=obj,
        contact_frames=contact_frames,
        ground=ground,
        body_model=body_model,
        problems=[p for p in out if not p.fatal],
        files=files,
        has_ground_truth=has_gt,
    )
    session._bad |= bad
    return session, list(out)


def validate(path: Path | str) -> tuple[Session | None, list[Problem]]:
    """Check a session thoroughly (decodes every frame file once); never raises for content problems.
    Returns the Session (None when something is fatal) and every problem found, fatal or not."""
    return _inspect(Path(path), deep=True)


def format_report(session: Session | None, problems: list[Problem]) -> str:
    """What `intercap validate` prints: the summary when the session loads, then every problem
    ("path: message", fatal ones first) and a final line "N problems (M fatal)"."""
    fatal = [p for p in problems if p.fatal]
    warnings = [p for p in problems if not p.fatal]
    lines = []
    if session is not None and not fatal:
        lines.append(session.summary())
    if fatal:
        lines.append("Errors (the session cannot be used until these are fixed):")
        lines += [f"  {p}" for p in fatal]
    if warnings:
        lines.append("Warnings:")
        lines += [f"  {p}" for p in warnings]
    lines.append(f"{len(problems)} problem{'' if len(problems) == 1 else 's'} ({len(fatal)} fatal)")
    return "\n".join(lines)
