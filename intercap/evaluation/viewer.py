"""`intercap view OUT`: an interactive 3D viewer of a results folder in the browser (viser).

Layers, each with a toggle: the body mesh (OUT/body_vertices.npy, body_faces.npy),
the object mesh (the session's mesh posed by OUT/object_poses.npz), the frame's
point cloud (OUT/prepare/clouds/<frame>.ply where prepare saved one, else the
session's depth back-projected with its calibration and lens distortion), the
camera frustums (calibration.json), the ground plane (OUT/prepare/ground.json),
contact (body vertices within `CONTACT_MARGIN_M` of the object in the frames
OUT/contact.npy marks, tinted; the touching regions of OUT/contact/contact.npz
named in the panel) and, when OUT/physics/physics.npz exists, hand and foot
force arrows. A timeline slider with play/pause and frame stepping.

Every array is loaded once at start; stepping a frame only sends new vertex
positions and poses to the browser (meshes are updated in place). The session
folder is the one `intercap run` recorded in OUT/run.json, or `--session`.
"""
from __future__ import annotations

import json
import logging
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

BODY_COLOR = (235, 40, 200)  # distinctive magenta: the browser tests look for it where the body is
OBJECT_COLOR = (70, 150, 255)
CONTACT_COLOR = (255, 210, 0)
FRUSTUM_COLOR = (40, 40, 40)
HAND_FORCE_COLOR = (255, 90, 0)
FOOT_FORCE_COLOR = (0, 170, 80)
CONTACT_MARGIN_M = 0.02  # body vertices this close to the object surface count as touching
FORCE_SCALE_M_PER_N = 0.002  # arrow length: 700 N (a body's weight) -> 1.4 m
CLOUD_STRIDE = 2  # pixel stride when back-projecting depth
CLOUD_POINT_SIZE = 0.008
CLOUD_PRELOAD_FRAMES = 600  # depth clouds computed ahead in the background (about 1.5 MB a frame)
CLOUD_RADIUS_M = 1.5  # the cloud is cropped to this horizontal distance from the person (walls, far floor out)
CLOUD_FLOOR_M = 0.04  # and to points this far above the ground plane (the grid draws the floor)


class ViewerError(RuntimeError):
    """The results folder cannot be shown (missing files, viser not installed)."""


def _require_viser():
    try:
        import viser
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ViewerError("the viewer needs viser: pip install viser (or pip install -e '.[view]')") from exc
    return viser


@dataclass
class ViewData:
    """What the viewer shows, loaded once (arrays indexed by frame like frame_ids)."""

    out_dir: Path
    session_root: Path | None
    frame_ids: np.ndarray  # (T,)
    fps: float = 30.0
    body_vertices: np.ndarray | None = None  # (T, V, 3) float32 (memory-mapped)
    body_faces: np.ndarray | None = None  # (F, 3)
    object_vertices: np.ndarray | None = None  # (N, 3) object coordinates
    object_faces: np.ndarray | None = None
    object_R: np.ndarray | None = None  # (T, 3, 3)
    object_t: np.ndarray | None = None  # (T, 3)
    contact: np.ndarray | None = None  # (T,) bool
    region_names: list[str] = field(default_factory=list)
    region_contact: np.ndarray | None = None  # (T, R) bool
    ground: tuple[np.ndarray, np.ndarray] | None = None  # point, unit normal
    cameras: list = field(default_factory=list)  # the session's CameraInfo (intercap.session), with distortion
    physics: dict | None = None  # hand_force (T,2,3), foot_force (T,2,3), foot_cop (T,2,3)
    keypoints3d: np.ndarray | None = None  # (T, 67, 3)
    cloud_files: dict[int, Path] = field(default_factory=dict)  # frame id -> OUT/prepare/clouds/*.ply
    notes: list[str] = field(default_factory=list)  # layers that could not be loaded, and why

    @property
    def num_frames(self) -> int:
        return int(len(self.frame_ids))


