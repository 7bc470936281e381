"""One animated glTF binary (.glb) per take: the fitted body and the posed object, frame by frame,
for Blender, three.js and any glTF 2.0 viewer. Written with numpy, struct and json only.

Scene layout (names as they appear in a viewer's outline):

  world                    the root: maps the results' world frame to glTF's (+Y up, metres): the floor
                           normal turns to +Y and the floor point moves to the origin (identity when the
                           floor is unknown); its 4x4 is also in the scene's extras as `world_to_gltf`
    body_<first frame>     one mesh per run of up to `frames_per_mesh` frames; each valid frame of the run
                           is a morph target holding that frame's vertices minus the run's first valid
                           frame (the mesh's base). Its weights switch one-hot from frame to frame (STEP);
                           the node is shown (scale 1) only in its own frames and hidden (scale 0) in the
                           rest and where the body fit failed. Runs keep the morph-target count a browser's
                           WebGL can hold (three.js puts one uniform per target in the vertex shader).
    object                 translation and rotation keyframed per frame (x_world = R x_obj + t, rotation as
                           a unit quaternion x, y, z, w); frames without a valid pose hide the object and
                           hold the last valid pose (before the first valid frame, the first valid one)
      object_free          the object's mesh, blue: shown in valid frames without contact
      object_contact       the same mesh, red: shown in valid frames with body-object contact

Every channel is STEP-interpolated at the take's frame rate (time = (frame id - first id) / fps), so any
frame shows exactly that frame's results. Scene extras: fps, frame_ids, contact, body_valid,
object_valid, world_to_gltf, units. Normals are not stored: viewers derive them from the positions
(three.js shades flat). Blender's importer turns glTF's +Y up into its +Z, so the floor lies on its
ground plane; its keys are in seconds, so set the scene's frame rate to the take's (extras `fps`) to
step one captured frame per Blender frame.

Size: the body takes T * V * 3 * 4 bytes (float32 per vertex and frame; about 165 kB per frame for
anny's 13,718 vertices, so 5 MB for 30 frames, 500 MB for 3,000), plus one base mesh per
`frames_per_mesh` frames and the faces once (F * 3 * 4 bytes); everything else is small.
`export.glb` turns the file off.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

GLB_MAGIC = 0x46546C67  # "glTF"
CHUNK_JSON = 0x4E4F534A  # "JSON"
CHUNK_BIN = 0x004E4942  # "BIN\0"
FRAMES_PER_MESH = 64  # morph targets per body mesh
BODY_RGBA = (0.75, 0.75, 0.75, 1.0)
OBJECT_RGBA = (0.27, 0.43, 0.86, 1.0)
CONTACT_RGBA = (0.90, 0.12, 0.12, 1.0)

_FLOAT, _UINT32 = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


class _Builder:
    """The glTF JSON and the binary chunk's layout; the binary parts are produced when written, so a
    long take's vertices never sit in memory at once."""

    def __init__(self):
        self.doc: dict = {"asset": {"version": "2.0", "generator": "intercap export"}, "buffers": [],
                          "bufferViews": [], "accessors": [], "meshes": [], "materials": [], "nodes": [],
                          "animations": [], "scenes": [], "scene": 0}
        self.parts: list = []  # (byte offset, byte length, callable returning a contiguous array)
        self.length = 0

    def view(self, nbytes: int, produce, target: int | None = None) -> int:
        offset = self.length
        self.parts.append((offset, nbytes, produce))
        self.length = offset + nbytes + (-nbytes) % 4  # every view starts 4-byte aligned
        view = {"buffer": 0, "byteOffset": offset, "byteLength": nbytes}
        if target is not None:
            view["target"] = target
        self.doc["bufferViews"].append(view)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, shape: tuple, component: int, produce, target: int | None = None, bounds=None) -> int:
        """An accessor over (count, n) float32 or uint32 values that `produce()` returns; bounds
        (min, max) per component where the format needs them (positions, animation times)."""
        count, n = shape
        kind = {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[n]
        acc = {"bufferView": self.view(count * n * 4, produce, target), "componentType": component,
               "count": int(count), "type": kind}
        if bounds is not None:
            acc["min"], acc["max"] = ([float(x) for x in np.atleast_1d(b)] for b in bounds)
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def array(self, values: np.ndarray, target: int | None = None, bounds: bool = False) -> int:
        """An accessor holding `values` (float -> float32, int -> uint32), shaped (count,) or (count, n)."""
        values = np.ascontiguousarray(values, np.uint32 if np.issubdtype(np.asarray(values).dtype, np.integer)
                                      else np.float32)
        flat = values.reshape(len(values), -1)
        component = _UINT32 if values.dtype == np.uint32 else _FLOAT
        b = (flat.min(0), flat.max(0)) if bounds else None
        return self.accessor(flat.shape, component, lambda: values, target, b)

    def add(self, kind: str, item: dict) -> int:
        self.doc[kind].append(item)
        return len(self.doc[kind]) - 1

    def write(self, path: Path) -> int:
        """The .glb at `path` (through a temporary file beside it); returns its size in bytes."""
        from intercap.io.files import atomic_file

        self.doc["buffers"] = [{"byteLength": self.length}] if self.length else []
        doc = {k: v for k, v in self.doc.items() if v != []}  # the format wants no empty arrays
        text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
        text += b" " * ((-len(text)) % 4)
        total = 12 + 8 + len(text) + (8 + self.length if self.length else 0)
        with atomic_file(path, ".glb") as tmp, open(tmp, "wb") as f:
            f.write(struct.pack("<III", GLB_MAGIC, 2, total))
            f.write(struct.pack("<II", len(text), CHUNK_JSON) + text)
            if not self.length:
                return total
            f.write(struct.pack("<II", self.length, CHUNK_BIN))
            written = 0
            for offset, nbytes, produce in self.parts:
                f.write(b"\0" * (offset - written))
                data = np.ascontiguousarray(produce()).tobytes()
                if len(data) != nbytes:
                    raise RuntimeError(f"glb: a part of {len(data)} bytes where {nbytes} were laid out")
                f.write(data)
                written = offset + nbytes
            f.write(b"\0" * (self.length - written))
        return total


def world_to_gltf(ground_point=None, ground_normal=None) -> np.ndarray:
    """4x4 from the results' world to glTF's frame: the floor normal to +Y (the shortest turn), the
    floor point to the origin; the identity without a (finite) floor."""
    M = np.eye(4)
    if ground_point is None or ground_normal is None:
        return M
    p, n = np.asarray(ground_point, float), np.asarray(ground_normal, float)
    if not (np.isfinite(p).all() and np.isfinite(n).all()) or np.linalg.norm(n) == 0:
        return M
    n = n / np.linalg.norm(n)
    y = np.array([0.0, 1.0, 0.0])
    axis, c = np.cross(n, y), float(n @ y)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        A = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])  # already up, or upside down: half a turn about x
    else:
        k = axis / s
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        A = np.eye(3) + s * K + (1 - c) * K @ K  # Rodrigues
    M[:3, :3], M[:3, 3] = A, -A @ p
    return M


