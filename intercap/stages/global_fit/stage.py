"""The `global` stage: body and object over all frames jointly, with contact (InterCap's last step).

The per-frame results (OUT/body/, OUT/object/) are refined together, the body's
shape fixed to the per-frame fits' sequence mean, by one L-BFGS problem per
window of frames (`fitter`), its energy the table of `terms`:
  * E_B, the body stage's own terms (keypoints, depth against visible vertices,
    pose / hand priors, self-penetration) with its weights;
  * E_O, the observed object points (each view's object pixels with depth)
    against the posed object's surface, through a signed-distance grid of the
    mesh; a weak anchor to the tracked pose where the tracker trusted it;
  * E_P, body vertices inside the object; E_C, the touching hands' nearest
    palm patch onto the object's surface, and E_C', a grasping palm onto the
    object's graspable vertices (`object.contact_vertices`), both only in the
    frames the `contact` stage marks; E_G, body and object above the ground;
  * E_A, the acceleration of the object's points; the acceleration of the
    body's vertices; the learned motion priors of body and hands (E_S, E_L,
    E_R; `intercap.energies.motion_prior`) when weighted (off by default: they
    helped one benchmark session and hurt the other, BENCHMARKS.md).
A take without an object to refine (none in the session, or none tracked) is fitted the same way with
the body's terms alone. The fit starts from the per-frame body low-passed in time, and frames whose
per-frame fit left its depth points from their neighbours' poses (`observations.load_per_frame`).
Long sequences run in overlapping windows (memory stays bounded; `fitter.windows`).
The take is cut into chunks of frames (`intercap.stages.chunks`), each fitted
in a worker process with a window's overlap of context either side and its own
checkpoint (OUT/global/progress_LO_HI.npz), from which a killed run resumes.
Frames that the per-frame stages could not fit stay free variables (the motion
terms carry them), but are written NaN, as before: marked, never invented.

Writes OUT/global/ (body_params.npz, body_vertices.npy, body_faces.npy,
keypoints3d.npy, object_poses.npz, overlays) and shows them at OUT/, where the
per-frame stages' results were; those stay in OUT/body/ and OUT/object/.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np
import torch

from intercap.body_models import BodyParams, shared_model
from intercap.dynamics.flight import warn_held
from intercap.evaluation.warnings import data_disagreement, unsynchronised
from intercap.geometry.cameras import Cameras
from intercap.io.files import per_frame_result, publish, save_npz, write_json
from intercap.parallel import shutdown, worker_count
from intercap.stages.body.stage import draw_overlay, save_body_results
from intercap.stages.chunks import Checkpoint, Chunk, fit_in_chunks, frame_chunks
from intercap.stages.global_fit.fitter import GlobalFitter, windows
from intercap.stages.global_fit.observations import (
    ObjectShape,
    Observations,
    PerFrameResults,
    acceleration_across_gaps,
    acceleration_scale,
    free_flight,
    grasping_hands,
    hand_object_distance,
    load_per_frame,
    no_flight,
    object_inside_body,
)

log = logging.getLogger(__name__)

OUTPUT_FILES = ("body_params.npz", "body_vertices.npy", "body_faces.npy", "keypoints3d.npy", "object_poses.npz")


def nothing_to_refine(out_dir: Path) -> str | None:
    """Why the joint fit has nothing to refine (the body fitted in no frame: a person never seen), or
    None. The per-frame results then stand, and the later stages run on them."""
    path = per_frame_result(out_dir, "body", "body_params.npz")
    if path.exists():
        with np.load(path) as saved:
            if not saved["valid"].any():
                return f"no frame has a body fit ({path})"
    return None  # a missing file: `load_per_frame` says which stage to run


def object_left_out(session, out_dir: Path) -> str | None:
    """Why the joint fit fits the body alone (no object in the session, or none of its tracked poses to
    refine: an object never found, or found only inside the body), or None when the object takes part."""
    if session.object is None:
        return "no object in session"
    path = per_frame_result(out_dir, "object", "object_poses.npz")
    if not path.exists():
        return None  # `load_per_frame` says which stage to run
    with np.load(path) as poses:
        valid = poses["valid"].astype(bool)
    if not valid.any():
        return f"the object was tracked in no frame ({path})"
    inside = Path(out_dir) / "global" / "object_inside_body.npy"  # `object_inside_body`'s, written by `run`
    if inside.exists() and not (valid & ~np.load(inside)).any():
        return "every tracked object pose lies inside the body"
    return None


def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `global` stage; see the module docstring. The take is fitted in chunks of frames by
    `run.workers` processes (`intercap.parallel`), each chunk with a window's overlap of context
    either side and its own resumable checkpoint. Without an object to refine, the body alone is
    fitted over time (its data, ground, acceleration and motion-prior terms)."""
    out_dir = Path(out_dir)
    reason = nothing_to_refine(out_dir)
    if reason is not None:
        log.warning("global: skipped: %s; the per-frame results stand", reason)
        return {"skipped": reason}
    g = cfg.global_
    inside = np.zeros(session.num_frames, bool)
    (out_dir / "global").mkdir(parents=True, exist_ok=True)
    if object_left_out(session, out_dir) is None:
        inside = object_inside_body(session, out_dir, g.object_inside_body_share)
        if inside.any():
            log.warning("global: %d tracked object pose(s) lie inside the body (fitted to the person's points):"
                        " not trusted here", int(inside.sum()))
    np.save(out_dir / "global" / "object_inside_body.npy", inside)
    left_out = object_left_out(session, out_dir)
    if left_out is not None:
        log.info("global: %s: the body is fitted over time alone", left_out)
    T = session.num_frames
    chunks = frame_chunks(T, worker_count(cfg), cfg.run.min_frames_per_worker, context=g.window_overlap)
    problem = None
    if len(chunks) == 1:
        problem = GlobalProblem(session, cfg, out_dir)
    elif left_out is None:  # workers load the session and set up the problem themselves, reading the grid built here
        object_shape(session, g, out_dir)
    fit = fit_in_chunks(fit_chunk, stitch, session, cfg, out_dir, chunks, "global", progress, extra=(problem,))
    if problem is None:
        shutdown()  # no later stage has chunks: the idle workers' memory goes before the outputs'
        problem = GlobalProblem(session, cfg, out_dir)
    warn_held(problem.flight["held"], "global")
    fitted = BodyParams.from_numpy_dict(fit["params"], dtype=problem.model.dtype, device=problem.model.faces.device)
    figures = write_outputs(session, problem.model, fitted, fit["R"], fit["centre"], problem.shape, problem.per_frame,
                            fit["seconds"], fit["history"], out_dir, problem.observations, problem.cameras, cfg,
                            problem.fitter.weight)
    before, after = (figures.get(f"energy_{when}", {}).get("body_keypoints", 0.0) for when in ("before", "after"))
    ratio = after / before if before > 0 else 1.0
    speed = pelvis_speed_p90(out_dir, session.fps)
    if g.max_keypoint_energy_ratio > 0 and ratio > g.max_keypoint_energy_ratio:
        log.warning("global: %s (the per-frame pelvis moves %.1f m/s at the 90th percentile at %g fps)",
                    data_disagreement(ratio, session.fps), speed, session.fps)
    offsets = camera_offsets_ms(session, problem, out_dir, cfg) if g.max_camera_offset_ms > 0 else {}
    out_of_sync = unsynchronised(offsets, g.max_camera_offset_ms)
    if out_of_sync:
        log.warning("global: %s", out_of_sync)
    repaired = np.flatnonzero(problem.per_frame.repaired)
    if len(repaired):
        log.info("global: %d frame(s) whose per-frame fit had left its data started from their neighbours: %s",
                 len(repaired), session.frame_ids[repaired].tolist())
    return {**figures, **problem.flight["figures"], "object_frames_inside_body": int(inside.sum()),
            "object_left_out": left_out, "frames_repaired": len(repaired),
            "body_acceleration_scale_median": float(np.median(problem.per_frame.acceleration_scale)),
            "body_acceleration_scale_max": float(np.max(problem.per_frame.acceleration_scale)),
            **start_width_figures(problem.per_frame.start_widths, session.fps),
            "repaired_frame_ids": session.frame_ids[repaired].tolist(),
            "workers": len(chunks), "pelvis_speed_p90_mps": speed, "keypoint_energy_ratio": ratio,
            "camera_time_offsets_ms": offsets}


