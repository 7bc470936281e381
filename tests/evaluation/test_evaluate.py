"""Evaluation against known truth on tiny hand-made sessions (a box / an irregular mesh, sphere bodies)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
import yaml

from intercap.evaluation.evaluate import EvalResult, evaluate
from intercap.evaluation.table import format_table, write_json
from intercap.geometry.surfaces import TriangleSurface
from intercap.geometry.symmetry import axis_angle_matrix, detect_symmetry, rotation_angle_deg

FPS = 30.0
BOX = (0.2, 0.3, 0.1)  # x, y, z extents (m); box centred on the object origin


def box_mesh():
    return trimesh.creation.box(extents=BOX)


def irregular_mesh():
    """A closed, non-symmetric hexahedron: a box with two corners pulled out by different amounts."""
    m = box_mesh()
    v = np.array(m.vertices)
    v[0] += [-0.03, -0.02, -0.01]
    v[5] += [0.01, 0.04, 0.02]
    return trimesh.Trimesh(v, m.faces, process=False)


def sphere(radius=0.1, subdivisions=2):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices), np.asarray(s.faces)


def gt_object_poses(T):
    """Object turning about z and sliding along x: R (T,3,3), t (T,3)."""
    R = np.stack([axis_angle_matrix([0, 0, 1], math.radians(3.0 * i)) for i in range(T)])
    t = np.stack([[0.01 * i, 0.0, 1.0] for i in range(T)])
    return R, t


def write_session(root, *, T=5, mesh=None, contact=None, body=None, poses=None, keypoints=None):
    """A session folder with session.yaml, object.ply and ground_truth/ arrays."""
    root.mkdir(parents=True, exist_ok=True)
    (mesh if mesh is not None else box_mesh()).export(root / "object.ply")
    cfg = {"fps": FPS, "object": {"mesh": "object.ply", "name": "box"}, "frames": {"start": 0, "end": T - 1}}
    (root / "session.yaml").write_text(yaml.safe_dump(cfg))
    gt = root / "ground_truth"
    gt.mkdir(exist_ok=True)
    R, t = poses if poses is not None else gt_object_poses(T)
    np.savez(gt / "object_poses.npz", R=R, t=t)
    if body is None:
        v, f = sphere()
        body = (np.stack([v + [0.5, 0.01 * i, 1.0] for i in range(T)]), f)
    np.save(gt / "body_vertices.npy", body[0].astype(np.float32))
    np.save(gt / "body_faces.npy", body[1])
    np.save(gt / "contact.npy", np.asarray(contact if contact is not None else np.zeros(T), bool))
    if keypoints is not None:
        np.save(gt / "keypoints3d.npy", keypoints.astype(np.float32))
    return root


def write_results(out, **arrays):
    """A results folder holding only the given arrays (object_poses=(R, t), others as .npy)."""
    out.mkdir(parents=True, exist_ok=True)
    for name, value in arrays.items():
        if name == "object_poses":
            np.savez(out / "object_poses.npz", R=value[0], t=value[1])
        else:
            np.save(out / f"{name}.npy", value)
    return out


def copy_gt_to_results(session, out, skip=()):
    gt = session / "ground_truth"
    arrays = {}
    with np.load(gt / "object_poses.npz") as z:
        arrays["object_poses"] = (z["R"], z["t"])
    for name in ("body_vertices", "body_faces", "contact", "keypoints3d"):
        if (gt / f"{name}.npy").exists():
            arrays[name] = np.load(gt / f"{name}.npy")
    return write_results(out, **{k: v for k, v in arrays.items() if k not in skip})


def test_identical_results_give_zero_errors(tmp_path):
    kp = np.random.default_rng(0).normal(size=(5, 67, 3))
    session = write_session(tmp_path / "s", contact=[0, 1, 1, 0, 0], keypoints=kp)
    out = copy_gt_to_results(session, tmp_path / "out")
    r = evaluate(out, session, surface_samples=500)
    m = r.metrics
    assert m["body_surface_mm"] == pytest.approx(0.0, abs=1e-6)
    assert m["object_add_mm"] == pytest.approx(0.0, abs=1e-9)
    assert m["object_rotation_deg"] == pytest.approx(0.0, abs=1e-6)
    assert m["object_translation_mm"] == pytest.approx(0.0, abs=1e-9)
    assert m["keypoint_mpjpe_mm"] == pytest.approx(0.0, abs=1e-9)
    assert m["hand_keypoint_mm"] == pytest.approx(0.0, abs=1e-9)
    assert m["contact_accuracy_pct"] == 100.0
    assert m["body_surface_frames_missing"] == 0 and m["object_frames_missing"] == 0
    assert len(r.per_frame["body_surface_mm"]) == 5 and len(r.per_frame["object_add_mm"]) == 5


def test_object_shifted_10mm_gives_add_10mm_and_nan_frame_is_missing(tmp_path):
    session = write_session(tmp_path / "s", mesh=irregular_mesh())
    R, t = gt_object_poses(5)
    shift = 0.010 * np.array([1.0, 2.0, 2.0]) / 3.0
    t_est = t + shift
    t_est[2] = np.nan  # frame 2 untrusted
    out = write_results(tmp_path / "out", object_poses=(R, t_est))
    m = evaluate(out, session).metrics
    assert m["object_add_mm"] == pytest.approx(10.0, abs=0.01)
    assert m["object_translation_mm"] == pytest.approx(10.0, abs=1e-6)
    assert m["object_rotation_deg"] == pytest.approx(0.0, abs=1e-6)
    assert m["object_frames_missing"] == 1
    r = evaluate(out, session)
    assert r.per_frame["object_add_mm"][2] is None and r.per_frame["object_add_mm"][0] == pytest.approx(10.0)


def test_rotation_of_5_degrees_about_a_known_axis(tmp_path):
    session = write_session(tmp_path / "s", mesh=irregular_mesh())
    R, t = gt_object_poses(5)
    axis = np.array([1.0, -2.0, 0.5])
    R_est = np.einsum("tij,jk->tik", R, axis_angle_matrix(axis, math.radians(5.0)))
    out = write_results(tmp_path / "out", object_poses=(R_est, t))
    r = evaluate(out, session)
    assert r.metrics["object_rotation_deg"] == pytest.approx(5.0, abs=1e-6)
    assert r.metrics["object_add_mm"] > 1.0
    assert r.metrics["object_symmetric"] == 0  # irregular mesh: no ADD-S
    assert "object_adds_mm" not in r.metrics


def test_box_flipped_about_symmetry_axis_is_free_under_adds(tmp_path):
    session = write_session(tmp_path / "s")
    R, t = gt_object_poses(5)
    R_est = np.einsum("tij,jk->tik", R, axis_angle_matrix([0, 0, 1], math.pi))  # 180 deg about the box's z
    out = write_results(tmp_path / "out", object_poses=(R_est, t))
    m = evaluate(out, session).metrics
    assert m["object_symmetric"] == 1
    assert m["object_adds_mm"] == pytest.approx(0.0, abs=1e-6)
    assert m["object_rotation_sym_deg"] == pytest.approx(0.0, abs=1e-4)
    assert m["object_rotation_deg"] == pytest.approx(180.0, abs=1e-4)
    assert m["object_add_mm"] > 100.0  # corners travel across the box
    m_off = evaluate(out, session, symmetric_object=False).metrics
    assert "object_adds_mm" not in m_off and "object_rotation_sym_deg" not in m_off


def test_symmetry_detection_on_box_cylinder_and_irregular_mesh():
    box = detect_symmetry(box_mesh())
    assert len(box.rotations) == 4 and not box.continuous_axes  # three 2-fold axes
    cyl = detect_symmetry(trimesh.creation.cylinder(radius=0.04, height=0.2, sections=32))
    assert len(cyl.continuous_axes) == 1 and abs(cyl.continuous_axes[0][2]) == pytest.approx(1.0)
    assert not detect_symmetry(irregular_mesh()).is_symmetric


def test_the_nearest_equivalent_rotation_takes_out_the_free_turn_only():
    """A cylinder turned about its axis or upside down and a box flipped 180 degrees look as before: the nearest
    equivalent rotation to the unturned pose is that pose; a tilt stays, and an asymmetric object keeps its own."""
    from intercap.geometry.symmetry import nearest_equivalent_rotation

    reference = axis_angle_matrix([0.3, -0.5, 0.8], 0.9)
    cylinder = detect_symmetry(trimesh.creation.cylinder(radius=0.05, height=0.2, sections=64))
    spun = reference @ axis_angle_matrix([0, 0, 1], math.radians(137))
    np.testing.assert_allclose(nearest_equivalent_rotation(spun, reference, cylinder), reference, atol=1e-9)
    upside_down = spun @ axis_angle_matrix([0.6, 0.8, 0], math.pi) @ axis_angle_matrix([0, 0, 1], math.radians(29))
    np.testing.assert_allclose(nearest_equivalent_rotation(upside_down, reference, cylinder), reference, atol=1e-9)
    tilted = spun @ axis_angle_matrix([1, 0, 0], math.radians(10))
    kept = nearest_equivalent_rotation(tilted, reference, cylinder)
    assert abs(rotation_angle_deg(kept, reference) - 10.0) < 1e-6  # the tilt is not a symmetry
    box = detect_symmetry(box_mesh())
    flipped = reference @ axis_angle_matrix([0, 1, 0], math.pi) @ axis_angle_matrix([0, 0, 1], math.radians(3))
    assert rotation_angle_deg(nearest_equivalent_rotation(flipped, reference, box), reference) == pytest.approx(3.0)
    asymmetric = detect_symmetry(irregular_mesh())
    np.testing.assert_allclose(nearest_equivalent_rotation(flipped, reference, asymmetric), flipped)  # nothing free


def test_cylinder_spin_is_free_but_tilt_is_not(tmp_path):
    session = write_session(tmp_path / "s", mesh=trimesh.creation.cylinder(radius=0.04, height=0.2, sections=32))
    R, t = gt_object_poses(5)
    spin_tilt = axis_angle_matrix([1, 0, 0], math.radians(10.0)) @ axis_angle_matrix([0, 0, 1], math.radians(70.0))
    out = write_results(tmp_path / "out", object_poses=(np.einsum("tij,jk->tik", R, spin_tilt), t))
    m = evaluate(out, session).metrics
    assert m["object_rotation_sym_deg"] == pytest.approx(10.0, abs=1e-4)
    assert m["object_rotation_deg"] > 60.0


def test_remeshed_body_offset_5mm_along_normals(tmp_path):
    v, f = sphere(radius=0.1, subdivisions=3)
    T = 3
    centres = np.array([[0.5, 0.01 * i, 1.0] for i in range(T)])
    session = write_session(tmp_path / "s", T=T, body=(np.stack([v + c for c in centres]), f))
    # different topology (every triangle split in four), then each vertex pushed 5 mm outwards
    v2, f2 = trimesh.remesh.subdivide(v, f)
    v2 = v2 + 0.005 * v2 / np.linalg.norm(v2, axis=1, keepdims=True)
    out = write_results(tmp_path / "out", body_vertices=np.stack([v2 + c for c in centres]).astype(np.float32),
                        body_faces=f2)
    r = evaluate(out, session, surface_samples=1500)
    assert len(f2) == 4 * len(f)
    assert r.metrics["body_surface_mm"] == pytest.approx(5.0, abs=0.1)
    assert all(x == pytest.approx(5.0, abs=0.1) for x in r.per_frame["body_surface_mm"])


def test_body_surface_is_symmetric_extra_part_counts_half(tmp_path):
    """Fit = GT sphere + a far copy: GT->fit is 0, fit->GT is half the copy's mean distance; we average both."""
    r, D = 0.1, 1.0
    v, f = sphere(radius=r, subdivisions=3)
    session = write_session(tmp_path / "s", T=2, body=(np.stack([v, v]), f))
    fit_v = np.concatenate([v, v + [D, 0.0, 0.0]])
    fit_f = np.concatenate([f, f + len(v)])
    out = write_results(tmp_path / "out", body_vertices=np.stack([fit_v, fit_v]).astype(np.float32), body_faces=fit_f)
    # mean over a sphere's surface of the distance to a sphere D away: D + r^2 / (3 D) - r
    expected_mm = 1000 * 0.5 * 0.5 * (D + r * r / (3 * D) - r)
    got = evaluate(out, session, surface_samples=4000).metrics["body_surface_mm"]
    assert got == pytest.approx(expected_mm, rel=0.05)


