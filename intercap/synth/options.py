"""The synthetic generator's settings and command line (`intercap synth`, `python -m intercap.synth`).

Kept apart from the generator (intercap/synth/generator.py, which re-exports these names) and free
of its heavy imports (torch, trimesh, cv2, pyrender), so that `--help` and a usage error answer at
once; the script and object names live here for the same reason (motions.py and objects.py take
them from here).
"""
from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass

DESCRIPTION = "Synthetic capture sessions with ground truth."

# `motions.get_script`'s scripts; bend, sit_stand and walk_out are of the person alone
SCRIPT_NAMES = ("pick_place", "lift_drink", "push_chair", "toss", "hold", "drop", "turn", "table_lift", "bend",
                "sit_stand", "walk_out")
# `objects.make_object`'s objects
OBJECT_NAMES = ("box", "cup", "chair", "block", "board", "carton", "flat_box", "tool", "ball")
NO_OBJECT = "none"  # the object "name" of a take of the person alone (no object anywhere)


# ----------------------------------------------------------------------------- configuration
@dataclass
class SynthConfig:
    """Everything that defines a synthetic session (defaults: a full-size session)."""

    # pick_place lift_drink push_chair toss hold drop (physics) turn table_lift; bend sit_stand walk_out (body only)
    script: str = "pick_place"
    object: str | None = None  # `OBJECT_NAMES` or "none" (the person alone); default: the script's own
    frames: int | None = None  # None: the whole script at its natural speed; else resampled to this many
    fps: float = 30.0
    seed: int = 0
    phenotype: tuple = (0.5, 0.5, 0.5, 0.5, 0.5, 0.5)  # anny: gender, age, muscle, weight, height, proportions
    heading_deg: float = 30.0  # walking direction at the start, degrees from +x ...
    heading_jitter_deg: float = 15.0  # ... plus a seed-dependent offset of up to this much
    # cameras
    cameras: int = 4
    width: int = 640
    height: int = 576
    focal_scale: float = 0.8  # fx = fy = focal_scale * width
    ring_radius: float = 3.0
    ring_height: float = 1.6
    ring_offset_deg: float = 45.0  # azimuth of the first camera
    look_at: tuple = (0.0, 0.0, 0.8)
    dist: tuple = (0.05, -0.02, 0.0005, -0.0003, 0.0)  # k1, k2, p1, p2, k3
    camera_jitter: float = 1.0  # scale of small per-camera differences in intrinsics and placement
    # scene and images
    walls: bool = True
    color_format: str = "jpg"  # jpg | png
    jpeg_quality: int = 90
    color_noise: float = 1.5  # sensor noise std, 8-bit levels
    # Kinect-like depth
    depth_sigma_base: float = 0.0015  # metres
    depth_sigma_quad: float = 0.0015  # metres per metre^2: sigma = base + quad * z^2 (15 mm at 3 m; Azure Kinect spec <= 17 mm)
    depth_min: float = 0.25
    depth_max: float = 5.0  # metres; Azure Kinect NFOV binned reaches 5.46
    edge_jump: float = 0.04  # depth step (metres, + 2 % of depth) that counts as a discontinuity
    edge_drop: float = 0.5  # fraction of edge pixels lost
    flying_pixels: float = 0.0  # fraction of the edge pixels that read a mix of the two sides' depths (time of flight)
    dark_threshold: float = 45.0  # luminance (0..255) below which surfaces are dark
    dark_drop: float = 0.4  # fraction of dark pixels lost
    holes: float = 1.5  # mean number of random holes per image
    clean_depth: bool = False  # write noise-free depth (tests, debugging)
    # simulated OpenPose
    keypoints: bool = True
    kp_sigma_body: float = 2.0  # pixels at 640 px width (scaled with the image width)
    kp_sigma_hand: float = 3.0
    occlusion_margin_body: float = 0.10  # metres behind the visible surface => occluded
    occlusion_margin_hand: float = 0.04
    masks: bool = True
    # appearance and lighting (real captures vary: skin tones, clothing, dim or bright rooms)
    appearance: int = 0  # 0: the default outfit; N > 0: a skin tone, hair and clothing colours drawn with seed N
    light: float = 1.0  # scale of the lights' intensities (0.4: a dim room; 1.6: a bright one)
    flight_turns: float = 0.0  # toss: whole turns the object spins in flight (1 = 2 turns/s, 24 degrees a frame at 30 fps)
    # dropped frames
    drop_rate: float = 0.0  # fraction of frames missing in one view
    drop_view: int = -1  # which camera (index) loses them
    # annotations the pipeline should normally find itself
    annotate: bool = False  # also write contact_frames, ground and the object's initial pose
    camera_world: bool = False  # camera 0 is the world (OpenCV axes, y down), as Kinect rigs write it; else z up
    # solver effort
    ik_iters: int = 100
    threads: int = 1  # torch CPU threads for the motion solve (1 is robust on busy machines)
    quiet: bool = False


PRESETS = {
    # The committed sample: 4 cameras, 320x288, 30 frames, well under 15 MB.
    "sample": dict(cameras=4, width=320, height=288, frames=30, fps=5.0, color_format="jpg", jpeg_quality=88),
    # One camera close in, the upper body in view (legs below the image), as at a desk or a close rig.
    "upper1": dict(cameras=1, ring_radius=1.8, ring_height=1.45, look_at=(0.0, 0.0, 1.2), focal_scale=1.0,
                   walls=True),
    # Tiny and fast (tests, smoke runs). 40 IK iterations, not fewer: at 25 the arm IK stopped 5-14 mm
    # short of the grasp, by how the body model's rounding fell (hand gaps 1-10 mm); at 40 it arrives
    # (gaps <= 2 mm) at the same cost.
    "tiny": dict(cameras=2, width=96, height=80, frames=4, fps=5.0, ik_iters=40),
}


