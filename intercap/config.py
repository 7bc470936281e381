"""One configuration tree for the whole pipeline.

Defaults live in the dataclasses below; a YAML file and ``section.key=value``
overrides from the command line change them; every results folder gets the
tree it was produced with (``OUT/config.yaml``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml


@dataclass
class BodyModelConfig:
    """Which body model, and where its files and caches are."""

    name: str = "anny"  # "anny" (default, ships with its package) or "smplx"
    cache_dir: str | None = None  # anny's cache folder; None: $ANNY_CACHE_DIR or ~/.cache/anny
    smplx_model_dir: str | None = None  # folder holding SMPLX_NEUTRAL.npz etc.
    dtype: str = "float32"


@dataclass
class PrepareConfig:
    """Point clouds, ground plane and the calibration check."""

    depth_min_m: float = 0.2
    depth_max_m: float = 8.0
    pixel_stride: int = 2  # back-project every n-th pixel for the fused clouds
    voxel_size_m: float = 0.01  # fused-cloud downsampling
    plane_distance_m: float = 0.015  # RANSAC inlier band for the ground plane
    plane_iterations: int = 2000
    ground_frames: int = 5  # frames (spread over the sequence) fused for the ground fit
    calib_frames: int = 3  # frames (spread over the sequence) used for the ICP check
    icp_max_distance_m: float = 0.10
    calib_warn_mm: float = 6.0  # a pair is flagged when its observable correction exceeds this (or calib_warn_deg)
    calib_warn_deg: float = 0.3
    calib_k_sigma: float = 4.0  # ... and also calib_k_sigma standard deviations of itself (clear evidence only)
    calib_min_blocks: int = 100  # ... over an overlap of >= this many (frame, 25 cm block) clusters (else not judged)
    calib_refine: str = "auto"  # correct the cameras' poses from the depth: auto (when the check flags a pair), always, never
    calib_refine_frames: int = 8  # frames (spread over the sequence) the refinement aligns
    calib_refine_iterations: int = 10
    calib_refine_prior: float = 1e-3  # pull of each camera's correction towards none (x the data's largest curvature)
    calib_refine_linear_beyond_m: float = 0.006  # ... on its square up to this length, on its length beyond (a bumped camera may move far)
    save_clouds: bool = True  # write one fused .ply per checked frame for inspection
    seed: int = 0


@dataclass
class DetectConfig:
    """2D whole-body keypoints: the session's OpenPose JSON, or our own detector."""

    use_session_keypoints: bool = True  # False: detect even when the session has keypoints
    detector: str = "mediapipe"  # see intercap.detect.available_detectors()
    person_crop: bool = True  # detect again on a square crop around the person, resized to crop_size_px
    crop_size_px: int = 512  # side of the resized crop
    crop_margin: float = 0.3  # the crop grows this fraction of the keypoints' box beyond it on each side
    rescue_margins: list[float] = field(default_factory=lambda: [1.0, 1.5])  # tried in turn around the
    # previous frame's box when the full image has no person (a loose crop finds a bent-over person more often)


