"""The prepare stage's calibration check on an exact rig whose views dropped frames: never flagged."""
import json
import shutil
from pathlib import Path

from intercap.config import PrepareConfig, load_config
from intercap.pipeline import run_pipeline
from intercap.session import Session
from intercap.stages.prepare.stage import checkable_frames, spread_frames

SAMPLE = Path(__file__).resolve().parents[2] / "data_samples" / "sample"
DROPPED = (14, 29)  # two of the three frames the check picks on the sample


def sample_without_depth(tmp_path: Path, cam: str, frames) -> Path:
    """A copy of the sample whose view `cam` lacks the depth files of `frames` (legal dropped frames)."""
    session = tmp_path / "session"
    shutil.copytree(SAMPLE, session, ignore=shutil.ignore_patterns("ground_truth"))
    for frame in frames:
        (session / cam / "depth" / f"{frame:06d}.png").unlink()
    return session


def test_checked_frames_are_frames_every_view_has(tmp_path):
    """With cam1's depth of two checked frames dropped, the check picks frames all four views have;
    an intact session keeps the frames it always had."""
    cfg = PrepareConfig()
    full = Session.load(SAMPLE)
    assert checkable_frames(full, cfg.calib_frames).tolist() == spread_frames(full.frame_ids, cfg.calib_frames).tolist()
    session = Session.load(sample_without_depth(tmp_path, "cam1", DROPPED))
    frames = checkable_frames(session, cfg.calib_frames)
    assert len(frames) == cfg.calib_frames and not set(DROPPED) & set(frames.tolist())


def test_dropped_depth_frames_do_not_flag_an_exact_rig(tmp_path):
    """An exact rig whose one view dropped two depth frames: prepare flags no pair and moves no camera."""
    session = sample_without_depth(tmp_path, "cam1", DROPPED)
    out = tmp_path / "out"
    cfg = load_config(overrides=["prepare.ground_frames=3", "run.stages=prepare", "report.enabled=false"])
    metrics = run_pipeline(session, out, cfg, progress=False)["prepare"]
    check = json.loads((out / "prepare" / "calibration_check.json").read_text())
    assert not set(DROPPED) & set(check["frames"])
    assert metrics["calibration_pairs_flagged"] == 0 and check["suspect_cameras"] == []
    assert not metrics["calibration_refined"] and not (out / "prepare" / "calibration_refined.json").exists()
