"""Synthetic capture sessions with ground truth.

An anny body performs a scripted interaction with a rigid object
(intercap/synth/motions.py, intercap/synth/objects.py); N calibrated cameras on a ring render it
headless with pyrender (colour, depth, person and object masks), the renders
get a real lens distortion (cv2.remap), Kinect-like depth noise and holes, and
simulated OpenPose detections. Everything is written in the session format of
docs/session_format.md, with ground_truth/.

    python -m intercap.synth OUT --preset sample
    python -m intercap.synth OUT --script lift_drink --cameras 6 --width 640 --height 576
    python -m intercap.synth OUT --script table_lift --object flat_box --no-masks --no-keypoints --camera-world
    python -m intercap.synth OUT --script sit_stand            # the person alone (also bend, walk_out)
    python -m intercap.synth OUT --script turn --object none   # any script's body motion, no object

The same seed gives byte-identical npy/json/png files.
"""
from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import dataclasses
import io
import json
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh
import yaml

from intercap.parallel import cpu_count
# the settings and the command line, light to import (`--help`), re-exported from here
from intercap.synth.options import (  # noqa: F401
    NO_OBJECT, OBJECT_NAMES, PRESETS, SCRIPT_NAMES, SynthConfig, _floats, apply_preset, build_arg_parser,
    config_from_args,
)

WORLD_NOTE = "metres; any right-handed frame; gravity is not assumed to be an axis"
FLOOR_TILE = 0.5


# ----------------------------------------------------------------------------- cameras
@dataclass
class Camera:
    """A pinhole camera with OpenCV distortion; T_world_from_cam in OpenCV axes (x right, y down, z forward)."""

    name: str
    width: int
    height: int
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (5,)
    T_world_from_cam: np.ndarray  # (4, 4)

    def to_json(self) -> dict:
        return {
            "name": self.name, "width": self.width, "height": self.height,
            "K": np.round(self.K, 6).tolist(), "dist": np.round(self.dist, 8).tolist(),
            "T_world_from_cam": np.round(self.T_world_from_cam, 9).tolist(),
        }


def look_at_pose(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) T_world_from_cam of an OpenCV camera at `eye` looking at `target`."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def ring_cameras(cfg: SynthConfig) -> list[Camera]:
    """N cameras evenly on a ring around the action, with small per-camera differences."""
    rng = np.random.default_rng([cfg.seed, 101])
    j = cfg.camera_jitter
    cams = []
    for i in range(cfg.cameras):
        az = np.radians(cfg.ring_offset_deg) + 2 * np.pi * i / cfg.cameras + j * rng.normal(0, 0.03)
        radius = cfg.ring_radius * (1 + j * rng.normal(0, 0.02))
        eye = np.array([radius * np.cos(az), radius * np.sin(az), cfg.ring_height + j * rng.normal(0, 0.05)])
        target = np.asarray(cfg.look_at, float) + j * rng.normal(0, 0.05, 3) * np.array([1, 1, 0.5])
        f = cfg.focal_scale * cfg.width * (1 + j * rng.normal(0, 0.01))
        K = np.array([[f, 0, (cfg.width - 1) / 2 + j * rng.normal(0, 0.01 * cfg.width)],
                      [0, f * (1 + j * rng.normal(0, 0.002)), (cfg.height - 1) / 2 + j * rng.normal(0, 0.01 * cfg.height)],
                      [0, 0, 1]])
        dist = np.asarray(cfg.dist, float) * (1 + j * rng.normal(0, 0.1, 5))
        cams.append(Camera(f"cam{i}", cfg.width, cfg.height, K, dist, look_at_pose(eye, target)))
    return cams


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV's radial-tangential model on normalised coordinates (..., 2)."""
    k1, k2, p1, p2, k3 = (list(dist) + [0.0] * 5)[:5]
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], -1)


