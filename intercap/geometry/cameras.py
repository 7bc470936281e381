"""Batched camera maths in torch (OpenCV conventions).

Camera frame: x right, y down, z forward (OpenCV). Pixel centres sit at integer
coordinates, so pixel (u, v) of a depth map is the ray through (u, v).
Distortion is OpenCV's rational model with eight coefficients
(k1, k2, p1, p2, k3, k4, k5, k6), the one Azure Kinect calibrations use, applied
to normalised coordinates (x/z, y/z) before the intrinsics:
    r2 = x^2 + y^2
    radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
With k4 = k5 = k6 = 0 the denominator is exactly 1, so 4- and 5-coefficient
calibrations give bit-for-bit the results of the plain polynomial model.

Everything is batched over cameras: a tensor's leading dimension C indexes the
camera, in the order of `Cameras.names`. All functions are differentiable with
respect to points, depth and camera parameters.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

N_DIST = 8  # k1, k2, p1, p2, k3, k4, k5, k6 (OpenCV order)


@dataclass
class Cameras:
    """C calibrated cameras as stacked tensors.

    K: (C, 3, 3) intrinsics; dist: (C, 8) k1, k2, p1, p2, k3, k4, k5, k6
    (zero-padded, see `padded_distortion`);
    T_world_from_cam: (C, 4, 4) camera-to-world rigid transforms;
    width, height: (C,) int64 image sizes in pixels; names: C camera names.
    """

    K: torch.Tensor
    dist: torch.Tensor
    T_world_from_cam: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor
    names: list[str] = field(default_factory=list)

    @classmethod
    def from_infos(cls, infos, device="cpu", dtype=torch.float32) -> "Cameras":
        """Stack per-camera records (objects with .name .width .height .K .dist
        .T_world_from_cam as numpy, e.g. `intercap.session.CameraInfo`)."""
        infos = list(infos)
        if not infos:
            raise ValueError("Cameras.from_infos: no cameras given")
        names = [str(info.name) for info in infos]
        K = np.stack([_checked_matrix(info.K, (3, 3), "K", info.name) for info in infos])
        T = np.stack(
            [_checked_matrix(info.T_world_from_cam, (4, 4), "T_world_from_cam", info.name) for info in infos]
        )
        dist = np.stack([padded_distortion(info.dist, info.name) for info in infos])
        width = np.array([int(info.width) for info in infos], dtype=np.int64)
        height = np.array([int(info.height) for info in infos], dtype=np.int64)
        return cls(
            K=torch.as_tensor(K, dtype=dtype, device=device),
            dist=torch.as_tensor(dist, dtype=dtype, device=device),
            T_world_from_cam=torch.as_tensor(T, dtype=dtype, device=device),
            width=torch.as_tensor(width, device=device),
            height=torch.as_tensor(height, device=device),
            names=names,
        )

    def __len__(self) -> int:
        return self.K.shape[0]

    @property
    def T_cam_from_world(self) -> torch.Tensor:
        """(C, 4, 4) world-to-camera transforms (rigid inverse, no matrix solve)."""
        return rigid_inverse(self.T_world_from_cam)

    @property
    def centers(self) -> torch.Tensor:
        """(C, 3) camera centres in world coordinates."""
        return self.T_world_from_cam[:, :3, 3]

    def to(self, device=None, dtype=None) -> "Cameras":
        """A copy on another device and/or floating dtype (sizes stay int64)."""
        floats = {k: getattr(self, k).to(device=device, dtype=dtype) for k in ("K", "dist", "T_world_from_cam")}
        return Cameras(
            **floats,
            width=self.width.to(device=device),
            height=self.height.to(device=device),
            names=list(self.names),
        )

    def select(self, indices) -> "Cameras":
        """The cameras at `indices` (a list of ints), in that order."""
        idx = torch.as_tensor(list(indices), dtype=torch.long, device=self.K.device)
        return Cameras(
            K=self.K[idx],
            dist=self.dist[idx],
            T_world_from_cam=self.T_world_from_cam[idx],
            width=self.width[idx],
            height=self.height[idx],
            names=[self.names[i] for i in idx.tolist()],
        )


def _checked_matrix(value, shape, what, name) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"camera {name!r}: {what} has shape {arr.shape}, expected {shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"camera {name!r}: {what} contains non-finite values")
    return arr


def padded_distortion(dist, name="?") -> np.ndarray:
    """(8,) k1, k2, p1, p2, k3, k4, k5, k6 from an OpenCV coefficient list
    (0, 4, 5 or 8 numbers in practice; any length up to 8 is zero-padded).
    OpenCV's longer lists (12 or 14: thin-prism and tilt terms) are accepted only
    if those extra terms are zero, since we do not model them."""
    d = np.zeros(N_DIST, dtype=np.float64)
    given = np.asarray([] if dist is None else dist, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(given)):
        raise ValueError(f"camera {name!r}: dist contains non-finite values")
    if given.size > N_DIST:
        if np.any(given[N_DIST:] != 0):
            raise ValueError(
                f"camera {name!r}: dist has {given.size} coefficients with non-zero terms beyond "
                "k1,k2,p1,p2,k3,k4,k5,k6 (thin-prism/tilt); only OpenCV's rational 8-coefficient "
                "model is supported"
            )
        given = given[:N_DIST]
    d[: given.size] = given
    return d


def rigid_inverse(T: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) inverse of rigid transforms: [R^T, -R^T t]."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    top = torch.cat([Rt, -Rt @ t], dim=-1)  # (..., 3, 4)
    bottom = torch.zeros_like(T[..., 3:, :])
    bottom[..., 3] = 1
    return torch.cat([top, bottom], dim=-2)


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply (C, 4, 4) transforms to (C, N, 3) or (N, 3) points -> (C, N, 3)."""
    if points.dim() == 2:
        points = points.unsqueeze(0).expand(T.shape[0], -1, -1)
    R = T[:, :3, :3]  # (C, 3, 3)
    t = T[:, :3, 3]  # (C, 3)
    return torch.einsum("cij,cnj->cni", R, points) + t[:, None, :]


