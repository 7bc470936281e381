"""The `global` stage: body and object over all frames jointly, with contact (InterCap's last step).

The per-frame results (OUT/body/, OUT/object/) are refined together, the body's
shape fixed to the per-frame fits' sequence mean, by one L-BFGS (strong Wolfe)
problem per window of frames:
  * E_B, the body stage's own terms (keypoints, depth against visible vertices,
    pose / hand priors, self-penetration) with its weights;
  * E_O, the observed object points (each view's object pixels with depth)
    against the posed object's surface, through a signed-distance grid of the
    mesh; a weak anchor to the tracked pose where the tracker trusted it;
  * E_P, body vertices inside the object; E_C, the touching hands' nearest
    palm patch onto the object's surface, and E_C', a grasping palm onto the
    object's graspable vertices (`object.contact_vertices`), both only in the
    frames the `contact` stage marks; E_G, body and object above the ground;
  * E_A, the acceleration of the object's points; the acceleration of the
    body's vertices; the learned motion priors of body and hands (E_S, E_L,
    E_R; `intercap.motion_prior`) when weighted (off by default: they helped
    one benchmark session and hurt the other, BENCHMARKS.md).
Long sequences run in overlapping windows (memory stays bounded): each window
after the first holds its first `window_history` frames fixed at the previous
window's result, so velocity and acceleration run on across the seam, and a
window commits only the frames that had `window_overlap - window_history`
frames of future in it. Frames that the per-frame stages could not fit stay
free variables (the motion terms carry them), but are written NaN, as before:
marked, never invented.

Writes OUT/global/ (body_params.npz, body_vertices.npy, body_faces.npy,
keypoints3d.npy, object_poses.npz, progress.npz for resume, overlays) and shows
them at OUT/, where the per-frame stages' results were; those stay in
OUT/body/ and OUT/object/.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from intercap.body_models import BodyParams, shared_model
from intercap.body_models.base import PARAM_FIELDS, BodyOutput, axis_angle_to_matrix, matrix_to_axis_angle
from intercap.dynamics.flight import warn_held
from intercap.energies import losses, optim
from intercap.energies.motion_prior import MODEL_FPS
from intercap.energies.optim import minimise
from intercap.geometry.cameras import Cameras
from intercap.geometry.symmetry import mesh_symmetry, unwrap_symmetry
from intercap.io.files import per_frame_result, publish, save_npz, write_json
from intercap.parallel import shutdown, worker_count
from intercap.stages.chunks import Chunk, frame_chunks, run_chunks
from intercap.session.session import in_threads
from intercap.stages.body.stage import (
    PHASES,
    BodyFitter,
    BodyObservations,
    KeypointSource,
    PersonPoints,
    draw_overlay,
    save_body_results,
    unseen_feet_support,
)

log = logging.getLogger(__name__)

BODY_TERMS = PHASES[-1].terms  # E_B: the per-frame stage's final phase
HANDS = ("left_hand", "right_hand")
OUTPUT_FILES = ("body_params.npz", "body_vertices.npy", "body_faces.npy", "keypoints3d.npy", "object_poses.npz")


class GlobalError(ValueError):
    pass


# ---------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------

def fill_gaps(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T, ...) values with invalid frames replaced by linear interpolation in time between the
    nearest valid frames (held at the ends). Axis-angle and translations vary slowly enough over a
    short gap for this to be only a starting point; the optimisation does the rest."""
    values = np.array(values, dtype=np.float64)
    if valid.all() or not valid.any():
        return values
    t = np.arange(len(values))
    flat = values.reshape(len(values), -1)
    for k in range(flat.shape[1]):
        flat[~valid, k] = np.interp(t[~valid], t[valid], flat[valid, k])
    return flat.reshape(values.shape)


@dataclass
class PerFrameResults:
    """What the per-frame stages left, gaps filled; T frames."""

    body: BodyParams  # (T, ...), shape already the sequence mean
    body_valid: np.ndarray  # (T,) bool
    R: np.ndarray  # (T, 3, 3) object -> world
    t: np.ndarray  # (T, 3)
    object_valid: np.ndarray  # (T,) bool
    object_confidence: np.ndarray  # (T,) in [0, 1], 0 where not trusted
    contact: np.ndarray  # (T,) bool
    hand_distance: np.ndarray | None  # (T, 2) metres from the left, right hand to the object (None: not measured yet)
    grasping: np.ndarray | None = None  # (T, 2) bool: the hand holds the object (a contact frame, hand within reach)


def load_per_frame(session, out_dir: Path, model) -> PerFrameResults:
    """Read OUT/body/, OUT/object/ and the contact stage's labels; clear errors when missing."""
    body_file = per_frame_result(out_dir, "body", "body_params.npz")
    object_file = per_frame_result(out_dir, "object", "object_poses.npz")
    for path, stage in ((body_file, "body"), (object_file, "object")):
        if not path.exists():
            raise GlobalError(f"{path} is missing: run the `{stage}` stage first "
                              f"(intercap run SESSION --out {out_dir} --stages {stage})")
    saved = np.load(body_file)
    if str(saved["model"]) != model.name:
        raise GlobalError(f"{body_file} holds a {saved['model']} fit but the session asks for {model.name}")
    body_valid = saved["valid"].astype(bool)
    if not body_valid.any():
        raise GlobalError(f"{body_file}: no frame has a body fit; nothing to refine")
    arrays = {k: fill_gaps(saved[k], body_valid).astype(np.float32) for k in PARAM_FIELDS}
    arrays["shape"][:] = saved["shape_mean"]
    body = BodyParams.from_numpy_dict(arrays, dtype=model.dtype, device=model.faces.device)

    poses = np.load(object_file)
    object_valid = poses["valid"].astype(bool)
    inside = out_dir / "global" / "object_inside_body.npy"  # `object_inside_body`'s, written by `run`
    if inside.exists():
        object_valid &= ~np.load(inside)
    if not object_valid.any():
        raise GlobalError(f"{object_file}: the object was tracked in no frame; nothing to refine")
    R, t = unwrap_symmetry(poses["R"], poses["t"], object_valid, *mesh_symmetry(session.object.load_mesh()))
    rotvec = fill_gaps(_rotvecs(R, object_valid), object_valid)
    R = axis_angle_to_matrix(torch.from_numpy(rotvec)).numpy()
    t = fill_gaps(t, object_valid)
    confidence = np.where(object_valid, np.nan_to_num(poses["confidence"]), 0.0)

    contact, hand_distance = load_contact_labels(out_dir, session.num_frames)
    return PerFrameResults(body, body_valid, R, t, object_valid, confidence, contact, hand_distance)


