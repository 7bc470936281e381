"""One Azure Kinect recording (.mkv) read with PyAV, without the Azure Kinect SDK: header,
tracks, tags, the `calibration.json` attachment, block timestamps, and the raw blocks
decoded to images. A small EBML walk checks that the file is complete (FFmpeg reads a
cut-off file quietly to where it ends).

Tracks: COLOR (MJPG, or raw NV12 / YUY2 / BGRA), DEPTH (`b16g`: 16-bit big-endian
millimetres; old recordings tag it `YUY2` and store it little-endian). Time: a block's
device timestamp is its pts + K4A_START_OFFSET_NS.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from intercap.io.k4a_calibration import COLOR_MODES, DeviceCalibration, parse_device_calibration

_DEPTH_BY_SIZE = {(640, 576): "NFOV_UNBINNED", (320, 288): "NFOV_2X2BINNED", (512, 512): "WFOV_2X2BINNED",
                  (1024, 1024): "WFOV_UNBINNED"}
_COLOR_BY_HEIGHT = {out[1]: name for name, (_, _, out) in COLOR_MODES.items()}


class K4AError(ValueError):
    """A recording that cannot be imported; the message names the file."""


class K4AMissingError(FileNotFoundError):
    """A recording or a part of it (track, attachment) that is absent; names the file."""


@dataclass
class Recording:
    """What one .mkv holds, read from its header (no frames decoded)."""

    path: Path
    serial: str
    sync_mode: str
    start_offset_ns: int
    depth_delay_ns: int
    fps: float
    color_index: int
    color_format: str  # MJPG, NV12, YUY2, BGRA
    color_size: tuple[int, int]  # (w, h)
    color_mode: str
    depth_index: int
    depth_big_endian: bool
    depth_size: tuple[int, int]
    depth_mode: str
    calibration: DeviceCalibration
    color_ts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (Nc,) device ns
    depth_ts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (Nd,) device ns


def _open(path: Path):
    import av

    if not path.is_file():
        raise K4AMissingError(f"{path}: recording not found")
    try:
        return av.open(str(path))
    except Exception as exc:  # av.error.* carry FFmpeg's reason
        raise K4AError(f"{path}: not a readable Matroska recording ({type(exc).__name__}: {exc})") from None


def _read_vint(f, keep_marker: bool) -> int | None:
    first = f.read(1)
    if not first:
        return None
    b = first[0]
    length = 1
    while length <= 8 and not b & (0x80 >> (length - 1)):
        length += 1
    if length > 8:
        return -2  # not EBML
    rest = f.read(length - 1)
    if len(rest) < length - 1:
        return None
    value = b if keep_marker else b & (0xFF >> length)
    for c in rest:
        value = (value << 8) | c
    if not keep_marker and value == (1 << (7 * length)) - 1:
        return -1  # unknown size
    return value


def check_complete(path: Path) -> None:
    """Walk the Matroska file's top-level elements (headers only, one seek per cluster) and
    raise when one runs past the end of the file: FFmpeg reads a cut-off file quietly to
    where it ends, which would make a truncated recording look like a short one."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        eid, n = _read_vint(f, True), _read_vint(f, False)
        if eid != 0x1A45DFA3 or n is None or n < 0:
            raise K4AError(f"{path}: not a Matroska file (no EBML header)")
        f.seek(n, 1)
        eid, n = _read_vint(f, True), _read_vint(f, False)
        if eid != 0x18538067 or n is None:
            raise K4AError(f"{path}: truncated or corrupt recording (no Matroska segment)")
        end = size if n == -1 else f.tell() + n
        if end > size:
            raise K4AError(f"{path}: truncated recording ({size} of {end} bytes present)")
        while f.tell() < end:
            eid, n = _read_vint(f, True), _read_vint(f, False)
            if eid is None or n is None:
                raise K4AError(f"{path}: truncated recording (cut inside an element header at byte {f.tell()})")
            if n == -1:
                return  # a live (unfinalised) cluster: sizes unknown from here on
            if f.tell() + n > end:
                raise K4AError(f"{path}: truncated recording (an element at byte {f.tell()} runs past the end)")
            f.seek(n, 1)