def world_to_camera(points: torch.Tensor, T_cam_from_world: torch.Tensor) -> torch.Tensor:
    """World points (C, N, 3) or (N, 3, shared by all views) -> camera frame (C, N, 3)."""
    return transform_points(T_cam_from_world, points)


def _radial_factor(r2: torch.Tensor, dist: torch.Tensor,
                   derivative: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Rational radial factor and its derivative in r2: r2 (C, N), dist (C, 8) -> 2 x (C, N).

    radial = n / d with n = 1 + k1 r2 + k2 r2^2 + k3 r2^3, d = 1 + k4 r2 + k5 r2^2 + k6 r2^3;
    d radial / d r2 = (n' - radial d') / d. With k4..k6 = 0 both reduce exactly to the
    polynomial model (division by 1, subtraction of 0). Without `derivative` (None in its place)
    it issues 15 kernels fewer: `distort` runs in every body evaluation's keypoint projection.
    """
    k1, k2, k3, k4, k5, k6 = (dist[:, i, None] for i in (0, 1, 4, 5, 6, 7))  # each (C, 1)
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    if not derivative:
        return radial, None
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    return radial, (dnum - radial * dden) / den


def distort(xy: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """OpenCV rational distortion of normalised coordinates: (C, N, 2), dist (C, 8) -> (C, N, 2).

    Coordinate by coordinate (`unbind`), x^2, y^2 and 2 x y made once: 85 kernels forward and
    backward where picking each coordinate apart took 99. On (C, N, 2) tensors whole it takes 67, but
    the CPU runs their size-2 innermost axis at half the speed (every body and object evaluation
    projects)."""
    p1, p2 = dist[:, 2, None], dist[:, 3, None]  # each (C, 1)
    x, y = xy.unbind(-1)  # (C, N)
    xx, yy, xy2 = x * x, y * y, 2 * x * y
    r2 = xx + yy
    radial, _ = _radial_factor(r2, dist, derivative=False)
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2 * xx)
    yd = y * radial + p1 * (r2 + 2 * yy) + p2 * xy2
    return torch.stack([xd, yd], dim=-1)


def distortion_jacobian(xy: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """d distort / d xy, analytic: (C, N, 2), dist (C, 8) -> (C, N, 2, 2)."""
    p1, p2 = dist[:, 2, None], dist[:, 3, None]
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial, dradial_dr2 = _radial_factor(r2, dist)
    dxx = radial + 2 * x * x * dradial_dr2 + 2 * p1 * y + 6 * p2 * x
    dxy = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
    dyx = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
    dyy = radial + 2 * y * y * dradial_dr2 + 6 * p1 * y + 2 * p2 * x
    return torch.stack([torch.stack([dxx, dxy], -1), torch.stack([dyx, dyy], -1)], -2)


def _newton_step(xy: torch.Tensor, target: torch.Tensor, dist: torch.Tensor, jac_grad: bool) -> torch.Tensor:
    """One Newton step of distort(xy) = target, solving the 2x2 system in closed form."""
    J = distortion_jacobian(xy, dist)
    if not jac_grad:
        J = J.detach()
    r = distort(xy, dist) - target  # (C, N, 2)
    a, b, c, d = J[..., 0, 0], J[..., 0, 1], J[..., 1, 0], J[..., 1, 1]
    det = a * d - b * c
    det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
    dx = (d * r[..., 0] - b * r[..., 1]) / det
    dy = (-c * r[..., 0] + a * r[..., 1]) / det
    return xy - torch.stack([dx, dy], dim=-1)


def undistort(xy_distorted: torch.Tensor, dist: torch.Tensor, iterations: int = 20) -> torch.Tensor:
    """Invert `distort` by Newton's method: (C, N, 2), dist (C, 8) -> (C, N, 2).

    Starts from the distorted coordinates, which is close for the moderate
    distortion of real lenses inside their field of view (where r -> r * radial
    is monotonic, as calibrations guarantee over the image).

    The iterations run without autograd; one last Newton step with the Jacobian
    held fixed carries the gradient, which at convergence equals the implicit
    function gradient (J^-1 for the input, -J^-1 df/d dist for the coefficients).
    """
    with torch.no_grad():
        target = xy_distorted.detach()
        xy = target.clone()
        d = dist.detach()
        tol = 4 * torch.finfo(xy.dtype).eps
        for _ in range(iterations):
            new = _newton_step(xy, target, d, jac_grad=True)
            converged = bool(((new - xy).abs() <= tol * (1 + xy.abs())).all()) if xy.numel() else True
            xy = new
            if converged:
                break
    return _newton_step(xy, xy_distorted, dist, jac_grad=False)


def _apply_intrinsics(xy: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Normalised (C, N, 2) -> pixels (C, N, 2) with K (C, 3, 3) (skew kept)."""
    x, y = xy.unbind(-1)
    u = K[:, 0, 0, None] * x + K[:, 0, 1, None] * y + K[:, 0, 2, None]
    v = K[:, 1, 1, None] * y + K[:, 1, 2, None]
    return torch.stack([u, v], dim=-1)


def remove_intrinsics(pixels: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pixels (C, N, 2) -> normalised distorted coordinates (C, N, 2)."""
    y = (pixels[..., 1] - K[:, 1, 2, None]) / K[:, 1, 1, None]
    x = (pixels[..., 0] - K[:, 0, 2, None] - K[:, 0, 1, None] * y) / K[:, 0, 0, None]
    return torch.stack([x, y], dim=-1)


def project(points_world: torch.Tensor, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (N, 3) or (C, N, 3) -> pixels (C, N, 2), depth z (C, N) in metres.

    Points at or behind a camera (z <= 0) give meaningless pixels; mask them
    with `depth > 0`.
    """
    p_cam = world_to_camera(points_world, cameras.T_cam_from_world)  # (C, N, 3)
    z = p_cam[..., 2]
    xy = p_cam[..., :2] / z[..., None]
    pixels = _apply_intrinsics(distort(xy, cameras.dist), cameras.K)
    return pixels, z


def backproject(pixels: torch.Tensor, depth: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """Pixels (C, N, 2) with depth z (C, N) in metres -> world points (C, N, 3).

    Inverse of `project`: depth is the z coordinate in the camera frame (what a
    depth camera stores), not the distance along the ray.
    """
    xy = undistort(remove_intrinsics(pixels, cameras.K), cameras.dist)  # (C, N, 2)
    p_cam = torch.cat([xy * depth[..., None], depth[..., None]], dim=-1)  # (C, N, 3)
    return transform_points(cameras.T_world_from_cam, p_cam)


def pixel_grid(height: int, width: int, stride: int = 1, device=None, dtype=torch.float32) -> torch.Tensor:
    """(N, 2) pixel coordinates (u, v) of every `stride`-th pixel, row-major."""
    v, u = torch.meshgrid(
        torch.arange(0, height, stride, device=device, dtype=dtype),
        torch.arange(0, width, stride, device=device, dtype=dtype),
        indexing="ij",
    )
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)


def pixel_rays(cameras: Cameras, height: int, width: int, stride: int = 1) -> torch.Tensor:
    """Undistorted normalised coordinates (x/z, y/z) of every `stride`-th pixel:
    (C, N, 2), row-major. The same for every frame, so compute once and pass to
    `depth_to_point_grid(..., rays=)` to skip the undistortion per frame."""
    pix = pixel_grid(height, width, stride, device=cameras.K.device, dtype=cameras.K.dtype)  # (N, 2)
    pix = pix.unsqueeze(0).expand(len(cameras), -1, -1)
    return undistort(remove_intrinsics(pix, cameras.K), cameras.dist)


def depth_to_point_grid(
    depth: torch.Tensor,
    cameras: Cameras,
    stride: int = 1,
    min_depth: float = 0.2,
    max_depth: float = 8.0,
    rays: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth maps (C, H, W) in metres -> world points (C, N, 3) and valid mask (C, N).

    N = ceil(H/stride) * ceil(W/stride), pixels in row-major order. A pixel is
    valid when min_depth < depth < max_depth and finite (0 = no measurement);
    invalid pixels still get a (meaningless) point, use the mask. `rays`:
    optional precomputed `pixel_rays(cameras, H, W, stride)`.
    """
    if depth.dim() != 3 or depth.shape[0] != len(cameras):
        raise ValueError(f"depth must be (C={len(cameras)}, H, W), got {tuple(depth.shape)}")
    C, H, W = depth.shape
    if bool((cameras.height != H).any()) or bool((cameras.width != W).any()):
        raise ValueError(
            f"depth maps are {W}x{H} but the cameras are "
            f"{list(zip(cameras.width.tolist(), cameras.height.tolist()))} (width x height)"
        )
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    depth = depth.to(cameras.K.dtype)
    d = depth[:, ::stride, ::stride].reshape(C, -1)  # (C, N)
    if rays is None:
        rays = pixel_rays(cameras, H, W, stride)  # (C, N, 2)
    elif rays.shape != (C, d.shape[1], 2):
        raise ValueError(f"rays must be (C, N, 2) = {(C, d.shape[1], 2)} for stride {stride}, got {tuple(rays.shape)}")
    valid = torch.isfinite(d) & (d > min_depth) & (d < max_depth)
    z = torch.where(valid, d, torch.ones_like(d))  # (C, N)
    p_cam = torch.cat([rays * z[..., None], z[..., None]], dim=-1)  # (C, N, 3)
    return transform_points(cameras.T_world_from_cam, p_cam), valid


def depth_to_points(
    depth: torch.Tensor,
    cameras: Cameras,
    stride: int = 1,
    min_depth: float = 0.2,
    max_depth: float = 8.0,
    rays: torch.Tensor | None = None,
) -> list[torch.Tensor]:
    """Depth maps (C, H, W) in metres -> list of C world point tensors (N_c, 3).

    Only valid pixels (min_depth < depth < max_depth) are kept, so the lists are
    ragged; `depth_to_point_grid` gives the padded (C, N, 3) tensor and mask.
    """
    points, valid = depth_to_point_grid(depth, cameras, stride, min_depth, max_depth, rays)
    return [points[c][valid[c]] for c in range(points.shape[0])]
