"""The `contact` stage on the committed sample session, its ground truth standing in for the per-frame results."""
import numpy as np
import pytest
from conftest import SAMPLE_SESSION

from intercap.config import load_config
from intercap.evaluation.metrics import contact_scores
from intercap.pipeline import run_pipeline
from intercap.session import Session
from intercap.stages import contact

GT = SAMPLE_SESSION / "ground_truth"


def write_per_frame(out, vertices=None, R=None, t=None):
    """OUT/body/ and OUT/object/ as the per-frame stages write them, from the sample's ground truth."""
    (out / "body").mkdir(parents=True, exist_ok=True)
    (out / "object").mkdir(parents=True, exist_ok=True)
    poses = np.load(GT / "object_poses.npz")
    vertices = np.load(GT / "body_vertices.npy") if vertices is None else vertices
    R = poses["R"] if R is None else R
    t = poses["t"] if t is None else t
    np.save(out / "body" / "body_vertices.npy", vertices.astype(np.float32))
    np.save(out / "body" / "body_faces.npy", np.load(GT / "body_faces.npy"))
    np.savez(out / "object" / "object_poses.npz", R=R, t=t, valid=np.isfinite(R).all((1, 2)),
             frame_ids=np.arange(len(R)))
    return out


@pytest.fixture(scope="module")
def session():
    return Session.load(SAMPLE_SESSION)


@pytest.fixture(scope="module")
def truth():
    return np.load(GT / "contact.npy")


@pytest.fixture(scope="module")
def detected(tmp_path_factory, session):
    out = write_per_frame(tmp_path_factory.mktemp("out"))
    figures = contact.run(session, load_config(), out, progress=False)
    return out, figures, contact.load_contact(out)


def test_3d_detector_matches_truth_on_true_geometry(detected, truth):
    out, figures, data = detected
    assert figures["method"] == "3d" and data["method"] == "3d"  # nothing annotated: the default detector
    saved = np.load(out / "contact.npy")
    assert saved.dtype == bool and saved.shape == truth.shape
    accuracy, precision, recall = contact_scores(saved, truth)
    assert accuracy >= 90.0, (saved.astype(int), truth.astype(int))
    assert precision >= 85.0 and recall >= 95.0
    assert np.array_equal(data["contact"], saved) and np.array_equal(data["distance_3d"], saved)


def test_region_fields_say_which_hands_touch(detected, truth):
    _, _, data = detected
    names = data["region_names"]
    assert {"left_hand", "right_hand"} <= set(names)
    left, right = names.index("left_hand"), names.index("right_hand")
    distance, touching = data["region_distance_m"], data["region_contact"]
    assert distance.shape == touching.shape == (len(truth), len(names))
    # pick_place holds the box with both hands: both palms on it (mm) in the middle of the grasp,
    # far (> 0.5 m) before the reach
    middle = np.flatnonzero(truth)[2:-2]
    assert (distance[middle][:, [left, right]] < 0.005).all()
    assert (distance[:5][:, [left, right]] > 0.5).all()
    assert touching[middle][:, [left, right]].all()
    assert not touching[~data["contact"]].any()  # no region touches outside contact frames


def test_hand_moved_10cm_away_is_not_in_contact(tmp_path, session, truth):
    regions, _ = contact.body_regions(load_config().body_model)
    vertices = np.load(GT / "body_vertices.npy")
    poses = np.load(GT / "object_poses.npz")
    frames = np.flatnonzero(truth)
    left = regions["left_hand"]
    mesh_centre = session.object.load_mesh().vertices.mean(0)
    for f in frames:  # move the left palm 10 cm straight away from the object's centre
        centre = poses["R"][f] @ mesh_centre + poses["t"][f]
        away = vertices[f, left].mean(0) - centre
        vertices[f, left] += 0.10 * away / np.linalg.norm(away)
    out = write_per_frame(tmp_path / "out", vertices=vertices)
    contact.run(session, load_config(), out, progress=False)
    data = contact.load_contact(out)
    k_left, k_right = data["region_names"].index("left_hand"), data["region_names"].index("right_hand")
    assert (data["region_distance_m"][frames, k_left] > 0.05).all()
    assert not data["region_contact"][frames, k_left].any()
    assert data["region_contact"][frames[2:-2], k_right].all()  # the right hand still holds it
    # with only the left hand counted, the moved hand means no contact at all
    contact.run(session, load_config(overrides=["contact.regions=left_hand"]), out, progress=False)
    assert not np.load(out / "contact.npy")[frames].any()


