"""The runner: stages in order, each saving its own output, resumable.

A stage is finished when OUT/<stage>/DONE.json exists and records the same
inputs (the session, the stage's config section and those of the stages it
depends on). A rerun skips finished stages and redoes a stage whose settings
changed, and everything after it. A stage that died halfway resumes from its
own checkpoints when its settings are unchanged (OUT/<stage>/STARTED.json
records them), and starts clean otherwise. Only stages that exist are run: asking for
one that is not built yet is an error, never a fake output.

The results folder is guarded: never in, over or containing a session folder, never
holding another session's results (OUT/run.json; `run.force` replaces them), and
written by one run at a time (OUT/.lock, held with flock for the whole run).
"""
from __future__ import annotations

import hashlib
import importlib
import json
import logging
import os
import shutil
import socket
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from intercap import parallel
from intercap.config import Config, ConfigError, resolved, save_config
from intercap.io.files import read_json, write_json
from intercap.session import frame_cache

log = logging.getLogger(__name__)

# The stages that read every frame's depth and masks: the first of them to run decodes them once.
READS_FRAMES = ("object", "body", "contact", "global")

# The order of DESIGN.md. Stages not yet built are listed so errors can say so.
ORDER = ["prepare", "detect", "object", "body", "contact", "global", "physics", "export"]


@dataclass
class Stage:
    name: str
    run: Callable  # (session, cfg, out_dir, progress) -> dict of figures for metrics.json
    config_sections: tuple[str, ...]  # the config sections whose change invalidates the output


def _stage_runner(module: str) -> Callable:
    """`run` of `intercap.stages.<module>.stage`, imported only when the stage runs (a run of some
    stages does not import the others)."""
    def run(session, cfg, out_dir, progress):
        return importlib.import_module(f"intercap.stages.{module}.stage").run(session, cfg, out_dir, progress=progress)

    return run


STAGES: dict[str, Stage] = {
    "prepare": Stage("prepare", _stage_runner("prepare"), ("prepare",)),
    "detect": Stage("detect", _stage_runner("detect"), ("detect",)),
    "object": Stage("object", _stage_runner("object"), ("object",)),
    "body": Stage("body", _stage_runner("body"), ("detect", "body")),
    "contact": Stage("contact", _stage_runner("contact"), ("contact", "global_")),  # global_: flight_*
    "global": Stage("global", _stage_runner("global_fit"), ("body", "global_")),
    "physics": Stage("physics", _stage_runner("physics"), ("physics",)),
    "export": Stage("export", _stage_runner("export"), ("export",)),
}


class StageError(RuntimeError):
    pass


class ResultsFolderError(StageError):
    """The results folder cannot take this run: it is, holds or lies in a session, holds another
    session's results, or another run is writing to it."""


LOCK_NAME = ".lock"  # OUT/.lock: the run writing to the folder (held with flock while it runs)


def saved_record(path: Path) -> dict:
    """A JSON record this runner wrote earlier (DONE.json, STARTED.json, metrics.json), or {} when it
    cannot be read (a run killed while writing, a damaged disk): said in the log, and the stage is then
    redone (no fingerprint matches) rather than the run stopped."""
    try:
        record = read_json(path)
    except (OSError, ValueError) as exc:
        log.warning("%s: unreadable (%s); ignoring it", path, exc)
        return {}
    if not isinstance(record, dict):
        log.warning("%s: not a JSON object; ignoring it", path)
        return {}
    return record


def available_stages() -> list[str]:
    return [name for name in ORDER if name in STAGES]


def stage_fingerprint(stage: Stage, cfg: Config, session_root: Path, upstream: list[str],
                      frames: tuple[int, int] | None = None) -> str:
    """Hash of what a stage's output depends on; `frames`: the part of the session a run took
    (`run --frames`; None, the whole range, keeps the hash of a whole-session run)."""
    payload = {
        "session": str(Path(session_root).resolve()),
        "config": {s: asdict(getattr(cfg, s)) for s in stage.config_sections},
        "upstream": upstream,
        "body_model": asdict(cfg.body_model),
    }
    if frames is not None:
        payload["frames"] = [int(f) for f in frames]
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def resolve_stages(requested: list[str] | None) -> list[str]:
    names = requested or available_stages()
    for name in names:
        if name not in STAGES:
            known = ", ".join(available_stages())
            if name in ORDER:
                raise StageError(f"stage {name!r} is not implemented yet; available: {known}")
            raise StageError(f"unknown stage {name!r}; available: {known}")
    return sorted(set(names), key=ORDER.index)


