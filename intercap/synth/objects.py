"""Rigid object meshes for synthetic sessions, with their grasps.

Every object is in metres with its origin at the centre of its bounding box and
+z up when it stands on the floor. Each object also says where hands hold it
(`Grasp`: a palm contact point and the direction the palm pushes, in object
coordinates, for a person standing on the object's -y side and facing +y) and
which of its vertices are likely contact vertices (the faces those grasps use).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from intercap.synth.options import NO_OBJECT, OBJECT_NAMES  # noqa: F401 - re-exported


@dataclass(frozen=True)
class Grasp:
    """Where one palm touches the object, in object coordinates.

    point (3,): palm-centre contact point on the surface; normal (3,): outward
    surface normal there (the palm faces -normal); finger_dir (3,): the direction
    the fingers point along the surface (perpendicular to normal); wraps: whether they close round
    under the part, as round a handle."""

    point: tuple
    normal: tuple
    finger_dir: tuple
    wraps: bool = False  # the fingers close round the part (a handle): it must stick out over a table's edge


@dataclass(frozen=True)
class ObjectSpec:
    """A rigid object: mesh, colour, mass and how the scripts hold it."""

    name: str
    mesh: trimesh.Trimesh = field(repr=False)
    color: tuple  # RGB 0..255
    mass_kg: float
    grasps: dict  # 'left' / 'right' -> Grasp (two-handed grasp); one-hand objects use 'right'
    contact_vertices: np.ndarray = field(repr=False)  # (C,) int, sorted
    sdf_cells: int = 80  # cells along the longest side of the hand solvers' distance grid (more for thin parts)

    @property
    def half_height(self) -> float:
        return float(-self.mesh.bounds[0, 2])


def _box_mesh(extents, max_edge: float) -> trimesh.Trimesh:
    """A closed, evenly subdivided box centred at the origin."""
    mesh = trimesh.creation.box(extents=extents)
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge)
    return trimesh.Trimesh(vertices, faces, process=True)


def box_mesh(extents=(0.30, 0.20, 0.15), max_edge: float = 0.03) -> trimesh.Trimesh:
    """Cardboard box lying flat, 0.30 (x) by 0.20 (y) by 0.15 (z) m."""
    return _box_mesh(extents, max_edge)


def cup_mesh(radius: float = 0.04, height: float = 0.10, sections: int = 32) -> trimesh.Trimesh:
    """Closed cylinder standing on z; side subdivided so the wall has vertices mid-height."""
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=0.025)
    return trimesh.Trimesh(vertices, faces, process=True)


def chair_mesh(width=0.45, depth=0.45, height=0.85, seat_height=0.45, bar=0.04, gap=0.001) -> trimesh.Trimesh:
    """A chair made of closed boxes that never overlap (1 mm gaps between parts).

    Seat, four legs, two back posts rising from the rear (-y) legs and a back
    panel between them. Disjoint closed parts keep the whole mesh watertight
    and make inside/outside tests well defined without a boolean union."""
    parts = []

    def add(lo, hi):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        part = _box_mesh(hi - lo, max_edge=0.06)
        part.apply_translation((lo + hi) / 2)
        parts.append(part)

    hw, hd = width / 2, depth / 2
    seat_lo, seat_hi = seat_height - 0.04, seat_height
    add((-hw, -hd, seat_lo), (hw, hd, seat_hi))  # seat
    for sx in (-1, 1):
        for sy in (-1, 1):
            x0 = hw - bar if sx > 0 else -hw
            y0 = hd - bar if sy > 0 else -hd
            add((x0, y0, 0.0), (x0 + bar, y0 + bar, seat_lo - gap))  # leg
        x0 = hw - bar if sx > 0 else -hw
        add((x0, -hd, seat_hi + gap), (x0 + bar, -hd + bar, height))  # back post
    add((-hw + bar + gap, -hd + 0.01, seat_hi + 0.15), (hw - bar - gap, -hd + 0.03, height - 0.02))  # back panel
    mesh = trimesh.util.concatenate(parts)
    mesh.apply_translation((0.0, 0.0, -height / 2))
    return mesh


def tool_mesh(length=0.60, bar=0.035, head=(0.06, 0.10), gap=0.001) -> trimesh.Trimesh:
    """A long thin tool lying flat (a scraper, a rake) along x: a square handle with a flat head across its
    -x end, both `bar` thick (so it lies on both), as two closed boxes 1 mm apart."""
    hx = length / 2
    handle = _box_mesh((length - head[0] - gap, bar, bar), max_edge=0.02)
    handle.apply_translation(((head[0] + gap) / 2, 0.0, 0.0))
    top = _box_mesh((head[0], head[1], bar), max_edge=0.02)
    top.apply_translation((head[0] / 2 - hx, 0.0, 0.0))
    return trimesh.util.concatenate([handle, top])


def ball_mesh(radius: float = 0.11, subdivisions: int = 3) -> trimesh.Trimesh:
    """A ball: an icosphere, evenly meshed (trimesh's has a vertex on each axis: the bounding box is
    centred at the origin and its lowest vertex lies at -radius)."""
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


def _vertices_near(mesh: trimesh.Trimesh, points, normals, radius: float) -> np.ndarray:
    """Vertices within `radius` of any grasp point whose vertex normal agrees with the grasp normal."""
    verts = np.asarray(mesh.vertices)
    vnormals = np.asarray(mesh.vertex_normals)
    keep = np.zeros(len(verts), dtype=bool)
    for p, n in zip(points, normals):
        close = np.linalg.norm(verts - np.asarray(p), axis=1) < radius
        facing = vnormals @ np.asarray(n) > 0.5
        keep |= close & facing
    return np.flatnonzero(keep)


def _end_grasps(hx: float, z: float, finger_dir) -> dict:
    """Both palms on the two x ends of an object at height z (object coordinates), fingers along finger_dir."""
    return {"right": Grasp((hx, -0.01, z), (1.0, 0.0, 0.0), finger_dir),
            "left": Grasp((-hx, -0.01, z), (-1.0, 0.0, 0.0), finger_dir)}


def _carton():
    """A 2 kg carton, 0.30 x 0.22 x 0.18 m: palms on the two short ends, fingers forward and down (they end
    above its base, so the hands never reach the surface it stands on)."""
    mesh = _box_mesh((0.30, 0.22, 0.18), max_edge=0.03)
    grasps = _end_grasps(float(mesh.bounds[1, 0]), 0.03, (0.0, 0.6, -0.8))
    return mesh, grasps, dict(color=(190, 150, 100), mass_kg=2.0, radius=0.13), None, None


def _flat_box():
    """A flat 1 kg box, 0.40 x 0.30 x 0.06 m (a pizza or board-game box): palms on the two short ends,
    fingers pointing forward and up to hook over the lid's edge, so no finger dips below its base."""
    mesh = _box_mesh((0.40, 0.30, 0.06), max_edge=0.03)
    grasps = _end_grasps(float(mesh.bounds[1, 0]), 0.005, (0.0, 0.6, 0.8))
    # fingers hook over its 6 cm lid's edge: a finer distance grid than 1/80 of 0.5 m (4 mm cells, not 6)
    return mesh, grasps, dict(color=(70, 100, 160), mass_kg=1.0, radius=0.10, sdf_cells=125), None, None


