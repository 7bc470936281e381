"""The `contact` stage on the committed sample session, its ground truth standing in for the per-frame results."""
import numpy as np
import pytest
from conftest import SAMPLE_SESSION

from intercap.config import load_config
from intercap.evaluation.metrics import contact_scores
from intercap.pipeline import run_pipeline
from intercap.session import Session
from intercap.stages.contact import stage as contact

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



def test_a_box_carried_in_the_air_by_hands_fitted_away_from_it_is_held(tmp_path, session, truth):
    """Both palms 10 cm off the box while it is high in the air (frames 14-21 of the 5 fps sample): the
    distances see no contact, but the box would have fallen 12 m: held, by the hands that lifted it."""
    import json

    regions, _ = contact.body_regions(load_config().body_model)
    vertices = np.load(GT / "body_vertices.npy")
    poses = np.load(GT / "object_poses.npz")
    mesh_centre = session.object.load_mesh().vertices.mean(0)
    carried = np.arange(14, 22)
    assert truth[carried].all() and (poses["t"][carried, 2] > 0.5).all()  # the test means something
    for f in carried:
        centre = poses["R"][f] @ mesh_centre + poses["t"][f]
        for hand in ("left_hand", "right_hand"):
            away = vertices[f, regions[hand]].mean(0) - centre
            vertices[f, regions[hand]] += 0.10 * away / np.linalg.norm(away)
    out = write_per_frame(tmp_path / "out", vertices=vertices)
    contact.run(session, load_config(overrides=["contact.held=false"]), out, progress=False)
    assert not np.load(out / "contact.npy")[carried].any()  # by distance alone: dropped
    (out / "prepare").mkdir()
    ground = json.loads((GT / "ground.json").read_text())
    (out / "prepare" / "ground.json").write_text(json.dumps({**ground, "inlier_ratio": 1.0, "rmse_m": 0.0}))
    figures = contact.run(session, load_config(), out, progress=False)
    data = contact.load_contact(out)
    assert figures["held_runs"] == [[14, 21]] and data["held"][carried].all() and data["held"].sum() == 8
    assert np.load(out / "contact.npy")[carried].all()
    names = data["region_names"]
    assert data["region_contact"][carried][:, [names.index("left_hand"), names.index("right_hand")]].all()
    assert contact_scores(np.load(out / "contact.npy"), truth)[0] >= 90.0

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


def test_nan_body_frames_are_listed_and_held_only_inside_a_contact_run(tmp_path, session, truth):
    """Frames without a body fit say nothing: inside a contact run they are held through (untracked), where
    contact begins they count as no contact."""
    vertices = np.load(GT / "body_vertices.npy")
    first = int(np.flatnonzero(truth)[0])
    inside, edge = np.flatnonzero(truth)[4:7], np.array([first - 1, first])  # 3 contact frames on each side
    lost = np.sort(np.r_[edge, inside])
    vertices[lost] = np.nan
    out = write_per_frame(tmp_path / "out", vertices=vertices)
    figures = contact.run(session, load_config(), out, progress=False)
    data = contact.load_contact(out)
    labels = np.load(out / "contact.npy")
    assert labels[inside].all() and data["untracked"][inside].all() and figures["untracked_gap_frames"] == 3
    assert not labels[edge].any()
    assert data["region_contact"][inside].any(1).all()
    assert np.isnan(data["region_distance_m"][lost]).all()
    assert figures["invalid_frame_ids"] == lost.tolist() and np.flatnonzero(data["invalid"]).tolist() == lost.tolist()


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


def _carried(T: int = 120, fps: float = 30.0):
    """A cup's centre (T, 3): on a table (0.8 m) until frame 20, lifted by the right hand (contact
    20-39), then, touching nothing by the labels, raised to the mouth (1.4 m), held there, and put back
    on the table by frame 85, where it stays."""
    z = np.full(T, 0.8)
    z[20:40] = np.linspace(0.8, 1.2, 20)
    z[40:55] = np.linspace(1.2, 1.4, 15)
    z[55:70] = 1.4
    z[70:86] = np.linspace(1.4, 0.8, 16)
    centres = np.stack([np.full(T, 0.3), np.zeros(T), z], 1)
    contact = np.zeros(T, bool)
    contact[20:40] = True
    regions = np.zeros((T, 2), bool)  # left hand, right hand
    regions[20:40, 1] = True
    return centres, contact, regions, fps


def test_an_object_that_touches_nothing_but_does_not_fall_is_held_by_the_hand_that_had_it():
    centres, contact, regions, fps = _carried()
    on_ground = centres[:, 2] < 0.02
    held, holding, runs = contact_module_held(contact, regions, centres, on_ground, fps)
    assert runs == [(40, 84)]  # until it lies on the table (frame 85: within 1.5 cm of where it stays)
    assert held[40:85].all() and not held[85:].any() and not held[:40].any()
    assert holding[held, 1].all() and not holding[:, 0].any()  # the right hand, which lifted it
    # taken from where it lay by a hand that touches it after the run: held since it left
    later = np.zeros_like(contact)
    later[86:100] = True
    hands = np.zeros_like(regions)
    hands[86:100, 0] = True
    held, holding, runs = contact_module_held(later, hands, centres, on_ground, fps)
    assert runs == [(21, 85)]  # it left the table at frame 20 (1.5 cm up by frame 21)
    assert holding[held, 0].all() and not holding[:, 1].any()


