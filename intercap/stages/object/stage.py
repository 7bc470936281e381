"""Stage 3, `object`: per-frame 6-DoF object tracking by silhouette and depth rendering.

Per frame, the object's pose (6D rotation + translation) minimises E_O over all views
(`intercap.stages.object.terms`: l_segm * silhouette + l_depth * depth) with the differentiable
renderer of `intercap.geometry.rendering`, starting from a constant-velocity prediction
(`intercap.stages.object.fitter`). Masks come from the session, or are derived from depth round
the prediction (`intercap.stages.object.observations`).

The first pose comes from session.yaml when given, else from registering the mesh to the first
frame's object points (`ObjectTracker.initialise`: PCA and FPFH starts, ICP, the best one's
quarter turns; the lowest E_O after a short fit wins). Where a track starts, where the object first
moves (a grasp shows its sides) and where E_O stays high, every axis-aligned orientation of the mesh
(its symmetries left out) is fitted and scored by E_O (`check_orientation`): a box resting on a
table shows two or three sides, and its quarter turn can fit those nearly as well. Without person
masks, a search over a whole view leaves out the person drawn from the run's keypoints (a head is a
box-sized blob of depth foreground). A fit whose silhouette IoU (over pixels
not hidden by something in front) is low or whose E_O jumps above its recent level is searched
again: locally (quarter turns about the mesh's principal axes: a chair's seat and legs look alike
every 90 deg), then by registration. Frames whose best fit still disagrees with the observations,
or where no view sees the object, get NaN poses and confidence 0 (marked, never invented).

The take is tracked in chunks (`intercap.stages.chunks`), several side by side in one process
(`object.side_by_side`), each from registration; `join_seams` tracks on across their seams as one
process tracking the whole take would.

Writes OUT/object/object_poses.npz (R (T,3,3), t (T,3), confidence (T,), valid (T,),
frame_ids (T,)), shown as OUT/object_poses.npz until the `global` stage replaces that with its
own, OUT/object/progress_LO_HI.npz per chunk of frames and OUT/object/seam_LO_SEED.npz per seam
while running (resume), and OUT/object/overlays/*.jpg (rendered outline on the colour images) for
a person to check.
"""
from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import cv2
import numpy as np
import torch

from intercap.geometry.symmetry import symmetric_rotation_error_deg, unwrap_symmetry
from intercap.io.files import publish, save_npz
from intercap.stages.chunks import Checkpoint, Chunk, chunk_groups, fit_in_chunks
from intercap.stages.object.fitter import ObjectTracker, predict_pose, run_searches, spin_prediction, turned_too_fast
from intercap.stages.object.observations import hard_silhouettes

log = logging.getLogger(__name__)

TRACKED, REINITIALISED, LOST, UNTRUSTED = 1, 2, 3, 4
# why a frame's orientation was checked (`check_orientation`): 0 not checked
AT_START, AT_FIRST_MOVE, AT_HIGH_ENERGY = 1, 2, 3
CHECK_NAMES = {AT_START: "start", AT_FIRST_MOVE: "first_move", AT_HIGH_ENERGY: "high_energy"}
STATUS_NAMES = {0: "pending", TRACKED: "tracked", REINITIALISED: "reinitialised", LOST: "lost", UNTRUSTED: "untrusted"}
FEW_TRUSTED = 0.5  # the run warns when the object is trusted in fewer than this share of frames


def untracked(T: int, orientations: int) -> dict[str, np.ndarray]:
    """`track_steps`'s state of T frames not yet tracked (status 0, pending); `orientations`: how many
    the mesh has (`ObjectTracker.orientations`), each a column of the checks' energies."""
    return {"R": np.full((T, 3, 3), np.nan), "t": np.full((T, 3), np.nan), "confidence": np.zeros(T),
            "status": np.zeros(T, np.int64), "energy": np.full(T, np.nan), "confirmed": np.zeros(T, bool),
            "checked": np.zeros(T, np.int64), "orientation_energy": np.full((T, orientations), np.nan)}


