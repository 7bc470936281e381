"""Stage 5, `contact`: which frames have body-object contact, and which body regions touch.

Three sources, each a small function:

* annotated: the session's `contact_frames` ranges (`annotated_labels`). When the
  session has them they are the answer (method "annotated"), unless the config
  names a detector explicitly (`contact.method=2d` / `3d`).
* 2D baseline (InterCap's): in each view the person and the object masks, each
  grown by a few pixels, overlap in more than T_view pixels; a frame is in contact
  when more than T_frame views say so (`overlap_labels`). Masks are the session's,
  or, when it has none, the visible pixels of the per-frame body fit and posed
  object rendered with a z-buffer (`rendered_labels`).
* 3D baseline: the distance from each body contact region's vertices (per-frame
  body fit) to the posed object's surface, exact point-to-triangle
  (`region_distances`, all frames in one open3d call); contact when a region of
  `contact.regions` (both hands by default) is nearer than T_d.

Detected labels miss a contact where the fit's hand is off the object (one or two views
cannot place a hand along their rays, a thin handle in a hand fitted from raw input); an
object that moves across a gap too short to be a flight is carried (`carried_gaps`), and one
that touches nothing and the floor for longer and does not fall is held (`held_frames`), by
the regions that held it next to the run.

Frames whose needed per-frame result is missing (NaN body or object pose) are listed; they
count as no contact unless contact runs of `contact.untracked_min_run` frames stand on both sides of
a run of them too short to be a flight (`untracked_gaps`: the object was held through it, by the
regions next to it). Detected labels can be cleaned in time (`clean_labels`:
gaps and runs shorter than `contact.clean_frames` are filled / dropped).

Writes OUT/contact.npy (bool (T,), docs/outputs.md) and OUT/contact/contact.npz:
contact (T,), method, frame_ids (T,), region_names (R,), region_distance_m (T, R)
(NaN where unknown), region_contact (T, R) (which regions touch in each contact
frame: for 3D those nearer than T_d; for annotated and 2D labels the nearest
region of `contact.regions` and every region within `region_margin_m`),
invalid (T,) (frames the method could not judge), held (T,), carried (T,) and untracked (T,)
(contact frames `held_frames`, `carried_gaps` and `untracked_gaps` added), and each source's labels
(annotated, overlap_2d, distance_3d) with the 2D overlap counts (T, C).
For the report: region_vertex_ids (concatenated, int32) with region_sizes (R,), and the
body model's rest_vertices (V, 3) (the contact heat map is drawn on them).
`load_contact(out_dir)` reads it back for the `global` stage.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import torch
from tqdm import tqdm

from intercap.body_models import setting_key, shared_model
from intercap.io.files import per_frame_result, publish, save_npy, save_npz
from intercap.session.session import in_threads

log = logging.getLogger(__name__)

METHODS = ("auto", "annotated", "2d", "3d")


class ContactError(ValueError):
    """Contact cannot be decided: a needed per-frame result or annotation is missing, or a bad setting."""


# -- the sources ------------------------------------------------------------------------------
def annotated_labels(contact_frames, frame_ids: np.ndarray) -> np.ndarray:
    """(T,) bool: frames inside any inclusive [start, end] range of `contact_frames`."""
    frame_ids = np.asarray(frame_ids)
    labels = np.zeros(len(frame_ids), bool)
    for start, end in contact_frames or []:
        labels |= (frame_ids >= start) & (frame_ids <= end)
    return labels


def region_distances(vertices: np.ndarray, region_ids: list[np.ndarray], R: np.ndarray, t: np.ndarray,
                     mesh_vertices: np.ndarray, mesh_faces: np.ndarray) -> np.ndarray:
    """(T, R) metres: per frame and region, the smallest distance from the region's vertices
    (vertices (T, V, 3), world) to the surface of the object posed by R (T, 3, 3), t (T, 3)
    (object -> world). NaN where the region's vertices or the pose are not finite.

    The vertices go into object coordinates (R^T (x - t)), so one ray-casting scene of
    the mesh serves every frame; all frames and regions are one distance query."""
    T = len(vertices)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh_vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh_faces, np.uint32)))
    ids = np.concatenate(region_ids)  # (N,)
    owner = np.repeat(np.arange(len(region_ids)), [len(r) for r in region_ids])  # (N,) region of each vertex
    points = np.asarray(vertices[:, ids], np.float64)  # (T, N, 3)
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    ok = np.isfinite(points).all(2) & np.isfinite(R).all((1, 2))[:, None] & np.isfinite(t).all(1)[:, None]  # (T, N)
    local = np.einsum("tnj,tjk->tnk", np.nan_to_num(points) - np.nan_to_num(t)[:, None], np.nan_to_num(R))  # (T, N, 3)
    dist = scene.compute_distance(o3d.core.Tensor(local.reshape(-1, 3).astype(np.float32))).numpy()
    dist = np.where(ok, dist.reshape(T, -1), np.inf)  # (T, N)
    out = np.full((T, len(region_ids)), np.inf)
    for r in range(len(region_ids)):  # regions, not frames
        out[:, r] = dist[:, owner == r].min(1) if (owner == r).any() else np.inf
    out[~np.isfinite(out)] = np.nan
    return out


def distance_labels(distance: np.ndarray, columns: list[int], threshold_m: float) -> np.ndarray:
    """(T,) bool: some region of `columns` is nearer than `threshold_m` (NaN: not)."""
    d = distance[:, columns]
    return (np.nan_to_num(d, nan=np.inf) < threshold_m).any(1)


def mask_overlap(person: np.ndarray, obj: np.ndarray, dilate_px: int) -> int:
    """Pixels where the person and the object mask, each grown by `dilate_px`, overlap."""
    if dilate_px > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1, 2 * dilate_px + 1))
        person = cv2.dilate(person.astype(np.uint8), kernel)
        obj = cv2.dilate(obj.astype(np.uint8), kernel)
    return int(np.count_nonzero(person.astype(bool) & obj.astype(bool)))


def overlap_labels(counts: np.ndarray, min_px: np.ndarray, views: int) -> np.ndarray:
    """(T,) bool from overlap counts (T, C) (negative: view unknown): more than `min_px` (C,)
    pixels in more than `views` views."""
    return ((counts > np.asarray(min_px)[None]).sum(1) > views)


def runs_of(mask: np.ndarray) -> np.ndarray:
    """(K, 2) [start, end) of the runs of True in a (T,) bool array."""
    step = np.diff(np.r_[0, np.asarray(mask, np.int8), 0])
    return np.stack([np.flatnonzero(step == 1), np.flatnonzero(step == -1)], 1)


def clean_labels(labels: np.ndarray, frames: int) -> np.ndarray:
    """Fill gaps shorter than `frames` between two contact runs, then drop runs shorter than `frames`."""
    out = np.asarray(labels, bool).copy()
    if frames <= 1:
        return out
    for s, e in runs_of(~out):
        if s > 0 and e < len(out) and e - s < frames:
            out[s:e] = True
    for s, e in runs_of(out):
        if e - s < frames:
            out[s:e] = False
    return out


def carried_gaps(contact: np.ndarray, centres: np.ndarray, max_frames: int, rest_m: float) -> np.ndarray:
    """(T,) bool: the frames of each gap in `contact` (T,) shorter than `max_frames` between two contact
    frames over which the object moved: its centre (T, 3; NaN where untracked) `rest_m` or more from
    where it was in the contact frame before, in a frame of the gap or the contact frame after. Too
    short to be a flight (`held_frames` needs `max_frames`), such a gap is a carry where the fit's hand
    lies a little off the object (a 3.5 cm tool handle in a hand fitted from raw input); a hand nearing
    an object at rest, touching it in some frames and not in others, is left as it is."""
    out = np.zeros(len(contact), bool)
    for first, end in runs_of(~np.asarray(contact, bool)):
        if first == 0 or end >= len(contact) or end - first >= max_frames or not np.isfinite(centres[first - 1]).all():
            continue
        moved = np.linalg.norm(centres[first:end + 1] - centres[first - 1], axis=1)
        if (np.nan_to_num(moved, nan=0.0) >= rest_m).any():
            out[first:end] = True
    return out


def untracked_gaps(contact: np.ndarray, judged: np.ndarray, max_frames: int, min_run: int) -> np.ndarray:
    """(T,) bool: the frames of each gap in `contact` (T,) shorter than `max_frames` in which nothing was
    judged (`judged` (T,) False: the object or body untrusted there), between two contact runs of
    `min_run` frames or more. Both sides say contact and the gap is too short to be a flight, so the
    object was held through it. A gap with a judged frame in it is that frame's to say, and a contact
    frame or two among untrusted ones (an object put down, its few trusted poses wrong) fills nothing."""
    contact, judged = np.asarray(contact, bool), np.asarray(judged, bool)
    runs = runs_of(contact)
    out = np.zeros(len(contact), bool)
    for (start, first), (end, last) in zip(runs[:-1], runs[1:]):  # the gap [first, end) between two runs
        if end - first < max_frames and min(first - start, last - end) >= min_run and not judged[first:end].any():
            out[first:end] = True
    return out


def neighbours_regions(touching: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(T, R) `touching` with each run of `frames` (T,) given the regions touching in the frames just
    before and after it."""
    out = touching.copy()
    for first, end in runs_of(frames):
        out[first:end] = touching[max(first - 1, 0)] | touching[min(end, len(touching) - 1)]
    return out


