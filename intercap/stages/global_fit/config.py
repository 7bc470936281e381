"""The `global` stage's settings (section `global` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass


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
