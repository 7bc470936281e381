"""Learned motion priors (intercap/energies/motion_prior.py): shipped weights, behaviour on real motion, invariances.

The real motion is the 1.5 s of held-out CMU walking (03_04, never trained on) that ships in
motion_prior_body.npz as anny parameters; it is run through anny here."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from intercap.energies import motion_prior as mp

FPS = 30.0
UP = torch.tensor([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def model():
    from intercap.body_models import load_body_model

    return load_body_model("anny")


@pytest.fixture(scope="module")
def walk(model) -> torch.Tensor:
    """(45, V, 3) anny vertices of the shipped held-out walk, 30 fps, world z up."""
    data = np.load(mp.PRIOR_FILES["body"])
    params = model.init_params(len(data["example_transl"]))
    params.body_pose = torch.from_numpy(data["example_body_pose"])
    params.global_orient = torch.from_numpy(data["example_global_orient"])
    params.transl = torch.from_numpy(data["example_transl"])
    with torch.no_grad():
        return model(params).vertices


def jitter(vertices: torch.Tensor, sigma_mm: float, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return vertices + torch.randn(vertices.shape, generator=gen) * sigma_mm / 1000


def rotation_z(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def test_shipped_weights_load_small_and_credited(model):
    total = sum(p.stat().st_size for p in mp.PRIOR_FILES.values())
    assert total < 1_000_000
    for kind in ("body", "hand"):
        prior = mp.load_motion_prior(kind)
        assert prior.num_vertices == model.num_vertices
        assert int(prior.point_ids.max()) < model.num_vertices
        assert "mocap.cs.cmu.edu" in str(np.load(mp.PRIOR_FILES[kind])["source"])
        assert not any(p.requires_grad for p in prior.parameters())
    body = mp.load_motion_prior("body")
    assert 40 <= len(body.markers) <= 70


def test_real_walk_scores_lower_than_jittered_walk(walk):
    clean = float(mp.body_motion_smoothness(walk, FPS, UP))
    for sigma, factor in ((2.0, 4.0), (5.0, 20.0)):  # measured: x17 and x102
        assert float(mp.body_motion_smoothness(jitter(walk, sigma), FPS, UP)) > factor * clean
    for side in ("L", "R"):
        clean_h = float(mp.hand_motion_smoothness(walk, FPS, side, UP))
        assert float(mp.hand_motion_smoothness(jitter(walk, 5.0), FPS, side, UP)) > 50 * clean_h  # measured x355, x465


def test_a_single_frame_spike_on_one_arm_raises_the_prior(walk, model):
    with torch.no_grad():
        tips = walk[20, model.fingertip_vertex_ids[:5]].mean(0)  # left fingertips
    arm = (walk[20] - tips).norm(dim=-1) < 0.4  # hand, forearm and what hangs beside them (17 markers)
    spiked = walk.clone()
    spiked[20, arm] += torch.tensor([0.0, 0.05, 0.0])  # 5 cm, one frame
    # measured x2.4 (the acceleration penalty of the same markers: x3.4)
    assert float(mp.body_motion_smoothness(spiked, FPS, UP)) > 1.8 * float(mp.body_motion_smoothness(walk, FPS, UP))


def test_gradients_reach_the_marker_vertices_only(walk):
    verts = jitter(walk, 5.0).requires_grad_(True)
    total = mp.body_motion_smoothness(verts, FPS) + sum(mp.hand_motion_smoothness(verts, FPS, s) for s in "LR")
    total.backward()  # up estimated: the neck points count too
    grad = verts.grad.norm(dim=-1).sum(0)  # (V,)
    assert torch.isfinite(verts.grad).all()
    used = torch.cat([mp.load_motion_prior(k).point_ids for k in ("body", "hand")]).unique()
    assert (grad[used] > 0).float().mean() > 0.9
    unused = torch.ones_like(grad, dtype=torch.bool)
    unused[used] = False
    assert float(grad[unused].abs().max()) == 0.0
    # a gradient step lowers the prior of the jittered motion
    with torch.no_grad():
        stepped = verts - 1e-7 * verts.grad
        assert float(mp.body_motion_smoothness(stepped, FPS, UP)) < float(mp.body_motion_smoothness(verts, FPS, UP))


def test_invariant_to_translation_and_heading(walk):
    base = float(mp.body_motion_smoothness(walk, FPS, UP))
    moved = walk + torch.tensor([1.5, -2.0, 0.3])
    assert float(mp.body_motion_smoothness(moved, FPS, UP)) == pytest.approx(base, rel=1e-3)
    turned = walk @ rotation_z(70.0).T
    assert float(mp.body_motion_smoothness(turned, FPS, UP)) == pytest.approx(base, rel=1e-3)
    hand = float(mp.hand_motion_smoothness(walk, FPS, "L", UP))
    assert float(mp.hand_motion_smoothness(turned + 0.7, FPS, "L", UP)) == pytest.approx(hand, rel=1e-3)
    # any world frame: a y-down world with the ground normal given, or up estimated from the body
    R = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]) @ rotation_z(25.0)
    other = walk @ R.T
    assert float(mp.body_motion_smoothness(other, FPS, R @ UP)) == pytest.approx(base, rel=1e-3)
    assert float(mp.body_motion_smoothness(other, FPS)) == pytest.approx(
        float(mp.body_motion_smoothness(walk, FPS)), rel=1e-3)
    # the up estimated from the trunk leans with it: same order as with the true up (measured +34 %)
    assert float(mp.body_motion_smoothness(walk, FPS)) == pytest.approx(base, rel=0.6)


def test_left_hand_of_the_mirrored_motion_scores_as_the_right_hand(walk, model):
    rest = model.core(None, None)["vertices"][0].detach().numpy()
    mirror = cKDTree(rest).query(rest * np.array([-1.0, 1.0, 1.0]))[1]
    mirrored = walk[:, torch.from_numpy(mirror)] * torch.tensor([-1.0, 1.0, 1.0])
    for a, b in (("L", "R"), ("R", "L")):
        assert float(mp.hand_motion_smoothness(mirrored, FPS, a, UP)) == pytest.approx(
            float(mp.hand_motion_smoothness(walk, FPS, b, UP)), rel=1e-3)


def test_batched_and_compact_inputs_match_single_sequences(walk):
    noisy = jitter(walk, 3.0)
    batched = mp.body_motion_smoothness(torch.stack([walk, noisy]), FPS, UP)
    assert batched.shape == (2,)
    assert float(batched[0]) == pytest.approx(float(mp.body_motion_smoothness(walk, FPS, UP)), rel=1e-4)
    assert float(batched[1]) == pytest.approx(float(mp.body_motion_smoothness(noisy, FPS, UP)), rel=1e-4)
    prior = mp.load_motion_prior("body")
    compact = walk[:, prior.point_ids]
    assert float(mp.motion_smoothness(compact, FPS, prior, UP)) == pytest.approx(float(batched[0]), rel=1e-5)


def test_higher_frame_rates_score_interleaved_phases(walk):
    """60 fps: the walk with midpoints inserted scores near its 30 fps value, jitter at 60 fps still far above."""
    mid = (walk[1:] + walk[:-1]) / 2
    fine = torch.stack([walk[:-1], mid], dim=1).flatten(0, 1)  # (2T-2, V, 3)
    at30 = float(mp.body_motion_smoothness(walk, FPS, UP))
    at60 = float(mp.body_motion_smoothness(fine, 60.0, UP))
    assert 0.5 * at30 < at60 < 2.0 * at30
    assert float(mp.body_motion_smoothness(jitter(fine, 5.0), 60.0, UP)) > 10 * at60


def test_acceleration_penalty_of_a_parabola():
    t = torch.arange(10.0)[:, None, None] / FPS  # (T, 1, 1) seconds
    a = torch.tensor([[[1.0, -2.0, 0.5]], [[0.0, 3.0, 0.0]]]).transpose(0, 1)  # (1, 2, 3): two points
    points = 0.5 * a * t**2 + torch.tensor([0.3, 0.0, 1.0])  # (T, 2, 3)
    expected = (10 - 2) * float(a.pow(2).sum(-1).mean())  # sum over frames of the mean over points
    assert float(mp.acceleration_penalty(points, FPS)) == pytest.approx(expected, rel=1e-3)
    assert mp.acceleration_penalty(torch.stack([points, points]), FPS).shape == (2,)
