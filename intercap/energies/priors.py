"""Priors of the body fit: joint limits, extreme bending, hands, learned body pose, shape, expression.

anny has no VPoser, so the body-pose prior is built here from two parts:

* **Joint limits from anatomy** (`joint_limit_penalty`). Each anatomical joint
  (knee, hip, elbow, ...) is one anny bone or two composed (anny splits thigh,
  shin, upper arm and forearm in two bones: the second carries no joint of its
  own, so the limit applies to the composed rotation D_01 @ D_02 of the pair,
  i.e. the distal half relative to the parent segment; the twists of the two
  bones add up, and the second bone alone may swing at most `SECOND_BONE_SWING`).
  The rotation is expressed in the joint's anatomical frame (flexion axis,
  abduction axis, segment axis) and split into swing and twist about the
  segment axis; the swing's two log-map components are the flexion and
  abduction angles, the twist is the axial rotation. Excursions beyond the
  ranges of motion in `BODY_JOINTS` (degrees, anatomical sign conventions, left
  side; the right side is its mirror image) cost a squared hinge in radians.
  Ranges follow the usual clinical tables (AAOS / Kapandji), widened where real
  CMU mocap poses showed they were too tight (see tools/train_pose_prior.py).
* **A learned prior** (`learned_pose_prior`): a Gaussian mixture over the
  rotations of the major joints, trained on CMU mocap retargeted to anny
  (tools/train_pose_prior.py), shipped in intercap/data/body_pose_prior.npz.

Spine and neck are limited bone by bone (no kinks) and as chains (thoracolumbar and
cervical totals). Shoulder twist is path dependent far from the A-pose (Codman's
paradox), so its range widens with the swing beyond 90 deg.

`extreme_bending` is the elbow and knee part of the limits (SMPLify-X's term),
`hand_pose_prior` the same construction for the 19 bones of each hand plus a
soft DIP-follows-PIP coupling. No open finger-motion data could be found, so
the hand prior is anatomy only. Frames and rest offsets are measured once on
anny's rest skeleton (`anatomy_from_model`) and shipped in
intercap/data/anny_anatomy.npz, so these functions need no body model.
All functions take batches and return (B,) tensors; zero (or the minimum) for
plausible input, differentiable everywhere used by the fit. They are anny's
(bone names and frames); `joint_angles` / `body_pose_from_joint_angles` and
`hand_angles` / `hand_pose_from_angles` convert between poses and anatomical angles.

Public: joint_limit_penalty, extreme_bending, hand_pose_prior, hands_pose_prior, learned_pose_prior,
shape_prior, expression_prior; joint_angles, joint_angle_names, joint_limit_excess,
body_pose_from_joint_angles, hand_angles, hand_pose_from_angles, learned_features, mirror_body_pose.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import roma
import torch

DATA_DIR = Path(__file__).resolve().parents[1] / "data"  # intercap/data
ANATOMY_FILE = DATA_DIR / "anny_anatomy.npz"
POSE_PRIOR_FILE = DATA_DIR / "body_pose_prior.npz"
# Mirror a right-side rotation vector into the left side's convention (model x is the person's left).
MIRROR = (1.0, -1.0, -1.0)
SECOND_BONE_SWING = 10.0  # degrees a thigh/shin/arm/forearm second bone may swing on its own
HAND_COUPLING_WEIGHT = 0.5  # DIP ~ 2/3 PIP, relative to the hinge terms
DIP_PIP_RATIO = 2.0 / 3.0
X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
NX, NY, NZ = (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0)


@dataclass(frozen=True)
class Joint:
    """One anatomical joint of the left side (or the midline), and its range of motion.

    bones: anny bones composed parent first (no side suffix); `end`: the bone whose
    rest head ends the segment (or a fixed direction) - the twist axis;
    `flex_dir` / `abd_dir`: where the segment's end moves for positive flexion /
    abduction (model axes: x left, -y forward, z up), or 'elbow' / 'palm' /
    'radial' for axes measured on the skeleton; `twist_probe` turns towards
    `twist_to` for positive twist. Ranges in degrees, anatomical (`rest` names
    the angles whose rest value is measured and subtracted: anny's A-pose has
    the shoulder abducted and the elbow bent)."""

    name: str
    bones: tuple[str, ...]
    end: str | tuple[float, float, float]
    flex_dir: str | tuple[float, float, float]
    abd_dir: str | tuple[float, float, float]
    twist_probe: tuple[float, float, float]
    twist_to: tuple[float, float, float]
    flex: tuple[float, float]
    abd: tuple[float, float]
    twist: tuple[float, float]
    sided: bool = True
    rest: tuple[str, ...] = ()
    twist_widening: float = 0.0  # twist range grows by this * (swing - 90 deg) beyond 90 deg of swing


SPINE = dict(flex_dir=NY, abd_dir=X, twist_probe=NY, twist_to=X, sided=False)
NECK = dict(end=Z, **SPINE)
# Ranges: flexion positive (hip: thigh forward, knee/elbow: bend, ankle: plantarflexion, wrist: palm-ward,
# spine/neck: forward), abduction positive away from the midline (spine/neck: bend to the left, clavicle:
# forward/protraction, wrist: radial deviation), twist positive = external rotation (spine/neck: turn left,
# ankle: inversion). Clinical ranges (AAOS, Kapandji) unless marked "CMU": widened because retargeted
# CMU mocap went further (tools/train_pose_prior.py reports how often real poses leave each range).
BODY_JOINTS: tuple[Joint, ...] = (
    Joint("pelvis", ("pelvis",), "upperleg01", NY, Z, NY, X, (-5, 5), (-5, 5), (-5, 5)),  # rigid
    Joint("hip", ("upperleg01", "upperleg02"), "lowerleg01", NY, X, NY, X,
          (-35, 140), (-40, 65), (-50, 55)),  # CMU: abduction 45 -> 65 (climbing)
    Joint("knee", ("lowerleg01", "lowerleg02"), "foot", Y, X, NY, X,
          (-8, 160), (-10, 10), (-50, 45), rest=("flex",)),  # CMU: axial +-40 -> -50/45
    Joint("ankle", ("foot",), "toe3-1", NZ, X, NZ, NX, (-50, 65), (-35, 35), (-30, 40)),  # CMU: dorsiflexion 30 -> 50
    Joint("toe_mtp", ("toe1-1", "toe2-1", "toe3-1", "toe4-1", "toe5-1"), NY, NZ, X, NZ, NX,
          (-75, 70), (-20, 20), (-15, 15)),  # CMU: flexion 45 -> 70 (a coarse toe segment)
    Joint("toe_ip", ("toe1-2", "toe2-2", "toe2-3", "toe3-2", "toe3-3", "toe4-2", "toe4-3", "toe5-2", "toe5-3"),
          NY, NZ, X, NZ, NX, (-15, 70), (-10, 10), (-10, 10)),
    # Each spine / neck bone on its own (no kinks), and the chain as a whole (thoracolumbar / cervical totals).
    Joint("spine05", ("spine05",), "spine04", flex=(-25, 35), abd=(-20, 20), twist=(-20, 20), **SPINE),
    Joint("spine04", ("spine04",), "spine03", flex=(-25, 35), abd=(-20, 20), twist=(-20, 20), **SPINE),
    Joint("spine03", ("spine03",), "spine02", flex=(-25, 35), abd=(-20, 20), twist=(-20, 20), **SPINE),
    Joint("spine02", ("spine02",), "spine01", flex=(-25, 35), abd=(-20, 20), twist=(-20, 20), **SPINE),
    Joint("spine01", ("spine01",), "neck01", flex=(-25, 35), abd=(-20, 20), twist=(-20, 20), **SPINE),
    Joint("spine", ("spine05", "spine04", "spine03", "spine02", "spine01"), "neck01",
          flex=(-40, 100), abd=(-45, 45), twist=(-50, 50), **SPINE),
    Joint("neck01", ("neck01",), flex=(-25, 25), abd=(-25, 25), twist=(-30, 30), **NECK),
    Joint("neck02", ("neck02",), flex=(-25, 25), abd=(-25, 25), twist=(-30, 30), **NECK),
    Joint("neck03", ("neck03",), flex=(-25, 25), abd=(-25, 25), twist=(-30, 30), **NECK),
    Joint("neck", ("neck01", "neck02", "neck03"), flex=(-65, 55), abd=(-45, 45), twist=(-65, 65), **NECK),
    Joint("head", ("head",), flex=(-30, 30), abd=(-20, 20), twist=(-40, 40), **NECK),
    Joint("eye", ("eye",), NY, Z, X, Z, X, (-35, 35), (-40, 40), (-8, 8)),  # gaze: looking up / to the left
    Joint("clavicle", ("clavicle", "shoulder01"), "upperarm01", Z, NY, Z, NY, (-15, 50), (-30, 35), (-40, 40)),
    # Shoulder twist is measured after the shortest-arc swing from the A-pose; far from it (arm overhead)
    # that twist depends on the path (Codman's paradox), so its range widens with the swing.
    Joint("shoulder", ("upperarm01", "upperarm02"), "lowerarm01", NY, Z, NY, X, (-70, 185), (-45, 185), (-100, 120),
          rest=("abd",), twist_widening=1.0),  # CMU: external rotation 90 -> 120
    Joint("elbow", ("lowerarm01", "lowerarm02"), "wrist", "elbow", "radial", NY, X, (-10, 155), (-12, 12), (-105, 105),
          rest=("flex",)),  # twist = pronation / supination; CMU: +-90 -> +-105
    Joint("wrist", ("wrist",), "finger3-1", "palm", "radial", NY, X,
          (-80, 85), (-40, 45), (-30, 30)),  # CMU: radial deviation 25 -> 45, twist 15 -> 30 (see README)
)
EXTREME_BENDING_JOINTS = ("elbow", "knee")

# Hand bones (anny: finger1 = thumb ... finger5 = little; metacarpal k carries finger k+1).
# Flexion = curl towards the palm (anny's finger_flex_axes), abduction towards the thumb side.
HAND_RANGES = {
    "finger1-1": ((-25, 55), (-45, 45), (-40, 40)),  # thumb CMC, opposition
    "finger1-2": ((-15, 70), (-15, 15), (-20, 20)),  # thumb MCP
    "finger1-3": ((-25, 90), (-10, 10), (-10, 10)),  # thumb IP
    "metacarpal1": ((-8, 8), (-8, 8), (-8, 8)),
    "metacarpal2": ((-8, 8), (-8, 8), (-8, 8)),
    "metacarpal3": ((-8, 18), (-10, 10), (-10, 10)),
    "metacarpal4": ((-8, 28), (-12, 12), (-12, 12)),
}
for _k in range(2, 6):
    HAND_RANGES[f"finger{_k}-1"] = ((-30, 100), (-25, 25), (-15, 15))  # MCP
    HAND_RANGES[f"finger{_k}-2"] = ((-10, 115), (-8, 8), (-10, 10))  # PIP
    HAND_RANGES[f"finger{_k}-3"] = ((-15, 95), (-8, 8), (-10, 10))  # DIP
HAND_BONES = (
    "finger1-1", "finger1-2", "finger1-3", "metacarpal1", "finger2-1", "finger2-2", "finger2-3",
    "metacarpal2", "finger3-1", "finger3-2", "finger3-3", "metacarpal3", "finger4-1", "finger4-2",
    "finger4-3", "metacarpal4", "finger5-1", "finger5-2", "finger5-3",
)

def body_joint_names_of_anny() -> list[str]:
    """anny's 65 body bones in body_pose order (fixed by the model; checked against it in the tests)."""
    toes = [f"toe{k}-{j}" for k in range(1, 6) for j in ((1, 2) if k == 1 else (1, 2, 3))]
    leg = ["pelvis", "upperleg01", "upperleg02", "lowerleg01", "lowerleg02", "foot"] + toes
    arm = ["clavicle", "shoulder01", "upperarm01", "upperarm02", "lowerarm01", "lowerarm02", "wrist"]
    return (
        [f"{b}.L" for b in leg] + [f"{b}.R" for b in leg] + ["spine05", "spine04", "spine03", "spine02", "spine01"]
        + [f"{b}.L" for b in arm] + [f"{b}.R" for b in arm]
        + ["neck01", "neck02", "neck03", "head", "eye.L", "eye.R"]
    )


