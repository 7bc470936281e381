"""Body model layer: one interface (`BodyModel`), backends anny (default) and SMPL-X."""
from __future__ import annotations

import dataclasses

import torch

from intercap.body_models.base import BodyModel, BodyOutput, BodyParams, axis_angle_to_matrix, matrix_to_axis_angle
from intercap.body_models.keypoints import KEYPOINT_NAMES, NUM_BODY_HANDS

BACKENDS = ("anny", "smplx")


def load_body_model(
    name: str = "anny",
    *,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    cache_dir: str | None = None,
    model_dir: str | None = None,
    **kwargs,
) -> BodyModel:
    """Construct a body model backend by name.

    anny needs nothing but its package (`cache_dir`: where its cache is built);
    smplx needs `model_dir`, the folder with the user's SMPL-X model files."""
    if name == "anny":
        from intercap.body_models.anny_backend import AnnyBody

        return AnnyBody(device=device, dtype=dtype, cache_dir=cache_dir, **kwargs)
    if name == "smplx":
        from intercap.body_models.smplx_backend import SmplxBody

        return SmplxBody(model_dir=model_dir, device=device, dtype=dtype, **kwargs)
    raise ValueError(f"unknown body model {name!r}; choose one of {BACKENDS}")


_SHARED: dict = {}


def setting_key(cfg) -> tuple:
    """A hashable key of a `BodyModelConfig`: what caches of per-model results are keyed on."""
    return tuple(sorted(dataclasses.asdict(cfg).items()))


def shared_model(cfg, device="cpu") -> BodyModel:
    """`load_from_config`, built once per process and setting (construction takes seconds, and a
    worker process fits one stage after another): shared, so callers must not change it."""
    key = (setting_key(cfg), str(device))
    if key not in _SHARED:
        _SHARED[key] = load_from_config(cfg, device)
    return _SHARED[key]


def load_from_config(cfg, device="cpu") -> BodyModel:
    """Body model from an `intercap.config.BodyModelConfig`."""
    return load_body_model(
        cfg.name,
        device=device,
        dtype=getattr(torch, cfg.dtype),
        cache_dir=cfg.cache_dir,
        model_dir=cfg.smplx_model_dir,
    )


__all__ = [
    "BodyModel", "BodyOutput", "BodyParams", "KEYPOINT_NAMES", "NUM_BODY_HANDS",
    "axis_angle_to_matrix", "matrix_to_axis_angle", "load_body_model", "load_from_config", "setting_key", "shared_model",
]
