"""Closest points on a mesh: `intercap.geometry.surfaces.TriangleSurface` (open3d's raycasting scene
picks the triangle, the point on it in float64) and open3d's `compute_closest_points` alone, against
an exact float64 search (the former `TriangleSurface`: KD-trees of triangle centroids), on the
inputs the pipeline gives them.

The uses measured: depth points and other meshes' samples near the fitted body (evaluation's
body-surface error, `tools/bench_body.py`'s cloud-to-mesh figures) and points near or rotated
samples on the object meshes (`geometry.symmetry`, which the object and global stages fit with;
evaluation's penetration and contact; the export's scene colours; the report's cloud-to-object
curves and contact heat map). Each row: the time to build the search structure and answer the
queries, and the largest differences of the closest points and of the distances from the exact
search's; then whether `detect_symmetry` finds the same symmetries, and `signed_distance` the same
sides, with either search.

    OMP_NUM_THREADS=1 python -m tools.bench_surfaces [--points 20000] [--repeat 3]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from intercap.geometry.surfaces import TriangleSurface, closest_points_on_triangles, sample_surface


def body_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The default body model's (anny) mesh in its initial pose: vertices (V, 3) float64, faces (F, 3)."""
    import torch

    from intercap.body_models import shared_model
    from intercap.config import BodyModelConfig

    model = shared_model(BodyModelConfig())
    with torch.no_grad():
        vertices = model(model.init_params(1)).vertices[0]
    return vertices.double().numpy(), model.faces.numpy()


def object_meshes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The synthetic sessions' props and the sample session's object."""
    from pathlib import Path

    import trimesh

    from intercap.synth.objects import box_mesh, chair_mesh, cup_mesh

    meshes = {"box": box_mesh(), "cup": cup_mesh(), "chair": chair_mesh()}
    sample = Path(__file__).resolve().parents[1] / "data_samples" / "sample" / "object.ply"
    if sample.is_file():
        meshes["sample object"] = trimesh.load(sample, process=False)
    return {name: (np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)) for name, m in meshes.items()}


def points_near(vertices, faces, n: int, spread_m: float, rng) -> np.ndarray:
    """n points (n, 3): surface samples moved up to `spread_m` in a random direction."""
    p = sample_surface(vertices, faces, n, rng)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return p + direction * rng.uniform(0, spread_m, (n, 1))


def rotated_samples(vertices, faces, n: int, rng) -> np.ndarray:
    """Surface samples turned about the centroid (what `detect_symmetry` queries)."""
    from scipy.spatial.transform import Rotation

    p = sample_surface(vertices, faces, n, rng)
    centre = p.mean(0)
    R = Rotation.from_rotvec(rng.normal(size=3) * 0.5).as_matrix()
    return (p - centre) @ R.T + centre


class KdTreeSurface(TriangleSurface):
    """The former `TriangleSurface` search, exact in float64 (the reference here): triangles grouped
    by size (centroid-to-corner radius, in doublings of the median), one centroid KD-tree per group;
    a point's candidates are the k triangles with the nearest centroids in each group, screened in
    float32, and every triangle of a group that the k-th centroid distance does not rule out (less
    the group's largest radius) is tested too in float64."""

    def __init__(self, vertices, faces, k: int = 6):
        from scipy.spatial import cKDTree

        super().__init__(vertices, faces)
        centroids = self.tri.mean(1)  # (F, 3)
        radius = np.linalg.norm(self.tri - centroids[:, None], axis=2).max(1)  # (F,)
        ref = max(float(np.median(radius)), 1e-12)
        level = np.ceil(np.log2(np.maximum(radius / ref, 1.0))).astype(np.int64)
        self.groups = []  # (face ids, KD-tree of their centroids, largest radius, k)
        for lv in np.unique(level):
            ids = np.flatnonzero(level == lv)
            tree = cKDTree(centroids[ids], balanced_tree=False, compact_nodes=False)
            self.groups.append((ids, tree, float(radius[ids].max()), int(min(k, len(ids)))))
        self.tri32 = self.tri.astype(np.float32)

    def closest_faces(self, points):
        return np.concatenate([self.closest_faces_of_chunk(points[s:s + 20000])
                               for s in range(0, len(points), 20000)])

    def closest_faces_of_chunk(self, p):
        n = len(p)
        workers = -1 if n >= 8192 else 1
        cand, kth = [], []
        for ids, tree, _, k in self.groups:
            dk, j = tree.query(p, k, workers=workers)
            cand.append(ids[j.reshape(n, -1)])
            kth.append(dk.reshape(n, -1)[:, -1] if k < len(ids) else np.full(n, np.inf))
        cand = np.concatenate(cand, axis=1)  # (N, C)
        t = self.tri32[cand]  # (N, C, 3, 3)
        p32 = p.astype(np.float32)[:, None]
        q, _ = closest_points_on_triangles(p32, t[..., 0, :], t[..., 1, :], t[..., 2, :])
        j = np.linalg.norm(q - p32, axis=-1).argmin(1)
        best_f = cand[np.arange(n), j]
        t = self.tri[best_f]  # the winner's distance in float64, for the bounds below
        best_d = np.linalg.norm(closest_points_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])[0] - p, axis=1)
        for (ids, tree, r_max, _), dk in zip(self.groups, kth):
            unsure = np.flatnonzero(dk - r_max < best_d)
            if len(unsure) == 0:
                continue
            balls = tree.query_ball_point(p[unsure], best_d[unsure] + r_max, workers=workers)
            counts = np.fromiter((len(b) for b in balls), np.int64, len(balls))
            if counts.sum() == 0:
                continue
            owner = np.repeat(unsure, counts)  # (M,)
            faces = ids[np.concatenate([np.asarray(b, np.int64) for b in balls])]
            t = self.tri[faces]
            qq, _ = closest_points_on_triangles(p[owner], t[:, 0], t[:, 1], t[:, 2])
            dd = np.linalg.norm(qq - p[owner], axis=1)
            order = np.lexsort((dd, owner))
            first = order[np.r_[True, owner[order][1:] != owner[order][:-1]]]
            better = dd[first] < best_d[owner[first]]
            best_d[owner[first[better]]] = dd[first[better]]
            best_f[owner[first[better]]] = faces[first[better]]
        return best_f


