"""SMPL-X backend, for users who hold the SMPL-X model files (never required).

Needs the optional `smplx` package (`pip install intercap[smplx]`) and a folder
with SMPLX_NEUTRAL.npz (or .pkl); SMPL-X's own licence applies to those files.
Model coordinates are SMPL-X's (y up, facing +z); world vertices are
``R(global_orient) @ v + transl`` like every backend here: the rotation is about
the model's origin. smplx itself rotates about the pelvis (the root joint of the
shaped rest pose, j0) and then adds its transl, so the same body in smplx's own
arguments has transl_smplx = transl + R j0 - j0 (`smplx_transl`,
`SmplxBody.smplx_parameters`, what the export writes as smplx_*).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from intercap.body_models.base import BodyModel, BodyOutput, BodyParams, axis_angle_to_matrix
from intercap.body_models.keypoints import NUM_ALL
from intercap.body_models.regions import contact_regions, farthest_point_subsample, palm_normal

JOINTS = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw", "left_eye", "right_eye",
]
HAND = [f"{f}{k}" for f in ("index", "middle", "pinky", "ring", "thumb") for k in (1, 2, 3)]
# smplx's extra joints after the 55 skeleton joints (its default vertex selector):
# nose, right/left eye, right/left ear, left big/small toe, heel, right big/small toe, heel,
# then fingertips left thumb..pinky (66-70), right thumb..pinky (71-75), then 51 face landmarks.
BODY25_FROM_SMPLX = [55, 12, 17, 19, 21, 16, 18, 20, 0, 2, 5, 8, 1, 4, 7, 56, 57, 58, 59, 60, 61, 62, 63, 64, 65]


def _hand_from_smplx(side: str) -> list[int]:
    """OpenPose hand order (wrist, thumb, index, middle, ring, little) in smplx joint ids."""
    base = 25 if side == "left" else 40
    tip0 = 66 if side == "left" else 71
    start = {f: base + 3 * i for i, f in enumerate(("index", "middle", "pinky", "ring", "thumb"))}
    wrist = 20 if side == "left" else 21
    ids = [wrist]
    for k, finger in enumerate(("thumb", "index", "middle", "ring", "pinky")):
        ids += [start[finger], start[finger] + 1, start[finger] + 2, tip0 + k]
    return ids


def smplx_transl(global_orient: torch.Tensor, transl: torch.Tensor, pelvis: torch.Tensor) -> torch.Tensor:
    """(B, 3) transl that smplx's forward needs to give our world vertices. Ours: R v + t, with v
    the body posed with no root rotation. smplx: its root joint's transform rotates the body about
    the rest pelvis j0 and keeps j0 in place, then adds transl: R (v - j0) + j0 + t_smplx. Equal for
    every v when t_smplx = t + R j0 - j0. global_orient is the same in both."""
    rotation = axis_angle_to_matrix(global_orient)  # (B, 3, 3)
    return transl + (rotation @ pelvis[..., None])[..., 0] - pelvis


def model_file(model_dir, gender: str = "neutral") -> Path:
    """The SMPL-X model file for `gender`: SMPLX_<GENDER>.npz (or .pkl) in `model_dir` itself or in its
    smplx/ folder (the layout smplx's own `create` expects of a folder)."""
    for folder in (Path(model_dir), Path(model_dir) / "smplx"):
        for ext in ("npz", "pkl"):
            path = folder / f"SMPLX_{gender.upper()}.{ext}"
            if path.is_file():
                return path
    raise FileNotFoundError(f"no SMPLX_{gender.upper()}.npz or .pkl in {model_dir} or {Path(model_dir) / 'smplx'} "
                            "(files from the SMPL-X website, under their licence)")


class SmplxBody(BodyModel):
    name = "smplx"

    def __init__(self, model_dir, device="cpu", dtype=torch.float32, gender="neutral", num_betas=10, num_expression=10):
        super().__init__()
        try:
            import smplx
        except ImportError as exc:
            raise ImportError("the SMPL-X backend needs `pip install intercap[smplx]`") from exc
        if model_dir is None or not Path(model_dir).exists():
            raise FileNotFoundError(
                f"SMPL-X model folder {model_dir!r} not found; set body_model.smplx_model_dir to the folder "
                "holding SMPLX_NEUTRAL.npz (files from the SMPL-X website, under their licence)"
            )
        self.core = smplx.create(
            str(model_file(model_dir, gender)), model_type="smplx", gender=gender, use_pca=False, flat_hand_mean=True,
            num_betas=num_betas, num_expression_coeffs=num_expression, use_face_contour=False,
        ).to(dtype=dtype)
        self.joint_names = JOINTS + [f"left_{h}" for h in HAND] + [f"right_{h}" for h in HAND]
        self.body_joint_names = JOINTS[1:]  # 21 body joints + jaw + eyes
        self.hand_joint_names = HAND
        self.num_shape = num_betas
        self.num_expression = num_expression
        self.register_buffer("faces", torch.as_tensor(np.asarray(self.core.faces, dtype=np.int64)))
        order = BODY25_FROM_SMPLX + _hand_from_smplx("left") + _hand_from_smplx("right")
        face = list(range(76, 76 + 51))  # OpenPose face landmarks 17..67
        self.register_buffer("keypoint_ids", torch.tensor(order))
        self.register_buffer("face_ids", torch.tensor(face))
        valid = torch.zeros(NUM_ALL, dtype=torch.bool)
        valid[: len(order)] = True
        valid[len(order) + 17 : len(order) + 68] = True
        self.keypoint_valid = valid
        self.up_axis = np.array([0.0, 1.0, 0.0])
        self.forward_axis = np.array([0.0, 0.0, 1.0])
        self._init_regions()
        self.to(device)

    def _init_regions(self) -> None:
        with torch.no_grad():
            rest = self.core(return_verts=True)
        vertices = rest.vertices[0].double().cpu().numpy()
        joints = rest.joints[0].double().cpu().numpy()
        dominant = self.core.lbs_weights.argmax(1).cpu().numpy()
        groups = {
            "hand.L": [20] + list(range(25, 40)), "hand.R": [21] + list(range(40, 55)),
            "foot.L": [7, 10], "foot.R": [8, 11], "forearm.L": [18], "forearm.R": [19],
            "thigh": [1, 2], "pelvis": [0],
        }
        palms = {"L": palm_normal(joints[20], joints[25], joints[31], "L"),
                 "R": palm_normal(joints[21], joints[40], joints[46], "R")}
        regions = contact_regions(
            vertices, self.faces.cpu().numpy(), dominant, groups, palms,
            up=self.up_axis, forward=self.forward_axis,
            hip_height=float(joints[1] @ self.up_axis), knee_height=float(joints[4] @ self.up_axis),
        )
        self.contact_regions = {k: torch.from_numpy(v) for k, v in regions.items()}
        self.fitting_subsample = torch.from_numpy(farthest_point_subsample(vertices, 2000))

    @property
    def dtype(self) -> torch.dtype:
        return self.core.shapedirs.dtype

    @property
    def num_vertices(self) -> int:
        return int(self.core.v_template.shape[0])

    def locate_joint(self, joint: str) -> tuple[str, int]:
        for side, prefix in (("L", "left_"), ("R", "right_")):
            if joint.startswith(prefix) and joint[len(prefix):] in HAND:
                return side, HAND.index(joint[len(prefix):])
        return "body", self.body_joint_names.index(joint)

    def rest_pelvis(self, params: BodyParams) -> torch.Tensor:
        """(B, 3) the root joint of the shaped rest pose (betas and expression; the pose does not move
        it), model coordinates: where smplx's global_orient rotates about."""
        batch = params.batch_size

        def zeros(n):
            return torch.zeros(batch, n, dtype=self.dtype, device=params.shape.device)

        # every pose given (smplx's own defaults have batch size 1)
        out = self.core(betas=params.shape, expression=params.expression, global_orient=zeros(3), transl=zeros(3),
                        body_pose=zeros(63), jaw_pose=zeros(3), leye_pose=zeros(3), reye_pose=zeros(3),
                        left_hand_pose=zeros(45), right_hand_pose=zeros(45), return_verts=False)
        return out.joints[:, 0]

    def smplx_parameters(self, params: BodyParams) -> dict[str, torch.Tensor]:
        """Our parameters as smplx's own forward arguments (for `smplx.create(model_type="smplx",
        use_pca=False, flat_hand_mean=True)` with this model's num_betas and num_expression_coeffs):
        the same vertices, with transl moved to smplx's rotation about the pelvis."""
        batch = params.batch_size
        body = params.body_pose  # (B, 24, 3): 21 body joints, jaw, left eye, right eye
        return {
            "betas": params.shape, "global_orient": params.global_orient,
            "transl": smplx_transl(params.global_orient, params.transl, self.rest_pelvis(params)),
            "body_pose": body[:, :21].reshape(batch, -1), "jaw_pose": body[:, 21], "leye_pose": body[:, 22],
            "reye_pose": body[:, 23], "left_hand_pose": params.left_hand_pose.reshape(batch, -1),
            "right_hand_pose": params.right_hand_pose.reshape(batch, -1), "expression": params.expression,
        }

    def forward(self, params: BodyParams) -> BodyOutput:
        batch = params.batch_size
        body = params.body_pose  # (B, 24, 3): 21 body joints, jaw, left eye, right eye
        zeros = torch.zeros(batch, 3, dtype=self.dtype, device=body.device)
        out = self.core(
            betas=params.shape, global_orient=zeros, transl=zeros,
            body_pose=body[:, :21].reshape(batch, -1), jaw_pose=body[:, 21], leye_pose=body[:, 22],
            reye_pose=body[:, 23], left_hand_pose=params.left_hand_pose.reshape(batch, -1),
            right_hand_pose=params.right_hand_pose.reshape(batch, -1), expression=params.expression,
            return_verts=True,
        )
        face = torch.zeros(batch, 70, 3, dtype=self.dtype, device=body.device)
        face[:, 17:68] = out.joints[:, self.face_ids]
        keypoints = torch.cat([out.joints[:, self.keypoint_ids], face], dim=1)  # (B, 137, 3)
        return self.world_output(out.vertices, out.joints[:, :55], keypoints, params)
