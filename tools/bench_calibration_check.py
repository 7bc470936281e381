"""Benchmark of the calibration check (prepare): false alarms and detection.

For each session (exact synthetic calibrations from the generator's rigs), the
check runs as prepare runs it (a few frames spread over the take) on the exact
calibration, then with one camera at a time moved by a known drift (default
10 mm / 0.5 deg, turned about the camera's own centre as a bumped camera turns,
or with --about rig about the rig centre, which moves what the camera sees
near the centre least; the camera's points are moved as its T_world_from_cam
would be). Prints per session: the largest observable correction and its sigma on
exact data, the pairs flagged (must be none), and for each drifted camera
whether it was flagged and named; seconds per check and per session frame.

    python -m tools.bench_calibration_check SESSION [SESSION ...] [--drift-mm 10 --drift-deg 0.5] [--about rig]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch


def drift_transform(rotation_deg: float, translation_mm: float, seed: int, pivot=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) world-frame rigid motion: rotation_deg about a random axis through `pivot` (the
    camera's centre, or the rig centre at the world origin) and translation_mm in a random
    direction."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotation_deg) * axis / np.linalg.norm(axis)).as_matrix()
    pivot = np.asarray(pivot, dtype=np.float64)
    T[:3, 3] = pivot - T[:3, :3] @ pivot + direction / np.linalg.norm(direction) * translation_mm / 1000
    return T


def load_views(session_dir: Path, frames: int):
    """Per camera, its world points of `frames` frames spread over the take, read as prepare reads them
    (`checkable_frames`, `view_points`: frames seen by fewer than two views left out)."""
    from intercap.config import PrepareConfig
    from intercap.geometry.cameras import Cameras
    from intercap.session import Session
    from intercap.stages.prepare.stage import ViewClouds, checkable_frames, view_points

    session = Session.load(session_dir)
    cameras = Cameras.from_infos(session.cameras)
    clouds = ViewClouds(session, cameras, PrepareConfig())
    per_view, _ = view_points(session, clouds, checkable_frames(session, frames), None, "", False)
    return session, cameras.centers.numpy(), per_view


def main(argv=None) -> None:
    from intercap.calib.alignment import suspect_cameras
    from intercap.config import PrepareConfig
    from intercap.stages.prepare.stage import check_views

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sessions", type=Path, nargs="+")
    parser.add_argument("--drift-mm", type=float, default=10.0)
    parser.add_argument("--drift-deg", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--about", choices=["camera", "rig"], default="camera",
                        help="the drift's rotation pivot: the camera's centre (default) or the rig centre")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cfg = PrepareConfig()
    print(f"calibration check: flag when the observable correction > {cfg.calib_warn_mm:g} mm "
          f"(or {cfg.calib_warn_deg:g} deg) and > {cfg.calib_k_sigma:g} sigma; {cfg.calib_frames} frames per check")
    header = (f"{'session':<28} {'views':>5} {'size':>8} {'exact: max corr mm (sigma)':>27} {'max deg':>8} "
              f"{'flags':>5}  {f'drift {args.drift_mm:g} mm/{args.drift_deg:g} deg about {args.about}: named':<40} "
              f"{'s/check':>7} {'s/frame':>7}")
    print(header)
    print("-" * len(header))
    for session_dir in args.sessions:
        session, centers, per_view = load_views(session_dir, cfg.calib_frames)
        names = [c.name for c in session.cameras]
        start = time.perf_counter()
        exact = check_views(per_view, names, centers, cfg)
        seconds = time.perf_counter() - start
        worst = max(exact, key=lambda r: r.correction_translation_mm if np.isfinite(r.correction_translation_mm) else -1)
        max_deg = max((r.correction_rotation_deg for r in exact if np.isfinite(r.correction_rotation_deg)), default=np.nan)
        n_flags = sum(r.flagged for r in exact)
        detected = []
        for c, name in enumerate(names):
            pivot = centers[c] if args.about == "camera" else np.zeros(3)
            T = drift_transform(args.drift_deg, args.drift_mm, args.seed + c, pivot)
            moved = [p if i != c else [f @ T[:3, :3].T + T[:3, 3] for f in p] for i, p in enumerate(per_view)]
            suspects = suspect_cameras(check_views(moved, names, centers, cfg))
            detected.append(f"{name}:{'+' if suspects == [name] else ('~' if any(name in s for s in suspects) else '-')}")
        info = session.cameras[0]
        print(f"{session_dir.name:<28} {len(names):>5} {f'{info.width}x{info.height}':>8} "
              f"{f'{worst.correction_translation_mm:.1f} ({worst.translation_sigma_mm:.1f})':>27} {max_deg:>8.2f} "
              f"{n_flags:>5}  {' '.join(detected):<40} {seconds:>7.2f} {seconds / session.num_frames:>7.3f}")
    print("named: + the drifted camera alone, ~ among others, - missed")


if __name__ == "__main__":
    main()
