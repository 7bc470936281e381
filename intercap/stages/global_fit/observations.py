"""What the data gives the joint fit: the per-frame stages' results (gaps filled), the contact stage's
labels, the object's shape (a signed-distance grid of its mesh), free-flight episodes, and each
window's observations (keypoints and person points as the body stage reads them, object points
from the object's pixels with depth).
"""
from __future__ import annotations

import copy
import hashlib
import logging
import multiprocessing
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from intercap.body_models import BodyParams
from intercap.body_models.base import (PARAM_FIELDS, axis_angle_to_matrix, continuous_axis_angle, fill_axis_angle_gaps,
                                       matrix_to_axis_angle)
from intercap.geometry.cameras import Cameras
from intercap.geometry.symmetry import mesh_symmetry, unwrap_symmetry
from intercap.io.files import per_frame_result, save_npz
from intercap.session.session import in_threads
from intercap.stages.body.observations import BodyObservations, KeypointSource, PersonPoints

log = logging.getLogger(__name__)

HANDS = ("left_hand", "right_hand")


class GlobalError(ValueError):
    """The joint fit cannot run: a per-frame result is missing or empty, or a setting is out of range."""


def fill_gaps(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T, ...) values with invalid frames replaced by linear interpolation in time between the
    nearest valid frames (held at the ends). Axis-angle and translations vary slowly enough over a
    short gap for this to be only a starting point; the optimisation does the rest."""
    values = np.array(values, dtype=np.float64)
    if valid.all() or not valid.any():
        return values
    t = np.arange(len(values))
    flat = values.reshape(len(values), -1)
    for k in range(flat.shape[1]):
        flat[~valid, k] = np.interp(t[~valid], t[valid], flat[valid, k])
    return flat.reshape(values.shape)


@dataclass
class PerFrameResults:
    """What the per-frame stages left, gaps filled; T frames."""

    body: BodyParams  # (T, ...), shape already the sequence mean
    body_valid: np.ndarray  # (T,) bool
    R: np.ndarray  # (T, 3, 3) object -> world
    t: np.ndarray  # (T, 3)
    object_valid: np.ndarray  # (T,) bool
    object_confidence: np.ndarray  # (T,) in [0, 1], 0 where not trusted
    contact: np.ndarray  # (T,) bool
    hand_distance: np.ndarray | None  # (T, 2) metres from the left, right hand to the object (None: not measured yet)
    grasping: np.ndarray | None = None  # (T, 2) bool: the hand holds the object (a contact frame, hand within reach)
    repaired: np.ndarray | None = None  # (T,) bool: fitted frames that had left their data, started from their neighbours
    acceleration_scale: np.ndarray | None = None  # (T,) the body's acceleration weight per frame, x the setting
    # (`acceleration_scale`: slow motion weighs more); None: 1 everywhere
    start_widths: np.ndarray | None = None  # (T,) frames: each frame's Gaussian width of the start; None: one width
    motion: BodyParams | None = None  # the start at its least width, where the take's motion is measured; None: body



def departed_frames(fit_to_data_mm: np.ndarray, valid: np.ndarray, factor: float, floor_mm: float,
                    reach: int) -> np.ndarray:
    """(T,) bool: fitted frames whose fit left their own depth points, `fit_to_data_mm` (the body stage's
    figure) above `factor` x the median of the fitted frames within `reach` either side, and above
    `floor_mm`. A frame without depth points (NaN) never counts."""
    gap = np.where(valid, np.asarray(fit_to_data_mm, np.float64), np.nan)
    out = np.zeros(len(gap), bool)
    for i in np.flatnonzero(np.isfinite(gap) & (gap > floor_mm)):
        near = gap[max(0, i - reach):i + reach + 1]
        near = near[np.isfinite(near)]
        out[i] = gap[i] > factor * float(np.median(near))
    return out


def shape_change_mm(model, body: BodyParams, own_shape: np.ndarray, valid: np.ndarray, frames: int = 32) -> float:
    """The largest mean vertex displacement (mm), over up to `frames` fitted frames spread over the take,
    between `body` (its shape the sequence mean) and the same poses with each frame's own phenotype."""
    rows = np.flatnonzero(valid)
    rows = rows[np.unique(np.linspace(0, len(rows) - 1, min(frames, len(rows))).round().astype(int))]
    picked = body[torch.as_tensor(rows)]
    with torch.no_grad():
        mean = model(picked).vertices
        picked.shape = torch.as_tensor(own_shape[rows], dtype=picked.shape.dtype, device=picked.shape.device)
        own = model(picked).vertices
    return float(1000 * (own - mean).norm(dim=-1).mean(-1).max())


