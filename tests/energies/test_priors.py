"""Priors: joint limits, extreme bending, hands, learned body-pose prior, shape and expression.

Uses only what ships in intercap/data (the anatomy frames and the learned mixture, whose npz
also holds a few held-out CMU poses); never the raw mocap."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from intercap.energies import priors

DEG = math.pi / 180.0


def rest_pose(batch: int = 1) -> torch.Tensor:
    return torch.zeros(batch, len(priors.ANNY_BODY_BONES), 3)


def pose(**angles) -> torch.Tensor:
    """Body pose from anatomical angles in degrees, keyword names with '_L'/'_R' for '.L'/'.R'."""
    return priors.body_pose_from_joint_angles({k.replace("_L", ".L").replace("_R", ".R"): v for k, v in angles.items()})


def angles_of(body_pose: torch.Tensor, row: str) -> np.ndarray:
    """Anatomical (flexion, abduction, twist) in degrees of one joint row."""
    a = priors.load_anatomy()
    r = a.row_names.index(row)
    return ((priors.joint_angles(body_pose)[:, r] + a.rest[r]) / DEG).detach().numpy()


WALKING = dict(
    hip_L=(25, 2, 0), hip_R=(-10, 2, 0), knee_L=(10, 0, 0), knee_R=(45, 0, 0), ankle_L=(-5, 0, 0),
    ankle_R=(15, 0, 0), shoulder_L=(-15, 10, 0), shoulder_R=(20, 10, 0), elbow_L=(20, 0, 0),
    elbow_R=(35, 0, 0), spine03=(3, 0, 0), neck02=(-3, 0, 0),
)


# -- shipped files ------------------------------------------------------------------

def test_shipped_files_load_and_are_small():
    assert priors.ANATOMY_FILE.stat().st_size < 100_000
    assert priors.POSE_PRIOR_FILE.stat().st_size < 1_000_000
    prior = priors.load_pose_prior()
    k, d = prior.means.shape
    assert 8 <= k <= 16 and d == len(priors.learned_feature_names())
    assert prior.precision_chol.shape == (k, d, d)
    assert float(prior.constants.min()) == 0.0 and torch.isfinite(prior.constants).all()
    assert len(priors.joint_angle_names()) == len(priors.load_anatomy().low)


def test_missing_prior_file_gives_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr(priors, "POSE_PRIOR_FILE", tmp_path / "nope.npz")
    priors.load_pose_prior.cache_clear()
    try:
        with pytest.raises(FileNotFoundError, match="nope.npz.*train_pose_prior"):
            priors.learned_pose_prior(rest_pose())
    finally:
        monkeypatch.undo()
        priors.load_pose_prior.cache_clear()


# -- joint limits ---------------------------------------------------------------------

def test_quaternion_product_is_roma_s_in_fewer_kernels():
    """The joint angles' composition (`priors.quat_product`): the Hamilton product (xyzw) of roma,
    values and gradients, as an outer product and one matrix product."""
    import roma
    from tools.count_ops import OperationCount

    generator = torch.Generator().manual_seed(0)
    p, q = (torch.randn(6, 5, 4, dtype=torch.float64, generator=generator) for _ in range(2))
    weights = torch.randn(6, 5, 4, dtype=torch.float64, generator=generator)
    results = {}
    for name, product in (("ours", priors.quat_product), ("roma", roma.quat_product)):
        a, b = p.clone().requires_grad_(True), q.clone().requires_grad_(True)
        with OperationCount() as count:
            out = product(a, b)
            (out * weights).sum().backward()
        results[name] = (out.detach(), a.grad, b.grad, count.kernels)
    for ours, theirs in zip(results["ours"][:3], results["roma"][:3]):
        torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-12)
    assert results["ours"][3] * 3 < results["roma"][3], (results["ours"][3], results["roma"][3])


def test_rest_pose_is_inside_every_limit():
    body = rest_pose(2)
    assert torch.equal(priors.joint_limit_penalty(body), torch.zeros(2))
    assert torch.equal(priors.extreme_bending(body), torch.zeros(2))
    hand = torch.zeros(2, 19, 3)
    assert torch.equal(priors.hand_pose_prior(hand, "L"), torch.zeros(2))
    assert torch.equal(priors.hand_pose_prior(hand, "R"), torch.zeros(2))


def test_angles_round_trip_through_the_pose_builder():
    wanted = {"knee.L": (60, 3, -10), "hip.R": (30, 10, 20), "shoulder.R": (90, 70, 40), "elbow.L": (90, 0, 30),
              "spine03": (10, -5, 8), "wrist.R": (-30, 10, 5)}
    body = priors.body_pose_from_joint_angles(wanted)
    for row, values in wanted.items():
        np.testing.assert_allclose(angles_of(body, row)[0], values, atol=1e-3)
    assert float(priors.joint_limit_penalty(body)) == 0.0


def test_normal_flexion_is_free_and_backward_bending_costs_the_squared_excess():
    assert float(priors.joint_limit_penalty(pose(knee_L=(120, 0, 0), elbow_R=(130, 0, 0), hip_L=(100, 0, 0)))) == 0.0
    # Knee range (-8, 160) deg; 40 deg backwards is 32 deg beyond: (32 deg)^2 in radians^2.
    knee_back = pose(knee_L=(-40, 0, 0))
    np.testing.assert_allclose(float(priors.joint_limit_penalty(knee_back)), (32 * DEG) ** 2, rtol=1e-3)
    np.testing.assert_allclose(float(priors.extreme_bending(knee_back)), (32 * DEG) ** 2, rtol=1e-3)
    # Elbow range (-10, 155) deg: hyperextended by 40 deg is 30 deg beyond; the right side mirrors the left.
    elbow_back = pose(elbow_R=(-40, 0, 0))
    np.testing.assert_allclose(float(priors.extreme_bending(elbow_back)), (30 * DEG) ** 2, rtol=1e-3)
    # A knee bent 30 deg sideways (range +-10).
    np.testing.assert_allclose(float(priors.extreme_bending(pose(knee_R=(20, 30, 0)))), (20 * DEG) ** 2, rtol=1e-2)
    # Relative to a normal pose the backward knee is expensive: gradient descent weights ~1 see it.
    assert float(priors.joint_limit_penalty(knee_back)) > 0.3


def test_real_held_out_mocap_poses_are_inside_the_limits():
    examples = torch.from_numpy(np.load(priors.POSE_PRIOR_FILE)["example_poses"])  # walking, uneven ground
    assert len(examples) >= 8
    assert float(priors.joint_limit_penalty(examples).max()) < 1e-3


def test_extreme_bending_only_looks_at_elbows_and_knees():
    neck = pose(neck02=(70, 0, 0))
    assert float(priors.joint_limit_penalty(neck)) > 0.3
    assert float(priors.extreme_bending(neck)) == 0.0


def test_second_bones_may_only_twist():
    body = rest_pose()
    i = priors.ANNY_BODY_BONES.index("lowerleg02.L")
    body[0, i] = torch.tensor([0.6, 0.0, 0.0])  # bending the shin in its middle
    assert float(priors.joint_limit_penalty(body)) > 0.1
    body[0, i] = torch.tensor([0.0, 0.0, 0.3])  # twisting it (about model z, roughly the shin): free
    assert float(priors.joint_limit_penalty(body)) < 1e-3


def test_gradient_descent_on_the_penalty_straightens_a_backward_knee():
    body = pose(knee_L=(-40, 0, 0), hip_R=(30, 0, 0)).requires_grad_(True)
    start = body.detach().clone()
    optimiser = torch.optim.Adam([body], lr=0.02)
    for _ in range(60):
        optimiser.zero_grad()
        loss = priors.joint_limit_penalty(body).sum()
        loss.backward()
        optimiser.step()
    knee = angles_of(body, "knee.L")[0]
    assert knee[0] > -8.5, knee  # back inside its range (-8, 160)
    assert float(priors.joint_limit_penalty(body.detach())) < 1e-4
    hip = priors.ANNY_BODY_BONES.index("upperleg01.R")
    torch.testing.assert_close(body[0, hip].detach(), start[0, hip])  # in-range joints untouched


def test_penalties_have_finite_gradients_at_rest():
    body = rest_pose().requires_grad_(True)
    hand = torch.zeros(1, 19, 3, requires_grad=True)
    total = priors.joint_limit_penalty(body) + priors.learned_pose_prior(body) + priors.hand_pose_prior(hand, "L")
    total.sum().backward()
    assert torch.isfinite(body.grad).all() and torch.isfinite(hand.grad).all()


# -- hands ----------------------------------------------------------------------------

def finger_angles(mcp: float, pip: float, dip: float, thumb=(20, 30, 30), twist: float = 0.0) -> torch.Tensor:
    """(1, 19, 3) degrees: the same curl on each finger, a thumb, the metacarpals at rest."""
    angles = torch.zeros(1, 19, 3)
    for k, name in enumerate(priors.HAND_BONES):
        if name.startswith("finger1"):
            angles[0, k, 0] = thumb[int(name[-1]) - 1]
        elif name.startswith("finger"):
            angles[0, k, 0] = {"1": mcp, "2": pip, "3": dip}[name[-1]]
            angles[0, k, 2] = twist
    return angles


@pytest.mark.parametrize("side", ["L", "R"])
def test_a_fist_is_human_and_fingers_bent_back_or_twisted_are_not(side):
    fist = priors.hand_pose_from_angles(finger_angles(85, 100, 67), side)
    np.testing.assert_allclose(priors.hand_angles(fist, side)[0, 5, 0] / DEG, 100, atol=1e-3)  # finger2-2
    open_hand = torch.zeros(1, 19, 3)
    bent_back = priors.hand_pose_from_angles(finger_angles(-60, -60, -60, thumb=(0, 0, 0)), side)
    twisted = priors.hand_pose_from_angles(finger_angles(20, 30, 20, twist=45), side)
    fist_score = float(priors.hand_pose_prior(fist, side))
    assert fist_score < 0.01
    assert float(priors.hand_pose_prior(open_hand, side)) == 0.0
    assert float(priors.hand_pose_prior(bent_back, side)) > 1.0
    assert float(priors.hand_pose_prior(twisted, side)) > 1.0


def test_both_hands_in_one_batch_score_as_each_hand_alone():
    """`hands_pose_prior` mirrors the right hand into the left's convention: the same value and
    gradients as the two one-sided priors added."""
    g = torch.Generator().manual_seed(3)
    left = (torch.randn(4, 19, 3, generator=g) * 0.6).requires_grad_(True)
    right = (torch.randn(4, 19, 3, generator=g) * 0.6).requires_grad_(True)
    alone = priors.hand_pose_prior(left, "L") + priors.hand_pose_prior(right, "R")
    assert float(alone.min()) > 0  # random hands break some limit: the comparison is not of zeros
    expected = torch.autograd.grad(alone.sum(), (left, right))
    together = priors.hands_pose_prior(left, right)
    assert torch.allclose(together, alone, rtol=1e-5)
    for got, want in zip(torch.autograd.grad(together.sum(), (left, right)), expected):
        assert torch.allclose(got, want, rtol=1e-4, atol=1e-6)


def test_pose_priors_in_one_pass_are_each_prior_apart():
    """`pose_priors` (every pose prior from one pass over the rotations) gives each prior's value
    and gradients to rounding (vectorised math rounds by the position in a tensor), only the terms
    asked for, in float32 and float64."""
    g = torch.Generator().manual_seed(5)
    for dtype in (torch.float32, torch.float64):
        body, left, right = ((torch.randn(6, n, 3, generator=g, dtype=dtype) * 0.6).requires_grad_(True)
                             for n in (65, 19, 19))
        apart = {"pose_prior": priors.learned_pose_prior(body), "joint_limits": priors.joint_limit_penalty(body),
                 "bending": priors.extreme_bending(body), "hand_prior": priors.hands_pose_prior(left, right)}
        assert all(float(v.min()) > 0 for v in apart.values())  # random poses break limits: no zeros compared
        together = priors.pose_priors(body, left, right, priors.POSE_PRIOR_TERMS)
        assert list(together) == list(apart)
        for term, value in apart.items():
            torch.testing.assert_close(together[term], value, rtol=1e-6, atol=0)
            want = torch.autograd.grad(value.sum(), (body, left, right), allow_unused=True, retain_graph=True)
            got = torch.autograd.grad(together[term].sum(), (body, left, right), allow_unused=True, retain_graph=True)
            for a, b in zip(got, want):
                assert (a is None) == (b is None) or float((a if b is None else b).abs().max()) == 0, term
                if a is not None and b is not None:
                    torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6 * float(b.abs().max()))
        assert list(priors.pose_priors(body, left, right, ("bending", "keypoints"))) == ["bending"]


def test_dip_following_pip_is_cheaper_than_dip_without_pip():
    follows = priors.hand_pose_from_angles(finger_angles(30, 60, 40), "L")
    alone = priors.hand_pose_from_angles(finger_angles(30, 0, 40), "L")
    assert float(priors.hand_pose_prior(follows, "L")) < 0.2 * float(priors.hand_pose_prior(alone, "L"))


# -- learned prior ----------------------------------------------------------------------

def test_learned_prior_ranks_real_poses_above_random_ones():
    examples = torch.from_numpy(np.load(priors.POSE_PRIOR_FILE)["example_poses"])  # held-out CMU frames
    walking = pose(**WALKING)
    gen = torch.Generator().manual_seed(0)
    a = priors.load_anatomy()
    kinds = ("spine0", "neck0", "shoulder", "elbow", "wrist", "hip", "knee", "ankle")  # bones, not chain totals
    major = [r for r, j in enumerate(a.row_joints) if j.rstrip("12345").startswith(kinds)]
    random_angles = {
        a.row_names[r]: (a.low[r] + torch.rand(200, 3, generator=gen) * (a.high[r] - a.low[r])) / DEG for r in major
    }
    random = priors.body_pose_from_joint_angles(random_angles, batch_size=200, anatomical=False)
    random = random[priors.joint_limit_penalty(random) == 0]  # drop swings past 180 deg (shoulders)
    assert len(random) > 100  # random, yet inside every limit
    real = priors.learned_pose_prior(examples)
    fake = priors.learned_pose_prior(random)
    assert float(real.max()) < float(fake.quantile(0.05))
    assert float(priors.learned_pose_prior(walking)) < float(fake.quantile(0.05))
    assert float(priors.learned_pose_prior(rest_pose())) < float(fake.min())


def test_learned_features_of_a_mirrored_pose_are_the_mirrored_features():
    body = pose(**WALKING) + 0.05 * torch.randn(1, 65, 3, generator=torch.Generator().manual_seed(1))
    mirrored = priors.mirror_body_pose(body)
    hip_l, hip_r = priors.ANNY_BODY_BONES.index("upperleg01.L"), priors.ANNY_BODY_BONES.index("upperleg01.R")
    torch.testing.assert_close(mirrored[0, hip_l], body[0, hip_r] * torch.tensor(priors.MIRROR))
    torch.testing.assert_close(priors.learned_features(mirrored), priors.mirror_features(priors.learned_features(body)),
                               atol=1e-5, rtol=1e-4)


def test_gradient_of_the_learned_prior_pulls_a_noisy_pose_towards_plausible():
    body = pose(**WALKING) + 0.4 * torch.randn(1, 65, 3, generator=torch.Generator().manual_seed(3))
    body.requires_grad_(True)
    start = float(priors.learned_pose_prior(body.detach()))
    optimiser = torch.optim.Adam([body], lr=0.01)
    for _ in range(30):
        optimiser.zero_grad()
        priors.learned_pose_prior(body).sum().backward()
        optimiser.step()
    assert float(priors.learned_pose_prior(body.detach())) < 0.5 * start


# -- shape and expression ------------------------------------------------------------------

def test_shape_prior_is_zero_at_the_average_and_grows_outside_the_unit_box():
    assert float(priors.shape_prior(torch.full((1, 6), 0.5))) == 0.0
    inside = priors.shape_prior(torch.tensor([[0.9, 0.5, 0.5, 0.5, 0.5, 0.5]]))
    outside = priors.shape_prior(torch.tensor([[1.2, 0.5, 0.5, 0.5, 0.5, 0.5]]))
    np.testing.assert_allclose(float(inside), 0.1 * 0.4**2, rtol=1e-5)
    np.testing.assert_allclose(float(outside), 0.2**2 + 0.1 * 0.7**2, rtol=1e-5)


def test_expression_prior_is_l2_plus_the_unit_box():
    assert float(priors.expression_prior(torch.zeros(1, 52))) == 0.0
    e = torch.zeros(1, 52)
    e[0, 3] = 0.5
    np.testing.assert_allclose(float(priors.expression_prior(e)), 0.25, rtol=1e-6)
    e[0, 3] = -0.5
    np.testing.assert_allclose(float(priors.expression_prior(e)), 0.25 + 10 * 0.25, rtol=1e-6)


# -- agreement with the body model ----------------------------------------------------------

@pytest.fixture(scope="module")
def anny():
    from intercap.body_models import load_body_model

    return load_body_model("anny")


def test_shipped_anatomy_matches_the_model(anny):
    assert list(anny.body_joint_names) == list(priors.ANNY_BODY_BONES)
    assert list(anny.hand_joint_names) == list(priors.HAND_BONES)
    measured = priors.anatomy_from_model(anny)
    shipped = np.load(priors.ANATOMY_FILE)
    for key in ("body_frames", "body_signs", "body_rest", "hand_frames", "hand_signs"):
        np.testing.assert_allclose(measured[key], shipped[key], atol=1e-4, err_msg=key)


def test_positive_angles_move_limbs_the_anatomical_way(anny):
    index = {b: i for i, b in enumerate(anny.joint_names)}

    def moved(body_pose, bone):
        p = anny.init_params(1)
        p.body_pose = body_pose
        with torch.no_grad():
            return (anny(p).joints[0, index[bone]] - anny(anny.init_params(1)).joints[0, index[bone]]).numpy()

    assert moved(pose(hip_L=(45, 0, 0)), "lowerleg01.L")[1] < -0.1  # thigh forward (-y)
    assert moved(pose(hip_R=(0, 30, 0)), "lowerleg01.R")[0] < -0.1  # right leg out (-x)
    assert moved(pose(knee_L=(90, 0, 0)), "foot.L")[1] > 0.2  # foot backwards (+y)
    assert moved(pose(shoulder_R=(90, 0, 0)), "lowerarm01.R")[1] < -0.1  # arm forward
    assert moved(pose(spine03=(30, 0, 0)), "head")[1] < -0.1  # bend forward
    up = moved(pose(elbow_L=(130, 0, 0)), "wrist.L")
    assert up[2] > 0.15  # the forearm folds up towards the shoulder


def test_hand_curl_sign_agrees_with_the_model(anny):
    for side in ("L", "R"):
        p = anny.init_params(1)
        anny.curl_fingers(p, side, 0.8)
        hand = p.left_hand_pose if side == "L" else p.right_hand_pose
        curl = priors.hand_angles(hand, side)[0, :, 0]
        fingers = [k for k, n in enumerate(priors.HAND_BONES) if n.startswith("finger") and not n.startswith("finger1")]
        np.testing.assert_allclose(curl[fingers].numpy(), 0.8, atol=5e-3)


# -- the CMU reader behind the learned prior (a tiny hand-written skeleton) ---------------------

TINY_ASF = """:version 1.10
:name tiny
:units
  mass 1.0
  length 0.45
  angle deg
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name lfemur
     direction 1 0 0
     length 4.5
     axis 0 0 0  XYZ
    dof rx ry rz
    limits (-180.0 180.0)
           (-180.0 180.0)
           (-180.0 180.0)
  end
  begin
     id 2
     name ltibia
     direction 1 0 0
     length 4.5
     axis 0 0 90  XYZ
    dof rx
    limits (-10.0 170.0)
  end
