"""The body fit: `BodyFitter` runs the phases of `terms.PHASES` over a batch of frames (each frame its own
L-BFGS, batched as tensors, where the frames do not interact: `minimise_per_frame`), initialised per
frame by aligning a template's pose to the triangulated torso keypoints. E_D's data association
(`BodyFitter.correspondences`) sees through a coarse z-buffer of the mesh (`visible_vertices`);
self-penetration is approximated by spheres along the limbs and trunk (`BodySpheres`). A fit far
from its depth points, or contorted to reach them, is refitted from the evidence
(`refit_from_evidence`); the template is sized to the person (`size_template`, `stature`)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from intercap.body_models import BodyParams
from intercap.body_models.base import axis_angle_to_matrix, matrix_to_axis_angle
from intercap.body_models.keypoints import NUM_BODY, NUM_BODY_HANDS
from intercap.energies import losses, optim
from intercap.energies.optim import minimise, minimise_per_frame
from intercap.energies.terms import evaluate_terms, weighted_sum
from intercap.geometry.cameras import Cameras, project
from intercap.stages.body.observations import (
    ORIENT_KEYPOINTS,
    TORSO_KEYPOINTS,
    BodyObservations,
    lift_keypoints,
    shares_shape,
    triangulate,
)
from intercap.stages.body.terms import FINAL_TERMS, PHASES, TERMS, BodyEvaluation, Phase, in_table_order

SHAPE_EPS = 1e-3  # shape logits start at most this close to the ends of [0, 1]
# Bones the keypoints cannot see: they stay at rest.
FROZEN_BONE_PREFIXES = ("toe", "eye", "pelvis")


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
    face adds one contiguous row of B normals to each of its corners, faster than frame by frame."""
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
        """{name: (B,) unweighted value} of each of `terms` (`Term`s of `terms.TERMS`) that applies, in
        table order. `matches`: E_D's `DepthPairs` from `correspondences`, needed by the depth term;
        `rho`: E_J's robust scale (default cfg.keypoint_rho); `out`: the model's output for `params`
        whose first vertices are the fitting subsample, when the caller has it already; `rest`: the
        model's `rest_state` of the subsample while shape and expression do not move."""
        if out is None:
            out = self.model.sparse_forward(params, self.subset, rest)  # vertices: the fitting subsample only
        terms = in_table_order(terms)
        evaluation = BodyEvaluation(self, params, obs, out, terms, matches, rho or self.cfg.keypoint_rho)
        return evaluate_terms(terms, evaluation)

    def energy(self, values: dict) -> torch.Tensor:
        """The weighted sum of `energy_terms`' values (per frame), in table order."""
        return weighted_sum(TERMS, values, {"": self.cfg})

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
            params, stats[phase.name] = self.fit_phase(phase, params, obs, shape_groups, groups, first, monitor)
        stats["terms"] = self.final_terms(params, obs)
        return params, stats

    def phase_leaves(self, phase: Phase, params: BodyParams, shape_groups: torch.Tensor, groups: int) -> dict:
        """The variables `phase` moves, as optimisation leaves: the free bones of the body pose, the
        phenotype per group as a logit (anny's phenotypes extrapolate wildly outside [0, 1])."""
        names = [n for n in phase.variables if (n != "expression" or self.cfg.fit_expression)
                 and (n != "shape" or self.held_shape is None)]
        leaves = {n: getattr(params, n).detach().clone() for n in names}
        if "body_pose" in leaves:
            leaves["body_pose"] = params.body_pose[:, self.free_bones].detach().clone()
        if "shape" in leaves:
            count = torch.bincount(shape_groups, minlength=groups)[:, None]
            mean = torch.zeros(groups, params.shape.shape[1], dtype=params.shape.dtype, device=params.shape.device)
            mean = mean.index_add(0, shape_groups, params.shape.detach()) / count
            leaves["shape"] = torch.logit(mean.clamp(SHAPE_EPS, 1 - SHAPE_EPS))
        return leaves

    def phase_state(self, phase: Phase, params: BodyParams, leaves: dict) -> dict:
        """What a phase's evaluations reuse: the rest state while shape and expression do not move (and
        E_D's correspondences'), the posed body while only its placement moves."""
        state = {"matches": None, "rest": None, "posed": None, "ring_rest": None}
        if "shape" not in leaves and "expression" not in leaves:  # the rest pose does not move: computed once
            with torch.no_grad():
                state["rest"] = self.model.rest_state(params, self.subset)
                if phase.fits_depth:  # and E_D's correspondences' (`correspondences`)
                    state["ring_rest"] = self.model.rest_state(params, self.ring_vertices)
        if set(leaves) <= {"global_orient", "transl"}:  # the body keeps its pose: posed once, only placed
            with torch.no_grad():  # per evaluation (every backend places its model-space output so)
                unplaced = dataclasses.replace(params, global_orient=torch.zeros_like(params.global_orient),
                                               transl=torch.zeros_like(params.transl))
                state["posed"] = self.model.sparse_forward(unplaced, self.subset, state["rest"])
        return state

    def fit_phase(self, phase: Phase, params: BodyParams, obs: BodyObservations, shape_groups: torch.Tensor,
                  groups: int, first: torch.Tensor, monitor=None) -> tuple[BodyParams, dict]:
        """One phase's L-BFGS from `params`; returns the parameters it reaches and its figures."""
        free, B, device = self.free_bones, params.batch_size, params.shape.device
        leaves = self.phase_leaves(phase, params, shape_groups, groups)
        state = self.phase_state(phase, params, leaves)

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
            return self.energy(self.energy_terms(now, obs, phase.terms, state["matches"],
                                                 getattr(self.cfg, phase.rho_key), out=out, rest=rest))

        graph = self.cfg.cuda_graphs and optim.records_graphs(device)  # each phase's evaluations: one recorded graph

        def find_pairs():  # recorded too: the pairs are then refreshed in place
            state["matches"] = state["matches"].refreshed(
                self.correspondences(current(), obs, state["ring_rest"]), graph)

        refresh_pairs = optim.recorded(find_pairs, graph, device)

        def refresh(step, value):
            if phase.fits_depth:
                refresh_pairs()
            if monitor is not None:
                monitor(phase.name, step, value)

        if phase.fits_depth:
            state["matches"] = self.correspondences(current(), obs, state["ring_rest"])
        budget = dict(max_steps=getattr(self.cfg, phase.steps_key), inner_iterations=self.cfg.inner_iterations,
                      ftol=self.cfg.ftol, monitor=refresh, graph=graph)
        if self.cfg.per_frame_lbfgs and ("shape" not in leaves or groups == B):  # the frames do not interact
            result = minimise_per_frame(list(leaves.values()), frame_energies, **budget)
        else:  # frames sharing a phenotype (or `per_frame_lbfgs` off): one problem
            result = minimise(list(leaves.values()), lambda: frame_energies().sum(), **budget,
                              line_search=self.cfg.line_search, max_line_search=self.cfg.max_line_search)
        return current().detach(), {"energy": result.energy, "steps": result.steps,
                                    "evaluations": result.evaluations, "stopped": result.stopped}

    def final_terms(self, params: BodyParams, obs: BodyObservations) -> dict[str, np.ndarray]:
        """Each term of the last phase per frame, (B,), unweighted, at `params`."""
        with torch.no_grad():
            final = self.energy_terms(params, obs, FINAL_TERMS, self.correspondences(params, obs))
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
    per frame: cheaper than all point-vertex distances, in the body stage's hot path."""
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
    return weighted_sum(TERMS, terms, {"": fitter.cfg})


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
