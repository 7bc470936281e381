"""Scripted human-object interactions for synthetic sessions.

A `Script` is data: named phases (seconds), eased keyframes for the body's
posture, heading, gait, hand targets and finger closure, and the object's
anchors. `animate` turns a script into per-frame body parameters, world-space
vertices and keypoints, object poses and contact labels:

1. keyframes -> per-frame bone rotations (quaternion slerp with smoothstep
   easing) plus a phase-driven walk cycle (legs swing, knees flex in swing,
   arms counter-swing);
2. the root follows the stance foot (no foot skating) and is lifted so the
   lowest vertex touches the floor z = 0;
3. the object's track is planned from its anchors (fixed in the world,
   carried in the person's heading frame, or held at the mouth);
4. L-BFGS on the body model bends the arms (and a little the spine) so each
   palm lies on its grasp point, facing the surface, with the hand kept out of
   the object and above the floor and the table tops the script names (solved at
   <= 5 Hz, spread, polished per frame);
5. per-finger curls (and the thumb) close until the fingers touch the object
   without sinking in (a signed-distance grid of the object, differentiable).
While the hands hold it, the object therefore moves rigidly with them: its pose
is the plan and the hands follow it (the measured gap is reported).

The bone names and axes are anny's (local-ref parameterisation, axes aligned
with the model axes at rest; the person faces -y with left on +x):
x flexes the spine forward (+), swings the thigh back (+) / forward (-) and
bends the knee (+); for the arms x swings the arm back (+) / forward (-).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation, Slerp

from intercap.synth.objects import NO_OBJECT, ObjectSpec, SdfGrid, SurfaceDistance, make_object
from intercap.synth.options import SCRIPT_NAMES

PHYSICS_SCRIPTS = ("toss", "hold", "drop")  # scripts with analytic physics (ground_truth/physics.npz)
GRAVITY = 9.81  # m/s^2 along the generator's up (+z)
TABLE_TOP = 0.74  # height of the "table" prop's top above the floor, metres

# Bones the IK may move, with the weight of their pull back to the scripted pose.
IK_BONES = {
    "spine03": 120.0, "spine02": 120.0, "spine01": 120.0,
    "clavicle.L": 10.0, "clavicle.R": 10.0,
    "upperarm01.L": 0.5, "upperarm01.R": 0.5, "upperarm02.L": 2.0, "upperarm02.R": 2.0,
    "lowerarm01.L": 0.5, "lowerarm01.R": 0.5, "lowerarm02.L": 1.0, "lowerarm02.R": 1.0,
    "wrist.L": 1.0, "wrist.R": 1.0,
}
SIDES = {"left": "L", "right": "R"}
HAND_OFFSET = {"L": 25, "R": 46}  # first keypoint of each hand in the 67-keypoint layout
FINGER_BONE_PREFIX = ["finger1", "finger2", "finger3", "finger4", "finger5"]  # thumb .. little


# ----------------------------------------------------------------------------- scripts
@dataclass
class ObjectKey:
    """The object's pose at time `t`: `rel` (4x4) in the person's heading frame,
    taken at time `t` when `frame == 'body'` (carried) or at time `ref` when
    `frame == 'world'` (resting where it was put); `frame == 'head'`: the
    heading frame moved to the nose (brought to the mouth)."""

    t: float
    frame: str
    rel: np.ndarray
    ref: float = 0.0
    on_floor: bool = False  # rest on the floor: the height becomes the object's own half height
    on_surface: float | None = None  # rest on a level surface this high (m): its height plus the half height


@dataclass
class Script:
    """A scripted interaction: phases and eased keyframes, times in seconds.

    pose_keys: (t, {bone: axis-angle}) posture, unnamed bones at rest;
    pitch_keys: (t, rad) forward tilt of the pelvis; yaw_keys: (t, rad) heading
    change (left turn +); walk_keys: (t, signed gait intensity, + forward);
    reach_keys: (t, weight of the grasp targets in the IK); gap_keys: (t, metres
    the palms stay off the surface along its normal, approach/withdraw);
    close_keys: (t, finger closure 0 relaxed .. 1 touching); contact: phases
    during which the hands touch the object; props: static scene meshes (name,
    kind, rel pose in the heading frame at time 0)."""

    name: str
    duration: float
    phases: dict
    default_object: str
    hands: tuple
    pose_keys: list
    pitch_keys: list
    yaw_keys: list
    walk_keys: list
    reach_keys: list
    gap_keys: list
    close_keys: list
    object_keys: list
    contact: tuple
    props: list = field(default_factory=list)
    # free flight: ("catch", t_release, t_catch) thrown and caught again, or ("drop", t_release)
    # falling onto the floor; the object follows an exact parabola under GRAVITY in between
    flight: tuple | None = None
    flight_turns: float = 0.0  # "catch": whole turns about the object's own x axis in flight (a spinning toss)
    hands_above: tuple = ()  # names of props (tables) whose top the hands and fingers stay above
    # (prop kind, script time): furniture set under the seated body at that time, its top where the
    # buttocks are (`seat_prop`), so it fits every phenotype
    seat: tuple | None = None
    # the person starts at the middle of the camera ring and walks out between two cameras, out of their
    # views, and back (the generator sets the heading and centres the scene on the start)
    leaves_ring: bool = False

    @property
    def holds_object(self) -> bool:
        """Whether the script handles an object (False for the body-only scripts and `without_object`)."""
        return bool(self.hands)


def _rel(x, y, z, rotvec=(0.0, 0.0, 0.0)):
    """A 4x4 pose in the heading frame (x right, y forward, z up, metres)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = (x, y, z)
    return T


# Postures (anny bone -> axis-angle), mirrored for the two sides where it matters.
FOREARM_AXIS_R = (-0.511, -0.684, -0.521)  # anny's right forearm at rest (elbow to wrist, model axes): its twist axis
ARMS_RELAXED = {"upperarm01.L": (0.0, 0.55, 0.0), "upperarm01.R": (0.0, -0.55, 0.0),
                "lowerarm01.L": (-0.15, 0.0, 0.0), "lowerarm01.R": (-0.15, 0.0, 0.0)}


def _stoop(depth: float, arms_forward: float = 1.0) -> dict:
    """Bend down to reach low (with a pelvis pitch of ~0.55 d): knees and hips flex, spine rounds,
    arms go forward; the soles stay flat (flat_feet)."""
    d = depth
    pose = {
        "upperleg01.L": (-0.5 * d, 0.0, 0.0), "upperleg01.R": (-0.5 * d, 0.0, 0.0),  # from the vertical
        "lowerleg01.L": (1.25 * d, 0.0, 0.0), "lowerleg01.R": (1.25 * d, 0.0, 0.0),
        "spine04": (0.18 * d, 0.0, 0.0), "spine03": (0.18 * d, 0.0, 0.0), "spine02": (0.12 * d, 0.0, 0.0),
        "neck01": (-0.25 * d, 0.0, 0.0), "head": (-0.2 * d, 0.0, 0.0),
        "upperarm01.L": (-0.7 * arms_forward, 0.15, 0.0), "upperarm01.R": (-0.7 * arms_forward, -0.15, 0.0),
        "lowerarm01.L": (-0.3, 0.0, 0.0), "lowerarm01.R": (-0.3, 0.0, 0.0),
    }
    return pose


def _hold(elbow: float = 1.2, forward: float = 0.5) -> dict:
    """Upright, forearms raised in front of the body (carrying or pushing)."""
    return {
        "upperarm01.L": (-forward, 0.15, 0.0), "upperarm01.R": (-forward, -0.15, 0.0),
        "lowerarm01.L": (-elbow, 0.0, 0.0), "lowerarm01.R": (-elbow, 0.0, 0.0),
    }


def pick_place() -> Script:
    """Walk to a box on the floor, bend, grasp it with both hands, lift, carry
    while turning left, put it down, let go and step back."""
    phases = {
        "approach": (0.0, 1.8), "reach": (1.8, 2.7), "grasp": (2.7, 3.0), "lift": (3.0, 3.8),
        "carry_turn": (3.8, 5.0), "put_down": (5.0, 5.8), "release": (5.8, 6.1), "step_back": (6.1, 7.2),
    }
    stoop = _stoop(1.0)
    carry = _hold(elbow=1.3, forward=0.35)
    pose_keys = [(0.0, ARMS_RELAXED), (1.8, ARMS_RELAXED), (2.7, stoop), (3.0, stoop), (3.8, carry),
                 (5.0, carry), (5.8, stoop), (6.1, stoop), (6.9, ARMS_RELAXED)]
    pitch_keys = [(0.0, 0.0), (1.8, 0.0), (2.7, 0.55), (3.0, 0.55), (3.8, 0.05), (5.0, 0.05), (5.8, 0.55),
                  (6.1, 0.55), (6.9, 0.0)]
    yaw_keys = [(0.0, 0.0), (3.9, 0.0), (4.9, np.pi / 2)]
    walk_keys = [(0.0, 0.0), (0.5, 1.0), (1.3, 1.0), (1.8, 0.0), (3.8, 0.0), (4.1, 0.45), (4.7, 0.45),
                 (5.0, 0.0), (6.1, 0.0), (6.5, -0.55), (6.8, -0.55), (7.2, 0.0)]
    reach_keys = [(0.0, 0.0), (2.0, 0.0), (2.6, 1.0), (6.1, 1.0), (6.6, 0.0)]
    gap_keys = [(0.0, 0.12), (2.0, 0.12), (2.7, 0.0), (5.8, 0.0), (6.3, 0.12)]
    close_keys = [(0.0, 0.0), (2.7, 0.0), (3.0, 1.0), (5.8, 1.0), (6.0, 0.0)]
    floor = _rel(0.0, 0.47, 0.075)  # box centre: 0.47 m ahead, lying on the floor
    carry_rel = _rel(0.0, 0.40, 0.88)
    object_keys = [
        ObjectKey(0.0, "world", floor, ref=2.7, on_floor=True), ObjectKey(3.0, "world", floor, ref=2.7, on_floor=True),
        ObjectKey(3.8, "body", carry_rel), ObjectKey(5.0, "body", carry_rel),
        ObjectKey(5.8, "world", floor, ref=5.8, on_floor=True), ObjectKey(7.2, "world", floor, ref=5.8, on_floor=True),
    ]
    return Script("pick_place", 7.2, phases, "box", ("left", "right"), pose_keys, pitch_keys, yaw_keys,
                  walk_keys, reach_keys, gap_keys, close_keys, object_keys, contact=("grasp", "put_down"))


