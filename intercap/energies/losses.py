"""Loss terms, each a small pure function named after its equation.

Stages compose them with weights from their config section. Shapes are
written (B frames, C views, h x w render grid).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from intercap.energies import optim


def geman_mcclure(residual: torch.Tensor, scale: float) -> torch.Tensor:
    """rho(r) = r^2 / (r^2 + s^2): quadratic near zero, saturates at 1 for outliers."""
    squared = residual * residual
    return squared / (squared + scale * scale)


def object_silhouette(rendered: torch.Tensor, observed: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """E_O's segmentation part, sum_v ||(R_S - S_v) * W_v||^2 / pixels, (B, C, h, w) -> (B,).

    InterCap writes the weight as S_v (only pixels of the observed mask count);
    alone that lets the rendering spill outside the mask for free, so W_v is 1
    over the crop except where the object may legitimately be hidden (pixels
    where something is measured in front of the rendered surface: a hand)."""
    error = (rendered - observed) ** 2 * weight
    return error.flatten(2).mean(-1).sum(-1)


def object_depth(
    rendered_depth: torch.Tensor,
    observed_depth: torch.Tensor,
    weight: torch.Tensor,
    scale: float,
) -> torch.Tensor:
    """E_O's depth part, sum_v rho(R_D - D_v) over the observed object pixels, (B, C, h, w) -> (B,).

    `weight` is S_v times the pixels where depth was measured and nothing stands
    in front of the object; where the rendering has no surface (R_D = 0) the
    pixel pays the saturated cost. rho is Geman-McClure with `scale` metres, so
    wrong Kinect depth cannot dominate. Normalised per view by the weight sum."""
    rho = geman_mcclure(rendered_depth - observed_depth, scale) * weight
    return (rho.flatten(2).sum(-1) / weight.flatten(2).sum(-1).clamp(min=1.0)).sum(-1)


def occlusion_weight(rendered_depth: torch.Tensor, observed_depth: torch.Tensor, margin: float) -> torch.Tensor:
    """1 where the object could be seen, 0 where the sensor measured something
    clearly in front of the rendered surface (an occluder such as a hand)."""
    occluded = (observed_depth > 0) & (rendered_depth > 0) & (observed_depth < rendered_depth - margin)
    return (~occluded).to(rendered_depth.dtype)


class _GramSchmidt(torch.autograd.Function):
    """The 6D representation's Gram-Schmidt, (..., 6) -> (..., 3, 3), with its backward written out:
    about 35 kernels forward and backward, roma's `special_gramschmidt` about 60 (the same forward
    steps, autograd's backward). Every object evaluation converts its poses."""

    @staticmethod
    def forward(ctx, r6: torch.Tensor) -> torch.Tensor:
        a, b = r6.unflatten(-1, (2, 3)).unbind(-2)
        a_norm = a.norm(dim=-1, keepdim=True)
        x = a / a_norm
        x_b = (x * b).sum(-1, keepdim=True)
        y_free = b - x_b * x
        y_norm = y_free.norm(dim=-1, keepdim=True)
        y = y_free / y_norm
        ctx.save_for_backward(x, y, a_norm, y_norm, x_b)  # not r6 (nor b): the fits move r6 in place
        return torch.stack([x, y, torch.linalg.cross(x, y)], -1)

    @staticmethod
    @once_differentiable  # no second derivatives: a double backward raises instead of going wrong silently
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        x, y, a_norm, y_norm, x_b = ctx.saved_tensors
        gx, gy, gz = grad.unbind(-1)
        gx = gx + torch.linalg.cross(y, gz)  # z = x × y
        gy = gy + torch.linalg.cross(gz, x)
        g_free = (gy - y * (y * gy).sum(-1, keepdim=True)) / y_norm  # y = y_free / |y_free|
        x_g = (x * g_free).sum(-1, keepdim=True)
        gb = g_free - x * x_g  # y_free = b - (x . b) x
        # b = y_free + (x . b) x: its part along x drops out of ga below, so b's gradient term is y_free (x . g)
        gx = gx - x_b * g_free - y * (y_norm * x_g)
        ga = (gx - x * (x * gx).sum(-1, keepdim=True)) / a_norm  # x = a / |a|
        return torch.cat([ga, gb], -1)


