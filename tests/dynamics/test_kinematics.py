"""Filtered derivatives: accelerations from 2 mm noise stay small; rotations give exact rates."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from intercap.dynamics import kinematics as kin


def test_noisy_parabola_acceleration():
    fps, T = 30.0, 90
    t = np.arange(T) / fps
    a_true = np.array([0.5, -1.0, -9.81])
    x = np.array([0.1, 0.2, 1.0]) + np.outer(t, [0.3, 0.0, 4.0]) + 0.5 * np.outer(t**2, a_true)
    noisy = x + np.random.default_rng(0).normal(0, 0.002, x.shape)
    _, v, a = kin.derivatives(noisy, fps, "savgol", window_s=0.5, order=3)
    err = np.linalg.norm(a - a_true, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.3
    _, _, a_raw = kin.derivatives(noisy, fps, "none")
    assert np.sqrt(np.mean(np.linalg.norm(a_raw - a_true, axis=1) ** 2)) > 1.5  # what the filter prevents
    v_true = np.array([0.3, 0.0, 4.0]) + np.outer(t, a_true)
    assert np.median(np.linalg.norm(v - v_true, axis=1)) < 0.03


def test_rotation_rates_exact_on_the_manifold():
    fps, T = 30.0, 60
    t = np.arange(T) / fps
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    angle = 0.4 + 1.5 * t + 0.5 * 2.0 * t**2  # omega = 1.5 + 2 t, alpha = 2 (rad/s^2) about a fixed axis
    base = Rotation.from_rotvec([0.3, -0.2, 1.0])
    R = (Rotation.from_rotvec(angle[:, None] * axis) * base).as_matrix()
    Rf, omega, alpha = kin.quaternion_derivatives(R, fps, method="savgol", window_s=0.3, order=3)
    inner = slice(8, -8)  # the window's edges are extrapolated
    assert np.allclose(omega[inner], (1.5 + 2.0 * t[inner])[:, None] * axis, atol=5e-3)
    assert np.allclose(alpha[inner], 2.0 * axis, atol=5e-2)
    assert np.allclose(Rf[inner], R[inner], atol=1e-3)
    assert np.abs(omega - (1.5 + 2.0 * t)[:, None] * axis).max() < 0.2


def test_short_and_gappy_sequences():
    x = np.array([[0.0, 0, 0], [np.nan, np.nan, np.nan], [2.0, 0, 0]])
    assert np.allclose(kin.fill_gaps(x), [[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    _, v, a = kin.derivatives(kin.fill_gaps(x), 10.0, "savgol")
    assert np.allclose(v[:, 0], 10.0) and np.allclose(a, 0, atol=1e-9)
    with pytest.raises(ValueError, match="physics.filter"):
        kin.derivatives(x, 10.0, "kalman")
