"""`intercap import k4a`: the object block (--object, --mass-kg) and rig poses matched to devices by serial number."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import trimesh
import yaml

from intercap.cli import main
from intercap.io.k4a import K4AError, import_k4a
from intercap.session import Session

from tests.io.test_k4a import _synthetic_rig


def _rig_file(path, cameras):
    path.write_text(json.dumps({"cameras": cameras}))
    return path


def _pose(x):
    T = np.eye(4)
    T[0, 3] = x
    return T.tolist()


def test_object_mesh_and_mass_make_a_complete_session(tmp_path, capsys):
    paths = _synthetic_rig(tmp_path, n=2, offsets_ns=(0,))
    box = tmp_path / "my box.ply"
    trimesh.creation.box((0.3, 0.2, 0.1)).export(box)
    out = tmp_path / "session"
    assert main(["import", "k4a", str(out), str(paths[0]), "--object", str(box), "--mass-kg", "1.5", "-q"]) == 0
    doc = yaml.safe_load((out / "session.yaml").read_text())
    assert doc["object"] == {"mesh": "object.ply", "name": "my box", "mass_kg": 1.5}
    session = Session.load(out)
    assert session.object is not None and session.object.mass_kg == 1.5
    assert np.allclose(trimesh.load(out / "object.ply").extents, (0.3, 0.2, 0.1))


def test_object_options_are_checked_before_any_work(tmp_path):
    paths = _synthetic_rig(tmp_path, n=2, offsets_ns=(0,))
    with pytest.raises(K4AError, match="--object"):
        import_k4a(tmp_path / "s", paths, mass_kg=2.0)
    (tmp_path / "notes.txt").write_text("not a mesh")
    with pytest.raises(K4AError, match=r"\.ply or \.obj"):
        import_k4a(tmp_path / "s", paths, object_mesh=tmp_path / "notes.txt")
    with pytest.raises(FileNotFoundError, match="object mesh not found"):
        import_k4a(tmp_path / "s", paths, object_mesh=tmp_path / "missing.ply")
    assert not (tmp_path / "s").exists()


def test_imported_calibration_records_the_serials(tmp_path):
    paths = _synthetic_rig(tmp_path, n=2)
    import_k4a(tmp_path / "s", paths, uncalibrated=True, end=0)
    cams = json.loads((tmp_path / "s" / "calibration.json").read_text())["cameras"]
    assert [c["serial"] for c in cams] == ["S0", "S1"]


def test_rig_poses_follow_the_serial_not_the_order(tmp_path, caplog):
    """The calibration's cameras in the other order than the recordings: each device gets the pose
    of the entry with its serial, and the summary says which got which."""
    paths = _synthetic_rig(tmp_path, n=2)
    rig = _rig_file(tmp_path / "rig.json", [{"name": "cam0", "serial": "S1", "T_world_from_cam": _pose(0.7)},
                                            {"name": "cam1", "serial": "S0", "T_world_from_cam": _pose(0.0)}])
    with caplog.at_level(logging.INFO, logger="intercap.io.k4a"):
        r = import_k4a(tmp_path / "s", paths, calibration=rig, end=0)
    cams = json.loads((tmp_path / "s" / "calibration.json").read_text())["cameras"]
    assert [c["T_world_from_cam"][0][3] for c in cams] == [0.0, 0.7]
    assert "matched by serial S1" in r["pose_sources"][1] and "'cam0'" in r["pose_sources"][1]
    assert not [rec for rec in caplog.records if rec.levelno >= logging.WARNING]
    bad = _rig_file(tmp_path / "bad.json", [{"name": "a", "serial": "S0", "T_world_from_cam": _pose(0)},
                                            {"name": "b", "serial": "X9", "T_world_from_cam": _pose(1)}])
    with pytest.raises(K4AError, match=r"dev1\.mkv \(S1\)"):
        import_k4a(tmp_path / "s2", paths, calibration=bad, end=0)


def test_rig_poses_without_serials_go_by_order_with_a_warning(tmp_path, caplog):
    paths = _synthetic_rig(tmp_path, n=2)
    rig = _rig_file(tmp_path / "rig.json", [{"name": "left", "T_world_from_cam": _pose(0.0)},
                                            {"name": "right", "T_world_from_cam": _pose(0.5)}])
    with caplog.at_level(logging.INFO, logger="intercap.io.k4a"):
        r = import_k4a(tmp_path / "s", paths, calibration=rig, end=0)
    assert "matched by position 1" in r["pose_sources"][1]
    warned = [rec.getMessage() for rec in caplog.records if rec.levelno == logging.WARNING]
    assert any("no serial number" in m and "order" in m for m in warned), warned