def rotation_6d_to_matrix(r6: torch.Tensor) -> torch.Tensor:
    """Continuous 6D rotation representation (..., 6) -> (..., 3, 3): Gram-Schmidt on the two
    columns (a, b): x = a / |a|, y = the part of b across x, normalised, z = x × y."""
    return _GramSchmidt.apply(r6)


def matrix_to_rotation_6d(R: torch.Tensor) -> torch.Tensor:
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


# ---------------------------------------------------------------------------
# Body fitting (PROX-D, multi-view): shapes (B frames, C views, K keypoints,
# P points per view, N fitting vertices).
# ---------------------------------------------------------------------------

def keypoint_reprojection(
    projected: torch.Tensor,
    observed: torch.Tensor,
    confidence: torch.Tensor,
    joint_weights: torch.Tensor,
    scale_px: torch.Tensor,
    rho: float,
) -> torch.Tensor:
    """E_J, sum_v sum_k w_k c_vk^2 rho(|Pi_v(J_k) - x_vk| / s_v), (B, C, K, 2) -> (B,).

    `scale_px` (C,) turns pixels into a common unit (pixels at a 1000 px focal
    length) so views of other resolutions weigh alike; rho is Geman-McClure
    with `rho` in those units, so a wrong detection costs at most w c^2.
    Scaled by rho^2 (SMPLify's GMoF), so small residuals cost their square in
    those pixels. Keypoints behind a camera must come with confidence 0."""
    residual = (projected - observed).norm(dim=-1) / scale_px[:, None]  # (B, C, K)
    weight = joint_weights * confidence**2
    return (weight * geman_mcclure(residual, rho)).sum((1, 2)) * rho**2


