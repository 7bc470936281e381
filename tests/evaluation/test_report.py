"""The HTML report: builds on a partial results folder (sections "not run") and on a full one made
from the sample's ground truth (every section, embedded figures, overlay links that resolve,
an evaluation of the ground truth against itself that reads zero)."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from conftest import SAMPLE_SESSION, trimmed_copy

from intercap.config import Config
from intercap.evaluation.report import write_report
from intercap.session import Session

SECTIONS = ("summary", "stages", "calibration", "overlays", "curves", "contact", "penetration", "motion", "physics",
            "evaluation")
FRAMES = 12  # the sample's contact starts at frame 10


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory):
    return trimmed_copy(SAMPLE_SESSION, tmp_path_factory.mktemp("report") / "session", FRAMES)


def _section(html: str, ident: str) -> str:
    m = re.search(rf'<section id="{ident}">(.*?)</section>', html, re.S)
    assert m, f"no section {ident}"
    return m.group(1)


def _cfg(every=7):
    cfg = Config()
    cfg.report.overlay_every = every
    return cfg


def results_from_ground_truth(session_dir, out):
    """A results folder whose stages all saved the ground truth (what a perfect run would write)."""
    gt = session_dir / "ground_truth"
    V, F = np.load(gt / "body_vertices.npy"), np.load(gt / "body_faces.npy")
    kp = np.load(gt / "keypoints3d.npy")
    poses = np.load(gt / "object_poses.npz")
    contact = np.load(gt / "contact.npy")
    T = len(V)
    for stage in ("body", "global"):
        (out / stage).mkdir(parents=True)
        np.save(out / stage / "body_vertices.npy", V)
        np.save(out / stage / "body_faces.npy", F)
        np.save(out / stage / "keypoints3d.npy", kp)
        np.savez(out / stage / "body_params.npz", valid=np.ones(T, bool))
    for stage in ("object", "global"):
        (out / stage).mkdir(parents=True, exist_ok=True)
        np.savez(out / stage / "object_poses.npz", R=poses["R"], t=poses["t"], valid=np.arange(T) != 3,
                 confidence=np.linspace(0.9, 0.6, T))
    for name in ("body_vertices.npy", "body_faces.npy", "keypoints3d.npy"):
        (out / name).write_bytes((out / "global" / name).read_bytes())
    np.savez(out / "object_poses.npz", R=poses["R"], t=poses["t"])
    np.save(out / "contact.npy", contact)
    # contact regions: stand-in ids (the 300 vertices nearest the object over the contact frames)
    centre = poses["t"][contact].mean(0)
    near = np.argsort(np.linalg.norm(V[contact].mean(0) - centre, axis=1))[:300]
    feet = np.argsort(V[0][:, 2])[:100]
    (out / "contact").mkdir()
    np.savez(out / "contact" / "contact.npz", contact=contact, method=np.array("annotated"),
             region_names=np.array(["hands", "left_foot"]), region_contact=np.c_[contact, np.zeros(T, bool)],
             region_distance_m=np.c_[np.where(contact, 0.0, 0.2), np.full(T, 0.5)],
             region_vertex_ids=np.r_[near, feet].astype(np.int32), region_sizes=np.array([300, 100], np.int32),
             rest_vertices=V[0].astype(np.float32))
    (out / "prepare").mkdir()
    (out / "prepare" / "calibration_check.json").write_text(json.dumps({"frames": [0], "warn_mm": 10.0, "flagged": [],
        "pairs": [{"cam_a": "cam0", "cam_b": "cam1", "icp_rmse_mm": 3.0, "correction_translation_mm": 0.4}]}))
    (out / "physics").mkdir()
    np.savez(out / "physics" / "physics.npz", frame_ids=np.arange(T), hand_force=np.ones((T, 2, 3)),
             foot_force=np.full((T, 2, 3), 200.0), residual_force=np.zeros((T, 3)), residual_torque=np.zeros((T, 3)),
             object_residual_force=np.zeros((T, 3)), valid=np.ones(T, bool), gravity=np.array([0.0, 0.0, -9.81]),
             body_mass_kg=np.array(70.0), object_mass_kg=np.array(1.2), flight_episodes=np.zeros((0, 2), int),
             flight_acceleration=np.zeros((0, 3)), flight_gravity_angle_deg=np.zeros(0))
    metrics = {s: {"seconds": 1.5, "seconds_per_frame": 0.1} for s in ("prepare", "object", "body", "contact", "global")}
    (out / "metrics.json").write_text(json.dumps(metrics))
    for s in metrics:
        (out / s / "DONE.json").write_text("{}")
    return out


def test_report_on_a_partial_results_folder(session_dir, tmp_path):
    out = tmp_path / "out"
    (out / "object").mkdir(parents=True)
    poses = np.load(session_dir / "ground_truth" / "object_poses.npz")
    np.savez(out / "object" / "object_poses.npz", R=poses["R"], t=poses["t"], valid=np.ones(FRAMES, bool),
             confidence=np.full(FRAMES, 0.8))
    path = write_report(out, session=session_dir, cfg=_cfg(), progress=False)
    html = path.read_text()
    for ident in SECTIONS:
        _section(html, ident)
    assert "not run" in _section(html, "calibration")
    assert "not run" in _section(html, "physics")
    assert "not run" in _section(html, "evaluation")
    assert "not run" in _section(html, "penetration")
    overlays = _section(html, "overlays")
    assert 'href="overlays/object/000000_cam0.jpg"' in overlays and "overlays/body/" not in overlays
    assert (out / "report" / "object_cam0.webm").is_file()  # the last stage that ran
    stages = _section(html, "stages")
    assert stages.count("not run") >= 5  # every stage but object (present, no DONE.json)

    # no session known at all: still a page, saying so
    bare = tmp_path / "bare"
    bare.mkdir()
    html = write_report(bare, progress=False).read_text()
    assert "session folder unknown" in _section(html, "summary")


def test_report_shows_the_refined_calibration(tmp_path):
    """When prepare refined the cameras' poses, the calibration section says so: each camera's
    correction and the check again with the refined poses."""
    out = tmp_path / "out"
    (out / "prepare").mkdir(parents=True)
    pair = {"cam_a": "cam0", "cam_b": "cam1", "correction_translation_mm": 24.2, "translation_sigma_mm": 1.5,
            "icp_rmse_mm": 3.1, "blocks": 400, "fitness": 0.6, "full_translation_mm": 30.0, "flagged": True}
    (out / "prepare" / "calibration_check.json").write_text(json.dumps({
        "frames": [0], "warn_mm": 6.0, "pairs": [pair], "flagged": [pair],
        "after_refinement": {"pairs": [{**pair, "correction_translation_mm": 3.7, "translation_sigma_mm": None,
                                        "flagged": False}], "flagged": []}}))
    (out / "prepare" / "calibration_refined.json").write_text(json.dumps({"cameras": [], "corrections": [
        {"name": "cam0", "moved_mm": 7.48, "turned_deg": 0.182}, {"name": "cam1", "moved_mm": 6.68, "turned_deg": 0.163}]}))
    calibration = _section(write_report(out, progress=False).read_text(), "calibration")
    assert "1 camera pair(s) disagree" in calibration and "were refined" in calibration
    assert "<td>7.48</td>" in calibration and "<td>3.7</td>" in calibration
    assert "no camera pair flagged after refining" in calibration
    # a few readable columns with units: the pair, the residual, the correction ± its sigma, a verdict
    first = re.search(r"<table[^>]*>(.*?)</table>", calibration, re.S).group(1)
    heads = re.findall(r"<th>([^<]*)</th>", first)
    assert heads == ["cameras", "residual (mm)", "correction (mm)", "verdict"], heads
    assert "<td>cam0 – cam1</td>" in first and "<td>24.2 ± 1.5</td>" in first and "disagrees" in first
    assert "<th>moved (mm)</th>" in calibration and "<th>turned (°)</th>" in calibration


def test_report_from_ground_truth(session_dir, tmp_path):
    out = results_from_ground_truth(session_dir, tmp_path / "out")
    path = write_report(out, session=session_dir, gt=session_dir, cfg=_cfg(), progress=False)
    html = path.read_text()
    assert "http://" not in html and "https://" not in html  # self-contained
    for ident in SECTIONS:
        if ident != "stages":  # detect and export did not run
            assert "not run" not in _section(html, ident), ident
    figures = re.findall(r'<img class="fig" alt="([^"]*)" src="data:image/png;base64,', html)
    for needed in ("keypoint reprojection", "Depth cloud", "object confidence", "Trusted", "Contact per frame",
                   "contact heat map", "penetration CDF", "Body: mean vertex acceleration", "Forces",
                   "Body error over time"):
        assert any(needed.lower() in f.lower() for f in figures), (needed, figures)
    links = re.findall(r'<a href="(overlays/[^"]+)"><img src="data:image/jpeg;base64,', html)
    assert len(links) == 3 * 2 * 4  # stages object, body, global x frames 0, 7 x 4 cameras
    assert "done" in _section(html, "stages")
    assert all((out / "report" / rel).is_file() for rel in links)
    assert (out / "report" / "global_cam0.webm").is_file()
    # the ground truth evaluated against itself
    rows = dict(re.findall(r'<tr><td title="(\w+)">[^<]*</td><td>([^<]*)</td>', _section(html, "evaluation")))
    assert float(rows["body_surface_mm"]) < 0.5 and float(rows["object_add_mm"]) < 1e-3
    assert float(rows["contact_accuracy_pct"]) == 100
    # perfect keypoints reproject onto the simulated detections within their noise (2-3 px)
    assert "keypoint reprojection" in html
    assert (out / "eval.json").is_file()


def test_cli_report(session_dir, tmp_path):
    from intercap.cli import main

    out = tmp_path / "out"
    (out / "prepare").mkdir(parents=True)
    (out / "run.json").write_text(json.dumps({"session": str(session_dir)}))
    (out / "config.yaml").write_text("report:\n  overlay_every: 5\n  video: false\nphysics:\n  no_such_key: 1\n")
    assert main(["report", str(out), "-q"]) == 0
    html = (out / "report" / "index.html").read_text()
    assert str(Session.load(session_dir).root) in _section(html, "summary")


def test_pipeline_writes_the_report_and_survives_its_failure(tiny_session, tmp_path, monkeypatch, caplog):
    from intercap.config import load_config
    from intercap.evaluation import report
    from intercap.pipeline import run_pipeline

    out = tmp_path / "out"
    run_pipeline(tiny_session, out, load_config(None, ["report.video=false"]), stages=["detect"], progress=False)
    assert "Stages and timings" in (out / "report" / "index.html").read_text()

    def broken(*args, **kwargs):
        raise RuntimeError("no GL")

    monkeypatch.setattr(report, "write_report", broken)
    metrics = run_pipeline(tiny_session, tmp_path / "out2", load_config(None, ["run.force=true"]), stages=["detect"],
                           progress=False)
    assert "detect" in metrics and "report not written" in caplog.text
    assert (tmp_path / "out2" / "detect" / "DONE.json").is_file()
    off = tmp_path / "out3"
    run_pipeline(tiny_session, off, load_config(None, ["report.enabled=false"]), stages=["detect"], progress=False)
    assert not (off / "report").exists()


def test_report_warns_when_the_joint_fit_left_the_keypoints(tmp_path):
    """A joint fit that raised the keypoints' energy six times (a thinned take still saying 30 fps)
    gets a warning in the motion section naming the frame rate; an ordinary one (x1.2) none."""
    for ratio, warned in ((6.2, True), (1.2, False)):
        out = tmp_path / f"out{ratio}"
        out.mkdir()
        (out / "metrics.json").write_text(json.dumps({"global": {"keypoint_energy_ratio": ratio}}))
        motion = _section(write_report(out, progress=False).read_text(), "motion")
        assert ("energy x6.2" in motion and "fps (30)" in motion) == warned, motion


def test_stage_figures_read_as_tables_with_units(tmp_path):
    """metrics.json's figures show as one small table per stage: a readable name, the value, the unit
    taken from the key (mm, px, %, % body weight, N, mm/s); no key=value dumps."""
    from intercap.evaluation.report import figure_name

    assert figure_name("penetration_mm_max") == ("penetration (max)", "mm")
    assert figure_name("residual_root_force_pct_bw_p95") == ("residual root force (p95)", "% body weight")
    assert figure_name("ground_reaction_mean_n") == ("ground reaction (mean)", "N")
    assert figure_name("foot_skating_mm_s") == ("foot skating", "mm/s")
    assert figure_name("frames_in_contact") == ("frames in contact", "")
    out = tmp_path / "out"
    (out / "body").mkdir(parents=True)
    (out / "body" / "DONE.json").write_text("{}")
    (out / "metrics.json").write_text(json.dumps({
        "body": {"seconds": 25.4, "seconds_per_frame": 0.85, "fit_to_data_mm_median": 12.7897, "frames_fitted": 30,
                 "reprojection_px_median": 1.46, "keypoints": "session", "repaired_frame_ids": []},
        "contact": {"method": "3d", "region_frames": {"left_hand": 14, "right_hand": 15}},
        "global": {"energy_before": {"body_keypoints": 100.0, "contact": 50.0},
                   "energy_after": {"body_keypoints": 110.0, "contact": 5.0}}}))
    stages = _section(write_report(out, progress=False).read_text(), "stages")
    assert "=" not in re.sub(r"<[^>]*>", "", stages)
    assert '<td>fit to data (median)</td><td>12.8</td><td class="unit">mm</td>' in stages
    assert '<td>reprojection (median)</td><td>1.46</td><td class="unit">px</td>' in stages
    assert "<td>frames fitted</td><td>30</td>" in stages and "repaired" not in stages  # empty lists left out
    assert "left hand 14\nright hand 15" in stages
    assert "<td>body keypoints</td><td>100</td><td>110</td><td>10</td>" in stages  # energy: before, after, change %
    assert "<th>time (s)</th>" in stages and "<td>25.4</td>" in stages


def test_report_uses_the_sessions_ground_truth(session_dir, tmp_path):
    """A session with ground_truth/ is evaluated without --gt; one without says how to give it."""
    import shutil

    out = results_from_ground_truth(session_dir, tmp_path / "out")
    cfg = _cfg()
    cfg.report.overlay_stages = []
    evaluation = _section(write_report(out, session=session_dir, cfg=cfg, progress=False).read_text(), "evaluation")
    rows = dict(re.findall(r'<tr><td title="(\w+)">[^<]*</td><td>([^<]*)</td>', evaluation))
    assert float(rows["body_surface_mm"]) < 0.5 and float(rows["contact_accuracy_pct"]) == 100
    bare = tmp_path / "bare_session"
    shutil.copytree(session_dir, bare, ignore=shutil.ignore_patterns("ground_truth"))
    (out / "eval.json").unlink()
    evaluation = _section(write_report(out, session=bare, cfg=cfg, progress=False).read_text(), "evaluation")
    assert "not run" in evaluation and "no ground_truth/ folder" in evaluation


def test_physics_plot_gives_each_force_its_own_colour(monkeypatch):
    """Every line of the forces plot has a colour of its own (the object residual once took the left
    foot's green)."""
    from matplotlib.colors import to_hex

    from intercap.evaluation import report

    drawn = []

    def record(fig, alt):
        drawn.append([to_hex(line.get_color()) for line in fig.axes[0].lines])
        return real(fig, alt)

    real = report.figure_html
    monkeypatch.setattr(report, "figure_html", record)
    T = 6
    physics = {"hand_force": np.ones((T, 2, 3)), "foot_force": np.ones((T, 2, 3)), "frame_ids": np.arange(T),
               "object_ground_force": np.ones((T, 3)), "residual_force": np.ones((T, 3)),
               "object_residual_force": np.ones((T, 3))}
    report.physics_section(physics, np.arange(T))
    assert len(drawn[0]) == 7 and len(set(drawn[0])) == 7, drawn
    colours = report.series_colours(["body", "global", "gt", "a", "b", "c", "d", "e", "f", "g", "h", "i", "j"])
    assert len(set(colours.values())) == 13, colours
