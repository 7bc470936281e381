"""Learned motion smoothness priors (LEMO-style) for the body (E_S) and each hand (E_L, E_R).

After Zhang et al. 2021, "Learning motion priors for 4D human body capture" (LEMO):
a temporal convolutional autoencoder is trained on the velocities of surface
markers over real motion, with its latent sequence kept smooth; a motion is then
scored by how much its latent code changes from frame to frame,

    E_S = sum_t || z_{t+1} - z_t ||^2 ,   z = encoder(marker velocities) (C_z, T-1),

which is small for real-looking motion and large for jitter, spikes and
motion no person makes. Only the encoder is needed here (the decoder served
the training, `tools/train_motion_prior.py`). One change to LEMO's training:
the autoencoder also reconstructs jittered copies of the motion, while only the
clean motion's code is kept smooth. Trained on clean motion alone, the encoder
learns to low-pass its input and so hides jitter (5 mm of jitter raised the
score only x1.8); made to carry the jitter, it shows it (x45).

What it is good for, measured (tools/bench_motion_prior.py, held-out CMU clips):
it separates real from jittered or spiked motion far better than the plain
acceleration penalty, but as the only smoothness term of a denoising fit it does
not beat the acceleration penalty: minimising it finds motions whose code is
smoother than real motion's without removing all the jitter. Use it beside the
acceleration term, not instead of it (see intercap/data/README.md for figures).

Inputs, so that the score does not depend on where the person stands or faces:
  * markers are fixed anny vertices (farthest-point sampled on the rest mesh,
    left-right symmetric), their velocities in m/s (fps-independent units);
  * velocities are expressed in the pelvis heading frame: lateral axis from the
    right to the left hip, projected off `up` and smoothed over ~0.5 s; up is the
    ground normal when given, else the mean pelvis-to-neck direction of the
    sequence. So the score is invariant to global translation and heading (and to
    any rotation when `up` is rotated with the motion or left to be estimated).
  * hand: positions of hand markers (back of the hand and palm, no fingers)
    relative to a wrist point, in the same heading frame. One network serves both
    hands: it is trained on right hands and mirrored left hands, and the left hand
    is scored mirrored (its markers are the mirror images of the right ones).

Hands: the training motion (CMU mocap) has one rigid hand segment, no fingers, so
the hand prior knows wrist/hand orientation dynamics only; it says nothing about
finger articulation (no open finger-motion data was found).

The networks run at MODEL_FPS (30). Other frame rates are scored on the
interleaved sub-sequences x[k::r], r = round(fps / 30), so every frame counts.

Shapes: vertices (T, V, 3) or batched (B, T, V, 3) in metres, V = anny's vertex
count, or V = len(prior.point_ids) for the compact point set the prior reads.
"""
from __future__ import annotations

import functools
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import nn

DATA_DIR = Path(__file__).resolve().parents[1] / "data"  # intercap/data
PRIOR_FILES = {"body": DATA_DIR / "motion_prior_body.npz", "hand": DATA_DIR / "motion_prior_hand.npz"}
MODEL_FPS = 30.0
HEADING_SMOOTH_S = 0.5  # box filter over the lateral hip axis, seconds
LEAKY_SLOPE = 0.2


