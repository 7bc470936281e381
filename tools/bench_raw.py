"""Benchmark of raw RGB-D input against given masks and keypoints, per object shape.

For each object a synthetic `table_lift` take is generated (the object rests on a table at the
start and the end, is lifted, carried through a turn and put back; a static stool stands nearby;
4 views, 320x288, 30 fps at natural speed by default) with masks and keypoints; its raw copy holds
the same colour and depth only (hard links), as `intercap import k4a` gives. The whole pipeline
runs on both (`intercap run`, default settings, in a child process each) and `intercap eval`
compares each with the ground truth. Printed per shape, given and raw side by side:

  * object ADD-S median (mm), frames a quarter turn or more off (rotation error modulo the mesh's
    symmetry > 45 deg), frames trusted;
  * body surface and MPJPE (mm), hands (mm), body vertex acceleration over the truth's (x),
    body-object penetration (mean over frames in contact, mm), contact accuracy (%);
  * calibration pairs flagged by the check (the rig is exact: any flag is a false alarm);
  * seconds per frame of the run (wall clock, model loading included).

    python -m tools.bench_raw [--objects carton,flat_box,tool,cup,ball] [--cameras 4]
                              [--width 320 --height 288] [--fps 30] [--frames N] [--camera-world]
                              [--keep DIR] [--md FILE] [--set SECTION.KEY=VALUE ...]

--keep DIR keeps the sessions and results there (sessions are reused, the pipeline redone); --md
writes the table as markdown too (BENCHMARKS.md).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OBJECTS = ("carton", "flat_box", "tool", "cup", "ball")
INPUT_FOLDERS = ("masks", "keypoints")  # what a raw capture lacks (cam*/masks/, cam*/keypoints/)


def generate(path: Path, synth: dict) -> None:
    """The session at `path`, generated in a child process unless it is there already."""
    if (path / "session.yaml").exists() and (path / "ground_truth").is_dir():
        return
    code = ("import json, sys; from intercap.synth.generator import SynthConfig, generate_session; "
            "generate_session(SynthConfig(**json.loads(sys.argv[1])), sys.argv[2])")
    subprocess.run([sys.executable, "-c", code, json.dumps(synth), str(path)], check=True)


def raw_copy(given: Path, raw: Path) -> None:
    """`given` without its masks and keypoints: colour, depth, calibration, session.yaml, the object
    and the ground truth, hard-linked where the file system allows."""
    if raw.exists():
        return
    shutil.copytree(given, raw, copy_function=os.link, ignore=lambda folder, names: [
        n for n in names if n in INPUT_FOLDERS and Path(folder).name.startswith("cam")])


def run_take(session: Path, out: Path, overrides: list[str]) -> float:
    """`intercap run` on one take into a fresh `out`; returns its wall-clock seconds."""
    shutil.rmtree(out, ignore_errors=True)
    command = [sys.executable, "-m", "intercap.cli", "run", str(session), "--out", str(out), "-q",
               "--set", "report.enabled=false"]
    for override in overrides:
        command += ["--set", override]
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def figures(session: Path, out: Path, seconds: float) -> dict:
    """The row of one take: accuracy against the ground truth, false calibration alarms, speed."""
    from intercap.evaluation.evaluate import evaluate

    result = evaluate(out, session)
    m, per_frame = result.metrics, result.per_frame
    rotation = per_frame.get("object_rotation_sym_deg", per_frame.get("object_rotation_deg", []))
    rotation = np.array([np.nan if v is None else v for v in rotation], float)
    metrics = json.loads((out / "metrics.json").read_text())
    frames = int(m.get("frames", 1))
    jitter, truth = m.get("jitter_mps2"), m.get("jitter_gt_mps2")
    return {
        "ADD-S mm": m.get("object_adds_mm_median", m.get("object_add_mm_median")),
        "turned": int(np.nansum(rotation > 45.0)),
        "trusted": f"{int(np.isfinite(rotation).sum())}/{frames}",
        "surface mm": m.get("body_surface_mm"), "MPJPE mm": m.get("keypoint_mpjpe_mm"),
        "hands mm": m.get("hand_keypoint_mm"),
        "accel x": jitter / truth if jitter is not None and truth else None,
        "pen. mm": m.get("penetration_mean_mm"), "contact %": m.get("contact_accuracy_pct"),
        "flagged": (metrics.get("prepare") or {}).get("calibration_pairs_flagged"),
        "s/frame": seconds / frames,
    }


def cell(value) -> str:
    if value is None:
        return "-"
    return f"{value:.1f}" if isinstance(value, float) else str(value)


def markdown(rows: list[tuple[str, str, dict]]) -> str:
    """The table (one row per shape and input) as markdown."""
    columns = list(rows[0][2])
    lines = ["| object | input | " + " | ".join(columns) + " |", "|---|---|" + "---:|" * len(columns)]
    lines += [f"| {name} | {kind} | " + " | ".join(cell(row[c]) for c in columns) + " |" for name, kind, row in rows]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", default=",".join(OBJECTS), help="comma-separated object names")
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=288)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--frames", type=int, default=None, help="default: the script at natural speed")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--camera-world", action="store_true", help="a camera as the world frame")
    parser.add_argument("--inputs", default="given,raw", choices=("given", "raw", "given,raw", "raw,given"),
                        help="given, raw, or both as given,raw")
    parser.add_argument("--keep", type=Path, default=None)
    parser.add_argument("--md", type=Path, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = parser.parse_args(argv)
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench_raw_"))
    rows = []
    for name in args.objects.split(","):
        synth = dict(script="table_lift", object=name, cameras=args.cameras, width=args.width, height=args.height,
                     fps=args.fps, frames=args.frames, seed=args.seed, camera_world=args.camera_world, quiet=True)
        tag = f"{name}_{args.cameras}v_{args.width}x{args.height}_{args.fps:g}fps" + ("_camworld" if args.camera_world
                                                                                       else "")
        given = root / f"{tag}_given"
        generate(given, synth)
        raw_copy(given, root / f"{tag}_raw")
        for kind in args.inputs.split(","):
            session = root / f"{tag}_{kind}"
            seconds = run_take(session, root / f"{tag}_{kind}_out", args.set)
            rows.append((name, kind, figures(session, root / f"{tag}_{kind}_out", seconds)))
            print(markdown(rows[-1:]).splitlines()[-1], flush=True)
    table = markdown(rows)
    print(f"\n{args.cameras} views, {args.width}x{args.height}, {args.fps:g} fps, table_lift, seed {args.seed}"
          + (", a camera as the world" if args.camera_world else "") + f" (sessions and results in {root})\n")
    print(table)
    if args.md:
        args.md.write_text(table + "\n")
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
