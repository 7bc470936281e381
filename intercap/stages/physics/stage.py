"""Stage 7, `physics`: contact forces, joint torques and free flight from the 4D result.

Reads the final results at OUT/ (body_params.npz, object_poses.npz, contact.npy and
OUT/contact/contact.npz's per-region labels) and the floor (OUT/prepare/ground.json), and
composes intercap.dynamics:

1. mass model (dynamics.mass): body mass from the fitted rest mesh (or session.yaml body.mass_kg),
   de Leva segments carried by the body model's bones; object mass from session.yaml;
2. kinematics (dynamics.kinematics): segment COMs and orientations, filtered and differentiated;
3. Newton-Euler (dynamics.newton_euler): what each segment and the object need;
4. contacts (dynamics.contact_forces, dynamics.supports): sole points within `physics.foot_contact_m`
   of the floor (friction pyramids), a 6D wrench per hand touching the object, object points on the
   floor or on a fixed support, body points on the fixed supports (session.yaml `supports`, a static
   object: seat, table, step; a 6D wrench per hand gripping one marked `grip`); bounded least squares
   per frame with a joint-torque prior on the trunk and legs; then joint torques per bone;
5. free flight (dynamics.flight): episodes where the object touches nothing, parabola fits.

Writes OUT/physics/physics.npz (keys of docs/outputs.md, SI units, world frame; extra keys:
hand_point (T, 2, 3) m where the hand wrench acts and about which hand_torque is taken,
object_residual_torque (T, 3), foot_contact (T, 2, P) bool, foot_points (T, 2, P, 3), hand_contact
(T, 2) bool, mu, body_mass_source, object_mass_source, and the per-frame plausibility inputs of
dynamics.plausibility: cone_violation, sole_speed, ground_penetration_m, object_ground_penetration_m)
and returns its figures for OUT/metrics.json (dynamics.plausibility.summarise of that file, plus masses).
`analyse(out_dir, session)` is the same from Python.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from intercap.body_models import shared_model
from intercap.dynamics import contact_forces as cf
from intercap.dynamics import kinematics as kin
from intercap.dynamics import mass as mass_model
from intercap.dynamics import newton_euler as ne
from intercap.dynamics import plausibility
from intercap.dynamics import supports as sup
from intercap.io.files import read_json, save_npz
from intercap.session.format import positive_number

log = logging.getLogger(__name__)

G = 9.81
SOLE_POINTS = 4
OBJECT_POINTS = 16
# body regions that a fixed support (seat, table, bar, step) can carry, and points sampled per region
SUPPORT_REGIONS = ("buttocks", "left_hand", "right_hand", "left_forearm", "right_forearm", "left_foot", "right_foot")
SUPPORT_POINTS_PER_REGION = 6
SEAT_REGIONS = ("buttocks", "back_of_thighs")  # pressed into a seat: reached from further (physics.seat_contact_m)
SEAT_POINTS_PER_REGION = 16  # a seat carries the body over an area: enough points to span it


class PhysicsError(ValueError):
    """The physics stage cannot run: a needed result, the floor or a mass is missing."""


# -- inputs ------------------------------------------------------------------------------------
def load_gravity(out_dir: Path, session) -> tuple[np.ndarray | None, np.ndarray, str]:
    """(floor point (3,), up (3,), source) from OUT/prepare/ground.json or session.yaml's ground,
    else up from OUT/global/gravity.json (free flight; floor point None: placed by the caller)."""
    path = Path(out_dir) / "prepare" / "ground.json"
    if path.exists():
        data = read_json(path)
        up = np.asarray(data["normal"], np.float64)
        return np.asarray(data["point"], np.float64), up / np.linalg.norm(up), str(data.get("source", "prepare"))
    if session.ground is not None:
        point, normal = session.ground
        return np.asarray(point, np.float64), np.asarray(normal, np.float64) / np.linalg.norm(normal), "session.yaml"
    flight = Path(out_dir) / "global" / "gravity.json"
    if flight.exists():  # no floor in view: the global stage found up from the object's free flight
        up = np.asarray(read_json(flight)["up"], np.float64)
        return None, up / np.linalg.norm(up), "flight (no floor seen; floor placed under the body's lowest vertex)"
    raise PhysicsError(f"physics: no ground plane ({path} missing and session.yaml has no `ground`), so gravity's "
                       f"direction is unknown; run the `prepare` stage or give `ground: {{point, normal}}` in session.yaml")


def session_body_mass(session) -> float | None:
    """`body: {mass_kg: ...}` of session.yaml, or None."""
    try:
        data = yaml.safe_load((Path(session.root) / "session.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return None
    body = data.get("body") if isinstance(data, dict) else None
    value = body.get("mass_kg") if isinstance(body, dict) else None
    if value is None:
        return None
    mass = positive_number(value)  # as validate reads it: `7e1` is a number, inf is not
    if mass is None:
        raise PhysicsError(f"{session.root / 'session.yaml'}: `body.mass_kg` must be a positive number, got {value!r}")
    return mass


def _require(path: Path, stage: str) -> Path:
    if not path.exists():
        raise PhysicsError(f"physics: {path} is missing; run the `{stage}` stage first "
                           f"(intercap run SESSION --out {path.parent} --stages {stage})")
    return path


# -- the body ----------------------------------------------------------------------------------
@dataclasses.dataclass
class BodyTrack:
    """The posed body per frame (world), from the body model."""

    heads: np.ndarray  # (T, J, 3) bone heads
    rotations: np.ndarray  # (T, J, 3, 3) bone orientations
    landmarks: dict  # name -> (T, 3)
    soles: np.ndarray  # (T, 2, P, 3) sole points, left / right
    hands: np.ndarray  # (T, 2, 3) palm centres, left / right
    lowest: np.ndarray  # (T,) m, lowest vertex above the floor (negative: below)
    support_points: np.ndarray  # (T, S, 3) body points a fixed support can carry (SUPPORT_REGIONS)


def _anny_core(model):
    if not hasattr(model, "core"):
        raise PhysicsError(f"physics: the {model.name} body model is not supported yet (its bone frames are needed); "
                           f"use body_model.name=anny")
    return model.core


def pose_body(model, params, ids: dict, point: np.ndarray, up: np.ndarray, chunk: int = 64) -> BodyTrack:
    """Bone frames and the few vertices the stage needs, chunk by chunk over frames."""
    core = _anny_core(model)
    T = params.batch_size
    heads, rots, picks, lowest = [], [], [], []
    order = np.concatenate([ids["landmarks"], ids["soles"].ravel(), *ids["hands"], ids["support"]])
    with torch.no_grad():
        for s in range(0, T, chunk):
            p = params[s:s + chunk]
            out = core(model.pose_matrices(p), phenotype_kwargs=p.shape, facial_actions=p.expression)
            Rg = ne_rot(p.global_orient)  # (B, 3, 3)
            tr = p.transl.double()
            bones = out["bone_poses"].double()
            heads.append((torch.einsum("bij,bkj->bki", Rg, bones[..., :3, 3]) + tr[:, None]).numpy())
            rots.append((Rg[:, None] @ bones[..., :3, :3]).numpy())
            verts = torch.einsum("bij,bkj->bki", Rg, out["vertices"].double()) + tr[:, None]  # (B, V, 3)
            picks.append(verts[:, torch.as_tensor(order)].numpy())
            lowest.append(((verts.numpy() - point) @ up).min(1))
    picks = np.concatenate(picks)
    L = len(ids["landmarks"])
    n_sole = ids["soles"].size
    h0, h1 = L + n_sole, L + n_sole + len(ids["hands"][0])
    h2 = h1 + len(ids["hands"][1])
    return BodyTrack(np.concatenate(heads), np.concatenate(rots),
                     {name: picks[:, k] for k, name in enumerate(ids["landmark_names"])},
                     picks[:, L:L + n_sole].reshape(T, *ids["soles"].shape, 3),
                     np.stack([picks[:, h0:h1].mean(1), picks[:, h1:h2].mean(1)], 1),
                     np.concatenate(lowest), picks[:, h2:])


def ne_rot(axis_angle: torch.Tensor) -> torch.Tensor:
    from intercap.body_models import axis_angle_to_matrix

    return axis_angle_to_matrix(axis_angle.double())


def body_landmarks(model, rest_vertices: np.ndarray, rest_heads: np.ndarray) -> dict:
    """Vertex ids at rest (anny: z up, facing -y): head top, heels and toe tips, four sole corners
    per foot, the palm regions."""
    core = _anny_core(model)
    dominant = model.dense_weights(core).argmax(1)
    names = list(model.joint_names)
    out_names, ids = ["head_top"], [int(np.argmax(rest_vertices[:, 2]))]
    soles = []
    forward = -rest_vertices[:, 1]
    for side, region in (("L", "left_foot"), ("R", "right_foot")):
        foot_bones = [i for i, b in enumerate(names) if b.endswith(f".{side}") and b.startswith(("foot", "toe"))]
        foot = np.flatnonzero(np.isin(dominant, foot_bones))
        out_names += [f"heel.{side}", f"toe_tip.{side}"]
        ids += [int(foot[np.argmin(forward[foot])]), int(foot[np.argmax(forward[foot])])]
        sole = model.contact_regions[region].cpu().numpy()
        f, lat = forward[sole], rest_vertices[sole, 0]
        soles.append([int(sole[np.argmax(sign_f * f + sign_l * lat)]) for sign_f in (-1, 1) for sign_l in (-1, 1)])
    hands = [model.contact_regions[r].cpu().numpy() for r in ("left_hand", "right_hand")]
    from intercap.body_models.regions import farthest_point_subsample

    support, support_region = [], []
    regions = {r: model.contact_regions[r].cpu().numpy() for r in SUPPORT_REGIONS if r in model.contact_regions}
    regions["back_of_thighs"] = back_of_thighs(model, rest_vertices, rest_heads, dominant)
    for region, vids in regions.items():
        if len(vids):
            count = SEAT_POINTS_PER_REGION if region in SEAT_REGIONS else SUPPORT_POINTS_PER_REGION
            picked = vids[farthest_point_subsample(rest_vertices[vids], count)]
            support += picked.tolist()
            support_region += [region] * len(picked)
    return {"landmark_names": out_names, "landmarks": np.array(ids), "soles": np.array(soles), "hands": hands,
            "support": np.array(support, np.int64), "support_region": np.array(support_region),
            "support_bone": dominant[np.array(support, np.int64)]}


def back_of_thighs(model, rest_vertices: np.ndarray, rest_heads: np.ndarray, dominant: np.ndarray) -> np.ndarray:
    """Vertex ids of the thighs' undersides when seated (at rest, z up facing -y: the back of the thighs
    from above the knees to mid-thigh), which a seat carries besides the buttocks."""
    from intercap.body_models.regions import vertex_normals

    names = list(model.joint_names)
    thigh = np.isin(dominant, [i for i, b in enumerate(names) if b.startswith("upperleg")])
    hip, knee = rest_heads[names.index("upperleg01.L"), 2], rest_heads[names.index("lowerleg01.L"), 2]
    backward = vertex_normals(rest_vertices, model.faces.numpy()) @ np.array([0.0, 1.0, 0.0]) > 0.3
    z = rest_vertices[:, 2]
    return np.flatnonzero(thigh & backward & (z > knee + 0.04) & (z <= (hip + knee) / 2))


# -- the analysis ------------------------------------------------------------------------------
def _td(a) -> torch.Tensor:
    return torch.as_tensor(a, dtype=torch.float64)


def load_body_params(out_dir: Path, model, T: int):
    """(params with gaps filled and the mean shape, the mean shape, valid (T,)) of OUT/body_params.npz."""
    from intercap.body_models import BodyParams
    from intercap.body_models.base import PARAM_FIELDS, fill_axis_angle_gaps

    saved = dict(np.load(_require(out_dir / "body_params.npz", "global")))
    if str(saved.get("model", model.name)) != model.name:
        raise PhysicsError(f"{out_dir / 'body_params.npz'} holds a {saved['model']} fit, "
                           f"the session asks for {model.name}")
    if len(saved["transl"]) != T:
        raise PhysicsError(f"{out_dir / 'body_params.npz'} has {len(saved['transl'])} frames, the session {T}")
    body_valid = saved["valid"].astype(bool) if "valid" in saved else np.ones(T, bool)
    body_valid &= np.isfinite(saved["transl"]).all(1)
    if not body_valid.any():
        raise PhysicsError(f"{out_dir / 'body_params.npz'}: no frame has a body fit")
    arrays = {k: (fill_axis_angle_gaps if k == "global_orient" else kin.fill_gaps)(saved[k], body_valid)
              .astype(np.float64) for k in PARAM_FIELDS}
    shape = saved["shape_mean"] if "shape_mean" in saved else saved["shape"][body_valid].mean(0)
    arrays["shape"][:] = shape
    return BodyParams.from_numpy_dict(arrays, dtype=model.dtype), shape, body_valid


def rest_body(model, shape) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3), bone poses (J, 4, 4)) of the body at rest with the given shape."""
    rest = model.init_params(1)
    rest.shape[:] = torch.as_tensor(shape, dtype=model.dtype)
    core = _anny_core(model)
    with torch.no_grad():
        rest_out = core(model.pose_matrices(rest), phenotype_kwargs=rest.shape, facial_actions=rest.expression)
    return rest_out["vertices"][0].double().numpy(), rest_out["bone_poses"][0].double().numpy()


