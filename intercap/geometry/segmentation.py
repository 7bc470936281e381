"""Person / object segmentation from depth when the session has no masks.

A static background is learnt per camera from depth over time (the far,
stable value of each pixel; the person's pixels left out; regions beyond the
sensor's range known as far), foreground is what lies clearly in front of it,
and object candidates are the foreground outside the person. Which pixels are
the object is decided by the tracker (`intercap.stages.object`): those whose 3D
points lie near the object's predicted pose.
"""
from __future__ import annotations

import cv2
import numpy as np


def background_depth(depth_stack: np.ndarray, percentile: float = 90.0, min_valid_fraction: float = 0.75,
                     ignore: np.ndarray | None = None, far_fraction: float = 0.8) -> np.ndarray:
    """Per-pixel background depth (H, W) from depth maps (T, H, W) in metres.

    Moving people and objects are nearer than the background, so a high
    percentile of the valid samples is the background. A missing measurement
    inside a region where nearly nothing is measured (more than `far_fraction`
    of a window ~1/70 of the width wide) means the surface is beyond the
    sensor's range: that sample counts as infinitely far, so a pixel that shows
    the far wall in enough frames has an unknown background, 0 (whatever is
    measured there is in front of it), even if the object stood there in the
    others. Speckled dropouts (dark surfaces, edges) are no measurement at all,
    and a pixel with fewer samples than `min_valid_fraction` of the frames has
    an unknown background. `ignore` (T, H, W) bool marks samples known not to
    be background (the person's mask): they count as no measurement."""
    stack = np.asarray(depth_stack, dtype=np.float32)
    T, H, W = stack.shape
    missing = stack <= 0
    k = 2 * max(2, int(round(W / 140))) + 1  # at least 5 x 5: 40% scattered dropouts never fill 80% of it
    far = np.stack([cv2.blur(m.astype(np.float32), (k, k)) > far_fraction for m in missing]) & missing
    valid = (~missing | far) if ignore is None else (~missing | far) & ~ignore
    count = valid.sum(0)  # (H, W) samples per pixel
    # np.nanpercentile falls back to a per-pixel loop when NaNs are present (~10 s per
    # camera): sort once instead (unusable samples as NaN go last, beyond-range ones as +inf
    # just before them) and interpolate between the two ranks around the percentile, as
    # numpy's default method does.
    ordered = np.sort(np.where(valid, np.where(far, np.inf, stack), np.nan), axis=0)
    position = (np.maximum(count, 1) - 1) * (percentile / 100.0)
    lower = np.floor(position).astype(np.int64)
    upper = np.minimum(lower + 1, np.maximum(count - 1, 0))
    low = np.take_along_axis(ordered, lower[None], 0)[0]
    high = np.take_along_axis(ordered, upper[None], 0)[0]
    with np.errstate(invalid="ignore"):
        background = low + (high - low) * (position - lower)
    background[~np.isfinite(background) | (count < min_valid_fraction * T)] = 0
    return background.astype(np.float32)


def foreground_mask(depth: np.ndarray, background: np.ndarray, margin_m: float = 0.04, relative: float = 0.015) -> np.ndarray:
    """Pixels clearly in front of the background, (H, W) bool.

    The margin grows with depth (Kinect noise does); an unknown background
    (0) counts as infinitely far, a missing measurement as background."""
    valid = depth > 0
    known = background > 0
    threshold = np.where(known, background - (margin_m + relative * background), np.inf)
    return valid & (depth < threshold)


def uncertain_mask(depth: np.ndarray, background: np.ndarray, margin_m: float = 0.01, relative: float = 0.005) -> np.ndarray:
    """Pixels somewhat in front of the background, (H, W) bool: with `foreground_mask`'s
    default margins removed, those too near the background to tell apart from it
    (an object's part touching the floor), to be treated as unknown."""
    return foreground_mask(depth, background, margin_m, relative)


