"""The viewer and the HTML report, opened the way a person does: in headless Chromium.

The results folder is the sample's ground truth copied into an OUT layout (no fitting), so
the viewer must show the ground-truth body exactly where the test projects it. Screenshots
stay in the test's tmp folder (and the report's in OUT/report/) for a person to open.
Chromium is Debian's `chromium` (setup.sh installs it); the browser tests skip without it.
"""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from cdp_browser import Browser, find_chromium
from conftest import SAMPLE_SESSION

CHROMIUM = find_chromium()
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (apt-get install chromium)")
CONTACT_FRAME = 15  # the sample carries the box in frames 11-23
FREE_FRAME = 3


def make_gt_results(out: Path) -> Path:
    """An OUT folder holding the sample's ground truth, as `intercap run` would lay it out."""
    gt = Path(SAMPLE_SESSION) / "ground_truth"
    out.mkdir(parents=True, exist_ok=True)
    for name in ("body_vertices.npy", "body_faces.npy", "object_poses.npz", "contact.npy", "keypoints3d.npy"):
        shutil.copy(gt / name, out / name)
    (out / "global").mkdir(exist_ok=True)  # the stage layout the report's overlays and video read
    for name in ("body_vertices.npy", "body_faces.npy", "object_poses.npz"):
        shutil.copy(gt / name, out / "global" / name)
    ground = json.loads((gt / "ground.json").read_text())
    (out / "prepare").mkdir(exist_ok=True)
    (out / "prepare" / "ground.json").write_text(json.dumps({**ground, "inlier_ratio": 1.0, "rmse_m": 0.0,
                                                             "source": "ground truth"}))
    (out / "run.json").write_text(json.dumps({"session": str(Path(SAMPLE_SESSION).resolve()), "stages": []}))
    # the report's tables as a full run fills them: every calibration column, long stage figures
    pair = {"overlap_points": 16771, "median_distance_mm": 6.274, "icp_rmse_mm": 9.661,
            "correction_rotation_deg": 0.1187, "correction_translation_mm": 1.945, "fitness": 0.5766, "unobservable": [], "full_translation_mm": 3.27,
            "full_rotation_deg": 0.2233, "translation_sigma_mm": 1.232, "rotation_sigma_deg": 0.06323,
            "observable_dof": 6, "significance": 2.505, "flagged": False, "blocks": 903, "judged": True, "frames": 3}
    cams = ["cam0", "cam1", "cam2", "cam3"]
    (out / "prepare" / "calibration_check.json").write_text(json.dumps({
        "frames": [0, 14, 29], "warn_mm": 6.0, "flagged": [], "unchecked_cameras": [],
        "pairs": [{"cam_a": a, "cam_b": b, **pair} for a, b in zip(cams, cams[1:] + cams[:1])]}))
    (out / "metrics.json").write_text(json.dumps({
        "prepare": {"ground_source": "ransac", "ground_rmse_mm": 7.13, "ground_inlier_ratio": 0.895, "seconds": 3.05},
        "global": {"contact_frames": 13, "penetration_mm_mean": 3.75, "jitter_mps2": 5.48,
                   "camera_time_offsets_ms": {c: 0.04 for c in cams}, "gravity_up": [0.0, 0.0, 1.0],
                   "energy_before": {"body_keypoints": 145300.0, "interpenetration": 347800.0},
                   "energy_after": {"body_keypoints": 147600.0, "interpenetration": 2914.0}, "seconds": 25.8},
        "physics": {"residual_root_force_pct_bw_mean": 6.92, "foot_skating_mm_s": 331.7,
                    "body_mass_source": "rest mesh volume x 1010 kg/m^3", "seconds": 0.67},
        "export": {"dataset": str(out / "export" / "sample.npz"), "glb_bytes": 5488292, "seconds": 0.09}}))
    T = len(np.load(gt / "contact.npy"))
    hand = np.zeros((T, 2, 3))
    hand[np.load(gt / "contact.npy"), :, 2] = 5.9  # half the box's weight per hand, upwards
    foot = np.zeros((T, 2, 3))
    foot[..., 2] = 350.0
    cop = np.zeros((T, 2, 3))
    (out / "physics").mkdir(exist_ok=True)
    np.savez(out / "physics" / "physics.npz", hand_force=hand, foot_force=foot, foot_cop=cop, frame_ids=np.arange(T),
             valid=np.ones(T, bool), gravity=np.array([0.0, 0.0, -9.81]), body_mass_kg=np.array(70.0),
             residual_force=np.zeros((T, 3)), residual_torque=np.zeros((T, 3)), object_residual_force=np.zeros((T, 3)),
             flight_episodes=np.zeros((0, 2), int), flight_acceleration=np.zeros((0, 3)),
             flight_gravity_angle_deg=np.zeros(0))
    return out