def resumed(checkpoint: Checkpoint | None, T: int, orientations: int, queue) -> tuple[dict, int]:
    """`track_steps`'s state of T frames and the first frame to track: from `checkpoint` where it
    holds T frames' progress, else untracked from frame 0. The frames resumed are put on `queue`."""
    state, start = untracked(T, orientations), 0
    saved = checkpoint.load() if checkpoint is not None else None
    if saved is not None and len(saved["status"]) == T:
        state = {k: saved[k] if k in saved else state[k] for k in state}
        start = int(saved["next"])
        log.info("object: resuming at frame %d of %d", start, T)
        if queue is not None:
            queue.put(start)
    return state, start


def prediction(tracker: ObjectTracker, history: list, i: int, initial_pose):
    """(predicted pose or None, reach m) for frame i from the trusted poses before it (`history`):
    the constant-velocity prediction, `initial_pose` for the first frame, or, for up to
    `coast_frames` after the last trusted frame, that frame's pose; reach: how far the object may
    be from the prediction, its largest recent step per frame since the last trusted one."""
    cfg = tracker.cfg
    predicted, reach = predict_pose(history, cfg.predict_turn_share), 0.0
    if predicted is None and i == 0 and initial_pose is not None:
        predicted = initial_pose
    trusted_at = [k for k in range(max(0, i - cfg.coast_frames), i) if history[k] is not None]
    if trusted_at:
        k = trusted_at[-1]
        if predicted is None:
            predicted = history[k]  # coast: the object was seen recently, start where it was
        steps = [np.linalg.norm(tracker.to_centre(*history[j]) - tracker.to_centre(*history[j - 1]))
                 for j in trusted_at[-5:] if j > 0 and history[j - 1] is not None]
        reach = max(steps, default=0.0) * (i - k)
    return predicted, reach


def energy_level(state: dict, i: int, cfg) -> float:
    """E_O's recent level before frame i: the median over the last 5 frames with a fit (trusted or
    not: where the object's visible part changes for good, say a cup put down out of the hand, a
    few frames marked untrusted raise the level and tracking is trusted again); at least the E_O
    of a frame in the last 5 whose search found nothing better than the tracked pose (a hand now
    covers part of the object: a new level, not searched again)."""
    window = state["energy"][max(0, i - cfg.energy_window):i]
    recent = window[np.isfinite(window)][-5:]
    reference = float(np.median(recent)) if len(recent) > 2 else np.inf
    confirmed = state["energy"][max(0, i - 5):i][state["confirmed"][max(0, i - 5):i]]
    if len(confirmed):
        reference = max(reference, float(confirmed.max()))
    return reference


def search_frame(tracker: ObjectTracker, obs, frame_id: int, predicted, reach: float, good, state: dict, i: int):
    """Search: frame i's (observation, fit, status) from `predicted`; without one, registration
    (`initialise`, or with derived masks `locate`: the object's likely places, each registered). The
    fit from the prediction, recut round the fit where the mask was cut wide, then, while not `good`,
    `refit` and registration (`initialise`); a registration no better than `confirm_ratio` of the
    tracked E_O confirms it (`state["confirmed"][i]`). The observation is the one the fit used."""
    cfg = tracker.cfg
    if predicted is None:
        if tracker.use_masks:
            return obs, (yield from tracker.initialise(obs)), REINITIALISED
        # while the object stays lost: its likeliest place alone, every place each `recheck_frames`
        lost_before = i > 0 and state["status"][i - 1] not in (TRACKED, REINITIALISED)
        obs, fit = yield from tracker.locate(frame_id, 1 if lost_before and i % cfg.recheck_frames else None)
        return obs, fit, REINITIALISED
    (fit,), status = (yield [(obs, *predicted, None)]), TRACKED
    if reach > cfg.near_margin_m and not tracker.use_masks:
        # A mask cut this wide round the prediction takes in the hands and arms of a
        # fast lift: cut it again round the fit and refine there, if that agrees.
        tight_obs, tight = yield from tracker.recut(frame_id, fit)
        if good(tight):
            obs, fit = tight_obs, tight
    if not good(fit):
        local = yield from tracker.refit(obs, fit, predicted)
        if local.energy < fit.energy:
            fit = local
        if not good(fit):
            alternative = yield from tracker.initialise(obs, extra=[predicted, (fit.R, fit.t)])
            better = alternative is not None and alternative.energy <= cfg.confirm_ratio * fit.energy
            state["confirmed"][i] = not better
            if alternative is not None and alternative.energy < fit.energy:
                fit, status = alternative, REINITIALISED
    return obs, fit, status


