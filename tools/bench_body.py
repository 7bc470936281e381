"""Benchmark of the `body` stage (per-frame whole-body fitting) against ground truth.

Synthetic sessions with different phenotypes (a child too), scripts, 1, 4 or 6
views, framings, outfits and lighting are generated, fitted with the `body` stage
(session keypoints and person masks; `raw4` has neither: `detect` finds the
keypoints, the body stage derives the masks) after `prepare` (the floor: until
2026-11-26 the bench ran without it, so a body-only figure from before then
lacks the floor terms), and scored:
  * body surface error (symmetric point-to-surface, mm; `intercap eval`'s),
  * MPJPE over BODY_25 (mm), hand keypoint error relative to the wrist (mm),
  * vertex-to-point-cloud distance: each view's segmented person points to the
    fitted surface, median per frame, averaged (the paper's fitting-accuracy
    figure; InterCap reports 19 mm at 3-5 minutes per frame), and the worst
    frame's mean distance (every frame within 20 mm on average),
  * frames not fitted, seconds per frame (all views) and peak memory.

    python -m tools.bench_body [--frames 30] [--sessions pick4,drink4,pick6] [--keep DIR] [--set body.KEY=VALUE]

`--frames N` spans each script with N frames (N=30 is about 5 fps: larger
motion between frames than a capture at 30 fps); `--frames 0` uses every
frame at 30 fps.
"""
from __future__ import annotations

import argparse
import logging
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

# name: (script, object, phenotype gender,age,muscle,weight,height,proportions, cameras[, other SynthConfig fields])
SESSIONS = {
    "pick4": ("pick_place", "box", (0.5, 0.5, 0.5, 0.5, 0.5, 0.5), 4),
    "drink4": ("lift_drink", "cup", (0.1, 0.3, 0.4, 0.7, 0.3, 0.6), 4),
    "pick6": ("pick_place", "box", (0.9, 0.7, 0.7, 0.3, 0.8, 0.4), 6),
    "drink6": ("lift_drink", "cup", (0.8, 0.2, 0.3, 0.5, 0.6, 0.5), 6),
    "turn1": ("turn", "box", (0.5, 0.5, 0.5, 0.5, 0.5, 0.5), 1),  # one view, the person turns round once
    "child1": ("hold", "box", (0.5, 0.25, 0.5, 0.5, 0.5, 0.5), 1),  # one view of a child (1.23 m)
    # one camera close in, upper body in view, turning round; another outfit
    "upper1": ("turn", "box", (0.5, 0.5, 0.5, 0.5, 0.5, 0.5), 1,
               dict(ring_radius=1.8, ring_height=1.45, look_at=(0.0, 0.0, 1.2), focal_scale=1.0, appearance=3)),
    # raw RGB-D: no keypoint or mask files (detected and derived), another outfit, a dim room
    "raw4": ("pick_place", "box", (0.5, 0.5, 0.5, 0.5, 0.5, 0.5), 4,
             dict(keypoints=False, masks=False, appearance=5, light=0.6)),
}


