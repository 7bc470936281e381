"""The `global` stage's settings (section `global` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class GlobalConfig:
    """The joint body-object stage over all frames (InterCap's global L-BFGS), in overlapping windows.

    E_B reuses the body stage's terms and weights (section `body`); the weights here are those of
    the terms the global stage adds (`intercap.stages.global_fit.terms`). Measured effects of these
    settings are in BENCHMARKS.md."""

    # windows and the optimiser
    window_frames: int = 48  # frames optimised together (>= 4); memory grows with it, the share fitted twice shrinks
    window_frames_gpu: int = 300  # window_frames on CUDA: a step costs its kernel launches whatever its length
    window_overlap: int = 8  # frames a window shares with the next, re-optimised with more future (< window_frames)
    window_history: int = 2  # of the shared frames, those held fixed at the previous window's result (<= overlap)
    steps: int = 15  # L-BFGS steps per window
    steps_dense: int = 12  # steps at run.dense_fps and above, where the per-frame fits start the windows closer
    inner_iterations: int = 8  # L-BFGS iterations per step (torch's max_iter)
    ftol: float = 1.0e-6  # a window stops when a step lowers its energy by less than this (relative)
    line_search: str = "auto"  # "strong_wolfe" (torch's), "armijo" (one host read per trial); auto: Armijo on CUDA
    max_line_search: int = 4  # Armijo's trials per L-BFGS iteration
    cuda_graphs: bool = True  # on CUDA a window's evaluations replay one recorded graph (`optim.gradient_evaluator`)
    correspondence_every: int = 5  # E_D's data association refreshed every this many steps

    # the object's data and shape
    object_points_per_view: int = 300  # object depth points per view for E_O (a seeded subset of its pixels)
    object_depth_scale_m: float = 0.02  # metres: Geman-McClure scale of E_O's point-to-surface distance
    sdf_resolution: int = 64  # the object's signed-distance grid: at least this many cells along its longest side,
    sdf_cell_m: float = 0.005  # metres: none wider than this, so thin parts (a chair's back panel) read as inside
    sdf_margin_m: float = 0.10  # metres: the grid reaches at most this far beyond the object's box

    # contact
    contact_vertices: int = 20  # E_C and E_C': a touching region's nearest this many vertices count
    hand_reach_m: float = 0.10  # metres: a hand nearer than this to the object in a contact frame is grasping
    object_inside_body_share: float = 0.1  # a tracked pose with more of its surface 2 cm inside the body is distrusted

    # frames whose per-frame fit left its data (`observations.departed_frames`), started from their neighbours
    repair_factor: float = 2.5  # fit-to-data above this many times the median of the frames around; 0: off
    repair_floor_mm: float = 40.0  # mm: never a departed frame below this fit-to-data
    repair_reach: int = 15  # frames either side whose median fit-to-data a frame is compared with

    start_smoothing_s: float = 0.05  # seconds: the per-frame body low-passed (Gaussian sigma) as the fit's start; 0: off
    start_smoothing_alone_s: float = 0.1  # the same in a body-only joint fit (BENCHMARKS.md: a stronger smoothed start)
    # a body-only joint fit's start is low-passed more where the per-frame fits' noise hides no motion, up to this
    # (seconds, `observations.adaptive_smoothing_frames`): a slow turn's start is smoothed widely, a bend's peak kept
    start_smoothing_most_alone_s: float = 0.3
    start_smoothing_confidence_alone: float = 1.0  # its confidence interval, in noise x kernel norms (BENCHMARKS.md)
    # the same with an object, up to this (BENCHMARKS.md: a raw cup's acceleration); start_smoothing_s: one width
    start_smoothing_most_s: float = 0.15
    start_smoothing_confidence: float = 1.0  # its confidence interval
    shape_change_limit_mm: float = 15.0  # mm: the sequence-mean phenotype moving a frame's body more: frames keep their own
    # frames that keep their own phenotype have it low-passed (Gaussian sigma): no step between the body stage's batches
    shape_smoothing_s: float = 0.2  # seconds; 0: off

    # checks of the take (warnings in the log and the report)
    max_keypoint_energy_ratio: float = 3.0  # warn when the fit raises E_J over this many times (fps wrong?); 0: off
    max_camera_offset_ms: float = 4.0  # ms: warn of cameras whose frames lag or lead the others' more; 0: off
    time_check_frames: int = 300  # frames spread over the take on which each camera's lag is measured

    # weights of the terms the joint fit adds (E_B's are the body section's)
    w_object: float = 3.0e7  # E_O: observed object points to the surface (mean over a frame's points, metres^2)
    w_object_anchor: float = 1.0e8  # the tracked pose (silhouette + depth) x its confidence, more exact than E_O alone
    w_interpenetration: float = 3.0e6  # E_P: body vertices inside the object (sum over vertices, metres^2)
    w_contact: float = 5.0e7  # E_C: a touching hand's patch onto the surface (mean over the patch, metres^2)
    w_hand_contact: float = 1.0e7  # E_C': a grasping palm onto the object's graspable points (metres^2)
    w_ground: float = 1.0e6  # E_G: body and object below the floor, per vertex; stiff, as all views' keypoints agree
    w_object_acceleration: float = 30.0  # E_A: the object's points' acceleration, (m/s^2)^2 per frame
    w_body_acceleration: float = 10.0  # the body vertices' acceleration, (m/s^2)^2 per frame, in fast motion
    # where the body moves slowly its acceleration weighs more: per frame x reference / a, within [1, max_scale],
    # a the start's mean vertex acceleration low-passed (`observations.acceleration_scale`); reference 0: off
    acceleration_reference_mps2: float = 4.5  # m/s^2: motion this fast or faster keeps the weight as set
    acceleration_max_scale: float = 8.0  # at most this many times the weight (a person turning on the spot)
    acceleration_smoothing_s: float = 0.1  # seconds: the start low-passed to this in all to measure its motion
    acceleration_reach_s: float = 0.25  # seconds: a frame's motion averaged over this (Gaussian sigma) either side
    acceleration_gap_s: float = 0.25  # seconds: frames with no body fit for longer (out of view) break the body's term
    w_body_acceleration_alone: float = 2.2  # the same in a body-only joint fit, at 10 fps and more; below, x (fps/10)^2
    # a body-only joint fit takes the scale to this power (its cap too): a person alone moves without the grasps'
    # and lifts' jolts, so noise shows against slow motion sooner, while a walk's foot strikes need the weight low;
    # 1: as with an object
    acceleration_power_alone: float = 2.5
    acceleration_max_scale_alone: float = 12.0  # acceleration_max_scale in a body-only joint fit (before the power)
    # in a body-only joint fit each window vertex weighs as many of the mesh's vertices as lie nearest it at rest,
    # so the term is the whole mesh's mean (the spread-out fitting subsample draws the dense face and hands with
    # few vertices, and a turning head jitters); takes with an object keep the plain mean (BENCHMARKS.md)
    acceleration_over_mesh_alone: bool = True
    w_body_motion_prior: float = 0.0  # E_S, the learned (LEMO-style) body motion prior; 0: off (session-dependent)
    w_hand_motion_prior: float = 0.0  # E_L + E_R, the learned hand motion priors; 0: off (used with E_S)
    w_flight: float = 1.0e9  # GraviCap: the object's centre onto the gravity parabola in free flight (m^2); 0: off

    # free flight (GraviCap)
    flight_min_frames: int = 8  # a free flight lasts at least this many frames touching neither body nor ground
    flight_ground_margin_m: float = 0.02  # metres: the object touches the ground when its surface comes this close
    flight_max_residual_m: float = 0.05  # metres: a path a parabola under gravity misses by more (RMS) is no flight
    seed: int = 0  # seeds the object's surface samples and the subsets of its depth points