def fill_missing(mask: np.ndarray, depth: np.ndarray, radius_px: int) -> np.ndarray:
    """`mask` plus the pixels without a depth measurement that a closing of radius
    `radius_px` adds to it (dropouts inside and between its parts), (H, W) bool."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
    closed = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel).astype(bool)
    return mask | (closed & (depth <= 0))


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


# BODY_25 bones a person occupies (keypoint a, keypoint b, width in metres): head, torso, arms,
# legs. The hands are left out: they are where a held object is.
PERSON_BONES = (
    (0, 1, 0.20), (0, 17, 0.12), (0, 18, 0.12), (1, 8, 0.34), (2, 9, 0.14), (5, 12, 0.14), (2, 5, 0.14),
    (2, 3, 0.12), (5, 6, 0.12), (3, 4, 0.07), (6, 7, 0.07), (9, 12, 0.16),
    (9, 10, 0.16), (12, 13, 0.16), (10, 11, 0.12), (13, 14, 0.12),
)

HEAD_KEYPOINTS = (0, 15, 16, 17, 18)  # BODY_25 nose, eyes and ears: the face, whichever of them a view sees
CROWN = 0.6  # the top of the head lies beyond the face by this share of the neck-to-face line


def keypoint_depth(depth: np.ndarray, xy: np.ndarray, radius_px: int) -> float:
    """The person's depth at one keypoint (metres, 0 when unknown): the near third of the valid depths
    in a small window (a keypoint on the silhouette's edge has the background in its window too)."""
    H, W = depth.shape
    x, y = int(round(xy[0])), int(round(xy[1]))
    window = depth[max(0, y - radius_px):min(H, y + radius_px + 1), max(0, x - radius_px):min(W, x + radius_px + 1)]
    valid = window[window > 0]
    return float(np.percentile(valid, 33)) if valid.size else 0.0


def person_from_keypoints(keypoints: np.ndarray, depth: np.ndarray, focal_px: float, min_confidence: float = 0.3,
                          depth_band_m: float = 0.2, joint_depth_m: np.ndarray | None = None,
                          hidden_m: float = 0.5) -> np.ndarray:
    """Pixels of the person's head, trunk, arms and legs, (H, W) bool, from one view's 2D keypoints
    (OpenPose BODY_25 first, pixels) and its depth map: each bone of `PERSON_BONES`, and the face to
    the crown (`CROWN`), drawn as wide as the body part is at its depth, kept where the depth lies
    within `depth_band_m` of the bone's. A joint's depth is read from the depth map round its keypoint, unless
    `joint_depth_m` ((25,) metres in this camera, triangulated from all views; 0 or NaN: unknown) lies more than
    `hidden_m` behind that: the keypoint is hidden behind something (knees behind a table top), whose depth it
    read, and the thigh's band would take in a box standing on the table as the person.

    Where a raw session has no person masks, this keeps the person out of the search for an
    object: without it a head is a box-sized blob of foreground. The hands are not drawn."""
    H, W = depth.shape
    out = np.zeros((H, W), bool)
    radius = max(1, int(round(W / 160)))
    z = np.zeros(len(keypoints))
    seen = keypoints[:, 2] >= min_confidence
    for k in np.flatnonzero(seen[:25]):
        z[k] = keypoint_depth(depth, keypoints[k, :2], radius)
        hidden = joint_depth_m is not None and z[k] > 0 and joint_depth_m[k] > z[k] + hidden_m  # NaN: False
        if hidden:
            z[k] = joint_depth_m[k]
    xy = keypoints[:, :2]
    bones = [(xy[a], xy[b], z[a], z[b], width) for a, b, width in PERSON_BONES if seen[a] and seen[b]]
    face = [k for k in HEAD_KEYPOINTS if seen[k] and z[k] > 0]
    if face and seen[1]:  # face to crown (a head's top is a box-sized blob of its own), at the face's depth
        centre, z_face = xy[face].mean(0), float(np.median(z[face]))
        bones.append((centre, centre + CROWN * (centre - xy[1]), z_face, z_face, 0.20))
    for xy_a, xy_b, z_a, z_b, width in bones:
        if z_a <= 0 or z_b <= 0:
            continue
        near, far = min(z_a, z_b) - depth_band_m, max(z_a, z_b) + depth_band_m
        thickness = max(1, int(round(focal_px * width / ((z_a + z_b) / 2))))
        bone = np.zeros((H, W), np.uint8)
        cv2.line(bone, tuple(int(round(v)) for v in xy_a), tuple(int(round(v)) for v in xy_b), 1, thickness)
        out |= bone.astype(bool) & (depth > near) & (depth < far)
    return out


def chromaticity(rgb: np.ndarray) -> np.ndarray:
    """(N, 2) normalised red and green, r / (r + g + b) and g / (r + g + b), of (N, 3) RGB colours:
    the colour without its brightness, which shading changes over a surface."""
    rgb = np.asarray(rgb, np.float64)
    return rgb[:, :2] / np.maximum(rgb.sum(1, keepdims=True), 1.0)


class ColourLikelihood:
    """How much likelier a colour is on the object than on what it is told apart from (a hand):
    the two chromaticity histograms (`bins` per side, each smoothed over its neighbouring bins),
    from colour samples of each. Colours darker than `min_brightness` (r + g + b, 0-765) have no
    reliable chromaticity and are never the object's."""

    def __init__(self, object_rgb: np.ndarray, other_rgb: np.ndarray, bins: int = 32, min_brightness: float = 60.0):
        self.bins, self.min_brightness = bins, min_brightness
        self.object, self.other = (self._histogram(self._bright(s)) for s in (object_rgb, other_rgb))
        floor = 0.1 / bins ** 2  # keeps colours neither was seen in from dividing by nothing
        self._ratios = (self.object + floor * 1e-3) / (self.other + floor)

    def _bright(self, rgb: np.ndarray) -> np.ndarray:
        rgb = np.asarray(rgb, np.float64).reshape(-1, 3)
        return rgb[rgb.sum(1) >= self.min_brightness]

    def _cells(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rg = np.clip((chromaticity(rgb) * self.bins).astype(int), 0, self.bins - 1)
        return rg[:, 0], rg[:, 1]

    def _histogram(self, rgb: np.ndarray) -> np.ndarray:
        counts = np.zeros((self.bins, self.bins))
        np.add.at(counts, self._cells(rgb), 1.0)
        counts = cv2.blur(counts, (3, 3), borderType=cv2.BORDER_CONSTANT)
        return counts / max(counts.sum(), 1.0)

    def ratio(self, rgb: np.ndarray) -> np.ndarray:
        """(N,) object over other likelihood of each colour (0 for dark ones)."""
        rgb = np.asarray(rgb, np.float64).reshape(-1, 3)
        return np.where(rgb.sum(1) >= self.min_brightness, self._ratios[self._cells(rgb)], 0.0)

    def separable(self, ratio: float) -> float:
        """The share of the object's samples (histogram mass) whose colour passes `ratio`: how
        much of the object the test can tell apart."""
        return float(self.object[self._ratios > ratio].sum())
