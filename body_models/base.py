"""The one narrow interface every body model backend implements.

A backend turns a :class:`BodyParams` batch into a :class:`BodyOutput`:
world-space vertices, joints and OpenPose-ordered keypoints. Stages only ever
talk to this interface, so the fitting code does not care whether anny or
SMPL-X is underneath.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import roma
import torch

PARAM_FIELDS = (
    "shape",
    "global_orient",
    "transl",
    "body_pose",
    "left_hand_pose",
    "right_hand_pose",
    "expression",
)


@dataclass
class BodyParams:
    """A batch of body-model parameters, batch dimension first.

    shape (B, S); global_orient (B, 3) axis-angle; transl (B, 3) metres;
    body_pose (B, Jb, 3), left_hand_pose / right_hand_pose (B, Jh, 3) axis-angle
    per bone in the model's `body_joint_names` / `hand_joint_names` order;
    expression (B, E). World vertices are ``R(global_orient) @ v_model + transl``.
    """

    shape: torch.Tensor
    global_orient: torch.Tensor
    transl: torch.Tensor
    body_pose: torch.Tensor
    left_hand_pose: torch.Tensor
    right_hand_pose: torch.Tensor
    expression: torch.Tensor

    @property
    def batch_size(self) -> int:
        return int(self.transl.shape[0])

    def tensors(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, name) for name in PARAM_FIELDS}

    def map(self, fn) -> "BodyParams":
        """A new BodyParams with `fn` applied to every tensor."""
        return BodyParams(**{name: fn(t) for name, t in self.tensors().items()})

    def to(self, *args, **kwargs) -> "BodyParams":
        return self.map(lambda t: t.to(*args, **kwargs))

    def detach(self) -> "BodyParams":
        return self.map(lambda t: t.detach())

    def clone(self) -> "BodyParams":
        return self.map(lambda t: t.clone())

    def __getitem__(self, index) -> "BodyParams":
        """Select frames: an int keeps the batch dimension."""
        if isinstance(index, int):
            index = slice(index, index + 1)
        return self.map(lambda t: t[index])

    @staticmethod
    def cat(items: list["BodyParams"]) -> "BodyParams":
        return BodyParams(
            **{name: torch.cat([getattr(p, name) for p in items]) for name in PARAM_FIELDS}
        )

    def to_numpy_dict(self) -> dict[str, np.ndarray]:
        return {name: t.detach().cpu().numpy() for name, t in self.tensors().items()}

    @staticmethod
    def from_numpy_dict(data, device="cpu", dtype=torch.float32) -> "BodyParams":
        missing = [name for name in PARAM_FIELDS if name not in data]
        if missing:
            raise KeyError(f"body parameters are missing {missing}")
        return BodyParams(
            **{name: torch.as_tensor(np.asarray(data[name]), device=device, dtype=dtype) for name in PARAM_FIELDS}
        )


@dataclass
class BodyOutput:
    """Posed body in world coordinates.

    vertices (B, V, 3); joints (B, J, 3) in the model's `joint_names` order;
    keypoints (B, K, 3) in OpenPose order (BODY_25, left hand 21, right hand 21,
    then face 70 where the model has face landmarks).
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    keypoints: torch.Tensor


_SKEW = {}  # (device, dtype) -> (3, 9): a rotation vector times it is its cross-product matrix, row-major


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors -> (..., 3, 3) matrices by Rodrigues' formula, R = I + a K + b K^2
    with K the cross-product matrix, a = sin t / t and b = (1 - cos t) / t^2 = (sin(t/2) / (t/2))^2 / 2
    (no cancellation at small angles). Smooth at zero, exact gradients there (the clamped angle only
    scales K and K^2, both zero there). About 70 kernels forward and backward, against roma's 150:
    every body evaluation converts each joint's rotation vector."""
    key = (axis_angle.device, axis_angle.dtype)
    if key not in _SKEW:
        skew = torch.zeros(3, 9, dtype=axis_angle.dtype)
        for axis, (row, col, sign) in enumerate(((2, 1, 1.0), (0, 2, 1.0), (1, 0, 1.0))):
            skew[axis, 3 * row + col], skew[axis, 3 * col + row] = sign, -sign
        _SKEW[key] = skew.to(axis_angle.device)
    squared = (axis_angle * axis_angle).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    half = 0.5 * squared.clamp(min=1e-12).sqrt()
    sin_half, cos_half = torch.sin(half), torch.cos(half)
    k = (axis_angle @ _SKEW[key]).unflatten(-1, (3, 3))
    first = sin_half * cos_half / half
    second = 0.5 * (sin_half / half) ** 2
    return torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device) + first * k + second * (k @ k)


def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle (roma, numerically robust)."""
    return roma.rotmat_to_rotvec(matrix)


def continuous_axis_angle(rotvecs: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(T, 3) rotation vectors, each valid one replaced by the equivalent vector (the same axis, its angle
    plus a whole number of turns) nearest the previous valid frame's, so that a person or an object turning
    past half a turn does not jump by 2 pi: interpolating or averaging them then turns the short way.
    The others (`valid` False, or not finite) are left as they are."""
    out = np.array(rotvecs, np.float64)
    previous = None
    usable = np.isfinite(out).all(1) & (True if valid is None else np.asarray(valid, bool))
    for i in np.flatnonzero(usable):
        angle = float(np.linalg.norm(out[i]))
        if previous is not None and angle > 1e-9:
            axis = out[i] / angle
            turns = np.round((float(previous @ axis) - angle) / (2 * np.pi)) + np.array([-1.0, 0.0, 1.0])
            options = axis[None] * (angle + 2 * np.pi * turns)[:, None]
            out[i] = options[np.argmin(np.linalg.norm(options - previous, axis=1))]
        previous = out[i]
    return out


