"""Benchmark of the whole pipeline at capture rate: the number users quote.

A synthetic session is generated (`intercap.synth.generator`; 30 fps, the pick_place script at
natural speed = 219 frames, 4 views, 640x576 by default), every built stage runs with default
settings (`run_pipeline`, as `intercap run` does), and the bench prints:
  * per-stage seconds per frame (OUT/metrics.json) and the total (sum of stages, and the whole
    run's wall clock including model loading), and the imports of the stages' modules apart (a
    fixed cost per run: 12 s of a 92 s GPU run on the lent H200 machine),
  * peak RSS of the pipeline, this process and the stages' worker processes summed (the session
    is generated in a child process beforehand so that its memory does not count; the generator's
    own peak is printed beside it),
  * the accuracy table of `intercap eval` against the session's ground truth (body surface, MPJPE,
    hands, object ADD(-S), penetration, contact).

    python -m tools.bench_pipeline [--frames 150] [--width 640 --height 576] [--cameras 4] [--fps 30]
                                   [--raw] [--keep DIR [--resume]] [--set SECTION.KEY=VALUE ...] [--profile]
    python -m tools.bench_pipeline --session data_samples/sample [--set run.device=cuda]

Quick check: `--frames 30 --width 320 --height 288` (30 frames resample the script: 7x faster
motion than capture rate, so accuracy is not comparable with the full-size figures).
Rows for real-capture cases: `--cameras 1` (one view), `--raw` (no keypoint or mask files: the
pipeline detects and derives them).
--keep DIR keeps (and reuses) the generated session there; the pipeline is always redone, unless
--resume: a killed run in DIR goes on where it stopped (stages done are skipped, the unfinished one
resumes from its checkpoints; the timings then cover only what this run did).
--session DIR runs on an existing session with ground truth (the committed sample, a kept one)
instead of generating one. With `--set run.device=cuda` the peak GPU memory is printed too, and
the recordings of CUDA graphs that failed (the fits then ran eagerly).
--profile wraps the pipeline in pyinstrument (when installed) and prints its top entries
(self time); with --keep the full tree goes to OUT/profile.txt.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

KEY_ACCURACY = [("body_surface_mm", "surface mm"), ("keypoint_mpjpe_mm", "MPJPE mm"), ("hand_keypoint_mm", "hands mm"),
                ("object_adds_mm", "ADD-S mm"), ("object_add_mm", "ADD mm"), ("object_rotation_deg", "rot deg"),
                ("penetration_mean_mm", "pen. mm"), ("contact_accuracy_pct", "contact %"),
                ("contact_touch_accuracy_pct", "touch %")]


def make_session(path: Path, synth: dict) -> float:
    """Generate the session in a child process (its memory stays out of the pipeline's peak RSS);
    returns the child's peak RSS in MB (0 when the session was already there)."""
    if (path / "session.yaml").exists() and (path / "ground_truth").is_dir():
        return 0.0
    code = ("import json, sys; from intercap.synth.generator import SynthConfig, generate_session; "
            "generate_session(SynthConfig(**json.loads(sys.argv[1])), sys.argv[2])")
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    subprocess.run([sys.executable, "-c", code, json.dumps(synth), str(path)], check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(after, before) / 1024


class PeakMemory:
    """Peak of the summed RSS of this process and all its descendants (the stages' worker
    processes run beside the parent), sampled every `interval` s; ru_maxrss alone would see
    only the largest single process. Falls back to ru_maxrss without psutil."""

    def __init__(self, interval: float = 0.2):
        self.interval, self.peak_mb, self._stop = interval, 0.0, threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        try:
            import psutil
        except ImportError:
            return
        me = psutil.Process()
        while not self._stop.is_set():
            total = 0
            for proc in [me, *me.children(recursive=True)]:
                try:
                    total += proc.memory_info().rss
                except psutil.Error:  # a worker that just ended
                    pass
            self.peak_mb = max(self.peak_mb, total / 2**20)
            self._stop.wait(self.interval)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak_mb = max(self.peak_mb, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def cpu_seconds() -> float:
    """CPU time of this process and its finished children (the stages' workers)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def import_stages() -> float:
    """Seconds to import every stage's module (torch, anny, roma and torch._dynamo with it, trimesh,
    scipy, Open3D): a fixed cost of each run, whatever its length, which `run` times apart."""
    import importlib

    start = time.perf_counter()
    for module in ("prepare", "detect", "object", "body", "contact", "global_fit", "physics", "export"):
        importlib.import_module(f"intercap.stages.{module}.stage")
    return time.perf_counter() - start


def run(session: Path, out: Path, overrides: list[str], profile: bool,
        resume: bool = False) -> tuple[dict, float, float, float, float, str | None]:
    """(metrics.json, wall seconds, import seconds, CPU seconds, peak MB, profile summary or None) of
    the full pipeline, default stages, redone from scratch unless `resume`. The stages' modules are
    imported first (`import_stages`), so the stages' timings leave the imports out; the wall clock
    counts them. CPU and memory include the stages' worker processes."""
    from intercap.config import load_config
    from intercap.pipeline import run_pipeline

    cfg = load_config(overrides=[f"run.force={str(not resume).lower()}", *overrides])
    profiler = None
    if profile:
        try:
            from pyinstrument import Profiler
        except ImportError:
            print("--profile: pyinstrument is not installed (pip install pyinstrument); running without it")
        else:
            profiler = Profiler(interval=0.01)  # a coarse 10 ms sampling: the run takes minutes, overhead stays low
            profiler.start()
    start, cpu0 = time.perf_counter(), cpu_seconds()
    with PeakMemory() as memory:
        imports = import_stages()
        metrics = run_pipeline(session, out, cfg, progress=False)
    wall, cpu = time.perf_counter() - start, cpu_seconds() - cpu0
    summary = None
    if profiler is not None:
        profiler.stop()
        (out / "profile.txt").write_text(profiler.output_text(unicode=False, color=False))
        flat = profiler.output_text(unicode=False, color=False, flat=True)
        summary = "\n".join(flat.splitlines()[:40])
    return metrics, wall, imports, cpu, memory.peak_mb, summary


def peak_gpu_mb() -> float | None:
    """Peak memory torch allocated on the GPU in this process, None where CUDA was not used."""
    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_available() or not torch.cuda.is_initialized():
        return None
    return torch.cuda.max_memory_allocated() / 2**20


def fmt(value, digits=1) -> str:
    return "-" if not isinstance(value, (int, float)) or value != value else f"{value:.{digits}f}"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=0, help="frames spanning the script; 0: natural speed at --fps")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=576)
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--script", default="pick_place", help="pick_place | lift_drink | push_chair")
    parser.add_argument("--raw", action="store_true",
                        help="raw RGB-D: the session has no keypoint or mask files (detected and derived)")
    parser.add_argument("--session", type=Path, help="run on this session (with ground_truth/) instead of generating one")
    parser.add_argument("--keep", type=Path, help="keep (and reuse) the session and the results here")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="config override")
    parser.add_argument("--resume", action="store_true", help="with --keep: continue the killed run kept there")
    parser.add_argument("--profile", action="store_true", help="profile with pyinstrument (if installed)")
    args = parser.parse_args(argv)
    if args.resume and args.keep is None:
        parser.error("--resume needs --keep DIR (the folder of the run to continue)")
    logging.basicConfig(level=logging.INFO if args.resume else logging.WARNING)  # a resume says what it skips
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

    synth = {"script": args.script, "frames": args.frames or None, "fps": args.fps, "cameras": args.cameras,
             "width": args.width, "height": args.height, "quiet": True}
    if args.raw:
        synth.update(keypoints=False, masks=False)
    work = args.keep or Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
    tag = (f"{args.script}_{args.frames or 'natural'}f_{args.fps:g}fps_{args.cameras}v_{args.width}x{args.height}"
           + ("_raw" if args.raw else ""))
    session, out = work / tag, work / f"{tag}_out"
    if args.session is not None:
        tag = args.session.resolve().name
        session, out = args.session, work / f"{tag}_out"
    try:
        start = time.perf_counter()
        synth_mb = make_session(session, synth)
        synth_s = time.perf_counter() - start
        metrics, wall, imports, cpu, peak_mb, profile = run(session, out, args.set, args.profile, resume=args.resume)
        from intercap.evaluation.evaluate import evaluate
        from intercap.evaluation.table import format_table

        result = evaluate(out, session)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)

    T = result.metrics.get("frames") or 1
    threads = os.environ.get("OMP_NUM_THREADS", "default")
    from intercap.session import Session

    views = len(Session.load(session).cameras)
    print(f"\nwhole pipeline on {tag}: {T} frames, {views} views, OMP_NUM_THREADS={threads}, "
          f"{os.cpu_count()} CPUs seen (session generated in {synth_s:.0f} s)")
    print(f"{'stage':10s} {'s/frame':>8s} {'seconds':>8s}")
    for stage, figures in metrics.items():
        print(f"{stage:10s} {figures.get('seconds_per_frame', float('nan')):8.3f} {figures.get('seconds', float('nan')):8.1f}")
    stage_sum = sum(f.get("seconds_per_frame", 0.0) for f in metrics.values())
    print(f"{'total':10s} {stage_sum:8.3f} {stage_sum * T:8.1f}   (stages)")
    print(f"{'imports':10s} {imports / T:8.3f} {imports:8.1f}   (the stages' modules, before the stages: a fixed cost)")
    print(f"{'wall':10s} {wall / T:8.3f} {wall:8.1f}   (run_pipeline, imports and model loading included)")
    print(f"{'cpu':10s} {cpu / T:8.3f} {cpu:8.1f}   (CPU time of all threads and workers: the figure to trust on a busy machine)")
    print(f"peak RSS {peak_mb:.0f} MB (pipeline and its workers together)" + (f"; generator {synth_mb:.0f} MB" if synth_mb else ""))
    gpu_mb = peak_gpu_mb()
    if gpu_mb is not None:
        from intercap.energies import optim

        print(f"peak GPU memory {gpu_mb:.0f} MB allocated by torch")
        failures = sorted(set(optim._graph_failures))  # this process's (one process on a GPU)
        print(f"CUDA graphs not recorded: {len(optim._graph_failures)}" + "".join(f"\n  {r}" for r in failures))
    print()
    print(format_table(result))
    print()
    print("  ".join(f"{h:>10s}" for _, h in KEY_ACCURACY))
    print("  ".join(f"{fmt(result.metrics.get(k), 2 if k.endswith('deg') else 1):>10s}" for k, _ in KEY_ACCURACY))
    if profile:
        print("\npyinstrument, top entries by self time (full tree in OUT/profile.txt with --keep):")
        print(profile)
    if args.keep:
        print(f"\nsession and results in {work}")


if __name__ == "__main__":
    main()
