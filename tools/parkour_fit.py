"""LAAS Parkour benchmark: the clips, the dataset's force and pose errors, contact timing, and anny fitted to the mocap.

The LAAS Parkour dataset (Li et al., CVPR 2019) holds 28 short clips of kong vaults, muscle-ups, pull-ups and
safety vaults at 25 fps: 16 mocap joints (metres, world z up, floor at z = 0) and the 6D contact wrenches
measured at both feet (floor force plates, moments about the ankle joints) and both hands (sensors on the
structure; the dataset's extractor leaves their moments about the sensor's own origin), world-parallel axes.
Its evaluator scores the first T - 3 frames of a clip; this module reimplements its definitions
(`force_errors`, `joint_errors`) so the benchmark needs neither Python 2 nor its library.

    python tools/parkour_fit.py DATA_DIR [CLIP ...]   # per-clip fit and contact-timing summary

DATA_DIR is the dataset folder (holding gt_motion_forces/) or gt_motion_forces/ itself.
"""
from __future__ import annotations

import pickle
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

JOINT_NAMES = ("l_hip", "l_knee", "l_ankle", "l_toes", "r_hip", "r_knee", "r_ankle", "r_toes",
               "l_shoulder", "l_elbow", "l_wrist", "l_fingers", "r_shoulder", "r_elbow", "r_wrist", "r_fingers")
CONTACT_NAMES = ("left_foot", "right_foot", "left_hand", "right_hand")
ACTIONS = {"kv": "kong vault", "mu": "muscle-up", "pu": "pull-up", "sv": "safety vault"}
EVAL_TAIL = 3  # the evaluator leaves the last 3 frames of every clip out
FILES = ("joint_3d_positions.pkl", "contact_forces_local.pkl")

# Each Parkour joint -> the anny bone whose head stands for it (anny's rest pose: z up, facing -y, left +x).
ANNY_BONES = {
    "l_hip": "upperleg01.L", "l_knee": "lowerleg01.L", "l_ankle": "foot.L", "l_toes": "toe3-1.L",
    "r_hip": "upperleg01.R", "r_knee": "lowerleg01.R", "r_ankle": "foot.R", "r_toes": "toe3-1.R",
    "l_shoulder": "upperarm01.L", "l_elbow": "lowerarm01.L", "l_wrist": "wrist.L", "l_fingers": "finger3-1.L",
    "r_shoulder": "upperarm01.R", "r_elbow": "lowerarm01.R", "r_wrist": "wrist.R", "r_fingers": "finger3-1.R",
}
# The body bones the fit rotates (both sides); the rest (pelvis, neck, head, toes, eyes, hands) stay at rest.
FIT_BONES = ("spine05", "spine04", "spine03", "spine02", "spine01",
             *(f"{b}.{s}" for s in "LR" for b in ("clavicle", "shoulder01", "upperarm01", "upperarm02", "lowerarm01",
                                                  "lowerarm02", "wrist", "upperleg01", "upperleg02", "lowerleg01",
                                                  "lowerleg02", "foot")))
ALIGN_JOINTS = (0, 4, 8, 12)  # hips and shoulders: the rigid initialisation's points


# -- data --------------------------------------------------------------------------------------
@dataclass
class Clip:
    """One clip of the dataset: joints (T, 16, 3) m; forces (T, 4, 6) [N | N m]; uncaptured (T, 4) True where
    that wrench was not measured (its value then reads 0)."""

    name: str
    action: str
    fps: float
    joints: np.ndarray
    forces: np.ndarray
    uncaptured: np.ndarray

    @property
    def num_frames(self) -> int:
        return len(self.joints)


def _ground_truth_dir(data_dir: str | Path) -> Path:
    root = Path(data_dir)
    for folder in (root / "gt_motion_forces", root):
        if all((folder / name).is_file() for name in FILES):
            return folder
    raise ValueError(f"{root}: no LAAS Parkour ground truth there (expected {' and '.join(FILES)} "
                     f"in {root / 'gt_motion_forces'} or {root})")


