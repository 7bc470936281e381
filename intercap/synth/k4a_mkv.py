"""Synthetic Azure Kinect recordings: a small Matroska (EBML) writer laid out like the
Azure Kinect recorder's files (1 us timecodes, COLOR and DEPTH tracks stored as
V_MS/VFW/FOURCC with the MJPG / b16g / YUY2 four-character code, K4A_* tags, the
device calibration as the `calibration.json` attachment).

PyAV cannot write these (FFmpeg's Matroska muxer drops the raw video's fourcc), so
the importer's tests and benchmark write them here. Not a general muxer.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np


def _vint_size(n: int) -> bytes:
    for length in range(1, 9):
        if n < (1 << (7 * length)) - 1:
            return (n | (1 << (7 * length))).to_bytes(length, "big")
    raise ValueError("EBML element too large")


def _el(eid: int, payload: bytes) -> bytes:
    return eid.to_bytes((eid.bit_length() + 7) // 8, "big") + _vint_size(len(payload)) + payload


def _uint(eid: int, v: int) -> bytes:
    return _el(eid, int(v).to_bytes(max(1, (int(v).bit_length() + 7) // 8), "big"))


def _str(eid: int, s: str) -> bytes:
    return _el(eid, s.encode("utf-8"))


def _bmp_header(width: int, height: int, fourcc: str, bits: int) -> bytes:
    """BITMAPINFOHEADER (40 bytes) naming the codec by its four-character code."""
    return struct.pack("<IiiHHIIiiII", 40, width, height, 1, bits, int.from_bytes(fourcc.encode(), "little"),
                       width * height * bits // 8, 0, 0, 0, 0)


def _simple_tags(pairs: dict, track_uid: int | None = None) -> bytes:
    targets = _uint(0x68CA, 50) + (_uint(0x63C5, track_uid) if track_uid else b"")
    body = _el(0x63C0, targets)
    for k, v in pairs.items():
        body += _el(0x67C8, _str(0x45A3, k) + _str(0x4487, str(v)))
    return _el(0x7373, body)


def write_k4a_mkv(
    path,
    color_frames: list[bytes],
    depth_frames: list[np.ndarray] | None,
    timestamps_us,
    calibration: bytes | None,
    *,
    fps: float = 30.0,
    serial: str = "000000000000",
    start_offset_ns: int = 0,
    sync_mode: str = "STANDALONE",
    color_format: str = "MJPG",
    color_size: tuple[int, int] = (1280, 720),
    color_mode: str = "MJPG_720P",
    depth_mode: str = "NFOV_UNBINNED",
    depth_tag: str = "b16g",
    depth_delay_ns: int = 0,
) -> Path:
    """Write a recording: frame k's colour block at timestamps_us[k] (file time, us;
    device time = that + start_offset_ns) and its depth block depth_delay_ns later.
    depth_frames: (H, W) uint16 mm each, or None for a file without a DEPTH track;
    calibration None leaves the attachment out. depth_tag 'YUY2' writes little-endian
    depth as old recordings did."""
    path = Path(path)
    ts = [int(t) for t in timestamps_us]
    head = _el(0x1A45DFA3, _uint(0x4286, 1) + _uint(0x42F7, 1) + _uint(0x42F2, 4) + _uint(0x42F3, 8)
               + _str(0x4282, "matroska") + _uint(0x4287, 4) + _uint(0x4285, 2))
    info = _el(0x1549A966, _uint(0x2AD7B1, 1000) + _str(0x4D80, "intercap synth") + _str(0x5741, "intercap synth")
               + _str(0x7BA9, "Azure Kinect"))
    period_ns = int(round(1e9 / fps))
    cw, ch = color_size
    tracks = _el(0xAE, _uint(0xD7, 1) + _uint(0x73C5, 1001) + _uint(0x83, 1) + _uint(0x9C, 0)
                 + _str(0x86, "V_MS/VFW/FOURCC") + _el(0x63A2, _bmp_header(cw, ch, color_format[:4], 16))
                 + _str(0x536E, "COLOR") + _uint(0x23E383, period_ns) + _el(0xE0, _uint(0xB0, cw) + _uint(0xBA, ch)))
    tags = _simple_tags({"K4A_DEPTH_DELAY_NS": depth_delay_ns, "K4A_WIRED_SYNC_MODE": sync_mode,
                         "K4A_DEVICE_SERIAL_NUMBER": serial, "K4A_START_OFFSET_NS": start_offset_ns})
    tags += _simple_tags({"K4A_COLOR_MODE": color_mode}, 1001)
    if depth_frames is not None:
        dh, dw = depth_frames[0].shape
        tracks += _el(0xAE, _uint(0xD7, 2) + _uint(0x73C5, 1002) + _uint(0x83, 1) + _uint(0x9C, 0)
                      + _str(0x86, "V_MS/VFW/FOURCC") + _el(0x63A2, _bmp_header(dw, dh, depth_tag, 16))
                      + _str(0x536E, "DEPTH") + _uint(0x23E383, period_ns) + _el(0xE0, _uint(0xB0, dw) + _uint(0xBA, dh)))
        tags += _simple_tags({"K4A_DEPTH_MODE": depth_mode}, 1002)
    segment = info + _el(0x1654AE6B, tracks) + _el(0x1254C367, tags)
    if calibration is not None:
        segment += _el(0x1941A469, _el(0x61A7, _str(0x466E, "calibration.json") + _str(0x4660, "application/octet-stream")
                                             + _el(0x465C, calibration) + _uint(0x46AE, 4242)))
    dtype = ">u2" if depth_tag.lower() == "b16g" else "<u2"
    delay_us = int(depth_delay_ns // 1000)
    with open(path, "wb") as f:
        f.write(head)
        f.write((0x18538067).to_bytes(4, "big") + bytes([0x01, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF]))  # unknown size
        f.write(segment)
        for k, t in enumerate(ts):
            blocks = _el(0xA3, b"\x81" + struct.pack(">hB", 0, 0x80) + color_frames[k])
            if depth_frames is not None and depth_frames[k] is not None:
                data = np.ascontiguousarray(depth_frames[k], dtype=dtype).tobytes()
                blocks += _el(0xA3, b"\x82" + struct.pack(">hB", delay_us, 0x80) + data)
            f.write(_el(0x1F43B675, _uint(0xE7, t) + blocks))
    return path


def device_calibration_json(depth_params, color_params, R, t, depth_radius: float = 1.74) -> bytes:
    """An Azure Kinect `calibration.json` with the given 14 Brown-Conrady parameters
    (cx, cy, fx, fy, k1..k6, codx, cody, p2, p1; normalised) per camera and the colour
    camera's Rt (depth -> colour, metres)."""

    def cam(params, location, purpose, Rm, tv, radius, w, h):
        return {"Intrinsics": {"ModelParameterCount": 14, "ModelParameters": [float(v) for v in params],
                               "ModelType": "CALIBRATION_LensDistortionModelBrownConrady"},
                "Location": location, "Purpose": purpose, "MetricRadius": radius,
                "Rt": {"Rotation": [float(v) for v in np.asarray(Rm).reshape(-1)],
                       "Translation": [float(v) for v in np.asarray(tv).reshape(-1)]},
                "SensorHeight": h, "SensorWidth": w}

    data = {"CalibrationInformation": {"Cameras": [
        cam(depth_params, "CALIBRATION_CameraLocationD0", "CALIBRATION_CameraPurposeDepth", np.eye(3), np.zeros(3),
            depth_radius, 1024, 1024),
        cam(color_params, "CALIBRATION_CameraLocationPV0", "CALIBRATION_CameraPurposePhotoVideo", R, t, 0, 4096, 3072),
    ]}}
    return json.dumps(data).encode("utf-8")
