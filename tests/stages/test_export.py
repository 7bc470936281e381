"""The `export` stage on a results folder made from the sample's ground truth (no fitting needed)."""
import pickle
import re
import shutil

import numpy as np
import open3d as o3d
import pytest
import trimesh
from conftest import SAMPLE_SESSION
from scipy.spatial.transform import Rotation

from intercap.config import load_config
from intercap.pipeline import run_pipeline
from intercap.session import Session
from intercap.stages.export import stage as export

GT = SAMPLE_SESSION / "ground_truth"
NAN_BODY, NAN_OBJECT = 3, 5  # frames whose body / object result is NaN
REGIONS = np.array(["left_hand", "right_hand"])


def write_results(out):
    """OUT/ as the fitting stages leave it, from the sample's ground truth (with two failed frames)."""
    out.mkdir(parents=True, exist_ok=True)
    verts = np.load(GT / "body_vertices.npy").astype(np.float32)
    verts[NAN_BODY] = np.nan
    np.save(out / "body_vertices.npy", verts)
    shutil.copy(GT / "body_faces.npy", out / "body_faces.npy")
    keypoints = np.load(GT / "keypoints3d.npy").astype(np.float32)
    keypoints[NAN_BODY] = np.nan
    np.save(out / "keypoints3d.npy", keypoints)
    params = dict(np.load(GT / "body_params.npz"))
    params["valid"] = np.isfinite(verts).all((1, 2))
    np.savez(out / "body_params.npz", **params)
    poses = np.load(GT / "object_poses.npz")
    R, t = poses["R"].copy(), poses["t"].copy()
    R[NAN_OBJECT], t[NAN_OBJECT] = np.nan, np.nan
    np.savez(out / "object_poses.npz", R=R, t=t, valid=np.isfinite(t).all(1))
    contact = np.load(GT / "contact.npy")
    np.save(out / "contact.npy", contact)
    T = len(contact)
    (out / "contact").mkdir(exist_ok=True)
    np.savez(out / "contact" / "contact.npz", contact=contact, method=np.array("annotated"), frame_ids=np.arange(T),
             region_names=REGIONS, region_contact=np.stack([contact, contact], 1),
             region_distance_m=np.linspace(0, 1, 2 * T).reshape(T, 2))
    (out / "prepare").mkdir(exist_ok=True)
    shutil.copy(GT / "ground.json", out / "prepare" / "ground.json")
    (out / "physics").mkdir(exist_ok=True)
    np.savez(out / "physics" / "physics.npz", frame_ids=np.arange(T), gravity=np.array([0, 0, -9.81]),
             hand_force=np.arange(T * 6, dtype=float).reshape(T, 2, 3))
    return out


@pytest.fixture(scope="module")
def session():
    return Session.load(SAMPLE_SESSION)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = write_results(tmp_path_factory.mktemp("export") / "out")
    cfg = load_config(None, ["export.scene=true", "export.behave=true"])
    metrics = run_pipeline(SAMPLE_SESSION, out, cfg, stages=["export"], progress=False)
    return out, metrics["export"]


def test_meshes_reopen_and_match_results_exactly(exported, session):
    out, _ = exported
    verts = np.load(out / "body_vertices.npy")
    faces = np.load(out / "body_faces.npy")
    poses = np.load(out / "object_poses.npz")
    template = session.object.load_mesh()
    for i in (0, 12, 29):
        body = trimesh.load(out / "meshes" / f"body_{i:06d}.ply", process=False)
        assert np.array_equal(body.vertices, verts[i].astype(np.float64))
        assert np.array_equal(body.faces, faces)
        o3d_body = o3d.io.read_triangle_mesh(str(out / "meshes" / f"body_{i:06d}.ply"))
        assert np.array_equal(np.asarray(o3d_body.vertices), verts[i].astype(np.float64))
        assert np.array_equal(np.asarray(o3d_body.triangles), faces)
        obj = trimesh.load(out / "meshes" / f"object_{i:06d}.ply", process=False)
        expected = (template.vertices @ poses["R"][i].T + poses["t"][i]).astype(np.float32)
        assert np.array_equal(obj.vertices, expected.astype(np.float64))
        assert np.array_equal(obj.faces, template.faces)
        # independently: the ground-truth pose as a 4x4 transform of the session's mesh
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = poses["R"][i], poses["t"][i]
        assert np.abs(obj.vertices - template.copy().apply_transform(T).vertices).max() < 1e-6
        o3d_obj = o3d.io.read_triangle_mesh(str(out / "meshes" / f"object_{i:06d}.ply"))
        assert np.array_equal(np.asarray(o3d_obj.vertices), expected.astype(np.float64))