def stitch(parts: list[dict]) -> dict:
    """The chunks' results (`fit_chunk`'s, in frame order) as the take's: body parameters (numpy), the
    object's `R` and `centre` (tensors), every window's `history`, the fit's `seconds`."""
    return {"params": {name: np.concatenate([p["params"][name] for p in parts]) for name in parts[0]["params"]},
            "R": torch.from_numpy(np.concatenate([p["R"] for p in parts])),
            "centre": torch.from_numpy(np.concatenate([p["centre"] for p in parts])),
            "history": [h for p in parts for h in p["history"]], "seconds": sum(p["seconds"] for p in parts)}


def camera_offsets_ms(session, problem: "GlobalProblem", out_dir: Path, cfg) -> dict:
    """Each camera's lag behind the fitted motion against the cameras' median, ms
    (calib.time_offsets), on `global.time_check_frames` frames spread over the take."""
    from intercap.calib.time_offsets import camera_time_offsets

    keypoints = np.load(out_dir / "global" / "keypoints3d.npy", mmap_mode="r")
    T = len(keypoints)
    if T < 3 or session.num_cameras < 2:
        return {}
    frames = np.unique(np.linspace(1, T - 2, min(T - 2, cfg.global_.time_check_frames)).round().astype(np.int64))
    observed = problem.observations.keypoints.batch(session.frame_ids[frames], cfg.body.min_keypoint_confidence)
    offsets = camera_time_offsets(keypoints, observed, frames, problem.cameras, session.fps)
    return {name: round(float(o) * 1000, 2) for name, o in zip(session.camera_names, offsets) if np.isfinite(o)}


