"""Contact forces by bounded least squares (issue 14, part 4).

Per frame, the body's needed wrench about its root W_b (6,) and the object's about its centre
of mass W_o (6,) (newton_euler) are explained by contact unknowns x:

* each hand touching the object: a free 6D wrench (f_h, tau_h at the hand's contact point r_h)
  applied by the hand to the object; the body feels the opposite;
* each sole point on the floor: a linearised friction cone, f = D c with c >= 0 and D (3, E)
  the pyramid's edges n + mu d_e (friction_pyramid);
* each object point on the floor: the same pyramid, acting on the object.

    min_x  |W_b - A_b x|^2 + w_o^2 |W_o - A_o x|^2 + sum_i lambda_i x_i^2,   c >= 0

solved per frame by scipy.optimize.lsq_linear (bounded variables; problems of ~50 unknowns). The
residuals W_b - A_b x and W_o - A_o x are the wrenches no contact explains. `unconstrained_feet`
solves the same with free 3D sole forces, to count friction-cone violations.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear


def friction_pyramid(normal: np.ndarray, mu: float, edges: int = 4) -> np.ndarray:
    """(3, E) edge directions n + mu d_e of the pyramid inscribed in the friction cone (|f_t| <= mu f_n)."""
    if mu < 0:
        raise ValueError(f"physics.mu must be non-negative, got {mu}")
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    angles = 2 * np.pi * np.arange(edges) / edges
    d = np.cos(angles)[:, None] * t1 + np.sin(angles)[:, None] * t2  # (E, 3)
    return (n + mu * d).T


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices: skew(a) @ b = a x b."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([z, -w, y, w, z, -x, -y, x, z], -1).reshape(*v.shape[:-1], 3, 3)


def wrench_map(points: np.ndarray, about: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(T, N, 6, K): the wrench (force; torque about `about` (T, 3)) of unit amounts along
    `directions` (3, K) applied at points (T, N, 3)."""
    arm = skew(points - about[:, None])  # (T, N, 3, 3)
    top = np.broadcast_to(directions, (*points.shape[:2], 3, directions.shape[1]))
    return np.concatenate([top, arm @ directions], -2)


@dataclass
class ContactSolution:
    hand_force: np.ndarray  # (T, 2, 3) N, by each hand on the object
    hand_torque: np.ndarray  # (T, 2, 3) N m, about the hand's contact point
    foot_point_force: np.ndarray  # (T, 2, P, 3) N, ground on each sole point
    object_ground_force: np.ndarray  # (T, Q, 3) N, ground on each object point
    body_residual: np.ndarray  # (T, 6) force N, torque N m about the root
    object_residual: np.ndarray  # (T, 6) force N, torque N m about the object's COM