def _track(container, title: str):
    for s in container.streams:
        if s.type == "video" and str(s.metadata.get("title", "")).upper() == title:
            return s
    return None


def _tag(stream) -> str:
    cc = stream.codec_context
    return str(getattr(cc, "codec_tag", "") or "").strip().upper()


def open_recording(path) -> Recording:
    """Header, tracks and device calibration of one recording, plus the device
    timestamps of every colour and depth block (one demux pass, nothing decoded)."""
    path = Path(path)
    if not path.is_file():
        raise K4AMissingError(f"{path}: recording not found")
    check_complete(path)
    c = _open(path)
    try:
        meta = dict(c.metadata)
        color, depth = _track(c, "COLOR"), _track(c, "DEPTH")
        if depth is None:
            raise K4AMissingError(f"{path}: recording has no DEPTH track (record with a depth mode other than OFF)")
        if color is None:
            raise K4AMissingError(f"{path}: recording has no COLOR track (record with a colour resolution)")
        attach = [s for s in c.streams if s.type == "attachment" and str(getattr(s, "name", "")) == "calibration.json"]
        if not attach:
            raise K4AMissingError(f"{path}: recording has no calibration.json attachment (device calibration)")
        cfmt = _tag(color) or "MJPG"
        if cfmt == "BGRA" or cfmt.startswith("BGRA"):
            cfmt = "BGRA"
        if cfmt not in ("MJPG", "NV12", "YUY2", "BGRA"):
            raise K4AError(f"{path}: colour format {cfmt!r} not supported (MJPG, NV12, YUY2, BGRA)")
        csize = (int(color.codec_context.width), int(color.codec_context.height))
        dsize = (int(depth.codec_context.width), int(depth.codec_context.height))
        cmode = str(color.metadata.get("K4A_COLOR_MODE", "")) or _COLOR_BY_HEIGHT.get(csize[1], "")
        dmode = str(depth.metadata.get("K4A_DEPTH_MODE", "")) or _DEPTH_BY_SIZE.get(dsize, "")
        dtag = _tag(depth)
        if dtag not in ("B16G", "YUY2"):
            raise K4AError(f"{path}: depth track format {dtag!r} not supported (b16g, or YUY2 in old recordings)")
        rate = color.average_rate or color.guessed_rate
        fps = float(rate) if rate else 0.0
        # K4ACalibrationError (a ValueError) names the file and the attachment
        calib = parse_device_calibration(bytes(attach[0].data), cmode, dmode, source=f"{path}:calibration.json")
        rec = Recording(
            path=path,
            serial=str(meta.get("K4A_DEVICE_SERIAL_NUMBER", "")),
            sync_mode=str(meta.get("K4A_WIRED_SYNC_MODE", "")),
            start_offset_ns=int(meta.get("K4A_START_OFFSET_NS", 0) or 0),
            depth_delay_ns=int(meta.get("K4A_DEPTH_DELAY_NS", 0) or 0),
            fps=fps,
            color_index=color.index,
            color_format=cfmt,
            color_size=csize,
            color_mode=cmode,
            depth_index=depth.index,
            depth_big_endian=dtag == "B16G",
            depth_size=dsize,
            depth_mode=dmode,
            calibration=calib,
        )
        if calib.color.width != csize[0] or calib.depth.width != dsize[0]:
            raise K4AError(f"{path}: track sizes {csize}, {dsize} do not match the modes {cmode}, {dmode}")
        cts, dts = [], []
        for pkt in _packets(c, path, [color, depth]):
            (cts if pkt.stream.index == color.index else dts).append(_pts_ns(pkt))
        if not cts:
            raise K4AError(f"{path}: COLOR track has no frames")
        rec.color_ts = np.sort(np.asarray(cts, dtype=np.int64)) + rec.start_offset_ns
        rec.depth_ts = np.sort(np.asarray(dts, dtype=np.int64)) + rec.start_offset_ns
        if not rec.fps:
            d = np.diff(rec.color_ts)
            rec.fps = float(1e9 / np.median(d)) if d.size else 30.0
        return rec
    finally:
        c.close()


