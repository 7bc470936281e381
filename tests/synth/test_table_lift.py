"""The table_lift script and its scene: objects of several shapes resting on a table top, lifted, turned
with and put back; static furniture in the depth; and the camera-as-world option of the generator.

Three tiny sessions (2 cameras, 96x80, 12 frames) are generated once for the module: the carton (two
hands) in the default z-up world and with camera 0 as the world, and the tool (one hand, by its handle).
The other objects' rests are checked on their planned track, which the generator writes as ground truth.
"""
from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
import torch
import yaml

from intercap.session import validate
from intercap.synth.generator import PRESETS, SynthConfig, build_arg_parser, config_from_args, generate_session
from intercap.synth.motions import (
    TABLE_TOP,
    LevelSurfaces,
    get_script,
    heading_frames,
    object_track,
    prop_meshes,
)
from intercap.synth.objects import SurfaceDistance, make_object

TINY = SynthConfig(**PRESETS["tiny"], quiet=True)
CARTON = dataclasses.replace(TINY, script="table_lift", frames=12, keypoints=False)
NEW_OBJECTS = ("carton", "flat_box", "tool", "ball")
REST_END, HELD, REST_AGAIN = 2.1, (2.9, 4.6), 5.2  # script seconds: resting until, held up, resting from


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    root = tmp_path_factory.mktemp("table_lift")
    return {"carton": generate_session(CARTON, root / "carton"),
            "camera_world": generate_session(dataclasses.replace(CARTON, camera_world=True), root / "camera_world"),
            "tool": generate_session(dataclasses.replace(CARTON, object="tool"), root / "tool")}


def ground_truth(session):
    gt = session / "ground_truth"
    info = json.loads((gt / "info.json").read_text())
    poses = np.load(gt / "object_poses.npz")
    return info, np.array(info["script_times"]), poses["R"], poses["t"]


def lowest_heights(spec, R, t) -> np.ndarray:
    """(T,) height of the object's lowest vertex in a z-up world."""
    return (np.einsum("tij,vj->tvi", R, np.asarray(spec.mesh.vertices))[..., 2] + t[:, None, 2]).min(1)


def check_rests_and_lift(spec, times, R, t):
    """On the table top (within 3 mm) and still while resting, well clear of it while held up."""
    low = lowest_heights(spec, R, t)
    for rest in (times <= REST_END, times >= REST_AGAIN):
        assert rest.sum() >= 2
        assert np.abs(low[rest] - TABLE_TOP).max() < 0.003, low[rest]
        assert np.abs(t[rest] - t[rest][0]).max() < 1e-9 and np.abs(R[rest] - R[rest][0]).max() < 1e-9
    held = (times >= HELD[0]) & (times <= HELD[1])
    assert held.any() and (low[held] > TABLE_TOP + 0.1).all(), low[held]


def table_lift_props(session):
    """The script's props (name, mesh centred on its bounding box, world pose), placed from the object's
    first (resting) pose."""
    info, _, R, t = ground_truth(session)
    spec = make_object(info["config"]["object"] or "carton")
    script = get_script("table_lift", spec)
    rest = script.object_keys[0].rel.copy()
    rest[2, 3] = script.object_keys[0].on_surface + spec.half_height
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R[0], t[0]
    world_from_heading = pose @ np.linalg.inv(rest)
    return [(name, mesh, world_from_heading @ rel) for name, mesh, rel in prop_meshes(script)]