def body_mass(session, pc, model, rest_vertices: np.ndarray) -> tuple[float, str]:
    """(mass kg, where it comes from): session.yaml's body.mass_kg, else the rest mesh's volume."""
    given = session_body_mass(session)
    if given is not None:
        return given, "session.yaml body.mass_kg"
    try:
        mass = mass_model.body_mass_from_volume(rest_vertices, model.faces.numpy(), pc.body_density_kg_m3)
    except mass_model.MassError as exc:
        raise PhysicsError(f"physics: {exc}; give `body: {{mass_kg: ...}}` in {session.root / 'session.yaml'}") from exc
    return mass, f"rest mesh volume x {pc.body_density_kg_m3:g} kg/m^3"


def female_share(pc, model, shape) -> float:
    """physics.sex as de Leva's female share: 0, 1, or the body model's gender phenotype (auto)."""
    if pc.sex not in ("auto", "male", "female"):
        raise PhysicsError(f"physics.sex must be auto, male or female, got {pc.sex!r}")
    labels = list(_anny_core(model).phenotype_labels)
    return {"male": 0.0, "female": 1.0}.get(pc.sex, float(shape[labels.index("gender")]) if "gender" in labels else 0.5)


@dataclasses.dataclass
class BodyNeeds:
    """What the body's segments need (Newton-Euler), per frame."""

    com: np.ndarray  # (T, S, 3) segment centres of mass
    force: torch.Tensor  # (T, S, 3) F of each segment
    torque: torch.Tensor  # (T, S, 3) N of each segment
    joints: torch.Tensor  # (T, J, 3) bone heads
    wrench: np.ndarray  # (T, 6) about the root