def fill_axis_angle_gaps(rotvecs: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T, 3) rotation vectors with the frames not `valid` interpolated between the nearest valid ones (held
    at the ends) the short way round (`continuous_axis_angle`), each filled one at most half a turn; the
    valid frames keep their own."""
    from scipy.spatial.transform import Rotation

    out = np.array(rotvecs, np.float64)
    valid = np.asarray(valid, bool) & np.isfinite(out).all(1)
    if valid.all() or not valid.any():
        return out
    turned = continuous_axis_angle(out, valid)
    t = np.arange(len(out))
    filled = np.stack([np.interp(t[~valid], t[valid], turned[valid, k]) for k in range(3)], 1)
    out[~valid] = Rotation.from_rotvec(filled).as_rotvec()
    return out


class BodyModel(torch.nn.Module):
    """Base class of the backends: what every stage may rely on.

    Attributes set by backends: `name`, `faces` (F, 3) long buffer,
    `joint_names`, `body_joint_names`, `hand_joint_names`, `num_shape`,
    `num_expression`, `keypoint_valid` (K,) bool (which OpenPose keypoints the
    model really has), `contact_regions` (name -> vertex ids), `fitting_subsample`
    (vertex ids), `up_axis` and `forward_axis` (model coordinates).
    """

    name: str = "base"

    def init_params(self, batch_size: int = 1, device=None, dtype=None) -> BodyParams:
        """Neutral shape, rest pose, identity orientation, zero translation."""
        device = device or self.faces.device
        dtype = dtype or self.dtype

        def zeros(*shape):
            return torch.zeros(batch_size, *shape, device=device, dtype=dtype)

        return BodyParams(
            shape=self.neutral_shape().to(device=device, dtype=dtype).expand(batch_size, -1).clone(),
            global_orient=zeros(3),
            transl=zeros(3),
            body_pose=zeros(len(self.body_joint_names), 3),
            left_hand_pose=zeros(len(self.hand_joint_names), 3),
            right_hand_pose=zeros(len(self.hand_joint_names), 3),
            expression=zeros(self.num_expression),
        )

    def neutral_shape(self) -> torch.Tensor:
        return torch.zeros(1, self.num_shape)

    @property
    def num_vertices(self) -> int:
        raise NotImplementedError

    @property
    def num_keypoints(self) -> int:
        return int(self.keypoint_valid.shape[0])

    def forward(self, params: BodyParams) -> BodyOutput:  # pragma: no cover - abstract
        raise NotImplementedError

    def rest_state(self, params: BodyParams, vertex_ids: torch.Tensor):
        """What `sparse_forward` can reuse while shape and expression stay fixed (None: nothing)."""
        return None

    def sparse_forward(self, params: BodyParams, vertex_ids: torch.Tensor, rest=None) -> BodyOutput:
        """`forward` keeping only the vertices `vertex_ids`; backends override it with a cheaper path
        (and may reuse `rest`, their `rest_state` for the same shape, expression and vertices)."""
        out = self.forward(params)
        return BodyOutput(vertices=out.vertices[:, vertex_ids], joints=out.joints, keypoints=out.keypoints)

    @staticmethod
    def to_world(points: torch.Tensor, params: BodyParams) -> torch.Tensor:
        """Model coordinates (B, N, 3) -> world with global_orient and transl."""
        rotation = axis_angle_to_matrix(params.global_orient)  # (B, 3, 3)
        return points @ rotation.transpose(1, 2) + params.transl[:, None, :]

    @classmethod
    def world_output(cls, vertices: torch.Tensor, joints: torch.Tensor, keypoints: torch.Tensor,
                     params: BodyParams) -> BodyOutput:
        """A BodyOutput of model-coordinate vertices, joints and keypoints moved to the world
        together (one rotation and one product instead of three: fitting calls it thousands of times)."""
        world = cls.to_world(torch.cat([vertices, joints, keypoints], 1), params)
        vertices, joints, keypoints = world.split([vertices.shape[1], joints.shape[1], keypoints.shape[1]], 1)
        return BodyOutput(vertices=vertices, joints=joints, keypoints=keypoints)

    def set_pose(self, params: BodyParams, joint: str, axis_angle: torch.Tensor) -> None:
        """Set one bone's local rotation in place, by the backend's bone name.

        Hand bones are named with the backend's side suffix (anny: '.L'/'.R')."""
        side, index = self.locate_joint(joint)
        target = {"body": params.body_pose, "L": params.left_hand_pose, "R": params.right_hand_pose}[side]
        target[:, index] = torch.as_tensor(axis_angle, dtype=target.dtype, device=target.device)

    def locate_joint(self, joint: str) -> tuple[str, int]:  # pragma: no cover - abstract
        raise NotImplementedError


def replace(params: BodyParams, **changes) -> BodyParams:
    return dataclasses.replace(params, **changes)
