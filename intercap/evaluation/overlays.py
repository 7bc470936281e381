"""Mesh overlays: a stage's body and object meshes rendered (pyrender, shaded, semi-transparent)
over each camera's colour image, with the camera's calibration and lens distortion.

pyrender renders an ideal pinhole image; lenses bend it. So each view is rendered on a
canvas padded wide enough for the distortion, then resampled with cv2.remap through a
map that says, for every pixel of the real (distorted) image, where its undistorted
ray lands on the pinhole canvas (`intercap.geometry.cameras.pixel_rays`). Silhouettes
are rendered the same way (pyrender's segmentation pass), so overlays can be checked
against the session's masks pixel for pixel (`silhouette_iou`).

Body regions in contact (OUT/contact/contact.npz: `region_contact`, `region_vertex_ids`)
are tinted. Per stage (`object`, `body`, `global`) every `report.overlay_every`-th frame
is drawn in every view (OUT/report/overlays/<stage>/<frame>_<camera>.jpg) and one camera
over the whole sequence goes into a video (PyAV; VP9 in WebM by default, which Chromium
builds without proprietary codecs play too; H.264 MP4 on request).
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

log = logging.getLogger(__name__)

BODY_COLOUR = (110, 160, 235)  # RGB, light blue
OBJECT_COLOUR = (80, 210, 120)  # green
CONTACT_COLOUR = (250, 70, 40)  # red-orange: body regions touching the object
OVERLAY_STAGES = ("object", "body", "global")
_SEG_BODY, _SEG_OBJECT = (255, 0, 0), (0, 255, 0)


def import_pyrender():
    """pyrender, imported headless: EGL unless the caller chose a platform (must precede the import)."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    import pyrender

    return pyrender


