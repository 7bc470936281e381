"""tools/parkour_fit: the LAAS Parkour benchmark's force errors, contact timing and anny fit.

Tests on the dataset skip unless PARKOUR_DATA names a local copy of it (the folder holding
gt_motion_forces/, or that folder itself); the others need no data."""
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from tools import parkour_fit as pk


def data_dir() -> Path:
    root = os.environ.get("PARKOUR_DATA")
    if not root:
        pytest.skip("PARKOUR_DATA is not set (a local copy of the LAAS Parkour dataset)")
    for folder in (Path(root) / "gt_motion_forces", Path(root)):
        if all((folder / name).is_file() for name in pk.FILES):
            return folder
    pytest.skip(f"PARKOUR_DATA={root} holds no {' / '.join(pk.FILES)}")


@pytest.fixture(scope="module")
def clips():
    return pk.load_clips(data_dir())


def tiny_clip(T: int = 5) -> pk.Clip:
    """T frames of still joints; the left foot's force 3-4-0 N and moment 0-0-2 N m in every frame, the
    right hand's force 0-6-8 N; the left foot uncaptured in frame 1 (its stored value then reads 0)."""
    forces = np.zeros((T, 4, 6))
    forces[:, 0, :3], forces[:, 0, 5], forces[:, 3, 1:3] = [3.0, 4.0, 0.0], 2.0, [6.0, 8.0]
    uncaptured = np.zeros((T, 4), bool)
    uncaptured[1, 0] = True
    forces[1, 0] = 0.0
    return pk.Clip("tiny", "test", 25.0, np.zeros((T, 16, 3)), forces, uncaptured)


