"""Reading the session format (docs/session_format.md): session.yaml, calibration.json, the
camera folders' frame files, the object block; each reader records what is wrong in a
problem list instead of raising, so one pass reports everything."""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh
import yaml

from intercap.session.problems import (
    MAX_TRANSLATION_M,
    ProblemList,
    intrinsics_issue,
    rigid_transform_issue,
    rotation_issue,
    translation_issue,
)

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


SESSION_KEYS = ("fps", "object", "frames", "contact_frames", "ground", "body", "supports")


OBJECT_KEYS = ("mesh", "name", "mass_kg", "density_kg_m3", "contact_vertices", "initial_pose", "static")
SUPPORT_KEYS = ("name", "mesh", "grip")
SUPPORT_EXTENT_M = 30.0  # a support mesh larger than this (m) is taken for millimetres
# Largest plausible object.mass_kg (kg) and object.density_kg_m3 (kg/m^3; steel is 7,850): beyond, a unit slip
OBJECT_LIMITS = {"mass_kg": 500.0, "density_kg_m3": 25000.0}
OBJECT_UNITS = {"mass_kg": ("kilograms", "grams"), "density_kg_m3": ("kg/m^3", "other units")}


_FRAME_NAME = re.compile(r"^(\d{6})(\.[^.]+)$")


_NUMBER_TEXT = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")  # 3e1, 1e-9: YAML 1.1 reads them as strings


FPS_RANGE = (1.0, 1000.0)  # frames per second


MESH_EXTENT_RANGE_M = (0.01, 3.0)  # the object's largest bounding-box side


def as_number(value: Any) -> float | None:
    """A YAML value where a number is expected, as a float (maybe inf or NaN); None when it is not one.
    Accepts strings such as `3e1` or `1e-9`, which YAML 1.1 (PyYAML) reads as strings for lack of a dot."""
    if isinstance(value, bool):
        return None
    if isinstance(value, str) and _NUMBER_TEXT.match(value.strip()):
        value = value.strip()
    elif not isinstance(value, (int, float, np.integer, np.floating)):
        return None
    try:
        return float(value)
    except (OverflowError, ValueError):
        return None


def positive_number(value: Any) -> float | None:
    """`as_number` when it is finite and > 0, else None."""
    x = as_number(value)
    return x if x is not None and np.isfinite(x) and x > 0 else None


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
    density_kg_m3: float | None = None  # mass from the mesh volume when mass_kg is absent
    contact_vertices: np.ndarray | None = None  # (K,) int64 vertex ids
    initial_pose: tuple[np.ndarray, np.ndarray] | None = None  # R (3, 3), t (3,): object -> world at frames.start
    static: bool = False  # furniture that never moves (a chair, a stool): physics takes it as a support
    _mesh: trimesh.Trimesh | None = field(default=None, init=False, repr=False, compare=False)

    def load_mesh(self) -> trimesh.Trimesh:
        """The mesh as stored (no merging or reordering, so vertex ids match the file); a fresh copy each call."""
        if self._mesh is None:
            self._mesh = load_mesh_file(self.mesh_path)
        return self._mesh.copy()


@dataclass
class SupportInfo:
    """A fixed structure that can carry the body (physics): a seat, a table, a bar; mesh in world metres."""

    name: str
    mesh_path: Path
    grip: bool = False  # hands may grip it (a bar, a handle): a free wrench per hand, not only pushes
    mesh: trimesh.Trimesh | None = field(default=None, repr=False, compare=False)


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


def decode_image(path: Path, flags: int) -> tuple[np.ndarray | None, str | None]:
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


def _yaml_error_text(exc: Exception) -> str:
    """One line: what PyYAML found wrong and where."""
    problem, mark = getattr(exc, "problem", None), getattr(exc, "problem_mark", None)
    if problem and mark is not None:
        context = getattr(exc, "context", None)
        return f"{problem} at line {mark.line + 1}, column {mark.column + 1}" + (f" ({context})" if context else "")
    return " ".join(str(exc).split()) or type(exc).__name__


def read_session_yaml(root: Path, out: ProblemList) -> dict | None:
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