def load_clips(data_dir: str | Path) -> dict[str, Clip]:
    """Every clip of the dataset at `data_dir` by name (the files are Python 2 pickles, read as latin-1)."""
    folder = _ground_truth_dir(data_dir)
    loaded = []
    for name in FILES:
        with open(folder / name, "rb") as handle:
            loaded.append(pickle.load(handle, encoding="latin1"))
    motion, wrenches = loaded
    clips = {}
    if set(motion) != set(wrenches):
        raise ValueError(f"{folder}: the two files hold different clips ({sorted(set(motion) ^ set(wrenches))})")
    for name in sorted(motion):
        m, w = motion[name], wrenches[name]
        if tuple(m["joint_names"]) != JOINT_NAMES:
            raise ValueError(f"{folder / FILES[0]}: clip {name} has joints {m['joint_names']}, expected {JOINT_NAMES}")
        clips[name] = Clip(name, ACTIONS.get(name[:2], "unknown"), float(m["fps"]),
                           np.asarray(m["joint_3d_positions"], np.float64),
                           np.asarray(w["contact_forces_local"], np.float64),
                           np.asarray(w["mask_uncaptured_forces"]).astype(bool))
    return clips


# -- the dataset's errors ----------------------------------------------------------------------
def force_errors(pred: np.ndarray, clip: Clip) -> dict[str, np.ndarray]:
    """The evaluator's contact-force errors of `pred` (T, 4, 6): over the first T - 3 frames, the norm of the
    captured linear (N) and moment (N m) differences per frame and contact, summed and divided by that
    contact's number of captured frames. {'linear_n': (4,), 'moment_nm': (4,)}."""
    n = clip.num_frames - EVAL_TAIL
    pred = np.asarray(pred, np.float64)
    if pred.shape[1:] != (4, 6) or len(pred) < n:
        raise ValueError(f"{clip.name}: forces must be ({clip.num_frames}, 4, 6), got {pred.shape}")
    captured = ~clip.uncaptured[:n]
    diff = (pred[:n] - clip.forces[:n]) * captured[..., None]
    count = captured.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):  # a contact never captured: nan, as the evaluator
        return {"linear_n": np.linalg.norm(diff[..., :3], axis=-1).sum(0) / count,
                "moment_nm": np.linalg.norm(diff[..., 3:], axis=-1).sum(0) / count}