def test_contact_with_two_of_ten_frames_flipped(tmp_path):
    gt = np.array([0, 0, 1, 1, 1, 1, 1, 0, 0, 0], bool)
    session = write_session(tmp_path / "s", T=10, contact=gt)
    pred = gt.copy()
    pred[[0, 1]] = True  # two false positives
    out = write_results(tmp_path / "out", contact=pred)
    m = evaluate(out, session).metrics
    assert m["contact_accuracy_pct"] == pytest.approx(80.0)
    assert m["contact_precision_pct"] == pytest.approx(100.0 * 5 / 7)
    assert m["contact_recall_pct"] == pytest.approx(100.0)


def test_penetration_counts_only_contact_frames(tmp_path):
    T = 5
    R, t = gt_object_poses(T)
    contact = np.array([0, 1, 1, 1, 0], bool)
    depth_mm = np.array([20.0, 8.0, 4.0, 8.0, 20.0])  # non-contact frames penetrate deeper: must be ignored
    v, f = sphere(radius=0.05, subdivisions=2)
    top = BOX[2] / 2
    frames = []
    for i in range(T):  # sphere's lowest vertex depth_mm below the box's top face, in object coordinates
        local = v + [0.01, -0.02, top - depth_mm[i] / 1000.0 - v[:, 2].min()]
        frames.append(local @ R[i].T + t[i])
    body = np.stack(frames)
    session = write_session(tmp_path / "s", T=T, contact=contact, body=(body, f))
    out = write_results(tmp_path / "out", object_poses=(R, t), body_vertices=body.astype(np.float32))
    r = evaluate(out, session)
    m = r.metrics
    assert m["penetration_max_mm"] == pytest.approx(8.0, abs=1e-3)
    assert m["penetration_mean_mm"] == pytest.approx(20.0 / 3.0, abs=1e-3)
    assert m["penetration_median_mm"] == pytest.approx(8.0, abs=1e-3)
    assert r.per_frame["penetration_mm"][0] is None
    assert r.per_frame["penetration_mm"][2] == pytest.approx(4.0, abs=1e-3)