def kd_tree(vertices, faces, points):
    d, q, face, _ = KdTreeSurface(vertices, faces).closest(points)
    return d, q, face


def open3d_alone(vertices, faces, points):
    """open3d's closest points as it gives them (float32)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    answer = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    q = answer["points"].numpy().astype(np.float64)
    return np.linalg.norm(q - points, axis=1), q, answer["primitive_ids"].numpy().astype(np.int64)


def triangle_surface(vertices, faces, points):
    """Today's `TriangleSurface`: open3d picks the triangle, the point on it in float64."""
    d, q, face, _ = TriangleSurface(vertices, faces).closest(points)
    return d, q, face


def timed(fn, repeat: int, *args):
    best, out = np.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - start)
    return best, out


def compare(name: str, vertices, faces, points, repeat: int) -> None:
    t_ref, (d0, q0, f0) = timed(kd_tree, repeat, vertices, faces, points)
    row = f"{name:<26} {len(points):>7} {t_ref:>8.3f}"
    for fn in (open3d_alone, triangle_surface):
        t, (d, q, f) = timed(fn, repeat, vertices, faces, points)
        row += (f" | {t:>8.3f} {1e6 * np.abs(q - q0).max():>9.3f} {1e6 * np.abs(d - d0).max():>9.3f}"
                f" {int((f != f0).sum()):>6}")
    print(row, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"{'':<26} {'':>7} {'KD-tree':>8} | {'open3d alone':^36} | {'TriangleSurface':^36}")
    columns = f" | {'s':>8} {'max dq um':>9} {'max dd um':>9} {'faces':>6}"
    print(f"{'mesh, points':<26} {'points':>7} {'s':>8}" + columns * 2)
    v, f = body_mesh()
    for n in (2000, args.points):
        compare("body, 5 cm around", v, f, points_near(v, f, n, 0.05, rng), args.repeat)
    compare("body, 0.5 m around", v, f, points_near(v, f, args.points, 0.5, rng), args.repeat)
    for name, (v, f) in object_meshes().items():
        compare(f"{name}, rotated", v, f, rotated_samples(v, f, 2000, rng), args.repeat)
        compare(f"{name}, 2 cm around", v, f, points_near(v, f, args.points, 0.02, rng), args.repeat)
    print("faces: points whose closest triangle differs from the KD-tree's (ties: equally near within float32)")
    meshes = object_meshes()
    symmetries_agree(meshes)
    signs_agree(meshes, args.points, rng)


def signs_agree(meshes, n: int, rng) -> None:
    """Signed distances (evaluation's penetration and contact) of points near each object, both searches."""
    for name, (v, f) in meshes.items():
        p = points_near(v, f, n, 0.02, rng)
        exact, now = KdTreeSurface(v, f).signed_distance(p), TriangleSurface(v, f).signed_distance(p)
        print(f"signed distance, {name}: max difference {1e6 * np.abs(now - exact).max():.3f} um, "
              f"{int((np.sign(now) != np.sign(exact)).sum())} of {n} points on the other side")


def symmetries_agree(meshes) -> None:
    """`detect_symmetry` of each object with the exact search and with `TriangleSurface`."""
    import trimesh

    from intercap.geometry import symmetry

    for name, (v, f) in meshes.items():
        mesh = trimesh.Trimesh(v, f, process=False)
        found = symmetry.detect_symmetry(mesh).description
        symmetry.TriangleSurface = KdTreeSurface
        try:
            exact = symmetry.detect_symmetry(mesh).description
        finally:
            symmetry.TriangleSurface = TriangleSurface
        print(f"symmetry of {name}: {'same' if found == exact else 'DIFFERENT'} ({found})")


if __name__ == "__main__":
    main()