def lift_drink() -> Script:
    """Stand at a table, pick up a cup with the right hand, drink, put it back."""
    phases = {"stand": (0.0, 0.6), "reach": (0.6, 1.5), "grasp": (1.5, 1.8), "lift": (1.8, 2.7),
              "drink": (2.7, 3.7), "lower": (3.7, 4.6), "release": (4.6, 4.9), "retract": (4.9, 5.8)}
    relaxed = ARMS_RELAXED
    reach = dict(ARMS_RELAXED, **{"upperarm01.R": (-0.6, 0.1, 0.0), "lowerarm01.R": (-0.6, 0.0, 0.0),
                                  "spine03": (0.08, 0.0, 0.0)})
    drink = dict(ARMS_RELAXED, **{"upperarm01.R": (-0.6, 0.3, 0.0), "lowerarm01.R": (-2.0, 0.0, 0.0),
                                  "head": (0.12, 0.0, 0.0), "neck01": (-0.15, 0.0, 0.0)})
    drink_tilt = dict(drink, **{"head": (-0.12, 0.0, 0.0), "neck01": (-0.25, 0.0, 0.0)})
    pose_keys = [(0.0, relaxed), (0.6, relaxed), (1.5, reach), (1.8, reach), (2.7, drink), (3.0, drink_tilt),
                 (3.4, drink_tilt), (3.7, drink), (4.6, reach), (4.9, reach), (5.8, relaxed)]
    pitch_keys = [(0.0, 0.0), (0.6, 0.0), (1.5, 0.12), (1.8, 0.12), (2.7, 0.0), (3.7, 0.0), (4.6, 0.12),
                  (4.9, 0.12), (5.8, 0.0)]
    yaw_keys = [(0.0, 0.0)]
    walk_keys = [(0.0, 0.0)]
    reach_keys = [(0.0, 0.0), (0.8, 0.0), (1.4, 1.0), (4.9, 1.0), (5.4, 0.0)]
    gap_keys = [(0.0, 0.10), (0.8, 0.10), (1.5, 0.0), (4.6, 0.0), (5.1, 0.10)]
    close_keys = [(0.0, 0.0), (1.5, 0.0), (1.8, 1.0), (4.6, 1.0), (4.8, 0.0)]
    table_h = 0.74
    on_table = _rel(0.12, 0.42, table_h + 0.05)
    # relative to the nose: the tilted cup's near rim touches the lips (4-5 cm below the nose)
    # (turned 0.6 rad about the vertical so the right hand holds it from the front-right)
    turn = Rotation.from_rotvec((0.0, 0.0, 0.6))
    at_mouth = _rel(0.01, 0.12, -0.12, rotvec=turn.as_rotvec())
    tilted = _rel(0.0, 0.068, -0.066, rotvec=(Rotation.from_rotvec((0.6, 0.0, 0.0)) * turn).as_rotvec())
    object_keys = [
        ObjectKey(0.0, "world", on_table, ref=0.0), ObjectKey(1.8, "world", on_table, ref=0.0),
        ObjectKey(2.7, "head", at_mouth), ObjectKey(3.0, "head", tilted), ObjectKey(3.4, "head", tilted),
        ObjectKey(3.7, "head", at_mouth), ObjectKey(4.6, "world", on_table, ref=0.0),
        ObjectKey(5.8, "world", on_table, ref=0.0),
    ]
    props = [("table", "table", _rel(0.05, 0.55, table_h / 2))]
    return Script("lift_drink", 5.8, phases, "cup", ("right",), pose_keys, pitch_keys, yaw_keys, walk_keys,
                  reach_keys, gap_keys, close_keys, object_keys, contact=("grasp", "lower"), props=props)


def push_chair() -> Script:
    """Step behind a chair, put both hands on its back, push it forward while
    walking, let go and step back."""
    phases = {"stand": (0.0, 0.4), "reach": (0.4, 1.2), "grasp": (1.2, 1.5), "push": (1.5, 3.9),
              "release": (3.9, 4.2), "step_back": (4.2, 5.4)}
    lean = dict(_hold(elbow=0.5, forward=0.6), **{"spine03": (0.1, 0.0, 0.0), "spine02": (0.05, 0.0, 0.0)})
    pose_keys = [(0.0, ARMS_RELAXED), (0.4, ARMS_RELAXED), (1.2, lean), (4.2, lean), (5.0, ARMS_RELAXED)]
    pitch_keys = [(0.0, 0.0), (0.4, 0.0), (1.2, 0.15), (4.2, 0.15), (5.0, 0.0)]
    yaw_keys = [(0.0, 0.0), (2.2, 0.0), (3.4, 0.35)]
    walk_keys = [(0.0, 0.0), (1.5, 0.0), (1.9, 0.7), (3.5, 0.7), (3.9, 0.0), (4.2, 0.0), (4.6, -0.55),
                 (5.0, -0.55), (5.4, 0.0)]
    reach_keys = [(0.0, 0.0), (0.5, 0.0), (1.1, 1.0), (4.2, 1.0), (4.7, 0.0)]
    gap_keys = [(0.0, 0.10), (0.5, 0.10), (1.2, 0.0), (3.9, 0.0), (4.4, 0.10)]
    close_keys = [(0.0, 0.0), (1.2, 0.0), (1.5, 1.0), (3.9, 1.0), (4.1, 0.0)]
    behind = _rel(0.0, 0.62, 0.425)
    object_keys = [ObjectKey(t, frame, behind, ref=ref, on_floor=True) for t, frame, ref in (
        (0.0, "world", 1.5), (1.5, "world", 1.5), (1.50001, "body", 0.0), (3.9, "body", 0.0),
        (3.90001, "world", 3.9), (5.4, "world", 3.9))]
    return Script("push_chair", 5.4, phases, "chair", ("left", "right"), pose_keys, pitch_keys, yaw_keys,
                  walk_keys, reach_keys, gap_keys, close_keys, object_keys, contact=("grasp", "push"))


def toss() -> Script:
    """Stand holding a small block in both hands at chest height, dip, throw it straight up and
    catch it 0.5 s later (15 frames of free flight at 30 fps: an exact parabola), hold it."""
    phases = {"hold": (0.0, 0.5), "windup": (0.5, 1.0), "flight": (1.0, 1.5), "catch": (1.5, 2.45)}  # held at the end
    carry = _hold(elbow=1.3, forward=0.35)
    pose_keys = [(0.0, carry), (2.4, carry)]
    reach_keys = [(0.0, 1.0), (2.4, 1.0)]
    gap_keys = [(0.0, 0.0), (1.0, 0.0), (1.1, 0.04), (1.4, 0.04), (1.5, 0.0)]  # palms open off the block in flight
    close_keys = [(0.0, 1.0), (1.0, 1.0), (1.08, 0.0), (1.42, 0.0), (1.5, 1.0)]
    held = _rel(0.0, 0.38, 1.0)
    low = _rel(0.0, 0.38, 0.92)
    object_keys = [ObjectKey(0.0, "body", held), ObjectKey(0.5, "body", held), ObjectKey(0.75, "body", low),
                   ObjectKey(1.0, "body", held), ObjectKey(2.4, "body", held)]
    return Script("toss", 2.4, phases, "block", ("left", "right"), pose_keys, [(0.0, 0.0)], [(0.0, 0.0)],
                  [(0.0, 0.0)], reach_keys, gap_keys, close_keys, object_keys, contact=("hold", "catch"),
                  flight=("catch", 1.0, 1.5))


def hold() -> Script:
    """Stand still holding a box (known mass) in both hands in front of the body."""
    phases = {"hold": (0.0, 2.05)}  # past the end: the last frame is held too
    carry = _hold(elbow=1.3, forward=0.35)
    held = _rel(0.0, 0.40, 0.95)
    return Script("hold", 2.0, phases, "box", ("left", "right"), [(0.0, carry)], [(0.0, 0.0)], [(0.0, 0.0)],
                  [(0.0, 0.0)], [(0.0, 1.0)], [(0.0, 0.0)], [(0.0, 1.0)], [ObjectKey(0.0, "body", held)],
                  contact=("hold", "hold"))


def drop() -> Script:
    """Stand holding a box in front of the body, open the hands and let it fall onto the floor
    (free fall from rest: an exact parabola until it lands flat), lower the arms."""
    phases = {"hold": (0.0, 0.6), "fall": (0.6, 2.0)}
    carry = _hold(elbow=1.3, forward=0.35)
    pose_keys = [(0.0, carry), (0.6, carry), (1.4, ARMS_RELAXED)]
    held = _rel(0.0, 0.40, 0.95)
    return Script("drop", 2.0, phases, "box", ("left", "right"), pose_keys, [(0.0, 0.0)], [(0.0, 0.0)],
                  [(0.0, 0.0)], [(0.0, 1.0), (0.6, 1.0), (1.1, 0.0)], [(0.0, 0.0), (0.6, 0.0), (0.7, 0.06)],
                  [(0.0, 1.0), (0.6, 1.0), (0.7, 0.0)], [ObjectKey(0.0, "body", held)], contact=("hold", "hold"),
                  flight=("drop", 0.6))


def turn() -> Script:
    """Turn round once on the spot holding a box in both hands: every camera sees the front, a side
    and the back in turn (the case where keypoints become ambiguous and a warm start goes wrong)."""
    phases = {"hold": (0.0, 6.05)}
    carry = _hold(elbow=1.3, forward=0.35)
    held = _rel(0.0, 0.40, 0.95)
    yaw = [(0.0, 0.0), (0.5, 0.0), (5.5, 2 * np.pi), (6.0, 2 * np.pi)]
    return Script("turn", 6.0, phases, "box", ("left", "right"), [(0.0, carry)], [(0.0, 0.0)], yaw,
                  [(0.0, 0.0)], [(0.0, 1.0)], [(0.0, 0.0)], [(0.0, 1.0)], [ObjectKey(0.0, "body", held)],
                  contact=("hold", "hold"))


ARM_BONE_PREFIXES = ("clavicle", "shoulder", "upperarm", "lowerarm", "wrist")


def _relax_arms(pose: dict) -> dict:
    """The posture with the arms hanging relaxed (ARMS_RELAXED) instead of as scripted."""
    kept = {bone: rv for bone, rv in pose.items() if not bone.startswith(ARM_BONE_PREFIXES)}
    return dict(kept, **ARMS_RELAXED)


def without_object(script: Script) -> Script:
    """The script's body motion with no object: the same phases, heading, gait and posture, the arms
    hanging relaxed where they would hold or reach for it, no contact, no flight; furniture stays."""
    if not script.holds_object:
        return script
    return dataclasses.replace(
        script, default_object=NO_OBJECT, hands=(), pose_keys=[(t, _relax_arms(p)) for t, p in script.pose_keys],
        reach_keys=[(0.0, 0.0)], gap_keys=[(0.0, 0.0)], close_keys=[(0.0, 0.0)], object_keys=[], contact=(),
        flight=None, flight_turns=0.0, hands_above=())


def _body_only(name: str, duration: float, phases: dict, pose_keys: list, pitch_keys: list, **extra) -> Script:
    """A script of the person alone: no object, standing on the spot (no walk, no turn) unless `extra` says."""
    fields = dict(yaw_keys=[(0.0, 0.0)], walk_keys=[(0.0, 0.0)], reach_keys=[(0.0, 0.0)], gap_keys=[(0.0, 0.0)],
                  close_keys=[(0.0, 0.0)], object_keys=[], contact=())
    fields.update(extra)
    return Script(name, duration, phases, NO_OBJECT, (), pose_keys, pitch_keys, **fields)