def test_nan_frames_are_skipped_and_counted(exported):
    out, figures = exported
    assert not (out / "meshes" / f"body_{NAN_BODY:06d}.ply").exists()
    assert (out / "meshes" / f"object_{NAN_BODY:06d}.ply").exists()
    assert not (out / "meshes" / f"object_{NAN_OBJECT:06d}.ply").exists()
    assert (out / "meshes" / f"body_{NAN_OBJECT:06d}.ply").exists()
    assert not (out / "meshes" / f"scene_{NAN_BODY:06d}.ply").exists()
    assert figures["frames_skipped_body"] == 1 and figures["skipped_body_frame_ids"] == [NAN_BODY]
    assert figures["frames_skipped_object"] == 1 and figures["skipped_object_frame_ids"] == [NAN_OBJECT]
    assert figures["body_meshes"] == 29 and figures["object_meshes"] == 29 and figures["scene_meshes"] == 28
    assert len(list((out / "meshes").glob("body_*.ply"))) == 29


def test_dataset_file_holds_the_documented_keys(exported, session):
    out, _ = exported
    with np.load(out / "export" / "sample.npz") as z:
        data = {k: z[k] for k in z.files}
    documented = set(re.findall(r"^    (\w+) \(", export.dataset_arrays.__doc__, re.M))
    params = set(np.load(out / "body_params.npz").files) - {"model"}
    prefixed = {k for k in data if k.startswith(("body_param_", "physics_"))}
    assert set(data) - prefixed <= documented, set(data) - prefixed - documented
    assert documented - {"body_param_shape_mean"} <= set(data) - prefixed | {"body_param_<name>"}
    assert prefixed == {f"body_param_{k}" for k in params} | {"physics_frame_ids", "physics_gravity", "physics_hand_force"}
    assert str(data["session_name"]) == "sample" and str(data["body_model"]) == "anny"
    assert str(data["object_name"]) == "box"
    assert np.array_equal(data["frame_ids"], np.arange(30))
    assert np.allclose(data["times_s"], np.arange(30) / 5.0)
    assert np.array_equal(data["body_vertices"], np.load(out / "body_vertices.npy"), equal_nan=True)
    assert data["body_vertices"].dtype == np.float32
    assert data["body_valid"].sum() == 29 and not data["body_valid"][NAN_BODY]
    assert data["object_valid"].sum() == 29 and not data["object_valid"][NAN_OBJECT]
    assert np.array_equal(data["body_param_body_pose"], np.load(GT / "body_params.npz")["body_pose"])
    assert np.array_equal(data["object_vertices"], session.object.load_mesh().vertices)
    assert np.array_equal(data["contact"], np.load(GT / "contact.npy"))
    assert list(data["contact_region_names"]) == list(REGIONS) and data["contact_regions"].shape == (30, 2)
    assert str(data["contact_method"]) == "annotated"
    for c, cam in enumerate(session.cameras):
        assert str(data["camera_names"][c]) == cam.name
        assert np.array_equal(data["camera_K"][c], cam.K)
        assert np.array_equal(data["camera_T_world_from_cam"][c], cam.T_world_from_cam)
        assert np.array_equal(data["camera_dist"][c, :len(cam.dist)], cam.dist)
        assert tuple(data["camera_sizes"][c]) == (cam.width, cam.height)
    assert np.array_equal(data["ground_normal"], [0, 0, 1]) and np.array_equal(data["ground_point"], [0, 0, 0])
    assert np.array_equal(data["physics_hand_force"], np.arange(180, dtype=float).reshape(30, 2, 3))


def test_float16_vertices_and_missing_results(tmp_path, session):
    out = write_results(tmp_path / "out")
    shutil.rmtree(out / "physics")
    cfg = load_config(None, ["export.vertices_float16=true", "export.meshes=false"])
    figures = export.run(session, cfg, out, progress=False)
    with np.load(out / "export" / "sample.npz") as z:
        assert z["body_vertices"].dtype == np.float16
        assert np.nanmax(np.abs(z["body_vertices"] - np.load(out / "body_vertices.npy"))) < 2e-3
        assert not any(k.startswith("physics_") for k in z.files)
    assert figures["left_out"] == ["physics"] and not (out / "meshes").exists()


