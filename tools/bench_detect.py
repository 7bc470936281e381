"""The keypoint detector (detect stage) against a synthetic session's ground truth.

The ground-truth 3D keypoints (ground_truth/keypoints3d.npy: BODY_25, left hand, right hand)
are projected into every view and compared with what the detector finds in each colour image,
run through the stage's own loop (`detect_session`: views in turn, frames in order, so the
person crop gets each view's previous box). Reported per mode:
* images where the whole person is in view (every projected BODY_25 point on the image) and how
  many of them came back with no person;
* 2D errors (pixels) of the detected body points and hand points (conf > 0) against the
  projected truth: median, mean, 90th percentile; hands also on the points the depth image
  shows (not hidden by the body or object: the measured depth there is not nearer than the
  point by more than a margin), and the fraction of hand points (on the image, and shown)
  that were detected;
* seconds per image (detector and image reading).

    OMP_NUM_THREADS=1 python -m tools.bench_detect --session S [--frames N] [--mode full|crop|both]
        [--crop-size 512[,384,...]] [--margin M] [--hint-margin M] [--rescue-margins M,M] [--no-hint]
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from intercap.geometry.cameras import Cameras, project
from intercap.session import Session, openpose_to_array
from intercap.stages.detect.stage import PersonCropDetector, detect_session, keypoints_path, make_detector

NUM_BODY, NUM_HANDS = 25, 42
HIDDEN_MARGIN_M = {"body": 0.10, "hand": 0.04}  # nearer measured depth than this: the point is hidden


def projected_truth(session: Session, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth keypoints of frames `rows` (indices into frame_ids) in every view:
    pixels (C, F, 67, 2) and camera depth (C, F, 67) in metres."""
    gt = session.ground_truth()
    if gt is None or gt.keypoints3d is None:
        raise SystemExit(f"{session.root} has no ground_truth/keypoints3d.npy")
    points = torch.as_tensor(gt.keypoints3d[rows], dtype=torch.float64)  # (F, 67, 3)
    cams = Cameras.from_infos(session.cameras, dtype=torch.float64)
    F, K, _ = points.shape
    uv, z = project(points.reshape(-1, 3), cams)  # (C, F*67, 2), (C, F*67)
    return uv.reshape(-1, F, K, 2).numpy(), z.reshape(-1, F, K).numpy()


