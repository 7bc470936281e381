"""The `body` stage: per-frame whole-body fitting to multi-view keypoints and depth (PROX-D).

For every frame the body model (anny by default) is fitted to
  * E_J, the 2D keypoints of every view (BODY_25 + both hands; the session's
    OpenPose JSON, or the `detect` stage's), reprojected through each camera
    with its lens distortion, Geman-McClure robust, weighted by confidence^2;
  * E_D, each view's segmented person points against the body vertices that
    view can see (visibility by a coarse z-buffer of the whole mesh plus the
    normal facing the camera, recomputed at every L-BFGS step);
  * priors: learned body-pose mixture + anatomical joint limits + extreme
    elbow/knee bending, finger ranges, shape, expression, and self-penetration
    approximated by spheres along the limbs and trunk (see `BodySpheres`).
As SMPLify-X, in phases (`PHASES`): orientation and translation from the torso
keypoints, then pose and shape from all keypoints, then everything with the
depth term. Frames are fitted in batches (the frames do not interact: each has
its own L-BFGS, batched as tensors, `minimise_per_frame`), initialised per frame
by aligning the previous batch's pose to the triangulated torso keypoints; a
process may fit several chunks of the take side by side, their batches in one
evaluation (`fit_chunks`: on a GPU that divides the kernel launches per frame by
their number); the phenotype is fitted on the first
`shape_batches` batches and held at their mean after (one person: re-fitted per
batch it drifted). A frame with too little evidence (see
`usable_frames`) is marked invalid and written as NaN, never invented.

Outputs (SESSION_FORMAT.md): body_params.npz (the model's parameters per
frame, `model`, `valid`, per-frame `shape` and its sequence mean `shape_mean`),
body_vertices.npy, body_faces.npy, keypoints3d.npy, kept in OUT/body/ (with
the resumable checkpoint and overlay pictures) and shown at OUT/ until the
`global` stage replaces them with its own.
"""
from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.spatial import cKDTree

from intercap.body_models import BodyParams, shared_model
from intercap.body_models.base import axis_angle_to_matrix, matrix_to_axis_angle
from intercap.body_models.keypoints import BODY_25, BODY_25_EDGES, NUM_BODY, NUM_BODY_HANDS
from intercap.energies import losses, optim, priors
from intercap.energies.optim import minimise, minimise_per_frame
from intercap.geometry.cameras import Cameras, _remove_intrinsics, pixel_rays, project, undistort
from intercap.geometry.ground import up_hint_from_cameras
from intercap.io.files import per_frame_result, publish, read_json, save_npy, save_npz
from intercap.stages.chunks import Chunk, lockstep, run_chunks
from intercap.stages.chunks import chunk_groups as parallel_chunk_groups
from intercap.session.session import in_threads

log = logging.getLogger(__name__)

SHAPE_EPS = 1e-3  # shape logits start at most this close to the ends of [0, 1]
# Bones the keypoints cannot see: they stay at rest.
FROZEN_BONE_PREFIXES = ("toe", "eye", "pelvis")
TORSO_KEYPOINTS = [BODY_25.index(n) for n in
                   ("neck", "right_shoulder", "left_shoulder", "mid_hip", "right_hip", "left_hip")]
# What the orient phase fits: the trunk and the legs, so a tilt of the trunk is not taken for a
# tilt of the whole body.
ORIENT_KEYPOINTS = TORSO_KEYPOINTS + [BODY_25.index(n) for n in
                                      ("right_knee", "left_knee", "right_ankle", "left_ankle")]
FOOT_KEYPOINTS = [BODY_25.index(n) for n in ("right_ankle", "left_ankle", "left_big_toe", "left_small_toe",
                                             "left_heel", "right_big_toe", "right_small_toe", "right_heel")]


# ---------------------------------------------------------------------------
# Observations
# ---------------------------------------------------------------------------

@dataclass
class BodyObservations:
    """What a batch of frames gives the fit. B frames, C views, K = 67 keypoints, P points per view."""

    frame_ids: np.ndarray  # (B,)
    keypoints: torch.Tensor  # (B, C, K, 3) pixels x, y and confidence (0 = not detected)
    points: torch.Tensor  # (B, C, P, 3) segmented person points, world
    point_valid: torch.Tensor  # (B, C, P) bool

    @property
    def batch_size(self) -> int:
        return int(self.keypoints.shape[0])

    @staticmethod
    def cat(items: list["BodyObservations"]) -> "BodyObservations":
        """The frames of all `items`, in order."""
        return BodyObservations(np.concatenate([o.frame_ids for o in items]), torch.cat([o.keypoints for o in items]),
                                torch.cat([o.points for o in items]), torch.cat([o.point_valid for o in items]))

    def select(self, index) -> "BodyObservations":
        """The observations of frames `index` (an index array; repeats allowed)."""
        rows = torch.as_tensor(index, device=self.keypoints.device)
        return BodyObservations(self.frame_ids[np.asarray(index)], self.keypoints[rows], self.points[rows],
                                self.point_valid[rows])


class KeypointSource:
    """Per view and frame, the (137, 3) OpenPose keypoints: the session's JSON where that view and
    frame has one, otherwise what the `detect` stage wrote under OUT/detect/."""

    def __init__(self, session, out_dir: Path, use_session: bool = True, cameras: Cameras | None = None,
                 view_check_px: float = 0.0):
        from intercap.stages.detect.stage import keypoints_path

        self.session = session
        # `reject_disagreeing_views` when both set; on the CPU, as a GPU would take a launch (and a wait)
        # for each of its small steps, and so that a GPU run drops the keypoints a CPU run drops
        self.cameras = None if cameras is None else cameras.to(device="cpu")
        self.view_check_px = view_check_px
        self.rejected = 0  # keypoints dropped by that check so far
        self.out_dir = Path(out_dir)
        self._path = keypoints_path
        self.use_session = use_session
        self.from_session = use_session and not session.missing("keypoints").any()
        if not self.from_session and not (self.out_dir / "detect" / "DONE.json").exists():
            raise RuntimeError(
                "the body fit needs 2D keypoints: the session lacks them for some views or frames and the `detect` "
                f"stage has not run into {self.out_dir}; run `intercap run SESSION --out OUT` (detect runs before body)"
            )

    def read(self, c: int, frame_id: int) -> np.ndarray | None:
        if self.use_session and self.session.has_frame(c, "keypoints", frame_id):
            return self.session.read_keypoints(c, frame_id)
        from intercap.session import openpose_to_array

        path = self._path(self.out_dir, self.session.camera_names[c], frame_id)
        if not path.exists():
            return None
        return openpose_to_array(read_json(path))[0]

    def batch(self, frame_ids: np.ndarray, min_confidence: float) -> np.ndarray:
        """(B, C, 67, 3) float32; confidences below `min_confidence` (and missing views) read 0."""
        out = np.zeros((len(frame_ids), self.session.num_cameras, NUM_BODY_HANDS, 3), np.float32)
        for b, f in enumerate(frame_ids):
            for c in range(self.session.num_cameras):
                kp = self.read(c, int(f))
                if kp is not None:
                    out[b, c] = kp[:NUM_BODY_HANDS]
        out[..., 2] = np.where(out[..., 2] >= min_confidence, out[..., 2], 0.0)
        if self.cameras is not None and self.view_check_px > 0:
            checked = reject_disagreeing_views(torch.from_numpy(out).to(self.cameras.K), self.cameras,
                                               self.view_check_px).numpy()
            self.rejected += int(((out[..., 2] > 0) & (checked[..., 2] == 0)).sum())
            out = checked
        return out


def pixels_inside(keypoints: np.ndarray, height: int, width: int) -> np.ndarray:
    """(N, 2) integer pixels (x, y) of the confident keypoints (K, 3) that lie in the image."""
    xy = np.round(keypoints[keypoints[:, 2] > 0, :2]).astype(int)
    return xy[(xy[:, 0] >= 0) & (xy[:, 0] < width) & (xy[:, 1] >= 0) & (xy[:, 1] < height)]