def parse_fps(cfg: dict, path: Path, out: ProblemList) -> float | None:
    if "fps" not in cfg:
        out.fatal(path, "missing `fps` (frames per second, required)")
        return None
    fps = positive_number(cfg["fps"])
    lo, hi = FPS_RANGE
    if fps is None or not lo <= fps <= hi:
        out.fatal(path, f"`fps` must be a positive number of frames per second ({lo:g}-{hi:g}), got {cfg['fps']!r}")
        return None
    return fps


def is_int(x: Any) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def _camera_from_json(entry: Any, i: int, path: Path, names: set, out: ProblemList) -> tuple[str | None, CameraInfo | None]:
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
        if key in entry and (not is_int(entry[key]) or entry[key] <= 0):
            out.fatal(path, f"{where}: `{key}` must be a positive integer, got {entry[key]!r}")
            ok = False
    if "K" in entry:
        size_ok = all(is_int(entry.get(key)) and entry[key] > 0 for key in ("width", "height"))
        issue = intrinsics_issue(entry["K"], *((entry["width"], entry["height"]) if size_ok else ()))
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
        issue = rigid_transform_issue(entry["T_world_from_cam"], max_translation=MAX_TRANSLATION_M)
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


def read_calibration(root: Path, out: ProblemList) -> list[tuple[str | None, CameraInfo | None]]:
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


def _scan_kind_folder(folder: Path, kind: str, out: ProblemList) -> dict[int, Path]:
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


def scan_camera(root: Path, name: str, out: ProblemList) -> dict[str, dict[int, Path] | None]:
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


def frame_range(cfg: dict, found: np.ndarray, path: Path, out: ProblemList) -> np.ndarray | None:
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
    if not is_int(start) or not is_int(end) or start < 0:
        out.fatal(path, f"`frames` start/end must be non-negative integers, got {frames!r}")
        return None
    if start > end:
        out.fatal(path, f"`frames`: start {start} is after end {end}")
        return None
    if found.size and (start < found[0] or end > found[-1]):
        out.fatal(path, f"`frames` {start}..{end} is outside the frames found ({found[0]}..{found[-1]})")
        return None
    return np.arange(start, end + 1, dtype=np.int64)


def parse_object(root: Path, block: Any, path: Path, out: ProblemList) -> ObjectInfo | None:
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
    mesh_path = session_file(root, mesh_name, "object.mesh", path, out)
    if mesh_path is None:
        return None
    obj = ObjectInfo(name=str(block.get("name") or mesh_path.stem), mesh_path=mesh_path)
    mesh = _read_object_mesh(mesh_path, out)
    ok = mesh is not None
    obj._mesh = mesh

    for key in ("mass_kg", "density_kg_m3"):
        if block.get(key) is not None:
            value = positive_number(block[key])
            if value is None:
                out.fatal(path, f"`object.{key}` must be a positive finite number, got {block[key]!r}")
                ok = False
            elif value > OBJECT_LIMITS[key]:
                unit, slip = OBJECT_UNITS[key]
                out.fatal(path, f"`object.{key}` is {value:g}, over {OBJECT_LIMITS[key]:g} for an object a person "
                          f"handles: is it in {slip}? It is in {unit}")
                ok = False
            setattr(obj, key, value)

    contacts = block.get("contact_vertices")
    if contacts is not None:
        obj.contact_vertices = _read_contact_vertices(root, contacts, mesh, path, out)
        ok = ok and obj.contact_vertices is not None

    pose = block.get("initial_pose")
    if pose is not None:
        obj.initial_pose = _parse_pose(pose, path, out)
        ok = ok and obj.initial_pose is not None
    static = block.get("static", False)
    if not isinstance(static, bool):
        out.fatal(path, f"`object.static` must be true or false, got {static!r}")
        ok = False
    obj.static = static is True
    return obj if ok else None


