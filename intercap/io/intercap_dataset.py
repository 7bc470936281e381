"""InterCap's released sequences (Huang et al., GCPR 2022 / IJCV 2024) to a session.

InterCap's layout (what this reads):
  SEQ_DIR = RGBD_Images/<subject 01..10>/<motion = object 01..10>/Seg_<n>/
    Frames_Cam<k>/color/<frame:05d>.jpg     k = 1..6, 1920x1080
    Frames_Cam<k>/depth/<frame:05d>.png     uint16 millimetres, registered to colour (resized when smaller)
  CALIB_DIR = their Data/ folder: calibration_first/, calibration_second/, calibration_third/, each with
    Color.json (camera 1) and Color_<k>.json (k = 2..6): {"f": [fx, fy], "c": [cx, cy],
    "k": [k1, k2, p1, p2, k3, k4, k5, k6] (OpenCV order), "R": Rodrigues vector (3,), "T": (3,) metres}
    with x_cam = Rodrigues(R) @ x_world + T and world = camera 1's colour frame.
  Which calibration applies depends on subject and motion, as InterCap's own tracking code maps it
  (`calibration_set`). OBJECTS_DIR/<motion>.ply: the object template (their objs/ folder).
  Optional fits: res_tuned.pkl, one dict per frame with "ob_pose" (axis-angle) and "ob_trans"
  posing the template centred on the mean of its vertices.

What it writes: cameras cam1..cam6, colour copied, depth as uint16 mm at the colour size,
calibration.json in InterCap's world (camera 1's colour frame; OpenCV axes; metres);
frame ids are InterCap's own frame numbers, so results line up with their files by index;
object.ply = the template centred on its vertex mean (so their fits are R = rotvec(ob_pose),
t = ob_trans in our convention); ground_truth/object_poses.npz from --fits when given.

Calibration direction, as InterCap's own code states it (github YinghaoHuang91/InterCap):
prox_first/prox/camera.py `PerspectiveCamera` builds its camera transform from
cv2.Rodrigues(R) and T and applies it to world points (x_cam = Rodrigues(R) @ x + T: world to
camera), and obj_track/utils.py `create_renderers` hard-codes the camera-to-world matrices
(MATs) that invert Data/calibration_first/Color_3.json (Rodrigues(R)^T and -Rodrigues(R)^T T
reproduce its MATs[2] to 6 decimals); the same file's distortion table `Ks` equals the
files' `k` (k1, k2, p1, p2, k3, k4, k5, k6: the tangential terms are the two small ones).
tests/io/test_dataset_conventions.py checks it on a fixture against cv2.projectPoints.
"""
from __future__ import annotations

import logging
import pickle
import re
import time
from pathlib import Path

import numpy as np
import yaml

from intercap.io.files import write_json
from intercap.io.importing import (
    DatasetImportError,
    camera_entry,
    copy_color,
    image_size,
    invert_rigid,
    read_json_file,
    rigid,
    staging,
    write_calibration,
    write_depth,
)

log = logging.getLogger(__name__)

CALIBRATION_SETS = ("first", "second", "third")
NUM_CAMERAS = 6
FRAME = re.compile(r"^(\d+)\.(jpg|jpeg|png)$")


def calibration_set(subject: int, motion: int) -> str:
    """The calibration session of a capture, as InterCap's tracking code selects it: the rig was
    re-calibrated twice, so subjects 1-3 (motions 1-7) and 4 (motions 1-4) use the first,
    subjects 8-10 and motions 8-10 of subjects 1, 2, 4-7 the second, subject 3's motions 8-10 and
    subjects 5-7's motions 1-7 the third. Their mapping leaves subject 4's motions 5-7 out, and
    their code then keeps the first set's matrices: so do we."""
    if subject in (8, 9, 10) or (subject in (1, 2, 4, 5, 6, 7) and motion in (8, 9, 10)):
        return "second"
    if (subject == 3 and motion in (8, 9, 10)) or (subject in (5, 6, 7) and motion <= 7):
        return "third"
    return "first"


