"""Stage 3, `object`: per-frame 6-DoF object tracking by silhouette and depth rendering.

Per frame, the object's pose (6D rotation + translation) minimises E_O over all
views (`losses.object_silhouette` + `losses.object_depth`) with the
differentiable renderer of `intercap.rendering`, starting from a constant-
velocity prediction (Adam; the step size shrinks once E_O stalls).

Masks come from the session, or are derived from depth: a background model per
camera (the person's pixels left out, beyond-range regions known as far), the
foreground outside the person, and of that the pixels whose 3D points lie near
the predicted pose (render-compare-and-preserve in 3D); pixels without depth or
barely in front of the background are unknown, not background. Where the object
may have moved far from the prediction (a fast lift), that cut is wide and takes
in the hands and arms that hold it: the mask is cut again round the fit, and the
fit refined on it (`ObjectTracker.recut`).

The first pose comes from session.yaml when given, else from registering the
mesh to the first frame's object points (PCA and FPFH starts, ICP, the best
one's quarter turns; the lowest E_O after a short fit wins). A fit whose
silhouette IoU (over pixels not hidden by something in front) is low or whose
E_O jumps above its recent level is searched again: locally (quarter turns
about the mesh's principal axes: a chair's seat and legs look alike every 90
deg), then by registration. Frames whose best fit still disagrees with the
observations, or where no view sees the object, get NaN poses and confidence 0
(marked, never invented).

Every fit is a request that `ObjectTracker.fit_many` serves together with others: a search's
candidate poses, and on a GPU the current frames of several chunks of the take tracked side by
side (`object.side_by_side_gpu`). Each fit keeps its own Adam state and stopping, so it ends
where it would alone, at one render per step for all.

Writes OUT/object/object_poses.npz (R (T,3,3), t (T,3), confidence (T,), valid (T,),
frame_ids (T,)), shown as OUT/object_poses.npz until the `global` stage
replaces that with its own, OUT/object/progress_LO_HI.npz per chunk of frames while running (resume), and
OUT/object/overlays/*.jpg (rendered outline on the colour images) for a person
to check.
"""
from __future__ import annotations

import dataclasses
import hashlib
import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import torch
import trimesh

from intercap.energies.losses import (
    matrix_to_rotation_6d,
    object_depth,
    object_silhouette,
    occlusion_weight,
    rotation_6d_to_matrix,
)
from intercap.energies import optim
from intercap.geometry.cameras import Cameras, pixel_rays, project
from intercap.geometry.pointclouds import open3d_threads
from intercap.geometry.rendering import Capacity, MeshTopology, crop_observation, render
from intercap.geometry.segmentation import (
    background_depth,
    clean_mask,
    components,
    fill_missing,
    foreground_mask,
    uncertain_mask,
)
from intercap.geometry.symmetry import (axis_angle_matrix, equivalent_pose, mesh_symmetry, rotation_angle_deg,
                                        unwrap_symmetry)
from intercap.io.files import publish, save_npz
from intercap.stages.chunks import Chunk, chunk_groups, lockstep, run_chunks
from intercap.session.session import in_threads

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
    _boxes: dict = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)  # `mask_box`'s, by view

    @property
    def visible_views(self) -> int:
        return int(self.has_view.sum())

    def mask_box(self, c: int) -> tuple[np.ndarray, np.ndarray] | None:
        """View c's mask pixels' bounds, (x, y) lowest and highest; None when it has none."""
        if c not in self._boxes:
            inside = self.mask[c] > 0.5
            xs, ys = np.flatnonzero(inside.any(0)), np.flatnonzero(inside.any(1))
            self._boxes[c] = (np.array([xs[0], ys[0]]), np.array([xs[-1], ys[-1]])) if len(xs) else None
        return self._boxes[c]


@dataclass
class Fit:
    R: np.ndarray  # (3, 3) object -> world
    t: np.ndarray  # (3,)
    energy: float
    confidence: float  # mean silhouette IoU over views that see the object (pixels hidden by an occluder left out)


def predict_pose(history: list[tuple[np.ndarray, np.ndarray] | None]):
    """Constant-velocity prediction from the last two trusted poses (or the last one)."""
    known = [h for h in history[-2:] if h is not None]
    if not known:
        return None
    if len(known) == 1 or history[-1] is None or history[-2] is None:
        return known[-1]
    (R1, t1), (R2, t2) = history[-2], history[-1]
    return R2 @ R1.T @ R2, t2 + (t2 - t1)


def same_pose(a, b, distance_m: float, angle_deg: float = 10.0) -> bool:
    """Poses (R, t) within `distance_m` (translation) and `angle_deg` (rotation) of each other."""
    cos = (np.trace(np.asarray(a[0]).T @ np.asarray(b[0])) - 1) / 2
    return bool(np.linalg.norm(np.asarray(a[1]) - np.asarray(b[1])) < distance_m and cos > np.cos(np.radians(angle_deg)))


def distinct(poses: list, distance_m: float, taken: list = ()) -> list:
    """`poses` (R, t) in order, without those `same_pose` as an earlier one or one in `taken`."""
    kept: list = []
    for pose in poses:
        if not any(same_pose(pose, k, distance_m) for k in [*taken, *kept]):
            kept.append(pose)
    return kept


