"""The `prepare` stage's settings (section `prepare` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PrepareConfig:
    """Point clouds, ground plane and the calibration check."""

    depth_min_m: float = 0.2  # depth readings nearer than this (m) are dropped (sensor's blind zone)
    depth_max_m: float = 8.0  # ... and farther than this (m): noisy far range, walls
    pixel_stride: int = 2  # back-project every n-th pixel (each image axis) for the clouds; 1 = every pixel
    voxel_size_m: float = 0.01  # fused ground cloud's voxel (m); the calibration check uses max(2x this, 2 cm)
    plane_distance_m: float = 0.015  # RANSAC inlier band for the ground plane (m, either side)
    plane_iterations: int = 2000  # RANSAC trials per plane candidate
    ground_frames: int = 5  # frames (spread over the sequence) fused for the ground fit
    calib_frames: int = 3  # frames (spread over the sequence) used for the ICP check
    icp_max_distance_m: float = 0.10  # check and refinement: farthest a point's match in the other view may be (m)
    calib_warn_mm: float = 6.0  # a pair is flagged when its observable correction exceeds this (or calib_warn_deg)
    calib_warn_deg: float = 0.3  # ... the rotation's threshold (degrees)
    calib_k_sigma: float = 4.0  # ... and also calib_k_sigma standard deviations of itself (clear evidence only)
    calib_min_blocks: int = 100  # ... over an overlap of >= this many (frame, 25 cm block) clusters (else not judged)
    # correct the cameras' poses from the depth: auto (when the check flags a pair), always, never
    calib_refine: str = "auto"
    calib_refine_frames: int = 8  # frames (spread over the sequence) the refinement aligns
    calib_refine_iterations: int = 10  # Gauss-Newton steps of the refinement, at most
    calib_refine_prior: float = 1e-3  # pull of each camera's correction towards none (x the data's largest curvature)
    # ... on its square up to this length (m, scaled twist), on its length beyond (a bumped camera may move far)
    calib_refine_linear_beyond_m: float = 0.006
    save_clouds: bool = True  # write one fused coloured .ply per checked frame (OUT/prepare/clouds/) for inspection
    seed: int = 0  # RANSAC's random seed (the same plane every run)
