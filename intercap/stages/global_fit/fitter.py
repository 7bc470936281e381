"""The joint fit of one window of frames: body and object together, by L-BFGS over the energy of
`terms.TERMS`, and the plan of overlapping windows that covers a take.

A window's variables are the body's pose, orientation, translation and hands (its shape and
expression stay as the body stage fitted them) and, per frame, a rotation about the object's
centroid and a shift of it from its per-frame pose. Each window after the first holds its first
`window_history` frames fixed at the previous window's result, so velocity and acceleration run on
across the seam, and commits only the frames that had `window_overlap - window_history` frames of
future in it.
"""
from __future__ import annotations

import torch

from intercap.body_models import BodyParams
from intercap.body_models.base import axis_angle_to_matrix
from intercap.energies import optim
from intercap.energies.optim import minimise
from intercap.energies.terms import Term, check_weights, evaluate_terms, weighted_sum
from intercap.geometry.cameras import Cameras
from intercap.geometry.pointclouds import nearest_shares
from intercap.stages.body.fitter import BodyFitter
from intercap.stages.global_fit.observations import HANDS, GlobalError, ObjectShape, WindowData
from intercap.stages.global_fit.terms import TERMS, GlobalEvaluation

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


class GlobalFitter:
    """One window's joint problem; holds the model, the body stage's fitter and the object shape."""

    def __init__(self, model, cameras: Cameras, bcfg, gcfg, shape: ObjectShape | None, ground, fps: float,
                 table: tuple[Term, ...] = TERMS):
        """`table`: the energy's terms (`terms.TERMS`; a test may pass another), their weights read from
        `gcfg` (section "") and `bcfg` (section "body"). `shape` None: a body-only joint fit (the
        object's terms do not apply and its pose is no variable)."""
        self.model, self.bcfg, self.gcfg = model, bcfg, gcfg
        self.table = check_weights(table, {"": type(gcfg), "body": type(bcfg)})
        self.configs = {"": gcfg, "body": bcfg}
        self.body = BodyFitter(model, cameras, bcfg)
        self.shape = None if shape is None else shape.on(self.body.subset.device)
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

        self.vertex_shares = None  # (U,) mean 1: the mesh's vertices each window vertex stands for
        if shape is None and gcfg.acceleration_over_mesh_alone:
            with torch.no_grad():
                mesh = model(model.init_params(1, device=subset.device)).vertices[0].double().cpu().numpy()
            shares = nearest_shares(mesh, self.vertex_ids.cpu().numpy())
            self.vertex_shares = torch.as_tensor(shares, dtype=torch.float32, device=subset.device)
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
    def evaluation(self, params: BodyParams, R, centre, data: WindowData, matches, rest=None) -> GlobalEvaluation:
        """What the terms read at `params`, (R, centre) (`GlobalEvaluation.of`)."""
        return GlobalEvaluation.of(self, params, R, centre, data, matches, rest)

    def energy_terms(self, params: BodyParams, R, centre, data: WindowData, matches, rest=None
                     ) -> dict[str, torch.Tensor]:
        """Every term of the table that applies, unweighted, in table order: per frame (W,) where it is
        per frame. `rest`: the model's `rest_state` of `vertex_ids` (shape and expression are fixed here)."""
        return evaluate_terms(self.table, self.evaluation(params, R, centre, data, matches, rest))

    def weighted_energy(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        """The weighted sum of `terms` (from `energy_terms`), each summed over the window's frames."""
        return weighted_sum(self.table, terms, self.configs, reduce=lambda v: v.sum())

    def weight(self, name: str) -> float:
        """The weight of the table's term `name`."""
        return next(term for term in self.table if term.name == name).weight_in(self.configs)

    def fit_window(self, init: BodyParams, R0: torch.Tensor, c0: torch.Tensor, fixed: int, data: WindowData,
                   monitor=None) -> tuple[BodyParams, torch.Tensor, torch.Tensor, dict]:
        """Optimise frames [fixed, W) of the window; the first `fixed` stay as given."""
        g = self.gcfg
        W = init.batch_size
        free = self.free_bones
        names = ("global_orient", "transl", "left_hand_pose", "right_hand_pose")
        leaves = {n: getattr(init, n)[fixed:].detach().clone() for n in names}
        leaves["body_pose"] = init.body_pose[fixed:, free].detach().clone()
        if self.shape is not None:
            leaves["rotation"] = torch.zeros(W - fixed, 3, dtype=R0.dtype, device=R0.device)
            leaves["shift"] = torch.zeros(W - fixed, 3, dtype=R0.dtype, device=R0.device)
        still = torch.zeros(fixed, 3, dtype=R0.dtype, device=R0.device)

        def current():
            values = {n: torch.cat([getattr(init, n)[:fixed].detach(), leaves[n]]) for n in names}
            pose = init.body_pose.detach()[fixed:].index_copy(1, free, leaves["body_pose"])
            body = BodyParams(shape=init.shape.detach(), expression=init.expression.detach(),
                              body_pose=torch.cat([init.body_pose[:fixed].detach(), pose]), **values)
            if self.shape is None:
                return body, R0, c0
            R, centre = self.object_pose(R0, c0, torch.cat([still, leaves["rotation"]]),
                                         torch.cat([still, leaves["shift"]]))
            return body, R, centre

        state = {"matches": self.body.correspondences(init, data.obs)}
        with torch.no_grad():
            rest = self.model.rest_state(init, self.vertex_ids)  # shape and expression stay as the body stage's

        def energy():
            body, R, centre = current()
            return self.weighted_energy(self.energy_terms(body, R, centre, data, state["matches"], rest))

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
            terms = self.energy_terms(body, R, centre, data, state["matches"], rest)
            after = {k: float(v.sum()) for k, v in terms.items()}
        stats = {"before": before, "after": after, "steps": result.steps, "evaluations": result.evaluations,
                 "stopped": result.stopped}
        return body, R, centre, stats
