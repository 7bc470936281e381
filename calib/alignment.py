"""Calibration check: do neighbouring cameras' point clouds agree?

Each camera's depth, back-projected with its calibration, gives a world point
cloud. Where two neighbouring views see the same surfaces, a good calibration
makes the clouds coincide. Point-to-plane ICP from one view onto the other,
started at identity, measures the rigid correction that would make them agree:
near zero for a good calibration, about the drift for a camera that has moved.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

reg = o3d.pipelines.registration


@dataclass
class PairAgreement:
    """How well view `cam_a` agrees with its neighbour `cam_b`.

    overlap_points: points of a (after voxel downsampling) within max_distance of b;
    median_distance_mm: before ICP, the median over those points of the distance
    to the nearest b point's tangent plane (point-to-plane, so it measures
    misalignment, not the ~voxel/2 spacing between two samplings of a surface);
    icp_rmse_mm: after ICP, the RMS point-to-plane residual of the correspondences
    (a's points within max_distance of b), the noise floor of the two sensors;
    correction_rotation_deg: rotation angle of the ICP correction;
    correction_translation_mm: how far the correction moves the centre of the overlap
    (so it does not depend on where the world origin is);
    fitness: fraction of a's points with a correspondence after ICP;
    correction: (4, 4) world-frame transform moving a's points onto b's
    (apply it to a's T_world_from_cam to re-align camera a to b).
    Distances are NaN when the views do not overlap.
    """

    cam_a: str
    cam_b: str
    overlap_points: int
    median_distance_mm: float
    icp_rmse_mm: float
    correction_rotation_deg: float
    correction_translation_mm: float
    fitness: float
    correction: np.ndarray = field(default_factory=lambda: np.eye(4), repr=False)


def neighbour_pairs(camera_centers) -> list[tuple[int, int]]:
    """Pairs of neighbouring cameras by angle around the rig centre.

    Camera centres (C, 3) are projected onto their best-fit plane; the rig
    centre is the circle through them (least squares), so an arc of cameras is
    seen from the middle of the room, not from its own centroid. Cameras are
    ordered by angle around it. A ring gives C pairs in ring order
    ((i0, i1), (i1, i2), ..., (i_{C-1}, i0)); when one angular gap is 150 deg or
    more the rig is an arc and that gap's pair is dropped; near-collinear rigs
    are chained along their line. Every camera appears at least once (C >= 2).
    """
    centers = np.asarray(camera_centers, dtype=np.float64).reshape(-1, 3)
    C = len(centers)
    if C < 2:
        return []
    if C == 2:
        return [(0, 1)]
    centered = centers - centers.mean(axis=0)
    _, s, vt = np.linalg.svd(centered, full_matrices=False)
    if s[1] < 0.1 * s[0]:  # near-collinear: a chain along the line
        order = np.argsort(centered @ vt[0], kind="stable").tolist()
        return list(zip(order[:-1], order[1:]))
    xy = centered @ vt[:2].T  # (C, 2) in the rig plane
    xy = xy - rig_centre_2d(xy)
    angles = np.arctan2(xy[:, 1], xy[:, 0])
    order = np.argsort(angles, kind="stable")
    sorted_angles = angles[order]
    gaps = np.append(np.diff(sorted_angles), 2 * np.pi - (sorted_angles[-1] - sorted_angles[0]))
    ring = [(int(order[k]), int(order[(k + 1) % C])) for k in range(C)]
    widest = int(np.argmax(gaps))
    if gaps[widest] >= np.radians(150.0):
        ring = ring[widest + 1 :] + ring[:widest]  # an arc: start after the widest gap
    return ring


def rig_centre_2d(xy: np.ndarray) -> np.ndarray:
    """(2,) centre of the circle best fitting (C, 2) points (algebraic least
    squares); their centroid when the fit is degenerate or far away."""
    A = np.column_stack([xy, np.ones(len(xy))])
    b = -(xy**2).sum(axis=1)
    (D, E, _), *_ = np.linalg.lstsq(A, b, rcond=None)
    centre = np.array([-D / 2, -E / 2])
    spread = np.abs(xy).max()
    if not np.all(np.isfinite(centre)) or np.linalg.norm(centre) > 5 * spread:
        return np.zeros(2)
    return centre


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees."""
    return math.degrees(math.acos(float(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def _view_cloud(points: np.ndarray, voxel_size: float, name: str) -> o3d.geometry.PointCloud:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"check_calibration: points of view {name!r} must be (N, 3), got {pts.shape}")
    pts = pts[np.isfinite(pts).all(axis=1)]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if voxel_size > 0 and len(pts):
        cloud = cloud.voxel_down_sample(float(voxel_size))
    if len(cloud.points):
        radius = 3 * voxel_size if voxel_size > 0 else 0.03
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    return cloud


def pair_agreement(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    cam_a: str,
    cam_b: str,
    max_distance: float,
    min_overlap: int = 50,
) -> PairAgreement:
    """Agreement of one view's cloud (source, a) with its neighbour's (target, b)."""
    nan = float("nan")
    if len(source.points) == 0 or len(target.points) == 0:
        return PairAgreement(cam_a, cam_b, 0, nan, nan, nan, nan, 0.0)
    src_pts = np.asarray(source.points)  # (N_a, 3)
    tgt_pts = np.asarray(target.points)  # (N_b, 3)
    tree = cKDTree(tgt_pts)
    nn, idx = tree.query(src_pts, k=1, distance_upper_bound=max_distance)
    overlap = np.isfinite(nn)  # a neighbour within max_distance
    n_overlap = int(overlap.sum())
    if n_overlap < min_overlap:
        return PairAgreement(cam_a, cam_b, n_overlap, nan, nan, nan, nan, 0.0)
    result = reg.registration_icp(
        source,
        target,
        float(max_distance),
        np.eye(4),
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9, max_iteration=100),
    )
    T = np.asarray(result.transformation)
    # after ICP: RMS point-to-plane residual of the correspondences ICP used
    moved_pts = src_pts @ T[:3, :3].T + T[:3, 3]
    nn_after, idx_after = tree.query(moved_pts, k=1, distance_upper_bound=max_distance)
    used = np.isfinite(nn_after)
    residual = ((moved_pts[used] - tgt_pts[idx_after[used]]) * np.asarray(target.normals)[idx_after[used]]).sum(1)
    # misalignment before ICP: distance to the neighbour's tangent plane, which
    # unlike the raw neighbour distance does not grow with the point spacing
    normals = np.asarray(target.normals)[idx[overlap]]
    off_plane = np.abs(((src_pts[overlap] - tgt_pts[idx[overlap]]) * normals).sum(axis=1))
    centre = src_pts[overlap].mean(axis=0)
    moved = T[:3, :3] @ centre + T[:3, 3]
    return PairAgreement(
        cam_a=cam_a,
        cam_b=cam_b,
        overlap_points=n_overlap,
        median_distance_mm=float(np.median(off_plane) * 1000),
        icp_rmse_mm=float(np.sqrt(np.mean(residual**2)) * 1000) if used.any() else float("nan"),
        correction_rotation_deg=rotation_angle_deg(T[:3, :3]),
        correction_translation_mm=float(np.linalg.norm(moved - centre) * 1000),
        fitness=float(result.fitness),
        correction=T.copy(),
    )


def check_calibration(
    points_per_view: list[np.ndarray],
    names: list[str],
    camera_centers,
    max_distance: float = 0.05,
    voxel_size: float = 0.01,
    pairs: list[tuple[int, int]] | None = None,
) -> list[PairAgreement]:
    """ICP agreement of each neighbouring pair of views' world clouds (N_c, 3).

    Pairs come from `neighbour_pairs(camera_centers)` unless given. For each
    pair (a, b), a's cloud is registered onto b's (point-to-plane ICP in world
    coordinates, from identity, correspondences up to max_distance metres).
    """
    if len(points_per_view) != len(names):
        raise ValueError(f"check_calibration: {len(points_per_view)} point clouds but {len(names)} names")
    if pairs is None:
        pairs = neighbour_pairs(camera_centers)
    clouds = [_view_cloud(p, voxel_size, n) for p, n in zip(points_per_view, names)]
    return [pair_agreement(clouds[a], clouds[b], names[a], names[b], max_distance) for a, b in pairs]


def format_agreement(results: list[PairAgreement], warn_mm: float = 10.0, warn_deg: float = 1.0) -> str:
    """A table a person reads: one row per pair, flagged when the views disagree
    by more than warn_mm (median distance or correction) or warn_deg."""
    header = (
        f"{'pair':<24} {'overlap':>8} {'median mm':>10} {'icp rmse mm':>12} "
        f"{'corr deg':>9} {'corr mm':>8} {'fitness':>8}  status"
    )
    lines = [header, "-" * len(header)]
    n_flagged = 0
    for r in results:
        if not np.isfinite(r.median_distance_mm):
            status = "NO OVERLAP"
            n_flagged += 1
        elif (
            r.median_distance_mm > warn_mm
            or r.correction_translation_mm > warn_mm
            or r.correction_rotation_deg > warn_deg
        ):
            status = "CHECK CALIBRATION"
            n_flagged += 1
        else:
            status = "ok"
        pair = f"{r.cam_a} -> {r.cam_b}"
        lines.append(
            f"{pair:<24} {r.overlap_points:>8d} {r.median_distance_mm:>10.1f} {r.icp_rmse_mm:>12.1f} "
            f"{r.correction_rotation_deg:>9.2f} {r.correction_translation_mm:>8.1f} {r.fitness:>8.2f}  {status}"
        )
    lines.append(
        f"{n_flagged} of {len(results)} pairs flagged (warn above {warn_mm:g} mm or {warn_deg:g} deg)"
        if n_flagged
        else f"all {len(results)} pairs agree within {warn_mm:g} mm and {warn_deg:g} deg"
    )
    return "\n".join(lines)
