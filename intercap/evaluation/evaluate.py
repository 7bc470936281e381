"""Evaluation of a results folder against a session's ground truth (`intercap eval OUT --gt SESSION`).

Reads only the results files named in docs/outputs.md (``object_poses.npz``,
``body_vertices.npy``, ``body_faces.npy``, ``contact.npy``, ``keypoints3d.npy``);
any subset may exist. Every metric is computed from what both sides have; what
had to be skipped, and why, is listed in ``EvalResult.notes``.

Nothing here assumes the fitted body has the ground truth's topology: bodies are
compared surface to surface (exact point-to-triangle distances), objects by
pose, contact by label, keypoints joint by joint.

Frames the results mark untrusted (NaN) are left out of the means and counted
in a ``*_frames_missing`` metric. Units are in the metric names
(``_mm``, ``_deg``, ``_pct``, ``_mps2``).

Definitions:
- body_surface_mm: per frame, the mean of (samples on the fit -> GT surface) and
  (samples on GT -> fitted surface), averaged over frames.
- keypoint_mpjpe_mm: BODY_25 joints 0..24; hand_keypoint_mm: joints of each hand
  relative to its wrist (25 left, 46 right); NaN joints on either side ignored.
- object_add_mm: mean over mesh vertices of |(R x + t) - (R_gt x + t_gt)|;
  object_adds_mm (symmetric objects only): mean distance to the closest GT-posed vertex.
- penetration_*_mm: on ground-truth contact frames, the per-frame maximum depth
  of fitted body vertices inside the fitted (posed) object; ``_max`` is the
  largest over those frames, ``_mean`` / ``_median`` the mean / median over
  those frames of the per-frame maximum (0 for a frame without penetration),
  as InterCap reports it.
- contact_touch_*_pct: contact scored against geometry instead of the labels: frames where some
  ground-truth body vertex lies within TOUCH_M of the ground-truth object (or inside it);
  contact_label_is_touch_pct: how often the labels say the same (synthetic labels are the script's
  grasp phases; hands touch a moment before and after).
- jitter_mps2: mean vertex acceleration magnitude (second difference x fps^2).
"""
from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
import yaml

from intercap.evaluation.metrics import (
    add_distances,
    adds_distances,
    contact_scores,
    frames_finite,
    keypoint_errors,
    penetration_depths,
    rigid_jitter,
    summarise,
    touching_frames,
    vertex_jitter,
)
from intercap.evaluation.physics_figures import physics_file, physics_metrics
from intercap.evaluation.table import json_list, jsonable
from intercap.geometry.surfaces import TriangleSurface, symmetric_surface_distance
from intercap.parallel import cpu_count
from intercap.geometry.symmetry import detect_symmetry, rotation_angle_deg, symmetric_rotation_error_deg

TOUCH_M = 0.005  # contact_touch_*: a body vertex this close to the object touches it

RESULT_FILES = ("object_poses.npz", "body_vertices.npy", "body_faces.npy", "contact.npy", "keypoints3d.npy")


_FILE_NAMES = {name.split(".")[0]: name for name in RESULT_FILES}


@dataclass
class EvalResult:
    """Scalar metrics, per-frame error arrays (to find bad frames) and notes on what was skipped."""

    metrics: dict[str, float | int | None] = field(default_factory=dict)
    per_frame: dict[str, list] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"metrics": jsonable(self.metrics), "per_frame": jsonable(self.per_frame), "notes": list(self.notes)}


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - re-raised with the file named
        raise ValueError(f"{path}: cannot read ({exc})") from exc


def _load_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """R (T, 3, 3), t (T, 3) from an object_poses.npz, with the file named on any defect."""
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = set(z.files)
            if not {"R", "t"} <= keys:
                raise ValueError(f"{path}: needs arrays 'R' (T,3,3) and 't' (T,3), found {sorted(keys)}")
            R, t = np.asarray(z["R"], np.float64), np.asarray(z["t"], np.float64)
    except ValueError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise ValueError(f"{path}: cannot read ({exc})") from exc
    if R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (R.shape[0], 3):
        raise ValueError(f"{path}: expected R (T,3,3) and t (T,3), got R {R.shape} and t {t.shape}")
    return R, t


