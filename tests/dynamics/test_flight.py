"""Free flight (GraviCap): episode detection, parabola fits, gravity from flight, the flight loss,
and prepare's fall-back when no floor is found."""
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from intercap.dynamics.flight import (falling_episodes, find_flight_episodes, fit_flight, gravity_from_flight,
                                      object_on_ground)
from intercap.energies.losses import flight_parabola
from intercap.synth.motions import flight_track, get_script

FPS = 30.0
UP = np.array([0.0, 0.0, 1.0])


def generator_flight(name: str, height: float = 0.95, half_height: float = 0.075):
    """The generator's own flight of script `name` from a still plan (T, 4, 4) at `height`:
    (object poses, flight (first, last), touching (T,) as a pipeline would label it)."""
    script = get_script(name)
    times = np.arange(int(script.duration * FPS) + 1) / FPS
    plan = np.tile(np.eye(4), (len(times), 1, 1))
    plan[:, :3, 3] = (0.3, -0.2, height)
    poses, flight = flight_track(script, plan, times, half_height)
    box = np.array([[x, y, z] for x in (-0.15, 0.15) for y in (-0.1, 0.1) for z in (-half_height, half_height)])
    corners = np.einsum("tij,mj->tmi", poses[:, :3, :3], box) + poses[:, None, :3, 3]
    touching = np.ones(len(times), bool)  # in the hands ...
    touching[flight[0]:] = False
    if name == "toss":
        touching[flight[1] + 1:] = True  # ... caught again
    touching |= object_on_ground(corners, np.zeros(3), UP, 0.01)  # ... or on the floor
    return poses, flight, touching


@pytest.mark.parametrize("name", ["toss", "drop"])
def test_generator_flight_detected_and_fits_gravity(name):
    poses, flight, touching = generator_flight(name)
    centres = poses[:, :3, 3]
    assert flight[1] - flight[0] + 1 >= 10  # 10+ flight frames at 30 fps
    episodes = find_flight_episodes(centres, touching, UP, FPS)
    assert len(episodes) == 1
    assert abs(episodes[0, 0] - flight[0]) <= 1 and abs(episodes[0, 1] - flight[1]) <= 1
    fit = fit_flight(centres, episodes, FPS, UP)
    np.testing.assert_allclose(fit["acceleration"][0], [0, 0, -9.81], atol=1e-6)
    assert fit["gravity_angle_deg"][0] < 1e-4 and fit["residual_m"][0] < 1e-9
    a, b = episodes[0]
    np.testing.assert_allclose(fit["fixed_fit"][a:b + 1], centres[a:b + 1], atol=1e-9)  # g fixed: the same parabola
    assert np.isnan(fit["fixed_fit"][:a]).all()

    # 2 mm of tracking noise and two lost frames: |g| within 0.3 m/s^2, direction within 3 degrees
    noisy = centres + np.random.default_rng(7).normal(0, 0.002, centres.shape)
    noisy[a + 3] = noisy[a + 6] = np.nan
    episodes = find_flight_episodes(noisy, touching, UP, FPS)
    assert len(episodes) == 1 and abs(episodes[0, 0] - flight[0]) <= 1 and abs(episodes[0, 1] - flight[1]) <= 1
    fit = fit_flight(noisy, episodes, FPS, UP)
    assert abs(fit["g_norm"][0] - 9.81) < 0.3
    assert fit["gravity_angle_deg"][0] < 3.0
    assert fit["frames_used"][0] == episodes[0, 1] - episodes[0, 0] - 1


def test_still_untouched_object_and_short_runs_are_not_flights():
    T = 40
    centres = np.tile([0.0, 0.0, 0.075], (T, 1)) + np.random.default_rng(0).normal(0, 0.002, (T, 3))
    touching = np.zeros(T, bool)  # lying on a floor the labels missed
    assert len(find_flight_episodes(centres, touching, UP, FPS)) == 0
    poses, flight, touching = generator_flight("toss")
    touching[flight[0] + 7] = True  # a contact label in the middle: two runs of < 8 frames
    assert len(find_flight_episodes(poses[:, :3, 3], touching, UP, FPS)) == 0


