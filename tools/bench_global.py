"""Benchmark of the `global` stage (joint body-object refinement): per-frame vs global against ground truth.

Synthetic sessions at 10 fps (the scripts at natural speed) are generated, the
per-frame stages run (prepare, object, body, contact), then the global stage,
and both results are scored with `intercap eval`'s metrics:
  * body surface error, MPJPE, hand keypoint error (mm), object ADD / ADD-S (mm),
  * penetration of the body into the object on ground-truth contact frames
    (mean / median / max over frames of the per-frame maximum, mm),
  * jitter: mean vertex acceleration of body and object (m/s^2) beside the
    ground truth's, and at the window seams against elsewhere,
  * contact-detection accuracy (%), seconds per frame of the global stage, peak memory;
  * each frame's mean distance from its own depth points to the fitted mesh: the worst frame's over
    the take's median (a frame whose fit left its data), and the frames the stage repaired.
Sessions named *_alone are a person alone (no object): the joint fit fits the body alone.

    python -m tools.bench_global [--sessions pick4,drink4] [--fps 10] [--keep DIR] [--set global.KEY=VALUE]

With --keep, sessions and per-frame results found there are reused (only the
global stage is redone), so weights can be compared quickly.
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

# name: (script, object, frames (None: the script at natural speed), phenotype, cameras)
SESSIONS = {
    "pick4": ("pick_place", "box", 73, (0.5, 0.5, 0.5, 0.5, 0.5, 0.5), 4),
    "drink4": ("lift_drink", "cup", 59, (0.1, 0.3, 0.4, 0.7, 0.3, 0.6), 4),
    "pick6": ("pick_place", "box", 73, (0.9, 0.7, 0.7, 0.3, 0.8, 0.4), 6),
    "pick1": ("pick_place", "box", 73, (0.5, 0.5, 0.5, 0.5, 0.5, 0.5), 1),
    "lift1": ("table_lift", "carton", 68, (0.4, 0.5, 0.5, 0.5, 0.5, 0.5), 1),
    "turn1_alone": ("turn", "none", None, (0.5, 0.5, 0.5, 0.5, 0.5, 0.5), 1),
    "turn4_alone": ("turn", "none", None, (0.3, 0.6, 0.5, 0.4, 0.6, 0.5), 4),
    "bend4_alone": ("bend", "none", None, (0.7, 0.4, 0.6, 0.5, 0.4, 0.5), 4),
    "bend1_alone": ("bend", "none", None, (0.7, 0.4, 0.6, 0.5, 0.4, 0.5), 1),
    "sit4_alone": ("sit_stand", "none", None, (0.2, 0.5, 0.4, 0.6, 0.5, 0.5), 4),
    "walk4_alone": ("walk_out", "none", None, (0.6, 0.5, 0.5, 0.5, 0.5, 0.5), 4),
    "walk1_alone": ("walk_out", "none", None, (0.6, 0.5, 0.5, 0.5, 0.5, 0.5), 1),
}
FPS = 10.0  # the default frame rate (--fps)
PER_FRAME_FILES = {"body": ("body_params.npz", "body_vertices.npy", "body_faces.npy", "keypoints3d.npy"),
                   "object": ("object_poses.npz",)}


def make_session(name: str, root: Path, width: int, height: int, fps: float = FPS) -> Path:
    from intercap.synth.generator import SynthConfig, generate_session

    script, obj, frames, phenotype, cams = SESSIONS[name]
    if frames is not None:
        frames = round(frames * fps / FPS)
    path = root / name
    if not (path / "session.yaml").exists():
        generate_session(SynthConfig(script=script, object=obj, frames=frames, fps=fps, phenotype=phenotype,
                               cameras=cams, width=width, height=height, quiet=True), path)
    return path


def per_frame_view(out: Path, view: Path) -> Path:
    """A results folder holding the per-frame stages' own files (and the contact labels) for `evaluate`."""
    shutil.rmtree(view, ignore_errors=True)
    view.mkdir(parents=True)
    for stage, names in PER_FRAME_FILES.items():
        for name in names:
            if (out / stage / name).exists():  # a person alone has no object poses
                os.link(out / stage / name, view / name)
    if (out / "contact.npy").exists():
        os.link(out / "contact.npy", view / "contact.npy")
    return view


