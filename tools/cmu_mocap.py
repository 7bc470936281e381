"""CMU motion capture (Acclaim ASF/AMC): reader, forward kinematics, retargeting to anny.

The CMU Graphics Lab database (mocap.cs.cmu.edu) stores a skeleton per subject
(`.asf`: bones with a rest direction in world axes, a length, an `axis` frame
and the degrees of freedom) and motions (`.amc`: per frame, the root
translation and rotation and every bone's dof angles in degrees).

Forward kinematics (the Acclaim convention): with C_b the bone's axis frame and
M_b its dof rotation, the world rotation of a bone is

    G_b = G_parent C_b M_b C_b^T ,   end_b = end_parent + length_b * G_b dir_b ,

so G_b is the rotation that carries the bone from its rest pose to the posed
one, in world axes. CMU's world is y-up with the subject facing +z and their
left on +x; lengths are in units of 0.45 inch (`:units length 0.45`), i.e.
metres = length * 0.0254 / 0.45.

Retargeting (`retarget_to_anny`): anny's 'local-ref' pose is SMPL-like, the
world rotation of a bone is G_c = G_parent D_c with D_c its body_pose entry. We
give each anny bone the world rotation of a CMU bone composed with a fixed
alignment A_c, G_c = G_cmu A_c, and read D_c = G_parent^T G_c:
  * limb bones (arms, legs, hands, feet): A_c carries anny's rest bone onto
    CMU's rest bone (direction first, then the elbow / knee hinge axis), so the
    posed anny bone points exactly where the CMU bone points and the hinge of
    elbow and knee stays a hinge; twists come from CMU's dofs (humerus, femur,
    wrist twist);
  * trunk (pelvis, spine, neck, head, clavicles): A_c = I, CMU's zero pose is
    taken as anny's rest posture; anny's five spine bones and three neck bones
    take rotations interpolated (slerp by height) between CMU's three spine and
    three neck/head bones, so the bend is spread as it is in a real spine;
  * CMU's tibia has no axial dof, so its shank rotation shows up at the foot;
    that twist about the shin axis is moved onto anny's lowerleg02;
  * what CMU does not capture (fingers, toes beyond one joint, eyes) stays at
    rest; the clavicle dofs are zero throughout these files.
Directions of the retargeted limbs match CMU's to 0.2 deg (thigh 3 deg: anny's
upperleg02 head is off the hip-knee line); the trunk keeps anny's own curvature.

`glitch_frames` flags frames where a limb dof leaves the skeleton file's own
limits by more than 45 deg, or a forearm twists more than 120 deg: solver flips
(most of 01_12 has the left foot turned by 180 deg). They are 936 of the 19451
frames read at step 4.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

UNIT_TO_METRES = 0.0254 / 0.45
# CMU world (y up, facing +z, left +x) -> anny model axes (z up, facing -y, left +x).
CMU_TO_ANNY = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
CMU_FPS = 120


@dataclass
class AsfBone:
    name: str
    direction: np.ndarray  # (3,) unit, world axes at rest
    length: float  # ASF units
    axis: np.ndarray  # (3, 3) C, the bone's dof frame in world axes
    dofs: tuple[str, ...]  # e.g. ("rx", "ry", "rz")
    limits: np.ndarray  # (n_dof, 2) degrees, the skeleton file's own declared range per dof
    parent: str = "root"


@dataclass
class Skeleton:
    """An ASF skeleton: bones in parent-before-child order, plus the root's channels."""

    bones: dict[str, AsfBone]
    root_order: tuple[str, ...]  # e.g. ("tx", "ty", "tz", "rx", "ry", "rz")
    root_axis: np.ndarray  # (3, 3)
    children: dict[str, list[str]] = field(default_factory=dict)