@dataclass
class ObjectConfig:
    """Per-frame object tracking by silhouette + depth rendering (E_O)."""

    use_session_masks: bool = True  # False: derive masks from depth even when the session has them
    crop_size: int = 64  # render grid (pixels) of the crop around the object in each view
    crop_margin: float = 0.25  # crop grows this fraction beyond the object and its mask
    sigma_px: float = 0.7  # silhouette edge softness (render-grid pixels)
    w_silhouette: float = 1.0  # l_segm
    w_depth: float = 1.0  # l_depth
    depth_scale_m: float = 0.03  # Geman-McClure scale of depth residuals
    occluder_margin_m: float = 0.03  # measured this much in front of the object = occluded there
    iterations: int = 60  # at most, per frame (early stopping ends most fits at 30 fps in 10-20)
    side_by_side: int = 1  # chunks of the take one process tracks at once, their fits in one render per step
    side_by_side_gpu: int = 8  # on CUDA (`side_by_side`: a GPU's step costs its kernel launches, not its size)
    cuda_graphs: bool = True  # on CUDA a fit's renders keep fixed shapes and each step replays one recorded graph
    read_ahead: bool = True  # on CUDA, with session masks: the next frame is read while this one is fitted
    stop_tolerance: float = 1e-3  # relative E_O decrease that counts as progress
    stop_patience: int = 3  # steps without progress before the step size shrinks (or the fit stops)
    stop_patience_dense: int = 2  # stop_patience at run.dense_fps and above (30 fps: 14 % fewer renders, same ADD-S;
    # at 5 fps 2 cost ADD-S 9 %: BENCHMARKS.md)
    init_iterations: int = 15  # per hypothesis, before the best is refined
    init_global_tries: int = 2  # FPFH RANSAC registrations among the hypotheses
    init_ransac_iterations: int = 5000
    init_keep: int = 6  # registration hypotheses (best ICP fitness) scored by E_O
    init_refine: int = 8  # of those (and the prediction), the lowest-E_O ones that get a short fit
    lr_rotation: float = 0.02
    lr_translation: float = 0.004
    lr_decay: float = 0.3  # step sizes shrink by this when E_O stalls ...
    lr_decays: int = 1  # ... this many times before the fit stops
    voxel_size_m: float = 0.005
    voxel_fraction: float = 0.0125  # registration voxel at least this fraction of the object's extent
    init_max_points: int = 1500  # observed points registered (evenly thinned beyond this)
    min_mask_px: int = 30
    min_views: int = 1  # views that must see the object for a pose
    min_confidence: float = 0.5  # mean silhouette IoU below this = not trusted
    reinit_energy_ratio: float = 1.5  # E_O above this times its recent median: search for a better pose
    trust_energy_ratio: float = 2.0  # E_O still above this times that median after the search: untrusted
    energy_window: int = 30  # frames whose E_O (the last 5 with a fit) set that median
    confirm_ratio: float = 0.9  # a search ending above this times the tracked E_O confirms it as the new level
    coast_frames: int = 15  # after losing track, fit from the last trusted pose for this many frames
    # a symmetric object's pose keeps its last trusted turn about its symmetry (else a spin, invisible
    # to E_O, lives on in the constant-velocity prediction: a cup turned 67-178 degrees per frame)
    hold_symmetric_turn: bool = True
    # a fit turned more than this per frame since the last trusted one is untrusted (0: no limit;
    # a real object rarely turns 45 degrees in 33 ms: a spinning toss at 2 turns/s turns 24) ...
    max_turn_deg_per_frame: float = 45.0
    fast_turn_energy_ratio: float = 0.8  # ... unless its E_O is below this times the recent level (turned back: a recovery)
    background_frames: int = 30
    background_valid_fraction: float = 0.3  # pixels measured in fewer of those frames have no background (dark floors lose ~40%)
    bridge_fraction: float = 0.006  # derived masks: join object fragments this far apart (fraction of image width)
    near_margin_m: float = 0.05  # derived masks: object pixels lie within this of the predicted bounding sphere
    checkpoint_every: int = 10
    overlay_every: int = 10
    seam_agree_frames: int = 3  # a chunk's own poses stand once this many frames tracked on across its seam match them
    seam_agree_mm: float = 10.0  # match: the posed surfaces this close (ADD-S: a symmetric object's look-alike pose matches)
    seed: int = 0