def test_contact_is_also_scored_against_the_bodys_distance_to_the_object(tmp_path):
    """Labels are grasp phases; contact_touch_* score against geometry: a ground-truth body vertex
    within 5 mm of the ground-truth object, or inside it."""
    T = 5
    R, t = gt_object_poses(T)
    gap_mm = np.array([20.0, 3.0, -2.0, 4.0, 8.0])  # the body's lowest point above the box's top face
    label = np.array([0, 0, 1, 1, 1], bool)
    v, f = sphere(radius=0.05, subdivisions=2)
    body = np.stack([(v + [0.01, -0.02, BOX[2] / 2 + gap_mm[i] / 1000.0 - v[:, 2].min()]) @ R[i].T + t[i]
                     for i in range(T)])
    session = write_session(tmp_path / "s", T=T, contact=label, body=(body, f))
    m = evaluate(write_results(tmp_path / "labels", contact=label), session).metrics
    assert m["contact_accuracy_pct"] == 100.0
    assert m["contact_label_is_touch_pct"] == pytest.approx(60.0)  # frames 1 and 4 disagree
    assert m["contact_touch_accuracy_pct"] == pytest.approx(60.0)
    assert m["contact_touch_precision_pct"] == pytest.approx(200 / 3)
    assert m["contact_touch_recall_pct"] == pytest.approx(200 / 3)
    m = evaluate(write_results(tmp_path / "touch", contact=np.array([0, 1, 1, 1, 0], bool)), session).metrics
    assert m["contact_touch_accuracy_pct"] == 100.0 and m["contact_accuracy_pct"] == pytest.approx(60.0)


