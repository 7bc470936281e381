"""Corrupted variants of the committed sample session, each run through the CLI and its outcome classified.

Every case copies data_samples/sample into a scratch folder (frame files hard-linked, the small files
and ground_truth/ copied; a corrupted file is written as a new file in place of the link, so the
sample itself is never written), corrupts the copy, runs one command line and judges what happened by
one rule: either exit 0 with sane outputs, or a non-zero exit with a short message naming the file or
key. Outcomes:

  clear      refused (non-zero exit) with at most five lines that name the file or key
  handled    exit 0 and the outputs are sane
  traceback  a Python traceback in the output, whatever the exit status
  unclear    refused, but the message names no file or key, is empty, or is over five lines
  silent     exit 0 where a refusal is expected, or the outputs are not sane (NaN without
             valid=False, ground truth changed, a calibration flag the corruption cannot have caused)
  refused    a non-zero exit on an input that is fine (a dropped frame, an optional file missing)

Run `python -m tools.fuzz_inputs` (from the repository root) for every case's outcome and the counts;
tests/test_fuzz.py asserts the rule case by case.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import logging
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "data_samples" / "sample"
CAMERAS = ("cam0", "cam1", "cam2", "cam3")
NUM_FRAMES = 30
MAX_MESSAGE_LINES = 5
TRACEBACK = "Traceback (most recent call last)"
# prepare on the sample, kept short: two frames for the calibration check, three for the ground, no
# refinement of a flagged calibration (the check's verdict is what the cases judge)
PREPARE = ["--stages", "prepare", "--set", "report.enabled=false", "--set", "prepare.calib_frames=2",
           "--set", "prepare.ground_frames=3", "--set", "prepare.save_clouds=false",
           "--set", "prepare.calib_refine=never", "-q"]
SUBPROCESS_TIMEOUT_S = 120
LINKED_FOLDERS = set(CAMERAS)  # top-level folders whose files are hard-linked, not copied


@dataclass(frozen=True)
class Case:
    """One corrupted variant: how to corrupt the session copy, what to run, what is expected.

    `expect`: "refuse" (must exit non-zero with a clear message), "accept" (must exit 0, sane),
    "either" (a clear refusal or a sane exit 0), "flag" (prepare must flag the calibration, or refuse).
    `names`: a refusal must mention one of these (the file or the key). `command`: "validate",
    "prepare" (`run --stages prepare`, short), or a function (S, O, scratch) -> argv for other
    command lines. `calibration`: the corruption touches calibration, so a calibration flag is fair."""

    name: str
    kind: str
    mutate: Callable[[Path], None]
    command: str | Callable[[Path, Path, Path], list[str]]
    expect: str
    names: tuple[str, ...]
    calibration: bool = False
    runner: str = "inprocess"  # or "subprocess" (seen from outside), "concurrent" (two at once), "killed"
    between: Callable[[Path], None] | None = None  # run twice, damaging OUT with this in between
    check: Callable[[Path, Path, Path], str | None] | None = None  # (S, O, scratch) -> why not sane, or None


@dataclass
class Result:
    """What one command line did: exit status and the text it wrote."""

    rc: int
    stdout: str
    stderr: str
    seconds: float = 0.0

    @property
    def output(self) -> str:
        return self.stdout + self.stderr


@dataclass
class Outcome:
    """A case's classified outcome: the class, why, the message shown to the user, the full output."""

    case: Case
    outcome: str
    why: str
    result: Result
    message: list[str] = field(default_factory=list)

    @property
    def follows_rule(self) -> bool:
        return self.outcome in ("clear", "handled")


# ----------------------------------------------------------------------------------------------
# Copies and corruptions


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def copy_sample(dst: Path) -> Path:
    """A copy of the sample at `dst`: camera frame files hard-linked, everything else copied."""
    dst.mkdir(parents=True)
    for entry in sorted(SAMPLE.iterdir()):
        target = dst / entry.name
        if entry.is_dir():
            copy = _link_or_copy if entry.name in LINKED_FOLDERS else shutil.copy2
            shutil.copytree(entry, target, copy_function=copy)
        else:
            shutil.copy2(entry, target)
    return dst


def write_bytes(path: Path, data: bytes) -> None:
    """`data` as a new file at `path`: a hard link there is replaced, never written through."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()  # never write through a hard link
    path.write_bytes(data)


def truncate(path: Path, fraction: float) -> None:
    data = path.read_bytes()
    write_bytes(path, data[: int(len(data) * fraction)])


def flip_bytes(path: Path, start: float, count: int, seed: int = 0) -> None:
    """XOR `count` bytes from `start` (fraction of the file) with random non-zero values."""
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(seed)
    at = int(len(data) * start)
    for i in range(at, min(at + count, len(data))):
        data[i] ^= int(rng.integers(1, 256))
    write_bytes(path, bytes(data))


def remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def frame(S: Path, cam: str, kind: str, idx: int) -> Path:
    ext = {"color": ".jpg", "keypoints": ".json"}.get(kind, ".png")
    folder = {"person": "masks/person", "object": "masks/object"}.get(kind, kind)
    return S / cam / folder / f"{idx:06d}{ext}"


def edit_yaml(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    def mutate(S: Path) -> None:
        data = yaml.safe_load((S / "session.yaml").read_text())
        fn(data)
        write_bytes(S / "session.yaml", yaml.safe_dump(data, sort_keys=False).encode())
    return mutate


def set_key(dotted: str, value) -> Callable[[Path], None]:
    """session.yaml with `a.b` set to `value` (the key dropped when value is DELETE)."""
    def fn(data: dict) -> None:
        *parents, leaf = dotted.split(".")
        node = data
        for p in parents:
            node = node.setdefault(p, {})
        if value is DELETE:
            node.pop(leaf, None)
        else:
            node[leaf] = value
    return edit_yaml(fn)


DELETE = object()


def yaml_text(text: str) -> Callable[[Path], None]:
    return lambda S: write_bytes(S / "session.yaml", text.encode())


def edit_calibration(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    def mutate(S: Path) -> None:
        data = json.loads((S / "calibration.json").read_text())
        fn(data)
        write_bytes(S / "calibration.json", json.dumps(data).encode())
    return mutate


def edit_camera(index: int, fn: Callable[[dict], None]) -> Callable[[Path], None]:
    return edit_calibration(lambda data: fn(data["cameras"][index]))


def edit_images(cams, kind: str, frames, fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], None]:
    """Rewrite the given frames of the given cameras through `fn` (decoded image -> image to write)."""
    def mutate(S: Path) -> None:
        for cam in cams:
            for idx in frames:
                path = frame(S, cam, kind, idx)
                img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                ok, data = cv2.imencode(path.suffix, fn(img))
                assert ok, path
                write_bytes(path, data.tobytes())
    return mutate


def edit_mesh(fn: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]) -> Callable[[Path], None]:
    """object.ply rewritten (binary PLY) from fn(vertices, faces)."""
    def mutate(S: Path) -> None:
        import trimesh

        mesh = trimesh.load(str(S / "object.ply"), process=False, force="mesh")
        v, f = fn(np.array(mesh.vertices), np.array(mesh.faces))
        data = trimesh.Trimesh(v, f, process=False, validate=False).export(file_type="ply")
        write_bytes(S / "object.ply", data)
    return mutate


def edit_npz(name: str, fn: Callable[[dict], dict]) -> Callable[[Path], None]:
    def mutate(S: Path) -> None:
        path = S / "ground_truth" / name
        with np.load(path) as z:
            arrays = fn({k: z[k] for k in z.files})
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        write_bytes(path, buf.getvalue())
    return mutate


def save_npy(name: str, fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], None]:
    def mutate(S: Path) -> None:
        path = S / "ground_truth" / name
        buf = io.BytesIO()
        np.save(buf, fn(np.load(path)), allow_pickle=True)
        write_bytes(path, buf.getvalue())
    return mutate


def edit_keypoints(cams, frames, fn: Callable[[dict], object]) -> Callable[[Path], None]:
    def mutate(S: Path) -> None:
        for cam in cams:
            for idx in frames:
                path = frame(S, cam, "keypoints", idx)
                write_bytes(path, json.dumps(fn(json.loads(path.read_text()))).encode())
    return mutate


def edit_contacts(value) -> Callable[[Path], None]:
    return lambda S: write_bytes(S / "object_contacts.json", json.dumps(value).encode())


def nothing(S: Path) -> None:
    """The sample as committed."""


ALL_FRAMES = range(NUM_FRAMES)


def scaled_keypoints(factor: float) -> Callable[[dict], dict]:
    def fn(data: dict) -> dict:
        for person in data["people"]:
            for key, values in person.items():
                if key.endswith("_2d"):
                    person[key] = [v * factor if i % 3 < 2 else v for i, v in enumerate(values)]
        return data
    return fn


def rigid(T: list, dx: float = 0.0, deg: float = 0.0) -> list:
    """T_world_from_cam moved `dx` metres along the camera's x axis and turned `deg` about its y axis."""
    T = np.array(T, float)
    a = math.radians(deg)
    turn = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    T[:3, 3] += T[:3, 0] * dx
    T[:3, :3] = T[:3, :3] @ turn
    return T.tolist()


