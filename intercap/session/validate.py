"""Checking a session before a long run: every file's content (`validate`), and the one
inspection that `Session.load` runs too (structure plus the first frames of each camera)."""
from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from intercap.session.format import (
    GT_FILES,
    KIND_DIRS,
    KINDS,
    CameraInfo,
    decode_image,
    depth_format_issue,
    frame_range,
    parse_body,
    parse_contact_frames,
    parse_fps,
    parse_ground,
    parse_object,
    parse_supports,
    read_calibration,
    read_session_yaml,
    scan_camera,
    size_issue,
)
from intercap.session.openpose import NUM_KEYPOINTS_3D, drop_implausible_keypoints, openpose_to_array
from intercap.session.problems import GT_ROTATION_TOL, Problem, ProblemList, format_frame_list, rotation_issue
from intercap.session.session import IO_WORKERS, Session

_FIRST_FRAME_TRIES = 5  # load: how many leading frames to try when the first ones do not decode (or hold no depth)


DEPTH_MEDIAN_RANGE_M = (0.2, 10.0)  # plausible median of a view's measured depth


class _FileIssue(NamedTuple):
    message: str
    fatal: bool
    dropped: bool  # the file cannot be used: the frame counts as dropped for this view


_EMPTY_DEPTH = _FileIssue("", False, False)  # a usable depth frame without a single measurement (all 0)


def depth_units_issue(depth_mm: np.ndarray) -> str | None:
    """Why a depth frame's median measured depth is implausible (depth not in millimetres), or None."""
    valid = depth_mm[depth_mm > 0]
    if not valid.size:
        return None
    median = float(np.median(valid)) / 1000.0
    lo, hi = DEPTH_MEDIAN_RANGE_M
    if lo <= median <= hi:
        return None
    guess = "was depth written in metres?" if median < lo else "was it written in units finer than millimetres?"
    return (f"median depth is {median:.3g} m, outside the plausible {lo:g}-{hi:g} m: depth PNGs hold uint16 "
            f"millimetres; {guess}")


def _check_frame_file(kind: str, path: Path, cam: CameraInfo | None) -> _FileIssue | None:
    """Decode one frame file and say what is wrong with it, or None if it is usable."""
    if kind == "keypoints":
        try:
            data = json.loads(path.read_text())
            kp, issues = openpose_to_array(data)
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            return _FileIssue(f"unreadable keypoints: {exc}; treated as a dropped frame", False, True)
        if cam is not None:
            issues += drop_implausible_keypoints(kp, cam.width, cam.height)[1]
        return _FileIssue("; ".join(issues), False, False) if issues else None
    flags = cv2.IMREAD_COLOR if kind == "color" else cv2.IMREAD_UNCHANGED
    img, reason = decode_image(path, flags)
    if img is None:
        return _FileIssue(reason, False, True)
    if kind == "depth":
        issue = depth_format_issue(img)
        if issue is not None:
            return _FileIssue(issue + "; treated as a dropped frame", False, True)
    if cam is not None:
        issue = size_issue(img, cam)
        if issue is not None:
            return _FileIssue(issue, True, True)
    if kind == "depth" and not img.any():
        return _EMPTY_DEPTH
    return None


