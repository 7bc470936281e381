"""The generator's physics scripts (toss, hold, drop): their object tracks and analytic ground truth,
checked without rendering or the body model's IK (object plan + flight, and physics_ground_truth
on a stand-in animation)."""
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from intercap.synth.generator import BODY_DENSITY, physics_ground_truth
from intercap.synth.motions import GRAVITY, contact_interval, flight_track, get_script, heading_frames, object_track
from intercap.synth.objects import make_object

FPS = 30.0


def script_object(name: str):
    """(times, planned poses, object poses, flight, contact) of a script for a person standing at the origin."""
    script = get_script(name)
    spec = make_object(script.default_object)
    times = np.arange(int(np.floor(script.duration * FPS + 1e-9)) + 1) / FPS
    heading = heading_frames(np.zeros(len(times)), np.zeros((len(times), 2)), 0.3)
    plan = object_track(script, {"body": heading, "head": heading}, times, half_height=spec.half_height)
    poses, flight = (plan, None) if script.flight is None else flight_track(script, plan, times, spec.half_height)
    c0, c1 = contact_interval(script)
    contact = (times >= c0) & (times < c1)
    if flight is not None:
        contact[flight[0]:flight[1] + 1] = False
    return script, spec, times, plan, poses, flight, contact


def test_toss_flight_is_an_exact_parabola_with_10_frames():
    script, spec, times, plan, poses, flight, contact = script_object("toss")
    a, b = flight
    assert b - a + 1 >= 10 and not contact[a:b + 1].any() and contact[a - 1] and contact[b + 1]
    # the flight leaves the hands at frame a - 1 and is caught at b + 1: the parabola spans a-1 .. b+1
    t = times[a - 1:b + 2] - times[a - 1]
    p = poses[a - 1:b + 2, :3, 3]
    A = np.stack([np.ones_like(t), t, 0.5 * t * t], 1)
    coef, *_ = np.linalg.lstsq(A, p, rcond=None)
    np.testing.assert_allclose(coef[2], [0.0, 0.0, -GRAVITY], atol=1e-8)
    np.testing.assert_allclose(A @ coef, p, atol=1e-10)
    assert p[:, 2].max() - p[0, 2] > 0.2  # thrown well up
    np.testing.assert_allclose(poses[a:b + 1, :3, :3], np.broadcast_to(poses[a - 1, :3, :3], (b - a + 1, 3, 3)))
    np.testing.assert_allclose(poses[:a], plan[:a])  # in the hands: the plan
    np.testing.assert_allclose(poses[b + 1:], plan[b + 1:])


def test_a_spinning_toss_turns_at_a_constant_rate_about_the_object_x_axis():
    """`flight_turns` = 1: one whole turn in the 0.5 s flight (24 degrees a frame at 30 fps) about
    the object's own x axis, the same parabola, and the planned pose again at the catch."""
    import dataclasses

    from scipy.spatial.transform import Rotation

    script, spec, times, plan, still, flight, contact = script_object("toss")
    spinning = dataclasses.replace(script, flight_turns=1.0)
    poses, same_flight = flight_track(spinning, plan, times, spec.half_height)
    a, b = flight
    assert same_flight == flight
    np.testing.assert_allclose(poses[:, :3, 3], still[:, :3, 3])
    np.testing.assert_allclose(poses[b + 1], plan[b + 1])
    steps = Rotation.from_matrix(np.einsum("tji,tjk->tik", poses[a - 1:b + 1, :3, :3], poses[a:b + 2, :3, :3]))
    np.testing.assert_allclose(np.degrees(steps.magnitude()), np.full(b - a + 2, 360.0 / (b - a + 2)), atol=1e-6)
    np.testing.assert_allclose(np.abs(steps.as_rotvec()[:, 0]), steps.magnitude(), atol=1e-9)  # about x (object frame)
    assert 23.0 < 360.0 / (b - a + 2) < 25.0


