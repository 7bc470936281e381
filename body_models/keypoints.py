"""OpenPose keypoint order: BODY_25, then left hand 21, right hand 21, then face 70.

Every body model maps its own joints and vertices onto this order, so 2D
detections, 3D ground truth and fitted bodies all share one layout.
"""
from __future__ import annotations

BODY_25 = [
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist",
    "left_shoulder", "left_elbow", "left_wrist", "mid_hip",
    "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle",
    "right_eye", "left_eye", "right_ear", "left_ear",
    "left_big_toe", "left_small_toe", "left_heel",
    "right_big_toe", "right_small_toe", "right_heel",
]

# OpenPose hand order: wrist, then thumb, index, middle, ring, little; four points each from the base.
FINGERS = ["thumb", "index", "middle", "ring", "little"]
HAND_21 = ["wrist"] + [f"{finger}_{k}" for finger in FINGERS for k in range(1, 5)]

NUM_BODY = 25
NUM_HAND = 21
NUM_FACE = 70
LEFT_HAND = slice(NUM_BODY, NUM_BODY + NUM_HAND)  # 25..45
RIGHT_HAND = slice(NUM_BODY + NUM_HAND, NUM_BODY + 2 * NUM_HAND)  # 46..66
FACE = slice(NUM_BODY + 2 * NUM_HAND, NUM_BODY + 2 * NUM_HAND + NUM_FACE)  # 67..136
NUM_BODY_HANDS = NUM_BODY + 2 * NUM_HAND  # 67, what ground truth and results store
NUM_ALL = NUM_BODY_HANDS + NUM_FACE  # 137, what an OpenPose JSON can hold

KEYPOINT_NAMES = (
    BODY_25
    + [f"left_hand_{n}" for n in HAND_21]
    + [f"right_hand_{n}" for n in HAND_21]
    + [f"face_{i:02d}" for i in range(NUM_FACE)]
)

# BODY_25 pairs used to draw skeletons.
BODY_25_EDGES = [
    (1, 8), (1, 2), (2, 3), (3, 4), (1, 5), (5, 6), (6, 7), (8, 9), (9, 10), (10, 11),
    (8, 12), (12, 13), (13, 14), (1, 0), (0, 15), (15, 17), (0, 16), (16, 18),
    (14, 19), (19, 20), (14, 21), (11, 22), (22, 23), (11, 24),
]
HAND_EDGES = [(0, 1 + 4 * f) for f in range(5)] + [
    (1 + 4 * f + k, 2 + 4 * f + k) for f in range(5) for k in range(3)
]