def find_session(out_dir: Path, given: str | Path | None) -> Path | None:
    """The session folder: `given`, else the one recorded in OUT/run.json (by `intercap run`) or
    OUT/report/session.json (by `intercap report`); None when unknown."""
    if given is not None:
        path = Path(given)
        if not (path / "session.yaml").is_file():
            raise ViewerError(f"{path}: not a session folder (no session.yaml)")
        return path
    for record in (out_dir / "run.json", out_dir / "report" / "session.json"):
        if not record.is_file():
            continue
        recorded = Path(json.loads(record.read_text()).get("session") or "")
        if (recorded / "session.yaml").is_file():
            return recorded
        log.warning("%s: the recorded session %s is not there; pass --session", record, recorded)
    return None


def read_cameras(root: Path) -> list:
    """The session's calibration.json as CameraInfo records (the session reader's parser and checks,
    without scanning the frame folders as `Session.load` does)."""
    from intercap.session.format import read_calibration
    from intercap.session.problems import ProblemList

    problems = ProblemList(root)
    cameras = read_calibration(root, problems)
    if problems.any_fatal:
        raise ViewerError("; ".join(f"{root / p.path}: {p.message}" for p in problems if p.fatal))
    return [cam for _, cam in cameras]


def _read_ply_cloud(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 points and (N, 3) uint8 colours of a PLY cloud (grey when uncoloured)."""
    import trimesh

    cloud = trimesh.load(path, process=False)
    points = np.asarray(cloud.vertices, dtype=np.float32)
    colors = getattr(cloud, "colors", None)
    if colors is None or len(colors) != len(points):
        colors = np.full((len(points), 3), 160, np.uint8)
    return points, np.asarray(colors, np.uint8)[:, :3]


def _session_meta(out_dir: Path, root: Path | None,
                  notes: list[str]) -> tuple[float, np.ndarray | None, list, Path | None]:
    """(fps, frame ids or None, cameras as the fits saw them, object mesh path or None) of the session."""
    import yaml

    fps, frame_ids, cameras, obj_mesh = 30.0, None, [], None
    if root is not None:
        meta = yaml.safe_load((root / "session.yaml").read_text()) or {}
        fps = float(meta.get("fps", fps))
        from intercap.session.session import refined_cameras

        cameras = read_cameras(root)
        cameras = refined_cameras(cameras, out_dir) or cameras  # as the fits saw them
        if meta.get("object", {}).get("mesh"):
            obj_mesh = root / meta["object"]["mesh"]
        frames = meta.get("frames") or {}
        if "start" in frames and "end" in frames:
            frame_ids = np.arange(int(frames["start"]), int(frames["end"]) + 1)
    else:
        notes.append("session unknown (no OUT/run.json; pass --session): no object mesh, cameras or depth clouds")
    return fps, frame_ids, cameras, obj_mesh


def _load_meshes(data: ViewData, out_dir: Path, obj_mesh: Path | None, notes: list[str]) -> None:
    """The body's vertices and faces, the object's poses and mesh."""
    if (out_dir / "body_vertices.npy").is_file() and (out_dir / "body_faces.npy").is_file():
        data.body_vertices = np.load(out_dir / "body_vertices.npy", mmap_mode="r")
        data.body_faces = np.load(out_dir / "body_faces.npy").astype(np.int64)
        if data.body_vertices.ndim != 3 or data.body_vertices.shape[2] != 3:
            raise ViewerError(f"{out_dir / 'body_vertices.npy'}: expected (T, V, 3), got {data.body_vertices.shape}")
    else:
        notes.append("no body (OUT/body_vertices.npy, body_faces.npy): run the body stage")
    if (out_dir / "object_poses.npz").is_file():
        with np.load(out_dir / "object_poses.npz") as z:
            data.object_R, data.object_t = z["R"].astype(np.float64), z["t"].astype(np.float64)
        if obj_mesh is not None and obj_mesh.is_file():
            from intercap.session.format import load_mesh_file

            mesh = load_mesh_file(obj_mesh)
            data.object_vertices = np.asarray(mesh.vertices, np.float32)
            data.object_faces = np.asarray(mesh.faces, np.int64)
        else:
            notes.append("object poses found but not the object mesh (session unknown)")
    else:
        notes.append("no object poses (OUT/object_poses.npz): run the object stage")


def _load_extras(data: ViewData, out_dir: Path, notes: list[str]) -> None:
    """Contact labels, the floor, physics forces, 3D keypoints and the fused depth clouds, where present."""
    if (out_dir / "contact.npy").is_file():
        data.contact = np.load(out_dir / "contact.npy").astype(bool)
    if (out_dir / "contact" / "contact.npz").is_file():
        with np.load(out_dir / "contact" / "contact.npz") as z:
            data.region_names = [str(n) for n in z["region_names"]]
            data.region_contact = z["region_contact"].astype(bool)
            if data.contact is None:
                data.contact = z["contact"].astype(bool)
    if data.contact is None:
        notes.append("no contact (OUT/contact.npy): run the contact stage")
    ground = out_dir / "prepare" / "ground.json"
    if ground.is_file():
        g = json.loads(ground.read_text())
        normal = np.asarray(g["normal"], float)
        data.ground = (np.asarray(g["point"], float), normal / np.linalg.norm(normal))
    elif (out_dir / "prepare" / "ground_unavailable.json").is_file():
        notes.append("no ground plane: prepare found no floor (OUT/prepare/ground_unavailable.json)")
    else:
        notes.append("no ground plane (OUT/prepare/ground.json): run the prepare stage")
    physics = out_dir / "physics" / "physics.npz"
    if physics.is_file():
        with np.load(physics) as z:
            data.physics = {k: z[k] for k in ("hand_force", "foot_force", "foot_cop") if k in z.files}
    if (out_dir / "keypoints3d.npy").is_file():
        data.keypoints3d = np.load(out_dir / "keypoints3d.npy", mmap_mode="r")
    clouds = out_dir / "prepare" / "clouds"
    if clouds.is_dir():
        data.cloud_files = {int(p.stem): p for p in clouds.glob("*.ply") if p.stem.isdigit()}


def load_view_data(out_dir: str | Path, session: str | Path | None = None) -> ViewData:
    """Load everything the viewer shows from a results folder (and its session, when known)."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise ViewerError(f"{out_dir}: no such results folder")
    root = find_session(out_dir, session)
    notes: list[str] = []
    fps, frame_ids, cameras, obj_mesh = _session_meta(out_dir, root, notes)
    data = ViewData(out_dir=out_dir, session_root=root, frame_ids=np.zeros(0, int), fps=fps, cameras=cameras)
    _load_meshes(data, out_dir, obj_mesh, notes)

    lengths = [len(a) for a in (data.body_vertices, data.object_R) if a is not None]
    T = lengths[0] if lengths else (len(frame_ids) if frame_ids is not None else 0)
    if T == 0:
        raise ViewerError(f"{out_dir}: nothing to show (no body_vertices.npy or object_poses.npz)")
    if any(n != T for n in lengths):
        raise ViewerError(f"{out_dir}: body_vertices.npy and object_poses.npz have different frame counts {lengths}")
    try:  # `run --frames`: the part of the session the run took
        first, last = json.loads((out_dir / "run.json").read_text())["frames"]
        frame_ids = np.arange(int(first), int(last) + 1)
    except (OSError, ValueError, KeyError, TypeError):
        pass
    data.frame_ids = frame_ids if frame_ids is not None and len(frame_ids) == T else np.arange(T)

    _load_extras(data, out_dir, notes)
    data.notes = notes
    return data


# -- small geometry helpers ---------------------------------------------------------------------------------
def rotation_to_wxyz(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) unit quaternion w, x, y, z."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, float)).as_quat()
    return np.array([w, x, y, z])


def plane_wxyz(normal: np.ndarray) -> np.ndarray:
    """Quaternion turning +z onto `normal` (for the xy grid that draws the ground)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, normal)
    s, c = np.linalg.norm(axis), float(z @ normal)
    if s < 1e-9:
        return np.array([1.0, 0.0, 0.0, 0.0]) if c > 0 else np.array([0.0, 1.0, 0.0, 0.0])
    angle = np.arctan2(s, c)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis / s])


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3), vectorised with bincount."""
    tri = vertices[faces]  # (F, 3, 3)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3)
    idx = faces.reshape(-1)
    normals = np.stack([np.bincount(idx, np.repeat(fn[:, k], 3), minlength=len(vertices)) for k in range(3)], 1)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


class FrameSource:
    """Per-frame derived geometry (posed object, contact vertices, clouds), cached by frame index."""

    def __init__(self, data: ViewData):
        self.data = data
        self._cloud_cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._lock = threading.Lock()
        self._backproject = None  # built in the background: importing torch takes seconds
        self._object_samples = None
        if data.object_vertices is not None:
            self._object_samples = self._sample_object_surface(4000)

    def _sample_object_surface(self, count: int) -> np.ndarray:
        """Points spread over the object mesh (vertices + area-weighted face samples), object coords."""
        v, f = self.data.object_vertices.astype(np.float64), self.data.object_faces
        tri = v[f]
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        rng = np.random.default_rng(0)
        pick = rng.choice(len(f), size=count, p=area / area.sum())
        a, b = rng.random((2, count, 1))
        flip = (a + b) > 1
        a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
        samples = tri[pick, 0] + a * (tri[pick, 1] - tri[pick, 0]) + b * (tri[pick, 2] - tri[pick, 0])
        return np.concatenate([v, samples])

    def body(self, i: int) -> np.ndarray | None:
        if self.data.body_vertices is None:
            return None
        v = np.asarray(self.data.body_vertices[i], np.float32)
        return v if np.isfinite(v).all() else None

    def object_pose(self, i: int) -> tuple[np.ndarray, np.ndarray] | None:
        if self.data.object_R is None:
            return None
        R, t = self.data.object_R[i], self.data.object_t[i]
        return (R, t) if np.isfinite(R).all() and np.isfinite(t).all() else None

    def contact_vertices(self, i: int, body: np.ndarray | None) -> np.ndarray:
        """Body vertex ids within CONTACT_MARGIN_M of the posed object in a contact frame."""
        pose = self.object_pose(i)
        if body is None or pose is None or self._object_samples is None or self.data.contact is None:
            return np.zeros(0, np.int64)
        if not self.data.contact[i]:
            return np.zeros(0, np.int64)
        from scipy.spatial import cKDTree

        R, t = pose
        obj = self._object_samples @ R.T + t
        lo, hi = obj.min(0) - CONTACT_MARGIN_M, obj.max(0) + CONTACT_MARGIN_M
        near = np.flatnonzero(((body >= lo) & (body <= hi)).all(1))  # box test first: cheap
        if len(near) == 0:
            return near
        dist, _ = cKDTree(obj).query(body[near], distance_upper_bound=CONTACT_MARGIN_M)
        return near[np.isfinite(dist)]

    def touching_regions(self, i: int) -> list[str]:
        d = self.data
        if d.region_contact is None or d.region_contact.shape[1] != len(d.region_names):
            return []
        return [n for n, on in zip(d.region_names, d.region_contact[i]) if on]

    def forces(self, i: int, body: np.ndarray | None, pose) -> tuple[np.ndarray, np.ndarray]:
        """Arrow segments (N, 2, 3) and colours (N, 3) for the hand and foot forces of frame i."""
        phys, segs, cols = self.data.physics, [], []
        if phys is None:
            return np.zeros((0, 2, 3), np.float32), np.zeros((0, 3), np.uint8)
        if "hand_force" in phys:
            kp = self.data.keypoints3d
            for side in range(2):  # left, right: applied at the hand's keypoint centre, else the object centre
                f = phys["hand_force"][i, side]
                if kp is not None and len(kp) > i:
                    start = np.nanmean(np.asarray(kp[i, 25 + 21 * side:46 + 21 * side], float), axis=0)
                else:
                    start = pose[1] if pose is not None else np.full(3, np.nan)
                segs.append((start, start + FORCE_SCALE_M_PER_N * f))
                cols.append(HAND_FORCE_COLOR)
        if "foot_force" in phys and "foot_cop" in phys:
            for side in range(2):
                start = phys["foot_cop"][i, side]
                segs.append((start, start + FORCE_SCALE_M_PER_N * phys["foot_force"][i, side]))
                cols.append(FOOT_FORCE_COLOR)
        segs = np.asarray(segs, np.float32).reshape(-1, 2, 3)
        cols = np.asarray(cols, np.uint8).reshape(-1, 3)
        keep = np.isfinite(segs).all((1, 2)) & (np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1) > 1e-4)
        return segs[keep], cols[keep]

    # -- point clouds ---------------------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Build the depth back-projection (imports torch, precomputes the undistorted pixel rays)."""
        if self.data.session_root is None or not self.data.cameras:
            return
        import torch

        from intercap.geometry.cameras import Cameras, depth_to_point_grid, pixel_rays

        cams = Cameras.from_infos(self.data.cameras)
        sizes = {(c.height, c.width) for c in self.data.cameras}
        if len(sizes) != 1:
            log.warning("viewer: cameras of different sizes; depth clouds only from OUT/prepare/clouds")
            return
        H, W = sizes.pop()
        rays = pixel_rays(cams, H, W, CLOUD_STRIDE)

        def backproject(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            points, valid = depth_to_point_grid(torch.from_numpy(depth), cams, CLOUD_STRIDE, rays=rays)
            return points.numpy(), valid.numpy()

        self._backproject = backproject

    def cloud(self, i: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(N, 3) points and (N, 3) uint8 colours of frame i, or None when not available (yet)."""
        with self._lock:
            if i in self._cloud_cache:
                return self._cloud_cache[i]
        frame = int(self.data.frame_ids[i])
        result = None
        if frame in self.data.cloud_files:
            result = _read_ply_cloud(self.data.cloud_files[frame])
        elif self._backproject is not None:
            result = self._depth_cloud(frame)
        if result is not None:
            with self._lock:
                self._cloud_cache[i] = result
        return result

    def _depth_cloud(self, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
        import cv2

        root, s = self.data.session_root, CLOUD_STRIDE
        depths, colors = [], []
        for cam in self.data.cameras:
            d = cv2.imread(str(root / cam.name / "depth" / f"{frame:06d}.png"), cv2.IMREAD_UNCHANGED)
            c = None
            for ext in (".jpg", ".png"):
                c = cv2.imread(str(root / cam.name / "color" / f"{frame:06d}{ext}"), cv2.IMREAD_COLOR)
                if c is not None:
                    break
            if d is None or d.shape != (cam.height, cam.width):
                d = np.zeros((cam.height, cam.width), np.uint16)  # a dropped view: no points
            if c is None:
                c = np.full((cam.height, cam.width, 3), 160, np.uint8)
            depths.append(d.astype(np.float32) / 1000.0)
            colors.append(c[::s, ::s, ::-1].reshape(-1, 3))
        points, valid = self._backproject(np.stack(depths))  # (C, N, 3), (C, N)
        return points[valid].astype(np.float32), np.stack(colors)[valid]


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class Viewer:
    """A running viewer: `set_frame(i)` shows frame index i; `stop()` ends the server."""

    def __init__(self, data: ViewData, port: int = 0, host: str = "127.0.0.1", verbose: bool = False):
        viser = _require_viser()
        start = time.perf_counter()
        self.data = data
        self.source = FrameSource(data)
        self.server = viser.ViserServer(host=host, port=port or _free_port(host), verbose=verbose)
        shown = ("localhost" if host in ("127.0.0.1", "localhost", "::1")
                 else socket.gethostname() if host in ("0.0.0.0", "::", "") else host)  # every interface: this machine's name
        self.url = f"http://{shown}:{self.server.get_port()}"
        self.index = -1
        self._stop = threading.Event()
        self._frame_lock = threading.RLock()
        self.clouds_ready = threading.Event()  # set once depth clouds can be shown
        self._build_scene()
        self._build_gui()
        self.set_frame(0)
        self.first_frame_s = time.perf_counter() - start
        self._threads = [threading.Thread(target=self._play_loop, daemon=True),
                         threading.Thread(target=self._warm_clouds, daemon=True)]
        for t in self._threads:
            t.start()

    # -- scene ------------------------------------------------------------------------------------------------
    def _build_scene(self) -> None:
        d, scene = self.data, self.server.scene
        up = d.ground[1] if d.ground is not None else np.array([0.0, 0.0, 1.0])
        scene.set_up_direction(tuple(float(x) for x in up))
        scene.configure_default_lights(cast_shadow=False)  # shadow maps cost more than they show here
        self.body = self.contact_mesh = self.object = self.cloud = self.arrows = None
        if d.body_vertices is not None:
            first = next((i for i in range(d.num_frames) if self.source.body(i) is not None), None)
            v0 = self.source.body(first) if first is not None else np.zeros((1, 3), np.float32)
            self.body = scene.add_mesh_simple("/body", v0, d.body_faces if first is not None else np.zeros((0, 3)),
                                              color=BODY_COLOR, flat_shading=False, side="double")
            self.contact_mesh = scene.add_mesh_simple("/contact", np.zeros((3, 3), np.float32),
                                                      np.array([[0, 1, 2]]), color=CONTACT_COLOR, side="double",
                                                      visible=False)
        if d.object_vertices is not None:
            self.object = scene.add_mesh_simple("/object", d.object_vertices, d.object_faces, color=OBJECT_COLOR,
                                                side="double")
        self._static = {"cameras": [], "ground": []}
        for cam in d.cameras:
            fov = 2 * np.arctan2(cam.height / 2, cam.K[1, 1])
            frustum = scene.add_camera_frustum(
                f"/cameras/{cam.name}", fov=float(fov), aspect=cam.width / cam.height, scale=0.2, thickness=0.008,
                color=FRUSTUM_COLOR, wxyz=rotation_to_wxyz(cam.T_world_from_cam[:3, :3]),
                position=cam.T_world_from_cam[:3, 3])
            label = scene.add_label(f"/cameras/{cam.name}/label", cam.name)
            self._static["cameras"] += [frustum, label]
        self.centre = self._scene_centre()
        if d.ground is not None:
            point, normal = d.ground
            on_plane = self.centre - ((self.centre - point) @ normal) * normal
            grid = scene.add_grid("/ground", width=6.0, height=6.0, plane="xy", cell_size=0.25, section_size=1.0,
                                  plane_color=(215, 215, 210), plane_opacity=0.5, wxyz=plane_wxyz(normal),
                                  position=on_plane)
            self._static["ground"].append(grid)
        self.cloud = scene.add_point_cloud("/cloud", np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8),
                                           point_size=CLOUD_POINT_SIZE, point_shape="circle", visible=False)
        if d.physics is not None:
            self.arrows = scene.add_arrows("/forces", np.zeros((1, 2, 3), np.float32), (0, 0, 0),
                                           shaft_radius=0.008, head_radius=0.02, head_length=0.04, visible=False)
        self._set_initial_camera(up)

    def _scene_centre(self) -> np.ndarray:
        d = self.data
        if d.body_vertices is not None:
            mid = np.asarray(d.body_vertices[d.num_frames // 2], float)
            if np.isfinite(mid).all():
                return mid.mean(0)
        if d.object_t is not None and np.isfinite(d.object_t).any():
            return np.nanmean(d.object_t, 0)
        return np.zeros(3)

    def _set_initial_camera(self, up: np.ndarray) -> None:
        """Look at the person from the first camera's side, 3.5 m away, slightly from above."""
        if self.data.cameras:
            side = self.data.cameras[0].T_world_from_cam[:3, 3] - self.centre
        else:
            side = np.array([1.0, 1.0, 0.0])
        side = side - (side @ up) * up
        side = side / max(np.linalg.norm(side), 1e-9)
        side = np.cos(np.pi / 5) * side + np.sin(np.pi / 5) * np.cross(up, side)  # between two cameras
        position = self.centre + 3.6 * side + 1.3 * up
        cam = self.server.initial_camera
        cam.fov = float(np.deg2rad(50.0))
        cam.look_at = tuple(float(x) for x in self.centre)
        cam.position = tuple(float(x) for x in position)
        cam.up = tuple(float(x) for x in up)
        self.camera_pose = {"position": position, "look_at": self.centre.copy(), "up": up.copy(), "fov": cam.fov}

    # -- gui ----------------------------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui, d = self.server.gui, self.data
        T = d.num_frames
        with gui.add_folder("Timeline"):
            self.slider = gui.add_slider("frame", min=0, max=max(T - 1, 1), step=1, initial_value=0,
                                         disabled=T < 2)
            prev_b = gui.add_button("previous")
            next_b = gui.add_button("next")
            self.play = gui.add_checkbox("play", initial_value=False)
            self.fps = gui.add_number("fps", initial_value=float(d.fps), min=0.5, max=120.0, step=0.5)
            self.info = gui.add_markdown("")
        with gui.add_folder("Layers"):
            self.toggles = {}
            for name, on in (("body", True), ("object", True), ("contact", True), ("cloud", True),
                             ("cameras", True), ("ground", True), ("forces", True)):
                self.toggles[name] = gui.add_checkbox(name, initial_value=on)
                self.toggles[name].on_update(lambda _e, n=name: self._apply_visibility(n))
        if d.notes:
            with gui.add_folder("Not shown", expand_by_default=False):
                gui.add_markdown("\n".join(f"- {n}" for n in d.notes))

        self.slider.on_update(lambda _e: self.set_frame(int(self.slider.value)))
        prev_b.on_click(lambda _e: self.step(-1))
        next_b.on_click(lambda _e: self.step(+1))

    def _apply_visibility(self, name: str) -> None:
        on = bool(self.toggles[name].value)
        for handle in self._static.get(name, []):  # cameras, ground: not per frame
            handle.visible = on
        with self._frame_lock:
            index, self.index = self.index, -1
        self.set_frame(index)  # re-applies per-frame visibility (NaN frames stay hidden)

    def step(self, delta: int) -> None:
        T = self.data.num_frames
        self.slider.value = (int(self.slider.value) + delta) % T  # triggers set_frame

    # -- frames -------------------------------------------------------------------------------------------------
    def set_frame(self, index: int) -> None:
        """Show frame `index` (0-based, like the results arrays): meshes updated in place."""
        with self._frame_lock:
            if index == self.index:
                return
            self.index = index
            src, on = self.source, {k: bool(t.value) for k, t in self.toggles.items()}
            body = src.body(index)
            pose = src.object_pose(index)
            with self.server.atomic():
                if self.body is not None:
                    self.body.visible = on["body"] and body is not None
                    if body is not None:
                        self.body.vertices = body
                    ids = src.contact_vertices(index, body) if on["contact"] else np.zeros(0, np.int64)
                    self._show_contact(body, ids)
                if self.object is not None:
                    self.object.visible = on["object"] and pose is not None
                    if pose is not None:
                        self.object.wxyz = rotation_to_wxyz(pose[0])
                        self.object.position = pose[1]
                cloud = self._cropped(src.cloud(index)) if on["cloud"] else None
                self.cloud.visible = cloud is not None and len(cloud[0]) > 0
                if self.cloud.visible:
                    self.cloud.points, self.cloud.colors = cloud
                if self.arrows is not None:
                    segs, cols = src.forces(index, body, pose)
                    self.arrows.visible = on["forces"] and len(segs) > 0
                    if len(segs):
                        self.arrows.points, self.arrows.colors = segs, cols
            self.info.content = self._info_text(index, body is not None, pose is not None)
            if int(self.slider.value) != index:
                self.slider.value = index  # its callback finds the frame shown already

    def _cropped(self, cloud):
        """The cloud near the person: within CLOUD_RADIUS_M horizontally, above the floor."""
        if cloud is None:
            return None
        points, colors = cloud
        up = self.data.ground[1] if self.data.ground is not None else np.array([0.0, 0.0, 1.0])
        rel = points - self.centre
        height = rel @ up
        keep = np.linalg.norm(rel - height[:, None] * up, axis=1) < CLOUD_RADIUS_M
        if self.data.ground is not None:
            keep &= (points - self.data.ground[0]) @ up > CLOUD_FLOOR_M
        return points[keep], colors[keep]

    def _show_contact(self, body: np.ndarray | None, ids: np.ndarray) -> None:
        faces = self.data.body_faces
        if body is None or len(ids) == 0:
            self.contact_mesh.visible = False
            return
        mark = np.zeros(len(body), bool)
        mark[ids] = True
        sub = faces[mark[faces].any(1)]
        # a patch just outside the skin (2 mm along the normals) so the tint is never hidden by the body
        lifted = body + 0.002 * vertex_normals(body, faces)
        used = np.unique(sub)
        remap = np.full(len(body), -1, np.int64)
        remap[used] = np.arange(len(used))
        self.contact_mesh.vertices = lifted[used].astype(np.float32)
        self.contact_mesh.faces = remap[sub].astype(np.uint32)
        self.contact_mesh.visible = True

    def _info_text(self, index: int, has_body: bool, has_object: bool) -> str:
        d = self.data
        parts = [f"**frame {int(d.frame_ids[index])}** ({index + 1}/{d.num_frames})"]
        if not has_body and d.body_vertices is not None:
            parts.append("body: not fitted in this frame")
        if not has_object and d.object_R is not None:
            parts.append("object: not tracked in this frame")
        if d.contact is not None:
            regions = self.source.touching_regions(index)
            parts.append("contact: " + (", ".join(regions) or "yes") if d.contact[index] else "contact: none")
        return "  \n".join(parts)

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            if bool(self.play.value) and self.data.num_frames > 1:
                t0 = time.perf_counter()
                self.step(+1)
                self._stop.wait(max(0.0, 1.0 / float(self.fps.value) - (time.perf_counter() - t0)))
            else:
                self._stop.wait(0.05)

    def _warm_clouds(self) -> None:
        try:
            self.source.warm_up()
        except Exception as exc:  # a broken session file must not take the viewer down
            log.warning("viewer: depth clouds unavailable: %s", exc)
            return
        with self._frame_lock:
            index, self.index = self.index, -1
        self.set_frame(index)  # now with the cloud
        T = self.data.num_frames
        for k in range(min(T, CLOUD_PRELOAD_FRAMES)):  # then every frame's, from the one shown on
            if self._stop.is_set():
                return
            self.source.cloud((max(index, 0) + k) % T)
        self.clouds_ready.set()

    def stop(self) -> None:
        self._stop.set()
        self.server.stop()


def serve(out_dir: str | Path, port: int = 0, session: str | Path | None = None, block: bool = True,
          verbose: bool = False, host: str = "127.0.0.1") -> Viewer:
    """Start the viewer on `host` (default this machine only) and print its URL; with block=True
    serve until Ctrl-C."""
    data = load_view_data(out_dir, session)
    viewer = Viewer(data, port=port, host=host, verbose=verbose)
    print(f"intercap view: {viewer.url}  ({data.num_frames} frames, first frame ready in "
          f"{viewer.first_frame_s:.2f} s; Ctrl-C to stop)", flush=True)
    for note in data.notes:
        print(f"  not shown: {note}", flush=True)
    if block:
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            viewer.stop()
    return viewer
