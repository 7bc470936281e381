"""The temporal check reads a camera's lag from its keypoints' residuals along the motion: a rig's
cameras see 67 points moving as a person's limbs do (0.5-1.5 m/s), one camera a known time late."""
import numpy as np
import pytest
import torch
from conftest import SAMPLE_SESSION

from intercap.calib.time_offsets import camera_time_offsets
from intercap.geometry.cameras import Cameras, project
from intercap.session import Session

FPS = 30.0


def moving_points(t: np.ndarray) -> np.ndarray:
    """(T, 67, 3) world points of a person-sized cloud, each swinging on its own phase."""
    rng = np.random.default_rng(0)
    base = rng.uniform([-0.3, -0.2, 0.1], [0.3, 0.2, 1.7], (67, 3))
    amplitude = rng.uniform(0.05, 0.25, (67, 3))
    phase = rng.uniform(0, 2 * np.pi, (67, 3))
    return base + amplitude * np.sin(2 * np.pi * 0.8 * t[:, None, None] + phase)


@pytest.mark.parametrize("lag_ms", [0.0, 16.7, -8.0])
def test_a_late_camera_is_read_from_its_keypoints(lag_ms):
    cameras = Cameras.from_infos(Session.load(SAMPLE_SESSION).cameras)
    C, T = len(cameras), 90
    t = np.arange(T) / FPS
    lags = np.zeros(C)
    lags[2] = lag_ms / 1000
    rng = np.random.default_rng(1)
    observed = np.zeros((T, C, 67, 3))
    for c in range(C):
        pix, _ = project(torch.from_numpy(moving_points(t + lags[c]).reshape(1, -1, 3)).float(),
                         cameras.select([c]))
        observed[:, c, :, :2] = pix[0].numpy().reshape(T, 67, 2) + rng.normal(0, 1.0, (T, 67, 2))  # 1 px noise
        observed[:, c, :, 2] = 0.9
    frames = np.arange(1, T - 1)
    offsets = camera_time_offsets(moving_points(t), observed[frames], frames, cameras, FPS) * 1000
    expected = lags * 1000 - np.median(lags * 1000)
    assert np.abs(offsets - expected).max() < 1.0, (offsets, expected)


def test_the_warning_names_only_the_cameras_past_the_limit():
    from intercap.config import load_config
    from intercap.evaluation.report import unsynchronised_warning
    from intercap.evaluation.warnings import unsynchronised

    text = unsynchronised({"cam0": -0.4, "cam1": 0.3, "cam2": 10.2}, 4.0)
    assert text.startswith("cam2 +10 ms") and "cam0" not in text and "cam1" not in text
    assert unsynchronised({"cam0": -0.4, "cam2": 10.2}, 0.0) == ""  # 0 turns the check off
    cfg = load_config(None, [])
    assert "cam2 +10 ms" in unsynchronised_warning({"camera_time_offsets_ms": {"cam0": 0.1, "cam2": 10.2}}, cfg)
    assert unsynchronised_warning({"camera_time_offsets_ms": {"cam0": 0.1, "cam2": 1.2}}, cfg) == ""
