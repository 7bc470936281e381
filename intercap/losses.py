"""Loss terms, each a small pure function named after its equation.

Stages compose them with weights from their config section. Shapes are
written (B frames, C views, h x w render grid).
"""
from __future__ import annotations

import torch


def geman_mcclure(residual: torch.Tensor, scale: float) -> torch.Tensor:
    """rho(r) = r^2 / (r^2 + s^2): quadratic near zero, saturates at 1 for outliers."""
    squared = residual * residual
    return squared / (squared + scale * scale)


def object_silhouette(rendered: torch.Tensor, observed: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """E_O's segmentation part, sum_v ||(R_S - S_v) * W_v||^2 / pixels, (B, C, h, w) -> (B,).

    InterCap writes the weight as S_v (only pixels of the observed mask count);
    alone that lets the rendering spill outside the mask for free, so W_v is 1
    over the crop except where the object may legitimately be hidden (pixels
    where something is measured in front of the rendered surface: a hand)."""
    error = (rendered - observed) ** 2 * weight
    return error.flatten(2).mean(-1).sum(-1)


def object_depth(
    rendered_depth: torch.Tensor,
    observed_depth: torch.Tensor,
    weight: torch.Tensor,
    scale: float,
) -> torch.Tensor:
    """E_O's depth part, sum_v rho(R_D - D_v) over the observed object pixels, (B, C, h, w) -> (B,).

    `weight` is S_v times the pixels where depth was measured and nothing stands
    in front of the object; where the rendering has no surface (R_D = 0) the
    pixel pays the saturated cost. rho is Geman-McClure with `scale` metres, so
    wrong Kinect depth cannot dominate. Normalised per view by the weight sum."""
    rho = geman_mcclure(rendered_depth - observed_depth, scale) * weight
    return (rho.flatten(2).sum(-1) / weight.flatten(2).sum(-1).clamp(min=1.0)).sum(-1)


def occlusion_weight(rendered_depth: torch.Tensor, observed_depth: torch.Tensor, margin: float) -> torch.Tensor:
    """1 where the object could be seen, 0 where the sensor measured something
    clearly in front of the rendered surface (an occluder such as a hand)."""
    occluded = (observed_depth > 0) & (rendered_depth > 0) & (observed_depth < rendered_depth - margin)
    return (~occluded).to(rendered_depth.dtype)


def rotation_6d_to_matrix(r6: torch.Tensor) -> torch.Tensor:
    """Continuous 6D rotation representation (..., 6) -> (..., 3, 3) by Gram-Schmidt (columns)."""
    a, b = r6[..., :3], r6[..., 3:]
    x = torch.nn.functional.normalize(a, dim=-1)
    y = torch.nn.functional.normalize(b - (x * b).sum(-1, keepdim=True) * x, dim=-1)
    z = torch.cross(x, y, dim=-1)
    return torch.stack([x, y, z], dim=-1)


def matrix_to_rotation_6d(R: torch.Tensor) -> torch.Tensor:
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)
