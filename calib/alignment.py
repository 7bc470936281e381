"""Calibration check: do neighbouring cameras' point clouds agree?

Each camera's depth, back-projected with its calibration, gives a world point
cloud. Where two neighbouring views see the same surfaces, a good calibration
makes the clouds coincide. Point-to-plane ICP from one view onto the other
(frame by frame: a moving person matches only itself), started at identity,
measures the rigid correction that would make them agree, but only in the
directions the overlap constrains, with its uncertainty: a pair is flagged
only when that correction is both large and many times its standard deviation.
Points are matched only where both views' normals (each turned to its own
camera) agree: two cameras far apart see two sides of an arm or a box, whose
nearest points are close but are not one surface (tools/bench_calibration_check);
and only where the target view saw the surface under the point: not at or beyond
the edge of what it covers (an image border, the shadow a table or a shelf casts
on the floor), where every offset leans outward and an exact rig reads as drifted.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
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
    blocks: the overlap's (frame, block) clusters, the sandwich's sample size; judged: enough of
    them (min_blocks) for the correction to be taken as evidence at all;
    translation_sigma_mm / rotation_sigma_deg: standard deviations of the observable
    correction along itself (cluster-robust, see pair_agreement); observable_dof: how
    many of the six directions the overlap constrains; significance: Mahalanobis size
    of the correction (sigmas); flagged: clear evidence of drift;
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
    translation_sigma_mm: float = float("nan")
    rotation_sigma_deg: float = float("nan")
    observable_dof: int = 0
    significance: float = float("nan")
    flagged: bool = False
    blocks: int = 0
    judged: bool = False
    agreement_gain_pct: float = float("nan")


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




def voxel_average(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """(N, 3) finite points -> one averaged point per occupied voxel (less noise, even density).

    The voxels are cells of one grid fixed in the world (corners at multiples of voxel_size), the
    same for every view: depth noise thicker than a voxel splits a surface into layers of averages,
    and on two grids offset from each other (a grid from each cloud's own bounds) the two views'
    layers lie at different heights, which at high resolution reads as an offset of several mm."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if voxel_size <= 0 or len(pts) == 0:
        return pts
    cells = np.floor(pts / voxel_size).astype(np.int64)
    _, cell_of_point, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    cell_of_point = cell_of_point.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, cell_of_point, pts)
    return sums / counts[:, None]


# A point on the edge of what its view covers: its neighbours' centroid lies off it by this share of their spread.
EDGE_OFFSET = 0.55
# The farthest a matched point may lie from the target's sample along the sample's tangent plane, as a share
# of the radius the planes are fitted over (3 cm at the check's 10 cm): the plane is the surface near its sample.
LATERAL_REACH = 0.3


def local_planes(points: np.ndarray, radius: float, neighbours: int = 16, max_flatness: float = 0.08,
                 max_edge_offset: float = EDGE_OFFSET):
    """Tangent planes of a cloud (N, 3): the points, unit normals (N, 3) from the PCA
    of their `neighbours` nearest points within `radius`, (N,) ok where at least 6
    neighbours were found and the patch is flat (smallest / total variance at most
    max_flatness: edges, corners and thin parts give no trustworthy normal), and (N,) edge
    where the point lies on the edge of what the cloud covers (an image border, an occlusion's
    shadow, a surface's outline): its neighbours' centroid lies off it, in their plane, by more
    than max_edge_offset x their in-plane spread (on a regular sampling, 16 neighbours: about 0.55 on
    its outermost row, 0 inside; depth noise spreads both), or fewer than 6 neighbours."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 6:
        return pts, np.zeros_like(pts), np.zeros(len(pts), bool), np.ones(len(pts), bool)
    k = min(neighbours, len(pts))
    dist, idx = cKDTree(pts).query(pts, k=k, distance_upper_bound=radius)
    found = np.isfinite(dist)  # (N, k)
    idx = np.where(found, idx, np.arange(len(pts))[:, None])
    nb = pts[idx]  # (N, k, 3)
    w = found[..., None].astype(np.float64)
    count = np.maximum(w.sum(axis=1), 1.0)  # (N, 1)
    mean = (nb * w).sum(axis=1) / count
    d = (nb - mean[:, None]) * w
    cov = np.einsum("nki,nkj->nij", d, d) / count[..., None]
    ev, vec = np.linalg.eigh(cov)  # ascending
    normals = vec[..., 0]
    flat = ev[:, 0] / np.maximum(ev.sum(axis=1), 1e-18)
    enough = found.sum(axis=1) >= 6
    ok = enough & (flat <= max_flatness)
    off = mean - pts
    off -= (off * normals).sum(axis=1, keepdims=True) * normals  # (N, 3) in the tangent plane
    spread = np.sqrt(np.maximum(ev[:, 1] + ev[:, 2], 1e-18))
    edge = ~enough | (np.linalg.norm(off, axis=1) > max_edge_offset * spread)
    return pts, normals, ok, edge


MIN_NORMAL_COS = math.cos(math.radians(45.0))


@dataclass
class _ViewFrame:
    """One view's points of one frame, with its tangent planes (as the target of a pair)."""

    points: np.ndarray  # (N, 3) voxel-averaged
    point_normals: np.ndarray  # (N, 3) unit normals facing the view's camera, 0 where untrustworthy
    planes: np.ndarray  # (M, 3) points with a trustworthy normal
    normals: np.ndarray  # (M, 3) their normals, facing the camera
    tree: cKDTree | None
    point_sigma: np.ndarray  # (N,) expected depth noise of the points (metres)
    plane_sigma: np.ndarray  # (M,)
    plane_edge: np.ndarray  # (M,) on the edge of what the view covers (`local_planes`)
    reach: float  # farthest (m) a matched point may lie from a plane's sample along the plane


