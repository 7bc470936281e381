"""Person / object segmentation from depth when the session has no masks.

A static background is learnt per camera from depth over time (the far,
stable value of each pixel), foreground is what lies clearly in front of it,
and object candidates are the foreground's connected components outside the
person. Which candidate is the object is decided by the tracker: the one that
best overlaps the rendering of the object's predicted pose
("render-compare-and-preserve", InterCap).
"""
from __future__ import annotations

import warnings

import cv2
import numpy as np


def background_depth(depth_stack: np.ndarray, percentile: float = 90.0, min_valid_fraction: float = 0.75) -> np.ndarray:
    """Per-pixel background depth (H, W) from depth maps (T, H, W) in metres.

    Moving people and objects are nearer than the background, so a high
    percentile of the valid samples is the background. A pixel that reads no
    measurement in many frames (beyond the sensor's range, or a dark far
    surface) has an unknown background, 0: whatever is measured there is in
    front of it. Sparse dropouts (edges, noise) stay below `min_valid_fraction`."""
    stack = np.asarray(depth_stack, dtype=np.float32)
    valid = stack > 0
    masked = np.where(valid, stack, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels
        background = np.nanpercentile(masked, percentile, axis=0)
    background[valid.mean(0) < min_valid_fraction] = 0
    return np.nan_to_num(background, nan=0.0).astype(np.float32)


def foreground_mask(depth: np.ndarray, background: np.ndarray, margin_m: float = 0.04, relative: float = 0.015) -> np.ndarray:
    """Pixels clearly in front of the background, (H, W) bool.

    The margin grows with depth (Kinect noise does); an unknown background
    (0) counts as infinitely far, a missing measurement as background."""
    valid = depth > 0
    known = background > 0
    threshold = np.where(known, background - (margin_m + relative * background), np.inf)
    return valid & (depth < threshold)


def clean_mask(mask: np.ndarray, open_px: int = 1) -> np.ndarray:
    """Remove speckle (morphological opening with a small disc)."""
    if open_px <= 0:
        return mask
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * open_px + 1, 2 * open_px + 1))
    return cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)


def components(mask: np.ndarray, min_area: int, bridge_px: int = 0) -> list[np.ndarray]:
    """Connected components (8-connected) of at least `min_area` pixels, largest first.

    `bridge_px` > 0 joins fragments separated by gaps up to about twice that
    (a thin-barred object cut apart by depth dropouts at its edges); each
    component keeps only pixels of `mask`."""
    joined = mask.astype(np.uint8)
    if bridge_px > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * bridge_px + 1, 2 * bridge_px + 1))
        joined = cv2.morphologyEx(joined, cv2.MORPH_CLOSE, kernel)
    count, labels, _, _ = cv2.connectedComponentsWithStats(joined, connectivity=8)
    parts = [(labels == k) & mask for k in range(1, count)]
    parts = [p for p in parts if p.sum() >= min_area]
    parts.sort(key=lambda p: -int(p.sum()))
    return parts


def select_object_candidate(
    foreground: np.ndarray,
    person: np.ndarray | None,
    predicted: np.ndarray | None,
    min_area: int = 30,
    grow_px: int = 6,
    bridge_px: int = 0,
) -> np.ndarray:
    """The object's mask in one view, (H, W) bool (empty when there is none).

    Candidates are foreground components outside the person mask. With a
    predicted silhouette (H, W) in [0, 1] (the rendering of the predicted pose),
    the candidate with the largest overlap wins and is clipped to the
    prediction grown by `grow_px` (cuts off the hand or arm still attached);
    without one, the largest candidate is returned."""
    candidates_mask = foreground & ~person if person is not None else foreground
    candidates = components(clean_mask(candidates_mask), min_area, bridge_px)
    if not candidates:
        return np.zeros_like(foreground, dtype=bool)
    if predicted is None:
        return candidates[0]
    weights = np.asarray(predicted, dtype=np.float32)
    overlaps = [float(weights[c].sum()) for c in candidates]
    best = int(np.argmax(overlaps))
    if overlaps[best] <= 0:
        return np.zeros_like(foreground, dtype=bool)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow_px + 1, 2 * grow_px + 1))
    region = cv2.dilate((weights > 0.5).astype(np.uint8), kernel).astype(bool)
    return candidates[best] & region
