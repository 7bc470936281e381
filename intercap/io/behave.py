"""BEHAVE sequences (Bhatnagar et al., CVPR 2022) to a session.

BEHAVE's layout (what this reads):
  SEQ_DIR = sequences/<Date>_<Sub>_<object>[_<action>]/
    info.json                       optional: {"cat": object, "kinects": [0, 1, 2, 3], "config": ..., "intrinsic": ...}
                                    (config / intrinsic relative to SEQ_DIR)
    t0003.000/                      one folder per frame, named by its time in seconds
      k<k>.color.jpg                colour of Kinect k
      k<k>.depth.png                uint16 millimetres, registered to that colour image
      k<k>.person_mask.png|.jpg     optional person mask
      k<k>.obj_rend_mask.png|.jpg   optional object mask (or k<k>.obj_mask.*)
      <object>/fit01/<object>_fit.pkl   optional object fit {"angle": axis-angle (3,), "trans": (3,)}
  CALIB_DIR/<Date>/config/<k>/config.json            {"rotation": 9 (row-major), "translation": 3}, metres:
                                                     this colour camera -> world, world = camera k1's colour frame
  CALIB_DIR/<Date>/intrinsics/<k>/calibration.json   {"color": {"width", "height", "fx", "fy", "cx", "cy",
  (or CALIB_DIR/intrinsics/<k>/...)                   "opencv": [cx, cy, fx, fy, k1, k2, p1, p2, k3, k4, k5, k6]}}
  OBJECTS_DIR/<object>/<object>_f<N>.ply   the simplified template BEHAVE's fits were made with
                                           (else <object>/<object>.obj or .ply)

What it writes: cameras k0..k3 named as in BEHAVE, their colour copied, depth copied (resized by
nearest neighbour when stored smaller), masks as binary PNG; calibration.json with BEHAVE's world
(camera k1's colour frame; OpenCV axes, metres; distortion as OpenCV's 8 coefficients); frames
numbered 0.. in time order (behave_frames.json keeps each frame's folder name and time);
object.ply = the template centred on the mean of its vertices, exactly as BEHAVE poses it
(v = Rotation.from_rotvec(angle) @ (x - mean) + trans), so a fit is R = rotvec(angle), t = trans
in our convention; ground_truth/object_poses.npz when every frame has a fit (else
behave_object_fits.npz with a `valid` mask).

Conventions, as BEHAVE's own loader states them (github xiexh20/behave-dataset):
* data/kinect_transform.py `local2world`: world = p @ R.T + t with config.json's `rotation`
  (reshaped 3x3, row-major) and `translation` (data/utils.py `load_kinect_poses`), so the pair
  is our T_world_from_cam as it stands; `world2color_mesh` uses its inverse and says the
  world is camera k1's colour frame.
* data/kinect_calib.py `KinectCalib`: K from the colour block's fx, fy, cx, cy, and the
  distortion handed to cv2.projectPoints is `opencv[4:]` (OpenCV's order k1, k2, p1, p2, k3,
  k4, k5, k6); `opencv[:4]` is not read there and not here.
tests/io/test_dataset_conventions.py checks both on a fixture against cv2 directly.
"""
from __future__ import annotations

import logging
import os
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
    read_json_file,
    rigid,
    staging,
    write_calibration,
    write_depth,
    write_mask,
)
from intercap.session.problems import format_frame_list

log = logging.getLogger(__name__)

FRAME_DIR = re.compile(r"^t(\d+(?:\.\d+)?)$")
COLOR = re.compile(r"^k(\d+)\.color\.(jpg|jpeg|png)$")


def behave_frames(seq: Path) -> list[tuple[str, float]]:
    """(folder name, seconds) of every frame folder, in time order."""
    frames = sorted(((p.name, float(m.group(1))) for p in seq.iterdir() if p.is_dir() and (m := FRAME_DIR.match(p.name))),
                    key=lambda f: f[1])
    if not frames:
        raise DatasetImportError(f"{seq}: no BEHAVE frame folders (t0000.000/ ...)")
    return frames


