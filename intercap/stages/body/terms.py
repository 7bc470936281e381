"""The body fit's energy as a table of terms (`intercap.energies.terms`), and its phases.

Each term is a function of one `BodyEvaluation` (the fitter, the parameters, the observations, the
model's output, E_D's correspondences, E_J's robust scale) giving its (B,) unweighted value, or None
where it does not apply; its weight is the `BodyConfig` setting it names. `TERMS` lists them in the
order the energy sums them. As SMPLify-X, the fit runs in phases (`PHASES`): orientation and
translation from the trunk's and legs' keypoints, then pose and shape from all keypoints, then
everything with the depth term; the global stage evaluates the last phase's terms (`FINAL_TERMS`).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import torch

from intercap.body_models.keypoints import NUM_BODY_HANDS
from intercap.energies import losses, priors
from intercap.energies.terms import Term, check_weights
from intercap.geometry.cameras import project
from intercap.stages.body.config import BodyConfig
from intercap.stages.body.observations import BodyObservations, foot_views, keypoint_views


def unseen_feet_support(vertices: torch.Tensor, keypoints: torch.Tensor, ground_point: torch.Tensor,
                        ground_normal: torch.Tensor) -> torch.Tensor:
    """(B,) E_S (`losses.ground_support`) on the frames where fewer than two views see the feet; where
    two do, their keypoints place the feet and the term is zero. Shared by the body and global stages."""
    unseen = (foot_views(keypoints) < 2).to(vertices.dtype)
    return losses.ground_support(vertices, ground_point, ground_normal) * unseen


@dataclass
class BodyEvaluation:
    """What the body terms read at one evaluation: `out` is the model's output for `params` whose
    first vertices are the fitting subsample; `matches` E_D's `DepthPairs` (`BodyFitter.correspondences`,
    needed by the depth term); `rho` E_J's robust scale; `terms` the terms evaluated (the pose priors
    are computed together, those among them only)."""

    fitter: Any  # BodyFitter: the model, cameras, config, sphere proxy, floor and shape prior's centre
    params: Any  # BodyParams
    obs: BodyObservations
    out: Any  # BodyOutput
    terms: tuple
    matches: Any = None
    rho: float = 0.0

    @property
    def cfg(self) -> BodyConfig:
        return self.fitter.cfg

    @cached_property
    def pose_priors(self) -> dict[str, torch.Tensor]:
        """The pose priors among `terms`, from one pass over the rotations they read (`priors.pose_priors`)."""
        p = self.params
        return priors.pose_priors(p.body_pose, p.left_hand_pose, p.right_hand_pose, [t.name for t in self.terms])

    @cached_property
    def floor(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """(fitting vertices, floor point, floor normal), or None when the fitter has no floor."""
        if self.fitter.ground is None:
            return None
        point, normal = (x.to(self.out.vertices) for x in self.fitter.ground)
        return self.out.vertices[:, :len(self.fitter.subset)], point, normal


def reprojection(ev: BodyEvaluation, weights: torch.Tensor) -> torch.Tensor:
    """E_J with per-joint `weights`: every view's keypoints, Geman-McClure robust, weighted by confidence."""
    fitter, out = ev.fitter, ev.out
    C = len(fitter.cameras)
    B, K = out.keypoints.shape[0], NUM_BODY_HANDS
    pix, z = project(out.keypoints.reshape(1, B * K, 3).expand(C, -1, -1), fitter.cameras)
    pix = pix.view(C, B, K, 2).transpose(0, 1)
    conf = ev.obs.keypoints[..., 2] * (z.view(C, B, K).transpose(0, 1) > 0.05)
    return losses.keypoint_reprojection(pix, ev.obs.keypoints[..., :2], conf, weights, fitter.scale_px, ev.rho)


def keypoints(ev: BodyEvaluation) -> torch.Tensor:
    """E_J over all 67 keypoints (hands weighted `hand_keypoint_weight`)."""
    return reprojection(ev, ev.fitter.joint_weights)


def orient_keypoints(ev: BodyEvaluation) -> torch.Tensor:
    """E_J over the trunk's and legs' keypoints only (`ORIENT_KEYPOINTS`): the orient phase's."""
    return reprojection(ev, ev.fitter.orient_weights)


def depth(ev: BodyEvaluation) -> torch.Tensor:
    """E_D, point to plane to the visible fitting vertices, x `one_view_depth_factor` on frames fewer than
    two views see with keypoints."""
    cfg = ev.cfg
    one_view = keypoint_views(ev.obs.keypoints, cfg) < 2
    value = losses.depth_point_to_plane(ev.out.vertices[:, :len(ev.fitter.subset)], ev.matches, cfg.depth_scale_m)
    return value * torch.where(one_view, cfg.one_view_depth_factor, 1.0)


def pose_prior(ev: BodyEvaluation) -> torch.Tensor:
    """The learned body-pose mixture's negative log-likelihood."""
    return ev.pose_priors["pose_prior"]


def joint_limits(ev: BodyEvaluation) -> torch.Tensor:
    """Squared hinges beyond the anatomical joint ranges."""
    return ev.pose_priors["joint_limits"]


