"""OpenPose JSON keypoints (BODY_25 + hands + face), the session format's keypoint files."""
from __future__ import annotations

from typing import Any

import numpy as np

# OpenPose JSON parts, in the order of the (137, 3) keypoint array.
OPENPOSE_PARTS = (
    ("pose_keypoints_2d", 25),
    ("hand_left_keypoints_2d", 21),
    ("hand_right_keypoints_2d", 21),
    ("face_keypoints_2d", 70),
)


NUM_KEYPOINTS_2D = sum(n for _, n in OPENPOSE_PARTS)  # 137


NUM_KEYPOINTS_3D = 67  # BODY_25 + left hand 21 + right hand 21


def openpose_to_array(data: Any) -> tuple[np.ndarray, list[str]]:
    """(137, 3) float32 [x, y, conf] of the first person in an OpenPose JSON object, and issues found.

    Order: BODY_25 (25), left hand (21), right hand (21), face (70). Missing or
    badly sized parts are left at zero (confidence 0 = not detected); no person
    gives all zeros. Raises ValueError when the object is not OpenPose JSON at all."""
    if not isinstance(data, dict) or not isinstance(data.get("people"), list):
        raise ValueError('not OpenPose JSON (expected {"people": [...]})')
    out = np.zeros((NUM_KEYPOINTS_2D, 3), np.float32)
    issues: list[str] = []
    if not data["people"]:
        return out, issues
    person = data["people"][0]
    if not isinstance(person, dict):
        raise ValueError("people[0] is not an object")
    start = 0
    for key, n in OPENPOSE_PARTS:
        values = person.get(key)
        if values is not None and len(values) > 0:
            try:
                arr = np.asarray(values, dtype=np.float32).reshape(-1)
            except (TypeError, ValueError):
                arr = None
            if arr is None or arr.size != 3 * n:
                size = "non-numeric" if arr is None else f"{arr.size} numbers"
                issues.append(f"{key} has {size}, expected {3 * n} ({n} points x [x, y, conf]); part ignored")
            else:
                out[start : start + n] = arr.reshape(n, 3)
        start += n
    return out, issues


CONFIDENCE_SLACK = 1e-3  # detectors' confidences may exceed 1 by float rounding


def drop_implausible_keypoints(kp: np.ndarray, width: int, height: int) -> tuple[np.ndarray, list[str]]:
    """`kp` (137, 3) with implausible keypoints set to zero (not detected), and what was dropped:
    non-finite values, confidence outside [0, 1], or a detected point more than an image size
    outside a width x height image. Confidences a hair above 1 are clipped to 1."""
    kp = kp.copy()
    finite = np.isfinite(kp).all(axis=1)
    conf = np.where(finite, kp[:, 2], 0.0)
    bad_conf = finite & ((conf < 0) | (conf > 1 + CONFIDENCE_SLACK))
    x, y = np.where(finite, kp[:, 0], 0.0), np.where(finite, kp[:, 1], 0.0)
    far = finite & (conf > 0) & ((np.abs(x - width / 2) > 1.5 * width) | (np.abs(y - height / 2) > 1.5 * height))
    issues = []
    for mask, what in ((~finite, "NaN or inf values"), (bad_conf, "confidence outside [0, 1]"),
                       (far & ~bad_conf, f"coordinates far outside the {width}x{height} image")):
        if mask.any():
            issues.append(f"{int(mask.sum())} keypoint(s) with {what} ignored (read as not detected)")
    kp[~finite | bad_conf | far] = 0.0
    kp[:, 2] = np.minimum(kp[:, 2], 1.0)
    return kp, issues
