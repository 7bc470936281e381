"""Benchmark of the `physics` stage.

    OMP_NUM_THREADS=1 python -m tools.bench_physics [--frames 90] [--skip-filters]

1. Filter choice (intercap.dynamics.kinematics): acceleration error (m/s^2, RMS over all frames and
   over the interior) of each filter on noisy synthetic trajectories: 2 mm white noise at 30 fps on
   human-like motions (sums of 0.3-3 Hz sinusoids of a few cm, a free-flight parabola, a still point).
2. Static hold with Kinect-like noise (intercap.synth.physics_cases): hand force sum vs m g and
   ground reaction vs (M + m) g (%, mean and worst frame), residual root force (% body weight),
   stage speed (s/frame without and with the body model's construction), peak RSS.
3. `--gt-motion DIR`: the stage on the ground-truth motion of every generator script (tiny one-camera
   sessions generated into DIR once, 30 fps): residual root force (% body weight) per script.
4. `--supports DIR`: fixed supports (session.yaml `supports`) on ground-truth motion: the seat's share of
   the body weight in a seated take, the table's share of a resting box's weight.
5. Toss / hold / drop sessions of the synthetic generator, when given (`--results OUT...`: results
   folders of `intercap run` on those sessions): their physics figures from metrics.json.
"""
from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from intercap.body_models import shared_model
from intercap.dynamics import kinematics as kin

G = 9.81


