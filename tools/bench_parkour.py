"""Benchmark of the `physics` stage against measured forces: the LAAS Parkour dataset.

    OMP_NUM_THREADS=1 python -m tools.bench_parkour DATA_DIR [--clips kv01_PKFC,...] [--mass-kg 74.6]

DATA_DIR is a local clone of github.com/zongmianli/Parkour-dataset (or its gt_motion_forces/);
nothing is downloaded. Per clip: anny fitted to the 16 mocap joints (tools/parkour_fit.fit_anny: an
IK fit of every frame at once with an acceleration term and one shape per clip), then the physics
stage on that motion (floor at z = 0, hands gripping a fixed structure) with the contact timing
taken two ways:

* `sensors`: each contact on where its force sensor reads over 20 N (the measured timing);
* `motion`: our own detection from the fitted motion alone (parkour_fit.motion_contacts): a foot
  carries where it is low and slow, or still while the hip moves over it (a step on the obstacle,
  pushing up through its lowest sole points), a hand grips where it is still and off the floor.

It prints, per action and overall, the dataset's errors (its evaluator's definitions, reimplemented
in parkour_fit.force_errors): mean linear force error (N) and moment error (N m) at the left / right
sole (moments about the ankle) and hand (about the fingers joint), beside Li et al.'s published
figures. The dataset's hand moments are the bar sensor's about its own origin, not about the hand,
so no estimate's hand moment is comparable to them (Li et al.'s own are 131 / 134 N m).

Data: the LAAS Parkour dataset (Li, Sedlar, Carpentier, Laptev, Mansard, Sivic, "Estimating 3D
Motion and Forces of Person-Object Interactions from Monocular Video", CVPR 2019; built on the LAAS
Parkour MoCap database of Maldonado et al., 2017). Please cite them when using these figures.
"""
from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from tools import parkour_fit as pk

CREDIT = ("Data: LAAS Parkour dataset (Li et al., CVPR 2019; LAAS Parkour MoCap database, Maldonado et al. 2017), "
          "github.com/zongmianli/Parkour-dataset")
# Li et al. 2019's mean errors over the dataset (left sole, right sole, left hand, right hand), from the
# CVPR paper's Parkour table as quoted in a public scoring script (the paper's PDF is not reachable from
# this machine): forces estimated from the video with their own estimated motion, a 74.6 kg body.
LI_FORCE_N = (144.23, 138.21, 107.91, 113.42)
LI_MOMENT_NM = (23.71, 22.32, 131.13, 134.21)
SENSOR_ON_N = 20.0
COLUMNS = ("l_sole", "r_sole", "l_hand", "r_hand")


def clip_session(clip: pk.Clip, root: Path, mass_kg: float | None) -> SimpleNamespace:
    """What the physics stage reads of a session, for a clip without images: its frames, rate, the
    floor (z = 0, z up), no object, no support mesh; body.mass_kg when given."""
    root.mkdir(parents=True, exist_ok=True)
    if mass_kg is not None:
        (root / "session.yaml").write_text(f"body: {{mass_kg: {mass_kg}}}\n")
    T = clip.num_frames
    return SimpleNamespace(root=root, fps=clip.fps, num_frames=T, frame_ids=np.arange(T), object=None, supports=[],
                           ground=(np.zeros(3), np.array([0.0, 0.0, 1.0])), body_model="anny")


def write_fit(params, out: Path) -> None:
    """OUT/body_params.npz of a fit, as the global stage writes it."""
    out.mkdir(parents=True, exist_ok=True)
    arrays = params.to_numpy_dict()
    np.savez(out / "body_params.npz", model=np.array("anny"), valid=np.ones(len(arrays["transl"]), bool),
             **{k: v.astype(np.float32) for k, v in arrays.items()})


def predicted_wrenches(z, fitted16: np.ndarray) -> np.ndarray:
    """(T, 4, 6) the environment's wrench on the left / right foot (about our ankle) and hand (about our
    fingers joint), world axes, from the stage's physics.npz."""
    T = len(fitted16)
    out = np.zeros((T, 4, 6))
    f = np.nan_to_num(z["foot_point_force"])  # (T, 2, P, 3) by the floor on each sole point
    for side, ankle in enumerate((2, 6)):
        out[:, side, :3] = f[:, side].sum(1)
        out[:, side, 3:] = np.cross(z["foot_points"][:, side] - fitted16[:, ankle, None], f[:, side]).sum(1)
    hand_f, hand_t = np.nan_to_num(z["hand_force"]), np.nan_to_num(z["hand_torque"])  # by the hand on the structure
    for side, fingers in enumerate((11, 15)):
        out[:, 2 + side, :3] = -hand_f[:, side]
        out[:, 2 + side, 3:] = -hand_t[:, side] + np.cross(z["hand_point"][:, side] - fitted16[:, fingers], -hand_f[:, side])
    return out


def timing(clip: pk.Clip, fitted16: np.ndarray, how: str) -> dict:
    """The contact timing the stage is given: measured (`sensors`) or detected from the fitted motion
    (`motion`, parkour_fit.motion_contacts)."""
    if how == "sensors":
        on = pk.sensor_contacts(clip, SENSOR_ON_N)
        return {"feet": on[:, :2], "grip": on[:, 2:]}
    on = pk.motion_contacts(fitted16, clip.fps)
    return {"feet": on[:, :2], "grip": on[:, 2:]}


