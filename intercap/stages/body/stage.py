"""The `body` stage: per-frame whole-body fitting to multi-view keypoints and depth (PROX-D).

For every frame the body model (anny by default) is fitted to
  * E_J, the 2D keypoints of every view (BODY_25 + both hands; the session's
    OpenPose JSON, or the `detect` stage's), reprojected through each camera
    with its lens distortion, Geman-McClure robust, weighted by confidence^2;
  * E_D, each view's segmented person points against the body vertices that
    view can see (visibility by a coarse z-buffer of the whole mesh plus the
    normal facing the camera, recomputed at every L-BFGS step);
  * priors: learned body-pose mixture + anatomical joint limits + extreme
    elbow/knee bending, finger ranges, shape, expression, and self-penetration
    approximated by spheres along the limbs and trunk (`fitter.BodySpheres`).
The rooms: `observations` (what the data gives the fit), `terms` (the energy table
and its phases, `terms.PHASES`), `fitter` (the optimisation), this module (the
take in chunks, the outputs). Frames are fitted in batches (`fitter.BodyFitter`),
each warm-started from the previous batch's last fit; a process may fit several
chunks of the take side by side, their batches in one evaluation (`fit_chunks`:
on a GPU that divides the kernel launches per frame by their number); the
phenotype is fitted on the first `shape_batches` batches and held at their mean
after (one person: re-fitted per batch it drifted). A frame with too little
evidence (see `observations.usable_frames`) is marked invalid and written as
NaN, never invented.

Outputs (docs/outputs.md): body_params.npz (the model's parameters per
frame, `model`, `valid`, per-frame `shape` and its sequence mean `shape_mean`),
body_vertices.npy, body_faces.npy, keypoints3d.npy, kept in OUT/body/ (with
the resumable checkpoints and overlay pictures) and shown at OUT/ until the
`global` stage replaces them with its own.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from intercap.body_models import BodyParams, shared_model
from intercap.body_models.keypoints import BODY_25_EDGES, NUM_BODY, NUM_BODY_HANDS
from intercap.energies import priors
from intercap.geometry.cameras import Cameras, project
from intercap.geometry.ground import up_hint_from_cameras
from intercap.io.files import publish, save_npy, save_npz
from intercap.stages import chunks
from intercap.stages.body.fitter import (
    BodyFitter,
    failure_limit,
    fit_to_data_mm,
    frame_energy,
    refit_from_evidence,
    reprojection_error_px,
    stature,
    upright_template,
)
from intercap.stages.body.observations import (
    BodyObservations,
    KeypointSource,
    PersonPoints,
    keypoint_views,
    shares_shape,
    usable_frames,
)
from intercap.stages.chunks import Checkpoint, Chunk, lockstep

log = logging.getLogger(__name__)


def draw_overlay(session, keypoints: np.ndarray, frame_id: int, cameras: Cameras, path: Path) -> None:
    """First camera's colour image with the fitted BODY_25 skeleton (green), from the frame's world
    keypoints (K, 3) as saved (projected on the CPU: on a GPU a frame's few points cost launches)."""
    image = session.read_color(0, frame_id)
    if image is None:
        return
    first = cameras.select([0]).to(device="cpu")
    pix, z = project(torch.as_tensor(keypoints[:NUM_BODY], dtype=first.K.dtype), first)
    canvas = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    pts = pix[0].numpy()
    for a, b in BODY_25_EDGES:
        if z[0, a] > 0 and z[0, b] > 0:
            cv2.line(canvas, tuple(int(v) for v in pts[a]), tuple(int(v) for v in pts[b]), (0, 220, 0), 2)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), canvas)


def world_up(session, out_dir: Path) -> np.ndarray:
    """(3,) unit up in the world frame: the ground plane's normal (given in session.yaml or fitted
    by `prepare`), else the cameras' mean -y axis. Never a world axis: rigs put the world anywhere."""
    from intercap.stages.prepare.stage import load_ground

    if (Path(out_dir) / "prepare" / "ground.json").exists():
        return load_ground(out_dir).normal
    if session.ground is not None:
        normal = np.asarray(session.ground[1], np.float64)
        return normal / np.linalg.norm(normal)
    return up_hint_from_cameras(np.stack([c.T_world_from_cam for c in session.cameras]))


def chunk_groups(T: int, cfg) -> list[tuple[Chunk, ...]]:
    """The take's body chunks dealt to the processes (`intercap.stages.chunks.chunk_groups`), cut on batches."""
    return chunks.chunk_groups(T, cfg, cfg.body, cfg.body.batch_frames)



