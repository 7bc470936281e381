"""Fixed supports that carry the body besides the floor: a seat, a table leant on, a bar gripped.

A support is a mesh in world coordinates (session.yaml `supports:`, or the object when it is
marked static or does not move). A body point touches it when it lies within `reach` of the
surface outside it or at most `depth` inside it; it is then pushed along the surface normal
at its closest point, within a friction cone (dynamics.contact_forces). Joints that carry a
contact (the contact's bone lies below them in the tree) feed the joint-torque prior.
"""
from __future__ import annotations

import numpy as np
import trimesh


def support_contacts(meshes: list[trimesh.Trimesh], points: np.ndarray, reach_m,
                     depth_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(active (T, S) bool, normals (T, S, 3), support index (T, S), -1 where none) of body points
    (T, S, 3) against the nearest of the support meshes, reach_m a number or one per point (S,);
    normals point out of the support."""
    T, S = points.shape[:2]
    flat = np.asarray(points, np.float64).reshape(-1, 3)
    finite = np.isfinite(flat).all(1)
    best_gap = np.full(len(flat), np.inf)
    normals = np.zeros((len(flat), 3))
    which = np.full(len(flat), -1)
    for k, mesh in enumerate(meshes):
        closest, tri = closest_points(mesh, flat[finite])
        distance = np.linalg.norm(flat[finite] - closest, axis=1)
        n = mesh.face_normals[tri]
        side = np.einsum("ij,ij->i", flat[finite] - closest, n)
        if not mesh.is_watertight:  # no inside: the normal faces the point
            n = n * np.where(side < 0, -1.0, 1.0)[:, None]
            side = np.abs(side)
        gap = np.where(side >= 0, distance, -distance)
        nearer = np.abs(gap) < np.abs(best_gap[finite])
        idx = np.flatnonzero(finite)[nearer]
        best_gap[idx], normals[idx], which[idx] = gap[nearer], n[nearer], k
    active = (best_gap.reshape(T, S) < reach_m) & (best_gap.reshape(T, S) > -depth_m)
    which = which.reshape(T, S)
    which[~active] = -1
    return active, normals.reshape(T, S, 3), which


def closest_points(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(closest surface points (N, 3), their triangle ids (N,)) of points (N, 3) on a mesh (open3d's ray-casting scene)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    answer = scene.compute_closest_points(o3d.core.Tensor(np.asarray(points, np.float32)))
    return answer["points"].numpy().astype(np.float64), answer["primitive_ids"].numpy().astype(np.int64)


def is_static(R: np.ndarray, t: np.ndarray, valid: np.ndarray, max_shift_m: float, max_turn_deg: float,
              min_tracked: float = 0.5) -> bool:
    """The tracked object never moves: tracked in at least `min_tracked` of the frames, its
    origin within max_shift_m and its orientation within max_turn_deg of their medians."""
    valid = np.asarray(valid, bool)
    if valid.mean() < min_tracked:
        return False
    t_med = np.median(t[valid], axis=0)
    if np.linalg.norm(t[valid] - t_med, axis=1).max() > max_shift_m:
        return False
    R_ref = R[valid][len(R[valid]) // 2]
    cos = (np.einsum("tij,ij->t", R[valid], R_ref) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max()) <= max_turn_deg


def carried_by(parents: np.ndarray, joints: np.ndarray, bones: np.ndarray) -> np.ndarray:
    """(J, N) bool: joint bone joints[j] is an ancestor of (or is) bones[n] in the tree parents (root -1)."""
    parents = np.asarray(parents)
    out = np.zeros((len(joints), len(bones)), bool)
    index = {int(j): k for k, j in enumerate(joints)}
    for n, b in enumerate(np.asarray(bones).ravel()):
        b = int(b)
        while b >= 0:
            if b in index:
                out[index[b], n] = True
            b = int(parents[b])
    return out