def _report_missing_frames(
    root: Path,
    names: list[str],
    files: list[dict[str, dict[int, Path] | None]],
    frame_ids: np.ndarray,
    out: ProblemList,
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


def _check_ground_truth(root: Path, T: int | None, has_object: bool, out: ProblemList) -> bool:
    """Check shapes of ground_truth/ arrays (headers only for the big ones); True when any is present."""
    gt = root / "ground_truth"
    if not gt.is_dir():
        return False
    present = {name: (gt / name).is_file() for name in GT_FILES}
    if not any(present.values()):
        out.warn(gt, "folder present but holds none of " + ", ".join(GT_FILES))
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
            try:
                R, t = (z["R"] if "R" in z.files else None), (z["t"] if "t" in z.files else None)
            except ValueError as exc:  # e.g. object arrays, which need pickle
                out.fatal(path, f"unreadable arrays: {exc}")
                return True
            if R is None or t is None:
                out.fatal(path, "must hold arrays `R` (T, 3, 3) and `t` (T, 3)")
            elif R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (R.shape[0], 3):
                out.fatal(path, f"bad shapes R {R.shape}, t {t.shape}; expected (T, 3, 3) and (T, 3)")
            else:
                check_T(path, R.shape[0])
                bad = [i for i in range(len(R)) if rotation_issue(R[i], GT_ROTATION_TOL)]
                if bad:
                    out.fatal(path, f"R is not a rotation in {len(bad)} frame(s) (rows {format_frame_list(bad)})")
                moved = np.flatnonzero(~np.isfinite(t).all(1))
                if len(moved):
                    out.fatal(path, f"t is NaN or inf in {len(moved)} frame(s) (rows {format_frame_list(moved.tolist())})")
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


def _check_first_frames(
    cams: list[CameraInfo | None], files: list[dict], frame_ids: np.ndarray | None, bad: set, out: ProblemList
) -> None:
    """load's image check: the first decodable colour and depth frame of each camera (size, depth dtype,
    depth units); a camera whose first depth frames hold no measurement is warned about, and when
    every camera's do, that is fatal."""
    empty_views = []
    depth_views = 0
    for cam, cam_files in zip(cams, files):
        for kind in ("color", "depth"):
            have = cam_files[kind]
            if not have:
                continue
            ids = sorted(have) if frame_ids is None else [int(i) for i in frame_ids if int(i) in have]
            empty = []
            for idx in ids[:_FIRST_FRAME_TRIES]:
                path = have[idx]
                flags = cv2.IMREAD_COLOR if kind == "color" else cv2.IMREAD_UNCHANGED
                img, reason = decode_image(path, flags)
                if img is None:
                    out.warn(path, reason)
                    bad.add(path)
                    continue
                if _first_frame_issues(kind, path, img, cam, bad, out) == "empty":
                    empty.append(path)
                    continue  # look on for a frame with measurements to check the units on
                break
            else:
                if empty:
                    empty_views.append((empty[0].parent, len(empty)))
            depth_views += kind == "depth" and bool(ids)
    if empty_views and len(empty_views) == depth_views:
        folders = ", ".join(out.rel(folder) for folder, _ in empty_views)
        out.fatal(out.root, f"no depth measurement in the first frames of every camera ({folders}): every pixel "
                  "is 0 (0 = no measurement), so there is nothing to fit to")
        return
    for folder, n in empty_views:
        out.warn(folder, f"no depth measurement in the first {n} frame(s): every pixel is 0 (0 = no measurement)")


def _first_frame_issues(kind: str, path: Path, img: np.ndarray, cam: CameraInfo | None, bad: set,
                        out: ProblemList) -> str | None:
    """Report what is wrong with a camera's first decoded frame; "empty" for a depth frame with no
    measurement (the caller looks at the next one)."""
    if kind == "depth":
        issue = depth_format_issue(img)
        if issue:
            out.fatal(path, issue + " (first depth frame of this camera: its depth is taken to be "
                      "written in the wrong format)")
            bad.add(path)
    if cam is not None:
        issue = size_issue(img, cam)
        if issue:
            out.fatal(path, issue)
            bad.add(path)
    if kind != "depth" or path in bad:
        return None
    if not img.any():
        return "empty"
    issue = depth_units_issue(img)
    if issue:
        out.fatal(path, issue)
    return None


def _check_all_frames(
    names: list[str], cams: list[CameraInfo | None], files: list[dict], frame_ids: np.ndarray,
    bad: set, out: ProblemList,
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
    with ThreadPoolExecutor(max_workers=IO_WORKERS) as pool:
        results = list(pool.map(lambda job: _check_frame_file(*job), jobs))
    empty: dict[Path, list[int]] = {}  # depth folder -> frames without a measurement
    alike: dict[tuple, list[Path]] = {}  # (camera folder, message, fatal) -> the files it concerns
    for (_, path, _), issue in zip(jobs, results):
        if issue is _EMPTY_DEPTH:
            empty.setdefault(path.parent, []).append(int(path.stem))
            continue
        if issue is None:
            continue
        camera = out.root / Path(out.rel(path)).parts[0]
        alike.setdefault((camera, issue.message, issue.fatal), []).append(path)
        if issue.dropped:
            bad.add(path)
    for (camera, message, fatal), paths in alike.items():  # one line per camera and problem, not per file
        said = [p for p in out if p.message == message and p.path.split("/")[0] == out.rel(camera)]
        for p in said:  # the first-frame check's line for the same problem joins this one
            out.remove(p)
        count = len(paths) + len(said)
        report = out.fatal if fatal else out.warn
        if count == 1:
            report(paths[0], message)
        else:
            folders = sorted({out.rel(p.parent) for p in paths})
            report(camera, f"{message} ({count} files in {', '.join(folders)})")
    for name, cam_files in zip(names, files):
        for kind in ("color", "depth"):
            have = cam_files[kind]
            in_range = [have[int(i)] for i in frame_ids if have and int(i) in have]
            stated = any(p.fatal and p.path.split("/")[0] == name for p in out)  # why is said already
            if in_range and all(p in bad for p in in_range) and not stated:
                out.fatal(out.root / name / KIND_DIRS[kind], f"no usable {kind} frame: every file is unreadable")
    for folder, ids in empty.items():
        out.warn(folder, f"{len(ids)} depth frame(s) without a single measurement (every pixel 0): "
                 + format_frame_list(ids))


def inspect_session(root: Path, deep: bool) -> tuple[Session | None, list[Problem]]:
    """Every check on a session folder; the Session when nothing fatal was found."""
    out = ProblemList(root)
    if not root.is_dir():
        out.fatal(root, f"session folder {root} does not exist or is not a folder")
        return None, list(out)
    yaml_path = root / "session.yaml"
    cfg = read_session_yaml(root, out)
    fps = parse_fps(cfg, yaml_path, out) if cfg is not None else None
    has_object = cfg is None or "object" in cfg  # unreadable yaml: do not guess
    cfg = cfg or {}
    entries = read_calibration(root, out)

    names = [name for name, _ in entries if name is not None]
    cams = [cam for name, cam in entries if name is not None]
    names_seen: set = set()
    scan_names, scan_cams = [], []
    for name, cam in zip(names, cams):  # duplicates were reported already; scan each folder once
        if name not in names_seen:
            names_seen.add(name)
            scan_names.append(name)
            scan_cams.append(cam)
    files = [scan_camera(root, name, out) for name in scan_names]

    found_set: set = set()
    for cam_files in files:
        for kind in ("color", "depth"):
            found_set.update(cam_files[kind] or ())
    found = np.array(sorted(found_set), dtype=np.int64)
    if entries and not found.size and all(f["color"] is not None for f in files):
        out.fatal(root, "no frames found in any camera's color or depth folder")
    frame_ids = frame_range(cfg, found, yaml_path, out)
    if frame_ids is not None and files:
        _report_missing_frames(root, scan_names, files, frame_ids, out)

    obj = parse_object(root, cfg.get("object"), yaml_path, out)
    contact_frames = parse_contact_frames(cfg.get("contact_frames"), frame_ids, yaml_path, out)
    ground = parse_ground(cfg.get("ground"), yaml_path, out)
    body_model = parse_body(cfg.get("body"), yaml_path, out)
    supports = parse_supports(root, cfg.get("supports"), yaml_path, out)
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
        supports=supports,
        problems=[p for p in out if not p.fatal],
        files=files,
        has_ground_truth=has_gt,
    )
    session._bad |= bad
    return session, list(out)


def validate(path: Path | str) -> tuple[Session | None, list[Problem]]:
    """Check a session thoroughly (decodes every frame file once); never raises for content problems.
    Returns the Session (None when something is fatal) and every problem found, fatal or not."""
    return inspect_session(Path(path), deep=True)


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
