"""What the data gives the object fit: per frame and view, the object's mask, the depth map and
where the mask's label is known (`Observation`), read from the session or derived from depth
(`ObservationReader`), and cut to the windows the fit renders (`crop_windows`).

Masks come from the session, or are derived from depth: a background model per camera (the
person's pixels left out, beyond-range regions known as far), the foreground outside the person,
and of that the pixels whose 3D points lie near the predicted pose (render-compare-and-preserve in
3D); pixels without depth or barely in front of the background are unknown, not background.
"""
from __future__ import annotations

import dataclasses
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from intercap.geometry.cameras import Cameras, pixel_rays, project, world_to_camera
from intercap.geometry.rendering import crop_observation
from intercap.geometry.segmentation import (
    ColourLikelihood,
    background_depth,
    clean_mask,
    components,
    fill_missing,
    foreground_mask,
    person_from_keypoints,
    uncertain_mask,
)
from intercap.session.session import in_threads


WRIST_ELBOW = ((4, 3), (7, 6))  # BODY_25 wrist and elbow of the right and the left arm
BODY_JOINTS = 25  # a keypoint row's BODY_25 part (its hands and face follow)


@dataclass
class Observation:
    """One frame's inputs for the object: (C, H, W) arrays per view."""

    mask: np.ndarray  # float32 in [0, 1]
    depth: np.ndarray  # float32 metres, 0 = missing
    has_view: np.ndarray  # (C,) bool: depth present and an object mask found
    known: np.ndarray  # float32, 1 where the mask's label is known (derived masks know nothing where depth is missing)
    # `mask_box`'s, by view
    _boxes: dict = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)

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

    Same values as cropping the full images, but only a window around each crop is copied and
    integrated (the integral image of whole views is a large share of a frame's time); pixels
    outside the image still read 0."""
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


class ObservationReader:
    """Reads one rigid object's `Observation`s from a session: the session's masks where it has
    them, else masks derived from depth round a predicted pose (`derived_mask`). It knows the
    mesh's size (centroid, extent, bounding-sphere radius), which the derived masks need;
    `ObjectTracker` (`intercap.stages.object.fitter`) is one."""

    def __init__(self, session, cfg, mesh, device: str = "cpu"):
        self.session, self.cfg, self.device = session, cfg, torch.device(device)
        self.cameras = Cameras.from_infos(session.cameras, device=device, dtype=torch.float32)
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.centroid = vertices.mean(0)
        self.extent = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        # the bounding sphere's radius about the centroid
        self.radius = float(np.linalg.norm(vertices - self.centroid, axis=1).max())
        # surface samples about the centroid (with their faces), and a tree of them for `near_surface`
        samples, self.sample_faces = trimesh.sample.sample_surface(mesh, 4000, seed=cfg.seed)
        self.surface_samples = np.asarray(samples, np.float64) - self.centroid
        self._surface_tree = cKDTree(self.surface_samples)
        self.sizes = [(c.height, c.width) for c in session.cameras]
        self.session_masks = cfg.use_session_masks  # the session's mask where a view and frame has one ...
        self.use_masks = cfg.use_session_masks and not session.missing("mask_object").any()  # ... or everywhere
        self._reader, self._ahead = None, {}  # `read_ahead`'s thread and its observations, by frame
        self.backgrounds = None
        self._lock = threading.Lock()
        self._rays: dict[int, torch.Tensor] = {}
        self._joints: dict[int, np.ndarray] = {}  # `person_joints`, by frame
        self._colours: ColourLikelihood | None | bool = False  # `colour_test` (False: not learnt yet)
        self._colour_lock = threading.Lock()
        self._colour_images: dict[tuple[int, int], np.ndarray | None] = {}  # `colour_image`: the latest frames'
        self.keypoints = None  # a `KeypointSource` (the run's detections): keeps the person out of a search

    def person_hint(self, c: int, frame_id: int, depth: np.ndarray, hidden_joints: bool = False) -> np.ndarray | None:
        """View c's person pixels drawn from its 2D keypoints (`person_from_keypoints`) where the session has no
        person mask; None without keypoints. `hidden_joints`: a keypoint hidden behind something takes its joint's
        depth triangulated from all views (knees behind a table top: a box on the table is not the person)."""
        keypoints = None if self.keypoints is None else self.keypoints.read(c, frame_id)
        if keypoints is None:
            return None
        focal = float(self.cameras.K[c, 0, 0])
        joint_depth = None
        if hidden_joints:  # NaN where a joint is not triangulated
            joints = torch.as_tensor(self.person_joints(frame_id), dtype=torch.float64)
            to_camera = self.cameras.T_cam_from_world[c:c + 1].double().cpu()
            joint_depth = world_to_camera(joints, to_camera)[0, :, 2].numpy()
        return person_from_keypoints(keypoints, depth, focal, self.cfg.person_keypoint_confidence,
                                     joint_depth_m=joint_depth)

    def person_joints(self, frame_id: int) -> np.ndarray:
        """World points (25, 3) of the person's BODY_25 joints in a frame, NaN where not found (all
        without keypoints): each triangulated from the views' keypoints of at least
        `person_keypoint_confidence`."""
        from intercap.stages.body.observations import triangulate

        if self.keypoints is None:
            return np.full((BODY_JOINTS, 3), np.nan)
        with self._lock:
            if frame_id in self._joints:
                return self._joints[frame_id]
        rows = np.zeros((len(self.sizes), BODY_JOINTS, 3), np.float32)
        for c in range(len(self.sizes)):
            row = self.keypoints.read(c, frame_id)
            if row is not None:
                rows[c] = row[:BODY_JOINTS]
        rows[..., 2] *= rows[..., 2] >= self.cfg.person_keypoint_confidence
        points, ok = triangulate(torch.from_numpy(rows)[None].to(self.cameras.K.device), self.cameras)
        points = points[0].cpu().double().numpy()
        points[~ok[0].cpu().numpy()] = np.nan
        with self._lock:
            if len(self._joints) > 64:
                self._joints.clear()
            self._joints[frame_id] = points
        return points

    def palms(self, frame_id: int) -> np.ndarray:
        """World points (n, 3) of the person's palms in a frame (none without keypoints): each wrist
        (`person_joints`) moved on along the forearm (elbow to wrist) by a third of it where the
        elbow is found too."""
        joints = self.person_joints(frame_id)
        palms = [joints[w] + (joints[w] - joints[e]) / 3 if np.isfinite(joints[e]).all() else joints[w]
                 for w, e in WRIST_ELBOW if np.isfinite(joints[w]).all()]
        return np.array(palms).reshape(-1, 3)

    def hand_pixels(self, c: int, frame_id: int, depth: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """(H, W) bool: of view c's `pixels`, those whose 3D points lie within `object.hand_radius_m`
        of a palm (`palms`)."""
        out = np.zeros_like(pixels)
        palms = self.palms(frame_id) if self.cfg.hand_radius_m > 0 else np.zeros((0, 3))
        if not len(palms):
            return out
        ys, xs = np.nonzero(pixels & (depth > 0))
        points = self._pixel_points(c, ys, xs, depth[ys, xs])
        near = (np.linalg.norm(points[:, None] - palms[None], axis=2) < self.cfg.hand_radius_m).any(1)
        out[ys[near], xs[near]] = True
        return out

    def colour_test(self) -> ColourLikelihood | None:
        """The object's colours against the hands' (`ColourLikelihood`), learnt once from
        `object.colour_frames` frames spread over the take, without poses: the object's samples from
        the likeliest place of its size (`candidate_places`) in frames where no joint of the person is near it, the
        hands' from the foreground round the palms away from every such place. None where either has
        too few samples, or where less than `colour_min_separable` of the object's colours pass
        `colour_ratio` (an object the colour of skin: its pixels near a hand stay unknown)."""
        with self._colour_lock:  # the views' threads wait for the one that learns it
            if self._colours is False:
                self._colours = self._learn_colours()
            return self._colours

    def _learn_colours(self) -> ColourLikelihood | None:
        """`colour_test`'s learning."""
        from intercap.stages.prepare.stage import spread_frames

        cfg, found, hands = self.cfg, [], []
        frames = [] if cfg.colour_frames <= 0 or cfg.hand_radius_m <= 0 or self.keypoints is None else \
            spread_frames(self.session.frame_ids, cfg.colour_frames)
        for frame_id in map(int, frames):
            palms, joints = self.palms(frame_id), self.person_joints(frame_id)
            if not len(palms):
                continue
            places, joints = self.candidate_places(frame_id), joints[np.isfinite(joints).all(1)]
            # a place of the object's size away from every joint (not the crown, not a hand)
            free = [p for p in places if np.linalg.norm(joints - p, axis=1).min() > self.radius + cfg.hand_radius_m]
            for c in range(len(self.sizes)):
                depth, colour = self.session.read_depth(c, frame_id), self.colour_image(c, frame_id)
                if depth is None or colour is None:
                    continue
                foreground = foreground_mask(depth, self._background()[c])
                ys, xs = np.nonzero(foreground & (depth > 0))
                points = self._pixel_points(c, ys, xs, depth[ys, xs])
                if free:  # the likeliest free place alone: a second one may be a part of the person
                    on = np.linalg.norm(points - free[0], axis=1) < self.radius
                    person = self.person_hint(c, frame_id, depth)
                    if person is not None:
                        on &= ~person[ys, xs].astype(bool)
                    found.append(colour[ys[on], xs[on]])
                near_hand = (np.linalg.norm(points[:, None] - palms[None], axis=2) < cfg.hand_radius_m).any(1)
                for p in places:
                    near_hand &= np.linalg.norm(points - p, axis=1) > self.radius + cfg.near_margin_m
                hands.append(colour[ys[near_hand], xs[near_hand]])
        test = None
        found, hands = (np.concatenate(s) if s else np.zeros((0, 3)) for s in (found, hands))
        if min(len(found), len(hands)) >= 4 * cfg.min_mask_px:
            test = ColourLikelihood(found, hands)
            if test.separable(cfg.colour_ratio) < cfg.colour_min_separable:
                test = None
        return test

    def colour_image(self, c: int, frame_id: int) -> np.ndarray | None:
        """View c's colour image of `frame_id`, kept for the two latest frames: a frame is observed
        more than once (a recut, a search), and each time near a hand."""
        key = (c, frame_id)
        with self._lock:
            if key in self._colour_images:
                return self._colour_images[key]
        image = self.session.read_color(c, frame_id)
        with self._lock:
            while len(self._colour_images) >= 2 * len(self.sizes):
                self._colour_images.pop(next(iter(self._colour_images)))
            self._colour_images[key] = image
        return image

    def object_coloured(self, c: int, frame_id: int, pixels: np.ndarray) -> np.ndarray:
        """(H, W) bool: of view c's `pixels`, those whose colour is at least `colour_ratio` times
        likelier the object's than a hand's (`colour_test`; none without one)."""
        test = self.colour_test() if pixels.any() else None
        colour = None if test is None else self.colour_image(c, frame_id)
        out = np.zeros_like(pixels)
        if colour is None:
            return out
        ys, xs = np.nonzero(pixels)
        keep = test.ratio(colour[ys, xs]) > self.cfg.colour_ratio
        out[ys[keep], xs[keep]] = True
        return out

    def near_surface(self, points: np.ndarray, R, t, within: float) -> np.ndarray:
        """(N,) bool: world `points` within `within` (m) of the mesh's surface under pose (R, t)."""
        local = (points - self.to_centre(R, t)) @ np.asarray(R)  # world -> centred object coordinates
        return self._surface_tree.query(local, distance_upper_bound=within)[0] < within

    def to_centre(self, R, t) -> np.ndarray:
        """The mesh centroid's world position under object->world pose (R, t)."""
        return np.asarray(R) @ self.centroid + np.asarray(t)

    def from_centre(self, R, t_c) -> np.ndarray:
        """The translation that puts the mesh centroid at `t_c` under rotation R."""
        return np.asarray(t_c) - np.asarray(R) @ self.centroid

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
        cores, and reading ahead there is slower."""
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
        than predicted. Where the reach is under the sphere's radius (the predicted turn
        means something), the point must also lie within that margin and reach of the
        posed surface: a long tool's sphere takes in the arm and body that hold it, its
        surface the hand alone. A reach of the radius or more is a place, its turn unknown:
        the person is left out there as in a search. Without a prediction, the component
        whose 3D extent best matches the
        object's. Pixels only slightly in front of the background (a chair's feet on the
        floor, a box's bottom edge) are neither object nor background: unknown."""
        place = predicted is not None and reach_m >= self.radius  # where the object may be, its turn unknown
        candidates, known, gap = self._candidates(c, frame_id, depth, predicted is None or place)
        if predicted is not None:
            R, t = predicted
            centre = self.to_centre(R, t)
            ys, xs = np.nonzero(candidates & (depth > 0))
            points = self._pixel_points(c, ys, xs, depth[ys, xs])
            near = np.linalg.norm(points - centre, axis=1) < self.radius + self.cfg.near_margin_m + reach_m
            if not place and near.any():
                near[near] = self.near_surface(points[near], R, t, self.cfg.near_margin_m + reach_m)
            mask = np.zeros_like(candidates)
            mask[ys[near], xs[near]] = True
            mask = fill_missing(mask, depth, gap) & candidates
            parts = components(mask, self.cfg.min_mask_px)  # drops specks the sphere cut off
            return (np.any(parts, axis=0) if parts else np.zeros_like(mask)), known
        sized = self._sized_parts(c, depth, candidates, gap)
        return (min(sized, key=lambda part: part[1])[0] if sized else np.zeros_like(candidates)), known

    def _candidates(self, c: int, frame_id: int, depth: np.ndarray, search: bool):
        """View c's object candidates (the depth foreground outside the person, (H, W) bool), its
        known labels (H, W) bool and the gap its fragments are bridged over (pixels); `search`: a
        search over the whole view, where the person drawn from keypoints is left out too; else,
        without a person mask, the hands found from keypoints are left out and unknown (`hand_pixels`)."""
        background = self._background()[c]
        foreground = foreground_mask(depth, background)
        known = (depth > 0) & ~(uncertain_mask(depth, background) & ~foreground)
        person = self.session.read_mask(c, frame_id, "person")
        if person is None and search:  # a search over the whole view: not the person
            person = self.person_hint(c, frame_id, depth)
        elif person is None:  # round a pose: the hands are neither object nor background, ...
            person = self.hand_pixels(c, frame_id, depth, foreground)
            person &= ~self.object_coloured(c, frame_id, person)  # ... but for what has the object's colour
            known &= ~person
        gap = self._bridge_px(c)
        # Dropouts (a dark surface loses much of its depth, speckled) would let the opening
        # in `clean_mask` erase thin parts: fill them first where foreground surrounds them.
        foreground = fill_missing(foreground, depth, gap)
        return clean_mask(foreground & ~person if person is not None else foreground), known, gap

    def _sized_parts(self, c: int, depth: np.ndarray, candidates: np.ndarray, gap: int) -> list[tuple]:
        """The parts of view c's candidates no larger than the object could look: (mask, size score,
        median world point) each; the score is |log| of the part's 3D extent over 0.8 of the mesh's
        (the visible extent is a little under the full one), 0 for a perfect match."""
        parts = []
        for cand in components(candidates, self.cfg.min_mask_px, gap):
            ys, xs = np.nonzero(cand & (depth > 0))
            points = self._pixel_points(c, ys, xs, depth[ys, xs])
            if len(points) < 20:
                continue
            extent = np.linalg.norm(np.percentile(points, 95, 0) - np.percentile(points, 5, 0))
            if extent < 1.6 * self.extent:
                parts.append((cand, abs(np.log(extent / (0.8 * self.extent))), np.median(points, 0)))
        return parts

    def candidate_places(self, frame_id: int) -> list[np.ndarray]:
        """World points (3,) where the object may be in this frame, most likely first, at most
        `init_places`: each view's foreground parts of about the object's size (`_sized_parts`);
        parts of several views within the object's radius of one another are one place, ranked by
        how many views see it, then by how well its size matches. A part of a leg can match a box's
        size in one view; the box is seen by more."""
        found = []
        for c in range(len(self.sizes)):
            depth = self.session.read_depth(c, frame_id)
            if depth is not None:
                candidates, _, gap = self._candidates(c, frame_id, depth, True)
                found += [(score, c, centre) for _, score, centre in self._sized_parts(c, depth, candidates, gap)]
        places: list[list] = []  # [centre, views, best score]
        for score, c, centre in sorted(found, key=lambda part: part[0]):
            near = next((p for p in places if np.linalg.norm(p[0] - centre) < self.radius), None)
            if near is None:
                places.append([centre, {c}, score])
            else:
                near[1].add(c)
        places.sort(key=lambda p: (-len(p[1]), p[2]))
        return [p[0] for p in places[: self.cfg.init_places]]

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