def _pts_ns(pkt) -> int:
    return int(round(pkt.pts * pkt.time_base * 1_000_000_000))


def _packets(container, path: Path, streams):
    """Demux with FFmpeg's errors turned into one-line errors naming the file; packets
    without a timestamp (stream end markers) are skipped; a short last block (a file cut
    off mid-frame) is reported as truncation."""
    it = container.demux(streams)
    while True:
        try:
            pkt = next(it)
        except StopIteration:
            return
        except Exception as exc:
            raise K4AError(f"{path}: truncated or corrupt recording ({type(exc).__name__}: {exc})") from None
        if pkt.pts is None or pkt.size == 0:
            continue
        yield pkt


def decode_color(rec: Recording, data: bytes) -> np.ndarray:
    """Raw colour block -> (h, w, 3) uint8 BGR (OpenCV order)."""
    import cv2

    w, h = rec.color_size
    buf = np.frombuffer(data, dtype=np.uint8)
    if rec.color_format == "MJPG":
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        if img is None:
            raise K4AError(f"{rec.path}: a COLOR frame is not a readable JPEG (truncated recording?)")
        return img
    need = {"NV12": w * h * 3 // 2, "YUY2": w * h * 2, "BGRA": w * h * 4}[rec.color_format]
    if buf.size < need:
        raise K4AError(f"{rec.path}: a COLOR frame has {buf.size} bytes, expected {need} (truncated recording?)")
    if rec.color_format == "NV12":
        return cv2.cvtColor(buf[:need].reshape(h * 3 // 2, w), cv2.COLOR_YUV2BGR_NV12)
    if rec.color_format == "YUY2":
        return cv2.cvtColor(buf[:need].reshape(h, w, 2), cv2.COLOR_YUV2BGR_YUY2)
    return np.ascontiguousarray(buf[:need].reshape(h, w, 4)[..., :3])


def decode_depth(rec: Recording, data: bytes) -> np.ndarray:
    """Raw depth block -> (h, w) uint16 millimetres in native byte order."""
    w, h = rec.depth_size
    if len(data) != w * h * 2:
        raise K4AError(f"{rec.path}: a DEPTH frame has {len(data)} bytes, expected {w * h * 2} (truncated recording?)")
    return np.frombuffer(data, dtype=">u2" if rec.depth_big_endian else "<u2").astype(np.uint16).reshape(h, w)


def frame_blocks(rec: Recording, wanted):
    """Yield (colour bytes, depth bytes or None) for `wanted` = [(colour pts, depth pts or None)]
    in time order, demuxing the file once; packets not wanted are dropped on the way."""
    c = _open(rec.path)
    try:
        pending: dict[tuple[int, int], bytes] = {}
        it = _packets(c, rec.path, [c.streams[rec.color_index], c.streams[rec.depth_index]])
        for cts, dts in wanted:
            need = [(rec.color_index, cts)] + ([(rec.depth_index, dts)] if dts is not None else [])
            while not all(k in pending for k in need):
                try:
                    pkt = next(it)
                except StopIteration:
                    raise K4AError(f"{rec.path}: recording ends before the frame at {cts / 1e9:.3f} s (truncated?)")
                key = (pkt.stream.index, _pts_ns(pkt) + rec.start_offset_ns)
                if key[1] >= min(cts, dts if dts is not None else cts):
                    pending[key] = bytes(pkt)
            yield pending.pop(need[0]), (pending.pop(need[1]) if len(need) > 1 else None)
            for k in [k for k in pending if k[1] <= cts]:
                del pending[k]
    finally:
        c.close()


