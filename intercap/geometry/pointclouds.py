"""Point-cloud helpers (numpy + open3d): checking (N, 3) arrays, conversion to open3d,
fusing the views' world clouds, what a subsample's points stand for."""
from __future__ import annotations

import contextlib

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree


def as_points(points, what="points") -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{what} must be (N, 3), got shape {arr.shape}")
    return arr


@contextlib.contextmanager
def open3d_threads(n: int):
    """Open3D's parallel loops use at most `n` threads inside the block."""
    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(n)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)


def to_o3d(points: np.ndarray) -> o3d.geometry.PointCloud:
    """(N, 3) numpy -> open3d point cloud."""
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(as_points(points)))


def fuse_points(points_per_view: list[np.ndarray], voxel_size: float) -> np.ndarray:
    """Concatenate the views' (N_c, 3) world clouds and voxel-downsample -> (N, 3).

    voxel_size <= 0 only concatenates. Empty views are skipped.
    """
    clouds = [as_points(p, f"view {i} points") for i, p in enumerate(points_per_view) if len(p)]
    if not clouds:
        return np.zeros((0, 3))
    merged = np.concatenate(clouds, axis=0)
    merged = merged[np.isfinite(merged).all(axis=1)]
    if voxel_size <= 0 or len(merged) == 0:
        return merged
    return np.asarray(to_o3d(merged).voxel_down_sample(float(voxel_size)).points)


def nearest_shares(points: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(len(ids),) how many of `points` (N, 3) lie nearest each of the points `ids`, over the mean (mean 1):
    weights that make a mean over a subsample stand for the mean over all points (a spread-out subsample
    of a body mesh draws the dense face and hands with few points)."""
    ids = np.asarray(ids)
    nearest = cKDTree(as_points(points)[ids]).query(points)[1]
    counts = np.bincount(nearest, minlength=len(ids)).astype(np.float64)
    return counts / counts.mean()
