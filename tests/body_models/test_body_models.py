"""Body model layer: shapes, keypoint layout, hands, world transform, regions."""
import os

import numpy as np
import pytest
import torch

from intercap.body_models import NUM_BODY_HANDS, BodyParams, axis_angle_to_matrix, load_body_model
from intercap.body_models.keypoints import BODY_25, LEFT_HAND, RIGHT_HAND


@pytest.fixture(scope="module")
def anny_model():
    return load_body_model("anny")


def test_output_shapes_and_keypoint_count(anny_model):
    params = anny_model.init_params(3)
    out = anny_model(params)
    V = anny_model.num_vertices
    assert V == 13718
    assert out.vertices.shape == (3, V, 3)
    assert out.joints.shape == (3, len(anny_model.joint_names), 3)
    assert out.keypoints.shape == (3, NUM_BODY_HANDS, 3) == (3, 67, 3)
    assert anny_model.faces.shape[1] == 3 and int(anny_model.faces.max()) == V - 1
    assert torch.isfinite(out.vertices).all() and torch.isfinite(out.keypoints).all()


def test_keypoints_are_anatomically_placed(anny_model):
    kp = anny_model(anny_model.init_params(1)).keypoints[0]
    name = {n: i for i, n in enumerate(BODY_25)}
    z = kp[:, 2]
    assert z[name["nose"]] > z[name["neck"]] > z[name["mid_hip"]] > z[name["left_knee"]] > z[name["left_ankle"]]
    # anny faces -y with the person's left on +x.
    assert kp[name["left_shoulder"], 0] > 0.1 and kp[name["right_shoulder"], 0] < -0.1
    assert kp[name["nose"], 1] < kp[name["neck"], 1]
    # Hand keypoint 0 is the body wrist; fingertips lie beyond their knuckles from the wrist.
    assert torch.allclose(kp[LEFT_HAND][0], kp[name["left_wrist"]])
    for hand in (kp[LEFT_HAND], kp[RIGHT_HAND]):
        wrist = hand[0]
        for finger in range(5):
            base, tip = hand[1 + 4 * finger], hand[4 + 4 * finger]
            assert (tip - wrist).norm() > (base - wrist).norm()


def test_hand_keypoints_follow_finger_pose(anny_model):
    params = anny_model.init_params(2)
    anny_model.curl_fingers(params[1], "L", 1.0)  # indexing returns views: curl frame 1 in place
    out = anny_model(params)
    moved = (out.keypoints[1] - out.keypoints[0]).norm(dim=-1)
    left_tips = moved[LEFT_HAND][[4, 8, 12, 16, 20]]
    assert (left_tips > 0.02).all(), left_tips
    assert moved[RIGHT_HAND].max() < 1e-6
    assert moved[:25].max() < 1e-6
    # Curling moves fingertips towards the palm side, closing the hand.
    hand_open, hand_closed = out.keypoints[0][LEFT_HAND], out.keypoints[1][LEFT_HAND]
    spread = lambda h: (h[[8, 12, 16, 20]] - h[0]).norm(dim=-1).mean()
    assert spread(hand_closed) < spread(hand_open) - 0.02


def test_world_transform(anny_model):
    params = anny_model.init_params(1)
    base = anny_model(params)
    moved = params.clone()
    moved.transl[:] = torch.tensor([0.1, -0.2, 0.3])
    moved.global_orient[:] = torch.tensor([0.0, 0.0, np.pi / 2])
    out = anny_model(moved)
    R = axis_angle_to_matrix(moved.global_orient)[0]
    expected = base.vertices[0] @ R.T + moved.transl[0]
    assert torch.allclose(out.vertices[0], expected, atol=1e-5)


def test_shape_changes_body_and_params_round_trip(anny_model):
    params = anny_model.init_params(2)
    params.shape[1, 4] = 1.0  # height
    out = anny_model(params)
    height = out.vertices[..., 2].amax(1) - out.vertices[..., 2].amin(1)
    assert height[1] > height[0] + 0.05
    again = BodyParams.from_numpy_dict(params.to_numpy_dict())
    for a, b in zip(again.tensors().values(), params.tensors().values()):
        assert torch.equal(a, b)
    with pytest.raises(KeyError, match="expression"):
        BodyParams.from_numpy_dict({k: v for k, v in params.to_numpy_dict().items() if k != "expression"})