def rotation_from_rodrigues(r) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(r, np.float64).reshape(3, 1))[0]


def read_intercap_camera(path: Path) -> tuple[np.ndarray, list[float], np.ndarray]:
    """(K (3, 3), dist, T_world_from_cam (4, 4)) of one Color*.json; its R, T map world to camera
    (InterCap's prox_first/prox/camera.py), so T_world_from_cam is their inverse."""
    data = read_json_file(path)
    try:
        (fx, fy), (cx, cy) = data["f"], data["c"]
        dist = [float(v) for v in data.get("k", [])]
        T_cam_from_world = rigid(rotation_from_rodrigues(data["R"]), data["T"])
    except (KeyError, ValueError, TypeError) as exc:
        raise DatasetImportError(f"{path}: needs f (2), c (2), R (Rodrigues, 3) and T (3): {exc}") from exc
    if len(dist) not in (0, 4, 5, 8):
        raise DatasetImportError(f"{path}: k has {len(dist)} coefficients; expected 4, 5 or 8")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], np.float64)
    return K, dist, invert_rigid(T_cam_from_world)


def calibration_file(calib_dir: Path, which: str, k: int) -> Path:
    return calib_dir / f"calibration_{which}" / ("Color.json" if k == 1 else f"Color_{k}.json")


def _frames(folder: Path) -> dict[int, Path]:
    if not folder.is_dir():
        raise DatasetImportError(f"{folder}: missing")
    return {int(m.group(1)): p for p in folder.iterdir() if (m := FRAME.match(p.name))}


def intercap_cameras(seq: Path, calib_dir: Path, which: str, color_files: list, first: int) -> tuple[list, list]:
    """(calibration.json camera entries, colour image sizes) of the segment's cameras."""
    cams, sizes = [], []
    for k in range(1, NUM_CAMERAS + 1):
        K, dist, T = read_intercap_camera(calibration_file(calib_dir, which, k))
        sample = color_files[k - 1].get(first) or next(iter(color_files[k - 1].values()), None)
        if sample is None:
            raise DatasetImportError(f"{seq / f'Frames_Cam{k}' / 'color'}: no frames")
        size = image_size(sample)
        cams.append(camera_entry(f"cam{k}", *size, K, dist, T))
        sizes.append(size)
    return cams, sizes


def write_intercap_object(tmp: Path, objects_dir, motion: int, doc: dict) -> None:
    """The motion's object template, centred, as object.ply (entered in `doc`)."""
    from intercap.session.format import load_mesh_file

    mesh_path = Path(objects_dir) / f"{motion:02d}.ply"
    if not mesh_path.is_file():
        raise DatasetImportError(f"{mesh_path}: missing (the object template of motion {motion:02d})")
    mesh = load_mesh_file(mesh_path)
    mesh.vertices = np.asarray(mesh.vertices, np.float64) - np.asarray(mesh.vertices, np.float64).mean(0)
    mesh.export(tmp / "object.ply")
    doc["object"] = {"mesh": "object.ply", "name": f"intercap_{motion:02d}"}


def write_intercap_fits(tmp: Path, fits, first: int, last: int) -> None:
    """InterCap's object fits (a pickle of per-frame ob_pose, ob_trans) of frames first..last as ground truth."""
    fits = Path(fits)
    frames = range(first, last + 1)
    try:
        with open(fits, "rb") as f:
            per_frame = pickle.load(f)
        pose = np.array([np.asarray(per_frame[i]["ob_pose"], np.float64).reshape(3) for i in frames])
        trans = np.array([np.asarray(per_frame[i]["ob_trans"], np.float64).reshape(3) for i in frames])
    except (OSError, pickle.UnpicklingError, KeyError, IndexError, TypeError) as exc:
        raise DatasetImportError(f"{fits}: needs one dict with ob_pose, ob_trans per frame {first}..{last}: "
                                 f"{exc}") from exc
    (tmp / "ground_truth").mkdir()
    np.savez(tmp / "ground_truth" / "object_poses.npz",
             R=np.stack([rotation_from_rodrigues(p) for p in pose]), t=trans)