# ----------------------------------------------------------------------------------------------
# The cases


def session_yaml_cases() -> list[Case]:
    V, Y = "validate", "session.yaml"
    c = [
        Case("fps zero", Y, set_key("fps", 0), V, "refuse", ("fps",)),
        Case("fps negative", Y, set_key("fps", -5), V, "refuse", ("fps",)),
        Case("fps text", Y, set_key("fps", "thirty"), V, "refuse", ("fps",)),
        Case("fps quoted number", Y, set_key("fps", "30"), V, "either", ("fps",)),
        Case("fps NaN", Y, yaml_text("fps: .nan\n"), V, "refuse", ("fps",)),
        Case("fps inf", Y, set_key("fps", float("inf")), V, "refuse", ("fps",)),
        Case("fps boolean", Y, set_key("fps", True), V, "refuse", ("fps",)),
        Case("fps missing", Y, set_key("fps", DELETE), V, "refuse", ("fps",)),
        Case("fps 30000 (implausible)", Y, set_key("fps", 30000), V, "refuse", ("fps",)),
        Case("fps 0.001 (implausible)", Y, set_key("fps", 0.001), V, "refuse", ("fps",)),
        Case("fps as list", Y, set_key("fps", [30]), V, "refuse", ("fps",)),
        Case("frames start after end", Y, set_key("frames", {"start": 5, "end": 2}), V, "refuse", ("frames",)),
        Case("frames negative start", Y, set_key("frames", {"start": -1, "end": 10}), V, "refuse", ("frames",)),
        Case("frames end beyond data", Y, set_key("frames", {"start": 0, "end": 500}), V, "refuse", ("frames",)),
        Case("frames float start", Y, set_key("frames", {"start": 0.5, "end": 10}), V, "refuse", ("frames",)),
        Case("frames as text", Y, set_key("frames", "all"), V, "refuse", ("frames",)),
        Case("frames unknown key", Y, set_key("frames", {"start": 0, "end": 29, "step": 2}), V, "refuse",
             ("frames",)),
        Case("object.mesh missing file", Y, set_key("object.mesh", "missing.ply"), V, "refuse",
             ("missing.ply", "object.mesh")),
        Case("object.mesh number", Y, set_key("object.mesh", 42), V, "refuse", ("object.mesh", "42")),
        Case("object.mass_kg negative", Y, set_key("object.mass_kg", -1.0), V, "refuse", ("mass_kg",)),
        Case("object.mass_kg NaN", Y, set_key("object.mass_kg", float("nan")), V, "refuse", ("mass_kg",)),
        Case("object.mass_kg text", Y, set_key("object.mass_kg", "1.2kg"), V, "refuse", ("mass_kg",)),
        Case("object.mass_kg in grams", Y, set_key("object.mass_kg", 1200), V, "refuse", ("mass_kg",)),
        Case("object.density zero", Y, set_key("object.density_kg_m3", 0), V, "refuse", ("density_kg_m3",)),
        Case("object.contact_vertices missing file", Y, set_key("object.contact_vertices", "nope.json"), V,
             "refuse", ("nope.json", "contact_vertices")),
        Case("object.initial_pose R scaled", Y, set_key("object.initial_pose", {
            "R": [[2, 0, 0], [0, 2, 0], [0, 0, 2]], "t": [0, 0, 0]}), V, "refuse", ("initial_pose",)),
        Case("object.initial_pose t NaN", Y, set_key("object.initial_pose", {
            "R": np.eye(3).tolist(), "t": [0, float("nan"), 0]}), V, "refuse", ("initial_pose",)),
        Case("object.initial_pose t in mm", Y, set_key("object.initial_pose", {
            "R": np.eye(3).tolist(), "t": [790.0, 325.0, 75.0]}), V, "refuse", ("initial_pose",)),
        Case("object block is a list", Y, set_key("object", ["object.ply"]), V, "refuse", ("object",)),
        Case("contact_frames reversed", Y, set_key("contact_frames", [[10, 5]]), V, "refuse", ("contact_frames",)),
        Case("contact_frames beyond range", Y, set_key("contact_frames", [[0, 100]]), V, "refuse",
             ("contact_frames",)),
        Case("contact_frames text", Y, set_key("contact_frames", "yes"), V, "refuse", ("contact_frames",)),
        Case("ground normal zero", Y, set_key("ground", {"point": [0, 0, 0], "normal": [0, 0, 0]}), V, "refuse",
             ("ground",)),
        Case("ground point NaN", Y, set_key("ground", {"point": [0, float("nan"), 0], "normal": [0, 0, 1]}), V,
             "refuse", ("ground",)),
        Case("ground without normal", Y, set_key("ground", {"point": [0, 0, 0]}), V, "refuse", ("ground",)),
        Case("body.model unknown", Y, set_key("body.model", "smpl"), V, "refuse", ("body.model",)),
        Case("body as text", Y, set_key("body", "anny"), V, "either", ("body",)),
        Case("body.mass_kg negative", Y, set_key("body.mass_kg", -70), V, "refuse", ("body.mass_kg",)),
        Case("body.mass_kg text", Y, set_key("body.mass_kg", "heavy"), V, "refuse", ("body.mass_kg",)),
        Case("unknown top-level key", Y, set_key("fsp", 30), V, "either", ("fsp",)),
    ]
    return c