def _run_stages(session, cfg: Config, out_dir: Path, names: list[str], metrics: dict, progress: bool) -> None:
    """Each stage in turn, skipping those done with the same settings and inputs; updates `metrics`
    and OUT/metrics.json after each."""
    metrics_path = out_dir / "metrics.json"
    upstream: list[str] = []
    order = available_stages()
    for name in order[:order.index(names[-1]) + 1]:
        stage = STAGES[name]
        fingerprint = stage_fingerprint(stage, cfg, session.root, upstream, getattr(session, "run_frames", None))
        upstream.append(fingerprint)  # also of stages not run now: `--stages global` finds the full run's work
        if name != "prepare":  # the later stages see the cameras `prepare` refined, in this run or a saved one
            session.use_refined_calibration(out_dir)
        if name not in names:
            continue
        marker = out_dir / name / "DONE.json"
        if marker.exists() and not cfg.run.force:
            done = saved_record(marker)
            if done.get("fingerprint") == fingerprint and name in metrics:
                log.info("%s: already done (%s), skipping; --force to redo", name, marker)
                continue
            if done.get("fingerprint") == fingerprint:  # its figures were lost with metrics.json
                log.info("%s: done, but its figures are not in %s: redoing", name, metrics_path)
            else:
                log.info("%s: settings or inputs changed since the saved run, redoing", name)
        marker.unlink(missing_ok=True)
        started = out_dir / name / "STARTED.json"
        if cfg.run.force or (started.exists() and saved_record(started).get("fingerprint") != fingerprint):
            shutil.rmtree(out_dir / name, ignore_errors=True)  # partial work of other settings is not resumed
        elif started.exists():
            log.info("%s: resuming the unfinished run", name)
        write_json(started, {"stage": name, "fingerprint": fingerprint})
        if name in READS_FRAMES and cfg.run.frame_cache and session.frame_cache is None:
            frame_cache.build(session, out_dir, progress)
        log.info("%s: running", name)
        start = time.perf_counter()
        figures = stage.run(session, cfg, out_dir, progress)
        seconds = time.perf_counter() - start
        figures = {**figures, "seconds": seconds, "seconds_per_frame": seconds / max(session.num_frames, 1)}
        metrics[name] = figures
        write_json(metrics_path, metrics)
        write_json(marker, {"stage": name, "fingerprint": fingerprint, "seconds": seconds,
                            "finished": time.strftime("%Y-%m-%dT%H:%M:%S")})
        log.info("%s: done in %.1f s", name, seconds)


def check_device(device: str) -> None:
    """A clear ConfigError, before any stage starts, for a `run.device` this machine cannot run on
    (rather than torch's assertion deep inside the first stage that moves a tensor there)."""
    if device == "cpu":
        return
    import torch

    try:
        chosen = torch.device(device)
    except RuntimeError:
        raise ConfigError(f"run.device: {device!r} is not a device; use cpu, cuda or cuda:N") from None
    if chosen.type != "cuda":
        raise ConfigError(f"run.device: {device!r}; only cpu and cuda (cuda:N) are supported")
    if not torch.backends.cuda.is_built():
        raise ConfigError(f"run.device={device}: this torch ({torch.__version__}) is a CPU-only build; "
                          "install a CUDA build of torch to run on a GPU")
    if not torch.cuda.is_available():
        raise ConfigError(f"run.device={device}: no CUDA GPU is visible to torch (driver, CUDA_VISIBLE_DEVICES?)")
    if chosen.index is not None and chosen.index >= torch.cuda.device_count():
        raise ConfigError(f"run.device={device}: this machine has {torch.cuda.device_count()} CUDA device(s)")


def check_results_folder(session_root: Path, out_dir: Path) -> None:
    """Refuse a results folder that would overwrite a session: the session folder itself, a folder
    inside it (OUT/ground_truth would replace the truth), one that contains it, any folder with a
    session.yaml at or above it, or a path that is a file."""
    out, root = Path(out_dir).resolve(), Path(session_root).resolve()
    if out.exists() and not out.is_dir():
        raise ResultsFolderError(f"results folder {out_dir}: is a file, not a folder")
    if out == root or root in out.parents:
        where = "is" if out == root else "lies inside"
        raise ResultsFolderError(f"results folder {out_dir}: {where} the session folder {root}; "
                                 "results go outside it")
    if out in root.parents:
        raise ResultsFolderError(f"results folder {out_dir}: contains the session folder {root}; "
                                 "choose a results folder outside it")
    for folder in (out, *out.parents):
        if (folder / "session.yaml").is_file():
            where = "is" if folder == out else "lies inside"
            raise ResultsFolderError(f"results folder {out_dir}: {where} a session folder ({folder / 'session.yaml'}); "
                                     "results go outside it")


@contextmanager
def results_lock(out_dir: Path):
    """Hold OUT/.lock (flock) while the block runs: one run at a time per results folder. The OS
    drops the lock when its process ends, even by kill -9, so a stale file never blocks a rerun."""
    import fcntl

    path = Path(out_dir) / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 4096).decode(errors="replace").strip() or "another run"
            raise ResultsFolderError(f"results folder {out_dir}: in use by {holder}; wait for it to end, "
                                     "or use another --out") from None
        except OSError as exc:  # a file system without flock (some network mounts): run unguarded
            log.warning("%s: cannot lock (%s); make sure no other run writes here", path, exc.strerror)
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}, started {time.strftime('%Y-%m-%d %H:%M:%S')}\n"
                 .encode())
        yield
    finally:
        os.close(fd)  # releases the lock


