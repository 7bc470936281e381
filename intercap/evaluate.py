"""Evaluation of a results folder against a session's ground truth (`intercap eval OUT --gt SESSION`).

Reads only the results files named in SESSION_FORMAT.md (``object_poses.npz``,
``body_vertices.npy``, ``body_faces.npy``, ``contact.npy``, ``keypoints3d.npy``);
any subset may exist. Every metric is computed from what both sides have; what
had to be skipped, and why, is listed in ``EvalResult.notes``.

Nothing here assumes the fitted body has the ground truth's topology: bodies are
compared surface to surface (exact point-to-triangle distances), objects by
pose, contact by label, keypoints joint by joint.

Frames the results mark untrusted (NaN) are left out of the means and counted
in a ``*_frames_missing`` metric. Units are in the metric names
(``_mm``, ``_deg``, ``_pct``, ``_mps2``).

Definitions:
- body_surface_mm: per frame, the mean of (samples on the fit -> GT surface) and
  (samples on GT -> fitted surface), averaged over frames.
- keypoint_mpjpe_mm: BODY_25 joints 0..24; hand_keypoint_mm: joints of each hand
  relative to its wrist (25 left, 46 right); NaN joints on either side ignored.
- object_add_mm: mean over mesh vertices of |(R x + t) - (R_gt x + t_gt)|;
  object_adds_mm (symmetric objects only): mean distance to the closest GT-posed vertex.
- penetration_*_mm: on ground-truth contact frames, the per-frame maximum depth
  of fitted body vertices inside the fitted (posed) object; ``_max`` is the
  largest over those frames, ``_mean`` / ``_median`` the mean / median over
  those frames of the per-frame maximum (0 for a frame without penetration),
  as InterCap reports it.
- jitter_mps2: mean vertex acceleration magnitude (second difference x fps^2).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
import yaml
from scipy.spatial import cKDTree

RESULT_FILES = ("object_poses.npz", "body_vertices.npy", "body_faces.npy", "contact.npy", "keypoints3d.npy")
_FILE_NAMES = {name.split(".")[0]: name for name in RESULT_FILES}

BODY25 = np.arange(0, 25)
LEFT_WRIST, RIGHT_WRIST = 25, 46
LEFT_HAND = np.arange(26, 46)  # 20 left-hand joints after the wrist
RIGHT_HAND = np.arange(47, 67)  # 20 right-hand joints after the wrist

SYMMETRY_TOLERANCE = 0.01  # max surface deviation under a symmetry, as a fraction of the bbox diagonal
SYMMETRY_ORDERS = (8, 6, 5, 4, 3, 2)  # n-fold rotations tried about each candidate axis
CONTINUOUS_TEST_ANGLES_DEG = (23.0, 61.0, 137.0)  # not multiples of 360/n for the orders above
QUERY_CHUNK = 20000  # points per closest-triangle batch (bounds memory)


@dataclass
class EvalResult:
    """Scalar metrics, per-frame error arrays (to find bad frames) and notes on what was skipped."""

    metrics: dict[str, float | int | None] = field(default_factory=dict)
    per_frame: dict[str, list] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"metrics": _jsonable(self.metrics), "per_frame": _jsonable(self.per_frame), "notes": list(self.notes)}


# --------------------------------------------------------------------------------------------
# reading the two folders


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - re-raised with the file named
        raise ValueError(f"{path}: cannot read ({exc})") from exc


def _load_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """R (T, 3, 3), t (T, 3) from an object_poses.npz, with the file named on any defect."""
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = set(z.files)
            if not {"R", "t"} <= keys:
                raise ValueError(f"{path}: needs arrays 'R' (T,3,3) and 't' (T,3), found {sorted(keys)}")
            R, t = np.asarray(z["R"], np.float64), np.asarray(z["t"], np.float64)
    except ValueError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise ValueError(f"{path}: cannot read ({exc})") from exc
    if R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (R.shape[0], 3):
        raise ValueError(f"{path}: expected R (T,3,3) and t (T,3), got R {R.shape} and t {t.shape}")
    return R, t


def _load_folder(folder: Path) -> tuple[dict[str, np.ndarray], dict[str, Path]]:
    """The contract files found in one folder (results or ground_truth/), checked for shape."""
    data: dict[str, np.ndarray] = {}
    files: dict[str, Path] = {}
    p = folder / "object_poses.npz"
    if p.is_file():
        data["object_R"], data["object_t"] = _load_poses(p)
        files["object_poses"] = p
    expected_ndim = {"body_vertices": 3, "body_faces": 2, "contact": 1, "keypoints3d": 3}
    for name, ndim in expected_ndim.items():
        p = folder / f"{name}.npy"
        if not p.is_file():
            continue
        arr = _load_npy(p)
        if arr.ndim != ndim or (ndim >= 2 and arr.shape[-1] != 3):
            raise ValueError(f"{p}: unexpected shape {arr.shape} for {name} (see SESSION_FORMAT.md)")
        data[name] = arr
        files[name] = p
    return data, files


def _frame_counts(data: dict[str, np.ndarray], files: dict[str, Path]) -> dict[str, tuple[Path, tuple, int]]:
    """file key -> (path, shape, T) for every array that has a frame axis."""
    out = {}
    for key, path in files.items():
        if key == "body_faces":
            continue
        arr = data["object_R"] if key == "object_poses" else data[key]
        out[key] = (path, arr.shape, arr.shape[0])
    return out


def check_frame_counts(res_data, res_files, gt_data, gt_files) -> int:
    """T shared by the results and the ground truth; ValueError naming both files when they differ."""
    gt_counts = _frame_counts(gt_data, gt_files)
    res_counts = _frame_counts(res_data, res_files)
    if not gt_counts:
        raise ValueError(f"no ground-truth arrays found under {next(iter(gt_files.values()), 'ground_truth/')}")
    ref_key = next(iter(gt_counts))
    ref_path, ref_shape, T = gt_counts[ref_key]
    for key, (path, shape, n) in gt_counts.items():
        if n != T:
            raise ValueError(
                f"ground truth disagrees on the number of frames: {path} has shape {shape} (T={n}) "
                f"but {ref_path} has shape {ref_shape} (T={T})"
            )
    for key, (path, shape, n) in res_counts.items():
        if n != T:
            gpath, gshape, _ = gt_counts.get(key, (ref_path, ref_shape, T))
            raise ValueError(
                f"frame count mismatch: results file {path} has shape {shape} (T={n}) but ground truth "
                f"{gpath} has shape {gshape} (T={T}); both must cover the same frames, counted from "
                f"frames.start in session.yaml"
            )
    return T


def _session_info(session_dir: Path) -> dict:
    """fps, first frame index and object mesh path from session.yaml."""
    path = session_dir / "session.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: is {session_dir} a capture session?")
    with open(path) as fh:
        cfg = yaml.safe_load(fh) or {}
    if "fps" not in cfg:
        raise ValueError(f"{path}: 'fps' is required")
    obj = cfg.get("object") or {}
    mesh = obj.get("mesh")
    frames = cfg.get("frames") or {}
    return {
        "fps": float(cfg["fps"]),
        "start": int(frames.get("start", 0)),
        "mesh_path": (session_dir / mesh) if mesh else None,
    }


def load_object_mesh(path: Path) -> trimesh.Trimesh:
    """The object's mesh in object coordinates (metres), duplicate vertices merged."""
    mesh = trimesh.load(str(path), force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: not a triangle mesh")
    return mesh


# --------------------------------------------------------------------------------------------
# exact point-to-triangle geometry


def closest_points_on_triangles(p, a, b, c):
    """Closest point on triangle (a, b, c) to p, and which feature it lies on.

    All inputs broadcast to (..., 3). Returns q (..., 3) and region (...,):
    0 face interior, 1/2/3 vertex a/b/c, 4/5/6 edge ab/bc/ca (the Voronoi
    regions of the triangle, tested in the order of Ericson, Real-Time
    Collision Detection 5.1.5). Works on barycentric weights (v, w) so that
    q = a + v ab + w ac is formed once.
    """
    ab, ac = b - a, c - a
    ap = p - a
    d1, d2 = np.einsum("...i,...i->...", ab, ap), np.einsum("...i,...i->...", ac, ap)
    ab_ab, ab_ac, ac_ac = (np.einsum("...i,...i->...", x, y) for x, y in ((ab, ab), (ab, ac), (ac, ac)))
    d3, d4 = d1 - ab_ab, d2 - ab_ac  # ab.(p-b), ac.(p-b)
    d5, d6 = d1 - ab_ac, d2 - ac_ac  # ab.(p-c), ac.(p-c)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2

    def ratio(num, den):
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.clip(np.where(den != 0, num / np.where(den != 0, den, 1.0), 0.0), 0.0, 1.0)

    den = va + vb + vc
    den = np.where(den == 0, 1.0, den)
    v, w = vb / den, vc / den
    region = np.zeros(v.shape, np.int8)
    zero, one = np.zeros_like(v), np.ones_like(v)
    t_ab, t_ac = ratio(d1, d1 - d3), ratio(d2, d2 - d6)
    t_bc = ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    cases = [  # (mask, v, w, region code) in Ericson's order; the first that holds wins
        ((d1 <= 0) & (d2 <= 0), zero, zero, 1),
        ((d3 >= 0) & (d4 <= d3), one, zero, 2),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), t_ab, zero, 4),
        ((d6 >= 0) & (d5 <= d6), zero, one, 3),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), zero, t_ac, 6),
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 1.0 - t_bc, t_bc, 5),
    ]
    for mask, cv, cw, code in reversed(cases):
        v, w = np.where(mask, cv, v), np.where(mask, cw, w)
        region = np.where(mask, np.int8(code), region)
    q = a + v[..., None] * ab + w[..., None] * ac
    return q, region


