"""Azure Kinect recordings (.mkv) -> a session, without the Azure Kinect SDK.

PyAV demuxes the Matroska file (k4a_recording.py): the COLOR track (MJPG, or raw NV12 / YUY2 / BGRA),
the DEPTH track (`b16g`: 16-bit big-endian millimetres; recordings from old SDK
versions tag it `YUY2` and store it little-endian), the file tags (serial number,
sync mode, K4A_START_OFFSET_NS, K4A_DEPTH_DELAY_NS) and the `calibration.json`
attachment. Depth is registered to the colour camera (k4a_calibration.py).

Time: a block's device timestamp is its pts + K4A_START_OFFSET_NS. Within one file the
depth image of a capture is the one whose timestamp minus the depth delay lies within
half a frame period of the colour image's; across files (a wired-sync rig) frames are
grouped the same way. A camera missing from a group is a dropped frame for that
camera (no file written, reported), never filled by shifting indices; a frame period
that no device has (every camera dropped it, e.g. one recording's drop) is a session
frame without files, so frame k stays at time k / fps.

Conventions of the written session: the camera of each device is its COLOUR camera
(depth registered to it), OpenCV axes (x right, y down, z forward), metres. The world
is the first recording's colour camera unless `--calibration` gives the rig's poses, matched
to the devices by serial number (each camera of the written calibration.json keeps its device's
`serial`). session.yaml holds the fps and, with `--object MESH [--mass-kg M]`, the object block
(the mesh copied into the session as object.ply / object.obj).
"""
from __future__ import annotations

import json
import logging
import os
import shutil
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from intercap.io.k4a_calibration import DepthRegistration
from intercap.io.k4a_recording import (
    K4AError,
    K4AMissingError,
    Recording,
    decode_color,
    decode_depth,
    frame_blocks,
    open_recording,
)

__all__ = ["K4AError", "K4AMissingError", "Recording", "align", "decode_depth", "import_k4a", "open_recording"]

log = logging.getLogger(__name__)


def _png_params() -> list[int]:
    """Fast lossless PNG for depth: zlib level 1, run-length strategy and the `up` filter
    (2x faster than libpng's adaptive filter choice here, and smaller)."""
    import cv2

    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):  # OpenCV >= 4.10
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]
    return params


_PNG_FAST = _png_params()


# ---------------------------------------------------------------- frame alignment


@dataclass
class Alignment:
    """Session frames over a rig: frames[g, d] = index into recording d's colour
    timestamps (-1 = dropped), depth[g, d] likewise for depth; times_ns[g] group time."""

    frames: np.ndarray  # (G, D) int
    depth: np.ndarray  # (G, D) int
    times_ns: np.ndarray  # (G,) int64
    fps: float


def align(recordings: list[Recording]) -> Alignment:
    """Group colour frames of all recordings whose device timestamps lie within half a
    frame period (the first one of a group is its anchor), keep the groups inside the
    time span every recording covers, and pair each colour frame with its depth frame."""
    fps = recordings[0].fps
    for r in recordings[1:]:
        if abs(r.fps - fps) > 0.01 * fps:
            raise K4AError(f"{r.path}: {r.fps:g} frames/s but {recordings[0].path} has {fps:g}")
    half = 0.5e9 / fps
    alone = [r.path.name for r in recordings if r.sync_mode.upper() == "STANDALONE"]
    if len(recordings) > 1 and alone:
        log.warning("%s recorded without wired sync (STANDALONE): device clocks are not shared, so pairing "
                    "frames by device time may pair the wrong frames (`intercap run` measures lags up to about a "
                    "frame: camera_time_offsets_ms in metrics.json)", ", ".join(alone))
    first = max(int(r.color_ts[0]) for r in recordings)
    last = min(int(r.color_ts[-1]) for r in recordings)
    if last < first - half:
        spans = "; ".join(f"{r.path.name}: {r.color_ts[0] / 1e9:.3f}-{r.color_ts[-1] / 1e9:.3f} s" for r in recordings)
        raise K4AError(
            f"{recordings[0].path}: recordings do not overlap in device time ({spans}); "
            "were the devices synchronised (wired sync, recorded together)?"
        )
    ts = np.concatenate([r.color_ts for r in recordings])
    dev = np.concatenate([np.full(len(r.color_ts), d) for d, r in enumerate(recordings)])
    idx = np.concatenate([np.arange(len(r.color_ts)) for r in recordings])
    order = np.argsort(ts, kind="stable")
    groups: list[list[int]] = []
    anchors: list[int] = []
    for k in order.tolist():  # one pass over the (few thousand) block times
        t = int(ts[k])
        if groups and t - anchors[-1] < half and dev[k] not in (dev[j] for j in groups[-1]):
            groups[-1].append(k)
        else:
            groups.append([k])
            anchors.append(t)
    keep = [g for g, a in enumerate(anchors) if first - half <= a <= last + half]
    rows, times = _timeline([anchors[g] for g in keep], fps)
    D = len(recordings)
    frames = np.full((len(times), D), -1, dtype=np.int64)
    for row, g in zip(rows, keep):
        for k in groups[g]:
            frames[row, dev[k]] = idx[k]
    depth = np.full_like(frames, -1)
    for d, r in enumerate(recordings):
        have = frames[:, d] >= 0
        if not r.depth_ts.size:
            continue
        want = r.color_ts[frames[have, d]] + r.depth_delay_ns  # (n,)
        j = np.clip(np.searchsorted(r.depth_ts, want), 1, len(r.depth_ts) - 1) if len(r.depth_ts) > 1 else np.zeros(
            len(want), dtype=np.int64)
        if len(r.depth_ts) > 1:
            j = np.where(np.abs(r.depth_ts[j - 1] - want) <= np.abs(r.depth_ts[j] - want), j - 1, j)
        ok = np.abs(r.depth_ts[j] - want) < half
        depth[np.flatnonzero(have), d] = np.where(ok, j, -1)
    return Alignment(frames, depth, times, fps)


