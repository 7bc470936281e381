"""Stage 3, `object`: per-frame 6-DoF object tracking by silhouette and depth rendering.

Per frame, the object's pose (6D rotation + translation) minimises E_O over all
views (`losses.object_silhouette` + `losses.object_depth`) with the
differentiable renderer of `intercap.rendering`, starting from a constant-
velocity prediction. Masks come from the session, or from a depth background
model per camera with the candidate kept that best overlaps the rendering of
the predicted pose (render-compare-and-preserve). The first pose comes from
session.yaml when given, else from registering the mesh to the first frame's
object points (several hypotheses, ICP, the lowest E_O wins). Frames where the
object cannot be trusted (mask gone in most views, E_O far above its recent
level after a re-initialisation attempt) get NaN poses and confidence 0.

Writes OUT/object_poses.npz (R (T,3,3), t (T,3), confidence (T,), valid (T,),
frame_ids (T,)), OUT/object/progress.npz while running (resume), and
OUT/object/overlays/*.jpg (rendered outline on the colour images) for a person
to check.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import torch
import trimesh
from tqdm import tqdm

from intercap.cameras import Cameras, depth_to_point_grid, pixel_rays, project
from intercap.io import save_npz
from intercap.losses import (
    matrix_to_rotation_6d,
    object_depth,
    object_silhouette,
    occlusion_weight,
    rotation_6d_to_matrix,
)
from intercap.rendering import MeshTopology, crop_observation, render
from intercap.segmentation import background_depth, clean_mask, components, foreground_mask, select_object_candidate

log = logging.getLogger(__name__)
reg = o3d.pipelines.registration
o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # RANSAC's per-call warnings are noise here


@dataclass
class Observation:
    """One frame's inputs for the object: (C, H, W) arrays per view."""

    mask: np.ndarray  # float32 in [0, 1]
    depth: np.ndarray  # float32 metres, 0 = missing
    has_view: np.ndarray  # (C,) bool: depth present and an object mask found
    known: np.ndarray  # float32, 1 where the mask's label is known (derived masks know nothing where depth is missing)

    @property
    def visible_views(self) -> int:
        return int(self.has_view.sum())


@dataclass
class Fit:
    R: np.ndarray  # (3, 3) object -> world
    t: np.ndarray  # (3,)
    energy: float
    confidence: float  # mean silhouette IoU over views that see the object


def predict_pose(history: list[tuple[np.ndarray, np.ndarray] | None]):
    """Constant-velocity prediction from the last two trusted poses (or the last one)."""
    known = [h for h in history[-2:] if h is not None]
    if not known:
        return None
    if len(known) == 1 or history[-1] is None or history[-2] is None:
        return known[-1]
    (R1, t1), (R2, t2) = history[-2], history[-1]
    return R2 @ R1.T @ R2, t2 + (t2 - t1)


def hard_silhouettes(vertices_world: np.ndarray, faces: np.ndarray, cameras: Cameras, sizes) -> list[np.ndarray]:
    """Binary silhouettes (H, W) per view by filling projected triangles (no gradient; for mask choice)."""
    pix, depth = project(torch.as_tensor(vertices_world, dtype=cameras.K.dtype), cameras)
    pix, depth = pix.numpy(), depth.numpy()
    out = []
    for c, (H, W) in enumerate(sizes):
        img = np.zeros((H, W), np.uint8)
        front = (depth[c][faces] > 0.05).all(1)
        tris = np.round(pix[c][faces[front]] * 4).astype(np.int32)  # 2 fractional bits
        inside = np.abs(tris).max(axis=(1, 2)) < 4 * 8 * max(H, W)
        if inside.any():
            cv2.fillPoly(img, list(tris[inside]), 1, lineType=cv2.LINE_8, shift=2)
        out.append(img.astype(bool))
    return out