def frame_slots(times: np.ndarray, fps: float) -> np.ndarray:
    """Session frame index of each frame time: its period count from the first, so a
    missing folder leaves an empty frame instead of shifting the later ones in time.
    Times that do not fall on distinct periods (uneven capture) keep consecutive indices."""
    slots = np.round((times - times[0]) * fps).astype(np.int64)
    return slots if len(slots) < 2 or (np.diff(slots) > 0).all() else np.arange(len(times))


def _first_file(*candidates: Path) -> Path | None:
    return next((p for p in candidates if p.is_file()), None)


def read_behave_camera(calib_dir: Path | None, info: dict, seq: Path, date: str, k: int) -> tuple[dict, np.ndarray]:
    """(colour intrinsics block, T_world_from_cam (4, 4)) of Kinect k; DatasetImportError naming a missing file."""
    roots_i, roots_c = [], []
    if info.get("intrinsic"):
        roots_i.append(Path(os.path.normpath(seq / info["intrinsic"])))
    if info.get("config"):
        roots_c.append(Path(os.path.normpath(seq / info["config"])))
    if calib_dir is not None:
        roots_i += [calib_dir / date / "intrinsics", calib_dir / "intrinsics"]
        roots_c += [calib_dir / date / "config", calib_dir / "config"]
    if not roots_i or not roots_c:
        raise DatasetImportError(f"{seq / 'info.json'}: no calibration paths; pass --calib DIR")
    ipath = _first_file(*(r / str(k) / "calibration.json" for r in roots_i)) or roots_i[0] / str(k) / "calibration.json"
    cpath = _first_file(*(r / str(k) / "config.json" for r in roots_c)) or roots_c[0] / str(k) / "config.json"
    intr, conf = read_json_file(ipath), read_json_file(cpath)
    color = intr.get("color")
    if not isinstance(color, dict) or not all(key in color for key in ("fx", "fy", "cx", "cy", "width", "height")):
        raise DatasetImportError(f"{ipath}: needs a `color` block with fx, fy, cx, cy, width, height")
    try:
        T = rigid(np.asarray(conf["rotation"], np.float64).reshape(3, 3), np.asarray(conf["translation"], np.float64))
    except (KeyError, ValueError) as exc:
        raise DatasetImportError(f"{cpath}: needs `rotation` (9 numbers) and `translation` (3): {exc}") from exc
    return {**color, "_file": str(ipath)}, T


def behave_dist(color: dict) -> list[float]:
    """OpenCV distortion from BEHAVE's colour block: opencv[4:] (k1, k2, p1, p2, k3[, k4, k5, k6]),
    as BEHAVE's data/kinect_calib.py passes it to cv2.projectPoints."""
    opencv = color.get("opencv")
    if opencv is None:
        return []
    dist = [float(v) for v in opencv[4:]]
    if len(dist) not in (0, 4, 5, 8):
        raise DatasetImportError(f"{color['_file']}: color.opencv has {len(opencv)} numbers; expected 4 + 4, 5 or 8")
    return dist


def find_template(objects_dir: Path | None, name: str) -> Path:
    """The template BEHAVE's fits were made with: the simplified <name>_f*.ply, else the full mesh."""
    if objects_dir is None:
        raise DatasetImportError(f"object {name!r}: pass --objects DIR (BEHAVE's objects/ folder)")
    folder = objects_dir / name
    simplified = sorted(folder.glob(f"{name}_f*.ply"))
    if simplified:
        return simplified[0]
    full = _first_file(folder / f"{name}.obj", folder / f"{name}.ply", objects_dir / f"{name}.ply")
    if full is None:
        raise DatasetImportError(f"{folder / (name + '_f1000.ply')}: missing (no template of {name!r} in {objects_dir})")
    return full