def axis_rotation(angle_rad: np.ndarray, axis: str) -> np.ndarray:
    """(...,) angles in radians about 'x', 'y' or 'z' -> (..., 3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    one, zero = np.ones_like(c), np.zeros_like(c)
    rows = {
        "x": [[one, zero, zero], [zero, c, -s], [zero, s, c]],
        "y": [[c, zero, s], [zero, one, zero], [-s, zero, c]],
        "z": [[c, -s, zero], [s, c, zero], [zero, zero, one]],
    }[axis]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def euler_matrix(angles_deg: np.ndarray, axes: str) -> np.ndarray:
    """(..., k) angles in degrees about `axes` (e.g. 'xyz', 'xz'), applied first to last -> (..., 3, 3).

    R = R_last ... R_first, the Acclaim convention (rotate about x, then y, then z)."""
    angles = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    out = np.broadcast_to(np.eye(3), angles.shape[:-1] + (3, 3))
    for k, ax in enumerate(axes):
        out = axis_rotation(angles[..., k], ax) @ out
    return out


def parse_asf(path: str | Path) -> Skeleton:
    """Read an Acclaim skeleton file."""
    path = Path(path)
    text = path.read_text()
    sections = re.split(r"^:", text, flags=re.M)
    root_order: tuple[str, ...] = ()
    root_axis = np.eye(3)
    bones: dict[str, AsfBone] = {}
    hierarchy: dict[str, list[str]] = {}
    for section in sections:
        head, _, body = section.partition("\n")
        key = head.split()[0] if head.split() else ""
        if key == "root":
            for line in body.splitlines():
                parts = line.split()
                if parts and parts[0] == "order":
                    root_order = tuple(p.lower() for p in parts[1:])
                elif parts and parts[0] == "axis":
                    if parts[1].upper() != "XYZ":
                        raise ValueError(f"{path}: root axis order {parts[1]} is not supported (only XYZ)")
        elif key == "bonedata":
            for block in re.findall(r"begin(.*?)end", body, flags=re.S):
                fields: dict[str, list[str]] = {}
                for line in block.splitlines():
                    parts = line.split()
                    if parts and parts[0] in ("name", "direction", "length", "axis", "dof"):
                        fields[parts[0]] = parts[1:]
                after = block.split("limits", 1)[1] if "limits" in block else ""
                limits = [float(v) for v in re.findall(r"[-+]?\d*\.?\d+(?:[eE][-+]?\d+)?", after)]
                try:
                    name = fields["name"][0]
                    direction = np.array([float(v) for v in fields["direction"][:3]])
                    axis_deg = np.array([float(v) for v in fields["axis"][:3]])
                    order = fields["axis"][3].lower()
                except (KeyError, IndexError, ValueError) as err:
                    raise ValueError(f"{path}: malformed bone block ({err}):\n{block}") from err
                bones[name] = AsfBone(
                    name=name,
                    direction=direction / max(np.linalg.norm(direction), 1e-12),
                    length=float(fields["length"][0]),
                    axis=euler_matrix(axis_deg, order),
                    dofs=tuple(fields.get("dof", [])),
                    limits=np.array(limits, dtype=np.float64).reshape(-1, 2),
                )
        elif key == "hierarchy":
            for line in body.splitlines():
                parts = line.split()
                if parts and parts[0] not in ("begin", "end"):
                    hierarchy[parts[0]] = parts[1:]
    if not bones or not hierarchy:
        raise ValueError(f"{path}: no :bonedata or :hierarchy section found")
    for parent, kids in hierarchy.items():
        for kid in kids:
            if kid not in bones:
                raise ValueError(f"{path}: hierarchy names unknown bone {kid!r}")
            bones[kid].parent = parent
    ordered: dict[str, AsfBone] = {}

    def visit(name: str) -> None:
        for kid in hierarchy.get(name, []):
            ordered[kid] = bones[kid]
            visit(kid)

    visit("root")
    return Skeleton(bones=ordered, root_order=root_order, root_axis=root_axis, children=hierarchy)


def parse_amc(path: str | Path, skeleton: Skeleton) -> dict[str, np.ndarray]:
    """Read an Acclaim motion file: bone name -> (T, n_dof) float array (root: (T, 6), degrees and ASF units)."""
    path = Path(path)
    values: dict[str, list[list[float]]] = {"root": []}
    for name, bone in skeleton.bones.items():
        if bone.dofs:
            values[name] = []
    frames = 0
    with open(path) as handle:
        for line in handle:
            if not line or line[0] in "#:":
                continue
            parts = line.split()
            if not parts:
                continue
            if parts[0].isdigit():
                frames += 1
                continue
            if parts[0] in values:
                values[parts[0]].append([float(v) for v in parts[1:]])
    out = {}
    for name, rows in values.items():
        if len(rows) != frames:
            raise ValueError(f"{path}: bone {name!r} appears in {len(rows)} of {frames} frames")
        out[name] = np.asarray(rows, dtype=np.float64).reshape(frames, -1)
    return out


WRIST_TWIST_GLITCH = 120.0  # degrees
# Not "wrist": its declared (-180, 0) is not what the data use (they are centred on 0).
GLITCH_BONES = ("femur", "tibia", "foot", "radius", "hand")


def wrap_degrees(values: np.ndarray) -> np.ndarray:
    """Angles mapped into (-180, 180] (AMC files sometimes store -407 for -47)."""
    return 180.0 - np.mod(180.0 - values, 360.0)


def glitch_frames(skeleton: Skeleton, motion: dict[str, np.ndarray], margin_deg: float = 45.0) -> np.ndarray:
    """(T,) bool: frames where a limb dof (GLITCH_BONES, both sides) leaves the skeleton file's own
    declared limits by more than `margin_deg` after wrapping - capture/solver glitches such as the
    left foot flipped by 180 degrees in most of CMU 01_12."""
    bad = np.zeros(motion["root"].shape[0], dtype=bool)
    for name, bone in skeleton.bones.items():
        if name[1:] in GLITCH_BONES and bone.dofs and len(bone.limits) == len(bone.dofs):
            values = wrap_degrees(motion[name])
            bad |= ((values < bone.limits[:, 0] - margin_deg) | (values > bone.limits[:, 1] + margin_deg)).any(1)
    for side in "lr":  # forearm twist: the data are centred on 0, a half turn is a flipped solve
        if f"{side}wrist" in motion:
            bad |= (np.abs(wrap_degrees(motion[f"{side}wrist"])) > WRIST_TWIST_GLITCH).any(1)
    return bad


def world_rotations(skeleton: Skeleton, motion: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """World rotation G_b (T, 3, 3) of the root and every bone, CMU axes (see module docstring)."""
    root = motion["root"]
    rot_cols = [i for i, c in enumerate(skeleton.root_order) if c.startswith("r")]
    rot_axes = "".join(skeleton.root_order[i][1] for i in rot_cols)
    C0 = skeleton.root_axis
    G = {"root": C0 @ euler_matrix(root[:, rot_cols], rot_axes) @ C0.T}
    T = root.shape[0]
    for name, bone in skeleton.bones.items():
        if bone.dofs:
            M = euler_matrix(motion[name], "".join(d[1] for d in bone.dofs))
        else:
            M = np.broadcast_to(np.eye(3), (T, 3, 3))
        G[name] = G[bone.parent] @ (bone.axis @ M @ bone.axis.T)
    return G


def forward_kinematics(skeleton: Skeleton, motion: dict[str, np.ndarray]) -> tuple[list[str], np.ndarray, dict]:
    """World positions in metres, CMU axes: (names ['root', bones...], ends (T, 1+nb, 3), rotations).

    'root' is the root position; each bone's entry is its end point (the next joint)."""
    G = world_rotations(skeleton, motion)
    root = motion["root"]
    trans_cols = [i for i, c in enumerate(skeleton.root_order) if c.startswith("t")]
    ends = {"root": root[:, trans_cols] * UNIT_TO_METRES}
    for name, bone in skeleton.bones.items():
        offset = (G[name] @ bone.direction) * bone.length * UNIT_TO_METRES  # (T, 3)
        ends[name] = ends[bone.parent] + offset
    names = ["root"] + list(skeleton.bones)
    return names, np.stack([ends[n] for n in names], axis=1), G