def touching_regions(contact: np.ndarray, distance: np.ndarray, columns: list[int], margin_m: float) -> np.ndarray:
    """(T, R) bool: in contact frames, the nearest region of `columns` and every region within `margin_m`."""
    d = np.nan_to_num(distance, nan=np.inf)
    touching = d < margin_m
    known = np.isfinite(d[:, columns]).any(1)
    nearest = np.asarray(columns)[np.argmin(d[:, columns], 1)]
    touching[np.flatnonzero(known), nearest[known]] = True
    return touching & np.asarray(contact, bool)[:, None]


def held_frames(contact: np.ndarray, regions: np.ndarray, centres: np.ndarray, on_ground: np.ndarray, up,
                fps: float, min_frames: int, max_residual_m: float, rest_m: float
                ) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """Frames where the object must be held though no region was seen touching it: it touches neither
    the body (`contact` (T,)) nor the floor (`on_ground` (T,)) for `min_frames` or more, moves, and does
    not fall (`dynamics.flight.falling_episodes`: a parabola under gravity misses its centres (T, 3) by
    more than `max_residual_m` RMS). Fewer than `min_frames` untracked frames in a row (NaN centres) do
    not end a run, nor stand between it and a contact. Whoever held it before the run (the `regions`
    (T, R) touching in the contact frame just before) holds it until it comes to rest where it stays
    (its centre within `rest_m` of where it lies over the run's last `min_frames` frames); whoever
    takes it after the run held it since it left where it lay. One view cannot place a hand along
    its rays: a cup at the mouth, its hand 13 cm behind it, touched nothing by distance for 2 s.
    Returns held (T,) bool, the regions holding (T, R) bool, and the runs (first, last)."""
    from intercap.dynamics.flight import falling_episodes, find_flight_episodes

    T = len(contact)
    held, holding, runs = np.zeros(T, bool), np.zeros(regions.shape, bool), []
    episodes = find_flight_episodes(centres, contact | on_ground, up, fps, min_frames, max_gap_frames=min_frames - 1)
    _, unfallen = falling_episodes(centres, episodes, fps, up, max_residual_m)
    tracked = np.isfinite(centres).all(1)

    def first_moved(frames: range) -> int:
        """The first of `frames` whose centre lies `rest_m` or more from where the first `min_frames`
        tracked ones lie (their median: one view's cup on a table jitters 5-16 mm frame to frame)
        (else the first)."""
        anchor = np.median(centres[[k for k in frames if tracked[k]][:min_frames]], axis=0)
        return next((k for k in frames if tracked[k] and np.linalg.norm(centres[k] - anchor) >= rest_m), frames[0])

    def past_untracked(k: int, step: int) -> int:
        """k, or the first tracked frame from k on in `step` within `min_frames` (frames the tracker did
        not trust say nothing of a fall: one view, a cup at the mouth, 4 untrusted frames cut a run)."""
        j = k
        while 0 <= j < T and not tracked[j] and abs(j - k) + 1 < min_frames:
            j += step
        return j

    nobody = np.zeros(regions.shape[1], bool)
    for a, b, _ in unfallen:
        i, j = past_untracked(a - 1, -1), past_untracked(b + 1, 1)
        before = regions[i] if i >= 0 and contact[i] else nobody
        after = regions[j] if j < T and contact[j] else nobody
        if not (before.any() or after.any()):
            continue  # nobody to give it to: `global` and `physics` say so
        first = i + 1 if before.any() else first_moved(range(a, b + 1))
        last = j - 1 if after.any() else first_moved(range(b, a - 1, -1))
        held[first:last + 1] = True
        holding[first:last + 1] = before | after
        runs.append((int(first), int(last)))
    return held, holding, runs