SMOOTHED = ("global_orient", "transl", "body_pose", "left_hand_pose", "right_hand_pose")


def gaussian_low_pass(values: np.ndarray, sigma_frames) -> np.ndarray:
    """`values` (T, ...) low-passed in time by a Gaussian of `sigma_frames`: one width, or (T,) one per
    frame (each frame the weighted mean of the frames around it by its own width); the ends repeat the
    first and last frames, as `scipy.ndimage.gaussian_filter1d`'s mode "nearest" does."""
    from scipy.ndimage import gaussian_filter1d

    if np.ndim(sigma_frames) == 0:
        return gaussian_filter1d(values, float(sigma_frames), axis=0, mode="nearest")
    sigma = np.maximum(np.asarray(sigma_frames, np.float64), 1e-3)
    reach = int(np.ceil(4 * sigma.max()))
    offsets = np.arange(-reach, reach + 1)
    weights = np.exp(-0.5 * (offsets[None] / sigma[:, None]) ** 2)  # (T, 2 reach + 1)
    weights /= weights.sum(1, keepdims=True)
    index = np.clip(np.arange(len(values))[:, None] + offsets[None], 0, len(values) - 1)
    return np.concatenate([np.einsum("tk,tk...->t...", weights[lo:lo + 256], values[index[lo:lo + 256]])
                           for lo in range(0, len(values), 256)])  # 256 frames at a time: a long take's memory


def adaptive_smoothing_frames(vertices: np.ndarray, levels: np.ndarray, confidence: float) -> np.ndarray:
    """(T,) the widest of the Gaussian widths `levels` (frames, ascending) that each frame's body, vertices
    (T, U, 3) of the per-frame fits, can be low-passed by without moving it further than their noise
    explains: the intersection of confidence intervals (Katkovnik's ICI rule) on the mean vertex. A level's
    estimate differs from each narrower one's by at most `confidence` x the noise x both kernels' norms;
    where motion bends faster than the noise, a wide Gaussian departs from the narrow ones and is refused.
    The noise is the per-frame fits' own, from their second differences (white noise: sqrt(6) x its size),
    around each frame. A frame takes the narrowest width chosen within its reach, so that the fast part of
    a take is not flattened by the slow frames beside it."""
    from scipy.ndimage import gaussian_filter1d, minimum_filter1d

    T = len(vertices)
    levels = np.asarray(levels, np.float64)
    if T < 5:
        return np.full(T, levels[0])
    second = np.linalg.norm(vertices[2:] - 2 * vertices[1:-1] + vertices[:-2], axis=-1).mean(-1) / np.sqrt(6.0)
    noise = gaussian_filter1d(np.pad(second, 1, mode="edge"), max(levels[-1], 1.0) * 2, mode="nearest")
    estimates = [gaussian_filter1d(vertices, level, axis=0, mode="nearest") for level in levels]
    norms = 1.0 / np.sqrt(2.0 * np.sqrt(np.pi) * np.maximum(levels, 0.5))  # a Gaussian kernel's L2 norm
    chosen = np.zeros(T, int)
    agree = np.ones(T, bool)
    for j in range(1, len(levels)):
        for i in range(j):
            apart = np.linalg.norm(estimates[j] - estimates[i], axis=-1).mean(-1)
            agree &= apart <= confidence * noise * (norms[i] + norms[j])
        chosen[agree] = j
    sigma = levels[chosen]
    return np.minimum(sigma, minimum_filter1d(sigma, 2 * int(np.ceil(levels[-1])) + 1, mode="nearest"))


def smoothed_start(arrays: dict, sigma_frames) -> dict:
    """The per-frame parameters (T, ...) low-passed in time (Gaussian, `sigma_frames`: one width or one per
    frame), the joint fit's start: frame-to-frame noise of the per-frame fits is the stiffest part of the
    acceleration term, which a few L-BFGS steps leave mostly in place at 30 fps. The root's rotation is
    low-passed as a quaternion of one sign (a person turning round passes every angle), the joints' small
    rotations as axis-angle."""
    from scipy.spatial.transform import Rotation

    out = dict(arrays)
    for name in SMOOTHED:
        values = np.asarray(arrays[name], np.float64)
        if name == "global_orient":
            q = Rotation.from_rotvec(values).as_quat()
            turns = np.sign(np.einsum("ti,ti->t", q[1:], q[:-1]) + 1e-12)  # -1 where a frame's sign flipped
            q *= np.concatenate([[1.0], np.cumprod(turns)])[:, None]
            q = gaussian_low_pass(q, sigma_frames)
            out[name] = Rotation.from_quat(q / np.linalg.norm(q, axis=1, keepdims=True)).as_rotvec().astype(np.float32)
            continue
        out[name] = gaussian_low_pass(values, sigma_frames).astype(np.float32)
    return out


