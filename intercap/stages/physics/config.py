"""The `physics` stage's settings (section `physics` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PhysicsConfig:
    """Forces, torques and free flight from the 4D result (the `physics` stage)."""

    mu: float = 0.5  # friction coefficient of the floor (sole and object contacts), dimensionless
    friction_edges: int = 4  # edges of the linearised friction cone (pyramid); more: closer to the cone, slower
    body_density_kg_m3: float = 1010.0  # body mass = rest mesh volume x this, unless session.yaml gives body.mass_kg
    sex: str = "auto"  # segment table: auto (blend by the fitted phenotype), male, female
    # smoothing before differentiating: adaptive (Savitzky-Golay, window per trajectory), savgol, butterworth, none
    filter: str = "adaptive"
    filter_window_s: float = 0.3  # the `savgol` filter's window (s)
    filter_order: int = 3  # Savitzky-Golay polynomial order (`adaptive` and `savgol`)
    cutoff_hz: float = 6.0  # the `butterworth` filter's cut-off (Hz; 4th order, forwards and backwards)
    foot_contact_m: float = 0.03  # a sole point this near (m) the floor can push on it
    object_ground_m: float = 0.02  # an object point this near (m) the floor can push on it
    support_contact_m: float = 0.03  # a body point this near (m) a fixed support (seat, table, bar) can push on it
    seat_contact_m: float = 0.06  # ... for buttocks and thighs: flesh a seat compresses, a model's skin does not
    support_depth_m: float = 0.05  # ... or this deep inside it (the fitted body sinks into a soft seat)
    static_object_m: float = 0.02  # an object whose tracked origin never strays this far (m) is a fixed support
    static_object_deg: float = 5.0  # ... nor turns this far (deg)
    torque_weight: float = 1e-2  # joint-torque prior that shares a load between contacts, (N m)^-2; 0: none
    object_weight: float = 10.0  # weight of the object's wrench equations against the body's (least squares)
    # the object's untracked frames in contact, in a gap this short (s) between tracked ones, are interpolated, so
    # the hands that carry it through the gap carry its weight; 0: off
    object_gap_fill_s: float = 0.5
    flight_min_frames: int = 8  # shortest free flight (object touching neither body nor floor), frames
    flight_max_residual_m: float = 0.05  # ... and a parabola under gravity within this (m, RMS) of its path