class TriangleSurface:
    """A triangle mesh prepared for exact closest-point and signed-distance queries.

    Triangles are grouped by size (centroid-to-corner radius, in doublings of
    the median), one centroid KD-tree per group. A point's candidates are the
    k triangles with the nearest centroids in each group; the answer is exact
    because a triangle outside a group's k nearest is at least (k-th centroid
    distance - the group's largest radius) away, and where that bound does not
    rule a group out, every triangle of the group within the bounding ball is
    tested too. Grouping keeps the bound tight on meshes that mix small and
    long, thin triangles (anny's body has radii from 0.4 to 35 mm). Candidates
    are screened in float32 (speed); the chosen triangle's distance is float64.
    """

    def __init__(self, vertices, faces, k: int = 6):
        self.vertices = np.asarray(vertices, np.float64)  # (V, 3)
        self.faces = np.asarray(faces, np.int64)  # (F, 3)
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise ValueError(f"faces must be a non-empty (F, 3) array, got {self.faces.shape}")
        self.tri = self.vertices[self.faces]  # (F, 3, 3)
        centroids = self.tri.mean(1)  # (F, 3)
        radius = np.linalg.norm(self.tri - centroids[:, None], axis=2).max(1)  # (F,)
        ref = max(float(np.median(radius)), 1e-12)
        level = np.ceil(np.log2(np.maximum(radius / ref, 1.0))).astype(np.int64)
        self.groups = []  # (face ids, KD-tree of their centroids, largest radius, k)
        for lv in np.unique(level):
            ids = np.flatnonzero(level == lv)
            tree = cKDTree(centroids[ids], balanced_tree=False, compact_nodes=False)
            self.groups.append((ids, tree, float(radius[ids].max()), int(min(k, len(ids)))))
        self.tri32 = self.tri.astype(np.float32)  # candidate screening only; answers are float64
        self._normals = None

    def closest(self, points):
        """Distance (N,), closest point (N, 3), face (N,) and region (N,) for points (N, 3)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        n = len(points)
        dist, q = np.empty(n), np.empty((n, 3))
        face, region = np.empty(n, np.int64), np.empty(n, np.int8)
        for s in range(0, n, QUERY_CHUNK):
            sl = slice(s, min(s + QUERY_CHUNK, n))
            face[sl] = self._closest_faces(points[sl])
            t = self.tri[face[sl]]
            q[sl], region[sl] = closest_points_on_triangles(points[sl], t[:, 0], t[:, 1], t[:, 2])
            dist[sl] = np.linalg.norm(q[sl] - points[sl], axis=1)
        return dist, q, face, region

    def _closest_faces(self, p):
        """Index (N,) of the triangle closest to each point (N, 3)."""
        n = len(p)
        cand, kth = [], []
        for ids, tree, _, k in self.groups:
            dk, j = tree.query(p, k, workers=-1)
            cand.append(ids[j.reshape(n, -1)])
            kth.append(dk.reshape(n, -1)[:, -1] if k < len(ids) else np.full(n, np.inf))
        cand = np.concatenate(cand, axis=1)  # (N, C)
        t = self.tri32[cand]  # (N, C, 3, 3)
        p32 = p.astype(np.float32)[:, None]
        q, _ = closest_points_on_triangles(p32, t[..., 0, :], t[..., 1, :], t[..., 2, :])
        d = np.linalg.norm(q - p32, axis=-1)  # (N, C)
        j = d.argmin(1)
        best_f = cand[np.arange(n), j]
        t = self.tri[best_f]  # the winner's distance in float64, for the bounds below
        best_d = np.linalg.norm(closest_points_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])[0] - p, axis=1)
        for (ids, tree, r_max, _), dk in zip(self.groups, kth):
            unsure = np.flatnonzero(dk - r_max < best_d)
            if len(unsure) == 0:
                continue
            balls = tree.query_ball_point(p[unsure], best_d[unsure] + r_max, workers=-1)
            counts = np.fromiter((len(b) for b in balls), np.int64, len(balls))
            if counts.sum() == 0:
                continue
            owner = np.repeat(unsure, counts)  # (M,)
            faces = ids[np.concatenate([np.asarray(b, np.int64) for b in balls])]
            t = self.tri[faces]
            qq, _ = closest_points_on_triangles(p[owner], t[:, 0], t[:, 1], t[:, 2])
            dd = np.linalg.norm(qq - p[owner], axis=1)
            order = np.lexsort((dd, owner))
            first = order[np.r_[True, owner[order][1:] != owner[order][:-1]]]
            better = dd[first] < best_d[owner[first]]
            best_d[owner[first[better]]] = dd[first[better]]
            best_f[owner[first[better]]] = faces[first[better]]
        return best_f

    def _pseudonormals(self):
        """Face, angle-weighted vertex and edge normals (Baerentzen & Aanaes), for the inside test."""
        if self._normals is None:
            f, tri = self.faces, self.tri
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3)
            fn = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
            if _signed_volume(self.vertices, f) < 0:  # inward winding: flip so that outside is +
                fn = -fn
            vn = np.zeros_like(self.vertices)
            for k in range(3):
                e1, e2 = tri[:, (k + 1) % 3] - tri[:, k], tri[:, (k + 2) % 3] - tri[:, k]
                angle = np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=1), (e1 * e2).sum(1))
                np.add.at(vn, f[:, k], angle[:, None] * fn)
            edges = np.sort(f[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)  # ab, bc, ca per face
            _, inv = np.unique(edges, axis=0, return_inverse=True)
            en = np.zeros((inv.max() + 1, 3))
            np.add.at(en, inv.ravel(), np.repeat(fn, 3, axis=0))
            self._normals = (fn, vn, en, inv.reshape(-1, 3))
        return self._normals

    def signed_distance(self, points):
        """Signed distance (N,) to a closed surface: negative inside, for points (N, 3)."""
        d, q, face, region = self.closest(points)
        fn, vn, en, face_edge = self._pseudonormals()
        normal = fn[face].copy()
        vert = (region >= 1) & (region <= 3)
        normal[vert] = vn[self.faces[face[vert], region[vert] - 1]]
        edge = region >= 4
        normal[edge] = en[face_edge[face[edge], region[edge] - 4]]
        side = ((np.asarray(points, np.float64).reshape(-1, 3) - q) * normal).sum(1)
        return np.where(side < 0, -d, d)


def _signed_volume(vertices, faces) -> float:
    tri = vertices[faces]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def sample_surface(vertices, faces, n: int, rng: np.random.Generator):
    """n points (n, 3) on a mesh, uniform over its area (area-weighted faces, uniform barycentrics)."""
    tri = np.asarray(vertices, np.float64)[faces]  # (F, 3, 3)
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    cdf = np.cumsum(area)
    f = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(cdf) - 1)
    u = rng.random((n, 2))
    flip = u.sum(1) > 1
    u[flip] = 1 - u[flip]
    t = tri[f]
    return t[:, 0] + u[:, :1] * (t[:, 1] - t[:, 0]) + u[:, 1:] * (t[:, 2] - t[:, 0])


def symmetric_surface_distance(verts_a, faces_a, verts_b, faces_b, n: int, rng) -> float:
    """Mean symmetric point-to-surface distance (m) between two meshes of any topology.

    n area-weighted samples on each mesh, each measured to the other mesh's
    surface (exact point-to-triangle); the two means are averaged.
    """
    surf_a, surf_b = TriangleSurface(verts_a, faces_a), TriangleSurface(verts_b, faces_b)
    d_ab = surf_b.closest(sample_surface(verts_a, faces_a, n, rng))[0]
    d_ba = surf_a.closest(sample_surface(verts_b, faces_b, n, rng))[0]
    return 0.5 * (float(d_ab.mean()) + float(d_ba.mean()))


# --------------------------------------------------------------------------------------------
# object: pose errors and symmetry


def rotation_angle_deg(Ra, Rb):
    """Geodesic angle (deg) between rotations (..., 3, 3); the chord form stays accurate near 0."""
    chord = np.linalg.norm(np.asarray(Ra) - np.asarray(Rb), axis=(-2, -1))  # = 2*sqrt(2)*sin(theta/2)
    return np.degrees(2.0 * np.arcsin(np.clip(chord / (2.0 * math.sqrt(2.0)), 0.0, 1.0)))


def axis_angle_matrix(axis, angle_rad):
    """Rotation matrix (3, 3) about a unit axis (Rodrigues)."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * (K @ K)


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