def in_frame(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points (..., 3) in the frame whose world pose is `pose` (4, 4)."""
    return (points - pose[:3, 3]) @ pose[:3, :3]


# ----------------------------------------------------------------------------- objects and props
def test_new_objects_have_their_shapes_masses_and_grasps_on_the_surface():
    sizes = {"carton": (0.30, 0.22, 0.18), "flat_box": (0.40, 0.30, 0.06), "tool": (0.60, 0.10, 0.035),
             "ball": (0.22, 0.22, 0.22)}
    masses = {"carton": 2.0, "flat_box": 1.0, "tool": 0.8, "ball": 0.5}
    for name in NEW_OBJECTS:
        spec = make_object(name)
        assert spec.mesh.is_watertight, name
        assert np.allclose(spec.mesh.extents, sizes[name], atol=1e-6), (name, spec.mesh.extents)
        assert np.allclose(spec.mesh.bounds.sum(0), 0.0, atol=1e-9)  # centred on its bounding box
        assert spec.mass_kg == masses[name]
        assert set(spec.grasps) == ({"right"} if name == "tool" else {"left", "right"})
        distance = SurfaceDistance(spec.mesh)
        for grasp in spec.grasps.values():
            assert abs(distance(np.array([grasp.point]))[0]) < 1e-4, (name, grasp)
            assert abs(np.dot(grasp.normal, grasp.finger_dir)) < 1e-9
            outside = np.asarray(grasp.point) + 0.01 * np.asarray(grasp.normal)
            assert distance(outside[None])[0] > 0.009, (name, grasp)  # the normal points out of the surface
        assert len(spec.contact_vertices) > 10 and spec.contact_vertices.max() < len(spec.mesh.vertices)


def test_props_are_closed_and_centred_on_their_bounding_box():
    meshes = {name: mesh for name, mesh, _ in prop_meshes(get_script("table_lift"))}
    assert set(meshes) == {"table", "shelf", "stool"}
    for name, mesh in meshes.items():
        assert mesh.is_watertight, name
        assert np.allclose(mesh.bounds.sum(0), 0.0, atol=1e-9), name
    assert meshes["table"].bounds[1, 2] * 2 == pytest.approx(TABLE_TOP)


def test_level_surfaces_push_only_points_over_a_top_and_below_it():
    top = np.eye(4)
    top[:3, 3] = (1.0, 2.0, 0.74)
    surfaces = LevelSurfaces(torch.tensor(top[None], dtype=torch.float32), torch.tensor([[0.4, 0.3]]))
    points = torch.tensor([[[1.1, 2.1, 0.73],  # over the top, 1 cm below it (+ 3 mm margin)
                            [1.6, 2.0, 0.70],  # beside the table
                            [1.0, 2.0, 0.80],  # above it
                            [1.0, 2.0, 0.40]]])  # far under it (a knee under the table)
    per_point = [float(surfaces.below(points[:, i:i + 1])) for i in range(4)]
    assert per_point[0] == pytest.approx((0.013 / 0.002) ** 2, rel=1e-3)
    assert per_point[1:] == [0.0, 0.0, 0.0]


# ----------------------------------------------------------------------------- the script
def test_every_object_rests_on_the_table_at_both_ends_and_is_lifted_between():
    """The planned track (the ground truth's object poses) for each object table_lift takes."""
    for name in NEW_OBJECTS + ("cup",):
        spec = make_object(name)
        script = get_script("table_lift", spec)
        assert script.hands == (("right",) if name in ("tool", "cup") else ("left", "right"))
        assert 6.0 <= script.duration <= 7.0
        times = np.arange(int(script.duration * 30) + 1) / 30.0
        heading = heading_frames(np.zeros(len(times)), np.zeros((len(times), 2)), 0.3)
        poses = object_track(script, {"body": heading, "head": heading}, times, half_height=spec.half_height)
        check_rests_and_lift(spec, times, poses[:, :3, :3], poses[:, :3, 3])
        assert (times <= REST_END).mean() > 0.3 and (times >= REST_AGAIN).mean() > 0.22  # a third, a quarter


def test_carton_and_tool_ground_truth_rest_on_the_table_with_the_hands_on_them(sessions):
    for name in ("carton", "tool"):
        info, times, R, t = ground_truth(sessions[name])
        spec = make_object(name)
        check_rests_and_lift(spec, times, R, t)
        contact = np.load(sessions[name] / "ground_truth" / "contact.npy")
        distance = np.array(info["hand_object_distance_m"])
        assert contact.any() and (np.abs(distance[contact]) < 0.01).all(), (name, distance)
        assert distance[0] > 0.05 and distance[-1] > 0.05
        for hand in info["hand_object"].values():
            assert hand["palm_gap_max_m"] < 0.01 and hand["penetration_max_m"] < 0.01, (name, hand)
        assert info["props"] == ["table", "shelf", "stool"]


def test_hands_stay_above_the_table_top(sessions):
    for name in ("carton", "tool"):
        _, table, pose = table_lift_props(sessions[name])[0]
        local = in_frame(np.load(sessions[name] / "ground_truth" / "body_vertices.npy"), pose)
        lo, hi = table.bounds
        over = (np.abs(local[..., :2]) < hi[:2]).all(-1) & (local[..., 2] > hi[2] - 0.15)
        assert over.any()  # the hands reach over the table
        assert local[..., 2][over].min() > hi[2] - 0.01, name


def test_table_and_furniture_appear_in_the_depth(sessions):
    """Points on the table top (away from the object) and on the shelf's and stool's tops read their own
    depth in the views that see them (not the floor's behind them); the furniture is in no mask."""
    session = sessions["carton"]
    cams = json.loads((session / "calibration.json").read_text())["cameras"]
    for name, mesh, pose in table_lift_props(session):
        lo, hi = mesh.bounds
        gx, gy = np.meshgrid(np.linspace(lo[0] + 0.04, hi[0] - 0.04, 9), np.linspace(lo[1] + 0.04, hi[1] - 0.04, 7))
        points = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, hi[2])], 1)  # its top, in its own frame
        assert (np.abs(SurfaceDistance(mesh)(points)) < 1e-6).all()
        points = points @ pose[:3, :3].T + pose[:3, 3]
        matched = seen = 0
        for cam in cams:
            T = np.linalg.inv(np.asarray(cam["T_world_from_cam"]))
            rvec, _ = cv2.Rodrigues(T[:3, :3])
            uv, _ = cv2.projectPoints(points, rvec, T[:3, 3], np.asarray(cam["K"]), np.asarray(cam["dist"]))
            uv = np.round(uv.reshape(-1, 2)).astype(int)
            z = points @ T[:3, :3].T[:, 2] + T[2, 3]
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam["width"]) & (uv[:, 1] >= 0) & (uv[:, 1] < cam["height"])
            for f in (0, CARTON.frames - 1):
                depth = cv2.imread(str(session / cam["name"] / "depth" / f"{f:06d}.png"), cv2.IMREAD_UNCHANGED) / 1000.0
                masks = [cv2.imread(str(session / cam["name"] / "masks" / k / f"{f:06d}.png"), 0) > 0
                         for k in ("person", "object")]
                u, v = uv[inside, 0], uv[inside, 1]
                free = ~masks[0][v, u] & ~masks[1][v, u] & (depth[v, u] > 0)
                seen += int(free.sum())
                matched += int((np.abs(depth[v, u] - z[inside])[free] < 0.05).sum())
        assert seen >= 20 and matched > 0.6 * seen, (name, matched, seen)