def test_annotations_take_precedence_unless_a_detector_is_named(tmp_path, session, truth):
    out = write_per_frame(tmp_path / "out")
    annotated = Session.load(SAMPLE_SESSION)
    annotated.contact_frames = [(3, 7), (20, 25)]
    expected = np.zeros(annotated.num_frames, bool)
    expected[3:8] = expected[20:26] = True
    figures = contact.run(annotated, load_config(), out, progress=False)
    data = contact.load_contact(out)
    assert figures["method"] == data["method"] == "annotated"
    assert np.array_equal(np.load(out / "contact.npy"), expected)
    assert np.array_equal(data["annotated"], expected)
    # annotated frames: the nearest hand always counts as touching; nothing outside them
    names = data["region_names"]
    hands = data["region_contact"][:, [names.index("left_hand"), names.index("right_hand")]]
    assert hands[expected].any(1).all() and not data["region_contact"][~expected].any()
    contact.run(annotated, load_config(overrides=["contact.method=3d"]), out, progress=False)
    assert contact.load_contact(out)["method"] == "3d"
    assert contact_scores(np.load(out / "contact.npy"), truth)[0] >= 90.0
    with pytest.raises(contact.ContactError, match="no contact_frames"):
        contact.run(session, load_config(overrides=["contact.method=annotated"]), out, progress=False)


def test_nan_body_frames_give_no_contact_and_are_listed(tmp_path, session, truth):
    vertices = np.load(GT / "body_vertices.npy")
    lost = np.flatnonzero(truth)[3:6]
    vertices[lost] = np.nan
    out = write_per_frame(tmp_path / "out", vertices=vertices)
    figures = contact.run(session, load_config(), out, progress=False)
    data = contact.load_contact(out)
    assert not np.load(out / "contact.npy")[lost].any()
    assert np.isnan(data["region_distance_m"][lost]).all()
    assert figures["invalid_frame_ids"] == lost.tolist() and np.flatnonzero(data["invalid"]).tolist() == lost.tolist()
    # a temporal clean-up bridges the hole between contact runs
    contact.run(session, load_config(overrides=["contact.clean_frames=4"]), out, progress=False)
    assert np.load(out / "contact.npy")[lost].all()


def test_missing_per_frame_results_name_the_stage_to_run(tmp_path, session):
    with pytest.raises(contact.ContactError, match="run the `body` stage"):
        contact.run(session, load_config(), tmp_path / "empty", progress=False)
    out = write_per_frame(tmp_path / "out")
    (out / "object" / "object_poses.npz").unlink()
    with pytest.raises(contact.ContactError, match="run the `object` stage"):
        contact.run(session, load_config(), out, progress=False)
    with pytest.raises(contact.ContactError, match="run the `contact` stage"):
        contact.load_contact(tmp_path / "empty")


def test_rendered_silhouettes_overlap_like_the_session_masks(detected, session, truth):
    """Without masks, the 2D baseline renders the per-frame fits: on true geometry it must see the same overlaps."""
    out, _, data = detected
    counts, source, judged = contact.overlap_counts(session, load_config(overrides=["contact.use_session_masks=false"]).contact,
                                                    contact.load_per_frame(out, session), session.object.load_mesh(),
                                                    progress=False)
    assert source == "rendered" and judged.all() and data["mask_source"] == "session"
    masks = data["overlap_px"]
    assert np.corrcoef(counts.ravel(), masks.ravel())[0, 1] > 0.97
    assert np.abs(counts - masks).mean() < 0.1 * masks[truth].mean()


def test_clean_labels_fills_gaps_and_drops_blips():
    labels = np.array([0, 1, 0, 0, 1, 1, 1, 0, 1, 1, 1, 1, 0, 0, 0, 0], bool)
    cleaned = contact.clean_labels(labels, 2)
    assert cleaned.tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0]
    assert contact.clean_labels(labels, 0).tolist() == labels.tolist()
    assert contact.annotated_labels([(1, 2), (5, 5)], np.arange(7)).tolist() == [0, 1, 1, 0, 0, 1, 0]


def test_pipeline_runs_the_contact_stage(tmp_path, truth):
    out = write_per_frame(tmp_path / "out")
    metrics = run_pipeline(SAMPLE_SESSION, out, load_config(overrides=["run.stages=contact"]), progress=False)
    saved = np.load(out / "contact.npy")
    assert saved.dtype == bool and saved.shape == truth.shape
    assert metrics["contact"]["method"] == "3d" and metrics["contact"]["gt_accuracy_3d_pct"] >= 90.0
    assert (out / "contact" / "DONE.json").exists()
