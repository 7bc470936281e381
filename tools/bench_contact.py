"""Benchmark of the `contact` stage's detectors against ground_truth/contact.npy.

For each synthetic session with per-frame results (the `object` and `body`
stages' own files in RESULTS/object/, RESULTS/body/), the sources are computed
once and then thresholded:
  * 3D: per frame the distance of each hand's contact region to the object's
    surface, contact below T_d (swept), optionally cleaned in time;
  * 2D: person / object mask overlap per view (session masks, and the per-frame
    fits rendered), contact with more than T_view pixels in more than T_frame
    views (swept, with two dilations);
and scored: accuracy / precision / recall (%) per session and over all frames,
seconds per frame of each source (wall and process CPU time).

    python -m tools.bench_contact [SESSION:RESULTS ...] [--generate pick4,drink4 --frames 30 --fps 10 --keep DIR]

Without arguments: the 10 fps sessions in /tmp/gb (pick4, drink4). `--generate`
writes small sessions with tools.synth and runs the prepare, object and body
stages on them first (minutes per session). Results folders are only read: the
per-frame files are copied into a scratch folder before the stage runs there.
"""
from __future__ import annotations

import argparse
import logging
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DEFAULT_PAIRS = ["/tmp/gb/pick4:/tmp/gb/out_pick4", "/tmp/gb/drink4:/tmp/gb/out_drink4"]
# name: (script, phenotype) of sessions --generate can write
GENERATE = {
    "pick4": ("pick_place", "0.5,0.5,0.5,0.5,0.5,0.5"),
    "drink4": ("lift_drink", "0.1,0.3,0.4,0.7,0.3,0.6"),
}
DISTANCES_MM = (5, 10, 20, 30, 50, 80)
CLEANS = (0, 2, 3)
OVERLAPS_PX = (5, 10, 20, 50, 100, 200, 400, 800)  # at 640 px width
DILATIONS_PX = (1, 3)


def scratch_results(results: Path, scratch: Path) -> Path:
    """A copy of the per-frame files the contact stage reads (never writes into `results`)."""
    for stage, name in (("body", "body_vertices.npy"), ("body", "body_faces.npy"), ("object", "object_poses.npz")):
        src = results / stage / name
        if not src.exists() and not (results / "global" / "DONE.json").exists():
            src = results / name  # folders written before stages kept their own copies
        if not src.exists():
            raise SystemExit(f"{results}: no per-frame `{stage}` result {name}; run the {stage} stage first")
        (scratch / stage).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, scratch / stage / name)
    return scratch


def generate(names: list[str], frames: int, fps: float, keep: Path) -> list[str]:
    """Write sessions with tools.synth and run the per-frame stages on them; SESSION:RESULTS pairs."""
    from intercap.config import load_config
    from intercap.pipeline import run_pipeline

    pairs = []
    for name in names:
        script, phenotype = GENERATE[name]
        session, results = keep / f"{name}_session", keep / f"{name}_results"
        if not (session / "session.yaml").exists():
            subprocess.run([sys.executable, "-m", "tools.synth", str(session), "--script", script, "--frames",
                            str(frames), "--fps", str(fps), "--phenotype", phenotype, "--cameras", "4", "--quiet"],
                           check=True)
        run_pipeline(session, results, load_config(), stages=["prepare", "object", "body"], progress=False)
        pairs.append(f"{session}:{results}")
    return pairs


def timed(fn, *args, **kwargs):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - wall, time.process_time() - cpu


def measure(session_dir: Path, results: Path, scratch: Path) -> dict:
    """Every source's raw signal on one session, with timings."""
    from intercap.config import load_config
    from intercap.session import Session
    from intercap.stages.contact import stage as contact

    session = Session.load(session_dir)
    gt = session.ground_truth()
    if gt is None or gt.contact is None:
        raise SystemExit(f"{session_dir}: no ground_truth/contact.npy")
    out = scratch_results(results, scratch)
    cfg = load_config()
    regions, _ = contact.body_regions(cfg.body_model)
    per_frame = contact.load_per_frame(out, session)
    mesh = session.object.load_mesh()
    hands = [regions["left_hand"], regions["right_hand"]]
    distance, w3, c3 = timed(contact.region_distances, per_frame.vertices, hands, per_frame.R, per_frame.t,
                             mesh.vertices, mesh.faces)
    row = {"name": session_dir.name, "T": session.num_frames, "gt": gt.contact, "distance": distance,
           "judged3d": per_frame.body_valid & per_frame.object_valid, "fps": session.fps,
           "seconds": {"3d": (w3, c3)}, "thresholds": contact.overlap_thresholds(session, cfg.contact) / cfg.contact.overlap_px,
           "counts": {}}
    for source in ("session", "rendered"):
        for dilate in DILATIONS_PX:
            ccfg = load_config(overrides=[f"contact.dilate_px={dilate}",
                                          f"contact.use_session_masks={'true' if source == 'session' else 'false'}"]).contact
            (counts, used, judged), w2, c2 = timed(contact.overlap_counts, session, ccfg, per_frame, mesh, progress=False)
            if used != source:
                continue  # the session has no masks
            row["counts"][(source, dilate)] = (counts, judged)
            row["seconds"][f"2d {source} d{dilate}"] = (w2, c2)
    # the whole stage with its defaults, as `intercap run --stages contact` runs it
    figures, ws, cs = timed(contact.run, session, cfg, out, progress=False)
    row["seconds"]["stage (default)"] = (ws, cs)
    row["stage"] = np.load(out / "contact.npy")
    row["stage_method"] = figures["method"]
    return row


