"""Camera maths against known truth: round trips, pinhole formula, OpenCV, gradients, depth."""
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from intercap.geometry.cameras import (
    Cameras,
    backproject,
    depth_to_point_grid,
    depth_to_points,
    distort,
    distortion_jacobian,
    pixel_rays,
    project,
    undistort,
)

W, H = 640, 576
K_KINECT = np.array([[504.0, 0.0, 321.5], [0.0, 503.2, 290.8], [0.0, 0.0, 1.0]])
DISTS = [
    [0.10, -0.05, 1e-3, -1e-3, 0.01],
    [0.12, -0.06, -8e-4, 1.2e-3, 0.008],
    [0.08, -0.04, 1.1e-3, 9e-4, 0.012],
]
# Azure-Kinect-like rational model (k1, k2, p1, p2, k3, k4, k5, k6) on a wider lens: with
# fx = 412 the 640 x 576 image spans about 75 x 68 degrees once undistorted.
K_WIDE = np.array([[412.0, 0.0, 319.2], [0.0, 411.5, 289.4], [0.0, 0.0, 1.0]])
RATIONAL_DISTS = [
    [0.5, -2.6, 1e-4, 1e-4, 1.5, 0.38, -2.4, 1.4],
    [0.52, -2.55, -1.2e-4, 8e-5, 1.45, 0.40, -2.35, 1.38],
    [0.48, -2.65, 9e-5, -1.1e-4, 1.55, 0.36, -2.45, 1.42],
]
UP = np.array([0.1, -0.98, 0.15]) / np.linalg.norm([0.1, -0.98, 0.15])  # world up, not an axis
TARGET = np.array([0.2, -0.1, 0.3])


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) T_world_from_cam of an OpenCV camera at `center` looking at `target`, upright."""
    z = target - center
    z /= np.linalg.norm(z)
    y = -(up - (up @ z) * z)  # image y points down
    y /= np.linalg.norm(y)
    x = np.cross(y, z)  # right-handed: x = y cross z
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = center
    return T


def ring_infos(dists=DISTS, radius=2.5, height=1.2, K0=K_KINECT):
    """Three camera records around TARGET (like intercap.session.CameraInfo)."""
    e1 = np.cross(UP, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(UP, e1)
    infos = []
    for i, d in enumerate(dists):
        a = 2 * np.pi * i / len(dists) + 0.3
        center = TARGET + radius * (np.cos(a) * e1 + np.sin(a) * e2) + height * UP
        K = K0.copy()
        K[0, 0] += 3 * i
        K[1, 2] -= 2 * i
        infos.append(
            SimpleNamespace(
                name=f"cam{i}", width=W, height=H, K=K, dist=np.array(d),
                T_world_from_cam=look_at(center, TARGET, UP),
            )
        )
    return infos


@pytest.fixture(scope="module")
def cams64():
    return Cameras.from_infos(ring_infos(), dtype=torch.float64)


def test_camera_frame_is_opencv_upright(cams64):
    # the target projects near the principal point, and "up" goes up in the image (smaller v)
    pix, depth = project(torch.tensor(np.stack([TARGET, TARGET + 0.3 * UP])), cams64)
    assert torch.all(depth > 0)
    assert torch.allclose(pix[:, 0], cams64.K[:, :2, 2], atol=1e-6)
    assert torch.all(pix[:, 1, 1] < pix[:, 0, 1] - 10)


def test_from_infos_pads_distortion_and_inverts_pose():
    infos = ring_infos(dists=[[0.1, -0.05], [], [0.1, -0.05, 1e-3, 1e-3, 0.01, 0.0, 0.0, 0.0]])
    cams = Cameras.from_infos(infos, dtype=torch.float64)
    assert cams.dist.shape == (3, 8)
    assert torch.equal(cams.dist[1], torch.zeros(8, dtype=torch.float64))
    assert cams.dist[0, 2:].abs().sum() == 0
    eye = cams.T_cam_from_world @ cams.T_world_from_cam
    assert torch.allclose(eye, torch.eye(4, dtype=torch.float64).expand(3, 4, 4), atol=1e-12)
    assert torch.allclose(cams.centers, torch.tensor(np.stack([i.T_world_from_cam[:3, 3] for i in infos])))
    assert torch.equal(cams.dist[2], torch.tensor([0.1, -0.05, 1e-3, 1e-3, 0.01, 0, 0, 0], dtype=torch.float64))
    rational = Cameras.from_infos(ring_infos(dists=RATIONAL_DISTS), dtype=torch.float64)
    assert torch.equal(rational.dist, torch.tensor(RATIONAL_DISTS, dtype=torch.float64))
    four = Cameras.from_infos(ring_infos(dists=[[0.1, -0.05, 1e-3, 2e-3]] * 3), dtype=torch.float64)
    assert torch.equal(four.dist[0], torch.tensor([0.1, -0.05, 1e-3, 2e-3, 0, 0, 0, 0], dtype=torch.float64))
    # OpenCV's 12/14-coefficient lists: zero thin-prism terms are fine, non-zero ones are not modelled
    ok = Cameras.from_infos(ring_infos(dists=[RATIONAL_DISTS[0] + [0.0] * 4] * 3), dtype=torch.float64)
    assert torch.equal(ok.dist, rational.dist[[0, 0, 0]])
    bad = ring_infos(dists=[RATIONAL_DISTS[0] + [0.0, 1e-3, 0.0, 0.0]] * 3)
    with pytest.raises(ValueError, match="cam0"):
        Cameras.from_infos(bad)


def points_in_view(cams, n=400, seed=0):
    """World points around the target, kept if every camera sees them inside its image."""
    rng = np.random.default_rng(seed)
    pts = torch.tensor(TARGET + rng.uniform(-0.9, 0.9, size=(n, 3)))
    pix, depth = project(pts, cams)
    inside = (depth > 0.3).all(0) & (pix[..., 0] >= 0).all(0) & (pix[..., 0] < W).all(0)
    inside &= (pix[..., 1] >= 0).all(0) & (pix[..., 1] < H).all(0)
    return pts[inside]


def test_project_backproject_round_trip(cams64):
    pts = points_in_view(cams64)  # (N, 3)
    assert len(pts) > 200
    pix, depth = project(pts, cams64)  # (C, N, 2), (C, N)
    back = backproject(pix, depth, cams64)  # (C, N, 3)
    err = (back - pts[None]).norm(dim=-1).max().item()
    print(f"project->backproject max error {err:.2e} m")
    assert err < 1e-5


def test_backproject_project_round_trip_full_image(cams64):
    g = torch.Generator().manual_seed(1)
    C, N = len(cams64), 2000
    pix = torch.rand(C, N, 2, generator=g, dtype=torch.float64) * torch.tensor([W - 1.0, H - 1.0], dtype=torch.float64)
    depth = 0.5 + 4.0 * torch.rand(C, N, generator=g, dtype=torch.float64)
    pts = backproject(pix, depth, cams64)
    pix2, depth2 = project(pts, cams64)
    err = (pix2 - pix).norm(dim=-1).max().item()
    print(f"backproject->project max error {err:.2e} px (float64)")
    assert err < 1e-4
    assert torch.allclose(depth2, depth, atol=1e-9)
    # float32 (the default dtype) stays well below a pixel
    cams32 = cams64.to(dtype=torch.float32)
    pix32, _ = project(backproject(pix.float(), depth.float(), cams32), cams32)
    err32 = (pix32.double() - pix).norm(dim=-1).max().item()
    print(f"backproject->project max error {err32:.2e} px (float32)")
    assert err32 < 5e-3


def test_undistort_inverts_distort_at_image_corners(cams64):
    corners = torch.tensor([[0.0, 0.0], [W - 1.0, 0], [0, H - 1.0], [W - 1.0, H - 1.0]], dtype=torch.float64)
    K = cams64.K
    xy = (corners[None] - K[:, None, :2, 2]) / torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None]  # (C, 4, 2)
    und = undistort(xy, cams64.dist)
    assert (distort(und, cams64.dist) - xy).abs().max() < 1e-10
    # distortion is not negligible here, so the test would see a missing undistortion
    assert (und - xy).abs().max() > 1e-2


def test_pinhole_without_distortion():
    infos = ring_infos(dists=[[], [], []])
    cams = Cameras.from_infos(infos, dtype=torch.float64)
    pts = points_in_view(cams)
    pix, depth = project(pts, cams)
    for c, info in enumerate(infos):
        T = np.linalg.inv(info.T_world_from_cam)
        p = pts.numpy() @ T[:3, :3].T + T[:3, 3]
        u = info.K[0, 0] * p[:, 0] / p[:, 2] + info.K[0, 2]
        v = info.K[1, 1] * p[:, 1] / p[:, 2] + info.K[1, 2]
        assert np.allclose(pix[c, :, 0].numpy(), u, atol=1e-9)
        assert np.allclose(pix[c, :, 1].numpy(), v, atol=1e-9)
        assert np.allclose(depth[c].numpy(), p[:, 2], atol=1e-12)


def test_distortion_matches_opencv(cams64):
    pts = points_in_view(cams64)
    pix, _ = project(pts, cams64)
    worst = 0.0
    for c, info in enumerate(ring_infos()):
        T = np.linalg.inv(info.T_world_from_cam)
        rvec, _ = cv2.Rodrigues(T[:3, :3])
        ref, _ = cv2.projectPoints(pts.numpy(), rvec, T[:3, 3], info.K, np.asarray(info.dist, dtype=np.float64))
        worst = max(worst, np.abs(ref[:, 0, :] - pix[c].numpy()).max())
    print(f"max difference to cv2.projectPoints {worst:.2e} px")
    assert worst < 1e-3


def test_gradients_flow_through_project_and_backproject(cams64):
    pts = points_in_view(cams64)[:4].clone().requires_grad_(True)
    dist = cams64.dist.clone().requires_grad_(True)
    K = cams64.K.clone().requires_grad_(True)

    def proj(p, d, k):
        cams = Cameras(k, d, cams64.T_world_from_cam, cams64.width, cams64.height, cams64.names)
        pix, depth = project(p, cams)
        return pix, depth

    assert torch.autograd.gradcheck(proj, (pts, dist, K))

    pix, depth = (t.detach().requires_grad_(True) for t in project(pts, cams64))

    def back(px, dp, d):
        cams = Cameras(cams64.K, d, cams64.T_world_from_cam, cams64.width, cams64.height, cams64.names)
        return backproject(px, dp, cams)

    assert torch.autograd.gradcheck(back, (pix, depth, dist))


def render_plane_depth(info, plane_point, plane_normal):
    """Analytic depth map (H, W) of an infinite plane, rays from OpenCV's own undistortion."""
    v, u = np.mgrid[0:H:2, 0:W:2].astype(np.float64)  # every 2nd pixel; the rest stay 0
    pix = np.stack([u.ravel(), v.ravel()], -1)[:, None, :]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    xy = cv2.undistortPoints(pix, info.K, np.asarray(info.dist, dtype=np.float64), R=None, P=None, criteria=crit)[:, 0]
    rays_cam = np.concatenate([xy, np.ones((len(xy), 1))], -1)  # (HW, 3), z = 1
    R, c = info.T_world_from_cam[:3, :3], info.T_world_from_cam[:3, 3]
    z = ((plane_point - c) @ plane_normal) / (rays_cam @ R.T @ plane_normal)
    z[~np.isfinite(z) | (z <= 0) | (z > 8.0)] = 0.0  # behind the camera / too far: no measurement
    depth = np.zeros((H, W))
    depth[::2, ::2] = z.reshape(depth[::2, ::2].shape)
    return depth