def test_scene_colours_contact_vertices(exported):
    out, _ = exported
    contact = np.load(GT / "contact.npy")
    touching, apart = int(np.flatnonzero(contact)[0]) + 1, 0
    for i, expect in ((touching, True), (apart, False)):
        scene = trimesh.load(out / "meshes" / f"scene_{i:06d}.ply", process=False)
        red = (scene.visual.vertex_colors[:, :3] == export.CONTACT_RED).all(1)
        assert red.any() == expect
    body = np.load(out / "body_vertices.npy")[touching]
    poses = np.load(out / "object_poses.npz")
    scene = trimesh.load(out / "meshes" / f"scene_{touching:06d}.ply", process=False)
    red_body = (scene.visual.vertex_colors[:len(body), :3] == export.CONTACT_RED).all(1)
    # the sample's object is a centred box of half extents (0.15, 0.1, 0.075): distance outside it, analytically
    local = (body - poses["t"][touching]) @ poses["R"][touching]
    outside = np.linalg.norm(np.maximum(np.abs(local) - [0.15, 0.1, 0.075], 0), axis=1)
    inside = (np.abs(local) <= [0.15, 0.1, 0.075]).all(1)
    assert red_body.any() and outside[red_body].max() <= 0.02 + 1e-6
    assert red_body[(outside < 0.019) & ~inside].all()


def test_behave_export_follows_their_conventions(exported, session, tmp_path):
    out, _ = exported
    seq = out / "export" / "behave" / "sequences" / "sample"
    template = trimesh.load(out / "export" / "behave" / "objects" / "box" / "box.ply", process=False)
    assert np.allclose(template.vertices.mean(0), 0, atol=1e-6)
    poses = np.load(out / "object_poses.npz")
    i = 12
    frame = seq / "t0002.400"  # frame 12 at 5 fps
    with open(frame / "box" / "fit01" / "box_fit.pkl", "rb") as f:
        fit = pickle.load(f)
    assert fit["angle"].shape == (3,) and fit["trans"].shape == (3,)
    posed = template.vertices @ Rotation.from_rotvec(fit["angle"]).as_matrix().T + fit["trans"]  # BEHAVE's loader
    world = session.object.load_mesh().vertices @ poses["R"][i].T + poses["t"][i]
    assert np.abs(posed - world).max() < 1e-5
    obj_fit = trimesh.load(frame / "box" / "fit01" / "box_fit.ply", process=False)
    assert np.abs(obj_fit.vertices - world).max() < 1e-5
    person = trimesh.load(frame / "person" / "fit02" / "person_fit.ply", process=False)
    assert np.array_equal(person.vertices, np.load(out / "body_vertices.npy")[i].astype(np.float64))
    with open(frame / "person" / "fit02" / "person_fit.pkl", "rb") as f:
        pfit = pickle.load(f)
    assert pfit["model"] == "anny" and np.array_equal(pfit["trans"], np.load(GT / "body_params.npz")["transl"][i])
    assert not (seq / "t0000.600" / "person").exists()  # frame 3: no body
    assert not (seq / "t0001.000" / "box").exists()  # frame 5: no object

    # in camera cam1's frame, as BEHAVE keeps its fits in its camera k1's frame
    cfg = load_config(None, ["export.behave_frame=cam1"])
    res = export.load_results(out, session.num_frames)
    export.write_behave(session, res, tmp_path, cfg.export.behave_frame, progress=False)
    frame = tmp_path / "export" / "behave" / "sequences" / "sample" / "t0002.400"
    with open(frame / "box" / "fit01" / "box_fit.pkl", "rb") as f:
        fit = pickle.load(f)
    T_cw = session.camera("cam1").T_cam_from_world
    posed = template.vertices @ Rotation.from_rotvec(fit["angle"]).as_matrix().T + fit["trans"]
    assert np.abs(posed - (world @ T_cw[:3, :3].T + T_cw[:3, 3])).max() < 1e-5
    with pytest.raises(export.ExportError, match="behave_frame"):
        export.write_behave(session, res, tmp_path, "k7", progress=False)