def _load_folder(folder: Path) -> tuple[dict[str, np.ndarray], dict[str, Path]]:
    """The contract files found in one folder (results or ground_truth/), checked for shape."""
    data: dict[str, np.ndarray] = {}
    files: dict[str, Path] = {}
    p = folder / "object_poses.npz"
    if p.is_file():
        data["object_R"], data["object_t"] = _load_poses(p)
        files["object_poses"] = p
    expected_ndim = {"body_vertices": 3, "body_faces": 2, "contact": 1, "keypoints3d": 3}
    for name, ndim in expected_ndim.items():
        p = folder / f"{name}.npy"
        if not p.is_file():
            continue
        arr = _load_npy(p)
        if arr.ndim != ndim or (ndim >= 2 and arr.shape[-1] != 3):
            raise ValueError(f"{p}: unexpected shape {arr.shape} for {name} (see docs/outputs.md)")
        data[name] = arr
        files[name] = p
    return data, files


def _frame_counts(data: dict[str, np.ndarray], files: dict[str, Path]) -> dict[str, tuple[Path, tuple, int]]:
    """file key -> (path, shape, T) for every array that has a frame axis."""
    out = {}
    for key, path in files.items():
        if key == "body_faces":
            continue
        arr = data["object_R"] if key == "object_poses" else data[key]
        out[key] = (path, arr.shape, arr.shape[0])
    return out


def check_frame_counts(res_data, res_files, gt_data, gt_files) -> int:
    """T shared by the results and the ground truth; ValueError naming both files when they differ."""
    gt_counts = _frame_counts(gt_data, gt_files)
    res_counts = _frame_counts(res_data, res_files)
    if not gt_counts:
        raise ValueError(f"no ground-truth arrays found under {next(iter(gt_files.values()), 'ground_truth/')}")
    ref_key = next(iter(gt_counts))
    ref_path, ref_shape, T = gt_counts[ref_key]
    for key, (path, shape, n) in gt_counts.items():
        if n != T:
            raise ValueError(
                f"ground truth disagrees on the number of frames: {path} has shape {shape} (T={n}) "
                f"but {ref_path} has shape {ref_shape} (T={T})"
            )
    for key, (path, shape, n) in res_counts.items():
        if n != T:
            gpath, gshape, _ = gt_counts.get(key, (ref_path, ref_shape, T))
            raise ValueError(
                f"frame count mismatch: results file {path} has shape {shape} (T={n}) but ground truth "
                f"{gpath} has shape {gshape} (T={T}); both must cover the same frames, counted from "
                f"frames.start in session.yaml"
            )
    return T


def run_frames(out_dir: Path) -> tuple[int, int] | None:
    """(first, last) session frames the run took, as OUT/run.json records them (`run --frames`)."""
    try:
        first, last = json.loads((Path(out_dir) / "run.json").read_text())["frames"]
        return int(first), int(last)
    except (OSError, ValueError, KeyError, TypeError):
        return None


def cut_to_run_frames(gt: dict[str, np.ndarray], out_dir: Path, start: int) -> int:
    """Cut the ground-truth arrays (rows from frames.start = `start`) to the frames the run took;
    returns the run's first frame. A run of the whole session leaves them as they are."""
    frames = run_frames(out_dir)
    if frames is None:
        return start
    first, last = frames
    lo = first - start
    for key in ("object_R", "object_t", "body_vertices", "contact", "keypoints3d"):
        if key in gt:
            if lo < 0 or last - start >= len(gt[key]):
                raise ValueError(f"the run took frames {first}..{last} but the ground truth covers "
                                 f"{start}..{start + len(gt[key]) - 1}")
            gt[key] = gt[key][lo:last - start + 1]
    return first


def _session_info(session_dir: Path) -> dict:
    """fps, first frame index and object mesh path from session.yaml."""
    path = session_dir / "session.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: is {session_dir} a capture session?")
    with open(path) as fh:
        cfg = yaml.safe_load(fh) or {}
    if "fps" not in cfg:
        raise ValueError(f"{path}: 'fps' is required")
    obj = cfg.get("object") or {}
    mesh = obj.get("mesh")
    frames = cfg.get("frames") or {}
    return {
        "fps": float(cfg["fps"]),
        "start": int(frames.get("start", 0)),
        "mesh_path": (session_dir / mesh) if mesh else None,
    }