def import_intercap(seq_dir, out_session, calib_dir, objects_dir=None, fits=None, which: str | None = None,
                    subject: int | None = None, motion: int | None = None, fps: float = 30.0,
                    overwrite: bool = False, start: int | None = None, end: int | None = None) -> dict:
    """Import one InterCap segment into `out_session` (a temporary folder renamed at the end).

    Subject and motion come from SEQ_DIR's path (<subject>/<motion>/Seg_<n>) unless given; `which`
    overrides the calibration set. Frames [start, end] (InterCap frame numbers, inclusive)."""
    t0 = time.perf_counter()
    seq = Path(seq_dir)
    if not seq.is_dir():
        raise DatasetImportError(f"{seq}: not a folder")
    try:
        subject = int(seq.parent.parent.name) if subject is None else int(subject)
        motion = int(seq.parent.name) if motion is None else int(motion)
    except ValueError as exc:
        raise DatasetImportError(f"{seq}: expected .../<subject>/<motion>/Seg_<n> (or pass --subject and --motion)") from exc
    which = which or calibration_set(subject, motion)
    if which not in CALIBRATION_SETS:
        raise DatasetImportError(f"calibration set must be one of {', '.join(CALIBRATION_SETS)}, got {which!r}")
    calib_dir = Path(calib_dir)
    color_files = [_frames(seq / f"Frames_Cam{k}" / "color") for k in range(1, NUM_CAMERAS + 1)]
    depth_files = [_frames(seq / f"Frames_Cam{k}" / "depth") for k in range(1, NUM_CAMERAS + 1)]
    ids = sorted(set().union(*color_files))
    ids = [i for i in ids if (start is None or i >= start) and (end is None or i <= end)]
    if not ids:
        raise DatasetImportError(f"{seq}: no colour frames in Frames_Cam*/color (range {start}..{end})")
    first, last = ids[0], ids[-1]

    cams, sizes = intercap_cameras(seq, calib_dir, which, color_files, first)
    dropped = {}
    with staging(out_session, overwrite) as tmp:
        for k in range(1, NUM_CAMERAS + 1):
            cdir, ddir = tmp / f"cam{k}" / "color", tmp / f"cam{k}" / "depth"
            cdir.mkdir(parents=True)
            ddir.mkdir(parents=True)
            miss = []
            for i in range(first, last + 1):
                color, depth = color_files[k - 1].get(i), depth_files[k - 1].get(i)
                if color is None or depth is None:
                    miss.append(i)  # a dropped frame of this view: tolerated by the session format
                    continue
                copy_color(color, cdir, i)
                write_depth(depth, ddir, i, sizes[k - 1])
            dropped[f"cam{k}"] = miss
        write_calibration(tmp, cams, world="metres; InterCap's world: camera 1's colour camera frame (OpenCV axes)")
        doc: dict = {"fps": float(fps), "frames": {"start": first, "end": last}, "body": {"model": "anny"}}
        if objects_dir is not None:
            write_intercap_object(tmp, objects_dir, motion, doc)
        if fits is not None:
            write_intercap_fits(tmp, fits, first, last)
        (tmp / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        write_json(tmp / "intercap_import.json", {"sequence": str(seq), "subject": subject, "motion": motion,
                                                  "calibration": f"calibration_{which}", "dropped": dropped})
    return {"frames": last - first + 1, "fps": float(fps), "cameras": [c["name"] for c in cams],
            "calibration": f"calibration_{which}", "dropped": dropped, "seconds": time.perf_counter() - t0}