def rest_positions(skeleton: Skeleton) -> dict[str, np.ndarray]:
    """Bone end points (3,) at rest, metres, CMU axes, root at the origin."""
    ends = {"root": np.zeros(3)}
    for name, bone in skeleton.bones.items():
        ends[name] = ends[bone.parent] + bone.direction * bone.length * UNIT_TO_METRES
    return ends


# ---------------------------------------------------------------------------
# Retargeting to anny
# ---------------------------------------------------------------------------

@dataclass
class AnnyRest:
    """What the retargeting needs from anny: bone labels, parents and rest heads (model axes)."""

    labels: list[str]
    parents: list[int]
    heads: np.ndarray  # (J, 3)
    body_joint_names: list[str]

    @staticmethod
    def from_model(model) -> "AnnyRest":
        core = model.core
        rest = core(None, None)
        heads = rest["bone_poses"][0, :, :3, 3].detach().double().cpu().numpy()
        parents = [int(p) for p in core.bone_parents]
        return AnnyRest(list(core.bone_labels), parents, heads, list(model.body_joint_names))

    def head(self, label: str) -> np.ndarray:
        return self.heads[self.labels.index(label)]


# anny limb bone -> (CMU bone whose rotation it takes, anny end bone giving its rest direction, hinge).
# Names without side; '{s}' is the anny side (L/R), CMU bones take 'l'/'r' in front.
LIMB_MAP = {
    "upperleg01": ("femur", "lowerleg01", "knee"),
    "upperleg02": ("femur", "lowerleg01", "knee"),
    "lowerleg01": ("tibia", "foot", "knee"),
    "lowerleg02": ("tibia", "foot", "knee"),
    "foot": ("foot", "toe3-1", "knee"),
    "upperarm01": ("humerus", "lowerarm01", "elbow"),
    "upperarm02": ("humerus", "lowerarm01", "elbow"),
    "lowerarm01": ("radius", "wrist", "elbow"),
    "lowerarm02": ("wrist", "wrist", "elbow"),
    "wrist": ("hand", "finger3-1", "elbow"),
}
# The CMU bone whose direction stands for the anny bone's rest direction (the wrist's is a short stub).
CMU_DIRECTION_BONE = {"wrist": "radius"}
TOE_BONES = tuple(f"toe{k}-1" for k in range(1, 6))
SPINE_BONES = ("spine05", "spine04", "spine03", "spine02", "spine01")
NECK_BONES = ("neck01", "neck02", "neck03", "head")
CMU_SPINE = ("lowerback", "upperback", "thorax")
CMU_NECK = ("lowerneck", "upperneck", "head")