def test_signed_distance_inside_box():
    s = TriangleSurface(box_mesh().vertices, box_mesh().faces)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.04], [0.09, 0.0, 0.0], [0.0, 0.0, 0.06], [0.11, 0.16, 0.0]])
    np.testing.assert_allclose(s.signed_distance(pts), [-0.05, -0.01, -0.01, 0.01, math.hypot(0.01, 0.01)],
                               atol=1e-12)


def test_jitter_zero_for_constant_velocity_and_known_for_alternating_offsets(tmp_path):
    T = 6
    v, f = sphere(radius=0.1, subdivisions=1)
    body = np.stack([v + [0.5, 0.02 * i, 1.0] for i in range(T)])  # constant velocity
    R = np.repeat(np.eye(3)[None], T, axis=0)
    t = np.array([[0.03 * i, 0.0, 1.0] for i in range(T)])
    session = write_session(tmp_path / "s", T=T, body=(body, f), poses=(R, t))
    wobble = body.copy()
    wobble[:, :, 0] += 0.001 * (-1.0) ** np.arange(T)[:, None]  # +-1 mm: |second difference| = 4 mm
    out = write_results(tmp_path / "out", object_poses=(R, t), body_vertices=wobble.astype(np.float32),
                        body_faces=f)
    m = evaluate(out, session).metrics
    assert m["jitter_gt_mps2"] == pytest.approx(0.0, abs=2e-3)
    assert m["jitter_mps2"] == pytest.approx(0.004 * FPS**2, rel=1e-3)
    assert m["object_jitter_mps2"] == pytest.approx(0.0, abs=1e-9)
    assert m["object_jitter_gt_mps2"] == pytest.approx(0.0, abs=1e-9)