def sparse_vertices(model, body: BodyParams, vertex_ids: torch.Tensor, dtype=torch.float32) -> np.ndarray:
    """(T, U, 3) the vertices `vertex_ids` of every frame of `body`, 256 frames at a time, as numpy."""
    with torch.no_grad():
        return np.concatenate([model.sparse_forward(body.map(lambda x: x[lo:lo + 256]), vertex_ids).vertices
                               .to(dtype).cpu().numpy() for lo in range(0, body.batch_size, 256)])


def acceleration_scale(model, body: BodyParams, fps: float, vertex_ids: torch.Tensor, reference_mps2: float,
                       max_scale: float, smoothing_s: float, start_smoothing_s: float, reach_s: float) -> np.ndarray:
    """(T,) the body's acceleration weight per frame, as a factor of its setting: reference / a where the
    take moves slower than `reference_mps2`, clipped to [1, `max_scale`]. `a` is the body's own motion
    around the frame: the mean acceleration of the start's vertices `vertex_ids`, low-passed to
    `smoothing_s` in all (the start is low-passed by `start_smoothing_s` already), so what remains is the
    motion and not the per-frame fits' noise, then averaged over `reach_s` (Gaussian sigma) either side.
    A slow take's per-frame noise is large against its motion, and the weight that smooths a fast take
    leaves it jittering; the one that smooths a slow take flattens a fast one (BENCHMARKS.md)."""
    from scipy.ndimage import gaussian_filter1d

    T = body.batch_size
    if reference_mps2 <= 0 or T < 3:
        return np.ones(T)
    vertices = sparse_vertices(model, body, vertex_ids, torch.float64)
    extra_frames = np.sqrt(max(smoothing_s ** 2 - start_smoothing_s ** 2, 0.0)) * fps
    if extra_frames >= 0.5:
        vertices = gaussian_filter1d(vertices, extra_frames, axis=0, mode="nearest")
    acc = np.linalg.norm(vertices[2:] - 2 * vertices[1:-1] + vertices[:-2], axis=-1).mean(-1) * fps ** 2
    acc = np.pad(acc, 1, mode="edge")
    if reach_s * fps >= 0.5:
        acc = gaussian_filter1d(acc, reach_s * fps, mode="nearest")
    return np.clip(reference_mps2 / np.maximum(acc, 1e-6), 1.0, max_scale)


def acceleration_across_gaps(valid: np.ndarray, longest_frames: float) -> np.ndarray:
    """(T,) 1, or 0 at frames whose acceleration (the frame and the one either side) reaches into a run of
    frames without a body fit longer than `longest_frames`: the person was out of view, and the straight
    path the gap is filled with would pull the last and first frames in view off their data."""
    from intercap.stages.contact.stage import runs_of

    keep = np.ones(len(valid))
    for start, end in runs_of(~np.asarray(valid, bool)):
        if end - start > longest_frames:
            keep[max(start - 1, 0):end + 1] = 0.0
    return keep


def start_smoothing_frames(model, arrays: dict, least_frames: float, most_frames: float, confidence: float,
                           vertex_step: int = 32) -> np.ndarray:
    """(T,) each frame's width of the smoothed start, from `least_frames` up to `most_frames`
    (`adaptive_smoothing_frames` on every `vertex_step`-th vertex of the per-frame fits)."""
    levels = least_frames * (max(most_frames, least_frames) / least_frames) ** np.linspace(0.0, 1.0, 4)
    body = BodyParams.from_numpy_dict(arrays, dtype=model.dtype, device=model.faces.device)
    ids = torch.arange(0, model.num_vertices, vertex_step, device=model.faces.device)
    return adaptive_smoothing_frames(sparse_vertices(model, body, ids), levels, confidence)