# -- inputs -----------------------------------------------------------------------------------
@dataclasses.dataclass
class PerFrame:
    """The per-frame stages' results the detectors read."""

    vertices: np.ndarray  # (T, V, 3) world, NaN where the body fit is invalid (memory-mapped)
    faces: np.ndarray  # (F, 3)
    R: np.ndarray  # (T, 3, 3) object -> world, NaN where untrusted
    t: np.ndarray  # (T, 3)
    body_valid: np.ndarray  # (T,) bool
    object_valid: np.ndarray  # (T,) bool


def load_per_frame(out_dir: Path, session) -> PerFrame:
    """The `body` and `object` stages' own results; ContactError naming the stage to run when absent."""
    T = session.num_frames
    paths = {"body": [per_frame_result(out_dir, "body", n) for n in ("body_vertices.npy", "body_faces.npy")],
             "object": [per_frame_result(out_dir, "object", "object_poses.npz")]}
    for stage, files in paths.items():
        missing = [str(p) for p in files if not p.exists()]
        if missing:
            raise ContactError(f"contact: needs the per-frame `{stage}` results ({', '.join(missing)} missing); "
                               f"run the `{stage}` stage first (intercap run SESSION --out OUT --stages {stage})")
    vertices = np.load(paths["body"][0], mmap_mode="r")
    faces = np.load(paths["body"][1])
    with np.load(paths["object"][0]) as z:
        R, t = z["R"].astype(np.float64), z["t"].astype(np.float64)
        obj_valid = z["valid"].astype(bool) if "valid" in z else np.ones(len(R), bool)
    if len(vertices) != T or len(R) != T:
        raise ContactError(f"contact: per-frame results hold {len(vertices)} body / {len(R)} object frames, the "
                           f"session {T}; rerun the `body` and `object` stages for this session")
    body_valid = np.isfinite(np.asarray(vertices[:, 0])).all(1)  # (T,) invalid fits are NaN rows
    obj_valid = obj_valid & np.isfinite(R).all((1, 2)) & np.isfinite(t).all(1)
    return PerFrame(vertices, faces, R, t, body_valid, obj_valid)


