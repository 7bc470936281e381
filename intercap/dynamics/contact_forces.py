"""Contact forces by bounded least squares.

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
    return friction_pyramids(normal, mu, edges)


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices: skew(a) @ b = a x b."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([z, -w, y, w, z, -x, -y, x, z], -1).reshape(*v.shape[:-1], 3, 3)


def wrench_map(points: np.ndarray, about: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(T, N, 6, K): the wrench (force; torque about `about` (T, 3)) of unit amounts along
    `directions` (3, K), or one set per point (T, N, 3, K), applied at points (T, N, 3)."""
    arm = skew(points - about[:, None])  # (T, N, 3, 3)
    top = np.broadcast_to(directions, (*points.shape[:2], 3, directions.shape[-1]))
    return np.concatenate([top, arm @ directions], -2)


@dataclass
class ContactSolution:
    hand_force: np.ndarray  # (T, 2, 3) N, by each hand on the object (or the fixed structure it grips)
    hand_torque: np.ndarray  # (T, 2, 3) N m, about the hand's contact point
    foot_point_force: np.ndarray  # (T, 2, P, 3) N, ground on each sole point
    object_ground_force: np.ndarray  # (T, Q, 3) N, ground on each object point
    body_residual: np.ndarray  # (T, 6) force N, torque N m about the root
    object_residual: np.ndarray  # (T, 6) force N, torque N m about the object's COM
    support_point_force: np.ndarray | None = None  # (T, S, 3) N, supports on each body point touching them


@dataclass
class TorquePrior:
    """Joint torques as a prior on how contacts share a load: tau = base + B x for the joints in
    `heads` (the physics stage: the trunk's and legs'); minimising w |tau|^2 besides the root's balance
    puts a seated body's weight through the seat rather than through bent knees (the body carries loads
    the way that needs least effort).
    carries_*: (J, n) bool, joint j carries that contact (its bone lies in the joint's subtree)."""

    heads: np.ndarray  # (T, J, 3) the joints' positions
    base: np.ndarray  # (T, J, 3) N m, their torques with no contact
    carries_hands: np.ndarray  # (J, 2)
    carries_feet: np.ndarray  # (J, 2P)
    carries_supports: np.ndarray | None = None  # (J, S)
    weight: float = 1e-2  # (N m)^-2 against the root balance's N^-2 / (N m)^-2


