"""The object fit: a rigid mesh's pose (6D rotation + translation) minimising E_O
(`intercap.stages.object.terms`) over all views with the differentiable renderer of
`intercap.geometry.rendering`, by Adam; the step size shrinks once E_O stalls.

Every fit is a request that `ObjectTracker.fit_many` serves together with others: a search's
candidate poses, and on a GPU the current frames of several chunks of the take tracked side by
side (`object.side_by_side`). Each fit keeps its own Adam state and stopping, so it ends where it
would alone, at one render per step for all. The searches (`recut`, `refit`, `initialise`, the
stage's `track_steps`) are generators of fit requests, run side by side by `run_searches`.
Where the object may have moved far from the prediction (a fast lift), the derived mask cut round
it is wide and takes in the hands and arms that hold it: the mask is cut again round the fit, and
the fit refined on it (`ObjectTracker.recut`).

Where no pose is given (the first frame without one in session.yaml, a chunk's cold start, an
object lost and searched for again), `ObjectTracker.initialise` registers the mesh to the frame's
object points: PCA alignments and FPFH RANSAC global registrations, each refined by ICP, plus the
best one's quarter turns about the mesh's principal axes, scored by E_O; the best few get a short
fit and the best of those the full one.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import torch
from scipy.spatial.transform import Rotation

from intercap.energies import optim
from intercap.energies.losses import matrix_to_rotation_6d, occlusion_weight, rotation_6d_to_matrix
from intercap.energies.terms import evaluate_terms
from intercap.geometry.cameras import project
from intercap.geometry.pointclouds import open3d_threads
from intercap.geometry.rendering import Capacity, MeshTopology, render
from intercap.geometry.symmetry import (axis_angle_matrix, equivalent_pose, mesh_symmetry,
                                        rotation_angle_deg, surface_moments)
from intercap.stages.chunks import lockstep
from intercap.stages.object import terms
from intercap.stages.object.observations import Observation, ObservationReader, crop_windows, hard_silhouettes

reg = o3d.pipelines.registration
# `locate`: a search's fit whose mask lies more than this share on the person is the person, and one whose
# silhouettes the masks show less than this share of is not the object
PERSON_SHARE, MIN_RECALL = 0.35, 0.1
o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # RANSAC's per-call warnings are noise here


@dataclass
class Fit:
    R: np.ndarray  # (3, 3) object -> world
    t: np.ndarray  # (3,)
    energy: float
    confidence: float  # mean silhouette IoU over views that see the object (pixels hidden by an occluder left out)


def predict_pose(history: list[tuple[np.ndarray, np.ndarray] | None], turn_share: float = 1.0):
    """Constant-velocity prediction from the last two trusted poses (or the last one), carrying on
    `turn_share` (0-1) of the last frame's turn."""
    known = [h for h in history[-2:] if h is not None]
    if not known:
        return None
    if len(known) == 1 or history[-1] is None or history[-2] is None:
        return known[-1]
    (R1, t1), (R2, t2) = history[-2], history[-1]
    turn = R2 @ R1.T
    if turn_share != 1.0:
        turn = Rotation.from_rotvec(turn_share * Rotation.from_matrix(turn).as_rotvec()).as_matrix()
    return turn @ R2, t2 + (t2 - t1)


def same_pose(a, b, distance_m: float, angle_deg: float = 10.0) -> bool:
    """Poses (R, t) within `distance_m` (translation) and `angle_deg` (rotation) of each other."""
    cos = (np.trace(np.asarray(a[0]).T @ np.asarray(b[0])) - 1) / 2
    return bool(np.linalg.norm(np.asarray(a[1]) - np.asarray(b[1])) < distance_m
                and cos > np.cos(np.radians(angle_deg)))


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


def signed_permutations() -> np.ndarray:
    """The 24 rotations (24, 3, 3) that map the coordinate axes onto each other (the cube's group),
    identity first."""
    out = []
    for perm in ([0, 1, 2], [1, 2, 0], [2, 0, 1], [1, 0, 2], [0, 2, 1], [2, 1, 0]):
        for signs in np.ndindex(2, 2, 2):
            M = np.zeros((3, 3))
            M[np.arange(3), perm] = 1 - 2 * np.asarray(signs)
            if np.linalg.det(M) > 0:
                out.append(M)
    return np.stack(out)


