"""The results folder's guard: never inside (or over) a session, never mixing two sessions' results,
one run at a time, and OS errors as one line. The stage is replaced by a stand-in where only the
guard is under test, so each test takes a fraction of a second."""
from __future__ import annotations

import dataclasses
import errno
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import intercap.pipeline as pipeline
from conftest import write_tiny_session
from intercap.cli import main
from intercap.config import load_config
from intercap.pipeline import ResultsFolderError, results_lock, run_pipeline

QUICK = ["run.stages=prepare", "report.enabled=false"]


@pytest.fixture
def stand_in_prepare(monkeypatch):
    """`prepare` as a stand-in that writes one result file; the list of the sessions it ran on."""
    ran = []

    def run(session, cfg, out_dir, progress):
        ran.append(Path(session.root).resolve())
        (Path(out_dir) / "prepare").mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "prepare" / "ground.json").write_text("{}")
        return {"ok": 1}

    monkeypatch.setitem(pipeline.STAGES, "prepare", dataclasses.replace(pipeline.STAGES["prepare"], run=run))
    return ran


def snapshot(folder: Path) -> dict:
    """Every file under `folder` and its bytes, less the lock file a refused run may leave."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".lock"}


def test_a_results_folder_in_or_over_a_session_is_refused(tiny_session, tmp_path, stand_in_prepare):
    """Inside the session (also through a symlink), the session itself, a folder containing it, or
    another session: refused before anything is written, the sessions untouched."""
    other = write_tiny_session(tmp_path / "other")
    (tmp_path / "link").symlink_to(tiny_session)
    before = snapshot(tmp_path)
    cases = [(tiny_session / "ground_truth", "lies inside the session folder"),
             (tmp_path / "link" / "results", "lies inside the session folder"),
             (tiny_session, "is the session folder"),
             (tmp_path, "contains the session folder"),
             (other, "is a session folder"),
             (other / "results", "lies inside a session folder")]
    for out, reason in cases:
        with pytest.raises(ResultsFolderError, match=reason):
            run_pipeline(tiny_session, out, load_config(overrides=QUICK), progress=False)
    assert snapshot(tmp_path) == before and not stand_in_prepare


def test_another_sessions_results_are_refused_unless_forced(tiny_session, tmp_path, stand_in_prepare, capsys):
    """OUT/run.json names session B: a run of A is refused with its files untouched; with --force
    the run replaces them, starting clean (none of B's files stay to be mixed with A's)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "run.json").write_text(json.dumps({"session": str(tmp_path / "B"), "stages": ["body"]}))
    (out / "body").mkdir()
    (out / "body" / "DONE.json").write_text("{}")
    (out / "body_vertices.npy").write_bytes(b"B's")
    before = snapshot(out)
    assert main(["run", str(tiny_session), "--out", str(out), *sum((["--set", q] for q in QUICK), [])]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"holds the results of session {tmp_path / 'B'}" in err and "--force" in err
    assert snapshot(out) == before and not stand_in_prepare

    run_pipeline(tiny_session, out, load_config(overrides=QUICK + ["run.force=true"]), progress=False)
    assert stand_in_prepare == [tiny_session.resolve()]
    assert sorted(p.name for p in out.iterdir()) == [".lock", "config.yaml", "metrics.json", "prepare", "run.json",
                                                     "run.log"]
    assert json.loads((out / "run.json").read_text())["session"] == str(tiny_session.resolve())
    run_pipeline(tiny_session, out, load_config(overrides=QUICK), progress=False)  # its own results: no refusal


def test_a_second_run_on_a_busy_folder_stops_at_once_naming_the_first(tiny_session, tmp_path, stand_in_prepare,
                                                                       capsys):
    """While one run holds OUT/.lock, another exits non-zero with one line naming the holder's pid
    and start time, writing nothing; once the lock is free the run goes ahead."""
    out = tmp_path / "out"
    out.mkdir()
    with results_lock(out):
        code = main(["run", str(tiny_session), "--out", str(out), "--set", "report.enabled=false",
                     "--stages", "prepare"])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1
        assert f"in use by pid {os.getpid()} on " in err and ", started 20" in err
        assert sorted(p.name for p in out.iterdir()) == [".lock"] and not stand_in_prepare
    run_pipeline(tiny_session, out, load_config(overrides=QUICK), progress=False)
    assert stand_in_prepare


def test_a_killed_runs_lock_file_does_not_block(tiny_session, tmp_path, stand_in_prepare):
    """A process holding the lock is killed with SIGKILL: its lock file stays, but the OS released
    the lock, so the next run proceeds (and writes its own pid into the file)."""
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from intercap.pipeline import results_lock\n"
                               f"with results_lock({str(out)!r}):\n    print('held', flush=True); time.sleep(60)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(ResultsFolderError, match=f"pid {holder.pid} "):
            run_pipeline(tiny_session, out, load_config(overrides=QUICK), progress=False)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert f"pid {holder.pid} " in (out / ".lock").read_text()  # stale, and harmless
    run_pipeline(tiny_session, out, load_config(overrides=QUICK), progress=False)
    assert stand_in_prepare and f"pid {os.getpid()} " in (out / ".lock").read_text()


def run_cli(session: Path, out: Path, capsys) -> tuple[int, str]:
    code = main(["run", str(session), "--out", str(out), "--stages", "prepare", "--set", "report.enabled=false"])
    return code, capsys.readouterr().err.strip()


def test_a_full_disk_is_one_line_naming_the_file_and_leaves_no_temporary(tiny_session, tmp_path, monkeypatch,
                                                                           stand_in_prepare, capsys):
    """Every rename into OUT fails with ENOSPC: exit 1, one line with the file and the cause, and
    no temporary files left in OUT."""
    out = tmp_path / "out"
    real_replace = os.replace

    def full(src, dst, *args, **kwargs):
        if Path(dst).parent == out:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", full)
    code, err = run_cli(tiny_session, out, capsys)
    assert code == 1 and err == f"intercap run: error: {out / 'config.yaml'}: No space left on device"
    assert sorted(p.name for p in out.iterdir()) == [".lock"]


@pytest.mark.parametrize("cause", [errno.EROFS, errno.EACCES])
def test_an_unwritable_results_folder_is_one_line(tiny_session, tmp_path, monkeypatch, cause, capsys):
    """Files cannot be created in OUT (a read-only file system, no permission; as root chmod does
    not stop writes, so os.open is made to refuse): exit 1, one line naming the path and the cause."""
    out = tmp_path / "out"
    out.mkdir()
    real_open = os.open

    def refuse(path, *args, **kwargs):
        if Path(path).parent == out:
            raise OSError(cause, os.strerror(cause), str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", refuse)
    code, err = run_cli(tiny_session, out, capsys)
    assert code == 1 and err == f"intercap run: error: {out / '.lock'}: {os.strerror(cause)}"
    assert not list(out.iterdir())


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_results_folder_is_one_line(tiny_session, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    out.chmod(0o555)
    try:
        code, err = run_cli(tiny_session, out, capsys)
    finally:
        out.chmod(0o755)
    assert code == 1 and err.endswith("Permission denied") and str(out) in err


def test_out_being_a_file_or_under_one_is_one_line(tiny_session, tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    code, err = run_cli(tiny_session, tmp_path / "file", capsys)
    assert code == 2 and err == f"intercap run: error: results folder {tmp_path / 'file'}: is a file, not a folder"
    code, err = run_cli(tiny_session, tmp_path / "file" / "out", capsys)
    assert code == 1 and err == f"intercap run: error: {tmp_path / 'file' / 'out'}: Not a directory"
    assert (tmp_path / "file").read_text() == "x"


def test_eval_and_report_wait_for_no_run(tmp_path, capsys):
    """`intercap eval` and `intercap report` on a folder a run holds exit at once naming the run, and
    write nothing there."""
    out = tmp_path / "out"
    out.mkdir()
    with results_lock(out):
        for argv in (["eval", str(out), "--gt", str(tmp_path)], ["report", str(out)]):
            code = main(argv)
            err = capsys.readouterr().err.strip()
            assert code == 2 and len(err.splitlines()) == 1 and f"in use by pid {os.getpid()} on " in err
    assert sorted(p.name for p in out.iterdir()) == [".lock"]