def parse_supports(root: Path, value: Any, path: Path, out: ProblemList) -> list[SupportInfo]:
    """`supports:` of session.yaml: a list of {name, mesh (world coordinates, metres), grip}."""
    if value is None:
        return []
    if not isinstance(value, list):
        out.fatal(path, f"`supports` must be a list of {{name, mesh, grip}} entries, got {value!r}")
        return []
    supports = []
    for i, entry in enumerate(value):
        key = f"supports[{i}]"
        if not isinstance(entry, dict) or not isinstance(entry.get("mesh"), str) or not entry["mesh"]:
            out.fatal(path, f"`{key}` must be a mapping with `mesh` (a mesh file in world coordinates), got {entry!r}")
            continue
        for k in entry:
            if k not in SUPPORT_KEYS:
                out.warn(path, f"unknown key `{key}.{k}` ignored (known: {', '.join(SUPPORT_KEYS)})")
        grip = entry.get("grip", False)
        if not isinstance(grip, bool):
            out.fatal(path, f"`{key}.grip` must be true or false, got {grip!r}")
            continue
        mesh_path = session_file(root, entry["mesh"], f"{key}.mesh", path, out)
        if mesh_path is None:
            continue
        mesh = _read_support_mesh(mesh_path, f"{key}.mesh", out)
        if mesh is not None:
            supports.append(SupportInfo(str(entry.get("name") or mesh_path.stem), mesh_path, grip, mesh))
    return supports


def _load_named_mesh(mesh_path: Path, what: str, key: str, out: ProblemList) -> trimesh.Trimesh | None:
    """The `what` mesh named by session.yaml's `key`, or None with a fatal problem: missing or unreadable."""
    if not mesh_path.is_file():
        out.fatal(mesh_path, f"{what} mesh missing (named by `{key}` in session.yaml)")
        return None
    try:
        return load_mesh_file(mesh_path)
    except Exception as exc:  # trimesh raises many kinds on bad files
        out.fatal(mesh_path, f"{what} mesh unreadable ({type(exc).__name__}: {exc})")
        return None


def _read_support_mesh(mesh_path: Path, key: str, out: ProblemList) -> trimesh.Trimesh | None:
    """A support's mesh, or None with a fatal problem: missing, unreadable, no faces, not metres."""
    mesh = _load_named_mesh(mesh_path, "support", key, out)
    if mesh is None:
        return None
    vertices = np.asarray(mesh.vertices)
    if len(mesh.faces) == 0 or not np.isfinite(vertices).all():
        out.fatal(mesh_path, "support mesh has no faces or non-finite vertices")
        return None
    extent = float(np.ptp(vertices, axis=0).max())
    if extent > SUPPORT_EXTENT_M:
        out.fatal(mesh_path, f"support mesh is {extent:.4g} m across (over {SUPPORT_EXTENT_M:g} m): is it in "
                  "millimetres? It must be in metres, world coordinates")
        return None
    return mesh


def session_file(root: Path, name: str, key: str, yaml_path: Path, out: ProblemList) -> Path | None:
    """root / name when that file lies inside the session folder, symbolic links resolved; else None,
    with a problem naming the key: a session reads no file outside its folder."""
    path = root / name
    try:
        resolved = path.resolve()
        inside = resolved.is_relative_to(root.resolve())
    except (OSError, RuntimeError):  # a symlink loop
        resolved, inside = None, False
    if not inside:
        link = "" if resolved is None or resolved == Path(os.path.abspath(path)) else f" (a link to {resolved})"
        out.fatal(yaml_path, f"`{key}` {name!r}{link} points outside the session folder; "
                  "files named in session.yaml must lie inside it")
        return None
    return path