def test_an_object_held_where_contact_was_missed_is_no_flight():
    """A toss falls (kept, 2 mm of tracking noise); a cup lifted to the mouth and held there for 2 s
    while the contact labels say nothing touches it does not fall: not a flight, and the global
    stage says so instead of pulling the cup onto a 20 m fall."""
    import trimesh

    from intercap.config import GlobalConfig
    from intercap.geometry.ground import GroundPlane
    from intercap.stages.global_fit.observations import ObjectShape, PerFrameResults, free_flight

    poses, flight, _ = generator_flight("toss")
    tossed = poses[:, :3, 3] + np.random.default_rng(3).normal(0, 0.002, (len(poses), 3))
    kept, held = falling_episodes(tossed, [flight], FPS, UP, 0.05)
    assert kept.tolist() == [list(flight)] and held == []

    T, lift = 90, 20
    height = np.concatenate([np.linspace(0.9, 1.5, lift), np.full(T - lift, 1.5)])
    centres = np.stack([0.02 * np.sin(np.arange(T) / 9), np.zeros(T), height], 1)
    centres += np.random.default_rng(4).normal(0, 0.002, centres.shape)
    kept, held = falling_episodes(centres, [[lift, T - 1]], FPS, UP, 0.05)
    assert len(kept) == 0 and held[0][:2] == (lift, T - 1) and held[0][2] > 1.0  # metres off a fall

    contact = np.arange(T) < lift  # the labels lose the hand once the cup is up
    per_frame = PerFrameResults(None, np.ones(T, bool), np.tile(np.eye(3), (T, 1, 1)), centres, np.ones(T, bool),
                                np.ones(T), contact, None)
    shape = ObjectShape(trimesh.creation.cylinder(radius=0.04, height=0.1), 16, None, samples=64)
    out = free_flight(per_frame, shape, GroundPlane(point=np.zeros(3), normal=UP), FPS, GlobalConfig())
    assert len(out["episodes"]) == 0 and (out["episode_of_frame"] < 0).all()
    assert out["figures"]["flight_runs_held"] == [[lift, T - 1]]

    from intercap.evaluation.report import physics_section
    from intercap.stages.physics.stage import flight_analysis

    physics = flight_analysis(centres, contact, UP, FPS, 8, 0.05)
    assert len(physics["episodes"]) == 0 and physics["held"].tolist() == [[lift, T - 1]]
    page = physics_section({"hand_force": np.zeros((T, 2, 3)), "flight_runs_held": physics["held"]}, np.arange(T))
    assert f"not falling (a missed contact, not a flight): frames {lift}-{T - 1}" in page


def test_gravity_from_flight_in_a_tilted_world():
    tilt = Rotation.from_rotvec([0.4, -0.9, 0.3])
    up = tilt.apply(UP)
    runs = []
    for name in ("toss", "drop"):
        poses, flight, touching = generator_flight(name)
        runs.append((tilt.apply(poses[:, :3, 3]) + [1.0, 2.0, -0.5], touching))
    centres = np.concatenate([c for c, _ in runs])
    touching = np.concatenate([np.r_[t[:-1], True] for _, t in runs])  # keep the two sequences' runs apart
    episodes = find_flight_episodes(centres, touching, up, FPS)
    assert len(episodes) == 2
    fit = gravity_from_flight(centres, episodes, FPS)
    np.testing.assert_allclose(fit["up"], up, atol=1e-8)
    assert abs(fit["g_norm"] - 9.81) < 1e-6
    noisy = centres + np.random.default_rng(3).normal(0, 0.002, centres.shape)
    fit = gravity_from_flight(noisy, episodes, FPS)
    assert np.degrees(np.arccos(np.clip(fit["up"] @ up, -1, 1))) < 3.0 and abs(fit["g_norm"] - 9.81) < 0.3
    line = np.outer(np.arange(20) / FPS, [0.5, 0.0, 0.0])  # sliding at constant speed: not gravity
    with pytest.raises(ValueError, match="not gravity"):
        gravity_from_flight(line, np.array([[0, 19]]), FPS)


