"""Physical plausibility figures of a physics result.

They need no ground truth, so they judge real captures too. The `physics` stage stores the
per-frame quantities in OUT/physics/physics.npz (besides the contract keys):

* `cone_violation` (T, 2) bool: the foot's total force in an *unconstrained* solve (free 3D sole
  forces, no friction cone, no unilateral contact) pulls on the floor or leaves the cone |f_t| <= mu f_n;
* `sole_speed` (T, 2, P) m/s: tangential speed of each sole point (foot skating where in contact);
* `ground_penetration_m` (T,): depth of the body's lowest vertex below the floor (0 above it);
* `object_ground_penetration_m` (T,): the same for the object (NaN without an object pose).

`summarise` turns a physics.npz (or the dict the stage writes into it) into the figures that
OUT/metrics.json and `intercap eval` show; what the file cannot support is left out.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np


def residual_pct_body_weight(residual_force: np.ndarray, body_mass: float, gravity: np.ndarray) -> np.ndarray:
    """(T,) |residual root force| as % of body weight M |g|."""
    return np.linalg.norm(residual_force, axis=-1) / (body_mass * np.linalg.norm(gravity)) * 100


def summarise(z: Mapping) -> dict:
    """Figures (plain floats / ints) of one physics result: residual root force (% body weight,
    mean and p95 over valid frames), friction-cone violations (% of foot-in-contact frames),
    foot skating (mm/s over sole points in contact), ground penetration (mm), free flight
    (|a - g| m/s^2, |a|, angle to gravity)."""
    valid = np.asarray(z["valid"], bool)
    gravity = np.asarray(z["gravity"], np.float64)
    mass = float(z["body_mass_kg"])
    out: dict = {}
    if valid.any():
        res = residual_pct_body_weight(np.asarray(z["residual_force"])[valid], mass, gravity)
        out["residual_root_force_pct_bw_mean"] = float(res.mean())
        out["residual_root_force_pct_bw_p95"] = float(np.percentile(res, 95))
        out["residual_root_torque_nm_mean"] = float(np.linalg.norm(np.asarray(z["residual_torque"])[valid], axis=1).mean())
        obj = np.linalg.norm(np.asarray(z["object_residual_force"])[valid], axis=1)
        if np.isfinite(obj).any():
            out["object_residual_force_n_mean"] = float(np.nanmean(obj))
    contact = np.asarray(z["foot_contact"], bool) & valid[:, None, None] if "foot_contact" in z else None
    if contact is not None and "cone_violation" in z:
        in_contact = contact.any(2)  # (T, 2)
        bad = np.asarray(z["cone_violation"], bool) & in_contact
        out["friction_cone_violation_pct"] = float(100 * bad.sum() / max(in_contact.sum(), 1))
    if contact is not None and "sole_speed" in z:
        speed = np.asarray(z["sole_speed"])[contact]
        out["foot_skating_mm_s"] = float(speed.mean() * 1000) if speed.size else 0.0
    if "ground_penetration_m" in z and valid.any():
        depth = np.asarray(z["ground_penetration_m"])[valid] * 1000
        out["ground_penetration_mm_mean"] = float(depth.mean())
        out["ground_penetration_mm_max"] = float(depth.max())
    if "object_ground_penetration_m" in z:
        od = np.asarray(z["object_ground_penetration_m"], np.float64)
        if np.isfinite(od).any():
            out["object_ground_penetration_mm_max"] = float(np.nanmax(od) * 1000)
    episodes = np.asarray(z["flight_episodes"]).reshape(-1, 2)
    out["flight_episodes"] = int(len(episodes))
    if len(episodes):
        acc = np.asarray(z["flight_acceleration"], np.float64).reshape(-1, 3)
        out["flight_accel_error_mps2_mean"] = float(np.nanmean(np.linalg.norm(acc - gravity, axis=1)))
        out["flight_g_norm_mps2_mean"] = float(np.nanmean(np.linalg.norm(acc, axis=1)))
        out["flight_gravity_angle_deg_mean"] = float(np.nanmean(np.asarray(z["flight_gravity_angle_deg"])))
    return out
