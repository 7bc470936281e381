"""Triangle meshes to binary PLY, written atomically (trimesh, open3d and MeshLab read them).

Vertices are stored as float32 (what the results arrays hold), faces as int32
vertex ids with a uchar count, colours (optional) as uchar RGB per vertex."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from intercap.io.files import atomic_file


def mesh_ply_bytes(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None) -> bytes:
    """The PLY file of a mesh: vertices (V, 3), faces (F, 3) int, colours (V, 3) uint8 or None."""
    vertices = np.asarray(vertices, np.float32).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"face ids must lie in [0, {len(vertices)}), got [{faces.min()}, {faces.max()}]")
    vfields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        vfields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vrec = np.empty(len(vertices), dtype=vfields)
    vrec["x"], vrec["y"], vrec["z"] = vertices.T
    if colors is not None:
        colors = np.asarray(colors, np.uint8).reshape(-1, 3)
        vrec["red"], vrec["green"], vrec["blue"] = colors.T
    frec = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    frec["n"], frec["v"] = 3, faces
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {n}\n" for n, t in vfields)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\n{props}"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    return header.encode("ascii") + vrec.tobytes() + frec.tobytes()


def write_mesh_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write a mesh as binary PLY, atomically (a crash never leaves a truncated file)."""
    path = Path(path)
    with atomic_file(path, ".ply") as tmp:
        tmp.write_bytes(mesh_ply_bytes(vertices, faces, colors))
