"""Benchmark of `intercap calibrate` against the true extrinsics of a synthetic board recording.

Renders (or reads, --session) a ChArUco or checkerboard board moved through a camera ring
(intercap.synth.boards), calibrates the rig and prints per camera: translation error (mm) and
rotation error (deg) against the truth (both in the first camera's frame), RMS reprojection
error (px), depth agreement with its neighbours (mm), with and without the depth ICP
refinement; then run time and peak memory.

    python -m tools.bench_calibrate [--cameras 4 --poses 10 --board charuco --depth-sigma 0.002]
"""
from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from intercap.calib.board import Board, calibrate_rig, pose_errors
from intercap.synth.boards import BoardSpec, board_rig, render_board_session


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", help="an existing board recording with ground_truth/calibration.json")
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--poses", type=int, default=10)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--board", choices=["charuco", "checkerboard"], default="charuco")
    ap.add_argument("--squares", default="7x5")
    ap.add_argument("--square-m", type=float, default=0.1)
    ap.add_argument("--marker-m", type=float, default=0.075)
    ap.add_argument("--depth-sigma", type=float, default=0.0, help="depth noise std in metres")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    squares = tuple(int(v) for v in args.squares.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        session = Path(args.session) if args.session else None
        if session is None:
            t = time.perf_counter()
            spec = BoardSpec(args.board, squares, args.square_m, args.marker_m)
            session = render_board_session(board_rig(args.cameras, args.width, args.height, seed=args.seed), spec,
                                           Path(tmp) / "rec", poses=args.poses, seed=args.seed,
                                           depth_sigma_m=args.depth_sigma)
            print(f"rendered {args.cameras} cameras x {args.poses} poses ({args.width}x{args.height}, {args.board}) "
                  f"in {time.perf_counter() - t:.1f} s")
        truth = np.array([c["T_world_from_cam"] for c in
                          json.loads((session / "ground_truth" / "calibration.json").read_text())["cameras"]])
        board = Board(args.board, squares, args.square_m, args.marker_m)
        for refine in (False, True):
            t, cpu = time.perf_counter(), time.process_time()
            result, _, _ = calibrate_rig(session, board, depth_refine=refine)
            wall, cpu = time.perf_counter() - t, time.process_time() - cpu
            trans, rot = pose_errors(result.T_world_from_cam, truth)
            print(f"\ndepth refinement {'on (applied)' if refine and result.depth_refined else 'on (not kept)' if refine else 'off'}")
            print(f"{'camera':<8} {'frames':>6} {'trans mm':>9} {'rot deg':>8} {'reproj px':>10} {'depth mm':>9}")
            for n, v, tm, rd, rp, dm in zip(result.names, result.views, trans, rot, result.reprojection_px,
                                            result.depth_mm):
                print(f"{n:<8} {v:>6d} {tm:>9.2f} {rd:>8.3f} {rp:>10.3f} {dm:>9.2f}")
            print(f"max {trans.max():.2f} mm / {rot.max():.3f} deg; {wall:.1f} s wall, {cpu:.1f} s CPU, "
                  f"{result.frames_used} shared frames")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
