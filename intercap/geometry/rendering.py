"""Differentiable silhouette and depth rendering of a rigid mesh, in pure PyTorch.

Used by the object stage (E_O): render the object's soft silhouette and depth in
a crop around it in every view and compare them with the observed mask and depth
resampled to the same grid (`crop_observation`). CPU and CUDA, batched over B
frames x C views, no compiled extension (no pytorch3d / nvdiffrast).

    topo = MeshTopology.from_faces(faces)                     # once per mesh
    crops = object_crops(vertices, cameras, (64, 64), 0.2)    # once per frame, then fixed
    out = render(vertices, topo, cameras, crops, (64, 64), sigma=0.6)
    mask = crop_observation(masks, crops[0], (64, 64), "area")      # (C, 64, 64)
    depth = crop_observation(depths, crops[0], (64, 64), "nearest")
    seen = crop_in_image(crops, cameras, (64, 64))            # where observations exist

Method
------
1. Vertices go through the real camera model (`cameras.project`, lens distortion
   included); triangles are rasterised in pixel space with straight edges between
   the projected vertices. Exact without distortion; with it, the image of a
   straight edge is really a curve: under the test lens (k1 = -0.25) a 75 px box
   edge bows by 2.8 px but a 12 px one by 0.07 px, so subdivide meshes with long
   edges (`trimesh.remesh.subdivide_to_size`; the project's objects already are).
2. Hard pass, no autograd. Facing comes from the projected winding (exactly what
   bounds the union of the straight-edged triangles; closed outward-wound meshes
   are culled to their front faces, `cull_backfaces=False` for open ones). Each
   triangle is cut into scanlines (rows, or columns for tall triangles) whose pixel
   spans are solved from its three edge inequalities, and a z-buffer (one
   `scatter_reduce` of packed (depth, face) keys) keeps the front face of every
   covered pixel centre. Work is the covered area plus one entry per line; never
   pixels x faces.
3. Depth (differentiable): camera z of that face at the pixel centre, from the
   plane of 1/z (linear in the image: perspective-correct), metres like Kinect
   depth, 0 where nothing is covered. Its gradient moves the surface under a fixed
   coverage; the occluding rim is the silhouette's job.
4. Soft silhouette (differentiable): S = sigmoid(signed distance to the outline /
   sigma), rescaled to be exactly 0 or 1 beyond `band_sigmas * sigma` pixels. The
   outline of the union of projected triangles lies on the contour edges (a drawn
   face on one side, a culled/missing one on the other), O(sqrt(F)) of them. They
   are cut into pieces about one band long; every piece tests a fixed window of
   pixels around it, the nearest piece per pixel is chosen without autograd and
   its distance recomputed with autograd, so gradients reach exactly the contour
   vertices. Sign: + where the pixel centre is covered. A piece whose outer side
   (one pixel beyond its midpoint) is covered lies inside the silhouette (a chair
   leg seen against the seat): covered pixels ignore it, so the interior is not
   dented (a few pixels near T-junctions can read 0.9-0.99).
   Rejected: SoftRas-style 1 - prod_f (1 - sigmoid(d_f / sigma)) over faces. Every
   edge between two faces reads 0.75 on it, and with hundreds of faces a few output
   pixels wide the whole interior reads about 0.8 (a biased loss); and it needs
   (pixel, face) pairs around every face, the cost that made this module's first
   version (pixels enumerated per face bounding box, no scanlines) take 80-240 ms
   for 4 views at 96x96 on long thin triangles.
   sigma is in output pixels: ~0.3 approximates area coverage (the crop's box
   filter), 0.5-1.5 gives a smoother loss.
5. Crops: a view renders an (h, w) grid over a box (x0, y0, x1, y1) in continuous
   full-image pixel coordinates (pixel centres at integers: the whole native image
   is (-0.5, -0.5, W - 0.5, H - 0.5)); output pixel (i, j) is centred at
   (x0 + (j + 0.5) (x1 - x0) / w, y0 + (i + 0.5) (y1 - y0) / h). `object_crops`
   makes square-pixel boxes around the projected vertices; keep them fixed while
   optimising a frame. `crop_observation`: 'area' (exact box filter; masks become
   the covered fraction, matching sigma ~0.3), 'nearest' (depth, no mixing across
   edges) or 'min' (smallest non-zero depth in the footprint); 0 = missing stays 0,
   outside the image reads 0 (`crop_in_image` says where).

Choice by measurement (`tools/bench_rendering.py`; 2-core CPU shared with other
jobs, so 1 thread and thread CPU time; torch 2.13, float32, 640x576 views with
rational distortion, object ~2 m away, sigma 0.6; ms per call)
    crop 64x64      fwd 1 view  f+b 1 view  fwd 4 views  f+b 4 views  peak MB (4v)
    box, 12 faces        4.4        6.1         5.2          7.2          2.5
    cylinder, 512        4.9        6.7         7.0          9.3          4.1
    box, 2048            5.1        7.1         7.4         10.4          4.7
    chair, 2400          5.3        7.4        10.4         13.4          5.7
    crop 96x96, f+b 4 views: 8.7 / 11.2 / 12.7 / 15.6 ms, 4.4-6.5 MB
    full native 640x576, 4 views, box 2048: 53 ms, 35 MB
About 4 ms of a call is fixed cost (~1500 small tensor ops), so batching views
(and frames: B x C in one call) is nearly free, and cost grows only weakly with
the face count: no mesh simplification is needed up to a few thousand faces.
Memory: `max_pairs`-sized chunks plus O(B C h w) buffers. With 2 torch threads on
a loaded machine every op can be 10x slower (thread hand-offs): the tracker
should run torch with 1 thread there. The code is device-agnostic.

Fixed shapes (`capacity=Capacity(...)`, the object fit on CUDA): the scanlines, their
pixels, the contour edges and the outline pieces go into slots of fixed number (a
cumulative sum and `searchsorted` instead of `nonzero` / `repeat_interleave`), every
face and pixel is kept with a mask, and nothing is read back from the device, so a
CUDA graph can record a render and replay it while the pose moves. The result is the
compact render's (coverage and depth bit for bit, the silhouette to float rounding)
as long as `RenderOutput.needed` fits the capacity; size it with `Capacity.fitting`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from intercap.geometry.cameras import Cameras, project, world_to_camera

DEFAULT_SIZE = (64, 64)  # output crop (h, w): ~10 ms forward + backward for 4 views of a 500-face object
_NO_KEY = torch.iinfo(torch.int64).max
# `max_pairs` by default: small chunks stay in the CPU allocator's cache; a GPU takes a frame in one
MAX_PAIRS = {"cpu": 1 << 15, "cuda": 1 << 22}
_DEPTH_KEY_SCALE = 1e5  # z quantised to 10 um for the z-buffer's tie order only
_DIST_KEY_SCALE = 1e4  # edge distances quantised to 1e-4 px for the nearest-edge choice only


@dataclass(frozen=True)
class MeshTopology:
    """Faces and edge adjacency of a triangle mesh, computed once per mesh.

    faces: (F, 3) long; edges: (E, 2) long unique undirected edges;
    face_edges: (F, 3) index of edge k = (faces[f, k], faces[f, k+1 mod 3]);
    opposite: (F, 3) the vertex opposite that edge (faces[f, k+2 mod 3]);
    faces_per_edge: (E,) how many faces share each edge (1 = mesh boundary);
    vertices: how many vertices the faces index (the largest index + 1), kept as a
    number so that `render` checks its input without reading the GPU.
    """

    faces: torch.Tensor
    edges: torch.Tensor
    face_edges: torch.Tensor
    opposite: torch.Tensor
    faces_per_edge: torch.Tensor
    vertices: int

    @classmethod
    def from_faces(cls, faces) -> "MeshTopology":
        faces = torch.as_tensor(faces).long()
        if faces.dim() != 2 or faces.shape[1] != 3:
            raise ValueError(f"rendering: faces must be (F, 3) vertex indices, got {tuple(faces.shape)}")
        if faces.numel() and int(faces.min()) < 0:
            raise ValueError("rendering: faces contain negative vertex indices")
        nxt = faces.roll(-1, dims=1)  # (F, 3) v_{k+1}
        lo, hi = torch.minimum(faces, nxt), torch.maximum(faces, nxt)
        n = int(faces.max()) + 1 if faces.numel() else 1
        keys = (lo * n + hi).reshape(-1)  # (3F,)
        uniq, inverse = torch.unique(keys, return_inverse=True)
        edges = torch.stack([uniq // n, uniq % n], dim=-1)  # (E, 2)
        return cls(
            faces=faces,
            edges=edges,
            face_edges=inverse.reshape(-1, 3),
            opposite=faces.roll(-2, dims=1),
            faces_per_edge=torch.bincount(inverse, minlength=len(uniq)),
            vertices=n if faces.numel() else 0,
        )

    def to(self, device) -> "MeshTopology":
        return MeshTopology(**{k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in vars(self).items()})


@dataclass
class RenderOutput:
    """silhouette (B, C, h, w) soft, in [0, 1]; depth (B, C, h, w) camera z in
    metres, 0 where no surface; coverage (B, C, h, w) bool, pixel centre covered
    (where depth is defined); crops (B, C, 4) the boxes rendered (see
    `crop_in_image` for which output pixels lie inside the camera image)."""

    silhouette: torch.Tensor
    depth: torch.Tensor
    coverage: torch.Tensor
    crops: torch.Tensor
    needed: torch.Tensor  # (4,) long: lines, pixels, contour edges, outline pieces enumerated (wanted, with a `Capacity`)


@dataclass(frozen=True)
class Capacity:
    """Fixed sizes for `render`'s data-dependent tensors: slots for the triangles' scanlines,
    their pixels, the contour edges and the outline pieces. With them a render waits on nothing
    and keeps its shapes from call to call, so that a CUDA graph can record it (the object fit,
    `optim.gradient_evaluator`). What does not fit is lost: check `RenderOutput.needed` with
    `holds` and render again with `fitting(needed)`."""

    lines: int
    pixels: int
    contours: int
    pieces: int

    @classmethod
    def fitting(cls, needed, slack: float = 0.5, quantum: int = 1024) -> "Capacity":
        """Room for the counts `needed` (lines, pixels, contours, pieces) and `slack` more, rounded
        up to `quantum` slots: a pose moved a little still fits, and the shapes repeat."""
        return cls(*(max(quantum, -(-int(n * (1 + slack)) // quantum) * quantum) for n in needed))

    def holds(self, needed) -> bool:
        """Whether counts `needed` (a `RenderOutput.needed`, read here) fit."""
        return all(int(n) <= c for n, c in zip(needed.tolist(), (self.lines, self.pixels, self.contours, self.pieces)))


# ----------------------------------------------------------------------------- crops


def _camera_frame(vertices_world: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """(B, V, 3) world -> (B, C, V, 3) camera-frame points."""
    B, V, _ = vertices_world.shape
    p = world_to_camera(vertices_world.reshape(B * V, 3), cameras.T_cam_from_world)  # (C, BV, 3)
    return p.reshape(len(cameras), B, V, 3).transpose(0, 1)


def _valid_vertices(p_cam: torch.Tensor, dist: torch.Tensor, znear: float, max_radius: float) -> torch.Tensor:
    """Camera-frame points (B, C, V, 3), distortion (C, 8) -> (B, C, V) bool: in front
    of the camera (z > znear) and inside the region where the lens model is
    one-to-one: |(x/z, y/z)| < max_radius and the radial map r -> r * radial(r)
    still increasing (beyond its fold a polynomial distortion maps far-away
    points back into the image)."""
    z = p_cam[..., 2]
    ok = torch.isfinite(p_cam).all(-1) & (z > znear)
    xy = p_cam[..., :2] / torch.where(ok, z, torch.ones_like(z))[..., None]
    r2 = (xy * xy).sum(-1)  # (B, C, V)
    ok &= r2 < max_radius**2
    # (without distortion this holds everywhere; it is checked anyway, as asking would wait on a GPU)
    k1, k2, k3, k4, k5, k6 = (dist[None, :, i, None] for i in (0, 1, 4, 5, 6, 7))  # (1, C, 1)
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    # d(r * num / den) / dr = (num den + 2 r2 (dnum den - num dden)) / den^2 > 0, with den > 0
    return ok & (den > 0) & (num * den + 2 * r2 * (dnum * den - num * dden) > 0)


def object_crops(
    vertices_world: torch.Tensor,
    cameras: Cameras,
    size=DEFAULT_SIZE,
    margin: float = 0.1,
    pad_px: float = 4.0,
    znear: float = 0.05,
    max_radius: float = 3.0,
) -> torch.Tensor:
    """(B, V, 3) or (V, 3) world vertices -> crops (B, C, 4) x0, y0, x1, y1 in pixels.

    The box of the projected (valid) vertices, widened by `margin` (fraction of
    its half-size) plus `pad_px` output pixels on each side, then grown on one
    axis so output pixels are square for the (h, w) `size`. A view that sees no
    vertex gets a native-resolution box at its image centre (renders empty).
    """
    with torch.no_grad():
        verts = vertices_world if vertices_world.dim() == 3 else vertices_world[None]
        cameras = _cameras_like(cameras, verts)
        B, V, _ = verts.shape
        C = len(cameras)
        h, w = _size(size)
        pix, _ = project(verts.reshape(B * V, 3), cameras)  # (C, BV, 2)
        pix = pix.reshape(C, B, V, 2).transpose(0, 1)  # (B, C, V, 2)
        valid = _valid_vertices(_camera_frame(verts, cameras), cameras.dist, znear, max_radius)
        valid = valid[..., None]  # (B, C, V, 1)
        inf = torch.full_like(pix, float("inf"))
        lo = torch.where(valid, pix, inf).amin(2)  # (B, C, 2)
        hi = torch.where(valid, pix, -inf).amax(2)
        seen = valid.any(2).squeeze(-1)  # (B, C)
        centre = torch.where(seen[..., None], (lo + hi) / 2, torch.zeros_like(lo))
        half = torch.where(seen[..., None], (hi - lo) / 2 * (1 + margin), torch.zeros_like(lo))
        out = torch.tensor([w, h], dtype=pix.dtype, device=pix.device)
        shrink = (1 - 2 * pad_px / out).clamp(min=0.1)  # room left for the object after the padding
        scale = (2 * half / (out * shrink)).amax(-1)  # (B, C) full-image pixels per output pixel
        scale = torch.where(seen & (scale > 1e-6), scale, torch.ones_like(scale))
        image_centre = torch.stack([(cameras.width - 1) / 2, (cameras.height - 1) / 2], -1).to(pix)  # (C, 2)
        centre = torch.where(seen[..., None], centre, image_centre[None].expand_as(centre))
        half = scale[..., None] * out / 2  # (B, C, 2)
        return torch.cat([centre - half, centre + half], -1)


def full_image_crops(cameras: Cameras, batch: int = 1) -> torch.Tensor:
    """(B, C, 4) boxes covering each whole image at native resolution."""
    w = cameras.width.to(cameras.K.dtype)
    h = cameras.height.to(cameras.K.dtype)
    box = torch.stack([torch.full_like(w, -0.5), torch.full_like(h, -0.5), w - 0.5, h - 0.5], -1)
    return box[None].expand(batch, -1, -1).clone()


def _size(size) -> tuple[int, int]:
    h, w = (int(size), int(size)) if isinstance(size, int) else (int(size[0]), int(size[1]))
    if h < 1 or w < 1:
        raise ValueError(f"rendering: output size must be positive (h, w), got {size}")
    return h, w


def _cameras_like(cameras: Cameras, ref: torch.Tensor) -> Cameras:
    if cameras.K.dtype != ref.dtype or cameras.K.device != ref.device:
        return cameras.to(device=ref.device, dtype=ref.dtype)
    return cameras


def _crop_scale(crops: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(N, 4) boxes -> (N, 2) full-image pixels per output pixel along x, y."""
    return torch.stack([(crops[:, 2] - crops[:, 0]) / w, (crops[:, 3] - crops[:, 1]) / h], -1).clamp(min=1e-9)