def body_needs(segments, bone_index: dict, parents, track: BodyTrack, fps: float, filt: dict,
               g_t: torch.Tensor) -> BodyNeeds:
    """Segment kinematics, filtered and differentiated, and the Newton-Euler needs of each segment."""
    com = mass_model.segment_coms(segments, bone_index, track.heads, track.landmarks)  # (T, S, 3)
    _, _, com_acc = kin.derivatives(com, fps, **filt)
    Rf, omega, alpha = kin.quaternion_derivatives(track.rotations[:, segments.carrier], fps, **filt)
    Q = Rf @ segments.carrier_rest.transpose(0, 2, 1)[None]  # (T, S, 3, 3) rotation from rest
    F = ne.newton_force(_td(segments.mass), _td(com_acc), g_t)
    N = ne.euler_torque(ne.rotate_inertia(_td(segments.inertia_rest), _td(Q)), _td(omega), _td(alpha))
    joints = _td(track.heads)
    f0, t0 = ne.joint_wrenches(parents, segments.carrier, F, N, _td(com), joints)
    return BodyNeeds(com, F, N, joints, torch.cat([f0[:, 0], t0[:, 0]], -1).numpy())


@dataclasses.dataclass
class ObjectTrack:
    """The object per frame (world) and, where its mass is known, the wrench it needs."""

    present: bool  # the session has an object and OUT/object_poses.npz exists
    mass: float = float("nan")
    mass_source: str = "no object"
    valid: np.ndarray = None  # (T,) bool
    filled: np.ndarray = None  # (T,) bool: not tracked, bridged by interpolation (`physics.object_gap_fill_s`)
    centres: np.ndarray = None  # (T, 3) centre of mass, NaN where not tracked
    on_ground: np.ndarray = None  # (T,) bool
    wrench: np.ndarray | None = None  # (T, 6)
    com_filled: np.ndarray | None = None  # (T, 3) centres with gaps filled
    points: np.ndarray | None = None  # (T, Q, 3) subsampled surface points
    ground_active: np.ndarray | None = None  # (T, Q) bool: point on the floor
    hand_active: np.ndarray | None = None  # (T, 2) bool
    support_active: np.ndarray | None = None  # (T, Q) bool: point resting on a fixed support (a table top)
    static: bool = False  # marked static or never moved: a fixed support, its own balance not solved
    mesh_world: object = None  # the static object's mesh where it stands (trimesh)


