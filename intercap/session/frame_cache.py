"""Decoded frames kept for one run: each depth and mask PNG decoded once, not once per stage.

The object, body, contact and global stages each read every frame's depth and masks, in their own
processes, so a run decoded every depth PNG three times and every mask up to four times (on one
H200, `cv2.imdecode` was the largest self time after the autograd engine). `build` decodes them
once, in IO threads, into raw files under OUT/cache/frames/: per camera and kind one file of
fixed-size slots, depth as its uint16 millimetres, masks as packed bits. `attach` makes a
Session read from there with one `pread` a frame (not a memory map: what a take touches would
otherwise count in the RSS of every worker). Values are exactly those of the PNGs.

A cache is tied to the session's files by their sizes and modification times; a mismatch (the
session changed, another session) means it is not attached, and `build` remakes it. Files found
unusable while building are listed with their reasons, so every process that attaches the cache
warns about them and drops those frames as reading them would have. The pipeline removes the
cache when its run finishes; a killed run keeps it for the resume.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np

from intercap.session.problems import ProblemList

log = logging.getLogger(__name__)

CACHED_KINDS = ("depth", "mask_person", "mask_object")
VERSION = 1
MANIFEST = "manifest.json"


def cache_dir(out_dir: Path | str) -> Path:
    return Path(out_dir) / "cache" / "frames"


def slot_bytes(kind: str, height: int, width: int) -> int:
    """Bytes of one frame: uint16 depth, or one bit a pixel of a mask."""
    return height * width * 2 if kind == "depth" else (height * width + 7) // 8


def _stored(session) -> list[tuple[int, str]]:
    """The (camera, kind) pairs the session has files of."""
    return [(c, kind) for c in range(session.num_cameras) for kind in CACHED_KINDS if session.has_kind(kind)[c]]


def cache_bytes(session) -> int:
    """How large the cache of this session is on disk."""
    return sum(slot_bytes(kind, session.cameras[c].height, session.cameras[c].width) * session.num_frames
               for c, kind in _stored(session))


def _signature(session) -> str:
    """Digest of the cached files' names, sizes and modification times (unusable ones included)."""
    digest = hashlib.sha1(f"{VERSION} {Path(session.root).resolve()} {session.frame_ids[0]}".encode())
    for c, kind in _stored(session):
        for frame_id, path in sorted(session._files[c][kind].items()):
            stat = path.stat()
            digest.update(f"{c} {kind} {frame_id} {path.name} {stat.st_size} {stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()


class FrameCache:
    """Reads the decoded frames of an attached cache (`attach`); thread-safe (`os.pread`)."""

    def __init__(self, folder: Path, session, present: dict[tuple[int, str], np.ndarray]):
        self.folder = folder
        self.first = int(session.frame_ids[0])
        self.sizes = [(cam.height, cam.width) for cam in session.cameras]
        self.present = present  # (camera, kind) -> (T,) bool: the frame was decoded and stored
        self._fds = {key: os.open(folder / f"{key[0]}_{key[1]}.bin", os.O_RDONLY) for key in present}

    def __del__(self) -> None:
        for fd in getattr(self, "_fds", {}).values():
            os.close(fd)

    def read(self, c: int, kind: str, frame_id: int) -> np.ndarray | None:
        """The stored frame: (H, W) uint16 depth or bool mask; None when it is not stored."""
        present = self.present.get((c, kind))
        t = int(frame_id) - self.first
        if present is None or not 0 <= t < len(present) or not present[t]:
            return None
        H, W = self.sizes[c]
        size = slot_bytes(kind, H, W)
        slot = np.empty((H, W), "<u2") if kind == "depth" else np.empty(size, np.uint8)  # writable, as a PNG's
        if hasattr(os, "preadv"):  # straight into the array
            got = os.preadv(self._fds[(c, kind)], [slot], t * size)
        else:  # macOS before 11
            data = os.pread(self._fds[(c, kind)], size, t * size)
            got = len(data)
            slot.reshape(-1).view(np.uint8)[:got] = np.frombuffer(data, np.uint8)
        if got != size:
            raise OSError(f"{self.folder}: frame cache truncated at camera {c}, {kind}, frame {frame_id}")
        return slot if kind == "depth" else np.unpackbits(slot, count=H * W).reshape(H, W).view(bool)


def build(session, out_dir: Path | str, progress: bool = True) -> bool:
    """Decode the session's depth and masks into OUT/cache/frames/ (unless a matching cache is
    there) and attach it to `session`. False, leaving the session reading its PNGs, when the
    disk has not room for it."""
    from tqdm import tqdm

    from intercap.session.session import in_threads

    folder = cache_dir(out_dir)
    signature = _signature(session)
    if attach(session, out_dir, signature):
        return True
    need = cache_bytes(session)
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(folder).free
    if need > free - (1 << 30):  # leave a GiB for the results
        log.warning("frames not cached: %.1f GB needed, %.1f GB free in %s; every stage decodes the PNGs",
                    need / 1e9, free / 1e9, folder)
        shutil.rmtree(folder, ignore_errors=True)
        return False
    T, keys = session.num_frames, _stored(session)
    present = {key: np.zeros(T, bool) for key in keys}
    fds = {key: os.open(folder / f"{key[0]}_{key[1]}.bin", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
           for key in keys}
    dropped: list[dict] = []
    bar = tqdm(total=T, desc="frames: decoding once", unit="frame", disable=not progress)

    def decode_frame(t: int) -> None:
        frame_id = int(session.frame_ids[t])
        for c, kind in keys:
            image = (session.read_depth_millimetres(c, frame_id) if kind == "depth"
                     else session.read_mask(c, frame_id, kind.removeprefix("mask_")))
            if image is None:
                path = session._files[c][kind].get(frame_id)
                if path is not None:  # there, but unusable: `_read_image` said why
                    name = ProblemList(session.root).rel(path)
                    reason = next((p.message for p in reversed(session.problems) if p.path == name), "unusable")
                    dropped.append({"camera": c, "kind": kind, "frame": frame_id, "message": reason})
                continue
            H, W = image.shape
            data = image.astype("<u2").tobytes() if kind == "depth" else np.packbits(image).tobytes()
            os.pwrite(fds[(c, kind)], data, t * slot_bytes(kind, H, W))
            present[(c, kind)][t] = True
        bar.update(1)

    try:
        in_threads(decode_frame, range(T))
    finally:
        bar.close()
        for fd in fds.values():
            os.close(fd)
    manifest = {"version": VERSION, "signature": signature, "frames": T, "dropped": dropped,
                "present": {f"{c}_{kind}": np.flatnonzero(~mask).tolist() for (c, kind), mask in present.items()}}
    (folder / MANIFEST).write_text(json.dumps(manifest))  # last: a killed build leaves no manifest
    return attach(session, out_dir, signature)


def attach(session, out_dir: Path | str, signature: str | None = None) -> bool:
    """Make `session` read depth and masks from OUT/cache/frames/ when a cache of these very files
    is there (True); else leave it reading its PNGs (False). `signature`: the session files'
    (`_signature`), when the caller has it already."""
    folder = cache_dir(out_dir)
    try:
        manifest = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        return False
    if (manifest.get("version"), manifest.get("frames")) != (VERSION, session.num_frames) \
            or manifest.get("signature") != (signature or _signature(session)):
        return False
    present = {}
    for key in _stored(session):
        missing = manifest["present"].get(f"{key[0]}_{key[1]}")
        if missing is None:
            return False
        present[key] = np.ones(session.num_frames, bool)
        present[key][missing] = False
    for entry in manifest["dropped"]:  # as `_read_image` finds them: warned about, dropped
        session._drop(session._files[entry["camera"]][entry["kind"]][entry["frame"]], entry["message"])
    session.frame_cache = FrameCache(folder, session, present)
    return True


def open_session(session, out_dir: Path | str):
    """A worker's session (workers are given its path), reading the run's frame cache where one is,
    with the cameras `prepare` refined."""
    from intercap.session import Session

    if not hasattr(session, "frame_ids"):
        session = Session.load(session)
        session.use_run_frames(out_dir)  # `run --frames`
        session.use_refined_calibration(out_dir)
        attach(session, out_dir)
    return session


def remove(out_dir: Path | str) -> None:
    """Delete the cache (the run is finished)."""
    shutil.rmtree(cache_dir(out_dir), ignore_errors=True)
    try:
        (Path(out_dir) / "cache").rmdir()
    except OSError:
        pass
