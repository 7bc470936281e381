"""Stage 7, `physics`: contact forces, joint torques and free flight from the 4D result.

Reads the final results at OUT/ (body_params.npz, object_poses.npz, contact.npy and
OUT/contact/contact.npz's per-region labels) and the floor (OUT/prepare/ground.json), and
composes intercap.dynamics:

1. mass model (dynamics.mass): body mass from the fitted rest mesh (or session.yaml body.mass_kg),
   de Leva segments carried by the body model's bones; object mass from session.yaml;
2. kinematics (dynamics.kinematics): segment COMs and orientations, filtered and differentiated;
3. Newton-Euler (dynamics.newton_euler): what each segment and the object need;
4. contacts (dynamics.contact_forces): sole points within `physics.foot_contact_m` of the floor
   (friction pyramids), a 6D wrench per hand touching the object, object points on the floor;
   bounded least squares per frame; then joint torques per bone with the solved contacts;
5. free flight (dynamics.flight): episodes where the object touches nothing, parabola fits.

Writes OUT/physics/physics.npz (keys of SESSION_FORMAT.md, SI units, world frame; extra keys:
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
from intercap.io.files import read_json, save_npz

log = logging.getLogger(__name__)

G = 9.81
SOLE_POINTS = 4
OBJECT_POINTS = 16


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
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise PhysicsError(f"{session.root / 'session.yaml'}: `body.mass_kg` must be a positive number, got {value!r}")
    return float(value)


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
    order = np.concatenate([ids["landmarks"], ids["soles"].ravel(), *ids["hands"]])
    with torch.no_grad():
        for s in range(0, T, chunk):
            p = params[s:s + chunk]
            out = core(model._pose_matrices(p), phenotype_kwargs=p.shape, facial_actions=p.expression)
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
    return BodyTrack(np.concatenate(heads), np.concatenate(rots),
                     {name: picks[:, k] for k, name in enumerate(ids["landmark_names"])},
                     picks[:, L:L + n_sole].reshape(T, *ids["soles"].shape, 3),
                     np.stack([picks[:, L + n_sole:L + n_sole + len(ids["hands"][0])].mean(1),
                               picks[:, L + n_sole + len(ids["hands"][0]):].mean(1)], 1),
                     np.concatenate(lowest))


def ne_rot(axis_angle: torch.Tensor) -> torch.Tensor:
    from intercap.body_models import axis_angle_to_matrix

    return axis_angle_to_matrix(axis_angle.double())


def body_landmarks(model, rest_vertices: np.ndarray) -> dict:
    """Vertex ids at rest (anny: z up, facing -y): head top, heels and toe tips, four sole corners
    per foot, the palm regions."""
    core = _anny_core(model)
    dominant = model._dense_weights(core).argmax(1)
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
    return {"landmark_names": out_names, "landmarks": np.array(ids), "soles": np.array(soles), "hands": hands}


# -- the analysis ------------------------------------------------------------------------------
def analyse(out_dir, session, cfg=None, progress: bool = False) -> dict:
    """Forces, torques and flight of a finished results folder; writes OUT/physics/physics.npz and
    returns the figures (metrics.json's `physics` entry). PhysicsError with a clear message when a
    result, the floor or the body mass is missing."""
    from intercap.body_models import BodyParams
    from intercap.body_models.base import PARAM_FIELDS
    from intercap.config import Config

    cfg = cfg or Config()
    pc = cfg.physics
    out_dir = Path(out_dir)
    start = time.perf_counter()
    point, up, ground_source = load_gravity(out_dir, session)
    gravity = -G * up
    T, fps = session.num_frames, float(session.fps)
    frame_ids = np.asarray(session.frame_ids)

    # body
    saved = dict(np.load(_require(out_dir / "body_params.npz", "global")))
    model = shared_model(dataclasses.replace(cfg.body_model, name=session.body_model))
    if str(saved.get("model", model.name)) != model.name:
        raise PhysicsError(f"{out_dir / 'body_params.npz'} holds a {saved['model']} fit, the session asks for {model.name}")
    if len(saved["transl"]) != T:
        raise PhysicsError(f"{out_dir / 'body_params.npz'} has {len(saved['transl'])} frames, the session {T}")
    body_valid = saved["valid"].astype(bool) if "valid" in saved else np.ones(T, bool)
    body_valid &= np.isfinite(saved["transl"]).all(1)
    if not body_valid.any():
        raise PhysicsError(f"{out_dir / 'body_params.npz'}: no frame has a body fit")
    arrays = {k: kin.fill_gaps(saved[k], body_valid).astype(np.float64) for k in PARAM_FIELDS}
    shape = saved["shape_mean"] if "shape_mean" in saved else saved["shape"][body_valid].mean(0)
    arrays["shape"][:] = shape
    params = BodyParams.from_numpy_dict(arrays, dtype=model.dtype)

    rest = model.init_params(1)
    rest.shape[:] = torch.as_tensor(shape, dtype=model.dtype)
    core = _anny_core(model)
    with torch.no_grad():
        rest_out = core(model._pose_matrices(rest), phenotype_kwargs=rest.shape, facial_actions=rest.expression)
    rest_vertices = rest_out["vertices"][0].double().numpy()
    rest_bones = rest_out["bone_poses"][0].double().numpy()
    given = session_body_mass(session)
    if given is not None:
        body_mass, body_source = given, "session.yaml body.mass_kg"
    else:
        try:
            body_mass = mass_model.body_mass_from_volume(rest_vertices, model.faces.numpy(), pc.body_density_kg_m3)
        except mass_model.MassError as exc:
            raise PhysicsError(f"physics: {exc}; give `body: {{mass_kg: ...}}` in {session.root / 'session.yaml'}") from exc
        body_source = f"rest mesh volume x {pc.body_density_kg_m3:g} kg/m^3"
    if pc.sex not in ("auto", "male", "female"):
        raise PhysicsError(f"physics.sex must be auto, male or female, got {pc.sex!r}")
    labels = list(core.phenotype_labels)
    female = {"male": 0.0, "female": 1.0}.get(pc.sex, float(shape[labels.index("gender")]) if "gender" in labels else 0.5)
    ids = body_landmarks(model, rest_vertices)
    rest_landmarks = {n: rest_vertices[i] for n, i in zip(ids["landmark_names"], ids["landmarks"])}
    segments = mass_model.build_segments(list(model.joint_names), rest_bones[:, :3, 3], rest_bones[:, :3, :3],
                                         rest_landmarks, body_mass, female, np.array([1.0, 0, 0]))
    track = pose_body(model, params, ids, np.zeros(3) if point is None else point, up)
    if point is None:  # the floor under the body's lowest vertex (5th percentile over the frames)
        point = up * np.nanpercentile(track.lowest[body_valid], 5)
        track.lowest -= point @ up
    bone_index = {b: i for i, b in enumerate(model.joint_names)}
    parents = np.asarray(core.bone_parents)

    # body kinematics and needs
    filt = dict(method=pc.filter, window_s=pc.filter_window_s, order=pc.filter_order, cutoff_hz=pc.cutoff_hz)
    com = mass_model.segment_coms(segments, bone_index, track.heads, track.landmarks)  # (T, S, 3)
    _, _, com_acc = kin.derivatives(com, fps, **filt)
    Rf, omega, alpha = kin.quaternion_derivatives(track.rotations[:, segments.carrier], fps, **filt)
    Q = Rf @ segments.carrier_rest.transpose(0, 2, 1)[None]  # (T, S, 3, 3) rotation from rest
    td = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    g_t = td(gravity)
    F = ne.newton_force(td(segments.mass), td(com_acc), g_t)
    N = ne.euler_torque(ne.rotate_inertia(td(segments.inertia_rest), td(Q)), td(omega), td(alpha))
    joints = td(track.heads)
    f0, t0 = ne.joint_wrenches(parents, segments.carrier, F, N, td(com), joints)
    body_wrench = torch.cat([f0[:, 0], t0[:, 0]], -1).numpy()  # (T, 6) about the root
    root = track.heads[:, 0]

    # object
    obj_info = session.object
    has_object = obj_info is not None and (out_dir / "object_poses.npz").exists()
    object_mass, object_source = float("nan"), "no object"
    obj_wrench = obj_com_w = obj_points = obj_active = hand_active = None
    obj_valid = np.zeros(T, bool)
    centres = np.full((T, 3), np.nan)
    obj_on_ground = np.zeros(T, bool)
    if obj_info is not None and not has_object:
        raise PhysicsError(f"physics: {out_dir / 'object_poses.npz'} is missing; run the `global` stage first")
    if has_object:
        with np.load(out_dir / "object_poses.npz") as z:
            R_obj, t_obj = z["R"].astype(np.float64), z["t"].astype(np.float64)
            obj_valid = z["valid"].astype(bool) if "valid" in z else np.ones(T, bool)
        obj_valid &= np.isfinite(R_obj).all((1, 2)) & np.isfinite(t_obj).all(1)
        mesh = obj_info.load_mesh()
        object_mass, object_source = mass_model.object_mass(obj_info.mass_kg, getattr(obj_info, "density_kg_m3", None),
                                                            mesh.vertices, mesh.faces)
        com_local, inertia_local = mass_model.object_inertia(mesh.vertices, mesh.faces,
                                                             object_mass if np.isfinite(object_mass) else 1.0)
        centres = np.einsum("tij,j->ti", R_obj, com_local) + t_obj
        centres[~obj_valid] = np.nan
        from intercap.body_models.regions import farthest_point_subsample

        sub = np.asarray(mesh.vertices)[farthest_point_subsample(np.asarray(mesh.vertices), OBJECT_POINTS)]
        obj_points = np.einsum("tij,kj->tki", R_obj, sub) + t_obj[:, None]  # (T, Q, 3)
        heights = (obj_points - point) @ up
        obj_active = np.nan_to_num(heights, nan=np.inf) < pc.object_ground_m
        obj_on_ground = obj_active.any(1)
        hand_active = hand_contacts(out_dir, T) & obj_valid[:, None]
        if np.isfinite(object_mass) and obj_valid.any():
            Ro, w_o, al_o = kin.quaternion_derivatives(kin.fill_gaps(R_obj, obj_valid), fps, **filt)
            _, _, acc_o = kin.derivatives(kin.fill_gaps(centres, obj_valid), fps, **filt)
            Fo, No = ne.rigid_body_wrench(object_mass, td(Ro @ inertia_local @ Ro.transpose(0, 2, 1)), td(acc_o),
                                          td(w_o), td(al_o), g_t)
            obj_wrench = torch.cat([Fo, No], -1).numpy()
            obj_wrench[~obj_valid] = np.nan
            obj_com_w = kin.fill_gaps(centres, obj_valid)
        elif not obj_valid.any():
            log.warning("physics: the object was tracked in no frame; hand and object forces are skipped")
        else:
            log.warning("physics: object mass %s; hand and object forces are skipped", object_source)

    # contacts
    soles = track.soles  # (T, 2, P, 3)
    foot_active = ((soles - point) @ up) < pc.foot_contact_m
    body_wrench[~body_valid] = np.nan
    sol = cf.solve_contacts(body_wrench, root, soles, foot_active, up, pc.mu, obj_wrench, obj_com_w,
                            track.hands, hand_active if obj_wrench is not None else None, obj_points, obj_active,
                            edges=pc.friction_edges, object_weight=pc.object_weight)
    foot_force = sol.foot_point_force.sum(2)  # (T, 2, 3)
    fn = sol.foot_point_force @ up  # (T, 2, P)
    with np.errstate(invalid="ignore", divide="ignore"):
        cop = np.einsum("tfp,tfpi->tfi", fn, soles) / fn.sum(2)[..., None]
    cop[fn.sum(2) < 1e-6] = np.nan
    cop = cop - ((cop - point) @ up)[..., None] * up  # on the floor

    # joint torques with the solved contacts: soles on the foot bones, hand reactions on the wrists
    P = soles.shape[2]
    ext_bone = [bone_index["foot.L"]] * P + [bone_index["foot.R"]] * P + [bone_index["wrist.L"], bone_index["wrist.R"]]
    hand_f = np.nan_to_num(sol.hand_force)
    hand_t = np.nan_to_num(sol.hand_torque)
    ext_f = np.concatenate([np.nan_to_num(sol.foot_point_force).reshape(T, 2 * P, 3), -hand_f], 1)
    ext_t = np.concatenate([np.zeros((T, 2 * P, 3)), -hand_t], 1)
    ext_p = np.concatenate([soles.reshape(T, 2 * P, 3), track.hands], 1)
    _, joint_torque = ne.joint_wrenches(parents, segments.carrier, F, N, td(com), joints, ext_bone, td(ext_f),
                                        td(ext_t), td(ext_p))
    joint_torque = joint_torque.numpy()
    valid = body_valid & np.isfinite(sol.body_residual).all(1)
    joint_torque[~valid] = np.nan

    object_known = obj_wrench is not None
    hand_force = np.where(object_known, sol.hand_force, np.nan)
    hand_torque = np.where(object_known, sol.hand_torque, np.nan)
    object_ground = sol.object_ground_force.sum(1) if object_known else np.full((T, 3), np.nan)

    # free flight
    flight = flight_analysis(centres, contact_labels(out_dir, T) | obj_on_ground, up, fps, pc.flight_min_frames,
                             pc.flight_max_residual_m) \
        if has_object else no_flight()

    arm = track.hands - root[:, None]  # the feet carry the body's needs plus what the hands push on the object
    feet_need = body_wrench.copy()
    feet_need[:, :3] += hand_f.sum(1)
    feet_need[:, 3:] += (np.cross(arm, hand_f) + hand_t).sum(1)
    per_frame = plausibility_arrays(feet_need, root, soles, foot_active, up, pc, fps, track.lowest, point,
                                    obj_points, obj_valid)
    arrays = dict(frame_ids=frame_ids, gravity=gravity, body_mass_kg=np.float64(body_mass),
                  object_mass_kg=np.float64(object_mass), hand_force=hand_force, hand_torque=hand_torque,
                  hand_point=track.hands, foot_force=foot_force, foot_cop=cop, object_ground_force=object_ground,
                  joint_torque=joint_torque, joint_names=np.array(model.joint_names),
                  residual_force=sol.body_residual[:, :3], residual_torque=sol.body_residual[:, 3:],
                  object_residual_force=sol.object_residual[:, :3], object_residual_torque=sol.object_residual[:, 3:],
                  valid=valid, flight_episodes=flight["episodes"], flight_acceleration=flight["acceleration"],
                  flight_gravity_angle_deg=flight["gravity_angle_deg"], flight_runs_held=flight["held"],
                  foot_contact=foot_active, foot_points=soles,
                  hand_contact=np.zeros((T, 2), bool) if hand_active is None else hand_active,
                  mu=np.float64(pc.mu), body_mass_source=np.array(body_source),
                  object_mass_source=np.array(object_source), **per_frame)
    save_npz(out_dir / "physics" / "physics.npz", **arrays)
    figures = plausibility.summarise(arrays)
    figures.update({
        "body_mass_kg": body_mass, "body_mass_source": body_source,
        "object_mass_kg": None if not np.isfinite(object_mass) else object_mass, "object_mass_source": object_source,
        "object_forces": ("solved" if object_known else "no object" if not has_object
                          else "skipped: object tracked in no frame" if not obj_valid.any()
                          else f"skipped: object mass {object_source}"),
        "ground_source": ground_source, "frames_valid": int(valid.sum()),
    })
    if valid.any():
        figures["ground_reaction_mean_n"] = float(np.linalg.norm(foot_force[valid].sum(1), axis=-1).mean())
        if object_known:
            figures["hand_force_sum_mean_n"] = float(np.linalg.norm(np.nansum(hand_force[valid], 1), axis=-1).mean())
    figures["physics_seconds_per_frame"] = (time.perf_counter() - start) / max(T, 1)
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