def test_trajectories(rng, fps: float, T: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, positions (T, 3), true accelerations (T, 3)) of a few motion kinds."""
    t = np.arange(T) / fps
    out = []
    for k in range(6):  # human-like: sums of sinusoids, acceleration up to ~2 m/s^2 each (trunk: slow, limbs: faster)
        x, a = np.zeros((T, 3)), np.zeros((T, 3))
        top = 1.5 if k < 3 else 3.0
        for _ in range(4):
            f = rng.uniform(0.2, top)
            amp = np.minimum(rng.uniform(0.01, 0.05, 3) / f**2, 0.15)
            ph = rng.uniform(0, 2 * np.pi, 3)
            w = 2 * np.pi * f
            x += amp * np.sin(w * t[:, None] + ph)
            a += -amp * w**2 * np.sin(w * t[:, None] + ph)
        out.append((("trunk" if k < 3 else "limb") + str(k), x, a))
    g = np.array([0, 0, -G])
    out.append(("flight", np.outer(t, [0.5, 0.1, 3.5]) + 0.5 * np.outer(t**2, g), np.tile(g, (T, 1))))
    out.append(("still", np.zeros((T, 3)), np.zeros((T, 3))))
    return out


def bench_filters(fps: float = 30.0, T: int = 90, noise_m: float = 0.002, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    cases = test_trajectories(rng, fps, T)
    candidates = [("none", {}), ("adaptive", {"order": 3}), ("adaptive", {"order": 2})]
    candidates += [("butterworth", {"cutoff_hz": c}) for c in (3.0, 6.0, 10.0)]
    candidates += [("savgol", {"window_s": w, "order": o}) for w in (0.3, 0.5, 0.7, 1.0) for o in (2, 3, 4, 5)]
    rows = []
    for method, kw in candidates:
        errs, inner, kinds = [], [], {}
        for _ in range(5):
            for name, x, a in cases:
                noisy = x + rng.normal(0, noise_m, x.shape)
                _, _, est = kin.derivatives(noisy, fps, method, **kw)
                e = np.linalg.norm(est - a, axis=1)
                errs.append(e)
                inner.append(e[10:-10])
                kinds.setdefault(name.rstrip("0123456789"), []).append(e)
        rows.append({"filter": method, **kw, "acc_rms_all": float(np.sqrt(np.mean(np.concatenate(errs) ** 2))),
                     "acc_rms_interior": float(np.sqrt(np.mean(np.concatenate(inner) ** 2))),
                     **{f"rms_{k}": float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in kinds.items()}})
    return rows


def bench_static_hold(frames: int, noise_m: float = 0.002, noise_rad: float = 0.002) -> dict:
    from intercap.config import Config
    from intercap.session import Session
    from intercap.stages.physics import stage as physics
    from intercap.synth.physics_cases import write_static_hold, write_tiny_camera_session

    tick = time.perf_counter()
    model = shared_model(Config().body_model)
    build = time.perf_counter() - tick
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        m = 2.0
        session = write_tiny_camera_session(root / "session", frames, object_mass_kg=m)
        write_static_hold(model, root / "out", frames, noise_m=noise_m, noise_rad=noise_rad)
        tick = time.perf_counter()
        figures = physics.analyse(root / "out", Session.load(session))
        seconds = time.perf_counter() - tick
        z = np.load(root / "out" / "physics" / "physics.npz")
        M = float(z["body_mass_kg"])
        hands = np.linalg.norm(z["hand_force"].sum(1) - [0, 0, m * G], axis=1) / (m * G) * 100
        ground = np.linalg.norm(z["foot_force"].sum(1) - [0, 0, (M + m) * G], axis=1) / ((M + m) * G) * 100
        out = {"frames": frames, "noise_mm": noise_m * 1000, "body_mass_kg": M,
               "hand_force_err_pct_mean": float(hands.mean()), "hand_force_err_pct_max": float(hands.max()),
               "ground_reaction_err_pct_mean": float(ground.mean()), "ground_reaction_err_pct_max": float(ground.max()),
               "residual_root_force_pct_bw_mean": figures["residual_root_force_pct_bw_mean"],
               "residual_root_force_pct_bw_p95": figures["residual_root_force_pct_bw_p95"],
               "friction_cone_violation_pct": figures["friction_cone_violation_pct"],
               "foot_skating_mm_s": figures["foot_skating_mm_s"],
               "stage_s_per_frame": seconds / frames, "stage_s_per_frame_with_model_build": (seconds + build) / frames}
    return out


def truth_as_results(session: Path, out: Path, hands) -> Path:
    """A results folder `out` holding a session's ground-truth motion as if fitted: body_params,
    object_poses, contact labels per hand (`hands` of the script on its contact frames), the floor."""
    import shutil

    out.mkdir(parents=True, exist_ok=True)
    gt = session / "ground_truth"
    for name in ("object_poses.npz", "contact.npy"):
        if (gt / name).exists():
            shutil.copy(gt / name, out / name)
    with np.load(gt / "body_params.npz") as z:
        params = {k: z[k] for k in z.files if k != "valid"}
    T = len(params["transl"])
    np.savez(out / "body_params.npz", valid=np.ones(T, bool), **params)
    (out / "prepare").mkdir(exist_ok=True)
    shutil.copy(gt / "ground.json", out / "prepare" / "ground.json")
    contact = np.load(gt / "contact.npy").astype(bool) if (gt / "contact.npy").exists() else np.zeros(T, bool)
    names = ["left_hand", "right_hand"]
    rc = np.stack([contact & any(h.lower().startswith(s) for h in hands) for s in ("l", "r")], 1)
    (out / "contact").mkdir(exist_ok=True)
    np.savez(out / "contact" / "contact.npz", contact=contact, region_names=np.array(names), region_contact=rc)
    return out


def gt_motion_results(script: str, root: Path, fps: float = 30.0, ik_iters: int = 30,
                      annotate: bool = False) -> tuple[Path, Path]:
    """A tiny session of a generator script (one 64x48 camera: the motion is what matters) and a
    results folder holding its ground-truth motion as if fitted (`truth_as_results`); `annotate`:
    the session's annotations too (its furniture as session.yaml `supports`)."""
    from intercap.synth.generator import SynthConfig, generate_session
    from intercap.synth.motions import get_script

    session = root / script
    if not (session / "ground_truth" / "body_params.npz").exists():
        cfg = SynthConfig(script=script, fps=fps, cameras=1, width=64, height=48, keypoints=False, masks=False,
                          walls=False, ik_iters=ik_iters, quiet=True, annotate=annotate)
        generate_session(cfg, session)
    return session, truth_as_results(session, root / f"{script}_out", get_script(script).hands)


