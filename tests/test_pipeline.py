"""Runner and prepare stage on the committed sample session."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from intercap.cli import main
from intercap.config import ConfigError, load_config
from intercap.pipeline import StageError, run_pipeline

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "sample"


def angle_deg(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    cfg = load_config(overrides=["prepare.calib_frames=2", "prepare.ground_frames=3", "run.stages=prepare"])
    metrics = run_pipeline(SAMPLE, out, cfg, progress=False)
    return out, cfg, metrics


def test_ground_plane_on_sample_matches_truth(prepared):
    out, _, metrics = prepared
    ground = json.loads((out / "prepare" / "ground.json").read_text())
    truth = json.loads((SAMPLE / "ground_truth" / "ground.json").read_text())
    assert ground["source"] == "ransac"
    assert angle_deg(ground["normal"], truth["normal"]) < 1.0  # also checks the up side
    offset = (np.array(ground["point"]) - np.array(truth["point"])) @ np.array(truth["normal"])
    assert abs(offset) < 0.01


def test_calibration_check_on_exact_calibration_is_small(prepared):
    out, _, _ = prepared
    check = json.loads((out / "prepare" / "calibration_check.json").read_text())
    assert len(check["pairs"]) >= 4  # a 4-camera ring: each camera with its neighbours
    for pair in check["pairs"]:
        if pair["overlap_points"] > 200:
            assert pair["correction_translation_mm"] < 10, pair
    assert not check["flagged"]


def test_outputs_config_and_metrics_written(prepared):
    out, _, metrics = prepared
    assert (out / "config.yaml").exists()
    assert set(metrics) == {"prepare"}
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["prepare"]["ground_source"] == "ransac"
    assert list((out / "prepare" / "clouds").glob("*.ply"))


def test_resume_skips_done_stage_and_redoes_changed_one(prepared):
    out, cfg, _ = prepared
    marker = out / "prepare" / "DONE.json"
    before = marker.read_text()
    run_pipeline(SAMPLE, out, cfg, progress=False)
    assert marker.read_text() == before  # skipped: the marker (with its finish time) is untouched
    changed = load_config(overrides=["prepare.calib_frames=1", "prepare.ground_frames=3", "run.stages=prepare"])
    run_pipeline(SAMPLE, out, changed, progress=False)
    assert json.loads(marker.read_text())["fingerprint"] != json.loads(before)["fingerprint"]


def test_unbuilt_or_unknown_stage_is_an_error_not_a_fake(tmp_path, monkeypatch):
    import intercap.pipeline as pipeline

    monkeypatch.setattr(pipeline, "ORDER", pipeline.ORDER + ["planned"])  # a listed stage not built yet
    with pytest.raises(StageError, match="not implemented yet"):
        run_pipeline(SAMPLE, tmp_path, load_config(overrides=["run.stages=planned"]), progress=False)
    with pytest.raises(StageError, match="unknown stage"):
        run_pipeline(SAMPLE, tmp_path, load_config(overrides=["run.stages=dance"]), progress=False)
    assert not (tmp_path / "planned").exists()


def test_config_overrides_and_errors(tmp_path):
    cfg = load_config(overrides=["prepare.voxel_size_m=0.02", "run.stages=prepare"])
    assert cfg.prepare.voxel_size_m == 0.02 and cfg.run.stages == ["prepare"]
    with pytest.raises(ConfigError, match="unknown config key 'prepare.voxel'"):
        load_config(overrides=["prepare.voxel=1"])
    with pytest.raises(ConfigError, match="expected a number"):
        load_config(overrides=["prepare.voxel_size_m=big"])
    assert load_config(overrides=["device=cuda"]).run.device == "cuda"  # a bare key: a `run` setting
    with pytest.raises(ConfigError, match="unknown config key 'voxel_size_m'"):
        load_config(overrides=["voxel_size_m=0.02"])
    with pytest.raises(ConfigError, match="global.line_search: expected one of auto, strong_wolfe, armijo"):
        load_config(overrides=["global.line_search=wolfe"])  # a choice is checked when read, not when reached
    yaml_file = tmp_path / "c.yaml"
    yaml_file.write_text("prepare:\n  pixel_stride: 4\n")
    assert load_config(yaml_file).prepare.pixel_stride == 4


def test_cli_validate_and_run_errors(tmp_path, capsys, monkeypatch):
    import intercap.pipeline as pipeline

    monkeypatch.setattr(pipeline, "ORDER", pipeline.ORDER + ["planned"])
    assert main(["validate", str(SAMPLE)]) == 0
    assert "cam" in capsys.readouterr().out
    assert main(["validate", str(tmp_path)]) == 1
    assert "session.yaml" in capsys.readouterr().out
    assert main(["run", str(SAMPLE), "--out", str(tmp_path / "o"), "--stages", "planned"]) == 2
    assert "not implemented yet" in capsys.readouterr().err


def test_a_device_this_machine_lacks_is_a_clear_error_before_any_stage(tmp_path, capsys):
    import torch

    cases = [("gpu", "is not a device"), ("mps", "only cpu and cuda")]
    if not torch.cuda.is_available():
        cases.append(("cuda", "CPU-only build" if not torch.backends.cuda.is_built() else "no CUDA GPU"))
    else:
        cases.append((f"cuda:{torch.cuda.device_count()}", "CUDA device"))
    for device, reason in cases:
        assert main(["run", str(SAMPLE), "--out", str(tmp_path / device), "--set", f"device={device}"]) == 2
        assert reason in capsys.readouterr().err
        assert not (tmp_path / device).exists()  # nothing started


def test_dense_frame_rates_run_with_the_dense_budgets(tiny_session, tmp_path, monkeypatch):
    """At run.dense_fps and above the stages get each *_dense budget in place of its plain one
    (a 30 fps take); below it, and in OUT/config.yaml, the settings stay as given."""
    import dataclasses

    import intercap.pipeline as pipeline
    from intercap.config import resolved, variant_settings

    cfg = load_config(overrides=["run.stages=prepare"])
    seen = []
    stage = pipeline.STAGES["prepare"]
    monkeypatch.setitem(pipeline.STAGES, "prepare", dataclasses.replace(
        stage, run=lambda session, cfg, out, progress: seen.append(cfg) or {}))
    run_pipeline(tiny_session, tmp_path / "out", cfg, progress=False)  # the tiny session is 30 fps
    budgets = [(section, setting, dense) for section in ("body", "global_", "object")
               for setting, dense, variant in variant_settings(getattr(cfg, section)) if variant == "dense"]
    assert len(budgets) == 3
    for section, setting, dense in budgets:
        given = getattr(cfg, section)
        assert getattr(given, setting) != getattr(given, dense)  # the test means something
        assert getattr(getattr(seen[0], section), setting) == getattr(given, dense)
        assert getattr(getattr(resolved(cfg, 5.0), section), setting) == getattr(given, setting)
        assert getattr(getattr(resolved(cfg, cfg.run.dense_fps), section), setting) == getattr(given, dense)
    assert load_config(tmp_path / "out" / "config.yaml").body.pose_steps == cfg.body.pose_steps


def test_a_stage_run_alone_keeps_the_work_of_the_full_run(tmp_path):
    """A stage's fingerprint covers the stages before it whether or not they run now: rerunning one
    stage alone (`--stages detect`, say after a crash) skips or resumes it, never wipes it."""
    cfg = load_config(overrides=["prepare.calib_frames=2", "prepare.ground_frames=3"])
    run_pipeline(SAMPLE, tmp_path, cfg, stages=["prepare", "detect"], progress=False)
    marker = tmp_path / "detect" / "DONE.json"
    before = marker.read_text()
    run_pipeline(SAMPLE, tmp_path, cfg, stages=["detect"], progress=False)
    assert marker.read_text() == before  # skipped, as in the full run
    changed = load_config(overrides=["prepare.calib_frames=1", "prepare.ground_frames=3"])
    run_pipeline(SAMPLE, tmp_path, changed, stages=["detect"], progress=False)  # its input's settings changed
    assert json.loads(marker.read_text())["fingerprint"] != json.loads(before)["fingerprint"]


def test_a_rerun_gives_the_same_numbers(tmp_path):
    """Two threads fit the body in one process (12 frames, one chunk): without `run.deterministic` the
    backward of indexing adds in thread order and the poses of two runs differed by 0.02 rad."""
    import torch

    from conftest import trimmed_copy

    session = trimmed_copy(SAMPLE, tmp_path / "session", 12)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        runs = []
        for k in range(2):
            run_pipeline(session, tmp_path / f"out{k}", load_config(overrides=["run.stages=body"]), progress=False)
            runs.append(np.load(tmp_path / f"out{k}" / "body" / "body_params.npz"))
    finally:
        torch.set_num_threads(threads)
    assert not torch.are_deterministic_algorithms_enabled()  # the caller's setting is given back
    for key in ("body_pose", "global_orient", "transl", "shape", "left_hand_pose"):
        assert np.array_equal(runs[0][key], runs[1][key]), key


def test_a_bumped_camera_is_refined_and_the_later_stages_see_it(tmp_path):
    """The sample with camera 2's calibration 10 mm / 0.5 deg off (a bumped camera): prepare's check
    flags it, `calib_refine=auto` corrects the poses (the cameras then put the subject at least 40 %
    nearer where most of them put it, and the whole world moves less than that), writes them as a
    calibration.json, and a worker's session takes
    them. With the refinement off, the next run's prepare leaves no corrected poses behind."""
    from intercap.session import Session
    from intercap.session.frame_cache import open_session
    from tools.bench_calibration_check import drift_transform
    from tools.bench_calibration_refine import subject_errors

    session = tmp_path / "bumped"
    session.mkdir()
    for entry in SAMPLE.iterdir():  # frame folders linked; files copied (session.yaml's paths stay inside)
        if entry.is_dir():
            (session / entry.name).symlink_to(entry)
        elif entry.name != "calibration.json":
            shutil.copy2(entry, session / entry.name)
    calibration = json.loads((SAMPLE / "calibration.json").read_text())
    true_poses = np.array([c["T_world_from_cam"] for c in calibration["cameras"]])
    bump = drift_transform(0.5, 10.0, seed=2, pivot=true_poses[2][:3, 3])
    calibration["cameras"][2]["T_world_from_cam"] = (bump @ true_poses[2]).tolist()
    (session / "calibration.json").write_text(json.dumps(calibration))

    out = tmp_path / "out"
    overrides = ["prepare.calib_frames=2", "prepare.ground_frames=3", "prepare.calib_refine_frames=4", "run.stages=prepare"]
    metrics = run_pipeline(session, out, load_config(overrides=overrides), progress=False)["prepare"]
    assert metrics["calibration_pairs_flagged"] >= 1 and metrics["calibration_refined"]
    refined = json.loads((out / "prepare" / "calibration_refined.json").read_text())
    poses = np.array([c["T_world_from_cam"] for c in refined["cameras"]])
    errors = poses @ np.linalg.inv(true_poses)  # world-frame error of each camera's pose
    subject = np.array([0.0, 0.0, 1.0])  # where the person stands
    before = subject_errors(np.stack([np.eye(4), np.eye(4), bump, np.eye(4)]), subject)
    after = subject_errors(errors, subject)
    print(f"cameras apart at the subject: {before[0]:.1f} -> {after[0]:.1f} mm, common shift {after[1]:.1f} mm")
    assert after[0] < 0.6 * before[0] and after[1] < before[0]
    worker = open_session(str(session), out)
    assert np.allclose([c.T_world_from_cam for c in worker.cameras], poses)
    assert np.allclose(worker.cameras[2].K, Session.load(session).cameras[2].K)

    run_pipeline(session, out, load_config(overrides=overrides + ["prepare.calib_refine=never"]), progress=False)
    assert not (out / "prepare" / "calibration_refined.json").exists()
    assert np.allclose(open_session(str(session), out).cameras[2].T_world_from_cam, bump @ true_poses[2])


