"""The Parkour benchmark's plumbing without the dataset: a still anny body standing on the floor and the
same body hanging from its hands, written as Parkour clips (16 joints, measured wrenches), fitted and
analysed by tools/bench_parkour: the stage's forces come back as the dataset's wrenches on the person."""
import numpy as np
import pytest

from intercap.config import Config
from intercap.stages.physics import stage as physics
from tools import bench_parkour
from tools import parkour_fit as pk

T, MASS, G = 12, 70.0, 9.81


@pytest.fixture(scope="module")
def rest_joints():
    """(16, 3) the default anny body's Parkour joints at rest, its lowest vertex on the floor."""
    model = pk.default_model()
    vertices, bones = physics.rest_body(model, model.init_params(1).shape[0].numpy())
    names = list(model.joint_names)
    joints = bones[[names.index(b) for b in pk.ANNY_BONES.values()], :3, 3]
    return joints - [0, 0, vertices[:, 2].min()]


def clip_of(joints, wrenches, name):
    return pk.Clip(name, "test", 25.0, np.tile(joints, (T, 1, 1)), np.tile(wrenches, (T, 1, 1)), np.zeros((T, 4), bool))


@pytest.mark.parametrize("case", ["standing", "hanging"])
def test_the_benchmark_returns_the_forces_on_the_person(tmp_path, rest_joints, case):
    W = MASS * G
    wrenches = np.zeros((4, 6))
    if case == "standing":
        wrenches[:2, 2] = W / 2  # the floor pushes each foot up
        joints = rest_joints
    else:
        wrenches[2:, 2] = W / 2  # the bar holds each hand up, the feet 40 cm off the floor
        joints = rest_joints + [0, 0, 0.4]
    clip = clip_of(joints, wrenches, case)
    row = bench_parkour.bench_clip(clip, pk.default_model(), tmp_path, MASS, Config())
    assert row["body_mass_kg"] == MASS and row["fit_mpjpe_mm"] < 30
    linear = np.array(row["sensors"]["linear_n"])
    loaded = [0, 1] if case == "standing" else [2, 3]
    assert np.all(linear[loaded] < 0.1 * W), linear  # each within a tenth of the body weight
    assert row["sensors"]["residual_pct_bw"] < 2.0


def test_a_pull_up_clip_beats_the_published_force_errors(tmp_path):
    """On the dataset (PARKOUR_DATA), clip pu02_PKLP with Li et al.'s 74.6 kg body: with the contact timing
    of the sensors and with our own, every contact's mean linear force error is below Li et al.'s (their
    forces come from video, ours from the mocap: the bar is lower for them)."""
    import os

    if not os.environ.get("PARKOUR_DATA"):
        pytest.skip("PARKOUR_DATA is not set (a local copy of the LAAS Parkour dataset)")
    try:
        clip = pk.load_clips(os.environ["PARKOUR_DATA"])["pu02_PKLP"]
    except ValueError as exc:
        pytest.skip(str(exc))
    row = bench_parkour.bench_clip(clip, pk.default_model(), tmp_path, 74.6, Config())
    for how in ("sensors", "motion"):
        assert np.all(np.array(row[how]["linear_n"]) < bench_parkour.LI_FORCE_N), (how, row[how])
