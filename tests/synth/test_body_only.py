"""Takes of the person alone (no object): `--object none` on any script, and the body-only scripts
bend, sit_stand and walk_out.

Four tiny sessions (2 cameras, 96x80) are generated once for the module: turn with no object
(4 frames), and bend (9 frames), sit_stand (11 frames) and walk_out (21 frames), which have no
object by default. The stool sit_stand sits on is checked on the animation itself (`animate`),
where its pose is known.
"""
from __future__ import annotations

import dataclasses
import json
import shutil

import cv2
import numpy as np
import pytest
import yaml

from intercap.evaluation.evaluate import evaluate
from intercap.session import Session, validate
from intercap.synth import motions as mo
from intercap.synth.generator import (
    PRESETS,
    SynthConfig,
    build_arg_parser,
    cached_body_model,
    config_from_args,
    generate_session,
)
from intercap.synth.objects import NO_OBJECT

TINY = SynthConfig(**PRESETS["tiny"], quiet=True)
NOSE, R_SHOULDER, R_ELBOW, R_WRIST, L_SHOULDER, L_ELBOW, L_WRIST, MID_HIP = 0, 2, 3, 4, 5, 6, 7, 8  # BODY_25
BODY_GT_FILES = ("body_vertices.npy", "body_faces.npy", "keypoints3d.npy", "contact.npy")


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    root = tmp_path_factory.mktemp("body_only")
    return {"turn": generate_session(dataclasses.replace(TINY, script="turn", object=NO_OBJECT), root / "turn"),
            "bend": generate_session(dataclasses.replace(TINY, script="bend", frames=9), root / "bend"),
            "sit_stand": generate_session(dataclasses.replace(TINY, script="sit_stand", frames=11), root / "sit_stand"),
            "walk_out": generate_session(dataclasses.replace(TINY, script="walk_out", frames=21), root / "walk_out")}


def keypoints(session) -> np.ndarray:
    return np.load(session / "ground_truth" / "keypoints3d.npy").astype(np.float64)


# ----------------------------------------------------------------------------- the session has no object
@pytest.mark.parametrize("name", ["turn", "bend", "sit_stand", "walk_out"])
def test_session_without_object_loads_and_validates_clean(sessions, name):
    session = sessions[name]
    doc = yaml.safe_load((session / "session.yaml").read_text())
    assert "object" not in doc and set(doc) == {"fps", "frames", "body"}
    assert not (session / "object.ply").exists() and not (session / "object_contacts.json").exists()
    loaded = Session.load(session)
    assert loaded.object is None and loaded.num_cameras == 2
    checked, problems = validate(session)
    assert checked is not None and checked.object is None
    assert problems == [], [str(p) for p in problems]


@pytest.mark.parametrize("name", ["turn", "bend", "sit_stand", "walk_out"])
def test_masks_are_of_the_person_alone(sessions, name):
    session = sessions[name]
    T = len(list((session / "cam0" / "color").glob("*.jpg")))
    for cam in ("cam0", "cam1"):
        assert not (session / cam / "masks" / "object").exists()
        person = sorted((session / cam / "masks" / "person").glob("*.png"))
        assert len(person) == T
        for path in person:
            mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}, path
        assert person_pixels(session, cam)[0] > 20  # the person is in view at the start (walk_out leaves later)


@pytest.mark.parametrize("name", ["turn", "bend", "sit_stand", "walk_out"])
def test_ground_truth_has_the_body_and_no_object(sessions, name):
    gt = sessions[name] / "ground_truth"
    for file in BODY_GT_FILES:
        assert (gt / file).is_file(), file
    assert not (gt / "object_poses.npz").exists() and not (gt / "physics.npz").exists()
    T = len(np.load(gt / "body_vertices.npy"))
    contact = np.load(gt / "contact.npy")
    assert contact.dtype == bool and contact.shape == (T,) and not contact.any()
    info = json.loads((gt / "info.json").read_text())
    assert info["hand_object"] == {} and info["hand_object_distance_m"] is None
    assert info["config"]["object"] == (NO_OBJECT if name == "turn" else None)


def test_evaluation_scores_the_body_of_a_session_without_object(sessions, tmp_path):
    """A results folder holding the ground truth's own body files scores zero error and skips the object."""
    session = sessions["sit_stand"]
    for file in BODY_GT_FILES:
        shutil.copy(session / "ground_truth" / file, tmp_path / file)
    result = evaluate(tmp_path, session, surface_samples=200)
    m = result.metrics
    assert m["frames"] == 11
    assert m["body_surface_mm"] == pytest.approx(0.0, abs=1e-6)
    assert m["keypoint_mpjpe_mm"] == pytest.approx(0.0, abs=1e-6)
    assert m["contact_accuracy_pct"] == 100.0
    assert not any(k.startswith(("object_", "penetration")) for k in m), sorted(m)
    assert any("object metrics skipped" in note for note in result.notes)


# ----------------------------------------------------------------------------- the motions
def elbow_flexion(kp: np.ndarray, shoulder: int, elbow: int, wrist: int) -> np.ndarray:
    """(T,) radians between the upper arm and the forearm (0: the arm straight)."""
    upper, fore = kp[:, elbow] - kp[:, shoulder], kp[:, wrist] - kp[:, elbow]
    cos = (upper * fore).sum(1) / np.linalg.norm(upper, axis=1) / np.linalg.norm(fore, axis=1)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def test_turn_without_object_turns_with_the_arms_relaxed(sessions):
    kp = keypoints(sessions["turn"])
    for joints in ((R_SHOULDER, R_ELBOW, R_WRIST), (L_SHOULDER, L_ELBOW, L_WRIST)):
        assert elbow_flexion(kp, *joints).max() < 0.9  # relaxed 0.72 rad by the keypoints; holding the box 1.16
    shoulders = kp[:, L_SHOULDER, :2] - kp[:, R_SHOULDER, :2]
    angle = np.degrees(np.abs(np.angle(complex(*shoulders[1]) / complex(*shoulders[0]))))
    assert angle > 45  # a third of the way through the script the person faces elsewhere