def _tool():
    """A 0.8 kg tool 0.60 m long (`tool_mesh`), held in the right hand alone by the end of its handle
    (+x), palm on top and fingers forward, closing round under it: it rests with that end out over a
    table's edge, as one leaves a pan or a hammer to pick it up again (table_lift then holds it upright)."""
    mesh = tool_mesh()
    top = float(mesh.bounds[1, 2])
    grasps = {"right": Grasp((0.245, 0.0, top), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), wraps=True)}
    points = [(0.245, 0.0, top), (0.245, top, 0.0), (0.245, 0.0, -top)]
    normals = [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.0, 0.0, -1.0)]
    # a 3.5 cm handle wants a finer distance grid than 1/80 of the tool's 0.7 m (4 mm cells, not 9)
    spec = dict(color=(215, 180, 40), mass_kg=0.8, radius=0.045, sdf_cells=175)
    return mesh, grasps, spec, points, normals


def _ball():
    """A 0.5 kg ball of radius 0.11 m: palms on its two sides at the equator, fingers forward."""
    mesh = ball_mesh()
    r = float(mesh.bounds[1, 0])
    grasps = {"right": Grasp((r, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
              "left": Grasp((-r, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0))}
    return mesh, grasps, dict(color=(225, 110, 40), mass_kg=0.5, radius=0.07), None, None


# objects built by their own function: name -> () -> (mesh, grasps, spec, contact points, contact normals)
_BUILDERS = {"carton": _carton, "flat_box": _flat_box, "tool": _tool, "ball": _ball}


def make_object(name: str) -> ObjectSpec:
    """The named object (`OBJECT_NAMES`) with its grasps and contact vertices (by default the faces
    round its grasp points)."""
    contact_points = contact_normals = None
    if name == "box":
        mesh = box_mesh()
        hx = mesh.bounds[1, 0]
        # Hands on the two short ends, fingers pointing forward and down.
        down_fwd = (0.0, 0.6, -0.8)
        grasps = {
            "right": Grasp((hx, -0.01, 0.025), (1.0, 0.0, 0.0), down_fwd),
            "left": Grasp((-hx, -0.01, 0.025), (-1.0, 0.0, 0.0), down_fwd),
        }
        spec = dict(color=(176, 128, 72), mass_kg=1.2, radius=0.13)
    elif name == "cup":
        mesh = cup_mesh()
        r = float(mesh.bounds[1, 0])
        # One right hand wraps the wall from the person's right side, fingers around the front.
        grasps = {"right": Grasp((r, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))}
        spec = dict(color=(200, 45, 45), mass_kg=0.3, radius=0.06)
        contact_points = [(r * np.cos(a), r * np.sin(a), 0.0) for a in np.linspace(-np.pi / 2, np.pi / 2, 7)]
        contact_normals = [(np.cos(a), np.sin(a), 0.0) for a in np.linspace(-np.pi / 2, np.pi / 2, 7)]
    elif name == "chair":
        mesh = chair_mesh()
        top = float(mesh.bounds[1, 2])
        hw = float(mesh.bounds[1, 0])
        hd = float(mesh.bounds[1, 1])
        # Both palms on top of the back posts (rear, -y), pushing down and forward.
        grasps = {
            "right": Grasp((hw - 0.02, -hd + 0.02, top), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
            "left": Grasp((-hw + 0.02, -hd + 0.02, top), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
        }
        spec = dict(color=(60, 110, 190), mass_kg=4.5, radius=0.08)
    elif name == "block":
        # A small wooden block (tossed and caught): palms on its two short ends, fingers forward.
        mesh = _box_mesh((0.16, 0.10, 0.08), max_edge=0.02)
        hx = mesh.bounds[1, 0]
        grasps = {
            "right": Grasp((hx, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
            "left": Grasp((-hx, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
        }
        spec = dict(color=(214, 170, 60), mass_kg=0.5, radius=0.06)
    elif name == "board":
        # A thin board (a tray, a drawing board): 2 cm thick, palms on its two short edges. Depth sees it
        # as little more than a plane, and a grid of 2 cm cells hardly sees inside it.
        mesh = _box_mesh((0.40, 0.30, 0.02), max_edge=0.03)
        hx = mesh.bounds[1, 0]
        grasps = {
            "right": Grasp((hx, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.6, -0.8)),
            "left": Grasp((-hx, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.6, -0.8)),
        }
        spec = dict(color=(90, 160, 110), mass_kg=0.9, radius=0.10)
    elif name in _BUILDERS:
        mesh, grasps, spec, contact_points, contact_normals = _BUILDERS[name]()
    else:
        raise ValueError(f"unknown object {name!r}; choose one of {OBJECT_NAMES}")
    if contact_points is None:
        contact_points = [g.point for g in grasps.values()]
        contact_normals = [g.normal for g in grasps.values()]
    contact = _vertices_near(mesh, contact_points, contact_normals, spec.pop("radius"))
    return ObjectSpec(name=name, mesh=mesh, grasps=grasps, contact_vertices=contact, **spec)


class SurfaceDistance:
    """Signed distance to a closed mesh (> 0 outside, < 0 inside), open3d ray casting."""

    def __init__(self, mesh: trimesh.Trimesh):
        import open3d as o3d

        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
            o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
        )

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points in object coordinates -> (N,) signed distances, metres."""
        import open3d as o3d

        pts = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
        # the inside test casts rays; one ray grazing an edge can flip the sign, so take a vote of three
        return self.scene.compute_signed_distance(pts, nsamples=3).numpy().astype(np.float64)


class SdfGrid:
    """Signed distance of a mesh sampled on a regular grid, queried with
    trilinear interpolation in torch (differentiable: used to keep hands out of
    the object and fingers on its surface). > 0 outside, metres."""

    def __init__(self, mesh: trimesh.Trimesh, margin: float = 0.05, max_cells: int = 80):
        import torch

        lo = np.asarray(mesh.bounds[0]) - margin
        hi = np.asarray(mesh.bounds[1]) + margin
        spacing = max(float((hi - lo).max()) / max_cells, 0.003)
        shape = np.ceil((hi - lo) / spacing).astype(int) + 1
        axes = [lo[k] + spacing * np.arange(shape[k]) for k in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        values = SurfaceDistance(mesh)(grid).reshape(*shape)  # (X, Y, Z)
        # grid_sample wants (N, C, D, H, W) with x indexing W: store as (Z, Y, X).
        self.volume = torch.as_tensor(values.transpose(2, 1, 0)[None, None], dtype=torch.float32)
        self.lo = torch.as_tensor(lo, dtype=torch.float32)
        self.hi = torch.as_tensor(lo + spacing * (shape - 1), dtype=torch.float32)

    def __call__(self, points):
        """(..., 3) torch points in object coordinates -> (...) signed distances."""
        import torch
        import torch.nn.functional as F

        shape = points.shape[:-1]
        p = points.reshape(-1, 3).to(self.volume.dtype)
        inside = torch.minimum(torch.maximum(p, self.lo), self.hi)
        outside = (p - inside).norm(dim=-1)  # distance beyond the grid box
        norm = 2 * (inside - self.lo) / (self.hi - self.lo) - 1  # (N, 3) in [-1, 1], x y z
        sample = F.grid_sample(self.volume, norm[None, None, None], align_corners=True, padding_mode="border")
        return (sample.reshape(-1) + outside).reshape(shape).to(points.dtype)
