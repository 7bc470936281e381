"""Differentiable silhouette and depth rendering of a rigid mesh, in pure PyTorch.

Used by the object stage (E_O): render the object's soft silhouette and depth in
a crop around it in every view, compare with the observed mask and depth cropped
to the same grid (`crop_observation`). Runs on CPU and CUDA, batched over B
frames and C views, no compiled extension.

Method (chosen by measurement, numbers below)
---------------------------------------------
1. Vertices are projected with the real camera model (`cameras.project`, lens
   distortion included). Triangles are rasterised in pixel space with straight
   edges between the projected vertices: an approximation under distortion,
   exact without it; the error is the bow of a distorted straight edge, which
   for the sub-pixel-to-1-pixel distortion curvature of Kinect lenses across one
   triangle is negligible for the subdivided meshes we use (subdivide a mesh
   with very large faces, e.g. `trimesh.remesh.subdivide_to_size`, if it is seen
   near the image border of a strongly distorted camera).
2. Hard pass, no autograd: every front-facing triangle (3D back-face test, the
   mesh is assumed closed; `cull_backfaces=False` for open meshes) enumerates
   the output pixels inside its own bounding box; pixel-centre inside tests and
   a z-buffer (one `scatter_reduce` on packed (depth, face) keys) give the hard
   coverage and the front face of each pixel. Work is the sum of triangle
   bounding-box areas (about 2-3x the object's pixel area), never pixels x faces.
3. Depth (differentiable): z of the winning face at the pixel centre, by
   perspective-correct barycentric interpolation (1/z is linear in the image):
   exactly the plane's camera z, metres, as Kinect depth; 0 where not covered.
   Gradients move the surface at fixed coverage; the silhouette term handles
   the occluding boundary.
4. Soft silhouette (differentiable): S = sigmoid(signed distance to the outline
   / sigma), rescaled so it is exactly 0 / 1 beyond `band_sigmas * sigma` from
   it. The outline of the union of projected triangles of a closed mesh lies on
   its contour edges (edges between a rendered front face and a back face, or
   mesh boundary edges), of which there are O(sqrt(F)). Only pixels within the
   band of a contour edge's box are paired with it; the nearest edge per pixel
   is found without autograd and its distance recomputed with autograd, so the
   gradient reaches exactly the contour vertices. Sign: + where the pixel centre
   is covered. Contour edges lying inside the silhouette (a chair leg in front
   of the seat) are skipped for a covered pixel when the point one pixel beyond
   the edge's nearest point is covered too, so such edges do not dent the
   interior. Why not SoftRas (1 - prod over faces of sigmoid(face distance)):
   every interior edge between two faces then reads 0.75 at its pixels; with
   hundreds of faces a few pixels wide at crop resolution the whole interior
   reads ~0.8, biasing the loss, and it costs pixels x faces pairs.
   sigma is in output pixels; ~0.3 px mimics area coverage (the box filter of a
   pixel), 0.5-1.5 px gives a smoother loss.
5. Crops: each view renders a (h, w) grid over a box (x0, y0, x1, y1) of the
   full image (continuous pixel coordinates, pixel centres at integers, so the
   full native image is (-0.5, -0.5, W - 0.5, H - 0.5)); output pixel (i, j) is
   centred at (x0 + (j + 0.5) (x1 - x0) / w, y0 + (i + 0.5) (y1 - y0) / h).
   `object_crops` makes square-pixel boxes around the projected vertices with a
   margin; compute them once per frame and keep them fixed while optimising.
   `crop_observation` resamples masks (area average: exact box filter) and
   depth ('nearest' or 'min' over the footprint of non-zero values; 0 stays
   missing) to the same grid.

Measured (2-core CPU, torch 2.13, float32, `tools/bench_rendering.py`, crop
96x96, sigma 0.6, object at 1.5 m in 640x576 views, 4 views in one call)
    mesh                       F      fwd 4 views   fwd+bwd 4 views   peak extra memory
    box (trimesh, 12 faces)    12     (filled in below)
See the table at the end of this docstring (kept in sync with the benchmark).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from intercap.cameras import Cameras, distortion_jacobian, project, world_to_camera

_NO_KEY = torch.iinfo(torch.int64).max
_DEPTH_KEY_SCALE = 1e5  # z quantised to 10 um for the z-buffer's tie order only
_DIST_KEY_SCALE = 1e4  # edge distances quantised to 1e-4 px for the nearest-edge choice only


@dataclass(frozen=True)
class MeshTopology:
    """Faces and edge adjacency of a triangle mesh, computed once per mesh.

    faces: (F, 3) long; edges: (E, 2) long unique undirected edges;
    face_edges: (F, 3) index of edge k = (faces[f, k], faces[f, k+1 mod 3]);
    opposite: (F, 3) the vertex opposite that edge (faces[f, k+2 mod 3]);
    faces_per_edge: (E,) how many faces share each edge (1 = mesh boundary).
    """

    faces: torch.Tensor
    edges: torch.Tensor
    face_edges: torch.Tensor
    opposite: torch.Tensor
    faces_per_edge: torch.Tensor

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
        )

    def to(self, device) -> "MeshTopology":
        return MeshTopology(*(getattr(self, k).to(device) for k in self.__dataclass_fields__))


@dataclass
class RenderOutput:
    """silhouette (B, C, h, w) soft, in [0, 1]; depth (B, C, h, w) camera z in
    metres, 0 where no surface; coverage (B, C, h, w) bool, pixel centre covered
    (where depth is defined); crops (B, C, 4) the boxes rendered; in_image
    (B, C, h, w) bool, output pixel centre inside the camera's image."""

    silhouette: torch.Tensor
    depth: torch.Tensor
    coverage: torch.Tensor
    crops: torch.Tensor
    in_image: torch.Tensor


