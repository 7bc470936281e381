"""The command line: --version, -v / -q on either side of the subcommand, a light --help, OUT/run.log,
no progress bars off a terminal, `run --frames` (and eval on those frames), `view --host`."""
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import intercap
from intercap.cli import build_parser, main, parse_frames
from intercap.config import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data_samples" / "sample"
PREPARE_FAST = ["--stages", "prepare", "--set", "prepare.calib_frames=2", "--set", "prepare.ground_frames=3",
                "--set", "report.enabled=false"]


def intercap_cli(*args, timeout=120):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "intercap.cli", *map(str, args)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_version_is_the_packages(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"intercap {intercap.__version__}"


@pytest.mark.parametrize("argv", [["-v", "run", "S", "--out", "O"], ["run", "S", "--out", "O", "-v"],
                                  ["run", "S", "-v", "--out", "O"]])
def test_verbose_before_or_after_the_subcommand(argv):
    args = build_parser("run").parse_args(argv)
    assert args.log_verbose is True and not getattr(args, "log_quiet", False)


@pytest.mark.parametrize("argv", [["-q", "report", "O"], ["report", "O", "--quiet"],
                                  ["import", "k4a", "S", "a.mkv", "-q"], ["eval", "O", "-q"]])
def test_quiet_before_or_after_the_subcommand(argv):
    args = build_parser(argv[0] if argv[0] != "-q" else argv[1]).parse_args(argv)
    assert args.log_quiet is True


def test_verbose_and_quiet_together_is_an_error(capsys):
    assert main(["run", "S", "--out", "O", "-v", "-q"]) == 2
    assert "-v and -q" in capsys.readouterr().err


def test_help_does_not_import_torch_or_open3d():
    code = ("import sys, contextlib, io\n"
            "from intercap.cli import main\n"
            "for argv in (['--help'], ['run', '--help'], ['import', 'k4a', '--help'], ['view', '--help']):\n"
            "    with contextlib.redirect_stdout(io.StringIO()):\n"
            "        try:\n"
            "            main(argv)\n"
            "        except SystemExit:\n"
            "            pass\n"
            "print(sorted(m for m in ('torch', 'open3d', 'trimesh', 'cv2') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("command, option", [("synth", "--preset"), ("calibrate", "--square-m")])
def test_synth_and_calibrate_help_do_not_import_the_heavy_libraries(command, option):
    """Their options come from light modules: the help lists them (and exits 0) with none of torch,
    open3d, trimesh or cv2 imported; the generator and the calibration import them when they run."""
    code = ("import sys, contextlib, io\n"
            "from intercap.cli import main\n"
            "text = io.StringIO()\n"
            "with contextlib.redirect_stdout(text):\n"
            "    try:\n"
            f"        main([{command!r}, '--help'])\n"
            "    except SystemExit as exc:\n"
            "        assert exc.code == 0, exc.code\n"
            f"assert {option!r} in text.getvalue(), text.getvalue()\n"
            "print(sorted(m for m in ('torch', 'open3d', 'trimesh', 'cv2') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_python_m_synth_help_does_not_import_torch():
    out = subprocess.run([sys.executable, "-X", "importtime", "-m", "intercap.synth", "--help"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "--preset" in out.stdout
    imported = {line.rsplit("|", 1)[-1].strip() for line in out.stderr.splitlines() if line.startswith("import time:")}
    assert "intercap.synth.options" in imported
    assert not imported & {"torch", "open3d", "trimesh", "cv2"}


def test_quiet_run_logs_to_run_log_without_progress_bars(tmp_path):
    """-q after the subcommand: nothing but warnings on stderr, no carriage returns (stderr is a pipe);
    OUT/run.log gets the INFO lines with timestamps, appended by the resumed run."""
    out = tmp_path / "out"
    first = intercap_cli("run", SAMPLE, "--out", out, *PREPARE_FAST, "-q")
    assert first.returncode == 0, first.stderr
    assert "\r" not in first.stderr and "INFO" not in first.stderr
    assert "prepare:" not in first.stdout and "results in" in first.stdout
    log = (out / "run.log").read_text()
    assert re.search(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ INFO intercap.pipeline: prepare: done", log, re.M)
    second = intercap_cli("-v", "run", SAMPLE, "--out", out, *PREPARE_FAST)
    assert second.returncode == 0, second.stderr
    assert "\r" not in second.stderr and "INFO" in second.stderr
    again = (out / "run.log").read_text()
    assert again.startswith(log) and "already done" in again[len(log):]
    assert "DEBUG" not in again  # the file keeps INFO and up


def test_parse_frames():
    assert parse_frames("5:14") == (5, 14)
    assert parse_frames("5:") == (5, None) and parse_frames(":14") == (None, 14)
    assert parse_frames(None) is None
    for bad in ("5", "a:b", "9:3", "-1:4"):
        with pytest.raises(ConfigError, match="--frames"):
            parse_frames(bad)


def test_session_restricted_to_frames_cuts_its_ground_truth():
    from intercap.session import Session

    session = Session.load(SAMPLE)
    full = session.ground_truth()
    session.restrict_frames(5, 14)
    assert session.frame_ids.tolist() == list(range(5, 15)) and session.run_frames == (5, 14)
    gt = session.ground_truth()
    np.testing.assert_array_equal(gt.body_vertices, full.body_vertices[5:15])
    np.testing.assert_array_equal(gt.object_t, full.object_t[5:15])
    np.testing.assert_array_equal(gt.contact, full.contact[5:15])
    with pytest.raises(ValueError, match="outside"):
        session.restrict_frames(3, 9)
    whole = Session.load(SAMPLE)
    whole.restrict_frames(None, None)
    assert whole.run_frames is None  # the whole range: a whole-session run, same stage fingerprints


def test_run_on_a_frame_range_records_it(tmp_path):
    out = tmp_path / "out"
    code = main(["run", str(SAMPLE), "--out", str(out), *PREPARE_FAST, "--frames", "5:14", "-q"])
    assert code == 0
    assert json.loads((out / "run.json").read_text())["frames"] == [5, 14]
    assert len(json.loads((out / "prepare" / "ground.json").read_text())["normal"]) == 3
    assert main(["run", str(SAMPLE), "--out", str(out), *PREPARE_FAST, "--frames", "20:40", "-q"]) == 2


def _results_from_truth(out: Path, rows: slice, frames: list[int] | None) -> None:
    """A results folder holding the ground truth's own rows (a perfect fit) of `rows`."""
    gt = SAMPLE / "ground_truth"
    out.mkdir()
    for name in ("body_vertices.npy", "contact.npy", "keypoints3d.npy"):
        np.save(out / name, np.load(gt / name)[rows])
    shutil.copy(gt / "body_faces.npy", out / "body_faces.npy")
    with np.load(gt / "object_poses.npz") as z:
        np.savez(out / "object_poses.npz", R=z["R"][rows], t=z["t"][rows])
    record = {"session": str(SAMPLE), "stages": []}
    if frames is not None:
        record["frames"] = frames
    (out / "run.json").write_text(json.dumps(record))


def test_eval_cuts_the_ground_truth_to_the_runs_frames(tmp_path):
    from intercap.evaluation.evaluate import evaluate

    _results_from_truth(tmp_path / "part", slice(5, 15), [5, 14])
    result = evaluate(tmp_path / "part", SAMPLE, surface_samples=200)
    assert result.metrics["frames"] == 10 and result.per_frame["frame"][0] == 5
    assert result.metrics["object_add_mm"] < 1e-3 and result.metrics["keypoint_mpjpe_mm"] < 1e-3
    _results_from_truth(tmp_path / "unrecorded", slice(5, 15), None)  # no range recorded: a mismatch
    with pytest.raises(ValueError, match="frame count mismatch"):
        evaluate(tmp_path / "unrecorded", SAMPLE, surface_samples=200)


def test_view_host_reaches_the_server(monkeypatch, tmp_path):
    import intercap.evaluation.viewer as viewer

    seen = {}
    monkeypatch.setattr(viewer, "serve", lambda out, **kw: seen.update(kw))
    assert main(["view", str(tmp_path), "--host", "0.0.0.0", "--port", "8123"]) == 0
    assert seen["host"] == "0.0.0.0" and seen["port"] == 8123
    assert build_parser("view").parse_args(["view", "O"]).host == "127.0.0.1"


def test_stage_workers_open_the_runs_frames(tmp_path):
    """Workers reload the session from its path: they take the range OUT/run.json records."""
    from intercap.session.frame_cache import open_session

    (tmp_path / "run.json").write_text(json.dumps({"session": str(SAMPLE), "stages": [], "frames": [5, 14]}))
    session = open_session(str(SAMPLE), tmp_path)
    assert session.frame_ids.tolist() == list(range(5, 15)) and session.run_frames == (5, 14)
    assert len(session.ground_truth().contact) == 10