def orientation_check_due(tracker: ObjectTracker, fit, history: list, state: dict, i: int) -> int:
    """Why frame i's orientation is to be checked (`AT_START`, `AT_FIRST_MOVE`, `AT_HIGH_ENERGY`), or 0:
    a track starts here (no trusted pose in the last `coast_frames`; while none is found, every
    `recheck_frames`); the object has moved
    `recheck_move_fraction` of its size from where the track's start check saw it, for the first
    time (a grasp shows its sides); or E_O has stayed above `recheck_energy_ratio` times its value at
    the last check for `recheck_frames` frames."""
    cfg = tracker.cfg
    if not cfg.check_orientations or fit is None:
        return 0
    checks = np.flatnonzero(state["checked"][:i])
    if not any(h is not None for h in history[max(0, i - cfg.coast_frames):i]):
        # (while the object stays lost, not every frame: once per `recheck_frames`)
        return AT_START if not len(checks) or i - checks[-1] >= cfg.recheck_frames else 0
    starts = checks[state["checked"][checks] == AT_START]
    if not len(starts):
        return 0
    k = int(checks[-1])
    if not (state["checked"][starts[-1]:i] == AT_FIRST_MOVE).any() and history[starts[-1]] is not None:
        moved = np.linalg.norm(tracker.to_centre(fit.R, fit.t) - tracker.to_centre(*history[starts[-1]]))
        if moved > cfg.recheck_move_fraction * tracker.extent:
            return AT_FIRST_MOVE
    recent = state["energy"][max(k + 1, i - cfg.recheck_frames + 1):i]
    if i - k >= cfg.recheck_frames and len(recent) == cfg.recheck_frames - 1 and np.all(
            np.concatenate([recent, [fit.energy]]) > cfg.recheck_energy_ratio * state["energy"][k]):
        return AT_HIGH_ENERGY
    return 0


def check_orientation(tracker: ObjectTracker, obs, fit, history: list, state: dict, i: int, frame_id: int):
    """Search, returns (fit, turned): frame i's fit, from `ObjectTracker.orientation_search` where a check
    is due (`orientation_check_due`; the best orientation wins at a track's start, elsewhere only
    where its E_O is below `confirm_ratio` of the fit's). Where E_O has stayed high, the object's points
    are registered again too (`ObjectTracker.initialise`, as where a track is lost): a long thin tool held
    across the body can slide along its own length while its ends are hidden, the constant-velocity
    prediction carrying the slide on, and no turn of it about its centre finds it again. turned: the
    pose changed."""
    why = orientation_check_due(tracker, fit, history, state, i)
    if not why:
        return fit, False
    best, energies = yield from tracker.orientation_search(obs, fit)
    state["checked"][i], state["orientation_energy"][i] = why, energies
    if why == AT_HIGH_ENERGY:  # a track can also have slid off: the object's points registered again
        found = yield from tracker.initialise(obs, extra=[(best.R, best.t)])
        if found is not None and found.energy < best.energy:
            best = found
    if best is fit or (why != AT_START and best.energy > tracker.cfg.confirm_ratio * fit.energy):
        return fit, False
    log.info("object: frame %d: orientation checked (%s): E_O %.4g -> %.4g", frame_id, CHECK_NAMES[why], fit.energy,
             best.energy)
    return best, True