@dataclass
class BodyConfig:
    """Per-frame whole-body fitting (multi-view PROX-D): E_J + E_D + priors, L-BFGS in phases."""

    use_session_masks: bool = True  # False: derive person masks from depth even when the session has them
    batch_frames: int = 16  # frames fitted as one batch (warm-started from the previous batch); 8: ~0.3 mm better, 1.4x slower
    # on CUDA kernel launches, not arithmetic, bound an L-BFGS step, so a larger batch costs about the same per step
    # (H200, the sample: 2.14 -> 1.17 s/frame at 30 frames, surface 6.0 -> 6.4 mm)
    batch_frames_gpu: int = 32
    side_by_side: int = 1  # chunks of the take one process fits at once, their batches in one evaluation (`fit_chunks`;
    # 2 on a 600-frame take: body 10 % faster, same accuracy; a short take pays a cold start per extra chunk)
    side_by_side_gpu: int = 8  # on CUDA: a GPU's step costs its kernel launches, so K chunks cost about what one does
    # (150 frames, 3 chunks of 32-frame batches: 2.4x fewer kernels per frame, surface 5.8 -> 5.6 mm; BENCHMARKS.md)
    min_keypoint_confidence: float = 0.2  # detections below this are ignored
    keypoint_view_check_px: float = 30.0  # a detection this far (at 640 px width) from the other views' point is dropped; 0: off
    min_body_keypoints: int = 6  # a view counts for a frame when it has this many confident body keypoints
    min_points: int = 100  # a view's depth counts when its person mask gives this many points
    points_per_view: int = 400  # segmented depth points per view used by E_D
    person_erode_px: int = 2  # drop mask border pixels (mixed depth) at 640 px width, scaled with it
    # A person who stays in place all take is in the depth background too: when under this share of a
    # view's confident body keypoints lie on the depth foreground, the mask is the keypoint box's pixels
    # within `still_person_band_m` of the keypoints' depths and above the floor (`PersonPoints.still_mask`).
    still_person_keypoints: float = 0.5
    still_person_band_m: float = 0.2
    keypoint_rho: float = 100.0  # Geman-McClure scale of E_J, pixels at a 1000 px focal length (final phase)
    keypoint_rho_start: float = 400.0  # the same in the first phases: far-off starts are not outliers
    hand_keypoint_weight: float = 1.0  # per-joint weight of the 2 x 21 hand keypoints (body: 1)
    depth_scale_m: float = 0.05  # Geman-McClure scale of E_D
    depth_model_to_data: float = 1.0  # weight of E_D's model-to-data half (each visible vertex to its nearest point)
    depth_model_to_data_max_m: float = 0.10  # a visible vertex with no point this near has none (hidden by the object)
    visibility_margin_m: float = 0.03  # a vertex is visible when at most this behind the nearest surface
    visibility_cells: int = 100  # z-buffer cells across the image width for the visibility test
    w_keypoints: float = 1.0
    w_depth: float = 3.0e5
    one_view_depth_factor: float = 3.3  # E_D x this on frames fewer than two views see (nothing triangulates: depth decides)
    w_pose_prior: float = 10.0  # learned Gaussian mixture (CMU)
    w_joint_limits: float = 1.0e4
    w_bending: float = 1.0e3
    w_ground: float = 1.0e6  # E_G: fitting vertices below the ground plane (prepare's), per vertex, as the global stage's
    w_ground_support: float = 1.0e5  # the body's lowest points onto the floor where fewer than two views see the feet
    w_hand_prior: float = 1.0e3
    w_shape: float = 100.0
    shared_shape: bool = True  # one phenotype per batch whose frames all have >= 2 keypoint views (one person; 10-20 %
    # faster); with fewer views each frame its own: one view's stooping frames would bend the upright ones' shape
    shape_batches: int = 2  # the phenotype is fitted on the first batches this many (a process's chunks together),
    # then held at their mean (one person): re-fitted on every batch it drifted from batch to batch (its prior is
    # weak), so the global stage's sequence mean fitted no batch's poses (150 frames in one chunk of 32-frame batches:
    # surface 22 -> 6.2 mm; 1 batch: 6.0 mm there but penetration +18 % on the held-out session; BENCHMARKS.md);
    # 0: every batch
    size_from_depth: bool = True  # template's stature from the 3D torso keypoints (children, tall people; one view)
    w_expression: float = 10.0
    w_penetration: float = 1.0e5
    fit_expression: bool = False  # anny has no face landmarks in our keypoint set: expression stays neutral
    orient_steps: int = 5  # L-BFGS steps of the phase that moves only orientation + translation
    pose_steps: int = 15  # + body pose and shape, keypoints only
    pose_steps_dense: int = 10  # pose_steps at run.dense_fps and above, where a batch's frames lie near the previous
    # batch's last fit (30 fps: body 16 % faster, surface +0.4 %; at 5 fps 10 steps cost 3 %: BENCHMARKS.md)
    full_steps: int = 20  # + hands, with the depth term and self-penetration (10: stoops stay 2x off, BENCHMARKS.md)
    inner_iterations: int = 8  # L-BFGS iterations per step (E_D correspondences are refreshed between steps)
    ftol: float = 1e-5
    line_search: str = "auto"  # of the phases fitting one shape over the batch: as global.line_search
    max_line_search: int = 4  # Armijo's trials per L-BFGS iteration there
    cuda_graphs: bool = True  # on CUDA each phase's evaluations replay one recorded graph (`optim.gradient_evaluator`)
    per_frame_lbfgs: bool = True  # each frame its own L-BFGS (`minimise_per_frame`) where the frames do not interact;
    # false: one L-BFGS over the batch's summed energy (150 frames, 32-frame batches: surface 6.2 against 5.8 mm)
    # tracking: a frame whose person points lie far from its fit (median distance, mm), or, seen with
    # keypoints by fewer than two views, whose pose the learned prior finds far less likely than recent
    # frames' (contorted to reach the evidence), is refitted from the evidence (the upright template at
    # four headings, stooped at two) instead of from the previous batch's pose; of the fits on their
    # points the one of lowest energy is kept, and later batches start from the last fit on its points
    track_floor_mm: float = 40.0  # fit-to-data: never a failure below this
    track_factor: float = 2.5  # fit-to-data: a failure above this many times its running median
    track_prior_factor: float = 1.5  # pose prior (frames < 2 keypoint views): a failure above this x its running median
    track_window: int = 30  # frames in those running medians
    overlay_every: int = 10
    seed: int = 0


