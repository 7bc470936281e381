"""The global stage's energy is its table of terms (`intercap.stages.global_fit.terms.TERMS`): a new
term is one entry in a copy of the table (and its weight one setting), nothing else."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from conftest import SAMPLE_SESSION

from intercap.body_models import BodyParams, load_from_config
from intercap.body_models.base import PARAM_FIELDS
from intercap.config import load_config
from intercap.energies.terms import Term, check_weights
from intercap.geometry.cameras import Cameras, project
from intercap.geometry.ground import GroundPlane
from intercap.session import Session
from intercap.stages.body.config import BodyConfig
from intercap.stages.body.observations import BodyObservations
from intercap.stages.global_fit.config import GlobalConfig
from intercap.stages.global_fit.fitter import GlobalFitter
from intercap.stages.global_fit.observations import ObjectShape, WindowData
from intercap.stages.global_fit.terms import BODY_TERMS, TERMS

GT = SAMPLE_SESSION / "ground_truth"
TARGET = torch.tensor([0.1, -0.2, 0.9])  # where the toy term pulls the object's centre (metres, world)


@dataclasses.dataclass
class ToyConfig(GlobalConfig):
    """The global section with one more weight: the toy term's."""

    w_toy_centre: float = 123.0


def toy_centre(ev) -> torch.Tensor:
    """A toy term: the squared distance of the object's centre from `TARGET`, per frame (W,)."""
    return (ev.centre - TARGET.to(ev.centre)).pow(2).sum(-1)


TOY = Term("toy_centre", toy_centre, "w_toy_centre")


@pytest.fixture(scope="module")
def window():
    """The sample's frames 16-18 at their true poses, the right hand grasping: (model, cameras, ground,
    object shape, body, R, object centre, `WindowData` with keypoints and a few object points)."""
    sample = Session.load(SAMPLE_SESSION)
    model = load_from_config(load_config().body_model)
    W, frame = 3, 16
    body = BodyParams.from_numpy_dict({k: np.load(GT / "body_params.npz")[k][frame:frame + W].astype(np.float32)
                                       for k in PARAM_FIELDS})
    poses = np.load(GT / "object_poses.npz")
    R = torch.as_tensor(poses["R"][frame:frame + W], dtype=torch.float32)
    t = torch.as_tensor(poses["t"][frame:frame + W], dtype=torch.float32)
    shape = ObjectShape(sample.object.load_mesh(), 24, sample.object.contact_vertices, samples=64)
    cameras = Cameras.from_infos(sample.cameras)
    C = len(cameras)
    with torch.no_grad():
        keypoints = model(body).keypoints[:, :67]
    pix, _ = project(keypoints.reshape(1, -1, 3).expand(C, -1, -1), cameras)
    observed = torch.cat([pix.view(C, W, 67, 2).transpose(0, 1), torch.ones(W, C, 67, 1)], -1)
    obs = BodyObservations(np.arange(W), observed, torch.zeros(W, C, 1, 3), torch.zeros(W, C, 1, dtype=torch.bool))
    reference = shape.samples @ R.transpose(1, 2) + t[:, None]
    grasping = torch.tensor([[0, 1], [0, 1], [0, 0]], dtype=torch.float32)
    data = WindowData(obs, reference[:, :20] + 0.003, torch.ones(W, 20, dtype=torch.bool), reference,
                      torch.ones(W), grasping)
    g = json.loads((GT / "ground.json").read_text())
    ground = GroundPlane(point=np.array(g["point"]), normal=np.array(g["normal"]))
    return model, cameras, ground, shape, body, R, t + R @ shape.centroid, data


def fitters(window, steps: int = 2, toy_weight: float = 123.0):
    """A fitter on the stage's table and one on a copy of it with the toy term, its weight a new setting."""
    model, cameras, ground, shape, *_ = window
    cfg = load_config(overrides=[f"global.steps={steps}"])
    toy_cfg = ToyConfig(**dataclasses.asdict(cfg.global_), w_toy_centre=toy_weight)
    plain = GlobalFitter(model, cameras, cfg.body, cfg.global_, shape, ground, 30.0)
    toy = GlobalFitter(model, cameras, cfg.body, toy_cfg, shape, ground, 30.0, table=(*TERMS, TOY))
    return plain, toy


def energy_and_gradients(fitter, window):
    """The fitter's terms, its energy and the energy's gradients with respect to the variables a window
    optimises (the body's orientation, translation and pose; the object's rotation and shift)."""
    *_, body, R0, c0, data = window
    leaves = {name: getattr(body, name).detach().clone().requires_grad_(True)
              for name in ("global_orient", "transl", "body_pose")}
    leaves["rotation"] = torch.zeros(len(R0), 3, requires_grad=True)
    leaves["shift"] = torch.zeros(len(R0), 3, requires_grad=True)
    params = dataclasses.replace(body, **{name: leaves[name] for name in ("global_orient", "transl", "body_pose")})
    R, centre = fitter.object_pose(R0, c0, leaves["rotation"], leaves["shift"])
    terms = fitter.energy_terms(params, R, centre, data, fitter.body.correspondences(body, data.obs))
    energy = fitter.weighted_energy(terms)
    gradients = dict(zip(leaves, torch.autograd.grad(energy, list(leaves.values()), retain_graph=True)))
    return terms, energy, gradients, leaves