@pytest.fixture(scope="module")
def gt_out(tmp_path_factory) -> Path:
    return make_gt_results(tmp_path_factory.mktemp("gt_results") / "out")


@pytest.fixture(scope="module")
def viewer(gt_out):
    from intercap.evaluation.viewer import Viewer, load_view_data

    v = Viewer(load_view_data(gt_out))
    yield v
    v.stop()


def test_viewer_shows_each_frame_in_place(viewer, gt_out):
    """Stepping puts the ground-truth body and posed object of that frame in the scene; contact
    is tinted only in contact frames, on body vertices touching the box; stepping is fast."""
    gt = Path(SAMPLE_SESSION) / "ground_truth"
    verts = np.load(gt / "body_vertices.npy")
    poses = np.load(gt / "object_poses.npz")
    contact = np.load(gt / "contact.npy")
    assert viewer.first_frame_s < 3.0
    assert viewer.data.session_root.resolve() == Path(SAMPLE_SESSION).resolve()  # found through OUT/run.json
    for i in (FREE_FRAME, CONTACT_FRAME):
        viewer.set_frame(i)
        assert int(viewer.slider.value) == i
        np.testing.assert_allclose(viewer.body.vertices, verts[i], atol=1e-6)
        np.testing.assert_allclose(viewer.object.position, poses["t"][i], atol=1e-6)
        assert viewer.contact_mesh.visible == bool(contact[i])
    ids = viewer.source.contact_vertices(CONTACT_FRAME, verts[CONTACT_FRAME])
    obj = viewer.source._object_samples @ poses["R"][CONTACT_FRAME].T + poses["t"][CONTACT_FRAME]
    nearest = np.min(np.linalg.norm(verts[CONTACT_FRAME][ids, None] - obj[None], axis=2), axis=1)
    assert len(ids) > 20 and nearest.max() < 0.021  # hand vertices on the box
    assert viewer.arrows.visible  # physics.npz present: force arrows
    viewer.step(+1)
    assert viewer.index == CONTACT_FRAME + 1
    assert viewer.clouds_ready.wait(60), "depth clouds were never ready"
    assert viewer.cloud.visible and len(viewer.cloud.points) > 1000
    times = []
    for i in range(viewer.data.num_frames):
        start = time.perf_counter()
        viewer.set_frame(i)
        times.append(time.perf_counter() - start)
    print(f"viewer step: mean {1e3 * np.mean(times):.1f} ms, max {1e3 * np.max(times):.1f} ms")
    assert np.median(times) < 0.15  # target 0.1 s; slack for a loaded CI machine