def _timeline(anchors: list[int], fps: float) -> tuple[list[int], np.ndarray]:
    """Rows of the groups' anchor times on a timeline of one row per frame period, and
    the rows' times: where every device dropped a frame (a single recording's drop, or
    a rig's common one) the gap keeps its rows, empty, so later frames are not shifted
    in time (the fits' velocity and acceleration terms assume one period per frame)."""
    if not anchors:
        return [], np.zeros(0, dtype=np.int64)
    period = 1e9 / fps
    steps = [max(1, int(round((b - a) / period))) for a, b in zip(anchors[:-1], anchors[1:])]
    rows = np.concatenate([[0], np.cumsum(steps)]).astype(np.int64)
    times = np.round(anchors[0] + np.arange(rows[-1] + 1) * period).astype(np.int64)
    times[rows] = anchors
    return rows.tolist(), times


# ---------------------------------------------------------------- session writing


def frame_selection(n: int, fps: float, start, end, stride: int) -> np.ndarray:
    """Indices into the aligned timeline: start/end inclusive, as frame numbers or
    seconds from the first aligned frame ("2.5s")."""

    def as_frame(v, default):
        if v is None:
            return default
        s = str(v).strip().lower()
        return int(round(float(s[:-1]) * fps)) if s.endswith("s") else int(s)

    a, b = as_frame(start, 0), min(as_frame(end, n - 1), n - 1)
    if stride < 1:
        raise K4AError(f"--stride must be >= 1, got {stride}")
    sel = np.arange(max(a, 0), b + 1, stride)
    if not sel.size:
        raise K4AError(f"frame range {start}..{end} selects no frame of the {n} aligned frames")
    return sel


def _parse_size(text, native: tuple[int, int]) -> tuple[int, int]:
    if text is None:
        return native
    s = str(text).lower().rstrip("p")
    if "x" in s:
        w, h = (int(v) for v in s.split("x"))
    else:
        h = int(s)
        w = int(round(native[0] * h / native[1]))
    if w > native[0] or h > native[1] or w < 16 or h < 16:
        raise K4AError(f"--color-resolution {text}: must be a downscale of {native[0]}x{native[1]}")
    return w, h