def distortion_maps(camera, pad: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of the distorted image (H, W), where to sample a pinhole rendering with the
    same K on a canvas padded by `pad` pixels: two (H, W) float32 maps for cv2.remap."""
    from intercap.geometry.cameras import Cameras, pixel_rays

    cams = Cameras.from_infos([camera], dtype=torch.float64)
    H, W = int(camera.height), int(camera.width)
    xy = pixel_rays(cams, H, W)[0].numpy()  # (H*W, 2) undistorted normalised coordinates
    K = np.asarray(camera.K, np.float64)
    u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2] + pad
    v = K[1, 1] * xy[:, 1] + K[1, 2] + pad
    return u.reshape(H, W).astype(np.float32), v.reshape(H, W).astype(np.float32)


@dataclass
class Rendered:
    """One view's render, distorted like the camera: colour (H, W, 3) uint8, coverage (H, W) float
    in [0, 1] (antialiased) and the visible body / object silhouettes (H, W) bool (None when the
    render skipped them)."""

    colour: np.ndarray
    coverage: np.ndarray
    body: np.ndarray | None = None
    object: np.ndarray | None = None


class OverlayRenderer:
    """One pyrender scene and offscreen renderer reused for every frame and view of a session.

    cameras: the session's CameraInfo list; object_mesh: trimesh in object coordinates (or None).
    Lights travel with the camera (a head light plus a fill), so every view is shaded alike."""

    def __init__(self, cameras, object_mesh=None, znear: float = 0.05, zfar: float = 50.0):
        self.pr = pr = import_pyrender()
        self.cameras = list(cameras)
        self.znear, self.zfar = znear, zfar
        self.maps, pads = [], []
        for cam in self.cameras:
            mx, my = distortion_maps(cam)
            pads.append(int(np.ceil(max(0.0, -mx.min(), -my.min(), mx.max() - (cam.width - 1),
                                        my.max() - (cam.height - 1)))) + 2)
            self.maps.append((mx, my))
        self.pad = max(pads)
        self.maps = [(mx + self.pad, my + self.pad) for mx, my in self.maps]
        w = max(c.width for c in self.cameras) + 2 * self.pad
        h = max(c.height for c in self.cameras) + 2 * self.pad
        self.renderer = pr.OffscreenRenderer(w, h)
        self.scene = pr.Scene(ambient_light=(0.35, 0.35, 0.35), bg_color=(0, 0, 0, 0))
        self.cam_node = self.scene.add(pr.IntrinsicsCamera(1, 1, 0, 0), pose=np.eye(4))
        self.lights = [self.scene.add(pr.DirectionalLight(intensity=i), pose=np.eye(4)) for i in (2.5, 1.0)]
        self.object_node = None
        if object_mesh is not None:
            import trimesh

            obj = trimesh.Trimesh(np.asarray(object_mesh.vertices), np.asarray(object_mesh.faces), process=False)
            obj.visual.vertex_colors = np.array(OBJECT_COLOUR + (255,), np.uint8)
            self.object_mesh = pr.Mesh.from_trimesh(obj, smooth=False)
        self.body_node = None

    def set_frame(self, body_vertices=None, body_faces=None, body_colours=None, object_pose=None) -> None:
        """Place the meshes of one frame: body (V, 3) world with faces (F, 3) and optional vertex
        colours (V, 3) uint8; object_pose (4, 4) object -> world. None (or NaN) leaves a mesh out."""
        pr = self.pr
        if self.body_node is not None:
            self.scene.remove_node(self.body_node)
            self.body_node = None
        if self.object_node is not None:
            self.scene.remove_node(self.object_node)
            self.object_node = None
        if body_vertices is not None and np.isfinite(body_vertices).all():
            colours = np.tile(np.array(BODY_COLOUR, np.uint8), (len(body_vertices), 1)) if body_colours is None \
                else np.asarray(body_colours, np.uint8)
            v = np.asarray(body_vertices, np.float32)
            prim = pr.Primitive(positions=v, normals=vertex_normals(v, body_faces), indices=body_faces,
                                color_0=np.c_[colours, np.full(len(colours), 255, np.uint8)].astype(np.float32) / 255,
                                material=pr.MetallicRoughnessMaterial(baseColorFactor=(1.0, 1.0, 1.0, 1.0),
                                                                      metallicFactor=0.0, roughnessFactor=0.8))
            self.body_node = self.scene.add(pr.Mesh([prim]))
        if object_pose is not None and np.isfinite(object_pose).all() and hasattr(self, "object_mesh"):
            self.object_node = self.scene.add(self.object_mesh, pose=np.asarray(object_pose, np.float64))

    def render(self, view: int, silhouettes: bool = True) -> Rendered:
        """The current frame seen by camera `view`, distorted like its lens; `silhouettes`: also
        the per-mesh masks (a second, segmentation pass)."""
        pr, cam, p = self.pr, self.cameras[view], self.pad
        K = np.asarray(cam.K, np.float64)
        # pyrender's pixel centres sit at i + 0.5, OpenCV's at i: shift the principal point by half a pixel
        self.cam_node.camera = pr.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2] + p + 0.5, K[1, 2] + p + 0.5,
                                                   znear=self.znear, zfar=self.zfar)
        pose = np.asarray(cam.T_world_from_cam, np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV -> OpenGL
        self.scene.set_pose(self.cam_node, pose)
        for node, tilt in zip(self.lights, (0.0, 0.6)):  # head light, and a fill from above-left
            c, s = np.cos(tilt), np.sin(tilt)
            self.scene.set_pose(node, pose @ np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]]))
        self.renderer.viewport_width, self.renderer.viewport_height = cam.width + 2 * p, cam.height + 2 * p
        mx, my = self.maps[view]
        H, W = cam.height, cam.width
        if self.body_node is None and self.object_node is None:
            empty = np.zeros((H, W), bool)
            return Rendered(np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.float32), empty, empty.copy())
        rgba, _ = self.renderer.render(self.scene, flags=pr.RenderFlags.RGBA)
        rgba = cv2.remap(rgba, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        rendered = Rendered(rgba[..., :3], rgba[..., 3].astype(np.float32) / 255.0)
        if not silhouettes:
            return rendered
        seg_map = {n: (0, 0, 0) for n in self.scene.mesh_nodes}
        if self.body_node is not None:
            seg_map[self.body_node] = _SEG_BODY
        if self.object_node is not None:
            seg_map[self.object_node] = _SEG_OBJECT
        seg, _ = self.renderer.render(self.scene, flags=pr.RenderFlags.SEG, seg_node_map=seg_map)
        seg = cv2.remap(seg, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        rendered.body, rendered.object = seg[..., 0] > 127, seg[..., 1] > 127
        return rendered

    def close(self) -> None:
        self.renderer.delete()


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 area-weighted unit vertex normals (bincount: fast enough per frame)."""
    tri = vertices[faces]  # (F, 3, 3)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3), length = 2 x area
    idx = np.asarray(faces).reshape(-1)
    n = np.stack([np.bincount(idx, np.repeat(fn[:, k], 3), minlength=len(vertices)) for k in range(3)], 1)
    return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def blend(image: np.ndarray, rendered: Rendered, alpha: float) -> np.ndarray:
    """The render laid over an RGB image (H, W, 3) uint8 with opacity `alpha`, outlines opaque."""
    a = alpha * rendered.coverage[..., None]  # (H, W, 1)
    out = ((1 - a) * image.astype(np.float32) + a * rendered.colour.astype(np.float32)).round().astype(np.uint8)
    for mask, colour in ((rendered.body, BODY_COLOUR), (rendered.object, OBJECT_COLOUR)):
        if mask is not None and mask.any():
            contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(out, contours, -1, colour, 1)
    return out


def silhouette_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (NaN when both are empty)."""
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else float("nan")


@dataclass
class SilhouetteScores:
    """Rendered silhouettes against the session's masks, per frame and view: intersection and union
    pixel counts (F, C) of the body with the person mask and of the object with the object mask
    (-1 where the mask file is missing, or the object is hidden: fewer than `min_object_px` in its mask).
    A result with one mesh only is compared outside the other's mask (see `overlap_counts`)."""

    frames: np.ndarray  # (F,) frame indices
    body_inter: np.ndarray
    body_union: np.ndarray
    object_inter: np.ndarray
    object_union: np.ndarray

    @staticmethod
    def pooled(inter: np.ndarray, union: np.ndarray) -> float:
        """IoU over every scored frame and view together (NaN when none)."""
        ok = union > 0
        return float(inter[ok].sum() / union[ok].sum()) if ok.any() else float("nan")

    @property
    def body_iou(self) -> float:
        return self.pooled(self.body_inter, self.body_union)

    @property
    def object_iou(self) -> float:
        return self.pooled(self.object_inter, self.object_union)


def silhouette_scores(session, meshes: "StageMeshes", frames, renderer: OverlayRenderer,
                      min_object_px: int = 20) -> SilhouetteScores:
    """Render a stage's meshes in every view of `frames` (indices) and count the overlap of the
    visible silhouettes (each occluding the other, like the masks) with the session's masks."""
    frames = np.asarray(list(frames), int)
    have_body, have_object = meshes.body_vertices is not None, meshes.object_R is not None
    counts = np.full((len(frames), session.num_cameras, 2, 2), -1, np.int64)
    for k, i in enumerate(frames):
        fid = int(session.frame_ids[i])
        body = None if meshes.body_vertices is None else np.asarray(meshes.body_vertices[i])
        renderer.set_frame(body, meshes.body_faces, None, meshes.object_pose(i))
        for c in range(session.num_cameras):
            out = renderer.render(c)
            person, thing = session.read_mask(c, fid, "person"), session.read_mask(c, fid, "object")
            got = overlap_counts(out, person if have_body else None, thing if have_object else None,
                                 hidden_body=thing if not have_object else None,
                                 hidden_object=person if not have_body else None, min_object_px=min_object_px)
            counts[k, c] = np.where(got[:, 1:] > 0, got, -1)  # nothing scored: -1
    return SilhouetteScores(frames, counts[..., 0, 0], counts[..., 0, 1], counts[..., 1, 0], counts[..., 1, 1])


# -- what a stage saved --------------------------------------------------------------------
@dataclass
class StageMeshes:
    """A stage's per-frame result: body (T, V, 3) world (or None), faces, object R (T, 3, 3), t (T, 3)."""

    stage: str
    body_vertices: np.ndarray | None = None
    body_faces: np.ndarray | None = None
    object_R: np.ndarray | None = None
    object_t: np.ndarray | None = None

    def object_pose(self, i: int) -> np.ndarray | None:
        if self.object_R is None:
            return None
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.object_R[i], self.object_t[i]
        return T

    @property
    def num_frames(self) -> int:
        return len(self.body_vertices) if self.body_vertices is not None else len(self.object_R)


def load_stage_meshes(out_dir, stage: str) -> StageMeshes | None:
    """The meshes a stage saved under OUT/<stage>/ (object: poses only; body: the body; global:
    both); None when the stage has not run."""
    folder = Path(out_dir) / stage
    meshes = StageMeshes(stage)
    if stage in ("body", "global") and (folder / "body_vertices.npy").is_file() and (folder / "body_faces.npy").is_file():
        meshes.body_vertices = np.load(folder / "body_vertices.npy", mmap_mode="r")
        meshes.body_faces = np.load(folder / "body_faces.npy").astype(np.int64)
    if stage in ("object", "global") and (folder / "object_poses.npz").is_file():
        with np.load(folder / "object_poses.npz") as z:
            meshes.object_R, meshes.object_t = z["R"].astype(np.float64), z["t"].astype(np.float64)
    if meshes.body_vertices is None and meshes.object_R is None:
        return None
    return meshes


def load_contact_tint(out_dir) -> tuple[np.ndarray, list[np.ndarray]] | None:
    """(T, R) bool regions touching per frame and each region's vertex ids, from OUT/contact/contact.npz;
    None when the contact stage has not run or saved no region vertex ids."""
    path = Path(out_dir) / "contact" / "contact.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:
        if "region_vertex_ids" not in z.files or "region_contact" not in z.files:
            return None
        ids = np.split(z["region_vertex_ids"].astype(np.int64), np.cumsum(z["region_sizes"])[:-1])
        return z["region_contact"].astype(bool), ids


def body_colours(num_vertices: int, touching: np.ndarray | None, region_ids: list[np.ndarray] | None) -> np.ndarray:
    """(V, 3) uint8 vertex colours: the body colour, regions touching the object tinted."""
    colours = np.tile(np.array(BODY_COLOUR, np.uint8), (num_vertices, 1))
    if touching is not None and region_ids is not None:
        for on, ids in zip(touching, region_ids):
            if on:
                colours[ids[ids < num_vertices]] = CONTACT_COLOUR
    return colours


# -- drawing a stage -----------------------------------------------------------------------
def render_overlays(session, out_dir, stage: str, report_dir, every: int = 10, alpha: float = 0.6,
                    video_camera: str | int | None = 0, video: bool = True, object_mesh=None,
                    renderer: OverlayRenderer | None = None, progress: bool = True, codec: str = "vp9") -> dict:
    """Overlay images of one stage (every `every`-th frame, every view) and a video of one camera
    (`codec`: a key of VIDEO_CODECS).

    Returns {"images": [(frame_id, camera, relative path)], "video": relative path or None,
    "iou": {"body": .., "object": ..} the silhouettes' IoU with the session's masks over the drawn
    frames and views (pooled; only kinds with masks)}; an empty dict when the stage has not run.
    Paths are relative to `report_dir`."""
    meshes = load_stage_meshes(out_dir, stage)
    if meshes is None:
        return {}
    if meshes.num_frames != session.num_frames:
        log.warning("overlays: %s holds %d frames, the session %d; skipped", stage, meshes.num_frames,
                    session.num_frames)
        return {}
    report_dir = Path(report_dir)
    if object_mesh is None and meshes.object_R is not None and session.object is not None:
        object_mesh = session.object.load_mesh()
    own = renderer is None
    renderer = renderer or OverlayRenderer(session.cameras, object_mesh)
    tint = load_contact_tint(out_dir) if meshes.body_vertices is not None else None
    T = session.num_frames
    shown = set(range(0, T, max(1, every)))
    cam_video = None
    if video and video_camera is not None:
        if isinstance(video_camera, int):
            cam_video = video_camera % session.num_cameras
        elif str(video_camera) in session.camera_names:
            cam_video = session.camera_names.index(str(video_camera))
        else:
            log.warning("overlays: no camera %r for the video; using the first", video_camera)
            cam_video = 0
    frames = range(T) if cam_video is not None else sorted(shown)
    writer = None
    images = []
    video_rel = None
    counts = np.zeros((2, 2), np.int64)  # body, object x intersection, union with the session's masks
    try:
        for i in tqdm(frames, desc=f"overlays {stage}", unit="frame", disable=not progress):
            fid = int(session.frame_ids[i])
            colours = None
            if meshes.body_vertices is not None:
                touching = tint[0][i] if tint is not None and i < len(tint[0]) else None
                colours = body_colours(meshes.body_vertices.shape[1], touching, tint[1] if tint else None)
            renderer.set_frame(None if meshes.body_vertices is None else np.asarray(meshes.body_vertices[i]),
                               meshes.body_faces, colours, meshes.object_pose(i))
            views = range(session.num_cameras) if i in shown else [cam_video]
            for c in views:
                cam = session.cameras[c]
                image = session.read_color(c, fid)
                if image is None:
                    image = np.zeros((cam.height, cam.width, 3), np.uint8)
                rendered = renderer.render(c, silhouettes=i in shown)
                out = blend(image, rendered, alpha)
                if i in shown:
                    _count_overlap(session, c, fid, rendered, meshes, counts)
                    rel = Path("overlays") / stage / f"{fid:06d}_{cam.name}.jpg"
                    (report_dir / rel).parent.mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(report_dir / rel), cv2.cvtColor(out, cv2.COLOR_RGB2BGR),
                                [cv2.IMWRITE_JPEG_QUALITY, 90])
                    images.append((fid, cam.name, rel.as_posix()))
                if c == cam_video:
                    if writer is None:
                        video_rel = video_name(f"{stage}_{cam.name}", codec)
                        writer = VideoWriter(report_dir / video_rel, session.fps, codec)
                    writer.write(out)
    finally:
        if writer is not None:
            writer.close()
        if own:
            renderer.close()
    iou = {k: float(counts[j, 0] / counts[j, 1]) for j, k in enumerate(("body", "object")) if counts[j, 1] > 0}
    return {"images": images, "video": video_rel, "iou": iou}


