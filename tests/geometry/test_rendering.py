"""The differentiable renderer against known truth: pyrender (OpenGL) images of the
same mesh and camera, cv2-remapped for lens distortion, central finite differences,
one-at-a-time rendering for batching, and the empty / out-of-view cases."""
import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
import trimesh

from intercap.geometry.cameras import Cameras
from intercap.geometry.rendering import (
    MeshTopology,
    crop_in_image,
    crop_observation,
    full_image_crops,
    object_crops,
    render,
)

W, H = 320, 256
K0 = np.array([[262.0, 0.0, 158.3], [0.0, 263.5, 129.6], [0.0, 0.0, 1.0]])
SMALL_DIST = [-0.12, 0.05, 8e-4, -6e-4, -0.01]  # k1 k2 p1 p2 k3: a mild barrel lens
LENS_DIST = [-0.25, 0.1, 1e-3, -8e-4, -0.02]  # a stronger one, a few pixels at the object
OBJECT_CENTER = np.array([0.02, -0.01, 0.85])


def look_at(center, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) T_world_from_cam, OpenCV axes (x right, y down, z forward), world z up."""
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = center
    return T


def make_cameras(dist=(), dtype=torch.float32) -> Cameras:
    """Two cameras about 1 m from the object, from different sides and heights."""
    centres = [np.array([0.25, -1.0, 1.45]), np.array([-0.9, 0.45, 1.1])]
    infos = []
    for i, c in enumerate(centres):
        K = K0.copy()
        K[0, 0] += 7 * i
        K[1, 2] += 3 * i
        infos.append(SimpleNamespace(name=f"cam{i}", width=W, height=H, K=K, dist=list(dist),
                                     T_world_from_cam=look_at(c, OBJECT_CENTER)))
    return Cameras.from_infos(infos, dtype=dtype)


def posed(mesh: trimesh.Trimesh, angle=0.5, axis=(1.0, 0.4, 0.3), offset=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    m = mesh.copy()
    m.apply_transform(trimesh.transformations.rotation_matrix(angle, np.asarray(axis) / np.linalg.norm(axis)))
    m.apply_translation(OBJECT_CENTER + np.asarray(offset))
    return m


MESHES = {
    "box": lambda: trimesh.creation.box(extents=(0.30, 0.20, 0.15)),
    "cylinder": lambda: trimesh.creation.cylinder(radius=0.07, height=0.22, sections=48),
}


def axis_angle_matrix(r: torch.Tensor) -> torch.Tensor:
    """(3,) -> (3, 3) Rodrigues rotation, differentiable (r not near 0 in these tests)."""
    theta = r.norm()
    k = r / theta
    Kx = torch.zeros(3, 3, dtype=r.dtype)
    Kx[0, 1], Kx[0, 2], Kx[1, 0], Kx[1, 2], Kx[2, 0], Kx[2, 1] = -k[2], k[1], k[2], -k[0], -k[1], k[0]
    return torch.eye(3, dtype=r.dtype) + torch.sin(theta) * Kx + (1 - torch.cos(theta)) * (Kx @ Kx)


# ----------------------------------------------------------------------------- pyrender reference


@pytest.fixture(scope="module")
def gl():
    """An offscreen pyrender renderer and the sub-pixel point it samples (see gl_offset)."""
    pyrender = pytest.importorskip("pyrender")
    try:
        renderer = pyrender.OffscreenRenderer(W, H)
    except Exception as exc:  # no EGL / GPU driver on this machine
        pytest.skip(f"pyrender offscreen rendering unavailable: {exc}")
    state = SimpleNamespace(pyrender=pyrender, renderer=renderer, offset=(0.0, 0.0))
    state.offset = gl_offset(state)
    yield state
    renderer.delete()


def gl_depth(gl, mesh: trimesh.Trimesh, K: np.ndarray, T_world_from_cam: np.ndarray,
             offset=None, scale: int = 1) -> np.ndarray:
    """pyrender depth (H, W) * scale, camera z in metres, 0 = background, in OpenCV pixel
    convention (scale > 1: the same camera supersampled, pixel u of the base image
    spanning pixels scale*u .. scale*u + scale - 1).

    OpenGL samples pixel (i, j) at window point (i + 0.5, j + 0.5) (rows counted from
    the bottom), so the OpenCV principal point moves by half a pixel; `offset` further
    corrects the point the driver actually samples (with multisampling, depth comes
    from one sample that is not the pixel centre)."""
    pr = gl.pyrender
    dx, dy = gl.offset if offset is None else offset
    Ks = K * np.array([[scale], [scale], [1.0]])
    Ks[:2, 2] += (scale - 1) / 2  # base pixel centre u -> scale * u + (scale - 1) / 2
    scene = pr.Scene()
    scene.add(pr.Mesh.from_trimesh(mesh))
    cam = pr.IntrinsicsCamera(Ks[0, 0], Ks[1, 1], Ks[0, 2] + 0.5 + dx, Ks[1, 2] + 0.5 + dy, znear=0.05, zfar=20.0)
    scene.add(cam, pose=T_world_from_cam @ np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenCV -> OpenGL camera axes
    gl.renderer.viewport_width, gl.renderer.viewport_height = W * scale, H * scale
    return gl.renderer.render(scene, flags=pr.RenderFlags.DEPTH_ONLY)


def gl_offset(gl) -> tuple[float, float]:
    """Where, relative to the pixel centre, this OpenGL driver samples depth: measured on
    two slanted planes whose exact depth is known (1/z is linear in the pixel
    coordinate), so the comparison below does not depend on the driver's choice."""
    K = np.array([[250.0, 0, (W - 1) / 2], [0, 250.0, (H - 1) / 2], [0, 0, 1]])
    out = []
    for axis in (0, 1):
        # plane z = 1 + 0.5 * (x or y) in the camera frame, a big quad filling the view
        s = np.array([-2.0, 2.0])
        a, b = np.meshgrid(s, s)
        xy = np.stack([a.ravel(), b.ravel()], -1)
        z = 1.0 + 0.5 * xy[:, axis]
        verts = np.concatenate([xy * 1.0, z[:, None]], -1)
        quad = trimesh.Trimesh(verts, [[0, 1, 3], [0, 3, 2], [0, 3, 1], [0, 2, 3]], process=False)
        depth = gl_depth(gl, quad, K, np.eye(4), offset=(0.0, 0.0))
        v, u = np.nonzero(depth > 0)
        coord = (u, v)[axis].astype(float)
        c, f = K[axis, 2], K[axis, axis]
        # z = 1 + 0.5 X with X = (p - c) / f * z  ->  p = c + f (1 - 1 / z) / 0.5
        sampled = c + f * (1 - 1 / depth[v, u]) / 0.5
        out.append(float(np.median(sampled - coord)))
    return out[0], out[1]


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def depth_errors(depth: np.ndarray, ref: np.ndarray, where: np.ndarray):
    err = np.abs(depth - ref)[where]
    return float(np.median(err)), float(np.percentile(err, 95))