def pelvis_speed_p90(out_dir: Path, fps: float) -> float:
    """90th percentile of the per-frame body's pelvis (BODY_25 mid-hip) speed between consecutive
    fitted frames, m/s at `fps`; 0 when there are no two."""
    path = per_frame_result(out_dir, "body", "keypoints3d.npy")
    if not path.exists():
        return 0.0
    speeds = np.linalg.norm(np.diff(np.load(path, mmap_mode="r")[:, 8], axis=0), axis=1) * fps
    speeds = speeds[np.isfinite(speeds)]
    return float(np.percentile(speeds, 90)) if len(speeds) else 0.0


def object_shape(session, g, out_dir: Path) -> ObjectShape:
    """The session object's `ObjectShape`, its grid cached in OUT/global/object_sdf.npz."""
    return ObjectShape(session.object.load_mesh(), g.sdf_resolution, session.object.contact_vertices, seed=g.seed,
                       cell_m=g.sdf_cell_m, margin_m=g.sdf_margin_m, cache=out_dir / "global" / "object_sdf.npz")


def start_width_figures(widths: np.ndarray | None, fps: float) -> dict:
    """Metrics of the smoothed start's widths per frame (seconds), where they vary (a body-only fit)."""
    if widths is None:
        return {}
    return {f"start_smoothing_s_{name}": float(value / fps)
            for name, value in (("min", widths.min()), ("median", np.median(widths)), ("max", widths.max()))}


def body_alone_acceleration_weight(weight: float, fps: float) -> float:
    """The body's acceleration weight in a body-only joint fit: `weight` at 10 fps and more; below, x (fps/10)^2,
    since a slow take's body moves more between frames, and the same weight would flatten its motion
    (BENCHMARKS.md, body-only joint fit)."""
    return weight * min(1.0, fps / 10.0) ** 2