def hand_object_distance(model, per_frame: PerFrameResults, shape: "ObjectShape") -> np.ndarray:
    """(T, 2) metres from each hand's contact region to the object's surface in the per-frame results."""
    ids = [torch.as_tensor(model.contact_regions[h]) for h in HANDS]
    distance = np.zeros((len(per_frame.contact), 2))
    R = torch.as_tensor(per_frame.R, dtype=torch.float32, device=model.faces.device)
    t = torch.as_tensor(per_frame.t, dtype=torch.float32, device=model.faces.device)
    with torch.no_grad():
        for s in range(0, len(distance), 32):
            sl = slice(s, s + 32)
            vertices = model.sparse_forward(per_frame.body[sl], torch.cat(ids)).vertices
            sd = shape.signed_distance((vertices - t[sl, None]) @ R[sl])
            distance[sl, 0] = sd[:, :len(ids[0])].min(1).values.cpu().numpy()
            distance[sl, 1] = sd[:, len(ids[0]):].min(1).values.cpu().numpy()
    return distance


def _rotvecs(R: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T, 3) axis-angle of the valid rotations, made continuous in time (no 2 pi jumps), NaN elsewhere."""
    out = np.full((len(R), 3), np.nan)
    out[valid] = matrix_to_axis_angle(torch.from_numpy(R[valid]).double()).numpy()
    previous = None
    for i in np.flatnonzero(valid):  # choose the equivalent axis-angle nearest the previous one
        if previous is not None:
            angle = np.linalg.norm(out[i])
            if angle > 1e-6:
                alt = out[i] * (1 - 2 * np.pi / angle)
                if np.linalg.norm(alt - previous) < np.linalg.norm(out[i] - previous):
                    out[i] = alt
        previous = out[i]
    return out


def load_contact_labels(out_dir: Path, T: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Contact per frame (T,) and each hand's per-frame distance to the object (T, 2) metres, from the
    `contact` stage; the distances are None where only OUT/contact.npy exists (measured here then)."""
    from intercap.stages.contact.stage import load_contact

    if (Path(out_dir) / "contact" / "contact.npz").exists():
        data = load_contact(out_dir)
        names = data["region_names"]
        if all(h in names for h in HANDS) and "region_distance_m" in data:
            distance = np.stack([data["region_distance_m"][:, names.index(h)] for h in HANDS], 1)
            return data["contact"].astype(bool), np.nan_to_num(distance, nan=np.inf)
        return data["contact"].astype(bool), None
    labels = Path(out_dir) / "contact.npy"
    if labels.exists():
        return np.load(labels).astype(bool), None
    log.warning("global: no contact labels (run the `contact` stage); contact terms are off")
    return np.zeros(T, bool), np.full((T, 2), np.inf)


# ---------------------------------------------------------------------------
# The object's geometry
# ---------------------------------------------------------------------------

def signed_distance_grid(vertices: np.ndarray, faces: np.ndarray, watertight: bool, resolution: int,
                         cell_m: float | None, margin_m: float | None, cells_max: int) -> dict:
    """`ObjectShape`'s grid: `sdf` (Z, Y, X) metres at the corners of cells from `lo` to `hi`."""
    import open3d as o3d

    lo, hi = vertices.min(0), vertices.max(0)
    margin = 0.2 * float((hi - lo).max()) + 0.05
    margin = min(margin, margin_m) if margin_m else margin
    lo, hi = lo - margin, hi + margin
    cell = float((hi - lo).max()) / resolution
    if cell_m:
        cell = max(min(cell, cell_m), (float(np.prod(hi - lo)) / cells_max) ** (1 / 3))
    counts = np.ceil((hi - lo) / cell).astype(int) + 1
    axes = [lo[k] + cell * np.arange(counts[k]) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).astype(np.float32)  # (X, Y, Z, 3)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces))
    if watertight:
        sdf = scene.compute_signed_distance(grid.reshape(-1, 3)).numpy()
    else:  # no inside to speak of: distances only, so nothing is pushed out of an open shell
        sdf = scene.compute_distance(grid.reshape(-1, 3)).numpy()
    # grid_sample wants (N, C, D, H, W) with x indexing W: store as (Z, Y, X).
    return {"sdf": np.ascontiguousarray(sdf.reshape(grid.shape[:3]).transpose(2, 1, 0)),
            "lo": lo, "hi": (lo + cell * (counts - 1)).astype(np.float32)}