def session_mask_labels(session, frame_id: int, sizes) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """Per view (person, object) masks of the session, None where one is missing; the views in IO threads."""
    def read_view(c: int):
        person, obj = session.read_mask(c, frame_id, "person"), session.read_mask(c, frame_id, "object")
        return None if person is None or obj is None else (person, obj)

    return in_threads(read_view, range(len(sizes)))


def rendered_labels(body_vertices: np.ndarray, body_faces, object_vertices: np.ndarray, object_faces, cameras,
                    sizes, device: str = "cpu") -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Visible person / object pixels of B frames' fits, [b][c] (person (H, W), object (H, W)) bool.

    Body (B, V, 3) and posed object (B, K, 3) are rendered with a z-buffer each; a
    pixel belongs to whichever surface is nearer, as in a segmentation."""
    from intercap.geometry.rendering import MeshTopology, full_image_crops, render

    H, W = max(s[0] for s in sizes), max(s[1] for s in sizes)
    B = len(body_vertices)
    crops = full_image_crops(cameras, B)
    with torch.no_grad():
        depth = []
        for verts, faces in ((body_vertices, body_faces), (object_vertices, object_faces)):
            topo = faces if isinstance(faces, MeshTopology) else MeshTopology.from_faces(torch.as_tensor(faces))
            v = torch.as_tensor(np.asarray(verts), dtype=cameras.K.dtype, device=cameras.K.device)
            depth.append(render(v, topo, cameras, crops, (H, W), sigma=0.6).depth.cpu().numpy())  # (B, C, H, W)
    body, obj = depth
    person = (body > 0) & ((obj <= 0) | (body <= obj))
    thing = (obj > 0) & ((body <= 0) | (obj < body))
    return [[(person[b, c, :h, :w], thing[b, c, :h, :w]) for c, (h, w) in enumerate(sizes)] for b in range(B)]


# -- the stage --------------------------------------------------------------------------------
def resolve_method(ccfg, session) -> str:
    """The method used: "auto" means the annotations when the session has them, else the detector."""
    if ccfg.method not in METHODS:
        raise ContactError(f"contact.method must be one of {', '.join(METHODS)}, got {ccfg.method!r}")
    if ccfg.detector not in ("2d", "3d"):
        raise ContactError(f"contact.detector must be '2d' or '3d', got {ccfg.detector!r}")
    if ccfg.method == "annotated" and session.contact_frames is None:
        raise ContactError("contact.method=annotated but the session has no contact_frames in session.yaml")
    if ccfg.method == "auto":
        return "annotated" if session.contact_frames is not None else ccfg.detector
    return ccfg.method


def overlap_counts(session, ccfg, per_frame: PerFrame | None, mesh, device: str = "cpu", progress: bool = True,
                   batch: int = 8) -> tuple[np.ndarray, str, np.ndarray]:
    """(T, C) overlap pixel counts (-1: view unknown), the mask source ("session" / "rendered")
    and (T,) which frames could be judged."""
    from intercap.geometry.cameras import Cameras

    T, C = session.num_frames, session.num_cameras
    sizes = [(c.height, c.width) for c in session.cameras]
    use_session = ccfg.use_session_masks and all(session.has_kind("mask_person")) and all(session.has_kind("mask_object"))
    counts = np.full((T, C), -1, np.int64)
    dilate = [max(1, int(round(ccfg.dilate_px * w / 640))) if ccfg.dilate_px > 0 else 0 for _, w in sizes]
    judged = np.zeros(T, bool)
    bar = tqdm(total=T, desc="contact 2d", unit="frame", disable=not progress)
    if use_session:
        for i, f in enumerate(session.frame_ids):
            for c, pair in enumerate(session_mask_labels(session, int(f), sizes)):
                if pair is not None:
                    counts[i, c] = mask_overlap(*pair, dilate[c])
            judged[i] = (counts[i] >= 0).any()
            bar.update(1)
        bar.close()
        return counts, "session", judged
    if per_frame is None:
        raise ContactError("contact 2d: the session has no masks and there are no per-frame fits to render")
    from intercap.geometry.rendering import MeshTopology

    cameras = Cameras.from_infos(session.cameras, device=device)
    body_topo = MeshTopology.from_faces(torch.as_tensor(np.asarray(per_frame.faces, np.int64)))
    obj_topo = MeshTopology.from_faces(torch.as_tensor(np.asarray(mesh.faces, np.int64)))
    obj_v = np.asarray(mesh.vertices, np.float64)
    ok = np.flatnonzero(per_frame.body_valid & per_frame.object_valid)
    for s in range(0, len(ok), batch):
        idx = ok[s:s + batch]
        posed = np.einsum("kj,tij->tki", obj_v, per_frame.R[idx]) + per_frame.t[idx][:, None]  # (B, K, 3)
        labels = rendered_labels(np.asarray(per_frame.vertices[idx]), body_topo, posed, obj_topo, cameras, sizes, device)
        for b, i in enumerate(idx):
            counts[i] = [mask_overlap(p, o, dilate[c]) for c, (p, o) in enumerate(labels[b])]
        bar.update(len(idx))
    bar.close()
    judged[ok] = True
    return counts, "rendered", judged


def overlap_thresholds(session, ccfg) -> np.ndarray:
    """(C,) T_view per view: `overlap_px` at 640 px width, scaled with the image area."""
    return np.array([ccfg.overlap_px * (c.width / 640) ** 2 for c in session.cameras])


_REGIONS: dict = {}
_REST: dict = {}  # body model setting -> rest vertices (V, 3), filled with _REGIONS


def body_regions(body_model_cfg) -> tuple[dict[str, np.ndarray], int]:
    """The body model's contact regions (name -> vertex ids) and vertex count; kept per
    model setting, since building a model takes seconds and the regions never change."""
    key = setting_key(body_model_cfg)
    if key not in _REGIONS:
        model = shared_model(body_model_cfg)
        _REGIONS[key] = ({r: ids.cpu().numpy() for r, ids in model.contact_regions.items()}, model.num_vertices)
        with torch.no_grad():  # the rest mesh (neutral shape, rest pose): the report's contact heat map
            _REST[key] = model(model.init_params(1)).vertices[0].float().cpu().numpy()
    return _REGIONS[key]


def _write_no_contact(stage_dir: Path, out_dir: Path, T: int, frame_ids: np.ndarray) -> dict:
    """The results of a session without an object: no contact in any frame."""
    log.info("contact: the session has no object; no contact in any frame")
    save_npz(stage_dir / "contact.npz", contact=np.zeros(T, bool), method=np.array("no object"), frame_ids=frame_ids,
             region_names=np.array([], str), region_distance_m=np.zeros((T, 0)), region_contact=np.zeros((T, 0), bool),
             invalid=np.zeros(T, bool))
    save_npy(stage_dir / "contact.npy", np.zeros(T, bool))
    publish(stage_dir / "contact.npy", out_dir / "contact.npy")
    return {"method": "no object", "frames_in_contact": 0}


def _checked_regions(cfg, session, per_frame) -> tuple[dict, list[str], list[int]]:
    """(the body model's regions, their names, the columns of contact.regions); ContactError when a region is
    unknown or the per-frame body is of another model."""
    ccfg = cfg.contact
    regions, num_vertices = body_regions(dataclasses.replace(cfg.body_model, name=session.body_model))
    names = list(regions)
    unknown = [r for r in ccfg.regions if r not in names]
    if unknown or not ccfg.regions:
        raise ContactError(f"contact.regions: {unknown or 'none given'}; the body model has {', '.join(names)}")
    if per_frame.vertices.shape[1] != num_vertices:
        raise ContactError(f"contact: the per-frame body has {per_frame.vertices.shape[1]} vertices, the body model "
                           f"{session.body_model!r} {num_vertices}; rerun the `body` stage")
    columns = [names.index(r) for r in ccfg.regions]
    return regions, names, columns


def _gt_accuracy(figures: dict, session, sources: dict) -> None:
    """With ground-truth contact (synthetic / annotated sessions): how good each source's labels are."""
    gt = session.ground_truth()
    if gt is not None and gt.contact is not None:
        from intercap.evaluation.metrics import contact_scores

        for name, labels in sources.items():
            figures[f"gt_accuracy_{name}_pct"] = contact_scores(labels, gt.contact)[0]


def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `contact` stage: writes OUT/contact.npy and OUT/contact/contact.npz."""
    ccfg = cfg.contact
    out_dir = Path(out_dir)
    stage_dir = out_dir / "contact"
    T = session.num_frames
    frame_ids = np.asarray(session.frame_ids)
    if session.object is None:
        return _write_no_contact(stage_dir, out_dir, T, frame_ids)
    method = resolve_method(ccfg, session)
    per_frame = load_per_frame(out_dir, session)
    regions, names, columns = _checked_regions(cfg, session, per_frame)
    mesh = session.object.load_mesh()

    # 3D: distances of every region in every frame (also what the other sources' region labels use)
    ids = [regions[r] for r in names]
    distance = region_distances(per_frame.vertices, ids, per_frame.R, per_frame.t, mesh.vertices, mesh.faces)
    judged_3d = per_frame.body_valid & per_frame.object_valid
    distance_3d = distance_labels(distance, columns, ccfg.distance_m)

    # 2D: mask overlap
    counts, mask_source, judged_2d = overlap_counts(session, ccfg, per_frame, mesh, cfg.run.device, progress)
    overlap_2d = overlap_labels(counts, overlap_thresholds(session, ccfg), ccfg.overlap_views)

    clean_frames = ccfg.clean_frames
    sources = {"2d": (overlap_2d, judged_2d), "3d": (distance_3d, judged_3d)}
    extra = {}
    if session.contact_frames is not None:
        extra["annotated"] = annotated_labels(session.contact_frames, frame_ids)
    carried, untracked = np.zeros(T, bool), np.zeros(T, bool)
    if method == "annotated":
        contact, invalid = extra["annotated"], np.zeros(T, bool)
    else:
        raw, judged = sources[method]
        contact, invalid = clean_labels(raw & judged, clean_frames), ~judged
        carried = carried_gaps(contact, object_centres(per_frame, mesh), cfg.global_.flight_min_frames,
                               ccfg.held_rest_m) & judged  # a frame without the results stays no contact
        contact = contact | carried
        untracked = untracked_gaps(contact, judged, cfg.global_.flight_min_frames, ccfg.untracked_min_run)
        contact = contact | untracked
    margin = ccfg.distance_m if method == "3d" else ccfg.region_margin_m
    touching = touching_regions(contact, distance, columns, margin)
    if method != "annotated":
        touching = neighbours_regions(touching, untracked)
    held, held_runs = np.zeros(T, bool), []
    # detected labels only (annotations are the user's word); the floor gives gravity's direction
    if method != "annotated" and ccfg.held and (out_dir / "prepare" / "ground.json").exists():
        held, holding, held_runs = object_held(session, cfg, per_frame, mesh, contact, touching, out_dir)
        contact = contact | held
        touching |= holding
        for first, last in held_runs:
            log.info("contact: frames %d-%d: the object touches nothing but does not fall: held by the region that "
                     "held it next to them", first, last)

    save_npz(stage_dir / "contact.npz", contact=contact, method=np.array(method), frame_ids=frame_ids,
             region_names=np.array(names), region_distance_m=distance, region_contact=touching, invalid=invalid,
             held=held, carried=carried, untracked=untracked,
             overlap_2d=overlap_2d & judged_2d, distance_3d=distance_3d & judged_3d, overlap_px=counts,
             mask_source=np.array(mask_source), region_vertex_ids=np.concatenate(ids).astype(np.int32),
             region_sizes=np.array([len(i) for i in ids], np.int32),
             rest_vertices=_REST.get(setting_key(dataclasses.replace(cfg.body_model, name=session.body_model)),
                                     np.zeros((0, 3), np.float32)),
             **extra)
    save_npy(stage_dir / "contact.npy", contact.astype(bool))
    publish(stage_dir / "contact.npy", out_dir / "contact.npy")
    if (invalid & ~untracked).any():
        log.warning("contact: %d frame(s) without the per-frame results %s needs count as no contact: %s",
                    int((invalid & ~untracked).sum()), method, frame_ids[invalid & ~untracked].tolist())
    figures = {
        "method": method,
        "frames_in_contact": int(contact.sum()),
        "frames_invalid": int(invalid.sum()),
        "invalid_frame_ids": frame_ids[invalid].tolist(),
        "mask_source": mask_source,
        "region_frames": {n: int(touching[:, k].sum()) for k, n in enumerate(names) if touching[:, k].any()},
        "carried_frames": int(carried.sum()),
        "untracked_gap_frames": int(untracked.sum()),
        "held_frames": int(held.sum()),
        "held_runs": [list(r) for r in held_runs],
    }
    _gt_accuracy(figures, session, {"2d": overlap_2d & judged_2d, "3d": distance_3d & judged_3d, **extra})
    return figures


def object_centres(per_frame, mesh) -> np.ndarray:
    """(T, 3) the mesh centroid's world position in each frame of the per-frame object track, NaN where
    it is not tracked."""
    R, t = np.nan_to_num(per_frame.R), np.nan_to_num(per_frame.t)
    return np.where(per_frame.object_valid[:, None], t + R @ np.asarray(mesh.vertices, np.float64).mean(0), np.nan)


def object_held(session, cfg, per_frame, mesh, contact: np.ndarray, touching: np.ndarray, out_dir: Path):
    """`held_frames` on the per-frame object track, with the floor prepare found and the free-flight
    settings of the global stage (`global.flight_*`: the same test that keeps a flight a flight)."""
    from intercap.dynamics.flight import object_on_ground
    from intercap.stages.prepare.stage import load_ground

    g = cfg.global_
    plane = load_ground(out_dir)
    vertices = np.asarray(mesh.vertices, np.float64)
    valid = per_frame.object_valid
    R, t = np.nan_to_num(per_frame.R), np.nan_to_num(per_frame.t)
    centres = object_centres(per_frame, mesh)
    samples = vertices[np.random.default_rng(0).choice(len(vertices), min(len(vertices), 256), replace=False)]
    points = np.where(valid[:, None, None], np.einsum("tij,mj->tmi", R, samples) + t[:, None], np.nan)
    on_ground = object_on_ground(points, plane.point, plane.normal, g.flight_ground_margin_m)
    return held_frames(contact, touching, centres, on_ground, np.asarray(plane.normal, np.float64), session.fps,
                       g.flight_min_frames, g.flight_max_residual_m, cfg.contact.held_rest_m)


def load_contact(out_dir) -> dict:
    """OUT/contact/contact.npz as a dict (method: str, region_names: list[str], arrays otherwise);
    ContactError when the `contact` stage has not run."""
    path = Path(out_dir) / "contact" / "contact.npz"
    if not path.exists():
        raise ContactError(f"{path} missing; run the `contact` stage first")
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    data["method"] = str(data["method"])
    data["region_names"] = [str(n) for n in data["region_names"]]
    if "mask_source" in data:
        data["mask_source"] = str(data["mask_source"])
    return data
