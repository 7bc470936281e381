"""Session layer: values that are well formed but implausible (NaN, wrong units, out-of-image
intrinsics, files outside the session) are reported by validate and refused by load, and values
that YAML 1.1 or other writers spell oddly (`3e1`, `body: anny`, 16-bit masks) read right.

Each case corrupts one thing in a 3-frame copy of data_samples/sample."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from conftest import SAMPLE_SESSION, trimmed_copy

from intercap.cli import main
from intercap.session import Session, SessionError, validate

FRAMES = 3


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    """One trimmed copy of the sample, validated clean; every case copies it."""
    root = trimmed_copy(SAMPLE_SESSION, tmp_path_factory.mktemp("clean") / "sample", FRAMES)
    session, problems = validate(root)
    assert session is not None and problems == [], "\n".join(map(str, problems))
    return root


@pytest.fixture
def copy(clean: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(clean, tmp_path / "session", symlinks=True))


# --------------------------------------------------------------------------- corruptions


def edit_yaml_text(root: Path, old: str, new: str) -> None:
    path = root / "session.yaml"
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))


def edit_camera(root: Path, fn, camera: int = 1) -> None:
    path = root / "calibration.json"
    calib = json.loads(path.read_text())
    fn(calib["cameras"][camera])
    path.write_text(json.dumps(calib))


def set_K(i: int, j: int, value: float):
    return lambda root: edit_camera(root, lambda c: c["K"][i].__setitem__(j, value))


def set_translation(value: float):
    return lambda root: edit_camera(root, lambda c: c["T_world_from_cam"][0].__setitem__(3, value))


def shear_rotation(root: Path) -> None:
    edit_camera(root, lambda c: c["T_world_from_cam"][0].__setitem__(0, c["T_world_from_cam"][0][0] + 0.05))


def edit_keypoint(index: int, value: float, frame: int = 1):
    def mutate(root: Path) -> None:
        path = root / f"cam0/keypoints/{frame:06d}.json"
        data = json.loads(path.read_text())
        data["people"][0]["pose_keypoints_2d"][index] = value
        path.write_text(json.dumps(data))  # NaN written as NaN, as Python's json reads it
    return mutate


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """An ASCII PLY as given, unchecked (trimesh would not export an invalid mesh)."""
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
             "property float z", f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(str(float(x)) for x in v) for v in vertices]
    lines += ["3 " + " ".join(str(int(i)) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")


def edit_mesh(fn):
    def mutate(root: Path) -> None:
        mesh = trimesh.load(str(root / "object.ply"), process=False)
        vertices, faces = fn(np.array(mesh.vertices), np.array(mesh.faces))
        write_ply(root / "object.ply", vertices, faces)
    return mutate


def nan_vertex(v, f):
    v[3, 1] = np.nan
    return v, f


def face_out_of_range(v, f):
    f[5, 2] = len(v) + 7
    return v, f


def edit_depth(fn, cameras=(1,)):
    def mutate(root: Path) -> None:
        for c in cameras:
            for path in sorted((root / f"cam{c}/depth").glob("*.png")):
                depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                cv2.imwrite(str(path), fn(depth).astype(np.uint16))
    return mutate


def outside_mesh(root: Path) -> Path:
    """A copy of the object mesh outside the session folder."""
    target = root.parent / "elsewhere" / "object.ply"
    target.parent.mkdir(exist_ok=True)
    shutil.copy(root / "object.ply", target)
    return target


def mesh_named(name_of):
    def mutate(root: Path) -> None:
        edit_yaml_text(root, "mesh: object.ply", f"mesh: {name_of(root)}")
    return mutate


def symlink_outside(root: Path) -> None:
    target = outside_mesh(root)
    (root / "object.ply").unlink()
    os.symlink(target, root / "object.ply")


def contacts_outside(root: Path) -> None:
    shutil.copy(root / "object_contacts.json", root.parent / "contacts.json")
    edit_yaml_text(root, "contact_vertices: object_contacts.json", "contact_vertices: ../contacts.json")


# (id, corruption, the problem's path, words its message must contain, fatal)
CASES = [
    ("keypoint_nan", edit_keypoint(3, float("nan")), "cam0/keypoints/000001.json", ["NaN"], False),
    ("keypoint_1e30", edit_keypoint(3, 1e30), "cam0/keypoints/000001.json", ["far outside"], False),
    ("confidence_1e6", edit_keypoint(2, 1e6), "cam0/keypoints/000001.json", ["confidence outside [0, 1]"], False),
    ("fx_1e-9", set_K(0, 0, 1e-9), "calibration.json", ["cam1", "fx"], True),
    ("cx_5000", set_K(0, 2, 5000.0), "calibration.json", ["cam1", "cx", "outside the image"], True),
    ("translation_1e12", set_translation(1e12), "calibration.json", ["cam1", "translation", "100 m"], True),
    ("rotation_not_orthonormal", shear_rotation, "calibration.json", ["cam1", "orthonormal"], True),
    ("mesh_face_out_of_range", edit_mesh(face_out_of_range), "object.ply", ["out of range"], True),
    ("mesh_nan_vertex", edit_mesh(nan_vertex), "object.ply", ["NaN"], True),
    ("mesh_all_equal", edit_mesh(lambda v, f: (np.ones_like(v), f)), "object.ply", ["vertices are equal"], True),
    ("mesh_in_millimetres", edit_mesh(lambda v, f: (v * 1000, f)), "object.ply", ["millimetres"], True),
    ("mass_inf", lambda r: edit_yaml_text(r, "mass_kg: 1.2", "mass_kg: .inf"), "session.yaml", ["mass_kg", "inf"],
     True),
    ("fps_1e-9", lambda r: edit_yaml_text(r, "fps: 5", "fps: 1e-9"), "session.yaml", ["fps", "1e-9"], True),
    ("depth_in_metres", edit_depth(lambda d: d // 1000), "cam1/depth/000000.png", ["median depth", "metres"], True),
    ("depth_zero_one_view", edit_depth(np.zeros_like), "cam1/depth", ["no depth measurement"], False),
    ("depth_zero_every_view", edit_depth(np.zeros_like, (0, 1, 2, 3)), ".", ["every camera", "cam2/depth"], True),
    ("mesh_path_up", mesh_named(lambda r: (outside_mesh(r), "../elsewhere/object.ply")[1]), "session.yaml",
     ["object.mesh", "../elsewhere/object.ply", "outside the session folder"], True),
    ("mesh_path_absolute", mesh_named(outside_mesh), "session.yaml", ["object.mesh", "outside the session folder"],
     True),
    ("mesh_symlink_outside", symlink_outside, "session.yaml", ["object.mesh", "outside the session folder"], True),
    ("contacts_path_up", contacts_outside, "session.yaml", ["object.contact_vertices", "outside"], True),
]


@pytest.mark.parametrize("case, mutate, path, words, fatal", CASES, ids=[c[0] for c in CASES])
def test_implausible_input_is_reported(copy: Path, case, mutate, path, words, fatal):
    """validate names the file (or key) and why; a fatal one stops `Session.load` (so `run`) too,
    a warning does not."""
    mutate(copy)
    session, problems = validate(copy)
    matching = [p for p in problems if p.path == path and all(w in p.message for w in words)]
    assert matching, f"no problem at {path!r} mentioning {words}; got:\n" + "\n".join(map(str, problems))
    assert matching[0].fatal == fatal
    if fatal:
        assert session is None
        with pytest.raises(SessionError) as err:
            Session.load(copy)
        assert str(matching[0]) in str(err.value)
    else:
        assert session is not None and not any(p.fatal for p in problems)
        Session.load(copy)


def test_implausible_keypoints_read_as_not_detected(copy: Path):
    """What validate warns about reads as confidence 0, so no NaN or 1e30 reaches a fit."""
    edit_keypoint(3, float("nan"))(copy)
    edit_keypoint(6, 1e30)(copy)
    edit_keypoint(11, 1e6)(copy)
    session = Session.load(copy)
    kp = session.read_keypoints("cam0", 1)
    assert np.isfinite(kp).all() and kp[:, 2].max() <= 1.0
    assert (kp[1:4] == 0).all()
    clean = session.read_keypoints("cam0", 0)
    assert clean[:, 2].max() > 0 and any(p.path == "cam0/keypoints/000001.json" for p in session.problems)


def test_run_refuses_what_validate_refuses(copy: Path, tmp_path: Path, capsys):
    """`intercap run` stops before any stage with the problem validate reports, exit 2, no traceback."""
    set_K(0, 0, 1e-9)(copy)
    code = main(["run", str(copy), "--out", str(tmp_path / "out"), "--stages", "prepare", "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "calibration.json" in err and "fx" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("text, fps", [("3e1", 30.0), ("2.5e1", 25.0), ("'30'", 30.0)])
def test_fps_written_in_exponent_form_is_a_number(copy: Path, text: str, fps: float):
    """YAML 1.1 reads `3e1` as a string (no dot); where a number is expected it is one."""
    edit_yaml_text(copy, "fps: 5", f"fps: {text}")
    session, problems = validate(copy)
    assert problems == [] and session.fps == fps


def test_mass_written_in_exponent_form_is_a_number(copy: Path):
    edit_yaml_text(copy, "mass_kg: 1.2", "mass_kg: 12e-1")
    session, problems = validate(copy)
    assert problems == [] and session.object.mass_kg == pytest.approx(1.2)


@pytest.mark.parametrize("text, model", [("body: anny", "anny"), ("body: smplx", "smplx"),
                                         ("body: {model: ' anny '}", "anny")])
def test_body_model_given_as_a_name_is_accepted(copy: Path, text: str, model: str):
    """`body: anny` is short for `body: {model: anny}`; spaces around the name do not matter."""
    edit_yaml_text(copy, "body:\n  model: anny", text)
    session, problems = validate(copy)
    assert problems == [] and session.body_model == model


def test_body_mass_must_be_finite(copy: Path):
    edit_yaml_text(copy, "body:\n  model: anny", "body: {model: anny, mass_kg: .nan}")
    session, problems = validate(copy)
    assert session is None and any(p.path == "session.yaml" and "body.mass_kg" in p.message for p in problems)


@pytest.mark.parametrize("high", [255, 65535])
def test_sixteen_bit_masks_read_as_binary(copy: Path, high: int):
    """A uint16 mask holding 0/255 or 0/65535 reads as the 8-bit one (plain grayscale decoding
    would read 0/255 as empty)."""
    path = copy / "cam0/masks/person/000000.png"
    want = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127
    assert want.any()
    cv2.imwrite(str(path), np.where(want, high, 0).astype(np.uint16))
    session, problems = validate(copy)
    assert problems == []
    np.testing.assert_array_equal(session.read_mask("cam0", 0, "person"), want)


def test_mesh_inside_the_session_through_a_symlink_is_accepted(copy: Path):
    """Links are resolved: one that stays inside the folder is fine."""
    (copy / "meshes").mkdir()
    (copy / "object.ply").rename(copy / "meshes/box.ply")
    os.symlink(Path("meshes/box.ply"), copy / "object.ply")
    session, problems = validate(copy)
    assert problems == [] and session.object.load_mesh().vertices.shape[0] > 0
