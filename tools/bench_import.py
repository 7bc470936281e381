"""Benchmark of `intercap import k4a`: the shared real recording (target < 2 s) and a
synthetic 4-device 720p rig written as Azure-Kinect-style MKVs (target >= 15 frames/s,
i.e. 60 camera-frames/s). The synthetic frames reuse the real recording's JPEG and depth
(shifted per frame), so encoding sizes are realistic.

Two figures for the rig: the wall-clock rig frames/s with the importer's default
parallelism (one process per device, at most the CPU count; the target's figure, valid only
on an otherwise idle machine: the load average is printed beside it) and the CPU time per
camera-frame (all processes; independent of the machine's load).

    OMP_NUM_THREADS=1 python -m tools.bench_import [--frames 60] [--workers N]
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from intercap.io.k4a import decode_depth, default_workers, import_k4a, open_recording
from intercap.synth.k4a_mkv import write_k4a_mkv

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "azure_kinect" / "recording.mkv"


def _cpu() -> float:
    """CPU seconds of this process and its finished children (the import's worker processes)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=60, help="frames per device of the synthetic rig (30 fps)")
    ap.add_argument("--devices", type=int, default=4)
    ap.add_argument("--workers", type=int, help="as `intercap import k4a --workers` (default: the importer's own)")
    args = ap.parse_args()
    import av

    tmp = Path(tempfile.mkdtemp(prefix="bench_import_"))
    try:
        t, cpu = time.perf_counter(), _cpu()
        r = import_k4a(tmp / "real", [REAL], workers=args.workers)
        print(f"real recording ({REAL.name}, {r['frames']} capture): {time.perf_counter() - t:.2f} s wall, "
              f"{_cpu() - cpu:.2f} s CPU (target < 2 s)")

        rec = open_recording(REAL)
        with av.open(str(REAL)) as c:
            jpg = next(bytes(p) for p in c.demux(c.streams[rec.color_index]) if p.size)
        with av.open(str(REAL)) as c:
            depth0 = decode_depth(rec, next(bytes(p) for p in c.demux(c.streams[rec.depth_index]) if p.size))
        calib = (REAL.parent / "calibration.json").read_bytes()
        n, D = args.frames, args.devices
        ts = [int(round(k * 1e6 / 30)) for k in range(n)]
        paths = []
        for d in range(D):
            depths = [np.where(depth0 > 0, depth0 + 3 * k, 0).astype(np.uint16) for k in range(n)]
            paths.append(write_k4a_mkv(tmp / f"dev{d}.mkv", [jpg] * n, depths, ts, calib, serial=f"{d:012d}",
                                       start_offset_ns=1_000_000_000 + 160_000 * d,
                                       sync_mode="MASTER" if d == 0 else "SUBORDINATE"))
        mb = sum(p.stat().st_size for p in paths) / 1e6
        load = os.getloadavg()[0]
        t, cpu = time.perf_counter(), _cpu()
        r = import_k4a(tmp / "rig", paths, uncalibrated=True, workers=args.workers)
        dt, cpu = time.perf_counter() - t, _cpu() - cpu
        per_frame = (dt - r["setup_seconds"]) / r["frames"]
        how = (f"workers={r['workers']} ({r['parallel']}; "
               f"{'default: ' + str(default_workers(D)) if args.workers is None else 'given'}) on {os.cpu_count()} CPUs")
        print(f"synthetic rig: {D} devices x {n} frames 720p + NFOV depth ({mb:.0f} MB), {how}")
        print(f"  wall clock: {dt:.2f} s = {r['frames'] / dt:.1f} rig frames/s overall "
              f"({1 / per_frame:.1f} after the {r['setup_seconds']:.2f} s setup); target >= 15 frames/s; "
              f"load average {load:.1f} before, {os.getloadavg()[0]:.1f} after (valid only when both are ~0)")
        per_cam = cpu / (r["frames"] * D)
        print(f"  CPU time: {cpu:.2f} s in all processes = {per_cam * 1000:.1f} ms per camera-frame "
              f"(= {1 / (per_cam * D):.1f} rig frames/s per fully used core, at most "
              f"{min(r['workers'], os.cpu_count() or 1) / (per_cam * D):.1f} with {r['workers']} workers on idle cores)")
        print(f"  extrapolated 30 s recording (900 frames), wall clock: {r['setup_seconds'] + 900 * per_frame:.0f} s "
              f"= {900 / (r['setup_seconds'] + 900 * per_frame):.1f} frames/s")
        print(f"peak RSS: this process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB, "
              f"largest worker {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024:.0f} MB")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
