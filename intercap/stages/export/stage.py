"""The `export` stage: meshes per frame, one self-describing dataset file, and
optionally a BEHAVE-style folder, from the final results at OUT/.

Reads (the results folder of docs/outputs.md): body_vertices.npy, body_faces.npy,
body_params.npz, object_poses.npz, contact.npy, contact/contact.npz,
prepare/ground.json and physics/physics.npz; each is optional (what is absent
is left out and said so), but at least the body or the object must be there.

Writes
  OUT/meshes/body_<frame id:06d>.ply    the fitted body, world frame, metres
  OUT/meshes/object_<frame id:06d>.ply  the session's object mesh posed by R, t (x_world = R x_obj + t)
  OUT/meshes/scene_<frame id:06d>.ply   (export.scene) both in one mesh, body vertices first; in contact
                                        frames the vertices within export.contact_distance_m of the other
                                        surface are red, the rest of the body grey, the object blue
  OUT/export/<session name>.npz         the dataset file (keys in `dataset_arrays`)
  OUT/export/behave/...                 (export.behave) BEHAVE's layout (see `write_behave`)
Frames whose body (object) result holds NaN get no body (object, scene) mesh;
they are counted in the stage's figures. Mesh vertices are float32, exactly
the results arrays' values (body) or float32(R @ x + t) computed in float64 (object).
"""
from __future__ import annotations

import logging
import pickle
from pathlib import Path

import numpy as np
from tqdm import tqdm

from intercap.io.files import read_json, save_npz, write_json
from intercap.io.ply import write_mesh_ply

log = logging.getLogger(__name__)

BODY_GREY = (200, 200, 200)
OBJECT_BLUE = (70, 110, 220)
CONTACT_RED = (230, 30, 30)


class ExportError(RuntimeError):
    pass


# -- reading the results ----------------------------------------------------------------------
def _load_npz(path: Path) -> dict | None:
    if not path.exists():
        return None
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def load_results(out_dir: Path, T: int) -> dict:
    """The final results at OUT/ as arrays (None where a file is absent); rows checked against T frames."""
    out_dir = Path(out_dir)
    res: dict = {}
    vpath, fpath = out_dir / "body_vertices.npy", out_dir / "body_faces.npy"
    res["body_vertices"] = np.load(vpath, mmap_mode="r") if vpath.exists() else None
    res["body_faces"] = np.load(fpath) if fpath.exists() else None
    if (res["body_vertices"] is None) != (res["body_faces"] is None):
        raise ExportError(f"{vpath if res['body_vertices'] is None else fpath} missing while its partner exists")
    res["body_params"] = _load_npz(out_dir / "body_params.npz")
    res["object"] = _load_npz(out_dir / "object_poses.npz")
    cpath = out_dir / "contact.npy"
    res["contact"] = np.load(cpath) if cpath.exists() else None
    res["contact_detail"] = _load_npz(out_dir / "contact" / "contact.npz")
    gpath = out_dir / "prepare" / "ground.json"
    res["ground"] = read_json(gpath) if gpath.exists() else None
    res["physics"] = _load_npz(out_dir / "physics" / "physics.npz")
    kpath = out_dir / "keypoints3d.npy"
    res["keypoints3d"] = np.load(kpath) if kpath.exists() else None
    for name, rows in (("body_vertices", res["body_vertices"]), ("contact", res["contact"]),
                       ("keypoints3d", res["keypoints3d"]),
                       ("object_poses.npz R", None if res["object"] is None else res["object"].get("R"))):
        if rows is not None and len(rows) != T:
            raise ExportError(f"{out_dir}: {name} has {len(rows)} frames, the session {T}; rerun the stages")
    if res["object"] is not None and ("R" not in res["object"] or "t" not in res["object"]):
        raise ExportError(f"{out_dir / 'object_poses.npz'}: needs arrays R (T, 3, 3) and t (T, 3)")
    return res


def object_valid(obj: dict | None, T: int) -> np.ndarray:
    """(T,) frames with a finite object pose (and valid=True where the file says)."""
    if obj is None:
        return np.zeros(T, bool)
    ok = np.isfinite(obj["R"]).all((1, 2)) & np.isfinite(obj["t"]).all(1)
    if "valid" in obj:
        ok &= np.asarray(obj["valid"], bool)
    return ok


