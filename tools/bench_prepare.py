"""Benchmark of the `prepare` stage against ground truth.

On a synthetic session (made here, or given with --session) it measures:
ground-plane error (angle in degrees, offset in mm) against the generator's
floor; the calibration check's answer when one camera's extrinsic is drifted
by a known amount (how much of the drift it recovers, mm / deg) and when the
calibration is exact; seconds per frame for back-projecting and fusing all
views; peak memory.

    python -m tools.bench_prepare [--session DIR] [--cameras 4 --width 640 --height 576 --frames 10]
"""
from __future__ import annotations

import argparse
import json
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def drift_transform(rotation_deg: float, translation_mm: float, seed: int = 0) -> np.ndarray:
    """A rigid world-frame perturbation of known size."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotation_deg) * axis).as_matrix()
    T[:3, 3] = direction * translation_mm / 1000
    return T


def drifted_copy(session_dir: Path, target: Path, camera: int, T_drift: np.ndarray) -> Path:
    """A copy of the session whose calibration has camera `camera` moved by T_drift (world frame).

    Images are linked, not copied."""
    target.mkdir(parents=True)
    for item in session_dir.iterdir():
        if item.name != "calibration.json":
            (target / item.name).symlink_to(item.resolve())
    calib = json.loads((session_dir / "calibration.json").read_text())
    T = np.array(calib["cameras"][camera]["T_world_from_cam"])
    calib["cameras"][camera]["T_world_from_cam"] = (T_drift @ T).tolist()
    (target / "calibration.json").write_text(json.dumps(calib, indent=1))
    return target


def run_prepare(session_dir: Path, out_dir: Path, overrides: list[str]) -> tuple[dict, float]:
    from intercap.config import load_config
    from intercap.pipeline import run_pipeline

    cfg = load_config(overrides=overrides + ["run.force=true"])
    start = time.perf_counter()
    metrics = run_pipeline(session_dir, out_dir, cfg, stages=["prepare"], progress=False)
    return metrics["prepare"], time.perf_counter() - start


def time_clouds(session_dir: Path) -> float:
    """Seconds per frame to read and back-project every view (rays cached, as the stage does)."""
    from intercap.config import PrepareConfig
    from intercap.geometry.cameras import Cameras
    from intercap.session import Session
    from intercap.stages.prepare.stage import ViewClouds

    session = Session.load(session_dir)
    clouds = ViewClouds(session, Cameras.from_infos(session.cameras), PrepareConfig())
    clouds.frame(int(session.frame_ids[0]))  # rays
    start = time.perf_counter()
    for frame_id in session.frame_ids:
        clouds.frame(int(frame_id))
    return (time.perf_counter() - start) / session.num_frames


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--session", type=Path, help="existing synthetic session (default: generate one)")
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=576)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--drift-mm", type=float, default=20.0)
    parser.add_argument("--drift-deg", type=float, default=1.0)
    args = parser.parse_args(argv)
    torch.set_num_threads(max(torch.get_num_threads(), 1))
    work = Path(tempfile.mkdtemp(prefix="bench_prepare_"))
    try:
        session = args.session
        if session is None:
            from intercap.synth.generator import SynthConfig, generate_session

            cfg = SynthConfig(cameras=args.cameras, width=args.width, height=args.height, frames=args.frames, quiet=True)
            t0 = time.perf_counter()
            session = generate_session(cfg, work / "session")
            print(f"generated {args.cameras} views x {args.frames} frames at {args.width}x{args.height} "
                  f"in {time.perf_counter() - t0:.1f} s")
        session = Path(session)
        truth = json.loads((session / "ground_truth" / "ground.json").read_text())
        num_frames = len(list((session / json.loads((session / "calibration.json").read_text())["cameras"][0]["name"] / "depth").glob("*.png")))

        # The stage as users run it (defaults: ground from 5 frames, ICP check on 3).
        figures, seconds = run_prepare(session, work / "exact", ["prepare.save_clouds=false"])
        ground = json.loads((work / "exact" / "prepare" / "ground.json").read_text())
        normal_err = angle_deg(ground["normal"], truth["normal"])
        offset_mm = abs((np.array(ground["point"]) - np.array(truth["point"])) @ np.array(truth["normal"])) * 1000
        check = json.loads((work / "exact" / "prepare" / "calibration_check.json").read_text())
        exact_corr = max(p["correction_translation_mm"] for p in check["pairs"])
        exact_rot = max(p["correction_rotation_deg"] for p in check["pairs"])
        clouds_seconds = time_clouds(session)

        T = drift_transform(args.drift_deg, args.drift_mm)
        drifted = drifted_copy(session, work / "drifted", 0, T)
        run_prepare(drifted, work / "drift_out", ["prepare.calib_frames=3"])
        dcheck = json.loads((work / "drift_out" / "prepare" / "calibration_check.json").read_text())
        name0 = json.loads((session / "calibration.json").read_text())["cameras"][0]["name"]
        involving = [p for p in dcheck["pairs"] if name0 in (p["cam_a"], p["cam_b"])]
        others = [p for p in dcheck["pairs"] if name0 not in (p["cam_a"], p["cam_b"])]
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

        print("\nprepare benchmark (synthetic, ground truth known)")
        print(f"  ground normal error        {normal_err:.3f} deg")
        print(f"  ground offset error        {offset_mm:.2f} mm   (rmse of inliers {figures['ground_rmse_mm']:.1f} mm)")
        print(f"  exact calibration: largest correction {exact_corr:.2f} mm / {exact_rot:.3f} deg over {len(check['pairs'])} pairs")
        print(f"  camera 0 drifted {args.drift_mm:.0f} mm / {args.drift_deg:.1f} deg: corrections found on its pairs "
              + ", ".join(f"{p['correction_translation_mm']:.1f} mm / {p['correction_rotation_deg']:.2f} deg" for p in involving))
        print("  other pairs: " + ", ".join(f"{p['correction_translation_mm']:.1f} mm" for p in others)
              + f"; flagged pairs: {[(p['cam_a'], p['cam_b']) for p in dcheck['flagged']]}")
        print(f"  speed: back-projection of all views {clouds_seconds:.3f} s per frame; the whole stage with defaults "
              f"{seconds:.1f} s for {num_frames} frames (ground from 5 frames, ICP check on 3)")
        print(f"  peak memory (process RSS) {peak_mb:.0f} MB")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