class GlobalProblem:
    """What every chunk of the stage needs: the model, the per-frame results, the object's shape,
    the ground, free-flight episodes, the fitter and the observation loader."""

    def __init__(self, session, cfg, out_dir: Path):
        from intercap.stages.prepare.stage import load_ground

        g = cfg.global_
        torch.manual_seed(g.seed)
        stage_dir = out_dir / "global"
        self.model = shared_model(dataclasses.replace(cfg.body_model, name=session.body_model),
                                  device=cfg.run.device)
        self.cameras = Cameras.from_infos(session.cameras, device=cfg.run.device)
        with_object = object_left_out(session, out_dir) is None
        repair = (g.repair_factor, g.repair_floor_mm, g.repair_reach) if g.repair_factor > 0 else None
        smoothing_s = g.start_smoothing_s if with_object else g.start_smoothing_alone_s
        most_s, confidence = ((g.start_smoothing_most_s, g.start_smoothing_confidence) if with_object else
                              (g.start_smoothing_most_alone_s, g.start_smoothing_confidence_alone))
        adaptive = (most_s * session.fps, confidence) if most_s > smoothing_s else None
        self.per_frame = per_frame = load_per_frame(session, out_dir, self.model, with_object, repair,
                                                    g.shape_change_limit_mm, smoothing_s * session.fps,
                                                    g.shape_smoothing_s * session.fps, adaptive)
        ground = load_ground(out_dir) if (out_dir / "prepare" / "ground.json").exists() else None
        if ground is None:
            log.warning("global: no ground plane (run the `prepare` stage); E_G is off")
        self.shape = object_shape(session, g, out_dir) if with_object else None
        if with_object:
            if per_frame.hand_distance is None:
                per_frame.hand_distance = hand_object_distance(self.model, per_frame, self.shape)
            per_frame.grasping = grasping_hands(per_frame.contact, per_frame.hand_distance, g.hand_reach_m)
        weights = g if with_object else dataclasses.replace(g, w_body_acceleration=body_alone_acceleration_weight(
            g.w_body_acceleration_alone, session.fps))
        self.fitter = GlobalFitter(self.model, self.cameras, cfg.body, weights, self.shape, ground, session.fps)
        per_frame.acceleration_scale = acceleration_scale(
            self.model, per_frame.body if per_frame.motion is None else per_frame.motion, session.fps,
            self.fitter.body.subset, g.acceleration_reference_mps2,
            g.acceleration_max_scale if with_object else g.acceleration_max_scale_alone, g.acceleration_smoothing_s,
            smoothing_s, g.acceleration_reach_s) ** (1.0 if with_object else g.acceleration_power_alone)
        per_frame.acceleration_scale *= acceleration_across_gaps(per_frame.body_valid,
                                                                 g.acceleration_gap_s * session.fps)
        self.flight = flight = (free_flight(per_frame, self.shape, ground, session.fps, g) if with_object
                                else no_flight(session.num_frames))
        if flight["episodes"].size and g.w_flight > 0:
            self.fitter.gravity = torch.as_tensor(-9.81 * flight["up"], dtype=torch.float32, device=cfg.run.device)
        if flight["figures"].get("gravity_source") == "flight":  # no floor in view: up from the object's free flight
            write_json(stage_dir / "gravity.json", {"up": flight["figures"]["gravity_up"], "source": "flight",
                                                    "gravity_mps2": (-9.81 * flight["up"]).tolist(),
                                                    "episodes": flight["figures"]["flight_episodes"]})
        self.observations = Observations(session, cfg, out_dir, self.cameras, with_object)