def body_valid(vertices, T: int) -> np.ndarray:
    """(T,) frames whose body vertices are all finite."""
    if vertices is None:
        return np.zeros(T, bool)
    return np.array([np.isfinite(vertices[i]).all() for i in range(T)], bool) if T else np.zeros(0, bool)


def pose_object(vertices: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Object vertices (K, 3) posed in world per frame: (T, K, 3) float64, x_world = R x + t."""
    return np.einsum("tij,kj->tki", np.asarray(R, np.float64), np.asarray(vertices, np.float64)) + np.asarray(t)[:, None]


def contact_vertices(body: np.ndarray, obj_posed: np.ndarray, obj_surface, R, t, distance_m: float):
    """Which body vertices (V,) lie within distance_m of the object surface, and which object
    vertices (K,) lie within distance_m of a body vertex (body vertices stand for its surface)."""
    from scipy.spatial import cKDTree

    local = (np.asarray(body, np.float64) - t) @ R  # world -> object coordinates, (V, 3)
    lo, hi = obj_surface.vertices.min(0) - distance_m, obj_surface.vertices.max(0) + distance_m
    near_body = ((local >= lo) & (local <= hi)).all(1)  # only vertices in the grown bounding box can be near
    if near_body.any():
        near_body[near_body] = obj_surface.closest(local[near_body])[0] <= distance_m
    near_obj = np.isfinite(cKDTree(np.asarray(body, np.float64)).query(obj_posed, 1, distance_upper_bound=distance_m)[0])
    return near_body, near_obj


# -- the dataset file -------------------------------------------------------------------------
def _add_body(a: dict, session, res: dict, T: int, float16: bool) -> None:
    """body_model and, with a body fit, body_valid, body_vertices, body_faces and body_param_*."""
    params = res["body_params"] or {}
    model = str(params.get("model", session.body_model)) if res["body_vertices"] is not None else ""
    a["body_model"] = np.array(model)
    if res["body_vertices"] is not None:
        verts = np.asarray(res["body_vertices"])
        a["body_valid"] = body_valid(verts, T)
        a["body_vertices"] = verts.astype(np.float16 if float16 else np.float32)
        a["body_faces"] = np.asarray(res["body_faces"], np.int32)
        for k, v in params.items():
            if k != "model":
                a[f"body_param_{k}"] = v
    if res.get("joints3d") is not None:
        a["joints3d"] = np.asarray(res["joints3d"], np.float32)
        a["joint_names"] = np.asarray(res["joint_names"], str)
    for k, v in (res.get("smplx") or {}).items():
        a[f"smplx_{k}"] = np.asarray(v, np.float32)
    if res.get("keypoints3d") is not None:
        from intercap.body_models.keypoints import KEYPOINT_NAMES

        a["keypoints3d"] = np.asarray(res["keypoints3d"], np.float32)
        a["keypoint_names"] = np.asarray(KEYPOINT_NAMES[:a["keypoints3d"].shape[1]], str)


def _add_object(a: dict, session, res: dict, T: int) -> None:
    """object_name and, with an object, its mesh and poses."""
    obj = session.object
    a["object_name"] = np.array(obj.name if obj is not None else "")
    if obj is not None:
        mesh = obj.load_mesh()
        a["object_vertices"] = np.asarray(mesh.vertices, np.float64)
        a["object_faces"] = np.asarray(mesh.faces, np.int32)
    if res["object"] is not None:
        a["object_R"] = np.asarray(res["object"]["R"], np.float64)
        a["object_t"] = np.asarray(res["object"]["t"], np.float64)
        a["object_valid"] = object_valid(res["object"], T)


def _add_contact(a: dict, res: dict, T: int) -> None:
    """contact and the contact stage's per-region labels, when it has run."""
    if res["contact"] is not None:
        a["contact"] = np.asarray(res["contact"], bool)
    detail = res["contact_detail"]
    if detail is not None:
        a["contact_method"] = np.array(str(detail.get("method", "")))
        a["contact_region_names"] = np.asarray(detail.get("region_names", np.array([], str)), str)
        a["contact_regions"] = np.asarray(detail.get("region_contact", np.zeros((T, 0))), bool)
        a["contact_region_distance_m"] = np.asarray(detail.get("region_distance_m", np.zeros((T, 0))), np.float64)
        if "contact" not in a and "contact" in detail:
            a["contact"] = np.asarray(detail["contact"], bool)


def _add_cameras(a: dict, session) -> None:
    """camera_names, camera_sizes, camera_K, camera_dist (zero-padded to 8) and camera_T_world_from_cam."""
    cams = session.cameras
    a["camera_names"] = np.array([c.name for c in cams])
    a["camera_sizes"] = np.array([[c.width, c.height] for c in cams], np.int64).reshape(-1, 2)
    a["camera_K"] = np.stack([np.asarray(c.K, np.float64) for c in cams])
    dist = np.zeros((len(cams), 8))
    for i, c in enumerate(cams):
        dist[i, :len(c.dist)] = c.dist
    a["camera_dist"] = dist
    a["camera_T_world_from_cam"] = np.stack([np.asarray(c.T_world_from_cam, np.float64) for c in cams])


def _add_ground(a: dict, session, res: dict) -> None:
    """ground_point and ground_normal: OUT/prepare/ground.json, else session.yaml, else NaN."""
    point, normal = np.full(3, np.nan), np.full(3, np.nan)
    if res["ground"] is not None:
        point, normal = np.asarray(res["ground"]["point"], float), np.asarray(res["ground"]["normal"], float)
    elif session.ground is not None:
        point, normal = (np.asarray(v, float) for v in session.ground)
    a["ground_point"], a["ground_normal"] = point, normal


def dataset_arrays(session, res: dict, float16: bool = False, provenance: dict | None = None) -> dict[str, np.ndarray]:
    """Everything a downstream user needs, as named arrays (the keys of OUT/export/<session>.npz).

    Frames: row i of every per-frame array is frame `frame_ids[i]` (T rows, one per session frame,
    NaN / valid False where a stage failed). World frame: the session's calibration world, metres,
    right-handed; cameras are OpenCV's (x right, y down, z forward).

    session_name ()              str, the session folder's name
    frame_ids (T,)               int64, the session's frame indices (its 6-digit file names)
    times_s (T,)                 float64, frame_ids / fps, seconds since frame 0
    fps ()                       float64, frames per second of the session
    body_model ()                str, "anny" or "smplx" (the model that body_param_* drive); "" without a body
    body_valid (T,)              bool, the body fit is finite in this frame
    body_vertices (T, V, 3)      float32 (float16 with export.vertices_float16), world, metres
    body_faces (F, 3)            int32, triangles of body_vertices (counter-clockwise seen from outside)
    body_param_<name> (T, ...)   every per-frame array of OUT/body_params.npz, unchanged (anny: shape (T, 6)
                                 phenotype in [0, 1], global_orient (T, 3) and the poses (T, J, 3) axis-angle
                                 radians, transl (T, 3) metres, expression (T, 52)); and body_param_shape_mean.
                                 Our convention: world = R(global_orient) @ v_model + transl, rotating about
                                 the model's origin (for SMPL-X use the smplx_* keys below)
    joints3d (T, J, 3)           float32, world, metres: the body model's skeleton joints of the fit (NaN where
                                 body_valid is False)
    joint_names (J,)             str, the body model's joint names, in joints3d's order
    keypoints3d (T, 67, 3)       float32, world: BODY_25 + left hand 21 + right hand 21 of the fit (OUT/keypoints3d.npy)
    keypoint_names (67,)         str, OpenPose names of keypoints3d's rows ("nose", ..., "left_hand_wrist", ...)
    smplx_<name> (T, ...)        float32, body_model "smplx" only: smplx's own forward arguments reproducing
                                 body_vertices: smplx_betas, smplx_global_orient, smplx_transl, smplx_body_pose
                                 (T, 63), smplx_jaw_pose, smplx_leye_pose, smplx_reye_pose, smplx_left_hand_pose,
                                 smplx_right_hand_pose (T, 45), smplx_expression; for smplx.create(model_type=
                                 "smplx", use_pca=False, flat_hand_mean=True, num_betas, num_expression_coeffs
                                 as their widths). smplx rotates about the pelvis, so smplx_transl =
                                 transl + R @ pelvis - pelvis (pelvis: the shaped rest pose's root joint)
    object_name ()               str, session.yaml's object name; "" for body-only sessions
    object_vertices (K, 3)       float64, the object mesh as stored in the session, object coordinates, metres
    object_faces (M, 3)          int32
    object_R (T, 3, 3)           float64, object -> world rotation: x_world = object_R @ x_obj + object_t
    object_t (T, 3)              float64, metres
    object_valid (T,)            bool, finite (and trusted) object pose
    contact (T,)                 bool, body-object contact per frame (OUT/contact.npy)
    contact_method ()            str, how contact was decided ("annotated", "3d", "2d", ...)
    contact_region_names (R,)    str, the body model's contact regions
    contact_regions (T, R)       bool, which regions touch the object per frame
    contact_region_distance_m (T, R)  float64, each region's distance to the object surface (NaN: no fit)
    camera_names (C,)            str
    camera_sizes (C, 2)          int64, (width, height) pixels
    camera_K (C, 3, 3)           float64, intrinsics of the colour image (depth is registered to it)
    camera_dist (C, 8)           float64, OpenCV distortion (k1, k2, p1, p2, k3, k4, k5, k6), zero-padded
    camera_T_world_from_cam (C, 4, 4)  float64, camera pose: x_world = T @ [x_cam, 1]
    ground_point (3,)            float64, a point on the floor plane
    ground_normal (3,)           float64, the floor plane's unit normal (normal points up, to the person's
                                 side; gravity = -normal): OUT/prepare/ground.json, else session.yaml, else NaN
    physics_<key>                every array of OUT/physics/physics.npz when the physics stage has run
                                 (SI units, world frame; keys in docs/outputs.md)
    intercap_version ()          str, the intercap that wrote the file
    torch_version ()             str
    body_model_version ()        str, the body model's package and version ("anny 0.6.2"); "" without a body
    config_hash ()               str, first 16 hex digits of the sha256 of the run's OUT/config.yaml
    command_line ()              str, the command that ran the export (shell-quoted argv)
    Absent results give absent keys (no body: no body_*, joints3d; no contact stage: no contact*)."""
    T = session.num_frames
    frame_ids = np.asarray(session.frame_ids, np.int64)
    a: dict[str, np.ndarray] = {
        "session_name": np.array(Path(session.root).name),
        "frame_ids": frame_ids,
        "times_s": frame_ids / float(session.fps),
        "fps": np.array(float(session.fps)),
    }
    _add_body(a, session, res, T, float16)
    _add_object(a, session, res, T)
    _add_contact(a, res, T)
    _add_cameras(a, session)
    _add_ground(a, session, res)
    for k, v in (res["physics"] or {}).items():
        a[f"physics_{k}"] = v
    for k, v in (provenance or {}).items():
        a[k] = np.array(str(v))
    return a


def provenance(out_dir: Path, cfg, body_model: str) -> dict[str, str]:
    """What made the dataset file (its provenance keys)."""
    import hashlib
    import shlex
    import sys
    from importlib import metadata

    import torch

    from intercap import __version__
    from intercap.config import config_to_dict

    path = Path(out_dir) / "config.yaml"
    if path.is_file():
        config = path.read_bytes()
    else:
        import yaml

        config = yaml.safe_dump(config_to_dict(cfg), sort_keys=False).encode()
    version = ""
    if body_model:
        try:
            version = f"{body_model} {metadata.version(body_model)}"
        except metadata.PackageNotFoundError:
            version = body_model
    return {"intercap_version": __version__, "torch_version": torch.__version__, "body_model_version": version,
            "config_hash": hashlib.sha256(config).hexdigest()[:16], "command_line": shlex.join(sys.argv)}


def body_model_arrays(res: dict, cfg, T: int) -> None:
    """Add to `res` what the body model gives from OUT/body_params.npz: `joints3d` (T, J, 3) with
    `joint_names`, and for SMPL-X `smplx` (its own forward arguments). Frames without a fit stay NaN.
    Left out, with a warning, when the parameters are not the configured model's."""
    params = res["body_params"]
    if params is None or res["body_vertices"] is None:
        return
    import torch

    from intercap.body_models import BodyParams, shared_model
    from intercap.body_models.base import PARAM_FIELDS

    missing = [k for k in PARAM_FIELDS if k not in params]
    if missing:
        log.warning("export: body_params.npz lacks %s: no joints3d", ", ".join(missing))
        return

    name = str(params.get("model", cfg.body_model.name))
    if name != cfg.body_model.name:
        log.warning("export: body_params.npz is of %s, the config's body model %s: no joints3d", name,
                    cfg.body_model.name)
        return
    try:
        model = shared_model(cfg.body_model)
    except (ImportError, FileNotFoundError) as exc:
        log.warning("export: body model %s not available (%s): no joints3d", name, exc)
        return
    ok = body_valid(res["body_vertices"], T)
    joints = np.full((T, len(model.joint_names), 3), np.nan, np.float32)
    smplx_arrays: dict[str, np.ndarray] = {}
    worst = 0.0
    with torch.no_grad():
        for s in range(0, T, 16):
            idx = np.arange(s, min(s + 16, T))
            idx = idx[ok[idx]]
            if not len(idx):
                continue
            batch = BodyParams.from_numpy_dict({k: np.asarray(params[k])[idx] for k in PARAM_FIELDS}, dtype=model.dtype)
            out = model(batch)
            joints[idx] = out.joints.cpu().numpy()
            worst = max(worst, float(np.abs(out.vertices.cpu().numpy() - np.asarray(res["body_vertices"][idx])).max()))
            if hasattr(model, "smplx_parameters"):
                for k, v in model.smplx_parameters(batch).items():
                    if k not in smplx_arrays:
                        smplx_arrays[k] = np.full((T, *v.shape[1:]), np.nan, np.float32)
                    smplx_arrays[k][idx] = v.cpu().numpy()
    if worst > 1e-3:
        log.warning("export: body_params.npz gives vertices up to %.1f mm from body_vertices.npy; joints3d follow "
                    "the parameters", worst * 1000)
    res["joints3d"], res["joint_names"] = joints, list(model.joint_names)
    if smplx_arrays:
        res["smplx"] = smplx_arrays


# -- BEHAVE-style folders ---------------------------------------------------------------------
# body_params.npz arrays of the whole take, not per frame (one with as many entries as the take has
# frames must not be cut into frames)
SEQUENCE_PARAMS = ("model", "shape_mean")


def behave_frame_name(seconds: float) -> str:
    """BEHAVE's frame folder name: 't' + seconds with 3 decimals, 8 characters wide ('t0003.000')."""
    return f"t{seconds:08.3f}"


def behave_frame_names(session) -> list[str]:
    """Each session frame's BEHAVE folder name: a session imported from BEHAVE keeps its
    source folders (behave_frames.json), so the export lines up with the sequence it came
    from; other frames are named by time: the first source folder's time + frame / fps."""
    source = Path(session.root) / "behave_frames.json"
    known, t0 = {}, 0.0
    if source.is_file():
        frames = read_json(source).get("frames", [])
        known = {int(f["frame"]): str(f["folder"]) for f in frames}
        t0 = min((float(f["time_s"]) - int(f["frame"]) / float(session.fps) for f in frames), default=0.0)
    return [known.get(int(i)) or behave_frame_name(t0 + float(i) / float(session.fps)) for i in session.frame_ids]


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations -> (T, 3) axis-angle (radians x unit axis)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, np.float64)).as_rotvec()