# ----------------------------------------------------------------------------- tests


def test_pyrender_offset_is_sub_pixel(gl):
    # sanity of the measurement itself: a driver samples inside its pixel
    assert all(abs(o) <= 0.5 for o in gl.offset)


@pytest.mark.parametrize("name", sorted(MESHES))
def test_matches_pyrender_without_distortion(gl, name):
    mesh = posed(MESHES[name]())
    cams = make_cameras()
    topo = MeshTopology.from_faces(mesh.faces)
    verts = torch.as_tensor(mesh.vertices, dtype=torch.float32)
    full = render(verts, topo, cams, full_image_crops(cams), size=(H, W), sigma=0.5)
    for c in range(len(cams)):
        ref = gl_depth(gl, mesh, cams.K[c].double().numpy(), cams.T_world_from_cam[c].double().numpy())
        sil = full.silhouette[0, c].numpy() > 0.5
        assert (ref > 0).sum() > 1000  # the object is well inside the view
        assert iou(sil, ref > 0) > 0.99  # (0.97 asked; both rasterise the same triangles at pixel centres)
        med, p95 = depth_errors(full.depth[0, c].numpy(), ref, full.coverage[0, c].numpy() & (ref > 0))
        assert med < 0.002 and p95 < 0.004, (med, p95)

    # a native-resolution crop around the object renders the same pixels as the full image
    crops = object_crops(verts, cams, (96, 128), margin=0.2)  # (1, C, 4)
    centre = (crops[..., :2] + crops[..., 2:]) / 2
    x0 = torch.round(centre[..., 0] - 64) - 0.5
    y0 = torch.round(centre[..., 1] - 48) - 0.5
    native = torch.stack([x0, y0, x0 + 128, y0 + 96], -1)
    out = render(verts, topo, cams, native, size=(96, 128), sigma=0.5)
    for c in range(len(cams)):
        i0, j0 = int(y0[0, c] + 0.5), int(x0[0, c] + 0.5)
        assert 0 <= i0 and i0 + 96 <= H and 0 <= j0 and j0 + 128 <= W
        window = full.silhouette[0, c, i0:i0 + 96, j0:j0 + 128]
        assert torch.allclose(out.silhouette[0, c], window, atol=1e-4)
        assert torch.allclose(out.depth[0, c], full.depth[0, c, i0:i0 + 96, j0:j0 + 128], atol=1e-5)