def crop_in_image(crops: torch.Tensor, cameras: Cameras, size=DEFAULT_SIZE) -> torch.Tensor:
    """(B, C, 4) or (C, 4) boxes -> (B, C, h, w) or (C, h, w) bool: output pixel centre
    inside the camera's image (outside it there is no observation to compare with)."""
    h, w = _size(size)
    squeeze = crops.dim() == 2
    crops = crops[None] if squeeze else crops
    B, C = crops.shape[:2]
    box = crops.reshape(B * C, 4)
    s = _crop_scale(box, h, w)
    u = box[:, 0, None] + (torch.arange(w, device=box.device, dtype=box.dtype) + 0.5) * s[:, 0, None]  # (BC, w)
    v = box[:, 1, None] + (torch.arange(h, device=box.device, dtype=box.dtype) + 0.5) * s[:, 1, None]  # (BC, h)
    W = cameras.width.to(box.dtype).repeat(B)[:, None]
    H = cameras.height.to(box.dtype).repeat(B)[:, None]
    ok_u = (u >= -0.5) & (u < W - 0.5)
    ok_v = (v >= -0.5) & (v < H - 0.5)
    out = (ok_v[:, :, None] & ok_u[:, None, :]).reshape(B, C, h, w)
    return out[0] if squeeze else out