def _match_calibration(recordings, names, cams: list[dict], path: Path) -> tuple[list[dict], list[str]]:
    """The calibration entry of each recording's device, and how each was matched.

    By serial number when the calibration's cameras carry one (`serial`, which this importer writes and
    `intercap calibrate` keeps): recordings given in another order than the calibration recording's
    still get their own device's pose. Without serials on both sides: by camera name, then by order,
    with a warning that the order must be the calibration recording's."""
    D = len(recordings)
    serials = [str(r.serial or "") for r in recordings]
    by_serial = {str(c["serial"]): c for c in cams if c.get("serial")}
    if by_serial and all(serials):
        missing = [f"{r.path.name} ({s})" for r, s in zip(recordings, serials) if s not in by_serial]
        if missing:
            raise K4AError(f"{path}: no camera with the serial number of {', '.join(missing)}; "
                           f"it has {', '.join(sorted(by_serial))}")
        return ([by_serial[s] for s in serials],
                [f"serial {s}" for s in serials])
    why = ("the calibration's cameras carry no serial number" if not by_serial else
           f"{', '.join(r.path.name for r, s in zip(recordings, serials) if not s)} carry no serial number")
    by_name = {str(c.get("name")): c for c in cams}
    if all(n in by_name for n in names):
        chosen, how = [by_name[n] for n in names], [f"name {n}" for n in names]
    elif len(cams) == D:
        chosen, how = list(cams), [f"position {d}" for d in range(D)]  # same order as the recordings
    else:
        raise K4AError(f"{path}: has cameras {sorted(by_name)}, need {names} or {D} cameras in recording order")
    if D > 1:
        log.warning("%s: %s, so poses go to the recordings by their order; give the recordings in the order "
                    "of the calibration recording", path, why)
    return chosen, how


def _rig_poses(recordings, names, calibration_file, uncalibrated: bool):
    """T_world_from_cam per camera, the names whose pose is a placeholder, and per camera which
    calibration entry gave its pose (empty without a calibration file)."""
    D = len(recordings)
    if calibration_file is not None:
        path = Path(calibration_file)
        try:
            cams = json.loads(path.read_text())["cameras"]
        except FileNotFoundError:
            raise K4AMissingError(f"{path}: calibration file not found") from None
        except (ValueError, KeyError, TypeError) as exc:
            raise K4AError(f"{path}: not a calibration.json of ours ({exc})") from None
        if not isinstance(cams, list) or not all(isinstance(c, dict) for c in cams):
            raise K4AError(f"{path}: not a calibration.json of ours (`cameras` is not a list of cameras)")
        chosen, how = _match_calibration(recordings, names, cams, path)
        sources = []
        for n, r, c, h in zip(names, recordings, chosen, how):
            sources.append(f"{n} ({r.path.name}): pose of calibration camera {c.get('name')!r}, matched by {h}")
            log.info("%s", sources[-1])
        poses = []
        for c in chosen:
            T = np.asarray(c["T_world_from_cam"], dtype=np.float64)
            if T.shape != (4, 4):
                raise K4AError(f"{path}: T_world_from_cam of {c.get('name')} is not 4x4")
            poses.append(T)
        return poses, [], sources
    if D > 1 and not uncalibrated:
        raise K4AError(
            f"{recordings[1].path}: {D} recordings, but the poses between devices are unknown: run "
            "`intercap calibrate` and pass its calibration.json with --calibration (or --uncalibrated "
            "to write placeholder poses, e.g. to import a calibration recording)"
        )
    return [np.eye(4) for _ in range(D)], names[1:], []


def default_workers(devices: int) -> int:
    """Worker count when none is given: one process per device of a rig (at most the CPU
    count), two threads for a single recording."""
    cpus = os.cpu_count() or 1
    return max(1, min(devices if devices > 1 else 2, cpus))


