"""Geometry shared by the stages, free of any stage: cameras (projection with lens
distortion), point clouds, the ground plane, the differentiable renderer, image
segmentation helpers, exact surface distances and object symmetries. Imports numpy,
torch, open3d, trimesh and nothing else of ours but other geometry modules."""
