"""`intercap run-many`: one pipeline per session as Ray tasks, a failing session reported, finished ones skipped."""
from __future__ import annotations

import csv
import json
import sys

import numpy as np
import pytest
from conftest import SAMPLE_SESSION, trimmed_copy

from intercap.cli import main

# prepare only, made cheap: one frame for the ground fit and one for the calibration check, no clouds written
QUICK = ["--stages", "prepare", "--set", "prepare.save_clouds=false", "--set", "prepare.calib_frames=1",
         "--set", "prepare.ground_frames=1"]


def make_sessions(tmp_path):
    sessions = tmp_path / "sessions"
    good = trimmed_copy(SAMPLE_SESSION, sessions / "good", 3)
    broken = sessions / "broken"
    broken.mkdir()
    (broken / "session.yaml").write_text("frames: [0, 1\nfps: : 30\n")  # unparsable YAML
    return sessions, good


def read_summary(root):
    with open(root / "summary.csv", newline="") as f:
        return {row["session"]: row for row in csv.DictReader(f)}


def test_run_many_on_local_ray_reports_failures_and_resumes(tmp_path, capsys):
    pytest.importorskip("ray", reason="ray not installed (pip install 'intercap[ray]')")
    sessions, good = make_sessions(tmp_path)
    root = tmp_path / "root"

    assert main(["run-many", str(sessions / "*"), "--out", str(root), *QUICK]) == 1  # one session failed
    printed = capsys.readouterr().out
    assert "good: 3 frames" in printed and "broken: failed: SessionError" in printed

    rows = read_summary(root)
    assert rows["good"]["status"] == "ok" and rows["good"]["frames"] == "3"
    assert float(rows["good"]["s_per_frame"]) > 0
    assert rows["broken"]["status"] == "failed"
    assert "session.yaml" in rows["broken"]["reason"] and "\n" not in rows["broken"]["reason"]
    done = root / "good" / "prepare" / "DONE.json"
    assert json.loads(done.read_text())["stage"] == "prepare"
    assert not (root / "broken" / "prepare" / "DONE.json").exists()
    # the good session's ground plane is the true one (z up, through the origin)
    truth = json.loads((good / "ground_truth" / "ground.json").read_text())
    fitted = json.loads((root / "good" / "prepare" / "ground.json").read_text())
    assert abs(np.dot(fitted["normal"], truth["normal"])) > 0.999

    # rerun (in-process this time: no second Ray start-up): the finished session is skipped, untouched
    stamp = done.stat().st_mtime_ns
    assert main(["run-many", str(sessions / "*"), "--out", str(root), "--local", *QUICK]) == 1
    rows = read_summary(root)
    assert rows["good"]["status"].startswith("skipped") and rows["good"]["frames"] == "3"
    assert rows["broken"]["status"] == "failed"
    assert done.stat().st_mtime_ns == stamp


def test_run_many_without_ray_says_how_to_install(tmp_path, monkeypatch, capsys):
    sessions, _ = make_sessions(tmp_path)
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    assert main(["run-many", str(sessions / "broken"), "--out", str(tmp_path / "root"), *QUICK]) == 2
    err = capsys.readouterr().err.strip()
    assert "pip install 'intercap[ray]'" in err and "--local" in err and len(err.splitlines()) == 1


def test_run_many_rejects_unmatched_pattern_and_name_clash(tmp_path):
    from intercap.batch import BatchError, expand_sessions

    with pytest.raises(BatchError, match="no session folder"):
        expand_sessions([str(tmp_path / "nothing*")])
    (tmp_path / "a" / "s").mkdir(parents=True)
    (tmp_path / "b" / "s").mkdir(parents=True)
    with pytest.raises(BatchError, match="two sessions named 's'"):
        expand_sessions([str(tmp_path / "*" / "s")])