def shown(session: Session, rows: np.ndarray, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(C, F, 67) bool: the point is on the image and the depth image does not show something
    nearer there (no measurement counts as shown)."""
    C, F, K = z.shape
    margin = np.r_[np.full(NUM_BODY, HIDDEN_MARGIN_M["body"]), np.full(NUM_HANDS, HIDDEN_MARGIN_M["hand"])]
    out = np.zeros((C, F, K), bool)
    for c, cam in enumerate(session.cameras):
        for i, row in enumerate(rows):
            depth = session.read_depth(c, int(session.frame_ids[row]))
            if depth is None:
                continue
            px = np.round(uv[c, i]).astype(int)  # (K, 2)
            on = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height) & (z[c, i] > 0)
            d = np.zeros(K, np.float32)
            d[on] = depth[px[on, 1], px[on, 0]]
            out[c, i] = on & ((d <= 0) | (d > z[c, i] - margin))
    return out


def run_detector(session: Session, rows: np.ndarray, detector) -> tuple[np.ndarray, float]:
    """Detected keypoints (C, F, 137, 3) of frames `rows` through the stage's loop (NaN where a
    frame was dropped), and the seconds per image."""
    only = np.zeros((session.num_cameras, session.num_frames), bool)
    only[:, rows] = True
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        counts = detect_session(session, tmp, detector, progress=False, only=only)
        seconds = (time.perf_counter() - start) / max(counts["written"], 1)
        out = np.full((session.num_cameras, len(rows), 137, 3), np.nan)
        for c, cam in enumerate(session.cameras):
            for i, row in enumerate(rows):
                path = keypoints_path(tmp, cam.name, int(session.frame_ids[row]))
                if path.is_file():
                    out[c, i], _ = openpose_to_array(json.loads(path.read_text()))
    return out, seconds


def summarise(detected: np.ndarray, uv: np.ndarray, z: np.ndarray, visible: np.ndarray, widths, heights,
              only: np.ndarray | None = None) -> dict:
    """The figures of one mode (module docstring), on the images where `only` (C, F) is True (all by default)."""
    if only is not None:
        detected = np.where(only[..., None, None], detected, np.nan)
    W = np.asarray(widths, np.float64)[:, None, None]
    H = np.asarray(heights, np.float64)[:, None, None]
    on_image = (uv[..., 0] >= -0.5) & (uv[..., 0] <= W - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= H - 0.5) & (z > 0)
    read = ~np.isnan(detected[..., 0, 0])  # (C, F)
    whole = on_image[..., :NUM_BODY].all(-1) & read  # (C, F)
    person = (np.nan_to_num(detected[..., 2]) > 0).any(-1)  # (C, F)
    found = np.nan_to_num(detected[..., :67, 2]) > 0  # (C, F, 67)
    err = np.linalg.norm(np.nan_to_num(detected[..., :67, :2]) - uv, axis=-1)  # (C, F, 67)
    body, hand = np.s_[..., :NUM_BODY], np.s_[..., NUM_BODY:67]
    read3 = read[..., None]

    def stats(e: np.ndarray) -> tuple[float, float, float]:
        return (float(np.median(e)), float(np.mean(e)), float(np.percentile(e, 90))) if e.size else (np.nan,) * 3

    return {
        "images": int(read.sum()),
        "whole": int(whole.sum()),
        "no_person_whole": int((whole & ~person).sum()),
        "no_person_all": int((read & ~person).sum()),
        "missed": [(int(c), int(i)) for c, i in zip(*np.nonzero(whole & ~person))],  # (view, row)
        "body": stats(err[body][found[body]]),
        "body_found": float(found[body][(on_image & read3)[body]].mean()),
        "hand": stats(err[hand][found[hand]]),
        "hand_shown": stats(err[hand][(found & visible)[hand]]),
        "hand_found": float(found[hand][(on_image & read3)[hand]].mean()),
        "hand_shown_found": float(found[hand][(visible & read3)[hand]].mean()),
    }


def build(size: int | None, args) -> object:
    """The detector of one mode: MediaPipe alone (size None) or inside PersonCropDetector."""
    inner = make_detector("mediapipe")
    if size is None:
        return inner
    detector = PersonCropDetector(inner, crop_size_px=size)
    if args.margin is not None:
        detector.margin = args.margin
    if args.hint_margin is not None:
        detector.hint_margin = args.hint_margin
    if args.rescue_margins is not None:
        detector.rescue_margins = tuple(float(m) for m in args.rescue_margins.split(",") if m)
    if args.no_hint:
        detector.takes_hint = False  # the full image first, every time; no rescue from neighbouring frames
    return detector


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--session", required=True, type=Path)
    parser.add_argument("--frames", type=int, default=0, help="an evenly spread subset of this many frames (0: all)")
    parser.add_argument("--mode", choices=("full", "crop", "both"), default="both")
    parser.add_argument("--crop-size", default="512", help="crop side(s) in pixels, comma-separated")
    parser.add_argument("--margin", type=float, help="crop margin (fraction of the box)")
    parser.add_argument("--hint-margin", type=float, help="crop margin around the previous frame's box")
    parser.add_argument("--rescue-margins", help="crop margins when the full image has no person, comma-separated")
    parser.add_argument("--no-hint", action="store_true", help="crop: no box from neighbouring frames")
    args = parser.parse_args(argv)

    session = Session.load(args.session)
    rows = np.arange(session.num_frames)
    if 0 < args.frames < session.num_frames:
        rows = np.unique(np.round(np.linspace(0, session.num_frames - 1, args.frames)).astype(int))
    uv, z = projected_truth(session, rows)
    visible = shown(session, rows, uv, z)
    widths, heights = [c.width for c in session.cameras], [c.height for c in session.cameras]
    print(f"{session.root.name}: {session.num_cameras} views x {len(rows)} frames, "
          f"{widths[0]}x{heights[0]}; person height in view (median px): "
          f"{np.median(np.ptp(uv[..., :NUM_BODY, 1], axis=-1)):.0f}")

    modes = [("full", None)] if args.mode in ("full", "both") else []
    if args.mode in ("crop", "both"):
        modes += [(f"crop {int(s)}{' no-hint' if args.no_hint else ''}", int(s)) for s in args.crop_size.split(",")]
    table, missed, results = [], [], []
    for label, size in modes:
        with build(size, args) as detector:
            detected, seconds = run_detector(session, rows, detector)
        results.append(detected)
        s = summarise(detected, uv, z, visible, widths, heights)
        runs = (f" ({(detector.crops + detector.full_passes) / max(s['images'], 1):.2f} runs/img)"
                if size is not None else "")
        table.append(
            f"{label:<18} {s['images']:>6} {s['whole']:>5} {s['no_person_whole']:>4} ({s['no_person_all']:>2})"
            f" {'%.1f/%.1f/%.1f' % s['body']:>16} {100 * s['body_found']:>5.1f}%"
            f" {'%.1f/%.1f/%.1f' % s['hand']:>16} {'%.1f/%.1f/%.1f' % s['hand_shown']:>16}"
            f" {100 * s['hand_found']:>5.1f}% {100 * s['hand_shown_found']:>6.1f}% {seconds:>6.3f}{runs}")
        missed.append(f"{label}: " + " ".join(f"{c}:{int(session.frame_ids[rows[i]])}" for c, i in s["missed"]))
        print(table[-1], flush=True)
    print("\nno-person: images with the whole person in view that found no person (of all images); px: median/"
          "mean/p90 of the detected points; body% / hand%: detected of the points on the image; shown: hand points "
          "the depth image shows")
    print(f"{'mode':<18} {'images':>6} {'whole':>5} {'no-person':>9} {'body px':>16} {'body%':>6} {'hand px':>16} "
          f"{'shown hand px':>16} {'hand%':>6} {'shown%':>7} {'s/img':>6}")
    print("\n".join(table))
    print("no person (view:frame):\n  " + "\n  ".join(missed))
    if len(results) > 1:  # the same images for every mode: those where each found a person
        common = np.logical_and.reduce([(np.nan_to_num(d[..., 2]) > 0).any(-1) for d in results])  # (C, F)
        print(f"on the {int(common.sum())} images where every mode found a person:")
        for (label, _), detected in zip(modes, results):
            s = summarise(detected, uv, z, visible, widths, heights, only=common)
            print(f"  {label:<16} body px {'%.1f/%.1f/%.1f' % s['body']:>15} {100 * s['body_found']:5.1f}%"
                  f"  hand px {'%.1f/%.1f/%.1f' % s['hand']:>15} {100 * s['hand_found']:5.1f}%"
                  f"  shown hand px {'%.1f/%.1f/%.1f' % s['hand_shown']:>15} {100 * s['hand_shown_found']:5.1f}%")


if __name__ == "__main__":
    main()