def fit_chunk(session, cfg, out_dir: Path, problem: GlobalProblem | None, chunk: Chunk, queue) -> dict:
    """Fit frames [chunk.lo_context, chunk.hi_context) in overlapping windows, checkpointed after
    every window (OUT/global/progress_LO_HI.npz); returns rows [chunk.lo, chunk.hi) of the body
    parameters (numpy), object rotation `R` and `centre`, the windows' `history` and `seconds`."""
    from intercap.session.frame_cache import open_session

    session = open_session(session, out_dir)
    g = cfg.global_
    out_dir = Path(out_dir)
    problem = problem or GlobalProblem(session, cfg, out_dir)
    per_frame, shape = problem.per_frame, problem.shape
    lo, hi = chunk.lo_context, chunk.hi_context
    plan = [(a + lo, b + lo, fixed, commit + lo) for a, b, fixed, commit in
            windows(hi - lo, g.window_frames, g.window_overlap, g.window_history)]
    fitted = per_frame.body.clone()
    device = problem.model.faces.device  # the windows are fitted there
    R_all = torch.as_tensor(per_frame.R, dtype=torch.float32, device=device)
    centre_all = torch.as_tensor(per_frame.t, dtype=torch.float32, device=device)
    if shape is not None:
        centre_all = centre_all + R_all @ shape.centroid.to(R_all)
    checkpoint = Checkpoint.of_chunk(out_dir, "global", chunk)
    next_window, seconds, history = 0, 0.0, []
    saved = checkpoint.load()
    if saved is not None:
        fitted = BodyParams.from_numpy_dict(saved, dtype=problem.model.dtype, device=device)
        R_all, centre_all = torch.from_numpy(saved["R"]).to(device), torch.from_numpy(saved["centre"]).to(device)
        next_window, seconds = int(saved["next_window"]), float(saved["seconds"])
        log.info("global: frames %d-%d resuming at window %d of %d", chunk.lo, chunk.hi - 1, next_window + 1, len(plan))
    reported = chunk.lo
    for k in range(next_window, len(plan)):
        start, end, fixed, commit = plan[k]
        tick = time.perf_counter()
        frames = np.arange(start, end)
        data = problem.observations.window(frames, per_frame, shape)
        episode = problem.flight["episode_of_frame"][frames]
        data.flight = torch.as_tensor(episode, device=device) if (episode >= 0).any() else None
        body, R, centre, stats = problem.fitter.fit_window(fitted[start:end], R_all[start:end],
                                                           centre_all[start:end], fixed, data)
        keep = slice(fixed, commit - start)
        for name, value in body.tensors().items():
            getattr(fitted, name)[start + fixed:commit] = value[keep]
        R_all[start + fixed:commit], centre_all[start + fixed:commit] = R[keep], centre[keep]
        seconds += time.perf_counter() - tick
        history.append(stats)
        log.debug("global window %d: %s", k, stats)
        checkpoint.save(**fitted.to_numpy_dict(), R=R_all.cpu().numpy(), centre=centre_all.cpu().numpy(),
                        next_window=k + 1, seconds=seconds)
        finished = min(commit, chunk.hi)
        if finished > reported:
            queue.put(finished - reported)
            reported = finished
    rows = slice(chunk.lo, chunk.hi)
    return {"params": fitted.map(lambda t: t[rows]).to_numpy_dict(), "R": R_all[rows].cpu().numpy(),
            "centre": centre_all[rows].cpu().numpy(), "history": history, "seconds": seconds}


