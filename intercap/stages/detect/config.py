"""The `detect` stage's settings (section `detect` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class DetectConfig:
    """2D whole-body keypoints: the session's OpenPose JSON, or our own detector."""

    use_session_keypoints: bool = True  # False: detect even when the session has keypoints
    detector: str = "mediapipe"  # see intercap.stages.detect.stage.available_detectors()
    person_crop: bool = True  # detect again on a square crop around the person, resized to crop_size_px
    crop_size_px: int = 512  # side of the resized crop (pixels)
    crop_margin: float = 0.3  # the crop grows this fraction of the keypoints' box (longer side) beyond it on each side
    # margins (fractions, as crop_margin) tried in turn around the previous frame's box when the full image has no
    # person: a loose crop finds a bent-over person more often
    rescue_margins: list[float] = field(default_factory=lambda: [1.0, 1.5])