def test_contact_regions_are_where_contact_happens(anny_model):
    regions = anny_model.contact_regions
    assert set(regions) >= {"left_hand", "right_hand", "left_foot", "right_foot", "buttocks", "left_forearm", "right_forearm"}
    verts = anny_model(anny_model.init_params(1)).vertices[0]
    z = verts[:, 2]
    for name in ("left_foot", "right_foot"):
        sole = z[regions[name]]
        assert len(sole) > 50 and sole.mean() < z.min() + 0.05  # soles are the lowest surface
    assert verts[regions["left_hand"], 0].mean() > 0.35 and verts[regions["right_hand"], 0].mean() < -0.35
    # The palm region is on the side the fingers curl to: curling brings fingertips close to it.
    params = anny_model.init_params(1)
    anny_model.curl_fingers(params, "R", 1.3)
    closed = anny_model(params)
    tips = closed.keypoints[0][RIGHT_HAND][[8, 12, 16]]
    palm = closed.vertices[0][regions["right_hand"]]
    assert torch.cdist(tips, palm).min(1).values.max() < 0.02
    back = verts[regions["buttocks"]]
    assert len(back) > 50 and back[:, 1].mean() > 0.0  # behind the body (the body faces -y)
    sub = anny_model.fitting_subsample
    assert 1500 <= len(sub) <= 2500 and len(torch.unique(sub)) == len(sub)


def test_unknown_backend_and_missing_smplx_files_are_clear():
    with pytest.raises(ValueError, match="unknown body model"):
        load_body_model("mano")
    pytest.importorskip("smplx")
    with pytest.raises(FileNotFoundError, match="smplx_model_dir"):
        load_body_model("smplx", model_dir="/nonexistent/smplx")


@pytest.mark.skipif(not os.environ.get("SMPLX_MODEL_DIR"), reason="set SMPLX_MODEL_DIR to a folder with SMPL-X model files")
def test_smplx_backend_with_user_files():
    pytest.importorskip("smplx")
    model = load_body_model("smplx", model_dir=os.environ["SMPLX_MODEL_DIR"])
    params = model.init_params(2)
    out = model(params)
    assert out.vertices.shape == (2, 10475, 3)
    assert out.keypoints.shape == (2, 137, 3)
    params.right_hand_pose[1, :, 0] = 0.8
    moved = (model(params).keypoints[1] - out.keypoints[1]).norm(dim=-1)
    assert moved[RIGHT_HAND].max() > 0.01 and moved[LEFT_HAND].max() < 1e-6


def test_phenotype_interpolation_is_annys_on_the_anchors_device(anny_model):
    """anny's phenotype interpolation, replaced so that it makes nothing on the CPU for a GPU run
    (`interpolation_weights`): the same values and gradients as anny's own, in and outside the
    anchors, on the anchors and with extrapolation."""
    from intercap.body_models.anny_backend import ANNY_INTERPOLATION, interpolation_weights

    assert len(ANNY_INTERPOLATION) == 1
    g = torch.Generator().manual_seed(0)
    for anchors in (torch.tensor([0.0, 0.1875, 0.5, 1.0]), torch.linspace(0, 1, 3), torch.linspace(0, 1, 2)):
        for extrapolate in (False, True):
            value = torch.cat([torch.rand(40, generator=g) * 1.4 - 0.2, anchors]).requires_grad_(True)
            ours = interpolation_weights(value, anchors, extrapolate)
            annys = ANNY_INTERPOLATION[0](value, anchors, extrapolate)
            assert torch.equal(ours, annys)
            weight = torch.randn(ours.shape, generator=g)
            assert torch.equal(*(torch.autograd.grad((w * weight).sum(), value)[0] for w in (ours, annys)))


