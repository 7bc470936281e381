"""The object stage on a raw-like take (depth, no masks): an object resting on a table is found and told
apart from the table, the person and the furniture.

A small `table_lift` session (4 views, 192x160, 40 frames over the whole script) is generated once for
the module, without masks; its keypoints are the generator's simulated detections (what the `detect`
stage would give), so the person can be left out of the searches.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from intercap.config import load_config
from intercap.evaluation.evaluate import evaluate
from intercap.pipeline import run_pipeline
from intercap.synth.generator import SynthConfig, generate_session

RAW = SynthConfig(script="table_lift", cameras=4, width=192, height=160, frames=40, masks=False, ik_iters=40,
                  quiet=True)


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
    no frame is a quarter turn off."""
    adds, rotation = tracked(takes["carton"], tmp_path / "out")
    assert np.isfinite(adds).sum() >= 38, adds
    assert adds[0] < 10.0 and np.nanmedian(adds) < 10.0, adds
    assert np.nanmax(rotation) < 20.0, rotation
