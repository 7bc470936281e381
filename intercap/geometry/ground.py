"""The ground plane: `fit_ground_plane` finds the floor by RANSAC without assuming which
world axis is up: among the few largest planes it keeps the one the person (or the
foreground) stands on.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from intercap.geometry.pointclouds import as_points, open3d_threads, to_o3d


def up_hint_from_cameras(T_world_from_cam: np.ndarray) -> np.ndarray:
    """(3,) unit 'up' guess from (C, 4, 4) camera poses: the mean of the cameras'
    -y axes (OpenCV y points down in the image), good when cameras are roughly upright."""
    T = np.asarray(T_world_from_cam, dtype=np.float64)
    up = -T[:, :3, 1].sum(axis=0)
    n = np.linalg.norm(up)
    if n < 1e-9:
        raise ValueError("cameras' up axes cancel out; no up hint can be derived")
    return up / n


@dataclass
class GroundPlane:
    """The floor: a point on it and its unit normal, pointing to the side where
    the person stands (gravity = -normal). inlier_ratio: fraction of the fitted
    cloud within the RANSAC band; rmse_m: RMS distance of those inliers."""

    point: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit
    inlier_ratio: float = 0.0
    rmse_m: float = 0.0

    def signed_distance(self, pts) -> np.ndarray:
        """(N, 3) -> (N,) metres; positive above the floor."""
        return (np.asarray(pts, dtype=np.float64).reshape(-1, 3) - self.point) @ self.normal

    def to_dict(self) -> dict:
        return {
            "point": [float(v) for v in self.point],
            "normal": [float(v) for v in self.normal],
            "inlier_ratio": float(self.inlier_ratio),
            "rmse_m": float(self.rmse_m),
        }


def least_squares_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) -> (centroid (3,), unit normal (3,)) minimising squared orthogonal distances."""
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    return centroid, vt[-1]


def ransac_planes(
    points: np.ndarray, distance_threshold: float, iterations: int, max_planes: int = 3, min_inliers: int = 50
) -> list[np.ndarray]:
    """Up to `max_planes` planes found one after another (inliers removed between
    searches), largest first; returns each plane's inlier indices into `points`.
    Seed open3d's RNG beforehand for determinism. Open3D runs single-threaded here: its threads
    share the RNG in whatever order the scheduler gives them, and one session's floor came out
    tilted differently in 1 run of 5."""
    remaining = np.arange(len(points))
    found = []
    for _ in range(max_planes):
        if len(remaining) < max(3, min_inliers):
            break
        with open3d_threads(1):
            _, idx = to_o3d(points[remaining]).segment_plane(
                distance_threshold=float(distance_threshold), ransac_n=3, num_iterations=int(iterations)
            )
        idx = np.asarray(idx, dtype=np.int64)
        if len(idx) < min_inliers:
            break
        found.append(remaining[idx])
        remaining = np.delete(remaining, idx)
    return found