@pytest.mark.parametrize("args, message", [
    (["--stages", ","], "--stages ',': an empty stage name"),
    (["--stages", "prepare,,detect"], "--stages 'prepare,,detect': an empty stage name"),
    (["--set", "prepare.pixel_stride={a"], "prepare.pixel_stride: '{a' is not a value"),
    (["--set", "prepare.pixel_stride=0"], "prepare.pixel_stride: must be greater than 0, got 0"),
    (["--set", "body.batch_frames=-2"], "body.batch_frames: must be greater than 0, got -2"),
    (["--set", "object.checkpoint_every=0"], "object.checkpoint_every: must be greater than 0, got 0"),
    (["--set", "run.workers=-1"], "run.workers: must be 0 or more, got -1"),
])
def test_cli_misuse_is_one_line_and_exit_2(tmp_path, capsys, args, message):
    """Bad --stages and --set values are refused when read, in one line, before anything is written."""
    assert main(["run", str(SAMPLE), "--out", str(tmp_path / "out"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"intercap run: error: {message}"), err
    assert not (tmp_path / "out").exists()


def test_a_session_that_does_not_exist_is_a_short_message(tmp_path, capsys):
    assert main(["run", str(tmp_path / "none"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and "Traceback" not in err and len(err.splitlines()) <= 5


def test_settings_below_their_range_are_refused_from_yaml_too(tmp_path):
    yaml_file = tmp_path / "c.yaml"
    yaml_file.write_text("global:\n  window_frames: 0\n")
    with pytest.raises(ConfigError, match="global.window_frames: must be greater than 0"):
        load_config(yaml_file)
    assert load_config(overrides=["run.workers=0", "prepare.pixel_stride=1"]).prepare.pixel_stride == 1


def test_an_unexpected_error_is_one_line_with_its_traceback_in_a_log(tmp_path, capsys, monkeypatch):
    """A bug inside a stage: one line with the error and the log file holding its traceback; -v
    lets the traceback through."""
    import intercap.pipeline as pipeline

    def broken(*args, **kwargs):
        raise RuntimeError("step must be nonzero")

    monkeypatch.setattr(pipeline, "run_pipeline", broken)
    assert main(["run", str(SAMPLE), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith("intercap run: unexpected error: RuntimeError: step must be nonzero (traceback in ")
    log_file = Path(err.split("traceback in ")[1].split(";")[0])
    try:
        assert "Traceback" in log_file.read_text() and "step must be nonzero" in log_file.read_text()
    finally:
        log_file.unlink()
    with pytest.raises(RuntimeError, match="step must be nonzero"):
        main(["-v", "run", str(SAMPLE), "--out", str(tmp_path / "out")])