def seam_jitter(vertices: np.ndarray, gt: np.ndarray, fps: float, plan) -> tuple[float, float]:
    """Mean |acceleration - ground truth's| (m/s^2) over body vertices, at second differences touching
    a window seam and elsewhere."""
    acc = lambda v: (v[2:] - 2 * v[1:-1] + v[:-2]) * fps**2  # noqa: E731
    excess = np.linalg.norm(acc(vertices) - acc(gt), axis=-1).mean(-1)  # (T-2,), over vertices
    seams = np.zeros(len(excess), bool)
    for _, _, _, commit in plan[:-1]:
        seams[max(0, commit - 3):commit] = True  # differences centred on commit-2 .. commit, i.e. across it
    ok = np.isfinite(excess)
    return float(excess[seams & ok].mean()) if (seams & ok).any() else float("nan"), float(excess[~seams & ok].mean())


def score(out: Path, session: Path) -> dict:
    from intercap.evaluation.evaluate import evaluate

    m = evaluate(out, session).metrics
    pick = ("body_surface_mm", "keypoint_mpjpe_mm", "hand_keypoint_mm", "object_add_mm", "object_adds_mm",
            "penetration_mean_mm", "penetration_median_mm", "penetration_max_mm", "jitter_mps2",
            "jitter_gt_mps2", "object_jitter_mps2", "object_jitter_gt_mps2", "contact_accuracy_pct")
    return {k: m.get(k) for k in pick}


