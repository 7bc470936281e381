"""Our SMPL-X parameters in smplx's own convention: smplx rotates the body about the rest pelvis and
then adds transl; we rotate about the model origin. `SmplxBody.smplx_parameters` must give smplx's
forward the arguments that reproduce our vertices.

Against the `smplx` package itself (a test dependency) on a model file each test run writes with random
weights in SMPL-X's layout (10,475 vertices, 55 joints, 10 shape and 10 expression directions, hand
components, face landmarks): no real model files are needed."""
import numpy as np
import pytest
import torch
from conftest import SAMPLE_SESSION

from intercap.body_models.base import axis_angle_to_matrix
from intercap.body_models.smplx_backend import SmplxBody, smplx_transl

smplx = pytest.importorskip("smplx")

# SMPL-X's kinematic tree: 22 body joints, jaw and eyes under the head, 15 joints per hand under the wrist
PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15]
for wrist in (20, 21):
    for finger in range(5):
        base = len(PARENTS)
        PARENTS += [wrist, base, base + 1]
V, FACES, BETAS, EXPR = 10475, 20000, 10, 10


def write_random_smplx(folder, seed=0):
    """SMPLX_NEUTRAL.npz with random weights in SMPL-X's layout; its path."""
    rng = np.random.default_rng(seed)
    J = len(PARENTS)
    regressor = rng.random((J, V)) ** 40
    weights = np.exp(3 * rng.normal(size=(V, J)))
    path = folder / "SMPLX_NEUTRAL.npz"
    np.savez(path, v_template=rng.uniform([-0.25, -1.1, -0.15], [0.25, 0.6, 0.15], (V, 3)),
             f=rng.integers(0, V, (FACES, 3)), J_regressor=regressor / regressor.sum(1, keepdims=True),
             weights=weights / weights.sum(1, keepdims=True), kintree_table=np.array([PARENTS, list(range(J))]),
             shapedirs=rng.normal(0, 0.01, (V, 3, BETAS + EXPR)),
             posedirs=rng.normal(0, 0.001, (V, 3, (J - 1) * 9)).astype(np.float32),
             hands_componentsl=np.eye(45), hands_componentsr=np.eye(45), hands_meanl=np.zeros(45),
             hands_meanr=np.zeros(45), lmk_faces_idx=rng.integers(0, FACES, 51), lmk_bary_coords=np.full((51, 3), 1 / 3))
    return path


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """(our backend, smplx's own model) on one random model file, float64."""
    path = write_random_smplx(tmp_path_factory.mktemp("smplx"))
    ours = SmplxBody(path.parent, dtype=torch.float64)
    theirs = smplx.create(str(path), model_type="smplx", use_pca=False, flat_hand_mean=True, num_betas=BETAS,
                          num_expression_coeffs=EXPR, use_face_contour=False).to(torch.float64)
    return ours, theirs


def random_params(model, B=4, seed=1):
    g = torch.Generator().manual_seed(seed)
    p = model.init_params(B, dtype=torch.float64)
    p.body_pose = torch.randn(B, 24, 3, generator=g, dtype=torch.float64) * 0.3
    p.left_hand_pose = torch.randn(B, 15, 3, generator=g, dtype=torch.float64) * 0.3
    p.right_hand_pose = torch.randn(B, 15, 3, generator=g, dtype=torch.float64) * 0.3
    p.shape = torch.randn(B, BETAS, generator=g, dtype=torch.float64)
    p.expression = torch.randn(B, EXPR, generator=g, dtype=torch.float64)
    p.global_orient = torch.randn(B, 3, generator=g, dtype=torch.float64) * 1.5
    p.transl = torch.randn(B, 3, generator=g, dtype=torch.float64)
    return p


def test_smplx_arguments_reproduce_our_vertices(models):
    model, core = models
    params = random_params(model)
    ours = model(params)
    with torch.no_grad():
        theirs = core(**model.smplx_parameters(params), return_verts=True)
    assert torch.allclose(theirs.vertices, ours.vertices, atol=1e-7)  # the file's pose blend shapes are float32
    assert torch.allclose(theirs.joints[:, :55], ours.joints, atol=1e-7)
    # our own transl given to smplx misses by the rotated pelvis offset: the correction matters
    with torch.no_grad():
        naive = core(**{**model.smplx_parameters(params), "transl": params.transl}, return_verts=True)
    assert (naive.vertices - ours.vertices).norm(dim=-1).min() > 1e-3


def test_smplx_transl_is_the_pelvis_correction():
    g = torch.Generator().manual_seed(3)
    orient, transl, pelvis = (torch.randn(5, 3, generator=g, dtype=torch.float64) for _ in range(3))
    R = axis_angle_to_matrix(orient)
    points = torch.randn(5, 7, 3, generator=g, dtype=torch.float64)
    ours = points @ R.transpose(1, 2) + transl[:, None]
    theirs = (points - pelvis[:, None]) @ R.transpose(1, 2) + pelvis[:, None] + smplx_transl(orient, transl, pelvis)[:, None]
    assert torch.allclose(ours, theirs, atol=1e-12)
    assert torch.allclose(smplx_transl(torch.zeros(5, 3, dtype=torch.float64), transl, pelvis), transl)


def test_export_writes_smplx_arguments_that_reproduce_the_results(models, monkeypatch):
    """The export's smplx_* arrays (and joints3d), from body_params.npz as the fitting stages write it."""
    import intercap.body_models as body_models
    from intercap.config import load_config
    from intercap.stages.export import stage as export

    model, core = models
    monkeypatch.setattr(body_models, "shared_model", lambda cfg, device="cpu": model)
    params = random_params(model, B=5)
    with torch.no_grad():
        vertices = model(params).vertices.numpy()
    arrays = {"model": np.array("smplx"), **params.to_numpy_dict()}
    arrays["transl"][2] = np.nan  # a frame without a fit
    vertices[2] = np.nan
    res = {"body_params": arrays, "body_vertices": vertices, "body_faces": np.zeros((1, 3), np.int64)}
    export.body_model_arrays(res, load_config(None, ["body_model.name=smplx"]), 5)
    exported = res["smplx"]
    assert exported["body_pose"].shape == (5, 63) and exported["left_hand_pose"].shape == (5, 45)
    ok = [0, 1, 3, 4]
    with torch.no_grad():
        again = core(**{k: torch.as_tensor(v[ok], dtype=torch.float64) for k, v in exported.items()}, return_verts=True)
    assert np.abs(again.vertices.numpy() - vertices[ok]).max() < 1e-5  # float32 in the file
    assert np.isnan(exported["transl"][2]).all() and np.isnan(res["joints3d"][2]).all()
    from intercap.session import Session

    session = Session.load(SAMPLE_SESSION)
    session.restrict_frames(0, 4)
    data = export.dataset_arrays(session, {**res, "object": None, "contact": None, "contact_detail": None,
                                           "ground": None, "physics": None, "keypoints3d": None})
    assert str(data["body_model"]) == "smplx"
    for k, v in exported.items():
        assert np.array_equal(data[f"smplx_{k}"], v, equal_nan=True)