class ObjectShape:
    """The rigid object in its own coordinates: a signed-distance grid (trilinear, differentiable in
    the query points), surface samples for E_A / E_G, and its graspable points for E_C'."""

    def __init__(self, mesh: trimesh.Trimesh, resolution: int, grasp_ids: np.ndarray | None, samples: int = 256,
                 seed: int = 0, cell_m: float | None = None, margin_m: float | None = None,
                 cells_max: int = 4_000_000, cache: Path | None = None):
        """`resolution` cells at least along the grid's longest side, none wider than `cell_m` (a
        chair's 2 cm back panel in 2 cm cells read as hardly inside: penetration seen 2.2 mm of 6.4),
        unless that takes more than `cells_max` cells; the grid reaches 0.2 of the object's size
        plus 5 cm, at most `margin_m`, beyond its box (further out: the border value plus the
        distance to the grid, an overestimate). With `cache` (an .npz) the grid is read from there
        when it was built for the same mesh and settings, else built and written there: a chair's
        takes 1.6 s, and every worker of the stage needs it."""
        vertices = np.asarray(mesh.vertices, dtype=np.float32)
        faces = np.asarray(mesh.faces, dtype=np.uint32)
        if not mesh.is_watertight:
            log.warning("global: the object mesh is not watertight; interpenetration is not measured")
        settings = np.array([resolution, cell_m or 0, margin_m or 0, cells_max], np.float64)
        key = hashlib.sha1(vertices.tobytes() + faces.tobytes() + settings.tobytes()).hexdigest()
        grid = None
        if cache is not None and Path(cache).exists():
            with np.load(cache) as saved:
                if str(saved["key"]) == key:
                    grid = {name: saved[name] for name in ("sdf", "lo", "hi")}
        if grid is None:
            grid = signed_distance_grid(vertices, faces, mesh.is_watertight, resolution, cell_m, margin_m, cells_max)
            if cache is not None:
                save_npz(cache, key=np.array(key), **grid)
        self.sdf = torch.from_numpy(grid["sdf"])[None, None]
        self.lo, self.hi = torch.from_numpy(grid["lo"]), torch.from_numpy(grid["hi"])
        points, _ = trimesh.sample.sample_surface_even(mesh, samples, seed=seed)
        self.samples = torch.as_tensor(np.asarray(points), dtype=torch.float32)  # (M, 3)
        ids = np.arange(len(vertices)) if grasp_ids is None or len(grasp_ids) == 0 else np.asarray(grasp_ids)
        self.grasp_points = torch.from_numpy(vertices[ids])  # (G, 3)
        self.centroid = torch.from_numpy(vertices.mean(0))

    def on(self, device) -> "ObjectShape":
        """A copy with its tensors on `device` (the fitter's: it then copies nothing per evaluation)."""
        moved = copy.copy(self)
        for name in ("sdf", "lo", "hi", "samples", "grasp_points", "centroid"):
            setattr(moved, name, getattr(self, name).to(device))
        return moved

    def signed_distance(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points in object coordinates -> (...) metres, positive outside. Beyond the grid:
        the border value plus the distance to the grid box (an overestimate that keeps its sign)."""
        lo, hi = self.lo.to(points), self.hi.to(points)
        inside = torch.minimum(torch.maximum(points, lo), hi)
        outside = (points - inside).norm(dim=-1)
        normalised = (inside - lo) / (hi - lo) * 2 - 1
        flat = normalised.reshape(1, -1, 1, 1, 3)
        value = torch.nn.functional.grid_sample(self.sdf.to(points), flat, mode="bilinear", align_corners=True)
        return value.reshape(points.shape[:-1]) + outside


# ---------------------------------------------------------------------------
# Windows
# ---------------------------------------------------------------------------

def windows(T: int, size: int, overlap: int, history: int) -> list[tuple[int, int, int, int]]:
    """(start, end, fixed, commit_end) per window: frames [start, end) are optimised together, the
    first `fixed` of them held at the previous window's result, and [start + fixed, commit_end)
    are final after this window."""
    if size < 4 or not 0 <= history <= overlap < size:
        raise GlobalError(f"bad window settings: size {size}, overlap {overlap}, history {history} "
                          "(need 0 <= history <= overlap < size, size >= 4)")
    out, start = [], 0
    while True:
        end = min(start + size, T)
        last = end == T
        out.append((start, end, history if start > 0 else 0, end if last else end - overlap + history))
        if last:
            return out
        start = end - overlap


# ---------------------------------------------------------------------------
# The fit
# ---------------------------------------------------------------------------

class GlobalFitter:
    """One window's joint problem; holds the model, the body stage's fitter and the object shape."""

    def __init__(self, model, cameras: Cameras, bcfg, gcfg, shape: ObjectShape, ground, fps: float):
        self.model, self.bcfg, self.gcfg = model, bcfg, gcfg
        self.body = BodyFitter(model, cameras, bcfg)
        self.shape = shape.on(self.body.subset.device)
        self.fps = float(fps)
        subset = self.body.subset
        self.ground = None if ground is None else (
            torch.as_tensor(ground.point, dtype=torch.float32, device=subset.device),
            torch.as_tensor(ground.normal, dtype=torch.float32, device=subset.device))
        regions = [model.contact_regions[h] for h in HANDS]
        feet = [model.contact_regions[f] for f in ("left_foot", "right_foot") if f in model.contact_regions]
        extra = [torch.as_tensor(r) for r in regions + feet]
        self.priors = {}
        if gcfg.w_body_motion_prior > 0 or gcfg.w_hand_motion_prior > 0:
            from intercap.energies.motion_prior import load_motion_prior

            self.priors = {k: load_motion_prior(k) for k in ("body", "hand")}
            extra += [self.priors[k].point_ids for k in self.priors]
        # the vertices the window needs: the fitting subsample first (E_B), then the rest, once each
        rest = torch.unique(torch.cat(extra).to(subset))
        rest = rest[~torch.isin(rest, subset)]
        self.vertex_ids = torch.cat([subset, rest])
        position = {v: i for i, v in enumerate(self.vertex_ids.tolist())}

        def slots(ids) -> torch.Tensor:
            """The window's vertex slots of model vertices `ids` (read on the host in one `tolist`)."""
            return torch.tensor([position[v] for v in torch.as_tensor(ids).tolist()], device=subset.device)

        self.hand_slots = [slots(r) for r in regions]
        self.prior_slots = {k: slots(p.point_ids) for k, p in self.priors.items()}
        self.free_bones = self.body.free_bones
        self.gravity = None  # (3,) m/s^2 for the free-flight term; set by `run` when episodes exist

    # -- parameters -----------------------------------------------------------------------
    def object_pose(self, R0: torch.Tensor, c0: torch.Tensor, rotation: torch.Tensor, shift: torch.Tensor):
        """The object's pose (R, centre) from the per-frame one turned by `rotation` (axis-angle,
        world, about the centroid) and its centroid moved by `shift`."""
        return axis_angle_to_matrix(rotation) @ R0, c0 + shift

    def to_object(self, points: torch.Tensor, R: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """World points (W, N, 3) -> object coordinates, with R (W, 3, 3) and the centroid's world position."""
        return (points - centre[:, None]) @ R + self.shape.centroid.to(points)

    def from_object(self, points: torch.Tensor, R: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """Object coordinates (M, 3) -> world (W, M, 3)."""
        points = points.to(R.device)  # the fitter's shape is there already (`ObjectShape.on`)
        return (points - self.shape.centroid.to(points)) @ R.transpose(1, 2) + centre[:, None]

    # -- energy ---------------------------------------------------------------------------
    def energy_terms(self, params: BodyParams, R, centre, data: "WindowData", matches, rest=None
                     ) -> dict[str, torch.Tensor]:
        """Every term, unweighted: per frame (W,) where it is per frame. `rest`: the model's
        `rest_state` of `vertex_ids` (shape and expression are fixed in this stage)."""
        g = self.gcfg
        out = self.model.sparse_forward(params, self.vertex_ids, rest)
        vertices = out.vertices  # (W, U, 3)
        subset_out = BodyOutput(vertices=vertices, joints=out.joints, keypoints=out.keypoints)
        terms = {f"body_{k}": v for k, v in self.body.energy_terms(
            params, data.obs, BODY_TERMS, matches, self.bcfg.keypoint_rho, out=subset_out).items()}

        object_world = self.from_object(self.shape.samples, R, centre)  # (W, M, 3)
        if data.object_points is not None:
            sd = self.shape.signed_distance(self.to_object(data.object_points, R, centre))
            terms["object"] = losses.object_point_to_surface(sd, data.object_point_valid, g.object_depth_scale_m)
        terms["object_anchor"] = losses.pose_anchor(object_world, data.object_reference, data.object_confidence)
        # Where the object's pose is a guess (untrusted, filled in from trusted frames), E_P and E_C move
        # the object, not the body: a wrong fill inside the body (fitted to the person's points) would
        # push the person away (a turn without masks: surface 9.4 -> 19.2 mm).
        trusted = (data.object_confidence > 0)[:, None, None]
        body_in_object = self.shape.signed_distance(
            self.to_object(torch.where(trusted, vertices, vertices.detach()), R, centre))  # (W, U)
        terms["interpenetration"] = losses.body_object_interpenetration(body_in_object)
        contact = torch.zeros_like(terms["interpenetration"])
        grasp = torch.zeros_like(contact)
        grasp_world = self.from_object(self.shape.grasp_points, R, centre)
        for h, slots in enumerate(self.hand_slots):
            touching = data.grasping[:, h]
            contact = contact + losses.contact_chamfer(body_in_object[:, slots], touching, g.contact_vertices)
            # E_C' over the grasping frames found on the host when the window was read; without
            # them (`grasp_rows` None), every frame weighted by `touching` (searching it would make a GPU wait)
            rows = None if data.grasp_rows is None else data.grasp_rows[h]
            if rows is None:
                grasp = grasp + losses.hand_contact(vertices[:, slots], grasp_world, touching, g.contact_vertices)
            elif len(rows):  # (half the windows' frames on the 150-frame bench: E_C' was a fifth of an evaluation)
                pick = (lambda x: x.index_select(0, rows))
                grasp = grasp.index_add(0, rows, losses.hand_contact(pick(vertices)[:, slots], pick(grasp_world),
                                                                     pick(touching), g.contact_vertices))
        terms["contact"], terms["hand_contact"] = contact, grasp
        if self.ground is not None:
            point, normal = (x.to(vertices) for x in self.ground)
            terms["ground"] = (losses.ground_penetration(vertices, point, normal)
                               + losses.ground_penetration(object_world, point, normal))
            if self.bcfg.w_ground_support > 0:  # E_S as in the body stage
                terms["body_ground_support"] = unseen_feet_support(vertices, data.obs.keypoints, point, normal)
        if self.gravity is not None and data.flight is not None:
            times = torch.arange(len(centre), dtype=centre.dtype, device=centre.device) / self.fps
            terms["flight"] = losses.flight_parabola(centre, data.flight, times, self.gravity.to(centre))
        if len(vertices) >= 3:
            terms["object_acceleration"] = losses.vertex_acceleration(object_world, self.fps)
            terms["body_acceleration"] = losses.vertex_acceleration(vertices, self.fps)
        if self.priors and len(vertices) >= 3 * max(1, round(self.fps / MODEL_FPS)):  # enough frames for its phases
            from intercap.energies.motion_prior import body_motion_smoothness, hand_motion_smoothness

            up = None if self.ground is None else self.ground[1].to(vertices)
            terms["body_motion_prior"] = body_motion_smoothness(vertices[:, self.prior_slots["body"]], self.fps, up)
            hand_points = vertices[:, self.prior_slots["hand"]]
            terms["hand_motion_prior"] = (hand_motion_smoothness(hand_points, self.fps, "L", up)
                                          + hand_motion_smoothness(hand_points, self.fps, "R", up))
        return terms

    def weight(self, term: str) -> float:
        if term.startswith("body_") and hasattr(self.bcfg, "w_" + term[5:]):
            return getattr(self.bcfg, "w_" + term[5:])
        return getattr(self.gcfg, "w_" + term)

    def fit_window(self, init: BodyParams, R0: torch.Tensor, c0: torch.Tensor, fixed: int, data: "WindowData",
                   monitor=None) -> tuple[BodyParams, torch.Tensor, torch.Tensor, dict]:
        """Optimise frames [fixed, W) of the window; the first `fixed` stay as given."""
        g = self.gcfg
        W = init.batch_size
        free = self.free_bones
        names = ("global_orient", "transl", "left_hand_pose", "right_hand_pose")
        leaves = {n: getattr(init, n)[fixed:].detach().clone() for n in names}
        leaves["body_pose"] = init.body_pose[fixed:, free].detach().clone()
        leaves["rotation"] = torch.zeros(W - fixed, 3, dtype=R0.dtype, device=R0.device)
        leaves["shift"] = torch.zeros(W - fixed, 3, dtype=R0.dtype, device=R0.device)
        still = torch.zeros(fixed, 3, dtype=R0.dtype, device=R0.device)

        def current():
            values = {n: torch.cat([getattr(init, n)[:fixed].detach(), leaves[n]]) for n in names}
            pose = init.body_pose.detach()[fixed:].index_copy(1, free, leaves["body_pose"])
            body = BodyParams(shape=init.shape.detach(), expression=init.expression.detach(),
                              body_pose=torch.cat([init.body_pose[:fixed].detach(), pose]), **values)
            R, centre = self.object_pose(R0, c0, torch.cat([still, leaves["rotation"]]),
                                         torch.cat([still, leaves["shift"]]))
            return body, R, centre

        state = {"matches": self.body.correspondences(init, data.obs)}
        with torch.no_grad():
            rest = self.model.rest_state(init, self.vertex_ids)  # shape and expression stay as the body stage fitted them

        def energy():
            body, R, centre = current()
            terms = self.energy_terms(body, R, centre, data, state["matches"], rest)
            return sum(self.weight(k) * v.sum() for k, v in terms.items())

        # evaluations replay a recorded CUDA graph (`gradient_evaluator`), but not with a free flight in the
        # window (its term picks each episode's frames on the CPU)
        graph = g.cuda_graphs and optim.records_graphs(R0.device) and (self.gravity is None or data.flight is None)

        def find_pairs():  # recorded too: the pairs are then refreshed in place
            state["matches"] = state["matches"].refreshed(
                self.body.correspondences(current()[0].detach(), data.obs), graph)

        refresh_pairs = optim.recorded(find_pairs, graph, R0.device)

        def refresh(step, value):
            if step % max(1, g.correspondence_every) == 0:
                refresh_pairs()
            if monitor is not None:
                monitor(step, value)

        with torch.no_grad():
            before = {k: float(v.sum()) for k, v in self.energy_terms(*current(), data, state["matches"], rest).items()}
        result = minimise(list(leaves.values()), energy, max_steps=g.steps, inner_iterations=g.inner_iterations,
                          ftol=g.ftol, monitor=refresh, graph=graph, line_search=g.line_search,
                          max_line_search=g.max_line_search)
        with torch.no_grad():
            body, R, centre = (x.detach() for x in current())
            after = {k: float(v.sum()) for k, v in self.energy_terms(body, R, centre, data, state["matches"], rest).items()}
        stats = {"before": before, "after": after, "steps": result.steps, "evaluations": result.evaluations,
                 "stopped": result.stopped}
        return body, R, centre, stats


@dataclass
class WindowData:
    """The observations of one window's W frames."""

    obs: BodyObservations
    object_points: torch.Tensor | None  # (W, P, 3) world
    object_point_valid: torch.Tensor | None  # (W, P)
    object_reference: torch.Tensor  # (W, M, 3) the object's samples where the tracker put them
    object_confidence: torch.Tensor  # (W,)
    grasping: torch.Tensor  # (W, 2) float
    flight: torch.Tensor | None = None  # (W,) long: free-flight episode id per frame, -1 outside (GraviCap);
    # None when no frame of the window is in flight
    grasp_rows: tuple | None = None  # per hand, (G,) long: the frames where it grasps, found on the host
    # when the window is read (E_C' measures only them); None: every frame, weighted by `grasping`


class Observations:
    """Loads what a window needs: keypoints and person points as the body stage does, object points
    from the object masks (given or derived around the tracked pose) with depth."""

    def __init__(self, session, cfg, out_dir: Path, cameras: Cameras):
        from intercap.stages.object.stage import ObjectTracker

        self.session, self.cfg = session, cfg
        self.device = cameras.K.device  # where the window's tensors go (the fit's device)
        self.keypoints = KeypointSource(session, out_dir, cfg.detect.use_session_keypoints, cameras,
                                        cfg.body.keypoint_view_check_px)
        self.person = PersonPoints(session, cameras, cfg.body, out_dir)
        self.tracker = ObjectTracker(session, cfg.object, session.object.load_mesh())

    def object_points(self, frame_id: int, R: np.ndarray, t: np.ndarray, trusted: bool, seed: int,
                      depths: list | None = None) -> np.ndarray:
        """(P, 3) world points of the object's pixels, a seeded subset; none where the tracker lost it.
        `depths`: the frame's depth maps when already read."""
        P = self.cfg.global_.object_points_per_view * self.session.num_cameras
        if not trusted:
            return np.zeros((0, 3))
        points = self.tracker.object_points(self.tracker.observe(frame_id, (R, t), depths=depths))
        if len(points) > P:
            points = points[np.random.default_rng([seed, frame_id]).choice(len(points), P, replace=False)]
        return points

    def window(self, frames: np.ndarray, per_frame: PerFrameResults, shape: ObjectShape) -> WindowData:
        ids = self.session.frame_ids[frames]
        kps = self.keypoints.batch(ids, self.cfg.body.min_keypoint_confidence)
        C, B = self.session.num_cameras, len(frames)
        points = np.zeros((B, C, self.cfg.body.points_per_view, 3), np.float32)
        point_valid = np.zeros(points.shape[:3], bool)
        P = self.cfg.global_.object_points_per_view * C
        cloud = np.zeros((B, P, 3), np.float32)
        cloud_valid = np.zeros((B, P), bool)

        def read_frame(b: int) -> None:  # in IO threads; each view's depth decoded once for person and object
            i, frame_id = frames[b], int(ids[b])
            depths = [self.session.read_depth(c, frame_id) for c in range(C)]
            points[b], point_valid[b] = self.person.frame(frame_id, kps[b], depths)
            pts = self.object_points(frame_id, per_frame.R[i], per_frame.t[i], bool(per_frame.object_valid[i]),
                                     self.cfg.global_.seed, depths)
            cloud[b, :len(pts)], cloud_valid[b, :len(pts)] = pts, True

        in_threads(read_frame, range(B))
        device = self.device
        obs = BodyObservations(ids, torch.from_numpy(kps).to(device), torch.from_numpy(points).to(device),
                               torch.from_numpy(point_valid).to(device))
        R = torch.as_tensor(per_frame.R[frames], dtype=torch.float32)
        t = torch.as_tensor(per_frame.t[frames], dtype=torch.float32)
        reference = (shape.samples @ R.transpose(1, 2)) + t[:, None]
        return WindowData(obs, torch.from_numpy(cloud).to(device), torch.from_numpy(cloud_valid).to(device),
                          reference.to(device),
                          torch.as_tensor(per_frame.object_confidence[frames], dtype=torch.float32, device=device),
                          torch.as_tensor(per_frame.grasping[frames], dtype=torch.float32, device=device),
                          grasp_rows=tuple(torch.as_tensor(np.flatnonzero(per_frame.grasping[frames, h]), device=device)
                                           for h in range(2)))


# ---------------------------------------------------------------------------
# The stage
# ---------------------------------------------------------------------------

def nothing_to_refine(out_dir: Path) -> str | None:
    """Why the joint fit has nothing to refine (the body fitted in no frame, or the object tracked in
    none: a person never seen, an object never found), or None. The per-frame results then stand,
    and the later stages run on them, as for a session without an object."""
    for stage, name, what in (("body", "body_params.npz", "no frame has a body fit"),
                              ("object", "object_poses.npz", "the object was tracked in no frame")):
        path = per_frame_result(out_dir, stage, name)
        if path.exists():
            with np.load(path) as saved:
                if not saved["valid"].any():
                    return f"{what} ({path})"
    return None  # missing files: `load_per_frame` says which stage to run


def object_inside_body(session, out_dir: Path, share: float, margin_m: float = 0.02) -> np.ndarray:
    """(T,) bool: frames whose tracked object pose has more than `share` of its surface samples at
    least `margin_m` inside the per-frame body (signed by the nearest body vertex's normal). Without
    masks the tracker can fit the object to the person's own points; the joint fit would then push
    the body out of it (a turn: body error 17 -> 42 mm). A held object stays outside the body but
    for the fingers (at most 0.03 on eight sessions)."""
    from scipy.spatial import cKDTree

    files = [per_frame_result(out_dir, stage, name) for stage, name in (
        ("object", "object_poses.npz"), ("body", "body_vertices.npy"), ("body", "body_faces.npy"),
        ("body", "body_params.npz"))]
    if not all(f.exists() for f in files):  # `load_per_frame` names a missing stage; no meshes: not checked
        return np.zeros(session.num_frames, bool)
    poses = np.load(files[0])
    vertices = np.load(files[1], mmap_mode="r")
    faces = np.load(files[2])
    valid = poses["valid"].astype(bool) & np.load(files[3])["valid"].astype(bool)
    samples, _ = trimesh.sample.sample_surface_even(session.object.load_mesh(), 256, seed=0)
    inside = np.zeros(len(valid), bool)

    def check(i: int) -> None:
        body = np.asarray(vertices[i], np.float64)
        normals = trimesh.Trimesh(body, faces, process=False).vertex_normals
        world = samples @ poses["R"][i].T + poses["t"][i]
        _, nearest = cKDTree(body).query(world)
        depth = ((body[nearest] - world) * normals[nearest]).sum(1)
        inside[i] = (depth > margin_m).mean() > share

    in_threads(check, np.flatnonzero(valid))
    return inside


def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `global` stage; see the module docstring. The take is fitted in chunks of frames by
    `run.workers` processes (`intercap.parallel`), each chunk with a window's overlap of context
    either side and its own resumable checkpoint."""
    if session.object is None:
        log.info("global: the session has no object; the per-frame body results stand")
        return {"skipped": "no object in session"}
    out_dir = Path(out_dir)
    reason = nothing_to_refine(out_dir)
    g = cfg.global_
    inside = np.zeros(session.num_frames, bool)
    if reason is None:
        inside = object_inside_body(session, out_dir, g.object_inside_body_share)
        (out_dir / "global").mkdir(parents=True, exist_ok=True)
        np.save(out_dir / "global" / "object_inside_body.npy", inside)
        if inside.any():
            log.warning("global: %d tracked object pose(s) lie inside the body (fitted to the person's points):"
                        " not trusted here", int(inside.sum()))
        if inside.any():
            with np.load(per_frame_result(out_dir, "object", "object_poses.npz")) as poses:
                if not (poses["valid"].astype(bool) & ~inside).any():
                    reason = "every tracked object pose lies inside the body"
    if reason is not None:
        log.warning("global: skipped: %s; the per-frame results stand", reason)
        return {"skipped": reason}
    T = session.num_frames
    chunks = frame_chunks(T, worker_count(cfg), cfg.run.min_frames_per_worker, context=g.window_overlap)
    if len(chunks) == 1:
        problem = GlobalProblem(session, cfg, out_dir)
        parts = run_chunks(fit_chunk, chunks, (session, cfg, out_dir, problem), T, "global", progress)
    else:  # workers load the session and set up the problem themselves, reading the grid built here
        object_shape(session, g, out_dir)
        parts = run_chunks(fit_chunk, chunks, (session.root, cfg, out_dir, None), T, "global", progress)
        shutdown()  # no later stage has chunks: the idle workers' memory (~1 GB each) goes before the outputs'
        problem = GlobalProblem(session, cfg, out_dir)
    warn_held(problem.flight["held"], "global")
    fitted = BodyParams.from_numpy_dict(
        {name: np.concatenate([p["params"][name] for p in parts]) for name in parts[0]["params"]},
        dtype=problem.model.dtype, device=problem.model.faces.device)
    R_all = torch.from_numpy(np.concatenate([p["R"] for p in parts]))
    centre_all = torch.from_numpy(np.concatenate([p["centre"] for p in parts]))
    history = [h for p in parts for h in p["history"]]
    seconds = sum(p["seconds"] for p in parts)
    figures = write_outputs(session, problem.model, fitted, R_all, centre_all, problem.shape, problem.per_frame,
                            seconds, history, out_dir, problem.observations, problem.cameras, cfg,
                            problem.fitter.weight)
    before, after = (figures.get(f"energy_{when}", {}).get("body_keypoints", 0.0) for when in ("before", "after"))
    ratio = after / before if before > 0 else 1.0
    speed = pelvis_speed_p90(out_dir, session.fps)
    if g.max_keypoint_energy_ratio > 0 and ratio > g.max_keypoint_energy_ratio:
        log.warning("global: %s (the per-frame pelvis moves %.1f m/s at the 90th percentile at %g fps)",
                    data_disagreement(ratio, session.fps), speed, session.fps)
    offsets = camera_offsets_ms(session, problem, out_dir, cfg) if g.max_camera_offset_ms > 0 else {}
    out_of_sync = unsynchronised(offsets, g.max_camera_offset_ms)
    if out_of_sync:
        log.warning("global: %s", out_of_sync)
    return {**figures, **problem.flight["figures"], "object_frames_inside_body": int(inside.sum()),
            "workers": len(chunks), "pelvis_speed_p90_mps": speed, "keypoint_energy_ratio": ratio,
            "camera_time_offsets_ms": offsets}


def camera_offsets_ms(session, problem: "GlobalProblem", out_dir: Path, cfg) -> dict:
    """Each camera's lag behind the fitted motion against the cameras' median, ms
    (calib.time_offsets), on `global.time_check_frames` frames spread over the take."""
    from intercap.calib.time_offsets import camera_time_offsets

    keypoints = np.load(out_dir / "global" / "keypoints3d.npy", mmap_mode="r")
    T = len(keypoints)
    if T < 3 or session.num_cameras < 2:
        return {}
    frames = np.unique(np.linspace(1, T - 2, min(T - 2, cfg.global_.time_check_frames)).round().astype(np.int64))
    observed = problem.observations.keypoints.batch(session.frame_ids[frames], cfg.body.min_keypoint_confidence)
    offsets = camera_time_offsets(keypoints, observed, frames, problem.cameras, session.fps)
    return {name: round(float(o) * 1000, 2) for name, o in zip(session.camera_names, offsets) if np.isfinite(o)}


def unsynchronised(offsets_ms: dict, limit_ms: float) -> str:
    """What a person is told (log and report) of cameras whose frames lag or lead the others' by
    more than `limit_ms` (global.max_camera_offset_ms); empty when none does."""
    off = {name: ms for name, ms in offsets_ms.items() if abs(ms) > limit_ms > 0}
    if not off:
        return ""
    return (", ".join(f"{name} {ms:+.0f} ms" for name, ms in off.items()) + " against the other cameras: their "
            "frames seem taken at other times (a lone camera shows part of its lag). Were the devices recorded with "
            "wired sync? Each such view puts the moving person where the others do not")


def data_disagreement(ratio: float, fps: float) -> str:
    """What a person is told (log and report) when the joint fit raised the keypoints' energy `ratio`
    times, past `global.max_keypoint_energy_ratio`: most often a wrong frame rate."""
    return (f"the joint fit moved the body away from its keypoints (their energy x{ratio:.1f}): the motion terms "
            f"and the data disagree. Is session.yaml's fps ({fps:g}) the rate of the frames given? If frames were "
            "skipped, set it to theirs")


def pelvis_speed_p90(out_dir: Path, fps: float) -> float:
    """90th percentile of the per-frame body's pelvis (BODY_25 mid-hip) speed between consecutive
    fitted frames, m/s at `fps`; 0 when there are no two."""
    path = per_frame_result(out_dir, "body", "keypoints3d.npy")
    if not path.exists():
        return 0.0
    speeds = np.linalg.norm(np.diff(np.load(path, mmap_mode="r")[:, 8], axis=0), axis=1) * fps
    speeds = speeds[np.isfinite(speeds)]
    return float(np.percentile(speeds, 90)) if len(speeds) else 0.0


def object_shape(session, g, out_dir: Path) -> ObjectShape:
    """The session object's `ObjectShape`, its grid cached in OUT/global/object_sdf.npz."""
    return ObjectShape(session.object.load_mesh(), g.sdf_resolution, session.object.contact_vertices, seed=g.seed,
                       cell_m=g.sdf_cell_m, margin_m=g.sdf_margin_m, cache=out_dir / "global" / "object_sdf.npz")


class GlobalProblem:
    """What every chunk of the stage needs: the model, the per-frame results, the object's shape,
    the ground, free-flight episodes, the fitter and the observation loader."""

    def __init__(self, session, cfg, out_dir: Path):
        from intercap.stages.prepare.stage import load_ground

        g = cfg.global_
        torch.manual_seed(g.seed)
        stage_dir = out_dir / "global"
        self.model = shared_model(dataclasses.replace(cfg.body_model, name=session.body_model),
                                  device=cfg.run.device)
        self.cameras = Cameras.from_infos(session.cameras, device=cfg.run.device)
        self.per_frame = load_per_frame(session, out_dir, self.model)
        ground = load_ground(out_dir) if (out_dir / "prepare" / "ground.json").exists() else None
        if ground is None:
            log.warning("global: no ground plane (run the `prepare` stage); E_G is off")
        self.shape = object_shape(session, g, out_dir)
        per_frame = self.per_frame
        if per_frame.hand_distance is None:
            per_frame.hand_distance = hand_object_distance(self.model, per_frame, self.shape)
        per_frame.grasping = per_frame.contact[:, None] & (per_frame.hand_distance < g.hand_reach_m)
        self.fitter = GlobalFitter(self.model, self.cameras, cfg.body, g, self.shape, ground, session.fps)
        self.flight = flight = free_flight(per_frame, self.shape, ground, session.fps, g)
        if flight["episodes"].size and g.w_flight > 0:
            self.fitter.gravity = torch.as_tensor(-9.81 * flight["up"], dtype=torch.float32, device=cfg.run.device)
        if flight["figures"]["gravity_source"] == "flight":  # no floor in view: up from the object's free flight
            write_json(stage_dir / "gravity.json", {"up": flight["figures"]["gravity_up"], "source": "flight",
                                                    "gravity_mps2": (-9.81 * flight["up"]).tolist(),
                                                    "episodes": flight["figures"]["flight_episodes"]})
        self.observations = Observations(session, cfg, out_dir, self.cameras)


def fit_chunk(session, cfg, out_dir: Path, problem: GlobalProblem | None, chunk: Chunk, queue) -> dict:
    """Fit frames [chunk.lo_context, chunk.hi_context) in overlapping windows, checkpointed after
    every window (OUT/global/progress_LO_HI.npz); returns rows [chunk.lo, chunk.hi) of the body
    parameters (numpy), object rotation `R` and `centre`, the windows' `history` and `seconds`."""
    from intercap.session.frame_cache import open_session

    session = open_session(session, out_dir)
    g = cfg.global_
    out_dir = Path(out_dir)
    problem = problem or GlobalProblem(session, cfg, out_dir)
    per_frame, shape = problem.per_frame, problem.shape
    lo, hi = chunk.lo_context, chunk.hi_context
    plan = [(a + lo, b + lo, fixed, commit + lo) for a, b, fixed, commit in
            windows(hi - lo, g.window_frames, g.window_overlap, g.window_history)]
    fitted = per_frame.body.clone()
    device = problem.model.faces.device  # the windows are fitted there
    R_all = torch.as_tensor(per_frame.R, dtype=torch.float32, device=device)
    centre_all = torch.as_tensor(per_frame.t, dtype=torch.float32, device=device) + R_all @ shape.centroid.to(R_all)
    checkpoint = out_dir / "global" / f"progress_{chunk.lo:06d}_{chunk.hi:06d}.npz"
    next_window, seconds, history = 0, 0.0, []
    if checkpoint.exists():
        saved = np.load(checkpoint)
        fitted = BodyParams.from_numpy_dict(saved, dtype=problem.model.dtype, device=device)
        R_all, centre_all = torch.from_numpy(saved["R"]).to(device), torch.from_numpy(saved["centre"]).to(device)
        next_window, seconds = int(saved["next_window"]), float(saved["seconds"])
        log.info("global: frames %d-%d resuming at window %d of %d", chunk.lo, chunk.hi - 1, next_window + 1, len(plan))
    reported = chunk.lo
    for k in range(next_window, len(plan)):
        start, end, fixed, commit = plan[k]
        tick = time.perf_counter()
        frames = np.arange(start, end)
        data = problem.observations.window(frames, per_frame, shape)
        episode = problem.flight["episode_of_frame"][frames]
        data.flight = torch.as_tensor(episode, device=device) if (episode >= 0).any() else None
        body, R, centre, stats = problem.fitter.fit_window(fitted[start:end], R_all[start:end],
                                                           centre_all[start:end], fixed, data)
        keep = slice(fixed, commit - start)
        for name, value in body.tensors().items():
            getattr(fitted, name)[start + fixed:commit] = value[keep]
        R_all[start + fixed:commit], centre_all[start + fixed:commit] = R[keep], centre[keep]
        seconds += time.perf_counter() - tick
        history.append(stats)
        log.debug("global window %d: %s", k, stats)
        save_npz(checkpoint, **fitted.to_numpy_dict(), R=R_all.cpu().numpy(), centre=centre_all.cpu().numpy(),
                 next_window=k + 1, seconds=seconds)
        finished = min(commit, chunk.hi)
        if finished > reported:
            queue.put(finished - reported)
            reported = finished
    rows = slice(chunk.lo, chunk.hi)
    return {"params": fitted.map(lambda t: t[rows]).to_numpy_dict(), "R": R_all[rows].cpu().numpy(),
            "centre": centre_all[rows].cpu().numpy(), "history": history, "seconds": seconds}


def free_flight(per_frame: PerFrameResults, shape: ObjectShape, ground, fps: float, g) -> dict:
    """The tracked object's free-flight episodes (GraviCap): frames where the contact stage sees no
    body contact and the object's surface is clear of the ground plane, for `flight_min_frames`.
    Gravity is -9.81 along the ground normal; with no ground plane (prepare found no floor) the up
    direction comes from the flights themselves (`gravity_from_flight`), written to
    OUT/global/gravity.json by the caller's metrics ("gravity_source": "flight")."""
    from intercap.dynamics.flight import falling_episodes, find_flight_episodes, gravity_from_flight, object_on_ground

    T = len(per_frame.contact)
    centres = per_frame.t + np.einsum("tij,j->ti", per_frame.R, shape.centroid.numpy())
    centres = np.where(per_frame.object_valid[:, None], centres, np.nan)
    touching = per_frame.contact.copy()
    if ground is not None:
        points = np.einsum("tij,mj->tmi", per_frame.R, shape.samples.numpy()) + per_frame.t[:, None]
        touching |= object_on_ground(points, ground.point, ground.normal, g.flight_ground_margin_m)
        up, source = np.asarray(ground.normal, np.float64), "ground"
    else:
        up, source = np.array([0.0, 0.0, 1.0]), "none"  # only to run the detection; replaced below
    episodes = find_flight_episodes(centres, touching, up, fps, g.flight_min_frames)
    held = []  # runs touching nothing that do not fall (`run` says so, once)
    if ground is not None:  # with no floor, `gravity_from_flight` checks the episodes against gravity itself
        episodes, held = falling_episodes(centres, episodes, fps, up, g.flight_max_residual_m)
    figures = {"flight_episodes": episodes.tolist(), "flight_runs_held": [[a, b] for a, b, _ in held]}
    if ground is None and len(episodes):
        try:
            fit = gravity_from_flight(centres, episodes, fps)
            up, source = fit["up"], "flight"
            figures.update(gravity_from_flight_g_norm=fit["g_norm"], gravity_from_flight_residual_mm=1e3 * fit["residual_m"])
        except ValueError as error:
            log.warning("global: %s; the free-flight term is off", error)
            episodes = episodes[:0]
    if ground is None and source != "flight":
        episodes = episodes[:0]
    figures["gravity_source"] = source
    figures["gravity_up"] = [float(v) for v in up]
    episode_of_frame = np.full(T, -1, np.int64)
    for e, (a, b) in enumerate(episodes):
        episode_of_frame[a:b + 1] = e
    figures["flight_frames"] = int((episode_of_frame >= 0).sum())
    return {"episodes": episodes, "up": up, "episode_of_frame": episode_of_frame, "figures": figures, "held": held}


def write_outputs(session, model, fitted: BodyParams, R, centre, shape: ObjectShape, per_frame: PerFrameResults,
                  seconds: float, history: list, out_dir: Path, observations: Observations, cameras, cfg,
                  weight) -> dict:
    """OUT/global/ files, shown at OUT/; frames the per-frame stages could not fit are NaN."""
    T = session.num_frames
    stage_dir = out_dir / "global"
    valid = per_frame.body_valid
    vertices, keypoints = save_body_results(stage_dir, model, fitted, valid, session.frame_ids)
    ok = per_frame.object_valid
    R_out = np.where(ok[:, None, None], R.numpy(), np.nan).astype(np.float32)
    t_world = centre - (R @ shape.centroid)
    t_out = np.where(ok[:, None], t_world.numpy(), np.nan).astype(np.float32)
    save_npz(stage_dir / "object_poses.npz", R=R_out, t=t_out, valid=ok, confidence=per_frame.object_confidence,
             frame_ids=session.frame_ids)
    for name in OUTPUT_FILES:
        publish(stage_dir / name, out_dir / name)

    for i in range(0, T, max(1, cfg.body.overlay_every)):
        fid = int(session.frame_ids[i])
        if valid[i]:
            draw_overlay(session, keypoints[i], fid, cameras, stage_dir / "overlays" / f"body_{fid:06d}.jpg")
        if ok[i]:
            from intercap.stages.object.stage import draw_overlay as draw_object

            draw_object(session, observations.tracker, fid, R_out[i], t_out[i],
                        stage_dir / "overlays" / f"object_{fid:06d}.jpg")
    figures = quality_figures(vertices, R_out, t_out, shape, per_frame, session.fps)
    totals = {}  # each term's weighted energy summed over windows, before and after the fit
    for stats in history:
        for when in ("before", "after"):
            for term, value in stats[when].items():
                totals.setdefault(f"energy_{when}", {}).setdefault(term, 0.0)
                totals[f"energy_{when}"][term] += weight(term) * value
    totals = {key: {term: float(f"{value:.4g}") for term, value in terms.items()} for key, terms in totals.items()}
    return {**figures, **totals, "windows": len(history), "seconds_per_frame_fit": seconds / max(T, 1),
            "evaluations": sum(h["evaluations"] for h in history), "steps": sum(h["steps"] for h in history)}


FIGURE_FRAMES = 256  # frames per step of `quality_figures`: a long take's (T, V, 3) temporaries stay bounded


def in_parts(frames: np.ndarray) -> list[np.ndarray]:
    """Frame indices (n,) -> consecutive parts of at most FIGURE_FRAMES."""
    return np.array_split(frames, -(-len(frames) // FIGURE_FRAMES))


def quality_figures(vertices: np.ndarray, R: np.ndarray, t: np.ndarray, shape: ObjectShape,
                    per_frame: PerFrameResults, fps: float) -> dict:
    """The stage's own checks (no ground truth): penetration on contact frames, jitter. Computed
    `FIGURE_FRAMES` frames at a time: over a whole 3,000-frame take at once, their temporaries
    took 1.5 GB."""
    both = per_frame.body_valid & per_frame.object_valid & per_frame.contact
    figures = {"contact_frames": int(per_frame.contact.sum())}
    if both.any():
        depth = []  # (n,) deepest body vertex inside the object per frame, FIGURE_FRAMES frames at a time
        for part in in_parts(np.flatnonzero(both)):
            local = np.einsum("tvj,tjk->tvk", vertices[part] - t[part, None], R[part]).astype(np.float32)
            depth.append(np.maximum(-shape.signed_distance(torch.from_numpy(local)).numpy(), 0).max(1))
        depth = np.concatenate(depth)
        figures.update(penetration_mm_mean=float(1000 * depth.mean()), penetration_mm_max=float(1000 * depth.max()))
    fine = np.flatnonzero(per_frame.body_valid[2:] & per_frame.body_valid[1:-1] & per_frame.body_valid[:-2])
    if len(fine):  # frame fine[i] + 1 and both its neighbours fitted
        total = 0.0
        for part in in_parts(fine):
            acc = np.linalg.norm(vertices[part + 2] - 2 * vertices[part + 1] + vertices[part], axis=-1)
            total += float(acc.sum(dtype=np.float64))
        figures["jitter_mps2"] = total / (len(fine) * vertices.shape[1]) * fps**2
    return figures