def bending(ev: BodyEvaluation) -> torch.Tensor:
    """Extreme elbow and knee bending."""
    return ev.pose_priors["bending"]


def hand_prior(ev: BodyEvaluation) -> torch.Tensor:
    """Both hands' finger ranges."""
    return ev.pose_priors["hand_prior"]


def shape(ev: BodyEvaluation) -> torch.Tensor:
    """The phenotype inside [0, 1], lightly pulled to the fitter's `shape_center`."""
    return priors.shape_prior(ev.params.shape, center=ev.fitter.shape_center)


def expression(ev: BodyEvaluation) -> torch.Tensor | None:
    """The rest face, where the expression is fitted (`fit_expression`)."""
    return priors.expression_prior(ev.params.expression) if ev.cfg.fit_expression else None


def ground(ev: BodyEvaluation) -> torch.Tensor | None:
    """E_G: fitting vertices below the floor, where the fitter has one."""
    return None if ev.floor is None else losses.ground_penetration(*ev.floor)


def ground_support(ev: BodyEvaluation) -> torch.Tensor | None:
    """E_S: the body's lowest points onto the floor where fewer than two views see the feet (`unseen_feet_support`)."""
    if ev.floor is None or ev.cfg.w_ground_support <= 0:
        return None
    vertices, point, normal = ev.floor
    return unseen_feet_support(vertices, ev.obs.keypoints, point, normal)


def penetration(ev: BodyEvaluation) -> torch.Tensor:
    """Self-penetration of the sphere proxy (`BodySpheres`)."""
    spheres, joints = ev.fitter.spheres, ev.out.joints
    return losses.sphere_self_penetration(spheres.centres(joints), spheres.radii.to(joints), spheres.pairs)


KEYPOINT_TERM = Term("keypoints", keypoints, "w_keypoints")
ORIENT_KEYPOINT_TERM = Term("orient_keypoints", orient_keypoints, "w_keypoints")
DEPTH_TERM = Term("depth", depth, "w_depth")
POSE_PRIOR_TERMS = (  # in the order `priors.pose_priors` gives them (`priors.POSE_PRIOR_TERMS`)
    Term("pose_prior", pose_prior, "w_pose_prior"),
    Term("joint_limits", joint_limits, "w_joint_limits"),
    Term("bending", bending, "w_bending"),
    Term("hand_prior", hand_prior, "w_hand_prior"),
)
SHAPE_TERM = Term("shape", shape, "w_shape")
EXPRESSION_TERM = Term("expression", expression, "w_expression")
GROUND_TERM = Term("ground", ground, "w_ground")
GROUND_SUPPORT_TERM = Term("ground_support", ground_support, "w_ground_support")
PENETRATION_TERM = Term("penetration", penetration, "w_penetration")

# the body's energy, in the order it is summed
TERMS = check_weights((KEYPOINT_TERM, ORIENT_KEYPOINT_TERM, DEPTH_TERM, *POSE_PRIOR_TERMS, SHAPE_TERM,
                       EXPRESSION_TERM, GROUND_TERM, GROUND_SUPPORT_TERM, PENETRATION_TERM), {"": BodyConfig})


@dataclass(frozen=True)
class Phase:
    """One SMPLify-X-style phase: which variables move, which terms count (`Term`s of `TERMS`), how long."""

    name: str
    variables: tuple[str, ...]
    terms: tuple[Term, ...]
    steps_key: str  # BodyConfig field holding its L-BFGS step budget
    rho_key: str = "keypoint_rho"  # BodyConfig field holding E_J's robust scale in this phase

    @property
    def fits_depth(self) -> bool:
        """Whether the phase counts E_D (and so needs its correspondences, refreshed between steps)."""
        return DEPTH_TERM in self.terms


def in_table_order(terms) -> tuple[Term, ...]:
    """`terms` (`Term`s of `TERMS`) in the order the energy sums them."""
    terms = tuple(terms)
    strays = [t for t in terms if not isinstance(t, Term) or t not in TERMS]
    if strays:
        raise ValueError(f"not terms of the body's table: {strays}")
    return tuple(t for t in TERMS if t in terms)


PHASES = (
    Phase("orient", ("global_orient", "transl"), (ORIENT_KEYPOINT_TERM,), "orient_steps", "keypoint_rho_start"),
    Phase("pose", ("global_orient", "transl", "body_pose", "shape"),
          in_table_order((KEYPOINT_TERM, *POSE_PRIOR_TERMS[:3], SHAPE_TERM, GROUND_TERM, GROUND_SUPPORT_TERM)),
          "pose_steps", "keypoint_rho_start"),
    Phase("full", ("global_orient", "transl", "body_pose", "shape", "left_hand_pose", "right_hand_pose", "expression"),
          in_table_order((KEYPOINT_TERM, DEPTH_TERM, *POSE_PRIOR_TERMS, SHAPE_TERM, EXPRESSION_TERM,
                          PENETRATION_TERM, GROUND_TERM, GROUND_SUPPORT_TERM)), "full_steps"),
)
FINAL_TERMS = PHASES[-1].terms  # what a fit is judged by (`BodyFitter.final_terms`) and the global stage's E_B