def _surface_moments(vertices, faces):
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
    centroid, cov = _surface_moments(v, f)
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


def _posed(vertices, R, t):
    """Object vertices (N, 3) under poses R (T, 3, 3), t (T, 3) -> (T, N, 3)."""
    return np.einsum("tij,nj->tni", R, vertices) + t[:, None]


def add_distances(vertices, R_est, t_est, R_gt, t_gt, chunk: int = 64):
    """ADD per frame (T,), metres: mean distance of each mesh vertex under the two poses."""
    out = np.empty(len(R_est))
    for s in range(0, len(R_est), chunk):
        sl = slice(s, s + chunk)
        diff = _posed(vertices, R_est[sl] - R_gt[sl], t_est[sl] - t_gt[sl])  # (t, N, 3)
        out[sl] = np.linalg.norm(diff, axis=-1).mean(1)
    return out


def adds_distances(vertices, R_est, t_est, R_gt, t_gt, chunk: int = 64):
    """ADD-S per frame (T,), metres: mean distance from each estimated vertex to the closest GT vertex.

    Estimated vertices are brought into the GT object frame, so one KD-tree on
    the mesh vertices serves every frame.
    """
    tree = cKDTree(vertices)
    out = np.empty(len(R_est))
    for s in range(0, len(R_est), chunk):
        sl = slice(s, s + chunk)
        world = _posed(vertices, R_est[sl], t_est[sl])  # (t, N, 3)
        local = np.einsum("tji,tnj->tni", R_gt[sl], world - t_gt[sl][:, None])
        out[sl] = tree.query(local.reshape(-1, 3))[0].reshape(local.shape[:2]).mean(1)
    return out


