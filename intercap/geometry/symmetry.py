"""Rotational symmetries of a rigid object's mesh (discrete n-fold and continuous), found
by testing candidate axes on surface samples; symmetry-aware rotation errors."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from intercap.geometry.surfaces import TriangleSurface, sample_surface

SYMMETRY_TOLERANCE = 0.01  # max surface deviation under a symmetry, as a fraction of the bbox diagonal


SYMMETRY_ORDERS = (8, 6, 5, 4, 3, 2)  # n-fold rotations tried about each candidate axis


CONTINUOUS_TEST_ANGLES_DEG = (23.0, 61.0, 137.0)  # not multiples of 360/n for the orders above


def rotation_angle_deg(Ra, Rb):
    """Geodesic angle (deg) between rotations (..., 3, 3); the chord form stays accurate near 0."""
    chord = np.linalg.norm(np.asarray(Ra) - np.asarray(Rb), axis=(-2, -1))  # = 2*sqrt(2)*sin(theta/2)
    return np.degrees(2.0 * np.arcsin(np.clip(chord / (2.0 * math.sqrt(2.0)), 0.0, 1.0)))


def axis_angle_matrix(axis, angle_rad):
    """Rotation matrix (3, 3) by `angle_rad` about `axis` (any length)."""
    a = np.asarray(axis, np.float64)
    return Rotation.from_rotvec(a / np.linalg.norm(a) * angle_rad).as_matrix()


@dataclass
class ObjectSymmetry:
    """Rotational symmetries of the object mesh, about axes through its surface centroid.

    rotations: the finite group found (G, 3, 3), identity first;
    continuous_axes: axes (in object coordinates) with symmetry under every angle.
    """

    rotations: np.ndarray
    continuous_axes: list
    description: str

    @property
    def is_symmetric(self) -> bool:
        return len(self.rotations) > 1 or len(self.continuous_axes) > 0


def surface_moments(vertices, faces):
    """Area-weighted surface centroid (3,) and covariance (3, 3), exact per triangle."""
    tri = vertices[faces]  # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    centroid = (area[:, None] * tri.mean(1)).sum(0) / area.sum()
    x = tri - centroid
    s = x.sum(1)
    second = np.einsum("f,fkij->ij", area / 12.0, x[:, :, :, None] * x[:, :, None, :])
    second += np.einsum("f,fi,fj->ij", area / 12.0, s, s)
    return centroid, second / area.sum()


def _group_closure(generators, limit: int = 120):
    """All products of the generator rotations (a finite rotation group), identity first."""
    group = [np.eye(3)]
    frontier = [np.eye(3)]
    while frontier and len(group) < limit:
        nxt = []
        for g in frontier:
            for h in generators:
                m = h @ g
                if all(np.abs(m - e).max() > 1e-6 for e in group):
                    group.append(m)
                    nxt.append(m)
        frontier = nxt
    return np.stack(group)


def detect_symmetry(mesh: trimesh.Trimesh, n_samples: int = 2000, seed: int = 0,
                    tolerance: float = SYMMETRY_TOLERANCE) -> ObjectSymmetry:
    """Rotation symmetries of a mesh about its principal axes (and the object frame's x, y, z).

    A rotation about an axis through the surface centroid is a symmetry when the
    rotated surface samples all lie on the original surface within
    ``tolerance`` x bbox diagonal (a point-to-surface test, so the mesh's
    triangulation does not have to be symmetric). Each axis is tried for
    continuous symmetry (three unrelated angles), then for n-fold symmetry.
    """
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    centroid, cov = surface_moments(v, f)
    _, eigvec = np.linalg.eigh(cov)
    candidates = []
    for axis in list(eigvec.T) + list(np.eye(3)):
        if all(abs(axis @ c) < 0.999 for c in candidates):
            candidates.append(axis / np.linalg.norm(axis))
    surf = TriangleSurface(v, f)
    pts = sample_surface(v, f, n_samples, np.random.default_rng(seed)) - centroid
    tol = tolerance * float(np.linalg.norm(v.max(0) - v.min(0)))

    def maps_onto_itself(R):  # a cheap screen on a few samples first: most rotations fail there
        if surf.closest(pts[:64] @ R.T + centroid)[0].max() > tol:
            return False
        return surf.closest(pts @ R.T + centroid)[0].max() <= tol

    generators, continuous, parts = [], [], []
    for axis in candidates:
        if all(maps_onto_itself(axis_angle_matrix(axis, math.radians(a))) for a in CONTINUOUS_TEST_ANGLES_DEG):
            continuous.append(axis)
            parts.append(f"continuous about {np.round(axis, 3).tolist()}")
            continue
        for n in SYMMETRY_ORDERS:
            R = axis_angle_matrix(axis, 2 * math.pi / n)
            if maps_onto_itself(R):
                generators.append(R)
                parts.append(f"{n}-fold about {np.round(axis, 3).tolist()}")
                break
    rotations = _group_closure(generators) if generators else np.eye(3)[None]
    desc = ("symmetric: " + "; ".join(parts) + f" (finite group of {len(rotations)})") if parts else "not symmetric"
    return ObjectSymmetry(rotations, continuous, desc)


def mesh_symmetry(mesh: trimesh.Trimesh) -> tuple[ObjectSymmetry, np.ndarray]:
    """The mesh's rotational symmetry and the surface centroid (3,) its axes pass through."""
    centre, _ = surface_moments(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces))
    return detect_symmetry(mesh), centre