def data_departure(vertices: np.ndarray, session_dir: Path, out: Path, overrides: list[str]) -> float:
    """The worst frame's mean distance from its own depth points (the person's, as the body stage
    segments them) to the nearest vertex of the fitted mesh, over the take's median of that figure."""
    from scipy.spatial import cKDTree

    from intercap.config import load_config
    from intercap.geometry.cameras import Cameras
    from intercap.session import Session
    from intercap.stages.global_fit.observations import Observations

    session = Session.load(session_dir)
    cfg = load_config(overrides=overrides)
    obs = Observations(session, cfg, out, Cameras.from_infos(session.cameras), with_object=False)
    frames = np.arange(len(vertices))
    mean = np.full(len(frames), np.nan)
    for part in np.array_split(frames, -(-len(frames) // 32)):
        window = obs.window(part, None, None).obs
        points, valid = window.points.numpy(), window.point_valid.numpy()
        for b, i in enumerate(part):
            if valid[b].any() and np.isfinite(vertices[i]).all():
                mean[i] = float(cKDTree(vertices[i]).query(points[b][valid[b]])[0].mean())
    return float(np.nanmax(mean) / np.nanmedian(mean))


def run_session(name: str, root: Path, overrides: list[str], width: int, height: int, fps: float = FPS) -> dict:
    from intercap.config import load_config
    from intercap.pipeline import available_stages, run_pipeline
    from intercap.stages.global_fit.fitter import windows

    session = make_session(name, root, width, height, fps)
    out = root / f"out_{name}"
    per_frame = [s for s in available_stages() if s not in ("global", "export")]
    run_pipeline(session, out, load_config(overrides=overrides), stages=per_frame, progress=False)
    before = score(per_frame_view(out, root / f"per_frame_{name}"), session)
    # the stage's own time: the HTML report the pipeline writes after it is not the joint fit's cost
    cfg = load_config(overrides=["run.force=true", "report.enabled=false", *overrides])
    cpu0, start = time.process_time(), time.perf_counter()
    figures = run_pipeline(session, out, cfg, stages=["global"], progress=False)["global"]
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu0
    after = score(out, session)
    T = len(np.load(out / "body_vertices.npy", mmap_mode="r"))
    gt = np.load(session / "ground_truth" / "body_vertices.npy")
    plan = windows(T, cfg.global_.window_frames, cfg.global_.window_overlap, cfg.global_.window_history)
    seam = seam_jitter(np.load(out / "body_vertices.npy"), gt, fps, plan)
    seam_pf = seam_jitter(np.load(out / "body" / "body_vertices.npy"), gt, fps, plan)
    for scores, folder in ((before, out / "body"), (after, out)):
        scores["departure"] = data_departure(np.load(folder / "body_vertices.npy"), session, out, overrides)
    return {"before": before, "after": after, "s_per_frame": wall / T, "cpu_per_frame": cpu / T, "frames": T,
            "seam": seam, "seam_per_frame": seam_pf, "windows": figures.get("windows"),
            "repaired": figures.get("frames_repaired"), "skipped": figures.get("skipped")}


def fmt(v, digits=1):
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{digits}f}"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sessions", default="pick4,drink4", help=f"any of {', '.join(SESSIONS)}")
    parser.add_argument("--fps", type=float, default=FPS)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=576)
    parser.add_argument("--keep", type=Path, help="keep (and reuse) sessions and per-frame results here")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench_global_"))
    root.mkdir(parents=True, exist_ok=True)
    rows = {}
    for name in args.sessions.split(","):
        rows[name] = run_session(name, root, args.set, args.width, args.height, args.fps)
        r = rows[name]
        print(f"[{name}] {r['frames']} frames, {r['windows']} windows, {r['repaired']} frames repaired, "
              f"{r['s_per_frame']:.2f} s/frame wall, {r['cpu_per_frame']:.2f} s/frame CPU"
              + (f", skipped: {r['skipped']}" if r["skipped"] else ""), flush=True)
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    columns = [("body_surface_mm", "surface mm"), ("keypoint_mpjpe_mm", "MPJPE mm"), ("hand_keypoint_mm", "hands mm"),
               ("object_adds_mm", "ADD(-S) mm"), ("penetration_mean_mm", "pen. mean"),
               ("penetration_median_mm", "pen. median"), ("penetration_max_mm", "pen. max"),
               ("jitter_mps2", "jitter m/s2"), ("jitter_ratio", "x truth"), ("object_jitter_mps2", "obj. jitter"),
               ("contact_accuracy_pct", "contact %"), ("departure", "worst/median")]
    print()
    print(f"{'session':8s} {'result':9s} " + " ".join(f"{h:>11s}" for _, h in columns))
    for name, r in rows.items():
        for label, key in (("per-frame", "before"), ("global", "after")):
            values = dict(r[key])
            if values.get("object_adds_mm") is None:
                values["object_adds_mm"] = values.get("object_add_mm")
            if values.get("jitter_mps2") and values.get("jitter_gt_mps2"):
                values["jitter_ratio"] = values["jitter_mps2"] / values["jitter_gt_mps2"]
            print(f"{name:8s} {label:9s} " + " ".join(f"{fmt(values.get(k), 2 if 'jitter' in k else 1):>11s}"
                                                     for k, _ in columns))
        gt = r["after"]
        print(f"{name:8s} {'truth':9s} " + " ".join(
            f"{fmt(gt.get('jitter_gt_mps2'), 2) if k == 'jitter_mps2' else fmt(gt.get('object_jitter_gt_mps2'), 2) if k == 'object_jitter_mps2' else '':>11s}"
            for k, _ in columns))
    print()
    for name, r in rows.items():
        print(f"[{name}] excess acceleration (m/s^2) at window seams {fmt(r['seam'][0], 2)} vs elsewhere "
              f"{fmt(r['seam'][1], 2)} (per-frame: {fmt(r['seam_per_frame'][0], 2)} / {fmt(r['seam_per_frame'][1], 2)})")
    print(f"peak memory {peak_gb:.2f} GB; sessions in {root}")


if __name__ == "__main__":
    main()
