"""The `object` stage's settings (section `object` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ObjectConfig:
    """Per-frame object tracking by silhouette + depth rendering (E_O).

    Weights (`w_*`) scale the unweighted terms of `intercap.stages.object.terms` (unitless multipliers,
    >= 0); `_gpu` and `_dense` variants replace their plain setting on CUDA and at `run.dense_fps`."""

    # evidence: masks, renders and E_O's terms
    use_session_masks: bool = True  # False: derive masks from depth even when the session has them
    crop_size: int = 64  # render grid (pixels, per side) of the square crop around the object in each view
    crop_margin: float = 0.25  # crop grows this fraction (>= 0) beyond the object and its mask
    sigma_px: float = 0.7  # silhouette edge softness (render-grid pixels, > 0)
    w_silhouette: float = 1.0  # l_segm: weight of the silhouette term
    w_depth: float = 1.0  # l_depth: weight of the depth term
    depth_scale_m: float = 0.03  # Geman-McClure scale of depth residuals (m)
    occluder_margin_m: float = 0.03  # measured this much (m) in front of the object = occluded there
    # the fit: Adam from the prediction, the step size shrinking once E_O stalls
    iterations: int = 60  # Adam steps at most, per frame (early stopping ends most fits well before)
    side_by_side: int = 1  # chunks of the take one process tracks at once, their fits in one render per step (>= 1)
    side_by_side_gpu: int = 8  # side_by_side on CUDA (a GPU's step costs its kernel launches, not its size)
    cuda_graphs: bool = True  # on CUDA a fit's renders keep fixed shapes and each step replays one recorded graph
    read_ahead: bool = True  # on CUDA, with session masks: the next frame is read while this one is fitted
    stop_tolerance: float = 1e-3  # relative E_O decrease (0-1) that counts as progress
    stop_patience: int = 3  # steps without progress before the step size shrinks (or the fit stops)
    stop_patience_dense: int = 2  # stop_patience at run.dense_fps and above (neighbouring frames start near the answer)
    # first poses: registration hypotheses scored by E_O
    init_iterations: int = 15  # Adam steps per hypothesis, before the best is refined
    init_global_tries: int = 2  # FPFH RANSAC registrations among the hypotheses (each its own seed)
    init_ransac_iterations: int = 5000  # RANSAC iterations of each of those registrations
    init_keep: int = 6  # registration hypotheses (best ICP fitness) scored by E_O
    init_refine: int = 8  # of those (and the prediction), the lowest-E_O ones that get a short fit
    init_places: int = 3  # derived masks: places (foreground parts of the object's size) registered in a search
    # orientation checks: every axis-aligned turn of the mesh scored by E_O where a track starts, ...
    check_orientations: bool = True
    recheck_move_fraction: float = 0.25  # ... where the object first moves this fraction of its size from there, ...
    recheck_energy_ratio: float = 1.5  # ... and where E_O stays above this times its value at the last check ...
    recheck_frames: int = 5  # ... for this many frames
    # Adam's step sizes (every fit's)
    lr_rotation: float = 0.02  # Adam step size of the 6D rotation parameters
    lr_translation: float = 0.004  # Adam step size of the centroid's position (m)
    lr_decay: float = 0.3  # step sizes shrink by this factor (0-1) when E_O stalls ...
    lr_decays: int = 1  # ... this many times before the fit stops
    voxel_size_m: float = 0.005  # registration voxel (m), at least; ICP and FPFH work on points this far apart
    voxel_fraction: float = 0.0125  # registration voxel at least this fraction of the object's extent
    init_max_points: int = 1500  # observed points registered (evenly thinned beyond this)
    # trust: which fits give a pose, when to search again
    min_mask_px: int = 30  # a view's object mask (or a derived mask's part) counts from this many pixels
    min_views: int = 1  # views that must see the object for a pose
    min_confidence: float = 0.5  # mean silhouette IoU (0-1) below this = not trusted
    reinit_energy_ratio: float = 1.5  # E_O above this times its recent median: search for a better pose
    trust_energy_ratio: float = 2.0  # E_O still above this times that median after the search: untrusted
    energy_window: int = 30  # frames whose E_O (the last 5 with a fit) set that median
    confirm_ratio: float = 0.9  # a search ending above this times the tracked E_O confirms it as the new level
    # of the last frame's turn, this share (0-1) is carried on into the prediction: all of it turns a rotation
    # E_O hardly sees (a cup's tilt under a hand) into a drift that grows frame by frame
    predict_turn_share: float = 0.5
    coast_frames: int = 15  # after losing track, fit from the last trusted pose for this many frames
    # a symmetric object's pose keeps its last trusted turn about its symmetry (else a spin, invisible
    # to E_O, lives on in the constant-velocity prediction)
    hold_symmetric_turn: bool = True
    # a fit turned more than this (degrees) per frame since the last trusted one is untrusted (0: no limit;
    # a real object rarely turns 45 degrees in 33 ms: a spinning toss at 2 turns/s turns 24) ...
    max_turn_deg_per_frame: float = 45.0
    # ... unless its E_O is below this times the recent level (turned back: a recovery)
    fast_turn_energy_ratio: float = 0.8
    # derived masks: the depth background and the cut round the prediction
    background_frames: int = 30  # frames spread over the take whose depth makes each camera's background
    background_valid_fraction: float = 0.3  # pixels measured in fewer of those frames (0-1) have no background
    # (dark floors lose much of their depth)
    bridge_fraction: float = 0.006  # derived masks: join object fragments this far apart (fraction of image width)
    near_margin_m: float = 0.05  # derived masks: object pixels lie within this (m) of the predicted bounding sphere
    # derived masks without person masks: a search over a whole view leaves out the person's head, trunk, arms
    # and legs drawn from the run's keypoints of at least this confidence (0-1; above 1: not left out)
    person_keypoint_confidence: float = 0.3
    # derived masks without person masks, round a pose: pixels within this (m) of a palm found from those keypoints
    # are unknown, neither object nor background (a hand holding a tool is otherwise part of it; 0: kept)
    hand_radius_m: float = 0.10
    # ... unless their colour is the object's: this many times (> 1) likelier on it than on the hands, as learnt
    # from `colour_frames` frames spread over the take (0: not learnt; all unknown), where that tells at least
    # `colour_min_separable` (0-1) of the object's colours apart
    colour_ratio: float = 4.0
    colour_frames: int = 12
    colour_min_separable: float = 0.5
    # the run: checkpoints, pictures, seams
    checkpoint_every: int = 10  # frames between saves of a chunk's progress (OUT/object/progress_LO_HI.npz)
    overlay_every: int = 10  # an overlay picture (OUT/object/overlays/) every this many frames
    seam_agree_frames: int = 3  # a chunk's own poses stand once this many frames tracked on across its seam match them
    seam_agree_mm: float = 10.0  # match: the posed surfaces this close (mm, ADD-S: a symmetric object's look-alike
    # pose matches)
    seam_agree_deg: float = 10.0  # and the rotations this close, up to the mesh's symmetry (a small cup tipped over
    # keeps its surface within the ADD-S of its upright pose)
    seed: int = 0  # seeds the mesh's surface samples, RANSAC and torch (a run repeats exactly)
