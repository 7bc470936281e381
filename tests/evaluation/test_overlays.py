"""Mesh overlays line up with the images: the sample's ground-truth meshes rendered through each
camera's calibration and lens distortion cover the session's person and object masks."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import SAMPLE_SESSION, trimmed_copy

from intercap.evaluation.overlays import OverlayRenderer, StageMeshes, render_overlays, silhouette_scores
from intercap.session import Session


def _gt_meshes(session, shift=(0.0, 0.0, 0.0)) -> StageMeshes:
    gt = session.ground_truth()
    return StageMeshes("gt", gt.body_vertices + np.asarray(shift, np.float32), gt.body_faces, gt.object_R, gt.object_t)


def _ious(session, renderer, frames, shift=(0.0, 0.0, 0.0)):
    scores = silhouette_scores(session, _gt_meshes(session, shift), frames, renderer)
    per_view = scores.body_inter / scores.body_union
    assert (scores.object_union > 0).sum() >= len(frames)  # the box is scored where visible (hidden: -1)
    return scores.body_iou, scores.object_iou, per_view.ravel()


def test_ground_truth_silhouettes_match_the_masks():
    """The overlay target (IoU > 0.9 with the masks) holds for the ground-truth meshes: in every view
    of the frames checked, and pooled; a body 2 cm off loses it, so the figure can fail."""
    session = Session.load(SAMPLE_SESSION)
    frames = [0, 12, 20, 29]
    renderer = OverlayRenderer(session.cameras, session.object.load_mesh())
    try:
        body, obj, per_view = _ious(session, renderer, frames)
        body_off, obj_same, _ = _ious(session, renderer, frames, shift=(0.02, 0.0, 0.0))
    finally:
        renderer.close()
    assert body > 0.99 and obj > 0.99, (body, obj)
    assert min(per_view) > 0.98, per_view
    assert body_off < 0.9 and body_off < body - 0.05, body_off  # 2 cm is ~1.7 px at 3 m: IoU is that sharp

    # the lens model matters: without the distortion the same meshes land off the masks
    flat = [dataclasses.replace(c, dist=np.zeros(5)) for c in session.cameras]
    renderer = OverlayRenderer(flat, session.object.load_mesh())
    try:
        body_flat, obj_flat, _ = _ious(session, renderer, frames)
    finally:
        renderer.close()
    assert body_flat < body - 0.01 and obj_flat < obj - 0.01, (body_flat, body, obj_flat, obj)


def test_render_overlays_writes_images_and_a_video(tmp_path):
    av = pytest.importorskip("av")
    session_dir = trimmed_copy(SAMPLE_SESSION, tmp_path / "session", 5)
    session = Session.load(session_dir)
    out = tmp_path / "out"
    (out / "global").mkdir(parents=True)
    gt = session_dir / "ground_truth"
    np.save(out / "global" / "body_vertices.npy", np.load(gt / "body_vertices.npy"))
    np.save(out / "global" / "body_faces.npy", np.load(gt / "body_faces.npy"))
    poses = np.load(gt / "object_poses.npz")
    np.savez(out / "global" / "object_poses.npz", R=poses["R"], t=poses["t"])

    res = render_overlays(session, out, "global", out / "report", every=2, alpha=0.5, video_camera="cam1",
                          progress=False)
    assert sorted({f for f, _, _ in res["images"]}) == [0, 2, 4]
    assert len(res["images"]) == 3 * session.num_cameras
    for _, _, rel in res["images"]:
        assert (out / "report" / rel).stat().st_size > 1000
    assert res["video"] == "global_cam1.webm"
    assert res["iou"]["body"] > 0.99 and res["iou"]["object"] > 0.99, res["iou"]  # the drawn frames, vs the masks
    with av.open(str(out / "report" / res["video"])) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 5 and frames[0].shape[:2] == (288, 320)
    # the overlay tints the person: inside the mask the video frame differs from the colour image
    mask = session.read_mask("cam1", 0, "person")
    diff = np.abs(frames[0].astype(int) - session.read_color("cam1", 0).astype(int)).sum(-1)
    assert diff[mask].mean() > 3 * diff[~mask].mean()
    # a stage that has not run gives nothing, and no error
    assert render_overlays(session, out, "body", out / "report", progress=False) == {}