# --------------------------------------------------------------------------------------------
# contact, penetration, jitter, keypoints


def contact_scores(pred, gt):
    """Accuracy, precision and recall (percent; None where undefined) of per-frame contact labels."""
    pred, gt = np.asarray(pred, bool), np.asarray(gt, bool)
    tp, fp, fn = int((pred & gt).sum()), int((pred & ~gt).sum()), int((~pred & gt).sum())
    acc = 100.0 * float((pred == gt).mean()) if len(pred) else None
    prec = 100.0 * tp / (tp + fp) if tp + fp else None
    rec = 100.0 * tp / (tp + fn) if tp + fn else None
    return acc, prec, rec


def penetration_depths(body_vertices, R, t, object_surface: TriangleSurface):
    """Per-frame maximum depth (T,), metres, of body vertices inside the posed object (0 if none).

    Body vertices (T, V, 3) are moved into object coordinates with the inverse
    of each frame's pose R (T, 3, 3), t (T, 3), so one prepared object surface
    serves all frames; only vertices inside the object's bounding box are
    tested. Depth is the distance to the object surface of a vertex whose
    signed distance is negative.
    """
    lo, hi = object_surface.vertices.min(0), object_surface.vertices.max(0)
    depth = np.zeros(len(R))
    for s in range(len(R)):  # one frame at a time bounds memory at (V, 3)
        local = (np.asarray(body_vertices[s], np.float64) - t[s]) @ R[s]  # R^T (x - t)
        near = np.all((local >= lo) & (local <= hi), axis=1)
        if near.any():
            sd = object_surface.signed_distance(local[near])
            depth[s] = max(0.0, float(-sd.min()))
    return depth