def test_depth_to_points_lies_on_rendered_plane(cams64):
    infos = ring_infos()
    n = UP + np.array([0.05, 0.0, -0.1])
    n /= np.linalg.norm(n)
    p0 = TARGET - 0.2 * UP
    depth = torch.tensor(np.stack([render_plane_depth(i, p0, n) for i in infos]))
    depth[:, 500:, :50] = 0.0  # a hole
    clouds = depth_to_points(depth, cams64, stride=2, min_depth=0.2, max_depth=8.0)
    rays = pixel_rays(cams64, H, W, stride=2)  # precomputed once per rig, reused per frame
    grid, valid = depth_to_point_grid(depth, cams64, stride=2, rays=rays)
    assert len(clouds) == 3 and grid.shape == (3, (H // 2) * (W // 2), 3)
    # only every 2nd pixel was rendered: stride 1 must drop the zeros and find the same points
    assert [len(p) for p in depth_to_points(depth, cams64, stride=1)] == [len(p) for p in clouds]
    for c in range(3):
        expected = int(((depth[c, ::2, ::2] > 0.2) & (depth[c, ::2, ::2] < 8.0)).sum())
        assert clouds[c].shape == (expected, 3) and expected > 0.3 * grid.shape[1]
        dist_to_plane = ((clouds[c].numpy() - p0) @ n)
        print(f"view {c}: {expected} points, max off-plane {np.abs(dist_to_plane).max():.2e} m")
        assert np.abs(dist_to_plane).max() < 1e-6
        assert torch.equal(grid[c][valid[c]], clouds[c])
    # with a wrong distortion the points leave the plane: the test can fail
    wrong = Cameras(
        cams64.K, torch.zeros_like(cams64.dist), cams64.T_world_from_cam, cams64.width, cams64.height, cams64.names
    )
    off = np.abs((depth_to_points(depth, wrong, stride=4)[0].numpy() - p0) @ n).max()
    assert off > 1e-3


def test_depth_size_mismatch_is_an_error(cams64):
    with pytest.raises(ValueError, match="depth"):
        depth_to_points(torch.zeros(3, H // 2, W // 2), cams64)


# --- OpenCV's rational 8-coefficient model (Azure Kinect calibrations) ---


@pytest.fixture(scope="module")
def rational64():
    return Cameras.from_infos(ring_infos(RATIONAL_DISTS, K0=K_WIDE), dtype=torch.float64)


def points_filling_images(cams, n=3000, seed=3):
    """World points whose projections cover each image up to its corners: (C, N, 3), pixels (C, N, 2).

    Built per camera from uniform pixels, undistorted by OpenCV (independent of our Newton),
    at random depths, so the whole field of view is exercised."""
    rng = np.random.default_rng(seed)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    pts, pixs = [], []
    for c in range(len(cams)):
        pix = rng.uniform([0, 0], [W - 1, H - 1], size=(n, 2))
        pix[:4] = [[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]]  # the corners, hardest for Newton
        K, d = cams.K[c].numpy(), cams.dist[c].numpy()
        xy = cv2.undistortPoints(pix[:, None], K, d, R=None, P=None, criteria=crit)[:, 0]
        z = rng.uniform(0.5, 4.5, size=n)
        p_cam = np.concatenate([xy * z[:, None], z[:, None]], -1)
        T = cams.T_world_from_cam[c].numpy()
        pts.append(p_cam @ T[:3, :3].T + T[:3, 3])
        pixs.append(pix)
    return torch.tensor(np.stack(pts)), torch.tensor(np.stack(pixs))


def test_rational_field_of_view_is_about_75_degrees(rational64):
    xy = torch.tensor([[[0.0, 289.4], [W - 1.0, 289.4]]], dtype=torch.float64).expand(3, -1, -1)
    K = rational64.K
    xn = (xy - K[:, None, :2, 2]) / torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None]
    und = undistort(xn, rational64.dist)
    fov = torch.rad2deg(torch.atan(und[..., 0].abs()).sum(-1))  # (C,) horizontal field of view
    assert torch.all((fov > 70) & (fov < 80)), fov


def test_rational_projection_matches_opencv(rational64):
    pts, _ = points_filling_images(rational64)  # (C, N, 3)
    pix, depth = project(pts, rational64)
    assert torch.all(depth > 0)
    worst, worst5 = 0.0, 0.0
    for c, info in enumerate(ring_infos(RATIONAL_DISTS, K0=K_WIDE)):
        T = np.linalg.inv(info.T_world_from_cam)
        rvec, _ = cv2.Rodrigues(T[:3, :3])
        d8 = np.asarray(info.dist, dtype=np.float64)
        assert d8.shape == (8,)
        ref, _ = cv2.projectPoints(pts[c].numpy(), rvec, T[:3, 3], info.K, d8)
        worst = max(worst, np.abs(ref[:, 0, :] - pix[c].numpy()).max())
        # dropping the denominator (k4..k6) moves pixels a lot: the test sees a missing rational term
        ref5, _ = cv2.projectPoints(pts[c].numpy(), rvec, T[:3, 3], info.K, d8[:5])
        worst5 = max(worst5, np.abs(ref5[:, 0, :] - pix[c].numpy()).max())
    print(f"rational model: max difference to cv2.projectPoints {worst:.2e} px")
    assert worst < 1e-3
    assert worst5 > 10.0


def test_rational_round_trips_over_the_image(rational64):
    pts, pix_cv = points_filling_images(rational64)
    pix, depth = project(pts, rational64)
    assert (pix - pix_cv).abs().max() < 1e-6  # OpenCV's undistortion, our distortion
    back = backproject(pix, depth, rational64)
    err3d = (back - pts).norm(dim=-1).max().item()
    g = torch.Generator().manual_seed(4)
    C, N = len(rational64), 4000
    pix0 = torch.rand(C, N, 2, generator=g, dtype=torch.float64) * torch.tensor([W - 1.0, H - 1.0], dtype=torch.float64)
    pix0[:, :4] = torch.tensor([[0.0, 0.0], [W - 1.0, 0], [0, H - 1.0], [W - 1.0, H - 1.0]], dtype=torch.float64)
    depth0 = 0.5 + 4.0 * torch.rand(C, N, generator=g, dtype=torch.float64)
    pix2, depth2 = project(backproject(pix0, depth0, rational64), rational64)
    err = (pix2 - pix0).norm(dim=-1).max().item()
    cams32 = rational64.to(dtype=torch.float32)
    pix32, _ = project(backproject(pix0.float(), depth0.float(), cams32), cams32)
    err32 = (pix32.double() - pix0).norm(dim=-1).max().item()
    print(f"rational: project->backproject {err3d:.2e} m, backproject->project {err:.2e} px (f64), {err32:.2e} px (f32)")
    assert err3d < 1e-6
    assert err < 1e-4
    assert torch.allclose(depth2, depth0, atol=1e-9)
    assert err32 < 5e-3


def test_rational_undistort_matches_opencv_at_corners(rational64):
    corners = np.array([[0.0, 0.0], [W - 1.0, 0], [0, H - 1.0], [W - 1.0, H - 1.0]])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    K = rational64.K
    xy = (torch.tensor(corners)[None] - K[:, None, :2, 2]) / torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None]
    und = undistort(xy, rational64.dist)  # (C, 4, 2)
    for c in range(3):
        ref = cv2.undistortPoints(corners[:, None], K[c].numpy(), rational64.dist[c].numpy(), criteria=crit)[:, 0]
        assert np.abs(und[c].numpy() - ref).max() < 1e-9
    assert (distort(und, rational64.dist) - xy).abs().max() < 1e-12


def test_distortion_jacobian_matches_autograd(rational64):
    g = torch.Generator().manual_seed(5)
    xy = (torch.rand(3, 50, 2, generator=g, dtype=torch.float64) * 2 - 1).requires_grad_(True)  # |x|,|y| < 1
    out = distort(xy, rational64.dist)
    rows = [torch.autograd.grad(out[..., i].sum(), xy, retain_graph=True)[0] for i in range(2)]  # each (C, N, 2)
    assert torch.allclose(distortion_jacobian(xy.detach(), rational64.dist), torch.stack(rows, -2), atol=1e-12)


def test_five_coefficients_are_the_polynomial_model(cams64):
    # zero k4..k6: exactly OpenCV's 5-coefficient formula
    g = torch.Generator().manual_seed(6)
    xy = torch.rand(3, 100, 2, generator=g, dtype=torch.float64) - 0.5
    k1, k2, p1, p2, k3 = (torch.tensor(DISTS, dtype=torch.float64)[:, i, None] for i in range(5))
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    ref = torch.stack([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                       y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], -1)
    assert (distort(xy, cams64.dist) - ref).abs().max() < 1e-14  # rounding only (values ~0.5)


def test_rational_gradients(rational64):
    pts_all, _ = points_filling_images(rational64, n=8)
    pts = pts_all[0, :4].clone().requires_grad_(True)  # includes image corners of view 0
    dist = rational64.dist.clone().requires_grad_(True)
    K = rational64.K.clone().requires_grad_(True)
    base = rational64

    def proj(p, d, k):
        return project(p, Cameras(k, d, base.T_world_from_cam, base.width, base.height, base.names))

    assert torch.autograd.gradcheck(proj, (pts, dist, K))
    pix, depth = (t.detach().requires_grad_(True) for t in project(pts, rational64))

    def back(px, dp, d, k):
        return backproject(px, dp, Cameras(k, d, base.T_world_from_cam, base.width, base.height, base.names))

    assert torch.autograd.gradcheck(back, (pix, depth, dist, K))