def load_per_frame(session, out_dir: Path, model, with_object: bool = True, repair=None,
                   shape_limit_mm: float = np.inf, smoothing_frames: float = 0.0,
                   shape_smoothing_frames: float = 0.0, adaptive_smoothing=None) -> PerFrameResults:
    """Read OUT/body/, OUT/object/ and the contact stage's labels; clear errors when missing. Without
    the object (`with_object` False: none in the session, or none to refine) its pose is the identity
    and trusted in no frame, and no frame is in contact. `repair` (factor, floor_mm, reach) of
    `departed_frames`: those frames start the joint fit from their neighbours' poses (filled in as gaps
    are), their data then pulls them back; None: every fit as it is. The body's shape is the sequence mean,
    unless that moves a frame's body by more than `shape_limit_mm` (`shape_change_mm`): each keeps its own then,
    low-passed in time (Gaussian, `shape_smoothing_frames`): the body stage's processes each fit theirs on their first
    batches of frames, and a step between two batches would jolt the whole body in one frame. `adaptive_smoothing`
    (most_frames, confidence): each frame's start is low-passed by its own width, from `smoothing_frames` up to
    most_frames (`start_smoothing_frames`), and `motion` keeps the start at `smoothing_frames`."""
    body_file = per_frame_result(out_dir, "body", "body_params.npz")
    object_file = per_frame_result(out_dir, "object", "object_poses.npz")
    for path, stage in ((body_file, "body"), (object_file, "object"))[:2 if with_object else 1]:
        if not path.exists():
            raise GlobalError(f"{path} is missing: run the `{stage}` stage first "
                              f"(intercap run SESSION --out {out_dir} --stages {stage})")
    saved = np.load(body_file)
    if str(saved["model"]) != model.name:
        raise GlobalError(f"{body_file} holds a {saved['model']} fit but the session asks for {model.name}")
    body_valid = saved["valid"].astype(bool)
    if not body_valid.any():
        raise GlobalError(f"{body_file}: no frame has a body fit; nothing to refine")
    T = len(body_valid)
    repaired = np.zeros(T, bool)
    if repair is not None and "fit_to_data_mm" in saved:
        repaired = departed_frames(saved["fit_to_data_mm"], body_valid, *repair)
        if repaired.all():  # nothing to start them from
            repaired[:] = False
    kept = body_valid & ~repaired
    arrays = {k: (fill_axis_angle_gaps if k == "global_orient" else fill_gaps)(saved[k], kept).astype(np.float32)
              for k in PARAM_FIELDS}  # the root turns the short way across a gap
    widths, motion = None, None
    if smoothing_frames >= 0.5:  # below half a frame the filter would hardly touch the fits
        if adaptive_smoothing is not None:
            widths = start_smoothing_frames(model, arrays, smoothing_frames, *adaptive_smoothing)
            motion = smoothed_start(arrays, smoothing_frames)
            arrays = smoothed_start(arrays, widths)
        else:
            arrays = smoothed_start(arrays, smoothing_frames)
    own = arrays["shape"].copy()
    arrays["shape"][:] = saved["shape_mean"]
    body = BodyParams.from_numpy_dict(arrays, dtype=model.dtype, device=model.faces.device)
    moved = shape_change_mm(model, body, own, body_valid) if np.isfinite(shape_limit_mm) else 0.0
    if moved > shape_limit_mm:
        said = log.warning if multiprocessing.parent_process() is None else log.debug  # once, not per worker
        said("global: the per-frame fits' phenotypes disagree (their mean moves the body by %.0f mm in a "
             "frame: the body stage's processes each held their own); each frame keeps its own", moved)
        if shape_smoothing_frames >= 0.5:
            from scipy.ndimage import gaussian_filter1d

            own = gaussian_filter1d(own, shape_smoothing_frames, axis=0, mode="nearest")
        body.shape.copy_(torch.as_tensor(own, dtype=body.shape.dtype))
    if motion is not None:
        motion = BodyParams.from_numpy_dict({**motion, "shape": body.shape.cpu().numpy()}, dtype=model.dtype,
                                            device=model.faces.device)
    start = dict(start_widths=widths, motion=motion)
    if not with_object:
        return PerFrameResults(body, body_valid, np.tile(np.eye(3), (T, 1, 1)), np.zeros((T, 3)), np.zeros(T, bool),
                               np.zeros(T), np.zeros(T, bool), np.full((T, 2), np.inf), np.zeros((T, 2), bool),
                               repaired, **start)

    poses = np.load(object_file)
    object_valid = poses["valid"].astype(bool)
    inside = out_dir / "global" / "object_inside_body.npy"  # `object_inside_body`'s, written by `run`
    if inside.exists():
        object_valid &= ~np.load(inside)
    if not object_valid.any():
        raise GlobalError(f"{object_file}: the object was tracked in no frame; nothing to refine")
    R, t = unwrap_symmetry(poses["R"], poses["t"], object_valid, *mesh_symmetry(session.object.load_mesh()))
    rotvec = fill_gaps(_rotvecs(R, object_valid), object_valid)
    R = axis_angle_to_matrix(torch.from_numpy(rotvec)).numpy()
    t = fill_gaps(t, object_valid)
    confidence = np.where(object_valid, np.nan_to_num(poses["confidence"]), 0.0)

    contact, hand_distance = load_contact_labels(out_dir, session.num_frames)
    return PerFrameResults(body, body_valid, R, t, object_valid, confidence, contact, hand_distance, None, repaired,
                           **start)