def test_flight_term_pulls_a_noisy_flight_onto_the_parabola():
    poses, flight, _ = generator_flight("toss")
    a, b = flight
    W = b - a + 7
    truth = torch.as_tensor(poses[a - 3:a - 3 + W, :3, 3])
    episode = torch.full((W,), -1, dtype=torch.long)
    episode[3:3 + b - a + 1] = 0
    times = torch.arange(W, dtype=torch.float64) / FPS
    gravity = torch.tensor([0.0, 0.0, -9.81], dtype=torch.float64)
    assert flight_parabola(truth, episode, times, gravity).abs().max() < 1e-20  # on the parabola: free
    noisy = truth + torch.as_tensor(np.random.default_rng(1).normal(0, 0.005, truth.shape))
    centres = noisy.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([centres], max_iter=200, line_search_fn="strong_wolfe", tolerance_grad=1e-12)

    def closure():
        opt.zero_grad()
        loss = ((centres - noisy) ** 2).sum() + 1e3 * flight_parabola(centres, episode, times, gravity).sum()
        loss.backward()
        return loss

    opt.step(closure)
    fitted = centres.detach()
    inside = episode >= 0
    before = (noisy - truth)[inside].norm(dim=-1).pow(2).mean().sqrt()
    after = (fitted - truth)[inside].norm(dim=-1).pow(2).mean().sqrt()
    assert after < 0.5 * before  # 14 frames on a 6-parameter curve: most of the noise goes
    assert flight_parabola(fitted, episode, times, gravity).max() < 1e-8
    torch.testing.assert_close(fitted[~inside], noisy[~inside])  # outside the flight: untouched


def test_prepare_without_a_floor_hands_gravity_to_the_flight(tmp_path, monkeypatch):
    from conftest import SAMPLE_SESSION, trimmed_copy

    from intercap.config import Config
    from intercap.session import Session
    from intercap.stages.prepare import stage as prepare

    def no_floor(*args, **kwargs):
        raise ValueError("fit_ground_plane: no plane with >= 50 points within 0.015 m")

    monkeypatch.setattr(prepare, "estimate_ground", no_floor)
    session = Session.load(trimmed_copy(SAMPLE_SESSION, tmp_path / "s", 2))
    cfg = Config()
    cfg.prepare.calib_frames = 1
    cfg.prepare.save_clouds = False
    figures = prepare.run(session, cfg, tmp_path / "out", progress=False)
    assert figures["ground_source"] == "unavailable" and "free flight" in figures["ground_fallback"]
    assert not (tmp_path / "out" / "prepare" / "ground.json").exists()
    assert (tmp_path / "out" / "prepare" / "ground_unavailable.json").exists()


@pytest.mark.parametrize("with_ground", [True, False])
def test_global_stage_flight_labels_and_gravity_without_floor(with_ground):
    import trimesh

    from intercap.config import GlobalConfig
    from intercap.geometry.ground import GroundPlane
    from intercap.stages.global_fit.observations import ObjectShape, PerFrameResults, free_flight

    tilt = Rotation.from_rotvec([0.3, 0.2, -1.0])
    poses, flight, touching = generator_flight("toss")
    T = len(poses)
    contact = touching.copy()  # the hands hold it except in flight
    R = np.einsum("ij,tjk->tik", tilt.as_matrix(), poses[:, :3, :3])
    t = tilt.apply(poses[:, :3, 3]) + np.random.default_rng(5).normal(0, 0.002, (T, 3))
    per_frame = PerFrameResults(None, np.ones(T, bool), R, t, np.ones(T, bool), np.ones(T), contact, None)
    shape = ObjectShape(trimesh.creation.box(extents=(0.16, 0.10, 0.08)), 16, None, samples=64)
    up = tilt.apply(UP)
    ground = GroundPlane(point=np.zeros(3), normal=up) if with_ground else None
    out = free_flight(per_frame, shape, ground, FPS, GlobalConfig())
    assert len(out["episodes"]) == 1 and np.abs(out["episodes"][0] - flight).max() <= 1
    assert (out["episode_of_frame"] >= 0).sum() == out["episodes"][0, 1] - out["episodes"][0, 0] + 1
    assert out["figures"]["gravity_source"] == ("ground" if with_ground else "flight")
    assert np.degrees(np.arccos(np.clip(out["up"] @ up, -1, 1))) < 3.0