class PersonPoints:
    """Segmented person points per view: the session's person masks, or depth foreground minus the
    object (its mask, or its tracked pose rendered) inside the keypoints' bounding box."""

    def __init__(self, session, cameras: Cameras, cfg, out_dir: Path):
        self.session = session
        self.cameras = cameras
        self.cfg = cfg
        self.session_masks = cfg.use_session_masks  # where a view and frame has its own mask file
        derives = not cfg.use_session_masks or session.missing("mask_person").any()
        # kept on the CPU: only read as numpy when picking points
        self.rays = [pixel_rays(cameras.select([c]), cam.height, cam.width)[0].cpu()
                     for c, cam in enumerate(session.cameras)]
        self._background = None
        self._lock = threading.Lock()
        self._object = None
        self._T = cameras.T_world_from_cam.cpu().numpy()  # for `frame`'s points
        self.ground = None  # (point, normal) of the floor, when prepare found it (`still_mask`)
        self.still_views = 0  # view-frames whose mask `still_mask` made, so far
        if (Path(out_dir) / "prepare" / "ground.json").exists():
            from intercap.stages.prepare.stage import load_ground

            plane = load_ground(out_dir)
            self.ground = (np.asarray(plane.point, np.float64), np.asarray(plane.normal, np.float64))
        poses = per_frame_result(out_dir, "object", "object_poses.npz")
        if derives and session.object is not None and poses.exists():
            data = np.load(poses)
            mesh = session.object.load_mesh()
            self._object = (np.asarray(mesh.vertices), np.asarray(mesh.faces), data["R"], data["t"],
                            {int(f): i for i, f in enumerate(data["frame_ids"])})

    def _backgrounds(self) -> list[np.ndarray]:
        from intercap.geometry.segmentation import background_depth
        from intercap.stages.prepare.stage import spread_frames

        with self._lock:  # `batch`'s threads ask at once
            if self._background is None:
                ids = spread_frames(self.session.frame_ids, 30)
                stacks = [[self.session.read_depth(c, int(f)) for f in ids] for c in range(self.session.num_cameras)]
                self._background = [
                    background_depth(np.stack([d for d in stack if d is not None])) for stack in stacks
                ]
        return self._background

    def object_mask(self, c: int, frame_id: int, shape) -> np.ndarray:
        mask = self.session.read_mask(c, frame_id, "object") if self.session.has_kind("mask_object")[c] else None
        if mask is None and self._object is not None:
            from intercap.stages.object.stage import hard_silhouettes

            vertices, faces, R, t, index = self._object
            i = index.get(frame_id)
            if i is not None and np.isfinite(R[i]).all():
                world = vertices @ R[i].T + t[i]
                mask = hard_silhouettes(world, faces, self.cameras.select([c]), [shape])[0]
        if mask is None:
            return np.zeros(shape, bool)
        return cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)

    def mask(self, c: int, frame_id: int, depth: np.ndarray, keypoints: np.ndarray) -> np.ndarray | None:
        """The person mask of view c: the session's file where it has one, else derived from depth."""
        if self.session_masks and self.session.has_frame(c, "mask_person", frame_id):
            mask = self.session.read_mask(c, frame_id, "person")
        else:
            from intercap.geometry.segmentation import foreground_mask

            seen = keypoints[:, 2] > 0
            if seen.sum() < 3:
                return None
            lo, hi = keypoints[seen, :2].min(0), keypoints[seen, :2].max(0)
            pad = 0.15 * (hi - lo).max()
            box = np.zeros(depth.shape, bool)
            x0, y0 = np.maximum(np.floor(lo - pad), 0).astype(int)
            x1, y1 = np.ceil(hi + pad).astype(int)
            box[y0:y1 + 1, x0:x1 + 1] = True
            mask = foreground_mask(depth, self._backgrounds()[c]) & box
            if self.on_mask(mask, keypoints[:NUM_BODY]) < self.cfg.still_person_keypoints:
                mask = self.still_mask(c, depth, keypoints[:NUM_BODY], box)
                with self._lock:
                    self.still_views += 1
            mask &= ~self.object_mask(c, frame_id, depth.shape)
        if mask is None:
            return None
        erode = int(round(self.cfg.person_erode_px * mask.shape[1] / 640))
        if erode > 0:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode + 1, 2 * erode + 1))
            mask = cv2.erode(mask.astype(np.uint8), kernel).astype(bool)
        return mask

    @staticmethod
    def on_mask(mask: np.ndarray, keypoints: np.ndarray, radius_px: int = 2) -> float:
        """The share of the confident keypoints (K, 3) that lie on the mask: at least half the pixels
        within `radius_px` are on it (depth noise speckles a background that took the person in)."""
        xy = pixels_inside(keypoints, *mask.shape)
        if not len(xy):
            return 1.0  # nothing to tell by
        share = cv2.blur(mask.astype(np.float32), (2 * radius_px + 1,) * 2)
        return float((share[xy[:, 1], xy[:, 0]] >= 0.5).mean())

    def still_mask(self, c: int, depth: np.ndarray, keypoints: np.ndarray, box: np.ndarray) -> np.ndarray:
        """The person of view c when the depth background took them in (they stood there all take):
        the box's pixels within `still_person_band_m` of the depths under the keypoints (K, 3), the
        floor (within 3 cm of the ground plane, when known) left out; the wall behind lies further."""
        H, W = depth.shape
        xy = pixels_inside(keypoints, H, W)
        under = [depth[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3] for x, y in xy]
        z = np.array([np.median(p[p > 0]) for p in under if (p > 0).any()])
        if len(z) < 3:
            return np.zeros((H, W), bool)
        lo, hi = np.percentile(z, 10) - self.cfg.still_person_band_m, np.percentile(z, 90) + self.cfg.still_person_band_m
        mask = box & (depth > lo) & (depth < hi)
        if self.ground is not None:
            point, normal = self.ground
            ys, xs = np.nonzero(mask)
            rays = self.rays[c].numpy().reshape(H, W, 2)[ys, xs]
            cam = np.concatenate([rays, np.ones((len(ys), 1), np.float32)], 1) * depth[ys, xs, None]
            world = cam @ self._T[c, :3, :3].T + self._T[c, :3, 3]
            floor = (world - point) @ normal < 0.03
            mask[ys[floor], xs[floor]] = False
        return mask

    def batch(self, frame_ids: np.ndarray, keypoints: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C, P, 3) world points and (B, C, P) validity; P = cfg.points_per_view, a seeded random
        subset of the masked pixels with depth (`frame`'s, the frames in IO threads)."""
        B, C, P = len(frame_ids), self.session.num_cameras, self.cfg.points_per_view
        points = np.zeros((B, C, P, 3), np.float32)
        valid = np.zeros((B, C, P), bool)

        def pick_frame(b: int) -> None:
            points[b], valid[b] = self.frame(int(frame_ids[b]), keypoints[b])

        in_threads(pick_frame, range(B))
        return torch.from_numpy(points), torch.from_numpy(valid)

    def frame(self, frame_id: int, keypoints: np.ndarray, depths: list | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One frame's (C, P, 3) world points and (C, P) validity, its own seeded stream; keypoints
        (C, K, 3); `depths`: its views' depth maps when already read (else read here)."""
        C, P = self.session.num_cameras, self.cfg.points_per_view
        points = np.zeros((C, P, 3), np.float32)
        valid = np.zeros((C, P), bool)
        rng = np.random.default_rng([self.cfg.seed, frame_id])
        for c in range(C):
            depth = self.session.read_depth(c, frame_id) if depths is None else depths[c]
            if depth is None:
                continue
            mask = self.mask(c, frame_id, depth, keypoints[c])
            if mask is None:
                continue
            pick = np.flatnonzero((mask & (depth > 0.2)).reshape(-1))
            if len(pick) < self.cfg.min_points:
                continue
            pick = rng.choice(pick, size=min(P, len(pick)), replace=False)
            z = depth.reshape(-1)[pick]
            xy = self.rays[c][pick].numpy()
            cam = np.concatenate([xy * z[:, None], z[:, None]], 1)
            points[c, :len(pick)] = cam @ self._T[c, :3, :3].T + self._T[c, :3, 3]
            valid[c, :len(pick)] = True
        return points, valid


def keypoint_views(keypoints: torch.Tensor, cfg) -> torch.Tensor:
    """(B,) per frame, the views with >= min_body_keypoints confident body keypoints."""
    return ((keypoints[:, :, :NUM_BODY, 2] > 0).sum(-1) >= cfg.min_body_keypoints).sum(-1)


def foot_views(keypoints: torch.Tensor, min_keypoints: int = 2) -> torch.Tensor:
    """(B,) per frame, the views with >= `min_keypoints` confident foot keypoints (ankles, heels, toes)."""
    feet = priors.device_constant(tuple(FOOT_KEYPOINTS), keypoints.device, torch.long)  # made once per device
    return ((keypoints[..., 2].index_select(2, feet) > 0).sum(-1) >= min_keypoints).sum(-1)


def unseen_feet_support(vertices: torch.Tensor, keypoints: torch.Tensor, ground_point: torch.Tensor,
                        ground_normal: torch.Tensor) -> torch.Tensor:
    """(B,) E_S (`losses.ground_support`) on the frames where fewer than two views see the feet; where
    two do, their keypoints place the feet and the term is zero. Shared by the body and global stages."""
    unseen = (foot_views(keypoints) < 2).to(vertices.dtype)
    return losses.ground_support(vertices, ground_point, ground_normal) * unseen


def shares_shape(obs: BodyObservations, cfg) -> bool:
    """Whether a batch is fitted with one phenotype (`body.shared_shape`): only when two or more views see
    every frame; from one view a stoop is as well explained by a shorter body as by a bent one."""
    return bool(cfg.shared_shape) and bool((keypoint_views(obs.keypoints, cfg) >= 2).all())


def usable_frames(keypoints: torch.Tensor, point_valid: torch.Tensor, cfg) -> torch.Tensor:
    """(B,) bool: enough evidence for a fit. Two views with >= min_body_keypoints confident body
    keypoints, or one such view plus one view's depth points; anything less is marked, not fitted."""
    kp_views = keypoint_views(keypoints, cfg)  # (B,)
    depth_views = (point_valid.sum(-1) >= cfg.min_points).sum(-1)
    return (kp_views >= 2) | ((kp_views >= 1) & (depth_views >= 1))


# ---------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------

def triangulate(keypoints: torch.Tensor, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """Confidence-weighted DLT over views: (B, C, K, 3) pixels + confidence -> (B, K, 3) world points
    and (B, K) validity (seen by at least two views, in front of them)."""
    B, C, K, _ = keypoints.shape
    pixels = keypoints[..., :2].permute(1, 0, 2, 3).reshape(C, B * K, 2)
    xy = undistort(_remove_intrinsics(pixels, cameras.K), cameras.dist)  # (C, BK, 2)
    P = cameras.T_cam_from_world[:, :3, :]  # (C, 3, 4) normalised projection matrices
    conf = keypoints[..., 2].permute(1, 0, 2).reshape(C, B * K)  # (C, BK)
    rows_x = xy[..., 0:1] * P[:, None, 2] - P[:, None, 0]  # (C, BK, 4)
    rows_y = xy[..., 1:2] * P[:, None, 2] - P[:, None, 1]
    A = torch.cat([rows_x, rows_y], 0) * torch.cat([conf, conf], 0)[..., None]  # (2C, BK, 4)
    A = A.permute(1, 0, 2)  # (BK, 2C, 4)
    _, _, Vh = torch.linalg.svd(A.double())
    X = Vh[:, -1]  # (BK, 4)
    w = X[:, 3:]
    points = (X[:, :3] / torch.where(w.abs() > 1e-12, w, torch.full_like(w, 1e-12))).to(keypoints.dtype)
    seen = (conf > 0).sum(0) >= 2
    z = (points[None] @ P[:, :, :3].transpose(1, 2))[..., 2] + P[:, None, 2, 3]  # (C, BK)
    in_front = ((z > 0) | (conf == 0)).all(0)
    return points.view(B, K, 3), (seen & in_front).view(B, K)


def reject_disagreeing_views(keypoints: torch.Tensor, cameras: Cameras, threshold_px: float,
                             rounds: int = 2) -> torch.Tensor:
    """(B, C, K, 3) keypoints with the detections that disagree with the other views dropped
    (confidence 0). Per frame and keypoint seen by three views or more, each view is left out in
    turn and the others triangulated; the view whose leaving out makes the others agree (all within
    `threshold_px` at 640 px image width, scaled with it) goes when it is itself farther than that
    from their point; then again on what is left (`rounds` times). A detector that gets one view of
    a bent-over person wrong (its joints 10-25 px off) otherwise pulls the fit as much as the views
    that agree."""
    kp = keypoints.clone()
    B, C, K, _ = kp.shape
    limit = (threshold_px * cameras.width.to(kp.dtype) / 640.0)[:, None, None]  # (C, 1, 1)
    for _ in range(rounds):
        seen = kp[..., 2] > 0  # (B, C, K)
        own = torch.full((C, B, K), float("inf"), dtype=kp.dtype, device=kp.device)  # left-out view's ratio
        rest = torch.full((C, B, K), float("inf"), dtype=kp.dtype, device=kp.device)  # the others' worst ratio
        for c in range(C):
            others = kp.clone()
            others[:, c, :, 2] = 0
            points, ok = triangulate(others, cameras)  # (B, K, 3)
            pix, z = project(points.reshape(1, -1, 3).expand(C, -1, -1), cameras)  # (C, B*K, 2)
            gap = (pix.view(C, B, K, 2) - kp.permute(1, 0, 2, 3)[..., :2]).norm(dim=-1) / limit  # (C, B, K)
            usable = ok[None] & (z.view(C, B, K) > 0) & seen.permute(1, 0, 2)
            own[c] = torch.where(usable[c], gap[c], own[c])
            gap = torch.where(usable, gap, torch.zeros_like(gap))
            gap[c] = 0
            rest[c] = torch.where(ok & seen[:, c], gap.amax(0), rest[c])
        best_rest, best = rest.min(0)  # (B, K): the view whose leaving out leaves the most agreement
        drop = (seen.sum(1) >= 3) & (best_rest <= 1) & (own.gather(0, best[None])[0] > 1)
        if not drop.any():
            break
        mask = torch.zeros_like(seen).scatter_(1, best[:, None], drop[:, None])
        kp[..., 2] = torch.where(mask, torch.zeros_like(kp[..., 2]), kp[..., 2])
    return kp


def lift_keypoints(keypoints: torch.Tensor, points: torch.Tensor, point_valid: torch.Tensor, cameras: Cameras,
                   radius_px: float = 12.0, behind_m: float = 0.06) -> tuple[torch.Tensor, torch.Tensor]:
    """3D keypoints from depth where triangulation has too few views: each detected keypoint takes the
    view's nearest segmented depth point in the image (within `radius_px`, scaled like the image
    width / 640), pushed `behind_m` further along its camera ray (joints lie inside the body, behind
    the surface the sensor sees), averaged over the views that lift it.

    (B, C, K, 3) pixels + confidence, (B, C, P, 3) world points, (B, C, P) validity
    -> (B, K, 3) world points and (B, K) validity."""
    B, C, K, _ = keypoints.shape
    P = points.shape[2]
    flat = points.permute(1, 0, 2, 3).reshape(C, B * P, 3)
    pix, z = project(flat, cameras)  # (C, BP, 2), (C, BP)
    pix = pix.view(C, B, P, 2).transpose(0, 1)  # (B, C, P, 2)
    gap = torch.cdist(keypoints[..., :2], pix)  # (B, C, K, P)
    gap = gap.masked_fill(~point_valid[:, :, None, :], float("inf"))
    nearest_gap, nearest = gap.min(-1)  # (B, C, K)
    scale = cameras.K[:, 0, 2] * 2 / 640  # (C,) ~ image width / 640
    ok = (keypoints[..., 2] > 0) & (nearest_gap < radius_px * scale[None, :, None])
    surface = torch.gather(points, 2, nearest[..., None].expand(B, C, K, 3))  # (B, C, K, 3)
    centres = cameras.T_world_from_cam[:, :3, 3]  # (C, 3)
    ray = torch.nn.functional.normalize(surface - centres[None, :, None], dim=-1)
    lifted = surface + behind_m * ray
    w = ok.to(points.dtype)[..., None]
    mean = (lifted * w).sum(1) / w.sum(1).clamp(min=1)
    return mean, ok.any(1)


def weighted_kabsch(source: torch.Tensor, target: torch.Tensor, weight: torch.Tensor):
    """Rotation R (B, 3, 3) and translation t (B, 3) minimising sum w |R s + t - x|^2, (B, K, 3) inputs."""
    w = weight[..., None] / weight.sum(1).clamp(min=1e-9)[:, None, None]
    mu_s, mu_t = (w * source).sum(1), (w * target).sum(1)
    H = ((source - mu_s[:, None]) * w).transpose(1, 2) @ (target - mu_t[:, None])  # (B, 3, 3)
    U, _, Vh = torch.linalg.svd(H)
    d = torch.sign(torch.det(Vh.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    R = Vh.transpose(1, 2) @ D @ U.transpose(1, 2)
    return R, mu_t - (R @ mu_s[..., None])[..., 0]


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) unit area-weighted vertex normals. Computed vertex-major ((V, B, 3)), so each
    face adds one contiguous row of B normals to each of its corners: 2.5x faster than per frame."""
    B, V, _ = vertices.shape
    rows = vertices.transpose(0, 1)  # (V, B, 3)
    a, b, c = rows[faces[:, 0]], rows[faces[:, 1]], rows[faces[:, 2]]  # (F, B, 3)
    face_normals = torch.linalg.cross(b - a, c - a, dim=-1).reshape(len(faces), B * 3)
    normals = torch.zeros(V, B * 3, dtype=vertices.dtype, device=vertices.device)
    for corner in range(3):
        normals = normals.index_add(0, faces[:, corner], face_normals)
    return torch.nn.functional.normalize(normals.view(V, B, 3), dim=-1).transpose(0, 1)


def visibility_rows(cameras: Cameras, cells: int) -> int:
    """Rows of `visible_vertices`' z-buffer: its cells are square, `cells` across every view
    (in float32, as the cells' size is)."""
    cell = cameras.width.cpu().numpy().astype(np.float32) / np.float32(cells)
    return int(np.ceil(cameras.height.cpu().numpy().astype(np.float32) / cell).max())


def visible_vertices(
    vertices: torch.Tensor, normals: torch.Tensor, subset: torch.Tensor, cameras: Cameras,
    cells: int, margin: float, rows: int | None = None,
) -> torch.Tensor:
    """(B, C, N) bool: which of the `subset` vertices each view sees. A coarse z-buffer of all
    the given vertices (cells x cells*H/W grid) plus the normal facing the camera; no gradient.
    `rows`: `visibility_rows` of these cameras (given, nothing here waits on a GPU)."""
    with torch.no_grad():
        B, V, _ = vertices.shape
        C = len(cameras)
        pix, z = project(vertices.reshape(1, B * V, 3).expand(C, -1, -1), cameras)  # (C, BV, 2), (C, BV)
        cell = (cameras.width.to(pix.dtype) / cells)[:, None, None]
        grid_w = cells
        grid_h = visibility_rows(cameras, cells) if rows is None else rows
        uv = torch.floor(pix / cell).long()
        inside = (z > 0.05) & (uv[..., 0] >= 0) & (uv[..., 0] < grid_w) & (uv[..., 1] >= 0) & (uv[..., 1] < grid_h)
        frame = torch.div(torch.arange(B * V, device=vertices.device), V, rounding_mode="floor")[None].expand(C, -1)
        key = (frame * grid_h + uv[..., 1].clamp(0, grid_h - 1)) * grid_w + uv[..., 0].clamp(0, grid_w - 1)
        zbuf = torch.full((C, B * grid_h * grid_w), float("inf"), dtype=z.dtype, device=z.device)
        zbuf.scatter_reduce_(1, key, torch.where(inside, z, torch.full_like(z, float("inf"))), "amin")
        nearest = zbuf.gather(1, key)  # (C, BV)
        seen = inside & (z <= nearest + margin)
        seen = seen.view(C, B, V)[:, :, subset].permute(1, 0, 2)  # (B, C, N)
        to_camera = cameras.centers[None, :, None, :] - vertices[:, None, subset]  # (B, C, N, 3)
        facing = (to_camera * normals[:, None, subset]).sum(-1) > 0
        return seen & facing


@dataclass
class BodySpheres:
    """Self-penetration proxy: spheres placed along bones (joint-to-joint interpolation), radius from
    the rest mesh (distance of the bone's own vertices to the bone axis, 0.8 of its median so the
    rest pose does not touch itself); pairs of spheres on different, non-adjacent segments."""

    start: torch.Tensor  # (S,) joint index of the segment start
    end: torch.Tensor  # (S,) joint index of the segment end
    fraction: torch.Tensor  # (S,) position along the segment
    radii: torch.Tensor  # (S,)
    pairs: torch.Tensor  # (Q, 2)

    SEGMENTS = {  # name: (from bone head, to bone head)
        "spine_low": ("spine05", "spine03"), "spine_high": ("spine03", "neck01"), "head": ("neck03", "head"),
        "upperarm.L": ("upperarm01.L", "lowerarm01.L"), "forearm.L": ("lowerarm01.L", "wrist.L"),
        "upperarm.R": ("upperarm01.R", "lowerarm01.R"), "forearm.R": ("lowerarm01.R", "wrist.R"),
        "thigh.L": ("upperleg01.L", "lowerleg01.L"), "shin.L": ("lowerleg01.L", "foot.L"),
        "thigh.R": ("upperleg01.R", "lowerleg01.R"), "shin.R": ("lowerleg01.R", "foot.R"),
    }
    ADJACENT = {("spine_low", "spine_high"), ("spine_high", "head"), ("upperarm.L", "forearm.L"),
                ("upperarm.R", "forearm.R"), ("thigh.L", "shin.L"), ("thigh.R", "shin.R"),
                ("spine_high", "upperarm.L"), ("spine_high", "upperarm.R"), ("spine_low", "thigh.L"),
                ("spine_low", "thigh.R"), ("thigh.L", "thigh.R")}

    @classmethod
    def from_model(cls, model, per_segment: int = 4) -> "BodySpheres":
        params = model.init_params(1)
        with torch.no_grad():
            out = model(params)
        vertices = out.vertices[0].double()
        joints = out.joints[0].double()
        index = {n: i for i, n in enumerate(model.joint_names)}
        start, end, fraction, radii, segment = [], [], [], [], []
        for name, (a, b) in cls.SEGMENTS.items():
            pa, pb = joints[index[a]], joints[index[b]]
            axis = pb - pa
            length = axis.norm()
            rel = vertices - pa
            along = (rel @ axis) / length**2
            radial = (rel - along[:, None] * axis).norm(dim=1)
            for k in range(per_segment):
                s = (k + 0.5) / per_segment
                near = (along - s).abs() < 0.5 / per_segment
                close = near & (radial < 0.25)
                r = 0.8 * float(radial[close].quantile(0.3)) if close.sum() > 10 else 0.03
                start.append(index[a]); end.append(index[b]); fraction.append(s); radii.append(r); segment.append(name)
        pairs = []
        for i in range(len(segment)):
            for j in range(i + 1, len(segment)):
                a, b = segment[i], segment[j]
                if a != b and (a, b) not in cls.ADJACENT and (b, a) not in cls.ADJACENT:
                    pairs.append((i, j))
        device = out.joints.device
        spheres = cls(torch.tensor(start, device=device), torch.tensor(end, device=device),
                      torch.tensor(fraction, dtype=torch.float32, device=device),
                      torch.tensor(radii, dtype=torch.float32, device=device), torch.tensor(pairs, device=device))
        centres = spheres.centres(out.joints.float())
        resting = losses.sphere_self_penetration(centres, spheres.radii, spheres.pairs)
        if float(resting) > 0:  # e.g. arms close to the trunk at rest: those pairs are dropped
            gap = (centres[0, spheres.pairs[:, 0]] - centres[0, spheres.pairs[:, 1]]).norm(dim=-1)
            keep = gap > spheres.radii[spheres.pairs[:, 0]] + spheres.radii[spheres.pairs[:, 1]]
            spheres.pairs = spheres.pairs[keep]
        return spheres

    def centres(self, joints: torch.Tensor) -> torch.Tensor:
        """(B, J, 3) posed joints -> (B, S, 3) sphere centres."""
        f = self.fraction.to(joints)[None, :, None]
        return joints[:, self.start] * (1 - f) + joints[:, self.end] * f


# ---------------------------------------------------------------------------
# The fit
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Phase:
    """One SMPLify-X-style phase: which variables move, which terms count, how long."""

    name: str
    variables: tuple[str, ...]
    terms: tuple[str, ...]
    steps_key: str  # BodyConfig field holding its L-BFGS step budget
    rho_key: str = "keypoint_rho"  # BodyConfig field holding E_J's robust scale in this phase


PHASES = (
    Phase("orient", ("global_orient", "transl"), ("orient_keypoints",), "orient_steps", "keypoint_rho_start"),
    Phase("pose", ("global_orient", "transl", "body_pose", "shape"),
          ("keypoints", "pose_prior", "joint_limits", "bending", "shape", "ground", "ground_support"), "pose_steps",
          "keypoint_rho_start"),
    Phase("full", ("global_orient", "transl", "body_pose", "shape", "left_hand_pose", "right_hand_pose", "expression"),
          ("keypoints", "depth", "pose_prior", "joint_limits", "bending", "hand_prior", "shape", "expression",
           "penetration", "ground", "ground_support"), "full_steps"),
)


class BodyFitter:
    """Fits batches of frames; holds the model, cameras, priors' tables and the sphere proxy."""

    def __init__(self, model, cameras: Cameras, cfg):
        self.model = model
        self.cameras = cameras
        self.cfg = cfg
        names = model.body_joint_names
        device = cameras.K.device
        self.free_bones = torch.tensor([i for i, n in enumerate(names) if not n.startswith(FROZEN_BONE_PREFIXES)],
                                       device=device)
        focal = cameras.K[:, 0, 0]
        self.scale_px = focal / 1000.0  # (C,)
        weights = torch.ones(NUM_BODY_HANDS, device=device)
        weights[NUM_BODY:] = cfg.hand_keypoint_weight
        self.joint_weights = weights
        orient = torch.zeros(NUM_BODY_HANDS, device=device)
        orient[ORIENT_KEYPOINTS] = 1.0
        self.orient_weights = orient
        self.subset = model.fitting_subsample.to(cameras.K.device)
        self.visibility_rows = visibility_rows(cameras, cfg.visibility_cells)
        # E_D's correspondences need the fitting vertices' normals, so the faces round them and
        # those faces' vertices (~45 % of the mesh, spread as evenly as the subset): the model is
        # skinned there only, and the same vertices fill the visibility test's coarse z-buffer.
        faces = model.faces.to(device)
        ring_faces = faces[torch.isin(faces, self.subset).any(1)]
        self.ring_vertices = torch.unique(ring_faces)  # sorted
        self.ring_faces = torch.searchsorted(self.ring_vertices, ring_faces)
        self.subset_in_ring = torch.searchsorted(self.ring_vertices, self.subset)
        self.spheres = BodySpheres.from_model(model)
        self.shape_center = 0.5  # the shape prior's centre: the average person until `size_template`
        self.held_shape = None  # (num_shape,) the person's phenotype once `hold_shape` has it: fits keep it fixed
        self.ground = None  # (point, normal) tensors: E_G keeps the body above the floor when set

    # -- size ---------------------------------------------------------------------------
    def torso_keypoints_3d(self, obs: BodyObservations) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 6, 3) torso keypoints in the world, triangulated where two views see them, else lifted
        from depth (`lift_keypoints`), and (B, 6) which of them are known."""
        target, seen = triangulate(obs.keypoints, self.cameras)
        lifted, liftable = lift_keypoints(obs.keypoints, obs.points, obs.point_valid, self.cameras)
        target = torch.where(seen[..., None], target, lifted)  # one view: depth gives the 3D position
        return target[:, TORSO_KEYPOINTS], (seen | liftable)[:, TORSO_KEYPOINTS]

    def size_template(self, obs: BodyObservations, template: BodyParams,
                      tolerance: float = 0.08) -> tuple[BodyParams, float | None]:
        """The template with the phenotype whose stature matches the person's measured size.

        Depth (or triangulation) gives the torso keypoints in metres, so their spread against the
        template's (median ratio of the pairwise distances) scales the stature: a child seen by one
        camera is otherwise fitted as an adult further away, which reprojects as well. Sizes within
        `tolerance` of the template's are left to the fit; otherwise below 1.5 m the age changes
        (children), above it the height, and the shape prior is centred there.
        Returns (template, measured stature ratio or None when too few keypoints or the model's
        shape is not anny's phenotype)."""
        if self.model.name != "anny":
            return template, None
        target, seen = self.torso_keypoints_3d(obs)
        with torch.no_grad():
            placed = self.model(template).keypoints[0, TORSO_KEYPOINTS]  # (6, 3)
        i, j = torch.triu_indices(len(TORSO_KEYPOINTS), len(TORSO_KEYPOINTS), 1, device=placed.device)
        model_len = (placed[i] - placed[j]).norm(dim=-1)  # (pairs,)
        both = seen[:, i] & seen[:, j]  # (B, pairs)
        ratio = (target[:, i] - target[:, j]).norm(dim=-1) / model_len.clamp(min=1e-6)
        ratio = ratio[both & (model_len > 0.1)]
        if ratio.numel() < 3:
            return template, None
        scale = float(ratio.median())
        if abs(scale - 1.0) < tolerance:  # within what the keypoints' depth lifting and joint placement blur
            return template, scale
        shape = phenotype_for_stature(self.model, template.shape[0], scale * stature(self.model, template.shape))
        sized = template.clone()
        sized.shape[:] = shape
        self.shape_center = shape.clone()
        return sized, scale

    # -- initialisation -------------------------------------------------------------
    def initialise(self, obs: BodyObservations, template: BodyParams) -> BodyParams:
        """Per frame: the template's pose and shape, turned about its own up axis and moved so its
        torso keypoints meet the triangulated ones (weighted, closed form).

        Only the heading is taken from the keypoints: a full rotation fitted to the shoulders and
        hips of a bending trunk tilts the whole body and swings the legs a metre off, while the
        heading of the trunk is stable; the orient phase then fits the tilt with the legs in view.
        Torso keypoints fewer than two views see are lifted from depth (`lift_keypoints`); frames
        with none at all are moved to their depth points' centroid."""
        B = obs.batch_size
        params = template.map(lambda t: t[-1:].expand(B, *t.shape[1:]).clone())
        target, seen = self.torso_keypoints_3d(obs)
        with torch.no_grad():
            placed = self.model(params).keypoints[:, TORSO_KEYPOINTS]  # (B, 6, 3) template as placed
        w = seen.to(placed.dtype)
        count = w.sum(1)
        mean = lambda x: (x * w[..., None]).sum(1) / count.clamp(min=1)[:, None]  # noqa: E731
        R0 = axis_angle_to_matrix(params.global_orient)  # (B, 3, 3)
        up = R0 @ torch.as_tensor(self.model.up_axis, dtype=R0.dtype, device=R0.device)  # (B, 3)
        a = placed - mean(placed)[:, None]
        b = target - mean(target)[:, None]
        sin = (torch.cross(a, b, dim=-1) * up[:, None]).sum(-1).mul(w).sum(1)
        cos = ((a * b).sum(-1) - (a * up[:, None]).sum(-1) * (b * up[:, None]).sum(-1)).mul(w).sum(1)
        yaw = torch.where(count >= 2, torch.atan2(sin, cos), torch.zeros_like(sin))
        centre = mean(placed)
        turn_about(params, axis_angle_to_matrix(up * yaw[:, None]), centre)  # about up through the torso centre
        params.transl[count >= 1] += (mean(target) - centre)[count >= 1]
        lone = (count == 0) & obs.point_valid.flatten(1).any(1)
        if lone.any():
            valid = obs.point_valid[lone].flatten(1, 2)[..., None].to(obs.points.dtype)
            centroid = (obs.points[lone].flatten(1, 2) * valid).sum(1) / valid.sum(1)
            params.transl[lone] += centroid - placed[lone].mean(1)
        return params

    # -- energy ----------------------------------------------------------------------
    def energy_terms(self, params: BodyParams, obs: BodyObservations, terms, matches=None,
                     rho: float | None = None, out=None, rest=None) -> dict[str, torch.Tensor]:
        """Each active term per frame, (B,), unweighted. `matches`: E_D's `DepthPairs` from
        `correspondences`, needed when "depth" is among the terms; `rho`: E_J's robust scale
        (default cfg.keypoint_rho); `out`: the model's output for `params` whose first vertices
        are the fitting subsample, when the caller has it already; `rest`: the model's `rest_state`
        of the subsample while shape and expression do not move."""
        if out is None:
            out = self.model.sparse_forward(params, self.subset, rest)  # vertices: the fitting subsample only
        C = len(self.cameras)
        B, K = out.keypoints.shape[0], NUM_BODY_HANDS
        result = {}
        if "keypoints" in terms or "orient_keypoints" in terms:
            pix, z = project(out.keypoints.reshape(1, B * K, 3).expand(C, -1, -1), self.cameras)
            pix = pix.view(C, B, K, 2).transpose(0, 1)
            conf = obs.keypoints[..., 2] * (z.view(C, B, K).transpose(0, 1) > 0.05)
            weights = self.orient_weights if "orient_keypoints" in terms else self.joint_weights
            result["keypoints"] = losses.keypoint_reprojection(
                pix, obs.keypoints[..., :2], conf, weights, self.scale_px, rho or self.cfg.keypoint_rho)
        if "depth" in terms:
            one_view = keypoint_views(obs.keypoints, self.cfg) < 2
            depth = losses.depth_point_to_plane(out.vertices[:, :len(self.subset)], matches, self.cfg.depth_scale_m)
            result["depth"] = depth * torch.where(one_view, self.cfg.one_view_depth_factor, 1.0)
        if set(priors.POSE_PRIOR_TERMS) & set(terms):
            result.update(priors.pose_priors(params.body_pose, params.left_hand_pose, params.right_hand_pose, terms))
        if "shape" in terms:
            result["shape"] = priors.shape_prior(params.shape, center=self.shape_center)
        if "expression" in terms and self.cfg.fit_expression:
            result["expression"] = priors.expression_prior(params.expression)
        if self.ground is not None and {"ground", "ground_support"} & set(terms):
            point, normal = (x.to(out.vertices) for x in self.ground)
            vertices = out.vertices[:, :len(self.subset)]
            if "ground" in terms:
                result["ground"] = losses.ground_penetration(vertices, point, normal)
            if "ground_support" in terms and self.cfg.w_ground_support > 0:
                result["ground_support"] = unseen_feet_support(vertices, obs.keypoints, point, normal)
        if "penetration" in terms:
            result["penetration"] = losses.sphere_self_penetration(
                self.spheres.centres(out.joints), self.spheres.radii.to(out.joints), self.spheres.pairs)
        return result

    def weight(self, term: str) -> float:
        return getattr(self.cfg, f"w_{term}")

    def correspondences(self, params: BodyParams, obs: BodyObservations, ring_rest=None) -> losses.DepthPairs:
        """E_D's data association, refreshed once per L-BFGS step (as ICP): each point with the
        nearest fitting vertex its view sees, and (when `depth_model_to_data` > 0) each fitting
        vertex a view sees with that view's nearest point, with the vertices' normals.
        `ring_rest`: the model's `rest_state` of the ring vertices when shape and expression are fixed."""
        with torch.no_grad():
            ring = self.model.sparse_forward(params, self.ring_vertices, ring_rest).vertices  # (B, R, 3)
            normals = vertex_normals(ring, self.ring_faces)  # exact at the fitting vertices (all their faces are here)
            visible = visible_vertices(ring, normals, self.subset_in_ring, self.cameras,
                                       self.cfg.visibility_cells, self.cfg.visibility_margin_m, self.visibility_rows)
            vertices = ring[:, self.subset_in_ring]
            nearest = losses.nearest_visible_vertices(obs.points, vertices, visible)
            to_vertices = None
            if self.cfg.depth_model_to_data > 0:
                to_vertices = losses.nearest_points(vertices, visible, obs.points, obs.point_valid,
                                                    self.cfg.depth_model_to_data_max_m)
            return losses.depth_pairs(obs.points, obs.point_valid, normals[:, self.subset_in_ring], nearest,
                                      to_vertices, self.cfg.depth_model_to_data)

    def fit(self, obs: BodyObservations, init: BodyParams, monitor=None,
            shape_groups: torch.Tensor | None = None) -> tuple[BodyParams, dict]:
        """Run PHASES from `init`; returns the fitted parameters and per-frame figures.

        `shape_groups` (B,) long: frames with the same number share one phenotype while shape is free
        (its rest state is then computed once per group and evaluation, not once per frame). Default:
        the whole batch one group where `shares_shape`, else each frame its own. A
        batch of competing starts (`refit_from_evidence`) gives each start its own group: a wrong start
        must not bend the shape of the others. With `held_shape` set, every frame has that phenotype and
        shape does not move."""
        params = init.clone()
        if self.held_shape is not None:
            params.shape[:] = self.held_shape
        free = self.free_bones
        B = params.batch_size
        device = params.shape.device
        if shape_groups is None:
            shape_groups = (torch.zeros(B, dtype=torch.long, device=device) if shares_shape(obs, self.cfg)
                            else torch.arange(B, device=device))
        groups = int(shape_groups.max()) + 1
        first = torch.full((groups,), B, device=device).scatter_reduce(0, shape_groups, torch.arange(B, device=device),
                                                                       "amin")  # a frame of each group
        stats = {}
        for phase in PHASES:
            names = [n for n in phase.variables if (n != "expression" or self.cfg.fit_expression)
                     and (n != "shape" or self.held_shape is None)]
            leaves = {n: getattr(params, n).detach().clone() for n in names}
            if "body_pose" in leaves:
                leaves["body_pose"] = params.body_pose[:, free].detach().clone()
            if "shape" in leaves:  # per group, optimised as a logit: anny's phenotypes extrapolate wildly outside [0, 1]
                count = torch.bincount(shape_groups, minlength=groups)[:, None]
                mean = torch.zeros(groups, params.shape.shape[1], dtype=params.shape.dtype, device=device)
                mean = mean.index_add(0, shape_groups, params.shape.detach()) / count
                leaves["shape"] = torch.logit(mean.clamp(SHAPE_EPS, 1 - SHAPE_EPS))
            state = {"matches": None, "rest": None, "posed": None, "ring_rest": None}
            if "shape" not in leaves and "expression" not in leaves:  # the rest pose does not move: computed once
                with torch.no_grad():
                    state["rest"] = self.model.rest_state(params, self.subset)
                    if "depth" in phase.terms:  # and E_D's correspondences' (`correspondences`)
                        state["ring_rest"] = self.model.rest_state(params, self.ring_vertices)
            if set(leaves) <= {"global_orient", "transl"}:  # the body keeps its pose: posed once, only placed
                with torch.no_grad():  # per evaluation (every backend places its model-space output so)
                    unplaced = dataclasses.replace(params, global_orient=torch.zeros_like(params.global_orient),
                                                   transl=torch.zeros_like(params.transl))
                    state["posed"] = self.model.sparse_forward(unplaced, self.subset, state["rest"])

            def current() -> BodyParams:
                values = {n: leaves.get(n, getattr(params, n).detach()) for n in
                          ("shape", "global_orient", "transl", "left_hand_pose", "right_hand_pose", "expression")}
                if "shape" in leaves:
                    values["shape"] = torch.sigmoid(leaves["shape"])[shape_groups]
                body_pose = params.body_pose.detach()
                if "body_pose" in leaves:
                    body_pose = body_pose.index_copy(1, free, leaves["body_pose"])
                return BodyParams(body_pose=body_pose, **values)

            def frame_energies() -> torch.Tensor:
                now = current()
                rest = state["rest"]
                if rest is None and "expression" not in leaves and groups < B:  # one rest state per group
                    rest = self.model.rest_state(now[first], self.subset)
                    rest = rest and rest.select(shape_groups)
                posed = state["posed"]
                out = None if posed is None else self.model.world_output(posed.vertices, posed.joints,
                                                                         posed.keypoints, now)
                terms = self.energy_terms(now, obs, phase.terms, state["matches"],
                                          getattr(self.cfg, phase.rho_key), out=out, rest=rest)
                return sum(self.weight(k) * v for k, v in terms.items())

            graph = self.cfg.cuda_graphs and optim.records_graphs(device)  # each phase's evaluations: one recorded graph

            def find_pairs():  # recorded too: the pairs are then refreshed in place
                state["matches"] = state["matches"].refreshed(
                    self.correspondences(current(), obs, state["ring_rest"]), graph)

            refresh_pairs = optim.recorded(find_pairs, graph, device)

            def refresh(step, value):
                if "depth" in phase.terms:
                    refresh_pairs()
                if monitor is not None:
                    monitor(phase.name, step, value)

            if "depth" in phase.terms:
                state["matches"] = self.correspondences(current(), obs, state["ring_rest"])
            budget = dict(max_steps=getattr(self.cfg, phase.steps_key), inner_iterations=self.cfg.inner_iterations,
                          ftol=self.cfg.ftol, monitor=refresh, graph=graph)
            if self.cfg.per_frame_lbfgs and ("shape" not in leaves or groups == B):  # the frames do not interact
                result = minimise_per_frame(list(leaves.values()), frame_energies, **budget)
            else:  # frames sharing a phenotype (or `per_frame_lbfgs` off): one problem
                result = minimise(list(leaves.values()), lambda: frame_energies().sum(), **budget,
                                  line_search=self.cfg.line_search, max_line_search=self.cfg.max_line_search)
            params = current().detach()
            stats[phase.name] = {"energy": result.energy, "steps": result.steps,
                                 "evaluations": result.evaluations, "stopped": result.stopped}
        stats["terms"] = self.final_terms(params, obs)
        return params, stats

    def final_terms(self, params: BodyParams, obs: BodyObservations) -> dict[str, np.ndarray]:
        """Each term of the last phase per frame, (B,), unweighted, at `params`."""
        with torch.no_grad():
            final = self.energy_terms(params, obs, PHASES[-1].terms, self.correspondences(params, obs))
        return {k: v.detach().cpu().numpy() for k, v in final.items()}


def turn_about(params: BodyParams, turn: torch.Tensor, centre: torch.Tensor) -> None:
    """Rotate each frame's body in place by `turn` (B, 3, 3) about the point `centre` (B, 3)."""
    R0 = axis_angle_to_matrix(params.global_orient)
    params.global_orient.copy_(matrix_to_axis_angle(turn @ R0).to(params.global_orient))
    params.transl.copy_(((params.transl - centre)[:, None] @ turn.transpose(1, 2))[:, 0] + centre)


def fit_to_data_mm(vertices: torch.Tensor, obs: BodyObservations) -> np.ndarray:
    """(B,) per frame, the median distance (mm) from its segmented person points to the nearest vertex
    of its fitted mesh (all vertices: a few mm above the distance to the surface at anny's vertex
    spacing); NaN without points. The body's fit-to-data figure: a fit far from its own depth points
    has failed, whatever its reprojection. Median: mask edges carry mixed-depth outliers. A k-d tree
    per frame: ~8x cheaper than all point-vertex distances, in the body stage's hot path."""
    vertices = vertices.detach().cpu().numpy()
    points, valid = obs.points.cpu().numpy(), obs.point_valid.cpu().numpy()
    out = np.full(len(vertices), np.nan)
    for b in range(len(vertices)):
        if valid[b].any():
            out[b] = 1000 * float(np.median(cKDTree(vertices[b]).query(points[b][valid[b]])[0]))
    return out


def frame_energy(fitter: BodyFitter, terms: dict[str, np.ndarray]) -> np.ndarray:
    """(B,) each frame's weighted energy from its `final_terms`: what the fit minimises, so that fits
    from different starts can be compared."""
    return sum(fitter.weight(k) * v for k, v in terms.items())


def failure_limit(recent: np.ndarray, factor: float, floor: float = 0.0) -> float:
    """The value above which a frame's figure counts as a failed fit: `factor` times the running median
    of the recent frames' figures (`recent`, last `track_window`), never below `floor`."""
    finite = recent[np.isfinite(recent)]
    median = float(np.median(finite)) if len(finite) else np.nan
    return max(floor, factor * median) if median > 0 else (floor or np.inf)


# anny bones of a stoop (picking something up from the floor), axis-angle about x, with the pelvis pitched forward
STOOP_POSE = {"upperleg01.L": -1.05, "upperleg01.R": -1.05, "lowerleg01.L": 1.25, "lowerleg01.R": 1.25,
              "foot.L": -0.75, "foot.R": -0.75, "spine04": 0.18, "spine03": 0.18, "spine02": 0.12}
STOOP_PITCH = 0.55  # rad


def stooped(model, params: BodyParams, centre: torch.Tensor) -> BodyParams:
    """`params` (upright) bent down: the pelvis pitched forward about the torso centre (B, 3), hips and
    knees flexed, the spine rounded (a start a warm start cannot reach from upright in a few frames)."""
    bent = params.clone()
    names = model.body_joint_names
    for bone, angle in STOOP_POSE.items():
        bent.body_pose[:, names.index(bone), 0] = angle
    R = axis_angle_to_matrix(bent.global_orient)
    lateral = np.cross(np.asarray(model.up_axis, float), np.asarray(model.forward_axis, float))
    side = R @ torch.as_tensor(lateral, dtype=R.dtype, device=R.device)  # (B, 3) the body's lateral axis, world
    turn_about(bent, axis_angle_to_matrix(side * STOOP_PITCH), centre)
    return bent


def refit_from_evidence(fitter: BodyFitter, obs: BodyObservations, params: BodyParams, energy: np.ndarray,
                        failed: np.ndarray, template: BodyParams, gap: np.ndarray | None = None,
                        gap_limit: float = np.inf) -> tuple[BodyParams, np.ndarray]:
    """Fit the `failed` frames again without their warm start: from the upright `template` turned to
    the keypoints' heading, and from the same turned a quarter, a half and three quarters round (one
    view's keypoints give the heading of a side or back view poorly), and (anny) from the same bent
    down (`stooped`) facing that heading and turned round. Per frame the fit of lowest energy
    (`frame_energy`, the fit's own objective) of these starts and the warm start's fit is kept, among the fits
    whose fit-to-data (mm; `gap` (B,) of the current fits) is within `gap_limit`: the robust depth
    term saturates, so a fit off its points can have the lower energy (one view: keypoints reproject
    as well at a wrong depth). Where none is within, the fit nearest its points is kept.
    Returns (params, replaced) for all frames of `obs`."""
    idx = np.flatnonzero(failed)
    n = len(idx)
    sub = obs.select(idx)
    init = fitter.initialise(sub, template)
    starts = [init]
    with torch.no_grad():
        centre = fitter.model(init).keypoints[:, TORSO_KEYPOINTS].mean(1)
        up = axis_angle_to_matrix(init.global_orient) @ torch.as_tensor(
            fitter.model.up_axis, dtype=centre.dtype, device=centre.device)
        for quarter in (1, 2, 3):
            turned = init.clone()
            turn_about(turned, axis_angle_to_matrix(up * (quarter * np.pi / 2)), centre)
            starts.append(turned)
        if fitter.model.name == "anny":  # bent down, facing the keypoints' heading and turned round
            bent = stooped(fitter.model, init, centre)
            starts.append(bent)
            turned = bent.clone()
            turn_about(turned, axis_angle_to_matrix(up * np.pi), centre)
            starts.append(turned)
    every = sub.select(np.tile(np.arange(n), len(starts)))  # all starts fitted as one batch, a phenotype each
    groups = None  # per frame
    if shares_shape(every, fitter.cfg):  # one phenotype per start, not one for all
        groups = torch.arange(len(starts), device=every.keypoints.device).repeat_interleave(n)
    fitted, stats = fitter.fit(every, BodyParams.cat(starts), shape_groups=groups)
    candidates = np.concatenate([energy[idx][None], frame_energy(fitter, stats["terms"]).reshape(len(starts), n)])
    candidates = np.nan_to_num(candidates, nan=np.inf)
    if gap is not None:
        with torch.no_grad():
            gaps = np.concatenate([gap[idx][None], fit_to_data_mm(fitter.model(fitted).vertices, every).reshape(
                len(starts), n)])
        off = gaps > gap_limit
        candidates = np.where(off, np.inf, candidates)
        none_on = off.all(0)
        candidates[:, none_on] = np.nan_to_num(gaps[:, none_on], nan=np.inf)  # none on its points: the nearest
    best = candidates.argmin(0)  # 0: keep the warm start's fit
    params, replaced = params.clone(), np.zeros(len(energy), bool)
    for k, (i, choice) in enumerate(zip(idx, best)):
        if choice:
            for name, value in params.tensors().items():
                value[i] = getattr(fitted, name)[k + (choice - 1) * n]
            replaced[i] = True
    return params, replaced


# ---------------------------------------------------------------------------
# The stage
# ---------------------------------------------------------------------------

def reprojection_error_px(model, params: BodyParams, obs: BodyObservations, cameras: Cameras) -> np.ndarray:
    """(B,) median pixel distance between fitted and detected keypoints over all views."""
    with torch.no_grad():
        kps = model(params).keypoints
        B, K = kps.shape[:2]
        pix, z = project(kps.reshape(1, B * K, 3).expand(len(cameras), -1, -1), cameras)
        pix = pix.view(len(cameras), B, K, 2).transpose(0, 1)
        err = (pix - obs.keypoints[..., :2]).norm(dim=-1)
        seen = obs.keypoints[..., 2] > 0
        out = np.full(B, np.nan)
        for b in range(B):
            if seen[b].any():
                out[b] = float(err[b][seen[b]].median())
        return out


def draw_overlay(session, keypoints: np.ndarray, frame_id: int, cameras: Cameras, path: Path) -> None:
    """First camera's colour image with the fitted BODY_25 skeleton (green), from the frame's world
    keypoints (K, 3) as saved (projected on the CPU: on a GPU a frame's few points cost launches)."""
    image = session.read_color(0, frame_id)
    if image is None:
        return
    first = cameras.select([0]).to(device="cpu")
    pix, z = project(torch.as_tensor(keypoints[:NUM_BODY], dtype=first.K.dtype), first)
    canvas = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    pts = pix[0].numpy()
    for a, b in BODY_25_EDGES:
        if z[0, a] > 0 and z[0, b] > 0:
            cv2.line(canvas, tuple(int(v) for v in pts[a]), tuple(int(v) for v in pts[b]), (0, 220, 0), 2)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), canvas)


def world_up(session, out_dir: Path) -> np.ndarray:
    """(3,) unit up in the world frame: the ground plane's normal (given in session.yaml or fitted
    by `prepare`), else the cameras' mean -y axis. Never a world axis: rigs put the world anywhere."""
    from intercap.stages.prepare.stage import load_ground

    if (Path(out_dir) / "prepare" / "ground.json").exists():
        return load_ground(out_dir).normal
    if session.ground is not None:
        normal = np.asarray(session.ground[1], np.float64)
        return normal / np.linalg.norm(normal)
    return up_hint_from_cameras(np.stack([c.T_world_from_cam for c in session.cameras]))


def stature(model, shape: torch.Tensor) -> torch.Tensor:
    """(B,) standing height (m) of phenotypes (B, S): the rest mesh's extent along the model's up."""
    params = model.init_params(len(shape))
    params.shape[:] = shape
    with torch.no_grad():
        vertices = model(params).vertices
    up = torch.as_tensor(model.up_axis, dtype=vertices.dtype, device=vertices.device)
    height = vertices @ up
    return height.max(1).values - height.min(1).values


def phenotype_for_stature(model, base: torch.Tensor, target_m: torch.Tensor | float, adult_min_m: float = 1.5,
                          steps: int = 41) -> torch.Tensor:
    """(S,) the phenotype `base` with its age (below `adult_min_m`: children) or its height (above)
    changed so the stature is `target_m`: the nearest of `steps` values on each path."""
    AGE, HEIGHT = 1, 4  # anny: gender, age, muscle, weight, height, proportions
    target = float(target_m)
    grid = torch.linspace(0.0, 1.0, steps, dtype=base.dtype, device=base.device)
    candidates = base.expand(steps, -1).clone()
    if target < adult_min_m:  # children and teenagers: age from newborn to the base's
        candidates[:, AGE] = grid * float(base[AGE])
    else:
        candidates[:, HEIGHT] = grid
    return candidates[(stature(model, candidates) - target).abs().argmin()]


def upright_template(model, up: np.ndarray) -> BodyParams:
    """The model's default parameters for one frame, turned so the model's up axis is the world's
    `up` (the shortest rotation; the heading is found per frame by `BodyFitter.initialise`)."""
    template = model.init_params(1)
    model_up = np.asarray(model.up_axis, np.float64)
    axis = np.cross(model_up, up)
    angle = np.arctan2(np.linalg.norm(axis), model_up @ up)
    if np.linalg.norm(axis) < 1e-9:  # parallel or opposite: any axis perpendicular to model up
        axis = np.cross(model_up, np.eye(3)[np.argmin(np.abs(model_up))])
    rotvec = torch.as_tensor(axis / np.linalg.norm(axis) * angle, dtype=template.global_orient.dtype,
                             device=template.global_orient.device)
    R = axis_angle_to_matrix(rotvec) @ axis_angle_to_matrix(template.global_orient[0])
    template.global_orient[0] = matrix_to_axis_angle(R)
    return template


def chunk_groups(T: int, cfg) -> list[tuple[Chunk, ...]]:
    """The take's body chunks dealt to the processes (`intercap.stages.chunks.chunk_groups`), cut on batches."""
    return parallel_chunk_groups(T, cfg, cfg.body, cfg.body.batch_frames)


def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `body` stage: writes OUT/body_params.npz, body_vertices.npy, body_faces.npy, keypoints3d.npy.

    The take is fitted in chunks of frames by `run.workers` processes (`intercap.parallel`), each
    fitting `side_by_side` chunks at once (`fit_chunks`); each chunk keeps its own resumable checkpoint."""
    out_dir = Path(out_dir)
    (out_dir / "body").mkdir(parents=True, exist_ok=True)
    T = session.num_frames
    groups = chunk_groups(T, cfg)
    where = session if len(groups) == 1 else session.root  # workers load the session themselves
    parts = [part for group in run_chunks(fit_chunks, groups, (where, cfg, out_dir), T, "body", progress)
             for part in group]
    model = shared_model(dataclasses.replace(cfg.body_model, name=session.body_model), device=cfg.run.device)
    fitted = BodyParams.from_numpy_dict(
        {name: np.concatenate([p["params"][name] for p in parts]) for name in parts[0]["params"]}, dtype=model.dtype,
        device=model.faces.device)
    valid, reproj, seconds, gap, reinitialised = (np.concatenate([p[key] for p in parts]) for key in (
        "valid", "reprojection_px", "seconds", "fit_to_data_mm", "reinitialised"))
    cameras = Cameras.from_infos(session.cameras, device=cfg.run.device)
    if not valid.any():
        log.warning("body: no frame has a body fit (no person seen in any view: check keypoints/, masks/ "
                    "or the detector's output in OUT/detect/)")
    figures = write_outputs(session, model, fitted, valid, reproj, seconds, out_dir, cfg.body, cameras,
                            fit_to_data_mm=gap.astype(np.float32), reinitialised=reinitialised)
    # detections dropped for disagreeing with the other views (this run's batches; `reject_disagreeing_views`)
    rejected = sum(int(p.get("keypoints_rejected", 0)) for p in parts)
    # view-frames whose person the depth background had taken in, masked by `PersonPoints.still_mask`
    still = sum(int(p.get("person_masks_still", 0)) for p in parts)
    return {**figures, "keypoints_rejected_by_views": rejected, "person_masks_from_keypoint_depth": still,
            "workers": len(groups),
            "chunks": len(parts)}


@dataclass
class ChunkWorkshop:
    """What the chunks one process fits share: the session, the model, the cameras, the evidence
    readers, one fitter, and the phenotype estimates of every chunk (one person, one shape)."""

    session: object
    cfg: object
    out_dir: Path
    model: object
    cameras: Cameras
    keypoint_source: KeypointSource
    person: PersonPoints
    fitter: BodyFitter
    shape_estimates: list  # one {first row of a batch: phenotype} per chunk

    @classmethod
    def open(cls, session, cfg, out_dir: Path) -> "ChunkWorkshop":
        from intercap.session.frame_cache import open_session

        session = open_session(session, out_dir)
        bcfg = cfg.body
        torch.manual_seed(bcfg.seed)
        out_dir = Path(out_dir)
        model = shared_model(dataclasses.replace(cfg.body_model, name=session.body_model), device=cfg.run.device)
        cameras = Cameras.from_infos(session.cameras, device=cfg.run.device)
        keypoint_source = KeypointSource(session, out_dir, cfg.detect.use_session_keypoints, cameras,
                                         bcfg.keypoint_view_check_px)
        person = PersonPoints(session, cameras, bcfg, out_dir)
        fitter = BodyFitter(model, cameras, bcfg)
        if (out_dir / "prepare" / "ground.json").exists():  # one view hides the legs: they must not sink through it
            from intercap.stages.prepare.stage import load_ground

            ground = load_ground(out_dir)
            fitter.ground = tuple(torch.as_tensor(x, dtype=torch.float32, device=cameras.K.device)
                                  for x in (ground.point, ground.normal))
        return cls(session, cfg, out_dir, model, cameras, keypoint_source, person, fitter, [])

    def hold_shape(self) -> bool:
        """Hold the fitter's phenotype at the mean of all chunks' estimates once there are
        `shape_batches` of them (one person, one shape: later batches fit pose only). True when it
        holds it now."""
        estimates = [v for chunk in self.shape_estimates for v in chunk.values()]
        batches, fitter = self.cfg.body.shape_batches, self.fitter
        if batches <= 0 or len(estimates) < batches or fitter.held_shape is not None:
            return False
        fitter.held_shape = torch.as_tensor(np.mean(estimates, 0), dtype=fitter.model.dtype,
                                            device=fitter.cameras.K.device)
        return True


def fit_chunks(session, cfg, out_dir: Path, chunks: tuple[Chunk, ...], queue) -> list[dict]:
    """Fit `chunks` side by side: each round, the next batch of every unfinished chunk goes into one
    fit, one evaluation for all (the frames do not interact; each chunk keeps its phenotype until it
    is held). On a GPU a step's cost is its kernel launches, not their size, so K chunks side by side
    cost about what one does; on the CPU it saves the per-operation overhead. Returns
    `chunk_batches`' result per chunk."""
    workshop = ChunkWorkshop.open(session, cfg, out_dir)
    runs = [chunk_batches(workshop, chunk, queue) for chunk in chunks]

    def serve(batches: list) -> list:
        obs = BodyObservations.cat([sub for sub, _ in batches])
        groups, first = [], 0  # each chunk its phenotype, as if fitted alone
        for sub, _ in batches:
            count = 1 if shares_shape(sub, workshop.fitter.cfg) else sub.batch_size
            groups.append(torch.full((sub.batch_size,), first) if count == 1 else first + torch.arange(count))
            first += count
        start = time.perf_counter()
        params, stats = workshop.fitter.fit(obs, BodyParams.cat([init for _, init in batches]),
                                            shape_groups=torch.cat(groups).to(obs.keypoints.device))
        seconds = (time.perf_counter() - start) / obs.batch_size
        replies, row = [], 0
        for sub, _ in batches:
            rows = slice(row, row + sub.batch_size)
            row = rows.stop
            replies.append((params[rows], {"terms": {name: v[rows] for name, v in stats["terms"].items()}},
                            seconds * sub.batch_size))
        return replies

    return lockstep(runs, serve)


def chunk_batches(workshop: ChunkWorkshop, chunk: Chunk, queue):
    """Fit frames [chunk.lo, chunk.hi) in batches, each warm-started from the previous batch's
    last fit; checkpointed after every batch (OUT/body/progress_LO_HI.npz). A generator: it yields
    each batch's (observations, initial parameters) and is sent back (parameters, statistics, seconds
    of the fit) (`fit_chunks`). Returns the rows' parameters (numpy), `valid`, `reprojection_px` and
    `seconds`. `queue.put(n)` per n frames done."""
    session, bcfg, out_dir = workshop.session, workshop.cfg.body, workshop.out_dir
    model, cameras, fitter = workshop.model, workshop.cameras, workshop.fitter
    keypoint_source, person = workshop.keypoint_source, workshop.person
    T = chunk.hi - chunk.lo
    frame_ids = session.frame_ids[chunk.lo:chunk.hi]
    checkpoint = out_dir / "body" / f"progress_{chunk.lo:06d}_{chunk.hi:06d}.npz"
    fitted = model.init_params(T)
    done = np.zeros(T, bool)
    valid = np.zeros(T, bool)
    reproj = np.full(T, np.nan)
    seconds = np.zeros(T)
    gap = np.full(T, np.nan)  # fit-to-data, mm
    prior = np.full(T, np.nan)  # the learned pose prior's energy of each frame's fit
    reinitialised = np.zeros(T, bool)
    rejected = 0  # keypoints dropped by the view check in this run's batches
    still = 0  # view-frames whose person stood in the depth background (`PersonPoints.still_mask`)
    sized = None  # the template's phenotype from the person's measured size (NaN: the template's own kept)
    shape_estimates = {}  # first row of a batch -> the phenotype fitted on it; `shape_batches` of them, then held
    workshop.shape_estimates.append(shape_estimates)
    if checkpoint.exists():
        saved = np.load(checkpoint)
        fitted = BodyParams.from_numpy_dict(saved, dtype=model.dtype, device=model.faces.device)
        done, valid, reproj, seconds = saved["done"], saved["valid"], saved["reprojection_px"], saved["seconds"]
        if "fit_to_data_mm" in saved:  # older checkpoints lack it
            gap, prior, reinitialised = saved["fit_to_data_mm"], saved["pose_prior"], saved["reinitialised"]
        if "sized_shape" in saved:
            sized = saved["sized_shape"]
        if "shape_estimates" in saved:  # those of batches still done (a resumed batch estimates again)
            shape_estimates.update({int(row): value for row, value in
                                    zip(saved["shape_estimate_rows"], saved["shape_estimates"]) if done[row]})
            workshop.hold_shape()
        log.info("body: resuming frames %d-%d, %d of %d already fitted", chunk.lo, chunk.hi - 1, int(done.sum()), T)
        queue.put(int(done.sum()))

    upright = upright_template(model, world_up(session, out_dir))
    if sized is not None and np.isfinite(sized).all():  # resumed: sized as before
        upright.shape[:] = torch.as_tensor(sized, dtype=upright.shape.dtype, device=upright.shape.device)
        fitter.shape_center = upright.shape[0].clone()
    template = upright  # the next batch starts from the last fit
    size = bcfg.batch_frames
    batches = [np.arange(s, min(s + size, T)) for s in range(0, T, size)]
    for batch in batches:
        if done[batch].all():
            if valid[batch].any():
                template = fitted[int(batch[valid[batch]][-1])]
            continue
        start = time.perf_counter()
        ids = frame_ids[batch]
        before = keypoint_source.rejected  # the reader is the process's: its count, this chunk's part of it
        kps = keypoint_source.batch(ids, bcfg.min_keypoint_confidence)
        rejected += keypoint_source.rejected - before
        before = person.still_views
        points, point_valid = person.batch(ids, kps)
        still += person.still_views - before
        device = cameras.K.device
        obs = BodyObservations(ids, torch.from_numpy(kps).to(device), points.to(device), point_valid.to(device))
        usable = usable_frames(obs.keypoints, obs.point_valid, bcfg).cpu().numpy()
        fit_seconds = 0.0
        if usable.any():
            keep = np.flatnonzero(usable)
            sub = obs.select(keep)
            if sized is None and template is upright and bcfg.size_from_depth:  # nothing fitted yet: size first
                resized, scale = fitter.size_template(sub, upright)
                if scale is not None:  # measured (else tried again on the next batch)
                    sized = np.full(model.num_shape, np.nan) if resized is upright else resized.shape[0].cpu().numpy()
                    upright = template = resized
                    log.info("body: measured size %.2f x the template's: starting from a stature of %.2f m",
                             scale, float(stature(model, upright.shape)))
            init = fitter.initialise(sub, template)
            waited = time.perf_counter()
            params, stats, fit_seconds = yield sub, init  # fitted with the other chunks' batches (`fit_chunks`)
            start += time.perf_counter() - waited
            with torch.no_grad():
                sub_gap = fit_to_data_mm(model(params).vertices, sub)
            recent = slice(max(0, batch[0] - bcfg.track_window), batch[0])
            one_view = keypoint_views(sub.keypoints, bcfg).cpu().numpy() < 2  # no triangulation to fix the heading
            gap_limit = failure_limit(gap[recent], bcfg.track_factor, bcfg.track_floor_mm)
            failed = ((sub_gap > gap_limit)
                      | (one_view & (stats["terms"]["pose_prior"]
                                     > failure_limit(prior[recent], bcfg.track_prior_factor))))
            if failed.any():  # off the points, or contorted to reach them: refit those frames from the evidence
                params, replaced = refit_from_evidence(fitter, sub, params, frame_energy(fitter, stats["terms"]), failed,
                                                       upright, sub_gap, gap_limit)
                reinitialised[batch[keep]] = replaced
                log.info("body: frames %s failed (fit-to-data or pose prior); refitted from the evidence, "
                         "%d replaced", ids[keep][failed].tolist(), int(replaced.sum()))
                with torch.no_grad():
                    sub_gap = fit_to_data_mm(model(params).vertices, sub)
                    prior[batch[keep]] = priors.learned_pose_prior(params.body_pose).cpu().numpy()
            else:
                prior[batch[keep]] = stats["terms"]["pose_prior"]
            gap[batch[keep]] = sub_gap
            for name, value in params.tensors().items():
                getattr(fitted, name)[batch[keep]] = value
            reproj[batch[keep]] = reprojection_error_px(model, params, sub, cameras)
            valid[batch[keep]] = True
            on_points = np.flatnonzero(sub_gap <= gap_limit)
            if len(on_points):  # the next batch starts from the last fit that lies on its points, not a failed one
                template = params[int(on_points[-1])]
                if fitter.held_shape is None and bcfg.shape_batches > 0:
                    shape_estimates[int(batch[0])] = params.shape[on_points].mean(0).cpu().numpy()
                    if workshop.hold_shape():
                        log.info("body: phenotype held from frame %d on (mean of %d batches' fits)",
                                 int(ids[keep][-1]) + 1, sum(map(len, workshop.shape_estimates)))
        done[batch] = True
        seconds[batch] = (time.perf_counter() - start + fit_seconds) / len(batch)
        queue.put(len(batch))
        save_npz(checkpoint, **fitted.to_numpy_dict(), done=done, valid=valid, reprojection_px=reproj, seconds=seconds,
                 fit_to_data_mm=gap, pose_prior=prior, reinitialised=reinitialised,
                 shape_estimates=np.array(list(shape_estimates.values()), np.float32).reshape(-1, model.num_shape),
                 shape_estimate_rows=np.array(list(shape_estimates), np.int64),
                 **({} if sized is None else {"sized_shape": sized}))
    return {"params": fitted.to_numpy_dict(), "valid": valid, "reprojection_px": reproj, "seconds": seconds,
            "fit_to_data_mm": gap, "reinitialised": reinitialised, "keypoints_rejected": rejected,
            "person_masks_still": still}


PER_FRAME_FILES = ("body_params.npz", "body_vertices.npy", "body_faces.npy", "keypoints3d.npy")


def save_body_results(folder: Path, model, fitted: BodyParams, valid: np.ndarray, frame_ids,
                      **extra) -> tuple[np.ndarray, np.ndarray]:
    """PER_FRAME_FILES of SESSION_FORMAT.md into `folder`, frames not `valid` NaN; returns the
    vertices (T, V, 3) and keypoints (T, 67, 3). `extra` arrays go into body_params.npz beside the
    parameters."""
    T = len(valid)
    vertices = np.full((T, model.num_vertices, 3), np.nan, np.float32)
    keypoints = np.full((T, NUM_BODY_HANDS, 3), np.nan, np.float32)
    with torch.no_grad():
        for s in range(0, T, 16):
            idx = np.arange(s, min(s + 16, T))
            idx = idx[valid[idx]]
            if len(idx):
                out = model(fitted.map(lambda t: t[idx]))
                vertices[idx] = out.vertices.cpu().numpy()
                keypoints[idx] = out.keypoints[:, :NUM_BODY_HANDS].cpu().numpy()
    arrays = fitted.to_numpy_dict()
    for name in arrays:
        arrays[name][~valid] = np.nan
    shape_mean = arrays["shape"][valid].mean(0) if valid.any() else np.full(model.num_shape, np.nan)
    save_npz(folder / "body_params.npz", model=np.array(model.name), **arrays, shape_mean=shape_mean.astype(np.float32),
             valid=valid, frame_ids=frame_ids, **extra)
    save_npy(folder / "body_vertices.npy", vertices)
    save_npy(folder / "body_faces.npy", model.faces.cpu().numpy().astype(np.int64))
    save_npy(folder / "keypoints3d.npy", keypoints)
    return vertices, keypoints


def write_outputs(session, model, fitted: BodyParams, valid, reproj, seconds, out_dir: Path, bcfg, cameras,
                  fit_to_data_mm: np.ndarray, reinitialised: np.ndarray) -> dict:
    """The SESSION_FORMAT.md files, kept in OUT/body/ and shown at OUT/ until the `global` stage
    replaces them; frames without a fit are NaN. body_params.npz also holds the per-frame
    `reprojection_px`, `fit_to_data_mm` and `reinitialised`."""
    T = session.num_frames
    stage_dir = out_dir / "body"
    _, keypoints = save_body_results(stage_dir, model, fitted, valid, session.frame_ids,
                                     reprojection_px=reproj.astype(np.float32), fit_to_data_mm=fit_to_data_mm,
                                     reinitialised=reinitialised)
    for name in PER_FRAME_FILES:
        publish(stage_dir / name, out_dir / name)
    for i in range(0, T, max(1, bcfg.overlay_every)):
        if valid[i]:
            draw_overlay(session, keypoints[i], int(session.frame_ids[i]), cameras,
                         stage_dir / "overlays" / f"{int(session.frame_ids[i]):06d}.jpg")
    return {
        "frames_fitted": int(valid.sum()),
        "frames_unusable": int((~valid).sum()),
        "reprojection_px_median": float(np.nanmedian(reproj)) if valid.any() else None,
        "fit_to_data_mm_median": float(np.nanmedian(fit_to_data_mm)) if np.isfinite(fit_to_data_mm).any() else None,
        "fit_to_data_mm_max": float(np.nanmax(fit_to_data_mm)) if np.isfinite(fit_to_data_mm).any() else None,
        "frames_reinitialised": int(reinitialised.sum()),
        "seconds_per_frame": float(seconds.mean()),
    }
