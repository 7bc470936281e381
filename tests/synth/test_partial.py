"""A view that sees part of the scene: outside a box of its image no colour, no depth, no mask and no
keypoint; inside it everything as captured, and the lens (intrinsics, image size) unchanged."""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SAMPLE_SESSION

from intercap.session import Session, validate
from intercap.synth.partial import crop_view

BOX = (40, 10, 200, 150)  # x0, y0, width, height of cam1's 320x288 image: the legs leave it


def test_crop_view_blanks_what_lies_outside_the_box_and_keeps_the_lens(tmp_path):
    out = crop_view(SAMPLE_SESSION, tmp_path / "crop", "cam1", BOX)
    session, problems = validate(out)
    assert session is not None and not [p for p in problems if p.fatal], [str(p) for p in problems]
    old, new = Session.load(SAMPLE_SESSION), session
    x0, y0, w, h = BOX
    a, b = old.camera("cam1"), new.camera("cam1")
    assert (b.width, b.height) == (a.width, a.height) and np.array_equal(b.K, a.K)
    assert np.array_equal(b.T_world_from_cam, a.T_world_from_cam) and np.array_equal(b.dist, a.dist)
    box = np.s_[y0:y0 + h, x0:x0 + w]
    outside = np.ones((a.height, a.width), bool)
    outside[box] = False
    depth_old, depth_new = old.read_depth_millimetres("cam1", 3), new.read_depth_millimetres("cam1", 3)
    assert np.array_equal(depth_new[box], depth_old[box]) and not depth_new[outside].any()
    assert depth_old[outside].any()
    mask_old, mask_new = old.read_mask("cam1", 3, "person"), new.read_mask("cam1", 3, "person")
    assert np.array_equal(mask_new[box], mask_old[box]) and not mask_new[outside].any()
    color = cv2.imread(str(out / "cam1" / "color" / "000003.jpg"))
    assert color.shape == (a.height, a.width, 3) and color[outside].max() < 16
    other = Path("cam0") / "color" / "000003.jpg"
    assert (out / other).read_bytes() == (SAMPLE_SESSION / other).read_bytes()

    before = json.loads((SAMPLE_SESSION / "cam1" / "keypoints" / "000003.json").read_text())["people"][0]
    after = json.loads((out / "cam1" / "keypoints" / "000003.json").read_text())["people"][0]
    kp0 = np.reshape(before["pose_keypoints_2d"], (-1, 3))
    kp1 = np.reshape(after["pose_keypoints_2d"], (-1, 3))
    u, v = kp0[:, 0] - x0, kp0[:, 1] - y0
    inside = (kp0[:, 2] > 0) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    assert inside.any() and (~inside & (kp0[:, 2] > 0)).any()  # the box keeps some joints and loses others
    assert np.array_equal(kp1[inside], kp0[inside])
    assert not kp1[~inside].any()


def test_crop_view_refuses_a_box_outside_the_image(tmp_path):
    with pytest.raises(ValueError, match="inside"):
        crop_view(SAMPLE_SESSION, tmp_path / "a", "cam1", (200, 0, 200, 100))
    with pytest.raises(ValueError, match="no such camera"):
        crop_view(SAMPLE_SESSION, tmp_path / "b", "cam9", BOX)