def project(points_world: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> distorted pixels (N, 2) and camera depth z (N,)."""
    T = np.linalg.inv(cam.T_world_from_cam)
    pc = points_world @ T[:3, :3].T + T[:3, 3]
    z = pc[:, 2]
    xy = pc[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None]
    xy = distort_normalized(xy, cam.dist)
    uv = xy * np.array([cam.K[0, 0], cam.K[1, 1]]) + np.array([cam.K[0, 2], cam.K[1, 2]])
    return uv, z


def distortion_maps(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """For each distorted output pixel, where to sample the pinhole rendering: (H, W) x and y maps
    in pinhole pixel coordinates (same K)."""
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    f = np.array([cam.K[0, 0], cam.K[1, 1]])
    c = np.array([cam.K[0, 2], cam.K[1, 2]])
    xy = undistort_normalized((np.stack([u, v], -1) - c) / f, cam.dist)
    src = xy * f + c
    return src[..., 0].astype(np.float32), src[..., 1].astype(np.float32)


def undistort_normalized(xy_d: np.ndarray, dist: np.ndarray, iterations: int = 100) -> np.ndarray:
    """Invert `distort_normalized` by fixed-point iteration (..., 2); checks convergence."""
    k1, k2, p1, p2, k3 = (list(dist) + [0.0] * 5)[:5]
    xy = xy_d.copy()
    for _ in range(iterations):
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        new = np.stack([(xy_d[..., 0] - dx) / radial, (xy_d[..., 1] - dy) / radial], -1)
        step = np.abs(new - xy).max()
        xy = new
        if step < 1e-13:
            break
    residual = np.abs(distort_normalized(xy, dist) - xy_d).max()
    if residual > 1e-6:
        raise ValueError(f"distortion {list(dist)} cannot be inverted over the image (residual {residual:.2e})")
    return xy


# ----------------------------------------------------------------------------- scene
BODY_COLOURS = {
    "skin": (224, 172, 140), "hair": (52, 36, 26), "shirt": (58, 128, 158),
    "pants": (72, 74, 98), "shoes": (112, 84, 62),
}
# drawn from by `outfit` (appearance > 0): skin tones from very light to very dark, hair, everyday clothes
SKIN_TONES = [(246, 214, 190), (224, 172, 140), (198, 140, 100), (160, 106, 72), (112, 72, 48), (72, 46, 32)]
HAIR_COLOURS = [(20, 16, 14), (52, 36, 26), (110, 72, 40), (196, 160, 100), (150, 150, 150)]
CLOTHES = [(20, 20, 24), (240, 240, 236), (58, 128, 158), (150, 30, 36), (40, 60, 110), (90, 110, 60),
           (200, 170, 60), (120, 120, 128), (72, 74, 98), (180, 100, 140)]


def outfit(appearance: int) -> dict:
    """Region colours (as BODY_COLOURS) of an appearance: 0 the default, N > 0 drawn with seed N
    (shirt and trousers always differ)."""
    if appearance == 0:
        return dict(BODY_COLOURS)
    rng = np.random.default_rng([appearance, 303])
    shirt, pants = rng.choice(len(CLOTHES), 2, replace=False)
    return {"skin": SKIN_TONES[rng.integers(len(SKIN_TONES))], "hair": HAIR_COLOURS[rng.integers(len(HAIR_COLOURS))],
            "shirt": CLOTHES[shirt], "pants": CLOTHES[pants], "shoes": CLOTHES[rng.integers(len(CLOTHES))]}


def body_vertex_colours(model, rest_vertices: np.ndarray, seed: int, appearance: int = 0) -> np.ndarray:
    """(V, 4) uint8 per-vertex colours: skin, hair, a short-sleeved shirt, trousers, shoes (`outfit`)."""
    from intercap.synth.motions import dominant_bones

    names = np.array(model.joint_names)[dominant_bones(model)]
    up = np.asarray(model.up_axis, float)
    fwd = np.asarray(model.forward_axis, float)
    height = rest_vertices @ up
    index = {n: i for i, n in enumerate(model.joint_names)}
    with torch.no_grad():
        joints = model(model.init_params(1)).joints[0].numpy()
    waist = joints[index["spine04"]] @ up
    eyes = joints[index["eye.L"]] @ up
    head_centre = joints[index["head"]]

    def starts(*prefixes):
        return np.char.startswith(names, prefixes[0]) if len(prefixes) == 1 else np.any(
            [np.char.startswith(names, p) for p in prefixes], axis=0)

    region = np.full(len(names), "skin", dtype=object)
    torso = starts("spine", "clavicle", "shoulder", "upperarm", "root", "pelvis")
    region[torso] = "shirt"
    region[starts("root", "pelvis", "spine05") | (torso & (height < waist))] = "pants"
    region[starts("upperleg", "lowerleg")] = "pants"
    region[starts("foot", "toe")] = "shoes"
    head = starts("head", "neck03", "eye")
    behind = (rest_vertices - head_centre) @ fwd < -0.01
    region[head & ((height > eyes + 0.045) | ((height > eyes - 0.06) & behind))] = "hair"
    palette = outfit(appearance)
    colours = np.array([palette[r] for r in region], dtype=np.float64)
    jitter = np.random.default_rng([seed, 202]).normal(0, 5, (len(names), 1))
    rgb = np.clip(colours + jitter, 0, 255).astype(np.uint8)
    return np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], 1)


PROP_COLOURS = {"table": (150, 112, 80), "shelf": (112, 124, 140), "stool": (168, 72, 56)}  # by prop name


def floor_mesh(half: float = 5.0, tile: float = FLOOR_TILE) -> trimesh.Trimesh:
    """A checkerboard floor at z = 0 (one quad per tile, per-vertex colours)."""
    n = int(round(2 * half / tile))
    verts, faces, cols = [], [], []
    for i in range(n):
        for j in range(n):
            x0, y0 = -half + i * tile, -half + j * tile
            k = len(verts)
            verts += [(x0, y0, 0), (x0 + tile, y0, 0), (x0 + tile, y0 + tile, 0), (x0, y0 + tile, 0)]
            faces += [(k, k + 1, k + 2), (k, k + 2, k + 3)]
            c = (188, 182, 170) if (i + j) % 2 else (146, 140, 130)
            cols += [c + (255,)] * 4
    return trimesh.Trimesh(np.array(verts, float), np.array(faces), vertex_colors=np.array(cols, np.uint8), process=False)


def wall_meshes(distance: float, height: float = 2.6, length: float = 10.0) -> list[trimesh.Trimesh]:
    """Two walls of a room corner (+y and -x sides), pale colours."""
    walls = []
    for centre, extents, colour in (((0, distance, height / 2), (length, 0.05, height), (205, 200, 188)),
                                    ((-distance, 0, height / 2), (0.05, length, height), (190, 198, 205))):
        w = trimesh.creation.box(extents=extents)
        w.apply_translation(centre)
        w.visual.vertex_colors = np.array(colour + (255,), np.uint8)
        walls.append(w)
    return walls


def remap_depth(depth: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Resample a depth image: bilinear within a surface, nearest across discontinuities
    and next to missing depth (never blends foreground with background)."""
    near = cv2.remap(depth, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    lin = cv2.remap(depth, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    # smooth: all 3x3 neighbours measured and the surface nearly planar there (small second differences)
    valid = cv2.erode((depth > 0).astype(np.uint8), np.ones((3, 3), np.uint8))
    bend = np.maximum(np.abs(cv2.filter2D(depth, -1, np.array([[1.0, -2.0, 1.0]], np.float32))),
                      np.abs(cv2.filter2D(depth, -1, np.array([[1.0], [-2.0], [1.0]], np.float32))))
    smooth = (valid > 0) & (bend < 0.005 + 0.002 * depth)
    smooth = cv2.erode(smooth.astype(np.uint8), np.ones((3, 3), np.uint8))
    smooth = cv2.remap(smooth, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0
    return np.where(smooth, lin, near).astype(np.float32)


class SceneRenderer:
    """One pyrender scene and one OffscreenRenderer reused for every frame and view.

    Renders pinhole images on a canvas padded so that the distortion remap never
    samples outside it, then remaps to the distorted camera image."""

    SEG_PERSON = (255, 0, 0)
    SEG_OBJECT = (0, 255, 0)

    def __init__(self, cams: list[Camera], body_faces: np.ndarray, body_colours: np.ndarray,
                 obj_mesh: trimesh.Trimesh | None, obj_colour, statics: list[trimesh.Trimesh], light: float = 1.0):
        """obj_mesh None: no object in the scene (its mask stays empty)."""
        import pyrender

        self.pyrender = pyrender
        self.cams = cams
        self.maps = [distortion_maps(c) for c in cams]
        pad = 2
        for (mx, my), c in zip(self.maps, cams):
            pad = max(pad, int(np.ceil(max(-mx.min(), -my.min(), mx.max() - (c.width - 1), my.max() - (c.height - 1)))) + 2)
        self.pad = pad
        w = max(c.width for c in cams) + 2 * pad
        h = max(c.height for c in cams) + 2 * pad
        self.renderer = pyrender.OffscreenRenderer(w, h)
        if light <= 0:
            raise ValueError(f"light must be positive, got {light}")
        self.scene = pyrender.Scene(ambient_light=(0.38 * light,) * 3, bg_color=(0.0, 0.0, 0.0, 1.0))
        for pose, intensity in ((look_at_pose(np.array([2.0, -1.5, 4.0]), np.zeros(3)), 2.2),
                                (look_at_pose(np.array([-3.0, 2.0, 3.0]), np.zeros(3)), 1.2)):
            # pyrender lights shine along their -z: turn the OpenCV look-at (+z forward) around
            self.scene.add(pyrender.DirectionalLight(intensity=intensity * light), pose=pose @ np.diag([1, -1, -1, 1.0]))
        self.static_nodes = [self.scene.add(pyrender.Mesh.from_trimesh(m, smooth=False)) for m in statics]
        self.obj_node = None
        if obj_mesh is not None:
            obj = obj_mesh.copy()
            obj.visual.vertex_colors = np.array(tuple(obj_colour) + (255,), np.uint8)
            self.obj_node = self.scene.add(pyrender.Mesh.from_trimesh(obj, smooth=False))
        self.body_faces = body_faces
        self.body_colours = body_colours
        self.body_node = None
        self.cam_node = self.scene.add(pyrender.IntrinsicsCamera(1, 1, 0, 0), pose=np.eye(4))
        self.znear, self.zfar = 0.05, 30.0

    def set_frame(self, body_vertices: np.ndarray, obj_pose: np.ndarray | None) -> None:
        if self.body_node is not None:
            self.scene.remove_node(self.body_node)
        body = trimesh.Trimesh(body_vertices, self.body_faces, vertex_colors=self.body_colours, process=False)
        self.body_node = self.scene.add(self.pyrender.Mesh.from_trimesh(body, smooth=True))
        if self.obj_node is not None:
            self.scene.set_pose(self.obj_node, obj_pose)

    def render(self, view: int) -> dict:
        """Colour (H, W, 3) uint8, clean depth (H, W) float32 metres, person and object masks (H, W) bool."""
        pr = self.pyrender
        cam = self.cams[view]
        p = self.pad
        # pyrender puts pixel centres at i + 0.5; OpenCV at i: shift the principal point by half a pixel.
        self.cam_node.camera = pr.IntrinsicsCamera(cam.K[0, 0], cam.K[1, 1], cam.K[0, 2] + p + 0.5, cam.K[1, 2] + p + 0.5,
                                                   znear=self.znear, zfar=self.zfar)
        self.scene.set_pose(self.cam_node, cam.T_world_from_cam @ np.diag([1.0, -1.0, -1.0, 1.0]))
        self.renderer.viewport_width = cam.width + 2 * p
        self.renderer.viewport_height = cam.height + 2 * p
        colour, _ = self.renderer.render(self.scene)  # multisampled: antialiased colour
        seg_map = {n: (0, 0, 0) for n in self.static_nodes}
        seg_map[self.body_node] = self.SEG_PERSON
        if self.obj_node is not None:
            seg_map[self.obj_node] = self.SEG_OBJECT
        # pyrender turns multisampling off for segmentation, so this depth is sampled exactly at
        # pixel centres (the multisampled pass's depth comes from one sub-sample, ~0.4 px off).
        seg, depth = self.renderer.render(self.scene, flags=pr.RenderFlags.SEG, seg_node_map=seg_map)
        mx, my = self.maps[view]
        mx, my = mx + p, my + p
        colour = cv2.remap(colour, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        depth = remap_depth(depth, mx, my)
        seg = cv2.remap(seg, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return {"color": colour, "depth": depth, "person": seg[..., 0] > 127, "object": seg[..., 1] > 127}

    def close(self) -> None:
        self.renderer.delete()


# ----------------------------------------------------------------------------- sensor models
def frame_rng(seed: int, purpose: int, frame: int, view: int) -> np.random.Generator:
    """An independent, order-free random stream per (purpose, frame, view)."""
    return np.random.default_rng([seed, purpose, frame, view])


def depth_edges(depth: np.ndarray, jump: float) -> np.ndarray:
    """(H, W) bool: pixels next to a depth discontinuity (step > jump + 2 % of depth) or to missing depth."""
    valid = depth > 0
    edge = np.zeros_like(valid)
    for axis in (0, 1):
        d = np.diff(depth, axis=axis)
        a = np.take(depth, np.arange(depth.shape[axis] - 1), axis=axis)
        step = (np.abs(d) > jump + 0.02 * np.maximum(a, a + d)) | (np.diff(valid.astype(np.int8), axis=axis) != 0)
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis] = slice(0, -1)
        hi[axis] = slice(1, None)
        edge[tuple(lo)] |= step
        edge[tuple(hi)] |= step
    return edge & valid


def flying_pixels(depth: np.ndarray, rng: np.random.Generator, jump: float, fraction: float) -> np.ndarray:
    """Depth (H, W) metres with `fraction` of the pixels beside a discontinuity (`depth_edges`' step)
    moved between the two sides: a time-of-flight pixel that sees both surfaces reads a mix of
    their depths (a "flying pixel"), a random share of each, along its own ray."""
    H, W = depth.shape
    valid = depth > 0
    padded = np.pad(depth, 1)
    step, across = np.zeros_like(depth), depth.copy()
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        other = padded[1 + dy:1 + dy + H, 1 + dx:1 + dx + W]
        jumps = np.where(valid & (other > 0), np.abs(other - depth), 0.0)
        larger = jumps > step
        step, across = np.where(larger, jumps, step), np.where(larger, other, across)
    flying = (step > jump + 0.02 * np.maximum(depth, across)) & (rng.random(depth.shape) < fraction)
    share = rng.uniform(0.1, 0.9, depth.shape)
    return np.where(flying, share * depth + (1 - share) * across, depth)


def kinect_depth(depth: np.ndarray, colour: np.ndarray, rng: np.random.Generator, cfg: SynthConfig) -> np.ndarray:
    """Clean depth (H, W) metres -> Kinect-like uint16 millimetres (0 = no measurement).

    Gaussian noise with sigma = base + quad * z^2; pixels lost at depth
    discontinuities (dilated edge map, a random fraction), on dark surfaces
    (colour luminance below a threshold, a random fraction), in a few random
    elliptical holes and outside the working range; millimetre quantisation."""
    H, W = depth.shape
    valid = (depth > cfg.depth_min) & (depth < cfg.depth_max)
    z = depth + rng.normal(0.0, 1.0, depth.shape) * (cfg.depth_sigma_base + cfg.depth_sigma_quad * depth**2)
    if cfg.flying_pixels > 0:
        z = flying_pixels(z, rng, cfg.edge_jump, cfg.flying_pixels)
    radius = max(1, int(round(W / 320)))
    edge = cv2.dilate(depth_edges(depth, cfg.edge_jump).astype(np.uint8), np.ones((2 * radius + 1,) * 2, np.uint8)) > 0
    lost = edge & (rng.random(depth.shape) < cfg.edge_drop)
    luminance = colour.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    lost |= (luminance < cfg.dark_threshold) & (rng.random(depth.shape) < cfg.dark_drop)
    holes = np.zeros((H, W), np.uint8)
    for _ in range(rng.poisson(cfg.holes)):
        centre = (int(rng.integers(0, W)), int(rng.integers(0, H)))
        axes = (int(W * rng.uniform(0.005, 0.03)) + 1, int(W * rng.uniform(0.005, 0.03)) + 1)
        cv2.ellipse(holes, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    lost |= holes > 0
    mm = np.clip(np.round(z * 1000.0), 1, 65535)
    return np.where(valid & ~lost, mm, 0).astype(np.uint16)


def clean_depth_mm(depth: np.ndarray, cfg: SynthConfig) -> np.ndarray:
    valid = (depth > cfg.depth_min) & (depth < cfg.depth_max)
    return np.where(valid, np.clip(np.round(depth * 1000.0), 1, 65535), 0).astype(np.uint16)


def noisy_colour(colour: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return colour
    return np.clip(colour.astype(np.float32) + rng.normal(0, sigma, colour.shape), 0, 255).astype(np.uint8)


def simulate_openpose(kp3d: np.ndarray, cam: Camera, depth: np.ndarray, rng: np.random.Generator,
                      cfg: SynthConfig) -> dict:
    """OpenPose JSON for one view from true keypoints (67, 3) and the clean depth (H, W).

    Visible keypoints: pixel noise, confidence 0.6-0.95 (body) / 0.5-0.9 (hands).
    Occluded ones (more than a margin behind the rendered surface): half are
    dropped (x = y = c = 0), half kept with confidence 0.05-0.3 and 3x the
    noise. Behind the camera or outside the image: dropped."""
    uv, z = project(kp3d.astype(np.float64), cam)
    n = len(kp3d)
    is_hand = np.arange(n) >= 25
    scale = cam.width / 640.0
    sigma = np.where(is_hand, cfg.kp_sigma_hand, cfg.kp_sigma_body) * scale
    margin = np.where(is_hand, cfg.occlusion_margin_hand, cfg.occlusion_margin_body)
    H, W = depth.shape
    inside = (z > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
    px = np.clip(np.round(uv).astype(int), 0, [W - 1, H - 1])
    surface = depth[px[:, 1], px[:, 0]]
    occluded = inside & (surface > 0) & (z > surface + margin)
    noise = rng.normal(0.0, 1.0, (n, 2)) * sigma[:, None]
    conf_vis = np.where(is_hand, rng.uniform(0.5, 0.9, n), rng.uniform(0.6, 0.95, n))
    keep_occluded = rng.random(n) < 0.5
    conf_occ = rng.uniform(0.05, 0.3, n)
    xy = uv + np.where(occluded[:, None], 3.0, 1.0) * noise
    conf = np.where(occluded, np.where(keep_occluded, conf_occ, 0.0), conf_vis)
    conf = np.where(inside, conf, 0.0)
    xy = np.where(conf[:, None] > 0, xy, 0.0)

    def triplets(sl) -> list:
        out = []
        for (x, y), c in zip(xy[sl], conf[sl]):
            out += [round(float(x), 2), round(float(y), 2), round(float(c), 3)]
        return out

    if not (conf > 0).any():
        return {"people": []}
    return {"people": [{
        "pose_keypoints_2d": triplets(slice(0, 25)),
        "hand_left_keypoints_2d": triplets(slice(25, 46)),
        "hand_right_keypoints_2d": triplets(slice(46, 67)),
        "face_keypoints_2d": [0.0] * 210,
    }]}


# ----------------------------------------------------------------------------- writing
def save_npz_deterministic(path: Path, **arrays) -> None:
    """Like np.savez, but with fixed zip timestamps so equal arrays give equal bytes."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in arrays:
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            zf.writestr(info, buf.getvalue())


def write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, separators=(",", ":"), sort_keys=False))


def write_png(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise OSError(f"could not write {path}")


def write_colour(path: Path, rgb: np.ndarray, cfg: SynthConfig) -> None:
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)] if cfg.color_format == "jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 9]
    if not cv2.imwrite(str(path), bgr, params):
        raise OSError(f"could not write {path}")


def session_yaml(cfg: SynthConfig, spec, T: int, anim) -> dict:
    """session.yaml's content; with `spec` None (the person alone) no `object` block."""
    doc = {"fps": int(cfg.fps) if float(cfg.fps).is_integer() else float(cfg.fps)}
    if spec is not None:
        doc["object"] = {"mesh": "object.ply", "name": spec.name, "mass_kg": float(spec.mass_kg),
                         "contact_vertices": "object_contacts.json"}
    doc["frames"] = {"start": 0, "end": T - 1}
    doc["body"] = {"model": "anny"}
    if cfg.annotate and spec is not None:
        pose = anim.object_poses[0]
        doc["object"]["initial_pose"] = {"R": np.round(pose[:3, :3], 6).tolist(), "t": np.round(pose[:3, 3], 6).tolist()}
    if cfg.annotate:
        frames = np.flatnonzero(anim.contact)
        ranges, start = [], None
        for f in range(T + 1):
            on = f < T and anim.contact[f]
            if on and start is None:
                start = f
            if not on and start is not None:
                ranges.append([int(start), int(f - 1)])
                start = None
        doc["contact_frames"] = ranges if frames.size else []
        doc["ground"] = {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]}
        if anim.props:  # the furniture's meshes, as a user who measured them gives them
            doc["supports"] = [{"name": name, "mesh": f"supports/{name}.ply"} for name in support_names(anim)]
    return doc


def support_names(anim) -> list[str]:
    """A unique file name per prop of the animation (table, stool, stool1, ...)."""
    names = []
    for name, _, _ in anim.props:
        names.append(name if name not in names else f"{name}{sum(n.startswith(name) for n in names)}")
    return names


# ----------------------------------------------------------------------------- physics ground truth
BODY_DENSITY = 1010.0  # kg/m^3, the human body's mean density


def rest_v_for_mass(model, shape) -> np.ndarray:
    """(V, 3) the body model's rest mesh with the session's shape (1, S) (mass from its volume)."""
    params = model.init_params(1)
    params.shape[:] = shape
    with torch.no_grad():
        return model(params).vertices[0].numpy().astype(np.float64)


def physics_ground_truth(anim, spec, faces: np.ndarray, rest_vertices: np.ndarray, fps: float, speed: float,
                         still_tol: float = 0.05) -> dict:
    """What is analytic about a physics script's session (SI units, world, z up; NaN where not analytic).

    Body mass M = rest mesh volume x 1010 kg/m^3; object mass m from its spec. Per frame:
    `hand_force` (T, 3) total force of the hands on the object: m g up while held and still
    (the object's acceleration is 0), 0 while it touches no hand; `ground_reaction` (T, 3):
    M g + the hands' load where the body is still (its vertices' acceleration below
    `still_tol` m/s^2) and the hand force is known; `object_ground_force` (T, 3): m g up
    while it lies untouched on the floor, 0 in flight. `flight_episodes` (E, 2) (first, last
    frame, inclusive) and `flight_acceleration` (E, 3) = g in session time (x speed^2)."""
    T = len(anim.object_poses)
    g_vec = np.array([0.0, 0.0, -9.81])
    mesh = trimesh.Trimesh(rest_vertices, faces, process=False)
    M = abs(float(mesh.volume)) * BODY_DENSITY
    m = float(spec.mass_kg)
    p = anim.object_poses[:, :3, 3]
    R = anim.object_poses[:, :3, :3].reshape(T, 9)

    def second_difference(x):  # (T, ...) -> (T,) largest |second difference| x fps^2, NaN at the ends
        out = np.full(T, np.nan)
        if T >= 3:
            d = np.abs(x[2:] - 2 * x[1:-1] + x[:-2]).reshape(T - 2, -1).max(1) * fps**2
            out[1:-1] = d
        return out

    object_still = (second_difference(p) < 1e-6) & (second_difference(R) < 1e-6)
    object_still[1:-1] &= np.abs(p[2:] - p[:-2]).max(1) < 1e-9  # and not moving at constant speed
    body_acc = second_difference(anim.vertices.astype(np.float64))
    body_still = body_acc < still_tol
    held = anim.contact.astype(bool)
    in_flight = np.zeros(T, bool)
    episodes = np.zeros((0, 2), np.int64)
    if anim.flight is not None:
        in_flight[anim.flight[0]:anim.flight[1] + 1] = True
        episodes = np.array([anim.flight], np.int64)
    verts = np.asarray(spec.mesh.vertices)
    lowest = (np.einsum("tij,vj->tvi", anim.object_poses[:, :3, :3], verts)[..., 2] + p[:, 2:3]).min(1)
    on_floor = ~held & ~in_flight & (lowest < 1e-6) & object_still
    nan3 = np.full((T, 3), np.nan)
    hand = nan3.copy()
    hand[held & object_still] = -m * g_vec
    hand[~held] = 0.0
    ground_obj = nan3.copy()
    ground_obj[on_floor] = -m * g_vec
    ground_obj[in_flight] = 0.0
    reaction = np.where((body_still & np.isfinite(hand).all(1))[:, None], -M * g_vec + hand, np.nan)
    flight_acc = np.tile(g_vec * speed**2, (len(episodes), 1))
    return dict(frame_ids=np.arange(T, dtype=np.int64), gravity=g_vec, body_mass_kg=np.float64(M),
                body_density_kg_m3=np.float64(BODY_DENSITY), object_mass_kg=np.float64(m), hand_force=hand,
                ground_reaction=reaction, object_ground_force=ground_obj, object_still=object_still,
                body_still=body_still, body_max_acceleration=body_acc, flight_episodes=episodes,
                flight_acceleration=flight_acc,
                note=np.array("body mass = anny rest mesh volume x 1010 kg/m^3; NaN where not analytic"))


# ----------------------------------------------------------------------------- the generator
def script_times(duration: float, cfg: SynthConfig) -> tuple[np.ndarray, float]:
    """Script time (seconds) of each frame and the speed factor (1 = natural speed)."""
    if cfg.frames is None:
        T = int(np.floor(duration * cfg.fps + 1e-9)) + 1
        return np.arange(T) / cfg.fps, 1.0
    T = int(cfg.frames)
    if T < 1:
        raise ValueError("frames must be at least 1")
    if T == 1:
        return np.array([duration / 2]), 1.0
    speed = duration / ((T - 1) / cfg.fps)
    return np.linspace(0.0, duration, T), speed


def centre_scene(anim) -> np.ndarray:
    """Shift (3,) that puts the middle of the action (root path and object track) over the origin."""
    pts = anim.params.transl.numpy()[:, :2]
    if anim.object_poses is not None:
        pts = np.concatenate([pts, anim.object_poses[:, :2, 3]])
    mid = (pts.min(0) + pts.max(0)) / 2
    return np.array([-mid[0], -mid[1], 0.0])


def exit_heading_deg(cfg: SynthConfig) -> float:
    """Walking direction (degrees from +x) of a script that leaves the camera ring: midway between two
    neighbouring cameras, or across the view of a single camera."""
    return cfg.ring_offset_deg + (180.0 / cfg.cameras if cfg.cameras > 1 else 90.0)


def start_at_centre(anim) -> np.ndarray:
    """Shift (3,) that puts the root's start over the origin (a walk out of the ring begins in its middle)."""
    start = anim.params.transl.numpy()[0, :2]
    return np.array([-start[0], -start[1], 0.0])


def shift_animation(anim, shift: np.ndarray):
    anim.vertices = anim.vertices + shift.astype(np.float32)
    anim.keypoints = anim.keypoints + shift.astype(np.float32)
    anim.params.transl = anim.params.transl + torch.as_tensor(shift, dtype=anim.params.transl.dtype)
    if anim.object_poses is not None:
        anim.object_poses = anim.object_poses.copy()
        anim.object_poses[:, :3, 3] += shift
    props = []
    for name, mesh, pose in anim.props:
        pose = pose.copy()
        pose[:3, 3] += shift
        props.append((name, mesh, pose))
    anim.props = props
    return anim


def dropped_frames(cfg: SynthConfig, T: int) -> set:
    if cfg.drop_rate <= 0 or T < 3:
        return set()
    rng = np.random.default_rng([cfg.seed, 303])
    count = int(round(cfg.drop_rate * T))
    # never the first frame: a pipeline may need it to initialise
    return set(int(f) for f in rng.choice(np.arange(1, T), size=min(count, T - 1), replace=False))


# options recorded in ground_truth/info.json only when set, so that sessions made without them keep their bytes
_RECORDED_WHEN_SET = ("camera_world",)


def recorded_config(cfg: SynthConfig) -> dict:
    """The config as ground_truth/info.json records it (JSON types; `_RECORDED_WHEN_SET` only when set)."""
    doc = json.loads(json.dumps(dataclasses.asdict(cfg)))
    return {k: v for k, v in doc.items() if v or k not in _RECORDED_WHEN_SET}


def log(cfg: SynthConfig, *args) -> None:
    if not cfg.quiet:
        print(*args, flush=True)


_MODELS: dict = {}


def cached_body_model():
    """The anny body model, constructed once per process (several sessions in one run share it)."""
    if "anny" not in _MODELS:
        from intercap.body_models import load_body_model

        _MODELS["anny"] = load_body_model("anny", device="cpu", dtype=torch.float32)
    return _MODELS["anny"]


def generate_session(cfg: SynthConfig, out_dir) -> Path:
    """Write a synthetic session to `out_dir` (created; existing frame files are overwritten)."""
    from tqdm import tqdm

    from intercap.synth.motions import animate, get_script, without_object
    from intercap.synth.objects import NO_OBJECT, make_object

    torch.manual_seed(cfg.seed)
    object_name = cfg.object or get_script(cfg.script).default_object
    spec = None if object_name == NO_OBJECT else make_object(object_name)
    script = get_script(cfg.script, spec)
    if spec is None:  # the person alone: the script's body motion, the arms relaxed where they would hold it
        script = without_object(script)
    elif not script.holds_object:
        raise ValueError(f"script {cfg.script!r} is of the person alone: it takes no object (--object {NO_OBJECT})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if cfg.flight_turns:
        if script.flight is None or script.flight[0] != "catch":
            raise ValueError(f"--flight-turns needs a script with a caught flight (toss), not {cfg.script!r}")
        script = dataclasses.replace(script, flight_turns=float(cfg.flight_turns))
    times, speed = script_times(script.duration, cfg)
    T = len(times)
    if abs(speed - 1) > 0.05:
        log(cfg, f"[synth] {cfg.script}: {T} frames at {cfg.fps:g} fps play the {script.duration:.1f} s script at {speed:.2f}x speed")

    t0 = time.perf_counter()
    model = cached_body_model()
    jitter = np.random.default_rng([cfg.seed, 404]).uniform(-1, 1)
    heading = cfg.heading_deg + cfg.heading_jitter_deg * jitter
    if script.leaves_ring:
        heading = exit_heading_deg(cfg) + 5.0 * jitter
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, int(cfg.threads)))
    try:
        anim = animate(model, script, spec, times, cfg.phenotype, heading0=np.radians(heading),
                       ik_iters=cfg.ik_iters, polish_iters=max(5, cfg.ik_iters // 5))
    finally:
        torch.set_num_threads(threads)
    anim = shift_animation(anim, start_at_centre(anim) if script.leaves_ring else centre_scene(anim))
    t_motion = time.perf_counter() - t0
    log(cfg, f"[synth] motion: {t_motion:.1f} s" + (
        f"; hand-object in contact frames: {json.dumps(anim.hand_gap)}" if spec is not None else "; no object"))

    cams = ring_cameras(cfg)
    faces = model.faces.cpu().numpy()
    with torch.no_grad():
        rest_v = model(model.init_params(1)).vertices[0].numpy()
    colours = body_vertex_colours(model, rest_v, cfg.seed, cfg.appearance)
    statics = [floor_mesh()] + (wall_meshes(cfg.ring_radius + 1.3) if cfg.walls else [])
    for name, mesh, pose in anim.props:
        m = mesh.copy()
        m.apply_transform(pose)
        m.visual.vertex_colors = np.array(PROP_COLOURS.get(name, PROP_COLOURS["table"]) + (255,), np.uint8)
        statics.append(m)

    # static files
    write_json(out / "calibration.json", {"world": WORLD_NOTE, "cameras": [c.to_json() for c in cams]})
    if cfg.annotate and anim.props:
        (out / "supports").mkdir(exist_ok=True)
        for name, mesh in zip(support_names(anim), statics[len(statics) - len(anim.props):]):
            mesh.export(out / "supports" / f"{name}.ply")
    if spec is not None:
        spec.mesh.export(out / "object.ply")
        write_json(out / "object_contacts.json", {"vertices": [int(i) for i in spec.contact_vertices]})
    (out / "session.yaml").write_text(yaml.safe_dump(session_yaml(cfg, spec, T, anim), sort_keys=False))
    gt = out / "ground_truth"
    gt.mkdir(exist_ok=True)
    np.save(gt / "body_vertices.npy", anim.vertices.astype(np.float32))
    np.save(gt / "body_faces.npy", faces.astype(np.int32))
    if spec is not None:
        save_npz_deterministic(gt / "object_poses.npz", R=anim.object_poses[:, :3, :3].astype(np.float64),
                               t=anim.object_poses[:, :3, 3].astype(np.float64))
    np.save(gt / "contact.npy", anim.contact.astype(bool))  # all False for the person alone
    np.save(gt / "keypoints3d.npy", anim.keypoints.astype(np.float32))
    params = {k: v.astype(np.float32) for k, v in anim.params.to_numpy_dict().items()}
    save_npz_deterministic(gt / "body_params.npz", model=np.array("anny"), **params)
    write_json(gt / "info.json", {
        "generator": "intercap.synth", "config": recorded_config(cfg),
        "script": script.name, "speed": round(speed, 6), "phases": anim.phases,
        "script_times": np.round(times, 6).tolist(),
        "hand_object": {h: {k: round(v, 6) for k, v in d.items()} for h, d in anim.hand_gap.items()},
        "hand_object_distance_m": None if anim.hand_distance is None else np.round(anim.hand_distance, 5).tolist(),
        "ground": {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
        "props": [name for name, _, _ in anim.props],
    })
    write_json(gt / "ground.json", {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]})  # the floor, z up
    from intercap.synth.motions import PHYSICS_SCRIPTS

    if script.name in PHYSICS_SCRIPTS and spec is not None:
        save_npz_deterministic(gt / "physics.npz", **physics_ground_truth(anim, spec, faces, rest_v_for_mass(model, anim.params.shape[:1]),
                                                                          cfg.fps, speed))

    for c in cams:
        for sub in ["color", "depth"] + (["keypoints"] if cfg.keypoints else []) + (
                (["masks/person"] + (["masks/object"] if spec is not None else []) if cfg.masks else [])):
            (out / c.name / sub).mkdir(parents=True, exist_ok=True)

    dropped = dropped_frames(cfg, T)
    drop_view = cfg.drop_view % len(cams)
    renderer = SceneRenderer(cams, faces, colours, None if spec is None else spec.mesh,
                             None if spec is None else spec.color, statics, light=cfg.light)
    t_render = time.perf_counter()
    views_done = 0
    ext = "jpg" if cfg.color_format == "jpg" else "png"

    def sensor_files(f: int, v: int, cam: Camera, r: dict) -> None:
        """One view's noisy colour and depth, masks and keypoints, written (in a worker thread: the
        noise and the PNG compression release the GIL while the next view renders)."""
        name = f"{f:06d}"
        colour = noisy_colour(r["color"], frame_rng(cfg.seed, 1, f, v), cfg.color_noise)
        write_colour(out / cam.name / "color" / f"{name}.{ext}", colour, cfg)
        if cfg.clean_depth:
            depth = clean_depth_mm(r["depth"], cfg)
        else:
            depth = kinect_depth(r["depth"], r["color"], frame_rng(cfg.seed, 2, f, v), cfg)
        write_png(out / cam.name / "depth" / f"{name}.png", depth)
        if cfg.masks:
            write_png(out / cam.name / "masks" / "person" / f"{name}.png", r["person"].astype(np.uint8) * 255)
            if spec is not None:
                write_png(out / cam.name / "masks" / "object" / f"{name}.png", r["object"].astype(np.uint8) * 255)
        if cfg.keypoints:
            people = simulate_openpose(anim.keypoints[f], cam, r["depth"], frame_rng(cfg.seed, 3, f, v), cfg)
            write_json(out / cam.name / "keypoints" / f"{name}.json", people)

    threads = min(8, cpu_count())
    pending: list = []
    try:
        with ThreadPoolExecutor(threads) as pool:
            for f in tqdm(range(T), desc="render", unit="frame", disable=cfg.quiet):
                renderer.set_frame(anim.vertices[f], None if anim.object_poses is None else anim.object_poses[f])
                for v, cam in enumerate(cams):
                    if v == drop_view and f in dropped:
                        continue
                    pending.append(pool.submit(sensor_files, f, v, cam, renderer.render(v)))
                    views_done += 1
                while len(pending) > 2 * threads:  # a bounded queue: rendered images wait in memory
                    pending.pop(0).result()
            for job in pending:
                job.result()  # re-raises a worker's error
    finally:
        renderer.close()
    if cfg.camera_world:  # the same images; calibration and ground truth in camera 0's frame
        from intercap.synth.reframe import camera_frame, reexpress_in_place

        reexpress_in_place(out, camera_frame(out, 0))
    elapsed = time.perf_counter() - t_render
    per_view = elapsed / max(views_done, 1)
    log(cfg, f"[synth] {T} frames x {len(cams)} views ({cfg.width}x{cfg.height}): "
             f"{per_view:.3f} s per frame per view (render + noise + write), motion {t_motion:.1f} s -> {out}")
    return out


# ----------------------------------------------------------------------------- command line
def main(argv=None) -> int:
    args = build_arg_parser().parse_args(argv)
    generate_session(config_from_args(args), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