def quaternions(R: np.ndarray) -> np.ndarray:
    """(T, 4) unit quaternions (x, y, z, w) of rotations (T, 3, 3), each on the side of the previous."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(R, np.float64)).as_quat() if len(R) else np.zeros((0, 4))
    for i in range(1, len(q)):
        if q[i] @ q[i - 1] < 0:
            q[i] = -q[i]
    return q


def _held(valid: np.ndarray) -> np.ndarray:
    """(T,) for each frame the index of the last valid frame at or before it; before the first valid
    frame, the first valid one."""
    idx = np.where(valid, np.arange(len(valid)), -1)
    last = np.maximum.accumulate(idx) if len(idx) else idx
    return np.where(last < 0, int(np.argmax(valid)), last)


def _visibility(builder: _Builder, shown: np.ndarray, times: np.ndarray) -> tuple[dict, list]:
    """A STEP scale sampler (1 where `shown`, else 0) keyed only where visibility changes, and the
    node's rest scale (its first frame's)."""
    keys = np.r_[0, np.flatnonzero(shown[1:] != shown[:-1]) + 1]
    scale = np.repeat(shown[keys].astype(np.float32)[:, None], 3, 1)
    sampler = {"input": builder.array(times[keys], bounds=True), "output": builder.array(scale),
               "interpolation": "STEP"}
    return sampler, [float(shown[0])] * 3


def write_glb(path, fps: float, frame_ids, body_vertices=None, body_faces=None, body_valid=None,
              object_vertices=None, object_faces=None, R=None, t=None, object_valid=None, contact=None,
              ground_point=None, ground_normal=None, frames_per_mesh: int = FRAMES_PER_MESH) -> dict:
    """Write the take as one animated .glb (layout in the module's docstring); returns figures.

    body_vertices (T, V, 3) world metres (may be memory-mapped), body_faces (F, 3); R (T, 3, 3), t (T, 3)
    object -> world with the object mesh (K, 3), (M, 3) in object coordinates; *_valid (T,) bool
    (a frame is shown where it is True and the values are finite); contact (T,) bool; the floor
    (point, normal) sets which way is up."""
    frame_ids = np.asarray(frame_ids, np.int64)
    T = len(frame_ids)
    if T == 0:
        raise ValueError("glb: no frames")
    times = ((frame_ids - frame_ids[0]) / float(fps)).astype(np.float32)
    contact = np.zeros(T, bool) if contact is None else np.asarray(contact, bool)
    b = _Builder()
    channels, samplers, children = [], [], []

    def animate(node: int, path_name: str, sampler: dict) -> None:
        samplers.append(sampler)
        channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path_name}})

    def material(name: str, rgba) -> int:
        return b.add("materials", {"name": name, "pbrMetallicRoughness": {"baseColorFactor": list(rgba),
                                   "metallicFactor": 0.0, "roughnessFactor": 0.8}})

    has_body = body_vertices is not None and body_faces is not None
    ok_body = np.zeros(T, bool)
    if has_body:
        if len(body_vertices) != T:
            raise ValueError(f"glb: {len(body_vertices)} body frames for {T} frame ids")
        ok_body = np.array([np.isfinite(np.asarray(body_vertices[i])).all() for i in range(T)], bool)
        if body_valid is not None:
            ok_body &= np.asarray(body_valid, bool)
        body_indices = body_material = None
        for start in range(0, T, frames_per_mesh):
            run = np.arange(start, min(start + frames_per_mesh, T))
            frames = run[ok_body[run]]
            if not len(frames):
                continue
            if body_indices is None:  # shared by every body mesh
                body_indices = b.array(np.asarray(body_faces, np.uint32).reshape(-1), _ELEMENT_ARRAY_BUFFER)
                body_material = material("body", BODY_RGBA)
            base = np.asarray(body_vertices[frames[0]], np.float32)
            V = len(base)
            targets = []
            for k in frames:
                delta = (lambda k=k, base=base: np.asarray(body_vertices[k], np.float32) - base)
                d = delta()
                targets.append({"POSITION": b.accessor((V, 3), _FLOAT, delta, _ARRAY_BUFFER, (d.min(0), d.max(0)))})
            position = b.accessor((V, 3), _FLOAT, lambda base=base: base, _ARRAY_BUFFER, (base.min(0), base.max(0)))
            weights = np.zeros((len(run), len(frames)), np.float32)  # one-hot per frame of the run, STEP
            weights[np.searchsorted(run, frames), np.arange(len(frames))] = 1.0
            mesh = b.add("meshes", {"name": f"body_{int(frame_ids[start]):06d}",
                                    "primitives": [{"attributes": {"POSITION": position}, "indices": body_indices,
                                                    "material": body_material, "mode": 4, "targets": targets}],
                                    "weights": weights[np.searchsorted(run, frames[0])].tolist(),
                                    "extras": {"targetNames": [f"frame_{int(frame_ids[k]):06d}" for k in frames]}})
            shown = np.zeros(T, bool)
            shown[run] = ok_body[run]
            scale_sampler, rest = _visibility(b, shown, times)
            node = b.add("nodes", {"name": f"body_{int(frame_ids[start]):06d}", "mesh": mesh, "scale": rest})
            children.append(node)
            animate(node, "weights", {"input": b.array(times[run], bounds=True),
                                      "output": b.array(weights.reshape(-1)), "interpolation": "STEP"})
            animate(node, "scale", scale_sampler)

    has_object = object_vertices is not None and object_faces is not None and R is not None and t is not None
    ok_obj = np.zeros(T, bool)
    if has_object:
        R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
        ok_obj = np.isfinite(R).all((1, 2)) & np.isfinite(t).all(1)
        if object_valid is not None:
            ok_obj &= np.asarray(object_valid, bool)
    if has_object and ok_obj.any():
        held = _held(ok_obj)
        q, trans = quaternions(R[held]), t[held]
        ov = np.asarray(object_vertices, np.float32)
        mesh_prim = {"attributes": {"POSITION": b.array(ov, _ARRAY_BUFFER, bounds=True)},
                     "indices": b.array(np.asarray(object_faces, np.uint32).reshape(-1), _ELEMENT_ARRAY_BUFFER),
                     "mode": 4}
        kids = []
        for name, rgba, shown in (("object_free", OBJECT_RGBA, ok_obj & ~contact),
                                  ("object_contact", CONTACT_RGBA, ok_obj & contact)):
            mesh = b.add("meshes", {"name": name, "primitives": [{**mesh_prim, "material": material(name, rgba)}]})
            scale_sampler, rest = _visibility(b, shown, times)
            kid = b.add("nodes", {"name": name, "mesh": mesh, "scale": rest})
            animate(kid, "scale", scale_sampler)
            kids.append(kid)
        node = b.add("nodes", {"name": "object", "children": kids, "translation": trans[0].tolist(),
                               "rotation": q[0].tolist()})
        children.append(node)
        all_times = b.array(times, bounds=True)
        animate(node, "translation", {"input": all_times, "output": b.array(trans), "interpolation": "STEP"})
        animate(node, "rotation", {"input": all_times, "output": b.array(q), "interpolation": "STEP"})

    M = world_to_gltf(ground_point, ground_normal)
    root = {"name": "world"}
    if children:
        root["children"] = children
    if not np.array_equal(M, np.eye(4)):
        root["matrix"] = M.T.reshape(-1).tolist()  # column-major
    root = b.add("nodes", root)
    b.doc["scenes"] = [{"name": "take", "nodes": [root], "extras": {
        "fps": float(fps), "frame_ids": frame_ids.tolist(), "contact": contact.tolist(),
        "body_valid": ok_body.tolist(), "object_valid": ok_obj.tolist(),
        "world_to_gltf": M.tolist(), "units": "metres"}}]
    if channels:
        b.doc["animations"] = [{"name": "take", "channels": channels, "samplers": samplers}]
    size = b.write(Path(path))
    return {"glb": str(path), "glb_bytes": int(size), "glb_body_frames": int(ok_body.sum()),
            "glb_object_frames": int(ok_obj.sum())}


def write_session_glb(session, res: dict, out_dir: Path) -> dict:
    """OUT/export/<session name>.glb from the export stage's loaded results (`load_results`)."""
    obj = session.object
    mesh = obj.load_mesh() if obj is not None and res["object"] is not None else None
    point = normal = None
    if res["ground"] is not None:
        point, normal = res["ground"].get("point"), res["ground"].get("normal")
    elif session.ground is not None:
        point, normal = session.ground
    poses = res["object"] if mesh is not None else None
    return write_glb(Path(out_dir) / "export" / f"{Path(session.root).name}.glb", session.fps, session.frame_ids,
                     body_vertices=res["body_vertices"], body_faces=res["body_faces"],
                     object_vertices=None if mesh is None else mesh.vertices,
                     object_faces=None if mesh is None else mesh.faces,
                     R=None if poses is None else poses["R"], t=None if poses is None else poses["t"],
                     object_valid=None if poses is None or "valid" not in poses else poses["valid"],
                     contact=res["contact"], ground_point=point, ground_normal=normal)