def looks_alike(S1: np.ndarray, S2: np.ndarray, symmetry, tolerance_deg: float = 5.0) -> bool:
    """Whether an object turned by S1 and one turned by S2 (object coordinates) look the same: S1^T S2
    is one of its symmetries (an element of the finite group, then any turn about a continuous axis)."""
    if len(symmetry.continuous_axes) >= 2:  # sphere-like
        return True
    D = S1.T @ S2
    for G in symmetry.rotations:
        rest = G.T @ D
        if symmetry.continuous_axes:
            a = np.asarray(symmetry.continuous_axes[0], np.float64)
            if float(a @ rest @ a) > np.cos(np.radians(tolerance_deg)):
                return True
        elif float(rotation_angle_deg(rest, np.eye(3))) < tolerance_deg:
            return True
    return False


def spin_prediction(history: list, max_deg_per_frame: float):
    """The constant-velocity rotation for the next frame (`predict_pose`) when the last two frames
    were trusted and turned at most `max_deg_per_frame` between them (a spin), else None: a jump
    let through as a turn back (`fast_turn_energy_ratio`) is not a rate to carry on (extrapolated,
    it lets a wrong fit in, and a cup is tracked upside down)."""
    if len(history) < 2 or history[-1] is None or history[-2] is None:
        return None
    if max_deg_per_frame > 0 and float(rotation_angle_deg(history[-1][0], history[-2][0])) > max_deg_per_frame:
        return None
    return predict_pose(history)[0]


def turned_too_fast(R, R_last, frames: int, max_deg_per_frame: float, R_predicted=None) -> bool:
    """A fit turned further from the last trusted rotation than `max_deg_per_frame` per frame since
    (0: no limit), and, given the constant-velocity prediction `R_predicted` for this frame, also
    further than `max_deg_per_frame` from that. One view of a cup at the mouth changes its
    silhouette little as it tilts toward or from the camera: fits a good E_O trusts can jump by
    tens of degrees in a frame while the cup hardly turned; such a fit is better left to the
    global stage's smoothing. A spinning toss the tracker caught up with after lagging turns fast
    from the last pose but not from the spin's prediction. `track_steps` still trusts one whose
    E_O is well below the recent level (`fast_turn_energy_ratio`): a turn back onto the object
    after frames tracked wrong."""
    if max_deg_per_frame <= 0 or float(rotation_angle_deg(R, R_last)) <= max_deg_per_frame * frames:
        return False
    return R_predicted is None or float(rotation_angle_deg(R, R_predicted)) > max_deg_per_frame