def trusted_pose(tracker: ObjectTracker, fit, history: list, i: int, reference: float, good, turned: bool = False,
                 energies: np.ndarray | None = None):
    """Frame i's pose from `fit` where it is trusted (E_O within `trust_energy_ratio` of the level:
    a hand closing round the object raises E_O a little), turned like the last trusted pose
    (`hold_symmetric_turn`); None where it is not, or where it turned too fast (`turned_too_fast`)
    unless it fits clearly better than the frames before and than the last trusted one (a turn
    back; `energies`: the frames' E_O: a hand letting go of a tool raises the level with untrusted
    frames, and a registration turned half round must still beat the pose trusted before them) or
    an orientation check turned it (`turned`)."""
    cfg = tracker.cfg
    if not good(fit, cfg.trust_energy_ratio):
        return None
    pose = (fit.R, fit.t)
    last_at = next((j for j in range(i - 1, -1, -1) if history[j] is not None), None)
    if last_at is not None and cfg.hold_symmetric_turn:
        pose = tracker.turned_like(*pose, history[last_at][0])
    if (last_at is not None and not turned
            and turned_too_fast(pose[0], history[last_at][0], i - last_at, cfg.max_turn_deg_per_frame,
                                spin_prediction(history, cfg.max_turn_deg_per_frame))
            and fit.energy > cfg.fast_turn_energy_ratio * min(
                reference, np.inf if energies is None else float(energies[last_at]))):
        return None
    return pose


def track_frame(tracker: ObjectTracker, frame_ids: np.ndarray, i: int, history: list, state: dict, initial_pose):
    """Search: frame i's (fit or None, trusted pose or None, status). With derived masks, nothing
    near the prediction sends the search over the whole foreground before the frame is lost."""
    cfg = tracker.cfg
    frame_id = int(frame_ids[i])
    predicted, reach = prediction(tracker, history, i, initial_pose)
    obs = tracker.observe(frame_id, predicted, reach)
    if i + 1 < len(frame_ids):
        tracker.read_ahead(int(frame_ids[i + 1]))  # read while this frame is fitted
    if predicted is not None and not tracker.use_masks and obs.visible_views < cfg.min_views:
        # Nothing near where the object should be: look for it anywhere before calling it lost.
        predicted = None
        obs = tracker.observe(frame_id, None)
    reference = energy_level(state, i, cfg)

    def good(f, ratio: float = cfg.reinit_energy_ratio) -> bool:
        """Silhouettes agree and E_O is not far above its level in recent trusted frames."""
        return f is not None and f.confidence >= cfg.min_confidence and f.energy <= ratio * reference

    fit, status, turned = None, LOST, False
    if obs.visible_views >= cfg.min_views:
        obs, fit, status = yield from search_frame(tracker, obs, frame_id, predicted, reach, good, state, i)
        if fit is not None:
            fit, turned = yield from check_orientation(tracker, obs, fit, history, state, i, frame_id)
    return fit, trusted_pose(tracker, fit, history, i, reference, good, turned, state["energy"]), status


def track_steps(tracker: ObjectTracker, frame_ids: np.ndarray, checkpoint: Checkpoint | None = None,
                initial_pose=None, queue=None, until=None):
    """Search (see `run_searches`): track the object through `frame_ids`; resumes from
    `checkpoint` when it exists; with `until(i, state)`, stops after the first frame i where it
    holds (later frames stay pending, status 0).

    Per frame (`track_frame`): fit from the constant-velocity prediction (or, for up to
    `coast_frames` after the last trusted frame, from that frame's pose). A fit
    whose silhouette IoU is below `min_confidence` or whose E_O is above
    `reinit_energy_ratio` times its recent level is searched again, locally
    (`ObjectTracker.refit`) and, if that fails too, from registration
    hypotheses (`initialise`); the lowest E_O wins. Its pose is trusted
    when the IoU is enough, E_O at most `trust_energy_ratio` times the level and
    it turned no faster than `max_turn_deg_per_frame` from the last trusted pose or from the
    constant-velocity prediction (unless E_O is under `fast_turn_energy_ratio` times the level);
    other frames, and those where no view sees the object, are marked (NaN pose,
    confidence 0).

    Returns R (T,3,3), t (T,3) (NaN where untrusted), confidence (T,), status (T,),
    energy (T,) and confirmed (T,): a search found nothing better than the tracked
    pose, so its E_O is the new level (for the next 5 frames at least). With `queue`, each
    finished frame is put on it (`intercap.parallel`)."""
    cfg = tracker.cfg
    T = len(frame_ids)
    state, start = resumed(checkpoint, T, len(tracker.orientations()), queue)
    history = [None if state["status"][i] not in (TRACKED, REINITIALISED) else (state["R"][i], state["t"][i])
               for i in range(start)]
    for i in range(start, T):
        fit, pose, status = yield from track_frame(tracker, frame_ids, i, history, state, initial_pose)
        if fit is not None:
            state["energy"][i] = fit.energy
            state["confidence"][i] = fit.confidence if pose is not None else 0.0
        if pose is not None:
            state["R"][i], state["t"][i] = pose
            state["status"][i] = status
        else:
            state["status"][i] = UNTRUSTED if fit is not None else LOST
        history.append(pose)
        done = until is not None and until(i, state)
        if checkpoint is not None and ((i + 1) % cfg.checkpoint_every == 0 or i + 1 == T or done):
            checkpoint.save(next=i + 1, **state)
        if queue is not None:
            queue.put(1)
        if done:
            break
    return state


