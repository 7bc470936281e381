"""What a person is told, in the log and the report, when the joint fit's checks find something wrong
with a take: cameras out of sync (`calib.time_offsets`), or the motion terms and the data disagreeing
(most often a wrong frame rate). Below the stages, so the report reads them without a stage.
"""
from __future__ import annotations


def unsynchronised(offsets_ms: dict, limit_ms: float) -> str:
    """What a person is told (log and report) of cameras whose frames lag or lead the others' by
    more than `limit_ms` (global.max_camera_offset_ms); empty when none does."""
    off = {name: ms for name, ms in offsets_ms.items() if abs(ms) > limit_ms > 0}
    if not off:
        return ""
    return (", ".join(f"{name} {ms:+.0f} ms" for name, ms in off.items()) + " against the other cameras: their "
            "frames seem taken at other times (a lone camera shows part of its lag). Were the devices recorded with "
            "wired sync? Each such view puts the moving person where the others do not")


def data_disagreement(ratio: float, fps: float) -> str:
    """What a person is told (log and report) when the joint fit raised the keypoints' energy `ratio`
    times, past `global.max_keypoint_energy_ratio`: most often a wrong frame rate."""
    return (f"the joint fit moved the body away from its keypoints (their energy x{ratio:.1f}): the motion terms "
            f"and the data disagree. Is session.yaml's fps ({fps:g}) the rate of the frames given? If frames were "
            "skipped, set it to theirs")