class ObjectTracker(ObservationReader):
    """Tracks one rigid mesh through a session: reads its observations (`ObservationReader`),
    fits its pose to them (`fit_many`) and searches for it where a fit fails (`recut`, `refit`,
    `initialise`)."""

    def __init__(self, session, cfg, mesh, device: str = "cpu"):
        super().__init__(session, cfg, mesh, device)
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        self.vertices_c = torch.as_tensor(vertices - self.centroid, dtype=torch.float32, device=device)  # centred
        self.topology = MeshTopology.from_faces(torch.as_tensor(self.faces, device=device))
        self.model_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.surface_samples))
        self.model_cloud.normals = o3d.utility.Vector3dVector(np.asarray(mesh.face_normals)[self.sample_faces])
        _, _, axes = np.linalg.svd(self.surface_samples, full_matrices=False)
        self.turns = [axis_rotation(a, angle) for a in axes for angle in (90, 180, 270)]  # (3, 3) in object coords
        self._orientations = None  # `orientations`, found when first asked
        # renders of fixed shapes (`rendering.Capacity`), each fit step one replayed CUDA graph
        self.fixed_shapes = optim.records_graphs(self.device) and cfg.cuda_graphs
        self.fixed_fits: dict[int, FixedShapeFits] = {}  # by the number of poses fitted at once
        self._mesh, self._symmetry = mesh, None  # `symmetry`'s, found when first asked

    # -- pose helpers ---------------------------------------------------------------------
    def world_vertices_np(self, R, t) -> np.ndarray:
        """Vertices of the original mesh under object->world pose (R, t)."""
        return (self.vertices_c.double().cpu().numpy() + self.centroid) @ np.asarray(R).T + np.asarray(t)

    def symmetry(self):
        """The mesh's rotational symmetry and the centre its axes pass through (`mesh_symmetry`)."""
        if self._symmetry is None:
            self._symmetry = mesh_symmetry(self._mesh)
        return self._symmetry

    def turned_like(self, R, t, reference_R):
        """The pose that looks as (R, t) does (the object's symmetry) whose rotation is nearest `reference_R`."""
        found, centre = self.symmetry()
        return equivalent_pose(R, t, reference_R, found, centre) if found.is_symmetric else (R, t)

    def orientations(self) -> list[np.ndarray]:
        """The mesh's distinct axis-aligned orientations (object coordinates, identity first): the 24
        rotations that map its principal axes onto each other, less those its symmetry makes look
        alike (a box-like mesh: 6 of 24 remain; a cylinder's 3; a sphere's 1)."""
        if self._orientations is None:
            found, _ = self.symmetry()
            # exact principal axes (rows): the sampled surface's are a few degrees off a box's edges
            _, covariance = surface_moments(np.asarray(self._mesh.vertices, np.float64), self.faces)
            A = np.linalg.eigh(covariance)[1].T
            kept: list[np.ndarray] = []
            for P in signed_permutations():
                S = A.T @ P @ A
                if not any(looks_alike(k, S, found) for k in kept):
                    kept.append(S)
            self._orientations = kept
        return self._orientations

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
        """E_O of P poses, each against its own windows: (E_O (P,), the terms' values {name: (P,)} in
        the order of `terms.TERMS`, the render output). obs_* (P, C, h, w), view_weight (P, C),
        R (P, 3, 3), t_c (P, 3), crops (P, C, 4); capacity: the renderer's fixed shapes
        (`rendering.Capacity`) or None."""
        cfg = self.cfg
        out = render(self.vertices_c @ R.transpose(1, 2) + t_c[:, None], self.topology, self.cameras, crops,
                     size=(cfg.crop_size, cfg.crop_size), sigma=cfg.sigma_px, capacity=capacity)
        visible = self._visible(out.depth.detach(), obs_depth, obs_mask)  # (P, C, h, w)
        evaluation = terms.PoseEvaluation(render=out, obs_mask=obs_mask, obs_depth=obs_depth, obs_known=obs_known,
                                          visible=visible, view_weight=view_weight[:, :, None, None],
                                          depth_scale_m=cfg.depth_scale_m)
        values = evaluate_terms(terms.TERMS, evaluation)
        return terms.energy(values, cfg), values, out

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
        fits = PoseFits(self, requests)
        while not fits.done.all():
            fits.iterate()
        return fits.results()

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
        centre = self.to_centre(R, t)
        return [(R @ S, self.from_centre(R @ S, centre)) for S in self.turns]

    def orientation_search(self, obs: Observation, fit: "Fit"):
        """Search, returns (Fit, energies): `fit`'s pose turned into each of the mesh's `orientations`
        about its centre, scored by E_O; the `init_refine` lowest get a short fit, and where the best of
        those is another orientation than the fit's, the full one, which wins where its E_O is below
        `fit`'s. `energies`: each orientation's E_O after its short fit (infinity for those not
        fitted), in `orientations`' order. A box seen
        resting shows two or three sides; its quarter turn can fit them nearly as well as the truth,
        and a tracker started there keeps it."""
        centre = self.to_centre(fit.R, fit.t)
        starts = [(fit.R @ S, self.from_centre(fit.R @ S, centre)) for S in self.orientations()]
        scored = yield [(obs, R, t, 0) for R, t in starts]
        order = np.argsort([f.energy for f in scored], kind="stable")[: self.cfg.init_refine]
        short = yield [(obs, scored[k].R, scored[k].t, self.cfg.init_iterations) for k in order]
        energies = np.full(len(starts), np.inf)
        energies[order] = [f.energy for f in short]
        winner = int(np.argmin(energies))
        if winner == 0:  # the fit's own orientation: the fit stands as it is
            return fit, energies
        best = short[list(order).index(winner)]
        (final,) = yield [(obs, best.R, best.t, None)]
        return (final if final.energy < fit.energy else fit), energies

    # -- initialisation ----------------------------------------------------------------------
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
        refined = sorted((self._icp(scene, R, centre, voxel) for R, centre in starts),
                         key=lambda r: (round(r[0], 2), r[1]))
        kept = distinct([(R, centre) for _, _, R, centre in refined], 2 * voxel)[: cfg.init_keep]
        # Part of a cylinder registers with its axis sideways about as well as upright, and a chair's
        # seat and legs fit every quarter turn: the best one's turns, registered again, join in.
        _, _, R, centre = refined[0]
        turned = [self._icp(scene, R @ S, centre, voxel, fine_only=True) for S in self.turns]
        kept += distinct([(R, c) for _, _, R, c in turned], 2 * voxel, kept)
        return [(R, self.from_centre(R, centre)) for R, centre in kept]

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
        """Registration voxel (m): `voxel_size_m`, coarser for large objects (a large object seen by
        several cameras gives many points; ICP's cost grows with them, its accuracy does not)."""
        return max(self.cfg.voxel_size_m, self.extent * self.cfg.voxel_fraction)

    def _global_registrations(self, scene) -> list[tuple[np.ndarray, np.ndarray]]:
        cfg = self.cfg
        voxel = self._voxel() * 2
        feats = []
        for cloud in (self.model_cloud.voxel_down_sample(voxel), scene.voxel_down_sample(voxel)):
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 3, max_nn=30))
            search = o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 6, max_nn=100)
            features = reg.compute_fpfh_feature(cloud, search)
            feats.append((cloud, features))
        (model, fm), (sc, fs) = feats
        out = []
        for k in range(cfg.init_global_tries):
            o3d.utility.random.seed(cfg.seed + k)
            result = reg.registration_ransac_based_on_feature_matching(
                model, sc, fm, fs, True, voxel * 2, reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnDistance(voxel * 2)],
                reg.RANSACConvergenceCriteria(cfg.init_ransac_iterations, 0.999))
            T = result.transformation  # model -> scene
            out.append((T[:3, :3], T[:3, 3]))
        return out

    def locate(self, frame_id: int, places: int | None = None):
        """Search, returns (observation, Fit or None): the object found in a frame without a prediction
        or session masks. At each of its `candidate_places` the masks are cut round the place (with a
        reach of the mesh's radius: a place is where its visible part is) and the mesh registered
        there (`initialise`), then cut again round the fit (`recut`). A fit is left out where its mask
        lies mostly on the person drawn from keypoints (`on_person`: a forearm or a shin looks like a
        tool) or where the observation shows under `MIN_RECALL` of its silhouette as object
        (`silhouette_recall`: a tool fitted to a few pixels at a head's edge, the rest of it over
        pixels without depth, agrees with them as well as the tool does with itself). Of the
        others, the highest IoU x recall wins, then the lowest E_O. Without a place, the whole view's
        best-sized part (`initialise`), left out alike. `places`: how many places at most (default
        `init_places`)."""
        best_obs, best, best_score = self.observe(frame_id, None), None, None
        tried = False
        for centre in self.candidate_places(frame_id)[:places]:
            obs = self.observe(frame_id, (np.eye(3), self.from_centre(np.eye(3), centre)), reach_m=self.radius)
            if obs.visible_views < self.cfg.min_views:
                continue
            fit = yield from self.initialise(obs)
            if fit is None:
                continue
            tried = True
            tight_obs, tight = yield from self.recut(frame_id, fit)
            if tight is not None and tight.confidence >= fit.confidence:
                obs, fit = tight_obs, tight
            score = self.located_score(frame_id, obs, fit, tight_obs)
            if score is not None and (best_score is None or score > best_score):
                best_obs, best, best_score = obs, fit, score
        if best is None and not tried:
            fit = yield from self.initialise(best_obs)
            best = fit if fit is not None and self.located_score(frame_id, best_obs, fit) is not None else None
        return best_obs, best

    def located_score(self, frame_id: int, obs: Observation, fit: Fit,
                      around: Observation | None = None) -> tuple[float, float] | None:
        """`locate`'s ranking of a fit found by a search (IoU x recall, then -E_O), or None where it is
        left out: on the person (by the masks cut round it, `around`, the person not left out: a place's
        cut leaves the person out, and a tool on a shin looks alone there), or too little of its
        silhouette observed."""
        recall = self.silhouette_recall(obs, fit)
        if recall < MIN_RECALL or self.on_person(frame_id, around or obs) > PERSON_SHARE:
            return None
        return fit.confidence * recall, -fit.energy

    def silhouette_recall(self, obs: Observation, fit: Fit) -> float:
        """The share (0-1) of the posed mesh's silhouettes, over all views, that the observation's
        masks show as object."""
        silhouettes = hard_silhouettes(self.world_vertices_np(fit.R, fit.t), self.faces, self.cameras, self.sizes)
        shown = sum(int((sil & (obs.mask[c, :sil.shape[0], :sil.shape[1]] > 0.5)).sum())
                    for c, sil in enumerate(silhouettes))
        return shown / max(1, sum(int(sil.sum()) for sil in silhouettes))

    def on_person(self, frame_id: int, obs: Observation) -> float:
        """The share (0-1) of the observation's object pixels that lie on the person drawn from the
        run's keypoints (`person_hint`, hidden keypoints at their joints' depths: knees behind a table top would
        make a box on the table the person's; 0 where the session has person masks or there are no
        keypoints: the person is out of the masks already, or cannot be told)."""
        inside = total = 0
        for c in map(int, np.flatnonzero(obs.has_view)):
            h, w = self.sizes[c]
            if self.session.read_mask(c, frame_id, "person") is not None:
                continue
            person = self.person_hint(c, frame_id, obs.depth[c, :h, :w], hidden_joints=True)
            if person is not None:
                mask = obs.mask[c, :h, :w] > 0.5
                inside, total = inside + int((mask & person).sum()), total + int(mask.sum())
        return inside / total if total else 0.0

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