def behave_cameras(calib_dir, info: dict, seq: Path, date: str, kinects: list[int]) -> tuple[list, list]:
    """(calibration.json camera entries, colour image sizes) of the sequence's Kinects."""
    cams, sizes = [], []
    for k in kinects:
        color, T = read_behave_camera(calib_dir, info, seq, date, k)
        size = (int(color["width"]), int(color["height"]))
        K = [[color["fx"], 0.0, color["cx"]], [0.0, color["fy"], color["cy"]], [0.0, 0.0, 1.0]]
        cams.append(camera_entry(f"k{k}", *size, K, behave_dist(color), T))
        sizes.append(size)
    return cams, sizes


def _frame_file(folder: Path, k: int, stem: str, exts) -> Path | None:
    return _first_file(*(folder / f"k{k}.{stem}.{e}" for e in exts))


def copy_behave_frame(folder: Path, kinects: list[int], sizes: list, tmp: Path, i: int) -> None:
    """Each camera's colour, depth and masks of one BEHAVE frame folder as session frame i."""
    for c, k in enumerate(kinects):
        color = _frame_file(folder, k, "color", ("jpg", "jpeg", "png"))
        depth = _frame_file(folder, k, "depth", ("png",))
        if color is None or depth is None:
            missing = folder / f"k{k}.{'color.jpg' if color is None else 'depth.png'}"
            raise DatasetImportError(f"{missing}: missing (camera k{k} of this BEHAVE frame)")
        if i == 0 and image_size(color) != sizes[c]:
            raise DatasetImportError(f"{color}: {image_size(color)[0]}x{image_size(color)[1]} but its "
                                     f"calibration says {sizes[c][0]}x{sizes[c][1]}")
        copy_color(color, tmp / f"k{k}" / "color", i)
        write_depth(depth, tmp / f"k{k}" / "depth", i, sizes[c])
        person = _frame_file(folder, k, "person_mask", ("png", "jpg"))
        if person is not None:
            write_mask(person, tmp / f"k{k}" / "masks" / "person", i, sizes[c])
        obj = (_frame_file(folder, k, "obj_rend_mask", ("png", "jpg"))
               or _frame_file(folder, k, "obj_mask", ("png", "jpg")))
        if obj is not None:
            write_mask(obj, tmp / f"k{k}" / "masks" / "object", i, sizes[c])


def write_behave_object(tmp: Path, objects_dir, name: str, fits: np.ndarray, doc: dict) -> np.ndarray:
    """The centred template as object.ply (entered in `doc`) and BEHAVE's object fits (n_slots, 2, 3) as
    ground truth (all frames fitted) or behave_object_fits.npz; returns which frames have a fit."""
    from intercap.session.format import load_mesh_file

    have_fit = np.isfinite(fits).all((1, 2))
    mesh_path = find_template(objects_dir, name)
    mesh = load_mesh_file(mesh_path)
    centred = mesh.copy()
    centred.vertices = np.asarray(mesh.vertices, np.float64) - np.asarray(mesh.vertices, np.float64).mean(0)
    centred.export(tmp / "object.ply")
    doc["object"] = {"mesh": "object.ply", "name": name}
    if have_fit.any():
        from scipy.spatial.transform import Rotation

        R = np.full((len(fits), 3, 3), np.nan)
        R[have_fit] = Rotation.from_rotvec(fits[have_fit, 0]).as_matrix()
        t = fits[:, 1]
        if have_fit.all():
            (tmp / "ground_truth").mkdir()
            np.savez(tmp / "ground_truth" / "object_poses.npz", R=R, t=t)
        else:
            np.savez(tmp / "behave_object_fits.npz", R=R, t=t, valid=have_fit)
    return have_fit