def test_force_errors_by_hand():
    clip = tiny_clip()
    pred = np.zeros((5, 4, 6))
    pred[:, 0, 0] = 3.0  # left foot: x right, y short by 4 N
    pred[1, 0, 0] = 100.0  # the uncaptured frame: not counted
    pred[3:, 3, 1] = 1000.0  # right hand: wrong only in the last 2 frames, which the evaluator leaves out
    errors = pk.force_errors(pred, clip)
    # frames 0..1 count (T - 3 = 2), frame 1 uncaptured for the left foot: its one frame errs by 4 N, 2 N m
    assert errors["linear_n"] == pytest.approx([4.0, 0.0, 0.0, 10.0])
    assert errors["moment_nm"] == pytest.approx([2.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="tiny"):
        pk.force_errors(np.zeros((5, 4, 3)), clip)


def test_missing_dataset_names_the_path(tmp_path):
    with pytest.raises(ValueError, match=str(tmp_path)):
        pk.load_clips(tmp_path)


def test_sensor_contacts_close_one_frame_gaps():
    clip = tiny_clip(8)
    clip.forces[:, 2, 2] = [0, 30, 0, 30, 30, 0, 0, 30]  # left hand: one gap of 1 frame, one of 2
    on = pk.sensor_contacts(clip)
    assert on[:, 2].tolist() == [False, True, True, True, True, False, False, True]
    assert not on[:, 0].any() and not on[:, 3].any()  # 5 N and 10 N: below the 20 N threshold
    clip.forces[:, 0, :3] *= 10  # 50 N but in the uncaptured frame 1: a 1-frame gap, closed
    clip.uncaptured[5:7, 0], clip.forces[5:7, 0] = True, 0.0  # 2 uncaptured frames: they stay off
    assert pk.sensor_contacts(clip)[:, 0].tolist() == [True, True, True, True, True, False, False, True]


def test_motion_contacts_hand_on_a_bar_and_a_planted_foot():
    """A body rising 0.5 m in one second while the fingers stay on a bar at 2 m and the left foot rests on
    the floor: both hands hold, the left foot is down; the same pose held still is no hand contact."""
    T = 25
    joints = np.zeros((T, 16, 3))
    rise = np.linspace(0.0, 0.5, T)[:, None]
    joints[:] = np.linspace([0, 0, 0.05], [0, 0, 2.0], 16)  # a column of joints
    joints[:, [0, 4, 8, 12], 2] += rise  # hips and shoulders rise
    joints[:, [11, 15], 2] = 2.0  # fingers on the bar
    joints[:, 3, 2] = 0.03  # left toes on the floor
    joints[:, 7, 2] = 0.6 + rise[:, 0]  # right foot lifted with the body
    joints[:, 6, 2] = 0.7 + rise[:, 0]
    on = pk.motion_contacts(joints, 25.0)
    assert on[:, 0].all() and not on[:, 1].any() and on[:, 2:].all()
    still = np.repeat(joints[:1], T, 0)
    assert not pk.motion_contacts(still, 25.0)[:, 2:].any() and pk.motion_contacts(still, 25.0)[:, 0].all()


def test_bone_chain_is_the_models_kinematics():
    """The fit's restricted chain gives the bone heads the physics stage reads from anny's core."""
    from intercap.body_models import axis_angle_to_matrix

    model = pk.default_model()
    T = 4
    params = model.init_params(T)
    fitted = [model.body_joint_names.index(b) for b in pk.FIT_BONES]
    bones = [model.joint_names.index(b) for b in pk.ANNY_BONES.values()]
    generator = torch.Generator().manual_seed(0)
    params.body_pose[:, fitted] = 0.4 * torch.randn(T, len(fitted), 3, generator=generator)
    params.global_orient[:] = torch.randn(T, 3, generator=generator)
    params.transl[:] = torch.randn(T, 3, generator=generator)
    params.shape[:] = torch.rand(1, model.num_shape, generator=generator)
    rest = model.rest_state(params[0], model.fitting_subsample[:1])
    _, heads = pk.BoneChain(model, bones, fitted)(params.global_orient, params.transl, params.body_pose[:, fitted],
                                                  rest.offsets[0, :, :3, 3])
    out = model.core(model.pose_matrices(params), phenotype_kwargs=params.shape, facial_actions=params.expression)
    rotation = axis_angle_to_matrix(params.global_orient)
    world = torch.einsum("bij,bkj->bki", rotation, out["bone_poses"][:, bones, :3, 3]) + params.transl[:, None]
    assert torch.allclose(heads, world, atol=1e-5)


def test_ground_truth_scores_zero_and_zeros_score_the_force_magnitudes(clips):
    for clip in clips.values():
        zero = pk.force_errors(clip.forces, clip)
        assert np.all(zero["linear_n"] == 0) and np.all(zero["moment_nm"] == 0), clip.name
        errors = pk.force_errors(np.zeros_like(clip.forces), clip)
        for k in range(4):  # the mean magnitude over the evaluated (first T - 3) captured frames
            frames = [t for t in range(clip.num_frames - 3) if not clip.uncaptured[t, k]]
            linear = [np.sqrt(sum(clip.forces[t, k, i] ** 2 for i in range(3))) for t in frames]
            moment = [np.sqrt(sum(clip.forces[t, k, i] ** 2 for i in range(3, 6))) for t in frames]
            assert errors["linear_n"][k] == pytest.approx(np.mean(linear), rel=1e-12), (clip.name, k)
            assert errors["moment_nm"][k] == pytest.approx(np.mean(moment), rel=1e-12, abs=1e-12), (clip.name, k)


def test_clips_load(clips):
    assert len(clips) == 28
    clip = clips["pu02_PKLP"]
    assert clip.action == "pull-up" and clip.fps == 25.0 and clip.joints.shape == (135, 16, 3)
    assert clip.forces.shape == (135, 4, 6) and clip.uncaptured.dtype == bool and clip.uncaptured.any()
    assert {c.action for c in clips.values()} == set(pk.ACTIONS.values())


def test_fit_anny_on_a_pull_up(clips):
    """The first 20 frames of a pull-up within 40 mm; the returned parameters reproduce the fitted joints
    through anny's own forward (bone heads plus the fitted offsets in the bones' frames)."""
    from intercap.body_models import axis_angle_to_matrix

    joints = clips["pu02_PKLP"].joints[:20]
    model = pk.default_model()
    params, fitted, info = pk.fit_anny(joints, 25.0, model=model)
    assert fitted.shape == (20, 16, 3) and params.batch_size == 20
    mpjpe = 1000 * np.linalg.norm(fitted - joints, axis=-1).mean()
    assert mpjpe < 40 and info["mpjpe_mm"] == pytest.approx(mpjpe)
    assert info["pa_mpjpe_mm"] <= mpjpe + 1.0 and info["seconds_per_frame"] > 0
    bones = [model.joint_names.index(b) for b in pk.ANNY_BONES.values()]
    with torch.no_grad():
        out = model.core(model.pose_matrices(params), phenotype_kwargs=params.shape, facial_actions=params.expression)
    frames = out["bone_poses"][:, bones].double()
    rotation = axis_angle_to_matrix(params.global_orient.double())
    heads = torch.einsum("bij,bkj->bki", rotation, frames[..., :3, 3]) + params.transl.double()[:, None]
    turned = rotation[:, None] @ frames[..., :3, :3]
    again = heads + (turned @ torch.as_tensor(info["offsets_m"])[:, :, None])[..., 0]
    assert np.abs(again.numpy() - fitted).max() < 1e-4