class TemporalConvNet(nn.Module):
    """1D temporal convolutions over (B, C, T): replicate padding keeps the length; LeakyReLU
    between layers, the last layer linear."""

    def __init__(self, channels: Sequence[int], kernel: int):
        super().__init__()
        self.layers = nn.ModuleList(
            nn.Conv1d(a, b, kernel, padding=kernel // 2, padding_mode="replicate")
            for a, b in zip(channels[:-1], channels[1:])
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for k, layer in enumerate(self.layers):
            x = layer(x)
            if k < len(self.layers) - 1:
                x = nn.functional.leaky_relu(x, LEAKY_SLOPE)
        return x


class MotionPrior(nn.Module):
    """One trained prior ('body' or 'hand'): its point ids on anny, input normalisation and encoder.

    Buffers (ids index `point_ids`, the compact point set, except `point_ids` itself which
    indexes anny's vertices): markers (M,) [hand: markers_R / markers_L, wrist_R / wrist_L (K,)],
    hip_L, hip_R, neck (K,), feature_mean / feature_std (3M,)."""

    def __init__(self, kind: str, arrays: dict[str, np.ndarray], channels: Sequence[int], kernel: int,
                 num_vertices: int):
        super().__init__()
        self.kind = kind
        self.num_vertices = num_vertices
        self.encoder = TemporalConvNet(channels, kernel)
        for name in ("point_ids", "hip_L", "hip_R", "neck", "feature_mean", "feature_std"):
            self.register_buffer(name, torch.as_tensor(arrays[name]))
        names = ("markers",) if kind == "body" else ("markers_R", "markers_L", "wrist_R", "wrist_L")
        for name in names:
            self.register_buffer(name, torch.as_tensor(arrays[name]))

    def compact(self, vertices: torch.Tensor) -> torch.Tensor:
        """(..., V, 3) anny vertices or compact points -> (..., U, 3) compact points."""
        if vertices.shape[-2] == len(self.point_ids):
            return vertices
        if vertices.shape[-2] != self.num_vertices:
            raise ValueError(f"motion prior expects anny vertices ({self.num_vertices}) or its "
                             f"{len(self.point_ids)} points, got {vertices.shape[-2]}")
        return vertices.index_select(-2, self.point_ids)

    def features(self, points: torch.Tensor, fps: float, up: torch.Tensor | None, side: str = "R") -> torch.Tensor:
        """Compact points (B, T, U, 3) -> normalised velocity features (B, 3M, T-1)."""
        R = heading_frames(points, self, fps, up)  # (B, T, 3, 3) columns: lateral, forward, up
        if self.kind == "body":
            markers = points[:, :, self.markers]  # (B, T, M, 3)
        else:
            wrist = getattr(self, f"wrist_{side}")
            markers = points[:, :, getattr(self, f"markers_{side}")] - points[:, :, wrist].mean(2, keepdim=True)
        velocity = (markers[:, 1:] - markers[:, :-1]) * fps  # (B, T-1, M, 3) m/s
        local = torch.einsum("btij,btmi->btmj", R[:, :-1], velocity)  # R^T v
        if self.kind == "hand" and side == "L":  # mirror the left hand onto a right hand: flip the lateral axis
            local = local * local.new_tensor([-1.0, 1.0, 1.0])
        feats = local.flatten(2)  # (B, T-1, 3M)
        return ((feats - self.feature_mean) / self.feature_std).transpose(1, 2)

    def latent(self, points: torch.Tensor, fps: float, up: torch.Tensor | None, side: str = "R") -> torch.Tensor:
        """Compact points (B, T, U, 3) -> latent sequence z (B, C_z, T-1)."""
        return self.encoder(self.features(points, fps, up, side))


def heading_frames(points: torch.Tensor, prior: MotionPrior, fps: float, up: torch.Tensor | None) -> torch.Tensor:
    """Pelvis heading frame per frame, (B, T, 3, 3) with columns (lateral, forward, up).

    Lateral: right hip -> left hip, made orthogonal to `up` and box-filtered over HEADING_SMOOTH_S;
    forward = lateral x up (anny faces -y with left +x, z up). `up` (3,) or (B, 3); None: the
    sequence's mean pelvis-to-neck direction."""
    hip_l = points[:, :, prior.hip_L].mean(2)  # (B, T, 3)
    hip_r = points[:, :, prior.hip_R].mean(2)
    if up is None:
        trunk = points[:, :, prior.neck].mean(2) - (hip_l + hip_r) / 2
        up = trunk.mean(1)  # (B, 3)
    up = torch.as_tensor(up, dtype=points.dtype, device=points.device).expand(points.shape[0], 3)
    up = nn.functional.normalize(up, dim=-1)[:, None]  # (B, 1, 3)
    lateral = hip_l - hip_r
    lateral = lateral - (lateral * up).sum(-1, keepdim=True) * up
    width = max(1, int(round(HEADING_SMOOTH_S * fps / 2)))
    if points.shape[1] > 1:
        padded = nn.functional.pad(lateral.transpose(1, 2), (width, width), mode="replicate")  # (B, 3, T+2w)
        lateral = nn.functional.avg_pool1d(padded, 2 * width + 1, stride=1).transpose(1, 2)
    lateral = nn.functional.normalize(lateral, dim=-1)
    up = up.expand_as(lateral)
    forward = torch.cross(lateral, up, dim=-1)
    return torch.stack([lateral, forward, up], dim=-1)


def latent_smoothness(z: torch.Tensor) -> torch.Tensor:
    """E_S = sum_t ||z_{t+1} - z_t||^2 over a latent sequence (..., C, T) -> (...)."""
    return (z[..., 1:] - z[..., :-1]).pow(2).sum((-2, -1))


def acceleration_penalty(points: torch.Tensor, fps: float) -> torch.Tensor:
    """Baseline: sum_t mean_n ||x_{t+1} - 2 x_t + x_{t-1}||^2 fps^4, in (m/s^2)^2.

    points (T, N, 3) -> scalar, or (B, T, N, 3) -> (B,)."""
    acc = (points[..., 2:, :, :] - 2 * points[..., 1:-1, :, :] + points[..., :-2, :, :]) * fps**2
    return acc.pow(2).sum(-1).mean(-1).sum(-1)


@functools.lru_cache(maxsize=8)
def _load(kind: str, device: str, dtype: torch.dtype) -> MotionPrior:
    path = PRIOR_FILES[kind]
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing; build it with `python tools/train_motion_prior.py`")
    data = np.load(path)
    channels = [int(c) for c in data["channels"]]
    prior = MotionPrior(kind, {k: data[k] for k in data.files}, channels, int(data["kernel"]),
                        int(data["num_vertices"]))
    state = {k[len("encoder."):]: torch.from_numpy(data[k].astype(np.float32))
             for k in data.files if k.startswith("encoder.")}
    prior.encoder.load_state_dict(state)
    prior = prior.to(device=device, dtype=dtype).eval()
    for p in prior.parameters():
        p.requires_grad_(False)
    return prior


def load_motion_prior(kind: str = "body", device: str | torch.device = "cpu",
                      dtype: torch.dtype = torch.float32) -> MotionPrior:
    """The shipped prior 'body' or 'hand' (cached; frozen, gradients flow to the inputs only)."""
    if kind not in PRIOR_FILES:
        raise ValueError(f"unknown motion prior {kind!r}; choose 'body' or 'hand'")
    return _load(kind, str(torch.device(device)), dtype)


def _phases(points: torch.Tensor, fps: float) -> tuple[torch.Tensor, float, int]:
    """(B, T, U, 3) at `fps` -> (B*r, T//r, U, 3) interleaved sub-sequences near MODEL_FPS, their fps, r."""
    r = max(1, int(round(fps / MODEL_FPS)))
    if r == 1:
        return points, fps, 1
    n = points.shape[1] // r
    if n < 3:
        raise ValueError(f"{points.shape[1]} frames at {fps} fps are too few for the motion prior")
    sub = points[:, : n * r].unflatten(1, (n, r)).movedim(2, 1)  # (B, r, n, U, 3)
    return sub.flatten(0, 1), fps / r, r


def motion_smoothness(vertices: torch.Tensor, fps: float, prior: MotionPrior, up=None, side: str = "R") -> torch.Tensor:
    """E_S of a vertex sequence under `prior`: (T, V, 3) -> scalar, (B, T, V, 3) -> (B,)."""
    single = vertices.dim() == 3
    points = prior.compact(vertices[None] if single else vertices)  # (B, T, U, 3)
    if points.shape[1] < 3:
        raise ValueError("the motion prior needs at least 3 frames")
    batch = points.shape[0]
    points, fps_r, r = _phases(points, float(fps))
    if up is not None:
        up = torch.as_tensor(up, dtype=points.dtype, device=points.device)
        up = up.expand(batch, 3).repeat_interleave(r, 0) if up.dim() == 2 else up
    value = latent_smoothness(prior.latent(points, fps_r, up, side)).view(batch, r).sum(1) / r
    return value[0] if single else value


def body_motion_smoothness(vertices: torch.Tensor, fps: float, up=None) -> torch.Tensor:
    """E_S, the learned body motion prior: anny vertices (T, V, 3) -> scalar (or (B, T, V, 3) -> (B,)).

    `up` (3,) or (B, 3): the world's up direction (the ground normal); None estimates it from the body."""
    return motion_smoothness(vertices, fps, load_motion_prior("body", vertices.device, vertices.dtype), up)


def hand_motion_smoothness(vertices: torch.Tensor, fps: float, side: str, up=None) -> torch.Tensor:
    """E_L / E_R, the learned hand motion prior (wrist/hand dynamics only; no fingers in the training
    data): anny vertices (T, V, 3) -> scalar (or (B, T, V, 3) -> (B,)); side 'L' or 'R'."""
    side = {"left": "L", "right": "R"}.get(side, side)
    if side not in ("L", "R"):
        raise ValueError(f"side must be 'L' or 'R', got {side!r}")
    return motion_smoothness(vertices, fps, load_motion_prior("hand", vertices.device, vertices.dtype), up, side)