def friction_pyramids(normals: np.ndarray, mu: float, edges: int = 4) -> np.ndarray:
    """(..., 3, E) friction_pyramid of each normal (..., 3), all at once; zero for a zero or NaN normal.
    The tangents: t1 = n x (x axis, or y where n is nearly along x), t2 = n x t1."""
    if mu < 0:
        raise ValueError(f"physics.mu must be non-negative, got {mu}")
    n = np.asarray(normals, np.float64)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = np.isfinite(n).all(-1, keepdims=True) & (length > 0)
    n = np.where(ok, n / np.where(ok, length, 1.0), [0.0, 0.0, 1.0])
    a = np.where(np.abs(n[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    t2 = np.cross(n, t1)
    angles = 2 * np.pi * np.arange(edges) / edges
    d = np.cos(angles)[:, None] * t1[..., None, :] + np.sin(angles)[:, None] * t2[..., None, :]  # (..., E, 3)
    return np.where(ok[..., None], np.swapaxes(n[..., None, :] + mu * d, -1, -2), 0.0)


def solve_contacts(body_wrench, root, foot_points, foot_active, normal, mu, object_wrench=None, object_com=None,
                   hand_points=None, hand_active=None, object_points=None, object_active=None, edges: int = 4,
                   object_weight: float = 10.0, reg_force: float = 1e-4, reg_torque: float = 1e-2,
                   support_points=None, support_normals=None, support_active=None, grip_active=None,
                   torque_prior: TorquePrior | None = None, object_normals=None) -> ContactSolution:
    """Contact forces of T frames. body_wrench (T, 6) about root (T, 3); foot_points (T, 2, P, 3)
    with foot_active (T, 2, P); object_wrench (T, 6) about object_com (T, 3) or None (object
    unknown: hands on it and object-ground contacts are left out); hand_points (T, 2, 3), hand_active
    (T, 2); object_points (T, Q, 3), object_active (T, Q). Fixed supports (a seat, a table, a bar):
    body points support_points (T, S, 3) touching them (support_active (T, S)) push along their
    surface normals support_normals (T, S, 3) within friction pyramids; grip_active (T, 2): a hand
    grips a fixed structure (a free wrench on the body only). torque_prior: joint torques kept small.
    object_normals (T, Q, 3): the surface each object point rests on (a table top), default the floor's.
    Frames with non-finite inputs give NaN."""
    body_wrench = np.asarray(body_wrench, np.float64)
    T, P = body_wrench.shape[0], foot_points.shape[2]
    D = friction_pyramid(normal, mu, edges)  # (3, E)
    E = D.shape[1]
    has_object = object_wrench is not None
    grips = np.zeros((T, 2), bool) if grip_active is None else np.asarray(grip_active, bool)
    hands_used = has_object or grips.any()
    S = 0 if support_points is None else support_points.shape[1]
    Q = object_points.shape[1] if has_object and object_points is not None else 0
    # columns: hands (2 x 6), feet (2 x P x E), object points (Q x E), support points (S x E)
    c_feet, c_obj = 12, 12 + 2 * P * E
    c_sup = c_obj + Q * E
    n = c_sup + S * E
    hand_body = -_hand_map(hand_points, root) if hands_used else np.zeros((T, 2, 6, 6))
    A_body_feet = wrench_map(foot_points.reshape(T, 2 * P, 3), root, D)  # (T, 2P, 6, E)
    rows = 12 + (3 * torque_prior.heads.shape[1] if torque_prior is not None else 0)
    A = np.zeros((T, rows, n))
    A[:, :6, :12] = hand_body.transpose(0, 2, 1, 3).reshape(T, 6, 12)
    A[:, :6, c_feet:c_obj] = A_body_feet.transpose(0, 2, 1, 3).reshape(T, 6, 2 * P * E)
    b = np.zeros((T, rows))
    b[:, :6] = body_wrench
    active = np.zeros((T, n), bool)
    active[:, c_feet:c_obj] = np.repeat(np.asarray(foot_active, bool).reshape(T, 2 * P), E, axis=1)
    if has_object:
        on_object = _hand_map(hand_points, object_com) * (~grips)[:, :, None, None]  # a gripping hand is not on it
        A[:, 6:12, :12] = on_object.transpose(0, 2, 1, 3).reshape(T, 6, 12) * object_weight
        if Q:
            D_obj = (np.broadcast_to(D, (T, Q, 3, E)) if object_normals is None
                     else friction_pyramids(object_normals, mu, edges))  # (T, Q, 3, E)
            A_obj = wrench_map(object_points, object_com, D_obj)  # (T, Q, 6, E)
            A[:, 6:12, c_obj:c_sup] = A_obj.transpose(0, 2, 1, 3).reshape(T, 6, Q * E) * object_weight
            active[:, c_obj:c_sup] = np.repeat(np.asarray(object_active, bool), E, axis=1)
        b[:, 6:12] = np.asarray(object_wrench, np.float64) * object_weight
        active[:, :12] = np.repeat(np.asarray(hand_active, bool), 6, axis=1)
    active[:, :12] |= np.repeat(grips, 6, axis=1)
    D_sup = None
    if S:
        D_sup = friction_pyramids(support_normals, mu, edges)  # (T, S, 3, E)
        A_sup = wrench_map(support_points, root, D_sup)  # (T, S, 6, E)
        A[:, :6, c_sup:] = A_sup.transpose(0, 2, 1, 3).reshape(T, 6, S * E)
        active[:, c_sup:] = np.repeat(np.asarray(support_active, bool), E, axis=1)
    if torque_prior is not None:
        _torque_rows(A, b, torque_prior, hand_points if hands_used else None, foot_points, D, support_points, D_sup,
                     (c_feet, c_obj, c_sup))
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
    resid = b[:, :12] - np.einsum("tkn,tn->tk", A[:, :12], x)
    resid[:, 6:] /= object_weight
    x[~good] = np.nan
    resid[~good] = np.nan
    hands = x[:, :12].reshape(T, 2, 6)
    feet = np.einsum("ie,tpe->tpi", D, x[:, c_feet:c_obj].reshape(T, 2 * P, E)).reshape(T, 2, P, 3)
    obj = np.einsum("tqie,tqe->tqi", D_obj, x[:, c_obj:c_sup].reshape(T, Q, E)) if Q else np.zeros((T, 0, 3))
    sup = np.einsum("tsie,tse->tsi", D_sup, x[:, c_sup:].reshape(T, S, E)) if S else None
    return ContactSolution(hands[..., :3], hands[..., 3:], feet, obj, resid[:, :6],
                           resid[:, 6:] if has_object else np.full((T, 6), np.nan), sup)


def _torque_rows(A, b, prior: TorquePrior, hand_points, foot_points, D, support_points, D_sup, starts) -> None:
    """Fill the joint-torque rows of A and b (in place): sqrt(w) (B x + base) -> 0. An external force f
    at r on the body changes the torque at joint p that carries it by -(r - p) x f (newton_euler);
    the hands' columns are what the hand applies, the body feels the opposite."""
    T, J = prior.heads.shape[:2]
    w = np.sqrt(prior.weight)
    c_feet, c_obj, c_sup = starts
    rows = slice(12, 12 + 3 * J)
    b[:, rows] = -w * prior.base.reshape(T, 3 * J)
    heads = prior.heads[:, :, None]  # (T, J, 1, 3)

    def block(points, dirs, carries):  # points (T, N, 3), dirs (T, N, 3, K) -> (T, 3J, N K)
        arm = skew(points[:, None] - heads)  # (T, J, N, 3, 3)
        out = -(arm @ dirs[:, None]) * carries[None, :, :, None, None]  # (T, J, N, 3, K)
        return out.transpose(0, 1, 3, 2, 4).reshape(T, 3 * J, -1)

    P2 = foot_points.shape[1] * foot_points.shape[2]
    E = D.shape[1]
    feet_dirs = np.broadcast_to(D, (T, P2, 3, E))
    A[:, rows, c_feet:c_obj] = w * block(foot_points.reshape(T, P2, 3), feet_dirs, prior.carries_feet)
    if hand_points is not None:
        eye = np.broadcast_to(np.eye(3), (T, 2, 3, 3))
        force_part = -block(hand_points, eye, prior.carries_hands).reshape(T, 3 * J, 2, 3)
        torque_part = np.einsum("jh,ik->jihk", prior.carries_hands.astype(float), np.eye(3)).reshape(3 * J, 2, 3)
        A[:, rows, :12] = w * np.concatenate([force_part, np.broadcast_to(torque_part, force_part.shape)],
                                             -1).reshape(T, 3 * J, 12)
    if D_sup is not None:
        A[:, rows, c_sup:] = w * block(support_points, D_sup, prior.carries_supports)


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
