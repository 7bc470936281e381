"""run.device=cuda: the body model, the body fit's energies and the priors give on the GPU what they give
on the CPU, and `intercap run --set run.device=cuda` fits the sample as well as the CPU does.

Skipped without a CUDA device (CI has none); run these where one is."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from conftest import SAMPLE_SESSION, trimmed_copy

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

DEVICE = "cuda"
RTOL, ATOL = 1e-4, 1e-5  # float32 on both sides; TF32 is switched off below
FRAMES = 12  # of the sample, for the whole run: its first contact is at frame 10


@pytest.fixture(autouse=True)
def exact_float32():
    """TF32 (cuDNN's default for convolutions) would make the GPU differ from the CPU by ~1e-3."""
    saved = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


@pytest.fixture(scope="module")
def models():
    """(the anny model on the CPU, the same on the GPU)."""
    from intercap.body_models import load_body_model

    return load_body_model("anny", device="cpu"), load_body_model("anny", device=DEVICE)


def close(on_gpu: torch.Tensor, on_cpu: torch.Tensor, what: str, rtol: float = RTOL, atol: float = ATOL) -> None:
    assert on_gpu.device.type == "cuda", f"{what}: computed on {on_gpu.device}, not the GPU"
    torch.testing.assert_close(on_gpu.detach().cpu(), on_cpu.detach(), rtol=rtol, atol=atol,
                               msg=lambda m: f"{what}: {m}")


def posed_params(model, batch: int, seed: int = 0):
    """A batch of varied poses, shapes and expressions (CPU tensors)."""
    g = torch.Generator().manual_seed(seed)
    params = model.init_params(batch)
    with torch.no_grad():
        for name, scale in (("body_pose", 0.2), ("left_hand_pose", 0.2), ("right_hand_pose", 0.2),
                            ("global_orient", 0.5), ("transl", 1.0)):
            value = getattr(params, name)
            value.copy_(scale * torch.randn(value.shape, generator=g, dtype=value.dtype))
        params.shape.copy_(0.2 + 0.6 * torch.rand(params.shape.shape, generator=g, dtype=params.shape.dtype))
        params.expression.copy_(0.3 * torch.rand(params.expression.shape, generator=g, dtype=params.expression.dtype))
    return params


def test_body_model_forward_on_gpu_matches_cpu(models):
    cpu, gpu = models
    assert gpu.faces.is_cuda and gpu.coco_weights.is_cuda
    assert all(t.is_cuda for t in gpu.init_params(2).tensors().values())
    params = posed_params(cpu, 3)
    with torch.no_grad():
        a, b = cpu(params), gpu(params.to(DEVICE))
        for name in ("vertices", "joints", "keypoints"):
            close(getattr(b, name), getattr(a, name), f"forward {name}")
        ids = cpu.fitting_subsample
        a = cpu.sparse_forward(params, ids)
        b = gpu.sparse_forward(params.to(DEVICE), ids.to(DEVICE))
        for name in ("vertices", "joints", "keypoints"):
            close(getattr(b, name), getattr(a, name), f"sparse_forward {name}")


def test_priors_and_motion_prior_on_gpu_match_cpu(models):
    from intercap.energies import losses, priors
    from intercap.energies.motion_prior import body_motion_smoothness, hand_motion_smoothness

    cpu, _ = models
    params = posed_params(cpu, 4, seed=1)
    terms = {
        "learned_pose_prior": lambda p: priors.learned_pose_prior(p.body_pose),
        "joint_limits": lambda p: priors.joint_limit_penalty(p.body_pose),
        "extreme_bending": lambda p: priors.extreme_bending(p.body_pose),
        "hand_prior": lambda p: priors.hands_pose_prior(p.left_hand_pose, p.right_hand_pose),
        "shape_prior": lambda p: priors.shape_prior(p.shape),
        "expression_prior": lambda p: priors.expression_prior(p.expression),
    }
    for name, term in terms.items():
        close(term(params.to(DEVICE)), term(params), name)

    # a short motion: poses blended from one to another while the body walks along x
    a, b = posed_params(cpu, 1, seed=2), posed_params(cpu, 1, seed=3)
    w = torch.linspace(0, 1, 9)[:, None]
    motion = a.map(lambda t: t.expand(9, *t.shape[1:]).clone())
    motion.body_pose = (1 - w[..., None]) * a.body_pose + w[..., None] * b.body_pose
    motion.transl = torch.stack([w[:, 0] * 0.6, torch.zeros(9), torch.full((9,), 0.9)], -1)
    with torch.no_grad():
        vertices = cpu(motion).vertices  # (9, V, 3)
    up = torch.tensor([0.0, 0.0, 1.0])
    close(body_motion_smoothness(vertices.to(DEVICE), 30.0, up), body_motion_smoothness(vertices, 30.0, up),
          "body motion prior")
    close(hand_motion_smoothness(vertices.to(DEVICE), 30.0, "L", up), hand_motion_smoothness(vertices, 30.0, "L", up),
          "hand motion prior")
    close(losses.vertex_acceleration(vertices.to(DEVICE), 30.0), losses.vertex_acceleration(vertices, 30.0),
          "vertex acceleration")


def test_body_fit_energies_on_gpu_match_cpu(models, tmp_path):
    """The body stage's fitter on the sample's first frames: initialisation and every term of its last phase."""
    from intercap.config import BodyConfig
    from intercap.geometry.cameras import Cameras
    from intercap.session import Session
    from intercap.stages.body.fitter import BodyFitter, upright_template
    from intercap.stages.body.observations import BodyObservations, KeypointSource, PersonPoints
    from intercap.stages.body.stage import world_up
    from intercap.stages.body.terms import DEPTH_TERM, PHASES

    session = Session.load(SAMPLE_SESSION)
    bcfg = BodyConfig()
    ids = session.frame_ids[:4]
    kps = torch.from_numpy(KeypointSource(session, tmp_path).batch(ids, bcfg.min_keypoint_confidence))
    fits = {}
    for model, device in zip(models, ("cpu", DEVICE)):
        cameras = Cameras.from_infos(session.cameras, device=device)
        points, valid = PersonPoints(session, cameras, bcfg, tmp_path).batch(ids, kps.numpy())
        obs = BodyObservations(ids, kps.to(device), points.to(device), valid.to(device))
        fitter = BodyFitter(model, cameras, bcfg)
        init = fitter.initialise(obs, upright_template(model, world_up(session, tmp_path)))
        fits[device] = (fitter, obs, init)
    (fc, oc, pc), (fg, og, pg) = fits["cpu"], fits[DEVICE]
    close(pg.global_orient, pc.global_orient, "initial orientation", atol=1e-3)
    close(pg.transl, pc.transl, "initial translation (m)", atol=1e-3)

    terms = PHASES[-1].terms
    with torch.no_grad():
        matches = fc.correspondences(pc, oc)
        on_gpu = fg.correspondences(pc.to(DEVICE), og)  # visibility and nearest vertices on the GPU
        assert on_gpu.vertex.is_cuda and on_gpu.point.is_cuda
        pairs = int((on_gpu.weight > 0).sum())  # the GPU keeps a slot per point and vertex, the empty ones weighted 0
        agree = pairs / len(matches.vertex)
        assert abs(agree - 1) < 0.02, f"{pairs} depth correspondences on the GPU, {len(matches.vertex)} on the CPU"
        expected = fc.energy_terms(pc, oc, terms, matches)
        got = fg.energy_terms(pc.to(DEVICE), og, terms, matches.to(DEVICE))
        close(fg.energy_terms(pc.to(DEVICE), og, [DEPTH_TERM], on_gpu)["depth"], expected["depth"],
              "E_D with the GPU's own correspondences", rtol=0.02)
    assert set(got) == set(expected)
    for name in expected:
        close(got[name], expected[name], f"body term {name}")


def test_intercap_run_on_gpu_fits_the_sample(tmp_path):
    """`intercap run` with run.device=cuda, every stage, on the sample's first frames; the body surface is
    as near the ground truth as the CPU run's (< 20 mm), and so is the object; every CUDA graph the
    body and global stages record is recorded."""
    from intercap.cli import main
    from intercap.evaluation.evaluate import evaluate
    from intercap.pipeline import available_stages

    from intercap.energies import optim

    session = trimmed_copy(SAMPLE_SESSION, tmp_path / "session", FRAMES)
    out = tmp_path / "out"
    optim._graph_failures.clear()
    # chunks of 4 frames: the object stage tracks three of them side by side (`object.side_by_side_gpu`)
    code = main(["run", str(session), "--out", str(out), "--quiet", "--set", "run.device=cuda",
                 "--set", "report.enabled=false", "--set", "prepare.save_clouds=false",
                 "--set", "run.min_frames_per_worker=4"])
    assert code == 0
    assert optim._graph_failures == [], optim._graph_failures  # the body's and global stage's fits were recorded
    assert not (out / "report").exists()
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(available_stages()) <= set(metrics), sorted(metrics)
    for name in ("body_params.npz", "body_vertices.npy", "body_faces.npy", "keypoints3d.npy", "object_poses.npz",
                 "contact.npy", "global/DONE.json", "physics/physics.npz", f"export/{session.name}.npz"):
        assert (out / name).exists(), name
    assert metrics["body"]["frames_fitted"] == FRAMES
    vertices = np.load(out / "body_vertices.npy")
    assert vertices.shape[0] == FRAMES and np.isfinite(vertices).all()
    result = evaluate(out, session)
    assert result.metrics["body_surface_mm"] < 20.0, result.metrics  # the CPU run: 7.4 mm
    assert result.metrics["object_translation_mm"] < 20.0, result.metrics  # the CPU run: 2.0 mm


def test_body_fit_replayed_from_cuda_graphs_is_the_eager_fit(models, tmp_path, monkeypatch):
    """Each phase's evaluations replay a recorded CUDA graph (`body.cuda_graphs`), the phenotype
    fitted too (its rest state in the graph); the fit is the eager one (keypoints within 1 mm on
    average: the GPU's atomic sums differ run to run) and recording does not fail."""
    import dataclasses

    from intercap.energies import optim
    from intercap.stages.body import fitter as body
    from intercap.stages.body.stage import world_up

    _, model = models
    session, bcfg, cameras, obs = gpu_observations(tmp_path, 6)
    template = body.upright_template(model, world_up(session, tmp_path))
    keypoints, replays = {}, []
    replay = torch.cuda.CUDAGraph.replay
    monkeypatch.setattr(torch.cuda.CUDAGraph, "replay", lambda graph: replays.append(1) or replay(graph))
    optim._graph_failures.clear()
    for graphs in (False, True):
        fitter = body.BodyFitter(model, cameras, dataclasses.replace(bcfg, cuda_graphs=graphs))
        fitted, _ = fitter.fit(obs, fitter.initialise(obs, template))
        with torch.no_grad():
            keypoints[graphs] = model(fitted).keypoints[:, :25].cpu()
        assert (len(replays) > 20) == graphs, len(replays)  # every phase's evaluations after its first
    assert optim._graph_failures == [], optim._graph_failures
    gap_mm = 1000 * (keypoints[True] - keypoints[False]).norm(dim=-1)
    assert float(gap_mm.mean()) < 1.0 and float(gap_mm.max()) < 5.0, gap_mm


def test_failed_fit_is_refitted_on_gpu(models, tmp_path):
    """The body stage's tracking path (fit-to-data, four-heading refit, energy choice) runs on the GPU:
    the sample's frame 0 turned round and 0.4 m off is brought back onto its depth points."""
    from intercap.body_models import BodyParams
    from intercap.body_models.base import axis_angle_to_matrix
    from intercap.stages.body import fitter as body

    _, model = models
    _, bcfg, cameras, obs = gpu_observations(tmp_path, 1)
    truth = BodyParams.from_numpy_dict(dict(np.load(SAMPLE_SESSION / "ground_truth" / "body_params.npz")))[0]
    wrong = truth.to(DEVICE)
    with torch.no_grad():
        centre = model(wrong).joints[:, 0]
        body.turn_about(wrong, axis_angle_to_matrix(torch.tensor([[0.0, 0.0, np.pi]], device=DEVICE)), centre)
        wrong.transl += torch.tensor([0.4, 0.0, 0.0], device=DEVICE)
    fitter = body.BodyFitter(model, cameras, bcfg)
    energy = body.frame_energy(fitter, fitter.final_terms(wrong, obs))
    template = body.upright_template(model, np.array([0.0, 0.0, 1.0]))
    refitted, replaced = body.refit_from_evidence(fitter, obs, wrong, energy, np.ones(1, bool), template)
    assert replaced.all() and refitted.transl.is_cuda
    with torch.no_grad():
        assert body.fit_to_data_mm(model(refitted).vertices, obs)[0] < 20


def keypoints_of(session, out_dir, ids, bcfg) -> np.ndarray:
    from intercap.stages.body.observations import KeypointSource

    return KeypointSource(session, out_dir).batch(ids, bcfg.min_keypoint_confidence)


def gpu_observations(tmp_path, frames: int):
    """(session, body config, cameras and the body's observations on the GPU) of the sample's first frames."""
    from intercap.config import BodyConfig
    from intercap.geometry.cameras import Cameras
    from intercap.session import Session
    from intercap.stages.body import observations as body

    session = Session.load(SAMPLE_SESSION)
    bcfg = BodyConfig()
    ids = session.frame_ids[:frames]
    cameras = Cameras.from_infos(session.cameras, device=DEVICE)
    kps = keypoints_of(session, tmp_path, ids, bcfg)
    points, valid = body.PersonPoints(session, cameras, bcfg, tmp_path).batch(ids, kps)
    obs = body.BodyObservations(ids, torch.from_numpy(kps).to(DEVICE), points.to(DEVICE), valid.to(DEVICE))
    return session, bcfg, cameras, obs


def test_object_fits_side_by_side_on_gpu_match_cpu(monkeypatch):
    """`ObjectTracker.fit_many` on the GPU: three fits at once (different frames and budgets) end
    where the CPU's do, their renders in fixed shapes and their steps replayed from a recorded
    CUDA graph (`object.cuda_graphs`)."""
    from intercap.config import load_config
    from intercap.energies import optim
    from intercap.session import Session
    from intercap.stages.object.fitter import ObjectTracker, axis_rotation

    replays = []
    replay = torch.cuda.CUDAGraph.replay
    monkeypatch.setattr(torch.cuda.CUDAGraph, "replay", lambda graph: replays.append(1) or replay(graph))
    optim._graph_failures.clear()

    session = Session.load(SAMPLE_SESSION)
    cfg = load_config().object
    truth = np.load(SAMPLE_SESSION / "ground_truth" / "object_poses.npz")
    on_cpu, on_gpu = (ObjectTracker(session, cfg, session.object.load_mesh(), device=d) for d in ("cpu", DEVICE))
    rng = np.random.default_rng(5)
    requests = []
    for frame, iterations in ((2, None), (6, 8), (10, None)):  # within the first FRAMES (what the GPU bundle carries)
        R, t = truth["R"][frame], truth["t"][frame]
        requests.append((on_cpu.observe(frame, (R, t)), axis_rotation(rng.normal(size=3) / np.sqrt(3), 5.0) @ R,
                         t + rng.normal(scale=0.01, size=3), iterations))
    assert on_gpu.fixed_shapes and not on_cpu.fixed_shapes
    for cpu, gpu in zip(on_cpu.fit_many(requests), on_gpu.fit_many(requests)):
        assert abs(cpu.energy - gpu.energy) < 1e-3 * max(1.0, cpu.energy)
        assert np.abs(cpu.t - gpu.t).max() < 1e-3 and np.abs(cpu.R - gpu.R).max() < 1e-2
    assert optim._graph_failures == [] and len(replays) > 5, (optim._graph_failures, len(replays))


def test_dense_nearest_search_on_gpu_finds_what_the_trees_find():
    """E_D's correspondences on the GPU (the dense matrix) are the CPU's k-d trees' ones."""
    from intercap.energies.losses import nearest_points, nearest_visible_vertices

    g = torch.Generator().manual_seed(6)
    points, vertices = torch.rand(4, 3, 50, 3, generator=g), torch.rand(4, 80, 3, generator=g)
    visible, valid = torch.rand(4, 3, 80, generator=g) > 0.3, torch.rand(4, 3, 50, generator=g) > 0.2
    cpu = nearest_visible_vertices(points, vertices, visible)
    gpu = nearest_visible_vertices(points.to(DEVICE), vertices.to(DEVICE), visible.to(DEVICE))
    assert gpu.device.type == "cuda" and (gpu.cpu() == cpu).all()
    cpu = nearest_points(vertices, visible, points, valid, 0.1)
    gpu = nearest_points(vertices.to(DEVICE), visible.to(DEVICE), points.to(DEVICE), valid.to(DEVICE), 0.1)
    assert (gpu.cpu() == cpu).all()