def bend() -> Script:
    """Stand, bend forward from the hips, the knees a little soft, until the hands hang at the knees
    (the head comes down about 0.7 m), hold a moment, straighten up again (4 s)."""
    phases = {"stand": (0.0, 0.5), "bend_down": (0.5, 1.7), "low": (1.7, 2.3), "straighten": (2.3, 3.5),
              "stand_again": (3.5, 4.05)}
    low = {"spine04": (0.2, 0.0, 0.0), "spine03": (0.2, 0.0, 0.0), "spine02": (0.15, 0.0, 0.0),
           "neck01": (-0.1, 0.0, 0.0), "head": (-0.1, 0.0, 0.0),
           "upperleg01.L": (-0.12, 0.0, 0.0), "upperleg01.R": (-0.12, 0.0, 0.0),  # from the vertical
           "lowerleg01.L": (0.3, 0.0, 0.0), "lowerleg01.R": (0.3, 0.0, 0.0),
           # arms swung forward with the trunk, hanging down towards the shins
           "upperarm01.L": (-1.3, 0.55, 0.0), "upperarm01.R": (-1.3, -0.55, 0.0),
           "lowerarm01.L": (-0.2, 0.0, 0.0), "lowerarm01.R": (-0.2, 0.0, 0.0)}
    pose_keys = [(0.0, ARMS_RELAXED), (0.5, ARMS_RELAXED), (1.7, low), (2.3, low), (3.5, ARMS_RELAXED)]
    pitch_keys = [(0.0, 0.0), (0.5, 0.0), (1.7, 1.05), (2.3, 1.05), (3.5, 0.0)]
    return _body_only("bend", 4.0, phases, pose_keys, pitch_keys)


def sit_stand() -> Script:
    """Stand in front of a stool, sit down onto it (leaning forward as the hips go back and down), sit
    upright a moment, lean forward again and stand up (5 s). The feet stay where they are; the stool
    (`Script.seat`) is static furniture placed under the seated body."""
    phases = {"stand": (0.0, 0.6), "sit_down": (0.6, 2.1), "seated": (2.1, 3.0), "stand_up": (3.0, 4.6),
              "stand_again": (4.6, 5.05)}

    def legs(thigh: float, knee: float) -> dict:  # thigh from the vertical (- forward), knee flexion
        return {"upperleg01.L": (thigh, 0.0, 0.0), "upperleg01.R": (thigh, 0.0, 0.0),
                "lowerleg01.L": (knee, 0.0, 0.0), "lowerleg01.R": (knee, 0.0, 0.0)}

    arms_forward = {"upperarm01.L": (-0.45, 0.4, 0.0), "upperarm01.R": (-0.45, -0.4, 0.0),
                    "lowerarm01.L": (-0.35, 0.0, 0.0), "lowerarm01.R": (-0.35, 0.0, 0.0)}
    lowering = dict(legs(-1.2, 1.15), **arms_forward, spine03=(0.1, 0.0, 0.0))
    seated = {**legs(-1.45, 1.45), **ARMS_RELAXED,  # hands resting towards the thighs
              "upperarm01.L": (-0.25, 0.45, 0.0), "upperarm01.R": (-0.25, -0.45, 0.0)}
    rising = dict(legs(-1.45, 1.45), **arms_forward, spine03=(0.12, 0.0, 0.0))
    half_up = dict(legs(-0.7, 0.65), **arms_forward)
    pose_keys = [(0.0, ARMS_RELAXED), (0.6, ARMS_RELAXED), (1.6, lowering), (2.1, seated), (3.0, seated),
                 (3.5, rising), (4.1, half_up), (4.6, ARMS_RELAXED)]
    pitch_keys = [(0.0, 0.0), (0.6, 0.0), (1.6, 0.5), (2.1, 0.12), (3.0, 0.12), (3.5, 0.6), (4.1, 0.35), (4.6, 0.0)]
    return _body_only("sit_stand", 5.0, phases, pose_keys, pitch_keys, seat=("stool", 2.5))


def walk_out() -> Script:
    """Stand at the middle of the room, walk 2.3 m straight ahead (out of the views of the cameras
    either side, `Script.leaves_ring`), stand there a moment, turn round, walk back, turn round
    again to face the way it started, stand (10 s)."""
    phases = {"stand": (0.0, 0.5), "walk_out": (0.5, 3.7), "away": (3.7, 4.2), "turn": (4.2, 5.4),
              "walk_back": (5.4, 8.6), "turn_back": (8.6, 9.8), "stand_again": (9.8, 10.05)}
    walk_keys = [(0.0, 0.0), (0.5, 0.0), (1.0, 0.9), (3.2, 0.9), (3.7, 0.0), (5.4, 0.0), (5.9, 0.9), (7.85, 0.9),
                 (8.35, 0.0)]
    yaw_keys = [(0.0, 0.0), (4.2, 0.0), (5.4, np.pi), (8.6, np.pi), (9.8, 2 * np.pi)]
    return _body_only("walk_out", 10.0, phases, [(0.0, ARMS_RELAXED)], [(0.0, 0.0)], yaw_keys=yaw_keys,
                      walk_keys=walk_keys, leaves_ring=True)