@dataclass
class GlobalConfig:
    """The joint body-object stage over all frames (InterCap's global L-BFGS), in overlapping windows.

    E_B reuses the body stage's terms and weights (section `body`); the weights
    here are those of the terms the global stage adds."""

    window_frames: int = 48  # frames optimised together; memory grows with it, the share fitted twice shrinks
    window_frames_gpu: int = 300  # on CUDA, where a step costs its kernel launches: the step budget is per window, so
    # kernels per frame fall with its length at the same accuracy (48 -> 144 -> 300 on the CPU: 150 frames in 1
    # window, not 4; 600 frames 333 evaluations, not 556; BENCHMARKS.md); memory grows with it (437 MB at 144, H100)
    window_overlap: int = 8  # frames a window shares with the next (re-optimised with more future)
    window_history: int = 2  # of the shared frames, those held fixed at the previous window's result
    steps: int = 15  # L-BFGS steps per window
    steps_dense: int = 12  # steps at run.dense_fps and above, where the per-frame fits start it closer (30 fps: 19 %
    # faster, MPJPE +4 %, penetration +5 %; at 5 fps 12 steps cost penetration 9 %: BENCHMARKS.md)
    inner_iterations: int = 8
    ftol: float = 1.0e-6
    line_search: str = "auto"  # "strong_wolfe" (torch's), "armijo" (one host read per trial), auto: Armijo on CUDA
    # (`optim.minimise`; the same accuracy on the CPU bench, BENCHMARKS.md)
    max_line_search: int = 4  # Armijo's trials per L-BFGS iteration
    cuda_graphs: bool = True  # on CUDA a window's evaluations replay one recorded graph (`optim.gradient_evaluator`)
    correspondence_every: int = 5  # E_D / E_O data association refreshed every this many steps
    object_points_per_view: int = 300  # object depth points per view for E_O
    object_depth_scale_m: float = 0.02  # Geman-McClure scale of E_O's point-to-surface distance
    sdf_resolution: int = 64  # object signed-distance grid: at least this many cells along its longest side,
    sdf_cell_m: float = 0.005  # none wider than this (thin parts: a chair's 2 cm back panel; BENCHMARKS.md stop 39)
    sdf_margin_m: float = 0.10  # and reaching at most this far beyond the object's box
    contact_vertices: int = 20  # E_C: the nearest this many vertices of a touching region
    hand_reach_m: float = 0.10  # a hand nearer than this to the object in a contact frame is grasping
    # A tracked object pose with more than this share of its surface samples 2 cm or more inside the
    # per-frame body was fitted to the person's own points (no masks): it is not trusted here. Right poses
    # stayed at or under 0.03 on eight sessions, wrong ones (a turn, no masks) had a median of 0.29.
    object_inside_body_share: float = 0.1
    # The acceleration terms and priors assume session.yaml's fps is the rate of the frames given. When
    # the joint fit raises the keypoints' energy more than this many times, the data and the motion terms
    # disagree, as when a take's frames were thinned (every 5th of 30 fps) but it still says 30 fps (x6.2,
    # body 11 -> 49 mm; x1.0-1.6 on six right takes): a warning says so. 0 turns it off.
    max_keypoint_energy_ratio: float = 3.0
    # Cameras that take their frames at other times than the rest (no wired sync: up to half a period)
    # show the person where the fitted motion puts them then; calib.time_offsets reads each camera's lag
    # from its keypoints (against the cameras' median, on `time_check_frames` frames) and a warning names
    # those past this many ms (a lone camera 16.7 ms late reads ~13; synchronised ones within 0.5). 0: off.
    max_camera_offset_ms: float = 4.0
    time_check_frames: int = 300
    w_object: float = 3.0e7  # E_O (mean over a frame's points, metres^2)
    w_object_anchor: float = 1.0e8  # the tracked (rendered silhouette + depth) pose x its confidence: measured more exact than E_O alone
    w_interpenetration: float = 3.0e6  # E_P (sum over body vertices)
    w_contact: float = 5.0e7  # E_C (mean over the patch; a hand's keypoints resist ~1e7 per m^2)
    w_hand_contact: float = 1.0e7  # E_C'
    w_ground: float = 1.0e6  # E_G: per vertex; stiff, since keypoints of all views move together
    w_object_acceleration: float = 30.0  # E_A, (m/s^2)^2 per frame
    w_body_acceleration: float = 10.0  # acceleration of body vertices, (m/s^2)^2 per frame (30 oversmooths: BENCHMARKS.md)
    w_body_motion_prior: float = 0.0  # E_S, learned (LEMO-style); 100 helped drink, hurt pick (BENCHMARKS.md)
    w_hand_motion_prior: float = 0.0  # E_L + E_R, learned; 20 with E_S above
    w_flight: float = 1.0e9  # GraviCap: object centre onto the gravity parabola in free flight (m^2 per frame); 0 = off
    flight_min_frames: int = 8  # free flight: at least this many frames touching neither body nor ground
    flight_ground_margin_m: float = 0.02  # the object touches the ground when its surface comes this close
    flight_max_residual_m: float = 0.05  # and its path is no flight when a parabola under gravity misses it by more (RMS)
    seed: int = 0


