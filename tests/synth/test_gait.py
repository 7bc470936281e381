"""The generator's walk is physically plausible: the supporting foot stays put and flat, and the
body moves at a near-constant speed in steady walking (no stop-and-go at every step), so the
physics stage can explain the ground-truth motion with floor contacts alone."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from intercap.stages.physics.stage import body_landmarks, rest_body
from intercap.synth import motions as mo
from intercap.synth.generator import SynthConfig, cached_body_model

RATE = 60.0


@pytest.fixture(scope="module")
def walk():
    """A leaning walk (pelvis pitched 0.15 rad, as when pushing): ramp up, 2 s steady, ramp down."""
    script = dataclasses.replace(mo.get_script("hold"), duration=3.4, pitch_keys=[(0.0, 0.15)],
                                 walk_keys=[(0.0, 0.0), (0.5, 0.8), (2.9, 0.8), (3.4, 0.0)])
    model = cached_body_model()
    times = np.arange(0.0, script.duration, 1.0 / RATE)
    shape = torch.as_tensor(SynthConfig().phenotype, dtype=model.dtype)[None]
    with torch.no_grad():
        rest = model(model.init_params(1)).vertices[0].numpy()
        local = model(mo.scripted_pose(model, script, times, shape, 0.25)).vertices.numpy()
    pitch = mo.eased_scalar(script.pitch_keys, times)
    R = mo.body_orientation(model, mo.heading_frames(np.zeros(len(times)), np.zeros((len(times), 2)), 0.0), pitch)
    root = mo.root_path(model, script, times, shape, 0.0, 0.25)
    world = np.einsum("tij,tvj->tvi", R, local)
    world[..., :2] += root[:, None]
    world[..., 2] -= world[..., 2].min(1, keepdims=True)  # lowest vertex on the floor, as animate places it
    steady = (times > 0.9) & (times < 2.5)
    rest_heads = rest_body(model, model.init_params(1).shape[0].numpy())[1][:, :3, 3]
    return (times, root, world, body_landmarks(model, rest, rest_heads)["soles"], mo.left_stance_weight(script, times),
            steady)


def test_steady_walk_has_near_constant_speed(walk):
    times, root, _, _, _, steady = walk
    speed = np.linalg.norm(np.gradient(root, 1.0 / RATE, axis=0), axis=1)[steady]
    assert speed.mean() > 0.3  # it walks
    assert speed.max() - speed.min() < 0.25 * speed.mean(), (speed.min(), speed.max())
    # body (root) acceleration on 30 fps samples stays in the range of real walking
    sub = root[::2]
    acc = np.linalg.norm(np.diff(sub, 2, axis=0) * 30.0**2, axis=1)[steady[::2][1:-1]]
    assert acc.max() < 3.0, acc.max()


def test_supporting_foot_stays_put_and_flat(walk):
    times, _, world, soles, w_left, steady = walk
    for side, on in ((0, w_left > 0.99), (1, w_left < 0.01)):
        corners = world[:, soles[side]]  # (T, 4, 3)
        stance = on & steady
        # split into stances, check each one's slide and the sole's height
        breaks = np.flatnonzero(np.diff(stance.astype(int)) != 0) + 1
        for run in np.split(np.arange(len(times)), breaks):
            if not stance[run[0]] or len(run) < 5:
                continue
            centre = corners[run].mean(1)
            slide = np.linalg.norm(centre[:, :2] - centre[:1, :2], axis=1).max()
            assert slide < 0.01, f"side {side} slides {slide * 1000:.1f} mm over one stance"
            assert np.ptp(corners[run][..., 2], axis=1).max() < 0.01  # the four sole corners level (flat)
            assert corners[run][..., 2].max() < 0.03  # and on the floor