def vertex_jitter(vertices, fps: float, chunk: int = 128):
    """Mean vertex acceleration magnitude (m/s^2) of a vertex track (T, V, 3).

    Acceleration is the second finite difference times fps^2; frame triples that
    touch a NaN frame are left out. Returns (mean, number of triples used).
    """
    T = len(vertices)
    if T < 3:
        return None, 0
    total, count = 0.0, 0
    for s in range(0, T - 2, chunk):
        e = min(s + chunk, T - 2)
        v = np.asarray(vertices[s:e + 2], np.float64)  # (n+2, V, 3)
        acc = np.linalg.norm(v[2:] - 2 * v[1:-1] + v[:-2], axis=-1) * fps**2  # (n, V)
        ok = np.isfinite(acc).all(1)
        total += float(acc[ok].mean(1).sum())
        count += int(ok.sum())
    return (total / count if count else None), count


def keypoint_errors(pred, gt):
    """Per-frame MPJPE (T,) in metres over BODY_25 and over both hands (wrist-relative); NaN joints ignored."""
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)

    def mean_valid(err):  # err (T, J) with NaN where either side has no joint
        ok = np.isfinite(err)
        n = ok.sum(1)
        return np.where(n > 0, np.where(ok, err, 0.0).sum(1) / np.maximum(n, 1), np.nan)

    body = mean_valid(np.linalg.norm(pred[:, BODY25] - gt[:, BODY25], axis=-1))
    hands = None
    if pred.shape[1] >= 67 and gt.shape[1] >= 67:
        rel = []
        for wrist, joints in ((LEFT_WRIST, LEFT_HAND), (RIGHT_WRIST, RIGHT_HAND)):
            rp = pred[:, joints] - pred[:, wrist:wrist + 1]
            rg = gt[:, joints] - gt[:, wrist:wrist + 1]
            rel.append(np.linalg.norm(rp - rg, axis=-1))
        hands = mean_valid(np.concatenate(rel, axis=1))
    return body, hands