@dataclass
class ContactConfig:
    """Which frames have body-object contact: annotated ranges, or detected (2D mask overlap, 3D distance)."""

    method: str = "auto"  # "auto": the session's contact_frames when given, else `detector`; or "annotated", "2d", "3d"
    detector: str = "3d"  # what "auto" uses without annotations (the better one on tools/bench_contact.py)
    regions: list[str] = field(default_factory=lambda: ["left_hand", "right_hand"])  # body regions whose touch counts
    distance_m: float = 0.01  # T_d: a region this close to the object's surface touches it (3D)
    use_session_masks: bool = True  # 2D: the session's masks; False (or none given): silhouettes of the per-frame fits
    dilate_px: int = 1  # 2D: masks grow by this (at 640 px image width, scaled with it) before overlapping
    overlap_px: int = 20  # T_view: overlapping pixels (at 640 px width, scaled with image area) for a view to count
    overlap_views: int = 3  # T_frame: a frame is in contact when more than this many views count (3: all of 4)
    region_margin_m: float = 0.05  # annotated / 2D contact frames: regions this close also touch (besides the nearest)
    clean_frames: int = 0  # detected labels: fill gaps and drop runs shorter than this many frames; 0 = off
    # detected labels: an object that touches nothing and the floor but does not fall is held (`held_frames`;
    # the global stage's flight_* settings decide a fall), by the regions that held it next to the run
    held: bool = True
    held_rest_m: float = 0.015  # ... until it comes to rest: its centre this near where it lies at the run's end


