"""The `object` stage's settings (section `object` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass


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
