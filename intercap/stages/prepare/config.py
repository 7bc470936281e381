"""The `prepare` stage's settings (section `prepare` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass


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