:hierarchy
  begin
    root lfemur
    lfemur ltibia
  end
"""
TINY_AMC = """:FULLY-SPECIFIED
:DEGREES
1
root 0 0 0 0 0 0
lfemur 0 0 0
ltibia 0
2
root 4.5 0 0 0 0 90
lfemur 0 0 0
ltibia 90
3
root 0 0 0 0 0 0
lfemur 0 0 0
ltibia 250
"""


def test_cmu_reader_forward_kinematics_and_glitches(tmp_path):
    from tools import cmu_mocap

    (tmp_path / "t.asf").write_text(TINY_ASF)
    (tmp_path / "t.amc").write_text(TINY_AMC)
    skeleton, motion = cmu_mocap.load_clip(tmp_path / "t.asf", tmp_path / "t.amc")
    assert list(skeleton.bones) == ["lfemur", "ltibia"] and skeleton.bones["ltibia"].parent == "lfemur"
    names, ends, _ = cmu_mocap.forward_kinematics(skeleton, motion)
    unit = 4.5 * 0.0254 / 0.45  # 4.5 units of 0.45 inch = 0.254 m
    np.testing.assert_allclose(ends[0, names.index("ltibia")], [2 * unit, 0, 0], atol=1e-9)
    # Frame 2: root moved by one bone length and turned 90 deg about z; the tibia bends 90 deg
    # about its dof axis (world y at rest), so it points down.
    np.testing.assert_allclose(ends[1, names.index("lfemur")], [unit, unit, 0], atol=1e-9)
    np.testing.assert_allclose(ends[1, names.index("ltibia")], [unit, unit, -unit], atol=1e-9)
    np.testing.assert_array_equal(cmu_mocap.glitch_frames(skeleton, motion), [False, False, True])  # 250 = -110 deg
