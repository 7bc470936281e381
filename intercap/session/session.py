"""The session layer: read and check one capture session folder.

The folder layout is the contract in docs/session_format.md. Two entry points:

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

import dataclasses
import json
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np

from intercap.session.format import (
    GT_FILES,
    KIND_DIRS,
    KIND_EXTS,
    KINDS,
    OPTIONAL_KINDS,
    CameraInfo,
    GroundTruth,
    ObjectInfo,
    SupportInfo,
    decode_image,
    depth_format_issue,
    is_int,
    size_issue,
)
from intercap.session.openpose import drop_implausible_keypoints, openpose_to_array
from intercap.session.problems import Problem, ProblemList, SessionError, format_frame_list

IO_WORKERS = max(1, min(8, (os.cpu_count() or 2) * 2))
REFINED_CALIBRATION = Path("prepare") / "calibration_refined.json"  # in a run's OUT: the cameras' corrected poses


def refined_cameras(cameras: list[CameraInfo], out_dir: Path | str) -> list[CameraInfo] | None:
    """`cameras` with the poses a run's `prepare` stage refined (OUT/prepare/calibration_refined.json,
    written only when it corrected them); None when there is none. Intrinsics stay the session's."""
    path = Path(out_dir) / REFINED_CALIBRATION
    if not path.exists():
        return None
    poses = {c["name"]: np.asarray(c["T_world_from_cam"], np.float64) for c in json.loads(path.read_text())["cameras"]}
    names = [c.name for c in cameras]
    if set(poses) != set(names) or any(T.shape != (4, 4) or not np.isfinite(T).all() for T in poses.values()):
        raise ValueError(f"{path}: not this session's cameras ({', '.join(names)}); delete it and run prepare again")
    return [dataclasses.replace(c, T_world_from_cam=poses[c.name]) for c in cameras]


def in_threads(fn, items, threads: int | None = None) -> list:
    """`[fn(x) for x in items]`, in `threads` threads (default: the process's share of the cores,
    torch's thread count, at most IO_WORKERS): cv2 decodes images without the GIL, so a batch's
    frames read side by side where the cores are free (a GPU run's one process; on 2 cores with 2
    worker processes each reads alone). Each item runs whole in one thread (a frame's views and
    its seeded picks keep their order)."""
    import torch

    items = list(items)
    threads = min(IO_WORKERS, len(items), threads or torch.get_num_threads())
    if threads <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(max_workers=threads) as pool:
        return list(pool.map(fn, items))