def test_drop_falls_from_rest_and_lands_flat():
    script, spec, times, plan, poses, flight, contact = script_object("drop")
    a, b = flight
    assert b - a + 1 >= 10 and not contact[a:].any() and contact[:a - 1].all()
    dt = times[a - 1:b + 1] - times[a - 1]
    np.testing.assert_allclose(poses[a - 1:b + 1, 2, 3], poses[a - 1, 2, 3] - 0.5 * GRAVITY * dt**2, atol=1e-12)
    np.testing.assert_allclose(poses[b + 1:, 2, 3], spec.half_height)  # lying on the floor
    assert poses[b, 2, 3] > spec.half_height


def fake_animation(name: str, body_moves: bool = False):
    script, spec, times, plan, poses, flight, contact = script_object(name)
    body = trimesh.creation.box(extents=(0.3, 0.2, 1.0))  # stand-in body: 0.06 m^3 -> 60.6 kg
    vertices = np.broadcast_to(np.asarray(body.vertices, np.float32), (len(times),) + body.vertices.shape).copy()
    if body_moves:
        vertices[:, :, 0] += (0.5 * times**2)[:, None]  # 1 m/s^2 throughout
    anim = SimpleNamespace(object_poses=poses, vertices=vertices, contact=contact, flight=flight)
    return anim, spec, body


def test_hold_ground_truth_is_static_equilibrium():
    anim, spec, body = fake_animation("hold")
    gt = physics_ground_truth(anim, spec, np.asarray(body.faces), np.asarray(body.vertices), FPS, 1.0)
    M, m = 0.06 * BODY_DENSITY, spec.mass_kg
    assert gt["body_mass_kg"] == pytest.approx(M) and gt["object_mass_kg"] == m
    inner = slice(1, -1)  # the first and last frame have no acceleration to tell
    np.testing.assert_allclose(gt["hand_force"][inner], np.tile([0, 0, m * 9.81], (len(anim.contact) - 2, 1)))
    np.testing.assert_allclose(gt["ground_reaction"][inner], np.tile([0, 0, (M + m) * 9.81], (len(anim.contact) - 2, 1)))
    assert np.isnan(gt["hand_force"][[0, -1]]).all() and len(gt["flight_episodes"]) == 0


@pytest.mark.parametrize("name", ["toss", "drop"])
def test_flight_ground_truth(name):
    anim, spec, body = fake_animation(name)
    gt = physics_ground_truth(anim, spec, np.asarray(body.faces), np.asarray(body.vertices), FPS, 1.0)
    a, b = anim.flight
    np.testing.assert_array_equal(gt["flight_episodes"], [[a, b]])
    np.testing.assert_allclose(gt["flight_acceleration"], [[0, 0, -9.81]])
    np.testing.assert_allclose(gt["hand_force"][a:b + 1], 0.0)  # nothing touches it
    np.testing.assert_allclose(gt["object_ground_force"][a:b + 1], 0.0)
    M = 0.06 * BODY_DENSITY
    np.testing.assert_allclose(gt["ground_reaction"][a:b + 1, 2], M * 9.81)  # the body carries only itself
    moving, _, _ = fake_animation(name, body_moves=True)
    gt = physics_ground_truth(moving, spec, np.asarray(body.faces), np.asarray(body.vertices), FPS, 1.0)
    assert np.isnan(gt["ground_reaction"][2:-2]).all()  # an accelerating body: not analytic
    if name == "toss":  # held still before the wind-up and after the catch: m g
        np.testing.assert_allclose(gt["hand_force"][5], [0, 0, spec.mass_kg * 9.81])
        assert np.isnan(gt["hand_force"][20]).all()  # wind-up: the object accelerates
    else:  # lying on the floor untouched
        np.testing.assert_allclose(gt["object_ground_force"][b + 3], [0, 0, spec.mass_kg * 9.81])