def _count_overlap(session, c: int, fid: int, rendered: Rendered, meshes: StageMeshes, counts: np.ndarray,
                   min_object_px: int = 20) -> None:
    """Add one view's silhouette overlap with the session's person / object masks to counts (2, 2)
    (see `overlap_counts`)."""
    have_body, have_object = meshes.body_vertices is not None, meshes.object_R is not None
    person = session.read_mask(c, fid, "person") if have_body or have_object else None
    thing = session.read_mask(c, fid, "object") if have_body or have_object else None
    counts += overlap_counts(rendered, person if have_body else None, thing if have_object else None,
                             hidden_body=thing if not have_object else None,
                             hidden_object=person if not have_body else None, min_object_px=min_object_px)


def overlap_counts(rendered: Rendered, person, thing, hidden_body=None, hidden_object=None,
                   min_object_px: int = 20) -> np.ndarray:
    """(2, 2) intersection and union pixel counts of the rendered body with the person mask and of the
    object with the object mask (zeros where a mask is None; the object's also where its mask has
    fewer than `min_object_px`: hidden). A result with only one of the meshes cannot occlude with the
    other, as the masks do: pixels where the other's mask lies (`hidden_body`: the object mask for a
    body-only result, `hidden_object`: the person mask) are left out of the comparison."""
    counts = np.zeros((2, 2), np.int64)
    for j, (mask, sil, hidden) in enumerate(((person, rendered.body, hidden_body),
                                             (thing, rendered.object, hidden_object))):
        if mask is None or sil is None or (j == 1 and np.count_nonzero(mask) < min_object_px):
            continue
        if hidden is not None:
            sil, mask = sil & ~hidden, mask & ~hidden
        counts[j] = np.count_nonzero(sil & mask), np.count_nonzero(sil | mask)
    return counts


