"""Many sessions at once: one pipeline per session, as Ray tasks (`intercap run-many`).

Each session SESSION/ gets its results folder ROOT/<session name>/ (`run_pipeline`'s output).
A session whose results folder already holds every requested stage's DONE.json with the
current fingerprint is skipped without starting a task, so a rerun after a crash or with
more sessions only does what is missing. A failing session does not stop the others: its
one-line reason goes into ROOT/summary.csv next to the others' frames, s/frame and key
figures from OUT/metrics.json.

Ray is optional (`pip install 'intercap[ray]'`): with no address a local Ray is started on
this machine's CPUs; `--address ray://HEAD:10001` (or `auto` on a cluster node) uses an
existing cluster, where the sessions and ROOT must be on storage every node sees under the
same path. `local=True` runs the sessions one after another in this process, without Ray.
"""
from __future__ import annotations

import csv
import dataclasses
import glob
import io
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from intercap.config import Config
from intercap.io.files import read_json, write_text
from intercap.parallel import on_gpu

log = logging.getLogger(__name__)

RAY_MISSING = ("ray is not installed: pip install 'intercap[ray]' (or pass --local to run the sessions "
               "one after another without Ray)")

# (stage, key in OUT/metrics.json, summary column): the figures worth a glance per session.
KEY_METRICS = [
    ("prepare", "ground_rmse_mm", "ground_rmse_mm"),
    ("prepare", "calibration_pairs_flagged", "calib_pairs_flagged"),
    ("object", "frames_lost", "object_frames_lost"),
    ("object", "mean_confidence", "object_confidence"),
    ("body", "frames_fitted", "body_frames_fitted"),
    ("body", "reprojection_px_median", "body_reproj_px"),
    ("contact", "frames_in_contact", "contact_frames"),
    ("global", "penetration_mm_mean", "penetration_mm"),
    ("global", "jitter_mps2", "jitter_mps2"),
]
COLUMNS = ["session", "status", "frames", "s_per_frame", "wall_s",
           *[c for _, _, c in KEY_METRICS], "reason", "session_path", "out"]


class BatchError(ValueError):
    """Bad batch input (no sessions matched, two sessions with one name, no GPU for device=cuda)."""


@dataclass
class SessionResult:
    """One session's line of the summary."""

    session: str
    session_path: str
    out: str
    status: str  # ok | skipped (already done) | failed
    frames: int | None = None
    s_per_frame: float | None = None  # sum over the requested stages of OUT/metrics.json's seconds_per_frame
    wall_s: float | None = None  # this run's wall clock for the session (0 when skipped)
    reason: str = ""  # failed: the one-line reason
    metrics: dict = field(default_factory=dict)  # summary column -> value

    def row(self) -> dict:
        out = {"session": self.session, "status": self.status, "frames": self.frames,
               "s_per_frame": _rounded(self.s_per_frame, 3), "wall_s": _rounded(self.wall_s, 1),
               "reason": self.reason, "session_path": self.session_path, "out": self.out}
        out.update({c: _rounded(self.metrics.get(c), 3) for _, _, c in KEY_METRICS})
        return {c: "" if out[c] is None else out[c] for c in COLUMNS}

    def progress_line(self) -> str:
        if self.status == "failed":
            return f"{self.session}: failed: {self.reason}"
        frames = "?" if self.frames is None else self.frames
        speed = "" if self.s_per_frame is None else f", {self.s_per_frame:.2f} s/frame"
        return f"{self.session}: {frames} frames{speed}, {self.status}"


def _rounded(value, digits):
    return round(value, digits) if isinstance(value, float) else value


def one_line(exc: BaseException) -> str:
    """`Type: first lines of the message` on one line, short enough for a table cell."""
    text = " ".join(line.strip() for line in str(exc).splitlines() if line.strip())
    text = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return text if len(text) <= 300 else text[:297] + "..."