def score(pred: np.ndarray, gt: np.ndarray) -> tuple:
    from intercap.evaluation.metrics import contact_scores

    return contact_scores(pred, gt)


def fmt(x) -> str:
    return "-" if x is None else f"{x:.1f}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("pairs", nargs="*", help="SESSION:RESULTS (default: the /tmp/gb sessions)")
    parser.add_argument("--generate", default="", help=f"comma list of {', '.join(GENERATE)}: write and fit these first")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--fps", type=float, default=10.0)
    parser.add_argument("--keep", type=Path, default=None, help="folder for generated sessions (default: temporary)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from intercap.stages.contact.stage import clean_labels, distance_labels, overlap_labels

    tmp = Path(tempfile.mkdtemp(prefix="bench_contact_"))
    pairs = list(args.pairs)
    if args.generate:
        pairs += generate([n for n in args.generate.split(",") if n], args.frames, args.fps, args.keep or tmp)
    pairs = pairs or DEFAULT_PAIRS
    rows = []
    for k, pair in enumerate(pairs):
        session_dir, results = (Path(p) for p in pair.split(":"))
        rows.append(measure(session_dir, results, tmp / f"scratch{k}"))
        print(f"measured {session_dir} ({rows[-1]['T']} frames, {rows[-1]['fps']:g} fps)", flush=True)

    # label sets: name -> per-session predictions
    variants: dict[str, list[np.ndarray]] = {}
    for d in DISTANCES_MM:
        for n in CLEANS:
            variants[f"3d T_d={d}mm clean={n}"] = [
                clean_labels(distance_labels(r["distance"], [0, 1], d / 1000) & r["judged3d"], n) for r in rows]
    keys = sorted({key for r in rows for key in r["counts"]})
    most_views = max(r["counts"][key][0].shape[1] for r in rows for key in r["counts"]) if keys else 0
    for source, dilate in keys:
        for px in OVERLAPS_PX:
            for views in range(most_views):
                name = f"2d {source} dilate={dilate} T_view={px}px T_frame={views}"
                preds = []
                for r in rows:
                    if (source, dilate) not in r["counts"]:
                        break
                    counts, judged = r["counts"][(source, dilate)]
                    preds.append(overlap_labels(counts, r["thresholds"] * px, views) & judged)
                else:
                    variants[name] = preds
    variants["stage default (" + "/".join(sorted({r["stage_method"] for r in rows})) + ")"] = [r["stage"] for r in rows]

    gts = [r["gt"] for r in rows]
    table = []
    for name, preds in variants.items():
        per = [score(p, g) for p, g in zip(preds, gts)]
        overall = score(np.concatenate(preds), np.concatenate(gts))
        table.append((name, per, overall))
    names = [r["name"] for r in rows]
    header = "| source / thresholds | " + " | ".join(f"{n} acc / prec / rec" for n in names) + " | all acc / prec / rec |"

    def line(name, per, overall):
        cells = [f"{fmt(a)} / {fmt(p)} / {fmt(c)}" for a, p, c in per]
        print(f"| {name} | " + " | ".join(cells) + f" | {fmt(overall[0])} / {fmt(overall[1])} / {fmt(overall[2])} |")

    best = {}
    for name, per, overall in table:
        family = name.split(" T_")[0].split(" dilate")[0] if name.startswith("2d") else name[:2]
        if name.startswith("stage"):
            family = "stage"
        if family not in best or (overall[0] or 0) > (best[family][2][0] or 0):
            best[family] = (name, per, overall)
    print("\nbest of each source (by overall accuracy):")
    print(header)
    print("|" + "---|" * (len(names) + 2))
    for name, per, overall in best.values():
        line(name, per, overall)
    print("\nfull sweep:")
    print(header)
    print("|" + "---|" * (len(names) + 2))
    for name, per, overall in table:
        line(name, per, overall)
    print("\nseconds per frame (wall / process CPU; shared 2-core machine):")
    for r in rows:
        print(f"  {r['name']}: " + ", ".join(f"{k} {w / r['T']:.4f} / {c / r['T']:.4f}" for k, (w, c) in r["seconds"].items()))
    print("GT frames in contact: " + ", ".join(f"{r['name']} {int(r['gt'].sum())}/{r['T']}" for r in rows))
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