ANNY_BODY_BONES = tuple(body_joint_names_of_anny())
SECOND_BONES = ("upperleg02", "lowerleg02", "upperarm02", "lowerarm02")
PER_BONE_JOINTS = ("toe_mtp", "toe_ip")  # groups of like bones, each limited on its own
MAX_CHAIN = max(len(j.bones) for j in BODY_JOINTS if j.name not in PER_BONE_JOINTS)


# The learned prior's features: rotation vectors (components along the joint frame's flexion,
# abduction, twist axes) of the composed rotations of the major joints. Spine and neck are grouped,
# as the mocap cannot say how anny's five spine bones share a bend; what CMU does not capture is
# left out (clavicles: always zero in the data; ankle inversion: no dof), limits alone govern it.
LEARNED_GROUPS = (
    # name, bones, joint whose frame is used, sided, components kept (f, a, t)
    ("lower_spine", ("spine05", "spine04", "spine03"), "spine05", False, "fat"),
    ("upper_spine", ("spine02", "spine01"), "spine02", False, "fat"),
    ("neck", ("neck01", "neck02", "neck03"), "neck01", False, "fat"),
    ("head", ("head",), "head", False, "fat"),
    ("shoulder", ("upperarm01", "upperarm02"), "shoulder", True, "fat"),
    ("elbow", ("lowerarm01", "lowerarm02"), "elbow", True, "fat"),
    ("wrist", ("wrist",), "wrist", True, "fat"),
    ("hip", ("upperleg01", "upperleg02"), "hip", True, "fat"),
    ("knee", ("lowerleg01", "lowerleg02"), "knee", True, "fat"),
    ("ankle", ("foot",), "ankle", True, "fa"),
)