def expand_sessions(patterns: list[str]) -> list[Path]:
    """Session folders from glob patterns (or plain paths), in order, each once. Two sessions with
    the same folder name would share ROOT/<name>: an error."""
    found: list[Path] = []
    for pattern in patterns:
        matches = sorted(glob.glob(os.path.expanduser(pattern))) or ([pattern] if Path(pattern).is_dir() else [])
        dirs = [Path(m).resolve() for m in matches if Path(m).is_dir()]
        if not dirs:
            raise BatchError(f"no session folder matches {pattern!r}")
        found += [d for d in dirs if d not in found]
    names: dict[str, Path] = {}
    for path in found:
        if path.name in names:
            raise BatchError(f"two sessions named {path.name!r} ({names[path.name]} and {path}) would share "
                             "one results folder; rename one")
        names[path.name] = path
    return found


def read_metrics(out_dir: Path, stages: list[str]) -> tuple[float | None, dict]:
    """(s/frame summed over `stages`, key figures) from OUT/metrics.json; (None, {}) when absent."""
    path = Path(out_dir) / "metrics.json"
    try:
        metrics = read_json(path)
    except (OSError, ValueError):
        return None, {}
    per_frame = [metrics[s]["seconds_per_frame"] for s in stages if "seconds_per_frame" in metrics.get(s, {})]
    keys = {col: metrics[s][k] for s, k, col in KEY_METRICS
            if s in stages and isinstance(metrics.get(s, {}).get(k), (int, float))}
    return (float(sum(per_frame)) if per_frame else None), keys


def is_finished(session_path: Path, out_dir: Path, cfg: Config, stages: list[str]) -> bool:
    """True when every requested stage's DONE.json in `out_dir` has the fingerprint this run would give
    (the runner's own test; the session folder is not read)."""
    from intercap.pipeline import STAGES, stage_fingerprint

    if cfg.run.force:
        return False
    upstream: list[str] = []
    for name in stages:
        fingerprint = stage_fingerprint(STAGES[name], cfg, session_path, upstream)
        upstream.append(fingerprint)
        try:
            if read_json(Path(out_dir) / name / "DONE.json").get("fingerprint") != fingerprint:
                return False
        except (OSError, ValueError):
            return False
    return True


def run_session(session_path: str, out_dir: str, cfg: Config, stages: list[str]) -> dict:
    """Run the pipeline on one session and describe the outcome; never raises (a Ray task or a loop step)."""
    from intercap.pipeline import run_pipeline
    from intercap.session import Session

    start = time.perf_counter()
    result = {"status": "ok", "frames": None, "reason": "", "wall_s": None}
    try:
        result["frames"] = Session.load(session_path).num_frames
        run_pipeline(session_path, out_dir, cfg, stages=stages, progress=False)
    except Exception as exc:  # noqa: BLE001 - any failure is this session's, reported in the summary
        log.debug("session %s failed", session_path, exc_info=True)
        result.update(status="failed", reason=one_line(exc))
    result["wall_s"] = time.perf_counter() - start
    return result


def _finish(base: SessionResult, outcome: dict, stages: list[str]) -> SessionResult:
    base.status, base.reason = outcome["status"], outcome["reason"]
    base.frames, base.wall_s = outcome["frames"], outcome["wall_s"]
    base.s_per_frame, base.metrics = read_metrics(Path(base.out), stages)
    return base


def _ray_init(address: str | None):
    """Connect to `address`, or start a quiet local Ray on this machine's CPUs. ImportError when missing."""
    import ray

    if ray.is_initialized():  # the caller's own Ray
        return ray, False
    quiet = {"logging_level": logging.WARNING, "log_to_driver": False}
    if address:
        try:
            ray.init(address=address, **quiet)
        except Exception as exc:  # noqa: BLE001 - ConnectionError, RuntimeError, ... : one line for the user
            raise BatchError(f"cannot connect to the Ray cluster at {address}: {one_line(exc)}") from exc
    else:
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        ray.init(num_cpus=cpus, include_dashboard=False, object_store_memory=128 * 1024**2, **quiet)
    return ray, True


def _gpus_per_task(requested: float | None, cfg: Config, cluster_gpus: float) -> float:
    if requested is not None:
        return requested
    if not on_gpu(cfg):
        return 0
    if cluster_gpus <= 0:
        raise BatchError("run.device=cuda but the Ray cluster has no GPU; use --set run.device=cpu")
    return 1