def write_outputs(session, model, fitted: BodyParams, R, centre, shape: ObjectShape | None,
                  per_frame: PerFrameResults, seconds: float, history: list, out_dir: Path,
                  observations: Observations, cameras, cfg, weight) -> dict:
    """OUT/global/ files, shown at OUT/; frames the per-frame stages could not fit are NaN. A body-only
    fit (`shape` None) writes no object poses: the object stage's, if any, stay shown."""
    T = session.num_frames
    stage_dir = out_dir / "global"
    valid = per_frame.body_valid
    vertices, keypoints = save_body_results(stage_dir, model, fitted, valid, session.frame_ids)
    ok = per_frame.object_valid
    R_out = np.where(ok[:, None, None], R.numpy(), np.nan).astype(np.float32)
    t_out = np.full((T, 3), np.nan, np.float32)
    if shape is not None:
        t_out = np.where(ok[:, None], (centre - (R @ shape.centroid)).numpy(), np.nan).astype(np.float32)
        save_npz(stage_dir / "object_poses.npz", R=R_out, t=t_out, valid=ok, confidence=per_frame.object_confidence,
                 frame_ids=session.frame_ids)
    for name in OUTPUT_FILES:
        if shape is not None or name != "object_poses.npz":
            publish(stage_dir / name, out_dir / name)

    for i in range(0, T, max(1, cfg.body.overlay_every)):
        fid = int(session.frame_ids[i])
        if valid[i]:
            draw_overlay(session, keypoints[i], fid, cameras, stage_dir / "overlays" / f"body_{fid:06d}.jpg")
        if ok[i]:
            from intercap.stages.object.stage import draw_overlay as draw_object

            draw_object(session, observations.tracker, fid, R_out[i], t_out[i],
                        stage_dir / "overlays" / f"object_{fid:06d}.jpg")
    figures = quality_figures(vertices, R_out, t_out, shape, per_frame, session.fps)
    totals = {}  # each term's weighted energy summed over windows, before and after the fit
    for stats in history:
        for when in ("before", "after"):
            for term, value in stats[when].items():
                totals.setdefault(f"energy_{when}", {}).setdefault(term, 0.0)
                totals[f"energy_{when}"][term] += weight(term) * value
    totals = {key: {term: float(f"{value:.4g}") for term, value in terms.items()} for key, terms in totals.items()}
    return {**figures, **totals, "windows": len(history), "seconds_per_frame_fit": seconds / max(T, 1),
            "evaluations": sum(h["evaluations"] for h in history), "steps": sum(h["steps"] for h in history)}


FIGURE_FRAMES = 256  # frames per step of `quality_figures`: a long take's (T, V, 3) temporaries stay bounded


def in_parts(frames: np.ndarray) -> list[np.ndarray]:
    """Frame indices (n,) -> consecutive parts of at most FIGURE_FRAMES."""
    return np.array_split(frames, -(-len(frames) // FIGURE_FRAMES))


def quality_figures(vertices: np.ndarray, R: np.ndarray, t: np.ndarray, shape: ObjectShape | None,
                    per_frame: PerFrameResults, fps: float) -> dict:
    """The stage's own checks (no ground truth): penetration on contact frames, jitter. Computed
    `FIGURE_FRAMES` frames at a time: over a whole long take at once, their temporaries would take
    gigabytes."""
    both = per_frame.body_valid & per_frame.object_valid & per_frame.contact & (shape is not None)
    figures = {"contact_frames": int(per_frame.contact.sum())}
    if both.any():
        depth = []  # (n,) deepest body vertex inside the object per frame, FIGURE_FRAMES frames at a time
        for part in in_parts(np.flatnonzero(both)):
            local = np.einsum("tvj,tjk->tvk", vertices[part] - t[part, None], R[part]).astype(np.float32)
            depth.append(np.maximum(-shape.signed_distance(torch.from_numpy(local)).numpy(), 0).max(1))
        depth = np.concatenate(depth)
        figures.update(penetration_mm_mean=float(1000 * depth.mean()), penetration_mm_max=float(1000 * depth.max()))
    fine = np.flatnonzero(per_frame.body_valid[2:] & per_frame.body_valid[1:-1] & per_frame.body_valid[:-2])
    if len(fine):  # frame fine[i] + 1 and both its neighbours fitted
        total = 0.0
        for part in in_parts(fine):
            acc = np.linalg.norm(vertices[part + 2] - 2 * vertices[part + 1] + vertices[part], axis=-1)
            total += float(acc.sum(dtype=np.float64))
        figures["jitter_mps2"] = total / (len(fine) * vertices.shape[1]) * fps**2
    return figures
