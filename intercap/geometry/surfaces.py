"""Exact point-to-triangle distances (open3d finds the closest triangle, numpy measures it in
float64) and surface sampling: the comparisons of surfaces that evaluation and the stages share,
whatever the meshes' topologies."""
from __future__ import annotations

import numpy as np


def closest_points_on_triangles(p, a, b, c):
    """Closest point on triangle (a, b, c) to p, and which feature it lies on.

    All inputs broadcast to (..., 3). Returns q (..., 3) and region (...,):
    0 face interior, 1/2/3 vertex a/b/c, 4/5/6 edge ab/bc/ca (the Voronoi
    regions of the triangle, tested in the order of Ericson, Real-Time
    Collision Detection 5.1.5). Works on barycentric weights (v, w) so that
    q = a + v ab + w ac is formed once.
    """
    ab, ac = b - a, c - a
    ap = p - a
    d1, d2 = np.einsum("...i,...i->...", ab, ap), np.einsum("...i,...i->...", ac, ap)
    ab_ab, ab_ac, ac_ac = (np.einsum("...i,...i->...", x, y) for x, y in ((ab, ab), (ab, ac), (ac, ac)))
    d3, d4 = d1 - ab_ab, d2 - ab_ac  # ab.(p-b), ac.(p-b)
    d5, d6 = d1 - ab_ac, d2 - ac_ac  # ab.(p-c), ac.(p-c)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2

    def ratio(num, den):
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.clip(np.where(den != 0, num / np.where(den != 0, den, 1.0), 0.0), 0.0, 1.0)

    den = va + vb + vc
    den = np.where(den == 0, 1.0, den)
    v, w = vb / den, vc / den
    region = np.zeros(v.shape, np.int8)
    zero, one = np.zeros_like(v), np.ones_like(v)
    t_ab, t_ac = ratio(d1, d1 - d3), ratio(d2, d2 - d6)
    t_bc = ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    cases = [  # (mask, v, w, region code) in Ericson's order; the first that holds wins
        ((d1 <= 0) & (d2 <= 0), zero, zero, 1),
        ((d3 >= 0) & (d4 <= d3), one, zero, 2),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), t_ab, zero, 4),
        ((d6 >= 0) & (d5 <= d6), zero, one, 3),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), zero, t_ac, 6),
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 1.0 - t_bc, t_bc, 5),
    ]
    for mask, cv, cw, code in reversed(cases):
        v, w = np.where(mask, cv, v), np.where(mask, cw, w)
        region = np.where(mask, np.int8(code), region)
    q = a + v[..., None] * ab + w[..., None] * ac
    return q, region


class TriangleSurface:
    """A triangle mesh prepared for exact closest-point and signed-distance queries.

    open3d's raycasting scene (Embree's bounding-volume hierarchy, float32) finds each point's
    closest triangle; the point on that triangle, the feature it lies on and the distance are
    computed again in float64 (`closest_points_on_triangles`). Where two triangles are equally
    near within float32 the scene may pick either: the distance is the same to float32's
    resolution, the closest point may be the other one (tools/bench_surfaces.py compares them with
    an exact float64 search). The scene is built on first use and not pickled (it cannot be).
    """

    def __init__(self, vertices, faces):
        self.vertices = np.asarray(vertices, np.float64)  # (V, 3)
        self.faces = np.asarray(faces, np.int64)  # (F, 3)
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise ValueError(f"faces must be a non-empty (F, 3) array, got {self.faces.shape}")
        self.tri = self.vertices[self.faces]  # (F, 3, 3)
        self._scene = None
        self._normals = None

    def __getstate__(self):
        return {**self.__dict__, "_scene": None}

    def closest(self, points):
        """Distance (N,), closest point (N, 3), face (N,) and region (N,) for points (N, 3)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        face = self.closest_faces(points)
        t = self.tri[face]
        q, region = closest_points_on_triangles(points, t[:, 0], t[:, 1], t[:, 2])
        return np.linalg.norm(q - points, axis=1), q, face, region

    def closest_faces(self, points):
        """Index (N,) of the triangle closest to each point (N, 3), chosen in float32."""
        import open3d as o3d

        if not np.isfinite(points).all():
            raise ValueError("closest points of non-finite points (nan or inf) asked for")
        if self._scene is None:
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                      o3d.core.Tensor(self.faces.astype(np.uint32)))
        query = o3d.core.Tensor(np.ascontiguousarray(points, np.float32))
        return self._scene.compute_closest_points(query)["primitive_ids"].numpy().astype(np.int64)

    def _pseudonormals(self):
        """Face, angle-weighted vertex and edge normals (Baerentzen & Aanaes), for the inside test."""
        if self._normals is None:
            f, tri = self.faces, self.tri
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3)
            fn = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
            if _signed_volume(self.vertices, f) < 0:  # inward winding: flip so that outside is +
                fn = -fn
            vn = np.zeros_like(self.vertices)
            for k in range(3):
                e1, e2 = tri[:, (k + 1) % 3] - tri[:, k], tri[:, (k + 2) % 3] - tri[:, k]
                angle = np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=1), (e1 * e2).sum(1))
                np.add.at(vn, f[:, k], angle[:, None] * fn)
            edges = np.sort(f[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)  # ab, bc, ca per face
            _, inv = np.unique(edges, axis=0, return_inverse=True)
            en = np.zeros((inv.max() + 1, 3))
            np.add.at(en, inv.ravel(), np.repeat(fn, 3, axis=0))
            self._normals = (fn, vn, en, inv.reshape(-1, 3))
        return self._normals

    def signed_distance(self, points):
        """Signed distance (N,) to a closed surface: negative inside, for points (N, 3)."""
        d, q, face, region = self.closest(points)
        fn, vn, en, face_edge = self._pseudonormals()
        normal = fn[face].copy()
        vert = (region >= 1) & (region <= 3)
        normal[vert] = vn[self.faces[face[vert], region[vert] - 1]]
        edge = region >= 4
        normal[edge] = en[face_edge[face[edge], region[edge] - 4]]
        side = ((np.asarray(points, np.float64).reshape(-1, 3) - q) * normal).sum(1)
        return np.where(side < 0, -d, d)


def _signed_volume(vertices, faces) -> float:
    tri = vertices[faces]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def sample_surface(vertices, faces, n: int, rng: np.random.Generator):
    """n points (n, 3) on a mesh, uniform over its area (area-weighted faces, uniform barycentrics)."""
    tri = np.asarray(vertices, np.float64)[faces]  # (F, 3, 3)
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    cdf = np.cumsum(area)
    f = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(cdf) - 1)
    u = rng.random((n, 2))
    flip = u.sum(1) > 1
    u[flip] = 1 - u[flip]
    t = tri[f]
    return t[:, 0] + u[:, :1] * (t[:, 1] - t[:, 0]) + u[:, 1:] * (t[:, 2] - t[:, 0])


def symmetric_surface_distance(verts_a, faces_a, verts_b, faces_b, n: int, rng) -> float:
    """Mean symmetric point-to-surface distance (m) between two meshes of any topology.

    n area-weighted samples on each mesh, each measured to the other mesh's
    surface (exact point-to-triangle); the two means are averaged.
    """
    surf_a, surf_b = TriangleSurface(verts_a, faces_a), TriangleSurface(verts_b, faces_b)
    d_ab = surf_b.closest(sample_surface(verts_a, faces_a, n, rng))[0]
    d_ba = surf_a.closest(sample_surface(verts_b, faces_b, n, rng))[0]
    return 0.5 * (float(d_ab.mean()) + float(d_ba.mean()))