def fitted_against_truth(session: Path, fitted: Path, scratch: Path, cfg=None) -> dict:
    """The physics stage on a fitted results folder and on the same session's ground-truth motion.

    Held frames: the truth has the object in contact with the body and the floor carries none of it.
    There the hands together should carry m (a - g), a the true object's acceleration (what the
    truth's hands, floor and residual explain together). The hand-contact agreement is the share of
    the fitted contact stage's contact frames in which the floor carries none of the fitted object
    whose hands carry at least a tenth of the object's weight. Frames the fitted results' physics could
    not solve (no object pose there: a contact frame held through untrusted ones) count in neither,
    and are counted (`contact_frames_unsolved`)."""
    from intercap.session import Session
    from intercap.stages.physics import stage as physics
    from intercap.synth.motions import get_script

    s = Session.load(session)
    info = json.loads((session / "ground_truth" / "info.json").read_text())
    truth = truth_as_results(session, scratch / f"{session.name}_truth", get_script(info["script"]).hands)
    figures, hands, floor = {}, {}, {}
    for name, folder in (("truth", truth), ("fitted", fitted)):
        figures[name] = physics.analyse(folder, s, cfg)
        with np.load(folder / "physics" / "physics.npz") as z:
            hands[name] = np.nansum(z["hand_force"], 1)
            floor[name] = np.nan_to_num(z["object_ground_force"])
            solved = z["valid"].astype(bool) & np.isfinite(z["hand_force"]).all((1, 2))  # last: the fitted's
            if name == "truth":
                need = hands[name] + floor[name] + z["object_residual_force"]
                weight = float(z["object_mass_kg"]) * float(np.linalg.norm(z["gravity"]))
    on_floor = {name: np.linalg.norm(f, axis=-1) > 1e-6 for name, f in floor.items()}
    held = np.load(truth / "contact.npy").astype(bool) & ~on_floor["truth"] & solved
    scale = np.maximum(np.linalg.norm(need, axis=-1), 1e-9)
    carried = np.linalg.norm(hands["fitted"], axis=-1) / scale
    error = np.linalg.norm(hands["fitted"] - need, axis=-1) / scale
    in_contact = np.load(fitted / "contact.npy").astype(bool)
    off_floor = in_contact & ~on_floor["fitted"] & solved
    has_wrench = np.linalg.norm(hands["fitted"], axis=-1) >= 0.1 * weight
    return {
        "frames": int(len(held)), "held_frames": int(held.sum()),
        "hands_carry_median": float(np.median(carried[held])) if held.any() else float("nan"),
        "hands_error_median": float(np.median(error[held])) if held.any() else float("nan"),
        "contact_with_hand_wrench_pct": float(100 * has_wrench[off_floor].mean()) if off_floor.any() else float("nan"),
        "contact_frames_unsolved": int((in_contact & ~solved).sum()),
        **{f"{k}_{name}": figures[name].get(k) for name in ("truth", "fitted")
           for k in ("residual_root_force_pct_bw_mean", "residual_root_force_pct_bw_p95", "foot_skating_mm_s",
                     "friction_cone_violation_pct")},
    }