def test_a_few_untracked_frames_neither_end_a_held_run_nor_hide_the_hand_after_it():
    """Frames the object tracker did not trust (NaN centres), fewer than `min_frames` in a row: inside
    the run at the mouth, and just before the hand that takes the cup from the table."""
    centres, contact, regions, fps = _carried()
    on_ground = centres[:, 2] < 0.02
    inside = centres.copy()
    inside[60:64] = np.nan
    held, holding, runs = contact_module_held(contact, regions, inside, on_ground, fps)
    assert runs == [(40, 84)] and held[40:85].all() and holding[held, 1].all()
    later = np.zeros_like(contact)
    later[86:100] = True
    hands = np.zeros_like(regions)
    hands[86:100, 0] = True
    before_hand = centres.copy()
    before_hand[82:86] = np.nan
    held, holding, runs = contact_module_held(later, hands, before_hand, on_ground, fps)
    assert runs == [(21, 85)] and holding[held, 0].all()
    far = centres.copy()
    far[78:86] = np.nan  # as many untracked frames as a flight needs: the hand after them says nothing
    held, _, runs = contact_module_held(later, hands, far, on_ground, fps)
    assert not held[78:86].any()


def test_a_held_run_ends_where_the_object_comes_to_rest_despite_jitter():
    """One view's cup on a table jitters from frame to frame (here +-7 mm along x, the last frame
    12 mm off): the hand let go where it came to rest (frame 85), not at the last jittery frame."""
    centres, contact, regions, fps = _carried()
    jitter = centres.copy()
    jitter[86:, 0] += 0.007 * (-1.0) ** np.arange(len(centres) - 86)
    jitter[-1, 0] = centres[-1, 0] + 0.012  # 19 mm from every other frame on the table
    held, _, runs = contact_module_held(contact, regions, jitter, centres[:, 2] < 0.02, fps)
    assert runs == [(40, 84)] and not held[85:].any()


def test_a_falling_object_or_one_nobody_held_is_not_held():
    T, fps = 60, 30.0
    t = np.arange(T) / fps
    z = np.where(t < 1.0, 1.5, 1.5 - 0.5 * 9.81 * (t - 1.0) ** 2)  # let go at frame 30: a free fall
    z = np.maximum(z, 0.05)
    centres = np.stack([np.zeros(T), np.zeros(T), z], 1)
    contact = np.zeros(T, bool)
    contact[:30] = True
    regions = np.zeros((T, 2), bool)
    regions[:30, 1] = True
    held, _, runs = contact_module_held(contact, regions, centres, z < 0.06, fps)
    assert not held.any() and runs == []
    # the carried cup without the contact that lifted it: nobody to give it to
    centres, contact, regions, fps = _carried()
    held, _, runs = contact_module_held(np.zeros_like(contact), np.zeros_like(regions), centres,
                                        centres[:, 2] < 0.02, fps)
    assert not held.any() and runs == []


def contact_module_held(contact_labels, regions, centres, on_ground, fps):
    return contact.held_frames(contact_labels, regions, centres, on_ground, np.array([0.0, 0.0, 1.0]), fps,
                               min_frames=8, max_residual_m=0.05, rest_m=0.015)


def test_a_short_gap_in_a_carry_is_filled_and_one_beside_an_object_at_rest_is_not():
    """A tool carried at 2 cm per frame, its hand fitted a little off it in 3 frames: those are carried.
    A 9-frame gap is `held_frames`' to judge (long enough for a flight), a gap at the take's edge has no
    contact on one side, and one after an untracked frame has nothing to measure the move from; a hand
    nearing an object at rest (3 mm jitter) touches it in some frames and not in others, and stays so."""
    T = 30
    moving = np.zeros((T, 3))
    moving[:, 0] = np.linspace(0.0, 0.58, T)
    labels = np.ones(T, bool)
    labels[10:13] = labels[20:29] = labels[:2] = False
    carried = contact.carried_gaps(labels, moving, 8, 0.015)
    assert carried[10:13].all() and carried.sum() == 3
    still = np.random.default_rng(0).normal(0.0, 0.003, (T, 3))
    assert not contact.carried_gaps(labels, still, 8, 0.015).any()
    untracked = moving.copy()
    untracked[9] = np.nan
    assert not contact.carried_gaps(labels, untracked, 8, 0.015)[10:13].any()


def test_an_untracked_gap_between_contact_frames_is_held_and_a_judged_one_is_not():
    """Frames where the object was not trusted say nothing: between two contact frames, a gap of them too
    short to be a flight is contact, touched by the regions next to it. A gap with a judged frame in it,
    one at the take's edge, one as long as a flight and one beside a contact frame alone stay as they are."""
    T = 40
    labels = np.ones(T, bool)
    judged = np.ones(T, bool)
    labels[5:7] = judged[5:7] = False  # two untrusted frames inside a carry
    labels[12:15] = False
    judged[12] = judged[14] = False  # frame 13 was judged: no contact
    labels[20:29] = judged[20:29] = False  # as long as a flight (8 frames or more)
    labels[:2] = judged[:2] = False  # the take's edge
    labels[32:34] = judged[32:34] = False  # a contact frame alone among untrusted ones
    labels[35:38] = judged[35:38] = False
    gaps = contact.untracked_gaps(labels, judged, 8, 3)
    assert np.flatnonzero(gaps).tolist() == [5, 6]
    touching = np.zeros((T, 3), bool)
    touching[labels, 1] = True
    touching[7, 2] = True
    regions = contact.neighbours_regions(touching, gaps)
    assert regions[5].tolist() == regions[6].tolist() == [False, True, True]
    assert (regions[~gaps] == touching[~gaps]).all()