def procrustes_align(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """`pred` (T, N, 3) moved onto `gt` frame by frame by the best rotation, scale and translation
    (Umeyama; a proper rotation): the evaluator's alignment."""
    a, b = pred - pred.mean(1, keepdims=True), gt - gt.mean(1, keepdims=True)
    u, sigma, vt = np.linalg.svd(a.transpose(0, 2, 1) @ b)  # (T, 3, 3)
    d = np.sign(np.linalg.det(u @ vt))
    sigma[:, -1] *= d
    vt[:, -1] *= d[:, None]
    rotation = u @ vt  # applied on the right: a @ rotation
    scale = sigma.sum(1) / (a ** 2).sum((1, 2))
    return scale[:, None, None] * a @ rotation + gt.mean(1, keepdims=True)


def joint_errors(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """MPJPE (mm) of `pred` against `gt` (T, 16, 3) m over the first T - 3 frames, as it stands ('raw') and after
    the per-frame Procrustes alignment ('procrustes', the dataset's figure)."""
    n = len(gt) - EVAL_TAIL
    pred, gt = np.asarray(pred, np.float64)[:n], np.asarray(gt, np.float64)[:n]
    raw = np.linalg.norm(pred - gt, axis=-1)
    aligned = np.linalg.norm(procrustes_align(pred, gt) - gt, axis=-1)
    return {"raw": 1000.0 * float(raw.mean()), "procrustes": 1000.0 * float(aligned.mean())}


# -- contact timing ----------------------------------------------------------------------------
def close_gaps(active: np.ndarray, gap: int = 1) -> np.ndarray:
    """(T, ...) bool with runs of at most `gap` False frames between two True frames set True."""
    out = active.copy()
    for g in range(1, gap + 1):
        for s in range(1, len(active) - g):
            hole = ~active[s:s + g].any(0) & active[s - 1] & active[s + g]
            out[s:s + g] |= hole
    return out


def sensor_contacts(clip: Clip, threshold_n: float = 20.0) -> np.ndarray:
    """(T, 4) bool: a contact is on where its sensor's linear force exceeds `threshold_n` (the measured timing),
    1-frame gaps closed. Uncaptured frames read False unless such a gap; compare on captured frames only."""
    on = (np.linalg.norm(clip.forces[..., :3], axis=-1) > threshold_n) & ~clip.uncaptured
    return close_gaps(on, 1)


def median_filter(active: np.ndarray, width: int = 3) -> np.ndarray:
    """(T, ...) bool: the majority over a centred window of `width` frames (edges repeated)."""
    half = width // 2
    padded = np.concatenate([active[:1].repeat(half, 0), active, active[-1:].repeat(half, 0)])
    votes = sum(padded[k:k + len(active)].astype(int) for k in range(width))
    return votes > half


def joint_speeds(joints: np.ndarray, fps: float) -> np.ndarray:
    """(T, N) m/s by central differences (one-sided at the ends)."""
    return np.linalg.norm(np.gradient(joints, axis=0), axis=-1) * fps if len(joints) > 1 else np.zeros(joints.shape[:2])


FOOT_HEIGHT_M = 0.12  # lowest of ankle and toes below this: near the floor
FOOT_SPEED_MPS = 0.15  # the slower of ankle and toes below this: planted on the floor
STILL_SPEED_MPS = 0.3  # an end joint (toes, fingers) slower than this: still
HAND_FLOOR_M = 0.3  # fingers above this: not on the floor
BODY_MOVE_M = 0.1  # a still spell counts where the body (hip, shoulder) moves this far against the end joint


def true_runs(active: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of every run of True in a (T,) bool."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], active.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def held(still: np.ndarray, end: np.ndarray, body: np.ndarray, move_m: float) -> np.ndarray:
    """(T,) bool: the still spells of an end joint (T, 3) in which the `body` point (T, 3) travels more than
    `move_m` relative to it: the body moving over a planted hand or foot, not a person standing still."""
    relative = body - end
    out = np.zeros_like(still)
    for s, e in true_runs(still):
        out[s:e] = np.linalg.norm(relative[s:e] - relative[s], axis=-1).max() > move_m
    return out


def motion_contacts(joints: np.ndarray, fps: float, foot_height_m: float = FOOT_HEIGHT_M,
                    foot_speed_mps: float = FOOT_SPEED_MPS, still_speed_mps: float = STILL_SPEED_MPS,
                    hand_floor_m: float = HAND_FLOOR_M, body_move_m: float = BODY_MOVE_M,
                    median: int = 5) -> np.ndarray:
    """(T, 4) bool contact timing from the joints alone (world z up, floor at 0), thresholds tuned against
    `sensor_contacts` on the dataset. A foot touches while its ankle or toes are near the floor and slow, or
    while its toes stay still as the hip moves over them (a step on the obstacle); a hand holds the fixed
    structure while its fingers stay still away from the floor as the shoulder moves against them (so hands
    kept still by someone standing are no contact). A `median`-frame majority filter removes flickers."""
    speed = joint_speeds(joints, fps)
    height = joints[..., 2]
    feet = []
    for ankle, toes, hip in ((2, 3, 0), (6, 7, 4)):
        slowest = speed[:, [ankle, toes]].min(1)
        floor = (height[:, [ankle, toes]].min(1) < foot_height_m) & (slowest < foot_speed_mps)
        feet.append(floor | held(slowest < still_speed_mps, joints[:, toes], joints[:, hip], body_move_m))
    hands = [held((speed[:, fingers] < still_speed_mps) & (height[:, fingers] > hand_floor_m),
                  joints[:, fingers], joints[:, shoulder], body_move_m) for fingers, shoulder in ((11, 8), (15, 12))]
    return median_filter(np.stack(feet + hands, 1), median)


def contact_agreement(clips: dict[str, Clip], **kwargs) -> np.ndarray:
    """(4,) % of captured frames over all clips where `motion_contacts` agrees with `sensor_contacts`."""
    same, count = np.zeros(4), np.zeros(4)
    for clip in clips.values():
        captured = ~clip.uncaptured
        same += ((motion_contacts(clip.joints, clip.fps, **kwargs) == sensor_contacts(clip)) & captured).sum(0)
        count += captured.sum(0)
    return 100.0 * same / count


# -- anny fitted to the mocap joints -----------------------------------------------------------
@dataclass
class FitWeights:
    """The fit's energy per frame: robust squared joint distances in cm^2 (pseudo-Huber, `robust_m`: mocap
    glitches move a joint by a metre now and then), priors in their own units."""

    robust_m: float = 0.05  # the data term is quadratic below this distance, linear above
    pose: float = 0.01  # per rad^2 of every fitted bone's rotation vector
    limits: float = 100.0  # per rad^2 beyond the anatomical ranges (intercap.energies.priors)
    smooth: float = 2e-4  # per (rad/s^2)^2 of every fitted bone's angular acceleration (second differences)
    offsets: float = 0.1  # per cm^2 of each joint's offset from its bone head
    shape: float = 1.0  # intercap.energies.priors.shape_prior


def default_model():
    """The project's anny model (float32, CPU), built once per process."""
    from intercap.body_models import shared_model
    from intercap.config import BodyModelConfig

    return shared_model(BodyModelConfig())


def rigid_fit(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R (T, 3, 3), t (T, 3)) with target[t] ~ R[t] source + t[t] (Kabsch, a proper rotation), for
    source (N, 3) and target (T, N, 3)."""
    a = source - source.mean(0)
    b = target - target.mean(1, keepdims=True)
    u, _, vt = np.linalg.svd(b.transpose(0, 2, 1) @ a)  # (T, 3, 3): sum b a^T
    d = np.sign(np.linalg.det(u @ vt))
    u[:, :, -1] *= d[:, None]
    rotation = u @ vt
    return rotation, target.mean(1) - rotation @ source.mean(0)


class BoneChain:
    """anny's forward kinematics ('local-ref', `AnnyBody.bone_transforms`) restricted to the bones the 16
    joints hang from (38 of 104), rotations and translations apart: a bone's frame is W_c = W_p K_c with
    K_c = [U_p^T D_c U_c | q_c] (U the reference orientations, D_c its pose rotation, q_c its link from the
    rest state), composed by pointer doubling; above the root the placement [R(global_orient) | transl].
    The model's own chain composes 4x4 frames of every bone: with its gradient, 3.6 times slower here (135
    frames, one core). anny only (its reference orientations and rest links)."""

    def __init__(self, model, bones: list[int], fitted: list[int]):
        parent = model.bone_parent.tolist()
        needed = set()
        for b in bones:
            while b not in needed:
                needed.add(b)
                b = parent[b]
        order = sorted(needed)
        self.ids = torch.tensor(order)  # model bone index of each chain node
        where = {b: k for k, b in enumerate(order)}
        n = len(order)
        top, identity = n, n + 1  # the placement and the identity, above the root
        ancestor = [top if parent[b] == b else where[parent[b]] for b in order] + [identity, identity]
        self.ancestors = []
        step = torch.tensor(ancestor)
        while bool((step[:n + 1] != identity).any()):
            self.ancestors.append(step)
            step = step[step]
        U = model.core.reference_bone_orientations
        self.left = U[[parent[b] for b in order]].mT.contiguous()  # (n, 3, 3) U_p^T
        self.right = U[order].contiguous()
        names = list(model.joint_names)
        source = {model.joint_names.index(model.body_joint_names[f]): k for k, f in enumerate(fitted)}
        self.sources = torch.tensor([source.get(b, len(fitted)) for b in order])  # len(fitted): identity
        self.select = torch.tensor([where[b] for b in bones])
        self.names = [names[b] for b in order]

    def __call__(self, global_orient: torch.Tensor, transl: torch.Tensor, pose: torch.Tensor,
                 links: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World (rotations (T, N, 3, 3), heads (T, N, 3)) of the selected bones, for global_orient and
        transl (T, 3), the fitted bones' rotation vectors pose (T, K, 3) and the rest links q (J, 3)."""
        from intercap.body_models import axis_angle_to_matrix

        T = len(pose)
        eye = torch.eye(3, dtype=pose.dtype).expand(T, 2, 3, 3)
        rotations = axis_angle_to_matrix(torch.cat([pose, global_orient[:, None]], 1))  # (T, K + 1, 3, 3)
        D = torch.cat([rotations[:, :-1], eye[:, :1]], 1).index_select(1, self.sources)
        R = torch.cat([self.left @ D @ self.right, rotations[:, -1:], eye[:, 1:]], 1)  # (T, n + 2, 3, 3)
        t = torch.cat([links.index_select(0, self.ids).expand(T, -1, -1), transl[:, None],
                       transl.new_zeros(T, 1, 3)], 1)
        for ancestors in self.ancestors:  # (R_a, t_a) o (R_c, t_c) = (R_a R_c, R_a t_c + t_a)
            Ra, ta = R.index_select(1, ancestors), t.index_select(1, ancestors)
            R, t = Ra @ R, (Ra @ t[..., None])[..., 0] + ta
        return R.index_select(1, self.select), t.index_select(1, self.select)


# The limbs `swing_pose` points along the joints: (side, bones, Parkour joints from the limb's root to its end).
LIMBS = (("L", ("upperleg01", "lowerleg01", "foot"), (0, 1, 2, 3)),
         ("R", ("upperleg01", "lowerleg01", "foot"), (4, 5, 6, 7)),
         ("L", ("upperarm01", "lowerarm01", "wrist"), (8, 9, 10, 11)),
         ("R", ("upperarm01", "lowerarm01", "wrist"), (12, 13, 14, 15)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True).clip(1e-9)


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T, 3, 3) the smallest rotations taking the directions a (T, 3) onto b (T, 3)."""
    from scipy.spatial.transform import Rotation

    a, b = _unit(a), _unit(b)
    axis = np.cross(a, b)
    angle = np.arctan2(np.linalg.norm(axis, axis=-1), (a * b).sum(-1))
    opposite = np.linalg.norm(axis, axis=-1) < 1e-9  # half a turn (or none): any axis normal to a
    axis[opposite] = np.cross(a[opposite], np.where(np.abs(a[opposite, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    return Rotation.from_rotvec(_unit(axis) * angle[:, None]).as_matrix()


def _frame(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """(..., 3, 3) orthonormal columns: primary, secondary made orthogonal to it, their cross product."""
    a = _unit(primary)
    b = _unit(secondary - (secondary * a).sum(-1, keepdims=True) * a)
    return np.stack([a, b, np.cross(a, b)], -1)


def swing_pose(rest: np.ndarray, joints: np.ndarray, root: np.ndarray) -> np.ndarray:
    """(T, len(FIT_BONES), 3) rotation vectors pointing each limb segment of the rest skeleton (the mapped
    bone heads, rest (16, 3)) along the joints (T, 16, 3), the body placed by `root` (T, 3, 3): the fit's
    start. anny's 'local-ref' pose composes world rotations as G_child = G_parent D_child. The thigh and the
    upper arm also turn their hinge (knee: model x; elbow: its rest bend) normal to the limb's plane where
    the limb is bent; the other segments take the smallest rotation from their parent's."""
    from scipy.spatial.transform import Rotation

    T = len(joints)
    pose = np.zeros((T, len(FIT_BONES), 3))
    column = {name: k for k, name in enumerate(FIT_BONES)}
    for side, bones, (a, b, c, d) in LIMBS:
        seg = [(rest[j] - rest[i], joints[:, j] - joints[:, i]) for i, j in ((a, b), (b, c), (c, d))]
        if bones[0].startswith("upperleg"):
            hinge = np.array([1.0, 0.0, 0.0])
        else:
            hinge = _unit(np.cross(seg[0][0], seg[1][0]))
        normal = np.cross(_unit(seg[0][1]), _unit(seg[1][1]))
        bent = np.linalg.norm(normal, axis=-1) > 0.25  # more than ~15 degrees
        parent = root
        for k, (bone, (rest_dir, target)) in enumerate(zip(bones, seg)):
            world = _min_rotation(np.einsum("tij,j->ti", parent, rest_dir), target) @ parent
            if k == 0:
                planar = _frame(target, normal) @ _frame(rest_dir, hinge).T
                world = np.where(bent[:, None, None], planar, world)
            pose[:, column[f"{bone}.{side}"]] = Rotation.from_matrix(parent.transpose(0, 2, 1) @ world).as_rotvec()
            parent = world
    return pose


def fit_anny(joints: np.ndarray, fps: float, iters: int = 150, model=None, offsets: bool = True,
             weights: FitWeights | None = None) -> tuple:
    """anny fitted to the 16 Parkour joints (T, 16, 3) of one clip, all frames in one optimisation: per-frame
    pose (FIT_BONES), orientation and translation, one shape for the clip (the subject's proportions) and,
    with `offsets`, one constant offset per joint in its bone's frame (the dataset's joints are marker
    centroids, e.g. its hips the mean of trochanter and iliac spine markers, not anny's joint centres).
    Starts from a rigid fit of the rest hips and shoulders to each frame with the limbs swung onto the joints
    (`swing_pose`); energy `FitWeights`, minimised by L-BFGS for at most `iters` iterations.

    Returns (BodyParams of T frames, fitted joints (T, 16, 3) m, info): info holds the MPJPE (mm) over all
    frames raw and after per-frame Procrustes, per joint, seconds, seconds per frame, L-BFGS steps and
    evaluations, the final energy, the mean joint-limit excess (rad^2), the offsets (16, 3) m in the bones'
    frames and the shape."""
    from intercap.body_models import matrix_to_axis_angle
    from intercap.body_models.base import replace
    from intercap.energies.optim import minimise
    from intercap.energies.priors import pose_priors, shape_prior

    start = time.perf_counter()
    model = model if model is not None else default_model()
    w = weights or FitWeights()
    dtype = model.dtype
    joints = np.asarray(joints, np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (16, 3) or not np.isfinite(joints).all():
        raise ValueError(f"joints must be finite (T, 16, 3), got {joints.shape}")
    T = len(joints)
    bones = [model.joint_names.index(b) for b in ANNY_BONES.values()]
    fitted_bones = [model.body_joint_names.index(b) for b in FIT_BONES]
    free = torch.tensor(fitted_bones)
    chain = BoneChain(model, bones, fitted_bones)
    base = model.init_params(T)
    vertex_ids = model.fitting_subsample[:1]  # rest_state wants a vertex set; only its bone links are used

    def links(shape: torch.Tensor) -> torch.Tensor:
        return model.rest_state(replace(base[0], shape=shape), vertex_ids).offsets[0, :, :3, 3]  # (J, 3)

    zero = torch.zeros(1, 3, dtype=dtype)
    with torch.no_grad():
        rest = chain(zero, zero, torch.zeros(1, len(free), 3, dtype=dtype), links(base.shape[:1]))[1][0]
    rest = rest.double().numpy()  # (16, 3) the mapped bone heads at rest, neutral shape
    align = list(ALIGN_JOINTS)
    rotation, translation = rigid_fit(rest[align], joints[:, align])
    global_orient = matrix_to_axis_angle(torch.as_tensor(rotation, dtype=dtype)).clone()
    transl = torch.as_tensor(translation, dtype=dtype).clone()  # the root sits at the model origin
    pose = torch.as_tensor(swing_pose(rest, joints, rotation), dtype=dtype).clone()
    # shape and offsets move every frame: scaled by 1 / sqrt(T), their curvature is like a frame's variables'
    # (L-BFGS starts from one step length for all; unscaled, these converged several times slower)
    unit = 1.0 / np.sqrt(T)
    shape_u = torch.zeros(1, model.num_shape, dtype=dtype)
    offset_u = torch.zeros(len(bones), 3, dtype=dtype)
    target = torch.as_tensor(joints, dtype=dtype)
    hands = base.left_hand_pose
    center = base.shape[:1]

    def posed() -> tuple[torch.Tensor, torch.Tensor]:
        shape = center + unit * shape_u
        R, heads = chain(global_orient, transl, pose, links(shape))
        return heads + (R @ (unit * offset_u)[:, :, None])[..., 0], shape

    def limit_excess() -> torch.Tensor:
        body_pose = base.body_pose.index_copy(1, free, pose)
        return pose_priors(body_pose, hands, hands, ("joint_limits",))["joint_limits"]  # (T,)

    def energy() -> torch.Tensor:
        points, shape = posed()
        squared = ((points - target) ** 2).sum(-1) / 1e-4  # cm^2
        s2 = (w.robust_m / 0.01) ** 2
        frame = (2.0 * s2 * (torch.sqrt(1.0 + squared / s2) - 1.0)).sum(1) + w.pose * (pose ** 2).sum((1, 2))
        if w.limits:
            frame = frame + w.limits * limit_excess()
        total = frame.mean()
        if T >= 3:
            acceleration = (pose[2:] - 2.0 * pose[1:-1] + pose[:-2]) * fps ** 2
            total = total + w.smooth * (acceleration ** 2).sum((1, 2)).mean()
        shared = w.shape * shape_prior(shape).sum()
        if offsets:
            shared = shared + w.offsets * ((unit * offset_u) ** 2).sum() / 1e-4
        return total + shared

    variables = [shape_u, global_orient, transl, pose] + ([offset_u] if offsets else [])
    result = minimise(variables, energy, max_steps=max(1, iters // 10), inner_iterations=10, ftol=1e-7)
    with torch.no_grad():
        points, shape = posed()
        excess = float(limit_excess().mean())
    params = replace(base, shape=shape.clamp(0.0, 1.0).expand(T, -1).clone(), global_orient=global_orient.detach(),
                     transl=transl.detach(), body_pose=base.body_pose.index_copy(1, free, pose.detach()))
    fitted = points.double().numpy()
    raw = np.linalg.norm(fitted - joints, axis=-1)
    aligned = np.linalg.norm(procrustes_align(fitted, joints) - joints, axis=-1)
    seconds = time.perf_counter() - start
    info = {"mpjpe_mm": 1000.0 * float(raw.mean()), "pa_mpjpe_mm": 1000.0 * float(aligned.mean()),
            "per_joint_mm": 1000.0 * raw.mean(0), "seconds": seconds, "seconds_per_frame": seconds / T,
            "steps": result.steps, "evaluations": result.evaluations, "energy": result.energy,
            "stopped": result.stopped, "limit_excess": excess,
            "offsets_m": (unit * offset_u).detach().double().numpy(), "shape": shape.double().numpy()[0]}
    return params, fitted, info


def main(argv: list[str] | None = None) -> int:
    """Fit every clip (or the named ones) and print the fit errors, speed and contact-timing agreement."""
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data_dir", help="the LAAS Parkour dataset folder (or its gt_motion_forces/)")
    parser.add_argument("clips", nargs="*", help="clip names (default: all)")
    parser.add_argument("--iters", type=int, default=150, help="L-BFGS iterations per clip")
    args = parser.parse_args(argv)
    try:
        clips = load_clips(args.data_dir)
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 2
    unknown = [name for name in args.clips if name not in clips]
    if unknown:
        print(f"unknown clips {unknown}; the dataset has {sorted(clips)}", file=sys.stderr)
        return 2
    chosen = {name: clips[name] for name in (args.clips or clips)}
    model = default_model()
    print(f"{'clip':<10} {'action':<13} {'T':>4} {'raw mm':>7} {'PA mm':>6} {'s/frame':>8}   contact agreement % "
          f"({', '.join(CONTACT_NAMES)})")
    frames, seconds, raw, aligned = 0, 0.0, [], []
    for name, clip in chosen.items():
        _, fitted, info = fit_anny(clip.joints, clip.fps, iters=args.iters, model=model)
        errors = joint_errors(fitted, clip.joints)
        agreement = contact_agreement({name: clip})
        frames, seconds = frames + clip.num_frames, seconds + info["seconds"]
        raw.append(errors["raw"])
        aligned.append(errors["procrustes"])
        print(f"{name:<10} {clip.action:<13} {clip.num_frames:>4} {errors['raw']:>7.1f} {errors['procrustes']:>6.1f} "
              f"{info['seconds_per_frame']:>8.3f}   {' '.join(f'{a:5.1f}' for a in agreement)}")
    overall = contact_agreement(chosen)
    print(f"{len(chosen)} clips, {frames} frames: MPJPE raw {np.mean(raw):.1f} mm (worst {np.max(raw):.1f}), "
          f"Procrustes {np.mean(aligned):.1f} mm; {seconds:.0f} s ({seconds / frames:.3f} s/frame); "
          f"contact agreement {', '.join(f'{n} {a:.1f}%' for n, a in zip(CONTACT_NAMES, overall))}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repository's packages
    raise SystemExit(main())