def _import_device(rec: Recording, size, lens, cam_dir: Path, frames: list[int], wanted, threads: int) -> None:
    """Write one device's frames: colour as recorded (or re-encoded when resized or raw) and
    depth registered to it. `frames[k]` is the session index of the k-th `wanted` block pair."""
    import cv2

    w, h = size
    (cam_dir / "color").mkdir(parents=True)
    (cam_dir / "depth").mkdir(parents=True)
    reg_fn = DepthRegistration(rec.calibration.depth, lens, rec.calibration.T_color_from_depth)

    def work(i: int, color: bytes, depth: bytes | None) -> None:
        if rec.color_format == "MJPG" and (w, h) == rec.color_size and color[:2] == b"\xff\xd8" \
                and b"\xff\xc4" in color[:4096]:
            if color[-2:] != b"\xff\xd9":
                raise K4AError(f"{rec.path}: a COLOR frame is cut short (truncated recording?)")
            (cam_dir / "color" / f"{i:06d}.jpg").write_bytes(color)  # the JPEG as recorded, no re-encoding
        else:
            img = decode_color(rec, color)
            if (w, h) != rec.color_size:
                img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(cam_dir / "color" / f"{i:06d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        if depth is not None:
            ok, buf = cv2.imencode(".png", reg_fn(decode_depth(rec, depth)), _PNG_FAST)
            (cam_dir / "depth" / f"{i:06d}.png").write_bytes(buf.tobytes())

    blocks = frame_blocks(rec, wanted)
    if threads <= 1:
        for i, (color, depth) in zip(frames, blocks):
            work(i, color, depth)
        return
    jobs = []
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for i, (color, depth) in zip(frames, blocks):
            jobs.append(pool.submit(work, i, color, depth))
            if len(jobs) > 4 * threads:  # bounded memory: wait for the oldest
                jobs.pop(0).result()
        for j in jobs:
            j.result()


def _import_devices(recs, al: Alignment, sel, sizes, lenses, tmp: Path, names, workers: int) -> None:
    """Each device's selected frames into tmp/<name>/: one process per device (at most `workers` at a time)
    for a rig, else `workers` threads."""
    tasks = []
    for d, r in enumerate(recs):
        rows = [(i, al.frames[g, d], al.depth[g, d]) for i, g in enumerate(sel) if al.frames[g, d] >= 0]
        wanted = [(int(r.color_ts[c]), int(r.depth_ts[k]) if k >= 0 else None) for _, c, k in rows]
        tasks.append((r, sizes[d], lenses[d], tmp / names[d], [i for i, _, _ in rows], wanted))
    if len(recs) > 1 and workers > 1:
        # one process per device at a time: demux, registration and PNG encoding of different
        # devices share nothing, and processes sidestep the GIL (threads gain little here)
        import multiprocessing as mp

        ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
        with ProcessPoolExecutor(max_workers=min(workers, len(recs)), mp_context=ctx) as pool:
            for job in [pool.submit(_import_device, *t, 1) for t in tasks]:
                job.result()
    else:
        for t in tasks:
            _import_device(*t, max(1, workers))


def _object_mesh(path, mass_kg):
    """The object mesh `--object` names, checked (a triangle mesh, .ply or .obj), or None; `--mass-kg`
    needs it and must be positive."""
    if path is None:
        if mass_kg is not None:
            raise K4AError("--mass-kg is the object's mass: give the object's mesh with --object too")
        return None
    path = Path(path)
    if not path.is_file():
        raise K4AMissingError(f"{path}: object mesh not found")
    if path.suffix.lower() not in (".ply", ".obj"):
        raise K4AError(f"{path}: the object mesh must be a .ply or .obj file (metres)")
    if mass_kg is not None and not (float(mass_kg) > 0):
        raise K4AError(f"--mass-kg {mass_kg}: the object's mass must be positive")
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file
        raise K4AError(f"{path}: cannot read the object mesh ({exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise K4AError(f"{path}: not a triangle mesh")
    extent = float(np.max(mesh.extents))
    if extent > 5.0:
        log.warning("%s: %.1f units across; session meshes are in metres (a mesh in millimetres?)", path, extent)
    return path


def _session_yaml(fps: float, mesh: Path | None, mass_kg) -> dict:
    """session.yaml's content: fps, and the object block when a mesh was given (copied as object.<ext>)."""
    doc: dict = {"fps": float(f"{fps:g}")}
    if mesh is not None:
        doc["object"] = {"mesh": f"object{mesh.suffix.lower()}", "name": mesh.stem}
        if mass_kg is not None:
            doc["object"]["mass_kg"] = float(mass_kg)
    return doc


def _write_session_files(tmp: Path, recs, al: Alignment, sel, names, lenses, poses, placeholders, calibration,
                         stride: int, mesh: Path | None = None, mass_kg=None) -> tuple[dict, dict, float]:
    """calibration.json, session.yaml (with the object's mesh copied beside it) and k4a_import.json in
    tmp; returns (dropped frames, frames without depth) per camera and the session's fps."""
    dropped = {n: [int(i) for i, g in enumerate(sel) if al.frames[g, d] < 0] for d, n in enumerate(names)}
    no_depth = {n: [int(i) for i, g in enumerate(sel) if al.frames[g, d] >= 0 and al.depth[g, d] < 0]
                for d, n in enumerate(names)}
    fps = al.fps / stride
    cams = []
    for d, n in enumerate(names):
        lens = lenses[d]
        cams.append({"name": n, "width": lens.width, "height": lens.height, "K": lens.K.tolist(),
                     # OpenCV rational model; the Azure Kinect's codx, cody are zero (checked on parsing)
                     "dist": lens.dist.tolist(), "T_world_from_cam": poses[d].tolist()})
        if recs[d].serial:  # kept by `intercap calibrate`, so a later import matches poses by device
            cams[-1]["serial"] = str(recs[d].serial)
    world = ("metres; OpenCV camera axes; the world is the colour camera of the first recording "
             f"({recs[0].path.name})" if calibration is None else f"metres; rig poses from {calibration}")
    calib = {"world": world, "cameras": cams}
    if placeholders:
        calib["extrinsics_unknown"] = placeholders
    (tmp / "calibration.json").write_text(json.dumps(calib, indent=1) + "\n")
    import yaml

    doc = _session_yaml(fps, mesh, mass_kg)
    if mesh is not None:
        shutil.copyfile(mesh, tmp / doc["object"]["mesh"])
    (tmp / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    report = {
        "source": "Azure Kinect recordings",
        "cameras": [{"name": n, "file": str(r.path), "serial": r.serial, "sync_mode": r.sync_mode,
                     "color_mode": r.color_mode, "depth_mode": r.depth_mode,
                     "start_offset_ns": r.start_offset_ns, "depth_delay_ns": r.depth_delay_ns,
                     "dropped_frames": dropped[n], "frames_without_depth": no_depth[n],
                     "device_time_ns": [int(r.color_ts[al.frames[g, d]]) if al.frames[g, d] >= 0 else None
                                        for g in sel]}
                    for d, (n, r) in enumerate(zip(names, recs))],
        "frame_time_ns": [int(al.times_ns[g]) for g in sel],
        "fps": fps, "stride": stride, "aligned_frames_total": int(len(al.times_ns)),
    }
    (tmp / "k4a_import.json").write_text(json.dumps(report, indent=1) + "\n")
    return dropped, no_depth, fps


def import_k4a(
    out_session,
    recordings,
    start=None,
    end=None,
    stride: int = 1,
    color_resolution=None,
    calibration=None,
    uncalibrated: bool = False,
    workers: int | None = None,
    overwrite: bool = False,
    object_mesh=None,
    mass_kg: float | None = None,
) -> dict:
    """Import Azure Kinect recordings into a session folder; returns a summary dict
    (frames, per-camera drops, timings, workers used). Written to a hidden folder beside
    `out_session` and renamed at the end, so a failure leaves no half session.

    workers: a rig is imported by one process per device (at most `workers` at a time;
    default: one per device, at most the CPU count), each streaming its recording with a
    bounded queue, so memory does not grow with the recording's length; a single recording
    uses `workers` threads (default: 2, at most the CPU count).

    object_mesh: the handled object's mesh (.ply / .obj, metres), copied into the session as object.<ext>
    and named in session.yaml's object block, with `mass_kg` when given; without it the session is
    body-only. calibration: with serial numbers in it, each device gets its own pose whatever the
    order of `recordings`; the summary's `pose_sources` says which camera got which pose."""
    import time

    t0 = time.perf_counter()
    out = Path(out_session)
    taken = (out.is_dir() and any(out.iterdir())) or (out.exists() and not out.is_dir())
    if taken and not overwrite:
        raise K4AError(f"{out}: already exists (choose a new folder or pass --overwrite)")
    recs = [open_recording(p) for p in recordings]
    if not recs:
        raise K4AError("no recording given")
    workers = default_workers(len(recs)) if workers is None else int(workers)
    if workers < 1:
        raise K4AError(f"--workers must be >= 1, got {workers}")
    names = [f"cam{d}" for d in range(len(recs))]
    poses, placeholders, pose_sources = _rig_poses(recs, names, calibration, uncalibrated)
    mesh = _object_mesh(object_mesh, mass_kg)
    al = align(recs)
    sel = frame_selection(len(al.times_ns), al.fps, start, end, stride)
    sizes = [_parse_size(color_resolution, r.color_size) for r in recs]
    lenses = [r.calibration.color.scaled(*s) for r, s in zip(recs, sizes)]
    t_setup = time.perf_counter() - t0

    tmp = out.parent / f".{out.name}.importing-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        _import_devices(recs, al, sel, sizes, lenses, tmp, names, workers)
        dropped, no_depth, fps = _write_session_files(tmp, recs, al, sel, names, lenses, poses, placeholders,
                                                      calibration, stride, mesh, mass_kg)
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {"frames": int(sel.size), "cameras": names, "dropped": dropped, "frames_without_depth": no_depth,
            "fps": fps, "seconds": time.perf_counter() - t0, "setup_seconds": t_setup,
            "placeholder_poses": placeholders, "pose_sources": pose_sources, "workers": workers,
            "parallel": "processes" if len(recs) > 1 and workers > 1 else ("threads" if workers > 1 else "none")}