class PoseFits:
    """The P fits of one `ObjectTracker.fit_many` call: their windows, parameters (6D rotation and
    centroid position, (P, 6) and (P, 3)), Adam state, best poses and stopping, stepped together
    (`iterate`) until every fit is done."""

    def __init__(self, tracker: ObjectTracker, requests: list[tuple]):
        cfg = self.cfg = tracker.cfg
        self.tracker = tracker
        P, dev = self.P, self.dev = len(requests), tracker.device
        crops = tracker.crops_for([(obs, R0, t0) for obs, R0, t0, _ in requests])  # (P, C, 4)
        cut = [tracker.windows(obs, c) for (obs, *_), c in zip(requests, crops)]
        self.obs_mask, self.obs_depth, self.obs_known = (torch.stack(parts) for parts in zip(*cut))
        self.view_weight = torch.as_tensor(np.stack([obs.has_view for obs, *_ in requests]), dtype=torch.float32,
                                           device=dev)
        self.budget = np.array([cfg.iterations if it is None else it for *_, it in requests])
        R0 = torch.as_tensor(np.stack([np.asarray(R) for _, R, _, _ in requests]), dtype=torch.float32, device=dev)
        r6 = matrix_to_rotation_6d(R0).clone().requires_grad_(True)
        t_c = torch.as_tensor(np.stack([tracker.to_centre(R, t) for _, R, t, _ in requests]), dtype=torch.float32,
                              device=dev).clone().requires_grad_(True)
        self.crops = crops.to(dev)  # cut on the CPU (`windows`), rendered where the fit runs
        self.stalled, self.decays, self.used = np.zeros(P, int), np.zeros(P, int), np.zeros(P, int)
        self.done = self.budget <= self.used
        self.fixed = None
        if tracker.fixed_shapes and not self.done.all():
            if P not in tracker.fixed_fits:
                tracker.fixed_fits[P] = FixedShapeFits(tracker, P)
            self.fixed = tracker.fixed_fits[P]
            self.fixed.load(self.obs_mask, self.obs_depth, self.obs_known, self.view_weight, self.crops, r6, t_c)
            r6, t_c, self.adam = self.fixed.r6, self.fixed.t_c, self.fixed.adam
        else:
            self.adam = optim.AdamRows([r6, t_c], [cfg.lr_rotation, cfg.lr_translation], P)
        self.r6, self.t_c = r6, t_c
        self.stepping = np.zeros(P, bool)  # the rows whose step is taken before the next evaluation
        self.best_value, self.best_r6, self.best_t = np.full(P, np.inf), r6.detach().clone(), t_c.detach().clone()

    def energy(self, rows=None):
        """`energy_terms` of the fits `rows` (an index tensor; None: all), as (P,) tensors and the render."""
        pick = (lambda x: x) if rows is None else (lambda x: x.index_select(0, rows))
        return self.tracker.energy_terms(pick(self.obs_mask), pick(self.obs_depth), pick(self.obs_known),
                                         pick(self.view_weight), rotation_6d_to_matrix(pick(self.r6)),
                                         pick(self.t_c), pick(self.crops))

    def iterate(self) -> None:
        """One iteration of the fits not done: evaluate E_O, note the progress, take the steps."""
        live = np.flatnonzero(~self.done)
        if self.fixed is not None:  # the last iteration's step, then the evaluation
            values, total = self.fixed.evaluate(self.stepping)[0][live], None
        else:
            total = self.energy(None if len(live) == self.P else torch.as_tensor(live, device=self.dev))[0]
            values = total.detach().cpu().numpy()
        stop = self._note_progress(live, values)
        self._step(live, stop, total)
        self.used[live] += 1
        self.done |= self.used >= self.budget

    def _note_progress(self, live: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Keep each live fit's best pose; a fit with no relative improvement of `stop_tolerance` for
        `stop_patience` steps is circling the minimum at its step size: it goes back to its best
        pose with smaller steps, `lr_decays` times, then stops. Returns the live fits that stalled."""
        cfg, dev, r6, t_c = self.cfg, self.dev, self.r6, self.t_c
        self.stalled[live] = np.where(values > self.best_value[live] * (1 - cfg.stop_tolerance),
                                      self.stalled[live] + 1, 0)
        better = values < self.best_value[live]
        if better.any():
            self.best_value[live[better]] = values[better]
            at = torch.as_tensor(live[better], device=dev)
            self.best_r6[at], self.best_t[at] = r6.detach()[at], t_c.detach()[at]
        stop = self.stalled[live] >= cfg.stop_patience
        self.done[live[stop & (self.decays[live] == cfg.lr_decays)]] = True
        back = live[stop & (self.decays[live] < cfg.lr_decays)]
        if len(back):
            self.decays[back] += 1
            self.stalled[back] = 0
            at = torch.as_tensor(back, device=dev)
            with torch.no_grad():
                self.adam.scale[at] *= cfg.lr_decay
                r6[at], t_c[at] = self.best_r6[at], self.best_t[at]
        return stop

    def _step(self, live: np.ndarray, stop: np.ndarray, total) -> None:
        """Mark the live fits that did not stall as stepping; the eager path (`total` given) steps
        them now, along their gradients (in fixed shapes the next evaluation takes the step)."""
        self.stepping[:] = False
        self.stepping[live[~stop]] = True
        if total is not None and not stop.all():
            steps = total if not stop.any() else total[torch.as_tensor(np.flatnonzero(~stop), device=self.dev)]
            steps.sum().backward()
            self.adam.step(torch.as_tensor(self.stepping, device=self.dev), [self.r6.grad, self.t_c.grad])
            self.r6.grad = self.t_c.grad = None

    def final(self) -> tuple[np.ndarray, np.ndarray]:
        """(E_O (P,), confidence (P,)) at the current poses (after the last step)."""
        if self.fixed is not None:
            return self.fixed.evaluate(self.stepping)
        with torch.no_grad():
            total, _, out = self.energy()
            return total.cpu().numpy(), self.tracker.confidence(out, self.obs_mask, self.obs_depth, self.obs_known,
                                                                self.view_weight).cpu().numpy()

    def results(self) -> list[Fit]:
        """The fits at their final poses, or at the best pose seen where the last step went up."""
        total, confidence = self.final()
        worse = total > self.best_value
        if worse.any():
            at = torch.as_tensor(np.flatnonzero(worse), device=self.dev)
            with torch.no_grad():
                self.r6[at], self.t_c[at] = self.best_r6[at], self.best_t[at]
            self.stepping[:] = False
            total, confidence = self.final()
        with torch.no_grad():
            R = rotation_6d_to_matrix(self.r6).double().cpu().numpy()
            t_c = self.t_c.double().cpu().numpy()
        return [Fit(R=R[p], t=self.tracker.from_centre(R[p], t_c[p]), energy=float(total[p]),
                    confidence=float(confidence[p])) for p in range(self.P)]


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
        total, _, out = self._terms(self.capacity)
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
                    fitting = Capacity.fitting(self._terms(None)[2].needed)
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