def mask_to_bool(img: np.ndarray) -> np.ndarray:
    """(H, W) bool of a decoded mask (`Session.read_mask`); a bool one (the frame cache's) as it is."""
    if img.dtype == bool:
        return img
    if img.dtype == np.uint16 and img.max(initial=0) > 255:
        return img > 32767
    return img > 127


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
        supports: list[SupportInfo] = (),
    ):
        self.root = root
        self.fps = fps
        self.cameras = cameras
        self.frame_ids = frame_ids  # (T,) int64, contiguous
        self.object = object
        self.contact_frames = contact_frames
        self.ground = ground
        self.body_model = body_model
        self.supports = list(supports)  # fixed structures that can carry the body (physics)
        self.problems = problems  # non-fatal warnings; read_* append files they find unusable
        self._files = files  # per camera: kind -> {frame index: path} (None: folder absent)
        self._has_ground_truth = has_ground_truth
        self._bad: set[Path] = set()  # files found unusable (dropped)
        self._reported: set[Problem] = set(problems)
        self._lock = threading.Lock()
        self.frame_cache = None  # decoded depth and masks of this run (`frame_cache.attach`)
        self.run_frames: tuple[int, int] | None = None  # (first, last) when a run takes part of the range
        self._gt_offset = 0  # ground-truth row of frame_ids[0]
        self._last = int(frame_ids[-1]) if len(frame_ids) else -1  # the session's own last frame

    # -- loading ----------------------------------------------------------------
    @classmethod
    def load(cls, path: Path | str) -> "Session":
        """Load a session folder; raises SessionError listing every fatal problem at once."""
        from intercap.session.validate import inspect_session  # validate builds Sessions: import at call time

        session, problems = inspect_session(Path(path), deep=False)
        if session is None:
            raise SessionError(path, problems)
        return session

    def restrict_frames(self, first: int | None = None, last: int | None = None) -> None:
        """Take frames first..last (inclusive; None keeps that end) of the session's range only, as
        `run --frames` asks; ground_truth() is cut to them. ValueError outside the session's range."""
        lo, hi = int(self.frame_ids[0]), int(self.frame_ids[-1])
        first = lo if first is None else int(first)
        last = hi if last is None else int(last)
        if not lo <= first <= last <= hi:
            raise ValueError(f"frames {first}..{last}: outside the session's frames {lo}..{hi}, or empty")
        self._gt_offset += first - lo
        self.frame_ids = np.arange(first, last + 1, dtype=np.int64)
        start = first - self._gt_offset  # the session's own first frame
        self.run_frames = None if (first, last) == (start, self._last) else (first, last)

    def use_run_frames(self, out_dir: Path | str) -> bool:
        """Take the frame range a run recorded in OUT/run.json (`run --frames`); True when it did."""
        try:
            frames = json.loads((Path(out_dir) / "run.json").read_text()).get("frames")
        except (OSError, ValueError, AttributeError):
            return False
        if not frames or [int(self.frame_ids[0]), int(self.frame_ids[-1])] == list(frames):
            return False
        self.restrict_frames(*frames)
        return True

    def use_refined_calibration(self, out_dir: Path | str) -> bool:
        """Take the camera poses a run's `prepare` stage refined (`refined_cameras`); True when it did."""
        refined = refined_cameras(self.cameras, out_dir)
        if refined is not None:
            self.cameras = refined
        return refined is not None

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
        if is_int(cam):
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
            self.problems.append(Problem(ProblemList(self.root).rel(path), message, False))

    def _read_image(self, c: int, kind: str, frame_id: int, flags: int) -> np.ndarray | None:
        path = self._usable_path(c, kind, frame_id)
        if path is None:
            return None
        img, reason = decode_image(path, flags)
        if img is None:
            self._drop(path, reason)
            return None
        if kind == "depth":
            issue = depth_format_issue(img)
            if issue:
                self._drop(path, issue + "; treated as a dropped frame")
                return None
        issue = size_issue(img, self.cameras[c])
        if issue:
            self._drop(path, issue + "; treated as a dropped frame")
            return None
        return img

    def read_color(self, cam: str | int, frame_id: int) -> np.ndarray | None:
        """(H, W, 3) uint8 RGB, or None for a dropped/unreadable frame."""
        img = self._read_image(self._cam_index(cam), "color", frame_id, cv2.IMREAD_COLOR)
        return None if img is None else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def _read_cached(self, c: int, kind: str, frame_id: int, flags: int) -> np.ndarray | None:
        """`_read_image`, from the attached frame cache where it holds the frame (masks as bool)."""
        if self.frame_cache is not None and self._usable_path(c, kind, frame_id) is not None:
            img = self.frame_cache.read(c, kind, frame_id)
            if img is not None:
                return img
        return self._read_image(c, kind, frame_id, flags)

    def read_depth_millimetres(self, cam: str | int, frame_id: int) -> np.ndarray | None:
        """(H, W) uint16 millimetres as stored (0 = no measurement), or None for a dropped frame."""
        return self._read_cached(self._cam_index(cam), "depth", frame_id, cv2.IMREAD_UNCHANGED)

    def read_depth(self, cam: str | int, frame_id: int) -> np.ndarray | None:
        """(H, W) float32 metres (0 = no measurement), or None for a dropped/unreadable frame."""
        img = self.read_depth_millimetres(cam, frame_id)
        return None if img is None else np.divide(img, np.float32(1000.0), dtype=np.float32)

    def read_mask(self, cam: str | int, frame_id: int, kind: str) -> np.ndarray | None:
        """(H, W) bool (pixel > 127) for kind 'person' or 'object'; None when absent/unreadable.
        A 16-bit mask reads as its 8-bit counterpart: > 127 when it holds values up to 255 (0/255
        written as uint16), else > 32767 (0/65535)."""
        if kind not in ("person", "object"):
            raise ValueError(f"mask kind must be 'person' or 'object', got {kind!r}")
        flags = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH  # plain IMREAD_GRAYSCALE reads uint16 as value >> 8
        img = self._read_cached(self._cam_index(cam), f"mask_{kind}", frame_id, flags)
        return None if img is None else mask_to_bool(img)

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
        camera = self.cameras[self._cam_index(cam)]
        kp, implausible = drop_implausible_keypoints(kp, camera.width, camera.height)
        issues = issues + implausible
        if issues:
            problem = Problem(ProblemList(self.root).rel(path), "; ".join(issues), False)
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

        in_threads(fill, [(t, c) for t in range(len(ids)) for c in range(self.num_cameras)], IO_WORKERS)
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
        """Per camera: whether it has any `kind` file (optional inputs may be absent; an empty
        folder counts as absent)."""
        return [bool(self._files[c][kind]) for c in range(self.num_cameras)]

    def has_frame(self, cam: str | int, kind: str, frame_id: int) -> bool:
        """Whether this view has a usable `kind` file for this frame: where it has none, stages
        detect or derive that input for that view and frame only."""
        return self._usable_path(self._cam_index(cam), kind, frame_id) is not None

    def missing(self, kind: str) -> np.ndarray:
        """(C, T) bool: the views and frames without a usable `kind` file."""
        return ~self.availability()[kind]

    # -- ground truth -------------------------------------------------------------
    def ground_truth(self) -> GroundTruth | None:
        """The arrays of ground_truth/ (None if the session has none); shapes were checked at load."""
        if not self._has_ground_truth:
            return None
        gt = self.root / "ground_truth"
        gt_data = GroundTruth()
        rows = slice(self._gt_offset, self._gt_offset + self.num_frames)  # the frames of this run
        if (gt / "body_vertices.npy").is_file():
            gt_data.body_vertices = np.load(gt / "body_vertices.npy", mmap_mode="r")[rows].astype(np.float32)
        if (gt / "body_faces.npy").is_file():
            gt_data.body_faces = np.load(gt / "body_faces.npy").astype(np.int64, copy=False)
        if (gt / "object_poses.npz").is_file():
            with np.load(gt / "object_poses.npz") as z:
                gt_data.object_R = z["R"][rows].astype(np.float64)
                gt_data.object_t = z["t"][rows].astype(np.float64)
        if (gt / "contact.npy").is_file():
            gt_data.contact = np.load(gt / "contact.npy")[rows].astype(bool)
        if (gt / "keypoints3d.npy").is_file():
            gt_data.keypoints3d = np.load(gt / "keypoints3d.npy")[rows].astype(np.float32, copy=False)
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
        images = self.num_cameras * T
        for kind in OPTIONAL_KINDS:
            missing = int((~avail[kind]).sum())
            fill = "detected" if kind == "keypoints" else "derived"
            optional.append(f"{KIND_DIRS[kind]} {images - missing}/{images} images"
                            + (f" ({missing} to be {fill})" if missing else ""))
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
            if o.static:
                extra.append("static (a support)")
            lines.append(f"  object: {o.name} ({o.mesh_path.name}; {', '.join(extra)})")
        if self.contact_frames is not None:
            lines.append("  contact frames (annotated): " + ", ".join(f"{a}-{b}" for a, b in self.contact_frames))
        if self.ground is not None:
            p, n = self.ground
            lines.append(f"  ground: given (point {np.round(p, 3).tolist()}, normal {np.round(n, 3).tolist()})")
        else:
            lines.append("  ground: estimated from the data")
        lines.append(f"  body model: {self.body_model}")
        if self.supports:
            lines.append("  supports: " + ", ".join(f"{s.name} ({s.mesh_path.name}{', grip' if s.grip else ''})"
                                                    for s in self.supports))
        if self._has_ground_truth:
            gt = self.root / "ground_truth"
            have = [name.split(".")[0] for name in GT_FILES if (gt / name).is_file()]
            lines.append("  ground truth: " + ", ".join(have))
        else:
            lines.append("  ground truth: none")
        return "\n".join(lines)