def two_vector_frame(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """(3, 3) orthonormal frame: columns primary, secondary made orthogonal to it, their cross product."""
    a = primary / np.linalg.norm(primary)
    b = secondary - (secondary @ a) * a
    b = b / np.linalg.norm(b)
    return np.stack([a, b, np.cross(a, b)], axis=1)


def anny_hinge_axes(rest: AnnyRest, side: str) -> dict[str, np.ndarray]:
    """Rest-pose hinge axes (model axes) of knee and elbow; positive rotation flexes."""
    h = lambda b: rest.head(f"{b}.{side}")  # noqa: E731
    upper, fore = h("lowerarm01") - h("upperarm01"), h("wrist") - h("lowerarm01")
    elbow = np.cross(upper, fore)
    return {"knee": np.array([1.0, 0.0, 0.0]), "elbow": elbow / np.linalg.norm(elbow)}


def cmu_hinge_axes(skeleton: Skeleton, side: str) -> dict[str, np.ndarray]:
    """Rest-pose hinge axes of knee and elbow in anny model axes; positive CMU angle flexes."""
    s = side.lower()
    return {
        "knee": CMU_TO_ANNY @ skeleton.bones[f"{s}tibia"].axis[:, 0],
        "elbow": CMU_TO_ANNY @ skeleton.bones[f"{s}radius"].axis[:, 0],
    }


def limb_alignments(skeleton: Skeleton, rest: AnnyRest) -> dict[str, tuple[str, np.ndarray]]:
    """anny limb bone label -> (CMU bone, A (3, 3)) with A carrying anny's rest bone onto CMU's rest bone."""
    out = {}
    for side in ("L", "R"):
        s = side.lower()
        hinge_anny, hinge_cmu = anny_hinge_axes(rest, side), cmu_hinge_axes(skeleton, side)
        for bone, (cmu, end, hinge) in LIMB_MAP.items():
            d_anny = rest.head(f"{end}.{side}") - rest.head(f"{bone}.{side}")
            if bone == "lowerarm02":  # share the forearm's direction (lowerarm01 -> wrist)
                d_anny = rest.head(f"wrist.{side}") - rest.head(f"lowerarm01.{side}")
            d_cmu = CMU_TO_ANNY @ skeleton.bones[s + CMU_DIRECTION_BONE.get(bone, cmu)].direction
            A = two_vector_frame(d_cmu, hinge_cmu[hinge]) @ two_vector_frame(d_anny, hinge_anny[hinge]).T
            out[f"{bone}.{side}"] = (s + cmu, A)
    return out


def chain_fractions(points: np.ndarray) -> np.ndarray:
    """(n+1, 3) polyline -> (n,) arc-length fraction of each segment's midpoint."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    return (cum[:-1] + cum[1:]) / 2 / cum[-1]


def slerp_rotations(keys_s: np.ndarray, keys_G: list[np.ndarray], query_s: np.ndarray) -> np.ndarray:
    """Interpolate world rotations along a chain: keys at arc fractions (K,), each (T, 3, 3) -> (T, Q, 3, 3).

    Slerp between the two neighbouring keys (clamped at the ends) via their relative rotation."""
    query = np.clip(query_s, keys_s[0], keys_s[-1])
    out = []
    for q in query:
        k = int(np.clip(np.searchsorted(keys_s, q, side="right") - 1, 0, len(keys_s) - 2))
        w = (q - keys_s[k]) / (keys_s[k + 1] - keys_s[k])
        rel = Rotation.from_matrix(np.swapaxes(keys_G[k], 1, 2) @ keys_G[k + 1]).as_rotvec()  # (T, 3)
        out.append(keys_G[k] @ Rotation.from_rotvec(w * rel).as_matrix())
    return np.stack(out, axis=1)


def twist_about(rotations: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(T, 3, 3) -> (T, 3, 3) the twist part about `axis` (swing-twist decomposition, either order)."""
    axis = axis / np.linalg.norm(axis)
    q = Rotation.from_matrix(rotations).as_quat()  # (T, 4) x, y, z, w
    along = q[:, :3] @ axis
    twist = np.concatenate([along[:, None] * axis, q[:, 3:]], axis=1)
    norm = np.linalg.norm(twist, axis=1, keepdims=True)
    twist = np.where(norm > 1e-9, twist / np.maximum(norm, 1e-12), np.array([0.0, 0.0, 0.0, 1.0]))
    return Rotation.from_quat(twist).as_matrix()


def retarget_to_anny(
    skeleton: Skeleton, G_cmu: dict[str, np.ndarray], rest: AnnyRest
) -> tuple[np.ndarray, np.ndarray]:
    """CMU world rotations (T, 3, 3) per bone -> anny (body_pose (T, 65, 3), global_orient (T, 3)) axis-angle."""
    P = CMU_TO_ANNY
    G = {name: P @ g @ P.T for name, g in G_cmu.items()}  # anny axes
    T = G["root"].shape[0]
    eye = np.broadcast_to(np.eye(3), (T, 3, 3))
    world: dict[str, np.ndarray] = {"root": G["root"]}

    # Trunk: slerp CMU's spine and neck rotations onto anny's bones by height.
    cmu_rest = rest_positions(skeleton)
    spine_pts = np.stack([np.zeros(3)] + [cmu_rest[b] for b in CMU_SPINE])
    cmu_spine_s = np.concatenate([[0.0], chain_fractions(spine_pts)])
    anny_spine_pts = np.stack([rest.head(b) for b in SPINE_BONES] + [rest.head("neck01")])
    spine = slerp_rotations(cmu_spine_s, [G["root"]] + [G[b] for b in CMU_SPINE], chain_fractions(anny_spine_pts))
    neck_pts = np.stack([cmu_rest["thorax"]] + [cmu_rest[b] for b in CMU_NECK])
    cmu_neck_s = np.concatenate([[0.0], chain_fractions(neck_pts)])
    head_top = rest.head("head") + (rest.head("head") - rest.head("neck03"))
    anny_neck_pts = np.stack([rest.head(b) for b in NECK_BONES] + [head_top])
    neck = slerp_rotations(cmu_neck_s, [G["thorax"]] + [G[b] for b in CMU_NECK], chain_fractions(anny_neck_pts))
    for k, b in enumerate(SPINE_BONES):
        world[b] = spine[:, k]
    for k, b in enumerate(NECK_BONES):
        world[b] = neck[:, k]
    limbs = limb_alignments(skeleton, rest)
    for side in ("L", "R"):
        s = side.lower()
        world[f"clavicle.{side}"] = G[f"{s}clavicle"]
        for bone in LIMB_MAP:
            cmu, A = limbs[f"{bone}.{side}"]
            world[f"{bone}.{side}"] = G[cmu] @ A
        # Toes: CMU's one toe joint drives the first joint of every anny toe, aligned like the foot.
        _, A_foot = limbs[f"foot.{side}"]
        for toe in TOE_BONES:
            world[f"{toe}.{side}"] = G[f"{s}toes"] @ A_foot

    # CMU's tibia has no axial dof, so the shank's axial rotation shows up at the foot (its rz, about
    # the vertical): move that twist about the shin axis from the ankle onto the shin (lowerleg02).
    for side in ("L", "R"):
        shin, foot = f"lowerleg02.{side}", f"foot.{side}"
        axis = rest.head(foot) - rest.head(shin)
        twist = twist_about(np.swapaxes(world[shin], 1, 2) @ world[foot], axis)  # (T, 3, 3)
        world[shin] = world[shin] @ twist

    # Every other bone follows its parent (D = I); read local rotations D_c = G_parent^T G_c.
    full = []
    for label, parent in zip(rest.labels, rest.parents):
        if label not in world:
            world[label] = world[rest.labels[parent]] if parent >= 0 else eye
        full.append(world[label])
    full = np.stack(full, axis=1)  # (T, J, 3, 3)
    parents = np.array(rest.parents)
    local = np.swapaxes(full[:, np.maximum(parents, 0)], -1, -2) @ full
    index = {b: i for i, b in enumerate(rest.labels)}
    ids = [index[b] for b in rest.body_joint_names]
    body = Rotation.from_matrix(local[:, ids].reshape(-1, 3, 3)).as_rotvec().reshape(T, len(ids), 3)
    orient = Rotation.from_matrix(full[:, 0]).as_rotvec()
    return body.astype(np.float32), orient.astype(np.float32)


def load_clip(asf: str | Path, amc: str | Path, step: int = 1) -> tuple[Skeleton, dict[str, np.ndarray]]:
    """Skeleton and motion of one clip, keeping every `step`-th frame."""
    skeleton = parse_asf(asf)
    motion = parse_amc(amc, skeleton)
    return skeleton, {k: v[::step] for k, v in motion.items()}


def list_clips(root: str | Path) -> list[tuple[Path, Path]]:
    """(asf, amc) pairs under a CMU folder laid out as subjects/NN/NN.asf, NN_MM.amc."""
    root = Path(root)
    pairs = []
    for amc in sorted(root.rglob("*.amc")):
        asf = amc.parent / f"{amc.stem.split('_')[0]}.asf"
        if not asf.exists():
            raise FileNotFoundError(f"{amc}: its skeleton {asf.name} is missing")
        pairs.append((asf, amc))
    if not pairs:
        raise FileNotFoundError(f"no .amc files under {root}")
    return pairs
