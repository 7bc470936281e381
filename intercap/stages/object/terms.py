"""The object fit's energy as a declared table: E_O = l_segm * silhouette + l_depth * depth, the
weights `object.w_silhouette` (l_segm) and `object.w_depth` (l_depth).

Each term reads one `PoseEvaluation` (P poses rendered against their observation windows) and
gives its value per pose, (P,); `energy` sums the weighted terms in table order.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from intercap.energies.losses import object_depth, object_silhouette
from intercap.energies.terms import Term, check_weights
from intercap.stages.object.config import ObjectConfig


@dataclass
class PoseEvaluation:
    """P poses rendered against their observation windows, (P, C, h, w) each but `view_weight`."""

    render: Any  # `rendering.render`'s output: silhouette, depth (and coverage, counts)
    obs_mask: torch.Tensor  # the object's share of the known pixels
    obs_depth: torch.Tensor  # measured depth (metres, 0 = missing)
    obs_known: torch.Tensor  # fraction of each cell whose mask label is known
    visible: torch.Tensor  # 1 where the rendered object is not behind a measured occluder
    view_weight: torch.Tensor  # (P, C, 1, 1): 1 for the views that see the object
    depth_scale_m: float  # Geman-McClure scale of the depth residuals


def silhouette(e: PoseEvaluation) -> torch.Tensor:
    """`losses.object_silhouette` over the visible pixels whose label is known, in the views that see the object."""
    return object_silhouette(e.render.silhouette, e.obs_mask, e.visible * e.obs_known * e.view_weight)


def depth(e: PoseEvaluation) -> torch.Tensor:
    """`losses.object_depth` over every observed object pixel with depth, covered or not: an uncovered one
    pays the full robust cost, so rendering nothing (or too little) is never the cheap answer."""
    depth_weight = (e.obs_mask > 0.5) & (e.obs_depth > 0)
    return object_depth(e.render.depth, e.obs_depth, depth_weight * e.visible * e.view_weight, e.depth_scale_m)


SILHOUETTE = Term("silhouette", silhouette, "w_silhouette")
DEPTH = Term("depth", depth, "w_depth")
TERMS = check_weights((SILHOUETTE, DEPTH), {"": ObjectConfig})


def energy(values: dict, cfg: ObjectConfig) -> torch.Tensor:
    """E_O (P,): the weighted terms of `values` ({name: (P,)}, `evaluate_terms`'s) summed in table
    order, w_1 * v_1 + w_2 * v_2 + ... (from the first term, not from 0: no extra addition, which
    would be one more launch in every step of a recorded fit)."""
    weighted = [term.weight_in({"": cfg}) * values[term.name] for term in TERMS if term.name in values]
    total = weighted[0]
    for value in weighted[1:]:
        total = total + value
    return total