@pytest.mark.parametrize("name", sorted(MESHES))
def test_matches_remapped_pyrender_with_distortion(gl, name):
    """With lens distortion, the reference is pyrender's pinhole image (rendered at 3x
    resolution) resampled through the lens model: each distorted pixel reads the
    pinhole image at its undistorted position (cv2.remap)."""
    base = MESHES[name]()
    # straight edges between projected vertices approximate the curved images of long
    # edges: subdivide so no edge spans more than 5 cm (about 15 px here)
    v, f = trimesh.remesh.subdivide_to_size(base.vertices, base.faces, max_edge=0.05)
    mesh = posed(trimesh.Trimesh(v, f), offset=(0.25, 0.1, 0.1))  # off the optical axis, where the lens bends
    cams = make_cameras(LENS_DIST)
    verts = torch.as_tensor(mesh.vertices, dtype=torch.float32)
    out = render(verts, mesh.faces, cams, full_image_crops(cams), size=(H, W), sigma=0.5)
    plain = render(verts, mesh.faces, make_cameras(), full_image_crops(cams), size=(H, W), sigma=0.5)
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel()], -1)[:, None, :]  # (H*W, 1, 2)
    s = 3
    for c in range(len(cams)):
        K = cams.K[c].double().numpy()
        und = cv2.undistortPoints(pix, K, np.array(LENS_DIST), P=K)[:, 0]  # (H*W, 2) pinhole pixels
        map_x = (s * und[:, 0] + (s - 1) / 2).reshape(H, W).astype(np.float32)
        map_y = (s * und[:, 1] + (s - 1) / 2).reshape(H, W).astype(np.float32)
        pinhole = gl_depth(gl, mesh, K, cams.T_world_from_cam[c].double().numpy(), scale=s)
        ref_mask = cv2.remap((pinhole > 0).astype(np.uint8), map_x, map_y, cv2.INTER_NEAREST) > 0
        ref_depth = cv2.remap(pinhole, map_x, map_y, cv2.INTER_LINEAR)
        # bilinear depth mixes in background at the rim: compare where the mask is solid
        solid = cv2.erode(ref_mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        sil = out.silhouette[0, c].numpy() > 0.5
        assert ref_mask.sum() > 1000
        assert iou(sil, ref_mask) > 0.97
        # the lens matters here: the same rendering without distortion is clearly worse
        assert iou(plain.coverage[0, c].numpy(), ref_mask) < iou(sil, ref_mask) - 0.02
        med, p95 = depth_errors(out.depth[0, c].numpy(), ref_depth, out.coverage[0, c].numpy() & solid)
        assert med < 0.002 and p95 < 0.004, (med, p95)


@pytest.mark.parametrize("name", sorted(MESHES))
def test_pose_gradient_matches_finite_differences(name):
    """d loss / d (axis-angle, translation) against central differences, float64,
    for loss = sum(silhouette * W1) + sum(depth * W2 * M) over two views; M keeps the
    depth term off the rim, where depth jumps from the surface to 0."""
    torch.manual_seed(0)
    cams = make_cameras(SMALL_DIST, dtype=torch.float64)
    base = MESHES[name]()
    v_obj = torch.as_tensor(base.vertices, dtype=torch.float64)
    topo = MeshTopology.from_faces(base.faces)
    pose0 = torch.tensor([0.4, -0.3, 0.2, *OBJECT_CENTER], dtype=torch.float64)
    size = (40, 48)

    def verts(pose):
        return v_obj @ axis_angle_matrix(pose[:3]).T + pose[3:]

    crops = object_crops(verts(pose0), cams, size, margin=0.3)
    ref = render(verts(pose0), topo, cams, crops, size, sigma=1.5)
    inside = -F.max_pool2d(-ref.coverage[0].double()[:, None], 5, 1, 2)[:, 0]  # eroded by 2 px
    W1 = torch.rand(ref.silhouette.shape, dtype=torch.float64)
    W2 = torch.rand(ref.depth.shape, dtype=torch.float64) * inside * 20

    def loss(pose):
        out = render(verts(pose), topo, cams, crops, size, sigma=1.5)
        return (out.silhouette * W1).sum() + (out.depth * W2).sum()

    pose = pose0.clone().requires_grad_(True)
    loss(pose).backward()
    analytic = pose.grad
    h = 1e-6
    numeric = torch.zeros(6, dtype=torch.float64)
    with torch.no_grad():
        for k in range(6):
            e = torch.zeros(6, dtype=torch.float64)
            e[k] = h
            numeric[k] = (loss(pose0 + e) - loss(pose0 - e)) / (2 * h)
    assert numeric.norm() > 1.0  # a real signal, not two zeros agreeing
    rel = (analytic - numeric).norm() / numeric.norm()
    assert rel < 0.05, (analytic, numeric)


def test_vertex_gradient_matches_finite_differences():
    """Per-vertex gradients (silhouette and depth) on a few vertices of the cylinder."""
    torch.manual_seed(1)
    cams = make_cameras(dtype=torch.float64)
    mesh = posed(MESHES["cylinder"]())
    v0 = torch.as_tensor(mesh.vertices, dtype=torch.float64)
    topo = MeshTopology.from_faces(mesh.faces)
    size = (48, 48)
    crops = object_crops(v0, cams, size, margin=0.3)
    ref = render(v0, topo, cams, crops, size, sigma=1.2)
    inside = -F.max_pool2d(-ref.coverage[0].double()[:, None], 5, 1, 2)[:, 0]
    W1 = torch.rand(ref.silhouette.shape, dtype=torch.float64)
    W2 = torch.rand(ref.depth.shape, dtype=torch.float64) * inside * 20

    def loss(v):
        out = render(v, topo, cams, crops, size, sigma=1.2)
        return (out.silhouette * W1).sum() + (out.depth * W2).sum()

    v = v0.clone().requires_grad_(True)
    loss(v).backward()
    g = v.grad
    picks = torch.argsort(g.norm(dim=1), descending=True)[:4]  # vertices the loss depends on most
    h = 1e-7
    for i in picks.tolist():
        num = torch.zeros(3, dtype=torch.float64)
        with torch.no_grad():
            for k in range(3):
                e = torch.zeros_like(v0)
                e[i, k] = h
                num[k] = (loss(v0 + e) - loss(v0 - e)) / (2 * h)
        assert (g[i] - num).norm() / num.norm() < 0.05, (i, g[i], num)


def test_batching_over_frames_and_views_equals_one_at_a_time():
    cams = make_cameras(SMALL_DIST)
    base = MESHES["cylinder"]()
    topo = MeshTopology.from_faces(base.faces)
    frames = [posed(base, angle=0.3 * b, offset=(0.03 * b, 0.0, 0.0)).vertices for b in range(3)]
    verts = torch.as_tensor(np.stack(frames), dtype=torch.float32).requires_grad_(True)  # (3, V, 3)
    size = (40, 56)
    crops = object_crops(verts.detach(), cams, size)
    out = render(verts, topo, cams, crops, size, sigma=0.8)
    w = torch.rand(out.silhouette.shape)
    ((out.silhouette * w).sum() + (out.depth * w).sum()).backward()
    for b in range(3):
        for c in range(len(cams)):
            vb = verts.detach()[b].clone().requires_grad_(True)
            one = render(vb, topo, cams.select([c]), crops[b, c][None], size, sigma=0.8)
            assert torch.allclose(one.silhouette[0, 0], out.silhouette[b, c], atol=1e-5)
            assert torch.allclose(one.depth[0, 0], out.depth[b, c], atol=1e-5)
            assert torch.equal(one.coverage[0, 0], out.coverage[b, c])
            ((one.silhouette[0, 0] * w[b, c]).sum() + (one.depth[0, 0] * w[b, c]).sum()).backward()
            if c == 0:
                grad_b = vb.grad.clone()
            else:
                grad_b += vb.grad
        assert torch.allclose(grad_b, verts.grad[b], atol=1e-4, rtol=1e-4)


def test_empty_and_out_of_view_cases_give_empty_outputs():
    cams = make_cameras(SMALL_DIST)
    mesh = posed(MESHES["box"]())
    topo = MeshTopology.from_faces(mesh.faces)
    verts = torch.as_tensor(mesh.vertices, dtype=torch.float32)
    size = (32, 32)
    # crops that miss the object
    far = torch.tensor([[0.0, 0.0, 20.0, 20.0], [280.0, 220.0, 300.0, 240.0]])
    # object behind both cameras: mirror it through each camera centre
    centres = cams.centers.mean(0)
    behind = 2 * centres - verts
    # object far to the side, outside every image
    aside = verts + torch.tensor([0.0, 0.0, 30.0])
    # object straddling a camera's image plane (some vertices behind, some in front)
    straddle = verts - torch.as_tensor(OBJECT_CENTER, dtype=torch.float32) + cams.centers[0]
    # one vertex exactly on camera 0's plane (z = 0), the rest in front of it
    T0 = cams.T_world_from_cam[0]
    on_plane = verts - verts[0] + T0[:3, 3] + 0.1 * T0[:3, 0]
    cases = [  # (vertices, crops, must be empty)
        (on_plane, None, False),
        (verts, far, True),
        (behind, None, True),
        (aside, None, True),  # beyond the field of view (|x/z|, |y/z| > max_radius): not drawn
        (straddle, None, False),
        (verts, torch.zeros(2, 4), True),  # zero-area crops
    ]
    for v, crops, empty in cases:
        v = v.clone().requires_grad_(True)
        out = render(v, topo, cams, crops, size, sigma=0.7)
        assert torch.isfinite(out.silhouette).all() and torch.isfinite(out.depth).all()
        (out.silhouette.sum() + out.depth.sum()).backward()  # still part of the graph
        assert torch.isfinite(v.grad).all()
        if empty:
            assert out.silhouette.abs().max() == 0 and out.depth.abs().max() == 0
    # an object just beside the image is drawn in a crop that follows it, where nothing is observed
    beside = verts + 1.4 * torch.as_tensor(make_cameras().T_world_from_cam[0, :3, 0])  # along camera 0's x
    crops = object_crops(beside, cams, size)
    assert not crop_in_image(crops, cams, size)[0, 0].any()
    assert render(beside, topo, cams, crops, size).coverage[0, 0].sum() > 100
    # an empty mesh
    out = render(verts, torch.zeros(0, 3, dtype=torch.long), cams, None, size)
    assert out.silhouette.abs().max() == 0 and out.depth.abs().max() == 0


def test_silhouette_is_not_dented_by_contours_inside_it():
    """Two bars, one in front of the other: the near bar's outline lies inside the
    silhouette; pixels around it are deep inside and must read 1."""
    front = trimesh.creation.box(extents=(0.04, 0.04, 0.30))
    back = trimesh.creation.box(extents=(0.30, 0.02, 0.12))
    front.apply_translation([0.0, -0.08, 0.0])
    mesh = trimesh.util.concatenate([front, back])
    T = look_at(np.array([0.0, -1.0, 0.0]), np.zeros(3))
    cams = Cameras.from_infos([SimpleNamespace(name="c", width=W, height=H, K=K0, dist=[], T_world_from_cam=T)])
    out = render(torch.as_tensor(mesh.vertices, dtype=torch.float32), mesh.faces, cams, full_image_crops(cams),
                 size=(H, W), sigma=1.0)
    cov = out.coverage[0, 0].float()[None, None]
    deep = (-F.max_pool2d(-cov, 13, 1, 6))[0, 0] > 0  # 6 px or more from any uncovered pixel
    assert deep.sum() > 500
    assert out.silhouette[0, 0][deep].min() > 0.999
    # while the outline itself is soft
    rim = (cov[0, 0] > 0) & ~deep
    assert (out.silhouette[0, 0][rim] < 0.9).any()


def test_crop_observation_modes():
    img = torch.arange(6 * 8, dtype=torch.float32).reshape(1, 6, 8) + 1
    # native crop: identity
    box = torch.tensor([[-0.5, -0.5, 7.5, 5.5]])
    for mode in ("nearest", "area", "min"):
        assert torch.allclose(crop_observation(img, box, (6, 8), mode), img)
    # factor-2 downsampling: area = 2x2 mean, min = 2x2 min, nearest = one of the four
    half = (3, 4)
    assert torch.allclose(crop_observation(img, box, half, "area"), F.avg_pool2d(img[None], 2)[0])
    assert torch.allclose(crop_observation(img, box, half, "min"), -F.max_pool2d(-img[None], 2)[0])
    near = crop_observation(img, box, half, "nearest")
    assert torch.all((near - F.avg_pool2d(img[None], 2)[0]).abs() <= 4.5)
    # zeros are missing depth for 'min'; outside the image reads 0
    holes = img.clone()
    holes[0, 0, 0] = 0
    assert crop_observation(holes, box, half, "min")[0, 0, 0] == 2
    shifted = torch.tensor([[3.5, -0.5, 11.5, 5.5]])  # right half outside the image
    out = crop_observation(img, shifted, (6, 8), "nearest")
    assert torch.equal(out[0, :, :4], img[0, :, 4:]) and out[0, :, 4:].abs().max() == 0
    area = crop_observation(torch.ones(1, 6, 8), torch.tensor([[-0.5, -0.5, 9.5, 5.5]]), (3, 5), "area")
    assert torch.allclose(area[0, :, -1], torch.zeros(3)) and torch.allclose(area[0, :, :4], torch.ones(3, 4))
    # a non-integer factor, against the overlap-weighted mean computed pixel by pixel
    rng = np.random.default_rng(3)
    im = rng.random((20, 30))
    x0, y0, x1, y1 = 1.3, -2.2, 33.9, 18.6
    h, w = 7, 11
    sx, sy = (x1 - x0) / w, (y1 - y0) / h
    want = np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            ax, bx, ay, by = x0 + j * sx, x0 + (j + 1) * sx, y0 + i * sy, y0 + (i + 1) * sy
            ox = np.clip(np.minimum(bx, np.arange(30) + 0.5) - np.maximum(ax, np.arange(30) - 0.5), 0, None)
            oy = np.clip(np.minimum(by, np.arange(20) + 0.5) - np.maximum(ay, np.arange(20) - 0.5), 0, None)
            want[i, j] = (oy[:, None] * ox[None, :] * im).sum() / (sx * sy)
    got = crop_observation(torch.as_tensor(im)[None], torch.tensor([[x0, y0, x1, y1]], dtype=torch.float64), (h, w))
    assert np.allclose(got[0].numpy(), want, atol=1e-9)


def test_rendered_crop_matches_cropped_full_rendering():
    """Conventions of `render` crops and `crop_observation` agree: a full-resolution
    hard coverage, area-averaged to a 3x coarser crop, matches the crop rendered
    directly with a sigma that mimics area coverage."""
    cams = make_cameras(SMALL_DIST)
    mesh = posed(MESHES["cylinder"]())
    verts = torch.as_tensor(mesh.vertices, dtype=torch.float32)
    topo = MeshTopology.from_faces(mesh.faces)
    full = render(verts, topo, cams, full_image_crops(cams), (H, W), sigma=0.3)
    size = (36, 40)
    crops = object_crops(verts, cams, size, margin=0.2)
    crops = torch.cat([crops[..., :2], crops[..., :2] + 3 * torch.tensor([40.0, 36.0])], -1)  # exactly 3x
    small = render(verts, topo, cams, crops, size, sigma=0.3)
    observed = crop_observation(full.coverage[0].float(), crops[0], size, "area")
    assert (small.silhouette[0] - observed).abs().mean() < 0.02
    assert iou(small.silhouette[0].numpy() > 0.5, observed.numpy() > 0.5) > 0.95
    depth_obs = crop_observation(full.depth[0], crops[0], size, "nearest")
    both = small.coverage[0] & (depth_obs > 0)
    assert (small.depth[0] - depth_obs)[both].abs().median() < 0.002


def _render_both(verts, mesh, cams, crops, size, **kw):
    """The compact render and the fixed-shape one sized from it (`Capacity.fitting`), each with
    the vertex gradient of a weighted sum of its silhouette and depth."""
    from intercap.geometry.rendering import Capacity

    outs = []
    for capacity in (None, "fitting"):
        v = verts.detach().clone().requires_grad_(True)
        if capacity == "fitting":
            capacity = Capacity.fitting(outs[0][0].needed)
        out = render(v, mesh, cams, crops, size, capacity=capacity, **kw)
        weight = torch.linspace(0.5, 1.5, out.silhouette.numel()).reshape(out.silhouette.shape)
        ((out.silhouette * weight).sum() + (out.depth * weight).sum()).backward()
        outs.append((out, v.grad))
    return outs


@pytest.mark.parametrize("name", ["box", "cylinder", "bars"])
def test_fixed_shapes_render_exactly_what_the_compact_render_does(name):
    """With a `Capacity` (no host waits, same shapes every call: what a CUDA graph records), the
    coverage and depth are the compact render's bit for bit, the silhouette and the vertex
    gradients to float rounding (the CPU's vectorised exp rounds by position in the array); the
    counts say when a capacity is too small."""
    from intercap.geometry.rendering import Capacity

    if name == "bars":  # contours inside the silhouette (inner pieces), 3 frames
        front = trimesh.creation.box(extents=(0.04, 0.04, 0.30))
        back = trimesh.creation.box(extents=(0.30, 0.02, 0.12))
        front.apply_translation([0.0, -0.08, 0.0])
        base = trimesh.util.concatenate([front, back])
    else:
        base = MESHES[name]()
    cams = make_cameras(LENS_DIST)
    frames = [posed(base, angle=0.4 + 0.7 * b, offset=(0.02 * b, -0.01 * b, 0.0)).vertices for b in range(3)]
    verts = torch.as_tensor(np.stack(frames), dtype=torch.float32)
    size = (48, 64)
    crops = object_crops(verts, cams, size, margin=0.3)
    crops[1, 0] += 20.0  # a frame whose object leaves its crop on one side
    (ref, ref_grad), (fix, fix_grad) = _render_both(verts, MeshTopology.from_faces(base.faces), cams, crops, size,
                                                    sigma=0.7)
    assert torch.equal(ref.needed, fix.needed) and ref.needed.min() > 0
    assert torch.equal(ref.coverage, fix.coverage) and torch.equal(ref.depth, fix.depth)
    assert torch.allclose(ref.silhouette, fix.silhouette, rtol=0, atol=1e-6)
    assert torch.allclose(ref_grad, fix_grad, rtol=1e-5, atol=1e-5)
    assert Capacity.fitting(ref.needed).holds(fix.needed)
    lines, pixels, contours, pieces = ref.needed.tolist()
    assert not Capacity(lines, pixels - 1, contours, pieces).holds(ref.needed)
    short = render(verts, base.faces, cams, crops, size, sigma=0.7, capacity=Capacity(lines, pixels // 2, contours, pieces))
    assert torch.equal(short.needed, ref.needed)  # the counts still tell what was wanted
    assert short.coverage.sum() < ref.coverage.sum()


def test_fixed_shapes_handle_empty_and_degenerate_views():
    """Views that see nothing, a vertex on a camera's plane, zero-area crops: finite outputs and
    gradients, equal to the compact render's."""
    cams = make_cameras(SMALL_DIST)
    verts = torch.as_tensor(posed(MESHES["box"]()).vertices, dtype=torch.float32)
    T0 = cams.T_world_from_cam[0]
    on_plane = verts - verts[0] + T0[:3, 3] + 0.1 * T0[:3, 0]
    far = torch.tensor([[0.0, 0.0, 20.0, 20.0], [280.0, 220.0, 300.0, 240.0]])
    for v, crops in ((verts, far), (on_plane, None), (verts, torch.zeros(2, 4)), (2 * cams.centers.mean(0) - verts, None)):
        (ref, ref_grad), (fix, fix_grad) = _render_both(v, MeshTopology.from_faces(MESHES["box"]().faces), cams,
                                                        crops, (32, 32), sigma=0.7)
        assert torch.isfinite(fix.silhouette).all() and torch.isfinite(fix.depth).all()
        assert torch.isfinite(fix_grad).all()
        assert torch.allclose(ref.silhouette, fix.silhouette, rtol=0, atol=1e-6) and torch.equal(ref.depth, fix.depth)
        assert torch.allclose(ref_grad, fix_grad, rtol=1e-5, atol=1e-5)


def test_fixed_shapes_render_waits_on_nothing():
    """No value read back, no data-dependent shape, nothing copied from the host: a CUDA graph
    can record it (`tests/host_waits.py`)."""
    from host_waits import HostWaits

    from intercap.geometry.rendering import Capacity

    cams = make_cameras(LENS_DIST)
    base = MESHES["cylinder"]()
    topo = MeshTopology.from_faces(base.faces)
    verts = torch.as_tensor(np.stack([posed(base, angle=a).vertices for a in (0.3, 0.9)]), dtype=torch.float32)
    crops = object_crops(verts, cams, (48, 48))
    capacity = Capacity.fitting(render(verts, topo, cams, crops, (48, 48)).needed)
    v = verts.clone().requires_grad_(True)
    with HostWaits() as waits:
        out = render(v, topo, cams, crops, (48, 48), capacity=capacity)
        torch.autograd.grad((out.silhouette.sum() + out.depth.sum()), v)
    assert waits.seen == []