def test_a_new_term_is_one_entry_in_a_copy_of_the_table(window):
    """The toy term appears among the energy's terms, after the table's own; the energy and its gradient
    change by exactly its weighted value and gradient; the stage's table is untouched."""
    plain, toy = fitters(window)
    terms, energy, gradients, _ = energy_and_gradients(plain, window)
    toy_terms, toy_energy, toy_gradients, leaves = energy_and_gradients(toy, window)
    assert "toy_centre" not in terms and TOY not in TERMS
    assert list(toy_terms) == [*terms, "toy_centre"]
    for name, value in terms.items():
        assert torch.equal(value, toy_terms[name]), name
    weighted = 123.0 * toy_terms["toy_centre"].sum()
    assert torch.equal(toy_energy, energy + weighted)
    toy_gradient = dict(zip(leaves, torch.autograd.grad(weighted, list(leaves.values()), allow_unused=True)))
    for name, gradient in gradients.items():
        if toy_gradient[name] is None:  # the toy term does not move the body
            assert torch.equal(toy_gradients[name], gradient), name
        else:
            assert toy_gradient[name].abs().max() > 0
            assert torch.allclose(toy_gradients[name], gradient + toy_gradient[name], rtol=1e-5, atol=1e-3), name


def test_the_energy_sums_the_weighted_terms_in_table_order(window):
    """The energy is each term's weight (its section's setting) x its value summed over the frames, added
    in table order; E_B comes first (the body stage's final terms, its weights), then the joint fit's."""
    plain, _ = fitters(window)
    terms, energy, _, _ = energy_and_gradients(plain, window)
    names = [t.name for t in TERMS]
    assert names[:len(BODY_TERMS)] == [t.name for t in BODY_TERMS] and names[0] == "body_keypoints"
    assert names[len(BODY_TERMS):] == ["object", "object_anchor", "interpenetration", "contact", "hand_contact",
                                       "ground", "body_ground_support", "flight", "object_acceleration",
                                       "body_acceleration", "body_motion_prior", "hand_motion_prior"]
    assert list(terms) == [n for n in names if n in terms]
    bcfg, gcfg = plain.bcfg, plain.gcfg
    assert plain.weight("body_keypoints") == bcfg.w_keypoints and plain.weight("contact") == gcfg.w_contact
    assert plain.weight("body_ground_support") == bcfg.w_ground_support
    assert torch.equal(energy, sum(plain.weight(k) * v.sum() for k, v in terms.items()))


def test_a_window_fit_optimises_a_term_added_to_the_table(window):
    """The window's fit runs on the fitter's table: the toy term is reported before and after, and the fit
    with it ends nearer the toy's target than the same fit on the stage's table (the term's own value
    need not fall: the window's acceleration terms move the object too)."""
    *_, body, R0, c0, data = window
    plain, toy = fitters(window, steps=3, toy_weight=1e4)
    _, _, centre, stats = toy.fit_window(body, R0, c0, 0, data)
    _, _, plain_centre, plain_stats = plain.fit_window(body, R0, c0, 0, data)
    assert "toy_centre" in stats["before"] and "toy_centre" in stats["after"] and "toy_centre" not in plain_stats["after"]
    assert not torch.equal(centre, c0)
    assert (centre - TARGET).norm(dim=-1).mean() < (plain_centre - TARGET).norm(dim=-1).mean()


def test_a_term_naming_a_weight_the_config_lacks_fails_the_check(window):
    """A misspelt or missing weight is an error when the table is checked (at import for the stage's
    table), and when a fitter is given such a table."""
    configs = {"": GlobalConfig, "body": BodyConfig}
    assert check_weights((*TERMS, TOY), {**configs, "": ToyConfig})[-1] is TOY
    with pytest.raises(ValueError, match="w_toy_centre"):
        check_weights((*TERMS, TOY), configs)
    with pytest.raises(ValueError, match="w_keypoint"):
        check_weights((*TERMS, Term("body_typo", toy_centre, "w_keypoint", "body")), configs)
    with pytest.raises(ValueError, match="twice"):
        check_weights((*TERMS, TERMS[0]), configs)
    model, cameras, ground, shape, *_ = window
    cfg = load_config()
    with pytest.raises(ValueError, match="w_toy_centre"):
        GlobalFitter(model, cameras, cfg.body, cfg.global_, shape, ground, 30.0, table=(*TERMS, TOY))
