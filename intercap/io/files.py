"""Small file helpers: every result is written atomically, so a run that dies
halfway never leaves a truncated file that a resumed run would trust."""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np


def atomic_target(path: Path, suffix: str):
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    return Path(tmp)


def write_json(path: str | Path, data) -> None:
    path = Path(path)
    tmp = atomic_target(path, ".json")
    tmp.write_text(json.dumps(data, indent=2, default=_to_builtin) + "\n")
    os.replace(tmp, path)


def read_json(path: str | Path):
    return json.loads(Path(path).read_text())


def save_npz(path: str | Path, **arrays) -> None:
    path = Path(path)
    tmp = atomic_target(path, ".npz")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


def save_npy(path: str | Path, array: np.ndarray) -> None:
    path = Path(path)
    tmp = atomic_target(path, ".npy")
    with open(tmp, "wb") as f:
        np.save(f, array)
    os.replace(tmp, path)


def publish(path: str | Path, public: str | Path) -> None:
    """Show a stage's own result file at `public` (the results folder's top level): a hard link
    where the file system allows, else a copy, replacing what was there atomically. A later
    stage that publishes its own file there leaves this one untouched in the stage folder."""
    path, public = Path(path), Path(public)
    tmp = atomic_target(public, path.suffix)
    tmp.unlink()
    try:
        os.link(path, tmp)
    except OSError:
        shutil.copyfile(path, tmp)
    os.replace(tmp, public)


def per_frame_result(out_dir: str | Path, stage: str, name: str) -> Path:
    """The per-frame stage's own copy of a result, OUT/<stage>/<name>.

    Results folders written before stages kept their own copies have only the
    top-level file; it is adopted into the stage folder first, so a later
    stage that replaces the top-level file cannot take its own output for
    the per-frame one."""
    out_dir = Path(out_dir)
    own = out_dir / stage / name
    if not own.exists() and (out_dir / name).exists():
        publish(out_dir / name, own)
    return own


def write_point_cloud_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Binary little-endian PLY of (N, 3) float points, optional (N, 3) uint8 colours."""
    path = Path(path)
    points = np.asarray(points, dtype=np.float32)
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    records = np.empty(len(points), dtype=fields)
    records["x"], records["y"], records["z"] = points.T
    if colors is not None:
        colors = np.asarray(colors, dtype=np.uint8)
        records["red"], records["green"], records["blue"] = colors.T
    props = "".join(f"property {'float' if t == 'f4' else 'uchar'} {n}\n" for n, t in fields)
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n{props}end_header\n"
    tmp = atomic_target(path, ".ply")
    with open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(records.tobytes())
    os.replace(tmp, path)


def _to_builtin(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")