def run_many(patterns: list[str], root, cfg: Config | None = None, stages: list[str] | None = None, *,
             address: str | None = None, local: bool = False, cpus_per_task: float = 1,
             gpus_per_task: float | None = None, report: Callable[[str], None] = print) -> list[SessionResult]:
    """Run the pipeline on every session matched by `patterns` into ROOT/<name>/, skipping finished ones.

    Writes ROOT/summary.csv and returns its rows in session order. `report` gets one line per
    session as it finishes. ImportError(RAY_MISSING) when Ray is wanted but not installed."""
    from intercap.pipeline import resolve_stages

    cfg = cfg or Config()
    names = resolve_stages(stages or cfg.run.stages)
    root = Path(root).resolve()
    root.mkdir(parents=True, exist_ok=True)
    sessions = expand_sessions(patterns)
    results = {p: SessionResult(p.name, str(p), str(root / p.name), "pending") for p in sessions}
    total, done = len(sessions), 0

    def finished(result: SessionResult) -> None:
        nonlocal done
        done += 1
        report(f"[{done}/{total}] {result.progress_line()}")

    todo = []
    for path, result in results.items():
        if is_finished(path, Path(result.out), cfg, names):
            result.status, result.wall_s = "skipped (already done)", 0.0
            result.s_per_frame, result.metrics = read_metrics(Path(result.out), names)
            result.frames = _frames_from_metrics(Path(result.out))
            finished(result)
        else:
            todo.append(path)

    if todo and local:
        for path in todo:
            finished(_finish(results[path], run_session(str(path), results[path].out, cfg, names), names))
    elif todo:
        try:
            ray, owned = _ray_init(address)
        except ImportError as exc:
            raise ImportError(RAY_MISSING) from exc
        try:
            gpus = _gpus_per_task(gpus_per_task, cfg, ray.cluster_resources().get("GPU", 0))
            task = ray.remote(run_session).options(num_cpus=cpus_per_task, num_gpus=gpus, max_retries=0)
            if not cfg.run.workers:  # a task's pipeline uses the CPUs it reserved, not one process per core
                cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, workers=max(1, int(cpus_per_task))))
            pending = {task.remote(str(p), results[p].out, cfg, names): p for p in todo}
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                path = pending.pop(ready[0])
                try:
                    outcome = ray.get(ready[0])
                except Exception as exc:  # noqa: BLE001 - the worker died (memory, node lost): this session failed
                    outcome = {"status": "failed", "reason": one_line(exc), "frames": None, "wall_s": None}
                finished(_finish(results[path], outcome, names))
        finally:
            if owned:
                ray.shutdown()

    rows = list(results.values())
    write_summary(rows, root / "summary.csv")
    return rows


def _frames_from_metrics(out_dir: Path) -> int | None:
    """Frames of a finished session without reading it: seconds / seconds_per_frame of any stage."""
    try:
        metrics = read_json(out_dir / "metrics.json")
    except (OSError, ValueError):
        return None
    for figures in metrics.values():
        s, spf = figures.get("seconds"), figures.get("seconds_per_frame")
        if isinstance(s, (int, float)) and isinstance(spf, (int, float)) and spf > 0:
            return int(round(s / spf))
    return None


def summary_csv(rows: list[SessionResult]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(r.row() for r in rows)
    return buffer.getvalue()


def write_summary(rows: list[SessionResult], path: Path) -> None:
    """ROOT/summary.csv, written atomically (no temp file left on a failure; the user's umask)."""
    write_text(path, summary_csv(rows))


def format_summary(rows: list[SessionResult]) -> str:
    """The summary as an aligned text table (the key figures that any session has, and reasons last)."""
    shown = ["session", "status", "frames", "s_per_frame", "wall_s"]
    shown += [c for _, _, c in KEY_METRICS if any(c in r.metrics for r in rows)]
    table = [[str(r.row()[c]) for c in shown] + [r.reason] for r in rows]
    header = shown + ["reason"]
    widths = [max([len(h)] + [len(t[i]) for t in table]) for i, h in enumerate(header)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)).rstrip()]
    lines += ["  ".join(v.ljust(w) for v, w in zip(t, widths)).rstrip() for t in table]
    return "\n".join(lines)