def _table_layout(spec: ObjectSpec, near_edge: float, right_edge: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Where table_lift puts the object, in the heading frame: its pose resting on the table (height
    set by `on_surface`), its pose held up, and the forward lean (rad) of the reach.

    The object rests 3 cm in from the table's near edge (`near_edge` m ahead), at least 0.45 m ahead,
    in the middle (one hand: its grasp 0.16 m right); one held by a handle (`Grasp.wraps`) rests 0.42 m
    ahead with that grasp 9 cm out over the table's right edge (`right_edge`). Held up, the palms'
    midpoint is 0.39 m ahead and 1.02 m high; one hand holds it 0.38 m ahead, 1.0 m high and 0.18 m
    right, turned so that the palm faces left with the fingers forward (a tool held upright)."""
    grasps = list(spec.grasps.values())
    point = np.mean([g.point for g in grasps], axis=0)
    wraps = any(g.wraps for g in grasps)
    x = right_edge + 0.09 - point[0] if wraps else (0.16 - point[0] if len(grasps) == 1 else 0.0)
    y = 0.42 if wraps else max(0.45, near_edge + 0.03 + float(spec.mesh.bounds[1, 1]))
    R, hand = np.eye(3), np.array([0.0, 0.39, 1.02])
    if len(grasps) == 1:
        n, f = np.asarray(grasps[0].normal, float), np.asarray(grasps[0].finger_dir, float)
        R, hand = np.column_stack([n, f, np.cross(n, f)]).T, np.array([0.18, 0.38, 1.0])  # n -> x, f -> y
    held = np.eye(4)
    held[:3, :3], held[:3, 3] = R, hand - R @ point
    # lean further for a grasp farther ahead, out to the right or nearer the table top (a flat box)
    height = TABLE_TOP + spec.half_height + point[2]
    far = 1.5 * (0.86 - height) + 1.5 * (y + point[1] - 0.45) + 1.5 * max(0.0, x + point[0] - 0.16)
    lean = float(np.clip(0.12 + far, 0.12, 0.3))
    return _rel(x, y, 0.0), held, lean


def table_lift(spec: ObjectSpec | None = None) -> Script:
    """Stand at a table beside a shelf and a stool, grasp the object resting on the table top (both hands,
    or the right hand alone for an object with one grasp), lift it, turn 90 degrees left holding it,
    turn back, put it down where it was, let go and step back. The object lies still on the table for
    the first third and the last quarter; the furniture never moves."""
    spec = spec if spec is not None else make_object("carton")
    one_hand = "left" not in spec.grasps
    phases = {"stand": (0.0, 0.8), "reach": (0.8, 1.8), "grasp": (1.8, 2.1), "lift": (2.1, 2.9), "turn": (2.9, 3.8),
              "turn_back": (3.8, 4.6), "put_down": (4.6, 5.2), "release": (5.2, 5.5), "step_back": (5.5, 6.8)}
    # Turning on the spot pivots about the feet, 12 cm ahead of the hips: the table's near edge stands
    # 0.36 m ahead so that the hips clear it at 90 degrees. The shelf (behind the table, open towards
    # it) and the stool stand 1.2-1.5 m off the action, between the default ring's cameras and low
    # enough that a camera behind them still sees the person over them.
    table_x, table_y = -0.15, 0.66
    rest, held, lean = _table_layout(spec, near_edge=table_y - 0.3, right_edge=table_x + 0.4)
    if one_hand:
        reach = dict(ARMS_RELAXED, **{"upperarm01.R": (-0.6, 0.1, 0.0), "lowerarm01.R": (-0.6, 0.0, 0.0),
                                      "spine03": (0.08, 0.0, 0.0)})
        if spec.grasps["right"].normal[2] > 0.5:  # palm down onto it: the forearm turned in (pronated)
            reach["lowerarm02.R"] = tuple(-1.2 * np.asarray(FOREARM_AXIS_R))
        carry = dict(ARMS_RELAXED, **{"upperarm01.R": (-0.45, -0.1, 0.0), "lowerarm01.R": (-1.3, 0.0, 0.0)})
    else:
        reach = {"upperarm01.L": (-0.6, 0.15, 0.0), "upperarm01.R": (-0.6, -0.15, 0.0),
                 "lowerarm01.L": (-0.5, 0.0, 0.0), "lowerarm01.R": (-0.5, 0.0, 0.0), "spine03": (0.08, 0.0, 0.0)}
        carry = _hold(elbow=1.3, forward=0.35)
    pose_keys = [(0.0, ARMS_RELAXED), (0.8, ARMS_RELAXED), (1.8, reach), (2.1, reach), (2.9, carry), (4.6, carry),
                 (5.2, reach), (5.5, reach), (6.3, ARMS_RELAXED)]
    pitch_keys = [(0.0, 0.0), (0.8, 0.0), (1.8, lean), (2.1, lean), (2.9, 0.05), (4.6, 0.05), (5.2, lean),
                  (5.5, lean), (6.3, 0.0)]
    yaw_keys = [(0.0, 0.0), (2.9, 0.0), (3.7, np.pi / 2), (3.9, np.pi / 2), (4.6, 0.0)]
    walk_keys = [(0.0, 0.0), (5.5, 0.0), (5.9, -0.55), (6.4, -0.55), (6.8, 0.0)]
    reach_keys = [(0.0, 0.0), (1.0, 0.0), (1.7, 1.0), (5.5, 1.0), (6.0, 0.0)]
    gap_keys = [(0.0, 0.12), (1.0, 0.12), (1.8, 0.0), (5.2, 0.0), (5.7, 0.12)]
    close_keys = [(0.0, 0.0), (1.8, 0.0), (2.1, 1.0), (5.2, 1.0), (5.4, 0.0)]
    on_table = [ObjectKey(t, "world", rest, on_surface=TABLE_TOP) for t in (0.0, 2.1, 5.2, 6.8)]
    object_keys = on_table[:2] + [ObjectKey(2.9, "body", held), ObjectKey(4.6, "body", held)] + on_table[2:]
    props = [("table", "table", _rel(table_x, table_y, TABLE_TOP / 2)),
             ("shelf", "shelf", _rel(0.8, 1.35, SHELF_SIZE[2] / 2)),
             ("stool", "stool", _rel(-1.0, 0.9, STOOL_SIZE[2] / 2, rotvec=(0.0, 0.0, 0.4)))]
    return Script("table_lift", 6.8, phases, "carton", ("right",) if one_hand else ("left", "right"), pose_keys,
                  pitch_keys, yaw_keys, walk_keys, reach_keys, gap_keys, close_keys, object_keys,
                  contact=("grasp", "put_down"), props=props, hands_above=("table",))


def get_script(name: str, spec: ObjectSpec | None = None) -> Script:
    """The named script (`SCRIPT_NAMES`); table_lift fits its grasp and layout to the object `spec`
    (its default, the carton, when None); the others hold every object the same way. bend,
    sit_stand and walk_out are body-only (no object; `without_object` makes any other script so)."""
    scripts = {"pick_place": pick_place, "lift_drink": lift_drink, "push_chair": push_chair, "toss": toss,
               "hold": hold, "drop": drop, "turn": turn, "bend": bend, "sit_stand": sit_stand,
               "walk_out": walk_out}
    if name == "table_lift":
        return table_lift(spec)
    if name not in scripts:
        raise ValueError(f"unknown script {name!r}; choose one of {SCRIPT_NAMES}")
    return scripts[name]()


def contact_interval(script: Script) -> tuple[float, float]:
    """Seconds during which the hands touch the object: start of the first
    contact phase to the end of the last (an empty interval for a script without contact)."""
    if not script.contact:
        return 0.0, 0.0
    return script.phases[script.contact[0]][0], script.phases[script.contact[1]][1]


SHELF_SIZE = (0.80, 0.35, 0.90)  # the "shelf" prop: width (x), depth (y), height (z), metres
STOOL_SIZE = (0.38, 0.38, 0.46)  # the "stool" prop: seat width, depth and height, metres


def _table_mesh() -> trimesh.Trimesh:
    """A table 0.8 x 0.6 m, 0.74 m high (TABLE_TOP): a top on four legs, centred on its bounding box."""
    parts = []
    top = trimesh.creation.box(extents=(0.8, 0.6, 0.04))
    top.apply_translation((0, 0, 0.37 - 0.02))
    parts.append(top)
    for sx in (-1, 1):
        for sy in (-1, 1):
            leg = trimesh.creation.box(extents=(0.05, 0.05, 0.70 - 0.001))
            leg.apply_translation((sx * 0.35, sy * 0.25, -0.37 + 0.35 - 0.0005))
            parts.append(leg)
    return trimesh.util.concatenate(parts)


def _boxes_mesh(boxes: list, size: tuple) -> trimesh.Trimesh:
    """Closed boxes given by (lo, hi) corners in a frame with the floor at z = 0 and the footprint
    centred, joined and moved so the whole is centred on its bounding box (`size`)."""
    parts = []
    for lo, hi in boxes:
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        part = trimesh.creation.box(extents=hi - lo)
        part.apply_translation((lo + hi) / 2 - (0.0, 0.0, size[2] / 2))
        parts.append(part)
    return trimesh.util.concatenate(parts)


def _shelf_mesh(size=SHELF_SIZE, board=0.02, gap=0.001) -> trimesh.Trimesh:
    """An open shelf unit, open to -y: two sides, a top, two boards and a back panel, 1 mm apart."""
    hw, hd, h = size[0] / 2, size[1] / 2, size[2]
    boxes = [((-hw, -hd, 0.0), (-hw + board, hd, h)), ((hw - board, -hd, 0.0), (hw, hd, h)),  # sides
             ((-hw + board + gap, hd - 0.01, 0.05), (hw - board - gap, hd, h - board - gap))]  # back panel
    for z in (0.05, 0.45, h - board):  # boards, the lowest above a plinth gap, the last the top
        boxes.append(((-hw + board + gap, -hd, z), (hw - board - gap, hd - 0.01 - gap, z + board)))
    return _boxes_mesh(boxes, size)


def _stool_mesh(size=STOOL_SIZE, bar=0.035, seat=0.04, gap=0.001) -> trimesh.Trimesh:
    """A stool: a square seat on four legs, 1 mm apart."""
    hw, hd, h = size[0] / 2, size[1] / 2, size[2]
    boxes = [((-hw, -hd, h - seat), (hw, hd, h))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            x0 = hw - 0.02 - bar if sx > 0 else -hw + 0.02
            y0 = hd - 0.02 - bar if sy > 0 else -hd + 0.02
            boxes.append(((x0, y0, 0.0), (x0 + bar, y0 + bar, h - seat - gap)))
    return _boxes_mesh(boxes, size)


PROP_KINDS = {"table": _table_mesh, "shelf": _shelf_mesh, "stool": _stool_mesh}


def prop_meshes(script: Script) -> list[tuple[str, trimesh.Trimesh, np.ndarray]]:
    """Static scene meshes of the script (name, mesh, rel pose in the heading frame at time 0); each
    mesh is centred on its bounding box (`PROP_KINDS`)."""
    out = []
    for name, kind, rel in script.props:
        if kind not in PROP_KINDS:
            raise ValueError(f"script {script.name}: unknown prop kind {kind!r}; choose one of {sorted(PROP_KINDS)}")
        out.append((name, PROP_KINDS[kind](), rel))
    return out


# ----------------------------------------------------------------------------- interpolation
def smoothstep(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def eased_segments(key_times: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each time, the index of the key before it and the eased weight of the next key."""
    idx = np.clip(np.searchsorted(key_times, times, side="right") - 1, 0, len(key_times) - 1)
    nxt = np.minimum(idx + 1, len(key_times) - 1)
    span = np.maximum(key_times[nxt] - key_times[idx], 1e-9)
    weight = np.where(nxt > idx, smoothstep((times - key_times[idx]) / span), 0.0)
    return idx, weight


def eased_scalar(keys: list, times: np.ndarray) -> np.ndarray:
    """(T,) smoothstep-eased interpolation of (t, value) keys; constant outside."""
    kt = np.array([k[0] for k in keys], float)
    kv = np.array([k[1] for k in keys], float)
    idx, w = eased_segments(kt, times)
    return kv[idx] * (1 - w) + kv[np.minimum(idx + 1, len(kv) - 1)] * w


def eased_rotations(key_times: np.ndarray, key_rotvecs: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(T, J, 3) axis-angles slerped between (K, J, 3) keys with smoothstep easing."""
    idx, w = eased_segments(key_times, times)
    nxt = np.minimum(idx + 1, len(key_times) - 1)
    K, J, _ = key_rotvecs.shape
    out = np.zeros((len(times), J, 3))
    for j in range(J):
        qa = Rotation.from_rotvec(key_rotvecs[idx, j])
        qb = Rotation.from_rotvec(key_rotvecs[nxt, j])
        delta = (qa.inv() * qb).as_rotvec()  # shortest arc from a to b
        out[:, j] = (qa * Rotation.from_rotvec(delta * w[:, None])).as_rotvec()
    return out


def interpolate_poses(T0: np.ndarray, T1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(T, 4, 4) poses between (T, 4, 4) T0 and T1: lerp translation, slerp rotation."""
    r0 = Rotation.from_matrix(T0[:, :3, :3])
    r1 = Rotation.from_matrix(T1[:, :3, :3])
    out = np.tile(np.eye(4), (len(w), 1, 1))
    out[:, :3, :3] = (r0 * Rotation.from_rotvec((r0.inv() * r1).as_rotvec() * w[:, None])).as_matrix()
    out[:, :3, 3] = T0[:, :3, 3] * (1 - w[:, None]) + T1[:, :3, 3] * w[:, None]
    return out


# ----------------------------------------------------------------------------- body timeline
def posture_rotvecs(script: Script, body_joint_names: list[str], times: np.ndarray) -> np.ndarray:
    """(T, Jb, 3) scripted posture from the pose keys."""
    index = {n: i for i, n in enumerate(body_joint_names)}
    keys = np.zeros((len(script.pose_keys), len(body_joint_names), 3))
    for k, (_, pose) in enumerate(script.pose_keys):
        for bone, rv in pose.items():
            if bone not in index:
                raise KeyError(f"script {script.name}: unknown bone {bone!r}")
            keys[k, index[bone]] = rv
    key_times = np.array([k[0] for k in script.pose_keys], float)
    return eased_rotations(key_times, keys, times)


STANCE = 0.5  # share of a gait cycle a foot is down
LEG_PHASE = {"L": 0.25, "R": 0.75}  # each leg's offset in the gait cycle: the walk starts mid-stride, thighs together


def leg_cycle(u: np.ndarray, stance: float = STANCE) -> tuple[np.ndarray, np.ndarray]:
    """Thigh swing (+1 forward .. -1 back) and swing lift (0..1) at leg phase u (cycles).

    In stance (u mod 1 < `stance`) the thigh sweeps back linearly, so the foot moves
    back under the hip at a near-constant speed and the body, anchored on that foot,
    walks at a near-constant speed (a sine sweep would stop it at every step). The
    swing returns the thigh by a cubic whose end slopes match the stance sweep, and
    the two legs, half a cycle apart, meet the floor at the same angle."""
    u = np.mod(u, 1.0)
    x = np.clip((u - stance) / (1.0 - stance), 0.0, 1.0)  # swing progress
    slope = -2.0 * (1.0 - stance) / stance  # the stance sweep's slope in swing units
    h00, h10, h01, h11 = 2 * x**3 - 3 * x**2 + 1, x**3 - 2 * x**2 + x, -2 * x**3 + 3 * x**2, x**3 - x**2
    swing = -h00 + slope * h10 + h01 + slope * h11
    thigh = np.where(u < stance, 1.0 - 2.0 * u / stance, swing)
    lift = np.where(u < stance, 0.0, np.sin(np.pi * x) ** 1.5)
    return thigh, lift


def gait_cycles(script: Script, times: np.ndarray, cadence_hz: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """(T,) gait cycles walked by `times` (the phase advances with the signed intensity, backwards
    when negative) and (T,) the gait amplitude (the intensity's magnitude)."""
    fine = np.linspace(0.0, max(float(times.max()), 1e-3), 2000)  # integrate the phase finely, whatever the frame rate
    cycles_fine = cadence_hz * np.concatenate(
        [[0.0], np.cumsum(eased_scalar(script.walk_keys, fine)[1:] * np.diff(fine))])
    return np.interp(times, fine, cycles_fine), np.abs(eased_scalar(script.walk_keys, times))


def left_stance_weight(script: Script, times: np.ndarray, stance: float = STANCE) -> np.ndarray:
    """(T,) share of the weight on the left foot: its stance phase of the gait cycle while
    walking, both feet alike while standing (amplitude below 5 %)."""
    cycles, amp = gait_cycles(script, times)
    on_left = (np.mod(cycles + LEG_PHASE["L"], 1.0) < stance).astype(float)
    return 0.5 + (on_left - 0.5) * np.clip(amp / 0.05, 0.0, 1.0)


def gait_rotvecs(script: Script, body_joint_names: list[str], times: np.ndarray):
    """(T, Jb, 3) walk-cycle rotations to compose with the posture.

    The gait phase advances with the signed intensity (backwards when negative),
    the amplitude follows its magnitude: thighs sweep +-0.38 rad (leg_cycle), the
    knee flexes in swing, arms counter-swing, the pelvis rotates. Also returns each
    side's swing lift (T,) for flat_feet."""
    cycles, amp = gait_cycles(script, times)
    index = {n: i for i, n in enumerate(body_joint_names)}
    out = np.zeros((len(times), len(body_joint_names), 3))
    lifts = {}
    for side, offset in LEG_PHASE.items():
        thigh, lift = leg_cycle(cycles + offset)
        out[:, index[f"upperleg01.{side}"], 0] = -0.38 * amp * thigh
        out[:, index[f"lowerleg01.{side}"], 0] = amp * (0.08 + 0.85 * lift)
        lifts[side] = amp * lift
        out[:, index[f"upperarm01.{side}"], 0] = 0.3 * amp * np.cos(2 * np.pi * (cycles + offset))
        out[:, index[f"lowerarm01.{side}"], 0] = -0.15 * amp
    out[:, index["spine04"], 2] = 0.06 * amp * np.cos(2 * np.pi * (cycles + LEG_PHASE["L"]))
    return out, lifts


def flat_feet(pose: np.ndarray, body_joint_names: list[str], pitch: np.ndarray, lifts: dict) -> np.ndarray:
    """The ankles set so each sole lies flat on the floor when its foot is down (pelvis pitch, hip and
    knee flexion undone; the leg bones turn about their x axes), the toes lifted by up to 0.25 rad in
    swing (lifts: side -> (T,) swing lift 0..1). pose (T, Jb, 3) axis-angles, changed in place."""
    index = {n: i for i, n in enumerate(body_joint_names)}
    for side, lift in lifts.items():
        leg = pitch + pose[:, index[f"upperleg01.{side}"], 0] + pose[:, index[f"lowerleg01.{side}"], 0]
        pose[:, index[f"foot.{side}"]] = 0.0
        pose[:, index[f"foot.{side}"], 0] = -leg * (1.0 - lift) - 0.25 * lift
    return pose


def compose_rotvecs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-element rotation a then b (R_a @ R_b) as axis-angles, (..., 3)."""
    shape = a.shape
    r = Rotation.from_rotvec(a.reshape(-1, 3)) * Rotation.from_rotvec(b.reshape(-1, 3))
    return r.as_rotvec().reshape(shape)


def heading_frames(yaw: np.ndarray, root_xy: np.ndarray, heading0: float) -> np.ndarray:
    """(T, 4, 4) person heading frames: x right, y forward, z up, origin under the root on the floor."""
    psi = heading0 + yaw
    out = np.tile(np.eye(4), (len(yaw), 1, 1))
    out[:, :3, :3] = Rotation.from_euler("z", (psi - np.pi / 2)[:, None]).as_matrix()
    out[:, :2, 3] = root_xy
    return out


def model_to_heading(model) -> np.ndarray:
    """(3, 3) rotation from model coordinates to the heading frame (right, forward, up)."""
    fwd = np.asarray(model.forward_axis, float)
    up = np.asarray(model.up_axis, float)
    return np.stack([np.cross(fwd, up), fwd, up])


def body_orientation(model, heading: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """(T, 3, 3) global body rotation: heading frame, then a forward pitch of the pelvis."""
    up = np.asarray(model.up_axis, float)
    fwd = np.asarray(model.forward_axis, float)
    axis = np.cross(up, fwd)
    R_pitch = Rotation.from_rotvec(pitch[:, None] * axis[None]).as_matrix()  # (T, 3, 3)
    return heading[:, :3, :3] @ model_to_heading(model)[None] @ R_pitch


def stance_anchored_root(feet_l: np.ndarray, feet_r: np.ndarray, w_left: np.ndarray) -> np.ndarray:
    """(T, 2) root xy that keeps the supporting foot still.

    feet_l/r (T, 3): sole centres relative to the root, in world orientation;
    w_left (T,): the left foot's share of the support. The root moves opposite
    to the supporting feet's motion relative to the root."""
    d_l = np.diff(feet_l[:, :2], axis=0)
    d_r = np.diff(feet_r[:, :2], axis=0)
    w = 0.5 * (w_left[1:] + w_left[:-1])[:, None]
    step = -(w * d_l + (1 - w) * d_r)
    return np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])


def object_track(script: Script, frames: dict, times: np.ndarray, scale: float = 1.0,
                 half_height: float | None = None) -> np.ndarray:
    """(T, 4, 4) object -> world poses from the script's object keys.

    frames: 'body' -> (T, 4, 4) heading frames, 'head' -> (T, 4, 4) the same
    axes with the origin at the nose. Carried poses (frame 'body') are scaled
    with the person's stature (`scale` = stature / 1.625 m, anny's neutral adult)."""
    keys = script.object_keys
    key_times = np.array([k.t for k in keys])
    heading = frames["body"]

    def anchor(key: ObjectKey) -> np.ndarray:  # (T, 4, 4) world pose of one key at every frame
        rel = key.rel.copy()
        if key.on_floor and half_height is not None:
            rel[2, 3] = half_height
        if key.on_surface is not None and half_height is not None:
            rel[2, 3] = key.on_surface + half_height
        if key.frame == "body":
            rel[:3, 3] *= scale
            return heading @ rel
        if key.frame == "head":
            return frames["head"] @ rel
        if key.frame != "world":
            raise ValueError(f"script {script.name}: unknown object key frame {key.frame!r}")
        ref = int(np.argmin(np.abs(times - key.ref)))
        return np.broadcast_to(heading[ref] @ rel, (len(times), 4, 4)).copy()

    anchors = [anchor(k) for k in keys]
    idx, w = eased_segments(key_times, times)
    out = np.empty((len(times), 4, 4))
    for k in range(len(keys)):
        sel = idx == k
        if not sel.any():
            continue
        nxt = min(k + 1, len(keys) - 1)
        out[sel] = interpolate_poses(anchors[k][sel], anchors[nxt][sel], w[sel])
    return out


def flight_track(script: Script, plan: np.ndarray, times: np.ndarray, half_height: float):
    """The object's poses (T, 4, 4) with the script's free flight put into the planned track
    `plan` (where the hands hold it), and the flight's (first, last) frame (inclusive) or None.

    The flight leaves the plan at the last frame r at or before the release time. "catch":
    it rejoins the plan at the first frame c at or after the catch time; in between the
    centre follows p(t) = p_r + v0 (t - t_r) - 0.5 GRAVITY (t - t_r)^2 z with v0 chosen to
    meet p_c, the rotation turns at a constant rate from R_r to R_c, plus `script.flight_turns`
    whole turns about the object's x axis (a principal axis of the generator's objects, so a
    constant spin is torque-free and exact when R_r = R_c). "drop": it falls from rest, R held,
    until its centre is `half_height` above the floor, then lies there."""
    out = plan.copy()
    kind, t_release = script.flight[0], script.flight[1]
    r = int(np.flatnonzero(times <= t_release + 1e-9)[-1])
    acc = np.array([0.0, 0.0, -GRAVITY])
    p_r = plan[r, :3, 3]
    if kind == "catch":
        c = int(np.flatnonzero(times >= script.flight[2] - 1e-9)[0])
        span = times[c] - times[r]
        v0 = (plan[c, :3, 3] - p_r) / span - 0.5 * acc * span
        sel = np.arange(r + 1, c)
        dt = times[sel] - times[r]
        out[sel, :3, 3] = p_r + dt[:, None] * v0 + 0.5 * dt[:, None] ** 2 * acc
        w = dt / span
        R_r, R_c = Rotation.from_matrix(plan[r, :3, :3]), Rotation.from_matrix(plan[c, :3, :3])
        spin = Rotation.from_rotvec(np.outer(2 * np.pi * script.flight_turns * w, [1.0, 0.0, 0.0]))
        out[sel, :3, :3] = (R_r * Rotation.from_rotvec((R_r.inv() * R_c).as_rotvec() * w[:, None]) * spin).as_matrix()
        return out, ((int(sel[0]), int(sel[-1])) if len(sel) else None)
    if kind != "drop":
        raise ValueError(f"script {script.name}: unknown flight kind {kind!r}")
    landing = times[r] + np.sqrt(2 * max(p_r[2] - half_height, 0.0) / GRAVITY)
    sel = np.flatnonzero(times > times[r] + 1e-9)
    dt = np.minimum(times[sel], landing) - times[r]
    out[sel, :3, :3] = plan[r, :3, :3]
    out[sel, :3, 3] = p_r + 0.5 * dt[:, None] ** 2 * acc
    out[sel[times[sel] >= landing], 2, 3] = half_height  # lies flat on the floor (no rounding below it)
    falling = sel[times[sel] < landing]
    return out, ((int(falling[0]), int(falling[-1])) if len(falling) else None)


# ----------------------------------------------------------------------------- hands
@dataclass
class HandGeometry:
    """Vertex ids of one hand (rest mesh): a palm-skin patch, the palm and back
    (skinned to wrist/metacarpals) and the five fingers (thumb .. little)."""

    palm_patch: torch.Tensor
    hand: torch.Tensor
    fingers: list

    @property
    def whole(self) -> torch.Tensor:
        return torch.cat([self.hand] + list(self.fingers))


def hand_vertices(geom: dict) -> tuple[torch.Tensor, dict]:
    """The vertex ids the hand solvers read (both hands' palm patches, palms and fingers) and `geom`
    re-indexed into them: `model.sparse_forward` skins those alone, where the full 13,718-vertex
    forward was most of an IK step's cost."""
    ids = torch.unique(torch.cat([torch.cat([g.palm_patch, g.whole]) for g in geom.values()]))
    lookup = torch.full((int(ids.max()) + 1,), -1, dtype=torch.long)
    lookup[ids] = torch.arange(len(ids))
    local = {side: HandGeometry(lookup[g.palm_patch], lookup[g.hand], [lookup[f] for f in g.fingers])
             for side, g in geom.items()}
    return ids, local


def dominant_bones(model) -> np.ndarray:
    """(V,) index into model.joint_names of the bone with the largest skinning weight (anny core)."""
    core = model.core
    ids = core.vertex_bone_indices.long().cpu().numpy()
    w = core.vertex_bone_weights.float().cpu().numpy()
    return ids[np.arange(len(ids)), w.argmax(1)]


def hand_geometry(model, rest_vertices: np.ndarray, rest_keypoints: np.ndarray, radius: float = 0.03) -> dict:
    """Per side ('L', 'R') the HandGeometry of the rest mesh."""
    dominant = dominant_bones(model)
    names = np.array(model.joint_names)[dominant]
    out = {}
    for side, region in (("L", "left_hand"), ("R", "right_hand")):
        o = HAND_OFFSET[side]
        wrist, index1, little1 = rest_keypoints[o], rest_keypoints[o + 5], rest_keypoints[o + 17]
        centre = wrist + 0.55 * ((index1 + little1) / 2 - wrist)
        ids = model.contact_regions[region].cpu().numpy()
        patch = ids[np.linalg.norm(rest_vertices[ids] - centre, axis=1) < radius]
        hand = np.flatnonzero((names == f"wrist.{side}") | np.char.startswith(names, "metacarpal") & np.char.endswith(names, f".{side}"))
        fingers = [np.flatnonzero(np.char.startswith(names, prefix + "-") & np.char.endswith(names, f".{side}"))
                   for prefix in FINGER_BONE_PREFIX]
        # the wrist bone also skins the forearm's end: keep what lies beyond the wrist joint
        along = (rest_vertices[hand] - wrist) @ ((index1 + little1) / 2 - wrist)
        hand = hand[along > 0]
        out[side] = HandGeometry(torch.as_tensor(patch), torch.as_tensor(hand), [torch.as_tensor(f) for f in fingers])
    return out


def palm_frames(keypoints: torch.Tensor, vertices: torch.Tensor, geom: HandGeometry, side: str):
    """Palm centre (B, 3), outward palm normal (B, 3), finger direction (B, 3) of one hand.

    The centre is the mean of a patch of palm-skin vertices; the directions come
    from the wrist and the index and little knuckles (rigid with the palm)."""
    o = HAND_OFFSET[side]
    wrist, index1, little1 = keypoints[:, o], keypoints[:, o + 5], keypoints[:, o + 17]
    d = (index1 + little1) / 2 - wrist
    lateral = index1 - little1
    n = torch.linalg.cross(lateral, d) if side == "R" else torch.linalg.cross(d, lateral)
    n = n / n.norm(dim=-1, keepdim=True)
    d = d / d.norm(dim=-1, keepdim=True)
    centre = vertices[:, geom.palm_patch].mean(1)
    return centre, n, d


def grasp_targets(script: Script, spec: ObjectSpec, obj_poses: np.ndarray, gap: np.ndarray) -> dict:
    """Per hand side: target palm centre (T, 3), palm normal (T, 3), finger direction (T, 3), world.

    The palm centre sits `gap` metres (plus 2 mm of skin clearance) out along
    the surface normal; the palm faces the surface."""
    out = {}
    for hand in script.hands:
        g = spec.grasps[hand]
        R, t = obj_poses[:, :3, :3], obj_poses[:, :3, 3]
        normal = R @ np.asarray(g.normal, float)
        point = (R @ np.asarray(g.point, float)) + t + normal * (0.002 + gap[:, None])
        fdir = np.asarray(g.finger_dir, float)
        out[SIDES[hand]] = (point, -normal, R @ (fdir / np.linalg.norm(fdir)))
    return out


def to_object_frame(points: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """World points (B, N, 3) -> object coordinates with object->world poses (B, 4, 4)."""
    return (points - poses[:, None, :3, 3]) @ poses[:, :3, :3]


def penetration(sdf, points_obj: torch.Tensor, margin: float) -> torch.Tensor:
    """(B,) sum over points of how far each is inside the surface grown by `margin`, squared."""
    return (torch.relu(margin - sdf(points_obj)) ** 2).sum(-1)


def below_floor(points: torch.Tensor, margin: float = 0.003) -> torch.Tensor:
    """(B,) sum of squared depths of points (B, N, 3) below the floor z = margin, over (2 mm)^2."""
    return (torch.relu(margin - points[..., 2]) ** 2).sum(-1) / 0.002**2


@dataclass
class LevelSurfaces:
    """Level rectangles (table tops) the hands stay above, as `below_floor` keeps them above the floor:
    per surface the pose of its top's centre in the world (z up) and the top's half sizes."""

    top_poses: torch.Tensor  # (S, 4, 4) top centre -> world
    half_sizes: torch.Tensor  # (S, 2) along the top's x and y

    @classmethod
    def of_props(cls, props: list, names: tuple) -> LevelSurfaces | None:
        """The tops of the props (name, mesh centred on its bounding box, world pose) named in `names`."""
        poses, halves = [], []
        for name, mesh, pose in props:
            if name in names:
                top = np.eye(4)
                top[2, 3] = mesh.bounds[1, 2]
                poses.append(pose @ top)
                halves.append(np.asarray(mesh.bounds[1, :2]))
        if not poses:
            return None
        return cls(torch.as_tensor(np.stack(poses), dtype=torch.float32),
                   torch.as_tensor(np.stack(halves), dtype=torch.float32))

    def below(self, points: torch.Tensor, margin: float = 0.003, reach: float = 0.15) -> torch.Tensor:
        """(B,) sum of squared depths of points (B, N, 3) below a top (+ margin), over (2 mm)^2, counting
        the points over a top's rectangle and less than `reach` below it."""
        poses = self.top_poses.to(points.dtype)
        local = torch.einsum("bnk,skj->bnsj", points, poses[:, :3, :3]) - torch.einsum(
            "sk,skj->sj", poses[:, :3, 3], poses[:, :3, :3])  # (B, N, S, 3) in each top's frame
        over = (local[..., :2].abs() < self.half_sizes.to(points.dtype)).all(-1) & (local[..., 2] > -reach)
        depth = torch.relu(margin - local[..., 2]) * over
        return (depth**2).sum((-1, -2)) / 0.002**2


def run_lbfgs(variables: list, loss_fn, iters: int) -> None:
    opt = torch.optim.LBFGS(variables, lr=1.0, max_iter=iters, history_size=50, line_search_fn="strong_wolfe",
                            tolerance_change=1e-10, tolerance_grad=1e-9)

    def closure():
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    opt.step(closure)


def solve_arm_ik(model, params, targets: dict, weight: np.ndarray, geom: dict, sdf, obj_poses: np.ndarray,
                 iters: int = 40, prior_pose: torch.Tensor | None = None, retries: int = 2,
                 surfaces: LevelSurfaces | None = None) -> torch.Tensor:
    """Bend spine and arms so the palms meet their targets, at frames where `weight` > 0.

    Minimises, per frame, with L-BFGS:
      w * sum_hands [ |c - c*|^2 / (1 cm)^2 + 10 (1 - n.n*) + 10 (1 - d.d*)
                      + |palm and back of hand inside the object|^2 / (2 mm)^2 ]
      + sum_bones lambda_b |theta_b - theta_b^script|^2  (+ the hands below `surfaces`' tops, if any)
    theta^script is `prior_pose` (T, Jb, 3) when given, else params.body_pose (the start).
    One L-BFGS over all frames can leave a few frames behind (a shared line
    search): frames whose palm is still > 4 mm off are solved again on their own
    (`retries` times). Returns the updated body_pose (T, Jb, 3)."""
    frames = np.flatnonzero(weight > 1e-3)
    body_pose = params.body_pose.detach().clone()
    if len(frames) == 0:
        return body_pose
    sub = params[torch.as_tensor(frames)].detach()
    bones = [b for b in IK_BONES if b in model.body_joint_names]
    ids = torch.tensor([model.body_joint_names.index(b) for b in bones])
    dtype = sub.body_pose.dtype
    lam = torch.tensor([IK_BONES[b] for b in bones], dtype=dtype)
    var = sub.body_pose[:, ids].clone().requires_grad_(True)
    prior = params.body_pose if prior_pose is None else prior_pose
    base = prior[torch.as_tensor(frames)][:, ids].detach().clone()
    w = torch.as_tensor(weight[frames], dtype=dtype)
    poses = torch.as_tensor(obj_poses[frames], dtype=dtype)
    tgt = {s: [torch.as_tensor(a[frames], dtype=dtype) for a in v] for s, v in targets.items()}
    fixed_pose = sub.body_pose.detach()
    vertex_ids, hands = hand_vertices(geom)
    rest = model.rest_state(sub, vertex_ids)

    def posed(pose):
        return model.sparse_forward(dataclasses.replace(sub, body_pose=fixed_pose.index_copy(1, ids, pose)), vertex_ids, rest)

    def loss_fn():
        out = posed(var)
        loss = (lam[None, :, None] * (var - base) ** 2).sum()
        for side, (c_t, n_t, d_t) in tgt.items():
            c, n, d = palm_frames(out.keypoints, out.vertices, hands[side], side)
            err = ((c - c_t) ** 2).sum(-1) / 0.01**2 + 10 * (1 - (n * n_t).sum(-1)) + 10 * (1 - (d * d_t).sum(-1))
            hand = out.vertices[:, hands[side].hand]
            inside = penetration(sdf, to_object_frame(hand, poses), 0.0) / 0.002**2
            inside = inside + below_floor(out.vertices[:, hands[side].whole])
            loss = loss + (w * (err + inside)).sum()
            if surfaces is not None:  # full weight in every frame solved, also while the hand comes near;
                # 12 mm clear, for the IK sees the fingers relaxed and they stretch open as the hand nears
                loss = loss + surfaces.below(out.vertices[:, hands[side].whole], margin=0.012).sum()
        return loss

    run_lbfgs([var], loss_fn, iters)
    body_pose[torch.as_tensor(frames)[:, None], ids[None]] = var.detach()
    if retries <= 0:
        return body_pose
    with torch.no_grad():
        out = posed(var)
        error = torch.zeros(len(frames), dtype=dtype)
        for side, (c_t, _, _) in tgt.items():
            c, _, _ = palm_frames(out.keypoints, out.vertices, hands[side], side)
            error = torch.maximum(error, (c - c_t).norm(dim=-1))
    bad = frames[((error > 0.004) & (w > 0.5)).numpy()]
    if len(bad) == 0:
        return body_pose
    again = np.zeros_like(weight)
    again[bad] = weight[bad]
    return solve_arm_ik(model, dataclasses.replace(params, body_pose=body_pose), targets, again, geom, sdf, obj_poses,
                        iters=iters, prior_pose=prior if prior_pose is None else prior_pose, retries=retries - 1,
                        surfaces=surfaces)


def finger_bone_ids(model, finger: int) -> list[int]:
    """Hand-pose indices of one finger's three phalanges (0 thumb .. 4 little)."""
    prefix = FINGER_BONE_PREFIX[finger]
    return [i for i, n in enumerate(model.hand_joint_names) if n.startswith(prefix + "-")]


def finger_pose(model, side: str, curls: torch.Tensor, thumb: torch.Tensor | None = None) -> torch.Tensor:
    """(B, Jh, 3) hand pose curling each finger by its own amount.

    curls (B, 5) radians per joint (thumb scaled by 0.6); thumb (B, 3) an extra
    rotation of the thumb's first bone (composed by adding axis-angles: small)."""
    axes = getattr(model, f"finger_flex_axes_{side}")  # (Jh, 3)
    scale = torch.zeros(len(model.hand_joint_names), 5, dtype=axes.dtype)
    for f in range(5):
        for j in finger_bone_ids(model, f):
            scale[j, f] = 0.6 if f == 0 else 1.0
    pose = (curls.to(axes.dtype) @ scale.T)[..., None] * axes[None]  # (B, Jh, 3)
    if thumb is not None:
        first = finger_bone_ids(model, 0)[0]
        pose = pose.index_add(1, torch.tensor([first]), thumb[:, None].to(axes.dtype))
    return pose


def solve_finger_grasp(model, params, frames: np.ndarray, geom: dict, sides: list, sdf, obj_poses: np.ndarray,
                       relaxed: float, iters: int = 40, init: dict | None = None,
                       surfaces: LevelSurfaces | None = None) -> dict:
    """Close the fingers onto the object at `frames` (contact frames).

    Per side, variables: a curl per finger (F, 5) and a thumb-base rotation (F, 3).
    Minimises  |hand inside the object|^2 / (2 mm)^2 + sum_fingers (gap of the
    finger's closest point)^2 / (4 mm)^2 + small priors, + temporal smoothness.
    Returns side -> (curls (F, 5), thumb (F, 3)) tensors."""
    sub = params[torch.as_tensor(frames)].detach()
    dtype = sub.body_pose.dtype
    poses = torch.as_tensor(obj_poses[frames], dtype=dtype)
    F_ = len(frames)
    if init is None:
        init = {s: (torch.full((F_, 5), relaxed, dtype=dtype), torch.zeros(F_, 3, dtype=dtype)) for s in sides}
    curls = {s: init[s][0].clone().to(dtype).requires_grad_(True) for s in sides}
    thumbs = {s: init[s][1].clone().to(dtype).requires_grad_(True) for s in sides}
    vertex_ids, local = hand_vertices(geom)
    rest = model.rest_state(sub, vertex_ids)

    def loss_fn():
        hands = {s: finger_pose(model, s, curls[s], thumbs[s]) for s in sides}
        out = model.sparse_forward(dataclasses.replace(sub, left_hand_pose=hands.get("L", sub.left_hand_pose),
                                                       right_hand_pose=hands.get("R", sub.right_hand_pose)), vertex_ids, rest)
        loss = 0.0
        for s in sides:
            g = local[s]
            loss = loss + penetration(sdf, to_object_frame(out.vertices[:, g.hand], poses), 0.001).sum() / 0.002**2
            loss = loss + below_floor(out.vertices[:, g.whole]).sum()
            if surfaces is not None:
                loss = loss + surfaces.below(out.vertices[:, g.whole]).sum()
            for f, ids in enumerate(g.fingers):
                d = sdf(to_object_frame(out.vertices[:, ids], poses))  # (F, n)
                loss = loss + (torch.relu(0.001 - d) ** 2).sum() / 0.002**2
                loss = loss + (torch.relu(d.min(1).values - 0.002) ** 2).sum() / 0.004**2
            c = curls[s]
            loss = loss + 0.5 * ((c - relaxed) ** 2).sum() + 2.0 * (thumbs[s] ** 2).sum()
            loss = loss + 10.0 * (torch.relu(c - 1.6) ** 2 + torch.relu(-0.3 - c) ** 2).sum()
            if F_ > 1:
                loss = loss + 20.0 * ((c[1:] - c[:-1]) ** 2).sum() + 20.0 * ((thumbs[s][1:] - thumbs[s][:-1]) ** 2).sum()
        return loss

    run_lbfgs(list(curls.values()) + list(thumbs.values()), loss_fn, iters)
    return {s: (curls[s].detach(), thumbs[s].detach()) for s in sides}


def coarse_subset(frames: np.ndarray, times: np.ndarray, rate_hz: float) -> np.ndarray:
    """A subset of `frames` at most ~1/rate_hz seconds apart, keeping the first and last."""
    if len(frames) == 0:
        return frames
    keep, last = [frames[0]], times[frames[0]]
    for f in frames[1:-1]:
        if times[f] - last >= 1.0 / rate_hz - 1e-9:
            keep.append(f)
            last = times[f]
    if frames[-1] != keep[-1]:
        keep.append(frames[-1])
    return np.array(keep)


def interpolate_corrections(base: torch.Tensor, solved: torch.Tensor, solved_frames: np.ndarray) -> torch.Tensor:
    """Spread per-bone rotation corrections solved at some frames over all frames.

    base (T, J, 3) scripted axis-angles; solved (S, J, 3) at `solved_frames`.
    The correction R_base^-1 R_solved is slerped between solved frames and held
    constant outside them; returns base composed with it, (T, J, 3)."""
    T, J, _ = base.shape
    b = Rotation.from_rotvec(base.double().numpy().reshape(-1, 3))
    b_s = Rotation.from_rotvec(base[solved_frames].double().numpy().reshape(-1, 3))
    corr = (b_s.inv() * Rotation.from_rotvec(solved.double().numpy().reshape(-1, 3))).as_rotvec().reshape(len(solved_frames), J, 3)
    frames = np.arange(T)
    if len(solved_frames) == 1:
        spread = np.broadcast_to(corr, (T, J, 3))
    else:
        spread = np.empty((T, J, 3))
        for j in range(J):
            slerp = Slerp(solved_frames.astype(float), Rotation.from_rotvec(corr[:, j]))
            spread[:, j] = slerp(np.clip(frames, solved_frames[0], solved_frames[-1]).astype(float)).as_rotvec()
    out = (b * Rotation.from_rotvec(spread.reshape(-1, 3))).as_rotvec().reshape(T, J, 3)
    return torch.as_tensor(out, dtype=base.dtype)


def coarse_to_fine_ik(model, params, targets, weight, geom, sdf, obj_poses, times, rate_hz, iters, polish_iters,
                      surfaces=None):
    """Arm IK solved at <= rate_hz, spread to all frames, then polished at every frame (hands above the
    floor and `surfaces`)."""
    active = np.flatnonzero(weight > 1e-3)
    coarse = coarse_subset(active, times, rate_hz)
    if len(coarse) == len(active):
        return solve_arm_ik(model, params, targets, weight, geom, sdf, obj_poses, iters=iters, surfaces=surfaces)
    mask = np.zeros(len(times), bool)
    mask[coarse] = True
    solved = solve_arm_ik(model, params, targets, np.where(mask, weight, 0.0), geom, sdf, obj_poses, iters=iters,
                          surfaces=surfaces)
    # anchor the spread at the frames just outside the active range (no correction there)
    anchors = np.unique(np.concatenate([coarse, np.clip([active[0] - 1, active[-1] + 1], 0, len(times) - 1)]))
    start = interpolate_corrections(params.body_pose.detach(), solved[anchors], anchors)
    warm = dataclasses.replace(params, body_pose=start)
    return solve_arm_ik(model, warm, targets, weight, geom, sdf, obj_poses, iters=polish_iters,
                        prior_pose=params.body_pose, surfaces=surfaces)


def coarse_to_fine_grip(model, params, frames, geom, sides, sdf, obj_poses, times, relaxed, rate_hz, iters,
                        polish_iters, surfaces=None) -> dict:
    """Finger grip solved at <= rate_hz among the contact frames, interpolated, then polished."""
    coarse = coarse_subset(frames, times, rate_hz)
    grip = solve_finger_grasp(model, params, coarse, geom, sides, sdf, obj_poses, relaxed, iters=iters,
                              surfaces=surfaces)
    if len(coarse) == len(frames):
        return grip
    if polish_iters <= 0:
        out = {}
        for s in sides:
            c, t = (g.numpy() for g in grip[s])
            ci = np.stack([np.interp(frames, coarse, c[:, k]) for k in range(5)], 1)
            ti = np.stack([np.interp(frames, coarse, t[:, k]) for k in range(3)], 1)
            out[s] = (torch.as_tensor(ci, dtype=grip[s][0].dtype), torch.as_tensor(ti, dtype=grip[s][0].dtype))
        return out
    init = {}
    for s in sides:
        c, t = (g.numpy() for g in grip[s])
        ci = np.stack([np.interp(frames, coarse, c[:, k]) for k in range(5)], 1)
        ti = np.stack([np.interp(frames, coarse, t[:, k]) for k in range(3)], 1)
        init[s] = (torch.as_tensor(ci), torch.as_tensor(ti))
    return solve_finger_grasp(model, params, frames, geom, sides, sdf, obj_poses, relaxed, iters=polish_iters,
                              init=init, surfaces=surfaces)


# ----------------------------------------------------------------------------- all together
@dataclass
class Animation:
    """What `animate` produces; world frame, metres, T frames."""

    params: object  # BodyParams (T, ...)
    vertices: np.ndarray  # (T, V, 3) float32
    keypoints: np.ndarray  # (T, 67, 3) float32
    object_poses: np.ndarray | None  # (T, 4, 4) object -> world; None: the person alone
    contact: np.ndarray  # (T,) bool
    props: list  # (name, mesh, 4x4 world pose) static scene meshes
    phases: dict  # phase -> (first frame, last frame)
    hand_gap: dict  # measured hand-to-object distances in contact frames
    hand_distance: np.ndarray | None = None  # (T,) closest grasping-hand vertex to the object surface, metres
    timings: dict = field(default_factory=dict)  # seconds per stage
    flight: tuple | None = None  # (first, last) frame of the object's free flight, inclusive


def hand_object_gap(vertices: np.ndarray, geom: dict, spec: ObjectSpec, obj_poses: np.ndarray, contact: np.ndarray,
                    hands: tuple) -> dict:
    """Per grasping hand over contact frames, metres: the gap between the palm
    patch and the surface (closest palm vertex, 0 when touching), and the
    deepest point of the whole hand (palm and fingers) inside the object."""
    out = {}
    frames = np.flatnonzero(contact)
    if not frames.size:
        return out
    sdf = SurfaceDistance(spec.mesh)
    for hand in hands:
        g = geom[SIDES[hand]]
        whole = g.whole.numpy()
        gaps, pens = [], []
        for f in frames:
            R, t = obj_poses[f, :3, :3], obj_poses[f, :3, 3]
            gaps.append(max(0.0, sdf((vertices[f, g.palm_patch.numpy()] - t) @ R).min()))
            pens.append(max(0.0, -sdf((vertices[f, whole] - t) @ R).min()))
        out[hand] = {"palm_gap_mean_m": float(np.mean(gaps)), "palm_gap_max_m": float(np.max(gaps)),
                     "penetration_max_m": float(np.max(pens)), "penetration_mean_m": float(np.mean(pens))}
    return out


def scripted_pose(model, script: Script, times: np.ndarray, shape: torch.Tensor, relaxed_curl: float):
    """BodyParams (T, ...) of the scripted posture and gait, identity orientation, zero translation."""
    params = model.init_params(len(times))
    params.shape[:] = shape
    names = model.body_joint_names
    pitch = eased_scalar(script.pitch_keys, times)
    gait, lifts = gait_rotvecs(script, names, times)
    posture = posture_rotvecs(script, names, times)
    # thigh angles are measured from the vertical, whatever the pelvis pitch (a forward lean flexes
    # the hips); while walking the legs follow the gait, sweeping about the vertical (else one foot
    # lands early and the stance switch jerks the body); standing, the posture
    walking = np.clip(gait_cycles(script, times)[1] / 0.3, 0.0, 1.0)
    for side in ("L", "R"):
        for bone in (f"upperleg01.{side}", f"lowerleg01.{side}"):
            posture[:, names.index(bone)] *= (1.0 - walking)[:, None]
        posture[:, names.index(f"upperleg01.{side}"), 0] -= pitch
    pose = flat_feet(compose_rotvecs(posture, gait), names, pitch, lifts)
    params.body_pose = torch.as_tensor(pose, dtype=params.body_pose.dtype)
    for side in ("L", "R"):
        model.curl_fingers(params, side, relaxed_curl)
    return params


def root_path(model, script: Script, times: np.ndarray, shape: torch.Tensor, heading0: float, relaxed_curl: float,
              rate_hz: float = 30.0) -> np.ndarray:
    """(T, 2) root xy at `times`, integrated from the stance foot on a fine time grid
    (>= rate_hz, so coarse frame rates still walk like the real thing)."""
    end = float(times.max())
    fine = np.union1d(np.linspace(0.0, end, max(2, int(np.ceil(end * rate_hz)) + 1)), times)
    with torch.no_grad():
        v_model = model(scripted_pose(model, script, fine, shape, relaxed_curl)).vertices.numpy()
    yaw = eased_scalar(script.yaw_keys, fine)
    pitch = eased_scalar(script.pitch_keys, fine)
    R = body_orientation(model, heading_frames(yaw, np.zeros((len(fine), 2)), heading0), pitch)  # (F, 3, 3)
    feet = {}
    for side in ("left", "right"):
        ids = model.contact_regions[f"{side}_foot"].cpu().numpy()
        feet[side] = np.einsum("tij,tj->ti", R, v_model[:, ids].mean(1))
    xy = stance_anchored_root(feet["left"], feet["right"], left_stance_weight(script, fine))
    return np.stack([np.interp(times, fine, xy[:, k]) for k in range(2)], 1)


def hand_object_distance(vertices: np.ndarray, geom: dict, spec: ObjectSpec, obj_poses: np.ndarray,
                         hands: tuple) -> np.ndarray:
    """(T,) per frame, the smallest signed distance (m, < 0 inside) from the
    grasping hands' vertices to the object surface: a contact check by geometry."""
    sdf = SurfaceDistance(spec.mesh)
    ids = np.concatenate([geom[SIDES[h]].whole.numpy() for h in hands])
    local = np.einsum("tvj,tjk->tvk", vertices[:, ids] - obj_poses[:, None, :3, 3], obj_poses[:, :3, :3])
    return sdf(local.reshape(-1, 3)).reshape(len(vertices), -1).min(1)


def phase_frame_ranges(script: Script, times: np.ndarray) -> dict:
    """Phase -> (first frame, last frame) of the frames at `times` within it (phases without a frame left out)."""
    out = {}
    for name, (a, b) in script.phases.items():
        sel = np.flatnonzero((times >= a) & (times < b))
        if sel.size:
            out[name] = (int(sel[0]), int(sel[-1]))
    return out


def place_body(model, script: Script, params, times: np.ndarray, heading0: float, relaxed_curl: float):
    """Steps 1-2: set params' global orientation (heading, pelvis pitch) and translation (the root on
    the stance foot, the lowest vertex on the floor) in place. Returns the model-coordinate output
    (identity orientation), the heading frames (T, 4, 4), the body rotations (T, 3, 3) and transl (T, 3)."""
    yaw = eased_scalar(script.yaw_keys, times)
    pitch = eased_scalar(script.pitch_keys, times)
    with torch.no_grad():
        local = model(params)  # identity orientation, zero translation: model coordinates
    v_model = local.vertices.numpy()
    root_xy = root_path(model, script, times, params.shape[:1], heading0, relaxed_curl)
    heading = heading_frames(yaw, root_xy, heading0)
    R = body_orientation(model, heading, pitch)
    lowest = np.einsum("tij,tvj->tv", R[:, 2:3], v_model).min(1)  # (T,) height of the lowest vertex
    transl = np.concatenate([root_xy, -lowest[:, None]], axis=1)
    params.global_orient = torch.as_tensor(Rotation.from_matrix(R).as_rotvec(), dtype=params.transl.dtype)
    params.transl = torch.as_tensor(transl, dtype=params.transl.dtype)
    return local, heading, R, transl


SEAT_BONES = ("pelvis", "upperleg01", "upperleg02", "spine05")  # what sits on a seat


def seat_prop(model, script: Script, shape: torch.Tensor, heading0: float, relaxed_curl: float):
    """The script's seat (`Script.seat`) as a static prop (kind, mesh, world pose): the body is posed and
    placed at the seat's time alone; the stool stands square to the heading, centred under the hip
    joints, its height (the mesh stretched along z) meeting the lowest buttock or thigh vertex over it."""
    kind, t = script.seat
    if kind != "stool":
        raise ValueError(f"script {script.name}: a seat must be a stool, got {kind!r}")
    times = np.array([float(t)])
    params = scripted_pose(model, script, times, shape, relaxed_curl)
    _, heading, _, _ = place_body(model, script, params, times, heading0, relaxed_curl)
    with torch.no_grad():
        out = model(params)
    vertices, joints = out.vertices[0].numpy().astype(np.float64), out.joints[0].numpy().astype(np.float64)
    names = np.array(model.joint_names)
    hips = joints[[model.joint_names.index(f"upperleg01.{s}") for s in ("L", "R")]].mean(0)
    axes = heading[0, :3, :3]  # columns: right, forward, up
    local = (vertices[:, :2] - hips[:2]) @ axes[:2, :2]  # (V, 2) right and forward of the hips
    over = (np.abs(local) < np.asarray(STOOL_SIZE[:2]) / 2).all(1)
    bones = names[dominant_bones(model)]
    sitting = np.any([np.char.startswith(bones, b) for b in SEAT_BONES], axis=0)
    height = float(vertices[over & sitting, 2].min())
    if height < 0.2:
        raise ValueError(f"script {script.name}: the seated body is {height:.2f} m above the floor; no stool fits")
    pose = np.eye(4)
    pose[:3, :3] = axes
    pose[:3, 3] = (hips[0], hips[1], height / 2)
    return kind, _stool_mesh(size=(STOOL_SIZE[0], STOOL_SIZE[1], height)), pose


def animate(model, script: Script, spec: ObjectSpec | None, times: np.ndarray, phenotype, heading0: float = 0.0,
            ik_iters: int = 100, polish_iters: int = 20, solve_rate_hz: float = 5.0, finger_iters: int = 60,
            grip_rate_hz: float = 3.0, relaxed_curl: float = 0.25) -> Animation:
    """Run the script on the body model at `times` (seconds of script time).

    The arm IK is solved at <= `solve_rate_hz` with `ik_iters` L-BFGS
    iterations, then polished at every frame (`polish_iters`); the finger grip
    (nearly constant while the hand holds the object) at <= `grip_rate_hz`,
    interpolated in between. With `spec` None the person is alone (a script
    without hands on an object, `without_object`): no object track, no IK, no
    contact; the Animation's object_poses and hand_distance are None."""
    if spec is None:
        if script.holds_object:
            raise ValueError(f"script {script.name} handles an object; without one use without_object(script)")
    elif not script.holds_object:
        raise ValueError(f"script {script.name} is of the person alone: it takes no object (object {NO_OBJECT!r})")
    missing = [h for h in script.hands if spec is not None and h not in spec.grasps]
    if missing:
        raise ValueError(f"script {script.name} holds the object with the {' and '.join(script.hands)} hand(s), "
                         f"but object {spec.name!r} has no grasp for the {' and '.join(missing)} hand")
    clock = {"start": time.perf_counter()}
    T = len(times)
    shape = torch.as_tensor(phenotype, dtype=model.dtype)[None]
    params = scripted_pose(model, script, times, shape, relaxed_curl)

    rest_params = model.init_params(1)
    rest_params.shape[:] = params.shape[:1]
    with torch.no_grad():
        rest = model(rest_params)
    rest_v, rest_k = rest.vertices[0].numpy(), rest.keypoints[0].numpy()
    geom = hand_geometry(model, rest_v, rest_k)

    # 1-2: body placement: heading, pitch, stance-anchored root, feet on the floor.
    local, heading, R, transl = place_body(model, script, params, times, heading0, relaxed_curl)
    props = [(name, mesh, heading[0] @ rel) for name, mesh, rel in prop_meshes(script)]
    if script.seat is not None:
        props.append(seat_prop(model, script, params.shape[:1], heading0, relaxed_curl))
    if spec is None:
        clock["placement"] = time.perf_counter()
        with torch.no_grad():
            out = model(params)
        clock["end"] = time.perf_counter()
        names = list(clock)
        return Animation(params.detach(), out.vertices.numpy().astype(np.float32),
                         out.keypoints.numpy().astype(np.float32), None, np.zeros(T, bool), props,
                         phase_frame_ranges(script, times), {}, None,
                         {b: clock[b] - clock[a] for a, b in zip(names[:-1], names[1:])})

    # 3: object track; 4: arms to the grasp points.
    stature = float(np.ptp(rest_v @ np.asarray(model.up_axis, float)))
    head = heading.copy()
    head[:, :3, 3] = np.einsum("tij,tj->ti", R, local.keypoints[:, 0].numpy()) + transl  # the nose, scripted pose
    obj_poses = object_track(script, {"body": heading, "head": head}, times, scale=stature / 1.625,
                             half_height=spec.half_height)
    plan, flight = obj_poses, None
    if script.flight is not None:  # the hands keep to the plan; the object flies
        obj_poses, flight = flight_track(script, plan, times, spec.half_height)
    sdf = SdfGrid(spec.mesh, max_cells=spec.sdf_cells)
    reach = eased_scalar(script.reach_keys, times)
    gap = eased_scalar(script.gap_keys, times)
    targets = grasp_targets(script, spec, plan, gap)
    surfaces = LevelSurfaces.of_props(props, script.hands_above)
    clock["placement"] = time.perf_counter()
    params.body_pose = coarse_to_fine_ik(model, params, targets, reach, geom, sdf, obj_poses, times, solve_rate_hz,
                                         ik_iters, polish_iters, surfaces)

    clock["arm_ik"] = time.perf_counter()
    # 5: fingers close onto the object during contact, open (relaxed) otherwise.
    c0, c1 = contact_interval(script)
    contact = (times >= c0) & (times < c1)
    if flight is not None:
        contact[flight[0]:flight[1] + 1] = False
    closure = eased_scalar(script.close_keys, times)
    sides = [SIDES[h] for h in script.hands]
    frames = np.flatnonzero(contact)
    if frames.size:
        grip = coarse_to_fine_grip(model, params, frames, geom, sides, sdf, obj_poses, times, relaxed_curl,
                                   grip_rate_hz, finger_iters, polish_iters, surfaces)
        dtype = params.transl.dtype
        k_reach = torch.as_tensor(reach, dtype=dtype)[:, None]
        k_close = torch.as_tensor(closure, dtype=dtype)[:, None]
        first, last = frames[0], frames[-1]
        for s in sides:
            # the grip shape per frame: solved in contact, held before and after
            curls = torch.empty(T, 5, dtype=dtype)
            thumb = torch.empty(T, 3, dtype=dtype)
            curls[torch.as_tensor(frames)], thumb[torch.as_tensor(frames)] = grip[s]
            curls[:first], thumb[:first] = grip[s][0][0], grip[s][1][0]
            curls[last + 1:], thumb[last + 1:] = grip[s][0][-1], grip[s][1][-1]
            unheld = np.setdiff1d(np.arange(first, last + 1), frames)
            if unheld.size:  # free flight between two holds: the grip of the frame before it
                before = torch.as_tensor(frames[np.searchsorted(frames, unheld) - 1])
                curls[torch.as_tensor(unheld)], thumb[torch.as_tensor(unheld)] = curls[before], thumb[before]
            # relaxed -> open (fingers stretched, as the hand nears) -> grip (as it closes)
            opened = torch.clamp(curls.min(0).values, max=0.0) - 0.1  # (5,)
            shape = relaxed_curl + k_reach * (opened - relaxed_curl) + k_close * (curls - opened)
            hand = finger_pose(model, s, shape, k_reach * thumb)
            if s == "L":
                params.left_hand_pose = hand
            else:
                params.right_hand_pose = hand

    clock["fingers"] = time.perf_counter()
    with torch.no_grad():
        out = model(params)
    vertices = out.vertices.numpy().astype(np.float32)
    keypoints = out.keypoints.numpy().astype(np.float32)
    phase_frames = phase_frame_ranges(script, times)
    gaps = hand_object_gap(vertices, geom, spec, obj_poses, contact, script.hands)
    distance = hand_object_distance(vertices, geom, spec, obj_poses, script.hands)
    clock["end"] = time.perf_counter()
    names = list(clock)
    timings = {b: clock[b] - clock[a] for a, b in zip(names[:-1], names[1:])}
    return Animation(params.detach(), vertices, keypoints, obj_poses, contact, props, phase_frames, gaps, distance,
                     timings, flight)
