"""The error measures that evaluation reports, each a small function over arrays
(ADD / ADD-S, contact scores, penetration depths, jitter, keypoint errors)."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from intercap.geometry.surfaces import TriangleSurface

BODY25 = np.arange(0, 25)

LEFT_WRIST, RIGHT_WRIST = 25, 46



LEFT_HAND = np.arange(26, 46)  # 20 left-hand joints after the wrist


RIGHT_HAND = np.arange(47, 67)  # 20 right-hand joints after the wrist


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


def contact_scores(pred, gt):
    """Accuracy, precision and recall (percent; None where undefined) of per-frame contact labels."""
    pred, gt = np.asarray(pred, bool), np.asarray(gt, bool)
    tp, fp, fn = int((pred & gt).sum()), int((pred & ~gt).sum()), int((~pred & gt).sum())
    acc = 100.0 * float((pred == gt).mean()) if len(pred) else None
    prec = 100.0 * tp / (tp + fp) if tp + fp else None
    rec = 100.0 * tp / (tp + fn) if tp + fn else None
    return acc, prec, rec


def nearest_signed_distance(body_vertices, R, t, object_surface: TriangleSurface, margin_m: float = 0.0):
    """Per-frame smallest signed distance (T,), metres, from body vertices to the posed object's
    surface (negative inside), over the vertices within `margin_m` of the object's bounding box;
    inf where none is.

    Body vertices (T, V, 3) are moved into object coordinates with the inverse of each frame's
    pose R (T, 3, 3), t (T, 3), so one prepared object surface serves all frames."""
    lo, hi = object_surface.vertices.min(0) - margin_m, object_surface.vertices.max(0) + margin_m
    nearest = np.full(len(R), np.inf)
    for s in range(len(R)):  # one frame at a time bounds memory at (V, 3)
        local = (np.asarray(body_vertices[s], np.float64) - t[s]) @ R[s]  # R^T (x - t)
        near = np.all((local >= lo) & (local <= hi), axis=1)
        if near.any():
            nearest[s] = float(object_surface.signed_distance(local[near]).min())
    return nearest


def penetration_depths(body_vertices, R, t, object_surface: TriangleSurface):
    """Per-frame maximum depth (T,), metres, of body vertices inside the posed object (0 if none):
    the distance to the object surface of the deepest vertex whose signed distance is negative
    (`nearest_signed_distance`; only vertices inside the object's bounding box can be)."""
    return np.maximum(0.0, -nearest_signed_distance(body_vertices, R, t, object_surface))


def touching_frames(body_vertices, R, t, object_surface: TriangleSurface, distance_m: float = 0.005):
    """(T,) bool: some body vertex lies within `distance_m` of the posed object's surface, or inside
    it (`nearest_signed_distance`). Geometry's contact, where a session's contact labels are its
    script's grasp phases (hands touch a moment before a grasp begins and after it ends)."""
    return nearest_signed_distance(body_vertices, R, t, object_surface, distance_m) < distance_m


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


def summarise(values_m, scale=1000.0):
    """Mean, median and p90 of the finite entries (scaled), and how many entries were NaN."""
    v = np.asarray(values_m, np.float64) * scale
    ok = np.isfinite(v)
    if not ok.any():
        return None, None, None, int((~ok).sum())
    return float(v[ok].mean()), float(np.median(v[ok])), float(np.percentile(v[ok], 90)), int((~ok).sum())


def frames_finite(arr):
    """(T,) True where a frame's array has no NaN."""
    arr = np.asarray(arr)
    return np.isfinite(arr.reshape(len(arr), -1)).all(1)


def rigid_jitter(verts, R, t, fps, chunk: int = 256):
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
