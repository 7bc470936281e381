"""Newton-Euler: a torque-free tumbling body in free fall needs no wrench; a held arm's shoulder torque."""
import numpy as np
import torch
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from intercap.dynamics import kinematics as kin
from intercap.dynamics import newton_euler as ne

G = np.array([0.0, 0.0, -9.81])


def tumbling_body(fps=30.0, T=60):
    """Euler's equations for an asymmetric body spinning about no principal axis (torque-free),
    integrated finely and sampled at `fps`; its centre follows a gravity parabola."""
    I_body = np.diag([0.02, 0.05, 0.08])

    def rhs(_, y):
        w = y[:3]  # body-frame angular velocity
        q = y[3:]  # x y z w, body -> world
        dw = np.linalg.solve(I_body, -np.cross(w, I_body @ w))
        qv, qw = q[:3], q[3]
        dq_v = 0.5 * (qw * w + np.cross(qv, w))  # q' = 0.5 q (0, w_body)
        dq_w = -0.5 * qv @ w
        return np.concatenate([dw, dq_v, [dq_w]])

    t = np.arange(T) / fps
    sol = solve_ivp(rhs, (0, t[-1]), np.r_[1.0, 0.6, 2.0, 0, 0, 0, 1.0], t_eval=t, rtol=1e-10, atol=1e-12)
    q = sol.y[3:].T
    R = Rotation.from_quat(q / np.linalg.norm(q, axis=1, keepdims=True)).as_matrix()
    centre = np.array([0.0, 0.0, 2.0]) + np.outer(t, [0.5, 0.2, 3.0]) + 0.5 * np.outer(t**2, G)
    return I_body, R, centre


def test_torque_free_body_needs_no_wrench():
    fps = 30.0
    I_body, R, centre = tumbling_body(fps)
    Rf, omega, alpha = kin.quaternion_derivatives(R, fps, method="savgol", window_s=0.3, order=3)
    _, _, acc = kin.derivatives(centre, fps, method="savgol", window_s=0.3, order=3)
    td = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    inertia = Rf @ I_body @ Rf.transpose(0, 2, 1)
    F, N = ne.rigid_body_wrench(1.5, td(inertia), td(acc), td(omega), td(alpha), td(G))
    inner = slice(6, -6)
    assert F.abs().max() < 1e-6  # a parabola is free fall exactly
    scale = np.linalg.norm(I_body) * np.linalg.norm(omega, axis=1).max() ** 2
    assert N[inner].norm(dim=1).max() < 0.02 * scale
    # the same body with its spin ignored would need a large torque: the test can fail
    N_bad = ne.euler_torque(td(inertia)[:, None], td(omega)[:, None], td(np.zeros_like(alpha))[:, None])[:, 0]
    assert N_bad[inner].norm(dim=1).max() > 0.2 * scale


def test_joint_torque_of_a_held_horizontal_arm():
    """Two bones: a fixed 'torso' root and a 0.6 m horizontal arm of 4 kg (COM at 0.3 m): the
    shoulder must supply m g 0.3 N m about the horizontal axis, the root carries the whole weight."""
    T = 5
    joints = torch.zeros(T, 2, 3, dtype=torch.float64)
    joints[:, 0] = torch.tensor([0, 0, 1.0])
    joints[:, 1] = torch.tensor([0, 0, 1.5])  # shoulder
    com = torch.stack([joints[:, 0], joints[:, 1] + torch.tensor([0.3, 0, 0], dtype=torch.float64)], 1)
    mass = torch.tensor([30.0, 4.0], dtype=torch.float64)
    F = ne.newton_force(mass, torch.zeros(T, 2, 3, dtype=torch.float64), torch.tensor(G))
    N = torch.zeros(T, 2, 3, dtype=torch.float64)
    f, tau = ne.joint_wrenches([-1, 0], [0, 1], F, N, com, joints)
    assert torch.allclose(f[:, 1], torch.tensor([0, 0, 4 * 9.81], dtype=torch.float64))
    assert torch.allclose(tau[:, 1], torch.tensor([0, -4 * 9.81 * 0.3, 0], dtype=torch.float64))
    assert torch.allclose(f[:, 0], torch.tensor([0, 0, 34 * 9.81], dtype=torch.float64))
    # a hand pushing the arm's tip up with the arm's weight cancels the shoulder torque... twice over
    ext_f = torch.tensor([[[0, 0, 4 * 9.81 / 2]]], dtype=torch.float64).expand(T, 1, 3)
    ext_p = (joints[:, 1] + torch.tensor([0.6, 0, 0], dtype=torch.float64))[:, None]
    f, tau = ne.joint_wrenches([-1, 0], [0, 1], F, N, com, joints, [1], ext_f, torch.zeros_like(ext_f), ext_p)
    assert torch.allclose(tau[:, 1], torch.zeros(T, 3, dtype=torch.float64), atol=1e-9)