def axis_rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotation (3, 3) by `angle_deg` about `axis` (any length)."""
    return axis_angle_matrix(axis, np.radians(angle_deg))


def hard_silhouettes(vertices_world: np.ndarray, faces: np.ndarray, cameras: Cameras, sizes) -> list[np.ndarray]:
    """Binary silhouettes (H, W) per view by filling projected triangles (no gradient; for mask choice)."""
    pix, depth = project(torch.as_tensor(vertices_world, dtype=cameras.K.dtype, device=cameras.K.device), cameras)
    pix, depth = pix.cpu().numpy(), depth.cpu().numpy()
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


def crop_windows(images, crops: torch.Tensor, size, modes: tuple[str, ...]) -> list[torch.Tensor]:
    """`crop_observation` of K images (C, H, W) (a list, or stacked), image k with modes[k], on crops
    (C, 4) -> K x (C, h, w).

    Same values as cropping the full images, but only a window around each crop is
    copied and integrated (the integral image of 4 whole 640x576 views per call was
    a third of a frame's time); pixels outside the image still read 0."""
    K, (C, H, W) = len(images), images[0].shape
    box = crops.double().numpy()
    lo = np.clip(np.floor(box[:, :2]) - 2, 0, [W, H]).astype(int)  # (C, 2) window start (x, y)
    hi = np.clip(np.ceil(box[:, 2:]) + 3, 0, [W, H]).astype(int)
    hi = np.maximum(hi, lo)
    ws, hs = max(1, int((hi - lo)[:, 0].max())), max(1, int((hi - lo)[:, 1].max()))
    window = np.zeros((K, C, hs, ws), np.float32)
    for c in range(C):
        (x0, y0), (x1, y1) = lo[c], hi[c]
        for k in range(K):
            window[k, c, : y1 - y0, : x1 - x0] = images[k][c, y0:y1, x0:x1]
    shift = torch.as_tensor(np.concatenate([lo, lo], 1), dtype=crops.dtype)
    # A window cut short by the image border ends where the image does; zeros padded
    # beyond a window that was not cut are never reached by its crop's footprint.
    local = crops - shift
    window = torch.from_numpy(window)
    return [crop_observation(window[k], local, size, mode) for k, mode in enumerate(modes)]


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
        self.radius = float(np.linalg.norm(vertices - self.centroid, axis=1).max())  # bounding sphere about the centroid
        samples, face_ids = trimesh.sample.sample_surface(mesh, 4000, seed=cfg.seed)
        self.model_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(samples) - self.centroid))
        self.model_cloud.normals = o3d.utility.Vector3dVector(np.asarray(mesh.face_normals)[face_ids])
        _, _, axes = np.linalg.svd(np.asarray(samples) - self.centroid, full_matrices=False)
        self.turns = [axis_rotation(a, angle) for a in axes for angle in (90, 180, 270)]  # (3, 3) in object coords
        self.sizes = [(c.height, c.width) for c in session.cameras]
        self.session_masks = cfg.use_session_masks  # the session's mask where a view and frame has one ...
        self.use_masks = cfg.use_session_masks and not session.missing("mask_object").any()  # ... or everywhere
        # renders of fixed shapes (`rendering.Capacity`), each fit step one replayed CUDA graph
        self.fixed_shapes = optim.records_graphs(self.device) and cfg.cuda_graphs
        self._fixed_fits: dict[int, FixedShapeFits] = {}  # by the number of poses fitted at once
        self._reader, self._ahead = None, {}  # `read_ahead`'s thread and its observations, by frame
        self.backgrounds = None
        self._lock = threading.Lock()
        self._rays: dict[int, torch.Tensor] = {}
        self._mesh, self._symmetry = mesh, None  # `symmetry`'s, found when first asked

    # -- observations ---------------------------------------------------------------
    def _background(self) -> list[np.ndarray]:
        """Depth background per camera over `background_frames` frames, the person's pixels left out."""
        with self._lock:  # observations are read in threads (the global stage's windows)
            if self.backgrounds is None:
                from intercap.stages.prepare.stage import spread_frames

                frames = spread_frames(self.session.frame_ids, self.cfg.background_frames)
                backgrounds = []
                for c, (H, W) in enumerate(self.sizes):
                    stack = [self.session.read_depth(c, int(f)) for f in frames]
                    stack = np.stack([d if d is not None else np.zeros((H, W), np.float32) for d in stack])
                    people = [self.session.read_mask(c, int(f), "person") for f in frames]
                    ignore = np.stack([m if m is not None else np.zeros((H, W), bool) for m in people])
                    backgrounds.append(background_depth(stack, min_valid_fraction=self.cfg.background_valid_fraction,
                                                        ignore=ignore))
                self.backgrounds = backgrounds
        return self.backgrounds

    def read_ahead(self, frame_id: int) -> None:
        """Start reading frame `frame_id`'s observation in a background thread, for `observe` to
        take, where that does not wait for a prediction (the session's masks everywhere), on a GPU
        (`object.read_ahead`), whose fits leave the cores to spare. On the CPU the fits use the
        cores: one process with two threads tracked the 150-frame bench 9 % slower reading ahead."""
        if not (self.cfg.read_ahead and self.use_masks and self.device.type == "cuda") or frame_id in self._ahead:
            return
        if self._reader is None:
            self._reader = ThreadPoolExecutor(max_workers=1)
        self._ahead[frame_id] = self._reader.submit(self._read, frame_id, None, 0.0)

    def observe(self, frame_id: int, predicted, reach_m: float = 0.0, depths: list | None = None) -> Observation:
        """Depth and object masks of all views (masks derived when the session has none).

        `reach_m`: how far the object may have moved from `predicted` (derived masks only);
        `depths`: the views' depth maps when already read."""
        if frame_id in self._ahead:  # read ahead (`read_ahead`: session masks, the same observation)
            return self._ahead.pop(frame_id).result()
        return self._read(frame_id, predicted, reach_m, depths)

    def _read(self, frame_id: int, predicted, reach_m: float, given: list | None = None) -> Observation:
        """`observe`'s reading; `given`: the depth maps already read."""
        C = len(self.sizes)
        H, W = max(s[0] for s in self.sizes), max(s[1] for s in self.sizes)
        masks = np.zeros((C, H, W), np.float32)
        depths = np.zeros((C, H, W), np.float32)
        known = np.zeros((C, H, W), np.float32)
        has = np.zeros(C, bool)

        def read_view(c: int) -> None:  # the views in IO threads (`in_threads`)
            h, w = self.sizes[c]
            depth = self.session.read_depth(c, frame_id) if given is None else given[c]
            if depth is None:
                return
            depths[c, :h, :w] = depth
            if self.session_masks and self.session.has_frame(c, "mask_object", frame_id):
                mask = self.session.read_mask(c, frame_id, "object")
                known[c, :h, :w] = 1.0
            else:
                mask, known[c, :h, :w] = self.derived_mask(c, frame_id, depth, predicted, reach_m)
            if mask is not None and mask.sum() >= self.cfg.min_mask_px:
                masks[c, :h, :w] = mask
                has[c] = True

        in_threads(read_view, range(C))
        return Observation(mask=masks, depth=depths, has_view=has, known=known)

    def derived_mask(self, c: int, frame_id: int, depth: np.ndarray, predicted, reach_m: float = 0.0):
        """Object mask (H, W) bool and known labels (H, W) bool of view c from depth alone.

        Candidates are the depth foreground outside the person. With a predicted pose,
        the object is every candidate pixel whose 3D point lies within the object's
        bounding sphere at that pose (grown by `reach_m` + `near_margin_m`): the 3D form of
        render-compare-and-preserve, which keeps all fragments of a thin-barred object
        and, unlike overlap in the image, does not cut off an object that moved more
        than predicted. Without one, the component whose 3D extent best matches the
        object's. Pixels only slightly in front of the background (a chair's feet on the
        floor, a box's bottom edge) are neither object nor background: unknown."""
        background = self._background()[c]
        foreground = foreground_mask(depth, background)
        known = (depth > 0) & ~(uncertain_mask(depth, background) & ~foreground)
        person = self.session.read_mask(c, frame_id, "person")
        gap = self._bridge_px(c)
        # Dropouts (a dark surface loses ~40% of its depth, speckled) would let the opening
        # in `clean_mask` erase thin parts: fill them first where foreground surrounds them.
        foreground = fill_missing(foreground, depth, gap)
        candidates = clean_mask(foreground & ~person if person is not None else foreground)
        if predicted is not None:
            R, t = predicted
            centre = self._to_centre(R, t)
            ys, xs = np.nonzero(candidates & (depth > 0))
            points = self._pixel_points(c, ys, xs, depth[ys, xs])
            near = np.linalg.norm(points - centre, axis=1) < self.radius + self.cfg.near_margin_m + reach_m
            mask = np.zeros_like(candidates)
            mask[ys[near], xs[near]] = True
            mask = fill_missing(mask, depth, gap) & candidates
            parts = components(mask, self.cfg.min_mask_px)  # drops specks the sphere cut off
            return (np.any(parts, axis=0) if parts else np.zeros_like(mask)), known
        best, best_score = None, np.inf
        for cand in components(candidates, self.cfg.min_mask_px, gap):
            ys, xs = np.nonzero(cand & (depth > 0))
            points = self._pixel_points(c, ys, xs, depth[ys, xs])
            if len(points) < 20:
                continue
            extent = np.linalg.norm(np.percentile(points, 95, 0) - np.percentile(points, 5, 0))
            score = abs(np.log(extent / (0.8 * self.extent)))  # visible extent is a little under the full one
            if score < best_score and extent < 1.6 * self.extent:
                best, best_score = cand, score
        return (best if best is not None else np.zeros_like(foreground)), known

    def _bridge_px(self, c: int) -> int:
        """Gap (pixels) bridged between fragments of the object's depth foreground in view c."""
        return max(1, int(round(self.cfg.bridge_fraction * self.sizes[c][1])))

    def _pixel_points(self, c: int, ys: np.ndarray, xs: np.ndarray, z: np.ndarray) -> np.ndarray:
        """World points (N, 3) of pixels (ys, xs) of view c at depths z (metres)."""
        if c not in self._rays:  # undistorting every pixel is the costly part: once per camera
            H, W = self.sizes[c]
            self._rays[c] = pixel_rays(self.cameras.select([c]), H, W, 1)[0].double().cpu().numpy().reshape(H, W, 2)
        ray = self._rays[c][ys, xs]  # (N, 2) undistorted x/z, y/z
        cam = np.concatenate([ray * z[:, None], z[:, None]], 1)
        T = self.cameras.T_world_from_cam[c].double().cpu().numpy()
        return cam @ T[:3, :3].T + T[:3, 3]

    def _points(self, c: int, depth: np.ndarray, x0: int = 0, y0: int = 0) -> np.ndarray:
        """World points (N, 3) of the pixels of one view's depth map with a measurement; `depth`
        may be a window of the view whose first pixel is (x0, y0)."""
        ys, xs = np.nonzero((depth > 0.1) & (depth < 10.0))
        return self._pixel_points(c, ys + y0, xs + x0, depth[ys, xs].astype(np.float64))

    # -- pose helpers ---------------------------------------------------------------------
    def world_vertices_np(self, R, t) -> np.ndarray:
        """Vertices of the original mesh under object->world pose (R, t)."""
        return (self.vertices_c.double().cpu().numpy() + self.centroid) @ np.asarray(R).T + np.asarray(t)

    def _to_centre(self, R, t) -> np.ndarray:
        return np.asarray(R) @ self.centroid + np.asarray(t)

    def _from_centre(self, R, t_c) -> np.ndarray:
        return np.asarray(t_c) - np.asarray(R) @ self.centroid

    def symmetry(self):
        """The mesh's rotational symmetry and the centre its axes pass through (`mesh_symmetry`)."""
        if self._symmetry is None:
            self._symmetry = mesh_symmetry(self._mesh)
        return self._symmetry

    def turned_like(self, R, t, reference_R):
        """The pose that looks as (R, t) does (the object's symmetry) whose rotation is nearest `reference_R`."""
        found, centre = self.symmetry()
        return equivalent_pose(R, t, reference_R, found, centre) if found.is_symmetric else (R, t)

    # -- fitting -------------------------------------------------------------------------------
    def crops_for(self, poses: list[tuple[Observation, np.ndarray, np.ndarray]]) -> torch.Tensor:
        """(P, C, 4) square boxes covering each (observation, R, t)'s projected pose and observed
        mask, per view. The P poses are projected together: one copy back from the fit's device."""
        cfg = self.cfg
        world = np.concatenate([self.world_vertices_np(R, t) for _, R, t in poses])  # (P * V, 3)
        pix, _ = project(torch.as_tensor(world, dtype=torch.float32, device=self.device), self.cameras)
        pix = pix.view(len(self.sizes), len(poses), -1, 2)
        lows, highs = pix.amin(2).cpu().numpy(), pix.amax(2).cpu().numpy()  # (C, P, 2): the boxes are made on the CPU
        boxes = np.zeros((len(poses), len(self.sizes), 4), np.float32)
        for p, (obs, _, _) in enumerate(poses):
            for c, (H, W) in enumerate(self.sizes):
                lo, hi = lows[c, p], highs[c, p]
                box = obs.mask_box(c) if obs.has_view[c] else None
                if box is not None:
                    lo, hi = np.minimum(lo, box[0]), np.maximum(hi, box[1])
                lo, hi = np.maximum(lo, [-W, -H]), np.minimum(hi, [2 * W, 2 * H])
                centre, half = (lo + hi) / 2, max((hi - lo).max() / 2 * (1 + cfg.crop_margin), 8.0)
                boxes[p, c] = [centre[0] - half, centre[1] - half, centre[0] + half, centre[1] + half]
        return torch.from_numpy(boxes)

    def _visible(self, rendered_depth, obs_depth, obs_mask) -> torch.Tensor:
        """1 where the rendered object could be seen: not behind a measured occluder. The
        object's own observed pixels never count as occluders, or a pose pushed behind the
        observed surface would hide from both terms of E_O."""
        visible = occlusion_weight(rendered_depth, obs_depth, self.cfg.occluder_margin_m)
        return torch.maximum(visible, (obs_mask > 0.5).to(visible.dtype))

    def energy_terms(self, obs_mask, obs_depth, obs_known, view_weight, R, t_c, crops, capacity=None):
        """E_O of P poses, each against its own windows: (total, silhouette, depth) (P,) and the
        render output. obs_* (P, C, h, w), view_weight (P, C), R (P, 3, 3), t_c (P, 3), crops (P, C, 4);
        capacity: the renderer's fixed shapes (`rendering.Capacity`) or None."""
        cfg = self.cfg
        out = render(self.vertices_c @ R.transpose(1, 2) + t_c[:, None], self.topology, self.cameras, crops,
                     size=(cfg.crop_size, cfg.crop_size), sigma=cfg.sigma_px, capacity=capacity)
        visible = self._visible(out.depth.detach(), obs_depth, obs_mask)  # (P, C, h, w)
        view_weight = view_weight[:, :, None, None]
        sil = object_silhouette(out.silhouette, obs_mask, visible * obs_known * view_weight)
        # Every observed object pixel counts, covered or not: an uncovered one pays the full
        # robust cost, so rendering nothing (or too little) is never the cheap answer.
        depth_weight = (obs_mask > 0.5) & (obs_depth > 0)
        dep = object_depth(out.depth, obs_depth, depth_weight * visible * view_weight, cfg.depth_scale_m)
        return cfg.w_silhouette * sil + cfg.w_depth * dep, sil, dep, out

    def windows(self, obs: Observation, crops: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The observation cut to `crops` (C, 4): the object's share of the known pixels, depth and
        the known fraction, (C, h, w) each, on the fitting device."""
        size = (self.cfg.crop_size, self.cfg.crop_size)
        obs_mask, obs_depth, obs_known = crop_windows([obs.mask * obs.known, obs.depth, obs.known], crops,
                                                      size, ("area", "nearest", "area"))
        # The object's share of the pixels whose label is known: where derived masks lose half of a
        # dark chair's depth to dropouts, the chair still fills its cells, at half the weight.
        obs_mask = torch.where(obs_known > 1e-3, obs_mask / obs_known.clamp(min=1e-3), torch.zeros_like(obs_mask))
        # the windows are cut on the CPU; the fit runs where the mesh and cameras are
        return tuple(x.to(self.device) for x in (obs_mask, obs_depth, obs_known))

    def fit(self, obs: Observation, R0, t0, iterations: int | None = None) -> Fit:
        """Minimise E_O over (6D rotation, translation) from (R0, t0) (`fit_many` of one)."""
        return self.fit_many([(obs, R0, t0, iterations)])[0]

    def settle(self, search):
        """The result of one search (`recut`, `refit`, `initialise`, `track_steps`), run alone."""
        return run_searches(self, [search])[0]

    def fit_many(self, requests: list[tuple]) -> list[Fit]:
        """Minimise E_O from each request's pose, (obs, R0, t0, iterations or None for
        `iterations`), all P fits in one render per step. Adam moves each parameter on its own, so
        each fit keeps its own moments, step count, step sizes, early stopping and budget: the
        result is each fit's alone, at the launches of one (a GPU's time follows the launches).
        With `fixed_shapes` the steps evaluate `FixedShapeFits` (all P poses rendered in fixed
        shapes; on CUDA one recorded graph, replayed by every later call with P poses too); the
        rows that are done are rendered but not moved."""
        cfg = self.cfg
        P, dev = len(requests), self.device
        crops = self.crops_for([(obs, R0, t0) for obs, R0, t0, _ in requests])  # (P, C, 4)
        cut = [self.windows(obs, c) for (obs, *_), c in zip(requests, crops)]
        obs_mask, obs_depth, obs_known = (torch.stack(parts) for parts in zip(*cut))
        view_weight = torch.as_tensor(np.stack([obs.has_view for obs, *_ in requests]), dtype=torch.float32, device=dev)
        budget = np.array([cfg.iterations if it is None else it for *_, it in requests])
        R0 = torch.as_tensor(np.stack([np.asarray(R) for _, R, _, _ in requests]), dtype=torch.float32, device=dev)
        r6 = matrix_to_rotation_6d(R0).clone().requires_grad_(True)
        t_c = torch.as_tensor(np.stack([self._to_centre(R, t) for _, R, t, _ in requests]), dtype=torch.float32,
                              device=dev).clone().requires_grad_(True)
        crops = crops.to(dev)  # cut on the CPU (`windows`), rendered where the fit runs
        stalled, decays, used = np.zeros(P, int), np.zeros(P, int), np.zeros(P, int)
        done = budget <= used
        fixed = None
        if self.fixed_shapes and not done.all():
            if P not in self._fixed_fits:
                self._fixed_fits[P] = FixedShapeFits(self, P)
            fixed = self._fixed_fits[P]
            fixed.load(obs_mask, obs_depth, obs_known, view_weight, crops, r6, t_c)
            r6, t_c, adam = fixed.r6, fixed.t_c, fixed.adam
        else:
            adam = optim.AdamRows([r6, t_c], [cfg.lr_rotation, cfg.lr_translation], P)
        stepping = np.zeros(P, bool)  # the rows whose step is taken before the next evaluation

        def energy(rows=None):
            """E_O of the fits `rows` (an index tensor; None: all), as (P,) tensors and the render."""
            pick = (lambda x: x) if rows is None else (lambda x: x.index_select(0, rows))
            return self.energy_terms(pick(obs_mask), pick(obs_depth), pick(obs_known), pick(view_weight),
                                     rotation_6d_to_matrix(pick(r6)), pick(t_c), pick(crops))

        best_value, best_r6, best_t = np.full(P, np.inf), r6.detach().clone(), t_c.detach().clone()
        while not done.all():
            live = np.flatnonzero(~done)
            if fixed is not None:  # the last iteration's step, then the evaluation
                values, total = fixed.evaluate(stepping)[0][live], None
            else:
                total = energy(None if len(live) == P else torch.as_tensor(live, device=dev))[0]
                values = total.detach().cpu().numpy()
            # No relative improvement of `stop_tolerance` for `stop_patience` steps: Adam is circling the
            # minimum at its step size; go back to the best pose with smaller steps, `lr_decays` times, then stop.
            stalled[live] = np.where(values > best_value[live] * (1 - cfg.stop_tolerance), stalled[live] + 1, 0)
            better = values < best_value[live]
            if better.any():
                best_value[live[better]] = values[better]
                at = torch.as_tensor(live[better], device=dev)
                best_r6[at], best_t[at] = r6.detach()[at], t_c.detach()[at]
            stop = stalled[live] >= cfg.stop_patience
            done[live[stop & (decays[live] == cfg.lr_decays)]] = True
            back = live[stop & (decays[live] < cfg.lr_decays)]
            if len(back):
                decays[back] += 1
                stalled[back] = 0
                at = torch.as_tensor(back, device=dev)
                with torch.no_grad():
                    adam.scale[at] *= cfg.lr_decay
                    r6[at], t_c[at] = best_r6[at], best_t[at]
            stepping[:] = False
            stepping[live[~stop]] = True
            if total is not None and not stop.all():  # the eager path steps now, along the rows' gradients
                steps = total if not stop.any() else total[torch.as_tensor(np.flatnonzero(~stop), device=dev)]
                steps.sum().backward()
                adam.step(torch.as_tensor(stepping, device=dev), [r6.grad, t_c.grad])
                r6.grad = t_c.grad = None
            used[live] += 1
            done |= used >= budget

        def final():
            """(E_O (P,), confidence (P,)) at the current poses (after the last step)."""
            if fixed is not None:
                return fixed.evaluate(stepping)
            with torch.no_grad():
                total, _, _, out = energy()
                return total.cpu().numpy(), self.confidence(out, obs_mask, obs_depth, obs_known, view_weight).cpu().numpy()

        total, confidence = final()
        worse = total > best_value  # the last step went up: the best pose seen
        if worse.any():
            at = torch.as_tensor(np.flatnonzero(worse), device=dev)
            with torch.no_grad():
                r6[at], t_c[at] = best_r6[at], best_t[at]
            stepping[:] = False
            total, confidence = final()
        with torch.no_grad():
            R = rotation_6d_to_matrix(r6).double().cpu().numpy()
            t_c = t_c.double().cpu().numpy()
        return [Fit(R=R[p], t=self._from_centre(R[p], t_c[p]), energy=float(total[p]), confidence=float(confidence[p]))
                for p in range(P)]

    # The searches below are generators: each yields lists of fit requests for `fit_many` and is
    # sent back their fits, so that `run_searches` can fit the requests of several at once.
    def recut(self, frame_id: int, fit: Fit):
        """Search: derived masks cut round `fit`'s pose with no reach, and the fit refined on them;
        returns (observation, fit or None when no view keeps enough object pixels). A mask cut wide
        round a prediction (a fast lift) takes in the hands and arms that hold the object; cut round
        the fit, it keeps the object alone."""
        obs = self.observe(frame_id, (fit.R, fit.t))
        if obs.visible_views < self.cfg.min_views:
            return obs, None
        (refined,) = yield [(obs, fit.R, fit.t, None)]
        return obs, refined

    @staticmethod
    def _iou(rendered: torch.Tensor, observed: torch.Tensor, has_view: torch.Tensor) -> torch.Tensor:
        """(P,) mean silhouette IoU over each fit's views that see the object (0 where none does)."""
        inter = (rendered & observed).flatten(2).sum(2).float()
        union = (rendered | observed).flatten(2).sum(2).float().clamp(min=1)
        views = has_view.float()
        return (inter / union * views).sum(1) / views.sum(1).clamp(min=1)

    def confidence(self, out, obs_mask, obs_depth, obs_known, view_weight) -> torch.Tensor:
        """(P,) silhouette IoU of renders `out` where the label is known and nothing stands in
        front of the rendered surface: a hand over the object hides it from the mask without
        the pose being wrong."""
        seen = (obs_known > 0.25) & (self._visible(out.depth.detach(), obs_depth, obs_mask) > 0.5)
        return self._iou(out.coverage & seen, (obs_mask > 0.5) & seen, view_weight > 0)

    # -- initialisation ----------------------------------------------------------------------
    def object_points(self, obs: Observation) -> np.ndarray:
        """World points of the object masks of all views, (N, 3)."""
        clouds = []
        for c in map(int, np.flatnonzero(obs.has_view)):  # within the mask's bounds: the same points, same order
            bounds = obs.mask_box(c)
            if bounds is None:
                continue
            (x0, y0), (x1, y1) = bounds
            box = np.s_[y0:y1 + 1, x0:x1 + 1]
            clouds.append(self._points(c, obs.depth[c][box] * (obs.mask[c][box] > 0.5), x0, y0))
        return np.concatenate(clouds) if clouds else np.zeros((0, 3))

    def registration_hypotheses(self, points: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Candidate object->world poses (R, t) registering the mesh to observed points: PCA alignments with
        every proper axis flip, and FPFH RANSAC global registrations, each refined by ICP; the
        `init_keep` distinct best (ICP fitness), and the best one's quarter turns, refined again.
        Open3D runs single-threaded here: its RANSAC's threads draw their samples in whatever order
        the scheduler gives them, so a run could not be repeated (Open3D issue 7475)."""
        with open3d_threads(1):
            return self._registration_hypotheses(points)

    def _registration_hypotheses(self, points: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        cfg = self.cfg
        voxel = self._voxel()
        scene = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
        scene, _ = scene.remove_statistical_outlier(20, 2.0)
        if len(scene.points) < 30:
            return []
        if len(scene.points) > cfg.init_max_points:  # ICP's cost is per scene point
            scene = scene.uniform_down_sample(int(np.ceil(len(scene.points) / cfg.init_max_points)))
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
        # Rank by how much of the scene lies on the model surface, then by residual.
        refined = sorted((self._icp(scene, R, centre, voxel) for R, centre in starts), key=lambda r: (round(r[0], 2), r[1]))
        kept = distinct([(R, centre) for _, _, R, centre in refined], 2 * voxel)[: cfg.init_keep]
        # Part of a cylinder registers with its axis sideways about as well as upright, and a chair's
        # seat and legs fit every quarter turn: the best one's turns, registered again, join in.
        _, _, R, centre = refined[0]
        turned = [self._icp(scene, R @ S, centre, voxel, fine_only=True) for S in self.turns]
        kept += distinct([(R, c) for _, _, R, c in turned], 2 * voxel, kept)
        return [(R, self._from_centre(R, centre)) for R, centre in kept]

    def _icp(self, scene, R, centre, voxel: float, fine_only: bool = False):
        """ICP (point-to-plane) of the observed points onto the model from pose (R, centre):
        (-fitness, inlier rmse, R, centre)."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R.T, -R.T @ centre  # scene -> centred model
        for dist in (voxel * 4, voxel * 2) if fine_only else (voxel * 12, voxel * 4, voxel * 2):
            result = reg.registration_icp(scene, self.model_cloud, dist, T, reg.TransformationEstimationPointToPlane())
            T = result.transformation
        Rw = T[:3, :3].T
        return -result.fitness, result.inlier_rmse, Rw, -Rw @ T[:3, 3]

    def _voxel(self) -> float:
        """Registration voxel (m): `voxel_size_m`, coarser for large objects (a chair seen by four
        cameras gives ~15k points; ICP's cost grows with them, its accuracy does not)."""
        return max(self.cfg.voxel_size_m, self.extent * self.cfg.voxel_fraction)

    def _global_registrations(self, scene) -> list[tuple[np.ndarray, np.ndarray]]:
        cfg = self.cfg
        voxel = self._voxel() * 2
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

    def refit(self, obs: Observation, fit: Fit, predicted):
        """Search, returns a Fit: local recovery before registration. The predicted pose and the
        fit's, each turned by 90/180/270 deg about every principal axis of the mesh (a chair's seat
        and legs look alike every 90 deg, only the backrest tells; a wrong turn drags the fit off
        the object's place, hence the prediction's turns), and the two lowest-E_O of them fitted
        with the full iteration budget."""
        starts = self.turned(*predicted) + self.turned(fit.R, fit.t)
        scored = sorted((yield [(obs, R, t, 0) for R, t in starts]), key=lambda f: f.energy)
        return min((yield [(obs, f.R, f.t, self.cfg.iterations) for f in scored[:2]]), key=lambda f: f.energy)

    def turned(self, R, t) -> list[tuple[np.ndarray, np.ndarray]]:
        """Pose (R, t) turned about its centre by 90/180/270 deg about each principal axis of the mesh."""
        centre = self._to_centre(R, t)
        return [(R @ S, self._from_centre(R @ S, centre)) for S in self.turns]

    def initialise(self, obs: Observation, extra: list | None = None):
        """Search, returns a Fit or None: the best of the registration hypotheses (plus `extra`
        poses): the few with the lowest E_O get a short fit, the best of those the full one."""
        hypotheses = list(extra or []) + self.registration_hypotheses(self.object_points(obs))
        if not hypotheses:
            return None
        scored = sorted((yield [(obs, R, t, 0) for R, t in hypotheses]), key=lambda f: f.energy)
        best = min((yield [(obs, f.R, f.t, self.cfg.init_iterations) for f in scored[: self.cfg.init_refine]]),
                   key=lambda f: f.energy)
        (fit,) = yield [(obs, best.R, best.t, None)]
        return fit


class FixedShapeFits:
    """The object fits of P poses at once in fixed shapes (`ObjectTracker.fixed_shapes`): input
    tensors that each `fit_many` call copies into, and one Adam step (of the rows `moving`, along
    the last evaluation's gradients) followed by one evaluation of E_O, its gradients, the
    confidence and the render's counts, recorded on them (`optim.recorded`: on CUDA one graph,
    recorded once and replayed by every later call). The render's capacity is sized from the
    first poses and grows when a pose outgrows it (the graph is then recorded again)."""

    def __init__(self, tracker: ObjectTracker, P: int):
        self.tracker, self.P, self.capacity, self._evaluate = tracker, P, None, None
        C, n, dev = len(tracker.sizes), tracker.cfg.crop_size, tracker.device
        self.inputs = [torch.zeros(P, C, n, n, device=dev) for _ in range(3)]  # mask, depth, known windows
        self.inputs += [torch.zeros(P, C, device=dev), torch.zeros(P, C, 4, device=dev)]  # view weights, crops
        self.r6 = torch.zeros(P, 6, device=dev, requires_grad=True)
        self.t_c = torch.zeros(P, 3, device=dev, requires_grad=True)
        self.adam = optim.AdamRows([self.r6, self.t_c], [tracker.cfg.lr_rotation, tracker.cfg.lr_translation], P)
        self.moving = torch.zeros(P, dtype=torch.bool, device=dev)
        self.grads = [torch.zeros_like(self.r6), torch.zeros_like(self.t_c)]
        self.values = torch.zeros(2 * P + 4, device=dev)

    @torch.no_grad()
    def load(self, *values) -> None:
        """Copy a call's windows, view weights, crops and starting poses into the recorded tensors;
        Adam starts afresh."""
        for target, value in zip(self.inputs + [self.r6, self.t_c], values):
            target.copy_(value)
        self.adam.reset()

    def _terms(self, capacity: Capacity | None):
        """`ObjectTracker.energy_terms` of the current poses on the recorded inputs."""
        obs_mask, obs_depth, obs_known, view_weight, crops = self.inputs
        return self.tracker.energy_terms(obs_mask, obs_depth, obs_known, view_weight, rotation_6d_to_matrix(self.r6),
                                         self.t_c, crops, capacity)

    def _outputs(self) -> torch.Tensor:
        """E_O (P,), confidence (P,) and the render's counts (4,), one tensor to read back."""
        total, _, _, out = self._terms(self.capacity)
        confidence = self.tracker.confidence(out, *self.inputs[:4])
        return torch.cat([total, confidence.to(total.dtype), out.needed.to(total.dtype)])

    def _step_and_evaluate(self) -> None:
        """The recorded work: Adam's step of the rows `moving`, then E_O and the rest at the new poses."""
        self.adam.step(self.moving, self.grads)
        values, grads = optim.energy_and_gradients([self.r6, self.t_c], self._outputs)
        self.values.copy_(values)
        for buffer, grad in zip(self.grads, grads):
            buffer.copy_(grad)

    def evaluate(self, stepping: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(E_O (P,), confidence (P,)) after a step of the rows `stepping` (P,) bool along the last
        evaluation's gradients (the step is taken once, also when the render is sized again)."""
        P = self.P
        self.moving.copy_(torch.from_numpy(stepping))
        while True:
            if self._evaluate is None:
                with torch.no_grad():  # room for the current poses' render (and never less than before)
                    fitting = Capacity.fitting(self._terms(None)[3].needed)
                self.capacity = fitting if self.capacity is None else Capacity(
                    *np.maximum(dataclasses.astuple(fitting), dataclasses.astuple(self.capacity)).tolist())
                self._evaluate = optim.recorded(self._step_and_evaluate, True, self.r6.device)
            self._evaluate()
            values = self.values.cpu().numpy()
            if self.capacity.holds(values[2 * P:]):
                return values[:P], values[P:2 * P]
            self.moving.zero_()  # a pose outgrew the shapes: size them again, evaluate again (not stepping)
            self._evaluate = None


def run_searches(tracker: ObjectTracker, searches: list) -> list:
    """Runs searches (generators of fit requests, sent their fits back) in lockstep: each round,
    the pending requests of all of them in one `fit_many`. Returns their results in order."""

    def serve(requests: list[list]) -> list[list[Fit]]:
        fits = tracker.fit_many([request for mine in requests for request in mine])
        bounds = np.cumsum([0] + [len(mine) for mine in requests])
        return [fits[a:b] for a, b in zip(bounds[:-1], bounds[1:])]

    return lockstep(searches, serve)


TRACKED, REINITIALISED, LOST, UNTRUSTED = 1, 2, 3, 4
STATUS_NAMES = {0: "pending", TRACKED: "tracked", REINITIALISED: "reinitialised", LOST: "lost", UNTRUSTED: "untrusted"}
FEW_TRUSTED = 0.5  # the run warns when the object is trusted in fewer than this share of frames


def untracked(T: int) -> dict[str, np.ndarray]:
    """`track_steps`'s state of T frames not yet tracked (status 0, pending)."""
    return {"R": np.full((T, 3, 3), np.nan), "t": np.full((T, 3), np.nan), "confidence": np.zeros(T),
            "status": np.zeros(T, np.int64), "energy": np.full(T, np.nan), "confirmed": np.zeros(T, bool)}


def spin_prediction(history: list, max_deg_per_frame: float):
    """The constant-velocity rotation for the next frame (`predict_pose`) when the last two frames
    were trusted and turned at most `max_deg_per_frame` between them (a spin), else None: a jump
    let through as a turn back (`fast_turn_energy_ratio`) is not a rate to carry on (seed 85: an
    88-degree jump, extrapolated, let a wrong fit in and the cup was tracked upside down)."""
    if len(history) < 2 or history[-1] is None or history[-2] is None:
        return None
    if max_deg_per_frame > 0 and float(rotation_angle_deg(history[-1][0], history[-2][0])) > max_deg_per_frame:
        return None
    return predict_pose(history)[0]


def turned_too_fast(R, R_last, frames: int, max_deg_per_frame: float, R_predicted=None) -> bool:
    """A fit turned further from the last trusted rotation than `max_deg_per_frame` per frame since
    (0: no limit), and, given the constant-velocity prediction `R_predicted` for this frame, also
    further than `max_deg_per_frame` from that. One view of a cup at the mouth changes its
    silhouette little as it tilts toward or from the camera: fits a good E_O trusts jumped 52-88
    degrees in a frame while the cup turned at most 6 (BENCHMARKS, stop 42); such a fit is better
    left to the global stage's smoothing. A spinning toss the tracker caught up with after lagging
    turns fast from the last pose but not from the spin's prediction (stop 44).
    `track_steps` still trusts one whose E_O is well below the recent level: a turn back onto the
    object after frames tracked wrong (2 views: 0.63 of the level, against 1.0-1.6 for the jumps)."""
    if max_deg_per_frame <= 0 or float(rotation_angle_deg(R, R_last)) <= max_deg_per_frame * frames:
        return False
    return R_predicted is None or float(rotation_angle_deg(R, R_predicted)) > max_deg_per_frame


def track_steps(tracker: ObjectTracker, frame_ids: np.ndarray, checkpoint: Path | None = None, initial_pose=None,
                queue=None, until=None):
    """Search (see `run_searches`): track the object through `frame_ids`; resumes from
    `checkpoint` when it exists; with `until(i, state)`, stops after the first frame i where it
    holds (later frames stay pending, status 0).

    Per frame: fit from the constant-velocity prediction (or, for up to
    `coast_frames` after the last trusted frame, from that frame's pose). A fit
    whose silhouette IoU is below `min_confidence` or whose E_O is above
    `reinit_energy_ratio` times its recent level is searched again, locally
    (`ObjectTracker.refit`, ~0.5 s) and, if that fails too, from registration
    hypotheses (`initialise`, seconds); the lowest E_O wins. Its pose is trusted
    when the IoU is enough, E_O at most `trust_energy_ratio` times the level and
    it turned no faster than `max_turn_deg_per_frame` from the last trusted pose or from the
    constant-velocity prediction (unless E_O is under `fast_turn_energy_ratio` times the level);
    other frames, and those where no view sees the object, are marked (NaN pose,
    confidence 0). With derived masks, nothing near the prediction sends the
    search over the whole foreground before the frame is called lost.

    Returns R (T,3,3), t (T,3) (NaN where untrusted), confidence (T,), status (T,),
    energy (T,) and confirmed (T,): a search found nothing better than the tracked
    pose, so its E_O is the new level (for the next 5 frames at least). With `queue`, each
    finished frame is put on it (`intercap.parallel`)."""
    cfg = tracker.cfg
    T = len(frame_ids)
    state = untracked(T)
    start = 0
    if checkpoint is not None and checkpoint.exists():
        saved = dict(np.load(checkpoint))
        if len(saved["status"]) == T:
            state = {k: saved[k] if k in saved else state[k] for k in state}
            start = int(saved["next"])
            log.info("object: resuming at frame %d of %d", start, T)
            if queue is not None:
                queue.put(start)
    history = [None if state["status"][i] not in (TRACKED, REINITIALISED) else (state["R"][i], state["t"][i])
               for i in range(start)]
    for i in range(start, T):
        frame_id = int(frame_ids[i])
        predicted, reach = predict_pose(history), 0.0
        if predicted is None and i == 0 and initial_pose is not None:
            predicted = initial_pose
        trusted_at = [k for k in range(max(0, i - cfg.coast_frames), i) if history[k] is not None]
        if trusted_at:
            k = trusted_at[-1]
            if predicted is None:
                predicted = history[k]  # coast: the object was seen recently, start where it was
            # How far the object may be from the prediction: its largest recent step, per frame since.
            steps = [np.linalg.norm(tracker._to_centre(*history[j]) - tracker._to_centre(*history[j - 1]))
                     for j in trusted_at[-5:] if j > 0 and history[j - 1] is not None]
            reach = max(steps, default=0.0) * (i - k)
        obs = tracker.observe(frame_id, predicted, reach)
        if i + 1 < T:
            tracker.read_ahead(int(frame_ids[i + 1]))  # read while this frame is fitted
        if predicted is not None and not tracker.use_masks and obs.visible_views < cfg.min_views:
            # Nothing near where the object should be: look for it anywhere before calling it lost.
            predicted = None
            obs = tracker.observe(frame_id, None)
        # E_O's level: the median over the last 5 frames with a fit (trusted or not: where the
        # object's visible part changes for good, say a cup put down out of the hand, a few
        # frames marked untrusted raise the level and tracking is trusted again).
        window = state["energy"][max(0, i - cfg.energy_window):i]
        recent = window[np.isfinite(window)][-5:]
        reference = float(np.median(recent)) if len(recent) > 2 else np.inf
        # A search in the last few frames that found nothing better than the tracked pose
        # confirmed a new level (a hand now covers part of the object): no new search for it.
        confirmed = state["energy"][max(0, i - 5):i][state["confirmed"][max(0, i - 5):i]]
        if len(confirmed):
            reference = max(reference, float(confirmed.max()))

        def good(f: Fit | None, ratio: float = cfg.reinit_energy_ratio) -> bool:
            """Silhouettes agree and E_O is not far above its level in recent trusted frames."""
            return f is not None and f.confidence >= cfg.min_confidence and f.energy <= ratio * reference

        fit, status = None, LOST
        if obs.visible_views >= cfg.min_views:
            if predicted is None:
                fit, status = (yield from tracker.initialise(obs)), REINITIALISED
            else:
                (fit,), status = (yield [(obs, *predicted, None)]), TRACKED
                if reach > cfg.near_margin_m and not tracker.use_masks:
                    # A mask cut this wide round the prediction takes in the hands and arms of a
                    # fast lift: cut it again round the fit and refine there, if that agrees.
                    tight_obs, tight = yield from tracker.recut(frame_id, fit)
                    if good(tight):
                        obs, fit = tight_obs, tight
                if not good(fit):
                    local = yield from tracker.refit(obs, fit, predicted)
                    if local.energy < fit.energy:
                        fit = local
                    if not good(fit):
                        alternative = yield from tracker.initialise(obs, extra=[predicted, (fit.R, fit.t)])
                        better = alternative is not None and alternative.energy <= cfg.confirm_ratio * fit.energy
                        state["confirmed"][i] = not better
                        if alternative is not None and alternative.energy < fit.energy:
                            fit, status = alternative, REINITIALISED
        pose = None
        if good(fit, cfg.trust_energy_ratio):  # a hand closing round the object raises E_O a little
            pose = (fit.R, fit.t)
            last_at = next((j for j in range(i - 1, -1, -1) if history[j] is not None), None)
            if last_at is not None and cfg.hold_symmetric_turn:
                pose = tracker.turned_like(*pose, history[last_at][0])
            if (last_at is not None
                    and turned_too_fast(pose[0], history[last_at][0], i - last_at, cfg.max_turn_deg_per_frame,
                                        spin_prediction(history, cfg.max_turn_deg_per_frame))
                    and fit.energy > cfg.fast_turn_energy_ratio * reference):
                pose = None  # unless it fits clearly better than the frames before: a turn back
        if fit is not None:
            state["energy"][i] = fit.energy
            state["confidence"][i] = fit.confidence if pose is not None else 0.0
        if pose is not None:
            state["R"][i], state["t"][i] = pose
            state["status"][i] = status
        else:
            state["status"][i] = UNTRUSTED if fit is not None else LOST
        history.append(pose)
        done = until is not None and until(i, state)
        if checkpoint is not None and ((i + 1) % cfg.checkpoint_every == 0 or i + 1 == T or done):
            save_npz(checkpoint, next=i + 1, **state)
        if queue is not None:
            queue.put(1)
        if done:
            break
    return state


def join_seams(tracker: ObjectTracker, frame_ids: np.ndarray, state: dict, starts: list[int],
               stage_dir: Path) -> tuple[dict, int]:
    """Track on across the chunks' seams, as one process tracking the whole take would.

    A chunk after the first starts cold, from registration; where the object is in a hand and no
    mask separates them, that can lock onto the wrong thing for the whole chunk (a held-out cup,
    3 views without masks: 0.5-0.8 m off from the seam on, against under 50 mm tracked in one
    process). Each chunk start `lo` (in `starts`) is tracked again from the frames before it until
    `seam_agree_frames` frames in a row match the chunk's own poses (`seam_agree_mm` of ADD-S: a
    box's cold start may find it turned by its symmetry; a cold start that was right costs those
    few frames); from there the chunk's poses stand. A seam whose frames before it changed is
    tracked again, until none does; the seams of a round side by side. Each keeps a checkpoint
    named by the frames it starts from. Returns the state and the number of frames tracked again."""
    from scipy.spatial import cKDTree

    cfg = tracker.cfg
    before = max(cfg.energy_window, cfg.coast_frames, 5)  # what `track_steps` looks back on
    points = tracker.world_vertices_np(np.eye(3), np.zeros(3))
    points = points[np.linspace(0, len(points) - 1, min(len(points), 500)).astype(int)]

    def matches(a: tuple, b: tuple) -> bool:  # ADD-S of the posed points within seam_agree_mm
        posed_a, posed_b = points @ a[0].T + a[1], points @ b[0].T + b[1]
        return float(cKDTree(posed_a).query(posed_b)[0].mean()) <= cfg.seam_agree_mm / 1000

    ends = starts[1:] + [len(frame_ids)]
    chunk_state = {key: value.copy() for key, value in state.items()}
    seeded: dict[int, str] = {}
    retracked = 0
    while True:
        jobs = []
        for lo, hi in zip(starts, ends):
            a = max(0, lo - before)
            prefix = {key: state[key][a:lo] for key in sorted(state)}
            seed = hashlib.sha1(b"".join(np.ascontiguousarray(v).tobytes() for v in prefix.values())).hexdigest()[:12]
            if seeded.get(lo) == seed:
                continue
            seeded[lo] = seed
            checkpoint = stage_dir / f"seam_{lo:06d}_{seed}.npz"
            for stale in stage_dir.glob(f"seam_{lo:06d}_*.npz"):
                if stale != checkpoint:
                    stale.unlink()
            if not checkpoint.exists():
                pending = untracked(hi - lo)
                rows = {key: np.concatenate([prefix[key], pending[key]]) for key in prefix}
                save_npz(checkpoint, next=lo - a, **rows)

            def agrees(i: int, sub: dict, a=a, lo=lo) -> bool:
                if i - (lo - a) + 1 < cfg.seam_agree_frames:
                    return False
                rows = range(a + i - cfg.seam_agree_frames + 1, a + i + 1)
                trusted = (TRACKED, REINITIALISED)
                return all(sub["status"][r - a] in trusted and chunk_state["status"][r] in trusted
                           and matches((sub["R"][r - a], sub["t"][r - a]), (chunk_state["R"][r], chunk_state["t"][r]))
                           for r in rows)

            jobs.append((lo, hi, a, track_steps(tracker, frame_ids[a:hi], checkpoint, None, None, agrees)))
        if not jobs:
            return state, retracked
        log.info("object: tracking on across the seam(s) at frame(s) %s",
                 ", ".join(str(int(frame_ids[job[0]])) for job in jobs))
        for (lo, hi, a, _), sub in zip(jobs, run_searches(tracker, [job[3] for job in jobs])):
            tracked = lo + int(np.flatnonzero(sub["status"][lo - a:] != 0).max(initial=-1)) + 1
            log.info("object: tracked on across the seam at frame %d: %d frames (%s)", int(frame_ids[lo]),
                     tracked - lo, "then the chunk's own poses" if tracked < hi else "the whole chunk")
            retracked += tracked - lo
            for key in state:
                state[key][lo:tracked] = sub[key][lo - a:tracked - a]
                state[key][tracked:hi] = chunk_state[key][tracked:hi]


def track_chunks(session, cfg, out_dir: Path, chunks: tuple[Chunk, ...], queue) -> list[dict[str, np.ndarray]]:
    """`track_steps` over each chunk's frames [lo, hi), the chunks side by side (`run_searches`),
    in a worker (`intercap.parallel`): a chunk after the first starts without a prediction, from
    registration, as a lost object is found again. Each chunk keeps its own checkpoint."""
    from intercap.session.frame_cache import open_session

    session = open_session(session, out_dir)
    torch.manual_seed(cfg.object.seed)
    tracker = ObjectTracker(session, cfg.object, session.object.load_mesh(), device=cfg.run.device)
    searches = [track_steps(tracker, session.frame_ids[c.lo:c.hi],
                            Path(out_dir) / "object" / f"progress_{c.lo:06d}_{c.hi:06d}.npz",
                            session.object.initial_pose if c.lo == 0 else None, queue) for c in chunks]
    return run_searches(tracker, searches)


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
    stage_dir = Path(out_dir) / "object"
    stage_dir.mkdir(parents=True, exist_ok=True)
    groups = chunk_groups(session.num_frames, cfg, ocfg)
    where = session if len(groups) == 1 else session.root  # workers load the session themselves
    parts = [part for group in run_chunks(track_chunks, groups, (where, cfg, out_dir), session.num_frames, "object",
                                          progress) for part in group]
    state = {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}
    tracker = ObjectTracker(session, ocfg, session.object.load_mesh(), device=cfg.run.device)
    starts = [chunk.lo for group in groups for chunk in group][1:]
    state, retracked = join_seams(tracker, session.frame_ids, state, starts, stage_dir) if starts else (state, 0)
    valid = np.isin(state["status"], (TRACKED, REINITIALISED))
    if ocfg.hold_symmetric_turn:  # across the seams too: each chunk began with its own turn
        state["R"], state["t"] = unwrap_symmetry(state["R"], state["t"], valid, *tracker.symmetry())
    save_npz(stage_dir / "object_poses.npz", R=state["R"], t=state["t"], confidence=state["confidence"],
             valid=valid, status=state["status"], frame_ids=session.frame_ids)
    publish(stage_dir / "object_poses.npz", Path(out_dir) / "object_poses.npz")
    for i in range(0, session.num_frames, max(1, ocfg.overlay_every)):
        draw_overlay(session, tracker, int(session.frame_ids[i]), state["R"][i], state["t"][i],
                     stage_dir / "overlays" / f"{int(session.frame_ids[i]):06d}.jpg")
    counts = {STATUS_NAMES[s]: int((state["status"] == s).sum()) for s in (TRACKED, REINITIALISED, LOST, UNTRUSTED)}
    images = session.num_cameras * session.num_frames
    derived = int(session.missing("mask_object").sum()) if tracker.session_masks else images
    if valid.mean() < FEW_TRUSTED:
        log.warning("object: the object was trusted in %s%s", f"only {int(valid.sum())} of {len(valid)} frames"
                    if valid.any() else "no frame", (
                        ": its masks were derived from depth, where an object that stays in place (or a person"
                        " who does, holding it) is part of the background, and one lying flat (a board on the"
                        " floor) hardly stands out of it; give the session object masks" if derived else
                        ": check its masks and object.ply (OUT/object/overlays/)"))
    return {
        "masks": "session" if derived == 0 else ("derived" if derived == images else "session+derived"),
        "masks_derived_images": derived,
        "frames_trusted": int(valid.sum()),
        **{f"frames_{k}": v for k, v in counts.items()},
        "mean_confidence": float(state["confidence"][valid].mean()) if valid.any() else 0.0,
        "seams": len(starts),
        "seam_frames_tracked_again": retracked,
    }
