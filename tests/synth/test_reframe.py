"""Re-expressing a session in another world frame keeps every measurement and moves every world array."""
import json

import numpy as np
import pytest
from conftest import SAMPLE_SESSION

from intercap.session import Session, validate
from intercap.synth.reframe import camera_as_world, reexpress


def test_camera_as_world_moves_calibration_and_ground_truth(tmp_path):
    out, T = camera_as_world(SAMPLE_SESSION, tmp_path / "cam0")
    session, problems = validate(out)
    assert session is not None, [str(p) for p in problems if p.fatal]
    old, new = Session.load(SAMPLE_SESSION), session
    assert np.allclose(new.cameras[0].T_world_from_cam, np.eye(4), atol=1e-9)  # camera 0 is the world
    for a, b in zip(old.cameras, new.cameras):  # relative poses unchanged
        assert np.allclose(T @ a.T_world_from_cam, b.T_world_from_cam, atol=1e-9)
    v_old = np.load(SAMPLE_SESSION / "ground_truth" / "body_vertices.npy")
    v_new = np.load(out / "ground_truth" / "body_vertices.npy")
    assert np.allclose(v_old @ T[:3, :3].T + T[:3, 3], v_new, atol=1e-5)
    up = json.loads((out / "ground_truth" / "ground.json").read_text())["normal"]
    assert abs(np.dot(up, [0, 1, 0])) > 0.5  # z-up world became camera axes: up is mostly along -y
    assert (out / "cam0" / "color" / "000000.jpg").read_bytes() == (
        SAMPLE_SESSION / "cam0" / "color" / "000000.jpg").read_bytes()


def test_reexpress_refuses_non_rigid_and_existing_folders(tmp_path):
    with pytest.raises(ValueError, match="rigid"):
        reexpress(SAMPLE_SESSION, tmp_path / "a", np.diag([2.0, 1.0, 1.0, 1.0]))
    (tmp_path / "b").mkdir()
    with pytest.raises(FileExistsError):
        reexpress(SAMPLE_SESSION, tmp_path / "b", np.eye(4))


def test_support_meshes_move_with_the_world_and_the_source_keeps_its_own(tmp_path):
    import shutil

    import trimesh
    import yaml

    src = tmp_path / "src"
    shutil.copytree(SAMPLE_SESSION, src)
    trimesh.creation.box(extents=(0.4, 0.4, 0.45)).export(src / "stool.ply")
    cfg = yaml.safe_load((src / "session.yaml").read_text())
    cfg["supports"] = [{"name": "stool", "mesh": "stool.ply"}]
    (src / "session.yaml").write_text(yaml.safe_dump(cfg))
    before = (src / "stool.ply").read_bytes()
    out, T = camera_as_world(src, tmp_path / "cam0")
    moved = Session.load(out).supports[0].mesh
    original = Session.load(src).supports[0].mesh
    assert (src / "stool.ply").read_bytes() == before  # the copy's mesh is not a link written through
    assert np.allclose(original.vertices @ T[:3, :3].T + T[:3, 3], moved.vertices, atol=1e-6)