def point_cloud_distances_mm(session_dir: Path, out_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """Per fitted frame, the median and the mean distance (mm) from the person points (all views)
    to the fitted mesh."""
    from intercap.config import Config
    from intercap.geometry.cameras import Cameras
    from intercap.geometry.surfaces import TriangleSurface
    from intercap.session import Session
    from intercap.stages.body.observations import PersonPoints

    session = Session.load(session_dir)
    cfg = Config().body
    points = PersonPoints(session, Cameras.from_infos(session.cameras), cfg, out_dir)
    vertices = np.load(out_dir / "body_vertices.npy", mmap_mode="r")
    faces = np.load(out_dir / "body_faces.npy")
    no_keypoints = np.zeros((session.num_cameras, 67, 3), np.float32)
    medians, means = [], []
    for i, f in enumerate(session.frame_ids):
        if not np.isfinite(vertices[i]).all():
            continue
        cloud, valid = points.batch(np.array([f]), no_keypoints[None])
        cloud = cloud[0][valid[0]].numpy()
        if len(cloud):
            distance = TriangleSurface(np.asarray(vertices[i]), faces).closest(cloud)[0]
            medians.append(np.median(distance)), means.append(np.mean(distance))
    return 1000 * np.asarray(medians, float), 1000 * np.asarray(means, float)


def cloud_figures(medians: np.ndarray, means: np.ndarray) -> tuple[float, float]:
    """(mean over frames of the per-frame median, the worst frame's mean distance), mm."""
    if not len(medians):
        return float("nan"), float("nan")
    return float(medians.mean()), float(means.max())


def fit_and_score(session: Path, out: Path, overrides: list[str]) -> dict:
    from intercap.config import load_config
    from intercap.evaluation.evaluate import evaluate
    from intercap.pipeline import run_pipeline

    cfg = load_config(overrides=["run.force=true", *overrides])
    run_pipeline(session, out, cfg, stages=["prepare"], progress=False)  # the floor, as every run has it (untimed)
    start = time.perf_counter()
    metrics = run_pipeline(session, out, cfg, stages=["detect", "body"], progress=False)["body"]  # detect: where files lack
    seconds = time.perf_counter() - start
    result = evaluate(out, session).metrics
    frames = result["frames"]
    return {
        "surface": result["body_surface_mm"], "surface_median": result["body_surface_mm_median"],
        "mpjpe": result["keypoint_mpjpe_mm"], "hands": result["hand_keypoint_mm"],
        **dict(zip(("cloud", "cloud_worst"), cloud_figures(*point_cloud_distances_mm(session, out)))),
        "unfitted": frames - metrics["frames_fitted"], "frames": frames, "s_per_frame": seconds / frames,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=576)
    parser.add_argument("--frames", type=int, default=30, help="frames spanning each script; 0: the script at 30 fps")
    parser.add_argument("--sessions", default="pick4,drink4,pick6", help=f"any of {', '.join(SESSIONS)}")
    parser.add_argument("--keep", type=Path, help="keep the sessions and results here")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="config override, e.g. body.batch_frames=4 (repeatable)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from intercap.synth.generator import SynthConfig, generate_session

    work = args.keep or Path(tempfile.mkdtemp(prefix="bench_body_"))
    rows = []
    try:
        for name in args.sessions.split(","):
            script, obj, phenotype, cameras, *other = SESSIONS[name]
            session = work / f"{name}_{args.frames}_session"
            if not (session / "session.yaml").exists():
                cfg = SynthConfig(script=script, object=obj, cameras=cameras, width=args.width, height=args.height,
                                  frames=args.frames or None, fps=30.0, phenotype=phenotype, quiet=True,
                                  **(other[0] if other else {}))
                generate_session(cfg, session)
            rows.append((name, script, cameras, fit_and_score(session, work / f"{name}_{args.frames}_body", args.set)))
            print(f"{name} done", flush=True)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\nbody fitting at {args.width}x{args.height}, {args.frames or 'all (30 fps)'} frames per session")
    print("session  script      views  surface  surf med  MPJPE  hands  cloud  worst frame  unfitted  s/frame")
    for name, script, cameras, r in rows:
        print(f"{name:8s} {script:11s} {cameras:5d} {r['surface']:8.1f} {r['surface_median']:9.1f} {r['mpjpe']:6.1f} "
              f"{r['hands']:6.1f} {r['cloud']:6.1f} {r['cloud_worst']:12.1f} {r['unfitted']:4d}/{r['frames']:<4d} "
              f"{r['s_per_frame']:7.2f}")
    print("(mm; surface: symmetric point-to-surface; hands: relative to the wrist; cloud: person points to the fit,\n"
          " median per frame averaged over frames; worst frame: the largest per-frame mean of those distances)")
    print(f"peak memory (process RSS) {peak_mb:.0f} MB")


if __name__ == "__main__":
    main()