def hand_object_distance(model, per_frame: PerFrameResults, shape: "ObjectShape") -> np.ndarray:
    """(T, 2) metres from each hand's contact region to the object's surface in the per-frame results."""
    ids = [torch.as_tensor(model.contact_regions[h]) for h in HANDS]
    distance = np.zeros((len(per_frame.contact), 2))
    R = torch.as_tensor(per_frame.R, dtype=torch.float32, device=model.faces.device)
    t = torch.as_tensor(per_frame.t, dtype=torch.float32, device=model.faces.device)
    with torch.no_grad():
        for s in range(0, len(distance), 32):
            sl = slice(s, s + 32)
            vertices = model.sparse_forward(per_frame.body[sl], torch.cat(ids)).vertices
            sd = shape.signed_distance((vertices - t[sl, None]) @ R[sl])
            distance[sl, 0] = sd[:, :len(ids[0])].min(1).values.cpu().numpy()
            distance[sl, 1] = sd[:, len(ids[0]):].min(1).values.cpu().numpy()
    return distance



def _rotvecs(R: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T, 3) axis-angle of the valid rotations, made continuous in time (no 2 pi jumps), NaN elsewhere."""
    out = np.full((len(R), 3), np.nan)
    out[valid] = matrix_to_axis_angle(torch.from_numpy(R[valid]).double()).numpy()
    return continuous_axis_angle(out, valid)


def load_contact_labels(out_dir: Path, T: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Contact per frame (T,) and each hand's per-frame distance to the object (T, 2) metres, from the
    `contact` stage; the distances are None where only OUT/contact.npy exists (measured here then)."""
    from intercap.stages.contact.stage import load_contact

    if (Path(out_dir) / "contact" / "contact.npz").exists():
        data = load_contact(out_dir)
        names = data["region_names"]
        if all(h in names for h in HANDS) and "region_distance_m" in data:
            distance = np.stack([data["region_distance_m"][:, names.index(h)] for h in HANDS], 1)
            return data["contact"].astype(bool), np.nan_to_num(distance, nan=np.inf)
        return data["contact"].astype(bool), None
    labels = Path(out_dir) / "contact.npy"
    if labels.exists():
        return np.load(labels).astype(bool), None
    log.warning("global: no contact labels (run the `contact` stage); contact terms are off")
    return np.zeros(T, bool), np.full((T, 2), np.inf)



def grasping_hands(contact: np.ndarray, hand_distance: np.ndarray, reach_m: float) -> np.ndarray:
    """(T, 2) bool: the hands that hold the object, in contact frames (T,) where a hand lies within
    `reach_m` of it (`hand_distance` (T, 2), inf where unmeasured). A contact frame with neither hand
    measured (the object untrusted there: `contact`'s untracked gaps) takes the hands of the nearest
    measured contact frame of its run."""
    from intercap.stages.contact.stage import runs_of

    contact = np.asarray(contact, bool)
    grasping = contact[:, None] & (hand_distance < reach_m)
    unmeasured = contact & ~np.isfinite(hand_distance).any(1)
    for first, end in runs_of(contact):
        measured = np.flatnonzero(~unmeasured[first:end]) + first
        for k in np.flatnonzero(unmeasured[first:end]) + first:
            if measured.size:
                grasping[k] = grasping[measured[np.argmin(np.abs(measured - k))]]
    return grasping


def signed_distance_grid(vertices: np.ndarray, faces: np.ndarray, watertight: bool, resolution: int,
                         cell_m: float | None, margin_m: float | None, cells_max: int) -> dict:
    """`ObjectShape`'s grid: `sdf` (Z, Y, X) metres at the corners of cells from `lo` to `hi`."""
    import open3d as o3d

    lo, hi = vertices.min(0), vertices.max(0)
    margin = 0.2 * float((hi - lo).max()) + 0.05
    margin = min(margin, margin_m) if margin_m else margin
    lo, hi = lo - margin, hi + margin
    cell = float((hi - lo).max()) / resolution
    if cell_m:
        cell = max(min(cell, cell_m), (float(np.prod(hi - lo)) / cells_max) ** (1 / 3))
    counts = np.ceil((hi - lo) / cell).astype(int) + 1
    axes = [lo[k] + cell * np.arange(counts[k]) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).astype(np.float32)  # (X, Y, Z, 3)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces))
    if watertight:
        sdf = scene.compute_signed_distance(grid.reshape(-1, 3)).numpy()
    else:  # no inside to speak of: distances only, so nothing is pushed out of an open shell
        sdf = scene.compute_distance(grid.reshape(-1, 3)).numpy()
    # grid_sample wants (N, C, D, H, W) with x indexing W: store as (Z, Y, X).
    return {"sdf": np.ascontiguousarray(sdf.reshape(grid.shape[:3]).transpose(2, 1, 0)),
            "lo": lo, "hi": (lo + cell * (counts - 1)).astype(np.float32)}