def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `body` stage: writes OUT/body_params.npz, body_vertices.npy, body_faces.npy, keypoints3d.npy.

    The take is fitted in chunks of frames by `run.workers` processes (`intercap.parallel`), each
    fitting `side_by_side` chunks at once (`fit_chunks`); each chunk keeps its own resumable checkpoint."""
    out_dir = Path(out_dir)
    (out_dir / "body").mkdir(parents=True, exist_ok=True)
    groups = chunk_groups(session.num_frames, cfg)
    take = chunks.fit_in_chunks(fit_chunks, stitch_chunks, session, cfg, out_dir, groups, "body", progress)
    model = shared_model(dataclasses.replace(cfg.body_model, name=session.body_model), device=cfg.run.device)
    fitted = BodyParams.from_numpy_dict(take["params"], dtype=model.dtype, device=model.faces.device)
    valid = take["valid"]
    cameras = Cameras.from_infos(session.cameras, device=cfg.run.device)
    if not valid.any():
        log.warning("body: no frame has a body fit (no person seen in any view: check keypoints/, masks/ "
                    "or the detector's output in OUT/detect/)")
    figures = write_outputs(session, model, fitted, valid, take["reprojection_px"], take["seconds"], out_dir, cfg.body,
                            cameras, fit_to_data_mm=take["fit_to_data_mm"].astype(np.float32),
                            reinitialised=take["reinitialised"])
    return {**figures, "keypoints_rejected_by_views": take["keypoints_rejected"],
            "keypoint_sides_swapped": take["keypoint_sides_swapped"],
            "person_masks_from_keypoint_depth": take["person_masks_still"], "workers": len(groups),
            "chunks": take["chunks"]}


def stitch_chunks(results: list[list[dict]]) -> dict:
    """The take from its chunks' results (`chunk_batches`', a list per process): the parameters (numpy)
    and per-frame arrays concatenated in frame order, the counts summed: detections dropped for
    disagreeing with the other views (this run's batches; `reject_disagreeing_views`) and view-frames
    whose person the depth background had taken in (masked by `PersonPoints.still_mask`)."""
    parts = [part for group in results for part in group]
    params = {name: np.concatenate([p["params"][name] for p in parts]) for name in parts[0]["params"]}
    arrays = {key: np.concatenate([p[key] for p in parts])
              for key in ("valid", "reprojection_px", "seconds", "fit_to_data_mm", "reinitialised")}
    return {"params": params, **arrays, "chunks": len(parts),
            "keypoints_rejected": sum(int(p.get("keypoints_rejected", 0)) for p in parts),
            "keypoint_sides_swapped": sum(int(p.get("keypoint_sides_swapped", 0)) for p in parts),
            "person_masks_still": sum(int(p.get("person_masks_still", 0)) for p in parts)}


@dataclass
class ChunkWorkshop:
    """What the chunks one process fits share: the session, the model, the cameras, the evidence
    readers, one fitter, and the phenotype estimates of every chunk (one person, one shape)."""

    session: object
    cfg: object
    out_dir: Path
    model: object
    cameras: Cameras
    keypoint_source: KeypointSource
    person: PersonPoints
    fitter: BodyFitter
    shape_estimates: list  # one {first row of a batch: phenotype} per chunk

    @classmethod
    def open(cls, session, cfg, out_dir: Path) -> "ChunkWorkshop":
        from intercap.session.frame_cache import open_session

        session = open_session(session, out_dir)
        bcfg = cfg.body
        torch.manual_seed(bcfg.seed)
        out_dir = Path(out_dir)
        model = shared_model(dataclasses.replace(cfg.body_model, name=session.body_model), device=cfg.run.device)
        cameras = Cameras.from_infos(session.cameras, device=cfg.run.device)
        keypoint_source = KeypointSource(session, out_dir, cfg.detect.use_session_keypoints, cameras,
                                         bcfg.keypoint_view_check_px)
        person = PersonPoints(session, cameras, bcfg, out_dir)
        fitter = BodyFitter(model, cameras, bcfg)
        if (out_dir / "prepare" / "ground.json").exists():  # one view hides the legs: they must not sink through it
            from intercap.stages.prepare.stage import load_ground

            ground = load_ground(out_dir)
            fitter.ground = tuple(torch.as_tensor(x, dtype=torch.float32, device=cameras.K.device)
                                  for x in (ground.point, ground.normal))
        return cls(session, cfg, out_dir, model, cameras, keypoint_source, person, fitter, [])

    def hold_shape(self) -> bool:
        """Hold the fitter's phenotype at the mean of all chunks' estimates once there are
        `shape_batches` of them (one person, one shape: later batches fit pose only). True when it
        holds it now."""
        estimates = [v for chunk in self.shape_estimates for v in chunk.values()]
        batches, fitter = self.cfg.body.shape_batches, self.fitter
        if batches <= 0 or len(estimates) < batches or fitter.held_shape is not None:
            return False
        fitter.held_shape = torch.as_tensor(np.mean(estimates, 0), dtype=fitter.model.dtype,
                                            device=fitter.cameras.K.device)
        return True


def fit_chunks(session, cfg, out_dir: Path, chunks: tuple[Chunk, ...], queue) -> list[dict]:
    """Fit `chunks` side by side: each round, the next batch of every unfinished chunk goes into one
    fit, one evaluation for all (the frames do not interact; each chunk keeps its phenotype until it
    is held). On a GPU a step's cost is its kernel launches, not their size, so K chunks side by side
    cost about what one does; on the CPU it saves the per-operation overhead. Returns
    `chunk_batches`' result per chunk."""
    workshop = ChunkWorkshop.open(session, cfg, out_dir)
    runs = [chunk_batches(workshop, chunk, queue) for chunk in chunks]

    def serve(batches: list) -> list:
        obs = BodyObservations.cat([sub for sub, _ in batches])
        groups, first = [], 0  # each chunk its phenotype, as if fitted alone
        for sub, _ in batches:
            count = 1 if shares_shape(sub, workshop.fitter.cfg) else sub.batch_size
            groups.append(torch.full((sub.batch_size,), first) if count == 1 else first + torch.arange(count))
            first += count
        start = time.perf_counter()
        params, stats = workshop.fitter.fit(obs, BodyParams.cat([init for _, init in batches]),
                                            shape_groups=torch.cat(groups).to(obs.keypoints.device))
        seconds = (time.perf_counter() - start) / obs.batch_size
        replies, row = [], 0
        for sub, _ in batches:
            rows = slice(row, row + sub.batch_size)
            row = rows.stop
            replies.append((params[rows], {"terms": {name: v[rows] for name, v in stats["terms"].items()}},
                            seconds * sub.batch_size))
        return replies

    return lockstep(runs, serve)


@dataclass
class ChunkProgress:
    """A chunk's rows so far, as its checkpoint (OUT/body/progress_LO_HI.npz) holds them."""

    fitted: BodyParams
    done: np.ndarray
    valid: np.ndarray
    reprojection_px: np.ndarray
    seconds: np.ndarray
    fit_to_data_mm: np.ndarray
    pose_prior: np.ndarray  # the learned pose prior's energy of each frame's fit
    reinitialised: np.ndarray
    shape_estimates: dict  # first row of a batch -> the phenotype fitted on it; `shape_batches` of them, then held
    sized: np.ndarray | None = None  # the template's phenotype from the person's measured size (NaN: its own kept)

    @classmethod
    def start(cls, model, T: int) -> "ChunkProgress":
        """Nothing fitted yet."""
        return cls(model.init_params(T), np.zeros(T, bool), np.zeros(T, bool), np.full(T, np.nan), np.zeros(T),
                   np.full(T, np.nan), np.full(T, np.nan), np.zeros(T, bool), {})

    def resume(self, saved: dict, model) -> bool:
        """Take the rows of a saved checkpoint; True when it holds phenotype estimates (those of batches
        still done: a resumed batch estimates again)."""
        self.fitted = BodyParams.from_numpy_dict(saved, dtype=model.dtype, device=model.faces.device)
        self.done, self.valid = saved["done"], saved["valid"]
        self.reprojection_px, self.seconds = saved["reprojection_px"], saved["seconds"]
        if "fit_to_data_mm" in saved:  # older checkpoints lack it
            self.fit_to_data_mm, self.pose_prior = saved["fit_to_data_mm"], saved["pose_prior"]
            self.reinitialised = saved["reinitialised"]
        if "sized_shape" in saved:
            self.sized = saved["sized_shape"]
        if "shape_estimates" not in saved:
            return False
        self.shape_estimates.update({int(row): value for row, value in
                                     zip(saved["shape_estimate_rows"], saved["shape_estimates"]) if self.done[row]})
        return True

    def save(self, checkpoint: Checkpoint, model) -> None:
        estimates = self.shape_estimates
        checkpoint.save(**self.fitted.to_numpy_dict(), done=self.done, valid=self.valid,
                        reprojection_px=self.reprojection_px, seconds=self.seconds,
                        fit_to_data_mm=self.fit_to_data_mm, pose_prior=self.pose_prior,
                        reinitialised=self.reinitialised,
                        shape_estimates=np.array(list(estimates.values()), np.float32).reshape(-1, model.num_shape),
                        shape_estimate_rows=np.array(list(estimates), np.int64),
                        **({} if self.sized is None else {"sized_shape": self.sized}))


def chunk_batches(workshop: ChunkWorkshop, chunk: Chunk, queue):
    """Fit frames [chunk.lo, chunk.hi) in batches, each warm-started from the previous batch's
    last fit; checkpointed after every batch (OUT/body/progress_LO_HI.npz). A generator: it yields
    each batch's (observations, initial parameters) and is sent back (parameters, statistics, seconds
    of the fit) (`fit_chunks`). Returns the rows' parameters (numpy), `valid`, `reprojection_px` and
    `seconds`. `queue.put(n)` per n frames done."""
    session, bcfg, model, fitter = workshop.session, workshop.cfg.body, workshop.model, workshop.fitter
    T = chunk.hi - chunk.lo
    frame_ids = session.frame_ids[chunk.lo:chunk.hi]
    checkpoint = Checkpoint.of_chunk(workshop.out_dir, "body", chunk)
    progress = ChunkProgress.start(model, T)
    rejected = swapped = 0  # keypoints dropped, view-limbs exchanged by the view check in this run's batches
    still = 0  # view-frames whose person stood in the depth background (`PersonPoints.still_mask`)
    workshop.shape_estimates.append(progress.shape_estimates)
    saved = checkpoint.load()
    if saved is not None:
        if progress.resume(saved, model):
            workshop.hold_shape()
        log.info("body: resuming frames %d-%d, %d of %d already fitted", chunk.lo, chunk.hi - 1,
                 int(progress.done.sum()), T)
        queue.put(int(progress.done.sum()))

    upright = upright_template(model, world_up(session, workshop.out_dir))
    if progress.sized is not None and np.isfinite(progress.sized).all():  # resumed: sized as before
        upright.shape[:] = torch.as_tensor(progress.sized, dtype=upright.shape.dtype, device=upright.shape.device)
        fitter.shape_center = upright.shape[0].clone()
    template = upright  # the next batch starts from the last fit
    size = bcfg.batch_frames
    for batch in [np.arange(s, min(s + size, T)) for s in range(0, T, size)]:
        if progress.done[batch].all():
            if progress.valid[batch].any():
                template = progress.fitted[int(batch[progress.valid[batch]][-1])]
            continue
        start = time.perf_counter()
        obs, dropped, exchanged, masked = read_batch(workshop, frame_ids[batch])
        rejected, swapped, still = rejected + dropped, swapped + exchanged, still + masked
        usable = usable_frames(obs.keypoints, obs.point_valid, bcfg).cpu().numpy()
        fit_seconds = 0.0
        if usable.any():
            keep = np.flatnonzero(usable)
            sub = obs.select(keep)
            if progress.sized is None and template is upright and bcfg.size_from_depth:  # nothing fitted yet: size
                resized = sized_template(workshop, progress, sub, upright)
                if resized is not None:
                    upright = template = resized
            init = fitter.initialise(sub, template)
            waited = time.perf_counter()
            params, stats, fit_seconds = yield sub, init  # fitted with the other chunks' batches (`fit_chunks`)
            start += time.perf_counter() - waited
            warm = record_fit(workshop, progress, batch, keep, sub, params, stats, upright)
            if warm is not None:
                template = warm
        progress.done[batch] = True
        progress.seconds[batch] = (time.perf_counter() - start + fit_seconds) / len(batch)
        queue.put(len(batch))
        progress.save(checkpoint, model)
    return {"params": progress.fitted.to_numpy_dict(), "valid": progress.valid,
            "reprojection_px": progress.reprojection_px, "seconds": progress.seconds,
            "fit_to_data_mm": progress.fit_to_data_mm, "reinitialised": progress.reinitialised,
            "keypoints_rejected": rejected, "keypoint_sides_swapped": swapped, "person_masks_still": still}


def read_batch(workshop: ChunkWorkshop, ids: np.ndarray) -> tuple[BodyObservations, int, int, int]:
    """The observations of frames `ids`, the keypoints the view check dropped and the view-limbs it
    exchanged among them, and the view-frames whose person mask `PersonPoints.still_mask` made (the
    readers are the process's: their counts, this batch's part of them)."""
    keypoint_source, person = workshop.keypoint_source, workshop.person
    before, swapped_before = keypoint_source.rejected, keypoint_source.swapped
    kps = keypoint_source.batch(ids, workshop.cfg.body.min_keypoint_confidence)
    rejected, swapped = keypoint_source.rejected - before, keypoint_source.swapped - swapped_before
    before = person.still_views
    points, point_valid = person.batch(ids, kps)
    still = person.still_views - before
    device = workshop.cameras.K.device
    obs = BodyObservations(ids, torch.from_numpy(kps).to(device), points.to(device), point_valid.to(device))
    return obs, rejected, swapped, still


def sized_template(workshop: ChunkWorkshop, progress: ChunkProgress, sub: BodyObservations,
                   upright: BodyParams) -> BodyParams | None:
    """The upright template sized to the person's measured size (`BodyFitter.size_template`), noted in
    `progress.sized`; None when not measured (tried again on the next batch)."""
    model = workshop.model
    resized, scale = workshop.fitter.size_template(sub, upright)
    if scale is None:
        return None
    progress.sized = np.full(model.num_shape, np.nan) if resized is upright else resized.shape[0].cpu().numpy()
    log.info("body: measured size %.2f x the template's: starting from a stature of %.2f m",
             scale, float(stature(model, resized.shape)))
    return resized


def tracked_fit(workshop: ChunkWorkshop, progress: ChunkProgress, batch: np.ndarray, keep: np.ndarray,
                sub: BodyObservations, params: BodyParams, stats: dict,
                upright: BodyParams) -> tuple[BodyParams, np.ndarray, float]:
    """The fits of the frames `keep` of the chunk's rows `batch`, those that failed (off their points, or
    contorted to reach them) refitted from the evidence; with their fit-to-data (mm) and the limit a
    fit-to-data failed above. Notes the rows' pose prior and which were replaced."""
    bcfg, model, fitter = workshop.cfg.body, workshop.model, workshop.fitter
    rows = batch[keep]
    with torch.no_grad():
        sub_gap = fit_to_data_mm(model(params).vertices, sub)
    recent = slice(max(0, batch[0] - bcfg.track_window), batch[0])
    one_view = keypoint_views(sub.keypoints, bcfg).cpu().numpy() < 2  # no triangulation to fix the heading
    gap_limit = failure_limit(progress.fit_to_data_mm[recent], bcfg.track_factor, bcfg.track_floor_mm)
    failed = ((sub_gap > gap_limit)
              | (one_view & (stats["terms"]["pose_prior"]
                             > failure_limit(progress.pose_prior[recent], bcfg.track_prior_factor))))
    if failed.any():  # off the points, or contorted to reach them: refit those frames from the evidence
        params, replaced = refit_from_evidence(fitter, sub, params, frame_energy(fitter, stats["terms"]), failed,
                                               upright, sub_gap, gap_limit)
        progress.reinitialised[rows] = replaced
        log.info("body: frames %s failed (fit-to-data or pose prior); refitted from the evidence, "
                 "%d replaced", sub.frame_ids[failed].tolist(), int(replaced.sum()))
        with torch.no_grad():
            sub_gap = fit_to_data_mm(model(params).vertices, sub)
            progress.pose_prior[rows] = priors.learned_pose_prior(params.body_pose).cpu().numpy()
    else:
        progress.pose_prior[rows] = stats["terms"]["pose_prior"]
    return params, sub_gap, gap_limit


def record_fit(workshop: ChunkWorkshop, progress: ChunkProgress, batch: np.ndarray, keep: np.ndarray,
               sub: BodyObservations, params: BodyParams, stats: dict, upright: BodyParams) -> BodyParams | None:
    """Keep the fits (`tracked_fit`) of the frames `keep` of the chunk's rows `batch`; returns the next
    batch's start, the last fit that lies on its points (None when none does: a failed fit is no start),
    and notes its phenotype estimate until the phenotype is held."""
    bcfg, fitter = workshop.cfg.body, workshop.fitter
    params, sub_gap, gap_limit = tracked_fit(workshop, progress, batch, keep, sub, params, stats, upright)
    rows = batch[keep]
    progress.fit_to_data_mm[rows] = sub_gap
    for name, value in params.tensors().items():
        getattr(progress.fitted, name)[rows] = value
    progress.reprojection_px[rows] = reprojection_error_px(workshop.model, params, sub, workshop.cameras)
    progress.valid[rows] = True
    on_points = np.flatnonzero(sub_gap <= gap_limit)
    if not len(on_points):
        return None
    start = params[int(on_points[-1])]
    if fitter.held_shape is None and bcfg.shape_batches > 0:
        progress.shape_estimates[int(batch[0])] = params.shape[on_points].mean(0).cpu().numpy()
        if workshop.hold_shape():
            log.info("body: phenotype held from frame %d on (mean of %d batches' fits)",
                     int(sub.frame_ids[-1]) + 1, sum(map(len, workshop.shape_estimates)))
    return start

PER_FRAME_FILES = ("body_params.npz", "body_vertices.npy", "body_faces.npy", "keypoints3d.npy")


def save_body_results(folder: Path, model, fitted: BodyParams, valid: np.ndarray, frame_ids,
                      **extra) -> tuple[np.ndarray, np.ndarray]:
    """PER_FRAME_FILES of docs/outputs.md into `folder`, frames not `valid` NaN; returns the
    vertices (T, V, 3) and keypoints (T, 67, 3). `extra` arrays go into body_params.npz beside the
    parameters."""
    T = len(valid)
    vertices = np.full((T, model.num_vertices, 3), np.nan, np.float32)
    keypoints = np.full((T, NUM_BODY_HANDS, 3), np.nan, np.float32)
    with torch.no_grad():
        for s in range(0, T, 16):
            idx = np.arange(s, min(s + 16, T))
            idx = idx[valid[idx]]
            if len(idx):
                out = model(fitted.map(lambda t: t[idx]))
                vertices[idx] = out.vertices.cpu().numpy()
                keypoints[idx] = out.keypoints[:, :NUM_BODY_HANDS].cpu().numpy()
    arrays = fitted.to_numpy_dict()
    for name in arrays:
        arrays[name][~valid] = np.nan
    shape_mean = arrays["shape"][valid].mean(0) if valid.any() else np.full(model.num_shape, np.nan)
    save_npz(folder / "body_params.npz", model=np.array(model.name), **arrays, shape_mean=shape_mean.astype(np.float32),
             valid=valid, frame_ids=frame_ids, **extra)
    save_npy(folder / "body_vertices.npy", vertices)
    save_npy(folder / "body_faces.npy", model.faces.cpu().numpy().astype(np.int64))
    save_npy(folder / "keypoints3d.npy", keypoints)
    return vertices, keypoints


def write_outputs(session, model, fitted: BodyParams, valid, reproj, seconds, out_dir: Path, bcfg, cameras,
                  fit_to_data_mm: np.ndarray, reinitialised: np.ndarray) -> dict:
    """The docs/outputs.md files, kept in OUT/body/ and shown at OUT/ until the `global` stage
    replaces them; frames without a fit are NaN. body_params.npz also holds the per-frame
    `reprojection_px`, `fit_to_data_mm` and `reinitialised`."""
    T = session.num_frames
    stage_dir = out_dir / "body"
    _, keypoints = save_body_results(stage_dir, model, fitted, valid, session.frame_ids,
                                     reprojection_px=reproj.astype(np.float32), fit_to_data_mm=fit_to_data_mm,
                                     reinitialised=reinitialised)
    for name in PER_FRAME_FILES:
        publish(stage_dir / name, out_dir / name)
    for i in range(0, T, max(1, bcfg.overlay_every)):
        if valid[i]:
            draw_overlay(session, keypoints[i], int(session.frame_ids[i]), cameras,
                         stage_dir / "overlays" / f"{int(session.frame_ids[i]):06d}.jpg")
    return {
        "frames_fitted": int(valid.sum()),
        "frames_unusable": int((~valid).sum()),
        "reprojection_px_median": float(np.nanmedian(reproj)) if valid.any() else None,
        "fit_to_data_mm_median": float(np.nanmedian(fit_to_data_mm)) if np.isfinite(fit_to_data_mm).any() else None,
        "fit_to_data_mm_max": float(np.nanmax(fit_to_data_mm)) if np.isfinite(fit_to_data_mm).any() else None,
        "frames_reinitialised": int(reinitialised.sum()),
        "seconds_per_frame": float(seconds.mean()),
    }
