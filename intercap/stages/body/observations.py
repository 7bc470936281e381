"""What the data gives the body fit: per batch of frames, each view's 2D keypoints (`KeypointSource`)
and segmented person points (`PersonPoints`), gathered as `BodyObservations`; how many views see
a frame (`keypoint_views`, `foot_views`, `usable_frames`); and the keypoints placed in 3D
(`triangulate`, `lift_keypoints`), with a view's limbs detected the wrong way round exchanged back
(`swap_disagreeing_sides`) and the views whose detections disagree dropped (`reject_disagreeing_views`)."""
from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from intercap.body_models.keypoints import BODY_25, NUM_BODY, NUM_BODY_HANDS
from intercap.energies import priors
from intercap.geometry.cameras import Cameras, pixel_rays, project, remove_intrinsics, undistort
from intercap.io.files import per_frame_result, read_json
from intercap.session.session import in_threads

TORSO_KEYPOINTS = [BODY_25.index(n) for n in
                   ("neck", "right_shoulder", "left_shoulder", "mid_hip", "right_hip", "left_hip")]
# What the orient phase fits: the trunk and the legs, so a tilt of the trunk is not taken for a
# tilt of the whole body.
ORIENT_KEYPOINTS = TORSO_KEYPOINTS + [BODY_25.index(n) for n in
                                      ("right_knee", "left_knee", "right_ankle", "left_ankle")]
FOOT_KEYPOINTS = [BODY_25.index(n) for n in ("right_ankle", "left_ankle", "left_big_toe", "left_small_toe",
                                             "left_heel", "right_big_toe", "right_small_toe", "right_heel")]


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
        self.swapped = 0  # view-limbs whose sides `swap_disagreeing_sides` exchanged so far
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
            sided, swapped = swap_disagreeing_sides(torch.from_numpy(out).to(self.cameras.K), self.cameras,
                                                    self.view_check_px)
            checked = reject_disagreeing_views(sided, self.cameras, self.view_check_px).numpy()
            self.rejected += int(((out[..., 2] > 0) & (checked[..., 2] == 0)).sum())
            self.swapped += swapped
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
            from intercap.stages.object.observations import hard_silhouettes

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
        band = self.cfg.still_person_band_m
        lo, hi = np.percentile(z, 10) - band, np.percentile(z, 90) + band
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



def triangulate(keypoints: torch.Tensor, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """Confidence-weighted DLT over views: (B, C, K, 3) pixels + confidence -> (B, K, 3) world points
    and (B, K) validity (seen by at least two views, in front of them)."""
    B, C, K, _ = keypoints.shape
    pixels = keypoints[..., :2].permute(1, 0, 2, 3).reshape(C, B * K, 2)
    xy = undistort(remove_intrinsics(pixels, cameras.K), cameras.dist)  # (C, BK, 2)
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


# (right, left) keypoints of the 67 (BODY_25, then the left and the right hand's 21) that a detector may give
# the other side in one view, each pair's first two deciding: elbow and wrist, then the hand (its landmarks
# follow its wrist); knee and ankle, then the foot
SIDE_GROUPS = (((3, 4, *range(46, 67)), (6, 7, *range(25, 46))),
               ((10, 11, 22, 23, 24), (13, 14, 19, 20, 21)))


def swap_disagreeing_sides(keypoints: torch.Tensor, cameras: Cameras, threshold_px: float,
                           rounds: int = 3) -> tuple[torch.Tensor, int]:
    """(B, C, K, 3) keypoints with the views whose left and right limbs were detected the wrong way round
    exchanged back, and how many view-limbs that exchanged. Per frame and limb pair (`SIDE_GROUPS`), each
    view with three or more of its elbows and wrists (knees, ankles) seen is compared with the other
    views' triangulation of them: where they lie farther than `threshold_px` (at 640 px image width,
    scaled with it) from its points on average, and exchanged within it and at under half that distance,
    the exchange helps; the view it helps most is exchanged, and the check runs again on what that gives
    (`rounds` times: a wrong view misleads the points the others are compared with). Hands close round a
    ball: one view put each wrist on the other hand, the triangulated wrists met in the ball, and the
    fit put both hands there, 14-35 cm from the truth."""
    kp = keypoints.clone()
    B, C, K, _ = kp.shape
    limit = (threshold_px * cameras.width.to(kp.dtype) / 640.0)[:, None, None]  # (C, 1, 1)
    swapped = 0
    for right, left in SIDE_GROUPS:
        idx = torch.as_tensor(right + left, device=kp.device)
        G = len(right)
        deciding = torch.as_tensor([0, 1, G, G + 1], device=kp.device)  # within the group
        for _ in range(rounds):
            group = kp[:, :, idx]  # (B, C, 2G, 3)
            mirrored = torch.cat([group[:, :, G:], group[:, :, :G]], 2)
            seen = group[:, :, deciding, 2] > 0  # (B, C, 4)
            gain = torch.full((B, C), -1.0, dtype=kp.dtype, device=kp.device)  # the exchange's gain, -1: none
            for c in range(C):
                others = group[:, :, deciding].clone()
                others[:, c, :, 2] = 0
                points, ok = triangulate(others, cameras)  # (B, 4, 3)
                pix, z = project(points.reshape(-1, 3), cameras.select([c]))  # (1, B*4, 2)
                pix, z = pix.view(B, 4, 2), z.view(B, 4)
                usable = ok & (z > 0) & seen[:, c] & ((others[..., 2] > 0).sum(1) >= 2)
                n = usable.sum(1)
                kept = ((pix - group[:, c, deciding, :2]).norm(dim=-1) / limit[c, 0]) * usable
                turned = ((pix - mirrored[:, c, deciding, :2]).norm(dim=-1) / limit[c, 0]) * usable
                kept, turned = kept.sum(1) / n.clamp(min=1), turned.sum(1) / n.clamp(min=1)
                helps = (n >= 3) & (kept > 1) & (turned < 1) & (turned < 0.5 * kept)
                gain[:, c] = torch.where(helps, kept - turned, gain[:, c])
            best = gain.argmax(1)  # one view per frame and round: a wrong one misleads the others' points
            exchange = torch.zeros(B, C, dtype=torch.bool, device=kp.device)
            exchange[torch.arange(B), best] = gain.amax(1) > 0
            if not exchange.any():
                break
            kp[:, :, idx] = torch.where(exchange[:, :, None, None], mirrored, group)
            swapped += int(exchange.sum())
    return kp, swapped


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