class ObjectTracker:
    """Tracks one rigid mesh through a session; see the module docstring."""

    def __init__(self, session, cfg, mesh, device: str = "cpu"):
        self.session, self.cfg, self.device = session, cfg, torch.device(device)
        self.cameras = Cameras.from_infos(session.cameras, device=device, dtype=torch.float32)
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.centroid = vertices.mean(0)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        self.vertices_c = torch.as_tensor(vertices - self.centroid, dtype=torch.float32, device=device)  # centred
        self.topology = MeshTopology.from_faces(torch.as_tensor(self.faces, device=device))
        self.extent = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        samples, face_ids = trimesh.sample.sample_surface(mesh, 4000, seed=cfg.seed)
        self.model_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(samples) - self.centroid))
        self.model_cloud.normals = o3d.utility.Vector3dVector(np.asarray(mesh.face_normals)[face_ids])
        self.sizes = [(c.height, c.width) for c in session.cameras]
        self.use_masks = cfg.use_session_masks and all(session.has_kind("mask_object"))
        self.backgrounds = None
        self._rays: dict[int, torch.Tensor] = {}

    # -- observations ---------------------------------------------------------------
    def _background(self) -> list[np.ndarray]:
        if self.backgrounds is None:
            from intercap.prepare import spread_frames

            frames = spread_frames(self.session.frame_ids, self.cfg.background_frames)
            self.backgrounds = []
            for c, (H, W) in enumerate(self.sizes):
                stack = [self.session.read_depth(c, int(f)) for f in frames]
                stack = np.stack([d if d is not None else np.zeros((H, W), np.float32) for d in stack])
                self.backgrounds.append(background_depth(stack))
        return self.backgrounds

    def observe(self, frame_id: int, predicted) -> Observation:
        """Depth and object masks of all views (masks derived when the session has none)."""
        C = len(self.sizes)
        H, W = max(s[0] for s in self.sizes), max(s[1] for s in self.sizes)
        masks = np.zeros((C, H, W), np.float32)
        depths = np.zeros((C, H, W), np.float32)
        known = np.zeros((C, H, W), np.float32)
        has = np.zeros(C, bool)
        guides = None
        if not self.use_masks and predicted is not None:
            R, t = predicted
            guides = hard_silhouettes(self.world_vertices_np(R, t), self.faces, self.cameras, self.sizes)
        for c, (h, w) in enumerate(self.sizes):
            depth = self.session.read_depth(c, frame_id)
            if depth is None:
                continue
            depths[c, :h, :w] = depth
            if self.use_masks:
                mask = self.session.read_mask(c, frame_id, "object")
                known[c, :h, :w] = 1.0
            else:
                mask = self.derived_mask(c, frame_id, depth, None if guides is None else guides[c])
                known[c, :h, :w] = depth > 0
            if mask is not None and mask.sum() >= self.cfg.min_mask_px:
                masks[c, :h, :w] = mask
                has[c] = True
        return Observation(mask=masks, depth=depths, has_view=has, known=known)

    def derived_mask(self, c: int, frame_id: int, depth: np.ndarray, guide) -> np.ndarray:
        """Object mask from depth foreground minus person, chosen by the predicted silhouette
        or, with no prediction, by matching the object's size in 3D."""
        foreground = foreground_mask(depth, self._background()[c])
        person = self.session.read_mask(c, frame_id, "person")
        if guide is not None:
            return select_object_candidate(foreground, person, guide.astype(np.float32), self.cfg.min_mask_px,
                                           bridge_px=self._bridge_px(c))
        candidates = components(clean_mask(foreground & ~person if person is not None else foreground),
                                self.cfg.min_mask_px, self._bridge_px(c))
        best, best_score = None, np.inf
        for cand in candidates:
            points = self._points(c, depth * cand)
            if len(points) < 20:
                continue
            extent = np.linalg.norm(np.percentile(points, 95, 0) - np.percentile(points, 5, 0))
            score = abs(np.log(extent / (0.8 * self.extent)))  # visible extent is a little under the full one
            if score < best_score and extent < 1.6 * self.extent:
                best, best_score = cand, score
        return best if best is not None else np.zeros_like(foreground)

    def _bridge_px(self, c: int) -> int:
        """Gap (pixels) bridged between fragments of the object's depth foreground in view c."""
        return max(1, int(round(self.cfg.bridge_fraction * self.sizes[c][1])))

    def _points(self, c: int, depth: np.ndarray) -> np.ndarray:
        """World points (N, 3) of the non-zero pixels of one view's depth map."""
        if c not in self._rays:  # undistorting every pixel is the costly part: once per camera
            H, W = self.sizes[c]
            self._rays[c] = pixel_rays(self.cameras.select([c]), H, W, 1)
        points, valid = depth_to_point_grid(torch.from_numpy(depth)[None], self.cameras.select([c]), 1, 0.1, 10.0,
                                            rays=self._rays[c])
        return points[0][valid[0]].numpy().astype(np.float64)

    # -- pose helpers ---------------------------------------------------------------------
    def world_vertices(self, R: torch.Tensor, t_c: torch.Tensor) -> torch.Tensor:
        """Centred model vertices posed by (R, centre translation) -> (V, 3)."""
        return self.vertices_c @ R.T + t_c

    def world_vertices_np(self, R, t) -> np.ndarray:
        """Vertices of the original mesh under object->world pose (R, t)."""
        return (self.vertices_c.double().numpy() + self.centroid) @ np.asarray(R).T + np.asarray(t)

    def _to_centre(self, R, t) -> np.ndarray:
        return np.asarray(R) @ self.centroid + np.asarray(t)

    def _from_centre(self, R, t_c) -> np.ndarray:
        return np.asarray(t_c) - np.asarray(R) @ self.centroid

    # -- fitting -------------------------------------------------------------------------------
    def crops_for(self, obs: Observation, R, t) -> torch.Tensor:
        """(C, 4) square boxes covering the projected pose and the observed mask, per view."""
        cfg = self.cfg
        pix, _ = project(torch.as_tensor(self.world_vertices_np(R, t), dtype=torch.float32), self.cameras)
        boxes = []
        for c, (H, W) in enumerate(self.sizes):
            lo, hi = pix[c].amin(0).numpy(), pix[c].amax(0).numpy()
            if obs.has_view[c]:
                ys, xs = np.nonzero(obs.mask[c] > 0.5)
                lo = np.minimum(lo, [xs.min(), ys.min()])
                hi = np.maximum(hi, [xs.max(), ys.max()])
            lo, hi = np.maximum(lo, [-W, -H]), np.minimum(hi, [2 * W, 2 * H])
            centre, half = (lo + hi) / 2, max((hi - lo).max() / 2 * (1 + cfg.crop_margin), 8.0)
            boxes.append([centre[0] - half, centre[1] - half, centre[0] + half, centre[1] + half])
        return torch.tensor(boxes, dtype=torch.float32)

    def energy_terms(self, obs_mask, obs_depth, obs_known, view_weight, R, t_c, crops):
        """E_O at a pose: (total, silhouette, depth, render output)."""
        cfg = self.cfg
        out = render(self.world_vertices(R, t_c)[None], self.topology, self.cameras, crops[None],
                     size=(cfg.crop_size, cfg.crop_size), sigma=cfg.sigma_px)
        rendered_depth = out.depth[0]
        visible = occlusion_weight(rendered_depth.detach(), obs_depth, cfg.occluder_margin_m)  # (C, h, w)
        view_weight = view_weight[:, None, None]
        sil = object_silhouette(out.silhouette, obs_mask[None], (visible * obs_known * view_weight)[None])
        # Every observed object pixel counts, covered or not: an uncovered one pays the full
        # robust cost, so rendering nothing (or too little) is never the cheap answer.
        depth_weight = (obs_mask > 0.5) & (obs_depth > 0)
        dep = object_depth(rendered_depth[None], obs_depth[None], (depth_weight * visible * view_weight)[None], cfg.depth_scale_m)
        total = cfg.w_silhouette * sil + cfg.w_depth * dep
        return total[0], sil[0], dep[0], out

    def fit(self, obs: Observation, R0, t0, iterations: int | None = None) -> Fit:
        """Minimise E_O over (6D rotation, translation) from (R0, t0)."""
        cfg = self.cfg
        crops = self.crops_for(obs, R0, t0)
        size = (cfg.crop_size, cfg.crop_size)
        obs_mask = crop_observation(torch.from_numpy(obs.mask), crops, size, "area")
        obs_depth = crop_observation(torch.from_numpy(obs.depth), crops, size, "nearest")
        obs_known = crop_observation(torch.from_numpy(obs.known), crops, size, "area")
        view_weight = torch.as_tensor(obs.has_view, dtype=torch.float32)
        r6 = matrix_to_rotation_6d(torch.tensor(np.asarray(R0), dtype=torch.float32)).clone().requires_grad_(True)
        t_c = torch.as_tensor(self._to_centre(R0, t0), dtype=torch.float32).clone().requires_grad_(True)
        optimiser = torch.optim.Adam([{"params": [r6], "lr": cfg.lr_rotation}, {"params": [t_c], "lr": cfg.lr_translation}])
        best = (np.inf, None, None)
        stalled = 0
        for step in range(cfg.iterations if iterations is None else iterations):
            optimiser.zero_grad()
            total, _, _, _ = self.energy_terms(obs_mask, obs_depth, obs_known, view_weight, rotation_6d_to_matrix(r6), t_c, crops)
            value = total.item()
            # Stop once E_O has not improved by a relative `stop_tolerance` for `stop_patience` steps.
            stalled = stalled + 1 if value > best[0] * (1 - cfg.stop_tolerance) else 0
            if value < best[0]:
                best = (value, r6.detach().clone(), t_c.detach().clone())
            if stalled >= cfg.stop_patience:
                break
            total.backward()
            optimiser.step()
        with torch.no_grad():
            R = rotation_6d_to_matrix(r6)
            total, _, _, out = self.energy_terms(obs_mask, obs_depth, obs_known, view_weight, R, t_c, crops)
            if total.item() > best[0]:
                R, t_c = rotation_6d_to_matrix(best[1]), best[2]
                total, _, _, out = self.energy_terms(obs_mask, obs_depth, obs_known, view_weight, R, t_c, crops)
            known = obs_known > 0.5
            confidence = self._iou(out.coverage[0] & known, (obs_mask > 0.5) & known, obs.has_view)
        R = R.detach().double().numpy()
        return Fit(R=R, t=self._from_centre(R, t_c.detach().double().numpy()), energy=float(total), confidence=confidence)

    @staticmethod
    def _iou(rendered: torch.Tensor, observed: torch.Tensor, has_view: np.ndarray) -> float:
        inter = (rendered & observed).flatten(1).sum(1).float()
        union = (rendered | observed).flatten(1).sum(1).float().clamp(min=1)
        iou = (inter / union).numpy()[has_view]
        return float(iou.mean()) if len(iou) else 0.0

    # -- initialisation ----------------------------------------------------------------------
    def object_points(self, obs: Observation) -> np.ndarray:
        """World points of the object masks of all views, (N, 3)."""
        clouds = [self._points(c, obs.depth[c, :h, :w] * (obs.mask[c, :h, :w] > 0.5))
                  for c, (h, w) in enumerate(self.sizes) if obs.has_view[c]]
        return np.concatenate(clouds) if clouds else np.zeros((0, 3))

    def registration_hypotheses(self, points: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Candidate object->world poses (R, t) registering the mesh to observed points: PCA alignments with
        every proper axis flip, and FPFH RANSAC global registrations; each refined by ICP."""
        cfg = self.cfg
        scene = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(cfg.voxel_size_m)
        scene, _ = scene.remove_statistical_outlier(20, 2.0)
        if len(scene.points) < 30:
            return []
        scene_pts = np.asarray(scene.points)
        model_pts = np.asarray(self.model_cloud.points)
        starts = []
        _, _, v_model = np.linalg.svd(model_pts - model_pts.mean(0), full_matrices=False)
        _, _, v_scene = np.linalg.svd(scene_pts - scene_pts.mean(0), full_matrices=False)
        for signs in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]):
            for perm in ([0, 1, 2], [1, 0, 2], [0, 2, 1], [2, 1, 0], [1, 2, 0], [2, 0, 1]):
                A = v_scene[perm] * np.array(signs)[:, None]
                R = A.T @ v_model  # model axes onto scene axes
                if np.linalg.det(R) < 0:
                    continue
                starts.append((R, scene_pts.mean(0)))
        starts += self._global_registrations(scene)
        refined = []
        model = self.model_cloud
        for R, t in starts:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R.T, -R.T @ t  # scene -> centred model
            for dist in (cfg.voxel_size_m * 12, cfg.voxel_size_m * 4, cfg.voxel_size_m * 2):
                result = reg.registration_icp(scene, model, dist, T, reg.TransformationEstimationPointToPlane())
                T = result.transformation
            Rw = T[:3, :3].T
            # Rank by how much of the scene lies on the model surface, then by residual.
            refined.append((-result.fitness, result.inlier_rmse, Rw, self._from_centre(Rw, -Rw @ T[:3, 3])))
        refined.sort(key=lambda r: (round(r[0], 2), r[1]))
        return [(R, t) for _, _, R, t in refined[: cfg.init_keep]]

    def _global_registrations(self, scene) -> list[tuple[np.ndarray, np.ndarray]]:
        cfg = self.cfg
        voxel = cfg.voxel_size_m * 2
        feats = []
        for cloud in (self.model_cloud.voxel_down_sample(voxel), scene.voxel_down_sample(voxel)):
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 3, max_nn=30))
            feats.append((cloud, reg.compute_fpfh_feature(cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 6, max_nn=100))))
        (model, fm), (sc, fs) = feats
        out = []
        for k in range(cfg.init_global_tries):
            o3d.utility.random.seed(cfg.seed + k)
            result = reg.registration_ransac_based_on_feature_matching(
                model, sc, fm, fs, True, voxel * 2, reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnDistance(voxel * 2)], reg.RANSACConvergenceCriteria(cfg.init_ransac_iterations, 0.999))
            T = result.transformation  # model -> scene
            out.append((T[:3, :3], T[:3, 3]))
        return out

    def initialise(self, obs: Observation, extra: list | None = None) -> Fit | None:
        """Best of the registration hypotheses (plus `extra` poses): the few with the lowest
        E_O get a short fit, the best of those the full one."""
        hypotheses = list(extra or []) + self.registration_hypotheses(self.object_points(obs))
        if not hypotheses:
            return None
        scored = sorted((self.fit(obs, R, t, iterations=0) for R, t in hypotheses), key=lambda f: f.energy)
        fits = [self.fit(obs, f.R, f.t, iterations=self.cfg.init_iterations) for f in scored[: self.cfg.init_refine]]
        best = min(fits, key=lambda f: f.energy)
        return self.fit(obs, best.R, best.t)


TRACKED, REINITIALISED, LOST, UNTRUSTED = 1, 2, 3, 4
STATUS_NAMES = {0: "pending", TRACKED: "tracked", REINITIALISED: "reinitialised", LOST: "lost", UNTRUSTED: "untrusted"}


def track(tracker: ObjectTracker, frame_ids: np.ndarray, checkpoint: Path | None = None, progress: bool = True,
          initial_pose=None) -> dict[str, np.ndarray]:
    """Track the object through `frame_ids`; resumes from `checkpoint` when it exists.

    Returns R (T,3,3), t (T,3) (NaN where untrusted), confidence (T,), status (T,),
    energy (T,)."""
    cfg = tracker.cfg
    T = len(frame_ids)
    state = {"R": np.full((T, 3, 3), np.nan), "t": np.full((T, 3), np.nan), "confidence": np.zeros(T),
             "status": np.zeros(T, np.int64), "energy": np.full(T, np.nan)}
    start = 0
    if checkpoint is not None and checkpoint.exists():
        saved = dict(np.load(checkpoint))
        if len(saved["status"]) == T:
            state = {k: saved[k] for k in state}
            start = int(saved["next"])
            log.info("object: resuming at frame %d of %d", start, T)
    history = [None if state["status"][i] not in (TRACKED, REINITIALISED) else (state["R"][i], state["t"][i])
               for i in range(start)]
    for i in tqdm(range(start, T), desc="object", disable=not progress, initial=start, total=T):
        frame_id = int(frame_ids[i])
        predicted = predict_pose(history) if history else None
        if predicted is None and i == 0 and initial_pose is not None:
            predicted = initial_pose
        obs = tracker.observe(frame_id, predicted)
        fit, status = None, LOST
        if obs.visible_views >= cfg.min_views:
            if predicted is None:
                fit, status = tracker.initialise(obs), REINITIALISED
            else:
                fit, status = tracker.fit(obs, *predicted), TRACKED
                recent = state["energy"][max(0, i - 10):i]
                recent = recent[np.isfinite(recent)]
                jumped = len(recent) > 2 and fit.energy > cfg.reinit_energy_ratio * np.median(recent)
                if fit.confidence < cfg.min_confidence or jumped:
                    alternative = tracker.initialise(obs, extra=[predicted])
                    if alternative is not None and alternative.energy < fit.energy:
                        fit, status = alternative, REINITIALISED
        trusted = fit is not None and fit.confidence >= cfg.min_confidence
        if fit is not None:
            state["energy"][i] = fit.energy
            state["confidence"][i] = fit.confidence if trusted else 0.0
        if trusted:
            state["R"][i], state["t"][i] = fit.R, fit.t
            state["status"][i] = status
        else:
            state["status"][i] = UNTRUSTED if fit is not None else LOST
        history.append((fit.R, fit.t) if trusted else None)
        if checkpoint is not None and ((i + 1) % cfg.checkpoint_every == 0 or i + 1 == T):
            save_npz(checkpoint, next=i + 1, **state)
    return state


def draw_overlay(session, tracker: ObjectTracker, frame_id: int, R, t, path: Path) -> None:
    """Colour views side by side with the tracked object's outline drawn on them."""
    sils = hard_silhouettes(tracker.world_vertices_np(R, t), tracker.faces, tracker.cameras, tracker.sizes) if np.isfinite(R).all() else None
    tiles = []
    for c, (H, W) in enumerate(tracker.sizes):
        color = session.read_color(c, frame_id)
        img = np.zeros((H, W, 3), np.uint8) if color is None else cv2.cvtColor(color, cv2.COLOR_RGB2BGR)
        if sils is not None:
            contours, _ = cv2.findContours(sils[c].astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(img, contours, -1, (0, 255, 0), 1)
        tiles.append(cv2.resize(img, (W * 240 // H, 240)))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(tiles, axis=1), [cv2.IMWRITE_JPEG_QUALITY, 85])


def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `object` stage: writes OUT/object_poses.npz and OUT/object/."""
    if session.object is None:
        log.info("object: the session has no object; nothing to track")
        return {"skipped": "no object in session"}
    ocfg = cfg.object
    torch.manual_seed(ocfg.seed)
    stage_dir = Path(out_dir) / "object"
    tracker = ObjectTracker(session, ocfg, session.object.load_mesh(), device=cfg.run.device)
    state = track(tracker, session.frame_ids, stage_dir / "progress.npz", progress, session.object.initial_pose)
    valid = np.isin(state["status"], (TRACKED, REINITIALISED))
    save_npz(Path(out_dir) / "object_poses.npz", R=state["R"], t=state["t"], confidence=state["confidence"],
             valid=valid, status=state["status"], frame_ids=session.frame_ids)
    for i in range(0, session.num_frames, max(1, ocfg.overlay_every)):
        draw_overlay(session, tracker, int(session.frame_ids[i]), state["R"][i], state["t"][i],
                     stage_dir / "overlays" / f"{int(session.frame_ids[i]):06d}.jpg")
    counts = {STATUS_NAMES[s]: int((state["status"] == s).sum()) for s in (TRACKED, REINITIALISED, LOST, UNTRUSTED)}
    return {
        "masks": "session" if tracker.use_masks else "derived",
        "frames_trusted": int(valid.sum()),
        **{f"frames_{k}": v for k, v in counts.items()},
        "mean_confidence": float(state["confidence"][valid].mean()) if valid.any() else 0.0,
    }
