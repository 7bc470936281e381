"""Mesh overlays line up with the images: the sample's ground-truth meshes rendered through each
camera's calibration and lens distortion cover the session's person and object masks."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import SAMPLE_SESSION, trimmed_copy

from intercap.evaluation.overlays import OverlayRenderer, render_overlays, silhouette_iou
from intercap.session import Session


def _gt_meshes(session):
    gt = session.ground_truth()
    poses = np.tile(np.eye(4), (len(gt.object_R), 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = gt.object_R, gt.object_t
    return gt.body_vertices, gt.body_faces, poses


def _ious(session, renderer, frames):
    V, F, poses = _gt_meshes(session)
    body, obj = [], []
    for i in frames:
        renderer.set_frame(V[i], F, None, poses[i])
        for c in range(session.num_cameras):
            out = renderer.render(c)
            person, thing = session.read_mask(c, i, "person"), session.read_mask(c, i, "object")
            body.append((out.body, person))
            if thing.sum() > 20:  # the box can be hidden behind the person
                obj.append((out.object, thing))

    def pooled(pairs):  # IoU over all views and frames together
        return silhouette_iou(np.concatenate([a.ravel() for a, _ in pairs]), np.concatenate([b.ravel() for _, b in pairs]))

    return pooled(body), pooled(obj), [silhouette_iou(a, b) for a, b in body]


def test_ground_truth_silhouettes_match_the_masks():
    session = Session.load(SAMPLE_SESSION)
    frames = [0, 12, 20, 29]
    renderer = OverlayRenderer(session.cameras, session.object.load_mesh())
    try:
        body, obj, per_view = _ious(session, renderer, frames)
    finally:
        renderer.close()
    assert body > 0.9 and obj > 0.9, (body, obj)
    assert min(per_view) > 0.9, per_view

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
    assert res["video"] == "global_cam1.mp4"
    with av.open(str(out / "report" / res["video"])) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 5 and frames[0].shape[:2] == (288, 320)
    # the overlay tints the person: inside the mask the video frame differs from the colour image
    mask = session.read_mask("cam1", 0, "person")
    diff = np.abs(frames[0].astype(int) - session.read_color("cam1", 0).astype(int)).sum(-1)
    assert diff[mask].mean() > 3 * diff[~mask].mean()
    # a stage that has not run gives nothing, and no error
    assert render_overlays(session, out, "body", out / "report", progress=False) == {}