# ---------------------------------------------------------------------------
# Rotation helpers: quaternions are roma's (x, y, z, w), batched over leading dimensions
# ---------------------------------------------------------------------------

def in_frame(q: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """Quaternions (..., J, 4) re-expressed in per-joint frames (J, 3, 3) whose columns are the new axes."""
    v = torch.einsum("jab,...ja->...jb", frames, q[..., :3])
    return torch.cat([v, q[..., 3:]], -1)


def swing_twist_angles(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) in a frame with the segment along z -> (..., 3) (swing about x, swing about y, twist about z).

    q = swing * twist with the twist about z; the swing (axis in the xy-plane) is
    reported as its rotation vector's x and y components, the twist as a signed angle."""
    q = q * torch.where(q[..., 3:] < 0, -1.0, 1.0)
    x, y, z, w = q.unbind(-1)
    n = torch.sqrt((w * w + z * z).clamp_min(1e-16))  # cos(swing / 2)
    m = torch.sqrt((x * x + y * y).clamp_min(1e-16))  # sin(swing / 2)
    scale = 2.0 * torch.atan2(m, n) / (m * n)
    swing_x = (x * w - y * z) * scale
    swing_y = (y * w + x * z) * scale
    twist = 2.0 * torch.atan2(z, w.clamp_min(0) + 1e-12)
    return torch.stack([swing_x, swing_y, twist], -1)


def squared_hinge(value: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """relu(low - value)^2 + relu(value - high)^2, elementwise."""
    return torch.relu(low - value) ** 2 + torch.relu(value - high) ** 2


# ---------------------------------------------------------------------------
# Anatomy: frames measured on anny's rest skeleton
# ---------------------------------------------------------------------------

def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _perpendicular(v: np.ndarray, axis: np.ndarray) -> np.ndarray:
    return _unit(v - (v @ axis) * axis)


def joint_frame(t: np.ndarray, flex_move: np.ndarray, abd_move: np.ndarray, probe, probe_to) -> np.ndarray:
    """(3, 3) columns (flexion axis, abduction axis, twist axis) so that positive angles move as asked.

    t: segment direction; a rotation by a small angle about axis k moves the
    segment's end along k x t, so the flexion axis is t x flex_move (made
    perpendicular to t), the abduction axis the one of +/- t x f whose motion
    points along abd_move, the twist axis the one of +/- t that turns `probe`
    towards `probe_to`."""
    t = _unit(t)
    f = _unit(np.cross(t, flex_move))
    a = _unit(np.cross(t, f))
    if np.cross(a, t) @ abd_move < 0:
        a = -a
    twist = t if np.cross(t, probe) @ probe_to > 0 else -t
    return np.stack([f, a, twist], axis=1)


def anatomy_from_model(model) -> dict[str, np.ndarray]:
    """Frames, handedness and rest offsets of `BODY_JOINTS` and the hand bones, from anny's rest skeleton.

    Returns arrays: body_frames (Jb, 3, 3), body_signs (Jb, 3) (+1/-1 per angle, making
    right-handed frames report the anatomical sign), body_rest (Jb, 3) radians,
    hand_frames (19, 3, 3), hand_signs (19, 3), and name lists."""
    params = model.init_params(1)
    with torch.no_grad():
        heads = model(params).joints[0].double().cpu().numpy()  # (J, 3) rest bone heads, model axes
    index = {b: i for i, b in enumerate(model.joint_names)}

    def head(b: str) -> np.ndarray:
        return heads[index[b]]

    L = lambda b: f"{b}.L"  # noqa: E731
    hand_lat = head(L("finger2-1")) - head(L("finger5-1"))  # little -> index (radial)
    hand_dir = (head(L("finger2-1")) + head(L("finger5-1"))) / 2 - head(L("wrist"))
    palm = _unit(np.cross(hand_dir, hand_lat))  # left palm normal (body_models.regions.palm_normal)
    upper = head(L("lowerarm01")) - head(L("upperarm01"))
    fore = head(L("wrist")) - head(L("lowerarm01"))
    named = {"palm": palm, "radial": _unit(hand_lat)}

    frames, signs, rest = [], [], []
    for joint in BODY_JOINTS:
        first = joint.bones[0] if not joint.sided else L(joint.bones[0])
        if isinstance(joint.end, str):
            end = L(joint.end) if joint.sided else joint.end
            t = head(end) - head(first)
        else:
            t = np.array(joint.end)
        t = _unit(t)
        if joint.flex_dir == "elbow":
            f = _unit(np.cross(upper, fore))  # positive rotation bends the forearm further
            flex_move = np.cross(f, t)
        else:
            flex_move = named.get(joint.flex_dir) if isinstance(joint.flex_dir, str) else np.array(joint.flex_dir)
        abd_move = named.get(joint.abd_dir) if isinstance(joint.abd_dir, str) else np.array(joint.abd_dir)
        probe, probe_to = np.array(joint.twist_probe), np.array(joint.twist_to)
        frame, sign = right_handed(joint_frame(t, flex_move, abd_move, probe, probe_to))
        frames.append(frame)
        signs.append(sign)
        offset = np.zeros(3)
        if "flex" in joint.rest:  # angle already bent at rest, measured about the flexion axis
            prev = upper if joint.name == "elbow" else head(L("lowerleg01")) - head(L("upperleg01"))
            offset[0] = signed_angle(prev, t, frame[:, 0] * sign[0])
        if "abd" in joint.rest:  # shoulder: arm abducted from hanging straight down
            offset[1] = signed_angle(np.array(NZ), t, frame[:, 1] * sign[1])
        rest.append(offset)

    flex_axes = model.finger_flex_axes_L.double().cpu().numpy()  # (19, 3)
    hand_frames, hand_signs = [], []
    for k, name in enumerate(model.hand_joint_names):
        if name.startswith("metacarpal"):
            end = head(L(f"finger{int(name[-1]) + 1}-1"))
        else:
            chain, j = name.split("-")
            end = head(L(f"{chain}-{int(j) + 1}")) if j != "3" else 2 * head(L(name)) - head(L(f"{chain}-2"))
        t = _unit(end - head(L(name)))
        f = _perpendicular(flex_axes[k], t)
        frame = joint_frame(t, np.cross(f, t), named["radial"], palm, named["radial"])
        frame, sign = right_handed(frame)
        hand_frames.append(frame)
        hand_signs.append(sign)
    return {
        "body_joint_names": np.array([j.name for j in BODY_JOINTS]),
        "body_frames": np.array(frames),
        "body_signs": np.array(signs),
        "body_rest": np.array(rest),
        "hand_joint_names": np.array(model.hand_joint_names),
        "hand_frames": np.array(hand_frames),
        "hand_signs": np.array(hand_signs),
    }


def right_handed(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Make a frame right-handed by flipping its abduction axis; return (frame, signs of the 3 angles)."""
    sign = np.ones(3)
    if np.linalg.det(frame) < 0:
        frame = frame.copy()
        frame[:, 1] *= -1
        sign[1] = -1
    return frame, sign


def signed_angle(a: np.ndarray, b: np.ndarray, axis: np.ndarray) -> float:
    """Angle (radians) rotating a onto b about `axis` (both projected perpendicular to it)."""
    axis = _unit(axis)
    a, b = _perpendicular(a, axis), _perpendicular(b, axis)
    return float(math.atan2(np.cross(a, b) @ axis, a @ b))


@dataclass
class Anatomy:
    """The shipped anatomy as tensors: one row per limited joint instance.

    A row composes one or more bones (knee.L = lowerleg01.L @ lowerleg02.L, spine =
    spine05 @ ... @ spine01); toe joints have a row per toe bone. Right-side rows mirror their rotations into
    the left side's convention and share its frame and ranges."""

    row_names: list[str]  # 'knee.L', 'spine05', 'toe2-1.L', ...
    row_joints: list[str]  # the BODY_JOINTS name of each row
    bones: torch.Tensor  # (R, MAX_CHAIN) indices into body_pose composed in order, -1 pads
    frames: torch.Tensor  # (R, 3, 3) columns: flexion, abduction, twist axes (right-handed)
    signs: torch.Tensor  # (R, 3) +-1: makes the right-handed frame report the anatomical sign
    mirror: torch.Tensor  # (R, 3) MIRROR for right-side rows, ones otherwise
    low: torch.Tensor  # (R, 3) radians, relative to anny's rest pose
    high: torch.Tensor
    twist_widening: torch.Tensor  # (R,)
    rest: torch.Tensor  # (R, 3) radians: anatomical angles of anny's rest pose (elbow, knee, shoulder)
    second_bones: torch.Tensor  # (Ns,) body_pose indices of bones without a joint of their own
    second_frames: torch.Tensor  # (Ns, 3, 3)
    second_mirror: torch.Tensor  # (Ns, 3)
    hand_frames: torch.Tensor  # (19, 3, 3)
    hand_signs: torch.Tensor  # (19, 3)
    hand_low: torch.Tensor  # (19, 3) radians
    hand_high: torch.Tensor
    pip: torch.Tensor  # (4,) hand indices of finger2..5 -2
    dip: torch.Tensor  # (4,) and -3

    def to(self, device, dtype) -> "Anatomy":
        moved = {}
        for key, value in self.__dict__.items():
            if isinstance(value, torch.Tensor):
                value = value.to(device=device, dtype=dtype if value.is_floating_point() else value.dtype)
            moved[key] = value
        return Anatomy(**moved)


def build_anatomy(data) -> Anatomy:
    """Anatomy tensors from the arrays of `anatomy_from_model` (the shipped npz) and the tables above."""
    stored = [str(n) for n in data["body_joint_names"]]
    if stored != [j.name for j in BODY_JOINTS]:
        raise ValueError(
            f"{ANATOMY_FILE}: lists joints {stored}, priors.py expects {[j.name for j in BODY_JOINTS]}; "
            "regenerate it with `python tools/train_pose_prior.py --anatomy-only`"
        )
    hand_names = [str(n) for n in data["hand_joint_names"]]
    if hand_names != list(HAND_BONES):
        raise ValueError(f"{ANATOMY_FILE}: lists hand bones {hand_names}, expected {list(HAND_BONES)}")
    index = {b: i for i, b in enumerate(ANNY_BODY_BONES)}
    rows = {k: [] for k in ("names", "joints", "bones", "frames", "signs", "mirror", "low", "high", "widening", "rest")}
    for k, joint in enumerate(BODY_JOINTS):
        ranges = np.deg2rad(np.array([joint.flex, joint.abd, joint.twist], dtype=np.float64))  # (3, 2)
        for side in (("L", "R") if joint.sided else ("",)):
            suffix = f".{side}" if side else ""
            groups = [(b,) for b in joint.bones] if joint.name in PER_BONE_JOINTS else [joint.bones]
            for group in groups:
                ids = [index[b + suffix] for b in group]
                rows["names"].append((group[0] if joint.name in PER_BONE_JOINTS else joint.name) + suffix)
                rows["joints"].append(joint.name)
                rows["bones"].append(ids + [-1] * (MAX_CHAIN - len(ids)))
                rows["frames"].append(data["body_frames"][k])
                rows["signs"].append(data["body_signs"][k])
                rows["mirror"].append(MIRROR if side == "R" else (1.0, 1.0, 1.0))
                rows["low"].append(ranges[:, 0] - data["body_rest"][k])
                rows["high"].append(ranges[:, 1] - data["body_rest"][k])
                rows["widening"].append(joint.twist_widening)
                rows["rest"].append(data["body_rest"][k])
    frame_of = {j.bones[1]: data["body_frames"][k] for k, j in enumerate(BODY_JOINTS) if j.bones[-1] in SECOND_BONES}
    second = [
        (index[f"{b}.{s}"], frame_of[b], MIRROR if s == "R" else (1.0, 1.0, 1.0)) for b in SECOND_BONES for s in "LR"
    ]
    hand_ranges = np.deg2rad(np.array([HAND_RANGES[n] for n in HAND_BONES], dtype=np.float64))  # (19, 3, 2)
    f32 = lambda v: torch.as_tensor(np.asarray(v), dtype=torch.float32)  # noqa: E731
    return Anatomy(
        row_names=rows["names"],
        row_joints=rows["joints"],
        bones=torch.tensor(rows["bones"]),
        frames=f32(rows["frames"]),
        signs=f32(rows["signs"]),
        mirror=f32(rows["mirror"]),
        low=f32(rows["low"]),
        high=f32(rows["high"]),
        twist_widening=f32(rows["widening"]),
        rest=f32(rows["rest"]),
        second_bones=torch.tensor([s[0] for s in second]),
        second_frames=f32([s[1] for s in second]),
        second_mirror=f32([s[2] for s in second]),
        hand_frames=f32(data["hand_frames"]),
        hand_signs=f32(data["hand_signs"]),
        hand_low=f32(hand_ranges[..., 0]),
        hand_high=f32(hand_ranges[..., 1]),
        pip=torch.tensor([HAND_BONES.index(f"finger{k}-2") for k in range(2, 6)]),
        dip=torch.tensor([HAND_BONES.index(f"finger{k}-3") for k in range(2, 6)]),
    )


@lru_cache(maxsize=None)
def _shipped_anatomy() -> Anatomy:
    if not ANATOMY_FILE.exists():
        raise FileNotFoundError(
            f"{ANATOMY_FILE} is missing: it ships with intercap; regenerate it with "
            "`python tools/train_pose_prior.py --anatomy-only`"
        )
    return build_anatomy(np.load(ANATOMY_FILE))


@lru_cache(maxsize=8)
def load_anatomy(device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> Anatomy:
    """The shipped anatomy (intercap/data/anny_anatomy.npz) as tensors on `device`, cached."""
    anatomy = _shipped_anatomy()
    return anatomy if (torch.device(device).type == "cpu" and dtype == torch.float32) else anatomy.to(device, dtype)


def _anatomy_like(t: torch.Tensor) -> Anatomy:
    return load_anatomy(t.device, t.dtype)


@lru_cache(maxsize=None)
def device_constant(values: tuple, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """A small constant tensor, made once per device: a fit's evaluations must not copy from the
    host each time (a GPU waits for it, and a recorded CUDA graph cannot hold it)."""
    return torch.tensor(values, device=device, dtype=dtype)


def _constant_like(values, t: torch.Tensor) -> torch.Tensor:
    return device_constant(tuple(values), t.device, t.dtype)


@lru_cache(maxsize=None)
def _limit_rows(joints: tuple[str, ...]) -> tuple[int, ...]:
    """The rows of `joint_limit_excess` that belong to `joints`."""
    return tuple(i for i, j in enumerate(_shipped_anatomy().row_joints) if j in joints)


# ---------------------------------------------------------------------------
# Body joint angles and limits
# ---------------------------------------------------------------------------

def _quaternion_product_table() -> tuple:
    """(16, 4): row 4 i + j, column k holds the coefficient of p_i q_j in (p q)_k, quaternions xyzw:
    (p q)_xyz = p_w q_xyz + q_w p_xyz + p_xyz x q_xyz, (p q)_w = p_w q_w - p_xyz . q_xyz."""
    table = np.zeros((4, 4, 4))
    for k in range(3):
        table[3, k, k] = table[k, 3, k] = 1.0
        table[k, k, 3] = -1.0
        i, j = (k + 1) % 3, (k + 2) % 3
        table[i, j, k], table[j, i, k] = 1.0, -1.0
    table[3, 3, 3] = 1.0
    return tuple(map(tuple, table.reshape(16, 4).tolist()))


QUATERNION_PRODUCT = _quaternion_product_table()


def quat_product(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """(..., 4), (..., 4) -> (..., 4) the product p q (xyzw), roma's `quat_product` as one outer
    product and one matrix product: 9 kernels forward and backward instead of 43, on every fit
    evaluation (the joint angles compose up to five bones a row)."""
    return (p[..., :, None] * q[..., None, :]).flatten(-2) @ _constant_like(QUATERNION_PRODUCT, p)


def composed_quaternions(body_pose: torch.Tensor, bones: torch.Tensor, mirror: torch.Tensor) -> torch.Tensor:
    """(B, 65, 3) axis-angle, (R, K) bone ids (-1 pads) -> (B, R, 4) the product D_b1 D_b2 ... per row.

    Rows whose `mirror` (R, 3) is MIRROR (right side) compose mirrored rotations, i.e. read
    in the left side's convention."""
    B, n = body_pose.shape[:2]
    both = torch.cat([body_pose, body_pose * _constant_like(MIRROR, body_pose)], 1)  # (B, 2n, 3)
    identity = _constant_like((0.0, 0.0, 0.0, 1.0), body_pose).expand(B, 1, 4)
    q = torch.cat([roma.rotvec_to_unitquat(both), identity], 1)  # (B, 2n + 1, 4)
    right = (mirror[:, 1:2] < 0).long() * n  # (R, 1) offset into the mirrored half
    index = torch.where(bones >= 0, bones + right, 2 * n)  # (R, K): a pad composes the identity (exactly)
    return composed_rows(q, index)


def composed_rows(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(B, T, 4) quaternions, (R, K) rows of indices into them -> (B, R, 4) each row's product in
    order. Every row at once: no search for the rows that go on (a GPU sync)."""
    out = table[:, index[:, 0]]
    for k in range(1, index.shape[1]):
        out = quat_product(out, table[:, index[:, k]])
    return out


def joint_angles(body_pose: torch.Tensor) -> torch.Tensor:
    """(B, 65, 3) anny body_pose -> (B, R, 3) (flexion, abduction, twist) radians relative to rest,
    one row per `joint_angle_names()`; sign conventions in BODY_JOINTS."""
    a = _anatomy_like(body_pose)
    q = composed_quaternions(body_pose, a.bones, a.mirror)
    return swing_twist_angles(in_frame(q, a.frames)) * a.signs


def joint_angle_names() -> list[str]:
    return list(_shipped_anatomy().row_names)


def joint_limit_excess(body_pose: torch.Tensor) -> torch.Tensor:
    """(B, R, 3) radians beyond each range (0 inside, positive on either side)."""
    return excess_of_angles(joint_angles(body_pose))


def excess_of_angles(angles: torch.Tensor) -> torch.Tensor:
    """`joint_limit_excess` of the (B, R, 3) `joint_angles`."""
    a = _anatomy_like(angles)
    swing = torch.sqrt((angles[..., :2] ** 2).sum(-1) + 1e-12)  # (B, R)
    widen = a.twist_widening * torch.relu(swing - math.pi / 2)  # (B, R)
    low = a.low.expand_as(angles).clone()
    high = a.high.expand_as(angles).clone()
    low[..., 2] = low[..., 2] - widen
    high[..., 2] = high[..., 2] + widen
    return torch.relu(low - angles) + torch.relu(angles - high)


def second_bone_swing(body_pose: torch.Tensor) -> torch.Tensor:
    """(B, Ns, 2) swing (radians) of the bones that carry no joint of their own (upperleg02, ...)."""
    a = _anatomy_like(body_pose)
    q = roma.rotvec_to_unitquat(body_pose[:, a.second_bones] * a.second_mirror)
    return swing_twist_angles(in_frame(q, a.second_frames))[..., :2]


def joint_limit_penalty(body_pose: torch.Tensor | None, joints: tuple[str, ...] | None = None,
                        excess: torch.Tensor | None = None, swing: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 65, 3) anny body_pose -> (B,) sum of squared hinges (radians) beyond the anatomical ranges.

    Zero inside every range. Includes the swing of thigh/shin/arm/forearm second bones
    beyond SECOND_BONE_SWING. `joints` restricts it to some BODY_JOINTS names (e.g. ('knee',)).
    `excess`, `swing`: `joint_limit_excess(body_pose)` and `second_bone_swing(body_pose)` when the
    caller has them (`pose_priors`); `body_pose` is then not read."""
    if excess is None:
        excess = joint_limit_excess(body_pose)
    if joints is not None:
        rows = device_constant(_limit_rows(tuple(joints)), excess.device, torch.long)
        return (excess.index_select(1, rows) ** 2).sum((1, 2))
    if swing is None:
        swing = second_bone_swing(body_pose)
    second = torch.relu(swing.abs() - math.radians(SECOND_BONE_SWING)) ** 2
    return (excess**2).sum((1, 2)) + second.sum((1, 2))


def body_pose_from_joint_angles(
    angles: dict[str, tuple[float, float, float]], batch_size: int = 1, anatomical: bool = True
) -> torch.Tensor:
    """(B, 65, 3) anny body_pose with the given joints set, the rest at rest (inverse of `joint_angles`).

    angles: row name ('knee.L', 'spine03', 'toe2-1.R', ...) -> (flexion, abduction, twist) in
    degrees, anatomical (as in BODY_JOINTS) unless `anatomical=False` (then relative to rest).
    Each joint's rotation goes on its first bone."""
    a = _shipped_anatomy()
    pose = torch.zeros(batch_size, len(ANNY_BODY_BONES), 3)
    for name, values in angles.items():
        if name not in a.row_names:
            raise KeyError(f"unknown joint {name!r}; choose from {a.row_names}")
        r = a.row_names.index(name)
        theta = torch.deg2rad(torch.as_tensor(values, dtype=torch.float32).reshape(-1, 3))  # (b, 3)
        if anatomical:
            theta = theta - a.rest[r]
        theta = theta * a.signs[r]  # signed angles about the stored (right-handed) frame's axes
        swing = torch.cat([theta[:, :2], torch.zeros_like(theta[:, :1])], 1)
        twist = torch.cat([torch.zeros_like(theta[:, :2]), theta[:, 2:]], 1)
        q = roma.quat_product(roma.rotvec_to_unitquat(swing), roma.rotvec_to_unitquat(twist))
        rotvec = roma.unitquat_to_rotvec(q) @ a.frames[r].T  # frame -> model axes
        pose[:, int(a.bones[r, 0])] = rotvec * a.mirror[r]
    return pose


def extreme_bending(body_pose: torch.Tensor, excess: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) SMPLify-X's elbow/knee term: squared hinge of elbows and knees bent beyond range,
    hyperextended or bent sideways (the joint-limit penalty restricted to those joints)."""
    return joint_limit_penalty(body_pose, EXTREME_BENDING_JOINTS, excess)


# ---------------------------------------------------------------------------
# Hands
# ---------------------------------------------------------------------------

def hand_angles(hand_pose: torch.Tensor, side: str) -> torch.Tensor:
    """(B, 19, 3) anny hand pose -> (B, 19, 3) (curl, abduction towards the thumb, twist) radians."""
    if side not in ("L", "R", "left", "right"):
        raise ValueError(f"side must be 'L' or 'R', got {side!r}")
    a = _anatomy_like(hand_pose)
    if side in ("R", "right"):
        hand_pose = hand_pose * _constant_like(MIRROR, hand_pose)
    q = roma.rotvec_to_unitquat(hand_pose)
    return swing_twist_angles(in_frame(q, a.hand_frames)) * a.hand_signs


def hand_pose_from_angles(angles: torch.Tensor, side: str) -> torch.Tensor:
    """(B, 19, 3) (curl, abduction, twist) in degrees per hand bone -> (B, 19, 3) anny hand pose
    (inverse of `hand_angles`)."""
    a = _shipped_anatomy()
    theta = torch.deg2rad(torch.as_tensor(angles, dtype=torch.float32)) * a.hand_signs
    swing = torch.cat([theta[..., :2], torch.zeros_like(theta[..., :1])], -1)
    twist = torch.cat([torch.zeros_like(theta[..., :2]), theta[..., 2:]], -1)
    q = roma.quat_product(roma.rotvec_to_unitquat(swing), roma.rotvec_to_unitquat(twist))
    pose = torch.einsum("jab,...jb->...ja", a.hand_frames, roma.unitquat_to_rotvec(q))  # frame -> model axes
    return pose * pose.new_tensor(MIRROR) if side in ("R", "right") else pose


def hand_pose_prior(hand_pose: torch.Tensor, side: str, coupling_weight: float = HAND_COUPLING_WEIGHT) -> torch.Tensor:
    """(B, 19, 3) anny hand pose -> (B,) squared hinges (radians) beyond finger ranges of motion,
    plus `coupling_weight` * (DIP - 2/3 PIP)^2 for the four fingers (tendons couple them).

    Anatomy only: no open finger-motion data could be found to learn from."""
    return hand_prior_of_angles(hand_angles(hand_pose, side), coupling_weight)


def hand_prior_of_angles(angles: torch.Tensor, coupling_weight: float = HAND_COUPLING_WEIGHT) -> torch.Tensor:
    """`hand_pose_prior` of the (B, 19, 3) `hand_angles`."""
    a = _anatomy_like(angles)
    penalty = squared_hinge(angles, a.hand_low, a.hand_high).sum((1, 2))
    coupling = angles[:, a.dip, 0] - DIP_PIP_RATIO * angles[:, a.pip, 0]
    return penalty + coupling_weight * (coupling**2).sum(1)


def hands_pose_prior(left_hand_pose: torch.Tensor, right_hand_pose: torch.Tensor) -> torch.Tensor:
    """(B,) `hand_pose_prior` of both hands, as one batch: the right hand mirrored into the left's
    convention (as `hand_angles` does), so the chain of small operations runs once, not twice."""
    both = torch.cat([left_hand_pose, right_hand_pose * _constant_like(MIRROR, right_hand_pose)])
    return hand_pose_prior(both, "L").view(2, -1).sum(0)


# ---------------------------------------------------------------------------
# Learned body-pose prior
# ---------------------------------------------------------------------------

def learned_features(body_pose: torch.Tensor) -> torch.Tensor:
    """(B, 65, 3) -> (B, D) rotation vectors of LEARNED_GROUPS (both sides, right mirrored to the
    left convention), components in each joint's frame, the kept components only."""
    table = _learned_table(body_pose.device, body_pose.dtype)
    q = composed_quaternions(body_pose, table["bones"], table["mirror"])
    rotvec = roma.unitquat_to_rotvec(in_frame(q, table["frames"])).flatten(1)  # (B, 3 G)
    return rotvec[:, table["keep"]]


def learned_feature_names() -> list[str]:
    return list(_learned_table(torch.device("cpu"), torch.float32)["feature_names"])


@lru_cache(maxsize=8)
def _learned_table(device, dtype) -> dict:
    a = _shipped_anatomy()
    bone_index = {b: i for i, b in enumerate(ANNY_BODY_BONES)}
    names, bones, frames, mirror, keep, feature_names = [], [], [], [], [], []
    for name, group, frame_joint, sided, components in LEARNED_GROUPS:
        for side in (("L", "R") if sided else ("",)):
            suffix = f".{side}" if side else ""
            ids = [bone_index[b + suffix] for b in group]
            for c, axis in enumerate("fat"):
                if axis in components:
                    keep.append(3 * len(names) + c)
                    feature_names.append(f"{name}{suffix}:{axis}")
            names.append(name + suffix)
            bones.append(ids + [-1] * (3 - len(ids)))
            frames.append(a.frames[a.row_names.index(frame_joint + (".L" if sided else ""))])
            mirror.append(MIRROR if side == "R" else (1.0, 1.0, 1.0))
    return {
        "names": names,
        "feature_names": feature_names,
        "keep": torch.tensor(keep, device=device),
        "bones": torch.tensor(bones, device=device),
        "frames": torch.stack(frames).to(device=device, dtype=dtype),
        "mirror": torch.tensor(mirror, device=device, dtype=dtype),
    }


def mirror_body_pose(body_pose: torch.Tensor) -> torch.Tensor:
    """(B, 65, 3) the left-right mirrored pose: sides swapped, rotation vectors mirrored through x."""
    names = list(ANNY_BODY_BONES)
    other = {".L": ".R", ".R": ".L"}
    swap = [names.index(n[:-2] + other[n[-2:]]) if n[-2:] in other else i for i, n in enumerate(names)]
    return body_pose[:, swap] * body_pose.new_tensor(MIRROR)


def mirror_features(features: torch.Tensor) -> torch.Tensor:
    """(B, D) learned features of the left-right mirrored pose.

    Sided features swap sides (both are stored in the left convention); midline ones,
    whose frames have their flexion axis along model x, keep flexion and negate the rest."""
    names = learned_feature_names()
    index = {n: i for i, n in enumerate(names)}
    swap, flip = [], []
    for n in names:
        joint, axis = n.split(":")
        if joint.endswith((".L", ".R")):
            swap.append(index[f"{joint[:-1]}{'R' if joint.endswith('L') else 'L'}:{axis}"])
            flip.append(1.0)
        else:
            swap.append(index[n])
            flip.append(1.0 if axis == "f" else -1.0)
    return features[:, swap] * features.new_tensor(flip)


@dataclass
class PosePrior:
    """Gaussian mixture over learned_features: weights (K,), means (K, D), precision Cholesky factors (K, D, D)."""

    log_weights: torch.Tensor
    means: torch.Tensor
    precision_chol: torch.Tensor  # L with L L^T = Sigma^-1
    constants: torch.Tensor  # (K,) -log w_k + 0.5 log det Sigma_k, shifted so min_k = 0
    feature_names: list[str]


@lru_cache(maxsize=8)
def load_pose_prior(device=None, dtype=torch.float32) -> PosePrior:
    """The shipped Gaussian mixture (intercap/data/body_pose_prior.npz), cached."""
    if not POSE_PRIOR_FILE.exists():
        raise FileNotFoundError(
            f"{POSE_PRIOR_FILE} is missing: the learned body-pose prior ships with intercap; "
            "retrain it with `python tools/train_pose_prior.py` (needs ../shared/data/cmu_mocap)"
        )
    data = np.load(POSE_PRIOR_FILE)
    names = [str(n) for n in data["feature_names"]]
    if names != learned_feature_names():
        raise ValueError(f"{POSE_PRIOR_FILE} was trained on other features than priors.py computes; retrain it")
    t = lambda k: torch.as_tensor(data[k], device=device, dtype=dtype)  # noqa: E731
    chol = t("precision_chol")
    log_det_precision = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    constants = -t("log_weights") - 0.5 * log_det_precision
    return PosePrior(t("log_weights"), t("means"), chol, constants - constants.min(), names)


def learned_pose_prior(body_pose: torch.Tensor) -> torch.Tensor:
    """(B, 65, 3) -> (B,) negative log-likelihood under the shipped mixture, min over components
    (SMPLify's MaxMixture): min_k 0.5 |L_k^T (x - mu_k)|^2 + c_k, with c_k >= 0 and 0 for the
    densest component, so the most likely pose scores about 0."""
    return mixture_nll(learned_features(body_pose))


def mixture_nll(x: torch.Tensor) -> torch.Tensor:
    """`learned_pose_prior` of the (B, D) `learned_features`."""
    prior = load_pose_prior(x.device if x.device.type != "cpu" else None, x.dtype)
    diff = x[:, None, :] - prior.means[None]  # (B, K, D)
    z = torch.einsum("kde,bkd->bke", prior.precision_chol, diff)  # L^T (x - mu)
    nll = 0.5 * (z * z).sum(-1) + prior.constants  # (B, K)
    return nll.min(1).values


# ---------------------------------------------------------------------------
# Every pose prior in one pass
# ---------------------------------------------------------------------------

POSE_PRIOR_TERMS = ("pose_prior", "joint_limits", "bending", "hand_prior")


@lru_cache(maxsize=8)
def _prior_rows(device, dtype) -> dict:
    """`pose_priors`' table: every rotation the priors read, as rows composing quaternions of
    [body (n) | mirrored body (n) | left hand (H) | mirrored right hand (H) | identity]: the joint
    rows, the second bones, both hands' bones and the learned groups, with their frames."""
    a = load_anatomy(device, dtype)
    learned = _learned_table(device, dtype)
    n, H = len(ANNY_BODY_BONES), a.hand_frames.shape[0]
    identity = 2 * n + 2 * H

    def body_rows(bones, mirror):  # right-side rows read the mirrored half; pads compose the identity
        return torch.where(bones >= 0, bones + (mirror[:, 1:2] < 0).long() * n, identity)

    hands = torch.arange(2 * n, 2 * n + 2 * H, device=device)[:, None]
    blocks = [body_rows(a.bones, a.mirror), body_rows(a.second_bones[:, None], a.second_mirror), hands,
              body_rows(learned["bones"], learned["mirror"])]
    width = max(b.shape[1] for b in blocks)
    index = torch.cat([torch.nn.functional.pad(b, (0, width - b.shape[1]), value=identity) for b in blocks])
    sizes = [len(b) for b in blocks]
    return {"index": index, "sizes": sizes,
            "frames": torch.cat([a.frames, a.second_frames, a.hand_frames, a.hand_frames, learned["frames"]])}


def pose_priors(body_pose: torch.Tensor, left_hand_pose: torch.Tensor, right_hand_pose: torch.Tensor,
                terms) -> dict[str, torch.Tensor]:
    """The pose priors among `terms` (POSE_PRIOR_TERMS: `learned_pose_prior`, `joint_limit_penalty`,
    `extreme_bending`, `hands_pose_prior`), each (B,), from one pass over every rotation they read:
    one quaternion conversion, one composition, one change of frame and one swing-twist split for
    all of them. Apart, each ran its own chain of small operations (4,300 of the 23,500 kernels per
    frame inside a GPU's graphs of the sample's body fit); the values are theirs (tested)."""
    rows = _prior_rows(body_pose.device, body_pose.dtype)
    R, Ns, H2, _ = rows["sizes"]
    mirror = _constant_like(MIRROR, body_pose)
    rotations = torch.cat([body_pose, body_pose * mirror, left_hand_pose, right_hand_pose * mirror], 1)
    B = len(body_pose)
    table = torch.cat([roma.rotvec_to_unitquat(rotations),
                       _constant_like((0.0, 0.0, 0.0, 1.0), body_pose).expand(B, 1, 4)], 1)
    q = in_frame(composed_rows(table, rows["index"]), rows["frames"])
    a = _anatomy_like(body_pose)
    angles = swing_twist_angles(q[:, :R + Ns + H2])
    result = {}
    if "pose_prior" in terms:
        features = roma.unitquat_to_rotvec(q[:, R + Ns + H2:]).flatten(1)
        result["pose_prior"] = mixture_nll(features[:, _learned_table(body_pose.device, body_pose.dtype)["keep"]])
    excess = excess_of_angles(angles[:, :R] * a.signs) if {"joint_limits", "bending"} & set(terms) else None
    if "joint_limits" in terms:
        result["joint_limits"] = joint_limit_penalty(None, excess=excess, swing=angles[:, R:R + Ns, :2])
    if "bending" in terms:
        result["bending"] = extreme_bending(None, excess)
    if "hand_prior" in terms:
        hands = angles[:, R + Ns:].reshape(2 * B, H2 // 2, 3) * a.hand_signs
        result["hand_prior"] = hand_prior_of_angles(hands).view(B, 2).sum(1)
    return result


# ---------------------------------------------------------------------------
# Shape and expression
# ---------------------------------------------------------------------------

def shape_prior(shape: torch.Tensor, center_weight: float = 0.1, center: torch.Tensor | float = 0.5) -> torch.Tensor:
    """(B, S) anny phenotype in [0, 1] -> (B,) squared hinge for leaving [0, 1],
    plus `center_weight` * |shape - center|^2 (a light pull to the average person, or to the
    phenotype the person's measured size suggests: `center` (S,))."""
    box = squared_hinge(shape, shape.new_zeros(()), shape.new_ones(())).sum(1)
    return box + center_weight * ((shape - center) ** 2).sum(1)


def expression_prior(expression: torch.Tensor, box_weight: float = 10.0) -> torch.Tensor:
    """(B, E) facial action weights -> (B,) |e|^2 (rest face preferred) plus `box_weight` *
    squared hinge for leaving [0, 1], the range anny's facial actions are defined on."""
    box = squared_hinge(expression, expression.new_zeros(()), expression.new_ones(()))
    return (expression**2).sum(1) + box_weight * box.sum(1)
