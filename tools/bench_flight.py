"""Benchmark of free flight (GraviCap): gravity from a tossed object, and the global stage's flight term.

A `toss` session (the generator's block thrown straight up and caught, 30 fps, 4 views,
320x288, 14 frames of exact parabolic flight) runs through the pipeline up to `global`,
then `global` is redone with `--set global.w_flight=0`. Printed (ground truth:
ground_truth/object_poses.npz and ground_truth/physics.npz):
  * the flight episodes the run detected against the true ones (frames);
  * |g| (m/s^2) and its angle (deg) to the true down and to the fitted ground's down, from the
    free parabola fit (g not imposed) of the object's centre: per-frame tracking (`object`),
    `global` without the term (the term imposes g, so its own fit is not evidence);
  * object ADD-S (mm) over the true flight frames and over all frames, per-frame tracking,
    global without and with the term; object jitter in flight: mean |a - g| (m/s^2) of the
    centre (second differences) and the mean vertex acceleration (m/s^2; truth: 9.81);
  * the global stage's seconds per frame and this process's peak RSS.

    python -m tools.bench_flight [--keep DIR] [--set global.KEY=VALUE ...]

With --keep DIR the session and the first run are reused when present (only `global`
without the term is redone).
"""
from __future__ import annotations

import argparse
import json
import resource
import shutil
import time
from pathlib import Path

import numpy as np

STAGES = ["prepare", "detect", "object", "body", "contact", "global"]


def generate(session: Path) -> None:
    from intercap.synth.generator import SynthConfig, generate_session

    generate_session(SynthConfig(script="toss", cameras=4, width=320, height=288, fps=30.0, quiet=True), session)


def run(session: Path, out: Path, overrides: list[str]) -> float:
    from intercap.config import load_config
    from intercap.pipeline import run_pipeline

    tick = time.perf_counter()
    run_pipeline(session, out, load_config(None, overrides), stages=STAGES, progress=False)
    return time.perf_counter() - tick


def poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    data = np.load(path)
    return data["R"].astype(np.float64), data["t"].astype(np.float64)