def behave_object_params(R, t, template_center, A=np.eye(3), b=np.zeros(3)):
    """BEHAVE's (angle (T, 3), trans (T, 3)) for our poses: BEHAVE poses the template centred on the
    mean of its vertices, x_out = rotvec(angle) @ (x_obj - center) + trans; (A, b) maps world to the
    export frame. So angle = rotvec(A R), trans = A (R center + t) + b."""
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    AR = np.einsum("ij,tjk->tik", A, R)
    trans = (np.einsum("tij,j->ti", R, template_center) + t) @ A.T + b
    return rotvec_from_matrix(AR), trans


def write_behave(session, res: dict, out_dir: Path, frame_name: str = "world", progress: bool = True) -> dict:
    """BEHAVE's layout under OUT/export/behave/:

      objects/<obj>/<obj>.ply                       the object template, centred: x - mean(vertices)
      sequences/<session>/info.json                 {"cat": <obj>, "kinects": [...], "gender": null, ...}
      sequences/<session>/t{s:08.3f}/person/fit02/person_fit.ply   the body mesh
      sequences/<session>/t{s:08.3f}/person/fit02/person_fit.pkl   {"pose", "betas", "trans", "model", all params}
      sequences/<session>/t{s:08.3f}/<obj>/fit01/<obj>_fit.ply     the posed object
      sequences/<session>/t{s:08.3f}/<obj>/fit01/<obj>_fit.pkl     {"angle": (3,), "trans": (3,)}
    Frame folders are named by seconds = frame id / fps, or as the BEHAVE sequence the session
    was imported from names them (behave_frame_names). Object parameters follow BEHAVE's
    parse_obj_pose: v = Rotation.from_rotvec(angle).as_matrix() @ (x - template mean) + trans, so
    loading the centred template above and applying angle, trans gives <obj>_fit.ply. Meshes and
    parameters are in our world frame, or (frame_name = a camera's name) in that camera's frame, as
    BEHAVE stores its fits in camera k1's colour frame. Person "pose" is global_orient followed by
    every pose array flattened, "betas" the shape, "trans" transl: SMPL-H-compatible only in layout;
    with anny they drive anny (the "model" key says which)."""
    root = Path(out_dir) / "export" / "behave"
    seq = root / "sequences" / Path(session.root).name
    A, b = np.eye(3), np.zeros(3)
    if frame_name != "world":
        names = [c.name for c in session.cameras]
        if frame_name not in names:
            raise ExportError(f"export.behave_frame: {frame_name!r} is neither 'world' nor a camera ({', '.join(names)})")
        T_cw = session.camera(frame_name).T_cam_from_world
        A, b = T_cw[:3, :3], T_cw[:3, 3]
    T = session.num_frames
    ok_body = body_valid(res["body_vertices"], T)
    ok_obj = object_valid(res["object"], T) if session.object is not None else np.zeros(T, bool)
    obj_name = session.object.name.replace("/", "_").replace(" ", "_") if session.object is not None else None
    write_json(seq / "info.json", {"cat": obj_name, "gender": None, "kinects": list(range(session.num_cameras)),
                                   "config": None, "intrinsic": None, "empty": None, "beta": None,
                                   "frame": frame_name, "exported_by": "intercap"})
    if obj_name is not None:
        mesh = session.object.load_mesh()
        center = np.asarray(mesh.vertices, np.float64).mean(0)
        write_mesh_ply(root / "objects" / obj_name / f"{obj_name}.ply", np.asarray(mesh.vertices) - center, mesh.faces)
        if ok_obj.any():
            R = np.where(ok_obj[:, None, None], res["object"]["R"], np.eye(3))  # (T, 3, 3), failed frames unused
            t = np.where(ok_obj[:, None], res["object"]["t"], 0.0)
            angle, trans = behave_object_params(R, t, center, A, b)
            posed = pose_object(mesh.vertices, R, t) @ A.T + b
    params = res["body_params"] or {}
    per_frame = {k: v for k, v in params.items() if k not in SEQUENCE_PARAMS and getattr(v, "ndim", 0) >= 1
                 and len(v) == T and k not in ("valid", "frame_ids")}
    pose_keys = ["global_orient"] + sorted(k for k in per_frame if k.endswith("pose"))
    folder_names = behave_frame_names(session)
    for i in tqdm(range(T), desc="export behave", unit="frame", disable=not progress):
        folder = seq / folder_names[i]
        if ok_body[i]:
            verts = np.asarray(res["body_vertices"][i], np.float64) @ A.T + b
            write_mesh_ply(folder / "person" / "fit02" / "person_fit.ply", verts, res["body_faces"])
            p = {k: np.asarray(v[i]) for k, v in per_frame.items()}
            fit = {"model": str(params.get("model", session.body_model)), **p, "frame": frame_name}
            if all(k in p for k in pose_keys):
                fit["pose"] = np.concatenate([p[k].reshape(-1) for k in pose_keys])
            if "shape" in p:
                fit["betas"] = p["shape"]
            if "shape_mean" in params:  # the take's one shape, whole in every frame's file
                fit["shape_mean"] = np.asarray(params["shape_mean"])
            if "transl" in p:
                fit["trans"] = p["transl"]
            _write_pickle(folder / "person" / "fit02" / "person_fit.pkl", fit)
        if ok_obj[i]:
            write_mesh_ply(folder / obj_name / "fit01" / f"{obj_name}_fit.ply", posed[i], mesh.faces)
            _write_pickle(folder / obj_name / "fit01" / f"{obj_name}_fit.pkl",
                          {"angle": angle[i].astype(np.float64), "trans": trans[i].astype(np.float64)})
    return {"behave_folder": str(seq), "behave_frames": int((ok_body | ok_obj).sum())}


