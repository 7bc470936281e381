"""The joint fit's energy as a table of terms (`intercap.energies.terms`).

Each term is a function of one `GlobalEvaluation` (the fitter, the window's body parameters and
object pose, its observations, and what several terms share: the window's vertices, E_B's values,
the object's surface samples in the world, the body's vertices in object coordinates) giving its
unweighted value per frame (W,), or None where it does not apply (no floor, no free flight, too few
frames). E_B is the body stage's final phase (section `body`, its weights); the terms the joint fit
adds weigh with the global section's settings. `TERMS` lists them in the order the energy sums
them. Adding a term is one function here (or in `intercap.energies`) and one entry in a table.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import torch

from intercap.body_models.base import BodyOutput
from intercap.energies import losses
from intercap.energies.motion_prior import MODEL_FPS
from intercap.energies.terms import Term, check_weights
from intercap.stages.body.config import BodyConfig
from intercap.stages.body.terms import FINAL_TERMS, unseen_feet_support
from intercap.stages.global_fit.config import GlobalConfig
from intercap.stages.global_fit.observations import WindowData


@dataclass
class GlobalEvaluation:
    """What the joint fit's terms read at one evaluation of a window's energy. `of` computes what
    every evaluation needs, in this order: the model's output at the window's vertices
    (`GlobalFitter.vertex_ids`, the fitting subsample first), E_B's values, the object's surface
    samples in the world; the rest is computed once, when a term first asks for it."""

    fitter: Any  # GlobalFitter: the model, the body stage's fitter, the object's shape, floor, gravity, priors
    params: Any  # BodyParams of the window's W frames
    R: torch.Tensor  # (W, 3, 3) object -> world
    centre: torch.Tensor  # (W, 3) the object's centroid in the world
    data: WindowData
    vertices: torch.Tensor  # (W, U, 3) the window's vertices
    body: dict  # E_B: the body stage's final terms, unweighted, (W,) each
    object_world: torch.Tensor | None  # (W, M, 3) the object's surface samples; None in a body-only fit

    @classmethod
    def of(cls, fitter, params, R: torch.Tensor, centre: torch.Tensor, data: WindowData, matches,
           rest=None) -> "GlobalEvaluation":
        """The evaluation at `params`, (R, centre); `matches`: E_D's correspondences; `rest`: the
        model's `rest_state` of the window's vertices (shape and expression are fixed in this stage)."""
        out = fitter.model.sparse_forward(params, fitter.vertex_ids, rest)
        vertices = out.vertices  # (W, U, 3)
        subset_out = BodyOutput(vertices=vertices, joints=out.joints, keypoints=out.keypoints)
        body = fitter.body.energy_terms(params, data.obs, FINAL_TERMS, matches, fitter.bcfg.keypoint_rho,
                                        out=subset_out)
        object_world = None if fitter.shape is None else fitter.from_object(fitter.shape.samples, R, centre)
        return cls(fitter, params, R, centre, data, vertices, body, object_world)

    @property
    def has_object(self) -> bool:
        """Whether the window has an object (a body-only joint fit has none: its terms do not apply)."""
        return self.object_world is not None

    @property
    def g(self) -> GlobalConfig:
        """The global section's settings."""
        return self.fitter.gcfg

    @cached_property
    def body_in_object(self) -> torch.Tensor:
        """(W, U) signed distance of the window's vertices to the object's surface. Where the object's
        pose is a guess (untrusted, filled in from trusted frames) E_P and E_C move the object, not
        the body: a wrong fill inside the body (fitted to the person's points) would push the person away."""
        trusted = (self.data.object_confidence > 0)[:, None, None]
        vertices = torch.where(trusted, self.vertices, self.vertices.detach())
        return self.fitter.shape.signed_distance(self.fitter.to_object(vertices, self.R, self.centre))

    @cached_property
    def hands_on_object(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(E_C, E_C'), each (W,), from one pass over the hands."""
        fitter, data, g = self.fitter, self.data, self.g
        vertices, body_in_object = self.vertices, self.body_in_object
        contact = body_in_object.new_zeros(body_in_object.shape[:1])
        grasp = torch.zeros_like(contact)
        grasp_world = fitter.from_object(fitter.shape.grasp_points, self.R, self.centre)
        for h, slots in enumerate(fitter.hand_slots):
            touching = data.grasping[:, h]
            contact = contact + losses.contact_chamfer(body_in_object[:, slots], touching, g.contact_vertices)
            # E_C' over the grasping frames found on the host when the window was read; without
            # them (`grasp_rows` None), every frame weighted by `touching` (searching it would make a GPU wait)
            rows = None if data.grasp_rows is None else data.grasp_rows[h]
            if rows is None:
                grasp = grasp + losses.hand_contact(vertices[:, slots], grasp_world, touching, g.contact_vertices)
            elif len(rows):  # the grasping frames only: often a small share of the window's
                pick = (lambda x: x.index_select(0, rows))
                grasp = grasp.index_add(0, rows, losses.hand_contact(pick(vertices)[:, slots], pick(grasp_world),
                                                                     pick(touching), g.contact_vertices))
        return contact, grasp

    @cached_property
    def floor(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(point, normal) of the ground plane, or None when prepare found none."""
        if self.fitter.ground is None:
            return None
        point, normal = (x.to(self.vertices) for x in self.fitter.ground)
        return point, normal

    @property
    def enough_frames_for_priors(self) -> bool:
        """Whether the learned motion priors are loaded and the window has enough frames for their phases."""
        return bool(self.fitter.priors) and len(self.vertices) >= 3 * max(1, round(self.fitter.fps / MODEL_FPS))

    @property
    def up(self) -> torch.Tensor | None:
        """The floor's normal (the motion priors' up), or None without a floor."""
        return None if self.fitter.ground is None else self.fitter.ground[1].to(self.vertices)


def body_term(name: str):
    """The energy of E_B's term `name`: its value among the body stage's (`GlobalEvaluation.body`)."""

    def energy(ev: GlobalEvaluation) -> torch.Tensor | None:
        return ev.body.get(name)

    energy.__name__ = energy.__qualname__ = f"body_{name}"
    return energy


def object_points(ev: GlobalEvaluation) -> torch.Tensor | None:
    """E_O: the observed object points against the posed object's surface (Geman-McClure)."""
    data = ev.data
    if data.object_points is None:
        return None
    sd = ev.fitter.shape.signed_distance(ev.fitter.to_object(data.object_points, ev.R, ev.centre))
    return losses.object_point_to_surface(sd, data.object_point_valid, ev.g.object_depth_scale_m)


def object_anchor(ev: GlobalEvaluation) -> torch.Tensor | None:
    """The object's surface samples to where the tracker put them, x its confidence."""
    if not ev.has_object:
        return None
    return losses.pose_anchor(ev.object_world, ev.data.object_reference, ev.data.object_confidence)


def interpenetration(ev: GlobalEvaluation) -> torch.Tensor | None:
    """E_P: body vertices inside the object."""
    if not ev.has_object:
        return None
    return losses.body_object_interpenetration(ev.body_in_object)


def contact(ev: GlobalEvaluation) -> torch.Tensor | None:
    """E_C: each touching hand's nearest palm patch onto the object's surface, in contact frames."""
    if not ev.has_object:
        return None
    return ev.hands_on_object[0]


def hand_contact(ev: GlobalEvaluation) -> torch.Tensor | None:
    """E_C': a grasping palm onto the object's graspable points."""
    if not ev.has_object:
        return None
    return ev.hands_on_object[1]


def ground(ev: GlobalEvaluation) -> torch.Tensor | None:
    """E_G: body vertices and object samples below the floor."""
    if ev.floor is None:
        return None
    point, normal = ev.floor
    below = losses.ground_penetration(ev.vertices, point, normal)
    return below + losses.ground_penetration(ev.object_world, point, normal) if ev.has_object else below


def body_ground_support(ev: GlobalEvaluation) -> torch.Tensor | None:
    """E_S as in the body stage: the body's lowest points onto the floor where fewer than two views see the feet."""
    if ev.floor is None or ev.fitter.bcfg.w_ground_support <= 0:
        return None
    point, normal = ev.floor
    return unseen_feet_support(ev.vertices, ev.data.obs.keypoints, point, normal)


def flight(ev: GlobalEvaluation) -> torch.Tensor | None:
    """GraviCap: the object's centre onto the gravity parabola of its free-flight episode."""
    if ev.fitter.gravity is None or ev.data.flight is None:
        return None
    centre = ev.centre
    times = torch.arange(len(centre), dtype=centre.dtype, device=centre.device) / ev.fitter.fps
    return losses.flight_parabola(centre, ev.data.flight, times, ev.fitter.gravity.to(centre))


def object_acceleration(ev: GlobalEvaluation) -> torch.Tensor | None:
    """E_A: the acceleration of the object's surface samples."""
    if not ev.has_object or len(ev.vertices) < 3:
        return None
    return losses.vertex_acceleration(ev.object_world, ev.fitter.fps)


def body_acceleration(ev: GlobalEvaluation) -> torch.Tensor | None:
    """The acceleration of the window's body vertices (in a body-only fit each weighing as many of the mesh's
    vertices as lie nearest it, `global.acceleration_over_mesh_alone`), x the frame's weight factor where the
    take moves slowly (`observations.acceleration_scale`)."""
    if len(ev.vertices) < 3:
        return None
    value = losses.vertex_acceleration(ev.vertices, ev.fitter.fps, ev.fitter.vertex_shares)
    scale = ev.data.acceleration_scale
    return value if scale is None else value * scale


def body_motion_prior(ev: GlobalEvaluation) -> torch.Tensor | None:
    """E_S, the learned body motion prior (`intercap.energies.motion_prior`), when loaded."""
    if not ev.enough_frames_for_priors:
        return None
    from intercap.energies.motion_prior import body_motion_smoothness

    return body_motion_smoothness(ev.vertices[:, ev.fitter.prior_slots["body"]], ev.fitter.fps, ev.up)


def hand_motion_prior(ev: GlobalEvaluation) -> torch.Tensor | None:
    """E_L + E_R, the learned hand motion priors, when loaded."""
    if not ev.enough_frames_for_priors:
        return None
    from intercap.energies.motion_prior import hand_motion_smoothness

    up, fps = ev.up, ev.fitter.fps
    hand_points = ev.vertices[:, ev.fitter.prior_slots["hand"]]
    return hand_motion_smoothness(hand_points, fps, "L", up) + hand_motion_smoothness(hand_points, fps, "R", up)


# E_B: the body's final phase, weighted as in the body stage; its own floor terms are left out, since the
# joint fit's body fitter has no floor: `ground` and `body_ground_support` below measure the window's vertices.
BODY_TERMS = tuple(Term(f"body_{t.name}", body_term(t.name), t.weight, "body") for t in FINAL_TERMS
                   if t.name not in ("ground", "ground_support"))

# the joint fit's energy, in the order it is summed
TERMS = check_weights((
    *BODY_TERMS,
    Term("object", object_points, "w_object"),
    Term("object_anchor", object_anchor, "w_object_anchor"),
    Term("interpenetration", interpenetration, "w_interpenetration"),
    Term("contact", contact, "w_contact"),
    Term("hand_contact", hand_contact, "w_hand_contact"),
    Term("ground", ground, "w_ground"),
    Term("body_ground_support", body_ground_support, "w_ground_support", "body"),
    Term("flight", flight, "w_flight"),
    Term("object_acceleration", object_acceleration, "w_object_acceleration"),
    Term("body_acceleration", body_acceleration, "w_body_acceleration"),
    Term("body_motion_prior", body_motion_prior, "w_body_motion_prior"),
    Term("hand_motion_prior", hand_motion_prior, "w_hand_motion_prior"),
), {"": GlobalConfig, "body": BodyConfig})
