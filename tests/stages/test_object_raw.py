"""The object stage on a raw-like take (depth, no masks): an object resting on a table is found and told
apart from the table, the person and the furniture; a cup in one hand is told from the hand by its colour.

Small `table_lift` sessions (4 views; 40 frames over the whole script, or 15 fps) are generated once for
the module; the tracked copies have no masks, and their keypoints are the generator's simulated
detections (what the `detect` stage would give), so the person can be left out of the searches.
"""
from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from conftest import SessionKeypoints
from intercap.config import load_config
from intercap.evaluation.evaluate import evaluate
from intercap.pipeline import run_pipeline
from intercap.session import Session
from intercap.stages.object.fitter import ObjectTracker
from intercap.synth.generator import SynthConfig, generate_session

RAW = SynthConfig(script="table_lift", cameras=4, width=192, height=160, frames=40, masks=False, ik_iters=40,
                  quiet=True)
# a red cup (8 cm across) held in the right hand, at the bench's 320x288, the script at its natural speed at
# 15 fps (103 frames), another person's skin and clothes
CUP = dataclasses.replace(RAW, object="cup", width=320, height=288, frames=None, fps=15.0, masks=True, appearance=2)


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    root = tmp_path_factory.mktemp("raw_takes")
    return {"carton": generate_session(dataclasses.replace(RAW, object="carton"), root / "carton")}


def tracked(session, out, overrides=()):
    """Per frame ADD-S (mm, NaN where untrusted) and rotation error modulo symmetry (degrees) of the object stage."""
    run_pipeline(session, out, load_config(overrides=list(overrides)), stages=["object"], progress=False)
    result = evaluate(out, session)
    values = {}
    for key in ("object_adds_mm", "object_rotation_sym_deg"):
        values[key] = np.array([np.nan if v is None else v for v in result.per_frame[key]], float)
    return values["object_adds_mm"], values["object_rotation_sym_deg"]


def test_a_box_resting_on_a_table_is_found_and_segmented(takes, tmp_path):
    """The carton rests on the table for the first third of the take, the person's hands beside it: it is
    found in the first frame (not the person's head or a leg, not the table) and trusted in every frame;
    no frame is a quarter turn off, and half its frames are within 5 degrees. (40 frames play the script at
    5x speed: the prediction, half the last frame's turn, lags a fast turn by up to 30 degrees.)"""
    adds, rotation = tracked(takes["carton"], tmp_path / "out")
    assert np.isfinite(adds).sum() >= 38, adds
    assert adds[0] < 10.0 and np.nanmedian(adds) < 10.0, adds
    assert np.nanmax(rotation) < 45.0 and np.nanmedian(rotation) < 5.0, rotation


@pytest.fixture(scope="module")
def cup_take(tmp_path_factory):
    """(session with masks, its raw copy: colour, depth and keypoints)."""
    root = tmp_path_factory.mktemp("raw_cup")
    given = generate_session(CUP, root / "given")
    shutil.copytree(given, root / "raw", ignore=shutil.ignore_patterns("masks"))
    return given, root / "raw"


def test_a_cup_in_a_hand_keeps_the_pixels_of_its_colour(cup_take):
    """Round the true pose of a cup held in one hand, the derived masks keep the cup's pixels near the palm
    by their colour (`object.colour_ratio`): over the frames in contact they hold at least half the true
    masks' pixels, and 0.85 of what they hold is the cup; with the colour test off (`object.colour_frames=0`)
    the pixels near the palm are all unknown and the masks keep less than half as much."""
    given, raw = cup_take
    with_masks, session = Session.load(given), Session.load(raw)
    truth = np.load(given / "ground_truth" / "object_poses.npz")
    contact = np.load(given / "ground_truth" / "contact.npy")
    recall, precision = {}, {}
    for colour_frames in (12, 0):
        cfg = load_config(overrides=[f"object.colour_frames={colour_frames}"]).object
        tracker = ObjectTracker(session, cfg, session.object.load_mesh())
        tracker.keypoints = SessionKeypoints(session)
        assert (tracker.colour_test() is None) == (colour_frames == 0)
        kept = shown = right = 0
        for frame in map(int, np.flatnonzero(contact)):
            obs = tracker.observe(frame, (truth["R"][frame], truth["t"][frame]))
            for c in range(session.num_cameras):
                cup = with_masks.read_mask(c, frame, "object")
                if cup.sum() >= 40:
                    mask = obs.mask[c] > 0.5
                    kept, shown, right = kept + (mask & cup).sum(), shown + cup.sum(), right + mask.sum()
        recall[colour_frames], precision[colour_frames] = kept / shown, kept / max(right, 1)
    assert recall[12] > 0.5 and recall[12] > 2 * recall[0] and precision[12] > 0.85, (recall, precision)


def test_a_cup_held_in_one_hand_is_tracked_upright(cup_take, tmp_path):
    """The raw cup take: the cup rests on the table, is lifted in one hand, carried through a turn and put
    back; it is trusted in nearly every frame, its ADD-S median is under 8 mm and it is tracked tipped over
    (45 degrees or more off upright) in at most 3 frames of 103 (it tipped over as the hand reached it and
    stayed so: the hand's pixels hid it, and each frame's prediction carried on the last frame's turn)."""
    adds, rotation = tracked(cup_take[1], tmp_path / "out")
    assert np.isfinite(adds).sum() >= 95, adds
    assert np.nanmedian(adds) < 8.0 and (rotation > 45.0).sum() <= 3, (adds, rotation)