def track_object(out_dir: Path, session, T: int, point, up, pc, fps: float, filt: dict,
                 g_t: torch.Tensor) -> ObjectTrack:
    """The object's poses, mass, floor contacts and needs (an empty track without an object)."""
    obj_info = session.object
    track = ObjectTrack(obj_info is not None and (out_dir / "object_poses.npz").exists(), valid=np.zeros(T, bool),
                        centres=np.full((T, 3), np.nan), on_ground=np.zeros(T, bool))
    if obj_info is not None and not track.present:
        raise PhysicsError(f"physics: {out_dir / 'object_poses.npz'} is missing; run the `global` stage first")
    if not track.present:
        return track
    with np.load(out_dir / "object_poses.npz") as z:
        R_obj, t_obj = z["R"].astype(np.float64), z["t"].astype(np.float64)
        obj_valid = z["valid"].astype(bool) if "valid" in z else np.ones(T, bool)
    obj_valid &= np.isfinite(R_obj).all((1, 2)) & np.isfinite(t_obj).all(1)
    hands = hand_contacts(out_dir, T)
    # an object lost for a moment while a hand touches it: interpolated, so its weight stays on the hands (not
    # in free flight, where a straight line would take gravity out of its path)
    track.filled = kin.short_gaps(obj_valid, int(round(pc.object_gap_fill_s * fps))) & hands.any(1)
    if track.filled.any():
        R_obj = np.where(track.filled[:, None, None], kin.fill_rotations(R_obj, obj_valid), R_obj)
        t_obj = np.where(track.filled[:, None], kin.fill_gaps(t_obj, obj_valid), t_obj)
        obj_valid = obj_valid | track.filled
    track.valid = obj_valid
    mesh = obj_info.load_mesh()
    track.mass, track.mass_source = mass_model.object_mass(obj_info.mass_kg, getattr(obj_info, "density_kg_m3", None),
                                                           mesh.vertices, mesh.faces)
    com_local, inertia_local = mass_model.object_inertia(mesh.vertices, mesh.faces,
                                                         track.mass if np.isfinite(track.mass) else 1.0)
    centres = np.einsum("tij,j->ti", R_obj, com_local) + t_obj
    centres[~obj_valid] = np.nan
    track.centres = centres
    from intercap.body_models.regions import farthest_point_subsample

    sub = np.asarray(mesh.vertices)[farthest_point_subsample(np.asarray(mesh.vertices), OBJECT_POINTS)]
    track.points = np.einsum("tij,kj->tki", R_obj, sub) + t_obj[:, None]  # (T, Q, 3)
    heights = (track.points - point) @ up
    track.ground_active = np.nan_to_num(heights, nan=np.inf) < pc.object_ground_m
    track.on_ground = track.ground_active.any(1)
    track.hand_active = hands & obj_valid[:, None]
    # furniture: marked static, or never moves and stands on the floor or is never touched (a box held
    # still in the air never moves either, but the hands carry it)
    track.static = obj_info.static or (
        sup.is_static(R_obj, t_obj, obj_valid, pc.static_object_m, pc.static_object_deg)
        and (track.on_ground[obj_valid].all() or not track.hand_active.any()))
    if track.static:  # furniture: it carries the body, the floor carries it
        k = np.flatnonzero(obj_valid)[obj_valid.sum() // 2] if obj_valid.any() else None
        if k is None:
            track.static = False
        else:
            track.mesh_world = mesh.copy().apply_transform(_pose_matrix(R_obj[k], t_obj[k]))
            track.mass_source += "; static: a support"
            return track
    if np.isfinite(track.mass) and obj_valid.any():
        Ro, w_o, al_o = kin.quaternion_derivatives(kin.fill_gaps(R_obj, obj_valid), fps, **filt)
        _, _, acc_o = kin.derivatives(kin.fill_gaps(centres, obj_valid), fps, **filt)
        Fo, No = ne.rigid_body_wrench(track.mass, _td(Ro @ inertia_local @ Ro.transpose(0, 2, 1)), _td(acc_o),
                                      _td(w_o), _td(al_o), g_t)
        track.wrench = torch.cat([Fo, No], -1).numpy()
        track.wrench[~obj_valid] = np.nan
        track.com_filled = kin.fill_gaps(centres, obj_valid)
    elif not obj_valid.any():
        log.warning("physics: the object was tracked in no frame; hand and object forces are skipped")
    else:
        log.warning("physics: object mass %s; hand and object forces are skipped", track.mass_source)
    return track


def _pose_matrix(R, t) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


def fixed_supports(session, obj: ObjectTrack, pc) -> list[tuple[str, object, bool]]:
    """(name, world mesh, grip) of every fixed support: session.yaml's `supports` and a static object."""
    fixed = [(s.name, s.mesh, s.grip) for s in getattr(session, "supports", ())]
    if obj.static and obj.mesh_world is not None:
        fixed.append((session.object.name, obj.mesh_world, False))
    return fixed


def support_contacts(fixed: list, track: BodyTrack, ids: dict, pc) -> dict:
    """solve_contacts' support keywords: body points on each support (pushes within friction cones),
    hands on a support that can be gripped (a free wrench instead); {} without supports."""
    if not fixed or not track.support_points.shape[1]:
        return {}
    reach = np.where(np.isin(ids["support_region"], SEAT_REGIONS), pc.seat_contact_m, pc.support_contact_m)
    active, normals, which = sup.support_contacts([m for _, m, _ in fixed], track.support_points, reach,
                                                  pc.support_depth_m)
    grippable = [k for k, (_, _, grip) in enumerate(fixed) if grip]
    grip = np.zeros((len(active), 2), bool)
    for h, region in enumerate(("left_hand", "right_hand")):
        on = ids["support_region"] == region
        grip[:, h] = np.isin(which[:, on], grippable).any(1)
        active[:, on] &= ~grip[:, h:h + 1]  # a gripping hand acts through its wrench
    return dict(support_points=track.support_points, support_normals=normals, support_active=active,
                grip_active=grip)


def object_on_supports(obj: ObjectTrack, fixed: list, up, pc) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(object points resting on the floor or on a fixed support (T, Q) bool, the normal of what each
    rests on (T, Q, 3)); the floor's alone (normals None) without supports or object forces."""
    if obj.wrench is None or obj.points is None or not fixed:
        return obj.ground_active, None
    on_support, normals, _ = sup.support_contacts([m for _, m, _ in fixed], np.nan_to_num(obj.points, nan=1e6),
                                                  pc.object_ground_m, pc.object_ground_m)
    floor = obj.ground_active
    normals = np.where(floor[..., None], up, normals)
    obj.support_active = on_support & ~floor
    return floor | on_support, normals


ARM_SEGMENTS = ("upper_arm", "forearm", "hand")
FLAGGED_FOOT_M = 0.10  # a foot flagged in contact by measured timing pushes through its sole points this near the floor


def timed_contacts(timing: dict, foot_active, soles, point, up, contacts: dict, T: int) -> tuple[np.ndarray, dict]:
    """(foot_active (T, 2, P), support keywords) with measured contact timing (`analyse`); a kind of
    contact the timing leaves out keeps its detection."""
    if "feet" in timing:
        feet = np.asarray(timing["feet"], bool)
        height = (soles - point) @ up
        lowest = height <= height.min(2, keepdims=True) + 0.01
        foot_active = ((height < FLAGGED_FOOT_M) | lowest) & feet[:, :, None]  # at least its lowest points
    grip = np.asarray(timing.get("grip", np.zeros((T, 2), bool)), bool)
    contacts = dict(contacts)
    contacts["grip_active"] = grip | contacts.get("grip_active", np.zeros((T, 2), bool))
    return foot_active, contacts


def torque_prior(pc, segments, parents, bone_index: dict, needs: BodyNeeds, track: BodyTrack, ids: dict):
    """The joint-torque prior of solve_contacts (None when physics.torque_weight is 0): the torques of
    the joints carrying a segment, without contacts, and which contacts each carries."""
    if pc.torque_weight <= 0:
        return None
    # the trunk's and legs' joints (the root's wrench is the balance itself): the arms' own effort left
    # out, or the prior would rest the arms' weight on whatever the hands touch
    trunk_and_legs = np.array([not str(n).startswith(ARM_SEGMENTS) for n in segments.names])
    joints = np.unique(segments.carrier[(segments.carrier > 0) & trunk_and_legs])
    _, torque = ne.joint_wrenches(parents, segments.carrier, needs.force, needs.torque, _td(needs.com), needs.joints)
    P = track.soles.shape[2]
    bones = contact_bones(bone_index, P)
    return cf.TorquePrior(track.heads[:, joints], torque.numpy()[:, joints],
                          sup.carried_by(parents, joints, bones[2 * P:]), sup.carried_by(parents, joints, bones[:2 * P]),
                          sup.carried_by(parents, joints, ids["support_bone"]), pc.torque_weight)


def centre_of_pressure(foot_point_force: np.ndarray, soles: np.ndarray, point, up) -> np.ndarray:
    """(T, 2, 3) each foot's centre of pressure on the floor; NaN where the foot carries nothing."""
    fn = foot_point_force @ up  # (T, 2, P)
    with np.errstate(invalid="ignore", divide="ignore"):
        cop = np.einsum("tfp,tfpi->tfi", fn, soles) / fn.sum(2)[..., None]
    cop[fn.sum(2) < 1e-6] = np.nan
    return cop - ((cop - point) @ up)[..., None] * up  # on the floor


def contact_bones(bone_index: dict, P: int, support_bones=()) -> list[int]:
    """The bone each contact acts on, in joint_torques' order: sole points, hands, support points."""
    return ([bone_index["foot.L"]] * P + [bone_index["foot.R"]] * P + [bone_index["wrist.L"], bone_index["wrist.R"]]
            + [int(b) for b in support_bones])


def joint_torques(sol, segments, parents, bone_index: dict, needs: BodyNeeds, soles, hands, support_points=None,
                  support_bones=()) -> np.ndarray:
    """(T, J, 3) joint torques with the solved contacts: soles on the foot bones, hand reactions on the
    wrists, fixed supports on the bones of the points they carry."""
    T, P = soles.shape[0], soles.shape[2]
    with_supports = sol.support_point_force is not None
    ext_bone = contact_bones(bone_index, P, support_bones if with_supports else ())
    hand_f = np.nan_to_num(sol.hand_force)
    hand_t = np.nan_to_num(sol.hand_torque)
    sup_f = [np.nan_to_num(sol.support_point_force)] if with_supports else []
    ext_f = np.concatenate([np.nan_to_num(sol.foot_point_force).reshape(T, 2 * P, 3), -hand_f, *sup_f], 1)
    ext_t = np.zeros_like(ext_f)
    ext_t[:, 2 * P:2 * P + 2] = -hand_t
    ext_p = np.concatenate([soles.reshape(T, 2 * P, 3), hands, *([support_points] if with_supports else [])], 1)
    _, joint_torque = ne.joint_wrenches(parents, segments.carrier, needs.force, needs.torque, _td(needs.com),
                                        needs.joints, ext_bone, _td(ext_f), _td(ext_t), _td(ext_p))
    return joint_torque.numpy()


def feet_load(sol, body_wrench: np.ndarray, hands: np.ndarray, root: np.ndarray,
              support_points: np.ndarray | None = None) -> np.ndarray:
    """(T, 6) what the feet carry about the root: the body's needs plus what the hands push on the object,
    less what fixed supports carry."""
    hand_f = np.nan_to_num(sol.hand_force)
    hand_t = np.nan_to_num(sol.hand_torque)
    arm = hands - root[:, None]
    feet_need = body_wrench.copy()
    feet_need[:, :3] += hand_f.sum(1)
    feet_need[:, 3:] += (np.cross(arm, hand_f) + hand_t).sum(1)
    if sol.support_point_force is not None:  # what fixed supports carry, the feet do not
        f = np.nan_to_num(sol.support_point_force)
        feet_need[:, :3] -= f.sum(1)
        feet_need[:, 3:] -= np.cross(support_points - root[:, None], f).sum(1)
    return feet_need


def analyse(out_dir, session, cfg=None, progress: bool = False, contact_timing: dict | None = None) -> dict:
    """Forces, torques and flight of a finished results folder; writes OUT/physics/physics.npz and
    returns the figures (metrics.json's `physics` entry). PhysicsError with a clear message when a
    result, the floor or the body mass is missing. contact_timing: measured contact timing that
    replaces the detected (a benchmark's force sensors): {"feet": (T, 2) bool, a foot carries only
    where flagged, then through its sole points within FLAGGED_FOOT_M of the floor; "grip": (T, 2)
    bool, the hand grips a fixed structure}."""
    from intercap.config import Config

    cfg = cfg or Config()
    pc = cfg.physics
    out_dir = Path(out_dir)
    start = time.perf_counter()
    point, up, ground_source = load_gravity(out_dir, session)
    gravity = -G * up
    T, fps = session.num_frames, float(session.fps)

    model = shared_model(dataclasses.replace(cfg.body_model, name=session.body_model))
    params, shape, body_valid = load_body_params(out_dir, model, T)
    rest_vertices, rest_bones = rest_body(model, shape)
    mass, body_source = body_mass(session, pc, model, rest_vertices)
    female = female_share(pc, model, shape)
    ids = body_landmarks(model, rest_vertices, rest_bones[:, :3, 3])
    rest_landmarks = {n: rest_vertices[i] for n, i in zip(ids["landmark_names"], ids["landmarks"])}
    segments = mass_model.build_segments(list(model.joint_names), rest_bones[:, :3, 3], rest_bones[:, :3, :3],
                                         rest_landmarks, mass, female, np.array([1.0, 0, 0]))
    track = pose_body(model, params, ids, np.zeros(3) if point is None else point, up)
    if point is None:  # the floor under the body's lowest vertex (5th percentile over the frames)
        point = up * np.nanpercentile(track.lowest[body_valid], 5)
        track.lowest -= point @ up
    bone_index = {b: i for i, b in enumerate(model.joint_names)}
    parents = np.asarray(_anny_core(model).bone_parents)

    filt = dict(method=pc.filter, window_s=pc.filter_window_s, order=pc.filter_order, cutoff_hz=pc.cutoff_hz)
    g_t = _td(gravity)
    needs = body_needs(segments, bone_index, parents, track, fps, filt, g_t)
    root = track.heads[:, 0]
    obj = track_object(out_dir, session, T, point, up, pc, fps, filt, g_t)

    soles = track.soles  # (T, 2, P, 3)
    foot_active = ((soles - point) @ up) < pc.foot_contact_m
    needs.wrench[~body_valid] = np.nan
    fixed = fixed_supports(session, obj, pc)
    contacts = support_contacts(fixed, track, ids, pc)
    if contact_timing is not None:
        foot_active, contacts = timed_contacts(contact_timing, foot_active, soles, point, up, contacts, T)
    prior = torque_prior(pc, segments, parents, bone_index, needs, track, ids)
    object_active, object_normals = object_on_supports(obj, fixed, up, pc)
    sol = cf.solve_contacts(needs.wrench, root, soles, foot_active, up, pc.mu, obj.wrench, obj.com_filled,
                            track.hands, obj.hand_active if obj.wrench is not None else None, obj.points,
                            object_active, edges=pc.friction_edges, object_weight=pc.object_weight,
                            torque_prior=prior, object_normals=object_normals, **contacts)
    foot_force = sol.foot_point_force.sum(2)  # (T, 2, 3)
    cop = centre_of_pressure(sol.foot_point_force, soles, point, up)
    joint_torque = joint_torques(sol, segments, parents, bone_index, needs, soles, track.hands,
                                 track.support_points, ids["support_bone"])
    valid = body_valid & np.isfinite(sol.body_residual).all(1)
    joint_torque[~valid] = np.nan

    object_known = obj.wrench is not None
    gripping = contacts.get("grip_active", np.zeros((T, 2), bool))
    hands_known = (object_known | gripping.any(1))[:, None, None]
    hand_force = np.where(hands_known, sol.hand_force, np.nan)
    hand_torque = np.where(hands_known, sol.hand_torque, np.nan)
    object_ground = sol.object_ground_force.sum(1) if object_known else np.full((T, 3), np.nan)
    resting = obj.on_ground | (obj.support_active.any(1) if obj.support_active is not None else False)
    flight = flight_analysis(obj.centres, contact_labels(out_dir, T) | resting, up, fps, pc.flight_min_frames,
                             pc.flight_max_residual_m) \
        if obj.present and not obj.static else no_flight()
    per_frame = plausibility_arrays(feet_load(sol, needs.wrench, track.hands, root, track.support_points), root,
                                    soles, foot_active, up, pc, fps, track.lowest, point, obj.points, obj.valid)
    S = track.support_points.shape[1]
    support_force = sol.support_point_force if sol.support_point_force is not None else np.zeros((T, S, 3))
    per_frame.update(support_force=support_force, support_points=track.support_points,
                     support_contact=contacts.get("support_active", np.zeros((T, S), bool)),
                     support_region=ids["support_region"], hand_grip=gripping,
                     support_names=np.array([name for name, _, _ in fixed], dtype=str))
    arrays = dict(frame_ids=np.asarray(session.frame_ids), gravity=gravity, body_mass_kg=np.float64(mass),
                  object_mass_kg=np.float64(obj.mass), hand_force=hand_force, hand_torque=hand_torque,
                  hand_point=track.hands, foot_force=foot_force, foot_cop=cop, object_ground_force=object_ground,
                  joint_torque=joint_torque, joint_names=np.array(model.joint_names),
                  residual_force=sol.body_residual[:, :3], residual_torque=sol.body_residual[:, 3:],
                  object_residual_force=sol.object_residual[:, :3], object_residual_torque=sol.object_residual[:, 3:],
                  valid=valid, flight_episodes=flight["episodes"], flight_acceleration=flight["acceleration"],
                  flight_gravity_angle_deg=flight["gravity_angle_deg"], flight_runs_held=flight["held"],
                  foot_contact=foot_active, foot_points=soles, foot_point_force=sol.foot_point_force,
                  hand_contact=(np.zeros((T, 2), bool) if obj.hand_active is None or obj.static else obj.hand_active),
                  mu=np.float64(pc.mu), body_mass_source=np.array(body_source),
                  object_mass_source=np.array(obj.mass_source), **per_frame)
    save_npz(out_dir / "physics" / "physics.npz", **arrays)
    figures = physics_figures(arrays, mass, body_source, obj, ground_source)
    figures["physics_seconds_per_frame"] = (time.perf_counter() - start) / max(T, 1)
    return figures


def physics_figures(arrays: dict, mass: float, body_source: str, obj: ObjectTrack, ground_source: str) -> dict:
    """metrics.json's `physics` entry from physics.npz's arrays (without the timing)."""
    object_known = obj.wrench is not None
    valid, foot_force, hand_force = arrays["valid"], arrays["foot_force"], arrays["hand_force"]
    figures = plausibility.summarise(arrays)
    figures.update({
        "body_mass_kg": mass, "body_mass_source": body_source,
        "object_mass_kg": None if not np.isfinite(obj.mass) else obj.mass, "object_mass_source": obj.mass_source,
        "object_forces": ("solved" if object_known else "no object" if not obj.present
                          else "static: a support" if obj.static
                          else "skipped: object tracked in no frame" if not obj.valid.any()
                          else f"skipped: object mass {obj.mass_source}"),
        "ground_source": ground_source, "frames_valid": int(valid.sum()),
        "object_frames_filled": 0 if obj.filled is None else int(obj.filled.sum()),
        "supports": [str(n) for n in arrays["support_names"]],
    })
    if len(arrays["support_names"]) and valid.any():
        figures["support_force_mean_n"] = float(np.linalg.norm(arrays["support_force"][valid].sum(1), axis=-1).mean())
    if valid.any():
        figures["ground_reaction_mean_n"] = float(np.linalg.norm(foot_force[valid].sum(1), axis=-1).mean())
        if object_known:
            figures["hand_force_sum_mean_n"] = float(np.linalg.norm(np.nansum(hand_force[valid], 1), axis=-1).mean())
    return figures


def hand_contacts(out_dir: Path, T: int) -> np.ndarray:
    """(T, 2) bool: the left / right hand touches the object, from the contact stage's region labels
    (OUT/contact/contact.npz), else both hands in the frames of OUT/contact.npy."""
    path = out_dir / "contact" / "contact.npz"
    if path.exists():
        with np.load(path) as z:
            names = [str(n) for n in z["region_names"]]
            if "region_contact" in z.files and {"left_hand", "right_hand"} <= set(names):
                rc = z["region_contact"].astype(bool)
                return np.stack([rc[:, names.index("left_hand")], rc[:, names.index("right_hand")]], 1)
    return np.repeat(contact_labels(out_dir, T)[:, None], 2, 1)


def contact_labels(out_dir: Path, T: int) -> np.ndarray:
    """(T,) bool body-object contact (OUT/contact.npy); all False when the contact stage has not run."""
    path = out_dir / "contact.npy"
    if not path.exists():
        log.warning("physics: %s missing; no hand contact assumed", path)
        return np.zeros(T, bool)
    labels = np.load(path).astype(bool)
    if len(labels) != T:
        raise PhysicsError(f"{path} has {len(labels)} frames, the session {T}")
    return labels


def flight_analysis(centres, touching, up, fps, min_frames, max_residual_m) -> dict:
    """Free-flight episodes of the object's centre and their parabola fits (dynamics.flight)."""
    from intercap.dynamics.flight import falling_episodes, find_flight_episodes, fit_flight, warn_held

    episodes = find_flight_episodes(centres, touching, up, fps, min_frames=min_frames)
    episodes, held = falling_episodes(centres, episodes, fps, up, max_residual_m)
    warn_held(held, "physics")
    runs_held = np.array([(a, b) for a, b, _ in held], np.int64).reshape(-1, 2)  # touching nothing, not falling
    if not len(episodes):
        return {**no_flight(), "held": runs_held}
    fit = fit_flight(centres, episodes, fps, up)
    return {"episodes": episodes, "acceleration": fit["acceleration"], "gravity_angle_deg": fit["gravity_angle_deg"],
            "held": runs_held}


def no_flight() -> dict:
    """`flight_analysis`'s result without an episode."""
    return {"episodes": np.zeros((0, 2), np.int64), "acceleration": np.zeros((0, 3)), "gravity_angle_deg": np.zeros(0),
            "held": np.zeros((0, 2), np.int64)}


def plausibility_arrays(feet_need, root, soles, foot_active, up, pc, fps, lowest, point, obj_points,
                        obj_valid) -> dict:
    """Per-frame inputs of the plausibility figures (dynamics.plausibility): friction-cone violations
    of the unconstrained solve of the feet's load `feet_need` (T, 6) about root, sole speeds,
    body and object depth below the floor."""
    free = cf.unconstrained_feet(feet_need, root, soles, foot_active)  # (T, 2, P, 3)
    violation = cf.cone_violation(free.sum(2), up, pc.mu) & np.isfinite(free).all((2, 3))  # (T, 2)
    _, vel, _ = kin.derivatives(soles, fps, method=pc.filter, window_s=pc.filter_window_s, order=pc.filter_order,
                                cutoff_hz=pc.cutoff_hz)
    tangential = vel - (vel @ up)[..., None] * up
    obj_depth = np.full(len(soles), np.nan)
    if obj_points is not None and obj_valid.any():
        obj_depth[obj_valid] = np.clip(-((obj_points[obj_valid] - point) @ up).min(1), 0, None)
    return {"cone_violation": violation, "sole_speed": np.linalg.norm(tangential, axis=-1),
            "ground_penetration_m": np.clip(-np.asarray(lowest, np.float64), 0, None),
            "object_ground_penetration_m": obj_depth}


def nothing_to_analyse(out_dir: Path) -> str | None:
    """Why there is nothing to analyse (the body was fitted in no frame: no person seen), or None."""
    path = Path(out_dir) / "body_params.npz"
    if not path.exists():
        return None  # analyse says which stage to run
    with np.load(path) as z:
        valid = z["valid"].astype(bool) if "valid" in z else np.isfinite(z["transl"]).all(1)
    return None if valid.any() else f"no frame has a body fit in {path} (no person detected or fitted)"


def run(session, cfg, out_dir: Path, progress: bool = True) -> dict:
    """The `physics` stage: OUT/physics/physics.npz and the figures for metrics.json; skipped,
    with the reason in the figures, when no frame has a body to analyse."""
    reason = nothing_to_analyse(out_dir)
    if reason is not None:
        log.warning("physics: skipped: %s", reason)
        return {"skipped": reason}
    return analyse(out_dir, session, cfg, progress)