def join_seams(tracker: ObjectTracker, frame_ids: np.ndarray, state: dict, starts: list[int],
               stage_dir: Path) -> tuple[dict, int]:
    """Track on across the chunks' seams, as one process tracking the whole take would.

    A chunk after the first starts cold, from registration; where the object is in a hand and no
    mask separates them, that can lock onto the wrong thing for the whole chunk. Each chunk start
    `lo` (in `starts`) is tracked again from the frames before it until `seam_agree_frames` frames
    in a row match the chunk's own poses (`seam_agree_mm` of ADD-S and `seam_agree_deg` of rotation, both up
    to the mesh's symmetry: a box's cold start may find it turned by it; a cold start that was right costs
    those few frames); from there the
    chunk's poses stand. A seam whose frames before it changed is tracked again, until none does;
    the seams of a round side by side. Each keeps a checkpoint named by the frames it starts from
    (OUT/object/seam_LO_SEED.npz). Returns the state and the number of frames tracked again."""
    from scipy.spatial import cKDTree

    cfg = tracker.cfg
    before = max(cfg.energy_window, cfg.coast_frames, 5)  # what `track_steps` looks back on
    points = tracker.world_vertices_np(np.eye(3), np.zeros(3))
    points = points[np.linspace(0, len(points) - 1, min(len(points), 500)).astype(int)]

    symmetry = tracker.symmetry()[0]

    def matches(a: tuple, b: tuple) -> bool:  # ADD-S within seam_agree_mm, rotation within seam_agree_deg
        if symmetric_rotation_error_deg(a[0][None], b[0][None], symmetry)[0] > cfg.seam_agree_deg:
            return False
        posed_a, posed_b = points @ a[0].T + a[1], points @ b[0].T + b[1]
        return float(cKDTree(posed_a).query(posed_b)[0].mean()) <= cfg.seam_agree_mm / 1000

    ends = starts[1:] + [len(frame_ids)]
    chunk_state = {key: value.copy() for key, value in state.items()}
    seeded: dict[int, str] = {}
    retracked = 0
    while True:
        jobs = []
        for lo, hi in zip(starts, ends):
            a = max(0, lo - before)
            prefix = {key: state[key][a:lo] for key in sorted(state)}
            seed = hashlib.sha1(b"".join(np.ascontiguousarray(v).tobytes() for v in prefix.values())).hexdigest()[:12]
            if seeded.get(lo) == seed:
                continue
            seeded[lo] = seed
            checkpoint = Checkpoint(stage_dir / f"seam_{lo:06d}_{seed}.npz")
            for stale in stage_dir.glob(f"seam_{lo:06d}_*.npz"):
                if stale != checkpoint.path:
                    stale.unlink()
            if not checkpoint.exists():
                pending = untracked(hi - lo, len(tracker.orientations()))
                checkpoint.save(next=lo - a, **{key: np.concatenate([prefix[key], pending[key]]) for key in prefix})

            def agrees(i: int, sub: dict, a=a, lo=lo) -> bool:
                if i - (lo - a) + 1 < cfg.seam_agree_frames:
                    return False
                rows = range(a + i - cfg.seam_agree_frames + 1, a + i + 1)
                trusted = (TRACKED, REINITIALISED)
                return all(sub["status"][r - a] in trusted and chunk_state["status"][r] in trusted
                           and matches((sub["R"][r - a], sub["t"][r - a]), (chunk_state["R"][r], chunk_state["t"][r]))
                           for r in rows)

            jobs.append((lo, hi, a, track_steps(tracker, frame_ids[a:hi], checkpoint, None, None, agrees)))
        if not jobs:
            return state, retracked
        log.info("object: tracking on across the seam(s) at frame(s) %s",
                 ", ".join(str(int(frame_ids[job[0]])) for job in jobs))
        for (lo, hi, a, _), sub in zip(jobs, run_searches(tracker, [job[3] for job in jobs])):
            tracked = lo + int(np.flatnonzero(sub["status"][lo - a:] != 0).max(initial=-1)) + 1
            log.info("object: tracked on across the seam at frame %d: %d frames (%s)", int(frame_ids[lo]),
                     tracked - lo, "then the chunk's own poses" if tracked < hi else "the whole chunk")
            retracked += tracked - lo
            for key in state:
                state[key][lo:tracked] = sub[key][lo - a:tracked - a]
                state[key][tracked:hi] = chunk_state[key][tracked:hi]