def apply_preset(cfg: SynthConfig, name: str | None) -> SynthConfig:
    if not name:
        return cfg
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return dataclasses.replace(cfg, **PRESETS[name])


# ----------------------------------------------------------------------------- command line
def _floats(text: str) -> tuple:
    return tuple(float(x) for x in text.split(","))


def build_arg_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """Add the generator's options (and the OUT argument) to `parser` (a new one if None)."""
    if parser is None:
        parser = argparse.ArgumentParser(prog="python -m intercap.synth", description=DESCRIPTION)
    d = SynthConfig()
    parser.add_argument("out", metavar="OUT", help="session folder to write")
    parser.add_argument("--preset", choices=sorted(PRESETS), help="a named set of defaults (sample: the committed sample session)")
    parser.add_argument("--script", choices=list(SCRIPT_NAMES),
                        default=None, help="toss, hold, drop: known physics (ground_truth/physics.npz); "
                                           "bend, sit_stand, walk_out: the person alone")
    parser.add_argument("--object", choices=list(OBJECT_NAMES) + [NO_OBJECT], default=None,
                        help=f"default: the script's object; {NO_OBJECT}: the person alone "
                             "(the default of bend, sit_stand, walk_out)")
    parser.add_argument("--frames", type=int, default=None, help="number of frames (default: whole script at natural speed)")
    parser.add_argument("--fps", type=float, default=None)
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--phenotype", type=_floats, default=None,
                        help="anny phenotype gender,age,muscle,weight,height,proportions in [0,1]")
    parser.add_argument("--cameras", type=int, default=None)
    parser.add_argument("--width", type=int, default=None)
    parser.add_argument("--height", type=int, default=None)
    parser.add_argument("--focal-scale", type=float, default=None, help=f"fx = focal_scale * width (default {d.focal_scale})")
    parser.add_argument("--ring-radius", type=float, default=None)
    parser.add_argument("--ring-height", type=float, default=None)
    parser.add_argument("--look-at", type=_floats, default=None, help="x,y,z")
    parser.add_argument("--dist", type=_floats, default=None, help="k1,k2,p1,p2,k3")
    parser.add_argument("--color-format", choices=["jpg", "png"], default=None)
    parser.add_argument("--depth-sigma", type=_floats, default=None, help="base,quad: sigma = base + quad * z^2 (metres)")
    parser.add_argument("--clean-depth", action="store_true", default=None, help="write noise-free depth")
    parser.add_argument("--flying-pixels", type=float, default=None,
                        help="fraction of the pixels at depth edges reading a mix of both sides (default 0)")
    parser.add_argument("--no-walls", action="store_true", default=None)
    parser.add_argument("--no-keypoints", action="store_true", default=None)
    parser.add_argument("--no-masks", action="store_true", default=None)
    parser.add_argument("--kp-sigma", type=_floats, default=None, help="body,hand pixel noise at 640 px width")
    parser.add_argument("--appearance", type=int, default=None,
                        help="0: the default outfit; N > 0: skin tone, hair and clothes drawn with seed N")
    parser.add_argument("--light", type=float, default=None, help="scale of the lights (0.4 dim, 1.6 bright)")
    parser.add_argument("--flight-turns", type=float, default=None,
                        help="toss: whole turns the object spins about its own x axis in flight (1 = 2 turns/s)")
    parser.add_argument("--drop-rate", type=float, default=None, help="fraction of frames missing in one view")
    parser.add_argument("--drop-view", type=int, default=None)
    parser.add_argument("--annotate", action="store_true", default=None,
                        help="also write contact_frames, ground and the object's initial pose to session.yaml")
    parser.add_argument("--camera-world", action="store_true", default=None,
                        help="camera 0 as the world frame (OpenCV axes, y down, as Kinect rigs write it), "
                             "not the default z-up world; the ground truth's body_params.npz is left out")
    parser.add_argument("--ik-iters", type=int, default=None, help="L-BFGS iterations of the arm IK")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads for the motion solve")
    parser.add_argument("--quiet", action="store_true", default=None)
    return parser


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    """SynthConfig from parsed arguments: defaults, then the preset, then explicit options."""
    cfg = apply_preset(SynthConfig(), getattr(args, "preset", None))
    changes = {}
    simple = ["script", "object", "frames", "fps", "seed", "phenotype", "cameras", "width", "height", "focal_scale",
              "ring_radius", "ring_height", "look_at", "dist", "color_format", "clean_depth", "drop_rate", "drop_view",
              "annotate", "ik_iters", "threads", "quiet", "appearance", "light", "flight_turns", "flying_pixels",
              "camera_world"]
    for name in simple:
        value = getattr(args, name, None)
        if value is not None:
            changes[name] = value
    if getattr(args, "depth_sigma", None) is not None:
        changes["depth_sigma_base"], changes["depth_sigma_quad"] = args.depth_sigma
    if getattr(args, "kp_sigma", None) is not None:
        changes["kp_sigma_body"], changes["kp_sigma_hand"] = args.kp_sigma
    for flag, key in (("no_walls", "walls"), ("no_keypoints", "keypoints"), ("no_masks", "masks")):
        if getattr(args, flag, None):
            changes[key] = False
    if "phenotype" in changes and len(changes["phenotype"]) != 6:
        raise ValueError("--phenotype needs 6 comma-separated values")
    return dataclasses.replace(cfg, **changes)