def session_file_cases() -> list[Case]:
    V, Y = "validate", "session.yaml"
    good = (SAMPLE / "session.yaml").read_text()
    return [
        Case("session.yaml top level list", Y, yaml_text("- fps: 5\n"), V, "refuse", (Y,)),
        Case("session.yaml invalid YAML", Y, yaml_text("fps: [5\nobject: {mesh: object.ply\n"), V, "refuse", (Y,)),
        Case("session.yaml empty", Y, yaml_text(""), V, "refuse", (Y, "fps")),
        Case("session.yaml binary garbage", Y, lambda S: write_bytes(S / Y, bytes(range(256)) * 4), V, "refuse",
             (Y,)),
        Case("session.yaml truncated", "truncation", yaml_text(good[: len(good) // 2]), V, "either", (Y,)),
        Case("session.yaml missing", "missing", lambda S: remove(S / Y), V, "refuse", (Y,)),
        Case("session.yaml tab indentation", Y, yaml_text(good.replace("  mesh", "\tmesh")), V, "refuse", (Y,)),
    ]


def calibration_cases() -> list[Case]:
    V, C = "validate", "calibration.json"
    cam = edit_camera
    sample_K = json.loads((SAMPLE / C).read_text())["cameras"][0]["K"]
    fx, cx, fy, cy = sample_K[0][0], sample_K[0][2], sample_K[1][1], sample_K[1][2]

    def k(value):
        return cam(0, lambda e: e.__setitem__("K", value))

    def setf(key, value, index=0):
        return cam(index, lambda e: e.__setitem__(key, value))

    def T(fn, index=0):
        return cam(index, lambda e: e.__setitem__("T_world_from_cam", fn(e["T_world_from_cam"])))

    cases = [
        Case("calibration.json missing", "missing", lambda S: remove(S / C), V, "refuse", (C,)),
        Case("calibration.json truncated", "truncation", lambda S: truncate(S / C, 0.5), V, "refuse", (C,)),
        Case("calibration.json garbage", C, lambda S: write_bytes(S / C, b"\x00\xff" * 100), V, "refuse", (C,)),
        Case("cameras empty", C, edit_calibration(lambda d: d.__setitem__("cameras", [])), V, "refuse", (C,)),
        Case("cameras as mapping", C, edit_calibration(lambda d: d.__setitem__("cameras", {"cam0": {}})), V,
             "refuse", (C,)),
        Case("K negative focal", C, k([[-fx, 0, cx], [0, fy, cy], [0, 0, 1]]), V, "refuse", ("K",)),
        Case("K NaN", C, k([[float("nan"), 0, cx], [0, fy, cy], [0, 0, 1]]), V, "refuse", ("K",)),
        Case("K 2x2", C, k([[fx, 0], [0, fy]]), V, "refuse", ("K",)),
        Case("K text", C, k("identity"), V, "refuse", ("K",)),
        Case("K transposed", "units", k([[fx, 0, 0], [0, fy, 0], [cx, cy, 1]]), V, "refuse", ("K",)),
        Case("K focal and centre swapped", "units", k([[cx, 0, fx], [0, cy, fy], [0, 0, 1]]), V, "refuse",
             ("K", C)),
        Case("K of twice the resolution", "units", k([[2 * fx, 0, 2 * cx], [0, 2 * fy, 2 * cy], [0, 0, 1]]), V,
             "refuse", ("K", C)),
        Case("K focal in mm", "units", k([[1.8, 0, cx], [0, 1.8, cy], [0, 0, 1]]), V, "refuse", ("K", C)),
        Case("width zero", C, setf("width", 0), V, "refuse", ("width",)),
        Case("width text", C, setf("width", "320"), V, "refuse", ("width",)),
        Case("width twice the images", C, setf("width", 640), V, "refuse", ("640", "width")),
        Case("width and height swapped", "units", cam(1, lambda e: e.update(width=e["height"], height=e["width"])),
             V, "refuse", ("cam1",)),
        Case("dist three numbers", C, setf("dist", [0.1, 0.0, 0.0]), V, "refuse", ("dist",)),
        Case("dist NaN", C, setf("dist", [float("nan"), 0, 0, 0, 0]), V, "refuse", ("dist",)),
        Case("dist huge", C, setf("dist", [50.0, -80.0, 0, 0, 0]), V, "either", ("dist",)),
        Case("T scaled", C, T(lambda t: (np.array(t) * np.diag([2, 2, 2, 1])).tolist()), V, "refuse",
             ("T_world_from_cam",)),
        Case("T last row wrong", C, T(lambda t: t[:3] + [[0, 0, 1, 1]]), V, "refuse", ("T_world_from_cam",)),
        Case("T NaN", C, T(lambda t: [[float("nan")] * 4] + t[1:]), V, "refuse", ("T_world_from_cam",)),
        Case("T translation in mm", "units", T(lambda t: [r[:3] + [r[3] * 1000] for r in t[:3]] + t[3:]), V,
             "refuse", ("T_world_from_cam", C)),
        Case("T of every camera in mm", "units", edit_calibration(lambda d: [
            e.__setitem__("T_world_from_cam", [r[:3] + [r[3] * 1000] for r in e["T_world_from_cam"][:3]]
                          + e["T_world_from_cam"][3:]) for e in d["cameras"]]), V, "refuse", ("T_world_from_cam", C)),
        Case("duplicate camera name", C, setf("name", "cam1"), V, "refuse", ("cam1", "duplicate")),
        Case("camera name with slash", C, setf("name", "../cam0"), V, "refuse", ("name",)),
        Case("camera without name", C, cam(0, lambda e: e.pop("name")), V, "refuse", ("name",)),
        Case("camera without folder", C, setf("name", "cam9", 3), V, "refuse", ("cam9",)),
        Case("camera without K", C, cam(2, lambda e: e.pop("K")), V, "refuse", ("K",)),
        Case("extra camera folder", "missing", lambda S: shutil.copytree(S / "cam3", S / "cam4",
                                                                         copy_function=_link_or_copy), V, "either",
             ("cam4",)),
    ]
    return cases


def calibration_prepare_cases() -> list[Case]:
    """Calibration that reads as valid but is wrong: only prepare's check can see it."""
    P, C = "prepare", "calibration.json"

    def T(index, fn):
        return edit_camera(index, lambda e: e.__setitem__("T_world_from_cam", fn(e["T_world_from_cam"])))

    inverted = T(2, lambda t: np.linalg.inv(np.array(t)).tolist())
    return [
        Case("camera bumped 5 cm (3 check frames)", "calibration", T(1, lambda t: rigid(t, dx=0.05)),
             run_argv("--set", "prepare.calib_frames=3"), "flag", ("cam1", C), calibration=True),
        Case("camera turned 1 degree", "calibration", T(1, lambda t: rigid(t, deg=1.0)), P, "flag", ("cam1", C),
             calibration=True),
        Case("camera turned 5 degrees (3 check frames)", "calibration", T(1, lambda t: rigid(t, deg=5.0)),
             run_argv("--set", "prepare.calib_frames=3"), "flag", ("cam1", C), calibration=True),
        Case("camera pose inverted", "calibration", inverted, P, "flag", ("cam2", C), calibration=True),
        Case("camera pose inverted (validate)", "calibration", inverted, "validate", "either", ("cam2", C),
             calibration=True),
        Case("T translation in mm (run)", "units", T(0, lambda t: [r[:3] + [r[3] * 1000] for r in t[:3]] + t[3:]),
             P, "refuse", ("T_world_from_cam", C), calibration=True),
        Case("K of twice the resolution (run)", "units", edit_camera(0, lambda e: e.__setitem__(
            "K", (np.array(e["K"]) * np.array([[2], [2], [1]])).tolist())), P, "refuse", ("K", C),
            calibration=True),
    ]


def keypoint_cases() -> list[Case]:
    V, K = "validate", "keypoints"
    one = ["cam0"], [7]
    return [
        Case("keypoints truncated", "truncation", lambda S: truncate(frame(S, "cam0", K, 7), 0.5), V, "accept",
             ("000007.json",)),
        Case("keypoints garbage", "bytes", lambda S: write_bytes(frame(S, "cam1", K, 3), b"\x89\x00garbage"), V,
             "accept", ("000003.json",)),
        Case("keypoints people not a list", K, edit_keypoints(*one, lambda d: {"people": {"a": 1}}), V, "accept",
             ("000007.json",)),
        Case("keypoints JSON list", K, edit_keypoints(*one, lambda d: []), V, "accept", ("000007.json",)),
        Case("keypoints NaN values", K, edit_keypoints(*one, lambda d: {"people": [{
            "pose_keypoints_2d": [float("nan")] * 75}]}), V, "either", ("000007.json",)),
        Case("keypoints wrong length", K, edit_keypoints(*one, lambda d: {"people": [{
            "pose_keypoints_2d": [1.0] * 72}]}), V, "either", ("000007.json",)),
        Case("keypoints as text values", K, edit_keypoints(*one, lambda d: {"people": [{
            "pose_keypoints_2d": ["x"] * 75}]}), V, "either", ("000007.json",)),
        Case("keypoints person not an object", K, edit_keypoints(*one, lambda d: {"people": [42]}), V, "accept",
             ("000007.json",)),
        Case("keypoints normalised coordinates", "units", edit_keypoints(CAMERAS, ALL_FRAMES, scaled_keypoints(
            1 / 320)), V, "either", ("keypoints",)),
        Case("keypoints far outside the image", K, edit_keypoints(["cam2"], ALL_FRAMES, scaled_keypoints(1e6)), V,
             "either", ("keypoints",)),
        Case("keypoints folder of cam0 removed", "missing", lambda S: remove(S / "cam0" / K), V, "accept",
             ("keypoints",)),
        Case("keypoints one file removed", "missing", lambda S: remove(frame(S, "cam3", K, 12)), V, "accept",
             ("000012.json",)),
    ]


def mesh_cases() -> list[Case]:
    V, M, J = "validate", "object.ply", "object_contacts.json"
    return [
        Case("mesh truncated", "truncation", lambda S: truncate(S / M, 0.5), V, "refuse", (M,)),
        Case("mesh garbage", "bytes", lambda S: write_bytes(S / M, os.urandom(4096)), V, "refuse", (M,)),
        Case("mesh empty file", M, lambda S: write_bytes(S / M, b""), V, "refuse", (M,)),
        Case("mesh header flipped", "bytes", lambda S: flip_bytes(S / M, 0.0, 12), V, "refuse", (M,)),
        Case("mesh body bytes flipped", "bytes", lambda S: flip_bytes(S / M, 0.6, 64), V, "either", (M,)),
        Case("mesh in millimetres", "units", edit_mesh(lambda v, f: (v * 1000, f)), V, "refuse", (M,)),
        Case("mesh in millimetres (run)", "units", edit_mesh(lambda v, f: (v * 1000, f)), "prepare", "refuse",
             (M,)),
        Case("mesh NaN vertex", M, edit_mesh(lambda v, f: (np.where(np.arange(len(v))[:, None] == 5, np.nan, v), f)),
             V, "refuse", (M,)),
        Case("mesh without faces", M, edit_mesh(lambda v, f: (v, f[:0])), V, "refuse", (M,)),
        Case("mesh face index out of range", M, edit_mesh(lambda v, f: (v, np.vstack([f, [[0, 1, 99999]]]))), V,
             "refuse", (M,)),
        Case("mesh all vertices at one point", M, edit_mesh(lambda v, f: (v * 0, f)), V, "refuse", (M,)),
        Case("mesh missing", "missing", lambda S: remove(S / M), V, "refuse", (M,)),
        Case("contacts out of range", J, edit_contacts({"vertices": [0, 5000]}), V, "refuse", (J,)),
        Case("contacts negative", J, edit_contacts({"vertices": [-1, 3]}), V, "refuse", (J,)),
        Case("contacts floats", J, edit_contacts({"vertices": [1.5, 2]}), V, "refuse", (J,)),
        Case("contacts text", J, edit_contacts({"vertices": "all"}), V, "refuse", (J,)),
        Case("contacts truncated", "truncation", lambda S: truncate(S / J, 0.5), V, "refuse", (J,)),
        Case("contacts missing", "missing", lambda S: remove(S / J), V, "refuse", (J,)),
    ]


def ground_truth_cases() -> list[Case]:
    V, G = "validate", "ground_truth"

    def poses(fn):
        return edit_npz("object_poses.npz", fn)

    def nan_first(a):
        a = a.copy()
        a[0] = np.nan
        return a

    return [
        Case("object_poses truncated", "truncation", lambda S: truncate(S / G / "object_poses.npz", 0.5), V,
             "refuse", ("object_poses.npz",)),
        Case("object_poses R NaN", "npz", poses(lambda z: {**z, "R": nan_first(z["R"])}), V, "refuse",
             ("object_poses.npz",)),
        Case("object_poses without t", "npz", poses(lambda z: {"R": z["R"]}), V, "refuse", ("object_poses.npz",)),
        Case("object_poses one frame short", "npz", poses(lambda z: {k: a[:-1] for k, a in z.items()}), V,
             "refuse", ("object_poses.npz",)),
        Case("object_poses t NaN", "npz", poses(lambda z: {**z, "t": nan_first(z["t"])}), V, "refuse",
             ("object_poses.npz",)),
        Case("object_poses t in mm", "units", poses(lambda z: {**z, "t": z["t"] * 1000}), V, "either",
             ("object_poses.npz",)),
        Case("object_poses pickled objects", "npz", poses(lambda z: {**z, "R": np.array([None] * 30, object)}), V,
             "refuse", ("object_poses.npz",)),
        Case("body_vertices truncated", "truncation", lambda S: truncate(S / G / "body_vertices.npy", 0.5), V,
             "refuse", ("body_vertices.npy",)),
        Case("body_vertices garbage", "bytes", lambda S: write_bytes(S / G / "body_vertices.npy", os.urandom(999)),
             V, "refuse", ("body_vertices.npy",)),
        # validate reads the big arrays' headers only, so NaN inside may pass it
        Case("body_vertices NaN", "npz", save_npy("body_vertices.npy", nan_first), V, "either",
             ("body_vertices.npy",)),
        Case("body_faces out of range", "npz", save_npy("body_faces.npy", lambda f: f + 10 ** 6), V, "refuse",
             ("body_faces.npy",)),
        Case("body_faces missing", "missing", lambda S: remove(S / G / "body_faces.npy"), V, "refuse",
             ("body_faces.npy",)),
        Case("contact floats", "npz", save_npy("contact.npy", lambda c: c.astype(float) * 0.5), V, "refuse",
             ("contact.npy",)),
        Case("contact wrong length", "npz", save_npy("contact.npy", lambda c: c[:10]), V, "refuse", ("contact.npy",)),
        Case("keypoints3d wrong shape", "npz", save_npy("keypoints3d.npy", lambda k: k[:, :25]), V, "refuse",
             ("keypoints3d.npy",)),
        Case("body_params truncated", "truncation", lambda S: truncate(S / G / "body_params.npz", 0.3), V, "either",
             ("body_params.npz",)),
        Case("ground_truth removed", "missing", lambda S: remove(S / G), V, "accept", (G,)),
    ]


def depth_in_metres(img: np.ndarray) -> np.ndarray:
    return np.round(img / 1000.0).astype(np.uint16)


def frame_cases() -> list[Case]:
    V, P = "validate", "prepare"
    color7, depth7 = (lambda S: frame(S, "cam0", "color", 7)), (lambda S: frame(S, "cam1", "depth", 7))
    return [
        Case("color truncated", "truncation", lambda S: truncate(color7(S), 0.5), V, "accept", ("000007.jpg",)),
        Case("color scan bytes flipped", "bytes", lambda S: flip_bytes(color7(S), 0.5, 32), V, "either",
             ("000007.jpg",)),
        Case("color header bytes flipped", "bytes", lambda S: flip_bytes(color7(S), 0.0, 16), V, "either",
             ("000007.jpg",)),
        Case("color empty file", "truncation", lambda S: write_bytes(color7(S), b""), V, "accept", ("000007.jpg",)),
        Case("color wrong size", "frames", edit_images(["cam0"], "color", [5], lambda i: i[::2, ::2]), V, "refuse",
             ("000005.jpg",)),
        Case("color grey PNG bytes in a .jpg", "frames", lambda S: write_bytes(color7(S), cv2.imencode(
            ".png", np.full((288, 320), 128, np.uint8))[1].tobytes()), V, "either", ("000007.jpg",)),
        Case("color every frame truncated", "truncation", lambda S: [truncate(frame(S, "cam2", "color", i), 0.3)
                                                                   for i in ALL_FRAMES], V, "refuse", ("cam2",)),
        Case("depth truncated", "truncation", lambda S: truncate(depth7(S), 0.5), V, "accept", ("000007.png",)),
        Case("depth bytes flipped", "bytes", lambda S: flip_bytes(depth7(S), 0.5, 32), V, "either", ("000007.png",)),
        Case("depth every frame truncated", "truncation", lambda S: [truncate(frame(S, "cam1", "depth", i), 0.5)
                                                                   for i in ALL_FRAMES], V, "refuse", ("cam1",)),
        Case("depth 8-bit first frame", "units", edit_images(["cam1"], "depth", [0], lambda d: (d // 40).astype(
            np.uint8)), V, "refuse", ("000000.png",)),
        Case("depth 8-bit one later frame", "units", edit_images(["cam1"], "depth", [9], lambda d: (d // 40).astype(
            np.uint8)), V, "accept", ("000009.png",)),
        Case("depth 3 channels", "units", edit_images(["cam2"], "depth", [0], lambda d: np.dstack([d, d, d])), V,
             "refuse", ("000000.png",)),
        Case("depth in metres", "units", edit_images(CAMERAS, "depth", ALL_FRAMES, depth_in_metres), V, "refuse",
             ("depth",)),
        Case("depth in metres (run)", "units", edit_images(CAMERAS, "depth", ALL_FRAMES, depth_in_metres), P,
             "refuse", ("depth",)),
        Case("depth in metres, one camera", "units", edit_images(["cam3"], "depth", ALL_FRAMES, depth_in_metres),
             V, "refuse", ("cam3",)),
        Case("depth in tenths of mm (run)", "units", edit_images(CAMERAS, "depth", ALL_FRAMES,
                                                                 lambda d: np.clip(d * 10.0, 0, 65535).astype(
                                                                     np.uint16)), P, "refuse", ("depth",)),
        Case("depth all zero, one camera (run)", "frames", edit_images(["cam0"], "depth", ALL_FRAMES,
                                                                      np.zeros_like), P, "either", ("cam0",)),
        Case("mask truncated", "truncation", lambda S: truncate(frame(S, "cam2", "person", 4), 0.4), V, "accept",
             ("000004.png",)),
        Case("mask wrong size", "frames", edit_images(["cam2"], "object", [4], lambda m: m[:100]), V, "either",
             ("000004.png",)),
    ]


def missing_cases() -> list[Case]:
    V, P = "validate", "prepare"

    def drop_frames(S: Path, frames, cams=CAMERAS, kinds=("color", "depth", "keypoints", "person", "object")):
        for cam in cams:
            for kind in kinds:
                for i in frames:
                    remove(frame(S, cam, kind, i))

    return [
        Case("color folder missing", "missing", lambda S: remove(S / "cam2" / "color"), V, "refuse", ("cam2",)),
        Case("depth folder missing", "missing", lambda S: remove(S / "cam1" / "depth"), V, "refuse", ("cam1",)),
        Case("camera folder missing", "missing", lambda S: remove(S / "cam3"), V, "refuse", ("cam3",)),
        Case("masks folder missing", "missing", lambda S: remove(S / "cam0" / "masks"), V, "accept", ("masks",)),
        Case("one depth frame missing", "missing", lambda S: remove(frame(S, "cam1", "depth", 3)), V, "accept",
             ("000003.png",)),
        Case("gap in every camera", "missing", lambda S: drop_frames(S, [10, 11, 12]), V, "either", ("10",)),
        Case("first frames missing everywhere", "missing", lambda S: drop_frames(S, [0, 1]), V, "either",
             ("frames",)),
        Case("misnamed frame file", "missing", lambda S: shutil.copy(frame(S, "cam0", "color", 0),
                                                                     S / "cam0" / "color" / "frame_0.jpg"), V,
             "accept", ("frame_0.jpg",)),
        Case("frame file is a folder", "missing", lambda S: (remove(frame(S, "cam0", "depth", 4)),
                                                             frame(S, "cam0", "depth", 4).mkdir()), V, "accept",
             ("000004",)),
        Case("sample as committed (run)", "baseline", nothing, P, "accept", ()),
        Case("sample as committed", "baseline", nothing, V, "accept", ()),
        Case("gap in every camera (run)", "missing", lambda S: drop_frames(S, [10, 11, 12]), P, "either", ("10",)),
        Case("keypoints and masks removed (run)", "missing", lambda S: [
            remove(S / c / d) for c in CAMERAS for d in ("keypoints", "masks")], P, "accept", ()),
        Case("one color truncated (run)", "truncation", lambda S: truncate(frame(S, "cam0", "color", 0), 0.5), P,
             "accept", ()),
        Case("one depth bytes flipped (run)", "bytes", lambda S: flip_bytes(frame(S, "cam2", "depth", 29), 0.5, 32),
             P, "either", ("000029.png",)),
    ]


def run_argv(*extra: str) -> Callable[[Path, Path, Path], list[str]]:
    """`intercap run S --out O` with the short prepare settings and `extra` after them."""
    return lambda S, O, scratch: ["run", str(S), "--out", str(O), *PREPARE, *extra]


def out_at(where: Callable[[Path, Path, Path], Path]) -> Callable[[Path, Path, Path], list[str]]:
    """The short prepare run with --out at `where` (S, O, scratch) -> path."""
    return lambda S, O, scratch: ["run", str(S), "--out", str(where(S, O, scratch)), *PREPARE]


def a_file(scratch: Path) -> Path:
    path = scratch / "notes.txt"
    if not path.exists():
        path.write_text("my notes\n")
    return path


def unchanged(path_of: Callable[[Path, Path, Path], Path], text: str | None = None):
    """A check: the file at path_of(S, O, scratch) still holds `text` (default: what it held before)."""
    def check(S: Path, O: Path, scratch: Path) -> str | None:
        path = path_of(S, O, scratch)
        want = text if text is not None else (SAMPLE / path.relative_to(S)).read_text()
        if not path.is_file() or path.read_text() != want:
            return f"{path} was changed or removed"
        return None
    return check


def config_file(text: str) -> Callable[[Path, Path, Path], list[str]]:
    def argv(S: Path, O: Path, scratch: Path) -> list[str]:
        path = scratch / "my_config.yaml"
        path.write_text(text)
        return ["run", str(S), "--out", str(O), "--config", str(path), *PREPARE]
    return argv


def cli_cases() -> list[Case]:
    R, X = "either", "cli"
    notes = (lambda S, O, scratch: a_file(scratch))
    return [
        Case("--set without =", X, nothing, run_argv("--set", "prepare.calib_frames"), "refuse",
             ("prepare.calib_frames",)),
        Case("--set unknown key", X, nothing, run_argv("--set", "prepare.nokey=1"), "refuse", ("nokey",)),
        Case("--set unknown section", X, nothing, run_argv("--set", "prepar.calib_frames=2"), "refuse", ("prepar",)),
        Case("--set text for a number", X, nothing, run_argv("--set", "prepare.calib_frames=abc"), "refuse",
             ("calib_frames",)),
        Case("--set negative count", X, nothing, run_argv("--set", "prepare.calib_frames=-3"), "refuse",
             ("calib_frames",)),
        Case("--set NaN size", X, nothing, run_argv("--set", "prepare.voxel_size_m=nan"), "refuse",
             ("voxel_size_m",)),
        Case("--set zero voxel", X, nothing, run_argv("--set", "prepare.voxel_size_m=0"), "refuse",
             ("voxel_size_m",)),
        Case("--set depth range empty", X, nothing, run_argv("--set", "prepare.depth_max_m=0.1"), "refuse",
             ("depth_max_m", "depth_min_m")),
        Case("--set bad choice", X, nothing, run_argv("--set", "prepare.calib_refine=sometimes"), "refuse",
             ("calib_refine",)),
        Case("--set bad boolean", X, nothing, run_argv("--set", "report.enabled=maybe"), "refuse",
             ("report.enabled",)),
        Case("--set run.device=tpu", X, nothing, run_argv("--set", "run.device=tpu"), "refuse", ("tpu",)),
        Case("--device beyond the GPUs", X, nothing, run_argv("--device", "cuda:7"), "refuse", ("cuda",)),
        Case("--stages misspelt", X, nothing, run_argv("--stages", "prepar"), "refuse", ("prepar",)),
        Case("--stages empty", X, nothing, run_argv("--stages", ""), "refuse", ("stages",), runner="subprocess"),
        Case("--stages only a comma", X, nothing, run_argv("--stages", ","), "refuse", ("stages",),
             runner="subprocess"),
        Case("--stages repeated", X, nothing, run_argv("--stages", "prepare,prepare"), R, ("stages",)),
        Case("--stages physics without its inputs", X, nothing, run_argv("--stages", "physics"), R,
             ("physics", "global", "body")),
        Case("--out is the session", "out", nothing, out_at(lambda S, O, scratch: S), "refuse", ("--out", "{S}")),
        Case("--out inside ground_truth", "out", nothing, out_at(lambda S, O, scratch: S / "ground_truth"),
             "refuse", ("--out", "ground_truth")),
        Case("--out a folder in the session", "out", nothing, out_at(lambda S, O, scratch: S / "results"),
             "refuse", ("--out", "{S}")),
        Case("--out a camera folder", "out", nothing, out_at(lambda S, O, scratch: S / "cam0"), "refuse",
             ("--out", "cam0")),
        Case("--out is a file", "out", nothing, out_at(notes), "refuse", ("notes.txt",),
             check=unchanged(notes, "my notes\n")),
        Case("--out is session.yaml", "out", nothing, out_at(lambda S, O, scratch: S / "session.yaml"), "refuse",
             ("session.yaml",), check=unchanged(lambda S, O, scratch: S / "session.yaml")),
        Case("--out below a file", "out", nothing, out_at(lambda S, O, scratch: a_file(scratch) / "out"), "refuse",
             ("notes.txt",)),
        Case("--out /dev/null", "out", nothing, out_at(lambda S, O, scratch: Path("/dev/null")), "refuse",
             ("/dev/null",)),
        Case("--config missing", X, nothing, lambda S, O, scratch: ["run", str(S), "--out", str(O), "--config",
                                                                     str(scratch / "nope.yaml"), *PREPARE], "refuse",
             ("nope.yaml",)),
        Case("--config invalid YAML", X, nothing, config_file("prepare: [1,\n"), "refuse", ("my_config.yaml",)),
        Case("--config top level list", X, nothing, config_file("- prepare\n"), "refuse", ("my_config.yaml",)),
        Case("--config unknown section", X, nothing, config_file("prepar:\n  calib_frames: 2\n"), "refuse",
             ("prepar",)),
        Case("--config section as value", X, nothing, config_file("prepare: 3\n"), "refuse", ("prepare",)),
        Case("session path missing", X, nothing, lambda S, O, scratch: ["validate", str(scratch / "nowhere")],
             "refuse", ("nowhere",)),
        Case("session path is a file", X, nothing, lambda S, O, scratch: ["validate", str(S / "session.yaml")],
             "refuse", ("session.yaml",)),
        Case("run on a missing session", X, nothing, lambda S, O, scratch: ["run", str(scratch / "nowhere"),
                                                                             "--out", str(O), *PREPARE], "refuse",
             ("nowhere",)),
        Case("validate without a session", X, nothing, lambda S, O, scratch: ["validate"], "refuse", ("session",)),
        Case("run without --out", X, nothing, lambda S, O, scratch: ["run", str(S)], "refuse", ("--out",)),
        Case("unknown command", X, nothing, lambda S, O, scratch: ["vaildate", str(S)], "refuse", ("vaildate",)),
        Case("unknown option", X, nothing, run_argv("--stagez", "prepare"), "refuse", ("--stagez",)),
        Case("eval of a folder without results", X, nothing, lambda S, O, scratch: ["eval", str(scratch),
                                                                                     "--gt", str(S)], "refuse",
             ("{scratch}", "object_poses", "results")),
        Case("two runs on one --out at once", "concurrency", nothing, run_argv(), "refuse",
             ("{O}", "lock", "in use", "another run"), runner="concurrent"),
    ]


def rerun_cases() -> list[Case]:
    """A second run on a results folder: as the first left it, or with one of its files damaged."""
    R = "resume"
    return [
        Case("rerun on a finished folder", R, nothing, run_argv(), "accept", (), between=lambda O: None),
        Case("rerun after a run was killed", R, nothing, run_argv(), "accept", (), runner="killed"),
        Case("rerun with DONE.json truncated", R, nothing, run_argv(), "either", ("DONE.json",),
             between=lambda O: truncate(O / "prepare" / "DONE.json", 0.5)),
        Case("rerun with metrics.json garbage", R, nothing, run_argv(), "either", ("metrics.json",),
             between=lambda O: write_bytes(O / "metrics.json", b"\x00{not json")),
        Case("rerun with run.json garbage", R, nothing, run_argv(), "either", ("run.json",),
             between=lambda O: write_bytes(O / "run.json", b"[1, 2")),
        Case("rerun with STARTED.json garbage", R, nothing, run_argv(), "either", ("STARTED.json",),
             between=lambda O: (remove(O / "prepare" / "DONE.json"),
                                write_bytes(O / "prepare" / "STARTED.json", b'{"stage'))),
    ]


def all_cases() -> list[Case]:
    cases = (session_yaml_cases() + session_file_cases() + calibration_cases() + calibration_prepare_cases()
             + keypoint_cases() + mesh_cases() + ground_truth_cases() + frame_cases() + missing_cases()
             + cli_cases() + rerun_cases())
    names = [c.name for c in cases]
    assert len(names) == len(set(names)), "case names must be unique"
    return cases


# ----------------------------------------------------------------------------------------------
# Running a case


def run_inprocess(argv: list[str]) -> Result:
    """`intercap ARGV` in this process (no torch import per case): exit status and captured text.
    Logging is pointed at the captured stderr as the CLI would set it up in a fresh process."""
    from intercap import cli

    out, err = io.StringIO(), io.StringIO()
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    root.handlers = []
    start = time.perf_counter()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = cli.main(argv)
            except SystemExit as exc:
                if isinstance(exc.code, str):
                    print(exc.code, file=sys.stderr)
                rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except Exception:  # noqa: BLE001 - what a user would see as a traceback
                traceback.print_exc()
                rc = 1
    finally:
        root.handlers, root.level = handlers, level
    return Result(int(rc or 0), out.getvalue(), err.getvalue(), time.perf_counter() - start)


def cli_process(argv: list[str]) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "intercap.cli", *argv], cwd=REPO, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def finish(proc: subprocess.Popen, start: float) -> Result:
    try:
        stdout, stderr = proc.communicate(timeout=max(1.0, SUBPROCESS_TIMEOUT_S - (time.perf_counter() - start)))
    except subprocess.TimeoutExpired:
        proc.kill()
        stdout, stderr = proc.communicate()
        stderr += f"\n[fuzz: killed after {SUBPROCESS_TIMEOUT_S} s: the command went on instead of refusing]"
        return Result(0, stdout, stderr, time.perf_counter() - start)
    return Result(proc.returncode, stdout, stderr, time.perf_counter() - start)


def run_subprocess(argv: list[str]) -> Result:
    start = time.perf_counter()
    return finish(cli_process(argv), start)


def run_concurrent(argv: list[str]) -> Result:
    """Two processes on one --out at once. One may refuse (its message is the case's message) while the
    other finishes; both finishing is reported as exit 0 (the folder was not guarded)."""
    start = time.perf_counter()
    first, second = cli_process(argv), cli_process(argv)
    a, b = finish(first, start), finish(second, start)
    if a.rc == 0 and b.rc == 0:
        return Result(0, a.stdout + b.stdout, a.stderr + b.stderr, time.perf_counter() - start)
    refused = a if a.rc != 0 else b
    other = b if refused is a else a
    if other.rc != 0:  # both failed: report both
        return Result(refused.rc, a.stdout + b.stdout, a.stderr + b.stderr, time.perf_counter() - start)
    return Result(refused.rc, refused.stdout, refused.stderr + other.output.replace(TRACEBACK, "[2nd] " + TRACEBACK)
                  if TRACEBACK in other.output else refused.stderr, time.perf_counter() - start)


def run_killed(argv: list[str], O: Path) -> Result:
    """A run killed (SIGKILL) once its first stage has started, then the same command again in this
    process: the second run's result (a dead run's leftovers must not block or corrupt it)."""
    start = time.perf_counter()
    proc = cli_process(argv)
    started = O / stages_run(argv)[0] / "STARTED.json"
    while proc.poll() is None and not started.exists() and time.perf_counter() - start < SUBPROCESS_TIMEOUT_S:
        time.sleep(0.02)
    if proc.poll() is not None:
        first = finish(proc, start)
        return Result(first.rc or 1, first.stdout, "[fuzz: the run ended before it could be killed]\n" + first.stderr)
    proc.kill()
    proc.communicate()
    second = run_inprocess(argv)
    second.seconds = time.perf_counter() - start
    return second


def run_twice(argv: list[str], between: Callable[[Path], None], O: Path) -> Result:
    first = run_inprocess(argv)
    if first.rc != 0:
        return Result(first.rc, first.stdout, "[first run failed]\n" + first.stderr, first.seconds)
    between(O)
    second = run_inprocess(argv)
    second.seconds += first.seconds
    return second


def tree_hash(folder: Path) -> str:
    """sha256 over every file's relative path and bytes ('absent' when the folder is not there)."""
    if not folder.is_dir():
        return "absent"
    h = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        h.update(path.relative_to(folder).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def sample_signature() -> dict[str, tuple[int, int]]:
    """(size, mtime) of every sample file: cheap, and any write through a hard link changes it."""
    return {p.relative_to(SAMPLE).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(SAMPLE.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------------------------------
# Judging a case


def _is_log_record(line: str) -> bool:
    head = line.split(" ", 1)[0]
    return head in ("INFO", "DEBUG") and ": " in line


def message_lines(argv: list[str], result: Result) -> list[str]:
    """What tells the user why a command was refused: the CLI's error (from its first line
    `intercap ...:` or argparse's `usage:`, else every stderr line), without INFO/DEBUG log records
    and their continuation lines; for `validate`, the fatal problems of its report (one a line)."""
    lines, in_record = [], False
    for line in result.stderr.splitlines():
        if _is_log_record(line):
            in_record = True
            continue
        if line.startswith(("intercap", "usage:", "WARNING", "ERROR", TRACEBACK)) or not line.startswith(" "):
            in_record = False
        if not in_record and line.strip():
            lines.append(line)
    starts = [i for i, line in enumerate(lines) if line.startswith(("intercap", "usage:"))]
    if starts:
        lines = lines[starts[0]:]
    if argv and argv[0] == "validate":
        report = result.stdout.splitlines()
        if any(line.startswith("Errors") for line in report):
            first = next(i for i, line in enumerate(report) if line.startswith("Errors")) + 1
            fatal = []
            for line in report[first:]:
                if not line.startswith("  "):
                    break
                fatal.append(line.strip())
            lines += fatal
    return lines


def _nonfinite(value, excused: bool = False) -> list[str]:
    """Paths of NaN/inf numbers in a JSON value outside records marked valid/judged false."""
    if isinstance(value, float) and not math.isfinite(value):
        return [] if excused else [""]
    if isinstance(value, dict):
        excused = excused or value.get("valid") is False or value.get("judged") is False
        return [f".{k}{p}" for k, v in value.items() for p in _nonfinite(v, excused)]
    if isinstance(value, list):
        return [f"[{i}]{p}" for i, v in enumerate(value) for p in _nonfinite(v, excused)]
    return []


def _nan_in_arrays(path: Path) -> str | None:
    """A results array with NaN where the file's `valid` does not say False, or None."""
    try:
        z = np.load(path, allow_pickle=False)
        arrays = {k: z[k] for k in z.files} if path.suffix == ".npz" else {path.stem: z}
    except Exception as exc:  # noqa: BLE001
        return f"{path.name} unreadable ({type(exc).__name__})"
    valid = arrays.get("valid")
    for key, a in arrays.items():
        if a.dtype.kind != "f" or np.isfinite(a).all():
            continue
        rows = ~np.isfinite(a).reshape(len(a), -1).all(axis=1) if a.ndim else np.array([True])
        if valid is None or valid.shape[:1] != rows.shape or valid[rows].any():
            return f"{path.name}: `{key}` has NaN/inf without valid=False"
    return None


def output_problems(case: Case, O: Path) -> list[str]:
    """Why a results folder is not sane: unreadable or NaN-holding files, a calibration flag the
    corruption cannot explain, a prepare run without its DONE.json."""
    problems: list[str] = []
    if not O.is_dir():
        return problems
    for path in sorted(O.rglob("*.json")):
        try:
            bad = _nonfinite(json.loads(path.read_text()))
        except ValueError as exc:
            problems.append(f"{path.relative_to(O)} is not JSON ({exc})")
            continue
        if bad:
            problems.append(f"{path.relative_to(O)}: NaN/inf at {', '.join(bad[:3])} without valid=False")
    for path in sorted([*O.rglob("*.npz"), *O.rglob("*.npy")]):
        if "cache" not in path.relative_to(O).parts:
            why = _nan_in_arrays(path)
            if why:
                problems.append(why)
    check = O / "prepare" / "calibration_check.json"
    if check.is_file() and not case.calibration:
        data = json.loads(check.read_text())
        if data.get("flagged") or data.get("suspect_cameras"):
            problems.append(f"prepare/calibration_check.json flags {data.get('flagged')} (suspect "
                            f"{data.get('suspect_cameras')}) though the corruption does not touch calibration")
    return problems


def calibration_flagged(O: Path) -> bool:
    check = O / "prepare" / "calibration_check.json"
    if not check.is_file():
        return False
    data = json.loads(check.read_text())
    return bool(data.get("flagged") or data.get("suspect_cameras"))


def calibration_unchecked(O: Path) -> list[str]:
    check = O / "prepare" / "calibration_check.json"
    return list(json.loads(check.read_text()).get("unchecked_cameras") or []) if check.is_file() else []


def stages_run(argv: list[str]) -> list[str]:
    """The stages a `run` command line asks for (the last --stages), [] for other commands."""
    if not argv or argv[0] != "run" or "--stages" not in argv:
        return []
    value = argv[len(argv) - 1 - argv[::-1].index("--stages") + 1]
    return [s.strip() for s in value.split(",") if s.strip()]


def classify(case: Case, argv: list[str], result: Result, S: Path, O: Path, scratch: Path,
             gt_changed: bool) -> Outcome:
    """The case's outcome class under the rule (see the module docstring)."""
    def outcome(kind: str, why: str, message: list[str] | None = None) -> Outcome:
        return Outcome(case, kind, why, result, message or [])

    if TRACEBACK in result.output:
        return outcome("traceback", "a Python traceback in the output")
    if gt_changed:
        return outcome("silent", "ground_truth/ of the session was changed")
    extra = case.check(S, O, scratch) if case.check else None
    if result.rc != 0:
        message = message_lines(argv, result)
        text = "\n".join(message)
        tokens = [n.format(S=S, O=O, scratch=scratch) for n in case.names]
        if extra:
            return outcome("silent", f"refused, but {extra}", message)
        if case.expect == "accept":
            return outcome("refused", "refused an input that is fine", message)
        if not message:
            return outcome("unclear", f"exit {result.rc} without a message", message)
        if len(message) > MAX_MESSAGE_LINES:
            return outcome("unclear", f"message of {len(message)} lines (at most {MAX_MESSAGE_LINES})", message)
        if not any(t in text for t in tokens):
            return outcome("unclear", f"message names none of {', '.join(tokens)}", message)
        return outcome("clear", f"exit {result.rc}", message)
    if case.expect == "refuse":
        return outcome("silent", "exit 0 where a refusal is expected")
    problems = output_problems(case, O) + ([extra] if extra else [])
    problems += [f"exit 0 but OUT/{stage}/DONE.json is missing" for stage in stages_run(argv)
                 if not (O / stage / "DONE.json").is_file()]
    if case.expect == "flag" and not calibration_flagged(O):
        unchecked = calibration_unchecked(O)
        problems.append("the calibration check flags nothing for a camera moved out of place"
                        + (f" (only lists {', '.join(unchecked)} as unchecked, with a warning)" if unchecked else ""))
    if problems:
        return outcome("silent", "; ".join(problems))
    return outcome("handled", "exit 0, outputs sane")


def case_argv(case: Case, S: Path, O: Path, scratch: Path) -> list[str]:
    if case.command == "validate":
        return ["validate", str(S)]
    if case.command == "prepare":
        return run_argv()(S, O, scratch)
    return case.command(S, O, scratch)


def run_case(case: Case, scratch: Path) -> Outcome:
    """Copy the sample into `scratch`, corrupt it, run the command, classify what happened."""
    S, O = scratch / "session", scratch / "out"
    copy_sample(S)
    case.mutate(S)
    gt_before = tree_hash(S / "ground_truth")
    argv = case_argv(case, S, O, scratch)
    if case.runner == "subprocess":
        result = run_subprocess(argv)
    elif case.runner == "concurrent":
        result = run_concurrent(argv)
    elif case.runner == "killed":
        result = run_killed(argv, O)
    elif case.between is not None:
        result = run_twice(argv, case.between, O)
    else:
        result = run_inprocess(argv)
    return classify(case, argv, result, S, O, scratch, tree_hash(S / "ground_truth") != gt_before)


def run_cases(cases: list[Case], root: Path | None = None, echo: Callable[[Outcome], None] | None = None
              ) -> list[Outcome]:
    """Every case in its own scratch folder under `root` (a temporary folder by default)."""
    outcomes = []
    with tempfile.TemporaryDirectory(prefix="intercap_fuzz_", dir=root) as tmp:
        for i, case in enumerate(cases):
            scratch = Path(tmp) / f"{i:03d}"
            scratch.mkdir()
            outcomes.append(run_case(case, scratch))
            shutil.rmtree(scratch, ignore_errors=True)
            if echo:
                echo(outcomes[-1])
    return outcomes


# ----------------------------------------------------------------------------------------------
# The command line: every case's outcome and the counts


OUTCOMES = ("clear", "handled", "traceback", "unclear", "silent", "refused")


def describe(o: Outcome) -> str:
    first = next((line for line in o.message if line.strip()), "")
    return f"{o.outcome:9s} {o.case.kind:12s} {o.case.name}  [{o.why}]" + (f"\n{'':22s}> {first[:150]}" if first
                                                                        else "")


def counts_table(outcomes: list[Outcome], seconds: float, title: str) -> str:
    """Markdown: cases per outcome, overall and per kind of corruption."""
    total = Counter(o.outcome for o in outcomes)
    kinds = sorted({o.case.kind for o in outcomes})
    lines = [f"### {title}", "",
             f"{len(outcomes)} cases in {seconds:.0f} s; {sum(o.follows_rule for o in outcomes)} follow the rule",
             "", "| kind | cases | " + " | ".join(OUTCOMES) + " |", "|---|---:|" + "---:|" * len(OUTCOMES)]
    for kind in kinds:
        c = Counter(o.outcome for o in outcomes if o.case.kind == kind)
        lines.append(f"| {kind} | {sum(c.values())} | " + " | ".join(str(c[k]) for k in OUTCOMES) + " |")
    lines.append(f"| **all** | **{len(outcomes)}** | " + " | ".join(f"**{total[k]}**" for k in OUTCOMES) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-k", help="only cases whose name contains this text")
    parser.add_argument("--md", help="append the counts table (markdown) to this file")
    parser.add_argument("--title", default="fuzz outcomes", help="the table's heading")
    parser.add_argument("--full", action="store_true", help="print the whole message of every case off the rule")
    args = parser.parse_args(argv)
    cases = [c for c in all_cases() if not args.k or args.k in c.name]
    before_hash, before_sig = tree_hash(SAMPLE), sample_signature()
    start = time.perf_counter()
    outcomes = run_cases(cases, echo=lambda o: print(describe(o), flush=True))
    seconds = time.perf_counter() - start
    table = counts_table(outcomes, seconds, args.title)
    print("\n" + table)
    broken = [o for o in outcomes if not o.follows_rule]
    if args.full:
        for o in broken:
            print(f"\n--- {o.outcome}: {o.case.name} (exit {o.result.rc}; {o.why})\n{o.result.output.strip()[-3000:]}")
    if tree_hash(SAMPLE) != before_hash or sample_signature() != before_sig:
        print("\nERROR: data_samples/sample was modified by the cases")
        return 2
    if args.md:
        with open(args.md, "a") as f:
            f.write(table + "\n\n")
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
