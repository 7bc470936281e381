"""The prepare stage's calibration check on exact rigs (views that dropped frames, a raw take with a view cut
across the floor): never flagged, nothing refined; a knocked camera still flagged."""
import json
import shutil
from pathlib import Path

import numpy as np

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


def raw_sample_with_a_view_cut(tmp_path: Path) -> Path:
    """The sample as an own rig records it, colour and depth only (no masks, no keypoints), with cam0
    seeing only the right half of its image: its neighbours see floor beyond that cut, as beyond the
    shadow a table or a shelf casts on a raw take, that cam0 saw nothing of."""
    from intercap.synth.partial import crop_view

    session = crop_view(SAMPLE, tmp_path / "raw", "cam0", (160, 0, 160, 288))
    for folder in [*session.glob("cam*/masks"), *session.glob("cam*/keypoints")]:
        shutil.rmtree(folder)
    return session


def bump_camera(session: Path, name: str, translation_mm: float, rotation_deg: float, seed: int) -> None:
    """Move camera `name` in the session's calibration.json as a knock moves it (turned about its own
    centre and shifted), the images left as captured."""
    from tools.bench_calibration_check import drift_transform

    path = session / "calibration.json"
    calibration = json.loads(path.read_text())
    camera = next(c for c in calibration["cameras"] if c["name"] == name)
    pose = np.asarray(camera["T_world_from_cam"], float)
    camera["T_world_from_cam"] = (drift_transform(rotation_deg, translation_mm, seed, pose[:3, 3]) @ pose).tolist()
    path.write_text(json.dumps(calibration))


def test_a_raw_exact_rig_is_not_flagged_nor_moved_and_a_bumped_camera_is_flagged(tmp_path):
    """A raw take (colour and depth only) whose exact rig has a view cut across the shared floor: prepare
    flags no pair and moves no camera (it flagged cam3 -> cam0 at 154 mm and refined every camera); the
    same rig with cam2 knocked by 15 mm and 0.5 deg is flagged in both of cam2's pairs, cam2 suspect."""
    session = raw_sample_with_a_view_cut(tmp_path)
    settings = ["prepare.ground_frames=3", "run.stages=prepare", "report.enabled=false"]
    metrics = run_pipeline(session, tmp_path / "exact", load_config(overrides=settings), progress=False)["prepare"]
    assert metrics["calibration_pairs_flagged"] == 0 and metrics["calibration_suspect_cameras"] == []
    assert not metrics["calibration_refined"]
    assert not (tmp_path / "exact" / "prepare" / "calibration_refined.json").exists()

    bump_camera(session, "cam2", 15.0, 0.5, seed=2)
    cfg = load_config(overrides=settings + ["prepare.calib_refine=never"])
    metrics = run_pipeline(session, tmp_path / "bumped", cfg, progress=False)["prepare"]
    check = json.loads((tmp_path / "bumped" / "prepare" / "calibration_check.json").read_text())
    assert {(p["cam_a"], p["cam_b"]) for p in check["flagged"]} == {("cam1", "cam2"), ("cam2", "cam3")}
    assert metrics["calibration_suspect_cameras"] == ["cam2"]
