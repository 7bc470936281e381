"""The runner: stages in order, each saving its own output, resumable.

A stage is finished when OUT/<stage>/DONE.json exists and records the same
inputs (the session, the stage's config section and those of the stages it
depends on). A rerun skips finished stages and redoes a stage whose settings
changed, and everything after it. A stage that died halfway resumes from its
own checkpoints when its settings are unchanged (OUT/<stage>/STARTED.json
records them), and starts clean otherwise. Only stages that exist are run: asking for
one that is not built yet is an error, never a fake output.
"""
from __future__ import annotations

import hashlib
import importlib
import json
import logging
import shutil
import time
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


def available_stages() -> list[str]:
    return [name for name in ORDER if name in STAGES]


def stage_fingerprint(stage: Stage, cfg: Config, session_root: Path, upstream: list[str]) -> str:
    """Hash of what a stage's output depends on."""
    payload = {
        "session": str(Path(session_root).resolve()),
        "config": {s: asdict(getattr(cfg, s)) for s in stage.config_sections},
        "upstream": upstream,
        "body_model": asdict(cfg.body_model),
    }
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
        fingerprint = stage_fingerprint(stage, cfg, session.root, upstream)
        upstream.append(fingerprint)  # also of stages not run now: `--stages global` finds the full run's work
        if name != "prepare":  # the later stages see the cameras `prepare` refined, in this run or a saved one
            session.use_refined_calibration(out_dir)
        if name not in names:
            continue
        marker = out_dir / name / "DONE.json"
        if marker.exists() and not cfg.run.force:
            done = read_json(marker)
            if done.get("fingerprint") == fingerprint:
                log.info("%s: already done (%s), skipping; --force to redo", name, marker)
                continue
            log.info("%s: settings or inputs changed since the saved run, redoing", name)
        marker.unlink(missing_ok=True)
        started = out_dir / name / "STARTED.json"
        if cfg.run.force or (started.exists() and read_json(started).get("fingerprint") != fingerprint):
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


def run_pipeline(session_path, out_dir, cfg: Config | None = None, stages: list[str] | None = None,
                 progress: bool = True) -> dict:
    """Run the requested stages (default: every built stage) on a session.

    Returns the metrics dictionary that is also written to OUT/metrics.json."""
    from intercap.session import Session

    cfg = cfg or Config()
    names = resolve_stages(stages or cfg.run.stages)
    check_device(cfg.run.device)
    session = Session.load(session_path)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.yaml")
    write_json(out_dir / "run.json", {"session": str(Path(session.root).resolve()), "stages": names})  # for `view`, `report`
    metrics_path = out_dir / "metrics.json"
    metrics = read_json(metrics_path) if metrics_path.exists() else {}

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