@dataclass
class PhysicsConfig:
    """Forces, torques and free flight from the 4D result (the `physics` stage)."""

    mu: float = 0.5  # friction coefficient of the floor (sole and object contacts)
    friction_edges: int = 4  # edges of the linearised friction cone (pyramid)
    body_density_kg_m3: float = 1010.0  # body mass = rest mesh volume x this, unless session.yaml gives body.mass_kg
    sex: str = "auto"  # segment table: auto (blend by the fitted phenotype), male, female
    filter: str = "adaptive"  # adaptive (Savitzky-Golay, window per trajectory), savgol, butterworth, none
    filter_window_s: float = 0.3  # the `savgol` filter's window
    filter_order: int = 3  # Savitzky-Golay polynomial order
    cutoff_hz: float = 6.0  # Butterworth cut-off
    foot_contact_m: float = 0.03  # a sole point this near the floor can push on it
    object_ground_m: float = 0.02  # an object point this near the floor can push on it
    object_weight: float = 10.0  # weight of the object's wrench equations against the body's
    flight_min_frames: int = 8  # shortest free flight (object touching neither body nor floor)
    flight_max_residual_m: float = 0.05  # and a parabola under gravity within this of its path (RMS)


@dataclass
class ExportConfig:
    """Meshes and one dataset file from the results (the `export` stage)."""

    meshes: bool = True  # OUT/meshes/body_<frame>.ply and object_<frame>.ply
    scene: bool = False  # also OUT/meshes/scene_<frame>.ply: body + object, contact vertices red
    contact_distance_m: float = 0.02  # scene: vertices this near the other surface in contact frames are red
    vertices_float16: bool = False  # body_vertices in the dataset file as float16 (half the size; steps of 1 mm at 1-2 m, 2 mm at 2-4 m)
    behave: bool = False  # also OUT/export/behave/ in BEHAVE's layout and conventions
    behave_frame: str = "world"  # BEHAVE files in our world frame, or in this camera's frame (BEHAVE uses its k1)


@dataclass
class ReportConfig:
    """Mesh overlays and the HTML report written at the end of `intercap run`."""

    enabled: bool = True  # `intercap run` writes OUT/report/index.html after the stages
    overlay_stages: list[str] = field(default_factory=lambda: ["object", "body", "global"])
    overlay_every: int = 10  # mesh overlays of every n-th frame, in every view
    alpha: float = 0.6  # opacity of the rendered meshes over the colour images
    video: bool = True  # a video of one camera over the whole sequence (the last stage that ran)
    video_camera: str = ""  # camera name for the video; "" = the first camera
    video_codec: str = "vp9"  # vp9 (WebM: plays in every browser) or h264 (MP4: needs a browser with proprietary codecs)
    thumbnail_width: int = 200  # pixels; thumbnails are embedded, the full images sit beside the page
    heatmap_distance_m: float = 0.02  # contact heat map: a vertex this close to the object touches it
    points_per_view: int = 300  # depth points per view for the cloud-to-fit curves
    max_frames: int = 600  # geometric per-frame curves use at most this many frames, evenly spread


@dataclass
class RunConfig:
    """What `intercap run` does."""

    stages: list[str] = field(default_factory=list)  # empty: every built stage
    device: str = "cpu"
    force: bool = False  # recompute stages whose output is already saved
    workers: int = 0  # processes the fitting stages cut a take into (0: one per CPU core; on a GPU, one; N > 1 share it)
    min_frames_per_worker: int = 48  # a take shorter than twice this runs in one process
    dense_fps: float = 20.0  # sessions at this frame rate and above take the fits' *_dense budgets (`for_frame_rate`)
    deterministic: bool = True  # on the CPU the same numbers every run (`parallel.repeatable`)
    frame_cache: bool = True  # decode depth and masks once a run into OUT/cache/frames/ (`session.frame_cache`)