def refine_plane(
    points: np.ndarray, point: np.ndarray, normal: np.ndarray, distance_threshold: float, rounds: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares plane on the points within the band, re-selecting the band
    each round. Keeps the normal's sign. -> (point, normal, inlier mask (N,))."""
    inliers = np.abs((points - point) @ normal) < distance_threshold
    for _ in range(rounds):
        if inliers.sum() < 3:
            break
        new_point, new_normal = least_squares_plane(points[inliers])
        if new_normal @ normal < 0:
            new_normal = -new_normal
        point, normal = new_point, new_normal
        inliers = np.abs((points - point) @ normal) < distance_threshold
    return point, normal, inliers


def _plane_foreground(points: np.ndarray, planes: list, person_points) -> tuple[np.ndarray, np.ndarray | None]:
    """(which points lie on any plane (N,), the foreground shared by every candidate or None: then each
    candidate's foreground is the points off it)."""
    on_any_plane = np.zeros(len(points), dtype=bool)
    for idx in planes:
        on_any_plane[idx] = True
    if person_points is not None and len(person_points):
        shared_foreground = as_points(person_points, "person_points")
    elif (~on_any_plane).sum() >= max(30, int(0.005 * len(points))):
        shared_foreground = points[~on_any_plane]
    else:
        shared_foreground = None
    return on_any_plane, shared_foreground


def _floor_candidate(points: np.ndarray, idx: np.ndarray, shared_foreground, up, distance_threshold: float,
                     min_height: float, max_angle_to_up_deg: float):
    """(rests_on, n_inliers, point, normal) of one RANSAC plane, its normal towards the foreground, or None
    when the foreground is not above it (or, with up, the plane is too tilted)."""
    point, normal = least_squares_plane(points[idx])
    if shared_foreground is not None:
        foreground = shared_foreground
    else:
        off = np.ones(len(points), dtype=bool)
        off[idx] = False
        foreground = points[off]
    if len(foreground) == 0:
        return None
    heights = (foreground - point) @ normal
    if np.median(heights) < 0:
        normal, heights = -normal, -heights
    if heights.mean() < min_height:
        return None
    if np.mean(heights < -max(0.05, 3 * distance_threshold)) > 0.10:
        return None
    if up is not None and np.degrees(np.arccos(np.clip(normal @ up, -1, 1))) > max_angle_to_up_deg:
        return None
    rests_on = np.percentile(heights, 2) < 0.25
    return rests_on, len(idx), point, normal


def _largest_plane(points: np.ndarray, planes: list, on_any_plane: np.ndarray, up,
                   max_angle_to_up_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The largest plane, its normal towards the points off the planes; ValueError when it is a wall."""
    point, normal = least_squares_plane(points[planes[0]])
    reference = points[~on_any_plane] if (~on_any_plane).any() else points
    if (reference.mean(axis=0) - point) @ normal < 0:
        normal = -normal
    if up is not None:  # a wall seen head-on is no floor: say so rather than return it
        tilt = np.degrees(np.arccos(np.clip(abs(normal @ up), 0, 1)))
        if tilt > max_angle_to_up_deg:
            raise ValueError(f"no floor in view: the largest plane is {tilt:.0f} deg from the cameras' up "
                             f"(a wall?), none within {max_angle_to_up_deg:g} deg")
    return point, normal


def fit_ground_plane(
    points,
    distance_threshold: float = 0.015,
    iterations: int = 2000,
    seed: int = 0,
    person_points: np.ndarray | None = None,
    up_hint: np.ndarray | None = None,
    max_planes: int = 3,
    min_height: float = 0.3,
    max_angle_to_up_deg: float = 45.0,
) -> GroundPlane:
    """The floor of a fused scene cloud (N, 3) by seeded RANSAC.

    Up to `max_planes` planes are extracted (inliers removed between searches).
    The foreground is `person_points` when given, else the points on none of
    those planes (or, if that is nearly empty, the points off each candidate).
    A candidate qualifies when the foreground's centroid lies at least
    `min_height` above it, at most 10% of the foreground lies below it, and,
    with `up_hint`, its normal is within `max_angle_to_up_deg` of up. Among
    qualifying planes, those the foreground rests on (its lowest 2% within
    0.25 m) are preferred, then the one with most inliers wins. The normal
    points towards the foreground; the plane is refined by least squares.
    """
    points = as_points(points)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 3:
        raise ValueError(f"fit_ground_plane: need at least 3 finite points, got {len(points)}")
    o3d.utility.random.seed(int(seed))
    min_inliers = max(50, int(0.02 * len(points)))
    planes = ransac_planes(points, distance_threshold, iterations, max_planes, min_inliers)
    if not planes:
        raise ValueError(
            f"fit_ground_plane: no plane with >= {min_inliers} points within {distance_threshold} m "
            f"in {len(points)} points"
        )

    on_any_plane, shared_foreground = _plane_foreground(points, planes, person_points)
    up = None
    if up_hint is not None:
        up = np.asarray(up_hint, dtype=np.float64).reshape(3)
        up = up / np.linalg.norm(up)

    candidates = []  # (rests_on, n_inliers, point, normal)
    for idx in planes:
        candidate = _floor_candidate(points, idx, shared_foreground, up, distance_threshold, min_height,
                                     max_angle_to_up_deg)
        if candidate is not None:
            candidates.append(candidate)

    if candidates:
        _, _, point, normal = max(candidates, key=lambda c: (c[0], c[1]))
    else:
        warnings.warn(
            "fit_ground_plane: no plane has the foreground above it; using the largest plane "
            "(pass person_points or up_hint, or give `ground` in session.yaml)"
        )
        point, normal = _largest_plane(points, planes, on_any_plane, up, max_angle_to_up_deg)

    point, normal, inliers = refine_plane(points, point, normal, distance_threshold)
    residual = (points[inliers] - point) @ normal
    rmse = float(np.sqrt(np.mean(residual**2))) if inliers.any() else float("nan")
    return GroundPlane(
        point=point, normal=normal / np.linalg.norm(normal), inlier_ratio=float(inliers.mean()), rmse_m=rmse
    )