def _write_pickle(path: Path, data: dict) -> None:
    from intercap.io.files import atomic_file

    with atomic_file(path, ".pkl") as tmp, open(tmp, "wb") as f:
        pickle.dump(data, f, protocol=4)


# -- the stage --------------------------------------------------------------------------------
def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `export` stage: OUT/meshes/*.ply, OUT/export/<session>.npz, optionally OUT/export/behave/."""
    from intercap.geometry.surfaces import TriangleSurface

    ecfg = cfg.export
    out_dir = Path(out_dir)
    T = session.num_frames
    res = load_results(out_dir, T)
    if res["body_vertices"] is None and res["object"] is None:
        raise ExportError(f"{out_dir}: neither body_vertices.npy nor object_poses.npz; run the fitting stages first")
    frame_ids = np.asarray(session.frame_ids)
    ok_body = body_valid(res["body_vertices"], T)
    has_obj = session.object is not None and res["object"] is not None
    ok_obj = object_valid(res["object"], T) if has_obj else np.zeros(T, bool)
    figures: dict = {}
    if ecfg.meshes:
        meshes = out_dir / "meshes"
        mesh = session.object.load_mesh() if has_obj else None
        posed = pose_object(mesh.vertices, np.where(ok_obj[:, None, None], res["object"]["R"], np.eye(3)),
                            np.where(ok_obj[:, None], res["object"]["t"], 0.0)) if has_obj else None
        surface = TriangleSurface(mesh.vertices, mesh.faces) if has_obj and ecfg.scene else None
        contact = res["contact"] if res["contact"] is not None else np.zeros(T, bool)
        scenes = 0
        for i in tqdm(range(T), desc="export meshes", unit="frame", disable=not progress):
            name = f"{int(frame_ids[i]):06d}.ply"
            if ok_body[i]:
                write_mesh_ply(meshes / f"body_{name}", res["body_vertices"][i], res["body_faces"])
            if ok_obj[i]:
                write_mesh_ply(meshes / f"object_{name}", posed[i], mesh.faces)
            if surface is not None and ok_body[i] and ok_obj[i]:
                body = np.asarray(res["body_vertices"][i])
                V = len(body)
                colors = np.vstack([np.tile(BODY_GREY, (V, 1)), np.tile(OBJECT_BLUE, (len(posed[i]), 1))]).astype(np.uint8)
                if contact[i]:
                    near_b, near_o = contact_vertices(body, posed[i], surface, res["object"]["R"][i],
                                                      res["object"]["t"][i], ecfg.contact_distance_m)
                    colors[:V][near_b] = CONTACT_RED
                    colors[V:][near_o] = CONTACT_RED
                faces = np.vstack([np.asarray(res["body_faces"]), np.asarray(mesh.faces) + V])
                write_mesh_ply(meshes / f"scene_{name}", np.vstack([body, posed[i]]), faces, colors)
                scenes += 1
        figures.update(body_meshes=int(ok_body.sum()), object_meshes=int(ok_obj.sum()), scene_meshes=scenes)
    skipped_body = frame_ids[~ok_body] if res["body_vertices"] is not None else frame_ids[:0]
    skipped_obj = frame_ids[~ok_obj] if has_obj else frame_ids[:0]
    figures.update(frames_skipped_body=int(len(skipped_body)), frames_skipped_object=int(len(skipped_obj)),
                   skipped_body_frame_ids=skipped_body.tolist(), skipped_object_frame_ids=skipped_obj.tolist())
    if len(skipped_body) or len(skipped_obj):
        log.warning("export: %d frame(s) without a body fit and %d without an object pose get no mesh",
                    len(skipped_body), len(skipped_obj))
    body_model_arrays(res, cfg, T)
    model_name = str((res["body_params"] or {}).get("model", session.body_model)) if res["body_vertices"] is not None else ""
    arrays = dataset_arrays(session, res, ecfg.vertices_float16, provenance(out_dir, cfg, model_name))
    dataset = out_dir / "export" / f"{Path(session.root).name}.npz"
    save_npz(dataset, **arrays)
    figures["dataset"] = str(dataset)
    figures["dataset_keys"] = len(arrays)
    missing = [n for n, v in (("body", res["body_vertices"]), ("object poses", res["object"]),
                              ("contact", res["contact"]), ("ground", res["ground"]), ("physics", res["physics"])) if v is None]
    if missing:
        log.info("export: not in the results, left out of the dataset file: %s", ", ".join(missing))
    figures["left_out"] = missing
    if ecfg.behave:
        figures.update(write_behave(session, res, out_dir, ecfg.behave_frame, progress))
    if ecfg.glb:
        from intercap.stages.export.gltf import write_session_glb

        figures.update(write_session_glb(session, res, out_dir))
    return figures