def test_phenotype_weights_are_annys_bit_for_bit(anny_model):
    """anny's phenotype blend weights made for every phenotype at once (`phenotype_weights`):
    anny's values and gradients bit for bit, for the model's labels and for all of anny's, inside,
    on and outside the anchors, clamped or extrapolated, in float32 and float64."""
    from anny.models.model_data import PHENOTYPE_LABELS
    from anny.models.phenotype import make_phenotype_anchors

    from intercap.body_models.anny_backend import ANNY_PHENOTYPE_WEIGHTS, phenotype_weights

    assert len(ANNY_PHENOTYPE_WEIGHTS) == 1
    core = anny_model.core
    g = torch.Generator().manual_seed(1)
    for dtype in (torch.float32, torch.float64):
        anchors = make_phenotype_anchors(dtype)
        mask = core.stacked_phenotype_blend_shapes_mask.to(dtype)
        for labels in (list(core.phenotype_labels), list(PHENOTYPE_LABELS)):
            on_anchors = torch.tensor([0.0, 0.5, 1.0, 1 / 3, 2 / 3, -1 / 3], dtype=dtype)
            values = torch.cat([torch.rand(30, len(labels), generator=g, dtype=dtype) * 1.6 - 0.3,
                                on_anchors[torch.randint(0, 6, (12, len(labels)), generator=g)]])
            for extrapolate in (False, True):
                ours_in, annys_in = values.clone().requires_grad_(True), values.clone().requires_grad_(True)
                ours = phenotype_weights(ours_in, labels, anchors, mask, extrapolate)
                annys = ANNY_PHENOTYPE_WEIGHTS[0](annys_in, labels, anchors, mask, extrapolate)
                assert ours.shape == annys.shape == (42, mask.shape[0])
                assert torch.equal(ours, annys)
                weight = torch.randn(ours.shape, generator=g, dtype=dtype)
                (ours * weight).sum().backward()
                (annys * weight).sum().backward()
                assert annys_in.grad.nan_to_num().abs().sum() > 0
                torch.testing.assert_close(ours_in.grad, annys_in.grad, rtol=0, atol=0, equal_nan=True)  # all races 0: NaN in both


def test_bone_transforms_are_annys_kinematics_in_the_world(anny_model):
    """Our forward kinematics (`bone_transforms`: pointer doubling, the world placement above the
    root) gives anny's bone frames and skinning transforms (`get_bone_transforms`, one level at a
    time) moved by the global orientation and translation, for random poses, shapes and placements."""
    from intercap.body_models.base import axis_angle_to_matrix

    g = torch.Generator().manual_seed(2)
    params = anny_model.init_params(4)
    for name in ("body_pose", "left_hand_pose", "right_hand_pose", "global_orient"):
        setattr(params, name, torch.randn(getattr(params, name).shape, generator=g) * 0.5)
    params.transl = torch.randn(4, 3, generator=g)
    params.shape = torch.rand(params.shape.shape, generator=g)
    rest = anny_model.rest_state(params, anny_model.fitting_subsample[:50])
    transforms, poses = anny_model.bone_transforms(params, rest)
    annys_transforms, annys_poses = anny_model.core.get_bone_transforms(anny_model.pose_matrices(params), rest.bones)
    place = torch.eye(4).repeat(4, 1, 1)
    place[:, :3, :3] = axis_angle_to_matrix(params.global_orient)
    place[:, :3, 3] = params.transl
    assert len(anny_model.bone_ancestors) == 5  # 17 levels and the placement: 2^5 >= 18
    torch.testing.assert_close(poses, place[:, None] @ annys_poses, rtol=0, atol=2e-6)
    torch.testing.assert_close(transforms, place[:, None] @ annys_transforms, rtol=0, atol=2e-6)