def score(name: str, R, t, gt: dict, vertices: np.ndarray, episodes: np.ndarray, up: np.ndarray, fps: float) -> dict:
    from intercap.dynamics.flight import fit_flight
    from intercap.evaluation.metrics import adds_distances

    T = len(t)
    ok = np.isfinite(t).all(1) & np.isfinite(R).all((1, 2))
    adds = np.full(T, np.nan)
    adds[ok] = adds_distances(vertices, R[ok], t[ok], gt["R"][ok], gt["t"][ok])
    flight = np.zeros(T, bool)
    for a, b in gt["episodes"]:
        flight[a:b + 1] = True
    centre = vertices.mean(0)
    centres = np.where(ok[:, None], np.einsum("tij,j->ti", np.nan_to_num(R), centre) + t, np.nan)
    acc = (centres[2:] - 2 * centres[1:-1] + centres[:-2]) * fps**2  # (T-2, 3) at frames 1..T-2
    inner = flight[1:-1] & flight[2:] & flight[:-2]
    g_vec = gt["acceleration"]
    posed = np.einsum("tij,nj->tni", R, vertices) + t[:, None]  # NaN where untracked
    vacc = np.linalg.norm(posed[2:] - 2 * posed[1:-1] + posed[:-2], axis=-1).mean(1) * fps**2
    out = {"run": name, "adds_flight_mm": 1e3 * np.nanmean(adds[flight]), "adds_all_mm": 1e3 * np.nanmean(adds),
           "adds_flight_max_mm": 1e3 * np.nanmax(adds[flight]),
           "flight_acc_error_mps2": float(np.nanmean(np.linalg.norm(acc[inner] - g_vec, axis=-1))),
           "flight_vertex_acc_mps2": float(np.nanmean(vacc[inner]))}  # frames next to a lost one: NaN
    if len(episodes):
        fit = fit_flight(centres, episodes, fps, up)
        down_true = g_vec / np.linalg.norm(g_vec)
        a = fit["acceleration"][0]
        out.update(g_norm=float(fit["g_norm"][0]), g_angle_to_ground_deg=float(fit["gravity_angle_deg"][0]),
                   g_angle_to_truth_deg=float(np.degrees(np.arccos(np.clip(a @ down_true / np.linalg.norm(a), -1, 1)))))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.bench_flight", description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep", type=Path, default=Path("/tmp/bench_flight"), help="work folder (reused)")
    parser.add_argument("--set", action="append", default=[], help="extra config overrides for both runs")
    parser.add_argument("--score-only", action="store_true", help="score the results already in --keep")
    args = parser.parse_args(argv)
    from intercap.session import Session

    work = args.keep
    session_dir, on_dir, off_dir = work / "toss", work / "out_flight", work / "out_no_flight"
    timings = {}
    if not (session_dir / "ground_truth" / "physics.npz").exists():
        tick = time.perf_counter()
        generate(session_dir)
        timings["generate_s"] = time.perf_counter() - tick
    if not args.score_only:
        timings["pipeline_with_term_s"] = run(session_dir, on_dir, args.set)
        if off_dir.exists():
            shutil.rmtree(off_dir / "global", ignore_errors=True)
        else:
            shutil.copytree(on_dir, off_dir, ignore=shutil.ignore_patterns("global"))
        timings["global_without_term_s"] = run(session_dir, off_dir, args.set + ["global.w_flight=0"])

    session = Session.load(session_dir)
    fps = float(session.fps)
    truth = np.load(session_dir / "ground_truth" / "physics.npz")
    R_gt, t_gt = poses(session_dir / "ground_truth" / "object_poses.npz")
    gt = {"R": R_gt, "t": t_gt, "episodes": truth["flight_episodes"], "acceleration": truth["flight_acceleration"][0]}
    vertices = np.asarray(session.object.load_mesh().vertices, np.float64)
    metrics = json.loads((on_dir / "metrics.json").read_text())
    flight_figures = metrics.get("global", metrics).get("flight_episodes")
    episodes = np.asarray(flight_figures if flight_figures is not None else [], np.int64).reshape(-1, 2)
    ground = json.loads((on_dir / "prepare" / "ground.json").read_text())
    up = np.asarray(ground["normal"], np.float64)
    rows = [score("object (per-frame)", *poses(on_dir / "object" / "object_poses.npz"), gt, vertices, episodes, up, fps),
            score("global, w_flight=0", *poses(off_dir / "global" / "object_poses.npz"), gt, vertices, episodes, up, fps),
            score("global, flight term", *poses(on_dir / "global" / "object_poses.npz"), gt, vertices, episodes, up, fps)]
    T = session.num_frames
    print(f"toss: {T} frames at {fps:g} fps; true flight {gt['episodes'].tolist()}, detected {episodes.tolist()}")
    print(f"{'run':22s} {'ADD-S flight mm':>15s} {'max':>6s} {'ADD-S all mm':>12s} {'|a-g| m/s2':>10s} "
          f"{'vert acc':>8s} {'|g| m/s2':>8s} {'ang gnd':>7s} {'ang true':>8s}")
    for r in rows:
        print(f"{r['run']:22s} {r['adds_flight_mm']:15.2f} {r['adds_flight_max_mm']:6.1f} {r['adds_all_mm']:12.2f} "
              f"{r['flight_acc_error_mps2']:10.2f} {r['flight_vertex_acc_mps2']:8.2f} {r.get('g_norm', np.nan):8.2f} "
              f"{r.get('g_angle_to_ground_deg', np.nan):7.2f} {r.get('g_angle_to_truth_deg', np.nan):8.2f}")
    gain = 1 - rows[2]["adds_flight_mm"] / rows[1]["adds_flight_mm"]
    print(f"flight term: ADD-S in flight {100 * gain:.1f} % lower than without (target >= 20 %)")
    off_metrics = json.loads((off_dir / "metrics.json").read_text())
    seconds = {k: m.get("global", m).get("seconds_per_frame_fit") for k, m in (("with", metrics), ("without", off_metrics))}
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"global fit s/frame: with term {seconds['with']}, without {seconds['without']}; timings {timings}; "
          f"peak RSS {rss:.0f} MB")
    (work / "bench_flight.json").write_text(json.dumps({"rows": rows, "episodes_detected": episodes.tolist(),
                                                         "episodes_true": gt["episodes"].tolist(), "timings": timings,
                                                         "seconds_per_frame": seconds}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