def depth_noise(distance: np.ndarray) -> np.ndarray:
    """Expected depth noise (metres) at `distance` from the camera: a time-of-flight sensor's
    1.5 mm + 1.5 mm/m^2 * d^2 (Azure Kinect-like). Only its shape matters: it weighs near
    points above far ones, whose noise is a thick slab that nearest-neighbour matching biases."""
    return 0.0015 + 0.0015 * np.asarray(distance) ** 2


def _view_frame(points: np.ndarray, voxel_size: float, plane_radius: float, name: str, centre) -> _ViewFrame:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"check_calibration: points of view {name!r} must be (N, 3), got {pts.shape}")
    pts = voxel_average(pts, voxel_size)
    q, n, ok, edge = local_planes(pts, plane_radius)
    to_camera = np.asarray(centre, float) - q
    n = np.where(((n * to_camera).sum(axis=1) < 0)[:, None], -n, n) * ok[:, None]
    sigma = depth_noise(np.linalg.norm(to_camera, axis=1))
    return _ViewFrame(pts, n, q[ok], n[ok], cKDTree(q[ok]) if ok.any() else None, sigma, sigma[ok], edge[ok],
                      LATERAL_REACH * plane_radius)


def _correspondences(src: list[_ViewFrame], tgt: list[_ViewFrame], T: np.ndarray, max_distance: float,
                     min_normal_cos: float = MIN_NORMAL_COS, keep_edges: bool = False):
    """Point-to-plane correspondences of the moved source points with the target planes, frame by
    frame (a moving person only matches itself in the same instant): moved points (K, 3),
    normals (K, 3), signed residuals (K,), frame index (K,), expected residual sigma (K,).
    Both views' normals face their own camera, so a surface both see has normals that agree;
    pairs whose normals differ by more than acos(min_normal_cos) are two sides of a thin part
    (an arm, a box wall) seen from two cameras, whose distance says nothing about calibration.
    A point whose nearest target sample lies on the edge of what the target view covers, or
    farther from it along its plane than the target's `reach`, is where the target saw nothing
    (beyond an image border, in an occlusion's shadow: one view sees floor the other does not):
    its offset from the last plane the target saw is no residual, and all such offsets lean the
    same way (outward), which on an exact rig reads as a shift of several millimetres; those are left
    out unless `keep_edges` (one of the refinement's two solves, `refine_rig`)."""
    qs, ns, rs, fs, ss = [], [], [], [], []
    for f, (s, t) in enumerate(zip(src, tgt)):
        if t.tree is None or len(s.points) == 0:
            continue
        q = s.points @ T[:3, :3].T + T[:3, 3]
        d, i = t.tree.query(q, k=1, distance_upper_bound=max_distance)
        hit = np.isfinite(d)
        hit[hit] = (s.point_normals[hit] @ T[:3, :3].T * t.normals[i[hit]]).sum(axis=1) >= min_normal_cos
        if not keep_edges:
            hit[hit] = ~t.plane_edge[i[hit]]
            offset = q[hit] - t.planes[i[hit]]
            along_normal = (offset * t.normals[i[hit]]).sum(axis=1)
            hit[hit] = np.linalg.norm(offset - along_normal[:, None] * t.normals[i[hit]], axis=1) <= t.reach
        n = t.normals[i[hit]]
        r = ((q[hit] - t.planes[i[hit]]) * n).sum(axis=1)
        qs.append(q[hit]), ns.append(n), rs.append(r), fs.append(np.full(len(r), f))
        ss.append(np.hypot(s.point_sigma[hit], t.plane_sigma[i[hit]]))
    if not qs:
        z = np.zeros((0, 3))
        return z, z, np.zeros(0), np.zeros(0, int), np.ones(0)
    return np.concatenate(qs), np.concatenate(ns), np.concatenate(rs), np.concatenate(fs), np.concatenate(ss)


