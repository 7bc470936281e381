"""The `body` stage's settings (section `body` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class BodyConfig:
    """Per-frame whole-body fitting (multi-view PROX-D): E_J + E_D + priors, L-BFGS in phases.

    Weights (`w_*`) scale the unweighted terms of `intercap.stages.body.terms` (unitless multipliers,
    >= 0); `_gpu` and `_dense` variants replace their plain setting on CUDA and at `run.dense_fps`."""

    # evidence: which keypoints and depth points the fit reads
    use_session_masks: bool = True  # False: derive person masks from depth even when the session has them
    batch_frames: int = 16  # frames fitted as one batch (warm-started from the previous batch); smaller: slower
    batch_frames_gpu: int = 32  # batch_frames on CUDA, where a step costs its kernel launches, not the batch's size
    side_by_side: int = 1  # chunks of the take one process fits at once, their batches in one evaluation
    # (`fit_chunks`; >= 1; a short take pays a cold start per extra chunk)
    side_by_side_gpu: int = 8  # side_by_side on CUDA: K chunks cost about what one does there
    min_keypoint_confidence: float = 0.2  # detections below this confidence (0-1) are ignored
    keypoint_view_check_px: float = 30.0  # a detection this far (px at 640 px width) from the other views' point
    # is dropped (`reject_disagreeing_views`), a view's left and right limbs this far from them and near them
    # exchanged are exchanged back first (`swap_disagreeing_sides`); 0: off
    min_body_keypoints: int = 6  # a view counts for a frame when it has this many confident body keypoints (of 25)
    min_points: int = 100  # a view's depth counts when its person mask gives this many points
    points_per_view: int = 400  # segmented depth points per view used by E_D (a seeded random subset)
    person_erode_px: int = 2  # mask border pixels dropped (mixed depth), at 640 px width, scaled with it
    # A person who stays in place all take is in the depth background too: when under this share (0-1) of a
    # view's confident body keypoints lie on the depth foreground, the mask is the keypoint box's pixels
    # within `still_person_band_m` of the keypoints' depths and above the floor (`PersonPoints.still_mask`).
    still_person_keypoints: float = 0.5
    still_person_band_m: float = 0.2  # depth band (m) either side of the keypoints' depths of that mask
    # robust scales and per-term factors
    keypoint_rho: float = 100.0  # Geman-McClure scale of E_J, pixels at a 1000 px focal length (final phase)
    keypoint_rho_start: float = 400.0  # the same in the first phases: far-off starts are not outliers
    hand_keypoint_weight: float = 1.0  # per-joint weight of the 2 x 21 hand keypoints in E_J (body: 1)
    depth_scale_m: float = 0.05  # Geman-McClure scale of E_D (m)
    depth_model_to_data: float = 1.0  # weight of E_D's model-to-data half (each visible vertex to its nearest
    # point) against its data-to-model half (1); 0: off
    depth_model_to_data_max_m: float = 0.10  # a visible vertex with no point this near (m) has none (hidden by
    # the object)
    visibility_margin_m: float = 0.03  # a vertex is visible when at most this far (m) behind the nearest surface
    visibility_cells: int = 100  # z-buffer cells across the image width for the visibility test
    w_keypoints: float = 1.0  # E_J, the 2D keypoints of every view (also the orient phase's trunk and legs)
    w_depth: float = 3.0e5  # E_D, the segmented person points against the visible vertices
    one_view_depth_factor: float = 3.3  # E_D x this on frames fewer than two views see (nothing triangulates:
    # depth decides)
    w_pose_prior: float = 10.0  # learned Gaussian mixture of body poses (CMU)
    w_joint_limits: float = 1.0e4  # anatomical joint ranges
    w_bending: float = 1.0e3  # extreme elbow and knee bending
    w_ground: float = 1.0e6  # E_G: fitting vertices below the ground plane (prepare's), per vertex, as the
    # global stage's
    w_ground_support: float = 1.0e5  # E_S: the body's lowest points onto the floor where fewer than two views see
    # the feet; 0: off
    w_hand_prior: float = 1.0e3  # finger ranges of both hands
    w_shape: float = 100.0  # phenotype inside [0, 1], lightly pulled to the average (or the measured) person
    shared_shape: bool = True  # one phenotype per batch whose frames all have >= 2 keypoint views (one person);
    # with fewer views each frame its own: one view's stooping frames would bend the upright ones' shape
    shape_batches: int = 2  # the phenotype is fitted on the first batches this many (a process's chunks together),
    # then held at their mean (one person; re-fitted per batch it drifts: its prior is weak); 0: every batch
    size_from_depth: bool = True  # template's stature from the 3D torso keypoints (children, tall people; one view)
    w_expression: float = 10.0  # rest face, where the expression is fitted
    w_penetration: float = 1.0e5  # self-penetration of the sphere proxy (`BodySpheres`)
    fit_expression: bool = False  # anny has no face landmarks in our keypoint set: expression stays neutral
    # optimisation budget: L-BFGS steps per phase (`terms.PHASES`)
    orient_steps: int = 5  # L-BFGS steps of the phase that moves only orientation + translation
    pose_steps: int = 15  # + body pose and shape, keypoints only
    pose_steps_dense: int = 10  # pose_steps at run.dense_fps and above, where a batch's frames lie near the
    # previous batch's last fit
    full_steps: int = 20  # + hands, with the depth term and self-penetration (fewer: stoops stay off)
    inner_iterations: int = 8  # L-BFGS iterations per step (E_D correspondences are refreshed between steps)
    ftol: float = 1e-5  # relative energy change below which a phase stops early
    line_search: str = "auto"  # of the phases fitting one shape over the batch: as global.line_search
    max_line_search: int = 4  # Armijo's trials per L-BFGS iteration there
    cuda_graphs: bool = True  # on CUDA each phase's evaluations replay one recorded graph (`optim.gradient_evaluator`)
    per_frame_lbfgs: bool = True  # each frame its own L-BFGS (`minimise_per_frame`) where the frames do not
    # interact; false: one L-BFGS over the batch's summed energy (less accurate)
    # tracking: a frame whose person points lie far from its fit (median distance, mm), or, seen with
    # keypoints by fewer than two views, whose pose the learned prior finds far less likely than recent
    # frames' (contorted to reach the evidence), is refitted from the evidence (the upright template at
    # four headings, stooped at two) instead of from the previous batch's pose; of the fits on their
    # points the one of lowest energy is kept, and later batches start from the last fit on its points
    track_floor_mm: float = 40.0  # fit-to-data: never a failure below this (mm)
    track_factor: float = 2.5  # fit-to-data: a failure above this many times its running median
    track_prior_factor: float = 1.5  # pose prior (frames < 2 keypoint views): a failure above this x its running
    # median
    track_window: int = 30  # frames in those running medians
    overlay_every: int = 10  # an overlay picture (OUT/body/overlays/) every this many frames
    seed: int = 0  # seeds the depth points' random subsets and torch