def mesh_content_issue(mesh: trimesh.Trimesh) -> str | None:
    """Why a loaded mesh cannot be the object (no faces, bad vertices or faces, not in metres), or None."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if len(faces) == 0:
        return "object mesh has no faces (the tracker renders its silhouette)"
    if not np.isfinite(vertices).all():
        return f"object mesh has {int((~np.isfinite(vertices).all(axis=1)).sum())} vertex/vertices with NaN or inf"
    if faces.min() < 0 or faces.max() >= len(vertices):
        return f"object mesh has face vertex indices out of range (0-{faces.max()} for {len(vertices)} vertices)"
    extent = float(np.ptp(vertices[np.unique(faces)], axis=0).max())
    lo, hi = MESH_EXTENT_RANGE_M
    if extent == 0:
        return "object mesh is degenerate: all its vertices are equal"
    if extent > hi:
        return f"object mesh is {extent:.4g} m across (over {hi:g} m): is the mesh in millimetres? It must be in metres"
    if extent < lo:
        return f"object mesh is {extent:.3g} m across (under {lo:g} m): is the mesh in metres?"
    return None


def _read_object_mesh(mesh_path: Path, out: ProblemList) -> trimesh.Trimesh | None:
    """The object's mesh, or None with a fatal problem when it is missing, unreadable or implausible."""
    mesh = _load_named_mesh(mesh_path, "object", "object.mesh", out)
    if mesh is None:
        return None
    issue = mesh_content_issue(mesh)
    if issue is not None:
        out.fatal(mesh_path, issue)
        return None
    if not mesh.is_watertight:
        out.warn(mesh_path, "object mesh is not watertight; its rendered silhouette and depth may have holes")
    return mesh


def _read_contact_vertices(root: Path, name: Any, mesh: trimesh.Trimesh | None, yaml_path: Path, out: ProblemList):
    if not isinstance(name, str) or not name:
        out.fatal(yaml_path, f"`object.contact_vertices` must name a JSON file, got {name!r}")
        return None
    path = session_file(root, name, "object.contact_vertices", yaml_path, out)
    if path is None:
        return None
    if not path.is_file():
        out.fatal(path, "contact vertex file missing (named by `object.contact_vertices`)")
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        out.fatal(path, f"malformed: cannot be parsed as JSON: {exc}")
        return None
    ids = data.get("vertices") if isinstance(data, dict) else None
    if not isinstance(ids, list) or not all(is_int(i) for i in ids):
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


def _parse_pose(pose: Any, path: Path, out: ProblemList) -> tuple[np.ndarray, np.ndarray] | None:
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
    issue = translation_issue(t)
    if issue:
        out.fatal(path, f"`object.initial_pose.t`: {issue}")
        return None
    return np.asarray(pose["R"], dtype=np.float64), t


def parse_contact_frames(value: Any, frame_ids: np.ndarray | None, path: Path, out: ProblemList):
    if value is None:
        return None
    if not isinstance(value, list):
        out.fatal(path, f"`contact_frames` must be a list of [start, end] ranges, got {value!r}")
        return None
    ranges = []
    ok = True
    for r in value:
        if not isinstance(r, (list, tuple)) or len(r) != 2 or not all(is_int(x) for x in r):
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


def parse_ground(value: Any, path: Path, out: ProblemList):
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


def parse_body(value: Any, path: Path, out: ProblemList) -> str:
    """The body model's name: `body: {model: NAME}` (or the short `body: NAME`), default anny;
    checks `body.mass_kg` too."""
    if value is None:
        return "anny"
    model = value if isinstance(value, str) else value.get("model", "anny") if isinstance(value, dict) else None
    model = model.strip() if isinstance(model, str) else model
    if isinstance(value, dict) and value.get("mass_kg") is not None and positive_number(value["mass_kg"]) is None:
        out.fatal(path, f"`body.mass_kg` must be a positive finite number, got {value['mass_kg']!r}")
    if model not in BODY_MODELS:
        got = value if model is None else model
        out.fatal(path, f"`body.model` must be one of {', '.join(BODY_MODELS)} (body: {{model: anny}}), got {got!r}")
        return "anny"
    return model


def depth_format_issue(img: np.ndarray) -> str | None:
    """Why a decoded depth image is not single-channel uint16 millimetres, or None."""
    if img.dtype == np.uint16 and img.ndim == 2:
        return None
    channels = 1 if img.ndim == 2 else img.shape[2]
    return f"depth PNG is {img.dtype} with {channels} channel(s), expected single-channel uint16 millimetres"


def size_issue(img: np.ndarray, cam: CameraInfo) -> str | None:
    h, w = img.shape[:2]
    if (w, h) != (cam.width, cam.height):
        return f"image is {w}x{h} but calibration.json gives {cam.width}x{cam.height} for camera {cam.name}"
    return None


GT_FILES = ("body_vertices.npy", "body_faces.npy", "object_poses.npz", "contact.npy", "keypoints3d.npy")