def project_body(pose: dict, vertices: np.ndarray, faces: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool silhouette of the body as the browser's initial camera sees it."""
    position, look_at, up = (np.asarray(pose[k], float) for k in ("position", "look_at", "up"))
    forward = (look_at - position) / np.linalg.norm(look_at - position)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    rel = vertices - position
    z = rel @ forward
    f = (height / 2) / np.tan(pose["fov"] / 2)  # three.js: vertical field of view
    px = np.stack([width / 2 + f * (rel @ right) / z, height / 2 - f * (rel @ cam_up) / z], axis=1)
    mask = np.zeros((height, width), np.uint8)
    cv2.fillPoly(mask, list(np.round(px[faces]).astype(np.int32)), 1)
    return mask.astype(bool)


def magenta(image: np.ndarray) -> np.ndarray:
    """Pixels with the viewer's body hue (BODY_COLOR, shaded): red and blue well above green."""
    r, g, b = (image[..., k].astype(int) for k in range(3))
    return (r - g > 60) & (b - g > 40)


@needs_chromium
def test_viewer_renders_in_chromium(viewer, tmp_path):
    """The viser client renders the scene: no console errors, the body's colour where the body is."""
    width, height = 900, 620
    viewer.set_frame(CONTACT_FRAME)
    body = np.asarray(viewer.data.body_vertices[CONTACT_FRAME])
    silhouette = project_body(viewer.camera_pose, body, viewer.data.body_faces, width, height)
    inside = cv2.erode(silhouette.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    near = cv2.dilate(silhouette.astype(np.uint8), np.ones((25, 25), np.uint8)).astype(bool)
    shot = tmp_path / "viewer_frame15.png"
    start = time.time()
    with Browser(width, height) as browser:
        browser.open(viewer.url)
        print(f"viewer page loaded after {time.time() - start:.1f} s")
        assert browser.wait_for("document.querySelector('canvas') !== null", 30), "viser drew no canvas"
        assert browser.wait_for("document.body.innerText.includes('frame 15')", 30), "GUI never showed frame 15"
        # the client fades the canvas in (opacity 0 -> 1, advanced by rendered frames): wait, then shoot
        browser.wait_for("parseFloat(getComputedStyle(document.querySelector('canvas')).opacity) > 0.99", 20)
        deadline, found = time.time() + 45, None
        while time.time() < deadline:  # and again while the fade is not over (software WebGL is slow)
            image = cv2.imread(str(browser.screenshot(shot)))[..., ::-1]
            hit = magenta(image)
            found = (hit[inside].mean(), hit[near].sum() / max(hit.sum(), 1), hit.sum())
            print(f"screenshot after {time.time() - start:.1f} s: body colour on {found[0]:.0%} of the body")
            if found[0] > 0.5:
                break
        # the GUI drives the server: clicking "next" steps the timeline
        browser.evaluate("Array.from(document.querySelectorAll('button'))"
                         ".find(b => b.innerText.trim() === 'next').click()")
        stepped = browser.wait_for("document.body.innerText.includes('frame 16')", 20)
        print(f"stepped after {time.time() - start:.1f} s")
        errors = list(browser.errors)
    print(f"viewer screenshot {shot}: body colour on {found[0]:.0%} of the projected body, "
          f"{found[1]:.0%} of body-coloured pixels near it ({found[2]} px)")
    assert not errors, errors
    assert image.std() > 10, "blank screenshot"
    assert found[0] > 0.5, "the body's colour is missing where the body should be"
    assert found[1] > 0.9, "body-coloured pixels away from the body"
    assert stepped and viewer.index == CONTACT_FRAME + 1, "the 'next' button did not step the viewer"


@needs_chromium
def test_report_renders_in_chromium(gt_out, tmp_path):
    """OUT/report/index.html opens from disk with no console errors, nothing fetched from a network,
    every image decoded, nothing wider than the page; the session's own ground truth is evaluated
    without being named. Screenshots (the top, and the stages, calibration, physics and evaluation
    sections) are kept beside the report and in the test's tmp folder."""
    try:
        from intercap.evaluation.report import write_report
    except ImportError as exc:  # the report module is built alongside; until then nothing to open
        pytest.skip(f"intercap.evaluation.report not importable: {exc}")
    page = write_report(gt_out, progress=False)  # the session (OUT/run.json) has ground_truth/
    with Browser(1100, 1400) as browser:
        browser.open(page.resolve().as_uri())
        browser.pump(1.0)
        # the overlay video (VP9 WebM by default) decodes and plays in the page
        playable = browser.wait_for("(() => { const v = document.querySelector('video');"
                                    " return !!v && (v.readyState >= 2 || v.error !== null); })()", 20)
        browser.evaluate("document.querySelector('video').play().then(() => true, () => false)")
        browser.wait_for("document.querySelector('video').currentTime > 0", 10)
        video = browser.evaluate("(() => { const v = document.querySelector('video'); return {src: v.currentSrc,"
                                 " ready: v.readyState, duration: v.duration, error: v.error && v.error.code,"
                                 " time: v.currentTime, width: v.videoWidth}; })()")
        images = browser.evaluate("Array.from(document.images).map(i => [i.src.slice(0, 40), i.complete, "
                                  "i.naturalWidth])")
        resources = browser.evaluate("performance.getEntriesByType('resource').map(e => e.name)")
        text = browser.evaluate("document.body.innerText")
        shot = browser.screenshot(page.parent / "screenshot.png")
        too_wide = browser.evaluate("(() => { const w = document.documentElement.clientWidth;"
                                    " return Array.from(document.querySelectorAll('table, img, video'))"
                                    ".filter(e => e.getBoundingClientRect().right > w + 1)"
                                    ".map(e => e.outerHTML.slice(0, 120)); })()")
        widths = browser.evaluate("[document.documentElement.scrollWidth, document.documentElement.clientWidth]")
        sections = {}
        for ident in ("stages", "calibration", "physics", "evaluation"):
            browser.evaluate(f"document.getElementById('{ident}').scrollIntoView()")
            browser.pump(0.3)
            sections[ident] = browser.screenshot(page.parent / f"screenshot_{ident}.png")
            shutil.copy(sections[ident], tmp_path / f"report_{ident}.png")
        evaluation = browser.evaluate("document.getElementById('evaluation').innerText")
        errors = list(browser.errors)
    shutil.copy(shot, tmp_path / "report.png")
    print(f"report screenshots: {tmp_path / 'report.png'}, " + ", ".join(str(tmp_path / f"report_{i}.png")
                                                                        for i in sections))
    assert not too_wide and widths[0] <= widths[1], (widths, too_wide)
    assert "body surface" in evaluation and "not run" not in evaluation, evaluation[:300]
    for ident, path in sections.items():
        assert cv2.imread(str(path)).std() > 10, f"blank screenshot of {ident}"
    assert not errors, errors
    print(f"report video: {video}")
    assert playable and video["error"] is None and video["ready"] >= 2, video
    assert video["duration"] > 0 and video["time"] > 0 and video["width"] == 320, video
    assert images and all(ok and w > 0 for _, ok, w in images), images
    assert not [r for r in resources if r.startswith(("http:", "https:"))], resources
    assert "frame" in text.lower() and len(text) > 200
    image = cv2.imread(str(shot))
    assert image.std() > 10, "blank screenshot"


def test_view_data_without_recorded_session(gt_out, tmp_path):
    """Without OUT/run.json the viewer still shows the body and says what it cannot show;
    --session brings back the object; a missing folder is a one-line error."""
    from intercap.cli import build_parser
    from intercap.evaluation.viewer import ViewerError, load_view_data

    bare = tmp_path / "bare"
    shutil.copytree(gt_out, bare)
    (bare / "run.json").unlink()
    shutil.rmtree(bare / "report", ignore_errors=True)  # the report records the session too
    data = load_view_data(bare)
    assert data.body_vertices is not None and data.object_vertices is None and not data.cameras
    assert any("session unknown" in n for n in data.notes)
    data = load_view_data(bare, session=SAMPLE_SESSION)
    assert data.object_vertices is not None and len(data.cameras) == 4 and data.fps == 5
    with pytest.raises(ViewerError, match="no such results folder"):
        load_view_data(tmp_path / "nowhere")
    args = build_parser().parse_args(["view", str(bare), "--port", "8123", "--session", str(SAMPLE_SESSION)])
    assert (args.port, args.session) == (8123, str(SAMPLE_SESSION))