def load_object_mesh(path: Path) -> trimesh.Trimesh:
    """The object's mesh in object coordinates (metres), duplicate vertices merged."""
    mesh = trimesh.load(str(path), force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: not a triangle mesh")
    return mesh


@dataclass
class _Inputs:
    """What one evaluation reads: both folders' arrays, which files exist, and session facts."""

    res: dict
    res_files: dict
    gt: dict
    gt_files: dict
    T: int
    fps: float
    mesh: trimesh.Trimesh | None
    surface: TriangleSurface | None
    result: EvalResult

    def has(self, what: str, res_keys, gt_keys) -> bool:
        """True when every input file is there; otherwise notes what is missing for `what`."""
        missing = [f"results {_FILE_NAMES[k]}" for k in res_keys if k not in self.res_files]
        missing += [f"ground_truth/{_FILE_NAMES[k]}" for k in gt_keys if k not in self.gt_files]
        if missing:
            self.result.notes.append(f"{what} skipped: no {', '.join(missing)}")
        return not missing


def _body_surface_metrics(inp: _Inputs, surface_samples: int, seed: int) -> None:
    m, pf = inp.result.metrics, inp.result.per_frame
    fv, ff, gv, gf = inp.res["body_vertices"], inp.res["body_faces"], inp.gt["body_vertices"], inp.gt["body_faces"]
    err = np.full(inp.T, np.nan)
    ok = frames_finite(fv) & frames_finite(gv)

    def frame_error(i: int) -> None:  # one mesh pair per frame: each needs its own search trees
        rng = np.random.default_rng([seed, int(i)])
        err[i] = symmetric_surface_distance(fv[i], ff, gv[i], gf, surface_samples, rng)

    # numpy and scipy's trees release the GIL: the frames side by side, 1.8x faster on two cores
    with ThreadPoolExecutor(max_workers=cpu_count()) as pool:
        list(pool.map(frame_error, np.flatnonzero(ok)))
    mean, med, p90, miss = summarise(err)
    m.update(body_surface_mm=mean, body_surface_mm_median=med, body_surface_mm_p90=p90,
             body_surface_frames_missing=miss)
    pf["body_surface_mm"] = json_list(err * 1000)


def _keypoint_metrics(inp: _Inputs) -> None:
    m, pf = inp.result.metrics, inp.result.per_frame
    body, hands = keypoint_errors(inp.res["keypoints3d"], inp.gt["keypoints3d"])
    mean, _, _, miss = summarise(body)
    m.update(keypoint_mpjpe_mm=mean, keypoint_frames_missing=miss)
    pf["keypoint_mpjpe_mm"] = json_list(body * 1000)
    if hands is None:
        inp.result.notes.append("hand_keypoint_mm skipped: keypoints3d has fewer than 67 joints")
        return
    mean, _, _, miss = summarise(hands)
    m.update(hand_keypoint_mm=mean, hand_keypoint_frames_missing=miss)
    pf["hand_keypoint_mm"] = json_list(hands * 1000)


def _object_metrics(inp: _Inputs, symmetric_object: bool | None, surface_samples: int, seed: int) -> None:
    m, pf, notes = inp.result.metrics, inp.result.per_frame, inp.result.notes
    Re, te, Rg, tg = inp.res["object_R"], inp.res["object_t"], inp.gt["object_R"], inp.gt["object_t"]
    ok = frames_finite(Re) & frames_finite(te) & frames_finite(Rg) & frames_finite(tg)

    def per_frame(values):  # (n_ok,) -> (T,) with NaN where a frame is untrusted
        full = np.full(inp.T, np.nan)
        full[ok] = values
        return full

    rot = per_frame(rotation_angle_deg(Re[ok], Rg[ok]))
    trans = per_frame(np.linalg.norm(te[ok] - tg[ok], axis=1))
    m["object_rotation_deg"] = summarise(rot, 1.0)[0]
    m["object_translation_mm"] = summarise(trans)[0]
    m["object_frames_missing"] = int((~ok).sum())
    pf["object_rotation_deg"], pf["object_translation_mm"] = json_list(rot), json_list(trans * 1000)
    if inp.mesh is None:
        return
    verts = np.asarray(inp.mesh.vertices, np.float64)
    add = per_frame(add_distances(verts, Re[ok], te[ok], Rg[ok], tg[ok]))
    mean, med, p90, _ = summarise(add)
    m.update(object_add_mm=mean, object_add_mm_median=med, object_add_mm_p90=p90)
    pf["object_add_mm"] = json_list(add * 1000)
    if symmetric_object is False:
        notes.append("object symmetry not considered (symmetric_object=False): no ADD-S")
        return
    sym = detect_symmetry(inp.mesh, surface_samples, seed)
    notes.append(f"object mesh {sym.description}")
    m["object_symmetric"] = int(sym.is_symmetric)
    if not (sym.is_symmetric or symmetric_object):
        return
    if not sym.is_symmetric:
        notes.append("symmetric_object=True but no symmetry found: object_rotation_sym_deg = object_rotation_deg")
    adds = per_frame(adds_distances(verts, Re[ok], te[ok], Rg[ok], tg[ok]))
    rsym = per_frame(symmetric_rotation_error_deg(Re[ok], Rg[ok], sym))
    mean, med, p90, _ = summarise(adds)
    m.update(object_adds_mm=mean, object_adds_mm_median=med, object_adds_mm_p90=p90,
             object_rotation_sym_deg=summarise(rsym, 1.0)[0])
    pf["object_adds_mm"], pf["object_rotation_sym_deg"] = json_list(adds * 1000), json_list(rsym)


def _contact_metrics(inp: _Inputs) -> None:
    pred = np.asarray(inp.res["contact"])
    ok = np.isfinite(pred.astype(np.float64))  # a float contact.npy may mark untrusted frames NaN
    label = np.asarray(inp.gt["contact"], bool)
    acc, prec, rec = contact_scores(pred[ok] > 0.5, label[ok])
    m = inp.result.metrics
    m.update(contact_accuracy_pct=acc, contact_precision_pct=prec, contact_recall_pct=rec,
             contact_frames_missing=int((~ok).sum()))
    if inp.surface is None or not all(k in inp.gt for k in ("body_vertices", "object_R", "object_t")):
        return
    bv, Rg, tg = inp.gt["body_vertices"], inp.gt["object_R"], inp.gt["object_t"]
    known = frames_finite(bv) & frames_finite(Rg) & frames_finite(tg)
    touch = np.zeros(inp.T, bool)
    touch[known] = touching_frames(bv[known], Rg[known], tg[known], inp.surface, TOUCH_M)
    acc, prec, rec = contact_scores(pred[ok & known] > 0.5, touch[ok & known])
    m.update(contact_touch_accuracy_pct=acc, contact_touch_precision_pct=prec, contact_touch_recall_pct=rec,
             contact_label_is_touch_pct=float(100 * (label[known] == touch[known]).mean()) if known.any() else None)


def _penetration_metrics(inp: _Inputs) -> None:
    """Fitted body into fitted object on GT-contact frames; mean/median are over frames of the per-frame max."""
    m = inp.result.metrics
    on = np.asarray(inp.gt["contact"], bool)
    bv, Re, te = inp.res["body_vertices"], inp.res["object_R"], inp.res["object_t"]
    ok = on & frames_finite(bv) & frames_finite(Re) & frames_finite(te)
    depth = np.full(inp.T, np.nan)
    if ok.any():
        depth[ok] = penetration_depths(bv[ok], Re[ok], te[ok], inp.surface)
    m["penetration_frames"] = int(on.sum())
    m["penetration_frames_missing"] = int((on & ~ok).sum())
    if ok.any():
        d = depth[ok] * 1000
        m.update(penetration_max_mm=float(d.max()), penetration_mean_mm=float(d.mean()),
                 penetration_median_mm=float(np.median(d)))
    else:
        m.update(penetration_max_mm=None, penetration_mean_mm=None, penetration_median_mm=None)
        inp.result.notes.append("penetration: no ground-truth contact frame with a trusted body and object")
    inp.result.per_frame["penetration_mm"] = json_list(depth * 1000)


def _jitter_metrics(inp: _Inputs) -> None:
    """Fitted body / object jitter, each next to the ground truth's (the floor a real motion has)."""
    m = inp.result.metrics
    if inp.has("body jitter", ["body_vertices"], []):
        m["jitter_mps2"] = vertex_jitter(inp.res["body_vertices"], inp.fps)[0]
        if "body_vertices" in inp.gt:
            m["jitter_gt_mps2"] = vertex_jitter(inp.gt["body_vertices"], inp.fps)[0]
    if inp.mesh is not None and inp.has("object jitter", ["object_poses"], []):
        verts = np.asarray(inp.mesh.vertices, np.float64)
        m["object_jitter_mps2"] = rigid_jitter(verts, inp.res["object_R"], inp.res["object_t"], inp.fps)
        if "object_R" in inp.gt:
            m["object_jitter_gt_mps2"] = rigid_jitter(verts, inp.gt["object_R"], inp.gt["object_t"], inp.fps)


def evaluate(out_dir, session_dir=None, *, symmetric_object: bool | None = None, surface_samples: int = 2000,
             seed: int = 0) -> EvalResult:
    """Compare a results folder with the session's ground truth; definitions in the module docstring.

    symmetric_object: None detects rotational symmetry of the object mesh;
    True forces the symmetric metrics (ADD-S, rotation error over the detected
    group); False turns them off. surface_samples: points per mesh for
    body_surface_mm (and for the symmetry test); seed makes the sampling repeatable.
    Raises ValueError when results and ground truth cover different numbers of frames.
    Physics figures (evaluation.physics_figures) come from OUT/physics/physics.npz ("not run"
    without it); with no session or no ground_truth/ they are all there is.
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"results folder {out_dir} not found")
    gt_dir = Path(session_dir) / "ground_truth" if session_dir is not None else None
    if gt_dir is None or not gt_dir.is_dir():  # real data: the physical plausibility figures only
        if not physics_file(out_dir).is_file():
            where = f"{gt_dir} not found" if gt_dir is not None else "no session with ground truth given"
            raise FileNotFoundError(f"{where}: evaluation needs a session with ground truth, or "
                                    f"{physics_file(out_dir)} for the physical plausibility figures")
        result = EvalResult()
        metrics, notes = physics_metrics(out_dir)
        result.metrics["frames"] = int(len(np.load(physics_file(out_dir))["valid"]))
        result.metrics.update(metrics)
        result.notes += ["no ground truth: physical plausibility figures only"] + notes
        return result
    session_dir = Path(session_dir)
    info = _session_info(session_dir)
    res, res_files = _load_folder(out_dir)
    gt, gt_files = _load_folder(gt_dir)
    if not res_files:
        raise FileNotFoundError(f"{out_dir} holds none of the results files {', '.join(RESULT_FILES)}")
    first = cut_to_run_frames(gt, out_dir, info["start"])
    T = check_frame_counts(res, res_files, gt, gt_files)

    result = EvalResult()
    result.metrics["frames"] = T
    result.per_frame["frame"] = list(range(first, first + T))
    mesh = surface = None
    if info["mesh_path"] is not None and info["mesh_path"].is_file():
        mesh = load_object_mesh(info["mesh_path"])
        surface = TriangleSurface(mesh.vertices, mesh.faces)
    elif info["mesh_path"] is not None:
        result.notes.append(f"object mesh {info['mesh_path']} not found: ADD, penetration, object jitter skipped")
    elif "object_poses" in res_files or "object_poses" in gt_files:
        result.notes.append("session.yaml names no object mesh: ADD, penetration, object jitter skipped")
    inp = _Inputs(res, res_files, gt, gt_files, T, info["fps"], mesh, surface, result)

    if inp.has("body_surface_mm", ["body_vertices", "body_faces"], ["body_vertices", "body_faces"]):
        _body_surface_metrics(inp, surface_samples, seed)
    if inp.has("keypoint_mpjpe_mm / hand_keypoint_mm", ["keypoints3d"], ["keypoints3d"]):
        _keypoint_metrics(inp)
    if inp.has("object metrics", ["object_poses"], ["object_poses"]):
        _object_metrics(inp, symmetric_object, surface_samples, seed)
    if inp.has("contact metrics", ["contact"], ["contact"]):
        _contact_metrics(inp)
    if inp.has("penetration", ["body_vertices", "object_poses"], ["contact"]) and surface is not None:
        _penetration_metrics(inp)
    _jitter_metrics(inp)
    metrics, notes = physics_metrics(out_dir, gt_dir if first == info["start"] else None)
    if first != info["start"] and physics_file(out_dir).is_file():
        notes.append(f"physics: the run took frames from {first} on (`run --frames`): not compared with "
                     "ground_truth/physics.npz")
    result.metrics.update(metrics)
    result.notes += notes
    return result
