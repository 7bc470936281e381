"""Benchmark of the calibration refinement (prepare, `prepare.calib_refine`): how much of a rig's
calibration error it takes out, and what it adds to an exact rig.

For each session (exact synthetic calibrations), each view's clouds of `prepare.calib_refine_frames`
frames are read as prepare reads them; then the cameras are put wrong by known drifts, their points
moved as a wrong T_world_from_cam would move them, and `refine_rig` runs as prepare runs it:
  exact        no drift (what refining a good rig costs);
  one camera   one camera turned `--one-deg` about its own centre and moved `--one-mm` (a bumped camera);
  all cameras  every camera turned `--all-deg` and moved `--all-mm` (a rig calibrated a little wrong
               everywhere), the common part taken out (the data cannot see it: the world frame itself).
Each camera's error is where it puts the subject (the clouds' centre) against where it is. Printed per
case: how far the cameras' displacements of the subject lie from the one most of them agree on (`apart`,
what the fits feel: views that disagree), that common displacement (`common`, a shift of the whole
world the fits follow), before and after, and seconds per refinement.

    python -m tools.bench_calibration_refine SESSION [SESSION ...] [--seeds 2] [--prior 1e-3] [--frames 8]
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np


def subject_errors(errors: np.ndarray, subject: np.ndarray) -> tuple[float, float, float]:
    """Cameras' world-frame pose errors (C, 4, 4) -> (mean mm their displacements of `subject` lie
    from the displacement most of them agree on (the geometric median: the fits follow the
    majority), mm of that common displacement, largest rotation error in degrees)."""
    from intercap.calib.alignment import geometric_median, rotation_angle_deg

    moved = errors[:, :3, :3] @ subject + errors[:, :3, 3] - subject  # (C, 3)
    common = geometric_median(moved)
    apart = np.linalg.norm(moved - common, axis=1).mean()
    return float(apart * 1000), float(np.linalg.norm(common) * 1000), max(rotation_angle_deg(E[:3, :3]) for E in errors)


def drifts(case: str, C: int, centers: np.ndarray, seed: int, args) -> np.ndarray:
    """(C, 4, 4) world-frame errors of the cameras' poses for `case`."""
    from intercap.calib.alignment import scaled_twist, twist_transform
    from tools.bench_calibration_check import drift_transform

    T = np.eye(4)[None].repeat(C, axis=0)
    if case == "one camera":
        c = seed % C
        T[c] = drift_transform(args.one_deg, args.one_mm, seed=seed, pivot=centers[c])
    elif case == "all cameras":
        T = np.stack([drift_transform(args.all_deg, args.all_mm, seed=100 * seed + c, pivot=centers[c]) for c in range(C)])
        centre, radius = np.zeros(3), 1.0  # the common part out, so the truth is the world frame the data can see
        x = np.stack([scaled_twist(t, centre, radius) for t in T])
        T = np.stack([twist_transform(v, centre, radius) for v in x - x.mean(axis=0)])
    return T


def main(argv=None) -> None:
    from intercap.config import PrepareConfig
    from intercap.stages.prepare.stage import refine_views
    from tools.bench_calibration_check import load_views

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sessions", nargs="+")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--one-mm", type=float, default=10.0)
    parser.add_argument("--one-deg", type=float, default=0.5)
    parser.add_argument("--all-mm", type=float, default=4.0)
    parser.add_argument("--all-deg", type=float, default=0.25)
    parser.add_argument("--prior", type=float, default=PrepareConfig.calib_refine_prior)
    parser.add_argument("--frames", type=int, default=PrepareConfig.calib_refine_frames)
    args = parser.parse_args(argv)
    cfg = dataclasses.replace(PrepareConfig(), calib_refine_prior=args.prior)

    print(f"{'session':<28} {'case':<14} {'seed':>4} {'apart mm':>16} {'common mm':>16} {'max deg':>14} {'s':>6}")
    for session_dir in args.sessions:
        session, centers, per_view = load_views(session_dir, args.frames)
        names = [c.name for c in session.cameras]
        subject = np.concatenate([np.concatenate(v) for v in per_view]).mean(axis=0)
        for case in ("exact", "one camera", "all cameras"):
            for seed in range(1 if case == "exact" else args.seeds):
                wrong = drifts(case, len(names), centers, seed, args)
                moved = [[f @ W[:3, :3].T + W[:3, 3] for f in view] for view, W in zip(per_view, wrong)]
                start = time.perf_counter()
                result = refine_views(moved, names, centers, cfg)
                seconds = time.perf_counter() - start
                before = subject_errors(wrong, subject)
                after = subject_errors(result.corrections @ wrong, subject)
                pairs = " -> ".join(f"{b:5.1f}" for b in (before[0], after[0]))
                common = " -> ".join(f"{b:5.1f}" for b in (before[1], after[1]))
                deg = " -> ".join(f"{b:4.2f}" for b in (before[2], after[2]))
                print(f"{str(session_dir)[-28:]:<28} {case:<14} {seed:>4} {pairs:>16} {common:>16} {deg:>14} {seconds:6.1f}",
                      flush=True)


if __name__ == "__main__":
    main()