def test_axis_angle_to_matrix_is_rodrigues_everywhere():
    """`axis_angle_to_matrix` (Rodrigues' formula in few kernels) gives roma's matrices in float64 at
    every angle from 1e-3 to near pi, rotations (orthonormal, determinant 1), the generators as its
    gradient at zero, and float32 gradients within 2e-5 of float64's at every angle (roma's are 2e-4
    off near 1.6e-4 rad)."""
    import math

    import roma

    g = torch.Generator().manual_seed(3)
    directions = torch.nn.functional.normalize(torch.randn(60, 3, generator=g, dtype=torch.float64), dim=-1)
    angles = torch.tensor([1e-9, 1e-6, 1.6e-4, 1e-3, 0.1, 1.0, 2.5, math.pi - 1e-4], dtype=torch.float64)
    x = (directions[:, None] * angles[None, :, None]).reshape(-1, 3)
    big = angles.repeat(60) >= 1e-3
    R = axis_angle_to_matrix(x)
    assert torch.allclose(R[big], roma.rotvec_to_rotmat(x[big]), atol=1e-12)
    assert torch.allclose(R @ R.mT, torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(len(R), dtype=torch.float64), atol=1e-12)
    zero = torch.zeros(1, 3, dtype=torch.float64)
    jacobian = torch.autograd.functional.jacobian(axis_angle_to_matrix, zero)[0, :, :, 0]  # (3, 3, 3)
    skew = torch.stack([roma.rotvec_to_rotmat(e[None] * 1e-7)[0] - torch.eye(3, dtype=torch.float64)
                        for e in torch.eye(3, dtype=torch.float64)], -1) / 1e-7  # dR/dx at 0: the generators
    assert torch.allclose(jacobian, skew, atol=1e-6)
    w = torch.randn(len(x), 3, 3, generator=g, dtype=torch.float64)
    grads = {}
    for dtype in (torch.float64, torch.float32):
        leaf = x.to(dtype).requires_grad_(True)
        R = axis_angle_to_matrix(leaf)
        (grads[dtype],) = torch.autograd.grad((R * w.to(dtype)).sum(), leaf)
        assert torch.isfinite(grads[dtype]).all()
    assert torch.allclose(grads[torch.float32].double(), grads[torch.float64], atol=2e-5)


def test_the_cache_lock_lets_one_builder_in_at_a_time(tmp_path):
    """Two builders of a fresh anny cache (a run's workers, Ray tasks) take turns: the second enters
    only after the first left, so it loads the finished file instead of a half-written one."""
    import threading
    import time

    from intercap.body_models.anny_backend import cache_lock

    events = []

    def build(name):
        with cache_lock(tmp_path / "cache"):
            events.append((name, "in"))
            time.sleep(0.3)
            events.append((name, "out"))

    first = threading.Thread(target=build, args=("a",))
    first.start()
    time.sleep(0.1)
    second = threading.Thread(target=build, args=("b",))
    second.start()
    first.join()
    second.join()
    assert events == [("a", "in"), ("a", "out"), ("b", "in"), ("b", "out")]


def test_blend_shapes_are_read_as_anny_reads_them(anny_model):
    """`load_blend_shape` (one numpy pass; anny's cache build in 32 s instead of 2 min 50) gives
    anny's own offsets to the bit, an empty target file included."""
    from pathlib import Path

    import anny.models.full_model

    from intercap.body_models.anny_backend import ANNY_LOAD_BLEND_SHAPE, load_blend_shape

    assert anny.models.full_model.load_blend_shape is load_blend_shape and ANNY_LOAD_BLEND_SHAPE
    targets = Path(anny.models.full_model.__file__).parents[1] / "data" / "mpfb2" / "targets"
    files = [targets / "macrodetails" / "african-female-baby.target.gz",
             targets / "macrodetails" / "universal-male-baby-averagemuscle-averageweight.target.gz",  # empty
             *sorted((targets / "arms").glob("*.target.gz"))[:2]]

    class Scale:  # a world transformation: decimetres to metres
        def apply(self, v):
            return v * 0.1

    n = 20000  # at least the base mesh's vertex count, what anny passes
    for f in files:
        ours = load_blend_shape(f, n, Scale(), torch.float32)
        theirs = ANNY_LOAD_BLEND_SHAPE[0](f, n, Scale(), torch.float32)
        assert torch.equal(ours, theirs), f
    assert not torch.equal(ours, torch.zeros_like(ours))
