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
from scipy.spatial.transform import Rotation

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
    correction_rotation_deg / correction_translation_mm: the trustworthy size of
    the correction, i.e. its OBSERVABLE part (rotation angle; how far it moves
    the centre of the overlap, so it does not depend on where the world origin is);
    observable_rotation_deg / observable_translation_mm: the same figures (kept
    under an explicit name for readers that want to be sure);
    full_rotation_deg / full_translation_mm: the unconstrained 6-dof ICP
    correction, which slides along poorly constrained directions (planes) on
    noisy data: diagnostic only, never flag on it;
    unobservable: the directions the overlap does not constrain (e.g.
    "translation along (0.00, 1.00, 0.00)", "rotation about (...)"), left out
    of the correction;
    fitness: fraction of a's points with a correspondence after ICP;
    correction: (4, 4) world-frame transform (observable part) moving a's points
    onto b's (apply it to a's T_world_from_cam to re-align camera a to b).
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
    observable_rotation_deg: float = float("nan")
    observable_translation_mm: float = float("nan")
    full_rotation_deg: float = float("nan")
    full_translation_mm: float = float("nan")
    unobservable: list = field(default_factory=list)


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
        cloud = cloud.voxel_down_sample(float(voxel_size))  # averages the points in a voxel: less noise
    if len(cloud.points):
        # a wide neighbourhood: depth noise of ~1 cm tilts normals estimated on a few cm
        radius = max(4 * voxel_size, 0.06)
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=60))
    return cloud