def test_keypoints_body_mpjpe_and_wrist_relative_hands(tmp_path):
    T = 5
    gt = np.random.default_rng(1).normal(size=(T, 67, 3))
    session = write_session(tmp_path / "s", T=T, keypoints=gt)
    est = gt.copy()
    est[:, :25] += [0.0, 0.0, 0.010]  # body joints 10 mm off
    est[:, 25:46] += [0.05, 0.0, 0.0]  # whole left hand moved with its wrist: no hand error
    est[:, 47] += [0.0, 0.004, 0.0]  # one right-hand joint 4 mm off (relative to its wrist)
    est[:, 3] = np.nan  # an untrusted joint is ignored
    est[4] = np.nan  # an untrusted frame is missing
    out = write_results(tmp_path / "out", keypoints3d=est.astype(np.float32))
    m = evaluate(out, session).metrics
    assert m["keypoint_mpjpe_mm"] == pytest.approx(10.0, abs=1e-3)
    assert m["hand_keypoint_mm"] == pytest.approx(4.0 / 40.0, abs=1e-3)
    assert m["keypoint_frames_missing"] == 1 and m["hand_keypoint_frames_missing"] == 1


def test_mismatched_frame_count_names_both_files(tmp_path):
    session = write_session(tmp_path / "s", T=5)
    R, t = gt_object_poses(6)
    out = write_results(tmp_path / "out", object_poses=(R, t))
    with pytest.raises(ValueError) as err:
        evaluate(out, session)
    msg = str(err.value)
    assert str(out / "object_poses.npz") in msg and str(session / "ground_truth" / "object_poses.npz") in msg
    assert "(6, 3, 3)" in msg and "(5, 3, 3)" in msg


def test_only_object_poses_evaluates_object_and_notes_skipped_body(tmp_path):
    session = write_session(tmp_path / "s", contact=[0, 1, 1, 0, 0])
    R, t = gt_object_poses(5)
    out = write_results(tmp_path / "out", object_poses=(R, t + [0.0, 0.0, 0.002]))
    r = evaluate(out, session)
    assert r.metrics["object_translation_mm"] == pytest.approx(2.0)
    assert "body_surface_mm" not in r.metrics and "jitter_mps2" not in r.metrics
    notes = "\n".join(r.notes)
    assert "body_surface_mm skipped" in notes and "body_vertices.npy" in notes
    assert "penetration skipped" in notes and "contact metrics skipped" in notes


def test_table_and_json(tmp_path):
    session = write_session(tmp_path / "s")
    R, t = gt_object_poses(5)
    t_est = t + [0.01, 0.0, 0.0]
    t_est[1] = np.nan
    out = write_results(tmp_path / "out", object_poses=(R, t_est))
    r = evaluate(out, session)
    table = format_table(r)
    line = next(ln for ln in table.splitlines() if ln.startswith("object_add_mm "))
    assert line.split()[1:] == ["10.000", "mm"]
    write_json(r, tmp_path / "eval.json")
    data = json.loads((tmp_path / "eval.json").read_text())
    assert data["metrics"]["object_add_mm"] == pytest.approx(10.0)
    assert data["per_frame"]["object_add_mm"][1] is None and data["notes"] == r.notes
    assert isinstance(r, EvalResult)
