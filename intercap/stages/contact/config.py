"""The `contact` stage's settings (section `contact` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class ContactConfig:
    """Which frames have body-object contact: annotated ranges, or detected (2D mask overlap, 3D distance)."""

    method: str = "auto"  # "auto": the session's contact_frames when given, else `detector`; or "annotated", "2d", "3d"
    detector: str = "3d"  # what "auto" uses without annotations: "2d" (mask overlap) or "3d" (distance)
    regions: list[str] = field(default_factory=lambda: ["left_hand", "right_hand"])  # body regions whose touch counts
    distance_m: float = 0.01  # T_d: a region this close (m) to the object's surface touches it (3D)
    use_session_masks: bool = True  # 2D: the session's masks; False (or none given): silhouettes of the per-frame fits
    dilate_px: int = 1  # 2D: masks grow by this (at 640 px image width, scaled with it) before overlapping; 0 = not
    overlap_px: int = 20  # T_view: overlapping pixels (at 640 px width, scaled with image area) for a view to count
    overlap_views: int = 3  # T_frame: a frame is in contact when more than this many views count (3: all of 4)
    region_margin_m: float = 0.05  # annotated / 2D frames: regions this close (m) touch too, not just the nearest
    untracked_min_run: int = 3  # detected labels: a gap of untrusted frames between contact runs this long is contact
    clean_frames: int = 0  # detected labels: fill gaps and drop runs shorter than this many frames; 0 = off
    # detected labels: an object that touches nothing and the floor but does not fall is held (`held_frames`;
    # the global stage's flight_* settings decide a fall), by the regions that held it next to the run
    held: bool = True
    held_rest_m: float = 0.015  # ... until it comes to rest: its centre this near (m) where it lies at the run's end
