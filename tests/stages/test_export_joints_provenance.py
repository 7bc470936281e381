"""The dataset file's joints, keypoints and provenance, and the BEHAVE pkl of a take as long as
the shape vector (the sample's results from its ground truth, no fitting)."""
import hashlib
import pickle

import numpy as np
import pytest
import torch
from conftest import SAMPLE_SESSION

import intercap
from intercap.body_models import BodyParams, load_body_model
from intercap.body_models.keypoints import KEYPOINT_NAMES
from intercap.config import load_config
from intercap.pipeline import run_pipeline
from intercap.session import Session
from intercap.stages.export import stage as export
from stages.test_export import GT, NAN_BODY, write_results


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = write_results(tmp_path_factory.mktemp("export") / "out")
    cfg = load_config(None, ["export.meshes=false", "export.glb=false"])
    run_pipeline(SAMPLE_SESSION, out, cfg, stages=["export"], progress=False)
    with np.load(out / "export" / "sample.npz") as z:
        return out, {k: z[k] for k in z.files}


def test_joints3d_are_the_body_models_joints_of_the_fit(dataset):
    _, data = dataset
    model = load_body_model("anny")
    params = dict(np.load(GT / "body_params.npz"))
    with torch.no_grad():
        joints = model(BodyParams.from_numpy_dict(params)).joints.numpy()
    assert data["joints3d"].shape == joints.shape and data["joints3d"].dtype == np.float32
    ok = np.arange(len(joints)) != NAN_BODY
    assert np.abs(data["joints3d"][ok] - joints[ok]).max() < 1e-5
    assert np.isnan(data["joints3d"][NAN_BODY]).all()
    assert list(data["joint_names"]) == list(model.joint_names)


def test_keypoints3d_carry_their_names(dataset):
    _, data = dataset
    truth = np.load(GT / "keypoints3d.npy")
    assert data["keypoints3d"].shape == truth.shape == (30, 67, 3)
    assert np.array_equal(data["keypoints3d"][0], truth[0].astype(np.float32))
    assert list(data["keypoint_names"]) == KEYPOINT_NAMES[:67]
    assert data["keypoint_names"][25] == "left_hand_wrist"


def test_provenance(dataset):
    out, data = dataset
    from importlib import metadata

    assert str(data["intercap_version"]) == intercap.__version__
    assert str(data["torch_version"]) == torch.__version__
    assert str(data["body_model_version"]) == f"anny {metadata.version('anny')}"
    assert str(data["config_hash"]) == hashlib.sha256((out / "config.yaml").read_bytes()).hexdigest()[:16]
    assert str(data["command_line"]) and str(data["session_name"]) == "sample"


def test_behave_pkl_keeps_shape_mean_whole_when_frames_equal_the_shape_count(tmp_path):
    """anny has 6 shape parameters: a 6-frame take's shape_mean (6,) is not a per-frame array."""
    session = Session.load(SAMPLE_SESSION)
    session.restrict_frames(0, 5)
    T = session.num_frames
    params = dict(np.load(GT / "body_params.npz"))
    assert params["shape"].shape[1] == T
    out = write_results(tmp_path / "full")
    res = export.load_results(out, 30)
    res["body_vertices"] = np.asarray(res["body_vertices"])[:T]
    res["object"] = {k: v[:T] for k, v in res["object"].items()}
    shape_mean = params["shape"][:T].mean(0).astype(np.float32)
    res["body_params"] = {**{k: (v[:T] if v.ndim else v) for k, v in params.items()}, "shape_mean": shape_mean}
    export.write_behave(session, res, tmp_path, progress=False)
    seq = tmp_path / "export" / "behave" / "sequences" / "sample"
    for i in (0, 4):
        with open(seq / f"t{i / 5:08.3f}" / "person" / "fit02" / "person_fit.pkl", "rb") as f:
            fit = pickle.load(f)
        assert fit["shape_mean"].shape == (6,) and np.array_equal(fit["shape_mean"], shape_mean)
        assert np.array_equal(fit["betas"], params["shape"][i])
