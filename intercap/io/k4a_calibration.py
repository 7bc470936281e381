"""Azure Kinect device calibration (the `calibration.json` a recording carries) and
depth-to-colour registration, without the Azure Kinect SDK.

Calibration semantics (as the SDK's calibration and transformation code define them):
- each camera's `Intrinsics.ModelParameters` holds 14 numbers in the order
  cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1 (note p2 before p1);
  cx, cy, fx, fy are normalised by the calibration image: scaled by the mode's
  (binned) calibration resolution, minus the mode's crop offset, minus 0.5 so that
  pixel centres sit at integer coordinates (OpenCV's convention, ours);
- the lens model is Brown-Conrady with a rational radial part, which is exactly
  OpenCV's rational model: dist = [k1, k2, p1, p2, k3, k4, k5, k6];
  codx, cody (a shifted centre of distortion) are zero in every calibration seen so
  far and have no OpenCV equivalent: non-zero values are refused rather than dropped;
- `Rt` maps depth-camera coordinates (the device origin, metres) to the camera's:
  x_cam = R x_depth + t (identity for the depth camera itself);
- `MetricRadius` bounds the normalised radius over which the lens model is valid
  (0 = unbounded); depth pixels beyond it are discarded.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

# mode name -> (calibration image binned resolution (w, h), crop offset (x, y), output resolution (w, h))
COLOR_MODES = {
    "720P": ((1280, 960), (0, 120), (1280, 720)),
    "1080P": ((1920, 1440), (0, 180), (1920, 1080)),
    "1440P": ((2560, 1920), (0, 240), (2560, 1440)),
    "1536P": ((2048, 1536), (0, 0), (2048, 1536)),
    "2160P": ((3840, 2880), (0, 360), (3840, 2160)),
    "3072P": ((4096, 3072), (0, 0), (4096, 3072)),
}
DEPTH_MODES = {
    "NFOV_2X2BINNED": ((512, 512), (96, 90), (320, 288)),
    "NFOV_UNBINNED": ((1024, 1024), (192, 180), (640, 576)),
    "WFOV_2X2BINNED": ((512, 512), (0, 0), (512, 512)),
    "WFOV_UNBINNED": ((1024, 1024), (0, 0), (1024, 1024)),
    "PASSIVE_IR": ((1024, 1024), (0, 0), (1024, 1024)),
}


class K4ACalibrationError(ValueError):
    """A device calibration that cannot be parsed or used (message names the file)."""


@dataclass
class Lens:
    """One camera of a device at its mode's resolution, OpenCV conventions.
    K (3, 3) pixels; dist (8,) k1, k2, p1, p2, k3, k4, k5, k6; metric_radius: normalised
    radius where the model stops being valid (inf = unbounded)."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    metric_radius: float = float("inf")

    def scaled(self, width: int, height: int) -> "Lens":
        """The same lens for an image resized to width x height (pixel centres kept:
        u' = (u + 0.5) s - 0.5)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Lens(K, self.dist.copy(), int(width), int(height), self.metric_radius)


@dataclass
class DeviceCalibration:
    depth: Lens
    color: Lens
    T_color_from_depth: np.ndarray  # (4, 4), metres


def _mode_key(mode: str, table: dict, what: str, source: str) -> str:
    key = str(mode).upper()
    for prefix in ("K4A_COLOR_RESOLUTION_", "K4A_DEPTH_MODE_", "MJPG_", "NV12_", "YUY2_", "BGRA32_", "BGRA_"):
        if key.startswith(prefix):
            key = key[len(prefix):]
    if key not in table:
        raise K4ACalibrationError(f"{source}: unknown {what} mode {mode!r} (known: {', '.join(table)})")
    return key


def lens_from_parameters(params, mode_info, metric_radius: float, source: str, purpose: str) -> Lens:
    """Brown-Conrady's 14 normalised parameters -> a Lens at the mode's resolution."""
    p = np.asarray(params, dtype=np.float64).reshape(-1)
    if p.size < 14:
        raise K4ACalibrationError(f"{source}: {purpose} camera has {p.size} model parameters, expected 14")
    (cal_w, cal_h), (crop_x, crop_y), (out_w, out_h) = mode_info
    cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1 = p[:14]
    if codx != 0 or cody != 0:
        # OpenCV's model has no shifted centre of distortion; dropping it would silently bias pixels.
        raise K4ACalibrationError(
            f"{source}: {purpose} camera has a non-zero centre of distortion (codx={codx}, cody={cody}), "
            "which OpenCV's lens model cannot represent"
        )
    K = np.array(
        [
            [fx * cal_w, 0.0, cx * cal_w - crop_x - 0.5],
            [0.0, fy * cal_h, cy * cal_h - crop_y - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = np.array([k1, k2, p1, p2, k3, k4, k5, k6], dtype=np.float64)
    radius = float(metric_radius) if metric_radius and metric_radius > 0 else float("inf")
    return Lens(K, dist, int(out_w), int(out_h), radius)


def parse_device_calibration(
    data, color_mode: str, depth_mode: str, source: str = "calibration.json"
) -> DeviceCalibration:
    """Device calibration (JSON text, bytes or the parsed dict) at the given colour
    resolution ("720P", "MJPG_720P", ...) and depth mode ("NFOV_UNBINNED", ...)."""
    if isinstance(data, (bytes, bytearray)):
        data = data.rstrip(b"\0").decode("utf-8", errors="replace")
    if isinstance(data, str):
        try:
            data = json.loads(data)
        except json.JSONDecodeError as exc:
            raise K4ACalibrationError(f"{source}: device calibration is not JSON ({exc})") from None
    try:
        cams = data["CalibrationInformation"]["Cameras"]
    except (KeyError, TypeError):
        raise K4ACalibrationError(f"{source}: no CalibrationInformation.Cameras in the device calibration") from None
    by_purpose = {}
    for cam in cams:
        by_purpose[str(cam.get("Purpose", ""))] = cam
    out = {}
    for purpose, key, table, mode in (
        ("depth", "CALIBRATION_CameraPurposeDepth", DEPTH_MODES, depth_mode),
        ("color", "CALIBRATION_CameraPurposePhotoVideo", COLOR_MODES, color_mode),
    ):
        if key not in by_purpose:
            raise K4ACalibrationError(f"{source}: device calibration has no {purpose} camera ({key})")
        cam = by_purpose[key]
        model = cam.get("Intrinsics", {}).get("ModelType", "")
        if "BrownConrady" not in model:
            raise K4ACalibrationError(f"{source}: {purpose} lens model {model!r} is not Brown-Conrady")
        info = table[_mode_key(mode, table, purpose, source)]
        lens = lens_from_parameters(
            cam["Intrinsics"]["ModelParameters"], info, cam.get("MetricRadius", 0.0), source, purpose
        )
        R = np.asarray(cam["Rt"]["Rotation"], dtype=np.float64).reshape(3, 3)
        t = np.asarray(cam["Rt"]["Translation"], dtype=np.float64).reshape(3)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        out[purpose] = (lens, T)
    # both Rt are depth -> camera; the depth camera's own is the identity in practice
    T_color_from_depth = out["color"][1] @ np.linalg.inv(out["depth"][1])
    return DeviceCalibration(out["depth"][0], out["color"][0], T_color_from_depth)


# ---------------------------------------------------------------- registration (numpy, float32)


def _distort_np(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV rational distortion of normalised coordinates (same model as geometry.cameras)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = (float(v) for v in d)
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xy2 = 2 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * xy2
    return xd, yd


def _undistort_np(xd: np.ndarray, yd: np.ndarray, d: np.ndarray, iterations: int = 20):
    """Invert `_distort_np` by Newton's method with the analytic 2x2 Jacobian (float64,
    the same model and derivative as geometry.cameras.distortion_jacobian, in numpy
    because a one-off pass over a full sensor is ~10x faster here than in torch)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = (float(v) for v in d)
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = num / den
        drad = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) - radial * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / den
        ex = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
        ey = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
        a = radial + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
        b = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
        c = radial + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
        det = a * c - b * b
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        dx = (c * ex - b * ey) / det
        dy = (a * ey - b * ex) / det
        x, y = x - dx, y - dy
        if np.nanmax(np.abs(dx) + np.abs(dy), initial=0.0) < 1e-14:
            break  # converged everywhere (Newton: a few steps inside the lens's valid range)
    return x, y