def twist_transform(x: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """(4, 4) rigid transform of a scaled twist x (6,) = [radius * rotation vector,
    translation of `centre`], the rotation being about `centre`."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.asarray(x[:3]) / radius).as_matrix()
    T[:3, 3] = centre - T[:3, :3] @ centre + x[3:]
    return T


def scaled_twist(T: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Inverse of twist_transform: (6,) [radius * rotation vector, motion of centre]."""
    rot = Rotation.from_matrix(T[:3, :3]).as_rotvec() * radius
    return np.concatenate([rot, T[:3, :3] @ centre + T[:3, 3] - centre])


def point_to_plane_system(q, n, residual, weights, centre, radius):
    """Weighted normal equations of point-to-plane alignment, per point.

    q (N, 3) moved source points, n (N, 3) target normals, residual (N,) signed
    distances, weights (N,). Rows J_i = [(q_i - centre) x n_i / radius, n_i], so
    the unknown is a scaled twist whose six entries are all lengths (a rotation
    counts by how far it moves points at `radius`). Returns H (6, 6) = J^T W J / sum(W)
    and g (6,) = J^T W r / sum(W)."""
    J = np.hstack([np.cross(q - centre, n) / radius, n])  # (N, 6)
    Jw = J * weights[:, None]
    total = max(float(weights.sum()), 1e-12)
    return Jw.T @ J / total, Jw.T @ residual / total


def observable_basis(H: np.ndarray, min_constraint: float) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-directions of H (6, 6) split into constrained (eigenvalue at least
    min_constraint x the largest) and unconstrained ones: (6, k), (6, 6 - k).

    A plane constrains only its normal translation and the two tilts; a scene that
    is mostly floor and walls leaves the rest to a little clutter, where noise
    and view-dependent sampling make ICP slide: those directions are dropped."""
    ev, V = np.linalg.eigh(H)
    keep = ev >= min_constraint * max(ev.max(), 1e-12)
    return V[:, keep], V[:, ~keep]


def describe_directions(V: np.ndarray) -> list[str]:
    """Words for unconstrained twist directions (6, k): a translation or a rotation axis."""
    out = []
    for v in V.T:
        rot, trans = v[:3], v[3:]
        kind, axis = ("rotation about", rot) if np.linalg.norm(rot) > np.linalg.norm(trans) else ("translation along", trans)
        axis = axis / max(np.linalg.norm(axis), 1e-12)
        axis = axis if axis[np.argmax(np.abs(axis))] > 0 else -axis
        out.append(f"{kind} ({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f})")
    return out


def robust_point_to_plane_icp(
    src: np.ndarray,
    tgt_tree: cKDTree,
    tgt: np.ndarray,
    tgt_normals: np.ndarray,
    max_distance: float,
    centre: np.ndarray,
    radius: float,
    basis: np.ndarray | None,
    iterations: int = 30,
) -> np.ndarray:
    """(4, 4) point-to-plane ICP of src (N, 3) onto tgt (M, 3), from identity.

    Huber weights (scale from the residuals' MAD) tame the noise and outliers;
    each Gauss-Newton step is solved only within `basis` (6, k) of scaled-twist
    directions (all six when None), so poorly constrained directions never move."""
    T = np.eye(4)
    for _ in range(iterations):
        q = src @ T[:3, :3].T + T[:3, 3]
        dist, idx = tgt_tree.query(q, k=1, distance_upper_bound=max_distance)
        ok = np.isfinite(dist)
        if ok.sum() < 6:
            break
        n = tgt_normals[idx[ok]]
        residual = ((q[ok] - tgt[idx[ok]]) * n).sum(axis=1)
        scale = 1.4826 * np.median(np.abs(residual - np.median(residual)))
        k = 1.345 * max(scale, 1e-4)
        weights = np.minimum(1.0, k / np.maximum(np.abs(residual), 1e-12))
        H, g = point_to_plane_system(q[ok], n, residual, weights, centre, radius)
        B = np.eye(6) if basis is None else basis
        if B.shape[1] == 0:
            break
        Hb = B.T @ H @ B
        x = -B @ np.linalg.lstsq(Hb, B.T @ g, rcond=None)[0]
        T = twist_transform(x, centre, radius) @ T
        if np.linalg.norm(x) < 1e-6:
            break
    return T


def correction_size(T: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    """(mm the correction moves `centre`, rotation angle in degrees)."""
    return float(np.linalg.norm(T[:3, :3] @ centre + T[:3, 3] - centre) * 1000), rotation_angle_deg(T[:3, :3])


def pair_agreement(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    cam_a: str,
    cam_b: str,
    max_distance: float,
    min_overlap: int = 50,
    min_constraint: float = 0.1,
) -> PairAgreement:
    """Agreement of one view's cloud (source, a) with its neighbour's (target, b).

    The correction is solved only in the directions the overlap constrains
    (see observable_basis); min_constraint=0 gives plain robust 6-dof ICP."""
    nan = float("nan")
    if len(source.points) == 0 or len(target.points) == 0:
        return PairAgreement(cam_a, cam_b, 0, nan, nan, nan, nan, 0.0)
    src_pts = np.asarray(source.points)  # (N_a, 3)
    tgt_pts = np.asarray(target.points)  # (N_b, 3)
    tgt_normals = np.asarray(target.normals)  # (N_b, 3)
    tree = cKDTree(tgt_pts)
    nn, idx = tree.query(src_pts, k=1, distance_upper_bound=max_distance)
    overlap = np.isfinite(nn)  # a neighbour within max_distance
    n_overlap = int(overlap.sum())
    if n_overlap < min_overlap:
        return PairAgreement(cam_a, cam_b, n_overlap, nan, nan, nan, nan, 0.0)
    over = src_pts[overlap]  # (K, 3)
    normals = tgt_normals[idx[overlap]]  # (K, 3)
    off_plane = ((over - tgt_pts[idx[overlap]]) * normals).sum(axis=1)
    centre = over.mean(axis=0)
    radius = float(np.sqrt(((over - centre) ** 2).sum(axis=1).mean()))
    H, _ = point_to_plane_system(over, normals, off_plane, np.ones(n_overlap), centre, radius)
    keep, drop = observable_basis(H, min_constraint)
    T = robust_point_to_plane_icp(src_pts, tree, tgt_pts, tgt_normals, max_distance, centre, radius, keep)
    T_full = robust_point_to_plane_icp(src_pts, tree, tgt_pts, tgt_normals, max_distance, centre, radius, None)
    # after ICP: RMS point-to-plane residual of the correspondences
    moved_pts = src_pts @ T[:3, :3].T + T[:3, 3]
    nn_after, idx_after = tree.query(moved_pts, k=1, distance_upper_bound=max_distance)
    used = np.isfinite(nn_after)
    residual = ((moved_pts[used] - tgt_pts[idx_after[used]]) * tgt_normals[idx_after[used]]).sum(1)
    mm, deg = correction_size(T, centre)
    full_mm, full_deg = correction_size(T_full, centre)
    return PairAgreement(
        cam_a=cam_a,
        cam_b=cam_b,
        overlap_points=n_overlap,
        median_distance_mm=float(np.median(np.abs(off_plane)) * 1000),
        icp_rmse_mm=float(np.sqrt(np.mean(residual**2)) * 1000) if used.any() else nan,
        correction_rotation_deg=deg,
        correction_translation_mm=mm,
        fitness=float(used.mean()),
        correction=T.copy(),
        observable_rotation_deg=deg,
        observable_translation_mm=mm,
        full_rotation_deg=full_deg,
        full_translation_mm=full_mm,
        unobservable=describe_directions(drop),
    )


def check_calibration(
    points_per_view: list[np.ndarray],
    names: list[str],
    camera_centers,
    max_distance: float = 0.05,
    voxel_size: float = 0.02,
    pairs: list[tuple[int, int]] | None = None,
    min_constraint: float = 0.1,
) -> list[PairAgreement]:
    """ICP agreement of each neighbouring pair of views' world clouds (N_c, 3).

    Pairs come from `neighbour_pairs(camera_centers)` unless given. For each
    pair (a, b), a's cloud is registered onto b's (robust point-to-plane ICP in
    world coordinates, from identity, correspondences up to max_distance metres),
    solving only the directions the overlap constrains (see pair_agreement).
    For a static scene, pass each camera's points of several frames together:
    more points beat the depth noise.
    """
    if len(points_per_view) != len(names):
        raise ValueError(f"check_calibration: {len(points_per_view)} point clouds but {len(names)} names")
    if pairs is None:
        pairs = neighbour_pairs(camera_centers)
    clouds = [_view_cloud(p, voxel_size, n) for p, n in zip(points_per_view, names)]
    return [pair_agreement(clouds[a], clouds[b], names[a], names[b], max_distance, min_constraint=min_constraint)
            for a, b in pairs]


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