# ----------------------------------------------------------------------------- crops


def _vertex_validity(vertices_world: torch.Tensor, cameras: Cameras, znear: float, max_radius: float) -> torch.Tensor:
    """(B, V, 3) -> (B, C, V) bool: vertex in front of the camera (z > znear) and
    inside the region where the distortion model is invertible (|x/z, y/z| below
    `max_radius` and the distortion Jacobian's determinant positive); beyond it
    polynomial distortion folds back and would paint far-away points into the image."""
    B, V, _ = vertices_world.shape
    p = world_to_camera(vertices_world.reshape(B * V, 3), cameras.T_cam_from_world)  # (C, BV, 3)
    z = p[..., 2]
    ok = torch.isfinite(p).all(-1) & (z > znear)
    xy = p[..., :2] / torch.where(ok, z, torch.ones_like(z))[..., None]  # (C, BV, 2)
    ok &= (xy * xy).sum(-1) < max_radius**2
    if bool((cameras.dist != 0).any()):
        J = distortion_jacobian(xy, cameras.dist)  # (C, BV, 2, 2)
        ok &= (J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]) > 0
    return ok.reshape(len(cameras), B, V).transpose(0, 1)


def object_crops(
    vertices_world: torch.Tensor,
    cameras: Cameras,
    size=(96, 96),
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
        valid = _vertex_validity(verts, cameras, znear, max_radius)[..., None]  # (B, C, V, 1)
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


def _in_image(crops: torch.Tensor, cameras: Cameras, B: int, h: int, w: int) -> torch.Tensor:
    """(B, C, 4) boxes -> (B, C, h, w) bool: output pixel centre inside the full image."""
    C = len(cameras)
    box = crops.reshape(B * C, 4)
    s = _crop_scale(box, h, w)
    u = box[:, 0, None] + (torch.arange(w, device=box.device, dtype=box.dtype) + 0.5) * s[:, 0, None]  # (BC, w)
    v = box[:, 1, None] + (torch.arange(h, device=box.device, dtype=box.dtype) + 0.5) * s[:, 1, None]  # (BC, h)
    W = cameras.width.to(box.dtype).repeat(B)[:, None]
    H = cameras.height.to(box.dtype).repeat(B)[:, None]
    ok_u = (u >= -0.5) & (u < W - 0.5)
    ok_v = (v >= -0.5) & (v < H - 0.5)
    return (ok_v[:, :, None] & ok_u[:, None, :]).reshape(B, C, h, w)


# ----------------------------------------------------------------------------- span enumeration


def _expand(counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """counts (M,) long -> (owner (P,), local (P,)): owner m repeated counts[m] times, local 0..counts[m]-1."""
    P = int(counts.sum()) if counts.numel() else 0
    owner = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts, output_size=P)
    first = counts.cumsum(0) - counts
    return owner, torch.arange(P, device=counts.device) - first[owner]


def _row_chunks(counts: torch.Tensor, max_pairs: int):
    """Split rows with `counts` pixels into consecutive ranges of about max_pairs pixels: yields (start, end)."""
    if counts.numel() == 0:
        return
    cum = counts.cumsum(0)
    total = int(cum[-1])
    start, done = 0, 0
    while start < counts.numel() and done < total:
        end = counts.numel() if total - done <= max_pairs else max(int(torch.searchsorted(cum, done + max_pairs, right=True)), start + 1)
        yield start, end
        done = int(cum[end - 1])
        start = end


def _span_pixels(x_lo: torch.Tensor, x_hi: torch.Tensor, max_pairs: int):
    """Rows with inclusive pixel spans [x_lo, x_hi] (R,) -> yields (row (P,), px (P,)) chunks."""
    counts = (x_hi - x_lo + 1).clamp(min=0)
    for a, b in _row_chunks(counts, max_pairs):
        row, local = _expand(counts[a:b])
        row = row + a
        yield row, x_lo[row] + local


def _rows(y_lo: torch.Tensor, y_hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Items with inclusive row ranges (M,) -> (item (R,), y (R,)) one entry per item row."""
    item, local = _expand((y_hi - y_lo + 1).clamp(min=0))
    return item, y_lo[item] + local


def _pixel_range(lo: torch.Tensor, hi: torch.Tensor, n: int, eps: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Continuous extents (M,) -> inclusive integer pixel ranges clipped to [0, n - 1]."""
    a = torch.ceil((lo - eps).clamp(-1, n)).long().clamp(min=0)
    b = torch.floor((hi + eps).clamp(-1, n)).long().clamp(max=n - 1)
    return a, b


# ----------------------------------------------------------------------------- hard passes (no autograd)

_SPAN_EPS = 1e-4  # pixels: spans are widened by this so a pixel centre on a shared edge is never lost


def _rasterize(uv, z, faces, rendered, h, w, max_pairs):
    """Hard z-buffer. uv (N, V, 2) crop-grid vertex positions, z (N, V), faces (F, 3),
    rendered (N, F) bool -> coverage (N*h*w,) bool and, for covered pixels,
    (pixel (Q,), view (Q,), face (Q,)) of the front-most face.

    Scanline enumeration: each triangle row's exact pixel span [x_lo, x_hi] is
    solved from the three edge inequalities, so work is the covered area (plus
    one entry per row), even for long thin triangles (cylinder cap fans)."""
    N = uv.shape[0]
    hw = h * w
    keys = torch.full((N * hw,), _NO_KEY, dtype=torch.long, device=uv.device)
    view, fid = rendered.nonzero(as_tuple=True)  # (M,)
    vidx = faces[fid]  # (M, 3)
    tri = uv[view[:, None], vidx]  # (M, 3, 2)
    tz = z[view[:, None], vidx]  # (M, 3)
    v0, v1, v2 = tri.unbind(1)
    area2 = _cross(v1 - v0, v2 - v0)  # (M,)
    keep = area2.abs() > 1e-10
    view, fid, tri, tz, area2 = view[keep], fid[keep], tri[keep], tz[keep], area2[keep]
    M = view.numel()
    if M:
        # b_k(p) = cross(v_{k+1} - p, v_{k+2} - p) / area2 = (cross(v_{k+1}, v_{k+2}) + p x (v_{k+1} - v_{k+2})) / area2
        vn, vnn = tri.roll(-1, dims=1), tri.roll(-2, dims=1)  # (M, 3, 2)
        dl = vn - vnn
        coef = torch.stack([dl[..., 1], -dl[..., 0], _cross(vn, vnn)], -1) / area2[:, None, None]  # (M, 3, 3) A, B, C
        inv_z = (coef / tz[..., None]).sum(1)  # (M, 3): 1/z = A x + B y + C, linear in the image
        lo, hi = tri.amin(1), tri.amax(1)  # (M, 2)
        y_lo, y_hi = _pixel_range(lo[:, 1], hi[:, 1], h, _SPAN_EPS)
        item, py = _rows(y_lo, y_hi)  # (R,)
        c = coef[item]  # (R, 3, 3)
        A = c[..., 0]
        rest = c[..., 1] * py[:, None] + c[..., 2]  # (R, 3): b_k = A_k x + rest_k >= 0
        bound = -rest / torch.where(A == 0, torch.ones_like(A), A)
        inf = torch.full_like(bound, float("inf"))
        flat_ok = (rest >= -_SPAN_EPS * c[..., 1].abs()) | (A != 0)  # horizontal edge: the row is inside or not
        x_min = torch.where(A > 0, bound, -inf).amax(1)
        x_max = torch.where(A < 0, bound, inf).amin(1)
        x_max = torch.where(flat_ok.all(1), x_max, -inf[:, 0])
        x_lo, x_hi = _pixel_range(torch.maximum(x_min, lo[item, 0]), torch.minimum(x_max, hi[item, 0]), w, _SPAN_EPS)
        iz = inv_z[item]  # (R, 3)
        row_inv_z = iz[:, 1] * py + iz[:, 2]
        row_ax = iz[:, 0]
        row_base = view[item] * hw + py * w
        for row, px in _span_pixels(x_lo, x_hi, max_pairs):
            invz = row_inv_z[row] + row_ax[row] * px
            key = (_DEPTH_KEY_SCALE / invz.clamp(min=1e-6)).round().clamp(max=1e12).long() * M + item[row]
            keys.scatter_reduce_(0, row_base[row] + px, key, "amin")
    covered = keys != _NO_KEY
    pixel = covered.nonzero(as_tuple=True)[0]
    item = keys[pixel] % max(M, 1)
    return covered, (pixel, view[item], fid[item])


def _contours(topo: MeshTopology, rendered: torch.Tensor, front: torch.Tensor):
    """Contour edges per view: rendered, front (N, F) bool -> (view (K,), a (K,), b (K,), third (K,))
    vertex indices of each contour edge and of a rendered face's opposite vertex (inner side)."""
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
    view, e = contour.nonzero(as_tuple=True)
    return view, topo.edges[e, 0], topo.edges[e, 1], third[view, e]


def _nearest_outline_edges(uv, covered, view, a, b, t, h, w, band, max_pairs):
    """For each output pixel within `band` of a contour edge: the nearest edge that
    bounds the silhouette. uv (N, V, 2) detached; covered (N*h*w,) bool; edges as
    vertex indices with their view -> (pixel (Q,), edge item (Q,)).

    Each edge visits, row by row, only the pixels of its band (a row's span is the
    segment's x-range over rows within `band`, widened by `band`)."""
    hw = h * w
    keys = torch.full_like(covered, _NO_KEY, dtype=torch.long)
    K = view.numel()
    if K:
        A, Bv, T = uv[view, a], uv[view, b], uv[view, t]  # (K, 2)
        d = Bv - A
        L2 = (d * d).sum(-1).clamp(min=1e-12)
        nrm = torch.stack([-d[:, 1], d[:, 0]], -1) / L2.sqrt()[:, None]  # unit normal
        nrm = torch.where(((nrm * (T - A)).sum(-1) > 0)[:, None], -nrm, nrm)  # outward: away from the face
        lo, hi = torch.minimum(A, Bv), torch.maximum(A, Bv)
        y_lo, y_hi = _pixel_range(lo[:, 1] - band, hi[:, 1] + band, h)
        item, py = _rows(y_lo, y_hi)  # (R,)
        Ai, di = A[item], d[item]
        yf = py.to(uv.dtype)
        steep = di[:, 1].abs() > 1e-9
        dy = torch.where(steep, di[:, 1], torch.ones_like(di[:, 1]))
        t1, t2 = (yf - band - Ai[:, 1]) / dy, (yf + band - Ai[:, 1]) / dy
        s0 = torch.where(steep, torch.minimum(t1, t2).clamp(0, 1), torch.zeros_like(t1))
        s1 = torch.where(steep, torch.maximum(t1, t2).clamp(0, 1), torch.ones_like(t1))
        xa, xb = Ai[:, 0] + s0 * di[:, 0], Ai[:, 0] + s1 * di[:, 0]
        x_lo, x_hi = _pixel_range(torch.minimum(xa, xb) - band, torch.maximum(xa, xb) + band, w)
        row_base = view[item] * hw + py * w
        for row, px in _span_pixels(x_lo, x_hi, max_pairs):
            e = item[row]
            p = torch.stack([px.to(uv.dtype), yf[row]], -1)  # (P, 2)
            Ae, de = A[e], d[e]
            s = ((p - Ae) * de).sum(-1).div(L2[e]).clamp(0, 1)
            q = Ae + s[:, None] * de  # nearest point on the edge
            dist = (p - q).norm(dim=-1)
            pixel = row_base[row] + px
            # a covered pixel ignores an edge whose outside (one pixel beyond its nearest point) is covered too
            m = (q + nrm[e]).round().long()
            in_crop = (m[:, 0] >= 0) & (m[:, 0] < w) & (m[:, 1] >= 0) & (m[:, 1] < h)
            m_cov = covered[view[e] * hw + m[:, 1].clamp(0, h - 1) * w + m[:, 0].clamp(0, w - 1)] & in_crop
            keep = (dist <= band) & ~(covered[pixel] & m_cov)
            key = (dist * _DIST_KEY_SCALE).round().long() * K + e
            keys.scatter_reduce_(0, pixel[keep], key[keep], "amin")
    pixel = (keys != _NO_KEY).nonzero(as_tuple=True)[0]
    return pixel, keys[pixel] % max(K, 1)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """2D cross product a_x b_y - a_y b_x over the last axis."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


# ----------------------------------------------------------------------------- differentiable parts


def _pixel_xy(pixel: torch.Tensor, h: int, w: int, dtype) -> torch.Tensor:
    """Flat pixel indices (Q,) -> (Q, 2) crop-grid coordinates (x, y) of their centres."""
    r = pixel % (h * w)
    return torch.stack([r % w, torch.div(r, w, rounding_mode="floor")], -1).to(dtype)


def _surface_depth(uv_flat, z_flat, V, faces, pixel, view, face, h, w):
    """Camera z of face `face` of view `view` at the centres of `pixel` (Q,), differentiable."""
    idx = view[:, None] * V + faces[face]  # (Q, 3)
    tri = uv_flat[idx]  # (Q, 3, 2)
    tz = z_flat[idx]  # (Q, 3)
    p = _pixel_xy(pixel, h, w, uv_flat.dtype)[:, None, :]  # (Q, 1, 2)
    rel = tri - p
    bary = _cross(rel.roll(-1, dims=1), rel.roll(-2, dims=1))  # (Q, 3) un-normalised barycentrics
    area2 = bary.sum(-1, keepdim=True)
    return area2.squeeze(-1) / (bary / tz).sum(-1)  # 1 / sum_k (b_k / z_k) with b normalised


def _outline_distance(uv_flat, V, pixel, view, a, b, h, w):
    """Unsigned distance (Q,) from pixel centres to edge (a, b) of their view, differentiable."""
    A = uv_flat[view * V + a]  # (Q, 2)
    Bv = uv_flat[view * V + b]
    p = _pixel_xy(pixel, h, w, uv_flat.dtype)
    d = Bv - A
    pa = p - A
    L2 = (d * d).sum(-1).clamp(min=1e-12)
    s = (pa * d).sum(-1) / L2
    line = _cross(d, pa).abs() / L2.sqrt()
    end = torch.where((s <= 0)[:, None], A, Bv)
    point = ((p - end) ** 2).sum(-1).add(1e-12).sqrt()
    return torch.where((s > 0) & (s < 1), line, point)


# ----------------------------------------------------------------------------- render


def render(
    vertices_world: torch.Tensor,
    mesh,
    cameras: Cameras,
    crops: torch.Tensor | None = None,
    size=(96, 96),
    sigma: float = 0.6,
    *,
    cull_backfaces: bool = True,
    margin: float = 0.1,
    band_sigmas: float = 5.0,
    znear: float = 0.05,
    max_radius: float = 3.0,
    max_pairs: int = 1 << 21,
) -> RenderOutput:
    """Soft silhouette and depth of a mesh in B frames x C views.

    vertices_world: (B, V, 3) or (V, 3) world coordinates (metres); mesh: faces
    (F, 3) or a `MeshTopology` (build it once per mesh: faster); cameras: C views;
    crops: (B, C, 4) or (C, 4) boxes x0, y0, x1, y1 in full-image pixels, or None
    for `object_crops(vertices, cameras, size, margin)`; size: (h, w) output grid;
    sigma: silhouette edge softness in output pixels.
    Gradients flow to `vertices_world` (and camera parameters); crops are constants.
    Faces with a vertex at z <= znear, or outside the region where the distortion
    model is invertible, are not drawn.
    """
    topo = mesh if isinstance(mesh, MeshTopology) else MeshTopology.from_faces(mesh)
    if topo.faces.device != vertices_world.device:
        topo = topo.to(vertices_world.device)
    verts = vertices_world if vertices_world.dim() == 3 else vertices_world[None]
    if verts.dim() != 3 or verts.shape[-1] != 3:
        raise ValueError(f"rendering: vertices must be (B, V, 3) or (V, 3), got {tuple(vertices_world.shape)}")
    if not verts.is_floating_point():
        raise ValueError("rendering: vertices must be a floating tensor")
    B, V, _ = verts.shape
    if topo.faces.numel() and int(topo.faces.max()) >= V:
        raise ValueError(f"rendering: faces index vertex {int(topo.faces.max())} but only {V} vertices given")
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
    N = B * C

    pix, z = project(verts.reshape(B * V, 3), cameras)  # (C, BV, 2), (C, BV)
    pix = pix.reshape(C, B, V, 2).transpose(0, 1).reshape(N, V, 2)
    z = z.reshape(C, B, V).transpose(0, 1).reshape(N, V)
    box = crops.reshape(N, 4)
    scale = _crop_scale(box, h, w)  # (N, 2)
    uv = (pix - box[:, None, :2]) / scale[:, None, :] - 0.5  # (N, V, 2) crop-grid coordinates

    faces = topo.faces
    band = band_sigmas * sigma
    with torch.no_grad():
        valid_v = _vertex_validity(verts.detach(), cameras, znear, max_radius).reshape(N, V)
        uv_d, z_d = uv.detach(), z.detach()
        uv_d = torch.where(valid_v[..., None], uv_d, torch.zeros_like(uv_d))  # keep garbage out of the maths
        z_d = torch.where(valid_v, z_d, torch.ones_like(z_d))
        valid_f = valid_v[:, faces].all(-1)  # (N, F)
        p_cam = _camera_points(verts.detach(), cameras).reshape(N, V, 3)
        tri = p_cam[:, faces]  # (N, F, 3, 3)
        normal = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
        front = (normal * tri[:, :, 0]).sum(-1) < 0  # (N, F) faces the camera
        rendered = valid_f & front if cull_backfaces else valid_f
        covered, (d_pixel, d_view, d_face) = _rasterize(uv_d, z_d, faces, rendered, h, w, max_pairs)
        c_view, c_a, c_b, c_t = _contours(topo, rendered, front)
        s_pixel, s_item = _nearest_outline_edges(uv_d, covered, c_view, c_a, c_b, c_t, h, w, band, max_pairs)

    uv_flat = uv.reshape(N * V, 2)
    z_flat = z.reshape(N * V)
    depth_vals = _surface_depth(uv_flat, z_flat, V, faces, d_pixel, d_view, d_face, h, w)
    depth = torch.zeros(N * h * w, dtype=verts.dtype, device=verts.device).index_put((d_pixel,), depth_vals)

    dist = _outline_distance(uv_flat, V, s_pixel, c_view[s_item], c_a[s_item], c_b[s_item], h, w)
    signed = torch.where(covered[s_pixel], dist, -dist).clamp(-band, band)
    lo = torch.sigmoid(torch.tensor(-band_sigmas, dtype=verts.dtype))
    soft = (torch.sigmoid(signed / sigma) - lo) / (1 - 2 * lo)
    silhouette = covered.to(verts.dtype).index_put((s_pixel,), soft)

    return RenderOutput(
        silhouette=silhouette.reshape(B, C, h, w),
        depth=depth.reshape(B, C, h, w),
        coverage=covered.reshape(B, C, h, w),
        crops=crops,
        in_image=_in_image(crops, cameras, B, h, w),
    )


def _camera_points(vertices_world: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """(B, V, 3) world -> (B, C, V, 3) camera-frame points."""
    B, V, _ = vertices_world.shape
    p = world_to_camera(vertices_world.reshape(B * V, 3), cameras.T_cam_from_world)  # (C, BV, 3)
    return p.reshape(len(cameras), B, V, 3).transpose(0, 1)


# ----------------------------------------------------------------------------- observations


def crop_observation(image: torch.Tensor, crops: torch.Tensor, size=(96, 96), mode: str = "area") -> torch.Tensor:
    """Resample full images (..., C, H, W) to the render grid of crops (..., C, 4) -> (..., C, h, w).

    mode 'area': exact box filter, each output pixel the area-weighted mean of
    the input pixels its footprint overlaps (for masks: the covered fraction;
    outside the image counts as 0). 'nearest': the input pixel nearest the output
    pixel centre (for depth: no mixing across edges). 'min': the smallest
    non-zero value within the footprint (depth, front-most; 0 = missing stays 0).
    Pixels outside the image read 0. Output is floating (float32 for integer input).
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
    if mode == "nearest":
        u = box[:, 0, None] + (torch.arange(w, device=img.device, dtype=img.dtype) + 0.5) * s[:, 0, None]  # (N, w)
        v = box[:, 1, None] + (torch.arange(h, device=img.device, dtype=img.dtype) + 0.5) * s[:, 1, None]  # (N, h)
        iu, iv = torch.floor(u + 0.5).long(), torch.floor(v + 0.5).long()
        ok = ((iv >= 0) & (iv < H))[:, :, None] & ((iu >= 0) & (iu < W))[:, None, :]
        out = img[n_idx[:, None, None], iv.clamp(0, H - 1)[:, :, None], iu.clamp(0, W - 1)[:, None, :]]
        return torch.where(ok, out, torch.zeros_like(out)).reshape(*lead, h, w)
    ix, wx = _footprint(box[:, 0], s[:, 0], w, W)  # (N, w, Kx)
    iy, wy = _footprint(box[:, 1], s[:, 1], h, H)  # (N, h, Ky)
    vals = img[n_idx[:, None, None, None, None], iy[:, :, :, None, None], ix[:, None, None, :, :]]  # (N, h, Ky, w, Kx)
    weight = wy[:, :, :, None, None] * wx[:, None, None, :, :]
    if mode == "area":
        out = (vals * weight).sum((2, 4)) / (s[:, 0] * s[:, 1])[:, None, None]
    else:
        big = torch.full_like(vals, float("inf"))
        out = torch.where((weight > 0) & (vals > 0), vals, big).amin(dim=(2, 4))
        out = torch.where(torch.isfinite(out), out, torch.zeros_like(out))
    return out.reshape(*lead, h, w)


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
