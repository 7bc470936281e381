"""Velocities and accelerations without noise blow-up.

2 mm of position noise at 30 fps becomes metres per second squared of acceleration noise under
plain finite differences, so trajectories are filtered while they are differentiated:

* `savgol`: Savitzky-Golay, a local polynomial fit whose derivatives are taken analytically
  (scipy.signal.savgol_filter with deriv=1, 2);
* `adaptive` (the default, best in tools/bench_physics.py on noisy synthetic trajectories):
  Savitzky-Golay with each trajectory's window chosen by the discrepancy principle (the longest
  window whose residual stays within the estimated noise level);
* `butterworth`: zero-phase low-pass (scipy.signal.filtfilt), then central differences;
* `none`: central differences of the raw samples (for reference).

Rotations are filtered on the manifold: unit quaternions made sign-continuous, filtered and
differentiated like positions, and the angular velocity and acceleration read off exactly
(w = 2 vec(q' q*), world frame; a its filtered derivative). Gaps (NaN frames) are bridged by linear
interpolation before filtering and stay flagged invalid by the caller.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import butter, filtfilt, savgol_filter
from scipy.spatial.transform import Rotation

METHODS = ("adaptive", "savgol", "butterworth", "none")
ADAPTIVE_WINDOWS_S = (0.3, 0.5, 0.7, 1.0)


def fill_gaps(x: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(T, ...) with invalid / non-finite frames linearly interpolated in time (ends held)."""
    x = np.asarray(x, np.float64)
    flat = x.reshape(len(x), -1)
    ok = np.isfinite(flat).all(1) if valid is None else (np.asarray(valid, bool) & np.isfinite(flat).all(1))
    if ok.all() or not ok.any():
        return x.copy()
    t = np.arange(len(x))
    out = np.stack([np.interp(t, t[ok], flat[ok, k]) for k in range(flat.shape[1])], 1)
    return out.reshape(x.shape)


def short_gaps(valid: np.ndarray, max_frames: int) -> np.ndarray:
    """(T,) bool: the invalid frames in runs of at most `max_frames` with valid frames on both sides (a
    track lost for a moment, which interpolation bridges; not its ends, nor a long loss)."""
    from intercap.stages.contact.stage import runs_of

    valid = np.asarray(valid, bool)
    out = np.zeros(len(valid), bool)
    if max_frames < 1 or not valid.any():
        return out
    for start, end in runs_of(~valid):
        if 0 < start and end < len(valid) and end - start <= max_frames:
            out[start:end] = True
    return out


