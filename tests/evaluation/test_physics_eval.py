"""`intercap eval` physics figures from a hand-made OUT/physics/physics.npz with known values."""
import numpy as np
import pytest

from intercap.evaluation.evaluate import evaluate
from intercap.evaluation.physics_figures import physics_metrics
from intercap.evaluation.table import format_table

G = np.array([0.0, 0.0, -9.81])
T, M, m = 20, 70.0, 2.0


def write_physics(out, flight=((5, 14),), residual_pct=5.0):
    valid = np.ones(T, bool)
    valid[0] = False  # an untrusted frame must not count
    residual = np.zeros((T, 3))
    residual[:, 0] = residual_pct / 100 * M * 9.81
    residual[0] = 1e6
    foot_contact = np.ones((T, 2, 4), bool)
    foot_contact[:, 1] = False  # the right foot is in the air
    sole_speed = np.full((T, 2, 4), 0.5)
    sole_speed[:, 0] = 0.01  # 10 mm/s on the standing foot
    cone = np.zeros((T, 2), bool)
    cone[1:4, 0] = True  # 3 of 19 valid frames of the standing foot
    cone[:, 1] = True  # the foot in the air does not count
    pen = np.zeros(T)
    pen[2] = 0.004
    hand = np.zeros((T, 2, 3))
    hand[:, :, 2] = m * 9.81 / 2 * 1.02  # 2 % too much
    acc = np.array([[0.0, 0.3, -9.81]])
    (out / "physics").mkdir(parents=True)
    np.savez(out / "physics" / "physics.npz", frame_ids=np.arange(T), gravity=G, body_mass_kg=M, object_mass_kg=m,
             valid=valid, residual_force=residual, residual_torque=np.zeros((T, 3)),
             object_residual_force=np.zeros((T, 3)), hand_force=hand, foot_force=np.tile([0, 0, (M + m) * 9.81 / 2], (T, 2, 1)),
             foot_contact=foot_contact, sole_speed=sole_speed, cone_violation=cone, ground_penetration_m=pen,
             flight_episodes=np.array(flight, np.int64).reshape(-1, 2), flight_acceleration=np.tile(acc, (len(flight), 1)),
             flight_gravity_angle_deg=np.full(len(flight), np.degrees(np.arctan2(0.3, 9.81))))


def test_plausibility_without_ground_truth(tmp_path):
    write_physics(tmp_path / "out")
    result = evaluate(tmp_path / "out")  # real data: no session, no ground truth
    f = result.metrics
    assert f["frames"] == T
    assert f["physics_residual_root_force_pct_bw_mean"] == pytest.approx(5.0)
    assert f["physics_residual_root_force_pct_bw_p95"] == pytest.approx(5.0)
    assert f["physics_friction_cone_violation_pct"] == pytest.approx(100 * 3 / 19)
    assert f["physics_foot_skating_mm_s"] == pytest.approx(10.0)
    assert f["physics_ground_penetration_mm_max"] == pytest.approx(4.0)
    assert f["physics_flight_accel_error_mps2_mean"] == pytest.approx(0.3)
    assert f["physics_flight_gravity_angle_deg_mean"] == pytest.approx(np.degrees(np.arctan2(0.3, 9.81)))
    table = format_table(result)
    assert "physics_foot_skating_mm_s" in table and "mm/s" in table and "no ground truth" in table


def test_not_run_and_nothing_to_evaluate(tmp_path):
    (tmp_path / "out").mkdir()
    metrics, notes = physics_metrics(tmp_path / "out")
    assert metrics == {"physics": "not run"} and "not run" in notes[0]
    with pytest.raises(FileNotFoundError, match="physics.npz"):
        evaluate(tmp_path / "out")


def test_against_physics_ground_truth(tmp_path):
    write_physics(tmp_path / "out", flight=((6, 14),))
    gt = tmp_path / "gt"
    gt.mkdir()
    hand = np.full((T, 3), np.nan)
    hand[:5] = [0, 0, m * 9.81]  # held still
    hand[5:15] = 0.0  # in flight
    np.savez(gt / "physics.npz", frame_ids=np.arange(T), gravity=G, body_mass_kg=M * 1.1, object_mass_kg=m,
             hand_force=hand, ground_reaction=np.full((T, 3), np.nan), flight_episodes=np.array([[5, 14]]),
             flight_acceleration=G[None])
    f, notes = physics_metrics(tmp_path / "out", gt)
    assert f["physics_hand_force_err_pct_mean"] == pytest.approx(2.0)
    assert f["physics_hand_force_truth_frames"] == 4  # frames 1-4: frame 0 is untrusted
    assert f["physics_flight_start_err_frames"] == 1 and f["physics_flight_end_err_frames"] == 0
    assert f["physics_flight_accel_vs_truth_mps2_mean"] == pytest.approx(0.3)
    assert f["physics_body_mass_err_pct"] == pytest.approx(100 / 11)
    np.savez(gt / "physics.npz", frame_ids=np.arange(T), gravity=G, body_mass_kg=M, object_mass_kg=m, hand_force=hand,
             ground_reaction=np.full((T, 3), np.nan), flight_episodes=np.array([[16, 19]]), flight_acceleration=G[None])
    f, notes = physics_metrics(tmp_path / "out", gt)
    assert f["physics_flight_start_err_frames"] is None and "not detected" in notes[-1]
