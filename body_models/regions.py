"""Likely-contact vertex regions and a fitting subsample, computed from a rest mesh.

The regions are derived from skinning (which bone moves a vertex) and the rest
surface normal, so any backend with bones and a rest mesh gets them without a
hand-painted file: palms and finger pads, soles, buttocks and back of thighs,
forearms. They are computed once at model construction (deterministic).
"""
from __future__ import annotations

import numpy as np


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, (V, 3)."""
    tri = vertices[faces]  # (F, 3, 3)
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def palm_normal(wrist: np.ndarray, index_base: np.ndarray, little_base: np.ndarray, side: str) -> np.ndarray:
    """Unit vector out of the palm of a hand at rest.

    Fingers point along d (wrist -> knuckles) and l runs from the little finger
    to the index; a right palm faces l x d, a left palm d x l (anatomy, not a
    convention of the model)."""
    d = (index_base + little_base) / 2 - wrist
    lateral = index_base - little_base
    n = np.cross(lateral, d) if side == "R" else np.cross(d, lateral)
    return n / np.linalg.norm(n)


def contact_regions(
    vertices: np.ndarray,
    faces: np.ndarray,
    dominant_bone: np.ndarray,
    bone_groups: dict[str, list[int]],
    palm_normals: dict[str, np.ndarray],
    up: np.ndarray,
    forward: np.ndarray,
    hip_height: float,
    knee_height: float,
) -> dict[str, np.ndarray]:
    """Vertex ids per likely-contact region on a rest mesh.

    bone_groups: 'hand.L', 'hand.R', 'foot.L', 'foot.R', 'forearm.L',
    'forearm.R', 'thigh', 'pelvis' -> bone indices; dominant_bone (V,) the bone
    with the largest skinning weight per vertex; heights along `up`.
    """
    normals = vertex_normals(vertices, faces)
    height = vertices @ up

    def in_group(name):
        return np.isin(dominant_bone, bone_groups[name])

    regions = {}
    for side, label in (("L", "left"), ("R", "right")):
        hand = in_group(f"hand.{side}")
        regions[f"{label}_hand"] = np.flatnonzero(hand & (normals @ palm_normals[side] > 0.3))
        foot = in_group(f"foot.{side}")
        regions[f"{label}_foot"] = np.flatnonzero(foot & (normals @ -up > 0.5))
        regions[f"{label}_forearm"] = np.flatnonzero(in_group(f"forearm.{side}"))
    seat_band = (height < hip_height + 0.05) & (height > (hip_height + knee_height) / 2)
    backward = normals @ -forward > 0.3
    seat = (in_group("thigh") | in_group("pelvis")) & seat_band & backward
    regions["buttocks"] = np.flatnonzero(seat)
    return regions


def farthest_point_subsample(points: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Ids of `count` well-spread points (greedy farthest-point sampling), sorted."""
    count = min(count, len(points))
    rng = np.random.default_rng(seed)
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = rng.integers(len(points))
    points = np.ascontiguousarray(points, np.float64)
    squared = np.einsum("nd,nd->n", points, points)
    dist = squared - 2 * points @ points[chosen[0]] + squared[chosen[0]]  # squared distances: same argmax
    for k in range(1, count):
        chosen[k] = int(np.argmax(dist))
        np.minimum(dist, squared - 2 * points @ points[chosen[k]] + squared[chosen[k]], out=dist)
    return np.sort(chosen)