def noise_weights(residual: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """(N,) IRLS weights: Huber on the residuals in units of their expected noise, times 1/sigma^2."""
    return huber_weights(residual / sigma) / sigma**2


def capped_cost(residual: np.ndarray, sigma: np.ndarray, cap: float = 3.0) -> float:
    """Mean over matches of (residual / sigma)^2, each capped at cap^2: how well two views agree,
    in units of their expected noise, without letting a few far matches decide."""
    return float(np.minimum((residual / sigma) ** 2, cap * cap).mean()) if len(residual) else float("nan")


def agreement_gain(before: tuple, after: tuple, x: np.ndarray, centre: np.ndarray, radius: float,
                   min_sensitivity: float = 0.3) -> float:
    """How much a correction x (scaled twist, 6) makes two views agree better: the fall of the
    `capped_cost` of the matches it moves (|J x / |x|| above min_sensitivity: a floor does not move
    under a slide along it), from the matches `before` (at the calibrated pose) to those `after`
    (under the correction), as a share of the former. Each is (q, n, r, frames, sigma)."""
    unit = x / max(float(np.linalg.norm(x)), 1e-12)
    costs = []
    for q, n, r, _, sg in (before, after):
        moved = np.abs(np.hstack([np.cross(q - centre, n) / radius, n]) @ unit) > min_sensitivity
        costs.append(capped_cost(r[moved], sg[moved]) if moved.any() else float("nan"))
    return (costs[0] - costs[1]) / costs[0] if np.isfinite(costs).all() and costs[0] > 0 else 0.0


def huber_weights(residual: np.ndarray) -> np.ndarray:
    """(N,) Huber IRLS weights of residuals (N,), scale from their MAD."""
    scale = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    k = 1.345 * max(scale, 1e-4)
    return np.minimum(1.0, k / np.maximum(np.abs(residual), 1e-12))


def block_labels(points: np.ndarray, frames: np.ndarray, block_size: float) -> np.ndarray:
    """(N,) label of the (frame, cubic cell of side block_size) holding each point (N, 3)."""
    cells = np.column_stack([frames, np.floor(points / block_size).astype(np.int64)])
    _, labels = np.unique(cells, axis=0, return_inverse=True)
    return labels.reshape(-1)


def correction_size(T: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    """(mm the correction moves `centre`, rotation angle in degrees)."""
    return float(np.linalg.norm(T[:3, :3] @ centre + T[:3, 3] - centre) * 1000), rotation_angle_deg(T[:3, :3])


def _sigma_along(cov3: np.ndarray, v: np.ndarray) -> float:
    """Standard deviation of a (3, 3) covariance along v (3,); the largest one when v is ~0."""
    norm = np.linalg.norm(v)
    if norm < 1e-12:
        return float(np.sqrt(max(np.linalg.eigvalsh(cov3).max(), 0.0)))
    u = v / norm
    return float(np.sqrt(max(u @ cov3 @ u, 0.0)))


def view_frames(pool, per_frame: list, names: list[str], centers: np.ndarray, voxel_size: float,
                plane_radius: float) -> list[list[_ViewFrame]]:
    """Per view, its frames' points with their tangent planes (`_view_frame`), built in `pool`'s threads."""
    futures = [[pool.submit(_view_frame, p, voxel_size, plane_radius, name, centre) for p in view]
               for view, name, centre in zip(per_frame, names, centers)]
    return [[f.result() for f in view] for view in futures]


def observable_icp(source: list[_ViewFrame], target: list[_ViewFrame], matches: tuple, keep: np.ndarray,
                   centre: np.ndarray, radius: float, max_distance: float, iterations: int, min_overlap: int,
                   goes_on):
    """(T (4, 4), the correspondences (q, n, r, frames, sigma) under T) of robust point-to-plane ICP in the
    observable directions `keep`, from identity and its correspondences `matches`; None when the overlap
    falls below min_overlap.

    One Gauss-Newton step from the calibrated pose measures a drift within max_distance directly.
    Re-associating nearest neighbours on noisy slabs (depth noise of ~1-3 cm at 3-4 m) walks by
    several mm on an exact calibration, so further ICP iterations only size a drift whose first
    step is already evidence: `goes_on(T)` of the first step's correction (`first_step_gate`)."""
    q, n, r, fr, sg = matches
    T = np.eye(4)
    for it in range(iterations):
        w = noise_weights(r, sg)
        H, g = point_to_plane_system(q, n, r, w, centre, radius)
        if keep.shape[1] == 0:
            break
        x = -keep @ np.linalg.solve(keep.T @ H @ keep, keep.T @ g)
        step = np.linalg.norm(x)
        if step > 0.3 * max_distance:  # a trust region: never jump past the correspondences that hold it
            x *= 0.3 * max_distance / step
        T = twist_transform(x, centre, radius) @ T
        q, n, r, fr, sg = _correspondences(source, target, T, max_distance)
        if len(r) < min_overlap:
            return None
        if step < 1e-5 or (it == 0 and not goes_on(T)):
            break
    return T, (q, n, r, fr, sg)


def first_step_gate(cov: np.ndarray, keep: np.ndarray, centre: np.ndarray, radius: float, refine_mm: float,
                    refine_deg: float, k_sigma: float):
    """When ICP goes on past its first step (`observable_icp`): the step's correction T moves the
    overlap's centre more than refine_mm (or turns more than refine_deg), or by k_sigma standard
    deviations of itself, `cov` (6, 6) being the step's covariance (the sandwich at the calibrated
    pose). On noisy depth a first step falls short of a drift (a camera turned 0.5 deg reads 0.3 deg
    at 30 sigma, just under the size gate), while on an exact rig it is within a few sigma."""
    def goes_on(T: np.ndarray) -> bool:
        mm, deg = correction_size(T, centre)
        x = keep @ keep.T @ scaled_twist(T, centre, radius)
        sigma_mm = _sigma_along(cov[3:, 3:], x[3:]) * 1000
        sigma_deg = math.degrees(_sigma_along(cov[:3, :3], x[:3]) / radius)
        return mm > refine_mm or deg > refine_deg or mm > k_sigma * sigma_mm or deg > k_sigma * sigma_deg

    return goes_on


def sandwich_covariance(q, n, r, fr, w, keep: np.ndarray, centre: np.ndarray, radius: float,
                        block_size: float) -> tuple[np.ndarray, int]:
    """(cov (6, 6) of the observable correction in scaled-twist units (metres), number of blocks):
    the cluster-robust sandwich over (frame, block of block_size metres) clusters."""
    J = np.hstack([np.cross(q - centre, n) / radius, n])  # (K, 6)
    A = keep.T @ ((J * w[:, None]).T @ J) @ keep  # (k, k)
    labels = block_labels(q, fr, block_size)
    blocks = int(labels.max()) + 1
    grad = np.zeros((blocks, 6))
    np.add.at(grad, labels, J * (w * r)[:, None])
    grad = grad @ keep  # (B, k)
    meat = grad.T @ grad * blocks / max(blocks - 1, 1)
    A_inv = np.linalg.inv(A) if keep.shape[1] else np.zeros((0, 0))
    return keep @ A_inv @ meat @ A_inv @ keep.T, blocks


def pair_agreement(
    source: list[_ViewFrame],
    target: list[_ViewFrame],
    cam_a: str,
    cam_b: str,
    max_distance: float,
    min_overlap: int = 50,
    min_constraint: float = 0.001,
    block_size: float = 0.25,
    k_sigma: float = 4.0,
    min_mm: float = 6.0,
    min_deg: float = 0.3,
    iterations: int = 15,
    bias_fraction: float = 0.0,
    min_blocks: int = 100,
    min_agreement_gain: float = 0.1,
) -> PairAgreement:
    """Agreement of view a's points (one (N, 3) array per frame) with view b's planes (same frames).

    Robust point-to-plane ICP from identity, each frame matched with its own frame, iterated past its
    first step only when that step is evidence (`first_step_gate`). The correction is solved only in
    the directions the overlap constrains (eigenvalues of the normal matrix at least min_constraint x
    the largest; a floor alone leaves its two in-plane translations and the rotation about its normal
    free), and its uncertainty is the
    cluster-robust ("sandwich") covariance over blocks of block_size metres per frame, since
    neighbouring residuals share sampling and sensor errors. Flagged only on clear evidence:
    correction above k_sigma of its standard deviation AND above min_mm (or both for min_deg), and
    only when the overlap spans at least min_blocks clusters: a view that shares a few patches of
    the person with its neighbour (a camera close in, the floor out of its image) gives a sandwich
    over too few clusters and the person's systematic depth errors (grazing sides), which pass
    4 sigma on an exact rig (tests/calib: 23-36 clusters against ~1000 with the floor). And only when
    the correction makes the views agree better where it moves them (`agreement_gain` at least
    min_agreement_gain): where only a few surfaces hold a direction (a person seen by cameras 45 degrees
    apart holds the turn about the vertical), their systematic depth errors walk ICP along it by a
    degree or more at many sigma, yet the views agree no better there (-10 % on that exact rig, 18-78 %
    on bumped ones, 71 % for a camera shifted 5 cm sideways: tools/bench_calibration_check)."""
    nan = float("nan")
    empty = PairAgreement(cam_a, cam_b, 0, nan, nan, nan, nan, 0.0)
    q, n, r, fr, sg = _correspondences(source, target, np.eye(4), max_distance)
    n_source = sum(len(s.points) for s in source)
    n_overlap = int(len(r))
    if n_overlap < min_overlap:
        empty.overlap_points = n_overlap
        return empty
    centre = q.mean(axis=0)
    radius = max(float(np.sqrt(((q - centre) ** 2).sum(axis=1).mean())), 1e-3)
    H0, _ = point_to_plane_system(q, n, r, noise_weights(r, sg), centre, radius)
    keep, drop = observable_basis(H0, min_constraint)
    median_before = float(np.median(np.abs(r)) * 1000)
    matches_before = (q, n, r, fr, sg)
    # a floor for what the sandwich cannot see: on noisy depth the first step itself is biased by
    # a fraction of the residuals' spread (nearest neighbours within thick slabs of noise)
    floor = bias_fraction * 1.4826 * float(np.median(np.abs(r - np.median(r))))
    refine_mm, refine_deg = max(min_mm, k_sigma * floor * 1000), max(min_deg, math.degrees(k_sigma * floor / radius))

    cov0, _ = sandwich_covariance(q, n, r, fr, noise_weights(r, sg), keep, centre, radius, block_size)
    gate = first_step_gate(cov0, keep, centre, radius, refine_mm, refine_deg, k_sigma)
    icp = observable_icp(source, target, (q, n, r, fr, sg), keep, centre, radius, max_distance, iterations,
                         min_overlap, gate)
    if icp is None:
        return PairAgreement(cam_a, cam_b, n_overlap, median_before, nan, nan, nan, 0.0)
    T, (q, n, r, fr, sg) = icp

    # uncertainty of the observable correction: cluster-robust sandwich over (frame, block)
    w = noise_weights(r, sg)
    cov6, blocks = sandwich_covariance(q, n, r, fr, w, keep, centre, radius, block_size)
    x6 = keep @ keep.T @ scaled_twist(T, centre, radius)
    significance = float(np.sqrt(max(x6 @ np.linalg.pinv(cov6, hermitian=True) @ x6, 0.0))) if keep.shape[1] else 0.0
    # a full 6-dof Gauss-Newton step from here: diagnostic only (it slides along free directions)
    H, g = point_to_plane_system(q, n, r, w, centre, radius)
    x_full = scaled_twist(T, centre, radius) - np.linalg.lstsq(H, g, rcond=None)[0]
    mm, deg = correction_size(T, centre)
    sigma_mm = math.hypot(_sigma_along(cov6[3:, 3:], x6[3:]), floor) * 1000
    sigma_deg = math.degrees(math.hypot(_sigma_along(cov6[:3, :3], x6[:3]), floor) / radius)
    judged = blocks >= min_blocks
    gain = agreement_gain(matches_before, (q, n, r, fr, sg), x6, centre, radius)
    flagged = judged and gain >= min_agreement_gain and bool((mm > min_mm and mm > k_sigma * sigma_mm)
                                                             or (deg > min_deg and deg > k_sigma * sigma_deg))
    return PairAgreement(
        cam_a=cam_a, cam_b=cam_b, overlap_points=n_overlap, median_distance_mm=median_before,
        icp_rmse_mm=float(np.sqrt(np.mean(r**2)) * 1000), correction_rotation_deg=deg, correction_translation_mm=mm,
        fitness=float(len(r) / max(n_source, 1)), correction=T.copy(), observable_rotation_deg=deg,
        observable_translation_mm=mm, full_rotation_deg=float(np.degrees(np.linalg.norm(x_full[:3]) / radius)),
        full_translation_mm=float(np.linalg.norm(x_full[3:]) * 1000), unobservable=describe_directions(drop),
        translation_sigma_mm=sigma_mm, rotation_sigma_deg=sigma_deg, observable_dof=int(keep.shape[1]),
        significance=significance, flagged=flagged, blocks=blocks, judged=judged, agreement_gain_pct=100 * gain,
    )


def check_calibration(
    points_per_view: list,
    names: list[str],
    camera_centers,
    max_distance: float = 0.1,
    voxel_size: float = 0.02,
    pairs: list[tuple[int, int]] | None = None,
    min_constraint: float = 0.001,
    block_size: float = 0.25,
    k_sigma: float = 4.0,
    min_mm: float = 6.0,
    min_deg: float = 0.3,
    plane_radius: float = 0.0,
    iterations: int = 15,
    min_blocks: int = 100,
    min_agreement_gain: float = 0.1,
) -> list[PairAgreement]:
    """Agreement of each neighbouring pair of views (see pair_agreement).

    points_per_view: per view, its world points (N, 3), or a list of such arrays, one per
    synchronised frame (all views the same frames): frames are matched only with themselves,
    so a moving person and object add evidence in every direction they constrain.
    Pairs come from `neighbour_pairs(camera_centers)` unless given."""
    if len(points_per_view) != len(names):
        raise ValueError(f"check_calibration: {len(points_per_view)} point clouds but {len(names)} names")
    per_frame = [[p] if isinstance(p, np.ndarray) else list(p) for p in points_per_view]
    if len({len(p) for p in per_frame}) > 1:
        raise ValueError(f"check_calibration: views have different frame counts {[len(p) for p in per_frame]}")
    if pairs is None:
        pairs = neighbour_pairs(camera_centers)
    plane_radius = plane_radius if plane_radius > 0 else max(5 * voxel_size, 0.10)
    centers = np.asarray(camera_centers, dtype=np.float64).reshape(-1, 3)
    # views x frames, then pairs, in threads: k-d trees, LAPACK and large numpy loops let go of the GIL
    with ThreadPoolExecutor(max(1, min(os.cpu_count() or 1, len(names) * len(per_frame[0])))) as pool:
        frames = view_frames(pool, per_frame, names, centers, voxel_size, plane_radius)
        agreements = [pool.submit(pair_agreement, frames[a], frames[b], names[a], names[b], max_distance,
                                  min_constraint=min_constraint, block_size=block_size, k_sigma=k_sigma,
                                  min_mm=min_mm, min_deg=min_deg, iterations=iterations, min_blocks=min_blocks,
                                  min_agreement_gain=min_agreement_gain)
                       for a, b in pairs]
        return [f.result() for f in agreements]


@dataclass
class RigRefinement:
    """Corrections to every camera's pose that make all views agree (`refine_rig`).

    corrections: (C, 4, 4) world-frame transforms, T_world_from_cam <- correction @ T_world_from_cam;
    moved_mm / turned_deg: (C,) how far each correction moves the clouds' centre, and its angle;
    pairs: ordered view pairs that overlapped; iterations: Gauss-Newton steps taken;
    residual_before_mm / residual_after_mm: weighted RMS point-to-plane residual of all pairs."""

    corrections: np.ndarray
    moved_mm: np.ndarray
    turned_deg: np.ndarray
    pairs: int
    iterations: int
    residual_before_mm: float
    residual_after_mm: float


def geometric_median(x: np.ndarray, iterations: int = 50) -> np.ndarray:
    """The point (D,) nearest to all rows of x (N, D) in summed distance (Weiszfeld's iteration)."""
    m = x.mean(axis=0)
    for _ in range(iterations):
        w = 1.0 / np.maximum(np.linalg.norm(x - m, axis=1), 1e-12)
        m = (w[:, None] * x).sum(axis=0) / w.sum()
    return m


def consensus(x: np.ndarray, k: float = 3.0, floor: float = 1e-3) -> np.ndarray:
    """The centre (D,) of the rows x (N, D) that agree: the mean of those within `k` x the rows'
    median distance (at least `floor`) of their geometric median; one far row is left out."""
    distance = np.linalg.norm(x - geometric_median(x), axis=1)
    return x[distance <= max(k * float(np.median(distance)), floor)].mean(axis=0)


def rig_pair_system(frames: list, T: np.ndarray, pair: tuple[int, int], max_distance: float, min_overlap: int,
                    centre: np.ndarray, radius: float, keep_edges: bool = False):
    """(a, b, H, g, weighted RMS residual) of the ordered view pair (a, b) under the poses' corrections
    T (C, 4, 4), in world coordinates; None when they overlap in fewer than min_overlap points."""
    a, b = pair
    q, n, r, _, sg = _correspondences(frames[a], frames[b], np.linalg.inv(T[b]) @ T[a], max_distance,
                                      keep_edges=keep_edges)
    if len(r) < min_overlap:
        return None
    w = noise_weights(r, sg)
    q, n = q @ T[b][:3, :3].T + T[b][:3, 3], n @ T[b][:3, :3].T  # b's frame of reference -> the world now
    H, g = point_to_plane_system(q, n, r, w, centre, radius)
    return a, b, H, g, float(np.sqrt((w * r * r).sum() / max(w.sum(), 1e-12)))


def rig_agreement(frames: list, T: np.ndarray, pairs: list, max_distance: float, min_overlap: int) -> float:
    """Mean over the ordered view pairs of their matches' `capped_cost` (the check's matches) under the
    poses' corrections T (C, 4, 4): how well the views agree, in units of their depth noise."""
    costs = []
    for a, b in pairs:
        _, _, r, _, sg = _correspondences(frames[a], frames[b], np.linalg.inv(T[b]) @ T[a], max_distance)
        if len(r) >= min_overlap:
            costs.append(capped_cost(r, sg))
    return float(np.mean(costs)) if costs else float("inf")


def rig_normal_equations(systems: list, C: int) -> tuple[np.ndarray, np.ndarray]:
    """(H (6C, 6C), g (6C,)) of all pairs' systems: r moves with +J under a's twist, -J under b's."""
    H = np.zeros((6 * C, 6 * C))
    g = np.zeros(6 * C)
    for a, b, Hp, gp, _ in systems:
        ia, ib = slice(6 * a, 6 * a + 6), slice(6 * b, 6 * b + 6)
        H[ia, ia] += Hp
        H[ib, ib] += Hp
        H[ia, ib] -= Hp
        H[ib, ia] -= Hp
        g[ia] += gp
        g[ib] -= gp
    return H, g


def refine_rig(
    points_per_view: list,
    names: list[str],
    camera_centers,
    max_distance: float = 0.1,
    voxel_size: float = 0.02,
    plane_radius: float = 0.0,
    iterations: int = 10,
    prior: float = 1e-3,
    linear_beyond_m: float = 0.006,
    min_overlap: int = 200,
    tolerance_m: float = 2e-5,
) -> RigRefinement:
    """Correct all cameras' poses at once so their clouds agree (the check only measures pairs).

    points_per_view as in `check_calibration` (per view, one (N, 3) world array per frame). Each
    ordered pair of views gives the check's point-to-plane correspondences, frame by frame, solved once
    with the matches at the edges of what the target view covers and once without; the poses of the
    solve under which the views agree better (`rig_agreement`) are kept: at 320x288 the edges' matches
    help the solve, at 1280x720 they walked the rig 25-39 mm apart (tools/bench_calibration_refine).
    The unknown is one scaled twist per camera about the clouds' centre, solved by Gauss-Newton over all
    pairs together. A prior of `prior` x the largest curvature on each camera's total
    correction keeps the directions the scene hardly constrains where they were (they would walk on
    depth noise; tools/bench_calibration_refine); it grows with the square of a correction's length
    (scaled twist, metres) up to `linear_beyond_m` and linearly beyond, so one camera that needs a
    large correction gets it instead of the error being shared out. Moving every camera together changes no residual,
    so the world frame is chosen: the corrections' `consensus` is none. Errors spread over all
    cameras average out (the mean: the world the fits saw before); one bumped camera of a rig, far
    from the rest, is moved back to the others, which keep their poses."""
    per_frame = [[p] if isinstance(p, np.ndarray) else list(p) for p in points_per_view]
    C = len(per_frame)
    if C != len(names) or len({len(p) for p in per_frame}) > 1:
        raise ValueError(f"refine_rig: {C} views for {len(names)} names, frame counts {[len(p) for p in per_frame]}")
    plane_radius = plane_radius if plane_radius > 0 else max(5 * voxel_size, 0.10)
    centers = np.asarray(camera_centers, dtype=np.float64).reshape(-1, 3)
    workers = max(1, min(os.cpu_count() or 1, C * len(per_frame[0])))
    with ThreadPoolExecutor(workers) as pool:
        frames = view_frames(pool, per_frame, names, centers, voxel_size, plane_radius)
        everything = np.concatenate([f.points for view in frames for f in view] or [np.zeros((1, 3))])
        centre = everything.mean(axis=0)
        radius = max(float(np.sqrt(((everything - centre) ** 2).sum(axis=1).mean())), 1e-3)
        pairs = [(a, b) for a in range(C) for b in range(C) if a != b]

        def solve(keep_edges: bool):
            X = np.zeros((C, 6))  # each camera's total correction, a scaled twist
            T = np.eye(4)[None].repeat(C, axis=0)
            residuals, used, steps = [], 0, 0

            def pair_system(pair):
                return rig_pair_system(frames, T, pair, max_distance, min_overlap, centre, radius, keep_edges)

            for steps in range(1, iterations + 1):
                systems = [s for s in pool.map(pair_system, pairs) if s is not None]
                H, g = rig_normal_equations(systems, C)
                residuals.append(float(np.mean([s[4] for s in systems])) if systems else float("nan"))
                used = len(systems)
                if not systems:
                    break
                damping = prior * max(float(np.linalg.eigvalsh(H).max()), 1e-12)
                # beyond `linear_beyond_m` a correction pays for its length, not its square (reweighted)
                damping = damping * np.repeat(linear_beyond_m / np.maximum(np.linalg.norm(X, axis=1), linear_beyond_m), 6)
                step = -np.linalg.solve(H + np.diag(damping), g + damping * X.reshape(-1)).reshape(C, 6)
                X += step
                T = np.stack([twist_transform(x, centre, radius) for x in X])
                if np.abs(step).max() < tolerance_m:
                    break
            X -= consensus(X)  # the data see no common motion: see the docstring
            T = np.stack([twist_transform(x, centre, radius) for x in X])
            after = [s for s in pool.map(pair_system, pairs) if s is not None]
            return T, used, steps, residuals, after

        # with coverage edges and without: the better agreeing of the two (see the docstring)
        solves = [solve(keep_edges) for keep_edges in (True, False)]
        T, used, steps, residuals, after = min(
            solves, key=lambda s: rig_agreement(frames, s[0], pairs, max_distance, min_overlap))
    moved_turned = np.array([correction_size(t, centre) for t in T]).reshape(C, 2)
    return RigRefinement(corrections=T, moved_mm=moved_turned[:, 0], turned_deg=moved_turned[:, 1], pairs=used,
                         iterations=steps, residual_before_mm=residuals[0] * 1000 if residuals else float("nan"),
                         residual_after_mm=float(np.mean([s[4] for s in after])) * 1000 if after else float("nan"))


def unchecked_cameras(results: list[PairAgreement]) -> list[str]:
    """Cameras none of whose pairs could be judged (no overlap, or too little): the check says
    nothing of their poses, which are used as given."""
    names = dict.fromkeys(n for r in results for n in (r.cam_a, r.cam_b))
    judged = {n for r in results if r.judged for n in (r.cam_a, r.cam_b)}
    return [n for n in names if n not in judged]


def isolated_cameras(results: list[PairAgreement]) -> list[str]:
    """Cameras of a rig of three or more whose depth meets no neighbour's (no point within the check's
    distance in any of their pairs) while other pairs do overlap: every camera of a capture rig sees the
    scene the others see, so such a pose is wrong (inverted, another rig's, in other units), not
    merely unchecked. Greedily the camera in the most such pairs, as `suspect_cameras`."""
    names = dict.fromkeys(n for r in results for n in (r.cam_a, r.cam_b))
    if len(names) < 3 or not any(r.overlap_points > 0 for r in results):
        return []
    empty = [(r.cam_a, r.cam_b) for r in results if r.overlap_points == 0]
    met = {n for r in results if r.overlap_points > 0 for n in (r.cam_a, r.cam_b)}
    isolated = []
    while empty:
        counts: dict[str, int] = {}
        for pair in empty:
            for cam in pair:
                if cam not in met:
                    counts[cam] = counts.get(cam, 0) + 1
        if not counts:
            break
        best = max(counts.values())
        top = sorted(c for c, k in counts.items() if k == best)[0]
        isolated.append(top)
        empty = [pair for pair in empty if top not in pair]
    return isolated


def suspect_cameras(results: list[PairAgreement]) -> list[str]:
    """Cameras that explain the flagged pairs: greedily the camera in the most flagged pairs
    (ties named together, "a or b", when nothing tells them apart), until every flagged pair
    is explained. A drifted camera of a ring flags both its pairs and is named alone."""
    flagged = [(r.cam_a, r.cam_b) for r in results if r.flagged]
    named = []
    while flagged:
        counts: dict[str, int] = {}
        for pair in flagged:
            for cam in pair:
                counts[cam] = counts.get(cam, 0) + 1
        best = max(counts.values())
        top = sorted(c for c, k in counts.items() if k == best)
        if best == 1 and len(top) > 1:  # lone pairs: either camera may have moved
            a, b = flagged[0]
            named.append(f"{a} or {b}")
            flagged = flagged[1:]
            continue
        named.append(" or ".join(top))
        flagged = [p for p in flagged if not set(p) & set(top)]
    return named


def format_agreement(results: list[PairAgreement], warn_mm: float = 6.0, warn_deg: float = 0.3,
                     k_sigma: float = 4.0) -> str:
    """A table a person reads: one row per pair, its observable correction with its standard
    deviation; CHECK CALIBRATION only on clear evidence (pair_agreement's flag)."""
    header = (
        f"{'pair':<24} {'overlap':>8} {'median mm':>10} {'rmse mm':>8} "
        f"{'corr mm':>14} {'corr deg':>14} {'dof':>4}  status"
    )
    lines = [header, "-" * len(header)]
    n_flagged = 0
    for r in results:
        if not np.isfinite(r.median_distance_mm):
            status = "NO OVERLAP"
        elif not r.judged:
            status = f"too little overlap to judge ({r.blocks} blocks)"
        elif r.flagged:
            status = "CHECK CALIBRATION"
            n_flagged += 1
        else:
            status = "ok"
        pair = f"{r.cam_a} -> {r.cam_b}"
        mm = f"{r.correction_translation_mm:.1f}+-{r.translation_sigma_mm:.1f}"
        deg = f"{r.correction_rotation_deg:.2f}+-{r.rotation_sigma_deg:.2f}"
        lines.append(
            f"{pair:<24} {r.overlap_points:>8d} {r.median_distance_mm:>10.1f} {r.icp_rmse_mm:>8.1f} "
            f"{mm:>14} {deg:>14} {r.observable_dof:>4d}  {status}"
        )
    rule = f"above {warn_mm:g} mm or {warn_deg:g} deg and {k_sigma:g} sigma"
    unjudged = sum(np.isfinite(r.median_distance_mm) and not r.judged for r in results)
    unjudged_note = f"; {unjudged} with too little overlap to judge" if unjudged else ""
    if n_flagged:
        lines.append(f"{n_flagged} of {len(results)} pairs flagged ({rule}){unjudged_note}; suspect: "
                     + ", ".join(suspect_cameras(results)))
    else:
        lines.append(f"no pair flagged ({rule}) over {len(results)} pairs{unjudged_note}")
    return "\n".join(lines)