def bench_supports(root: Path, fps: float = 15.0, cfg=None) -> dict:
    """Fixed supports on ground-truth motion (tiny sessions with the furniture given as session.yaml
    `supports`): `sit_stand`, the seat's and the feet's share of the body weight while seated and the
    seat's while standing; `table_lift`, the table's share of the box's weight while it rests on the
    table untouched, and the box's unexplained force there (its weight's %)."""
    from intercap.session import Session
    from intercap.stages.physics import stage as physics

    out = {}
    for script in ("sit_stand", "table_lift"):
        session, results = gt_motion_results(script, root / "supports", fps, annotate=True)
        tick = time.perf_counter()
        figures = physics.analyse(results, Session.load(session), cfg)
        seconds = (time.perf_counter() - tick) / max(figures["frames_valid"], 1)
        with np.load(results / "physics" / "physics.npz") as z:
            body_weight, object_weight = float(z["body_mass_kg"]) * G, float(z["object_mass_kg"]) * G
            seat, feet = z["support_force"].sum(1)[:, 2], z["foot_force"].sum(1)[:, 2]
            object_support, object_residual = z["object_ground_force"][:, 2], z["object_residual_force"]
        if script == "sit_stand":
            phases = json.loads((session / "ground_truth" / "info.json").read_text())["phases"]
            seated = np.arange(phases["seated"][0], phases["seated"][1] + 1)
            standing = np.r_[np.arange(phases["stand"][0], phases["stand"][1] + 1),
                             np.arange(phases["stand_again"][0], phases["stand_again"][1] + 1)]
            out[script] = {"seated_frames": len(seated), "seat_share_median": float(np.median(seat[seated]) / body_weight),
                           "seat_share_min": float(seat[seated].min() / body_weight),
                           "feet_share_median": float(np.median(feet[seated]) / body_weight),
                           "seat_share_standing_max": float(seat[standing].max() / body_weight)}
        else:
            contact = np.load(session / "ground_truth" / "contact.npy").astype(bool)
            position = np.load(session / "ground_truth" / "object_poses.npz")["t"]
            still = np.linalg.norm(np.gradient(position, axis=0), axis=1) < 1e-3
            resting = ~contact & (position[:, 2] > 0.3) & still
            out[script] = {"resting_frames": int(resting.sum()),
                           "table_share_median": float(np.median(object_support[resting]) / object_weight),
                           "object_residual_pct_max": float(100 * np.linalg.norm(object_residual[resting], axis=1).max()
                                                            / object_weight)}
        out[script].update(residual_root_force_pct_bw_mean=figures["residual_root_force_pct_bw_mean"], s_per_frame=seconds)
    return out


SCRIPTS = ("pick_place", "lift_drink", "push_chair", "toss", "hold", "drop")


