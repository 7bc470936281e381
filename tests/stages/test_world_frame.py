"""Results do not depend on the world frame: the sample with camera 0 as the world (OpenCV axes,
y down, as BEHAVE / InterCap rigs write it) is fitted as well as in its z-up world, and the fits
agree once moved back."""
import numpy as np
from conftest import SAMPLE_SESSION, trimmed_copy

from intercap.config import load_config
from intercap.evaluation import evaluate
from intercap.pipeline import run_pipeline
from intercap.synth.reframe import camera_as_world


def test_body_fit_is_the_same_in_a_camera_as_world_frame(tmp_path):
    zup = trimmed_copy(SAMPLE_SESSION, tmp_path / "zup", 8)
    cam, T = camera_as_world(zup, tmp_path / "cam0")
    cfg = load_config(overrides=["prepare.save_clouds=false"])
    errors = {}
    vertices = {}
    for name, session in (("zup", zup), ("cam", cam)):
        out = tmp_path / f"out_{name}"
        run_pipeline(session, out, cfg, stages=["prepare", "body"], progress=False)
        errors[name] = evaluate(out, session).metrics
        vertices[name] = np.load(out / "body_vertices.npy")
    for key in ("body_surface_mm", "keypoint_mpjpe_mm"):
        a, b = errors["zup"][key], errors["cam"][key]
        assert b <= max(1.05 * a, a + 1.0), (key, a, b)
    assert errors["cam"]["body_surface_mm"] < 20.0
    back = (vertices["cam"] - T[:3, 3]) @ T[:3, :3]  # camera-as-world results moved to the z-up world
    gap_mm = 1000 * np.linalg.norm(back - vertices["zup"], axis=-1).mean()
    assert gap_mm < 10.0, gap_mm