# ----------------------------------------------------------------------------- camera 0 as the world
def test_camera_world_moves_calibration_and_ground_truth_not_the_images(sessions):
    base, moved = sessions["carton"], sessions["camera_world"]
    session, problems = validate(moved)
    assert session is not None, [str(p) for p in problems if p.fatal]
    old = json.loads((base / "calibration.json").read_text())["cameras"]
    new = json.loads((moved / "calibration.json").read_text())["cameras"]
    T = np.linalg.inv(np.asarray(old[0]["T_world_from_cam"]))
    assert np.allclose(new[0]["T_world_from_cam"], np.eye(4), atol=1e-9)
    for a, b in zip(old, new):
        assert np.allclose(T @ np.asarray(a["T_world_from_cam"]), b["T_world_from_cam"], atol=1e-9)
        assert a["K"] == b["K"] and a["dist"] == b["dist"]
    for sub in ("depth", "masks/person", "masks/object"):
        for path in sorted((base / "cam1" / sub).glob("*.png")):
            assert path.read_bytes() == (moved / "cam1" / sub / path.name).read_bytes(), path
    for path in sorted((base / "cam0" / "color").glob("*.jpg")):
        assert np.array_equal(cv2.imread(str(path)), cv2.imread(str(moved / "cam0" / "color" / path.name)))
    gt_old, gt_new = base / "ground_truth", moved / "ground_truth"
    v_old, v_new = np.load(gt_old / "body_vertices.npy"), np.load(gt_new / "body_vertices.npy")
    assert np.allclose(v_old @ T[:3, :3].T + T[:3, 3], v_new, atol=1e-5)
    p_old, p_new = np.load(gt_old / "object_poses.npz"), np.load(gt_new / "object_poses.npz")
    assert np.allclose(T[:3, :3] @ p_old["R"], p_new["R"], atol=1e-9)
    assert np.allclose(p_old["t"] @ T[:3, :3].T + T[:3, 3], p_new["t"], atol=1e-9)
    up = json.loads((gt_new / "ground.json").read_text())["normal"]
    assert np.allclose(up, T[:3, 2]) and up[1] < -0.5  # z up became camera axes: up is mostly -y
    assert not (gt_new / "body_params.npz").exists() and (gt_old / "body_params.npz").exists()
    assert json.loads((gt_new / "info.json").read_text())["config"]["camera_world"] is True
    assert "camera_world" not in json.loads((gt_old / "info.json").read_text())["config"]  # default bytes kept
    assert yaml.safe_load((moved / "session.yaml").read_text()) == yaml.safe_load((base / "session.yaml").read_text())


def test_cli_options_for_the_new_script_objects_and_world():
    args = build_arg_parser().parse_args(["OUT", "--script", "table_lift", "--object", "flat_box", "--camera-world"])
    cfg = config_from_args(args)
    assert (cfg.script, cfg.object, cfg.camera_world) == ("table_lift", "flat_box", True)
    assert config_from_args(build_arg_parser().parse_args(["OUT"])).camera_world is False