# --------------------------------------------------------------------------------------------
# the evaluation


def _summary(values_m, scale=1000.0):
    """Mean, median and p90 of the finite entries (scaled), and how many entries were NaN."""
    v = np.asarray(values_m, np.float64) * scale
    ok = np.isfinite(v)
    if not ok.any():
        return None, None, None, int((~ok).sum())
    return float(v[ok].mean()), float(np.median(v[ok])), float(np.percentile(v[ok], 90)), int((~ok).sum())


def _frames_finite(arr):
    """(T,) True where a frame's array has no NaN."""
    arr = np.asarray(arr)
    return np.isfinite(arr.reshape(len(arr), -1)).all(1)


@dataclass
class _Inputs:
    """What one evaluation reads: both folders' arrays, which files exist, and session facts."""

    res: dict
    res_files: dict
    gt: dict
    gt_files: dict
    T: int
    fps: float
    mesh: trimesh.Trimesh | None
    surface: TriangleSurface | None
    result: EvalResult

    def has(self, what: str, res_keys, gt_keys) -> bool:
        """True when every input file is there; otherwise notes what is missing for `what`."""
        missing = [f"results {_FILE_NAMES[k]}" for k in res_keys if k not in self.res_files]
        missing += [f"ground_truth/{_FILE_NAMES[k]}" for k in gt_keys if k not in self.gt_files]
        if missing:
            self.result.notes.append(f"{what} skipped: no {', '.join(missing)}")
        return not missing


def _body_surface_metrics(inp: _Inputs, surface_samples: int, seed: int) -> None:
    m, pf = inp.result.metrics, inp.result.per_frame
    fv, ff, gv, gf = inp.res["body_vertices"], inp.res["body_faces"], inp.gt["body_vertices"], inp.gt["body_faces"]
    err = np.full(inp.T, np.nan)
    ok = _frames_finite(fv) & _frames_finite(gv)
    for i in np.flatnonzero(ok):  # one mesh pair per frame: each needs its own search trees
        rng = np.random.default_rng([seed, int(i)])
        err[i] = symmetric_surface_distance(fv[i], ff, gv[i], gf, surface_samples, rng)
    mean, med, p90, miss = _summary(err)
    m.update(body_surface_mm=mean, body_surface_mm_median=med, body_surface_mm_p90=p90,
             body_surface_frames_missing=miss)
    pf["body_surface_mm"] = _list(err * 1000)


def _keypoint_metrics(inp: _Inputs) -> None:
    m, pf = inp.result.metrics, inp.result.per_frame
    body, hands = keypoint_errors(inp.res["keypoints3d"], inp.gt["keypoints3d"])
    mean, _, _, miss = _summary(body)
    m.update(keypoint_mpjpe_mm=mean, keypoint_frames_missing=miss)
    pf["keypoint_mpjpe_mm"] = _list(body * 1000)
    if hands is None:
        inp.result.notes.append("hand_keypoint_mm skipped: keypoints3d has fewer than 67 joints")
        return
    mean, _, _, miss = _summary(hands)
    m.update(hand_keypoint_mm=mean, hand_keypoint_frames_missing=miss)
    pf["hand_keypoint_mm"] = _list(hands * 1000)