def bench_gt_motion(root: Path, scripts=SCRIPTS, fps: float = 30.0, cfg=None) -> list[dict]:
    """The physics stage on each script's ground-truth motion: residual root force (% body weight)."""
    from intercap.session import Session
    from intercap.stages.physics import stage as physics

    rows = []
    for script in scripts:
        session, out = gt_motion_results(script, root, fps)
        tick = time.perf_counter()
        f = physics.analyse(out, Session.load(session), cfg)
        rows.append({"script": script, "frames": int(f["frames_valid"]),
                     **{k: f.get(k) for k in ("residual_root_force_pct_bw_mean", "residual_root_force_pct_bw_p95",
                                              "friction_cone_violation_pct", "foot_skating_mm_s",
                                              "ground_penetration_mm_max", "flight_episodes")},
                     "s_per_frame": (time.perf_counter() - tick) / max(f["frames_valid"], 1)})
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--skip-filters", action="store_true")
    ap.add_argument("--results", nargs="*", default=[], help="results folders of toss/hold/drop runs")
    ap.add_argument("--gt-motion", metavar="DIR", help="run the stage on the ground-truth motion of every generator "
                    "script (sessions generated into DIR once, at --fps) and print the residual table")
    ap.add_argument("--fitted", nargs=2, action="append", metavar=("SESSION", "OUT"), default=[],
                    help="the stage on a fitted results folder OUT of a generated SESSION and on its ground-truth "
                    "motion (repeatable); scratch folders go to --scratch")
    ap.add_argument("--scratch", default=None, help="where --fitted writes the truth's results (default: a temp dir)")
    ap.add_argument("--supports", metavar="DIR", help="fixed supports on ground-truth motion: a seated take and a box "
                    "resting on a table (sessions generated into DIR once, at --fps, default 15 here)")
    ap.add_argument("--scripts", default=",".join(SCRIPTS))
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a configuration override for the stage (e.g. physics.torque_weight=0), repeatable")
    args = ap.parse_args(argv)
    from intercap.config import load_config

    cfg = load_config(None, args.set)
    if args.fitted:
        scratch = Path(args.scratch or tempfile.mkdtemp(prefix="bench_physics_"))
        print("fitted motion against the truth's: hands carry |F_hands| / |m (a - g)| over held frames (median), "
              "its error |F_hands - m (a - g)| / |m (a - g)|, fitted contact frames off the floor with a hand wrench, "
              "residual root force (% body weight), foot skating (mm/s)")
        for session, out in args.fitted:
            r = fitted_against_truth(Path(session), Path(out), scratch, cfg)
            print(f"  {Path(session).name}: held {r['held_frames']}/{r['frames']}, hands carry {r['hands_carry_median']:.2f}, "
                  f"error {r['hands_error_median']:.2f}, contact with hand wrench {r['contact_with_hand_wrench_pct']:.1f} % "
                  f"({r['contact_frames_unsolved']} contact frames unsolved), "
                  f"residual {r['residual_root_force_pct_bw_mean_fitted']:.1f} (truth {r['residual_root_force_pct_bw_mean_truth']:.1f}, "
                  f"p95 {r['residual_root_force_pct_bw_p95_fitted']:.1f} / {r['residual_root_force_pct_bw_p95_truth']:.1f}) % BW, "
                  f"skating {r['foot_skating_mm_s_fitted']:.0f} (truth {r['foot_skating_mm_s_truth']:.0f}) mm/s, "
                  f"cone violations {r['friction_cone_violation_pct_fitted']:.1f} (truth {r['friction_cone_violation_pct_truth']:.1f}) %")
        return
    if args.supports:
        r = bench_supports(Path(args.supports), args.fps if args.fps != 30.0 else 15.0, cfg)
        sit, table = r["sit_stand"], r["table_lift"]
        print(f"supports on ground-truth motion: sit_stand seated {sit['seated_frames']} frames, seat carries "
              f"{sit['seat_share_median']:.3f} of the body weight (median; min {sit['seat_share_min']:.3f}), feet "
              f"{sit['feet_share_median']:.3f}, seat while standing {sit['seat_share_standing_max']:.3f} (max); "
              f"residual {sit['residual_root_force_pct_bw_mean']:.2f} % BW; {sit['s_per_frame']:.3f} s/frame")
        print(f"  table_lift: box resting untouched {table['resting_frames']} frames, the table carries "
              f"{table['table_share_median']:.3f} of its weight (median), box unexplained force "
              f"{table['object_residual_pct_max']:.2f} % of its weight (max); residual "
              f"{table['residual_root_force_pct_bw_mean']:.2f} % BW; {table['s_per_frame']:.3f} s/frame")
        return
    if args.gt_motion:
        rows = bench_gt_motion(Path(args.gt_motion), args.scripts.split(","), args.fps, cfg)
        print(f"ground-truth motion at {args.fps:g} fps: residual root force (% body weight)")
        print("  script      frames  resid_mean  resid_p95  cone_viol_%  skating_mm_s  penetr_max_mm  flights  s/frame")
        for r in rows:
            print(f"  {r['script']:10s} {r['frames']:6d}  {r['residual_root_force_pct_bw_mean']:10.2f}  "
                  f"{r['residual_root_force_pct_bw_p95']:9.2f}  {r['friction_cone_violation_pct']:11.1f}  "
                  f"{r['foot_skating_mm_s']:12.1f}  {r['ground_penetration_mm_max']:13.1f}  {r['flight_episodes']:7d}  "
                  f"{r['s_per_frame']:.3f}")
        return
    if not args.skip_filters:
        print("filter choice: acceleration error on 2 mm noise at 30 fps (m/s^2)")
        rows = sorted(bench_filters(), key=lambda r: r["acc_rms_all"])
        for r in rows:
            name = r["filter"] + "".join(f" {k}={v}" for k, v in r.items() if k in ("cutoff_hz", "window_s", "order"))
            kinds = "  ".join(f"{k[4:]} {v:5.2f}" for k, v in r.items() if k.startswith("rms_"))
            print(f"  {name:32s} all {r['acc_rms_all']:5.2f}  interior {r['acc_rms_interior']:5.2f}  | {kinds}")
    hold = bench_static_hold(args.frames)
    print("static hold, Kinect-like noise (2 mm, 0.11 deg):")
    for k, v in hold.items():
        print(f"  {k:40s} {v:.4g}")
    for folder in args.results:
        metrics = json.loads((Path(folder) / "metrics.json").read_text()).get("physics", {})
        print(f"{folder}: " + ", ".join(f"{k}={v:.3g}" for k, v in metrics.items() if isinstance(v, (int, float))))
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
