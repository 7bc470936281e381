"""The `export` stage's settings (section `export` of the config tree)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ExportConfig:
    """Meshes and one dataset file from the results (the `export` stage)."""

    meshes: bool = True  # OUT/meshes/body_<frame>.ply and object_<frame>.ply
    scene: bool = False  # with `meshes`, also OUT/meshes/scene_<frame>.ply: body + object, contact vertices red
    contact_distance_m: float = 0.02  # scene: vertices this near (m) the other surface in contact frames are red
    # body_vertices in the dataset file as float16: half the size; steps of 1 mm at 1-2 m, 2 mm at 2-4 m
    vertices_float16: bool = False
    # OUT/export/<session>.glb: the take animated (body, object, contact) for Blender / three.js; T*V*12 bytes
    glb: bool = True
    behave: bool = False  # also OUT/export/behave/ in BEHAVE's layout and conventions
    behave_frame: str = "world"  # BEHAVE files in our world frame, or in this camera's frame (BEHAVE uses its k1)
