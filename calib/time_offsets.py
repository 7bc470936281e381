"""Temporal check of a rig: are its cameras' frames taken at the same time?

A camera whose frames are taken δ seconds after the others' (devices recording without wired sync
drift by up to half a frame period) sees the person where the fitted motion puts them δ later: its
2D keypoints lie off the fit's projections along the projected velocity. The least-squares δ of
those residuals on that velocity, per camera, measures it. The fit follows the cameras' majority,
so a lone late camera shows only part of its lag, and offsets are given against the cameras'
median (figures on late and synchronised rigs: BENCHMARKS.md, 2026-11-29, cameras out of sync).
"""
from __future__ import annotations

import numpy as np
import torch

from intercap.geometry.cameras import Cameras, project


def camera_time_offsets(keypoints3d: np.ndarray, observed: np.ndarray, frames: np.ndarray, cameras: Cameras,
                        fps: float, max_residual_px: float = 20.0) -> np.ndarray:
    """(C,) seconds each camera's keypoints lag the fitted motion, against the cameras' median;
    NaN for a camera without moving keypoints.

    keypoints3d: (T, K, 3) fitted world keypoints of every frame (NaN where none); observed:
    (F, C, K, 3) pixels and confidence (0: none) of the frames `frames` (F,) (indices into T, each
    with both neighbours); residuals over `max_residual_px` (a wrong detection) are left out."""
    X = np.asarray(keypoints3d, np.float64)
    frames = np.asarray(frames, np.int64)
    velocity = (X[frames + 1] - X[frames - 1]) * fps / 2  # (F, K, 3) m/s
    here = X[frames]
    cams = cameras.to(device="cpu", dtype=torch.float64)
    step = 1e-3  # s: the projection's derivative along the motion, by a small step
    offsets = np.full(len(cameras), np.nan)
    for c in range(len(cameras)):
        one = cams.select([c])
        pix, _ = project(torch.from_numpy(here.reshape(1, -1, 3)), one)
        ahead, _ = project(torch.from_numpy((here + step * velocity).reshape(1, -1, 3)), one)
        pix = pix[0].numpy().reshape(here.shape[:2] + (2,))
        along = (ahead[0].numpy().reshape(pix.shape) - pix) / step  # (F, K, 2) px/s
        residual = observed[:, c, :, :2] - pix
        weight = observed[:, c, :, 2]
        ok = (weight > 0) & np.isfinite(residual).all(-1) & np.isfinite(along).all(-1)
        ok &= np.linalg.norm(np.where(np.isfinite(residual), residual, np.inf), axis=-1) < max_residual_px
        w = weight[ok][:, None]
        curvature = float((w * along[ok] ** 2).sum())
        if curvature > 0:
            offsets[c] = float((w * residual[ok] * along[ok]).sum()) / curvature
    return offsets - np.nanmedian(offsets) if np.isfinite(offsets).any() else offsets
