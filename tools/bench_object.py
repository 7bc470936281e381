"""Benchmark of the `object` stage (per-frame tracking) against ground truth.

For each generated object (box: pick_place, cup: lift_drink, chair: push_chair)
a synthetic session is made, then tracked with the session's object masks and
with masks derived from depth. Prints median and 90th-percentile ADD (ADD-S
for symmetric objects, said in the table), rotation error (modulo the
object's symmetry) and translation error, frames marked (lost or untrusted:
NaN pose), seconds per frame (all views; wall clock and process CPU time, all
threads: on a shared machine the wall time includes waiting for other jobs,
so both are printed, with the load average) and peak memory.

    python -m tools.bench_object [--cameras 4 --width 640 --height 576 --frames 40] [--objects box,cup,chair]
"""
from __future__ import annotations

import argparse
import logging
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

SCRIPTS = {"box": "pick_place", "cup": "lift_drink", "chair": "push_chair"}


def track_and_score(session: Path, out: Path, masks: bool) -> dict:
    from intercap.config import load_config
    from intercap.evaluation.evaluate import evaluate
    from intercap.pipeline import run_pipeline

    cfg = load_config(overrides=[f"object.use_session_masks={str(masks).lower()}", "run.force=true"])
    start, cpu_start = time.perf_counter(), time.process_time()
    metrics = run_pipeline(session, out, cfg, stages=["object"], progress=False)["object"]
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu_start
    result = evaluate(out, session)
    per_frame = result.per_frame
    symmetric = bool(result.metrics.get("object_symmetric"))
    add = np.array([np.nan if v is None else v for v in per_frame["object_adds_mm" if symmetric else "object_add_mm"]], float)
    rot_key = "object_rotation_sym_deg" if symmetric else "object_rotation_deg"
    rot = np.array([np.nan if v is None else v for v in per_frame[rot_key]], float)
    trans = np.array([np.nan if v is None else v for v in per_frame["object_translation_mm"]], float)
    frames = len(add)
    return {
        "add": "ADD-S" if symmetric else "ADD",
        "add_median": np.nanmedian(add), "add_p90": np.nanpercentile(add, 90),
        "rot_median": np.nanmedian(rot), "rot_p90": np.nanpercentile(rot, 90),
        "trans_median": np.nanmedian(trans), "trans_p90": np.nanpercentile(trans, 90),
        "lost": frames - int(metrics["frames_trusted"]), "frames": frames,
        "reinitialised": int(metrics.get("frames_reinitialised", 0)),
        "s_per_frame": seconds / frames, "cpu_per_frame": cpu_seconds / frames,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=576)
    parser.add_argument("--frames", type=int, default=40, help="frames spanning each script; 0: the script at 30 fps")
    parser.add_argument("--masks", default="given,derived", help="which mask sources to run")
    parser.add_argument("--objects", default="box,cup,chair")
    parser.add_argument("--keep", type=Path, help="keep the sessions and results here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from intercap.synth.generator import SynthConfig, generate_session

    work = args.keep or Path(tempfile.mkdtemp(prefix="bench_object_"))
    rows = []
    try:
        for name in args.objects.split(","):
            session = work / f"{name}_session"
            if not (session / "session.yaml").exists():
                cfg = SynthConfig(script=SCRIPTS[name], object=name, cameras=args.cameras, width=args.width,
                                  height=args.height, frames=args.frames or None, fps=30.0, quiet=True)
                generate_session(cfg, session)
            for masks in [m == "given" for m in args.masks.split(",")]:
                row = track_and_score(session, work / f"{name}_{'masks' if masks else 'derived'}", masks)
                rows.append((name, "given" if masks else "derived", row))
                print(f"{name:6s} {'given' if masks else 'derived':8s} done", flush=True)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    import torch

    print(f"\nobject tracking, {args.cameras} views at {args.width}x{args.height}, "
          f"{args.frames or 'all (30 fps)'} frames per session; {torch.get_num_threads()} torch threads, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    print("object masks    metric  ADD med  ADD p90  rot med  rot p90  trans med  trans p90  marked  reinit  "
          "s/frame  CPU s/frame")
    for name, masks, r in rows:
        print(f"{name:6s} {masks:8s} {r['add']:6s} {r['add_median']:8.1f} {r['add_p90']:8.1f} {r['rot_median']:8.2f} "
              f"{r['rot_p90']:8.2f} {r['trans_median']:10.1f} {r['trans_p90']:10.1f} {r['lost']:4d}/{r['frames']:<3d} "
              f"{r['reinitialised']:6d} {r['s_per_frame']:8.2f} {r['cpu_per_frame']:12.2f}")
    print("(mm, degrees; ADD-S and rotation modulo the symmetry group for symmetric objects; marked: frames lost or "
          "untrusted, NaN pose; reinit: frames whose pose came from registration)")
    print(f"peak memory (process RSS) {peak_mb:.0f} MB")


if __name__ == "__main__":
    main()