def test_bend_brings_the_head_down_and_up_again(sessions):
    kp = keypoints(sessions["bend"])
    nose = kp[:, NOSE, 2]
    assert nose[0] - nose[len(nose) // 2] > 0.3
    assert abs(nose[-1] - nose[0]) < 0.01
    hands = kp[len(nose) // 2, [L_WRIST, R_WRIST], 2]
    assert (hands < 0.65).all(), hands  # the hands hang low, by the knees (0.9 m standing)
    vertices = np.load(sessions["bend"] / "ground_truth" / "body_vertices.npy")
    assert np.abs(vertices[..., 2].min(1)).max() < 1e-3  # the feet stay on the floor


def test_sit_stand_lowers_the_pelvis_and_stands_up_again(sessions):
    kp = keypoints(sessions["sit_stand"])
    hip = kp[:, MID_HIP, 2]
    assert hip[0] - hip[len(hip) // 2] > 0.2
    assert abs(hip[-1] - hip[0]) < 0.01
    info = json.loads((sessions["sit_stand"] / "ground_truth" / "info.json").read_text())
    assert info["props"] == ["stool"]


def person_pixels(session, cam: str) -> np.ndarray:
    """(T,) person-mask pixels of one view per frame."""
    paths = sorted((session / cam / "masks" / "person").glob("*.png"))
    return np.array([(cv2.imread(str(p), cv2.IMREAD_UNCHANGED) > 127).sum() for p in paths])


def test_walk_out_leaves_a_view_and_comes_back(sessions):
    session = sessions["walk_out"]
    pixels = {cam: person_pixels(session, cam) for cam in ("cam0", "cam1")}
    for cam, n in pixels.items():
        assert n[0] > 50 and n[-1] > 50, (cam, n)  # in every view at the start and the end
    assert any((n == 0).sum() >= 2 for n in pixels.values()), pixels  # out of a view for a while
    root = np.load(session / "ground_truth" / "body_params.npz")["transl"][:, :2].astype(np.float64)
    away = np.linalg.norm(root - root[0], axis=1)
    assert away.max() > 2.0 and away[-1] < 0.3, away
    assert np.linalg.norm(root[0]) < 1e-6  # it starts in the middle of the ring


@pytest.mark.parametrize("height", [0.5, 1.0])
def test_the_stool_stands_under_the_seated_body_and_nothing_sinks_in(height):
    """For a person of mean height and a tall one: seated, the buttocks rest on the stool's top (within
    3 mm); at no time does the body sink more than 3 mm into the seat; standing, it is clear of it."""
    model = cached_body_model()
    script = mo.get_script("sit_stand")
    times = np.arange(0.0, script.duration + 1e-9, 0.25)
    phenotype = (0.5, 0.5, 0.5, 0.5, height, 0.5)
    anim = mo.animate(model, script, None, times, phenotype)
    assert anim.object_poses is None and not anim.contact.any()
    (name, mesh, pose), = anim.props
    assert name == "stool" and mesh.is_watertight
    lo, hi = mesh.bounds
    assert lo[2] + pose[2, 3] == pytest.approx(0.0, abs=1e-9)  # it stands on the floor
    local = (anim.vertices.astype(np.float64) - pose[:3, 3]) @ pose[:3, :3]  # (T, V, 3) in the stool's frame
    over = (np.abs(local[..., :2]) < hi[:2]).all(-1) & (local[..., 2] > lo[2])
    depth = np.where(over, hi[2] - local[..., 2], -np.inf).max(1)  # (T,) deepest body point below the top
    seated = (times >= script.phases["seated"][0]) & (times < script.phases["seated"][1])
    standing = times <= script.phases["stand"][1]
    assert np.abs(depth[seated]).max() < 0.003, depth[seated]
    assert depth.max() < 0.003, depth
    assert (depth[standing] < -0.1).all(), depth[standing]


def test_without_object_keeps_the_motion_and_relaxes_the_arms():
    for name in mo.SCRIPT_NAMES:
        script = mo.get_script(name)
        alone = mo.without_object(script)
        assert not alone.holds_object and alone.object_keys == [] and alone.flight is None
        assert mo.contact_interval(alone) == (0.0, 0.0)
        assert alone.yaw_keys == script.yaw_keys and alone.walk_keys == script.walk_keys
        assert alone.pitch_keys == script.pitch_keys and alone.props == script.props
        if not script.holds_object:
            assert alone is script
            continue
        for (t, pose), (t0, scripted) in zip(alone.pose_keys, script.pose_keys):
            assert t == t0
            for bone, rv in pose.items():
                if bone.startswith(mo.ARM_BONE_PREFIXES):
                    assert rv == mo.ARMS_RELAXED[bone], (name, bone)
                else:
                    assert rv == scripted[bone], (name, bone)


def test_command_line_object_none_and_body_only_scripts_refuse_an_object(tmp_path):
    args = build_arg_parser().parse_args([str(tmp_path / "a"), "--script", "pick_place", "--object", "none"])
    assert config_from_args(args).object == NO_OBJECT
    args = build_arg_parser().parse_args([str(tmp_path / "b"), "--script", "sit_stand"])
    assert config_from_args(args).script == "sit_stand"
    with pytest.raises(ValueError, match="takes no object"):
        generate_session(dataclasses.replace(TINY, script="bend", object="box"), tmp_path / "c")
    assert not (tmp_path / "c").exists()