class ObjectShape:
    """The rigid object in its own coordinates: a signed-distance grid (trilinear, differentiable in
    the query points), surface samples for E_A / E_G, and its graspable points for E_C'."""

    def __init__(self, mesh: trimesh.Trimesh, resolution: int, grasp_ids: np.ndarray | None, samples: int = 256,
                 seed: int = 0, cell_m: float | None = None, margin_m: float | None = None,
                 cells_max: int = 4_000_000, cache: Path | None = None):
        """`resolution` cells at least along the grid's longest side, none wider than `cell_m` (thin
        parts, a chair's back panel, read as hardly inside in cells as wide as they are), unless that
        takes more than `cells_max` cells; the grid reaches 0.2 of the object's size plus 5 cm, at
        most `margin_m`, beyond its box (further out: the border value plus the distance to the grid,
        an overestimate). With `cache` (an .npz) the grid is read from there when it was built for
        the same mesh and settings, else built and written there: every worker of the stage needs it,
        and a large object's grid takes a while to build."""
        vertices = np.asarray(mesh.vertices, dtype=np.float32)
        faces = np.asarray(mesh.faces, dtype=np.uint32)
        if not mesh.is_watertight:
            log.warning("global: the object mesh is not watertight; interpenetration is not measured")
        settings = np.array([resolution, cell_m or 0, margin_m or 0, cells_max], np.float64)
        key = hashlib.sha1(vertices.tobytes() + faces.tobytes() + settings.tobytes()).hexdigest()
        grid = None
        if cache is not None and Path(cache).exists():
            with np.load(cache) as saved:
                if str(saved["key"]) == key:
                    grid = {name: saved[name] for name in ("sdf", "lo", "hi")}
        if grid is None:
            grid = signed_distance_grid(vertices, faces, mesh.is_watertight, resolution, cell_m, margin_m, cells_max)
            if cache is not None:
                save_npz(cache, key=np.array(key), **grid)
        self.sdf = torch.from_numpy(grid["sdf"])[None, None]
        self.lo, self.hi = torch.from_numpy(grid["lo"]), torch.from_numpy(grid["hi"])
        points, _ = trimesh.sample.sample_surface_even(mesh, samples, seed=seed)
        self.samples = torch.as_tensor(np.asarray(points), dtype=torch.float32)  # (M, 3)
        ids = np.arange(len(vertices)) if grasp_ids is None or len(grasp_ids) == 0 else np.asarray(grasp_ids)
        self.grasp_points = torch.from_numpy(vertices[ids])  # (G, 3)
        self.centroid = torch.from_numpy(vertices.mean(0))

    def on(self, device) -> "ObjectShape":
        """A copy with its tensors on `device` (the fitter's: it then copies nothing per evaluation)."""
        moved = copy.copy(self)
        for name in ("sdf", "lo", "hi", "samples", "grasp_points", "centroid"):
            setattr(moved, name, getattr(self, name).to(device))
        return moved

    def signed_distance(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points in object coordinates -> (...) metres, positive outside. Beyond the grid:
        the border value plus the distance to the grid box (an overestimate that keeps its sign)."""
        lo, hi = self.lo.to(points), self.hi.to(points)
        inside = torch.minimum(torch.maximum(points, lo), hi)
        outside = (points - inside).norm(dim=-1)
        normalised = (inside - lo) / (hi - lo) * 2 - 1
        flat = normalised.reshape(1, -1, 1, 1, 3)
        value = torch.nn.functional.grid_sample(self.sdf.to(points), flat, mode="bilinear", align_corners=True)
        return value.reshape(points.shape[:-1]) + outside


@dataclass
class WindowData:
    """The observations of one window's W frames."""

    obs: BodyObservations
    object_points: torch.Tensor | None  # (W, P, 3) world
    object_point_valid: torch.Tensor | None  # (W, P)
    object_reference: torch.Tensor | None  # (W, M, 3) the object's samples where the tracker put them; None: no object
    object_confidence: torch.Tensor  # (W,)
    grasping: torch.Tensor  # (W, 2) float
    flight: torch.Tensor | None = None  # (W,) long: free-flight episode id per frame, -1 outside (GraviCap);
    # None when no frame of the window is in flight
    grasp_rows: tuple | None = None  # per hand, (G,) long: the frames where it grasps, found on the host
    # when the window is read (E_C' measures only them); None: every frame, weighted by `grasping`
    acceleration_scale: torch.Tensor | None = None  # (W,) the body's acceleration weight per frame, x the setting


class Observations:
    """Loads what a window needs: keypoints and person points as the body stage does, object points
    from the object masks (given or derived around the tracked pose) with depth; with `with_object`
    False (a body-only joint fit) no object points."""

    def __init__(self, session, cfg, out_dir: Path, cameras: Cameras, with_object: bool = True):
        from intercap.stages.object.fitter import ObjectTracker

        self.session, self.cfg = session, cfg
        self.device = cameras.K.device  # where the window's tensors go (the fit's device)
        self.keypoints = KeypointSource(session, out_dir, cfg.detect.use_session_keypoints, cameras,
                                        cfg.body.keypoint_view_check_px)
        self.person = PersonPoints(session, cameras, cfg.body, out_dir)
        self.tracker = ObjectTracker(session, cfg.object, session.object.load_mesh()) if with_object else None

    def object_points(self, frame_id: int, R: np.ndarray, t: np.ndarray, trusted: bool, seed: int,
                      depths: list | None = None) -> np.ndarray:
        """(P, 3) world points of the object's pixels, a seeded subset; none where the tracker lost it.
        `depths`: the frame's depth maps when already read."""
        P = self.cfg.global_.object_points_per_view * self.session.num_cameras
        if not trusted:
            return np.zeros((0, 3))
        points = self.tracker.object_points(self.tracker.observe(frame_id, (R, t), depths=depths))
        if len(points) > P:
            points = points[np.random.default_rng([seed, frame_id]).choice(len(points), P, replace=False)]
        return points

    def window(self, frames: np.ndarray, per_frame: PerFrameResults, shape: ObjectShape | None) -> WindowData:
        """The observations of take frames `frames` (W,), on the fit's device; `shape` None: the body's only."""
        ids = self.session.frame_ids[frames]
        kps = self.keypoints.batch(ids, self.cfg.body.min_keypoint_confidence)
        C, B = self.session.num_cameras, len(frames)
        points = np.zeros((B, C, self.cfg.body.points_per_view, 3), np.float32)
        point_valid = np.zeros(points.shape[:3], bool)
        P = self.cfg.global_.object_points_per_view * C
        cloud = np.zeros((B, P, 3), np.float32)
        cloud_valid = np.zeros((B, P), bool)

        def read_frame(b: int) -> None:  # in IO threads; each view's depth decoded once for person and object
            i, frame_id = frames[b], int(ids[b])
            depths = [self.session.read_depth(c, frame_id) for c in range(C)]
            points[b], point_valid[b] = self.person.frame(frame_id, kps[b], depths)
            if shape is None:
                return
            pts = self.object_points(frame_id, per_frame.R[i], per_frame.t[i], bool(per_frame.object_valid[i]),
                                     self.cfg.global_.seed, depths)
            cloud[b, :len(pts)], cloud_valid[b, :len(pts)] = pts, True

        in_threads(read_frame, range(B))
        device = self.device
        obs = BodyObservations(ids, torch.from_numpy(kps).to(device), torch.from_numpy(points).to(device),
                               torch.from_numpy(point_valid).to(device))
        scale = getattr(per_frame, "acceleration_scale", None)  # per_frame None: the body's observations alone
        scale = None if scale is None else torch.as_tensor(scale[frames], dtype=torch.float32, device=device)
        if shape is None:
            none = torch.zeros(B, 2, device=device)
            return WindowData(obs, None, None, None, torch.zeros(B, device=device), none, grasp_rows=None,
                              acceleration_scale=scale)
        R = torch.as_tensor(per_frame.R[frames], dtype=torch.float32)
        t = torch.as_tensor(per_frame.t[frames], dtype=torch.float32)
        reference = (shape.samples @ R.transpose(1, 2)) + t[:, None]
        return WindowData(obs, torch.from_numpy(cloud).to(device), torch.from_numpy(cloud_valid).to(device),
                          reference.to(device),
                          torch.as_tensor(per_frame.object_confidence[frames], dtype=torch.float32, device=device),
                          torch.as_tensor(per_frame.grasping[frames], dtype=torch.float32, device=device),
                          grasp_rows=tuple(torch.as_tensor(np.flatnonzero(per_frame.grasping[frames, h]), device=device)
                                           for h in range(2)), acceleration_scale=scale)


def object_inside_body(session, out_dir: Path, share: float, margin_m: float = 0.02) -> np.ndarray:
    """(T,) bool: frames whose tracked object pose has more than `share` of its surface samples at
    least `margin_m` inside the per-frame body (signed by the nearest body vertex's normal). Without
    masks the tracker can fit the object to the person's own points; the joint fit would then push
    the body out of it. A held object stays outside the body but for the fingers
    (`global.object_inside_body_share`)."""
    from scipy.spatial import cKDTree

    files = [per_frame_result(out_dir, stage, name) for stage, name in (
        ("object", "object_poses.npz"), ("body", "body_vertices.npy"), ("body", "body_faces.npy"),
        ("body", "body_params.npz"))]
    if not all(f.exists() for f in files):  # `load_per_frame` names a missing stage; no meshes: not checked
        return np.zeros(session.num_frames, bool)
    poses = np.load(files[0])
    vertices = np.load(files[1], mmap_mode="r")
    faces = np.load(files[2])
    valid = poses["valid"].astype(bool) & np.load(files[3])["valid"].astype(bool)
    samples, _ = trimesh.sample.sample_surface_even(session.object.load_mesh(), 256, seed=0)
    inside = np.zeros(len(valid), bool)

    def check(i: int) -> None:
        body = np.asarray(vertices[i], np.float64)
        normals = trimesh.Trimesh(body, faces, process=False).vertex_normals
        world = samples @ poses["R"][i].T + poses["t"][i]
        _, nearest = cKDTree(body).query(world)
        depth = ((body[nearest] - world) * normals[nearest]).sum(1)
        inside[i] = (depth > margin_m).mean() > share

    in_threads(check, np.flatnonzero(valid))
    return inside


def free_flight(per_frame: PerFrameResults, shape: ObjectShape, ground, fps: float, g) -> dict:
    """The tracked object's free-flight episodes (GraviCap): frames where the contact stage sees no
    body contact and the object's surface is clear of the ground plane, for `flight_min_frames`.
    Gravity is -9.81 along the ground normal; with no ground plane (prepare found no floor) the up
    direction comes from the flights themselves (`gravity_from_flight`), written to
    OUT/global/gravity.json by the caller's metrics ("gravity_source": "flight")."""
    from intercap.dynamics.flight import falling_episodes, find_flight_episodes, gravity_from_flight, object_on_ground

    T = len(per_frame.contact)
    centres = per_frame.t + np.einsum("tij,j->ti", per_frame.R, shape.centroid.numpy())
    centres = np.where(per_frame.object_valid[:, None], centres, np.nan)
    touching = per_frame.contact.copy()
    if ground is not None:
        points = np.einsum("tij,mj->tmi", per_frame.R, shape.samples.numpy()) + per_frame.t[:, None]
        touching |= object_on_ground(points, ground.point, ground.normal, g.flight_ground_margin_m)
        up, source = np.asarray(ground.normal, np.float64), "ground"
    else:
        up, source = np.array([0.0, 0.0, 1.0]), "none"  # only to run the detection; replaced below
    episodes = find_flight_episodes(centres, touching, up, fps, g.flight_min_frames)
    held = []  # runs touching nothing that do not fall (`run` says so, once)
    if ground is not None:  # with no floor, `gravity_from_flight` checks the episodes against gravity itself
        episodes, held = falling_episodes(centres, episodes, fps, up, g.flight_max_residual_m)
    figures = {"flight_episodes": episodes.tolist(), "flight_runs_held": [[a, b] for a, b, _ in held]}
    if ground is None and len(episodes):
        try:
            fit = gravity_from_flight(centres, episodes, fps)
            up, source = fit["up"], "flight"
            figures.update(gravity_from_flight_g_norm=fit["g_norm"],
                           gravity_from_flight_residual_mm=1e3 * fit["residual_m"])
        except ValueError as error:
            log.warning("global: %s; the free-flight term is off", error)
            episodes = episodes[:0]
    if ground is None and source != "flight":
        episodes = episodes[:0]
    figures["gravity_source"] = source
    figures["gravity_up"] = [float(v) for v in up]
    episode_of_frame = np.full(T, -1, np.int64)
    for e, (a, b) in enumerate(episodes):
        episode_of_frame[a:b + 1] = e
    figures["flight_frames"] = int((episode_of_frame >= 0).sum())
    return {"episodes": episodes, "up": up, "episode_of_frame": episode_of_frame, "figures": figures, "held": held}


def no_flight(T: int) -> dict:
    """`free_flight`'s result for a take without an object: no episodes."""
    return {"episodes": np.zeros((0, 2), np.int64), "up": np.array([0.0, 0.0, 1.0]),
            "episode_of_frame": np.full(T, -1, np.int64), "figures": {}, "held": []}