def nearest_visible_vertices(points: torch.Tensor, vertices: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """For each point (B, C, P, 3), the index (B, C, P) of the nearest vertex (B, N, 3) that its view
    sees (visible (B, C, N)); -1 where the view sees none. No gradient: E_D's correspondences.
    A k-d tree per frame and view (scipy): a dense distance matrix costs 20x more."""
    B, C = visible.shape[:2]
    every = torch.ones(points.shape[:3], dtype=torch.bool, device=points.device)
    per_view = vertices[:, None].expand(B, C, *vertices.shape[1:])
    return nearest_per_view(points, every, per_view, visible, np.inf).to(points.device)


def nearest_per_view(queries: torch.Tensor, query_mask: torch.Tensor, targets: torch.Tensor,
                      target_mask: torch.Tensor, max_distance: float) -> torch.Tensor:
    """Per frame and view, the index (B, C, Q) of the nearest of the masked targets (B, C, T, 3) to
    each masked query (B, C, Q, 3); -1 for unmasked queries, none within `max_distance`, or no
    target. On the CPU a k-d tree per frame and view (scipy): a dense distance matrix costs 20x
    more there. On a GPU the dense matrix (`nearest_dense`): a few kernels instead of copying to
    the CPU and B x C trees (the H100's 150-frame bench spent 14 s of 169 in the trees), and
    recordable as a CUDA graph (`optim.records_graphs`)."""
    if optim.records_graphs(queries.device):
        return nearest_dense(queries, query_mask, targets, target_mask, max_distance)
    from scipy.spatial import cKDTree

    B, C, Q, _ = queries.shape
    qs, qm = queries.detach().cpu().numpy(), query_mask.cpu().numpy()
    ts, tm = targets.detach().cpu().numpy(), target_mask.cpu().numpy()
    nearest = np.full((B, C, Q), -1, np.int64)
    for b in range(B):
        for c in range(C):
            ids, have = np.flatnonzero(qm[b, c]), np.flatnonzero(tm[b, c])
            if len(ids) and len(have):
                distance, index = cKDTree(ts[b, c, have]).query(qs[b, c, ids], distance_upper_bound=max_distance)
                found = np.isfinite(distance)
                nearest[b, c, ids[found]] = have[index[found]]
    return torch.from_numpy(nearest)


def nearest_dense(queries: torch.Tensor, query_mask: torch.Tensor, targets: torch.Tensor,
                   target_mask: torch.Tensor, max_distance: float, max_entries: int = 1 << 26) -> torch.Tensor:
    """`nearest_per_view` by the dense distance matrix, in chunks of frames of at most
    `max_entries` (query, target) pairs. The squared distances up to each query's own |q|^2,
    |t|^2 - 2 q.t, are one batched matrix product (with torch.cdist's exact mode, slow on GPUs,
    the H200's 132 s bench waited 26 s on the refresh); coordinates are centred per frame and
    view first, so fp32 rounding (about 1e-7 m^2) decides only near-exact ties, and the chosen
    target's exact distance is what `max_distance` bounds."""
    B, C, Q, _ = queries.shape
    T = targets.shape[2]
    nearest = torch.full((B, C, Q), -1, dtype=torch.long, device=queries.device)
    step = max(1, max_entries // max(C * Q * T, 1))
    for a in range(0, B, step):
        q_mask, t_mask = query_mask[a:a + step], target_mask[a:a + step]
        q = torch.where(q_mask[..., None], queries[a:a + step].detach(), 0)
        t = torch.where(t_mask[..., None], targets[a:a + step].detach(), 0)
        n = q.shape[0]
        centre = q.sum(2, keepdim=True) / q_mask.sum(2).clamp(min=1)[..., None, None]
        q, t = q - centre, t - centre
        far = torch.where(t_mask, (t * t).sum(-1), torch.inf)  # (n, C, T): unmasked targets out of reach
        partial = torch.baddbmm(far.reshape(n * C, 1, T), q.reshape(n * C, Q, 3),
                                t.reshape(n * C, T, 3).transpose(1, 2), alpha=-2.0)  # (nC, Q, T)
        best, index = partial.view(n, C, Q, T).min(-1)
        chosen = t.gather(2, index[..., None].expand(n, C, Q, 3))
        keep = q_mask & torch.isfinite(best) & ((q - chosen).norm(dim=-1) <= max_distance)
        nearest[a:a + step] = torch.where(keep, index, -1)
    return nearest


def nearest_points(vertices: torch.Tensor, visible: torch.Tensor, points: torch.Tensor, point_valid: torch.Tensor,
                   max_distance: float) -> torch.Tensor:
    """For each fitting vertex (B, N, 3) a view sees (visible (B, C, N)), the index (B, C, N) of that
    view's nearest segmented point (B, C, P, 3); -1 where the view sees it not, has no point, or the
    nearest is farther than `max_distance` (a part the object hides has no points of its own).
    No gradient: the model-to-data half of E_D's correspondences."""
    B, C = visible.shape[:2]
    per_view = vertices[:, None].expand(B, C, *vertices.shape[1:])
    return nearest_per_view(per_view, visible, points, point_valid, max_distance).to(points.device)


@dataclass
class DepthPairs:
    """E_D's correspondences, both halves, as one flat list of K (fitting vertex, point) pairs:
    each segmented point with the nearest fitting vertex its view sees (data to model), and each
    fitting vertex a view sees with that view's nearest point (model to data). Built without
    gradient once per refresh (`depth_pairs`); the term then touches these pairs only, not every
    (frame, view, vertex) of which most are hidden."""

    vertex: torch.Tensor  # (K,) row of the vertex in the (B * N, 3) fitting vertices
    frame: torch.Tensor  # (K,)
    point: torch.Tensor  # (3, K) the point, one row per coordinate
    normal: torch.Tensor  # (3, K) the vertex's unit normal
    weight: torch.Tensor  # (K,) 1 / pairs of its (frame, view, half), times the half's weight (0: an empty slot)
    batch_size: int

    def tensors(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "batch_size"}

    def to(self, device) -> "DepthPairs":
        return dataclasses.replace(self, **{name: t.to(device) for name, t in self.tensors().items()})

    def assign(self, other: "DepthPairs") -> None:
        """Take `other`'s pairs in place (a recorded CUDA graph reads these tensors); as many pairs
        as `other` (`depth_pairs` with compact off: one per slot)."""
        for name, t in self.tensors().items():
            t.copy_(getattr(other, name))

    def refreshed(self, new: "DepthPairs", in_place: bool) -> "DepthPairs":
        """The pairs after a refresh: `new`, or these holding `new`'s values (`assign`) where a
        recorded graph reads them (`in_place`)."""
        if not in_place:
            return new
        self.assign(new)
        return self


def depth_pairs(points: torch.Tensor, point_valid: torch.Tensor, normals: torch.Tensor, nearest: torch.Tensor,
                nearest_to_vertices: torch.Tensor | None = None, model_to_data: float = 1.0,
                compact: bool | None = None) -> DepthPairs:
    """`DepthPairs` from the points (B, C, P, 3) and their mask, the fitting vertices' normals
    (B, N, 3), `nearest` (B, C, P) from `nearest_visible_vertices` and `nearest_to_vertices`
    (B, C, N) from `nearest_points` (None: the model-to-data half is off), that half weighted
    `model_to_data`. Each half is a mean per view over its pairs, as in PROX's E_D.

    `compact` (default: where no graph is recorded, `optim.records_graphs`) lists the pairs that
    exist only; otherwise every (frame, view, point) and (frame, view, vertex) slot is a pair, those
    without a partner weighted 0: a GPU then neither waits for `nonzero` nor sees the count change
    between refreshes (a CUDA graph of the energy reads the pairs in place, `DepthPairs.assign`)."""
    B, N = normals.shape[:2]
    if compact is None:
        compact = not optim.records_graphs(points.device)

    def half(mask, vertex_of, point_of, weight):
        count = mask.sum(-1).clamp(min=1).to(points.dtype)  # (B, C) pairs per view
        if compact:
            b, c, i = torch.nonzero(mask, as_tuple=True)
            return b * N + vertex_of(b, c, i), b, point_of(b, c, i), weight / count[b, c]
        b, c, i = (x.reshape(-1) for x in torch.meshgrid(*(torch.arange(n, device=mask.device) for n in mask.shape),
                                                          indexing="ij"))
        return (b * N + vertex_of(b, c, i).clamp(min=0), b, point_of(b, c, i),
                (mask / count[..., None]).reshape(-1) * weight)

    halves = [half(point_valid & (nearest >= 0), lambda b, c, p: nearest[b, c, p],
                   lambda b, c, p: points[b, c, p], 1.0)]
    if nearest_to_vertices is not None and model_to_data > 0:
        halves.append(half(nearest_to_vertices >= 0, lambda b, c, n: n,
                           lambda b, c, n: points[b, c, nearest_to_vertices[b, c, n].clamp(min=0)], model_to_data))
    vertex, frame, point, weight = (torch.cat(parts) for parts in zip(*halves))
    normal = normals.reshape(B * N, 3)[vertex]
    return DepthPairs(vertex, frame, point.t().contiguous(), normal.t().contiguous(), weight, B)


def depth_point_to_plane(vertices: torch.Tensor, pairs: DepthPairs, scale: float,
                         tangent_weight: float = 0.25) -> torch.Tensor:
    """E_D, both halves, (B, N, 3) fitting vertices -> (B,): per view the mean over its segmented
    points of rho(distance to the nearest vertex the view sees), plus per view the mean over the
    vertices it sees of rho(distance to the nearest point), summed over views.

    The data-to-model half alone lets a part of the surface hang where the sensor saw nothing (a
    stooped torso 5 cm below its points, whose points then match the arms and thighs): every
    visible vertex should have data on it. The distance is point-to-plane at the vertex plus
    `tangent_weight` times the in-plane offset, so the term does not pull the surface towards the
    sparse vertex positions (the fitting subsample is ~3 cm apart); with a unit normal n and
    offset o that is (1 - w) (o.n)^2 + w |o|^2. rho is Geman-McClure with `scale` metres (points
    of the object, other people or flying pixels saturate), scaled by scale^2 so a small offset
    costs its square in metres^2. Coordinates are written out: sums over a size-3 axis are slow
    on the CPU."""
    v = vertices.reshape(-1, 3).t().index_select(1, pairs.vertex)  # (3, K)
    offset = pairs.point - v
    along = offset[0] * pairs.normal[0] + offset[1] * pairs.normal[1] + offset[2] * pairs.normal[2]
    squared = ((1 - tangent_weight) * along * along
               + tangent_weight * (offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2]))
    rho = squared / (squared + scale * scale) * pairs.weight
    return vertices.new_zeros(pairs.batch_size).index_add(0, pairs.frame, rho) * scale**2


def sphere_self_penetration(centres: torch.Tensor, radii: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """Self-penetration approximated by spheres on the body's segments, (B, S, 3) -> (B,):
    sum over non-adjacent sphere pairs (Q, 2) of relu(r_i + r_j - |c_i - c_j|)^2 in metres^2."""
    gap = (centres[:, pairs[:, 0]] - centres[:, pairs[:, 1]]).norm(dim=-1)  # (B, Q)
    overlap = torch.relu(radii[pairs[:, 0]] + radii[pairs[:, 1]] - gap)
    return (overlap * overlap).sum(-1)



# ---------------------------------------------------------------------------
# Global body-object stage: shapes (W frames, N body vertices, M object points).
# Signed distances come from the object's SDF (positive outside, metres).
# ---------------------------------------------------------------------------

def object_point_to_surface(signed_distance: torch.Tensor, valid: torch.Tensor, scale: float) -> torch.Tensor:
    """E_O, the mean over a frame's observed object points of rho(distance to the posed object's
    surface), (W, P) -> (W,). Geman-McClure with `scale` metres (hand pixels that slipped into the
    object mask saturate), scaled by scale^2 so a small offset costs its square in metres^2."""
    rho = geman_mcclure(signed_distance, scale) * valid
    return rho.sum(-1) / valid.sum(-1).clamp(min=1) * scale**2


def pose_anchor(points: torch.Tensor, reference: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Mean squared distance of posed points (W, M, 3) to where the per-frame fit put them, times a
    per-frame weight (W,) (its confidence; 0 where it has no trusted pose) -> (W,), metres^2."""
    return (points - reference).pow(2).sum(-1).mean(-1) * weight


def body_object_interpenetration(signed_distance: torch.Tensor) -> torch.Tensor:
    """E_P, sum over body vertices of their depth inside the object squared, (W, N) -> (W,), metres^2."""
    return torch.relu(-signed_distance).pow(2).sum(-1)


def contact_chamfer(signed_distance: torch.Tensor, touching: torch.Tensor, count: int) -> torch.Tensor:
    """E_C, for a body contact region that touches the object in a frame: the mean squared gap
    between the object surface and the region's `count` vertices nearest to it (the patch that
    should lie on the surface), (W, N) region vertices, touching (W,) bool -> (W,), metres^2.
    Depth inside is E_P's business, so only gaps outside count."""
    nearest = torch.topk(signed_distance, min(count, signed_distance.shape[-1]), dim=-1, largest=False).values
    return torch.relu(nearest).pow(2).mean(-1) * touching


def hand_contact(hand_vertices: torch.Tensor, grasp_points: torch.Tensor, grasping: torch.Tensor,
                 count: int) -> torch.Tensor:
    """E_C', a grasping hand's palm on the object's graspable parts: the mean squared distance of
    the `count` hand-region vertices (W, N, 3) nearest to the graspable points (W, G, 3) to their
    nearest graspable point, in frames where the hand grasps (W,) -> (W,), metres^2.

    The pairs are chosen without gradient and only they are measured with it: the same value and
    gradient (a minimum's flows to its argument only) without differentiating all N x G distances."""
    with torch.no_grad():
        distance, nearest_point = torch.cdist(hand_vertices, grasp_points).min(-1)  # (W, N)
        chosen = torch.topk(distance, min(count, distance.shape[-1]), dim=-1, largest=False).indices  # (W, k)
    vertices = hand_vertices.gather(1, chosen[..., None].expand(-1, -1, 3))
    points = grasp_points.gather(1, nearest_point.gather(1, chosen)[..., None].expand(-1, -1, 3))
    return (vertices - points).pow(2).sum(-1).mean(-1) * grasping


def ground_penetration(points: torch.Tensor, ground_point: torch.Tensor, ground_normal: torch.Tensor) -> torch.Tensor:
    """E_G, sum over points (W, N, 3) of their depth below the ground plane squared -> (W,), metres^2."""
    height = (points - ground_point) @ ground_normal
    return torch.relu(-height).pow(2).sum(-1)


def ground_support(points: torch.Tensor, ground_point: torch.Tensor, ground_normal: torch.Tensor,
                   lowest: int = 5, reach_m: float = 0.3) -> torch.Tensor:
    """E_S: a person handling objects stands on the floor. Per frame (W,), the height of the body's
    lowest points above the ground plane squared (mean of the `lowest` lowest of `points` (W, N, 3),
    metres^2): zero on or below the floor (E_G's side), and zero when higher than `reach_m` (sitting on
    something, on a step, in the air: not a hovering fit)."""
    height = (points - ground_point) @ ground_normal  # (W, N)
    bottom = torch.topk(height, min(lowest, height.shape[-1]), dim=-1, largest=False).values.mean(-1)
    return torch.where(bottom < reach_m, torch.relu(bottom).pow(2), torch.zeros_like(bottom))


def vertex_acceleration(points: torch.Tensor, fps: float, weights: torch.Tensor | None = None) -> torch.Tensor:
    """E_A on the object's points, and the plain smoothness term on body vertices: per frame the
    mean squared acceleration of points (W, M, 3) by second differences -> (W,), (m/s^2)^2; the
    first and last frame have none (0). `weights` (M,), mean 1: each point's share of the mean."""
    acc = (points[2:] - 2 * points[1:-1] + points[:-2]) * fps**2
    squared = acc.pow(2).sum(-1)
    per_frame = (squared if weights is None else squared * weights).mean(-1)
    return torch.nn.functional.pad(per_frame, (1, 1))


def flight_parabola(centres: torch.Tensor, episode: torch.Tensor, times: torch.Tensor,
                    gravity: torch.Tensor) -> torch.Tensor:
    """GraviCap's free-flight term: per frame the squared distance of the object's centre of mass
    (W, 3) to the parabola p0 + v0 t + 0.5 g t^2 that fits best, with g (3,) fixed, the frames of
    each flight episode (episode (W,) long: its id, -1 outside any flight) in the window, times
    (W,) seconds. p0, v0 are solved in closed form per episode (linear least squares on
    centre - 0.5 g t^2), so the term is differentiable in the centres and only the trajectory's
    departure from a gravity parabola costs -> (W,), metres^2 (0 outside flights and for
    episodes with fewer than 3 frames in the window)."""
    out = torch.zeros(len(centres), dtype=centres.dtype, device=centres.device)
    for e in torch.unique(episode[episode >= 0]).tolist():
        sel = torch.nonzero(episode == e)[:, 0]
        if len(sel) < 3:
            continue
        t = (times[sel] - times[sel[0]]).to(centres)[:, None]  # (n, 1)
        y = centres[sel] - 0.5 * t * t * gravity.to(centres)  # (n, 3): p0 + v0 t when on the parabola
        dt, dy = t - t.mean(0), y - y.mean(0)
        v0 = (dt * dy).sum(0) / (dt * dt).sum(0).clamp(min=1e-12)
        residual = dy - dt * v0
        out = out.index_put((sel,), residual.pow(2).sum(-1))
    return out
