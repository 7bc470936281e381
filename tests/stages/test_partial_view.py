"""A view that sees only part of the person (a camera close in: the legs below its image) is
fitted as well as the full view: what leaves the image is neither a keypoint nor a depth point,
and body vertices outside the image are not asked to find data there."""
from conftest import SAMPLE_SESSION, trimmed_copy

from intercap.config import load_config
from intercap.evaluation import evaluate
from intercap.pipeline import run_pipeline
from intercap.synth.partial import crop_view


def test_body_fit_with_a_view_that_loses_the_legs(tmp_path):
    full = trimmed_copy(SAMPLE_SESSION, tmp_path / "full", 8)
    # cam1 sees the person in rows 71-206 of 288; its upper 150 rows keep head to thighs
    partial = crop_view(full, tmp_path / "partial", "cam1", (0, 0, 320, 150))
    cfg = load_config(overrides=["prepare.save_clouds=false"])
    errors = {}
    for name, session in (("full", full), ("partial", partial)):
        out = tmp_path / f"out_{name}"
        run_pipeline(session, out, cfg, stages=["prepare", "body"], progress=False)
        errors[name] = evaluate(out, session).metrics
    for key in ("body_surface_mm", "keypoint_mpjpe_mm"):
        a, b = errors["full"][key], errors["partial"][key]
        assert b <= max(1.15 * a, a + 1.5), (key, a, b)
    assert errors["partial"]["body_surface_mm"] < 20.0