def claim_results_folder(session_root: Path, out_dir: Path, force: bool) -> None:
    """A folder holding another session's results (OUT/run.json) is refused, unless `force`: then
    those results are removed and this run starts clean. Called with the folder's lock held."""
    record = out_dir / "run.json"
    if not record.exists():
        return
    try:
        recorded = read_json(record).get("session")
    except (OSError, ValueError, AttributeError):
        recorded = None
    root = str(Path(session_root).resolve())
    if recorded == root:
        return
    other = f"session {recorded}" if recorded else "an unknown session (unreadable run.json)"
    if not force:
        raise ResultsFolderError(f"results folder {out_dir}: holds the results of {other}; use another --out, "
                                 "or --force to replace them")
    log.warning("%s: replacing the results of %s", out_dir, other)
    for entry in out_dir.iterdir():
        if entry.name == LOCK_NAME:
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def run_pipeline(session_path, out_dir, cfg: Config | None = None, stages: list[str] | None = None,
                 progress: bool = True, frames: tuple[int | None, int | None] | None = None) -> dict:
    """Run the requested stages (default: every built stage) on a session.

    frames: (first, last) session frame indices, inclusive (None: that end of the session's range),
    to run on part of a take; recorded in OUT/run.json, where stage workers, `report` and `eval`
    (which cuts the ground truth to them) read it.
    Returns the metrics dictionary that is also written to OUT/metrics.json."""
    from intercap.session import Session

    cfg = cfg or Config()
    names = resolve_stages(stages or cfg.run.stages)
    check_device(cfg.run.device)
    session = Session.load(session_path)
    if frames is not None:
        session.restrict_frames(*frames)
    out_dir = Path(out_dir)
    check_results_folder(session.root, out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with results_lock(out_dir):
        claim_results_folder(session.root, out_dir, cfg.run.force)
        return _run_in(session, out_dir, cfg, names, progress)


def _run_in(session, out_dir: Path, cfg: Config, names: list[str], progress: bool) -> dict:
    """`run_pipeline` once the results folder is checked and locked."""
    save_config(cfg, out_dir / "config.yaml")
    write_json(out_dir / "run.json", {"session": str(Path(session.root).resolve()), "stages": names,  # for `view`, `report`
                                      "frames": [int(session.frame_ids[0]), int(session.frame_ids[-1])]})
    with run_log(out_dir / RUN_LOG):
        return _run_logged(session, out_dir, cfg, names, progress)


RUN_LOG = "run.log"  # OUT/run.log: INFO and above of every run into the folder, appended


@contextmanager
def run_log(path: Path):
    """Copy this process's log records (INFO and above, timestamped) into `path` while the block runs,
    and those of the stages' worker processes (`parallel.logging_to`)."""
    handler = logging.FileHandler(path, mode="a", encoding="utf-8")
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter(parallel.LOG_FORMAT))
    root = logging.getLogger()
    level, shown = root.level, root.getEffectiveLevel()
    held = [(h, h.level) for h in root.handlers if h.level < shown]  # the console keeps what it showed
    if shown > logging.INFO:
        for h, _ in held:
            h.setLevel(shown)
        root.setLevel(logging.INFO)
    root.addHandler(handler)
    try:
        with parallel.logging_to(path):
            yield
    finally:
        root.removeHandler(handler)
        root.setLevel(level)
        for h, was in held:
            h.setLevel(was)
        handler.close()


def _run_logged(session, out_dir: Path, cfg: Config, names: list[str], progress: bool) -> dict:
    """`_run_in` with OUT/run.log open."""
    log.info("run of %s, frames %d..%d, stages %s", session.root, session.frame_ids[0], session.frame_ids[-1],
             ",".join(names))
    metrics_path = out_dir / "metrics.json"
    metrics = saved_record(metrics_path) if metrics_path.exists() else {}

    try:
        with parallel.repeatable(cfg):
            _run_stages(session, resolved(cfg, session.fps), out_dir, names, metrics, progress)
    finally:
        parallel.shutdown()  # the stages' worker processes
    if cfg.report.enabled:  # OUT/report/index.html; a failure there never loses the results above
        try:
            from intercap.evaluation.report import write_report

            write_report(out_dir, session=session, cfg=cfg, progress=progress)
        except Exception as exc:  # noqa: BLE001
            log.warning("report not written (%s: %s); retry with `intercap report %s`", type(exc).__name__, exc, out_dir)
    frame_cache.remove(out_dir)  # kept only for the resume of a run that died
    return metrics