def run_tracker(session, cfg, out_dir: Path) -> ObjectTracker:
    """The run's tracker: the session's object, with the run's keypoints (the session's or the
    `detect` stage's, where it ran) to keep the person out of its searches."""
    from intercap.stages.body.observations import KeypointSource

    tracker = ObjectTracker(session, cfg.object, session.object.load_mesh(), device=cfg.run.device)
    try:
        tracker.keypoints = KeypointSource(session, out_dir)
    except RuntimeError:  # no keypoints yet (the object stage run alone): searches see the person too
        tracker.keypoints = None
    return tracker


def track_chunks(session, cfg, out_dir: Path, chunks: tuple[Chunk, ...], queue) -> list[dict[str, np.ndarray]]:
    """`track_steps` over each chunk's frames [lo, hi), the chunks side by side (`run_searches`),
    in a worker (`intercap.parallel`): a chunk after the first starts without a prediction, from
    registration, as a lost object is found again. Each chunk keeps its own checkpoint
    (OUT/object/progress_LO_HI.npz)."""
    from intercap.session.frame_cache import open_session

    session = open_session(session, out_dir)
    torch.manual_seed(cfg.object.seed)
    tracker = run_tracker(session, cfg, out_dir)
    searches = [track_steps(tracker, session.frame_ids[c.lo:c.hi], Checkpoint.of_chunk(out_dir, "object", c),
                            session.object.initial_pose if c.lo == 0 else None, queue) for c in chunks]
    return run_searches(tracker, searches)


def stitched(session, cfg, stage_dir: Path, starts: list[int]):
    """`fit_in_chunks`'s stitch: the chunks' states end to end, tracked on across the seams at
    `starts` (`join_seams`); returns (the tracker, the state, the frames tracked again)."""

    def stitch(results: list) -> tuple[ObjectTracker, dict, int]:
        parts = [part for group in results for part in group]
        state = {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}
        tracker = run_tracker(session, cfg, stage_dir.parent)
        state, retracked = join_seams(tracker, session.frame_ids, state, starts, stage_dir) if starts else (state, 0)
        return tracker, state, retracked

    return stitch