def fill_rotations(R: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations with the invalid frames interpolated (`fill_gaps` on the matrices, then the
    nearest rotation)."""
    filled = fill_gaps(R, valid)
    U, _, Vt = np.linalg.svd(filled)
    D = np.ones((len(R), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[:, None]) @ Vt


def _savgol_window(T: int, window: int, order: int) -> tuple[int, int]:
    """An odd window no longer than the sequence, and an order below it."""
    w = min(int(window) | 1, T if T % 2 else T - 1)
    return w, min(order, w - 1)


def derivatives(x: np.ndarray, fps: float, method: str = "adaptive", window_s: float = 0.3, order: int = 3,
                cutoff_hz: float = 6.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Filtered position, velocity and acceleration of samples x (T, ...) taken at `fps`."""
    if method not in METHODS:
        raise ValueError(f"physics.filter must be one of {', '.join(METHODS)}, got {method!r}")
    x = np.asarray(x, np.float64)
    T, dt = len(x), 1.0 / fps
    if T < 3:
        return x.copy(), np.zeros_like(x), np.zeros_like(x)
    if method == "adaptive":
        return adaptive_savgol(x, fps, order)
    if method == "savgol":
        w, p = _savgol_window(T, int(round(window_s * fps)), order)
        if w < 3 or p < 2:
            method = "none"
        else:
            return (savgol_filter(x, w, p, axis=0, mode="interp"),
                    savgol_filter(x, w, p, deriv=1, delta=dt, axis=0, mode="interp"),
                    savgol_filter(x, w, p, deriv=2, delta=dt, axis=0, mode="interp"))
    if method == "butterworth" and T > 15 and cutoff_hz < fps / 2:
        b, a = butter(4, cutoff_hz / (fps / 2))
        x = filtfilt(b, a, x, axis=0, padlen=min(3 * max(len(a), len(b)), T - 1))
    v = np.gradient(x, dt, axis=0)
    return x, v, np.gradient(v, dt, axis=0)


def noise_sigma(x: np.ndarray) -> np.ndarray:
    """(C,) robust white-noise level of each column of x (T, C) from third differences
    (var(d3 noise) = 20 sigma^2; smooth motion barely contributes at capture rates)."""
    d = np.diff(x, 3, axis=0)
    mad = np.median(np.abs(d - np.median(d, 0)), 0)
    return 1.4826 * mad / np.sqrt(20.0)


def adaptive_savgol(x: np.ndarray, fps: float, order: int = 3, windows_s=ADAPTIVE_WINDOWS_S, slack: float = 1.2):
    """Savitzky-Golay with the window chosen per column (discrepancy principle): the longest of
    `windows_s` whose smoothing residual is no larger than the column's estimated noise level,
    so still and free-flying trajectories get long windows and fast limbs short ones."""
    shape = x.shape
    flat = x.reshape(len(x), -1)
    T, dt = len(flat), 1.0 / fps
    if T < 8:
        return derivatives(x, fps, "savgol", window_s=windows_s[0], order=order)
    sigma = noise_sigma(flat)  # (C,)
    choice = np.zeros(flat.shape[1], int)
    for k, w_s in enumerate(windows_s):
        w, p = _savgol_window(T, int(round(w_s * fps)), order)
        if w <= p + 1:
            continue
        resid = np.sqrt(np.mean((flat - savgol_filter(flat, w, p, axis=0, mode="interp")) ** 2, 0))
        choice[resid <= slack * sigma] = k
    outs = [np.empty_like(flat) for _ in range(3)]
    for k in np.unique(choice):
        cols = choice == k
        w, p = _savgol_window(T, int(round(windows_s[k] * fps)), order)
        for d in range(3):
            outs[d][:, cols] = savgol_filter(flat[:, cols], w, p, deriv=d, delta=dt, axis=0, mode="interp")
    return tuple(o.reshape(shape) for o in outs)


def quaternion_derivatives(R: np.ndarray, fps: float, **filter_args) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Filtered rotations (T, ..., 3, 3), angular velocity (T, ..., 3) rad/s and angular
    acceleration (T, ..., 3) rad/s^2 in the world frame, from rotations R (T, ..., 3, 3)
    (body -> world)."""
    R = np.asarray(R, np.float64)
    lead = R.shape[:-2]
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(*lead, 4)  # (T, ..., 4) x y z w
    # sign continuity in time: flip where the quaternion jumps to the other hemisphere
    dots = np.sum(q[1:] * q[:-1], -1)  # (T-1, ...)
    flips = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
    q[1:] *= flips[..., None]
    qf, dq, ddq = derivatives(q, fps, **filter_args)
    norm2 = np.sum(qf * qf, -1, keepdims=True)
    omega = 2 * _vec_of_product_conj(dq, qf) / norm2
    # alpha = 2 vec(q'' q*) holds for unit q only; the filtered q is not quite unit, so the angular
    # velocity is differentiated instead (the same filter, its first derivative)
    alpha = derivatives(omega, fps, **filter_args)[1]
    Rf = Rotation.from_quat((qf / np.sqrt(norm2)).reshape(-1, 4)).as_matrix().reshape(*lead, 3, 3)
    return Rf, omega, alpha


def _vec_of_product_conj(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Vector part of p * conj(q) for quaternions stored x y z w (..., 4)."""
    pv, pw, qv, qw = p[..., :3], p[..., 3:], q[..., :3], q[..., 3:]
    return qw * pv - pw * qv - np.cross(pv, qv)
