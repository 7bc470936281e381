"""Newton-Euler over rigid segments in the world frame, batched over frames.

Each segment s has mass m, centre of mass c (T, 3), inertia I (T, 3, 3) about c (world frame),
linear acceleration a, angular velocity w and acceleration al. What it needs to move as it does:

    F = m (a - g)                       (newton_force)
    N = I al + w x (I w)                (euler_torque, about c)

A tree of bones carries the segments (each segment rides on one bone). The wrench that a
bone's parent must apply through the joint at the bone's head p_j to its whole subtree is the
sum of the subtree's needs minus the external (contact) wrenches acting on it:

    f_j = sum_s F_s - sum_k f_k
    t_j = sum_s (N_s + (c_s - p_j) x F_s) - sum_k (tau_k + (r_k - p_j) x f_k)   (joint_wrenches)

computed in one reverse sweep over the bones (children before parents), all frames at once.
At the root, (f_0, t_0) is the residual wrench no contact explains (a free-flying root's
"actuation"): zero for a body moved by its contacts alone.
"""
from __future__ import annotations

import numpy as np
import torch


def newton_force(mass: torch.Tensor, acc: torch.Tensor, gravity: torch.Tensor) -> torch.Tensor:
    """(T, S, 3) N: m (a - g) for masses (S,), accelerations (T, S, 3), gravity (3,)."""
    return mass[None, :, None] * (acc - gravity)


def euler_torque(inertia: torch.Tensor, omega: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """(T, S, 3) N m about the COM: I al + w x (I w), inertia (T, S, 3, 3) world frame."""
    Iw = torch.einsum("tsij,tsj->tsi", inertia, omega)
    return torch.einsum("tsij,tsj->tsi", inertia, alpha) + torch.cross(omega, Iw, dim=-1)


def rotate_inertia(inertia_rest: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """(T, S, 3, 3) world inertia Q I_rest Q^T for rest inertias (S, 3, 3) and rotations Q (T, S, 3, 3)."""
    return rotation @ inertia_rest[None] @ rotation.transpose(-1, -2)


def joint_wrenches(parents, seg_bone, force, torque, com, joints, ext_bone=None, ext_force=None,
                   ext_torque=None, ext_point=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Force (T, J, 3) and torque (T, J, 3) about each bone's head that the parent applies to the
    bone's subtree. parents (J,) with parents[j] < j (root -1); segment needs force / torque
    (T, S, 3) at com (T, S, 3) carried by bones seg_bone (S,); bone heads joints (T, J, 3);
    external wrenches ext_force / ext_torque (T, K, 3) at ext_point (T, K, 3) on bones ext_bone (K,)."""
    T, J = joints.shape[:2]
    dev, dt = joints.device, joints.dtype
    seg_bone = torch.as_tensor(np.asarray(seg_bone), device=dev, dtype=torch.long)
    own_f = torch.zeros(T, J, 3, dtype=dt, device=dev).index_add_(1, seg_bone, force)
    moment = torque + torch.cross(com, force, dim=-1)  # about the world origin, additive
    own_m = torch.zeros(T, J, 3, dtype=dt, device=dev).index_add_(1, seg_bone, moment)
    if ext_bone is not None and len(ext_bone):
        eb = torch.as_tensor(np.asarray(ext_bone), device=dev, dtype=torch.long)
        own_f = own_f.index_add(1, eb, -ext_force)
        own_m = own_m.index_add(1, eb, -(ext_torque + torch.cross(ext_point, ext_force, dim=-1)))
    f, m = list(own_f.unbind(1)), list(own_m.unbind(1))
    for j in range(J - 1, 0, -1):  # bones, not frames: children before parents
        p = int(parents[j])
        f[p] = f[p] + f[j]
        m[p] = m[p] + m[j]
    f, m = torch.stack(f, 1), torch.stack(m, 1)
    return f, m - torch.cross(joints, f, dim=-1)


def rigid_body_wrench(mass: float, inertia: torch.Tensor, acc: torch.Tensor, omega: torch.Tensor,
                      alpha: torch.Tensor, gravity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Force (T, 3) and torque about the COM (T, 3) one rigid body (the object) needs; inertia (T, 3, 3)."""
    m = torch.as_tensor([mass], dtype=acc.dtype, device=acc.device)
    F = newton_force(m, acc[:, None], gravity)[:, 0]
    N = euler_torque(inertia[:, None], omega[:, None], alpha[:, None])[:, 0]
    return F, N
