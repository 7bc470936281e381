"""`intercap run` on the imported real Azure Kinect recording (one capture of a room with a
mug on a desk, no person, no object mesh, no ground given): the raw path must end with
clear outcomes, never a crash. Cheap stages only: prepare, detect, and physics's skip."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from intercap.config import Config
from intercap.io.k4a import import_k4a
from intercap.pipeline import run_pipeline
from intercap.session import validate
from intercap.stages.physics import stage as physics
from intercap.stages.detect.stage import available_detectors

REC = Path(__file__).parents[2].parent / "shared" / "data" / "azure_kinect" / "recording.mkv"
pytestmark = pytest.mark.skipif(not REC.exists(), reason=f"real Azure Kinect recording absent ({REC})")


@pytest.fixture(scope="module")
def real_session(tmp_path_factory):
    out = tmp_path_factory.mktemp("k4a_real") / "session"
    import_k4a(out, [REC])
    return out


def test_imported_real_session_validates(real_session):
    session, problems = validate(real_session)
    assert session is not None and not [p for p in problems if p.fatal], problems
    assert session.camera_names == ["cam0"] and session.num_frames == 1 and session.object is None


@pytest.mark.skipif("mediapipe" not in available_detectors(), reason="MediaPipe detector not installed")
def test_prepare_and_detect_on_the_real_session(real_session, tmp_path):
    out = tmp_path / "out"
    cfg = Config()
    cfg.report.enabled = False
    metrics = run_pipeline(real_session, out, cfg, stages=["prepare", "detect"], progress=False)
    # the one view sees a desk and a wall head-on, no floor: no plane is passed off as the ground
    assert metrics["prepare"]["ground_source"] == "unavailable"
    assert not (out / "prepare" / "ground.json").exists()
    why = json.loads((out / "prepare" / "ground_unavailable.json").read_text())["error"]
    assert why.startswith("no floor in view") and "\n" not in why
    assert metrics["prepare"]["calibration_max_correction_mm"] is None  # one camera: nothing to cross-check
    # the detector ran on the one image and wrote OpenPose JSON (a person or none: both read the same way)
    assert metrics["detect"]["keypoints_detected"] == 1 and metrics["detect"]["written"] == 1
    keypoints = json.loads((out / "detect" / "cam0" / "keypoints" / "000000.json").read_text())
    assert "people" in keypoints
    # no body fitted (as the body stage finds here): physics says so instead of failing the run
    np.savez(out / "body_params.npz", model=np.array("anny"), transl=np.full((1, 3), np.nan), valid=np.zeros(1, bool))
    figures = physics.run(None, cfg, out, progress=False)
    assert figures["skipped"].startswith("no frame has a body fit")