@dataclass
class Config:
    body_model: BodyModelConfig = field(default_factory=BodyModelConfig)
    prepare: PrepareConfig = field(default_factory=PrepareConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    object: ObjectConfig = field(default_factory=ObjectConfig)
    body: BodyConfig = field(default_factory=BodyConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    global_: GlobalConfig = field(default_factory=GlobalConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    export: ExportConfig = field(default_factory=ExportConfig)
    report: ReportConfig = field(default_factory=ReportConfig)
    run: RunConfig = field(default_factory=RunConfig)


class ConfigError(ValueError):
    """A YAML file or override names a key that does not exist or has a bad value."""


def _coerce(value: Any, current: Any, key: str) -> Any:
    """Parse a command-line string into the type of the field it overrides."""
    if not isinstance(value, str):
        return value
    parsed = yaml.safe_load(value)
    if current is None or parsed is None:
        return parsed
    if isinstance(current, bool):
        if not isinstance(parsed, bool):
            raise ConfigError(f"{key}: expected true/false, got {value!r}")
        return parsed
    if isinstance(current, float) and isinstance(parsed, str):
        try:
            parsed = float(parsed)  # YAML reads 3e7 (no dot, no sign) as a string
        except ValueError:
            pass
    if isinstance(current, (int, float)) and not isinstance(parsed, (int, float)):
        raise ConfigError(f"{key}: expected a number, got {value!r}")
    if isinstance(current, float):
        return float(parsed)
    if isinstance(current, list) and isinstance(parsed, str):
        return [p.strip() for p in parsed.split(",") if p.strip()]
    return parsed


# The budgets `for_frame_rate` swaps in at dense frame rates: (section, setting, its dense twin).
DENSE_BUDGETS = (("body", "pose_steps", "pose_steps_dense"), ("global_", "steps", "steps_dense"),
                 ("object", "stop_patience", "stop_patience_dense"))


def for_frame_rate(cfg: Config, fps: float) -> Config:
    """The settings a session at `fps` runs with: at `run.dense_fps` and above, each budget in
    DENSE_BUDGETS replaced by its dense twin. Frames close in time start their fits near the
    answer (the previous frame's object pose, the previous batch's body, the per-frame results),
    so fewer steps reach the same place; sparse takes keep the full budgets."""
    if fps < cfg.run.dense_fps:
        return cfg
    sections = {name: dataclasses.replace(getattr(cfg, name), **{setting: getattr(getattr(cfg, name), dense)})
                for name, setting, dense in DENSE_BUDGETS}
    return dataclasses.replace(cfg, **sections)


# Settings with a fixed set of values, checked when the config is read (not when a stage reaches them).
LINE_SEARCHES = ("auto", "strong_wolfe", "armijo")  # `optim.minimise`'s
CHOICES = {("body", "line_search"): LINE_SEARCHES, ("global_", "line_search"): LINE_SEARCHES,
           ("prepare", "calib_refine"): ("auto", "always", "never")}


# Sections whose name is a Python keyword: written `global` in YAML and overrides.
KEYWORD_SECTIONS = {"global": "global_"}


def _apply(node: Any, updates: dict, prefix: str = "", section: str = "") -> None:
    names = {f.name for f in dataclasses.fields(node)}
    for key, value in updates.items():
        path = f"{prefix}{key}"
        key = KEYWORD_SECTIONS.get(key, key) if not prefix else key
        if key not in names:
            raise ConfigError(f"unknown config key {path!r}; known here: {sorted(names)}")
        current = getattr(node, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ConfigError(f"{path} is a section; give it a mapping")
            _apply(current, value, prefix=path + ".", section=key)
        else:
            value = _coerce(value, current, path)
            allowed = CHOICES.get((section, key))
            if allowed and value not in allowed:
                raise ConfigError(f"{path}: expected one of {', '.join(allowed)}, got {value!r}")
            setattr(node, key, value)


def load_config(yaml_path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults, then the YAML file, then ``section.key=value`` overrides (``key=value`` for the
    `run` section's settings: ``device=cuda``)."""
    cfg = Config()
    if yaml_path is not None:
        try:
            data = yaml.safe_load(Path(yaml_path).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"cannot read config {yaml_path}: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"{yaml_path}: top level must be a mapping")
        _apply(cfg, data)
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override {item!r} is not of the form section.key=value")
        dotted, value = item.split("=", 1)
        *sections, leaf = dotted.strip().split(".")
        if not sections and leaf in {f.name for f in dataclasses.fields(RunConfig)}:
            sections = ["run"]  # a bare key names a `run` setting: `--set device=cuda`
        nested: dict = {leaf: value}
        for section in reversed(sections):
            nested = {section: nested}
        _apply(cfg, nested)
    return cfg


def config_to_dict(cfg: Config) -> dict:
    spelled = {field: name for name, field in KEYWORD_SECTIONS.items()}
    return {spelled.get(k, k): v for k, v in dataclasses.asdict(cfg).items()}


def save_config(cfg: Config, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