# ----------------------------------------------------------------------------- span enumeration
# Hot paths gather with index_select on 1D tensors: on CPU it is 4-10x faster than
# advanced indexing (t[idx]) for the 10^4-10^5 element gathers done here.


def _take(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    return t.index_select(0, idx)


def _take_cols(table: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Gather columns of a (k, M) table -> (k, P); each row stays contiguous, which keeps
    the following elementwise maths on the fast (vectorised) path."""
    return table.index_select(1, idx)


def _expand(counts: torch.Tensor, capacity: int | None = None):
    """counts (M,) long -> (owner (P,), local (P,), used): owner m repeated counts[m] times, local
    0..counts[m]-1. P = sum(counts), read back from the device, and used is None; or, with
    `capacity` (M >= 1), P = capacity slots and no wait on the device: used (P,) marks the
    sum(counts) slots in use, the rest repeat the last owner and must be masked."""
    if capacity is None:
        P = int(counts.sum()) if counts.numel() else 0
        owner = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts, output_size=P)
        first = counts.cumsum(0) - counts
        return owner, torch.arange(P, device=counts.device) - _take(first, owner), None
    cum = counts.cumsum(0)
    slot = torch.arange(capacity, device=counts.device)
    owner = torch.searchsorted(cum, slot, right=True).clamp(max=counts.numel() - 1)
    return owner, slot - (_take(cum, owner) - _take(counts, owner)), slot < cum[-1:]


def _span_pixels(s_lo: torch.Tensor, s_hi: torch.Tensor, max_pairs: int, capacity: int | None = None):
    """Lines with inclusive pixel spans [s_lo, s_hi] (R,) -> yields (line (P,), s (P,), used) in
    chunks of about `max_pairs` pixels (a line is never split), bounding memory; with
    `capacity`, one chunk of that many slots, `used` marking those in use (`_expand`)."""
    counts = (s_hi - s_lo + 1).clamp(min=0)
    if capacity is not None:
        line, local, used = _expand(counts, capacity)
        yield line, _take(s_lo, line) + local, used
        return
    if counts.numel() == 0:
        return
    cum = counts.cumsum(0)
    total = int(cum[-1])
    start, done = 0, 0
    while start < counts.numel() and done < total:
        if total - done <= max_pairs:
            end = counts.numel()
        else:
            end = max(int(torch.searchsorted(cum, done + max_pairs, right=True)), start + 1)
        line, local, _ = _expand(counts[start:end])
        line = line + start
        yield line, _take(s_lo, line) + local, None
        done = int(cum[end - 1])
        start = end


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """2D cross product a_x b_y - a_y b_x over the last axis."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


# ----------------------------------------------------------------------------- hard passes (no autograd)

_SPAN_EPS = 1e-4  # pixels: spans are widened by this so a pixel centre on a shared edge is never lost


def _rasterize(tri, grad, inv_z, view, N, h, w, max_pairs, capacity=None, drawn=None):
    """Hard z-buffer over M triangles: tri (M, 3, 2) crop-grid vertices, grad (M, 3, 2)
    barycentric gradients (b_k(p) = [k == 0] + grad_k . (p - tri[:, 0])), inv_z (M, 3) =
    (d/dx, d/dy, value at vertex 0) of 1/z, view (M,) in [0, N) -> keys (N*h*w,) long:
    for a covered pixel, quantised depth * M + index of its front-most triangle;
    _NO_KEY where nothing covers it; and how many lines and pixels it enumerated (0-dim).
    `drawn` (M,) bool: only these triangles are drawn. `capacity` (a `Capacity`): lines and
    pixels go into slots of that fixed number (no wait on the device; what does not fit is
    lost, which the counts returned tell).

    Scanline enumeration: a triangle is cut into lines (rows, or columns for tall
    triangles) and each line's pixel span is solved exactly from the three edge
    inequalities (relative to vertex 0, which keeps float32 exact enough for thin
    triangles far from the crop origin). Work is the covered area plus one entry
    per line, even for long thin triangles (cylinder walls, cap fans), never
    pixels x faces."""
    M = tri.shape[0]
    hw = h * w
    keys = torch.full((N * hw,), _NO_KEY, dtype=torch.long, device=tri.device)
    if M == 0:
        return keys, keys.new_zeros(()), keys.new_zeros(())
    lo, hi = tri.amin(1), tri.amax(1)  # (M, 2)
    tall = (hi[:, 1] - lo[:, 1]) > (hi[:, 0] - lo[:, 0])  # scan columns
    t3 = tall[:, None].expand(-1, 3)

    def axes(x, y, t):  # (line axis, span axis) values per triangle
        return torch.where(t, x, y), torch.where(t, y, x)

    o_l, o_s = axes(tri[:, 0, 0], tri[:, 0, 1], tall)
    lo_l, lo_s = axes(lo[:, 0], lo[:, 1], tall)
    hi_l, hi_s = axes(hi[:, 0], hi[:, 1], tall)
    g_l, g_s = axes(grad[..., 0], grad[..., 1], t3)  # (M, 3)
    iz_l, iz_s = axes(inv_z[:, 0], inv_z[:, 1], tall)
    n_line = torch.where(tall, w, h)
    n_span = torch.where(tall, h, w)
    l_lo = torch.ceil(torch.maximum(lo_l - _SPAN_EPS, torch.full_like(lo_l, -1.0))).long().clamp(min=0)
    l_hi = torch.minimum(torch.floor(hi_l + _SPAN_EPS).clamp(max=1e6).long(), n_line - 1)
    line_counts = (l_hi - l_lo + 1).clamp(min=0)
    if drawn is not None:
        line_counts = torch.where(drawn, line_counts, 0)
    item, line, line_used = _expand(line_counts, capacity and capacity.lines)  # (R,): one entry per triangle line
    line = _take(l_lo, item) + line
    # one gather of every per-triangle number a line needs: (R, 13)
    table = torch.cat([g_s.T, g_l.T, torch.stack([o_l, o_s, lo_s, hi_s, iz_l, iz_s, inv_z[:, 2]])])  # (13, M)
    r = _take_cols(table, item)  # (13, R)
    slope, gl = r[0:3], r[3:6]
    ro_l, ro_s, rlo_s, rhi_s, riz_l, riz_s, riz_c = r[6:].unbind(0)
    dl = line.to(r.dtype) - ro_l
    rest = gl * dl
    rest[0] += 1  # b_k = slope_k (s - o_s) + rest_k >= 0 along the line
    bound = -rest / torch.where(slope == 0, torch.ones_like(slope), slope)
    inf = torch.full_like(bound, float("inf"))
    s_min = torch.where(slope > 0, bound, -inf).amax(0) + ro_s
    s_max = torch.where(slope < 0, bound, inf).amin(0) + ro_s
    outside = ((slope == 0) & (rest < -_SPAN_EPS * gl.abs())).any(0)  # an edge along the line, line beyond it
    s_min = torch.maximum(s_min, rlo_s) - _SPAN_EPS
    s_max = torch.where(outside, -inf[0], torch.minimum(s_max, rhi_s) + _SPAN_EPS)
    rn_span = _take(n_span, item)
    s_lo = torch.ceil(s_min.clamp(min=-1.0)).long().clamp(min=0)
    s_hi = torch.minimum(torch.floor(s_max.clamp(max=1e6)).long(), rn_span - 1)
    if line_used is not None:
        s_hi = torch.where(line_used, s_hi, s_lo - 1)  # slots beyond the lines: no pixels
    rt = _take(tall, item)
    per_line = torch.stack([riz_c + riz_l * dl, riz_s, ro_s])  # (3, R): 1/z = [0] + [1] (s - [2]) along the line
    ints = torch.stack([_take(view, item) * hw + torch.where(rt, line, line * w), torch.where(rt, w, 1), item])
    for row, s, used in _span_pixels(s_lo, s_hi, max_pairs, capacity and capacity.pixels):
        f = _take_cols(per_line, row)
        i = _take_cols(ints, row)
        invz = f[0] + f[1] * (s.to(f.dtype) - f[2])
        zq = (_DEPTH_KEY_SCALE / invz.clamp(min=1e-6)).round().clamp(max=1e12).long()
        at, key = i[0] + s * i[1], zq * M + i[2]
        if used is not None:
            at, key = torch.where(used, at, 0), torch.where(used, key, _NO_KEY)
        keys.scatter_reduce_(0, at, key, "amin")
    return keys, line_counts.sum(), (s_hi - s_lo + 1).clamp(min=0).sum()


def _contours(topo: MeshTopology, rendered: torch.Tensor, front: torch.Tensor, capacity: int | None = None):
    """Contour edges per view: rendered, front (N, F) bool -> (view (K,), a (K,), b (K,), third (K,))
    vertex indices of each contour edge and of a rendered face's opposite vertex (inner side),
    used (`_expand`: K = `capacity` slots, or None) and how many there are (0-dim).

    A contour edge bounds the drawn surface: some but not all of its faces are drawn
    (front/back), it is a mesh boundary, or (without culling) its drawn faces fold."""
    N = rendered.shape[0]
    fe = topo.face_edges.reshape(-1)  # (3F,)
    E = topo.edges.shape[0]
    r3 = rendered.repeat_interleave(3, dim=1)  # (N, 3F), same order as fe
    f3 = (rendered & front).repeat_interleave(3, dim=1)
    n_r = torch.zeros(N, E, dtype=torch.long, device=rendered.device).index_add_(1, fe, r3.long())
    n_f = torch.zeros(N, E, dtype=torch.long, device=rendered.device).index_add_(1, fe, f3.long())
    fpe = topo.faces_per_edge[None]
    contour = (n_r > 0) & ((n_r < fpe) | (fpe == 1) | ((n_f > 0) & (n_f < n_r)))
    opp = topo.opposite.reshape(-1)[None].expand(N, -1)  # (N, 3F)
    third = torch.full((N, E), -1, dtype=torch.long, device=rendered.device)
    third.scatter_reduce_(1, fe[None].expand(N, -1), torch.where(r3, opp, -1), "amax")
    flat = contour.reshape(-1)
    if capacity is None:
        at, used = flat.nonzero(as_tuple=True)[0], None
    else:
        at, _, used = _expand(flat.long(), capacity)
    view, e = torch.div(at, E, rounding_mode="floor"), at % E
    return (view, _take(topo.edges[:, 0], e), _take(topo.edges[:, 1], e), _take(third.reshape(-1), at), used,
            flat.sum())


def _outline_pieces(A, Bv, T, view, covered, h, w, band, piece_px, used=None, capacity=None):
    """Cut contour edges (end points A, Bv (K, 2), inner-side point T (K, 2), view (K,),
    `used` (K,) or None: all) into pieces of at most `piece_px` pixels, keeping only what lies
    within `band` of the crop -> (edge (P,), t0 (P,), t1 (P,), inner (P,), used, count):
    piece = A + [t0, t1] (Bv - A); inner: the piece lies inside the silhouette, judged by the
    hard coverage (N*h*w,) one pixel beyond its midpoint on the outer side (a chair leg's
    outline seen against the seat; a covered pixel must not measure its distance to it);
    used: `_expand`'s, with P = `capacity` slots or None; count: pieces wanted (0-dim)."""
    d = Bv - A
    # clip each segment to the crop widened by the band (Liang-Barsky), t in [ta, tb]
    lo = torch.full((2,), -band, dtype=A.dtype, device=A.device)
    hi = torch.where(torch.arange(2, device=A.device) == 0, w - 1 + band, h - 1 + band).to(A.dtype)  # x, y
    safe = torch.where(d == 0, torch.ones_like(d), d)
    t_lo, t_hi = (lo - A) / safe, (hi - A) / safe  # (K, 2)
    inside = (A >= lo) & (A <= hi)  # needed where the segment runs parallel to a side
    enter = torch.where(d == 0, torch.where(inside, -torch.inf, torch.inf), torch.minimum(t_lo, t_hi))
    leave = torch.where(d == 0, torch.where(inside, torch.inf, -torch.inf), torch.maximum(t_lo, t_hi))
    ta = enter.amax(1).clamp(min=0)
    tb = leave.amin(1).clamp(max=1)
    length = d.norm(dim=-1)
    span = (tb - ta).clamp(min=0)
    n = torch.where(tb > ta, torch.ceil(span * length / piece_px).clamp(min=1), torch.zeros_like(span)).long()
    if used is not None:
        n = torch.where(used, n, 0)
    edge, j, pieces_used = _expand(n, capacity)
    nf = _take(n, edge).clamp(min=1).to(A.dtype)
    ta_e, span_e = _take(ta, edge), _take(span, edge)
    t0 = ta_e + span_e * j.to(A.dtype) / nf
    t1 = ta_e + span_e * (j + 1).to(A.dtype) / nf
    de, Ae = _take(d, edge), _take(A, edge)
    mid = Ae + ((t0 + t1) / 2)[:, None] * de
    nrm = torch.stack([-de[:, 1], de[:, 0]], -1) / _take(length, edge).clamp(min=1e-12)[:, None]
    nrm = torch.where(((nrm * (_take(T, edge) - Ae)).sum(-1) > 0)[:, None], -nrm, nrm)  # outward
    m = (mid + nrm).round().clamp(-1, max(h, w)).long()
    in_crop = (m[:, 0] >= 0) & (m[:, 0] < w) & (m[:, 1] >= 0) & (m[:, 1] < h)
    pix = _take(view, edge) * (h * w) + m[:, 1].clamp(0, h - 1) * w + m[:, 0].clamp(0, w - 1)
    return edge, t0, t1, _take(covered, pix) & in_crop, pieces_used, n.sum()


def _nearest_outline_pieces(A, Bv, inner, view, covered, h, w, band, max_pairs, used=None, window=None):
    """For each output pixel within `band` of an outline piece (end points A, Bv (P, 2),
    view (P,)): the nearest piece that bounds the silhouette, i.e. any piece for an
    uncovered pixel, a piece not `inner` for a covered one -> (pixel (Q,), piece (Q,), found).
    found is None; or, with `used` (P,) (only these pieces count) and `window` (the side of
    the pixel square each piece tests, at least what its length needs), Q is every pixel,
    found (Q,) marks those within `band` of a piece, and nothing waits on the device.

    Pieces are short (about `band` long), so each one tests a fixed square window of
    pixels around it: a dense (P, n, n) computation, no ragged enumeration."""
    hw = h * w
    keys = torch.full_like(covered, _NO_KEY, dtype=torch.long)
    K = view.numel()
    if K == 0:
        return keys.new_zeros(0), keys.new_zeros(0), None
    lo = torch.minimum(A, Bv) - band  # (P, 2) window corner (continuous)
    if window is None:
        window = int(torch.ceil((torch.maximum(A, Bv) - lo).max()).item() + band) + 1
    n = max(min(window, max(h, w) + 1), 1)  # window side
    x0 = torch.ceil(lo.clamp(-n - 1.0, max(h, w) + 1.0)).long()  # (P, 2) first pixel of the window
    d = Bv - A
    inv_L2 = 1 / (d * d).sum(-1).clamp(min=1e-12)
    step = torch.arange(n, device=A.device)
    per_chunk = K if used is not None else max(1, max_pairs // (n * n))
    for a in range(0, K, per_chunk):
        b = min(K, a + per_chunk)
        px = x0[a:b, 0, None, None] + step[None, None, :]  # (p, 1, n)
        py = x0[a:b, 1, None, None] + step[None, :, None]  # (p, n, 1)
        rx = px.to(A.dtype) - A[a:b, 0, None, None]  # (p, 1, n) p - A
        ry = py.to(A.dtype) - A[a:b, 1, None, None]  # (p, n, 1)
        dx, dy = d[a:b, 0, None, None], d[a:b, 1, None, None]
        t = ((rx * dx + ry * dy) * inv_L2[a:b, None, None]).clamp(0, 1)  # (p, n, n)
        ox, oy = rx - t * dx, ry - t * dy  # p - q, q the nearest point on the piece
        dist = torch.sqrt(ox * ox + oy * oy)
        inside = ((px >= 0) & (px < w)) & ((py >= 0) & (py < h))  # (p, n, n)
        pixel = (view[a:b, None, None] * hw + py.clamp(0, h - 1) * w + px.clamp(0, w - 1)).reshape(-1)
        ok = inside & (dist <= band) & ~(covered.index_select(0, pixel).view_as(dist) & inner[a:b, None, None])
        if used is not None:
            ok &= used[a:b, None, None]
        key = (dist * _DIST_KEY_SCALE).round().long() * K + torch.arange(a, b, device=A.device)[:, None, None]
        keys.scatter_reduce_(0, pixel, torch.where(ok, key, _NO_KEY).reshape(-1), "amin")
    if used is not None:
        return torch.arange(keys.numel(), device=keys.device), keys % K, keys != _NO_KEY
    pixel = (keys != _NO_KEY).nonzero(as_tuple=True)[0]
    return pixel, _take(keys, pixel) % K, None


# ----------------------------------------------------------------------------- differentiable parts


def _pixel_xy(pixel: torch.Tensor, h: int, w: int, dtype) -> torch.Tensor:
    """Flat pixel indices (Q,) -> crop-grid coordinates (Q, 2) (x, y) of their centres."""
    r = pixel % (h * w)
    return torch.stack([r % w, torch.div(r, w, rounding_mode="floor")], -1).to(dtype)


def _triangle_planes(tri: torch.Tensor, tz: torch.Tensor, drawn: torch.Tensor | None = None):
    """tri (M, 3, 2) projected vertices, tz (M, 3) their camera z -> barycentric gradients
    grad (M, 3, 2), b_k(p) = [k == 0] + grad_k . (p - tri[:, 0]), and inv_z (M, 3) =
    (d/dx, d/dy, value at vertex 0) of 1/z, which is linear in the image for a planar
    face (perspective-correct interpolation). `drawn` (M,): triangles not drawn, perhaps
    degenerate, get a unit area, so that no inf reaches the gradients."""
    vn, vnn = tri.roll(-1, dims=1), tri.roll(-2, dims=1)  # (M, 3, 2) v_{k+1}, v_{k+2}
    dl = vn - vnn  # b_k(p) = cross(v_{k+1} - p, v_{k+2} - p) / area2: gradient (dl_y, -dl_x) / area2
    area2 = _cross(dl[:, 1], dl[:, 2])  # (M,) = cross(v1 - v0, v2 - v0), the same floats
    if drawn is not None:
        area2 = torch.where(drawn, area2, 1.0)
    grad = torch.stack([dl[..., 1], -dl[..., 0]], -1) / area2[:, None, None]
    iz = 1 / tz  # (M, 3)
    return grad, torch.cat([(grad * iz[..., None]).sum(1), iz[:, :1]], -1)


def _segment_distance(p: torch.Tensor, A: torch.Tensor, Bv: torch.Tensor) -> torch.Tensor:
    """Distance (Q,) from points p (Q, 2) to segments A-Bv (Q, 2), differentiable (line distance
    inside the segment, end-point distance beyond it). The differences are taken on the (Q, 2)
    tensors whole and then unbound (80 kernels forward and backward where picking each coordinate
    apart took 95); the products stay on (Q,) columns, which the CPU runs faster than a size-2 axis."""
    (dx, dy), (rx, ry) = (Bv - A).unbind(-1), (p - A).unbind(-1)
    L2 = (dx * dx + dy * dy).clamp(min=1e-12)
    s = (rx * dx + ry * dy) / L2
    line = (dx * ry - dy * rx).abs() / L2.sqrt()
    ex, ey = (p - torch.where((s <= 0)[:, None], A, Bv)).unbind(-1)
    point = (ex * ex + ey * ey + 1e-12).sqrt()
    return torch.where((s > 0) & (s < 1), line, point)


# ----------------------------------------------------------------------------- render


def _render_setup(vertices_world: torch.Tensor, mesh, cameras: Cameras, crops, size, sigma: float, margin: float,
                  znear: float, max_radius: float):
    """(topology on the vertices' device, vertices (B, V, 3), cameras like them, crops (B, C, 4) constant,
    (h, w)): `render`'s inputs checked and completed."""
    topo = mesh if isinstance(mesh, MeshTopology) else MeshTopology.from_faces(mesh)
    if topo.faces.device != vertices_world.device:
        topo = topo.to(vertices_world.device)
    verts = vertices_world if vertices_world.dim() == 3 else vertices_world[None]
    if verts.dim() != 3 or verts.shape[-1] != 3 or not verts.is_floating_point():
        raise ValueError(
            f"rendering: vertices must be a float (B, V, 3) or (V, 3) tensor, got {tuple(vertices_world.shape)}"
        )
    B, V, _ = verts.shape
    if topo.vertices > V:
        raise ValueError(f"rendering: faces index vertex {topo.vertices - 1} but only {V} vertices given")
    if sigma <= 0:
        raise ValueError(f"rendering: sigma must be positive, got {sigma}")
    cameras = _cameras_like(cameras, verts)
    C = len(cameras)
    h, w = _size(size)
    if crops is None:
        crops = object_crops(verts, cameras, (h, w), margin=margin, znear=znear, max_radius=max_radius)
    crops = torch.as_tensor(crops, dtype=verts.dtype, device=verts.device).detach()
    if crops.dim() == 2:
        crops = crops[None].expand(B, -1, -1)
    if tuple(crops.shape) != (B, C, 4):
        raise ValueError(f"rendering: crops must be (B={B}, C={C}, 4), got {tuple(crops.shape)}")
    return topo, verts, cameras, crops, (h, w)


def _crop_vertices(verts: torch.Tensor, cameras: Cameras, crops: torch.Tensor, h: int, w: int, znear: float,
                   max_radius: float):
    """(valid (B, C, V): which vertices each camera can draw, uv (N*V, 2) crop-grid coordinates, z (N*V,)
    camera depth), N = B x C views, with autograd."""
    B, V, _ = verts.shape
    C = len(cameras)
    N = B * C
    with torch.no_grad():
        valid_v = _valid_vertices(_camera_frame(verts.detach(), cameras), cameras.dist, znear, max_radius)  # (B, C, V)
        ahead = cameras.centers + cameras.T_world_from_cam[:, :3, 2]  # (C, 3) a point 1 m ahead of each camera
    # vertices a camera cannot draw are swapped for a harmless point before projecting, so that
    # a vertex on a camera's plane (z = 0) cannot put inf / nan into forward or backward
    pts = torch.where(valid_v.transpose(0, 1).reshape(C, B * V, 1), verts.reshape(1, B * V, 3), ahead[:, None, :])
    pix, z = project(pts, cameras)  # (C, BV, 2), (C, BV)
    pix = pix.reshape(C, B, V, 2).transpose(0, 1).reshape(N, V, 2)
    box = crops.reshape(N, 4)
    scale = _crop_scale(box, h, w)  # (N, 2)
    uv = ((pix - box[:, None, :2]) / scale[:, None, :] - 0.5).reshape(N * V, 2)  # crop-grid coordinates
    z = z.reshape(C, B, V).transpose(0, 1).reshape(N * V)
    return valid_v, uv, z


@dataclass
class _DrawnFaces:
    """Which faces `render` draws in each of its N views, and their outline edges (no autograd)."""

    uv_d: torch.Tensor  # (N*V, 2) detached crop-grid coordinates
    drawn: torch.Tensor | None  # (N*F,) with fixed shapes: which of all faces are drawn
    f_view: torch.Tensor  # (M,) each face's view
    f_idx: torch.Tensor  # (3M,) rows of uv / z of its vertices
    tri_d: torch.Tensor  # (M, 3, 2) detached projected faces
    contours: tuple  # `_contours`: view, a, b, inner vertex, used, count


def _drawn_faces(topo: MeshTopology, uv: torch.Tensor, valid_v: torch.Tensor, N: int, V: int, cull_backfaces: bool,
                 capacity, fixed: bool) -> _DrawnFaces:
    """The faces each view draws (in front, inside the lens' one-to-one region, not degenerate, facing the
    camera when culling) and their contour edges."""
    faces = topo.faces
    F = faces.shape[0]
    device = uv.device
    with torch.no_grad():
        valid_v = valid_v.reshape(N * V)
        uv_d = uv.detach()
        all_idx = (torch.arange(N, device=device)[:, None, None] * V + faces).reshape(-1)  # (N*F*3,)
        tri_all = _take(uv_d, all_idx).reshape(N, -1, 3, 2)
        area2 = _cross(tri_all[:, :, 1] - tri_all[:, :, 0], tri_all[:, :, 2] - tri_all[:, :, 0])  # (N, F)
        # facing from the projected winding (y down: counter-clockwise outward faces read negative);
        # for straight-edged triangles this is exactly what bounds their union in the image
        front = area2 < 0
        rendered = _take(valid_v, all_idx).reshape(N, -1, 3).all(-1) & (area2.abs() > 1e-10)
        if cull_backfaces:
            rendered &= front
        contours = _contours(topo, rendered, front, capacity and capacity.contours)
        drawn = rendered.reshape(-1) if fixed else None
        # (M,) index into N*F: the drawn faces, or with fixed shapes every face (`drawn` masks them)
        f_flat = torch.arange(N * F, device=device) if fixed else rendered.reshape(-1).nonzero(as_tuple=True)[0]
        f_view = torch.div(f_flat, faces.shape[0], rounding_mode="floor")
        f_idx = _take(all_idx.reshape(-1, 3), f_flat).reshape(-1)  # (3M,) rows of uv / z
        tri_d = _take(tri_all.reshape(-1, 3, 2), f_flat)
    return _DrawnFaces(uv_d, drawn, f_view, f_idx, tri_d, contours)


def _depth(uv: torch.Tensor, z: torch.Tensor, faces: _DrawnFaces, N: int, h: int, w: int, chunk: int, capacity,
           fixed: bool):
    """(depth (N*h*w,) with autograd, 0 where nothing is drawn, covered (N*h*w,) bool, lines and pixels the
    rasteriser needed): per-face planes with autograd, then the hard z-buffer on their detached values."""
    dtype, device = uv.dtype, uv.device
    hw = h * w
    f_view, f_idx, tri_d, drawn = faces.f_view, faces.f_idx, faces.tri_d, faces.drawn
    # per-face planes with autograd (M faces), then the hard z-buffer on their detached values
    tri = _take(uv, f_idx).reshape(-1, 3, 2)  # (M, 3, 2)
    grad, inv_z = _triangle_planes(tri, _take(z, f_idx).reshape(-1, 3), drawn)
    with torch.no_grad():
        keys, n_lines, n_pixels = _rasterize(tri_d, grad.detach(), inv_z.detach(), f_view, N, h, w, chunk, capacity,
                                             drawn)
        covered = keys != _NO_KEY
        # (Q,) pixels with depth: the covered ones, or with fixed shapes all (`covered` masks them)
        d_pixel = torch.arange(N * hw, device=device) if fixed else covered.nonzero(as_tuple=True)[0]
        d_face = _take(keys, d_pixel) % max(f_view.numel(), 1)
    qx, qy = _pixel_xy(d_pixel, h, w, dtype).unbind(-1)
    ox, oy = _take(tri[:, 0], d_face).unbind(-1)  # (Q,) each: the face's vertex 0
    iz_x, iz_y, iz_0 = _take(inv_z, d_face).unbind(-1)  # (Q,) each
    inv_depth = iz_0 + iz_x * (qx - ox) + iz_y * (qy - oy)
    if fixed:
        depth = torch.where(covered, 1 / torch.where(covered, inv_depth, 1.0), 0.0)
    else:
        depth = torch.zeros(N * hw, dtype=dtype, device=device).index_put((d_pixel,), 1 / inv_depth)
    return depth, covered, n_lines, n_pixels


def _silhouette(uv: torch.Tensor, uv_d: torch.Tensor, contours: tuple, covered: torch.Tensor, V: int, h: int,
                w: int, sigma: float, band_sigmas: float, piece_px: float | None, chunk: int, capacity, fixed: bool):
    """(silhouette (N*h*w,) with autograd, pieces the outline needed): the soft silhouette, a sigmoid of the
    signed distance to the nearest outline piece, reaching 0 / 1 at band_sigmas x sigma."""
    dtype = uv.dtype
    band = band_sigmas * sigma
    c_view, c_a, c_b, c_t, c_used, n_contours = contours
    A = _take(uv, c_view * V + c_a)  # (K, 2) contour edges, with autograd
    Bv = _take(uv, c_view * V + c_b)
    with torch.no_grad():
        inner_side = _take(uv_d, c_view * V + c_t)  # (K, 2) a vertex on each contour edge's face side
        piece = piece_px or max(band, 2.0)
        p_edge, p_t0, p_t1, p_inner, p_used, n_pieces = _outline_pieces(
            A.detach(), Bv.detach(), inner_side, c_view, covered, h, w, band, piece, c_used,
            capacity and capacity.pieces)
        PA = _take(A.detach(), p_edge)
        PD = _take(Bv.detach(), p_edge) - PA
        # with fixed shapes, each piece's window is as wide as the longest piece could need
        window = int(math.ceil(piece + band) + band) + 2 if fixed else None
        s_pixel, s_piece, s_found = _nearest_outline_pieces(
            PA + p_t0[:, None] * PD, PA + p_t1[:, None] * PD, p_inner, _take(c_view, p_edge), covered, h, w, band,
            chunk, p_used, window)
        s_edge, s_t0, s_t1 = _take(p_edge, s_piece), _take(p_t0, s_piece), _take(p_t1, s_piece)
    EA, EB = _take(A, s_edge), _take(Bv, s_edge)
    ED = EB - EA
    dist = _segment_distance(_pixel_xy(s_pixel, h, w, dtype), EA + s_t0[:, None] * ED, EA + s_t1[:, None] * ED)
    signed = torch.where(_take(covered, s_pixel), dist, -dist).clamp(-band, band)
    lo = 1 / (1 + math.exp(band_sigmas))  # sigmoid(-band / sigma)
    soft = (torch.sigmoid(signed / sigma) - lo) / (1 - 2 * lo)
    if fixed:
        silhouette = torch.where(s_found, soft, covered.to(dtype))
    else:
        silhouette = covered.to(dtype).index_put((s_pixel,), soft)
    return silhouette, n_pieces


def render(
    vertices_world: torch.Tensor,
    mesh,
    cameras: Cameras,
    crops: torch.Tensor | None = None,
    size=DEFAULT_SIZE,
    sigma: float = 0.6,
    *,
    cull_backfaces: bool = True,
    margin: float = 0.1,
    band_sigmas: float = 5.0,
    znear: float = 0.05,
    max_radius: float = 3.0,
    max_pairs: int | None = None,
    piece_px: float | None = None,
    capacity: Capacity | None = None,
) -> RenderOutput:
    """Soft silhouette and depth of a mesh in B frames x C views.

    vertices_world: (B, V, 3) or (V, 3) world coordinates (metres); mesh: faces
    (F, 3) or a `MeshTopology` (build it once per mesh: faster); cameras: C views;
    crops: (B, C, 4) or (C, 4) boxes x0, y0, x1, y1 in full-image pixels, or None
    for `object_crops(vertices, cameras, size, margin)`; size: (h, w) output grid;
    sigma: silhouette edge softness in output pixels; band_sigmas: the soft edge
    reaches exactly 0 / 1 at this many sigmas from the outline.
    Gradients flow to `vertices_world` (and camera parameters); crops are constants.
    Faces with a vertex at z <= znear, or outside the region where the lens model
    is one-to-one (`max_radius` on x/z, y/z), are not drawn. `max_pairs` bounds
    the pixel-candidate tensors (memory; default 32768 on CPU, where small
    temporaries stay in the allocator's cache and are measurably faster, 4M on
    CUDA); more work is done in chunks. `piece_px`: contour edges are judged
    outline / inside the silhouette in pieces of at most this many output pixels
    (default: the band). `capacity`: fixed shapes (a `Capacity`): the same result while
    `out.needed` fits, nothing read back from the device, and the same shapes every call.
    """
    topo, verts, cameras, crops, (h, w) = _render_setup(vertices_world, mesh, cameras, crops, size, sigma, margin,
                                                         znear, max_radius)
    B, V, _ = verts.shape
    C = len(cameras)
    N = B * C
    valid_v, uv, z = _crop_vertices(verts, cameras, crops, h, w, znear, max_radius)
    fixed = capacity is not None and topo.faces.shape[0] > 0
    capacity = capacity if fixed else None
    chunk = max_pairs or MAX_PAIRS.get(verts.device.type, MAX_PAIRS["cuda"])
    faces = _drawn_faces(topo, uv, valid_v, N, V, cull_backfaces, capacity, fixed)
    depth, covered, n_lines, n_pixels = _depth(uv, z, faces, N, h, w, chunk, capacity, fixed)
    silhouette, n_pieces = _silhouette(uv, faces.uv_d, faces.contours, covered, V, h, w, sigma, band_sigmas, piece_px,
                                       chunk, capacity, fixed)
    n_contours = faces.contours[5]
    return RenderOutput(
        silhouette=silhouette.reshape(B, C, h, w),
        depth=depth.reshape(B, C, h, w),
        coverage=covered.reshape(B, C, h, w),
        crops=crops,
        needed=torch.stack([n_lines, n_pixels, n_contours, n_pieces]),
    )


# ----------------------------------------------------------------------------- observations


def crop_observation(image: torch.Tensor, crops: torch.Tensor, size=DEFAULT_SIZE, mode: str = "area") -> torch.Tensor:
    """Resample full images (..., C, H, W) to the render grid of crops (..., C, 4) -> (..., C, h, w).

    mode 'area': exact box filter, each output pixel the area-weighted mean of the
    input pixels its footprint overlaps (for masks: the covered fraction; outside
    the image counts as 0); computed from a float64 integral image, so its cost
    does not grow with the downsampling factor. 'nearest': the input pixel
    nearest the output pixel centre (depth: no mixing across edges). 'min': the
    smallest non-zero value within the footprint (depth: front-most; 0 = missing
    stays 0). Pixels outside the image read 0. Output is floating (float32 for
    integer input).
    """
    if mode not in ("area", "nearest", "min"):
        raise ValueError(f"crop_observation: mode must be 'area', 'nearest' or 'min', got {mode!r}")
    h, w = _size(size)
    lead = image.shape[:-2]
    H, W = image.shape[-2:]
    img = image if image.is_floating_point() else image.float()
    img = img.reshape(-1, H, W)  # (N, H, W)
    box = torch.as_tensor(crops, dtype=img.dtype, device=img.device).reshape(-1, 4)
    if box.shape[0] != img.shape[0] or tuple(crops.shape[:-1]) != tuple(lead):
        raise ValueError(f"crop_observation: crops {tuple(crops.shape)} do not match images {tuple(image.shape)}")
    N = img.shape[0]
    s = _crop_scale(box, h, w)  # (N, 2)
    n_idx = torch.arange(N, device=img.device)
    jx = torch.arange(w + 1, device=img.device, dtype=img.dtype)
    jy = torch.arange(h + 1, device=img.device, dtype=img.dtype)
    ex = box[:, 0, None] + jx * s[:, 0, None]  # (N, w + 1) footprint edges, full-image pixel coordinates
    ey = box[:, 1, None] + jy * s[:, 1, None]  # (N, h + 1)
    if mode == "nearest":
        iu = torch.floor((ex[:, :-1] + ex[:, 1:]) / 2 + 0.5).long()  # (N, w) pixel containing the centre
        iv = torch.floor((ey[:, :-1] + ey[:, 1:]) / 2 + 0.5).long()
        ok = ((iv >= 0) & (iv < H))[:, :, None] & ((iu >= 0) & (iu < W))[:, None, :]
        out = img[n_idx[:, None, None], iv.clamp(0, H - 1)[:, :, None], iu.clamp(0, W - 1)[:, None, :]]
        return torch.where(ok, out, torch.zeros_like(out)).reshape(*lead, h, w)
    if mode == "area":
        # integral image on pixel boundaries (pixel i spans [i - 0.5, i + 0.5]): the integral of a
        # piecewise-constant image is bilinear within each pixel, so interpolating it is exact
        integral = torch.zeros(N, H + 1, W + 1, dtype=torch.float64, device=img.device)
        integral[:, 1:, 1:] = img.double().cumsum(1).cumsum(2)
        gx = (ex + 0.5).clamp(0, W).double()  # (N, w + 1) in integral-table units
        gy = (ey + 0.5).clamp(0, H).double()
        I = _bilinear_table(integral, gy, gx)  # (N, h + 1, w + 1)
        total = I[:, 1:, 1:] - I[:, :-1, 1:] - I[:, 1:, :-1] + I[:, :-1, :-1]
        out = (total / (s[:, 0] * s[:, 1]).double()[:, None, None]).to(img.dtype)
        return out.reshape(*lead, h, w)
    # 'min': gather each footprint's pixels, a block of output rows at a time (bounded memory)
    ix, wx = _footprint(box[:, 0], s[:, 0], w, W)  # (N, w, Kx)
    iy, wy = _footprint(box[:, 1], s[:, 1], h, H)  # (N, h, Ky)
    rows = max(1, (1 << 22) // max(1, N * w * ix.shape[-1] * iy.shape[-1]))
    out = []
    for r in range(0, h, rows):
        vals = img[n_idx[:, None, None, None, None], iy[:, r:r + rows, :, None, None], ix[:, None, None, :, :]]
        ok = (wy[:, r:r + rows, :, None, None] > 0) & (wx[:, None, None, :, :] > 0) & (vals > 0)
        m = torch.where(ok, vals, torch.full_like(vals, float("inf"))).amin(dim=(2, 4))  # (N, rows, w)
        out.append(torch.where(torch.isfinite(m), m, torch.zeros_like(m)))
    return torch.cat(out, 1).reshape(*lead, h, w)


def _bilinear_table(table: torch.Tensor, gy: torch.Tensor, gx: torch.Tensor) -> torch.Tensor:
    """Bilinear interpolation of tables (N, A, B) at the grid gy (N, a) x gx (N, b) -> (N, a, b)."""
    N, A, Bn = table.shape
    y0 = gy.floor().clamp(0, A - 2).long()
    x0 = gx.floor().clamp(0, Bn - 2).long()
    fy, fx = (gy - y0)[:, :, None], (gx - x0)[:, None, :]
    n = torch.arange(N, device=table.device)[:, None, None]
    Y0, X0 = y0[:, :, None], x0[:, None, :]
    t00, t01 = table[n, Y0, X0], table[n, Y0, X0 + 1]
    t10, t11 = table[n, Y0 + 1, X0], table[n, Y0 + 1, X0 + 1]
    return (t00 * (1 - fx) + t01 * fx) * (1 - fy) + (t10 * (1 - fx) + t11 * fx) * fy


def _footprint(start: torch.Tensor, step: torch.Tensor, n_out: int, n_in: int):
    """Input pixels overlapped by each output pixel's footprint along one axis.

    start (N,), step (N,) -> indices (N, n_out, K) clamped into the image and
    overlap lengths (N, n_out, K), 0 for pixels outside the image or footprint.
    """
    K = int(torch.ceil(step.max()).item()) + 1 if step.numel() else 1
    j = torch.arange(n_out, device=start.device, dtype=start.dtype)
    a = start[:, None] + j * step[:, None]  # (N, n_out) footprint start
    b = a + step[:, None]
    first = torch.floor(a + 0.5)  # input pixel containing a
    idx = first[..., None] + torch.arange(K, device=start.device, dtype=start.dtype)  # (N, n_out, K)
    overlap = (torch.minimum(b[..., None], idx + 0.5) - torch.maximum(a[..., None], idx - 0.5)).clamp(min=0)
    overlap = torch.where((idx >= 0) & (idx < n_in), overlap, torch.zeros_like(overlap))
    return idx.long().clamp(0, n_in - 1), overlap