def _object_metrics(inp: _Inputs, symmetric_object: bool | None, surface_samples: int, seed: int) -> None:
    m, pf, notes = inp.result.metrics, inp.result.per_frame, inp.result.notes
    Re, te, Rg, tg = inp.res["object_R"], inp.res["object_t"], inp.gt["object_R"], inp.gt["object_t"]
    ok = _frames_finite(Re) & _frames_finite(te) & _frames_finite(Rg) & _frames_finite(tg)

    def per_frame(values):  # (n_ok,) -> (T,) with NaN where a frame is untrusted
        full = np.full(inp.T, np.nan)
        full[ok] = values
        return full

    rot = per_frame(rotation_angle_deg(Re[ok], Rg[ok]))
    trans = per_frame(np.linalg.norm(te[ok] - tg[ok], axis=1))
    m["object_rotation_deg"] = _summary(rot, 1.0)[0]
    m["object_translation_mm"] = _summary(trans)[0]
    m["object_frames_missing"] = int((~ok).sum())
    pf["object_rotation_deg"], pf["object_translation_mm"] = _list(rot), _list(trans * 1000)
    if inp.mesh is None:
        return
    verts = np.asarray(inp.mesh.vertices, np.float64)
    add = per_frame(add_distances(verts, Re[ok], te[ok], Rg[ok], tg[ok]))
    mean, med, p90, _ = _summary(add)
    m.update(object_add_mm=mean, object_add_mm_median=med, object_add_mm_p90=p90)
    pf["object_add_mm"] = _list(add * 1000)
    if symmetric_object is False:
        notes.append("object symmetry not considered (symmetric_object=False): no ADD-S")
        return
    sym = detect_symmetry(inp.mesh, surface_samples, seed)
    notes.append(f"object mesh {sym.description}")
    m["object_symmetric"] = int(sym.is_symmetric)
    if not (sym.is_symmetric or symmetric_object):
        return
    if not sym.is_symmetric:
        notes.append("symmetric_object=True but no symmetry found: object_rotation_sym_deg = object_rotation_deg")
    adds = per_frame(adds_distances(verts, Re[ok], te[ok], Rg[ok], tg[ok]))
    rsym = per_frame(symmetric_rotation_error_deg(Re[ok], Rg[ok], sym))
    mean, med, p90, _ = _summary(adds)
    m.update(object_adds_mm=mean, object_adds_mm_median=med, object_adds_mm_p90=p90,
             object_rotation_sym_deg=_summary(rsym, 1.0)[0])
    pf["object_adds_mm"], pf["object_rotation_sym_deg"] = _list(adds * 1000), _list(rsym)


def _contact_metrics(inp: _Inputs) -> None:
    pred = np.asarray(inp.res["contact"])
    ok = np.isfinite(pred.astype(np.float64))  # a float contact.npy may mark untrusted frames NaN
    acc, prec, rec = contact_scores(pred[ok] > 0.5, np.asarray(inp.gt["contact"], bool)[ok])
    inp.result.metrics.update(contact_accuracy_pct=acc, contact_precision_pct=prec, contact_recall_pct=rec,
                              contact_frames_missing=int((~ok).sum()))


def _penetration_metrics(inp: _Inputs) -> None:
    """Fitted body into fitted object on GT-contact frames; mean/median are over frames of the per-frame max."""
    m = inp.result.metrics
    on = np.asarray(inp.gt["contact"], bool)
    bv, Re, te = inp.res["body_vertices"], inp.res["object_R"], inp.res["object_t"]
    ok = on & _frames_finite(bv) & _frames_finite(Re) & _frames_finite(te)
    depth = np.full(inp.T, np.nan)
    if ok.any():
        depth[ok] = penetration_depths(bv[ok], Re[ok], te[ok], inp.surface)
    m["penetration_frames"] = int(on.sum())
    m["penetration_frames_missing"] = int((on & ~ok).sum())
    if ok.any():
        d = depth[ok] * 1000
        m.update(penetration_max_mm=float(d.max()), penetration_mean_mm=float(d.mean()),
                 penetration_median_mm=float(np.median(d)))
    else:
        m.update(penetration_max_mm=None, penetration_mean_mm=None, penetration_median_mm=None)
        inp.result.notes.append("penetration: no ground-truth contact frame with a trusted body and object")
    inp.result.per_frame["penetration_mm"] = _list(depth * 1000)


def _jitter_metrics(inp: _Inputs) -> None:
    """Fitted body / object jitter, each next to the ground truth's (the floor a real motion has)."""
    m = inp.result.metrics
    if inp.has("body jitter", ["body_vertices"], []):
        m["jitter_mps2"] = vertex_jitter(inp.res["body_vertices"], inp.fps)[0]
        if "body_vertices" in inp.gt:
            m["jitter_gt_mps2"] = vertex_jitter(inp.gt["body_vertices"], inp.fps)[0]
    if inp.mesh is not None and inp.has("object jitter", ["object_poses"], []):
        verts = np.asarray(inp.mesh.vertices, np.float64)
        m["object_jitter_mps2"] = _rigid_jitter(verts, inp.res["object_R"], inp.res["object_t"], inp.fps)
        if "object_R" in inp.gt:
            m["object_jitter_gt_mps2"] = _rigid_jitter(verts, inp.gt["object_R"], inp.gt["object_t"], inp.fps)