def solve_contacts(body_wrench, root, foot_points, foot_active, normal, mu, object_wrench=None, object_com=None,
                   hand_points=None, hand_active=None, object_points=None, object_active=None, edges: int = 4,
                   object_weight: float = 10.0, reg_force: float = 1e-4, reg_torque: float = 1e-2) -> ContactSolution:
    """Contact forces of T frames. body_wrench (T, 6) about root (T, 3); foot_points (T, 2, P, 3)
    with foot_active (T, 2, P); object_wrench (T, 6) about object_com (T, 3) or None (object
    unknown: hands and object-ground contacts are left out); hand_points (T, 2, 3), hand_active
    (T, 2); object_points (T, Q, 3), object_active (T, Q). Frames with non-finite inputs give NaN."""
    body_wrench = np.asarray(body_wrench, np.float64)
    T, P = body_wrench.shape[0], foot_points.shape[2]
    D = friction_pyramid(normal, mu, edges)  # (3, E)
    E = D.shape[1]
    has_object = object_wrench is not None
    # columns: hands (2 x 6), feet (2 x P x E), object points (Q x E)
    cols_body = [-np.broadcast_to(_hand_map(hand_points, root), (T, 2, 6, 6)) if has_object else np.zeros((T, 2, 6, 6))]
    A_body_feet = wrench_map(foot_points.reshape(T, 2 * P, 3), root, D)  # (T, 2P, 6, E)
    Q = object_points.shape[1] if has_object and object_points is not None else 0
    n = 12 + 2 * P * E + Q * E
    A = np.zeros((T, 12, n))
    A[:, :6, :12] = cols_body[0].transpose(0, 2, 1, 3).reshape(T, 6, 12)
    A[:, :6, 12:12 + 2 * P * E] = A_body_feet.transpose(0, 2, 1, 3).reshape(T, 6, 2 * P * E)
    b = np.zeros((T, 12))
    b[:, :6] = body_wrench
    active = np.zeros((T, n), bool)
    active[:, 12:12 + 2 * P * E] = np.repeat(np.asarray(foot_active, bool).reshape(T, 2 * P), E, axis=1)
    if has_object:
        A[:, 6:, :12] = _hand_map(hand_points, object_com).transpose(0, 2, 1, 3).reshape(T, 6, 12) * object_weight
        if Q:
            A_obj = wrench_map(object_points, object_com, D)  # (T, Q, 6, E)
            A[:, 6:, 12 + 2 * P * E:] = A_obj.transpose(0, 2, 1, 3).reshape(T, 6, Q * E) * object_weight
            active[:, 12 + 2 * P * E:] = np.repeat(np.asarray(object_active, bool), E, axis=1)
        b[:, 6:] = np.asarray(object_wrench, np.float64) * object_weight
        active[:, :12] = np.repeat(np.asarray(hand_active, bool), 6, axis=1)
    reg = np.full(n, reg_force)
    reg[[3, 4, 5, 9, 10, 11]] = reg_torque
    lb = np.zeros(n)
    lb[:12] = -np.inf
    x = np.zeros((T, n))
    good = np.isfinite(A).all((1, 2)) & np.isfinite(b).all(1)
    for t in np.flatnonzero(good):  # small bounded problems, one per frame
        cols = np.flatnonzero(active[t])
        if not len(cols):
            continue
        At = np.concatenate([A[t][:, cols], np.diag(np.sqrt(reg[cols]))])
        bt = np.concatenate([b[t], np.zeros(len(cols))])
        if np.isfinite(lb[cols]).any():
            x[t, cols] = lsq_linear(At, bt, bounds=(lb[cols], np.inf), method="bvls").x
        else:
            x[t, cols] = np.linalg.lstsq(At, bt, rcond=None)[0]
    resid = b - np.einsum("tkn,tn->tk", A, x)
    resid[:, 6:] /= object_weight
    x[~good] = np.nan
    resid[~good] = np.nan
    hands = x[:, :12].reshape(T, 2, 6)
    feet = np.einsum("ie,tpe->tpi", D, x[:, 12:12 + 2 * P * E].reshape(T, 2 * P, E)).reshape(T, 2, P, 3)
    obj = np.einsum("ie,tqe->tqi", D, x[:, 12 + 2 * P * E:].reshape(T, Q, E))
    return ContactSolution(hands[..., :3], hands[..., 3:], feet, obj, resid[:, :6],
                           resid[:, 6:] if has_object else np.full((T, 6), np.nan))


def _hand_map(points: np.ndarray, about: np.ndarray) -> np.ndarray:
    """(T, 2, 6, 6): wrench about `about` of a unit force / torque at each hand point."""
    T = points.shape[0]
    out = np.zeros((T, 2, 6, 6))
    out[..., :3, :3] = np.eye(3)
    out[..., 3:, :3] = skew(points - about[:, None])
    out[..., 3:, 3:] = np.eye(3)
    return out


def unconstrained_feet(body_wrench, root, foot_points, foot_active, reg: float = 1e-4) -> np.ndarray:
    """(T, 2, P, 3) N: free 3D sole forces explaining the body wrench (T, 6) about root (T, 3)
    by ridge least squares (no friction cone, no unilateral constraint), all frames at once."""
    T, P = foot_points.shape[0], foot_points.shape[2]
    A = wrench_map(foot_points.reshape(T, 2 * P, 3), root, np.eye(3))  # (T, 2P, 6, 3)
    A = A.transpose(0, 2, 1, 3).reshape(T, 6, 6 * P)
    A = A * np.repeat(np.asarray(foot_active, bool).reshape(T, 2 * P), 3, axis=1)[:, None]
    good = np.isfinite(A).all((1, 2)) & np.isfinite(body_wrench).all(1)
    A, w = np.where(good[:, None, None], A, 0), np.where(good[:, None], body_wrench, 0)
    H = A.transpose(0, 2, 1) @ A + reg * np.eye(6 * P)
    x = np.linalg.solve(H, np.einsum("tkn,tk->tn", A, w)[..., None])[..., 0]
    x[~good] = np.nan
    return x.reshape(T, 2, P, 3)


def cone_violation(forces: np.ndarray, normal: np.ndarray, mu: float, min_force: float = 1.0) -> np.ndarray:
    """(...,) bool: forces (..., 3) outside the friction cone (pulling, or |f_t| > mu f_n);
    forces below `min_force` N count as none."""
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    fn = forces @ n
    ft = np.linalg.norm(forces - fn[..., None] * n, axis=-1)
    big = np.linalg.norm(forces, axis=-1) >= min_force
    return big & ((fn < 0) | (ft > mu * fn + 1e-9))