def import_behave(seq_dir, out_session, calib_dir=None, objects_dir=None, overwrite: bool = False,
                  start: int | None = None, end: int | None = None) -> dict:
    """Import one BEHAVE sequence into `out_session` (written to a temporary folder, renamed at the end).

    Frames [start, end] (inclusive, in time order) when given. Returns a summary dict."""
    t0 = time.perf_counter()
    seq = Path(seq_dir)
    if not seq.is_dir():
        raise DatasetImportError(f"{seq}: not a folder")
    calib_dir = Path(calib_dir) if calib_dir else None
    objects_dir = Path(objects_dir) if objects_dir else None
    info = read_json_file(seq / "info.json") if (seq / "info.json").is_file() else {}
    parts = seq.name.split("_")
    date = parts[0]
    name = info.get("cat") or (parts[2] if len(parts) > 2 else None)
    frames = behave_frames(seq)[slice(start, None if end is None else end + 1)]
    if not frames:
        raise DatasetImportError(f"{seq}: no frames in the range {start}..{end}")
    first = seq / frames[0][0]
    kinects = [int(k) for k in info["kinects"]] if info.get("kinects") else sorted(
        int(m.group(1)) for p in first.iterdir() if (m := COLOR.match(p.name)))
    if not kinects:
        raise DatasetImportError(f"{first}: no k<k>.color.jpg images")

    cams, sizes = behave_cameras(calib_dir, info, seq, date, kinects)

    times = np.array([f[1] for f in frames])
    dt = np.diff(times)
    fps = float(np.round(1.0 / np.median(dt), 3)) if len(dt) and np.median(dt) > 0 else 30.0
    slots = frame_slots(times, fps)
    with staging(out_session, overwrite) as tmp:
        for c, k in enumerate(kinects):
            for sub in ("color", "depth"):
                (tmp / f"k{k}" / sub).mkdir(parents=True)
        n_slots = int(slots[-1]) + 1
        fits = np.full((n_slots, 2, 3), np.nan)
        for i, (folder_name, _) in zip(slots.tolist(), frames):
            folder = seq / folder_name
            copy_behave_frame(folder, kinects, sizes, tmp, i)
            if name:
                pkl = folder / name / "fit01" / f"{name}_fit.pkl"
                if pkl.is_file():
                    with open(pkl, "rb") as f:
                        fit = pickle.load(f)
                    fits[i] = (np.asarray(fit["angle"], np.float64).reshape(3),
                               np.asarray(fit["trans"], np.float64).reshape(3))
        write_calibration(tmp, cams, world="metres; BEHAVE's world: camera k1's colour camera frame (OpenCV axes)")
        doc: dict = {"fps": fps, "frames": {"start": 0, "end": n_slots - 1}, "body": {"model": "anny"}}
        have_fit = write_behave_object(tmp, objects_dir, name, fits, doc) if name else np.isfinite(fits).all((1, 2))
        (tmp / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        write_json(tmp / "behave_frames.json", {"sequence": str(seq), "frames": [
            {"frame": int(i), "folder": f, "time_s": s} for i, (f, s) in zip(slots, frames)],
            "object_fits": int(have_fit.sum())})
    gaps = sorted(set(range(n_slots)) - set(slots.tolist()))
    if gaps:
        log.warning("behave: %d frame time(s) of the %.3g fps timeline have no folder; they are session frames "
                    "without files (%s), so every frame keeps its time", len(gaps), fps, format_frame_list(gaps))
    elif len(dt) and np.ptp(dt) > 0.25 * np.median(dt):
        log.warning("behave: frame times are unevenly spaced (%.3f..%.3f s); fps %.3g is their median; "
                    "behave_frames.json keeps each frame's time", dt.min(), dt.max(), fps)
    return {"frames": n_slots, "folders": len(frames), "gaps": gaps, "fps": fps, "cameras": [c["name"] for c in cams],
            "object": name, "object_fits": int(have_fit.sum()), "seconds": time.perf_counter() - t0}