def bench_clip(clip: pk.Clip, model, scratch: Path, mass_kg: float | None, cfg) -> dict:
    """Fit, then the physics stage under both timings; the dataset's errors of each."""
    from intercap.stages.physics import stage as physics

    params, fitted16, info = pk.fit_anny(clip.joints, clip.fps, model=model)
    out = scratch / clip.name
    write_fit(params, out)
    session = clip_session(clip, scratch / f"{clip.name}_session", mass_kg)
    row = {"clip": clip.name, "action": clip.action, "frames": clip.num_frames, "fit_mpjpe_mm": info["mpjpe_mm"],
           "fit_s_per_frame": info["seconds_per_frame"]}
    for how in ("sensors", "motion"):
        tick = time.perf_counter()
        figures = physics.analyse(out, session, cfg, contact_timing=timing(clip, fitted16, how))
        with np.load(out / "physics" / "physics.npz") as z:
            errors = pk.force_errors(predicted_wrenches(z, fitted16), clip)
            row["body_mass_kg"] = float(z["body_mass_kg"])
        row[how] = {"linear_n": errors["linear_n"].tolist(), "moment_nm": errors["moment_nm"].tolist(),
                    "residual_pct_bw": figures.get("residual_root_force_pct_bw_mean"),
                    "physics_s_per_frame": (time.perf_counter() - tick) / clip.num_frames}
    return row


def action_table(rows: list[dict], how: str) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(action, mean linear errors (4,), mean moment errors (4,)) per action and over all clips: the
    clips' means averaged (a channel a clip never captured is left out of that channel's mean)."""
    out = []
    for action in [*dict.fromkeys(r["action"] for r in rows), "all"]:
        chosen = [r for r in rows if action in ("all", r["action"])]
        lin = np.nanmean([r[how]["linear_n"] for r in chosen], axis=0)
        mom = np.nanmean([r[how]["moment_nm"] for r in chosen], axis=0)
        out.append((action, lin, mom))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data_dir", help="a local clone of the Parkour dataset (or its gt_motion_forces/)")
    ap.add_argument("--clips", default="", help="comma-separated clip names (default: all 28)")
    ap.add_argument("--mass-kg", type=float, default=None,
                    help="body mass for every clip (Li et al. use 74.6); default: the fitted rest mesh's volume")
    ap.add_argument("--scratch", default=None, help="where fits and physics outputs go (default: a temp dir)")
    ap.add_argument("--json", default=None, help="also write the per-clip rows here")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="configuration override")
    args = ap.parse_args(argv)
    from intercap.config import load_config

    cfg = load_config(None, args.set)
    clips = pk.load_clips(args.data_dir)
    if args.clips:
        unknown = sorted(set(args.clips.split(",")) - set(clips))
        if unknown:
            raise SystemExit(f"unknown clip(s) {', '.join(unknown)}; the dataset has {', '.join(sorted(clips))}")
        clips = {k: clips[k] for k in args.clips.split(",")}
    scratch = Path(args.scratch or tempfile.mkdtemp(prefix="bench_parkour_"))
    model = pk.default_model()
    rows = []
    start = time.perf_counter()
    for k, clip in enumerate(clips.values()):
        row = bench_clip(clip, model, scratch, args.mass_kg, cfg)
        rows.append(row)
        s, m = row["sensors"], row["motion"]
        print(f"[{k + 1}/{len(clips)}] {clip.name}: {clip.num_frames} frames, fit {row['fit_mpjpe_mm']:.1f} mm, "
              f"mass {row['body_mass_kg']:.1f} kg; sensor timing force {np.round(s['linear_n'], 0).tolist()} N, "
              f"motion timing {np.round(m['linear_n'], 0).tolist()} N", flush=True)
    elapsed = time.perf_counter() - start
    frames = sum(r["frames"] for r in rows)
    print(f"\n{CREDIT}")
    print("mean linear force error (N) | moment error (N m), per contact: left sole, right sole, left hand, right hand")
    for how, label in (("sensors", "contact timing from the force sensors (> 20 N)"),
                       ("motion", "contact timing detected from the motion (ours)")):
        print(f"  {label}:")
        for action, lin, mom in action_table(rows, how):
            print(f"    {action:13s} force {'  '.join(f'{v:7.1f}' for v in lin)}   moment "
                  f"{'  '.join(f'{v:6.1f}' for v in mom)}")
    print(f"  Li et al. 2019 (video, all) force {'  '.join(f'{v:7.1f}' for v in LI_FORCE_N)}   moment "
          f"{'  '.join(f'{v:6.1f}' for v in LI_MOMENT_NM)}")
    print("  (hand moments: the dataset's are about the bar sensor's origin, not comparable)")
    print(f"fit MPJPE {np.mean([r['fit_mpjpe_mm'] for r in rows]):.1f} mm (mean over clips); "
          f"{elapsed / max(frames, 1):.3f} s/frame in all ({frames} frames), "
          f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
