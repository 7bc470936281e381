"""Benchmark `intercap report` and `intercap view` on a results folder (default: the sample's
ground truth laid out as the object, body and global stages' results, so it needs no fitting).

Prints, for the report: wall and CPU seconds of `write_report` (with --gt: the evaluation
section too), the overlay silhouette IoU it found per stage; for the viewer: seconds from start
to the first frame (loading the arrays + building the scene), and per-frame stepping in ms
(without and with the depth clouds). Targets: report <= 10 s on the sample, viewer
first frame <= 3 s, stepping <= 100 ms.

CPU times are process CPU seconds; run with one thread for figures comparable across machines:

    OMP_NUM_THREADS=1 python -m tools.bench_report [--out OUT] [--session S] [--gt S] [--profile]

--profile prints a pyinstrument profile of the report (where its time goes).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "sample"


def gt_results(session: Path, out: Path) -> Path:
    """An OUT folder with the session's ground truth as the object, body and global stages' results
    (and published at OUT/, as `intercap run` leaves them)."""
    gt = session / "ground_truth"
    out.mkdir(parents=True, exist_ok=True)
    for stage, names in (("object", ("object_poses.npz",)), ("body", ("body_vertices.npy", "body_faces.npy")),
                         ("global", ("body_vertices.npy", "body_faces.npy", "object_poses.npz"))):
        (out / stage).mkdir(exist_ok=True)
        for name in names:
            shutil.copy(gt / name, out / stage / name)
    for name in ("body_vertices.npy", "body_faces.npy", "object_poses.npz", "contact.npy", "keypoints3d.npy"):
        shutil.copy(gt / name, out / name)
    (out / "run.json").write_text(json.dumps({"session": str(session.resolve()), "stages": []}))
    return out


def timed(fn, *args, **kwargs):
    """(result, wall s, CPU s) of one call."""
    w, c = time.perf_counter(), time.process_time()
    result = fn(*args, **kwargs)
    return result, time.perf_counter() - w, time.process_time() - c


def bench_report(out: Path, session, gt, profile: bool) -> None:
    from intercap.evaluation import overlays
    from intercap.evaluation.report import write_report

    ious = {}
    original = overlays.render_overlays

    def recording(session_, out_dir, stage, *a, **k):  # keep each stage's IoU for the printout
        res = original(session_, out_dir, stage, *a, **k)
        ious[stage] = res.get("iou", {})
        return res

    overlays.render_overlays = recording  # the report imports it when it draws the overlays
    try:
        if profile:
            from pyinstrument import Profiler

            profiler = Profiler(interval=0.005)
            profiler.start()
        path, wall, cpu = timed(write_report, out, session=session, gt=gt, progress=False)
        if profile:
            profiler.stop()
    finally:
        overlays.render_overlays = original
    videos = sorted(p.name for p in (out / "report").glob("*.webm")) + sorted(p.name for p in (out / "report").glob("*.mp4"))
    size = sum(p.stat().st_size for p in (out / "report").rglob("*") if p.is_file()) / 1e6
    print(f"report: {wall:.2f} s wall, {cpu:.2f} s CPU ({path}, {size:.1f} MB with overlays, videos {videos})")
    for stage, iou in ious.items():
        print(f"  overlay silhouette IoU vs the session's masks, {stage}: "
              + (", ".join(f"{k} {v:.3f}" for k, v in iou.items()) or "no masks"))
    if profile:
        print(profiler.output_text(unicode=False, color=False, show_all=False))


COLD_VIEWER = """
import sys, time
from intercap.evaluation.viewer import Viewer, load_view_data
viewer = Viewer(load_view_data(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else None))
print(f"FIRST {time.process_time():.3f}", flush=True)
viewer.stop()
"""


def cold_viewer_start(out: Path, session) -> tuple[float, float]:
    """(wall s, CPU s) from launching a fresh Python to the viewer's first frame, imports included
    (what a person waits for after typing `intercap view OUT`)."""
    import subprocess
    import sys

    start = time.perf_counter()
    args = [sys.executable, "-c", COLD_VIEWER, str(out)] + ([str(session)] if session else [])
    res = subprocess.run(args, capture_output=True, text=True, timeout=300)
    wall = time.perf_counter() - start
    line = next((ln for ln in res.stdout.splitlines() if ln.startswith("FIRST")), None)
    if line is None:
        raise RuntimeError(f"the viewer did not start: {res.stderr[-2000:]}")
    return wall, float(line.split()[1])


def bench_viewer(out: Path, session) -> None:
    from intercap.evaluation.viewer import Viewer, load_view_data

    wall, cpu = cold_viewer_start(out, session)
    print(f"viewer, fresh process: first frame {wall:.2f} s wall, {cpu:.2f} s CPU after launch (imports included)")

    start_w, start_c = time.perf_counter(), time.process_time()
    data = load_view_data(out, session)
    viewer = Viewer(data)
    first_w, first_c = time.perf_counter() - start_w, time.process_time() - start_c
    try:
        print(f"viewer, modules loaded: first frame {first_w:.2f} s wall, {first_c:.2f} s CPU after start "
              f"(scene {viewer.first_frame_s:.2f} s; {data.num_frames} frames)")
        for label in ("without clouds", "with clouds"):
            if label == "with clouds":
                if not viewer.clouds_ready.wait(120):
                    print("viewer: depth clouds not ready after 120 s")
                    break
            times = []
            for i in list(range(1, data.num_frames)) + [0]:
                t = time.perf_counter()
                viewer.set_frame(i)
                times.append(time.perf_counter() - t)
            times = 1e3 * np.asarray(times)
            print(f"viewer stepping {label}: median {np.median(times):.1f} ms, mean {times.mean():.1f} ms, "
                  f"max {times.max():.1f} ms per frame")
    finally:
        viewer.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", help="results folder (default: the sample's ground truth in a temporary folder)")
    parser.add_argument("--session", help="session folder (default: the sample, or OUT/run.json's)")
    parser.add_argument("--gt", help="session with ground_truth/ for the evaluation section (default: none)")
    parser.add_argument("--profile", action="store_true", help="print a pyinstrument profile of the report")
    parser.add_argument("--no-viewer", action="store_true")
    args = parser.parse_args()
    print(f"threads: OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}")
    tmp = None
    if args.out:
        out = Path(args.out)
        session = args.session
    else:
        tmp = Path(tempfile.mkdtemp(prefix="bench_report_"))
        session = Path(args.session or SAMPLE)
        out = gt_results(session, tmp / "out")
        print(f"results: {session.name}'s ground truth as object, body and global results in {out}")
    try:
        bench_report(out, session, args.gt, args.profile)
        if not args.no_viewer:
            bench_viewer(out, session)
    finally:
        print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