def evaluate(out_dir, session_dir, *, symmetric_object: bool | None = None, surface_samples: int = 2000,
             seed: int = 0) -> EvalResult:
    """Compare a results folder with the session's ground truth; definitions in the module docstring.

    symmetric_object: None detects rotational symmetry of the object mesh;
    True forces the symmetric metrics (ADD-S, rotation error over the detected
    group); False turns them off. surface_samples: points per mesh for
    body_surface_mm (and for the symmetry test); seed makes the sampling repeatable.
    Raises ValueError when results and ground truth cover different numbers of frames.
    """
    out_dir, session_dir = Path(out_dir), Path(session_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"results folder {out_dir} not found")
    gt_dir = session_dir / "ground_truth"
    if not gt_dir.is_dir():
        raise FileNotFoundError(f"{gt_dir} not found: evaluation needs a session with ground truth")
    info = _session_info(session_dir)
    res, res_files = _load_folder(out_dir)
    gt, gt_files = _load_folder(gt_dir)
    if not res_files:
        raise FileNotFoundError(f"{out_dir} holds none of the results files {', '.join(RESULT_FILES)}")
    T = check_frame_counts(res, res_files, gt, gt_files)

    result = EvalResult()
    result.metrics["frames"] = T
    result.per_frame["frame"] = list(range(info["start"], info["start"] + T))
    mesh = surface = None
    if info["mesh_path"] is not None and info["mesh_path"].is_file():
        mesh = load_object_mesh(info["mesh_path"])
        surface = TriangleSurface(mesh.vertices, mesh.faces)
    elif info["mesh_path"] is not None:
        result.notes.append(f"object mesh {info['mesh_path']} not found: ADD, penetration, object jitter skipped")
    elif "object_poses" in res_files or "object_poses" in gt_files:
        result.notes.append("session.yaml names no object mesh: ADD, penetration, object jitter skipped")
    inp = _Inputs(res, res_files, gt, gt_files, T, info["fps"], mesh, surface, result)

    if inp.has("body_surface_mm", ["body_vertices", "body_faces"], ["body_vertices", "body_faces"]):
        _body_surface_metrics(inp, surface_samples, seed)
    if inp.has("keypoint_mpjpe_mm / hand_keypoint_mm", ["keypoints3d"], ["keypoints3d"]):
        _keypoint_metrics(inp)
    if inp.has("object metrics", ["object_poses"], ["object_poses"]):
        _object_metrics(inp, symmetric_object, surface_samples, seed)
    if inp.has("contact metrics", ["contact"], ["contact"]):
        _contact_metrics(inp)
    if inp.has("penetration", ["body_vertices", "object_poses"], ["contact"]) and surface is not None:
        _penetration_metrics(inp)
    _jitter_metrics(inp)
    return result


def _rigid_jitter(verts, R, t, fps, chunk: int = 256):
    """vertex_jitter of the object's vertices under poses R (T, 3, 3), t (T, 3), built chunk by chunk."""
    T = len(R)
    if T < 3:
        return None
    total, count = 0.0, 0
    for s in range(0, T - 2, chunk):
        e = min(s + chunk, T - 2)
        mean, n = vertex_jitter(_posed(verts, R[s:e + 2], t[s:e + 2]), fps)
        if n:
            total, count = total + mean * n, count + n
    return total / count if count else None


# --------------------------------------------------------------------------------------------
# reporting

_UNITS = (("_frames_missing", "frames"), ("_mm", "mm"), ("_deg", "deg"), ("_pct", "%"), ("_mps2", "m/s^2"))


def _unit(name: str) -> str:
    for key, unit in _UNITS:
        if name.endswith(key) or (key + "_") in name:
            return unit
    return "frames" if name in ("frames", "penetration_frames") else ""


def format_table(result: EvalResult) -> str:
    """A plain-text table (metric, value, unit) followed by the notes."""
    rows = [("metric", "value", "unit")]
    for name, value in result.metrics.items():
        if value is None:
            text = "n/a"
        elif isinstance(value, (int, np.integer)):
            text = str(int(value))
        else:
            text = f"{value:.3f}"
        rows.append((name, text, _unit(name)))
    w0, w1 = max(len(r[0]) for r in rows), max(len(r[1]) for r in rows)
    lines = [f"{a:<{w0}}  {b:>{w1}}  {c}".rstrip() for a, b, c in rows]
    lines.insert(1, "-" * len(lines[0]))
    if result.notes:
        lines += ["", "notes:"] + [f"  - {n}" for n in result.notes]
    return "\n".join(lines)


def _list(arr) -> list:
    """Array -> list with None where NaN (JSON has no NaN)."""
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(arr, np.float64).ravel()]


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    return obj


def write_json(result: EvalResult, path) -> None:
    """metrics, per_frame and notes as JSON (NaN written as null)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        json.dump(result.to_dict(), fh, indent=2)