def nearest_equivalent_rotation(R, reference, sym: ObjectSymmetry) -> np.ndarray:
    """Of the rotations R S that look the same (S in the object's symmetry: each element of the
    finite group, followed by the best turn about a continuous axis), the one nearest to
    `reference` (3, 3). The turn about axis a maximises trace(Q^T Rot(a, angle)), Q = (R S)^T reference."""
    R, reference = np.asarray(R, np.float64), np.asarray(reference, np.float64)
    if len(sym.continuous_axes) >= 2:  # sphere-like: every orientation is the same
        return reference.copy()
    best, best_angle = R, np.inf
    for S in sym.rotations:
        candidate = R @ S
        if sym.continuous_axes:
            a = np.asarray(sym.continuous_axes[0], np.float64)
            Q = candidate.T @ reference
            w = np.array([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]])  # trace([a]x^T Q) = a . w
            candidate = candidate @ axis_angle_matrix(a, math.atan2(a @ w, np.trace(Q) - a @ Q @ a))
        angle = float(rotation_angle_deg(candidate, reference))
        if angle < best_angle:
            best, best_angle = candidate, angle
    return best


def equivalent_pose(R, t, reference, sym: ObjectSymmetry, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The object->world pose that looks as (R, t) does, its rotation nearest `reference`
    (`nearest_equivalent_rotation`; the symmetry's axes pass through `centre`)."""
    nearest = nearest_equivalent_rotation(R, reference, sym)
    return nearest, np.asarray(t, np.float64) + np.asarray(R, np.float64) @ centre - nearest @ centre


def unwrap_symmetry(R: np.ndarray, t: np.ndarray, valid: np.ndarray, sym: ObjectSymmetry, centre: np.ndarray):
    """Per-frame poses (T, 3, 3), (T, 3) of a symmetric object, each valid one replaced by its
    look-alike nearest in rotation to the previous valid frame's (`equivalent_pose`): a tracker may
    pick any of them frame by frame, and nothing downstream should see a box turn 180 degrees
    between frames or a cup spin about its axis. Unchanged (the same arrays) when not symmetric."""
    if not sym.is_symmetric:
        return R, t
    R, t = np.array(R, np.float64), np.array(t, np.float64)
    previous = None
    for i in np.flatnonzero(valid):
        if previous is not None:
            R[i], t[i] = equivalent_pose(R[i], t[i], previous, sym, centre)
        previous = R[i]
    return R, t


def symmetric_rotation_error_deg(R_est, R_gt, sym: ObjectSymmetry):
    """Rotation error (T,) in degrees minimised over the object's symmetry group.

    Poses R and R @ S look the same for every symmetry S, so the error is
    min_S angle(R_est^T R_gt S). About a continuous axis a the minimum is the
    angle between a and (R_est^T R_gt) a (or -a when a 2-fold flip reverses a).
    """
    if len(sym.continuous_axes) >= 2:  # sphere-like: every orientation is the same
        return np.zeros(len(R_est))
    Q = np.einsum("tji,tjk->tik", R_est, R_gt)  # (T, 3, 3) R_est^T R_gt
    if sym.continuous_axes:
        a = sym.continuous_axes[0]
        cos = np.einsum("tij,j,i->t", Q, a, a)
        if any(a @ S @ a < -0.5 for S in sym.rotations):
            cos = np.abs(cos)
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    QS = np.einsum("tij,gjk->tgik", Q, sym.rotations)  # (T, G, 3, 3)
    return rotation_angle_deg(QS, np.eye(3)).min(1)