def draw_overlay(session, tracker: ObjectTracker, frame_id: int, R, t, path: Path) -> None:
    """Colour views side by side with the tracked object's outline drawn on them."""
    sils = (hard_silhouettes(tracker.world_vertices_np(R, t), tracker.faces, tracker.cameras, tracker.sizes)
            if np.isfinite(R).all() else None)
    tiles = []
    for c, (H, W) in enumerate(tracker.sizes):
        color = session.read_color(c, frame_id)
        img = np.zeros((H, W, 3), np.uint8) if color is None else cv2.cvtColor(color, cv2.COLOR_RGB2BGR)
        if sils is not None:
            contours, _ = cv2.findContours(sils[c].astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(img, contours, -1, (0, 255, 0), 1)
        tiles.append(cv2.resize(img, (W * 240 // H, 240)))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(tiles, axis=1), [cv2.IMWRITE_JPEG_QUALITY, 85])


def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `object` stage: writes OUT/object_poses.npz and OUT/object/."""
    if session.object is None:
        log.info("object: the session has no object; nothing to track")
        return {"skipped": "no object in session"}
    ocfg = cfg.object
    stage_dir = Path(out_dir) / "object"
    stage_dir.mkdir(parents=True, exist_ok=True)
    groups = chunk_groups(session.num_frames, cfg, ocfg)
    starts = [chunk.lo for group in groups for chunk in group][1:]
    tracker, state, retracked = fit_in_chunks(track_chunks, stitched(session, cfg, stage_dir, starts), session, cfg,
                                              out_dir, groups, "object", progress)
    valid = np.isin(state["status"], (TRACKED, REINITIALISED))
    if ocfg.hold_symmetric_turn:  # across the seams too: each chunk began with its own turn
        state["R"], state["t"] = unwrap_symmetry(state["R"], state["t"], valid, *tracker.symmetry())
    save_npz(stage_dir / "object_poses.npz", R=state["R"], t=state["t"], confidence=state["confidence"],
             valid=valid, status=state["status"], frame_ids=session.frame_ids)
    publish(stage_dir / "object_poses.npz", Path(out_dir) / "object_poses.npz")
    for i in range(0, session.num_frames, max(1, ocfg.overlay_every)):
        draw_overlay(session, tracker, int(session.frame_ids[i]), state["R"][i], state["t"][i],
                     stage_dir / "overlays" / f"{int(session.frame_ids[i]):06d}.jpg")
    return outputs(session, tracker, state, valid, len(starts), retracked)


def outputs(session, tracker: ObjectTracker, state: dict, valid: np.ndarray, seams: int, retracked: int) -> dict:
    """The stage's metrics (masks used, frames by status, mean confidence, seams), with a warning
    where the object was trusted in few frames."""
    counts = {STATUS_NAMES[s]: int((state["status"] == s).sum()) for s in (TRACKED, REINITIALISED, LOST, UNTRUSTED)}
    images = session.num_cameras * session.num_frames
    derived = int(session.missing("mask_object").sum()) if tracker.session_masks else images
    if valid.mean() < FEW_TRUSTED:
        log.warning("object: the object was trusted in %s%s", f"only {int(valid.sum())} of {len(valid)} frames"
                    if valid.any() else "no frame", (
                        ": its masks were derived from depth, where an object that stays in place (or a person"
                        " who does, holding it) is part of the background, and one lying flat (a board on the"
                        " floor) hardly stands out of it; give the session object masks" if derived else
                        ": check its masks and object.ply (OUT/object/overlays/)"))
    return {
        "masks": "session" if derived == 0 else ("derived" if derived == images else "session+derived"),
        "masks_derived_images": derived,
        "frames_trusted": int(valid.sum()),
        **{f"frames_{k}": v for k, v in counts.items()},
        "mean_confidence": float(state["confidence"][valid].mean()) if valid.any() else 0.0,
        "seams": seams,
        "seam_frames_tracked_again": retracked,
        **orientation_figures(session, state),
    }


def orientation_figures(session, state: dict) -> dict:
    """The orientation checks (`check_orientation`) for metrics and the report: how many, and per check its
    frame, why, and each orientation's E_O after its short fit, lowest first (None: not fitted)."""
    checks = []
    for i in map(int, np.flatnonzero(state["checked"])):
        energies = np.sort(state["orientation_energy"][i])
        checks.append({"frame": int(session.frame_ids[i]), "why": CHECK_NAMES[int(state["checked"][i])],
                       "energies": [round(float(e), 5) if np.isfinite(e) else None for e in energies]})
    return {"orientation_checks": len(checks), "orientation_hypotheses": checks}