VIDEO_CODECS = {  # name -> (PyAV encoder, container suffix, pixel format, encoder options)
    # VP9 in WebM: every browser plays it, Chromium builds without proprietary codecs too
    "vp9": ("libvpx-vp9", ".webm", "yuv420p", {"crf": "32", "b": "0", "deadline": "realtime", "cpu-used": "8",
                                                "row-mt": "1"}),
    # H.264 in MP4: for editors, players and Safari; Chromium builds without proprietary codecs do not play it
    # (Debian 12's chromium 156 does: checked with tests/evaluation/cdp_browser.py)
    "h264": ("libx264", ".mp4", "yuv420p", {"crf": "23", "preset": "veryfast"}),
}


def video_name(stem: str, codec: str = "vp9") -> str:
    """The video's file name for a codec of VIDEO_CODECS (its container's suffix)."""
    if codec not in VIDEO_CODECS:
        raise ValueError(f"unknown video codec {codec!r} (one of {', '.join(VIDEO_CODECS)})")
    return stem + VIDEO_CODECS[codec][1]


class VideoWriter:
    """A video of RGB frames with PyAV: VP9/WebM by default (plays in any browser), or H.264/MP4
    (`codec`, see VIDEO_CODECS); frames padded to even sizes (yuv420p); written atomically."""

    def __init__(self, path, fps: float, codec: str = "vp9"):
        import av

        if codec not in VIDEO_CODECS:
            raise ValueError(f"unknown video codec {codec!r} (one of {', '.join(VIDEO_CODECS)})")
        self.codec = codec
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = self.path.with_name(f".{self.path.name}.part{VIDEO_CODECS[codec][1]}")
        self.container = av.open(str(self.tmp), mode="w")
        self.fps = fps
        self.stream = None

    def write(self, rgb: np.ndarray) -> None:
        import av

        h, w = rgb.shape[:2]
        rgb = np.pad(rgb, ((0, h % 2), (0, w % 2), (0, 0)))
        if self.stream is None:
            from fractions import Fraction

            encoder, _, pix_fmt, options = VIDEO_CODECS[self.codec]
            self.stream = self.container.add_stream(encoder, rate=Fraction(self.fps).limit_denominator(1000))
            self.stream.width, self.stream.height = rgb.shape[1], rgb.shape[0]
            self.stream.pix_fmt = pix_fmt
            self.stream.options = dict(options)
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)

    def close(self) -> None:
        if self.stream is not None:
            for packet in self.stream.encode():
                self.container.mux(packet)
        self.container.close()
        if self.stream is not None:
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)
