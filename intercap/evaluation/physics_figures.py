"""Physics figures of `intercap eval`: physical plausibility of OUT/physics/physics.npz (no ground
truth needed, so real captures get them too) and, where the session has ground_truth/physics.npz
(the generator's toss / hold / drop scripts), the errors against what is analytic there.

Metric names start with `physics_`; units are in the names as elsewhere (`_pct`, `_mm`, `_mm_s`,
`_deg`, `_mps2`, `_frames`). Definitions:
- physics_residual_root_force_pct_bw_mean / _p95: |residual force on the body's root| / (M |g|);
- physics_friction_cone_violation_pct: feet in contact whose force in an unconstrained solve
  leaves the friction cone (or pulls), % of foot-frames in contact;
- physics_foot_skating_mm_s: mean tangential speed of sole points in ground contact;
- physics_ground_penetration_mm_mean / _max: the body's lowest vertex below the floor;
- physics_flight_accel_error_mps2_mean: |a - g| of the free-flight parabola fits (g not imposed);
  physics_flight_gravity_angle_deg_mean: angle of a to the ground normal's down;
- against ground truth: physics_hand_force_err_pct_mean (|sum of hand forces - truth| / (m |g|)
  on frames where the truth holds the object still), physics_ground_reaction_err_pct_mean
  (|sum of foot forces - truth| / |truth|, where the truth is analytic), physics_body_mass_err_pct,
  physics_flight_start_err_frames / _end_err_frames (largest |first / last frame - truth| over the
  true episodes; None when an episode was missed), physics_flight_accel_vs_truth_mps2_mean.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from intercap.dynamics.plausibility import summarise

NOT_RUN = "not run"


def physics_file(out_dir) -> Path:
    return Path(out_dir) / "physics" / "physics.npz"


def _load(path: Path) -> dict:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 - re-raised with the file named
        raise ValueError(f"{path}: cannot read ({exc})") from exc


def physics_metrics(out_dir, gt_dir=None) -> tuple[dict, list[str]]:
    """(metrics, notes): the physics figures of a results folder, `{"physics": "not run"}` with a note
    when OUT/physics/physics.npz is missing."""
    path = physics_file(out_dir)
    if not path.is_file():
        return {"physics": NOT_RUN}, [f"physics figures: not run (no {path}; `intercap run SESSION --out OUT "
                                      f"--stages physics` computes them)"]
    z = _load(path)
    for key in ("valid", "gravity", "body_mass_kg", "residual_force", "residual_torque", "object_residual_force",
                "flight_episodes", "flight_acceleration", "flight_gravity_angle_deg"):
        if key not in z:
            raise ValueError(f"{path}: key {key!r} missing (see docs/outputs.md)")
    metrics = {f"physics_{k}": v for k, v in summarise(z).items()}
    metrics["physics_body_mass_kg"] = float(z["body_mass_kg"])
    notes = []
    missing = [k for k in ("cone_violation", "sole_speed", "ground_penetration_m") if k not in z]
    if missing:
        notes.append(f"physics: {path} predates the plausibility arrays ({', '.join(missing)}): "
                     f"rerun the physics stage for friction-cone, skating and penetration figures")
    gt_path = Path(gt_dir) / "physics.npz" if gt_dir is not None else None
    if gt_path is not None and gt_path.is_file():
        metrics.update(_against_truth(z, _load(gt_path), path, gt_path, notes))
    return metrics, notes


def _against_truth(z: dict, gt: dict, path: Path, gt_path: Path, notes: list) -> dict:
    T = len(z["valid"])
    if len(gt["frame_ids"]) != T:
        raise ValueError(f"frame count mismatch: {path} has {T} frames, {gt_path} {len(gt['frame_ids'])}")
    out = {}
    valid = np.asarray(z["valid"], bool)
    g = float(np.linalg.norm(gt["gravity"]))
    M_true, m_true = float(gt["body_mass_kg"]), float(gt["object_mass_kg"])
    out["physics_body_mass_err_pct"] = abs(float(z["body_mass_kg"]) - M_true) / M_true * 100
    hand_true = np.asarray(gt["hand_force"], np.float64)  # (T, 3) total, NaN where not analytic
    hand = np.asarray(z["hand_force"], np.float64).sum(1)  # (T, 3)
    held = valid & np.isfinite(hand_true).all(1) & (np.linalg.norm(hand_true, axis=1) > 0)
    if held.any() and np.isfinite(hand[held]).all():
        err = np.linalg.norm(hand[held] - hand_true[held], axis=1) / (m_true * g) * 100
        out.update(physics_hand_force_err_pct_mean=float(err.mean()), physics_hand_force_err_pct_max=float(err.max()),
                   physics_hand_force_truth_frames=int(held.sum()))
    elif held.any():
        notes.append("physics: the object's forces were not solved (object mass unknown): no hand force error")
    ground_true = np.asarray(gt["ground_reaction"], np.float64)
    ground = np.asarray(z["foot_force"], np.float64).sum(1)
    ok = valid & np.isfinite(ground_true).all(1) & np.isfinite(ground).all(1)
    if ok.any():
        err = np.linalg.norm(ground[ok] - ground_true[ok], axis=1) / np.linalg.norm(ground_true[ok], axis=1) * 100
        out.update(physics_ground_reaction_err_pct_mean=float(err.mean()),
                   physics_ground_reaction_truth_frames=int(ok.sum()))
    true_eps = np.asarray(gt["flight_episodes"]).reshape(-1, 2)
    if len(true_eps):
        eps = np.asarray(z["flight_episodes"]).reshape(-1, 2)
        acc, acc_true = np.asarray(z["flight_acceleration"]).reshape(-1, 3), np.asarray(gt["flight_acceleration"]).reshape(-1, 3)
        starts, ends, acc_err = [], [], []
        for k, (a, b) in enumerate(true_eps):
            overlap = [min(b, e1) - max(a, e0) + 1 for e0, e1 in eps]
            if not overlap or max(overlap) <= 0:
                starts.append(np.inf)
                ends.append(np.inf)
                continue
            j = int(np.argmax(overlap))
            starts.append(abs(int(eps[j, 0]) - int(a)))
            ends.append(abs(int(eps[j, 1]) - int(b)))
            acc_err.append(float(np.linalg.norm(acc[j] - acc_true[k])))
        missed = int(np.sum(np.isinf(starts)))
        out["physics_flight_episodes_truth"] = int(len(true_eps))
        out["physics_flight_start_err_frames"] = None if missed else int(max(starts))
        out["physics_flight_end_err_frames"] = None if missed else int(max(ends))
        out["physics_flight_accel_vs_truth_mps2_mean"] = float(np.mean(acc_err)) if acc_err else None
        if missed:
            notes.append(f"physics: {missed} of {len(true_eps)} true free-flight episodes not detected")
    return out