def undistorted_rays(lens: Lens, pixels: np.ndarray | None = None) -> np.ndarray:
    """(N, 2) undistorted normalised coordinates of `pixels` (N, 2), by default every
    pixel centre row-major; NaN where the inversion does not reproduce the pixel or
    beyond the lens's metric radius (the model is not valid there)."""
    if pixels is None:
        v, u = np.mgrid[0 : lens.height, 0 : lens.width]
        pixels = np.stack([u.reshape(-1), v.reshape(-1)], -1).astype(np.float64)
    K = lens.K
    yd = (pixels[:, 1] - K[1, 2]) / K[1, 1]
    xd = (pixels[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    x, y = _undistort_np(xd, yd, lens.dist)
    bx, by = _distort_np(x, y, lens.dist)
    bad = (np.maximum(np.abs(bx - xd) * K[0, 0], np.abs(by - yd) * K[1, 1]) > 1e-3) | (
        x * x + y * y > lens.metric_radius**2
    )
    bad |= ~(np.isfinite(x) & np.isfinite(y))
    rays = np.stack([x, y], -1)
    rays[bad] = np.nan
    return rays


def _max_radius2(lens: Lens) -> float:
    """Largest squared undistorted radius seen by the image (over its border pixels), with a
    margin: points beyond it cannot land in the image, and the rational model may fold
    them back into view if projected, so they are dropped before projection."""
    W, H = lens.width, lens.height
    u = np.arange(W, dtype=np.float64)
    v = np.arange(H, dtype=np.float64)
    border = np.concatenate(
        [np.stack([u, np.zeros_like(u)], -1), np.stack([u, np.full_like(u, H - 1)], -1),
         np.stack([np.zeros_like(v), v], -1), np.stack([np.full_like(v, W - 1), v], -1)]
    )
    rays = undistorted_rays(lens, border)
    r2 = (rays**2).sum(1)
    r2 = r2[np.isfinite(r2)]
    return float(r2.max() * 1.1**2) if r2.size else float("inf")


class DepthRegistration:
    """Depth maps of one device -> depth in the colour camera's geometry.

    Each valid depth pixel is back-projected through its undistorted ray, moved into
    the colour camera, projected with the colour lens's distortion and splatted onto
    the 2x2 colour pixels around its projection (the colour grid is denser than the
    depth grid over the shared field of view, so single-pixel splats would leave
    holes); a z-buffer keeps the nearest surface. Output: uint16 millimetres, 0 = none.
    """

    def __init__(self, depth: Lens, color: Lens, T_color_from_depth: np.ndarray):
        self.depth, self.color = depth, color
        rays = undistorted_rays(depth)  # (N, 2)
        R = np.asarray(T_color_from_depth, dtype=np.float64)[:3, :3]
        self.t = np.asarray(T_color_from_depth, dtype=np.float64)[:3, 3].astype(np.float32)
        ok = np.isfinite(rays).all(1)
        a = np.zeros((rays.shape[0], 3))
        a[ok] = np.concatenate([rays[ok], np.ones((ok.sum(), 1))], 1) @ R.T  # R applied to the ray (x, y, 1)
        self.ray_ok = ok
        # colour-frame point of depth pixel i at depth z: z * a_i + t (a: (N, 3), kept per axis for fast gathers)
        self.ax, self.ay, self.az = (np.ascontiguousarray(a[:, k], dtype=np.float32) for k in range(3))
        self.n_pixels = depth.height * depth.width
        self.color_r2max = np.float32(_max_radius2(color))

    def __call__(self, depth_mm: np.ndarray) -> np.ndarray:
        """(H, W) uint16 millimetres in the depth camera -> (Hc, Wc) uint16 in the colour camera."""
        if depth_mm.shape != (self.depth.height, self.depth.width):
            raise ValueError(
                f"depth map is {depth_mm.shape[1]}x{depth_mm.shape[0]}, calibration expects "
                f"{self.depth.width}x{self.depth.height}"
            )
        flat = depth_mm.reshape(-1)
        # every pixel at once (invalid ones masked at the end: cheaper than gathering the valid ones)
        z = flat.astype(np.float32) * np.float32(1e-3)  # (N,) metres
        X = self.ax * z + self.t[0]
        Y = self.ay * z + self.t[1]
        Z = self.az * z + self.t[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1 / Z
            x, y = X * inv, Y * inv
            ok = (flat > 0) & self.ray_ok & (Z > 1e-3) & (x * x + y * y < self.color_r2max)
        x, y, Z = x[ok], y[ok], Z[ok]  # (M,)
        xd, yd = _distort_np(x, y, self.color.dist)
        K = self.color.K
        u = np.float32(K[0, 0]) * xd + np.float32(K[0, 1]) * yd + np.float32(K[0, 2])
        v = np.float32(K[1, 1]) * yd + np.float32(K[1, 2])
        zmm = np.clip(np.rint(Z * 1000), 1, 65535).astype(np.uint16)
        return zbuffer_splat(u, v, zmm, self.color.width, self.color.height)


def zbuffer_splat(u: np.ndarray, v: np.ndarray, zmm: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-wins splat of points at sub-pixel (u, v) onto the 2x2 pixels around each:
    (M,) float, (M,) uint16 -> (height, width) uint16, 0 where nothing landed.
    The z-buffer is `np.minimum.at` (unbuffered, so repeated pixels keep the nearest;
    numpy >= 1.25 runs it at scatter speed, no sort needed)."""
    W, H = int(width), int(height)
    u0 = np.floor(u).astype(np.int32)
    v0 = np.floor(v).astype(np.int32)
    # a padded canvas (H+2, W+2) with the image at offset (1, 1): every footprint of a point
    # with -1 <= u0 < W, -1 <= v0 < H lies on it, so one mask suffices
    keep = (u0 >= -1) & (u0 < W) & (v0 >= -1) & (v0 < H)
    Wp = W + 2
    base = (v0[keep] + 1) * Wp + (u0[keep] + 1)  # (M',)
    z = zmm[keep]
    canvas = np.full((H + 2) * Wp, 65535, dtype=np.uint16)
    for off in (0, 1, Wp, Wp + 1):  # the 2x2 footprint
        np.minimum.at(canvas, base + off, z)
    canvas[canvas == 65535] = 0
    return canvas.reshape(H + 2, Wp)[1 : H + 1, 1 : W + 1].copy()
