"""Free flight of the object (GraviCap): episodes where nothing touches it, and parabola fits.

While the object touches neither the body nor the ground, its centre of mass follows
p(t) = p0 + v0 t + 0.5 a t^2 with a = g = -9.81 m/s^2 along the floor's normal. Fitting
that parabola to the tracked centres gives (free fit, a unknown) the gravity vector as the
data see it (|a| and its angle to -up: a check of the reconstruction's metric scale and of
the ground plane), (fixed fit, a = g) a trajectory to pull the object onto, and, with no
floor in view, the up direction itself (`gravity_from_flight`).

Arrays: centres (T, 3) metres, world; frames are indices into the session's frame_ids,
times are index / fps. NaN centres (untracked frames) are left out of every fit.
"""
from __future__ import annotations

import logging

import numpy as np

G = 9.81  # m/s^2
log = logging.getLogger(__name__)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"up direction {v.tolist()} has no direction")
    return v / n


def find_flight_episodes(centres, touching, up, fps: float, min_frames: int = 8,
                         min_travel_m: float = 0.03, max_gap_frames: int = 2) -> np.ndarray:
    """(E, 2) int: first and last frame (inclusive) of each run of at least `min_frames` frames in
    which the object touches nothing (`touching` (T,) bool: body contact or object-ground contact).

    A few untracked (NaN) frames inside a run do not split it, but a run needs at least
    `min_frames` tracked frames and no more than `max_gap_frames` NaN frames in a row; runs
    that start or end with NaN frames are trimmed to tracked ones. A run in which the centre
    travels less than `min_travel_m` (an object lying untouched: not a flight) is dropped."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    touching = np.asarray(touching, dtype=bool).reshape(-1)
    if len(touching) != len(centres):
        raise ValueError(f"touching has {len(touching)} frames, centres {len(centres)}")
    _unit(up)
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    tracked = np.isfinite(centres).all(1)
    free = ~touching
    out = []
    edges = np.diff(np.concatenate([[0], free.astype(np.int8), [0]]))
    for first, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        ok = tracked[first:stop]
        if not ok.any():
            continue
        # split the run where too many frames in a row are untracked
        pieces, start, missing = [], None, 0
        for k, good in enumerate(ok):
            if good:
                if start is None:
                    start = k
                last, missing = k, 0
            elif start is not None:
                missing += 1
                if missing > max_gap_frames:
                    pieces.append((start, last))
                    start, missing = None, 0
        if start is not None:
            pieces.append((start, last))
        for a, b in pieces:
            a, b = first + a, first + b
            sel = tracked[a:b + 1]
            if sel.sum() < min_frames:
                continue
            pts = centres[a:b + 1][sel]
            if np.linalg.norm(pts.max(0) - pts.min(0)) < min_travel_m:
                continue
            out.append((a, b))
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def _episode_design(frames: np.ndarray, first: int, fps: float) -> np.ndarray:
    t = (frames - first) / fps
    return np.stack([np.ones_like(t), t, 0.5 * t * t], 1)  # (n, 3)


def fit_flight(centres, episodes, fps: float, up, g: float = G) -> dict:
    """Least-squares parabolas through each episode's tracked centres.

    Returns (E episodes, T frames):
      acceleration (E, 3) m/s^2, free fit (g not imposed); g_norm (E,) its length;
      gravity_angle_deg (E,) its angle to -up; p0 (E, 3), v0 (E, 3) of the free fit at the
      episode's first frame; residual_m (E,) RMS distance of the centres to the free fit;
      fixed_fit (T, 3) positions of the fit with a = -g up imposed (NaN outside episodes),
      fixed_p0, fixed_v0 (E, 3), fixed_residual_m (E,); frames_used (E,) int.
    Episodes with fewer than 3 tracked frames (4 for the free fit's residual) give NaN."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    episodes = np.asarray(episodes, dtype=np.int64).reshape(-1, 2)
    up = _unit(up)
    gravity = -g * up
    E, T = len(episodes), len(centres)
    out = {k: np.full((E, 3), np.nan) for k in ("acceleration", "p0", "v0", "fixed_p0", "fixed_v0")}
    for k in ("g_norm", "gravity_angle_deg", "residual_m", "fixed_residual_m"):
        out[k] = np.full(E, np.nan)
    out["frames_used"] = np.zeros(E, np.int64)
    out["fixed_fit"] = np.full((T, 3), np.nan)
    for e, (a, b) in enumerate(episodes):
        if not (0 <= a <= b < T):
            raise ValueError(f"flight episode {a}..{b} lies outside the {T} frames")
        frames = np.arange(a, b + 1)
        frames = frames[np.isfinite(centres[frames]).all(1)]
        out["frames_used"][e] = len(frames)
        if len(frames) < 3:
            continue
        A = _episode_design(frames, a, fps)
        p = centres[frames]
        coef, *_ = np.linalg.lstsq(A, p, rcond=None)  # (3, 3): p0, v0, a per axis
        acc = coef[2]
        out["p0"][e], out["v0"][e], out["acceleration"][e] = coef
        out["g_norm"][e] = np.linalg.norm(acc)
        cos = acc @ -up / max(np.linalg.norm(acc), 1e-12)
        out["gravity_angle_deg"][e] = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        if len(frames) > 3:
            out["residual_m"][e] = np.sqrt(np.mean(np.sum((A @ coef - p) ** 2, 1)))
        lin, *_ = np.linalg.lstsq(A[:, :2], p - A[:, 2:] * gravity, rcond=None)  # p0, v0 with a = g
        out["fixed_p0"][e], out["fixed_v0"][e] = lin
        every = _episode_design(np.arange(a, b + 1), a, fps)
        out["fixed_fit"][a:b + 1] = every[:, :2] @ lin + every[:, 2:] * gravity
        out["fixed_residual_m"][e] = np.sqrt(np.mean(np.sum((A[:, :2] @ lin + A[:, 2:] * gravity - p) ** 2, 1)))
    return out


def falling_episodes(centres, episodes, fps: float, up, max_residual_m: float, g: float = G
                     ) -> tuple[np.ndarray, list[tuple[int, int, float]]]:
    """The episodes (E, 2) whose tracked centres follow a parabola under gravity (`fit_flight`'s
    fixed fit) within `max_residual_m` RMS, and the others as (first, last, residual_m). An object
    that touches nothing by the contact labels yet does not fall is held by a contact they missed
    (a cup at the mouth for 3 s, one view: it would have fallen 44 m)."""
    episodes = np.asarray(episodes, dtype=np.int64).reshape(-1, 2)
    if not len(episodes):
        return episodes, []
    residual = fit_flight(centres, episodes, fps, up, g)["fixed_residual_m"]
    falls = np.isfinite(residual) & (residual <= max_residual_m)
    return episodes[falls], [(int(a), int(b), float(r)) for (a, b), r in zip(episodes[~falls], residual[~falls])]


def warn_held(held: list[tuple[int, int, float]], stage: str) -> None:
    """Say which runs `falling_episodes` found held, not flying."""
    for a, b, residual in held:
        log.warning("%s: frames %d-%d: the object touches nothing by the contact labels, but does not fall (a "
                    "parabola under gravity misses its path by %.0f mm RMS): a contact they missed, not a free "
                    "flight", stage, a, b, 1000 * residual)


def gravity_from_flight(centres, episodes, fps: float, g_range=(6.0, 14.0)) -> dict:
    """The up direction from free flight alone (no floor in view): one acceleration shared by
    all episodes (each with its own p0, v0) fitted by least squares; up = -a / |a|.

    Returns up (3,), g_norm, acceleration (3,), episodes_used, frames_used, residual_m.
    Raises ValueError when no episode has 4 tracked frames or |a| lies outside `g_range`
    (then the flight is no flight, or the trajectory is not metric)."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    episodes = np.asarray(episodes, dtype=np.int64).reshape(-1, 2)
    blocks, rows = [], []
    for a, b in episodes:
        frames = np.arange(a, b + 1)
        frames = frames[np.isfinite(centres[frames]).all(1)]
        if len(frames) >= 4:
            blocks.append(_episode_design(frames, a, fps))
            rows.append(centres[frames])
    if not blocks:
        raise ValueError("gravity from flight: no free-flight episode with 4 tracked frames")
    n, E = sum(len(b) for b in blocks), len(blocks)
    A = np.zeros((n, 2 * E + 1))  # per episode p0, v0; one shared 0.5 t^2 column
    at = 0
    for e, block in enumerate(blocks):
        A[at:at + len(block), 2 * e:2 * e + 2] = block[:, :2]
        A[at:at + len(block), -1] = block[:, 2]
        at += len(block)
    p = np.concatenate(rows)
    coef, *_ = np.linalg.lstsq(A, p, rcond=None)
    acc = coef[-1]
    norm = float(np.linalg.norm(acc))
    if not g_range[0] <= norm <= g_range[1]:
        raise ValueError(f"gravity from flight: the fitted acceleration is {norm:.2f} m/s^2, not gravity "
                         f"(expected {g_range[0]}..{g_range[1]})")
    residual = float(np.sqrt(np.mean(np.sum((A @ coef - p) ** 2, 1))))
    return {"up": -acc / norm, "g_norm": norm, "acceleration": acc, "episodes_used": E, "frames_used": n,
            "residual_m": residual}


def object_on_ground(points, ground_point, up, margin_m: float = 0.02) -> np.ndarray:
    """(T,) bool: the posed object's surface points (T, M, 3) come within `margin_m` of the floor."""
    points = np.asarray(points, dtype=np.float64)
    height = (points - np.asarray(ground_point, np.float64)) @ _unit(up)  # (T, M)
    with np.errstate(invalid="ignore"):
        return np.nanmin(np.where(np.isfinite(height), height, np.inf), axis=1) < margin_m
