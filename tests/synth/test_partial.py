"""A cropped view sees the same scene through a smaller image: pixels, depth and keypoints move by
the box's corner, the intrinsics with them, and what leaves the box is not detected."""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SAMPLE_SESSION

from intercap.session import Session, validate
from intercap.synth.partial import crop_view

BOX = (40, 10, 200, 150)  # x0, y0, width, height of cam1's 320x288 image: the legs leave it


def test_crop_view_moves_pixels_intrinsics_and_keypoints(tmp_path):
    out = crop_view(SAMPLE_SESSION, tmp_path / "crop", "cam1", BOX)
    session, problems = validate(out)
    assert session is not None and not [p for p in problems if p.fatal], [str(p) for p in problems]
    old, new = Session.load(SAMPLE_SESSION), session
    x0, y0, w, h = BOX
    a, b = old.camera("cam1"), new.camera("cam1")
    assert (b.width, b.height) == (w, h)
    assert np.allclose(b.K, a.K - np.array([[0, 0, x0], [0, 0, y0], [0, 0, 0]]))
    assert np.array_equal(b.T_world_from_cam, a.T_world_from_cam) and np.array_equal(b.dist, a.dist)
    box = np.s_[y0:y0 + h, x0:x0 + w]
    assert np.array_equal(new.read_depth_millimetres("cam1", 3), old.read_depth_millimetres("cam1", 3)[box])
    assert np.array_equal(new.read_mask("cam1", 3, "person"), old.read_mask("cam1", 3, "person")[box])
    assert cv2.imread(str(out / "cam1" / "color" / "000003.jpg")).shape == (h, w, 3)
    other = Path("cam0") / "color" / "000003.jpg"
    assert (out / other).read_bytes() == (SAMPLE_SESSION / other).read_bytes()

    before = json.loads((SAMPLE_SESSION / "cam1" / "keypoints" / "000003.json").read_text())["people"][0]
    after = json.loads((out / "cam1" / "keypoints" / "000003.json").read_text())["people"][0]
    kp0 = np.reshape(before["pose_keypoints_2d"], (-1, 3))
    kp1 = np.reshape(after["pose_keypoints_2d"], (-1, 3))
    u, v = kp0[:, 0] - x0, kp0[:, 1] - y0
    inside = (kp0[:, 2] > 0) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    assert inside.any() and (~inside & (kp0[:, 2] > 0)).any()  # the box keeps some joints and loses others
    assert np.allclose(kp1[inside, :2], kp0[inside, :2] - [x0, y0]) and np.array_equal(kp1[inside, 2], kp0[inside, 2])
    assert not kp1[~inside].any()


def test_crop_view_refuses_a_box_outside_the_image(tmp_path):
    with pytest.raises(ValueError, match="inside"):
        crop_view(SAMPLE_SESSION, tmp_path / "a", "cam1", (200, 0, 200, 100))
    with pytest.raises(ValueError, match="no such camera"):
        crop_view(SAMPLE_SESSION, tmp_path / "b", "cam9", BOX)
